//! The service's loop for one machine: take what the machine reports, keep its phase, start
//! cycles when the policy says so and the machine is idle, solve and validate each cycle,
//! store everything (SQLite and MCAP), serve only validated compensation, raise alerts.
//!
//! Time comes from the caller (`step(now)`), so a simulated day runs in seconds in tests and
//! at any time scale live. This is shell code around the pure core.

use driftwatch_core::units;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use thiserror::Error;
use tracing::{error, info, warn};

use crate::link::{LinkEvent, MachineLink};
use crate::recorder::{Recorder, RecorderError};
use crate::store::{
    AlertEventKind, DetectionRow, FileStatus, NewAlertEvent, Sample, Store, StoreError,
};
use driftwatch_core::cycle::{CycleChecks, process_cycle};
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::Plan;
use driftwatch_core::recording::{self as rec, DetectionIssue, DetectionMsg, ResultStatus, Timed};
use driftwatch_core::thermal_model::Event;
use driftwatch_machine::alerts::{AlertEngine, AlertEvent, ClockInput, Input, Rule};
use driftwatch_machine::compensation::{self, CompensationSet, ValidationLimits};
use driftwatch_machine::live_model::LiveModel;
use driftwatch_machine::phase::{PhaseConfig, PhaseError, PhaseInfo, PhaseTracker};
use driftwatch_machine::scheduler::{Decision, SchedulePolicy, SchedulerState, decide};

#[derive(Debug, Error)]
pub enum DaemonError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Recorder(#[from] RecorderError),
    #[error("machine {machine}: {source}")]
    Phase { machine: String, source: PhaseError },
    #[error("machine {machine}: alert rules: {message}")]
    Alerts { machine: String, message: String },
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
    pub thermal: ThermalView,
    pub health: LoopHealth,
}

/// The machine's cycles: the last and the open one, the schedule, and the counts by outcome.
#[derive(Debug, Clone, Default)]
pub struct CycleView {
    pub last: Option<i64>,
    pub open: Option<i64>,
    /// Detections the open cycle has received so far (they are stored when it ends).
    pub open_received: Option<usize>,
    /// Steps the plan expects per cycle.
    pub steps_per_cycle: usize,
    /// Why the scheduler waits, or why the last cycle started.
    pub schedule: String,
    pub next_due_ns: Option<i64>,
    pub ok: u64,
    pub rejected: u64,
    pub abandoned: u64,
    /// Time spent validating and solving cycles, s.
    pub solve_seconds_sum: f64,
}

/// The thermal model: its state, the last prediction, and a copy of the running predictor
/// for predictions at a later time.
#[derive(Debug, Clone, Default)]
pub struct ThermalView {
    pub model: Option<driftwatch_machine::live_model::ModelView>,
    pub prediction: Vec<driftwatch_core::thermal_model::Prediction>,
    pub prediction_t_ns: Option<i64>,
    /// Why the last prediction was not served, if it was not.
    pub prediction_note: Option<String>,
    pub predictor: Option<Arc<driftwatch_core::thermal_model::Predictor>>,
}

/// The machine loop's own health.
#[derive(Debug, Clone, Default)]
pub struct LoopHealth {
    /// The service clock at the loop's last completed step, ns.
    pub clock_ns: Option<i64>,
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

/// Operator requests and alert acknowledgements waiting for the loop.
#[derive(Debug, Default)]
pub struct Inbox {
    pub requests: Vec<(String, i64)>,
    /// (alert id, who)
    pub acks: Vec<(u64, String)>,
}

#[derive(Debug, Clone)]
pub struct Settings {
    pub phase: PhaseConfig,
    pub schedule: SchedulePolicy,
    pub validation: ValidationLimits,
    pub alert_rules: Vec<Rule>,
    pub prediction: driftwatch_machine::compensation::PredictionPolicy,
    /// A thermal model fitted elsewhere to start from (the machine's `thermal_model`).
    pub initial_model: Option<Arc<driftwatch_core::thermal_model::ThermalModel>>,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            phase: PhaseConfig::default(),
            schedule: SchedulePolicy::default(),
            validation: ValidationLimits::default(),
            alert_rules: driftwatch_machine::alerts::default_rules(),
            prediction: Default::default(),
            initial_model: None,
        }
    }
}

