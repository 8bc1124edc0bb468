//! The library of candidate effects the diagnosis searches (docs/physics.md 3 and 4.2), pure code.
//! Each effect is an event-level signature (how one unit of it moves every reading, from the
//! exact measurement model) times a time shape (what drives it: the spindle, a logged
//! temperature, the time of day, the speed, the feed, the sense of the last rotary move). A
//! candidate is one such product; it predicts its footprint on every reading at once, which is
//! what keeps a search from blaming the wrong effect.

use driftwatch_core::units;
use std::collections::BTreeMap;

use serde::Serialize;

use crate::rows::Rows;
use driftwatch_core::error_name::channel_unit;
use driftwatch_thermal::model::{Event, Features, ModelConfig, TemperatureInput};

/// One effect of the library, as `diagnose --list-effects` prints it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Effect {
    /// Stable id (used in `diagnosis.json`).
    pub id: &'static str,
    pub label: &'static str,
    /// The physics it stands for.
    pub physics: &'static str,
    /// Which readings it moves and how (the event-level signature).
    pub signature: &'static str,
    /// The time shapes tried.
    pub shapes: &'static str,
    /// The parameters fitted and their units.
    pub parameters: &'static str,
    /// The change to the measurement plan that separates it from what it can be confused with.
    pub split_by: &'static str,
    /// The parts of that change a plan's own readings can show (any one of them splits it in
    /// principle): advice a plan already follows is not given again ([`advice`]).
    #[serde(skip)]
    pub splits: &'static [PlanFeature],
    /// Largest plausible effect on a reading, um: a larger fitted footprint is refused.
    pub max_um: f64,
    /// Needs at least two days of data (slow or daily terms).
    pub slow: bool,
}

