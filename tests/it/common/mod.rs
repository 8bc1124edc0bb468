//! The service for integration tests, started the way `driftwatch serve` starts it: through
//! `launch`, on a listener bound to port 0 that the test keeps, on a manual clock that the test
//! moves (hours of a plant day in seconds; nothing sleeps on the wall clock to pass).

// Each test module uses a part of this module.
#![allow(dead_code)]

pub mod child;
pub mod fl_thermal;

use std::path::PathBuf;
use std::time::Duration;

use axum::body::Body;
use axum::http::{HeaderMap, Request, StatusCode};
use http_body_util::BodyExt;
use serde_json::Value;
use tokio_util::sync::CancellationToken;

use driftwatch_service::config::{Role, ServiceConfig, Token};
use driftwatch_service::launch::{ClockKind, LaunchOptions, Service, launch_with};
use driftwatch_service::store::Store;

pub const MIN: i64 = driftwatch_core::units::NS_PER_MIN;

/// An empty scratch directory under the test target's temporary directory. Every module of
/// `tests/it` runs in the one process at the same time: each names its directories with its own
/// prefix (`api-`, `faults-`, ...), so no two tests share one.
pub fn scratch(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// With `DRIFTWATCH_TEST_BACKEND=postgres`, the URL of the database of data directory `dir` on
/// a throwaway PostgreSQL server (one per test process, so one for every module of `tests/it`;
/// a fresh database the first time a directory asks, the same one after, as a restart on the
/// same directory finds its SQLite file): the tests that take their store from here then run
/// against PostgreSQL instead of SQLite (`.ci/run` runs them both ways).
pub fn test_database_url(dir: &std::path::Path) -> Option<String> {
    use driftwatch_scratch_pg::ScratchPg;
    static SERVER: std::sync::OnceLock<ScratchPg> = std::sync::OnceLock::new();
    static BY_DIR: std::sync::Mutex<Vec<(PathBuf, String)>> = std::sync::Mutex::new(Vec::new());
    match std::env::var("DRIFTWATCH_TEST_BACKEND").as_deref() {
        Ok("postgres") => {}
        Ok("sqlite") | Err(_) => return None,
        Ok(other) => panic!("DRIFTWATCH_TEST_BACKEND={other}: sqlite or postgres"),
    }
    let server = SERVER.get_or_init(|| {
        ScratchPg::start(std::path::Path::new(env!("CARGO_TARGET_TMPDIR")))
            .unwrap_or_else(|e| panic!("{e}"))
    });
    let mut by_dir = BY_DIR.lock().unwrap();
    if let Some((_, url)) = by_dir.iter().find(|(d, _)| d == dir) {
        return Some(url.clone());
    }
    let url = server
        .database_blocking()
        .unwrap_or_else(|e| panic!("{e}"))
        .1;
    by_dir.push((dir.to_path_buf(), url.clone()));
    Some(url)
}

/// The store of a test that runs a machine itself: SQLite in `dir`, or PostgreSQL (see
/// [`test_database_url`]).
pub async fn test_store(dir: &std::path::Path) -> Store {
    match test_database_url(dir) {
        Some(url) => Store::connect(&url).await.unwrap(),
        None => Store::open(&dir.join("driftwatch.db")).await.unwrap(),
    }
}

/// The shipped default configuration with its data in `dir` (its database: see
/// [`test_database_url`]), and literal tokens: `read-token` (dashboard, read), `write-token`
/// (operator, write).
pub fn config(dir: &std::path::Path) -> ServiceConfig {
    let mut cfg = ServiceConfig::load(None).unwrap();
    cfg.data_dir = dir.to_path_buf();
    cfg.database_url = test_database_url(dir);
    cfg.http.tokens = vec![
        Token {
            name: "dashboard".into(),
            token: "read-token".into(),
            role: Role::Read,
        },
        Token {
            name: "operator".into(),
            token: "write-token".into(),
            role: Role::Write,
        },
    ];
    cfg
}

/// [`config`] with its one machine as `m1`: `table_bc` running the patent plan on the
/// simulated patent day (the API tests' machine).
pub fn patent_m1(dir: &std::path::Path) -> ServiceConfig {
    let mut cfg = config(dir);
    let m = &mut cfg.machines[0];
    m.id = "m1".into();
    m.machine = "table_bc".into();
    m.plan = Some("patent".into());
    m.link = driftwatch_service::config::LinkConfig::Simulated {
        scenario: "patent".into(),
        seed: None,
    };
    cfg
}

pub struct TestService {
    pub svc: Service,
    client: reqwest::Client,
}

/// Launch `cfg` on a manual clock (at `start_ns`, or where the service would start).
pub async fn launch_test(cfg: ServiceConfig, start_ns: Option<i64>) -> TestService {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let opts = LaunchOptions {
        clock: ClockKind::Manual,
        start_ns,
        ..Default::default()
    };
    let svc = launch_with(cfg, listener, CancellationToken::new(), opts)
        .await
        .unwrap();
    TestService {
        svc,
        client: reqwest::Client::new(),
    }
}

impl TestService {
    /// A service launched by the test itself (its own options).
    pub fn new(svc: Service) -> Self {
        TestService {
            svc,
            client: reqwest::Client::new(),
        }
    }

    pub fn t0(&self) -> i64 {
        self.svc.t0_ns
    }

    pub fn store(&self) -> &Store {
        self.svc.store()
    }

    /// Move the clock to `t_ns` and wait (bounded) until every machine has stepped to it.
    pub async fn run_to(&self, t_ns: i64) {
        let ids: Vec<&str> = self.svc.views.keys().map(String::as_str).collect();
        self.run_to_for(t_ns, &ids).await;
    }

    /// Move the clock to `t_ns` and wait (bounded) until the machines `moving` have stepped
    /// to it (a step that failed counts: a loop whose store refuses writes still steps).
    pub async fn run_to_for(&self, t_ns: i64, moving: &[&str]) {
        self.svc.manual_clock.as_ref().unwrap().set(t_ns);
        let reached = async {
            loop {
                let done = moving.iter().all(|id| {
                    self.svc.views[*id]
                        .lock()
                        .unwrap()
                        .health
                        .attempt_ns
                        .is_some_and(|t| t >= t_ns)
                });
                if done {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        };
        tokio::time::timeout(Duration::from_secs(120), reached)
            .await
            .unwrap_or_else(|_| panic!("the machines {moving:?} did not reach the clock's time"));
    }

    /// Send `req` to the running service over HTTP: status, headers and the body as JSON
    /// (`Null` when it is not JSON).
    pub async fn call(&self, req: Request<Body>) -> (StatusCode, HeaderMap, Value) {
        let (parts, body) = req.into_parts();
        let bytes = body.collect().await.unwrap().to_bytes();
        let url = format!("http://{}{}", self.svc.addr, parts.uri);
        let r = self
            .client
            .request(parts.method, url)
            .headers(parts.headers)
            .body(bytes)
            .send()
            .await
            .unwrap();
        let status = r.status();
        let headers = r.headers().clone();
        let bytes = r.bytes().await.unwrap();
        let body = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        (status, headers, body)
    }

    /// The body as text (for `/metrics`).
    pub async fn text(&self, path: &str) -> (StatusCode, String) {
        let r = self
            .client
            .get(format!("http://{}{path}", self.svc.addr))
            .send()
            .await
            .unwrap();
        (r.status(), r.text().await.unwrap())
    }

    /// Stop the service and wait (bounded) for it.
    pub async fn stop(self) {
        self.svc.stop();
        tokio::time::timeout(Duration::from_secs(60), self.svc.wait())
            .await
            .expect("the service stops");
    }
}

/// Make every insert of `machine` into `tables` fail, as a full disk or a read-only file
/// would, through the real SQLite file at `db`: triggers that abort the insert (or, with
/// `refuse` false, drop them).
pub async fn refuse_inserts(db: &std::path::Path, tables: &[&str], machine: &str, refuse: bool) {
    let url = format!("sqlite://{}", db.display());
    let pool = sqlx::SqlitePool::connect(&url).await.unwrap();
    for table in tables {
        let name = format!("refuse_{table}");
        let sql = if refuse {
            format!(
                "CREATE TRIGGER {name} BEFORE INSERT ON {table} WHEN NEW.machine_id = '{machine}' \
                 BEGIN SELECT RAISE(ABORT, 'injected fault: {machine} may not write'); END"
            )
        } else {
            format!("DROP TRIGGER {name}")
        };
        // The names are the tests' own constants: nothing from outside.
        sqlx::query(sqlx::AssertSqlSafe(sql))
            .execute(&pool)
            .await
            .unwrap();
    }
    pool.close().await;
}
