//! Bands by horizon from CV errors, their coverage (on the CV folds and on a free run), and
//! the score of a free run.

use super::cv::{CvError, rms};
use super::grid::Grid;
use driftwatch_core::units;

/// Upper edges of the horizon bins of a band, hours after the last reading used: a free
/// run's error grows with the horizon, so one band for all horizons is too wide early and
/// too narrow late.
pub const BAND_EDGES_H: [f64; 4] = [1.0, 3.0, 8.0, 20.0];

/// Fewest CV errors a horizon bin needs for its own quantiles; a thinner bin takes the
/// previous bin's.
const MIN_BIN: usize = 20;

/// A band by horizon, from CV errors: in each bin the 68 % and 95 % quantiles of the
/// errors' size, never narrower than the bin before (the last bin holds every longer
/// horizon, beyond what the CV saw: there the band is extrapolated flat, and says so by
/// its hold-out coverage).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Bands {
    /// Upper edge of each bin but the last, in grid steps.
    pub edges: Vec<usize>,
    pub b68: Vec<f64>,
    pub b95: Vec<f64>,
}

impl Bands {
    pub fn from_errors(errors: &[CvError], step_ns: i64) -> Bands {
        let edges: Vec<usize> = BAND_EDGES_H
            .iter()
            .map(|h| (h * units::NS_PER_H as f64 / step_ns.max(1) as f64).round() as usize)
            .collect();
        let pooled: Vec<f64> = errors.iter().map(|c| c.e).collect();
        let (mut b68, mut b95) = (Vec::new(), Vec::new());
        let mut prev = (quantile_abs(&pooled, 0.68), quantile_abs(&pooled, 0.95));
        let mut first = true;
        for i in 0..=edges.len() {
            let lo = if i == 0 { 0 } else { edges[i - 1] };
            let hi = edges.get(i).copied().unwrap_or(usize::MAX);
            let e: Vec<f64> = errors
                .iter()
                .filter(|c| c.horizon >= lo && c.horizon < hi)
                .map(|c| c.e)
                .collect();
            let here = if e.len() >= MIN_BIN {
                let q = (quantile_abs(&e, 0.68), quantile_abs(&e, 0.95));
                if first {
                    q
                } else {
                    (q.0.max(prev.0), q.1.max(prev.1))
                }
            } else {
                prev
            };
            first = false;
            b68.push(here.0);
            b95.push(here.1);
            prev = here;
        }
        Bands { edges, b68, b95 }
    }

    /// The 68 % and 95 % half-widths at `horizon` grid steps after the last reading.
    pub fn at(&self, horizon: usize) -> (f64, f64) {
        let i = self.edges.partition_point(|&e| e <= horizon);
        (
            self.b68.get(i).copied().unwrap_or(f64::NAN),
            self.b95.get(i).copied().unwrap_or(f64::NAN),
        )
    }

    /// The shares of `errors` (by horizon) within the 68 % and 95 % bands.
    pub fn coverage(&self, errors: &[(usize, f64)]) -> (f64, f64) {
        if errors.is_empty() {
            return (f64::NAN, f64::NAN);
        }
        let (mut c68, mut c95) = (0usize, 0usize);
        for &(h, e) in errors {
            let (b68, b95) = self.at(h);
            c68 += usize::from(e.abs() <= b68);
            c95 += usize::from(e.abs() <= b95);
        }
        let n = errors.len() as f64;
        (c68 as f64 / n, c95 as f64 / n)
    }
}

/// The calibration of CV bands on the CV folds themselves: each fold's errors against the
/// bands the other folds give, pooled. A band built and judged on the same errors would
/// cover its share by construction.
pub(super) fn cv_coverage(errors: &[CvError], step_ns: i64) -> (f64, f64) {
    let n_folds = errors.iter().map(|c| c.fold + 1).max().unwrap_or(0);
    let (mut c68, mut c95, mut n) = (0.0, 0.0, 0usize);
    for f in 0..n_folds {
        let others: Vec<CvError> = errors.iter().filter(|c| c.fold != f).copied().collect();
        let mine: Vec<(usize, f64)> = errors
            .iter()
            .filter(|c| c.fold == f)
            .map(|c| (c.horizon, c.e))
            .collect();
        if others.is_empty() || mine.is_empty() {
            continue;
        }
        let (a, b) = Bands::from_errors(&others, step_ns).coverage(&mine);
        c68 += a * mine.len() as f64;
        c95 += b * mine.len() as f64;
        n += mine.len();
    }
    if n == 0 {
        (f64::NAN, f64::NAN)
    } else {
        (c68 / n as f64, c95 / n as f64)
    }
}

/// How a free run from `origin` did: `values[i]` was served at grid point `origin + i`, from the
/// readings before `origin` alone. Scored on the readings the sensor updated (a held value is
/// no reading), against holding the last reading before `origin` (persistence), with the
/// shares of errors within the bands at their horizons.
#[derive(Debug, Clone, PartialEq)]
pub struct FreeRunScore {
    /// Served minus measured, on the updated readings.
    pub errors: Vec<f64>,
    pub rmse: f64,
    pub persistence_rmse: f64,
    /// The largest |error|.
    pub max_abs: f64,
    pub within68: f64,
    pub within95: f64,
}

