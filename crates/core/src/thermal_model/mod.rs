//! The fitted thermal model (docs/physics.md 2.1): every channel (an apparent location error or a
//! displacement sensor) is
//!
//! `y(t) = offset + sum_j K_j lag(u; tau_j) + sum_s sum_k G_sk lag(T_s - T_s,ref; tau_sk)
//!         + c (n / n_ref)^2`,
//!
//! with `u = (n / n_ref)^gamma` from the whole spindle log (measurement spins included) and a
//! fixed, log-spaced pole basis, so that every parameter enters linearly: the fit has no local
//! minima. Lags advance by exact zero-order-hold steps between events.
//!
//! The batch fit is the posterior of a Gaussian prior (weak, plus ridge where the held-out
//! data prefer it) and the observations; the online [`Predictor`] is a Kalman filter over the
//! same parameters, starting from that posterior, with a random walk on the offset between
//! observations. With no random walk, the filter run over the fit's data from the fit's prior
//! gives the fit's posterior. Pure code.
//!
//! Here: the model file ([`ThermalModel`], [`MODEL_FORMAT`]); each part in its own file,
//! re-exported.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

mod config;
mod events;
mod features;
mod fit;
mod guard;
mod predictor;
mod replay;

pub use config::{
    Anchoring, DEFAULT_MODEL_CONFIG, ModelConfig, ModelError, ModelInput, TemperatureInput,
    default_temperature_taus,
};
pub use events::{Event, events_from, sensors_of};
pub use features::Features;
pub use fit::{ChangeRegression, ChannelFit, Obs, fit, fit_rows};
pub use guard::{Guard, GuardSummary, Served, beyond_chance, channel_unit};
pub use predictor::{Prediction, Predictor};
pub use replay::{HoldoutScore, ReplayStep, TruthScore, TruthSeries, replay, truth_scores};

pub use crate::units::{MAX_PLAUSIBLE_RPM, PLAUSIBLE_CELSIUS, plausible_celsius, plausible_rpm};

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

#[cfg(test)]
mod tests;
