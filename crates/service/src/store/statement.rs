//! One statement of a write, on the connection the write holds ([`super::writer`]): SQLite's
//! writer or a PostgreSQL connection of the pool. The SQL is one text for both engines (`$n`
//! placeholders, which both read); only the running differs.
//!
//! On SQLite the statement runs on the calling thread, through `rusqlite` on the writer's own
//! connection. sqlx runs each SQLite connection on a thread of its own, and a write there is
//! tens of microseconds: handing every statement to that thread and waking the caller again
//! cost more than the write (a simulated year, 290 000 statements: 48.5 s wall with the
//! hand-offs, 29.2 s without, the same rows stored). A write so holds its caller's thread for
//! as long as SQLite takes, as the loop's own computing does; a checkpoint of the write-ahead
//! log (every 1000 pages written) is the longest of them. The store's reads stay on sqlx's
//! pool, off the loop's path.

use std::borrow::Cow;

use super::StoreError;

/// A value bound to a statement.
#[derive(Debug, Clone)]
pub(super) enum Arg<'q> {
    Bool(bool),
    Int(Option<i64>),
    Real(Option<f64>),
    Text(Option<Cow<'q, str>>),
}

impl From<bool> for Arg<'_> {
    fn from(v: bool) -> Self {
        Arg::Bool(v)
    }
}
impl From<i64> for Arg<'_> {
    fn from(v: i64) -> Self {
        Arg::Int(Some(v))
    }
}
impl From<Option<i64>> for Arg<'_> {
    fn from(v: Option<i64>) -> Self {
        Arg::Int(v)
    }
}
impl From<f64> for Arg<'_> {
    fn from(v: f64) -> Self {
        Arg::Real(Some(v))
    }
}
impl From<&f64> for Arg<'_> {
    fn from(v: &f64) -> Self {
        Arg::Real(Some(*v))
    }
}
impl From<Option<f64>> for Arg<'_> {
    fn from(v: Option<f64>) -> Self {
        Arg::Real(v)
    }
}
impl<'q> From<&'q str> for Arg<'q> {
    fn from(v: &'q str) -> Self {
        Arg::Text(Some(Cow::Borrowed(v)))
    }
}
impl<'q> From<&'q String> for Arg<'q> {
    fn from(v: &'q String) -> Self {
        Arg::Text(Some(Cow::Borrowed(v)))
    }
}
impl From<String> for Arg<'_> {
    fn from(v: String) -> Self {
        Arg::Text(Some(Cow::Owned(v)))
    }
}
impl<'q> From<Option<&'q str>> for Arg<'q> {
    fn from(v: Option<&'q str>) -> Self {
        Arg::Text(v.map(Cow::Borrowed))
    }
}

/// A statement to run: `query(sql).bind(a).bind(b).execute(&mut conn)`.
pub(super) struct Stmt<'q> {
    sql: Cow<'q, str>,
    args: Vec<Arg<'q>>,
    /// Kept prepared for the next call (the default), or prepared for this call only.
    persistent: bool,
}

pub(super) fn query<'q>(sql: impl Into<Cow<'q, str>>) -> Stmt<'q> {
    Stmt {
        sql: sql.into(),
        args: Vec::new(),
        persistent: true,
    }
}

/// A row a write read back (`RETURNING`, or a check in its transaction).
pub(super) enum Row {
    Sqlite(Vec<rusqlite::types::Value>),
    Any(sqlx::any::AnyRow),
}

impl Row {
    /// Column `i` as a `T`.
    pub(super) fn get<T>(&self, i: usize) -> Result<T, StoreError>
    where
        T: rusqlite::types::FromSql + for<'r> sqlx::Decode<'r, sqlx::Any> + sqlx::Type<sqlx::Any>,
    {
        match self {
            Row::Sqlite(values) => {
                let v = values.get(i).ok_or_else(|| {
                    StoreError::Corrupt(format!(
                        "a row of {} columns has no column {i}",
                        values.len()
                    ))
                })?;
                T::column_result(v.into())
                    .map_err(|e| StoreError::Corrupt(format!("column {i}: {e}")))
            }
            Row::Any(row) => Ok(sqlx::Row::try_get(row, i)?),
        }
    }
}

impl<'q> Stmt<'q> {
    pub(super) fn bind(mut self, value: impl Into<Arg<'q>>) -> Self {
        self.args.push(value.into());
        self
    }

