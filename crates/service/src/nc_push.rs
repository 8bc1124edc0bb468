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
//!    travel). With `?wait_s=S` (up to 60) the answer waits up to S seconds for an order
//!    when none is pending, and comes as soon as one is given.
//! 3. The NC runs the steps and posts each detection as `/probe/detection` with that cycle
//!    number (the order's step labels are a suggestion; an approach that did not trip may be
//!    retried at once, as the next approach, and the retry replaces it).

use std::sync::{Arc, Mutex, MutexGuard, OnceLock};

use tokio::sync::{Notify, watch};

use driftwatch_core::kinematics::Limits;
use driftwatch_core::plan::Plan;
pub use driftwatch_machine::nc_door::{
    Accepted, ClockTolerance, CycleOrder, EventBatch, MAX_QUEUED, NcDoor, NcDoorError,
    ORDER_TOLERANCE, OrderStep, PostedEvent, default_max_ahead_s, default_max_behind_s,
};

use crate::clock::ServiceClock;
use crate::link::{LinkError, LinkEvent, MachineLink};

/// The API side: takes the NC's posts, hands out the order.
#[derive(Clone)]
pub struct NcPushHandle {
    door: Arc<Mutex<NcDoor>>,
    /// Wakes the machine's loop when a batch is taken.
    wake: Arc<Notify>,
    /// Counts the orders given: an NC waiting for one is woken by its change.
    ordered: watch::Sender<u64>,
    /// The service clock a batch's times are judged against as it arrives, once the service
    /// has one (it is made after the links); until then the loop's last look.
    clock: Arc<OnceLock<ServiceClock>>,
}

/// The service side: a `MachineLink`.
pub struct NcPushLink {
    door: Arc<Mutex<NcDoor>>,
    wake: Arc<Notify>,
    ordered: watch::Sender<u64>,
    clock: Arc<OnceLock<ServiceClock>>,
}

/// The longest an NC may wait for an order in one request (`GET .../nc/request?wait_s=`).
pub const MAX_ORDER_WAIT_S: f64 = 60.0;

/// The door's lock. Every decision is the door's and leaves it whole, so a holder that
/// panicked left nothing half-done: the door is used as it is.
fn lock(door: &Mutex<NcDoor>) -> MutexGuard<'_, NcDoor> {
    door.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

pub fn nc_push(
    plan: Arc<Plan>,
    limits: Limits,
    tolerance: ClockTolerance,
) -> (NcPushLink, NcPushHandle) {
    let door = Arc::new(Mutex::new(NcDoor::new(plan, limits, tolerance)));
    let wake = Arc::new(Notify::new());
    let ordered = watch::Sender::new(0);
    let clock = Arc::new(OnceLock::new());
    (
        NcPushLink {
            door: door.clone(),
            wake: wake.clone(),
            ordered: ordered.clone(),
            clock: clock.clone(),
        },
        NcPushHandle {
            door,
            wake,
            ordered,
            clock,
        },
    )
}

impl NcPushHandle {
    /// Take a batch of events whole, or refuse it whole with the first bad event named; its
    /// times are judged against the service clock now.
    pub fn post(&self, batch: &EventBatch) -> Result<Accepted, NcDoorError> {
        let now = self.clock.get().map(ServiceClock::now_ns);
        let accepted = lock(&self.door).post(batch, now)?;
        self.wake.notify_one();
        Ok(accepted)
    }

    /// Detections of no ordered cycle, counted and dropped.
    pub fn stray_detections(&self) -> u64 {
        lock(&self.door).stray_detections()
    }

    /// The pending cycle order, if any, until the NC posts a detection of it.
    pub fn order(&self) -> Option<CycleOrder> {
        lock(&self.door).order().cloned()
    }

    /// The pending cycle order, waiting up to `wait` of wall time for one when none is
    /// pending (a long poll: a gateway asks once a minute instead of every second and still
    /// hears of an order at once).
    pub async fn order_within(&self, wait: std::time::Duration) -> Option<CycleOrder> {
        // Subscribed before the look: an order given between the two is not missed.
        let mut given = self.ordered.subscribe();
        if let Some(o) = self.order() {
            return Some(o);
        }
        let _ = tokio::time::timeout(wait, given.changed()).await;
        self.order()
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
        lock(&self.door).request_cycle(number, now_ns)?;
        self.ordered.send_modify(|n| *n += 1);
        Ok(())
    }

    fn abort_cycle(&mut self, number: i64, _now_ns: i64) {
        lock(&self.door).abort_cycle(number)
    }

    fn next_event_ns(&self) -> Option<i64> {
        None
    }

    fn waker(&self) -> Option<Arc<Notify>> {
        Some(self.wake.clone())
    }

