//! Measurement programs: each dialect's program for the default plan is a golden file (replayed
//! through the truth simulator by the lab's tests); every family's plan in every dialect reads
//! back to the plan's own approaches and machine time; a bad program is refused by line.

use std::path::PathBuf;

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::measurement::latched;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_nc::dialect::Dialect;
use driftwatch_nc::program::{ProgramError, ProgramOptions, write};
use driftwatch_nc::reader::{Block, ReadError, ReplayError, read, replay};

const FAMILIES: [&str; 5] = [
    "table_bc",
    "head_b_table_c",
    "table_d45_c",
    "head_d45_table_c",
    "trunnion_ac",
];

/// The trt families as LinuxCNC's kinematics take them (table axes in the direct sense).
const LINUXCNC_MACHINES: [&str; 2] = ["xyzbc-trt", "xyzac-trt"];

fn plan_of(machine: &str) -> (Kinematics, Plan) {
    let k = if LINUXCNC_MACHINES.contains(&machine) {
        let path = format!(
            "{}/../../deploy/linuxcnc/machines/{machine}.toml",
            env!("CARGO_MANIFEST_DIR")
        );
        Kinematics::load(&path).unwrap()
    } else {
        Kinematics::builtin(machine).unwrap()
    };
    let cfg = PlanConfig::load(&k.config.plan).unwrap();
    let plan = Plan::build(&k, &cfg).unwrap();
    (k, plan)
}

fn program(k: &Kinematics, plan: &Plan, d: Dialect) -> String {
    write(k, plan, d, &ProgramOptions::defaults(d))
        .unwrap()
        .text
}

fn golden(d: Dialect) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(format!("patent_table_bc.{}", d.extension()))
}

/// The default plan's program in each dialect is the golden file, byte for byte (run with
/// `DRIFTWATCH_BLESS=1` to rewrite them after a deliberate change, and review the diff).
#[test]
fn default_programs_match_their_golden_files() {
    let (k, plan) = plan_of("table_bc");
    for d in Dialect::ALL {
        let text = program(&k, &plan, d);
        let path = golden(d);
        if std::env::var_os("DRIFTWATCH_BLESS").is_some() {
            std::fs::write(&path, &text).unwrap();
        }
        let want = std::fs::read_to_string(&path).unwrap();
        assert_eq!(
            text,
            want,
            "{d}: the program differs from {}",
            path.display()
        );
    }
}

/// Every family's own plan, in every dialect, reads back to the plan's approaches in order
/// (label, pose, start, axis, sense, feed, travel) and replays in the plan's machine time.
#[test]
fn every_family_reads_back_to_its_plan() {
    for machine in FAMILIES {
        let (k, plan) = plan_of(machine);
        let nominal = k.nominal_state();
        for d in Dialect::ALL {
            let text = program(&k, &plan, d);
            let p = read(&text, d).unwrap_or_else(|e| panic!("{machine} {d}: {e}"));
            let r = replay(&k, &p, |a| {
                let s = &plan.steps[a.number - 1];
                let start =
                    driftwatch_core::geometry::Vec3::new(a.start[0], a.start[1], a.start[2]);
                latched(&k, &nominal, &a.angles, &s.approach, &start, None).ok()
            })
            .unwrap_or_else(|e| panic!("{machine} {d}: {e}"));
            assert_eq!(r.approaches.len(), plan.steps.len(), "{machine} {d}");
            for ((a, v), s) in r.approaches.iter().zip(&plan.steps) {
                let what = format!("{machine} {d} {}", s.label);
                assert_eq!(a.label, s.label, "{what}");
                assert_eq!(a.axis, s.approach.axis, "{what}");
                assert_eq!(a.direction, s.approach.direction, "{what}");
                assert_eq!(a.feed_mm_min, s.approach.feed_mm_min, "{what}");
                assert!((a.travel_mm - s.max_travel_mm).abs() < 1e-3, "{what}");
                for i in 0..k.rotary.len() {
                    assert!((a.angles[i] - s.angles[i]).abs() < 1e-3, "{what}");
                }
                for i in 0..3 {
                    assert!((a.start[i] - s.start[i]).abs() <= 5e-4, "{what}");
                }
                assert!(
                    (v - s.expected).abs() < 2e-3,
                    "{what}: {v} vs {}",
                    s.expected
                );
                assert!((a.t_start_s - s.t_start_s).abs() < 0.01, "{what}");
            }
            assert!(
                (r.run_time_s - plan.machine_time_s).abs() < 0.01,
                "{machine} {d}: {} vs {}",
                r.run_time_s,
                plan.machine_time_s
            );
        }
    }
}

