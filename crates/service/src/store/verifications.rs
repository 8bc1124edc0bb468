//! Verifications: reference results (an R-test) compared with the tool setter's, as the API
//! returned them.

use serde::Serialize;
use sqlx::Row;

use driftwatch_machine::verification::Verification;

use super::statement::query;
use super::{Store, StoreError};

/// A verification as stored: its number, when and by whom it was posted, and the comparison.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct StoredVerification {
    /// Numbered per machine from 1, in the order they were posted.
    pub id: i64,
    /// The service clock when it was posted, ns since the Unix epoch.
    pub created_ns: i64,
    /// The token holder who posted it.
    pub requested_by: String,
    #[serde(flatten)]
    pub verification: Verification,
}

impl Store {
    /// Store a verification and keep only the machine's newest `keep` (at least 1: numbers are
    /// never given twice); returns its number.
    pub async fn add_verification(
        &self,
        v: &Verification,
        created_ns: i64,
        requested_by: &str,
        keep: i64,
    ) -> Result<i64, StoreError> {
        let payload = serde_json::to_string(v)?;
        let mut conn = self.write_conn().await?;
        // One statement: the number and the row together, whatever else writes meanwhile.
        let id: i64 = query(
            "INSERT INTO verifications (machine_id, id, t_ns, created_ns, requested_by, instrument, method, exceeds, worst_z, payload)
             VALUES ($1, (SELECT COALESCE(MAX(id), 0) + 1 FROM verifications WHERE machine_id = $1),
                     $2, $3, $4, $5, $6, $7, $8, $9)
             RETURNING id",
        )
        .bind(&v.machine_id)
        .bind(v.t_ns)
        .bind(created_ns)
        .bind(requested_by)
        .bind(&v.instrument)
        .bind(v.method.as_str())
        .bind(v.exceeds_any)
        .bind(v.worst_z)
        .bind(&payload)
        .fetch_one(&mut conn)
        .await?
        .get(0)?;
        query("DELETE FROM verifications WHERE machine_id = $1 AND id <= $2")
            .bind(&v.machine_id)
            .bind(id - keep.max(1))
            .execute(&mut conn)
            .await?;
        Ok(id)
    }

    /// The verifications of a machine whose reference time lies in `[from_ns, to_ns]`, the
    /// latest reference time first (then the latest posted): at most `limit`.
    pub async fn verifications(
        &self,
        machine: &str,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
    ) -> Result<Vec<StoredVerification>, StoreError> {
        let rows = sqlx::query(
            "SELECT id, created_ns, requested_by, payload FROM verifications
             WHERE machine_id = $1 AND t_ns >= $2 AND t_ns <= $3
             ORDER BY t_ns DESC, id DESC LIMIT $4",
        )
        .bind(machine)
        .bind(from_ns)
        .bind(to_ns)
        .bind(limit)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                let payload: String = r.try_get(3)?;
                Ok(StoredVerification {
                    id: r.try_get(0)?,
                    created_ns: r.try_get(1)?,
                    requested_by: r.try_get(2)?,
                    verification: serde_json::from_str(&payload)?,
                })
            })
            .collect()
    }
}
