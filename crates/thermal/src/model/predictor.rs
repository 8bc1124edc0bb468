//! The online model: each channel's Kalman filter over the fit's parameters, run forward in
//! time and corrected by every observation, and served through its guard.

use std::collections::BTreeMap;

use nalgebra::DVector;
use serde::Serialize;

#[cfg(doc)]
use super::config::ModelConfig;
use super::events::Event;
use super::features::Features;
use super::fitted::ThermalModel;
use super::guard::{Guard, GuardSummary, Served};
use super::state::ChannelState;

/// A prediction of one channel: what is served, and the model's own value.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Prediction {
    pub channel: String,
    /// The served value: the model's, or its fallback when the model did worse on the
    /// held-out observations (`source`).
    pub value: f64,
    /// Standard uncertainty of the channel's true value. The model's (parameters, offset
    /// walk since the last observation, model discrepancy) is scaled by the factor learned
    /// from the held-out observations; a fallback's is its held-out error.
    pub sigma: f64,
    pub source: Served,
    /// The model's prediction (the served value when `source` is `model`).
    pub model_value: f64,
    /// No change: the channel's cold value (the model's offset).
    pub no_change_value: f64,
    /// Why a fallback is served.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// The model run forward in time, corrected by every observation (Kalman filter), each
/// channel served from the model or its fallback.
#[derive(Debug, Clone)]
pub struct Predictor {
    pub model: std::sync::Arc<ThermalModel>,
    pub(super) features: Features,
    channels: BTreeMap<String, ChannelState>,
}

impl Predictor {
    /// Start from the fitted posterior at `t0_ns` with the inputs of a cold machine.
    pub fn new(model: &ThermalModel, t0_ns: i64) -> Self {
        let features = Features::new(&model.config, &model.t_ref_c, t0_ns);
        Self::resume(std::sync::Arc::new(model.clone()), features, t0_ns)
    }

    /// Continue from the fitted posterior with lag states already run up to now (the
    /// model's configuration and references must be the ones the states were made with);
    /// `last_obs_ns` is when the fit last saw an observation, where the offset walk starts.
    pub fn resume(
        model: std::sync::Arc<ThermalModel>,
        features: Features,
        last_obs_ns: i64,
    ) -> Self {
        let channels = model
            .channels
            .iter()
            .map(|c| {
                let walk = c
                    .offset_walk_per_h
                    .unwrap_or(model.config.offset_walk_per_h);
                let mut st = ChannelState::of_fit(c, walk / 3600.0, last_obs_ns);
                st.anchoring = model.config.anchoring;
                (c.name.clone(), st)
            })
            .collect();
        Predictor {
            features,
            channels,
            model,
        }
    }

    /// Start from the fit's prior instead (zero mean, its prior precision), with no offset
    /// walk and nothing scored: run over the fit's own data it reproduces the fit (the
    /// batch-online check).
    pub fn from_prior(model: &ThermalModel, t0_ns: i64) -> Self {
        let mut p = Predictor::new(model, t0_ns);
        for c in &model.channels {
            p.channels.insert(
                c.name.clone(),
                ChannelState::prior(&c.prior_precision, c.discrepancy_um.powi(2), 0.0, t0_ns),
            );
        }
        p
    }

    pub fn t_ns(&self) -> i64 {
        self.features.t_ns()
    }

    /// Take an event in time order: inputs move the lags, observations correct their
    /// channel. An observation of a channel the model does not have is ignored (returns false).
    pub fn apply(&mut self, e: &Event) -> bool {
        self.features.apply(e);
        let Event::Observation {
            t_ns,
            channel,
            value,
            sigma,
        } = e
        else {
            return true;
        };
        let h = self.features.row();
        self.observe_row(channel, *t_ns, *value, *sigma, &h)
    }

    /// Correct a channel with an observation made at `t_ns` whose design row `h` is known
    /// (the lag states at that time, when the filter has already run past it). The
    /// observation is scored first: the model, the last measured value and no change
    /// against it, before it corrects anything.
    pub fn observe_row(
        &mut self,
        channel: &str,
        t_ns: i64,
        value: f64,
        sigma: Option<f64>,
        h: &DVector<f64>,
    ) -> bool {
        let min_scored = self.model.config.min_scored;
        let run_gap_ns = driftwatch_core::units::h_to_ns(self.model.config.run_gap_h);
        let Some(s) = self.channels.get_mut(channel) else {
            return false;
        };
        if !value.is_finite() || h.len() != s.beta.len() {
            return false;
        }
        let obs_var = sigma
            .filter(|x| driftwatch_core::units::positive(*x))
            .map_or(0.0, |x| x * x);
        s.walk_to(t_ns);
        let mut guard = std::mem::take(&mut s.guard);
        s.score_into(
            &mut guard,
            (value, obs_var),
            h,
            t_ns,
            (min_scored, run_gap_ns),
        );
        s.guard = guard;
        s.correct(h, value, obs_var);
        true
    }

    /// Every channel at `t_ns` (not before the last event), inputs held since the last one:
    /// the served value (the model, or its fallback) and its band.
    pub fn predict(&mut self, t_ns: i64) -> Vec<Prediction> {
        self.features.advance_to(t_ns);
        let h = self.features.row();
        let min_scored = self.model.config.min_scored;
        self.channels
            .iter()
            .map(|(name, s)| {
                let walk = s.walk_per_s * (t_ns - s.t_ns).max(0) as f64 / 1e9;
                let (m, v) = s.served_model(&s.guard, &h, t_ns, min_scored);
                let reg = s.reg_value(&s.guard, &h);
                let (value, sigma, source) =
                    s.guard
                        .serve((m, v + walk), s.cold(walk), reg, min_scored, t_ns);
                let reason =
                    (source != Served::Model).then(|| s.guard.reason(name, min_scored, source));
                Prediction {
                    channel: name.clone(),
                    value,
                    sigma,
                    source,
                    model_value: m,
                    no_change_value: s.beta[0],
                    reason,
                }
            })
            .collect()
    }

    /// Current parameter mean of a channel (for reports and the batch-online check).
    pub fn coef(&self, channel: &str) -> Option<Vec<f64>> {
        self.channels
            .get(channel)
            .map(|s| s.beta.iter().copied().collect())
    }

    /// What each channel serves and why, with its held-out scores and offset walk.
    pub fn guards(&self) -> Vec<GuardSummary> {
        let min_scored = self.model.config.min_scored;
        self.model
            .channels
            .iter()
            .filter_map(|c| {
                let s = self.channels.get(&c.name)?;
                Some(s.guard.summary(
                    &c.name,
                    (min_scored, self.model.config.anchoring),
                    (s.walk_per_s * 3600.0, c.offset_walk_per_h.is_some()),
                ))
            })
            .collect()
    }

    /// A channel's guard (its last observation, mean and scores).
    pub fn guard(&self, channel: &str) -> Option<&Guard> {
        self.channels.get(channel).map(|s| &s.guard)
    }
}
