//! The executor of one machine: it feeds what the machine reports, the operator's requests and
//! the end of each step into the machine's decisions ([`MachineCore`], pure), and runs the
//! effects they return: the link, the blocking pool for solves and the view the API reads
//! itself; the store's rows, the MCAP recording and the webhooks through its writes
//! ([`writes`], on its own thread or on one of their own).
//!
//! The effects run in order from a queue. One that fails (a store that refuses writes, a
//! recorder that cannot write) stays at the head of the queue and the step fails; the next
//! step runs the queue from there before it takes anything new from the machine, so that a
//! fault neither loses nor repeats a write and nothing is served before it is stored.
//!
//! Time comes from the caller (`step(now)`), so a simulated day runs in seconds in tests and
//! at any time scale live.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;

use thiserror::Error;
use tracing::{error, info, warn};

use crate::clock::ServiceClock;
use crate::link::{LinkEvent, MachineLink};
use crate::nc_push::NcPushHandle;
use crate::recorder::{Recorder, RecorderError};
use crate::store::{FileStatus, Store, StoreError};
use driftwatch_core::cycle::CycleChecks;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::Plan;
use driftwatch_core::units::{NS_PER_MIN, NS_PER_S};
use driftwatch_machine::compensation::{self, CompensationSet};
use driftwatch_machine::machine_core::{CoreError, Effect, Input, Level, MachineCore, Restored};
use driftwatch_machine::phase::{PastEvent, PhaseInfo};
use driftwatch_thermal::model::Event;
use writes::{Job, Writer, Writes};

pub use driftwatch_machine::machine_core::{CycleView, Settings, ThermalView};

mod writes;

#[derive(Debug, Error)]
pub enum DaemonError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Recorder(#[from] RecorderError),
    #[error("machine {machine}: {source}")]
    Core { machine: String, source: CoreError },
    #[error("the loop's writer: {0}")]
    Writes(String),
}

/// Whether each of `machines` loops in one process makes its writes on a thread of its own
/// ([`MachineRuntime::write_apart`]): only while every loop and its writer can have a core
/// (`cores`) to themselves. Beyond that the loops already keep the cores busy, and handing
/// each write to another thread would only add the hand-over.
pub fn writes_apart(machines: usize, cores: usize) -> bool {
    machines > 0 && 2 * machines <= cores
}

/// Who runs a machine, as the API shows it.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, utoipa::ToSchema)]
pub struct FleetView {
    /// The process holding the machine's lease (none: nobody runs it now).
    pub holder: Option<String>,
    /// Where the holder's API answers, if it said.
    pub url: Option<String>,
    pub term: Option<i64>,
    /// Whether this process runs it.
    pub here: bool,
}

/// What the API and the fleet hold of a running machine: its view, its inbox, its NC door
/// (`nc_push` links) and its kinematics.
#[derive(Clone)]
pub struct MachineHandle {
    pub view: Arc<Mutex<MachineView>>,
    pub inbox: Arc<Mutex<Inbox>>,
    /// Set for machines on the `nc_push` link.
    pub nc: Option<NcPushHandle>,
    /// The machine's kinematics, for diagnoses of its stored data.
    pub kinematics: Option<Arc<driftwatch_core::kinematics::Kinematics>>,
}

/// What the API may see of a machine, shared with the loop: one part per aggregate.
#[derive(Debug, Clone, Default)]
pub struct MachineView {
    pub id: String,
    pub kinematics: String,
    pub phase: Option<PhaseInfo>,
    pub cycles: CycleView,
    /// The set the NC reads: the last validated one.
    pub compensation: Option<CompensationSet>,
    /// The same set as the NC endpoint sends it, serialised once per version.
    pub nc_body: Option<Arc<NcBody>>,
    pub open_alerts: Vec<driftwatch_machine::alerts::Alert>,
    /// The threshold alert rules with their references (the dashboard's limit lines).
    pub thresholds: Vec<driftwatch_machine::machine_core::AlertThreshold>,
    pub thermal: ThermalView,
    pub health: LoopHealth,
    /// In a fleet: who runs the machine (absent: this process runs every machine alone).
    pub fleet: Option<FleetView>,
}

/// The machine loop's own health.
#[derive(Debug, Clone, Default)]
pub struct LoopHealth {
    /// The service clock at the loop's last completed step, ns.
    pub clock_ns: Option<i64>,
    /// The service clock the loop has caught up with, ns: its last step, completed or failed,
    /// or, while it waits to try a failed step again, the time it waited at.
    pub attempt_ns: Option<i64>,
    /// The service clock the loop sleeps until (its core's next time, or its retry time),
    /// ns: a loop still short of it when the clock has passed it is behind.
    pub wake_ns: Option<i64>,
    /// Steps that failed (a store or recorder error) and were tried again.
    pub faults: u64,
    /// Whether the last step failed.
    pub failing: bool,
    /// The last failure: service-clock time (ns) and what went wrong.
    pub last_fault: Option<(i64, String)>,
}

