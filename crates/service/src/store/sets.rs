//! Compensation sets: every version served, measured or predicted.

use std::collections::BTreeMap;

use sqlx::Row;

use super::statement::query;
use super::writer::Conn;
use super::{Store, StoreError};

pub(super) async fn insert_set(
    conn: &mut Conn<'_>,
    machine: &str,
    c: &NewCompensation<'_>,
    lease_term: Option<i64>,
) -> Result<(), StoreError> {
    query(
        "INSERT INTO compensation_sets (machine_id, version, valid_from_ns, source, cycle, reason, payload, lease_term)
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8)",
    )
    .bind(machine)
    .bind(c.version)
    .bind(c.valid_from_ns)
    .bind(c.source)
    .bind(c.cycle)
    .bind(c.reason)
    .bind(&c.values)
    .bind(lease_term)
    .execute(conn)
    .await?;
    Ok(())
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

impl Store {
    /// Store a new compensation set; versions must increase (the primary key refuses a
    /// repeated version).
    pub async fn insert_compensation(
        &self,
        machine: &str,
        c: &NewCompensation<'_>,
    ) -> Result<(), StoreError> {
        if self.fence.is_some() {
            let mut tx = super::Tx::begin(self).await?;
            let term = self.fence(&mut tx, machine).await?;
            insert_set(&mut tx, machine, c, term).await?;
            tx.commit().await?;
            return Ok(());
        }
        // One statement commits on its own: no transaction round trips for the predicted sets
        // that go out every few minutes.
        let mut conn = self.write_conn().await?;
        insert_set(&mut conn, machine, c, None).await
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
        self.latest_set(machine, None, None).await
    }

    /// The newest set of a machine before version `version`: the one served before it.
    pub async fn compensation_before(
        &self,
        machine: &str,
        version: u64,
    ) -> Result<Option<driftwatch_machine::compensation::CompensationSet>, StoreError> {
        let before = i64::try_from(version).unwrap_or(i64::MAX);
        self.latest_set(machine, None, Some(before)).await
    }

    /// The newest measured compensation set of a machine, with the values its cycle measured
    /// (the set itself may have been ramped towards them from a predicted one): what the next
    /// cycle's step is checked against.
    pub async fn latest_measurement(
        &self,
        machine: &str,
    ) -> Result<Option<driftwatch_machine::compensation::CompensationSet>, StoreError> {
        let Some(mut set) = self.latest_set(machine, Some("measured"), None).await? else {
            return Ok(None);
        };
        if let Some(c) = set.cycle
            && let Some(r) = self.result(machine, c).await?
            && let (Some(e), Some(s)) = (r.errors, r.sigma)
            // A measured set's cycle passed validation: its names are the set's.
            && let (Ok(e), Ok(s)) = (
                driftwatch_machine::compensation::typed(&e),
                driftwatch_machine::compensation::typed(&s),
            )
        {
            set.errors = e;
            set.sigma = s;
        }
        Ok(Some(set))
    }

    async fn latest_set(
        &self,
        machine: &str,
        source: Option<&str>,
        before: Option<i64>,
    ) -> Result<Option<driftwatch_machine::compensation::CompensationSet>, StoreError> {
        use driftwatch_core::error_name::ErrorName;
        use driftwatch_machine::compensation::{CompensationSet, Source};
        let row = sqlx::query(
            "SELECT version, valid_from_ns, source, cycle, reason, payload FROM compensation_sets
             WHERE machine_id = $1 AND ($2 IS NULL OR source = $2)
               AND ($3 IS NULL OR version < $3)
             ORDER BY version DESC LIMIT 1",
        )
        .bind(machine)
        .bind(source)
        .bind(before)
        .fetch_optional(&self.pool)
        .await?;
        let Some(r) = row else {
            return Ok(None);
        };
        #[derive(serde::Deserialize)]
        struct Values {
            errors: BTreeMap<ErrorName, f64>,
            sigma: BTreeMap<ErrorName, f64>,
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
            // The NC offsets are the machine's layout's: its core fills them in.
            offsets: BTreeMap::new(),
            errors: v.errors,
            sigma: v.sigma,
            reason: r.try_get(4)?,
        }))
    }
}
