//! Storage of the service: SQLite through sqlx, schema in `migrations/` (embedded, applied at
//! open), WAL with synchronous NORMAL, foreign keys on. Runtime queries in portable SQL.
//! Shell code, with `recorder` and `recording::mcap_io` the only modules that touch files.

use std::collections::BTreeMap;
use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

use serde::Serialize;
use serde_json::Value;
use sqlx::Row;
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use thiserror::Error;

use driftwatch_core::recording::{CycleResultMsg, ResultStatus};
use driftwatch_machine::alerts::{EventKind, Severity};

/// A cycle's state in the `cycles` table (stored as its lowercase name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, sqlx::Type, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
#[sqlx(rename_all = "lowercase")]
pub enum CycleStatus {
    /// Started, no result yet (or left by a crash until the restart abandons it).
    Open,
    /// Solved and validated.
    Ok,
    /// Closed with a result that failed validation.
    Rejected,
    /// Closed without a result (a crash, a stop, a timeout).
    Abandoned,
}

impl std::fmt::Display for CycleStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            CycleStatus::Open => "open",
            CycleStatus::Ok => "ok",
            CycleStatus::Rejected => "rejected",
            CycleStatus::Abandoned => "abandoned",
        })
    }
}

impl From<ResultStatus> for CycleStatus {
    fn from(s: ResultStatus) -> Self {
        match s {
            ResultStatus::Ok => CycleStatus::Ok,
            ResultStatus::Rejected => CycleStatus::Rejected,
        }
    }
}

/// How a diagnosis run ended (stored as its lowercase name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, sqlx::Type, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
#[sqlx(rename_all = "lowercase")]
pub enum DiagnosisStatus {
    Done,
    Failed,
}

/// An MCAP file's state in the `mcap_files` table (stored as its lowercase name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, sqlx::Type)]
#[serde(rename_all = "lowercase")]
#[sqlx(rename_all = "lowercase")]
pub enum FileStatus {
    /// Being written (`.partial`).
    Open,
    /// Finished and renamed.
    Closed,
    /// Rescued up to its last flush after a crash.
    Recovered,
}

/// What happened to an alert (stored as its lowercase name): the engine's events and the
/// operator's acknowledgement.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, sqlx::Type, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
#[sqlx(rename_all = "lowercase")]
pub enum AlertEventKind {
    Raised,
    Updated,
    Resolved,
    Acknowledged,
}

impl From<EventKind> for AlertEventKind {
    fn from(k: EventKind) -> Self {
        match k {
            EventKind::Raised => AlertEventKind::Raised,
            EventKind::Updated => AlertEventKind::Updated,
            EventKind::Resolved => AlertEventKind::Resolved,
        }
    }
}

/// An alert's severity as stored (the engine's [`Severity`], lowercase; an acknowledgement
/// has none and stores the empty string, as rows written before this type did).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum AlertSeverity {
    Warning,
    Critical,
}

impl AlertSeverity {
    fn column(s: Option<AlertSeverity>) -> &'static str {
        match s {
            None => "",
            Some(AlertSeverity::Warning) => "warning",
            Some(AlertSeverity::Critical) => "critical",
        }
    }

    fn of_column(s: &str) -> Result<Option<AlertSeverity>, StoreError> {
        match s {
            "" => Ok(None),
            "warning" => Ok(Some(AlertSeverity::Warning)),
            "critical" => Ok(Some(AlertSeverity::Critical)),
            other => Err(StoreError::Corrupt(format!(
                "alert severity '{other}' is none of warning, critical"
            ))),
        }
    }
}

/// An alert event to store.
#[derive(Debug, Clone)]
pub struct NewAlertEvent<'a> {
    pub alert: i64,
    pub t_ns: i64,
    pub kind: AlertEventKind,
    pub rule: &'a str,
    /// None for an acknowledgement.
    pub severity: Option<AlertSeverity>,
    pub message: &'a str,
    pub value: Option<f64>,
}

impl From<Severity> for AlertSeverity {
    fn from(s: Severity) -> Self {
        match s {
            Severity::Warning => AlertSeverity::Warning,
            Severity::Critical => AlertSeverity::Critical,
        }
    }
}

