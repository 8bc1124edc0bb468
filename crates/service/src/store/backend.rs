//! The two database engines behind the store, SQLite (the default, one file in the data
//! directory) and PostgreSQL (`database_url = "postgres://..."`): what differs between them is
//! here, the queries themselves are one portable implementation (reads over sqlx's `Any` driver,
//! writes through [`super::statement`]).
//!
//! What stays SQLite's: the connection's pragmas (WAL, synchronous NORMAL, foreign keys, busy
//! timeout), creating the file, `WITHOUT ROWID` tables (in its migrations only) and
//! `PRAGMA integrity_check` / `journal_mode`.

use std::borrow::Cow;
use std::path::Path;
use std::sync::{LazyLock, Once};

use sqlx::AnyPool;
use sqlx::SqlSafeStr;
use sqlx::any::AnyPoolOptions;
use sqlx::migrate::{Migration, MigrationType, Migrator};

use super::StoreError;

/// Every migration file, `(version, description, text)` (written by the crate's build script).
mod embedded {
    include!(concat!(env!("OUT_DIR"), "/migrations.rs"));
}

/// The SQLite schema (`migrations/sqlite/`).
static SQLITE_MIGRATIONS: LazyLock<Migrator> = LazyLock::new(|| migrator(embedded::SQLITE));
/// The same schema in PostgreSQL's types (`migrations/postgres/`).
static POSTGRES_MIGRATIONS: LazyLock<Migrator> = LazyLock::new(|| migrator(embedded::POSTGRES));

