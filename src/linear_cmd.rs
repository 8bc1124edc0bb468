//! `driftwatch diagonal simulate|solve` and `driftwatch correction-table`: the linear axes
//! (seeds 004 and 003). The library (`driftwatch-linear`) computes; this reads and
//! writes the files.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::Subcommand;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use driftwatch_core::geometry::Vec3;
use driftwatch_linear::axis_errors::{AxisErrors, Placed, Profile};
use driftwatch_linear::correction_table::{Face, LoopSettings, Table, n_max, run};
use driftwatch_linear::step_diagonal::{
    DIAGONALS, Estimate, Setup, conventional, diagonal_name, from_csv, robust, simulate, to_csv,
};
use driftwatch_nc::dialect::Dialect;
use driftwatch_nc::facing::{FacingPass, facing_program, x_is_diameter};

#[derive(Subcommand)]
pub enum DiagonalCmd {
    /// Simulate the laser step diagonal on a machine with random linear-axis errors and
    /// mirror tilts; write the interferometer log (CSV) and print the truth.
    Simulate(SimulateArgs),
    /// Solve an interferometer log both ways: the conventional nine-unknown formulation and
    /// the set-up-robust one (positioning measured directly).
    Solve(SolveArgs),
}

#[derive(clap::Args)]
pub struct StepArgs {
    /// Step, mm.
    #[arg(long, default_value_t = 10.0)]
    step_mm: f64,
    /// Steps per axis.
    #[arg(long, default_value_t = 12)]
    steps: usize,
    /// Interferometer noise per reading, um (weights and uncertainties).
    #[arg(long, default_value_t = 0.1)]
    noise_um: f64,
    /// Time per move (one reading), s: the clock of the drift model.
    #[arg(long, default_value_t = 5.0)]
    step_time_s: f64,
}

#[derive(clap::Args)]
pub struct SimulateArgs {
    #[command(flatten)]
    step: StepArgs,
    /// Mirror tilt off each diagonal, urad (random direction per diagonal).
    #[arg(long, default_value_t = 150.0)]
    tilt_urad: f64,
    /// Linear drift of the tool point during the runs, um/min along X, Y, Z.
    #[arg(
        long,
        value_delimiter = ',',
        num_args = 1,
        allow_negative_numbers = true,
        default_value = "0,0,0"
    )]
    drift_um_per_min: Vec<f64>,
    /// Run each diagonal out and back (the return leg reads the same points): the solve then
    /// estimates each diagonal's drift.
    #[arg(long)]
    out_and_back: bool,
    #[arg(long, default_value_t = 4)]
    seed: u64,
    #[arg(long, default_value = "diagonal.csv")]
    out: PathBuf,
    /// Measure the virtual machine of this scenario (built-in name or TOML) at its start, its
    /// linear axes as the kinematics model them (scale, squareness, ISO 230-1 components),
    /// instead of random errors.
    #[arg(long)]
    scenario: Option<String>,
    /// With --scenario: the cube's start corner in machine coordinates, mm (X,Y,Z).
    #[arg(
        long,
        value_delimiter = ',',
        allow_negative_numbers = true,
        default_value = "0,0,0"
    )]
    origin_mm: Vec<f64>,
}

#[derive(clap::Args)]
pub struct SolveArgs {
    #[command(flatten)]
    step: StepArgs,
    /// The log: `diagonal,step,axis,reading_um` (diagonal ppp|npp|pnp|ppn, or `line` for the
    /// direct positioning along the axis); steps past --steps are the return leg of an
    /// out-and-back log, detected from them.
    #[arg(long)]
    from: PathBuf,
    #[arg(long)]
    json: bool,
    /// Write the set-up-robust result as a machine geometry (JSON: the body's `geometry` for
    /// `POST /api/v1/machines/{id}/geometry`, or `driftwatch diagnose --geometry`).
    #[arg(long)]
    geometry_out: Option<PathBuf>,
    /// The measured cube's start corner in machine coordinates, mm (X,Y,Z): where the
    /// component polynomials are placed.
    #[arg(long, value_delimiter = ',', default_value = "0,0,0")]
    origin_mm: Vec<f64>,
}

