//! The thermal model as one machine's loop keeps it: the input history until there are
//! enough validated cycles to fit, then a [`Predictor`] fed with every spindle change,
//! temperature sample and validated cycle. It answers what the errors are now, how certain
//! that is, and whether a cycle is needed for certainty. Pure: the loop does the I/O.

use driftwatch_core::units;
use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;

use serde::Serialize;

use crate::compensation::PredictionPolicy;
use crate::scheduler::{SchedulerState, Uncertain};
use driftwatch_core::error_name::ErrorName;
use driftwatch_thermal::model::{
    Event, Features, GuardSummary, Obs, Prediction, Predictor, Served, ThermalModel, fit_rows,
};
use nalgebra::DVector;

/// How far the rows' lag states trail the inputs: longer than any cycle, so that a cycle's
/// reference time is never behind them when its result arrives.
pub const HOLD_BACK_NS: i64 = units::NS_PER_H;

/// What the API shows of the model.
#[derive(Debug, Clone, Serialize)]
pub struct ModelView {
    /// `waiting` (not enough cycles yet), `initial` (a model fitted elsewhere, until the
    /// machine's own fit), `fitted`, or `disabled`.
    pub status: String,
    pub message: String,
    pub validated_cycles: usize,
    pub model: Option<Arc<ThermalModel>>,
    /// Observations the online filter has taken since the fit.
    pub updates_since_fit: usize,
    /// What each error serves (the model, or its fallback: the last measured value or no
    /// change) and why: its held-out scores, the band's factor and the offset walk.
    pub served: Vec<GuardSummary>,
    /// Why the model's predictions are not served until it predicts a cycle within its
    /// band again (none: it is trusted).
    pub suspect: Option<String>,
}

#[derive(Debug, Clone)]
pub struct LiveModel {
    policy: PredictionPolicy,
    /// Lag states of every input since the first one (`None` before any input), held back
    /// by the inputs in `pending`, so that a cycle's row is taken at its reference time (the
    /// middle of its probing), which the loop learns only at its end. The predictor runs
    /// its own copy up to now.
    lagged: Option<Features>,
    pending: VecDeque<Held>,
    /// References of the temperature inputs when a model fitted elsewhere gave them.
    t_ref_c: BTreeMap<String, f64>,
    /// Validated cycles of the last `history_days` with their design rows: the fits need
    /// nothing else, so a refit costs the rows, not a replay of the inputs.
    window: Window,
    /// A model fitted elsewhere, served until the machine's own first fit.
    initial: Option<Arc<ThermalModel>>,
    ok_cycles: usize,
    cycles_since_fit: usize,
    predictor: Option<Predictor>,
    updates: usize,
    message: String,
    /// Why the model may not serve until it predicts a cycle within its band.
    suspect: Option<String>,
    /// Counts the changes of what [`LiveModel::view`] shows, so that the loop rebuilds that
    /// view (its guard summaries are formatted text) only when it changed, not at every
    /// look at the prediction.
    revision: u64,
}

impl LiveModel {
    pub fn new(policy: PredictionPolicy) -> Self {
        let message = if policy.enabled {
            format!("waiting for {} validated cycles", policy.min_cycles)
        } else {
            "disabled in the configuration".into()
        };
        LiveModel {
            policy,
            lagged: None,
            pending: VecDeque::new(),
            t_ref_c: BTreeMap::new(),
            window: Window::default(),
            initial: None,
            ok_cycles: 0,
            cycles_since_fit: 0,
            predictor: None,
            updates: 0,
            message,
            suspect: None,
            revision: 0,
        }
    }

    /// Start from a model fitted elsewhere (`driftwatch fit` on an earlier day of the same
    /// machine): it predicts from the first input on, and its configuration and temperature
    /// references replace the policy's model for the machine's own fits later.
    pub fn with_initial(mut policy: PredictionPolicy, model: Arc<ThermalModel>) -> Self {
        policy.model = model.config.clone();
        let mut m = LiveModel::new(policy);
        if m.policy.enabled {
            m.t_ref_c = model.t_ref_c.clone();
            m.message = format!(
                "started from a model fitted on {:.1} h of earlier data; the machine's own fit after {} validated cycles",
                units::ns_to_h(model.to_ns - model.from_ns),
                m.policy.min_cycles
            );
            m.initial = Some(model);
        }
        m
    }

    pub fn policy(&self) -> &PredictionPolicy {
        &self.policy
    }

    /// Changes whenever [`LiveModel::view`] may show something else.
    pub fn revision(&self) -> u64 {
        self.revision
    }

