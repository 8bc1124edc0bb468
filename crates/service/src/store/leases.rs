//! Leases of a fleet: which process runs each machine (see `migrations/*/..._fleet.sql`).
//!
//! A process holds a machine while it renews the lease within `ttl`; another takes it only
//! once it has expired, and that bumps the term. A store bound to a lease ([`Store::fenced`])
//! checks, in the transaction of each cycle and compensation write, that the term is still
//! its own and unexpired, holding the lease row (PostgreSQL: `FOR SHARE`) until the write
//! commits, so that a process that lost its machine (a pause, a partition) cannot write
//! after the next holder took over, and a takeover waits for a write in flight.

use sqlx::Row;

use super::statement::query;
use super::writer::Conn;
use super::{Store, StoreError};

/// A held lease: the machine, its holder and the term.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Lease {
    pub machine: String,
    pub holder: String,
    pub term: i64,
}

/// A lease as stored, with the database's time it was read at.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, utoipa::ToSchema)]
pub struct LeaseRow {
    pub machine_id: String,
    pub holder: String,
    /// Where the holder's API answers, if it said.
    pub url: Option<String>,
    pub term: i64,
    pub expires_ms: i64,
    /// The database's clock when this was read, ms since the Unix epoch.
    pub now_ms: i64,
}

/// One term of a machine's lease.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, utoipa::ToSchema)]
pub struct TermRow {
    pub term: i64,
    pub holder: String,
    pub acquired_ms: i64,
    pub renewed_ms: i64,
    /// When the holder's right to run ended, unless it released earlier: the last renewal
    /// plus the lease time.
    pub expires_ms: i64,
    pub released_ms: Option<i64>,
}

impl Store {
    /// The database's clock, ms since the Unix epoch.
    pub async fn db_now_ms(&self) -> Result<i64, StoreError> {
        let sql = format!("SELECT {}", self.backend.now_ms_sql());
        Ok(sqlx::query_scalar(sqlx::AssertSqlSafe(sql))
            .fetch_one(&self.pool)
            .await?)
    }

    /// Take `machine` for `holder` if nobody holds it or its lease has expired: the new term,
    /// or `None` when another process holds it.
    pub async fn acquire_lease(
        &self,
        machine: &str,
        holder: &str,
        url: Option<&str>,
        ttl_ms: i64,
    ) -> Result<Option<Lease>, StoreError> {
        let now = self.backend.now_ms_sql();
        let mut tx = super::Tx::begin(self).await?;
        // One statement decides, under the row's lock: two processes cannot both take it.
        let upsert = format!(
            "INSERT INTO leases (machine_id, holder, url, term, expires_ms)
             VALUES ($1, $2, $3, 1, {now} + $4)
             ON CONFLICT (machine_id) DO UPDATE SET holder = excluded.holder,
                 url = excluded.url, term = leases.term + 1, expires_ms = excluded.expires_ms
             WHERE leases.expires_ms < {now}
             RETURNING term, expires_ms"
        );
        let row = query(upsert)
            .bind(machine)
            .bind(holder)
            .bind(url)
            .bind(ttl_ms)
            .fetch_optional(&mut tx)
            .await?;
        let Some(row) = row else {
            tx.rollback().await?;
            return Ok(None);
        };
        let (term, expires_ms): (i64, i64) = (row.get(0)?, row.get(1)?);
        let log = format!(
            "INSERT INTO lease_terms (machine_id, term, holder, acquired_ms, renewed_ms, expires_ms)
             VALUES ($1, $2, $3, {now}, {now}, $4)"
        );
        query(log)
            .bind(machine)
            .bind(term)
            .bind(holder)
            .bind(expires_ms)
            .execute(&mut tx)
            .await?;
        tx.commit().await?;
        Ok(Some(Lease {
            machine: machine.to_string(),
            holder: holder.to_string(),
            term,
        }))
    }

    /// Extend a held lease by `ttl_ms` from now: false when the term is no longer this
    /// holder's (another process took the machine).
    pub async fn renew_lease(&self, lease: &Lease, ttl_ms: i64) -> Result<bool, StoreError> {
        let now = self.backend.now_ms_sql();
        let mut tx = super::Tx::begin(self).await?;
        let sql = format!(
            "UPDATE leases SET expires_ms = {now} + $4
             WHERE machine_id = $1 AND holder = $2 AND term = $3"
        );
        let held = query(sql)
            .bind(&lease.machine)
            .bind(&lease.holder)
            .bind(lease.term)
            .bind(ttl_ms)
            .execute(&mut tx)
            .await?
            == 1;
        if held {
            let log = format!(
                "UPDATE lease_terms SET renewed_ms = {now}, expires_ms = {now} + $3
                 WHERE machine_id = $1 AND term = $2"
            );
            query(log)
                .bind(&lease.machine)
                .bind(lease.term)
                .bind(ttl_ms)
                .execute(&mut tx)
                .await?;
        }
        tx.commit().await?;
        Ok(held)
    }

