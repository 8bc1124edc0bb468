//! Scenarios for the truth simulator: machine, spindle program, cycle times, noise, the
//! virtual machine's thermal behaviour and the effects switched on. TOML, every key documented
//! in `config/scenarios/patent.toml`.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use driftwatch_core::recording::MachineStateKind;
use driftwatch_core::thermal::{Channel, InputConfig, LagTerm};

pub const BUILTIN_SCENARIOS: &[(&str, &str)] = &[
    (
        "patent",
        include_str!("../../../config/scenarios/patent.toml"),
    ),
    (
        "patent_head_b_table_c",
        include_str!("../../../config/scenarios/patent_head_b_table_c.toml"),
    ),
    (
        "patent_table_d45_c",
        include_str!("../../../config/scenarios/patent_table_d45_c.toml"),
    ),
    (
        "patent_head_d45_table_c",
        include_str!("../../../config/scenarios/patent_head_d45_table_c.toml"),
    ),
    (
        "patent_trunnion_ac",
        include_str!("../../../config/scenarios/patent_trunnion_ac.toml"),
    ),
    (
        "warmup",
        include_str!("../../../config/scenarios/warmup.toml"),
    ),
    (
        "two_shift",
        include_str!("../../../config/scenarios/two_shift.toml"),
    ),
    (
        "monday",
        include_str!("../../../config/scenarios/monday.toml"),
    ),
    (
        "ambient_swing",
        include_str!("../../../config/scenarios/ambient_swing.toml"),
    ),
];

