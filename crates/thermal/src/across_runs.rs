//! Learning across runs: a plant's thermal tests are many runs (days), each starting from
//! its own state and zeroed at its start. A model is learnt from earlier runs and predicts a
//! new run whole, from its first reading, with no reading after it: how a model is used in
//! production. Every family here takes a channel's reading and its inputs as changes since
//! the run's first grid point, `z_k = y_k - y_0`, `v_k = u_k - u_0`, which is what zeroed
//! sensors mean and what a new run gives at its start:
//! - persistence: `z = 0` (the first reading held);
//! - regression on every input: `z_k = b' v_k`, each run with its own offset (fitted by
//!   removing each run's means, the fixed-effects estimator), anchored at the first reading
//!   when predicting;
//! - key-temperature regression: the same on the inputs forward selection keeps by the
//!   leave-earlier-runs CV below;
//! - ARX run freely from the start: `z_k = a z_(k-1) + sum_l b_l' v_(k-l)`.
//!
//! The choice is made by forward chaining over whole runs (predict run j from the runs
//! before it), and a family replaces the textbook baseline (regression on every input) only
//! when it wins beyond chance (the sign test of [`sign_test_wins`]). Pure:
//! grids in, figures out.

use nalgebra::{DMatrix, DVector};

use crate::families::{Family, Grid, forward_select, rms};
use driftwatch_core::least_squares::least_squares;
use driftwatch_core::stats::sign_test_wins;

/// The families that compete across runs (the grey box's filter needs one timeline).
pub const FAMILIES: [Family; 4] = [
    Family::Persistence,
    Family::Regression,
    Family::KeyRegression,
    Family::Arx,
];

/// A family fitted on several runs.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RunsFitted {
    pub family: Family,
    /// Input indices of the grids.
    pub inputs: Vec<usize>,
    /// Regression: one gain per input. ARX: `a`, then `b_j0, b_j1` per input.
    pub coef: Vec<f64>,
}

/// Fit `family` on `runs` with `inputs` (key regression chooses its own among them).
pub fn fit(family: Family, runs: &[&Grid], inputs: &[usize]) -> Option<RunsFitted> {
    match family {
        Family::Persistence => Some(RunsFitted {
            family,
            inputs: Vec::new(),
            coef: Vec::new(),
        }),
        Family::Regression => fit_regression(runs, inputs),
        Family::KeyRegression => {
            let key = key_inputs(runs, inputs);
            fit_regression(runs, &key).map(|f| RunsFitted { family, ..f })
        }
        Family::Arx => fit_arx(runs, inputs),
        _ => None,
    }
}

/// Fixed-effects least squares: each run's means removed from the reading and the inputs.
fn fit_regression(runs: &[&Grid], inputs: &[usize]) -> Option<RunsFitted> {
    let n: usize = runs
        .iter()
        .map(|g| g.fresh.iter().filter(|f| **f).count())
        .sum();
    let mut x = DMatrix::zeros(n, inputs.len());
    let mut y = DVector::zeros(n);
    let mut row = 0;
    for g in runs {
        let ks: Vec<usize> = (0..g.len()).filter(|&k| g.fresh[k]).collect();
        let m = ks.len().max(1) as f64;
        let my = ks.iter().map(|&k| g.y[k]).sum::<f64>() / m;
        let mu: Vec<f64> = inputs
            .iter()
            .map(|&j| ks.iter().map(|&k| g.inputs[j][k]).sum::<f64>() / m)
            .collect();
        for k in (0..g.len()).filter(|&k| g.fresh[k]) {
            y[row] = g.y[k] - my;
            for (c, &j) in inputs.iter().enumerate() {
                x[(row, c)] = g.inputs[j][k] - mu[c];
            }
            row += 1;
        }
    }
    if inputs.is_empty() {
        return Some(RunsFitted {
            family: Family::Regression,
            inputs: Vec::new(),
            coef: Vec::new(),
        });
    }
    let b = least_squares(&x, &y).ok()?;
    Some(RunsFitted {
        family: Family::Regression,
        inputs: inputs.to_vec(),
        coef: b.iter().copied().collect(),
    })
}

/// First-order ARX on changes since each run's start, two input lags, no constant (a run's
/// change is zero at its start), fitted one step ahead on every run's rows; stable only.
fn fit_arx(runs: &[&Grid], inputs: &[usize]) -> Option<RunsFitted> {
    let p = 1 + 2 * inputs.len();
    let mut rows: Vec<Vec<f64>> = Vec::new();
    let mut ys = Vec::new();
    for g in runs {
        for k in 1..g.len() {
            let mut r = vec![g.y[k - 1] - g.y[0]];
            for &j in inputs {
                let u = &g.inputs[j];
                r.push(u[k] - u[0]);
                r.push(u[k - 1] - u[0]);
            }
            rows.push(r);
            ys.push(g.y[k] - g.y[0]);
        }
    }
    let x = DMatrix::from_fn(rows.len(), p, |i, j| rows[i][j]);
    let theta = least_squares(&x, &DVector::from_vec(ys)).ok()?;
    (theta[0].abs() < 1.0).then(|| RunsFitted {
        family: Family::Arx,
        inputs: inputs.to_vec(),
        coef: theta.iter().copied().collect(),
    })
}

