//! From a `/cycle/result` to the compensation the NC applies: validation against limits,
//! versioned compensation sets with the NC offsets of the machine's layout
//! ([`crate::nc_offsets`]), step limiting of served values, and the `/compensation` message.
//!
//! Compensation values move a real machine, so this module fails closed: a set is only ever
//! built from a result that passed [`validate`], every refusal names each failed check with
//! its numbers, and a limit that is not a usable number refuses rather than waving values
//! through (a comparison with NaN is false, which would otherwise pass everything).
//!
//! The errors a set holds and its NC offsets are the machine's ([`NcLayout`]): on `table_bc`
//! the six of the patent and the offsets `B_pivot_x_um = EX0B`, `B_pivot_z_um = EZ0B`,
//! `C_pivot_x_um = EX0B + EX0C`, `C_pivot_y_um = EY0C`, `C_tilt_a_urad = EA0C`,
//! `C_tilt_b_urad = EB0C`. The errors are the apparent (tool-relative) values a cycle
//! measures: the tool-tip drift is already folded into them, and that is what the NC must
//! compensate, since it positions the tool, not the spindle nose.

use driftwatch_core::units;
use std::collections::BTreeMap;

use driftwatch_core::error_name::ErrorName;

use crate::nc_offsets::NcLayout;

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use thiserror::Error;

use driftwatch_core::recording::{CycleResultMsg, ResultStatus};
use driftwatch_core::stats::chi2_quantile;
use driftwatch_core::units::positive;

/// The location errors a `table_bc` cycle identifies, in report order (test data).
#[cfg(test)]
pub(crate) const TABLE_BC_ERRORS: [ErrorName; 6] = [
    ErrorName::from_static("EX0B"),
    ErrorName::from_static("EZ0B"),
    ErrorName::from_static("EY0C"),
    ErrorName::from_static("EX0C"),
    ErrorName::from_static("EA0C"),
    ErrorName::from_static("EB0C"),
];

/// A map keyed by error names as strings (a cycle result's errors or sigma) with its names
/// parsed; the first name that is not a location error name refuses it.
pub fn typed(
    m: &BTreeMap<String, f64>,
) -> Result<BTreeMap<ErrorName, f64>, driftwatch_core::error_name::BadErrorName> {
    m.iter()
        .map(|(k, v)| Ok((ErrorName::parse(k)?, *v)))
        .collect()
}

/// Whether a model channel names an orientation error (urad); a position error, or a channel
/// that is no error name, is in um.
fn angular_channel(channel: &str) -> bool {
    ErrorName::parse(channel).is_ok_and(|e| e.is_angular())
}

// ---------------------------------------------------------------------------------------------
// Validation
// ---------------------------------------------------------------------------------------------

/// What a cycle result must meet before it may become compensation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ValidationLimits {
    /// Probability of the chi-square point the fit's chi-square must stay within (default
    /// 0.999: a correct model and noise level exceed it once in a thousand cycles).
    pub chi2_quantile: f64,
    /// Largest standard uncertainty of a position error, um (default 2.0).
    pub max_sigma_um: f64,
    /// Largest standard uncertainty of an orientation error, urad (default 15.0).
    pub max_sigma_urad: f64,
    /// Largest believable position error from zero, um (default 200: no thermal drift of a
    /// machine in working order gets there; a value beyond is a wrong setup or a unit error).
    pub max_abs_um: f64,
    /// Largest believable orientation error from zero, urad (default 500).
    pub max_abs_urad: f64,
    /// Largest change of a position error from the served value in one step, um (default 50,
    /// HEIDENHAIN KinematicsOpt's change limit).
    pub max_step_um: f64,
    /// Largest change of an orientation error from the served value in one step, urad
    /// (default 100).
    pub max_step_urad: f64,
    /// The step limits grow by this much per minute since the served set: a machine that
    /// cooled overnight has legitimately moved more than one step, a cycle minutes after the
    /// last has not. um/min (default 4: above the 3.5 um/min the patent's fastest drift shows).
    pub max_rate_um_per_min: f64,
    /// The same for orientation errors, urad/min (default 10).
    pub max_rate_urad_per_min: f64,
}

/// The step limit between a served set and a later one: `base + rate x minutes`, the largest
/// change of an error from the served value that many minutes after it (a machine that cooled
/// overnight has legitimately moved more than one step). The one place the rule is written:
/// validation, the ramp of served sets and the NC writer's check all use it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepLimit {
    pub base: f64,
    /// Per minute.
    pub rate: f64,
    pub minutes: f64,
}

impl StepLimit {
    /// From a set valid from `from_ns` to one at `to_ns` (a time before `from_ns` counts as
    /// no time).
    pub fn new(base: f64, rate: f64, from_ns: i64, to_ns: i64) -> Self {
        StepLimit {
            base,
            rate,
            minutes: units::ns_to_min(to_ns - from_ns).max(0.0),
        }
    }

    /// The limit itself.
    pub fn max(&self) -> f64 {
        self.base + self.rate * self.minutes
    }
}

impl ValidationLimits {
    /// The step limit of an orientation (`angular`) or position error from a set valid from
    /// `from_ns` to one at `to_ns`.
    pub fn step_limit(&self, angular: bool, from_ns: i64, to_ns: i64) -> StepLimit {
        let (base, rate) = if angular {
            (self.max_step_urad, self.max_rate_urad_per_min)
        } else {
            (self.max_step_um, self.max_rate_um_per_min)
        };
        StepLimit::new(base, rate, from_ns, to_ns)
    }

    /// Every limit finite and in range: a NaN or negative limit would reject every cycle (or
    /// pass every one), so it is refused at start with its name.
    pub fn check(&self) -> Result<(), String> {
        if !(self.chi2_quantile > 0.5 && self.chi2_quantile < 1.0) {
            return Err(format!(
                "validation.chi2_quantile must be between 0.5 and 1 (exclusive), not {}",
                self.chi2_quantile
            ));
        }
        let positive = [
            ("max_sigma_um", self.max_sigma_um),
            ("max_sigma_urad", self.max_sigma_urad),
            ("max_abs_um", self.max_abs_um),
            ("max_abs_urad", self.max_abs_urad),
            ("max_step_um", self.max_step_um),
            ("max_step_urad", self.max_step_urad),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!(
                    "validation.{name} must be a finite number above 0, not {v}"
                ));
            }
        }
        let rates = [
            ("max_rate_um_per_min", self.max_rate_um_per_min),
            ("max_rate_urad_per_min", self.max_rate_urad_per_min),
        ];
        for (name, v) in rates {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!(
                    "validation.{name} must be a finite number of at least 0, not {v}"
                ));
            }
        }
        Ok(())
    }
}

impl Default for ValidationLimits {
    fn default() -> Self {
        ValidationLimits {
            chi2_quantile: 0.999,
            max_sigma_um: 2.0,
            max_sigma_urad: 15.0,
            max_abs_um: 200.0,
            max_abs_urad: 500.0,
            max_step_um: 50.0,
            max_step_urad: 100.0,
            max_rate_um_per_min: 4.0,
            max_rate_urad_per_min: 10.0,
        }
    }
}

/// The verdict on one cycle result: `ok` only when `reasons` is empty.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Validation {
    pub ok: bool,
    /// Every failed check, with its numbers.
    pub reasons: Vec<String>,
}

