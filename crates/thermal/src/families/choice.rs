//! The choice of what a channel serves: the baseline and the challenger that beats it beyond
//! chance, inside the fit range and beyond it; the excursion beyond the fit range; what
//! `fit` keeps ([`ChannelChoice`]) and what it serves from an origin.

use super::cv::{CvError, Run, cv_rms, folds, null_as_nan};
use super::fitted::Family;
use super::grid::Grid;
use driftwatch_core::stats::sign_test_wins;

/// How the served family was chosen for one regime of the inputs.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RegimeChoice {
    pub family: Family,
    /// The family with the lowest CV error on the regime's points, and on how many folds
    /// (of those with such points) it beat the baseline.
    pub best_cv: Family,
    pub fold_wins: usize,
    pub folds: usize,
    /// CV points in the regime, and the RMSE there of the chosen family and the baseline.
    pub points: usize,
    /// NaN where a family has no CV points here (null in JSON, read back as NaN).
    #[serde(deserialize_with = "null_as_nan")]
    pub rmse: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub baseline_rmse: f64,
    pub why: String,
}

/// How the served prediction of a channel was chosen. Warm-up data leave the fit's input
/// range by design, and a model that predicts well inside what it was fitted on may not
/// outside it, so each regime has its own choice, judged on the CV points of that regime:
/// **inside** (every input within its fold's fit range, widened by [`RANGE_SLACK`] of it)
/// and **beyond** (from the first point in a fold where some input is not). At prediction
/// time the inputs are measured as they happen, so which regime a point is in is known
/// causally. A challenger replaces the textbook baseline in a regime only where it wins
/// beyond chance on folds with separate prediction windows ([`independent_folds`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Choice {
    /// The inside choice's family (the one the channel is named by).
    pub family: Family,
    /// The textbook baseline every choice starts from: least squares on every input, or
    /// persistence where that could not be fitted. A challenger replaces it only where it
    /// wins beyond chance ([`sign_test_wins`]).
    pub baseline: Family,
    pub inside: RegimeChoice,
    /// `None` where the CV folds never left their fit range.
    pub beyond: Option<RegimeChoice>,
    /// The largest excursion beyond the fit range the CV folds tested (a share of each
    /// input's range, [`excursion`]; infinite, written as null, where a forced family serves
    /// everywhere).
    #[serde(deserialize_with = "null_as_nan")]
    pub tested_excursion: f64,
    /// The horizon of use and the longest the CV folds tested, grid steps.
    pub horizon: usize,
    pub tested_horizon: usize,
    pub why: String,
}

impl RegimeChoice {
    /// The choice among `runs` on the CV points where `mask` holds.
    fn of(
        runs: &[(Run, Option<f64>)],
        baseline: Family,
        mask: &[bool],
        independent: &[usize],
        regime: &str,
    ) -> Self {
        let pick = |r: &Run| -> Vec<CvError> {
            r.cv.iter()
                .zip(mask)
                .filter(|(_, m)| **m)
                .map(|(c, _)| *c)
                .collect()
        };
        let usable: Vec<(Family, Vec<CvError>)> = runs
            .iter()
            .filter(|(r, _)| r.cv.len() == mask.len())
            .map(|(r, _)| (r.family, pick(r)))
            .filter(|(_, e)| !e.is_empty() && cv_rms(e).is_finite())
            .collect();
        let base = usable.iter().find(|(f, _)| *f == baseline);
        let best = usable
            .iter()
            .min_by(|a, b| cv_rms(&a.1).total_cmp(&cv_rms(&b.1)));
        let points = base.map_or(0, |b| b.1.len());
        let (best_cv, wins, folds) = match (best, base) {
            (Some(b), Some(base)) => {
                let (w, n) = fold_wins(&b.1, &base.1, independent);
                (b.0, w, n)
            }
            (Some(b), None) => (b.0, 0, 0),
            _ => (baseline, 0, 0),
        };
        let replaced = best_cv != baseline && sign_test_wins(folds).is_some_and(|w| wins >= w);
        let family = if replaced { best_cv } else { baseline };
        let rmse_of = |f: Family| {
            usable
                .iter()
                .find(|(g, _)| *g == f)
                .map_or(f64::NAN, |(_, e)| cv_rms(e))
        };
        let why = if best_cv == baseline {
            format!("{regime}: {} has the lowest CV error", baseline.as_str())
        } else if replaced {
            format!(
                "{regime}: {} beat the textbook baseline ({}) on {wins} of {folds} CV folds with separate prediction windows",
                best_cv.as_str(),
                baseline.as_str()
            )
        } else {
            format!(
                "{regime}: {} served; {} had the lowest CV error but beat it on {wins} of {folds} folds with separate prediction windows ({}), not beyond chance",
                baseline.as_str(),
                best_cv.as_str(),
                sign_test_wins(folds).map_or("too few folds for the test".into(), |w| format!(
                    "the bar is {w}"
                ))
            )
        };
        RegimeChoice {
            family,
            best_cv,
            fold_wins: wins,
            folds,
            points,
            rmse: rmse_of(family),
            baseline_rmse: rmse_of(baseline),
            why,
        }
    }
}

