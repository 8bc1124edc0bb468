//! The per-minute spindle and temperature samples (the thermal model's inputs).

use std::collections::BTreeMap;

use sqlx::Row;

use super::statement::query;
use super::{Store, StoreError};

/// One sample of a per-minute series.
/// A per-minute sample: the machine core decides which samples are kept.
pub use driftwatch_machine::machine_core::Sample;

impl Store {
    /// Store a batch of spindle and temperature samples: one multi-row statement per table,
    /// both in one transaction (the per-minute series are most of the service's writes, and a
    /// commit is most of a small write's cost on SQLite: a simulated year, 52 560 batches, wrote
    /// one commit a batch fewer). A batch that failed is written again whole, which the
    /// upserts make harmless (a repeated key takes the same value).
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
        let mut tx = super::Tx::begin(self).await?;
        // SQLite allows 32766 bound values per statement: chunks of 1000 rows stay far below.
        let spindle: Vec<_> = spindle.into_iter().collect();
        for chunk in spindle.chunks(1000) {
            let sql = format!(
                "INSERT INTO spindle_samples (machine_id, t_ns, rpm) {}
                 ON CONFLICT (machine_id, t_ns) DO UPDATE SET rpm = excluded.rpm",
                super::values_placeholders(chunk.len(), 3)
            );
            let mut q = query(sql);
            for (t, rpm) in chunk {
                q = q.bind(machine).bind(*t).bind(*rpm);
            }
            q.execute(&mut tx).await?;
        }
        let temps: Vec<_> = temps.into_iter().collect();
        for chunk in temps.chunks(1000) {
            let sql = format!(
                "INSERT INTO temperature_samples (machine_id, t_ns, sensor, celsius) {}
                 ON CONFLICT (machine_id, sensor, t_ns) DO UPDATE SET celsius = excluded.celsius",
                super::values_placeholders(chunk.len(), 4)
            );
            let mut q = query(sql);
            for ((sensor, t), c) in chunk {
                q = q.bind(machine).bind(*t).bind(*sensor).bind(*c);
            }
            q.execute(&mut tx).await?;
        }
        tx.commit().await
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
}
