//! The name of an ISO 230-7 location error of a rotary axis, parsed once at the boundary so
//! that its unit is read from a type rather than guessed from a string's prefix.
//!
//! A name is four ASCII characters (`docs/kinematics-conventions.md`): `E`, the component
//! (`X`, `Y`, `Z` for a position error in um; `A`, `B`, `C` for an orientation error in urad,
//! the rotation about X, Y, Z), `0` (a location error, not a motion error), and the rotary
//! axis it belongs to (`A`, `B`, `C`, or `D`, the 45-degree inclined axis of the patent's
//! Figs. 11 and 12): `EX0B`, `EZ0B`, `EA0B`, `EC0B`, `EB0B` (the zero angle of B), `EX0C`,
//! `EY0C`, `EA0C`, `EB0C`, `EC0C`. An inclined axis' components are those of its own frame
//! (the machine frame turned so that the axis is one of its axes; for D, its Y).
//!
//! [`ErrorName`] orders, hashes and compares exactly as its string does and borrows as a
//! `str`, so a `BTreeMap<ErrorName, _>` iterates and serializes in the order a
//! `BTreeMap<String, _>` does and is looked up with a `&str`.

use std::borrow::Borrow;
use std::fmt;
use std::hash::{Hash, Hasher};
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use thiserror::Error;

/// Whether a location error moves an axis line (position, um) or turns it (orientation, urad).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ErrorKind {
    Position,
    Orientation,
}

impl ErrorKind {
    /// The interface unit: "um" for a position error, "urad" for an orientation error.
    pub fn unit(self) -> &'static str {
        match self {
            ErrorKind::Position => "um",
            ErrorKind::Orientation => "urad",
        }
    }
}

/// A string that is not a location error name, with what is wrong with it.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error(
    "bad location error name {name:?}: {why} (a name is E, the component X/Y/Z (position, um) \
     or A/B/C (orientation, urad), 0 and the rotary axis A/B/C/D, e.g. EX0B or EA0C)"
)]
pub struct BadErrorName {
    /// The name as given (cut to its first 32 characters).
    pub name: String,
    /// What is wrong with it.
    pub why: &'static str,
}

/// An ISO 230-7 location error name such as `EX0B` or `EA0C` (module docs). Copy, four bytes.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct ErrorName([u8; 4]);

/// The checks of a name, usable in a `const` (see [`ErrorName::from_static`]).
const fn check(b: &[u8]) -> Result<[u8; 4], &'static str> {
    if b.len() != 4 {
        return Err("it must have exactly 4 characters");
    }
    if b[0] != b'E' {
        return Err("it must begin with E");
    }
    if !matches!(b[1], b'X' | b'Y' | b'Z' | b'A' | b'B' | b'C') {
        return Err("the second character must be one of X, Y, Z, A, B, C");
    }
    if b[2] != b'0' {
        return Err("the third character must be 0");
    }
    if !matches!(b[3], b'A' | b'B' | b'C' | b'D') {
        return Err("the fourth character must be the rotary axis A, B, C or D");
    }
    Ok([b[0], b[1], b[2], b[3]])
}

impl ErrorName {
    /// Parse a name; refuses anything that is not exactly a location error name (no case
    /// folding, no surrounding blanks).
    pub fn parse(s: &str) -> Result<Self, BadErrorName> {
        check(s.as_bytes())
            .map(ErrorName)
            .map_err(|why| BadErrorName {
                name: s.chars().take(32).collect(),
                why,
            })
    }

    /// A name known when compiling (a bad one fails the build when used in a `const`).
    pub const fn from_static(s: &'static str) -> Self {
        match check(s.as_bytes()) {
            Ok(b) => ErrorName(b),
            Err(_) => panic!("not a location error name"),
        }
    }

    pub fn as_str(&self) -> &str {
        // Four ASCII bytes by construction.
        std::str::from_utf8(&self.0).expect("a parsed name is ASCII")
    }

    pub fn kind(&self) -> ErrorKind {
        match self.0[1] {
            b'A' | b'B' | b'C' => ErrorKind::Orientation,
            _ => ErrorKind::Position,
        }
    }

    /// Whether this is an orientation error (urad).
    pub fn is_angular(&self) -> bool {
        self.kind() == ErrorKind::Orientation
    }