/// Check a cycle result before it may become compensation: the solver's verdict, exactly the
/// machine's identified errors (`layout`) present, finite and believable, their uncertainties within limits, the
/// chi-square of the fit within its `chi2_quantile` point, the step from the served set
/// (`previous`) within limits, and the cycle newer than the served one. Every failed check is
/// named; nothing stops at the first.
pub fn validate(
    result: &CycleResultMsg,
    previous: Option<&CompensationSet>,
    limits: &ValidationLimits,
    layout: &NcLayout,
) -> Validation {
    let mut reasons = result_shape_reasons(result, layout);
    let limit = usable_limits(limits, &mut reasons);

    match (result.chi2, result.dof) {
        (None, _) | (_, None) => reasons.push(
            "no chi-square and dof in the result: the fit cannot be checked against the noise"
                .into(),
        ),
        (Some(_), Some(0)) => reasons.push(
            "0 dof: the cycle has no redundancy, so the fit cannot be checked against the noise"
                .into(),
        ),
        (Some(chi2), Some(_)) if !(chi2.is_finite() && chi2 >= 0.0) => {
            reasons.push(format!(
                "chi-square {chi2} is not a finite non-negative number"
            ));
        }
        (Some(chi2), Some(dof)) => {
            if let Some(p) = limit.chi2_quantile {
                let q = chi2_quantile(p, dof);
                if !within(chi2, q) {
                    reasons.push(format!(
                        "chi-square {} beyond its {} % point {q:.2} for {dof} dof",
                        shown(chi2, q, 1),
                        percent(p)
                    ));
                }
            }
        }
    }
    if let Some(rms) = result.residual_rms_um
        && !rms.is_finite()
    {
        reasons.push(format!("residual rms {rms} um is not a finite number"));
    }

    let errors = result.errors.as_ref();
    let sigma = result.sigma.as_ref();
    for &name in &layout.errors {
        let Some(&value) = errors.and_then(|e| e.get(name.as_str())) else {
            continue; // named by result_shape_reasons
        };
        if !value.is_finite() {
            continue; // named by result_shape_reasons
        }
        let u = name.unit();
        let angular = name.is_angular();
        let max_abs = if angular {
            limit.max_abs_urad
        } else {
            limit.max_abs_um
        };
        if let Some(max) = max_abs
            && !within(value.abs(), max)
        {
            reasons.push(format!(
                "{name} {} {u} from zero beyond the believable {} {u}",
                shown(value.abs(), max, 1),
                limit_str(max)
            ));
        }
        let max_sigma = if angular {
            limit.max_sigma_urad
        } else {
            limit.max_sigma_um
        };
        if let (Some(max), Some(&s)) = (max_sigma, sigma.and_then(|s| s.get(name.as_str())))
            && positive(s)
            && !within(s, max)
        {
            reasons.push(format!(
                "{name} uncertainty {} {u} over its limit {} {u}",
                shown(s, max, 1),
                limit_str(max)
            ));
        }
        if let Some(prev) = previous {
            let max_step = if angular {
                limit.max_step_urad
            } else {
                limit.max_step_um
            };
            match prev.errors.get(&name) {
                None => reasons.push(format!(
                    "{name} has no value in the served set {} to measure the step from",
                    prev.version
                )),
                Some(&served) if !served.is_finite() => reasons.push(format!(
                    "{name} served value {served} in set {} is not a finite number to measure \
                     the step from",
                    prev.version
                )),
                Some(&served) => {
                    let step = (value - served).abs();
                    let rate = if angular {
                        limit.max_rate_urad_per_min
                    } else {
                        limit.max_rate_um_per_min
                    };
                    if let Some(base) = max_step {
                        let grown = StepLimit::new(base, rate, prev.valid_from_ns, result.t_ns);
                        let (max, minutes) = (grown.max(), grown.minutes);
                        if !within(step, max) {
                            reasons.push(format!(
                                "{name} step {} {u} from the served value {} {u} to {} {u} over \
                                 the limit {} {u} ({} {u} + {} {u}/min over {:.0} min)",
                                shown(step, max, 1),
                                fixed(served),
                                fixed(value),
                                limit_str(max),
                                limit_str(base),
                                limit_str(rate),
                                minutes
                            ));
                        }
                    }
                }
            }
        }
    }

    if let Some(prev) = previous
        && let Some(served_cycle) = prev.cycle
        && result.cycle <= served_cycle
    {
        reasons.push(format!(
            "cycle {} is not newer than cycle {served_cycle} of the served set {}",
            result.cycle, prev.version
        ));
    }

    Validation {
        ok: reasons.is_empty(),
        reasons,
    }
}

/// A validated cycle's two sets: what the NC gets (`nc`) and what the cycle measured
/// (`measured`). They differ only when the measurement lies beyond the step limit from the
/// served set (a predicted one, or one ramped before): the NC then gets the served values
/// moved by the limit towards the measurement, and the predictions that follow carry on.
#[derive(Debug, Clone, PartialEq)]
pub struct Admitted {
    pub nc: CompensationSet,
    pub measured: CompensationSet,
}

/// What the service does with one solved cycle: the result as it is stored (rejected, with
/// every reason, when it fails [`validate`] or no set can be built from it; the chi-square
/// point it was checked against filled in) and, when it passes, its sets. `served` is the set
/// the NC has (it fixes the version and the time order), `measured` the last measured one: the
/// step check measures from it, so a measurement is never rejected because of a step from a
/// prediction. `now_ns` is when the cycle closed. The command line's `solve` gives the same
/// verdict offline.
pub fn admit(
    mut result: CycleResultMsg,
    served: Option<&CompensationSet>,
    measured: Option<&CompensationSet>,
    limits: &ValidationLimits,
    now_ns: i64,
    layout: &NcLayout,
) -> (CycleResultMsg, Option<Admitted>) {
    if result.status != ResultStatus::Ok {
        return (result, None);
    }
    if let Some(dof) = result.dof.filter(|d| *d > 0)
        && positive(limits.chi2_quantile)
        && limits.chi2_quantile < 1.0
    {
        result.chi2_point = Some(chi2_quantile(limits.chi2_quantile, dof));
    }
    let v = validate(&result, measured, limits, layout);
    let refused = if v.ok {
        match next_set(served, &result, &v, now_ns, layout) {
            Ok(set) => {
                let nc = match served {
                    Some(from) => ramped(from, &set, limits, layout),
                    None => set.clone(),
                };
                return (result, Some(Admitted { nc, measured: set }));
            }
            Err(refused) => refused.reasons,
        }
    } else {
        v.reasons
    };
    result.status = ResultStatus::Rejected;
    result.reason = Some(refused.join("; "));
    (result, None)
}

/// `to` with its values moved from `from`'s by at most the step limit (grown by the rate
/// limits over the time between them); the reason names each value held back.
fn ramped(
    from: &CompensationSet,
    to: &CompensationSet,
    limits: &ValidationLimits,
    layout: &NcLayout,
) -> CompensationSet {
    let step = |angular| {
        limits
            .step_limit(angular, from.valid_from_ns, to.valid_from_ns)
            .max()
    };
    let errors = ramp(from, &to.errors, step(false), step(true));
    let held: Vec<String> = to
        .errors
        .iter()
        .filter(|(n, v)| errors.get(*n).is_some_and(|r| (r - *v).abs() > 1e-9))
        .map(|(n, v)| format!("{n} {:.1} of {v:.1}", errors[n]))
        .collect();
    let mut set = to.clone();
    if !held.is_empty() {
        set.reason.push_str(&format!(
            "; ramped to the step limit from set {} ({:?}): {}",
            from.version,
            from.source,
            held.join(", ")
        ));
        set.offsets = layout.offsets(&errors);
        set.errors = errors;
    }
    set
}

/// `x` at most `max`; false when either is NaN, so that a NaN fails the check it is in.
fn within(x: f64, max: f64) -> bool {
    x <= max
}

/// The limits that are usable numbers; each one that is not is a reason, and the checks that
/// need it are skipped rather than run against a NaN.
struct Usable {
    chi2_quantile: Option<f64>,
    max_sigma_um: Option<f64>,
    max_sigma_urad: Option<f64>,
    max_abs_um: Option<f64>,
    max_abs_urad: Option<f64>,
    max_step_um: Option<f64>,
    max_step_urad: Option<f64>,
    max_rate_um_per_min: f64,
    max_rate_urad_per_min: f64,
}

