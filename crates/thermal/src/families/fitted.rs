//! What a fitted family is ([`Family`], [`Fitted`]) and its free-run simulation from an
//! origin.

use super::grid::Grid;

/// The families that compete.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Family {
    /// The last training reading, held.
    Persistence,
    /// Least squares on every input at the same time.
    Regression,
    /// Least squares on the inputs forward selection keeps (at most [`MAX_KEY`](super::MAX_KEY)).
    KeyRegression,
    /// `y_k = sum a_i y_(k-i) + sum b_jl u_j,(k-l) + c`, fitted one step ahead, run freely.
    Arx,
    /// The pole-basis grey box with its filter (`thermal_model`), as `fit` and `predict` run it.
    GreyBox,
    /// The other families but persistence, averaged with weights inversely proportional to
    /// their CV mean square error (Bates and Granger, 1969): a combination of forecasts
    /// often beats the single model a noisy CV picks, and it competes in the same CV.
    Combination,
}

impl Family {
    pub const ALL: [Family; 6] = [
        Family::Persistence,
        Family::Regression,
        Family::KeyRegression,
        Family::Arx,
        Family::GreyBox,
        Family::Combination,
    ];
    pub fn as_str(self) -> &'static str {
        match self {
            Family::Persistence => "persistence",
            Family::Regression => "regression",
            Family::KeyRegression => "key_regression",
            Family::Arx => "arx",
            Family::GreyBox => "grey_box",
            Family::Combination => "combination",
        }
    }
    pub fn parse(s: &str) -> Option<Family> {
        Family::ALL.into_iter().find(|f| f.as_str() == s)
    }
}

/// A fitted family: what it needs to predict forward from an origin.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Fitted {
    Persistence,
    Linear {
        inputs: Vec<usize>,
        /// Intercept first, then one gain per input (on the inputs' own scale).
        coef: Vec<f64>,
    },
    Arx {
        na: usize,
        nb: usize,
        inputs: Vec<usize>,
        /// a_1..a_na, then b_j0..b_j(nb-1) per input, then c.
        theta: Vec<f64>,
    },
    /// The grey box is fitted and run on the events themselves.
    GreyBox,
    /// Each part with its weight (the weights sum to one).
    Combination {
        parts: Vec<(Fitted, f64)>,
    },
}

impl Fitted {
    /// The inputs the fit uses, by name.
    fn input_names(&self, g: &Grid) -> Vec<String> {
        match self {
            Fitted::Linear { inputs, .. } | Fitted::Arx { inputs, .. } => {
                inputs.iter().map(|&j| g.names[j].clone()).collect()
            }
            Fitted::Persistence => Vec::new(),
            Fitted::GreyBox => g.names.clone(),
            Fitted::Combination { .. } => self
                .empirical_inputs()
                .iter()
                .map(|&j| g.names[j].clone())
                .collect(),
        }
    }

    /// The grid inputs an empirical (regression or ARX) part uses: the ones whose range
    /// a combination's description names.
    fn empirical_inputs(&self) -> Vec<usize> {
        let mut out: Vec<usize> = match self {
            Fitted::Linear { inputs, .. } | Fitted::Arx { inputs, .. } => inputs.clone(),
            Fitted::Persistence | Fitted::GreyBox => Vec::new(),
            Fitted::Combination { parts } => parts
                .iter()
                .flat_map(|(f, _)| f.empirical_inputs())
                .collect(),
        };
        out.sort_unstable();
        out.dedup();
        out
    }
    pub fn describe(&self, g: &Grid) -> String {
        match self {
            Fitted::Persistence => "last value held".into(),
            Fitted::Linear { inputs, .. } => {
                format!(
                    "{} inputs: {}",
                    inputs.len(),
                    self.input_names(g).join(", ")
                )
            }
            Fitted::Arx { na, nb, inputs, .. } => format!(
                "na {na}, nb {nb}, {} inputs: {}",
                inputs.len(),
                self.input_names(g).join(", ")
            ),
            Fitted::GreyBox => "pole basis + every temperature".into(),
            Fitted::Combination { parts } => parts
                .iter()
                .map(|(f, w)| format!("{w:.2} x [{}]", f.describe(g)))
                .collect::<Vec<_>>()
                .join(" + "),
        }
    }
}

/// Predictions for grid indices `origin..end`, from readings before `origin` only (and the
/// inputs, which are measured as they happen).
pub fn simulate(f: &Fitted, g: &Grid, origin: usize, end: usize) -> Vec<f64> {
    let end = end.min(g.len());
    if origin == 0 || origin >= end {
        return Vec::new();
    }
    match f {
        Fitted::Persistence => vec![g.y[origin - 1]; end - origin],
        Fitted::Linear { inputs, coef } => {
            let at = |k: usize| {
                coef[0]
                    + inputs
                        .iter()
                        .enumerate()
                        .map(|(i, &j)| coef[i + 1] * g.inputs[j][k])
                        .sum::<f64>()
            };
            (origin..end).map(at).collect()
        }
        Fitted::Arx {
            na,
            nb,
            inputs,
            theta,
        } => {
            // The past outputs: measured before the origin, simulated after it.
            let mut y: Vec<f64> = g.y[..origin].to_vec();
            for k in origin..end {
                let mut v = theta[theta.len() - 1];
                for i in 0..*na {
                    v += theta[i] * y[k - 1 - i];
                }
                for (ji, &j) in inputs.iter().enumerate() {
                    for l in 0..*nb {
                        if k >= l {
                            v += theta[na + ji * nb + l] * g.inputs[j][k - l];
                        }
                    }
                }
                y.push(v);
            }
            y.split_off(origin)
        }
        Fitted::GreyBox | Fitted::Combination { .. } => Vec::new(),
    }
}

/// [`simulate`] with the grey box's own predictions for `origin..end` (`grey`, which only
/// the events can give): the grey box and a combination that holds it run too. Empty when a
/// part cannot run.
pub fn simulate_with(f: &Fitted, g: &Grid, origin: usize, end: usize, grey: &[f64]) -> Vec<f64> {
    match f {
        Fitted::GreyBox => grey.to_vec(),
        Fitted::Combination { parts } => {
            let n = end.min(g.len()).saturating_sub(origin);
            let mut sum = vec![0.0; n];
            for (part, w) in parts {
                let p = simulate_with(part, g, origin, end, grey);
                if p.len() != n {
                    return Vec::new();
                }
                sum.iter_mut().zip(&p).for_each(|(s, p)| *s += w * p);
            }
            sum
        }
        _ => simulate(f, g, origin, end),
    }
}
