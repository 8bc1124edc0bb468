//! The API's one error type: a stable code (an enum, so that the OpenAPI document lists every
//! code), the HTTP status it answers with, and a message for people.

use axum::Json;
use axum::extract::Request;
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use serde::Serialize;

/// What went wrong, as a client may test for it. Each code has its status
/// ([`ErrorCode::status`]); the framework's own refusals keep theirs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// A path or query parameter that does not parse (the framework's words).
    BadRequest,
    /// A query parameter that parses but is not valid.
    BadQuery,
    /// A body that is JSON but not the request's shape.
    BadBody,
    BodyTooLarge,
    UnsupportedMediaType,
    MethodNotAllowed,
    NotFound,
    /// No bearer token where one is needed.
    TokenRequired,
    /// A bearer token that is not known.
    BadToken,
    /// The token's role may not do this.
    Role,
    UnknownMachine,
    /// The machine is run by another process of the fleet (or by none just now).
    RunElsewhere,
    UnknownCycle,
    UnknownDiagnosis,
    UnknownAlert,
    NoCompensation,
    /// A compensation format that is not one of json, fanuc, siemens, heidenhain, linuxcnc.
    BadFormat,
    /// The served set may not be put in the NC's form (a step beyond the limit, a set that
    /// does not look validated, a machine chain without that form).
    OffsetsRefused,
    /// FANUC's parameters and LinuxCNC's kinematics pins are absolute: the commissioned value
    /// of each one written must be given (a constraint between `format` and `fanuc_nominal` or
    /// `linuxcnc_nominal` that OpenAPI cannot state).
    MissingNominal,
    NoModel,
    BeforeLastInput,
    BadWindow,
    BadEvery,
    BadSource,
    BadSigma,
    NoKinematics,
    NoDetections,
    DiagnosisBusy,
    DiagnosisFailed,
    DiagnosisPanicked,
    NotNcPush,
    /// A reference result that cannot be taken (the message names the field).
    BadReference,
    /// A linear-axis geometry that cannot be taken (the message names the field).
    BadGeometry,
    /// No accepted tool-setter result near enough in time to a reference.
    NoSetterResult,
    BadEvent,
    ClockSkew,
    /// Too many NC events wait for the loop.
    Busy,
    /// The request was not answered within `http.request_timeout_s`.
    Timeout,
    /// The database could not answer.
    Storage,
    /// Any other failure the framework answered.
    Error,
}

impl ErrorCode {
    /// The status this code answers with.
    pub fn status(self) -> StatusCode {
        use ErrorCode::*;
        match self {
            BadRequest | BadQuery | BadFormat | MissingNominal | BeforeLastInput | BadWindow
            | BadEvery | BadSource | BadSigma | BadEvent | ClockSkew | BadReference
            | BadGeometry => StatusCode::BAD_REQUEST,
            BadBody | NoDetections | DiagnosisFailed | NoSetterResult => {
                StatusCode::UNPROCESSABLE_ENTITY
            }
            BodyTooLarge => StatusCode::PAYLOAD_TOO_LARGE,
            UnsupportedMediaType => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            NotFound | UnknownMachine | UnknownCycle | UnknownDiagnosis | UnknownAlert
            | NoCompensation | NoModel => StatusCode::NOT_FOUND,
            TokenRequired | BadToken => StatusCode::UNAUTHORIZED,
            Role => StatusCode::FORBIDDEN,
            NoKinematics | NotNcPush | OffsetsRefused | RunElsewhere => StatusCode::CONFLICT,
            DiagnosisBusy => StatusCode::TOO_MANY_REQUESTS,
            Busy | Timeout => StatusCode::SERVICE_UNAVAILABLE,
            DiagnosisPanicked | Storage | Error => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }
}

/// The body of every error answer.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct ErrorBody {
    pub code: ErrorCode,
    pub message: String,
}

/// An error as the API answers it: a code, its status and a message for people.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    body: ErrorBody,
}

impl ApiError {
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        ApiError {
            status: code.status(),
            body: ErrorBody {
                code,
                message: message.into(),
            },
        }
    }

    /// A refusal the framework decided, with the framework's status (a body rejected as too
    /// large or of the wrong shape).
    pub fn with_status(status: StatusCode, code: ErrorCode, message: impl Into<String>) -> Self {
        ApiError {
            status,
            body: ErrorBody {
                code,
                message: message.into(),
            },
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut r = (self.status, Json(self.body)).into_response();
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
        ApiError::new(ErrorCode::Storage, "the database could not answer")
    }
}

/// Every error answer is the API's JSON error, also those the framework writes itself (a path
/// or query parameter that does not parse, a body too large or of the wrong type, a method
/// not allowed): their text becomes the message, the status gives the code.
pub(super) async fn json_errors(req: Request, next: Next) -> Response {
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
        StatusCode::BAD_REQUEST => ErrorCode::BadRequest,
        StatusCode::NOT_FOUND => ErrorCode::NotFound,
        StatusCode::METHOD_NOT_ALLOWED => ErrorCode::MethodNotAllowed,
        StatusCode::PAYLOAD_TOO_LARGE => ErrorCode::BodyTooLarge,
        StatusCode::UNSUPPORTED_MEDIA_TYPE => ErrorCode::UnsupportedMediaType,
        StatusCode::UNPROCESSABLE_ENTITY => ErrorCode::BadBody,
        // The only 503 without a JSON body: the timeout layer's.
        StatusCode::SERVICE_UNAVAILABLE => ErrorCode::Timeout,
        _ => ErrorCode::Error,
    };
    let message = if text.is_empty() {
        status.canonical_reason().unwrap_or("error").to_string()
    } else {
        text
    };
    let mut out = ApiError::with_status(status, code, message).into_response();
    // Keep what the framework said besides the body (Allow on a 405, for one).
    for (k, v) in parts.headers.iter() {
        if k != header::CONTENT_TYPE && k != header::CONTENT_LENGTH {
            out.headers_mut().insert(k.clone(), v.clone());
        }
    }
    out
}
