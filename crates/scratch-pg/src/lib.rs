//! A throwaway PostgreSQL server, for the tests and the fleet benchmark: `initdb` in a fresh
//! directory, `postgres` on a free port of 127.0.0.1 with its socket in that directory, and one
//! fresh database per user of it ([`ScratchPg::database`]), so tests stay independent. The
//! server stops (and its files are removed) when this process exits or drops the handle: a
//! shell holds it and waits on a pipe whose writing end only this process has.
//!
//! PostgreSQL refuses to run as root: as root the server runs as the `postgres` user (or
//! `nobody`) through `runuser`. Without PostgreSQL's server programs the error names the
//! Debian package to install; the tests that need a server fail with it, they never skip.

use std::path::{Path, PathBuf};
use std::process::{ChildStdin, Command, Stdio};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use sqlx::Connection;

/// A running throwaway server.
#[derive(Debug)]
pub struct ScratchPg {
    pub port: u16,
    /// The server's programs (initdb, postgres, createdb).
    bin: PathBuf,
    /// Its directory (data, socket, log), removed when it stops.
    pub dir: PathBuf,
    next: AtomicU32,
    /// Closed when this is dropped or the process exits: the shell holding the server then
    /// stops it.
    _hold: Mutex<ChildStdin>,
}

fn bin_dir() -> Result<PathBuf, String> {
    if let Ok(d) = std::env::var("DRIFTWATCH_PG_BIN") {
        let d = PathBuf::from(d);
        if d.join("initdb").exists() && d.join("postgres").exists() {
            return Ok(d);
        }
        return Err(format!(
            "DRIFTWATCH_PG_BIN={} holds no initdb and postgres: install the Debian package \
             `postgresql` (apt-get install postgresql), or name the directory holding them",
            d.display()
        ));
    }
    // Debian's layout, newest version first, then the PATH.
    let mut versions: Vec<PathBuf> = std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path().join("bin"))
        .filter(|b| b.join("initdb").exists())
        .collect();
    versions.sort_by_key(|b| {
        b.parent()
            .and_then(|v| v.file_name()?.to_str()?.parse::<u32>().ok())
            .unwrap_or(0)
    });
    if let Some(b) = versions.pop() {
        return Ok(b);
    }
    for dir in std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default()) {
        if dir.join("initdb").exists() && dir.join("postgres").exists() {
            return Ok(dir);
        }
    }
    Err(
        "PostgreSQL's server programs (initdb, postgres) are not installed: install the Debian \
         package `postgresql` (apt-get install postgresql), or set DRIFTWATCH_PG_BIN to the \
         directory holding them"
            .to_string(),
    )
}

