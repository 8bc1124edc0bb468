//! The online model: each channel's Kalman filter over the fit's parameters, run forward in
//! time and corrected by every observation, and served through its guard.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use serde::Serialize;

use super::ThermalModel;
use super::config::Anchoring;
#[cfg(doc)]
use super::config::ModelConfig;
use super::events::Event;
use super::features::Features;
use super::fit::{ChangeRegression, ChannelFit};
use super::guard::{Guard, GuardSummary, Served};

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

/// One channel's filter: parameter mean and covariance, the offset walk, the guard.
#[derive(Debug, Clone)]
pub(super) struct ChannelState {
    beta: DVector<f64>,
    p: DMatrix<f64>,
    /// Time of the last observation (or of the start).
    t_ns: i64,
    discrepancy2: f64,
    /// Random walk of the offset, the channel's unit squared per second.
    walk_per_s: f64,
    guard: Guard,
    /// Columns held to the fit data's range (see [`ChannelFit::held_to_range`]).
    held: Vec<(usize, f64, f64)>,
    pub(super) reg: Option<ChangeRegression>,
    /// [`ModelConfig::anchoring`].
    pub(super) anchoring: Anchoring,
}

impl ChannelState {
    /// From a fit's posterior, the walk starting at `t_ns`.
    pub(super) fn of_fit(c: &ChannelFit, walk_per_s: f64, t_ns: i64) -> Self {
        ChannelState {
            beta: DVector::from_column_slice(&c.coef),
            p: c.cov_matrix(),
            t_ns,
            discrepancy2: c.discrepancy_um.powi(2),
            walk_per_s,
            guard: c.guard.clone(),
            held: c.held_to_range.clone(),
            reg: c.regression.clone(),
            anchoring: Anchoring::Never,
        }
    }

    /// From a prior (zero mean, precision `lambda`).
    pub(super) fn prior(lambda: &[f64], discrepancy2: f64, walk_per_s: f64, t_ns: i64) -> Self {
        ChannelState {
            beta: DVector::zeros(lambda.len()),
            p: DMatrix::from_diagonal(&DVector::from_iterator(
                lambda.len(),
                lambda.iter().map(|l| 1.0 / l),
            )),
            t_ns,
            discrepancy2,
            walk_per_s,
            guard: Guard::default(),
            held: Vec::new(),
            reg: None,
            anchoring: Anchoring::Never,
        }
    }

    /// The model's value at design row `h` at `t_ns` as served and its variance: anchored at
    /// `guard`'s last observation as [`ModelConfig::anchoring`] says, for as long as the last
    /// measured value may be held (it was judged at the gaps scored; a free run of hours from
    /// one reading is the filter's own).
    fn served_model(
        &self,
        guard: &Guard,
        h: &DVector<f64>,
        t_ns: i64,
        min_scored: usize,
    ) -> (f64, f64) {
        self.pick(self.model_pair(guard, h, t_ns), guard, min_scored)
    }

    /// Of the model's value as fitted and anchored ([`ChannelState::model_pair`]), the one
    /// served.
    fn pick(
        &self,
        (fitted, anchored): ((f64, f64), Option<(f64, f64)>),
        guard: &Guard,
        min_scored: usize,
    ) -> (f64, f64) {
        match anchored {
            Some(a) if self.anchoring.applies(guard, min_scored) => a,
            _ => fitted,
        }
    }

    /// Score the observation `y` (stated variance `obs_var`, design row `h`, at `t_ns`) into
    /// `guard` before it corrects the filter: the model as served and as fitted and anchored,
    /// the cold value and the regression; then the guard takes it as its last value.
    pub(super) fn score_into(
        &self,
        guard: &mut Guard,
        (y, obs_var): (f64, f64),
        h: &DVector<f64>,
        t_ns: i64,
        (min_scored, run_gap_ns): (usize, i64),
    ) {
        let pair = self.model_pair(guard, h, t_ns);
        let served = self.pick(pair, guard, min_scored);
        let reg = self.reg_value(guard, h);
        let anchored = pair.1.map_or(f64::NAN, |a| a.0);
        guard.score_anchor(y, pair.0.0, anchored, t_ns, run_gap_ns);
        guard.observe(
            y,
            obs_var,
            served,
            self.cold(0.0),
            reg,
            min_scored,
            t_ns,
            h,
            run_gap_ns,
        );
    }

