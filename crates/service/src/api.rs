//! The HTTP API (axum, JSON under `/api/v1`): machines, the NC's compensation endpoint with
//! ETag and 304, cycles, error series, operator requests. Bearer tokens with roles; reads may
//! be anonymous by configuration. Shell code: it reads what the machine loops publish and
//! the store, and never blocks on a running solve.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use axum::Json;
use axum::Router;
use axum::extract::{Path, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{MethodRouter, get, post};
use serde::Deserialize;
use serde_json::json;

use crate::config::Role;
use crate::daemon::{Inbox, MachineView};
use crate::nc_push::{EventBatch, NcPushHandle};
use crate::store::Store;
use crate::webhook::WebhookStats;

#[derive(Clone)]
pub struct MachineHandle {
    pub view: Arc<Mutex<MachineView>>,
    pub inbox: Arc<Mutex<Inbox>>,
    /// Set for machines on the `nc_push` link.
    pub nc: Option<NcPushHandle>,
    /// The machine's kinematics, for diagnoses of its stored data.
    pub kinematics: Option<Arc<driftwatch_core::kinematics::Kinematics>>,
}

pub struct Auth {
    /// (holder, token, role)
    pub tokens: Vec<(String, String, Role)>,
    pub anonymous_read: bool,
}

pub struct ApiState {
    pub machines: BTreeMap<String, MachineHandle>,
    pub store: Store,
    pub auth: Auth,
    pub latency: RequestLatency,
    pub webhooks: Arc<WebhookStats>,
    /// Diagnoses that may run at once (each takes a core for seconds).
    pub diagnosis_slots: Arc<tokio::sync::Semaphore>,
    /// Diagnoses kept per machine (`http.diagnoses_kept`).
    pub diagnoses_kept: i64,
}

impl ApiState {
    pub fn new(machines: BTreeMap<String, MachineHandle>, store: Store, auth: Auth) -> Self {
        ApiState {
            machines,
            store,
            auth,
            latency: RequestLatency::default(),
            webhooks: Arc::default(),
            diagnosis_slots: Arc::new(tokio::sync::Semaphore::new(1)),
            diagnoses_kept: 200,
        }
    }
}

/// Upper bounds of the request-latency histogram, seconds.
const LATENCY_BUCKETS: [f64; 12] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5, 2.5,
];

/// Request latency per route (the route pattern, never the raw path, so ids do not make
/// new series): cumulative bucket counts, count and sum as Prometheus histograms want them.
#[derive(Default)]
pub struct RequestLatency {
    routes: Mutex<BTreeMap<String, LatencyHistogram>>,
}

#[derive(Default, Clone)]
struct LatencyHistogram {
    buckets: [u64; LATENCY_BUCKETS.len()],
    count: u64,
    sum: f64,
}

impl RequestLatency {
    fn observe(&self, route: &str, seconds: f64) {
        if let Ok(mut m) = self.routes.lock() {
            let h = match m.get_mut(route) {
                Some(h) => h,
                None => m.entry(route.to_string()).or_default(),
            };
            for (b, le) in h.buckets.iter_mut().zip(LATENCY_BUCKETS) {
                if seconds <= le {
                    *b += 1;
                }
            }
            h.count += 1;
            h.sum += seconds;
        }
    }

    fn render(&self, out: &mut String) {
        let name = "driftwatch_http_request_duration_seconds";
        out.push_str(&format!(
            "# HELP {name} Time to answer an HTTP request, by route.\n# TYPE {name} histogram\n"
        ));
        let routes = match self.routes.lock() {
            Ok(m) => m.clone(),
            Err(_) => return,
        };
        for (route, h) in routes {
            for (n, le) in h.buckets.iter().zip(LATENCY_BUCKETS) {
                out.push_str(&format!(
                    "{name}_bucket{{route=\"{route}\",le=\"{le}\"}} {n}\n"
                ));
            }
            out.push_str(&format!(
                "{name}_bucket{{route=\"{route}\",le=\"+Inf\"}} {c}\n{name}_sum{{route=\"{route}\"}} {s}\n{name}_count{{route=\"{route}\"}} {c}\n",
                c = h.count,
                s = h.sum
            ));
        }
    }
}

async fn timed(State(st): State<Shared>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<axum::extract::MatchedPath>()
        .map_or("unmatched", |p| p.as_str())
        .to_string();
    let t0 = std::time::Instant::now();
    let res = next.run(req).await;
    st.latency.observe(&route, t0.elapsed().as_secs_f64());
    res
}

/// Every error answer is the API's JSON error, also those the framework writes itself (a path
/// or query parameter that does not parse, a body too large or of the wrong type, a method
/// not allowed): their text becomes the message, the status gives the code.
async fn json_errors(req: Request, next: Next) -> Response {
    let res = next.run(req).await;
    let status = res.status();
    let is_json = res
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return res;
    }
    let (parts, body) = res.into_parts();
    let text = match axum::body::to_bytes(body, 64 * 1024).await {
        Ok(b) => String::from_utf8_lossy(&b).trim().to_string(),
        Err(_) => String::new(),
    };
    let code = match status {
        StatusCode::BAD_REQUEST => "bad_request",
        StatusCode::NOT_FOUND => "not_found",
        StatusCode::METHOD_NOT_ALLOWED => "method_not_allowed",
        StatusCode::PAYLOAD_TOO_LARGE => "body_too_large",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_media_type",
        StatusCode::UNPROCESSABLE_ENTITY => "bad_body",
        _ => "error",
    };
    let message = if text.is_empty() {
        status.canonical_reason().unwrap_or("error").to_string()
    } else {
        text
    };
    let mut out = ApiError::new(status, code, message).into_response();
    // Keep what the framework said besides the body (Allow on a 405, for one).
    for (k, v) in parts.headers.iter() {
        if k != header::CONTENT_TYPE && k != header::CONTENT_LENGTH {
            out.headers_mut().insert(k.clone(), v.clone());
        }
    }
    out
}

