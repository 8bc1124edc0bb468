//! Where the store's writes run: the connection a write takes ([`Conn`]) and the store's own
//! transactions on it ([`Tx`]).
//!
//! On SQLite one connection of the pool is the store's writer, held between writes: every
//! write of every machine goes through it in turn. SQLite lets one connection write at a time
//! anyway (a second one waits in its busy handler, which sleeps); a held writer also keeps its
//! page cache between writes, where a connection that another one's commit overtook must read
//! those pages again, and a write costs no trip to the pool and back. The pool's other
//! connections are left to the reads (the API's among them), which the write-ahead log never
//! blocks. On PostgreSQL, which writes concurrently, a write takes a connection of the pool.

use sqlx::pool::PoolConnection;
use sqlx::{Any, AnyPool, Connection};
use tokio::sync::{Mutex, MutexGuard};

use super::StoreError;

/// SQLite's writer: the connection, once the first write has taken it from the pool.
#[derive(Default)]
pub(super) struct Writer {
    slot: Mutex<Option<PoolConnection<Any>>>,
}

impl Writer {
    /// The writer, once the write before this one has finished.
    pub(super) async fn lock<'a>(&'a self, pool: &AnyPool) -> Result<Conn<'a>, StoreError> {
        let mut slot = self.slot.lock().await;
        // The pool's own check at a release (sqlx's count); the store's transactions close
        // their connection themselves when they do not end.
        if slot.as_ref().is_some_and(|c| c.is_in_transaction()) {
            discard(&mut slot);
        }
        if slot.is_none() {
            *slot = Some(pool.acquire().await?);
        }
        Ok(Conn::Writer(slot))
    }

    /// Give the connection back to the pool (before the pool closes: it waits for every one).
    pub(super) async fn release(&self) {
        self.slot.lock().await.take();
    }
}

/// Close the writer's connection now, which ends whatever the engine still held of it (an
/// open transaction and its lock); the next write takes a fresh one from the pool.
fn discard(slot: &mut Option<PoolConnection<Any>>) {
    if let Some(mut c) = slot.take() {
        c.close_on_drop();
    }
}

/// A connection to write on: SQLite's writer (its slot, filled), or one of the pool's.
pub(super) enum Conn<'a> {
    Pooled(PoolConnection<Any>),
    Writer(MutexGuard<'a, Option<PoolConnection<Any>>>),
}

impl Conn<'_> {
    /// Do not use this connection again: it may be in a state the engine and the store see
    /// differently. It is closed.
    fn discard(&mut self) {
        match self {
            Conn::Pooled(c) => c.close_on_drop(),
            Conn::Writer(slot) => discard(slot),
        }
    }
}

impl std::ops::Deref for Conn<'_> {
    type Target = sqlx::AnyConnection;
    fn deref(&self) -> &sqlx::AnyConnection {
        match self {
            Conn::Pooled(c) => c,
            Conn::Writer(slot) => slot
                .as_deref()
                .unwrap_or_else(|| unreachable!("the writer's slot is filled while lent")),
        }
    }
}

impl std::ops::DerefMut for Conn<'_> {
    fn deref_mut(&mut self) -> &mut sqlx::AnyConnection {
        match self {
            Conn::Pooled(c) => c,
            Conn::Writer(slot) => slot
                .as_deref_mut()
                .unwrap_or_else(|| unreachable!("the writer's slot is filled while lent")),
        }
    }
}

/// A transaction whose connection is used again only once it has ended by its own COMMIT or
/// ROLLBACK. One that failed or was dropped part way (an error, a cancelled future) discards
/// its connection instead ([`Conn::discard`]), which ends whatever the engine still held of
/// it. So a connection is never used again in a state the engine and the store see
/// differently: a COMMIT that fails on a full disk may leave SQLite's transaction open
/// (holding the write lock for every other connection), or end it. Statements outside a
/// transaction commit or roll back on their own. That is what lets the pool take a connection
/// back without asking the engine about it first.
///
/// BEGIN, COMMIT and ROLLBACK are plain statements (the same in both engines), not sqlx's
/// transaction type: that one owns its connection and cannot mark it to be closed.
pub(super) struct Tx<'a> {
    conn: Conn<'a>,
    ended: bool,
}

impl<'a> Tx<'a> {
    pub(super) async fn begin(store: &'a super::Store) -> Result<Tx<'a>, StoreError> {
        // Made before BEGIN: a BEGIN that fails discards the connection too.
        let mut tx = Tx {
            conn: store.write_conn().await?,
            ended: false,
        };
        tx.run("BEGIN").await?;
        Ok(tx)
    }

    async fn run(&mut self, sql: &'static str) -> Result<(), StoreError> {
        sqlx::raw_sql(sql).execute(&mut *self.conn).await?;
        Ok(())
    }

    pub(super) async fn commit(mut self) -> Result<(), StoreError> {
        self.run("COMMIT").await?;
        self.ended = true;
        Ok(())
    }

    pub(super) async fn rollback(mut self) -> Result<(), StoreError> {
        self.run("ROLLBACK").await?;
        self.ended = true;
        Ok(())
    }
}

impl std::ops::Deref for Tx<'_> {
    type Target = sqlx::AnyConnection;
    fn deref(&self) -> &sqlx::AnyConnection {
        &self.conn
    }
}

impl std::ops::DerefMut for Tx<'_> {
    fn deref_mut(&mut self) -> &mut sqlx::AnyConnection {
        &mut self.conn
    }
}

impl Drop for Tx<'_> {
    fn drop(&mut self) {
        if !self.ended {
            self.conn.discard();
        }
    }
}