impl Settings {
    pub fn from_config(cfg: &crate::config::ServiceConfig) -> Self {
        Settings {
            phase: cfg.phase.clone(),
            schedule: cfg.schedule.clone(),
            validation: cfg.validation.clone(),
            alert_rules: cfg.alerts.clone(),
            prediction: cfg.thermal.clone(),
            initial_model: None,
        }
    }
}

struct OpenCycle {
    number: i64,
    detections: Vec<Timed<Result<DetectionMsg, DetectionIssue>>>,
}

pub struct MachineRuntime {
    pub id: String,
    /// Shared with the blocking pool the solves run on.
    k: Arc<Kinematics>,
    link: Box<dyn MachineLink>,
    phase: PhaseTracker,
    policy: SchedulePolicy,
    sched: SchedulerState,
    checks: CycleChecks,
    limits: ValidationLimits,
    alerts: AlertEngine,
    recorder: Recorder,
    store: Store,
    open: Option<OpenCycle>,
    served: Option<CompensationSet>,
    /// The last measured set with its cycle's reference time: the next cycle's step and the
    /// predictions are checked against it (the served set may be predicted, or ramped).
    measured: Option<(i64, CompensationSet)>,
    /// Minute and speed of the last stored spindle sample (every change is stored, and one
    /// sample a minute besides), and what is known of each temperature sensor.
    last_spindle: (i64, f64),
    last_temp: BTreeMap<String, SensorLog>,
    /// Per-minute samples not yet written.
    samples: Vec<Sample>,
    pub view: Arc<Mutex<MachineView>>,
    pub inbox: Arc<Mutex<Inbox>>,
    /// Every alert event so far (also stored), newest last.
    pub alert_log: Vec<AlertEvent>,
    notifier: crate::webhook::Notifier,
    thermal: LiveModel,
    /// Machine time of the last look at the prediction, and the last refusal said.
    last_prediction_ns: i64,
    last_refusal: Option<String>,
    /// The service clock at the current step: recording files and refusals follow it.
    clock_ns: i64,
}

/// Machine time the per-minute samples are held before they are written together.
const SAMPLE_BATCH_NS: i64 = 10 * units::NS_PER_MIN;

/// A temperature sample is stored at least this often (minutes), and whenever it changes.
pub const TEMPERATURE_HEARTBEAT_MIN: i64 = 10;

/// What the loop remembers of a temperature sensor: the minute it last took a reading into
/// the model, and the last stored sample.
struct SensorLog {
    minute: i64,
    stored_minute: i64,
    stored_c: f64,
}