fn usable_limits(l: &ValidationLimits, reasons: &mut Vec<String>) -> Usable {
    let mut pos = |name: &str, v: f64| {
        if positive(v) {
            Some(v)
        } else {
            reasons.push(format!(
                "limit {name} = {v} is not a positive finite number"
            ));
            None
        }
    };
    let max_sigma_um = pos("max_sigma_um", l.max_sigma_um);
    let max_sigma_urad = pos("max_sigma_urad", l.max_sigma_urad);
    let max_abs_um = pos("max_abs_um", l.max_abs_um);
    let max_abs_urad = pos("max_abs_urad", l.max_abs_urad);
    let max_step_um = pos("max_step_um", l.max_step_um);
    let max_step_urad = pos("max_step_urad", l.max_step_urad);
    let mut rate = |name: &str, v: f64| {
        if driftwatch_core::units::non_negative(v) {
            v
        } else {
            reasons.push(format!("limit {name} = {v} is not a finite number >= 0"));
            0.0
        }
    };
    let max_rate_um_per_min = rate("max_rate_um_per_min", l.max_rate_um_per_min);
    let max_rate_urad_per_min = rate("max_rate_urad_per_min", l.max_rate_urad_per_min);
    let p = l.chi2_quantile;
    let chi2_quantile = if p > 0.0 && p < 1.0 {
        Some(p)
    } else {
        reasons.push(format!(
            "limit chi2_quantile = {p} is not a probability strictly between 0 and 1"
        ));
        None
    };
    Usable {
        chi2_quantile,
        max_sigma_um,
        max_sigma_urad,
        max_abs_um,
        max_abs_urad,
        max_step_um,
        max_step_urad,
        max_rate_um_per_min,
        max_rate_urad_per_min,
    }
}

/// The checks that need no limits: the solver's verdict and exactly the machine's identified
/// errors, finite, each with a finite positive uncertainty. [`next_set`] repeats them, so a set can
/// never be built from a result without usable numbers, whatever `Validation` it is handed.
fn result_shape_reasons(result: &CycleResultMsg, layout: &NcLayout) -> Vec<String> {
    let mut reasons = Vec::new();
    if result.status == ResultStatus::Rejected {
        reasons.push(format!(
            "rejected by the solver: {}",
            result.reason.as_deref().unwrap_or("no reason given")
        ));
    }
    let errors = match &result.errors {
        Some(e) if !e.is_empty() => e,
        _ => {
            reasons.push("no errors".into());
            return reasons;
        }
    };
    for name in &layout.errors {
        match errors.get(name.as_str()) {
            None => reasons.push(format!("{name} missing from the errors")),
            Some(v) if !v.is_finite() => {
                reasons.push(format!("{name} = {v} is not a finite number"));
            }
            Some(_) => {}
        }
    }
    for name in errors.keys() {
        if !layout.holds(name) {
            reasons.push(format!(
                "unexpected error {name}: a {} set holds only {}",
                layout.machine,
                layout.list()
            ));
        }
    }
    match &result.sigma {
        None => reasons.push("no uncertainties (sigma)".into()),
        Some(sigma) => {
            for name in &layout.errors {
                if !errors.contains_key(name.as_str()) {
                    continue;
                }
                match sigma.get(name.as_str()) {
                    None => reasons.push(format!("{name} has no uncertainty")),
                    Some(&s) if !positive(s) => reasons.push(format!(
                        "{name} uncertainty {s} {} is not a positive finite number",
                        name.unit()
                    )),
                    Some(_) => {}
                }
            }
        }
    }
    reasons
}

// ---------------------------------------------------------------------------------------------
// Compensation sets
// ---------------------------------------------------------------------------------------------

/// Where a set's values come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub enum Source {
    /// Identified in a measurement cycle.
    Measured,
    /// From the thermal model between cycles.
    Predicted,
}

/// One version of the compensation served to the NC.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct CompensationSet {
    /// 1 for the first set, then one more for each set.
    pub version: u64,
    /// From when the NC may apply it, ns since the Unix epoch.
    pub valid_from_ns: i64,
    pub source: Source,
    /// The cycle it was measured in.
    pub cycle: Option<i64>,
    /// Apparent location errors, um and urad.
    #[cfg_attr(feature = "openapi", schema(value_type = BTreeMap<String, f64>))]
    pub errors: BTreeMap<ErrorName, f64>,
    /// Their standard uncertainties, same units.
    #[cfg_attr(feature = "openapi", schema(value_type = BTreeMap<String, f64>))]
    pub sigma: BTreeMap<ErrorName, f64>,
    /// The errors in the form the NC applies (see the module docs).
    pub offsets: BTreeMap<String, f64>,
    /// Why this set exists, for the operator.
    pub reason: String,
}

/// A set that may not be built, with every reason.
#[derive(Debug, Clone, PartialEq, Error)]
#[error("no compensation set: {}", .reasons.join("; "))]
pub struct Refused {
    pub reasons: Vec<String>,
}

/// The next compensation set from a validated cycle result.
///
/// `validation` must be the verdict of [`validate`] on this `result` against this `previous`.
/// The checks that need no limits are repeated here, so a result without usable numbers is
/// refused even with a `Validation` that says ok. `now_ns` becomes `valid_from_ns` and may not
/// lie before the served set's, so that the newest version is also the latest in time.
pub fn next_set(
    previous: Option<&CompensationSet>,
    result: &CycleResultMsg,
    validation: &Validation,
    now_ns: i64,
    layout: &NcLayout,
) -> Result<CompensationSet, Refused> {
    let mut reasons = Vec::new();
    if !validation.ok {
        reasons.extend(validation.reasons.iter().cloned());
        if reasons.is_empty() {
            reasons.push("the result did not pass validation".into());
        }
    } else if !validation.reasons.is_empty() {
        reasons.push("the validation says ok but names failed checks".into());
        reasons.extend(validation.reasons.iter().cloned());
    }
    for r in result_shape_reasons(result, layout) {
        if !reasons.contains(&r) {
            reasons.push(r);
        }
    }
    let version = match previous {
        None => Some(1),
        Some(prev) => {
            if now_ns < prev.valid_from_ns {
                reasons.push(format!(
                    "valid from {now_ns} ns would lie before the served set {} (valid from {} ns)",
                    prev.version, prev.valid_from_ns
                ));
            }
            prev.version.checked_add(1)
        }
    };
    let Some(version) = version else {
        reasons.push("no version number after u64::MAX".into());
        return Err(Refused { reasons });
    };
    if !reasons.is_empty() {
        return Err(Refused { reasons });
    }

    // Both maps are present with every name: result_shape_reasons found nothing.
    let (Some(all_errors), Some(all_sigma)) = (&result.errors, &result.sigma) else {
        return Err(Refused {
            reasons: vec!["no errors".into()],
        });
    };
    let pick = |m: &BTreeMap<String, f64>| -> BTreeMap<ErrorName, f64> {
        layout
            .errors
            .iter()
            .filter_map(|&n| m.get(n.as_str()).map(|&v| (n, v)))
            .collect()
    };
    let errors = pick(all_errors);
    let sigma = pick(all_sigma);
    let fit = match (result.chi2, result.dof) {
        (Some(chi2), Some(dof)) => format!(", chi-square {chi2:.1} for {dof} dof"),
        _ => String::new(),
    };
    Ok(CompensationSet {
        version,
        valid_from_ns: now_ns,
        source: Source::Measured,
        cycle: Some(result.cycle),
        offsets: layout.offsets(&errors),
        errors,
        sigma,
        reason: format!(
            "measured in cycle {} (reference time {} ns{fit})",
            result.cycle, result.t_ns
        ),
    })
}

