//! One service process per data directory: an exclusive lock on `driftwatch.lock` in it (the
//! operating system's advisory file lock, released when the process ends, however it ends),
//! holding who took it. A second `serve` on the same directory, which would write the same
//! SQLite store and the same recordings, is refused at start with the first one named.
//! Several processes share machines only through PostgreSQL and `[fleet]`, each with its own
//! data directory.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use thiserror::Error;

#[derive(Debug, Error)]
pub enum LockError {
    #[error(
        "the data directory {dir} is in use by another driftwatch process ({holder}): one \
         process per data directory and SQLite store. Stop it first, or give this one its own \
         data_dir (several processes share machines through PostgreSQL and [fleet])"
    )]
    Held { dir: PathBuf, holder: String },
    #[error("cannot lock the data directory {dir} ({path}): {source}")]
    Io {
        dir: PathBuf,
        path: PathBuf,
        source: std::io::Error,
    },
}

/// The held lock: released when dropped (or when the process ends).
#[derive(Debug)]
pub struct DirLock {
    _file: File,
    pub path: PathBuf,
}

/// Take the data directory's lock, writing `who` (process id, address, start time) into it
/// for the message a second process gets.
pub fn lock(dir: &Path, who: &str) -> Result<DirLock, LockError> {
    let path = dir.join("driftwatch.lock");
    let io = |source| LockError::Io {
        dir: dir.to_path_buf(),
        path: path.clone(),
        source,
    };
    // Not truncated on open: the holder's text must stay readable to the refused process.
    let mut file = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(io)?;
    match file.try_lock() {
        Ok(()) => {}
        Err(TryLockError::WouldBlock) => {
            let mut holder = String::new();
            let _ = file.read_to_string(&mut holder);
            let holder = holder.trim();
            return Err(LockError::Held {
                dir: dir.to_path_buf(),
                holder: if holder.is_empty() {
                    "it has not said who it is yet".to_string()
                } else {
                    holder.to_string()
                },
            });
        }
        Err(TryLockError::Error(e)) => return Err(io(e)),
    }
    file.set_len(0).map_err(io)?;
    file.seek(SeekFrom::Start(0)).map_err(io)?;
    file.write_all(who.as_bytes()).map_err(io)?;
    file.flush().map_err(io)?;
    Ok(DirLock { _file: file, path })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_on_a_directory_is_refused_naming_the_first() {
        let (_tmp, dir) = crate::scratch_dir("lock");
        let first = lock(&dir, "pid 1, listening on 127.0.0.1:8080").unwrap();
        let err = lock(&dir, "pid 2").unwrap_err().to_string();
        assert!(
            err.contains("pid 1, listening on 127.0.0.1:8080") && err.contains("in use"),
            "{err}"
        );
        drop(first);
        // Released: the next process takes it and says who it is.
        let second = lock(&dir, "pid 2").unwrap();
        assert_eq!(std::fs::read_to_string(&second.path).unwrap(), "pid 2");
    }
}