/// The catalogue, in the order of docs/physics.md 3.
pub const EFFECTS: &[Effect] = &[
    Effect {
        id: "skip_latency",
        label: "skip latency x feed",
        physics: "setter filter, NC skip sampling and servo lag: the axis is latched F*t_d further along the approach than where the beam was cut",
        signature: "every reading shifts by F*t_d along its approach; cancels in the patent's sums (y1+y3, x2+x4); constant feed makes it a constant absorbed by the setter and radius calibration",
        shapes: "the feed of each approach (a feed change or two feeds); a step at a time located by likelihood (an NC parameter or firmware change)",
        parameters: "t_d, ms (latency beyond the calibrated one, or its change at the step)",
        split_by: "probe at two feeds",
        splits: &[PlanFeature::TwoFeeds],
        max_um: 50.0,
        slow: false,
    },
    Effect {
        id: "radius_speed",
        label: "effective tool radius vs speed",
        physics: "dynamic runout envelope and detection threshold change with speed (centrifugal growth of a 10-mm carbide tool is only ~3 nm)",
        signature: "lateral readings only, opposite on the two sides: cancels in the sums",
        shapes: "(n/n_ref)^2 at the reading's spindle speed",
        parameters: "radius change at n_ref, um",
        split_by: "probe at two spindle speeds",
        splits: &[PlanFeature::TwoSpeeds],
        max_um: 20.0,
        slow: false,
    },
    Effect {
        id: "radius_change",
        label: "effective tool radius change",
        physics: "a tool change, a chipped or worn edge, a runout change: the effective radius jumps",
        signature: "lateral readings only, opposite on the two sides of the beam: cancels in the sums",
        shapes: "a step at a time located by likelihood",
        parameters: "radius change at the step, um",
        split_by: "probe at two feeds (a latency change moves the readings with the feed, a radius change does not) or from both sides of the beam",
        splits: &[PlanFeature::TwoFeeds, PlanFeature::BothSides],
        max_um: 20.0,
        slow: false,
    },
    Effect {
        id: "spindle_axial_growth",
        label: "spindle axial thermal growth",
        physics: "shaft, holder and tool grow along the spindle axis with spindle heat",
        signature: "a common shift of every z reading, the same as the B axis' Z location error",
        shapes: "spindle heat lags",
        parameters: "gain per lag, um",
        split_by: "a bed-fixed reference artefact, or a prior from a spindle-only test",
        splits: &[],
        max_um: 200.0,
        slow: false,
    },
    Effect {
        id: "speed_shift",
        label: "speed-dependent instant Z shift",
        physics: "centrifugal and Poisson shrink of the shaft, bearing contact angle, draw-in: a z shift within seconds of a speed change",
        signature: "every z reading, like EZ0B, but following the speed at once",
        shapes: "(n/n_ref)^2 at the reading's spindle speed",
        parameters: "shift at n_ref, um",
        split_by: "cycles at two or more spindle speeds",
        splits: &[PlanFeature::TwoSpeeds],
        max_um: 30.0,
        slow: false,
    },
    Effect {
        id: "spindle_xy_drift",
        label: "spindle X/Y drift",
        physics: "headstock and column bending with spindle heat",
        signature: "common shift of the x or y readings, the same as EX0B / EY0C",
        shapes: "spindle heat lags",
        parameters: "gain per lag, um",
        split_by: "a second tool length or a bed-fixed reference",
        splits: &[],
        max_um: 100.0,
        slow: false,
    },
    Effect {
        id: "setter_drift",
        label: "tool-setter mount drift",
        physics: "table and riser expansion move the beam (about 1 um/K)",
        signature: "the beam's place in the table frame: x, y (lateral readings) or z (z readings)",
        shapes: "each logged temperature and its 60/120/240-min lags; 24-h Fourier pair when no temperature explains it; a step at a time located by likelihood (the setter knocked or moved)",
        parameters: "um per K (or um per Fourier term, or um at the step)",
        // In simulation, B = +90 and -90 alone do not split it from the scales, squarenesses
        // and location errors in its time shape (docs/physics.md 4.3); both sides do.
        split_by: "touch the beam from both sides on the lateral approaches (as the patent_both_sides plan does), or a second setter height",
        splits: &[PlanFeature::BothSides],
        max_um: 30.0,
        slow: false,
    },
    Effect {
        id: "squareness",
        label: "linear-axis squareness (static and thermal)",
        physics: "column pitch and roll: the axes are not square, more so as the column warms",
        signature: "enters through lever arms: readings taken at different heights and positions",
        shapes: "constant, spindle heat lags, logged temperatures",
        parameters: "urad (per unit of the shape)",
        split_by: "a second tool length or Z stand-off",
        splits: &[],
        max_um: 30.0,
        slow: false,
    },
    Effect {
        id: "scale_expansion",
        label: "linear-scale thermal expansion",
        physics: "scales grow about 8-12 ppm/K with their temperature",
        signature: "position-proportional: readings scale with their distance to the scale datum",
        shapes: "each logged temperature and its lags; 24-h Fourier pair",
        parameters: "ppm (per K)",
        split_by: "probe at positions farther apart along the axis",
        splits: &[],
        max_um: 30.0,
        slow: false,
    },
    Effect {
        id: "slow_mode",
        label: "a slow structural time constant",
        physics: "heavy castings respond over hours to days; thermal memory from the day before",
        signature: "a location error (any of them) following spindle heat",
        shapes: "spindle heat lags of 1200 and 2400 min (beyond the baseline's 600)",
        parameters: "um per unit heat",
        split_by: "longer records, idle days",
        splits: &[],
        max_um: 100.0,
        slow: true,
    },
    Effect {
        id: "ambient",
        label: "hall temperature (day-night cycle)",
        physics: "the hall warms and cools over the day; the structure follows with a lag",
        signature: "a location error (any of them) following the air",
        shapes: "each logged temperature and its 60/120/240-min lags; 24-h and 12-h Fourier pairs when the air is not logged",
        parameters: "um per K (or um per Fourier term)",
        // What tells a location error following the air from the setter or a scale following
        // it (both sides: in simulation, docs/physics.md 4.3); logging the air names the driver
        // (a Fourier term's statement says so), it does not split the group.
        split_by: "touch the beam from both sides on the lateral approaches (as the patent_both_sides plan does), a bed-fixed reference artefact, or a second setter",
        splits: &[PlanFeature::BothSides],
        max_um: 50.0,
        slow: true,
    },
    Effect {
        id: "b_tilt_heating",
        label: "B-axis heating while tilted",
        physics: "the drive holds the gravity torque at B = +-90; its losses heat the trunnion",
        signature: "a location error following the time spent tilted",
        shapes: "lags (15, 60 min) of the tilt duty (|B| > 45 deg) the detections show",
        parameters: "um (urad) per unit duty",
        split_by: "log the B motor current; vary the time spent tilted",
        splits: &[],
        max_um: 30.0,
        slow: false,
    },
    Effect {
        id: "rotary_backlash",
        label: "rotary backlash by approach direction",
        physics: "lost motion of a worm or gear: the axis stops short by delta/2 on the side it came from",
        signature: "the axis' angle is off by +-delta/2 with the sense of its last move",
        shapes: "the sense of the axis' last move (+1/-1)",
        parameters: "half the backlash, urad",
        split_by: "reach each pose from both senses",
        splits: &[PlanFeature::BothSenses],
        max_um: 20.0,
        slow: false,
    },
    Effect {
        id: "c_indexing",
        label: "C-axis angular positioning error",
        physics: "the C axis' angle error depends on the commanded angle (encoder, gear)",
        signature: "a lateral shift d*eps_C(c) of the probed point, zero where the beam passes the C axis",
        shapes: "first and second harmonic of the C angle (cos, sin)",
        parameters: "urad per harmonic",
        split_by: "put the beam off the C axis (d != 0) or probe more C angles",
        splits: &[],
        max_um: 20.0,
        slow: false,
    },
    Effect {
        id: "location_step",
        label: "a location error changes at one time",
        physics: "a collision, re-clamping, a table or fixture moved: an axis line jumps and stays",
        signature: "a location error (any of them) from one time on",
        shapes: "a step at a time located by likelihood",
        parameters: "um (urad) at the step",
        split_by: "a bed-fixed reference artefact, or a second setter: a location error moves both, the setter only one",
        splits: &[],
        max_um: 100.0,
        slow: false,
    },
    Effect {
        id: "measurement_heating",
        label: "measurement-induced heating",
        physics: "each cycle spins the spindle for minutes: a thermal input the production log does not show",
        signature: "a location error following the cycles' own spins",
        shapes: "the baseline's own response to the cycles' spins that the spindle log lacks (one switch)",
        parameters: "scale of that response (1: the cycles heat the machine as production does)",
        split_by: "log the spindle speed during cycles",
        splits: &[],
        max_um: 100.0,
        slow: false,
    },
    Effect {
        id: "in_cycle_drift",
        label: "in-cycle drift",
        physics: "the machine moves while one cycle's readings are taken (3.5 um/min after a start)",
        signature: "every reading at its own time: the baseline takes each detection at its own timestamp, so this is in the baseline, not a candidate",
        shapes: "built into the baseline",
        parameters: "none",
        split_by: "time-symmetric cycles",
        splits: &[PlanFeature::TimeSymmetric],
        max_um: 0.0,
        slow: false,
    },
    Effect {
        id: "second_mode",
        label: "second thermal mode",
        physics: "the structure has more than one thermal path: a fast one (spindle, shaft) and a slow one (headstock, column), often of opposite sign",
        signature: "displacement recordings: the channel follows a further lag of the spindle heat input",
        shapes: "the spindle heat input (n/n_ref)^gamma through each lag of the 10-pole basis",
        parameters: "um per unit heat input",
        split_by: "runs and stops of different lengths (a mode shows in the shape of the warm-up and of the recovery)",
        splits: &[],
        max_um: 200.0,
        slow: false,
    },
    Effect {
        id: "missing_temperature",
        label: "missing temperature input",
        physics: "a part of the structure heated or cooled by something other than the spindle (motor, coolant, hydraulics, the hall) whose sensor was logged but not used",
        signature: "displacement recordings: the channel follows a logged temperature",
        shapes: "each logged temperature and its 60/120/240-min lags",
        parameters: "um/K",
        split_by: "vary that temperature's source independently of the spindle",
        splits: &[],
        max_um: 200.0,
        slow: false,
    },
    Effect {
        id: "coolant_cycle",
        label: "coolant or chiller cycle",
        physics: "an on-off chiller or coolant temperature controller swings the spindle or structure temperature with a period of minutes to an hour",
        signature: "displacement recordings: a periodic residual that a logged temperature carries at the same period",
        shapes: "each logged temperature less its 60-min lag (its fast swing)",
        parameters: "um/K",
        split_by: "log the coolant temperature; hold the chiller steady",
        splits: &[],
        max_um: 50.0,
        slow: false,
    },
    Effect {
        id: "onset_drift",
        label: "drift after an onset",
        physics: "a part that starts to heat or cool partway through the run and then follows one temperature (a ball screw that starts to work, a door opened, a coolant switched on): nothing before, the temperature's change after",
        signature: "displacement recordings: what the selected terms leave follows a logged temperature's change since some hour",
        shapes: "the located temperature's change since the located onset, (T(t) - T(t_on)) 1[t >= t_on], itself or through a 30/120/480-min lag; without an onset, the temperature itself and its lags",
        parameters: "um/K",
        split_by: "a run where that temperature and time do not move together (its source held constant for a day, or cycled), long enough after the onset for the held-out end",
        splits: &[],
        max_um: 200.0,
        slow: false,
    },
    Effect {
        id: "outliers",
        label: "outliers",
        physics: "coolant mist, chips on the tool, a skipped trigger",
        signature: "single readings far from a robust fit of the baseline (leave-one-out residual beyond 5 sigma); removed before the search and listed",
        shapes: "none",
        parameters: "count",
        split_by: "double touches",
        splits: &[],
        max_um: 0.0,
        slow: false,
    },
];