/// What the service does with the thermal model's predictions (the `[thermal]` section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PredictionPolicy {
    /// Serve predicted sets between cycles at all.
    pub enabled: bool,
    /// Validated cycles before the first fit of the model.
    pub min_cycles: usize,
    /// The model is fitted again on its history after this many more validated cycles
    /// (between refits the filter corrects it with each cycle).
    pub refit_every_cycles: usize,
    /// History the fits use, days.
    pub history_days: f64,
    /// Machine time between predicted sets at most, s: a new set goes out when this has passed
    /// and a value moved by more than the thresholds below.
    pub refresh_s: f64,
    pub move_threshold_um: f64,
    pub move_threshold_urad: f64,
    /// A predicted value less certain than this is not served (the last set stays and a
    /// cycle is asked for).
    pub max_sigma_um: f64,
    pub max_sigma_urad: f64,
    /// A cycle is asked for (in the next idle window) once a prediction is less certain than
    /// this.
    pub cycle_above_sigma_um: f64,
    pub cycle_above_sigma_urad: f64,
    /// A predicted value must lie within this many combined standard uncertainties of the
    /// latest measurement (widened by the drift the validation's rate limits allow since it);
    /// otherwise no predicted set is served and the model is suspect until it predicts a
    /// cycle within as many of its own.
    pub consistency_sigmas: f64,
    /// The model (pole basis, inputs, offset walk).
    pub model: driftwatch_thermal::model::ModelConfig,
}

impl Default for PredictionPolicy {
    fn default() -> Self {
        PredictionPolicy {
            enabled: true,
            min_cycles: 6,
            refit_every_cycles: 6,
            history_days: 7.0,
            refresh_s: 60.0,
            move_threshold_um: 1.0,
            move_threshold_urad: 5.0,
            max_sigma_um: 5.0,
            max_sigma_urad: 30.0,
            cycle_above_sigma_um: 3.0,
            cycle_above_sigma_urad: 20.0,
            consistency_sigmas: 5.0,
            model: driftwatch_thermal::model::ModelConfig::default(),
        }
    }
}

impl PredictionPolicy {
    pub fn validate(&self) -> Result<(), String> {
        if self.refit_every_cycles == 0 {
            return Err("thermal.refit_every_cycles must be at least 1".into());
        }
        for (k, v) in [
            ("history_days", self.history_days),
            ("refresh_s", self.refresh_s),
            ("max_sigma_um", self.max_sigma_um),
            ("max_sigma_urad", self.max_sigma_urad),
            ("cycle_above_sigma_um", self.cycle_above_sigma_um),
            ("cycle_above_sigma_urad", self.cycle_above_sigma_urad),
            ("consistency_sigmas", self.consistency_sigmas),
        ] {
            if !positive(v) {
                return Err(format!("thermal.{k} must be > 0, not {v}"));
            }
        }
        for (k, v) in [
            ("move_threshold_um", self.move_threshold_um),
            ("move_threshold_urad", self.move_threshold_urad),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("thermal.{k} must be >= 0, not {v}"));
            }
        }
        if self.min_cycles < 2 {
            return Err("thermal.min_cycles must be at least 2".into());
        }
        self.model.validate().map_err(|e| e.to_string())
    }

    /// Whether `predicted` differs enough from the served set to be worth a new version.
    pub fn moved(&self, served: &CompensationSet, predicted: &BTreeMap<String, f64>) -> bool {
        predicted.iter().any(|(n, v)| {
            let limit = if angular_channel(n) {
                self.move_threshold_urad
            } else {
                self.move_threshold_um
            };
            served
                .errors
                .get(n.as_str())
                .is_none_or(|s| (s - v).abs() > limit)
        })
    }
}

/// The next compensation set from the thermal model's prediction (`value`, `sigma` per
/// error). Refused, with every reason, when an error is missing or not finite, less certain
/// than the policy allows, or beyond the believable size. A step beyond the limit (which grows
/// with the time since the served set, as for measured sets) is ramped: the set moves by the
/// limit and says so.
pub fn predicted_set(
    previous: Option<&CompensationSet>,
    predicted: &BTreeMap<String, (f64, f64)>,
    limits: &ValidationLimits,
    policy: &PredictionPolicy,
    now_ns: i64,
    note: &str,
    layout: &NcLayout,
) -> Result<CompensationSet, Refused> {
    let mut reasons = Vec::new();
    let mut errors = BTreeMap::new();
    let mut sigma = BTreeMap::new();
    for &n in &layout.errors {
        let Some(&(v, s)) = predicted.get(n.as_str()) else {
            reasons.push(format!("the model does not predict {n}"));
            continue;
        };
        let ang = n.is_angular();
        let u = n.unit();
        if !(v.is_finite() && s.is_finite()) {
            reasons.push(format!("{n}: predicted value or sigma is not finite"));
            continue;
        }
        let (max_s, max_abs) = if ang {
            (policy.max_sigma_urad, limits.max_abs_urad)
        } else {
            (policy.max_sigma_um, limits.max_abs_um)
        };
        if s > max_s {
            reasons.push(format!(
                "{n}: predicted sigma {s:.2} {u} over the {max_s} {u} limit: a cycle is needed"
            ));
        }
        if v.abs() > max_abs {
            reasons.push(format!(
                "{n}: predicted {v:.1} {u} beyond the believable {max_abs} {u}"
            ));
        }
        // A prediction means nothing below a nanometre; the rounding keeps the stored sets
        // short.
        errors.insert(n, (v * 1e3).round() / 1e3);
        sigma.insert(n, (s * 1e3).round() / 1e3);
    }
    if let Some(prev) = previous
        && now_ns < prev.valid_from_ns
    {
        reasons.push("a prediction may not lie before the served set".into());
    }
    if !reasons.is_empty() {
        return Err(Refused { reasons });
    }
    let version = previous.map_or(Some(1), |p| p.version.checked_add(1));
    let Some(version) = version else {
        return Err(Refused {
            reasons: vec!["no version number after u64::MAX".into()],
        });
    };
    let set = CompensationSet {
        version,
        valid_from_ns: now_ns,
        source: Source::Predicted,
        cycle: None,
        offsets: layout.offsets(&errors),
        errors,
        sigma,
        reason: format!("predicted by {note}"),
    };
    Ok(match previous {
        Some(prev) => ramped(prev, &set, limits, layout),
        None => set,
    })
}

/// Where predicted values (`value`, `sigma` per error, at `t_ns`) disagree with a measured
/// set (its cycle's reference time `measured_t_ns`): beyond `k` combined standard
/// uncertainties plus the drift the rate limits allow over the time between. One reason per
/// error that disagrees; empty when all agree.
pub fn inconsistent(
    predicted: &BTreeMap<String, (f64, f64)>,
    measured: &CompensationSet,
    measured_t_ns: i64,
    t_ns: i64,
    k: f64,
    limits: &ValidationLimits,
) -> Vec<String> {
    let minutes = (units::ns_to_min(t_ns - measured_t_ns)).abs();
    let mut reasons = Vec::new();
    for (n, &(v, s)) in predicted {
        // A channel that is not an error name has no measured value to disagree with.
        let Ok(name) = ErrorName::parse(n) else {
            continue;
        };
        let (Some(&m), Some(&sm)) = (measured.errors.get(&name), measured.sigma.get(&name)) else {
            continue;
        };
        let u = name.unit();
        let rate = if name.is_angular() {
            limits.max_rate_urad_per_min
        } else {
            limits.max_rate_um_per_min
        };
        let combined = s.hypot(sm);
        let allowed = k * combined + rate * minutes;
        // `within` is false for a NaN anywhere: it disagrees.
        if !within((v - m).abs(), allowed) {
            reasons.push(format!(
                "{n} predicted {v:.2} +- {s:.2} {u} lies {:.0} combined sigmas from the \
                 {m:.2} +- {sm:.2} {u} measured{}, {minutes:.1} min before (allowed: {k} sigmas \
                 + {rate} {u}/min, {allowed:.2} {u})",
                (v - m).abs() / combined,
                measured
                    .cycle
                    .map(|c| format!(" in cycle {c}"))
                    .unwrap_or_default(),
            ));
        }
    }
    reasons
}