#[derive(clap::Args)]
pub struct CorrectionArgs {
    /// Workpiece diameter, mm.
    #[arg(long, default_value_t = 100.0)]
    diameter_mm: f64,
    /// The NC's resolution, um (bounds the divisions: n_max = D / 2 resolution).
    #[arg(long, default_value_t = 0.1)]
    resolution_um: f64,
    /// Radial divisions of the table.
    #[arg(long, default_value_t = 50)]
    divisions: usize,
    /// A measured profile through the centre (CSV `x_mm,dz_um`, edge first): build its table.
    #[arg(long, conflicts_with = "simulate")]
    profile: Option<PathBuf>,
    /// Run the cut-measure-correct loop on a simulated face instead.
    #[arg(long)]
    simulate: bool,
    /// Tolerance dz_a, um, and the iteration cap (with --simulate).
    #[arg(long, default_value_t = 0.5)]
    tolerance_um: f64,
    #[arg(long, default_value_t = 6)]
    max_iterations: usize,
    /// Measurement noise per point, um (with --simulate).
    #[arg(long, default_value_t = 0.05)]
    noise_um: f64,
    #[arg(long, default_value_t = 3)]
    seed: u64,
    /// Write the table the NC loads (CSV `x_mm,dz_um`) here.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the corrected facing pass as a lathe program in this dialect (for a control
    /// without a built-in correction table): X as the diameter for fanuc, siemens (DIAMON)
    /// and heidenhain (turning mode), as the radius for iso (G8).
    #[arg(long, requires = "program_out", value_parser = ["fanuc", "siemens", "heidenhain", "iso"])]
    program: Option<String>,
    /// The program file.
    #[arg(long, requires = "program")]
    program_out: Option<PathBuf>,
    /// The face's nominal Z, mm: the program's Z is this minus the table's d1.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    z0_mm: f64,
    /// The facing feed of the program, mm/min.
    #[arg(long, default_value_t = 20.0)]
    feed_mm_min: f64,
}

fn setup_of(s: &StepArgs) -> Result<Setup> {
    if !(s.step_mm > 0.0 && s.noise_um > 0.0 && s.step_time_s > 0.0) || s.steps < 2 {
        bail!("--step-mm, --noise-um and --step-time-s must be positive and --steps at least 2");
    }
    Ok(Setup {
        step_mm: s.step_mm,
        steps: s.steps,
        mirror_tilt_urad: [[0.0; 2]; 4],
        noise_um: s.noise_um,
        positioning_noise_um: s.noise_um,
        drift_um_per_min: Default::default(),
        step_time_s: s.step_time_s,
        out_and_back: false,
        beam_tilt_urad: [0.0; 4],
    })
}

