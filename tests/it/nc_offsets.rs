//! The compensation endpoint in each NC's form (`?format=`): a FANUC, Siemens, HEIDENHAIN and
//! LinuxCNC program and the JSON list made from the set the NC is served, the default body
//! unchanged, an unknown format and a missing FANUC or LinuxCNC nominal refused, LinuxCNC's
//! trt kinematics refused for a machine in the ISO table sense, a step beyond the limit refused.

use crate::common;

use axum::http::{StatusCode, header};
use serde_json::Value;

use common::{MIN, TestService, config, launch_test, patent_m1, scratch};
use driftwatch_service::config::LinkConfig;

async fn service(name: &str) -> TestService {
    let mut cfg = patent_m1(&scratch(&format!("nc-offsets-{name}")));
    cfg.http.anonymous_read = true;
    launch_test(cfg, None).await
}

async fn get(app: &TestService, uri: &str) -> (StatusCode, axum::http::HeaderMap, Value) {
    app.call(
        axum::http::Request::get(uri)
            .body(axum::body::Body::empty())
            .unwrap(),
    )
    .await
}

/// The line of `program` that writes `name`, and the value written.
fn written(program: &str, prefix: &str) -> f64 {
    let line = program
        .lines()
        .find(|l| l.starts_with(prefix))
        .unwrap_or_else(|| panic!("no line {prefix} in\n{program}"));
    let rest = &line[prefix.len()..];
    let end = rest.find([' ', ';', '(']).unwrap_or(rest.len());
    rest[..end].trim().parse().unwrap()
}

#[tokio::test]
async fn each_control_gets_the_served_set_in_its_own_form() {
    let app = service("forms").await;
    let (s, _, b) = get(&app, "/api/v1/machines/m1/compensation?format=fanuc").await;
    assert_eq!(s, StatusCode::NOT_FOUND, "no set yet: {b}");
    app.run_to(app.t0() + 100 * MIN).await;
    let (s, _, set) = get(&app, "/api/v1/machines/m1/compensation").await;
    assert_eq!(s, StatusCode::OK);
    assert!(
        set.get("variables").is_none(),
        "the default body is unchanged"
    );
    let version = set["version"].as_u64().unwrap();
    assert!(version >= 2, "two sets for a step: {set}");
    let e = |n: &str| set["errors"][n].as_f64().unwrap();

    // FANUC, IS-B (1 um), nominal 0: R is each vector's offset in um.
    let nominal = "fanuc_nominal=19700:0,19702:0,19703:-100,19704:0";
    let (s, _, b) = get(&app, "/api/v1/machines/m1/compensation?format=fanuc").await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert_eq!(b["code"], "missing_nominal");
    assert!(b["message"].as_str().unwrap().contains("19700"), "{b}");
    let uri = format!("/api/v1/machines/m1/compensation?format=fanuc&{nominal}");
    let r = app.text(&uri).await;
    assert_eq!(r.0, StatusCode::OK);
    let p = r.1;
    assert!(p.contains("G10 L52\n") && p.contains("\nG11\n"), "{p}");
    assert_eq!(written(&p, "N19700 R"), e("EX0B").round());
    assert_eq!(written(&p, "N19702 R"), e("EZ0B").round());
    assert_eq!(written(&p, "N19703 R"), (-100_000.0 + e("EX0C")).round());
    assert_eq!(written(&p, "N19704 R"), e("EY0C").round());

    // Siemens: the fine offset of l2 is the B line's move in mm.
    let (_, p) = app
        .text("/api/v1/machines/m1/compensation?format=siemens&siemens_carrier=3")
        .await;
    let mm = |um: f64| (um * 10.0).round() / 1e4;
    assert_eq!(written(&p, "$TC_CARR44[3]="), mm(e("EX0B")));
    assert_eq!(written(&p, "$TC_CARR56[3]="), mm(e("EY0C")));
    let (_, p) = app
        .text("/api/v1/machines/m1/compensation?format=heidenhain")
        .await;
    assert!(p.starts_with("0 BEGIN PGM DWOFFSET MM"), "{p}");

    // LinuxCNC's trt kinematics turn the table in the direct sense: table_bc (ISO 841) is
    // refused, saying how to describe the machine; a pin the kinematics lack is a bad query.
    let (s, _, b) = get(
        &app,
        "/api/v1/machines/m1/compensation?format=linuxcnc\
         &linuxcnc_nominal=x-rot-point:0,y-rot-point:0,x-offset:0,z-offset:0",
    )
    .await;
    assert_eq!(s, StatusCode::CONFLICT, "{b}");
    assert_eq!(b["code"], "offsets_refused");
    assert!(
        b["message"]
            .as_str()
            .unwrap()
            .contains("sense = \"direct\""),
        "{b}"
    );
    let (s, _, b) = get(
        &app,
        "/api/v1/machines/m1/compensation?format=linuxcnc&linuxcnc_nominal=tool-offset:0",
    )
    .await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{b}");
    assert_eq!(b["code"], "bad_query");
    assert!(
        b["message"].as_str().unwrap().contains("tool-offset"),
        "{b}"
    );

    // json: the set, plus each variable with its step from the previous served set.
    let (s, h, j) = get(&app, "/api/v1/machines/m1/compensation?format=json").await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(j["version"], set["version"]);
    assert_eq!(j["previous_version"].as_u64(), Some(version - 1));
    let vars = j["variables"].as_array().unwrap();
    let bz = vars.iter().find(|v| v["name"] == "B_pivot_z_um").unwrap();
    assert_eq!(
        bz["value"].as_f64().unwrap(),
        (e("EZ0B") * 1e3).round() / 1e3
    );
    assert!(bz["step"].is_number());
    assert!(!j["datum_shift"].as_array().unwrap().is_empty());
    // A per-format ETag, and 304 on it.
    let etag = h[header::ETAG].to_str().unwrap().to_string();
    assert!(etag.ends_with("-json\""), "{etag}");
    let req = axum::http::Request::get("/api/v1/machines/m1/compensation?format=json")
        .header(header::IF_NONE_MATCH, &etag)
        .body(axum::body::Body::empty())
        .unwrap();
    assert_eq!(app.call(req).await.0, StatusCode::NOT_MODIFIED);

    let (s, _, b) = get(&app, "/api/v1/machines/m1/compensation?format=mazak").await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert_eq!(b["code"], "bad_format");
    assert!(b["message"].as_str().unwrap().contains("mazak"), "{b}");
    app.stop().await;
}

