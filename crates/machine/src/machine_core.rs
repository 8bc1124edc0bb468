//! One machine's decisions as a state machine without I/O: an [`Input`] (something the
//! machine reported, an operator's request, the answer to an effect, the end of a step) goes
//! in with the time, and [`Effect`]s come out, in the order they must happen: record this,
//! store that, ask the machine for a cycle, solve a cycle, raise an alert, publish the view.
//!
//! The service's executor runs the effects (SQLite, MCAP, the link, the blocking pool) and
//! feeds the answers of the two effects that have one back in: [`Effect::RequestCycle`] is
//! answered by [`Input::CycleRequested`], [`Effect::Solve`] by [`Input::Solved`]. Nothing here
//! awaits, reads a clock or touches storage, so the unit tests drive a machine's day with
//! plain calls.
//!
//! Invariants the core keeps:
//! - a compensation set is served (the view's `compensation`) only after the effect that
//!   stores it, so an executor that runs the effects in order never serves an unstored set;
//! - a cycle result is admitted only through [`compensation::admit`], a predicted set only
//!   through [`compensation::predicted_set`] and the model's consistency check;
//! - cycle numbers rise by one per started cycle from the number the store gave at start-up.

use std::collections::BTreeMap;
use std::sync::Arc;

use driftwatch_core::cycle::{CycleChecks, CycleOutcome, process_cycle};
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::recording::{
    CycleResultMsg, DetectionIssue, DetectionMsg, ResultStatus, SpindleMsg, StateMsg,
    TemperatureMsg, Timed,
};
use driftwatch_core::units;
use driftwatch_thermal::model::{Event, Prediction, Predictor};
use thiserror::Error;

use crate::alerts::{Alert, AlertEngine, AlertEvent, AlertState, ClockInput, LoggedAlerts, Rule};
use crate::compensation::{self, CompensationSet, PredictionPolicy, ValidationLimits};
use crate::link_event::{LinkEvent, RawJson};
use crate::live_model::{LiveModel, ModelView};
use crate::nc_offsets::NcLayout;
use crate::phase::{PhaseConfig, PhaseError, PhaseInfo, PhaseTracker};
use crate::scheduler::{Decision, Reason, SchedulePolicy, SchedulerState, decide};

/// Machine time the per-minute samples are held before they are stored together.
pub const SAMPLE_BATCH_NS: i64 = 10 * units::NS_PER_MIN;

/// A temperature sample is stored at least this often (minutes), and whenever it changes.
pub const TEMPERATURE_HEARTBEAT_MIN: i64 = 10;

#[derive(Debug, Error)]
pub enum CoreError {
    #[error(transparent)]
    Phase(#[from] PhaseError),
    #[error("alert rules: {0}")]
    Alerts(String),
    #[error("the stored linear geometry cannot be taken: {0}")]
    Geometry(String),
}

/// What the machine core is told.
#[derive(Debug, Clone)]
pub enum Input {
    /// What the machine's link reported, as the link reported it.
    Link(LinkEvent),
    /// An operator asks for a cycle.
    Request {
        by: String,
    },
    /// A verification against a reference instrument was stored: its alert rules run on it.
    Verification(Box<crate::verification::Verification>),
    /// A linear-axis geometry version was stored: the solves from now on start from it;
    /// `label` names it in their results.
    Geometry {
        label: String,
        geometry: Box<driftwatch_core::linear_axes::LinearGeometry>,
    },
    /// An operator acknowledges an alert.
    Ack {
        alert: u64,
        by: String,
    },
    /// The end of a step: look at the prediction, decide on a cycle, publish the view.
    Tick,
    /// The machine's answer to [`Effect::RequestCycle`].
    CycleRequested {
        number: i64,
        result: Result<(), String>,
    },
    /// The answer to [`Effect::Solve`]: the outcome, or why there is none (the solver
    /// failed), and the seconds the solve took.
    Solved {
        number: i64,
        outcome: Box<Result<CycleOutcome, String>>,
        seconds: f64,
    },
    /// The service stops: give up the open cycle, store what is held.
    /// The executor's steps began to fail (`failing`, with the failure and the count of
    /// failed steps) or succeed again: the loop's health alert follows.
    LoopFault {
        failing: bool,
        failed_steps: u64,
        message: String,
    },
    Shutdown,
}

/// A message for the machine's recording.
#[derive(Debug, Clone)]
pub enum Record {
    Spindle(Timed<SpindleMsg>),
    State(Timed<StateMsg>),
    Temperature(Timed<TemperatureMsg>),
    Detection(Timed<DetectionMsg>),
    Compensation {
        t_ns: i64,
        set: CompensationSet,
    },
    Result {
        t_ns: i64,
        result: CycleResultMsg,
    },
    /// A link's message recorded as it is under its own topic.
    Raw {
        topic: &'static str,
        t_ns: i64,
        json: RawJson,
    },
}

/// A per-minute sample for the time series.
#[derive(Debug, Clone, PartialEq)]
pub enum Sample {
    Spindle {
        t_ns: i64,
        rpm: f64,
    },
    Temperature {
        t_ns: i64,
        sensor: String,
        celsius: f64,
    },
}

/// A stored sample is an input of the thermal model's timeline.
impl From<Sample> for Event {
    fn from(s: Sample) -> Event {
        match s {
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
        }
    }
}

impl Sample {
    pub fn t_ns(&self) -> i64 {
        match self {
            Sample::Spindle { t_ns, .. } | Sample::Temperature { t_ns, .. } => *t_ns,
        }
    }
}

/// A detection as it is stored with its cycle.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredDetection {
    pub t_ns: i64,
    pub step: String,
    /// The detection message as JSON.
    pub payload: String,
}