type Shared = Arc<ApiState>;

/// An error as the API answers it: a status, a stable code and a message for people.
pub struct ApiError {
    status: StatusCode,
    code: &'static str,
    message: String,
}

impl ApiError {
    fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> Self {
        ApiError {
            status,
            code,
            message: message.into(),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut r = (
            self.status,
            Json(json!({"code": self.code, "message": self.message})),
        )
            .into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            r.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        r
    }
}

impl From<crate::store::StoreError> for ApiError {
    fn from(e: crate::store::StoreError) -> Self {
        tracing::error!(error = %e, "store error in a request");
        ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "storage",
            "the database could not answer",
        )
    }
}

/// Who made a request (after authentication).
#[derive(Clone, Debug)]
pub struct Caller {
    pub name: String,
    pub role: Option<Role>,
}

/// What an anonymous reader sees of token holders: not their names (who acknowledged an
/// alert, who asked for a diagnosis). Authenticated readers see everything.
fn for_caller(mut v: serde_json::Value, caller: &Caller) -> serde_json::Value {
    fn walk(v: &mut serde_json::Value) {
        match v {
            serde_json::Value::Object(m) => {
                for (k, x) in m.iter_mut() {
                    match (k.as_str(), &mut *x) {
                        ("requested_by", serde_json::Value::String(_)) => {
                            *x = json!("a token holder");
                        }
                        ("acknowledged", serde_json::Value::Object(a)) => {
                            if a.contains_key("by") {
                                a.insert("by".into(), json!("a token holder"));
                            }
                        }
                        ("message", serde_json::Value::String(t))
                            if t.starts_with("acknowledged by ") =>
                        {
                            *x = json!("acknowledged");
                        }
                        _ => walk(x),
                    }
                }
            }
            serde_json::Value::Array(a) => a.iter_mut().for_each(walk),
            _ => {}
        }
    }
    if caller.role.is_none() {
        walk(&mut v);
    }
    v
}

/// Equal-time comparison: the time taken does not tell how much of a token matched.
fn same(a: &[u8], b: &[u8]) -> bool {
    let mut diff = a.len() ^ b.len();
    for i in 0..a.len().max(b.len()) {
        diff |= usize::from(a.get(i).copied().unwrap_or(0) ^ b.get(i).copied().unwrap_or(0));
    }
    diff == 0
}

async fn authenticate(
    State(st): State<Shared>,
    mut req: Request,
    next: Next,
) -> Result<Response, ApiError> {
    // The scheme is case-insensitive (RFC 7235 section 2.1, RFC 6750).
    let presented = req
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim_start().split_once(' '))
        .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
        .map(|(_, tok)| tok.trim());
    let caller = match presented {
        None => Caller {
            name: "anonymous".into(),
            role: None,
        },
        Some(tok) => {
            let found = st.auth.tokens.iter().fold(None, |acc, (name, t, role)| {
                if same(t.as_bytes(), tok.as_bytes()) {
                    Some((name.clone(), *role))
                } else {
                    acc
                }
            });
            match found {
                Some((name, role)) => Caller {
                    name,
                    role: Some(role),
                },
                None => {
                    return Err(ApiError::new(
                        StatusCode::UNAUTHORIZED,
                        "bad_token",
                        "the bearer token is not known",
                    ));
                }
            }
        }
    };
    // The safe methods (RFC 9110 section 9.2.1) read; one a path does not have then gets its
    // 405, not a request for a token.
    let needed = if req.method().is_safe() {
        Role::Read
    } else {
        Role::Write
    };
    match caller.role {
        None if needed == Role::Read && st.auth.anonymous_read => {}
        None => {
            return Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                "token_required",
                format!("this endpoint needs a bearer token with role {needed:?}").to_lowercase(),
            ));
        }
        Some(r) if !r.allows(needed) => {
            return Err(ApiError::new(
                StatusCode::FORBIDDEN,
                "role",
                format!(
                    "the token of '{}' has role {r:?}; this endpoint needs {needed:?}",
                    caller.name
                )
                .to_lowercase(),
            ));
        }
        Some(_) => {}
    }
    req.extensions_mut().insert(caller);
    Ok(next.run(req).await)
}

/// The OpenAPI document of the API, generated from the handlers.
#[derive(utoipa::OpenApi)]
#[openapi(
    info(title = "driftwatch", description = "Rotary-axis compensation of 5-axis machine tools: machines, the NC's compensation endpoint, cycles, errors, alerts, the nc_push link."),
    paths(ready, machines, machine, compensation, cycles, cycle, errors, model, prediction, request_cycle, alerts, ack_alert, metrics, nc_events, nc_request, request_diagnosis, diagnoses, diagnosis),
    components(schemas(DiagnosisRequest, EventBatch, crate::nc_push::PostedEvent, crate::nc_push::CycleOrder, crate::nc_push::OrderStep)),
    modifiers(&BearerAuth, &StandardErrors)
)]
pub struct ApiDoc;

/// The error answers every operation may give besides its own, so that the document lists
/// every status a path returns: each is the JSON error `{"code", "message"}`.
struct StandardErrors;

