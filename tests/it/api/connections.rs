//! The server's connection limits (`[http]` max_connections, header_read_timeout_s,
//! idle_timeout_s): idle and slow sockets are closed by the server within their timeouts, a
//! flood beyond the cap evicts only itself, and meanwhile the NC's `GET /compensation` is
//! answered. Short timeouts from the test's configuration; small, bounded socket counts on
//! 127.0.0.1.

use std::time::Duration;

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::Instant;

use super::common::{MIN, TestService, launch_test, patent_m1, scratch};

const COMPENSATION: &str = "/api/v1/machines/m1/compensation";
/// Slack for a loaded CI machine on every bound a test waits for.
const SLACK: Duration = Duration::from_secs(10);

/// The patent day's `m1` with the given limits, run until it serves a validated set.
async fn service(name: &str, cap: usize, header_read_s: f64, idle_s: f64) -> TestService {
    let mut cfg = patent_m1(&scratch(&format!("api-conns-{name}")));
    cfg.http.max_connections = cap;
    cfg.http.header_read_timeout_s = header_read_s;
    cfg.http.idle_timeout_s = idle_s;
    let app = launch_test(cfg, None).await;
    app.run_to(app.t0() + 45 * MIN).await;
    app
}

/// The NC's poll: the set with its ETag, then 304 with If-None-Match; each answered within
/// the slack.
async fn nc_polls(app: &TestService) {
    let get = Request::get(COMPENSATION).body(Body::empty()).unwrap();
    let (s, h, body) = tokio::time::timeout(SLACK, app.call(get))
        .await
        .expect("the NC's GET is answered");
    assert_eq!(s, StatusCode::OK, "{body}");
    assert!(body["version"].as_u64().unwrap() >= 1);
    let etag = h[header::ETAG].to_str().unwrap().to_string();
    let again = Request::get(COMPENSATION)
        .header(header::IF_NONE_MATCH, &etag)
        .body(Body::empty())
        .unwrap();
    let (s, _, _) = tokio::time::timeout(SLACK, app.call(again))
        .await
        .expect("the NC's second GET is answered");
    assert_eq!(s, StatusCode::NOT_MODIFIED);
}

/// One request on `s` and its answer's head (the body, sized by Content-Length, read past),
/// within the slack.
async fn exchange(s: &mut TcpStream, request: &str) -> String {
    s.write_all(request.as_bytes()).await.unwrap();
    let mut buf: Vec<u8> = Vec::new();
    let mut chunk = [0u8; 4096];
    loop {
        let n = tokio::time::timeout(SLACK, s.read(&mut chunk))
            .await
            .expect("answered within the slack")
            .unwrap();
        assert!(n > 0, "the server closed the NC's connection");
        buf.extend_from_slice(&chunk[..n]);
        let Some(end) = buf.windows(4).position(|w| w == b"\r\n\r\n") else {
            continue;
        };
        let head = String::from_utf8_lossy(&buf[..end]).to_string();
        let length: usize = head
            .lines()
            .find_map(|l| {
                let (k, v) = l.split_once(':')?;
                k.eq_ignore_ascii_case("content-length")
                    .then(|| v.trim().parse().ok())?
            })
            .unwrap_or(0);
        while buf.len() < end + 4 + length {
            let n = tokio::time::timeout(SLACK, s.read(&mut chunk))
                .await
                .expect("the body within the slack")
                .unwrap();
            assert!(n > 0, "the server closed the NC's connection mid-body");
            buf.extend_from_slice(&chunk[..n]);
        }
        return head;
    }
}

/// The NC's two polls on one kept-alive connection of its own (a client's pool may open a
/// second connection for the second poll, which at the cap would rightly close a flood
/// socket): the set with its ETag, then 304 with If-None-Match.
async fn nc_polls_on_one_connection(addr: std::net::SocketAddr) {
    let mut s = TcpStream::connect(addr).await.unwrap();
    let head = exchange(
        &mut s,
        &format!("GET {COMPENSATION} HTTP/1.1\r\nHost: test\r\n\r\n"),
    )
    .await;
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    let etag = head
        .lines()
        .find_map(|l| {
            let (k, v) = l.split_once(':')?;
            k.eq_ignore_ascii_case("etag").then(|| v.trim().to_string())
        })
        .expect("an ETag");
    let head = exchange(
        &mut s,
        &format!("GET {COMPENSATION} HTTP/1.1\r\nHost: test\r\nIf-None-Match: {etag}\r\n\r\n"),
    )
    .await;
    assert!(head.starts_with("HTTP/1.1 304"), "{head}");
}

/// Wait (at most the slack) until the server closes `s`: end of stream or a reset. The time
/// it took, from `since`. Any byte received is a failure: these sockets sent no request.
async fn closed_by_server(s: &mut TcpStream, since: Instant) -> Duration {
    let mut buf = [0u8; 256];
    match tokio::time::timeout(SLACK, s.read(&mut buf)).await {
        Ok(Ok(0)) | Ok(Err(_)) => since.elapsed(),
        Ok(Ok(n)) => panic!(
            "the server answered a socket that sent no request: {:?}",
            String::from_utf8_lossy(&buf[..n])
        ),
        Err(_) => panic!("the server kept the socket open beyond {SLACK:?}"),
    }
}

