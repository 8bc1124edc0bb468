//! The HTTP server: the API's router on hyper's connections (HTTP/1.1 and HTTP/2, as
//! `axum::serve` serves it), each connection driven by a task of its own that holds it to the
//! `[http]` limits, so that idle or slow sockets cannot starve the NC's requests:
//!
//! - **header-read timeout**: a new connection must send a complete request head within
//!   `header_read_timeout_s` of its accept, and a kept-alive connection within that of the
//!   first byte of its next request; a client that trickles its head (slowloris) is cut there
//!   however steadily it sends.
//! - **idle timeout**: a kept-alive connection that has not begun its next request within
//!   `idle_timeout_s` of its last answer is closed.
//! - **connection cap**: at most `max_connections` are open. At the cap a new connection is
//!   still accepted and the oldest connection that has not yet sent a complete request head is
//!   closed for it (failing that, the one kept alive idle the longest): a flood of idle or
//!   slow sockets then only ever evicts itself, and a client that sends its request promptly
//!   (the NC) is answered. Connections with a request in progress are never closed for room;
//!   when all are busy, accepting waits (the kernel's backlog holds the client) until one ends.
//!
//! Without these, every idle socket stayed open until its client left, and at the process's
//! file limit `accept` failed and no one was answered.
//!
//! A request's time in the handler is bounded by the router's own `request_timeout_s`.
//! Graceful shutdown: accepting stops, idle connections close, requests in progress finish
//! (a connection still sending its head has at most its header-read timeout).

use std::collections::BTreeMap;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::Router;
use axum::body::{Body, Bytes};
use hyper::body::{Body as HttpBody, Frame, Incoming, SizeHint};
use hyper_util::rt::{TokioExecutor, TokioIo};
use hyper_util::server::conn::auto::Builder;
use hyper_util::service::TowerToHyperService;
use thiserror::Error;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Notify;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tower::ServiceExt as _;
use tracing::{debug, info, warn};

use crate::config::HttpConfig;

/// The limits a connection is held to (`[http]` in the configuration).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConnLimits {
    pub max_connections: usize,
    pub header_read_timeout: Duration,
    pub idle_timeout: Duration,
}

impl ConnLimits {
    /// The configuration's limits (validated by `ServiceConfig::validate`).
    pub fn from_config(http: &HttpConfig) -> Self {
        ConnLimits {
            max_connections: http.max_connections,
            header_read_timeout: Duration::from_secs_f64(http.header_read_timeout_s),
            idle_timeout: Duration::from_secs_f64(http.idle_timeout_s),
        }
    }
}

#[derive(Debug, Error)]
pub enum ServerError {
    #[error(
        "http.max_connections = {max_connections} does not fit the process's file limit of \
         {soft} (hard limit {hard}): the service keeps {reserved} file descriptors for its \
         database, recordings and links beside one per connection (and one more being \
         accepted); lower http.max_connections to at most {fits}, or raise the limit \
         (LimitNOFILE= in the systemd unit, `ulimit -n` in a shell)"
    )]
    FileLimit {
        max_connections: usize,
        soft: u64,
        hard: u64,
        reserved: u64,
        fits: u64,
    },
}

/// File descriptors kept beside the connections: the two runtimes (the loops' and the API's),
/// standard streams and logs, the store's pool (a SQLite connection holds the database, its
/// WAL and shared memory: 3 each; PostgreSQL one socket each), webhook deliveries and the
/// recordings diagnoses read (one file at a time each): 96 in all; and per machine its open
/// recording, and for a link over a socket of its own (MTConnect, OPC UA) two more (the
/// session and a reconnect). A running service with one simulated machine holds about 30; ten
/// thousand nc_push machines hold one each (their NCs come in over the API's connections).
pub fn reserved_fds(machines: usize, socket_links: usize) -> u64 {
    96 + machines as u64 + 2 * socket_links as u64
}

/// The process's file limit as it stands after [`raise_file_limit`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FileLimit {
    pub soft: u64,
    pub hard: u64,
}