pub type Entry = Timed<Result<DetectionMsg, DetectionIssue>>;

/// A cycle to solve: pure work, run wherever the executor likes (a blocking pool).
#[derive(Debug, Clone)]
pub struct SolveJob {
    pub number: i64,
    k: Arc<Kinematics>,
    checks: CycleChecks,
    detections: Vec<Entry>,
}

impl SolveJob {
    pub fn run(&self) -> CycleOutcome {
        process_cycle(&self.k, self.number, &self.detections, &self.checks)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Level {
    Info,
    Warn,
    Error,
}

/// What the core asks the executor to do, in order.
#[derive(Debug, Clone)]
pub enum Effect {
    Record(Box<Record>),
    /// Write the recording's buffered messages out (the end of a cycle).
    FlushRecording,
    StoreSamples(Vec<Sample>),
    /// Ask the machine for cycle `number`; answered by [`Input::CycleRequested`].
    RequestCycle {
        number: i64,
    },
    AbortCycle {
        number: i64,
    },
    OpenCycle {
        number: i64,
        t_ns: i64,
        trigger: String,
        attempt: i64,
    },
    StoreDetections {
        number: i64,
        rows: Vec<StoredDetection>,
    },
    /// Solve a cycle; answered by [`Input::Solved`].
    Solve(Box<SolveJob>),
    AbandonCycle {
        number: i64,
        t_ns: i64,
        reason: String,
    },
    /// Store a cycle's result and, when it was admitted, the set it makes: together, before
    /// the set is served.
    CloseCycle {
        result: Box<CycleResultMsg>,
        t_ns: i64,
        set: Option<Box<CompensationSet>>,
    },
    /// Store a predicted set (before it is served).
    StoreSet(Box<CompensationSet>),
    /// Keep the alert engine's state (after its events): a restart goes on from it.
    StoreAlertState {
        t_ns: i64,
        state: Box<AlertState>,
    },
    Alert(Box<AlertEvent>),
    Acknowledged {
        alert: u64,
        by: String,
        t_ns: i64,
    },
    /// The view changed: show [`MachineCore::view`] to the API.
    PublishView,
    Log(Level, String),
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
    /// Shared, and rebuilt only when the model changed: the view is copied at every look at
    /// the prediction (once a machine minute), the model's part seldom changes.
    pub model: Option<Arc<ModelView>>,
    pub prediction: Vec<Prediction>,
    pub prediction_t_ns: Option<i64>,
    /// Why the last prediction was not served, if it was not.
    pub prediction_note: Option<String>,
    pub predictor: Option<Arc<Predictor>>,
    /// Counts the changes of this view, so that a reader copies it only when it changed.
    pub revision: u64,
}

/// What the core shows of the machine.
#[derive(Debug, Clone, Default)]
pub struct View {
    pub phase: Option<PhaseInfo>,
    pub cycles: CycleView,
    /// The set the NC reads: the last validated one.
    pub compensation: Option<CompensationSet>,
    pub open_alerts: Vec<Alert>,
    /// The threshold rules with the reference each measures from, for charts that draw them.
    pub thresholds: Vec<AlertThreshold>,
    /// Counts the changes of `open_alerts` and `thresholds`, so that a reader copies them only
    /// when they changed (the loop publishes its view at every step).
    pub alerts_revision: u64,
    pub thermal: ThermalView,
}

/// A threshold alert rule as a chart draws it: `|value - reference|` above `limit` raises,
/// below `clear` resolves.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct AlertThreshold {
    /// The rule's name in alerts, `threshold:EZ0B`.
    pub rule: String,
    pub error: String,
    /// um, or urad for an angular error.
    pub limit: f64,
    /// Same unit: back within it resolves.
    pub clear: f64,
    /// The value the distance is measured from: the configured one, else the first validated
    /// value of the error the alert rules saw (absent before it).
    pub reference: Option<f64>,
    /// Whether `reference` is configured (else the first validated value).
    pub reference_configured: bool,
}

/// The threshold rules of `alerts` with their references as they stand.
fn thresholds(alerts: &AlertEngine) -> Vec<AlertThreshold> {
    alerts
        .rules()
        .iter()
        .filter_map(|r| match r {
            Rule::Threshold {
                error,
                limit,
                clear,
                reference,
            } => Some(AlertThreshold {
                rule: r.name(),
                error: error.clone(),
                limit: *limit,
                clear: *clear,
                reference: alerts.reference(error),
                reference_configured: reference.is_some(),
            }),
            _ => None,
        })
        .collect()
}

/// The settings of one machine's decisions.
#[derive(Debug, Clone)]
pub struct Settings {
    pub phase: PhaseConfig,
    pub schedule: SchedulePolicy,
    pub validation: ValidationLimits,
    pub alert_rules: Vec<Rule>,
    pub prediction: PredictionPolicy,
    /// A thermal model fitted elsewhere to start from (the machine's `thermal_model`).
    pub initial_model: Option<Arc<driftwatch_thermal::model::ThermalModel>>,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            phase: PhaseConfig::default(),
            schedule: SchedulePolicy::default(),
            validation: ValidationLimits::default(),
            alert_rules: crate::alerts::default_rules(),
            prediction: Default::default(),
            initial_model: None,
        }
    }
}

