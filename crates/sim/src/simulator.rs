//! The truth simulator: a virtual machine whose location errors, tool-tip drift, setter,
//! tool radius and linear axes follow a thermal model driven by the complete spindle log
//! (measurement spins included), measured by cycles whose every detection happens at its own
//! time in exact geometry, with noise, outliers and failed approaches. Deterministic for a
//! given seed; no I/O.

use driftwatch_core::units;
use std::collections::BTreeMap;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use thiserror::Error;

use crate::scenario::Scenario;
use driftwatch_core::geometry::Vec3;
use driftwatch_core::kinematics::{Kinematics, MachineState};
use driftwatch_core::measurement::latched;
use driftwatch_core::plan::Plan;
use driftwatch_core::recording::{
    DetectionMsg, DetectionStatus, MachineInfo, MachineStateKind, SpindleMsg, StateMsg,
    TemperatureMsg, Timed,
};
use driftwatch_core::thermal::LagModel;

#[derive(Debug, Error)]
pub enum SimError {
    #[error(
        "scenario channel '{0}' is not a location error of the machine nor one of sx, sy, sz, setter_x, setter_y, setter_z, radius, kx, ky, kz, sxy, sxz, syz"
    )]
    UnknownChannel(String),
    #[error(
        "scenario '{scenario}' uses machine '{scenario_machine}' but was given machine '{machine}'"
    )]
    MachineMismatch {
        scenario: String,
        scenario_machine: String,
        machine: String,
    },
}

/// The truth at one instant: the apparent (tool-relative) location errors a perfect cycle
/// would report, and every raw channel.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TruthSample {
    pub t_ns: i64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cycle: Option<i64>,
    pub rpm: f64,
    pub apparent: BTreeMap<String, f64>,
    pub channels: BTreeMap<String, f64>,
}

impl TruthSample {
    /// The same sample with every value rounded to `step` (um or urad). A recording at
    /// 1e-4 um (0.1 nm) keeps far more than any measurement could see and compresses several
    /// times better than full binary64 digits.
    pub fn rounded(mut self, step: f64) -> TruthSample {
        // Dividing by the reciprocal gives the shortest decimal (0.81443, not 0.8144299999).
        let per = 1.0 / step;
        // Rounded in the sample's own maps: a copy (or new maps) would cost the allocations
        // and frees of every key, once a simulated minute.
        for v in self.apparent.values_mut().chain(self.channels.values_mut()) {
            *v = (*v * per).round() / per;
        }
        self
    }
}

#[derive(Debug, Clone)]
pub struct SimCycle {
    pub number: i64,
    pub start_ns: i64,
    pub detections: Vec<Timed<DetectionMsg>>,
    /// Truth at the cycle's reference time (mean time of its `ok` detections).
    pub truth: TruthSample,
}

#[derive(Debug, Clone)]
pub struct Simulation {
    pub info: MachineInfo,
    pub states: Vec<Timed<StateMsg>>,
    pub spindle: Vec<Timed<SpindleMsg>>,
    pub temperatures: Vec<Timed<TemperatureMsg>>,
    pub truth: Vec<TruthSample>,
    pub cycles: Vec<SimCycle>,
}

impl Simulation {
    /// The simulation as a reader would take it from its recording (without the truth).
    pub fn recording(&self) -> driftwatch_core::recording::Recording {
        driftwatch_core::recording::Recording {
            info: Some(self.info.clone()),
            states: self.states.clone(),
            spindle: self.spindle.clone(),
            temperatures: self.temperatures.clone(),
            detections: self.detection_stream(),
            ..Default::default()
        }
    }

    /// Every detection of every cycle, as a reader of the recording would take them.
    pub fn detection_stream(
        &self,
    ) -> Vec<Timed<Result<DetectionMsg, driftwatch_core::recording::DetectionIssue>>> {
        self.cycles
            .iter()
            .flat_map(|c| c.detections.iter())
            .map(|d| Timed {
                t_ns: d.t_ns,
                msg: Ok(d.msg.clone()),
            })
            .collect()
    }
}

