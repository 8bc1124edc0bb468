//! The NC door's decisions, without I/O: what a real NC (or its edge gateway, or the OPC UA
//! link on its behalf) posts is taken whole or refused whole, judged against the machine's
//! limits, the service clock and the pending order; the order is handed out until the NC runs
//! it; the cycle closes when every measurement of the plan has tripped (by pose, approach and
//! feed, labels free, the rule of [`Tally`]), when the NC leaves the `measuring` state after
//! posting detections of the order (a failed approach it did not retry), or when the
//! scheduler's timeout abandons it. The service holds a door behind a lock; the HTTP handler
//! posts into it and the machine's loop polls it.

use std::collections::BTreeMap;
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use serde_json::Value;
use thiserror::Error;

use driftwatch_core::cycle::{ExpectedMeasurements, Tally, plan_measurements};
use driftwatch_core::kinematics::{Limits, MAX_NAME_CHARS};
use driftwatch_core::plan::Plan;
use driftwatch_core::recording::{
    self as rec, MachineStateKind, SpindleMsg, StateMsg, TemperatureMsg, Timed, parse_detection,
};
use driftwatch_core::units;

use crate::link_event::{LinkError, LinkEvent};

#[derive(Debug, Error, PartialEq)]
pub enum NcDoorError {
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
    #[error(
        "{queued} events wait for the service loop already (at most {MAX_QUEUED}): send this batch again in a few seconds"
    )]
    Busy { queued: usize },
    #[error(
        "event {index} ({topic}): t_ns {t_ns} is {} s {} the service clock ({now_ns}), beyond the {} s allowed: is the NC's clock set to local time, or not synchronised?",
        (t_ns - now_ns).abs() as f64 / 1e9,
        if t_ns > now_ns { "ahead of" } else { "behind" },
        *limit_ns as f64 / 1e9
    )]
    ClockSkew {
        index: usize,
        topic: String,
        t_ns: i64,
        now_ns: i64,
        limit_ns: i64,
    },
}

/// Events taken but not yet handed to the loop, at most: a gateway that floods the endpoint
/// faster than the loop polls is told to come back, instead of growing the service's memory.
pub const MAX_QUEUED: usize = 50_000;

/// What a batch added: events queued for the loop, and detections of no ordered cycle, which
/// are counted but not kept (nothing could use them: the cycle they name is not running).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Accepted {
    pub accepted: usize,
    pub stray: usize,
}

/// How far an event's time may lie from the service clock. A state stamped an hour ahead
/// would otherwise hide every correct state after it, and a cycle stamped a day ahead would
/// make every later cycle's set lie "before" the served one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockTolerance {
    pub ahead_ns: i64,
    pub behind_ns: i64,
}

impl Default for ClockTolerance {
    fn default() -> Self {
        ClockTolerance {
            ahead_ns: units::NS_PER_MIN,
            behind_ns: 24 * units::NS_PER_H,
        }
    }
}

/// The default of every link's `max_ahead_s`, s: [`ClockTolerance::default`]'s.
pub fn default_max_ahead_s() -> f64 {
    ClockTolerance::default().ahead_ns as f64 / 1e9
}

/// The default of every link's `max_behind_s`, s: [`ClockTolerance::default`]'s.
pub fn default_max_behind_s() -> f64 {
    ClockTolerance::default().behind_ns as f64 / 1e9
}

/// One event as the NC posts it: a contract topic, its time, its message.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(deny_unknown_fields)]
pub struct PostedEvent {
    /// `/spindle`, `/machine/state`, `/temperature` or `/probe/detection`.
    pub topic: String,
    /// ns since the Unix epoch.
    pub t_ns: i64,
    /// The message in the recording contract's shape for that topic.
    #[cfg_attr(feature = "openapi", schema(value_type = Object))]
    pub msg: Value,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(deny_unknown_fields)]
pub struct EventBatch {
    pub events: Vec<PostedEvent>,
}

/// One step of a cycle order.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct OrderStep {
    pub step: String,
    pub b_deg: f64,
    pub c_deg: f64,
    #[cfg_attr(feature = "openapi", schema(value_type = String))]
    pub axis: driftwatch_core::measurement::Axis,
    pub direction: i8,
    pub feed_mm_min: f64,
    /// Commanded start of the approach, mm.
    pub start_mm: [f64; 3],
    /// The approach ends as `no_trip` after this travel, mm.
    pub max_travel_mm: f64,
}

