//! Storage of the service: SQLite (the default, one file in the data directory) or PostgreSQL
//! (`database_url = "postgres://..."`), one implementation of the queries in portable SQL. The
//! reads go through sqlx's `Any` driver; the writes through [`statement`], which runs the same
//! SQL on SQLite's writer (on the calling thread) or on a PostgreSQL connection. What differs
//! between the engines (connecting, migrations, SQLite's pragmas) is in [`backend`]. Schemas
//! in `migrations/sqlite/` and `migrations/postgres/` (embedded, applied at open). Shell code;
//! with `recorder` (through the recording crate's `mcap_io`) the only module that touches files.

mod alerts;
mod backend;
mod cycles;
mod diagnoses;
mod files;
mod geometries;
mod holds;
mod leases;
mod samples;
mod sets;
mod statement;
mod verifications;
mod writer;

pub use alerts::{AlertEventKind, AlertEventRow, AlertSeverity, NewAlertEvent};
pub use backend::Backend;
pub use cycles::{CycleRow, CycleStatus, DetectionRow};
pub use diagnoses::{DiagnosisRow, DiagnosisStatus, NewDiagnosis, StoredDiagnosis};
pub use files::FileStatus;
pub use geometries::StoredGeometry;
pub use holds::MachineHold;
pub use leases::{Lease, LeaseAudit, LeaseRow, TermRow};
pub use samples::Sample;
pub use sets::NewCompensation;
pub use verifications::StoredVerification;

use std::path::Path;

use sqlx::AnyPool;
use thiserror::Error;

use writer::{Conn, Tx, Writer};

#[derive(Debug, Error)]
pub enum StoreError {
    #[error("cannot open database {path}: {source}")]
    Open { path: String, source: sqlx::Error },
    #[error("database URL {0}: neither sqlite:// nor postgres://")]
    Url(String),
    #[error("cannot apply the database migrations: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error("database: {0}")]
    Sql(#[from] sqlx::Error),
    /// From SQLite's writer ([`writer`]).
    #[error("database: {0}")]
    Sqlite(#[from] rusqlite::Error),
    #[error("cannot open the database {path} for writing: {source}")]
    OpenWriter {
        path: String,
        source: rusqlite::Error,
    },
    #[error("stored JSON: {0}")]
    Json(#[from] serde_json::Error),
    #[error("stored value: {0}")]
    Corrupt(String),
    /// The database file is damaged or is not a database: named at open, nothing written.
    #[error(
        "the database {database} is damaged or is not a driftwatch database ({detail}); \
         nothing was written to it. Restore it from a backup, or move it aside to start a new \
         store"
    )]
    Damaged { database: String, detail: String },
    /// A fenced write refused: this process no longer holds the machine's lease.
    #[error("machine {machine}: lease term {term} is no longer held ({why}); nothing was written")]
    LeaseLost {
        machine: String,
        term: i64,
        why: String,
    },
    #[error("fleet: {0}")]
    Fleet(String),
    /// Another process runs the machine on this database outside a fleet.
    #[error(
        "machine {machine} is run by another driftwatch process on this database ({holders}): \
         one writer per machine. Stop it first, or share the machines with [fleet]"
    )]
    Held { machine: String, holders: String },
}

pub use crate::series::ErrorSample;

#[derive(Clone)]
pub struct Store {
    pool: AnyPool,
    backend: Backend,
    /// The lease a machine's loop holds in a fleet: its cycle and compensation writes are
    /// checked against it ([`Store::fenced`]).
    fence: Option<std::sync::Arc<Lease>>,
    /// The name drawn when this database's schema was made: a set's ETag carries it, so that
    /// a version number of an emptied (or another) database never passes for this one's.
    epoch: std::sync::Arc<str>,
    /// SQLite's one writer connection ([`writer`]); none on PostgreSQL.
    writer: Option<std::sync::Arc<Writer>>,
}

/// Whether a statement that binds an `Option<f64>` may be a cached prepared statement: no.
/// sqlx 0.9.0's `Any` driver sends a `None` of `f64` to PostgreSQL as a NULL `float4` (its
/// `Real` and `Double` nulls are swapped), so a statement first prepared with that NULL keeps
/// a `float4` parameter and refuses every later value ("incorrect binary data format in bind
/// parameter"); an unnamed statement is prepared with each call's own types. Reported upstream
/// as sqlx issue 4284 (fixed by its pull request 4359, not in 0.9.0); pinned by the store test
/// `a_null_real_first_does_not_break_later_values`, which fails if this is switched back.
const NULLABLE_REAL_CACHED: bool = false;

