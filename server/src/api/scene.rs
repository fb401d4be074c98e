//! Which scene answered: REST's side of `c4g_service::sets::scene`. A request's `"scene"` is
//! resolved once, before any work (`SetSource::resolve_scene`, so `auto` cannot change its mind
//! half way), and the answer carries `X-C4G-Scene: feed-forward | fitted`.

use axum::http::{HeaderName, HeaderValue};
use axum::response::Response;
use c4g_service::sets::scene::Scene;

/// The header that names the scene that served an answer.
pub const HEADER: HeaderName = HeaderName::from_static("x-c4g-scene");

/// `response` labelled with the scene that served it.
pub fn label(mut response: Response, scene: Scene) -> Response {
    response
        .headers_mut()
        .insert(HEADER, HeaderValue::from_static(scene.name()));
    response
}
