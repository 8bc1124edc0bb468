//! Contract conformance on recordings driftwatch did not write: `tests/data/conformance/`
//! holds recordings from an independent Python writer of the contract
//! (`tests/python/contract_writer.py`, written from `docs/` alone) with their truth sidecars.
//! Each is solved through the command line as a user would, and the diagnosed ones are
//! diagnosed. See `tests/data/conformance/SOURCE.md` for the cases and the acceptance rules.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

const Z_MAX: f64 = 4.0;
/// The setter's place from the nuisance estimate, um: 4x the 0.42 um Cramer-Rao bound of the
/// 12-approach plan, rounded up.
const SETTER_TOL_UM: f64 = 2.0;

fn data() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/conformance")
}

fn json(path: &Path) -> Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn run(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_driftwatch"))
        .args(args)
        .output()
        .expect("run driftwatch");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn f(v: &Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or(f64::NAN)
}

/// Solve one case and check it against its truth: problems found, and the z-scores.
fn check_solve(name: &str, case: &Value) -> (Vec<String>, Vec<f64>) {
    let dir = data();
    let rec = dir.join(case["recording"].as_str().unwrap());
    let truth = json(&dir.join(case["truth"].as_str().unwrap()));
    let machine = case["machine"].as_str().unwrap();
    // A machine file lives beside the recordings; a plain name is built in.
    let machine = if machine.ends_with(".toml") {
        dir.join(machine).display().to_string()
    } else {
        machine.to_string()
    };
    let rec = rec.display().to_string();
    let mut args = vec![
        "solve",
        "--machine",
        machine.as_str(),
        "--recording",
        rec.as_str(),
        "--json",
    ];
    let extra: Vec<&str> = case["solve_args"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a.as_str().unwrap())
        .collect();
    args.extend(&extra);
    let (ok, out, err) = run(&args);
    let mut problems = Vec::new();
    if !ok {
        return (vec![format!("{name}: solve failed: {err}")], Vec::new());
    }
    let results: BTreeMap<i64, Value> = out
        .lines()
        .filter(|l| l.starts_with('{'))
        .map(|l| {
            let v: Value = serde_json::from_str(l).unwrap();
            (v["cycle"].as_i64().unwrap(), v)
        })
        .collect();
    let mut zs = Vec::new();
    let truth_cycles = truth["cycles"].as_array().unwrap();
    for tc in truth_cycles {
        let c = tc["cycle"].as_i64().unwrap();
        let Some(r) = results.get(&c) else {
            problems.push(format!("{name}: cycle {c} missing from the output"));
            continue;
        };
        if r["status"] != "ok" {
            problems.push(format!(
                "{name}: cycle {c} {}: {}",
                r["status"], r["reason"]
            ));
            continue;
        }
        let dt = r["t_ns"].as_i64().unwrap() - tc["t_ns"].as_i64().unwrap();
        if dt.abs() > 1000 {
            problems.push(format!("{name}: cycle {c} t_ns off by {dt} ns"));
        }
        for (k, want) in tc["errors"].as_object().unwrap() {
            let (est, sig) = (f(&r["errors"], k), f(&r["sigma"], k));
            let z = (est - want.as_f64().unwrap()) / sig;
            if z.is_nan() || z.abs() >= Z_MAX {
                problems.push(format!(
                    "{name}: cycle {c} {k} = {est:.3} +- {sig:.3}, truth {want}, z {z:.1}"
                ));
            }
            zs.push(z);
        }
        if let (Some(nu), Some(want)) = (
            r.get("nuisance").filter(|n| n.is_object()),
            truth["setter_apparent_um"].as_array(),
        ) {
            for (key, i) in [("setter_height_um", 2), ("setter_lateral_um", 1)] {
                let (got, w) = (f(nu, key), want[i].as_f64().unwrap());
                if nu.get(key).is_some() && (got.is_nan() || (got - w).abs() > SETTER_TOL_UM) {
                    problems.push(format!(
                        "{name}: cycle {c} nuisance {key} {got:.2}, truth {w:.2}"
                    ));
                }
            }
        }
    }
    // A cycle the truth does not list (the one a cut-short file ends inside) must not be
    // served.
    for (c, r) in &results {
        if !truth_cycles.iter().any(|t| t["cycle"].as_i64() == Some(*c)) && r["status"] == "ok" {
            problems.push(format!(
                "{name}: cycle {c} is not complete in the file but solved ok"
            ));
        }
    }
    (problems, zs)
}

fn check_diagnose(name: &str, case: &Value) -> Vec<String> {
    let dir = data();
    let rec = dir.join(case["recording"].as_str().unwrap());
    let truth = json(&dir.join(case["truth"].as_str().unwrap()));
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join("conformance")
        .join(name);
    let _ = std::fs::remove_dir_all(&out);
    let (ok, stdout, err) = run(&[
        "diagnose",
        "--machine",
        "table_bc",
        "--recording",
        rec.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    if !ok {
        return vec![format!("{name}: diagnose failed: {err} {stdout}")];
    }
    let d = json(&out.join("diagnosis.json"));
    let trips: u64 = truth["cycles"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["accepted"].as_u64().unwrap())
        .sum();
    // Clean Gaussian readings: every one is read and none is screened out.
    let read = d["readings"].as_u64().unwrap_or(0);
    let mut problems = Vec::new();
    if read != trips {
        problems.push(format!(
            "{name}: diagnosis used {read} detections of {trips} (outliers {})",
            d["outliers"]
        ));
    }
    if d["unparsed_detections"].as_u64() != Some(0) {
        problems.push(format!(
            "{name}: unparsed_detections {}",
            d["unparsed_detections"]
        ));
    }
    let cycles = truth["cycles"].as_array().unwrap().len() as u64;
    if d["cycles"].as_u64() != Some(cycles) {
        problems.push(format!(
            "{name}: {} cycles diagnosed of {cycles}",
            d["cycles"]
        ));
    }
    problems
}

#[test]
fn recordings_of_an_independent_writer_solve_to_their_truth() {
    let cases = json(&data().join("cases.json"));
    let cases = cases["cases"].as_object().unwrap();
    assert!(cases.len() >= 15, "{} cases", cases.len());
    let mut problems = Vec::new();
    let mut all = Vec::new();
    for (name, case) in cases {
        let (p, zs) = check_solve(name, case);
        let rms = (zs.iter().map(|z| z * z).sum::<f64>() / zs.len() as f64).sqrt();
        println!(
            "{name}: {} estimates, z RMS {rms:.2}, {} problems",
            zs.len(),
            p.len()
        );
        problems.extend(p);
        all.extend(zs);
        if case["diagnose"].as_bool() == Some(true) {
            problems.extend(check_diagnose(name, case));
        }
    }
    let rms = (all.iter().map(|z| z * z).sum::<f64>() / all.len() as f64).sqrt();
    println!("all: {} estimates, z RMS {rms:.2}", all.len());
    assert!(problems.is_empty(), "{problems:#?}");
    // The reported sigmas are honest on another writer's noise, not merely large.
    assert!(all.len() >= 150, "{}", all.len());
    assert!((0.7..1.3).contains(&rms), "z RMS {rms:.2}");
}

/// The other machine families through a second independent writer:
/// `tests/python/family_writer.py`, written from `docs/` and the machine and plan files alone
/// (no Rust source), simulates `head_b_table_c` (a head axis, the NC's pivot model) and
/// `trunnion_ac` with and without a tool-tip displacement of (30, -40, -60) um. Every cycle
/// solves ok through the command line, within 4 sigma of the writer's apparent truth, and the
/// z-scores have an RMS near 1.
#[test]
fn other_families_from_an_independent_writer_solve_to_their_truth() {
    let dir = data().join("families");
    let mut zs = Vec::new();
    let mut problems = Vec::new();
    for m in ["head_b_table_c", "trunnion_ac"] {
        for case in ["plain", "tool_shift"] {
            let rec = dir.join(format!("{m}_{case}.mcap"));
            let truth = json(&dir.join(format!("{m}_{case}.mcap.truth.json")));
            let plan = format!("{m}_patent");
            let rec_s = rec.display().to_string();
            let (ok, out, err) = run(&[
                "solve",
                "--machine",
                m,
                "--recording",
                &rec_s,
                "--plan",
                &plan,
                "--json",
            ]);
            assert!(ok, "{m} {case}: {err}");
            let results: BTreeMap<i64, Value> = out
                .lines()
                .filter(|l| l.starts_with('{'))
                .map(|l| {
                    let v: Value = serde_json::from_str(l).unwrap();
                    (v["cycle"].as_i64().unwrap(), v)
                })
                .collect();
            let cycles = truth["cycles"].as_array().unwrap();
            assert_eq!(results.len(), cycles.len(), "{m} {case}");
            for tc in cycles {
                let c = tc["cycle"].as_i64().unwrap();
                let r = &results[&c];
                if r["status"] != "ok" {
                    problems.push(format!("{m} {case} cycle {c}: {}", r["reason"]));
                    continue;
                }
                for (k, want) in tc["errors"].as_object().unwrap() {
                    let z = (f(&r["errors"], k) - want.as_f64().unwrap()) / f(&r["sigma"], k);
                    if z.is_nan() || z.abs() >= Z_MAX {
                        problems.push(format!("{m} {case} cycle {c} {k}: z {z:.2}"));
                    }
                    zs.push(z);
                }
            }
        }
    }
    let rms = (zs.iter().map(|z| z * z).sum::<f64>() / zs.len() as f64).sqrt();
    println!("{} values, z RMS {rms:.3}", zs.len());
    assert!(problems.is_empty(), "{problems:?}");
    assert!(
        zs.len() == 144 && (0.75..1.3).contains(&rms),
        "{} {rms}",
        zs.len()
    );
}