    fn start_at(&mut self, t_ns: i64) {
        if self.lagged.is_none() {
            // A model fitted elsewhere starts predicting: the view's status changes.
            self.revision += 1;
            self.lagged = Some(Features::new(&self.policy.model, &self.t_ref_c, t_ns));
            if let Some(model) = &self.initial {
                self.predictor = Some(Predictor::resume(
                    model.clone(),
                    Features::new(&self.policy.model, &self.t_ref_c, t_ns),
                    t_ns,
                ));
            }
        }
    }

    /// The lag states of now: the held-back ones with the pending inputs applied.
    fn features_now(&self) -> Option<Features> {
        let mut f = self.lagged.clone()?;
        for h in &self.pending {
            h.apply_to(&mut f);
        }
        Some(f)
    }

    /// Apply the held-back inputs up to `t_ns` to the lagged states.
    fn catch_up(&mut self, t_ns: i64) {
        let Some(lagged) = &mut self.lagged else {
            return;
        };
        while self.pending.front().is_some_and(|h| h.t_ns <= t_ns) {
            if let Some(h) = self.pending.pop_front() {
                h.apply_to(lagged);
            }
        }
        lagged.advance_to(t_ns);
    }

    /// A spindle change or a temperature sample, in time order.
    pub fn input(&mut self, e: Event) {
        if !self.policy.enabled {
            return;
        }
        let t = e.t_ns();
        self.start_at(t);
        if let Some(p) = &mut self.predictor {
            p.apply(&e);
        }
        if let Some(f) = &self.lagged {
            self.pending.push_back(Held::of(&e, f));
        }
        self.catch_up(t - HOLD_BACK_NS);
    }

    /// A validated cycle's errors and uncertainties at its reference time `t_ns` (at most
    /// [`HOLD_BACK_NS`] ago). Returns a note when this observation made a fit (or the fit
    /// failed and says why).
    pub fn observe(
        &mut self,
        t_ns: i64,
        errors: &BTreeMap<String, f64>,
        sigma: &BTreeMap<String, f64>,
    ) -> Option<String> {
        if !self.policy.enabled {
            return None;
        }
        // The counts, the message or the fit change.
        self.revision += 1;
        // The state before, to come back to if the update leaves the model unable to predict.
        let before = self.clone();
        self.take(t_ns, errors, sigma);
        let due = match (&self.predictor, &self.initial) {
            (Some(_), None) => self.cycles_since_fit >= self.policy.refit_every_cycles,
            _ => self.ok_cycles >= self.policy.min_cycles,
        };
        let note = due.then(|| self.fit(t_ns));
        if let Some(bad) = self.unhealthy(t_ns) {
            // The state before, but a view that says so: a new revision.
            let revision = self.revision + 1;
            *self = before;
            self.revision = revision;
            self.message = format!(
                "the update with the cycle at {t_ns} ns was rolled back: it left {bad}; the model \
                 goes on from its state before"
            );
            return Some(self.message.clone());
        }
        note
    }

    /// What is wrong with the model's predictions at `t_ns`, if anything: a value or band
    /// that is not a finite number (a sigma of 0 included: nothing is that certain).
    fn unhealthy(&self, t_ns: i64) -> Option<String> {
        let mut p = self.predictor.clone()?;
        p.predict(t_ns)
            .into_iter()
            .find(|x| !(x.value.is_finite() && driftwatch_core::units::positive(x.sigma)))
            .map(|x| format!("{} predicted as {} +- {}", x.channel, x.value, x.sigma))
    }

    /// Whether predictions may be served: a reason when the model is suspect.
    pub fn suspect(&self) -> Option<&str> {
        self.suspect.as_deref()
    }

    /// Check predictions against the latest measurement before they are served (see
    /// [`crate::compensation::inconsistent`]); on disagreement the model becomes suspect
    /// and the reasons are returned.
    pub fn check_consistency(
        &mut self,
        predicted: &BTreeMap<String, (f64, f64)>,
        measured: &crate::compensation::CompensationSet,
        measured_t_ns: i64,
        t_ns: i64,
        limits: &crate::compensation::ValidationLimits,
    ) -> Result<(), String> {
        let k = self.policy.consistency_sigmas;
        let reasons =
            crate::compensation::inconsistent(predicted, measured, measured_t_ns, t_ns, k, limits);
        if reasons.is_empty() {
            return Ok(());
        }
        let why = reasons.join("; ");
        if self.suspect.as_deref() != Some(why.as_str()) {
            self.suspect = Some(why.clone());
            self.revision += 1;
        }
        Err(why)
    }

