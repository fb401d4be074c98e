//! The c4g service: the network edge over the engine.
//!
//! | module | holds |
//! |---|---|
//! | [`config`] | every setting, as a CLI flag with a `C4G_*` environment variable |
//! | `state` | what handlers share: the loaded model |
//! | `api` | one file per endpoint group: `health` (`/health`, `/ready`), `models` (`/v1/models`) |
//! | `error` | the one place where errors become HTTP statuses and JSON bodies |
//!
//! Handlers translate HTTP into calls on [`c4g_engine`]; what a request means lives there.

mod api;
pub mod config;
mod error;
mod state;

pub use api::router;
pub use error::ApiError;
pub use state::AppState;
