//! Diagnosis of where a model and a cycle recording differ (docs/physics.md 4.6), pure code:
//! the joint baseline over the rows of `rows`, outliers, located mismatches, the search over the
//! effect library (`effects`), ambiguity groups, what cannot be identified and what stays
//! unexplained.

use driftwatch_core::units;
use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;

use driftwatch_core::identify::SolveOptions;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::recording::{DetectionMsg, Timed};

pub use crate::rows::{
    DetectionRow, DiagnosisError, Rows, SIGMA_UM_RANGE, SIGNATURES, detection_rows,
};
use driftwatch_core::least_squares::{basis, inverse_form, lsq, residual_of, scan};

/// The baseline of docs/physics.md 4.6.1: every design parameter (the location errors and the
/// nuisances) as an offset plus gains on the spindle pole basis, fitted jointly to every
/// detection at its own time. Clean data must fit it to the noise before any search.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Baseline {
    /// `<parameter>` (offset) and `<parameter>*spindle_lag_<tau>min`, in column order.
    pub columns: Vec<String>,
    pub coef: Vec<f64>,
    /// Residual of every row, um.
    pub residual_um: Vec<f64>,
    pub chi2: f64,
    pub dof: usize,
    pub chi2_dof: f64,
}

/// Fit the baseline to `rows` with the spindle log `spindle` (every speed change, the
/// cycles' own spins included) and one-reading uncertainty `sigma_um`.
pub fn fit_baseline(
    rows: &Rows,
    spindle: &[driftwatch_thermal::model::Event],
    cfg: &driftwatch_thermal::model::ModelConfig,
    sigma_um: f64,
) -> Result<Baseline, DiagnosisError> {
    if rows.rows.is_empty() {
        return Err(DiagnosisError::NoDetections);
    }
    let drivers = Drivers::new(rows, spindle, &[], cfg);
    let a = baseline_matrix(rows, &drivers.spindle, sigma_um);
    let n = rows.rows.len();
    let y = DVector::from_iterator(n, rows.rows.iter().map(|r| r.deviation_um / sigma_um));
    let f = lsq(&a, &y);
    let resid = &y - &a * &f.beta;
    let dof = n.saturating_sub(f.rank).max(1);
    let (beta, chi2) = (f.beta, f.chi2);
    let p = a.ncols();
    let mut columns = Vec::with_capacity(p);
    for name in &rows.params {
        columns.push(name.clone());
        for t in &cfg.taus_min {
            columns.push(format!("{name}*spindle_lag_{t}min"));
        }
    }
    Ok(Baseline {
        columns,
        coef: beta.iter().copied().collect(),
        residual_um: resid.iter().map(|r| r * sigma_um).collect(),
        chi2,
        dof,
        chi2_dof: chi2 / dof as f64,
    })
}

/// The baseline's design, whitened: each design parameter's sensitivity times
/// `[1, spindle lags...]`, column `param * (1 + lags) + shape`.
fn baseline_matrix(rows: &Rows, spindle_lags: &[Vec<f64>], sigma_um: f64) -> DMatrix<f64> {
    let basis_len = 1 + spindle_lags.len();
    DMatrix::from_fn(rows.rows.len(), rows.params.len() * basis_len, |i, c| {
        let (j, b) = (c / basis_len, c % basis_len);
        let g = if b == 0 { 1.0 } else { spindle_lags[b - 1][i] };
        rows.rows[i].sensitivity[j] * g / sigma_um
    })
}

/// A group of readings whose residuals do not average to zero.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Mismatch {
    /// What the readings are grouped by (`approach`, `pose`, `B sense`, ...).
    pub by: String,
    pub group: String,
    pub n: usize,
    pub mean_um: f64,
    /// The mean in units of its standard error, `sigma / sqrt(n)`.
    pub t: f64,
}

/// Where the residuals are systematic: the mean residual of the readings grouped by approach
/// (axis and direction), pose, the sense each rotary axis last moved in and the time within
/// the cycle (15-s bins), every group with `|t| >= t_min`, largest first.
pub fn locate(rows: &Rows, residual_um: &[f64], sigma_um: f64, t_min: f64) -> Vec<Mismatch> {
    type Key = fn(&DetectionRow) -> String;
    let groupings: [(&str, Key); 5] = [
        ("approach", |r| {
            format!(
                "{}{}",
                r.axis.name(),
                if r.direction > 0 { "+" } else { "-" }
            )
        }),
        ("pose", |r| format!("B{} C{}", r.b_deg, r.c_deg)),
        ("B sense", |r| format!("{:+}", r.rotary_sense[0])),
        ("C sense", |r| format!("{:+}", r.rotary_sense[1])),
        ("time in cycle", |r| {
            let bin = (r.t_in_cycle_s / 15.0).floor() * 15.0;
            format!("{bin}-{} s", bin + 15.0)
        }),
    ];
    let mut out = Vec::new();
    for (by, key) in groupings {
        group_means(
            by,
            rows.rows.iter().map(key),
            residual_um,
            sigma_um,
            t_min,
            &mut out,
        );
    }
    out.sort_by(|a, b| b.t.abs().total_cmp(&a.t.abs()));
    out
}

// ---------------------------------------------------------------------------------------
// The search (docs/physics.md 4.6.1): baseline, outliers, located mismatches, forward selection over
// the effect library with backward pruning, ambiguity groups, what cannot be identified and
// what stays unexplained.

use crate::effects::{Candidate, Drivers};
use driftwatch_thermal::model::{Event, ModelConfig, ModelInput};
use nalgebra::{DMatrix, DVector};

mod search;
use search::Search;
pub use search::{SerialCorrelation, UNEXPLAINED_P};

/// The baseline's spindle pole basis, min.
pub const DIAGNOSIS_TAUS_MIN: [f64; 10] =
    [4.0, 7.0, 12.0, 20.0, 35.0, 60.0, 100.0, 170.0, 300.0, 600.0];

/// The acceptance rules of docs/physics.md 4.6.1, with the defaults it gives.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DiagnoseOptions {
    /// One-reading standard uncertainty, um.
    pub sigma_um: f64,
    pub model: ModelConfig,
    pub min_delta_bic: f64,
    pub min_t: f64,
    /// Fraction of held-out blocks a term must improve.
    pub min_blocks_improved: f64,
    /// |cos| above which two candidates form an ambiguity group.
    pub ambiguity_cos: f64,
    /// Readings further than this many sigma from the baseline are outliers.
    pub outlier_sigma: f64,
    pub max_terms: usize,
    /// Relative energy of a candidate outside the baseline below which it is structurally
    /// confounded with it.
    pub structural_tol: f64,
    /// An effect none of whose candidates has this much energy outside the baseline is
    /// reported as not identifiable in practice (and its candidates stay in the search).
    pub practical_tol: f64,
}

