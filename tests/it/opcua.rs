//! The `opcua` link against a real OPC UA server: the Python `asyncua` package
//! (`pip install asyncua`; CI installs it) running `tests/python/opcua_machine.py`, a simulated
//! machine that implements the node contract from docs/integrate-nc.md ("The node contract")
//! alone. driftwatch follows it, orders a cycle, reads the detections back, validates and
//! serves the result and writes it to the server; the server is then killed and started again
//! (with another spindle speed, so that updates after the restart are seen to arrive), and
//! driftwatch reconnects with nothing lost: the stored result still served, the set written
//! back to the new server, a second cycle completed.
//!
//! The service runs on a manual clock that the test keeps at the wall clock (the server stamps
//! its values with the wall clock, as a real NC does); every wait polls with a deadline.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use serde_json::Value;

use common::{TestService, launch_test, scratch};
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::recording::MachineStateKind;
use driftwatch_service::config::ServiceConfig;
use driftwatch_service::store::CycleStatus;
use driftwatch_sim::scenario::Scenario;
use driftwatch_sim::simulator::VirtualMachine;

const MACHINE: &str = "op1";
const SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/opcua_machine.py");

fn wall_ns() -> i64 {
    chrono::Utc::now().timestamp_nanos_opt().unwrap()
}

/// The server process, killed when dropped (a failing test leaves none behind).
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn asyncua_available() -> Result<(), String> {
    let out = Command::new("python3")
        .args(["-c", "import asyncua"])
        .output()
        .map_err(|e| format!("python3 cannot be run: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(String::from_utf8_lossy(&out.stderr).into_owned())
    }
}

fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().port()
}

struct Rig {
    dir: PathBuf,
    port: u16,
    detections: PathBuf,
    report: PathBuf,
}

impl Rig {
    /// The plan's readings from the truth simulator (the patent scenario's machine, 30 min into
    /// a warm-up at 20 000 min^-1), one per step label, for the server to play back.
    fn new(name: &str) -> Rig {
        // The link's and the client's log, with RUST_LOG (e.g. RUST_LOG=info), for a failure.
        // The subscriber is the process's: once installed it also takes the logs of the other
        // modules' services that run at the same time (only printed for a failing test).
        let _ = tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
            .with_test_writer()
            .try_init();
        if let Err(e) = asyncua_available() {
            panic!("this test needs Python 3 with the asyncua package (pip install asyncua): {e}");
        }
        let dir = scratch(name);
        let scn = Scenario::load("patent").unwrap();
        let k = Kinematics::load(&scn.machine).unwrap();
        let plan = Plan::build(&k, &PlanConfig::load("patent").unwrap()).unwrap();
        let mut vm = VirtualMachine::new(&k, &scn).unwrap();
        let start = vm.start_ns() + 30 * common::MIN;
        let rpm = plan.config.spindle_rpm;
        let readings: Vec<Value> = plan
            .steps
            .iter()
            .map(|step| {
                vm.advance_to(start + (step.t_start_s * 1e9) as i64, rpm);
                serde_json::to_value(vm.probe(&k, step, 0, rpm).msg).unwrap()
            })
            .collect();
        let detections = dir.join("detections.json");
        std::fs::write(&detections, serde_json::to_vec(&readings).unwrap()).unwrap();
        Rig {
            report: dir.join("report.json"),
            port: free_port(),
            dir,
            detections,
        }
    }

    fn start(&self, rpm: f64, security: &str) -> Server {
        let _ = std::fs::remove_file(&self.report);
        let child = Command::new("python3")
            .arg(SCRIPT)
            .args(["--port", &self.port.to_string()])
            .args(["--rpm", &rpm.to_string()])
            .arg("--detections")
            .arg(&self.detections)
            .arg("--report")
            .arg(&self.report)
            .arg("--workdir")
            .arg(&self.dir)
            .args(["--security", security])
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("python3 starts");
        Server(child)
    }

    /// What the server last reported (none before its first report).
    fn report(&self) -> Option<Value> {
        let text = std::fs::read_to_string(&self.report).ok()?;
        serde_json::from_str(&text).ok()
    }

    fn config(&self, extra: &str) -> ServiceConfig {
        let mut cfg = common::config(&self.dir.join("data"));
        cfg.time_scale = 1.0;
        let m = &mut cfg.machines[0];
        m.id = MACHINE.into();
        m.machine = "table_bc".into();
        m.plan = Some("patent".into());
        // The node ids the server uses for spindle, state, request and detections are the
        // link's defaults; temperatures and compensation are the plant's own.
        let link = format!(
            r#"
            kind = "opcua"
            endpoint = "opc.tcp://127.0.0.1:{port}/driftwatch/"
            reconnect_first_s = 0.2
            reconnect_max_s = 2.0
            {extra}
            [nodes.temperatures]
            spindle_housing = "ns=2;s=Monitoring/Temperature/SpindleHousing"
            ambient = "ns=2;s=Monitoring/Temperature/Ambient"
            [nodes.compensation]
            C_pivot_x_um = "ns=2;s=Driftwatch/Compensation/C_pivot_x_um"
            C_tilt_b_urad = "ns=2;s=Driftwatch/Compensation/C_tilt_b_urad"
            version = "ns=2;s=Driftwatch/Compensation/version"
            "#,
            port = self.port
        );
        m.link = toml::from_str(&link).unwrap();
        cfg
    }
}