impl utoipa::Modify for StandardErrors {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::{RefOr, ResponseBuilder};
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

pub fn router(state: Shared) -> Router {
    // Authentication on each route's methods (route_layer), so that a method a path does
    // not have is 405 before any token is asked for.
    let auth = middleware::from_fn_with_state(state.clone(), authenticate);
    let guard = |m: MethodRouter<Shared>| m.route_layer(auth.clone());
    let api = Router::new()
        .route("/machines", guard(get(machines)))
        .route("/machines/{id}", guard(get(machine)))
        .route("/machines/{id}/compensation", guard(get(compensation)))
        .route(
            "/machines/{id}/cycles",
            guard(get(cycles).post(request_cycle)),
        )
        .route("/machines/{id}/cycles/{n}", guard(get(cycle)))
        .route("/machines/{id}/errors", guard(get(errors)))
        .route("/machines/{id}/model", guard(get(model)))
        .route("/machines/{id}/prediction", guard(get(prediction)))
        .route("/machines/{id}/alerts", guard(get(alerts)))
        .route("/machines/{id}/alerts/{alert}/ack", guard(post(ack_alert)))
        .route(
            "/machines/{id}/diagnoses",
            guard(get(diagnoses).post(request_diagnosis)),
        )
        .route("/machines/{id}/diagnoses/{n}", guard(get(diagnosis)))
        .route("/machines/{id}/nc/events", guard(post(nc_events)))
        .route("/machines/{id}/nc/request", guard(get(nc_request)))
        .with_state(state.clone());
    use utoipa::OpenApi as _;
    Router::new()
        .merge(
            utoipa_swagger_ui::SwaggerUi::new("/api/v1/docs")
                .url("/api/v1/openapi.json", ApiDoc::openapi()),
        )
        .nest("/api/v1", api)
        // They name the machines: readers only (anonymous ones when anonymous_read allows).
        // /healthz says no more than that the process answers.
        .merge(
            Router::new()
                .route("/readyz", guard(get(ready)))
                .route("/metrics", guard(get(metrics)))
                .with_state(state.clone()),
        )
        .route("/healthz", get(|| async { "ok" }))
        .route_layer(middleware::from_fn_with_state(state.clone(), timed))
        .with_state(state)
        .fallback(|| async {
            ApiError::new(StatusCode::NOT_FOUND, "not_found", "no such endpoint")
        })
        .layer(middleware::from_fn(json_errors))
}

fn handle<'a>(st: &'a ApiState, id: &str) -> Result<&'a MachineHandle, ApiError> {
    st.machines.get(id).ok_or_else(|| {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown_machine",
            format!("no machine '{id}'"),
        )
    })
}

fn view(h: &MachineHandle) -> MachineView {
    h.view.lock().map(|v| v.clone()).unwrap_or_default()
}

#[utoipa::path(get, path = "/readyz", responses((status = 200, description = "every machine loop is running"), (status = 503, description = "waiting for a machine loop")))]
async fn ready(State(st): State<Shared>) -> Response {
    let waiting: Vec<String> = st
        .machines
        .iter()
        .filter(|(_, h)| view(h).phase.is_none())
        .map(|(id, _)| id.clone())
        .collect();
    if waiting.is_empty() {
        (StatusCode::OK, "ready").into_response()
    } else {
        (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("waiting for {}", waiting.join(", ")),
        )
            .into_response()
    }
}

fn summary(v: &MachineView) -> serde_json::Value {
    json!({
        "id": v.id,
        "kinematics": v.kinematics,
        "phase": v.phase,
        "last_cycle": v.last_cycle,
        "open_cycle": v.open_cycle,
        "open_cycle_progress": v.open_cycle.map(|_| json!({"received": v.open_cycle_received.unwrap_or(0), "expected": v.steps_per_cycle})),
        "schedule": v.schedule,
        "next_due_ns": v.next_due_ns,
        "compensation_version": v.compensation.as_ref().map(|c| c.version),
        "clock_ns": v.clock_ns,
        "faults": v.faults,
        "fault": v.fault,
    })
}

#[utoipa::path(get, path = "/api/v1/machines", responses((status = 200, description = "every machine: phase, last and open cycle, schedule, compensation version, the clock at its loop's last step, its loop's failed steps and the last failure while it lasts")), security((), ("bearer" = [])))]
async fn machines(State(st): State<Shared>) -> Json<serde_json::Value> {
    Json(json!(
        st.machines
            .values()
            .map(|h| summary(&view(h)))
            .collect::<Vec<_>>()
    ))
}

#[utoipa::path(get, path = "/api/v1/machines/{id}", params(("id" = String, Path, description = "machine id")), responses((status = 200, description = "one machine"), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
async fn machine(
    State(st): State<Shared>,
    Path(id): Path<String>,
) -> Result<Json<serde_json::Value>, ApiError> {
    Ok(Json(summary(&view(handle(&st, &id)?))))
}

/// The NC's endpoint: the last validated set, with its version as ETag.
#[utoipa::path(get, path = "/api/v1/machines/{id}/compensation", params(("id" = String, Path, description = "machine id"), ("If-None-Match" = Option<String>, Header, description = "the ETag last read")), responses((status = 200, description = "the last validated compensation set (version, valid_from_ns, source, errors, offsets, sigma); ETag header"), (status = 304, description = "unchanged since the ETag given"), (status = 404, description = "no validated set yet")), security((), ("bearer" = [])))]
async fn compensation(
    State(st): State<Shared>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    // Only the prepared body is taken from the view: no clone of the machine's state, no
    // serialisation per request.
    let body = handle(&st, &id)?
        .view
        .lock()
        .ok()
        .and_then(|v| v.nc_body.clone());
    let Some(body) = body else {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "no_compensation",
            format!(
                "machine '{id}' has no validated compensation yet: the NC keeps its own values"
            ),
        ));
    };
    let etag = format!("\"{id}-v{}\"", body.version);
    let matches = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|h| h.to_str().ok())
        .is_some_and(|h| h.split(',').any(|t| t.trim() == etag || t.trim() == "*"));
    let mut r = if matches {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        (
            [(header::CONTENT_TYPE, "application/json")],
            body.json.clone(),
        )
            .into_response()
    };
    if let Ok(h) = HeaderValue::from_str(&etag) {
        r.headers_mut().insert(header::ETAG, h);
    }
    Ok(r)
}

