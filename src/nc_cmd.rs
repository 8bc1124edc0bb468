//! `driftwatch nc ...`: the NC side from the command line. `nc program` is in
//! `nc_program_cmd`; `nc offsets` turns a compensation
//! set as the service serves it (the JSON of `GET /api/v1/machines/{id}/compensation`) into
//! one control's variables and the program that writes them (`driftwatch_nc::offsets`).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};

use driftwatch_core::kinematics::Kinematics;
use driftwatch_machine::compensation::CompensationSet;
use driftwatch_nc::offsets::{LINUXCNC_PINS, NcOptions, OffsetFormat, json_body, nc_offsets};

#[derive(clap::Subcommand)]
pub enum NcCmd {
    /// Write a plan's measurement cycle as a program for one control (FANUC, Siemens,
    /// HEIDENHAIN, ISO/RS274-NGC); `--check` reads it back and replays it on the simulator.
    Program(crate::nc_program_cmd::ProgramArgs),
    /// A compensation set in one control's form: its variables with units and the step from
    /// the previous set, the program that writes them, and how far the part zero moves.
    Offsets(OffsetsArgs),
}

#[derive(clap::Args)]
pub struct OffsetsArgs {
    /// fanuc, siemens, heidenhain, linuxcnc (a halcmd script for LinuxCNC's xyzbc-trt-kins or
    /// xyzac-trt-kins) or json.
    #[arg(long)]
    format: String,
    /// The machine the set belongs to: required, since two families can share error names.
    #[arg(long)]
    machine: String,
    /// The set, as `GET /api/v1/machines/{id}/compensation` returns it (`-`: stdin).
    #[arg(long)]
    from: PathBuf,
    /// The set served before it, same form: its step is stated and held to the limit.
    #[arg(long)]
    previous: Option<PathBuf>,
    /// Service configuration whose `[validation]` step limits apply (default: the shipped).
    #[arg(long)]
    config: Option<PathBuf>,
    /// FANUC: the commissioned value of a parameter written, NUMBER=MM (repeat per parameter).
    #[arg(long = "nominal", value_name = "NUMBER=MM")]
    nominal: Vec<String>,
    /// FANUC: the increment of 19700-19714, mm (0.001 IS-B, 0.0001 IS-C).
    #[arg(long, default_value_t = 0.001)]
    increment_mm: f64,
    /// FANUC: the program number.
    #[arg(long, default_value_t = 8100)]
    program_number: u32,
    /// Siemens: the swivel data record number.
    #[arg(long, default_value_t = 1)]
    carrier: u32,
    /// Siemens: -1 when the commissioned rotary axis vectors point against the machine file's.
    #[arg(long, default_value_t = 1.0, allow_hyphen_values = true)]
    axis_sign: f64,
    /// HEIDENHAIN: the first Q parameter written.
    #[arg(long, default_value_t = 1600)]
    q_base: u32,
    /// LinuxCNC: the commissioned value of a trt kinematics pin written, PIN=MM, the pin's name
    /// without the module's prefix (x-rot-point, y-rot-point, z-rot-point, x-offset, y-offset,
    /// z-offset; repeat per pin).
    #[arg(long = "pin-nominal", value_name = "PIN=MM")]
    pin_nominal: Vec<String>,
    /// The work origin of the datum-shift report, x,y,z mm in the table frame.
    #[arg(long, value_delimiter = ',', num_args = 3, allow_hyphen_values = true)]
    origin: Option<Vec<f64>>,
    /// Print everything as JSON (variables, steps, datum shift, program) instead of the program.
    #[arg(long)]
    json: bool,
}

pub fn cmd_nc(cmd: NcCmd) -> Result<ExitCode> {
    match cmd {
        NcCmd::Program(a) => crate::nc_program_cmd::cmd_nc_program(a),
        NcCmd::Offsets(a) => cmd_offsets(a),
    }
}

fn read_set(path: &Path) -> Result<CompensationSet> {
    let text = if path == Path::new("-") {
        std::io::read_to_string(std::io::stdin()).context("reading the set from stdin")?
    } else {
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?
    };
    serde_json::from_str(&text).with_context(|| {
        format!(
            "{} is not a compensation set as the service serves it",
            path.display()
        )
    })
}

fn options(a: &OffsetsArgs) -> Result<NcOptions> {
    let mut o = NcOptions {
        fanuc_increment_mm: a.increment_mm,
        fanuc_program: a.program_number,
        siemens_carrier: a.carrier,
        siemens_axis_sign: a.axis_sign,
        heidenhain_q_base: a.q_base,
        ..NcOptions::default()
    };
    for n in &a.nominal {
        let parsed = n
            .split_once('=')
            .and_then(|(p, v)| Some((p.trim().parse().ok()?, v.trim().parse().ok()?)));
        let Some((p, v)) = parsed else {
            bail!("--nominal {n}: NUMBER=MM, e.g. 19700=-123.456");
        };
        o.fanuc_nominal_mm.insert(p, v);
    }
    for n in &a.pin_nominal {
        let parsed = n.split_once('=').and_then(|(p, v)| {
            let p = p.trim();
            let v: f64 = v.trim().parse().ok()?;
            (LINUXCNC_PINS.contains(&p) && v.is_finite()).then_some((p, v))
        });
        let Some((p, v)) = parsed else {
            bail!(
                "--pin-nominal {n}: PIN=MM, e.g. x-rot-point=0, PIN one of {}",
                LINUXCNC_PINS.join(", ")
            );
        };
        o.linuxcnc_nominal_mm.insert(p.to_string(), v);
    }
    if let Some(v) = &a.origin {
        o.work_origin_mm = [v[0], v[1], v[2]];
    }
    Ok(o)
}

fn cmd_offsets(a: OffsetsArgs) -> Result<ExitCode> {
    let format = OffsetFormat::parse(&a.format)?;
    let k = Kinematics::load(&a.machine).with_context(|| format!("machine {}", a.machine))?;
    let limits = driftwatch_service::config::ServiceConfig::load(a.config.as_deref())?.validation;
    // The offsets in a file are not trusted: they are the machine's layout of its errors.
    let layout = driftwatch_machine::nc_offsets::NcLayout::of(&k);
    let mut set = read_set(&a.from)?;
    set.offsets = layout.offsets(&set.errors);
    let previous = a.previous.as_deref().map(read_set).transpose()?;
    let opts = options(&a)?;
    let o = nc_offsets(format, &k, &set, previous.as_ref(), &limits, &opts)
        .context("no NC values written")?;
    let mut out = std::io::stdout().lock();
    if a.json {
        writeln!(out, "{}", serde_json::to_string_pretty(&o)?)?;
    } else if let Some(p) = &o.program {
        write!(out, "{p}")?;
    } else {
        writeln!(
            out,
            "{}",
            serde_json::to_string_pretty(&json_body(&set, &o))?
        )?;
    }
    Ok(ExitCode::SUCCESS)
}
