//! Verification of the tool-setter results against a reference instrument (an R-test, a
//! double ballbar evaluation, ...): a client gives the reference's location errors at its
//! reference time ([`ReferenceResult`]); the machine's accepted tool-setter results are brought
//! to that time (interpolated between the results on either side, or the nearest one) and each
//! common error's difference is judged against the combined standard uncertainty
//! ([`compare`], [`Verification`]).
//!
//! Both instruments give the same quantities: the apparent (tool-relative) location errors
//! named and in the units of the `/cycle/result` message (`EX0B` um, `EA0C` urad, ...). A
//! reference whose frame differs (another zero pose, a table-fixed frame) must be brought to
//! this one before it is posted; `frame_note` says what was done.
//!
//! Pure: the service clock comes in as an argument, the setter results as data.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use driftwatch_core::error_name::ErrorName;
use driftwatch_core::recording::{CycleResultMsg, ResultStatus};
use driftwatch_core::units;

/// The coverage factor of the default configuration: a difference beyond 2 combined standard
/// uncertainties exceeds (about 5 % of agreeing pairs of a normal error, per error).
pub const DEFAULT_K: f64 = 2.0;

/// The earliest reference time taken, 2000-01-01T00:00:00Z in ns: an earlier one is a time in
/// s or ms, or a zero.
pub const EARLIEST_T_NS: i64 = 946_684_800_000_000_000;

/// How far ahead of the service clock a reference may be stamped (the instrument's computer
/// is not the service's clock; a reference time is the mean of readings already taken).
pub const MAX_AHEAD_NS: i64 = 10 * units::NS_PER_MIN;

/// Largest magnitude of a reference value taken, um or urad: far beyond any location error a
/// machine that runs has, and beyond the validation limits of a setter result.
pub const MAX_ABS_VALUE: f64 = 10_000.0;

/// Longest text of `instrument`, in characters.
pub const MAX_INSTRUMENT_CHARS: usize = 64;

/// Longest text of `frame_note` and `source`, in characters.
pub const MAX_NOTE_CHARS: usize = 1024;

/// A reference instrument's result, as a client posts it (JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ReferenceResult {
    /// The instrument, e.g. `rtest` (1 to 64 characters).
    #[cfg_attr(feature = "openapi", schema(min_length = 1, max_length = 64))]
    pub instrument: String,
    /// The reference time: the mean time of its readings, ns since the Unix epoch (from
    /// 2000-01-01, at most 10 min ahead of the service clock).
    #[cfg_attr(feature = "openapi", schema(minimum = 946_684_800_000_000_000_i64))]
    pub t_ns: i64,
    /// Location errors by name, as in `/cycle/result` (`EX0B` um, `EA0C` urad, ...): only
    /// errors the machine identifies, finite, at most 10 000 in magnitude.
    pub errors: BTreeMap<String, f64>,
    /// One standard uncertainty of each error in `errors` (same names and units), > 0.
    pub sigma: BTreeMap<String, f64>,
    /// How the reference's frame was brought to the tool setter's (free text, at most 1024
    /// characters).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(max_length = 1024))]
    pub frame_note: Option<String>,
    /// Where it comes from: a file, a test name (free text, at most 1024 characters).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(max_length = 1024))]
    pub source: Option<String>,
}

/// How the setter's values were brought to the reference time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub enum Method {
    /// Linear interpolation between the accepted results just before and just after it.
    Interpolated,
    /// The accepted result nearest in time (none on one side within the gap, or one at the
    /// reference time itself).
    Nearest,
}

impl Method {
    pub fn as_str(self) -> &'static str {
        match self {
            Method::Interpolated => "interpolated",
            Method::Nearest => "nearest",
        }
    }
}

/// One error of a verification.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ErrorComparison {
    /// `um` or `urad`.
    pub unit: String,
    pub reference: f64,
    pub reference_sigma: f64,
    /// The tool setter's value at the reference time.
    pub setter: f64,
    pub setter_sigma: f64,
    /// reference - setter.
    pub difference: f64,
    /// sqrt(reference_sigma^2 + setter_sigma^2).
    pub combined_sigma: f64,
    /// difference / combined_sigma.
    pub z: f64,
    /// |difference| > k * combined_sigma.
    pub exceeds: bool,
}