pub fn effect(id: &str) -> Option<&'static Effect> {
    EFFECTS.iter().find(|e| e.id == id)
}

/// A way of probing that splits effects apart, as far as a plan's readings show it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlanFeature {
    /// Readings at two or more feeds.
    TwoFeeds,
    /// Readings at two or more spindle speeds.
    TwoSpeeds,
    /// The beam touched from both sides along some axis at one pose.
    BothSides,
    /// Some pose reached from both senses of a rotary axis.
    BothSenses,
    /// Each measurement made twice in a cycle (time-symmetric cycles).
    TimeSymmetric,
}

impl PlanFeature {
    /// How `rows` show this feature, when they do.
    pub fn shown_by(self, rows: &Rows) -> Option<String> {
        let distinct = |v: &mut Vec<i64>| {
            v.sort_unstable();
            v.dedup();
            v.len()
        };
        let r = &rows.rows;
        match self {
            PlanFeature::TwoFeeds => {
                let mut f: Vec<i64> = r.iter().map(|x| x.feed_mm_min.round() as i64).collect();
                let n = distinct(&mut f);
                (n >= 2).then(|| format!("probes at {n} feeds"))
            }
            PlanFeature::TwoSpeeds => {
                let mut f: Vec<i64> = r
                    .iter()
                    .filter(|x| x.spindle_rpm > 0.0)
                    .map(|x| x.spindle_rpm.round() as i64)
                    .collect();
                let n = distinct(&mut f);
                (n >= 2).then(|| format!("probes at {n} spindle speeds"))
            }
            PlanFeature::BothSides => {
                // At one pose: opposite approaches at different C angles meet different sides
                // of a beam that turns with C, but each pose then sees one side only.
                let mut seen: BTreeMap<(i64, i64, usize), [bool; 2]> = BTreeMap::new();
                for x in r {
                    let pose = (
                        x.b_deg.round() as i64,
                        x.c_deg.round() as i64,
                        x.axis.index(),
                    );
                    seen.entry(pose).or_default()[usize::from(x.direction > 0)] = true;
                }
                seen.values()
                    .any(|s| s[0] && s[1])
                    .then(|| "touches the beam from both sides at a pose".to_string())
            }
            PlanFeature::BothSenses => {
                let mut seen: BTreeMap<(i64, i64, usize), [bool; 2]> = BTreeMap::new();
                for x in r {
                    for (i, &sense) in x.rotary_sense.iter().enumerate() {
                        if sense != 0 {
                            let pose = (x.b_deg.round() as i64, x.c_deg.round() as i64, i);
                            seen.entry(pose).or_default()[usize::from(sense > 0)] = true;
                        }
                    }
                }
                seen.values()
                    .any(|s| s[0] && s[1])
                    .then(|| "reaches a pose from both senses".to_string())
            }
            PlanFeature::TimeSymmetric => {
                let mut per: BTreeMap<(i64, &str), usize> = BTreeMap::new();
                for x in r {
                    *per.entry((x.cycle, x.step.as_str())).or_default() += 1;
                }
                per.values()
                    .any(|&k| k >= 2)
                    .then(|| "makes each measurement twice in a cycle".to_string())
            }
        }
    }
}