#[derive(Deserialize)]
struct Page {
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
                    ApiError::new(
                        StatusCode::BAD_REQUEST,
                        "bad_query",
                        format!("before={b} is not a number"),
                    )
                })
            })
            .transpose()
    }
}

/// A page of a newest-first list, with an RFC 8288 `Link: <...>; rel="next"` header when it
/// is full (there may be more before its last row).
fn paged(
    rows: Vec<serde_json::Value>,
    limit: i64,
    next: impl Fn(&serde_json::Value) -> Option<String>,
    path: &str,
) -> Response {
    let more = rows.len() as i64 == limit;
    let link = more
        .then(|| rows.last().and_then(&next))
        .flatten()
        .map(|cursor| format!("<{path}?limit={limit}&before={cursor}>; rel=\"next\""));
    let mut r = Json(serde_json::Value::Array(rows)).into_response();
    if let Some(l) = link.and_then(|l| header::HeaderValue::from_str(&l).ok()) {
        r.headers_mut().insert(header::LINK, l);
    }
    r
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/cycles", params(("id" = String, Path, description = "machine id"), ("limit" = Option<i64>, Query, description = "newest first, at most this many (default 100, at most 1000)"), ("before" = Option<i64>, Query, description = "only cycles numbered below this (the next page: see the Link header)")), responses((status = 200, description = "cycles with status and reason; a full page has a Link header (rel=next) to the next"), (status = 400, description = "a query parameter that is not valid (bad_query)"), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
async fn cycles(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(q): Query<Page>,
) -> Result<Response, ApiError> {
    handle(&st, &id)?;
    let rows = st.store.cycles(&id, q.limit(), q.before_number()?).await?;
    let rows = rows.iter().map(|r| json!(r)).collect();
    Ok(paged(
        rows,
        q.limit(),
        |r| r["cycle"].as_i64().map(|c| c.to_string()),
        &format!("/api/v1/machines/{id}/cycles"),
    ))
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/cycles/{n}", params(("id" = String, Path, description = "machine id"), ("n" = i64, Path, description = "cycle number")), responses((status = 200, description = "the cycle, its detections and its result"), (status = 404, description = "no such cycle")), security((), ("bearer" = [])))]
async fn cycle(
    State(st): State<Shared>,
    Path((id, n)): Path<(String, i64)>,
) -> Result<Json<serde_json::Value>, ApiError> {
    handle(&st, &id)?;
    let row = st.store.cycle(&id, n).await?.ok_or_else(|| {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown_cycle",
            format!("machine '{id}' has no cycle {n}"),
        )
    })?;
    let detections = st.store.detections(&id, n).await?;
    let result = st.store.result(&id, n).await?;
    Ok(Json(json!({
        "cycle": row,
        "detections": detections.into_iter().map(|(t, d)| json!({"t_ns": t, "detection": d})).collect::<Vec<_>>(),
        "result": result,
    })))
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/model", params(("id" = String, Path, description = "machine id")), responses((status = 200, description = "the thermal model: status (waiting, fitted, disabled), parameters with their standard uncertainties, fit quality, time constants, data span; per error what is served (model, last_measured or no_change) and why, its held-out scores, band factor and offset walk"), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
async fn model(
    State(st): State<Shared>,
    Path(id): Path<String>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let m = handle(&st, &id)?
        .view
        .lock()
        .ok()
        .and_then(|v| v.model.clone());
    let Some(m) = m else {
        return Ok(Json(
            json!({"status": "starting", "message": "the machine loop has not looked at the model yet"}),
        ));
    };
    let fitted = m.model.as_ref().map(|model| {
        let channels: Vec<serde_json::Value> = model
            .channels
            .iter()
            .map(|c| {
                let n = c.coef.len();
                let sd: Vec<f64> = (0..n).map(|i| c.cov[i * n + i].max(0.0).sqrt()).collect();
                json!({
                    "name": c.name,
                    "parameters": model.columns.iter().zip(c.coef.iter().zip(&sd)).map(|(col, (v, s))| json!({"column": col, "value": v, "sigma": s})).collect::<Vec<_>>(),
                    "n_obs": c.n_obs,
                    "rms": c.rms_um,
                    "chi2_dof": c.chi2_dof,
                    "discrepancy": c.discrepancy_um,
                    "ridge": c.ridge,
                    "held_out_rmse": c.cv_rmse_um,
                    "offset_walk_per_h": c.offset_walk_per_h.unwrap_or(model.config.offset_walk_per_h),
                    "served": m.served.iter().find(|g| g.channel == c.name),
                    // Temperature gains not jointly significant: held to the fit data's range.
                    "temperatures_held_to_fit_range": !c.held_to_range.is_empty(),
                })
            })
            .collect();
        json!({
            "format": model.format,
            "spindle_time_constants_min": model.config.taus_min,
            "temperature_inputs": model.config.temperatures,
            "n_ref_rpm": model.config.n_ref_rpm,
            "gamma": model.config.gamma,
            "offset_walk_per_h": model.config.offset_walk_per_h,
            "t_ref_c": model.t_ref_c,
            "data_from_ns": model.from_ns,
            "data_to_ns": model.to_ns,
            "data_span_h": (model.to_ns - model.from_ns) as f64 / 3.6e12,
            "channels": channels,
        })
    });
    Ok(Json(json!({
        "status": m.status,
        "message": m.message,
        "validated_cycles": m.validated_cycles,
        "updates_since_fit": m.updates_since_fit,
        "served": m.served,
        "model": fitted,
    })))
}

#[derive(Deserialize)]
struct At {
    at: Option<i64>,
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/prediction", params(("id" = String, Path, description = "machine id"), ("at" = Option<i64>, Query, description = "ns since the Unix epoch; default: the loop's last look. Not before it: the model runs forward, with the inputs held")), responses((status = 200, description = "each error's served value and standard uncertainty (um, urad), its source (model, last_measured or no_change, with the reason for a fallback) and the model's own value"), (status = 400, description = "a time before the model's last input"), (status = 404, description = "no model fitted yet")), security((), ("bearer" = [])))]
async fn prediction(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(q): Query<At>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let (snapshot, note) = match handle(&st, &id)?.view.lock() {
        Ok(v) => (v.predictor.clone(), v.prediction_note.clone()),
        Err(_) => (None, None),
    };
    let Some(p) = snapshot else {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "no_model",
            format!("machine '{id}' has no fitted thermal model yet (see /machines/{id}/model)"),
        ));
    };
    let now = p.t_ns();
    let at = q.at.unwrap_or(now);
    if at < now {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "before_last_input",
            format!(
                "at = {at} lies before the model's last input ({now}): it predicts forward only; past values are in /machines/{id}/errors"
            ),
        ));
    }
    let mut p = (*p).clone();
    let values = p.predict(at);
    Ok(Json(json!({
        "t_ns": at,
        "inputs_held_from_ns": now,
        "values": values,
        "served_note": note,
    })))
}