/// A slowloris client: a request line, then one header byte every 100 ms, never the blank
/// line. Returns how long the server let it trickle, and how many bytes it sent.
async fn slowloris(addr: std::net::SocketAddr) -> (Duration, usize) {
    let s = TcpStream::connect(addr).await.unwrap();
    let t0 = Instant::now();
    let (mut rd, mut wr) = s.into_split();
    // Atomic only to be shared by the two halves' futures (the task may move between threads).
    let sent = std::sync::atomic::AtomicUsize::new(0);
    let trickle = async {
        let head = format!("GET {COMPENSATION} HTTP/1.1\r\nHost: test\r\nX-Slow: ");
        if wr.write_all(head.as_bytes()).await.is_err() {
            return;
        }
        loop {
            tokio::time::sleep(Duration::from_millis(100)).await;
            if wr.write_all(b"a").await.is_err() {
                return;
            }
            sent.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
    };
    let mut buf = [0u8; 256];
    let closed = async {
        match rd.read(&mut buf).await {
            Ok(0) | Err(_) => {}
            Ok(n) => panic!(
                "the server answered an incomplete head: {:?}",
                String::from_utf8_lossy(&buf[..n])
            ),
        }
    };
    tokio::time::timeout(SLACK, async {
        tokio::select! {
            () = trickle => {}
            () = closed => {}
        }
    })
    .await
    .expect("the server cuts a slowloris connection");
    (t0.elapsed(), sent.into_inner())
}

/// The client's clock starts when its connect or write returns, which may be a little after
/// the server's (accept, answer) started: lower bounds are held with this much leeway.
const LEEWAY: Duration = Duration::from_millis(200);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_and_slow_sockets_are_closed_at_their_timeouts_while_the_nc_is_answered() {
    // A cap well above the sockets opened here: every close is a timeout's, none the cap's.
    let header_read = Duration::from_secs(1);
    let idle = Duration::from_millis(1500);
    let app = service(
        "timeouts",
        64,
        header_read.as_secs_f64(),
        idle.as_secs_f64(),
    )
    .await;
    let addr = app.svc.addr;
    let mut flood = Vec::new();
    for _ in 0..20 {
        flood.push((TcpStream::connect(addr).await.unwrap(), Instant::now()));
    }
    let slow =
        tokio::spawn(
            async move { tokio::join!(slowloris(addr), slowloris(addr), slowloris(addr)) },
        );
    // A kept-alive connection: one request, its answer, then nothing.
    let mut kept = TcpStream::connect(addr).await.unwrap();
    let req = format!("GET {COMPENSATION} HTTP/1.1\r\nHost: test\r\n\r\n");
    kept.write_all(req.as_bytes()).await.unwrap();
    let kept_sent = Instant::now();
    nc_polls(&app).await;
    for (s, since) in &mut flood {
        let took = closed_by_server(s, *since).await;
        // The server's clock starts at its accept, after the client's connect returned.
        assert!(
            took + LEEWAY >= header_read,
            "closed after {took:?}, before its timeout"
        );
        assert!(took < header_read + SLACK);
    }
    let (a, b, c) = slow.await.unwrap();
    for (took, sent) in [a, b, c] {
        assert!(took + LEEWAY >= header_read, "slowloris cut after {took:?}");
        assert!(took < header_read + SLACK);
        // It kept sending all along, and was cut all the same.
        assert!(sent >= 2, "slowloris sent {sent} bytes before the cut");
    }
    // The kept-alive connection got its answer, then was closed at its idle timeout.
    let mut answer = Vec::new();
    tokio::time::timeout(SLACK, kept.read_to_end(&mut answer))
        .await
        .expect("the server closes an idle kept-alive connection")
        .unwrap();
    let took = kept_sent.elapsed();
    let text = String::from_utf8_lossy(&answer);
    assert!(text.starts_with("HTTP/1.1 200"), "{text}");
    // Its idle timeout, not the shorter header-read timeout.
    assert!(
        took + LEEWAY >= idle,
        "kept-alive connection closed after {took:?}"
    );
    // The NC is still answered after all that (on a new connection: the client's pooled one
    // may be the one the server has just closed at its idle timeout).
    let mut fresh = TcpStream::connect(addr).await.unwrap();
    let once = format!("GET {COMPENSATION} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n");
    fresh.write_all(once.as_bytes()).await.unwrap();
    let mut answer = Vec::new();
    tokio::time::timeout(SLACK, fresh.read_to_end(&mut answer))
        .await
        .expect("answered")
        .unwrap();
    assert!(answer.starts_with(b"HTTP/1.1 200"));
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_beyond_the_cap_evicts_itself_oldest_first_and_the_nc_is_answered() {
    // Timeouts far beyond the test: every close seen here is the cap's.
    let cap = 8;
    let app = service("cap", cap, 120.0, 120.0).await;
    let addr = app.svc.addr;
    let mut flood = Vec::new();
    for _ in 0..(4 * cap) {
        flood.push((TcpStream::connect(addr).await.unwrap(), Instant::now()));
    }
    // The oldest were closed to make room for the newer: all but the last `cap`.
    let (old, newest) = flood.split_at_mut(3 * cap);
    for (s, since) in old.iter_mut() {
        closed_by_server(s, *since).await;
    }
    // The NC connects now and is answered, twice on its kept-alive connection: that
    // connection takes the place of the oldest idle socket, never its own, and its second poll
    // needs no room.
    nc_polls_on_one_connection(addr).await;
    let (s, since) = &mut newest[0];
    closed_by_server(s, *since).await;
    // The others are open still.
    for (s, _) in &newest[1..] {
        let mut buf = [0u8; 1];
        match s.try_read(&mut buf) {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            other => panic!("a socket within the cap was closed: {other:?}"),
        }
    }
    // Shutdown closes them (the service stops within its bound).
    app.stop().await;
}