/// A compensation set ready to send: its version and its JSON.
#[derive(Debug)]
pub struct NcBody {
    pub version: u64,
    pub json: bytes::Bytes,
}

impl NcBody {
    pub fn of(set: &CompensationSet) -> Option<Arc<NcBody>> {
        let json = serde_json::to_vec(&compensation::compensation_message(set)).ok()?;
        Some(Arc::new(NcBody {
            version: set.version,
            json: json.into(),
        }))
    }
}

/// Operator requests, alert acknowledgements and stored verifications waiting for the loop;
/// each one put in wakes the loop.
#[derive(Debug, Default)]
pub struct Inbox {
    pub(crate) requests: Vec<(String, i64)>,
    /// (alert id, who)
    pub(crate) acks: Vec<(u64, String)>,
    /// Verifications stored by the API, for the alert rules.
    pub(crate) verifications: Vec<driftwatch_machine::verification::Verification>,
    /// Geometry versions stored by the API: (label, geometry).
    pub(crate) geometries: Vec<(String, driftwatch_core::linear_axes::LinearGeometry)>,
    wake: Arc<Notify>,
}

impl Inbox {
    /// An operator's request for a cycle, by `by` at service time `t_ns`.
    pub fn request(&mut self, by: String, t_ns: i64) {
        self.requests.push((by, t_ns));
        self.wake.notify_one();
    }

    /// An acknowledgement of `alert` by `by`.
    pub fn ack(&mut self, alert: u64, by: String) {
        self.acks.push((alert, by));
        self.wake.notify_one();
    }

    /// A verification the API stored.
    pub fn verification(&mut self, v: driftwatch_machine::verification::Verification) {
        self.verifications.push(v);
        self.wake.notify_one();
    }

    /// A geometry version the API stored.
    pub fn geometry(&mut self, label: String, g: driftwatch_core::linear_axes::LinearGeometry) {
        self.geometries.push((label, g));
        self.wake.notify_one();
    }

    /// What the loop waits on besides its clock.
    pub fn waker(&self) -> Arc<Notify> {
        self.wake.clone()
    }
}

/// The settings of a machine's decisions from the service's configuration.
pub fn settings_from_config(cfg: &crate::config::ServiceConfig) -> Settings {
    Settings {
        phase: cfg.phase.clone(),
        schedule: cfg.schedule.clone(),
        validation: cfg.validation.clone(),
        alert_rules: cfg.alerts.clone(),
        prediction: cfg.thermal.clone(),
        initial_model: None,
    }
}

/// The events and jobs a loop's queues keep room for between steps.
const QUEUE_KEPT: usize = 16;

pub struct MachineRuntime {
    pub id: String,
    core: MachineCore,
    link: Box<dyn MachineLink>,
    /// For the reads the loop makes; its writes are the writer's.
    store: Store,
    /// The writes, inline or on a thread of their own.
    writes: Writes,
    /// The loop's own work not yet done (and writes not yet queued), in order; a failed job
    /// stays at the head.
    queue: VecDeque<Job>,
    /// Events taken from the link and not yet fed to the core (a step failed meanwhile).
    events: VecDeque<LinkEvent>,
    pub view: Arc<Mutex<MachineView>>,
    pub inbox: Arc<Mutex<Inbox>>,
    /// The loop's health alert is sent from the loop itself (its writes may be held up by the
    /// fault it reports).
    notifier: crate::webhook::Notifier,
    /// The set version last handed to the link, thermal-view revision and alerts revision
    /// last shown to the API.
    published: (Option<u64>, u64, u64),
    /// The service clock at the current step.
    clock_ns: i64,
    /// Steps failed since the last one that succeeded (0: healthy).
    failed_steps: u64,
}

/// The stored spindle and temperature samples and validated cycle results in a window, as
/// the thermal model's timeline (inputs before observations at the same time).
async fn stored_events(
    store: &Store,
    machine: &str,
    from_ns: i64,
    to_ns: i64,
) -> Result<Vec<Event>, DaemonError> {
    let mut ev: Vec<Event> = store
        .samples(machine, from_ns, to_ns)
        .await?
        .into_iter()
        .map(Event::from)
        .collect();
    ev.extend(
        store
            .error_series(machine, from_ns, to_ns, true, false)
            .await?
            .into_iter()
            .map(|v| Event::Observation {
                t_ns: v.t_ns,
                channel: v.name,
                value: v.value,
                sigma: Some(v.sigma).filter(|s| s.is_finite()),
            }),
    );
    ev.sort_by_key(|e| (e.t_ns(), matches!(e, Event::Observation { .. })));
    Ok(ev)
}

