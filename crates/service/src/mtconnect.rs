//! MTConnect without I/O: an agent's XML documents as typed observations, and the bookkeeping
//! that follows an agent's `sample` stream across agent restarts and buffer overruns.
//!
//! An MTConnect agent keeps a ring buffer of observations numbered by a `sequence` that rises
//! by one per observation; every answer's `Header` gives the buffer's `firstSequence`,
//! `lastSequence` and `nextSequence` and the agent's `instanceId`, which changes whenever the
//! agent restarts (its sequence numbers then start again). A client reads `current` once for
//! the state in force and `nextSequence`, then asks `sample?from=<next>&count=N` over and over.
//! Two things break the chain and are handled here:
//! - an agent restart: the `instanceId` changes. The follower re-reads `current` and resumes
//!   at the new instance's `firstSequence` (the oldest observation it still holds), so nothing
//!   the new agent saw is skipped; an observation no later than the last one taken of its data
//!   item is not taken again (a restarted agent announces the values it starts with);
//! - a gap: the follower fell behind and the agent's buffer moved past `from` (the agent
//!   answers `OUT_OF_RANGE`, or a lenient one starts its answer at `firstSequence`). The size
//!   of the gap is `firstSequence - from` observations; they are lost, the follower says so and
//!   resumes at `firstSequence`.
//!
//! Observations become the recording contract's messages (`/spindle`, `/machine/state`,
//! `/temperature`) through the configured data item ids ([`Items`]); the HTTP shell is
//! `mtconnect_link`.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::link::LinkEvent;
use driftwatch_core::kinematics::{Limits, MAX_NAME_CHARS};
use driftwatch_core::recording::{MachineStateKind, SpindleMsg, StateMsg, TemperatureMsg, Timed};

#[derive(Debug, Error, PartialEq)]
pub enum MtcError {
    #[error("not XML: {0}")]
    Xml(String),
    #[error("the document is a <{0}>, not MTConnectStreams or MTConnectError")]
    Root(String),
    #[error("the document has no Header")]
    NoHeader,
    #[error("Header attribute {name}: {message}")]
    Header { name: &'static str, message: String },
    #[error("observation of data item '{item}': {message}")]
    Observation { item: String, message: String },
    #[error("the agent answered {code}: {text}")]
    Agent { code: String, text: String },
}

/// The data item ids (as the agent's `probe` names them) the link maps to the contract.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Items {
    /// The spindle's `RotaryVelocity` (or the older `SpindleSpeed`) SAMPLE, rev/min.
    pub spindle_speed: String,
    /// The controller's `Execution` EVENT.
    pub execution: String,
    /// The controller's `ControllerMode` EVENT (optional): a control in MANUAL or
    /// MANUAL_DATA_INPUT mode is not reported idle.
    #[serde(default)]
    pub controller_mode: Option<String>,
    /// `Temperature` SAMPLEs, deg C, by the sensor name they are recorded under.
    #[serde(default)]
    pub temperatures: BTreeMap<String, String>,
}

/// An agent's `Header`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Header {
    pub instance_id: String,
    /// Absent in an error document.
    pub first_sequence: Option<u64>,
    pub next_sequence: Option<u64>,
    pub last_sequence: Option<u64>,
}

/// One observation of a data item.
#[derive(Debug, Clone, PartialEq)]
pub struct Observation {
    pub item: String,
    pub sequence: u64,
    pub t_ns: i64,
    /// `None` for `UNAVAILABLE`.
    pub value: Option<String>,
}

/// An agent's answer.
#[derive(Debug, Clone, PartialEq)]
pub enum Document {
    Streams {
        header: Header,
        observations: Vec<Observation>,
    },
    Error {
        header: Option<Header>,
        /// `errorCode` and text of each error.
        errors: Vec<(String, String)>,
    },
}

fn attr_u64(node: roxmltree::Node, name: &'static str) -> Result<Option<u64>, MtcError> {
    node.attribute(name)
        .map(|v| {
            v.trim().parse::<u64>().map_err(|e| MtcError::Header {
                name,
                message: format!("'{v}': {e}"),
            })
        })
        .transpose()
}

