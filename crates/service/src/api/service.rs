//! The service itself, as a reader of the machines' times needs it: the clock those times are
//! on (the wall clock, the wall clock sped up for a simulated plant, or a clock a test moves
//! by hand) and which machines are simulated.

use axum::Json;
use axum::Router;
use axum::extract::State;
use axum::routing::get;
use serde::Serialize;

use super::{Guard, Shared};
use crate::clock::ServiceClock;

/// What moves the service clock.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ClockMode {
    /// The wall clock (`time_scale` 1).
    Wall,
    /// The wall clock sped up (or slowed) `time_scale` times: a simulated plant.
    Scaled,
    /// Moved by hand, by a test or a replay: it stands still between moves.
    Manual,
}

/// The service clock and the machines that are simulated.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct ServiceInfo {
    /// The service clock when this answer was made, ns since the Unix epoch (absent when the
    /// API is not told the clock).
    pub clock_ns: Option<i64>,
    /// What moves the clock (absent when the API is not told).
    pub clock: Option<ClockMode>,
    /// Machine seconds per wall second (absent for a manual clock).
    pub time_scale: Option<f64>,
    /// The machines whose link is the truth simulator: no NC behind them.
    pub simulated: Vec<String>,
}

/// The clock's mode and scale.
fn mode(clock: &ServiceClock) -> (ClockMode, Option<f64>) {
    match (clock.is_manual(), clock.scale()) {
        (true, _) | (false, None) => (ClockMode::Manual, None),
        (false, Some(1.0)) => (ClockMode::Wall, Some(1.0)),
        (false, Some(s)) => (ClockMode::Scaled, Some(s)),
    }
}

#[utoipa::path(get, path = "/api/v1/service", responses((status = 200, description = "the service clock now, what moves it (wall, scaled with its time_scale, manual) and the machines that are simulated", body = ServiceInfo)), security((), ("bearer" = [])))]
pub(super) async fn service(State(st): State<Shared>) -> Json<ServiceInfo> {
    let (clock, time_scale) = match st.clock.as_ref().map(mode) {
        Some((m, s)) => (Some(m), s),
        None => (None, None),
    };
    Json(ServiceInfo {
        clock_ns: st.clock.as_ref().map(ServiceClock::now_ns),
        clock,
        time_scale,
        simulated: st.simulated.iter().cloned().collect(),
    })
}

pub(super) fn routes(guard: &Guard) -> Router<Shared> {
    Router::new().route("/service", guard(get(service)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clock_says_what_moves_it() {
        assert_eq!(
            mode(&ServiceClock::scaled(0, 60.0)),
            (ClockMode::Scaled, Some(60.0))
        );
        assert_eq!(
            mode(&ServiceClock::scaled(0, 1.0)),
            (ClockMode::Wall, Some(1.0))
        );
        let (manual, _hand) = ServiceClock::manual(0);
        assert_eq!(mode(&manual), (ClockMode::Manual, None));
    }
}