/// What the NC is asked to run.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct CycleOrder {
    pub cycle: i64,
    pub requested_ns: i64,
    pub plan: String,
    pub spindle_rpm: f64,
    pub steps: Vec<OrderStep>,
}

/// One machine's NC door: the events taken and not yet polled, the order, and what the door
/// knows of the NC (its state, the service clock at the loop's last look, the counts).
#[derive(Debug)]
pub struct NcDoor {
    /// Shared by every machine of the same kinematics and plan.
    plan: Arc<Plan>,
    limits: Limits,
    expected: ExpectedMeasurements,
    tolerance: ClockTolerance,
    queue: Vec<LinkEvent>,
    order: Option<CycleOrder>,
    /// The NC has posted a detection of the order: it runs it, so the order is no longer
    /// handed out (an NC polling again before the loop closed the cycle would run it twice).
    order_running: bool,
    state: Option<MachineStateKind>,
    /// The time of the state above: an older state posted later does not overwrite it.
    state_t_ns: i64,
    /// The service clock at the loop's last look (none before it).
    clock_ns: Option<i64>,
    /// Events refused for their time (whole batches: each bad event counted once).
    refused_clock_skew: u64,
    /// Refusals since the loop's last poll, and the largest skew among them (signed).
    skew_since_poll: Option<(u64, i64)>,
    /// Detections of no ordered cycle, counted and dropped.
    stray_detections: u64,
    /// Per cycle, the measurements tripped so far.
    received: BTreeMap<i64, Tally>,
}

/// How far a detection's spindle speed and feed may lie from the order's, as a share: a
/// spindle override of a few percent is normal, a different program is not.
pub const ORDER_TOLERANCE: f64 = 0.05;

/// Why a detection of the ordered cycle was not made as ordered, if it was not: its spindle
/// speed away from the order's (the thermal state and the tool's growth depend on it), or a
/// feed that no step of the order has (the trip's latency depends on it).
fn against_order(m: &rec::DetectionMsg, o: &CycleOrder) -> Option<String> {
    let near = |got: f64, want: f64| (got - want).abs() <= ORDER_TOLERANCE * want.abs().max(1.0);
    if !near(m.spindle_rpm, o.spindle_rpm) {
        return Some(format!(
            "spindle_rpm {} is not the {} min^-1 cycle {} was ordered at (within {} %)",
            m.spindle_rpm,
            o.spindle_rpm,
            o.cycle,
            ORDER_TOLERANCE * 100.0
        ));
    }
    if !o.steps.iter().any(|s| near(m.feed_mm_min, s.feed_mm_min)) {
        let mut feeds: Vec<String> = o.steps.iter().map(|s| s.feed_mm_min.to_string()).collect();
        feeds.dedup();
        return Some(format!(
            "feed_mm_min {} is no feed of cycle {}'s order ({} mm/min, within {} %)",
            m.feed_mm_min,
            o.cycle,
            feeds.join(", "),
            ORDER_TOLERANCE * 100.0
        ));
    }
    None
}

fn typed<T: for<'de> Deserialize<'de>>(
    index: usize,
    topic: &str,
    v: &Value,
) -> Result<T, NcDoorError> {
    serde_json::from_value(v.clone()).map_err(|e| NcDoorError::Message {
        index,
        topic: topic.to_string(),
        message: e.to_string(),
    })
}

fn refuse(index: usize, topic: &str, message: String) -> NcDoorError {
    NcDoorError::Message {
        index,
        topic: topic.to_string(),
        message,
    }
}

/// A name an event carries, no longer than [`MAX_NAME_CHARS`] (it is stored and logged).
fn named(index: usize, topic: &str, what: &str, name: &str) -> Result<(), NcDoorError> {
    let n = name.chars().count();
    if n > MAX_NAME_CHARS {
        return Err(refuse(
            index,
            topic,
            format!("{what} is {n} characters long, more than {MAX_NAME_CHARS}"),
        ));
    }
    Ok(())
}

