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
//! Each part in its own file, re-exported here.

mod config;
mod events;
mod features;
mod fit;
mod fitted;
mod guard;
mod predictor;
mod replay;
mod state;

pub use config::{
    Anchoring, DEFAULT_MODEL_CONFIG, ModelConfig, ModelError, ModelInput, TemperatureInput,
    default_temperature_taus,
};
pub use events::{Event, events_from, sensors_of};
pub use features::Features;
pub use fit::{Obs, fit, fit_rows};
pub use fitted::{ChangeRegression, ChannelFit, MODEL_FORMAT, ThermalModel};
pub use guard::{Guard, GuardSummary, Served, beyond_chance};
pub use predictor::{Prediction, Predictor};
pub use replay::{HoldoutScore, ReplayStep, TruthScore, TruthSeries, replay, truth_scores};

pub use driftwatch_core::units::{
    MAX_PLAUSIBLE_RPM, PLAUSIBLE_CELSIUS, plausible_celsius, plausible_rpm,
};

#[cfg(test)]
mod tests;