/// `VALUES ($1, $2, ...), (...)` for `rows` rows of `cols` columns: a multi-row insert in the
/// placeholders both engines read (the `Any` driver's query builder writes `?`, which
/// PostgreSQL does not).
fn values_placeholders(rows: usize, cols: usize) -> String {
    // Built for every batch of samples: `itoa`, not `write!`, which took several times as long.
    let mut number = itoa::Buffer::new();
    let mut s = String::with_capacity(8 + rows * cols * 6);
    s.push_str("VALUES ");
    for r in 0..rows {
        if r > 0 {
            s.push_str(", ");
        }
        s.push('(');
        for c in 0..cols {
            if c > 0 {
                s.push_str(", ");
            }
            s.push('$');
            s.push_str(number.format(r * cols + c + 1));
        }
        s.push(')');
    }
    s
}

impl Store {
    /// A connection to write on ([`writer`]): SQLite's writer, once the write before has
    /// finished, or one of PostgreSQL's pool.
    async fn write_conn(&self) -> Result<Conn<'_>, StoreError> {
        match &self.writer {
            Some(w) => w.lock().await,
            None => Ok(Conn::Pooled(self.pool.acquire().await?)),
        }
    }

    /// Open (creating if needed) the SQLite database file and apply the migrations.
    pub async fn open(path: &Path) -> Result<Self, StoreError> {
        Self::connect(&Backend::sqlite_url(path)).await
    }

    /// Connect to `sqlite://PATH` (created if missing) or `postgres://...` and apply that
    /// engine's migrations.
    pub async fn connect(url: &str) -> Result<Self, StoreError> {
        let backend =
            Backend::of_url(url).ok_or_else(|| StoreError::Url(backend::redacted(url)))?;
        let pool = backend.connect(url).await?;
        let epoch: Option<String> =
            sqlx::query_scalar("SELECT value FROM store_meta WHERE key = 'epoch'")
                .fetch_optional(&pool)
                .await?;
        let epoch = epoch.ok_or_else(|| {
            StoreError::Corrupt(
                "the database has no epoch (store_meta): not made by driftwatch's migrations"
                    .into(),
            )
        })?;
        Ok(Store {
            pool,
            backend,
            fence: None,
            epoch: epoch.into(),
            writer: match backend {
                Backend::Sqlite => {
                    Some(std::sync::Arc::new(Writer::new(backend::sqlite_path(url)?)))
                }
                Backend::Postgres => None,
            },
        })
    }

    /// The database's epoch (see [`Store`]): the same for every process on it, new for a
    /// database made anew.
    pub fn epoch(&self) -> &str {
        &self.epoch
    }

    /// Whether the database holds no machine at all: a new or emptied one.
    pub async fn is_empty(&self) -> Result<bool, StoreError> {
        let n: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM machines")
            .fetch_one(&self.pool)
            .await?;
        Ok(n == 0)
    }

    /// The engine this store runs on.
    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// Whether every write runs on the calling thread, needing no runtime's reactor: SQLite's
    /// writer outside a fleet (PostgreSQL's connections, and a fleet's fence, go through sqlx).
    pub(crate) fn writes_on_calling_thread(&self) -> bool {
        self.backend == Backend::Sqlite && self.fence.is_none()
    }

    /// SQLite's `PRAGMA integrity_check`: "ok" for a sound database (on PostgreSQL, which
    /// checks its own pages, it says it does not apply).
    pub async fn integrity_check(&self) -> Result<String, StoreError> {
        self.backend.integrity_check(&self.pool).await
    }

    /// SQLite's journal mode, "wal" as opened (PostgreSQL always logs ahead: "wal").
    pub async fn journal_mode(&self) -> Result<String, StoreError> {
        self.backend.journal_mode(&self.pool).await
    }

    pub async fn close(&self) {
        if let Some(w) = &self.writer {
            w.release().await;
        }
        self.pool.close().await;
    }

    pub async fn ensure_machine(
        &self,
        id: &str,
        kinematics: &str,
        now_ns: i64,
    ) -> Result<(), StoreError> {
        statement::query(
            "INSERT INTO machines (id, kinematics, created_ns) VALUES ($1, $2, $3)
             ON CONFLICT (id) DO UPDATE SET kinematics = excluded.kinematics",
        )
        .bind(id)
        .bind(kinematics)
        .bind(now_ns)
        .execute(&mut self.write_conn().await?)
        .await?;
        Ok(())
    }

    /// The latest time stored of a machine (samples, cycles, compensation sets, alert events),
    /// ns: where a restarted simulated machine resumes.
    pub async fn latest_time(&self, machine: &str) -> Result<Option<i64>, StoreError> {
        let t: Option<i64> = sqlx::query_scalar(
            "SELECT MAX(t) FROM (
                SELECT MAX(t_ns) AS t FROM spindle_samples WHERE machine_id = $1
                UNION ALL SELECT MAX(t_ns) FROM temperature_samples WHERE machine_id = $1
                UNION ALL SELECT MAX(COALESCE(finished_ns, started_ns)) FROM cycles WHERE machine_id = $1
                UNION ALL SELECT MAX(valid_from_ns) FROM compensation_sets WHERE machine_id = $1
                UNION ALL SELECT MAX(t_ns) FROM alert_events WHERE machine_id = $1
            ) AS latest",
        )
        .bind(machine)
        .fetch_one(&self.pool)
        .await?;
        Ok(t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::recording::{CycleResultMsg, ResultStatus};
    use std::collections::BTreeMap;

    /// A fresh SQLite file's URL, in a directory removed when the test ends.
    fn sqlite_db(name: &str) -> (tempfile::TempDir, String) {
        let (dir, path) = crate::scratch_dir(&format!("store-{name}"));
        (dir, Backend::sqlite_url(&path.join("driftwatch.db")))
    }

    /// Each row's placeholders number on from the row before's, past one digit.
    #[test]
    fn a_multi_row_insert_numbers_its_placeholders_row_by_row() {
        assert_eq!(values_placeholders(1, 1), "VALUES ($1)");
        assert_eq!(
            values_placeholders(2, 3),
            "VALUES ($1, $2, $3), ($4, $5, $6)"
        );
        assert!(values_placeholders(4, 3).ends_with("($10, $11, $12)"));
    }

    /// `integrity_check`'s answer on a sound database of `store`'s engine.
    fn sound(store: &Store) -> &'static str {
        match store.backend() {
            Backend::Sqlite => "ok",
            Backend::Postgres => "not applicable (PostgreSQL)",
        }
    }

    /// Each test body runs twice, on a fresh database of each engine: `sqlite::NAME` on a new
    /// file, `postgres::NAME` on a new database of the test server (`scratch_pg`).
    macro_rules! on_both_backends {
        ($(async fn $name:ident($db:ident: &str) $body:block)*) => {
            mod sqlite {
                use super::*;
                $(
                    #[tokio::test]
                    async fn $name() {
                        let (_dir, url) = sqlite_db(stringify!($name));
                        let $db: &str = &url;
                        $body
                    }
                )*
            }
            mod postgres {
                use super::*;
                $(
                    #[tokio::test]
                    async fn $name() {
                        let $db: &str = &driftwatch_scratch_pg::test_database().await;
                        $body
                    }
                )*
            }
        };
    }

    /// A batch of samples is stored whole or not at all: when its temperatures are refused
    /// (SQLite stores a NaN as NULL, which the column refuses), its spindle rows, written
    /// first, are not kept either, and the same batch written again in good order is stored.
    #[tokio::test]
    async fn a_batch_of_samples_that_fails_part_way_stores_none_of_it() {
        let (_dir, url) = sqlite_db("samples-whole");
        let store = Store::connect(&url).await.unwrap();
        store.ensure_machine("m1", "table_bc", 0).await.unwrap();
        let batch = |celsius: f64| {
            [
                Sample::Spindle {
                    t_ns: 60,
                    rpm: 12000.0,
                },
                Sample::Temperature {
                    t_ns: 60,
                    sensor: "spindle".into(),
                    celsius,
                },
            ]
        };
        assert!(store.add_samples("m1", &batch(f64::NAN)).await.is_err());
        assert!(store.samples("m1", 0, 1000).await.unwrap().is_empty());
        store.add_samples("m1", &batch(21.5)).await.unwrap();
        assert_eq!(store.samples("m1", 0, 1000).await.unwrap(), batch(21.5));
        store.close().await;
    }

    // SQLite's writer opens its own connection to the file the store opened: a file gone
    // since is refused with its name, not made anew as an empty store.
    #[tokio::test]
    async fn a_sqlite_file_gone_since_the_open_is_not_written_anew() {
        let (dir, url) = sqlite_db("gone");
        let store = Store::connect(&url).await.unwrap();
        let path = dir.path().join("driftwatch.db");
        std::fs::remove_file(&path).unwrap();
        let e = store.ensure_machine("m1", "table_bc", 0).await.unwrap_err();
        assert!(
            matches!(&e, StoreError::OpenWriter { path: p, .. } if p.ends_with("driftwatch.db")),
            "{e}"
        );
        assert!(!path.exists(), "a new database file was made");
        store.close().await;
    }

    fn result(cycle: i64, ok: bool) -> CycleResultMsg {
        let errors: BTreeMap<String, f64> =
            [("EZ0B".to_string(), 12.5), ("EX0B".to_string(), 3.0)].into();
        let sigma: BTreeMap<String, f64> =
            [("EZ0B".to_string(), 0.2), ("EX0B".to_string(), 0.25)].into();
        CycleResultMsg {
            cycle,
            t_ns: 1_000 + cycle,
            status: if ok {
                ResultStatus::Ok
            } else {
                ResultStatus::Rejected
            },
            reason: (!ok).then(|| "missing steps".to_string()),
            errors: ok.then_some(errors),
            sigma: ok.then_some(sigma),
            residual_rms_um: ok.then_some(0.4),
            chi2: ok.then_some(4.2),
            dof: ok.then_some(4),
            n_detections: Some(12),
            nuisance: None,
            redundancy_um: None,
            chi2_point: None,
            geometry: None,
            notes: None,
        }
    }

    /// Outside a fleet, a machine on PostgreSQL is held by one process: a second is refused,
    /// naming the first; once the first lets go, the second takes it.
    #[tokio::test]
    async fn a_machine_on_postgres_is_held_by_one_process_outside_a_fleet() {
        let db = driftwatch_scratch_pg::test_database().await;
        let store = Store::connect(&db).await.unwrap();
        let ids = ["m1".to_string(), "m2".to_string()];
        let first = store
            .hold_machines(&db, &ids, "pid 1 on host-a")
            .await
            .unwrap();
        assert!(first.is_some());
        let err = store
            .hold_machines(&db, &ids[1..], "pid 2 on host-b")
            .await
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("machine m2") && err.contains("driftwatch pid 1 on host-a"),
            "{err}"
        );
        // Another machine is free.
        let other = store
            .hold_machines(&db, &["m3".to_string()], "pid 2 on host-b")
            .await
            .unwrap();
        assert!(other.is_some());
        // Released (a service's stop): taken at once by the next.
        first.unwrap().release().await;
        let taken = store
            .hold_machines(&db, &ids, "pid 2 on host-b")
            .await
            .unwrap();
        assert!(taken.is_some(), "m1 and m2 are free once the first let go");
        // On SQLite the data directory's lock is the rule: nothing to hold here.
        let (_dir, url) = sqlite_db("holds");
        let lite = Store::connect(&url).await.unwrap();
        assert!(
            lite.hold_machines("unused", &ids, "x")
                .await
                .unwrap()
                .is_none()
        );
    }

    on_both_backends! {
        async fn a_null_real_first_does_not_break_later_values(db: &str) {
            // One connection, so that a statement prepared with the NULL is the one reused.
            let store = Store::connect(db).await.unwrap();
            store.ensure_machine("m1", "table_bc", 0).await.unwrap();
            for (c, ok) in [(1, false), (2, true), (3, false), (4, true)] {
                store.open_cycle("m1", c, 10 * c, "warm-up", 1).await.unwrap();
                store.close_cycle("m1", &result(c, ok), 10 * c + 5).await.unwrap();
                assert_eq!(store.result("m1", c).await.unwrap().unwrap(), result(c, ok));
            }
            for (i, value) in [None, Some(31.5), None, Some(2.0)].into_iter().enumerate() {
                let ev = NewAlertEvent {
                    alert: 1,
                    t_ns: i as i64,
                    kind: AlertEventKind::Updated,
                    rule: "threshold",
                    severity: None,
                    message: "m",
                    value,
                };
                store.add_alert_event("m1", &ev).await.unwrap();
            }
            let values: Vec<Option<f64>> = store
                .alert_events("m1", 10, None)
                .await
                .unwrap()
                .iter()
                .map(|e| e.value)
                .collect();
            assert_eq!(values, [Some(2.0), None, Some(31.5), None]);
        }

        async fn a_cycle_round_trips_with_its_detections_result_and_series(db: &str) {
            let store = Store::connect(db).await.unwrap();
            assert_eq!(store.journal_mode().await.unwrap(), "wal");
            store.ensure_machine("m1", "table_bc", 0).await.unwrap();
            assert_eq!(store.next_cycle_number("m1").await.unwrap(), 1);
            store.open_cycle("m1", 1, 10, "warm-up", 1).await.unwrap();
            store
                .add_detections(
                    "m1",
                    1,
                    &[DetectionRow {
                        t_ns: 11,
                        step: "B0C0/z",
                        payload: r#"{"step":"B0C0/z"}"#.into(),
                    }],
                )
                .await
                .unwrap();
            assert_eq!(store.open_cycles("m1").await.unwrap(), vec![1]);
            store.close_cycle("m1", &result(1, true), 20).await.unwrap();
            assert!(store.open_cycles("m1").await.unwrap().is_empty());
            assert_eq!(
                store.result("m1", 1).await.unwrap().unwrap(),
                result(1, true)
            );
            let d = store.detections("m1", 1).await.unwrap();
            assert_eq!(d[0].1["step"], "B0C0/z");
            store
                .open_cycle("m1", 2, 30, "after stop", 1)
                .await
                .unwrap();
            store
                .close_cycle("m1", &result(2, false), 40)
                .await
                .unwrap();
            // Only validated values make the series.
            let series = store
                .error_series("m1", 0, i64::MAX, true, true)
                .await
                .unwrap();
            assert_eq!(series.len(), 2);
            assert!(series.iter().all(|s| s.cycle == 1));
            let cycles = store.cycles("m1", 10, None).await.unwrap();
            assert_eq!(cycles[0].status, CycleStatus::Rejected);
            assert_eq!(cycles[0].reason.as_deref(), Some("missing steps"));
            assert_eq!(store.next_cycle_number("m1").await.unwrap(), 3);
            assert_eq!(store.integrity_check().await.unwrap(), sound(&store));
        }

        async fn foreign_keys_and_versions_are_enforced(db: &str) {
            let store = Store::connect(db).await.unwrap();
            store.ensure_machine("m1", "table_bc", 0).await.unwrap();
            // A detection of a cycle that was never opened is refused.
            let row = DetectionRow {
                t_ns: 1,
                step: "x",
                payload: "{}".into(),
            };
            assert!(store.add_detections("m1", 9, &[row]).await.is_err());
            let v = || r#"{"errors": {"EZ0B": 1.0}, "sigma": {"EZ0B": 0.5}}"#.to_string();
            store
                .insert_compensation(
                    "m1",
                    &NewCompensation {
                        version: 1,
                        valid_from_ns: 5,
                        source: "measured",
                        cycle: Some(1),
                        reason: "cycle 1",
                        values: v(),
                    },
                )
                .await
                .unwrap();
            assert!(
                store
                    .insert_compensation(
                        "m1",
                        &NewCompensation {
                            version: 1,
                            valid_from_ns: 6,
                            source: "measured",
                            cycle: Some(2),
                            reason: "again",
                            values: v()
                        }
                    )
                    .await
                    .is_err()
            );
            store
                .insert_compensation(
                    "m1",
                    &NewCompensation {
                        version: 2,
                        valid_from_ns: 7,
                        source: "measured",
                        cycle: Some(2),
                        reason: "cycle 2",
                        values: v(),
                    },
                )
                .await
                .unwrap();
            let latest = store.latest_compensation("m1").await.unwrap().unwrap();
            assert_eq!(
                (latest.version, latest.errors["EZ0B"], latest.sigma["EZ0B"]),
                (2, 1.0, 0.5)
            );
            // Offsets are the machine's layout's, filled in by its core, not the store's.
            assert!(latest.offsets.is_empty());
            assert!(
                store
                    .insert_compensation(
                        "m1",
                        &NewCompensation {
                            version: 3,
                            valid_from_ns: 8,
                            source: "guessed",
                            cycle: None,
                            reason: "bad source",
                            values: v()
                        }
                    )
                    .await
                    .is_err()
            );
        }

        async fn data_survives_reopening(db: &str) {
                    {
                let store = Store::connect(db).await.unwrap();
                store.ensure_machine("m1", "table_bc", 0).await.unwrap();
                let rows = [
                    Sample::Spindle {
                        t_ns: 60,
                        rpm: 20000.0,
                    },
                    Sample::Temperature {
                        t_ns: 60,
                        sensor: "ambient".into(),
                        celsius: 20.5,
                    },
                    // A repeated time replaces the value rather than failing the batch.
                    Sample::Spindle {
                        t_ns: 60,
                        rpm: 18000.0,
                    },
                ];
                store.add_samples("m1", &rows).await.unwrap();
                store
                    .mcap_file_opened("m1", "m1/2026-03-02.mcap.partial", 1)
                    .await
                    .unwrap();
                store
                    .add_alert_event(
                        "m1",
                        &NewAlertEvent {
                            alert: 1,
                            t_ns: 5,
                            kind: AlertEventKind::Raised,
                            rule: "threshold:EZ0B",
                            severity: Some(AlertSeverity::Warning),
                            message: "EZ0B high",
                            value: Some(31.0),
                        },
                    )
                    .await
                    .unwrap();
                store
                    .add_alert_event(
                        "m1",
                        &NewAlertEvent {
                            alert: 1,
                            t_ns: 6,
                            kind: AlertEventKind::Resolved,
                            rule: "threshold:EZ0B",
                            severity: Some(AlertSeverity::Warning),
                            message: "EZ0B back",
                            value: Some(20.0),
                        },
                    )
                    .await
                    .unwrap();
                store.close().await;
            }
            let store = Store::connect(db).await.unwrap();
            assert_eq!(
                store.samples("m1", 0, 100).await.unwrap(),
                vec![
                    Sample::Spindle {
                        t_ns: 60,
                        rpm: 18000.0
                    },
                    Sample::Temperature {
                        t_ns: 60,
                        sensor: "ambient".into(),
                        celsius: 20.5
                    }
                ]
            );
            assert!(store.samples("m1", 61, 100).await.unwrap().is_empty());
            assert_eq!(
                store.mcap_files("m1").await.unwrap(),
                vec![("m1/2026-03-02.mcap.partial".to_string(), FileStatus::Open)]
            );
            store
                .mcap_file_closed(
                    "m1",
                    "m1/2026-03-02.mcap.partial",
                    "m1/2026-03-02.mcap",
                    9,
                    FileStatus::Recovered,
                    42,
                )
                .await
                .unwrap();
            assert_eq!(
                store.mcap_files("m1").await.unwrap(),
                vec![("m1/2026-03-02.mcap".to_string(), FileStatus::Recovered)]
            );
            assert_eq!(store.integrity_check().await.unwrap(), sound(&store));
        }

        // A transaction that never reached its COMMIT (an error part way, a cancelled
        // future) takes its connection with it: every later write, on SQLite's writer opened
        // anew or on whichever connection of PostgreSQL's pool, commits and is seen by another
        // process (not held in a transaction left open, nor stuck behind its lock).
        async fn a_transaction_dropped_before_its_commit_leaves_no_connection_in_it(db: &str) {
            let store = Store::connect(db).await.unwrap();
            store.ensure_machine("m1", "table_bc", 0).await.unwrap();
            for attempt in 1..=3 {
                let mut tx = Tx::begin(&store).await.unwrap();
                statement::query("UPDATE machines SET kinematics = $1 WHERE id = 'm1'")
                    .bind(format!("dropped {attempt}"))
                    .execute(&mut tx)
                    .await
                    .unwrap();
                drop(tx);
            }
            // More writes than PostgreSQL's pool has connections.
            let temp = |t_ns| Sample::Temperature {
                t_ns,
                sensor: "ambient".into(),
                celsius: 20.0,
            };
            let rows: Vec<Sample> = (1..=12).map(temp).collect();
            for row in &rows {
                store.add_samples("m1", std::slice::from_ref(row)).await.unwrap();
            }
            store.close().await;
            let other = Store::connect(db).await.unwrap();
            assert_eq!(other.samples("m1", 0, 1_000).await.unwrap(), rows);
            let kinematics: String =
                sqlx::query_scalar("SELECT kinematics FROM machines WHERE id = 'm1'")
                    .fetch_one(&other.pool)
                    .await
                    .unwrap();
            assert_eq!(kinematics, "table_bc");
        }

        // Writes that come at once (many machines' loops) are all stored; while a transaction
        // is open, reads are answered, and on SQLite another write waits for its end (on the
        // one writer) instead of failing or going into it.
        async fn writes_at_once_are_stored_in_turn_and_reads_go_on_beside_them(db: &str) {
            let store = Store::connect(db).await.unwrap();
            let machines: Vec<String> = (0..12).map(|i| format!("m{i:02}")).collect();
            for m in &machines {
                store.ensure_machine(m, "table_bc", 0).await.unwrap();
            }
            let set = |version: i64| NewCompensation {
                version,
                valid_from_ns: version,
                source: "predicted",
                cycle: None,
                reason: "",
                values: r#"{"errors": {}, "sigma": {}}"#.into(),
            };
            let mut tasks = tokio::task::JoinSet::new();
            for m in machines.clone() {
                let store = store.clone();
                tasks.spawn(async move {
                    for v in 1..=5 {
                        store.insert_compensation(&m, &set(v)).await?;
                    }
                    Ok::<_, StoreError>(())
                });
            }
            while let Some(done) = tasks.join_next().await {
                done.unwrap().unwrap();
            }
            for m in &machines {
                assert_eq!(store.compensation_versions(m).await.unwrap().len(), 5, "{m}");
            }

            let mut tx = Tx::begin(&store).await.unwrap();
            sets::insert_set(&mut tx, "m00", &set(6), None).await.unwrap();
            let waiting = tokio::spawn({
                let store = store.clone();
                async move { store.insert_compensation("m01", &set(6)).await }
            });
            // Reads do not wait for the writer: the transaction's row is not seen yet.
            assert_eq!(store.compensation_versions("m00").await.unwrap().len(), 5);
            if store.backend() == Backend::Sqlite {
                // SQLite's one writer: the other machine's write waits for the commit.
                tokio::task::yield_now().await;
                assert!(!waiting.is_finished(), "a write went past an open transaction");
            }
            tx.commit().await.unwrap();
            waiting.await.unwrap().unwrap();
            for m in ["m00", "m01"] {
                assert_eq!(store.compensation_versions(m).await.unwrap().len(), 6, "{m}");
            }
            store.close().await;
        }

        // A batch whose first statement committed and whose second failed is written again
        // whole by the loop: the store then holds what one write of the batch holds.
        async fn a_half_written_sample_batch_written_again_is_stored_once(db: &str) {
            let store = Store::connect(db).await.unwrap();
            store.ensure_machine("m1", "table_bc", 0).await.unwrap();
            let spindle = |t_ns, rpm| Sample::Spindle { t_ns, rpm };
            let temp = |t_ns, celsius| Sample::Temperature {
                t_ns,
                sensor: "ambient".into(),
                celsius,
            };
            let batch = [spindle(60, 20000.0), temp(60, 20.5), spindle(120, 0.0), temp(120, 20.7)];
            // The spindle statement alone (the temperatures' failed), then the retry.
            store
                .add_samples("m1", &[batch[0].clone(), batch[2].clone()])
                .await
                .unwrap();
            store.add_samples("m1", &batch).await.unwrap();
            assert_eq!(store.samples("m1", 0, 1_000).await.unwrap(), batch.to_vec());
        }

        async fn verifications_round_trip_are_listed_by_reference_time_and_capped(db: &str) {
            use driftwatch_machine::verification::{ReferenceResult, compare};
            let store = Store::connect(db).await.unwrap();
            store.ensure_machine("m1", "table_bc", 0).await.unwrap();
            for (c, ok) in [(1, true), (2, false), (3, true)] {
                store
                    .open_cycle("m1", c, 900 + c, "warm-up", 1)
                    .await
                    .unwrap();
                store
                    .close_cycle("m1", &result(c, ok), 1_100)
                    .await
                    .unwrap();
            }
            // Accepted results only, by reference time (1001 and 1003).
            let setter = store
                .accepted_results_between("m1", 0, 1_002)
                .await
                .unwrap();
            assert_eq!(setter, vec![result(1, true)]);
            let setter = store
                .accepted_results_between("m1", 0, 5_000)
                .await
                .unwrap();
            assert_eq!(setter.iter().map(|r| r.cycle).collect::<Vec<_>>(), [1, 3]);
            let verify = |t_ns: i64, ez0b: f64| {
                let r = ReferenceResult {
                    instrument: "rtest".into(),
                    t_ns,
                    errors: [("EZ0B".to_string(), ez0b)].into(),
                    sigma: [("EZ0B".to_string(), 0.3)].into(),
                    frame_note: None,
                    source: Some("bench".into()),
                };
                compare("m1", &r, &setter, 10, 2.0).unwrap()
            };
            let a = verify(1_002, 12.5);
            assert_eq!(a.setter_cycles, vec![1, 3]);
            let b = verify(1_001, 20.0);
            assert!(b.exceeds_any);
            assert_eq!(
                store.add_verification(&a, 5, "operator", 10).await.unwrap(),
                1
            );
            assert_eq!(
                store.add_verification(&b, 6, "operator", 10).await.unwrap(),
                2
            );
            let list = store.verifications("m1", 0, i64::MAX, 100).await.unwrap();
            assert_eq!(list.iter().map(|v| v.id).collect::<Vec<_>>(), [1, 2]);
            assert_eq!(list[0].verification, a);
            assert_eq!(
                (list[1].created_ns, list[1].requested_by.as_str()),
                (6, "operator")
            );
            let list = store.verifications("m1", 1_001, 1_001, 100).await.unwrap();
            assert_eq!(list.len(), 1);
            assert_eq!(list[0].verification, b);
            assert_eq!(
                store
                    .verifications("m1", 0, i64::MAX, 1)
                    .await
                    .unwrap()
                    .len(),
                1
            );
            assert!(
                store
                    .verifications("m2", 0, i64::MAX, 100)
                    .await
                    .unwrap()
                    .is_empty()
            );
            // Kept: the newest `keep` by number; numbers are not given again.
            assert_eq!(
                store.add_verification(&a, 7, "operator", 1).await.unwrap(),
                3
            );
            let list = store.verifications("m1", 0, i64::MAX, 100).await.unwrap();
            assert_eq!(list.iter().map(|v| v.id).collect::<Vec<_>>(), [3]);
            // A machine that does not exist has no verification stored.
            let mut c = a.clone();
            c.machine_id = "nope".into();
            assert!(store.add_verification(&c, 8, "operator", 10).await.is_err());
        }
        async fn leases_give_a_machine_to_one_holder_at_a_time_and_fence_its_writes(db: &str) {
            let store = Store::connect(db).await.unwrap();
            store.ensure_machine("m1", "table_bc", 0).await.unwrap();
            let set = |version: i64, at: i64| NewCompensation {
                version,
                valid_from_ns: at,
                source: "measured",
                cycle: None,
                reason: "test",
                values: r#"{"errors":{},"sigma":{}}"#.into(),
            };
            let a = store
                .acquire_lease("m1", "a", Some("http://a:8080"), 60_000)
                .await
                .unwrap()
                .expect("a free machine is taken");
            assert_eq!(a.term, 1);
            // Held and unexpired: nobody else, not even twice by its holder.
            assert!(store.acquire_lease("m1", "b", None, 60_000).await.unwrap().is_none());
            assert!(store.acquire_lease("m1", "a", None, 60_000).await.unwrap().is_none());
            assert!(store.renew_lease(&a, 60_000).await.unwrap());
            let fa = store.fenced(&a);
            fa.open_cycle("m1", 1, 10, "warm-up", 1).await.unwrap();
            fa.insert_compensation("m1", &set(1, 10)).await.unwrap();
            // Expired (renewed for no time): a's writes are refused and nothing is written.
            assert!(store.renew_lease(&a, -1).await.unwrap());
            let refused = fa.insert_compensation("m1", &set(2, 20)).await.unwrap_err();
            assert!(matches!(refused, StoreError::LeaseLost { term: 1, .. }), "{refused}");
            assert!(matches!(
                fa.open_cycle("m1", 2, 20, "warm-up", 1).await,
                Err(StoreError::LeaseLost { .. })
            ));
            assert_eq!(store.open_cycles("m1").await.unwrap(), vec![1]);
            // b takes it over in a new term; a can no longer renew or write.
            let b = store
                .acquire_lease("m1", "b", None, 60_000)
                .await
                .unwrap()
                .expect("an expired lease is taken over");
            assert_eq!(b.term, 2);
            assert!(!store.renew_lease(&a, 60_000).await.unwrap());
            let fb = store.fenced(&b);
            fb.abandon_cycle("m1", 1, 30, "its holder stopped").await.unwrap();
            fb.insert_compensation("m1", &set(2, 30)).await.unwrap();
            let err = fa.abandon_cycle("m1", 1, 40, "late").await.unwrap_err();
            assert!(err.to_string().contains("held by 'b' in term 2"), "{err}");
            assert_eq!(store.leases().await.unwrap()[0].holder, "b");
            // Released: taken at once, in term 3.
            store.release_lease(&b).await.unwrap();
            let a3 = store.acquire_lease("m1", "a", None, 60_000).await.unwrap().unwrap();
            assert_eq!(a3.term, 3);
            let audit = store.lease_audit("m1").await.unwrap();
            assert_eq!(
                audit.terms.iter().map(|t| t.holder.as_str()).collect::<Vec<_>>(),
                ["a", "b", "a"]
            );
            assert!(audit.terms[1].released_ms.is_some());
            assert_eq!(audit.sets, vec![(1, 10, Some(1)), (2, 30, Some(2))]);
            assert_eq!(audit.cycles[0].3, Some(1));
            assert!(audit.problems().is_empty(), "{:?}", audit.problems());
            // The audit sees a breach: a set of an older term after a newer one.
            let mut bad = audit.clone();
            bad.sets.push((3, 40, Some(1)));
            assert_eq!(bad.problems().len(), 1, "{:?}", bad.problems());
            // A fleet's clock is set by its first process and followed by the others.
            let t = store.fleet_clock_now(1_000_000_000_000, 60.0).await.unwrap();
            let u = store.fleet_clock_now(5, 60.0).await.unwrap();
            assert!(t >= 1_000_000_000_000 && u >= t && u - t < 60 * 10_000_000_000, "{t} {u}");
            assert!(matches!(
                store.fleet_clock_now(5, 1.0).await,
                Err(StoreError::Fleet(_))
            ));
        }
    }
}