/// What the store remembers of the machine at start-up.
#[derive(Debug, Clone, Default)]
pub struct Restored {
    /// Start of the last cycle and time of the last good result.
    pub last_start_ns: Option<i64>,
    pub last_good_ns: Option<i64>,
    /// The stored inputs and validated results of the thermal model's window, in time order
    /// (inputs before observations at the same time); read only when
    /// [`Restored::takes_history`] says so.
    pub history: Vec<Event>,
    /// The served set, and the last measured one with its cycle's reference time.
    pub served: Option<CompensationSet>,
    pub measured: Option<(i64, CompensationSet)>,
    pub last_closed: Option<i64>,
    /// The number the next cycle takes.
    pub next_cycle: i64,
    /// The alert engine's kept state (none: never kept) and what the alert log holds.
    pub alerts: Option<AlertState>,
    pub logged_alerts: LoggedAlerts,
    /// The stored spindle samples and cycle spans of the phase's window
    /// ([`Restored::phase_window_ns`]), for the phase to go on from.
    pub phase_history: Vec<crate::phase::PastEvent>,
}

impl Restored {
    /// How far back the phase needs the machine's history: past the longest of its
    /// thresholds (a run longer than that is steady, a stop longer is cold either way).
    pub fn phase_window_ns(phase: &PhaseConfig) -> i64 {
        let longest = phase
            .warmup_min
            .max(phase.cold_after_min)
            .max(phase.cooling_min);
        units::min_to_ns(longest + 1.0)
    }

    /// The window of stored events the thermal model comes back from, if the store is to be
    /// taken at all: a store whose cycles lie ahead of the clock (a simulated day started
    /// again from its morning) is not.
    pub fn history_window(
        last_start_ns: Option<i64>,
        policy: &PredictionPolicy,
        now_ns: i64,
    ) -> Option<(i64, i64)> {
        (policy.enabled && last_start_ns.is_some_and(|t| t <= now_ns))
            .then(|| (now_ns - units::h_to_ns(policy.history_days * 24.0), now_ns))
    }
}

struct OpenCycle {
    number: i64,
    detections: Vec<Entry>,
}

/// What the core remembers of a temperature sensor: the minute it last took a reading into
/// the model, and the last stored sample.
struct SensorLog {
    minute: i64,
    stored_minute: i64,
    stored_c: f64,
}

fn minute(t_ns: i64) -> i64 {
    t_ns.div_euclid(units::NS_PER_MIN)
}

/// One machine's decisions.
pub struct MachineCore {
    k: Arc<Kinematics>,
    /// The errors its sets hold and the NC offsets they make.
    layout: NcLayout,
    checks: CycleChecks,
    phase: PhaseTracker,
    policy: SchedulePolicy,
    sched: SchedulerState,
    /// The tool tip's displacement per unit of each error at the policy's reference pose.
    tip_sensitivity: BTreeMap<String, [f64; 3]>,
    limits: ValidationLimits,
    alerts: AlertEngine,
    /// The alert state the store was last asked to keep: a change emits it again.
    kept_alerts: AlertState,
    /// The alert engine's count of edits when its state was last compared with `kept_alerts`
    /// (none: never, so the first input compares).
    kept_alerts_edits: Option<u64>,
    thermal: LiveModel,
    open: Option<OpenCycle>,
    /// A cycle asked of the machine, waiting for its answer: number and trigger.
    requested: Option<(i64, String)>,
    /// A finished cycle being solved: number and the time it finished.
    solving: Option<(i64, i64)>,
    next_cycle: i64,
    served: Option<CompensationSet>,
    /// The last measured set with its cycle's reference time: the next cycle's step and the
    /// predictions are checked against it (the served set may be predicted, or ramped).
    measured: Option<(i64, CompensationSet)>,
    /// Minute and speed of the last stored spindle sample (every change is stored, and one
    /// sample a minute besides), and what is known of each temperature sensor.
    last_spindle: (i64, f64),
    /// The time the last spindle sample was stored under, ns.
    last_spindle_ns: i64,
    last_temp: BTreeMap<String, SensorLog>,
    /// Per-minute samples not yet stored.
    samples: Vec<Sample>,
    /// Machine time of the last look at the prediction, and the last refusal said.
    last_prediction_ns: i64,
    last_refusal: Option<String>,
    /// Times the last step said the core wants to be called again.
    next_due_ns: Option<i64>,
    phase_changes_ns: Option<i64>,
    /// The link's clock-skew refusals since the last step's end, and the last worst skew.
    skew: (u64, i64),
    /// The [`LiveModel::revision`] that `view.thermal.model` shows.
    model_shown: Option<u64>,
    /// The scheduler's reason to wait that `view.cycles.schedule` says (`None`: it says
    /// something else): the same reason is not formatted again at every step.
    wait_shown: Option<Reason>,
    view: View,
}