/// A program that does not say what driftwatch wrote is refused with its line.
#[test]
fn a_changed_program_is_refused_by_line() {
    let (k, plan) = plan_of("table_bc");
    let text = program(&k, &plan, Dialect::Fanuc);
    let incremental = text.replacen("G21 G90", "G21 G91", 1);
    match read(&incremental, Dialect::Fanuc) {
        Err(ReadError::Line { line, message, .. }) => {
            assert_eq!(
                line,
                1 + text.lines().position(|l| l.starts_with("G21")).unwrap()
            );
            assert!(message.contains("G91"), "{message}");
        }
        other => panic!("G91 read as {other:?}"),
    }
    // The result no longer stored: the skip is not paired.
    let unstored = text.replacen("#601=#5063", "#601=1", 1);
    assert!(read(&unstored, Dialect::Fanuc).is_err());
    // Truncated: no end block.
    let cut: String = text.lines().take(40).map(|l| format!("{l}\n")).collect();
    assert_eq!(read(&cut, Dialect::Fanuc), Err(ReadError::NoEnd));
    let siemens = program(&k, &plan, Dialect::Siemens).replacen("$AA_MM[Z]", "$AA_MW[Z]", 1);
    assert!(read(&siemens, Dialect::Siemens).is_err());
}

/// An approach that does not trip stops the replay, naming it; the program has the check
/// that makes a real control stop there too.
#[test]
fn a_failed_trip_stops_the_program() {
    let (k, plan) = plan_of("table_bc");
    for d in Dialect::ALL {
        let text = program(&k, &plan, d);
        let p = read(&text, d).unwrap();
        let third = plan.steps[2].label.clone();
        let r = replay(&k, &p, |a| (a.number != 3).then_some(0.0));
        assert_eq!(
            r.map(|_| ()),
            Err(ReplayError::NoTrip {
                number: 3,
                label: third
            }),
            "{d}"
        );
        let check = match d {
            Dialect::Fanuc => "GOTO9001",
            Dialect::Siemens => "IF $AC_MEA[1]==0 GOTO NOTRIP",
            // The TNC and LinuxCNC stop by themselves when a probing move makes no contact.
            Dialect::Heidenhain => "TCH PROBE 0.0",
            Dialect::Iso => "G38.2",
        };
        assert_eq!(
            text.matches(check).count(),
            plan.steps.len(),
            "{d}: one check per approach"
        );
        assert!(
            p.blocks
                .iter()
                .any(|b| matches!(b, Block::Spindle(s) if *s == plan.config.spindle_rpm))
        );
    }
}

/// A move as both readers see it: kind, the axis words with their values (f32 precision, as
/// the `gcode` crate keeps them).
fn moves_of_reader(blocks: &[Block]) -> Vec<(String, Vec<(char, f32)>)> {
    blocks
        .iter()
        .map(|b| match b {
            Block::Spindle(s) => ("spindle".to_string(), vec![('S', *s as f32)]),
            Block::Rapid(to) => (
                "rapid".to_string(),
                ['X', 'Y', 'Z']
                    .into_iter()
                    .zip(to)
                    .filter_map(|(c, v)| v.map(|v| (c, v as f32)))
                    .collect(),
            ),
            Block::Index(w) => (
                "rapid".to_string(),
                w.iter().map(|(c, v)| (*c, *v as f32)).collect(),
            ),
            Block::Dwell(s) => ("dwell".to_string(), vec![('T', *s as f32)]),
            Block::Skip {
                axis, end, feed, ..
            } => (
                "skip".to_string(),
                vec![
                    (
                        axis.name().to_ascii_uppercase().chars().next().unwrap(),
                        *end as f32,
                    ),
                    ('F', *feed as f32),
                ],
            ),
        })
        .collect()
}

