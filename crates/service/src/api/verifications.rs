//! Verifications: a reference instrument's result (an R-test) compared with the machine's
//! tool-setter results at its reference time, stored, listed, and handed to the machine's
//! loop for its alert rules.

use axum::Json;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde::Deserialize;
use serde_json::json;

use driftwatch_machine::nc_offsets::NcLayout;
use driftwatch_machine::verification::{ReferenceResult, VerifyError, compare};

use super::{ApiError, Caller, ErrorCode, Guard, MAX_PAGE, Shared, for_caller, handle};
use crate::store::StoredVerification;

/// The service clock as the machine's loop last saw it (the wall clock before its first
/// step): a simulated machine's time is not the wall clock's.
pub(super) fn service_now(h: &super::MachineHandle) -> i64 {
    h.view
        .lock()
        .ok()
        .and_then(|v| v.health.clock_ns)
        .unwrap_or_else(|| chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0))
}

fn refusal(e: VerifyError) -> ApiError {
    match e {
        VerifyError::BadReference { .. } => ApiError::new(ErrorCode::BadReference, e.to_string()),
        VerifyError::NoSetterResult { .. } => {
            ApiError::new(ErrorCode::NoSetterResult, e.to_string())
        }
        VerifyError::Setting(_) => {
            tracing::error!(error = %e, "a verification setting passed the configuration's check");
            ApiError::new(ErrorCode::Error, e.to_string())
        }
    }
}

/// Compare a reference instrument's result with the machine's accepted tool-setter results
/// at its reference time; the comparison is stored, returned, and its alert rules run on it
/// at the loop's next step.
#[utoipa::path(post, path = "/api/v1/machines/{id}/verifications", params(("id" = String, Path, description = "machine id")), request_body(content = ReferenceResult, description = "the reference's location errors at its reference time, named and in the units of /cycle/result (EX0B um, EA0C urad, ...), each with one standard uncertainty"), responses((status = 201, description = "the verification as stored: for each error of the reference the setter's value at the reference time (interpolated between the accepted results just before and after it, or the nearest within verification.max_gap_min), the difference reference - setter, the combined standard uncertainty, z, and whether |difference| exceeds k combined sigma; an alert (rule verification) is raised when any does", body = StoredVerification), (status = 400, description = "a reference that cannot be taken (bad_reference): the message names the field (an error the machine does not identify, a value not finite, a sigma not > 0 or missing, a time before 2000 or more than 10 min ahead of the service clock, an empty instrument)"), (status = 422, description = "the body is not a reference's shape (bad_body), or no accepted tool-setter result lies within verification.max_gap_min of the reference time (no_setter_result)"), (status = 409, description = "another process of the fleet runs the machine (run_elsewhere); or the machine's kinematics are not known to the API (no_kinematics)")), security(("bearer" = [])))]
pub(super) async fn verify(
    State(st): State<Shared>,
    Path(id): Path<String>,
    axum::Extension(caller): axum::Extension<Caller>,
    Json(reference): Json<ReferenceResult>,
) -> Result<Response, ApiError> {
    let h = handle(&st, &id)?;
    super::run_here(&id, h)?;
    let k = h.kinematics.clone().ok_or_else(|| {
        ApiError::new(
            ErrorCode::NoKinematics,
            format!("machine '{id}' has no kinematics in this service"),
        )
    })?;
    let now = service_now(h);
    let identified = NcLayout::of(&k).errors;
    reference.validate(&identified, now).map_err(refusal)?;
    let cfg = &st.verification;
    let gap = cfg.max_gap_ns();
    let t = reference.t_ns;
    let setter = st
        .store
        .accepted_results_between(&id, t.saturating_sub(gap), t.saturating_add(gap))
        .await?;
    let v = compare(&id, &reference, &setter, gap, cfg.k).map_err(refusal)?;
    let n = st
        .store
        .add_verification(&v, now, &caller.name, cfg.kept)
        .await?;
    tracing::info!(machine = %id, by = %caller.name, verification = n, "{}", v.summary());
    if let Ok(mut inbox) = h.inbox.lock() {
        inbox.verification(v.clone());
    }
    Ok((
        StatusCode::CREATED,
        Json(StoredVerification {
            id: n,
            created_ns: now,
            requested_by: caller.name,
            verification: v,
        }),
    )
        .into_response())
}

#[derive(Deserialize)]
pub(super) struct VerificationQuery {
    from: Option<i64>,
    to: Option<i64>,
    limit: Option<i64>,
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/verifications", params(("id" = String, Path, description = "machine id"), ("from" = Option<i64>, Query, description = "reference times from this, ns since the Unix epoch"), ("to" = Option<i64>, Query, description = "reference times up to this, ns since the Unix epoch (the next page: the last reference time of this one, less 1)"), ("limit" = Option<i64>, Query, description = "at most this many (default 100, at most 1000)")), responses((status = 200, description = "the stored verifications whose reference time lies in the window, the latest reference time first", body = Vec<StoredVerification>), (status = 400, description = "from after to (bad_window)")), security((), ("bearer" = [])))]
pub(super) async fn verifications(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(q): Query<VerificationQuery>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Json<Vec<serde_json::Value>>, ApiError> {
    handle(&st, &id)?;
    let (from, to) = (q.from.unwrap_or(i64::MIN), q.to.unwrap_or(i64::MAX));
    if from > to {
        return Err(ApiError::new(ErrorCode::BadWindow, "'from' is after 'to'"));
    }
    let limit = q.limit.unwrap_or(100).clamp(1, MAX_PAGE);
    let rows = st
        .store
        .verifications(&id, from, to, limit)
        .await?
        .iter()
        .map(|r| for_caller(json!(r), &caller))
        .collect();
    Ok(Json(rows))
}

pub(super) fn routes(guard: &Guard) -> Router<Shared> {
    Router::new().route(
        "/machines/{id}/verifications",
        guard(get(verifications).post(verify)),
    )
}
