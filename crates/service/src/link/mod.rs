//! How the service talks to a machine: one trait, polled with the current time, and the events
//! every link reports in. The simulated machine is a link of its own (`simulated`): the only
//! part of the service that runs the truth simulator, built with the `simulated` feature (on
//! by default; a build without it takes no simulator into the NC's path).

pub use driftwatch_machine::link_event::{LinkError, LinkEvent, RawJson};

#[cfg(feature = "simulated")]
mod simulated;
#[cfg(feature = "simulated")]
pub use simulated::Simulated;

pub trait MachineLink: Send {
    /// Everything that happened up to `now_ns`, in time order.
    fn poll(&mut self, now_ns: i64) -> Vec<LinkEvent>;
    /// Ask the machine to run measurement cycle `number` now.
    fn request_cycle(&mut self, number: i64, now_ns: i64) -> Result<(), LinkError>;
    /// Stop a cycle (timeout or shutdown).
    fn abort_cycle(&mut self, number: i64, now_ns: i64);
    /// The earliest time the machine will report something by itself.
    fn next_event_ns(&self) -> Option<i64>;
    /// What the link notifies when something arrives that `poll` would return (an NC's post,
    /// an agent's sample): the machine's loop sleeps on it and on its clock, and looks at
    /// nothing in between. `None`: the link reports only at [`Self::next_event_ns`] or when
    /// asked.
    fn waker(&self) -> Option<std::sync::Arc<tokio::sync::Notify>> {
        None
    }
    /// The compensation set served from now on (validated: the loop publishes only those). A
    /// link that writes it to the NC does so; the others ignore it.
    fn serve(&mut self, _set: &driftwatch_machine::compensation::CompensationSet) {}
    /// Bring a simulated machine to `t_ns` unobserved (a fleet process taking it over); a
    /// real machine is where it is.
    fn resume_at(&mut self, _t_ns: i64) {}
    /// The service clock, once the service has made it (after its links): a link that judges
    /// an NC's times as they arrive judges them against it.
    fn set_clock(&mut self, _clock: &crate::clock::ServiceClock) {}
}