fn output(cmd: &mut Command) -> Option<String> {
    let out = cmd.output().ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// As root, the unprivileged user the server runs as: `postgres` if it exists, else `nobody`.
type RunAs = Option<(String, u32, u32)>;

fn run_as() -> Result<RunAs, String> {
    if output(Command::new("id").arg("-u")).as_deref() != Some("0") {
        return Ok(None);
    }
    for user in ["postgres", "nobody"] {
        if let (Some(uid), Some(gid)) = (
            output(Command::new("id").args(["-u", user])),
            output(Command::new("id").args(["-g", user])),
        ) && let (Ok(uid), Ok(gid)) = (uid.parse(), gid.parse())
        {
            return Ok(Some((user.to_string(), uid, gid)));
        }
    }
    Err(
        "running as root and neither a `postgres` nor a `nobody` user exists to run PostgreSQL"
            .to_string(),
    )
}

fn command(user: &RunAs, program: &Path) -> Command {
    match user {
        None => Command::new(program),
        Some((name, _, _)) => {
            let mut c = Command::new("runuser");
            c.args(["-u", name, "--"]).arg(program);
            c
        }
    }
}

impl ScratchPg {
    /// Start a server in a new directory `pg-<pid>-<n>` under `parent` (directories of earlier
    /// runs left there empty are removed first).
    pub fn start(parent: &Path) -> Result<ScratchPg, String> {
        static STARTED: AtomicU32 = AtomicU32::new(0);
        let bin = bin_dir()?;
        let user = run_as()?;
        // Absolute: the server reads its socket directory (`-k`) from inside its data
        // directory, so a relative `parent` (`bench fleet`'s default `out/bench`) would name
        // a directory that is not there.
        let parent = std::path::absolute(parent)
            .map_err(|e| format!("naming the server's directory ({}): {e}", parent.display()))?;
        // The server's shell removes what it may when it stops (the directory's contents; the
        // directory itself belongs to `parent`'s owner): empty ones of earlier runs go here.
        for old in std::fs::read_dir(&parent).into_iter().flatten().flatten() {
            if old.file_name().to_string_lossy().starts_with("pg-") {
                let _ = std::fs::remove_dir(old.path());
            }
        }
        let dir = parent.join(format!(
            "pg-{}-{}",
            std::process::id(),
            STARTED.fetch_add(1, Ordering::Relaxed)
        ));
        let io = |what: &str, e: std::io::Error| format!("{what} ({}): {e}", dir.display());
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).map_err(|e| io("creating the server's directory", e))?;
        if let Some((_, uid, gid)) = &user {
            std::os::unix::fs::chown(&dir, Some(*uid), Some(*gid))
                .map_err(|e| io("handing the directory to the server's user", e))?;
        }
        let data = dir.join("data");
        let init = command(&user, &bin.join("initdb"))
            .arg("-D")
            .arg(&data)
            .args([
                "-U",
                "postgres",
                "--auth=trust",
                "--encoding=UTF8",
                "--locale=C",
                "--no-sync",
            ])
            .output()
            .map_err(|e| io("running initdb", e))?;
        if !init.status.success() {
            return Err(format!(
                "initdb failed: {}",
                String::from_utf8_lossy(&init.stderr)
            ));
        }
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map_err(|e| io("finding a free port", e))?
            .port();
        // The shell starts the server, waits for its standard input to close (this process
        // exiting or dropping the handle), then stops the server and removes the directory.
        let script = r#"
            "$1/postgres" -D "$2/data" -p "$3" -k "$2/data" -c listen_addresses=127.0.0.1 \
                -c fsync=off -c synchronous_commit=off -c full_page_writes=off \
                -c max_connections=300 >"$2/server.log" 2>&1 </dev/null &
            pid=$!
            cat >/dev/null
            kill -INT "$pid"
            wait "$pid"
            rm -rf "$2"/* 2>/dev/null; rmdir "$2" 2>/dev/null
        "#;
        let mut holder = command(&user, Path::new("/bin/sh"))
            .args(["-c", script, "sh"])
            .arg(&bin)
            .arg(&dir)
            .arg(port.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| io("starting the server", e))?;
        let hold = holder
            .stdin
            .take()
            .ok_or("the server's holder has no standard input")?;
        let deadline = Instant::now() + Duration::from_secs(60);
        let log = || std::fs::read_to_string(dir.join("server.log")).unwrap_or_default();
        loop {
            let ready = Command::new(bin.join("pg_isready"))
                .args(["-q", "-h", "127.0.0.1", "-p", &port.to_string()])
                .status()
                .map(|s| s.success())
                .unwrap_or(false);
            if ready {
                break;
            }
            if let Ok(Some(status)) = holder.try_wait() {
                return Err(format!(
                    "the PostgreSQL server exited ({status}): {}",
                    log()
                ));
            }
            if Instant::now() > deadline {
                return Err(format!(
                    "the PostgreSQL server did not start within 60 s: {}",
                    log()
                ));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        Ok(ScratchPg {
            port,
            bin,
            dir,
            next: AtomicU32::new(1),
            _hold: Mutex::new(hold),
        })
    }

    /// The URL of a database on this server.
    pub fn url(&self, name: &str) -> String {
        format!("postgres://postgres@127.0.0.1:{}/{name}", self.port)
    }

    /// The size of database `name` on disk, bytes.
    pub async fn database_size(&self, name: &str) -> Result<i64, sqlx::Error> {
        let mut conn = sqlx::postgres::PgConnection::connect(&self.url("postgres")).await?;
        let size: i64 = sqlx::query_scalar("SELECT pg_database_size($1)")
            .bind(name)
            .fetch_one(&mut conn)
            .await?;
        conn.close().await.ok();
        Ok(size)
    }

    /// A fresh, empty database made without an async runtime (PostgreSQL's `createdb`): its
    /// name and URL.
    pub fn database_blocking(&self) -> Result<(String, String), String> {
        let name = format!("db_{}", self.next.fetch_add(1, Ordering::Relaxed));
        let out = Command::new(self.bin.join("createdb"))
            .args([
                "-h",
                "127.0.0.1",
                "-p",
                &self.port.to_string(),
                "-U",
                "postgres",
            ])
            .arg(&name)
            .output()
            .map_err(|e| format!("running createdb: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "createdb {name} failed: {}",
                String::from_utf8_lossy(&out.stderr)
            ));
        }
        let url = self.url(&name);
        Ok((name, url))
    }

    /// A fresh, empty database: its name and URL.
    pub async fn database(&self) -> Result<(String, String), sqlx::Error> {
        let name = format!("db_{}", self.next.fetch_add(1, Ordering::Relaxed));
        let mut conn = sqlx::postgres::PgConnection::connect(&self.url("postgres")).await?;
        sqlx::query(sqlx::AssertSqlSafe(format!("CREATE DATABASE {name}")))
            .execute(&mut conn)
            .await?;
        conn.close().await.ok();
        let url = self.url(&name);
        Ok((name, url))
    }
}

/// For a crate's own tests: one server per test binary under the target directory, and the
/// URL of a fresh database on it (panics: a test without its server fails).
pub async fn test_database() -> String {
    static SERVER: std::sync::OnceLock<ScratchPg> = std::sync::OnceLock::new();
    let server: &'static ScratchPg = tokio::task::spawn_blocking(|| {
        SERVER.get_or_init(|| {
            // The test binary is in target/<profile>/deps.
            let exe = std::env::current_exe().expect("the test binary's path");
            let target = exe
                .parent()
                .and_then(Path::parent)
                .unwrap_or(Path::new("."));
            ScratchPg::start(target).unwrap_or_else(|e| panic!("{e}"))
        })
    })
    .await
    .expect("start the PostgreSQL test server");
    server.database().await.expect("create a test database").1
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A parent named relative to the working directory (as `bench fleet`'s default
    /// `out/bench`) gives a server that starts and makes databases.
    #[test]
    fn a_server_starts_under_a_relative_parent() {
        // The target directory (the test binary is in target/<profile>/deps), named from the
        // working directory by way of their common ancestor.
        let exe = std::env::current_exe().unwrap();
        let target = exe.parent().and_then(Path::parent).unwrap();
        let cwd = std::env::current_dir().unwrap();
        let common = cwd.ancestors().find(|a| target.starts_with(a)).unwrap();
        let up: std::path::PathBuf = cwd
            .strip_prefix(common)
            .unwrap()
            .components()
            .map(|_| "..")
            .collect();
        let parent = up
            .join(target.strip_prefix(common).unwrap())
            .join(format!("scratch-pg-relative-{}", std::process::id()));
        assert!(parent.is_relative());
        std::fs::create_dir_all(&parent).unwrap();
        let server = ScratchPg::start(&parent).unwrap_or_else(|e| panic!("{e}"));
        let (name, _) = server.database_blocking().unwrap();
        assert!(name.starts_with("db_"), "{name}");
        drop(server);
        let _ = std::fs::remove_dir_all(&parent);
    }
}