#[derive(Debug, Error)]
pub enum StoreError {
    #[error("cannot open database {path}: {source}")]
    Open { path: String, source: sqlx::Error },
    #[error("cannot apply the database migrations: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error("database: {0}")]
    Sql(#[from] sqlx::Error),
    #[error("stored JSON: {0}")]
    Json(#[from] serde_json::Error),
    #[error("stored value: {0}")]
    Corrupt(String),
}

async fn insert_set(
    conn: &mut sqlx::SqliteConnection,
    machine: &str,
    c: &NewCompensation<'_>,
) -> Result<(), StoreError> {
    sqlx::query(
        "INSERT INTO compensation_sets (machine_id, version, valid_from_ns, source, cycle, reason, payload)
         VALUES ($1, $2, $3, $4, $5, $6, $7)",
    )
    .bind(machine)
    .bind(c.version)
    .bind(c.valid_from_ns)
    .bind(c.source)
    .bind(c.cycle)
    .bind(c.reason)
    .bind(&c.values)
    .execute(&mut *conn)
    .await?;
    Ok(())
}

/// A diagnosis run's columns 0-6 (id .. summary) as JSON.
/// A diagnosis run as stored, without its result.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct DiagnosisRow {
    pub id: i64,
    pub requested_ns: i64,
    /// The token holder who asked.
    pub requested_by: String,
    pub from_ns: i64,
    pub to_ns: i64,
    pub status: DiagnosisStatus,
    pub summary: String,
}

/// A diagnosis run with its result (the `diagnosis.json` layout; none when it failed).
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct StoredDiagnosis {
    #[serde(flatten)]
    pub row: DiagnosisRow,
    #[schema(value_type = Option<Object>)]
    pub result: Option<Value>,
}

/// An alert event as stored.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct AlertEventRow {
    pub alert: i64,
    pub seq: i64,
    pub t_ns: i64,
    pub kind: AlertEventKind,
    pub rule: String,
    /// None for an acknowledgement.
    pub severity: Option<AlertSeverity>,
    pub message: String,
    pub value: Option<f64>,
}

fn diagnosis_row(r: &sqlx::sqlite::SqliteRow) -> Result<DiagnosisRow, StoreError> {
    Ok(DiagnosisRow {
        id: r.try_get(0)?,
        requested_ns: r.try_get(1)?,
        requested_by: r.try_get(2)?,
        from_ns: r.try_get(3)?,
        to_ns: r.try_get(4)?,
        status: r.try_get(5)?,
        summary: r.try_get(6)?,
    })
}

fn cycle_row(r: &sqlx::sqlite::SqliteRow) -> Result<CycleRow, StoreError> {
    Ok(CycleRow {
        cycle: r.try_get(0)?,
        started_ns: r.try_get(1)?,
        trigger: r.try_get(2)?,
        attempt: r.try_get(3)?,
        status: r.try_get(4)?,
        finished_ns: r.try_get(5)?,
        reason: r.try_get(6)?,
    })
}

/// A compensation set to store with the cycle that produced it.
pub struct NewCompensation<'a> {
    pub version: i64,
    pub valid_from_ns: i64,
    pub source: &'a str,
    pub cycle: Option<i64>,
    pub reason: &'a str,
    /// `{"errors": {...}, "sigma": {...}}`: all of the set that the columns do not hold and
    /// that cannot be derived (the offsets are computed from the errors when read).
    pub values: String,
}

impl<'a> NewCompensation<'a> {
    /// The row of `set`.
    pub fn of(set: &'a driftwatch_machine::compensation::CompensationSet) -> Self {
        NewCompensation {
            version: set.version as i64,
            valid_from_ns: set.valid_from_ns,
            source: match set.source {
                driftwatch_machine::compensation::Source::Measured => "measured",
                driftwatch_machine::compensation::Source::Predicted => "predicted",
            },
            cycle: set.cycle,
            reason: &set.reason,
            values: serde_json::json!({"errors": set.errors, "sigma": set.sigma}).to_string(),
        }
    }
}

/// A cycle as stored.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct CycleRow {
    pub cycle: i64,
    pub started_ns: i64,
    pub trigger: String,
    pub attempt: i64,
    pub status: CycleStatus,
    pub finished_ns: Option<i64>,
    pub reason: Option<String>,
}

pub use driftwatch_core::series::ErrorSample;

/// One detection as received: its time, step label and contract JSON.
#[derive(Debug, Clone)]
pub struct DetectionRow<'a> {
    pub t_ns: i64,
    pub step: &'a str,
    pub payload: String,
}

/// A diagnosis run to store.
pub struct NewDiagnosis<'a> {
    pub machine: &'a str,
    pub requested_ns: i64,
    pub requested_by: &'a str,
    pub from_ns: i64,
    pub to_ns: i64,
    pub status: DiagnosisStatus,
    pub summary: &'a str,
    pub result: Option<&'a str>,
}

/// One sample of a per-minute series.
#[derive(Debug, Clone, PartialEq)]
pub enum Sample {
    Spindle {
        t_ns: i64,
        rpm: f64,
    },
    Temperature {
        t_ns: i64,
        sensor: String,
        celsius: f64,
    },
}

impl Sample {
    pub fn t_ns(&self) -> i64 {
        match self {
            Sample::Spindle { t_ns, .. } | Sample::Temperature { t_ns, .. } => *t_ns,
        }
    }
}

#[derive(Clone)]
pub struct Store {
    pool: SqlitePool,
}