    /// The model's value and variance at design row `h` as fitted, and anchored at `guard`'s
    /// last observation (`None` without one, or where it is stale).
    fn model_pair(
        &self,
        guard: &Guard,
        h: &DVector<f64>,
        t_ns: i64,
    ) -> ((f64, f64), Option<(f64, f64)>) {
        let (m, v) = self.model_at(h);
        let anchored = match guard.last {
            Some(last) if !guard.last_is_stale(t_ns) && guard.last_row.len() == h.len() => {
                let (at_last, _) = self.model_at(&DVector::from_column_slice(&guard.last_row));
                // The anchor's own noise rides on every value until the next observation.
                Some((m + last - at_last, v + guard.last_var))
            }
            _ => None,
        };
        ((m, v), anchored)
    }

    /// The regression's value at design row `h` from `guard`'s last observation (the last
    /// observation itself without a regression; NaN before any).
    fn reg_value(&self, guard: &Guard, h: &DVector<f64>) -> f64 {
        match (&self.reg, guard.last) {
            (Some(r), Some(last)) => r.value(last, &guard.last_row, h),
            (None, Some(last)) => last,
            _ => f64::NAN,
        }
    }

    /// The offset walk from the last observation up to `t_ns` (never back).
    pub(super) fn walk_to(&mut self, t_ns: i64) {
        self.p[(0, 0)] += self.walk_per_s * (t_ns - self.t_ns).max(0) as f64 / 1e9;
        self.t_ns = self.t_ns.max(t_ns);
    }

    /// The model's value for the design row `h` and its variance (of the true value:
    /// parameters, walk so far, discrepancy).
    pub(super) fn model_at(&self, h: &DVector<f64>) -> (f64, f64) {
        let h = self.hold(h);
        (
            h.dot(&self.beta),
            h.dot(&(&self.p * &h)) + self.discrepancy2,
        )
    }

    /// The design row with the held columns inside the fit data's range.
    fn hold(&self, h: &DVector<f64>) -> DVector<f64> {
        let mut h = h.clone();
        for &(j, lo, hi) in &self.held {
            if j < h.len() && lo <= hi {
                h[j] = h[j].clamp(lo, hi);
            }
        }
        h
    }

    /// The cold value (the offset: every thermal term at zero) and its variance, with
    /// `walk` of the offset since the last observation.
    fn cold(&self, walk: f64) -> (f64, f64) {
        (self.beta[0], self.p[(0, 0)] + walk + self.discrepancy2)
    }

    /// The Kalman correction by an observation `y` with stated variance `obs_var`.
    pub(super) fn correct(&mut self, h: &DVector<f64>, y: f64, obs_var: f64) {
        let h = &self.hold(h);
        let r = obs_var + self.discrepancy2;
        let r = if r > 0.0 { r } else { 1e-12 };
        let ph = &self.p * h;
        let s = h.dot(&ph) + r;
        let innovation = y - h.dot(&self.beta);
        self.beta.axpy(innovation / s, &ph, 1.0);
        // P - (Ph)(Ph)^T / S: symmetric by construction, O(n^2).
        self.p.ger(-1.0 / s, &ph, &ph, 1.0);
    }
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
        let run_gap_ns = crate::units::h_to_ns(self.model.config.run_gap_h);
        let Some(s) = self.channels.get_mut(channel) else {
            return false;
        };
        if !value.is_finite() || h.len() != s.beta.len() {
            return false;
        }
        let obs_var = sigma
            .filter(|x| crate::units::positive(*x))
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