    /// "um" or "urad".
    pub fn unit(&self) -> &'static str {
        self.kind().unit()
    }

    /// The component letter: X, Y, Z (position) or A, B, C (orientation).
    pub fn component(&self) -> char {
        self.0[1] as char
    }

    /// The rotary axis the error belongs to: A, B, C or D.
    pub fn axis(&self) -> char {
        self.0[3] as char
    }
}

/// The unit of a channel's values: a channel is a location error (`EZ0B`, `EA0C`: um or urad,
/// as its name says) or a displacement sensor (`ch1` of a displacement recording: um). Only a
/// channel that parses as an orientation error is in urad.
pub fn channel_unit(channel: &str) -> &'static str {
    ErrorName::parse(channel).map_or("um", |e| e.unit())
}

impl fmt::Display for ErrorName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.pad(self.as_str())
    }
}

impl fmt::Debug for ErrorName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self.as_str(), f)
    }
}

impl FromStr for ErrorName {
    type Err = BadErrorName;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        ErrorName::parse(s)
    }
}

impl TryFrom<&str> for ErrorName {
    type Error = BadErrorName;
    fn try_from(s: &str) -> Result<Self, Self::Error> {
        ErrorName::parse(s)
    }
}

impl AsRef<str> for ErrorName {
    fn as_ref(&self) -> &str {
        self.as_str()
    }
}

/// Sound because `Eq`, `Ord` and `Hash` are those of the string.
impl Borrow<str> for ErrorName {
    fn borrow(&self) -> &str {
        self.as_str()
    }
}

impl Hash for ErrorName {
    fn hash<H: Hasher>(&self, state: &mut H) {
        self.as_str().hash(state)
    }
}

impl PartialEq<str> for ErrorName {
    fn eq(&self, other: &str) -> bool {
        self.as_str() == other
    }
}

impl PartialEq<&str> for ErrorName {
    fn eq(&self, other: &&str) -> bool {
        self.as_str() == *other
    }
}

impl PartialEq<ErrorName> for str {
    fn eq(&self, other: &ErrorName) -> bool {
        self == other.as_str()
    }
}

impl PartialEq<ErrorName> for &str {
    fn eq(&self, other: &ErrorName) -> bool {
        *self == other.as_str()
    }
}

impl From<ErrorName> for String {
    fn from(n: ErrorName) -> String {
        n.as_str().to_string()
    }
}

