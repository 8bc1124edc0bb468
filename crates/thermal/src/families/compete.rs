//! The competition on one channel: each family's CV errors and hold-out predictions (the grey
//! box's from the events), the inverse-MSE combination, each family's scores, and the sign
//! test a challenger must pass.

use super::bands::{Bands, cv_coverage, quantile_abs};
use super::choice::{Choice, fold_excursions, independent_folds};
use super::cv::{
    CvError, Run, cv_rms, cv_run, fold_errors, folds, null_as_nan, origin_residual, rms,
    tested_horizon,
};
use super::fit::{fit_family, fresh_rows, grey_box, varying_on};
use super::fitted::{Family, Fitted, simulate};
use super::grid::Grid;
use crate::model::{Event, ModelConfig};

/// One family's figures on one channel.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FamilyScore {
    pub family: String,
    /// What the fit on the whole training span chose (inputs, orders).
    pub detail: String,
    /// Rolling-origin CV on the training span, RMSE.
    pub cv_rmse: f64,
    /// The 68 % and 95 % quantiles of the CV errors' size, all horizons pooled.
    pub band68: f64,
    pub band95: f64,
    /// The band by horizon the family claims (absent in model files written before it).
    #[serde(default)]
    pub bands: Option<Bands>,
    /// The bands' coverage on the CV folds, each fold against the others' bands.
    #[serde(default)]
    pub cv_cover68: Option<f64>,
    #[serde(default)]
    pub cv_cover95: Option<f64>,
    /// Hold-out (after the training span, no reading used): RMSE, largest error, and the
    /// shares within the 68 % and 95 % bands at their horizons.
    /// NaN where there is no hold-out: JSON writes it as null, and null reads back as NaN.
    #[serde(deserialize_with = "null_as_nan")]
    pub holdout_rmse: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub holdout_max: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub cover68: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub cover95: f64,
    pub chosen: bool,
    /// A combination's parts and weights.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub weights: Vec<(String, f64)>,
    /// The relaxation time the CV chose, h: the residual at the origin (the last reading
    /// less the model there) decays with it into the prediction. None: the model's mean
    /// alone.
    #[serde(default)]
    pub relax_h: Option<f64>,
}

/// The grey box's CV errors and hold-out predictions; `None` when a fold cannot be fitted.
fn grey_box_run(
    events: &[Event],
    cfg: &ModelConfig,
    g: &Grid,
    n_train: usize,
    horizon: usize,
) -> Option<GreyRun> {
    // Each run starts a step early: its first value, at the last reading before the origin,
    // gives the residual there.
    let mut e = Vec::new();
    let mut r0 = Vec::new();
    for (i, (o, stop)) in folds(n_train, horizon).into_iter().enumerate() {
        let p = grey_box(events, cfg, g, o - 1, stop)?;
        r0.push(g.y[o - 1] - p[0]);
        e.extend(fold_errors(i, &p[1..], &g.y[o..stop], &g.fresh[o..stop]));
    }
    if e.is_empty() {
        return None;
    }
    // No hold-out when the training span is the whole grid.
    let (hold, hold_r0) = if n_train < g.len() {
        let p = grey_box(events, cfg, g, n_train - 1, g.len())?;
        (p[1..].to_vec(), g.y[n_train - 1] - p[0])
    } else {
        (Vec::new(), 0.0)
    };
    Some(GreyRun {
        cv: e,
        hold,
        r0,
        hold_r0,
    })
}

/// The grey box's CV errors, hold-out predictions, and residuals at the origins.
struct GreyRun {
    cv: Vec<CvError>,
    hold: Vec<f64>,
    r0: Vec<f64>,
    hold_r0: f64,
}

/// The inverse-MSE combination of every run but persistence (at least two, with the same
/// folds and hold-out).
fn combine(runs: &[Run]) -> Option<Run> {
    let parts: Vec<&Run> = runs
        .iter()
        .filter(|r| r.family != Family::Persistence)
        .collect();
    let first = parts.first()?;
    if parts.len() < 2
        || parts
            .iter()
            .any(|r| r.cv.len() != first.cv.len() || r.hold.len() != first.hold.len())
    {
        return None;
    }
    let inv: Vec<f64> = parts
        .iter()
        .map(|r| 1.0 / cv_rms(&r.cv).powi(2).max(1e-12))
        .collect();
    let total: f64 = inv.iter().sum();
    let w: Vec<f64> = inv.iter().map(|v| v / total).collect();
    let mut cv = first.cv.clone();
    for (i, c) in cv.iter_mut().enumerate() {
        c.e = parts.iter().zip(&w).map(|(r, w)| w * r.cv[i].e).sum();
    }
    let hold = (0..first.hold.len())
        .map(|i| parts.iter().zip(&w).map(|(r, w)| w * r.hold[i]).sum())
        .collect();
    // Its prediction is the weighted sum, so is its residual at each origin.
    let r0 = (0..first.r0.len())
        .map(|i| {
            parts
                .iter()
                .zip(&w)
                .map(|(r, w)| w * r.r0.get(i).copied().unwrap_or(0.0))
                .sum()
        })
        .collect();
    let hold_r0 = parts.iter().zip(&w).map(|(r, w)| w * r.hold_r0).sum();
    let weights: Vec<(String, f64)> = parts
        .iter()
        .zip(&w)
        .map(|(r, w)| (r.family.as_str().to_string(), *w))
        .collect();
    Some(Run {
        family: Family::Combination,
        detail: weights
            .iter()
            .map(|(f, w)| format!("{w:.2} {f}"))
            .collect::<Vec<_>>()
            .join(" + "),
        cv,
        hold,
        weights,
        r0,
        hold_r0,
    })
}

