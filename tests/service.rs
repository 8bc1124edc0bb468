//! The service as `driftwatch serve` starts it: through `launch`, on a listener bound to port 0
//! that the test keeps, with a manual clock that the test moves (hours of a plant day in
//! seconds, nothing sleeps on the wall clock to pass).

use std::path::PathBuf;
use std::time::Duration;

use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_util::sync::CancellationToken;

use driftwatch_core::units::NS_PER_MIN;
use driftwatch_service::config::ServiceConfig;
use driftwatch_service::launch::{ClockKind, LaunchOptions, Service, launch_with};
use driftwatch_service::store::Store;

fn scratch(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("service-{name}"));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The shipped default with its simulated machine twice (sim-1, sim-2), on one store in `dir`.
fn two_machines(dir: &std::path::Path) -> ServiceConfig {
    let mut cfg = ServiceConfig::load(None).unwrap();
    cfg.data_dir = dir.to_path_buf();
    let mut second = cfg.machines[0].clone();
    assert_eq!(cfg.machines[0].id, "sim-1");
    second.id = "sim-2".into();
    cfg.machines.push(second);
    cfg
}

async fn start(cfg: ServiceConfig) -> Service {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let opts = LaunchOptions {
        clock: ClockKind::Manual,
        until_min: None,
    };
    launch_with(cfg, listener, CancellationToken::new(), opts)
        .await
        .unwrap()
}

/// One GET on a fresh connection: status and body.
async fn get(addr: std::net::SocketAddr, path: &str) -> (u16, String) {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!("GET {path} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n");
    s.write_all(req.as_bytes()).await.unwrap();
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).await.unwrap();
    let text = String::from_utf8_lossy(&buf).to_string();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text
        .split_once("\r\n\r\n")
        .map_or("", |(_, b)| b)
        .to_string();
    (status, body)
}

/// Move the clock to `t_ns` and wait (bounded) until every machine in `moving` has stepped to
/// it.
async fn advance(svc: &Service, t_ns: i64, moving: &[&str]) {
    svc.manual_clock.as_ref().unwrap().set(t_ns);
    let reached = async {
        loop {
            let done = moving.iter().all(|id| {
                svc.views[*id]
                    .lock()
                    .unwrap()
                    .clock_ns
                    .is_some_and(|t| t >= t_ns)
            });
            if done {
                return;
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    };
    tokio::time::timeout(Duration::from_secs(60), reached)
        .await
        .unwrap_or_else(|_| panic!("the machines {moving:?} did not reach the clock's time"));
}

/// Make every write of `machine` to the samples and cycles tables fail, as a full disk or a
/// read-only file would, through the real SQLite: triggers that abort the insert.
async fn refuse_writes_of(db: &std::path::Path, machine: &str, refuse: bool) {
    let url = format!("sqlite://{}", db.display());
    let pool = sqlx::SqlitePool::connect(&url).await.unwrap();
    for table in ["spindle_samples", "temperature_samples", "cycles"] {
        let name = format!("refuse_{table}");
        let sql = if refuse {
            format!(
                "CREATE TRIGGER {name} BEFORE INSERT ON {table} WHEN NEW.machine_id = '{machine}' \
                 BEGIN SELECT RAISE(ABORT, 'injected fault: {machine} may not write'); END"
            )
        } else {
            format!("DROP TRIGGER {name}")
        };
        // The names are the test's own constants: nothing from outside.
        sqlx::query(sqlx::AssertSqlSafe(sql))
            .execute(&pool)
            .await
            .unwrap();
    }
    pool.close().await;
}

fn view_of(svc: &Service, id: &str) -> driftwatch_service::daemon::MachineView {
    svc.views[id].lock().unwrap().clone()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_machine_whose_store_fails_stops_neither_the_others_nor_the_api() {
    let dir = scratch("store-fault");
    let db = dir.join("driftwatch.db");
    // The schema first, then the fault: sim-2's samples and cycles may not be written.
    Store::open(&db).await.unwrap().close().await;
    refuse_writes_of(&db, "sim-2", true).await;

    let svc = start(two_machines(&dir)).await;
    let t0 = svc.t0_ns;
    // Six hours of the plant day, ten minutes at a time; only sim-1 must keep up.
    for k in 1..=36 {
        advance(&svc, t0 + k * 10 * NS_PER_MIN, &["sim-1"]).await;
        // The API answers throughout.
        let (code, body) = get(svc.addr, "/api/v1/machines").await;
        assert_eq!(code, 200, "{body}");
    }
    let one = view_of(&svc, "sim-1");
    let two = view_of(&svc, "sim-2");
    assert!(
        one.cycles_ok >= 5,
        "sim-1 keeps cycling: {} validated cycles",
        one.cycles_ok
    );
    assert!(one.compensation.is_some(), "sim-1 serves a set");
    assert_eq!(one.faults, 0, "sim-1 has no fault: {:?}", one.fault);
    assert!(two.faults > 0, "sim-2's failed writes are counted");
    assert!(
        two.fault
            .as_deref()
            .is_some_and(|f| f.contains("injected fault")),
        "sim-2 says why: {:?}",
        two.fault
    );
    assert_eq!(two.cycles_ok, 0, "sim-2 could not store a cycle");

    // /metrics counts the faults by machine.
    let (code, metrics) = get(svc.addr, "/metrics").await;
    assert_eq!(code, 200);
    let faults = |id: &str| -> f64 {
        let key = format!("driftwatch_machine_faults_total{{machine=\"{id}\"}} ");
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(&key)?.parse().ok())
            .unwrap_or_else(|| panic!("no {key} in /metrics:\n{metrics}"))
    };
    assert_eq!(faults("sim-1"), 0.0);
    assert!(faults("sim-2") >= 1.0);
    // The machine's own page answers too, with the fault.
    let (code, body) = get(svc.addr, "/api/v1/machines/sim-2").await;
    assert_eq!(code, 200, "{body}");
    let v: Value = serde_json::from_str(&body).unwrap();
    assert!(v.to_string().contains("injected fault"), "{v}");

    // The store heals: sim-2 catches up by itself (its retries), and keeps going.
    refuse_writes_of(&db, "sim-2", false).await;
    let t_heal = t0 + 36 * 10 * NS_PER_MIN;
    for k in 1..=18 {
        advance(&svc, t_heal + k * 10 * NS_PER_MIN, &["sim-1", "sim-2"]).await;
    }
    let two = view_of(&svc, "sim-2");
    assert!(two.fault.is_none(), "the fault clears: {:?}", two.fault);
    assert!(
        two.cycles_ok >= 1,
        "sim-2 cycles again after the store heals"
    );

    // A graceful stop: the loops close their recordings and the server its connections.
    svc.stop();
    tokio::time::timeout(Duration::from_secs(60), svc.wait())
        .await
        .expect("the service stops");
    let store = Store::open(&db).await.unwrap();
    assert!(store.open_cycles("sim-1").await.unwrap().is_empty());
    store.close().await;
}