/// Raise the soft limit on open files (RLIMIT_NOFILE) to the hard limit where the system
/// allows it, and log both: a shell's or unit's common soft limit of 1024 would otherwise cap
/// the connections the service can hold. A refusal is logged; the limit then stays.
pub fn raise_file_limit() -> io::Result<FileLimit> {
    let (before, hard) = rlimit::getrlimit(rlimit::Resource::NOFILE)?;
    let soft = match rlimit::increase_nofile_limit(hard) {
        Ok(soft) => soft,
        Err(e) => {
            warn!(soft = before, hard, error = %e, "the open-file limit could not be raised to its hard limit");
            before
        }
    };
    if soft != before {
        info!(
            soft,
            hard,
            was = before,
            "open-file limit raised to the hard limit"
        );
    } else {
        info!(soft, hard, "open-file limit");
    }
    Ok(FileLimit { soft, hard })
}

/// Whether `max_connections` fits the file limit beside [`reserved_fds`]; refused rather
/// than lowered, so that the cap in force is the one configured (the message says what fits).
pub fn check_fits(
    max_connections: usize,
    machines: usize,
    socket_links: usize,
    limit: FileLimit,
) -> Result<(), ServerError> {
    let reserved = reserved_fds(machines, socket_links);
    // One more than the cap: a connection is accepted before the one it replaces is closed.
    let needed = (max_connections as u64)
        .saturating_add(1)
        .saturating_add(reserved);
    if needed <= limit.soft {
        Ok(())
    } else {
        Err(ServerError::FileLimit {
            max_connections,
            soft: limit.soft,
            hard: limit.hard,
            reserved,
            fits: limit.soft.saturating_sub(reserved + 1),
        })
    }
}

/// Raise the file limit and check the cap against it, before the server starts.
pub fn prepare(
    limits: &ConnLimits,
    machines: usize,
    socket_links: usize,
) -> Result<(), ServerError> {
    match raise_file_limit() {
        Ok(limit) => check_fits(limits.max_connections, machines, socket_links, limit),
        // No limit to read (not a Unix system): nothing to hold the cap to.
        Err(e) => {
            warn!(error = %e, "the open-file limit could not be read");
            Ok(())
        }
    }
}

/// Serve `app` on `listener` under `limits` until `shutdown`, then close gracefully: stop
/// accepting, let requests in progress finish, and return once every connection has closed.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: ConnLimits,
    shutdown: CancellationToken,
) -> io::Result<()> {
    let registry = Arc::new(Registry::default());
    let tasks = TaskTracker::new();
    let mut next_id = 0u64;
    info!(
        max_connections = limits.max_connections,
        header_read_timeout_s = limits.header_read_timeout.as_secs_f64(),
        idle_timeout_s = limits.idle_timeout.as_secs_f64(),
        "HTTP connection limits"
    );
    loop {
        // Over the cap (all busy when the last was accepted): wait for room before accepting.
        while registry.len() > limits.max_connections {
            if registry.evict(None, limits.max_connections) {
                continue;
            }
            tokio::select! {
                _ = registry.freed.notified() => {}
                // A busy connection that turns idle frees no slot but becomes evictable.
                _ = tokio::time::sleep(ROOM_POLL) => {}
                _ = shutdown.cancelled() => break,
            }
        }
        let stream = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(e) if is_connection_error(&e) => continue,
                Err(e) => {
                    // Out of file descriptors or the like: the cap fits the limit, so this
                    // means something else holds them; try again shortly.
                    warn!(error = %e, "accepting a connection failed; trying again");
                    tokio::select! {
                        _ = tokio::time::sleep(ACCEPT_RETRY) => continue,
                        _ = shutdown.cancelled() => break,
                    }
                }
            },
            _ = shutdown.cancelled() => break,
        };
        next_id += 1;
        let conn = Arc::new(Conn::new(next_id));
        registry.insert(conn.clone());
        if registry.len() > limits.max_connections {
            registry.evict(Some(conn.id), limits.max_connections);
        }
        tasks.spawn(drive(
            conn,
            stream,
            app.clone(),
            limits,
            shutdown.clone(),
            registry.clone(),
        ));
        // Let the connections just accepted read their heads before the next accept: under a
        // flood that reconnects as fast as it is cut, a prompt client's head must arrive before
        // the cap's worth of newer connections makes it the oldest without a request.
        tokio::task::yield_now().await;
    }
    drop(listener);
    tasks.close();
    tasks.wait().await;
    Ok(())
}

