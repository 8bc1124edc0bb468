//! Thermal response as sums of first-order lags of heat inputs (docs/physics.md 2.1):
//!
//! `y(t) = offset + sum_j K_j * lag(u; tau_j) + sum_m G_m * lag(T_amb - T_ref; tau_m)
//!        + c * (n / n_ref)^2`,
//! `u = (n / n_ref)^gamma` from the complete spindle-speed log (measurement spins included).
//!
//! Lags advance by exact zero-order-hold steps, `x <- e^(-dt/tau) x + (1 - e^(-dt/tau)) u`,
//! stable for any step.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LagTerm {
    /// Steady-state gain (channel units per unit input).
    pub gain: f64,
    /// Time constant, min.
    pub tau_min: f64,
}

/// One output channel of a thermal model.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Channel {
    /// Constant part.
    pub offset: f64,
    /// Lags of the spindle heat input `u = (n / n_ref)^gamma`.
    pub spindle: Vec<LagTerm>,
    /// Lags of the ambient temperature deviation `T_amb - T_ref` (gain per K).
    pub ambient: Vec<LagTerm>,
    /// Instantaneous speed term at `n_ref` (scales with `(n / n_ref)^2`, no lag).
    pub instant: f64,
}

/// Inputs shared by every channel of a model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputConfig {
    /// Reference spindle speed, min^-1.
    pub n_ref_rpm: f64,
    /// Exponent of the spindle heat input.
    pub gamma: f64,
    /// Ambient reference temperature, deg C.
    pub t_ref_c: f64,
}

impl Default for InputConfig {
    fn default() -> Self {
        InputConfig {
            n_ref_rpm: 20000.0,
            gamma: 1.5,
            t_ref_c: 20.0,
        }
    }
}

impl InputConfig {
    pub fn heat(&self, rpm: f64) -> f64 {
        (rpm.abs() / self.n_ref_rpm).powf(self.gamma)
    }
    pub fn instant_factor(&self, rpm: f64) -> f64 {
        (rpm / self.n_ref_rpm).powi(2)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Input {
    Spindle,
    Ambient,
}

#[derive(Debug, Clone, Copy)]
struct Lag {
    input: Input,
    tau_s: f64,
    x: f64,
}

/// A set of channels sharing lag states: each distinct (input, tau) is integrated once.
#[derive(Debug, Clone)]
pub struct LagModel {
    pub inputs: InputConfig,
    names: Vec<String>,
    channels: Vec<Channel>,
    lags: Vec<Lag>,
    /// Per channel: (lag index, gain).
    terms: Vec<Vec<(usize, f64)>>,
}

impl LagModel {
    pub fn new(inputs: InputConfig, channels: Vec<(String, Channel)>) -> Self {
        let mut lags: Vec<Lag> = Vec::new();
        let mut terms = Vec::new();
        let mut names = Vec::new();
        let mut chans = Vec::new();
        for (name, ch) in channels {
            let mut t = Vec::new();
            let all = ch
                .spindle
                .iter()
                .map(|l| (Input::Spindle, l))
                .chain(ch.ambient.iter().map(|l| (Input::Ambient, l)));
            for (input, term) in all {
                let tau_s = term.tau_min * 60.0;
                let idx = match lags
                    .iter()
                    .position(|l| l.input == input && l.tau_s == tau_s)
                {
                    Some(i) => i,
                    None => {
                        lags.push(Lag {
                            input,
                            tau_s,
                            x: 0.0,
                        });
                        lags.len() - 1
                    }
                };
                t.push((idx, term.gain));
            }
            terms.push(t);
            names.push(name);
            chans.push(ch);
        }
        LagModel {
            inputs,
            names,
            channels: chans,
            lags,
            terms,
        }
    }

    pub fn names(&self) -> &[String] {
        &self.names
    }

    pub fn index(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Advance by `dt_s` with the spindle at `rpm` and the ambient at `ambient_c`, both held.
    pub fn advance(&mut self, dt_s: f64, rpm: f64, ambient_c: f64) {
        if dt_s <= 0.0 {
            return;
        }
        let u_sp = self.inputs.heat(rpm);
        let u_amb = ambient_c - self.inputs.t_ref_c;
        for l in &mut self.lags {
            let u = match l.input {
                Input::Spindle => u_sp,
                Input::Ambient => u_amb,
            };
            let a = (-dt_s / l.tau_s).exp();
            l.x = a * l.x + (1.0 - a) * u;
        }
    }

    /// Start from the steady state of constant inputs (e.g. a machine cold at ambient).
    pub fn settle(&mut self, rpm: f64, ambient_c: f64) {
        let u_sp = self.inputs.heat(rpm);
        let u_amb = ambient_c - self.inputs.t_ref_c;
        for l in &mut self.lags {
            l.x = match l.input {
                Input::Spindle => u_sp,
                Input::Ambient => u_amb,
            };
        }
    }

    /// Value of channel `i` with the spindle at `rpm` now.
    pub fn value(&self, i: usize, rpm: f64) -> f64 {
        let ch = &self.channels[i];
        let lagged: f64 = self.terms[i].iter().map(|(l, g)| g * self.lags[*l].x).sum();
        ch.offset + lagged + ch.instant * self.inputs.instant_factor(rpm)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(taus: &[f64]) -> LagModel {
        let ch = Channel {
            spindle: taus
                .iter()
                .map(|t| LagTerm {
                    gain: 1.0,
                    tau_min: *t,
                })
                .collect(),
            ..Default::default()
        };
        LagModel::new(InputConfig::default(), vec![("y".into(), ch)])
    }

    #[test]
    fn zoh_step_is_exact_for_a_constant_input() {
        let mut a = model(&[12.0]);
        let mut b = model(&[12.0]);
        a.advance(1800.0, 20000.0, 20.0);
        for _ in 0..1800 {
            b.advance(1.0, 20000.0, 20.0);
        }
        let exact = 1.0 - (-30.0f64 / 12.0).exp();
        assert!((a.value(0, 0.0) - exact).abs() < 1e-12);
        assert!((b.value(0, 0.0) - exact).abs() < 1e-12);
    }

    #[test]
    fn shared_lags_are_integrated_once() {
        let ch = Channel {
            spindle: vec![LagTerm {
                gain: 2.0,
                tau_min: 10.0,
            }],
            ..Default::default()
        };
        let m = LagModel::new(
            InputConfig::default(),
            vec![("a".into(), ch.clone()), ("b".into(), ch)],
        );
        assert_eq!(m.lags.len(), 1);
    }

    #[test]
    fn heat_input_follows_the_speed_power_law() {
        let i = InputConfig::default();
        assert!((i.heat(10000.0) - 0.5f64.powf(1.5)).abs() < 1e-15);
        assert_eq!(i.heat(0.0), 0.0);
    }
}
