//! The dashboard at `/`: a page, a script and a style sheet, embedded in the binary and served
//! as they are (no build step, nothing fetched from elsewhere). The browser draws everything
//! from the public JSON API, with the API's own authentication; this module only serves the
//! files, so `/` and `/assets/...` need no token and are not in the OpenAPI document.

use axum::Router;
use axum::extract::Path;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;

use super::{ApiError, ErrorCode};

/// (name under `/assets/`, content type, body)
const ASSETS: &[(&str, &str, &str)] = &[
    (
        "app.js",
        "text/javascript; charset=utf-8",
        include_str!("dashboard/app.js"),
    ),
    (
        "style.css",
        "text/css; charset=utf-8",
        include_str!("dashboard/style.css"),
    ),
];

const INDEX: &str = include_str!("dashboard/index.html");

/// Only this origin's scripts, styles and API: the page works offline and nothing injected
/// into it runs.
const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; img-src 'self' data:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// A strong validator of a body: FNV-1a, 64 bits (the files change only with the binary).
fn etag(body: &str) -> String {
    use std::hash::Hasher;
    let mut h = fnv::FnvHasher::default();
    h.write(body.as_bytes());
    format!("\"{:016x}\"", h.finish())
}

/// The body with its type; `no-cache` with an ETag, so a browser asks again each time and
/// gets 304 until a new binary serves new files.
fn file(headers: &HeaderMap, content_type: &'static str, body: &'static str) -> Response {
    let tag = etag(body);
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|h| h.to_str().ok())
        .is_some_and(|h| h.split(',').any(|t| t.trim() == tag));
    let mut r = if fresh {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, content_type)], body).into_response()
    };
    let h = r.headers_mut();
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    if let Ok(v) = HeaderValue::from_str(&tag) {
        h.insert(header::ETAG, v);
    }
    r
}

async fn index(headers: HeaderMap) -> Response {
    let mut r = file(&headers, "text/html; charset=utf-8", INDEX);
    r.headers_mut().insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    r
}

async fn asset(Path(name): Path<String>, headers: HeaderMap) -> Response {
    match ASSETS.iter().find(|(n, _, _)| *n == name) {
        Some((_, content_type, body)) => file(&headers, content_type, body),
        None => ApiError::new(ErrorCode::NotFound, format!("no asset '{name}'")).into_response(),
    }
}

/// `/` and `/assets/{name}`, without authentication.
pub(super) fn routes<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new()
        .route("/", get(index))
        .route("/assets/{name}", get(asset))
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::body::Body;
    use axum::http::Request;
    use tower::ServiceExt;

    async fn get(uri: &str, if_none_match: Option<&str>) -> Response {
        let mut b = Request::get(uri);
        if let Some(t) = if_none_match {
            b = b.header(header::IF_NONE_MATCH, t);
        }
        routes::<()>()
            .oneshot(b.body(Body::empty()).unwrap())
            .await
            .unwrap()
    }

    #[tokio::test]
    async fn the_page_and_its_assets_have_their_types_and_revalidate() {
        for (uri, ty) in [
            ("/", "text/html; charset=utf-8"),
            ("/assets/app.js", "text/javascript; charset=utf-8"),
            ("/assets/style.css", "text/css; charset=utf-8"),
        ] {
            let r = get(uri, None).await;
            assert_eq!(r.status(), StatusCode::OK, "{uri}");
            assert_eq!(r.headers()[header::CONTENT_TYPE], ty, "{uri}");
            assert_eq!(r.headers()[header::CACHE_CONTROL], "no-cache", "{uri}");
            let tag = r.headers()[header::ETAG].to_str().unwrap().to_string();
            let again = get(uri, Some(&tag)).await;
            assert_eq!(again.status(), StatusCode::NOT_MODIFIED, "{uri}");
        }
        assert!(
            get("/", None)
                .await
                .headers()
                .contains_key(header::CONTENT_SECURITY_POLICY)
        );
        assert_eq!(
            get("/assets/nope.js", None).await.status(),
            StatusCode::NOT_FOUND
        );
    }

    #[test]
    fn the_page_loads_only_its_own_assets() {
        for (name, _, _) in ASSETS {
            assert!(INDEX.contains(&format!("/assets/{name}")), "{name}");
        }
        // Nothing from another host (the SVG namespace is a name, not a fetch).
        for text in std::iter::once(INDEX).chain(ASSETS.iter().map(|a| a.2)) {
            let text = text.replace("http://www.w3.org/2000/svg", "");
            assert!(!text.contains("http://") && !text.contains("https://"));
        }
    }
}