#[derive(Deserialize)]
struct Window {
    from: Option<i64>,
    to: Option<i64>,
    every: Option<String>,
    source: Option<String>,
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/errors", params(("id" = String, Path, description = "machine id"), ("from" = Option<i64>, Query, description = "ns since the Unix epoch"), ("to" = Option<i64>, Query, description = "ns since the Unix epoch"), ("source" = Option<String>, Query, pattern = "^(measured|predicted|all)$", description = "measured (validated cycles), predicted (the thermal model's served sets) or all (default); every value says its source"), ("every" = Option<String>, Query, pattern = r"^([1-9][0-9]{0,6}s?|[1-9][0-9]{0,4}m|[1-9][0-9]{0,2}h|([1-9][0-9]?|[12][0-9]{2}|3[0-5][0-9]|36[0-6])d)$", description = "bucket width, 1 s to 366 d: seconds or a number with s, m, h or d (15m, 1h; decimals are taken too); each bucket gives per error n, the inverse-variance weighted mean, its sigma, min, max and the last cycle")), responses((status = 200, description = "validated error values (um, urad) at each cycle reference time, or their buckets with `every`"), (status = 400, description = "from after to, or a bad `every`")), security((), ("bearer" = [])))]
async fn errors(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(w): Query<Window>,
) -> Result<Json<serde_json::Value>, ApiError> {
    handle(&st, &id)?;
    let (from, to) = (w.from.unwrap_or(i64::MIN), w.to.unwrap_or(i64::MAX));
    if from > to {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "bad_window",
            "'from' is after 'to'",
        ));
    }
    let every = match w.every.as_deref().map(driftwatch_core::series::parse_every) {
        None => None,
        Some(Ok(e)) => Some(e),
        Some(Err(m)) => return Err(ApiError::new(StatusCode::BAD_REQUEST, "bad_every", m)),
    };
    let (measured, predicted) = match w.source.as_deref().unwrap_or("all") {
        "all" => (true, true),
        "measured" => (true, false),
        "predicted" => (false, true),
        other => {
            return Err(ApiError::new(
                StatusCode::BAD_REQUEST,
                "bad_source",
                format!("source = '{other}': use measured, predicted or all"),
            ));
        }
    };
    let samples = st
        .store
        .error_series(&id, from, to, measured, predicted)
        .await?;
    Ok(Json(match every {
        None => json!(samples),
        Some(e) => json!(driftwatch_core::series::downsample(&samples, e)),
    }))
}

#[utoipa::path(post, path = "/api/v1/machines/{id}/cycles", params(("id" = String, Path, description = "machine id")), responses((status = 202, description = "a cycle will run at the next idle moment"), (status = 401, description = "no or unknown token"), (status = 403, description = "the token may only read")), security(("bearer" = [])))]
async fn request_cycle(
    State(st): State<Shared>,
    Path(id): Path<String>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Response, ApiError> {
    let h = handle(&st, &id)?;
    let now = chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0);
    if let Ok(mut inbox) = h.inbox.lock() {
        inbox.requests.push((caller.name.clone(), now));
    }
    tracing::info!(machine = %id, by = %caller.name, "operator requested a cycle");
    Ok((
        StatusCode::ACCEPTED,
        Json(json!({"message": format!("a cycle will run on '{id}' at the next idle moment"), "by": caller.name})),
    )
        .into_response())
}

/// The stored window a diagnosis runs on (by default the three days up to the last
/// detection).
#[derive(Debug, Default, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DiagnosisRequest {
    /// First detection time, ns since the epoch (default: `to_ns` less three days).
    pub from_ns: Option<i64>,
    /// Last detection time, ns since the epoch (default: the last stored detection).
    pub to_ns: Option<i64>,
    /// One-reading standard uncertainty, um, 0.001-100 (default: the machine's).
    pub sigma_um: Option<f64>,
}

/// Spindle and temperature history read before the window, so the thermal lags start warm.
const DIAGNOSIS_LEAD_NS: i64 = 24 * 3_600_000_000_000;
/// The default window, and the longest one a request may ask for.
const DIAGNOSIS_DEFAULT_NS: i64 = 3 * 24 * 3_600_000_000_000;
const DIAGNOSIS_MAX_NS: i64 = 31 * 24 * 3_600_000_000_000;

