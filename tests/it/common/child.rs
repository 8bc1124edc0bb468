//! `driftwatch serve` as a real child process, talked to over plain HTTP/1.1: for the tests
//! that kill it (crash, fleet failover). The only waiting on the wall clock is polling that
//! child (every wait is bounded).

use std::fs::{self, File};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

/// A `driftwatch serve` child; killed if the test panics while it runs.
pub struct Serve {
    pub child: Child,
    pub addr: SocketAddr,
    pub log: PathBuf,
}

impl Drop for Serve {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// The address `serve` says it listens on ("driftwatch serving ... on http://ADDR (...").
fn served_addr(log: &str) -> Option<SocketAddr> {
    let line = log.lines().find(|l| l.starts_with("driftwatch serving"))?;
    let rest = line.split_once("http://")?.1;
    rest.split_whitespace().next()?.parse().ok()
}

impl Serve {
    /// Start `serve` with `args` (plus `--listen 127.0.0.1:0`: a port the system picks, no
    /// race for a free port), read the address it prints, and wait (bounded) until its API
    /// answers.
    pub fn start(args: &[String], log: PathBuf) -> Serve {
        let out = File::create(&log).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_driftwatch"))
            .arg("serve")
            .args(args)
            .arg("--listen")
            .arg("127.0.0.1:0")
            .stdin(Stdio::null())
            .stdout(out.try_clone().unwrap())
            .stderr(out)
            .spawn()
            .unwrap();
        let unbound: SocketAddr = ([127, 0, 0, 1], 0).into();
        let mut s = Serve {
            child,
            addr: unbound,
            log,
        };
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let Some(status) = s.child.try_wait().unwrap() {
                panic!("serve exited at start ({status}):\n{}", s.log_text());
            }
            if s.addr == unbound
                && let Some(a) = served_addr(&s.log_text())
            {
                s.addr = a;
            }
            if s.addr != unbound
                && get(s.addr, "/api/v1/machines").is_some_and(|(code, _)| code == 200)
            {
                return s;
            }
            assert!(
                Instant::now() < deadline,
                "serve did not answer within 30 s:\n{}",
                s.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    pub fn log_text(&self) -> String {
        fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// GET that must answer; the JSON body.
    pub fn get(&self, path: &str) -> (u16, Value) {
        get(self.addr, path).unwrap_or_else(|| panic!("GET {path}: no answer\n{}", self.log_text()))
    }

    /// POST an empty body with a bearer token, that must be answered; the status and JSON
    /// body.
    pub fn post(&self, path: &str, token: &str) -> (u16, Value) {
        request(self.addr, "POST", path, Some(token))
            .unwrap_or_else(|| panic!("POST {path}: no answer\n{}", self.log_text()))
    }

    /// The entry of machine `id` in `/api/v1/machines`.
    pub fn machine(&self, id: &str) -> Value {
        let (code, body) = self.get("/api/v1/machines");
        assert_eq!(code, 200, "{body}");
        body.as_array()
            .and_then(|a| a.iter().find(|m| m["id"] == id))
            .unwrap_or_else(|| panic!("no {id} in {body}"))
            .clone()
    }

    /// Machine `id`'s cycles, newest first.
    pub fn cycles(&self, id: &str) -> Vec<Value> {
        let (code, body) = self.get(&format!("/api/v1/machines/{id}/cycles?limit=1000"));
        assert_eq!(code, 200, "{body}");
        body.as_array().unwrap().clone()
    }

    /// Wait (bounded) for the child to end by itself.
    pub fn wait_exit(&mut self, within: Duration) -> ExitStatus {
        let deadline = Instant::now() + within;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(
                Instant::now() < deadline,
                "serve still running {within:?} after the signal:\n{}",
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

/// A plain HTTP/1.1 GET: status and JSON body (`Null` if the body is not JSON); `None` if the
/// server does not answer.
pub fn get(addr: SocketAddr, path: &str) -> Option<(u16, Value)> {
    request(addr, "GET", path, None)
}

fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    token: Option<&str>,
) -> Option<(u16, Value)> {
    let auth = token.map_or(String::new(), |t| format!("Authorization: Bearer {t}\r\n"));
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\n{auth}Accept: application/json\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    );
    exchange(addr, &head).map(|(code, _, body)| (code, body))
}

/// Send a request's `head` (ending in a blank line; with `Connection: close`) and read the
/// answer to its end: the status, the answer's head and its JSON body (`Null` if not JSON);
/// `None` if the server does not answer.
pub fn exchange(addr: SocketAddr, head: &str) -> Option<(u16, String, Value)> {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(2)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(10))).ok()?;
    s.set_write_timeout(Some(Duration::from_secs(10))).ok()?;
    s.write_all(head.as_bytes()).ok()?;
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).ok()?;
    let text = String::from_utf8(raw).ok()?;
    let (head, body) = text.split_once("\r\n\r\n")?;
    let code = head.split_whitespace().nth(1)?.parse().ok()?;
    let chunked = head.lines().any(|l| {
        let l = l.to_ascii_lowercase();
        l.starts_with("transfer-encoding:") && l.contains("chunked")
    });
    let body = if chunked {
        dechunk(body)?
    } else {
        body.to_string()
    };
    Some((
        code,
        head.to_string(),
        serde_json::from_str(&body).unwrap_or(Value::Null),
    ))
}

fn dechunk(mut s: &str) -> Option<String> {
    let mut out = String::new();
    loop {
        let (size, rest) = s.split_once("\r\n")?;
        let n = usize::from_str_radix(size.split(';').next()?.trim(), 16).ok()?;
        if n == 0 {
            return Some(out);
        }
        out.push_str(rest.get(..n)?);
        s = rest.get(n + 2..)?;
    }
}
