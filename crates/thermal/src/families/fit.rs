//! The families and their fits: least squares on every input or on the key inputs chosen by
//! forward selection, ARX, the grey box; and their free-run simulation from an origin.

use nalgebra::{DMatrix, DVector};

use super::cv::{cv_errors, cv_rms};
use super::fitted::{Family, Fitted};
use super::grid::Grid;
use crate::model::{self, Event, ModelConfig};
use driftwatch_core::least_squares::least_squares;

/// Most inputs key-temperature regression keeps.
pub const MAX_KEY: usize = 5;

/// The inputs among `inputs` that vary over grid points `0..end`: one constant over the fit
/// data is the intercept again, and the vanishing ridge would split the intercept between
/// them, an arbitrary gain that moves the prediction when the input does.
fn varying(g: &Grid, inputs: &[usize], end: usize) -> Vec<usize> {
    let rows: Vec<usize> = (0..end.min(g.len())).collect();
    varying_on(g, inputs, &rows)
}

/// [`varying`] over the grid points `rows` (those a fit uses): a spindle that stood only
/// while the sensor held its value varies over the grid, but not over the fresh readings,
/// and there it is the intercept again.
pub(super) fn varying_on(g: &Grid, inputs: &[usize], rows: &[usize]) -> Vec<usize> {
    inputs
        .iter()
        .copied()
        .filter(|&j| {
            let x = &g.inputs[j];
            rows.first().is_some_and(|&r0| {
                rows.iter()
                    .any(|&k| (x[k] - x[r0]).abs() > 1e-12 * x[r0].abs().max(1.0))
            })
        })
        .collect()
}

/// The grid points before `end` with a fresh reading: the rows a fit takes.
pub(super) fn fresh_rows(g: &Grid, end: usize) -> Vec<usize> {
    (0..end.min(g.len())).filter(|&k| g.fresh[k]).collect()
}

fn fit_linear(g: &Grid, inputs: &[usize], end: usize) -> Option<Fitted> {
    let rows = fresh_rows(g, end);
    let inputs = &varying_on(g, inputs, &rows);
    let x = DMatrix::from_fn(rows.len(), inputs.len() + 1, |i, j| {
        if j == 0 {
            1.0
        } else {
            g.inputs[inputs[j - 1]][rows[i]]
        }
    });
    let y = DVector::from_iterator(rows.len(), rows.iter().map(|&k| g.y[k]));
    let coef = least_squares(&x, &y).ok()?;
    Some(Fitted::Linear {
        inputs: inputs.to_vec(),
        coef: coef.iter().copied().collect(),
    })
}

fn fit_arx(g: &Grid, na: usize, nb: usize, inputs: &[usize], end: usize) -> Option<Fitted> {
    let inputs = &varying(g, inputs, end);
    let lag = na.max(nb.saturating_sub(1));
    if end <= lag + 1 {
        return None;
    }
    let rows = end - lag;
    let p = na + nb * inputs.len() + 1;
    let x = DMatrix::from_fn(rows, p, |r, c| {
        let k = r + lag;
        if c < na {
            g.y[k - 1 - c]
        } else if c < na + nb * inputs.len() {
            let (j, l) = ((c - na) / nb, (c - na) % nb);
            g.inputs[inputs[j]][k - l]
        } else {
            1.0
        }
    });
    let y = DVector::from_fn(rows, |r, _| g.y[r + lag]);
    let theta = least_squares(&x, &y).ok()?;
    let a: Vec<f64> = theta.iter().take(na).copied().collect();
    // Run freely, the model must be stable: every root of z^na - a1 z^(na-1) - ... inside
    // the unit circle (checked for the orders used here, 1 and 2).
    let stable = match a.as_slice() {
        [a1] => a1.abs() < 1.0,
        // Jury's conditions for z^2 - a1 z - a2.
        [a1, a2] => a2.abs() < 1.0 && (1.0 - a1 - a2) > 0.0 && (1.0 + a1 - a2) > 0.0,
        _ => false,
    };
    stable.then(|| Fitted::Arx {
        na,
        nb,
        inputs: inputs.to_vec(),
        theta: theta.iter().copied().collect(),
    })
}

