//! What `fit` keeps of a channel ([`ChannelChoice`]): the competition run, the chosen family
//! fitted on the whole training span, and what it serves from an origin in each regime.

use super::bands::Bands;
use super::choice::{Choice, RANGE_SLACK, RegimeChoice, excursion, input_ranges};
use super::compete::{FamilyScore, compete};
use super::cv::{origin_residual, relax_weight};
use super::fit::fit_family;
use super::fitted::{Family, Fitted, simulate_with};
use super::grid::Grid;
use crate::model::{Event, ModelConfig};
use driftwatch_core::units;

/// What `fit` keeps of a channel's competition: the chosen family fitted on the whole
/// training span, its CV band, and every family's CV figures.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ChannelChoice {
    pub channel: String,
    pub family: String,
    pub fitted: Fitted,
    /// The grid the family was fitted on: step and input names (a recording to predict must
    /// have the same inputs).
    pub step_ns: i64,
    pub inputs: Vec<String>,
    /// Each input's range over the fit data (see [`excursion`]).
    pub ranges: Vec<[f64; 2]>,
    pub band68: f64,
    pub band95: f64,
    /// The band by horizon (absent in model files written before it: the pooled band
    /// serves).
    #[serde(default)]
    pub bands: Option<Bands>,
    /// The relaxation of the residual at the origin (see [`FamilyScore::relax_h`]).
    #[serde(default)]
    pub relax_h: Option<f64>,
    pub scores: Vec<FamilyScore>,
    /// How the family was chosen (absent in model files written before it: there the grey
    /// box takes over where an empirical family leaves its fit range).
    #[serde(default)]
    pub choice: Option<Choice>,
    /// The family that serves beyond the fit data's range, fitted, and its relaxation.
    #[serde(default)]
    pub beyond_fitted: Option<Fitted>,
    #[serde(default)]
    pub beyond_relax_h: Option<f64>,
}

impl ChannelChoice {
    /// The band by horizon, or the pooled band at every horizon in model files written
    /// before bands by horizon.
    pub fn bands_or_pooled(&self) -> Bands {
        self.bands.clone().unwrap_or_else(|| Bands {
            edges: Vec::new(),
            b68: vec![self.band68],
            b95: vec![self.band95],
        })
    }

    /// The 68 % and 95 % half-widths `horizon` grid steps after the last reading used.
    pub fn band_at(&self, horizon: usize) -> (f64, f64) {
        self.bands
            .as_ref()
            .map_or((self.band68, self.band95), |b| b.at(horizon))
    }

    /// Whether serving from `origin` needs the grey box's predictions.
    pub fn needs_grey(&self) -> bool {
        let uses = |f: &str| f == Family::GreyBox.as_str() || f == Family::Combination.as_str();
        match &self.choice {
            None => true,
            Some(c) => {
                uses(&self.family) || c.beyond.as_ref().is_some_and(|b| uses(b.family.as_str()))
            }
        }
    }

    /// The value the regime of excursion `x` serves at hold-out index `i`.
    fn regime_value(
        &self,
        x: f64,
        i: usize,
        inside: &[f64],
        beyond: Option<&Vec<f64>>,
        held: f64,
    ) -> (f64, Served) {
        let beyond_at = beyond.and_then(|p| p.get(i)).copied();
        match self.choice.as_ref().and_then(|c| c.beyond.as_ref()) {
            _ if x <= RANGE_SLACK => (inside[i], Served::Inside(self.family.clone())),
            // No beyond choice (the CV never went beyond): the inside family, said to serve
            // where the CV never tested it (warm-up runs leave the range by design).
            None => (inside[i], Served::BeyondUntested(self.family.clone())),
            Some(b) => match beyond_at {
                Some(v) => (v, Served::Beyond(b.family)),
                // A beyond family that could not be run holds the reading.
                None => (held, Served::Held),
            },
        }
    }