/// Score a free run (see [`FreeRunScore`]); `origin` must be at least 1 (a last reading).
pub fn score_free_run(g: &Grid, origin: usize, values: &[f64], bands: &Bands) -> FreeRunScore {
    let held = origin.checked_sub(1).and_then(|k| g.y.get(k)).copied();
    let mut by_horizon = Vec::new();
    let mut persistence = Vec::new();
    for (i, v) in values.iter().enumerate() {
        let k = origin + i;
        let (Some(&y), Some(true)) = (g.y.get(k), g.fresh.get(k).copied()) else {
            continue;
        };
        by_horizon.push((i, v - y));
        persistence.push(held.map_or(f64::NAN, |h| h - y));
    }
    let (within68, within95) = bands.coverage(&by_horizon);
    let errors: Vec<f64> = by_horizon.into_iter().map(|(_, e)| e).collect();
    FreeRunScore {
        rmse: rms(&errors),
        persistence_rmse: rms(&persistence),
        max_abs: errors.iter().fold(0.0f64, |m, e| m.max(e.abs())),
        errors,
        within68,
        within95,
    }
}

/// The share of errors within `band` (NaN without errors).
pub fn coverage(errors: &[f64], band: f64) -> f64 {
    if errors.is_empty() {
        return f64::NAN;
    }
    errors.iter().filter(|e| e.abs() <= band).count() as f64 / errors.len() as f64
}

pub(super) fn quantile_abs(e: &[f64], q: f64) -> f64 {
    let mut a: Vec<f64> = e.iter().map(|v| v.abs()).collect();
    a.sort_by(f64::total_cmp);
    if a.is_empty() {
        return f64::NAN;
    }
    let i = ((a.len() as f64 * q).ceil() as usize).clamp(1, a.len()) - 1;
    a[i]
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: i64 = units::NS_PER_MIN;

    /// A free run is scored on the updated readings only, against the last reading before the
    /// origin held, each error judged by the band of its horizon.
    #[test]
    fn a_free_run_is_scored_on_updated_readings_with_the_band_of_each_horizon() {
        let g = Grid {
            channel: "d".into(),
            t_ns: (0..6).map(|k| k * MIN).collect(),
            y: vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
            names: vec![],
            inputs: vec![],
            // Index 4 holds the reading before it: not scored, whatever was served there.
            fresh: vec![true, true, true, true, false, true],
        };
        let bands = Bands {
            edges: vec![1],
            b68: vec![0.6, 0.01],
            b95: vec![1.0, 0.5],
        };
        let s = score_free_run(&g, 2, &[2.5, 3.2, 40.0, 5.0], &bands);
        assert_eq!(s.errors.len(), 3, "{s:?}");
        assert!(
            (s.rmse - ((0.25 + 0.04) / 3.0f64).sqrt()).abs() < 1e-12,
            "{s:?}"
        );
        // Holding y[1] = 1: errors -1, -2, -4.
        assert!((s.persistence_rmse - 7.0f64.sqrt()).abs() < 1e-12, "{s:?}");
        assert!((s.max_abs - 0.5).abs() < 1e-12, "{s:?}");
        // 0.5 at horizon 0 is within 0.6; 0.2 at horizon 1 is not within 0.01 but within 0.5.
        assert!((s.within68 - 2.0 / 3.0).abs() < 1e-12, "{s:?}");
        assert!((s.within95 - 1.0).abs() < 1e-12, "{s:?}");
    }

    /// Errors that grow with the horizon get a band that grows with it; the band from one
    /// fold's errors, judged on another fold like it, covers about its share.
    #[test]
    fn bands_widen_with_the_horizon_and_are_judged_on_other_folds() {
        let step = 5 * MIN;
        let mut rng = 7u64;
        let mut errors = Vec::new();
        for fold in 0..4 {
            for horizon in 0..300 {
                rng = rng
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let u = ((rng >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0;
                errors.push(CvError {
                    fold,
                    horizon,
                    e: u * (1.0 + horizon as f64 / 12.0),
                });
            }
        }
        let b = Bands::from_errors(&errors, step);
        // Edges at 1, 3, 8 and 20 h on a 5-min grid.
        assert_eq!(b.edges, [12, 36, 96, 240]);
        assert!(b.b68.windows(2).all(|w| w[0] <= w[1]), "{b:?}");
        assert!(b.at(0).0 < 0.5 * b.at(200).0, "{b:?}");
        assert!(b.at(0).0 < b.at(0).1);
        // Uniform errors: the 68 % quantile of |u| is 0.68 of the half-width.
        let (c68, c95) = cv_coverage(&errors, step);
        assert!(
            (c68 - 0.68).abs() < 0.05 && (c95 - 0.95).abs() < 0.03,
            "{c68} {c95}"
        );
    }
}