impl NcDoor {
    pub fn new(plan: Arc<Plan>, limits: Limits, tolerance: ClockTolerance) -> NcDoor {
        let expected = plan_measurements(&plan);
        NcDoor {
            plan,
            limits,
            expected,
            tolerance,
            queue: Vec::new(),
            order: None,
            order_running: false,
            state: None,
            state_t_ns: i64::MIN,
            clock_ns: None,
            refused_clock_skew: 0,
            skew_since_poll: None,
            stray_detections: 0,
            received: BTreeMap::new(),
        }
    }

    /// Take a batch of events whole, or refuse it whole with the first bad event named. Each
    /// event's time is judged against `now_ns`, the service clock as the batch arrives; without
    /// one, against the clock at the loop's last look, which may lag it by as long as the loop
    /// sleeps.
    pub fn post(
        &mut self,
        batch: &EventBatch,
        now_ns: Option<i64>,
    ) -> Result<Accepted, NcDoorError> {
        let mut parsed = Vec::with_capacity(batch.events.len());
        let mut stray = 0;
        let now_ns = now_ns.or(self.clock_ns);
        for (index, e) in batch.events.iter().enumerate() {
            self.within_clock(index, e, now_ns)?;
            match self.event(index, e)? {
                Some(ev) => parsed.push(ev),
                None => stray += 1,
            }
        }
        if self.queue.len() + parsed.len() > MAX_QUEUED {
            return Err(NcDoorError::Busy {
                queued: self.queue.len(),
            });
        }
        if let Some(o) = &self.order
            && parsed
                .iter()
                .any(|e| matches!(e, LinkEvent::Detection(d) if d.msg.cycle == o.cycle))
        {
            self.order_running = true;
        }
        let n = parsed.len();
        self.queue.extend(parsed);
        self.stray_detections += stray as u64;
        Ok(Accepted { accepted: n, stray })
    }

    /// An event's time is not negative and lies within the tolerance of the service clock
    /// `now_ns` (none: before the loop's first look, nothing to judge by); a refusal is counted
    /// for the loop's clock alert.
    fn within_clock(
        &mut self,
        index: usize,
        e: &PostedEvent,
        now_ns: Option<i64>,
    ) -> Result<(), NcDoorError> {
        if e.t_ns < 0 {
            return Err(NcDoorError::Time {
                index,
                t_ns: e.t_ns,
            });
        }
        let Some(now_ns) = now_ns else {
            return Ok(());
        };
        let limit_ns = if e.t_ns > now_ns {
            self.tolerance.ahead_ns
        } else {
            self.tolerance.behind_ns
        };
        if e.t_ns.abs_diff(now_ns) <= limit_ns.unsigned_abs() {
            return Ok(());
        }
        self.refused_clock_skew += 1;
        let skew = e.t_ns.saturating_sub(now_ns);
        let (n, worst) = self.skew_since_poll.unwrap_or((0, 0));
        let worst = if skew.unsigned_abs() > worst.unsigned_abs() {
            skew
        } else {
            worst
        };
        self.skew_since_poll = Some((n + 1, worst));
        Err(NcDoorError::ClockSkew {
            index,
            topic: e.topic.clone(),
            t_ns: e.t_ns,
            now_ns,
            limit_ns,
        })
    }

