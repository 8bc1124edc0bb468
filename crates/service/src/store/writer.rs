//! Where the store's writes run: the connection a write takes ([`Conn`]) and the store's own
//! transactions on it ([`Tx`]).
//!
//! On SQLite one connection is the store's writer, held between writes: every write of every
//! machine goes through it in turn. SQLite lets one connection write at a time anyway (a
//! second one waits in its busy handler, which sleeps); a held writer also keeps its page
//! cache between writes, where a connection that another one's commit overtook must read
//! those pages again. It is the store's own connection, apart from sqlx's pool, and runs its
//! statements on the calling thread ([`super::statement`]). The pool's connections are left to
//! the reads (the API's among them), which the write-ahead log never blocks. On PostgreSQL,
//! which writes concurrently, a write takes a connection of the pool.

use std::path::PathBuf;

use sqlx::Any;
use sqlx::pool::PoolConnection;
use tokio::sync::{Mutex, MutexGuard};

use super::StoreError;
use super::statement::{Engine, Target};

/// SQLite's writer: its own connection to the file, opened at the first write (and again
/// after one was discarded), through `rusqlite` so that a write runs on the calling thread
/// ([`super::statement`]).
pub(super) struct Writer {
    path: PathBuf,
    slot: Mutex<Option<rusqlite::Connection>>,
}

impl Writer {
    pub(super) fn new(path: PathBuf) -> Self {
        Writer {
            path,
            slot: Mutex::new(None),
        }
    }

    /// The writer, once the write before this one has finished.
    pub(super) async fn lock(&self) -> Result<Conn<'_>, StoreError> {
        let mut slot = self.slot.lock().await;
        // A transaction that did not end closes its connection itself; this is the check
        // that nothing else left one open.
        if slot.as_ref().is_some_and(|c| !c.is_autocommit()) {
            slot.take();
        }
        if slot.is_none() {
            *slot = Some(super::backend::open_sqlite_writer(&self.path)?);
        }
        Ok(Conn::Writer(slot))
    }

    /// Close the connection (before the pool closes, so that the last connection to close,
    /// which folds the write-ahead log into the file, is the pool's).
    pub(super) async fn release(&self) {
        self.slot.lock().await.take();
    }
}

/// A connection to write on: SQLite's writer (its slot, filled), or one of PostgreSQL's pool.
pub(super) enum Conn<'a> {
    Pooled(PoolConnection<Any>),
    Writer(MutexGuard<'a, Option<rusqlite::Connection>>),
}

impl Conn<'_> {
    /// Do not use this connection again: it may be in a state the engine and the store see
    /// differently. It is closed (which ends whatever the engine still held of it: an open
    /// transaction and its lock); SQLite's next write opens a fresh one.
    fn discard(&mut self) {
        match self {
            Conn::Pooled(c) => c.close_on_drop(),
            Conn::Writer(slot) => drop(slot.take()),
        }
    }
}

impl Target for Conn<'_> {
    fn engine(&mut self) -> Engine<'_> {
        match self {
            Conn::Pooled(c) => Engine::Any(c),
            Conn::Writer(slot) => Engine::Sqlite(
                slot.as_ref()
                    .unwrap_or_else(|| unreachable!("the writer's slot is filled while lent")),
            ),
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
        super::statement::query(sql).execute(&mut self.conn).await?;
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

impl<'a> std::ops::Deref for Tx<'a> {
    type Target = Conn<'a>;
    fn deref(&self) -> &Conn<'a> {
        &self.conn
    }
}

impl<'a> std::ops::DerefMut for Tx<'a> {
    fn deref_mut(&mut self) -> &mut Conn<'a> {
        &mut self.conn
    }
}

impl Target for Tx<'_> {
    fn engine(&mut self) -> Engine<'_> {
        self.conn.engine()
    }
}

impl Drop for Tx<'_> {
    fn drop(&mut self) {
        if !self.ended {
            self.conn.discard();
        }
    }
}