/// A machine of `deploy/linuxcnc/machines` (table axes in the direct sense) gets its served set
/// as a halcmd script of `xyzbc-trt-kins` pins: each commissioned value plus its lines' moves;
/// without the commissioned values the pins are named and nothing is written.
#[tokio::test]
async fn linuxcnc_gets_the_pins_of_its_trt_kinematics() {
    let mut cfg = patent_m1(&scratch("nc-offsets-linuxcnc"));
    cfg.http.anonymous_read = true;
    cfg.machines[0].machine = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/deploy/linuxcnc/machines/xyzbc-trt.toml"
    )
    .into();
    let app = launch_test(cfg, None).await;
    app.run_to(app.t0() + 100 * MIN).await;
    let (s, _, set) = get(&app, "/api/v1/machines/m1/compensation").await;
    assert_eq!(s, StatusCode::OK, "{set}");
    let e = |n: &str| set["errors"][n].as_f64().unwrap();

    let uri = "/api/v1/machines/m1/compensation?format=linuxcnc";
    let (s, _, b) = get(&app, uri).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{b}");
    assert_eq!(b["code"], "missing_nominal");
    assert!(
        b["message"]
            .as_str()
            .unwrap()
            .contains("x-rot-point, y-rot-point, x-offset, z-offset"),
        "{b}"
    );
    let nominal = "linuxcnc_nominal=x-rot-point:10,y-rot-point:-20,x-offset:0.5,z-offset:-50";
    let (s, p) = app.text(&format!("{uri}&{nominal}")).await;
    assert_eq!(s, StatusCode::OK, "{p}");
    // Commissioned + move, to 6 decimals (half a nm).
    let pins = [
        ("x-rot-point", 10.0 + (e("EX0B") + e("EX0C")) * 1e-3),
        ("y-rot-point", -20.0 + e("EY0C") * 1e-3),
        ("x-offset", 0.5 - e("EX0C") * 1e-3),
        ("z-offset", -50.0 + e("EZ0B") * 1e-3),
    ];
    for (pin, want) in pins {
        let got = written(&p, &format!("setp xyzbc-trt-kins.{pin} "));
        assert!((got - want).abs() <= 5e-7 + 1e-12, "{pin}: {got} vs {want}");
    }
    assert!(
        p.contains("# kinematics: KINEMATICS = xyzbc-trt-kins\n"),
        "{p}"
    );
    assert!(p.contains("# not written: EA0C = "), "{p}");
    for l in p.lines() {
        assert!(
            l.starts_with('#') || (l.starts_with("setp ") && l.split(' ').count() == 3),
            "{l}"
        );
    }
    assert_eq!(p.lines().filter(|l| l.starts_with("setp ")).count(), 4);
    app.stop().await;
}

/// A service restarted with tighter step limits than the ones its served sets were ramped
/// under: the served set's step from the one before it now lies beyond the limit, and the NC's
/// form is refused with the step, never written; the default body still answers.
#[tokio::test]
async fn a_step_beyond_the_limit_is_refused_not_written() {
    let app = service("step").await;
    app.run_to(app.t0() + 100 * MIN).await;
    let dir = std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("nc-offsets-step");
    app.stop().await;
    let mut cfg = config(&dir);
    cfg.http.anonymous_read = true;
    let m = &mut cfg.machines[0];
    m.id = "m1".into();
    m.machine = "table_bc".into();
    m.plan = Some("patent".into());
    m.link = LinkConfig::Simulated {
        scenario: "patent".into(),
        seed: None,
    };
    cfg.validation.max_step_um = 0.001;
    cfg.validation.max_step_urad = 0.001;
    cfg.validation.max_rate_um_per_min = 0.0;
    cfg.validation.max_rate_urad_per_min = 0.0;
    let app = launch_test(cfg, None).await;
    let (s, _, b) = get(&app, "/api/v1/machines/m1/compensation?format=siemens").await;
    assert_eq!(s, StatusCode::CONFLICT, "{b}");
    assert_eq!(b["code"], "offsets_refused");
    let m = b["message"].as_str().unwrap();
    assert!(m.contains("beyond the limit") && m.contains("step"), "{m}");
    let (s, _, _) = get(&app, "/api/v1/machines/m1/compensation").await;
    assert_eq!(s, StatusCode::OK);
    app.stop().await;
}
