//! One measurement cycle from detections to a result: grouping by cycle, validation of every
//! detection (finite values, duplicates, failed approaches, missing steps, plausibility
//! against the nominal geometry), identification, and the `/cycle/result` message. A cycle
//! that fails any check is rejected with every reason; other cycles go on.

use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;

use crate::geometry::Vec3;
use crate::identify::{Identifier, Observation, Solution, SolveOptions, mean_time_ns};
use crate::kinematics::Kinematics;
use crate::measurement::{Approach, latched};
use crate::recording::{
    CycleResultMsg, DetectionIssue, DetectionMsg, DetectionStatus, ResultStatus, Timed,
};

#[derive(Debug, Clone)]
pub struct CycleChecks {
    /// Largest distance of a reading from its nominal value before it is refused, mm.
    pub max_deviation_mm: f64,
    /// Step labels every cycle must have (from the plan, or inferred from the recording).
    pub expected_steps: Option<BTreeSet<String>>,
    pub solve: SolveOptions,
}

impl CycleChecks {
    pub fn new(k: &Kinematics) -> Self {
        CycleChecks {
            max_deviation_mm: 1.0,
            expected_steps: None,
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

/// The step set shared by most cycles (at least two), to check the others against.
pub fn infer_expected_steps(
    groups: &BTreeMap<i64, Vec<Entry>>,
) -> Option<(BTreeSet<String>, usize)> {
    let mut counts: BTreeMap<BTreeSet<String>, usize> = BTreeMap::new();
    for entries in groups.values() {
        let set: BTreeSet<String> = entries
            .iter()
            .filter_map(|e| e.msg.as_ref().ok().map(|m| m.step.clone()))
            .collect();
        *counts.entry(set).or_default() += 1;
    }
    counts
        .into_iter()
        .filter(|(_, n)| *n >= 2)
        .max_by_key(|(s, n)| (*n, s.len()))
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
    let mut ok: Vec<(i64, &DetectionMsg)> = Vec::new();
    for e in entries {
        match &e.msg {
            Err(issue) => reasons.push(format!(
                "step '{}': {}",
                issue.step.as_deref().unwrap_or("?"),
                issue.message
            )),
            Ok(m) => ok.push((e.t_ns, m)),
        }
    }
    let mut seen: BTreeMap<&str, usize> = BTreeMap::new();
    for (_, m) in &ok {
        *seen.entry(m.step.as_str()).or_default() += 1;
    }
    for (step, n) in &seen {
        if *n > 1 {
            reasons.push(format!("step '{step}' appears {n} times"));
        }
    }
    if let Some(expected) = &checks.expected_steps {
        // A step whose message could not be read is reported above, not as missing.
        let unreadable: BTreeSet<&str> = entries
            .iter()
            .filter_map(|e| e.msg.as_ref().err().and_then(|i| i.step.as_deref()))
            .collect();
        let missing: Vec<&String> = expected
            .iter()
            .filter(|s| !seen.contains_key(s.as_str()) && !unreadable.contains(s.as_str()))
            .collect();
        if !missing.is_empty() {
            reasons.push(format!(
                "missing steps: {}",
                missing
                    .iter()
                    .map(|s| format!("'{s}'"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
    }
    let nominal = k.nominal_state();
    for (_, m) in &ok {
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
        if m.status() != DetectionStatus::Ok {
            let s = if m.status() == DetectionStatus::NoTrip {
                "no_trip"
            } else {
                "aborted"
            };
            reasons.push(format!(
                "step '{}' did not trip ({s}): broken tool, blocked beam or wrong tool?",
                m.step
            ));
            continue;
        }
        let o = observation(k, 0, m);
        match latched(k, &nominal, &o.angles, &o.approach, &o.position, None) {
            Ok(expected) => {
                let got = o.reading();
                let dev = got - expected;
                if dev.abs() > checks.max_deviation_mm {
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
                        checks.max_deviation_mm
                    ));
                }
            }
            Err(e) => reasons.push(format!(
                "step '{}': no trip is possible at x = {}, y = {}, z = {} mm in pose B {} C {} ({e}): values off or a wrong pose?",
                m.step, m.x_mm, m.y_mm, m.z_mm, m.b_deg, m.c_deg
            )),
        }
    }
    let times = ok
        .iter()
        .filter(|(_, m)| m.status() == DetectionStatus::Ok)
        .map(|(t, _)| *t);
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