/// Run the diagnosis on the stored detections, spindle and temperature series of a window;
/// the result (or why it failed) is stored and returned.
#[utoipa::path(post, path = "/api/v1/machines/{id}/diagnoses", params(("id" = String, Path, description = "machine id")), request_body = DiagnosisRequest, responses((status = 201, description = "the diagnosis: id, summary and the result in the diagnosis.json layout"), (status = 400, description = "a bad window or body (bad_window), or a sigma_um outside 0.001-100 um (bad_sigma)"), (status = 422, description = "the window holds no usable detections, or the diagnosis failed (stored with its reason)"), (status = 409, description = "the machine's kinematics are not known to the API"), (status = 429, description = "another diagnosis is running")), security(("bearer" = [])))]
async fn request_diagnosis(
    State(st): State<Shared>,
    Path(id): Path<String>,
    axum::Extension(caller): axum::Extension<Caller>,
    body: Option<Json<DiagnosisRequest>>,
) -> Result<Response, ApiError> {
    use driftwatch_diagnosis::cycles::{DiagnoseOptions, Inputs, diagnose_inputs};
    let h = handle(&st, &id)?;
    let k = h.kinematics.clone().ok_or_else(|| {
        ApiError::new(
            StatusCode::CONFLICT,
            "no_kinematics",
            format!("machine '{id}' has no kinematics in this service"),
        )
    })?;
    let requested_ns = chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0);
    let req = body.map(|b| b.0).unwrap_or_default();
    let to = match req.to_ns {
        Some(t) => t,
        None => st.store.last_detection_ns(&id).await?.unwrap_or(0),
    };
    let from = req
        .from_ns
        .unwrap_or_else(|| to.saturating_sub(DIAGNOSIS_DEFAULT_NS));
    if from > to {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "bad_window",
            format!("from_ns {from} is after to_ns {to}"),
        ));
    }
    if to.saturating_sub(from) > DIAGNOSIS_MAX_NS {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "bad_window",
            "a diagnosis window may span at most 31 days",
        ));
    }
    let sigma = req.sigma_um.unwrap_or(k.setter.sigma_um);
    let (lo, hi) = driftwatch_diagnosis::cycles::SIGMA_UM_RANGE;
    if !(lo..=hi).contains(&sigma) {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "bad_sigma",
            driftwatch_diagnosis::cycles::DiagnosisError::BadSigma { sigma }.to_string(),
        ));
    }
    let mut inputs = Inputs {
        detections: Vec::new(),
        spindle: Vec::new(),
        temperatures: Vec::new(),
        unparsed: 0,
    };
    for (t_ns, payload) in st.store.detections_between(&id, from, to).await? {
        match serde_json::from_str(&payload) {
            Ok(msg) => inputs
                .detections
                .push(driftwatch_core::recording::Timed { t_ns, msg }),
            Err(_) => inputs.unparsed += 1,
        }
    }
    let (Some(first), Some(last)) = (inputs.detections.first(), inputs.detections.last()) else {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "no_detections",
            format!("machine '{id}' has no stored detection in the window"),
        ));
    };
    let (from, to) = (first.t_ns, last.t_ns);
    for s in st
        .store
        .samples(&id, from.saturating_sub(DIAGNOSIS_LEAD_NS), to)
        .await?
    {
        match s {
            crate::store::Sample::Spindle { t_ns, rpm } => inputs
                .spindle
                .push(driftwatch_core::thermal_model::Event::Spindle { t_ns, rpm }),
            crate::store::Sample::Temperature {
                t_ns,
                sensor,
                celsius,
            } => inputs
                .temperatures
                .push(driftwatch_core::thermal_model::Event::Temperature {
                    t_ns,
                    sensor,
                    celsius,
                }),
        }
    }
    let opts = DiagnoseOptions::new(sigma);
    let unparsed = inputs.unparsed;
    let Ok(_slot) = st.diagnosis_slots.clone().try_acquire_owned() else {
        return Err(ApiError::new(
            StatusCode::TOO_MANY_REQUESTS,
            "diagnosis_busy",
            "another diagnosis is running; ask again when it has answered",
        ));
    };
    let run =
        tokio::task::spawn_blocking(move || diagnose_inputs(&k, &inputs, &opts).map(|d| (d, opts)))
            .await
            .map_err(|e| {
                ApiError::new(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    "diagnosis_panicked",
                    e.to_string(),
                )
            })?;
    let (status, summary, result) = match &run {
        Ok((d, opts)) => (
            "done",
            format!(
                "{} readings in {} cycles over {:.1} h; baseline chi2/dof {:.3}; held-out RMS {:.3} -> {:.3} um; accepted: {}",
                d.readings,
                d.cycles,
                d.span_h,
                d.baseline.chi2_dof,
                d.baseline.rms_heldout_um,
                d.final_fit.rms_heldout_um,
                if d.accepted.is_empty() {
                    "none".to_string()
                } else {
                    d.accepted
                        .iter()
                        .map(|a| a.effect.to_string())
                        .collect::<Vec<_>>()
                        .join(", ")
                }
            ),
            Some(json!({
                "format": "driftwatch-diagnosis/1",
                "machine": id,
                "window": {"from_ns": from, "to_ns": to},
                "unparsed_detections": unparsed,
                "options": opts,
                "diagnosis": d,
            })),
        ),
        Err(e) => ("failed", format!("the diagnosis failed: {e}"), None),
    };
    let text = result.as_ref().map(|r| r.to_string());
    let n = st
        .store
        .add_diagnosis(
            &crate::store::NewDiagnosis {
                machine: &id,
                requested_ns,
                requested_by: &caller.name,
                from_ns: from,
                to_ns: to,
                status,
                summary: &summary,
                result: text.as_deref(),
            },
            st.diagnoses_kept,
        )
        .await?;
    tracing::info!(machine = %id, by = %caller.name, diagnosis = n, "{summary}");
    if status == "failed" {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "diagnosis_failed",
            format!("diagnosis {n}: {summary}"),
        ));
    }
    Ok((
        StatusCode::CREATED,
        [(
            header::LOCATION,
            format!("/api/v1/machines/{id}/diagnoses/{n}"),
        )],
        Json(json!({"id": n, "status": status, "summary": summary, "result": result})),
    )
        .into_response())
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/diagnoses", params(("id" = String, Path, description = "machine id"), ("limit" = Option<i64>, Query, description = "newest first, at most this many (default 100, at most 1000)"), ("before" = Option<i64>, Query, description = "only diagnoses numbered below this (the next page: see the Link header)")), responses((status = 200, description = "the diagnosis runs, newest first: id, window, who asked, status, summary; a full page has a Link header (rel=next) to the next"), (status = 400, description = "a query parameter that is not valid (bad_query)"), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
async fn diagnoses(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(q): Query<Page>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Response, ApiError> {
    handle(&st, &id)?;
    let rows = st
        .store
        .diagnoses(&id, q.limit(), q.before_number()?)
        .await?
        .into_iter()
        .map(|r| for_caller(r, &caller))
        .collect();
    Ok(paged(
        rows,
        q.limit(),
        |r| r["id"].as_i64().map(|c| c.to_string()),
        &format!("/api/v1/machines/{id}/diagnoses"),
    ))
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/diagnoses/{n}", params(("id" = String, Path, description = "machine id"), ("n" = i64, Path, description = "diagnosis number")), responses((status = 200, description = "the diagnosis run with its result (the diagnosis.json layout)"), (status = 404, description = "no such diagnosis")), security((), ("bearer" = [])))]
async fn diagnosis(
    State(st): State<Shared>,
    Path((id, n)): Path<(String, i64)>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Json<serde_json::Value>, ApiError> {
    handle(&st, &id)?;
    let d = st.store.diagnosis(&id, n).await?.ok_or_else(|| {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown_diagnosis",
            format!("machine '{id}' has no diagnosis {n}"),
        )
    })?;
    Ok(Json(for_caller(d, &caller)))
}

fn nc_handle<'a>(st: &'a ApiState, id: &str) -> Result<&'a NcPushHandle, ApiError> {
    handle(st, id)?.nc.as_ref().ok_or_else(|| {
        ApiError::new(
            StatusCode::CONFLICT,
            "not_nc_push",
            format!("machine '{id}' is not on the nc_push link"),
        )
    })
}