#[derive(Clone, Copy)]
enum Target {
    Location(usize, usize, f64),
    Tool(usize),
    Setter(usize),
    Radius,
    Scale(usize),
    Sxy,
    Sxz,
    Syz,
    /// An ISO 230-1 component coefficient: axis, rotation?, direction, power of `p / 100 mm`.
    Component(usize, bool, usize, usize),
}

/// A truth channel naming one coefficient of an ISO 230-1 component error: the component's
/// name and the power of `p / 100 mm` (`EZX2`: X's straightness along Z, the `u^2` term, um;
/// `EBX1`: X's rotation about Y per 100 mm, urad).
fn component(name: &str) -> Option<(usize, bool, usize, usize)> {
    let (iso, power) = name.split_at_checked(3)?;
    let n = match power {
        "1" => 1,
        "2" => 2,
        "3" => 3,
        _ => return None,
    };
    let (j, rot, i) = driftwatch_core::linear_axes::parse_component(iso)?;
    Some((j, rot, i, n))
}

/// The virtual machine: thermal state plus the map from channels to the machine state.
#[derive(Clone)]
struct Virtual {
    model: LagModel,
    targets: Vec<Target>,
    sensors: LagModel,
    base: MachineState,
    /// Seconds since the scenario start (for the periodic terms and latency changes).
    t_s: f64,
    /// Periodic disturbances: target, amplitude, angular frequency (rad/s), phase (rad).
    periodic: Vec<(Target, f64, f64, f64)>,
    skip: crate::scenario::SkipConfig,
}

impl Virtual {
    fn new(k: &Kinematics, scn: &Scenario) -> Result<Self, SimError> {
        let channels: Vec<_> = scn
            .truth_channels(&k.identify_names())
            .into_iter()
            .collect();
        let target = |name: &str| -> Result<Target, SimError> {
            Ok(match name {
                "sx" => Target::Tool(0),
                "sy" => Target::Tool(1),
                "sz" => Target::Tool(2),
                "setter_x" => Target::Setter(0),
                "setter_y" => Target::Setter(1),
                "setter_z" => Target::Setter(2),
                "radius" => Target::Radius,
                "kx" => Target::Scale(0),
                "ky" => Target::Scale(1),
                "kz" => Target::Scale(2),
                "sxy" => Target::Sxy,
                "sxz" => Target::Sxz,
                "syz" => Target::Syz,
                other => match (component(other), k.error_id(other)) {
                    (Some((j, rot, i, n)), _) => Target::Component(j, rot, i, n),
                    (None, Some(id)) => Target::Location(id.axis, id.slot, id.scale()),
                    (None, None) => return Err(SimError::UnknownChannel(other.to_string())),
                },
            })
        };
        let mut targets = Vec::new();
        for (name, _) in &channels {
            targets.push(target(name)?);
        }
        let mut periodic = Vec::new();
        for p in &scn.truth.periodic {
            periodic.push((
                target(&p.channel)?,
                p.amplitude,
                std::f64::consts::TAU / (p.period_min * 60.0),
                p.phase_deg.to_radians(),
            ));
        }
        let inputs = scn.truth.inputs();
        let mut base = k.nominal_state();
        // The NC's held values are its belief, not the truth: the truth starts from zero.
        base.loc = [[0.0; 5]; driftwatch_core::kinematics::MAX_ROTARY];
        // So is a measured linear geometry: the truth's comes from its channels alone.
        base.linear = driftwatch_core::kinematics::LinearErrors {
            stack: k.linear.stack,
            abbe_mm: k.linear.abbe_mm,
            ..Default::default()
        };
        base.latency_s = scn.skip.latency_ms * 1e-3;
        Ok(Virtual {
            model: LagModel::new(inputs, channels),
            targets,
            sensors: LagModel::new(inputs, scn.sensors().into_iter().collect()),
            base,
            t_s: 0.0,
            periodic,
            skip: scn.skip.clone(),
        })
    }