    /// Judge the model on a validated cycle before it learns from it: its prediction for
    /// now must lie within `consistency_sigmas` of the measurement (plus the drift the rate
    /// limits allow since the cycle's reference time). A suspect model that passes is trusted
    /// again; one that fails becomes suspect. Returns a note when the verdict changed.
    pub fn judge(
        &mut self,
        measured: &crate::compensation::CompensationSet,
        measured_t_ns: i64,
        now_ns: i64,
        limits: &crate::compensation::ValidationLimits,
    ) -> Option<String> {
        let preds = self.predict(now_ns)?;
        let values: BTreeMap<String, (f64, f64)> = preds
            .iter()
            .filter(|p| measured.errors.contains_key(p.channel.as_str()))
            .map(|p| (p.channel.clone(), (p.value, p.sigma)))
            .collect();
        let was = self.suspect.take();
        self.revision += 1;
        match self.check_consistency(&values, measured, measured_t_ns, now_ns, limits) {
            Ok(()) => was.map(|_| {
                "it predicted the cycle within its band again: its predictions are served again"
                    .to_string()
            }),
            Err(why) => {
                (was.is_none()).then(|| format!("suspect, its predictions not served: {why}"))
            }
        }
    }

    /// Record a validated cycle: its rows, and the filter's correction.
    fn take(&mut self, t_ns: i64, errors: &BTreeMap<String, f64>, sigma: &BTreeMap<String, f64>) {
        self.ok_cycles += 1;
        self.cycles_since_fit += 1;
        self.start_at(t_ns);
        self.catch_up(t_ns);
        // One row for every channel of the cycle.
        let Some(row) = self.lagged.as_ref().map(Features::row) else {
            return;
        };
        let finite = || errors.iter().filter(|(_, v)| v.is_finite());
        for (name, v) in finite() {
            if let Some(p) = &mut self.predictor
                && p.observe_row(name, t_ns, *v, sigma.get(name).copied(), &row)
            {
                self.updates += 1;
            }
        }
        let keep_from = t_ns - units::h_to_ns(self.policy.history_days * 24.0);
        self.window.push(
            t_ns,
            &row,
            finite().map(|(name, v)| {
                let s = sigma.get(name).copied();
                (name.as_str(), *v, s.filter(|s| units::positive(*s)))
            }),
            keep_from,
        );
    }

    /// Bring back the state a running service had: the stored inputs and validated cycle
    /// results of the history window, in time order (inputs before observations at the same
    /// time), then one fit. Returns the fit's note, if one was made.
    pub fn restore(&mut self, events: &[Event]) -> Option<String> {
        if !self.policy.enabled {
            return None;
        }
        self.revision += 1;
        let mut i = 0;
        while i < events.len() {
            match &events[i] {
                Event::Observation { t_ns, .. } => {
                    // One cycle: every observation at this time.
                    let t = *t_ns;
                    let (mut errors, mut sigma) = (BTreeMap::new(), BTreeMap::new());
                    while let Some(Event::Observation {
                        t_ns,
                        channel,
                        value,
                        sigma: s,
                    }) = events.get(i)
                        && *t_ns == t
                    {
                        errors.insert(channel.clone(), *value);
                        if let Some(s) = s {
                            sigma.insert(channel.clone(), *s);
                        }
                        i += 1;
                    }
                    self.take(t, &errors, &sigma);
                }
                e => {
                    self.input(e.clone());
                    i += 1;
                }
            }
        }
        let t = events.last()?.t_ns();
        (self.ok_cycles >= self.policy.min_cycles).then(|| self.fit(t))
    }

    fn fit(&mut self, t_ns: i64) -> String {
        self.cycles_since_fit = 0;
        let Some(features) = self.features_now() else {
            return "no inputs yet".into();
        };
        let per = &self.window.per_channel();
        let span = (
            per.values()
                .filter_map(|v| v.first())
                .map(|o| o.t_ns)
                .min()
                .unwrap_or(t_ns),
            per.values()
                .filter_map(|v| v.last())
                .map(|o| o.t_ns)
                .max()
                .unwrap_or(t_ns),
        );
        match fit_rows(&self.policy.model, features.t_ref_c(), span, per) {
            Ok(model) => {
                let worst = model
                    .channels
                    .iter()
                    .map(|c| format!("{} {:.2}", c.name, c.rms_um))
                    .collect::<Vec<_>>()
                    .join(", ");
                let cycles = per.get("EZ0B").map_or(0, Vec::len);
                let missing = features.unseen_sensors();
                self.message = format!(
                    "fitted on {cycles} validated cycles over {:.1} h; residual rms {worst}{}",
                    units::ns_to_h(model.to_ns - model.from_ns),
                    if missing.is_empty() {
                        String::new()
                    } else {
                        format!("; not logged, left out: {}", missing.join(", "))
                    }
                );
                // The posterior holds every kept observation: the filter goes on from it
                // with the lag states of now, and takes no observation twice.
                self.predictor = Some(Predictor::resume(Arc::new(model), features, span.1));
                self.initial = None;
                self.updates = 0;
                self.message.clone()
            }
            Err(e) => {
                self.message = format!("fit failed, tried again at the next cycle: {e}");
                self.message.clone()
            }
        }
    }

