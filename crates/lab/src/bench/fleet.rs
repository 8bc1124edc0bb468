//! `bench fleet`: N simulated machines through a simulated day in one process, the service as
//! `driftwatch serve` runs it (`launch`: store, machine loops, HTTP API) on a manual clock that
//! moves a minute at a time as soon as every loop has reached it, while a client polls the
//! NC's compensation endpoint of random machines at a steady rate.
//!
//! Each machine is `table_bc` with the patent plan on the two-shift day, with its own noise
//! seed; `--stagger-min` spreads the machines' days over that many minutes (0: every machine
//! starts, warms up and cycles in the same instant, the worst case for peaks).
//!
//! With `--link nc-push` the machines are what a plant runs: `nc_push` doors with no
//! simulator behind them, driven over HTTP by a load generator that replays a recorded day of
//! NC traffic (`nc_traffic`). The run then measures the service alone: its memory per machine
//! loop, its CPU per machine-day without the generator's, the endpoint under the write bursts,
//! the traffic at 1x, and the CPU of a fleet whose NCs are silent.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use rand::{Rng, SeedableRng};
use tokio_util::sync::CancellationToken;

use driftwatch_core::units::{NS_PER_H, NS_PER_MIN};
use driftwatch_scratch_pg::ScratchPg;
use driftwatch_service::config::{LinkConfig, ServiceConfig};
use driftwatch_service::daemon::MachineView;
use driftwatch_service::launch::{ClockKind, LaunchOptions, Service, launch_with};
use driftwatch_service::store::{CycleStatus, Store};
use driftwatch_sim::scenario::Scenario;

use super::cpu_time::{clock_tick, machine_busy_s, own_cpu_s, peak_rss, tree_cpu_s};
use super::nc_traffic::{Drive, Generator, ORDER_POLL_S, Recorded, Sent};
use super::size_of;

/// The database the fleet writes to.
#[derive(Clone, Copy, Debug, PartialEq, clap::ValueEnum)]
pub enum FleetBackend {
    Sqlite,
    Postgres,
}

/// What the machines are.
#[derive(Clone, Copy, Debug, PartialEq, clap::ValueEnum)]
pub enum FleetLink {
    /// The truth simulator in the service (each loop carries its virtual machine).
    Simulated,
    /// `nc_push` doors driven over HTTP by the recorded NC traffic.
    NcPush,
}

pub struct FleetOptions {
    pub machines: usize,
    pub link: FleetLink,
    pub backend: FleetBackend,
    /// A PostgreSQL database to use instead of a throwaway server (an empty one: machines the
    /// store already knows resume where they were).
    pub database_url: Option<String>,
    pub days: f64,
    pub dir: PathBuf,
    pub stagger_min: f64,
    /// After the simulated days, this many minutes with the clock at 1x.
    pub realtime_min: f64,
    /// `nc-push`: then this many seconds at 1x with every NC silent.
    pub idle_s: f64,
}

/// The clock moves this much machine time at a time.
const STEP_NS: i64 = NS_PER_MIN;
/// The endpoint client: this many requests per second in all, over this many keep-alive
/// connections (an NC polls every few seconds; a few hundred per second is a plant's worth).
const REQUESTS_PER_S: f64 = 200.0;
const CONNECTIONS: usize = 4;
/// A loop that has not reached the clock after this much wall time is reported stuck.
const STALL: Duration = Duration::from_secs(600);
const SCENARIO: &str = "two_shift";
/// The NCs' bearer token on the bench's own loopback service.
const NC_TOKEN: &str = "bench-nc-write-token";

/// The database: where it is, and how big it is now.
enum Db {
    /// The SQLite file (and its write-ahead log) in the data directory.
    Sqlite(PathBuf),
    /// A PostgreSQL database; the throwaway server when the bench started one (kept here:
    /// dropping it stops it).
    Postgres {
        url: String,
        server: Option<ScratchPg>,
    },
}

impl Db {
    async fn open(opts: &FleetOptions, data_dir: &Path) -> Result<Db> {
        Ok(match (opts.backend, &opts.database_url) {
            (FleetBackend::Sqlite, None) => Db::Sqlite(data_dir.join("driftwatch.db")),
            (FleetBackend::Sqlite, Some(_)) => {
                anyhow::bail!("--database-url is for --backend postgres")
            }
            (FleetBackend::Postgres, Some(url)) => Db::Postgres {
                url: url.clone(),
                server: None,
            },
            (FleetBackend::Postgres, None) => {
                let parent = opts.dir.clone();
                let server = tokio::task::spawn_blocking(move || ScratchPg::start(&parent))
                    .await?
                    .map_err(|e| anyhow::anyhow!("starting a throwaway PostgreSQL: {e}"))?;
                let (_, url) = server
                    .database()
                    .await
                    .context("creating the bench's database")?;
                Db::Postgres {
                    url,
                    server: Some(server),
                }
            }
        })
    }