impl DiagnoseOptions {
    pub fn new(sigma_um: f64) -> Self {
        DiagnoseOptions {
            sigma_um,
            // Denser than the service's six poles: on clean three-day recordings the six leave
            // chi2/dof 1.01-1.07 of basis misfit (the truth's 11-, 45-, 60-, 90- and 120-min
            // lags) that spindle-driven sensors' lags then pick up; ten fit to the noise.
            model: ModelConfig {
                taus_min: DIAGNOSIS_TAUS_MIN.to_vec(),
                ..ModelConfig::default()
            },
            min_delta_bic: 10.0,
            min_t: 4.0,
            min_blocks_improved: 2.0 / 3.0,
            ambiguity_cos: 0.9,
            outlier_sigma: 5.0,
            max_terms: 8,
            structural_tol: 1e-6,
            practical_tol: 0.05,
        }
    }
}

/// A fit's figures.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FitFigures {
    pub parameters: usize,
    pub chi2_dof: f64,
    pub dof: usize,
    /// RMS of the residuals of the fit on the training blocks, um.
    pub rms_train_um: f64,
    /// RMS on the last block when fitted on the others, um.
    pub rms_heldout_um: f64,
    /// The held-out RMS is over 5 times the training RMS and over 5 sigma: the last block
    /// holds spindle history the training part never saw (typical under two days), so the
    /// figure measures extrapolation, not the fit.
    pub heldout_extrapolates: bool,
}

/// One fitted parameter.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Parameter {
    pub name: String,
    pub unit: String,
    pub value: f64,
    pub sigma: f64,
}

/// Another explanation of an accepted term's footprint.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GroupMember {
    pub effect: String,
    pub term: String,
    /// |cos| between the accepted footprint and this candidate, after projecting out the rest.
    pub cos: f64,
    /// How much worse the data fit with it in place of the accepted term (chi2; negative:
    /// better).
    pub delta_chi2: f64,
    /// The part of the term's footprint it cannot carry (chi2).
    pub footprint_left_chi2: f64,
    /// Its parameters beyond the rest of the model (profiled ones counted).
    pub parameters: usize,
    /// It explains the data comparably: it carries the footprint but for a relative 1e-3,
    /// or `min(footprint_left_chi2, delta_chi2) + 2 x (its parameters beyond the term's)`
    /// is under `min_delta_bic`.
    pub comparable: bool,
    /// For a comparable member the plan can tell apart in principle: the factor by which the
    /// term's amplitude would have to grow for this member to fit the data worse by
    /// `min_delta_bic` (its `footprint_left_chi2` grows with the square of the amplitude, and
    /// so does the expected `delta_chi2`). Null when it is not comparable (already split), when
    /// it carries the footprint at any amplitude, or when it is in the group because it
    /// coincides in time.
    pub splits_at: Option<f64>,
    /// Why it is in the group.
    pub reason: String,
}

/// One alternative explanation of an accepted term, as [`GroupMember`] reports it.
struct Alternative {
    cos: f64,
    miss: f64,
    data: f64,
    parameters: usize,
    comparable: bool,
    splits_at: Option<f64>,
}

/// A term the search accepted.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Accepted {
    pub effect: String,
    pub label: String,
    pub term: String,
    pub parameters: Vec<Parameter>,
    /// RMS of the term's footprint over the readings, um.
    pub amplitude_rms_um: f64,
    pub peak_um: f64,
    pub t: f64,
    pub delta_bic: f64,
    /// Held-out RMS on the last block without and with the term, um.
    pub heldout_rms_before_um: f64,
    pub heldout_rms_after_um: f64,
    pub blocks_improved: usize,
    pub blocks: usize,
    /// Named: no other effect in its ambiguity group explains the data comparably (within
    /// delta-chi2 `min_delta_bic`) and it does not coincide in time with another accepted
    /// effect. Otherwise the term is reported as one of its group, not as `effect`.
    pub named: bool,
    /// For a term not named: the factor by which its amplitude would have to grow for it to
    /// be named on this plan (the largest `splits_at` of its comparable members of other
    /// effects). Null when it is named, when some member carries its footprint at any
    /// amplitude or coincides with it in time (no amplitude names it on this plan).
    pub named_at: Option<f64>,
    /// The located time of a step term, ns.
    pub step_ns: Option<i64>,
    /// Empty when no other candidate explains it; otherwise the group and how to split it.
    pub ambiguity_group: Vec<GroupMember>,
    pub split_by: String,
    /// What it is and what it did, in words.
    pub statement: String,
    /// What it adds to the thermal model (`none` when the model cannot carry it: a
    /// measurement-model effect to correct at its source, or a clock term).
    pub model_input: ModelInput,
}

/// What an accepted term with this signature and time shape adds to the thermal model: only
/// terms on a location error (what the model predicts), driven by the spindle, a logged
/// temperature or the speed.
fn model_input(
    signature: &str,
    shape: &str,
    locations: &[String],
    sensors: &[String],
) -> ModelInput {
    if !locations.iter().any(|l| l == signature) {
        return ModelInput::None;
    }
    if shape == "(n/n_ref)^2" {
        return ModelInput::InstantSpeed;
    }
    let lag = |s: &str| s.strip_suffix(" min").and_then(|x| x.parse::<f64>().ok());
    // Sensors first: a sensor may be named "spindle".
    for sensor in sensors {
        let tau = if shape == sensor {
            Some(0.0)
        } else {
            shape
                .strip_prefix(sensor.as_str())
                .and_then(|r| r.strip_prefix(" lag "))
                .and_then(lag)
        };
        if let Some(tau) = tau {
            return ModelInput::Temperature {
                sensor: sensor.clone(),
                taus_min: vec![tau],
            };
        }
    }
    if let Some(tau) = shape.strip_prefix("spindle lag ").and_then(lag) {
        return ModelInput::SpindleLag { tau_min: tau };
    }
    ModelInput::None
}

/// A candidate that looked strong but failed a rule.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Refused {
    pub effect: String,
    pub term: String,
    pub delta_bic: f64,
    pub t: f64,
    pub reason: String,
}

/// An effect this plan cannot tell from what the baseline already has.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NotIdentifiable {
    pub effect: String,
    pub label: String,
    /// The design parameter its signature looks most like, with |cos|.
    pub confounded_with: String,
    pub cos: f64,
    pub reason: String,
    pub split_by: String,
}