/// What the store remembers of a machine, for its core.
async fn restore(
    store: &Store,
    id: &str,
    settings: &Settings,
    now_ns: i64,
) -> Result<Restored, DaemonError> {
    let (last_start_ns, last_good_ns) = store.schedule_memory(id).await?;
    let window = Restored::history_window(last_start_ns, &settings.prediction, now_ns);
    let history = match window {
        Some((from, to)) => stored_events(store, id, from, to).await?,
        None => Vec::new(),
    };
    let measured = match store.latest_measurement(id).await? {
        Some(m) => {
            let t = match m.cycle {
                Some(c) => store.result(id, c).await?.map(|r| r.t_ns),
                None => None,
            };
            Some((t.unwrap_or(m.valid_from_ns), m))
        }
        None => None,
    };
    // The phase's window: the spindle samples and the cycles' spans, so that a cycle's spin
    // is not taken for a spindle start.
    let from = now_ns.saturating_sub(Restored::phase_window_ns(&settings.phase));
    // The thermal model's window usually holds the phase's: its samples are read once.
    let mut phase_history: Vec<PastEvent> = match window {
        Some((start, _)) if start <= from => history
            .iter()
            .filter_map(|e| match e {
                Event::Spindle { t_ns, rpm } if *t_ns >= from => Some(PastEvent::Spindle {
                    t_ns: *t_ns,
                    rpm: *rpm,
                }),
                _ => None,
            })
            .collect(),
        _ => store
            .samples(id, from, now_ns)
            .await?
            .into_iter()
            .filter_map(|s| match s {
                crate::store::Sample::Spindle { t_ns, rpm } => {
                    Some(PastEvent::Spindle { t_ns, rpm })
                }
                crate::store::Sample::Temperature { .. } => None,
            })
            .collect(),
    };
    for (start, end) in store.cycle_spans(id, from, now_ns).await? {
        phase_history.push(PastEvent::Cycle {
            t_ns: start,
            active: true,
        });
        phase_history.push(PastEvent::Cycle {
            t_ns: end.unwrap_or(now_ns),
            active: false,
        });
    }
    Ok(Restored {
        last_start_ns,
        last_good_ns,
        history,
        served: store.latest_compensation(id).await?,
        measured,
        last_closed: store.last_closed_cycle(id).await?,
        next_cycle: store.next_cycle_number(id).await?,
        alerts: store.alert_state(id).await?,
        logged_alerts: store.logged_alerts(id).await?,
        phase_history,
    })
}

impl MachineRuntime {
    pub fn kinematics(&self) -> &Kinematics {
        self.core.kinematics()
    }

    #[allow(clippy::too_many_arguments)]
    pub async fn new(
        id: &str,
        k: Kinematics,
        plan: &Plan,
        link: Box<dyn MachineLink>,
        settings: &Settings,
        store: Store,
        mut recorder: Recorder,
        now_ns: i64,
    ) -> Result<Self, DaemonError> {
        store.ensure_machine(id, &k.name, now_ns).await?;
        // A cycle left open by a crash cannot be finished: its machine moved on.
        for c in store.open_cycles(id).await? {
            store
                .abandon_cycle(id, c, now_ns, "the service stopped during the cycle")
                .await?;
        }
        for f in recorder.recover()? {
            info!(machine = id, path = %f.path.display(), messages = f.messages, "recovered a recording left open");
            store
                .mcap_file_closed(
                    id,
                    &f.partial.display().to_string(),
                    &f.path.display().to_string(),
                    now_ns,
                    FileStatus::Recovered,
                    f.messages as i64,
                )
                .await?;
        }
        let restored = restore(&store, id, settings, now_ns).await?;
        // The newest stored geometry version, not the machine file's, is what the solves
        // start from.
        let k = match store.latest_geometry(id).await? {
            Some(g) => {
                let label = g.label();
                info!(machine = id, geometry = %label, "linear geometry restored from the store");
                k.with_geometry(&g.geometry, &label)
                    .map_err(|e| DaemonError::Core {
                        machine: id.to_string(),
                        source: driftwatch_machine::machine_core::CoreError::Geometry(
                            e.to_string(),
                        ),
                    })?
            }
            None => k,
        };
        let mut checks = CycleChecks::new(&k);
        checks.expected = Some(driftwatch_core::cycle::plan_measurements(plan));
        let kin_name = k.name.clone();
        let (core, said) = MachineCore::new(
            Arc::new(k),
            checks,
            plan.steps.len(),
            settings,
            restored,
            now_ns,
        )
        .map_err(|source| DaemonError::Core {
            machine: id.to_string(),
            source,
        })?;
        // The core starts from the store's newest set: that is the stored set.
        let stored_set = core.served().cloned();
        let view_version = stored_set.as_ref().map(|c| c.version);
        let cv = core.view();
        let view = MachineView {
            id: id.to_string(),
            kinematics: kin_name,
            compensation: stored_set.clone(),
            nc_body: stored_set.as_ref().and_then(NcBody::of),
            cycles: cv.cycles.clone(),
            open_alerts: cv.open_alerts.clone(),
            thresholds: cv.thresholds.clone(),
            ..Default::default()
        };
        let alerts_revision = cv.alerts_revision;
        let view = Arc::new(Mutex::new(view));
        let writer = Writer::new(id, store.clone(), recorder, view.clone());
        let mut rt = MachineRuntime {
            id: id.to_string(),
            core,
            link,
            store,
            writes: Writes::Inline(Box::new(writer)),
            queue: VecDeque::new(),
            events: VecDeque::new(),
            view,
            inbox: Arc::new(Mutex::new(Inbox::default())),
            notifier: Default::default(),
            published: (view_version, 0, alerts_revision),
            clock_ns: now_ns,
            failed_steps: 0,
        };
        rt.queue.extend(said.into_iter().map(Job::Core));
        rt.drain().await?;
        Ok(rt)
    }