impl MachineCore {
    /// A machine's core as the store left it; the effects are what it has to say at start
    /// (log lines).
    pub fn new(
        k: Arc<Kinematics>,
        checks: CycleChecks,
        steps_per_cycle: usize,
        settings: &Settings,
        mut restored: Restored,
        now_ns: i64,
    ) -> Result<(Self, Vec<Effect>), CoreError> {
        let mut out = Vec::new();
        let mut thermal = match &settings.initial_model {
            Some(m) => {
                let live = LiveModel::with_initial(settings.prediction.clone(), m.clone());
                out.push(Effect::Log(
                    Level::Info,
                    format!("thermal model: {}", live.view().message),
                ));
                live
            }
            None => LiveModel::new(settings.prediction.clone()),
        };
        // The scheduler remembers the last cycle and the last good result across a restart,
        // so that a restart does not by itself cause a cycle.
        let mut sched = SchedulerState::default();
        if restored.last_start_ns.is_some_and(|t| t <= now_ns) {
            if thermal.policy().enabled
                && let Some(note) = thermal.restore(&restored.history)
            {
                out.push(Effect::Log(
                    Level::Info,
                    format!("thermal model restored from the store: {note}"),
                ));
            }
            sched.last_cycle_start_ns = restored.last_start_ns;
            sched.last_good_ns = restored.last_good_ns.filter(|t| *t <= now_ns);
        } else if restored.last_start_ns.is_some() {
            out.push(Effect::Log(
                Level::Info,
                "the stored cycles lie ahead of the clock (a simulated day started again): the scheduler starts afresh".into(),
            ));
        }
        let mut phase = PhaseTracker::new(settings.phase.clone())?;
        phase.replay(std::mem::take(&mut restored.phase_history), now_ns);
        // Open alerts, acknowledgements and ids go on from what the store kept.
        let kept_alerts = restored.alerts.clone().unwrap_or_default();
        let (alerts, resolved) = AlertEngine::resume(
            settings.alert_rules.clone(),
            restored.alerts.take(),
            &restored.logged_alerts,
            now_ns,
        )
        .map_err(|e| CoreError::Alerts(e.to_string()))?;
        raise(resolved, &mut out);
        // A loop-fault alert kept open by a stop is over: this start's loop has not failed.
        let mut alerts = alerts;
        raise(
            alerts.loop_fault(false, 0, "the service restarted", now_ns),
            &mut out,
        );
        // The NC offsets of the stored sets are this machine's, whatever the store kept.
        let layout = NcLayout::of(&k);
        let sets = restored
            .served
            .iter_mut()
            .chain(restored.measured.iter_mut().map(|(_, m)| m));
        for set in sets {
            set.offsets = layout.offsets(&set.errors);
        }
        let view = View {
            compensation: restored.served.clone(),
            open_alerts: alerts.open_alerts().into_iter().cloned().collect(),
            thresholds: thresholds(&alerts),
            cycles: CycleView {
                last: restored.last_closed,
                steps_per_cycle,
                ..Default::default()
            },
            ..Default::default()
        };
        let tip_sensitivity = crate::tool_tip::sensitivity(
            &k,
            settings.schedule.tip_point_mm,
            settings.schedule.tip_pose_deg,
        );
        let core = MachineCore {
            k,
            layout,
            checks,
            phase,
            tip_sensitivity,
            policy: settings.schedule.clone(),
            sched,
            limits: settings.validation.clone(),
            alerts,
            kept_alerts,
            kept_alerts_edits: None,
            thermal,
            open: None,
            requested: None,
            solving: None,
            next_cycle: restored.next_cycle.max(1),
            served: restored.served,
            measured: restored.measured,
            last_spindle: (i64::MIN, f64::NAN),
            last_spindle_ns: i64::MIN,
            last_temp: BTreeMap::new(),
            samples: Vec::new(),
            last_prediction_ns: i64::MIN,
            last_refusal: None,
            next_due_ns: None,
            phase_changes_ns: None,
            skew: (0, 0),
            model_shown: None,
            wait_shown: None,
            view,
        };
        Ok((core, out))
    }

    pub fn view(&self) -> &View {
        &self.view
    }

    pub fn served(&self) -> Option<&CompensationSet> {
        self.served.as_ref()
    }

    pub fn kinematics(&self) -> &Kinematics {
        &self.k
    }

    /// The open cycle's number, if one runs.
    pub fn open_cycle(&self) -> Option<i64> {
        self.open.as_ref().map(|o| o.number)
    }

    /// When the core wants its next [`Input::Tick`] at the latest, after a step at `now_ns`
    /// (a minute at most; earlier when a cycle falls due, the phase changes or the model's
    /// prediction is to be looked at again).
    pub fn wake_after(&self, now_ns: i64) -> i64 {
        let refresh = self
            .thermal
            .is_fitted()
            .then(|| now_ns + (self.thermal.policy().refresh_s * 1e9) as i64);
        [self.next_due_ns, self.phase_changes_ns, refresh]
            .into_iter()
            .flatten()
            .filter(|t| *t > now_ns)
            .fold(now_ns + units::NS_PER_MIN, i64::min)
    }

