//! Error time series for dashboards: the validated values of each error, and their
//! aggregation into fixed time buckets (`?every=`). Pure code.

use std::collections::BTreeMap;

use serde::Serialize;

/// One value of one error: measured (at a cycle's reference time) or predicted (when the
/// service served it).
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct ErrorSample {
    pub t_ns: i64,
    /// The cycle that measured it, or the last cycle before a prediction.
    pub cycle: i64,
    pub name: String,
    pub value: f64,
    pub sigma: f64,
    /// `measured` or `predicted`.
    pub source: String,
}

/// The samples of one error and source that fall in one bucket.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct ErrorBucket {
    /// Start of the bucket (a multiple of its width since the Unix epoch), ns.
    pub t_ns: i64,
    pub name: String,
    pub source: String,
    pub n: usize,
    /// Inverse-variance weighted mean of the values in the bucket.
    pub value: f64,
    /// Standard uncertainty of that mean from the values' own uncertainties. It does not
    /// include the drift within the bucket: `min` and `max` show that.
    pub sigma: f64,
    pub min: f64,
    pub max: f64,
    /// The last cycle that contributed.
    pub last_cycle: i64,
}

/// Parse a bucket width: seconds (`900`) or a number with a unit `s`, `m`, `h`, `d`
/// (`15m`, `1h`, `0.5d`). At least one second.
pub fn parse_every(text: &str) -> Result<i64, String> {
    let t = text.trim();
    let (num, unit) = match t.char_indices().last() {
        Some((i, c)) if c.is_ascii_alphabetic() => (&t[..i], c),
        _ => (t, 's'),
    };
    let scale = match unit {
        's' => 1.0,
        'm' => 60.0,
        'h' => 3600.0,
        'd' => 86400.0,
        u => {
            return Err(format!(
                "every = '{text}': unknown unit '{u}' (use s, m, h or d)"
            ));
        }
    };
    let v: f64 = num
        .trim()
        .parse()
        .map_err(|_| format!("every = '{text}' is not a duration such as 900, 15m or 1h"))?;
    let s = v * scale;
    if !(1.0..=366.0 * 86400.0).contains(&s) {
        return Err(format!("every = '{text}' must be between 1 s and 366 d"));
    }
    Ok((s * 1e9).round() as i64)
}

/// Aggregate samples into buckets of `every_ns`, one row per bucket and error, in time order.
pub fn downsample(samples: &[ErrorSample], every_ns: i64) -> Vec<ErrorBucket> {
    #[derive(Default)]
    struct Acc {
        n: usize,
        w: f64,
        wx: f64,
        min: f64,
        max: f64,
        last_cycle: i64,
    }
    let mut acc: BTreeMap<(i64, &str, &str), Acc> = BTreeMap::new();
    for s in samples {
        let start = s.t_ns.div_euclid(every_ns) * every_ns;
        let a = acc.entry((start, &s.name, &s.source)).or_insert(Acc {
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            ..Default::default()
        });
        // A sample without a usable uncertainty counts like one at 1 (unit) rather than
        // dominating the mean.
        let w = if s.sigma.is_finite() && s.sigma > 0.0 {
            1.0 / (s.sigma * s.sigma)
        } else {
            1.0
        };
        a.n += 1;
        a.w += w;
        a.wx += w * s.value;
        a.min = a.min.min(s.value);
        a.max = a.max.max(s.value);
        a.last_cycle = a.last_cycle.max(s.cycle);
    }
    acc.into_iter()
        .map(|((t_ns, name, source), a)| ErrorBucket {
            t_ns,
            name: name.to_string(),
            source: source.to_string(),
            n: a.n,
            value: a.wx / a.w,
            sigma: (1.0 / a.w).sqrt(),
            min: a.min,
            max: a.max,
            last_cycle: a.last_cycle,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::units;

    const MIN: i64 = units::NS_PER_MIN;

    fn s(t_min: i64, name: &str, value: f64, sigma: f64) -> ErrorSample {
        ErrorSample {
            t_ns: t_min * MIN,
            cycle: t_min,
            name: name.into(),
            value,
            sigma,
            source: "measured".into(),
        }
    }

    #[test]
    fn durations_parse_with_units_and_bad_ones_are_named() {
        assert_eq!(parse_every("900").unwrap(), 900 * 1_000_000_000);
        assert_eq!(parse_every("15m").unwrap(), 15 * MIN);
        assert_eq!(parse_every("1h").unwrap(), 60 * MIN);
        assert_eq!(parse_every("0.5d").unwrap(), 720 * MIN);
        for bad in ["", "0", "-5m", "abc", "3w", "NaNs", "0.1"] {
            assert!(parse_every(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn buckets_hold_weighted_means_and_their_spread() {
        let samples = [
            s(1, "EZ0B", 10.0, 1.0),
            s(1, "EX0B", 5.0, 1.0),
            s(20, "EZ0B", 13.0, 0.5),
            s(59, "EZ0B", 40.0, 1.0),
            s(60, "EZ0B", 50.0, 2.0),
            s(-1, "EZ0B", 1.0, 1.0),
        ];
        let b = downsample(&samples, 30 * MIN);
        let rows: Vec<(i64, &str, usize)> = b
            .iter()
            .map(|r| (r.t_ns / MIN, r.name.as_str(), r.n))
            .collect();
        assert_eq!(
            rows,
            [
                (-30, "EZ0B", 1),
                (0, "EX0B", 1),
                (0, "EZ0B", 2),
                (30, "EZ0B", 1),
                (60, "EZ0B", 1)
            ]
        );
        let ez = &b[2];
        // weights 1 and 4: (10 + 4 * 13) / 5
        assert!((ez.value - 12.4).abs() < 1e-12);
        assert!((ez.sigma - (0.2f64).sqrt()).abs() < 1e-12);
        assert_eq!((ez.min, ez.max, ez.last_cycle), (10.0, 13.0, 20));
        // One sample per bucket gives the sample back.
        let one = downsample(&samples, units::NS_PER_MIN / 60);
        assert_eq!(one.len(), samples.len());
        assert!(one.iter().all(|r| r.n == 1));
    }
}