    /// Give a lease back (a clean stop): another process may take the machine at once.
    pub async fn release_lease(&self, lease: &Lease) -> Result<(), StoreError> {
        let now = self.backend.now_ms_sql();
        let mut tx = super::Tx::begin(self).await?;
        let sql = "UPDATE leases SET expires_ms = 0
                   WHERE machine_id = $1 AND holder = $2 AND term = $3";
        let held = query(sql)
            .bind(&lease.machine)
            .bind(&lease.holder)
            .bind(lease.term)
            .execute(&mut tx)
            .await?
            == 1;
        if held {
            let log = format!(
                "UPDATE lease_terms SET released_ms = {now}, expires_ms = {now}
                 WHERE machine_id = $1 AND term = $2"
            );
            query(log)
                .bind(&lease.machine)
                .bind(lease.term)
                .execute(&mut tx)
                .await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// Every lease, by machine.
    pub async fn leases(&self) -> Result<Vec<LeaseRow>, StoreError> {
        let sql = format!(
            "SELECT machine_id, holder, url, term, expires_ms, {} FROM leases ORDER BY machine_id",
            self.backend.now_ms_sql()
        );
        let rows = sqlx::query(sqlx::AssertSqlSafe(sql))
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| {
                Ok(LeaseRow {
                    machine_id: r.try_get(0)?,
                    holder: r.try_get(1)?,
                    url: r.try_get(2)?,
                    term: r.try_get(3)?,
                    expires_ms: r.try_get(4)?,
                    now_ms: r.try_get(5)?,
                })
            })
            .collect()
    }

    /// Every term of a machine's lease, oldest first.
    pub async fn lease_terms(&self, machine: &str) -> Result<Vec<TermRow>, StoreError> {
        let rows = sqlx::query(
            "SELECT term, holder, acquired_ms, renewed_ms, expires_ms, released_ms
             FROM lease_terms WHERE machine_id = $1 ORDER BY term",
        )
        .bind(machine)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(TermRow {
                    term: r.try_get(0)?,
                    holder: r.try_get(1)?,
                    acquired_ms: r.try_get(2)?,
                    renewed_ms: r.try_get(3)?,
                    expires_ms: r.try_get(4)?,
                    released_ms: r.try_get(5)?,
                })
            })
            .collect()
    }

    /// The machine time a fleet shares, now: the first process to ask sets it from its own
    /// `t0_ns` and `scale`; the others follow it. Err when this process's scale differs.
    pub async fn fleet_clock_now(&self, t0_ns: i64, scale: f64) -> Result<i64, StoreError> {
        let now = self.backend.now_ms_sql();
        let insert = format!(
            "INSERT INTO fleet_clock (id, t0_ns, wall0_ms, scale) VALUES (1, $1, {now}, $2)
             ON CONFLICT (id) DO NOTHING"
        );
        query(insert)
            .bind(t0_ns)
            .bind(scale)
            .execute(&mut self.write_conn().await?)
            .await?;
        let select = format!("SELECT t0_ns, wall0_ms, scale, {now} FROM fleet_clock WHERE id = 1");
        let row = sqlx::query(sqlx::AssertSqlSafe(select))
            .fetch_one(&self.pool)
            .await?;
        let (t0, wall0, stored_scale, now_ms): (i64, i64, f64, i64) = (
            row.try_get(0)?,
            row.try_get(1)?,
            row.try_get(2)?,
            row.try_get(3)?,
        );
        if (stored_scale - scale).abs() > 1e-9 * scale.abs().max(1.0) {
            return Err(StoreError::Fleet(format!(
                "the fleet's clock runs at time_scale {stored_scale}, this process's configuration \
                 says {scale}: every process of a fleet must run at the same scale"
            )));
        }
        Ok(t0.saturating_add(((now_ms - wall0) as f64 * 1e6 * stored_scale) as i64))
    }

    /// This store, bound to a held lease: its cycle and compensation writes are fenced by it.
    pub fn fenced(&self, lease: &Lease) -> Store {
        Store {
            fence: Some(std::sync::Arc::new(lease.clone())),
            ..self.clone()
        }
    }

    /// In a write's transaction: the term to stamp the row with, after checking that the
    /// lease this store is bound to is still held (and keeping it so until commit).
    pub(super) async fn fence(
        &self,
        tx: &mut Conn<'_>,
        machine: &str,
    ) -> Result<Option<i64>, StoreError> {
        let Some(lease) = self.fence.as_deref() else {
            return Ok(None);
        };
        let sql = format!(
            "SELECT holder, term, expires_ms, {} FROM leases WHERE machine_id = $1{}",
            self.backend.now_ms_sql(),
            self.backend.share_lock()
        );
        let row = query(sql).bind(machine).fetch_optional(tx).await?;
        let lost = |why: String| {
            Err(StoreError::LeaseLost {
                machine: machine.to_string(),
                term: lease.term,
                why,
            })
        };
        let Some(row) = row else {
            return lost("the machine has no lease".to_string());
        };
        let (holder, term, expires, now): (String, i64, i64, i64) =
            (row.get(0)?, row.get(1)?, row.get(2)?, row.get(3)?);
        if machine != lease.machine || holder != lease.holder || term != lease.term {
            return lost(format!("it is held by '{holder}' in term {term}"));
        }
        if expires <= now {
            return lost(format!("it expired {} ms ago", now - expires));
        }
        Ok(Some(term))
    }
}

