//! Diagnoses run on a stored window, and their list.

use axum::Json;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use driftwatch_core::units;
use serde::Deserialize;
use serde::Serialize;
use serde_json::json;

use super::{ApiError, Caller, ErrorCode, Guard, Page, Shared, for_caller, handle, paged};
use crate::store::{DiagnosisRow, DiagnosisStatus, StoredDiagnosis};

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

/// A diagnosis that ran and was stored.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct DiagnosisCreated {
    pub id: i64,
    /// `done` (a failed run is answered 422 and stored with its reason).
    pub status: DiagnosisStatus,
    pub summary: String,
    /// The result in the `diagnosis.json` layout (docs/diagnosis.md).
    #[schema(value_type = Option<Object>)]
    pub result: Option<serde_json::Value>,
}

/// Spindle and temperature history read before the window, so the thermal lags start warm.
const DIAGNOSIS_LEAD_NS: i64 = 24 * units::NS_PER_H;

/// The default window, and the longest one a request may ask for.
const DIAGNOSIS_DEFAULT_NS: i64 = 3 * 24 * units::NS_PER_H;

const DIAGNOSIS_MAX_NS: i64 = 31 * 24 * units::NS_PER_H;

/// Run the diagnosis on the stored detections, spindle and temperature series of a window;
/// the result (or why it failed) is stored and returned.
#[utoipa::path(post, path = "/api/v1/machines/{id}/diagnoses", params(("id" = String, Path, description = "machine id")), request_body = DiagnosisRequest, responses((status = 201, description = "the diagnosis: id, summary and the result in the diagnosis.json layout", body = DiagnosisCreated), (status = 400, description = "a bad window or body (bad_window), or a sigma_um outside 0.001-100 um (bad_sigma)"), (status = 422, description = "the window holds no usable detections, or the diagnosis failed (stored with its reason)"), (status = 409, description = "the machine's kinematics are not known to the API"), (status = 429, description = "another diagnosis is running")), security(("bearer" = [])))]
pub(super) async fn request_diagnosis(
    State(st): State<Shared>,
    Path(id): Path<String>,
    axum::Extension(caller): axum::Extension<Caller>,
    body: Option<Json<DiagnosisRequest>>,
) -> Result<Response, ApiError> {
    use driftwatch_diagnosis::cycles::{DiagnoseOptions, diagnose_inputs};
    let h = handle(&st, &id)?;
    let k = h.kinematics.clone().ok_or_else(|| {
        ApiError::new(
            ErrorCode::NoKinematics,
            format!("machine '{id}' has no kinematics in this service"),
        )
    })?;
    // The machine's newest geometry version is the model the diagnosis compares with.
    let k = match st.store.latest_geometry(&id).await? {
        Some(g) => std::sync::Arc::new(
            (*k).clone()
                .with_geometry(&g.geometry, &g.label())
                .map_err(|e| {
                    ApiError::new(ErrorCode::Error, format!("the stored geometry: {e}"))
                })?,
        ),
        None => k,
    };
    let requested_ns = chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0);
    let req = body.map(|b| b.0).unwrap_or_default();
    let (from, to) = requested_window(&st, &id, &req).await?;
    let sigma = req.sigma_um.unwrap_or(k.setter.sigma_um);
    let (lo, hi) = driftwatch_diagnosis::cycles::SIGMA_UM_RANGE;
    if !(lo..=hi).contains(&sigma) {
        return Err(ApiError::new(
            ErrorCode::BadSigma,
            driftwatch_diagnosis::cycles::DiagnosisError::BadSigma { sigma }.to_string(),
        ));
    }
    let (inputs, from, to) = stored_inputs(&st, &id, from, to).await?;
    let opts = DiagnoseOptions::new(sigma);
    let unparsed = inputs.unparsed;
    let Ok(_slot) = st.diagnosis_slots.clone().try_acquire_owned() else {
        return Err(ApiError::new(
            ErrorCode::DiagnosisBusy,
            "another diagnosis is running; ask again when it has answered",
        ));
    };
    let run =
        tokio::task::spawn_blocking(move || diagnose_inputs(&k, &inputs, &opts).map(|d| (d, opts)))
            .await
            .map_err(|e| ApiError::new(ErrorCode::DiagnosisPanicked, e.to_string()))?;
    let (status, summary, result) = match &run {
        Ok((d, opts)) => (
            DiagnosisStatus::Done,
            done_summary(d),
            Some(json!({
                "format": "driftwatch-diagnosis/1",
                "machine": id,
                "window": {"from_ns": from, "to_ns": to},
                "unparsed_detections": unparsed,
                "options": opts,
                "diagnosis": d,
            })),
        ),
        Err(e) => (
            DiagnosisStatus::Failed,
            format!("the diagnosis failed: {e}"),
            None,
        ),
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
    if status == DiagnosisStatus::Failed {
        return Err(ApiError::new(
            ErrorCode::DiagnosisFailed,
            format!("diagnosis {n}: {summary}"),
        ));
    }
    Ok((
        StatusCode::CREATED,
        [(
            header::LOCATION,
            format!("/api/v1/machines/{id}/diagnoses/{n}"),
        )],
        Json(DiagnosisCreated {
            id: n,
            status,
            summary,
            result,
        }),
    )
        .into_response())
}

