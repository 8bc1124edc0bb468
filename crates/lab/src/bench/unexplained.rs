//! `bench unexplained`: how often the cycle diagnosis calls a clean recording "unexplained".
//! Clean recordings are the diagnosis suite's three production days (docs/physics.md 4.8) with
//! nothing injected, read at the noise the diagnosis is told; the same seeds read 20 % noisier
//! than it is told show that the flag still answers a real misfit. Per recording the flag and
//! what raised it: chi2/dof over 1.2, serial correlation (the smallest Ljung-Box p over the
//! channels, judged over all of them at 0.001), a periodic residual; next to it the rule of
//! one channel at 0.001 on its own, and the terms the search accepted.

use std::process::ExitCode;

use anyhow::Result;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_diagnosis::cycles::{
    DiagnoseOptions, Inputs, SerialCorrelation, UNEXPLAINED_P, diagnose_inputs,
};
use driftwatch_sim::scenario::Scenario;

/// The noise the diagnosis is told, um.
const SIGMA_UM: f64 = 0.5;
/// The test level per recording.
const LEVEL: f64 = UNEXPLAINED_P;
/// Where the seeds start (away from the tests' own).
const FIRST_SEED: u64 = 5000;

/// One recording's verdict.
#[derive(Debug, Clone, Default, serde::Serialize)]
struct Verdict {
    seed: u64,
    noise_um: f64,
    flagged: bool,
    chi2_dof: f64,
    /// The smallest Ljung-Box p of a channel, and over the channels tested.
    ljung_box_p: f64,
    ljung_box_p_channels: f64,
    channels: usize,
    periodic: bool,
    accepted: usize,
    error: Option<String>,
}

fn judge(machine: &str, plan: &str, seed: u64, noise_um: f64) -> Verdict {
    let mut v = Verdict {
        seed,
        noise_um,
        ..Default::default()
    };
    let run = || -> Result<driftwatch_diagnosis::cycles::Diagnosis> {
        let mut scn = Scenario::load("ambient_swing")?.diagnosis_days(machine, plan, seed);
        scn.noise.sigma_um = noise_um;
        let k = Kinematics::load(machine)?;
        let p = Plan::build(&k, &PlanConfig::load(plan)?)?;
        let sim = driftwatch_sim::simulator::simulate(&scn, &k, &p)?;
        Ok(diagnose_inputs(
            &k,
            &Inputs::of(&sim.recording()),
            &DiagnoseOptions::new(SIGMA_UM),
        )?)
    };
    match run() {
        Ok(d) => {
            v.chi2_dof = d.final_fit.chi2_dof;
            v.accepted = d.accepted.len();
            v.flagged = !d.unexplained.is_empty();
            v.periodic = d.unexplained.iter().any(|u| u.periodic.is_some());
            let serial = SerialCorrelation::of(&d.channels);
            v.ljung_box_p = serial.p;
            v.ljung_box_p_channels = serial.p_channels;
            v.channels = serial.tested;
        }
        Err(e) => v.error = Some(format!("{e:#}")),
    }
    v
}

/// `n` clean recordings on table_bc at the told noise and 20 % above it.
pub fn unexplained(n: usize, json: bool) -> Result<ExitCode> {
    let machine = "table_bc";
    let plan = Kinematics::load(machine)?.config.plan;
    let jobs: Vec<(u64, f64)> = [SIGMA_UM, 1.2 * SIGMA_UM]
        .into_iter()
        .flat_map(|noise| (0..n as u64).map(move |i| (FIRST_SEED + i, noise)))
        .collect();
    let wall = std::time::Instant::now();
    let verdicts = super::par_map(&jobs, |&(seed, noise)| judge(machine, &plan, seed, noise));
    if json {
        println!("{}", serde_json::to_string_pretty(&verdicts)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "{n} three-day recordings on {machine} (seeds {FIRST_SEED}..{}), the diagnosis told {SIGMA_UM} um; flagged \"unexplained\" at {LEVEL} per recording",
        FIRST_SEED + n as u64 - 1
    );
    for noise in [SIGMA_UM, 1.2 * SIGMA_UM] {
        let vs: Vec<&Verdict> = verdicts.iter().filter(|v| v.noise_um == noise).collect();
        let ok: Vec<&&Verdict> = vs.iter().filter(|v| v.error.is_none()).collect();
        let count = |f: &dyn Fn(&Verdict) -> bool| ok.iter().filter(|v| f(v)).count();
        let flagged = count(&|v| v.flagged);
        let chi2 = count(&|v| v.chi2_dof > 1.2);
        let lb = count(&|v| v.ljung_box_p_channels < LEVEL);
        let per_channel = count(&|v| v.ljung_box_p < LEVEL);
        let periodic = count(&|v| v.periodic);
        let accepted: usize = ok.iter().map(|v| v.accepted).sum();
        println!(
            "  read at {noise:.2} um: {flagged} of {} flagged ({:.1} %; nominal {:.1} %): chi2/dof over 1.2 {chi2}, serial correlation over the channels {lb} (one channel at {LEVEL} on its own: {per_channel}), periodic {periodic}; terms accepted {accepted}; failed {}",
            ok.len(),
            100.0 * flagged as f64 / ok.len().max(1) as f64,
            100.0 * LEVEL,
            vs.len() - ok.len()
        );
        for v in vs.iter().filter(|v| v.error.is_some()) {
            println!("    seed {}: {}", v.seed, v.error.as_deref().unwrap_or(""));
        }
    }
    println!(
        "wall time {:.0} s on {} threads",
        wall.elapsed().as_secs_f64(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    Ok(ExitCode::SUCCESS)
}