/// Forward selection of key inputs on `0..end`, by the inner rolling-origin CV of a
/// regression on them: add the input that lowers it most, stop when none lowers it by 1 %.
pub fn key_inputs(g: &Grid, end: usize, horizon: usize) -> Vec<usize> {
    let all: Vec<usize> = (0..g.names.len()).collect();
    forward_select(&all, f64::INFINITY, &|with| {
        cv_errors(g, end, horizon, &|o| fit_linear(g, with, o))
            .map_or(f64::INFINITY, |e| cv_rms(&e))
    })
}

/// Forward selection of at most [`MAX_KEY`] of `candidates`: add the one whose `score`
/// (lower is better; infinite where it cannot be had) is lowest, while it lowers the score
/// by 1 % from `start` (the score of none).
pub(crate) fn forward_select(
    candidates: &[usize],
    start: f64,
    score: &dyn Fn(&[usize]) -> f64,
) -> Vec<usize> {
    let mut chosen: Vec<usize> = Vec::new();
    let mut best = start;
    while chosen.len() < MAX_KEY {
        let step = candidates
            .iter()
            .filter(|j| !chosen.contains(j))
            .map(|&j| {
                let mut with = chosen.clone();
                with.push(j);
                (j, score(&with))
            })
            .filter(|(_, s)| s.is_finite())
            .min_by(|a, b| a.1.total_cmp(&b.1));
        match step {
            Some((j, s)) if s < 0.99 * best => {
                chosen.push(j);
                best = s;
            }
            _ => break,
        }
    }
    chosen
}

/// Fit `family` on grid points `0..end` (its inner choices made there).
pub fn fit_family(family: Family, g: &Grid, end: usize, horizon: usize) -> Option<Fitted> {
    let all: Vec<usize> = (0..g.names.len()).collect();
    match family {
        Family::Persistence => Some(Fitted::Persistence),
        Family::Regression => fit_linear(g, &all, end),
        Family::KeyRegression => {
            let key = key_inputs(g, end, horizon);
            fit_linear(g, &key, end)
        }

        Family::Arx => {
            // Orders and inputs by the inner CV: first or second order, on the key inputs
            // or on every input.
            let key = key_inputs(g, end, horizon);
            let mut best: Option<(Fitted, f64)> = None;
            for inputs in [&key, &all] {
                if inputs.is_empty() {
                    continue;
                }
                for na in [1, 2] {
                    let nb = 2;
                    let Some(e) = cv_errors(g, end, horizon, &|o| fit_arx(g, na, nb, inputs, o))
                    else {
                        continue;
                    };
                    let s = cv_rms(&e);
                    if best.as_ref().is_none_or(|(_, b)| s < *b)
                        && let Some(f) = fit_arx(g, na, nb, inputs, end)
                    {
                        best = Some((f, s));
                    }
                }
            }
            best.map(|(f, _)| f)
        }
        Family::GreyBox => Some(Fitted::GreyBox),
        // Its weights come from the competition's CV: see `choose`.
        Family::Combination => None,
    }
}

/// The grey box's configuration for a grid's inputs: the spindle basis when the spindle
/// turned, and every temperature with the default lags.
pub fn grey_box_config(g: &Grid) -> ModelConfig {
    let spins = g.names.iter().any(|n| n == "spindle_rpm");
    let n_ref = g
        .names
        .iter()
        .position(|n| n == "spindle_rpm")
        .and_then(|j| g.inputs[j].iter().map(|v| v.abs()).reduce(f64::max))
        .filter(|m| *m > 0.0)
        .unwrap_or(1.0);
    let base = ModelConfig::default();
    ModelConfig {
        taus_min: if spins {
            base.taus_min.clone()
        } else {
            Vec::new()
        },
        n_ref_rpm: n_ref,
        temperatures: g
            .names
            .iter()
            .filter(|n| n.as_str() != "spindle_rpm")
            .map(|s| model::TemperatureInput {
                sensor: s.clone(),
                taus_min: model::default_temperature_taus(),
            })
            .collect(),
        ..base
    }
}