    /// What the channel serves at grid points `origin..end`, from the readings before
    /// `origin` and the inputs as they happen: each point's value and what gave it. `grey`:
    /// the grey box's free run over the same points and `grey_prev` its value at the last
    /// reading (NaN where [`ChannelChoice::needs_grey`] is false). Inside the fit data's
    /// range the inside choice serves, beyond it the beyond choice ([`Choice`]), or the
    /// inside choice, said to be untested there, where the CV folds never left their range;
    /// once a point has left a regime the rest of the run stays out of it (warm-up does not
    /// come back).
    pub fn serve(
        &self,
        g: &Grid,
        origin: usize,
        end: usize,
        grey: &[f64],
        grey_prev: f64,
    ) -> Vec<(f64, Served)> {
        let end = end.min(g.len());
        if origin == 0 || origin >= end {
            return Vec::new();
        }
        let run = |f: &Fitted, relax_h: Option<f64>| -> Vec<f64> {
            let mut p = simulate_with(f, g, origin, end, grey);
            let r0 = origin_residual(f, g, origin, grey_prev);
            for (h, v) in p.iter_mut().enumerate() {
                *v += r0 * relax_weight(relax_h, h, self.step_ns);
            }
            p
        };
        let inside = run(&self.fitted, self.relax_h);
        let beyond = self
            .beyond_fitted
            .as_ref()
            .map(|f| run(f, self.beyond_relax_h));
        let held = g.y[origin - 1];
        let mut x = 0.0f64;
        (origin..end)
            .enumerate()
            .map(|(i, k)| {
                x = x.max(excursion(g, &self.ranges, k));
                // An input constant over the fit data has moved: no family learnt what it
                // does (a spindle that never stopped teaches nothing of a stop). The regime's
                // family goes on serving, said to be untested there: handing over to the grey
                // box's pole basis (which models a stop) lost to least squares on the lathe's
                // warm-up runs where it happened (docs/physics.md 2.5).
                match &self.choice {
                    // A model file from before the regimes: the grey box beyond the range.
                    None if x > RANGE_SLACK => (
                        grey.get(i).copied().unwrap_or(held),
                        Served::Beyond(Family::GreyBox),
                    ),
                    None => (inside[i], Served::Inside(self.family.clone())),
                    Some(_) => {
                        let (v, s) = self.regime_value(x, i, &inside, beyond.as_ref(), held);
                        if x.is_infinite() {
                            let s = match s {
                                Served::BeyondUntested(f) => Served::Inside(f),
                                s => s,
                            };
                            (v, Served::Untested(Box::new(s)))
                        } else {
                            (v, s)
                        }
                    }
                }
            })
            .collect()
    }
}

/// The sources of a served run in words: the first, then each change with its time (h
/// after the run's first grid point).
pub fn describe_served(served: &[(f64, Served)], g: &Grid, origin: usize) -> String {
    let mut out: Vec<String> = Vec::new();
    let mut last: Option<&Served> = None;
    for (i, (_, s)) in served.iter().enumerate() {
        if last != Some(s) {
            let h = units::ns_to_h(g.t_ns[origin + i] - g.t_ns[0]);
            out.push(if last.is_none() {
                s.to_string()
            } else {
                format!("{s} from {h:.2} h")
            });
            last = Some(s);
        }
    }
    out.join(", then ")
}

/// What gave a served value.
#[derive(Debug, Clone, PartialEq)]
pub enum Served {
    /// The inside choice (the channel's family), inputs within the fit data's range.
    Inside(String),
    /// The beyond choice, some input beyond the fit data's range.
    Beyond(Family),
    /// The inside choice beyond the fit data's range, where the CV folds never went (no
    /// beyond choice could be made).
    BeyondUntested(String),
    /// What the regime serves, where an input constant over the fit data has moved.
    Untested(Box<Served>),
    /// The last reading held: the family for the regime could not be run.
    Held,
}

impl std::fmt::Display for Served {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Served::Inside(family) => write!(f, "{family}"),
            Served::Beyond(family) => write!(f, "{} (beyond the fit range)", family.as_str()),
            Served::BeyondUntested(family) => write!(
                f,
                "{family} (beyond the fit range, further than the CV folds went: untested)"
            ),
            Served::Untested(s) => write!(
                f,
                "{s} (untested: an input constant over the fit data moved)"
            ),
            Served::Held => write!(
                f,
                "last reading held (the family for the regime could not be run)"
            ),
        }
    }
}