    /// Take one input at `now_ns` (the service clock of the step); the effects come out in
    /// the order they must run.
    pub fn handle(&mut self, input: Input, now_ns: i64) -> Vec<Effect> {
        let mut out = Vec::new();
        match input {
            Input::Link(ev) => self.on_link(ev, &mut out),
            Input::Request { by } => self.sched.request(by, now_ns),
            Input::Verification(v) => self.on_verification(&v, now_ns, &mut out),
            Input::Geometry { label, geometry } => {
                match (*self.k).clone().with_geometry(&geometry, &label) {
                    Ok(k) => {
                        self.tip_sensitivity = crate::tool_tip::sensitivity(
                            &k,
                            self.policy.tip_point_mm,
                            self.policy.tip_pose_deg,
                        );
                        self.k = Arc::new(k);
                        out.push(Effect::Log(
                            Level::Info,
                            format!(
                                "linear geometry {label}: the solves from now on start from it"
                            ),
                        ));
                    }
                    // The API checks a geometry before it stores it; one that fails here
                    // is refused and the solves keep the geometry they had.
                    Err(e) => out.push(Effect::Log(
                        Level::Error,
                        format!("linear geometry {label} refused, the previous one kept: {e}"),
                    )),
                }
            }
            Input::Ack { alert, by } => match self.alerts.ack(alert, &by, now_ns) {
                Ok(false) => {}
                Ok(true) => {
                    out.push(Effect::Log(
                        Level::Info,
                        format!("alert {alert} acknowledged by {by}"),
                    ));
                    out.push(Effect::Acknowledged {
                        alert,
                        by,
                        t_ns: now_ns,
                    });
                }
                Err(e) => out.push(Effect::Log(
                    Level::Warn,
                    format!("acknowledgement of alert {alert} refused: {e}"),
                )),
            },
            Input::Tick => self.tick(now_ns, &mut out),
            Input::CycleRequested { number, result } => {
                self.cycle_requested(number, result, now_ns, &mut out)
            }
            Input::Solved {
                number,
                outcome,
                seconds,
            } => self.solved(number, *outcome, seconds, &mut out),
            Input::Shutdown => self.shutdown(now_ns, &mut out),
            Input::LoopFault {
                failing,
                failed_steps,
                message,
            } => {
                let events = self
                    .alerts
                    .loop_fault(failing, failed_steps, &message, now_ns);
                if !events.is_empty() {
                    raise(events, &mut out);
                    self.show_open_alerts();
                    out.push(Effect::PublishView);
                }
            }
        }
        // After the events that changed it, so that the store keeps the state they led to.
        // Compared only when the engine handed its state out to be changed since the last look.
        let edits = self.alerts.edits();
        if self.kept_alerts_edits != Some(edits) {
            self.kept_alerts_edits = Some(edits);
            if self.alerts.state() != &self.kept_alerts {
                self.kept_alerts = self.alerts.state().clone();
                out.push(Effect::StoreAlertState {
                    t_ns: now_ns,
                    state: Box::new(self.kept_alerts.clone()),
                });
            }
        }
        out
    }

    /// A stored verification: logged, and its alert rules run on it (the view shows the
    /// alert at once).
    fn on_verification(
        &mut self,
        v: &crate::verification::Verification,
        now_ns: i64,
        out: &mut Vec<Effect>,
    ) {
        let level = if v.exceeds_any {
            Level::Warn
        } else {
            Level::Info
        };
        out.push(Effect::Log(level, format!("verification: {}", v.summary())));
        let input = crate::alerts::Input::Verification(v.into());
        let events = self.alerts.evaluate(&input, now_ns);
        if !events.is_empty() {
            raise(events, out);
            self.show_open_alerts();
            out.push(Effect::PublishView);
        }
    }

    fn on_spindle(&mut self, m: Timed<SpindleMsg>, out: &mut Vec<Effect>) {
        let (t_ns, rpm) = (m.t_ns, m.msg.rpm);
        let _ = self.phase.on_spindle(t_ns, rpm);
        self.thermal.input(Event::Spindle { t_ns, rpm });
        out.push(Effect::Record(Box::new(Record::Spindle(m))));
        // Every change, so that the stored log replays the heat input exactly.
        if (minute(t_ns), rpm) != self.last_spindle {
            self.last_spindle = (minute(t_ns), rpm);
            // The store keeps one speed per instant: a change at the instant of the last one
            // (a stop and a cycle's spin at the same ns) is stored a nanosecond later, so that
            // neither is lost and the stored log replays the run and its stop.
            let t_ns = t_ns.max(self.last_spindle_ns.saturating_add(1));
            self.last_spindle_ns = t_ns;
            self.buffer_sample(Sample::Spindle { t_ns, rpm }, out);
        }
    }

    fn on_temperature(&mut self, m: Timed<TemperatureMsg>, out: &mut Vec<Effect>) {
        let (t_ns, sensor, celsius) = (m.t_ns, m.msg.sensor.clone(), m.msg.celsius);
        out.push(Effect::Record(Box::new(Record::Temperature(m))));
        let now_min = minute(t_ns);
        let last = self.last_temp.entry(sensor.clone()).or_insert(SensorLog {
            minute: i64::MIN,
            stored_minute: i64::MIN,
            stored_c: f64::NAN,
        });
        if now_min == last.minute {
            return;
        }
        last.minute = now_min;
        // Stored on change, and every few minutes to show the sensor is alive: a steady
        // hall would otherwise fill the database with one value.
        let store = celsius != last.stored_c
            || last.stored_minute.saturating_add(TEMPERATURE_HEARTBEAT_MIN) <= now_min;
        if store {
            last.stored_c = celsius;
            last.stored_minute = now_min;
        }
        self.thermal.input(Event::Temperature {
            t_ns,
            sensor: sensor.clone(),
            celsius,
        });
        if store {
            self.buffer_sample(
                Sample::Temperature {
                    t_ns,
                    sensor,
                    celsius,
                },
                out,
            );
        }
    }

    fn on_link(&mut self, ev: LinkEvent, out: &mut Vec<Effect>) {
        match ev {
            LinkEvent::Spindle(m) => self.on_spindle(m, out),
            LinkEvent::State(m) => {
                let _ = self.phase.on_state(m.t_ns, m.msg.state);
                out.push(Effect::Record(Box::new(Record::State(m))));
            }
            LinkEvent::Temperature(m) => self.on_temperature(m, out),
            LinkEvent::Detection(d) => self.on_detection(d, out),
            LinkEvent::CycleDone { cycle, t_ns } => {
                if self.open.as_ref().is_some_and(|o| o.number == cycle) {
                    self.finish_cycle(t_ns, out);
                }
            }
            LinkEvent::Record { topic, t_ns, json } => {
                out.push(Effect::Record(Box::new(Record::Raw { topic, t_ns, json })))
            }
            // Summed until the end of the step, where the clock alert looks at them.
            LinkEvent::ClockSkew {
                refused,
                worst_skew_ns,
                ..
            } => self.skew = (self.skew.0 + refused, worst_skew_ns),
        }
    }