fn header_of(node: roxmltree::Node) -> Result<Header, MtcError> {
    let instance_id = node
        .attribute("instanceId")
        .ok_or(MtcError::Header {
            name: "instanceId",
            message: "missing".into(),
        })?
        .trim()
        .to_string();
    Ok(Header {
        instance_id,
        first_sequence: attr_u64(node, "firstSequence")?,
        next_sequence: attr_u64(node, "nextSequence")?,
        last_sequence: attr_u64(node, "lastSequence")?,
    })
}

/// An MTConnect timestamp (ISO 8601, UTC; `Z` may be missing in older agents) as ns since the
/// Unix epoch.
pub fn timestamp_ns(s: &str) -> Option<i64> {
    let s = s.trim();
    let dt = chrono::DateTime::parse_from_rfc3339(s)
        .map(|d| d.with_timezone(&chrono::Utc))
        .or_else(|_| {
            chrono::NaiveDateTime::parse_from_str(s, "%Y-%m-%dT%H:%M:%S%.f").map(|n| n.and_utc())
        })
        .ok()?;
    dt.timestamp_nanos_opt()
}

/// Parse an agent's answer. `device` (name or uuid), when given, keeps only that device's
/// streams. Conditions are not read (the link maps samples and events only).
pub fn parse(xml: &str, device: Option<&str>) -> Result<Document, MtcError> {
    let doc = roxmltree::Document::parse(xml).map_err(|e| MtcError::Xml(e.to_string()))?;
    let root = doc.root_element();
    let header = root
        .children()
        .find(|n| n.is_element() && n.tag_name().name() == "Header");
    match root.tag_name().name() {
        "MTConnectError" => {
            let header = header.map(header_of).transpose()?;
            let errors = root
                .descendants()
                .filter(|n| n.is_element() && n.tag_name().name() == "Error")
                .map(|n| {
                    (
                        n.attribute("errorCode").unwrap_or("UNKNOWN").to_string(),
                        n.text().unwrap_or("").trim().to_string(),
                    )
                })
                .collect();
            Ok(Document::Error { header, errors })
        }
        "MTConnectStreams" => {
            let header = header_of(header.ok_or(MtcError::NoHeader)?)?;
            let mut observations = Vec::new();
            let streams = root
                .descendants()
                .filter(|n| n.is_element() && n.tag_name().name() == "DeviceStream")
                .filter(|n| {
                    device.is_none_or(|d| {
                        n.attribute("name") == Some(d) || n.attribute("uuid") == Some(d)
                    })
                });
            for ds in streams {
                let groups = ds.descendants().filter(|n| {
                    n.is_element() && matches!(n.tag_name().name(), "Samples" | "Events")
                });
                for group in groups {
                    for o in group.children().filter(|n| n.is_element()) {
                        observations.push(observation_of(o)?);
                    }
                }
            }
            observations.sort_by_key(|o| o.sequence);
            Ok(Document::Streams {
                header,
                observations,
            })
        }
        other => Err(MtcError::Root(other.to_string())),
    }
}

fn observation_of(o: roxmltree::Node) -> Result<Observation, MtcError> {
    let item = o.attribute("dataItemId").unwrap_or("").to_string();
    let bad = |message: String| MtcError::Observation {
        item: item.clone(),
        message,
    };
    let sequence = o
        .attribute("sequence")
        .ok_or_else(|| bad("no sequence".into()))?
        .trim()
        .parse::<u64>()
        .map_err(|e| bad(format!("sequence: {e}")))?;
    let ts = o
        .attribute("timestamp")
        .ok_or_else(|| bad("no timestamp".into()))?;
    let t_ns = timestamp_ns(ts).ok_or_else(|| bad(format!("timestamp '{ts}' is not ISO 8601")))?;
    let text = o.text().unwrap_or("").trim();
    let value = (text != "UNAVAILABLE").then(|| text.to_string());
    Ok(Observation {
        item,
        sequence,
        t_ns,
        value,
    })
}

/// What the follower asks the agent for next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request {
    /// `current`: the state in force and the header.
    Current,
    /// `sample?from=..&count=..`.
    Sample { from: u64, count: u32 },
}