    /// Show the machine in `view` and take requests from `inbox` (the API's, kept by a fleet
    /// across the loops that run the machine one after another) instead of the loop's own.
    pub fn adopt(&mut self, view: &Arc<Mutex<MachineView>>, inbox: &Arc<Mutex<Inbox>>) {
        let mine = self.view.lock().map(|v| v.clone()).unwrap_or_default();
        if let Ok(mut v) = view.lock() {
            let fleet = v.fleet.take();
            *v = MachineView { fleet, ..mine };
        }
        self.view = view.clone();
        self.inbox = inbox.clone();
        self.writes.set_view(view, self.waker());
    }

    /// What wakes the loop when the API puts something in its inbox (the inbox it takes
    /// requests from now: a fleet may have handed it another).
    fn waker(&self) -> Option<Arc<Notify>> {
        self.inbox.lock().map(|i| i.waker()).ok()
    }

    /// Send alert events to these webhooks from now on.
    pub fn set_notifier(&mut self, notifier: crate::webhook::Notifier) {
        self.writes.set_notifier(notifier.clone());
        self.notifier = notifier;
    }

    /// Make the loop's writes on a thread of their own from now on, where its store writes
    /// on the calling thread (SQLite outside a fleet); elsewhere they stay on the loop's.
    /// Worth a core: [`writes_apart`] says when. An error (no thread could be started) leaves
    /// them on the loop's thread, and says why.
    pub fn write_apart(&mut self) -> Result<(), DaemonError> {
        let wake = self.waker();
        self.writes.go_apart(wake)
    }

    /// Whether the loop's writes run on a thread of their own.
    pub fn writes_are_apart(&self) -> bool {
        matches!(self.writes, Writes::Apart(_))
    }

    /// Handle everything up to `now_ns`; returns when to call again at the latest. A step
    /// that fails raises the loop's health alert at once (shown and sent, stored when the
    /// store takes writes again); the first step that succeeds after it resolves it.
    pub async fn step(&mut self, now_ns: i64) -> Result<i64, DaemonError> {
        match self.step_inner(now_ns).await {
            Ok(wake) if self.failed_steps == 0 => Ok(wake),
            Ok(wake) => {
                let failed_steps = std::mem::take(&mut self.failed_steps);
                info!(machine = %self.id, failed_steps, "the machine loop steps again: its pending writes are stored");
                self.feed(
                    Input::LoopFault {
                        failing: false,
                        failed_steps,
                        message: format!(
                            "the loop steps again after {failed_steps} failed steps; every \
                             pending write is stored"
                        ),
                    },
                    now_ns,
                );
                self.drain().await.map_err(|e| self.failed(now_ns, e))?;
                self.writes
                    .step_done()
                    .await
                    .map_err(|e| self.failed(now_ns, e))?;
                Ok(wake)
            }
            Err(e) => Err(self.failed(now_ns, e)),
        }
    }

