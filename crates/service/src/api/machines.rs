//! Machines: their state, the NC's compensation endpoint, the thermal model and its
//! prediction, the error series for dashboards; and `/readyz`.

use axum::Json;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde::Deserialize;

use crate::series::{ErrorBucket, ErrorSample};
use driftwatch_core::units::NS_PER_H;
use driftwatch_machine::compensation::CompensationSet;
use driftwatch_machine::phase::PhaseInfo;
use driftwatch_thermal::model::{GuardSummary, Prediction, TemperatureInput};
use serde::Serialize;

use super::{ApiError, ErrorCode, Guard, Shared, handle, view};
use crate::daemon::MachineView;

#[utoipa::path(get, path = "/healthz", responses((status = 200, description = "the process answers (no more)", body = String, content_type = "text/plain")))]
pub(super) async fn healthz() -> &'static str {
    "ok"
}

#[utoipa::path(get, path = "/readyz", responses((status = 200, description = "every machine loop is running and storing", body = String, content_type = "text/plain"), (status = 503, description = "a machine loop has not started, or its steps fail (its store or recorder refuses writes: the NC is served the last stored set, no new one); the text names each machine and why", body = String, content_type = "text/plain")))]
pub(super) async fn ready(State(st): State<Shared>) -> Response {
    let mut problems = Vec::new();
    for (id, h) in st.machines.iter() {
        let v = view(h);
        if v.fleet.as_ref().is_some_and(|f| !f.here) {
            // Run by another process of the fleet: that process answers for its loop.
            continue;
        }
        if v.phase.is_none() {
            problems.push(format!("waiting for {id}"));
        } else if v.health.failing {
            let why = v.health.last_fault.as_ref().map_or("", |(_, m)| m.as_str());
            problems.push(format!(
                "{id} is failing (serving its last stored set, version {}): {why}",
                v.compensation
                    .as_ref()
                    .map_or("none".to_string(), |c| c.version.to_string())
            ));
        }
    }
    if problems.is_empty() {
        (StatusCode::OK, "ready").into_response()
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, problems.join("\n")).into_response()
    }
}

/// One machine as the API shows it.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct MachineSummary {
    pub id: String,
    /// The machine description's name.
    pub kinematics: String,
    /// The thermal phase (none before the loop's first step).
    pub phase: Option<PhaseInfo>,
    pub last_cycle: Option<i64>,
    pub open_cycle: Option<i64>,
    pub open_cycle_progress: Option<CycleProgress>,
    /// What the scheduler decided at the last step, in words.
    pub schedule: String,
    pub next_due_ns: Option<i64>,
    /// The version of the set served to the NC (none before the first validated cycle).
    pub compensation_version: Option<u64>,
    /// The set served to the NC, as its compensation endpoint serves it (none before the
    /// first validated cycle).
    pub compensation: Option<CompensationSet>,
    /// The service clock at the loop's last completed step, ns.
    pub clock_ns: Option<i64>,
    /// The service clock when this answer was made, ns: never before any time the answer
    /// holds that the loop stamped (absent when the API is not told the clock). The age of
    /// the served set is `service_clock_ns - compensation.valid_from_ns`.
    pub service_clock_ns: Option<i64>,
    /// Steps of the loop that failed (a store or recorder error) and were tried again.
    pub faults: u64,
    /// Whether the last step failed.
    pub failing: bool,
    pub last_fault: Option<Fault>,
    /// In a fleet of processes: who runs the machine (absent: this process runs every
    /// machine alone). A machine run by another process is shown from the database: its
    /// served set and cycles, not its phase, alerts or predictions.
    pub fleet: Option<crate::daemon::FleetView>,
}

/// Detections an open cycle has received of those its plan expects.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct CycleProgress {
    pub received: usize,
    pub expected: usize,
}

/// A failed step of a machine loop.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct Fault {
    pub t_ns: i64,
    pub message: String,
}

impl MachineSummary {
    /// The summary of `v`, with the service clock read after it was taken.
    fn of(v: &MachineView, service_clock_ns: Option<i64>) -> Self {
        MachineSummary {
            id: v.id.clone(),
            kinematics: v.kinematics.clone(),
            phase: v.phase,
            last_cycle: v.cycles.last,
            open_cycle: v.cycles.open,
            open_cycle_progress: v.cycles.open.map(|_| CycleProgress {
                received: v.cycles.open_received.unwrap_or(0),
                expected: v.cycles.steps_per_cycle,
            }),
            schedule: v.cycles.schedule.clone(),
            next_due_ns: v.cycles.next_due_ns,
            compensation_version: v.compensation.as_ref().map(|c| c.version),
            compensation: v.compensation.clone(),
            clock_ns: v.health.clock_ns,
            service_clock_ns,
            faults: v.health.faults,
            failing: v.health.failing,
            last_fault: v.health.last_fault.as_ref().map(|(t_ns, message)| Fault {
                t_ns: *t_ns,
                message: message.clone(),
            }),
            fleet: v.fleet.clone(),
        }
    }
}

