//! The `nc_push` machine link: a real NC, or its edge gateway, posts what happens (spindle
//! speed, NC state, temperatures, detections, in the recording contract's message shapes) and
//! polls for a cycle order. When the NC is idle and an order is pending it runs the measurement
//! program and posts each detection; the cycle closes when every step of the plan has arrived,
//! or the scheduler's timeout abandons it.
//!
//! Handshake (documented in the README):
//! 1. `POST /api/v1/machines/{id}/nc/events` `{"events": [{"topic": "/spindle", "t_ns": ..,
//!    "msg": {"rpm": ..}}, ...]}` at every change (and at least once a minute while turning).
//!    A batch is taken whole or refused whole (400 naming the bad event), so a retry loses
//!    nothing and doubles nothing.
//! 2. `GET /api/v1/machines/{id}/nc/request`: 204 when nothing is asked, else 200 with the
//!    order: cycle number, plan, spindle speed and every step (pose, approach, start position,
//!    travel).
//! 3. The NC runs the steps and posts each detection as `/probe/detection` with that cycle
//!    number and the step's label.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::{Arc, Mutex};

use serde::{Deserialize, Serialize};
use serde_json::Value;
use thiserror::Error;

use crate::link::{LinkError, LinkEvent, MachineLink};
use crate::plan::Plan;
use crate::recording::{
    self as rec, MachineStateKind, SpindleMsg, StateMsg, TemperatureMsg, Timed, parse_detection,
};

#[derive(Debug, Error, PartialEq)]
pub enum NcPushError {
    #[error(
        "event {index}: topic '{topic}' is not one the NC sends (/spindle, /machine/state, /temperature, /probe/detection)"
    )]
    Topic { index: usize, topic: String },
    #[error("event {index} ({topic}): {message}")]
    Message {
        index: usize,
        topic: String,
        message: String,
    },
    #[error("event {index}: t_ns {t_ns} is negative")]
    Time { index: usize, t_ns: i64 },
}

/// One event as the NC posts it: a contract topic, its time, its message.
#[derive(Debug, Clone, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PostedEvent {
    /// `/spindle`, `/machine/state`, `/temperature` or `/probe/detection`.
    pub topic: String,
    /// ns since the Unix epoch.
    pub t_ns: i64,
    /// The message in the recording contract's shape for that topic.
    #[schema(value_type = Object)]
    pub msg: Value,
}

#[derive(Debug, Clone, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct EventBatch {
    pub events: Vec<PostedEvent>,
}

/// One step of a cycle order.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct OrderStep {
    pub step: String,
    pub b_deg: f64,
    pub c_deg: f64,
    #[schema(value_type = String)]
    pub axis: crate::measurement::Axis,
    pub direction: i8,
    pub feed_mm_min: f64,
    /// Commanded start of the approach, mm.
    pub start_mm: [f64; 3],
    /// The approach ends as `no_trip` after this travel, mm.
    pub max_travel_mm: f64,
}

/// What the NC is asked to run.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct CycleOrder {
    pub cycle: i64,
    pub requested_ns: i64,
    pub plan: String,
    pub spindle_rpm: f64,
    pub steps: Vec<OrderStep>,
}

struct Shared {
    queue: Vec<LinkEvent>,
    order: Option<CycleOrder>,
    state: Option<MachineStateKind>,
    received: BTreeMap<i64, BTreeSet<String>>,
}

/// The API side: takes the NC's posts, hands out the order.
#[derive(Clone)]
pub struct NcPushHandle {
    shared: Arc<Mutex<Shared>>,
}

/// The service side: a `MachineLink`.
pub struct NcPushLink {
    shared: Arc<Mutex<Shared>>,
    plan: Plan,
    expected: BTreeSet<String>,
}

pub fn nc_push(plan: Plan) -> (NcPushLink, NcPushHandle) {
    let shared = Arc::new(Mutex::new(Shared {
        queue: Vec::new(),
        order: None,
        state: None,
        received: BTreeMap::new(),
    }));
    let expected = plan.steps.iter().map(|s| s.label.clone()).collect();
    (
        NcPushLink {
            shared: shared.clone(),
            plan,
            expected,
        },
        NcPushHandle { shared },
    )
}

fn typed<T: for<'de> Deserialize<'de>>(
    index: usize,
    topic: &str,
    v: &Value,
) -> Result<T, NcPushError> {
    serde_json::from_value(v.clone()).map_err(|e| NcPushError::Message {
        index,
        topic: topic.to_string(),
        message: e.to_string(),
    })
}