/// A reference result compared with the tool setter's at its time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Verification {
    pub machine_id: String,
    /// The reference time, ns since the Unix epoch.
    pub t_ns: i64,
    pub instrument: String,
    pub method: Method,
    /// The setter cycles used: the one before and the one after (interpolated), or the
    /// nearest.
    pub setter_cycles: Vec<i64>,
    /// The time of the setter values compared: the reference time when interpolated, the
    /// nearest result's time otherwise.
    pub setter_t_ns: i64,
    /// The longest time between the reference and a setter result used, ns.
    pub gap_ns: i64,
    /// The coverage factor of `exceeds`.
    pub k: f64,
    /// Each error of the reference.
    pub per_error: BTreeMap<String, ErrorComparison>,
    /// Whether any error exceeds.
    pub exceeds_any: bool,
    /// The error with the largest |z|, and that z (signed).
    pub worst_error: String,
    pub worst_z: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_note: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
}

impl Verification {
    /// The latest setter cycle compared (the cycle an alert names): the nearest one, or the
    /// one after the reference time when interpolated.
    pub fn latest_cycle(&self) -> i64 {
        self.setter_cycles.last().copied().unwrap_or(0)
    }

    /// One line for the log and alerts: what exceeds (or that nothing does), and how the
    /// setter's values were had.
    pub fn summary(&self) -> String {
        let how = match self.method {
            Method::Interpolated => format!(
                "interpolated between cycles {}",
                self.setter_cycles
                    .iter()
                    .map(i64::to_string)
                    .collect::<Vec<_>>()
                    .join(" and ")
            ),
            Method::Nearest => format!(
                "cycle {} ({:.1} min from it)",
                self.latest_cycle(),
                units::ns_to_min(self.gap_ns)
            ),
        };
        let over: Vec<String> = self
            .per_error
            .iter()
            .filter(|(_, c)| c.exceeds)
            .map(|(n, c)| {
                format!(
                    "{n} {:+.2} {} (z {:+.2}, k sigma {:.2})",
                    c.difference,
                    c.unit,
                    c.z,
                    self.k * c.combined_sigma
                )
            })
            .collect();
        if over.is_empty() {
            format!(
                "{} agrees with the tool setter ({how}): every difference within {} combined sigma, largest |z| {:.2} ({})",
                self.instrument,
                self.k,
                self.worst_z.abs(),
                self.worst_error
            )
        } else {
            format!(
                "{} differs from the tool setter ({how}) beyond {} combined sigma: {}",
                self.instrument,
                self.k,
                over.join(", ")
            )
        }
    }
}

/// Why a reference is refused or cannot be compared.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum VerifyError {
    /// A field of the reference that cannot be taken (`field` is its path, e.g. `sigma.EZ0B`).
    #[error("{field}: {message}")]
    BadReference { field: String, message: String },
    /// No accepted tool-setter result holding the reference's errors within `max_gap_ns` of
    /// the reference time.
    #[error(
        "no accepted tool-setter result with {errors} lies within {max_gap_min} min of the reference time {t_ns}{nearest}"
    )]
    NoSetterResult {
        t_ns: i64,
        errors: String,
        max_gap_min: f64,
        /// What the nearest accepted result was, if any.
        nearest: String,
    },
    /// A comparison setting that is not valid (k, the gap).
    #[error("verification setting {0}")]
    Setting(String),
}

fn bad(field: impl Into<String>, message: impl Into<String>) -> VerifyError {
    VerifyError::BadReference {
        field: field.into(),
        message: message.into(),
    }
}

