//! The `mtconnect` link against an agent served over HTTP by the test: documents in the
//! MTConnect standard's own layout (MTConnectStreams 1.3 with a Header holding instanceId,
//! firstSequence, nextSequence and lastSequence; DeviceStream, ComponentStream, Samples and
//! Events; MTConnectError OUT_OF_RANGE for a `from` that left the buffer, as cppagent answers).
//! The agent can restart with a new instanceId and overrun its small buffer while the link
//! cannot reach it, to make a gap. No PyPI or Debian package of a real agent that follows the
//! standard's sequence protocol could be installed (see docs/integrate-nc.md, "The MTConnect
//! link").
//!
//! The network is real (loopback), so the test polls for a condition with a timeout; nothing
//! waits a fixed time to pass.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use tokio_util::sync::CancellationToken;

use driftwatch_core::kinematics::Limits;
use driftwatch_core::recording::MachineStateKind;
use driftwatch_service::config::{LinkConfig, ServiceConfig};
use driftwatch_service::launch::{ClockKind, LaunchOptions, launch_with};
use driftwatch_service::link::{LinkError, LinkEvent, MachineLink};
use driftwatch_service::mtconnect::Items;
use driftwatch_service::mtconnect_link::{MtconnectLink, MtconnectSettings};
use driftwatch_service::nc_push::ClockTolerance;

const DEVICE: &str = "VMC-1";
/// 2026-03-02T06:00:00Z, the agent's first time.
const T0: i64 = 1_772_431_200_000_000_000;

struct Obs {
    seq: u64,
    item: &'static str,
    t_ns: i64,
    value: String,
}

/// A small MTConnect agent: a ring buffer of observations with the standard's sequence
/// numbers, `current` and `sample` for one device.
struct Agent {
    instance: u64,
    next: u64,
    capacity: usize,
    buffer: Vec<Obs>,
    /// Answer 503 to everything (the agent cannot be reached).
    down: bool,
    requests: u64,
}

fn element(item: &str) -> (&'static str, &'static str) {
    match item {
        "S1speed" => ("Samples", "RotaryVelocity"),
        "T1" | "Tamb" => ("Samples", "Temperature"),
        "exec" => ("Events", "Execution"),
        _ => ("Events", "ControllerMode"),
    }
}

impl Agent {
    fn new(instance: u64, capacity: usize) -> Self {
        Agent {
            instance,
            next: 1,
            capacity,
            buffer: Vec::new(),
            down: false,
            requests: 0,
        }
    }

    fn push(&mut self, item: &'static str, t_ns: i64, value: &str) {
        self.buffer.push(Obs {
            seq: self.next,
            item,
            t_ns,
            value: value.to_string(),
        });
        self.next += 1;
        if self.buffer.len() > self.capacity {
            self.buffer.remove(0);
        }
    }

    fn first(&self) -> u64 {
        self.buffer.first().map_or(self.next, |o| o.seq)
    }