    fn advance(&mut self, dt_s: f64, rpm: f64, ambient_c: f64) {
        self.model.advance(dt_s, rpm, ambient_c);
        self.sensors.advance(dt_s, rpm, ambient_c);
        self.t_s += dt_s;
    }

    /// The true skip latency now, s.
    fn latency_s(&self) -> f64 {
        self.skip.latency_s_at(self.t_s / 60.0)
    }

    fn state(&self, rpm: f64) -> MachineState {
        let mut s = self.base;
        s.latency_s = self.latency_s();
        let thermal = self
            .targets
            .iter()
            .enumerate()
            .map(|(i, t)| (*t, self.model.value(i, rpm)));
        let periodic = self
            .periodic
            .iter()
            .map(|(t, a, w, ph)| (*t, a * (w * self.t_s + ph).sin()));
        for (t, v) in thermal.chain(periodic) {
            match t {
                Target::Location(a, slot, scale) => s.loc[a][slot] += v * scale,
                Target::Tool(j) => s.tool_tip[j] += v * 1e-3,
                Target::Setter(j) => s.beam_point[j] += v * 1e-3,
                Target::Radius => s.radius += v * 1e-3,
                Target::Scale(j) => s.linear.k[j] += v * 1e-6,
                Target::Sxy => s.linear.sxy += v * 1e-6,
                Target::Sxz => s.linear.sxz += v * 1e-6,
                Target::Syz => s.linear.syz += v * 1e-6,
                Target::Component(j, rot, i, n) => match rot {
                    true => s.linear.axes[j].rotation_urad[i][n - 1] += v,
                    false => s.linear.axes[j].translation_um[i][n - 1] += v,
                },
            }
        }
        s
    }

    fn sample(&self, k: &Kinematics, t_ns: i64, rpm: f64, cycle: Option<i64>) -> TruthSample {
        let app = k.apparent_state(&self.state(rpm));
        let mut apparent = BTreeMap::new();
        for id in &k.identify {
            apparent.insert(
                k.error_name(*id).to_string(),
                app.loc[id.axis][id.slot] / id.scale(),
            );
        }
        let shift = (app.beam_point - k.setter.point) * 1e3;
        apparent.insert("setter_x_um".into(), shift.x);
        apparent.insert("setter_y_um".into(), shift.y);
        apparent.insert("setter_z_um".into(), shift.z);
        let channels = self
            .model
            .names()
            .iter()
            .enumerate()
            .map(|(i, n)| (n.clone(), self.model.value(i, rpm)))
            .collect();
        TruthSample {
            t_ns,
            cycle,
            rpm,
            apparent,
            channels,
        }
    }
}

/// The virtual machine of a scenario, driven step by step: the truth simulator's state, its
/// noise and its clock. The batch `simulate` and the daemon's simulated link both use it.
#[derive(Clone)]
pub struct VirtualMachine {
    vm: Virtual,
    rng: ChaCha8Rng,
    noise: crate::scenario::NoiseConfig,
    ambient: crate::scenario::AmbientConfig,
    unlogged: Vec<String>,
    start_ns: i64,
    /// Seconds since `start_ns`.
    now_s: f64,
    rotary: crate::scenario::RotaryEffects,
    /// The sense each rotary axis last moved in, along the approaches.
    sense: driftwatch_core::kinematics::RotarySense,
}

impl VirtualMachine {
    /// The machine of a scenario at the scenario's start, settled cold at ambient.
    pub fn new(k: &Kinematics, scn: &Scenario) -> Result<Self, SimError> {
        let mut vm = Virtual::new(k, scn)?;
        let start_ns = scn.start_ns();
        let amb = ambient_at(&scn.ambient, start_ns);
        vm.model.settle(0.0, amb);
        vm.sensors.settle(0.0, amb);
        Ok(VirtualMachine {
            vm,
            rng: ChaCha8Rng::seed_from_u64(scn.seed),
            noise: scn.noise.clone(),
            ambient: scn.ambient.clone(),
            unlogged: scn.truth.unlogged.clone(),
            start_ns,
            now_s: 0.0,
            rotary: scn.rotary.clone(),
            sense: Default::default(),
        })
    }