/// The prediction of a run from its first grid point, at every grid point (the first is the
/// reading itself).
pub fn predict(f: &RunsFitted, g: &Grid) -> Vec<f64> {
    let n = g.len();
    if n == 0 {
        return Vec::new();
    }
    let y0 = g.y[0];
    let v = |j: usize, k: usize| g.inputs[j][k] - g.inputs[j][0];
    match f.family {
        Family::Arx => {
            let mut z = 0.0;
            let mut out = vec![y0];
            for k in 1..n {
                let mut next = f.coef[0] * z;
                for (c, &j) in f.inputs.iter().enumerate() {
                    next += f.coef[1 + 2 * c] * v(j, k) + f.coef[2 + 2 * c] * v(j, k - 1);
                }
                z = next;
                out.push(y0 + z);
            }
            out
        }
        // Persistence has no inputs: the first reading held.
        _ => (0..n)
            .map(|k| {
                y0 + f
                    .inputs
                    .iter()
                    .zip(&f.coef)
                    .map(|(&j, b)| b * v(j, k))
                    .sum::<f64>()
            })
            .collect(),
    }
}

/// The errors of a run's prediction after its first point.
fn errors(f: &RunsFitted, g: &Grid) -> Vec<f64> {
    predict(f, g)
        .iter()
        .zip(&g.y)
        .zip(&g.fresh)
        .skip(1)
        .filter(|(_, fresh)| **fresh)
        .map(|((p, y), _)| p - y)
        .collect()
}

/// Forward chaining over whole runs: each run from the second on, predicted by `family`
/// fitted on the runs before it. The errors per predicted run; `None` when a fit failed.
pub fn chained_errors(family: Family, runs: &[&Grid], inputs: &[usize]) -> Option<Vec<Vec<f64>>> {
    (1..runs.len())
        .map(|i| fit(family, &runs[..i], inputs).map(|f| errors(&f, runs[i])))
        .collect()
}

/// Forward selection of key inputs by the chained CV of a fixed-effects regression on them:
/// add the input that lowers it most, stop when none lowers it by 1 %. With a single run
/// (no chain) the in-sample fit decides.
fn key_inputs(runs: &[&Grid], inputs: &[usize]) -> Vec<usize> {
    let score = |with: &[usize]| -> f64 {
        if runs.len() >= 2 {
            chained_errors(Family::Regression, runs, with)
                .map_or(f64::INFINITY, |e| rms(&e.concat()))
        } else {
            fit_regression(runs, with).map_or(f64::INFINITY, |f| rms(&errors(&f, runs[0])))
        }
    };
    forward_select(inputs, score(&[]), &score)
}

/// How the family that predicts a new run was chosen.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RunsChoice {
    pub channel: String,
    pub family: Family,
    pub fitted: RunsFitted,
    pub step_ns: i64,
    /// The grids' input names (a run to predict must have the same).
    pub names: Vec<String>,
    /// Each input's change since its run's start over the fit runs: a new run whose changes
    /// leave it is beyond what was learnt.
    pub change_ranges: Vec<[f64; 2]>,
    /// Each family's chained CV RMSE over the fit runs (none where it could not be run).
    pub cv: Vec<(Family, Option<f64>)>,
    pub fold_wins: usize,
    pub folds: usize,
    pub why: String,
}