#[derive(Debug, Error)]
pub enum ScenarioError {
    #[error(transparent)]
    Source(#[from] driftwatch_core::source::SourceError),
    #[error("scenario {origin} is not valid TOML for a scenario: {message}")]
    Parse { origin: String, message: String },
    #[error("scenario '{name}': {message}")]
    Invalid { name: String, message: String },
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProgramSegment {
    /// From this time on (min from the scenario start)...
    pub at_min: f64,
    /// ... the spindle turns at this speed (min^-1) ...
    pub rpm: f64,
    /// ... and the NC reports this state.
    #[serde(default = "idle")]
    pub state: MachineStateKind,
    #[serde(default)]
    pub program: Option<String>,
}

fn idle() -> MachineStateKind {
    MachineStateKind::Idle
}

#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CycleSchedule {
    /// Explicit cycle start times, min.
    pub at_min: Vec<f64>,
    /// Or a regular cadence: every `every_min` from `from_min` up to `to_min`.
    pub every_min: Option<f64>,
    pub from_min: f64,
    pub to_min: Option<f64>,
    /// Spindle speed of each cycle, min^-1: cycle `c` (from 0) takes entry `c % len`. Empty:
    /// the plan's speed.
    pub rpm_sequence: Vec<f64>,
    /// Probing feed of each cycle, mm/min, taken the same way. Empty: the plan's feed.
    pub feed_sequence: Vec<f64>,
    /// Plan edits: from `at_min` on, every cycle probes at `feed_mm_min` (over the sequence).
    pub feed_changes: Vec<FeedChange>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FeedChange {
    pub at_min: f64,
    pub feed_mm_min: f64,
}

impl CycleSchedule {
    /// Speed and feed of cycle `c` (from 0) starting at `t_min`, given the plan's.
    pub fn settings(&self, c: usize, t_min: f64, plan_rpm: f64, plan_feed: f64) -> (f64, f64) {
        let pick = |v: &[f64], d: f64| if v.is_empty() { d } else { v[c % v.len()] };
        let rpm = pick(&self.rpm_sequence, plan_rpm);
        let feed = self
            .feed_changes
            .iter()
            .filter(|f| f.at_min <= t_min)
            .max_by(|a, b| a.at_min.total_cmp(&b.at_min))
            .map_or_else(|| pick(&self.feed_sequence, plan_feed), |f| f.feed_mm_min);
        (rpm, feed)
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NoiseConfig {
    /// Trip noise, one standard deviation, um.
    pub sigma_um: f64,
    /// Probability that a reading is an outlier (chips, coolant mist).
    pub outlier_rate: f64,
    /// Outlier size range, um.
    pub outlier_um: [f64; 2],
    /// Which way an outlier moves the reading: `random` (either sign) or `early` (the skip
    /// trips before the beam is cut: the reading falls short along the approach, as a chip
    /// or a coolant drop on the tool does).
    pub outlier_sense: OutlierSense,
    /// Probability that an approach ends without a trip.
    pub no_trip_rate: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutlierSense {
    #[default]
    Random,
    Early,
}

impl Default for NoiseConfig {
    fn default() -> Self {
        NoiseConfig {
            sigma_um: 0.5,
            outlier_rate: 0.0,
            outlier_um: [5.0, 30.0],
            outlier_sense: OutlierSense::Random,
            no_trip_rate: 0.0,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AmbientConfig {
    pub mean_c: f64,
    /// Half the day-night swing, K.
    pub amplitude_k: f64,
    pub period_h: f64,
    /// Hour of the UTC day with the warmest air.
    pub peak_h: f64,
    /// Whether an `ambient` sensor is written to `/temperature`.
    pub logged: bool,
}

impl Default for AmbientConfig {
    fn default() -> Self {
        AmbientConfig {
            mean_c: 20.0,
            amplitude_k: 0.0,
            period_h: 24.0,
            peak_h: 15.0,
            logged: true,
        }
    }
}

/// The thermal behaviour of the virtual machine. `channels` and `sensors` are merged over the
/// defaults (the patent reproduction): an entry given here replaces the default of that name.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TruthConfig {
    /// Reference spindle speed of the heat input `u = (n / n_ref)^gamma`, min^-1.
    pub n_ref_rpm: f64,
    pub gamma: f64,
    /// Ambient reference temperature of the ambient lags, deg C.
    pub t_ref_c: f64,
    /// Location errors (um, urad), tool-tip drift sx, sy, sz (um), setter shift in the table
    /// frame setter_x, setter_y, setter_z (um), effective radius change `radius` (um), scale
    /// errors kx, ky, kz (ppm), squareness errors sxy, sxz, syz (urad) and ISO 230-1 component
    /// coefficients, named by the component and the power of `p / 100 mm` (`EZX2`: X's
    /// straightness along Z, um at 100 mm; `EAY1`: Y's rotation about X per 100 mm, urad).
    pub channels: BTreeMap<String, Channel>,
    /// Temperature sensors (deg C), written to `/temperature` unless listed in `unlogged`.
    pub sensors: BTreeMap<String, Channel>,
    pub unlogged: Vec<String>,
    /// Periodic disturbances added to channels (the same channel names).
    pub periodic: Vec<PeriodicTerm>,
}

impl Default for TruthConfig {
    fn default() -> Self {
        let i = InputConfig::default();
        TruthConfig {
            n_ref_rpm: i.n_ref_rpm,
            gamma: i.gamma,
            t_ref_c: i.t_ref_c,
            channels: BTreeMap::new(),
            sensors: BTreeMap::new(),
            unlogged: Vec::new(),
            periodic: Vec::new(),
        }
    }
}

impl TruthConfig {
    pub fn inputs(&self) -> InputConfig {
        InputConfig {
            n_ref_rpm: self.n_ref_rpm,
            gamma: self.gamma,
            t_ref_c: self.t_ref_c,
        }
    }
}

fn lag(gain: f64, tau_min: f64) -> Channel {
    Channel {
        spindle: vec![LagTerm { gain, tau_min }],
        ..Default::default()
    }
}

/// The default virtual machine: reproduces the patent experiment (see `config/scenarios/patent.toml`
/// for the reasoning). EZ0B_app = EZ0B - sz splits into tool growth (fast) and structure (slow).
/// On another machine the same story drives its own errors: the tilting axis' first and second
/// identified position errors (`identify[0]`, `identify[1]`) take EX0B's and EZ0B's lags; the
/// C errors keep their names; a default the machine has no error for is left out.
pub fn default_channels(identify: &[String]) -> BTreeMap<String, Channel> {
    let tilt = |i: usize, fallback: &str| identify.get(i).cloned().unwrap_or(fallback.into());
    let mut m = BTreeMap::new();
    m.insert("sz".into(), lag(-41.0, 11.0));
    m.insert(tilt(1, "EZ0B"), lag(48.0, 120.0));
    m.insert(tilt(0, "EX0B"), lag(22.0, 60.0));
    m.insert("sy".into(), lag(-4.0, 45.0));
    for (name, gain) in [("EX0C", 2.0), ("EA0C", 3.0), ("EB0C", -4.0)] {
        if identify.is_empty() || identify.iter().any(|n| n == name) {
            m.insert(name.into(), lag(gain, 90.0));
        }
    }
    m
}

pub fn default_sensors() -> BTreeMap<String, Channel> {
    let mut m = BTreeMap::new();
    let mut head = lag(14.0, 15.0);
    head.offset = 20.0;
    head.ambient = vec![LagTerm {
        gain: 1.0,
        tau_min: 60.0,
    }];
    m.insert("spindle_head".into(), head);
    m
}

/// Errors of the rotary axes that depend on how and where they are positioned (one entry per
/// rotary axis, in the machine file's order; missing entries are zero). They act on each
/// approach through the axis' angle, not through the six location errors.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RotaryEffects {
    /// Full backlash, urad: the angle is off by `+backlash/2` after a move in the positive
    /// sense and by `-backlash/2` after a negative one (0 before the first move).
    pub backlash_urad: Vec<f64>,
    /// Indexing error as a Fourier series in the commanded angle: `[harmonic, cos_urad,
    /// sin_urad]` terms, `sum (a cos(h theta) + b sin(h theta))`; harmonic 0 is a constant.
    pub index_urad: Vec<Vec<[f64; 3]>>,
}

impl RotaryEffects {
    /// The angle error of axis `i`, rad, at the commanded angle `theta_deg` after a move in
    /// the sense `last_dir` (-1, 0 or +1).
    pub fn angle_error_rad(&self, i: usize, theta_deg: f64, last_dir: f64) -> f64 {
        let theta = theta_deg.to_radians();
        let backlash = self.backlash_urad.get(i).copied().unwrap_or(0.0) * 0.5 * last_dir;
        let index: f64 = self.index_urad.get(i).map_or(0.0, |terms| {
            terms
                .iter()
                .map(|[h, a, b]| a * (h * theta).cos() + b * (h * theta).sin())
                .sum()
        });
        (backlash + index) * 1e-6
    }

    pub fn is_zero(&self) -> bool {
        self.backlash_urad.iter().all(|v| *v == 0.0)
            && self
                .index_urad
                .iter()
                .flatten()
                .all(|[_, a, b]| *a == 0.0 && *b == 0.0)
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SkipConfig {
    /// True skip latency of the virtual machine, ms (the machine file holds the calibrated one).
    pub latency_ms: f64,
    /// Changes of the true latency: from `at_min` on it is `latency_ms` (an NC parameter or
    /// firmware change, a new setter filter), whatever the feed.
    pub changes: Vec<LatencyChange>,
}

impl Default for SkipConfig {
    fn default() -> Self {
        SkipConfig {
            latency_ms: 0.0,
            changes: Vec::new(),
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LatencyChange {
    pub at_min: f64,
    pub latency_ms: f64,
}

impl SkipConfig {
    /// The true latency at `t_min` after the scenario start, s.
    pub fn latency_s_at(&self, t_min: f64) -> f64 {
        self.changes
            .iter()
            .filter(|c| c.at_min <= t_min)
            .max_by(|a, b| a.at_min.total_cmp(&b.at_min))
            .map_or(self.latency_ms, |c| c.latency_ms)
            * 1e-3
    }
}

/// A periodic disturbance of one truth channel, outside any thermal lag (a coolant or chiller
/// cycle, a hydraulic unit switching): `amplitude * sin(2 pi t / period + phase)`, t from the
/// scenario start.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PeriodicTerm {
    /// A truth channel name (see `TruthConfig::channels`).
    pub channel: String,
    /// In the channel's unit (um, ppm, urad).
    pub amplitude: f64,
    pub period_min: f64,
    #[serde(default)]
    pub phase_deg: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// Built-in machine name or path to a machine TOML.
    pub machine: String,
    #[serde(default = "default_machine_id")]
    pub machine_id: String,
    /// Built-in plan name or path to a plan TOML.
    pub plan: String,
    pub seed: u64,
    /// Scenario start, RFC 3339 (UTC).
    pub start_utc: String,
    pub duration_min: f64,
    /// Interval of `/temperature` and `/sim/truth` samples, s.
    #[serde(default = "sixty")]
    pub sample_s: f64,
    pub spindle: Vec<ProgramSegment>,
    #[serde(default)]
    pub cycles: CycleSchedule,
    #[serde(default)]
    pub noise: NoiseConfig,
    #[serde(default)]
    pub skip: SkipConfig,
    #[serde(default)]
    pub rotary: RotaryEffects,
    #[serde(default)]
    pub ambient: AmbientConfig,
    #[serde(default)]
    pub truth: TruthConfig,
}

fn default_machine_id() -> String {
    "sim-1".into()
}

fn sixty() -> f64 {
    60.0
}

impl Scenario {
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, ScenarioError> {
        let s: Scenario = toml::from_str(text).map_err(|e| ScenarioError::Parse {
            origin: origin.to_string(),
            message: e.to_string(),
        })?;
        s.validate()?;
        Ok(s)
    }

    pub fn load(name_or_path: &str) -> Result<Self, ScenarioError> {
        let text =
            driftwatch_core::source::builtin_or_file("scenario", name_or_path, BUILTIN_SCENARIOS)?;
        Self::from_toml(&text, name_or_path)
    }

    fn validate(&self) -> Result<(), ScenarioError> {
        let bad = |m: &str| {
            Err(ScenarioError::Invalid {
                name: self.name.clone(),
                message: m.to_string(),
            })
        };
        if !driftwatch_core::units::positive(self.duration_min) {
            return bad("duration_min must be > 0");
        }
        if self.spindle.is_empty() {
            return bad("the spindle program needs at least one segment");
        }
        if self.spindle.windows(2).any(|w| w[1].at_min <= w[0].at_min) {
            return bad("spindle segments must have increasing at_min");
        }
        if self
            .spindle
            .iter()
            .any(|s| !s.rpm.is_finite() || s.rpm < 0.0)
        {
            return bad("spindle rpm must be finite and >= 0");
        }
        if !driftwatch_core::units::non_negative(self.noise.sigma_um)
            || !(0.0..=1.0).contains(&self.noise.outlier_rate)
            || !(0.0..=1.0).contains(&self.noise.no_trip_rate)
        {
            return bad("noise: sigma_um >= 0, rates within [0, 1]");
        }
        if self
            .skip
            .changes
            .iter()
            .any(|c| !c.at_min.is_finite() || !c.latency_ms.is_finite())
        {
            return bad("skip.changes: finite times and latencies");
        }
        if self.truth.periodic.iter().any(|p| {
            !p.amplitude.is_finite()
                || !driftwatch_core::units::positive(p.period_min)
                || !p.phase_deg.is_finite()
        }) {
            return bad("truth.periodic: finite amplitude and phase, period_min > 0");
        }
        if !driftwatch_core::units::positive(self.sample_s) {
            return bad("sample_s must be > 0");
        }
        if let Some(e) = self.cycles.every_min
            && !driftwatch_core::units::positive(e)
        {
            return bad("cycles.every_min must be > 0");
        }
        let c = &self.cycles;
        if c.rpm_sequence
            .iter()
            .any(|v| !driftwatch_core::units::positive(*v))
            || c.feed_sequence
                .iter()
                .any(|v| !driftwatch_core::units::positive(*v))
            || c.feed_changes
                .iter()
                .any(|f| !driftwatch_core::units::positive(f.feed_mm_min))
        {
            return bad("cycle speeds and feeds must be > 0");
        }
        if self.rotary.backlash_urad.len() > driftwatch_core::kinematics::MAX_ROTARY
            || self.rotary.index_urad.len() > driftwatch_core::kinematics::MAX_ROTARY
            || self.rotary.backlash_urad.iter().any(|v| !v.is_finite())
            || self
                .rotary
                .index_urad
                .iter()
                .flatten()
                .any(|t| t.iter().any(|v| !v.is_finite()) || t[0] < 0.0 || t[0].fract() != 0.0)
        {
            return bad(
                "rotary: at most one entry per rotary axis, finite values, whole harmonics >= 0",
            );
        }
        if chrono::DateTime::parse_from_rfc3339(&self.start_utc).is_err() {
            return bad("start_utc must be an RFC 3339 time, e.g. 2026-03-02T06:00:00Z");
        }
        Ok(())
    }

    pub fn start_ns(&self) -> i64 {
        chrono::DateTime::parse_from_rfc3339(&self.start_utc)
            .map(|t| t.timestamp_nanos_opt().unwrap_or(0))
            .unwrap_or(0)
    }

    /// A cycle every `every_min` from 5 min on, for the whole scenario (instead of its own
    /// cycle times): the cadence the diagnosis' recordings use.
    pub fn with_cycles_every(mut self, every_min: f64) -> Scenario {
        self.cycles.at_min.clear();
        self.cycles.every_min = Some(every_min);
        self.cycles.from_min = 5.0;
        self.cycles.to_min = None;
        self
    }

    /// The same scenario over `days` days: the spindle program of its first day (`at_min` under
    /// 1440) repeated each day, and the duration made `days` days.
    pub fn repeated_days(&self, days: usize) -> Scenario {
        let day: Vec<ProgramSegment> = self
            .spindle
            .iter()
            .filter(|s| s.at_min < 1440.0)
            .cloned()
            .collect();
        let mut out = self.clone();
        out.spindle = (0..days)
            .flat_map(|d| {
                day.iter().map(move |s| ProgramSegment {
                    at_min: s.at_min + 1440.0 * d as f64,
                    ..s.clone()
                })
            })
            .collect();
        out.duration_min = 1440.0 * days as f64;
        out
    }

    /// Three production days as the diagnosis' simulated recordings have them (the suite of
    /// docs/physics.md 4.8), on `machine` with its `plan`: this scenario's program each day
    /// (the two-shift one of `ambient_swing`), a cycle every 30 min, 0.5-um noise, the hall
    /// at a constant 20 C (logged), no thermal truth (an injection adds its own). Day 2 starts
    /// two hours late and day 3 (the held-out day) has the first shift only: days alike would
    /// let the spindle's daily rhythm stand in for any other daily one.
    pub fn diagnosis_days(&self, machine: &str, plan: &str, seed: u64) -> Scenario {
        let mut scn = self.repeated_days(3).with_cycles_every(30.0);
        scn.machine = machine.to_string();
        scn.plan = plan.to_string();
        scn.spindle
            .retain(|s| !(s.at_min > 2880.0 + 840.0 && s.at_min < 2880.0 + 1320.0));
        for s in &mut scn.spindle {
            match (s.at_min / 1440.0).floor() as i64 {
                1 if s.at_min > 1440.0 => s.at_min += 120.0,
                2 if s.at_min == 2880.0 + 840.0 => s.rpm = 0.0,
                _ => {}
            }
        }
        scn.seed = seed;
        scn.noise.sigma_um = 0.5;
        scn.ambient.amplitude_k = 0.0;
        scn.truth.channels.clear();
        scn
    }

    /// Cycle start times, min, sorted.
    pub fn cycle_times_min(&self) -> Vec<f64> {
        let mut t = self.cycles.at_min.clone();
        if let Some(every) = self.cycles.every_min {
            let end = self.cycles.to_min.unwrap_or(self.duration_min);
            let mut x = self.cycles.from_min;
            while x <= end + 1e-9 {
                t.push(x);
                x += every;
            }
        }
        t.retain(|x| *x >= 0.0 && *x < self.duration_min);
        t.sort_by(f64::total_cmp);
        t.dedup();
        t
    }

    /// Truth channels: the defaults for a machine identifying `identify` (see
    /// [`default_channels`]) with this scenario's channels over them.
    pub fn truth_channels(&self, identify: &[String]) -> BTreeMap<String, Channel> {
        let mut m = default_channels(identify);
        for (k, v) in &self.truth.channels {
            m.insert(k.clone(), v.clone());
        }
        m
    }

    pub fn sensors(&self) -> BTreeMap<String, Channel> {
        let mut m = default_sensors();
        for (k, v) in &self.truth.sensors {
            m.insert(k.clone(), v.clone());
        }
        m
    }
}