/// Something the follower has to say besides the observations (the shell logs it).
#[derive(Debug, Clone, PartialEq)]
pub enum Note {
    /// The agent restarted: another instance, whose sequence numbers start again.
    Restarted { old: String, new: String },
    /// `lost` observations fell out of the agent's buffer before they were read.
    Gap { from: u64, first: u64, lost: u64 },
    /// An observation of a mapped item that is not taken (not a number, beyond the machine's
    /// limits, a name too long).
    Refused { item: String, message: String },
    /// The agent's numbering lies behind the `from` asked for although its instance is the
    /// same: resumed at its `next`.
    Rewound { from: u64, next: u64 },
    /// The data item is UNAVAILABLE (the agent lost its adapter, or the machine is off): the
    /// last value holds, since the agent cannot say which.
    Unavailable { item: String },
}

/// Counters since the start.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct FollowStats {
    pub restarts: u64,
    pub gaps: u64,
    pub lost_observations: u64,
    pub taken: u64,
}

/// The state of following one agent.
#[derive(Debug, Clone)]
pub struct Follower {
    items: Items,
    limits: Limits,
    count: u32,
    instance: Option<String>,
    /// The next sequence to read; `None` until `current` is read (again).
    from: Option<u64>,
    /// The `from` an OUT_OF_RANGE answer refused, until `current` gives the buffer's bounds.
    refused_from: Option<u64>,
    /// Per data item, the time and value of the last observation taken.
    taken: BTreeMap<String, (i64, Option<String>)>,
    execution: Option<String>,
    mode: Option<String>,
    state: Option<MachineStateKind>,
    /// The last sample answer ended before the agent's last sequence: ask again at once.
    pub behind: bool,
    pub stats: FollowStats,
}

/// How MTConnect's `Execution` (and `ControllerMode`) map to driftwatch's NC state. `None`:
/// not known (the state in force holds).
///
/// - `ACTIVE`: a program runs: `cutting` (MTConnect cannot tell machining from a warm-up
///   program; driftwatch's phase follows the spindle speed either way).
/// - `INTERRUPTED`, `FEED_HOLD`, `WAIT`, `OPTIONAL_STOP`, `PROGRAM_OPTIONAL_STOP`: a program
///   is under way and will go on: `cutting` (the machine is not free).
/// - `READY`, `STOPPED`, `PROGRAM_STOPPED`, `PROGRAM_COMPLETED`: no program runs: `idle`,
///   unless the controller mode is `MANUAL` or `MANUAL_DATA_INPUT` (an operator moves the
///   machine by hand): `cutting`, i.e. busy. `EDIT` mode moves nothing and stays `idle`.
/// - `UNAVAILABLE` or an unknown value: nothing.
///
/// Alarms come through MTConnect conditions, which this link does not read.
pub fn machine_state(execution: &str, mode: Option<&str>) -> Option<MachineStateKind> {
    use MachineStateKind::{Cutting, Idle};
    match execution {
        "ACTIVE"
        | "INTERRUPTED"
        | "FEED_HOLD"
        | "WAIT"
        | "OPTIONAL_STOP"
        | "PROGRAM_OPTIONAL_STOP" => Some(Cutting),
        "READY" | "STOPPED" | "PROGRAM_STOPPED" | "PROGRAM_COMPLETED" => match mode {
            Some("MANUAL" | "MANUAL_DATA_INPUT") => Some(Cutting),
            _ => Some(Idle),
        },
        _ => None,
    }
}

impl Follower {
    pub fn new(items: Items, limits: Limits, count: u32) -> Self {
        Follower {
            items,
            limits,
            count: count.max(1),
            instance: None,
            from: None,
            refused_from: None,
            taken: BTreeMap::new(),
            execution: None,
            mode: None,
            state: None,
            behind: false,
            stats: FollowStats::default(),
        }
    }

    pub fn request(&self) -> Request {
        match self.from {
            None => Request::Current,
            Some(from) => Request::Sample {
                from,
                count: self.count,
            },
        }
    }

    /// The agent instance followed.
    pub fn instance(&self) -> Option<&str> {
        self.instance.as_deref()
    }