/// A periodic residual at a period no library shape has (a coolant or chiller cycle, a
/// hydraulic unit): modelled as a discrepancy so that no library term is forced into it, and
/// reported as unexplained.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PeriodicResidual {
    pub period_min: f64,
    /// Other periods that fit within delta-chi2 `min_delta_bic` of it (aliases of the cycle
    /// cadence: the data cannot tell them apart).
    pub aliases_min: Vec<f64>,
    /// What the pair (every design parameter times cos and sin) takes from the residuals.
    pub delta_chi2: f64,
    /// The same less `(2 p + 1) ln N` (the period counted as a parameter).
    pub delta_bic: f64,
    /// RMS and peak of its footprint on the readings in the final fit, um.
    pub amplitude_rms_um: f64,
    pub peak_um: f64,
    /// The design parameters that carry it: amplitude (sqrt(cos^2 + sin^2)) with its sigma,
    /// those at 3 sigma or more, largest first.
    pub carried_by: Vec<Parameter>,
    pub statement: String,
}

/// Structure left after the search.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Unexplained {
    pub chi2_dof: f64,
    /// Smallest Ljung-Box p over the channels, and that channel.
    pub ljung_box_p: f64,
    /// The same over all the channels tested (Sidak: `1 - (1 - p)^m`): what is held against
    /// 0.001, so that a clean recording is flagged at that rate however many channels it has.
    pub ljung_box_p_channels: f64,
    pub channels_tested: usize,
    pub channel: String,
    /// Where: the largest located mismatches of the final residuals.
    pub located: Vec<Mismatch>,
    /// When: the cycles with the largest mean residual (time, mean um).
    pub when: Vec<(i64, f64)>,
    /// RMS of what the noise does not explain, um.
    pub discrepancy_um: f64,
    /// A periodic residual at a period outside the library, when one was found.
    pub periodic: Option<PeriodicResidual>,
}

/// Before and after, one channel (one step of the cycle).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChannelFigures {
    pub channel: String,
    pub n: usize,
    pub chi2_dof_before: f64,
    pub chi2_dof_after: f64,
    pub rms_train_before_um: f64,
    pub rms_train_after_um: f64,
    pub rms_heldout_before_um: f64,
    pub rms_heldout_after_um: f64,
    /// Ljung-Box p (10 lags) of the final residuals in time order (none: too few readings).
    pub ljung_box_p_after: Option<f64>,
}

/// One outlier reading.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Outlier {
    pub t_ns: i64,
    pub cycle: i64,
    /// What was measured (pose, approach, feed; see `cycle::MeasurementKey`), not the free label.
    pub step: String,
    pub residual_um: f64,
}

/// A per-cycle consistency figure free of every location error (docs/physics.md 4.1).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Redundancy {
    /// Degrees of freedom of a full cycle (the most common; a cycle with a missing reading has
    /// fewer, and is judged on its own).
    pub dof: usize,
    /// `(cycle, t_ns, chi2)`.
    pub cycles: Vec<(i64, i64, f64)>,
    /// Cycles over the 0.999 quantile of their own degrees of freedom.
    pub alarms: Vec<i64>,
    /// First cycle at which a CUSUM of `chi2/dof - 1` (k 0.5, h 5) alarmed.
    pub cusum_alarm: Option<i64>,
    /// `1.4826 MAD` of the redundancy residuals, um: sigma without any thermal model.
    pub sigma_um: Option<f64>,
}

/// The whole result (`diagnosis.json`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Diagnosis {
    pub sigma_um: f64,
    pub readings: usize,
    pub cycles: usize,
    pub span_h: f64,
    /// Held-out blocks (`[start, end)` ns); the last is the held-out part of the figures.
    pub blocks: Vec<(i64, i64)>,
    pub redundancy: Redundancy,
    pub baseline: FitFigures,
    pub outliers: Vec<Outlier>,
    pub located: Vec<Mismatch>,
    /// The strongest candidate drivers before the search: partial correlation with the
    /// baseline's residuals given the baseline (as t).
    pub drivers: Vec<(String, f64)>,
    pub accepted: Vec<Accepted>,
    pub refused: Vec<Refused>,
    pub not_identifiable: Vec<NotIdentifiable>,
    /// Candidates not tried: slow and daily terms need two days.
    pub not_tested: Vec<String>,
    /// The smallest amplitude of each one-parameter candidate that reaches the acceptance
    /// bar (delta-BIC `min_delta_bic`, or |t| `min_t` where that binds harder) with 50 %
    /// power on this plan (docs/physics.md 4.3), in its unit.
    pub thresholds: Vec<Threshold>,
    pub unexplained: Vec<Unexplained>,
    #[serde(rename = "final")]
    pub final_fit: FitFigures,
    pub channels: Vec<ChannelFigures>,
    /// Rows' times, baseline and final residuals, um (for the report's plots).
    #[serde(skip)]
    pub series: Series,
}

/// The detection threshold of one candidate.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Threshold {
    pub effect: &'static str,
    pub term: String,
    pub unit: String,
    pub amplitude: f64,
}

/// Per-row series kept for plots and tests.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Series {
    pub t_ns: Vec<i64>,
    pub cycle: Vec<i64>,
    pub step: Vec<String>,
    pub baseline_um: Vec<f64>,
    pub final_um: Vec<f64>,
    /// Prediction of every row's deviation by the baseline and the final model fitted
    /// without the last block, um.
    pub heldout_baseline_um: Vec<f64>,
    pub heldout_final_um: Vec<f64>,
    pub heldout: Vec<bool>,
    /// The accepted terms' footprints, `(term, [row])`, um.
    pub footprints: Vec<(String, Vec<f64>)>,
    pub deviation_um: Vec<f64>,
    /// An orthonormal basis of the baseline's columns (rows x rank): what any effect's
    /// footprint shares with the baseline is its projection on it.
    pub baseline_basis: DMatrix<f64>,
}

impl Series {
    /// `v` without its part in the baseline's column space.
    pub fn beyond_baseline(&self, v: &[f64]) -> Vec<f64> {
        let v = DVector::from_column_slice(v);
        let r = &v - &self.baseline_basis * self.baseline_basis.tr_mul(&v);
        r.iter().copied().collect()
    }
}

/// Leverage above which a reading is not screened.
const MAX_SCREEN_LEVERAGE: f64 = 0.9;

/// The readings that are outliers against a robust fit of the baseline: `(row, residual um)`,
/// in row order. The baseline is fitted by iteratively reweighted least squares (three Huber
/// steps, k = 1.5 sigma, then Tukey's bisquare, c = 4.685 sigma, to convergence), so that the
/// readings it screens cannot pull it; a reading is an outlier when its residual, scaled to a
/// leave-one-out residual by its leverage (`r / sqrt(1 - h)`), is beyond `k_sigma` sigma. On
/// clean data the scaled residuals are standard normal: the false share is `2 Phi(-k)`
/// (5.7e-7 at 5 sigma). A reading of leverage above [`MAX_SCREEN_LEVERAGE`] is not judged.
pub fn screen_outliers(
    rows: &Rows,
    spindle: &[Event],
    cfg: &ModelConfig,
    sigma_um: f64,
    k_sigma: f64,
) -> Vec<(usize, f64)> {
    if rows.rows.is_empty() {
        return Vec::new();
    }
    let drivers = Drivers::new(rows, spindle, &[], cfg);
    let a = baseline_matrix(rows, &drivers.spindle, sigma_um);
    let y = DVector::from_iterator(
        rows.rows.len(),
        rows.rows.iter().map(|r| r.deviation_um / sigma_um),
    );
    let (r, h) = robust_fit(&a, &y);
    (0..r.len())
        // A reading the fit passes through (leverage near 1: a short recording, nearly as
        // many parameters as readings) cannot be judged: its scaled residual is rounding.
        .filter(|&i| h[i] < MAX_SCREEN_LEVERAGE)
        .filter_map(|i| {
            let loo = r[i] / (1.0 - h[i]).sqrt();
            (loo.abs() > k_sigma).then_some((i, r[i] * sigma_um))
        })
        .collect()
}