impl ReferenceResult {
    /// Checks the reference against the machine's identified errors and the service clock:
    /// an instrument named, a plausible time, at least one error, each an identified error
    /// with a finite value and a standard uncertainty > 0, a sigma for each value and none
    /// without one. The first fault is named by its field.
    pub fn validate(&self, identified: &[ErrorName], now_ns: i64) -> Result<(), VerifyError> {
        let n = self.instrument.chars().count();
        if self.instrument.trim().is_empty() || n > MAX_INSTRUMENT_CHARS {
            return Err(bad(
                "instrument",
                format!("must name the instrument in 1 to {MAX_INSTRUMENT_CHARS} characters"),
            ));
        }
        for (field, text) in [("frame_note", &self.frame_note), ("source", &self.source)] {
            if text
                .as_ref()
                .is_some_and(|t| t.chars().count() > MAX_NOTE_CHARS)
            {
                return Err(bad(field, format!("at most {MAX_NOTE_CHARS} characters")));
            }
        }
        if self.t_ns < EARLIEST_T_NS {
            return Err(bad(
                "t_ns",
                format!(
                    "{} is before 2000-01-01: the reference time is in ns since the Unix epoch",
                    self.t_ns
                ),
            ));
        }
        if self.t_ns > now_ns.saturating_add(MAX_AHEAD_NS) {
            return Err(bad(
                "t_ns",
                format!(
                    "{} is {:.1} min ahead of the service clock ({now_ns}); a reference time is the mean time of readings already taken",
                    self.t_ns,
                    units::ns_to_min(self.t_ns - now_ns)
                ),
            ));
        }
        if self.errors.is_empty() {
            return Err(bad("errors", "no error given"));
        }
        let names: Vec<&str> = identified.iter().map(ErrorName::as_str).collect();
        for (name, value) in &self.errors {
            let field = format!("errors.{name}");
            if let Err(e) = ErrorName::parse(name) {
                return Err(bad(field, e.to_string()));
            }
            if !names.contains(&name.as_str()) {
                return Err(bad(
                    field,
                    format!(
                        "the machine does not identify {name}; its errors are {}",
                        names.join(", ")
                    ),
                ));
            }
            if !value.is_finite() || value.abs() > MAX_ABS_VALUE {
                return Err(bad(
                    field,
                    format!("{value} is not a finite value within +-{MAX_ABS_VALUE}"),
                ));
            }
            match self.sigma.get(name) {
                None => {
                    return Err(bad(
                        format!("sigma.{name}"),
                        "missing: every error needs its standard uncertainty",
                    ));
                }
                Some(s) if !(units::positive(*s) && *s <= MAX_ABS_VALUE) => {
                    return Err(bad(
                        format!("sigma.{name}"),
                        format!(
                            "{s} is not a standard uncertainty > 0 (and at most {MAX_ABS_VALUE})"
                        ),
                    ));
                }
                Some(_) => {}
            }
        }
        if let Some(name) = self.sigma.keys().find(|n| !self.errors.contains_key(*n)) {
            return Err(bad(
                format!("sigma.{name}"),
                "an uncertainty without a value in errors",
            ));
        }
        Ok(())
    }
}

/// One accepted setter result as far as a comparison needs it.
struct SetterPoint<'a> {
    cycle: i64,
    t_ns: i64,
    errors: &'a BTreeMap<String, f64>,
    sigma: &'a BTreeMap<String, f64>,
}

/// The accepted results holding every one of `names` with a finite value and a sigma > 0,
/// in time order (then cycle).
fn usable<'a>(results: &'a [CycleResultMsg], names: &[&String]) -> Vec<SetterPoint<'a>> {
    let mut out: Vec<SetterPoint> = results
        .iter()
        .filter(|r| r.status == ResultStatus::Ok)
        .filter_map(|r| {
            let (errors, sigma) = (r.errors.as_ref()?, r.sigma.as_ref()?);
            let complete = names.iter().all(|n| {
                errors.get(*n).is_some_and(|v| v.is_finite())
                    && sigma.get(*n).is_some_and(|s| units::positive(*s))
            });
            complete.then_some(SetterPoint {
                cycle: r.cycle,
                t_ns: r.t_ns,
                errors,
                sigma,
            })
        })
        .collect();
    out.sort_by_key(|p| (p.t_ns, p.cycle));
    out
}