/// The plan change that would split `e` from its look-alikes on a recording with `rows`: its
/// `split_by`, unless the plan already does what splits it, which is then said instead (the
/// same advice again would be no advice).
pub fn advice(e: &Effect, rows: &Rows) -> String {
    match e.splits.iter().find_map(|f| f.shown_by(rows)) {
        Some(done) => format!(
            "this plan already {done}, which splits it in principle but not on these readings (more cycles where it differs, or a larger difference)"
        ),
        None => e.split_by.to_string(),
    }
}

/// One candidate: an effect's signature times a time shape, `columns` (one or a Fourier pair)
/// giving each reading's change per unit of the parameter, um.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    pub effect: &'static str,
    /// `<signature> x <shape>`, unique within a search.
    pub term: String,
    /// The parameter's unit (per unit of the shape).
    pub unit: String,
    pub columns: Vec<Vec<f64>>,
    /// The signature's name (a design parameter or a [`Rows::signatures`] entry).
    pub signature: String,
    /// What kind of time shape multiplies the signature ...
    pub shape_kind: ShapeKind,
    /// ... and the shape itself per row, one vector per column (`columns[j] = signature x
    /// shape[j]`); what another signature would need to explain the term in the same time.
    pub shape: Vec<Vec<f64>>,
    /// Nonlinear parameters profiled to build it (the located time of a step): counted in
    /// its BIC penalty.
    pub profiled: usize,
    /// The located time of a step shape, ns.
    pub step_ns: Option<i64>,
}

/// The kinds of time shape of the library (docs/physics.md 4.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ShapeKind {
    Constant,
    /// The feed of the approach (in the signature itself: the shape is 1).
    Feed,
    Speed2,
    SpindleLag,
    Temperature,
    Fourier,
    Tilt,
    Sense,
    Harmonic,
    Step,
    MissingSpins,
}

/// The signature classes an ambiguity check swaps in, each with the effect it stands for
/// given the time shape. Tool-tip shifts (sx, sy, sz) are not a class: the cycle measures
/// the location errors relative to the tool tip, so they are the location errors.
pub fn signature_classes(rows: &Rows) -> Vec<(&'static str, Vec<String>)> {
    let names = |v: &[&str]| -> Vec<String> {
        v.iter()
            .filter(|n| rows.signature(n).is_some() || rows.param(n).is_some())
            .map(|n| n.to_string())
            .collect()
    };
    let mut out = vec![
        ("latency", names(&["latency"])),
        ("radius", names(&["radius"])),
        ("setter", names(&["setter_x", "setter_y", "setter_z"])),
        ("scale", names(&["kx", "ky", "kz"])),
        ("squareness", names(&["sxy", "sxz", "syz"])),
        ("location", rows.locations.clone()),
    ];
    for s in &rows.signatures {
        if let Some(axis) = s.strip_prefix("angle_") {
            out.push((
                if axis == "C" {
                    "angle_C"
                } else {
                    "angle_other"
                },
                vec![s.clone()],
            ));
        }
    }
    out.retain(|(_, v)| !v.is_empty());
    out
}

/// The effect a signature class stands for under a time shape: only where that effect's
/// physics allows the shape (the shapes the library gives it, [`Effect::shapes`]). `None`:
/// that product is the baseline itself, or nothing of the machine moves so (a tool-setter
/// mount that follows the spindle speed, a scale that flips with the approach sense, a
/// latency that warms with the hall), and it joins no ambiguity group.
pub fn class_effect(class: &str, kind: ShapeKind) -> Option<&'static str> {
    use ShapeKind::*;
    Some(match (class, kind) {
        ("latency", Feed | Step | Constant) => "skip_latency",
        ("radius", Speed2) => "radius_speed",
        ("radius", Step) => "radius_change",
        ("setter", Temperature | Fourier | Step) => "setter_drift",
        ("scale", Temperature | Fourier) => "scale_expansion",
        // Fourier: a 24-h pair stands for a temperature not logged, as for the hall.
        ("squareness", Constant | SpindleLag | Temperature | Fourier) => "squareness",
        ("angle_C" | "angle_other", Sense) => "rotary_backlash",
        ("angle_C", Harmonic) => "c_indexing",
        ("angle_other", Tilt) => "b_tilt_heating",
        ("location", Step) => "location_step",
        ("location", Temperature | Fourier) => "ambient",
        ("location", SpindleLag) => "slow_mode",
        ("location", Tilt) => "b_tilt_heating",
        ("location", Speed2) => "speed_shift",
        ("location", Sense) => "rotary_backlash",
        ("location", Harmonic) => "c_indexing",
        ("location", MissingSpins) => "measurement_heating",
        _ => return None,
    })
}