/// The grey box's free-run predictions for grid points `origin..stop`: fitted on the events
/// before the origin, replayed with no correction after it, the value `predict` serves.
pub fn grey_box(
    events: &[Event],
    cfg: &ModelConfig,
    g: &Grid,
    origin: usize,
    stop: usize,
) -> Option<Vec<f64>> {
    let t0 = *g.t_ns.get(origin)?;
    let t1 = *g.t_ns.get(stop.checked_sub(1)?)?;
    let until: Vec<Event> = events
        .iter()
        .filter(|e| e.t_ns() <= t1)
        .filter(|e| !matches!(e, Event::Observation { channel, .. } if *channel != g.channel))
        .cloned()
        .collect();
    let model = model::fit(cfg, &until, Some(t0 - 1)).ok()?;
    let step = g.t_ns.get(1).map_or(1, |t1| t1 - g.t_ns[0]);
    let (steps, _, _) = model::replay(&model, &until, step, t0 - 1, t0);
    // Replay steps run from the first event; take the step at or just before each grid time.
    let mut out = Vec::with_capacity(stop - origin);
    let mut s = 0;
    for &t in &g.t_ns[origin..stop] {
        while s + 1 < steps.len() && steps[s + 1].t_ns <= t {
            s += 1;
        }
        let v = steps
            .get(s)
            .and_then(|st| st.predictions.iter().find(|p| p.channel == g.channel))
            .map(|p| p.value)?;
        out.push(v);
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::families::fitted::simulate;
    use driftwatch_core::units;

    const MIN: i64 = units::NS_PER_MIN;

    /// A spindle that stood only while the sensor held its value: over the fresh readings
    /// least squares fits on, it never moved, and it gets no gain (before, it took an
    /// arbitrary share of the intercept, and a later speed doubled that into the prediction).
    #[test]
    fn an_input_that_moved_only_between_fresh_readings_gets_no_gain() {
        let n = 40;
        let temp: Vec<f64> = (0..n).map(|k| 20.0 + 0.1 * k as f64).collect();
        let stood = |k: usize| (15..25).contains(&k);
        let g = Grid {
            channel: "d".into(),
            t_ns: (0..n as i64).map(|k| k * MIN).collect(),
            y: temp.iter().map(|t| 5.0 + 2.0 * (t - 20.0)).collect(),
            names: vec!["t".into(), "spindle_rpm".into()],
            inputs: vec![
                temp.clone(),
                (0..n)
                    .map(|k| if stood(k) { 0.0 } else { 1000.0 })
                    .collect(),
            ],
            fresh: (0..n).map(|k| !stood(k)).collect(),
        };
        let f = fit_family(Family::Regression, &g, n, 10).unwrap();
        let Fitted::Linear { inputs, coef } = &f else {
            panic!("{f:?}")
        };
        assert_eq!(inputs, &vec![0], "{f:?}");
        assert!((coef[1] - 2.0).abs() < 1e-6, "{f:?}");
        // At twice the speed the prediction follows the temperature alone.
        let mut h = g.clone();
        h.inputs[1].iter_mut().for_each(|v| *v = 2000.0);
        let p = simulate(&f, &h, n - 1, n);
        assert!((p[0] - h.y[n - 1]).abs() < 1e-4, "{p:?}");
    }

    #[test]
    fn an_unstable_arx_is_not_run() {
        // A growing series: the one-step fit has a pole outside the unit circle.
        let mut g = Grid {
            channel: "d".into(),
            t_ns: (0..50).collect(),
            y: (0..50).map(|k| 1.1f64.powi(k)).collect(),
            names: vec!["u".into()],
            inputs: vec![vec![0.0; 50]],
            fresh: vec![true; 50],
        };
        g.inputs[0][3] = 1.0;
        assert!(fit_arx(&g, 1, 2, &[0], 50).is_none());
    }
}
