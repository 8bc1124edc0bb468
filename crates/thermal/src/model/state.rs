//! One channel's Kalman filter: the parameters' mean and covariance from a fit or a prior, the
//! offset's random walk, corrections by observations, and the channel's guard.

use super::config::Anchoring;
use super::fitted::{ChangeRegression, ChannelFit};
use super::guard::Guard;
use nalgebra::{DMatrix, DVector};
use std::borrow::Cow;
use std::sync::Arc;

/// One channel's filter: parameter mean and covariance, the offset walk, the guard.
#[derive(Debug, Clone)]
pub(super) struct ChannelState {
    pub(super) beta: DVector<f64>,
    /// The parameters' covariance, shared with the copies the loop takes of a running
    /// predictor at every look (for the API): it changes only at an observation, which then
    /// copies it once, where every look had copied it (a machine's six of them, some 5 KB).
    p: Arc<DMatrix<f64>>,
    /// Time of the last observation (or of the start).
    pub(super) t_ns: i64,
    discrepancy2: f64,
    /// Random walk of the offset, the channel's unit squared per second.
    pub(super) walk_per_s: f64,
    pub(super) guard: Guard,
    /// Columns held to the fit data's range (see [`ChannelFit::held_to_range`]).
    /// (This and the regression are the fit's, shared by the copies: the loop copies a
    /// running predictor at every look, for the API.)
    held: Arc<[(usize, f64, f64)]>,
    pub(super) reg: Option<Arc<ChangeRegression>>,
    /// [`ModelConfig::anchoring`].
    pub(super) anchoring: Anchoring,
}

impl ChannelState {
    /// From a fit's posterior, the walk starting at `t_ns`.
    pub(super) fn of_fit(c: &ChannelFit, walk_per_s: f64, t_ns: i64) -> Self {
        ChannelState {
            beta: DVector::from_column_slice(&c.coef),
            p: Arc::new(c.cov_matrix()),
            t_ns,
            discrepancy2: c.discrepancy_um.powi(2),
            walk_per_s,
            guard: c.guard.clone(),
            held: c.held_to_range.as_slice().into(),
            reg: c.regression.clone().map(Arc::new),
            anchoring: Anchoring::Never,
        }
    }

    /// From a prior (zero mean, precision `lambda`).
    pub(super) fn prior(lambda: &[f64], discrepancy2: f64, walk_per_s: f64, t_ns: i64) -> Self {
        ChannelState {
            beta: DVector::zeros(lambda.len()),
            p: Arc::new(DMatrix::from_diagonal(&DVector::from_iterator(
                lambda.len(),
                lambda.iter().map(|l| 1.0 / l),
            ))),
            t_ns,
            discrepancy2,
            walk_per_s,
            guard: Guard::default(),
            held: Arc::new([]),
            reg: None,
            anchoring: Anchoring::Never,
        }
    }

    /// The model's value at design row `h` at `t_ns` as served and its variance: anchored at
    /// `guard`'s last observation as [`ModelConfig::anchoring`] says, for as long as the last
    /// measured value may be held (it was judged at the gaps scored; a free run of hours from
    /// one reading is the filter's own).
    pub(super) fn served_model(
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
            Some(a) if guard.anchored_under(self.anchoring, min_scored) => a,
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
    pub(super) fn reg_value(&self, guard: &Guard, h: &DVector<f64>) -> f64 {
        match (&self.reg, guard.last) {
            (Some(r), Some(last)) => r.value(last, &guard.last_row, h),
            (None, Some(last)) => last,
            _ => f64::NAN,
        }
    }

    /// The offset walk from the last observation up to `t_ns` (never back).
    pub(super) fn walk_to(&mut self, t_ns: i64) {
        Arc::make_mut(&mut self.p)[(0, 0)] +=
            self.walk_per_s * (t_ns - self.t_ns).max(0) as f64 / 1e9;
        self.t_ns = self.t_ns.max(t_ns);
    }

    /// The model's value for the design row `h` and its variance (of the true value:
    /// parameters, walk so far, discrepancy).
    pub(super) fn model_at(&self, h: &DVector<f64>) -> (f64, f64) {
        let h: &DVector<f64> = &self.hold(h);
        (
            h.dot(&self.beta),
            h.dot(&(&*self.p * h)) + self.discrepancy2,
        )
    }

    /// The design row with the held columns inside the fit data's range (the row itself,
    /// not a copy, when no column is held: this runs for every observation of every fit).
    fn hold<'a>(&self, h: &'a DVector<f64>) -> Cow<'a, DVector<f64>> {
        if self.held.is_empty() {
            return Cow::Borrowed(h);
        }
        let mut h = h.clone();
        for &(j, lo, hi) in self.held.iter() {
            if j < h.len() && lo <= hi {
                h[j] = h[j].clamp(lo, hi);
            }
        }
        Cow::Owned(h)
    }

    /// The cold value (the offset: every thermal term at zero) and its variance, with
    /// `walk` of the offset since the last observation.
    pub(super) fn cold(&self, walk: f64) -> (f64, f64) {
        (self.beta[0], self.p[(0, 0)] + walk + self.discrepancy2)
    }

    /// The Kalman correction by an observation `y` with stated variance `obs_var`.
    pub(super) fn correct(&mut self, h: &DVector<f64>, y: f64, obs_var: f64) {
        self.predict_and_correct(h, y, obs_var);
    }

    /// [`ChannelState::model_at`] before the correction by `y`, then the correction: the
    /// two share the product `P h`.
    pub(super) fn predict_and_correct(
        &mut self,
        h: &DVector<f64>,
        y: f64,
        obs_var: f64,
    ) -> (f64, f64) {
        let h: &DVector<f64> = &self.hold(h);
        let r = obs_var + self.discrepancy2;
        let r = if r > 0.0 { r } else { 1e-12 };
        let p = Arc::make_mut(&mut self.p);
        let ph = &*p * h;
        let hph = h.dot(&ph);
        let m = h.dot(&self.beta);
        let s = hph + r;
        self.beta.axpy((y - m) / s, &ph, 1.0);
        // P - (Ph)(Ph)^T / S: symmetric by construction, O(n^2).
        p.ger(-1.0 / s, &ph, &ph, 1.0);
        (m, hph + self.discrepancy2)
    }
}
