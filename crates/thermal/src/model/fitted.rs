//! The fitted model as `driftwatch fit` writes it ([`ThermalModel`], [`MODEL_FORMAT`]): each
//! channel's posterior and held-out check ([`ChannelFit`]) and the least squares it must beat
//! ([`ChangeRegression`]).

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use super::config::{ModelConfig, ModelError};
use super::guard::Guard;

/// A fitted model: what `driftwatch fit` writes as JSON.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ThermalModel {
    pub format: String,
    pub config: ModelConfig,
    pub columns: Vec<String>,
    /// Temperature reference of each sensor (its first reading in the fit data), deg C.
    pub t_ref_c: BTreeMap<String, f64>,
    /// First and last event time of the fit data, ns.
    pub from_ns: i64,
    pub to_ns: i64,
    pub channels: Vec<ChannelFit>,
}

pub const MODEL_FORMAT: &str = "driftwatch.thermal_model.v1";

impl ThermalModel {
    /// Read a model file written by `driftwatch fit`, checking its format and configuration.
    pub fn from_json(text: &str) -> Result<Self, ModelError> {
        let m: ThermalModel = serde_json::from_str(text)
            .map_err(|e| ModelError::Config(format!("not a driftwatch model: {e}")))?;
        if m.format != MODEL_FORMAT {
            return Err(ModelError::Config(format!(
                "model format '{}', expected '{MODEL_FORMAT}'",
                m.format
            )));
        }
        m.config.validate()?;
        let n = m.config.columns().len();
        if m.columns != m.config.columns()
            || m.channels
                .iter()
                .any(|c| c.coef.len() != n || c.cov.len() != n * n)
        {
            return Err(ModelError::Config(
                "the model's parameters do not match its configuration's columns".into(),
            ));
        }
        Ok(m)
    }
}

/// One channel's fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelFit {
    pub name: String,
    /// Posterior mean of the parameters, in the model's column order.
    pub coef: Vec<f64>,
    /// Posterior covariance, row-major.
    pub cov: Vec<f64>,
    /// Prior precision of each parameter (weak prior plus ridge); the prior mean is zero.
    pub prior_precision: Vec<f64>,
    /// Ridge factor chosen by blocked cross-validation.
    pub ridge: f64,
    /// Model scatter beyond the observations' own uncertainty, um (added in quadrature).
    pub discrepancy_um: f64,
    pub n_obs: usize,
    pub rms_um: f64,
    /// Weighted chi-square per degree of freedom with the discrepancy included (1 when the
    /// discrepancy is positive).
    pub chi2_dof: f64,
    /// Held-out RMS of the chosen ridge factor (blocked cross-validation), um.
    pub cv_rmse_um: f64,
    /// The random walk of the offset learned from this channel's observations, its unit
    /// squared per hour (`None`: too few to learn, the configuration's `offset_walk_per_h`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset_walk_per_h: Option<f64>,
    /// The held-out check of the fit: the model against the last measured value and no
    /// change on the latest observations, and what the served value starts from.
    #[serde(default)]
    pub guard: Guard,
    /// Columns (index, lowest, highest) the prediction holds to the range of the fit data:
    /// the temperature inputs when their gains are not jointly significant.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub held_to_range: Vec<(usize, f64, f64)>,
    /// The textbook least squares the model must beat on the same observations (`None`
    /// with fewer observations than its inputs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub regression: Option<ChangeRegression>,
}

/// Least squares on every input (each one's fastest column: the spindle's shortest lag, each
/// temperature's own), fitted on the changes within each run of observations (an offset per
/// run, [`ModelConfig::run_gap_h`]): the regression a thermal engineer tries first, learned
/// across days as a thermal test zeroed at each start is. It predicts the last observation
/// moved by the inputs' changes since it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChangeRegression {
    /// Columns of the design row and their gains.
    pub columns: Vec<usize>,
    pub gains: Vec<f64>,
}

impl ChangeRegression {
    /// The value at design row `to` of a channel last observed as `last` at row `from`.
    pub fn value(&self, last: f64, from: &[f64], to: &DVector<f64>) -> f64 {
        if from.len() != to.len() {
            return last;
        }
        last + self
            .columns
            .iter()
            .zip(&self.gains)
            .map(|(&j, g)| g * (to[j] - from[j]))
            .sum::<f64>()
    }
}

impl ChannelFit {
    fn n(&self) -> usize {
        self.coef.len()
    }
    pub fn cov_matrix(&self) -> DMatrix<f64> {
        DMatrix::from_row_slice(self.n(), self.n(), &self.cov)
    }
    /// The time constant and gain of each spindle lag (um per unit heat input).
    pub fn spindle_gains(&self, cfg: &ModelConfig) -> Vec<(f64, f64)> {
        cfg.taus_min
            .iter()
            .zip(self.coef.iter().skip(1))
            .map(|(t, k)| (*t, *k))
            .collect()
    }
}
