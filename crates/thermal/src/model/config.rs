//! The model's configuration (inputs and their lags, the fit's and the guard's settings, the
//! shipped default) and the errors of a configuration, a fit or a model file.

use serde::{Deserialize, Serialize};
use thiserror::Error;

#[derive(Debug, Error, PartialEq)]
pub enum ModelError {
    #[error("model configuration: {0}")]
    Config(String),
    #[error("channel {channel}: {message}")]
    Channel { channel: String, message: String },
    #[error("no observations to fit{0}")]
    NoData(String),
}

/// A temperature input and its lags.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct TemperatureInput {
    pub sensor: String,
    /// Time constants, min; 0 is the temperature itself without lag.
    #[serde(default = "default_temperature_taus")]
    pub taus_min: Vec<f64>,
}

/// What an accepted diagnosis term adds to the thermal model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ModelInput {
    SpindleLag {
        tau_min: f64,
    },
    Temperature {
        sensor: String,
        taus_min: Vec<f64>,
    },
    InstantSpeed,
    /// Nothing the thermal model can carry (a clock term, or a measurement-model effect).
    None,
}

/// The default lags of a temperature input, min: the temperature itself, 1 h and 4 h.
pub fn default_temperature_taus() -> Vec<f64> {
    vec![0.0, 60.0, 240.0]
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelConfig {
    /// Pole basis of the spindle heat input, min.
    pub taus_min: Vec<f64>,
    /// Reference speed of the heat input, min^-1.
    pub n_ref_rpm: f64,
    /// Exponent of the heat input.
    pub gamma: f64,
    pub temperatures: Vec<TemperatureInput>,
    /// An instantaneous speed term `c (n / n_ref)^2` (centrifugal and bearing-contact shift).
    pub instant_speed: bool,
    /// Ridge factors tried by blocked cross-validation (times each column's mean square);
    /// the smallest held-out error wins, 0 unless a larger one does better.
    pub ridge_grid: Vec<f64>,
    /// Random walk of a channel's offset between observations, in the channel's own unit
    /// squared per hour (um^2/h, urad^2/h): how fast its prediction loses credit without a
    /// measurement. Used for a channel with too few observations to learn its own walk
    /// (the name `offset_walk_um2_per_h` of earlier model files is read as this).
    #[serde(alias = "offset_walk_um2_per_h")]
    pub offset_walk_per_h: f64,
    /// Candidate walks, the channel's unit squared per hour: each channel takes the one under
    /// which its own observations, each predicted before it corrects the filter, are the
    /// likeliest (empty: every channel keeps `offset_walk_per_h`).
    pub offset_walk_grid_per_h: Vec<f64>,
    /// Share of each channel's observations, the latest, held out at every fit: the model
    /// fitted on the rest predicts them one by one (corrected by each after it is scored) and
    /// is scored against the last measured value and against no change.
    pub holdout_share: f64,
    /// Scored observations (held out at the fit, then every new one before it corrects the
    /// filter) a channel needs before its served value may fall back from the model to the
    /// last measured value or to no change, and before its band is scaled.
    pub min_scored: usize,
    /// Prior standard deviation of every gain (um per unit input): what the data must
    /// overrule. Thermal errors of tens of um make 100 um a weak but physical bound.
    pub prior_gain_sd: f64,
    /// Hours without an observation that end a run (the machine stood, e.g. overnight):
    /// the least squares the model must beat takes an offset per run (the inputs as changes
    /// within each run), as a thermal test zeroed at each start is read.
    pub run_gap_h: f64,
    /// When the model is served as its change since the last observation added to that
    /// observation, instead of the filter's own value ([`Anchoring`]; the `anchored = true`
    /// or `false` of earlier files reads as always or never).
    #[serde(alias = "anchored", deserialize_with = "anchoring_or_bool")]
    pub anchoring: Anchoring,
}

/// Whether a channel's model is served anchored at its last observation: its change since
/// that observation added to it. The filter weighs each observation against the model's
/// scatter as if that scatter were new at every instant, while a model's error on a real
/// machine persists from one hour to the next; but an anchor also carries the observation's
/// own noise into every value until the next one. Only for as long as the last measured
/// value may be held: it was judged at the gaps scored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Anchoring {
    /// The filter's own value.
    Never,
    /// Anchored where the anchored value beat the filter's own on the channel's scored
    /// observations beyond chance (the guard's `anchors`): on real thermal tests with precise
    /// readings it does, on small orientation errors that barely move it does not.
    #[default]
    HeldOut,
    /// Always anchored.
    Always,
}

/// An [`Anchoring`] by name, or the boolean of earlier files (true: always, false: never).
fn anchoring_or_bool<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Anchoring, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Repr {
        Bool(bool),
        Name(Anchoring),
    }
    Ok(match Repr::deserialize(d)? {
        Repr::Bool(true) => Anchoring::Always,
        Repr::Bool(false) => Anchoring::Never,
        Repr::Name(a) => a,
    })
}

impl Default for ModelConfig {
    fn default() -> Self {
        ModelConfig {
            taus_min: vec![6.0, 15.0, 40.0, 100.0, 250.0, 600.0],
            n_ref_rpm: 20000.0,
            gamma: 1.5,
            temperatures: Vec::new(),
            instant_speed: false,
            ridge_grid: vec![0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0],
            offset_walk_per_h: 1.0,
            offset_walk_grid_per_h: vec![0.0, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0],
            holdout_share: 0.3,
            min_scored: 4,
            prior_gain_sd: 100.0,
            run_gap_h: 8.0,
            anchoring: Anchoring::HeldOut,
        }
    }
}