/// The fleet's leases as the database holds them.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct FleetStatus {
    /// This process's name in the leases (absent: it is not part of a fleet).
    pub process: Option<String>,
    pub leases: Vec<crate::store::LeaseRow>,
}

#[utoipa::path(get, path = "/api/v1/fleet", responses((status = 200, description = "this process's name in the fleet and every machine's lease (holder, its address, term, expiry and the database's clock, ms); empty outside a fleet", body = FleetStatus)), security((), ("bearer" = [])))]
pub(super) async fn fleet(State(st): State<Shared>) -> Result<Json<FleetStatus>, ApiError> {
    Ok(Json(FleetStatus {
        process: st.fleet_process.clone(),
        leases: st.store.leases().await?,
    }))
}

#[utoipa::path(get, path = "/api/v1/machines", responses((status = 200, description = "every machine: phase, last and open cycle, schedule, the served set and its version, the clock at its loop's last step and when the answer was made, its loop's failed steps, whether the last step failed, and the last failure", body = Vec<MachineSummary>)), security((), ("bearer" = [])))]
pub(super) async fn machines(State(st): State<Shared>) -> Json<Vec<MachineSummary>> {
    let views: Vec<MachineView> = st.machines.values().map(view).collect();
    // Read after every view: a loop stamps its sets with the clock, so no set in them is
    // younger than this time.
    let now = st.clock.as_ref().map(crate::clock::ServiceClock::now_ns);
    Json(views.iter().map(|v| MachineSummary::of(v, now)).collect())
}

#[utoipa::path(get, path = "/api/v1/machines/{id}", params(("id" = String, Path, description = "machine id")), responses((status = 200, description = "one machine", body = MachineSummary), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
pub(super) async fn machine(
    State(st): State<Shared>,
    Path(id): Path<String>,
) -> Result<Json<MachineSummary>, ApiError> {
    let v = view(handle(&st, &id)?);
    let now = st.clock.as_ref().map(crate::clock::ServiceClock::now_ns);
    Ok(Json(MachineSummary::of(&v, now)))
}