/// Compares a reference with the machine's tool-setter results (any order; only accepted
/// ones, `status: ok`, holding every error of the reference, are taken). With accepted results
/// both before and after the reference time within `max_gap_ns`, each error is interpolated
/// linearly to the reference time between the last before and the first after, its sigma
/// propagated with the interpolation weights (the two taken as independent); otherwise the
/// nearest within `max_gap_ns` is taken as it is (a result at the reference time itself is
/// the nearest). None within `max_gap_ns` is refused. For each error of the reference:
/// difference = reference - setter, combined sigma = sqrt(s_ref^2 + s_setter^2),
/// z = difference / combined, exceeds when |difference| > k x combined.
///
/// The reference is expected to have passed [`ReferenceResult::validate`]; its values are
/// checked for being finite here too.
pub fn compare(
    machine_id: &str,
    reference: &ReferenceResult,
    setter_results: &[CycleResultMsg],
    max_gap_ns: i64,
    k: f64,
) -> Result<Verification, VerifyError> {
    if !(units::positive(k) && k.is_finite()) {
        return Err(VerifyError::Setting(format!("k must be > 0, not {k}")));
    }
    if max_gap_ns < 0 {
        return Err(VerifyError::Setting(format!(
            "max_gap_ns must be >= 0, not {max_gap_ns}"
        )));
    }
    if reference.errors.is_empty() {
        return Err(bad("errors", "no error given"));
    }
    for (name, v) in &reference.errors {
        let s = reference.sigma.get(name).copied().unwrap_or(f64::NAN);
        if !(v.is_finite() && units::positive(s) && s.is_finite()) {
            return Err(bad(
                format!("errors.{name}"),
                format!("value {v} with sigma {s} cannot be compared"),
            ));
        }
    }
    let names: Vec<&String> = reference.errors.keys().collect();
    let points = usable(setter_results, &names);
    let t = reference.t_ns;
    let within = |p: &&SetterPoint| (p.t_ns - t).abs() <= max_gap_ns;
    let before = points.iter().rev().find(|p| p.t_ns <= t).filter(within);
    let after = points.iter().find(|p| p.t_ns >= t).filter(within);
    // (point, weight) pairs whose weighted sum is the setter's value at the reference time.
    let (method, used, setter_t_ns, gap_ns): (Method, Vec<(&SetterPoint, f64)>, i64, i64) =
        match (before, after) {
            (Some(b), Some(a)) if b.t_ns < t && t < a.t_ns => {
                let w_after = (t - b.t_ns) as f64 / (a.t_ns - b.t_ns) as f64;
                (
                    Method::Interpolated,
                    vec![(b, 1.0 - w_after), (a, w_after)],
                    t,
                    (t - b.t_ns).max(a.t_ns - t),
                )
            }
            (b, a) => {
                // Nearest; on a tie the later result (the machine's newer state).
                let nearest = match (b, a) {
                    (Some(b), Some(a)) if t - b.t_ns < a.t_ns - t => Some(b),
                    (_, Some(a)) => Some(a),
                    (b, None) => b,
                };
                let Some(p) = nearest else {
                    return Err(no_setter_result(reference, &points, max_gap_ns));
                };
                (Method::Nearest, vec![(p, 1.0)], p.t_ns, (p.t_ns - t).abs())
            }
        };
    let mut per_error = BTreeMap::new();
    for (name, r) in &reference.errors {
        let s_ref = reference.sigma[name];
        let setter: f64 = used.iter().map(|(p, w)| w * p.errors[name]).sum();
        let setter_sigma = used
            .iter()
            .map(|(p, w)| (w * p.sigma[name]).powi(2))
            .sum::<f64>()
            .sqrt();
        let difference = r - setter;
        let combined_sigma = s_ref.hypot(setter_sigma);
        per_error.insert(
            name.clone(),
            ErrorComparison {
                unit: ErrorName::parse(name)
                    .map_or("um", |n| n.unit())
                    .to_string(),
                reference: *r,
                reference_sigma: s_ref,
                setter,
                setter_sigma,
                difference,
                combined_sigma,
                z: difference / combined_sigma,
                exceeds: difference.abs() > k * combined_sigma,
            },
        );
    }
    let (worst_error, worst_z) = per_error.iter().map(|(n, c)| (n.clone(), c.z)).fold(
        (String::new(), 0.0_f64),
        |acc, (n, z)| {
            if acc.0.is_empty() || z.abs() > acc.1.abs() {
                (n, z)
            } else {
                acc
            }
        },
    );
    Ok(Verification {
        machine_id: machine_id.to_string(),
        t_ns: t,
        instrument: reference.instrument.clone(),
        method,
        setter_cycles: used.iter().map(|(p, _)| p.cycle).collect(),
        setter_t_ns,
        gap_ns,
        k,
        exceeds_any: per_error.values().any(|c| c.exceeds),
        per_error,
        worst_error,
        worst_z,
        frame_note: reference.frame_note.clone(),
        source: reference.source.clone(),
    })
}