/// Iteratively reweighted least squares on whitened columns (unit scale): the residuals and
/// each row's leverage `w_i a_i^T (A^T W A)^+ a_i` at the final weights.
fn robust_fit(a: &DMatrix<f64>, y: &DVector<f64>) -> (DVector<f64>, Vec<f64>) {
    const HUBER_STEPS: usize = 3;
    const MAX_STEPS: usize = 30;
    let n = y.len();
    let mut w = vec![1.0; n];
    let mut prev: Option<DVector<f64>> = None;
    for step in 0..MAX_STEPS {
        let sw: Vec<f64> = w.iter().map(|v: &f64| v.sqrt()).collect();
        let mut aw = a.clone();
        for (i, s) in sw.iter().enumerate() {
            aw.row_mut(i).scale_mut(*s);
        }
        let yw = DVector::from_fn(n, |i, _| y[i] * sw[i]);
        let f = lsq(&aw, &yw);
        let r = y - a * &f.beta;
        let converged = step > HUBER_STEPS
            && prev
                .as_ref()
                .is_some_and(|p: &DVector<f64>| (p - &r).amax() < 1e-3);
        if converged || step + 1 == MAX_STEPS {
            let h = (0..n)
                .map(|i| {
                    let ai = a.row(i).transpose();
                    w[i] * ai.dot(&(&f.cov * &ai))
                })
                .collect();
            return (r, h);
        }
        w = r
            .iter()
            .map(|e| {
                if step < HUBER_STEPS {
                    (1.5 / e.abs().max(1e-12)).min(1.0)
                } else {
                    let u = e / 4.685;
                    if u.abs() >= 1.0 {
                        0.0
                    } else {
                        (1.0 - u * u).powi(2)
                    }
                }
            })
            .collect();
        prev = Some(r);
    }
    (y.clone(), vec![0.0; n])
}

/// Fewest cycles on either side of a located step: a change in the first or last quarter
/// day of a record is an edge effect as much as a step.
const STEP_MIN_CYCLES: usize = 12;

/// One step candidate per signature that can jump ([`crate::effects::step_signatures`]), at
/// the cycle start that explains most of the residual `e` beyond the baseline (orthonormal
/// basis `q`), with at least [`STEP_MIN_CYCLES`] cycles on either side. The located time
/// is profiled: it counts in the candidate's BIC penalty.
fn step_candidates(rows: &Rows, q: &DMatrix<f64>, e: &DVector<f64>, sigma: f64) -> Vec<Candidate> {
    // Cycles in time order with their rows.
    let mut by_cycle: BTreeMap<i64, (i64, Vec<usize>)> = BTreeMap::new();
    for (i, r) in rows.rows.iter().enumerate() {
        let c = by_cycle.entry(r.cycle).or_insert((r.t_ns, Vec::new()));
        c.0 = c.0.min(r.t_ns);
        c.1.push(i);
    }
    let mut cycles: Vec<(i64, Vec<usize>)> = by_cycle.into_values().collect();
    cycles.sort_by_key(|c| c.0);
    let nc = cycles.len();
    if nc < 2 * STEP_MIN_CYCLES {
        return Vec::new();
    }
    let r = q.ncols();
    let mut out = Vec::new();
    for (effect, name) in crate::effects::step_signatures(rows) {
        let Some(col) = crate::effects::signature_column(rows, &name) else {
            continue;
        };
        // Suffix sums over cycles: a'e, a'a and Q'a of the step column from cycle c on.
        let (mut se, mut saa) = (0.0, 0.0);
        let mut sq = DVector::<f64>::zeros(r);
        let mut best: Option<(f64, usize)> = None;
        for c in (0..nc).rev() {
            for &i in &cycles[c].1 {
                let a = col[i] / sigma;
                se += a * e[i];
                saa += a * a;
                sq.axpy(a, &q.row(i).transpose(), 1.0);
            }
            if c < STEP_MIN_CYCLES || nc - c < STEP_MIN_CYCLES {
                continue;
            }
            let free = saa - sq.norm_squared();
            if free <= 1e-9 * saa.max(1e-300) {
                continue;
            }
            let d = se * se / free;
            if best.is_none_or(|(b, _)| d > b) {
                best = Some((d, c));
            }
        }
        let Some((_, c)) = best else { continue };
        let t0 = cycles[c].0;
        let step: Vec<f64> = rows
            .rows
            .iter()
            .map(|r| if r.t_ns >= t0 { 1.0 } else { 0.0 })
            .collect();
        let when = chrono::DateTime::from_timestamp_nanos(t0).format("%Y-%m-%dT%H:%M:%SZ");
        out.push(Candidate {
            effect,
            term: format!("{name} x step at {when}"),
            unit: crate::effects::signature_unit(&name).to_string(),
            columns: vec![col.iter().zip(&step).map(|(a, b)| a * b).collect()],
            signature: name,
            shape_kind: crate::effects::ShapeKind::Step,
            shape: vec![step],
            profiled: 1,
            step_ns: Some(t0),
        });
    }
    out
}

/// Periods a periodic residual is looked for at, min: from a few cycles' worth down to a
/// few minutes (the library's own periodic shapes are 24 h and 12 h).
pub const PERIODIC_RANGE_MIN: [f64; 2] = [8.0, 240.0];

