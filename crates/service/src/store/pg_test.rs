//! A throwaway PostgreSQL server for the tests: `initdb` in a fresh directory under the target
//! directory, `postgres` on a free port of 127.0.0.1 with its socket in that directory, started
//! once per test binary, and one fresh database per test ([`database`]), so tests stay
//! independent. The server stops (and its files are removed) when the test binary exits: a
//! shell holds it and waits on a pipe whose writing end only this process has.
//!
//! PostgreSQL refuses to run as root: as root the server runs as the `postgres` user (or
//! `nobody`) through `runuser`. Without PostgreSQL's server programs the tests fail, naming the
//! Debian package to install; they never skip.

use std::path::{Path, PathBuf};
use std::process::{ChildStdin, Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

use sqlx::Connection;

struct Server {
    port: u16,
    /// Closed when the process exits: the shell holding the server then stops it.
    _hold: Mutex<ChildStdin>,
}

fn bin_dir() -> PathBuf {
    if let Ok(d) = std::env::var("DRIFTWATCH_PG_BIN") {
        let d = PathBuf::from(d);
        if d.join("initdb").exists() && d.join("postgres").exists() {
            return d;
        }
        panic!(
            "DRIFTWATCH_PG_BIN={} holds no initdb and postgres: install the Debian package \
             `postgresql` (apt-get install postgresql), or name the directory holding them",
            d.display()
        );
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
        return b;
    }
    for dir in std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default()) {
        if dir.join("initdb").exists() && dir.join("postgres").exists() {
            return dir;
        }
    }
    panic!(
        "PostgreSQL's server programs (initdb, postgres) are not installed, and the store tests \
         run against a real PostgreSQL server: install the Debian package `postgresql` \
         (apt-get install postgresql), or set DRIFTWATCH_PG_BIN to the directory holding them"
    );
}

fn output(cmd: &mut Command) -> Option<String> {
    let out = cmd.output().ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// As root, the unprivileged user the server runs as: `postgres` if it exists, else `nobody`.
fn run_as() -> Option<(String, u32, u32)> {
    if output(Command::new("id").arg("-u")).as_deref() != Some("0") {
        return None;
    }
    for user in ["postgres", "nobody"] {
        if let (Some(uid), Some(gid)) = (
            output(Command::new("id").args(["-u", user])),
            output(Command::new("id").args(["-g", user])),
        ) {
            return Some((user.to_string(), uid.parse().ok()?, gid.parse().ok()?));
        }
    }
    panic!("running as root and neither a `postgres` nor a `nobody` user exists to run PostgreSQL");
}

fn command(user: &Option<(String, u32, u32)>, program: &Path) -> Command {
    match user {
        None => Command::new(program),
        Some((name, _, _)) => {
            let mut c = Command::new("runuser");
            c.args(["-u", name, "--"]).arg(program);
            c
        }
    }
}

fn start() -> Server {
    let bin = bin_dir();
    let user = run_as();
    // Under the target directory (the test binary is in target/<profile>/deps).
    let exe = std::env::current_exe().expect("the test binary's path");
    let target = exe
        .parent()
        .and_then(Path::parent)
        .unwrap_or_else(|| Path::new("."));
    // The server's shell removes what it may when it stops (the directory's contents; the
    // directory itself is the target directory's owner's): empty ones of earlier runs go here.
    for old in std::fs::read_dir(target).into_iter().flatten().flatten() {
        if old.file_name().to_string_lossy().starts_with("pg-test-") {
            let _ = std::fs::remove_dir(old.path());
        }
    }
    let dir = target.join(format!("pg-test-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("the PostgreSQL test directory");
    if let Some((_, uid, gid)) = &user {
        std::os::unix::fs::chown(&dir, Some(*uid), Some(*gid)).expect("chown the test directory");
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
        .expect("run initdb");
    assert!(
        init.status.success(),
        "initdb failed: {}",
        String::from_utf8_lossy(&init.stderr)
    );
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    // The shell starts the server, waits for its standard input to close (this process
    // exiting), then stops the server and removes the directory.
    let script = r#"
        "$1/postgres" -D "$2/data" -p "$3" -k "$2/data" -c listen_addresses=127.0.0.1 \
            -c fsync=off -c synchronous_commit=off -c full_page_writes=off \
            -c max_connections=200 >"$2/server.log" 2>&1 </dev/null &
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
        .expect("start the PostgreSQL server");
    let hold = holder.stdin.take().expect("the holder's stdin");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let ready = Command::new(bin.join("pg_isready"))
            .args(["-q", "-h", "127.0.0.1", "-p", &port.to_string()])
            .status()
            .map(|s| s.success())
            .unwrap_or(false);
        if ready {
            break;
        }
        let log = || std::fs::read_to_string(dir.join("server.log")).unwrap_or_default();
        if let Ok(Some(status)) = holder.try_wait() {
            panic!("the PostgreSQL test server exited ({status}): {}", log());
        }
        assert!(
            Instant::now() < deadline,
            "the PostgreSQL test server did not start within 60 s: {}",
            log()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    Server {
        port,
        _hold: Mutex::new(hold),
    }
}

/// The URL of a fresh, empty database on the test server (started on first use).
pub async fn database() -> String {
    static SERVER: OnceLock<Server> = OnceLock::new();
    static NEXT: AtomicU32 = AtomicU32::new(1);
    let port = tokio::task::spawn_blocking(|| SERVER.get_or_init(start).port)
        .await
        .expect("start the PostgreSQL test server");
    let name = format!("test_{}", NEXT.fetch_add(1, Ordering::Relaxed));
    let admin = format!("postgres://postgres@127.0.0.1:{port}/postgres");
    let mut conn = sqlx::postgres::PgConnection::connect(&admin)
        .await
        .expect("connect to the PostgreSQL test server");
    sqlx::query(sqlx::AssertSqlSafe(format!("CREATE DATABASE {name}")))
        .execute(&mut conn)
        .await
        .expect("create a test database");
    conn.close().await.ok();
    format!("postgres://postgres@127.0.0.1:{port}/{name}")
}