    /// The link's clock-skew refusals since the last step, judged at every step's end, also
    /// with none, so that a quiet clock lets its alert resolve.
    fn judge_clock(&mut self, now_ns: i64, out: &mut Vec<Effect>) {
        let (refused, worst_skew_ns) = std::mem::take(&mut self.skew);
        let skew = ClockInput {
            t_ns: now_ns,
            refused,
            worst_skew_s: worst_skew_ns as f64 / 1e9,
        };
        let events = self
            .alerts
            .evaluate(&crate::alerts::Input::Clock(skew), now_ns);
        raise(events, out);
    }

    fn on_detection(&mut self, d: Timed<DetectionMsg>, out: &mut Vec<Effect>) {
        out.push(Effect::Record(Box::new(Record::Detection(d.clone()))));
        if let Some(open) = self.open.as_mut().filter(|o| o.number == d.msg.cycle) {
            open.detections.push(Timed {
                t_ns: d.t_ns,
                msg: Ok(d.msg),
            });
            self.view.cycles.open_received = Some(open.detections.len());
        } else {
            out.push(Effect::Log(
                Level::Warn,
                format!(
                    "detection of cycle {}, which is not open: kept in the recording only",
                    d.msg.cycle
                ),
            ));
        }
    }

    /// Keep a per-minute sample for the next batch; store the batch once it spans
    /// [`SAMPLE_BATCH_NS`] of machine time (a crash loses at most that much of the
    /// per-minute series; the raw stream is in the recording).
    fn buffer_sample(&mut self, s: Sample, out: &mut Vec<Effect>) {
        let t = s.t_ns();
        let first = self.samples.first().map_or(t, Sample::t_ns);
        self.samples.push(s);
        if t - first >= SAMPLE_BATCH_NS {
            self.flush_samples(out);
        }
    }

    fn flush_samples(&mut self, out: &mut Vec<Effect>) {
        if !self.samples.is_empty() {
            out.push(Effect::StoreSamples(std::mem::take(&mut self.samples)));
        }
    }

    /// The end of a step: the prediction, the scheduler's decision, the view.
    fn tick(&mut self, now_ns: i64, out: &mut Vec<Effect>) {
        self.judge_clock(now_ns, out);
        self.predict_and_serve(now_ns, out);
        let phase = self.phase.phase(now_ns);
        self.phase_changes_ns = phase.changes_at_ns;
        // A step while a cycle is asked for or solved changes nothing of it.
        if self.requested.is_some() || self.solving.is_some() {
            return;
        }
        let decision = decide(&self.policy, &phase, &self.sched, now_ns);
        self.next_due_ns = None;
        match decision {
            Decision::Start { reason } => {
                let number = self.next_cycle;
                self.requested = Some((number, reason.to_string()));
                // The view goes out with the machine's answer.
                out.push(Effect::RequestCycle { number });
                return;
            }
            Decision::Wait {
                next_due_ns,
                reason,
            } => {
                self.next_due_ns = next_due_ns;
                self.show_wait(reason);
            }
            Decision::Abandon { cycle, retry } => {
                out.push(Effect::Log(
                    Level::Warn,
                    format!(
                        "cycle {cycle} timed out, abandoned{}",
                        if retry { "; a retry is due" } else { "" }
                    ),
                ));
                out.push(Effect::AbortCycle { number: cycle });
                if let Some(open) = self.open.take() {
                    out.push(store_detections(&open));
                }
                out.push(Effect::AbandonCycle {
                    number: cycle,
                    t_ns: now_ns,
                    reason: "timed out before every step arrived".into(),
                });
                self.sched.abandoned(now_ns);
                let _ = self.phase.on_cycle(now_ns, false);
                self.view.cycles.abandoned += 1;
                self.show_schedule(format!("cycle {cycle} abandoned (timeout)"));
            }
        }
        self.publish(now_ns, out);
    }

    /// The view's schedule line: the scheduler's reason to wait, formatted only when it is not
    /// the one shown already (the loop asks the scheduler at every step).
    fn show_wait(&mut self, reason: Reason) {
        if self.wait_shown.as_ref() != Some(&reason) {
            self.view.cycles.schedule = reason.to_string();
            self.wait_shown = Some(reason);
        }
    }

    /// Any other schedule line (a cycle started, refused or abandoned).
    fn show_schedule(&mut self, line: String) {
        self.view.cycles.schedule = line;
        self.wait_shown = None;
    }

    /// The open alerts as they stand in the view, its revision moved if they changed.
    fn show_open_alerts(&mut self) {
        let open = self.alerts.open_alerts();
        let v = &mut self.view;
        if !open.iter().copied().eq(v.open_alerts.iter()) {
            v.open_alerts = open.into_iter().cloned().collect();
            v.alerts_revision += 1;
        }
    }