/// The migrations as sqlx resolves a directory of them: the checksum of each file's text (the
/// one a store created earlier holds), in a transaction unless the text opts out.
fn migrator(files: &[(i64, &str, &'static str)]) -> Migrator {
    Migrator::with_migrations(
        files
            .iter()
            .map(|(version, description, sql)| {
                Migration::new(
                    *version,
                    Cow::Owned(description.to_string()),
                    MigrationType::Simple,
                    sqlx::AssertSqlSafe(*sql).into_sql_str(),
                    sql.starts_with("-- no-transaction"),
                )
            })
            .collect(),
    )
}

/// Which engine a store runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    Sqlite,
    Postgres,
}

fn install_drivers() {
    static ONCE: Once = Once::new();
    ONCE.call_once(sqlx::any::install_default_drivers);
}

/// A database URL with its password (if any) left out, for messages and logs.
pub fn redacted(url: &str) -> String {
    match (url.find("://"), url.rfind('@')) {
        (Some(s), Some(at)) if at > s + 3 => {
            let user_info = &url[s + 3..at];
            let user = user_info.split(':').next().unwrap_or("");
            format!("{}{user}@{}", &url[..s + 3], &url[at + 1..])
        }
        _ => url.to_string(),
    }
}

/// Whether SQLite says the file is damaged (SQLITE_CORRUPT) or is not a database
/// (SQLITE_NOTADB), by its primary result code.
fn is_corruption(e: &sqlx::Error) -> bool {
    let sqlx::Error::Database(db) = e else {
        return false;
    };
    let code = db.code().and_then(|c| c.parse::<i64>().ok());
    code.is_some_and(|c| matches!(c & 0xff, 11 | 26))
        || db.message().contains("malformed")
        || db.message().contains("not a database")
}

fn corrupt(url: &str, e: &sqlx::Error) -> StoreError {
    // The file as the user named it: no scheme, no connection options.
    let url = redacted(url);
    let name = url.split('?').next().unwrap_or(&url);
    StoreError::Damaged {
        database: name.strip_prefix("sqlite://").unwrap_or(name).to_string(),
        detail: e.to_string(),
    }
}

/// Every SQLite connection's settings: a 5 s wait on a lock instead of failing, foreign keys
/// enforced, the write-ahead log, and synchronous NORMAL, which in WAL mode never corrupts and
/// keeps every commit through a process crash (only a power loss can take the last commits).
const SQLITE_PRAGMAS: [&str; 4] = [
    "PRAGMA busy_timeout = 5000",
    "PRAGMA foreign_keys = ON",
    "PRAGMA journal_mode = WAL",
    "PRAGMA synchronous = NORMAL",
];

/// The file a `sqlite:` URL names, as sqlx reads the URL.
pub(super) fn sqlite_path(url: &str) -> Result<std::path::PathBuf, StoreError> {
    use std::str::FromStr;
    let options =
        sqlx::sqlite::SqliteConnectOptions::from_str(url).map_err(|source| StoreError::Open {
            path: redacted(url),
            source,
        })?;
    Ok(options.get_filename().to_path_buf())
}

/// The store's SQLite writer ([`super::writer`]): a connection of its own to the file the pool
/// made (never creating one: a file gone since is an error, not a new empty store), with the
/// pool's settings and as many prepared statements kept as sqlx keeps.
pub(super) fn open_sqlite_writer(path: &Path) -> Result<rusqlite::Connection, StoreError> {
    use rusqlite::OpenFlags;
    let open = || {
        let conn = rusqlite::Connection::open_with_flags(
            path,
            OpenFlags::SQLITE_OPEN_READ_WRITE | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )?;
        for pragma in SQLITE_PRAGMAS {
            // Some answer with a row (`journal_mode`): each is read as a query.
            conn.query_row(pragma, [], |_| Ok(()))
                .or_else(|e| match e {
                    rusqlite::Error::QueryReturnedNoRows => Ok(()),
                    e => Err(e),
                })?;
        }
        conn.set_prepared_statement_cache_capacity(100);
        Ok(conn)
    };
    open().map_err(|source| StoreError::OpenWriter {
        path: path.display().to_string(),
        source,
    })
}

/// Whether a connection given back to the pool is fit to be used again: not in a transaction
/// by sqlx's count. The store's own transactions ([`super::Tx`]) give a connection back only
/// after their COMMIT or ROLLBACK succeeded and close it otherwise, so what the engine holds
/// needs no question to it here (a `BEGIN; ROLLBACK` round trip at every release was 40 % of
/// a simulated year's requests to SQLite).
async fn connection_sound(conn: &mut sqlx::AnyConnection) -> Result<bool, sqlx::Error> {
    use sqlx::Connection;
    Ok(!conn.is_in_transaction())
}

/// One connection to the SQLite file before the pool is built: a damaged file, or one that is
/// not a database, is named as such at once (the pool would retry its connections until its
/// acquire timeout and say only that it timed out).
async fn probe_sqlite(url: &str) -> Result<(), StoreError> {
    use sqlx::Connection;
    let named = |e: sqlx::Error| {
        if is_corruption(&e) {
            corrupt(url, &e)
        } else {
            StoreError::Open {
                path: redacted(url),
                source: e,
            }
        }
    };
    let mut conn = sqlx::AnyConnection::connect(url).await.map_err(named)?;
    // Reading the schema reads the file's first pages: a truncated or overwritten file fails.
    for sql in [
        "PRAGMA journal_mode = WAL",
        "SELECT COUNT(*) FROM sqlite_schema",
    ] {
        sqlx::query(sql).execute(&mut conn).await.map_err(named)?;
    }
    conn.close().await.map_err(named)
}

impl Backend {
    /// The engine a URL names: `sqlite://PATH` or `postgres://...` (`postgresql://...`).
    pub fn of_url(url: &str) -> Option<Backend> {
        if url.starts_with("sqlite:") {
            Some(Backend::Sqlite)
        } else if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            Some(Backend::Postgres)
        } else {
            None
        }
    }

    /// The URL of the SQLite file at `path`.
    pub fn sqlite_url(path: &Path) -> String {
        format!("sqlite://{}", path.display())
    }

    /// Connect a pool and apply this engine's migrations.
    pub(super) async fn connect(self, url: &str) -> Result<AnyPool, StoreError> {
        install_drivers();
        let open_error = |source| StoreError::Open {
            path: redacted(url),
            source,
        };
        let pool = match self {
            Backend::Sqlite => {
                // Created if missing (mode=rwc); each connection with `SQLITE_PRAGMAS`.
                let sep = if url.contains('?') { '&' } else { '?' };
                let url = format!("{url}{sep}mode=rwc");
                probe_sqlite(&url).await?;
                AnyPoolOptions::new()
                    // For the reads: the writes have their own connection (`writer`).
                    .max_connections(3)
                    // A ping at each acquire only asks the connection's thread whether it is
                    // there (a file has no network to lose); a connection is unfit only after
                    // a transaction that did not end, and the store closes such a one itself.
                    .test_before_acquire(false)
                    .after_release(|conn, _meta| Box::pin(connection_sound(conn)))
                    .after_connect(|conn, _meta| {
                        Box::pin(async move {
                            for pragma in SQLITE_PRAGMAS {
                                sqlx::query(pragma).execute(&mut *conn).await?;
                            }
                            Ok(())
                        })
                    })
                    .connect(&url)
                    .await
                    .map_err(open_error)?
            }
            Backend::Postgres => AnyPoolOptions::new()
                .max_connections(8)
                .connect(url)
                .await
                .map_err(open_error)?,
        };
        if let Err(e) = self.migrator().run(&pool).await {
            return Err(match e {
                sqlx::migrate::MigrateError::Execute(e) if is_corruption(&e) => corrupt(url, &e),
                e => StoreError::Migrate(e),
            });
        }
        Ok(pool)
    }

    fn migrator(self) -> &'static Migrator {
        match self {
            Backend::Sqlite => &SQLITE_MIGRATIONS,
            Backend::Postgres => &POSTGRES_MIGRATIONS,
        }
    }

    /// The database's clock, ms since the Unix epoch, as an SQL expression: the one clock
    /// every process of a fleet compares its leases with.
    pub(super) fn now_ms_sql(self) -> &'static str {
        match self {
            Backend::Sqlite => "CAST((julianday('now') - 2440587.5) * 86400000.0 AS BIGINT)",
            Backend::Postgres => "CAST(EXTRACT(EPOCH FROM clock_timestamp()) * 1000 AS BIGINT)",
        }
    }

    /// What keeps a row read in a transaction from changing until it commits: PostgreSQL's
    /// `FOR SHARE`; SQLite has one writer at a time and no such clause.
    pub(super) fn share_lock(self) -> &'static str {
        match self {
            Backend::Sqlite => "",
            Backend::Postgres => " FOR SHARE",
        }
    }

    /// SQLite's `PRAGMA integrity_check` ("ok" for a sound file). PostgreSQL has no such
    /// statement (it checks its pages itself): the answer says so.
    pub(super) async fn integrity_check(self, pool: &AnyPool) -> Result<String, StoreError> {
        match self {
            Backend::Sqlite => Ok(sqlx::query_scalar("PRAGMA integrity_check")
                .fetch_one(pool)
                .await?),
            Backend::Postgres => {
                // The server answers: the connection and the schema are there.
                sqlx::query("SELECT 1 FROM machines LIMIT 1")
                    .fetch_optional(pool)
                    .await?;
                Ok("not applicable (PostgreSQL)".to_string())
            }
        }
    }

    /// SQLite's journal mode ("wal" as opened). PostgreSQL always writes ahead to its log:
    /// "wal".
    pub(super) async fn journal_mode(self, pool: &AnyPool) -> Result<String, StoreError> {
        match self {
            Backend::Sqlite => Ok(sqlx::query_scalar("PRAGMA journal_mode")
                .fetch_one(pool)
                .await?),
            Backend::Postgres => Ok("wal".to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_name_their_engine_and_hide_passwords() {
        assert_eq!(Backend::of_url("sqlite://x.db"), Some(Backend::Sqlite));
        assert_eq!(
            Backend::of_url("postgres://u:p@h/db"),
            Some(Backend::Postgres)
        );
        assert_eq!(
            Backend::of_url("postgresql://h/db"),
            Some(Backend::Postgres)
        );
        assert_eq!(Backend::of_url("mysql://h/db"), None);
        assert_eq!(
            redacted("postgres://u:secret@h:5/db"),
            "postgres://u@h:5/db"
        );
        assert_eq!(redacted("postgres://h/db"), "postgres://h/db");
    }

    /// The embedded migrations are what sqlx itself reads from the directories (as its
    /// `migrate!` macro, which earlier builds used, did): the same versions, descriptions and
    /// checksums, so a store created by an earlier build opens and is not migrated again.
    #[tokio::test]
    async fn the_embedded_migrations_are_the_files_as_sqlx_reads_them() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../migrations");
        for (engine, embedded) in [
            ("sqlite", &*SQLITE_MIGRATIONS),
            ("postgres", &*POSTGRES_MIGRATIONS),
        ] {
            let read = Migrator::new(root.join(engine)).await.unwrap();
            let key = |m: &Migration| {
                (
                    m.version,
                    m.description.to_string(),
                    m.checksum.to_vec(),
                    m.no_tx,
                    m.migration_type,
                )
            };
            let want: Vec<_> = read.iter().map(key).collect();
            assert!(want.len() >= 3, "{engine}: {want:?}");
            assert_eq!(
                embedded.iter().map(key).collect::<Vec<_>>(),
                want,
                "{engine}"
            );
        }
    }
}
