//! The c4g service: the network edge over the engine and the renderer.
//!
//! | module | holds |
//! |---|---|
//! | [`config`] | every setting, as a CLI flag with a `C4G_*` environment variable, and the limits |
//! | [`intake`] | untrusted uploads (videos via FFmpeg, image archives) to timed context frames |
//! | [`store`] | the clip store: content-addressed clips on disk, features in an LRU cache |
//! | [`service`] | upload, decode, render: what both transports call |
//! | [`jobs`] | refinement jobs: durable records, the queue, worker leases |
//! | `refine` | refinement requests, and the video a worker gets |
//! | `workers` | the gRPC service `c4g.v1.Jobs` that refinement workers pull from |
//! | `render` | cameras as clients state them, the rasterizer choice, PNG and MP4 encoding |
//! | `wire` | Gaussian sets as JSON, packed binary and gRPC messages |
//! | `api` | the REST routes, one file per endpoint group; `/openapi.json` and `/docs` |
//! | `grpc` | the gRPC service `c4g.v1.C4G`, health and reflection, on the same port |
//! | `auth` | API-key checks |
//! | `metrics` | the Prometheus recorder and per-request metrics |
//! | `error` | the one place where errors become HTTP and gRPC statuses |
//!
//! Handlers translate requests into calls on [`service::Service`]; what a request means lives
//! there and in [`c4g_engine`].

mod api;
mod auth;
pub mod config;
mod error;
mod grpc;
pub mod intake;
pub mod jobs;
pub mod metrics;
mod refine;
mod render;
pub mod service;
mod state;
pub mod store;
mod wire;
mod workers;

pub use api::router;
pub use error::ApiError;
pub use state::AppState;