/// The NC's endpoint: the last validated set, with its version as ETag.
#[utoipa::path(get, path = "/api/v1/machines/{id}/compensation", params(("id" = String, Path, description = "machine id"), ("If-None-Match" = Option<String>, Header, description = "the ETag last read"), ("format" = Option<super::nc_offsets::FormatName>, Query, description = "absent: the set as it always was; json: the set plus each NC variable with its step from the previous served set, the errors no variable carries, notes and the datum shift; fanuc, siemens, heidenhain, linuxcnc: the control's program (text/plain) writing its variables (LinuxCNC: a halcmd script setting the trt kinematics' pins; docs/nc.md)"), ("fanuc_increment_mm" = Option<f64>, Query, exclusive_minimum = 0.0, maximum = 0.01, description = "FANUC: the increment of parameters 19700-19714, mm (default 0.001, IS-B; 0.0001 for IS-C)"), ("fanuc_nominal" = Option<String>, Query, pattern = r"^[0-9]{1,9}:-?[0-9]{1,6}(\.[0-9]{1,6})?(,[0-9]{1,9}:-?[0-9]{1,6}(\.[0-9]{1,6})?)*$", description = "FANUC: the commissioned value of each parameter written, PARAMETER:MM,... (required: the parameters are absolute)"), ("linuxcnc_nominal" = Option<String>, Query, pattern = r"^[xyz]-(rot-point|offset):-?[0-9]{1,6}(\.[0-9]{1,6})?(,[xyz]-(rot-point|offset):-?[0-9]{1,6}(\.[0-9]{1,6})?)*$", description = "LinuxCNC: the commissioned value of each trt kinematics pin written, PIN:MM,... by the pin's name without the module's prefix, e.g. x-rot-point:0,y-rot-point:0,x-offset:0,z-offset:0 (required: the pins are absolute)"), ("siemens_carrier" = Option<u32>, Query, minimum = 1, maximum = 9999, description = "Siemens: the swivel data record number (default 1)"), ("siemens_axis_sign" = Option<f64>, Query, description = "Siemens: +1 (default) when the commissioned rotary axis vectors point along the machine file's axes, -1 (any negative number) against"), ("heidenhain_q_base" = Option<u32>, Query, maximum = 1999, description = "HEIDENHAIN: the first Q parameter written (default 1600)"), ("work_origin_mm" = Option<String>, Query, pattern = r"^-?[0-9]{1,6}(\.[0-9]{1,6})?,-?[0-9]{1,6}(\.[0-9]{1,6})?,-?[0-9]{1,6}(\.[0-9]{1,6})?$", description = "the work origin of the datum-shift report, x,y,z mm in the table frame (default 0,0,0)")), responses((status = 200, description = "the last validated compensation set (version, valid_from_ns, source, errors, offsets, sigma; with format=json also variables, not_written, notes, datum_shift, previous_version) or, with format=fanuc|siemens|heidenhain|linuxcnc, the program as text/plain; ETag header (per format)", content((CompensationSet = "application/json"), (String = "text/plain"))), (status = 304, description = "unchanged since the ETag given"), (status = 400, description = "an unknown format (bad_format), an option that does not parse (bad_query), a FANUC parameter or LinuxCNC pin without its commissioned value (missing_nominal)"), (status = 404, description = "no validated set yet"), (status = 409, description = "the set may not be put in that form (offsets_refused): a step from the previous served set beyond the validation limit, a set that does not look validated, a chain without that form (LinuxCNC: two table axes, +Y or +X then +Z, in the direct sense)")), security((), ("bearer" = [])))]
pub(super) async fn compensation(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(q): Query<super::nc_offsets::FormatQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    if let Some(format) = &q.format {
        return super::nc_offsets::in_format(&st, &id, format, &q, &headers).await;
    }
    // Options without a format change nothing, but a bad one is still refused.
    super::nc_offsets::options(&q)?;
    // Only the prepared body is taken from the view: no clone of the machine's state, no
    // serialisation per request.
    let body = handle(&st, &id)?
        .view
        .lock()
        .ok()
        .and_then(|v| v.nc_body.clone());
    let Some(body) = body else {
        return Err(ApiError::new(
            ErrorCode::NoCompensation,
            format!(
                "machine '{id}' has no validated compensation yet: the NC keeps its own values"
            ),
        ));
    };
    // The store's epoch with the version: a version of an emptied or another database never
    // matches a tag the NC kept.
    let etag = format!("\"{id}-{}-v{}\"", st.store.epoch(), body.version);
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

/// The thermal model as the API shows it.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct ModelResponse {
    /// `starting` (the loop has not looked at it yet), `waiting` (not enough cycles),
    /// `initial` (fitted elsewhere), `fitted` or `disabled`.
    pub status: String,
    pub message: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub validated_cycles: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub updates_since_fit: Option<usize>,
    /// What each error serves and why.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub served: Option<Vec<GuardSummary>>,
    /// The fit (none before the first).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<Option<FittedModel>>,
}

/// A fitted thermal model.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct FittedModel {
    pub format: String,
    pub spindle_time_constants_min: Vec<f64>,
    pub temperature_inputs: Vec<TemperatureInput>,
    pub n_ref_rpm: f64,
    pub gamma: f64,
    /// The offset walk's prior, the error's unit squared per hour.
    pub offset_walk_per_h: f64,
    /// Reference temperature of each sensor, deg C.
    pub t_ref_c: std::collections::BTreeMap<String, f64>,
    pub data_from_ns: i64,
    pub data_to_ns: i64,
    pub data_span_h: f64,
    pub channels: Vec<ModelChannel>,
}

