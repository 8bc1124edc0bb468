//! The HTTP API (axum, JSON under `/api/v1`): one router per resource (machines, cycles,
//! diagnoses, verifications, alerts, the NC door, metrics), bearer tokens with roles (`auth`), one error type
//! (`error`); and the dashboard's static files at `/` (`dashboard`), the API's first client. Reads may be anonymous by configuration. Shell code: it reads what the machine
//! loops publish and the store, and never blocks on a running solve.

mod alerts;
mod auth;
mod cycles;
mod dashboard;
mod diagnoses;
mod error;
mod geometry;
mod machines;
mod metrics;
mod nc;
mod nc_offsets;
mod service;
mod verifications;

pub use auth::Caller;
use auth::for_caller;
pub use diagnoses::DiagnosisRequest;
pub use error::{ApiError, ErrorBody, ErrorCode};
pub use metrics::Metrics;

use std::collections::BTreeMap;
use std::sync::Arc;

use axum::Json;
use axum::Router;
use axum::http::header;
use axum::middleware;
use axum::response::{IntoResponse, Response};
use axum::routing::{MethodRouter, get};
use serde::Deserialize;

use crate::config::Role;
pub use crate::daemon::MachineHandle;
use crate::daemon::MachineView;
use crate::nc_push::EventBatch;
use crate::store::Store;
use crate::webhook::WebhookStats;

pub struct Auth {
    /// (holder, token, role)
    pub tokens: Vec<(String, String, Role)>,
    pub anonymous_read: bool,
}

pub struct ApiState {
    pub machines: BTreeMap<String, MachineHandle>,
    pub store: Store,
    pub auth: Auth,
    pub metrics: Metrics,
    pub webhooks: Arc<WebhookStats>,
    /// Diagnoses that may run at once (each takes a core for seconds).
    pub diagnosis_slots: Arc<tokio::sync::Semaphore>,
    /// Diagnoses kept per machine (`http.diagnoses_kept`).
    pub diagnoses_kept: i64,
    /// A request not answered by then is answered 503 (`http.request_timeout_s`).
    pub request_timeout: std::time::Duration,
    /// The step limits the compensation endpoint's NC forms hold a set to (`[validation]`).
    pub validation: driftwatch_machine::compensation::ValidationLimits,
    /// How references are compared with the tool setter (`[verification]`).
    pub verification: driftwatch_machine::verification::VerificationConfig,
    /// This process's name in a fleet (`[fleet]`).
    pub fleet_process: Option<String>,
    /// The service clock the machines run on (absent: the API is not told, and its answers
    /// carry no clock of their own).
    pub clock: Option<crate::clock::ServiceClock>,
    /// The machines whose link is the truth simulator (no NC behind them).
    pub simulated: std::collections::BTreeSet<String>,
}

impl ApiState {
    pub fn new(machines: BTreeMap<String, MachineHandle>, store: Store, auth: Auth) -> Self {
        ApiState {
            machines,
            store,
            auth,
            metrics: Metrics::default(),
            webhooks: Arc::default(),
            diagnosis_slots: Arc::new(tokio::sync::Semaphore::new(1)),
            diagnoses_kept: 200,
            request_timeout: std::time::Duration::from_secs(120),
            validation: Default::default(),
            verification: Default::default(),
            fleet_process: None,
            clock: None,
            simulated: Default::default(),
        }
    }
}

type Shared = Arc<ApiState>;

/// The OpenAPI document of the API, generated from the handlers.
#[derive(utoipa::OpenApi)]
#[openapi(
    info(title = "driftwatch", description = "Rotary-axis compensation of 5-axis machine tools: machines, the NC's compensation endpoint, cycles, errors, alerts, verifications against a reference instrument, the nc_push link."),
    paths(machines::healthz, machines::ready, service::service, machines::fleet, machines::machines, machines::machine, machines::compensation, cycles::cycles, cycles::cycle, machines::errors, machines::model, machines::prediction, cycles::request_cycle, alerts::alerts, alerts::ack_alert, metrics::metrics, nc::nc_events, nc::nc_request, diagnoses::request_diagnosis, diagnoses::diagnoses, diagnoses::diagnosis, verifications::verify, verifications::verifications, geometry::post_geometry, geometry::geometry),
    components(schemas(ErrorBody, ErrorCode, nc_offsets::FormatName, DiagnosisRequest, driftwatch_machine::verification::ReferenceResult, geometry::GeometryPost, driftwatch_core::linear_axes::LinearGeometry, driftwatch_core::linear_axes::Squareness, crate::store::StoredGeometry, EventBatch, crate::nc_push::PostedEvent, crate::nc_push::CycleOrder, crate::nc_push::OrderStep)),
    modifiers(&BearerAuth, &StandardErrors)
)]
pub struct ApiDoc;

