//! Cycles: the list, one cycle with its detections and result, an operator's request.

use axum::Json;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde::Serialize;

use super::{ApiError, Caller, ErrorCode, Guard, Page, Shared, handle, paged};
use crate::store::CycleRow;
use driftwatch_core::recording::CycleResultMsg;

/// A cycle with its detections as received and its result (the contract's `/cycle/result`).
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct CycleDetail {
    pub cycle: CycleRow,
    pub detections: Vec<StoredDetection>,
    /// The `/cycle/result` message (docs/recording-format.md); none for an open or abandoned
    /// cycle.
    #[schema(value_type = Option<Object>)]
    pub result: Option<CycleResultMsg>,
}

/// A detection as received: its time and the contract's `/probe/detection` message.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct StoredDetection {
    pub t_ns: i64,
    #[schema(value_type = Object)]
    pub detection: serde_json::Value,
}

/// An operator's request for a cycle, taken.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct CycleRequested {
    pub message: String,
    /// The token holder who asked.
    pub by: String,
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/cycles", params(("id" = String, Path, description = "machine id"), ("limit" = Option<i64>, Query, description = "newest first, at most this many (default 100, at most 1000)"), ("before" = Option<i64>, Query, description = "only cycles numbered below this (the next page: see the Link header)")), responses((status = 200, description = "cycles with status and reason; a full page has a Link header (rel=next) to the next", body = Vec<CycleRow>), (status = 400, description = "a query parameter that is not valid (bad_query)"), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
pub(super) async fn cycles(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(q): Query<Page>,
) -> Result<Response, ApiError> {
    handle(&st, &id)?;
    let rows = st.store.cycles(&id, q.limit(), q.before_number()?).await?;
    Ok(paged(
        rows,
        q.limit(),
        |r| Some(r.cycle.to_string()),
        &format!("/api/v1/machines/{id}/cycles"),
    ))
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/cycles/{n}", params(("id" = String, Path, description = "machine id"), ("n" = i64, Path, description = "cycle number")), responses((status = 200, description = "the cycle, its detections and its result", body = CycleDetail), (status = 404, description = "no such cycle")), security((), ("bearer" = [])))]
pub(super) async fn cycle(
    State(st): State<Shared>,
    Path((id, n)): Path<(String, i64)>,
) -> Result<Json<CycleDetail>, ApiError> {
    handle(&st, &id)?;
    let row = st.store.cycle(&id, n).await?.ok_or_else(|| {
        ApiError::new(
            ErrorCode::UnknownCycle,
            format!("machine '{id}' has no cycle {n}"),
        )
    })?;
    let detections = st.store.detections(&id, n).await?;
    let result = st.store.result(&id, n).await?;
    Ok(Json(CycleDetail {
        cycle: row,
        detections: detections
            .into_iter()
            .map(|(t_ns, detection)| StoredDetection { t_ns, detection })
            .collect(),
        result,
    }))
}

#[utoipa::path(post, path = "/api/v1/machines/{id}/cycles", params(("id" = String, Path, description = "machine id")), responses((status = 202, description = "a cycle will run at the next idle moment", body = CycleRequested), (status = 401, description = "no or unknown token"), (status = 403, description = "the token may only read"), (status = 409, description = "another process of the fleet runs the machine, or none does just now (run_elsewhere): the message names the holder and its address")), security(("bearer" = [])))]
pub(super) async fn request_cycle(
    State(st): State<Shared>,
    Path(id): Path<String>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Response, ApiError> {
    let h = handle(&st, &id)?;
    super::run_here(&id, h)?;
    let now = chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0);
    if let Ok(mut inbox) = h.inbox.lock() {
        inbox.request(caller.name.clone(), now);
    }
    tracing::info!(machine = %id, by = %caller.name, "operator requested a cycle");
    Ok((
        StatusCode::ACCEPTED,
        Json(CycleRequested {
            message: format!("a cycle will run on '{id}' at the next idle moment"),
            by: caller.name,
        }),
    )
        .into_response())
}

pub(super) fn routes(guard: &Guard) -> Router<Shared> {
    Router::new()
        .route(
            "/machines/{id}/cycles",
            guard(get(cycles).post(request_cycle)),
        )
        .route("/machines/{id}/cycles/{n}", guard(get(cycle)))
}
