//! Null recordings that look like real data, to calibrate the diagnosis: the readings of a
//! channel replaced by slow noise (a random walk, an AR process) that no input drives, or
//! the temperatures replaced by phase-randomised surrogates (the same amplitude spectrum,
//! random phases: no relation to the readings, as the diagnosis' own
//! significance test makes them) or by a block-shuffled copy (the same
//! values and short-range shape, their order in time broken). Whatever a diagnosis accepts
//! on such a recording, beyond the effect injected into it, is a false positive.
//!
//! Pure and deterministic given the seed.

use driftwatch_core::units;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use driftwatch_diagnosis::surrogates::phase_randomised;
use driftwatch_thermal::model::Event;

/// The kinds of null recording.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Null {
    /// The channel's readings are a random walk (plus white reading noise).
    RandomWalk,
    /// The channel's readings are a slow AR(2) process (plus white reading noise).
    ArNoise,
    /// Every temperature phase-randomised; the readings and the spindle as recorded.
    PhaseRandomised,
    /// Every temperature cut into blocks that are put in a random order (the same order for
    /// every sensor); the readings and the spindle as recorded.
    ShuffledBlocks,
}

impl Null {
    pub const ALL: [Null; 4] = [
        Null::RandomWalk,
        Null::ArNoise,
        Null::PhaseRandomised,
        Null::ShuffledBlocks,
    ];
    pub fn as_str(self) -> &'static str {
        match self {
            Null::RandomWalk => "random_walk",
            Null::ArNoise => "ar_noise",
            Null::PhaseRandomised => "phase_randomised",
            Null::ShuffledBlocks => "shuffled_blocks",
        }
    }
    /// Whether the readings are replaced (then every accepted term is false), or the
    /// temperatures (then every accepted temperature term is).
    pub fn replaces_readings(self) -> bool {
        matches!(self, Null::RandomWalk | Null::ArNoise)
    }
}

/// A random order of `n` samples in blocks of `block` (the last may be shorter).
pub fn block_order(n: usize, block: usize, rng: &mut impl Rng) -> Vec<usize> {
    let block = block.max(1);
    let mut starts: Vec<usize> = (0..n).step_by(block).collect();
    // Fisher-Yates.
    for i in (1..starts.len()).rev() {
        let j = rng.random_range(0..=i);
        starts.swap(i, j);
    }
    starts
        .into_iter()
        .flat_map(|s| s..(s + block).min(n))
        .collect()
}

/// A random walk of `n` steps of standard deviation `step`, from 0.
pub fn random_walk(n: usize, step: f64, rng: &mut impl Rng) -> Vec<f64> {
    let mut x = 0.0;
    (0..n)
        .map(|_| {
            x += step * rng.sample::<f64, _>(StandardNormal);
            x
        })
        .collect()
}

/// A stationary AR(2) process with a double pole at `pole` (0..1) and innovations of
/// standard deviation `sigma`, started at 0.
pub fn ar2(n: usize, pole: f64, sigma: f64, rng: &mut impl Rng) -> Vec<f64> {
    let (a1, a2) = (2.0 * pole, -pole * pole);
    let (mut x1, mut x2) = (0.0, 0.0);
    (0..n)
        .map(|_| {
            let x = a1 * x1 + a2 * x2 + sigma * rng.sample::<f64, _>(StandardNormal);
            x2 = x1;
            x1 = x;
            x
        })
        .collect()
}

/// Each temperature sensor resampled every `step_ns` (the last value at or before each
/// time, from its first reading), as `(sensor, times, values)`.
fn temperature_grid(events: &[Event], step_ns: i64) -> Vec<(String, Vec<i64>, Vec<f64>)> {
    let sensors = driftwatch_thermal::model::sensors_of(events);
    let end = events.last().map_or(0, Event::t_ns);
    sensors
        .into_iter()
        .map(|s| {
            let mine: Vec<(i64, f64)> = events
                .iter()
                .filter_map(|e| match e {
                    Event::Temperature {
                        t_ns,
                        sensor,
                        celsius,
                    } if *sensor == s => Some((*t_ns, *celsius)),
                    _ => None,
                })
                .collect();
            let (mut t, mut v) = (Vec::new(), Vec::new());
            if let Some(&(t0, _)) = mine.first() {
                let mut k = 0;
                let mut now = t0;
                while now <= end {
                    while k + 1 < mine.len() && mine[k + 1].0 <= now {
                        k += 1;
                    }
                    t.push(now);
                    v.push(mine[k].1);
                    now += step_ns.max(1);
                }
            }
            (s, t, v)
        })
        .collect()
}

fn sorted(mut ev: Vec<Event>) -> Vec<Event> {
    ev.sort_by_key(Event::t_ns);
    ev
}

