//! One measurement cycle from detections to a result: grouping by cycle, validation of every
//! detection (finite values, duplicates, failed approaches, missing steps, plausibility
//! against the nominal geometry), identification, and the `/cycle/result` message. A cycle
//! that fails any check is rejected with every reason; other cycles go on.

use std::collections::BTreeMap;

use serde::Serialize;

use crate::geometry::Vec3;
use crate::identify::{Identifier, Observation, Solution, SolveOptions, mean_time_ns};
use crate::kinematics::Kinematics;
use crate::measurement::{Approach, Axis, latched};
use crate::plan::{Plan, Step};
use crate::recording::{
    CycleResultMsg, DetectionIssue, DetectionMsg, DetectionStatus, ResultStatus, Timed,
};

/// What a detection measured, by its content: the pose (angles modulo 360 deg, to 0.001 deg),
/// the moving axis and its direction, and the feed (to 0.01 mm/min). The contract calls `step`
/// a free label, so a writer may repeat a label, retry an approach under its label or use a
/// labelling of its own: this key, not the label, says which measurement a detection is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct MeasurementKey {
    b_mdeg: i64,
    c_mdeg: i64,
    axis: Axis,
    direction: i8,
    feed_cmm_min: i64,
}

/// An angle in millidegrees, in (-180000, 180000].
fn pose_mdeg(deg: f64) -> i64 {
    let m = ((deg * 1e3).round() as i64).rem_euclid(360_000);
    if m > 180_000 { m - 360_000 } else { m }
}

impl MeasurementKey {
    pub fn new(b_deg: f64, c_deg: f64, approach: &Approach) -> Self {
        MeasurementKey {
            b_mdeg: pose_mdeg(b_deg),
            c_mdeg: pose_mdeg(c_deg),
            axis: approach.axis,
            direction: approach.direction.signum(),
            feed_cmm_min: (approach.feed_mm_min * 100.0).round() as i64,
        }
    }

    pub fn of_detection(m: &DetectionMsg) -> Self {
        MeasurementKey {
            b_mdeg: pose_mdeg(m.b_deg),
            c_mdeg: pose_mdeg(m.c_deg),
            axis: m.axis,
            direction: m.direction.signum(),
            feed_cmm_min: (m.feed_mm_min * 100.0).round() as i64,
        }
    }

    pub fn of_step(s: &Step) -> Self {
        Self::new(s.b_deg, s.c_deg, &s.approach)
    }
}

impl std::fmt::Display for MeasurementKey {
    /// `B-90C90/x- F100`: the pose, the approach and the feed.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let deg = |m: i64| {
            let s = format!("{:.3}", m as f64 / 1e3);
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        };
        write!(
            f,
            "B{}C{}/{}{} F{}",
            deg(self.b_mdeg),
            deg(self.c_mdeg),
            self.axis.name(),
            if self.direction < 0 { '-' } else { '+' },
            {
                let s = format!("{:.2}", self.feed_cmm_min as f64 / 100.0);
                s.trim_end_matches('0').trim_end_matches('.').to_string()
            }
        )
    }
}

/// How many tripped detections of each measurement a cycle must have.
pub type ExpectedMeasurements = BTreeMap<MeasurementKey, usize>;

/// The measurements of a plan, each as often as the plan makes it.
pub fn plan_measurements(plan: &Plan) -> ExpectedMeasurements {
    let mut m = ExpectedMeasurements::new();
    for s in &plan.steps {
        *m.entry(MeasurementKey::of_step(s)).or_default() += 1;
    }
    m
}

#[derive(Debug, Clone)]
pub struct CycleChecks {
    /// Largest distance of a reading from its nominal value before it is refused, mm.
    pub max_deviation_mm: f64,
    /// The measurements every cycle must have, by content (from the plan, or inferred from
    /// the recording); labels are not compared.
    pub expected: Option<ExpectedMeasurements>,
    pub solve: SolveOptions,
}