/// The API served by a runtime of its own, on threads of its own ([`serve_apart`]): what
/// the service keeps of it.
pub struct ApartServer {
    ended: tokio::sync::oneshot::Receiver<io::Result<()>>,
    /// Dropped when the service has closed its store: the runtime is kept until then.
    _keep: std::sync::mpsc::Sender<()>,
    /// The server's own shutdown (a child of the service's): a service dropped without being
    /// stopped stops its API too, as it did when the server was a task of the loops' runtime.
    stop: CancellationToken,
}

impl Drop for ApartServer {
    fn drop(&mut self) {
        self.stop.cancel();
    }
}

impl ApartServer {
    /// Wait for the server to close its last connection (after `shutdown`); `Err` with a
    /// message when its thread ended without an outcome (a panic).
    pub async fn ended(&mut self) -> Result<io::Result<()>, &'static str> {
        (&mut self.ended)
            .await
            .map_err(|_| "the API's thread ended without closing its connections (it panicked)")
    }

    /// Let the API's runtime go: after the store has closed. A store connection the API opened
    /// (PostgreSQL's pool grows from whichever request needs one) is driven by this runtime's
    /// reactor, and the loops and the store's close may use it after the server has ended.
    pub fn release(self) {}
}

/// [`serve`] on a runtime and threads of its own, apart from the machine loops' runtime.
///
/// Why apart: on one runtime a request waits for a worker, and at ten thousand loops that catch
/// up as fast as they can every worker is running a loop's step (a SQLite write holds its
/// thread for as long as SQLite takes). The NC's `GET /compensation` then waited behind them.
/// On threads of its own the request is the operating system's to schedule, which wakes a
/// thread that was waiting on its socket ahead of the busy ones.
pub fn serve_apart(
    listener: TcpListener,
    app: Router,
    limits: ConnLimits,
    shutdown: CancellationToken,
) -> io::Result<ApartServer> {
    let listener = listener.into_std()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .thread_name("driftwatch-api")
        .enable_all()
        .build()?;
    let (ended_tx, ended) = tokio::sync::oneshot::channel();
    let (keep, kept) = std::sync::mpsc::channel::<()>();
    let stop = shutdown.child_token();
    let server_stop = stop.clone();
    std::thread::Builder::new()
        .name("driftwatch-api".into())
        .spawn(move || {
            let served = rt.block_on(async move {
                // Registered with this runtime's reactor, as are the connections it accepts.
                serve(TcpListener::from_std(listener)?, app, limits, server_stop).await
            });
            let _ = ended_tx.send(served);
            // Until the service lets it go, or is dropped without waiting for it.
            let _ = kept.recv();
            drop(rt);
        })?;
    Ok(ApartServer {
        ended,
        _keep: keep,
        stop,
    })
}

/// How often a full server looks again for a connection it may close for room.
const ROOM_POLL: Duration = Duration::from_millis(50);
/// Wait after an accept that failed for a reason other than the connection itself.
const ACCEPT_RETRY: Duration = Duration::from_millis(100);
/// Warnings that connections are being closed for room come at most this often.
const EVICTION_WARN_EVERY: Duration = Duration::from_secs(60);

/// An accept error that concerns only the connection being accepted (as `axum::serve` sorts
/// them): the next accept is tried at once.
fn is_connection_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
    )
}

/// Why a connection was closed by the server.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Cut {
    HeaderRead,
    Idle,
}

