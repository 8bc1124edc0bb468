//! The MCAP files of each machine and their states.

use serde::Serialize;
use sqlx::Row;

use super::statement::query;
use super::{Store, StoreError};

/// An MCAP file's state in the `mcap_files` table (stored as its lowercase name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FileStatus {
    /// Being written (`.partial`).
    Open,
    /// Finished and renamed.
    Closed,
    /// Rescued up to its last flush after a crash.
    Recovered,
}

impl FileStatus {
    /// The stored text.
    pub fn as_str(self) -> &'static str {
        match self {
            FileStatus::Open => "open",
            FileStatus::Closed => "closed",
            FileStatus::Recovered => "recovered",
        }
    }

    fn of_column(s: &str) -> Result<Self, StoreError> {
        match s {
            "open" => Ok(FileStatus::Open),
            "closed" => Ok(FileStatus::Closed),
            "recovered" => Ok(FileStatus::Recovered),
            other => Err(StoreError::Corrupt(format!(
                "file status '{other}' is none of open, closed, recovered"
            ))),
        }
    }
}

impl Store {
    pub async fn mcap_file_opened(
        &self,
        machine: &str,
        path: &str,
        opened_ns: i64,
    ) -> Result<(), StoreError> {
        query(
            "INSERT INTO mcap_files (machine_id, path, opened_ns, status) VALUES ($1, $2, $3, $4)
             ON CONFLICT (path) DO UPDATE SET status = $4, closed_ns = NULL",
        )
        .bind(machine)
        .bind(path)
        .bind(opened_ns)
        .bind(FileStatus::Open.as_str())
        .execute(&mut self.write_conn().await?)
        .await?;
        Ok(())
    }

    /// Mark a file written as `partial` closed under `path` (`closed`), or rescued from a
    /// crash (`recovered`).
    pub async fn mcap_file_closed(
        &self,
        machine: &str,
        partial: &str,
        path: &str,
        closed_ns: i64,
        status: FileStatus,
        messages: i64,
    ) -> Result<(), StoreError> {
        let mut tx = super::Tx::begin(self).await?;
        query(
            "INSERT INTO mcap_files (machine_id, path, opened_ns, status) VALUES ($1, $2, $3, $4)
             ON CONFLICT (path) DO NOTHING",
        )
        .bind(machine)
        .bind(partial)
        .bind(closed_ns)
        .bind(FileStatus::Open.as_str())
        .execute(&mut tx)
        .await?;
        query(
            "UPDATE mcap_files SET path = $2, closed_ns = $3, status = $4, messages = $5 WHERE path = $1",
        )
        .bind(partial)
        .bind(path)
        .bind(closed_ns)
        .bind(status.as_str())
        .bind(messages)
        .execute(&mut tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// (path, status) of every MCAP file of a machine, oldest first.
    pub async fn mcap_files(&self, machine: &str) -> Result<Vec<(String, FileStatus)>, StoreError> {
        let rows = sqlx::query(
            "SELECT path, status FROM mcap_files WHERE machine_id = $1 ORDER BY opened_ns",
        )
        .bind(machine)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok((
                    r.try_get(0)?,
                    FileStatus::of_column(&r.try_get::<String, _>(1)?)?,
                ))
            })
            .collect()
    }
}