    pub fn start_ns(&self) -> i64 {
        self.start_ns
    }

    pub fn now_ns(&self) -> i64 {
        self.to_ns(self.now_s)
    }

    fn to_ns(&self, t_s: f64) -> i64 {
        self.start_ns + (t_s * 1e9).round() as i64
    }

    /// Advance to `t_ns` with the spindle held at `rpm` (ambient in steps of at most 60 s).
    pub fn advance_to(&mut self, t_ns: i64, rpm: f64) {
        let te = (t_ns - self.start_ns) as f64 / 1e9;
        while self.now_s < te {
            let dt = (te - self.now_s).min(60.0);
            let amb = ambient_at(&self.ambient, self.to_ns(self.now_s + dt / 2.0));
            self.vm.advance(dt, rpm, amb);
            self.now_s += dt;
        }
        self.now_s = self.now_s.max(te);
    }

    /// One approach starting now, the spindle at `rpm`: the detection with its own time, in
    /// exact geometry, with noise, outliers and failed approaches. The state is not advanced
    /// (the trip lies within seconds; the caller advances the clock).
    pub fn probe(
        &mut self,
        k: &Kinematics,
        step: &driftwatch_core::plan::Step,
        cycle: i64,
        rpm: f64,
    ) -> Timed<DetectionMsg> {
        let te = self.now_s;
        let amb = ambient_at(&self.ambient, self.now_ns());
        let feed = step.approach.feed_mm_min / 60.0;
        let travel = step.travel();
        let dir = f64::from(step.approach.direction);
        let lat = step.approach.latency_shift(self.vm.latency_s());
        // The rotary axes' own errors at this pose: backlash by the sense of their last move,
        // indexing error by their angle. Production moves between cycles are not known here:
        // the sense comes from the approaches alone.
        let sense = self.sense.go_to(&step.angles);
        let mut angle_error = [0.0; driftwatch_core::kinematics::MAX_ROTARY];
        if !self.rotary.is_zero() {
            for (i, e) in angle_error.iter_mut().enumerate() {
                *e = self
                    .rotary
                    .angle_error_rad(i, step.angles[i], f64::from(sense[i]));
            }
        }
        // The trip time depends on where the beam is: two passes.
        let mut t_trip = te + (step.expected - travel.start).abs() / feed;
        let mut outcome = None;
        for _ in 0..2 {
            let mut peek = self.vm.clone();
            peek.advance(t_trip - te, rpm, amb);
            let mut s = peek.state(rpm);
            for (e, add) in s.angle_error.iter_mut().zip(angle_error) {
                *e += add;
            }
            let r = latched(
                k,
                &s,
                &step.angles,
                &step.approach,
                &step.start,
                Some(travel),
            );
            if let Ok(v) = r {
                t_trip = te + ((v - lat) - travel.start).abs() / feed;
            }
            outcome = Some(r);
        }
        let mut pos = step.start;
        let axis = step.approach.axis.index();
        let forced_no_trip = self.rng.random::<f64>() < self.noise.no_trip_rate;
        let (status, t_det) = match outcome {
            Some(Ok(v)) if !forced_no_trip => {
                let z: f64 = StandardNormal.sample(&mut self.rng);
                let mut e_um = self.noise.sigma_um * z;
                if self.rng.random::<f64>() < self.noise.outlier_rate {
                    let [lo, hi] = self.noise.outlier_um;
                    let size = lo + (hi - lo) * self.rng.random::<f64>();
                    let positive = self.rng.random::<bool>();
                    e_um += match self.noise.outlier_sense {
                        // Tripped before the beam is cut: short of it along the approach.
                        crate::scenario::OutlierSense::Early => -dir * size,
                        crate::scenario::OutlierSense::Random if positive => size,
                        crate::scenario::OutlierSense::Random => -size,
                    };
                }
                pos[axis] = v + e_um * 1e-3;
                (None, t_trip + self.vm.latency_s())
            }
            _ => {
                pos[axis] = travel.start + dir * travel.max_mm;
                (Some(DetectionStatus::NoTrip), te + travel.max_mm / feed)
            }
        };
        Timed {
            t_ns: self.to_ns(t_det),
            msg: DetectionMsg {
                cycle,
                step: step.label.clone(),
                b_deg: step.b_deg,
                c_deg: step.c_deg,
                axis: step.approach.axis,
                direction: step.approach.direction,
                feed_mm_min: step.approach.feed_mm_min,
                spindle_rpm: rpm,
                tool_id: k.tool_id.clone(),
                x_mm: pos.x,
                y_mm: pos.y,
                z_mm: pos.z,
                status,
            },
        }
    }

