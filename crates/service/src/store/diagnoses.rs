//! Diagnosis runs asked for through the API, with their results.

use serde::Serialize;
use serde_json::Value;
use sqlx::Row;

use super::statement::query;
use super::{Store, StoreError};

/// How a diagnosis run ended (stored as its lowercase name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum DiagnosisStatus {
    Done,
    Failed,
}

impl DiagnosisStatus {
    /// The stored text.
    pub fn as_str(self) -> &'static str {
        match self {
            DiagnosisStatus::Done => "done",
            DiagnosisStatus::Failed => "failed",
        }
    }

    fn of_column(s: &str) -> Result<Self, StoreError> {
        match s {
            "done" => Ok(DiagnosisStatus::Done),
            "failed" => Ok(DiagnosisStatus::Failed),
            other => Err(StoreError::Corrupt(format!(
                "diagnosis status '{other}' is none of done, failed"
            ))),
        }
    }
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

fn diagnosis_row(r: &sqlx::any::AnyRow) -> Result<DiagnosisRow, StoreError> {
    Ok(DiagnosisRow {
        id: r.try_get(0)?,
        requested_ns: r.try_get(1)?,
        requested_by: r.try_get(2)?,
        from_ns: r.try_get(3)?,
        to_ns: r.try_get(4)?,
        status: DiagnosisStatus::of_column(&r.try_get::<String, _>(5)?)?,
        summary: r.try_get(6)?,
    })
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

impl Store {
    /// Store a diagnosis run (its result JSON when it succeeded) and keep only the machine's
    /// newest `keep` (at least 1: numbers are never given twice); returns its number.
    pub async fn add_diagnosis(&self, d: &NewDiagnosis<'_>, keep: i64) -> Result<i64, StoreError> {
        let mut conn = self.write_conn().await?;
        // One statement: the number and the row together, whatever else writes meanwhile.
        let id: i64 = query(
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
        .bind(d.status.as_str())
        .bind(d.summary)
        .bind(d.result)
        .fetch_one(&mut conn)
        .await?
        .get(0)?;
        query("DELETE FROM diagnoses WHERE machine_id = $1 AND id <= $2")
            .bind(d.machine)
            .bind(id - keep.max(1))
            .execute(&mut conn)
            .await?;
        Ok(id)
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
}