/// One error's fit.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct ModelChannel {
    pub name: String,
    /// Each column's coefficient with its standard uncertainty.
    pub parameters: Vec<ModelParameter>,
    pub n_obs: usize,
    pub rms: f64,
    pub chi2_dof: f64,
    pub discrepancy: f64,
    pub ridge: f64,
    pub held_out_rmse: f64,
    pub offset_walk_per_h: f64,
    pub served: Option<GuardSummary>,
    /// Temperature gains not jointly significant: held to the fit data's range.
    pub temperatures_held_to_fit_range: bool,
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct ModelParameter {
    pub column: String,
    pub value: f64,
    pub sigma: f64,
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/model", params(("id" = String, Path, description = "machine id")), responses((status = 200, description = "the thermal model: status (waiting, fitted, disabled), parameters with their standard uncertainties, fit quality, time constants, data span; per error what is served (model, last_measured or no_change) and why, its held-out scores, band factor and offset walk", body = ModelResponse), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
pub(super) async fn model(
    State(st): State<Shared>,
    Path(id): Path<String>,
) -> Result<Json<ModelResponse>, ApiError> {
    let m = handle(&st, &id)?
        .view
        .lock()
        .ok()
        .and_then(|v| v.thermal.model.clone());
    let Some(m) = m else {
        return Ok(Json(ModelResponse {
            status: "starting".into(),
            message: "the machine loop has not looked at the model yet".into(),
            validated_cycles: None,
            updates_since_fit: None,
            served: None,
            model: None,
        }));
    };
    let fitted = m.model.as_ref().map(|model| {
        let channels = model
            .channels
            .iter()
            .map(|c| {
                let n = c.coef.len();
                let parameters = model
                    .columns
                    .iter()
                    .zip(&c.coef)
                    .enumerate()
                    .map(|(i, (column, value))| ModelParameter {
                        column: column.clone(),
                        value: *value,
                        sigma: c.cov[i * n + i].max(0.0).sqrt(),
                    })
                    .collect();
                ModelChannel {
                    name: c.name.clone(),
                    parameters,
                    n_obs: c.n_obs,
                    rms: c.rms_um,
                    chi2_dof: c.chi2_dof,
                    discrepancy: c.discrepancy_um,
                    ridge: c.ridge,
                    held_out_rmse: c.cv_rmse_um,
                    offset_walk_per_h: c
                        .offset_walk_per_h
                        .unwrap_or(model.config.offset_walk_per_h),
                    served: m.served.iter().find(|g| g.channel == c.name).cloned(),
                    temperatures_held_to_fit_range: !c.held_to_range.is_empty(),
                }
            })
            .collect();
        FittedModel {
            format: model.format.clone(),
            spindle_time_constants_min: model.config.taus_min.clone(),
            temperature_inputs: model.config.temperatures.clone(),
            n_ref_rpm: model.config.n_ref_rpm,
            gamma: model.config.gamma,
            offset_walk_per_h: model.config.offset_walk_per_h,
            t_ref_c: model.t_ref_c.clone(),
            data_from_ns: model.from_ns,
            data_to_ns: model.to_ns,
            data_span_h: (model.to_ns - model.from_ns) as f64 / NS_PER_H as f64,
            channels,
        }
    });
    Ok(Json(ModelResponse {
        status: m.status.clone(),
        message: m.message.clone(),
        validated_cycles: Some(m.validated_cycles),
        updates_since_fit: Some(m.updates_since_fit),
        served: Some(m.served.clone()),
        model: Some(fitted),
    }))
}

/// Each error's prediction at one time.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct PredictionResponse {
    pub t_ns: i64,
    /// The inputs (spindle, temperatures) are held from here on.
    pub inputs_held_from_ns: i64,
    pub values: Vec<Prediction>,
    /// Why the loop serves what it serves (a refused or held prediction).
    pub served_note: Option<String>,
}

#[derive(Deserialize)]
pub(super) struct At {
    at: Option<i64>,
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/prediction", params(("id" = String, Path, description = "machine id"), ("at" = Option<i64>, Query, description = "ns since the Unix epoch; default: the loop's last look. Not before it: the model runs forward, with the inputs held")), responses((status = 200, description = "each error's served value and standard uncertainty (um, urad), its source (model, last_measured or no_change, with the reason for a fallback) and the model's own value", body = PredictionResponse), (status = 400, description = "a time before the model's last input"), (status = 404, description = "no model fitted yet")), security((), ("bearer" = [])))]
pub(super) async fn prediction(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(q): Query<At>,
) -> Result<Json<PredictionResponse>, ApiError> {
    let (snapshot, note) = match handle(&st, &id)?.view.lock() {
        Ok(v) => (
            v.thermal.predictor.clone(),
            v.thermal.prediction_note.clone(),
        ),
        Err(_) => (None, None),
    };
    let Some(p) = snapshot else {
        return Err(ApiError::new(
            ErrorCode::NoModel,
            format!("machine '{id}' has no fitted thermal model yet (see /machines/{id}/model)"),
        ));
    };
    let now = p.t_ns();
    let at = q.at.unwrap_or(now);
    if at < now {
        return Err(ApiError::new(
            ErrorCode::BeforeLastInput,
            format!(
                "at = {at} lies before the model's last input ({now}): it predicts forward only; past values are in /machines/{id}/errors"
            ),
        ));
    }
    let mut p = (*p).clone();
    let values = p.predict(at);
    Ok(Json(PredictionResponse {
        t_ns: at,
        inputs_held_from_ns: now,
        values,
        served_note: note,
    }))
}

/// Validated error values at each cycle's reference time, or with `every` their buckets.
#[derive(Debug, Serialize)]
#[serde(untagged)]
pub enum ErrorSeries {
    Samples(Vec<ErrorSample>),
    Buckets(Vec<ErrorBucket>),
}

// By hand: anyOf, not the derive's oneOf, because an empty list is both.
impl utoipa::PartialSchema for ErrorSeries {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        use utoipa::openapi::Ref;
        use utoipa::openapi::schema::{AnyOfBuilder, ArrayBuilder};
        AnyOfBuilder::new()
            .item(ArrayBuilder::new().items(Ref::from_schema_name("ErrorSample")))
            .item(ArrayBuilder::new().items(Ref::from_schema_name("ErrorBucket")))
            .description(Some(
                "the values (without `every`) or their buckets (with `every`)",
            ))
            .into()
    }
}