impl Choice {
    /// `regression_has_inputs`: some input varied over the fit data (else least squares is
    /// a constant, the fit data's mean, and holding the last reading is the baseline).
    pub(super) fn of(
        runs: &[(Run, Option<f64>)],
        excursions: &[f64],
        independent: &[usize],
        (tested, horizon): (usize, usize),
        regression_has_inputs: bool,
    ) -> Self {
        let find = |f: Family| runs.iter().find(|(r, _)| r.family == f).map(|(r, _)| r);
        let baseline = [Family::Regression, Family::Persistence]
            .into_iter()
            .find(|f| {
                find(*f).is_some_and(|r| {
                    cv_rms(&r.cv).is_finite()
                        && (*f == Family::Persistence || regression_has_inputs)
                })
            })
            .unwrap_or(Family::Persistence);
        let inside_mask: Vec<bool> = excursions.iter().map(|x| *x <= RANGE_SLACK).collect();
        let beyond_mask: Vec<bool> = inside_mask.iter().map(|m| !m).collect();
        let inside = RegimeChoice::of(
            runs,
            baseline,
            &inside_mask,
            independent,
            "inside the fit range",
        );
        let beyond = (beyond_mask.iter().filter(|m| **m).count() >= MIN_BEYOND).then(|| {
            RegimeChoice::of(
                runs,
                baseline,
                &beyond_mask,
                independent,
                "beyond the fit range",
            )
        });
        let tested_excursion = if beyond.is_some() {
            excursions.iter().copied().fold(0.0, f64::max)
        } else {
            RANGE_SLACK
        };
        let mut why = inside.why.clone();
        match &beyond {
            Some(b) => why.push_str(&format!(
                "; {} (excursions up to {:.2} of an input's fit range tested)",
                b.why, tested_excursion
            )),
            None => why.push_str(&format!(
                "; the CV folds never left their fit range by more than {:.0} % of it: beyond that untested",
                100.0 * RANGE_SLACK
            )),
        }
        if tested < horizon && horizon < usize::MAX / 2 {
            why.push_str(&format!(
                "; the CV tested horizons up to {tested} grid steps, the model is used {horizon} ahead: beyond what the CV saw"
            ));
        }
        Choice {
            family: inside.family,
            baseline,
            inside,
            beyond,
            tested_excursion,
            horizon,
            tested_horizon: tested,
            why,
        }
    }
}

/// Fewest CV points beyond the folds' fit range for a choice there.
pub const MIN_BEYOND: usize = 10;

/// The folds whose prediction windows do not overlap, taken from the last (the one fitted
/// on the most data) backwards: overlapping folds predict the same readings from nearly the
/// same fit, so they are not separate trials for the sign test.
pub fn independent_folds(folds: &[(usize, usize)]) -> Vec<usize> {
    let mut out = Vec::new();
    let mut before = usize::MAX;
    for (i, &(a, b)) in folds.iter().enumerate().rev() {
        if b <= before {
            out.push(i);
            before = a;
        }
    }
    out.reverse();
    out
}

/// On how many folds `a`'s mean square error is below `b`'s, of the `independent` folds
/// both have.
fn fold_wins(a: &[CvError], b: &[CvError], independent: &[usize]) -> (usize, usize) {
    let per_fold = |e: &[CvError]| {
        let mut m: std::collections::BTreeMap<usize, (f64, usize)> = Default::default();
        for c in e {
            let x = m.entry(c.fold).or_default();
            x.0 += c.e * c.e;
            x.1 += 1;
        }
        m
    };
    let (pa, pb) = (per_fold(a), per_fold(b));
    let mut wins = 0;
    let mut n = 0;
    for (f, (sa, na)) in pa.iter().filter(|(f, _)| independent.contains(f)) {
        if let Some((sb, nb)) = pb.get(f) {
            n += 1;
            wins += usize::from(sa / (*na as f64) < sb / (*nb as f64));
        }
    }
    (wins, n)
}

