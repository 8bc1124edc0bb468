//! Tool setter and R-test on the same drifting machine: a scenario's virtual machine (the
//! truth simulator) measured by both, the two brought to the same time and frame, compared.
//!
//! **The session at each of the scenario's cycle times**: a tool-setter cycle (the plan, the
//! spindle at the plan's speed), the spindle stopped and the R-test ball put in (`change_s`),
//! the R-test (BK1 and XYC by default, out and back, the spindle stopped), the tool back, a
//! second tool-setter cycle; then the scenario's spindle program resumes. The virtual machine
//! runs through all of it with the real spindle history, so the R-test sees the machine cool
//! while the ball is in.
//!
//! **Same time.** The R-test's errors refer to its readings' mean time `t_r` (a constant
//! drift of the ball is estimated with them). The tool setter's nearest cycle (at `t_s`) is
//! moved to `t_r` by driftwatch's thermal model (the grey box of `thermal_model`, fitted on
//! every tool-setter result of the day with the session's spindle history, R-test stops
//! included): `setter(t_r) = setter(t_s) + m(t_r) - m(t_s)`, where `m` is the model's value;
//! the difference's variance from the model's parameter covariance is added to the
//! setter's. This is an offline comparison: the fit sees the whole day.
//!
//! **Same frame.** Both give apparent errors: the tool setter's relative to the tool tip, the
//! R-test's relative to the ball, whose centre is calibrated against the tool reference point
//! with a standard uncertainty (`head_sigma_um`) that is part of the R-test's uncertainty. The
//! ball is taken to share the spindle's thermal growth with the tool (the tool's own growth
//! beyond the holder is not modelled in the truth either).

use std::collections::BTreeMap;

use driftwatch_core::cycle::{CycleChecks, process_cycle};
use driftwatch_core::geometry::Vec3;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::Plan;
use driftwatch_core::recording::Timed;
use driftwatch_sim::scenario::Scenario;
use driftwatch_sim::simulator::VirtualMachine;
use driftwatch_thermal::model::{Event, Features, ModelConfig, ThermalModel, fit};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::Serialize;

use driftwatch_rtest::identify::{Options, identify};
use driftwatch_rtest::instrument::{Imperfections, Instrument, Setting, calibrate};
use driftwatch_rtest::kinematic_test::{Setup, TestKind, TestSpec, simulate};
use driftwatch_rtest::process::process;

#[derive(Debug, Clone, PartialEq)]
pub struct CrossOptions {
    pub setting: Setting,
    pub tests: Vec<TestKind>,
    /// Sweep step, deg; feed, mm/min; dwell at each reading, s.
    pub step_deg: f64,
    pub feed_mm_min: f64,
    pub dwell_s: f64,
    /// Time to change between the tool and the ball, s.
    pub change_s: f64,
    /// Standard uncertainty of the ball centre's calibration against the tool, um.
    pub head_sigma_um: f64,
    /// Agreement bound in combined standard uncertainties.
    pub k: f64,
    /// Estimate the drifts during the R-test (`identify::Options::drift_rates`).
    pub drift: bool,
    /// The R-test device's departures from its design (drawn once for the day).
    pub imperfections: Imperfections,
    pub seed: u64,
}

impl Default for CrossOptions {
    fn default() -> Self {
        CrossOptions {
            setting: Setting::E,
            tests: vec![TestKind::Bk1, TestKind::Xyc],
            step_deg: 15.0,
            feed_mm_min: 2000.0,
            dwell_s: 0.5,
            change_s: 30.0,
            head_sigma_um: 0.5,
            k: 2.0,
            drift: true,
            imperfections: Imperfections::seed(),
            seed: 18,
        }
    }
}