    /// One posted event as the link reports it, or none for a detection of no ordered cycle
    /// (a stray, counted and dropped); a bad event refuses the batch.
    fn event(&self, index: usize, e: &PostedEvent) -> Result<Option<LinkEvent>, NcDoorError> {
        let t_ns = e.t_ns;
        Ok(Some(match e.topic.as_str() {
            rec::TOPIC_SPINDLE => {
                let m: SpindleMsg = typed(index, &e.topic, &e.msg)?;
                let max = self.limits.spindle_max_rpm;
                if !(m.rpm.is_finite() && m.rpm.abs() <= max) {
                    return Err(refuse(
                        index,
                        &e.topic,
                        format!(
                            "rpm {} is not a speed of this spindle (finite, at most {max} min^-1 either way: limits.spindle_max_rpm of the machine file)",
                            m.rpm
                        ),
                    ));
                }
                LinkEvent::Spindle(Timed { t_ns, msg: m })
            }
            rec::TOPIC_STATE => {
                let m: StateMsg = typed(index, &e.topic, &e.msg)?;
                named(
                    index,
                    &e.topic,
                    "program",
                    m.program.as_deref().unwrap_or(""),
                )?;
                LinkEvent::State(Timed { t_ns, msg: m })
            }
            rec::TOPIC_TEMPERATURE => {
                let m: TemperatureMsg = typed(index, &e.topic, &e.msg)?;
                named(index, &e.topic, "sensor", &m.sensor)?;
                let [lo, hi] = self.limits.celsius;
                if !(lo..=hi).contains(&m.celsius) {
                    return Err(refuse(
                        index,
                        &e.topic,
                        format!(
                            "{} deg C from sensor '{}' is not a temperature of this machine ({lo} to {hi}: limits.celsius of the machine file)",
                            m.celsius, m.sensor
                        ),
                    ));
                }
                LinkEvent::Temperature(Timed { t_ns, msg: m })
            }
            rec::TOPIC_DETECTION => {
                let text = e.msg.to_string();
                let m = parse_detection(text.as_bytes())
                    .map_err(|i| refuse(index, &e.topic, i.message))?;
                named(index, &e.topic, "step", &m.step)?;
                named(index, &e.topic, "tool_id", &m.tool_id)?;
                let Some(o) = self.order.as_ref().filter(|o| o.cycle == m.cycle) else {
                    return Ok(None);
                };
                if let Some(message) = against_order(&m, o) {
                    return Err(refuse(index, &e.topic, message));
                }
                LinkEvent::Detection(Timed { t_ns, msg: m })
            }
            other => {
                return Err(NcDoorError::Topic {
                    index,
                    topic: other.to_string(),
                });
            }
        }))
    }

    /// Detections of no ordered cycle, counted and dropped.
    pub fn stray_detections(&self) -> u64 {
        self.stray_detections
    }

    /// The pending cycle order, if any, until the NC posts a detection of it (it runs it then;
    /// an NC that dies mid-cycle gets a new order after the scheduler's timeout).
    pub fn order(&self) -> Option<&CycleOrder> {
        self.order.as_ref().filter(|_| !self.order_running)
    }

    /// Events refused because their time lay too far from the service clock.
    pub fn refused_clock_skew(&self) -> u64 {
        self.refused_clock_skew
    }

    /// The NC's state as the door holds it (the newest posted, by its time).
    pub fn state(&self) -> Option<MachineStateKind> {
        self.state
    }

    /// The loop's look at `now_ns`: everything taken since the last look, in time order, with
    /// a cycle's end where the door sees it, and the clock refusals last.
    pub fn poll(&mut self, now_ns: i64) -> Vec<LinkEvent> {
        self.clock_ns = Some(now_ns);
        let mut events = std::mem::take(&mut self.queue);
        events.sort_by_key(LinkEvent::t_ns);
        let mut out = Vec::with_capacity(events.len() + 2);
        for ev in events {
            let order_cycle = self.order.as_ref().map(|o| o.cycle);
            let done = match &ev {
                LinkEvent::State(m) => {
                    // A state older than the one in force (a late batch) does not replace it.
                    if m.t_ns >= self.state_t_ns {
                        self.state = Some(m.msg.state);
                        self.state_t_ns = m.t_ns;
                    }
                    // Leaving `measuring` after posting detections of the order ends its
                    // program, whatever did not trip.
                    order_cycle
                        .filter(|c| {
                            m.msg.state != MachineStateKind::Measuring
                                && self.received.contains_key(c)
                        })
                        .map(|c| (c, m.t_ns))
                }
                // Only the ordered cycle's detections are counted; others pass on to the
                // loop, which says they belong to no open cycle.
                LinkEvent::Detection(d) if order_cycle == Some(d.msg.cycle) => {
                    let got = self.received.entry(d.msg.cycle).or_default();
                    got.add(d.t_ns, &d.msg);
                    got.covers(&self.expected).then_some((d.msg.cycle, d.t_ns))
                }
                _ => None,
            };
            out.push(ev);
            if let Some((cycle, t_ns)) = done {
                self.order = None;
                self.received.remove(&cycle);
                out.push(LinkEvent::CycleDone { cycle, t_ns });
            }
        }
        // Last, stamped with the poll's time.
        if let Some((refused, worst_skew_ns)) = self.skew_since_poll.take() {
            out.push(LinkEvent::ClockSkew {
                t_ns: now_ns,
                refused,
                worst_skew_ns,
            });
        }
        out
    }

