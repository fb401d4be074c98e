//! The c4g service's network edge: REST and gRPC on one port over the core (`c4g-service`),
//! which holds what every request means and knows no transport.
//!
//! | module | holds |
//! |---|---|
//! | `api` | the REST routes, one file per endpoint group; `/openapi.json`, `/docs` and the viewer (`/viewer`, files in `server/viewer/`) |
//! | `grpc` | the gRPC service `c4g.v1.C4G`, one file per endpoint group mirroring `api`; health and reflection, on the same port |
//! | `workers` | the gRPC service `c4g.v1.Jobs` that refinement workers pull from |
//! | `wire` | Gaussian sets as JSON and gRPC messages (the binary `C4GS` codec is `c4g-formats`') |
//! | `auth` | API-key checks |
//! | [`body_deadline`] | slow clients: a request body must arrive within `C4G_BODY_TIMEOUT_S` |
//! | [`metrics`] | the Prometheus recorder and per-request metrics |
//! | `error` | the one place where a `ServiceError` becomes an HTTP status and a gRPC code |
//! | [`AppState`] (`state`) | the server's state: the settings, the service once the model has loaded, draining |
//! | `fuzzing` | the fuzz targets' entry points (feature `fuzzing`): untrusted bytes in, bugs out |
//!
//! Handlers translate requests into calls on [`c4g_service::Service`] and its layers, and
//! translate the answers back.

mod api;
mod auth;
pub mod body_deadline;
mod error;
#[cfg(feature = "fuzzing")]
pub mod fuzzing;
mod grpc;
pub mod metrics;
mod state;
mod wire;
mod workers;

pub use api::router;
pub use state::AppState;
