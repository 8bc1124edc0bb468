//! `driftwatch serve` killed with SIGKILL in the middle of a measurement cycle, then started
//! again on the same data directory: no validated compensation is lost, the cycle that was
//! running is abandoned, the recording left open is recovered, and a clean stop leaves only
//! finished MCAP files and a sound database.
//!
//! The service runs as a real child process; the test talks to it over plain HTTP/1.1. The only
//! waiting on the wall clock is polling that child (every wait is bounded).
#![cfg(unix)]

use crate::common;

use std::collections::BTreeSet;
use std::fs::{self, File};
use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::Value;

use driftwatch_recording::mcap_io::{ReadOptions, read_file};
use driftwatch_service::store::{CycleStatus, FileStatus, Store};

use common::child::Serve;

const MACHINE: &str = "sim-1";
/// Steps of the default `patent` plan: one detection each.
const STEPS: usize = 24;

/// `serve` on `data` at `time_scale`.
fn start(data: &Path, time_scale: f64, log: PathBuf) -> Serve {
    let args = [
        "--time-scale".to_string(),
        time_scale.to_string(),
        "--data-dir".to_string(),
        data.display().to_string(),
    ];
    Serve::start(&args, log)
}

fn copy_dir(from: &Path, to: &Path) {
    fs::create_dir_all(to).unwrap();
    for e in fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// File names in `dir` ending with `suffix`, sorted.
fn files_ending(dir: &Path, suffix: &str) -> Vec<String> {
    let mut v: Vec<String> = fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(suffix))
        .collect();
    v.sort();
    v
}

fn status_of(cycles: &[Value], n: i64) -> String {
    cycles
        .iter()
        .find(|c| c["cycle"].as_i64() == Some(n))
        .and_then(|c| c["status"].as_str())
        .unwrap_or("missing")
        .to_string()
}

/// What the database held at the moment of the kill (read from a copy, so that the restarted
/// service finds the data directory exactly as the kill left it).
struct AtKill {
    open: Vec<i64>,
    open_detections: usize,
    closed: BTreeSet<i64>,
    ok: BTreeSet<i64>,
    version: u64,
}

fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