impl NcPushHandle {
    /// Take a batch of events whole, or refuse it whole with the first bad event named.
    pub fn post(&self, batch: &EventBatch) -> Result<usize, NcPushError> {
        let mut parsed = Vec::with_capacity(batch.events.len());
        for (index, e) in batch.events.iter().enumerate() {
            if e.t_ns < 0 {
                return Err(NcPushError::Time {
                    index,
                    t_ns: e.t_ns,
                });
            }
            let t_ns = e.t_ns;
            let ev = match e.topic.as_str() {
                rec::TOPIC_SPINDLE => {
                    let m: SpindleMsg = typed(index, &e.topic, &e.msg)?;
                    if !m.rpm.is_finite() {
                        return Err(NcPushError::Message {
                            index,
                            topic: e.topic.clone(),
                            message: "rpm is not a finite number".into(),
                        });
                    }
                    LinkEvent::Spindle(Timed { t_ns, msg: m })
                }
                rec::TOPIC_STATE => LinkEvent::State(Timed {
                    t_ns,
                    msg: typed::<StateMsg>(index, &e.topic, &e.msg)?,
                }),
                rec::TOPIC_TEMPERATURE => LinkEvent::Temperature(Timed {
                    t_ns,
                    msg: typed::<TemperatureMsg>(index, &e.topic, &e.msg)?,
                }),
                rec::TOPIC_DETECTION => {
                    let text = e.msg.to_string();
                    let m = parse_detection(text.as_bytes()).map_err(|i| NcPushError::Message {
                        index,
                        topic: e.topic.clone(),
                        message: i.message,
                    })?;
                    LinkEvent::Detection(Timed { t_ns, msg: m })
                }
                other => {
                    return Err(NcPushError::Topic {
                        index,
                        topic: other.to_string(),
                    });
                }
            };
            parsed.push(ev);
        }
        let n = parsed.len();
        if let Ok(mut s) = self.shared.lock() {
            s.queue.extend(parsed);
        }
        Ok(n)
    }

    /// The pending cycle order, if any.
    pub fn order(&self) -> Option<CycleOrder> {
        self.shared.lock().ok().and_then(|s| s.order.clone())
    }
}

impl MachineLink for NcPushLink {
    fn poll(&mut self, _now_ns: i64) -> Vec<LinkEvent> {
        let Ok(mut s) = self.shared.lock() else {
            return Vec::new();
        };
        let mut events = std::mem::take(&mut s.queue);
        events.sort_by_key(LinkEvent::t_ns);
        let mut out = Vec::with_capacity(events.len() + 1);
        for ev in events {
            match &ev {
                LinkEvent::State(m) => s.state = Some(m.msg.state),
                LinkEvent::Detection(d) => {
                    s.received
                        .entry(d.msg.cycle)
                        .or_default()
                        .insert(d.msg.step.clone());
                }
                _ => {}
            }
            let done = match (&ev, &s.order) {
                (LinkEvent::Detection(d), Some(o)) if d.msg.cycle == o.cycle => s
                    .received
                    .get(&o.cycle)
                    .is_some_and(|got| self.expected.is_subset(got))
                    .then_some((o.cycle, d.t_ns)),
                _ => None,
            };
            out.push(ev);
            if let Some((cycle, t_ns)) = done {
                s.order = None;
                s.received.remove(&cycle);
                out.push(LinkEvent::CycleDone { cycle, t_ns });
            }
        }
        out
    }

    fn request_cycle(&mut self, number: i64, now_ns: i64) -> Result<(), LinkError> {
        let Ok(mut s) = self.shared.lock() else {
            return Err(LinkError::NotIdle(MachineStateKind::Alarm));
        };
        if let Some(o) = &s.order {
            return Err(LinkError::Busy(o.cycle));
        }
        match s.state {
            Some(MachineStateKind::Idle) => {}
            other => return Err(LinkError::NotIdle(other.unwrap_or(MachineStateKind::Off))),
        }
        s.order = Some(CycleOrder {
            cycle: number,
            requested_ns: now_ns,
            plan: self.plan.name.clone(),
            spindle_rpm: self.plan.config.spindle_rpm,
            steps: self
                .plan
                .steps
                .iter()
                .map(|st| OrderStep {
                    step: st.label.clone(),
                    b_deg: st.b_deg,
                    c_deg: st.c_deg,
                    axis: st.approach.axis,
                    direction: st.approach.direction,
                    feed_mm_min: st.approach.feed_mm_min,
                    start_mm: [st.start.x, st.start.y, st.start.z],
                    max_travel_mm: st.max_travel_mm,
                })
                .collect(),
        });
        Ok(())
    }

    fn abort_cycle(&mut self, number: i64, _now_ns: i64) {
        if let Ok(mut s) = self.shared.lock()
            && s.order.as_ref().is_some_and(|o| o.cycle == number)
        {
            s.order = None;
            s.received.remove(&number);
        }
    }

    fn next_event_ns(&self) -> Option<i64> {
        None
    }
}