    /// Every predicted error at `t_ns` (the loop's now), once fitted.
    pub fn predict(&mut self, t_ns: i64) -> Option<Vec<Prediction>> {
        self.predictor.as_mut().map(|p| p.predict(t_ns))
    }

    /// The first error whose prediction is less certain than the policy's cycle limit.
    pub fn uncertain(&self, predictions: &[Prediction], t_ns: i64) -> Option<Uncertain> {
        predictions
            .iter()
            .filter_map(|p| {
                // The location errors (a model may have other channels).
                let name = ErrorName::parse(&p.channel).ok()?;
                Some((p, name))
            })
            .find(|(p, name)| {
                let limit = if name.is_angular() {
                    self.policy.cycle_above_sigma_urad
                } else {
                    self.policy.cycle_above_sigma_um
                };
                p.sigma > limit
            })
            .map(|(p, _)| Uncertain {
                since_ns: t_ns,
                error: p.channel.clone(),
                sigma: p.sigma,
            })
    }

    /// One look of the scheduler at the model's predictions made at `t_ns` (`None`: the model
    /// does not predict): the first error less certain than its cycle limit, kept from when
    /// it first was, and the tool tip's band through `sens` ([`crate::tool_tip`]). The machine
    /// loop and the benches that replay its schedule look the same way.
    pub fn look(
        &self,
        st: &mut SchedulerState,
        predictions: Option<&[Prediction]>,
        sens: &BTreeMap<String, [f64; 3]>,
        t_ns: i64,
    ) {
        let Some(preds) = predictions else {
            st.look(None);
            return;
        };
        st.uncertain = match (self.uncertain(preds, t_ns), &st.uncertain) {
            (Some(mut u), Some(old)) => {
                u.since_ns = old.since_ns;
                Some(u)
            }
            (u, _) => u,
        };
        st.look(Some(crate::tool_tip::uncertainty(
            sens,
            preds,
            self.suspect(),
            t_ns,
        )));
    }

    /// The errors served from a fallback instead of the model, for a served set's reason
    /// (empty when every error is the model's).
    pub fn fallback_note(predictions: &[Prediction]) -> String {
        let held: Vec<String> = predictions
            .iter()
            .filter(|p| p.source != Served::Model)
            .map(|p| format!("{} {}", p.channel, p.source.as_str().replace('_', " ")))
            .collect();
        if held.is_empty() {
            String::new()
        } else {
            format!(
                "; served instead of the model (it did worse on held-out cycles): {}",
                held.join(", ")
            )
        }
    }

    pub fn is_fitted(&self) -> bool {
        self.predictor.is_some()
    }

    /// A copy of the running predictor (for `GET /prediction?at=`).
    pub fn snapshot(&self) -> Option<Predictor> {
        self.predictor.clone()
    }

    pub fn view(&self) -> ModelView {
        ModelView {
            status: if !self.policy.enabled {
                "disabled".into()
            } else if self.predictor.is_some() && self.initial.is_some() {
                "initial".into()
            } else if self.predictor.is_some() {
                "fitted".into()
            } else {
                "waiting".into()
            },
            message: self.message.clone(),
            validated_cycles: self.ok_cycles,
            model: self.predictor.as_ref().map(|p| p.model.clone()),
            updates_since_fit: self.updates,
            served: self
                .predictor
                .as_ref()
                .map(Predictor::guards)
                .unwrap_or_default(),
            suspect: self.suspect.clone(),
        }
    }
}

/// An input held back for the lagged states: its sensor by its place among the model's
/// sensors, not by name (a loop holds an hour of these).
#[derive(Debug, Clone, Copy)]
struct Held {
    t_ns: i64,
    input: HeldInput,
}

#[derive(Debug, Clone, Copy)]
enum HeldInput {
    Spindle(f64),
    /// A configured sensor ([`Features::sensor_index`]) and its reading.
    Sensor(usize, f64),
    /// Only the time moves on: a sensor the model does not take, or an observation.
    Time,
}

impl Held {
    fn of(e: &Event, f: &Features) -> Self {
        let input = match e {
            Event::Spindle { rpm, .. } => HeldInput::Spindle(*rpm),
            Event::Temperature {
                sensor, celsius, ..
            } => f
                .sensor_index(sensor)
                .map_or(HeldInput::Time, |k| HeldInput::Sensor(k, *celsius)),
            Event::Observation { .. } => HeldInput::Time,
        };
        Held {
            t_ns: e.t_ns(),
            input,
        }
    }