impl Store {
    /// Open (creating if needed) the database file and apply the migrations.
    pub async fn open(path: &Path) -> Result<Self, StoreError> {
        let url = format!("sqlite://{}", path.display());
        let opts = SqliteConnectOptions::from_str(&url)
            .map_err(|source| StoreError::Open {
                path: path.display().to_string(),
                source,
            })?
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            // NORMAL in WAL mode never corrupts and keeps every commit through a process crash;
            // only a power loss can take the last commits.
            .synchronous(SqliteSynchronous::Normal)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(5));
        let pool = SqlitePoolOptions::new()
            .max_connections(4)
            .connect_with(opts)
            .await
            .map_err(|source| StoreError::Open {
                path: path.display().to_string(),
                source,
            })?;
        sqlx::migrate!("../../migrations").run(&pool).await?;
        Ok(Store { pool })
    }

    /// `PRAGMA integrity_check`: "ok" for a sound database.
    pub async fn integrity_check(&self) -> Result<String, StoreError> {
        let row = sqlx::query("PRAGMA integrity_check")
            .fetch_one(&self.pool)
            .await?;
        Ok(row.try_get::<String, _>(0)?)
    }

    pub async fn journal_mode(&self) -> Result<String, StoreError> {
        let row = sqlx::query("PRAGMA journal_mode")
            .fetch_one(&self.pool)
            .await?;
        Ok(row.try_get::<String, _>(0)?)
    }

    pub async fn close(&self) {
        self.pool.close().await;
    }

    pub async fn ensure_machine(
        &self,
        id: &str,
        kinematics: &str,
        now_ns: i64,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO machines (id, kinematics, created_ns) VALUES ($1, $2, $3)
             ON CONFLICT (id) DO UPDATE SET kinematics = excluded.kinematics",
        )
        .bind(id)
        .bind(kinematics)
        .bind(now_ns)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// The number the next cycle of a machine gets (1 for the first).
    pub async fn next_cycle_number(&self, machine: &str) -> Result<i64, StoreError> {
        let row =
            sqlx::query("SELECT COALESCE(MAX(cycle), 0) + 1 FROM cycles WHERE machine_id = $1")
                .bind(machine)
                .fetch_one(&self.pool)
                .await?;
        Ok(row.try_get::<i64, _>(0)?)
    }

    pub async fn open_cycle(
        &self,
        machine: &str,
        cycle: i64,
        started_ns: i64,
        trigger: &str,
        attempt: i64,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO cycles (machine_id, cycle, started_ns, trigger, attempt, status)
             VALUES ($1, $2, $3, $4, $5, $6)",
        )
        .bind(machine)
        .bind(cycle)
        .bind(started_ns)
        .bind(trigger)
        .bind(attempt)
        .bind(CycleStatus::Open)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Store a cycle's detections in arrival order (`seq` 0, 1, ...), in one statement.
    pub async fn add_detections(
        &self,
        machine: &str,
        cycle: i64,
        rows: &[DetectionRow<'_>],
    ) -> Result<(), StoreError> {
        let numbered: Vec<(i64, &DetectionRow)> = rows
            .iter()
            .enumerate()
            .map(|(i, r)| (i as i64, r))
            .collect();
        for chunk in numbered.chunks(1000) {
            let mut q = sqlx::QueryBuilder::new(
                "INSERT INTO detections (machine_id, cycle, seq, t_ns, step, payload) ",
            );
            q.push_values(chunk, |mut b, (seq, r)| {
                b.push_bind(machine)
                    .push_bind(cycle)
                    .push_bind(*seq)
                    .push_bind(r.t_ns)
                    .push_bind(r.step)
                    .push_bind(r.payload.as_str());
            });
            q.build().execute(&self.pool).await?;
        }
        Ok(())
    }

    /// Close a cycle with its result, in one transaction: the cycle's status, the result and
    /// one row per error.
    pub async fn close_cycle(
        &self,
        machine: &str,
        result: &CycleResultMsg,
        finished_ns: i64,
    ) -> Result<(), StoreError> {
        self.close_cycle_with(machine, result, finished_ns, None)
            .await
    }

    /// Close a cycle and, when it produced one, store its compensation set in the same
    /// transaction: a crash leaves either both or neither.
    pub async fn close_cycle_with(
        &self,
        machine: &str,
        result: &CycleResultMsg,
        finished_ns: i64,
        compensation: Option<&NewCompensation<'_>>,
    ) -> Result<(), StoreError> {
        let status = CycleStatus::from(result.status);
        let payload = serde_json::to_string(result)?;
        let mut tx = self.pool.begin().await?;
        sqlx::query(
            "UPDATE cycles SET status = $3, finished_ns = $4, reason = $5
             WHERE machine_id = $1 AND cycle = $2",
        )
        .bind(machine)
        .bind(result.cycle)
        .bind(status)
        .bind(finished_ns)
        .bind(result.reason.as_deref())
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "INSERT INTO results (machine_id, cycle, t_ns, status, reason, residual_rms_um, chi2, dof, payload)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9)",
        )
        .bind(machine)
        .bind(result.cycle)
        .bind(result.t_ns)
        .bind(status)
        .bind(result.reason.as_deref())
        .bind(result.residual_rms_um)
        .bind(result.chi2)
        .bind(result.dof.map(|d| d as i64))
        .bind(&payload)
        .execute(&mut *tx)
        .await?;
        if let (Some(errors), Some(sigma)) = (&result.errors, &result.sigma) {
            for (name, value) in errors {
                sqlx::query(
                    "INSERT INTO result_values (machine_id, cycle, name, t_ns, value, sigma)
                     VALUES ($1, $2, $3, $4, $5, $6)",
                )
                .bind(machine)
                .bind(result.cycle)
                .bind(name)
                .bind(result.t_ns)
                .bind(value)
                .bind(sigma.get(name).copied().unwrap_or(f64::NAN))
                .execute(&mut *tx)
                .await?;
            }
        }
        if let Some(c) = compensation {
            insert_set(&mut tx, machine, c).await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// The last cycle of a machine that has a result, if any.
    pub async fn last_closed_cycle(&self, machine: &str) -> Result<Option<i64>, StoreError> {
        let row = sqlx::query("SELECT MAX(cycle) FROM results WHERE machine_id = $1")
            .bind(machine)
            .fetch_one(&self.pool)
            .await?;
        Ok(row.try_get::<Option<i64>, _>(0)?)
    }

    /// When the last cycle started and when the last good (`ok`) cycle finished: what the
    /// scheduler remembers across a restart.
    pub async fn schedule_memory(
        &self,
        machine: &str,
    ) -> Result<(Option<i64>, Option<i64>), StoreError> {
        let row = sqlx::query(
            "SELECT MAX(started_ns),
                    MAX(CASE WHEN status = $2 THEN finished_ns END)
             FROM cycles WHERE machine_id = $1",
        )
        .bind(machine)
        .bind(CycleStatus::Ok)
        .fetch_one(&self.pool)
        .await?;
        Ok((row.try_get(0)?, row.try_get(1)?))
    }

    pub async fn abandon_cycle(
        &self,
        machine: &str,
        cycle: i64,
        now_ns: i64,
        reason: &str,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "UPDATE cycles SET status = $5, finished_ns = $3, reason = $4
             WHERE machine_id = $1 AND cycle = $2 AND status = $6",
        )
        .bind(machine)
        .bind(cycle)
        .bind(now_ns)
        .bind(reason)
        .bind(CycleStatus::Abandoned)
        .bind(CycleStatus::Open)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Cycles still open (left by a crash), oldest first.
    pub async fn open_cycles(&self, machine: &str) -> Result<Vec<i64>, StoreError> {
        let rows = sqlx::query(
            "SELECT cycle FROM cycles WHERE machine_id = $1 AND status = $2 ORDER BY cycle",
        )
        .bind(machine)
        .bind(CycleStatus::Open)
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(|r| Ok(r.try_get::<i64, _>(0)?)).collect()
    }

    /// A machine's cycles, newest first: at most `limit`, numbered below `before` if given
    /// (the next page starts before the last number of this one).
    pub async fn cycles(
        &self,
        machine: &str,
        limit: i64,
        before: Option<i64>,
    ) -> Result<Vec<CycleRow>, StoreError> {
        let rows = sqlx::query(
            "SELECT cycle, started_ns, trigger, attempt, status, finished_ns, reason FROM cycles
             WHERE machine_id = $1 AND cycle < $3 ORDER BY cycle DESC LIMIT $2",
        )
        .bind(machine)
        .bind(limit)
        .bind(before.unwrap_or(i64::MAX))
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(cycle_row).collect()
    }

    /// One cycle of a machine, if it exists.
    pub async fn cycle(&self, machine: &str, cycle: i64) -> Result<Option<CycleRow>, StoreError> {
        let row = sqlx::query(
            "SELECT cycle, started_ns, trigger, attempt, status, finished_ns, reason FROM cycles
             WHERE machine_id = $1 AND cycle = $2",
        )
        .bind(machine)
        .bind(cycle)
        .fetch_optional(&self.pool)
        .await?;
        row.as_ref().map(cycle_row).transpose()
    }

    /// The detections of a cycle as received, in order.
    pub async fn detections(
        &self,
        machine: &str,
        cycle: i64,
    ) -> Result<Vec<(i64, Value)>, StoreError> {
        let rows = sqlx::query(
            "SELECT t_ns, payload FROM detections WHERE machine_id = $1 AND cycle = $2 ORDER BY seq",
        )
        .bind(machine)
        .bind(cycle)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                let text: String = r.try_get(1)?;
                Ok((r.try_get(0)?, serde_json::from_str(&text)?))
            })
            .collect()
    }

    pub async fn result(
        &self,
        machine: &str,
        cycle: i64,
    ) -> Result<Option<CycleResultMsg>, StoreError> {
        let row = sqlx::query("SELECT payload FROM results WHERE machine_id = $1 AND cycle = $2")
            .bind(machine)
            .bind(cycle)
            .fetch_optional(&self.pool)
            .await?;
        match row {
            Some(r) => Ok(Some(serde_json::from_str(&r.try_get::<String, _>(0)?)?)),
            None => Ok(None),
        }
    }

    /// Validated error values between two times, oldest first: the measured values of `ok`
    /// cycles and, with `predicted`, the values of every predicted set the service served.
    pub async fn error_series(
        &self,
        machine: &str,
        from_ns: i64,
        to_ns: i64,
        measured: bool,
        predicted: bool,
    ) -> Result<Vec<ErrorSample>, StoreError> {
        let mut out = Vec::new();
        if measured {
            let rows = sqlx::query(
                "SELECT v.t_ns, v.cycle, v.name, v.value, v.sigma FROM result_values v
                 JOIN results r ON r.machine_id = v.machine_id AND r.cycle = v.cycle
                 WHERE v.machine_id = $1 AND v.t_ns >= $2 AND v.t_ns <= $3 AND r.status = $4
                 ORDER BY v.t_ns, v.name",
            )
            .bind(machine)
            .bind(from_ns)
            .bind(to_ns)
            .bind(CycleStatus::Ok)
            .fetch_all(&self.pool)
            .await?;
            for r in &rows {
                out.push(ErrorSample {
                    t_ns: r.try_get(0)?,
                    cycle: r.try_get(1)?,
                    name: r.try_get(2)?,
                    value: r.try_get(3)?,
                    sigma: r.try_get(4)?,
                    source: "measured".into(),
                });
            }
        }
        if predicted {
            let rows = sqlx::query(
                "SELECT valid_from_ns, cycle, payload FROM compensation_sets
                 WHERE machine_id = $1 AND source = 'predicted'
                   AND valid_from_ns >= $2 AND valid_from_ns <= $3
                 ORDER BY valid_from_ns",
            )
            .bind(machine)
            .bind(from_ns)
            .bind(to_ns)
            .fetch_all(&self.pool)
            .await?;
            for r in &rows {
                let t_ns: i64 = r.try_get(0)?;
                let cycle: Option<i64> = r.try_get(1)?;
                let payload: String = r.try_get(2)?;
                let v: Value = serde_json::from_str(&payload)?;
                let (Some(errors), sigma) = (v["errors"].as_object(), &v["sigma"]) else {
                    continue;
                };
                for (name, value) in errors {
                    if let Some(value) = value.as_f64() {
                        out.push(ErrorSample {
                            t_ns,
                            cycle: cycle.unwrap_or(0),
                            name: name.clone(),
                            value,
                            sigma: sigma[name].as_f64().unwrap_or(f64::NAN),
                            source: "predicted".into(),
                        });
                    }
                }
            }
        }
        out.sort_by(|a, b| a.t_ns.cmp(&b.t_ns).then_with(|| a.name.cmp(&b.name)));
        Ok(out)
    }

    /// Store a new compensation set; versions must increase (the primary key refuses a
    /// repeated version).
    pub async fn insert_compensation(
        &self,
        machine: &str,
        c: &NewCompensation<'_>,
    ) -> Result<(), StoreError> {
        // One statement commits on its own: no transaction round trips for the predicted sets
        // that go out every few minutes.
        let mut conn = self.pool.acquire().await?;
        insert_set(&mut conn, machine, c).await
    }

    /// Every compensation set of a machine, oldest first: (version, source, cycle).
    pub async fn compensation_versions(
        &self,
        machine: &str,
    ) -> Result<Vec<(i64, String, Option<i64>)>, StoreError> {
        let rows = sqlx::query(
            "SELECT version, source, cycle FROM compensation_sets WHERE machine_id = $1
             ORDER BY version",
        )
        .bind(machine)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| Ok((r.try_get(0)?, r.try_get(1)?, r.try_get(2)?)))
            .collect()
    }

    /// The newest compensation set of a machine.
    pub async fn latest_compensation(
        &self,
        machine: &str,
    ) -> Result<Option<driftwatch_machine::compensation::CompensationSet>, StoreError> {
        self.latest_set(machine, None).await
    }

    /// The newest measured compensation set of a machine, with the values its cycle measured
    /// (the set itself may have been ramped towards them from a predicted one): what the next
    /// cycle's step is checked against.
    pub async fn latest_measurement(
        &self,
        machine: &str,
    ) -> Result<Option<driftwatch_machine::compensation::CompensationSet>, StoreError> {
        let Some(mut set) = self.latest_set(machine, Some("measured")).await? else {
            return Ok(None);
        };
        if let Some(c) = set.cycle
            && let Some(r) = self.result(machine, c).await?
            && let (Some(e), Some(s)) = (r.errors, r.sigma)
        {
            set.offsets = driftwatch_machine::compensation::offsets(&e);
            set.errors = e;
            set.sigma = s;
        }
        Ok(Some(set))
    }

    async fn latest_set(
        &self,
        machine: &str,
        source: Option<&str>,
    ) -> Result<Option<driftwatch_machine::compensation::CompensationSet>, StoreError> {
        use driftwatch_machine::compensation::{CompensationSet, Source, offsets};
        let row = sqlx::query(
            "SELECT version, valid_from_ns, source, cycle, reason, payload FROM compensation_sets
             WHERE machine_id = $1 AND ($2 IS NULL OR source = $2)
             ORDER BY version DESC LIMIT 1",
        )
        .bind(machine)
        .bind(source)
        .fetch_optional(&self.pool)
        .await?;
        let Some(r) = row else {
            return Ok(None);
        };
        #[derive(serde::Deserialize)]
        struct Values {
            errors: BTreeMap<String, f64>,
            sigma: BTreeMap<String, f64>,
        }
        let v: Values = serde_json::from_str(&r.try_get::<String, _>(5)?)?;
        let version: i64 = r.try_get(0)?;
        let source: String = r.try_get(2)?;
        Ok(Some(CompensationSet {
            version: version.max(0) as u64,
            valid_from_ns: r.try_get(1)?,
            source: if source == "predicted" {
                Source::Predicted
            } else {
                Source::Measured
            },
            cycle: r.try_get(3)?,
            offsets: offsets(&v.errors),
            errors: v.errors,
            sigma: v.sigma,
            reason: r.try_get(4)?,
        }))
    }

    pub async fn add_alert_event(
        &self,
        machine: &str,
        ev: &NewAlertEvent<'_>,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO alert_events (machine_id, alert_id, seq, t_ns, kind, rule, severity, message, value)
             VALUES ($1, $2, (SELECT COALESCE(MAX(seq), 0) + 1 FROM alert_events WHERE machine_id = $1 AND alert_id = $2),
                     $3, $4, $5, $6, $7, $8)",
        )
        .bind(machine)
        .bind(ev.alert)
        .bind(ev.t_ns)
        .bind(ev.kind)
        .bind(ev.rule)
        .bind(AlertSeverity::column(ev.severity))
        .bind(ev.message)
        .bind(ev.value)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Alert events of a machine, newest first.
    /// A machine's alert events, newest first: at most `limit`, before the cursor `(t_ns,
    /// alert, seq)` of the last event of the previous page if given.
    pub async fn alert_events(
        &self,
        machine: &str,
        limit: i64,
        before: Option<(i64, i64, i64)>,
    ) -> Result<Vec<AlertEventRow>, StoreError> {
        let (t, a, q) = before.unwrap_or((i64::MAX, i64::MAX, i64::MAX));
        let rows = sqlx::query(
            "SELECT alert_id, seq, t_ns, kind, rule, severity, message, value FROM alert_events
             WHERE machine_id = $1 AND (t_ns, alert_id, seq) < ($3, $4, $5)
             ORDER BY t_ns DESC, alert_id DESC, seq DESC LIMIT $2",
        )
        .bind(machine)
        .bind(limit)
        .bind(t)
        .bind(a)
        .bind(q)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(AlertEventRow {
                    alert: r.try_get(0)?,
                    seq: r.try_get(1)?,
                    t_ns: r.try_get(2)?,
                    kind: r.try_get(3)?,
                    rule: r.try_get(4)?,
                    severity: AlertSeverity::of_column(r.try_get::<&str, _>(5)?)?,
                    message: r.try_get(6)?,
                    value: r.try_get(7)?,
                })
            })
            .collect()
    }

    /// Store a batch of spindle and temperature samples in one transaction (one commit
    /// instead of one per sample: the per-minute series are most of the service's writes).
    pub async fn add_samples(&self, machine: &str, rows: &[Sample]) -> Result<(), StoreError> {
        if rows.is_empty() {
            return Ok(());
        }
        // One multi-row statement per table; a repeated key keeps its last value (PostgreSQL
        // refuses to update one row twice in one statement).
        let mut spindle = BTreeMap::new();
        let mut temps = BTreeMap::new();
        for r in rows {
            match r {
                Sample::Spindle { t_ns, rpm } => {
                    spindle.insert(*t_ns, *rpm);
                }
                Sample::Temperature {
                    t_ns,
                    sensor,
                    celsius,
                } => {
                    temps.insert((sensor.as_str(), *t_ns), *celsius);
                }
            }
        }
        let mut tx = self.pool.begin().await?;
        // SQLite allows 32766 bound values per statement: chunks of 1000 rows stay far below.
        let spindle: Vec<_> = spindle.into_iter().collect();
        for chunk in spindle.chunks(1000) {
            let mut q =
                sqlx::QueryBuilder::new("INSERT INTO spindle_samples (machine_id, t_ns, rpm) ");
            q.push_values(chunk, |mut b, (t, rpm)| {
                b.push_bind(machine).push_bind(*t).push_bind(*rpm);
            });
            q.push(" ON CONFLICT (machine_id, t_ns) DO UPDATE SET rpm = excluded.rpm");
            q.build().execute(&mut *tx).await?;
        }
        let temps: Vec<_> = temps.into_iter().collect();
        for chunk in temps.chunks(1000) {
            let mut q = sqlx::QueryBuilder::new(
                "INSERT INTO temperature_samples (machine_id, t_ns, sensor, celsius) ",
            );
            q.push_values(chunk, |mut b, ((sensor, t), c)| {
                b.push_bind(machine)
                    .push_bind(*t)
                    .push_bind(*sensor)
                    .push_bind(*c);
            });
            q.push(
                " ON CONFLICT (machine_id, sensor, t_ns) DO UPDATE SET celsius = excluded.celsius",
            );
            q.build().execute(&mut *tx).await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// The stored spindle and temperature samples in `[from_ns, to_ns]`, in time order
    /// (spindle before temperature at the same time).
    pub async fn samples(
        &self,
        machine: &str,
        from_ns: i64,
        to_ns: i64,
    ) -> Result<Vec<Sample>, StoreError> {
        let rows = sqlx::query(
            "SELECT t_ns, NULL AS sensor, rpm AS value FROM spindle_samples
               WHERE machine_id = $1 AND t_ns >= $2 AND t_ns <= $3
             UNION ALL
             SELECT t_ns, sensor, celsius AS value FROM temperature_samples
               WHERE machine_id = $1 AND t_ns >= $2 AND t_ns <= $3
             ORDER BY t_ns, sensor NULLS FIRST",
        )
        .bind(machine)
        .bind(from_ns)
        .bind(to_ns)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                let t_ns: i64 = r.try_get(0)?;
                let sensor: Option<String> = r.try_get(1)?;
                let value: f64 = r.try_get(2)?;
                Ok(match sensor {
                    None => Sample::Spindle { t_ns, rpm: value },
                    Some(sensor) => Sample::Temperature {
                        t_ns,
                        sensor,
                        celsius: value,
                    },
                })
            })
            .collect()
    }

    pub async fn mcap_file_opened(
        &self,
        machine: &str,
        path: &str,
        opened_ns: i64,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO mcap_files (machine_id, path, opened_ns, status) VALUES ($1, $2, $3, $4)
             ON CONFLICT (path) DO UPDATE SET status = $4, closed_ns = NULL",
        )
        .bind(machine)
        .bind(path)
        .bind(opened_ns)
        .bind(FileStatus::Open)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Mark a file written as `partial` closed under `path` (`closed`), or rescued from a
    /// crash (`recovered`).
    pub async fn mcap_file_closed(
        &self,
        machine: &str,
        partial: &str,
        path: &str,
        closed_ns: i64,
        status: FileStatus,
        messages: i64,
    ) -> Result<(), StoreError> {
        let mut tx = self.pool.begin().await?;
        sqlx::query(
            "INSERT INTO mcap_files (machine_id, path, opened_ns, status) VALUES ($1, $2, $3, $4)
             ON CONFLICT (path) DO NOTHING",
        )
        .bind(machine)
        .bind(partial)
        .bind(closed_ns)
        .bind(FileStatus::Open)
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "UPDATE mcap_files SET path = $2, closed_ns = $3, status = $4, messages = $5 WHERE path = $1",
        )
        .bind(partial)
        .bind(path)
        .bind(closed_ns)
        .bind(status)
        .bind(messages)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// Every stored detection of the cycles with a detection in `[from_ns, to_ns]` (whole
    /// cycles, so a window edge never leaves a partial one), in time order: `(t_ns, payload)`.
    pub async fn detections_between(
        &self,
        machine: &str,
        from_ns: i64,
        to_ns: i64,
    ) -> Result<Vec<(i64, String)>, StoreError> {
        let rows = sqlx::query(
            "SELECT t_ns, payload FROM detections WHERE machine_id = $1 AND cycle IN
               (SELECT DISTINCT cycle FROM detections WHERE machine_id = $1 AND t_ns >= $2 AND t_ns <= $3)
             ORDER BY t_ns, cycle, seq",
        )
        .bind(machine)
        .bind(from_ns)
        .bind(to_ns)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| Ok((r.try_get(0)?, r.try_get(1)?)))
            .collect()
    }

    /// Store a diagnosis run (its result JSON when it succeeded) and keep only the machine's
    /// newest `keep` (at least 1: numbers are never given twice); returns its number.
    pub async fn add_diagnosis(&self, d: &NewDiagnosis<'_>, keep: i64) -> Result<i64, StoreError> {
        // One statement: the number and the row together, whatever else writes meanwhile.
        let id: i64 = sqlx::query_scalar(
            "INSERT INTO diagnoses (machine_id, id, requested_ns, requested_by, from_ns, to_ns, status, summary, result)
             VALUES ($1, (SELECT COALESCE(MAX(id), 0) + 1 FROM diagnoses WHERE machine_id = $1),
                     $2, $3, $4, $5, $6, $7, $8)
             RETURNING id",
        )
        .bind(d.machine)
        .bind(d.requested_ns)
        .bind(d.requested_by)
        .bind(d.from_ns)
        .bind(d.to_ns)
        .bind(d.status)
        .bind(d.summary)
        .bind(d.result)
        .fetch_one(&self.pool)
        .await?;
        sqlx::query("DELETE FROM diagnoses WHERE machine_id = $1 AND id <= $2")
            .bind(d.machine)
            .bind(id - keep.max(1))
            .execute(&self.pool)
            .await?;
        Ok(id)
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
            )",
        )
        .bind(machine)
        .fetch_one(&self.pool)
        .await?;
        Ok(t)
    }

    /// The time of the machine's last stored detection.
    pub async fn last_detection_ns(&self, machine: &str) -> Result<Option<i64>, StoreError> {
        Ok(
            sqlx::query_scalar("SELECT MAX(t_ns) FROM detections WHERE machine_id = $1")
                .bind(machine)
                .fetch_one(&self.pool)
                .await?,
        )
    }

    /// The diagnosis runs of a machine, newest first, without their results: at most `limit`,
    /// numbered below `before` if given.
    pub async fn diagnoses(
        &self,
        machine: &str,
        limit: i64,
        before: Option<i64>,
    ) -> Result<Vec<DiagnosisRow>, StoreError> {
        let rows = sqlx::query(
            "SELECT id, requested_ns, requested_by, from_ns, to_ns, status, summary FROM diagnoses
             WHERE machine_id = $1 AND id < $3 ORDER BY id DESC LIMIT $2",
        )
        .bind(machine)
        .bind(limit)
        .bind(before.unwrap_or(i64::MAX))
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(diagnosis_row).collect()
    }

    /// One diagnosis run with its result.
    pub async fn diagnosis(
        &self,
        machine: &str,
        id: i64,
    ) -> Result<Option<StoredDiagnosis>, StoreError> {
        let row = sqlx::query(
            "SELECT id, requested_ns, requested_by, from_ns, to_ns, status, summary, result FROM diagnoses
             WHERE machine_id = $1 AND id = $2",
        )
        .bind(machine)
        .bind(id)
        .fetch_optional(&self.pool)
        .await?;
        let Some(r) = row else { return Ok(None) };
        let result: Option<String> = r.try_get(7)?;
        Ok(Some(StoredDiagnosis {
            row: diagnosis_row(&r)?,
            result: result
                .map(|t| serde_json::from_str::<Value>(&t))
                .transpose()?,
        }))
    }

    /// (path, status) of every MCAP file of a machine, oldest first.
    pub async fn mcap_files(&self, machine: &str) -> Result<Vec<(String, FileStatus)>, StoreError> {
        let rows = sqlx::query(
            "SELECT path, status FROM mcap_files WHERE machine_id = $1 ORDER BY opened_ns",
        )
        .bind(machine)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| Ok((r.try_get(0)?, r.try_get(1)?)))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn temp_db(name: &str) -> std::path::PathBuf {
        let dir =
            std::env::temp_dir().join(format!("driftwatch-store-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir.join("driftwatch.db")
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
            notes: None,
        }
    }

    #[tokio::test]
    async fn a_cycle_round_trips_with_its_detections_result_and_series() {
        let store = Store::open(&temp_db("cycle")).await.unwrap();
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
        assert_eq!(store.integrity_check().await.unwrap(), "ok");
    }

    #[tokio::test]
    async fn foreign_keys_and_versions_are_enforced() {
        let store = Store::open(&temp_db("fk")).await.unwrap();
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
        assert_eq!(latest.offsets["B_pivot_z_um"], 1.0);
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

    #[tokio::test]
    async fn data_survives_reopening() {
        let path = temp_db("reopen");
        {
            let store = Store::open(&path).await.unwrap();
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
        let store = Store::open(&path).await.unwrap();
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
        assert_eq!(store.integrity_check().await.unwrap(), "ok");
    }
}
