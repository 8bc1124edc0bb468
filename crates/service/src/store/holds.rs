//! One writer per machine on PostgreSQL outside a fleet: a process that runs machines on a
//! shared database without `[fleet]` holds a session advisory lock per machine on a connection
//! of its own, kept for the life of the service (PostgreSQL ends it with the session, however
//! the process ends). A second such process naming a held machine is refused at start, with
//! the holder named from `pg_stat_activity` (the connection's `application_name`). In a fleet
//! the leases do this job; on SQLite the data directory's lock does.

use sqlx::{Connection, Row};

use super::{Backend, Store, StoreError, backend::redacted};

/// The held machines: released when dropped.
pub struct MachineHold {
    _conn: sqlx::AnyConnection,
}

impl std::fmt::Debug for MachineHold {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("MachineHold")
    }
}

impl MachineHold {
    /// Let the machines go now (a restart in the same moment finds them free), then close.
    pub async fn release(mut self) {
        let _ = sqlx::query("SELECT pg_advisory_unlock_all()")
            .execute(&mut self._conn)
            .await;
        let _ = self._conn.close().await;
    }
}

/// The advisory lock key of a machine (a 32-bit hash, in the key space of this product).
const KEY_SQL: &str = "hashtext('driftwatch machine ' || $1)";

impl Store {
    /// On PostgreSQL, hold `machines` for this process (named `who`) through the database at
    /// `url`; None on SQLite, where the data directory's lock is the rule.
    pub async fn hold_machines(
        &self,
        url: &str,
        machines: &[String],
        who: &str,
    ) -> Result<Option<MachineHold>, StoreError> {
        if self.backend != Backend::Postgres {
            return Ok(None);
        }
        let mut conn =
            sqlx::AnyConnection::connect(url)
                .await
                .map_err(|source| StoreError::Open {
                    path: redacted(url),
                    source,
                })?;
        // PostgreSQL cuts application_name at 63 bytes.
        let name: String = format!("driftwatch {who}").chars().take(60).collect();
        sqlx::query("SELECT set_config('application_name', $1, false)")
            .bind(&name)
            .execute(&mut conn)
            .await?;
        for m in machines {
            let taken: bool = sqlx::query_scalar(sqlx::AssertSqlSafe(format!(
                "SELECT pg_try_advisory_lock({KEY_SQL})"
            )))
            .bind(m)
            .fetch_one(&mut conn)
            .await?;
            if !taken {
                let holders = sqlx::query(
                    "SELECT application_name, COALESCE(CAST(client_addr AS TEXT), 'local')
                     FROM pg_stat_activity
                     WHERE application_name LIKE 'driftwatch %' AND pid <> pg_backend_pid()",
                )
                .fetch_all(&mut conn)
                .await?
                .iter()
                .map(|r| {
                    Ok(format!(
                        "{} from {}",
                        r.try_get::<String, _>(0)?,
                        r.try_get::<String, _>(1)?
                    ))
                })
                .collect::<Result<Vec<_>, StoreError>>()?;
                return Err(StoreError::Held {
                    machine: m.clone(),
                    holders: if holders.is_empty() {
                        "a session that did not say who it is".into()
                    } else {
                        holders.join("; ")
                    },
                });
            }
        }
        Ok(Some(MachineHold { _conn: conn }))
    }
}
