//! The c4g service: the network edge over the engine and the renderer.
//!
//! | module | holds |
//! |---|---|
//! | [`config`] | every setting, as a CLI flag with a `C4G_*` environment variable, and the limits |
//! | [`intake`] | untrusted uploads (videos via FFmpeg, image archives) to timed context frames |
//! | [`store`] | the clip store: content-addressed clips on disk, features in an LRU cache |
//! | `shared_clips` | clips shared by replicas through object storage (`C4G_SHARED_STORE`): publish, fetch, one encode cluster-wide |
//! | [`service`] | upload, decode, render: what both transports call |
//! | `work` | work slots: decodes and renders on blocking threads, bounded, queued, cancellable |
//! | `batching` | exact decodes of one clip from concurrent requests gathered into shared decoder runs |
//! | [`jobs`] | refinement jobs: durable records, the queue, worker leases; on disk or in PostgreSQL |
//! | `refine` | refinement requests, and the video a worker gets |
//! | `camera` | cameras as clients state them, or the input camera at a time |
//! | `keyframes` | keyframed decoding as clients ask for it, checked against the limits |
//! | `quality` | the speed/accuracy presets (exact, balanced, fast) and pruning as clients ask for it |
//! | `pruning` | which Gaussians a pruned request keeps: each clip's scene analysis, cached |
//! | `streaming` | streams of sets over a time range, planned once, decoded ahead of the reader |
//! | `camera_scale` | given cameras fitted to the model's depth scale at upload |
//! | `recovery` | recovered cameras: each context frame's camera by photometric alignment of the model's Gaussians |
//! | `tracking` | point tracks: query points followed through a clip by the Gaussians that explain them, or by matching their lifted features |
//! | `features` | the 4D feature field: decodes with lifted features, feature images (raw, and a per-clip PCA colouring), segments |
//! | `exports` | 4D exports: a time range as a zip of `.ply` or `.spz` files, or a fitted `.splatv` |
//! | `renderer` | the rasterizer choice |
//! | `image_formats` | what renders answer with: PNG, raw depth and alpha, MP4 |
//! | `service_error` | [`ServiceError`]: what went wrong, in domain words, and its kinds |
//! | [`faults`] | fault points where tests stop the server to kill it (off unless named) |
//! | `fuzzing` | the fuzz targets' entry points (feature `fuzzing`): untrusted bytes in, bugs out |
//! | *the edge* | |
//! | `api` | the REST routes, one file per endpoint group; `/openapi.json`, `/docs` and the viewer (`/viewer`, files in `server/viewer/`) |
//! | `grpc` | the gRPC service `c4g.v1.C4G`, health and reflection, on the same port |
//! | `workers` | the gRPC service `c4g.v1.Jobs` that refinement workers pull from |
//! | `wire` | Gaussian sets as JSON and gRPC messages (the binary `C4GS` codec is the renderer's) |
//! | `auth` | API-key checks |
//! | [`body_deadline`] | slow clients: a request body must arrive within `C4G_BODY_TIMEOUT_S` |
//! | `metrics` | the Prometheus recorder and per-request metrics |
//! | `error` | the one place where a [`ServiceError`] becomes an HTTP status and a gRPC code |
//!
//! Handlers translate requests into calls on [`service::Service`]; what a request means lives
//! there and in [`c4g_engine`]. The core (everything above the edge) returns [`ServiceError`] and
//! imports neither axum nor tonic.

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