/// What drives the time shapes, row by row.
#[derive(Debug, Clone, Default)]
pub struct Drivers {
    /// Spindle heat lags of the baseline's pole basis, `[tau][row]`.
    pub spindle: Vec<Vec<f64>>,
    pub spindle_taus_min: Vec<f64>,
    /// Lags beyond the basis (slow mode), `[tau][row]`.
    pub slow: Vec<Vec<f64>>,
    pub slow_taus_min: Vec<f64>,
    /// Logged temperatures minus their first reading and their lags: `(label, [row])`.
    pub temperatures: Vec<(String, Vec<f64>)>,
    /// The cycles' spins missing from the spindle log, as lags of the basis; empty when the
    /// log has them.
    pub missing_spins: Vec<Vec<f64>>,
    /// Lags of the tilt duty, `(tau, [row])`.
    pub tilt: Vec<(f64, Vec<f64>)>,
    /// Hours since the first row (for the Fourier pairs).
    pub hours: Vec<f64>,
    /// Span of the rows, h.
    pub span_h: f64,
}

/// The slow time constants tried beyond the basis, min.
pub const SLOW_TAUS_MIN: [f64; 2] = [1200.0, 2400.0];
/// Lags of every logged temperature tried, min (0: the temperature itself).
pub const TEMPERATURE_TAUS_MIN: [f64; 4] = [0.0, 60.0, 120.0, 240.0];

/// Every sensor as a temperature input with the lags the search tries.
pub fn temperature_inputs(sensors: &[String]) -> Vec<TemperatureInput> {
    sensors
        .iter()
        .map(|s| TemperatureInput {
            sensor: s.clone(),
            taus_min: TEMPERATURE_TAUS_MIN.to_vec(),
        })
        .collect()
}

/// Evaluate first-order lags (ZOH exact) of an input given as steps `(t_ns, u)` at sorted
/// `times`, from zero before the first step.
fn lags_of_steps(steps: &[(i64, f64)], times: &[i64], tau_min: f64) -> Vec<f64> {
    let mut order: Vec<usize> = (0..times.len()).collect();
    order.sort_by_key(|i| times[*i]);
    let mut out = vec![0.0; times.len()];
    let (mut x, mut u, mut t) = (0.0, 0.0, i64::MIN);
    let mut k = 0;
    let step = |x: &mut f64, t: &mut i64, to: i64, u: f64| {
        if *t != i64::MIN && to > *t {
            let a = (-((to - *t) as f64 / 1e9) / (tau_min * 60.0)).exp();
            *x = a * *x + (1.0 - a) * u;
        }
        *t = to;
    };
    for i in order {
        while k < steps.len() && steps[k].0 <= times[i] {
            step(&mut x, &mut t, steps[k].0, u);
            u = steps[k].1;
            k += 1;
        }
        step(&mut x, &mut t, times[i], u);
        out[i] = x;
    }
    out
}