/// The error answers every operation may give besides its own, so that the document lists
/// every status a path returns; and every error answer's body, the JSON error
/// [`ErrorBody`] `{"code", "message"}`.
struct StandardErrors;

impl utoipa::Modify for StandardErrors {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::{Content, Ref, RefOr, ResponseBuilder};
        for (path, item) in openapi.paths.paths.iter_mut() {
            let machine = path.contains("{id}");
            for (op, write) in [(&mut item.get, false), (&mut item.post, true)] {
                let Some(op) = op.as_mut() else { continue };
                let body = op.request_body.is_some();
                let mut add = |code: &str, text: &str| {
                    op.responses
                        .responses
                        .entry(code.to_string())
                        .or_insert_with(|| {
                            RefOr::T(ResponseBuilder::new().description(text).build())
                        });
                };
                add(
                    "400",
                    "a path or query parameter that does not parse (bad_request, bad_query), or a bad body",
                );
                add(
                    "401",
                    "no token where one is needed (token_required: a write, or any read with anonymous_read = false), or a token not known (bad_token)",
                );
                add("500", "the database could not answer (storage)");
                add(
                    "503",
                    "not answered within http.request_timeout_s (timeout)",
                );
                if machine {
                    add("404", "no such machine (unknown_machine)");
                }
                if write {
                    add("403", "the token may only read (role)");
                }
                if body {
                    add("413", "the body is larger than 2 MB (body_too_large)");
                    add("415", "the body is not application/json");
                    add("422", "the body is JSON but not the request's shape");
                }
                for (status, response) in op.responses.responses.iter_mut() {
                    let error = status.starts_with('4') || status.starts_with('5');
                    if let (true, RefOr::T(r)) = (error, response)
                        && r.content.is_empty()
                    {
                        r.content.insert(
                            "application/json".into(),
                            Content::new(Some(Ref::from_schema_name("ErrorBody"))).into(),
                        );
                    }
                }
            }
        }
    }
}

struct BearerAuth;

impl utoipa::Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
    }
}

/// A route's methods behind authentication.
type Guard = dyn Fn(MethodRouter<Shared>) -> MethodRouter<Shared>;

/// Largest request body taken, bytes (a batch of NC events is the largest body sent).
pub const MAX_BODY_BYTES: usize = 2 * 1024 * 1024;

pub fn router(state: Shared) -> Router {
    // Authentication on each route's methods (route_layer), so that a method a path does
    // not have is 405 before any token is asked for.
    let timeout = state.request_timeout;
    let auth = middleware::from_fn_with_state(state.clone(), auth::authenticate);
    let guard = move |m: MethodRouter<Shared>| m.route_layer(auth.clone());
    let api = Router::new()
        .merge(service::routes(&guard))
        .merge(machines::routes(&guard))
        .merge(cycles::routes(&guard))
        .merge(alerts::routes(&guard))
        .merge(diagnoses::routes(&guard))
        .merge(verifications::routes(&guard))
        .merge(geometry::routes(&guard))
        .merge(nc::routes(&guard))
        .with_state(state.clone());
    use utoipa::OpenApi as _;
    let app = Router::new()
        .merge(
            utoipa_swagger_ui::SwaggerUi::new("/api/v1/docs")
                .url("/api/v1/openapi.json", ApiDoc::openapi()),
        )
        .nest("/api/v1", api)
        // They name the machines: readers only (anonymous ones when anonymous_read allows).
        // /healthz says no more than that the process answers.
        .merge(
            Router::new()
                .route("/readyz", guard(get(machines::ready)))
                .route("/metrics", guard(get(metrics::metrics)))
                .with_state(state.clone()),
        )
        .route("/healthz", get(machines::healthz))
        .route_layer(middleware::from_fn_with_state(
            state.clone(),
            metrics::timed,
        ))
        // The dashboard's files: no token (its data calls follow the API's rules), not timed,
        // and not in the OpenAPI document (they are not JSON).
        .merge(dashboard::routes())
        .with_state(state)
        .fallback(|| async { ApiError::new(ErrorCode::NotFound, "no such endpoint") });
    edges(app, timeout)
}

/// The layers every answer passes: the body limit and the timeout inside `json_errors`, so
/// that their refusals (413, 503) are the API's JSON error too, and request tracing outside.
fn edges(app: Router, timeout: std::time::Duration) -> Router {
    app.layer(tower_http::limit::RequestBodyLimitLayer::new(
        MAX_BODY_BYTES,
    ))
    .layer(tower_http::timeout::TimeoutLayer::with_status_code(
        axum::http::StatusCode::SERVICE_UNAVAILABLE,
        timeout,
    ))
    .layer(middleware::from_fn(error::json_errors))
    .layer(
        tower_http::trace::TraceLayer::new_for_http().make_span_with(
            |req: &axum::http::Request<axum::body::Body>| {
                // The path only: a query string may carry a token a client put there, and
                // logs are read by more people than tokens are given to.
                tracing::debug_span!("request", method = %req.method(), path = %req.uri().path())
            },
        ),
    )
}

