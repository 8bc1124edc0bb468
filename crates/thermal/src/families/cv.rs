//! Rolling-origin (forward-chaining) cross-validation: the folds, each fold's errors and its
//! residual at the origin, the residual's relaxation, and root mean squares.

use super::fitted::{Family, Fitted, simulate, simulate_with};
use super::grid::Grid;
use driftwatch_core::units;

/// Rolling origins of the CV: this many, spread evenly (fewer on a short span).
pub const N_FOLDS: usize = 8;

/// Rolling origins over the first `end` grid points for a model used `horizon` grid steps
/// ahead of its last reading: [`N_FOLDS`] origins, each fold fitted on what comes before it
/// and predicting freely up to `horizon` steps, never past `end`. The CV judges a model at
/// the horizon it is used for, as far as the data allow: the origins run from half the span
/// to where a fold still has its whole horizon, or to three quarters of it when the horizon
/// is longer than a quarter. No fold is fitted on less than half the span: a fold fitted on
/// far less data than the model it judges misjudges it (on short warm-up runs, least squares
/// on two dozen temperatures fitted on a third of the fit lost to persistence in CV and beat
/// it on the hold-out). What the folds test is [`tested_horizon`]; a longer horizon of use is
/// beyond what the CV saw, and the choice says so.
pub fn folds(end: usize, horizon: usize) -> Vec<(usize, usize)> {
    if end < 2 {
        return Vec::new();
    }
    let horizon = horizon.max(1);
    let first = (end / 2).max(1);
    let last = end
        .saturating_sub(horizon.min((end - first) / 2).max(1))
        .max(first);
    let mut o: Vec<usize> = (0..N_FOLDS)
        .map(|i| first + (last - first) * i / (N_FOLDS - 1))
        .collect();
    o.dedup();
    o.into_iter()
        .map(|a| (a, a.saturating_add(horizon).min(end)))
        .filter(|(a, b)| a < b && *a > 0)
        .collect()
}

/// The longest horizon, in grid steps, the folds of [`folds`] test.
pub fn tested_horizon(end: usize, horizon: usize) -> usize {
    folds(end, horizon)
        .iter()
        .map(|(a, b)| b - a)
        .max()
        .unwrap_or(0)
}

/// One CV error: its fold, its horizon in grid steps after the fold's origin, its value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CvError {
    pub fold: usize,
    pub horizon: usize,
    pub e: f64,
}

/// A fold's errors on the fresh readings (`fresh` and `y` from the fold's origin).
pub(super) fn fold_errors<'a>(
    fold: usize,
    p: &'a [f64],
    y: &'a [f64],
    fresh: &'a [bool],
) -> impl Iterator<Item = CvError> + 'a {
    p.iter()
        .zip(y)
        .enumerate()
        .filter(|(h, _)| fresh[*h])
        .map(move |(horizon, (p, y))| CvError {
            fold,
            horizon,
            e: p - y,
        })
}

/// The errors of a fit procedure over the folds of `0..end`; `None` when a fold could not
/// be fitted.
pub(super) fn cv_errors(
    g: &Grid,
    end: usize,
    horizon: usize,
    fit: &dyn Fn(usize) -> Option<Fitted>,
) -> Option<Vec<CvError>> {
    cv_run(g, end, horizon, fit).map(|r| r.0)
}

/// [`cv_errors`], and each fold's residual at its origin: the last reading before it less
/// the fold's model there.
pub(super) fn cv_run(
    g: &Grid,
    end: usize,
    horizon: usize,
    fit: &dyn Fn(usize) -> Option<Fitted>,
) -> Option<(Vec<CvError>, Vec<f64>)> {
    let mut e = Vec::new();
    let mut r0 = Vec::new();
    for (i, (o, stop)) in folds(end, horizon).into_iter().enumerate() {
        let f = fit(o)?;
        let p = simulate(&f, g, o, stop);
        e.extend(fold_errors(i, &p, &g.y[o..stop], &g.fresh[o..stop]));
        r0.push(origin_residual(&f, g, o, f64::NAN));
    }
    (!e.is_empty()).then_some((e, r0))
}