    /// What [`Features::apply`] does with the event this was made of.
    fn apply_to(&self, f: &mut Features) {
        match self.input {
            HeldInput::Spindle(rpm) => f.set_rpm(self.t_ns, rpm),
            HeldInput::Sensor(k, celsius) => f.set_sensor(self.t_ns, k, celsius),
            HeldInput::Time => f.advance_to(self.t_ns),
        }
    }
}

/// The validated cycles of the history window, packed in one buffer: each cycle's design row,
/// then each channel's value and standard uncertainty (NaN: none). A loop holds a week of
/// cycles; kept as observations per channel, each with a handle to a shared row, they took
/// about twice the memory, and a plant runs thousands of loops in one process.
#[derive(Debug, Clone, Default)]
struct Window {
    /// The channels in the order of their values in a record; a channel stays once seen.
    channels: Vec<String>,
    /// The design row's length.
    width: usize,
    /// Each cycle's reference time, oldest first.
    t_ns: Vec<i64>,
    /// The records, [`Window::stride`] numbers each, oldest first.
    data: Vec<f64>,
}

impl Window {
    fn stride(&self) -> usize {
        self.width + 2 * self.channels.len()
    }

    /// Add a cycle at `t_ns` (not before the last one) with its (channel, value, uncertainty)
    /// triples, and drop the cycles before `keep_from_ns`.
    fn push<'a>(
        &mut self,
        t_ns: i64,
        row: &DVector<f64>,
        values: impl Iterator<Item = (&'a str, f64, Option<f64>)> + Clone,
        keep_from_ns: i64,
    ) {
        if row.len() != self.width {
            // Rows of another model's columns cannot be fitted with these.
            *self = Window {
                channels: std::mem::take(&mut self.channels),
                width: row.len(),
                ..Window::default()
            };
        }
        for (name, ..) in values.clone() {
            if !self.channels.iter().any(|c| c == name) {
                self.add_channel(name);
            }
        }
        let start = self.data.len();
        self.data.extend_from_slice(row.as_slice());
        self.data.resize(start + self.stride(), f64::NAN);
        for (name, y, sigma) in values {
            if let Some(k) = self.channels.iter().position(|c| c == name) {
                let at = start + self.width + 2 * k;
                self.data[at] = y;
                self.data[at + 1] = sigma.unwrap_or(f64::NAN);
            }
        }
        self.t_ns.push(t_ns);
        let old = self.t_ns.partition_point(|t| *t < keep_from_ns);
        self.t_ns.drain(..old);
        self.data.drain(..old * self.stride());
        // Once the window is full it stops growing: without this, the capacity left from the
        // last doubling (up to half of it unused) stays with every machine.
        self.t_ns.shrink_to(self.t_ns.len() + self.t_ns.len() / 8);
        self.data.shrink_to(self.data.len() + self.data.len() / 8);
    }

    /// A channel first seen: every record so far gets an empty value for it.
    fn add_channel(&mut self, name: &str) {
        let old = self.stride();
        let mut data = Vec::with_capacity(self.t_ns.len() * (old + 2));
        for r in self.data.chunks_exact(old.max(1)) {
            data.extend_from_slice(r);
            data.extend_from_slice(&[f64::NAN, f64::NAN]);
        }
        self.data = data;
        self.channels.push(name.to_string());
    }