    /// A restart: another instance, numbering from 1. It announces every item UNAVAILABLE,
    /// then the values its adapter held, at their own (old) times, as an adapter that replays
    /// its last observations on reconnecting does.
    fn restart(&mut self, instance: u64, at_ns: i64) {
        let last: Vec<(&'static str, i64, String)> = ["S1speed", "exec", "mode", "T1"]
            .iter()
            .filter_map(|i| {
                self.buffer
                    .iter()
                    .rev()
                    .find(|o| o.item == *i)
                    .map(|o| (o.item, o.t_ns, o.value.clone()))
            })
            .collect();
        self.instance = instance;
        self.next = 1;
        self.buffer.clear();
        for (item, _, _) in &last {
            self.push(item, at_ns, "UNAVAILABLE");
        }
        for (item, t, v) in last {
            self.push(item, t, &v);
        }
    }

    fn header(&self) -> String {
        format!(
            r#"<Header creationTime="2026-03-02T06:00:00Z" sender="test-agent" instanceId="{}" version="1.3.0.18" bufferSize="{}" nextSequence="{}" firstSequence="{}" lastSequence="{}"/>"#,
            self.instance,
            self.capacity,
            self.next,
            self.first(),
            self.next - 1
        )
    }

    fn streams(&self, header: String, obs: &[&Obs]) -> String {
        let mut samples = String::new();
        let mut events = String::new();
        for o in obs {
            let (group, name) = element(o.item);
            let ts = chrono::DateTime::from_timestamp_nanos(o.t_ns)
                .format("%Y-%m-%dT%H:%M:%S%.6fZ")
                .to_string();
            let xml = format!(
                r#"<{name} dataItemId="{}" timestamp="{ts}" sequence="{}">{}</{name}>"#,
                o.item, o.seq, o.value
            );
            if group == "Samples" {
                samples.push_str(&xml);
            } else {
                events.push_str(&xml);
            }
        }
        format!(
            r#"<?xml version="1.0" encoding="UTF-8"?>
<MTConnectStreams xmlns:m="urn:mtconnect.org:MTConnectStreams:1.3" xmlns="urn:mtconnect.org:MTConnectStreams:1.3" xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance">
  {header}
  <Streams>
    <DeviceStream name="{DEVICE}" uuid="vmc-1">
      <ComponentStream component="Rotary" name="C" componentId="c1"><Samples>{samples}</Samples></ComponentStream>
      <ComponentStream component="Controller" name="controller" componentId="cn1"><Events>{events}</Events></ComponentStream>
    </DeviceStream>
  </Streams>
</MTConnectStreams>"#
        )
    }

    fn current(&self) -> String {
        let mut latest: Vec<&Obs> = Vec::new();
        for o in &self.buffer {
            latest.retain(|l| l.item != o.item);
            latest.push(o);
        }
        self.streams(self.header(), &latest)
    }

    fn error(&self, code: &str, text: &str) -> String {
        format!(
            r#"<?xml version="1.0" encoding="UTF-8"?><MTConnectError xmlns="urn:mtconnect.org:MTConnectError:1.3"><Header creationTime="2026-03-02T06:00:00Z" sender="test-agent" instanceId="{}" version="1.3.0.18" bufferSize="{}"/><Errors><Error errorCode="{code}">{text}</Error></Errors></MTConnectError>"#,
            self.instance, self.capacity
        )
    }

    fn sample(&self, from: u64, count: u64) -> Result<String, String> {
        if from < self.first() || from > self.next {
            return Err(self.error(
                "OUT_OF_RANGE",
                &format!(
                    "'from' must be greater than or equal to {} and less than or equal to {}",
                    self.first(),
                    self.next
                ),
            ));
        }
        let end = (from + count).min(self.next);
        let obs: Vec<&Obs> = self
            .buffer
            .iter()
            .filter(|o| o.seq >= from && o.seq < end)
            .collect();
        let header = self.header().replace(
            &format!(r#"nextSequence="{}""#, self.next),
            &format!(r#"nextSequence="{end}""#),
        );
        Ok(self.streams(header, &obs))
    }
}

type Shared = Arc<Mutex<Agent>>;

fn xml(status: StatusCode, body: String) -> Response {
    (status, [("content-type", "text/xml")], body).into_response()
}

async fn answer(
    State(a): State<Shared>,
    Path((device, what)): Path<(String, String)>,
    Query(q): Query<std::collections::HashMap<String, String>>,
) -> Response {
    let mut a = a.lock().unwrap();
    a.requests += 1;
    if a.down {
        return (StatusCode::SERVICE_UNAVAILABLE, "down").into_response();
    }
    if device != DEVICE {
        let e = a.error("NO_DEVICE", &format!("no device {device}"));
        return xml(StatusCode::NOT_FOUND, e);
    }
    match what.as_str() {
        "current" => xml(StatusCode::OK, a.current()),
        "sample" => {
            let from = q
                .get("from")
                .and_then(|f| f.parse().ok())
                .unwrap_or(a.first());
            let count = q.get("count").and_then(|c| c.parse().ok()).unwrap_or(100);
            match a.sample(from, count) {
                Ok(body) => xml(StatusCode::OK, body),
                Err(body) => xml(StatusCode::BAD_REQUEST, body),
            }
        }
        _ => xml(
            StatusCode::BAD_REQUEST,
            a.error("UNSUPPORTED", "not a request"),
        ),
    }
}

async fn serve_agent(agent: Agent) -> (String, Shared) {
    let a = Arc::new(Mutex::new(agent));
    let app = Router::new()
        .route("/{device}/{what}", get(answer))
        .with_state(a.clone());
    let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", l.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(l, app).await });
    (url, a)
}

fn items() -> Items {
    Items {
        spindle_speed: "S1speed".into(),
        execution: "exec".into(),
        controller_mode: Some("mode".into()),
        temperatures: [("spindle_head".to_string(), "T1".to_string())].into(),
    }
}

const S: i64 = 1_000_000_000;

/// Poll the link (with the service clock at `now`) until `done` holds for what it gave, or
/// 20 s pass.
async fn poll_until(
    link: &mut MtconnectLink,
    got: &mut Vec<LinkEvent>,
    now: i64,
    done: impl Fn(&[LinkEvent]) -> bool,
) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while !done(got) {
        assert!(
            tokio::time::Instant::now() < deadline,
            "timed out; got {got:#?}; status {:?}",
            link.status()
        );
        got.extend(link.poll(now));
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

fn has_rpm(ev: &[LinkEvent], rpm: f64) -> bool {
    ev.iter()
        .any(|e| matches!(e, LinkEvent::Spindle(s) if s.msg.rpm == rpm))
}

fn has_celsius(ev: &[LinkEvent], c: f64) -> bool {
    ev.iter()
        .any(|e| matches!(e, LinkEvent::Temperature(t) if t.msg.celsius == c && t.msg.sensor == "spindle_head"))
}

#[tokio::test]
async fn the_link_follows_an_agent_through_a_restart_and_a_gap() {
    let mut agent = Agent::new(1001, 8);
    agent.push("exec", T0, "READY");
    agent.push("mode", T0, "AUTOMATIC");
    agent.push("S1speed", T0, "0");
    agent.push("T1", T0, "21.0");
    let (url, agent) = serve_agent(agent).await;
    let settings = MtconnectSettings {
        agent: url,
        device: Some(DEVICE.into()),
        items: items(),
        poll: Duration::from_millis(20),
        // Small pages: the link reads a burst in several requests.
        count: 3,
        tolerance: ClockTolerance::default(),
    };
    let mut link = MtconnectLink::start("vmc-1", settings, Limits::default()).unwrap();
    let now = T0 + 3600 * S;
    let mut got = Vec::new();

    // The state in force, from `current`.
    poll_until(&mut link, &mut got, now, |ev| {
        has_rpm(ev, 0.0) && has_celsius(ev, 21.0)
    })
    .await;
    assert!(got.iter().any(
        |e| matches!(e, LinkEvent::State(s) if s.msg.state == MachineStateKind::Idle && s.t_ns == T0)
    ));
    // MTConnect takes no orders: the link says so.
    assert_eq!(
        link.request_cycle(1, now),
        Err(LinkError::ObserveOnly("mtconnect"))
    );

    // The stream: a program starts, the spindle runs up, the head warms; more than a page.
    {
        let mut a = agent.lock().unwrap();
        a.push("exec", T0 + 60 * S, "ACTIVE");
        a.push("S1speed", T0 + 61 * S, "12000");
        a.push("T1", T0 + 62 * S, "22.5");
        a.push("S1speed", T0 + 63 * S, "15000");
        a.push("T1", T0 + 64 * S, "23.5");
        // Beyond the machine's limits: logged, not taken.
        a.push("T1", T0 + 65 * S, "250.0");
    }
    poll_until(&mut link, &mut got, now, |ev| has_celsius(ev, 23.5)).await;
    assert!(has_rpm(&got, 12000.0) && has_rpm(&got, 15000.0));
    assert!(got.iter().any(
        |e| matches!(e, LinkEvent::State(s) if s.msg.state == MachineStateKind::Cutting && s.t_ns == T0 + 60 * S)
    ));

    // The agent restarts: a new instance that replays the last values at their own times,
    // then goes on.
    {
        let mut a = agent.lock().unwrap();
        a.restart(2002, T0 + 100 * S);
        a.push("S1speed", T0 + 101 * S, "8000");
        a.push("exec", T0 + 102 * S, "READY");
    }
    poll_until(&mut link, &mut got, now, |ev| has_rpm(ev, 8000.0)).await;
    poll_until(&mut link, &mut got, now, |ev| {
        ev.iter().any(|e| {
            matches!(e, LinkEvent::State(s) if s.msg.state == MachineStateKind::Idle && s.t_ns == T0 + 102 * S)
        })
    })
    .await;
    let st = link.status();
    assert_eq!(st.stats.restarts, 1, "{st:?}");
    assert_eq!(st.instance.as_deref(), Some("2002"));
    assert_eq!(st.stats.lost_observations, 0);

    // The agent cannot be reached while 20 observations pass through its 8-deep buffer: the
    // link finds its `from` gone, measures the gap, resumes at the first sequence kept.
    let (next_before, expected_lost) = {
        let mut a = agent.lock().unwrap();
        a.down = true;
        let next_before = a.next;
        for i in 0..20 {
            a.push("T1", T0 + (200 + i) * S, &format!("{}.0", 30 + i));
        }
        let lost = a.first() - next_before;
        a.down = false;
        (next_before, lost)
    };
    assert_eq!(expected_lost, 12, "from {next_before}");
    poll_until(&mut link, &mut got, now, |ev| has_celsius(ev, 49.0)).await;
    let st = link.status();
    assert_eq!(st.stats.gaps, 1, "{st:?}");
    assert_eq!(st.stats.lost_observations, expected_lost);
    // What the buffer kept is all there: 42.0 to 49.0; what it lost is not.
    for c in 42..50 {
        assert!(has_celsius(&got, c as f64), "{c}");
    }
    assert!(!has_celsius(&got, 41.0));

    // No observation was taken twice: each (topic, time) once, the replay after the restart
    // included; nothing beyond the limits.
    let mut keys: Vec<(u8, i64)> = got
        .iter()
        .map(|e| {
            let topic = match e {
                LinkEvent::Spindle(_) => 0,
                LinkEvent::State(_) => 1,
                LinkEvent::Temperature(_) => 2,
                other => panic!("unexpected {other:?}"),
            };
            (topic, e.t_ns())
        })
        .collect();
    let n = keys.len();
    keys.sort_unstable();
    keys.dedup();
    assert_eq!(keys.len(), n, "{got:#?}");
    assert!(!has_celsius(&got, 250.0));
    let temps = got
        .iter()
        .filter(|e| matches!(e, LinkEvent::Temperature(_)))
        .count();
    assert_eq!(temps, 3 + 8, "21.0, 22.5, 23.5 and the 8 the buffer kept");
}

#[tokio::test]
async fn events_far_from_the_service_clock_are_refused() {
    let mut agent = Agent::new(7, 16);
    agent.push("exec", T0, "READY");
    agent.push("S1speed", T0, "0");
    let (url, _agent) = serve_agent(agent).await;
    let settings = MtconnectSettings {
        agent: url,
        device: Some(DEVICE.into()),
        items: items(),
        poll: Duration::from_millis(20),
        count: 100,
        tolerance: ClockTolerance::default(),
    };
    let mut link = MtconnectLink::start("vmc-1", settings, Limits::default()).unwrap();
    // The service clock two days after the agent's stamps (beyond the 24 h allowed).
    let mut got = Vec::new();
    poll_until(&mut link, &mut got, T0 + 48 * 3600 * S, |ev| {
        ev.iter()
            .any(|e| matches!(e, LinkEvent::ClockSkew { refused: 2, .. }))
    })
    .await;
    assert!(got.iter().all(|e| matches!(e, LinkEvent::ClockSkew { .. })));
    assert_eq!(link.status().refused_clock_skew, 2);
}

fn mtconnect_config(dir: &std::path::Path, agent: &str) -> ServiceConfig {
    let text = driftwatch_service::config::DEFAULT_CONFIG
        .replace("time_scale = 60.0", "time_scale = 1.0")
        .replace(
            r#"link = { kind = "simulated", scenario = "two_shift" }"#,
            &format!(
                r#"link = {{ kind = "mtconnect", agent = "{agent}", device = "{DEVICE}", poll_ms = 50, items = {{ spindle_speed = "S1speed", execution = "exec", controller_mode = "mode", temperatures = {{ ambient = "T1" }} }} }}"#
            ),
        );
    let mut cfg = ServiceConfig::from_toml(&text, "test").unwrap();
    cfg.data_dir = dir.to_path_buf();
    cfg.http.tokens.clear();
    cfg
}

#[tokio::test]
async fn the_service_runs_a_machine_on_an_mtconnect_link() {
    let mut agent = Agent::new(5, 64);
    agent.push("exec", T0, "READY");
    agent.push("mode", T0, "AUTOMATIC");
    agent.push("S1speed", T0, "0");
    agent.push("T1", T0, "20.0");
    let (url, agent) = serve_agent(agent).await;
    let dir = std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("mtconnect-launch");
    let _ = std::fs::remove_dir_all(&dir);
    let cfg = mtconnect_config(&dir, &url);
    assert!(matches!(cfg.machines[0].link, LinkConfig::Mtconnect { .. }));
    // A real machine on a sped-up clock is refused, naming the link.
    let mut fast = cfg.clone();
    fast.time_scale = 60.0;
    let e = fast.validate("t").unwrap_err().to_string();
    assert!(e.contains("mtconnect"), "{e}");

    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let opts = LaunchOptions {
        clock: ClockKind::Manual,
        start_ns: Some(T0),
        ..Default::default()
    };
    let stop = CancellationToken::new();
    let mut svc = launch_with(cfg, listener, stop.clone(), opts)
        .await
        .unwrap();
    let clock = svc.manual_clock.take().unwrap();
    let view = svc.views["sim-1"].clone();
    {
        let mut a = agent.lock().unwrap();
        a.push("exec", T0 + 60 * S, "ACTIVE");
        a.push("S1speed", T0 + 61 * S, "18000");
    }
    // The machine's view follows the agent as the clock passes the agent's times.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    let mut t = T0;
    loop {
        let phase = view.lock().unwrap().phase;
        if let Some(p) = phase
            && p.spindle_rpm == 18000.0
            && p.state == MachineStateKind::Cutting
            && p.state_reported
        {
            break;
        }
        assert!(tokio::time::Instant::now() < deadline, "{phase:?}");
        t = (t + 5 * S).min(T0 + 120 * S);
        clock.set(t);
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // The program ends; the spindle stops: idle, and a cycle is due after the stop, which
    // the link cannot order: the schedule says why. (The agent stamps what happens now: the
    // clock is there first, since stamps more than max_ahead_s ahead are refused.)
    t = T0 + 600 * S;
    clock.set(t);
    {
        let mut a = agent.lock().unwrap();
        a.push("S1speed", T0 + 600 * S, "0");
        a.push("exec", T0 + 601 * S, "PROGRAM_COMPLETED");
    }
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let (schedule, state) = {
            let v = view.lock().unwrap();
            (v.cycles.schedule.clone(), v.phase.as_ref().map(|p| p.state))
        };
        if schedule.contains("only observes") {
            assert_eq!(state, Some(MachineStateKind::Idle));
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{schedule} {state:?}"
        );
        t = (t + 60 * S).min(T0 + 3 * 3600 * S);
        clock.set(t);
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // The spindle series went to the store, the API has no NC door for this machine.
    let base = format!("http://{}", svc.addr);
    let r = reqwest::get(format!("{base}/api/v1/machines/sim-1/nc/request"))
        .await
        .unwrap();
    assert_ne!(r.status(), reqwest::StatusCode::OK);
    svc.stop();
    svc.wait().await;
    assert!(agent.lock().unwrap().requests > 2);
}