fn score(r: Run, g: &Grid, n_train: usize) -> FamilyScore {
    let step_ns = g.t_ns.get(1).map_or(1, |t| t - g.t_ns[0]);
    let he: Vec<(usize, f64)> = r
        .hold
        .iter()
        .zip(&g.y[n_train..])
        .enumerate()
        .filter(|(h, _)| g.fresh[n_train + h])
        .map(|(h, (p, y))| (h, p - y))
        .collect();
    let bands = Bands::from_errors(&r.cv, step_ns);
    let (cover68, cover95) = bands.coverage(&he);
    let (cv68, cv95) = cv_coverage(&r.cv, step_ns);
    let pooled: Vec<f64> = r.cv.iter().map(|c| c.e).collect();
    let hold_e: Vec<f64> = he.iter().map(|x| x.1).collect();
    FamilyScore {
        family: r.family.as_str().to_string(),
        detail: r.detail,
        cv_rmse: rms(&pooled),
        band68: quantile_abs(&pooled, 0.68),
        band95: quantile_abs(&pooled, 0.95),
        bands: Some(bands),
        cv_cover68: Some(cv68),
        cv_cover95: Some(cv95),
        holdout_rmse: if he.is_empty() {
            f64::NAN
        } else {
            rms(&hold_e)
        },
        holdout_max: if he.is_empty() {
            f64::NAN
        } else {
            hold_e.iter().fold(0.0, |m: f64, e| m.max(e.abs()))
        },
        cover68,
        cover95,
        chosen: false,
        weights: r.weights,
        relax_h: None,
    }
}

