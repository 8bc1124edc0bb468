//! Each channel's guard: every observation scored before it corrects the filter, and what the
//! channel serves (the model, anchored or not, or a fallback that beat it) and why.

use nalgebra::DVector;
use serde::{Deserialize, Serialize};

use super::config::Anchoring;
use driftwatch_core::error_name::channel_unit;

/// Where a served value comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub enum Served {
    /// The thermal model, corrected by every observation.
    #[default]
    Model,
    /// The last measured value, held.
    LastMeasured,
    /// No change: the channel's value on a cold machine at the reference temperatures (the
    /// model's offset, every thermal term at zero), which is what no thermal compensation
    /// leaves in place.
    NoChange,
    /// The last measured value moved by least squares on the inputs' changes since it: the
    /// textbook regression on the temperatures, which the model must beat
    /// ([`ChangeRegression`](super::ChangeRegression)).
    Regression,
}

impl Served {
    pub fn as_str(self) -> &'static str {
        match self {
            Served::Model => "model",
            Served::LastMeasured => "last_measured",
            Served::NoChange => "no_change",
            Served::Regression => "regression",
        }
    }
}

/// Smallest and largest factor on the model's band.
const SCALE_RANGE: (f64, f64) = (0.1, 10.0);

/// A channel's record of its predictions and what it serves. Every observation is scored
/// before it corrects the filter: the model's prediction, the last measured value and no
/// change (the model's offset: its cold value) against it, and the served value in its
/// served band. It starts from the fit's held-out tail. Sums only: cheap to copy and to keep
/// in a model file.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Guard {
    /// The last observation and its stated variance.
    pub last: Option<f64>,
    pub last_var: f64,
    /// Scored observations and the sums of squared errors of the model, the last measured
    /// value and no change.
    pub n: usize,
    pub sse_model: f64,
    pub sse_last: f64,
    pub sse_cold: f64,
    /// Sums of the model's variance of the true value and of the observations' own.
    pub sum_model_var: f64,
    pub sum_obs_var: f64,
    /// The served value against each scored observation in the band served at the time
    /// (with the observation's own variance): the sum of z^2, and |z| <= 1 and <= 2 counts.
    pub sum_z2: f64,
    pub within_1: usize,
    pub within_2: usize,
    /// Sums of the paired differences of squared errors, the model's less the fallback's,
    /// and of their squares: the last measured value and no change.
    pub d_last: f64,
    pub d2_last: f64,
    pub d_cold: f64,
    pub d2_cold: f64,
    /// The same for least squares on the inputs' changes
    /// ([`ChangeRegression`](super::ChangeRegression); the last measured value where the
    /// channel has none).
    pub sse_reg: f64,
    pub d_reg: f64,
    pub d2_reg: f64,
    /// The design row of the last observation: where the regression's changes start.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub last_row: Vec<f64>,
    /// The last observation's time, and the sum of the gaps before the scored ones, s: the
    /// last measured value was judged at those gaps, and is not held much longer.
    pub last_t_ns: Option<i64>,
    pub sum_gap_s: f64,
    /// The model anchored at the last observation against the model as fitted: the
    /// observations where both were scored, and the sums of the paired differences of
    /// squared errors (the fitted model's less the anchored one's) and of their squares.
    pub n_anchor: usize,
    pub d_anchor: f64,
    pub d2_anchor: f64,
}

/// The one-sided Diebold-Mariano test on `n` paired differences of squared errors (sum and
/// sum of squares): the statistic when their mean is positive by more than 1.645 of its
/// standard error (5 %, one-sided).
pub fn beyond_chance(n: usize, sum_d: f64, sum_d2: f64) -> Option<f64> {
    if n < 2 {
        return None;
    }
    let n = n as f64;
    let mean = sum_d / n;
    let var = ((sum_d2 / n - mean * mean) * n / (n - 1.0)).max(0.0);
    let t = mean / (var / n).sqrt().max(1e-300);
    (mean > 0.0 && t > FALLBACK_T).then_some(t)
}