/// Choose and fit the family that predicts a new run from the runs `runs` (in time order).
pub fn choose(runs: &[&Grid]) -> Option<RunsChoice> {
    let first = runs.first()?;
    let inputs: Vec<usize> = (0..first.names.len()).collect();
    let chains: Vec<(Family, Option<Vec<Vec<f64>>>)> = FAMILIES
        .iter()
        .map(|&f| (f, chained_errors(f, runs, &inputs)))
        .collect();
    let cv: Vec<(Family, Option<f64>)> = chains
        .iter()
        .map(|(f, e)| {
            (
                *f,
                e.as_ref()
                    .map(|e| rms(&e.concat()))
                    .filter(|v| v.is_finite()),
            )
        })
        .collect();
    let of = |f: Family| chains.iter().find(|c| c.0 == f).and_then(|c| c.1.as_ref());
    let baseline = if of(Family::Regression).is_some() {
        Family::Regression
    } else {
        Family::Persistence
    };
    let best = cv
        .iter()
        .filter_map(|(f, e)| e.map(|e| (*f, e)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map_or(baseline, |c| c.0);
    let (wins, folds) = match (of(best), of(baseline)) {
        (Some(a), Some(b)) => (
            a.iter().zip(b).filter(|(a, b)| rms(a) < rms(b)).count(),
            a.len(),
        ),
        _ => (0, 0),
    };
    let replaced = best != baseline && sign_test_wins(folds).is_some_and(|w| wins >= w);
    let family = if replaced { best } else { baseline };
    let why = if best == baseline {
        format!(
            "{} has the lowest CV error over {folds} later runs",
            baseline.as_str()
        )
    } else if replaced {
        format!(
            "{} beat {} on {wins} of {folds} later runs",
            best.as_str(),
            baseline.as_str()
        )
    } else {
        format!(
            "{} served: {} had the lowest CV error but beat it on {wins} of {folds} later runs, not beyond chance{}",
            baseline.as_str(),
            best.as_str(),
            if sign_test_wins(folds).is_none() {
                " (too few runs for any test)"
            } else {
                ""
            }
        )
    };
    let fitted = fit(family, runs, &inputs)?;
    let change_ranges = inputs
        .iter()
        .map(|&j| {
            let mut r = [f64::INFINITY, f64::NEG_INFINITY];
            for g in runs {
                for v in &g.inputs[j] {
                    let d = v - g.inputs[j][0];
                    r = [r[0].min(d), r[1].max(d)];
                }
            }
            r
        })
        .collect();
    Some(RunsChoice {
        channel: first.channel.clone(),
        family,
        fitted,
        step_ns: first.t_ns.get(1).map_or(1, |t| t - first.t_ns[0]),
        names: first.names.clone(),
        change_ranges,
        cv,
        fold_wins: wins,
        folds,
        why,
    })
}

/// Where a new run leaves what the fit runs taught: the first grid point where an input the
/// fitted family uses has changed since the run's start beyond the fit runs' changes by more
/// than half their span, with the input and its change.
pub fn leaves_changes(c: &RunsChoice, g: &Grid) -> Option<(usize, usize, f64)> {
    for k in 0..g.len() {
        for &j in &c.fitted.inputs {
            let [lo, hi] = *c.change_ranges.get(j)?;
            let slack = 0.5 * (hi - lo);
            let d = g.inputs[j][k] - g.inputs[j][0];
            if d < lo - slack || d > hi + slack {
                return Some((k, j, d));
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run driven by one temperature with a run-specific offset, sampled on a grid, and a
    /// second input that is noise.
    fn run(seed: u64, offset: f64, amp: f64) -> Grid {
        let mut rng = seed;
        let mut noise = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((rng >> 33) as f64 / (1u64 << 31) as f64) - 0.5
        };
        let n = 120;
        let drive: Vec<f64> = (0..n)
            .map(|k| 20.0 + amp * (1.0 - (-(k as f64) / 30.0).exp()))
            .collect();
        let other: Vec<f64> = (0..n).map(|_| 21.0 + noise()).collect();
        let y = drive
            .iter()
            .map(|d| offset + 3.0 * (d - 20.0) + 0.05 * noise())
            .collect();
        Grid {
            channel: "x".into(),
            t_ns: (0..n as i64).map(|k| k * 60_000_000_000).collect(),
            y,
            names: vec!["drive".into(), "other".into()],
            inputs: vec![drive, other],
            fresh: vec![true; n],
        }
    }

    #[test]
    fn a_regression_across_runs_learns_the_gain_whatever_each_run_starts_from() {
        let runs: Vec<Grid> = (0..6)
            .map(|i| run(i + 1, 10.0 * i as f64, 2.0 + i as f64))
            .collect();
        let refs: Vec<&Grid> = runs.iter().collect();
        let c = choose(&refs[..5]).unwrap();
        // The gain on the driving input, whatever the offsets.
        let f = fit(Family::Regression, &refs[..5], &[0, 1]).unwrap();
        assert!((f.coef[0] - 3.0).abs() < 0.05, "{f:?}");
        // The new run, predicted from its start, to within the noise; persistence far off.
        let e = errors(&c.fitted, &runs[5]);
        let p = errors(&fit(Family::Persistence, &refs, &[]).unwrap(), &runs[5]);
        assert!(rms(&e) < 0.1 && rms(&p) > 5.0, "{} {}", rms(&e), rms(&p));
        assert!(leaves_changes(&c, &runs[5]).is_none());
        // Four later runs: too few for the sign test, so the baseline serves.
        assert_eq!(c.folds, 4);
        assert_eq!(c.family, Family::Regression, "{}", c.why);
    }

    #[test]
    fn a_run_that_heats_far_beyond_the_fit_runs_is_flagged() {
        let runs: Vec<Grid> = (0..3).map(|i| run(i + 1, 0.0, 2.0)).collect();
        let refs: Vec<&Grid> = runs.iter().collect();
        let c = choose(&refs).unwrap();
        let hot = run(9, 0.0, 8.0);
        let (k, j, _) = leaves_changes(&c, &hot).unwrap();
        assert_eq!(c.names[j], "drive");
        assert!(k > 0);
    }
}
