//! The compensation endpoint in an NC's own form (`?format=fanuc|siemens|heidenhain|linuxcnc|json`):
//! the served set through `driftwatch_nc::offsets`, its previous version from the store for
//! the step, the options a control needs from the query. Without `format` the endpoint keeps
//! its prepared JSON body (`machines::compensation`).

use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;

use driftwatch_nc::offsets::{
    LINUXCNC_PINS, NcOptions, OffsetFormat, OffsetsError, json_body, nc_offsets,
};

use super::{ApiError, ErrorCode, Shared, handle};

/// The forms of the compensation endpoint (its `format` parameter in the OpenAPI document).
#[derive(utoipa::ToSchema)]
#[schema(rename_all = "snake_case")]
// Never built: it exists to state the parameter's values in the document.
#[allow(dead_code)]
pub(super) enum FormatName {
    Json,
    Fanuc,
    Siemens,
    Heidenhain,
    Linuxcnc,
}

/// The query of the compensation endpoint.
// Unknown parameters are ignored, as the endpoint always has: no client breaks.
#[derive(Debug, Default, Deserialize)]
pub(super) struct FormatQuery {
    pub format: Option<String>,
    /// FANUC: the increment of 19700-19714, mm (0.001 IS-B, 0.0001 IS-C).
    pub fanuc_increment_mm: Option<f64>,
    /// FANUC: the commissioned values, `19700:-123.456,19702:50` (mm).
    pub fanuc_nominal: Option<String>,
    pub siemens_carrier: Option<u32>,
    pub siemens_axis_sign: Option<f64>,
    pub heidenhain_q_base: Option<u32>,
    /// LinuxCNC: the commissioned values of the trt kinematics' pins,
    /// `x-rot-point:0,y-rot-point:0,x-offset:0,z-offset:-50` (mm).
    pub linuxcnc_nominal: Option<String>,
    /// `x,y,z` mm in the table frame.
    pub work_origin_mm: Option<String>,
}

fn bad(message: String) -> ApiError {
    ApiError::new(ErrorCode::BadQuery, message)
}

/// The options of the query, each checked as the OpenAPI document states it, with or without
/// `format`: a request the document calls invalid is refused, never half read.
pub(super) fn options(q: &FormatQuery) -> Result<NcOptions, ApiError> {
    let mut o = NcOptions::default();
    if let Some(v) = q.fanuc_increment_mm {
        if !(v > 0.0 && v <= 0.01) {
            return Err(bad(format!(
                "fanuc_increment_mm = {v}: the increment of 19700-19714 in mm, in (0, 0.01] \
                 (0.001 IS-B, 0.0001 IS-C)"
            )));
        }
        o.fanuc_increment_mm = v;
    }
    if let Some(list) = &q.fanuc_nominal {
        for pair in list.split(',') {
            let parsed = pair.split_once(':').and_then(|(n, v)| {
                Some((n.trim().parse::<u32>().ok()?, v.trim().parse::<f64>().ok()?))
            });
            match parsed {
                Some((n, v)) if v.is_finite() => {
                    o.fanuc_nominal_mm.insert(n, v);
                }
                _ => {
                    return Err(bad(format!(
                        "fanuc_nominal entry '{pair}' is not PARAMETER:MM (e.g. 19700:-123.456)"
                    )));
                }
            }
        }
    }
    if let Some(list) = &q.linuxcnc_nominal {
        for pair in list.split(',') {
            let parsed = pair.split_once(':').and_then(|(n, v)| {
                let n = n.trim();
                let v = v.trim().parse::<f64>().ok()?;
                LINUXCNC_PINS.contains(&n).then_some((n, v))
            });
            match parsed {
                Some((n, v)) if v.is_finite() => {
                    o.linuxcnc_nominal_mm.insert(n.to_string(), v);
                }
                _ => {
                    return Err(bad(format!(
                        "linuxcnc_nominal entry '{pair}' is not PIN:MM (e.g. x-rot-point:0), PIN \
                         one of {}",
                        LINUXCNC_PINS.join(", ")
                    )));
                }
            }
        }
    }
    if let Some(v) = q.siemens_carrier {
        if !(1..=9999).contains(&v) {
            return Err(bad(format!(
                "siemens_carrier = {v}: a record number, 1 to 9999"
            )));
        }
        o.siemens_carrier = v;
    }
    // Any negative number means "against": the sign is all that is asked.
    if let Some(v) = q.siemens_axis_sign {
        o.siemens_axis_sign = if v < 0.0 { -1.0 } else { 1.0 };
    }
    if let Some(v) = q.heidenhain_q_base {
        // Q parameters run to Q1999; the variables written follow the first.
        if v > 1999 {
            return Err(bad(format!(
                "heidenhain_q_base = {v}: Q parameters end at Q1999"
            )));
        }
        o.heidenhain_q_base = v;
    }
    if let Some(s) = &q.work_origin_mm {
        let v: Vec<f64> = s
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad(format!("work_origin_mm '{s}' is not x,y,z in mm")))?;
        o.work_origin_mm = v
            .try_into()
            .map_err(|_| bad(format!("work_origin_mm '{s}' is not x,y,z in mm")))?;
    }
    Ok(o)
}

/// The served set in `format`: JSON (the set, its variables, steps and datum shift) or the
/// control's program as text. Refusals name why; no value is ever served that the set's
/// validation or the step limit did not pass.
pub(super) async fn in_format(
    st: &Shared,
    id: &str,
    format: &str,
    q: &FormatQuery,
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    let format = OffsetFormat::parse(format)
        .map_err(|e| ApiError::new(ErrorCode::BadFormat, e.to_string()))?;
    let opts = options(q)?;
    let h = handle(st, id)?;
    let set = h.view.lock().ok().and_then(|v| v.compensation.clone());
    let Some(set) = set else {
        return Err(ApiError::new(
            ErrorCode::NoCompensation,
            format!(
                "machine '{id}' has no validated compensation yet: the NC keeps its own values"
            ),
        ));
    };
    let k = h.kinematics.clone().ok_or_else(|| {
        ApiError::new(
            ErrorCode::NoKinematics,
            format!("machine '{id}' has no kinematics in this service"),
        )
    })?;
    let etag = format!(
        "\"{id}-{}-v{}-{}\"",
        st.store.epoch(),
        set.version,
        format.name()
    );
    if headers
        .get(header::IF_NONE_MATCH)
        .and_then(|h| h.to_str().ok())
        .is_some_and(|h| h.split(',').any(|t| t.trim() == etag || t.trim() == "*"))
    {
        return Ok(with_etag(StatusCode::NOT_MODIFIED.into_response(), &etag));
    }
    let previous = st.store.compensation_before(id, set.version).await?;
    let o = nc_offsets(format, &k, &set, previous.as_ref(), &st.validation, &opts).map_err(
        |e| match e {
            OffsetsError::MissingNominal { .. } | OffsetsError::MissingPinNominal { .. } => {
                ApiError::new(ErrorCode::MissingNominal, e.to_string())
            }
            OffsetsError::BadOption(_) => bad(e.to_string()),
            e => ApiError::new(ErrorCode::OffsetsRefused, e.to_string()),
        },
    )?;
    let r = match &o.program {
        Some(program) => (
            [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
            program.clone(),
        )
            .into_response(),
        None => {
            let body = json_body(&set, &o);
            axum::Json(body).into_response()
        }
    };
    Ok(with_etag(r, &etag))
}

fn with_etag(mut r: Response, etag: &str) -> Response {
    if let Ok(h) = HeaderValue::from_str(etag) {
        r.headers_mut().insert(header::ETAG, h);
    }
    r
}