/// How many mean scored gaps the last measured value may be held (beyond, it was never
/// judged: a value 15 s old predicts well, six hours old it does not).
const STALE_GAPS: f64 = 2.0;

/// How many standard errors a fallback must beat the model by (one-sided, 95 %).
const FALLBACK_T: f64 = 1.645;

/// A channel's guard as the views and reports show it.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct GuardSummary {
    pub channel: String,
    pub unit: String,
    /// What is served now, and why.
    pub source: Served,
    pub reason: String,
    /// The model is served anchored at its last observation (the configuration's
    /// `anchoring`): the last observation moved by the model's change since it.
    pub anchored: bool,
    /// The offset walk in force, the channel's unit squared per hour, and whether it was
    /// learned from the channel's own observations.
    pub offset_walk_per_h: f64,
    pub offset_walk_learned: bool,
    /// Held-out observations scored (each before it corrected the model).
    pub scored: usize,
    pub rmse_model: f64,
    pub rmse_last_measured: f64,
    pub rmse_no_change: f64,
    pub rmse_regression: f64,
    /// The factor on the model's band learned from the scored observations.
    pub sigma_scale: f64,
    /// The served value in its served band: RMS of z, share within 1 and 2 sigma.
    pub z_rms: f64,
    pub within_1_sigma: f64,
    pub within_2_sigma: f64,
}

impl std::fmt::Display for GuardSummary {
    /// One line: what is served, its scores, band and walk (the fit, predict and the bench
    /// print it).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let u = &self.unit;
        write!(
            f,
            "{:<6} serves {}{}: {} scored, RMSE model {:.2} / last measured {:.2} / no change {:.2} / regression {:.2} {u}; band x{:.2}: z rms {:.2}, within 1 sigma {:.0} %, 2 sigma {:.0} %; offset walk {} {u}^2/h ({})",
            self.channel,
            self.source.as_str(),
            if self.anchored && self.source == Served::Model {
                " (anchored at the last observation)"
            } else {
                ""
            },
            self.scored,
            self.rmse_model,
            self.rmse_last_measured,
            self.rmse_no_change,
            self.rmse_regression,
            self.sigma_scale,
            self.z_rms,
            100.0 * self.within_1_sigma,
            100.0 * self.within_2_sigma,
            self.offset_walk_per_h,
            if self.offset_walk_learned {
                "learned"
            } else {
                "default"
            }
        )
    }
}

impl Guard {
    fn rms(&self, sse: f64) -> f64 {
        if self.n == 0 {
            f64::NAN
        } else {
            (sse / self.n as f64).sqrt()
        }
    }

    /// Whether the last measured value at `t_ns` is older than it was ever judged at.
    pub(super) fn last_is_stale(&self, t_ns: i64) -> bool {
        match self.last_t_ns {
            Some(t) if self.n > 0 => {
                (t_ns - t) as f64 / 1e9 > STALE_GAPS * self.sum_gap_s / self.n as f64
            }
            _ => false,
        }
    }

    /// The factor on the model's sigma that makes the scored observations' z^2 average 1:
    /// `c^2 = (sse_model - sum_obs_var) / sum_model_var`, with `min_scored` observations at
    /// `c = 1` added so that a few scores move it little, within 0.1 to 10; 1 until
    /// `min_scored` are scored.
    pub fn sigma_scale(&self, min_scored: usize) -> f64 {
        if self.n < min_scored || !driftwatch_core::units::positive(self.sum_model_var) {
            return 1.0;
        }
        let prior = min_scored as f64 * self.sum_model_var / self.n as f64;
        let c2 =
            ((self.sse_model - self.sum_obs_var).max(0.0) + prior) / (self.sum_model_var + prior);
        c2.sqrt().clamp(SCALE_RANGE.0, SCALE_RANGE.1)
    }