impl utoipa::ToSchema for ErrorSeries {
    fn schemas(
        schemas: &mut Vec<(
            String,
            utoipa::openapi::RefOr<utoipa::openapi::schema::Schema>,
        )>,
    ) {
        use utoipa::PartialSchema as _;
        schemas.push(("ErrorSample".into(), ErrorSample::schema()));
        schemas.push(("ErrorBucket".into(), ErrorBucket::schema()));
    }
}

#[derive(Deserialize)]
pub(super) struct Window {
    from: Option<i64>,
    to: Option<i64>,
    every: Option<String>,
    source: Option<String>,
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/errors", params(("id" = String, Path, description = "machine id"), ("from" = Option<i64>, Query, description = "ns since the Unix epoch"), ("to" = Option<i64>, Query, description = "ns since the Unix epoch"), ("source" = Option<String>, Query, pattern = "^(measured|predicted|all)$", description = "measured (validated cycles), predicted (the thermal model's served sets) or all (default); every value says its source"), ("every" = Option<String>, Query, pattern = r"^([1-9][0-9]{0,6}s?|[1-9][0-9]{0,4}m|[1-9][0-9]{0,2}h|([1-9][0-9]?|[12][0-9]{2}|3[0-5][0-9]|36[0-6])d)$", description = "bucket width, 1 s to 366 d: seconds or a number with s, m, h or d (15m, 1h; decimals are taken too); each bucket gives per error n, the inverse-variance weighted mean, its sigma, min, max and the last cycle")), responses((status = 200, description = "validated error values (um, urad) at each cycle reference time, or their buckets with `every`", body = ErrorSeries), (status = 400, description = "from after to, or a bad `every`")), security((), ("bearer" = [])))]
pub(super) async fn errors(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(w): Query<Window>,
) -> Result<Json<ErrorSeries>, ApiError> {
    handle(&st, &id)?;
    let (from, to) = (w.from.unwrap_or(i64::MIN), w.to.unwrap_or(i64::MAX));
    if from > to {
        return Err(ApiError::new(ErrorCode::BadWindow, "'from' is after 'to'"));
    }
    let every = match w.every.as_deref().map(crate::series::parse_every) {
        None => None,
        Some(Ok(e)) => Some(e),
        Some(Err(m)) => return Err(ApiError::new(ErrorCode::BadEvery, m)),
    };
    let (measured, predicted) = match w.source.as_deref().unwrap_or("all") {
        "all" => (true, true),
        "measured" => (true, false),
        "predicted" => (false, true),
        other => {
            return Err(ApiError::new(
                ErrorCode::BadSource,
                format!("source = '{other}': use measured, predicted or all"),
            ));
        }
    };
    let samples = st
        .store
        .error_series(&id, from, to, measured, predicted)
        .await?;
    Ok(Json(match every {
        None => ErrorSeries::Samples(samples),
        Some(e) => ErrorSeries::Buckets(crate::series::downsample(&samples, e)),
    }))
}

pub(super) fn routes(guard: &Guard) -> Router<Shared> {
    Router::new()
        .route("/fleet", guard(get(fleet)))
        .route("/machines", guard(get(machines)))
        .route("/machines/{id}", guard(get(machine)))
        .route("/machines/{id}/compensation", guard(get(compensation)))
        .route("/machines/{id}/errors", guard(get(errors)))
        .route("/machines/{id}/model", guard(get(model)))
        .route("/machines/{id}/prediction", guard(get(prediction)))
}