/// One error at one session.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Compared {
    /// The tool setter's first cycle at its own time, and both moved to the R-test's time.
    pub setter: f64,
    pub setter_sigma: f64,
    pub setter_at_rtest: f64,
    pub setter_at_rtest_sigma: f64,
    pub rtest: f64,
    pub rtest_sigma: f64,
    pub difference: f64,
    pub combined_sigma: f64,
    pub z: f64,
    /// The simulator's truth at the R-test's reference time, and at the setter's.
    pub truth: f64,
    pub setter_truth: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Session {
    pub t_min: f64,
    /// Reference times from the scenario start, min: the two setter cycles, the R-test.
    pub setter_min: [f64; 2],
    pub rtest_min: f64,
    pub errors: BTreeMap<String, Compared>,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CrossCheck {
    pub machine: String,
    pub scenario: String,
    pub k: f64,
    pub sessions: Vec<Session>,
    /// Comparisons beyond `k` combined standard uncertainties, of all.
    pub beyond: usize,
    pub total: usize,
    /// Largest |z| and RMS z over all comparisons.
    pub max_abs_z: f64,
    pub rms_z: f64,
    /// The same without moving the setter to the R-test's time (nearest cycle as it is).
    pub beyond_without_transfer: usize,
    pub rms_z_without_transfer: f64,
    /// The same with the two setter cycles interpolated linearly to the R-test's time (what
    /// the service's verification does).
    pub beyond_interpolated: usize,
    pub rms_z_interpolated: f64,
    /// Sessions whose errors disagree jointly: the sum of their z^2 beyond the chi-square
    /// quantile of as many degrees of freedom at the coverage of `k` sigma (95.45 % for 2;
    /// the errors taken as independent, which the setter's are not quite).
    pub sessions_beyond_joint: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum CrossError {
    #[error("{0}")]
    Setup(String),
    #[error("tool-setter cycle at {t_min:.1} min: {reason}")]
    Cycle { t_min: f64, reason: String },
    #[error("R-test at {t_min:.1} min: {reason}")]
    Rtest { t_min: f64, reason: String },
    #[error("thermal model: {0}")]
    Model(String),
}

/// A tool-setter cycle: its reference time and, per error, value, sigma and the truth then.
type SetterResult = (i64, BTreeMap<String, (f64, f64, f64)>);

/// The scenario's spindle speed at `t_min` outside the sessions.
fn program_rpm(scn: &Scenario, t_min: f64) -> f64 {
    scn.spindle
        .iter()
        .rev()
        .find(|s| s.at_min <= t_min + 1e-9)
        .map_or(0.0, |s| s.rpm)
}

/// The virtual machine and the spindle log, advanced together.
struct Drive<'a> {
    vm: VirtualMachine,
    scn: &'a Scenario,
    spindle: Vec<Event>,
    rpm: f64,
}

impl Drive<'_> {
    fn set_rpm(&mut self, rpm: f64) {
        if rpm != self.rpm {
            self.rpm = rpm;
            self.spindle.push(Event::Spindle {
                t_ns: self.vm.now_ns(),
                rpm,
            });
        }
    }

    /// On the scenario's program up to `t_ns`, speed changes included.
    fn program_to(&mut self, t_ns: i64) {
        let start = self.vm.start_ns();
        let to_min = |t: i64| (t - start) as f64 / 60e9;
        let mut changes: Vec<f64> = self
            .scn
            .spindle
            .iter()
            .map(|s| s.at_min)
            .filter(|m| *m > to_min(self.vm.now_ns()) && *m < to_min(t_ns))
            .collect();
        changes.push(to_min(t_ns));
        for m in changes {
            let rpm = program_rpm(self.scn, to_min(self.vm.now_ns()));
            self.set_rpm(rpm);
            self.vm.advance_to(start + (m * 60e9) as i64, self.rpm);
        }
        let rpm = program_rpm(self.scn, to_min(t_ns));
        self.set_rpm(rpm);
    }

    /// One tool-setter cycle from now: its solved errors at its reference time.
    fn setter_cycle(
        &mut self,
        k: &Kinematics,
        plan: &Plan,
        number: i64,
    ) -> Result<SetterResult, String> {
        let t0 = self.vm.now_ns();
        self.set_rpm(plan.config.spindle_rpm);
        let before = self.vm.clone();
        let mut entries = Vec::new();
        for step in &plan.steps {
            self.vm
                .advance_to(t0 + (step.t_start_s * 1e9) as i64, self.rpm);
            let d = self.vm.probe(k, step, number, self.rpm);
            entries.push(Timed {
                t_ns: d.t_ns,
                msg: Ok(d.msg),
            });
        }
        self.vm
            .advance_to(t0 + (plan.machine_time_s * 1e9) as i64, self.rpm);
        let outcome = process_cycle(k, number, &entries, &CycleChecks::new(k));
        let ok = outcome.is_ok();
        let Some(sol) = outcome.solution.filter(|_| ok) else {
            return Err(outcome.reason.unwrap_or_else(|| "no solution".into()));
        };
        let truth = before
            .truth_at(k, outcome.t_ref_ns, self.rpm, None)
            .apparent;
        let errors = sol
            .errors
            .iter()
            .map(|e| {
                let t = truth.get(&e.name).copied().unwrap_or(f64::NAN);
                (e.name.clone(), (e.value, e.sigma, t))
            })
            .collect();
        Ok((outcome.t_ref_ns, errors))
    }
}

