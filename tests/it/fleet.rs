//! Two `driftwatch serve` processes on one PostgreSQL database share a fleet of three
//! simulated machines through leases. The first takes them all; the second shows them from the
//! database and refuses to change them. The first is killed with SIGKILL in the middle of a
//! measurement cycle; the second takes its machines over within the lease time and carries on.
//! From the stored data: no validated result the first served is lost, no compensation version
//! is reused or goes backwards, and no machine was run by two processes at once.
//!
//! Real processes and a real PostgreSQL server (Debian `postgresql`; the test fails, naming
//! the package, without it). Leases run on the wall clock: the waits poll and are bounded.
#![cfg(unix)]

use crate::common;

use std::collections::BTreeMap;
use std::fs;
use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::Value;

use common::child::Serve;
use driftwatch_scratch_pg::ScratchPg;
use driftwatch_service::store::Store;

const MACHINES: [&str; 3] = ["f1", "f2", "f3"];
const LEASE_S: f64 = 2.0;
/// Steps of the `patent` plan: one detection each.
const STEPS: u64 = 24;
const TOKEN: &str = "fleet-test-operator";

fn config(dir: &Path, process: &str, url: &str) -> PathBuf {
    let mut text = format!(
        r#"data_dir = "{data}"
database_url = "{url}"
time_scale = 300.0
max_file_mib = 256

[http]
listen = "127.0.0.1:0"
anonymous_read = true
tokens = [{{ name = "operator", token = "{TOKEN}", role = "write" }}]

[fleet]
process = "{process}"
lease_s = {LEASE_S}
"#,
        data = dir.join(process).display()
    );
    for (i, id) in MACHINES.iter().enumerate() {
        text.push_str(&format!(
            "\n[[machines]]\nid = \"{id}\"\nmachine = \"table_bc\"\nplan = \"patent\"\n\
             link = {{ kind = \"simulated\", scenario = \"two_shift\", seed = {} }}\n",
            i + 1
        ));
    }
    let path = dir.join(format!("{process}.toml"));
    fs::write(&path, text).unwrap();
    path
}

fn serve(dir: &Path, process: &str, url: &str) -> Serve {
    let cfg = config(dir, process, url);
    Serve::start(
        &["--config".to_string(), cfg.display().to_string()],
        dir.join(format!("{process}.log")),
    )
}

/// Machine id -> (holder, live) from `/api/v1/fleet`.
fn holders(s: &Serve) -> BTreeMap<String, (String, bool)> {
    let (code, body) = s.get("/api/v1/fleet");
    assert_eq!(code, 200, "{body}");
    body["leases"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| {
            let live = l["expires_ms"].as_i64() > l["now_ms"].as_i64();
            (
                l["machine_id"].as_str().unwrap().to_string(),
                (l["holder"].as_str().unwrap().to_string(), live),
            )
        })
        .collect()
}

fn all_held_by(s: &Serve, process: &str) -> bool {
    let h = holders(s);
    MACHINES
        .iter()
        .all(|m| h.get(*m).is_some_and(|(p, live)| p == process && *live))
}