pub(super) fn handle<'a>(st: &'a ApiState, id: &str) -> Result<&'a MachineHandle, ApiError> {
    st.machines
        .get(id)
        .ok_or_else(|| ApiError::new(ErrorCode::UnknownMachine, format!("no machine '{id}'")))
}

/// A request that changes a machine goes to the process that runs it: refused (409
/// `run_elsewhere`, naming the holder and its address) when another process of the fleet
/// does, or nobody does right now.
pub(super) fn run_here(id: &str, h: &MachineHandle) -> Result<(), ApiError> {
    let fleet = h.view.lock().ok().and_then(|v| v.fleet.clone());
    match fleet {
        Some(f) if !f.here => Err(ApiError::new(
            ErrorCode::RunElsewhere,
            match (f.holder, f.url) {
                (Some(p), Some(url)) => {
                    format!("machine '{id}' is run by process '{p}': send this request to {url}")
                }
                (Some(p), None) => format!(
                    "machine '{id}' is run by process '{p}' of the fleet: send this request there"
                ),
                (None, _) => format!(
                    "machine '{id}' is run by no process right now (its lease is being taken \
                     over): try again shortly"
                ),
            },
        )),
        _ => Ok(()),
    }
}

pub(super) fn view(h: &MachineHandle) -> MachineView {
    h.view.lock().map(|v| v.clone()).unwrap_or_default()
}

#[derive(Deserialize)]
pub(super) struct Page {
    limit: Option<i64>,
    before: Option<String>,
}

/// Most rows one page of a list may hold.
const MAX_PAGE: i64 = 1000;

impl Page {
    fn limit(&self) -> i64 {
        self.limit.unwrap_or(100).clamp(1, MAX_PAGE)
    }

    /// `before` as a number (cycles, diagnoses).
    fn before_number(&self) -> Result<Option<i64>, ApiError> {
        self.before
            .as_deref()
            .map(|b| {
                b.parse().map_err(|_| {
                    ApiError::new(ErrorCode::BadQuery, format!("before={b} is not a number"))
                })
            })
            .transpose()
    }
}

/// A page of a newest-first list, with an RFC 8288 `Link: <...>; rel="next"` header when it
/// is full (there may be more before its last row).
pub(super) fn paged<T: serde::Serialize>(
    rows: Vec<T>,
    limit: i64,
    next: impl Fn(&T) -> Option<String>,
    path: &str,
) -> Response {
    let more = rows.len() as i64 == limit;
    let link = more
        .then(|| rows.last().and_then(&next))
        .flatten()
        .map(|cursor| format!("<{path}?limit={limit}&before={cursor}>; rel=\"next\""));
    let mut r = Json(rows).into_response();
    if let Some(l) = link.and_then(|l| header::HeaderValue::from_str(&l).ok()) {
        r.headers_mut().insert(header::LINK, l);
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::body::Body;
    use axum::http::{Request, StatusCode};
    use http_body_util::BodyExt;
    use std::time::Duration;
    use tower::ServiceExt;

    async fn answer(app: Router, req: Request<Body>) -> (StatusCode, serde_json::Value) {
        let res = app.oneshot(req).await.unwrap();
        let status = res.status();
        let bytes = res.into_body().collect().await.unwrap().to_bytes();
        (status, serde_json::from_slice(&bytes).unwrap_or_default())
    }

    // The clock is tokio's paused one: the hour-long handler is timed out without waiting.
    #[tokio::test(start_paused = true)]
    async fn a_request_not_answered_in_time_gets_the_json_timeout_error() {
        let slow = Router::new().route(
            "/slow",
            get(|| async {
                tokio::time::sleep(Duration::from_secs(3600)).await;
                "late"
            }),
        );
        let req = Request::get("/slow").body(Body::empty()).unwrap();
        let (status, body) = answer(edges(slow, Duration::from_secs(2)), req).await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(body["code"], "timeout", "{body}");
    }

    #[tokio::test]
    async fn a_body_over_the_limit_gets_the_json_error_before_the_handler_reads_it() {
        let echo = Router::new().route("/echo", axum::routing::post(|b: String| async { b }));
        let big = "x".repeat(MAX_BODY_BYTES + 1);
        let req = Request::post("/echo").body(Body::from(big)).unwrap();
        let (status, body) = answer(edges(echo.clone(), Duration::from_secs(2)), req).await;
        assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
        assert_eq!(body["code"], "body_too_large", "{body}");
        let req = Request::post("/echo").body(Body::from("small")).unwrap();
        let res = edges(echo, Duration::from_secs(2))
            .oneshot(req)
            .await
            .unwrap();
        assert_eq!(res.status(), StatusCode::OK);
    }
}
