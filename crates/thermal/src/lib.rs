//! Forecasting between measurement cycles: the thermal model ([`model`]: configuration,
//! features, fit, guard, predictor, replay), the model families that compete with it on a
//! channel's history ([`families`]), and learning across runs ([`across_runs`]).
//!
//! Pure code on the core's units, statistics and least squares: no async runtime, no database,
//! no network, no clock, no globals; deterministic for a given seed. The theory is in
//! docs/physics.md 2.1.

pub mod across_runs;
pub mod families;
pub mod model;