    /// The true machine state now, the spindle at `rpm`: what any instrument on this machine
    /// (the tool setter, an R-test) measures.
    pub fn state(&self, rpm: f64) -> MachineState {
        self.vm.state(rpm)
    }

    /// The truth now, the spindle at `rpm`.
    pub fn truth(&self, k: &Kinematics, rpm: f64, cycle: Option<i64>) -> TruthSample {
        self.vm.sample(k, self.now_ns(), rpm, cycle)
    }

    /// The truth at an earlier or later time `t_ns` of a cycle run at `rpm`, from this state.
    pub fn truth_at(&self, k: &Kinematics, t_ns: i64, rpm: f64, cycle: Option<i64>) -> TruthSample {
        let mut v = self.clone();
        v.advance_to(t_ns, rpm);
        v.truth(k, rpm, cycle)
    }

    /// Logged temperatures now: the ambient (if logged) and every logged sensor.
    pub fn temperatures(&self, rpm: f64) -> Vec<(String, f64)> {
        let mut out = Vec::new();
        if self.ambient.logged {
            out.push((
                "ambient".to_string(),
                ambient_at(&self.ambient, self.now_ns()),
            ));
        }
        for (i, name) in self.vm.sensors.names().iter().enumerate() {
            if !self.unlogged.contains(name) {
                out.push((name.clone(), self.vm.sensors.value(i, rpm)));
            }
        }
        out
    }
}

#[derive(Debug, Clone, Copy, PartialEq, PartialOrd)]
enum Event {
    Segment(usize),
    CycleEnd(usize),
    CycleStart(usize),
    Probe(usize, usize),
    Sample,
    Heartbeat,
}

fn ambient_at(a: &crate::scenario::AmbientConfig, t_ns: i64) -> f64 {
    if a.amplitude_k == 0.0 {
        return a.mean_c;
    }
    let hours = units::ns_to_h(t_ns.rem_euclid(units::NS_PER_DAY));
    a.mean_c + a.amplitude_k * (2.0 * std::f64::consts::PI * (hours - a.peak_h) / a.period_h).cos()
}

/// A scenario's timeline: the cycle windows (s from the start) with each cycle's spindle
/// speed and feed, and what the machine does at any time.
struct Timeline<'a> {
    scn: &'a Scenario,
    windows: Vec<(f64, f64)>,
    settings: Vec<(f64, f64)>,
}