impl Drivers {
    /// The drivers of `rows` from the spindle log (every speed change) and the temperature
    /// log (`(t_ns, sensor, celsius)`, any order).
    pub fn new(
        rows: &Rows,
        spindle: &[Event],
        temperatures: &[Event],
        cfg: &ModelConfig,
    ) -> Drivers {
        let times: Vec<i64> = rows.rows.iter().map(|r| r.t_ns).collect();
        let t0 = times.iter().copied().min().unwrap_or(0);
        let t1 = times.iter().copied().max().unwrap_or(0);
        let sensors = driftwatch_thermal::model::sensors_of(temperatures);
        let full = ModelConfig {
            taus_min: cfg.taus_min.iter().copied().chain(SLOW_TAUS_MIN).collect(),
            temperatures: temperature_inputs(&sensors),
            instant_speed: false,
            ..cfg.clone()
        };
        let mut events: Vec<&Event> = spindle.iter().chain(temperatures).collect();
        events.sort_by_key(|e| e.t_ns());
        let start = events.first().map_or(t0, |e| e.t_ns()).min(t0);
        let mut f = Features::new(&full, &BTreeMap::new(), start);
        let mut order: Vec<usize> = (0..times.len()).collect();
        order.sort_by_key(|i| times[*i]);
        let ncol = full.columns().len();
        let mut x = vec![vec![0.0; times.len()]; ncol];
        let mut k = 0;
        for &i in &order {
            while k < events.len() && events[k].t_ns() <= times[i] {
                f.apply(events[k]);
                k += 1;
            }
            f.advance_to(times[i]);
            for (c, v) in f.row().iter().enumerate() {
                x[c][i] = *v;
            }
        }
        let nb = cfg.taus_min.len();
        let mut cols = x.into_iter().skip(1);
        let spindle_lags: Vec<Vec<f64>> = cols.by_ref().take(nb).collect();
        let slow: Vec<Vec<f64>> = cols.by_ref().take(SLOW_TAUS_MIN.len()).collect();
        let mut temps = Vec::new();
        for s in &sensors {
            for tau in TEMPERATURE_TAUS_MIN {
                let label = if tau == 0.0 {
                    s.clone()
                } else {
                    format!("{s} lag {tau} min")
                };
                temps.push((label, cols.next().unwrap_or_default()));
            }
        }

        // The cycles' own spins, from the rows: a cycle turns at its detections' speed from
        // 30 s before its first detection to its last. When the log shows another speed at
        // most detections, it lacks them: the candidate is the lags of the corrected log
        // minus those of the log.
        let mut cycles: BTreeMap<i64, (i64, i64, f64)> = BTreeMap::new();
        for r in &rows.rows {
            let e = cycles
                .entry(r.cycle)
                .or_insert((r.t_ns, r.t_ns, r.spindle_rpm));
            e.0 = e.0.min(r.t_ns);
            e.1 = e.1.max(r.t_ns);
        }
        let logged: Vec<(i64, f64)> = spindle
            .iter()
            .filter_map(|e| match e {
                Event::Spindle { t_ns, rpm } => Some((*t_ns, *rpm)),
                _ => None,
            })
            .collect();
        let logged_at = |t: i64| {
            let k = logged.partition_point(|(s, _)| *s <= t);
            if k == 0 { 0.0 } else { logged[k - 1].1 }
        };
        let off = rows
            .rows
            .iter()
            .filter(|r| {
                (logged_at(r.t_ns) - r.spindle_rpm).abs() > 0.01 * r.spindle_rpm.abs().max(1.0)
            })
            .count();
        let heat = driftwatch_core::thermal::InputConfig {
            n_ref_rpm: cfg.n_ref_rpm,
            gamma: cfg.gamma,
            t_ref_c: 20.0,
        };
        let missing_spins = if off * 2 > rows.rows.len() {
            let lead = 30_000_000_000;
            let windows: Vec<(i64, i64, f64)> = cycles
                .values()
                .map(|(a, b, r)| (a - lead, *b, *r))
                .collect();
            let inside = |t: i64| windows.iter().any(|(a, b, _)| t >= *a && t < *b);
            let mut corrected: Vec<(i64, f64)> = logged
                .iter()
                .filter(|(t, _)| !inside(*t))
                .map(|(t, r)| (*t, heat.heat(*r)))
                .collect();
            for (a, b, r) in &windows {
                corrected.push((*a, heat.heat(*r)));
                corrected.push((*b, heat.heat(logged_at(*b))));
            }
            corrected.sort_by_key(|s| s.0);
            let as_logged: Vec<(i64, f64)> =
                logged.iter().map(|(t, r)| (*t, heat.heat(*r))).collect();
            cfg.taus_min
                .iter()
                .map(|tau| {
                    let a = lags_of_steps(&corrected, &times, *tau);
                    let b = lags_of_steps(&as_logged, &times, *tau);
                    a.iter().zip(&b).map(|(x, y)| x - y).collect()
                })
                .collect()
        } else {
            Vec::new()
        };

        // Time spent tilted, as the detections show it.
        let mut tilt_steps: Vec<(i64, f64)> = Vec::new();
        let mut by_time: Vec<&crate::rows::DetectionRow> = rows.rows.iter().collect();
        by_time.sort_by_key(|r| r.t_ns);
        for w in by_time.windows(2) {
            let tilted = if w[0].b_deg.abs() > 45.0 { 1.0 } else { 0.0 };
            tilt_steps.push((w[0].t_ns, tilted));
            if w[1].cycle != w[0].cycle {
                tilt_steps.push((w[0].t_ns + 1, 0.0));
            }
        }
        let tilt = if tilt_steps.iter().any(|s| s.1 > 0.0) {
            [15.0, 60.0]
                .iter()
                .map(|tau| (*tau, lags_of_steps(&tilt_steps, &times, *tau)))
                .collect()
        } else {
            Vec::new()
        };

        Drivers {
            spindle: spindle_lags,
            spindle_taus_min: cfg.taus_min.clone(),
            slow,
            slow_taus_min: SLOW_TAUS_MIN.to_vec(),
            temperatures: temps,
            missing_spins,
            tilt,
            hours: times.iter().map(|t| units::ns_to_h(t - t0)).collect(),
            span_h: units::ns_to_h(t1 - t0),
        }
    }
}

/// Every candidate of the library for these rows and drivers. `n_ref_rpm` scales the speed
/// shapes.
pub fn candidates(rows: &Rows, d: &Drivers, n_ref_rpm: f64) -> Vec<Candidate> {
    let mut out = Vec::new();
    spindle_candidates(rows, d, n_ref_rpm, &mut out);
    let f24 = fourier(&d.hours, 24.0);
    let f12 = fourier(&d.hours, 12.0);
    class_candidates(rows, d, &f24, &mut out);
    location_candidates(rows, d, [&f24, &f12], &mut out);
    rotary_candidates(rows, &mut out);
    out
}

/// The candidate `signature` (column `s`) times the time shape `shape` (columns `g`).
fn candidate(
    effect: &'static str,
    (signature, shape): (&str, &str),
    unit: &str,
    kind: ShapeKind,
    s: &[f64],
    g: Vec<&[f64]>,
) -> Candidate {
    let times =
        |s: &[f64], g: &[f64]| -> Vec<f64> { s.iter().zip(g).map(|(a, b)| a * b).collect() };
    Candidate {
        effect,
        term: format!("{signature} x {shape}"),
        unit: unit.to_string(),
        columns: g.iter().map(|g| times(s, g)).collect(),
        signature: signature.to_string(),
        shape_kind: kind,
        shape: g.iter().map(|g| g.to_vec()).collect(),
        profiled: 0,
        step_ns: None,
    }
}

/// A Fourier pair of period `period_h` at `hours`.
fn fourier(hours: &[f64], period_h: f64) -> [Vec<f64>; 2] {
    let w = std::f64::consts::TAU / period_h;
    [
        hours.iter().map(|h| (w * h).cos()).collect(),
        hours.iter().map(|h| (w * h).sin()).collect(),
    ]
}

fn spindle_lag_label(tau: f64) -> String {
    format!("spindle lag {tau} min")
}