/// What the stored data says of who ran a machine: its lease terms, and the term that wrote
/// each cycle and compensation set.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct LeaseAudit {
    pub machine: String,
    pub terms: Vec<TermRow>,
    /// (cycle, started_ns, status, lease term), by cycle number.
    pub cycles: Vec<(i64, i64, String, Option<i64>)>,
    /// (version, valid_from_ns, lease term), by version.
    pub sets: Vec<(i64, i64, Option<i64>)>,
}

impl LeaseAudit {
    /// Every breach of "one process at a time, versions only forward" the data shows: a
    /// term that began before the one before it had ended, a cycle or set written by an
    /// older term after a newer one, versions with a gap, or a version valid before the one
    /// it follows. Empty when the data is sound.
    pub fn problems(&self) -> Vec<String> {
        let m = &self.machine;
        let mut out = Vec::new();
        for w in self.terms.windows(2) {
            let ended = w[0]
                .released_ms
                .unwrap_or(w[0].expires_ms)
                .min(w[0].expires_ms);
            if w[1].acquired_ms < ended {
                out.push(format!(
                    "{m}: term {} ('{}') began {} ms before term {} ('{}') ended",
                    w[1].term,
                    w[1].holder,
                    ended - w[1].acquired_ms,
                    w[0].term,
                    w[0].holder
                ));
            }
        }
        let mut last: Option<(i64, i64, i64)> = None;
        for (cycle, started, _, term) in &self.cycles {
            if let (Some((c0, s0, t0)), Some(t)) = (last, term) {
                if *t < t0 {
                    out.push(format!(
                        "{m}: cycle {cycle} was written by term {t} after cycle {c0} by term {t0}"
                    ));
                }
                if *started < s0 {
                    out.push(format!("{m}: cycle {cycle} started before cycle {c0}"));
                }
            }
            if let Some(t) = term {
                last = Some((*cycle, *started, *t));
            }
        }
        for w in self.sets.windows(2) {
            let ((v0, f0, t0), (v1, f1, t1)) = (w[0], w[1]);
            if v1 != v0 + 1 {
                out.push(format!("{m}: compensation version {v1} follows {v0}"));
            }
            if f1 < f0 {
                out.push(format!(
                    "{m}: compensation version {v1} is valid from before version {v0}"
                ));
            }
            if let (Some(a), Some(b)) = (t0, t1)
                && b < a
            {
                out.push(format!(
                    "{m}: compensation version {v1} was written by term {b} after version {v0} by term {a}"
                ));
            }
        }
        out
    }
}

impl Store {
    /// The stored record of who ran `machine`, for [`LeaseAudit::problems`].
    pub async fn lease_audit(&self, machine: &str) -> Result<LeaseAudit, StoreError> {
        let cycles = sqlx::query(
            "SELECT cycle, started_ns, status, lease_term FROM cycles WHERE machine_id = $1
             ORDER BY cycle",
        )
        .bind(machine)
        .fetch_all(&self.pool)
        .await?
        .iter()
        .map(|r| Ok((r.try_get(0)?, r.try_get(1)?, r.try_get(2)?, r.try_get(3)?)))
        .collect::<Result<_, sqlx::Error>>()?;
        let sets = sqlx::query(
            "SELECT version, valid_from_ns, lease_term FROM compensation_sets
             WHERE machine_id = $1 ORDER BY version",
        )
        .bind(machine)
        .fetch_all(&self.pool)
        .await?
        .iter()
        .map(|r| Ok((r.try_get(0)?, r.try_get(1)?, r.try_get(2)?)))
        .collect::<Result<_, sqlx::Error>>()?;
        Ok(LeaseAudit {
            machine: machine.to_string(),
            terms: self.lease_terms(machine).await?,
            cycles,
            sets,
        })
    }
}