/// Where a connection stands, for its timeouts and for choosing one to close at the cap.
#[derive(Debug)]
struct Phase {
    accepted: Instant,
    /// Request heads received so far.
    requests: u64,
    /// Requests whose answer has not been sent in full yet.
    in_flight: usize,
    /// Since when no request is in progress.
    idle_since: Instant,
    /// The first byte of the next request on a kept-alive connection.
    head_started: Option<Instant>,
}

impl Phase {
    /// When the connection is to be closed unless it moves on, and why; none while a request
    /// is in progress.
    fn deadline(&self, l: &ConnLimits) -> Option<(Instant, Cut)> {
        if self.in_flight > 0 {
            None
        } else if self.requests == 0 {
            Some((self.accepted + l.header_read_timeout, Cut::HeaderRead))
        } else if let Some(t) = self.head_started {
            Some((t + l.header_read_timeout, Cut::HeaderRead))
        } else {
            Some((self.idle_since + l.idle_timeout, Cut::Idle))
        }
    }
}

struct Conn {
    /// Accept order.
    id: u64,
    phase: Mutex<Phase>,
    /// The phase changed: the connection's task computes its deadline again.
    changed: Notify,
    /// Closed to make room at the cap.
    evicted: CancellationToken,
}

impl Conn {
    fn new(id: u64) -> Self {
        let now = Instant::now();
        Conn {
            id,
            phase: Mutex::new(Phase {
                accepted: now,
                requests: 0,
                in_flight: 0,
                idle_since: now,
                head_started: None,
            }),
            changed: Notify::new(),
            evicted: CancellationToken::new(),
        }
    }

    fn phase(&self) -> MutexGuard<'_, Phase> {
        // The phase holds plain numbers: one a panicking holder left is still consistent.
        self.phase.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Bytes arrived: on an idle kept-alive connection, the next request's head has begun.
    fn on_bytes(&self) {
        let mut p = self.phase();
        if p.in_flight == 0 && p.requests > 0 && p.head_started.is_none() {
            p.head_started = Some(Instant::now());
            drop(p);
            self.changed.notify_one();
        }
    }

    /// A request head is complete (hyper calls the service with it).
    fn request_started(self: &Arc<Self>) -> InFlight {
        let mut p = self.phase();
        p.requests += 1;
        p.in_flight += 1;
        p.head_started = None;
        drop(p);
        self.changed.notify_one();
        InFlight(self.clone())
    }
}

/// A request in progress: ends when its answer's body has been sent (or dropped).
struct InFlight(Arc<Conn>);

impl Drop for InFlight {
    fn drop(&mut self) {
        let mut p = self.0.phase();
        p.in_flight = p.in_flight.saturating_sub(1);
        if p.in_flight == 0 {
            p.idle_since = Instant::now();
            // Bytes read while a request was in progress may be the next head's: they count
            // from now, under the idle timeout (hyper reads on to spot a closed connection).
            p.head_started = None;
        }
        drop(p);
        self.0.changed.notify_one();
    }
}

/// The open connections, in accept order.
#[derive(Default)]
struct Registry {
    conns: Mutex<BTreeMap<u64, Arc<Conn>>>,
    /// A connection closed.
    freed: Notify,
    evicted: AtomicU64,
    last_warning: Mutex<Option<Instant>>,
}

impl Registry {
    fn lock(&self) -> MutexGuard<'_, BTreeMap<u64, Arc<Conn>>> {
        self.conns.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn len(&self) -> usize {
        self.lock().len()
    }

    fn insert(&self, c: Arc<Conn>) {
        self.lock().insert(c.id, c);
    }

    fn remove(&self, id: u64) {
        if self.lock().remove(&id).is_some() {
            self.freed.notify_one();
        }
    }