    pub(super) fn persistent(mut self, persistent: bool) -> Self {
        self.persistent = persistent;
        self
    }

    /// Run it; the number of rows it changed.
    pub(super) async fn execute(self, conn: &mut impl Target) -> Result<u64, StoreError> {
        match conn.engine() {
            Engine::Sqlite(c) => Ok(self.on_sqlite(c, |st| st.raw_execute().map(|n| n as u64))?),
            Engine::Any(c) => Ok(self.on_any().execute(c).await?.rows_affected()),
        }
    }

    /// Run it; the rows it gave.
    pub(super) async fn fetch_all(&self, conn: &mut impl Target) -> Result<Vec<Row>, StoreError> {
        match conn.engine() {
            Engine::Sqlite(c) => Ok(self.on_sqlite(c, |st| {
                let n = st.column_count();
                let mut rows = st.raw_query();
                let mut out = Vec::new();
                while let Some(r) = rows.next()? {
                    out.push(Row::Sqlite(
                        (0..n).map(|i| r.get(i)).collect::<Result<_, _>>()?,
                    ));
                }
                Ok(out)
            })?),
            Engine::Any(c) => Ok(self
                .on_any()
                .fetch_all(c)
                .await?
                .into_iter()
                .map(Row::Any)
                .collect()),
        }
    }

    /// Run it; its first row, if it gave one.
    pub(super) async fn fetch_optional(
        &self,
        conn: &mut impl Target,
    ) -> Result<Option<Row>, StoreError> {
        Ok(self.fetch_all(conn).await?.into_iter().next())
    }

    /// Run it; its first row, which it must give.
    pub(super) async fn fetch_one(&self, conn: &mut impl Target) -> Result<Row, StoreError> {
        self.fetch_optional(conn).await?.ok_or_else(|| {
            StoreError::Corrupt(format!("the statement gave no row: {}", summary(&self.sql)))
        })
    }

    /// Prepare it on SQLite's writer, bind its arguments by their `$n` names and hand it to
    /// `run`.
    fn on_sqlite<T>(
        &self,
        c: &rusqlite::Connection,
        run: impl FnOnce(&mut rusqlite::Statement<'_>) -> rusqlite::Result<T>,
    ) -> rusqlite::Result<T> {
        let mut cached;
        let mut once;
        let st: &mut rusqlite::Statement<'_> = if self.persistent {
            cached = c.prepare_cached(&self.sql)?;
            &mut cached
        } else {
            once = c.prepare(&self.sql)?;
            &mut once
        };
        // SQLite numbers parameters in their order of first appearance, which need not be
        // `$1, $2, ...`: each is bound by its name.
        for index in 1..=st.parameter_count() {
            let name = st.parameter_name(index).unwrap_or("");
            let arg = name
                .strip_prefix('$')
                .and_then(|n| n.parse::<usize>().ok())
                .and_then(|n| self.args.get(n.wrapping_sub(1)))
                .ok_or_else(|| rusqlite::Error::InvalidParameterName(name.to_string()))?;
            match arg {
                Arg::Bool(v) => st.raw_bind_parameter(index, v)?,
                Arg::Int(v) => st.raw_bind_parameter(index, v)?,
                Arg::Real(v) => st.raw_bind_parameter(index, v)?,
                Arg::Text(v) => st.raw_bind_parameter(index, v.as_deref())?,
            }
        }
        run(st)
    }

    /// The same statement for sqlx's `Any` driver.
    fn on_any(&self) -> sqlx::query::Query<'_, sqlx::Any, sqlx::any::AnyArguments> {
        let mut q = sqlx::query(sqlx::AssertSqlSafe(self.sql.as_ref())).persistent(self.persistent);
        for arg in &self.args {
            q = match arg {
                Arg::Bool(v) => q.bind(*v),
                Arg::Int(v) => q.bind(*v),
                Arg::Real(v) => q.bind(*v),
                Arg::Text(v) => q.bind(v.as_deref()),
            };
        }
        q
    }
}

/// The start of a statement, for a message.
fn summary(sql: &str) -> String {
    sql.split_whitespace().take(6).collect::<Vec<_>>().join(" ")
}

/// What a statement runs on: the connection a write holds, or its transaction.
pub(super) trait Target {
    fn engine(&mut self) -> Engine<'_>;
}

/// The connection a statement runs on, by engine.
pub(super) enum Engine<'c> {
    Sqlite(&'c rusqlite::Connection),
    Any(&'c mut sqlx::AnyConnection),
}