/// Skip latency by feed, the radius and the spindle's axial shift by speed, and the
/// spindle's growth and drift in the baseline's spindle lags.
fn spindle_candidates(rows: &Rows, d: &Drivers, n_ref_rpm: f64, out: &mut Vec<Candidate>) {
    use ShapeKind::*;
    let sig = |name: &str| signature_column(rows, name);
    let ones = vec![1.0; rows.rows.len()];
    let speed2: Vec<f64> = rows
        .rows
        .iter()
        .map(|r| (r.spindle_rpm / n_ref_rpm).powi(2))
        .collect();
    if let Some(s) = sig("latency") {
        out.push(candidate(
            "skip_latency",
            ("latency", "feed"),
            "ms",
            Feed,
            &s,
            vec![&ones],
        ));
    }
    if let Some(s) = sig("radius") {
        out.push(candidate(
            "radius_speed",
            ("radius", "(n/n_ref)^2"),
            "um",
            Speed2,
            &s,
            vec![&speed2],
        ));
    }
    for (sname, effect) in [
        ("sz", "spindle_axial_growth"),
        ("sx", "spindle_xy_drift"),
        ("sy", "spindle_xy_drift"),
    ] {
        if let Some(s) = sig(sname) {
            for (tau, g) in d.spindle_taus_min.iter().zip(&d.spindle) {
                out.push(candidate(
                    effect,
                    (sname, &spindle_lag_label(*tau)),
                    "um",
                    SpindleLag,
                    &s,
                    vec![g],
                ));
            }
        }
    }
    if let Some(s) = sig("sz") {
        out.push(candidate(
            "speed_shift",
            ("sz", "(n/n_ref)^2"),
            "um",
            Speed2,
            &s,
            vec![&speed2],
        ));
    }
}

/// The unit of a signature class member.
fn class_unit(name: &str) -> &'static str {
    crate::rows::SIGNATURES
        .iter()
        .find(|(n, _)| *n == name)
        .map_or(
            if name.starts_with("angle_") {
                "urad"
            } else {
                "um"
            },
            |(_, u)| *u,
        )
}

/// The setter's drift, the scales' expansion and the squareness: each signature by every
/// logged temperature, and the 24-h pair (squareness: a constant and the spindle lags).
fn class_candidates(rows: &Rows, d: &Drivers, f24: &[Vec<f64>; 2], out: &mut Vec<Candidate>) {
    use ShapeKind::*;
    let ones = vec![1.0; rows.rows.len()];
    for (effect, names) in [
        ("setter_drift", &["setter_x", "setter_y", "setter_z"][..]),
        ("scale_expansion", &["kx", "ky", "kz"][..]),
        ("squareness", &["sxy", "sxz", "syz"][..]),
    ] {
        for name in names {
            let Some(s) = signature_column(rows, name) else {
                continue;
            };
            let unit = class_unit(name);
            for (label, g) in &d.temperatures {
                out.push(candidate(
                    effect,
                    (name, label),
                    &format!("{unit}/K"),
                    Temperature,
                    &s,
                    vec![g],
                ));
            }
            if effect == "squareness" {
                out.push(candidate(
                    effect,
                    (name, "constant"),
                    unit,
                    Constant,
                    &s,
                    vec![&ones],
                ));
                for (tau, g) in d.spindle_taus_min.iter().zip(&d.spindle) {
                    out.push(candidate(
                        effect,
                        (name, &spindle_lag_label(*tau)),
                        unit,
                        SpindleLag,
                        &s,
                        vec![g],
                    ));
                }
            } else {
                out.push(candidate(
                    effect,
                    (name, "24-h Fourier pair"),
                    unit,
                    Fourier,
                    &s,
                    vec![&f24[0], &f24[1]],
                ));
            }
        }
    }
}

/// Every location error by the slow modes, every logged temperature, the 24-h and 12-h pairs
/// (`[f24, f12]`) and the tilt duty's lags.
fn location_candidates(
    rows: &Rows,
    d: &Drivers,
    [f24, f12]: [&[Vec<f64>; 2]; 2],
    out: &mut Vec<Candidate>,
) {
    use ShapeKind::*;
    for p in &rows.locations {
        let Some(s) = signature_column(rows, p) else {
            continue;
        };
        let unit = channel_unit(p);
        for (tau, g) in d.slow_taus_min.iter().zip(&d.slow) {
            out.push(candidate(
                "slow_mode",
                (p, &spindle_lag_label(*tau)),
                unit,
                SpindleLag,
                &s,
                vec![g],
            ));
        }
        for (label, g) in &d.temperatures {
            out.push(candidate(
                "ambient",
                (p, label),
                &format!("{unit}/K"),
                Temperature,
                &s,
                vec![g],
            ));
        }
        for (pair, f) in [("24-h Fourier pair", f24), ("12-h Fourier pair", f12)] {
            out.push(candidate(
                "ambient",
                (p, pair),
                unit,
                Fourier,
                &s,
                vec![&f[0], &f[1]],
            ));
        }
        for (tau, g) in &d.tilt {
            out.push(candidate(
                "b_tilt_heating",
                (p, &format!("tilt duty lag {tau} min")),
                unit,
                Tilt,
                &s,
                vec![g],
            ));
        }
    }
}