/// The shipped default (`config/thermal.toml`).
pub const DEFAULT_MODEL_CONFIG: &str = include_str!("../../../../config/thermal.toml");

impl ModelConfig {
    /// Parse and check a model configuration TOML.
    pub fn from_toml(text: &str) -> Result<Self, ModelError> {
        let c: ModelConfig = toml::from_str(text).map_err(|e| ModelError::Config(e.to_string()))?;
        c.validate()?;
        Ok(c)
    }

    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |m: String| Err(ModelError::Config(m));
        if self
            .taus_min
            .iter()
            .any(|t| !driftwatch_core::units::positive(*t))
        {
            return bad(format!("spindle taus_min must be > 0: {:?}", self.taus_min));
        }
        if !driftwatch_core::units::positive(self.n_ref_rpm)
            || !driftwatch_core::units::positive(self.gamma)
        {
            return bad("n_ref_rpm and gamma must be > 0".into());
        }
        for t in &self.temperatures {
            if t.taus_min.is_empty()
                || t.taus_min
                    .iter()
                    .any(|x| !driftwatch_core::units::non_negative(*x))
            {
                return bad(format!("sensor {}: taus_min must be >= 0", t.sensor));
            }
        }
        if self.ridge_grid.is_empty()
            || self
                .ridge_grid
                .iter()
                .any(|x| !driftwatch_core::units::non_negative(*x))
        {
            return bad("ridge_grid needs values >= 0".into());
        }
        if !driftwatch_core::units::positive(self.prior_gain_sd) {
            return bad("prior_gain_sd must be > 0".into());
        }
        if !driftwatch_core::units::non_negative(self.offset_walk_per_h)
            || self
                .offset_walk_grid_per_h
                .iter()
                .any(|x| !driftwatch_core::units::non_negative(*x))
        {
            return bad("offset_walk_per_h and offset_walk_grid_per_h must be >= 0".into());
        }
        if !(0.0..0.9).contains(&self.holdout_share) {
            return bad(format!(
                "holdout_share must be in [0, 0.9), not {}",
                self.holdout_share
            ));
        }
        if self.min_scored == 0 {
            return bad("min_scored must be at least 1".into());
        }
        if !driftwatch_core::units::positive(self.run_gap_h) {
            return bad(format!("run_gap_h must be > 0, not {}", self.run_gap_h));
        }
        Ok(())
    }

    /// This configuration with what accepted diagnosis terms add (time constants and
    /// lags kept sorted and unique).
    pub fn with_inputs(&self, inputs: &[ModelInput]) -> ModelConfig {
        let mut m = self.clone();
        for i in inputs {
            match i {
                ModelInput::SpindleLag { tau_min } => m.taus_min.push(*tau_min),
                ModelInput::Temperature { sensor, taus_min } => {
                    match m.temperatures.iter_mut().find(|t| &t.sensor == sensor) {
                        Some(t) => t.taus_min.extend(taus_min),
                        None => m.temperatures.push(TemperatureInput {
                            sensor: sensor.clone(),
                            taus_min: taus_min.clone(),
                        }),
                    }
                }
                ModelInput::InstantSpeed => m.instant_speed = true,
                ModelInput::None => {}
            }
        }
        let tidy = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v.dedup();
        };
        tidy(&mut m.taus_min);
        for t in &mut m.temperatures {
            tidy(&mut t.taus_min);
        }
        m
    }

    /// Column names: `offset`, `spindle_lag_<tau>`, `<sensor>_lag_<tau>`, `speed_squared`.
    pub fn columns(&self) -> Vec<String> {
        let mut c = vec!["offset".to_string()];
        c.extend(self.taus_min.iter().map(|t| format!("spindle_lag_{t}min")));
        for s in &self.temperatures {
            c.extend(
                s.taus_min
                    .iter()
                    .map(|t| format!("{}_lag_{t}min", s.sensor)),
            );
        }
        if self.instant_speed {
            c.push("speed_squared".into());
        }
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The boolean of earlier model files and configurations reads as always or never.
    #[test]
    fn anchoring_reads_by_name_and_as_the_boolean_of_earlier_files() {
        let read = |text: &str| serde_json::from_str::<ModelConfig>(text).unwrap().anchoring;
        assert_eq!(read(r#"{"anchored": true}"#), Anchoring::Always);
        assert_eq!(read(r#"{"anchored": false}"#), Anchoring::Never);
        assert_eq!(read(r#"{"anchoring": "never"}"#), Anchoring::Never);
        assert_eq!(read("{}"), Anchoring::HeldOut);
        assert!(serde_json::from_str::<ModelConfig>(r#"{"anchoring": "sometimes"}"#).is_err());
    }

    #[test]
    fn the_shipped_configuration_is_the_default() {
        let c = ModelConfig::from_toml(DEFAULT_MODEL_CONFIG).unwrap();
        assert_eq!(c, ModelConfig::default());
        let with = format!("{DEFAULT_MODEL_CONFIG}\n[[temperatures]]\nsensor = \"ambient\"\n");
        let c = ModelConfig::from_toml(&with).unwrap();
        assert_eq!(c.temperatures[0].taus_min, [0.0, 60.0, 240.0]);
        assert!(ModelConfig::from_toml("gamma = -1.0").is_err());
        assert!(ModelConfig::from_toml("tau = 3").is_err());
    }
}
