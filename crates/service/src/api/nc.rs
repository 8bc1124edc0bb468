//! The NC door of a machine on the `nc_push` link: events in, cycle orders out.

use axum::Json;
use axum::Router;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};

use super::{ApiError, ApiState, ErrorCode, Guard, Shared, handle};
use crate::nc_push::{EventBatch, NcPushHandle};

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

/// The NC polls for a cycle order: 204 when none. A read (the order stays until the NC posts a
/// detection of it), so a reader without a token may see it where anonymous reads are on.
#[utoipa::path(get, path = "/api/v1/machines/{id}/nc/request", params(("id" = String, Path, description = "machine id")), responses((status = 200, description = "the cycle order to run", body = crate::nc_push::CycleOrder), (status = 204, description = "nothing asked"), (status = 409, description = "another process of the fleet runs the machine (run_elsewhere); or the machine is not on the nc_push link")), security((), ("bearer" = [])))]
pub(super) async fn nc_request(
    State(st): State<Shared>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let nc = nc_handle(&st, &id)?;
    Ok(match nc.order() {
        Some(o) => Json(o).into_response(),
        None => StatusCode::NO_CONTENT.into_response(),
    })
}

pub(super) fn routes(guard: &Guard) -> Router<Shared> {
    Router::new()
        .route("/machines/{id}/nc/events", guard(post(nc_events)))
        .route("/machines/{id}/nc/request", guard(get(nc_request)))
}