impl CycleChecks {
    pub fn new(k: &Kinematics) -> Self {
        CycleChecks {
            max_deviation_mm: 1.0,
            expected: None,
            solve: SolveOptions::new(k.setter.sigma_um),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct CycleOutcome {
    pub cycle: i64,
    pub t_ref_ns: i64,
    pub status: ResultStatus,
    pub reason: Option<String>,
    pub n_detections: usize,
    /// What was set aside without rejecting the cycle (a failed approach its retry replaced,
    /// a message received twice).
    pub notes: Vec<String>,
    /// The linear-axis geometry the solve started from (`Kinematics::linear_source`).
    pub geometry: Option<String>,
    #[serde(skip)]
    pub solution: Option<Solution>,
}

impl CycleOutcome {
    pub fn is_ok(&self) -> bool {
        self.status == ResultStatus::Ok
    }

    /// The `/cycle/result` message (errors and sigma null when there is no solution).
    pub fn message(&self) -> CycleResultMsg {
        let s = self.solution.as_ref();
        let map = |f: fn(&crate::identify::Estimate) -> f64| {
            s.map(|s| {
                s.errors
                    .iter()
                    .map(|e| (e.name.clone(), f(e)))
                    .collect::<BTreeMap<_, _>>()
            })
        };
        CycleResultMsg {
            cycle: self.cycle,
            t_ns: self.t_ref_ns,
            status: self.status,
            reason: self.reason.clone(),
            errors: map(|e| e.value),
            sigma: map(|e| e.sigma),
            residual_rms_um: s.map(|s| s.residual_rms_um()),
            chi2: s.map(|s| s.chi2),
            dof: s.map(|s| s.dof),
            n_detections: Some(self.n_detections),
            nuisance: s.map(|s| {
                s.nuisance
                    .iter()
                    .map(|e| (e.name.clone(), e.value))
                    .collect()
            }),
            redundancy_um: s.map(|s| s.redundancy_um.clone()),
            chi2_point: None,
            notes: (!self.notes.is_empty()).then(|| self.notes.clone()),
            geometry: self.geometry.clone(),
        }
    }
}

/// Detections that could not be assigned to a cycle, with why.
#[derive(Debug, Clone, Default)]
pub struct Unassigned {
    pub problems: Vec<String>,
}

type Entry = Timed<Result<DetectionMsg, DetectionIssue>>;

/// Group detections by cycle number, in increasing cycle order.
pub fn group_by_cycle(detections: &[Entry]) -> (BTreeMap<i64, Vec<Entry>>, Unassigned) {
    let mut groups: BTreeMap<i64, Vec<Entry>> = BTreeMap::new();
    let mut un = Unassigned::default();
    for d in detections {
        let cycle = match &d.msg {
            Ok(m) => Some(m.cycle),
            Err(i) => i.cycle,
        };
        match cycle {
            Some(c) => groups.entry(c).or_default().push(d.clone()),
            None => un.problems.push(format!(
                "a /probe/detection message at t = {} ns has no readable cycle number: {}",
                d.t_ns,
                d.msg
                    .as_ref()
                    .err()
                    .map(|i| i.message.as_str())
                    .unwrap_or("")
            )),
        }
    }
    (groups, un)
}

/// The tripped measurements of one cycle's readable detections, with how often each tripped.
fn tripped(entries: &[Entry]) -> ExpectedMeasurements {
    let mut tally = Tally::default();
    for e in entries {
        if let Ok(d) = &e.msg {
            tally.add(e.t_ns, d);
        }
    }
    tally.counts
}

/// The measurements a cycle has tripped so far, each delivered reading counted once (the same
/// message at the same time twice is a retried upload): the one rule by which the NC door
/// closes a cycle and the solver finds it complete.
#[derive(Debug, Clone, Default)]
pub struct Tally {
    counts: ExpectedMeasurements,
    seen: Vec<(i64, DetectionMsg)>,
}

impl Tally {
    /// Count a reading if it tripped and was not counted before.
    pub fn add(&mut self, t_ns: i64, d: &DetectionMsg) {
        if d.status() != DetectionStatus::Ok || self.seen.iter().any(|(t, m)| *t == t_ns && m == d)
        {
            return;
        }
        self.seen.push((t_ns, d.clone()));
        *self
            .counts
            .entry(MeasurementKey::of_detection(d))
            .or_default() += 1;
    }

    /// The expected measurements tripped fewer times than needed, with the counts.
    pub fn short_of<'a>(
        &'a self,
        expected: &'a ExpectedMeasurements,
    ) -> impl Iterator<Item = (&'a MeasurementKey, usize, usize)> + 'a {
        expected.iter().filter_map(|(key, need)| {
            let got = self.counts.get(key).copied().unwrap_or(0);
            (got < *need).then_some((key, got, *need))
        })
    }

    /// Every expected measurement has tripped as often as needed.
    pub fn covers(&self, expected: &ExpectedMeasurements) -> bool {
        self.short_of(expected).next().is_none()
    }
}

/// The measurements shared by most cycles (at least two), to check the others against.
pub fn infer_expected(groups: &BTreeMap<i64, Vec<Entry>>) -> Option<(ExpectedMeasurements, usize)> {
    let mut counts: BTreeMap<ExpectedMeasurements, usize> = BTreeMap::new();
    for entries in groups.values() {
        *counts.entry(tripped(entries)).or_default() += 1;
    }
    counts
        .into_iter()
        .filter(|(s, n)| *n >= 2 && !s.is_empty())
        .max_by_key(|(s, n)| (*n, s.values().sum::<usize>()))
}

pub fn observation(k: &Kinematics, t_ns: i64, m: &DetectionMsg) -> Observation {
    Observation {
        label: m.step.clone(),
        angles: k.angles_from_fields(m.b_deg, m.c_deg),
        approach: Approach {
            axis: m.axis,
            direction: m.direction,
            feed_mm_min: m.feed_mm_min,
        },
        position: Vec3::new(m.x_mm, m.y_mm, m.z_mm),
        t_ns,
    }
}

/// Validate and solve one cycle.
pub fn process_cycle(
    k: &Kinematics,
    cycle: i64,
    entries: &[Entry],
    checks: &CycleChecks,
) -> CycleOutcome {
    let mut reasons: Vec<String> = Vec::new();
    let mut notes: Vec<String> = Vec::new();
    let unique = readable_once(entries, &mut reasons, &mut notes);
    let ok = tripped_or_retried(&unique, &mut reasons, &mut notes);
    if let Some(expected) = &checks.expected
        && let Some(missing) = missing_measurements(expected, &ok)
    {
        reasons.push(missing);
    }
    check_values(k, &ok, checks.max_deviation_mm, &mut reasons);
    let times = ok.iter().map(|(t, _)| *t);
    let t_ref = if times.clone().next().is_some() {
        mean_time_ns(times)
    } else {
        mean_time_ns(entries.iter().map(|e| e.t_ns))
    };
    let mut outcome = CycleOutcome {
        cycle,
        t_ref_ns: t_ref,
        status: ResultStatus::Rejected,
        reason: None,
        n_detections: entries.len(),
        notes,
        geometry: k.linear_source.clone(),
        solution: None,
    };
    if !reasons.is_empty() {
        outcome.reason = Some(reasons.join("; "));
        return outcome;
    }
    let obs: Vec<Observation> = ok.iter().map(|(t, m)| observation(k, *t, m)).collect();
    match Identifier::new(k, &obs, &checks.solve).and_then(|id| id.solve(&obs)) {
        Ok(sol) => {
            outcome.t_ref_ns = sol.t_ref_ns;
            outcome.status = ResultStatus::Ok;
            outcome.solution = Some(sol);
        }
        Err(e) => outcome.reason = Some(e.to_string()),
    }
    outcome
}

/// The readable detections of a cycle in time order, each delivered message once; a
/// detection that cannot be read is a reason to reject the cycle.
fn readable_once<'a>(
    entries: &'a [Entry],
    reasons: &mut Vec<String>,
    notes: &mut Vec<String>,
) -> Vec<(i64, &'a DetectionMsg)> {
    let mut readable: Vec<(i64, &DetectionMsg)> = Vec::new();
    for e in entries {
        match &e.msg {
            Err(issue) => reasons.push(format!(
                "step '{}': {}",
                issue.step.as_deref().unwrap_or("?"),
                issue.message
            )),
            Ok(m) => readable.push((e.t_ns, m)),
        }
    }
    // The same message at the same time twice is one reading delivered twice (a retried
    // upload), not a second measurement: counted once.
    readable.sort_by_key(|(t, _)| *t);
    let mut unique: Vec<(i64, &DetectionMsg)> = Vec::with_capacity(readable.len());
    for (t, m) in readable {
        if unique.iter().any(|(t2, m2)| *t2 == t && *m2 == m) {
            notes.push(format!(
                "step '{}' at t = {t} ns received twice: counted once",
                m.step
            ));
        } else {
            unique.push((t, m));
        }
    }
    unique
}

/// The detections that tripped; an approach that did not trip is a reason to reject the
/// cycle unless it was retried at once.
fn tripped_or_retried<'a>(
    unique: &[(i64, &'a DetectionMsg)],
    reasons: &mut Vec<String>,
    notes: &mut Vec<String>,
) -> Vec<(i64, &'a DetectionMsg)> {
    // A failed approach retried at once (the next approaches are the same measurement, and one
    // of them trips) is replaced by its retry. Any other failed approach rejects the cycle: a
    // trip of the same measurement later in the cycle is another pass of the plan, not a retry.
    let mut ok: Vec<(i64, &DetectionMsg)> = Vec::with_capacity(unique.len());
    for (i, (t, m)) in unique.iter().enumerate() {
        if m.status() == DetectionStatus::Ok {
            ok.push((*t, m));
            continue;
        }
        let key = MeasurementKey::of_detection(m);
        let s = if m.status() == DetectionStatus::NoTrip {
            "no_trip"
        } else {
            "aborted"
        };
        let retried = unique[i + 1..]
            .iter()
            .take_while(|(_, next)| MeasurementKey::of_detection(next) == key)
            .any(|(_, next)| next.status() == DetectionStatus::Ok);
        if retried {
            notes.push(format!(
                "step '{}' ({key}) did not trip ({s}) and was retried: the retry replaces it",
                m.step
            ));
        } else {
            reasons.push(format!(
                "step '{}' ({key}) did not trip ({s}): broken tool, blocked beam or wrong tool?",
                m.step
            ));
        }
    }
    ok
}

/// The expected measurements the tripped detections fall short of, as a reason.
fn missing_measurements(
    expected: &ExpectedMeasurements,
    ok: &[(i64, &DetectionMsg)],
) -> Option<String> {
    // A detection that could not be read is reported above; the count says what is short.
    let mut have = Tally::default();
    for (t, m) in ok {
        have.add(*t, m);
    }
    let missing: Vec<String> = have
        .short_of(expected)
        .map(|(key, got, need)| {
            if need == 1 {
                key.to_string()
            } else {
                format!("{key} ({got} of {need})")
            }
        })
        .collect();
    (!missing.is_empty()).then(|| {
        format!(
            "missing measurements (pose, approach, feed): {}",
            missing.join(", ")
        )
    })
}

/// Each tripped detection's values: finite, and a reading within `max_deviation_mm` of its
/// nominal trip.
fn check_values(
    k: &Kinematics,
    ok: &[(i64, &DetectionMsg)],
    max_deviation_mm: f64,
    reasons: &mut Vec<String>,
) {
    let nominal = k.nominal_state();
    for (_, m) in ok {
        let values = [
            ("b_deg", m.b_deg),
            ("c_deg", m.c_deg),
            ("feed_mm_min", m.feed_mm_min),
            ("spindle_rpm", m.spindle_rpm),
            ("x_mm", m.x_mm),
            ("y_mm", m.y_mm),
            ("z_mm", m.z_mm),
        ];
        if let Some((name, _)) = values.iter().find(|(_, v)| !v.is_finite()) {
            reasons.push(format!("step '{}': {name} is not a finite number", m.step));
            continue;
        }
        let o = observation(k, 0, m);
        match latched(k, &nominal, &o.angles, &o.approach, &o.position, None) {
            Ok(expected) => {
                let got = o.reading();
                let dev = got - expected;
                if dev.abs() > max_deviation_mm {
                    let ratio = if expected.abs() > 1e-6 { got / expected } else { f64::NAN };
                    let unit = if (500.0..2000.0).contains(&ratio.abs()) {
                        " (about 1000 times the nominal: written in um instead of mm?)"
                    } else {
                        ""
                    };
                    reasons.push(format!(
                        "step '{}': {}_mm = {got:.4} is {:.4} mm from its nominal {expected:.4}, more than {} mm{unit}",
                        m.step,
                        m.axis.name(),
                        dev.abs(),
                        max_deviation_mm
                    ));
                }
            }
            Err(e) => reasons.push(format!(
                "step '{}': no trip is possible at x = {}, y = {}, z = {} mm in pose B {} C {} ({e}): values off or a wrong pose?",
                m.step, m.x_mm, m.y_mm, m.z_mm, m.b_deg, m.c_deg
            )),
        }
    }
}

/// Validate and solve every cycle of a detection stream.
pub fn process_all(
    k: &Kinematics,
    detections: &[Entry],
    checks: &CycleChecks,
) -> (Vec<CycleOutcome>, Unassigned) {
    let (groups, un) = group_by_cycle(detections);
    let out = groups
        .iter()
        .map(|(c, entries)| process_cycle(k, *c, entries, checks))
        .collect();
    (out, un)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::PlanConfig;

    fn approach(axis: Axis, direction: i8, feed_mm_min: f64) -> Approach {
        Approach {
            axis,
            direction,
            feed_mm_min,
        }
    }

    #[test]
    fn a_measurement_is_its_pose_modulo_a_turn_its_approach_and_its_feed() {
        let a = approach(Axis::X, -1, 100.0);
        let k = MeasurementKey::new(-90.0, -270.0, &a);
        assert_eq!(k, MeasurementKey::new(-90.0, 90.0, &a));
        assert_eq!(k, MeasurementKey::new(270.0, 450.0004, &a));
        assert_eq!(k.to_string(), "B-90C90/x- F100");
        assert_eq!(
            MeasurementKey::new(0.0, 180.0, &a),
            MeasurementKey::new(-0.0, -180.0, &a)
        );
        assert_ne!(
            k,
            MeasurementKey::new(-90.0, 90.0, &approach(Axis::X, 1, 100.0))
        );
        assert_ne!(
            k,
            MeasurementKey::new(-90.0, 90.0, &approach(Axis::X, -1, 200.0))
        );
        assert_ne!(k, MeasurementKey::new(-90.0, 90.5, &a));
        assert_eq!(
            MeasurementKey::new(12.5, 0.0, &approach(Axis::Z, -1, 87.25)).to_string(),
            "B12.5C0/z- F87.25"
        );
    }

    #[test]
    fn the_time_symmetric_plan_makes_each_measurement_twice() {
        let k = Kinematics::load("table_bc").unwrap();
        let p = Plan::build(&k, &PlanConfig::load("patent").unwrap()).unwrap();
        let m = plan_measurements(&p);
        assert_eq!(m.len(), 12);
        assert!(m.values().all(|n| *n == 2), "{m:?}");
        let seq = Plan::build(&k, &PlanConfig::load("patent_sequential").unwrap()).unwrap();
        let s = plan_measurements(&seq);
        assert_eq!(s.keys().collect::<Vec<_>>(), m.keys().collect::<Vec<_>>());
        assert!(s.values().all(|n| *n == 1));
    }
}