    fn publish(&mut self, now_ns: i64, out: &mut Vec<Effect>) {
        self.show_open_alerts();
        let v = &mut self.view;
        v.phase = Some(self.phase.phase(now_ns));
        v.cycles.open = self.open.as_ref().map(|c| c.number);
        v.cycles.open_received = self.open.as_ref().map(|c| c.detections.len());
        v.cycles.next_due_ns = self.next_due_ns;
        out.push(Effect::PublishView);
    }

    fn cycle_requested(
        &mut self,
        number: i64,
        result: Result<(), String>,
        now_ns: i64,
        out: &mut Vec<Effect>,
    ) {
        let Some((asked, reason)) = self.requested.take() else {
            return;
        };
        if asked != number {
            self.requested = Some((asked, reason));
            return;
        }
        let schedule = match result {
            Ok(()) => {
                out.push(Effect::Log(
                    Level::Info,
                    format!("cycle {number} started: {reason}"),
                ));
                out.push(Effect::OpenCycle {
                    number,
                    t_ns: now_ns,
                    trigger: reason.clone(),
                    attempt: i64::from(self.sched.failures) + 1,
                });
                self.sched.started(number, now_ns);
                let _ = self.phase.on_cycle(now_ns, true);
                self.next_cycle = number + 1;
                self.open = Some(OpenCycle {
                    number,
                    detections: Vec::new(),
                });
                format!("cycle {number} started: {reason}")
            }
            Err(e) => format!("a cycle is due ({reason}) but the machine refused: {e}"),
        };
        self.show_schedule(schedule);
        self.publish(now_ns, out);
    }

    /// The machine finished the open cycle at `t_ns`: store its detections and solve it.
    fn finish_cycle(&mut self, t_ns: i64, out: &mut Vec<Effect>) {
        let Some(open) = self.open.take() else {
            return;
        };
        out.push(store_detections(&open));
        let _ = self.phase.on_cycle(t_ns, false);
        self.solving = Some((open.number, t_ns));
        out.push(Effect::Solve(Box::new(SolveJob {
            number: open.number,
            k: Arc::clone(&self.k),
            checks: self.checks.clone(),
            detections: open.detections,
        })));
    }

    /// Validate, store, serve and alert on a solved cycle.
    fn solved(
        &mut self,
        number: i64,
        outcome: Result<CycleOutcome, String>,
        seconds: f64,
        out: &mut Vec<Effect>,
    ) {
        let Some((solving, now_ns)) = self.solving.take() else {
            return;
        };
        if solving != number {
            self.solving = Some((solving, now_ns));
            return;
        }
        let outcome = match outcome {
            Ok(o) => o,
            Err(why) => {
                // A solver that failed gives no result: the cycle is abandoned with the
                // reason, and the scheduler retries it like any failed cycle.
                out.push(Effect::Log(
                    Level::Error,
                    format!("the solve of cycle {number} failed; cycle abandoned: {why}"),
                ));
                out.push(Effect::AbandonCycle {
                    number,
                    t_ns: now_ns,
                    reason: format!("the solve failed: {why}"),
                });
                self.sched.abandoned(now_ns);
                self.view.cycles.abandoned += 1;
                self.publish(now_ns, out);
                return;
            }
        };
        let (result, admitted) = compensation::admit(
            outcome.message(),
            self.served.as_ref(),
            self.measured.as_ref().map(|(_, m)| m),
            &self.limits,
            now_ns,
            &self.layout,
        );
        if result.status == ResultStatus::Rejected {
            out.push(Effect::Log(
                Level::Warn,
                format!(
                    "cycle {number} rejected: {}",
                    result.reason.as_deref().unwrap_or("")
                ),
            ));
        }
        // The result and the set it makes are stored together, before anything is served.
        out.push(Effect::CloseCycle {
            result: Box::new(result.clone()),
            t_ns: now_ns,
            set: admitted.as_ref().map(|a| Box::new(a.nc.clone())),
        });
        if let Some(a) = admitted {
            out.push(Effect::Record(Box::new(Record::Compensation {
                t_ns: now_ns,
                set: a.nc.clone(),
            })));
            out.push(Effect::Log(
                Level::Info,
                format!(
                    "cycle {number}: compensation updated to version {}",
                    a.nc.version
                ),
            ));
            // Judged on the cycle before it learns from it.
            if let Some(note) = self
                .thermal
                .judge(&a.measured, result.t_ns, now_ns, &self.limits)
            {
                out.push(Effect::Log(Level::Warn, format!("thermal model: {note}")));
            }
            if let (Some(e), Some(sg)) = (&result.errors, &result.sigma)
                && let Some(note) = self.thermal.observe(result.t_ns, e, sg)
            {
                out.push(Effect::Log(Level::Info, format!("thermal model: {note}")));
            }
            self.served = Some(a.nc);
            self.measured = Some((result.t_ns, a.measured));
        }
        let ok = result.status == ResultStatus::Ok;
        let alert_input = crate::alerts::Input::from(&result);
        out.push(Effect::Record(Box::new(Record::Result {
            t_ns: now_ns,
            result,
        })));
        out.push(Effect::FlushRecording);
        self.flush_samples(out);
        self.sched.finished(ok, now_ns);
        let events = self.alerts.evaluate(&alert_input, now_ns);
        raise(events, out);
        let v = &mut self.view;
        v.cycles.last = Some(number);
        v.compensation = self.served.clone();
        v.cycles.solve_seconds_sum += seconds;
        if ok {
            v.cycles.ok += 1;
        } else {
            v.cycles.rejected += 1;
        }
        v.cycles.open = None;
        self.show_open_alerts();
        // A cycle's first validated values become the references of rules without one.
        let rules = thresholds(&self.alerts);
        if rules != self.view.thresholds {
            self.view.thresholds = rules;
            self.view.alerts_revision += 1;
        }
        out.push(Effect::PublishView);
    }