/// The strongest periodic structure of the residuals of model `m`: every design parameter
/// times a Fourier pair at a period scanned over [`PERIODIC_RANGE_MIN`] (a grid at half the
/// record's frequency resolution, the best peaks refined at a quarter of it). Reported when
/// its delta-BIC, with the period counted as a parameter, reaches the acceptance bar. Returns
/// the finding (amplitudes filled in by the caller's final fit) and its whitened columns.
fn periodic_scan(
    rows: &Rows,
    m: &DMatrix<f64>,
    y: &DVector<f64>,
    sigma: f64,
    opts: &DiagnoseOptions,
) -> Option<(PeriodicResidual, DMatrix<f64>)> {
    let n = rows.rows.len();
    let t0 = rows.rows.iter().map(|r| r.t_ns).min()?;
    let tmin: Vec<f64> = rows
        .rows
        .iter()
        .map(|r| (r.t_ns - t0) as f64 / 6e10)
        .collect();
    let span = tmin.iter().copied().fold(0.0, f64::max);
    let [lo, hi] = PERIODIC_RANGE_MIN;
    if span < 4.0 * hi {
        return None;
    }
    let p = rows.params.len();
    let e = residual_of(m, y);
    let block = |period: f64| -> DMatrix<f64> {
        let w = std::f64::consts::TAU / period;
        // One sine and cosine per row, not one per column: the trigonometry was a quarter of
        // a diagnosis' time.
        let pair: Vec<(f64, f64)> = tmin.iter().map(|t| (w * t).sin_cos()).collect();
        DMatrix::from_fn(n, 2 * p, |i, c| {
            let (j, k) = (c % p, c / p);
            let (sin, cos) = pair[i];
            rows.rows[i].sensitivity[j] / sigma * if k == 0 { cos } else { sin }
        })
    };
    // Coarse: the pair's fit to the residual, not projected on the model (its smooth
    // columns hardly overlap a pair of a few hours or less).
    let df = 1.0 / (2.0 * span);
    let mut pairs = CoarsePairs::new(rows, &e, sigma, &tmin, df);
    let mut coarse = Vec::new();
    let mut f = 1.0 / hi;
    while f <= 1.0 / lo {
        if coarse.len() % CoarsePairs::RESEED == 0 {
            pairs.seed(f);
        }
        coarse.push((f, pairs.explained()));
        pairs.advance();
        f += df;
    }
    // Local maxima, strongest first.
    let mut peaks: Vec<(f64, f64)> = (0..coarse.len())
        .filter(|&i| {
            (i == 0 || coarse[i].1 >= coarse[i - 1].1)
                && (i + 1 == coarse.len() || coarse[i].1 >= coarse[i + 1].1)
        })
        .map(|i| coarse[i])
        .collect();
    peaks.sort_by(|a, b| b.1.total_cmp(&a.1));
    peaks.truncate(4);
    let q = basis(m);
    let exact = |period: f64| scan(&q, &e, &block(period)).0;
    let mut refined: Vec<(f64, f64)> = peaks
        .iter()
        .map(|(f, _)| {
            (-4..=4)
                .map(|k| {
                    let fr = f + f64::from(k) * df / 4.0;
                    (1.0 / fr, exact(1.0 / fr))
                })
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap_or((1.0 / f, 0.0))
        })
        .collect();
    refined.sort_by(|a, b| b.1.total_cmp(&a.1));
    let (period, d) = *refined.first()?;
    let delta_bic = d - (2 * p + 1) as f64 * (n as f64).ln();
    if delta_bic < opts.min_delta_bic {
        return None;
    }
    let aliases_min = refined
        .iter()
        .skip(1)
        .filter(|(_, x)| d - x < opts.min_delta_bic)
        .map(|(p, _)| *p)
        .collect();
    Some((
        PeriodicResidual {
            period_min: period,
            aliases_min,
            delta_chi2: d,
            delta_bic,
            amplitude_rms_um: 0.0,
            peak_um: 0.0,
            carried_by: Vec::new(),
            statement: String::new(),
        },
        block(period),
    ))
}

/// The coarse periodic scan's fit of the residual `e` by every design parameter times a
/// Fourier pair, at each frequency of a uniform grid. Its normal equations are built from
/// per-row products taken once: with `c = cos wt` and `s = sin wt`, `c^2 = (1 + cos 2wt)/2`,
/// `s^2 = (1 - cos 2wt)/2` and `cs = sin 2wt / 2`, so the pair's `X^T X` is the rows'
/// `u u^T` (`u` the whitened sensitivities) summed plain and against `cos 2wt` and `sin 2wt`.
/// From one frequency to the next each row's phase turns by one complex multiplication, not
/// a `sin_cos`. Forming `X` and `X^T X` at every frequency was half of a diagnosis' time.
struct CoarsePairs {
    p: usize,
    tmin: Vec<f64>,
    /// Per row, `u_j u_l` for `j <= l`, packed row-major.
    uu: Vec<f64>,
    /// Per row, `u_j e`.
    ue: Vec<f64>,
    /// `sum u_j u_l` over the rows, packed as `uu`.
    plain: Vec<f64>,
    /// Per row, `(cos wt, sin wt)` at the current frequency, and the turn of one grid step.
    phase: Vec<(f64, f64)>,
    turn: Vec<(f64, f64)>,
}

impl CoarsePairs {
    /// Grid steps between exact phases: the turns' rounding stays near 1e-14.
    const RESEED: usize = 64;

    fn new(rows: &Rows, e: &DVector<f64>, sigma: f64, tmin: &[f64], df: f64) -> Self {
        let p = rows.params.len();
        let packed = p * (p + 1) / 2;
        let (mut uu, mut ue) = (Vec::with_capacity(rows.rows.len() * packed), Vec::new());
        let mut plain = vec![0.0; packed];
        for (r, ei) in rows.rows.iter().zip(e.iter()) {
            let u: Vec<f64> = r.sensitivity[..p].iter().map(|s| s / sigma).collect();
            let mut k = 0;
            for j in 0..p {
                ue.push(u[j] * ei);
                for l in j..p {
                    uu.push(u[j] * u[l]);
                    plain[k] += u[j] * u[l];
                    k += 1;
                }
            }
        }
        let turn = tmin
            .iter()
            .map(|t| (std::f64::consts::TAU * df * t).sin_cos())
            .map(|(s, c)| (c, s))
            .collect();
        CoarsePairs {
            p,
            tmin: tmin.to_vec(),
            uu,
            ue,
            plain,
            phase: vec![(1.0, 0.0); tmin.len()],
            turn,
        }
    }

    /// Sets the phases exactly at frequency `f` (1/min).
    fn seed(&mut self, f: f64) {
        let w = std::f64::consts::TAU * f;
        for (ph, t) in self.phase.iter_mut().zip(&self.tmin) {
            let (s, c) = (w * t).sin_cos();
            *ph = (c, s);
        }
    }

    /// One grid step up in frequency.
    fn advance(&mut self) {
        for ((c, s), (tc, ts)) in self.phase.iter_mut().zip(&self.turn) {
            (*c, *s) = (*c * tc - *s * ts, *s * tc + *c * ts);
        }
    }