fn moves_of_gcode_crate(text: &str) -> Vec<(String, Vec<(char, f32)>)> {
    // The crate reads G-code words, not macro statements: leave out the assignments, the
    // trip checks and the alarm block (the project's own reader checks those).
    let words: String = text
        .lines()
        .filter(|l| !(l.starts_with('#') || l.starts_with("IF") || l.starts_with("N9001")))
        .map(|l| format!("{l}\n"))
        .collect();
    let program = gcode::parse(&words).unwrap_or_else(|d| panic!("{d:?}"));
    let lit = |v: &gcode::Value| match v {
        gcode::Value::Literal(x) => *x,
        other => panic!("{other:?}"),
    };
    let mut out = Vec::new();
    for b in &program.blocks {
        let s_word = b.word_addresses.iter().find(|w| w.letter == 'S');
        for code in &b.codes {
            match code {
                gcode::Code::General(g) => {
                    let args: Vec<(char, f32)> =
                        g.args.iter().map(|a| (a.letter, lit(&a.value))).collect();
                    match g.number.to_string().as_str() {
                        "0" => out.push(("rapid".to_string(), args)),
                        "31" | "38.2" => out.push(("skip".to_string(), args)),
                        "4" => out.push(("dwell".to_string(), vec![('T', args[0].1)])),
                        _ => {}
                    }
                }
                gcode::Code::Miscellaneous(m) => match m.number.to_string().as_str() {
                    "3" => out.push((
                        "spindle".to_string(),
                        vec![('S', lit(&s_word.expect("M3 with S").value))],
                    )),
                    "5" => out.push(("spindle".to_string(), vec![('S', 0.0)])),
                    _ => {}
                },
                _ => {}
            }
        }
    }
    out
}

/// The `gcode` crate, an independent parser, reads the same moves from the FANUC and ISO
/// programs of every family as the project's reader does.
#[test]
fn an_independent_gcode_parser_reads_the_same_moves() {
    for machine in FAMILIES {
        let (k, plan) = plan_of(machine);
        for d in [Dialect::Fanuc, Dialect::Iso] {
            let text = program(&k, &plan, d);
            let ours = moves_of_reader(&read(&text, d).unwrap().blocks);
            let theirs = moves_of_gcode_crate(&text);
            assert_eq!(ours.len(), theirs.len(), "{machine} {d}");
            for (i, (a, b)) in ours.iter().zip(&theirs).enumerate() {
                assert_eq!(a.0, b.0, "{machine} {d} move {i}");
                assert_eq!(a.1.len(), b.1.len(), "{machine} {d} move {i}: {a:?} {b:?}");
                for ((ca, va), (cb, vb)) in a.1.iter().zip(&b.1) {
                    assert_eq!(ca, cb, "{machine} {d} move {i}");
                    assert!(
                        (va - vb).abs() <= 1e-4 * va.abs().max(1.0),
                        "{machine} {d} move {i}"
                    );
                }
            }
        }
    }
}

/// LinuxCNC's standalone interpreter (`rs274` of the `linuxcnc-uspace` package; `./test.sh`
/// installs it where it is missing).
const RS274: &str = "/usr/bin/rs274";