    /// Whether a fallback beat the model on the scored observations beyond chance: the mean
    /// of the paired differences of squared errors (the model's less the fallback's) is
    /// positive by more than [`FALLBACK_T`] of its standard error (a one-sided
    /// Diebold-Mariano test), so that a noisy channel does not flip between the model and a
    /// noisy last reading. Returns the statistic when it did.
    fn beaten_by(&self, sum_d: f64, sum_d2: f64) -> Option<f64> {
        beyond_chance(self.n, sum_d, sum_d2)
    }

    /// Whether the model is served anchored at the last observation: it beat the model as
    /// fitted on the scored observations beyond chance (the same test as the fallbacks'),
    /// once `min_scored` are scored.
    pub fn anchors(&self, min_scored: usize) -> bool {
        self.n_anchor >= min_scored
            && beyond_chance(self.n_anchor, self.d_anchor, self.d2_anchor).is_some()
    }

    /// Whether the model is served anchored under `anchoring`, given this guard.
    pub(super) fn anchored_under(&self, anchoring: Anchoring, min_scored: usize) -> bool {
        match anchoring {
            Anchoring::Never => false,
            Anchoring::HeldOut => self.anchors(min_scored),
            Anchoring::Always => true,
        }
    }

    /// Score the model as fitted (`fitted`) and anchored at the last observation
    /// (`anchored`, NaN where there is no anchor) against the observation `y` at `t_ns`,
    /// before [`Guard::observe`] takes it: on the observations that one scores.
    pub(super) fn score_anchor(
        &mut self,
        y: f64,
        fitted: f64,
        anchored: f64,
        t_ns: i64,
        run_gap_ns: i64,
    ) {
        let new_run = self.last_t_ns.is_some_and(|t| t_ns - t > run_gap_ns);
        if self.last.is_none() || new_run || !anchored.is_finite() {
            return;
        }
        let d = (y - fitted).powi(2) - (y - anchored).powi(2);
        self.n_anchor += 1;
        self.d_anchor += d;
        self.d2_anchor += d * d;
    }

    /// What to serve: the model unless a fallback (the last measured value, no change, or
    /// least squares on the inputs' changes) beat it on the scored observations beyond
    /// chance (the model until `min_scored` are scored); of several that beat it, the one
    /// with the smallest error.
    pub fn source(&self, min_scored: usize) -> Served {
        self.fallback(min_scored, true)
    }

    /// [`Guard::source`], the fallbacks anchored at the last observation (the last measured
    /// value, the regression from it) left out unless `anchored`.
    fn fallback(&self, min_scored: usize, anchored: bool) -> Served {
        if self.n < min_scored || self.last.is_none() {
            return Served::Model;
        }
        let mut best: Option<(f64, Served)> = None;
        for (sse, d, d2, served) in [
            (self.sse_cold, self.d_cold, self.d2_cold, Served::NoChange),
            (
                self.sse_last,
                self.d_last,
                self.d2_last,
                Served::LastMeasured,
            ),
            (self.sse_reg, self.d_reg, self.d2_reg, Served::Regression),
        ] {
            let eligible = anchored || served == Served::NoChange;
            if eligible && self.beaten_by(d, d2).is_some() && best.is_none_or(|(b, _)| sse < b) {
                best = Some((sse, served));
            }
        }
        best.map_or(Served::Model, |(_, s)| s)
    }