    /// A failed step: on the first of a run, the health alert is raised in the core, shown in
    /// the view and sent at once; its storing waits in the queue behind the failed write.
    fn failed(&mut self, now_ns: i64, e: DaemonError) -> DaemonError {
        self.failed_steps += 1;
        if self.failed_steps == 1 {
            let message = format!(
                "the machine loop cannot store (no new compensation set is served until it \
                 can; the NC keeps the last stored one): {e}"
            );
            let input = Input::LoopFault {
                failing: true,
                failed_steps: 1,
                message,
            };
            for effect in self.core.handle(input, now_ns) {
                match effect {
                    Effect::Alert(ev) => {
                        warn!(machine = %self.id, alert = ev.id, rule = %ev.rule, kind = ?ev.kind, "{}", ev.message);
                        self.notifier.notify(&self.id, &ev);
                        self.queue.push_back(Job::StoreAlert(ev));
                    }
                    // The view's alerts only: the served set stays the stored one.
                    Effect::PublishView => self.publish(),
                    other => self.queue.push_back(Job::Core(other)),
                }
            }
        }
        e
    }

    async fn step_inner(&mut self, now_ns: i64) -> Result<i64, DaemonError> {
        self.clock_ns = now_ns;
        // What a failed step left: its effects first, then its events.
        self.drain().await?;
        self.events.extend(self.link.poll(now_ns));
        while let Some(ev) = self.events.pop_front() {
            self.feed(Input::Link(ev), now_ns);
            self.drain().await?;
        }
        let (requests, acks, verifications, geometries) = match self.inbox.lock() {
            Ok(mut inbox) => (
                std::mem::take(&mut inbox.requests),
                std::mem::take(&mut inbox.acks),
                std::mem::take(&mut inbox.verifications),
                std::mem::take(&mut inbox.geometries),
            ),
            Err(_) => Default::default(),
        };
        for (label, g) in geometries {
            self.feed(
                Input::Geometry {
                    label,
                    geometry: Box::new(g),
                },
                now_ns,
            );
        }
        for (alert, by) in acks {
            self.feed(Input::Ack { alert, by }, now_ns);
        }
        for v in verifications {
            self.feed(Input::Verification(Box::new(v)), now_ns);
        }
        // Stamped with the loop's time: a simulated machine's clock is not the wall clock.
        for (by, _) in requests {
            self.feed(Input::Request { by }, now_ns);
        }
        self.feed(Input::Tick, now_ns);
        self.drain().await?;
        self.writes.step_done().await?;
        // Both are empty now. A burst (an NC posting an hour of events at once) grows them,
        // and at that size they would stay with the loop for good.
        self.events.shrink_to(QUEUE_KEPT);
        self.queue.shrink_to(QUEUE_KEPT);
        let wake = self.core.wake_after(now_ns);
        Ok(match self.link.next_event_ns() {
            Some(t) if t > now_ns => wake.min(t),
            _ => wake,
        })
    }

    fn feed(&mut self, input: Input, now_ns: i64) {
        let effects = self.core.handle(input, now_ns);
        self.queue.extend(effects.into_iter().map(Job::Core));
    }

    /// Run the queue in order; a job that fails stays at its head (a write, at the head of
    /// the writer's queue). Writes that failed before are tried again first.
    async fn drain(&mut self) -> Result<(), DaemonError> {
        self.writes.retry_failed().await?;
        while let Some(job) = self.queue.pop_front() {
            if job.is_write() {
                self.writes.push(job, self.clock_ns).await?;
                continue;
            }
            match self.run(&job).await {
                Ok(follow) => {
                    // What a job gives (the answer to a request, a solve's effects) runs
                    // before the rest of the queue.
                    for j in follow.into_iter().rev() {
                        self.queue.push_front(j);
                    }
                }
                Err(e) => {
                    self.queue.push_front(job);
                    return Err(e);
                }
            }
        }
        Ok(())
    }

    /// Run one of the loop's own jobs; returns the jobs it gives, to run next.
    async fn run(&mut self, job: &Job) -> Result<Vec<Job>, DaemonError> {
        let now = self.clock_ns;
        let core_jobs = |effects: Vec<Effect>| effects.into_iter().map(Job::Core).collect();
        let Job::Core(effect) = job else {
            return Ok(Vec::new());
        };
        match effect {
            Effect::RequestCycle { number } => {
                let result = self
                    .link
                    .request_cycle(*number, now)
                    .map_err(|e| e.to_string());
                let input = Input::CycleRequested {
                    number: *number,
                    result,
                };
                return Ok(core_jobs(self.core.handle(input, now)));
            }
            Effect::AbortCycle { number } => self.link.abort_cycle(*number, now),
            Effect::Solve(job) => {
                let input = Self::solve(job).await;
                return Ok(core_jobs(self.core.handle(input, now)));
            }
            Effect::PublishView => self.publish(),
            Effect::Log(level, message) => match level {
                Level::Info => info!(machine = %self.id, "{message}"),
                Level::Warn => warn!(machine = %self.id, "{message}"),
                Level::Error => error!(machine = %self.id, "{message}"),
            },
            // The writer's: never run here.
            _ => {}
        }
        Ok(Vec::new())
    }