/// Poll `f` (bounded) until it holds.
fn wait_for(what: &str, within: Duration, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + within;
    while !f() {
        assert!(Instant::now() < deadline, "not within {within:?}: {what}");
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// (version, valid_from_ns) of the set a process serves for `id`, if any.
fn served(s: &Serve, id: &str) -> Option<(u64, i64)> {
    let (code, body) = s.get(&format!("/api/v1/machines/{id}/compensation"));
    (code == 200).then(|| {
        (
            body["version"].as_u64().unwrap(),
            body["valid_from_ns"].as_i64().unwrap(),
        )
    })
}

fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

#[test]
fn a_fleet_survives_the_kill_of_a_process_mid_cycle() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("fleet");
    let _ = fs::remove_dir_all(&dir);
    fs::create_dir_all(&dir).unwrap();
    let pg = ScratchPg::start(&dir).unwrap_or_else(|e| panic!("{e}"));
    let (_, url) = rt().block_on(pg.database()).unwrap();

    // 1. `a` takes every machine; `b`, started after, holds none and shows them from the
    // database, refusing to change them.
    let mut a = serve(&dir, "a", &url);
    wait_for("a holds every machine", Duration::from_secs(30), || {
        all_held_by(&a, "a")
    });
    let mut b = serve(&dir, "b", &url);
    wait_for("b shows a as the holder", Duration::from_secs(10), || {
        MACHINES.iter().all(|m| {
            let f = &b.machine(m)["fleet"];
            f["holder"] == "a" && f["here"] == false
        })
    });
    assert!(all_held_by(&b, "a"), "{:?}", holders(&b));
    let (code, body) = b.post("/api/v1/machines/f1/cycles", TOKEN);
    assert_eq!(code, 409, "{body}");
    assert_eq!(body["code"], "run_elsewhere", "{body}");
    assert!(
        body["message"].as_str().unwrap().contains("process 'a'"),
        "{body}"
    );

    // 2. Run until a has served sets and a cycle is half-way, recording every set a served
    // (and checking that b serves the same from the database); then SIGKILL a.
    let mut seen: BTreeMap<(String, u64), i64> = BTreeMap::new();
    let deadline = Instant::now() + Duration::from_secs(90);
    let killed_in = loop {
        assert!(
            Instant::now() < deadline,
            "no half-way cycle after served sets within 90 s\n{}",
            a.log_text()
        );
        for m in MACHINES {
            if let Some((v, from)) = served(&a, m) {
                seen.insert((m.to_string(), v), from);
            }
        }
        let half_way = MACHINES.iter().find(|m| {
            let v = a.machine(m);
            let received = v["open_cycle_progress"]["received"].as_u64().unwrap_or(0);
            v["open_cycle"].is_i64() && (2..=STEPS - 6).contains(&received)
        });
        if let Some(m) = half_way.filter(|_| seen.len() >= 2) {
            let open = a.machine(m)["open_cycle"].as_i64().unwrap();
            a.child.kill().unwrap();
            break (m.to_string(), open);
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let killed_at = Instant::now();
    let status = a.child.wait().unwrap();
    assert_eq!(status.signal(), Some(9), "{status}");
    let b_followed = MACHINES
        .iter()
        .filter_map(|m| served(&b, m).map(|s| (m, s)))
        .collect::<Vec<_>>();
    assert!(!b_followed.is_empty(), "b served nothing of a's machines");
    for (m, (v, from)) in &b_followed {
        assert_eq!(
            seen.get(&(m.to_string(), *v)),
            Some(from),
            "b served {m} v{v} from the database as a did"
        );
    }

    // 3. b takes every machine over within the lease time (plus its own supervision tick).
    wait_for("b holds every machine", Duration::from_secs(30), || {
        all_held_by(&b, "b")
    });
    let takeover = killed_at.elapsed().as_secs_f64();
    println!("takeover {takeover:.2} s after the kill (lease {LEASE_S} s)");
    assert!(
        takeover <= LEASE_S * 1.2 + 1.0,
        "takeover took {takeover:.2} s with a {LEASE_S} s lease"
    );
    // The killed cycle is abandoned; b carries on to validate a cycle of its own.
    let (km, kc) = &killed_in;
    let last_a_version: BTreeMap<&str, u64> = MACHINES
        .iter()
        .map(|m| {
            let v = seen
                .keys()
                .filter(|(id, _)| id == m)
                .map(|(_, v)| *v)
                .max()
                .unwrap_or(0);
            (*m, v)
        })
        .collect();
    wait_for("b validates a cycle", Duration::from_secs(90), || {
        MACHINES.iter().any(|m| {
            b.cycles(m)
                .iter()
                .any(|c| c["status"] == "ok" && c["cycle"].as_i64() > Some(*kc))
        })
    });
    let killed_status = b
        .cycles(km)
        .into_iter()
        .find(|c| c["cycle"].as_i64() == Some(*kc))
        .map(|c| c["status"].clone());
    assert_eq!(killed_status, Some(Value::from("abandoned")));
    let pid = b.child.id().to_string();
    assert!(
        Command::new("kill")
            .args(["-TERM", &pid])
            .status()
            .unwrap()
            .success()
    );
    let status = b.wait_exit(Duration::from_secs(30));
    assert!(status.success(), "{status}\n{}", b.log_text());

    // 4. From the stored data.
    rt().block_on(async {
        let store = Store::connect(&url).await.unwrap();
        for m in MACHINES {
            let audit = store.lease_audit(m).await.unwrap();
            assert!(audit.problems().is_empty(), "{m}: {:?}", audit.problems());
            let holders: Vec<&str> = audit.terms.iter().map(|t| t.holder.as_str()).collect();
            assert_eq!(holders, ["a", "b"], "{m}");
            let (ta, tb) = (&audit.terms[0], &audit.terms[1]);
            // a was killed: its term ended by expiry, never released; b's by release.
            assert!(ta.released_ms.is_none() && tb.released_ms.is_some(), "{m}");
            println!(
                "{m}: a's term ended at {} ms, b's began {} ms later",
                ta.expires_ms,
                tb.acquired_ms - ta.expires_ms
            );
            // Every set a served is stored as served; b's versions come after a's.
            for ((id, v), from) in &seen {
                if id == m {
                    let set = audit.sets.iter().find(|s| s.0 == *v as i64);
                    assert_eq!(
                        set.map(|s| (s.1, s.2)),
                        Some((*from, Some(ta.term))),
                        "{m} v{v}"
                    );
                }
            }
            let b_sets: Vec<i64> = audit
                .sets
                .iter()
                .filter(|s| s.2 == Some(tb.term))
                .map(|s| s.0)
                .collect();
            assert!(
                b_sets.iter().all(|v| *v > last_a_version[m] as i64),
                "{m}: b wrote {b_sets:?} after a served v{}",
                last_a_version[m]
            );
            if m == km {
                let c = audit.cycles.iter().find(|c| c.0 == *kc).unwrap();
                assert_eq!((c.2.as_str(), c.3), ("abandoned", Some(ta.term)));
            }
        }
    });
    // The same audit from the command line.
    let out = Command::new(env!("CARGO_BIN_EXE_driftwatch"))
        .args(["fleet-audit", "--config"])
        .arg(dir.join("a.toml"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for m in MACHINES {
        assert!(text.contains(&format!("{m}: ")), "{text}");
    }
    assert_eq!(text.matches("term 1 'a'").count(), 3, "{text}");
    assert_eq!(text.matches("term 2 'b'").count(), 3, "{text}");
    assert!(text.ends_with("0 problems\n"), "{text}");
}
