//! Alerts: the open ones and the latest events, and acknowledgement.

use axum::Json;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::Serialize;
use serde_json::json;

use crate::store::AlertEventRow;
use driftwatch_machine::alerts::Alert;
use driftwatch_machine::machine_core::AlertThreshold;

use super::{ApiError, Caller, ErrorCode, Guard, Page, Shared, for_caller, handle, view};

/// A machine's open alerts and its latest alert events. For an anonymous reader the names of
/// token holders are replaced by "a token holder".
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct AlertsResponse {
    pub open: Vec<Alert>,
    pub events: Vec<AlertEventRow>,
    /// The machine's threshold rules: an error `limit` from its reference raises, back
    /// within `clear` resolves (um, urad).
    pub thresholds: Vec<AlertThreshold>,
    /// The cursor of the next page (`before`), when this one is full.
    pub next_before: Option<String>,
}

/// An acknowledgement taken, or found already made.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct AckResponse {
    pub alert: u64,
    /// Who acknowledged it (first).
    pub by: String,
    /// When it was first acknowledged (only when it already was).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub t_ns: Option<i64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub already: Option<bool>,
}

/// Open alerts (from the loop) and the latest alert events (from the store).
#[utoipa::path(get, path = "/api/v1/machines/{id}/alerts", params(("id" = String, Path, description = "machine id"), ("limit" = Option<i64>, Query, description = "events newest first, at most this many (default 100, at most 1000)"), ("before" = Option<String>, Query, pattern = r"^-?[0-9]{1,18}\.[0-9]{1,9}\.[0-9]{1,18}$", description = "events before this cursor, `t_ns.alert.seq` of the last event of the previous page (see next_before)")), responses((status = 200, description = "open alerts, the latest alert events and the threshold rules with their references; next_before is the cursor of the next page when this one is full", body = AlertsResponse), (status = 400, description = "a query parameter that is not valid (bad_query)"), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
pub(super) async fn alerts(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(q): Query<Page>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let v = view(handle(&st, &id)?);
    let before = match q.before.as_deref() {
        None => None,
        Some(b) => {
            let parts: Vec<Option<i64>> = b.split('.').map(|p| p.parse().ok()).collect();
            match parts.as_slice() {
                [Some(t), Some(a), Some(s)] => Some((*t, *a, *s)),
                _ => {
                    return Err(ApiError::new(
                        ErrorCode::BadQuery,
                        format!("before={b} is not a cursor t_ns.alert.seq"),
                    ));
                }
            }
        }
    };
    let events = st.store.alert_events(&id, q.limit(), before).await?;
    let next = (events.len() as i64 == q.limit())
        .then(|| events.last())
        .flatten()
        .map(|e| format!("{}.{}.{}", e.t_ns, e.alert, e.seq));
    let body = AlertsResponse {
        open: v.open_alerts,
        events,
        thresholds: v.thresholds,
        next_before: next,
    };
    Ok(Json(for_caller(json!(body), &caller)))
}

#[utoipa::path(post, path = "/api/v1/machines/{id}/alerts/{alert}/ack", params(("id" = String, Path, description = "machine id"), ("alert" = u64, Path, description = "alert id")), responses((status = 202, description = "the acknowledgement is taken (the loop applies it at its next step)", body = AckResponse), (status = 200, description = "already acknowledged: who did it first, and when (nothing changes)", body = AckResponse), (status = 404, description = "no such open alert, or no such machine"), (status = 400, description = "an alert id that is not a number (bad_request)"), (status = 401, description = "no or unknown token"), (status = 403, description = "the token may only read"), (status = 409, description = "another process of the fleet runs the machine, or none does just now (run_elsewhere): the message names the holder and its address")), security(("bearer" = [])))]
pub(super) async fn ack_alert(
    State(st): State<Shared>,
    Path((id, alert)): Path<(String, u64)>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Response, ApiError> {
    let h = handle(&st, &id)?;
    super::run_here(&id, h)?;
    let Some(open) = view(h).open_alerts.into_iter().find(|a| a.id == alert) else {
        return Err(ApiError::new(
            ErrorCode::UnknownAlert,
            format!("machine '{id}' has no open alert {alert}"),
        ));
    };
    // Idempotent: an acknowledged alert stays acknowledged by whoever did it first.
    if let Some(a) = open.acknowledged {
        return Ok((
            StatusCode::OK,
            Json(AckResponse {
                alert,
                by: a.by,
                t_ns: Some(a.t_ns),
                already: Some(true),
            }),
        )
            .into_response());
    }
    if let Ok(mut inbox) = h.inbox.lock() {
        inbox.ack(alert, caller.name.clone());
    }
    Ok((
        StatusCode::ACCEPTED,
        Json(AckResponse {
            alert,
            by: caller.name,
            t_ns: None,
            already: None,
        }),
    )
        .into_response())
}

pub(super) fn routes(guard: &Guard) -> Router<Shared> {
    Router::new()
        .route("/machines/{id}/alerts", guard(get(alerts)))
        .route("/machines/{id}/alerts/{alert}/ack", guard(post(ack_alert)))
}
