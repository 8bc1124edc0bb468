//! The `nc_push` flow end to end over HTTP: a test client plays the NC (a virtual machine from
//! the truth simulator), posts its events, polls for cycle orders and runs them; the service
//! loop runs on simulated time.

use crate::common;

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use serde_json::{Value, json};

use common::{MIN, TestService, launch_test, scratch};
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::recording::DetectionStatus;
use driftwatch_service::config::{Role, ServiceConfig, Token};
use driftwatch_service::nc_push::CycleOrder;
use driftwatch_service::store::CycleStatus;
use driftwatch_sim::scenario::Scenario;
use driftwatch_sim::simulator::VirtualMachine;

async fn send(
    app: &TestService,
    method: &str,
    uri: &str,
    token: Option<&str>,
    body: Option<Value>,
) -> (StatusCode, Value) {
    let mut b = Request::builder().method(method).uri(uri);
    if let Some(t) = token {
        b = b.header(header::AUTHORIZATION, format!("Bearer {t}"));
    }
    let req = match body {
        Some(v) => b
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(v.to_string()))
            .unwrap(),
        None => b.body(Body::empty()).unwrap(),
    };
    let (s, _, v) = app.call(req).await;
    (s, v)
}

/// The shipped configuration with one machine `nc1` on the `nc_push` link, the NC's write
/// token and a reader's.
fn nc_config(dir: &std::path::Path) -> ServiceConfig {
    let mut cfg = common::config(dir);
    // A real NC runs on the wall clock (the test moves a manual one).
    cfg.time_scale = 1.0;
    cfg.http.tokens = vec![
        Token {
            name: "nc".into(),
            token: "nc-token".into(),
            role: Role::Write,
        },
        Token {
            name: "dash".into(),
            token: "read-token".into(),
            role: Role::Read,
        },
    ];
    let m = &mut cfg.machines[0];
    m.id = "nc1".into();
    m.machine = "table_bc".into();
    m.plan = Some("patent".into());
    m.link = toml::from_str(r#"kind = "nc_push""#).unwrap();
    cfg
}

#[tokio::test]
async fn a_test_nc_drives_the_service_through_nc_push() {
    let scn = Scenario::load("patent").unwrap();
    let k = Kinematics::load(&scn.machine).unwrap();
    let plan = Plan::build(&k, &PlanConfig::load("patent").unwrap()).unwrap();
    let mut vm = VirtualMachine::new(&k, &scn).unwrap();
    let t0 = vm.start_ns();
    // The service clock starts where the test's NC does.
    let app = launch_test(nc_config(&scratch("nc-push")), Some(t0)).await;
    let events = "/api/v1/machines/nc1/nc/events";
    let request = "/api/v1/machines/nc1/nc/request";

    // Authorisation and bad input first.
    let one = json!({"events": [{"topic": "/spindle", "t_ns": t0, "msg": {"rpm": 20000.0}}]});
    assert_eq!(
        send(&app, "POST", events, None, Some(one.clone())).await.0,
        StatusCode::UNAUTHORIZED
    );
    assert_eq!(
        send(&app, "POST", events, Some("read-token"), Some(one.clone()))
            .await
            .0,
        StatusCode::FORBIDDEN
    );
    let bad = json!({"events": [
        {"topic": "/spindle", "t_ns": t0, "msg": {"rpm": 20000.0}},
        {"topic": "/machine/state", "t_ns": t0, "msg": {"state": "dancing", "program": null}}
    ]});
    let (s, body) = send(&app, "POST", events, Some("nc-token"), Some(bad)).await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert!(
        body["message"].as_str().unwrap().contains("event 1"),
        "{body}"
    );
    let (s, body) = send(
        &app,
        "POST",
        events,
        Some("nc-token"),
        Some(json!({"events": [{"topic": "/nope", "t_ns": t0, "msg": {}}]})),
    )
    .await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert!(
        body["message"].as_str().unwrap().contains("/nope"),
        "{body}"
    );
    assert_eq!(
        send(&app, "GET", request, Some("nc-token"), None).await.0,
        StatusCode::NO_CONTENT
    );

    // The NC: idle with the spindle at 20000 min^-1 (the patent's running-in), events every
    // minute, orders run at once, cycle 2 with a failed approach.
    let rpm = 20000.0;
    let mut now = t0;
    let mut orders = 0;
    let mut versions = Vec::new();
    while now < t0 + 100 * MIN {
        vm.advance_to(now, rpm);
        let mut evs = vec![
            json!({"topic": "/spindle", "t_ns": now, "msg": {"rpm": rpm}}),
            json!({"topic": "/machine/state", "t_ns": now, "msg": {"state": "idle", "program": "running-in"}}),
        ];
        for (sensor, celsius) in vm.temperatures(rpm) {
            evs.push(json!({"topic": "/temperature", "t_ns": now, "msg": {"sensor": sensor, "celsius": celsius}}));
        }
        let (s, _) = send(
            &app,
            "POST",
            events,
            Some("nc-token"),
            Some(json!({"events": evs})),
        )
        .await;
        assert_eq!(s, StatusCode::ACCEPTED);
        app.run_to(now).await;
        let (s, order) = send(&app, "GET", request, Some("nc-token"), None).await;
        if s == StatusCode::OK {
            let order: CycleOrder = serde_json::from_value(order).unwrap();
            orders += 1;
            let start = now;
            let mut dets = vec![
                json!({"topic": "/machine/state", "t_ns": start, "msg": {"state": "measuring", "program": "cycle"}}),
            ];
            for st in &order.steps {
                let step = plan.steps.iter().find(|s| s.label == st.step).unwrap();
                vm.advance_to(start + (step.t_start_s * 1e9) as i64, rpm);
                let mut det = vm.probe(&k, step, order.cycle, rpm);
                if order.cycle == 2 && st.step == "B0C-180/y#2" {
                    det.msg.status = Some(DetectionStatus::NoTrip);
                }
                dets.push(json!({"topic": "/probe/detection", "t_ns": det.t_ns, "msg": det.msg}));
            }
            let end = start + (plan.machine_time_s * 1e9) as i64;
            dets.push(json!({"topic": "/machine/state", "t_ns": end, "msg": {"state": "idle", "program": "running-in"}}));
            let (s, body) = send(
                &app,
                "POST",
                events,
                Some("nc-token"),
                Some(json!({"events": dets})),
            )
            .await;
            assert_eq!(s, StatusCode::ACCEPTED, "{body}");
            now = end;
            app.run_to(now).await;
            let (s, comp) =
                send(&app, "GET", "/api/v1/machines/nc1/compensation", None, None).await;
            if s == StatusCode::OK {
                versions.push((order.cycle, comp["version"].as_u64().unwrap()));
            }
        }
        now += MIN;
    }
    let cycles = app.store().cycles("nc1", 100, None).await.unwrap();
    println!("{orders} orders; versions after each cycle: {versions:?}");
    for c in cycles.iter().rev() {
        println!(
            "cycle {} {} {} {:?}",
            c.cycle, c.status, c.trigger, c.reason
        );
    }
    assert!(orders >= 4, "{orders}");
    assert_eq!(cycles.len(), orders);
    let two = cycles.iter().find(|c| c.cycle == 2).unwrap();
    assert_eq!(two.status, CycleStatus::Rejected);
    assert!(two.reason.as_ref().unwrap().contains("no_trip"));
    assert!(
        cycles
            .iter()
            .filter(|c| c.cycle != 2)
            .all(|c| c.status == CycleStatus::Ok)
    );
    // The rejected cycle left the served set as it was; every other one moved it up by one.
    let v = |c: i64| versions.iter().find(|(n, _)| *n == c).map(|(_, v)| *v);
    assert_eq!(v(1), Some(1));
    assert_eq!(v(2), Some(1));
    assert_eq!(v(3), Some(2));

    // A gateway that sends local time as UTC: its events an hour ahead of the service clock
    // are refused with the skew named, counted, and the correct ones after them still count.
    let ahead = json!({"events": [
        {"topic": "/machine/state", "t_ns": now + 60 * MIN, "msg": {"state": "cutting", "program": "O1"}}
    ]});
    let (s, body) = send(&app, "POST", events, Some("nc-token"), Some(ahead)).await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("clock_skew"))
    );
    assert!(
        body["message"]
            .as_str()
            .unwrap()
            .contains("ahead of the service clock"),
        "{body}"
    );
    let (_, text) = app.text("/metrics").await;
    assert!(
        text.contains("driftwatch_nc_events_refused_clock_skew_total{machine=\"nc1\"} 1"),
        "{text}"
    );
    // ... and a clock_skew alert is raised for the machine at the loop's next step, naming the
    // skew; it resolves after 10 min of machine time without a refusal.
    // A step at the same time (1 ns later: the loop steps when the clock moves).
    app.run_to(now + 1).await;
    let alerts = "/api/v1/machines/nc1/alerts";
    let (_, a) = send(&app, "GET", alerts, Some("read-token"), None).await;
    let open = a["open"].as_array().unwrap();
    let skew = open
        .iter()
        .find(|x| x["rule"] == "clock_skew")
        .unwrap_or_else(|| panic!("{a}"));
    // The service clock stood at the loop's last step, a minute before `now`.
    assert_eq!(skew["value"].as_f64(), Some(3660.0), "{skew}");
    assert!(
        skew["message"].as_str().unwrap().contains("3660 s ahead"),
        "{skew}"
    );
    for m in 1..=10 {
        app.run_to(now + m * MIN).await;
    }
    let (_, a) = send(&app, "GET", alerts, Some("read-token"), None).await;
    assert!(
        !a["open"]
            .as_array()
            .unwrap()
            .iter()
            .any(|x| x["rule"] == "clock_skew"),
        "{a}"
    );
    assert!(
        a["events"]
            .as_array()
            .unwrap()
            .iter()
            .any(|x| x["rule"] == "clock_skew" && x["kind"] == "resolved"),
        "{a}"
    );
}