    fn url(&self) -> Option<String> {
        match self {
            Db::Sqlite(_) => None,
            Db::Postgres { url, .. } => Some(url.clone()),
        }
    }

    /// Bytes on disk: the SQLite file and its log, or `pg_database_size`.
    async fn size(&self) -> Result<u64> {
        match self {
            Db::Sqlite(path) => Ok(sqlite_size(path)),
            Db::Postgres { url, .. } => {
                use sqlx::Connection;
                let mut conn = sqlx::postgres::PgConnection::connect(url)
                    .await
                    .context("connecting to PostgreSQL for the database's size")?;
                let size: i64 = sqlx::query_scalar("SELECT pg_database_size(current_database())")
                    .fetch_one(&mut conn)
                    .await
                    .context("asking PostgreSQL for the database's size")?;
                conn.close().await.ok();
                Ok(size.max(0) as u64)
            }
        }
    }

    /// The size the run starts from: an empty store's. SQLite's is measured on an empty
    /// file opened and closed beside it, since the service's own file holds its schema in a
    /// log that is folded in (and shrinks) only when the store closes.
    async fn empty_size(&self) -> Result<u64> {
        let Db::Sqlite(path) = self else {
            return self.size().await;
        };
        let empty = path.with_file_name("empty.db");
        let store = Store::open(&empty).await?;
        store.close().await;
        let size = sqlite_size(&empty);
        for suffix in ["", "-wal", "-shm"] {
            let mut p = empty.clone().into_os_string();
            p.push(suffix);
            let _ = std::fs::remove_file(p);
        }
        Ok(size)
    }

    /// CPU seconds of the throwaway server's processes so far (none for another server).
    fn server_cpu_s(&self, tick: f64) -> Option<f64> {
        let Db::Postgres {
            server: Some(s), ..
        } = self
        else {
            return None;
        };
        let pid_file = std::fs::read_to_string(s.dir.join("data").join("postmaster.pid")).ok()?;
        let pid: u32 = pid_file.lines().next()?.trim().parse().ok()?;
        Some(tree_cpu_s(pid, tick))
    }
}

/// An SQLite database's file and its write-ahead log, bytes.
fn sqlite_size(path: &Path) -> u64 {
    let mut wal = path.as_os_str().to_owned();
    wal.push("-wal");
    size_of(path) + size_of(Path::new(&wal))
}