/// Every family on one channel: CV on grid points before `train_end_ns` at `horizon` grid
/// steps (the horizon the model is used for), hold-out on the rest. The choice is [`Choice`].
pub fn compete(
    events: &[Event],
    g: &Grid,
    train_end_ns: i64,
    families: &[Family],
    grey: &ModelConfig,
    horizon: usize,
) -> (Vec<FamilyScore>, Choice) {
    let n_train = g.index_at(train_end_ns);
    let n = g.len();
    let mut runs = Vec::new();
    for &family in families {
        let run = match family {
            Family::Combination => continue,
            Family::GreyBox => grey_box_run(events, grey, g, n_train, horizon).map(|r| Run {
                family,
                detail: Fitted::GreyBox.describe(g),
                cv: r.cv,
                hold: r.hold,
                weights: Vec::new(),
                r0: r.r0,
                hold_r0: r.hold_r0,
            }),
            _ => cv_run(g, n_train, horizon, &|o| fit_family(family, g, o, horizon)).and_then(
                |(cv, r0)| {
                    let f = fit_family(family, g, n_train, horizon)?;
                    Some(Run {
                        family,
                        detail: f.describe(g),
                        cv,
                        hold: simulate(&f, g, n_train, n),
                        weights: Vec::new(),
                        r0,
                        hold_r0: origin_residual(&f, g, n_train, f64::NAN),
                    })
                },
            ),
        };
        runs.extend(run);
    }
    if families.contains(&Family::Combination)
        && let Some(c) = combine(&runs)
    {
        runs.push(c);
    }
    // The combination as served: with the relaxation its CV prefers. The textbook baselines
    // stay as the textbook has them; the grey box has its own offset walk, learned from the
    // data by its filter.
    let step_ns = g.t_ns.get(1).map_or(1, |t| t - g.t_ns[0]);
    let runs: Vec<(Run, Option<f64>)> = runs
        .into_iter()
        .map(|r| {
            if r.family == Family::Combination {
                r.relaxed(step_ns)
            } else {
                (r, None)
            }
        })
        .collect();
    let excursions = fold_excursions(g, n_train, horizon);
    let independent = independent_folds(&folds(n_train, horizon));
    let all: Vec<usize> = (0..g.names.len()).collect();
    let choice = Choice::of(
        &runs,
        &excursions,
        &independent,
        (tested_horizon(n_train, horizon), horizon),
        !varying_on(g, &all, &fresh_rows(g, n_train)).is_empty(),
    );
    let out = runs
        .into_iter()
        .map(|(r, relax_h)| {
            let chosen = r.family == choice.family;
            let mut s = score(r, g, n_train);
            s.relax_h = relax_h;
            s.chosen = chosen;
            if let Some(h) = relax_h {
                s.detail
                    .push_str(&format!("; the residual at the origin relaxes over {h} h"));
            }
            s
        })
        .collect();
    (out, choice)
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::units;

    const MIN: i64 = units::NS_PER_MIN;

    #[test]
    fn a_score_without_a_hold_out_round_trips_through_json() {
        let score = FamilyScore {
            family: "grey_box".into(),
            detail: String::new(),
            cv_rmse: 1.0,
            band68: 1.0,
            band95: 2.0,
            bands: None,
            cv_cover68: None,
            cv_cover95: None,
            holdout_rmse: f64::NAN,
            holdout_max: f64::NAN,
            cover68: f64::NAN,
            cover95: f64::NAN,
            chosen: true,
            weights: Vec::new(),
            relax_h: None,
        };
        let text = serde_json::to_string(&score).unwrap();
        assert!(text.contains("\"holdout_rmse\":null"), "{text}");
        let back: FamilyScore = serde_json::from_str(&text).unwrap();
        assert!(back.holdout_rmse.is_nan() && back.cover95.is_nan());
        assert_eq!(back.cv_rmse, 1.0);
    }

    /// Two runs with opposite errors: the inverse-MSE combination has the smaller CV error,
    /// weights that sum to one, and leaves persistence out.
    #[test]
    fn the_combination_weighs_by_cv_error_and_leaves_persistence_out() {
        let cv = |scale: f64| -> Vec<CvError> {
            (0..40)
                .map(|h| CvError {
                    fold: h / 20,
                    horizon: h % 20,
                    e: scale * if h % 2 == 0 { 1.0 } else { -1.0 },
                })
                .collect()
        };
        let run = |family, scale: f64| Run {
            family,
            detail: String::new(),
            cv: cv(scale),
            hold: vec![scale; 5],
            weights: Vec::new(),
            r0: vec![scale, scale],
            hold_r0: scale,
        };
        let runs = vec![
            run(Family::Persistence, 0.1),
            run(Family::Regression, 1.0),
            run(Family::Arx, -2.0),
        ];
        let c = combine(&runs).unwrap();
        let w: Vec<f64> = c.weights.iter().map(|x| x.1).collect();
        assert_eq!(c.weights[0].0, "regression");
        assert_eq!(c.weights.len(), 2);
        assert!(
            (w[0] - 0.8).abs() < 1e-12 && (w[1] - 0.2).abs() < 1e-12,
            "{w:?}"
        );
        // 0.8 * 1 + 0.2 * (-2) = 0.4 on every point.
        assert!((cv_rms(&c.cv) - 0.4).abs() < 1e-12);
        assert!(c.hold.iter().all(|h| (h - 0.4).abs() < 1e-12));
        assert!(combine(&runs[..2]).is_none());
    }

    /// A model off by its origin's residual for hours: the CV holds the residual (the longest
    /// relaxation); a residual that says nothing of what follows is not carried at all.
    #[test]
    fn the_cv_chooses_how_long_the_residual_at_the_origin_lasts() {
        let step = 5 * MIN;
        let run = |e: &dyn Fn(usize, usize) -> f64, r0: Vec<f64>| Run {
            family: Family::Combination,
            detail: String::new(),
            cv: (0..2)
                .flat_map(|fold| (0..100).map(move |horizon| (fold, horizon)))
                .map(|(fold, horizon)| CvError {
                    fold,
                    horizon,
                    e: e(fold, horizon),
                })
                .collect(),
            hold: vec![0.0; 3],
            weights: Vec::new(),
            r0,
            hold_r0: 1.0,
        };
        // The model is 2 um low (fold 0) or 1 um high (fold 1) throughout, and the last
        // reading said so.
        let (held, tau) =
            run(&|f, _| if f == 0 { -2.0 } else { 1.0 }, vec![2.0, -1.0]).relaxed(step);
        assert_eq!(tau, Some(64.0));
        assert!(cv_rms(&held.cv) < 0.2, "{:?}", &held.cv[..3]);
        assert!(held.hold.iter().all(|p| (p - 1.0).abs() < 0.01));
        // Errors that alternate whatever the residual was.
        let (plain, tau) =
            run(&|_, h| if h % 2 == 0 { 1.0 } else { -1.0 }, vec![3.0, -3.0]).relaxed(step);
        assert_eq!(tau, None);
        assert_eq!(plain.hold, vec![0.0; 3]);
    }
}
