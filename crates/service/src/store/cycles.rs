//! Cycles: their numbers and states, their detections as received, their results and the
//! error series built from the validated ones.

use serde::Serialize;
use serde_json::Value;
use sqlx::Row;

use driftwatch_core::recording::{CycleResultMsg, ResultStatus};

use super::sets::insert_set;
use super::statement::query;
use super::{ErrorSample, NewCompensation, Store, StoreError};

/// A cycle's state in the `cycles` table (stored as its lowercase name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
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

impl CycleStatus {
    /// The stored text (both engines store the states as text).
    pub fn as_str(self) -> &'static str {
        match self {
            CycleStatus::Open => "open",
            CycleStatus::Ok => "ok",
            CycleStatus::Rejected => "rejected",
            CycleStatus::Abandoned => "abandoned",
        }
    }

    fn of_column(s: &str) -> Result<Self, StoreError> {
        match s {
            "open" => Ok(CycleStatus::Open),
            "ok" => Ok(CycleStatus::Ok),
            "rejected" => Ok(CycleStatus::Rejected),
            "abandoned" => Ok(CycleStatus::Abandoned),
            other => Err(StoreError::Corrupt(format!(
                "cycle status '{other}' is none of open, ok, rejected, abandoned"
            ))),
        }
    }
}

impl std::fmt::Display for CycleStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
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

fn cycle_row(r: &sqlx::any::AnyRow) -> Result<CycleRow, StoreError> {
    Ok(CycleRow {
        cycle: r.try_get(0)?,
        started_ns: r.try_get(1)?,
        trigger: r.try_get(2)?,
        attempt: r.try_get(3)?,
        status: CycleStatus::of_column(&r.try_get::<String, _>(4)?)?,
        finished_ns: r.try_get(5)?,
        reason: r.try_get(6)?,
    })
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

/// One detection as received: its time, step label and contract JSON.
#[derive(Debug, Clone)]
pub struct DetectionRow<'a> {
    pub t_ns: i64,
    pub step: &'a str,
    pub payload: String,
}

