//! The alert log: every event of every alert, and acknowledgements.

use serde::Serialize;
use sqlx::Row;

use driftwatch_machine::alerts::{EventKind, Severity};

use super::statement::query;
use super::{Store, StoreError};

/// What happened to an alert (stored as its lowercase name): the engine's events and the
/// operator's acknowledgement.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum AlertEventKind {
    Raised,
    Updated,
    Resolved,
    Acknowledged,
}

impl AlertEventKind {
    /// The stored text.
    pub fn as_str(self) -> &'static str {
        match self {
            AlertEventKind::Raised => "raised",
            AlertEventKind::Updated => "updated",
            AlertEventKind::Resolved => "resolved",
            AlertEventKind::Acknowledged => "acknowledged",
        }
    }

    fn of_column(s: &str) -> Result<Self, StoreError> {
        match s {
            "raised" => Ok(AlertEventKind::Raised),
            "updated" => Ok(AlertEventKind::Updated),
            "resolved" => Ok(AlertEventKind::Resolved),
            "acknowledged" => Ok(AlertEventKind::Acknowledged),
            other => Err(StoreError::Corrupt(format!(
                "alert event kind '{other}' is none of raised, updated, resolved, acknowledged"
            ))),
        }
    }
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

impl Store {
    pub async fn add_alert_event(
        &self,
        machine: &str,
        ev: &NewAlertEvent<'_>,
    ) -> Result<(), StoreError> {
        query(
            "INSERT INTO alert_events (machine_id, alert_id, seq, t_ns, kind, rule, severity, message, value)
             VALUES ($1, $2, (SELECT COALESCE(MAX(seq), 0) + 1 FROM alert_events WHERE machine_id = $1 AND alert_id = $2),
                     $3, $4, $5, $6, $7, $8)",
        )
        .bind(machine)
        .bind(ev.alert)
        .bind(ev.t_ns)
        .bind(ev.kind.as_str())
        .bind(ev.rule)
        .bind(AlertSeverity::column(ev.severity))
        .bind(ev.message)
        .bind(ev.value)
        // Not a cached prepared statement: see `NULLABLE_REAL` in the store's module.
        .persistent(super::NULLABLE_REAL_CACHED)
        .execute(&mut self.write_conn().await?)
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
                    kind: AlertEventKind::of_column(&r.try_get::<String, _>(3)?)?,
                    rule: r.try_get(4)?,
                    severity: AlertSeverity::of_column(&r.try_get::<String, _>(5)?)?,
                    message: r.try_get(6)?,
                    value: r.try_get(7)?,
                })
            })
            .collect()
    }

    /// Keep a machine's alert engine state (replacing the one kept before).
    pub async fn put_alert_state(
        &self,
        machine: &str,
        t_ns: i64,
        state: &driftwatch_machine::alerts::AlertState,
    ) -> Result<(), StoreError> {
        let json = serde_json::to_string(state)?;
        query(
            "INSERT INTO alert_state (machine_id, t_ns, state) VALUES ($1, $2, $3)
             ON CONFLICT (machine_id) DO UPDATE SET t_ns = excluded.t_ns, state = excluded.state",
        )
        .bind(machine)
        .bind(t_ns)
        .bind(json)
        .execute(&mut self.write_conn().await?)
        .await?;
        Ok(())
    }

    /// A machine's alert engine state as last kept, if any.
    pub async fn alert_state(
        &self,
        machine: &str,
    ) -> Result<Option<driftwatch_machine::alerts::AlertState>, StoreError> {
        let json: Option<String> =
            sqlx::query_scalar("SELECT state FROM alert_state WHERE machine_id = $1")
                .bind(machine)
                .fetch_optional(&self.pool)
                .await?;
        json.map(|j| {
            serde_json::from_str(&j)
                .map_err(|e| StoreError::Corrupt(format!("the alert state of {machine}: {e}")))
        })
        .transpose()
    }

    /// What the alert log holds of a machine: the alerts raised and never resolved, and the
    /// highest id.
    pub async fn logged_alerts(
        &self,
        machine: &str,
    ) -> Result<driftwatch_machine::alerts::LoggedAlerts, StoreError> {
        let rows = sqlx::query(
            "SELECT alert_id, MAX(rule), MIN(severity) FROM alert_events
             WHERE machine_id = $1 AND kind <> 'acknowledged'
             GROUP BY alert_id
             HAVING SUM(CASE WHEN kind = 'resolved' THEN 1 ELSE 0 END) = 0
             ORDER BY alert_id",
        )
        .bind(machine)
        .fetch_all(&self.pool)
        .await?;
        let open = rows
            .iter()
            .map(|r| {
                let severity = match AlertSeverity::of_column(&r.try_get::<String, _>(2)?)? {
                    Some(AlertSeverity::Critical) => Severity::Critical,
                    _ => Severity::Warning,
                };
                Ok((
                    r.try_get::<i64, _>(0)?.max(0) as u64,
                    r.try_get(1)?,
                    severity,
                ))
            })
            .collect::<Result<Vec<_>, StoreError>>()?;
        let max: Option<i64> =
            sqlx::query_scalar("SELECT MAX(alert_id) FROM alert_events WHERE machine_id = $1")
                .bind(machine)
                .fetch_one(&self.pool)
                .await?;
        Ok(driftwatch_machine::alerts::LoggedAlerts {
            open,
            max_id: max.unwrap_or(0).max(0) as u64,
        })
    }
}