/// The served errors moved towards `to` by at most `max_step_um` (positions) or
/// `max_step_urad` (orientations) per value, so the NC never sees a jump.
///
/// A name served in `from` but absent (or not finite) in `to` holds its value. A name new in
/// `to`, or served as a non-finite value, starts from 0, which is what the NC applies without
/// compensation. A step limit that is not a positive finite number moves nothing.
pub fn ramp(
    from: &CompensationSet,
    to: &BTreeMap<ErrorName, f64>,
    max_step_um: f64,
    max_step_urad: f64,
) -> BTreeMap<ErrorName, f64> {
    let mut out = BTreeMap::new();
    let names = from.errors.keys().chain(to.keys());
    for name in names {
        if out.contains_key(name) {
            continue;
        }
        let served = from.errors.get(name).copied().filter(|v| v.is_finite());
        let target = to.get(name).copied().filter(|v| v.is_finite());
        let current = match (served, target) {
            (None, None) => continue,
            (Some(s), _) => s,
            (None, Some(_)) => 0.0,
        };
        let Some(target) = target else {
            out.insert(*name, current);
            continue;
        };
        let max = if name.is_angular() {
            max_step_urad
        } else {
            max_step_um
        };
        let step = if positive(max) { max } else { 0.0 };
        let d = target - current;
        let next = if d.abs() <= step {
            target
        } else {
            current + step.copysign(d)
        };
        out.insert(*name, next);
    }
    out
}

/// The `/compensation` message of a set (the contract's fields plus `sigma`, `cycle` and
/// `reason`).
pub fn compensation_message(set: &CompensationSet) -> Value {
    json!({
        "version": set.version,
        "valid_from_ns": set.valid_from_ns,
        "source": set.source,
        "errors": set.errors,
        "offsets": set.offsets,
        "sigma": set.sigma,
        "cycle": set.cycle,
        "reason": set.reason,
    })
}

// ---------------------------------------------------------------------------------------------
// Number formatting for reasons
// ---------------------------------------------------------------------------------------------

/// `value` with the fewest decimals (at least `min_dec`) at which it does not read the same as
/// `limit`, so that "50.0 over the limit 50.0" never appears.
fn shown(value: f64, limit: f64, min_dec: usize) -> String {
    for d in min_dec..=6 {
        let v = format!("{value:.d$}");
        if v != format!("{limit:.d$}") {
            return v;
        }
    }
    format!("{value}")
}

/// A limit as configured: one decimal for whole numbers, otherwise every digit it has.
fn limit_str(x: f64) -> String {
    if x.fract() == 0.0 {
        format!("{x:.1}")
    } else {
        format!("{x}")
    }
}

fn fixed(x: f64) -> String {
    format!("{x:.1}")
}