impl Store {
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
        let mut tx = super::Tx::begin(self).await?;
        let term = self.fence(&mut tx, machine).await?;
        query(
            "INSERT INTO cycles (machine_id, cycle, started_ns, trigger, attempt, status, lease_term)
             VALUES ($1, $2, $3, $4, $5, $6, $7)",
        )
        .bind(machine)
        .bind(cycle)
        .bind(started_ns)
        .bind(trigger)
        .bind(attempt)
        .bind(CycleStatus::Open.as_str())
        .bind(term)
        .execute(&mut tx)
        .await?;
        tx.commit().await?;
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
        let mut conn = self.write_conn().await?;
        for chunk in numbered.chunks(1000) {
            let sql = format!(
                "INSERT INTO detections (machine_id, cycle, seq, t_ns, step, payload) {}",
                super::values_placeholders(chunk.len(), 6)
            );
            let mut q = query(sql);
            for (seq, r) in chunk {
                q = q
                    .bind(machine)
                    .bind(cycle)
                    .bind(*seq)
                    .bind(r.t_ns)
                    .bind(r.step)
                    .bind(r.payload.as_str());
            }
            q.execute(&mut conn).await?;
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
        let mut tx = super::Tx::begin(self).await?;
        let term = self.fence(&mut tx, machine).await?;
        query(
            "UPDATE cycles SET status = $3, finished_ns = $4, reason = $5
             WHERE machine_id = $1 AND cycle = $2",
        )
        .bind(machine)
        .bind(result.cycle)
        .bind(status.as_str())
        .bind(finished_ns)
        .bind(result.reason.as_deref())
        .execute(&mut tx)
        .await?;
        query(
            "INSERT INTO results (machine_id, cycle, t_ns, status, reason, residual_rms_um, chi2, dof, payload)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9)",
        )
        .bind(machine)
        .bind(result.cycle)
        .bind(result.t_ns)
        .bind(status.as_str())
        .bind(result.reason.as_deref())
        .bind(result.residual_rms_um)
        .bind(result.chi2)
        .bind(result.dof.map(|d| d as i64))
        .bind(&payload)
        // Not a cached prepared statement: see `NULLABLE_REAL` in the store's module.
        .persistent(super::NULLABLE_REAL_CACHED)
        .execute(&mut tx)
        .await?;
        // One multi-row statement for the errors (one request instead of one per error).
        if let (Some(errors), Some(sigma)) = (&result.errors, &result.sigma)
            && !errors.is_empty()
        {
            let sql = format!(
                "INSERT INTO result_values (machine_id, cycle, name, t_ns, value, sigma) {}",
                super::values_placeholders(errors.len(), 6)
            );
            let mut q = query(sql);
            for (name, value) in errors {
                q = q
                    .bind(machine)
                    .bind(result.cycle)
                    .bind(name)
                    .bind(result.t_ns)
                    .bind(value)
                    .bind(sigma.get(name).copied().unwrap_or(f64::NAN));
            }
            q.execute(&mut tx).await?;
        }
        if let Some(c) = compensation {
            insert_set(&mut tx, machine, c, term).await?;
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
        .bind(CycleStatus::Ok.as_str())
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
        let mut tx = super::Tx::begin(self).await?;
        self.fence(&mut tx, machine).await?;
        query(
            "UPDATE cycles SET status = $5, finished_ns = $3, reason = $4
             WHERE machine_id = $1 AND cycle = $2 AND status = $6",
        )
        .bind(machine)
        .bind(cycle)
        .bind(now_ns)
        .bind(reason)
        .bind(CycleStatus::Abandoned.as_str())
        .bind(CycleStatus::Open.as_str())
        .execute(&mut tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// Cycles still open (left by a crash), oldest first.
    pub async fn open_cycles(&self, machine: &str) -> Result<Vec<i64>, StoreError> {
        let rows = sqlx::query(
            "SELECT cycle FROM cycles WHERE machine_id = $1 AND status = $2 ORDER BY cycle",
        )
        .bind(machine)
        .bind(CycleStatus::Open.as_str())
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(|r| Ok(r.try_get::<i64, _>(0)?)).collect()
    }

    /// The spans of a machine's cycles that end at or after `from_ns` and start before
    /// `to_ns`, in start order: (started, finished; none while open), for the phase to tell a
    /// cycle's spin from a spindle start after a restart.
    pub async fn cycle_spans(
        &self,
        machine: &str,
        from_ns: i64,
        to_ns: i64,
    ) -> Result<Vec<(i64, Option<i64>)>, StoreError> {
        let rows = sqlx::query(
            "SELECT started_ns, finished_ns FROM cycles
             WHERE machine_id = $1 AND started_ns < $3 AND COALESCE(finished_ns, started_ns) >= $2
             ORDER BY started_ns",
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

    /// The accepted (`ok`) results whose reference time lies in `[from_ns, to_ns]`, in time
    /// order: what a verification compares a reference with.
    pub async fn accepted_results_between(
        &self,
        machine: &str,
        from_ns: i64,
        to_ns: i64,
    ) -> Result<Vec<CycleResultMsg>, StoreError> {
        let rows = sqlx::query(
            "SELECT payload FROM results
             WHERE machine_id = $1 AND status = $2 AND t_ns >= $3 AND t_ns <= $4
             ORDER BY t_ns, cycle",
        )
        .bind(machine)
        .bind(CycleStatus::Ok.as_str())
        .bind(from_ns)
        .bind(to_ns)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| Ok(serde_json::from_str(&r.try_get::<String, _>(0)?)?))
            .collect()
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

    /// The time of the machine's last stored detection.
    pub async fn last_detection_ns(&self, machine: &str) -> Result<Option<i64>, StoreError> {
        Ok(
            sqlx::query_scalar("SELECT MAX(t_ns) FROM detections WHERE machine_id = $1")
                .bind(machine)
                .fetch_one(&self.pool)
                .await?,
        )
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
            .bind(CycleStatus::Ok.as_str())
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
}