    /// Solve on the blocking pool, so that the async threads keep answering the API and the
    /// other machines meanwhile. A solver that panics gives no outcome, and says why.
    async fn solve(job: &driftwatch_machine::machine_core::SolveJob) -> Input {
        let number = job.number;
        let job = job.clone();
        let solved = tokio::task::spawn_blocking(move || {
            let started = std::time::Instant::now();
            let outcome = job.run();
            (outcome, started.elapsed().as_secs_f64())
        })
        .await;
        match solved {
            Ok((outcome, seconds)) => Input::Solved {
                number,
                outcome: Box::new(Ok(outcome)),
                seconds,
            },
            Err(e) => Input::Solved {
                number,
                outcome: Box::new(Err(e.to_string())),
                seconds: 0.0,
            },
        }
    }

    /// Show the core's view to the API. The set it shows is the writer's, the newest one
    /// stored (the core's own may not be stored yet); a link that writes the set to the NC
    /// gets it here, as the API does, once stored. The copies are made before the lock is
    /// taken and the old values dropped after it is released, so that the NC's reads never
    /// wait on them; the thermal view and the alerts are copied only when they changed.
    fn publish(&mut self) {
        let cv = self.core.view();
        let thermal = (cv.thermal.revision != self.published.1).then(|| cv.thermal.clone());
        let alerts = (cv.alerts_revision != self.published.2)
            .then(|| (cv.open_alerts.clone(), cv.thresholds.clone()));
        self.published.1 = cv.thermal.revision;
        self.published.2 = cv.alerts_revision;
        let mut cycles = cv.cycles.clone();
        let phase = cv.phase;
        let mut old_thermal = None;
        let mut old_alerts = None;
        let mut stored = None;
        if let Ok(mut v) = self.view.lock() {
            v.phase = phase;
            std::mem::swap(&mut v.cycles, &mut cycles);
            if let Some((open, rules)) = alerts {
                old_alerts = Some((
                    std::mem::replace(&mut v.open_alerts, open),
                    std::mem::replace(&mut v.thresholds, rules),
                ));
            }
            if let Some(t) = thermal {
                old_thermal = Some(std::mem::replace(&mut v.thermal, t));
            }
            let version = v.compensation.as_ref().map(|c| c.version);
            if version != self.published.0 {
                self.published.0 = version;
                stored = v.compensation.clone();
            }
        }
        drop((cycles, old_alerts, old_thermal));
        if let Some(set) = stored {
            self.link.serve(&set);
        }
    }

    /// Give up the open cycle, store what is held and close the recording cleanly.
    pub async fn shutdown(&mut self, now_ns: i64) -> Result<(), DaemonError> {
        self.clock_ns = now_ns;
        self.feed(Input::Shutdown, now_ns);
        self.drain().await?;
        self.writes.stop(now_ns).await
    }

    /// Wait until every write the loop has decided is made (inline they are already); one
    /// that fails fails the step it is part of.
    pub async fn settle_writes(&mut self, now_ns: i64) -> Result<(), DaemonError> {
        self.writes
            .settle()
            .await
            .map_err(|e| self.failed(now_ns, e))
    }

    /// The set served: the newest one stored.
    pub fn served(&self) -> Option<CompensationSet> {
        self.view.lock().ok().and_then(|v| v.compensation.clone())
    }

    pub fn store(&self) -> &Store {
        &self.store
    }
}

/// A failing loop waits this much machine time before it tries again, doubling up to
/// [`MAX_RETRY_NS`].
const FIRST_RETRY_NS: i64 = NS_PER_S;
const MAX_RETRY_NS: i64 = 10 * NS_PER_MIN;

/// A loop steps at least once a minute; each machine at its own place in the minute (from its
/// id), so that loops started together do not all step, and write, in the same instant for
/// ever after: the API's answers would wait behind each burst.
const HEARTBEAT_NS: i64 = NS_PER_MIN;

/// The places in the minute are this far apart. Every timer that fires wakes a runtime thread
/// (a context switch, most of what a quiet loop costs); loops that share a place share the
/// wake. A tenth of a second: 600 places, so 10 000 machines wake in groups of about 17.
const HEARTBEAT_SLOT_NS: i64 = NS_PER_S / 10;

/// The machine's place in the minute, ns in `[0, HEARTBEAT_NS)`, a whole number of
/// [`HEARTBEAT_SLOT_NS`]: FNV-1a of its id, stable from one start to the next.
fn heartbeat_phase(id: &str) -> i64 {
    use std::hash::Hasher;
    let mut h = fnv::FnvHasher::default();
    h.write(id.as_bytes());
    (h.finish() % (HEARTBEAT_NS / HEARTBEAT_SLOT_NS) as u64) as i64 * HEARTBEAT_SLOT_NS
}