    /// `b^T A^-1 b` at the current frequency (`A = X^T X` with a relative ridge of 1e-9,
    /// `b = X^T e`), 0 when `A` is not positive definite.
    fn explained(&self) -> f64 {
        let (p, packed) = (self.p, self.plain.len());
        let (mut c2, mut s2) = (vec![0.0; packed], vec![0.0; packed]);
        let (mut bc, mut bs) = (vec![0.0; p], vec![0.0; p]);
        for (i, &(c, s)) in self.phase.iter().enumerate() {
            let (cos2, sin2) = (c * c - s * s, 2.0 * c * s);
            let uu = &self.uu[i * packed..(i + 1) * packed];
            for ((a, b), x) in c2.iter_mut().zip(s2.iter_mut()).zip(uu) {
                *a += x * cos2;
                *b += x * sin2;
            }
            let ue = &self.ue[i * p..(i + 1) * p];
            for ((a, b), x) in bc.iter_mut().zip(bs.iter_mut()).zip(ue) {
                *a += x * c;
                *b += x * s;
            }
        }
        let mut a = DMatrix::zeros(2 * p, 2 * p);
        let mut k = 0;
        for j in 0..p {
            for l in j..p {
                let (cc, ss, cs) = (
                    0.5 * (self.plain[k] + c2[k]),
                    0.5 * (self.plain[k] - c2[k]),
                    0.5 * s2[k],
                );
                for (r, q, v) in [
                    (j, l, cc),
                    (l, j, cc),
                    (p + j, p + l, ss),
                    (p + l, p + j, ss),
                    (j, p + l, cs),
                    (p + l, j, cs),
                    (l, p + j, cs),
                    (p + j, l, cs),
                ] {
                    a[(r, q)] = v;
                }
                k += 1;
            }
        }
        let ridge = 1e-9 * a.trace() / a.nrows() as f64;
        for i in 0..a.nrows() {
            a[(i, i)] += ridge;
        }
        let b = DVector::from_iterator(2 * p, bc.into_iter().chain(bs));
        inverse_form(a, &b).unwrap_or(0.0)
    }
}

/// The rows' phase: the production spindle (the log without the cycles' own spins) on for
/// less than 36 min (three fast time constants) is warm-up, longer steady; off for less than
/// 36 min cool-down, longer idle.
fn phases(rows: &Rows, spindle: &[Event]) -> Vec<&'static str> {
    let mut windows: BTreeMap<i64, (i64, i64)> = BTreeMap::new();
    for r in &rows.rows {
        let w = windows.entry(r.cycle).or_insert((r.t_ns, r.t_ns));
        w.0 = w.0.min(r.t_ns);
        w.1 = w.1.max(r.t_ns);
    }
    let margin = 120_000_000_000;
    let inside = |t: i64| {
        windows
            .values()
            .any(|(a, b)| t >= a - margin && t <= b + margin)
    };
    let production: Vec<(i64, f64)> = spindle
        .iter()
        .filter_map(|e| match e {
            Event::Spindle { t_ns, rpm } if !inside(*t_ns) => Some((*t_ns, *rpm)),
            _ => None,
        })
        .collect();
    rows.rows
        .iter()
        .map(|r| {
            let start = windows.get(&r.cycle).map_or(r.t_ns, |w| w.0 - margin);
            let mut on = false;
            let mut since = i64::MIN;
            for (t, rpm) in production.iter().filter(|(t, _)| *t <= start) {
                let now_on = *rpm > 0.0;
                if now_on != on || since == i64::MIN {
                    since = *t;
                }
                on = now_on;
            }
            let fresh = since != i64::MIN && start - since < 36 * units::NS_PER_MIN;
            match (on, fresh) {
                (true, true) => "warm-up",
                (true, false) => "steady",
                (false, true) => "cool-down",
                (false, false) => "idle",
            }
        })
        .collect()
}

fn group_means<'a>(
    by: &str,
    labels: impl Iterator<Item = String> + 'a,
    residual_um: &[f64],
    sigma_um: f64,
    t_min: f64,
    out: &mut Vec<Mismatch>,
) {
    let mut groups: BTreeMap<String, (usize, f64)> = BTreeMap::new();
    for (g, e) in labels.zip(residual_um) {
        let s = groups.entry(g).or_default();
        s.0 += 1;
        s.1 += e;
    }
    for (group, (n, sum)) in groups {
        let mean = sum / n as f64;
        let t = mean / (sigma_um / (n as f64).sqrt());
        if t.abs() >= t_min {
            out.push(Mismatch {
                by: by.to_string(),
                group,
                n,
                mean_um: mean,
                t,
            });
        }
    }
}

/// Held-out blocks: UTC-day-long blocks from the first reading when the rows span two days or
/// more (a last block under 6 h joins the one before), else three equal blocks in time.
fn blocks(times: &[i64]) -> Vec<(i64, i64)> {
    let t0 = times.iter().copied().min().unwrap_or(0);
    let t1 = times.iter().copied().max().unwrap_or(0) + 1;
    const DAY: i64 = units::NS_PER_DAY;
    let mut b = Vec::new();
    if t1 - t0 >= 2 * DAY {
        let mut a = t0;
        while a < t1 {
            b.push((a, (a + DAY).min(t1)));
            a += DAY;
        }
        if b.len() > 1
            && let Some(last) = b.last().copied()
            && last.1 - last.0 < DAY / 4
        {
            b.pop();
            if let Some(l) = b.last_mut() {
                l.1 = last.1;
            }
        }
    } else {
        let w = (t1 - t0) / 3;
        b = vec![(t0, t0 + w), (t0 + w, t0 + 2 * w), (t0 + 2 * w, t1)];
    }
    b
}

/// Residual sum of squares on the rows of `test` of a fit on the rows of `train`.
fn heldout_sse(m: &DMatrix<f64>, y: &DVector<f64>, train: &[usize], test: &[usize]) -> f64 {
    let mt = m.select_rows(train.iter());
    let yt = y.select_rows(train.iter());
    let f = lsq(&mt, &yt);
    test.iter()
        .map(|&i| (y[i] - m.row(i).transpose().dot(&f.beta)).powi(2))
        .sum()
}

fn heldout_prediction(m: &DMatrix<f64>, y: &DVector<f64>, train: &[usize]) -> DVector<f64> {
    let f = lsq(&m.select_rows(train.iter()), &y.select_rows(train.iter()));
    m * f.beta
}