/// Each rotary axis' backlash by its approach sense, and C's indexing error in its first two
/// harmonics.
fn rotary_candidates(rows: &Rows, out: &mut Vec<Candidate>) {
    use ShapeKind::*;
    for (i, name) in rows.signatures.iter().enumerate() {
        let Some(axis) = name.strip_prefix("angle_") else {
            continue;
        };
        let s = signature_column(rows, name).unwrap_or_default();
        let sense: Vec<f64> = rows
            .rows
            .iter()
            .map(|r| f64::from(r.rotary_sense[i - crate::rows::SIGNATURES.len()]))
            .collect();
        out.push(candidate(
            "rotary_backlash",
            (name, &format!("{axis} approach sense")),
            "urad",
            Sense,
            &s,
            vec![&sense],
        ));
        if axis == "C" {
            for h in [1.0, 2.0] {
                let c: Vec<f64> = rows
                    .rows
                    .iter()
                    .map(|r| (h * r.c_deg.to_radians()).cos())
                    .collect();
                let sn: Vec<f64> = rows
                    .rows
                    .iter()
                    .map(|r| (h * r.c_deg.to_radians()).sin())
                    .collect();
                out.push(candidate(
                    "c_indexing",
                    (name, &format!("harmonic {h} of C")),
                    "urad",
                    Harmonic,
                    &s,
                    vec![&c, &sn],
                ));
            }
        }
    }
}

/// The signatures that can change at one time, with their effect and unit: skip latency,
/// radius, the setter's place and every location error.
pub fn step_signatures(rows: &Rows) -> Vec<(&'static str, String)> {
    let mut out: Vec<(&'static str, String)> = Vec::new();
    for (effect, name) in [
        ("skip_latency", "latency"),
        ("radius_change", "radius"),
        ("setter_drift", "setter_x"),
        ("setter_drift", "setter_y"),
        ("setter_drift", "setter_z"),
    ] {
        if rows.signature(name).is_some() {
            out.push((effect, name.to_string()));
        }
    }
    for p in &rows.locations {
        out.push(("location_step", p.clone()));
    }
    out
}

/// The column of one signature (a design parameter or a signature column), um per unit.
pub fn signature_column(rows: &Rows, name: &str) -> Option<Vec<f64>> {
    if let Some(j) = rows.param(name) {
        return Some(rows.rows.iter().map(|r| r.sensitivity[j]).collect());
    }
    let j = rows.signature(name)?;
    Some(rows.rows.iter().map(|r| r.signature[j]).collect())
}

/// The unit of one signature.
pub fn signature_unit(name: &str) -> &'static str {
    crate::rows::SIGNATURES
        .iter()
        .find(|(n, _)| *n == name)
        .map_or(
            if name.starts_with("angle_") || channel_unit(name) == "urad" {
                "urad"
            } else {
                "um"
            },
            |(_, u)| *u,
        )
}

#[cfg(test)]
mod tests {
    use super::{PlanFeature, advice, effect};
    use crate::rows::{DetectionRow, Rows};
    use driftwatch_core::measurement::Axis;

    fn row(cycle: i64, step: &str, feed: f64, rpm: f64, b: f64, dir: i8) -> DetectionRow {
        DetectionRow {
            t_ns: cycle * 1_800_000_000_000,
            cycle,
            step: step.into(),
            b_deg: b,
            c_deg: 0.0,
            axis: Axis::X,
            direction: dir,
            feed_mm_min: feed,
            spindle_rpm: rpm,
            t_in_cycle_s: 0.0,
            rotary_sense: Default::default(),
            deviation_um: 0.0,
            sensitivity: Vec::new(),
            signature: Vec::new(),
        }
    }

    fn rows(rows: Vec<DetectionRow>) -> Rows {
        Rows {
            params: Vec::new(),
            locations: Vec::new(),
            signatures: Vec::new(),
            rows,
        }
    }

    /// Advice is what the plan does not do yet: "probe at two feeds" on a one-feed plan, and on
    /// a plan that already has two feeds a statement that it does; likewise for speeds.
    #[test]
    fn advice_already_followed_by_the_plan_is_not_given_again() {
        let latency = effect("skip_latency").unwrap();
        let speed = effect("radius_speed").unwrap();
        let one = rows(vec![
            row(1, "a", 100.0, 8000.0, 0.0, 1),
            row(2, "a", 100.0, 8000.0, 0.0, 1),
        ]);
        let two = rows(vec![
            row(1, "a", 100.0, 8000.0, 0.0, 1),
            row(2, "a", 200.0, 20000.0, 0.0, -1),
        ]);
        assert_eq!(advice(latency, &one), latency.split_by);
        assert_eq!(advice(speed, &one), speed.split_by);
        assert!(
            advice(latency, &two).contains("already probes at 2 feeds"),
            "{}",
            advice(latency, &two)
        );
        assert!(advice(speed, &two).contains("already probes at 2 spindle speeds"));
        assert!(PlanFeature::BothSides.shown_by(&two).is_some());
        assert!(PlanFeature::BothSides.shown_by(&one).is_none());
        assert!(PlanFeature::TimeSymmetric.shown_by(&one).is_none());
        let twice = rows(vec![
            row(1, "a", 100.0, 0.0, 90.0, 1),
            row(1, "a", 100.0, 0.0, -90.0, 1),
        ]);
        assert!(PlanFeature::TimeSymmetric.shown_by(&twice).is_some());
        // An effect no plan feature splits keeps its advice.
        let squareness = effect("squareness").unwrap();
        assert_eq!(advice(squareness, &two), squareness.split_by);
        // The setter and the hall's effects: both sides of the beam.
        let setter = effect("setter_drift").unwrap();
        assert_eq!(advice(setter, &one), setter.split_by);
        assert!(
            advice(setter, &two).contains("already touches the beam from both sides at a pose")
        );
    }
}