fn no_setter_result(
    reference: &ReferenceResult,
    points: &[SetterPoint],
    max_gap_ns: i64,
) -> VerifyError {
    let t = reference.t_ns;
    let nearest = points
        .iter()
        .min_by_key(|p| (p.t_ns - t).unsigned_abs())
        .map_or_else(
            || " (the machine has no accepted result holding them)".to_string(),
            |p| {
                format!(
                    " (the nearest, cycle {}, is {:.1} min {})",
                    p.cycle,
                    units::ns_to_min((p.t_ns - t).abs()),
                    if p.t_ns < t { "before" } else { "after" }
                )
            },
        );
    VerifyError::NoSetterResult {
        t_ns: t,
        errors: reference
            .errors
            .keys()
            .cloned()
            .collect::<Vec<_>>()
            .join(", "),
        max_gap_min: units::ns_to_min(max_gap_ns),
        nearest,
    }
}

/// The `[verification]` section of the service configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VerificationConfig {
    /// Coverage factor: a difference beyond k combined standard uncertainties exceeds.
    pub k: f64,
    /// The longest time between the reference and a setter result compared with it, min.
    pub max_gap_min: f64,
    /// Verifications kept per machine; the oldest beyond are deleted.
    pub kept: i64,
}

impl Default for VerificationConfig {
    fn default() -> Self {
        VerificationConfig {
            k: DEFAULT_K,
            max_gap_min: 60.0,
            kept: 10_000,
        }
    }
}

impl VerificationConfig {
    pub fn validate(&self) -> Result<(), String> {
        if !(units::positive(self.k) && self.k <= 100.0) {
            return Err(format!(
                "verification.k must be in (0, 100], not {}",
                self.k
            ));
        }
        if !(units::positive(self.max_gap_min) && self.max_gap_min <= 7.0 * 24.0 * 60.0) {
            return Err(format!(
                "verification.max_gap_min must be in (0, 10080] (a week), not {}",
                self.max_gap_min
            ));
        }
        if self.kept < 1 {
            return Err(format!(
                "verification.kept must be at least 1, not {}",
                self.kept
            ));
        }
        Ok(())
    }