    /// Take an answer to [`Follower::request`]; returns the contract events (in sequence
    /// order) and notes. An error the agent answered other than OUT_OF_RANGE is returned
    /// (the shell retries the same request later).
    pub fn take(
        &mut self,
        asked: Request,
        doc: Document,
    ) -> Result<(Vec<LinkEvent>, Vec<Note>), MtcError> {
        let mut events = Vec::new();
        let mut notes = Vec::new();
        match (asked, doc) {
            (_, Document::Error { header, errors }) => {
                if let Some(h) = &header
                    && self.instance.as_deref().is_some_and(|i| i != h.instance_id)
                {
                    // A restarted agent that does not know `from`: `current` says the rest.
                    self.from = None;
                    return Ok((events, notes));
                }
                if errors.iter().any(|(code, _)| code == "OUT_OF_RANGE") {
                    // `from` left the buffer (or lies beyond it): `current` gives its bounds.
                    if let Request::Sample { from, .. } = asked {
                        self.refused_from = Some(from);
                    }
                    self.from = None;
                    return Ok((events, notes));
                }
                let (code, text) = errors
                    .into_iter()
                    .next()
                    .unwrap_or(("UNKNOWN".into(), "an error without a code".into()));
                return Err(MtcError::Agent { code, text });
            }
            (
                Request::Current,
                Document::Streams {
                    header,
                    observations,
                },
            ) => {
                let (Some(first), Some(next)) = (header.first_sequence, header.next_sequence)
                else {
                    return Err(MtcError::Header {
                        name: "firstSequence/nextSequence",
                        message: "missing from a streams document".into(),
                    });
                };
                let refused = self.refused_from.take();
                match self.instance.take() {
                    None => {
                        // The first look: the state in force now, then what comes after it.
                        for o in &observations {
                            self.map(o, &mut events, &mut notes);
                        }
                        self.from = Some(next);
                    }
                    Some(old) if old != header.instance_id => {
                        self.stats.restarts += 1;
                        notes.push(Note::Restarted {
                            old,
                            new: header.instance_id.clone(),
                        });
                        // Everything the new instance holds, in order; what was taken before
                        // the restart is not taken again (per item, by time).
                        self.from = Some(first);
                    }
                    Some(_) => {
                        // The same agent, asked again after OUT_OF_RANGE: resume where the
                        // refused request wanted to, or at the buffer's start if that is gone.
                        let want = refused.unwrap_or(next);
                        self.from = Some(if want > next {
                            // Beyond the buffer's end with the same instance (an agent whose
                            // numbering went back): from its end on; the per-item times
                            // keep what was taken from being taken again.
                            notes.push(Note::Rewound { from: want, next });
                            next
                        } else {
                            self.resume(want, first, &mut notes)
                        });
                    }
                }
                self.instance = Some(header.instance_id);
            }
            (
                Request::Sample { from, .. },
                Document::Streams {
                    header,
                    observations,
                },
            ) => {
                if self.instance.as_deref() != Some(header.instance_id.as_str()) {
                    // Restarted between two samples: these sequence numbers are another
                    // instance's; `current` first.
                    self.from = None;
                    return Ok((events, notes));
                }
                let (Some(first), Some(next)) = (header.first_sequence, header.next_sequence)
                else {
                    return Err(MtcError::Header {
                        name: "firstSequence/nextSequence",
                        message: "missing from a streams document".into(),
                    });
                };
                let start = self.resume(from, first, &mut notes);
                for o in observations.iter().filter(|o| o.sequence >= start) {
                    self.map(o, &mut events, &mut notes);
                }
                // The agent says where its answer ended; never go back.
                self.from = Some(next.max(start));
                self.behind = header.last_sequence.is_some_and(|last| next <= last);
            }
        }
        Ok((events, notes))
    }

    /// Where to read from when `want` is asked and the agent holds `first..`: a `want` before
    /// `first` fell out of the buffer, a gap of `first - want` observations.
    fn resume(&mut self, want: u64, first: u64, notes: &mut Vec<Note>) -> u64 {
        if want >= first {
            return want;
        }
        let lost = first - want;
        self.stats.gaps += 1;
        self.stats.lost_observations += lost;
        notes.push(Note::Gap {
            from: want,
            first,
            lost,
        });
        first
    }

