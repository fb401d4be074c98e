//! The HTTP routes, one file per endpoint group.

mod health;
mod models;

use axum::Router;
use axum::routing::get;

use crate::AppState;

/// Every route of the service.
pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/health", get(health::health))
        .route("/ready", get(health::ready))
        .route("/v1/models", get(models::list))
        .with_state(state)
}