    /// Between cycles: look at the model's prediction every `refresh_s` of machine time, ask
    /// for a cycle when it is too uncertain, and serve it as a new compensation set when it
    /// moved and passes the checks. Never during a cycle.
    fn predict_and_serve(&mut self, now_ns: i64, out: &mut Vec<Effect>) {
        // This runs at every step: the policy is only copied once a look is due.
        let refresh_ns = (self.thermal.policy().refresh_s * 1e9) as i64;
        if !self.thermal.policy().enabled
            || now_ns < self.last_prediction_ns.saturating_add(refresh_ns)
        {
            return;
        }
        self.last_prediction_ns = now_ns;
        let preds = self.thermal.predict(now_ns);
        self.thermal.look(
            &mut self.sched,
            preds.as_deref(),
            &self.tip_sensitivity,
            now_ns,
        );
        let Some(preds) = preds else {
            // No prediction: the view moves only if the model's part did (a quiet loop looks
            // once a minute; an unchanged view is not published again).
            if self.show_model() {
                self.view.thermal.revision += 1;
            }
            return;
        };
        // Not during a cycle, and not in the moment a measured set went out.
        let idle = self.open.is_none() && self.requested.is_none() && self.solving.is_none();
        let note = if idle
            && self
                .served
                .as_ref()
                .is_some_and(|s| s.valid_from_ns < now_ns)
        {
            self.serve_prediction(&preds, now_ns, out)
        } else {
            None
        };
        self.show_model();
        let t = &mut self.view.thermal;
        t.revision += 1;
        t.prediction = preds;
        t.prediction_t_ns = Some(now_ns);
        t.prediction_note = note;
        t.predictor = self.thermal.snapshot().map(Arc::new);
    }

    /// The model's part of the view, rebuilt only when the model changed since it was shown;
    /// whether it was.
    fn show_model(&mut self) -> bool {
        let revision = self.thermal.revision();
        let changed = self.model_shown != Some(revision) || self.view.thermal.model.is_none();
        if changed {
            self.view.thermal.model = Some(Arc::new(self.thermal.view()));
            self.model_shown = Some(revision);
        }
        changed
    }

    /// Serve the prediction as a new set if the model is trusted, the prediction moved and
    /// the set passes its checks; otherwise say why not (once per new reason in the log).
    fn serve_prediction(
        &mut self,
        preds: &[Prediction],
        now_ns: i64,
        out: &mut Vec<Effect>,
    ) -> Option<String> {
        let served = self.served.as_ref()?;
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
        let policy = self.thermal.policy();
        let values: BTreeMap<String, f64> =
            preds.iter().map(|p| (p.channel.clone(), p.value)).collect();
        let refused = match trusted {
            Err(why) => why,
            Ok(()) if !policy.moved(served, &values) => return None,
            Ok(()) => {
                let about = format!(
                    "the thermal model{}{}",
                    served
                        .cycle
                        .map(|c| format!(" after cycle {c}"))
                        .unwrap_or_default(),
                    LiveModel::fallback_note(preds)
                );
                match compensation::predicted_set(
                    Some(served),
                    &with_sigma,
                    &self.limits,
                    policy,
                    now_ns,
                    &about,
                    &self.layout,
                ) {
                    Ok(mut set) => {
                        set.cycle = served.cycle;
                        // Stored and recorded before it is served.
                        out.push(Effect::StoreSet(Box::new(set.clone())));
                        out.push(Effect::Record(Box::new(Record::Compensation {
                            t_ns: now_ns,
                            set: set.clone(),
                        })));
                        self.view.compensation = Some(set.clone());
                        self.served = Some(set);
                        self.last_refusal = None;
                        return None;
                    }
                    Err(refused) => refused.reasons.join("; "),
                }
            }
        };
        if self.last_refusal.as_deref() != Some(&refused) {
            out.push(Effect::Log(
                Level::Warn,
                format!("predicted set not served: {refused}"),
            ));
        }
        self.last_refusal = Some(refused.clone());
        Some(refused)
    }

    fn shutdown(&mut self, now_ns: i64, out: &mut Vec<Effect>) {
        self.flush_samples(out);
        if let Some(open) = self.open.take() {
            out.push(Effect::AbortCycle {
                number: open.number,
            });
            out.push(store_detections(&open));
            out.push(Effect::AbandonCycle {
                number: open.number,
                t_ns: now_ns,
                reason: "the service shut down during the cycle".into(),
            });
        }
    }
}

/// The detections a cycle received, stored when it ends (finished, timed out or shut down):
/// two commits per cycle instead of one per step. A crash during a cycle loses its detections
/// from the database only; the cycle is abandoned at restart either way.
fn store_detections(open: &OpenCycle) -> Effect {
    let rows = open
        .detections
        .iter()
        .filter_map(|d| {
            let m = d.msg.as_ref().ok()?;
            Some(StoredDetection {
                t_ns: d.t_ns,
                step: m.step.clone(),
                payload: serde_json::to_string(m).ok()?,
            })
        })
        .collect();
    Effect::StoreDetections {
        number: open.number,
        rows,
    }
}

fn raise(events: Vec<AlertEvent>, out: &mut Vec<Effect>) {
    out.extend(events.into_iter().map(|e| Effect::Alert(Box::new(e))));
}
