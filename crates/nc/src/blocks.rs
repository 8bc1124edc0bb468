//! The program text both writers build: blocks (numbered on HEIDENHAIN), comments in the
//! dialect's form, coordinate words to a number of decimals.

use std::fmt::Write as _;

use crate::dialect::Dialect;

pub(crate) struct Blocks {
    pub(crate) d: Dialect,
    pub(crate) text: String,
    /// HEIDENHAIN block number.
    block: usize,
    pub(crate) decimals: usize,
}

impl Blocks {
    pub(crate) fn new(d: Dialect, decimals: usize) -> Self {
        Blocks {
            d,
            text: String::new(),
            block: 0,
            decimals,
        }
    }

    pub(crate) fn emit(&mut self, s: &str) {
        if self.d == Dialect::Heidenhain {
            let _ = writeln!(self.text, "{} {s}", self.block);
            self.block += 1;
        } else {
            let _ = writeln!(self.text, "{s}");
        }
    }

    pub(crate) fn comment(&mut self, s: &str) {
        match self.d {
            Dialect::Fanuc | Dialect::Iso => self.emit(&format!("({s})")),
            Dialect::Siemens | Dialect::Heidenhain => self.emit(&format!("; {s}")),
        }
    }

    /// A coordinate word: `X12.345`, HEIDENHAIN `X+12.345`.
    pub(crate) fn word(&self, letter: char, v: f64) -> String {
        // Negative zero after rounding reads as "-0.000"; print it as zero.
        let scale = 10f64.powi(self.decimals as i32);
        let v = (v * scale).round() / scale + 0.0;
        match self.d {
            Dialect::Heidenhain => format!("{letter}{v:+.*}", self.decimals),
            _ => format!("{letter}{v:.*}", self.decimals),
        }
    }
}

/// A number without trailing zeros (`100`, `0.5`, `2.5`).
pub(crate) fn fmt_plain(v: f64) -> String {
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s.is_empty() || s == "-" {
        "0".into()
    } else {
        s.to_string()
    }
}