    pub fn max_gap_ns(&self) -> i64 {
        units::min_to_ns(self.max_gap_min)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: i64 = units::NS_PER_MIN;
    const T0: i64 = 1_772_431_200_000_000_000;

    fn names() -> Vec<ErrorName> {
        ["EX0B", "EZ0B", "EY0C", "EX0C", "EA0C", "EB0C"]
            .iter()
            .map(|n| ErrorName::parse(n).unwrap())
            .collect()
    }

    fn map(pairs: &[(&str, f64)]) -> BTreeMap<String, f64> {
        pairs.iter().map(|(k, v)| (k.to_string(), *v)).collect()
    }

    /// An accepted setter result at `T0 + minute`, EZ0B drifting linearly by 0.5 um/min from
    /// 10 um, EA0C constant at 20 urad.
    fn setter(cycle: i64, minute: i64, sigma_z: f64) -> CycleResultMsg {
        CycleResultMsg {
            cycle,
            t_ns: T0 + minute * MIN,
            status: ResultStatus::Ok,
            reason: None,
            errors: Some(map(&[("EZ0B", 10.0 + 0.5 * minute as f64), ("EA0C", 20.0)])),
            sigma: Some(map(&[("EZ0B", sigma_z), ("EA0C", 3.0)])),
            residual_rms_um: Some(0.5),
            chi2: None,
            dof: None,
            n_detections: None,
            nuisance: None,
            redundancy_um: None,
            chi2_point: None,
            geometry: None,
            notes: None,
        }
    }

    fn reference(minute: i64, ez0b: f64, sigma: f64) -> ReferenceResult {
        ReferenceResult {
            instrument: "rtest".into(),
            t_ns: T0 + minute * MIN,
            errors: map(&[("EZ0B", ez0b)]),
            sigma: map(&[("EZ0B", sigma)]),
            frame_note: None,
            source: Some("test".into()),
        }
    }

    #[test]
    fn interpolation_is_exact_on_a_linear_drift() {
        let results = [setter(1, 0, 0.4), setter(2, 30, 0.4), setter(3, 60, 0.4)];
        // 12 min after cycle 2: the drift gives 10 + 0.5 * 42 = 31 um.
        let r = reference(42, 31.0, 0.3);
        let v = compare("m1", &r, &results, 60 * MIN, DEFAULT_K).unwrap();
        assert_eq!(v.method, Method::Interpolated);
        assert_eq!(v.setter_cycles, vec![2, 3]);
        assert_eq!(v.setter_t_ns, r.t_ns);
        assert_eq!(v.gap_ns, 18 * MIN);
        let c = &v.per_error["EZ0B"];
        assert!((c.setter - 31.0).abs() < 1e-12, "{}", c.setter);
        assert!(c.difference.abs() < 1e-12);
        assert!(!c.exceeds && !v.exceeds_any);
        assert_eq!(c.unit, "um");
        assert_eq!(v.worst_error, "EZ0B");
        // Results given out of order, a rejected one in between: the same answer.
        let mut rejected = setter(9, 40, 0.4);
        rejected.status = ResultStatus::Rejected;
        let shuffled = [
            setter(3, 60, 0.4),
            rejected,
            setter(1, 0, 0.4),
            setter(2, 30, 0.4),
        ];
        let w = compare("m1", &r, &shuffled, 60 * MIN, DEFAULT_K).unwrap();
        assert_eq!(w, v);
    }

    #[test]
    fn sigma_is_propagated_with_the_interpolation_weights() {
        // Before: sigma 0.3 at 0 min; after: 0.6 at 40 min; the reference at 10 min: weights
        // 0.75 and 0.25, setter sigma sqrt((0.75*0.3)^2 + (0.25*0.6)^2).
        let results = [setter(1, 0, 0.3), setter(2, 40, 0.6)];
        let r = reference(10, 15.0, 0.2);
        let v = compare("m1", &r, &results, 60 * MIN, DEFAULT_K).unwrap();
        let c = &v.per_error["EZ0B"];
        let want = (0.75_f64 * 0.3).hypot(0.25 * 0.6);
        assert!((c.setter_sigma - want).abs() < 1e-12, "{}", c.setter_sigma);
        assert!((c.combined_sigma - 0.2_f64.hypot(want)).abs() < 1e-12);
        assert!((c.z - c.difference / c.combined_sigma).abs() < 1e-12);
        // The interpolated sigma is below either end's: the two are taken as independent.
        assert!(c.setter_sigma < 0.3);
        // At the nearest result itself, its own sigma.
        let v = compare("m1", &reference(0, 10.0, 0.2), &results, 60 * MIN, 2.0).unwrap();
        assert_eq!(v.per_error["EZ0B"].setter_sigma, 0.3);
    }

    #[test]
    fn nearest_when_one_side_is_missing_or_beyond_the_gap_or_at_the_time_itself() {
        let results = [setter(1, 0, 0.4), setter(2, 100, 0.4)];
        // 20 min after cycle 1, cycle 2 is 80 min away: beyond a 60 min gap.
        let v = compare("m1", &reference(20, 20.0, 0.3), &results, 60 * MIN, 2.0).unwrap();
        assert_eq!(v.method, Method::Nearest);
        assert_eq!((v.setter_cycles.clone(), v.gap_ns), (vec![1], 20 * MIN));
        assert_eq!(v.setter_t_ns, T0);
        assert_eq!(v.per_error["EZ0B"].setter, 10.0);
        assert!(
            v.summary().contains("cycle 1 (20.0 min from it)"),
            "{}",
            v.summary()
        );
        // After the last result: the last.
        let v = compare("m1", &reference(130, 70.0, 0.3), &results, 60 * MIN, 2.0).unwrap();
        assert_eq!(
            (v.method, v.setter_cycles.clone()),
            (Method::Nearest, vec![2])
        );
        // Before the first: the first.
        let v = compare("m1", &reference(-5, 10.0, 0.3), &results, 60 * MIN, 2.0).unwrap();
        assert_eq!(
            (v.method, v.setter_cycles.clone()),
            (Method::Nearest, vec![1])
        );
        // At a result's own time: that result, not an interpolation.
        let v = compare("m1", &reference(100, 60.0, 0.3), &results, 200 * MIN, 2.0).unwrap();
        assert_eq!(
            (v.method, v.setter_cycles.clone(), v.gap_ns),
            (Method::Nearest, vec![2], 0)
        );
        // Both within a wider gap: interpolated.
        let v = compare("m1", &reference(20, 20.0, 0.3), &results, 100 * MIN, 2.0).unwrap();
        assert_eq!(
            (v.method, v.setter_cycles.clone()),
            (Method::Interpolated, vec![1, 2])
        );
        assert!(v.summary().contains("interpolated between cycles 1 and 2"));
    }

    #[test]
    fn a_result_without_the_references_errors_is_not_used() {
        let mut partial = setter(2, 30, 0.4);
        partial.errors.as_mut().unwrap().remove("EZ0B");
        let results = [setter(1, 0, 0.4), partial];
        let v = compare("m1", &reference(25, 20.0, 0.3), &results, 60 * MIN, 2.0).unwrap();
        assert_eq!((v.method, v.setter_cycles), (Method::Nearest, vec![1]));
    }

    #[test]
    fn refused_when_no_accepted_result_lies_within_the_gap() {
        let results = [setter(1, 0, 0.4), setter(2, 30, 0.4)];
        let e = compare("m1", &reference(95, 20.0, 0.3), &results, 60 * MIN, 2.0).unwrap_err();
        assert!(matches!(e, VerifyError::NoSetterResult { .. }), "{e}");
        let text = e.to_string();
        assert!(text.contains("within 60 min"), "{text}");
        assert!(
            text.contains("the nearest, cycle 2, is 65.0 min before"),
            "{text}"
        );
        // Exactly at the gap is within.
        assert!(compare("m1", &reference(90, 20.0, 0.3), &results, 60 * MIN, 2.0).is_ok());
        // Only rejected results: none.
        let mut rejected = setter(3, 90, 0.4);
        rejected.status = ResultStatus::Rejected;
        let e = compare("m1", &reference(90, 20.0, 0.3), &[rejected], 60 * MIN, 2.0).unwrap_err();
        assert!(e.to_string().contains("has no accepted result"), "{e}");
        let e = compare("m1", &reference(90, 20.0, 0.3), &[], 60 * MIN, 2.0).unwrap_err();
        assert!(matches!(e, VerifyError::NoSetterResult { .. }));
    }

    #[test]
    fn exceeds_beyond_k_combined_sigma_on_both_sides() {
        // Setter at 0 min: EZ0B 10 um, sigma 0.4; reference sigma 0.3: combined 0.5, k 2: 1 um.
        let results = [setter(1, 0, 0.4)];
        let at = |ez0b: f64, k: f64| {
            compare("m1", &reference(0, ez0b, 0.3), &results, 60 * MIN, k).unwrap()
        };
        for (value, exceeds) in [(10.99, false), (11.01, true), (9.01, false), (8.99, true)] {
            let v = at(value, 2.0);
            assert_eq!(v.per_error["EZ0B"].exceeds, exceeds, "{value}");
            assert_eq!(v.exceeds_any, exceeds, "{value}");
        }
        let v = at(8.5, 2.0);
        assert!((v.per_error["EZ0B"].z + 3.0).abs() < 1e-9);
        assert!((v.worst_z + 3.0).abs() < 1e-9, "signed");
        assert!(
            v.summary().contains("EZ0B -1.50 um (z -3.00"),
            "{}",
            v.summary()
        );
        // A larger k takes it.
        assert!(!at(8.5, 4.0).exceeds_any);
        // The worst of several errors, in its own unit.
        let mut r = reference(0, 10.0, 0.3);
        r.errors.insert("EA0C".into(), 30.0);
        r.sigma.insert("EA0C".into(), 4.0);
        let v = compare("m1", &r, &results, 60 * MIN, 2.0).unwrap();
        assert_eq!(v.worst_error, "EA0C");
        assert!((v.worst_z - 2.0).abs() < 1e-12);
        assert_eq!(v.per_error["EA0C"].unit, "urad");
        assert!(
            !v.per_error["EA0C"].exceeds,
            "exactly k sigma does not exceed"
        );
    }

    #[test]
    fn bad_settings_are_refused() {
        let results = [setter(1, 0, 0.4)];
        for k in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(matches!(
                compare("m1", &reference(0, 10.0, 0.3), &results, MIN, k),
                Err(VerifyError::Setting(_))
            ));
        }
        assert!(matches!(
            compare("m1", &reference(0, 10.0, 0.3), &results, -1, 2.0),
            Err(VerifyError::Setting(_))
        ));
        let mut nan = reference(0, f64::NAN, 0.3);
        assert!(matches!(
            compare("m1", &nan, &results, MIN, 2.0),
            Err(VerifyError::BadReference { .. })
        ));
        nan.errors.clear();
        assert!(matches!(
            compare("m1", &nan, &results, MIN, 2.0),
            Err(VerifyError::BadReference { .. })
        ));
    }