/// A null recording of kind `null` made from `events`, for `channel` (the readings kinds),
/// seeded. Temperature kinds resample every sensor to `step_ns` first. `noise_um` scales
/// the slow noise: the random walk's standard deviation after 10 h, and the AR process's
/// stationary standard deviation; 0.1 um of white reading noise is added to both.
pub fn null_recording(
    events: &[Event],
    null: Null,
    channel: &str,
    step_ns: i64,
    noise_um: f64,
    seed: u64,
) -> Vec<Event> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    if null.replaces_readings() {
        let n = events
            .iter()
            .filter(|e| matches!(e, Event::Observation { channel: c, .. } if c == channel))
            .count();
        let times: Vec<i64> = events
            .iter()
            .filter_map(|e| match e {
                Event::Observation {
                    t_ns, channel: c, ..
                } if c == channel => Some(*t_ns),
                _ => None,
            })
            .collect();
        let dt_h = match (times.first(), times.last()) {
            (Some(a), Some(b)) if n > 1 => units::ns_to_h(b - a) / (n - 1) as f64,
            _ => 1.0,
        };
        let slow = match null {
            Null::RandomWalk => random_walk(n, noise_um * (dt_h / 10.0).sqrt(), &mut rng),
            _ => {
                // A double pole with a 2-h time constant; innovations scaled to the wanted
                // stationary standard deviation (for a double pole p: var = s^2 (1 + p^2) /
                // (1 - p^2)^3).
                let p = (-dt_h / 2.0).exp();
                let s = noise_um * ((1.0 - p * p).powi(3) / (1.0 + p * p)).sqrt();
                ar2(n, p, s, &mut rng)
            }
        };
        return map_readings(events, channel, |k, _| {
            slow[k] + 0.1 * rng.sample::<f64, _>(StandardNormal)
        });
    }
    let grid = temperature_grid(events, step_ns);
    // Two hours a block: longer than the lags the candidates use, so a block keeps a
    // temperature's short-range shape.
    let block = (2.0 * units::NS_PER_H as f64 / step_ns.max(1) as f64).round() as usize;
    let order = block_order(grid.first().map_or(0, |g| g.2.len()), block, &mut rng);
    let mut out: Vec<Event> = events
        .iter()
        .filter(|e| !matches!(e, Event::Temperature { .. }))
        .cloned()
        .collect();
    for (sensor, t, v) in grid {
        let new = match null {
            Null::PhaseRandomised => phase_randomised(&v, &mut rng),
            _ => order.iter().filter_map(|&i| v.get(i).copied()).collect(),
        };
        out.extend(
            t.iter()
                .zip(new)
                .map(|(&t_ns, celsius)| Event::Temperature {
                    t_ns,
                    sensor: sensor.clone(),
                    celsius,
                }),
        );
    }
    sorted(out)
}

/// `events` with an effect of `sensor` added to `channel`'s readings: a gain times the
/// sensor's change since `from_ns` (0 before it; from the first reading when `None`), the
/// gain chosen so that the added series has RMS `rms_um` over the readings. The sensor's
/// value at a reading is its last reading at or before it.
pub fn with_temperature_effect(
    events: &[Event],
    channel: &str,
    sensor: &str,
    rms_um: f64,
    from_ns: Option<i64>,
) -> Vec<Event> {
    let mut now: Option<f64> = None;
    let mut at_from: Option<f64> = None;
    let from = from_ns.unwrap_or(i64::MIN);
    // First pass: the change at each reading.
    let mut change = Vec::new();
    for e in events {
        match e {
            Event::Temperature {
                sensor: s, celsius, ..
            } if s == sensor => now = Some(*celsius),
            Event::Observation {
                t_ns, channel: c, ..
            } if c == channel => {
                if *t_ns >= from && at_from.is_none() {
                    at_from = now;
                }
                change.push(match (now, at_from) {
                    (Some(v), Some(v0)) if *t_ns >= from => v - v0,
                    _ => 0.0,
                });
            }
            _ => {}
        }
    }
    let r = (change.iter().map(|v| v * v).sum::<f64>() / change.len().max(1) as f64).sqrt();
    let gain = if r > 0.0 { rms_um / r } else { 0.0 };
    map_readings(events, channel, |k, v| v + gain * change[k])
}

/// `events` with the `k`-th reading `v` of `channel` replaced by `f(k, v)`.
fn map_readings(
    events: &[Event],
    channel: &str,
    mut f: impl FnMut(usize, f64) -> f64,
) -> Vec<Event> {
    let mut k = 0;
    events
        .iter()
        .map(|e| match e {
            Event::Observation {
                t_ns,
                channel: c,
                value,
                sigma,
            } if c == channel => {
                let v = f(k, *value);
                k += 1;
                Event::Observation {
                    t_ns: *t_ns,
                    channel: c.clone(),
                    value: v,
                    sigma: *sigma,
                }
            }
            other => other.clone(),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_block_order_is_a_permutation_of_whole_blocks() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let o = block_order(23, 5, &mut rng);
        let mut s = o.clone();
        s.sort_unstable();
        assert_eq!(s, (0..23).collect::<Vec<_>>());
        assert_ne!(o, (0..23).collect::<Vec<_>>());
        // Within a block the order runs on.
        let runs = o.windows(2).filter(|w| w[1] != w[0] + 1).count();
        assert!(runs <= 4, "{o:?}");
    }

    #[test]
    fn the_noise_has_the_size_asked_for() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let p = (-1.0f64 / 24.0).exp();
        let s = ((1.0 - p * p).powi(3) / (1.0 + p * p)).sqrt();
        let x = ar2(200_000, p, s, &mut rng);
        let sd = (x.iter().map(|v| v * v).sum::<f64>() / x.len() as f64).sqrt();
        assert!((sd - 1.0).abs() < 0.1, "{sd}");
        let w = random_walk(100, 0.5, &mut rng);
        assert_eq!(w.len(), 100);
    }
}