/// The first time after `now` at the machine's place in the minute: a wake the core asked for
/// later than that is brought forward to it (an extra step changes nothing; the core's own
/// fallback wake is a minute after each step, which would keep the loops in step).
fn heartbeat_after(now: i64, phase: i64) -> i64 {
    let next = now - (now - phase).rem_euclid(HEARTBEAT_NS) + HEARTBEAT_NS;
    debug_assert!(next > now && next <= now + HEARTBEAT_NS);
    next
}

/// When the loop steps next, given the clock's time (`target`, at most the run's end), the
/// time the last step asked to be called again (`wake`) and the last step's time: at each time
/// it asked for, up to the clock, so that a clock that jumped ahead (a manual clock, a machine
/// that slept) is caught up with as if it had run, not in one stride that would start every
/// due cycle late; and at the clock's time when something woke it (its inbox, its link, a
/// held clock's hand). A failing loop (`wake` is then its retry time) steps not before its
/// retry time, unless the run ends first: stepping at each post of its NC would retry the
/// failed write, and log it, as often as the NC posts, whatever the doubling wait says.
/// `None`: wait.
fn step_at(target: i64, wake: i64, last: i64, failing: bool, end: Option<i64>) -> Option<i64> {
    if failing && target < wake && end.is_none_or(|e| target < e) {
        return None;
    }
    Some(target.min(wake.max(last.saturating_add(1))))
}

/// Sleep until the clock reaches `wake`, something is put in the inbox, the link has news
/// or the service stops; nothing else wakes a loop, so a quiet machine costs nothing between
/// the times its core asked for.
async fn wait(
    inbox: Option<Arc<Notify>>,
    link: Option<&Notify>,
    clock: &mut ServiceClock,
    wake: i64,
    shutdown: &CancellationToken,
) {
    let news = async {
        match link {
            Some(l) => l.notified().await,
            None => std::future::pending().await,
        }
    };
    let asked = async {
        match &inbox {
            Some(i) => i.notified().await,
            None => std::future::pending().await,
        }
    };
    tokio::select! {
        _ = clock.sleep_until(wake) => {}
        _ = news => {}
        _ = asked => {}
        _ = shutdown.cancelled() => {}
    }
}

/// One machine's loop: step it on the clock; a failing step (a store that refuses writes, a
/// recorder that cannot write) is logged, counted in its view (and so in `/metrics`) and
/// tried again with a doubling wait, and never stops the other machines or the API.
///
/// The runtime comes boxed: an async fn keeps its arguments beside its locals, so a runtime
/// passed by value would sit twice in every loop's task.
pub(crate) async fn run_machine(
    mut rt: Box<MachineRuntime>,
    mut clock: ServiceClock,
    start_ns: i64,
    end: Option<i64>,
    shutdown: CancellationToken,
) {
    let link = rt.link.waker();
    let phase = heartbeat_phase(&rt.id);
    let mut retry_ns = FIRST_RETRY_NS;
    let mut last = i64::MIN;
    let mut failing = false;
    // The first step is at the clock's start, however far the clock has gone since.
    let mut wake = start_ns;
    loop {
        // Looked at, not just read: a hand that moves the clock while the loop steps wakes
        // its next wait at once.
        let seen = clock.look();
        let target = end.map_or(seen, |e| seen.min(e));
        let Some(now) = step_at(target, wake, last, failing, end) else {
            // Waiting to try a failed step again: the loop has looked at the clock's time.
            if let Ok(mut v) = rt.view.lock() {
                v.health.attempt_ns = Some(target);
            }
            wait(rt.waker(), link.as_deref(), &mut clock, wake, &shutdown).await;
            if shutdown.is_cancelled() {
                break;
            }
            continue;
        };
        last = now;
        // Boxed: inline, the step's future (about 1 KB) would stay in every loop's task
        // between steps; on the heap it lives only while a step runs.
        let mut stepped = Box::pin(rt.step(now)).await;
        // Caught up with the clock, the loop waits for its writes before it says it stepped
        // and sleeps: a reader who saw the step sees its rows. Only a loop behind its clock
        // (a replay as fast as it goes) steps on while its writer writes.
        if let Ok(wake) = stepped
            && now >= target
        {
            stepped = Box::pin(rt.settle_writes(now)).await.map(|()| wake);
        }
        if let Ok(mut v) = rt.view.lock() {
            v.health.attempt_ns = Some(now);
        }
        failing = stepped.is_err();
        wake = match stepped {
            Ok(wake) => {
                retry_ns = FIRST_RETRY_NS;
                if let Ok(mut v) = rt.view.lock() {
                    v.health.clock_ns = Some(now);
                    v.health.failing = false;
                }
                wake.min(heartbeat_after(now, phase))
            }
            Err(e) => {
                error!(machine = %rt.id, error = %e, retry_in_s = retry_ns / NS_PER_S, "the machine loop failed a step; trying again");
                if let Ok(mut v) = rt.view.lock() {
                    v.health.faults += 1;
                    v.health.failing = true;
                    v.health.last_fault = Some((now, e.to_string()));
                }
                let at = now.saturating_add(retry_ns);
                retry_ns = (retry_ns * 2).min(MAX_RETRY_NS);
                at
            }
        };
        if let Ok(mut v) = rt.view.lock() {
            v.health.wake_ns = Some(wake);
        }
        if end.is_some_and(|e| now >= e) || shutdown.is_cancelled() {
            break;
        }
        if now < target {
            continue;
        }
        wait(rt.waker(), link.as_deref(), &mut clock, wake, &shutdown).await;
    }
    let now = end
        .map_or(clock.now_ns(), |e| clock.now_ns().min(e))
        .max(last);
    if let Err(e) = Box::pin(rt.shutdown(now)).await {
        error!(machine = %rt.id, error = %e, "the machine loop could not close its recordings cleanly");
    }
}

