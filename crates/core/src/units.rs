//! Units at the interfaces and the conversions between them, so that a time in ns, a duration
//! in minutes and an error's unit are spelled one way across the project.
//!
//! The conventions (docs/kinematics-conventions.md): times are ns since the Unix epoch (`i64`),
//! positions and angles commanded are mm and deg, location errors are um (position) or urad
//! (orientation), as their parsed name says ([`crate::error_name::ErrorName::unit`]). Inside,
//! the models work in mm, rad and minutes or hours.

/// Nanoseconds in a second.
pub const NS_PER_S: i64 = 1_000_000_000;
/// Nanoseconds in a minute.
pub const NS_PER_MIN: i64 = 60 * NS_PER_S;
/// Nanoseconds in an hour.
pub const NS_PER_H: i64 = 60 * NS_PER_MIN;
/// Nanoseconds in a day.
pub const NS_PER_DAY: i64 = 24 * NS_PER_H;

/// A duration in ns as minutes.
pub fn ns_to_min(ns: i64) -> f64 {
    ns as f64 / NS_PER_MIN as f64
}

/// A duration in ns as hours.
pub fn ns_to_h(ns: i64) -> f64 {
    ns as f64 / NS_PER_H as f64
}

/// A duration in ns as seconds.
pub fn ns_to_s(ns: i64) -> f64 {
    ns as f64 / NS_PER_S as f64
}

/// Minutes as a duration in ns, rounded (saturating for absurd values; NaN gives 0).
pub fn min_to_ns(minutes: f64) -> i64 {
    (minutes * NS_PER_MIN as f64).round() as i64
}

/// Hours as a duration in ns, rounded (saturating; NaN gives 0).
pub fn h_to_ns(hours: f64) -> i64 {
    (hours * NS_PER_H as f64).round() as i64
}

/// Seconds as a duration in ns, rounded (saturating; NaN gives 0).
pub fn s_to_ns(seconds: f64) -> i64 {
    (seconds * NS_PER_S as f64).round() as i64
}

/// A finite number above zero (false for NaN).
pub fn positive(x: f64) -> bool {
    x.is_finite() && x > 0.0
}

/// A finite number of at least zero (false for NaN).
pub fn non_negative(x: f64) -> bool {
    x.is_finite() && x >= 0.0
}

/// The fastest spindle speed any machine tool turns, min^-1 (either sense): no model takes a
/// speed beyond it (a value of 1e300 made every state infinite and every prediction NaN).
pub const MAX_PLAUSIBLE_RPM: f64 = 200_000.0;

/// The temperatures a machine tool's sensors can read, deg C.
pub const PLAUSIBLE_CELSIUS: (f64, f64) = (-60.0, 200.0);

/// A spindle speed a model takes: finite and within [`MAX_PLAUSIBLE_RPM`].
pub fn plausible_rpm(rpm: f64) -> bool {
    rpm.is_finite() && rpm.abs() <= MAX_PLAUSIBLE_RPM
}

/// A temperature a model takes: within [`PLAUSIBLE_CELSIUS`].
pub fn plausible_celsius(celsius: f64) -> bool {
    (PLAUSIBLE_CELSIUS.0..=PLAUSIBLE_CELSIUS.1).contains(&celsius)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conversions_round_trip_and_name_the_units() {
        assert_eq!(NS_PER_DAY, 86_400 * NS_PER_S);
        assert_eq!(min_to_ns(1.5), 90 * NS_PER_S);
        assert_eq!(ns_to_min(min_to_ns(37.25)), 37.25);
        assert_eq!(ns_to_h(h_to_ns(3.5)), 3.5);
        assert_eq!(ns_to_s(s_to_ns(0.25)), 0.25);
        assert_eq!(min_to_ns(f64::NAN), 0);
        assert!(!positive(f64::NAN) && !non_negative(-1e-12) && non_negative(0.0));
        assert!(plausible_rpm(-12_000.0) && !plausible_rpm(1e300) && !plausible_rpm(f64::NAN));
        assert!(plausible_celsius(20.0) && !plausible_celsius(f64::NAN));
    }
}
