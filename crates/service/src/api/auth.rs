//! Bearer tokens with roles, and what an anonymous reader may see.

use axum::extract::{Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::Response;
use serde_json::json;

use super::{ApiError, ErrorCode, Shared};
use crate::config::Role;

/// Who made a request (after authentication).
#[derive(Clone, Debug)]
pub struct Caller {
    pub name: String,
    pub role: Option<Role>,
}

/// What an anonymous reader sees of token holders: not their names (who acknowledged an
/// alert, who asked for a diagnosis). Authenticated readers see everything.
pub(super) fn for_caller(mut v: serde_json::Value, caller: &Caller) -> serde_json::Value {
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
pub(super) fn same(a: &[u8], b: &[u8]) -> bool {
    let mut diff = a.len() ^ b.len();
    for i in 0..a.len().max(b.len()) {
        diff |= usize::from(a.get(i).copied().unwrap_or(0) ^ b.get(i).copied().unwrap_or(0));
    }
    diff == 0
}

pub(super) async fn authenticate(
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
                        ErrorCode::BadToken,
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
                ErrorCode::TokenRequired,
                format!("this endpoint needs a bearer token with role {needed:?}").to_lowercase(),
            ));
        }
        Some(r) if !r.allows(needed) => {
            return Err(ApiError::new(
                ErrorCode::Role,
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
