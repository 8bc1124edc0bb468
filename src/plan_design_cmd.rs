//! `driftwatch plan design`: parse, call `driftwatch_core::plan_design::design`, print the
//! Pareto front and the chosen plan, write it as plan TOML.

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::ValueEnum;

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::PlanConfig;
use driftwatch_core::plan_design::{
    AliasLimit, DEFAULT_ALIAS_FRACTION, DesignOptions, PlanEvaluation, Weight, design,
};

#[derive(Clone, Copy, ValueEnum)]
pub enum WeightArg {
    /// Each error in its own unit: um for positions, urad for orientations.
    Unit,
    /// Orientation errors times --lever-mm: their effect at the tool tip, um.
    Tip,
}

#[derive(clap::Args)]
pub struct DesignArgs {
    /// Machine TOML, or a built-in name (table_bc, head_b_table_c, table_d45_c,
    /// head_d45_table_c, trunnion_ac).
    #[arg(long)]
    machine: String,
    /// Machine-time budget, s (default: the reference plan's machine time).
    #[arg(long)]
    budget_s: Option<f64>,
    /// One-reading standard uncertainty, um (default: the machine's).
    #[arg(long)]
    sigma_um: Option<f64>,
    /// How errors of different units are compared.
    #[arg(long, value_enum, default_value = "unit")]
    weight: WeightArg,
    /// Lever arm of --weight tip, mm.
    #[arg(long, default_value_t = 100.0)]
    lever_mm: f64,
    /// Largest bias of any error per 1 um/min of tool-tip drift, in the objective's units
    /// (default: 0.1 times the plan's own worst sigma).
    #[arg(long)]
    max_alias: Option<f64>,
    /// Plan whose probing parameters the designs use, whose time is the default budget and
    /// which is placed against the front (built-in name or TOML path; default the machine's
    /// own plan).
    #[arg(long)]
    reference: Option<String>,
    /// Largest repeats of a pose to try.
    #[arg(long, default_value_t = 4)]
    max_repeats: u32,
    /// Accept plans that hold a setter nuisance the reference estimates (their errors then
    /// take any setter movement one-to-one).
    #[arg(long)]
    allow_held_setter: bool,
    /// Write the chosen plan here (plan TOML, as `--plan FILE` reads it).
    #[arg(long)]
    out: Option<PathBuf>,
}

pub fn cmd_plan_design(a: DesignArgs) -> Result<ExitCode> {
    let k = Kinematics::load(&a.machine)?;
    let reference = PlanConfig::load(a.reference.as_deref().unwrap_or(&k.config.plan))?;
    let mut opts = DesignOptions::new(a.sigma_um.unwrap_or(k.setter.sigma_um));
    opts.weight = match a.weight {
        WeightArg::Unit => Weight::Unit,
        WeightArg::Tip => Weight::Tip {
            lever_mm: a.lever_mm,
        },
    };
    opts.max_alias = match a.max_alias {
        Some(x) => AliasLimit::Absolute(x),
        None => AliasLimit::Relative(DEFAULT_ALIAS_FRACTION),
    };
    opts.budget_s = a.budget_s;
    opts.max_repeats = a.max_repeats;
    opts.keep_reference_nuisances = !a.allow_held_setter;
    let d = design(&k, &reference, &opts)?;
    let mut out = std::io::stdout().lock();
    let unit = &d.chosen.objective_unit;
    writeln!(
        out,
        "plan design for '{}': sigma {} um, objective worst sigma ({unit}), alias limit {}, budget {:.1} s",
        k.name,
        opts.sigma_um,
        match opts.max_alias {
            AliasLimit::Absolute(x) => format!("{x} {unit} per um/min"),
            AliasLimit::Relative(f) => format!("{f} x worst sigma per um/min"),
        },
        d.budget_s
    )?;
    writeln!(
        out,
        "{} candidate pose-approach units; {} plans evaluated, {} feasible",
        d.units, d.evaluated, d.feasible
    )?;
    writeln!(out, "Pareto front (worst sigma against machine time):")?;
    writeln!(
        out,
        "{:>7} {:>4} {:>8}  {:<6} {:>9}  poses",
        "time/s", "n", "worst", "error", "alias"
    )?;
    for e in &d.front {
        row(&mut out, &k, e)?;
    }
    writeln!(out, "chosen (best within {:.1} s):", d.budget_s)?;
    row(&mut out, &k, &d.chosen)?;
    for s in &d.chosen.sigmas {
        writeln!(out, "  {:>6} {:>8.3} {}", s.name, s.sigma, s.unit)?;
    }
    writeln!(
        out,
        "  estimated besides: {}",
        d.chosen.nuisances.join(", ")
    )?;
    let r = &d.reference;
    writeln!(out, "reference '{}':", r.evaluation.config.name)?;
    row(&mut out, &k, &r.evaluation)?;
    match (r.front_worst_at_time, r.ratio) {
        (Some(w), Some(q)) => writeln!(
            out,
            "  the front reaches {w:.3} {unit} in {:.1} s: the reference's worst sigma is {:.1} % above it",
            r.evaluation.machine_time_s,
            (q - 1.0) * 100.0
        )?,
        _ => writeln!(out, "  no front plan is as fast")?,
    }
    if let Some(t) = r.front_time_at_worst {
        writeln!(
            out,
            "  the front reaches its worst sigma {:.3} {unit} in {t:.1} s ({:.0} % of its time)",
            r.evaluation.worst,
            t / r.evaluation.machine_time_s * 100.0
        )?;
    }
    if !r.evaluation.alias_ok() {
        writeln!(
            out,
            "  (the reference itself aliases drift beyond the limit: {:.3} on {})",
            r.evaluation.max_alias, r.evaluation.max_alias_at
        )?;
    }
    if let Some(path) = &a.out {
        let text = toml::to_string(&d.chosen.config).context("writing the plan as TOML")?;
        let header = format!(
            "# Designed by `driftwatch plan design --machine {}`: {:.1} s, worst sigma {:.3} {unit} ({}).\n",
            a.machine, d.chosen.machine_time_s, d.chosen.worst, d.chosen.worst_error
        );
        std::fs::write(path, header + &text)
            .with_context(|| format!("writing {}", path.display()))?;
        writeln!(out, "wrote {}", path.display())?;
    }
    Ok(ExitCode::SUCCESS)
}

fn row(out: &mut impl std::io::Write, k: &Kinematics, e: &PlanEvaluation) -> std::io::Result<()> {
    writeln!(
        out,
        "{:>7.1} {:>4} {:>8.3}  {:<6} {:>9.2e}  {}",
        e.machine_time_s,
        e.approaches,
        e.worst,
        e.worst_error,
        e.max_alias,
        e.poses_text(k)
    )
}