fn minute(t_ns: i64) -> i64 {
    t_ns.div_euclid(units::NS_PER_MIN)
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
        .map(|s| match s {
            Sample::Spindle { t_ns, rpm } => Event::Spindle { t_ns, rpm },
            Sample::Temperature {
                t_ns,
                sensor,
                celsius,
            } => Event::Temperature {
                t_ns,
                sensor,
                celsius,
            },
        })
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

impl MachineRuntime {
    pub fn kinematics(&self) -> &Kinematics {
        &self.k
    }

    #[allow(clippy::too_many_arguments)]
    pub async fn new(
        id: &str,
        k: Kinematics,
        plan: Plan,
        link: Box<dyn MachineLink>,
        settings: &Settings,
        store: Store,
        recorder: Recorder,
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
        // The scheduler remembers the last cycle and the last good result across a restart,
        // so that a restart does not by itself cause a cycle. A store whose times lie ahead of
        // the clock (a simulated day started again from its morning) is not taken.
        let mut sched = SchedulerState::default();
        let (last_start, last_good) = store.schedule_memory(id).await?;
        let mut thermal = match &settings.initial_model {
            Some(m) => {
                let live = LiveModel::with_initial(settings.prediction.clone(), m.clone());
                info!(machine = id, "thermal model: {}", live.view().message);
                live
            }
            None => LiveModel::new(settings.prediction.clone()),
        };
        if last_start.is_some_and(|t| t <= now_ns) {
            // The thermal model comes back from the stored inputs and results of its window.
            if thermal.policy().enabled {
                let from = now_ns - units::h_to_ns(thermal.policy().history_days * 24.0);
                let events = stored_events(&store, id, from, now_ns).await?;
                if let Some(note) = thermal.restore(&events) {
                    info!(
                        machine = id,
                        "thermal model restored from the store: {note}"
                    );
                }
            }
            sched.last_cycle_start_ns = last_start;
            sched.last_good_ns = last_good.filter(|t| *t <= now_ns);
        } else if last_start.is_some() {
            info!(
                machine = id,
                "the stored cycles lie ahead of the clock (a simulated day started again): the scheduler starts afresh"
            );
        }
        let served = store.latest_compensation(id).await?;
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
        let mut checks = CycleChecks::new(&k);
        checks.expected = Some(driftwatch_core::cycle::plan_measurements(&plan));
        let phase =
            PhaseTracker::new(settings.phase.clone()).map_err(|source| DaemonError::Phase {
                machine: id.to_string(),
                source,
            })?;
        let alerts =
            AlertEngine::new(settings.alert_rules.clone()).map_err(|e| DaemonError::Alerts {
                machine: id.to_string(),
                message: e.to_string(),
            })?;
        let view = MachineView {
            id: id.to_string(),
            kinematics: k.name.clone(),
            compensation: served.clone(),
            nc_body: served.as_ref().and_then(NcBody::of),
            cycles: CycleView {
                last: store.last_closed_cycle(id).await?,
                steps_per_cycle: plan.steps.len(),
                ..Default::default()
            },
            ..Default::default()
        };
        Ok(MachineRuntime {
            id: id.to_string(),
            k: Arc::new(k),
            link,
            phase,
            policy: settings.schedule.clone(),
            sched,
            checks,
            limits: settings.validation.clone(),
            alerts,
            recorder,
            store,
            open: None,
            served,
            measured,
            last_spindle: (i64::MIN, f64::NAN),
            last_temp: BTreeMap::new(),
            samples: Vec::new(),
            view: Arc::new(Mutex::new(view)),
            inbox: Arc::new(Mutex::new(Inbox::default())),
            alert_log: Vec::new(),
            notifier: Default::default(),
            thermal,
            last_prediction_ns: i64::MIN,
            last_refusal: None,
            clock_ns: now_ns,
        })
    }

    /// Send alert events to these webhooks from now on.
    pub fn set_notifier(&mut self, notifier: crate::webhook::Notifier) {
        self.notifier = notifier;
    }

    /// Handle everything up to `now_ns`; returns when to call again at the latest.
    pub async fn step(&mut self, now_ns: i64) -> Result<i64, DaemonError> {
        self.clock_ns = now_ns;
        let mut skew = ClockInput {
            t_ns: now_ns,
            refused: 0,
            worst_skew_s: 0.0,
        };
        for ev in self.link.poll(now_ns) {
            if let LinkEvent::ClockSkew {
                refused,
                worst_skew_ns,
                ..
            } = ev
            {
                skew.refused += refused;
                skew.worst_skew_s = worst_skew_ns as f64 / 1e9;
                continue;
            }
            self.on_event(ev).await?;
        }
        // Every step, so that a quiet clock lets the alert resolve.
        let events = self.alerts.evaluate(&Input::Clock(skew), now_ns);
        self.raise(events).await?;
        let (requests, acks) = match self.inbox.lock() {
            Ok(mut inbox) => (
                std::mem::take(&mut inbox.requests),
                std::mem::take(&mut inbox.acks),
            ),
            Err(_) => (Vec::new(), Vec::new()),
        };
        for (id, by) in acks {
            match self.alerts.ack(id, &by, now_ns) {
                Ok(false) => {}
                Ok(true) => {
                    info!(machine = %self.id, alert = id, by = %by, "alert acknowledged");
                    self.store
                        .add_alert_event(
                            &self.id,
                            &NewAlertEvent {
                                alert: id as i64,
                                t_ns: now_ns,
                                kind: AlertEventKind::Acknowledged,
                                rule: "",
                                severity: None,
                                message: &format!("acknowledged by {by}"),
                                value: None,
                            },
                        )
                        .await?;
                }
                Err(e) => warn!(machine = %self.id, alert = id, "acknowledgement refused: {e}"),
            }
        }
        // Stamped with the loop's time: a simulated machine's clock is not the wall clock.
        for (by, _) in requests {
            self.sched.request(by, now_ns);
        }
        self.predict_and_serve(now_ns).await?;
        let phase = self.phase.phase(now_ns);
        let decision = decide(&self.policy, &phase, &self.sched, now_ns);
        let mut next_due = None;
        let schedule = match &decision {
            Decision::Start { reason } => {
                let number = self.store.next_cycle_number(&self.id).await?;
                match self.link.request_cycle(number, now_ns) {
                    Ok(()) => {
                        info!(machine = %self.id, cycle = number, reason = %reason, "cycle started");
                        self.store
                            .open_cycle(
                                &self.id,
                                number,
                                now_ns,
                                &reason.to_string(),
                                i64::from(self.sched.failures) + 1,
                            )
                            .await?;
                        self.sched.started(number, now_ns);
                        let _ = self.phase.on_cycle(now_ns, true);
                        self.open = Some(OpenCycle {
                            number,
                            detections: Vec::new(),
                        });
                        format!("cycle {number} started: {reason}")
                    }
                    Err(e) => format!("a cycle is due ({reason}) but the machine refused: {e}"),
                }
            }
            Decision::Wait {
                next_due_ns,
                reason,
            } => {
                next_due = *next_due_ns;
                reason.to_string()
            }
            Decision::Abandon { cycle, retry } => {
                warn!(machine = %self.id, cycle, retry, "cycle timed out, abandoned");
                self.link.abort_cycle(*cycle, now_ns);
                if let Some(open) = self.open.take() {
                    self.store_detections(&open).await?;
                }
                self.store
                    .abandon_cycle(
                        &self.id,
                        *cycle,
                        now_ns,
                        "timed out before every step arrived",
                    )
                    .await?;
                self.sched.abandoned(now_ns);
                let _ = self.phase.on_cycle(now_ns, false);
                self.open = None;
                if let Ok(mut v) = self.view.lock() {
                    v.cycles.abandoned += 1;
                }
                format!("cycle {cycle} abandoned (timeout)")
            }
        };
        if let Ok(mut v) = self.view.lock() {
            v.open_alerts = self.alerts.open_alerts().into_iter().cloned().collect();
            v.phase = Some(self.phase.phase(now_ns));
            v.cycles.open = self.open.as_ref().map(|c| c.number);
            v.cycles.open_received = self.open.as_ref().map(|c| c.detections.len());
            v.cycles.schedule = schedule;
            v.cycles.next_due_ns = next_due;
        }
        let mut wake = now_ns + units::NS_PER_MIN;
        let refresh = self
            .thermal
            .is_fitted()
            .then(|| now_ns + (self.thermal.policy().refresh_s * 1e9) as i64);
        for t in [
            self.link.next_event_ns(),
            next_due,
            phase.changes_at_ns,
            refresh,
        ]
        .into_iter()
        .flatten()
        {
            if t > now_ns {
                wake = wake.min(t);
            }
        }
        Ok(wake)
    }

    async fn on_event(&mut self, ev: LinkEvent) -> Result<(), DaemonError> {
        match ev {
            LinkEvent::Spindle(m) => {
                let _ = self.phase.on_spindle(m.t_ns, m.msg.rpm);
                self.thermal.input(Event::Spindle {
                    t_ns: m.t_ns,
                    rpm: m.msg.rpm,
                });
                self.record(rec::TOPIC_SPINDLE, m.t_ns, &m.msg).await?;
                // Every change, so that the stored log replays the heat input exactly.
                if (minute(m.t_ns), m.msg.rpm) != self.last_spindle {
                    self.last_spindle = (minute(m.t_ns), m.msg.rpm);
                    self.buffer_sample(Sample::Spindle {
                        t_ns: m.t_ns,
                        rpm: m.msg.rpm,
                    })
                    .await?;
                }
            }
            LinkEvent::State(m) => {
                let _ = self.phase.on_state(m.t_ns, m.msg.state);
                self.record(rec::TOPIC_STATE, m.t_ns, &m.msg).await?;
            }
            LinkEvent::Temperature(m) => {
                self.record(rec::TOPIC_TEMPERATURE, m.t_ns, &m.msg).await?;
                let now_min = minute(m.t_ns);
                let last = self
                    .last_temp
                    .entry(m.msg.sensor.clone())
                    .or_insert(SensorLog {
                        minute: i64::MIN,
                        stored_minute: i64::MIN,
                        stored_c: f64::NAN,
                    });
                if now_min == last.minute {
                    return Ok(());
                }
                last.minute = now_min;
                // Stored on change, and every few minutes to show the sensor is alive: a
                // steady hall would otherwise fill the database with one value.
                let store = m.msg.celsius != last.stored_c
                    || last.stored_minute.saturating_add(TEMPERATURE_HEARTBEAT_MIN) <= now_min;
                if store {
                    last.stored_c = m.msg.celsius;
                    last.stored_minute = now_min;
                }
                self.thermal.input(Event::Temperature {
                    t_ns: m.t_ns,
                    sensor: m.msg.sensor.clone(),
                    celsius: m.msg.celsius,
                });
                if store {
                    self.buffer_sample(Sample::Temperature {
                        t_ns: m.t_ns,
                        sensor: m.msg.sensor,
                        celsius: m.msg.celsius,
                    })
                    .await?;
                }
            }
            LinkEvent::Truth(t) => {
                self.record(rec::TOPIC_TRUTH, t.t_ns, &t.rounded(1e-4))
                    .await?;
            }
            LinkEvent::Detection(d) => {
                self.record(rec::TOPIC_DETECTION, d.t_ns, &d.msg).await?;
                if let Some(open) = self.open.as_mut().filter(|o| o.number == d.msg.cycle) {
                    open.detections.push(Timed {
                        t_ns: d.t_ns,
                        msg: Ok(d.msg),
                    });
                    let n = open.detections.len();
                    if let Ok(mut v) = self.view.lock() {
                        v.cycles.open_received = Some(n);
                    }
                } else {
                    warn!(machine = %self.id, cycle = d.msg.cycle, "detection of a cycle that is not open: kept in the recording only");
                }
            }
            LinkEvent::CycleDone { cycle, t_ns } => {
                if self.open.as_ref().is_some_and(|o| o.number == cycle) {
                    self.close_cycle(t_ns).await?;
                }
            }
            // Taken by `step`, which feeds the alert engine.
            LinkEvent::ClockSkew { .. } => {}
        }
        Ok(())
    }

    /// Keep a per-minute sample for the next batch; write the batch once it spans
    /// `SAMPLE_BATCH_NS` of machine time (a crash loses at most that much of the per-minute
    /// series; the raw stream is in the recording).
    async fn buffer_sample(&mut self, s: Sample) -> Result<(), DaemonError> {
        let t = s.t_ns();
        let first = self.samples.first().map_or(t, Sample::t_ns);
        self.samples.push(s);
        if t - first >= SAMPLE_BATCH_NS {
            self.flush_samples().await?;
        }
        Ok(())
    }

    async fn flush_samples(&mut self) -> Result<(), DaemonError> {
        self.store.add_samples(&self.id, &self.samples).await?;
        self.samples.clear();
        Ok(())
    }

    async fn record<T: serde::Serialize>(
        &mut self,
        topic: &str,
        t_ns: i64,
        msg: &T,
    ) -> Result<(), DaemonError> {
        let rotation = self.recorder.write(topic, t_ns, self.clock_ns, msg)?;
        if let Some(closed) = rotation.closed {
            self.file_closed(&closed, self.clock_ns).await?;
        }
        if let Some(opened) = rotation.opened {
            self.store
                .mcap_file_opened(&self.id, &opened.display().to_string(), self.clock_ns)
                .await?;
        }
        Ok(())
    }

    /// Between cycles: look at the model's prediction every `refresh_s` of machine time, ask
    /// for a cycle when it is too uncertain, and serve it as a new compensation set when it
    /// moved and passes the checks. Never during a cycle.
    async fn predict_and_serve(&mut self, now_ns: i64) -> Result<(), DaemonError> {
        // This runs at every step: the policy is only copied once a look is due.
        let refresh_ns = (self.thermal.policy().refresh_s * 1e9) as i64;
        if !self.thermal.policy().enabled
            || now_ns < self.last_prediction_ns.saturating_add(refresh_ns)
        {
            return Ok(());
        }
        let policy = self.thermal.policy().clone();
        let Some(preds) = self.thermal.predict(now_ns) else {
            if let Ok(mut v) = self.view.lock() {
                v.thermal.model = Some(self.thermal.view());
            }
            self.last_prediction_ns = now_ns;
            return Ok(());
        };
        self.last_prediction_ns = now_ns;
        self.sched.uncertain = match (
            self.thermal.uncertain(&preds, now_ns),
            &self.sched.uncertain,
        ) {
            (Some(mut u), Some(old)) => {
                u.since_ns = old.since_ns;
                Some(u)
            }
            (u, _) => u,
        };
        let mut note = None;
        // Not during a cycle, and not in the moment a measured set went out.
        if self.open.is_none()
            && let Some(served) = self.served.as_ref().filter(|s| s.valid_from_ns < now_ns)
        {
            let values: BTreeMap<String, f64> =
                preds.iter().map(|p| (p.channel.clone(), p.value)).collect();
            let with_sigma: BTreeMap<String, (f64, f64)> = preds
                .iter()
                .map(|p| (p.channel.clone(), (p.value, p.sigma)))
                .collect();
            let trusted = match (&self.measured, self.thermal.suspect()) {
                (_, Some(why)) => Err(format!(
                    "the model is suspect until it predicts a cycle within its band ({why})"
                )),
                (Some((t_m, m)), None) => self
                    .thermal
                    .check_consistency(&with_sigma, m, *t_m, now_ns, &self.limits)
                    .map_err(|why| format!("inconsistent with the latest measurement: {why}")),
                (None, None) => Ok(()),
            };
            if let Err(why) = trusted {
                if self.last_refusal.as_deref() != Some(&why) {
                    warn!(machine = %self.id, "predicted set not served: {why}");
                }
                note = Some(why.clone());
                self.last_refusal = Some(why);
            } else if policy.moved(served, &values) {
                let about = format!(
                    "the thermal model{}{}",
                    served
                        .cycle
                        .map(|c| format!(" after cycle {c}"))
                        .unwrap_or_default(),
                    LiveModel::fallback_note(&preds)
                );
                match compensation::predicted_set(
                    Some(served),
                    &with_sigma,
                    &self.limits,
                    &policy,
                    now_ns,
                    &about,
                ) {
                    Ok(mut set) => {
                        set.cycle = served.cycle;
                        self.publish_predicted(set, now_ns).await?;
                        self.last_refusal = None;
                    }
                    Err(refused) => {
                        let why = refused.reasons.join("; ");
                        if self.last_refusal.as_deref() != Some(&why) {
                            warn!(machine = %self.id, "predicted set not served: {why}");
                        }
                        note = Some(why.clone());
                        self.last_refusal = Some(why);
                    }
                }
            }
        }
        let model = self.thermal.view();
        let snapshot = self.thermal.snapshot().map(Arc::new);
        if let Ok(mut v) = self.view.lock() {
            v.thermal.prediction = preds;
            v.thermal.prediction_t_ns = Some(now_ns);
            v.thermal.prediction_note = note;
            v.thermal.model = Some(model);
            v.thermal.predictor = snapshot;
        }
        Ok(())
    }

    async fn publish_predicted(
        &mut self,
        set: CompensationSet,
        now_ns: i64,
    ) -> Result<(), DaemonError> {
        self.store
            .insert_compensation(&self.id, &crate::store::NewCompensation::of(&set))
            .await?;
        self.record(
            rec::TOPIC_COMPENSATION,
            now_ns,
            &compensation::compensation_message(&set),
        )
        .await?;
        if let Ok(mut v) = self.view.lock() {
            v.nc_body = NcBody::of(&set);
            v.compensation = Some(set.clone());
        }
        self.served = Some(set);
        Ok(())
    }

    /// Store the detections a cycle received, when it ends (finished, timed out or shut
    /// down): two commits per cycle instead of one per step. A crash during a cycle loses its
    /// detections from the database only; the cycle is abandoned at restart either way.
    async fn store_detections(&mut self, open: &OpenCycle) -> Result<(), DaemonError> {
        let rows: Vec<DetectionRow> = open
            .detections
            .iter()
            .filter_map(|d| {
                let m = d.msg.as_ref().ok()?;
                Some(DetectionRow {
                    t_ns: d.t_ns,
                    step: &m.step,
                    payload: serde_json::to_string(m).ok()?,
                })
            })
            .collect();
        self.store
            .add_detections(&self.id, open.number, &rows)
            .await?;
        Ok(())
    }

    /// Solve, validate, store, serve and alert on the open cycle.
    async fn close_cycle(&mut self, now_ns: i64) -> Result<(), DaemonError> {
        let Some(open) = self.open.take() else {
            return Ok(());
        };
        self.store_detections(&open).await?;
        let _ = self.phase.on_cycle(now_ns, false);
        // The solve takes a core for a moment: on the blocking pool, so that the async
        // threads keep answering the API and the other machines meanwhile.
        let (k, checks, number) = (Arc::clone(&self.k), self.checks.clone(), open.number);
        let solved = tokio::task::spawn_blocking(move || {
            let started = std::time::Instant::now();
            let outcome = process_cycle(&k, number, &open.detections, &checks);
            (outcome, started.elapsed().as_secs_f64())
        })
        .await;
        let (outcome, solve_seconds) = match solved {
            Ok(s) => s,
            Err(e) => {
                // A solver that panicked gives no result: the cycle is abandoned with the
                // reason, and the scheduler retries it like any failed cycle.
                error!(machine = %self.id, cycle = number, error = %e, "the solve failed; cycle abandoned");
                let reason = format!("the solve failed: {e}");
                self.store
                    .abandon_cycle(&self.id, number, now_ns, &reason)
                    .await?;
                self.sched.abandoned(now_ns);
                if let Ok(mut v) = self.view.lock() {
                    v.cycles.abandoned += 1;
                    v.cycles.open = None;
                }
                return Ok(());
            }
        };
        let (result, admitted) = compensation::admit(
            outcome.message(),
            self.served.as_ref(),
            self.measured.as_ref().map(|(_, m)| m),
            &self.limits,
            now_ns,
        );
        if result.status == ResultStatus::Rejected {
            warn!(machine = %self.id, cycle = number, reason = result.reason.as_deref().unwrap_or(""), "cycle rejected");
        }
        // The result and the set it makes go in one transaction, before anything is served.
        let stored = admitted
            .as_ref()
            .map(|a| crate::store::NewCompensation::of(&a.nc));
        self.store
            .close_cycle_with(&self.id, &result, now_ns, stored.as_ref())
            .await?;
        if let Some(a) = admitted {
            self.record(
                rec::TOPIC_COMPENSATION,
                now_ns,
                &compensation::compensation_message(&a.nc),
            )
            .await?;
            info!(machine = %self.id, cycle = number, version = a.nc.version, "compensation updated");
            // Judged on the cycle before it learns from it.
            if let Some(note) = self
                .thermal
                .judge(&a.measured, result.t_ns, now_ns, &self.limits)
            {
                warn!(machine = %self.id, "thermal model: {note}");
            }
            if let (Some(e), Some(sg)) = (&result.errors, &result.sigma)
                && let Some(note) = self.thermal.observe(result.t_ns, e, sg)
            {
                info!(machine = %self.id, "thermal model: {note}");
            }
            self.served = Some(a.nc);
            self.measured = Some((result.t_ns, a.measured));
        }

        self.record(rec::TOPIC_RESULT, now_ns, &result).await?;
        self.recorder.flush()?;
        self.flush_samples().await?;
        self.sched
            .finished(result.status == ResultStatus::Ok, now_ns);
        let events = self.alerts.evaluate(&Input::from(&result), now_ns);
        self.raise(events).await?;
        if let Ok(mut v) = self.view.lock() {
            v.cycles.last = Some(number);
            if v.compensation.as_ref().map(|c| c.version) != self.served.as_ref().map(|c| c.version)
            {
                v.nc_body = self.served.as_ref().and_then(NcBody::of);
            }
            v.compensation = self.served.clone();
            v.open_alerts = self.alerts.open_alerts().into_iter().cloned().collect();
            v.cycles.solve_seconds_sum += solve_seconds;
            if result.status == ResultStatus::Ok {
                v.cycles.ok += 1;
            } else {
                v.cycles.rejected += 1;
            }
        }
        Ok(())
    }

    /// Store, log and notify alert events.
    async fn raise(&mut self, events: Vec<AlertEvent>) -> Result<(), DaemonError> {
        for ev in events {
            warn!(machine = %self.id, alert = ev.id, rule = %ev.rule, kind = ?ev.kind, "{}", ev.message);
            self.store
                .add_alert_event(
                    &self.id,
                    &NewAlertEvent {
                        alert: ev.id as i64,
                        t_ns: ev.t_ns,
                        kind: ev.kind.into(),
                        rule: &ev.rule,
                        severity: Some(ev.severity.into()),
                        message: &ev.message,
                        value: Some(ev.value),
                    },
                )
                .await?;
            self.notifier.notify(&self.id, &ev);
            self.alert_log.push(ev);
        }
        Ok(())
    }

    /// Close the recording cleanly (shutdown).
    pub async fn shutdown(&mut self, now_ns: i64) -> Result<(), DaemonError> {
        self.clock_ns = now_ns;
        self.flush_samples().await?;
        if let Some(open) = self.open.take() {
            self.link.abort_cycle(open.number, now_ns);
            self.store_detections(&open).await?;
            self.store
                .abandon_cycle(
                    &self.id,
                    open.number,
                    now_ns,
                    "the service shut down during the cycle",
                )
                .await?;
        }
        if let Some(closed) = self.recorder.close()? {
            self.file_closed(&closed, now_ns).await?;
        }
        Ok(())
    }

    async fn file_closed(
        &mut self,
        f: &crate::recorder::ClosedFile,
        now_ns: i64,
    ) -> Result<(), DaemonError> {
        self.store
            .mcap_file_closed(
                &self.id,
                &f.partial.display().to_string(),
                &f.path.display().to_string(),
                now_ns,
                FileStatus::Closed,
                f.messages as i64,
            )
            .await?;
        Ok(())
    }

    pub fn served(&self) -> Option<&CompensationSet> {
        self.served.as_ref()
    }

    pub fn store(&self) -> &Store {
        &self.store
    }
}
