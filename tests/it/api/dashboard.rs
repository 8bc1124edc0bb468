//! The dashboard in a real browser: headless Chromium driven through WebDriver (Debian's
//! `chromium` and `chromium-driver`) against the service on a manual clock. The overview lists
//! the machine with its served set aged on the clock of the same answer, why it is that old,
//! what each value is (the served set's, an alert's cycle's) and the simulated clock; the
//! machine page draws as many measured points as the API holds for its window, the EZ0B alert
//! limits about their reference, and the NC offsets with their units; an acknowledgement is
//! refused without a token (the API's message shown) and taken with the write token.
//! Screenshots go to `target/tmp/dashboard/` (printed).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::json;

use crate::common::{MIN, launch_test, patent_m1, scratch};
use driftwatch_core::units::NS_PER_S;

const CHROMEDRIVER: &str = "/usr/bin/chromedriver";
const CHROMIUM: &str = "/usr/bin/chromium";
/// Longest wait for the page to show something (it polls the API every 5 s).
const PATIENCE: Duration = Duration::from_secs(30);

/// chromedriver on a free port, ended when dropped.
struct Driver {
    child: Child,
    url: String,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_driver() -> Driver {
    assert!(
        Path::new(CHROMEDRIVER).exists() && Path::new(CHROMIUM).exists(),
        "the dashboard's browser test needs headless Chromium and its WebDriver: \
         install them with `apt-get install -y chromium chromium-driver` \
         ({CHROMIUM} and {CHROMEDRIVER})"
    );
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .unwrap()
        .port();
    let child = Command::new(CHROMEDRIVER)
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap_or_else(|e| panic!("{CHROMEDRIVER} does not start: {e}"));
    Driver {
        child,
        url: format!("http://127.0.0.1:{port}"),
    }
}

/// A headless Chromium session with a fresh profile in `profile`.
async fn browser(driver: &Driver, profile: &Path) -> Client {
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        json!({
            "binary": CHROMIUM,
            "args": [
                "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync",
                "--window-size=1400,1000",
                format!("--user-data-dir={}", profile.display()),
            ],
        }),
    );
    // chromedriver answers once it listens: bounded polling of the connection.
    let mut last = String::new();
    for _ in 0..100 {
        match ClientBuilder::rustls()
            .expect("rustls")
            .capabilities(caps.clone())
            .connect(&driver.url)
            .await
        {
            Ok(c) => return c,
            Err(e) => last = e.to_string(),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!(
        "no WebDriver session from {CHROMEDRIVER} at {}: {last}",
        driver.url
    );
}

/// An age as the page writes it (app.js `age`).
fn age_text(ns: i64) -> String {
    let s = ns as f64 / 1e9;
    if s < 120.0 {
        format!("{} s", s.round())
    } else if s < 7200.0 {
        format!("{} min", (s / 60.0).round())
    } else {
        format!("{:.1} h", s / 3600.0)
    }
}

async fn screenshot(c: &Client, name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("dashboard");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join(name);
    std::fs::write(&file, c.screenshot().await.unwrap()).unwrap();
    println!("screenshot: {}", file.display());
    file
}

async fn text_of(c: &Client, css: &str) -> String {
    c.wait()
        .at_most(PATIENCE)
        .for_element(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no {css} on the page: {e}"))
        .text()
        .await
        .unwrap()
}

/// Wait (bounded) until `css` matches nothing.
async fn gone(c: &Client, css: &str) {
    let deadline = tokio::time::Instant::now() + PATIENCE;
    while !c.find_all(Locator::Css(css)).await.unwrap().is_empty() {
        assert!(tokio::time::Instant::now() < deadline, "{css} stays");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_shows_the_fleet_and_a_machine_and_acknowledges_in_a_real_browser() {
    let driver = start_driver();
    let dir = scratch("api-dashboard");
    let mut cfg = patent_m1(&dir.join("data"));
    cfg.http.anonymous_read = true;
    let app = launch_test(cfg, None).await;
    let t0 = app.t0();
    // Four hours of the patent day: validated cycles, the thermal model fitted (by about
    // 150 min) and serving predictions, and the EZ0B threshold alert open.
    // 45 s past 240 min, while the cycle started then runs: the set served (this seed: the
    // prediction of 240 min) is some seconds old, so that an age taken on another clock than
    // the answer's would show.
    app.run_to(t0 + 240 * MIN + 45 * NS_PER_S).await;
    let base = format!("http://{}", app.svc.addr);
    let c = browser(&driver, &dir.join("profile")).await;

    // The overview: one tile per machine the API lists.
    c.goto(&format!("{base}/")).await.unwrap();
    let tile = text_of(&c, ".tile[data-machine='m1']").await;
    let (s, _, machines) = app
        .call(
            Request::get("/api/v1/machines")
                .body(Body::empty())
                .unwrap(),
        )
        .await;
    assert_eq!(s, StatusCode::OK);
    let tiles = c.find_all(Locator::Css(".tile")).await.unwrap();
    assert_eq!(tiles.len(), machines.as_array().unwrap().len());
    let phase = machines[0]["phase"]["phase"]
        .as_str()
        .unwrap()
        .replace('_', " ");
    assert!(tile.contains(&phase), "{tile}");
    let m1 = &machines[0];
    let (s, _, service) = app
        .call(Request::get("/api/v1/service").body(Body::empty()).unwrap())
        .await;
    assert_eq!(s, StatusCode::OK);
    // The test's clock is moved by hand and m1 is the simulator: the page says both.
    assert_eq!(service["clock"], "manual", "{service}");
    assert_eq!(service["simulated"], json!(["m1"]), "{service}");
    let kind = text_of(&c, "#clock-kind").await;
    assert!(
        kind.contains("simulated clock") && kind.contains("moved by hand"),
        "{kind}"
    );
    assert!(
        text_of(&c, ".tile[data-machine='m1'] .badge.sim").await == "simulated machine",
        "{tile}"
    );

    // The served set's age is measured on the service clock of the answer that holds the set:
    // the clock stands still (manual), so the page's answer had the clock the test reads.
    let set = &m1["compensation"];
    let clock = m1["service_clock_ns"]
        .as_i64()
        .expect("the clock of the answer");
    let valid_from = set["valid_from_ns"].as_i64().unwrap();
    let age_ns = clock - valid_from;
    assert!(age_ns >= 0, "{m1}");
    let served = c
        .find(Locator::Css(".tile[data-machine='m1'] .served"))
        .await
        .unwrap();
    // To the rounding of JavaScript's numbers: the ns since the epoch (some 1.8e18) are
    // doubles on the page, 256 ns apart; an age on another clock would be seconds off.
    let page_age: i64 = served
        .attr("data-age-ns")
        .await
        .unwrap()
        .and_then(|a| a.parse::<f64>().ok())
        .map(|a| a as i64)
        .unwrap_or_else(|| panic!("no age on the page, {m1}"));
    assert!(
        (page_age - age_ns).abs() <= 1_000,
        "the page's age {page_age} ns, the answer's {age_ns} ns"
    );
    let served_text = served.text().await.unwrap();
    let version = set["version"].as_u64().unwrap();
    let source = set["source"].as_str().unwrap();
    assert!(
        served_text.contains(&format!("v{version}, {source}"))
            && served_text.contains(&format!("{} old", age_text(age_ns))),
        "{served_text} against {age_ns} ns"
    );
    // Why the set is as old as it is: the reason the machine page shows too.
    let reason = set["reason"].as_str().unwrap();
    assert_eq!(
        text_of(&c, ".tile[data-machine='m1'] .served .reason").await,
        format!("why: {reason}")
    );
    // Each value says what it is: a served value names its set, an alert its cycle.
    let largest = text_of(&c, ".tile[data-machine='m1'] .largest[data-unit='um']").await;
    assert!(largest.contains(&format!("served v{version}")), "{largest}");
    let (_, _, alerts) = app
        .call(
            Request::get("/api/v1/machines/m1/alerts")
                .body(Body::empty())
                .unwrap(),
        )
        .await;
    let ez = alerts["open"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["rule"] == "threshold:EZ0B")
        .expect("EZ0B above its limit")
        .clone();
    let line = text_of(
        &c,
        ".tile[data-machine='m1'] .alert-line[data-rule='threshold:EZ0B']",
    )
    .await;
    assert!(
        line.contains(&format!("at cycle {}", ez["last_cycle"]))
            && line.contains(ez["message"].as_str().unwrap()),
        "{line} against {ez}"
    );
    let overview = screenshot(&c, "overview.png").await;

    // The machine page: per error, as many measured points as the API's accepted results in
    // the window the page shows.
    c.goto(&format!("{base}/#/machine/m1")).await.unwrap();
    c.wait()
        .at_most(PATIENCE)
        .for_element(Locator::Css("svg.chart circle.measured"))
        .await
        .unwrap();
    let charts = c.find_all(Locator::Css("svg.chart")).await.unwrap();
    assert!(!charts.is_empty());
    let (mut drawn, mut predicted) = (0, 0);
    for chart in &charts {
        let attr = |name: &'static str| {
            let chart = chart.clone();
            async move { chart.attr(name).await.unwrap().unwrap() }
        };
        let (name, from, to) = (
            attr("data-error").await,
            attr("data-from").await,
            attr("data-to").await,
        );
        // The API's values of this error in the window, of one source.
        let count = |source: &'static str| {
            let uri = format!("/api/v1/machines/m1/errors?source={source}&from={from}&to={to}");
            let (app, name) = (&app, &name);
            async move {
                let (s, _, series) = app
                    .call(Request::get(uri).body(Body::empty()).unwrap())
                    .await;
                assert_eq!(s, StatusCode::OK);
                series
                    .as_array()
                    .unwrap()
                    .iter()
                    .filter(|v| v["name"] == name.as_str())
                    .count()
            }
        };
        let points = chart
            .find_all(Locator::Css("circle.measured"))
            .await
            .unwrap()
            .len();
        assert_eq!(
            points,
            count("measured").await,
            "{name}: points drawn against the API's accepted results"
        );
        // The predicted line: one vertex per served prediction (none before the model's).
        let line = chart
            .find_all(Locator::Css("polyline.predicted"))
            .await
            .unwrap();
        let vertices = match line.first() {
            Some(l) => l
                .attr("points")
                .await
                .unwrap()
                .unwrap()
                .split_whitespace()
                .count(),
            None => 0,
        };
        assert_eq!(vertices, count("predicted").await, "{name}: predicted line");
        predicted += vertices;
        drawn += points;
    }
    assert!(drawn >= 6, "{drawn} measured points in all");
    assert!(predicted > 0, "no predicted line in any chart");

    // The EZ0B threshold as the API publishes it: about the first validated EZ0B value (the
    // rule has no reference of its own), drawn as lines at reference +- limit and +- clear.
    let rule = alerts["thresholds"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["error"] == "EZ0B")
        .expect("the EZ0B threshold rule")
        .clone();
    let (_, _, first) = app
        .call(
            Request::get("/api/v1/machines/m1/errors?source=measured")
                .body(Body::empty())
                .unwrap(),
        )
        .await;
    let first_ez = first
        .as_array()
        .unwrap()
        .iter()
        .filter(|v| v["name"] == "EZ0B")
        .min_by_key(|v| v["t_ns"].as_i64().unwrap())
        .unwrap()["value"]
        .as_f64()
        .unwrap();
    assert_eq!(rule["reference"].as_f64(), Some(first_ez), "{rule}");
    let (limit, clear) = (
        rule["limit"].as_f64().unwrap(),
        rule["clear"].as_f64().unwrap(),
    );
    let chart = c
        .find(Locator::Css("svg.chart[data-error='EZ0B']"))
        .await
        .unwrap();
    // (value, y) of each line of a class, highest value first.
    let lines = |class: &'static str| {
        let chart = chart.clone();
        async move {
            let mut out = Vec::new();
            for l in chart.find_all(Locator::Css(class)).await.unwrap() {
                let get = |a: &'static str| {
                    let l = l.clone();
                    async move { l.attr(a).await.unwrap().unwrap().parse::<f64>().unwrap() }
                };
                out.push((get("data-value").await, get("y1").await));
            }
            out.sort_by(|a, b| b.0.total_cmp(&a.0));
            out
        }
    };
    let (limits, clears, reference) = (
        lines("line.limit").await,
        lines("line.clear").await,
        lines("line.reference").await,
    );
    let close = |a: f64, b: f64| (a - b).abs() < 1e-9;
    assert!(
        limits.len() == 2
            && close(limits[0].0, first_ez + limit)
            && close(limits[1].0, first_ez - limit),
        "{limits:?} against {rule}"
    );
    assert!(
        clears.len() == 2
            && close(clears[0].0, first_ez + clear)
            && close(clears[1].0, first_ez - clear),
        "{clears:?} against {rule}"
    );
    // Drawn in order from the top (SVG y grows downwards): +limit, +clear, reference, ...
    let ys: Vec<f64> = [limits[0], clears[0], reference[0], clears[1], limits[1]]
        .iter()
        .map(|l| l.1)
        .collect();
    assert!(ys.windows(2).all(|w| w[0] < w[1]), "{ys:?}");

    // The page's served set is the one of its machine answer, aged on that answer's clock.
    let served_now = c.find(Locator::Css(".served-now")).await.unwrap();
    let now_age = served_now
        .attr("data-age-ns")
        .await
        .unwrap()
        .and_then(|a| a.parse::<f64>().ok())
        .map_or(i64::MIN, |a| a as i64);
    assert!(
        (now_age - age_ns).abs() <= 1_000,
        "{now_age} against {age_ns}"
    );
    // The NC offsets themselves, each with its unit.
    let offsets = set["offsets"].as_object().unwrap();
    assert!(!offsets.is_empty(), "{set}");
    let rows = c
        .find_all(Locator::Css("table.offsets tr[data-offset]"))
        .await
        .unwrap();
    assert_eq!(rows.len(), offsets.len());
    for row in rows {
        let name = row.attr("data-offset").await.unwrap().unwrap();
        let cells: Vec<String> = {
            let mut v = Vec::new();
            for td in row.find_all(Locator::Css("td")).await.unwrap() {
                v.push(td.text().await.unwrap());
            }
            v
        };
        let value = offsets[&name].as_f64().unwrap();
        let unit = name.rsplit('_').next().unwrap();
        assert!(
            cells[1] == format!("{value:.2}") && cells[2] == unit && matches!(unit, "um" | "urad"),
            "{name}: {cells:?} against {value}"
        );
    }
    // An open alert's message names the cycle whose value it holds.
    let message = text_of(&c, &format!("tr[data-alert='{}'] .alert-message", ez["id"])).await;
    assert!(
        message.starts_with(&format!("at cycle {}: ", ez["last_cycle"])),
        "{message}"
    );

    // An acknowledgement without a token: refused, with the API's own message on the page.
    let alert = ez["id"].as_u64().unwrap();
    let row = format!("tr[data-alert='{alert}']");
    let (s, _, refusal) = app
        .call(
            Request::post(format!("/api/v1/machines/m1/alerts/{alert}/ack"))
                .body(Body::empty())
                .unwrap(),
        )
        .await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    c.find(Locator::Css(&format!("{row} button.ack")))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let note = text_of(&c, &format!("{row} .ack-note.refused")).await;
    assert!(
        note.contains(refusal["message"].as_str().unwrap()),
        "{note} against {refusal}"
    );

    // With the write token typed in: taken, and shown acknowledged once the loop applied it.
    c.find(Locator::Css("#token"))
        .await
        .unwrap()
        .send_keys("write-token")
        .await
        .unwrap();
    c.find(Locator::Css("#token-form button[type='submit']"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    // A new token clears the old answers: the page has redrawn once the refusal is gone.
    gone(&c, &format!("{row} .ack-note.refused")).await;
    c.find(Locator::Css(&format!("{row} button.ack")))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    // The note that the acknowledgement was taken, or already the acknowledged state: the
    // acknowledgement wakes the loop even on a manual clock, and it may apply it before the
    // page redraws (the note is not shown once the alert says acknowledged).
    let note = text_of(&c, &format!("{row} .ack-note.ok, {row} .acked")).await;
    assert!(note.contains("operator"), "{note}");
    app.run_to(t0 + 241 * MIN).await;
    let acked = text_of(&c, &format!("{row} .acked")).await;
    assert_eq!(acked, "acknowledged by operator");
    // Tall enough for the whole page, from its top (the header with the clock).
    c.set_window_size(1400, 2600).await.unwrap();
    c.execute("window.scrollTo(0, 0)", vec![]).await.unwrap();
    let machine = screenshot(&c, "machine.png").await;

    c.close().await.unwrap();
    for f in [overview, machine] {
        let png = std::fs::read(&f).unwrap();
        assert!(png.starts_with(b"\x89PNG"), "{}", f.display());
    }
    drop(driver);
    app.stop().await;
}
