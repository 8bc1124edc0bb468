//! Linear-axis geometry versions: a machine's measured scale, squareness and component errors,
//! as posted through the API. The newest is what the machine's solves start from.

use serde::Serialize;
use sqlx::Row;

use driftwatch_core::linear_axes::LinearGeometry;

use super::statement::query;
use super::{Store, StoreError};

/// A geometry version as stored.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct StoredGeometry {
    /// Numbered per machine from 1, in the order they were posted.
    pub version: i64,
    /// The service clock when it was posted, ns since the Unix epoch.
    pub created_ns: i64,
    /// The token holder who posted it.
    pub requested_by: String,
    /// What measured it, in the poster's words.
    pub source: String,
    pub geometry: LinearGeometry,
}

impl StoredGeometry {
    /// The name every cycle result solved with it carries.
    pub fn label(&self) -> String {
        format!("version {}: {}", self.version, self.source)
    }
}

impl Store {
    /// Store a machine's new geometry version; returns its number.
    pub async fn add_geometry(
        &self,
        machine: &str,
        g: &LinearGeometry,
        source: &str,
        created_ns: i64,
        requested_by: &str,
    ) -> Result<i64, StoreError> {
        let payload = serde_json::to_string(g)?;
        let version: i64 = query(
            "INSERT INTO geometries (machine_id, version, created_ns, requested_by, source, payload)
             VALUES ($1, (SELECT COALESCE(MAX(version), 0) + 1 FROM geometries WHERE machine_id = $1),
                     $2, $3, $4, $5)
             RETURNING version",
        )
        .bind(machine)
        .bind(created_ns)
        .bind(requested_by)
        .bind(source)
        .bind(&payload)
        .fetch_one(&mut self.write_conn().await?)
        .await?
        .get(0)?;
        Ok(version)
    }

    /// A machine's geometry versions, the newest first.
    pub async fn geometries(&self, machine: &str) -> Result<Vec<StoredGeometry>, StoreError> {
        let rows = sqlx::query(
            "SELECT version, created_ns, requested_by, source, payload FROM geometries
             WHERE machine_id = $1 ORDER BY version DESC",
        )
        .bind(machine)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                let payload: String = r.try_get(4)?;
                Ok(StoredGeometry {
                    version: r.try_get(0)?,
                    created_ns: r.try_get(1)?,
                    requested_by: r.try_get(2)?,
                    source: r.try_get(3)?,
                    geometry: serde_json::from_str(&payload)?,
                })
            })
            .collect()
    }

    /// The newest geometry version of a machine.
    pub async fn latest_geometry(
        &self,
        machine: &str,
    ) -> Result<Option<StoredGeometry>, StoreError> {
        Ok(self.geometries(machine).await?.into_iter().next())
    }
}