/// The redundancy of each cycle: its readings projected on the left null space of the
/// cycle's design (free of every design parameter).
fn redundancy(rows: &Rows, sigma_um: f64) -> Redundancy {
    let mut by_cycle: BTreeMap<i64, Vec<usize>> = BTreeMap::new();
    for (i, r) in rows.rows.iter().enumerate() {
        by_cycle.entry(r.cycle).or_default().push(i);
    }
    let p = rows.params.len();
    let mut cycles = Vec::new();
    let mut all = Vec::new();
    let mut dofs = Vec::new();
    for (c, idx) in &by_cycle {
        let s = DMatrix::from_fn(idx.len(), p, |i, j| rows.rows[idx[i]].sensitivity[j]);
        let y = DVector::from_iterator(idx.len(), idx.iter().map(|i| rows.rows[*i].deviation_um));
        let q = basis(&s);
        let dof = idx.len().saturating_sub(q.ncols());
        if dof == 0 {
            continue;
        }
        // What no parameter of the cycle's design can absorb: the residual of its projection.
        let resid = &y - &q * q.tr_mul(&y);
        let chi2 = resid.norm_squared() / sigma_um.powi(2);
        // Components of the residual in an orthonormal basis of the null space have the
        // readings' sigma; the residual's own entries are shrunk by sqrt(dof / n).
        let shrink = (dof as f64 / idx.len() as f64).sqrt();
        all.extend(resid.iter().map(|v| v / shrink));
        dofs.push(dof);
        // The mean time, summed as offsets: a sum of epoch nanoseconds overflows.
        let t0 = rows.rows[idx[0]].t_ns;
        let t = t0 + idx.iter().map(|i| rows.rows[*i].t_ns - t0).sum::<i64>() / idx.len() as i64;
        cycles.push((*c, t, chi2));
    }
    // Each cycle against its own degrees of freedom: one with a missing reading has fewer.
    let alarms = cycles
        .iter()
        .zip(&dofs)
        .filter(|((_, _, c), d)| *c > driftwatch_core::stats::chi2_quantile(0.999, **d))
        .map(|((c, _, _), _)| *c)
        .collect();
    let norm: Vec<f64> = cycles
        .iter()
        .zip(&dofs)
        .map(|((_, _, c), d)| c / *d as f64 - 1.0)
        .collect();
    let mut count: BTreeMap<usize, usize> = BTreeMap::new();
    for d in &dofs {
        *count.entry(*d).or_default() += 1;
    }
    let dof_common = count
        .iter()
        .max_by_key(|(d, n)| (**n, **d))
        .map_or(0, |(d, _)| *d);
    let cu = driftwatch_core::stats::cusum(&norm, 0.0, 0.5, 5.0);
    Redundancy {
        dof: dof_common,
        alarms,
        cusum_alarm: cu.first_alarm.map(|i| cycles[i].0),
        sigma_um: if cycles.len() >= 20 {
            driftwatch_core::stats::mad_sigma(&all)
        } else {
            None
        },
        cycles,
    }
}

/// Run the whole search on `rows` with the spindle log (every speed change, the cycles' spins
/// included when logged) and the temperature log.
pub fn diagnose(
    rows: &Rows,
    spindle: &[Event],
    temperatures: &[Event],
    opts: &DiagnoseOptions,
) -> Result<Diagnosis, DiagnosisError> {
    if !(SIGMA_UM_RANGE.0..=SIGMA_UM_RANGE.1).contains(&opts.sigma_um) {
        return Err(DiagnosisError::BadSigma {
            sigma: opts.sigma_um,
        });
    }
    if rows.rows.is_empty() {
        return Err(DiagnosisError::NoDetections);
    }
    let sensors = driftwatch_thermal::model::sensors_of(temperatures);
    let redundancy = redundancy(rows, opts.sigma_um);
    // Outliers against a robust baseline, removed once.
    let (rows, outliers) = search::without_outliers(rows, spindle, opts);
    let mut s = Search::new(rows, spindle, temperatures, opts);
    // The baseline, and where it misses.
    let baseline = s.figures(&s.base);
    let resid_um: Vec<f64> = baseline.resid.iter().map(|v| v * opts.sigma_um).collect();
    let phase = phases(&s.rows, spindle);
    let located = s.locate(&resid_um, &phase);
    // The library, whitened, and what the baseline cannot tell apart from it.
    let q0 = basis(&s.base);
    s.candidates(&q0, &baseline.resid);
    let drivers = s.screen(&q0, &baseline.resid);
    let thresholds = s.thresholds();
    let not_tested = s.allow();
    let not_identifiable = s.not_identifiable();
    // Forward selection and backward pruning, again over a periodic discrepancy if one is
    // found; then the terms that coincide in time with an earlier one.
    let (base_eff, mut sel, periodic) = s.periodic(s.select(&s.base));
    let coincidences = s.coincidences(&base_eff, &mut sel.chosen);
    // The final fit, each term's figures and its ambiguity group.
    let fin = s.final_fit(base_eff, sel.chosen, sel.blocks_better, coincidences);
    let (accepted, footprints) = s.accepted(&fin, &sensors);
    // One verdict per effect: what the search accepted (named, or in an accepted term's
    // group) was identified on this plan, whatever the energy rule said before the search.
    let mut not_identifiable = not_identifiable;
    not_identifiable.retain(|n| {
        !accepted
            .iter()
            .any(|a| a.effect == n.effect || a.ambiguity_group.iter().any(|g| g.effect == n.effect))
    });
    let mut refused = sel.refused;
    refused.retain(|r| {
        !accepted
            .iter()
            .any(|a| a.term == r.term && a.effect == r.effect)
    });
    // Per channel, before and after; what stays structured.
    let channels = s.channels(&baseline, &fin);
    let periodic = periodic.map(|(found, kb)| s.size_periodic(&fin, found, kb));
    let unexplained = s.unexplained(&fin, &phase, periodic, &channels);
    let series = series(&s, &baseline, &fin, resid_um, footprints, q0);
    Ok(Diagnosis {
        sigma_um: opts.sigma_um,
        readings: s.n,
        cycles: series.cycle.iter().collect::<BTreeSet<_>>().len(),
        span_h: s.drivers.span_h,
        blocks: s.blocks,
        redundancy,
        baseline: baseline.figures,
        outliers,
        located,
        drivers,
        accepted,
        refused,
        not_identifiable,
        not_tested,
        thresholds,
        unexplained,
        final_fit: fin.fit.figures,
        channels,
        series,
    })
}

/// The per-row series of search `s` for plots: baseline residuals `resid_um`, the final ones,
/// the held-out predictions and the accepted terms' `footprints`, and the baseline's
/// orthonormal basis `q0`.
fn series(
    s: &Search,
    baseline: &search::Fit,
    fin: &search::Final,
    resid_um: Vec<f64>,
    footprints: Vec<(String, Vec<f64>)>,
    q0: DMatrix<f64>,
) -> Series {
    let (rows, sigma, nb) = (&s.rows, s.sigma, s.blocks.len());
    Series {
        t_ns: s.times.clone(),
        cycle: rows.rows.iter().map(|r| r.cycle).collect(),
        step: rows.rows.iter().map(|r| r.step.clone()).collect(),
        baseline_um: resid_um,
        final_um: fin.fit.resid.iter().map(|v| v * sigma).collect(),
        heldout_baseline_um: baseline.pred.iter().map(|v| v * sigma).collect(),
        heldout_final_um: fin.fit.pred.iter().map(|v| v * sigma).collect(),
        heldout: s.block_of.iter().map(|b| *b == nb - 1).collect(),
        footprints,
        deviation_um: rows.rows.iter().map(|r| r.deviation_um).collect(),
        baseline_basis: q0,
    }
}

