//! A measurement plan as a program for one control: safe moves, the spindle at the plan's
//! speed, each approach as a skip (probing) move at its feed with a bounded travel, the latched
//! coordinate stored under the step, a failed trip detected and reported.
//!
//! The program follows the plan's move list exactly (`Plan::moves`), so its run time is the
//! plan's machine time and `reader` + a replay can check that the program measures what the
//! plan measures. Each approach is preceded by a comment naming its step (`STEP n label`), and
//! its latched coordinate goes to result variable `first + n - 1`.
//!
//! What each dialect assumes of the control, and where each variable comes from, is in
//! `docs/nc.md`. In short:
//! - **FANUC** (custom macro B): the program claims work offset `G54.1 P48` with a zero origin
//!   (written by `G10 L20`) so that its coordinates are machine coordinates; `G31` skips; the
//!   skip position is read from `#5061`-`#5063`; a move that ends at its end point did not
//!   trip and raises macro alarm `#3000`.
//! - **Siemens** 840D: `G500` (no settable frame); `MEAS=1` deletes the distance to go at the
//!   probe's edge; `$AC_MEA[1]` says whether it tripped; `$AA_MM[...]` is the latched machine
//!   coordinate; a line per approach goes to a log file with `WRITE`.
//! - **HEIDENHAIN** (Klartext): `TCH PROBE 0` from a pre-position, the probed coordinate in a
//!   Q parameter; the probing feed and the measuring range come from the touch-probe table, so
//!   the program names the row values it needs (`PROBE TABLE F.. DIST..`); the control stops
//!   with an error when no contact is made within the range.
//! - **ISO** (RS274/NGC as LinuxCNC runs it): `G38.2` probes and errors out without contact;
//!   `#5061`-`#5063` hold the latched position; `(LOG,n value)` writes a line per approach to a
//!   file and `(DEBUG,DW n x y z)` sends the step number and the latched position to the
//!   control's message channel, where a gateway reads each trip as it happens; the program
//!   claims `G59.3` with a zero origin.

use thiserror::Error;

use driftwatch_core::geometry::wrap_deg;
use driftwatch_core::kinematics::{Kinematics, MAX_ROTARY};
use driftwatch_core::measurement::Axis;
use driftwatch_core::plan::beam_contacts;
use driftwatch_core::plan::{MoveKind, Plan};

use crate::blocks::{Blocks, fmt_plain};
use crate::dialect::Dialect;

#[derive(Debug, Error, PartialEq)]
pub enum ProgramError {
    #[error(
        "rotary axis {0} has no NC address in this dialect (A, B, C, or D programmed as B); \
         rename it in the machine file"
    )]
    NoAddress(String),
    #[error("rotary axes {0} and {1} would share the NC address {2}")]
    SharedAddress(String, String, char),
    #[error("decimals must be 1..=5, not {0}")]
    Decimals(usize),
    #[error(
        "clamp code '{0}': one M code (M10, M101, ...) or \"\" for none, and not one of M0-M9 or \
         M30, which stop, end, turn the spindle, change the tool or switch coolant"
    )]
    ClampCode(String),
    #[error("plan '{plan}' has a probing move without a step; it cannot be written")]
    ProbeWithoutStep { plan: String },
    #[error(
        "plan '{plan}' on machine '{machine}' moves the tool through the setter's beam outside a \
         probing move ({contacts} such moves), first {first}"
    )]
    StrikesBeam {
        plan: String,
        machine: String,
        contacts: usize,
        first: String,
    },
}

/// Choices a plant makes when it loads the program; the defaults are documented in
/// `docs/nc.md` and by `driftwatch nc program --help`.
#[derive(Debug, Clone, PartialEq)]
pub struct ProgramOptions {
    /// FANUC `O` number, the program name elsewhere (`DW<number>`).
    pub number: u32,
    /// M code that unclamps the rotary axes before an index (empty: the PLC does it).
    pub unclamp: String,
    /// M code that clamps them after.
    pub clamp: String,
    /// Decimals of positions and angles: the control's least input increment (3: 0.001 mm).
    pub decimals: usize,
    /// The first result variable (FANUC `#`, Siemens `R`, HEIDENHAIN `Q`, ISO `#`).
    pub first_result: u32,
}