/// The thermal model's design row at each time: the spindle history applied up to it.
fn rows_at(model: &ThermalModel, spindle: &[Event], times: &[i64]) -> Vec<nalgebra::DVector<f64>> {
    let mut order: Vec<usize> = (0..times.len()).collect();
    order.sort_by_key(|&i| times[i]);
    let mut f = Features::new(&model.config, &model.t_ref_c, model.from_ns);
    let mut out = vec![nalgebra::DVector::zeros(0); times.len()];
    let mut next = 0;
    for i in order {
        while next < spindle.len() && spindle[next].t_ns() <= times[i] {
            f.apply(&spindle[next]);
            next += 1;
        }
        f.advance_to(times[i]);
        out[i] = f.row();
    }
    out
}

/// One session's measurements.
struct Raw {
    t_min: f64,
    setters: [SetterResult; 2],
    rtest: driftwatch_rtest::identify::Identification,
    truth: BTreeMap<String, f64>,
}

/// The R-test device of the day and how it sits: drawn, calibrated, the ball's offset.
struct Device {
    inst: Instrument,
    cal: driftwatch_rtest::instrument::Calibration,
    setup: Setup,
    specs: Vec<TestSpec>,
}

fn device(k: &Kinematics, opts: &CrossOptions, rng: &mut ChaCha8Rng) -> Result<Device, CrossError> {
    let inst = Instrument::drawn(opts.setting, &opts.imperfections, rng);
    let cal = calibrate(&inst, 0.05, 3, 0.0, opts.imperfections.sphericity_um, rng)
        .map_err(|e| CrossError::Setup(e.to_string()))?;
    // One ball, calibrated once: its offset from the tool is the same all day.
    let mut normal = || -> f64 {
        let z: f64 = StandardNormal.sample(rng);
        z * opts.head_sigma_um * 1e-3
    };
    let head_object_mm = Vec3::new(normal(), normal(), normal());
    let specs = opts
        .tests
        .iter()
        .map(|&t| {
            TestSpec::default_for(k, t).map(|mut s| {
                s.step_deg = opts.step_deg;
                s.feed_mm_min = opts.feed_mm_min;
                s.dwell_s = opts.dwell_s;
                s
            })
        })
        .collect::<Result<_, _>>()
        .map_err(|e| CrossError::Setup(e.to_string()))?;
    Ok(Device {
        inst,
        cal,
        setup: Setup {
            table_object_mm: Vec3::new(0.012, -0.008, 0.005),
            head_object_mm,
        },
        specs,
    })
}

impl Drive<'_> {
    /// The R-test from now, the spindle stopped: its identification and the truth at its
    /// reference time.
    fn rtest(
        &mut self,
        k: &Kinematics,
        dev: &Device,
        opts: &CrossOptions,
        rng: &mut ChaCha8Rng,
    ) -> Result<
        (
            driftwatch_rtest::identify::Identification,
            BTreeMap<String, f64>,
        ),
        String,
    > {
        let before = self.vm.clone();
        let mut processed = Vec::new();
        for spec in &dev.specs {
            let t0 = self.vm.now_ns();
            let vm = &mut self.vm;
            let mut state_at = |t, _: &[f64; driftwatch_core::kinematics::MAX_ROTARY]| {
                vm.advance_to(t, 0.0);
                vm.state(0.0)
            };
            let run = simulate(k, spec, &dev.inst, &mut state_at, t0, &dev.setup, rng)
                .map_err(|e| e.to_string())?;
            processed.push(process(k, &run, &dev.cal).map_err(|e| e.to_string())?);
        }
        let opts = Options {
            head_sigma_um: opts.head_sigma_um,
            drift_rates: opts.drift,
            ..Options::default()
        };
        let id = identify(k, &processed, &opts).map_err(|e| e.to_string())?;
        let truth = before.truth_at(k, id.t_ns, 0.0, None).apparent;
        Ok((id, truth))
    }
}