/// How far grid point `k` lies beyond `ranges`: the largest of each input's distance
/// outside its range, as a share of the range (0 inside; an input constant over the fit
/// data that moves counts as far beyond anything, `f64::INFINITY`).
pub fn excursion(g: &Grid, ranges: &[[f64; 2]], k: usize) -> f64 {
    excursion_by_input(g, ranges, k).0
}

/// [`excursion`] and the input that makes it (the first of equals).
pub fn excursion_by_input(g: &Grid, ranges: &[[f64; 2]], k: usize) -> (f64, usize) {
    g.inputs
        .iter()
        .zip(ranges)
        .map(|(x, &[lo, hi])| {
            let v = x[k];
            let out = (lo - v).max(v - hi).max(0.0);
            if out <= 1e-9 * lo.abs().max(hi.abs()).max(1.0) {
                0.0
            } else if hi - lo <= 0.0 {
                f64::INFINITY
            } else {
                out / (hi - lo)
            }
        })
        .enumerate()
        .fold(
            (0.0, 0),
            |best, (j, x)| if x > best.0 { (x, j) } else { best },
        )
}

/// For each CV error of [`cv_run`]'s order: the running largest [`excursion`] in its fold
/// from the origin to the point (a fold that has left its fit range counts as beyond from
/// then on, as the served prediction does). An input constant over a fold's fit data is left
/// out there: the fold's models have no gain on it, and the model served has one wherever
/// it varied in the fit data, so such a fold says nothing of how it extrapolates (it would
/// judge the regime by a never-seen input, as a spindle stage that starts after a fold's
/// origin is).
pub(super) fn fold_excursions(g: &Grid, n_train: usize, horizon: usize) -> Vec<f64> {
    let mut out = Vec::new();
    for (o, stop) in folds(n_train, horizon) {
        let ranges: Vec<[f64; 2]> = input_ranges(g, o)
            .into_iter()
            .map(|[lo, hi]| {
                if hi > lo {
                    [lo, hi]
                } else {
                    [f64::NEG_INFINITY, f64::INFINITY]
                }
            })
            .collect();
        let mut run = 0.0f64;
        for k in o..stop {
            run = run.max(excursion(g, &ranges, k));
            if g.fresh[k] {
                out.push(run);
            }
        }
    }
    out
}

/// How far beyond an input's fitted range, as a share of it, an empirical family still serves.
pub const RANGE_SLACK: f64 = 0.5;

/// Each input's range over grid points `0..n_train`.
pub fn input_ranges(g: &Grid, n_train: usize) -> Vec<[f64; 2]> {
    g.inputs
        .iter()
        .map(|x| {
            let seen = &x[..n_train.min(x.len())];
            [
                seen.iter().copied().fold(f64::INFINITY, f64::min),
                seen.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            ]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_excursion_is_a_share_of_the_fit_range_and_names_its_input() {
        let g = Grid {
            channel: "d".into(),
            t_ns: vec![0, 1, 2],
            y: vec![0.0; 3],
            names: vec!["a".into(), "b".into(), "c".into()],
            inputs: vec![vec![20.0, 21.0, 23.0], vec![5.0, 5.0, 2.0], vec![1.0; 3]],
            fresh: vec![true; 3],
        };
        let ranges = input_ranges(&g, 2);
        assert_eq!(ranges, [[20.0, 21.0], [5.0, 5.0], [1.0, 1.0]]);
        assert_eq!(excursion_by_input(&g, &ranges, 1), (0.0, 0));
        // a is 2 of its range beyond it; b, constant over the fit data, moved: infinitely far.
        assert_eq!(excursion_by_input(&g, &ranges, 2), (f64::INFINITY, 1));
        let no_b = [ranges[0], [f64::NEG_INFINITY, f64::INFINITY], ranges[2]];
        assert_eq!(excursion_by_input(&g, &no_b, 2), (2.0, 0));
    }

    #[test]
    fn folds_with_overlapping_windows_are_one_trial() {
        assert_eq!(
            independent_folds(&[(0, 10), (5, 15), (10, 20), (15, 25)]),
            [1, 3]
        );
        assert_eq!(independent_folds(&[(0, 4), (4, 8), (8, 12)]), [0, 1, 2]);
        assert_eq!(independent_folds(&folds(96, 72)).len(), 1);
    }
}