impl ProgramOptions {
    pub fn defaults(d: Dialect) -> Self {
        // LinuxCNC, the control the ISO dialect is written for, defines no clamp M code (it
        // stops at an unknown one): a machine that clamps maps a user M code to its script.
        let (unclamp, clamp) = match d {
            Dialect::Iso => ("", ""),
            _ => ("M11", "M10"),
        };
        ProgramOptions {
            number: 9100,
            unclamp: unclamp.into(),
            clamp: clamp.into(),
            decimals: 3,
            first_result: match d {
                // FANUC common variables #500-#999 are kept over power-off.
                Dialect::Fanuc => 601,
                Dialect::Siemens => 101,
                // TNC: Q1600-Q1999 are free for the user.
                Dialect::Heidenhain => 1601,
                Dialect::Iso => 1001,
            },
        }
    }
}

/// Where one approach's latched coordinate is left.
#[derive(Debug, Clone, PartialEq)]
pub struct ResultSlot {
    /// 1-based approach number in the program.
    pub number: usize,
    pub label: String,
    /// The variable as the control names it (`#601`, `R101`, `Q1601`, `#1001`).
    pub variable: String,
    pub axis: Axis,
}

#[derive(Debug, Clone)]
pub struct Program {
    pub dialect: Dialect,
    pub text: String,
    pub results: Vec<ResultSlot>,
    /// The variable that holds the number of the approach running (the failed one after a
    /// no-trip alarm) and the one set to 1 when the cycle completes.
    pub step_variable: String,
    pub done_variable: String,
}

/// The NC address of each rotary axis (index as in `Kinematics::rotary`).
pub fn rotary_addresses(k: &Kinematics) -> Result<Vec<char>, ProgramError> {
    let mut out: Vec<char> = Vec::new();
    for (i, ax) in k.rotary.iter().enumerate() {
        // `D` is the tool-radius offset word on every control: an inclined axis is
        // programmed under the letter of the axis it replaces (B on the 45-degree heads).
        let a = match ax.name.as_str() {
            "A" => 'A',
            "B" | "D" => 'B',
            "C" => 'C',
            _ => return Err(ProgramError::NoAddress(ax.name.clone())),
        };
        if let Some(j) = out.iter().position(|b| *b == a) {
            return Err(ProgramError::SharedAddress(
                k.rotary[j].name.clone(),
                k.rotary[i].name.clone(),
                a,
            ));
        }
        out.push(a);
    }
    Ok(out)
}

fn variable(d: Dialect, n: u32) -> String {
    match d {
        Dialect::Fanuc | Dialect::Iso => format!("#{n}"),
        Dialect::Siemens => format!("R{n}"),
        Dialect::Heidenhain => format!("Q{n}"),
    }
}