impl<'a> Timeline<'a> {
    fn new(scn: &'a Scenario, plan: &Plan, duration_s: f64) -> Self {
        let cycle_len = plan.machine_time_s;
        // Cycle windows, pushed back so that they never overlap.
        let mut windows: Vec<(f64, f64)> = Vec::new();
        for t in scn.cycle_times_min() {
            let mut s = t * 60.0;
            if let Some((_, e)) = windows.last()
                && s < *e
            {
                s = *e;
            }
            if s < duration_s {
                windows.push((s, s + cycle_len));
            }
        }
        let settings: Vec<(f64, f64)> = windows
            .iter()
            .enumerate()
            .map(|(c, (s, _))| {
                scn.cycles.settings(
                    c,
                    s / 60.0,
                    plan.config.spindle_rpm,
                    plan.config.feed_mm_min,
                )
            })
            .collect();
        Timeline {
            scn,
            windows,
            settings,
        }
    }

    fn in_cycle(&self, t: f64) -> Option<usize> {
        self.windows.iter().position(|(s, e)| t >= *s && t < *e)
    }

    fn segment_at(&self, t: f64) -> Option<usize> {
        self.scn.spindle.iter().rposition(|s| s.at_min * 60.0 <= t)
    }

    fn rpm_at(&self, t: f64) -> f64 {
        match self.in_cycle(t) {
            Some(c) => self.settings[c].0,
            None => self
                .segment_at(t)
                .map(|i| self.scn.spindle[i].rpm)
                .unwrap_or(0.0),
        }
    }

    /// The machine's state and program at `t`.
    fn state_at(&self, t: f64) -> (MachineStateKind, Option<String>) {
        match self.in_cycle(t) {
            Some(c) => (
                MachineStateKind::Measuring,
                Some(format!("driftwatch cycle {}", c + 1)),
            ),
            None => match self.segment_at(t) {
                Some(i) => (
                    self.scn.spindle[i].state,
                    self.scn.spindle[i].program.clone(),
                ),
                None => (MachineStateKind::Off, None),
            },
        }
    }

    /// Every event of the run before `duration_s`, in time order: spindle segments, cycle
    /// starts, probes and ends, samples and heartbeats.
    fn events(&self, plan: &Plan, duration_s: f64) -> Vec<(f64, Event)> {
        let mut events: Vec<(f64, Event)> = Vec::new();
        for (i, s) in self.scn.spindle.iter().enumerate() {
            events.push((s.at_min * 60.0, Event::Segment(i)));
        }
        for (c, (s, e)) in self.windows.iter().enumerate() {
            events.push((*s, Event::CycleStart(c)));
            for (i, st) in plan.steps.iter().enumerate() {
                events.push((s + st.t_start_s, Event::Probe(c, i)));
            }
            events.push((*e, Event::CycleEnd(c)));
        }
        let mut t = 0.0;
        while t < duration_s {
            events.push((t, Event::Sample));
            t += self.scn.sample_s;
        }
        let mut t = 0.0;
        while t < duration_s {
            events.push((t, Event::Heartbeat));
            t += 10.0;
        }
        events.retain(|(t, _)| *t >= 0.0 && *t < duration_s);
        events.sort_by(|a, b| {
            a.0.total_cmp(&b.0)
                .then(a.1.partial_cmp(&b.1).unwrap_or(std::cmp::Ordering::Equal))
        });
        events
    }
}

/// A cycle at its end: its truth at the mean time of its `ok` detections, from the snapshot
/// of the virtual machine at the last probe start before then, the spindle at `rpm`.
fn close_cycle(
    mut cy: SimCycle,
    snapshots: &[VirtualMachine],
    k: &Kinematics,
    rpm: f64,
) -> SimCycle {
    let ok = cy
        .detections
        .iter()
        .filter(|d| d.msg.status() == DetectionStatus::Ok)
        .map(|d| d.t_ns);
    let t_ref = driftwatch_core::identify::mean_time_ns(ok);
    let snap = snapshots
        .iter()
        .rev()
        .find(|v| v.now_ns() <= t_ref)
        .or(snapshots.first());
    if let Some(v) = snap {
        cy.truth = v.truth_at(k, t_ref, rpm, Some(cy.number));
    }
    cy
}

