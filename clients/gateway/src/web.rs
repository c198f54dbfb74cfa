//! The phone page, compiled into the binary so the gateway needs no files at run time.

use crate::shared::Shared;
use axum::Router;
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::get;
use std::sync::Arc;

const INDEX_HTML: &str = include_str!("../../phone-web/index.html");
const APP_JS: &str = include_str!("../../phone-web/app.js");
const HEADSET_JS: &str = include_str!("../../phone-web/headset.js");
const VIDEO_JS: &str = include_str!("../../phone-web/video.js");
const STYLE_CSS: &str = include_str!("../../phone-web/style.css");

fn asset(content_type: &'static str, body: &'static str) -> impl IntoResponse {
    // no-store: after an upgrade of the gateway the phone must not keep running an old page.
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CACHE_CONTROL, "no-store"),
        ],
        body,
    )
}

/// `/`, `/app.js`, `/headset.js`, `/video.js`, `/style.css`.
pub(crate) fn routes() -> Router<Arc<Shared>> {
    Router::new()
        .route(
            "/",
            get(|| async { asset("text/html; charset=utf-8", INDEX_HTML) }),
        )
        .route(
            "/index.html",
            get(|| async { asset("text/html; charset=utf-8", INDEX_HTML) }),
        )
        .route(
            "/app.js",
            get(|| async { asset("text/javascript; charset=utf-8", APP_JS) }),
        )
        .route(
            "/headset.js",
            get(|| async { asset("text/javascript; charset=utf-8", HEADSET_JS) }),
        )
        .route(
            "/video.js",
            get(|| async { asset("text/javascript; charset=utf-8", VIDEO_JS) }),
        )
        .route(
            "/style.css",
            get(|| async { asset("text/css; charset=utf-8", STYLE_CSS) }),
        )
}