    fn set_clock(&mut self, clock: &ServiceClock) {
        // Set once: a link is started with one service.
        let _ = self.clock.set(clock.clone());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::kinematics::Kinematics;
    use driftwatch_core::plan::PlanConfig;
    use std::time::Duration;

    const T0: i64 = 1_700_000_000_000_000_000;

    fn door() -> (NcPushLink, NcPushHandle) {
        let k = Kinematics::load("table_bc").expect("a built-in machine");
        let plan = Plan::build(&k, &PlanConfig::load("patent").expect("a built-in plan"))
            .expect("the patent plan builds");
        let tolerance = ClockTolerance {
            ahead_ns: 60 * 1_000_000_000,
            behind_ns: 3_600 * 1_000_000_000,
        };
        nc_push(Arc::new(plan), k.config.limits, tolerance)
    }

    fn idle(handle: &NcPushHandle) {
        let batch: EventBatch = serde_json::from_value(serde_json::json!({"events": [
            {"topic": "/machine/state", "t_ns": T0, "msg": {"state": "idle", "program": null}}
        ]}))
        .expect("a valid batch");
        handle.post(&batch).expect("the batch is taken");
    }

    /// Whether `n` holds a wake (a permit stored by `notify_one`), taking it.
    async fn woken(n: &Notify) -> bool {
        tokio::select! {
            biased;
            _ = n.notified() => true,
            _ = std::future::ready(()) => false,
        }
    }

    /// A quiet machine's loop looks once a minute; a batch arriving 50 s after its look from an
    /// NC whose clock is 15 s fast is 65 s ahead of that look but 15 s ahead of the service
    /// clock, which is what it is judged by once the service has given the link its clock.
    #[test]
    fn a_batch_is_judged_against_the_service_clock_not_the_loops_last_look() {
        let (mut link, handle) = door();
        let s = 1_000_000_000;
        let post = |t_ns: i64| {
            let batch: EventBatch = serde_json::from_value(serde_json::json!({"events": [
                {"topic": "/spindle", "t_ns": t_ns, "msg": {"rpm": 1000.0}}
            ]}))
            .expect("a valid batch");
            handle.post(&batch)
        };
        link.poll(T0);
        assert!(
            post(T0 + 65 * s).is_err(),
            "no clock: judged by the last look"
        );
        let (clock, hand) = ServiceClock::manual(T0);
        link.set_clock(&clock);
        hand.set(T0 + 50 * s);
        assert_eq!(post(T0 + 65 * s).map(|a| a.accepted), Ok(1));
        assert!(post(T0 + 111 * s).is_err(), "61 s ahead of the clock");
        assert_eq!(handle.refused_clock_skew(), 2);
    }

    #[tokio::test]
    async fn a_batch_taken_wakes_the_loop_and_a_refused_one_does_not() {
        let (link, handle) = door();
        let wake = link.waker().expect("the nc_push link has a waker");
        assert!(!woken(&wake).await);
        let bad: EventBatch = serde_json::from_value(serde_json::json!({"events": [
            {"topic": "/machine/state", "t_ns": T0, "msg": {"state": "dancing", "program": null}}
        ]}))
        .expect("a batch in shape");
        assert!(handle.post(&bad).is_err());
        assert!(!woken(&wake).await, "a refused batch has nothing to poll");
        idle(&handle);
        assert!(woken(&wake).await, "a batch taken wakes the loop");
    }

    #[tokio::test]
    async fn an_nc_waiting_for_an_order_gets_it_as_soon_as_it_is_given() {
        let (mut link, handle) = door();
        idle(&handle);
        // The loop takes the NC's state at its poll.
        assert_eq!(link.poll(T0).len(), 1);
        let waiting = {
            let handle = handle.clone();
            tokio::spawn(async move { handle.order_within(Duration::from_secs(3600)).await })
        };
        // On the test's one thread the waiter runs up to its wait before the order is given.
        tokio::task::yield_now().await;
        assert!(!waiting.is_finished());
        link.request_cycle(7, T0)
            .expect("an idle NC takes an order");
        let order = tokio::time::timeout(Duration::from_secs(60), waiting)
            .await
            .expect("the waiter hears of the order at once")
            .expect("the waiter does not panic");
        assert_eq!(order.map(|o| o.cycle), Some(7));
    }

    #[tokio::test(start_paused = true)]
    async fn an_nc_waiting_for_an_order_hears_none_at_the_end_of_its_wait() {
        let (_link, handle) = door();
        idle(&handle);
        let t = tokio::time::Instant::now();
        assert!(handle.order_within(Duration::from_secs(30)).await.is_none());
        assert!(t.elapsed() >= Duration::from_secs(30));
    }
}