/// The NC posts what happened (contract message shapes), a batch taken whole or refused whole.
#[utoipa::path(post, path = "/api/v1/machines/{id}/nc/events", params(("id" = String, Path, description = "machine id")), request_body = EventBatch, responses((status = 202, description = "the batch was taken whole: events queued for the loop, and detections of no ordered cycle (stray: counted in /metrics, not kept)", body = crate::nc_push::Accepted), (status = 400, description = "the batch was refused whole; the message names the bad event (bad_event), or an event's time lies beyond the link's tolerance from the service clock (clock_skew)"), (status = 409, description = "the machine is not on the nc_push link"), (status = 503, description = "too many events wait for the service loop (busy): send the batch again in a few seconds")), security(("bearer" = [])))]
async fn nc_events(
    State(st): State<Shared>,
    Path(id): Path<String>,
    body: Result<Json<EventBatch>, axum::extract::rejection::JsonRejection>,
) -> Result<Response, ApiError> {
    let nc = nc_handle(&st, &id)?;
    let Json(batch) = body.map_err(|e| {
        let code = if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            "body_too_large"
        } else {
            "bad_body"
        };
        ApiError::new(e.status(), code, e.body_text())
    })?;
    let taken = nc.post(&batch).map_err(|e| {
        let (status, code) = match e {
            crate::nc_push::NcPushError::ClockSkew { .. } => {
                (StatusCode::BAD_REQUEST, "clock_skew")
            }
            crate::nc_push::NcPushError::Busy { .. } => (StatusCode::SERVICE_UNAVAILABLE, "busy"),
            _ => (StatusCode::BAD_REQUEST, "bad_event"),
        };
        ApiError::new(status, code, e.to_string())
    })?;
    Ok((StatusCode::ACCEPTED, Json(taken)).into_response())
}

/// The NC polls for a cycle order: 204 when none.
#[utoipa::path(get, path = "/api/v1/machines/{id}/nc/request", params(("id" = String, Path, description = "machine id")), responses((status = 200, description = "the cycle order to run", body = crate::nc_push::CycleOrder), (status = 204, description = "nothing asked"), (status = 409, description = "the machine is not on the nc_push link")), security(("bearer" = [])))]
async fn nc_request(
    State(st): State<Shared>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let nc = nc_handle(&st, &id)?;
    Ok(match nc.order() {
        Some(o) => Json(o).into_response(),
        None => StatusCode::NO_CONTENT.into_response(),
    })
}