/// A probability as a percentage without trailing zeros (0.999 -> "99.9").
fn percent(p: f64) -> String {
    let s = format!("{:.6}", p * 100.0);
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The layout of `table_bc`, the machine these tests judge results of.
    fn tbc() -> &'static NcLayout {
        static L: std::sync::OnceLock<NcLayout> = std::sync::OnceLock::new();
        L.get_or_init(|| {
            NcLayout::of(&driftwatch_core::kinematics::Kinematics::builtin("table_bc").unwrap())
        })
    }

    // The functions under test on table_bc (these shadow the module's own).
    fn validate(
        r: &CycleResultMsg,
        prev: Option<&CompensationSet>,
        limits: &ValidationLimits,
    ) -> Validation {
        super::validate(r, prev, limits, tbc())
    }
    fn next_set(
        prev: Option<&CompensationSet>,
        r: &CycleResultMsg,
        v: &Validation,
        now_ns: i64,
    ) -> Result<CompensationSet, Refused> {
        super::next_set(prev, r, v, now_ns, tbc())
    }
    fn admit(
        r: CycleResultMsg,
        served: Option<&CompensationSet>,
        measured: Option<&CompensationSet>,
        limits: &ValidationLimits,
        now_ns: i64,
    ) -> (CycleResultMsg, Option<Admitted>) {
        super::admit(r, served, measured, limits, now_ns, tbc())
    }
    fn predicted_set(
        prev: Option<&CompensationSet>,
        p: &BTreeMap<String, (f64, f64)>,
        limits: &ValidationLimits,
        policy: &PredictionPolicy,
        now_ns: i64,
        note: &str,
    ) -> Result<CompensationSet, Refused> {
        super::predicted_set(prev, p, limits, policy, now_ns, note, tbc())
    }
    fn offsets(e: &BTreeMap<ErrorName, f64>) -> BTreeMap<String, f64> {
        tbc().offsets(e)
    }

    fn predictions(v: f64, s: f64) -> BTreeMap<String, (f64, f64)> {
        TABLE_BC_ERRORS
            .iter()
            .map(|n| (n.to_string(), (v, s)))
            .collect()
    }

    #[test]
    fn predicted_sets_are_refused_when_uncertain_and_ramped_over_the_step_limit() {
        let limits = ValidationLimits::default();
        let policy = PredictionPolicy::default();
        let first = predicted_set(None, &predictions(10.0, 1.0), &limits, &policy, 0, "m").unwrap();
        assert_eq!((first.version, first.source), (1, Source::Predicted));
        // Too uncertain: refused with the reason, for every error.
        let e = predicted_set(
            Some(&first),
            &predictions(10.0, 6.0),
            &limits,
            &policy,
            60,
            "m",
        )
        .unwrap_err();
        assert!(
            e.reasons
                .iter()
                .any(|r| r.contains("EZ0B") && r.contains("cycle is needed")),
            "{e}"
        );
        // A jump of 80 um one minute later: 50 + 4 um allowed, the rest waits.
        let next = predicted_set(
            Some(&first),
            &predictions(90.0, 1.0),
            &limits,
            &policy,
            units::NS_PER_MIN,
            "m",
        )
        .unwrap();
        assert!(
            (next.errors["EZ0B"] - 64.0).abs() < 1e-9,
            "{:?}",
            next.errors
        );
        assert!(next.reason.contains("ramped"), "{}", next.reason);
        assert_eq!(next.version, 2);
        // Orientation errors have their own limit (100 + 10 urad): 90 urad is within it.
        assert_eq!(next.errors["EA0C"], 90.0);
        assert!(policy.moved(&first, &BTreeMap::from([("EZ0B".to_string(), 11.1)])));
        assert!(!policy.moved(&first, &BTreeMap::from([("EZ0B".to_string(), 10.9)])));
    }

    const T0: i64 = 1_700_000_000_000_000_000;

    fn map(pairs: &[(&str, f64)]) -> BTreeMap<String, f64> {
        pairs.iter().map(|&(k, v)| (k.to_string(), v)).collect()
    }

    fn tmap(pairs: &[(&str, f64)]) -> BTreeMap<ErrorName, f64> {
        typed(&map(pairs)).unwrap()
    }

    fn clean_errors() -> BTreeMap<String, f64> {
        map(&[
            ("EX0B", 12.0),
            ("EZ0B", 40.0),
            ("EY0C", -5.0),
            ("EX0C", 3.0),
            ("EA0C", 20.0),
            ("EB0C", -30.0),
        ])
    }

    fn clean(cycle: i64) -> CycleResultMsg {
        CycleResultMsg {
            cycle,
            t_ns: T0 + cycle * 1_800_000_000_000,
            status: ResultStatus::Ok,
            reason: None,
            errors: Some(clean_errors()),
            sigma: Some(map(&[
                ("EX0B", 0.7),
                ("EZ0B", 0.6),
                ("EY0C", 0.9),
                ("EX0C", 0.6),
                ("EA0C", 7.0),
                ("EB0C", 6.0),
            ])),
            residual_rms_um: Some(0.5),
            chi2: Some(12.0),
            dof: Some(16),
            n_detections: Some(24),
            nuisance: None,
            redundancy_um: None,
            chi2_point: None,
            geometry: None,
            notes: None,
        }
    }

    fn set_error(r: &mut CycleResultMsg, name: &str, v: f64) {
        r.errors.as_mut().unwrap().insert(name.into(), v);
    }

    fn set_sigma(r: &mut CycleResultMsg, name: &str, v: f64) {
        r.sigma.as_mut().unwrap().insert(name.into(), v);
    }

    #[test]
    fn admit_gives_the_services_verdict_with_the_chi_square_point() {
        let limits = ValidationLimits::default();
        let (r, set) = admit(clean(1), None, None, &limits, T0 + 1_800_000_000_000);
        let point = r.chi2_point.unwrap();
        assert!((point - chi2_quantile(0.999, 16)).abs() < 1e-12 && point > 12.0);
        assert_eq!(r.status, ResultStatus::Ok);
        let set = set.unwrap();
        assert_eq!(set.nc, set.measured);
        let set = set.nc;
        assert_eq!((set.version, set.cycle), (1, Some(1)));
        // Beyond the point: refused, the numbers kept for the metrologist, no set.
        let mut bad = clean(2);
        bad.chi2 = Some(43.0);
        bad.dof = Some(9);
        let (r, none) = admit(
            bad,
            Some(&set),
            Some(&set),
            &limits,
            T0 + 2 * 1_800_000_000_000,
        );
        assert!(none.is_none());
        assert_eq!(r.status, ResultStatus::Rejected);
        let why = r.reason.unwrap();
        assert!(
            why.contains("chi-square 43.0 beyond its 99.9 % point 27.88"),
            "{why}"
        );
        assert!(r.errors.is_some() && r.chi2_point.is_some());
        // A result the solver rejected stays as it is.
        let mut solver_no = clean(3);
        solver_no.status = ResultStatus::Rejected;
        solver_no.reason = Some("missing".into());
        let (r, none) = admit(solver_no.clone(), Some(&set), Some(&set), &limits, T0);
        assert!(none.is_none() && r == solver_no);
    }

    /// A prediction 150 combined sigmas from a measurement 11 s old is
    /// caught, while one that drifted as far as the rate limits allow is not; and the next
    /// true measurement is not rejected for its step from a far predicted set: it is
    /// admitted, and the NC gets it ramped from the served set.
    #[test]
    fn a_far_prediction_is_refused_and_never_blocks_a_measurement() {
        let limits = ValidationLimits::default();
        let (_, a) = admit(clean(1), None, None, &limits, T0 + 1_800_000_000_000);
        let measured = a.unwrap().measured;
        let t_m = clean(1).t_ns;
        let mut pred: BTreeMap<String, (f64, f64)> = clean_errors()
            .into_iter()
            .map(|(n, v)| (n, (v, 0.3)))
            .collect();
        let now = t_m + 11_000_000_000;
        assert!(inconsistent(&pred, &measured, t_m, now, 5.0, &limits).is_empty());
        pred.insert("EZ0B".into(), (40.0 + 41.8, 0.27));
        let why = inconsistent(&pred, &measured, t_m, now, 5.0, &limits);
        assert_eq!(why.len(), 1, "{why:?}");
        assert!(
            why[0].contains("EZ0B predicted 81.80 +- 0.27 um lies 64 combined sigmas"),
            "{why:?}"
        );
        // Twelve minutes later the same value is within the 4 um/min the limits allow.
        let later = t_m + 12 * units::NS_PER_MIN;
        assert!(inconsistent(&pred, &measured, t_m, later, 5.0, &limits).is_empty());
        // NaN disagrees.
        pred.insert("EA0C".into(), (f64::NAN, 1.0));
        let why = inconsistent(&pred, &measured, t_m, later, 5.0, &limits);
        assert!(
            why.len() == 1 && why[0].starts_with("EA0C predicted NaN"),
            "{why:?}"
        );

        // A predicted set 60 um off was served; the next measurement (the truth, 40 um) is
        // 60 um from it but 0 from the last measurement: admitted, and ramped for the NC.
        let mut far = measured.clone();
        far.version = 2;
        far.source = Source::Predicted;
        far.valid_from_ns = T0 + 1_800_000_000_000 + 11_000_000_000;
        far.errors.insert(ErrorName::from_static("EZ0B"), 100.0);
        let closed = far.valid_from_ns + units::NS_PER_MIN;
        let mut next = clean(2);
        next.t_ns = closed - 30_000_000_000;
        let (r, a) = admit(next.clone(), Some(&far), Some(&measured), &limits, closed);
        assert_eq!(r.status, ResultStatus::Ok, "{:?}", r.reason);
        let a = a.unwrap();
        assert_eq!((a.nc.version, a.measured.errors["EZ0B"]), (3, 40.0));
        // 50 um + 4 um/min over the minute since the predicted set: 54 um of the 60.
        assert!(
            (a.nc.errors["EZ0B"] - 46.0).abs() < 1e-9,
            "{:?}",
            a.nc.errors
        );
        assert!((a.nc.offsets["B_pivot_z_um"] - 46.0).abs() < 1e-9);
        assert!(
            a.nc.reason.contains("ramped to the step limit from set 2"),
            "{}",
            a.nc.reason
        );
        // Against the far set as the reference (the old behaviour) it would have been refused.
        let (r, none) = admit(next, Some(&far), Some(&far), &limits, closed);
        assert!(none.is_none() && r.reason.unwrap().contains("EZ0B step"));
    }

    /// Validation fails with exactly one reason containing every fragment, and no set follows.
    fn refused_with(
        r: &CycleResultMsg,
        prev: Option<&CompensationSet>,
        limits: &ValidationLimits,
        fragments: &[&str],
    ) {
        let v = validate(r, prev, limits);
        assert!(!v.ok, "passed: {r:?}");
        assert_eq!(v.reasons.len(), 1, "{:?}", v.reasons);
        for f in fragments {
            assert!(v.reasons[0].contains(f), "'{f}' not in '{}'", v.reasons[0]);
        }
        let e = next_set(prev, r, &v, T0 + 10_i64.pow(13)).unwrap_err();
        assert!(e.reasons.contains(&v.reasons[0]), "{e}");
    }

    #[test]
    fn a_clean_result_passes_and_yields_version_1_then_2() {
        let limits = ValidationLimits::default();
        let r1 = clean(1);
        let v1 = validate(&r1, None, &limits);
        assert!(v1.ok && v1.reasons.is_empty(), "{:?}", v1.reasons);
        let s1 = next_set(None, &r1, &v1, T0 + 100).unwrap();
        assert_eq!(s1.version, 1);
        assert_eq!(s1.valid_from_ns, T0 + 100);
        assert_eq!(s1.source, Source::Measured);
        assert_eq!(s1.cycle, Some(1));
        assert_eq!(s1.errors, typed(&clean_errors()).unwrap());
        assert_eq!(s1.sigma, typed(r1.sigma.as_ref().unwrap()).unwrap());
        assert_eq!(s1.offsets["C_pivot_x_um"], 15.0);
        assert!(s1.reason.contains("cycle 1"), "{}", s1.reason);

        // 45 um away from zero but only 5 um from the served value: the step is what counts.
        let mut r2 = clean(2);
        set_error(&mut r2, "EZ0B", 45.0);
        let v2 = validate(&r2, Some(&s1), &limits);
        assert!(v2.ok, "{:?}", v2.reasons);
        let s2 = next_set(Some(&s1), &r2, &v2, T0 + 200).unwrap();
        assert_eq!(s2.version, 2);
        assert_eq!(s2.errors["EZ0B"], 45.0);
        assert_eq!(s2.offsets["B_pivot_z_um"], 45.0);
    }

    #[test]
    fn a_result_rejected_by_the_solver_gives_its_reason() {
        let mut r = clean(1);
        r.status = ResultStatus::Rejected;
        r.reason = Some("step C-90/x did not trip".into());
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["rejected by the solver: step C-90/x did not trip"],
        );
    }

    #[test]
    fn a_rejected_result_without_numbers_gives_both_reasons() {
        let mut r = clean(1);
        r.status = ResultStatus::Rejected;
        r.reason = Some("did not converge".into());
        r.errors = None;
        r.sigma = None;
        r.chi2 = None;
        r.dof = None;
        let v = validate(&r, None, &ValidationLimits::default());
        assert!(!v.ok);
        assert!(
            v.reasons
                .contains(&"rejected by the solver: did not converge".to_string())
        );
        assert!(v.reasons.contains(&"no errors".to_string()));
        assert!(next_set(None, &r, &v, T0).is_err());
    }

    #[test]
    fn empty_errors_are_no_errors() {
        let mut r = clean(1);
        r.errors = Some(BTreeMap::new());
        refused_with(&r, None, &ValidationLimits::default(), &["no errors"]);
    }

    #[test]
    fn chi_square_beyond_its_point_is_refused_with_numbers() {
        let mut r = clean(1);
        r.chi2 = Some(41.2);
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["chi-square 41.2 beyond its 99.9 % point 39.25 for 16 dof"],
        );
        // Just inside passes.
        r.chi2 = Some(39.25);
        assert!(validate(&r, None, &ValidationLimits::default()).ok);
    }

    #[test]
    fn a_fit_that_cannot_be_checked_is_refused() {
        let mut r = clean(1);
        r.chi2 = None;
        refused_with(&r, None, &ValidationLimits::default(), &["no chi-square"]);
        let mut r = clean(1);
        r.dof = Some(0);
        refused_with(&r, None, &ValidationLimits::default(), &["0 dof"]);
        let mut r = clean(1);
        r.chi2 = Some(f64::NAN);
        refused_with(&r, None, &ValidationLimits::default(), &["chi-square NaN"]);
    }

    #[test]
    fn an_uncertainty_over_its_limit_is_refused() {
        let mut r = clean(1);
        set_sigma(&mut r, "EZ0B", 2.6);
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["EZ0B uncertainty 2.6 um over its limit 2.0 um"],
        );
        let mut r = clean(1);
        set_sigma(&mut r, "EB0C", 16.0);
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["EB0C uncertainty 16.0 urad over its limit 15.0 urad"],
        );
        // Barely over still reads as over.
        let mut r = clean(1);
        set_sigma(&mut r, "EX0B", 2.004);
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["EX0B uncertainty 2.004 um over its limit 2.0 um"],
        );
    }

    #[test]
    fn unusable_uncertainties_are_refused() {
        for (s, what) in [(f64::NAN, "NaN"), (-1.0, "-1"), (0.0, "0")] {
            let mut r = clean(1);
            set_sigma(&mut r, "EY0C", s);
            refused_with(
                &r,
                None,
                &ValidationLimits::default(),
                &["EY0C uncertainty", what, "not a positive finite number"],
            );
        }
        let mut r = clean(1);
        r.sigma.as_mut().unwrap().remove("EX0C");
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["EX0C has no uncertainty"],
        );
        let mut r = clean(1);
        r.sigma = None;
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["no uncertainties"],
        );
    }

    #[test]
    fn an_unbelievable_error_is_refused() {
        let mut r = clean(1);
        set_error(&mut r, "EZ0B", -250.0);
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["EZ0B 250.0 um from zero beyond the believable 200.0 um"],
        );
        let mut r = clean(1);
        set_error(&mut r, "EA0C", 600.0);
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["EA0C 600.0 urad from zero beyond the believable 500.0 urad"],
        );
    }

    #[test]
    fn missing_non_finite_and_foreign_errors_are_refused() {
        let mut r = clean(1);
        r.errors.as_mut().unwrap().remove("EY0C");
        r.sigma.as_mut().unwrap().remove("EY0C");
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["EY0C missing from the errors"],
        );
        let mut r = clean(1);
        set_error(&mut r, "EX0C", f64::INFINITY);
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["EX0C = inf is not a finite number"],
        );
        let mut r = clean(1);
        set_error(&mut r, "EC0B", 1.0);
        refused_with(
            &r,
            None,
            &ValidationLimits::default(),
            &["unexpected error EC0B"],
        );
    }

    #[test]
    fn the_step_limit_grows_with_the_time_since_the_served_set() {
        let limits = ValidationLimits::default();
        let r1 = clean(1);
        let s1 = next_set(None, &r1, &validate(&r1, None, &limits), r1.t_ns).unwrap();
        // A 90 um step: refused 5 min after the served set (limit 70 um), accepted an hour
        // after it (limit 290 um).
        let mut r2 = clean(2);
        set_error(&mut r2, "EZ0B", 130.0);
        r2.t_ns = s1.valid_from_ns + 5 * units::NS_PER_MIN;
        let v = validate(&r2, Some(&s1), &limits);
        assert!(
            !v.ok && v.reasons[0].contains("limit 70.0 um (50.0 um + 4.0 um/min over 5 min)"),
            "{:?}",
            v.reasons
        );
        r2.t_ns = s1.valid_from_ns + 60 * units::NS_PER_MIN;
        assert!(validate(&r2, Some(&s1), &limits).ok);
    }

    #[test]
    fn a_step_over_the_limit_is_refused_with_both_values() {
        // Without the allowance for elapsed time (the cycles here are an hour apart).
        let limits = ValidationLimits {
            max_rate_um_per_min: 0.0,
            max_rate_urad_per_min: 0.0,
            ..Default::default()
        };
        let r1 = clean(1);
        let s1 = next_set(None, &r1, &validate(&r1, None, &limits), T0).unwrap();
        let mut r2 = clean(2);
        set_error(&mut r2, "EZ0B", 103.0);
        refused_with(
            &r2,
            Some(&s1),
            &limits,
            &[
                "EZ0B step 63.0 um",
                "served value 40.0 um",
                "to 103.0 um",
                "limit 50.0 um",
            ],
        );
        let mut r2 = clean(2);
        set_error(&mut r2, "EA0C", -90.5);
        refused_with(
            &r2,
            Some(&s1),
            &limits,
            &[
                "EA0C step 110.5 urad",
                "served value 20.0 urad",
                "to -90.5 urad",
                "100.0 urad",
            ],
        );
        // Without a served set the same value is only checked against zero.
        assert!(validate(&r2, None, &limits).ok);
    }

    #[test]
    fn a_step_against_a_served_set_without_the_value_is_refused() {
        let limits = ValidationLimits::default();
        let r1 = clean(1);
        let mut s1 = next_set(None, &r1, &validate(&r1, None, &limits), T0).unwrap();
        s1.errors.remove("EB0C");
        refused_with(
            &clean(2),
            Some(&s1),
            &limits,
            &["EB0C has no value in the served set 1"],
        );
    }

    #[test]
    fn an_older_cycle_than_the_served_one_is_refused() {
        let limits = ValidationLimits::default();
        let r5 = clean(5);
        let s = next_set(None, &r5, &validate(&r5, None, &limits), T0).unwrap();
        refused_with(
            &clean(4),
            Some(&s),
            &limits,
            &["cycle 4 is not newer than cycle 5 of the served set 1"],
        );
        refused_with(&clean(5), Some(&s), &limits, &["cycle 5 is not newer"]);
    }

    #[test]
    fn unusable_limits_refuse_instead_of_passing_everything() {
        let limits = ValidationLimits {
            max_sigma_um: f64::NAN,
            ..ValidationLimits::default()
        };
        refused_with(
            &clean(1),
            None,
            &limits,
            &["limit max_sigma_um = NaN is not a positive finite number"],
        );
        let limits = ValidationLimits {
            chi2_quantile: 1.0,
            ..ValidationLimits::default()
        };
        refused_with(&clean(1), None, &limits, &["limit chi2_quantile = 1"]);
    }

    #[test]
    fn every_failed_check_is_named_at_once() {
        let mut r = clean(1);
        r.chi2 = Some(100.0);
        set_sigma(&mut r, "EZ0B", 3.0);
        set_error(&mut r, "EX0B", 300.0);
        let v = validate(&r, None, &ValidationLimits::default());
        assert_eq!(v.reasons.len(), 3, "{:?}", v.reasons);
        let e = next_set(None, &r, &v, T0).unwrap_err();
        assert_eq!(e.reasons, v.reasons);
        assert!(e.to_string().contains("chi-square 100.0"), "{e}");
    }

    #[test]
    fn a_forged_validation_does_not_produce_a_set() {
        let ok = Validation {
            ok: true,
            reasons: vec![],
        };
        let mut r = clean(1);
        r.status = ResultStatus::Rejected;
        r.reason = Some("singular".into());
        let e = next_set(None, &r, &ok, T0).unwrap_err();
        assert_eq!(
            e.reasons,
            vec!["rejected by the solver: singular".to_string()]
        );

        let mut r = clean(1);
        set_error(&mut r, "EZ0B", f64::NAN);
        let e = next_set(None, &r, &ok, T0).unwrap_err();
        assert!(e.reasons[0].contains("EZ0B = NaN"), "{e}");

        let inconsistent = Validation {
            ok: true,
            reasons: vec!["EZ0B uncertainty 3.0 um over its limit 2.0 um".into()],
        };
        let e = next_set(None, &clean(1), &inconsistent, T0).unwrap_err();
        assert_eq!(e.reasons.len(), 2, "{e}");

        let failed_silently = Validation {
            ok: false,
            reasons: vec![],
        };
        let e = next_set(None, &clean(1), &failed_silently, T0).unwrap_err();
        assert_eq!(
            e.reasons,
            vec!["the result did not pass validation".to_string()]
        );
    }

    #[test]
    fn a_set_never_lies_before_the_served_one() {
        let limits = ValidationLimits::default();
        let r1 = clean(1);
        let s1 = next_set(None, &r1, &validate(&r1, None, &limits), T0 + 1000).unwrap();
        let r2 = clean(2);
        let v2 = validate(&r2, Some(&s1), &limits);
        let e = next_set(Some(&s1), &r2, &v2, T0 + 999).unwrap_err();
        assert!(e.reasons[0].contains("before the served set 1"), "{e}");
        assert!(next_set(Some(&s1), &r2, &v2, T0 + 1000).is_ok());

        let mut last = s1.clone();
        last.version = u64::MAX;
        let e = next_set(Some(&last), &r2, &v2, T0 + 2000).unwrap_err();
        assert!(e.reasons[0].contains("u64::MAX"), "{e}");
    }

    #[test]
    fn offsets_follow_the_table_bc_convention() {
        let o = offsets(&typed(&clean_errors()).unwrap());
        assert_eq!(
            o,
            map(&[
                ("B_pivot_x_um", 12.0),
                ("B_pivot_z_um", 40.0),
                ("C_pivot_x_um", 15.0),
                ("C_pivot_y_um", -5.0),
                ("C_dir_x_urad", -30.0),
                ("C_dir_y_urad", -20.0),
                ("C_tilt_a_urad", 20.0),
                ("C_tilt_b_urad", -30.0),
            ])
        );
        // Without EX0C the C line's X is unknown, and is not guessed.
        let mut e = typed(&clean_errors()).unwrap();
        e.remove("EX0C");
        e.insert(ErrorName::from_static("EY0C"), f64::NAN);
        let o = offsets(&e);
        assert!(!o.contains_key("C_pivot_x_um") && !o.contains_key("C_pivot_y_um"));
        assert_eq!(o["B_pivot_x_um"], 12.0);
    }

    fn served(errors: BTreeMap<ErrorName, f64>) -> CompensationSet {
        CompensationSet {
            version: 1,
            valid_from_ns: T0,
            source: Source::Measured,
            cycle: Some(1),
            offsets: offsets(&errors),
            sigma: BTreeMap::new(),
            errors,
            reason: String::new(),
        }
    }

    #[test]
    fn repeated_ramping_reaches_the_target_and_never_exceeds_the_step() {
        let from = typed(&clean_errors()).unwrap();
        let to = tmap(&[
            ("EX0B", -20.0),
            ("EZ0B", 163.0),
            ("EY0C", -5.0),
            ("EX0C", 3.4),
            ("EA0C", -250.0),
            ("EB0C", 170.0),
        ]);
        let (step_um, step_urad) = (10.0, 25.0);
        let mut set = served(from);
        let mut n = 0;
        while set.errors != to {
            let next = ramp(&set, &to, step_um, step_urad);
            for (name, &v) in &next {
                let before = set.errors[name];
                let max = if name.is_angular() {
                    step_urad
                } else {
                    step_um
                };
                assert!(
                    (v - before).abs() <= max * (1.0 + 1e-12),
                    "{name}: {before} -> {v}"
                );
                // Never past the target.
                assert!((to[name] - v).abs() <= (to[name] - before).abs(), "{name}");
            }
            set = served(next);
            n += 1;
            assert!(n <= 13, "not there after {n} steps: {:?}", set.errors);
        }
        // EZ0B needs ceil(123 / 10) = 13 steps, the slowest of all.
        assert_eq!(n, 13);
    }

    #[test]
    fn ramp_holds_and_starts_from_zero_where_it_must() {
        let set = served(tmap(&[("EX0B", 5.0), ("EZ0B", 1.0)]));
        let to = tmap(&[("EX0B", f64::NAN), ("EY0C", 30.0)]);
        let out = ramp(&set, &to, 10.0, 10.0);
        // EX0B: the target is not a number, so the served value holds; EZ0B: no target.
        assert_eq!(out["EX0B"], 5.0);
        assert_eq!(out["EZ0B"], 1.0);
        // EY0C: new, from no compensation at all.
        assert_eq!(out["EY0C"], 10.0);
        // An unusable step moves nothing.
        let out = ramp(&set, &tmap(&[("EX0B", 50.0)]), f64::NAN, 10.0);
        assert_eq!(out["EX0B"], 5.0);
        let out = ramp(&set, &tmap(&[("EX0B", 50.0)]), -1.0, 10.0);
        assert_eq!(out["EX0B"], 5.0);
    }

    proptest::proptest! {
        #[test]
        fn ramp_never_exceeds_its_step(
            a in -500.0..500.0_f64, b in -500.0..500.0_f64, step in 0.001..100.0_f64
        ) {
            let set = served(tmap(&[("EZ0B", a), ("EB0C", a)]));
            let to = tmap(&[("EZ0B", b), ("EB0C", b)]);
            let out = ramp(&set, &to, step, 2.0 * step);
            proptest::prop_assert!((out["EZ0B"] - a).abs() <= step * (1.0 + 1e-12) + 1e-12);
            proptest::prop_assert!((out["EB0C"] - a).abs() <= 2.0 * step * (1.0 + 1e-12) + 1e-12);
            proptest::prop_assert!((b - out["EZ0B"]).abs() <= (b - a).abs());
        }
    }

    #[test]
    fn the_compensation_message_has_the_contract_fields() {
        let limits = ValidationLimits::default();
        let r = clean(3);
        let set = next_set(None, &r, &validate(&r, None, &limits), T0 + 5).unwrap();
        let m = compensation_message(&set);
        assert_eq!(m["version"], 1);
        assert_eq!(m["valid_from_ns"], T0 + 5);
        assert_eq!(m["source"], "measured");
        assert_eq!(m["errors"]["EZ0B"], 40.0);
        assert_eq!(m["offsets"]["C_pivot_x_um"], 15.0);
        assert_eq!(m["sigma"]["EA0C"], 7.0);
        assert_eq!(m["cycle"], 3);
        assert_eq!(
            serde_json::to_value(Source::Predicted).unwrap(),
            Value::from("predicted")
        );
        // A set survives a round trip through its own serialisation.
        let back: CompensationSet =
            serde_json::from_str(&serde_json::to_string(&set).unwrap()).unwrap();
        assert_eq!(back, set);
    }

    #[test]
    fn limits_default_from_an_empty_config_and_refuse_unknown_keys() {
        let l: ValidationLimits = toml::from_str("").unwrap();
        assert_eq!(l, ValidationLimits::default());
        let l: ValidationLimits = toml::from_str("max_step_um = 20.0").unwrap();
        assert_eq!(l.max_step_um, 20.0);
        assert_eq!(l.max_sigma_um, 2.0);
        assert!(toml::from_str::<ValidationLimits>("max_step = 20.0").is_err());
    }
}