/// A scored family fitted on grid points `0..end` (a combination with its CV weights), its
/// inner choices made by CV at `horizon`.
pub fn fit_scored(score: &FamilyScore, g: &Grid, end: usize, horizon: usize) -> Option<Fitted> {
    match Family::parse(&score.family)? {
        Family::Combination => {
            let mut parts = Vec::new();
            for (name, w) in &score.weights {
                parts.push((fit_family(Family::parse(name)?, g, end, horizon)?, *w));
            }
            Some(Fitted::Combination { parts })
        }
        family => fit_family(family, g, end, horizon),
    }
}

/// Run the competition on the training span (`train_end_ns`: all of the grid when it lies
/// beyond it) for a model used `horizon` grid steps ahead, and keep the chosen family, or
/// `force` it. `None` when nothing could be fitted.
pub fn choose(
    events: &[Event],
    g: &Grid,
    train_end_ns: i64,
    families: &[Family],
    grey: &ModelConfig,
    force: Option<Family>,
    horizon: usize,
) -> Option<ChannelChoice> {
    let (scores, mut choice) = compete(events, g, train_end_ns, families, grey, horizon);
    let pick = match force {
        Some(f) => {
            // A forced family serves in every regime.
            choice.why = format!(
                "{} forced (the CV would serve {})",
                f.as_str(),
                choice.family.as_str()
            );
            choice.family = f;
            choice.inside.family = f;
            choice.beyond = Some(RegimeChoice {
                family: f,
                ..choice.inside.clone()
            });
            choice.tested_excursion = f64::INFINITY;
            scores.iter().find(|s| s.family == f.as_str())?
        }
        None => scores.iter().find(|s| s.chosen)?,
    };
    let n_train = g.index_at(train_end_ns);
    let fitted = fit_scored(pick, g, n_train, horizon)?;
    let ranges = input_ranges(g, n_train);
    let beyond = choice
        .beyond
        .as_ref()
        .and_then(|b| scores.iter().find(|s| s.family == b.family.as_str()));
    let beyond_fitted = beyond.and_then(|s| fit_scored(s, g, n_train, horizon));
    Some(ChannelChoice {
        channel: g.channel.clone(),
        family: pick.family.clone(),
        fitted,
        step_ns: g.t_ns.get(1).map_or(1, |t| t - g.t_ns[0]),
        inputs: g.names.clone(),
        ranges,
        band68: pick.band68,
        band95: pick.band95,
        bands: pick.bands.clone(),
        relax_h: pick.relax_h,
        beyond_relax_h: beyond.and_then(|s| s.relax_h),
        scores,
        choice: Some(choice),
        beyond_fitted,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::families::grey_box_config;
    use driftwatch_core::units;

    const MIN: i64 = units::NS_PER_MIN;

    /// An input that leaves the fit data's range further than any CV fold went: the inside
    /// family goes on serving, and says it is untested there.
    #[test]
    fn beyond_what_the_cv_tested_the_served_value_says_untested() {
        let n = 300;
        let u: Vec<f64> = (0..n)
            .map(|k| {
                if k < 200 {
                    (k as f64 / 10.0).sin()
                } else {
                    1.0 + 0.05 * (k - 200) as f64
                }
            })
            .collect();
        let g = Grid {
            channel: "d".into(),
            t_ns: (0..n as i64).map(|k| k * MIN).collect(),
            y: u.iter().map(|v| 2.0 * v).collect(),
            names: vec!["u".into()],
            inputs: vec![u.clone()],
            fresh: vec![true; n],
        };
        let ev: Vec<Event> = Vec::new();
        let fams = [Family::Persistence, Family::Regression];
        let c = choose(&ev, &g, 200 * MIN, &fams, &grey_box_config(&g), None, 100).unwrap();
        assert!(
            c.choice.as_ref().unwrap().beyond.is_none(),
            "{:?}",
            c.choice
        );
        let served = c.serve(&g, 200, n, &[f64::NAN; 100], f64::NAN);
        // The range is [-1, 1]: past u = 2 (k = 220) the excursion exceeds half of it.
        assert!(matches!(served[5].1, Served::Inside(_)), "{:?}", served[5]);
        assert!(
            matches!(served[40].1, Served::BeyondUntested(_)),
            "{:?}",
            served[40]
        );
        assert!(
            (served[40].0 - 2.0 * u[240]).abs() < 1e-6,
            "{:?}",
            served[40]
        );
        let text = describe_served(&served, &g, 200);
        assert!(text.contains("further than the CV folds went"), "{text}");
    }
}