pub fn cmd_diagonal(cmd: DiagonalCmd) -> Result<ExitCode> {
    match cmd {
        DiagonalCmd::Simulate(a) => {
            let mut rng = ChaCha8Rng::seed_from_u64(a.seed);
            let range = a.step.step_mm * a.step.steps as f64;
            let errors = AxisErrors::random(range, &mut rng);
            let scenario_truth = match &a.scenario {
                Some(name) => Some(scenario_linear(name)?),
                None => None,
            };
            let mut setup = Setup::seed(a.tilt_urad, &mut rng);
            let base = setup_of(&a.step)?;
            setup.step_mm = base.step_mm;
            setup.steps = base.steps;
            setup.noise_um = base.noise_um;
            setup.positioning_noise_um = base.noise_um;
            setup.step_time_s = base.step_time_s;
            let [dx, dy, dz] = a.drift_um_per_min[..] else {
                bail!("--drift-um-per-min takes three numbers, X,Y,Z");
            };
            if !(dx.is_finite() && dy.is_finite() && dz.is_finite()) {
                bail!("--drift-um-per-min must be finite");
            }
            setup.drift_um_per_min = Vec3::new(dx, dy, dz);
            setup.out_and_back = a.out_and_back;
            let (runs, pos, square, scale) = match &scenario_truth {
                Some(linear) => {
                    let [ox, oy, oz] = a.origin_mm[..] else {
                        bail!("--origin-mm takes three numbers, X,Y,Z");
                    };
                    let field = Placed {
                        errors: linear,
                        origin_mm: Vec3::new(ox, oy, oz),
                    };
                    let (runs, pos) = simulate(&field, &setup, &mut rng);
                    let square = [linear.sxy, linear.sxz, linear.syz].map(|v| v * 1e6);
                    (runs, pos, square, linear.k.map(|v| v * 1e6))
                }
                None => {
                    let (runs, pos) = simulate(&errors, &setup, &mut rng);
                    (runs, pos, errors.squareness_urad, errors.scale_ppm)
                }
            };
            std::fs::write(&a.out, to_csv(&runs, &pos))
                .with_context(|| format!("writing {}", a.out.display()))?;
            let [sxy, sxz, syz] = square.map(|v| v * range * 1e-3);
            println!(
                "truth: squareness X-Y {sxy:.2}, X-Z {sxz:.2}, Y-Z {syz:.2} um over {range} mm; scale {:.2}, {:.2}, {:.2} ppm; mirror tilts {} urad",
                scale[0], scale[1], scale[2], a.tilt_urad
            );
            // Along each beam (the diagonal; the mirror's tilt changes it by its cosine).
            let along: Vec<String> = DIAGONALS
                .iter()
                .map(|s| {
                    let l = Vec3::new(s[0], s[1], s[2]) / 3f64.sqrt();
                    format!("{} {:.3}", diagonal_name(s), l.dot(&setup.drift_um_per_min))
                })
                .collect();
            println!(
                "drift {dx}, {dy}, {dz} um/min (along the beams: {} um/min); {} runs, {} s per move",
                along.join(", "),
                if a.out_and_back {
                    "out-and-back"
                } else {
                    "one-way"
                },
                setup.step_time_s
            );
            println!("wrote {}", a.out.display());
        }
        DiagonalCmd::Solve(a) => {
            let setup = setup_of(&a.step)?;
            let text = std::fs::read_to_string(&a.from)
                .with_context(|| format!("reading {}", a.from.display()))?;
            let (runs, pos) =
                from_csv(&text, setup.steps).with_context(|| format!("{}", a.from.display()))?;
            let c = conventional(&runs, &setup)?;
            let r = robust(&runs, &pos, &setup)?;
            if a.json {
                println!(
                    "{}",
                    serde_json::to_string_pretty(
                        &serde_json::json!({"conventional": c, "robust": r})
                    )?
                );
            } else {
                print_estimates(&c, &r, setup.step_mm * setup.steps as f64);
            }
            if let Some(path) = &a.geometry_out {
                let [ox, oy, oz] = a.origin_mm[..] else {
                    bail!("--origin-mm takes three numbers, X,Y,Z");
                };
                let g = r.geometry(setup.step_mm, &Vec3::new(ox, oy, oz));
                g.errors()
                    .context("the measured geometry is beyond what a machine can have")?;
                std::fs::write(path, serde_json::to_string_pretty(&g)? + "\n")
                    .with_context(|| format!("writing {}", path.display()))?;
                println!(
                    "wrote the set-up-robust geometry to {} (post it as a geometry version, or pass it to diagnose --geometry)",
                    path.display()
                );
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The linear axes of a scenario's virtual machine at its start.
fn scenario_linear(name: &str) -> Result<driftwatch_core::kinematics::LinearErrors> {
    let scn = driftwatch_sim::scenario::Scenario::load(name)
        .with_context(|| format!("scenario '{name}'"))?;
    let k = driftwatch_core::kinematics::Kinematics::load(&scn.machine)
        .with_context(|| format!("machine '{}'", scn.machine))?;
    let s = driftwatch_sim::simulator::initial_state(&scn, &k)
        .with_context(|| format!("scenario '{name}'"))?;
    Ok(s.linear)
}

fn print_estimates(c: &Estimate, r: &Estimate, range: f64) {
    if r.drift_um_per_min.is_some() {
        println!("runs: out-and-back, a drift rate estimated per diagonal");
    } else {
        println!("runs: one-way, a drift of the tool point is in the geometry below");
    }
    println!("{:<22} {:>14} {:>22}", "", "conventional", "set-up-robust");
    for (i, name) in ["squareness X-Y", "squareness X-Z", "squareness Y-Z"]
        .iter()
        .enumerate()
    {
        println!(
            "{name:<22} {:>11.2} um {:>11.2} +- {:.2} um   (over {range} mm)",
            c.squareness_um_over(i, range),
            r.squareness_um_over(i, range),
            r.squareness_sigma_urad[i] * range * 1e-3
        );
    }
    for (j, axis) in ["X", "Y", "Z"].iter().enumerate() {
        let end = |e: &Estimate| e.positioning_um[j].last().copied().unwrap_or(f64::NAN);
        println!(
            "positioning {axis} at end {:>11.2} um {:>11.2} um   (robust: measured directly)",
            end(c),
            end(r)
        );
    }
    let names = ["Y of X", "Z of X", "X of Y", "Z of Y", "X of Z", "Y of Z"];
    for (k, name) in names.iter().enumerate() {
        let peak = |e: &Estimate| {
            e.straightness_um[k]
                .iter()
                .map(|v| v.abs())
                .fold(0.0, f64::max)
        };
        println!(
            "straightness {name:<9} {:>11.2} um {:>11.2} +- {:.2} um   (largest from the end-point line; its point's largest sigma)",
            peak(c),
            peak(r),
            r.straightness_sigma_um[k]
        );
    }
    if let (Some(cd), Some(rd), Some(rs)) = (
        c.drift_um_per_min,
        r.drift_um_per_min,
        r.drift_sigma_um_per_min,
    ) {
        for (d, s) in DIAGONALS.iter().enumerate() {
            println!(
                "drift along {:<10} {:>11.3} um/min {:>7.3} +- {:.3} um/min",
                diagonal_name(s),
                cd[d],
                rd[d],
                rs[d]
            );
        }
    }
}

pub fn cmd_correction_table(a: CorrectionArgs) -> Result<ExitCode> {
    let limit = n_max(a.diameter_mm, a.resolution_um);
    println!(
        "n_max = D / (2 resolution) = {} / (2 x {} um) = {limit}",
        a.diameter_mm, a.resolution_um
    );
    let table = if let Some(p) = &a.profile {
        let text =
            std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
        let (mut xs, mut dz) = (Vec::new(), Vec::new());
        for (i, line) in text.lines().enumerate().skip(1) {
            if line.trim().is_empty() {
                continue;
            }
            let cells: Vec<&str> = line.split(',').map(str::trim).collect();
            let num = |c: Option<&&str>| -> Result<f64> {
                let s = c.with_context(|| format!("line {}: two cells expected", i + 1))?;
                s.parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .with_context(|| format!("line {}: '{s}' is not a number", i + 1))
            };
            xs.push(num(cells.first())?);
            dz.push(num(cells.get(1))?);
        }
        if xs.len() < 2 || xs.len() - 1 > limit {
            bail!(
                "{} points: at least 2 and at most n_max + 1 = {}",
                xs.len(),
                limit + 1
            );
        }
        let t = Table::from_profile(&xs, &dz);
        println!(
            "table of {} points, referenced at x = {} mm; largest correction {:.3} um",
            xs.len(),
            xs[0],
            t.max_abs_um()
        );
        t
    } else if a.simulate {
        let face = Face {
            diameter_mm: a.diameter_mm,
            straightness: Profile {
                amplitudes_um: vec![4.0, 0.0, 1.0],
            },
            feed_mm_min: 20.0,
            drift_um_per_min: 0.8,
            drift_sd_um_per_min: 0.02,
            noise_um: a.noise_um,
        };
        let settings = LoopSettings {
            divisions: a.divisions,
            resolution_um: a.resolution_um,
            tolerance_um: a.tolerance_um,
            max_iterations: a.max_iterations,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(a.seed);
        let r = run(&face, &settings, &mut rng)?;
        for c in &r.cuts {
            println!(
                "cut {}: dz_max {:.3} um (true flatness {:.3} um)",
                c.iteration, c.dz_max_um, c.true_flatness_um
            );
        }
        println!("{}", r.verdict);
        r.table
    } else {
        bail!("give --profile F.csv (a measured section) or --simulate");
    };
    if let Some(out) = &a.out {
        std::fs::write(out, table.csv()).with_context(|| format!("writing {}", out.display()))?;
        println!("table: {}", out.display());
    }
    if let (Some(d), Some(out)) = (&a.program, &a.program_out) {
        let d = Dialect::parse(d).with_context(|| format!("dialect '{d}'"))?;
        let name = match &a.profile {
            Some(p) => format!("from the section {}", p.display()),
            None => format!("from the simulated loop, seed {}", a.seed),
        };
        let text = facing_program(d, &facing_pass(&table, &name, &a)?)?;
        std::fs::write(out, text).with_context(|| format!("writing {}", out.display()))?;
        println!(
            "facing pass ({d}, X as the {}): {}",
            if x_is_diameter(d) {
                "diameter"
            } else {
                "radius"
            },
            out.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// The corrected facing pass: the table's radial points from the edge to the centre, Z the
/// nominal face minus the table's `d1` (the `dz` of `Table::csv` added), rounded to the NC's
/// resolution.
fn facing_pass(table: &Table, name: &str, a: &CorrectionArgs) -> Result<FacingPass> {
    if !(a.z0_mm.is_finite() && a.feed_mm_min > 0.0) {
        bail!("--z0-mm must be finite and --feed-mm-min positive");
    }
    let res = a.resolution_um;
    // The decimals that resolve the resolution (0.1 um: 4, 0.0001 mm).
    let decimals = (-(res * 1e-3).log10() - 1e-9).ceil().max(1.0) as usize;
    let points = table
        .x_mm
        .iter()
        .zip(&table.d1_um)
        .map(|(x, d1)| (*x, a.z0_mm - (d1 / res).round() * res * 1e-3))
        .collect();
    Ok(FacingPass {
        number: 9200,
        comments: vec![
            format!("correction table {name}"),
            format!(
                "{} points, x {} to {} mm, resolution {res} um, z = z0 - d1, z0 {} mm",
                table.x_mm.len(),
                table.x_mm.first().copied().unwrap_or(f64::NAN),
                table.x_mm.last().copied().unwrap_or(f64::NAN),
                a.z0_mm
            ),
        ],
        points,
        feed_mm_min: a.feed_mm_min,
        clearance_mm: 1.0,
        decimals,
    })
}
