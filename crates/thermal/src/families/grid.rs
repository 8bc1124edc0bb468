//! The sampling grid: a channel and its inputs on a regular grid of times, and the step used
//! when none is given.

use crate::model::{self, Event};
use driftwatch_core::units;

/// One channel on a regular grid: the latest reading and the latest value of every input
/// at each grid time (held between readings).
#[derive(Debug, Clone)]
pub struct Grid {
    pub channel: String,
    pub t_ns: Vec<i64>,
    pub y: Vec<f64>,
    /// Input names: the temperature sensors, then `spindle_rpm` when the spindle turned.
    pub names: Vec<String>,
    /// `inputs[j][k]`: input j at grid time k.
    pub inputs: Vec<Vec<f64>>,
    /// `fresh[k]`: a reading of the channel arrived since the grid time before (else `y[k]`
    /// is the last reading held). Fits and scores use fresh points only: a sensor that holds
    /// its value while the machine stands says nothing then.
    pub fresh: Vec<bool>,
}

impl Grid {
    pub fn len(&self) -> usize {
        self.t_ns.len()
    }
    pub fn is_empty(&self) -> bool {
        self.t_ns.is_empty()
    }
    /// The first grid index at or after `t_ns`.
    pub fn index_at(&self, t_ns: i64) -> usize {
        self.t_ns.partition_point(|&t| t < t_ns)
    }
}

/// Sample `channel` and the inputs every `step_ns`, from the first time the channel and
/// every input have a value. A spindle that never turned is no input (a column of zeros
/// says nothing and makes every design singular).
pub fn grid(events: &[Event], channel: &str, step_ns: i64) -> Option<Grid> {
    let sensors = model::sensors_of(events);
    let spins = events
        .iter()
        .any(|e| matches!(e, Event::Spindle { rpm, .. } if *rpm != 0.0));
    let mut names = sensors.clone();
    if spins {
        names.push("spindle_rpm".into());
    }
    let mut now: Vec<Option<f64>> = vec![None; names.len()];
    if spins {
        // The spindle is off until told otherwise.
        if let Some(last) = now.last_mut() {
            *last = Some(0.0);
        }
    }
    let mut y: Option<f64> = None;
    let step_ns = step_ns.max(1);
    let mut g = Grid {
        channel: channel.to_string(),
        t_ns: Vec::new(),
        y: Vec::new(),
        names: names.clone(),
        inputs: vec![Vec::new(); names.len()],
        fresh: Vec::new(),
    };
    let mut fresh = false;
    let mut next: Option<i64> = None;
    let mut k = 0;
    let last_t = events.last()?.t_ns();
    loop {
        // Take every event up to the next grid time (or the first event).
        let until = next.unwrap_or(events.first()?.t_ns());
        while k < events.len() && events[k].t_ns() <= until {
            match &events[k] {
                Event::Spindle { rpm, .. } if spins => {
                    if let Some(last) = now.last_mut() {
                        *last = Some(*rpm);
                    }
                }
                Event::Temperature {
                    sensor, celsius, ..
                } => {
                    if let Ok(i) = sensors.binary_search(sensor) {
                        now[i] = Some(*celsius);
                    }
                }
                Event::Observation {
                    channel: c, value, ..
                } if c == channel => {
                    y = Some(*value);
                    fresh = true;
                }
                _ => {}
            }
            k += 1;
        }
        if let (Some(v), true) = (y, now.iter().all(Option::is_some)) {
            g.t_ns.push(until);
            g.y.push(v);
            g.fresh.push(std::mem::take(&mut fresh));
            for (j, x) in now.iter().enumerate() {
                g.inputs[j].push(x.unwrap_or(0.0));
            }
        }
        let t = until.checked_add(step_ns)?;
        if t > last_t {
            break;
        }
        next = Some(t);
    }
    (!g.is_empty()).then_some(g)
}

/// The grid step for runs of a thermal test when none is given: the temperatures' median
/// sample spacing, but at least a 400th of the shortest run (a fine grid on a long test only
/// costs time; a coarse one on a short run leaves least squares on two dozen inputs with too
/// few rows to fit).
pub fn default_step_ns(runs: &[&[Event]]) -> i64 {
    let mut spacing = Vec::new();
    let mut shortest = i64::MAX;
    for r in runs {
        let t: Vec<i64> = r
            .iter()
            .filter(|e| matches!(e, Event::Temperature { .. }))
            .map(Event::t_ns)
            .collect();
        spacing.extend(t.windows(2).map(|w| w[1] - w[0]).filter(|d| *d > 0));
        if let (Some(a), Some(b)) = (t.first(), t.last()) {
            shortest = shortest.min(b - a);
        }
    }
    spacing.sort_unstable();
    let median = spacing
        .get(spacing.len() / 2)
        .copied()
        .unwrap_or(units::NS_PER_MIN);
    median.max(shortest / 400).max(1)
}
