//! What a machine link reports, the one event type from a link to the machine core: the
//! recording contract's messages, the end of a cycle's program, a message to record as it is,
//! and the link's clock-skew refusals. Every link (the NC door, MTConnect, OPC UA, the
//! simulated machine) speaks it, and [`crate::machine_core::Input::Link`] takes it as it is.

use thiserror::Error;

use driftwatch_core::recording::{
    DetectionMsg, MachineStateKind, SpindleMsg, StateMsg, TemperatureMsg, Timed,
};

/// Something the machine reported.
#[derive(Debug, Clone, PartialEq)]
pub enum LinkEvent {
    Spindle(Timed<SpindleMsg>),
    State(Timed<StateMsg>),
    Temperature(Timed<TemperatureMsg>),
    Detection(Timed<DetectionMsg>),
    /// The machine finished the cycle's program (every expected step has been sent).
    CycleDone {
        cycle: i64,
        t_ns: i64,
    },
    /// A message to record as it is under its own topic, never used to compute what is served
    /// (a simulated machine's ground truth).
    Record {
        topic: &'static str,
        t_ns: i64,
        json: RawJson,
    },
    /// Since the last poll the link refused `refused` events stamped too far from the service
    /// clock (`t_ns`, the poll's time); `worst_skew_ns` is the largest skew, signed (positive:
    /// ahead of the clock).
    ClockSkew {
        t_ns: i64,
        refused: u64,
        worst_skew_ns: i64,
    },
}

/// A JSON message kept as its text, written to a recording byte for byte.
#[derive(Debug, Clone, serde::Serialize)]
#[serde(transparent)]
pub struct RawJson(pub Box<serde_json::value::RawValue>);

impl PartialEq for RawJson {
    fn eq(&self, other: &Self) -> bool {
        self.0.get() == other.0.get()
    }
}

impl LinkEvent {
    pub fn t_ns(&self) -> i64 {
        match self {
            LinkEvent::Spindle(m) => m.t_ns,
            LinkEvent::State(m) => m.t_ns,
            LinkEvent::Temperature(m) => m.t_ns,
            LinkEvent::Detection(m) => m.t_ns,
            LinkEvent::CycleDone { t_ns, .. } => *t_ns,
            LinkEvent::Record { t_ns, .. } => *t_ns,
            LinkEvent::ClockSkew { t_ns, .. } => *t_ns,
        }
    }
}

/// Why a link did not start a cycle.
#[derive(Debug, Error, PartialEq)]
pub enum LinkError {
    #[error("the machine is {0:?}, not idle: a cycle runs only when it is idle")]
    NotIdle(MachineStateKind),
    #[error("cycle {0} is already running")]
    Busy(i64),
    #[error(
        "the NC has not reported its state yet: a cycle runs only once it reports idle (the state shown is inferred)"
    )]
    NoState,
    #[error(
        "the {0} link only observes the machine and cannot order a cycle: cycles must be ordered by another route (an nc_push gateway, or the NC's own program)"
    )]
    ObserveOnly(&'static str),
    /// The link cannot reach the NC now (a network link between sessions).
    #[error("the NC cannot be reached: {0}")]
    Unavailable(String),
}