/// Every session of the scenario, and the spindle history they made.
fn measure(
    k: &Kinematics,
    scn: &Scenario,
    plan: &Plan,
    opts: &CrossOptions,
) -> Result<(Vec<Raw>, Vec<Event>, i64), CrossError> {
    let vm = VirtualMachine::new(k, scn).map_err(|e| CrossError::Setup(e.to_string()))?;
    let start = vm.start_ns();
    let mut drive = Drive {
        vm,
        scn,
        spindle: vec![Event::Spindle {
            t_ns: start,
            rpm: 0.0,
        }],
        rpm: 0.0,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let dev = device(k, opts, &mut rng)?;
    let change_ns = (opts.change_s * 1e9) as i64;
    let mut raws = Vec::new();
    let mut number = 0;
    for t_min in scn.cycle_times_min() {
        let t_ns = start + (t_min * 60e9) as i64;
        if t_ns < drive.vm.now_ns() {
            continue;
        }
        drive.program_to(t_ns);
        let cycle_error = |reason| CrossError::Cycle { t_min, reason };
        number += 1;
        let first = drive.setter_cycle(k, plan, number).map_err(cycle_error)?;
        drive.set_rpm(0.0);
        drive.vm.advance_to(drive.vm.now_ns() + change_ns, 0.0);
        let (rtest, truth) = drive
            .rtest(k, &dev, opts, &mut rng)
            .map_err(|reason| CrossError::Rtest { t_min, reason })?;
        drive.vm.advance_to(drive.vm.now_ns() + change_ns, 0.0);
        number += 1;
        let second = drive.setter_cycle(k, plan, number).map_err(cycle_error)?;
        raws.push(Raw {
            t_min,
            setters: [first, second],
            rtest,
            truth,
        });
    }
    drive.program_to(start + (scn.duration_min * 60e9) as i64);
    Ok((raws, drive.spindle, start))
}

/// The thermal model on every tool-setter result, with the sessions' spindle history.
fn fit_setter(raws: &[Raw], spindle: &[Event]) -> Result<ThermalModel, CrossError> {
    let mut events = spindle.to_vec();
    for r in raws {
        for (t, errors) in &r.setters {
            for (name, (v, s, _)) in errors {
                events.push(Event::Observation {
                    t_ns: *t,
                    channel: name.clone(),
                    value: *v,
                    sigma: Some(*s),
                });
            }
        }
    }
    events.sort_by_key(Event::t_ns);
    fit(&ModelConfig::default(), &events, None).map_err(|e| CrossError::Model(e.to_string()))
}

/// One session compared: both setter cycles, each moved to the R-test's time by the model,
/// averaged with inverse-variance weights (the model's part is shared, so its variance is
/// that of the weighted shift); and, for contrast, the nearer cycle as it is. The z scores
/// (with the move, the nearer cycle as it is, the two interpolated linearly) are appended.
fn compare(
    r: &Raw,
    model: &ThermalModel,
    spindle: &[Event],
    z: &mut [Vec<f64>; 3],
) -> (BTreeMap<String, Compared>, [i64; 3]) {
    let times = [r.setters[0].0, r.setters[1].0, r.rtest.t_ns];
    let rows = rows_at(model, spindle, &times);
    let dr = [&rows[2] - &rows[0], &rows[2] - &rows[1]];
    let mut errors = BTreeMap::new();
    for (name, est) in &r.rtest.errors {
        let (Some(a), Some(b), Some(ch)) = (
            r.setters[0].1.get(name),
            r.setters[1].1.get(name),
            model.channels.iter().find(|c| &c.name == name),
        ) else {
            continue;
        };
        let coef = nalgebra::DVector::from_column_slice(&ch.coef);
        let (wa, wb) = (1.0 / (a.1 * a.1), 1.0 / (b.1 * b.1));
        let (wa, wb) = (wa / (wa + wb), wb / (wa + wb));
        let shift = &dr[0] * wa + &dr[1] * wb;
        let moved = wa * (a.0 + dr[0].dot(&coef)) + wb * (b.0 + dr[1].dot(&coef));
        let model_var = (shift.transpose() * ch.cov_matrix() * &shift)[(0, 0)].max(0.0);
        let moved_sigma = ((wa * a.1).powi(2) + (wb * b.1).powi(2) + model_var).sqrt();
        let combined = (moved_sigma.powi(2) + est.sigma.powi(2)).sqrt();
        let near = if (times[0] - times[2]).abs() <= (times[1] - times[2]).abs() {
            a
        } else {
            b
        };
        z[0].push((est.value - moved) / combined);
        z[1].push((est.value - near.0) / (near.1 * near.1 + est.sigma.powi(2)).sqrt());
        let f = (times[2] - times[0]) as f64 / (times[1] - times[0]).max(1) as f64;
        let lin = a.0 + f * (b.0 - a.0);
        let lin_var = ((1.0 - f) * a.1).powi(2) + (f * b.1).powi(2);
        z[2].push((est.value - lin) / (lin_var + est.sigma.powi(2)).sqrt());
        errors.insert(
            name.clone(),
            Compared {
                setter: a.0,
                setter_sigma: a.1,
                setter_at_rtest: moved,
                setter_at_rtest_sigma: moved_sigma,
                rtest: est.value,
                rtest_sigma: est.sigma,
                difference: est.value - moved,
                combined_sigma: combined,
                z: (est.value - moved) / combined,
                truth: r.truth.get(name).copied().unwrap_or(f64::NAN),
                setter_truth: a.2,
            },
        );
    }
    (errors, times)
}

/// Runs the sessions of a scenario and compares the two instruments.
pub fn run(
    k: &Kinematics,
    scn: &Scenario,
    plan: &Plan,
    opts: &CrossOptions,
) -> Result<CrossCheck, CrossError> {
    let (raws, spindle, start) = measure(k, scn, plan, opts)?;
    let model = fit_setter(&raws, &spindle)?;
    let to_min = |t: i64| (t - start) as f64 / 60e9;
    let mut z = [Vec::new(), Vec::new(), Vec::new()];
    let sessions: Vec<Session> = raws
        .iter()
        .map(|r| {
            let (errors, times) = compare(r, &model, &spindle, &mut z);
            Session {
                t_min: r.t_min,
                setter_min: [to_min(times[0]), to_min(times[1])],
                rtest_min: to_min(times[2]),
                errors,
            }
        })
        .collect();
    let coverage = erf(opts.k / std::f64::consts::SQRT_2);
    let sessions_beyond_joint = sessions
        .iter()
        .filter(|s: &&Session| {
            let chi2: f64 = s.errors.values().map(|e| e.z * e.z).sum();
            chi2 > driftwatch_core::stats::chi2_quantile(coverage, s.errors.len())
        })
        .count();
    let rms = |z: &[f64]| (z.iter().map(|v| v * v).sum::<f64>() / z.len().max(1) as f64).sqrt();
    let beyond = |z: &[f64]| z.iter().filter(|v| v.abs() > opts.k).count();
    Ok(CrossCheck {
        machine: k.name.clone(),
        scenario: scn.name.clone(),
        k: opts.k,
        beyond: beyond(&z[0]),
        total: z[0].len(),
        max_abs_z: z[0].iter().map(|v| v.abs()).fold(0.0, f64::max),
        rms_z: rms(&z[0]),
        beyond_without_transfer: beyond(&z[1]),
        rms_z_without_transfer: rms(&z[1]),
        beyond_interpolated: beyond(&z[2]),
        rms_z_interpolated: rms(&z[2]),
        sessions_beyond_joint,
        sessions,
    })
}

/// The error function (Abramowitz and Stegun 7.1.26, |error| < 1.5e-7): the coverage of
/// `k` sigma is `erf(k / sqrt 2)`.
fn erf(x: f64) -> f64 {
    let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
    let y = 1.0
        - (((((1.061_405_429 * t - 1.453_152_027) * t) + 1.421_413_741) * t - 0.284_496_736) * t
            + 0.254_829_592)
            * t
            * (-x * x).exp();
    if x >= 0.0 { y } else { -y }
}

#[cfg(test)]
mod tests {
    #[test]
    fn two_sigma_covers_95_45_percent() {
        assert!((super::erf(2.0 / std::f64::consts::SQRT_2) - 0.954_499_7).abs() < 1e-6);
        assert!((super::erf(-1.0) + 0.842_700_8).abs() < 1e-6);
    }
}