/// The program text of `plan` on machine `k` in dialect `d`.
pub fn write(
    k: &Kinematics,
    plan: &Plan,
    d: Dialect,
    opts: &ProgramOptions,
) -> Result<Program, ProgramError> {
    if !(1..=5).contains(&opts.decimals) {
        return Err(ProgramError::Decimals(opts.decimals));
    }
    // The reader takes the codes the header names for clamping and nothing else: a code with
    // another meaning would be read as a clamp and hide what it does.
    for code in [&opts.unclamp, &opts.clamp] {
        let number = code
            .strip_prefix('M')
            .filter(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
            .and_then(|n| n.parse::<u32>().ok());
        let ok = code.is_empty() || number.is_some_and(|n| n >= 10 && n != 30);
        if !ok {
            return Err(ProgramError::ClampCode(code.clone()));
        }
    }
    let addresses = rotary_addresses(k)?;
    // A rapid that puts the beam inside the tool strikes the setter on the machine (LinuxCNC
    // stops with "Probe tripped during non-probe move").
    let contacts = beam_contacts(k, plan);
    if let Some(first) = contacts.first() {
        return Err(ProgramError::StrikesBeam {
            plan: plan.name.clone(),
            machine: k.name.clone(),
            contacts: contacts.len(),
            first: first.to_string(),
        });
    }
    let mut w = Writer {
        b: Blocks::new(d, opts.decimals),
        addresses,
    };
    let step_var = variable(d, opts.first_result - 1);
    let done_var = variable(d, opts.first_result - 2);
    let results: Vec<ResultSlot> = plan
        .steps
        .iter()
        .enumerate()
        .map(|(i, s)| ResultSlot {
            number: i + 1,
            label: s.label.clone(),
            variable: variable(d, opts.first_result + i as u32),
            axis: s.approach.axis,
        })
        .collect();
    w.header(k, plan, opts, &results, &step_var, &done_var);
    // Where the plan's layout starts: the zero pose over the machine origin at the safe Z.
    let mut pos = [f64::NAN; 3];
    let mut angles = [f64::NAN; MAX_ROTARY];
    w.rapid(&mut pos, [None, None, Some(k.motion.safe_z_mm)]);
    w.rapid(&mut pos, [Some(0.0), Some(0.0), None]);
    w.index(&mut angles, &[0.0; MAX_ROTARY], k.rotary.len(), opts);
    w.spindle(plan.config.spindle_rpm);
    for m in &plan.moves {
        match m.kind {
            MoveKind::Rapid => w.rapid(&mut pos, m.to.map(Some)),
            MoveKind::Rotary => w.index(&mut angles, &m.angles_deg, k.rotary.len(), opts),
            MoveKind::Dwell => {
                if let Some(i) = m.step {
                    w.b.comment(&format!("STEP {} {}", i + 1, plan.steps[i].label));
                }
                w.dwell(m.duration_s);
            }
            MoveKind::Probe => {
                let i = m.step.ok_or_else(|| ProgramError::ProbeWithoutStep {
                    plan: plan.name.clone(),
                })?;
                let s = &plan.steps[i];
                let ax = s.approach.axis.index();
                let mut end = pos;
                end[ax] = s.start[ax] + f64::from(s.approach.direction) * s.max_travel_mm;
                w.skip(
                    i + 1,
                    &results[i],
                    &step_var,
                    (s.approach.axis, s.approach.direction),
                    (pos, end),
                    s.approach.feed_mm_min,
                );
                // Where the skip stops is the measurement: the next rapid names every axis it
                // moves from there.
                pos[ax] = f64::NAN;
            }
        }
    }
    w.footer(&done_var, &step_var, opts.number);
    Ok(Program {
        dialect: d,
        text: w.b.text,
        results,
        step_variable: step_var,
        done_variable: done_var,
    })
}

struct Writer {
    b: Blocks,
    addresses: Vec<char>,
}

impl Writer {
    fn header(
        &mut self,
        k: &Kinematics,
        plan: &Plan,
        opts: &ProgramOptions,
        results: &[ResultSlot],
        step_var: &str,
        done_var: &str,
    ) {
        let title = format!(
            "DRIFTWATCH PLAN {} ON {} - GENERATED, DO NOT EDIT",
            plan.name, k.name
        );
        match self.b.d {
            Dialect::Fanuc => {
                self.b.emit("%");
                self.b.emit(&format!("O{:04} ({title})", opts.number));
            }
            Dialect::Heidenhain => self.b.emit(&format!("BEGIN PGM DW{} MM", opts.number)),
            Dialect::Siemens => self.b.comment(&format!("DW{} {title}", opts.number)),
            Dialect::Iso => {
                self.b.emit("%");
                self.b.comment(&format!("DW{} {title}", opts.number));
            }
        }
        self.b.comment(&format!(
            "TOOL {} IN THE SPINDLE, SETTER BEAM CLEAR; MACHINE TIME {:.1} S",
            k.tool_id, plan.machine_time_s
        ));
        self.b.comment(&format!(
            "RESULTS {}..{} LATCHED COORDINATE PER STEP, {step_var} STEP RUNNING, {done_var} 1 WHEN DONE",
            results.first().map_or("", |r| r.variable.as_str()),
            results.last().map_or("", |r| r.variable.as_str()),
        ));
        // The clamp codes, named so that a reader takes these M codes and no other.
        let code = |c: &str| {
            if c.is_empty() {
                "NONE".to_string()
            } else {
                c.to_string()
            }
        };
        self.b.comment(&format!(
            "UNCLAMP {} CLAMP {}",
            code(&opts.unclamp),
            code(&opts.clamp)
        ));
        let travel = plan.steps.first().map_or(0.0, |s| s.max_travel_mm);
        match self.b.d {
            Dialect::Fanuc => {
                self.b.emit("G21 G90 G17 G40 G49 G80 G94");
                self.b
                    .comment("WORK OFFSET G54.1 P48 IS SET TO ZERO: COORDINATES ARE MACHINE");
                let rot: String = self.addresses.iter().map(|a| format!(" {a}0")).collect();
                self.b.emit(&format!("G10 L20 P48 X0 Y0 Z0{rot}"));
                self.b.emit("G54.1 P48");
                self.b.emit(&format!("{done_var}=0"));
            }
            Dialect::Siemens => {
                self.b.emit("DEF INT DW_ERR");
                self.b.emit("G71 G90 G17 G40 G94 G500");
                self.b.emit(&format!("{done_var}=0"));
            }
            Dialect::Heidenhain => {
                self.b.comment(&format!(
                    "PROBE TABLE F{} DIST{}",
                    fmt_plain(plan.config.feed_mm_min),
                    fmt_plain(travel)
                ));
                self.b
                    .comment("ACTIVE PRESET ALL ZERO: COORDINATES ARE MACHINE");
                self.b.emit(&format!("FN 0: {done_var} = +0"));
            }
            Dialect::Iso => {
                self.b.emit("G21 G90 G17 G40 G49 G94");
                let rot: String = self.addresses.iter().map(|a| format!(" {a}0")).collect();
                self.b.emit(&format!("G10 L2 P9 X0 Y0 Z0{rot}"));
                self.b.emit("G59.3");
                self.b.emit(&format!(
                    "(LOGOPEN,dw{}_{}.log)",
                    opts.number,
                    plan.name.replace(['/', ' '], "_")
                ));
                self.b.emit(&format!("{done_var}=0"));
            }
        }
    }

    fn spindle(&mut self, rpm: f64) {
        let rpm = rpm.round() as i64;
        match self.b.d {
            Dialect::Fanuc => self.b.emit(&format!("S{rpm} M03")),
            Dialect::Siemens | Dialect::Iso => self.b.emit(&format!("S{rpm} M3")),
            Dialect::Heidenhain => {
                self.b.emit(&format!("TOOL CALL Z S{rpm}"));
                self.b.emit("L M3");
            }
        }
    }

    /// A rapid to the given coordinates (None: unchanged); nothing when nothing moves.
    fn rapid(&mut self, pos: &mut [f64; 3], to: [Option<f64>; 3]) {
        let mut words = Vec::new();
        for (i, letter) in ['X', 'Y', 'Z'].into_iter().enumerate() {
            if let Some(v) = to[i] {
                let moved = self.b.word(letter, v) != self.b.word(letter, pos[i]);
                if moved || pos[i].is_nan() {
                    words.push(self.b.word(letter, v));
                }
                pos[i] = v;
            }
        }
        if words.is_empty() {
            return;
        }
        let w = words.join(" ");
        match self.b.d {
            Dialect::Fanuc => self.b.emit(&format!("G00 {w}")),
            Dialect::Siemens | Dialect::Iso => self.b.emit(&format!("G0 {w}")),
            Dialect::Heidenhain => self.b.emit(&format!("L {w} R0 FMAX")),
        }
    }

    /// Unclamp, index the rotary axes, clamp; nothing when no axis moves.
    fn index(&mut self, angles: &mut [f64], to: &[f64], n: usize, opts: &ProgramOptions) {
        let moved = (0..n).any(|i| angles[i].is_nan() || wrap_deg(angles[i] - to[i]).abs() > 1e-9);
        if !moved {
            return;
        }
        let words: Vec<String> = (0..n)
            .map(|i| self.b.word(self.addresses[i], to[i]))
            .collect();
        angles[..n].copy_from_slice(&to[..n]);
        let m = |s: &mut Self, code: &str| {
            if code.is_empty() {
                return;
            }
            match s.b.d {
                Dialect::Heidenhain => s.b.emit(&format!("L {code}")),
                _ => s.b.emit(code),
            }
        };
        m(self, &opts.unclamp);
        let w = words.join(" ");
        match self.b.d {
            Dialect::Fanuc => self.b.emit(&format!("G00 {w}")),
            Dialect::Siemens | Dialect::Iso => self.b.emit(&format!("G0 {w}")),
            Dialect::Heidenhain => self.b.emit(&format!("L {w} R0 FMAX")),
        }
        m(self, &opts.clamp);
    }

    fn dwell(&mut self, s: f64) {
        if s <= 0.0 {
            return;
        }
        let s = fmt_plain(s);
        match self.b.d {
            Dialect::Fanuc => self.b.emit(&format!("G04 X{s}")),
            Dialect::Siemens => self.b.emit(&format!("G4 F{s}")),
            Dialect::Iso => self.b.emit(&format!("G4 P{s}")),
            Dialect::Heidenhain => {
                self.b.emit("CYCL DEF 9.0 DWELL TIME");
                self.b.emit(&format!("CYCL DEF 9.1 DWELL {s}"));
            }
        }
    }

    /// One approach: the skip move from `start` towards `end` (the bounded travel), the latched
    /// coordinate stored, a move that reached its end reported as no trip.
    fn skip(
        &mut self,
        number: usize,
        slot: &ResultSlot,
        step_var: &str,
        (axis, direction): (Axis, i8),
        (start, end): ([f64; 3], [f64; 3]),
        feed: f64,
    ) {
        let letter = axis.name().to_ascii_uppercase();
        let l = letter.chars().next().unwrap_or('Z');
        let target = self.b.word(l, end[axis.index()]);
        let f = fmt_plain(feed);
        let var = slot.variable.clone();
        match self.b.d {
            Dialect::Fanuc => {
                self.b.emit(&format!("{step_var}={number}"));
                self.b.emit(&format!("G31 {target} F{f}"));
                let sys = 5061 + axis.index();
                self.b.emit(&format!("{var}=#{sys}"));
                // Without a skip signal the block ends at its end point.
                let end_v = &target[1..];
                self.b
                    .emit(&format!("IF[ABS[#{sys}-[{end_v}]]LT0.0005]GOTO9001"));
            }
            Dialect::Siemens => {
                self.b.emit(&format!("{step_var}={number}"));
                self.b.emit(&format!("MEAS=1 G1 {target} F{f}"));
                self.b.emit("STOPRE");
                self.b.emit("IF $AC_MEA[1]==0 GOTO NOTRIP");
                self.b.emit(&format!("{var}=$AA_MM[{letter}]"));
                self.b.emit(&format!(
                    "WRITE(DW_ERR,\"DRIFTWATCH_LOG\",\"{} {} \"<<{var})",
                    number, slot.label
                ));
            }
            Dialect::Heidenhain => {
                let sign = if direction > 0 { '+' } else { '-' };
                self.b.emit(&format!("FN 0: {step_var} = +{number}"));
                self.b
                    .emit(&format!("TCH PROBE 0.0 REF. PLANE {var} {letter}{sign}"));
                let pre: Vec<String> = ['X', 'Y', 'Z']
                    .into_iter()
                    .enumerate()
                    .map(|(i, c)| self.b.word(c, start[i]))
                    .collect();
                self.b.emit(&format!("TCH PROBE 0.1 {}", pre.join(" ")));
            }
            Dialect::Iso => {
                self.b.emit(&format!("{step_var}={number}"));
                self.b.emit(&format!("G38.2 {target} F{f}"));
                let sys = 5061 + axis.index();
                self.b.emit(&format!("{var}=#{sys}"));
                // The step number and the value only: LinuxCNC substitutes every `#n` in a LOG
                // line's text, so a label's pass (`z#1`) would be logged as `z0.000000`. The
                // STEP comment above names the label.
                self.b.emit(&format!("(LOG,{number} #{sys})"));
                // The same trip to whoever reads the control's messages as it happens (a
                // gateway that posts detections): the step number and the whole latched
                // position, after the probe, so the interpreter has its result.
                self.b
                    .emit(&format!("(DEBUG,DW {number} #5061 #5062 #5063)"));
            }
        }
    }

    fn footer(&mut self, done_var: &str, step_var: &str, number: u32) {
        match self.b.d {
            Dialect::Fanuc => {
                self.b.emit(&format!("{done_var}=1"));
                self.b.emit("M05");
                self.b.emit("M30");
                self.b.emit(&format!(
                    "N9001 #3000=1(DRIFTWATCH NO TRIP - STEP IN {step_var})"
                ));
                self.b.emit("%");
            }
            Dialect::Siemens => {
                self.b.emit(&format!("{done_var}=1"));
                self.b.emit("M5");
                self.b.emit("M30");
                self.b.emit("NOTRIP:");
                self.b.emit(&format!(
                    "MSG(\"DRIFTWATCH: NO TRIP AT STEP \"<<{step_var})"
                ));
                self.b.emit("SETAL(65100)");
                self.b.emit("M30");
            }
            Dialect::Heidenhain => {
                self.b.emit(&format!("FN 0: {done_var} = +1"));
                self.b.emit("L M5");
                self.b.emit(&format!("END PGM DW{number} MM"));
            }
            Dialect::Iso => {
                self.b.emit(&format!("{done_var}=1"));
                self.b.emit("(LOGCLOSE)");
                self.b.emit("M5");
                self.b.emit("M2");
                self.b.emit("%");
            }
        }
    }
}