/// Keep the service clock at the wall clock, and poll `what` until it gives a value or the
/// deadline passes.
async fn wait_for<T, F, Fut>(app: &TestService, secs: u64, what: &str, mut f: F) -> T
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Option<T>>,
{
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        app.run_to(wall_ns()).await;
        if let Some(v) = f().await {
            return v;
        }
        assert!(
            Instant::now() < deadline,
            "waited {secs} s for {what}: {:?}",
            app.svc.views[MACHINE].lock().unwrap().phase
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

async fn send(app: &TestService, method: &str, uri: &str) -> (StatusCode, Value) {
    let req = Request::builder()
        .method(method)
        .uri(uri)
        .header(header::AUTHORIZATION, "Bearer write-token")
        .body(Body::empty())
        .unwrap();
    let (s, _, v) = app.call(req).await;
    (s, v)
}

/// The spindle speed and NC state the loop last took from the link.
fn seen(app: &TestService) -> Option<(f64, MachineStateKind)> {
    let v = app.svc.views[MACHINE].lock().unwrap();
    v.phase.as_ref().map(|p| (p.spindle_rpm, p.state))
}

/// Ask for a cycle and wait until the store holds one numbered above `after` with status ok
/// (the scheduler may order cycles of its own besides: a machine warming up is measured); its
/// number. A cycle after `after` closed otherwise fails the test, with its reason.
async fn cycle_after(app: &TestService, after: i64) -> i64 {
    let (s, body) = send(app, "POST", &format!("/api/v1/machines/{MACHINE}/cycles")).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{body}");
    wait_for(app, 60, "a validated cycle", || async {
        let rows = app.store().cycles(MACHINE, 100, None).await.unwrap();
        let newer: Vec<_> = rows.iter().filter(|c| c.cycle > after).collect();
        for c in &newer {
            assert!(
                matches!(c.status, CycleStatus::Open | CycleStatus::Ok),
                "cycle {} {:?}: {:?}; all: {rows:?}",
                c.cycle,
                c.status,
                c.reason
            );
        }
        newer
            .iter()
            .filter(|c| c.status == CycleStatus::Ok)
            .map(|c| c.cycle)
            .min()
    })
    .await
}

/// The cycles the store holds with status ok.
async fn ok_cycles(app: &TestService) -> Vec<i64> {
    let rows = app.store().cycles(MACHINE, 100, None).await.unwrap();
    let mut ok: Vec<i64> = rows
        .iter()
        .filter(|c| c.status == CycleStatus::Ok)
        .map(|c| c.cycle)
        .collect();
    ok.sort_unstable();
    ok
}

/// Whether the server's report lists `cycle` among those it ran.
fn server_ran(rig: &Rig, cycle: i64) -> bool {
    rig.report().is_some_and(|r| {
        r["cycles_run"]
            .as_array()
            .is_some_and(|a| a.iter().any(|c| c.as_i64() == Some(cycle)))
    })
}

/// The served set's version and its C_pivot_x_um.
async fn served(app: &TestService) -> (u64, f64) {
    let (s, comp) = send(
        app,
        "GET",
        &format!("/api/v1/machines/{MACHINE}/compensation"),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{comp}");
    let version = comp["version"].as_u64().unwrap();
    let x = comp["offsets"]["C_pivot_x_um"]
        .as_f64()
        .unwrap_or_else(|| panic!("{comp}"));
    (version, x)
}

/// Wait until the server holds the set served now (its version and C_pivot_x_um; the
/// scheduler may serve a newer one meanwhile); that set.
async fn written_to_server(app: &TestService, rig: &Rig) -> (u64, f64) {
    wait_for(app, 30, "the served set written to the server", || async {
        let want = served(app).await;
        let r = rig.report()?;
        let version = r["version"].as_u64()?;
        let x = r["compensation"]["C_pivot_x_um"].as_f64()?;
        (version == want.0 && (x - want.1).abs() < 1e-9).then_some(want)
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_opcua_link_follows_a_real_server_orders_cycles_and_survives_its_restart() {
    let rig = Rig::new("opcua-link");
    let server = rig.start(20000.0, "none");
    let app = launch_test(rig.config(""), Some(wall_ns())).await;

    // The link follows the machine: its spindle speed and program state arrive.
    wait_for(&app, 60, "the server's spindle speed and state", || async {
        seen(&app).filter(|(rpm, state)| *rpm == 20000.0 && *state == MachineStateKind::Idle)
    })
    .await;

    // A cycle ordered through the node contract: run by the server, read back, validated,
    // stored, served, and written to the server's compensation nodes.
    let first = cycle_after(&app, 0).await;
    assert!(server_ran(&rig, first), "{:?}", rig.report());
    let set = written_to_server(&app, &rig).await;
    assert!(set.0 >= 1);

    // Another cycle, and the server dies in the middle of it (killed: no goodbye to its
    // clients), a few approaches read: eight approaches of 0.15 s are done on the server,
    // at least the first few of them published to the link (every 0.25 s).
    wait_for(&app, 60, "no cycle open", || async {
        let open = app.store().open_cycles(MACHINE).await.unwrap();
        open.is_empty().then_some(())
    })
    .await;
    let (s, body) = send(&app, "POST", &format!("/api/v1/machines/{MACHINE}/cycles")).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{body}");
    let cut = wait_for(&app, 60, "a cycle under way on the server", || async {
        let r = rig.report()?;
        let running = &r["running"];
        (running["done"].as_u64()? >= 8).then(|| running["cycle"].as_i64())?
    })
    .await;
    drop(server);
    let ok_before = ok_cycles(&app).await;

    // It comes back with another spindle speed: the link reconnects and follows it again.
    let _server = rig.start(15000.0, "none");
    wait_for(&app, 60, "updates from the restarted server", || async {
        seen(&app).filter(|(rpm, state)| *rpm == 15000.0 && *state == MachineStateKind::Idle)
    })
    .await;
    // The interrupted cycle is closed honestly: the restarted NC reports its program ended, so
    // the cycle closes with the detections read before the kill (kept) and is rejected naming
    // what is missing; it is not run again.
    let interrupted = wait_for(&app, 60, "the interrupted cycle closed", || async {
        let c = app.store().cycle(MACHINE, cut).await.unwrap()?;
        (c.status != CycleStatus::Open).then_some(c)
    })
    .await;
    assert_eq!(interrupted.status, CycleStatus::Rejected, "{interrupted:?}");
    assert!(
        interrupted
            .reason
            .as_deref()
            .is_some_and(|r| r.contains("missing measurements")),
        "{interrupted:?}"
    );
    let kept = app.store().detections(MACHINE, cut).await.unwrap().len();
    assert!(
        (3..24).contains(&kept),
        "{kept} detections of cycle {cut} stored"
    );
    assert!(
        !server_ran(&rig, cut),
        "the restarted server ran cycle {cut} again"
    );
    // Nothing lost: every validated result still stored, the served set not gone back, and
    // written again to the restarted server, which had forgotten it.
    let ok_after = ok_cycles(&app).await;
    assert!(
        ok_before.iter().all(|c| ok_after.contains(c)),
        "{ok_before:?} {ok_after:?}"
    );
    let now = written_to_server(&app, &rig).await;
    assert!(now.0 >= set.0);

    // A cycle after the restart completes, run by the new server, and moves the served set on.
    let second = cycle_after(&app, cut).await;
    assert!(server_ran(&rig, second), "{:?}", rig.report());
    let set2 = written_to_server(&app, &rig).await;
    assert!(set2.0 > now.0, "{set2:?} after {now:?}");
    app.stop().await;
}

/// The same link over a secure channel: Basic256Sha256 with signing and encryption, the
/// client's certificate made in its pki directory at first start, the server's trusted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_opcua_link_runs_a_cycle_over_sign_and_encrypt() {
    let rig = Rig::new("opcua-secure");
    let _server = rig.start(20000.0, "sign_and_encrypt");
    let pki = rig.dir.join("pki");
    let security = format!(
        "security = {{ mode = \"sign_and_encrypt\", policy = \"Basic256Sha256\", trust_server = true, pki_dir = {:?} }}",
        pki.display().to_string()
    );
    let app = launch_test(rig.config(&security), Some(wall_ns())).await;
    wait_for(
        &app,
        60,
        "the server's spindle speed over a secure channel",
        || async { seen(&app).filter(|(rpm, _)| *rpm == 20000.0) },
    )
    .await;
    let n = cycle_after(&app, 0).await;
    assert!(server_ran(&rig, n));
    written_to_server(&app, &rig).await;
    assert!(
        has_file(&pki.join("own")),
        "the client made its certificate in the pki directory"
    );
    app.stop().await;
}

fn has_file(dir: &Path) -> bool {
    std::fs::read_dir(dir).is_ok_and(|mut d| d.next().is_some())
}
