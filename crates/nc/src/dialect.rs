//! The controls driftwatch writes for.

use serde::{Deserialize, Serialize};

/// An NC dialect: the family of controls whose program syntax and variables are meant.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Dialect {
    /// FANUC Series 30i/31i/0i with custom macro B: `G31` skip, `#5061`-`#5063`, `G10`.
    Fanuc,
    /// Siemens SINUMERIK 840D sl/ONE: `MEAS`, `$AA_MM`, `$AC_MEA`, `$TC_CARR`.
    Siemens,
    /// HEIDENHAIN TNC 640/620 (Klartext): `TCH PROBE`, Q parameters.
    Heidenhain,
    /// RS274/NGC (the NIST interpreter of ISO 6983 that LinuxCNC runs): `G38.2`, `#5061`.
    Iso,
}

impl Dialect {
    pub const ALL: [Dialect; 4] = [
        Dialect::Fanuc,
        Dialect::Siemens,
        Dialect::Heidenhain,
        Dialect::Iso,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Dialect::Fanuc => "fanuc",
            Dialect::Siemens => "siemens",
            Dialect::Heidenhain => "heidenhain",
            Dialect::Iso => "iso",
        }
    }

    /// The program file's extension as the control's file manager expects it.
    pub fn extension(self) -> &'static str {
        match self {
            Dialect::Fanuc => "nc",
            Dialect::Siemens => "mpf",
            Dialect::Heidenhain => "h",
            Dialect::Iso => "ngc",
        }
    }

    pub fn parse(s: &str) -> Option<Dialect> {
        Dialect::ALL.into_iter().find(|d| d.name() == s)
    }
}

impl std::fmt::Display for Dialect {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_back() {
        for d in Dialect::ALL {
            assert_eq!(Dialect::parse(d.name()), Some(d));
        }
        assert_eq!(Dialect::parse("mazak"), None);
    }
}