    /// Each channel's observations as the fit takes them, in time order; the channels of a
    /// cycle share its row. A channel with no observation left in the window is left out, not
    /// handed to the fit empty (where its failure would fail every channel's fit).
    fn per_channel(&self) -> BTreeMap<String, Vec<Obs>> {
        let stride = self.stride();
        if stride == 0 {
            return BTreeMap::new();
        }
        let records = || self.data.chunks_exact(stride).zip(&self.t_ns);
        let rows: Vec<Arc<DVector<f64>>> = records()
            .map(|(r, _)| Arc::new(DVector::from_column_slice(&r[..self.width])))
            .collect();
        let obs = |k: usize| -> Vec<Obs> {
            records()
                .zip(&rows)
                .filter_map(|((r, t_ns), row)| {
                    let (y, sigma) = (r[self.width + 2 * k], r[self.width + 2 * k + 1]);
                    (!y.is_nan()).then(|| Obs {
                        t_ns: *t_ns,
                        row: Arc::clone(row),
                        y,
                        sigma: (!sigma.is_nan()).then_some(sigma),
                    })
                })
                .collect()
        };
        self.channels
            .iter()
            .enumerate()
            .map(|(k, name)| (name.clone(), obs(k)))
            .filter(|(_, obs)| !obs.is_empty())
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compensation::TABLE_BC_ERRORS;

    const MIN: i64 = units::NS_PER_MIN;

    /// The packed window hands the fit each channel's values in time order with its cycle's
    /// row, a channel first seen later included, the cycles before the window gone, and a
    /// channel with none left in the window left out.
    #[test]
    fn the_window_gives_the_fit_each_channels_observations() {
        let row = |x: f64| DVector::from_vec(vec![1.0, x, 2.0 * x]);
        let mut w = Window::default();
        w.push(10, &row(1.0), [("B", 1.0, Some(0.5))].into_iter(), 0);
        w.push(
            20,
            &row(2.0),
            [("A", 2.0, None), ("B", 3.0, Some(0.25))].into_iter(),
            0,
        );
        w.push(30, &row(3.0), [("A", 4.0, Some(0.125))].into_iter(), 15);
        let per = w.per_channel();
        let seen = |name: &str| -> Vec<(i64, Vec<f64>, f64, Option<f64>)> {
            per[name]
                .iter()
                .map(|o| (o.t_ns, o.row.iter().copied().collect(), o.y, o.sigma))
                .collect()
        };
        assert_eq!(
            seen("A"),
            vec![
                (20, vec![1.0, 2.0, 4.0], 2.0, None),
                (30, vec![1.0, 3.0, 6.0], 4.0, Some(0.125))
            ]
        );
        assert_eq!(seen("B"), vec![(20, vec![1.0, 2.0, 4.0], 3.0, Some(0.25))]);
        assert!(Arc::ptr_eq(&per["A"][0].row, &per["B"][0].row));
        // The cycle at 20 leaves the window, and B's last value with it.
        w.push(40, &row(4.0), [("A", 5.0, None)].into_iter(), 25);
        let per = w.per_channel();
        assert_eq!(per.keys().collect::<Vec<_>>(), ["A"]);
        assert_eq!(
            per["A"].iter().map(|o| o.t_ns).collect::<Vec<_>>(),
            [30, 40]
        );
        // Rows of another width (another model's columns) start the window anew.
        w.push(
            50,
            &DVector::from_vec(vec![1.0, 5.0]),
            [("B", 6.0, None)].into_iter(),
            0,
        );
        let per = w.per_channel();
        assert_eq!(per.keys().collect::<Vec<_>>(), ["B"]);
        assert_eq!(per["B"].len(), 1);
        assert_eq!(per["B"][0].row.len(), 2);
    }

    /// An input held back by its sensor's place moves the lag states as the event itself does,
    /// a sensor the model does not take and an observation included.
    #[test]
    fn held_inputs_move_the_lags_as_their_events_do() {
        let mut cfg = driftwatch_thermal::model::ModelConfig::default();
        for sensor in ["ambient", "spindle_housing"] {
            cfg.temperatures
                .push(driftwatch_thermal::model::TemperatureInput {
                    sensor: sensor.into(),
                    taus_min: vec![0.0, 30.0],
                });
        }
        let t = |sensor: &str, t_ns: i64, celsius: f64| Event::Temperature {
            t_ns,
            sensor: sensor.into(),
            celsius,
        };
        let events = [
            Event::Spindle {
                t_ns: MIN,
                rpm: 12000.0,
            },
            t("spindle_housing", 2 * MIN, 24.0),
            t("ambient", 3 * MIN, 20.0),
            t("coolant", 4 * MIN, 18.0),
            t("spindle_housing", 9 * MIN, 27.5),
            Event::Observation {
                t_ns: 15 * MIN,
                channel: "EZ0B".into(),
                value: 3.0,
                sigma: None,
            },
            Event::Spindle {
                t_ns: 20 * MIN,
                rpm: 0.0,
            },
            t("ambient", 40 * MIN, 21.0),
        ];
        let mut by_event = Features::new(&cfg, &BTreeMap::new(), 0);
        let mut held = by_event.clone();
        for e in &events {
            by_event.apply(e);
            Held::of(e, &held).apply_to(&mut held);
            assert_eq!(held.t_ns(), by_event.t_ns());
            assert_eq!(held.row(), by_event.row(), "after {e:?}");
        }
        assert_eq!(held.t_ref_c(), by_event.t_ref_c());
        assert!(held.row().iter().any(|x| *x != 0.0 && *x != 1.0));
    }

    #[test]
    fn it_waits_for_cycles_fits_and_then_asks_for_a_cycle_when_uncertain() {
        let mut policy = PredictionPolicy {
            min_cycles: 4,
            ..Default::default()
        };
        policy
            .model
            .temperatures
            .push(driftwatch_thermal::model::TemperatureInput {
                sensor: "ambient".into(),
                taus_min: vec![0.0],
            });
        let mut m = LiveModel::new(policy);
        assert_eq!(m.view().status, "waiting");
        m.input(Event::Spindle {
            t_ns: 0,
            rpm: 20000.0,
        });
        let mut note = None;
        for i in 0..6 {
            let t = (i * 30 + 5) * MIN;
            // A 12-min lag of 40 um seen in every error.
            let v = 40.0 * (1.0 - (-units::ns_to_min(t) / 12.0).exp());
            let errors: BTreeMap<String, f64> =
                TABLE_BC_ERRORS.iter().map(|n| (n.to_string(), v)).collect();
            let sigma = TABLE_BC_ERRORS
                .iter()
                .map(|n| (n.to_string(), 0.3))
                .collect();
            if let Some(n) = m.observe(t, &errors, &sigma) {
                note = Some((i, n));
            }
        }
        let (i, note) = note.expect("a fit");
        assert_eq!(i, 3, "{note}");
        assert!(note.contains("fitted on 4"), "{note}");
        assert!(note.contains("not logged, left out: ambient"), "{note}");
        let v = m.view();
        assert_eq!((v.status.as_str(), v.updates_since_fit), ("fitted", 12));
        // Six cycles after the first fit, it is fitted again on the whole history.
        for i in 6..10 {
            let t = (i * 30 + 5) * MIN;
            let errors: BTreeMap<String, f64> = TABLE_BC_ERRORS
                .iter()
                .map(|n| (n.to_string(), 40.0))
                .collect();
            let sigma = TABLE_BC_ERRORS
                .iter()
                .map(|n| (n.to_string(), 0.3))
                .collect();
            let refit = m.observe(t, &errors, &sigma);
            assert_eq!(refit.is_some(), i == 9, "cycle {i}: {refit:?}");
        }
        assert_eq!(m.view().updates_since_fit, 0);
        let p = m.predict(180 * MIN).unwrap();
        let ez = p.iter().find(|p| p.channel == "EZ0B").unwrap();
        assert!((ez.value - 40.0).abs() < 1.0, "{ez:?}");
        assert!(m.uncertain(&p, 180 * MIN).is_none(), "{p:?}");
        // Ten hours without a cycle: the offset walk passes the 3-um limit.
        let p = m.predict(780 * MIN).unwrap();
        let u = m.uncertain(&p, 780 * MIN).expect("uncertain after 10 h");
        assert!(u.sigma > 3.0);
    }

    #[test]
    fn a_model_fitted_elsewhere_predicts_from_the_first_input_until_the_own_fit() {
        // The earlier day: a 12-min lag of 40 um in EZ0B, seen every 30 min.
        let lag = |t: i64| 40.0 * (1.0 - (-units::ns_to_min(t) / 12.0).exp());
        let mut earlier = vec![Event::Spindle {
            t_ns: 0,
            rpm: 20000.0,
        }];
        for i in 0..8 {
            let t = (i * 30 + 5) * MIN;
            earlier.push(Event::Observation {
                t_ns: t,
                channel: "EZ0B".into(),
                value: lag(t),
                sigma: Some(0.3),
            });
        }
        let model = driftwatch_thermal::model::fit(&Default::default(), &earlier, None).unwrap();
        let policy = PredictionPolicy {
            min_cycles: 3,
            ..Default::default()
        };
        let mut m = LiveModel::with_initial(policy, Arc::new(model));
        assert!(m.predict(0).is_none(), "nothing before the first input");
        // Today starts a day later, with the spindle on.
        let day = 1440 * MIN;
        m.input(Event::Spindle {
            t_ns: day,
            rpm: 20000.0,
        });
        assert_eq!(m.view().status, "initial");
        let p = m.predict(day + 20 * MIN).unwrap();
        assert!((p[0].value - lag(20 * MIN)).abs() < 1.0, "{p:?}");
        let one = |v: f64| BTreeMap::from([("EZ0B".to_string(), v)]);
        for i in 0..3 {
            let t = (i * 30 + 25) * MIN;
            let note = m.observe(day + t, &one(lag(t)), &one(0.3));
            assert_eq!(note.is_some(), i == 2, "cycle {i}: {note:?}");
        }
        assert_eq!(m.view().status, "fitted");
        let p = m.predict(day + 120 * MIN).unwrap();
        assert!((p[0].value - lag(120 * MIN)).abs() < 1.0, "{p:?}");
    }

    #[test]
    fn disabled_does_nothing() {
        let mut m = LiveModel::new(PredictionPolicy {
            enabled: false,
            ..Default::default()
        });
        m.input(Event::Spindle { t_ns: 0, rpm: 1.0 });
        assert!(m.observe(0, &BTreeMap::new(), &BTreeMap::new()).is_none());
        assert!(m.predict(0).is_none());
        assert_eq!(m.view().status, "disabled");
    }

    /// A model fitted on a 40 um plateau, for judging and health checks.
    fn plateau() -> LiveModel {
        let mut m = LiveModel::new(PredictionPolicy {
            min_cycles: 4,
            ..Default::default()
        });
        m.input(Event::Spindle {
            t_ns: 0,
            rpm: 20000.0,
        });
        for i in 0..6 {
            let t = (i * 30 + 5) * MIN;
            m.observe(t, &all(40.0), &all(0.3));
        }
        assert_eq!(m.view().status, "fitted");
        m
    }

    fn all(v: f64) -> BTreeMap<String, f64> {
        TABLE_BC_ERRORS.iter().map(|n| (n.to_string(), v)).collect()
    }

    fn set(v: f64, t: i64) -> crate::compensation::CompensationSet {
        crate::compensation::CompensationSet {
            version: 1,
            valid_from_ns: t,
            source: crate::compensation::Source::Measured,
            cycle: Some(7),
            offsets: BTreeMap::new(),
            errors: crate::compensation::typed(&all(v)).unwrap(),
            sigma: crate::compensation::typed(&all(0.3)).unwrap(),
            reason: String::new(),
        }
    }

    #[test]
    fn a_model_that_misses_a_cycle_is_suspect_until_it_predicts_one_within_its_band() {
        let limits = crate::compensation::ValidationLimits::default();
        let mut m = plateau();
        let t = 200 * MIN;
        assert_eq!(m.judge(&set(40.0, t), t, t, &limits), None);
        assert!(m.suspect().is_none());
        // The cycle measured 140 um: the model said 40; suspect, and says why.
        let note = m.judge(&set(140.0, t), t, t, &limits).unwrap();
        assert!(
            note.contains("suspect") && note.contains("EZ0B predicted 40"),
            "{note}"
        );
        assert!(m.view().suspect.is_some());
        // Still missing: no new note, still suspect.
        assert_eq!(m.judge(&set(140.0, t), t, t, &limits), None);
        assert!(m.suspect().is_some());
        // It predicts the next cycle within its band: trusted again.
        let note = m.judge(&set(40.2, t), t, t, &limits).unwrap();
        assert!(note.contains("served again"), "{note}");
        assert!(m.suspect().is_none());
    }

    /// The loop rebuilds the model's view only when [`LiveModel::revision`] moved: every
    /// change of what the view shows must move it (a first input with a model fitted
    /// elsewhere, cycles taken and fitted, a verdict, a rolled-back update).
    #[test]
    fn every_change_of_the_view_moves_the_revision() {
        fn seen(m: &LiveModel) -> (u64, String) {
            (m.revision(), serde_json::to_string(&m.view()).unwrap())
        }
        fn check(m: &LiveModel, before: &mut (u64, String), what: &str) {
            let now = seen(m);
            if now.1 != before.1 {
                assert_ne!(
                    now.0, before.0,
                    "{what}: the view changed, the revision did not"
                );
            }
            *before = now;
        }
        let mut m = plateau();
        let mut before = seen(&m);
        let limits = crate::compensation::ValidationLimits::default();
        let t = 200 * MIN;
        m.judge(&set(140.0, t), t, t, &limits);
        assert!(m.suspect().is_some());
        check(&m, &mut before, "suspect");
        m.judge(&set(40.0, t), t, t, &limits);
        check(&m, &mut before, "trusted again");
        for i in 0..7 {
            m.observe(t + i * 30 * MIN, &all(40.0), &all(0.3));
            check(&m, &mut before, "observed");
        }
        m.observe(t + 300 * MIN, &all(f64::MAX), &all(1e-300));
        check(&m, &mut before, "rolled back");
        m.input(Event::Spindle {
            t_ns: t + 301 * MIN,
            rpm: 0.0,
        });
        let _ = m.predict(t + 400 * MIN);
        check(&m, &mut before, "an input and a prediction");

        let initial = plateau().predictor.unwrap().model.clone();
        let mut m = LiveModel::with_initial(PredictionPolicy::default(), initial);
        let mut before = seen(&m);
        m.input(Event::Spindle { t_ns: 0, rpm: 1.0 });
        assert_eq!(m.view().status, "initial");
        check(&m, &mut before, "a model fitted elsewhere starts");
    }

    #[test]
    fn an_update_that_leaves_the_model_unable_to_predict_is_rolled_back() {
        let mut m = plateau();
        let t = 200 * MIN;
        let before = m.predict(t).unwrap();
        // Finite, but beyond anything the filter's arithmetic survives.
        let note = m.observe(t, &all(f64::MAX), &all(1e-300)).unwrap();
        assert!(note.contains("rolled back"), "{note}");
        let after = m.predict(t).unwrap();
        assert_eq!(after, before);
        assert_eq!(m.view().validated_cycles, 6);
        // The next good cycle is taken as usual.
        assert!(m.observe(t + 30 * MIN, &all(40.0), &all(0.3)).is_none());
        assert_eq!(m.view().validated_cycles, 7);
    }
}