/// The probe moves LinuxCNC's interpreter makes of a program: each `STRAIGHT_PROBE(x, y, z,
/// a, b, c)` of its canonical output, and whether it reached `PROGRAM_END()`.
fn probes_of_rs274(text: &str, name: &str) -> (Vec<[f64; 6]>, bool) {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("rs274");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(format!("{name}.ngc"));
    std::fs::write(&path, text).unwrap();
    let out = std::process::Command::new(RS274)
        .arg("-g")
        .arg(&path)
        .current_dir(&dir)
        .output()
        .unwrap_or_else(|e| panic!("{RS274} (package linuxcnc-uspace): {e}"));
    let canon =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{name}: rs274 failed:\n{canon}");
    // Each approach's LOG line, as LinuxCNC writes it: its step number and the latched
    // value (standalone, a probe move latches its end point), nothing substituted away.
    let logs: Vec<&str> = canon
        .lines()
        .filter_map(|l| {
            l.split_once("LOG(\"")
                .map(|(_, s)| s.trim_end_matches("\")"))
        })
        .collect();
    let probes: Vec<[f64; 6]> = canon
        .lines()
        .filter_map(|l| l.split_once("STRAIGHT_PROBE("))
        .map(|(_, args)| {
            let v: Vec<f64> = args
                .trim_end_matches(')')
                .split(',')
                .map(|x| x.trim().parse().unwrap())
                .collect();
            [v[0], v[1], v[2], v[3], v[4], v[5]]
        })
        .collect();
    assert_eq!(logs.len(), probes.len(), "{name}: {logs:?}");
    for (i, (log, _)) in logs.iter().zip(&probes).enumerate() {
        let (n, v) = log
            .split_once(' ')
            .unwrap_or_else(|| panic!("{name}: {log}"));
        assert_eq!(n, (i + 1).to_string(), "{name}: {log}");
        v.parse::<f64>()
            .unwrap_or_else(|e| panic!("{name}: {log}: {e}"));
    }
    // Each approach's message to the control's message channel (what a gateway posts as the
    // detection): its step number and the whole latched position, as substituted.
    let messages: Vec<Vec<f64>> = canon
        .lines()
        .filter_map(|l| l.split_once("MESSAGE(\"DW "))
        .map(|(_, s)| {
            s.trim_end_matches("\")")
                .split(' ')
                .map(|x| x.parse().unwrap_or_else(|e| panic!("{name}: {s}: {e}")))
                .collect()
        })
        .collect();
    assert_eq!(messages.len(), probes.len(), "{name}: {messages:?}");
    for (i, (m, p)) in messages.iter().zip(&probes).enumerate() {
        assert_eq!(m.len(), 4, "{name}: {m:?}");
        assert_eq!(m[0], (i + 1) as f64, "{name}: {m:?}");
        for c in 0..3 {
            assert!(
                (m[1 + c] - p[c]).abs() < 1e-6,
                "{name}: step {}: {m:?} vs {p:?}",
                i + 1
            );
        }
    }
    (probes, canon.contains("PROGRAM_END()"))
}

/// LinuxCNC's own interpreter runs every family's ISO program to its end (no clamp M code it
/// does not know), and those of the two machines LinuxCNC's trt kinematics drive
/// (deploy/linuxcnc/machines), with one probe move per approach of the plan, each to the point the
/// project's reader reads: the travel's end on the probing axis, the other axes and the rotary
/// axes where the program left them.
#[test]
fn linuxcncs_interpreter_runs_every_familys_iso_program_to_the_end() {
    for machine in FAMILIES.into_iter().chain(LINUXCNC_MACHINES) {
        let (k, plan) = plan_of(machine);
        let text = program(&k, &plan, Dialect::Iso);
        let (probes, ended) = probes_of_rs274(&text, machine);
        assert!(ended, "{machine}: LinuxCNC did not reach the program's end");
        assert_eq!(probes.len(), plan.steps.len(), "{machine}");
        // The reader's view: linear position and rotary angles (A, B, C) before each skip.
        let mut pos = [0.0; 3];
        let mut rot = [0.0; 3];
        let mut want = Vec::new();
        for b in read(&text, Dialect::Iso).unwrap().blocks {
            match b {
                Block::Rapid(to) => {
                    for (p, v) in pos.iter_mut().zip(to) {
                        *p = v.unwrap_or(*p);
                    }
                }
                Block::Index(words) => {
                    for (c, v) in words {
                        rot[(c as u8 - b'A') as usize] = v;
                    }
                }
                Block::Skip { axis, end, .. } => {
                    let mut p = pos;
                    p[axis.index()] = end;
                    want.push([p[0], p[1], p[2], rot[0], rot[1], rot[2]]);
                }
                _ => {}
            }
        }
        assert_eq!(want.len(), probes.len(), "{machine}");
        for (i, (w, got)) in want.iter().zip(&probes).enumerate() {
            for (a, b) in w.iter().zip(got) {
                assert!(
                    (a - b).abs() < 1e-4,
                    "{machine} probe {i}: {w:?} vs {got:?}"
                );
            }
        }
    }
}

