//! The `nc_push` machine link: a real NC, or its edge gateway, posts what happens (spindle
//! speed, NC state, temperatures, detections, in the recording contract's message shapes) and
//! polls for a cycle order. When the NC is idle and an order is pending it runs the measurement
//! program and posts each detection. Every decision (what is taken, the order, when a cycle
//! closes) is the machine crate's [`NcDoor`]; this module holds one behind a lock, shared by
//! the HTTP handler and the machine's loop.
//!
//! Handshake (documented in docs/integrate-nc.md):
//! 1. `POST /api/v1/machines/{id}/nc/events` `{"events": [{"topic": "/spindle", "t_ns": ..,
//!    "msg": {"rpm": ..}}, ...]}` at every change (and at least once a minute while turning).
//!    A batch is taken whole or refused whole (400 naming the bad event), so a retry loses
//!    nothing and doubles nothing.
//! 2. `GET /api/v1/machines/{id}/nc/request`: 204 when nothing is asked, else 200 with the
//!    order: cycle number, plan, spindle speed and every step (pose, approach, start position,
//!    travel).
//! 3. The NC runs the steps and posts each detection as `/probe/detection` with that cycle
//!    number (the order's step labels are a suggestion; an approach that did not trip may be
//!    retried at once, as the next approach, and the retry replaces it).

use std::sync::{Arc, Mutex, MutexGuard};

use driftwatch_core::kinematics::Limits;
use driftwatch_core::plan::Plan;
pub use driftwatch_machine::nc_door::{
    Accepted, ClockTolerance, CycleOrder, EventBatch, MAX_QUEUED, NcDoor, NcDoorError,
    ORDER_TOLERANCE, OrderStep, PostedEvent, default_max_ahead_s, default_max_behind_s,
};

use crate::link::{LinkError, LinkEvent, MachineLink};

/// The API side: takes the NC's posts, hands out the order.
#[derive(Clone)]
pub struct NcPushHandle {
    door: Arc<Mutex<NcDoor>>,
}

/// The service side: a `MachineLink`.
pub struct NcPushLink {
    door: Arc<Mutex<NcDoor>>,
}

/// The door's lock. Every decision is the door's and leaves it whole, so a holder that
/// panicked left nothing half-done: the door is used as it is.
fn lock(door: &Mutex<NcDoor>) -> MutexGuard<'_, NcDoor> {
    door.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

pub fn nc_push(
    plan: Plan,
    limits: Limits,
    tolerance: ClockTolerance,
) -> (NcPushLink, NcPushHandle) {
    let door = Arc::new(Mutex::new(NcDoor::new(plan, limits, tolerance)));
    (NcPushLink { door: door.clone() }, NcPushHandle { door })
}

impl NcPushHandle {
    /// Take a batch of events whole, or refuse it whole with the first bad event named.
    pub fn post(&self, batch: &EventBatch) -> Result<Accepted, NcDoorError> {
        lock(&self.door).post(batch)
    }

    /// Detections of no ordered cycle, counted and dropped.
    pub fn stray_detections(&self) -> u64 {
        lock(&self.door).stray_detections()
    }

    /// The pending cycle order, if any, until the NC posts a detection of it.
    pub fn order(&self) -> Option<CycleOrder> {
        lock(&self.door).order().cloned()
    }

    /// Events refused because their time lay too far from the service clock.
    pub fn refused_clock_skew(&self) -> u64 {
        lock(&self.door).refused_clock_skew()
    }
}

impl MachineLink for NcPushLink {
    fn poll(&mut self, now_ns: i64) -> Vec<LinkEvent> {
        lock(&self.door).poll(now_ns)
    }

    fn request_cycle(&mut self, number: i64, now_ns: i64) -> Result<(), LinkError> {
        lock(&self.door).request_cycle(number, now_ns)
    }

    fn abort_cycle(&mut self, number: i64, _now_ns: i64) {
        lock(&self.door).abort_cycle(number)
    }

    fn next_event_ns(&self) -> Option<i64> {
        None
    }
}