    #[test]
    fn validation_names_the_field() {
        let now = T0 + 60 * MIN;
        let good = reference(0, 10.0, 0.3);
        assert_eq!(good.validate(&names(), now), Ok(()));
        let field = |r: &ReferenceResult| match r.validate(&names(), now) {
            Err(VerifyError::BadReference { field, .. }) => field,
            other => panic!("{other:?}"),
        };
        let with = |f: &dyn Fn(&mut ReferenceResult)| {
            let mut r = good.clone();
            f(&mut r);
            field(&r)
        };
        assert_eq!(with(&|r| r.instrument = " ".into()), "instrument");
        assert_eq!(with(&|r| r.instrument = "x".repeat(65)), "instrument");
        assert_eq!(with(&|r| r.source = Some("x".repeat(1025))), "source");
        assert_eq!(
            with(&|r| r.frame_note = Some("x".repeat(1025))),
            "frame_note"
        );
        assert_eq!(with(&|r| r.t_ns = 1_772_431_200), "t_ns");
        assert_eq!(with(&|r| r.t_ns = now + 11 * MIN), "t_ns");
        assert_eq!(with(&|r| r.errors.clear()), "errors");
        assert_eq!(
            with(&|r| {
                r.errors.insert("EZ0A".into(), 1.0);
            }),
            "errors.EZ0A"
        );
        assert_eq!(
            with(&|r| {
                r.errors.insert("ez0b".into(), 1.0);
            }),
            "errors.ez0b"
        );
        assert_eq!(
            with(&|r| {
                r.errors.insert("EZ0B".into(), f64::INFINITY);
            }),
            "errors.EZ0B"
        );
        assert_eq!(
            with(&|r| {
                r.errors.insert("EZ0B".into(), 1e5);
            }),
            "errors.EZ0B"
        );
        for s in [0.0, -0.1, f64::NAN] {
            assert_eq!(
                with(&|r| {
                    r.sigma.insert("EZ0B".into(), s);
                }),
                "sigma.EZ0B"
            );
        }
        assert_eq!(
            with(&|r| {
                r.sigma.clear();
            }),
            "sigma.EZ0B"
        );
        assert_eq!(
            with(&|r| {
                r.sigma.insert("EX0B".into(), 0.2);
            }),
            "sigma.EX0B"
        );
        // The message says which errors the machine has.
        let mut r = good.clone();
        r.errors.insert("EZ0A".into(), 1.0);
        let text = r.validate(&names(), now).unwrap_err().to_string();
        assert!(
            text.starts_with("errors.EZ0A: the machine does not identify EZ0A"),
            "{text}"
        );
        assert!(text.contains("EX0B, EZ0B, EY0C"), "{text}");
    }