/// The clamp codes a plant names (`--unclamp`, `--clamp`) are written into the program's
/// header, and the reader takes those M codes and no other: a LinuxCNC machine's user M codes
/// (M100-M199, a script each) in the ISO program and a builder's M68/M69 in the FANUC one read
/// back to the same moves as the defaults; an M code the header does not name is refused.
#[test]
fn the_clamp_codes_a_program_names_are_the_only_ones_read() {
    let (k, plan) = plan_of("table_bc");
    for (d, unclamp, clamp) in [
        (Dialect::Iso, "M101", "M100"),
        (Dialect::Fanuc, "M69", "M68"),
        (Dialect::Siemens, "M69", "M68"),
        (Dialect::Heidenhain, "M69", "M68"),
    ] {
        let mut opts = ProgramOptions::defaults(d);
        let plain = write(&k, &plan, d, &opts).unwrap().text;
        opts.unclamp = unclamp.into();
        opts.clamp = clamp.into();
        let mapped = write(&k, &plan, d, &opts).unwrap().text;
        assert!(mapped.contains(unclamp) && !plain.contains(unclamp), "{d}");
        assert_eq!(
            read(&mapped, d).unwrap().blocks,
            read(&plain, d).unwrap().blocks,
            "{d}"
        );
        // The same program with the header naming other codes: its clamp lines are refused.
        let renamed = mapped.replace(
            &format!("UNCLAMP {unclamp} CLAMP {clamp}"),
            "UNCLAMP M11 CLAMP M10",
        );
        assert!(
            matches!(read(&renamed, d), Err(ReadError::Line { text, .. }) if text.ends_with(unclamp)),
            "{d}"
        );
    }
    // A code with another meaning, or not one M word, is refused when the program is written.
    for bad in ["M5", "M30", "M10 P1", "X10", "M"] {
        let mut opts = ProgramOptions::defaults(Dialect::Fanuc);
        opts.clamp = bad.into();
        assert!(
            matches!(
                write(&k, &plan, Dialect::Fanuc, &opts),
                Err(ProgramError::ClampCode(c)) if c == bad
            ),
            "{bad}"
        );
    }
}

/// A plan whose crossing passes through the beam (trunnion_ac at A-90 C-135 crossed at its
/// lateral start + 5, as plans were laid out before the crossing followed the beam's slope) is
/// refused in every dialect, with the move named.
#[test]
fn a_path_through_the_beam_is_refused() {
    let (k, mut plan) = plan_of("trunnion_ac");
    let j = plan
        .moves
        .iter()
        .enumerate()
        .position(|(j, m)| {
            j > 0
                && m.note == "to the approach"
                && plan.moves[j - 1].note == "up clear of the setter"
                && plan.moves[j..]
                    .iter()
                    .find_map(|n| n.step)
                    .is_some_and(|s| plan.steps[s].label.starts_with("A-90C-135/y"))
        })
        .expect("a crossing to a lateral start at A-90 C-135");
    let next = plan.moves[j..].iter().find_map(|n| n.step).unwrap();
    let old = plan.steps[next].start.z + 5.0;
    for m in &mut plan.moves[j - 1..=j] {
        m.to[2] = old;
    }
    for d in Dialect::ALL {
        match write(&k, &plan, d, &ProgramOptions::defaults(d)) {
            Err(ProgramError::StrikesBeam { first, .. }) => {
                assert!(first.contains("A-90C-135/y"), "{first}")
            }
            other => panic!("{d}: {:?}", other.map(|p| p.text.len())),
        }
    }
}