/// The window a request asks for (by default the three days up to the last stored
/// detection), refused when it is reversed or longer than 31 days.
async fn requested_window(
    st: &Shared,
    id: &str,
    req: &DiagnosisRequest,
) -> Result<(i64, i64), ApiError> {
    let to = match req.to_ns {
        Some(t) => t,
        None => st.store.last_detection_ns(id).await?.unwrap_or(0),
    };
    let from = req
        .from_ns
        .unwrap_or_else(|| to.saturating_sub(DIAGNOSIS_DEFAULT_NS));
    if from > to {
        return Err(ApiError::new(
            ErrorCode::BadWindow,
            format!("from_ns {from} is after to_ns {to}"),
        ));
    }
    if to.saturating_sub(from) > DIAGNOSIS_MAX_NS {
        return Err(ApiError::new(
            ErrorCode::BadWindow,
            "a diagnosis window may span at most 31 days",
        ));
    }
    Ok((from, to))
}

/// The stored detections of the window, and the spindle and temperature samples from
/// [`DIAGNOSIS_LEAD_NS`] before the first of them to the last; with the window narrowed to
/// the detections' times. No detection: 422.
async fn stored_inputs(
    st: &Shared,
    id: &str,
    from: i64,
    to: i64,
) -> Result<(driftwatch_diagnosis::cycles::Inputs, i64, i64), ApiError> {
    let mut inputs = driftwatch_diagnosis::cycles::Inputs {
        detections: Vec::new(),
        spindle: Vec::new(),
        temperatures: Vec::new(),
        unparsed: 0,
    };
    for (t_ns, payload) in st.store.detections_between(id, from, to).await? {
        match serde_json::from_str(&payload) {
            Ok(msg) => inputs
                .detections
                .push(driftwatch_core::recording::Timed { t_ns, msg }),
            Err(_) => inputs.unparsed += 1,
        }
    }
    let (Some(first), Some(last)) = (inputs.detections.first(), inputs.detections.last()) else {
        return Err(ApiError::new(
            ErrorCode::NoDetections,
            format!("machine '{id}' has no stored detection in the window"),
        ));
    };
    let (from, to) = (first.t_ns, last.t_ns);
    for s in st
        .store
        .samples(id, from.saturating_sub(DIAGNOSIS_LEAD_NS), to)
        .await?
    {
        match s {
            crate::store::Sample::Spindle { t_ns, rpm } => inputs
                .spindle
                .push(driftwatch_thermal::model::Event::Spindle { t_ns, rpm }),
            crate::store::Sample::Temperature {
                t_ns,
                sensor,
                celsius,
            } => inputs
                .temperatures
                .push(driftwatch_thermal::model::Event::Temperature {
                    t_ns,
                    sensor,
                    celsius,
                }),
        }
    }
    Ok((inputs, from, to))
}

/// The stored summary of a diagnosis that ran.
fn done_summary(d: &driftwatch_diagnosis::cycles::Diagnosis) -> String {
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
    )
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/diagnoses", params(("id" = String, Path, description = "machine id"), ("limit" = Option<i64>, Query, description = "newest first, at most this many (default 100, at most 1000)"), ("before" = Option<i64>, Query, description = "only diagnoses numbered below this (the next page: see the Link header)")), responses((status = 200, description = "the diagnosis runs, newest first: id, window, who asked, status, summary; a full page has a Link header (rel=next) to the next", body = Vec<DiagnosisRow>), (status = 400, description = "a query parameter that is not valid (bad_query)"), (status = 404, description = "no such machine")), security((), ("bearer" = [])))]
pub(super) async fn diagnoses(
    State(st): State<Shared>,
    Path(id): Path<String>,
    Query(q): Query<Page>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Response, ApiError> {
    handle(&st, &id)?;
    let rows: Vec<serde_json::Value> = st
        .store
        .diagnoses(&id, q.limit(), q.before_number()?)
        .await?
        .iter()
        .map(|r| for_caller(json!(r), &caller))
        .collect();
    Ok(paged(
        rows,
        q.limit(),
        |r| r["id"].as_i64().map(|c| c.to_string()),
        &format!("/api/v1/machines/{id}/diagnoses"),
    ))
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/diagnoses/{n}", params(("id" = String, Path, description = "machine id"), ("n" = i64, Path, description = "diagnosis number")), responses((status = 200, description = "the diagnosis run with its result (the diagnosis.json layout)", body = StoredDiagnosis), (status = 404, description = "no such diagnosis")), security((), ("bearer" = [])))]
pub(super) async fn diagnosis(
    State(st): State<Shared>,
    Path((id, n)): Path<(String, i64)>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Json<serde_json::Value>, ApiError> {
    handle(&st, &id)?;
    let d = st.store.diagnosis(&id, n).await?.ok_or_else(|| {
        ApiError::new(
            ErrorCode::UnknownDiagnosis,
            format!("machine '{id}' has no diagnosis {n}"),
        )
    })?;
    Ok(Json(for_caller(json!(d), &caller)))
}

pub(super) fn routes(guard: &Guard) -> Router<Shared> {
    Router::new()
        .route(
            "/machines/{id}/diagnoses",
            guard(get(diagnoses).post(request_diagnosis)),
        )
        .route("/machines/{id}/diagnoses/{n}", guard(get(diagnosis)))
}
