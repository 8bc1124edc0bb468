//! `driftwatch nc program`: a plan as a program for one control, optionally read back and
//! replayed on the truth simulator against the plan itself.

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::ValueEnum;

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_lab::nc_check::against_truth;
use driftwatch_nc::dialect::Dialect;
use driftwatch_nc::program::{ProgramOptions, write};
use driftwatch_sim::scenario::Scenario;

#[derive(Clone, Copy, ValueEnum)]
pub enum DialectArg {
    /// FANUC 30i/31i/0i, custom macro B: G31 skip, #5061-#5063.
    Fanuc,
    /// Siemens SINUMERIK 840D sl / ONE: MEAS=1, $AA_MM, $AC_MEA.
    Siemens,
    /// HEIDENHAIN TNC (Klartext): TCH PROBE 0, Q parameters.
    Heidenhain,
    /// RS274/NGC as LinuxCNC runs it: G38.2, #5061-#5063, (LOG,...).
    Iso,
}

impl From<DialectArg> for Dialect {
    fn from(d: DialectArg) -> Dialect {
        match d {
            DialectArg::Fanuc => Dialect::Fanuc,
            DialectArg::Siemens => Dialect::Siemens,
            DialectArg::Heidenhain => Dialect::Heidenhain,
            DialectArg::Iso => Dialect::Iso,
        }
    }
}

#[derive(clap::Args)]
pub struct ProgramArgs {
    /// Machine TOML, or a built-in name (table_bc, head_b_table_c, table_d45_c,
    /// head_d45_table_c, trunnion_ac).
    #[arg(long)]
    machine: String,
    /// Plan TOML or built-in name; default the machine file's `plan`.
    #[arg(long)]
    plan: Option<String>,
    #[arg(long, value_enum)]
    dialect: DialectArg,
    /// Write the program here (default: standard output).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Program number (FANUC O number; DW<number> elsewhere).
    #[arg(long, default_value_t = 9100)]
    number: u32,
    /// M code that unclamps the rotary axes before an index; "" when the PLC does it
    /// (default M11; none in the ISO dialect: LinuxCNC defines no clamp M code, a machine that
    /// clamps maps a user M code M100-M199 to its script).
    #[arg(long)]
    unclamp: Option<String>,
    /// M code that clamps them after (default M10; none in the ISO dialect).
    #[arg(long)]
    clamp: Option<String>,
    /// Decimals of positions and angles: the control's least input increment.
    #[arg(long, default_value_t = 3)]
    decimals: usize,
    /// First result variable (default per dialect: #601, R101, Q1601, #1001).
    #[arg(long)]
    first_result: Option<u32>,
    /// Read the program back, replay it on the truth simulator next to the plan itself and
    /// print both solves and run times.
    #[arg(long)]
    check: bool,
    /// Scenario of --check (default `patent` on table_bc, `patent_<machine>` otherwise).
    #[arg(long)]
    scenario: Option<String>,
    /// Minutes of warm-up at the plan's spindle speed before the checked cycle.
    #[arg(long, default_value_t = 40.0)]
    warm_min: f64,
}

pub fn cmd_nc_program(a: ProgramArgs) -> Result<ExitCode> {
    let k = Kinematics::load(&a.machine)?;
    let plan_name = a.plan.clone().unwrap_or_else(|| k.config.plan.clone());
    let cfg = PlanConfig::load(&plan_name)?;
    let plan = Plan::build(&k, &cfg)?;
    let d: Dialect = a.dialect.into();
    let mut opts = ProgramOptions::defaults(d);
    opts.number = a.number;
    if let Some(m) = &a.unclamp {
        opts.unclamp = m.clone();
    }
    if let Some(m) = &a.clamp {
        opts.clamp = m.clone();
    }
    opts.decimals = a.decimals;
    if let Some(f) = a.first_result {
        if f < 3 {
            bail!(
                "--first-result must be at least 3 (the two before it hold the step and done flags)"
            );
        }
        opts.first_result = f;
    }
    let p = write(&k, &plan, d, &opts)?;
    match &a.out {
        Some(path) => {
            std::fs::write(path, &p.text).with_context(|| format!("writing {}", path.display()))?
        }
        None => std::io::stdout().write_all(p.text.as_bytes())?,
    }
    if !a.check {
        return Ok(ExitCode::SUCCESS);
    }
    let scenario = a.scenario.clone().unwrap_or_else(|| {
        if k.name == "table_bc" {
            "patent".into()
        } else {
            format!("patent_{}", k.name)
        }
    });
    let scn = Scenario::load(&scenario)?;
    let c = against_truth(&k, &plan, &p.text, d, &scn, a.warm_min)?;
    // The report goes where the program does not.
    let mut r: Box<dyn std::io::Write> = if a.out.is_some() {
        Box::new(std::io::stdout())
    } else {
        Box::new(std::io::stderr())
    };
    writeln!(
        r,
        "{d} program for plan {} on {}: {} approaches replayed on scenario {scenario} after {} min",
        plan.name, k.name, c.approaches, a.warm_min
    )?;
    writeln!(
        r,
        "{:>8} {:>14} {:>14} {:>12} {:>10}",
        "error", "plan", "program", "difference", "sigma"
    )?;
    for e in &c.errors {
        writeln!(
            r,
            "{:>8} {:>11.4} {:<2} {:>11.4} {:<2} {:>12.5} {:>10.3}",
            e.name,
            e.plan,
            e.unit,
            e.program,
            e.unit,
            e.program - e.plan,
            e.sigma
        )?;
    }
    writeln!(
        r,
        "run time: program {:.3} s, plan {:.3} s at the same trips ({:.3} s at nominal trips)",
        c.program_time_s, c.plan_time_at_trips_s, c.plan_time_s
    )?;
    writeln!(
        r,
        "largest difference: {:.5} um, {:.5} urad",
        c.worst("um"),
        c.worst("urad")
    )?;
    Ok(ExitCode::SUCCESS)
}
