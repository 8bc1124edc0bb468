//! `driftwatch nc offsets` end to end: a set as the service serves it becomes a FANUC, Siemens,
//! LinuxCNC or json answer with the step from the previous set; a step beyond the limit and an
//! unknown format are refused with the reason and no program.

use std::path::PathBuf;
use std::process::Command;

use serde_json::{Value, json};

fn run(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_driftwatch"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// A table_bc set as `GET /compensation` returns it, written to a file.
fn set_file(name: &str, version: u64, minute: i64, ez0b: f64) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("nc-cli");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    let set = json!({
        "version": version,
        "valid_from_ns": 1_772_431_200_000_000_000i64 + minute * 60_000_000_000,
        "source": "measured",
        "cycle": version,
        "errors": {"EX0B": 21.4, "EZ0B": ez0b, "EY0C": -3.25, "EX0C": 6.5, "EA0C": 12.0, "EB0C": -8.0},
        "sigma": {"EX0B": 0.4, "EZ0B": 0.6, "EY0C": 0.3, "EX0C": 0.3, "EA0C": 3.0, "EB0C": 3.0},
        // Stale on purpose: the command derives the offsets from the errors.
        "offsets": {"B_pivot_x_um": 999.0},
        "reason": "test"
    });
    std::fs::write(&path, set.to_string()).unwrap();
    path
}

fn arg(p: &std::path::Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn nc_offsets_writes_each_form_with_its_steps() {
    let prev = set_file("prev.json", 4, 0, 30.0);
    let next = set_file("next.json", 5, 10, 42.5);
    let base = [
        "nc",
        "offsets",
        "--machine",
        "table_bc",
        "--from",
        arg(&next),
        "--previous",
        arg(&prev),
    ];
    let (ok, out, err) = run(&[
        &base[..],
        &[
            "--format",
            "fanuc",
            "--nominal",
            "19700=-100",
            "--nominal",
            "19702=20.0001",
            "--nominal",
            "19703=0.5004",
            "--nominal",
            "19704=0",
        ],
    ]
    .concat());
    assert!(ok, "{err}");
    // (-100 mm + 21.4 um) / 1 um = -99978.6 -> -99979; 20.0001 mm + 42.5 um = 20042.6 -> 20043,
    // from 20030.1 -> 20030: a step of 13 increments; 0.5004 mm + 6.5 um = 506.9 -> 507.
    assert!(out.contains("\nN19700 R-99979 ("), "{out}");
    assert!(out.contains("\nN19702 R20043 ("), "{out}");
    let z = out.lines().find(|l| l.starts_with("N19702 ")).unwrap();
    assert!(z.contains("STEP +13 "), "{z}");
    assert!(
        out.contains("\nN19703 R507 (") && out.contains("\nN19704 R-3 ("),
        "{out}"
    );

    let (ok, out, err) = run(&[&base[..], &["--format", "siemens", "--carrier", "2"]].concat());
    assert!(ok, "{err}");
    assert!(
        out.contains("\n$TC_CARR46[2]=0.0425 ; l2 fine z, step +0.0125 mm"),
        "{out}"
    );

    let (ok, out, err) = run(&[&base[..], &["--format", "json"]].concat());
    assert!(ok, "{err}");
    let j: Value = serde_json::from_str(&out).unwrap();
    assert_eq!(j["version"], 5);
    assert_eq!(j["previous_version"], 4);
    assert_eq!(
        j["offsets"]["C_pivot_x_um"], 27.9,
        "derived from the errors: {j}"
    );
    let cx = j["variables"]
        .as_array()
        .unwrap()
        .iter()
        .find(|v| v["name"] == "B_pivot_z_um")
        .unwrap();
    assert_eq!(cx["step"], 12.5);
}

/// LinuxCNC's `xyzbc-trt-kins` pins for the machine of `deploy/linuxcnc/machines` (table_bc's
/// errors in the direct sense): commissioned value + move as `setp` lines, each after its step;
/// a pin the kinematics lack and table_bc (ISO 841 table sense) refused.
#[test]
fn nc_offsets_writes_the_linuxcnc_pins() {
    let prev = set_file("lcnc-prev.json", 4, 0, 30.0);
    let next = set_file("lcnc-next.json", 5, 10, 42.5);
    let machine = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/deploy/linuxcnc/machines/xyzbc-trt.toml"
    );
    let args = |machine: &'static str, extra: &'static [&'static str]| -> Vec<String> {
        [
            "nc",
            "offsets",
            "--format",
            "linuxcnc",
            "--machine",
            machine,
            "--from",
            arg(&next),
            "--previous",
            arg(&prev),
            "--pin-nominal",
            "x-rot-point=0",
            "--pin-nominal",
            "y-rot-point=0",
            "--pin-nominal",
            "x-offset=0",
            "--pin-nominal",
            "z-offset=-50",
        ]
        .iter()
        .chain(extra)
        .map(|s| s.to_string())
        .collect()
    };
    let call = |a: Vec<String>| run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let (ok, out, err) = call(args(machine, &[]));
    assert!(ok, "{err}");
    // EX0B 21.4 + EX0C 6.5 um; EY0C -3.25 um; -EX0C; EZ0B 42.5 um (from 30: +12.5 um).
    assert!(
        out.contains("\n# x-rot-point, step +0 mm\nsetp xyzbc-trt-kins.x-rot-point 0.027900\n"),
        "{out}"
    );
    assert!(
        out.contains("\nsetp xyzbc-trt-kins.y-rot-point -0.003250\n"),
        "{out}"
    );
    assert!(
        out.contains("\nsetp xyzbc-trt-kins.x-offset -0.006500\n"),
        "{out}"
    );
    assert!(
        out.contains("\n# z-offset, step +0.0125 mm\nsetp xyzbc-trt-kins.z-offset -49.957500\n"),
        "{out}"
    );
    assert!(
        out.contains("\n# not written: EA0C = 12.000 urad\n"),
        "{out}"
    );
    assert!(
        out.lines()
            .all(|l| l.starts_with('#') || l.starts_with("setp xyzbc-trt-kins.")),
        "{out}"
    );
    let (ok, _, err) = call(args(machine, &["--pin-nominal", "tool-offset=0"]));
    assert!(!ok && err.contains("tool-offset"), "{err}");
    let (ok, out, err) = call(args("table_bc", &[]));
    assert!(!ok && out.is_empty(), "{out}");
    assert!(err.contains("sense = \"direct\""), "{err}");
}

#[test]
fn nc_offsets_refuses_a_step_beyond_the_limit_and_an_unknown_format() {
    // 80 um in 1 min: over 50 um + 4 um/min.
    let prev = set_file("far-prev.json", 1, 0, -30.0);
    let next = set_file("far-next.json", 2, 1, 50.0);
    let (ok, out, err) = run(&[
        "nc",
        "offsets",
        "--format",
        "siemens",
        "--machine",
        "table_bc",
        "--from",
        arg(&next),
        "--previous",
        arg(&prev),
    ]);
    assert!(!ok && out.is_empty(), "{out}");
    assert!(
        err.contains("EZ0B") && err.contains("beyond the limit"),
        "{err}"
    );
    let (ok, _, err) = run(&[
        "nc",
        "offsets",
        "--format",
        "mazak",
        "--machine",
        "table_bc",
        "--from",
        arg(&next),
    ]);
    assert!(!ok && err.contains("mazak"), "{err}");
}