    /// Close one connection to make room (never `spare`, the one just accepted): the oldest
    /// that has not completed a request head, else the one idle the longest between requests.
    /// False when every other connection has a request in progress.
    fn evict(&self, spare: Option<u64>, cap: usize) -> bool {
        let victim = {
            let mut conns = self.lock();
            let mut first_head: Option<u64> = None;
            let mut kept_alive: Option<(Instant, u64)> = None;
            for (id, c) in conns.iter() {
                if Some(*id) == spare {
                    continue;
                }
                let p = c.phase();
                if p.in_flight > 0 {
                    continue;
                }
                if p.requests == 0 {
                    first_head = Some(*id);
                    break;
                }
                if kept_alive.is_none_or(|(t, _)| p.idle_since < t) {
                    kept_alive = Some((p.idle_since, *id));
                }
            }
            let Some(id) = first_head.or(kept_alive.map(|(_, id)| id)) else {
                return false;
            };
            conns.remove(&id)
        };
        let Some(c) = victim else { return false };
        c.evicted.cancel();
        let n = self.evicted.fetch_add(1, Ordering::Relaxed) + 1;
        debug!(
            connection = c.id,
            "closed a connection to make room at the cap"
        );
        let now = Instant::now();
        let mut last = self
            .last_warning
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if last.is_none_or(|t| now.duration_since(t) >= EVICTION_WARN_EVERY) {
            *last = Some(now);
            warn!(
                max_connections = cap,
                closed_for_room_total = n,
                "HTTP connections at the cap: closing the oldest that sent no request for new \
                 ones (an idle-socket flood, or http.max_connections too low; said at most once \
                 a minute)"
            );
        }
        true
    }
}

/// One connection from accept to close.
async fn drive(
    conn: Arc<Conn>,
    stream: TcpStream,
    app: Router,
    limits: ConnLimits,
    shutdown: CancellationToken,
    registry: Arc<Registry>,
) {
    let io = TokioIo::new(Watched {
        io: stream,
        conn: conn.clone(),
    });
    let service = {
        let conn = conn.clone();
        tower::service_fn(move |req: axum::http::Request<Incoming>| {
            let in_flight = conn.request_started();
            let app = app.clone();
            async move {
                let res = app.oneshot(req.map(Body::new)).await;
                res.map(|r| {
                    r.map(|body| {
                        Body::new(Answer {
                            body,
                            _in_flight: in_flight,
                        })
                    })
                })
            }
        })
    };
    let mut builder = Builder::new(TokioExecutor::new());
    // As `axum::serve`: the CONNECT protocol for HTTP/2.
    builder.http2().enable_connect_protocol();
    // Boxed, so that it can be dropped (the socket closed) before the slot is given back.
    let mut served =
        Box::pin(builder.serve_connection_with_upgrades(io, TowerToHyperService::new(service)));
    let mut draining = false;
    loop {
        let deadline = conn.phase().deadline(&limits);
        tokio::select! {
            r = served.as_mut() => {
                if let Err(e) = r {
                    debug!(connection = conn.id, error = %e, "connection ended with an error");
                }
                break;
            }
            _ = conn.changed.notified() => {}
            _ = conn.evicted.cancelled() => break,
            _ = shutdown.cancelled(), if !draining => {
                draining = true;
                served.as_mut().graceful_shutdown();
            }
            _ = sleep_until(deadline.map(|(t, _)| t)) => {
                // The phase may have moved on since the deadline was taken.
                if let Some((t, cut)) = conn.phase().deadline(&limits)
                    && t <= Instant::now()
                {
                    debug!(connection = conn.id, reason = ?cut, "closed a connection at its timeout");
                    break;
                }
            }
        }
    }
    // Dropping the connection closes the socket.
    drop(served);
    registry.remove(conn.id);
}

async fn sleep_until(t: Option<Instant>) {
    match t {
        Some(t) => tokio::time::sleep_until(t).await,
        None => std::future::pending().await,
    }
}

/// The socket, telling its connection when bytes arrive.
struct Watched {
    io: TcpStream,
    conn: Arc<Conn>,
}

impl AsyncRead for Watched {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let r = Pin::new(&mut this.io).poll_read(cx, buf);
        if matches!(r, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            this.conn.on_bytes();
        }
        r
    }
}