/// Run the diagnosis on already-read inputs.
pub fn diagnose_inputs(
    k: &Kinematics,
    inputs: &Inputs,
    opts: &DiagnoseOptions,
) -> Result<Diagnosis, DiagnosisError> {
    let rows = detection_rows(k, &inputs.detections, &SolveOptions::new(opts.sigma_um))?;
    diagnose(&rows, &inputs.spindle, &inputs.temperatures, opts)
}

/// What the diagnosis takes from a recording: the parsed detections, the spindle log and the
/// temperature log as model input events. Unparseable detections are counted, not used.
pub struct Inputs {
    pub detections: Vec<Timed<DetectionMsg>>,
    pub spindle: Vec<Event>,
    pub temperatures: Vec<Event>,
    pub unparsed: usize,
}

impl Inputs {
    pub fn of(rec: &driftwatch_core::recording::Recording) -> Inputs {
        let mut detections = Vec::new();
        let mut unparsed = 0;
        for d in &rec.detections {
            match &d.msg {
                Ok(m) => detections.push(Timed {
                    t_ns: d.t_ns,
                    msg: m.clone(),
                }),
                Err(_) => unparsed += 1,
            }
        }
        Inputs {
            detections,
            spindle: rec
                .spindle
                .iter()
                .map(|m| Event::Spindle {
                    t_ns: m.t_ns,
                    rpm: m.msg.rpm,
                })
                .collect(),
            temperatures: rec
                .temperatures
                .iter()
                .map(|m| Event::Temperature {
                    t_ns: m.t_ns,
                    sensor: m.msg.sensor.clone(),
                    celsius: m.msg.celsius,
                })
                .collect(),
            unparsed,
        }
    }

    /// Append another recording of the same machine (a recording per day).
    pub fn extend(&mut self, other: Inputs) {
        self.detections.extend(other.detections);
        self.spindle.extend(other.spindle);
        self.temperatures.extend(other.temperatures);
        self.unparsed += other.unparsed;
        self.spindle.sort_by_key(Event::t_ns);
        self.temperatures.sort_by_key(Event::t_ns);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::kinematics::MAX_ROTARY;
    use driftwatch_core::measurement::Axis;

    fn row(cycle: i64, k: i64, deviation_um: f64) -> DetectionRow {
        DetectionRow {
            t_ns: cycle * units::NS_PER_H + k * 1_000_000_000,
            cycle,
            step: format!("z{k}"),
            b_deg: 0.0,
            c_deg: 0.0,
            axis: Axis::Z,
            direction: -1,
            feed_mm_min: 100.0,
            spindle_rpm: 0.0,
            t_in_cycle_s: k as f64,
            rotary_sense: [0; MAX_ROTARY],
            deviation_um,
            sensitivity: vec![1.0],
            signature: Vec::new(),
        }
    }

    /// One design parameter (a common offset), so a cycle of n readings has n - 1 degrees of
    /// freedom and its chi-square is the spread of its readings about their mean.
    fn cycle(c: i64, deviations: &[f64]) -> Vec<DetectionRow> {
        deviations
            .iter()
            .enumerate()
            .map(|(k, d)| row(c, k as i64, *d))
            .collect()
    }

    /// The coarse scan's normal equations (products taken once, phases turned from step to
    /// step, exact again every `RESEED` steps) against `X^T X` and `X^T e` formed at each
    /// frequency, over more steps than one reseed.
    #[test]
    fn the_coarse_periodic_scan_agrees_with_the_normal_equations_formed_at_each_period() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let p = 3;
        let rows = Rows {
            params: (0..p).map(|j| format!("p{j}")).collect(),
            locations: Vec::new(),
            signatures: Vec::new(),
            rows: (0..300)
                .map(|i| DetectionRow {
                    t_ns: i * 7 * units::NS_PER_MIN + rng.random_range(0..units::NS_PER_MIN),
                    sensitivity: (0..p).map(|_| rng.random_range(-1.0..1.0)).collect(),
                    ..row(i, 0, 0.0)
                })
                .collect(),
        };
        let e = DVector::from_fn(rows.rows.len(), |_, _| rng.random_range(-2.0..2.0));
        let sigma = 0.7;
        let tmin: Vec<f64> = rows.rows.iter().map(|r| r.t_ns as f64 / 6e10).collect();
        let span = tmin[tmin.len() - 1];
        let df = 1.0 / (2.0 * span);
        let direct = |f: f64| {
            let w = std::f64::consts::TAU * f;
            let x = DMatrix::from_fn(rows.rows.len(), 2 * p, |i, c| {
                let (s, co) = (w * tmin[i]).sin_cos();
                rows.rows[i].sensitivity[c % p] / sigma * if c < p { co } else { s }
            });
            let mut a = x.tr_mul(&x);
            let ridge = 1e-9 * a.trace() / a.nrows() as f64;
            for i in 0..a.nrows() {
                a[(i, i)] += ridge;
            }
            inverse_form(a, &x.tr_mul(&e)).unwrap_or(0.0)
        };
        let mut pairs = CoarsePairs::new(&rows, &e, sigma, &tmin, df);
        let f0 = 1.0 / 240.0;
        for k in 0..(2 * CoarsePairs::RESEED + 5) {
            let f = f0 + k as f64 * df;
            if k % CoarsePairs::RESEED == 0 {
                pairs.seed(f);
            }
            let (got, want) = (pairs.explained(), direct(f));
            assert!(want > 0.0);
            assert!(
                (got - want).abs() <= 1e-9 * want,
                "step {k}: {got} against {want}"
            );
            pairs.advance();
        }
    }

    #[test]
    fn a_cycle_with_a_missing_reading_is_judged_on_its_own_degrees_of_freedom() {
        // Cycle 1 lost two readings: 3 left, dof 2, chi2 = 15 (over the 0.999 quantile of 2
        // dof, 13.8; under that of 4 dof, 18.5). Cycles 2 and 3 are full and quiet.
        let s = 15f64.sqrt() / 2f64.sqrt();
        let mut rows = cycle(1, &[-s, 0.0, s]);
        rows.extend(cycle(2, &[0.1, -0.1, 0.2, -0.2, 0.0]));
        rows.extend(cycle(3, &[0.2, 0.0, -0.1, 0.1, -0.2]));
        let r = redundancy(
            &Rows {
                params: vec!["offset".into()],
                locations: Vec::new(),
                signatures: Vec::new(),
                rows,
            },
            1.0,
        );
        assert_eq!(r.dof, 4, "the full cycles' degrees of freedom");
        assert!((r.cycles[0].2 - 15.0).abs() < 1e-9, "{:?}", r.cycles);
        assert_eq!(r.alarms, vec![1]);
    }
}