impl Serialize for ErrorName {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> Deserialize<'de> for ErrorName {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = ErrorName;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a location error name such as EX0B or EA0C")
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<ErrorName, E> {
                ErrorName::parse(v).map_err(E::custom)
            }
        }
        d.deserialize_str(Visitor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    const ALL: [&str; 10] = [
        "EX0B", "EZ0B", "EA0B", "EC0B", "EB0B", "EX0C", "EY0C", "EA0C", "EB0C", "EC0C",
    ];

    #[test]
    fn a_channel_is_in_urad_only_when_it_names_an_orientation_error() {
        assert_eq!(channel_unit("EA0C"), "urad");
        assert_eq!(channel_unit("EB0C"), "urad");
        assert_eq!(channel_unit("EZ0B"), "um");
        assert_eq!(channel_unit("ch1"), "um");
        assert_eq!(channel_unit("EA"), "um");
    }

    #[test]
    fn good_names_parse_with_their_kind_and_unit() {
        for s in ALL {
            let n = ErrorName::parse(s).unwrap();
            assert_eq!(n.as_str(), s);
            assert_eq!(n.to_string(), s);
            assert_eq!(format!("{n:?}"), format!("{s:?}"));
            assert_eq!(s.parse::<ErrorName>().unwrap(), n);
            let angular = matches!(&s[1..2], "A" | "B" | "C");
            assert_eq!(n.is_angular(), angular, "{s}");
            assert_eq!(n.unit(), if angular { "urad" } else { "um" }, "{s}");
            assert_eq!(n.axis(), s.chars().nth(3).unwrap());
            assert_eq!(n.component(), s.chars().nth(1).unwrap());
        }
        assert_eq!(
            ErrorName::parse("EZ0B").unwrap().kind(),
            ErrorKind::Position
        );
        assert_eq!(
            ErrorName::parse("EA0C").unwrap().kind(),
            ErrorKind::Orientation
        );
        const EX0B: ErrorName = ErrorName::from_static("EX0B");
        assert_eq!(EX0B, "EX0B");
    }

    #[test]
    fn bad_names_are_refused_with_what_is_wrong() {
        for (s, why) in [
            ("", "exactly 4 characters"),
            ("EX0", "exactly 4 characters"),
            ("EX0BB", "exactly 4 characters"),
            (" EX0B", "exactly 4 characters"),
            ("ch1", "exactly 4 characters"),
            ("ex0b", "begin with E"),
            ("XX0B", "begin with E"),
            ("EQ0B", "second character"),
            ("Ex0B", "second character"),
            ("EX1B", "third character must be 0"),
            ("EX0X", "rotary axis A, B, C or D"),
            ("EX0E", "rotary axis A, B, C or D"),
            ("EÅ0B", "exactly 4 characters"),
        ] {
            let e = ErrorName::parse(s).unwrap_err();
            let m = e.to_string();
            assert!(m.contains(why), "{s}: {m}");
            assert!(m.contains(&format!("{s:?}")), "{s}: {m}");
        }
        let long = "E".repeat(1000);
        assert_eq!(ErrorName::parse(&long).unwrap_err().name.len(), 32);
    }

    #[test]
    fn order_equality_and_hash_are_the_strings() {
        let mut names: Vec<ErrorName> = ALL.iter().map(|s| ErrorName::parse(s).unwrap()).collect();
        let mut strings: Vec<&str> = ALL.to_vec();
        names.sort();
        strings.sort();
        assert_eq!(
            names.iter().map(|n| n.as_str()).collect::<Vec<_>>(),
            strings
        );
        for a in ALL {
            for b in ALL {
                let (x, y) = (ErrorName::parse(a).unwrap(), ErrorName::parse(b).unwrap());
                assert_eq!(x.cmp(&y), a.cmp(b), "{a} {b}");
                assert_eq!(x == y, a == b);
            }
        }
        let hash = |h: &dyn Fn(&mut std::collections::hash_map::DefaultHasher)| {
            let mut s = std::collections::hash_map::DefaultHasher::new();
            h(&mut s);
            s.finish()
        };
        let n = ErrorName::parse("EB0C").unwrap();
        assert_eq!(hash(&|s| n.hash(s)), hash(&|s| "EB0C".hash(s)));
        // Looked up by &str through Borrow.
        let m: BTreeMap<ErrorName, f64> = [(n, 1.0)].into_iter().collect();
        assert_eq!(m.get("EB0C"), Some(&1.0));
        assert_eq!(m.get("EA0C"), None);
    }

    #[test]
    fn serde_is_the_plain_string_and_refuses_a_bad_name() {
        let m: BTreeMap<ErrorName, f64> = ALL
            .iter()
            .enumerate()
            .map(|(i, s)| (ErrorName::parse(s).unwrap(), i as f64))
            .collect();
        let s: BTreeMap<String, f64> = m.iter().map(|(k, v)| (k.to_string(), *v)).collect();
        let json = serde_json::to_string(&m).unwrap();
        assert_eq!(json, serde_json::to_string(&s).unwrap());
        assert_eq!(
            serde_json::from_str::<BTreeMap<ErrorName, f64>>(&json).unwrap(),
            m
        );
        let n = ErrorName::parse("EA0C").unwrap();
        assert_eq!(serde_json::to_string(&n).unwrap(), "\"EA0C\"");
        assert_eq!(serde_json::from_str::<ErrorName>("\"EA0C\"").unwrap(), n);
        let e = serde_json::from_str::<ErrorName>("\"EA0Q\"")
            .unwrap_err()
            .to_string();
        assert!(e.contains("bad location error name \"EA0Q\""), "{e}");
        let e = serde_json::from_str::<BTreeMap<ErrorName, f64>>(r#"{"ch1": 1.0}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("\"ch1\""), "{e}");
        let e = serde_json::from_str::<ErrorName>("3")
            .unwrap_err()
            .to_string();
        assert!(e.contains("a location error name"), "{e}");
    }
}