    #[test]
    fn the_body_is_json_and_unknown_fields_are_refused() {
        let text = r#"{"instrument": "rtest", "t_ns": 1772431200000000000,
            "errors": {"EZ0B": 12.5, "EA0C": -3.0}, "sigma": {"EZ0B": 0.5, "EA0C": 4.0},
            "frame_note": "R-test frame turned to the machine frame", "source": "rtest-0412.csv"}"#;
        let r: ReferenceResult = serde_json::from_str(text).unwrap();
        assert_eq!(r.errors["EA0C"], -3.0);
        assert_eq!(r.validate(&names(), T0), Ok(()));
        let typo = text.replace("\"source\"", "\"sources\"");
        assert!(serde_json::from_str::<ReferenceResult>(&typo).is_err());
        let v = compare("m1", &r, &[setter(1, 0, 0.4)], MIN, 2.0).unwrap();
        let back: Verification = serde_json::from_value(serde_json::to_value(&v).unwrap()).unwrap();
        assert_eq!(back, v);
        assert_eq!(serde_json::to_value(&v).unwrap()["method"], "nearest");
    }

    #[test]
    fn the_configuration_is_checked() {
        assert_eq!(VerificationConfig::default().validate(), Ok(()));
        assert_eq!(VerificationConfig::default().max_gap_ns(), 60 * MIN);
        for bad in [
            VerificationConfig {
                k: 0.0,
                ..Default::default()
            },
            VerificationConfig {
                max_gap_min: f64::NAN,
                ..Default::default()
            },
            VerificationConfig {
                max_gap_min: 1e6,
                ..Default::default()
            },
            VerificationConfig {
                kept: 0,
                ..Default::default()
            },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }
}