    /// The served value and its sigma (of the true value) from the model's value and
    /// variance and its cold value (the offset) and that one's variance: the model's, its
    /// sigma scaled by [`Guard::sigma_scale`], unless a fallback beat it ([`Guard::source`]).
    /// (Not on the width of the bands: a fallback's scored error holds for the gaps between
    /// the scored cycles, not for any time since the last one.) A fallback's sigma is its
    /// scored error less the observations' own noise, at least its own uncertainty
    /// ([`Guard::reason`] says why).
    /// `reg` is the regression's value
    /// ([`ChangeRegression::value`](super::ChangeRegression::value)).
    pub fn serve(
        &self,
        model: (f64, f64),
        cold: (f64, f64),
        reg: f64,
        min_scored: usize,
        t_ns: i64,
    ) -> (f64, f64, Served) {
        let scale = self.sigma_scale(min_scored);
        let model_sd = scale * model.1.max(0.0).sqrt();
        let n = self.n.max(1) as f64;
        let obs_var = self.sum_obs_var / n;
        let mut source = self.source(min_scored);
        // Both fallbacks anchored at the last observation were judged at the gaps scored.
        if matches!(source, Served::LastMeasured | Served::Regression) && self.last_is_stale(t_ns) {
            source = self.fallback(min_scored, false);
        }
        match (source, self.last) {
            (Served::NoChange, _) => {
                let var = (self.sse_cold / n - obs_var).max(cold.1);
                (cold.0, var.sqrt(), Served::NoChange)
            }
            (Served::LastMeasured, Some(last)) => {
                let var = (self.sse_last / n - obs_var).max(self.last_var);
                (last, var.sqrt(), Served::LastMeasured)
            }
            (Served::Regression, Some(_)) if reg.is_finite() => {
                let var = (self.sse_reg / n - obs_var).max(self.last_var);
                (reg, var.sqrt(), Served::Regression)
            }
            _ => (model.0, model_sd, Served::Model),
        }
    }

