//! The NC door of a machine on the `nc_push` link: events in, cycle orders out.

use axum::Json;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};

use super::{ApiError, ApiState, ErrorCode, Guard, Shared, handle};
use crate::nc_push::{EventBatch, MAX_ORDER_WAIT_S, NcPushHandle};

pub(super) fn nc_handle<'a>(st: &'a ApiState, id: &str) -> Result<&'a NcPushHandle, ApiError> {
    let h = handle(st, id)?;
    super::run_here(id, h)?;
    h.nc.as_ref().ok_or_else(|| {
        ApiError::new(
            ErrorCode::NotNcPush,
            format!("machine '{id}' is not on the nc_push link"),
        )
    })
}

/// The NC posts what happened (contract message shapes), a batch taken whole or refused whole.
#[utoipa::path(post, path = "/api/v1/machines/{id}/nc/events", params(("id" = String, Path, description = "machine id")), request_body = EventBatch, responses((status = 202, description = "the batch was taken whole: events queued for the loop, and detections of no ordered cycle (stray: counted in /metrics, not kept)", body = crate::nc_push::Accepted), (status = 400, description = "the batch was refused whole; the message names the bad event (bad_event), or an event's time lies beyond the link's tolerance from the service clock (clock_skew)"), (status = 409, description = "another process of the fleet runs the machine (run_elsewhere); or the machine is not on the nc_push link"), (status = 503, description = "too many events wait for the service loop (busy): send the batch again in a few seconds")), security(("bearer" = [])))]
pub(super) async fn nc_events(
    State(st): State<Shared>,
    Path(id): Path<String>,
    body: Result<Json<EventBatch>, axum::extract::rejection::JsonRejection>,
) -> Result<Response, ApiError> {
    let nc = nc_handle(&st, &id)?;
    let Json(batch) = body.map_err(|e| {
        let code = if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            ErrorCode::BodyTooLarge
        } else {
            ErrorCode::BadBody
        };
        ApiError::with_status(e.status(), code, e.body_text())
    })?;
    let taken = nc.post(&batch).map_err(|e| {
        let code = match e {
            crate::nc_push::NcDoorError::ClockSkew { .. } => ErrorCode::ClockSkew,
            crate::nc_push::NcDoorError::Busy { .. } => ErrorCode::Busy,
            _ => ErrorCode::BadEvent,
        };
        ApiError::new(code, e.to_string())
    })?;
    Ok((StatusCode::ACCEPTED, Json(taken)).into_response())
}

/// How long the NC's poll may wait for an order.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub(super) struct OrderWait {
    /// Wait up to this many seconds (0 to 60; default 0: answer at once) for an order when
    /// none is pending; the answer comes as soon as one is given. Keep it below the
    /// service's request timeout.
    #[param(minimum = 0.0, maximum = 60.0)]
    wait_s: Option<f64>,
}

/// The NC polls for a cycle order: 204 when none. A read (the order stays until the NC posts a
/// detection of it), so a reader without a token may see it where anonymous reads are on.
#[utoipa::path(get, path = "/api/v1/machines/{id}/nc/request", params(("id" = String, Path, description = "machine id"), OrderWait), responses((status = 200, description = "the cycle order to run", body = crate::nc_push::CycleOrder), (status = 204, description = "nothing asked (within wait_s)"), (status = 400, description = "wait_s is not a number of seconds from 0 to 60 (bad_query)"), (status = 409, description = "another process of the fleet runs the machine (run_elsewhere); or the machine is not on the nc_push link")), security((), ("bearer" = [])))]
pub(super) async fn nc_request(
    State(st): State<Shared>,
    Path(id): Path<String>,
    query: Result<Query<OrderWait>, axum::extract::rejection::QueryRejection>,
) -> Result<Response, ApiError> {
    let Query(q) = query.map_err(|e| ApiError::new(ErrorCode::BadQuery, e.body_text()))?;
    let wait = q.wait_s.unwrap_or(0.0);
    if !(0.0..=MAX_ORDER_WAIT_S).contains(&wait) {
        return Err(ApiError::new(
            ErrorCode::BadQuery,
            format!("wait_s must be from 0 to {MAX_ORDER_WAIT_S} s, not {wait}"),
        ));
    }
    let nc = nc_handle(&st, &id)?.clone();
    let order = if wait > 0.0 {
        nc.order_within(std::time::Duration::from_secs_f64(wait))
            .await
    } else {
        nc.order()
    };
    Ok(match order {
        Some(o) => Json(o).into_response(),
        None => StatusCode::NO_CONTENT.into_response(),
    })
}

pub(super) fn routes(guard: &Guard) -> Router<Shared> {
    Router::new()
        .route("/machines/{id}/nc/events", guard(post(nc_events)))
        .route("/machines/{id}/nc/request", guard(get(nc_request)))
}