#[test]
fn a_kill_during_a_cycle_loses_no_validated_result_and_leaves_recoverable_files() {
    let tmp = PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
    // Another `cargo test` on the same target directory may run this test at the same time:
    // one at a time, since both use the directory left behind for the recording check.
    let lock = File::create(tmp.join("crash.lock")).unwrap();
    lock.lock().unwrap();
    let base = tmp.join("crash");
    let _ = fs::remove_dir_all(&base);
    fs::create_dir_all(&base).unwrap();
    let data = base.join("data");
    let rec_dir = data.join("mcap").join(MACHINE);

    // 1. Run fast until two cycles were validated and a later one is half-way, then SIGKILL.
    let mut first = start(&data, 300.0, base.join("serve-1.log"));
    let deadline = Instant::now() + Duration::from_secs(60);
    let (open_cycle, seen_version, ok_before, seen_detections) = loop {
        assert!(
            Instant::now() < deadline,
            "no cycle open after two validated ones within 60 s; last view {}\n{}",
            first.machine(MACHINE),
            first.log_text()
        );
        let m = first.machine(MACHINE);
        let version = m["compensation_version"].as_u64().unwrap_or(0);
        if let (true, Some(n)) = (version >= 2, m["open_cycle"].as_i64()) {
            let ok: BTreeSet<i64> = first
                .cycles(MACHINE)
                .iter()
                .filter(|c| c["status"] == "ok")
                .map(|c| c["cycle"].as_i64().unwrap())
                .collect();
            let (code, c) = first.get(&format!("/api/v1/machines/{MACHINE}/cycles/{n}"));
            let d = m["open_cycle_progress"]["received"].as_u64().unwrap_or(0) as usize;
            assert_eq!(
                m["open_cycle_progress"]["expected"].as_u64(),
                Some(STEPS as u64)
            );
            // Half-way: at least a few detections received and a few still to come, so the
            // kill lands inside the cycle however the poll and the signal are delayed.
            if code == 200 && c["cycle"]["status"] == "open" && (2..=STEPS - 6).contains(&d) {
                first.child.kill().unwrap();
                break (n, version, ok, d);
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let status = first.child.wait().unwrap();
    assert_eq!(status.signal(), Some(9), "{status}");
    // At least one compensation version per validated cycle (predicted sets come between).
    assert!(
        seen_version >= ok_before.len() as u64,
        "ok cycles {ok_before:?} vs version {seen_version}"
    );

    // The kill left the recording open.
    let partials = files_ending(&rec_dir, ".mcap.partial");
    assert_eq!(partials.len(), 1, "{partials:?}");
    let kill_partial = partials[0].clone();
    let snapshot = base.join("at-kill");
    copy_dir(&data, &snapshot);
    let at_kill = rt().block_on(async {
        let store = Store::open(&snapshot.join("driftwatch.db")).await.unwrap();
        let cycles = store.cycles(MACHINE, 1000, None).await.unwrap();
        let open = store.open_cycles(MACHINE).await.unwrap();
        let open_detections = store.detections(MACHINE, open_cycle).await.unwrap().len();
        let version = store
            .latest_compensation(MACHINE)
            .await
            .unwrap()
            .map_or(0, |v| v.version);
        store.close().await;
        AtKill {
            open,
            open_detections,
            closed: cycles
                .iter()
                .filter(|c| matches!(c.status, CycleStatus::Ok | CycleStatus::Rejected))
                .map(|c| c.cycle)
                .collect(),
            ok: cycles
                .iter()
                .filter(|c| c.status == CycleStatus::Ok)
                .map(|c| c.cycle)
                .collect(),
            version,
        }
    });
    assert_eq!(
        at_kill.open,
        vec![open_cycle],
        "the kill was not inside the cycle"
    );
    // A cycle's detections are written with its end (result, timeout or shutdown): the
    // interrupted cycle left none in the database, only an open row that the restart abandons.
    assert!(seen_detections >= 2);
    assert_eq!(
        at_kill.open_detections, 0,
        "cycle {open_cycle}: detections stored before its end"
    );
    assert_eq!(
        at_kill.version, seen_version,
        "the stored set differs from the served one"
    );
    assert_eq!(at_kill.ok, ok_before);
    let highest_ok = *at_kill.ok.last().unwrap();
    // What the partial file holds up to its last complete chunk: flushed after every cycle.
    let cut = read_file(
        &rec_dir.join(&kill_partial),
        &ReadOptions {
            recover_truncated: true,
            ..Default::default()
        },
    )
    .unwrap();
    let cut_results: BTreeSet<i64> = cut.results.iter().map(|r| r.msg.cycle).collect();
    assert_eq!(cut_results, at_kill.closed, "results in the cut recording");

    // 2. Start again on the same data directory. At 1x its clock stays before the 06:00 power-on
    // while the test looks, so no new cycle can run: what it serves is what survived the kill.
    let mut second = start(&data, 1.0, base.join("serve-2.log"));
    let (code, comp) = second.get(&format!("/api/v1/machines/{MACHINE}/compensation"));
    assert_eq!(code, 200, "{comp}");
    let served = comp["version"].as_u64().unwrap();
    assert_eq!(
        served, seen_version,
        "served version after the restart; before the kill {seen_version}"
    );
    assert_eq!(comp["cycle"].as_i64(), Some(highest_ok), "{comp}");
    let m = second.machine(MACHINE);
    assert_eq!(m["compensation_version"].as_u64(), Some(served), "{m}");
    assert!(m["open_cycle"].is_null(), "{m}");
    let cycles = second.cycles(MACHINE);
    assert_eq!(status_of(&cycles, open_cycle), "abandoned", "{cycles:?}");
    for n in &at_kill.ok {
        assert_eq!(status_of(&cycles, *n), "ok", "cycle {n}");
    }
    assert!(cycles.iter().all(|c| c["status"] != "open"), "{cycles:?}");
    assert_eq!(
        cycles.iter().filter_map(|c| c["cycle"].as_i64()).max(),
        Some(open_cycle),
        "a cycle ran after the restart: {cycles:?}"
    );
    // The partial file was recovered under its final name; the new run writes its own.
    let recovered_name = kill_partial.trim_end_matches(".partial").to_string();
    assert!(
        !rec_dir.join(&kill_partial).exists(),
        "{kill_partial} was not recovered"
    );
    assert!(rec_dir.join(&recovered_name).exists(), "{recovered_name}");

    // Stop cleanly with SIGTERM.
    let pid = second.child.id().to_string();
    let killed = Command::new("kill").args(["-TERM", &pid]).status().unwrap();
    assert!(killed.success());
    let status = second.wait_exit(Duration::from_secs(30));
    assert!(status.success(), "{status}\n{}", second.log_text());
    drop(second);

    // 3. The files after the clean stop: nothing left open, every file finished.
    assert_eq!(files_ending(&rec_dir, ".partial"), Vec::<String>::new());
    let finished = files_ending(&rec_dir, ".mcap");
    assert!(finished.len() >= 2, "{finished:?}");
    assert!(finished.contains(&recovered_name), "{finished:?}");
    for f in &finished {
        let r = read_file(&rec_dir.join(f), &ReadOptions::default())
            .unwrap_or_else(|e| panic!("{f}: {e}"));
        assert!(r.truncated.is_none(), "{f}: {:?}", r.truncated);
        assert!(r.info.is_some(), "{f}: no /machine/info");
    }
    // The recovered file holds every contract message the cut file held.
    let recovered = read_file(&rec_dir.join(&recovered_name), &ReadOptions::default()).unwrap();
    assert_eq!(recovered.results.len(), cut.results.len());
    assert_eq!(recovered.detections.len(), cut.detections.len());
    assert_eq!(recovered.spindle.len(), cut.spindle.len());
    assert_eq!(recovered.temperatures.len(), cut.temperatures.len());
    assert_eq!(recovered.states.len(), cut.states.len());
    for c in &at_kill.ok {
        let n = recovered
            .detections
            .iter()
            .filter(|d| d.msg.as_ref().is_ok_and(|d| d.cycle == *c))
            .count();
        assert_eq!(n, STEPS, "cycle {c}: detections in {recovered_name}");
    }

    // The database after the clean stop.
    rt().block_on(async {
        let store = Store::open(&data.join("driftwatch.db")).await.unwrap();
        assert_eq!(store.integrity_check().await.unwrap(), "ok");
        let rows = store.cycles(MACHINE, 1000, None).await.unwrap();
        let status = |n: i64| {
            rows.iter()
                .find(|r| r.cycle == n)
                .map(|r| r.status)
                .ok_or("missing")
        };
        for n in &ok_before {
            assert_eq!(
                status(*n),
                Ok(CycleStatus::Ok),
                "cycle {n} reported ok before the kill"
            );
        }
        let abandoned = rows.iter().find(|r| r.cycle == open_cycle).unwrap();
        assert_eq!(abandoned.status, CycleStatus::Abandoned);
        assert!(abandoned.reason.is_some());
        let latest = store.latest_compensation(MACHINE).await.unwrap().unwrap();
        assert_eq!(latest.version, served, "{latest:?}");
        assert_eq!(latest.cycle, Some(highest_ok), "{latest:?}");
        let files = store.mcap_files(MACHINE).await.unwrap();
        assert!(
            files.iter().any(
                |(p, s)| Path::new(p).file_name() == Some(recovered_name.as_ref())
                    && *s == FileStatus::Recovered
            ),
            "{files:?}"
        );
        assert!(
            files.iter().all(|(_, s)| *s != FileStatus::Open),
            "{files:?}"
        );
        store.close().await;
    });
}
