//! Reads a measurement program back into the moves it commands, and replays them.
//!
//! The reader knows the words `program` writes, in each dialect, and refuses anything else by
//! line number: it checks that a generated program says what driftwatch meant, it is not a
//! general interpreter. No G-code crate reads FANUC macro B, Siemens or HEIDENHAIN Klartext,
//! so the four small readers are here. `replay` runs the read moves on a machine's motion
//! (rapid rate, rotary speeds, clamp time: the same timing model as the plan's estimate,
//! implemented again from the moves) and asks a caller's probe what each approach latches,
//! so a test can run a program through the truth simulator.

use thiserror::Error;

use driftwatch_core::geometry::wrap_deg;
use driftwatch_core::kinematics::{Kinematics, MAX_ROTARY};
use driftwatch_core::measurement::Axis;

use crate::dialect::Dialect;
use crate::program::{ProgramError, rotary_addresses};

#[derive(Debug, Error, PartialEq)]
pub enum ReadError {
    #[error("line {line}: {message}: `{text}`")]
    Line {
        line: usize,
        text: String,
        message: String,
    },
    #[error("the program ends without its end block")]
    NoEnd,
}

#[derive(Debug, Error, PartialEq)]
pub enum ReplayError {
    #[error(transparent)]
    Address(#[from] ProgramError),
    #[error("rotary address {0} is not an axis of machine {1}")]
    UnknownAxis(char, String),
    #[error("approach {number} ({label}) did not trip: the program stops here")]
    NoTrip { number: usize, label: String },
    #[error("a move before every coordinate is known (the program must position X, Y, Z first)")]
    Unpositioned,
}

/// One move or setting of a read program.
#[derive(Debug, Clone, PartialEq)]
pub enum Block {
    /// Spindle on at this speed (M3) or off (0).
    Spindle(f64),
    /// Rapid of the linear axes; `None` keeps a coordinate.
    Rapid([Option<f64>; 3]),
    /// Rapid of the rotary axes, by NC address.
    Index(Vec<(char, f64)>),
    Dwell(f64),
    /// A skip move along `axis` to `end` (the travel's end) at `feed` mm/min, whose latched
    /// coordinate is stored in `variable` under step `number`/`label`.
    Skip {
        number: usize,
        label: String,
        axis: Axis,
        end: f64,
        feed: f64,
        variable: String,
    },
}

#[derive(Debug, Clone, PartialEq)]
pub struct ReadProgram {
    pub dialect: Dialect,
    pub blocks: Vec<Block>,
}

/// What a line means to the reader before the skip bookkeeping.
enum Item {
    Nothing,
    Block(Block),
    Step(usize, String),
    /// A skip move without its result (`end` absolute), the variable stored next.
    SkipMove {
        axis: Axis,
        end: Option<f64>,
        direction: Option<i8>,
        feed: Option<f64>,
        variable: Option<String>,
    },
    /// `variable = latched coordinate of axis`.
    Store(String, Axis),
    End,
}

struct Parsed {
    items: Vec<(usize, String, Item)>,
}

fn err(line: usize, text: &str, message: impl Into<String>) -> ReadError {
    ReadError::Line {
        line,
        text: text.to_string(),
        message: message.into(),
    }
}

/// The clamp M codes a program names in its header (`UNCLAMP M11 CLAMP M10`, `NONE` for
/// none): the only M codes besides the spindle's and the end's the reader takes. A program
/// without that line (written before it) clamps with M10 and M11.
fn clamp_codes(text: &str) -> Vec<String> {
    for raw in text.lines() {
        let t = raw.trim();
        // HEIDENHAIN blocks start with their number.
        let t = t
            .split_once(' ')
            .filter(|(n, _)| n.parse::<u32>().is_ok())
            .map_or(t, |(_, rest)| rest.trim());
        let inner = t
            .strip_prefix('(')
            .and_then(|c| c.strip_suffix(')'))
            .or_else(|| t.strip_prefix(';'))
            .map(str::trim);
        let Some(rest) = inner.and_then(|c| c.strip_prefix("UNCLAMP ")) else {
            continue;
        };
        let words: Vec<&str> = rest.split_whitespace().collect();
        if let [unclamp, "CLAMP", clamp] = words[..] {
            return [unclamp, clamp]
                .into_iter()
                .filter(|c| *c != "NONE")
                .map(String::from)
                .collect();
        }
    }
    vec!["M10".into(), "M11".into()]
}

/// Read a program of dialect `d`.
pub fn read(text: &str, d: Dialect) -> Result<ReadProgram, ReadError> {
    let clamp = clamp_codes(text);
    let mut parsed = Parsed { items: Vec::new() };
    let mut probe_table: Option<(f64, f64)> = None;
    let mut ended = false;
    for (n, raw) in text.lines().enumerate() {
        let line = n + 1;
        let t = raw.trim();
        if t.is_empty() || ended {
            continue;
        }
        let item = match d {
            Dialect::Fanuc | Dialect::Iso => line_gcode(d, t, &clamp),
            Dialect::Siemens => line_siemens(t, &clamp),
            Dialect::Heidenhain => line_heidenhain(t, &clamp, &mut probe_table),
        }
        .map_err(|m| err(line, t, m))?;
        if matches!(item, Item::End) {
            ended = true;
        }
        parsed.items.push((line, t.to_string(), item));
    }
    if !ended {
        return Err(ReadError::NoEnd);
    }
    assemble(d, parsed, probe_table)
}

/// Pair each skip move with its step comment and the store that follows it.
fn assemble(
    d: Dialect,
    parsed: Parsed,
    probe_table: Option<(f64, f64)>,
) -> Result<ReadProgram, ReadError> {
    let mut blocks = Vec::new();
    let mut step: Option<(usize, String)> = None;
    // A skip move waiting for the store of its result (its `variable` still empty).
    let mut pending: Option<Block> = None;
    let mut pos = [f64::NAN; 3];
    for (line, text, item) in parsed.items {
        match item {
            Item::Nothing | Item::End => {}
            Item::Step(n, label) => step = Some((n, label)),
            Item::Block(b) => {
                if pending.is_some() {
                    return Err(err(
                        line,
                        &text,
                        "a move before the skip's result is stored",
                    ));
                }
                if let Block::Rapid(to) = &b {
                    for i in 0..3 {
                        if let Some(v) = to[i] {
                            pos[i] = v;
                        }
                    }
                }
                blocks.push(b);
            }
            Item::SkipMove {
                axis,
                end,
                direction,
                feed,
                variable,
            } => {
                let (number, label) = step
                    .take()
                    .ok_or_else(|| err(line, &text, "a skip move without a STEP comment"))?;
                let (end, feed) = match (end, direction, feed, probe_table) {
                    (Some(e), _, Some(f), _) => (e, f),
                    (None, Some(dir), None, Some((f, dist))) => {
                        let start = pos[axis.index()];
                        if start.is_nan() {
                            return Err(err(line, &text, "probing from an unknown position"));
                        }
                        (start + f64::from(dir) * dist, f)
                    }
                    _ => {
                        return Err(err(
                            line,
                            &text,
                            "a skip move without its end and feed (HEIDENHAIN: the PROBE TABLE line)",
                        ));
                    }
                };
                let skip = Block::Skip {
                    number,
                    label,
                    axis,
                    end,
                    feed,
                    variable: variable.clone().unwrap_or_default(),
                };
                // A cycle that names its result variable (HEIDENHAIN's) stores it itself.
                if variable.is_some() {
                    blocks.push(skip);
                } else {
                    pending = Some(skip);
                }
            }
            Item::Store(var, axis) => match pending.take() {
                Some(Block::Skip {
                    number,
                    label,
                    axis: skip_axis,
                    end,
                    feed,
                    ..
                }) if skip_axis == axis => blocks.push(Block::Skip {
                    number,
                    label,
                    axis,
                    end,
                    feed,
                    variable: var,
                }),
                Some(_) => {
                    return Err(err(line, &text, "the stored coordinate is not the skip's"));
                }
                None => return Err(err(line, &text, "a result stored without a skip move")),
            },
        }
    }
    Ok(ReadProgram { dialect: d, blocks })
}

/// `X12.5` -> ('X', 12.5); HEIDENHAIN signs (`X+12.5`) read too.
fn words(s: &str) -> Result<Vec<(char, f64)>, String> {
    s.split_whitespace()
        .map(|w| {
            let mut c = w.chars();
            let letter = c
                .next()
                .filter(|l| l.is_ascii_alphabetic())
                .ok_or(format!("`{w}` is not a word"))?;
            let v: f64 = c
                .as_str()
                .parse()
                .map_err(|_| format!("`{w}` has no number"))?;
            Ok((letter.to_ascii_uppercase(), v))
        })
        .collect()
}

fn axis_of(c: char) -> Option<Axis> {
    match c {
        'X' => Some(Axis::X),
        'Y' => Some(Axis::Y),
        'Z' => Some(Axis::Z),
        _ => None,
    }
}

/// A rapid of linear or rotary words (never both: the writer does not mix them).
fn rapid(ws: &[(char, f64)]) -> Result<Item, String> {
    let mut lin = [None; 3];
    let mut rot = Vec::new();
    for (c, v) in ws {
        match (axis_of(*c), c) {
            (Some(a), _) => lin[a.index()] = Some(*v),
            (None, 'A' | 'B' | 'C') => rot.push((*c, *v)),
            _ => return Err(format!("word {c} in a rapid")),
        }
    }
    match (lin.iter().any(Option::is_some), rot.is_empty()) {
        (true, true) => Ok(Item::Block(Block::Rapid(lin))),
        (false, false) => Ok(Item::Block(Block::Index(rot))),
        (true, false) => Err("linear and rotary words in one rapid".into()),
        (false, true) => Err("a rapid without coordinates".into()),
    }
}

/// `(STEP 3 B0C0/z#1)` or `; STEP 3 ...` -> the step.
fn step_comment(c: &str) -> Option<Item> {
    let rest = c.trim().strip_prefix("STEP ")?;
    let (n, label) = rest.split_once(' ')?;
    Some(Item::Step(n.parse().ok()?, label.trim().to_string()))
}

/// One skip move `G31 Z-1.5 F100` / `MEAS=1 G1 Z.. F..` / `G38.2 ...`: its axis, end, feed.
fn skip_words(ws: &[(char, f64)]) -> Result<Item, String> {
    let mut target = None;
    let mut feed = None;
    for (c, v) in ws {
        match (axis_of(*c), c) {
            (Some(a), _) if target.is_none() => target = Some((a, *v)),
            (_, 'F') => feed = Some(*v),
            _ => return Err(format!("word {c} in a skip move (one axis and F only)")),
        }
    }
    let (axis, end) = target.ok_or("a skip move without an axis")?;
    Ok(Item::SkipMove {
        axis,
        end: Some(end),
        direction: None,
        feed: Some(feed.ok_or("a skip move without F")?),
        variable: None,
    })
}

/// `#601=#5063` -> store of Z; `#600=3` and other constants -> nothing.
fn gcode_assignment(t: &str) -> Result<Item, String> {
    let (lhs, rhs) = t.split_once('=').ok_or("not an assignment")?;
    let lhs = lhs.trim();
    if !lhs.starts_with('#') || lhs[1..].parse::<u32>().is_err() {
        return Err("not a numbered variable".into());
    }
    let rhs = rhs.trim();
    match rhs {
        "#5061" => Ok(Item::Store(lhs.into(), Axis::X)),
        "#5062" => Ok(Item::Store(lhs.into(), Axis::Y)),
        "#5063" => Ok(Item::Store(lhs.into(), Axis::Z)),
        _ if rhs.parse::<f64>().is_ok() => Ok(Item::Nothing),
        _ => Err("an assignment the reader does not know".into()),
    }
}

fn line_gcode(d: Dialect, t: &str, clamp: &[String]) -> Result<Item, String> {
    // Comments: the step labels; LOG lines (ISO) are checked for their number only.
    if let Some(c) = t.strip_prefix('(').and_then(|c| c.strip_suffix(')')) {
        return Ok(step_comment(c).unwrap_or(Item::Nothing));
    }
    if t == "%" {
        return Ok(Item::Nothing);
    }
    if t.starts_with('#') {
        return gcode_assignment(t);
    }
    if d == Dialect::Fanuc {
        if t.starts_with('O') && t[1..5.min(t.len())].chars().all(|c| c.is_ascii_digit()) {
            return Ok(Item::Nothing);
        }
        if t.starts_with("IF[ABS[#506") && t.ends_with("GOTO9001") {
            return Ok(Item::Nothing);
        }
        if t == "M30" {
            return Ok(Item::End);
        }
    }
    if d == Dialect::Iso && t == "M2" {
        return Ok(Item::End);
    }
    if clamp.iter().any(|c| c == t) {
        return Ok(Item::Nothing);
    }
    let code = t.split('(').next().unwrap_or(t).trim();
    let ws = words(code)?;
    let Some(&(first, v)) = ws.first() else {
        return Err("an empty block".into());
    };
    let setup_g = [17.0, 21.0, 40.0, 49.0, 80.0, 90.0, 94.0];
    match (first, v) {
        ('G', 0.0) => rapid(&ws[1..]),
        ('G', g) if (d == Dialect::Fanuc && g == 31.0) || (d == Dialect::Iso && g == 38.2) => {
            skip_words(&ws[1..])
        }
        ('G', 4.0) => match ws.get(1) {
            Some(('X', s)) if d == Dialect::Fanuc => Ok(Item::Block(Block::Dwell(*s))),
            Some(('P', s)) if d == Dialect::Iso => Ok(Item::Block(Block::Dwell(*s))),
            _ => Err("a dwell without its time word".into()),
        },
        ('G', 10.0) => {
            // The program's own work offset: it must be the zero offset.
            if ws[1..]
                .iter()
                .all(|(c, v)| matches!(c, 'L' | 'P') || *v == 0.0)
            {
                Ok(Item::Nothing)
            } else {
                Err("a work offset that is not zero".into())
            }
        }
        ('G', 54.1 | 59.3) => Ok(Item::Nothing),
        ('G', _) => {
            if ws.iter().all(|(c, g)| *c == 'G' && setup_g.contains(g)) {
                Ok(Item::Nothing)
            } else {
                Err("G codes the reader does not know (incremental G91 is refused)".into())
            }
        }
        ('S', rpm) => Ok(Item::Block(Block::Spindle(rpm))),
        ('M', 5.0) => Ok(Item::Block(Block::Spindle(0.0))),
        _ => Err("a block the reader does not know".into()),
    }
}

fn line_siemens(t: &str, clamp: &[String]) -> Result<Item, String> {
    if let Some(c) = t.strip_prefix(';') {
        return Ok(step_comment(c).unwrap_or(Item::Nothing));
    }
    let fixed = [
        "DEF INT DW_ERR",
        "G71 G90 G17 G40 G94 G500",
        "STOPRE",
        "IF $AC_MEA[1]==0 GOTO NOTRIP",
    ];
    if fixed.contains(&t) || t.starts_with("WRITE(DW_ERR,") || clamp.iter().any(|c| c == t) {
        return Ok(Item::Nothing);
    }
    if t == "M30" {
        return Ok(Item::End);
    }
    if t == "M5" {
        return Ok(Item::Block(Block::Spindle(0.0)));
    }
    if let Some(rest) = t.strip_prefix("MEAS=1 G1 ") {
        return skip_words(&words(rest)?);
    }
    if let Some((lhs, rhs)) = t.split_once('=')
        && lhs.starts_with('R')
        && lhs[1..].parse::<u32>().is_ok()
    {
        let rhs = rhs.trim();
        return match rhs {
            "$AA_MM[X]" => Ok(Item::Store(lhs.into(), Axis::X)),
            "$AA_MM[Y]" => Ok(Item::Store(lhs.into(), Axis::Y)),
            "$AA_MM[Z]" => Ok(Item::Store(lhs.into(), Axis::Z)),
            _ if rhs.parse::<f64>().is_ok() => Ok(Item::Nothing),
            _ => Err("an assignment the reader does not know".into()),
        };
    }
    let ws = words(t)?;
    match ws.first() {
        Some(('G', 0.0)) => rapid(&ws[1..]),
        Some(('G', 4.0)) => match ws.get(1) {
            Some(('F', s)) => Ok(Item::Block(Block::Dwell(*s))),
            _ => Err("a dwell without F".into()),
        },
        Some(('S', rpm)) => Ok(Item::Block(Block::Spindle(*rpm))),
        _ => Err("a block the reader does not know".into()),
    }
}

fn line_heidenhain(
    t: &str,
    clamp: &[String],
    probe_table: &mut Option<(f64, f64)>,
) -> Result<Item, String> {
    // Every block starts with its number.
    let (n, body) = t.split_once(' ').ok_or("a block without its number")?;
    n.parse::<u32>().map_err(|_| "a block without its number")?;
    let b = body.trim();
    if let Some(c) = b.strip_prefix(';') {
        let c = c.trim();
        if let Some(rest) = c.strip_prefix("PROBE TABLE ") {
            // `DIST2.5` is not a one-letter word: take it apart by hand.
            let f = rest
                .split_whitespace()
                .find_map(|w| w.strip_prefix('F'))
                .and_then(|v| v.parse::<f64>().ok());
            let dist = rest
                .split_whitespace()
                .find_map(|w| w.strip_prefix("DIST"))
                .and_then(|v| v.parse::<f64>().ok());
            match (f, dist) {
                (Some(f), Some(d)) => *probe_table = Some((f, d)),
                _ => return Err("PROBE TABLE needs F and DIST".into()),
            }
            return Ok(Item::Nothing);
        }
        return Ok(step_comment(c).unwrap_or(Item::Nothing));
    }
    if b.starts_with("BEGIN PGM ") {
        return Ok(Item::Nothing);
    }
    if b.starts_with("END PGM ") {
        return Ok(Item::End);
    }
    if b.starts_with("FN 0: Q") || b == "CYCL DEF 9.0 DWELL TIME" {
        return Ok(Item::Nothing);
    }
    if let Some(s) = b.strip_prefix("CYCL DEF 9.1 DWELL ") {
        return Ok(Item::Block(Block::Dwell(
            s.trim().parse().map_err(|_| "a dwell without its time")?,
        )));
    }
    if let Some(s) = b.strip_prefix("TOOL CALL Z S") {
        return Ok(Item::Block(Block::Spindle(
            s.trim()
                .parse()
                .map_err(|_| "a spindle speed that is not a number")?,
        )));
    }
    if b == "L M3"
        || b.strip_prefix("L ")
            .is_some_and(|m| clamp.iter().any(|c| c == m))
    {
        return Ok(Item::Nothing);
    }
    if b == "L M5" {
        return Ok(Item::Block(Block::Spindle(0.0)));
    }
    if let Some(rest) = b.strip_prefix("TCH PROBE 0.0 REF. PLANE ") {
        let (var, dir) = rest
            .split_once(' ')
            .ok_or("REF. PLANE without its direction")?;
        let mut c = dir.chars();
        let axis = c
            .next()
            .and_then(axis_of)
            .ok_or("a probing axis that is not X, Y, Z")?;
        let direction = match c.as_str() {
            "+" => 1,
            "-" => -1,
            _ => return Err("a probing direction that is not + or -".into()),
        };
        return Ok(Item::SkipMove {
            axis,
            end: None,
            direction: Some(direction),
            feed: None,
            variable: Some(var.to_string()),
        });
    }
    if let Some(rest) = b.strip_prefix("TCH PROBE 0.1 ") {
        // The pre-position; the writer puts it where the tool already is.
        return match rapid(&words(rest)?)? {
            Item::Block(Block::Rapid(_)) => Ok(Item::Nothing),
            _ => Err("a pre-position that is not X, Y, Z".into()),
        };
    }
    if let Some(rest) = b.strip_prefix("L ")
        && let Some(coords) = rest.strip_suffix(" R0 FMAX")
    {
        return rapid(&words(coords)?);
    }
    Err("a block the reader does not know".into())
}

/// One approach as the replay meets it.
#[derive(Debug, Clone, PartialEq)]
pub struct ReplayApproach {
    pub number: usize,
    pub label: String,
    /// Rotary angles, deg, indexed as `Kinematics::rotary`.
    pub angles: [f64; MAX_ROTARY],
    pub start: [f64; 3],
    pub axis: Axis,
    pub direction: i8,
    pub feed_mm_min: f64,
    pub travel_mm: f64,
    /// Seconds from the cycle start (the plan's zero pose over the origin at safe Z).
    pub t_start_s: f64,
    pub spindle_rpm: f64,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Replayed {
    /// Each approach with the latched coordinate its probe returned.
    pub approaches: Vec<(ReplayApproach, f64)>,
    pub run_time_s: f64,
}

/// Run `program` on machine `k`'s motion from the plan's start point; `probe` answers each
/// approach with its latched coordinate (None: no trip, which stops the program).
pub fn replay(
    k: &Kinematics,
    program: &ReadProgram,
    mut probe: impl FnMut(&ReplayApproach) -> Option<f64>,
) -> Result<Replayed, ReplayError> {
    let addresses = rotary_addresses(k)?;
    let rapid = k.motion.rapid_mm_min / 60.0;
    let mut pos = [0.0, 0.0, k.motion.safe_z_mm];
    let mut angles = [0.0; MAX_ROTARY];
    let mut rpm = 0.0;
    let mut t = 0.0;
    let mut out = Vec::new();
    for b in &program.blocks {
        match b {
            Block::Spindle(s) => rpm = *s,
            Block::Rapid(to) => {
                let mut d2 = 0.0;
                for i in 0..3 {
                    if let Some(v) = to[i] {
                        d2 += (v - pos[i]).powi(2);
                        pos[i] = v;
                    }
                }
                t += d2.sqrt() / rapid;
            }
            Block::Index(words) => {
                let mut dur: f64 = 0.0;
                for (c, v) in words {
                    let i = addresses
                        .iter()
                        .position(|a| a == c)
                        .ok_or_else(|| ReplayError::UnknownAxis(*c, k.name.clone()))?;
                    let speed = k.rotary[i].speed_deg_min / 60.0;
                    dur = dur.max(wrap_deg(v - angles[i]).abs() / speed);
                    angles[i] = *v;
                }
                // Unclamping and clamping take their time only around a move.
                if dur > 0.0 {
                    t += dur + k.motion.clamp_s;
                }
            }
            Block::Dwell(s) => t += s,
            Block::Skip {
                number,
                label,
                axis,
                end,
                feed,
                ..
            } => {
                let ax = axis.index();
                let a = ReplayApproach {
                    number: *number,
                    label: label.clone(),
                    angles,
                    start: pos,
                    axis: *axis,
                    direction: if *end >= pos[ax] { 1 } else { -1 },
                    feed_mm_min: *feed,
                    travel_mm: (end - pos[ax]).abs(),
                    t_start_s: t,
                    spindle_rpm: rpm,
                };
                let v = probe(&a).ok_or_else(|| ReplayError::NoTrip {
                    number: *number,
                    label: label.clone(),
                })?;
                t += (v - pos[ax]).abs() / (feed / 60.0);
                pos[ax] = v;
                out.push((a, v));
            }
        }
    }
    Ok(Replayed {
        approaches: out,
        run_time_s: t,
    })
}