#[cfg(test)]
mod tests {
    use super::{HEARTBEAT_NS, HEARTBEAT_SLOT_NS, heartbeat_after, heartbeat_phase, step_at};

    /// A loop's task holds its runtime by a pointer and a step's future only while the step
    /// runs: with the runtime by value and the step inline it held 11.6 KB between steps, for
    /// each of thousands of loops.
    #[test]
    fn a_loops_task_is_small_between_steps() {
        fn future_size<A, B, C, D, E, F>(_: fn(A, B, C, D, E) -> F) -> usize {
            std::mem::size_of::<F>()
        }
        let task = future_size(super::run_machine);
        assert!(task < 1280, "a loop's task holds {task} bytes");
    }

    /// Every loop steps within a minute of its last step, at its own place in the minute, and
    /// the machines of a fleet spread over the minute.
    #[test]
    fn loops_beat_once_a_minute_each_at_its_own_second() {
        let phase = heartbeat_phase("m0001");
        assert_eq!(phase, heartbeat_phase("m0001"), "stable");
        assert_eq!(phase % HEARTBEAT_SLOT_NS, 0, "on a place of the minute");
        for now in [0, 1, phase - 1, phase, phase + 1, 7 * HEARTBEAT_NS + 12_345] {
            let next = heartbeat_after(now, phase);
            assert!(next > now && next <= now + HEARTBEAT_NS, "{now} -> {next}");
            assert_eq!((next - phase).rem_euclid(HEARTBEAT_NS), 0);
        }
        // 1000 machines: every tenth of the minute holds 100 +- 40 of them.
        let mut tenths = [0usize; 10];
        for i in 0..1000 {
            tenths[(heartbeat_phase(&format!("m{i:04}")) * 10 / HEARTBEAT_NS) as usize] += 1;
        }
        assert!(tenths.iter().all(|n| (60..=140).contains(n)), "{tenths:?}");
    }

    const S: i64 = 1_000_000_000;

    /// A healthy loop steps at each time it asked for, up to the clock, and at the clock's
    /// time when it looks at its inbox; a failing one waits for its retry time, and steps at
    /// the run's end if that comes first.
    #[test]
    fn a_failing_loop_steps_again_at_its_retry_time_not_at_each_look_at_its_inbox() {
        // Caught up, healthy: the inbox look steps at the clock.
        assert_eq!(
            step_at(100 * S, 200 * S, 100 * S, false, None),
            Some(100 * S)
        );
        // Behind the clock: the time it asked for first.
        assert_eq!(
            step_at(300 * S, 200 * S, 100 * S, false, None),
            Some(200 * S)
        );
        // Failing, retry at 200 s, the clock at 101 s: wait (stepping at 101 s would retry).
        assert_eq!(step_at(101 * S, 200 * S, 100 * S, true, None), None);
        // The retry time reached, or passed: step at it.
        assert_eq!(
            step_at(200 * S, 200 * S, 100 * S, true, None),
            Some(200 * S)
        );
        assert_eq!(
            step_at(900 * S, 200 * S, 100 * S, true, None),
            Some(200 * S)
        );
        // The run ends before the retry: the last step at its end.
        assert_eq!(
            step_at(150 * S, 200 * S, 100 * S, true, Some(150 * S)),
            Some(150 * S)
        );
    }
}