/// The shipped default configuration with `n` simulated machines `m001`.. in `dir`, each with
/// its own seed and its day shifted by `i * stagger / n` minutes (a scenario file per machine).
fn fleet_config(
    opts: &FleetOptions,
    data_dir: &Path,
    url: Option<String>,
) -> Result<ServiceConfig> {
    let mut cfg = ServiceConfig::load(None)?;
    cfg.data_dir = data_dir.to_path_buf();
    cfg.database_url = url;
    // Anonymous reads (the default) are what the client uses; no operator token to resolve.
    cfg.http.anonymous_read = true;
    cfg.http.tokens.clear();
    let template = cfg
        .machines
        .first()
        .context("the default configuration has no machine")?
        .clone();
    let base = Scenario::load(SCENARIO)?;
    let start = chrono::DateTime::parse_from_rfc3339(&base.start_utc)
        .with_context(|| format!("scenario {SCENARIO}: start_utc"))?;
    let scenarios = opts.dir.join("scenarios");
    std::fs::create_dir_all(&scenarios)
        .with_context(|| format!("creating {}", scenarios.display()))?;
    if opts.link == FleetLink::NcPush {
        // Real NCs run on the wall clock (the bench holds and runs its own).
        cfg.time_scale = 1.0;
        // The NCs post with a token of the write role; reads stay anonymous.
        cfg.http.tokens = vec![driftwatch_service::config::Token {
            name: "ncs".into(),
            token: NC_TOKEN.into(),
            role: driftwatch_service::config::Role::Write,
        }];
        // Room for the generator's and the pollers' connections beside the dashboards'.
        cfg.http.max_connections = cfg.http.max_connections.max(256);
        cfg.machines = (0..opts.machines)
            .map(|i| {
                let mut m = template.clone();
                m.id = super::nc_traffic::fleet_id(i);
                m.machine = base.machine.clone();
                m.plan = Some(base.plan.clone());
                m.link = toml::from_str(r#"kind = "nc_push""#)?;
                Ok(m)
            })
            .collect::<Result<_>>()?;
        return Ok(cfg);
    }
    cfg.machines = (0..opts.machines)
        .map(|i| {
            let id = super::nc_traffic::fleet_id(i);
            let shift_min = opts.stagger_min * i as f64 / opts.machines as f64;
            let scenario = if shift_min == 0.0 {
                SCENARIO.to_string()
            } else {
                let mut scn = base.clone();
                let shift = chrono::Duration::milliseconds((shift_min * 60e3).round() as i64);
                scn.start_utc = (start + shift).to_rfc3339();
                let path = scenarios.join(format!("{id}.toml"));
                std::fs::write(&path, toml::to_string(&scn)?)
                    .with_context(|| format!("writing {}", path.display()))?;
                path.display().to_string()
            };
            let mut m = template.clone();
            m.id = id;
            m.link = LinkConfig::Simulated {
                scenario,
                seed: Some(1000 + i as u64),
            };
            Ok(m)
        })
        .collect::<Result<_>>()?;
    Ok(cfg)
}

/// What the endpoint client saw.
#[derive(Default)]
struct Polls {
    /// Latencies of the 200 answers.
    latencies: Latencies,
    /// 404: the machine has no validated set yet (its first cycle has not run).
    no_set: u64,
    errors: u64,
}

/// `CONNECTIONS` clients, each on its own keep-alive connection, GET the compensation of a
/// random machine on a fixed schedule (`REQUESTS_PER_S` in all) until `stop`. They run on a
/// thread and runtime of their own, as an NC is a process of its own: their latencies are the
/// service's answers (and the cores it shares), not the wait of a client task queued behind
/// the service's own tasks on its runtime.
fn poll_endpoint(
    addr: std::net::SocketAddr,
    ids: Vec<String>,
    stop: CancellationToken,
) -> Result<std::thread::JoinHandle<Polls>> {
    let ids = Arc::new(ids);
    let period = Duration::from_secs_f64(CONNECTIONS as f64 / REQUESTS_PER_S);
    let thread = std::thread::Builder::new()
        .name("endpoint-client".into())
        .spawn(move || {
            let mut polls = Polls::default();
            let rt = match tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
            {
                Ok(rt) => rt,
                Err(_) => {
                    polls.errors += 1;
                    return polls;
                }
            };
            rt.block_on(async {
                let clients: Vec<_> = (0..CONNECTIONS)
                    .map(|c| tokio::spawn(one_client(addr, ids.clone(), c, period, stop.clone())))
                    .collect();
                for c in clients {
                    match c.await {
                        Ok(p) => {
                            polls.latencies.merge(&p.latencies);
                            polls.no_set += p.no_set;
                            polls.errors += p.errors;
                        }
                        Err(_) => polls.errors += 1,
                    }
                }
            });
            polls
        })?;
    Ok(thread)
}

/// Latencies as a count of each whole microsecond: the quantiles of every answer, exactly,
/// in memory that does not grow with the run. A list of every answer's grew with the wall
/// time (200 a second), and the run's memory per machine loop, taken from the longer runs of
/// larger fleets, counted it: some 40 KB a loop between 20 and 60 machines through a week.
#[derive(Default)]
struct Latencies {
    count_us: BTreeMap<u64, u64>,
    n: u64,
}

impl Latencies {
    fn add(&mut self, us: u64) {
        *self.count_us.entry(us).or_default() += 1;
        self.n += 1;
    }

    fn merge(&mut self, other: &Latencies) {
        for (&us, &k) in &other.count_us {
            *self.count_us.entry(us).or_default() += k;
        }
        self.n += other.n;
    }

    /// The `q` quantile as the bench's `quantile` takes it of the sorted latencies (NaN: none).
    fn quantile(&self, q: f64) -> f64 {
        if self.n == 0 {
            return f64::NAN;
        }
        let at = ((self.n as f64 - 1.0) * q).round() as u64;
        let mut seen = 0;
        for (&us, &k) in &self.count_us {
            seen += k;
            if seen > at {
                return us as f64;
            }
        }
        f64::NAN
    }

    fn max(&self) -> u64 {
        self.count_us.keys().next_back().copied().unwrap_or(0)
    }
}

/// Client `c` of [`poll_endpoint`].
async fn one_client(
    addr: std::net::SocketAddr,
    ids: Arc<Vec<String>>,
    c: usize,
    period: Duration,
    stop: CancellationToken,
) -> Polls {
    let mut polls = Polls::default();
    let Ok(client) = reqwest::Client::builder().pool_max_idle_per_host(1).build() else {
        polls.errors += 1;
        return polls;
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(c as u64);
    // The connections take turns rather than all sending at once.
    let first = tokio::time::Instant::now() + period * c as u32 / CONNECTIONS as u32;
    let mut tick = tokio::time::interval_at(first, period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = stop.cancelled() => break,
            _ = tick.tick() => {}
        }
        let id = &ids[rng.random_range(0..ids.len())];
        let url = format!("http://{addr}/api/v1/machines/{id}/compensation");
        let t = Instant::now();
        match client.get(&url).send().await {
            Ok(r) => {
                let status = r.status();
                let body = r.bytes().await;
                match (status.as_u16(), body) {
                    (200, Ok(_)) => polls.latencies.add(t.elapsed().as_micros() as u64),
                    (404, Ok(_)) => polls.no_set += 1,
                    _ => polls.errors += 1,
                }
            }
            Err(_) => polls.errors += 1,
        }
    }
    polls
}

/// Whether every loop has stepped to `t_ns`; `from` is the first one not yet seen there (the
/// ones before it need not be looked at again).
fn reached(views: &[Arc<Mutex<MachineView>>], t_ns: i64, from: &mut usize) -> Result<bool> {
    while let Some(v) = views.get(*from) {
        let at = v
            .lock()
            .map_err(|_| anyhow::anyhow!("a machine's view lock is poisoned"))?
            .health
            .clock_ns;
        if at.is_none_or(|t| t < t_ns) {
            return Ok(false);
        }
        *from += 1;
    }
    Ok(true)
}

/// Move the clock a step at a time to `end_ns`, each as soon as every loop has reached the
/// last (and the NCs, if any, have posted what happened up to it and asked for their orders);
/// the wall time of each simulated hour (the last one may be shorter: its length too).
async fn drive(
    svc: &Service,
    end_ns: i64,
    ncs: Option<&Generator>,
    sent: &Mutex<Sent>,
) -> Result<Vec<(f64, f64)>> {
    let clock = svc
        .manual_clock
        .as_ref()
        .context("the service has no manual clock")?;
    let views: Vec<_> = svc.views.values().cloned().collect();
    let mut hours = Vec::new();
    let (mut t, mut hour_t, mut hour_wall) = (svc.t0_ns, svc.t0_ns, Instant::now());
    while t < end_ns {
        if let Some(g) = ncs {
            let s = g.drive(Drive::To(t)).await?;
            if let Ok(mut all) = sent.lock() {
                all.add(s);
            }
        }
        t = (t + STEP_NS).min(end_ns);
        clock.set(t);
        let since = Instant::now();
        let mut from = 0;
        // A short poll: the loops need the cores, and a step takes them a millisecond or more.
        while !reached(&views, t, &mut from)? {
            if since.elapsed() > STALL {
                let (id, at) = svc
                    .views
                    .iter()
                    .nth(from)
                    .map(|(id, v)| (id.clone(), v.lock().map(|v| v.health.clone())))
                    .context("a machine that never reached the clock")?;
                anyhow::bail!(
                    "machine {id} did not reach the clock in {} s: {at:?}",
                    STALL.as_secs()
                );
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        if t - hour_t >= NS_PER_H || t == end_ns {
            hours.push(((t - hour_t) as f64 / 1e9, hour_wall.elapsed().as_secs_f64()));
            (hour_t, hour_wall) = (t, Instant::now());
        }
    }
    Ok(hours)
}

/// CPU time a phase took, s.
struct Usage {
    wall_s: f64,
    user_s: f64,
    sys_s: f64,
    /// The throwaway PostgreSQL server's processes.
    server_s: Option<f64>,
    /// Every process of the machine (this one included): what else ran meanwhile shows.
    machine_s: f64,
}

impl Usage {
    fn own_s(&self) -> f64 {
        self.user_s + self.sys_s
    }

    /// CPU of the processes other than this one and the bench's PostgreSQL server, s.
    fn others_s(&self) -> f64 {
        (self.machine_s - self.own_s() - self.server_s.unwrap_or(0.0)).max(0.0)
    }
}

/// The CPU counters at one moment.
struct Counters {
    at: Instant,
    own: (f64, f64),
    server: Option<f64>,
    machine: f64,
}

impl Counters {
    fn read(db: &Db, tick: f64) -> Counters {
        Counters {
            at: Instant::now(),
            own: own_cpu_s(tick),
            server: db.server_cpu_s(tick),
            machine: machine_busy_s(tick),
        }
    }

    fn since(&self, before: &Counters) -> Usage {
        Usage {
            wall_s: self.at.duration_since(before.at).as_secs_f64(),
            user_s: self.own.0 - before.own.0,
            sys_s: self.own.1 - before.own.1,
            server_s: self.server.zip(before.server).map(|(b, a)| b - a),
            machine_s: self.machine - before.machine,
        }
    }
}

/// Run `phase` while the client polls the endpoint: what it returned, the CPU it took, and
/// what the client saw.
async fn under_polls<T>(
    svc: &Service,
    db: &Db,
    tick: f64,
    phase: impl std::future::Future<Output = Result<T>>,
) -> Result<(T, Usage, Polls)> {
    let stop = CancellationToken::new();
    let clients = poll_endpoint(svc.addr, svc.views.keys().cloned().collect(), stop.clone())?;
    let before = Counters::read(db, tick);
    let out = phase.await;
    let usage = Counters::read(db, tick).since(&before);
    stop.cancel();
    let polls = tokio::task::spawn_blocking(move || clients.join())
        .await?
        .map_err(|_| anyhow::anyhow!("the endpoint client's thread panicked"))?;
    Ok((out?, usage, polls))
}

/// The clock at 1x for `span`: it runs on with the wall clock from where it stands, as in
/// production, and each loop wakes when its own time comes or its NC posts. Every 100 ms, the
/// largest lag of a loop behind the time it asked to be woken at, s (0 when every loop keeps
/// up).
async fn pace(svc: &Service, span: Duration) -> Result<Vec<f64>> {
    let clock = svc
        .manual_clock
        .as_ref()
        .context("the service has no manual clock")?;
    clock.run(1.0);
    let views: Vec<_> = svc.views.values().cloned().collect();
    let wall0 = Instant::now();
    let mut lags = Vec::new();
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    while wall0.elapsed() < span {
        tick.tick().await;
        let now = clock.now_ns();
        let mut worst = 0;
        for v in &views {
            let wake = v
                .lock()
                .map_err(|_| anyhow::anyhow!("a machine's view lock is poisoned"))?
                .health
                .wake_ns
                .unwrap_or(svc.t0_ns);
            worst = worst.max(now - wake);
        }
        lags.push(worst as f64 / 1e9);
    }
    Ok(lags)
}

/// The 1x phase: where it started (machine time), its CPU, the client's view, the lags.
struct Paced {
    from_ns: i64,
    usage: Usage,
    polls: Polls,
    lags_s: Vec<f64>,
}

/// What the run measured.
struct Figures {
    /// Wall time to launch the service (store, every machine's loop, the API), s.
    launch_s: f64,
    /// (simulated s, wall s) of each simulated hour.
    hours: Vec<(f64, f64)>,
    usage: Usage,
    polls: Polls,
    paced: Option<Paced>,
    db_growth: i64,
    mcap: u64,
    cycles: usize,
    ok: usize,
    faults: u64,
    /// `nc-push` only.
    nc: Option<NcFigures>,
}

/// What the `nc-push` run measured beyond the rest.
#[derive(Default)]
struct NcFigures {
    /// Resident memory before the service started, after it started, at the end.
    rss_before: Resident,
    rss_launched: Resident,
    rss_end: Resident,
    /// The generator's CPU in the simulated days and at 1x, s.
    gen_fast_s: f64,
    gen_paced_s: f64,
    fast: Sent,
    paced: Sent,
    /// Recorded events a machine-day (its NC's posts without cycles).
    events_per_day: usize,
    /// The silent phase: its CPU.
    idle: Option<Usage>,
}

pub async fn fleet(opts: FleetOptions) -> Result<ExitCode> {
    anyhow::ensure!(opts.machines >= 1, "--machines must be at least 1");
    anyhow::ensure!(
        opts.days.is_finite() && opts.days > 0.0,
        "--days must be > 0"
    );
    anyhow::ensure!(
        opts.stagger_min.is_finite() && opts.stagger_min >= 0.0,
        "--stagger-min must be >= 0"
    );
    anyhow::ensure!(
        opts.realtime_min.is_finite() && opts.realtime_min >= 0.0,
        "--realtime-min must be >= 0"
    );
    anyhow::ensure!(
        opts.idle_s.is_finite() && opts.idle_s >= 0.0,
        "--idle-s must be >= 0"
    );
    let _ = std::fs::remove_dir_all(&opts.dir);
    std::fs::create_dir_all(&opts.dir)
        .with_context(|| format!("creating {}", opts.dir.display()))?;
    let data_dir = opts.dir.join("data");
    let db = Db::open(&opts, &data_dir).await?;
    let cfg = fleet_config(&opts, &data_dir, db.url())?;
    // The NCs' day is recorded before the service starts: its memory is not the service's.
    let recorded = match opts.link {
        FleetLink::NcPush => {
            let scn = Scenario::load(SCENARIO)?;
            let k = driftwatch_core::kinematics::Kinematics::load(&scn.machine)?;
            let plan = driftwatch_core::plan::Plan::build(
                &k,
                &driftwatch_core::plan::PlanConfig::load(&scn.plan)?,
            )?;
            Some((Recorded::record(&scn, &k, &plan)?, scn.start_ns()))
        }
        FleetLink::Simulated => None,
    };
    let rss_before = rss();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let launch = LaunchOptions {
        clock: ClockKind::Manual,
        start_ns: recorded.as_ref().map(|(_, t0)| *t0),
        ..Default::default()
    };
    let launched = Instant::now();
    let svc = launch_with(cfg, listener, CancellationToken::new(), launch)
        .await
        .context("launching the service")?;
    let launch_s = launched.elapsed().as_secs_f64();
    let rss_launched = rss();
    let ncs = match recorded {
        Some((rec, _)) => {
            let events_per_day = rec.events_per_day();
            let stagger = (opts.stagger_min * 60e9).round() as i64;
            let ids = svc.views.keys().cloned().collect();
            let g = Generator::start(
                svc.addr,
                NC_TOKEN,
                ids,
                rec,
                svc.t0_ns,
                stagger,
                clock_tick(),
            )?;
            Some((g, events_per_day))
        }
        None => None,
    };
    let f = run(&svc, &opts, &db, ncs.as_ref().map(|(g, _)| g)).await;
    let rss_end = rss();
    let per_day = ncs.as_ref().map_or(0, |(_, n)| *n);
    // The NCs stop first: the service they talk to is about to.
    drop(ncs);
    svc.stop();
    svc.wait().await;
    let mut f = f?;
    f.launch_s = launch_s;
    if let Some(nc) = f.nc.as_mut() {
        nc.rss_before = rss_before;
        nc.rss_launched = rss_launched;
        nc.rss_end = rss_end;
        nc.events_per_day = per_day;
    }
    // After the store has closed: SQLite has folded its log into the file.
    f.db_growth += db.size().await? as i64;
    f.mcap = size_of(&data_dir.join("mcap"));
    report(&opts, &f);
    Ok(ExitCode::SUCCESS)
}

/// The resident set of this process, bytes: all of it (VmRSS), and its anonymous part
/// (RssAnon: the heap and the stacks). The rest is mapped files, the program's own code
/// among them: pages that its first run through a code path brings in, the same for one
/// machine as for ten thousand, and shared with every other process that maps them.
#[derive(Clone, Copy, Default)]
struct Resident {
    total: u64,
    anon: u64,
}

/// This process' resident set now (zeros where /proc does not say).
fn rss() -> Resident {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| -> u64 {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|rest| rest.split_whitespace().next()?.parse::<u64>().ok())
            .map_or(0, |kb| kb * 1024)
    };
    Resident {
        total: field("VmRSS:"),
        anon: field("RssAnon:"),
    }
}

/// The run itself, on the launched service: the simulated days as fast as the loops keep up,
/// then the 1x phase if asked for, each under the client's polls, then (NCs only) the silent
/// phase; everything but the sizes after the store closes.
async fn run(
    svc: &Service,
    opts: &FleetOptions,
    db: &Db,
    ncs: Option<&Generator>,
) -> Result<Figures> {
    let tick = clock_tick();
    let size0 = db.empty_size().await?;
    let end_ns = svc.t0_ns + (opts.days * 86_400e9).round() as i64;
    let mut nc = ncs.map(|_| NcFigures::default());
    let gen_cpu = async || match ncs {
        Some(g) => g.cpu_s().await,
        None => Ok(0.0),
    };
    let sent = Mutex::new(Sent::default());
    let g0 = gen_cpu().await?;
    let (hours, usage, polls) = under_polls(svc, db, tick, drive(svc, end_ns, ncs, &sent)).await?;
    let g1 = gen_cpu().await?;
    let paced = if opts.realtime_min > 0.0 {
        let span = Duration::from_secs_f64(opts.realtime_min * 60.0);
        let traffic = async {
            match ncs {
                Some(g) => {
                    let clock = svc.clock.clone();
                    g.drive(Drive::Paced {
                        clock,
                        span,
                        order_poll_s: ORDER_POLL_S,
                    })
                    .await
                }
                None => Ok(Sent::default()),
            }
        };
        let both = async {
            let (lags, traffic) = tokio::join!(pace(svc, span), traffic);
            Ok((lags?, traffic?))
        };
        let ((lags_s, paced_sent), usage, polls) = under_polls(svc, db, tick, both).await?;
        if let Some(nc) = nc.as_mut() {
            nc.paced = paced_sent;
        }
        Some(Paced {
            from_ns: end_ns,
            usage,
            polls,
            lags_s,
        })
    } else {
        None
    };
    let g2 = gen_cpu().await?;
    if let Some(nc) = nc.as_mut() {
        nc.fast = sent.lock().map(|s| *s).unwrap_or_default();
        nc.gen_fast_s = g1 - g0;
        nc.gen_paced_s = g2 - g1;
        if opts.idle_s > 0.0 {
            // Silent NCs, nobody polling: what the loops cost by themselves at 1x.
            if let Some(clock) = svc.manual_clock.as_ref() {
                clock.run(1.0);
            }
            let before = Counters::read(db, tick);
            tokio::time::sleep(Duration::from_secs_f64(opts.idle_s)).await;
            nc.idle = Some(Counters::read(db, tick).since(&before));
        }
    }
    let (mut cycles, mut ok, mut faults) = (0, 0, 0);
    for (id, view) in &svc.views {
        let rows = svc.store().cycles(id, i64::MAX, None).await?;
        cycles += rows.len();
        ok += rows.iter().filter(|c| c.status == CycleStatus::Ok).count();
        faults += view.lock().map_or(0, |v| v.health.faults);
    }
    Ok(Figures {
        launch_s: 0.0,
        hours,
        usage,
        polls,
        paced,
        db_growth: -(size0 as i64),
        mcap: 0,
        cycles,
        ok,
        faults,
        nc,
    })
}

fn summary(opts: &FleetOptions) -> String {
    let backend = match (opts.backend, &opts.database_url) {
        (FleetBackend::Sqlite, _) => "SQLite",
        (FleetBackend::Postgres, None) => "PostgreSQL (a throwaway server on this machine)",
        (FleetBackend::Postgres, Some(_)) => "PostgreSQL (--database-url)",
    };
    let what = match opts.link {
        FleetLink::Simulated => format!("simulated machines (seeds 1000-{})", 999 + opts.machines),
        FleetLink::NcPush => {
            "nc_push machines driven over HTTP by a recorded day of NC traffic".to_string()
        }
    };
    format!(
        "{} {what} (table_bc, patent plan, {SCENARIO} day, days spread over {} min) on {backend}, {} simulated days as fast as they keep up{}",
        opts.machines,
        opts.stagger_min,
        opts.days,
        if opts.realtime_min > 0.0 {
            format!(", then {} min at 1x", opts.realtime_min)
        } else {
            String::new()
        }
    )
}

/// The client's latencies and answers as one line's words.
fn polled(p: &Polls, wall_s: f64) -> String {
    let lat = &p.latencies;
    format!(
        "{} requests answered 200, p50 {:.0} us, p99 {:.0} us, max {:.0} us; {} answered 404 (no set yet), {} errors ({CONNECTIONS} keep-alive connections, {:.0} req/s of the {REQUESTS_PER_S} asked for)",
        lat.n,
        lat.quantile(0.5),
        lat.quantile(0.99),
        lat.max(),
        p.no_set,
        p.errors,
        (lat.n + p.no_set + p.errors) as f64 / wall_s
    )
}

/// The figures as plain lines, each starting with what it is.
fn report(opts: &FleetOptions, f: &Figures) {
    let machine_days = opts.machines as f64 * opts.days;
    // The stored data and the cycles cover the 1x phase too.
    let stored_days = opts.machines as f64 * (opts.days + opts.realtime_min / 1440.0);
    let u = &f.usage;
    let speed = opts.days * 86_400.0 / u.wall_s;
    let (slowest_i, slowest) = f
        .hours
        .iter()
        .map(|(sim, wall)| sim / wall)
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap_or((0, f64::NAN));
    println!("fleet: {}", summary(opts));
    println!(
        "wall: {:.1} s, {speed:.1}x real time on average, {slowest:.1}x in the slowest simulated hour (hour {} of {}); real time {}",
        u.wall_s,
        slowest_i + 1,
        f.hours.len(),
        if speed >= 1.0 && slowest >= 1.0 {
            "kept"
        } else {
            "NOT kept"
        }
    );
    let each: Vec<String> = f
        .hours
        .iter()
        .map(|(sim, wall)| format!("{:.0}", sim / wall))
        .collect();
    println!(
        "hours: speed of each simulated hour from the start (x): {}; the launch took {:.1} s",
        each.join(" "),
        f.launch_s
    );
    println!(
        "cpu: {:.1} s of this process (user {:.1}, sys {:.1}; the client included), {:.2} s/machine-day{}; other processes of the machine {:.1} s",
        u.own_s(),
        u.user_s,
        u.sys_s,
        u.own_s() / machine_days,
        match u.server_s {
            Some(s) => format!(
                "; PostgreSQL server {s:.1} s, {:.2} s/machine-day",
                s / machine_days
            ),
            None if opts.backend == FleetBackend::Postgres => {
                "; the PostgreSQL server's not measured (--database-url)".to_string()
            }
            None => String::new(),
        },
        u.others_s()
    );
    println!(
        "database: {:.2} MB growth, {:.1} MB/machine-year",
        f.db_growth as f64 / 1e6,
        f.db_growth as f64 / 1e6 * 365.0 / stored_days
    );
    println!(
        "mcap: {:.2} MB, {:.2} MB/machine-day",
        f.mcap as f64 / 1e6,
        f.mcap as f64 / 1e6 / stored_days
    );
    println!("endpoint: {}", polled(&f.polls, u.wall_s));
    println!(
        "cycles: {} run, {} validated, {:.1}/machine-day; loop step faults {}",
        f.cycles,
        f.ok,
        f.cycles as f64 / stored_days,
        f.faults
    );
    println!(
        "rss: peak {:.0} MB",
        peak_rss().map_or(f64::NAN, |b| b as f64 / 1e6)
    );
    println!(
        "estimate: about {:.0} machines at the slowest hour's pace if the work grew linearly with the fleet (the simulated work only: see realtime)",
        opts.machines as f64 * slowest
    );
    if let Some(p) = &f.paced {
        report_paced(opts, p);
    }
    if let Some(nc) = &f.nc {
        report_nc(opts, f, nc);
    }
}

/// The `nc-push` run's own lines: the service without its load generator.
fn report_nc(opts: &FleetOptions, f: &Figures, nc: &NcFigures) {
    let n = opts.machines as f64;
    let kb = |b: u64| b as f64 / 1024.0;
    let (b, l, e) = (nc.rss_before, nc.rss_launched, nc.rss_end);
    println!(
        "memory: {:.1} MB resident before the service started ({:.1} MB of it anonymous), {:.1} MB ({:.1}) with {} machine loops started, {:.1} MB ({:.1}) at the end",
        b.total as f64 / 1e6,
        b.anon as f64 / 1e6,
        l.total as f64 / 1e6,
        l.anon as f64 / 1e6,
        opts.machines,
        e.total as f64 / 1e6,
        e.anon as f64 / 1e6,
    );
    println!(
        "memory per machine loop over the start: {:.0} KB anonymous ({:.0} KB resident) with the loops started, {:.0} KB ({:.0} KB) at the end (the load generator's HTTP clients, in this process, included)",
        kb(l.anon.saturating_sub(b.anon)) / n,
        kb(l.total.saturating_sub(b.total)) / n,
        kb(e.anon.saturating_sub(b.anon)) / n,
        kb(e.total.saturating_sub(b.total)) / n,
    );
    let u = &f.usage;
    let machine_days = n * opts.days;
    let service_s = u.own_s() - nc.gen_fast_s;
    println!(
        "service cpu: {service_s:.1} s in the simulated days without the generator's {:.1} s (the endpoint client's included), {:.3} s/machine-day{}",
        nc.gen_fast_s,
        service_s / machine_days,
        u.server_s.map_or(String::new(), |s| format!(
            ", and the PostgreSQL server's {:.3} s/machine-day",
            s / machine_days
        ))
    );
    println!(
        "nc traffic: {} posts ({} events; the recorded day has {} events a machine-day), {} order polls, {} orders answered, {} errors",
        nc.fast.posts,
        nc.fast.events,
        nc.events_per_day,
        nc.fast.order_polls,
        nc.fast.orders,
        nc.fast.errors
    );
    if let Some(p) = &f.paced {
        let w = p.usage.wall_s;
        println!(
            "realtime nc traffic: {:.0} posts/s, {:.0} order polls/s (each NC every {ORDER_POLL_S} s), {} orders, {} errors; cores busy: the service {:.3}, the generator {:.3}",
            nc.paced.posts as f64 / w,
            nc.paced.order_polls as f64 / w,
            nc.paced.orders,
            nc.paced.errors,
            (p.usage.own_s() - nc.gen_paced_s) / w,
            nc.gen_paced_s / w
        );
    }
    if let Some(idle) = &nc.idle {
        println!(
            "idle: {:.0} s at 1x with every NC silent and no client: {:.2} % of a core (user {:.2} s, sys {:.2} s){}",
            idle.wall_s,
            100.0 * idle.own_s() / idle.wall_s,
            idle.user_s,
            idle.sys_s,
            idle.server_s.map_or(String::new(), |s| format!(
                "; PostgreSQL server {:.2} % of a core",
                100.0 * s / idle.wall_s
            ))
        );
    }
}

/// The 1x phase's lines.
fn report_paced(opts: &FleetOptions, p: &Paced) {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as f64;
    let u = &p.usage;
    let mut lags = p.lags_s.clone();
    lags.sort_by(f64::total_cmp);
    let q = |q: f64| {
        lags.get(((lags.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    let used = (u.own_s() + u.server_s.unwrap_or(0.0)) / u.wall_s;
    println!(
        "realtime: {:.1} min at 1x from {} (machine time), cores busy: this process {:.2}, PostgreSQL server {}, other processes {:.2}, of {cores}; loops behind the clock p50 {:.2} s, p99 {:.2} s, max {:.2} s; real time {}",
        u.wall_s / 60.0,
        chrono::DateTime::from_timestamp_nanos(p.from_ns).format("%H:%M"),
        u.own_s() / u.wall_s,
        u.server_s
            .map_or("-".to_string(), |s| format!("{:.2}", s / u.wall_s)),
        u.others_s() / u.wall_s,
        q(0.5),
        q(0.99),
        q(1.0),
        if q(1.0) < 1.0 {
            "kept (no loop 1 s behind)"
        } else {
            "NOT kept (a loop 1 s or more behind)"
        }
    );
    println!("realtime endpoint: {}", polled(&p.polls, u.wall_s));
    println!(
        "realtime estimate: this fleet kept {used:.2} of {cores} cores busy at 1x: about {:.0} machines if that grew linearly",
        opts.machines as f64 * cores / used
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The counts give the quantiles the sorted list of every latency gives, merged or not.
    #[test]
    fn latency_counts_give_the_sorted_lists_quantiles() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let all: Vec<u64> = (0..5000).map(|_| rng.random_range(50..20_000)).collect();
        let (mut a, mut b) = (Latencies::default(), Latencies::default());
        for (i, &us) in all.iter().enumerate() {
            if i % 3 == 0 { a.add(us) } else { b.add(us) }
        }
        a.merge(&b);
        let mut sorted = all.clone();
        sorted.sort_unstable();
        for q in [0.0, 0.5, 0.9, 0.99, 0.999, 1.0] {
            assert_eq!(a.quantile(q), super::super::quantile(&sorted, q), "q {q}");
        }
        assert_eq!(a.n, 5000);
        assert_eq!(a.max(), *sorted.last().unwrap());
        assert!(
            a.count_us.len() < all.len(),
            "equal latencies share a count"
        );
        assert!(Latencies::default().quantile(0.5).is_nan());
    }
}
