//! The lag states of every input, advanced along the timeline by exact zero-order-hold steps:
//! the design row that the fit and the filter use.

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::DVector;

use super::config::ModelConfig;
use super::events::Event;
use driftwatch_core::units::{plausible_celsius, plausible_rpm};

/// The lag states of every input, advanced along the timeline.
#[derive(Debug, Clone)]
pub struct Features {
    /// Shared by the copies: the loop copies a running predictor at every look, for the API.
    cfg: Arc<ModelConfig>,
    /// Reference of each configured sensor (in `cfg.temperatures` order): given, or its
    /// first reading.
    t_ref: Vec<Option<f64>>,
    t_ns: i64,
    rpm: f64,
    /// The spindle heat input `(|n| / n_ref)^gamma`, kept with `rpm`.
    heat: f64,
    /// Last reading of each configured sensor.
    temps: Vec<Option<f64>>,
    /// One per column after the offset, in column order (the speed term last, if any).
    x: Vec<f64>,
}

impl Features {
    /// States at `t0_ns` of a machine that has stood cold: spindle lags at zero, temperature
    /// lags at their reference. A sensor without a given reference takes its first reading.
    pub fn new(cfg: &ModelConfig, t_ref_c: &BTreeMap<String, f64>, t0_ns: i64) -> Self {
        let n = cfg.columns().len() - 1;
        Features {
            cfg: Arc::new(cfg.clone()),
            t_ref: cfg
                .temperatures
                .iter()
                .map(|s| t_ref_c.get(&s.sensor).copied())
                .collect(),
            t_ns: t0_ns,
            rpm: 0.0,
            heat: 0.0,
            temps: vec![None; cfg.temperatures.len()],
            x: vec![0.0; n],
        }
    }

    pub fn t_ns(&self) -> i64 {
        self.t_ns
    }

    /// The reference temperature of every configured sensor seen so far.
    pub fn t_ref_c(&self) -> BTreeMap<String, f64> {
        self.cfg
            .temperatures
            .iter()
            .zip(&self.t_ref)
            .filter_map(|(s, r)| r.map(|r| (s.sensor.clone(), r)))
            .collect()
    }

    /// Configured sensors that have had no reading yet.
    pub fn unseen_sensors(&self) -> Vec<String> {
        self.cfg
            .temperatures
            .iter()
            .zip(&self.temps)
            .filter(|(_, t)| t.is_none())
            .map(|(s, _)| s.sensor.clone())
            .collect()
    }

    /// Visit every state with the input it follows and its time constant in seconds (0: no
    /// lag), in column order, without allocating (this runs for every event).
    fn for_each_state(&mut self, mut f: impl FnMut(&mut f64, f64, f64)) {
        let mut i = 0;
        for t in &self.cfg.taus_min {
            f(&mut self.x[i], self.heat, t * 60.0);
            i += 1;
        }
        for (k, s) in self.cfg.temperatures.iter().enumerate() {
            let d = match (self.temps[k], self.t_ref[k]) {
                (Some(t), Some(r)) => t - r,
                _ => 0.0,
            };
            for t in &s.taus_min {
                f(&mut self.x[i], d, t * 60.0);
                i += 1;
            }
        }
        if self.cfg.instant_speed {
            f(&mut self.x[i], (self.rpm / self.cfg.n_ref_rpm).powi(2), 0.0);
        }
    }

    /// Advance to `t_ns` with the inputs held (exact zero-order hold). Time never runs back.
    pub fn advance_to(&mut self, t_ns: i64) {
        if t_ns <= self.t_ns {
            return;
        }
        let dt = (t_ns - self.t_ns) as f64 / 1e9;
        self.for_each_state(|x, u, tau| {
            if tau <= 0.0 {
                *x = u;
            } else {
                let a = (-dt / tau).exp();
                *x = a * *x + (1.0 - a) * u;
            }
        });
        self.t_ns = t_ns;
    }

    fn refresh_instant(&mut self) {
        self.for_each_state(|x, u, tau| {
            if tau <= 0.0 {
                *x = u;
            }
        });
    }

    pub fn set_rpm(&mut self, t_ns: i64, rpm: f64) {
        self.advance_to(t_ns);
        if plausible_rpm(rpm) && rpm != self.rpm {
            self.rpm = rpm;
            self.heat = (rpm.abs() / self.cfg.n_ref_rpm).powf(self.cfg.gamma);
            self.refresh_instant();
        }
    }

    pub fn set_temperature(&mut self, t_ns: i64, sensor: &str, celsius: f64) {
        match self.sensor_index(sensor) {
            Some(k) => self.set_sensor(t_ns, k, celsius),
            None => self.advance_to(t_ns),
        }
    }

    /// Where a sensor sits among the configured ones (`None`: not configured, its readings
    /// only move the time on): an input held for later may keep this instead of the name.
    pub fn sensor_index(&self, sensor: &str) -> Option<usize> {
        self.cfg
            .temperatures
            .iter()
            .position(|s| s.sensor == sensor)
    }

    /// A reading of the configured sensor `k` ([`Features::sensor_index`]); an index out of
    /// range only moves the time on.
    pub fn set_sensor(&mut self, t_ns: i64, k: usize, celsius: f64) {
        self.advance_to(t_ns);
        if k < self.temps.len() && plausible_celsius(celsius) {
            self.temps[k] = Some(celsius);
            self.t_ref[k].get_or_insert(celsius);
            self.refresh_instant();
        }
    }

    /// Apply an input event (observations do not change the inputs).
    pub fn apply(&mut self, e: &Event) {
        match e {
            Event::Spindle { t_ns, rpm } => self.set_rpm(*t_ns, *rpm),
            Event::Temperature {
                t_ns,
                sensor,
                celsius,
            } => self.set_temperature(*t_ns, sensor, *celsius),
            Event::Observation { t_ns, .. } => self.advance_to(*t_ns),
        }
    }

    /// The design row at the current time: `[1, states...]`.
    pub fn row(&self) -> DVector<f64> {
        let mut r = Vec::with_capacity(self.x.len() + 1);
        r.push(1.0);
        r.extend_from_slice(&self.x);
        DVector::from_vec(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::units;

    const MIN: i64 = units::NS_PER_MIN;

    #[test]
    fn zero_order_hold_is_exact_for_any_step() {
        let cfg = ModelConfig::default();
        let mut a = Features::new(&cfg, &BTreeMap::new(), 0);
        let mut b = a.clone();
        a.set_rpm(0, 20000.0);
        b.set_rpm(0, 20000.0);
        a.advance_to(100 * MIN);
        for m in 1..=100 {
            b.advance_to(m * MIN);
        }
        for (x, y) in a.row().iter().zip(b.row().iter()) {
            assert!((x - y).abs() < 1e-12);
        }
        // The 6-min lag after 100 min at full heat: 1 - e^(-100/6).
        assert!((a.row()[1] - (1.0 - (-100.0f64 / 6.0).exp())).abs() < 1e-12);
    }
}