impl AsyncWrite for Watched {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

/// An answer's body, holding its request in progress until hyper has sent it (and drops it).
struct Answer {
    body: Body,
    _in_flight: InFlight,
}

impl HttpBody for Answer {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.get_mut().body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> ConnLimits {
        ConnLimits {
            max_connections: 4,
            header_read_timeout: Duration::from_secs(2),
            idle_timeout: Duration::from_secs(30),
        }
    }

    #[test]
    fn a_cap_that_leaves_no_room_beside_the_reserve_is_refused_with_what_fits() {
        let limit = FileLimit {
            soft: 1024,
            hard: 1024,
        };
        let reserved = reserved_fds(1, 0);
        let fits = 1024 - reserved - 1;
        assert!(check_fits(fits as usize, 1, 0, limit).is_ok());
        let e = check_fits(fits as usize + 1, 1, 0, limit).unwrap_err();
        let ServerError::FileLimit { fits: said, .. } = &e;
        assert_eq!(*said, fits);
        assert!(e.to_string().contains("LimitNOFILE"), "{e}");
        // More machines keep more descriptors, a link over its own socket more again.
        assert!(check_fits(fits as usize, 2, 0, limit).is_err());
        assert!(check_fits(fits as usize - 1, 1, 1, limit).is_err());
        // The shipped cap fits the common soft limit of 1024 with a few machines, and ten
        // thousand nc_push machines fit a limit of 20000.
        let shipped = crate::config::ServiceConfig::load(None).unwrap();
        assert!(check_fits(shipped.http.max_connections, 8, 8, limit).is_ok());
        let plant = FileLimit {
            soft: 20_000,
            hard: 20_000,
        };
        assert!(check_fits(shipped.http.max_connections, 10_000, 0, plant).is_ok());
    }

    #[tokio::test(start_paused = true)]
    async fn the_deadline_follows_the_phase() {
        let l = limits();
        let c = Arc::new(Conn::new(1));
        let t0 = c.phase().accepted;
        assert_eq!(
            c.phase().deadline(&l),
            Some((t0 + l.header_read_timeout, Cut::HeaderRead))
        );
        // Bytes of the first head do not move its deadline: it counts from the accept.
        tokio::time::advance(Duration::from_secs(1)).await;
        c.on_bytes();
        assert_eq!(
            c.phase().deadline(&l),
            Some((t0 + l.header_read_timeout, Cut::HeaderRead))
        );
        let req = c.request_started();
        assert_eq!(c.phase().deadline(&l), None, "none while a request runs");
        tokio::time::advance(Duration::from_secs(100)).await;
        drop(req);
        let t1 = Instant::now();
        assert_eq!(
            c.phase().deadline(&l),
            Some((t1 + l.idle_timeout, Cut::Idle))
        );
        tokio::time::advance(Duration::from_secs(5)).await;
        c.on_bytes();
        assert_eq!(
            c.phase().deadline(&l),
            Some((
                t1 + Duration::from_secs(5) + l.header_read_timeout,
                Cut::HeaderRead
            )),
            "the next head has the header-read timeout from its first byte"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn at_the_cap_the_oldest_without_a_request_goes_first_then_the_longest_idle() {
        let r = Registry::default();
        let conns: Vec<Arc<Conn>> = (1..=4).map(|i| Arc::new(Conn::new(i))).collect();
        for c in &conns {
            r.insert(c.clone());
        }
        // 1: busy; 2: kept alive, idle since t0; 3: never sent a request; 4: kept alive, idle
        // for less long.
        let _busy = conns[0].request_started();
        drop(conns[1].request_started());
        tokio::time::advance(Duration::from_secs(1)).await;
        drop(conns[3].request_started());
        assert!(r.evict(Some(4), 4));
        assert!(conns[2].evicted.is_cancelled(), "the one without a request");
        assert!(r.evict(None, 4));
        assert!(conns[1].evicted.is_cancelled(), "then the longest idle");
        // Only the busy one and the spared one are left.
        assert!(!r.evict(Some(4), 4));
        assert!(!conns[0].evicted.is_cancelled());
        assert_eq!(r.len(), 2);
    }
}