/// Open alerts (from the loop) and the latest alert events (from the store).
#[utoipa::path(get, path = "/api/v1/machines/{id}/alerts", params(("id" = String, Path, description = "machine id"), ("limit" = Option<i64>, Query, description = "events newest first, at most this many (default 100, at most 1000)"), ("before" = Option<String>, Query, pattern = r"^-?[0-9]{1,18}\.[0-9]{1,9}\.[0-9]{1,18}$", description = "events before this cursor, `t_ns.alert.seq` of the last event of the previous page (see next_before)")), responses((status = 200, description = "open alerts and the latest alert events; next_before is the cursor of the next page when this one is full"), (status = 400, description = "a query parameter that is not valid (bad_query)"), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
async fn alerts(
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
                        StatusCode::BAD_REQUEST,
                        "bad_query",
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
        .map(|e| format!("{}.{}.{}", e["t_ns"], e["alert"], e["seq"]));
    Ok(Json(for_caller(
        json!({"open": v.open_alerts, "events": events, "next_before": next}),
        &caller,
    )))
}

#[utoipa::path(post, path = "/api/v1/machines/{id}/alerts/{alert}/ack", params(("id" = String, Path, description = "machine id"), ("alert" = u64, Path, description = "alert id")), responses((status = 202, description = "the acknowledgement is taken (the loop applies it at its next step)"), (status = 200, description = "already acknowledged: who did it first, and when (nothing changes)"), (status = 404, description = "no such open alert, or no such machine"), (status = 400, description = "an alert id that is not a number (bad_request)"), (status = 401, description = "no or unknown token"), (status = 403, description = "the token may only read")), security(("bearer" = [])))]
async fn ack_alert(
    State(st): State<Shared>,
    Path((id, alert)): Path<(String, u64)>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Response, ApiError> {
    let h = handle(&st, &id)?;
    let Some(open) = view(h).open_alerts.into_iter().find(|a| a.id == alert) else {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown_alert",
            format!("machine '{id}' has no open alert {alert}"),
        ));
    };
    // Idempotent: an acknowledged alert stays acknowledged by whoever did it first.
    if let Some(a) = open.acknowledged {
        return Ok((
            StatusCode::OK,
            Json(json!({"alert": alert, "by": a.by, "t_ns": a.t_ns, "already": true})),
        )
            .into_response());
    }
    if let Ok(mut inbox) = h.inbox.lock() {
        inbox.acks.push((alert, caller.name.clone()));
    }
    Ok((
        StatusCode::ACCEPTED,
        Json(json!({"alert": alert, "by": caller.name})),
    )
        .into_response())
}

/// Prometheus text: cycles by status, solve time, compensation version, open alerts.
#[utoipa::path(get, path = "/metrics", responses((status = 200, description = "Prometheus text: cycles by outcome, solve time, compensation version, open alerts")))]
async fn metrics(State(st): State<Shared>) -> Response {
    let mut out = String::new();
    let mut metric = |name: &str, kind: &str, help: &str, rows: Vec<(String, f64)>| {
        out.push_str(&format!("# HELP {name} {help}\n# TYPE {name} {kind}\n"));
        for (labels, v) in rows {
            out.push_str(&format!("{name}{{{labels}}} {v}\n"));
        }
    };
    let views: Vec<MachineView> = st.machines.values().map(view).collect();
    let per = |f: &dyn Fn(&MachineView) -> f64| -> Vec<(String, f64)> {
        views
            .iter()
            .map(|v| (format!("machine=\"{}\"", v.id), f(v)))
            .collect()
    };
    let mut cycles = Vec::new();
    for v in &views {
        for (status, n) in [
            ("ok", v.cycles_ok),
            ("rejected", v.cycles_rejected),
            ("abandoned", v.cycles_abandoned),
        ] {
            cycles.push((
                format!("machine=\"{}\",status=\"{status}\"", v.id),
                n as f64,
            ));
        }
    }
    metric(
        "driftwatch_cycles_total",
        "counter",
        "Measurement cycles by outcome.",
        cycles,
    );
    metric(
        "driftwatch_solve_seconds_sum",
        "counter",
        "Time spent validating and solving cycles.",
        per(&|v| v.solve_seconds_sum),
    );
    metric(
        "driftwatch_machine_faults_total",
        "counter",
        "Steps of a machine loop that failed (a store or recorder error) and were tried again.",
        per(&|v| v.faults as f64),
    );
    metric(
        "driftwatch_compensation_version",
        "gauge",
        "Version of the compensation set served to the NC (0: none).",
        per(&|v| v.compensation.as_ref().map_or(0.0, |c| c.version as f64)),
    );
    metric(
        "driftwatch_open_alerts",
        "gauge",
        "Alerts open now.",
        per(&|v| v.open_alerts.len() as f64),
    );
    metric(
        "driftwatch_nc_events_refused_clock_skew_total",
        "counter",
        "NC events refused because their time lay beyond the tolerance from the service clock.",
        st.machines
            .iter()
            .filter_map(|(id, h)| {
                let n = h.nc.as_ref()?.refused_clock_skew();
                Some((format!("machine=\"{id}\""), n as f64))
            })
            .collect(),
    );
    metric(
        "driftwatch_nc_stray_detections_total",
        "counter",
        "NC detections of no ordered cycle: counted, not kept.",
        st.machines
            .iter()
            .filter_map(|(id, h)| {
                let n = h.nc.as_ref()?.stray_detections();
                Some((format!("machine=\"{id}\""), n as f64))
            })
            .collect(),
    );
    use std::sync::atomic::Ordering::Relaxed;
    let w = &st.webhooks;
    metric(
        "driftwatch_webhook_events_total",
        "counter",
        "Alert events by webhook outcome (retried counts attempts that failed and were retried).",
        [
            ("delivered", &w.delivered),
            ("retried", &w.retried),
            ("failed", &w.failed),
            ("dropped", &w.dropped),
        ]
        .into_iter()
        .map(|(k, n)| (format!("outcome=\"{k}\""), n.load(Relaxed) as f64))
        .collect(),
    );
    st.latency.render(&mut out);
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out).into_response()
}