    /// Order cycle `number`: only of an NC that reported itself idle, one order at a time.
    pub fn request_cycle(&mut self, number: i64, now_ns: i64) -> Result<(), LinkError> {
        if let Some(o) = &self.order {
            return Err(LinkError::Busy(o.cycle));
        }
        match self.state {
            Some(MachineStateKind::Idle) => {}
            Some(other) => return Err(LinkError::NotIdle(other)),
            None => return Err(LinkError::NoState),
        }
        self.order_running = false;
        self.order = Some(CycleOrder {
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

    /// Stop cycle `number` (the scheduler's timeout, or shutdown): its order is withdrawn.
    pub fn abort_cycle(&mut self, number: i64) {
        if self.order.as_ref().is_some_and(|o| o.cycle == number) {
            self.order = None;
            self.received.remove(&number);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::kinematics::Kinematics;
    use driftwatch_core::plan::PlanConfig;
    use driftwatch_core::recording::{DetectionMsg, DetectionStatus};

    fn setup() -> (NcDoor, Plan) {
        let k = Kinematics::load("table_bc").unwrap();
        let plan = Plan::build(&k, &PlanConfig::load("patent").unwrap()).unwrap();
        let door = NcDoor::new(
            Arc::new(plan.clone()),
            k.config.limits,
            ClockTolerance::default(),
        );
        (door, plan)
    }

    fn state(t_ns: i64, state: MachineStateKind) -> LinkEvent {
        LinkEvent::State(Timed {
            t_ns,
            msg: StateMsg {
                state,
                program: None,
            },
        })
    }

    /// The plan's detections of `cycle`, labelled by the NC's own scheme.
    fn detections(plan: &Plan, cycle: i64, t0: i64) -> Vec<LinkEvent> {
        plan.steps
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let mut p = s.start;
                p[s.approach.axis.index()] = s.expected;
                LinkEvent::Detection(Timed {
                    t_ns: t0 + i as i64 * 1_000_000_000,
                    msg: DetectionMsg {
                        cycle,
                        step: format!("P{}", i % 5),
                        b_deg: s.b_deg,
                        c_deg: s.c_deg,
                        axis: s.approach.axis,
                        direction: s.approach.direction,
                        feed_mm_min: s.approach.feed_mm_min,
                        spindle_rpm: 20000.0,
                        tool_id: "EM10".into(),
                        x_mm: p.x,
                        y_mm: p.y,
                        z_mm: p.z,
                        status: Some(DetectionStatus::Ok),
                    },
                })
            })
            .collect()
    }

    fn push(door: &mut NcDoor, evs: Vec<LinkEvent>) {
        door.queue.extend(evs);
    }

    fn done(evs: &[LinkEvent]) -> Vec<i64> {
        evs.iter()
            .filter_map(|e| match e {
                LinkEvent::CycleDone { cycle, .. } => Some(*cycle),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn an_event_stamped_beyond_the_clock_tolerance_is_refused_and_a_late_state_does_not_win() {
        let (mut door, _) = setup();
        let hour = units::NS_PER_H;
        let now = 1_800_000_000 * 1_000_000_000;
        let post = |door: &mut NcDoor, t_ns: i64, state: &str| {
            door.post(
                &EventBatch {
                    events: vec![PostedEvent {
                        topic: "/machine/state".into(),
                        t_ns,
                        msg: serde_json::json!({"state": state}),
                    }],
                },
                None,
            )
        };
        // The loop's look sets the clock the events are judged by.
        door.poll(now);
        // An hour ahead (local time sent as UTC): refused, naming the skew, counted.
        let e = post(&mut door, now + hour, "cutting").unwrap_err();
        assert!(matches!(e, NcDoorError::ClockSkew { .. }), "{e}");
        assert!(e.to_string().contains("3600 s ahead"), "{e}");
        assert_eq!(door.refused_clock_skew(), 1);
        // Within the tolerance either way: taken.
        assert_eq!(
            post(&mut door, now + 30_000_000_000, "idle").map(|a| a.accepted),
            Ok(1)
        );
        door.poll(now);
        assert_eq!(door.state, Some(MachineStateKind::Idle));
        // A day and more behind: refused; an older state within it does not replace the newer.
        assert!(post(&mut door, now - 25 * hour, "cutting").is_err());
        assert_eq!(
            post(&mut door, now - hour, "cutting").map(|a| a.accepted),
            Ok(1)
        );
        door.poll(now + 1);
        assert_eq!(door.state, Some(MachineStateKind::Idle));
        assert_eq!(door.refused_clock_skew(), 2);
    }

    /// A loop that sleeps between its looks (a quiet machine looks once a minute) must not make
    /// a sound event look ahead of the clock: a batch is judged against the service clock as
    /// it arrives when the caller gives it. An NC 15 s fast posting 50 s after the last look
    /// is 65 s ahead of that look, beyond the 60-s tolerance, but 15 s ahead of the clock.
    #[test]
    fn a_batch_is_judged_against_the_clock_as_it_arrives_not_the_loops_last_look() {
        let (mut door, _) = setup();
        let s = 1_000_000_000;
        let look = 1_800_000_000 * s;
        let batch = |t_ns: i64| EventBatch {
            events: vec![PostedEvent {
                topic: "/spindle".into(),
                t_ns,
                msg: serde_json::json!({"rpm": 1000.0}),
            }],
        };
        door.poll(look);
        let arrives = look + 50 * s;
        assert_eq!(
            door.post(&batch(arrives + 15 * s), Some(arrives))
                .map(|a| a.accepted),
            Ok(1)
        );
        assert_eq!(door.refused_clock_skew(), 0);
        // Without the clock, the last look is all the door has: refused.
        assert!(door.post(&batch(arrives + 15 * s), None).is_err());
        // The tolerance still holds against the clock: 61 s ahead of it is refused.
        let e = door
            .post(&batch(arrives + 61 * s), Some(arrives))
            .unwrap_err();
        assert!(e.to_string().contains("61 s ahead"), "{e}");
        assert_eq!(door.refused_clock_skew(), 2);
    }

    #[test]
    fn an_implausible_speed_or_temperature_refuses_the_batch_and_says_why() {
        let (mut door, _) = setup();
        let batch = |topic: &str, msg: serde_json::Value| EventBatch {
            events: vec![
                PostedEvent {
                    topic: "/spindle".into(),
                    t_ns: 1,
                    msg: serde_json::json!({"rpm": 12000.0}),
                },
                PostedEvent {
                    topic: topic.into(),
                    t_ns: 2,
                    msg,
                },
            ],
        };
        let long = "x".repeat(MAX_NAME_CHARS + 1);
        for (topic, msg, says) in [
            (
                "/spindle",
                serde_json::json!({"rpm": 1e300}),
                "not a speed of this spindle",
            ),
            // The machine file's limits, not only physics: table_bc's spindle turns at most
            // 30 000 min^-1 and its sensors read -10 to 100 deg C.
            (
                "/spindle",
                serde_json::json!({"rpm": -30001.0}),
                "at most 30000 min^-1",
            ),
            (
                "/temperature",
                serde_json::json!({"sensor": "ambient", "celsius": 1e6}),
                "not a temperature of this machine",
            ),
            (
                "/temperature",
                serde_json::json!({"sensor": "ambient", "celsius": -10.5}),
                "(-10 to 100",
            ),
            (
                "/temperature",
                serde_json::json!({"sensor": long, "celsius": 20.0}),
                "sensor is 65 characters long",
            ),
            (
                "/machine/state",
                serde_json::json!({"state": "idle", "program": long}),
                "program is 65 characters long",
            ),
        ] {
            let e = door.post(&batch(topic, msg), None).unwrap_err();
            assert!(
                matches!(e, NcDoorError::Message { index: 1, .. }) && e.to_string().contains(says),
                "{e}"
            );
        }
        // Nothing of a refused batch is kept; a plausible one is taken whole (reverse
        // rotation included).
        assert!(door.queue.is_empty());
        let ok = batch("/spindle", serde_json::json!({"rpm": -30000.0}));
        assert_eq!(door.post(&ok, None).unwrap().accepted, 2);
        let name = "y".repeat(MAX_NAME_CHARS);
        let ok = batch(
            "/temperature",
            serde_json::json!({"sensor": name, "celsius": 99.0}),
        );
        assert_eq!(door.post(&ok, None).unwrap().accepted, 2);
    }

    /// Before the NC says anything, no cycle is ordered, and the refusal says it is the
    /// missing report (not that the machine is off).
    #[test]
    fn no_cycle_before_the_nc_reports_its_state() {
        let (mut door, _) = setup();
        assert_eq!(door.request_cycle(1, 0), Err(LinkError::NoState));
        assert!(door.order().is_none());
        push(&mut door, vec![state(0, MachineStateKind::Idle)]);
        door.poll(0);
        assert_eq!(door.request_cycle(1, 1), Ok(()));
    }

    /// A detection of the ordered cycle made at another spindle speed or a
    /// feed the order does not have is refused at the door, naming it.
    #[test]
    fn a_detection_not_made_as_ordered_is_refused() {
        let (mut door, plan) = setup();
        push(&mut door, vec![state(0, MachineStateKind::Idle)]);
        door.poll(0);
        door.request_cycle(4, 1).unwrap();
        let LinkEvent::Detection(d) = detections(&plan, 4, 10).remove(0) else {
            unreachable!()
        };
        let post = |door: &mut NcDoor, m: &DetectionMsg| {
            door.post(
                &EventBatch {
                    events: vec![PostedEvent {
                        topic: "/probe/detection".into(),
                        t_ns: 10,
                        msg: serde_json::to_value(m).unwrap(),
                    }],
                },
                None,
            )
        };
        let mut slow = d.msg.clone();
        slow.spindle_rpm = 0.0;
        let e = post(&mut door, &slow).unwrap_err().to_string();
        assert!(e.contains("spindle_rpm 0 is not the 20000 min^-1"), "{e}");
        let mut fast = d.msg.clone();
        fast.feed_mm_min = 5000.0;
        let e = post(&mut door, &fast).unwrap_err().to_string();
        assert!(e.contains("feed_mm_min 5000 is no feed of cycle 4"), "{e}");
        let mut named = d.msg.clone();
        named.tool_id = "T".repeat(MAX_NAME_CHARS + 1);
        let e = post(&mut door, &named).unwrap_err().to_string();
        assert!(e.contains("tool_id is 65 characters long"), "{e}");
        // A 2 % spindle override is no reason to refuse; nor is a cycle not ordered (the loop
        // says it belongs to no open cycle).
        let mut over = d.msg.clone();
        over.spindle_rpm = 20400.0;
        assert!(
            door.order().is_some(),
            "refused detections do not start the order"
        );
        assert_eq!(post(&mut door, &over).map(|a| a.accepted), Ok(1));
        // Being run: not handed out again, however soon the NC polls.
        assert!(door.order().is_none());
        let mut other = slow.clone();
        other.cycle = 5;
        assert_eq!(
            post(&mut door, &other),
            Ok(Accepted {
                accepted: 0,
                stray: 1
            })
        );
    }

    /// Detections of no ordered cycle are counted, not kept, and a flood
    /// faster than the loop polls is told to come back; memory stays bounded either way.
    #[test]
    fn stray_detections_are_counted_not_kept_and_the_queue_is_bounded() {
        let (mut door, plan) = setup();
        let LinkEvent::Detection(d) = detections(&plan, 9, 10).remove(0) else {
            unreachable!()
        };
        let det = PostedEvent {
            topic: "/probe/detection".into(),
            t_ns: 10,
            msg: serde_json::to_value(&d.msg).unwrap(),
        };
        let batch = EventBatch {
            events: vec![det; 1000],
        };
        for _ in 0..300 {
            assert_eq!(door.post(&batch, None).unwrap().stray, 1000);
        }
        assert_eq!(door.stray_detections(), 300_000);
        assert!(door.queue.is_empty());
        assert!(door.poll(20).is_empty());
        let spindle = EventBatch {
            events: vec![
                PostedEvent {
                    topic: "/spindle".into(),
                    t_ns: 10,
                    msg: serde_json::json!({"rpm": 1000.0}),
                };
                10_000
            ],
        };
        for _ in 0..MAX_QUEUED / 10_000 {
            door.post(&spindle, None).unwrap();
        }
        let e = door.post(&spindle, None).unwrap_err();
        assert!(matches!(e, NcDoorError::Busy { queued: MAX_QUEUED }), "{e}");
        assert_eq!(door.poll(20).len(), MAX_QUEUED);
        assert!(door.post(&spindle, None).is_ok());
    }

    #[test]
    fn a_cycle_closes_when_every_measurement_tripped_whatever_the_labels() {
        let (mut door, plan) = setup();
        push(&mut door, vec![state(0, MachineStateKind::Idle)]);
        door.poll(0);
        door.request_cycle(7, 1).unwrap();
        let mut dets = detections(&plan, 7, 10);
        let last = dets.pop().unwrap();
        push(&mut door, dets);
        assert!(
            done(&door.poll(2)).is_empty(),
            "one measurement is still to come"
        );
        push(&mut door, vec![last]);
        assert_eq!(done(&door.poll(3)), vec![7]);
        assert!(door.order().is_none());
    }

    /// The patent plan makes each measurement twice: a reading the gateway delivered twice (a
    /// retried upload) is one reading, so it does not stand in for the second measurement and
    /// close the cycle early (the solver, judging by the same rule, would find it incomplete).
    #[test]
    fn a_reading_delivered_twice_is_counted_once() {
        let (mut door, plan) = setup();
        push(&mut door, vec![state(0, MachineStateKind::Idle)]);
        door.poll(0);
        door.request_cycle(8, 1).unwrap();
        let mut dets = detections(&plan, 8, 10);
        let last = dets.pop().unwrap();
        let key = |e: &LinkEvent| match e {
            LinkEvent::Detection(d) => driftwatch_core::cycle::MeasurementKey::of_detection(&d.msg),
            _ => unreachable!(),
        };
        let twin = dets
            .iter()
            .find(|e| key(e) == key(&last))
            .cloned()
            .expect("the plan makes the last measurement twice");
        dets.push(twin);
        push(&mut door, dets);
        assert!(
            done(&door.poll(2)).is_empty(),
            "a reading delivered twice is not the second measurement"
        );
        push(&mut door, vec![last]);
        assert_eq!(done(&door.poll(3)), vec![8]);
    }

    #[test]
    fn a_failed_approach_waits_for_its_retry_or_the_end_of_the_program() {
        let (mut door, plan) = setup();
        push(&mut door, vec![state(0, MachineStateKind::Idle)]);
        door.poll(0);
        door.request_cycle(3, 1).unwrap();
        let mut dets = detections(&plan, 3, 10);
        if let LinkEvent::Detection(d) = &mut dets[4] {
            d.msg.status = Some(DetectionStatus::NoTrip);
        }
        push(&mut door, vec![state(5, MachineStateKind::Measuring)]);
        push(&mut door, dets.clone());
        assert!(done(&door.poll(2)).is_empty(), "a retry may still come");
        // The retry, under the same label, completes the cycle.
        let mut retry = dets[4].clone();
        if let LinkEvent::Detection(d) = &mut retry {
            d.t_ns += 100_000_000_000;
            d.msg.status = None;
        }
        push(&mut door, vec![retry]);
        assert_eq!(done(&door.poll(3)), vec![3]);

        // Without a retry, the NC leaving `measuring` ends the cycle.
        push(
            &mut door,
            vec![state(200_000_000_000, MachineStateKind::Idle)],
        );
        door.poll(4);
        door.request_cycle(4, 5).unwrap();
        let mut dets = detections(&plan, 4, 300_000_000_000);
        if let LinkEvent::Detection(d) = &mut dets[4] {
            d.msg.status = Some(DetectionStatus::NoTrip);
        }
        push(
            &mut door,
            vec![state(299_000_000_000, MachineStateKind::Measuring)],
        );
        push(&mut door, dets);
        assert!(done(&door.poll(6)).is_empty());
        push(
            &mut door,
            vec![state(400_000_000_000, MachineStateKind::Idle)],
        );
        assert_eq!(done(&door.poll(7)), vec![4]);
    }

    #[test]
    fn detections_of_cycles_never_ordered_are_not_kept() {
        let (mut door, plan) = setup();
        push(&mut door, detections(&plan, 99, 10));
        let out = door.poll(1);
        assert_eq!(out.len(), plan.steps.len(), "passed on to the loop");
        assert!(done(&out).is_empty());
        assert!(door.received.is_empty());
    }
}