/// The virtual machine's true state at the scenario's start, the spindle off (each channel
/// at its starting value): what an instrument on the cold machine measures, e.g. the linear
/// axes for `driftwatch diagonal simulate --scenario`.
pub fn initial_state(scn: &Scenario, k: &Kinematics) -> Result<MachineState, SimError> {
    Ok(Virtual::new(k, scn)?.state(0.0))
}

/// Run a scenario.
pub fn simulate(scn: &Scenario, k: &Kinematics, plan: &Plan) -> Result<Simulation, SimError> {
    let mut vm = VirtualMachine::new(k, scn)?;
    let start_ns = vm.start_ns();
    let to_ns = |t_s: f64| start_ns + (t_s * 1e9).round() as i64;
    let duration_s = scn.duration_min * 60.0;
    let timeline = Timeline::new(scn, plan, duration_s);
    let events = timeline.events(plan, duration_s);

    let mut sim = Simulation {
        info: MachineInfo {
            machine_id: scn.machine_id.clone(),
            kinematics: k.name.clone(),
            software: format!("driftwatch {}", env!("CARGO_PKG_VERSION")),
        },
        states: Vec::new(),
        spindle: Vec::new(),
        temperatures: Vec::new(),
        truth: Vec::new(),
        cycles: Vec::new(),
    };
    let mut now = 0.0;
    let mut last_rpm = f64::NAN;
    let mut last_state: Option<(MachineStateKind, Option<String>)> = None;
    // Snapshots of the virtual machine at each probe start of the open cycle.
    let mut snapshots: Vec<VirtualMachine> = Vec::new();
    let mut open: Option<SimCycle> = None;

    for (te, ev) in events {
        // Every speed change is an event: the speed since `now` held until `te`.
        let t_ns = to_ns(te);
        vm.advance_to(t_ns, timeline.rpm_at(now));
        now = te;
        let rpm_now = timeline.rpm_at(te);
        if rpm_now != last_rpm || (matches!(ev, Event::Heartbeat) && rpm_now > 0.0) {
            sim.spindle.push(Timed {
                t_ns,
                msg: SpindleMsg { rpm: rpm_now },
            });
            last_rpm = rpm_now;
        }
        let state_now = timeline.state_at(te);
        if last_state.as_ref() != Some(&state_now) {
            sim.states.push(Timed {
                t_ns,
                msg: StateMsg {
                    state: state_now.0,
                    program: state_now.1.clone(),
                },
            });
            last_state = Some(state_now);
        }
        match ev {
            Event::Sample => {
                for (sensor, celsius) in vm.temperatures(rpm_now) {
                    sim.temperatures.push(Timed {
                        t_ns,
                        msg: TemperatureMsg { sensor, celsius },
                    });
                }
                sim.truth.push(vm.truth(k, rpm_now, None));
            }
            Event::CycleStart(c) => {
                snapshots.clear();
                open = Some(SimCycle {
                    number: c as i64 + 1,
                    start_ns: t_ns,
                    detections: Vec::new(),
                    truth: vm.truth(k, rpm_now, Some(c as i64 + 1)),
                });
            }
            Event::Probe(c, i) => {
                snapshots.push(vm.clone());
                let mut step = plan.steps[i].clone();
                step.approach.feed_mm_min = timeline.settings[c].1;
                let d = vm.probe(k, &step, c as i64 + 1, rpm_now);
                if let Some(cy) = open.as_mut() {
                    cy.detections.push(d);
                }
            }
            Event::CycleEnd(c) => {
                if let Some(cy) = open.take() {
                    let rpm = timeline.settings[c].0;
                    sim.cycles.push(close_cycle(cy, &snapshots, k, rpm));
                }
            }
            Event::Segment(_) | Event::Heartbeat => {}
        }
    }
    Ok(sim)
}

/// A machine position as a vector (helper for callers building observations).
pub fn detection_position(d: &DetectionMsg) -> Vec3 {
    Vec3::new(d.x_mm, d.y_mm, d.z_mm)
}
