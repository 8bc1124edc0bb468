//! Linear-axis geometry versions: a machine's measured scale, squareness and ISO 230-1
//! component errors (e.g. from `driftwatch diagonal solve --geometry-out`), stored as a new
//! version and handed to the machine's loop, whose solves start from it from then on.

use axum::Json;
use axum::Router;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde::Deserialize;
use serde_json::json;

use driftwatch_core::linear_axes::LinearGeometry;

use super::{ApiError, Caller, ErrorCode, Guard, Shared, for_caller, handle};
use crate::store::StoredGeometry;

/// A geometry version to store.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GeometryPost {
    /// What measured it (instrument, date, report): named in every result solved with it.
    #[schema(min_length = 1, max_length = 200, pattern = r"\S")]
    pub source: String,
    pub geometry: LinearGeometry,
}

/// The longest `source` taken, characters.
const MAX_SOURCE: usize = 200;

#[utoipa::path(post, path = "/api/v1/machines/{id}/geometry", params(("id" = String, Path, description = "machine id")), request_body(content = GeometryPost, description = "the linear axes' geometry: scale_ppm [X, Y, Z], squareness_urad {xy, xz, yz} in the kinematics' convention, ISO 230-1 component polynomials by name (EZX, EBY, ...: [c1, c2, c3] of p / 100 mm, um or urad), the stack from the bed up and the Abbe offset; and what measured it"), responses((status = 201, description = "the geometry as stored with its version number; the machine's solves start from it from the loop's next step, and each cycle result names it (`geometry`)", body = StoredGeometry), (status = 400, description = "a geometry that cannot be taken (bad_geometry): the message names the field (a value not finite or beyond the limits, an unknown component name, a stack that is not X, Y and Z once each, an empty or overlong source)"), (status = 422, description = "the body is not a geometry's shape (bad_body)"), (status = 409, description = "another process of the fleet runs the machine, or none does just now (run_elsewhere): the message names the holder and its address")), security(("bearer" = [])))]
pub(super) async fn post_geometry(
    State(st): State<Shared>,
    Path(id): Path<String>,
    axum::Extension(caller): axum::Extension<Caller>,
    Json(body): Json<GeometryPost>,
) -> Result<Response, ApiError> {
    let h = handle(&st, &id)?;
    super::run_here(&id, h)?;
    let source = body.source.trim();
    if source.is_empty() || source.chars().count() > MAX_SOURCE {
        return Err(ApiError::new(
            ErrorCode::BadGeometry,
            format!("source must name what measured the geometry in 1 to {MAX_SOURCE} characters"),
        ));
    }
    body.geometry
        .errors()
        .map_err(|e| ApiError::new(ErrorCode::BadGeometry, e.to_string()))?;
    let now = super::verifications::service_now(h);
    let version = st
        .store
        .add_geometry(&id, &body.geometry, source, now, &caller.name)
        .await?;
    let stored = StoredGeometry {
        version,
        created_ns: now,
        requested_by: caller.name.clone(),
        source: source.to_string(),
        geometry: body.geometry,
    };
    tracing::info!(machine = %id, by = %caller.name, version, "linear geometry stored");
    if let Ok(mut inbox) = h.inbox.lock() {
        inbox.geometry(stored.label(), stored.geometry.clone());
    }
    Ok((StatusCode::CREATED, Json(stored)).into_response())
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/geometry", params(("id" = String, Path, description = "machine id")), responses((status = 200, description = "the machine's geometry versions, the newest (the one its solves start from) first; empty when none was posted (the machine file's geometry, if any, is used)", body = Vec<StoredGeometry>)), security((), ("bearer" = [])))]
pub(super) async fn geometry(
    State(st): State<Shared>,
    Path(id): Path<String>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Json<Vec<serde_json::Value>>, ApiError> {
    handle(&st, &id)?;
    let rows = st
        .store
        .geometries(&id)
        .await?
        .iter()
        .map(|g| for_caller(json!(g), &caller))
        .collect();
    Ok(Json(rows))
}

pub(super) fn routes(guard: &Guard) -> Router<Shared> {
    Router::new().route(
        "/machines/{id}/geometry",
        guard(get(geometry).post(post_geometry)),
    )
}
