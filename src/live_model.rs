//! The thermal model as one machine's loop keeps it: the input history until there are
//! enough validated cycles to fit, then a [`Predictor`] fed with every spindle change,
//! temperature sample and validated cycle. It answers what the errors are now, how certain
//! that is, and whether a cycle is needed for certainty. Pure: the loop does the I/O.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use serde::Serialize;

use crate::compensation::PredictionPolicy;
use crate::compensation::TABLE_BC_ERRORS;
use crate::scheduler::Uncertain;
use crate::thermal_model::{Event, Prediction, Predictor, ThermalModel, fit};

/// What the API shows of the model.
#[derive(Debug, Clone, Serialize)]
pub struct ModelView {
    /// `waiting` (not enough cycles yet), `fitted`, or `disabled`.
    pub status: String,
    pub message: String,
    pub validated_cycles: usize,
    pub model: Option<Arc<ThermalModel>>,
    /// Observations the online filter has taken since the fit.
    pub updates_since_fit: usize,
}

#[derive(Debug, Clone)]
pub struct LiveModel {
    policy: PredictionPolicy,
    /// Inputs and observations of the last `history_days`, for the fits.
    history: Vec<Event>,
    ok_cycles: usize,
    cycles_since_fit: usize,
    predictor: Option<Predictor>,
    updates: usize,
    message: String,
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
            history: Vec::new(),
            ok_cycles: 0,
            cycles_since_fit: 0,
            predictor: None,
            updates: 0,
            message,
        }
    }

    pub fn policy(&self) -> &PredictionPolicy {
        &self.policy
    }

    /// A spindle change or a temperature sample, in time order.
    pub fn input(&mut self, e: Event) {
        if !self.policy.enabled {
            return;
        }
        if let Some(p) = &mut self.predictor {
            p.apply(&e);
        }
        self.history.push(e);
    }

    /// A validated cycle's errors and uncertainties, known at `t_ns`. Returns a note when
    /// this observation made the first fit (or the fit failed and says why).
    pub fn observe(
        &mut self,
        t_ns: i64,
        errors: &BTreeMap<String, f64>,
        sigma: &BTreeMap<String, f64>,
    ) -> Option<String> {
        if !self.policy.enabled {
            return None;
        }
        self.ok_cycles += 1;
        self.cycles_since_fit += 1;
        let obs: Vec<Event> = errors
            .iter()
            .map(|(n, v)| Event::Observation {
                t_ns,
                channel: n.clone(),
                value: *v,
                sigma: sigma.get(n).copied(),
            })
            .collect();
        if let Some(p) = &mut self.predictor {
            for e in &obs {
                if p.apply(e) {
                    self.updates += 1;
                }
            }
        }
        self.history.extend(obs);
        let keep_from = t_ns - (self.policy.history_days * 86_400e9) as i64;
        if self.history.first().is_some_and(|e| e.t_ns() < keep_from) {
            self.history.retain(|e| e.t_ns() >= keep_from);
        }
        let due = match self.predictor {
            None => self.ok_cycles >= self.policy.min_cycles,
            Some(_) => self.cycles_since_fit >= self.policy.refit_every_cycles,
        };
        due.then(|| self.fit())
    }

    fn fit(&mut self) -> String {
        let mut cfg = self.policy.model.clone();
        // A temperature input the machine does not log is left out, and said so.
        let seen: BTreeSet<&str> = self
            .history
            .iter()
            .filter_map(|e| match e {
                Event::Temperature { sensor, .. } => Some(sensor.as_str()),
                _ => None,
            })
            .collect();
        let missing: Vec<String> = cfg
            .temperatures
            .iter()
            .filter(|t| !seen.contains(t.sensor.as_str()))
            .map(|t| t.sensor.clone())
            .collect();
        cfg.temperatures
            .retain(|t| seen.contains(t.sensor.as_str()));
        self.history
            .sort_by_key(|e| (e.t_ns(), matches!(e, Event::Observation { .. })));
        self.cycles_since_fit = 0;
        match fit(&cfg, &self.history, None) {
            Ok(model) => {
                let t0 = self.history.first().map_or(0, Event::t_ns);
                let mut p = Predictor::new(&model, t0);
                for e in &self.history {
                    p.apply(e);
                }
                let worst = model
                    .channels
                    .iter()
                    .map(|c| format!("{} {:.2}", c.name, c.rms_um))
                    .collect::<Vec<_>>()
                    .join(", ");
                let cycles = self
                    .history
                    .iter()
                    .filter(
                        |e| matches!(e, Event::Observation { channel, .. } if channel == "EZ0B"),
                    )
                    .count();
                self.message = format!(
                    "fitted on {cycles} validated cycles over {:.1} h; residual rms {worst}{}",
                    (model.to_ns - model.from_ns) as f64 / 3.6e12,
                    if missing.is_empty() {
                        String::new()
                    } else {
                        format!("; not logged, left out: {}", missing.join(", "))
                    }
                );
                self.predictor = Some(p);
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
            .filter(|p| TABLE_BC_ERRORS.contains(&p.channel.as_str()))
            .find(|p| {
                let limit = if crate::compensation::unit(&p.channel) == "urad" {
                    self.policy.cycle_above_sigma_urad
                } else {
                    self.policy.cycle_above_sigma_um
                };
                p.sigma > limit
            })
            .map(|p| Uncertain {
                since_ns: t_ns,
                error: p.channel.clone(),
                sigma: p.sigma,
            })
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
            } else if self.predictor.is_some() {
                "fitted".into()
            } else {
                "waiting".into()
            },
            message: self.message.clone(),
            validated_cycles: self.ok_cycles,
            model: self.predictor.as_ref().map(|p| p.model.clone()),
            updates_since_fit: self.updates,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: i64 = 60_000_000_000;

    #[test]
    fn it_waits_for_cycles_fits_and_then_asks_for_a_cycle_when_uncertain() {
        let mut policy = PredictionPolicy {
            min_cycles: 4,
            ..Default::default()
        };
        policy
            .model
            .temperatures
            .push(crate::thermal_model::TemperatureInput {
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
            let v = 40.0 * (1.0 - (-(t as f64) / 60e9 / 12.0).exp());
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
}