    /// One observation as a contract event, if it is of a mapped item and not taken before.
    fn map(&mut self, o: &Observation, events: &mut Vec<LinkEvent>, notes: &mut Vec<Note>) {
        enum Kind {
            Spindle,
            Execution,
            Mode,
            Temperature(String),
        }
        let kind = if o.item == self.items.spindle_speed {
            Kind::Spindle
        } else if o.item == self.items.execution {
            Kind::Execution
        } else if self.items.controller_mode.as_deref() == Some(o.item.as_str()) {
            Kind::Mode
        } else if let Some((sensor, _)) = self
            .items
            .temperatures
            .iter()
            .find(|(_, id)| **id == o.item)
        {
            Kind::Temperature(sensor.clone())
        } else {
            return;
        };
        // Taken already: an older observation, or the same one again (a restarted agent
        // announcing the values it starts with, at their old time).
        if let Some((t, v)) = self.taken.get(&o.item)
            && (o.t_ns < *t || (o.t_ns == *t && *v == o.value))
        {
            return;
        }
        self.taken.insert(o.item.clone(), (o.t_ns, o.value.clone()));
        self.stats.taken += 1;
        let Some(text) = o.value.as_deref() else {
            notes.push(Note::Unavailable {
                item: o.item.clone(),
            });
            return;
        };
        let refuse = |notes: &mut Vec<Note>, message: String| {
            notes.push(Note::Refused {
                item: o.item.clone(),
                message,
            })
        };
        let t_ns = o.t_ns;
        match kind {
            Kind::Spindle => {
                let max = self.limits.spindle_max_rpm;
                match text.parse::<f64>() {
                    Ok(rpm) if rpm.is_finite() && rpm.abs() <= max => {
                        events.push(LinkEvent::Spindle(Timed {
                            t_ns,
                            msg: SpindleMsg { rpm },
                        }))
                    }
                    _ => refuse(
                        notes,
                        format!(
                            "spindle speed '{text}' is not a speed of this spindle (a number, at most {max} min^-1 either way: limits.spindle_max_rpm of the machine file)"
                        ),
                    ),
                }
            }
            Kind::Temperature(sensor) => {
                let [lo, hi] = self.limits.celsius;
                match text.parse::<f64>() {
                    Ok(celsius) if (lo..=hi).contains(&celsius) => {
                        events.push(LinkEvent::Temperature(Timed {
                            t_ns,
                            msg: TemperatureMsg { sensor, celsius },
                        }))
                    }
                    _ => refuse(
                        notes,
                        format!(
                            "temperature '{text}' of sensor '{sensor}' is not one of this machine ({lo} to {hi} deg C: limits.celsius of the machine file)"
                        ),
                    ),
                }
            }
            Kind::Execution | Kind::Mode => {
                if text.chars().count() > MAX_NAME_CHARS {
                    return refuse(
                        notes,
                        format!("a value of {} characters", text.chars().count()),
                    );
                }
                if matches!(kind, Kind::Execution) {
                    self.execution = Some(text.to_string());
                } else {
                    self.mode = Some(text.to_string());
                }
                let Some(exec) = self.execution.as_deref() else {
                    return;
                };
                match machine_state(exec, self.mode.as_deref()) {
                    Some(state) if Some(state) != self.state => {
                        self.state = Some(state);
                        events.push(LinkEvent::State(Timed {
                            t_ns,
                            msg: StateMsg {
                                state,
                                program: None,
                            },
                        }));
                    }
                    Some(_) => {}
                    None => refuse(
                        notes,
                        format!("Execution '{exec}' is not one driftwatch maps"),
                    ),
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A document in the standard's own layout (MTConnectStreams 1.3, as cppagent writes it).
    fn streams(instance: &str, first: u64, next: u64, obs: &[(&str, &str, u64, &str)]) -> String {
        let mut body = String::new();
        for (kind, item, seq, value) in obs {
            body.push_str(&format!(
                r#"<{kind} dataItemId="{item}" timestamp="2026-03-02T06:00:{:02}.250000Z" sequence="{seq}">{value}</{kind}>"#,
                seq % 60
            ));
        }
        format!(
            r#"<?xml version="1.0" encoding="UTF-8"?>
<MTConnectStreams xmlns:m="urn:mtconnect.org:MTConnectStreams:1.3" xmlns="urn:mtconnect.org:MTConnectStreams:1.3">
  <Header creationTime="2026-03-02T06:01:00Z" sender="agent" instanceId="{instance}" version="1.3.0.18" bufferSize="16" nextSequence="{next}" firstSequence="{first}" lastSequence="{}"/>
  <Streams>
    <DeviceStream name="VMC-1" uuid="vmc-1-uuid">
      <ComponentStream component="Rotary" name="C" componentId="c1"><Samples>{body}</Samples></ComponentStream>
      <ComponentStream component="Path" name="path" componentId="p1"><Events></Events><Condition><Normal dataItemId="cond" timestamp="2026-03-02T06:00:00Z" sequence="1" type="SYSTEM"/></Condition></ComponentStream>
    </DeviceStream>
    <DeviceStream name="other" uuid="other"><ComponentStream component="Rotary" name="C" componentId="x"><Samples><RotaryVelocity dataItemId="S1speed" timestamp="2026-03-02T06:00:00Z" sequence="2">99</RotaryVelocity></Samples></ComponentStream></DeviceStream>
  </Streams>
</MTConnectStreams>"#,
            next - 1
        )
    }

    fn follower() -> Follower {
        let items = Items {
            spindle_speed: "S1speed".into(),
            execution: "exec".into(),
            controller_mode: Some("mode".into()),
            temperatures: [("spindle_head".to_string(), "T1".to_string())].into(),
        };
        Follower::new(items, Limits::default(), 100)
    }

    fn feed(f: &mut Follower, xml: &str) -> (Vec<LinkEvent>, Vec<Note>) {
        let asked = f.request();
        f.take(asked, parse(xml, Some("VMC-1")).unwrap()).unwrap()
    }

    fn rpms(ev: &[LinkEvent]) -> Vec<f64> {
        ev.iter()
            .filter_map(|e| match e {
                LinkEvent::Spindle(s) => Some(s.msg.rpm),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn a_streams_document_parses_to_observations_of_the_device() {
        let xml = streams(
            "17",
            1,
            4,
            &[
                ("RotaryVelocity", "S1speed", 3, "12000"),
                ("Temperature", "T1", 2, "UNAVAILABLE"),
            ],
        );
        let Document::Streams {
            header,
            observations,
        } = parse(&xml, Some("vmc-1-uuid")).unwrap()
        else {
            panic!("a streams document")
        };
        assert_eq!(header.instance_id, "17");
        assert_eq!(
            (
                header.first_sequence,
                header.next_sequence,
                header.last_sequence
            ),
            (Some(1), Some(4), Some(3))
        );
        // In sequence order, the condition and the other device left out.
        assert_eq!(observations.len(), 2);
        assert_eq!(observations[0].item, "T1");
        assert_eq!(observations[0].value, None);
        assert_eq!(observations[1].value.as_deref(), Some("12000"));
        assert_eq!(
            observations[1].t_ns,
            timestamp_ns("2026-03-02T06:00:03.25Z").unwrap()
        );
        let Document::Streams { observations, .. } = parse(&xml, None).unwrap() else {
            panic!()
        };
        assert_eq!(observations.len(), 3, "every device without a filter");
    }

    #[test]
    fn errors_and_bad_documents_are_named() {
        let err = r#"<MTConnectError xmlns="urn:mtconnect.org:MTConnectError:1.3"><Header creationTime="2026-03-02T06:01:00Z" sender="a" instanceId="17" version="1.3" bufferSize="16"/><Errors><Error errorCode="OUT_OF_RANGE">'from' must be greater than 4</Error></Errors></MTConnectError>"#;
        let Document::Error { header, errors } = parse(err, None).unwrap() else {
            panic!()
        };
        assert_eq!(header.unwrap().instance_id, "17");
        assert_eq!(errors[0].0, "OUT_OF_RANGE");
        assert!(matches!(parse("<a", None), Err(MtcError::Xml(_))));
        assert!(matches!(
            parse("<MTConnectDevices/>", None),
            Err(MtcError::Root(_))
        ));
        let bad_seq = streams("1", 1, 3, &[("RotaryVelocity", "S1speed", 2, "1")])
            .replace(r#"sequence="2""#, r#"sequence="two""#);
        assert!(matches!(
            parse(&bad_seq, None),
            Err(MtcError::Observation { .. })
        ));
        assert!(timestamp_ns("2026-03-02T06:00:00.5").is_some(), "no Z: UTC");
        assert!(timestamp_ns("yesterday").is_none());
    }

    #[test]
    fn execution_and_mode_map_to_the_nc_state() {
        use MachineStateKind::{Cutting, Idle};
        assert_eq!(machine_state("ACTIVE", None), Some(Cutting));
        assert_eq!(machine_state("FEED_HOLD", Some("AUTOMATIC")), Some(Cutting));
        assert_eq!(machine_state("INTERRUPTED", None), Some(Cutting));
        assert_eq!(machine_state("READY", Some("AUTOMATIC")), Some(Idle));
        assert_eq!(machine_state("PROGRAM_COMPLETED", None), Some(Idle));
        assert_eq!(machine_state("READY", Some("MANUAL")), Some(Cutting));
        assert_eq!(machine_state("READY", Some("EDIT")), Some(Idle));
        assert_eq!(machine_state("UNAVAILABLE", None), None);
    }

    #[test]
    fn the_stream_is_followed_from_current_without_doubles() {
        let mut f = follower();
        assert_eq!(f.request(), Request::Current);
        let (ev, _) = feed(
            &mut f,
            &streams(
                "A",
                1,
                10,
                &[
                    ("RotaryVelocity", "S1speed", 7, "0"),
                    ("Execution", "exec", 8, "READY"),
                    ("ControllerMode", "mode", 9, "AUTOMATIC"),
                ],
            ),
        );
        assert_eq!(rpms(&ev), vec![0.0]);
        assert!(
            ev.iter()
                .any(|e| matches!(e, LinkEvent::State(s) if s.msg.state == MachineStateKind::Idle))
        );
        assert_eq!(
            f.request(),
            Request::Sample {
                from: 10,
                count: 100
            }
        );
        // An answer that repeats an observation before `from` (a sloppy agent): not taken.
        let (ev, notes) = feed(
            &mut f,
            &streams(
                "A",
                1,
                13,
                &[
                    ("RotaryVelocity", "S1speed", 9, "5"),
                    ("RotaryVelocity", "S1speed", 10, "12000"),
                    ("Execution", "exec", 11, "ACTIVE"),
                    ("Temperature", "T1", 12, "24.5"),
                ],
            ),
        );
        assert!(notes.is_empty(), "{notes:?}");
        assert_eq!(rpms(&ev), vec![12000.0]);
        assert!(
            ev.iter().any(
                |e| matches!(e, LinkEvent::State(s) if s.msg.state == MachineStateKind::Cutting)
            )
        );
        assert!(ev.iter().any(|e| matches!(e, LinkEvent::Temperature(t) if t.msg.sensor == "spindle_head" && t.msg.celsius == 24.5)));
        assert_eq!(
            f.request(),
            Request::Sample {
                from: 13,
                count: 100
            }
        );
        // Nothing new: the same place.
        let (ev, _) = feed(&mut f, &streams("A", 1, 13, &[]));
        assert!(ev.is_empty());
        assert_eq!(
            f.request(),
            Request::Sample {
                from: 13,
                count: 100
            }
        );
        assert_eq!(f.stats.taken, 6);
    }

    #[test]
    fn a_restart_rereads_current_and_takes_each_observation_once() {
        let mut f = follower();
        feed(
            &mut f,
            &streams("A", 1, 5, &[("RotaryVelocity", "S1speed", 4, "1000")]),
        );
        feed(
            &mut f,
            &streams(
                "A",
                1,
                7,
                &[
                    ("RotaryVelocity", "S1speed", 5, "2000"),
                    ("RotaryVelocity", "S1speed", 6, "3000"),
                ],
            ),
        );
        // The agent restarts: its answer to `sample?from=7` comes from another instance.
        let (ev, notes) = feed(
            &mut f,
            &streams("B", 1, 3, &[("RotaryVelocity", "S1speed", 1, "9999")]),
        );
        assert!(
            ev.is_empty() && notes.is_empty(),
            "nothing taken from an instance not yet read"
        );
        assert_eq!(f.request(), Request::Current);
        let (ev, notes) = feed(
            &mut f,
            &streams("B", 1, 4, &[("RotaryVelocity", "S1speed", 3, "4000")]),
        );
        assert!(ev.is_empty());
        assert_eq!(
            notes,
            vec![Note::Restarted {
                old: "A".into(),
                new: "B".into()
            }]
        );
        assert_eq!(f.instance(), Some("B"));
        // From the new instance's first sequence: its announcement of the value taken before
        // (same time, same value) is not taken again; what is new is.
        assert_eq!(
            f.request(),
            Request::Sample {
                from: 1,
                count: 100
            }
        );
        let (ev, _) = feed(
            &mut f,
            &streams(
                "B",
                1,
                4,
                &[
                    ("RotaryVelocity", "S1speed", 6, "3000"),
                    ("RotaryVelocity", "S1speed", 7, "3500"),
                    ("RotaryVelocity", "S1speed", 8, "4000"),
                ],
            )
            .replace(r#"sequence="6""#, r#"sequence="1""#)
            .replace(r#"sequence="7""#, r#"sequence="2""#)
            .replace(r#"sequence="8""#, r#"sequence="3""#),
        );
        assert_eq!(rpms(&ev), vec![3500.0, 4000.0]);
        assert_eq!(f.stats.restarts, 1);
        assert_eq!(f.stats.lost_observations, 0);
    }

    #[test]
    fn a_gap_is_measured_and_the_stream_resumes_at_the_first_sequence() {
        let mut f = follower();
        feed(&mut f, &streams("A", 1, 5, &[]));
        // cppagent's way: OUT_OF_RANGE, then `current` gives the bounds.
        let err = r#"<MTConnectError><Header instanceId="A" sender="a" creationTime="2026-03-02T06:01:00Z" version="1.3" bufferSize="16"/><Errors><Error errorCode="OUT_OF_RANGE">'from' must be greater than or equal to 20</Error></Errors></MTConnectError>"#;
        let (ev, notes) = feed(&mut f, err);
        assert!(ev.is_empty() && notes.is_empty());
        assert_eq!(f.request(), Request::Current);
        let (_, notes) = feed(&mut f, &streams("A", 20, 36, &[]));
        assert_eq!(
            notes,
            vec![Note::Gap {
                from: 5,
                first: 20,
                lost: 15
            }]
        );
        assert_eq!(
            f.request(),
            Request::Sample {
                from: 20,
                count: 100
            }
        );
        // A lenient agent's way: it answers from its first sequence.
        let (ev, notes) = feed(
            &mut f,
            &streams(
                "A",
                30,
                40,
                &[
                    ("RotaryVelocity", "S1speed", 30, "800"),
                    ("RotaryVelocity", "S1speed", 39, "900"),
                ],
            ),
        );
        assert_eq!(
            notes,
            vec![Note::Gap {
                from: 20,
                first: 30,
                lost: 10
            }]
        );
        assert_eq!(rpms(&ev), vec![800.0, 900.0]);
        assert_eq!(f.stats.gaps, 2);
        assert_eq!(f.stats.lost_observations, 25);
        // Another error is the shell's to retry.
        let other = r#"<MTConnectError><Header instanceId="A" sender="a" creationTime="2026-03-02T06:01:00Z" version="1.3" bufferSize="16"/><Errors><Error errorCode="NO_DEVICE">no VMC-1</Error></Errors></MTConnectError>"#;
        let asked = f.request();
        let e = f.take(asked, parse(other, None).unwrap()).unwrap_err();
        assert!(e.to_string().contains("NO_DEVICE"), "{e}");
        assert_eq!(f.request(), asked);
    }

    #[test]
    fn implausible_and_unavailable_values_are_not_taken() {
        let mut f = follower();
        let (ev, notes) = feed(
            &mut f,
            &streams(
                "A",
                1,
                6,
                &[
                    ("RotaryVelocity", "S1speed", 1, "1e9"),
                    ("Temperature", "T1", 2, "-80"),
                    ("Execution", "exec", 3, "DANCING"),
                    ("Temperature", "T1", 4, "UNAVAILABLE"),
                    ("RotaryVelocity", "S1speed", 5, "abc"),
                ],
            ),
        );
        assert!(ev.is_empty(), "{ev:?}");
        assert_eq!(
            notes
                .iter()
                .filter(|n| matches!(n, Note::Refused { .. }))
                .count(),
            4,
            "{notes:?}"
        );
        assert!(notes.contains(&Note::Unavailable { item: "T1".into() }));
    }
}
