//! The machine's timeline: spindle, temperature and observation events, and the events of
//! recordings.

use driftwatch_core::recording::{Recording, ResultStatus};

/// What happens on the machine's timeline, in time order.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    Spindle {
        t_ns: i64,
        rpm: f64,
    },
    Temperature {
        t_ns: i64,
        sensor: String,
        celsius: f64,
    },
    /// A measured value of a channel; `sigma` its standard uncertainty when known.
    Observation {
        t_ns: i64,
        channel: String,
        value: f64,
        sigma: Option<f64>,
    },
}

impl Event {
    pub fn t_ns(&self) -> i64 {
        match self {
            Event::Spindle { t_ns, .. }
            | Event::Temperature { t_ns, .. }
            | Event::Observation { t_ns, .. } => *t_ns,
        }
    }
}

/// The temperature sensors the events name, sorted and unique.
pub fn sensors_of(events: &[Event]) -> Vec<String> {
    let mut v: Vec<String> = events
        .iter()
        .filter_map(|e| match e {
            Event::Temperature { sensor, .. } => Some(sensor.clone()),
            _ => None,
        })
        .collect();
    v.sort();
    v.dedup();
    v
}

/// The timeline of recordings: spindle, temperatures, displacement readings and the errors of
/// every validated (`ok`) cycle result at its reference time. Inputs sort before observations
/// at the same time.
pub fn events_from(recordings: &[Recording]) -> Vec<Event> {
    let mut ev = Vec::new();
    for r in recordings {
        ev.extend(r.spindle.iter().map(|m| Event::Spindle {
            t_ns: m.t_ns,
            rpm: m.msg.rpm,
        }));
        ev.extend(r.temperatures.iter().map(|m| Event::Temperature {
            t_ns: m.t_ns,
            sensor: m.msg.sensor.clone(),
            celsius: m.msg.celsius,
        }));
        ev.extend(r.displacements.iter().map(|m| Event::Observation {
            t_ns: m.t_ns,
            channel: m.msg.sensor.clone(),
            value: m.msg.um,
            sigma: None,
        }));
        for res in &r.results {
            let m = &res.msg;
            if m.status != ResultStatus::Ok {
                continue;
            }
            let (Some(errors), sigma) = (&m.errors, &m.sigma) else {
                continue;
            };
            for (name, v) in errors {
                ev.push(Event::Observation {
                    t_ns: m.t_ns,
                    channel: name.clone(),
                    value: *v,
                    sigma: sigma.as_ref().and_then(|s| s.get(name)).copied(),
                });
            }
        }
    }
    ev.sort_by_key(|e| (e.t_ns(), matches!(e, Event::Observation { .. })));
    ev
}
