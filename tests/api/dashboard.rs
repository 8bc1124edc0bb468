//! The dashboard in a real browser: headless Chromium driven through WebDriver (Debian's
//! `chromium` and `chromium-driver`) against the service on a manual clock. The overview lists
//! the machine, the machine page draws as many measured points as the API holds for its
//! window, an acknowledgement is refused without a token (the API's message shown) and taken
//! with the write token. Screenshots go to `target/tmp/dashboard/` (printed).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::json;

use crate::common::{MIN, launch_test, patent_m1, scratch};

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
    app.run_to(t0 + 240 * MIN).await;
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
    assert!(tile.contains("served set"), "{tile}");
    assert!(
        tile.contains("threshold:") || tile.contains("limit"),
        "{tile}"
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

    // An acknowledgement without a token: refused, with the API's own message on the page.
    let (_, _, alerts) = app
        .call(
            Request::get("/api/v1/machines/m1/alerts")
                .body(Body::empty())
                .unwrap(),
        )
        .await;
    let alert = alerts["open"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["rule"] == "threshold:EZ0B")
        .expect("EZ0B above its limit")["id"]
        .as_u64()
        .unwrap();
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
    // loop looks at its inbox every 200 ms of wall time even on a manual clock, and may apply
    // it before the page redraws (the note is not shown once the alert says acknowledged).
    let note = text_of(&c, &format!("{row} .ack-note.ok, {row} .acked")).await;
    assert!(note.contains("operator"), "{note}");
    app.run_to(t0 + 241 * MIN).await;
    let acked = text_of(&c, &format!("{row} .acked")).await;
    assert_eq!(acked, "acknowledged by operator");
    // Tall enough for the whole page.
    c.set_window_size(1400, 2600).await.unwrap();
    let machine = screenshot(&c, "machine.png").await;

    c.close().await.unwrap();
    for f in [overview, machine] {
        let png = std::fs::read(&f).unwrap();
        assert!(png.starts_with(b"\x89PNG"), "{}", f.display());
    }
    drop(driver);
    app.stop().await;
}