    /// Score the observation `y` at `t_ns` (stated variance `obs_var`) before it corrects
    /// the model, whose prediction of it is `model` (value, variance of the true value) and
    /// whose cold value is `cold` and the regression's `reg`, then take it as the last value
    /// with its design row `row`. The first observation of a channel has no last value and
    /// is only taken; so is the first of a run (more than `run_gap_ns` after the last): the
    /// fallbacks anchored at the last observation are judged within runs, and after a stand
    /// they are stale ([`Guard::serve`]), so a night's change is not theirs to answer for.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn observe(
        &mut self,
        y: f64,
        obs_var: f64,
        model: (f64, f64),
        cold: (f64, f64),
        reg: f64,
        min_scored: usize,
        t_ns: i64,
        row: &DVector<f64>,
        run_gap_ns: i64,
    ) {
        let new_run = self.last_t_ns.is_some_and(|t| t_ns - t > run_gap_ns);
        if let Some(last) = self.last.filter(|_| !new_run) {
            let reg = if reg.is_finite() { reg } else { last };
            self.score(y, obs_var, (model, cold, reg), min_scored, t_ns, last);
        }
        self.last = Some(y);
        self.last_var = obs_var;
        self.last_t_ns = Some(t_ns);
        self.last_row = row.iter().copied().collect();
    }

    /// `by`: the model's value and variance, the cold value and variance, the regression's.
    fn score(
        &mut self,
        y: f64,
        obs_var: f64,
        by: ((f64, f64), (f64, f64), f64),
        min_scored: usize,
        t_ns: i64,
        last: f64,
    ) {
        let (model, cold, reg) = by;
        let (v, s, _) = self.serve(model, cold, reg, min_scored, t_ns);
        if let Some(t) = self.last_t_ns {
            self.sum_gap_s += (t_ns - t).max(0) as f64 / 1e9;
        }
        let z2 = (y - v).powi(2) / (s * s + obs_var).max(1e-24);
        self.sum_z2 += z2;
        self.within_1 += usize::from(z2 <= 1.0);
        self.within_2 += usize::from(z2 <= 4.0);
        self.n += 1;
        let (em, el, ec) = (
            (y - model.0).powi(2),
            (y - last).powi(2),
            (y - cold.0).powi(2),
        );
        self.sse_model += em;
        self.sse_last += el;
        self.sse_cold += ec;
        self.d_last += em - el;
        self.d2_last += (em - el).powi(2);
        self.d_cold += em - ec;
        self.d2_cold += (em - ec).powi(2);
        let er = (y - reg).powi(2);
        self.sse_reg += er;
        self.d_reg += em - er;
        self.d2_reg += (em - er).powi(2);
        self.sum_model_var += model.1.max(0.0);
        self.sum_obs_var += obs_var;
    }

    /// Why the channel serves `served` (its [`Guard::source`], or what [`Guard::serve`] gave).
    pub fn reason(&self, channel: &str, min_scored: usize, served: Served) -> String {
        let u = channel_unit(channel);
        let (m, l, c, r) = (
            self.rms(self.sse_model),
            self.rms(self.sse_last),
            self.rms(self.sse_cold),
            self.rms(self.sse_reg),
        );
        let n = self.n;
        match served {
            Served::Model if n < min_scored => format!(
                "model: {n} held-out observation(s) scored, {min_scored} needed to judge it"
            ),
            Served::Model => format!(
                "model: RMSE {m:.2} {u} on {n} held-out observations, against last measured {l:.2}, no change {c:.2} and least squares on the inputs' changes {r:.2} (no fallback better beyond chance)"
            ),
            Served::LastMeasured => format!(
                "last measured: the model's RMSE {m:.2} {u} on {n} held-out observations is worse than the last measured value's {l:.2} beyond chance (t = {:.1}; no change {c:.2})",
                self.beaten_by(self.d_last, self.d2_last)
                    .unwrap_or(f64::NAN)
            ),
            Served::NoChange => format!(
                "no change (its cold value, as if not compensated): the model's RMSE {m:.2} {u} on {n} held-out observations is worse than no change's {c:.2} beyond chance (t = {:.1}; last measured {l:.2})",
                self.beaten_by(self.d_cold, self.d2_cold)
                    .unwrap_or(f64::NAN)
            ),
            Served::Regression => format!(
                "least squares on the inputs' changes since the last measured value: the model's RMSE {m:.2} {u} on {n} held-out observations is worse than least squares' {r:.2} beyond chance (t = {:.1}; last measured {l:.2}, no change {c:.2})",
                self.beaten_by(self.d_reg, self.d2_reg).unwrap_or(f64::NAN)
            ),
        }
    }

    pub fn summary(
        &self,
        channel: &str,
        (min_scored, anchoring): (usize, Anchoring),
        walk: (f64, bool),
    ) -> GuardSummary {
        let n = self.n.max(1) as f64;
        GuardSummary {
            channel: channel.to_string(),
            unit: channel_unit(channel).to_string(),
            source: self.source(min_scored),
            reason: self.reason(channel, min_scored, self.source(min_scored)),
            anchored: self.anchored_under(anchoring, min_scored),
            offset_walk_per_h: walk.0,
            offset_walk_learned: walk.1,
            scored: self.n,
            rmse_model: self.rms(self.sse_model),
            rmse_last_measured: self.rms(self.sse_last),
            rmse_no_change: self.rms(self.sse_cold),
            rmse_regression: self.rms(self.sse_reg),
            sigma_scale: self.sigma_scale(min_scored),
            z_rms: self.rms(self.sum_z2),
            within_1_sigma: self.within_1 as f64 / n,
            within_2_sigma: self.within_2 as f64 / n,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::units;

    const MIN: i64 = units::NS_PER_MIN;

    /// The model anchored at the last observation is served where it beat the fitted
    /// model on the scored observations beyond chance: a fitted model 3 off all along loses
    /// to its anchored self; where the observations are noise about a fitted model that is
    /// right, the anchor carries the noise and is not taken.
    #[test]
    fn the_model_is_anchored_where_the_anchor_beat_it_on_the_scored_observations() {
        let at = |k: i64| k * 30 * MIN;
        let row = DVector::from_element(1, 1.0);
        let run = |y: &dyn Fn(i64) -> f64, fitted: &dyn Fn(i64) -> f64| {
            let mut g = Guard::default();
            for k in 0..8 {
                let anchored = g.last.map_or(f64::NAN, |l| l + fitted(k) - fitted(k - 1));
                g.score_anchor(y(k), fitted(k), anchored, at(k), i64::MAX);
                let m = (fitted(k), 0.1);
                g.observe(
                    y(k),
                    0.01,
                    m,
                    (0.0, 0.1),
                    f64::NAN,
                    4,
                    at(k),
                    &row,
                    i64::MAX,
                );
            }
            g
        };
        let drift = |k: i64| 5.0 + 0.5 * k as f64 + if k % 2 == 0 { 0.05 } else { -0.05 };
        let g = run(&drift, &|k| 2.0 + 0.5 * k as f64);
        assert_eq!(g.n_anchor, 7);
        assert!(g.anchors(4), "{g:?}");
        assert!(!g.anchors(8), "not before min_scored are scored: {g:?}");
        let noise = |k: i64| if k % 2 == 0 { 1.0 } else { -1.0 };
        let g = run(&noise, &|_| 0.0);
        assert!(!g.anchors(4), "{g:?}");
    }

    #[test]
    fn the_served_value_falls_back_when_the_model_does_worse_and_says_why() {
        // Observations every 40 min; `obs` scores one before it becomes the last value.
        let at = |k: i64| k * 40 * MIN;
        let mut g = Guard::default();
        // Before min_scored: the model, and it says so.
        let cold = (1.0, 0.1);
        let row = DVector::from_element(1, 1.0);
        g.observe(1.0, 0.25, (1.0, 0.5), cold, 1.0, 4, at(0), &row, i64::MAX);
        for (k, y) in [1.2, 0.8, 1.1].into_iter().enumerate() {
            // The model is 3 off each time; the cold value is close.
            g.observe(
                y,
                0.25,
                (y + 3.0, 0.5),
                cold,
                f64::NAN,
                4,
                at(k as i64 + 1),
                &row,
                i64::MAX,
            );
        }
        assert_eq!(g.source(4), Served::Model);
        let r = g.reason("EA0C", 4, g.source(4));
        assert!(r.contains("3 held-out"), "{r}");
        g.observe(
            0.9,
            0.25,
            (3.9, 0.5),
            cold,
            f64::NAN,
            4,
            at(4),
            &row,
            i64::MAX,
        );
        assert_eq!(g.source(4), Served::NoChange);
        let (v, s, src) = g.serve((100.0, 0.5), cold, 0.9, 4, at(5));
        assert_eq!((v, src), (1.0, Served::NoChange));
        assert!(s.is_finite() && s >= 0.1f64.sqrt(), "{s}");
        let r = g.reason("EA0C", 4, src);
        assert!(
            r.contains("urad") && r.contains("worse than no change"),
            "{r}"
        );
        // A channel that wanders: the last measured value does best, for as long as it was
        // judged (two gaps); held for hours it was never judged, and the model is served.
        let mut g = Guard::default();
        for k in 0..=6 {
            let y = 5.0 * k as f64;
            g.observe(
                y,
                0.01,
                (y - 6.0, 0.5),
                (0.0, 0.1),
                f64::NAN,
                4,
                at(k),
                &row,
                i64::MAX,
            );
        }
        assert_eq!(g.source(4), Served::LastMeasured);
        assert_eq!(g.serve((0.0, 1.0), (0.0, 0.1), 30.0, 4, at(7)).0, 30.0);
        assert_eq!(
            g.serve((0.0, 1.0), (0.0, 0.1), 30.0, 4, at(6) + 6 * 60 * MIN)
                .2,
            Served::Model
        );
        // A model that did best on the scores is served, however wide its band now.
        let mut g = Guard::default();
        for k in 0..=6 {
            let y = 0.1 * k as f64;
            g.observe(
                y,
                0.01,
                (y, 0.01),
                (0.0, 0.01),
                f64::NAN,
                4,
                at(k),
                &row,
                i64::MAX,
            );
        }
        assert_eq!(g.source(4), Served::Model);
        assert_eq!(
            g.serve((0.3, 100.0), (0.0, 0.01), 0.6, 4, at(7)).2,
            Served::Model
        );
    }
}