/// The residual at an origin: the last reading before grid point `origin` less what `f`
/// gives there (`grey_prev`: the grey box's value there, for a fit that holds it). 0 when it
/// cannot be had (the relaxation then adds nothing).
pub fn origin_residual(f: &Fitted, g: &Grid, origin: usize, grey_prev: f64) -> f64 {
    if origin == 0 || origin > g.len() {
        return 0.0;
    }
    let p = simulate_with(f, g, origin - 1, origin, &[grey_prev]);
    match p.first() {
        Some(v) if v.is_finite() => g.y[origin - 1] - v,
        _ => 0.0,
    }
}

/// Relaxation times the CV chooses among, hours: the residual at the origin decays
/// `exp(-t / tau)` into the prediction (none: the model's mean alone; 64 h: about holding it
/// over any horizon here).
pub const RELAX_H: [f64; 4] = [1.0, 4.0, 16.0, 64.0];

/// The weight of the origin's residual `horizon` grid points after the origin (the first
/// prediction is one step after the last reading).
pub fn relax_weight(relax_h: Option<f64>, horizon: usize, step_ns: i64) -> f64 {
    relax_h.map_or(0.0, |tau| {
        (-((horizon + 1) as f64) * step_ns as f64 / (tau * units::NS_PER_H as f64)).exp()
    })
}

pub(super) fn cv_rms(e: &[CvError]) -> f64 {
    rms(&e.iter().map(|c| c.e).collect::<Vec<_>>())
}

/// Root mean square (0 for no values).
pub fn rms(e: &[f64]) -> f64 {
    (e.iter().map(|v| v * v).sum::<f64>() / e.len().max(1) as f64).sqrt()
}

/// A figure that may be NaN: serde_json writes NaN as null, so null reads back as NaN (a
/// model file written by `fit` without a hold-out must load again).
pub(super) fn null_as_nan<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(<Option<f64> as serde::Deserialize>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// A family's CV errors and hold-out predictions, before scoring.
pub(super) struct Run {
    pub(super) family: Family,
    pub(super) detail: String,
    pub(super) cv: Vec<CvError>,
    pub(super) hold: Vec<f64>,
    pub(super) weights: Vec<(String, f64)>,
    /// Each fold's residual at its origin, and the hold-out's.
    pub(super) r0: Vec<f64>,
    pub(super) hold_r0: f64,
}

impl Run {
    /// The relaxation the CV prefers (none, or one of [`RELAX_H`]), applied to the CV errors
    /// and the hold-out predictions.
    pub(super) fn relaxed(mut self, step_ns: i64) -> (Run, Option<f64>) {
        let with = |tau: Option<f64>| -> Vec<CvError> {
            self.cv
                .iter()
                .map(|c| CvError {
                    e: c.e
                        + self.r0.get(c.fold).copied().unwrap_or(0.0)
                            * relax_weight(tau, c.horizon, step_ns),
                    ..*c
                })
                .collect()
        };
        let best = std::iter::once(None)
            .chain(RELAX_H.iter().map(|h| Some(*h)))
            .map(|tau| (cv_rms(&with(tau)), tau))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .and_then(|b| b.1);
        self.cv = with(best);
        for (h, p) in self.hold.iter_mut().enumerate() {
            *p += self.hold_r0 * relax_weight(best, h, step_ns);
        }
        (self, best)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folds_chain_forward_and_cover_the_second_half() {
        // A short horizon: origins from half the span to where the horizon still fits.
        assert_eq!(
            folds(80, 8),
            [40, 44, 49, 53, 58, 62, 67, 72].map(|o| (o, o + 8))
        );
        // A horizon longer than a quarter of the span: from half to three quarters, each
        // fold to the end.
        let long = folds(96, 72);
        assert_eq!(long.first(), Some(&(48, 96)));
        assert_eq!(long.last(), Some(&(72, 96)));
        assert!(long.iter().all(|f| f.1 == 96), "{long:?}");
        assert_eq!(tested_horizon(96, 72), 48);
        assert_eq!(tested_horizon(80, 8), 8);
        assert!(folds(1, 5).is_empty());
    }
}
