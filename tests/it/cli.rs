//! The command line end to end: simulate and solve contract recordings, and refuse bad input
//! with a clear reason while carrying on with the rest.

use std::path::{Path, PathBuf};
use std::process::Command;

use driftwatch_core::recording::{self as rec, CycleResultMsg, ResultStatus};
use driftwatch_recording::mcap_io::{ReadOptions, RecordingWriter, read_file};
use serde_json::Value;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_driftwatch"))
}

fn tmp(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("cli");
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn run(args: &[&str]) -> (bool, String, String) {
    let out = bin().args(args).output().unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn simulated(name: &str) -> PathBuf {
    let path = tmp(name);
    let (ok, out, err) = run(&[
        "simulate",
        "--scenario",
        "patent",
        "--out",
        path.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    path
}

#[test]
fn simulate_writes_every_contract_topic_and_solve_reproduces_its_results() {
    let path = simulated("patent.mcap");
    let bytes = std::fs::read(&path).unwrap();
    let summary = mcap::Summary::read(&bytes)
        .unwrap()
        .expect("a summary section");
    let mut topics = std::collections::BTreeMap::new();
    for ch in summary.channels.values() {
        assert_eq!(ch.message_encoding, "json", "{}", ch.topic);
        let schema = ch.schema.as_ref().expect("every channel has a schema");
        assert_eq!(schema.encoding, "jsonschema");
        let doc: Value = serde_json::from_slice(&schema.data).unwrap();
        assert_eq!(doc["type"], "object");
        let count = summary.stats.as_ref().unwrap().channel_message_counts[&ch.id];
        topics.insert(ch.topic.clone(), count);
    }
    for t in [
        rec::TOPIC_INFO,
        rec::TOPIC_STATE,
        rec::TOPIC_SPINDLE,
        rec::TOPIC_TEMPERATURE,
        rec::TOPIC_DETECTION,
        rec::TOPIC_RESULT,
    ] {
        assert!(topics.contains_key(t), "missing {t}: {topics:?}");
    }
    assert_eq!(topics[rec::TOPIC_DETECTION], 15 * 24);
    assert_eq!(topics[rec::TOPIC_RESULT], 15);
    // The solver, run again on the file, gives the results the file holds.
    let recording = read_file(&path, &ReadOptions::default()).unwrap();
    let (ok, out, err) = run(&[
        "solve",
        "--machine",
        "table_bc",
        "--recording",
        path.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{err}");
    let lines: Vec<CycleResultMsg> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), recording.results.len());
    for (a, b) in lines.iter().zip(&recording.results) {
        assert_eq!(a.cycle, b.msg.cycle);
        assert_eq!(a.status, ResultStatus::Ok);
        assert_eq!(a.t_ns, b.msg.t_ns);
        let (ea, eb) = (a.errors.as_ref().unwrap(), b.msg.errors.as_ref().unwrap());
        for (k, v) in ea {
            assert!((v - eb[k]).abs() < 1e-9, "{k}");
        }
    }
}

/// Rewrite a recording, changing the detections of some cycles with `edit`.
fn rewrite(src: &Path, dst: &Path, edit: impl Fn(i64, &str, &mut Value) -> Vec<String>) {
    let r = read_file(src, &ReadOptions::default()).unwrap();
    let mut w = RecordingWriter::create_file(dst).unwrap();
    if let Some(info) = &r.info {
        w.write(rec::TOPIC_INFO, r.detections[0].t_ns, info)
            .unwrap();
    }
    for d in &r.detections {
        let m = d.msg.as_ref().unwrap();
        let mut v = serde_json::to_value(m).unwrap();
        for text in edit(m.cycle, &m.step, &mut v) {
            w.write_json_bytes(rec::TOPIC_DETECTION, d.t_ns, text.as_bytes())
                .unwrap();
        }
    }
    w.finish().unwrap();
}

#[test]
fn bad_detections_reject_their_cycle_with_the_reason_and_the_rest_is_solved() {
    let good = simulated("good.mcap");
    let bad = tmp("bad.mcap");
    rewrite(&good, &bad, |cycle, step, v| {
        let one = |v: &Value| vec![v.to_string()];
        match (cycle, step) {
            (2, "B0C-90/z#1") => vec![v.to_string().replace(&v["z_mm"].to_string(), "NaN")],
            (3, "B0C0/y#2") => vec![v.to_string().replace(&v["y_mm"].to_string(), "-Infinity")],
            (4, "B-90C-270/x#1") => vec![],
            (5, "B0C-180/z#2") => vec![v.to_string(), v.to_string()],
            (6, "B90C-90/x#2") => {
                v["status"] = "no_trip".into();
                one(v)
            }
            (7, "B0C-270/x#1") => {
                let x = v["x_mm"].as_f64().unwrap() * 1000.0;
                v["x_mm"] = x.into();
                one(v)
            }
            // Labels are free: the second pass under the first pass' label ...
            (8, "B0C0/z#2") => {
                v["step"] = "B0C0/z#1".into();
                one(v)
            }
            // ... a failed approach retried under its label (the retry replaces it) ...
            (9, "B90C-90/x#2") => {
                let mut failed = v.clone();
                failed["status"] = "no_trip".into();
                failed["x_mm"] = (v["x_mm"].as_f64().unwrap() - 1.5).into();
                v["status"] = "ok".into();
                vec![failed.to_string(), v.to_string()]
            }
            // ... one label for every detection, and an explicit "ok".
            (10, _) => {
                v["step"] = "Q".into();
                v["status"] = "ok".into();
                one(v)
            }
            // A reading 20 um off: plausible alone, but the fit's chi-square tells.
            (11, "B0C-90/x#1") => {
                v["x_mm"] = (v["x_mm"].as_f64().unwrap() + 0.02).into();
                one(v)
            }
            _ => one(v),
        }
    });
    let (ok, out, err) = run(&[
        "solve",
        "--machine",
        "table_bc",
        "--recording",
        bad.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{err}");
    let results: Vec<CycleResultMsg> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(results.len(), 15);
    let reason = |c: i64| {
        let r = results.iter().find(|r| r.cycle == c).unwrap();
        assert_eq!(
            r.status,
            ResultStatus::Rejected,
            "cycle {c} should be rejected"
        );
        assert!(r.errors.is_none());
        r.reason.clone().unwrap()
    };
    // A removed detection is named by what it measured (C -270 is C 90), and how many of
    // the plan's passes tripped.
    let expect = [
        (2, vec!["B0C-90/z#1", "z_mm", "NaN"]),
        (3, vec!["B0C0/y#2", "y_mm", "finite"]),
        (4, vec!["missing measurements", "B-90C90/x- F100 (1 of 2)"]),
        (6, vec!["B90C-90/x#2", "no_trip"]),
        (7, vec!["B0C-270/x#1", "1000 times"]),
    ];
    for (c, words) in expect {
        let r = reason(c);
        println!("cycle {c}: {r}");
        for w in words {
            assert!(r.contains(w), "cycle {c}: '{w}' not in: {r}");
        }
    }
    // Solved, but refused as the service would refuse it: chi-square beyond its point, with
    // the point, and the numbers kept for the metrologist.
    let r11 = results.iter().find(|r| r.cycle == 11).unwrap();
    let why = r11.reason.clone().unwrap_or_default();
    println!("cycle 11: {why}");
    assert_eq!(r11.status, ResultStatus::Rejected);
    assert!(
        why.contains("chi-square") && why.contains("99.9 % point"),
        "{why}"
    );
    assert!(r11.errors.is_some() && r11.chi2.unwrap() > r11.chi2_point.unwrap());
    for r in results
        .iter()
        .filter(|r| ![2, 3, 4, 6, 7, 11].contains(&r.cycle))
    {
        assert_eq!(
            r.status,
            ResultStatus::Ok,
            "cycle {}: {:?}",
            r.cycle,
            r.reason
        );
    }
    // What was set aside without rejecting the cycle is said.
    let notes = |c: i64| {
        let r = results.iter().find(|r| r.cycle == c).unwrap();
        r.notes.clone().unwrap_or_default().join("; ")
    };
    assert!(notes(5).contains("received twice"), "{}", notes(5));
    assert!(notes(9).contains("retried"), "{}", notes(9));
    assert!(notes(8).is_empty() && notes(10).is_empty());
    // With the plan, the same verdicts: measurements are matched by content, not label.
    let with_plan = solve_json(&bad, &["--plan", "patent"]);
    for (a, b) in results.iter().zip(&with_plan) {
        assert_eq!((a.cycle, a.status), (b.cycle, b.status), "{:?}", b.reason);
    }
    // The repeated, retried and relabelled cycles solve to what the clean file gives.
    let clean = solve_json(&good, &[]);
    for c in [5, 8, 9, 10] {
        let (a, b) = (
            results.iter().find(|r| r.cycle == c).unwrap(),
            clean.iter().find(|r| r.cycle == c).unwrap(),
        );
        let (ea, eb) = (a.errors.as_ref().unwrap(), b.errors.as_ref().unwrap());
        for (k, v) in ea {
            assert!((v - eb[k]).abs() < 1e-9, "cycle {c} {k}: {v} vs {}", eb[k]);
        }
    }
}

fn solve_json(path: &Path, extra: &[&str]) -> Vec<CycleResultMsg> {
    let mut args = vec![
        "solve",
        "--machine",
        "table_bc",
        "--recording",
        path.to_str().unwrap(),
        "--json",
    ];
    args.extend_from_slice(extra);
    let (ok, out, err) = run(&args);
    assert!(ok, "{err}");
    out.lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

#[test]
fn unknown_machine_and_malformed_or_truncated_recordings_are_named() {
    let good = simulated("trunc-src.mcap");
    let g = good.to_str().unwrap();
    let (ok, _, err) = run(&["solve", "--machine", "no_such_machine", "--recording", g]);
    assert!(
        !ok && err.contains("no_such_machine") && err.contains("table_bc"),
        "{err}"
    );

    let garbage = tmp("garbage.mcap");
    std::fs::write(&garbage, b"this is not a recording at all").unwrap();
    let (ok, _, err) = run(&[
        "solve",
        "--machine",
        "table_bc",
        "--recording",
        garbage.to_str().unwrap(),
    ]);
    assert!(
        !ok && err.contains("garbage.mcap") && err.contains("not an MCAP"),
        "{err}"
    );

    let missing = tmp("does-not-exist.mcap");
    let (ok, _, err) = run(&[
        "solve",
        "--machine",
        "table_bc",
        "--recording",
        missing.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("does-not-exist.mcap"), "{err}");

    let bytes = std::fs::read(&good).unwrap();
    let cut = tmp("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let c = cut.to_str().unwrap();
    let (ok, _, err) = run(&["solve", "--machine", "table_bc", "--recording", c]);
    assert!(!ok && err.contains("--recover"), "{err}");
    let (ok, out, err) = run(&[
        "solve",
        "--machine",
        "table_bc",
        "--recording",
        c,
        "--recover",
    ]);
    assert!(ok, "{err}");
    assert!(err.contains("warning"), "{err}");
    assert!(out.contains(" ok "), "{out}");

    // A recording of another machine's kinematics is refused by name.
    let other = tmp("other.mcap");
    let r = read_file(&good, &ReadOptions::default()).unwrap();
    let mut w = RecordingWriter::create_file(&other).unwrap();
    let mut info = r.info.clone().unwrap();
    info.kinematics = "head_d".into();
    w.write(rec::TOPIC_INFO, 1, &info).unwrap();
    w.finish().unwrap();
    let (ok, _, err) = run(&[
        "solve",
        "--machine",
        "table_bc",
        "--recording",
        other.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("head_d"), "{err}");
}

#[test]
fn experiment_and_plan_commands_report_their_figures() {
    let dir = tmp("experiment");
    let (ok, out, err) = run(&["experiment", "patent", "--out-dir", dir.to_str().unwrap()]);
    assert!(ok, "{err}");
    assert!(out.contains("EZ0B rise"), "{out}");
    for f in [
        "patent_experiment.csv",
        "patent_experiment.svg",
        "patent_experiment.mcap",
        "summary.json",
    ] {
        assert!(dir.join(f).exists(), "{f}");
    }
    // A CSV any reader takes: a header naming each error's value, sigma and truth, and one
    // record of as many fields per cycle.
    let mut csv = csv::Reader::from_path(dir.join("patent_experiment.csv")).unwrap();
    let header = csv.headers().unwrap().clone();
    assert_eq!(&header[0], "cycle");
    assert!(header.iter().any(|h| h == "EZ0B_truth"), "{header:?}");
    let records: Vec<csv::StringRecord> = csv.records().map(|r| r.unwrap()).collect();
    assert_eq!(records.len(), 15);
    assert!(records.iter().all(|r| r.len() == header.len()));
    let svg = std::fs::read_to_string(dir.join("patent_experiment.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("EZ0B"));
    let (ok, out, err) = run(&[
        "plan",
        "--machine",
        "table_bc",
        "--plan",
        "patent_sequential",
        "--sigma-um",
        "1",
    ]);
    assert!(ok, "{err}");
    assert!(
        out.contains("12 approaches") && out.contains("Cramer-Rao"),
        "{out}"
    );
    // The Cramer-Rao bound of the patent design with B = +90 (docs/physics.md 5.1, R and H
    // re-estimated, sigma 1 um): EX0B 0.71, EY0C 0.86, EZ0B 0.61, EX0C 0.62 um, EA0C 7.07 urad.
    for (name, v) in [
        ("EX0B", "0.707"),
        ("EY0C", "0.86"),
        ("EZ0B", "0.612"),
        ("EX0C", "0.6"),
        ("EA0C", "7.07"),
    ] {
        let line = out
            .lines()
            .find(|l| l.trim_start().starts_with(name))
            .unwrap();
        assert!(line.contains(v), "{line}");
    }
}

/// Another family through the command line: its patent experiment in its own names, its
/// recording solved with the first-order relations beside the exact solve.
#[test]
fn experiment_and_solve_run_on_another_machine_family() {
    let dir = tmp("experiment-trunnion");
    let (ok, out, err) = run(&[
        "experiment",
        "patent",
        "--machine",
        "trunnion_ac",
        "--out-dir",
        dir.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(
        out.contains("on trunnion_ac") && out.contains("EZ0A rise"),
        "{out}"
    );
    let svg = std::fs::read_to_string(dir.join("patent_experiment.svg")).unwrap();
    assert!(svg.contains("EY0A") && svg.contains("trunnion_ac"));
    let mcap = dir.join("patent_experiment.mcap");
    let (ok, out, err) = run(&[
        "solve",
        "--machine",
        "trunnion_ac",
        "--recording",
        mcap.to_str().unwrap(),
        "--relations",
    ]);
    assert!(ok, "{err}");
    let first: Vec<&str> = out.lines().filter(|l| l.contains("first order")).collect();
    assert_eq!(first.len(), 15, "{out}");
    // The relations use a subset of the readings, unweighted: within a few sigma of the exact.
    for l in &first {
        let values = l.split_once(':').unwrap().1;
        for d in values.split('(').skip(1) {
            let v: f64 = d.split(')').next().unwrap().parse().unwrap();
            assert!(v.abs() < 8.0, "{l}");
        }
    }
}

#[test]
fn import_fit_and_predict_a_thermal_test_table() {
    // Five hours at 60 s: 10000 min^-1 for 3 h, then stopped; ch1 is a 30-min lag, 12 um.
    let mut csv = String::from("t_s,rpm,ambient,ch1\n");
    let mut x = 0.0;
    for i in 0..=300 {
        let rpm = if i < 180 { 10000.0 } else { 0.0 };
        csv.push_str(&format!("{},{rpm},20.0,{:.4}\n", i * 60, 12.0 * x));
        let u = if rpm > 0.0 { 1.0 } else { 0.0 };
        let a = (-1.0f64 / 30.0).exp();
        x = a * x + (1.0 - a) * u;
    }
    let csv_path = tmp("table.csv");
    std::fs::write(&csv_path, csv).unwrap();
    let rec = tmp("table.mcap");
    let model = tmp("table-model.json");
    let (ok, out, err) = run(&[
        "import",
        "csv",
        "--force",
        "--in",
        csv_path.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--time-column",
        "t_s",
        "--spindle-column",
        "rpm",
        "--temperature-columns",
        "ambient",
        "--displacement-columns",
        "ch1",
        "--start",
        "2026-03-02T06:00:00Z",
    ]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("301 rows"), "{out}");
    // An existing recording is not overwritten without --force.
    let (ok, _, err) = run(&[
        "import",
        "csv",
        "--in",
        csv_path.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--interval-s",
        "60",
        "--temperature-columns",
        "ambient",
    ]);
    assert!(
        !ok && err.contains("exists: give --force to replace it"),
        "{err}"
    );
    let r = read_file(&rec, &ReadOptions::default()).unwrap();
    assert_eq!(r.displacements.len(), 301);
    assert_eq!(r.temperatures.len(), 301);
    assert_eq!(r.info.as_ref().unwrap().machine_id, "table");
    let (ok, out, err) = run(&[
        "fit",
        "--machine",
        "table_bc",
        "--recording",
        rec.to_str().unwrap(),
        "--out",
        model.to_str().unwrap(),
        "--until",
        "3h",
        "--n-ref-rpm",
        "10000",
        "--family",
        "grey_box",
    ]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("ch1"), "{out}");
    assert!(out.contains("<- forced; pole basis"), "{out}");
    let (ok, out, err) = run(&[
        "predict",
        "--model",
        model.to_str().unwrap(),
        "--recording",
        rec.to_str().unwrap(),
        "--step-s",
        "600",
        "--json",
        "--update-until",
        "3h",
    ]);
    assert!(ok, "{err}");
    let lines: Vec<Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 31, "every 10 min over 5 h");
    for l in &lines {
        let c = &l["values"]["ch1"];
        assert!(
            c["value"].is_number() && c["sigma"].as_f64().unwrap() > 0.0,
            "{l}"
        );
        let after = l["t_ns"].as_i64().unwrap()
            > lines[0]["t_ns"].as_i64().unwrap() + 3 * 3_600_000_000_000;
        if after {
            assert_eq!(c["source"], "predicted", "{l}");
        }
    }
    assert_eq!(lines[3]["values"]["ch1"]["source"], "measured");
    // The cooling after 3 h is predicted from the fit on the heating alone.
    assert!(
        err.contains("ch1: 120 readings after the last update"),
        "{err}"
    );
    let rmse: f64 = err
        .split("RMSE ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .unwrap()
        .parse()
        .unwrap();
    // A 30-min lag between the basis poles (15, 40 min), 4-decimal data: within 1 um of a
    // 12-um swing, where holding the last reading is 10 um off.
    assert!(rmse < 1.0, "{err}");
    // Left to choose, the families compete on the fit data: there the spindle never stops
    // and the hall is constant, so least squares has no input and holding the last reading
    // is the baseline; ARX predicts the heating perfectly in the CV, but three hours hold one
    // fold with a window of its own, too few to tell beyond chance. When the spindle stops
    // (right at the cut) an input no family learnt moves: what is served is said to be
    // untested there (the grey box knows what a stop does here, but handing over to it lost
    // on real warm-up runs).
    let auto = tmp("table-auto.json");
    let plot = tmp("table-auto.svg");
    let _ = std::fs::remove_file(&plot);
    let (ok, out, err) = run(&[
        "fit",
        "--recording",
        rec.to_str().unwrap(),
        "--out",
        auto.to_str().unwrap(),
        "--until",
        "3h",
        "--n-ref-rpm",
        "10000",
    ]);
    assert!(ok, "{out}{err}");
    for family in [
        "persistence",
        "regression",
        "key_regression",
        "arx",
        "grey_box",
    ] {
        assert!(out.contains(&format!("ch1          {family}")), "{out}");
    }
    assert!(out.contains("<- chosen; last value held"), "{out}");
    assert!(
        out.contains("persistence served; arx had the lowest CV error")
            && out.contains("not beyond chance"),
        "{out}"
    );
    let (ok, out, err) = run(&[
        "predict",
        "--model",
        auto.to_str().unwrap(),
        "--recording",
        rec.to_str().unwrap(),
        "--step-s",
        "600",
        "--json",
        "--update-until",
        "3h",
        "--plot",
        plot.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(
        err.contains(
            "ch1: served persistence (untested: an input constant over the fit data moved)"
        ),
        "{err}"
    );
    assert!(
        std::fs::read_to_string(&plot)
            .unwrap()
            .contains("updates stop")
    );
    let lines: Vec<Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 12, "every 10 min over the last 2 h: {out}");
    assert!(
        lines.iter().all(|l| l["values"]["ch1"]["family"]
            .as_str()
            .is_some_and(|f| f.contains("untested"))
            && l["values"]["ch1"]["measured"].is_number()),
        "{out}"
    );
    // What is served is the last reading held, scored as persistence is.
    let figure = |after: &str| -> f64 {
        err.split(after)
            .nth(1)
            .and_then(|s| s.split([' ', ')']).next())
            .unwrap()
            .parse()
            .unwrap()
    };
    assert_eq!(
        figure("updated readings on the 1-min grid: RMSE "),
        figure("(persistence "),
        "{err}"
    );
    // Without a spindle log the models use the temperatures alone, and fit says so.
    let bare = tmp("table-bare.mcap");
    let (ok, out, err) = run(&[
        "import",
        "csv",
        "--force",
        "--in",
        csv_path.to_str().unwrap(),
        "--out",
        bare.to_str().unwrap(),
        "--time-column",
        "t_s",
        "--temperature-columns",
        "ambient",
        "--displacement-columns",
        "ch1",
    ]);
    assert!(ok, "{out}{err}");
    let (ok, out, err) = run(&[
        "fit",
        "--recording",
        bare.to_str().unwrap(),
        "--out",
        auto.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    assert!(
        err.contains("warning: the recordings have no spindle speed"),
        "{err}"
    );
    assert!(out.contains("inputs: temperatures ambient"), "{out}");
    // Bad input is named.
    let (ok, _, err) = run(&[
        "fit",
        "--recording",
        rec.to_str().unwrap(),
        "--out",
        auto.to_str().unwrap(),
        "--family",
        "neural",
    ]);
    assert!(
        !ok && err.contains("--family neural: use auto, persistence"),
        "{err}"
    );
    let (ok, _, err) = run(&[
        "import",
        "csv",
        "--force",
        "--in",
        csv_path.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--time-column",
        "t_s",
        "--spindle-column",
        "speed",
    ]);
    assert!(!ok && err.contains("'speed'"), "{err}");
    let (ok, _, err) = run(&[
        "predict",
        "--model",
        csv_path.to_str().unwrap(),
        "--recording",
        rec.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("not a driftwatch model"), "{err}");
}

#[test]
fn the_thermal_model_fits_the_six_errors_of_a_simulated_recording() {
    let rec = simulated("patent-fit.mcap");
    let model = tmp("patent-model.json");
    let (ok, out, err) = run(&[
        "fit",
        "--machine",
        "table_bc",
        "--recording",
        rec.to_str().unwrap(),
        "--out",
        model.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("model of 6 channel(s)"), "{out}");
    for e in ["EX0B", "EZ0B", "EY0C", "EX0C", "EA0C", "EB0C"] {
        assert!(out.contains(e), "{out}");
    }
    // The service starts a machine's predictions from such a file, and refuses one it
    // cannot read, naming the machine and the file.
    let default =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/default.toml"))
            .unwrap();
    let serve = |model: &Path| {
        let cfg = tmp(&format!(
            "serve-{}.toml",
            model.file_stem().unwrap().to_str().unwrap()
        ));
        let text = default.replacen(
            "# thermal_model = \"models/sim-1.json\"",
            &format!("thermal_model = {:?}", model.to_str().unwrap()),
            1,
        );
        assert_ne!(text, default);
        std::fs::write(&cfg, text).unwrap();
        let data = tmp(&format!(
            "serve-data-{}",
            model.file_stem().unwrap().to_str().unwrap()
        ));
        // A store left by an earlier run would be restored: each run starts empty.
        let _ = std::fs::remove_dir_all(&data);
        run(&[
            "serve",
            "--config",
            cfg.to_str().unwrap(),
            "--until",
            "10",
            "--time-scale",
            "100000",
            "--listen",
            "127.0.0.1:0",
            "--data-dir",
            data.to_str().unwrap(),
        ])
    };
    let (ok, out, err) = serve(&model);
    assert!(ok, "{out}{err}");
    assert!(
        format!("{out}{err}").contains("started from a model fitted on"),
        "{out}{err}"
    );
    let (ok, out, err) = serve(&tmp("no-such-model.json"));
    assert!(!ok);
    assert!(
        err.contains("machine 'sim-1': thermal_model") && err.contains("no-such-model.json"),
        "{out}{err}"
    );
}

/// `driftwatch diagnose` of a `table_bc` recording into `tmp(dir)` with `extra` arguments:
/// its standard output and `diagnosis.json`.
fn diagnose_table_bc(rec: &Path, dir: &str, extra: &[&str]) -> (String, Value) {
    let dir = tmp(dir);
    let mut args = vec![
        "diagnose",
        "--machine",
        "table_bc",
        "--recording",
        rec.to_str().unwrap(),
        "--out",
        dir.to_str().unwrap(),
    ];
    args.extend(extra);
    let (ok, out, err) = run(&args);
    assert!(ok, "{out}{err}");
    let j = serde_json::from_str(&std::fs::read_to_string(dir.join("diagnosis.json")).unwrap())
        .unwrap();
    (out, j)
}

/// One simulated day of the patent plan on `table_bc` (a cycle every 20 min, 0.5 um noise, the
/// spindle at 20000 min^-1 for the first five hours) with `extra` TOML appended (its own
/// sections); returns the scenario file and the recording `driftwatch simulate` wrote.
fn one_day(name: &str, seed: u64, extra: &str) -> (PathBuf, PathBuf) {
    let scn = tmp(&format!("{name}.toml"));
    std::fs::write(
        &scn,
        format!(
            r#"
name = "{name}"
machine = "table_bc"
plan = "patent"
seed = {seed}
start_utc = "2026-03-02T06:00:00Z"
duration_min = 600.0
spindle = [{{ at_min = 0.0, rpm = 20000.0, state = "idle" }}, {{ at_min = 300.0, rpm = 0.0, state = "idle" }}]
[noise]
sigma_um = 0.5
{extra}
"#
        ),
    )
    .unwrap();
    let rec = tmp(&format!("{name}.mcap"));
    let (ok, out, err) = run(&[
        "simulate",
        "--scenario",
        scn.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    (scn, rec)
}

#[test]
fn diagnose_names_a_skip_latency_that_cancels_in_the_sums_and_writes_its_report() {
    // One day: the skip lags 2.4 ms beyond the calibration and the probing feed is raised
    // from 100 to 200 mm/min halfway. The patent's sums cancel it; the diagnosis names it.
    let (_, rec) = one_day(
        "latency",
        5,
        "[cycles]\nevery_min = 20.0\nfeed_changes = [{ at_min = 300.0, feed_mm_min = 200.0 }]\n[skip]\nlatency_ms = 2.4",
    );
    let (out, j) = diagnose_table_bc(&rec, "diagnosis", &[]);
    let dir = tmp("diagnosis");
    assert!(out.contains("skip latency"), "{out}");
    assert_eq!(j["format"], "driftwatch-diagnosis/1");
    assert!(
        j["baseline"]["chi2_dof"].as_f64().unwrap() > 1.2,
        "{}",
        j["baseline"]
    );
    let acc = j["accepted"].as_array().unwrap();
    let lat = acc
        .iter()
        .find(|a| a["effect"] == "skip_latency")
        .unwrap_or_else(|| panic!("{acc:?}"));
    let ms = lat["parameters"][0]["value"].as_f64().unwrap();
    assert!((ms / 2.4 - 1.0).abs() < 0.2, "{ms}");
    // A measurement-model effect: corrected at its source, never put into the thermal model.
    assert_eq!(lat["model_input"]["kind"], "none");
    assert!(out.contains("not carried into the thermal model"), "{out}");
    assert!(
        j["final"]["chi2_dof"].as_f64().unwrap() < 1.2,
        "{}",
        j["final"]
    );
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("<svg") && html.contains("skip latency"));

    // The library, listed.
    let (ok, out, err) = run(&["diagnose", "--list-effects", "--json"]);
    assert!(ok, "{err}");
    let list: Value = serde_json::from_str(&out).unwrap();
    let ids: Vec<&str> = list
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["id"].as_str().unwrap())
        .collect();
    let mut unique = ids.clone();
    unique.sort();
    unique.dedup();
    assert_eq!(unique.len(), ids.len());
    assert!(
        ids.len() >= 14 && ids.contains(&"rotary_backlash"),
        "{ids:?}"
    );
    // Without a recording it says what is missing; a recording of cycles needs the machine.
    let (ok, _, err) = run(&["diagnose"]);
    assert!(!ok && err.contains("--recording"), "{err}");
    let (ok, _, err) = run(&[
        "diagnose",
        "--recording",
        rec.to_str().unwrap(),
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("--machine is required"), "{err}");
}

#[test]
fn diagnose_a_displacement_recording_names_the_chiller_driver_and_writes_a_model() {
    let rec = tmp("fl.mcap");
    let csv = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/fl-thermal/fl_thermal.csv"
    );
    let temps: Vec<String> = (1..=16).map(|i| format!("t{i}_C")).collect();
    let (ok, out, err) = run(&[
        "import",
        "csv",
        "--force",
        "--in",
        csv,
        "--out",
        rec.to_str().unwrap(),
        "--time-column",
        "time_s",
        "--spindle-column",
        "spindle_rpm",
        "--temperature-columns",
        &temps.join(","),
        "--displacement-columns",
        "ch1_um,ch5_um",
    ]);
    assert!(ok, "{out}{err}");
    let dir = tmp("fl-diagnosis");
    let (ok, out, err) = run(&[
        "diagnose",
        "--recording",
        rec.to_str().unwrap(),
        "--channels",
        "ch1_um",
        "--holdout-from-h",
        "40",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("t4_C swings with it"), "{out}");
    let j: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("diagnosis.json")).unwrap())
            .unwrap();
    assert_eq!(j["format"], "driftwatch-displacement-diagnosis/1");
    assert_eq!(j["channels"].as_array().unwrap().len(), 1);
    assert_eq!(j["channels"][0]["periodic"]["driver"], "t4_C");
    // The new model version is a thermal model the service can load.
    let m = driftwatch_thermal::model::ThermalModel::from_json(
        &std::fs::read_to_string(dir.join("model.json")).unwrap(),
    )
    .unwrap();
    assert!(m.config.temperatures.iter().any(|t| t.sensor == "t4_C"));
    assert!(
        std::fs::read_to_string(dir.join("report.html"))
            .unwrap()
            .contains("<svg")
    );
    // A channel the recording does not have is refused by name.
    let (ok, _, err) = run(&[
        "diagnose",
        "--recording",
        rec.to_str().unwrap(),
        "--channels",
        "ch9_um",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(!ok);
    assert!(err.contains("ch9_um"), "{err}");
}

/// `--time-scale` may not bypass the configuration's refusal to run a real
/// NC (`nc_push`) on anything but the wall clock; the service stops before it listens.
#[test]
fn the_command_line_cannot_bypass_a_configuration_check() {
    let cfg = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/nc_push.example.toml");
    let data = tmp("bypass-data");
    let (ok, out, err) = run(&[
        "serve",
        "--config",
        cfg.to_str().unwrap(),
        "--time-scale",
        "60",
        "--listen",
        "127.0.0.1:1",
        "--data-dir",
        data.to_str().unwrap(),
    ]);
    assert!(!ok, "{out}{err}");
    assert!(
        err.contains("a real NC (nc_push) runs on the wall clock"),
        "{err}"
    );
    assert!(!data.join("driftwatch.db").exists());
}

/// `nc program` writes the golden FANUC program of the default plan, and `--check` replays a
/// family's program on the simulator next to its plan and prints both solves.
#[test]
fn nc_program_writes_the_golden_file_and_checks_against_the_plan() {
    let (ok, out, err) = run(&[
        "nc",
        "program",
        "--machine",
        "table_bc",
        "--dialect",
        "fanuc",
    ]);
    assert!(ok, "{err}");
    let golden = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("crates/nc/tests/golden/patent_table_bc.nc"),
    )
    .unwrap();
    assert_eq!(out, golden);

    let path = tmp("trunnion.ngc");
    let (ok, out, err) = run(&[
        "nc",
        "program",
        "--machine",
        "trunnion_ac",
        "--dialect",
        "iso",
        "--out",
        path.to_str().unwrap(),
        "--check",
    ]);
    assert!(ok, "{err}");
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.contains("G38.2") && text.contains("G0 A"), "{text}");
    let worst = out
        .lines()
        .find_map(|l| l.strip_prefix("largest difference: "))
        .unwrap_or_else(|| panic!("{out}"));
    let um: f64 = worst.split(' ').next().unwrap().parse().unwrap();
    assert!(um <= 0.01, "{out}");

    // An increment the controls do not have is refused, naming the option.
    let (ok, _, err) = run(&[
        "nc",
        "program",
        "--machine",
        "table_bc",
        "--dialect",
        "siemens",
        "--decimals",
        "9",
    ]);
    assert!(!ok && err.contains("decimals"), "{err}");
}

/// `rtest simulate`, `process` and `identify`: the errors put into the virtual machine come
/// back within their uncertainties, the report has its plots, and the reference measurement
/// is the verification endpoint's body.
#[test]
fn rtest_simulates_processes_and_identifies_a_machine() {
    let rec_path = tmp("rtest.mcap");
    let p = rec_path.to_str().unwrap();
    let (ok, out, err) = run(&[
        "rtest",
        "simulate",
        "--machine",
        "table_bc",
        "--error",
        "EX0C=10",
        "--error",
        "EZ0B=-5",
        "--out",
        p,
    ]);
    assert!(ok, "{out}{err}");
    let report = tmp("rtest.html");
    let (ok, out, err) = run(&[
        "rtest",
        "process",
        "--from",
        p,
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    let xyc_radial = out
        .lines()
        .find(|l| l.starts_with("XYC") && l.contains("radial"))
        .unwrap_or_else(|| panic!("{out}"));
    let harmonic: f64 = xyc_radial
        .split_whitespace()
        .nth(6)
        .unwrap()
        .parse()
        .unwrap();
    assert!((harmonic - 10.0).abs() < 0.2, "{xyc_radial}");
    let html = std::fs::read_to_string(&report).unwrap();
    assert_eq!(html.matches("<svg").count(), 6, "two plots per test");

    let reference = tmp("rtest-reference.json");
    let (ok, out, err) = run(&[
        "rtest",
        "identify",
        "--from",
        p,
        "--reference",
        reference.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    let body: Value = serde_json::from_str(&std::fs::read_to_string(&reference).unwrap()).unwrap();
    assert_eq!(body["instrument"], "rtest");
    // It is the verification endpoint's body, valid for this machine.
    let k = driftwatch_core::kinematics::Kinematics::builtin("table_bc").unwrap();
    let names: Vec<_> = k
        .identify
        .iter()
        .map(|id| k.rotary[id.axis].error_names[id.slot])
        .collect();
    let reference: driftwatch_machine::verification::ReferenceResult =
        serde_json::from_value(body.clone()).unwrap();
    reference.validate(&names, reference.t_ns).unwrap();
    for (name, truth) in [("EX0C", 10.0), ("EZ0B", -5.0), ("EA0C", 0.0)] {
        let (v, s) = (
            body["errors"][name].as_f64().unwrap(),
            body["sigma"][name].as_f64().unwrap(),
        );
        assert!((v - truth).abs() < 4.0 * s, "{name}: {v} +- {s}");
    }
    // Asked for every error, it names what these tests cannot separate instead of guessing.
    let all_ref = tmp("rtest-reference-all.json");
    let (ok, out, err) = run(&[
        "rtest",
        "identify",
        "--from",
        p,
        "--errors",
        "all",
        "--reference",
        all_ref.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("not identifiable: EC0C"), "{out}");
    // The reference keeps only what the tool setter has to compare with.
    let body: Value = serde_json::from_str(&std::fs::read_to_string(&all_ref).unwrap()).unwrap();
    let keys: Vec<&String> = body["errors"].as_object().unwrap().keys().collect();
    assert_eq!(keys, ["EA0C", "EB0C", "EX0B", "EX0C", "EY0C", "EZ0B"]);
}

/// A device's CSV export (angle and the three sensors) imported and processed; a bad cell is
/// refused by line.
#[test]
fn rtest_csv_exports_are_imported_and_bad_cells_refused_by_line() {
    let rec_path = tmp("rtest-for-csv.mcap");
    let p = rec_path.to_str().unwrap();
    let (ok, out, err) = run(&[
        "rtest",
        "simulate",
        "--machine",
        "table_bc",
        "--tests",
        "xyc",
        "--error",
        "EX0C=10",
        "--ideal",
        "--uncalibrated",
        "--out",
        p,
    ]);
    assert!(ok, "{out}{err}");
    let recording = read_file(
        &rec_path,
        &ReadOptions {
            keep_raw: true,
            ..Default::default()
        },
    )
    .unwrap();
    let mut csv = String::from("angle_deg,u_um,v_um,w_um\n");
    for m in recording.raw.iter().filter(|m| m.topic == "/rtest/reading") {
        let r: Value = serde_json::from_slice(&m.data).unwrap();
        csv += &format!("{},{},{},{}\n", r["c_deg"], r["u_um"], r["v_um"], r["w_um"]);
    }
    let csv_path = tmp("rtest.csv");
    std::fs::write(&csv_path, &csv).unwrap();
    let imported = tmp("rtest-imported.mcap");
    let args = |csv: &Path| {
        vec![
            "import".to_string(),
            "rtest-csv".into(),
            "--csv".into(),
            csv.display().to_string(),
            "--machine".into(),
            "table_bc".into(),
            "--test".into(),
            "xyc".into(),
            "--setting".into(),
            "e".into(),
            "--out".into(),
            imported.display().to_string(),
        ]
    };
    let a = args(&csv_path);
    let (ok, out, err) = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(ok, "{out}{err}");
    let (ok, out, err) = run(&["rtest", "process", "--from", imported.to_str().unwrap()]);
    assert!(ok, "{out}{err}");
    let radial = out.lines().find(|l| l.contains("radial")).unwrap();
    let harmonic: f64 = radial.split_whitespace().nth(6).unwrap().parse().unwrap();
    assert!((harmonic - 10.0).abs() < 0.2, "{radial}");

    let bad = tmp("rtest-bad.csv");
    std::fs::write(&bad, csv.replacen("\n0.0,", "\nzero,", 1)).unwrap();
    let a = args(&bad);
    let (ok, _, err) = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!ok);
    assert!(
        err.contains("line 2") && err.contains("'zero' is not a number"),
        "{err}"
    );
}

/// `diagonal simulate` and `solve` (seed 004): mirror tilts push the conventional squareness
/// far off, the set-up-robust one stays on the truth; `correction-table` (seed 003) loops to
/// GOOD and builds a table from a measured section, refusing a bad cell by line.
/// A round trip from the command line: a static X-Z squareness of 40 urad in the
/// virtual machine; `diagnose` blames `squareness`; `diagonal simulate --scenario` measures the
/// same machine's axes and `diagonal solve --geometry-out` writes the geometry; `diagnose
/// --geometry` with it no longer finds the squareness.
#[test]
fn a_squareness_is_blamed_measured_and_gone_once_its_geometry_is_loaded() {
    let (scn, rec) = one_day(
        "square",
        19,
        "[cycles]\nevery_min = 20.0\n[truth.channels.sxz]\noffset = 40.0",
    );
    let diagnose = |dir: &str, extra: &[&str]| -> Vec<Value> {
        let (_, j) = diagnose_table_bc(&rec, dir, extra);
        j["accepted"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|a| a["effect"] == "squareness" && a["term"].as_str().unwrap().contains("sxz"))
            .cloned()
            .collect()
    };
    let before = diagnose("square-before", &[]);
    assert!(!before.is_empty(), "the squareness is not blamed");
    let blamed = &before[0]["parameters"][0];
    let log = tmp("square-diagonal.csv");
    let (ok, out, err) = run(&[
        "diagonal",
        "simulate",
        "--scenario",
        scn.to_str().unwrap(),
        "--out",
        log.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    let g = tmp("square-geometry.json");
    let (ok, out, err) = run(&[
        "diagonal",
        "solve",
        "--from",
        log.to_str().unwrap(),
        "--geometry-out",
        g.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    let geometry: Value = serde_json::from_str(&std::fs::read_to_string(&g).unwrap()).unwrap();
    let measured = geometry["squareness_urad"]["xz"].as_f64().unwrap();
    let (value, sigma) = (
        blamed["value"].as_f64().unwrap(),
        blamed["sigma"].as_f64().unwrap(),
    );
    let (ok, out, err) = run(&[
        "diagonal",
        "solve",
        "--from",
        log.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{out}{err}");
    let solved: Value = serde_json::from_str(&out).unwrap();
    let diag_sigma = solved["robust"]["squareness_sigma_urad"][1]
        .as_f64()
        .unwrap();
    println!(
        "diagnosis: sxz {value:.2} +- {sigma:.2} urad; step diagonal {measured:.2} +- {diag_sigma:.2} urad; truth 40"
    );
    assert!((measured - 40.0).abs() < 3.0 * diag_sigma, "{measured}");
    assert!(
        (measured - value).abs() < 3.0 * sigma.hypot(diag_sigma),
        "{measured} vs {value} +- {sigma}"
    );
    let after = diagnose("square-after", &["--geometry", g.to_str().unwrap()]);
    assert!(after.is_empty(), "still blamed: {after:?}");
}

/// The numbers among a line's words.
fn numbers(line: &str) -> Vec<f64> {
    line.split_whitespace()
        .filter_map(|w| w.parse().ok())
        .collect()
}

/// The lines of `out` that start with `prefix`.
fn lines_starting<'a>(out: &'a str, prefix: &str) -> Vec<&'a str> {
    out.lines().filter(|l| l.starts_with(prefix)).collect()
}

/// The simulated squareness X-Y, X-Z, Y-Z (um) from `diagonal simulate`'s `truth:` line.
fn simulated_squareness(out: &str) -> Vec<f64> {
    let line = lines_starting(out, "truth:");
    assert_eq!(line.len(), 1, "{out}");
    line[0]
        .split([',', ';'])
        .take(3)
        .map(|part| {
            part.split_whitespace()
                .find_map(|w| w.parse().ok())
                .unwrap()
        })
        .collect()
}

#[test]
fn the_step_diagonal_and_the_correction_table_from_the_command_line() {
    let log = tmp("diagonal.csv");
    let (ok, out, err) = run(&["diagonal", "simulate", "--out", log.to_str().unwrap()]);
    assert!(ok, "{out}{err}");
    let truth = simulated_squareness(&out);
    let (ok, out, err) = run(&["diagonal", "solve", "--from", log.to_str().unwrap()]);
    assert!(ok, "{out}{err}");
    let squareness = lines_starting(&out, "squareness");
    assert_eq!(squareness.len(), 3, "{out}");
    for (line, t) in squareness.iter().zip(&truth) {
        let nums = numbers(line);
        let (conventional, robust, sigma) = (nums[0], nums[1], nums[2]);
        assert!(
            (robust - t).abs() < 4.0 * sigma + 0.05,
            "{line} against {t}"
        );
        assert!((conventional - t).abs() > 1.0, "{line} against {t}");
    }
    assert!(out.contains("runs: one-way"), "{out}");

    // Out and back with a drift: the log's return leg is detected and each diagonal's drift
    // along its beam estimated, the squareness still within its uncertainty.
    let log2 = tmp("diagonal-oab.csv");
    let (ok, out, err) = run(&[
        "diagonal",
        "simulate",
        "--drift-um-per-min",
        "0.3,-0.2,1.0",
        "--out-and-back",
        "--out",
        log2.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    let beams: Vec<f64> = out
        .lines()
        .find(|l| l.starts_with("drift "))
        .and_then(|l| l.split_once("along the beams: "))
        .unwrap()
        .1
        .split(')')
        .next()
        .unwrap()
        .split([',', ' '])
        .filter_map(|w| w.parse().ok())
        .collect();
    assert_eq!(beams.len(), 4, "{out}");
    let truth = simulated_squareness(&out);
    let (ok, out, err) = run(&["diagonal", "solve", "--from", log2.to_str().unwrap()]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("runs: out-and-back"), "{out}");
    let drift_lines = lines_starting(&out, "drift along");
    assert_eq!(drift_lines.len(), 4, "{out}");
    for (line, t) in drift_lines.iter().zip(&beams) {
        let nums = numbers(line);
        let (robust, sigma) = (nums[1], nums[2]);
        assert!(
            (robust - t).abs() < 4.0 * sigma + 0.001,
            "{line} against {t}"
        );
    }
    let squareness = lines_starting(&out, "squareness");
    assert_eq!(squareness.len(), 3, "{out}");
    for (line, t) in squareness.iter().zip(&truth) {
        let nums = numbers(line);
        assert!(
            (nums[1] - t).abs() < 4.0 * nums[2] + 0.05,
            "{line} against {t}"
        );
    }
    let (ok, _, err) = run(&[
        "diagonal",
        "simulate",
        "--drift-um-per-min",
        "1,2",
        "--out",
        log2.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("three numbers"), "{err}");

    let (ok, out, err) = run(&["correction-table", "--simulate"]);
    assert!(ok, "{out}{err}");
    assert!(
        out.contains("n_max = D / (2 resolution) = 100 / (2 x 0.1 um) = 500000"),
        "{out}"
    );
    assert_eq!(
        out.lines().filter(|l| l.trim() == "GOOD").count(),
        1,
        "{out}"
    );
    let profile = tmp("profile.csv");
    std::fs::write(&profile, "x_mm,dz_um\n50,1.0\n25,2.5\n0,0.5\n").unwrap();
    let table = tmp("table.csv");
    let (ok, out, err) = run(&[
        "correction-table",
        "--profile",
        profile.to_str().unwrap(),
        "--out",
        table.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    assert_eq!(
        std::fs::read_to_string(&table).unwrap(),
        "x_mm,dz_um\n50.0000,-0.0000\n25.0000,-1.5000\n0.0000,0.5000\n"
    );
    // The corrected facing pass as a program: its feed moves read back to the table's points,
    // Z = z0 - d1 (the table CSV's dz added), within the 0.1 um resolution.
    let table_rows: Vec<(f64, f64)> = std::fs::read_to_string(&table)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let (x, dz) = l.split_once(',').unwrap();
            (x.parse().unwrap(), dz.parse().unwrap())
        })
        .collect();
    for (dialect, diameter) in [
        ("fanuc", true),
        ("siemens", true),
        ("heidenhain", true),
        ("iso", false),
    ] {
        let program = tmp(&format!("facing-{dialect}.txt"));
        let (ok, out, err) = run(&[
            "correction-table",
            "--profile",
            profile.to_str().unwrap(),
            "--z0-mm",
            "-2",
            "--program",
            dialect,
            "--program-out",
            program.to_str().unwrap(),
        ]);
        assert!(ok, "{out}{err}");
        let text = std::fs::read_to_string(&program).unwrap();
        assert!(
            text.contains("LATHE FACING PASS") && text.contains("PROFILE.CSV"),
            "{text}"
        );
        assert!(text.contains("RESOLUTION 0.1 UM"), "{text}");
        let points = facing_points(&text, diameter);
        assert_eq!(points.len(), table_rows.len(), "{dialect}: {text}");
        for ((x, dz), (r, z)) in table_rows.iter().zip(&points) {
            assert!((x - r).abs() < 1e-4, "{dialect}: x {r} for {x}");
            let back = (z + 2.0) * 1e3;
            assert!(
                (back - dz).abs() < 0.1,
                "{dialect}: dz {back} for {dz} at {x}"
            );
        }
    }

    std::fs::write(&profile, "x_mm,dz_um\n50,1.0\n25,two\n").unwrap();
    let (ok, _, err) = run(&["correction-table", "--profile", profile.to_str().unwrap()]);
    assert!(
        !ok && err.contains("line 3") && err.contains("'two'"),
        "{err}"
    );
}

/// The (radius, Z) points of a facing program's feed moves: `G01`/`G1` (modal) or a
/// HEIDENHAIN `L` block without `FMAX`; X halved when it is the diameter. Comments skipped.
fn facing_points(text: &str, diameter: bool) -> Vec<(f64, f64)> {
    let (mut x, mut z, mut feed) = (f64::NAN, f64::NAN, false);
    let mut out = Vec::new();
    for line in text.lines() {
        let code = line.split([';', '(']).next().unwrap_or("");
        let words: Vec<&str> = code.split_whitespace().collect();
        let mut moved = false;
        for w in &words {
            match *w {
                "G00" | "G0" | "FMAX" => feed = false,
                "G01" | "G1" => feed = true,
                "L" => feed = !words.contains(&"FMAX"),
                _ => {
                    if let Some(v) = w.strip_prefix('X').and_then(|v| v.parse::<f64>().ok()) {
                        x = v;
                        moved = true;
                    }
                    if let Some(v) = w.strip_prefix('Z').and_then(|v| v.parse::<f64>().ok()) {
                        z = v;
                        moved = true;
                    }
                }
            }
        }
        if moved && feed {
            out.push((if diameter { x / 2.0 } else { x }, z));
        }
    }
    out
}

/// The number written just before `word` on the line of `out` starting with `prefix`
/// ("12.5 s," before "s,"); the line must exist once.
fn figure_before(out: &str, prefix: &str, word: &str) -> f64 {
    let lines = lines_starting(out, prefix);
    assert_eq!(lines.len(), 1, "one '{prefix}' line in:\n{out}");
    let words: Vec<&str> = lines[0].split_whitespace().collect();
    let i = words
        .iter()
        .position(|w| w.trim_end_matches([',', ';']) == word)
        .unwrap_or_else(|| panic!("no '{word}' in '{}'", lines[0]));
    assert!(i > 0, "nothing before '{word}' in '{}'", lines[0]);
    words[i - 1]
        .trim_end_matches(['x', ','])
        .parse()
        .unwrap_or_else(|_| panic!("no number before '{word}' in '{}'", lines[0]))
}

/// The number written just after `word` on that line ("p99 1234 us").
fn figure_after(out: &str, prefix: &str, word: &str) -> f64 {
    let line = lines_starting(out, prefix)[0];
    let words: Vec<&str> = line.split_whitespace().collect();
    let i = words
        .iter()
        .position(|w| *w == word)
        .unwrap_or_else(|| panic!("no '{word}' in '{line}'"));
    words[i + 1]
        .trim_end_matches([',', ';'])
        .parse()
        .unwrap_or_else(|_| panic!("no number after '{word}' in '{line}'"))
}

#[test]
fn bench_fleet_of_nc_push_machines_reports_memory_per_loop_anonymous_and_resident() {
    let dir = tmp("bench-fleet-nc");
    let (ok, out, err) = run(&[
        "bench",
        "fleet",
        "--link",
        "nc-push",
        "--machines",
        "2",
        "--days",
        "0.05",
        "--realtime-min",
        "0",
        "--idle-s",
        "0",
        "--dir",
        dir.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    // Before, with the loops started and at the end: the whole resident set and its anonymous
    // part (the heap and stacks, without the program's mapped code), both read from /proc.
    let numbers = |line: &str| -> Vec<f64> {
        line.split(|c: char| !(c.is_ascii_digit() || c == '.'))
            .filter_map(|w| w.parse().ok())
            .collect()
    };
    let m = numbers(lines_starting(&out, "memory:")[0]);
    // [total, anon] before, [total, anon] started (and the machine count), [total, anon] end.
    assert_eq!(m.len(), 7, "{out}");
    for (total, anon) in [(m[0], m[1]), (m[2], m[3]), (m[5], m[6])] {
        assert!(anon > 0.0 && anon <= total, "{out}");
    }
    assert_eq!(m[4], 2.0, "{out}");
    let per_loop = numbers(lines_starting(&out, "memory per machine loop")[0]);
    assert_eq!(per_loop.len(), 4, "{out}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bench_fleet_runs_machines_through_the_launched_service_and_reports_its_figures() {
    let dir = tmp("bench-fleet");
    let (ok, out, err) = run(&[
        "bench",
        "fleet",
        "--machines",
        "2",
        "--days",
        "0.1",
        "--realtime-min",
        "0.05",
        "--dir",
        dir.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    // The machines really worked: the warm-up's cycles ran and were validated, no loop step
    // failed, and their data reached the store and the recordings.
    let cycles = figure_before(&out, "cycles:", "run");
    let validated = figure_before(&out, "cycles:", "validated");
    assert!(
        cycles >= 2.0 && validated >= 1.0 && validated <= cycles,
        "{out}"
    );
    assert_eq!(figure_after(&out, "cycles:", "faults"), 0.0, "{out}");
    assert!(figure_before(&out, "database:", "MB") > 0.0, "{out}");
    assert!(
        figure_before(&out, "database:", "MB/machine-year") > 0.0,
        "{out}"
    );
    assert!(figure_before(&out, "mcap:", "MB") > 0.0, "{out}");
    // The endpoint answered the client, with latencies in order.
    let answered = figure_before(&out, "endpoint:", "requests");
    let (p50, p99, max) = (
        figure_after(&out, "endpoint:", "p50"),
        figure_after(&out, "endpoint:", "p99"),
        figure_after(&out, "endpoint:", "max"),
    );
    assert!(
        answered >= 1.0 && p50 > 0.0 && p50 <= p99 && p99 <= max,
        "{out}"
    );
    assert_eq!(figure_before(&out, "endpoint:", "errors"), 0.0, "{out}");
    // Wall and CPU time were measured (their size is not asserted: it is the figure).
    assert!(figure_before(&out, "wall:", "s") > 0.0, "{out}");
    // Per machine-day (two decimals): the total, one decimal, reads 0.0 on a fast run.
    assert!(figure_before(&out, "cpu:", "s/machine-day") > 0.0, "{out}");
    assert!(figure_before(&out, "wall:", "real") > 0.0, "{out}");
    // Then 3 s at 1x: the loops' lag behind the clock was sampled, the endpoint answered.
    let lag = figure_after(&out, "realtime:", "max");
    assert!(lag.is_finite() && lag >= 0.0, "{out}");
    assert!(
        figure_before(&out, "realtime endpoint:", "requests") >= 1.0,
        "{out}"
    );
    assert_eq!(
        figure_before(&out, "realtime endpoint:", "errors"),
        0.0,
        "{out}"
    );
}

/// fl-thermal cut into five runs of about nine hours (each run's time from 0) with a run
/// column, ch3 and four temperatures: a thermal test of several days as a plant keeps it.
fn fl_thermal_runs(path: &Path) {
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/fl-thermal/fl_thermal.csv"),
    )
    .unwrap();
    let mut rd = csv::Reader::from_reader(text.as_bytes());
    let h = rd.headers().unwrap().clone();
    let col = |n: &str| h.iter().position(|x| x == n).unwrap();
    let keep = ["t1_C", "t5_C", "t9_C", "t13_C", "ch3_um"].map(col);
    let mut out = String::from("run,time_s,t1_C,t5_C,t9_C,t13_C,ch3_um\n");
    let run_s = 9.0 * 3600.0;
    for r in rd.records() {
        let r = r.unwrap();
        let t: f64 = r[col("time_s")].parse().unwrap();
        let run = (t / run_s).floor() as usize;
        if run >= 5 {
            continue;
        }
        let cells: Vec<&str> = keep.iter().map(|&i| &r[i]).collect();
        out.push_str(&format!(
            "day{run},{},{}\n",
            t - run as f64 * run_s,
            cells.join(",")
        ));
    }
    std::fs::write(path, out).unwrap();
}

/// Several runs in one table: `import csv --run-column` writes one recording per run, `fit
/// --runs` learns across the first four (forward chaining over whole runs, least squares on
/// the changes since each run's start as the baseline) and `predict --new-run` predicts the
/// fifth whole from its first reading, better than holding that reading; `bench thermal
/// --data` reads the same table from a manifest and reports it within and across runs.
#[test]
fn a_thermal_test_of_several_runs_is_learnt_across_runs_and_a_new_run_predicted_from_its_start() {
    let dir = tmp("runs");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let csv_path = dir.join("runs.csv");
    fl_thermal_runs(&csv_path);
    let recs = dir.join("recs");
    let (ok, out, err) = run(&[
        "import",
        "csv",
        "--in",
        csv_path.to_str().unwrap(),
        "--out",
        recs.to_str().unwrap(),
        "--time-column",
        "time_s",
        "--run-column",
        "run",
        "--temperature-columns",
        "t1_C,t5_C,t9_C,t13_C",
        "--displacement-columns",
        "ch3_um",
    ]);
    assert!(ok, "{out}{err}");
    let runs: Vec<String> = (0..5)
        .map(|i| {
            recs.join(format!("day{i}.mcap"))
                .to_str()
                .unwrap()
                .to_string()
        })
        .collect();
    assert!(runs.iter().all(|r| Path::new(r).exists()), "{out}");
    let model = dir.join("model.json");
    let mut args = vec![
        "fit",
        "--runs",
        "--out",
        model.to_str().unwrap(),
        "--recording",
    ];
    args.extend(runs[..4].iter().map(String::as_str));
    let (ok, out, err) = run(&args);
    assert!(ok, "{out}{err}");
    assert!(
        out.contains("ch3_um: 4 runs") && out.contains("served:"),
        "{out}"
    );
    let (ok, out, err) = run(&[
        "predict",
        "--new-run",
        "--model",
        model.to_str().unwrap(),
        "--recording",
        &runs[4],
    ]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("predicted ("), "{out}");
    // "RMSE a (first reading held b)"
    let figure = |after: &str| -> f64 {
        let i = err.find(after).unwrap_or_else(|| panic!("{err}")) + after.len();
        err[i..].split([' ', ')']).next().unwrap().parse().unwrap()
    };
    let (served, held) = (figure("RMSE "), figure("first reading held "));
    assert!(served < held, "{err}");
    // The same table as a data set.
    std::fs::write(
        dir.join("manifest.toml"),
        "name = \"fl-thermal in runs\"\ncsv = \"runs.csv\"\nrun = \"run\"\ntime = \"time_s\"\n\
         temperatures = [\"t1_C\", \"t5_C\", \"t9_C\", \"t13_C\"]\ndisplacements = [\"ch3_um\"]\nstep_min = 5.0\n",
    )
    .unwrap();
    let (ok, out, err) = run(&[
        "bench",
        "thermal",
        "--data",
        dir.to_str().unwrap(),
        "--no-simulated",
        "--json",
    ]);
    assert!(ok, "{out}{err}");
    let v: Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["within"].as_array().unwrap().len(), 5, "{out}");
    assert_eq!(v["across"].as_array().unwrap().len(), 4, "{out}");
    for row in v["across"].as_array().unwrap() {
        // Too few earlier runs for a challenger: pooled least squares is what is served.
        assert_eq!(row["served"], "regression", "{row}");
        assert_eq!(row["served_rmse"], row["regression"], "{row}");
    }
}

/// `bench located --data` on a small set: two 9-h runs cut from fl-thermal, four
/// temperatures, one channel. Under each sensor rule, each run gives a row with the rule's
/// sensor and onset and an outcome at every size (or, under `separable`, why no sensor
/// qualifies), and the table has a row per rule and size with every judged run as a trial.
#[test]
fn bench_located_reports_every_run_at_every_size() {
    let dir = tmp("located");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let csv_path = dir.join("runs.csv");
    fl_thermal_runs(&csv_path);
    // The first two runs only: the bench runs four diagnoses a run.
    let text = std::fs::read_to_string(&csv_path).unwrap();
    let two: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("run,") || l.starts_with("day0,") || l.starts_with("day1,"))
        .collect();
    std::fs::write(&csv_path, two.join("\n") + "\n").unwrap();
    std::fs::write(
        dir.join("manifest.toml"),
        "name = \"fl-thermal in runs\"\ncsv = \"runs.csv\"\nrun = \"run\"\ntime = \"time_s\"\n\
         temperatures = [\"t1_C\", \"t5_C\", \"t9_C\", \"t13_C\"]\ndisplacements = [\"ch3_um\"]\n",
    )
    .unwrap();
    let (ok, out, err) = run(&[
        "bench",
        "located",
        "--data",
        dir.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{out}{err}");
    let v: Value = serde_json::from_str(&out).unwrap();
    let all = v["runs"].as_array().unwrap();
    assert_eq!(all.len(), 4, "{out}");
    for r in all.iter().filter(|r| r["rule"] == "separable") {
        // A sensor that moves apart from time and the warm-up, or the reason there is none.
        assert!(
            r["error"].is_null()
                || r["error"]
                    .as_str()
                    .unwrap()
                    .contains("moves apart from time and the warm-up"),
            "{r}"
        );
    }
    let runs: Vec<&Value> = all.iter().filter(|r| r["rule"] == "range").collect();
    assert_eq!(runs.len(), 2, "{out}");
    for r in runs {
        assert!(r["error"].is_null(), "{r}");
        assert!(r["sensor"].as_str().unwrap().starts_with('t'), "{r}");
        let onset = r["onset_h"].as_f64().unwrap();
        assert!((3.0..4.0).contains(&onset), "{r}");
        let sizes: Vec<f64> = r["outcomes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|o| o["rms_um"].as_f64().unwrap())
            .collect();
        assert_eq!(sizes, [0.0, 1.5, 3.0, 6.0], "{r}");
    }
    let table = v["sizes"].as_array().unwrap();
    assert_eq!(table.len(), 8, "{out}");
    for s in table {
        let judged = 2 - s["not_judged"].as_u64().unwrap();
        assert_eq!(s["trials"], judged, "{s}");
        assert!(s["found"].as_u64().unwrap() <= judged, "{s}");
    }
    assert!(
        table
            .iter()
            .any(|s| s["rule"] == "range" && s["trials"] == 2)
    );
    // The text form: a line per run and the table.
    let (ok, out, err) = run(&["bench", "located", "--data", dir.to_str().unwrap()]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("day0") && out.contains("day1"), "{out}");
    assert!(
        out.contains("found and modelled") && out.contains("wall time"),
        "{out}"
    );
    assert!(
        out.contains("sensor rule range") && out.contains("sensor rule separable"),
        "{out}"
    );
}

/// A fresh folder holding the shipped fl-thermal set with its spindle manifest only.
fn fl_thermal_copy(name: &str) -> PathBuf {
    let dir = tmp(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/fl-thermal");
    std::fs::copy(data.join("manifest.toml"), dir.join("manifest.toml")).unwrap();
    std::fs::copy(data.join("fl_thermal.csv"), dir.join("fl_thermal.csv")).unwrap();
    dir
}

/// `bench served` replays the service's live model on the shipped fl-thermal run with a cycle
/// every 30 min: every channel is scored between its cycles, the model serves most of them,
/// and the served value beats the last cycle held on every channel. With `anchoring =
/// "always"` in the service's configuration (the last cycle moved by the model's change since
/// it) the model's median is better than with "never": the configuration is the one the
/// replay runs.
#[test]
fn bench_served_replays_the_live_model_between_cycles_on_a_real_run() {
    let dir = fl_thermal_copy("served");
    let bench = |extra: &[&str]| -> Value {
        let mut args = vec![
            "bench",
            "served",
            "--data",
            dir.to_str().unwrap(),
            "--cycle-every-min",
            "30",
            "--json",
        ];
        args.extend_from_slice(extra);
        let (ok, out, err) = run(&args);
        assert!(ok, "{out}{err}");
        serde_json::from_str(&out).unwrap()
    };
    let v = bench(&[]);
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 5, "{v}");
    for r in rows {
        let f = |k: &str| r[k].as_f64().unwrap();
        assert!(r["cycles"].as_u64().unwrap() >= 80, "{r}");
        let sources: Vec<u64> = r["sources"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap())
            .collect();
        assert!(
            sources[0] * 2 > sources.iter().sum::<u64>(),
            "the model serves most readings: {r}"
        );
        assert!(f("served_rmse") < f("last_cycle_rmse"), "{r}");
        // Judged gap by gap against the better baseline: never worse beyond chance here.
        assert!(r["gaps"].as_u64().unwrap() >= 80, "{r}");
        assert!(r["worse_beyond_chance"].is_null(), "{r}");
    }
    assert_eq!(v["summary"][0]["worse_beyond_chance"], 0, "{v}");
    let median = |v: &Value| v["summary"][0]["median_model"].as_f64().unwrap();
    let config =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/default.toml"))
            .unwrap();
    let with = |anchoring: &str| {
        let shipped = "anchoring = \"held_out\"";
        assert!(config.contains(shipped));
        let path = dir.join(format!("{anchoring}.toml"));
        let text = config.replace(shipped, &format!("anchoring = \"{anchoring}\""));
        std::fs::write(&path, text).unwrap();
        bench(&["--config", path.to_str().unwrap()])
    };
    let (never, always) = (with("never"), with("always"));
    assert!(
        median(&always) < median(&never),
        "anchored {} vs the filter's own value {}",
        median(&always),
        median(&never)
    );
}

/// `bench served --schedules` replays the service's scheduler on the shipped fl-thermal run:
/// its phases come from the run's spindle (warm-up and after-stop cycles), every cycle is
/// ordered by a rule, and each schedule's fixed cadence is the longest whole minute that plans
/// as many cycles. A tool-tip limit the band never reaches orders no cycle itself, but while
/// the trusted model holds it, it replaces the minute cadences: fewer of those.
#[test]
fn bench_served_replays_the_services_schedules_against_a_fixed_cadence() {
    let dir = fl_thermal_copy("served-schedules");
    let (ok, out, err) = run(&[
        "bench",
        "served",
        "--data",
        dir.to_str().unwrap(),
        "--schedules",
        "--tip-sigma",
        "1000",
        "--json",
    ]);
    assert!(ok, "{out}{err}");
    let v: Value = serde_json::from_str(&out).unwrap();
    let lines = v["summary"][0]["schedules"].as_array().unwrap();
    assert_eq!(lines.len(), 4, "{v}");
    let reasons = |l: &Value, k: &str| l["reasons"][k].as_u64().unwrap_or(0);
    let cadence = |l: &Value| {
        ["warm_up", "after_stop", "steady"]
            .map(|k| reasons(l, k))
            .iter()
            .sum::<u64>()
    };
    // The run's one span, min (rows 15 s apart from 0 to 166 710 s).
    let span_min = 166_710.0 / 60.0;
    for pair in lines.chunks(2) {
        let (scheduled, fixed) = (&pair[0], &pair[1]);
        let n = scheduled["cycles"].as_u64().unwrap();
        let by_rule: u64 = scheduled["reasons"]
            .as_object()
            .unwrap()
            .values()
            .map(|x| x.as_u64().unwrap())
            .sum();
        assert_eq!(by_rule, n, "every cycle has its rule: {scheduled}");
        let every = fixed["every_min"].as_f64().unwrap();
        let planned = |m: f64| (span_min / m).floor() as u64 + 1;
        assert!(
            planned(every) >= n && planned(every + 1.0) < n,
            "{every} min for {n} cycles"
        );
        assert_eq!(fixed["cycles"].as_u64().unwrap(), planned(every), "{fixed}");
    }
    let (offsets, tip) = (&lines[0], &lines[2]);
    assert!(
        reasons(offsets, "warm_up") > 0 && reasons(offsets, "after_stop") > 0,
        "{offsets}"
    );
    assert_eq!(reasons(tip, "tip"), 0, "{tip}");
    assert!(cadence(tip) < cadence(offsets), "{tip} {offsets}");
}
