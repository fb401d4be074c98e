//! The c4g client: a Rust library for the c4g inference service, and (in `main.rs`) the `c4g`
//! command-line tool built on it.
//!
//! One [`Client`] speaks both of the server's protocols on its one port: REST under `/v1` for
//! requests that answer once (upload, describe, decode, render, fit and refinement jobs; a job's
//! progress as server-sent events) and gRPC (`c4g.v1.C4G`, h2c) for [`Client::stream`], where a
//! server-streaming call carries many Gaussian sets with the transport's flow control.
//! `docs/api.md` is the contract both sides are written against.
//!
//! | module | what |
//! |---|---|
//! | [`client`] | [`Client`]: base URL, API key, the REST plumbing and how error answers are read |
//! | [`error`] | [`Error`]: every failure, with the server's status, `kind` and message kept |
//! | [`model`] | [`Model`]: the served package (`GET /v1/models`) |
//! | [`clips`] | [`Clip`]: describe, list and delete clips |
//! | [`upload`] | [`Client::upload`]: videos, archives and image directories, streamed with progress |
//! | [`gaussians`] | [`Client::gaussians`] (parsed) and [`Client::gaussians_raw`] (JSON, binary, PLY, .splat) |
//! | [`keyframes`] | [`Keyframes`]: exact sets at keyframes, interpolated between them, for decodes, streams and trajectories |
//! | [`quality`] | [`Approximation`]: a [`Quality`] preset, keyframes, [`Prune`] and the [`Scene`] (feed-forward or fitted), for decodes, streams and renders |
//! | [`wire`] | parsers of the packed Gaussian payloads: the `C4GS` binary format and the proto's arrays |
//! | [`export`] | [`Client::export`]: a time range as one file other viewers open (a zip of `.ply` or `.spz` files, a fitted `.splatv`) |
//! | [`render`] | [`RenderRequest`] and [`Client::render`]: images, depth, alpha and trajectory videos |
//! | [`cameras`] | [`Client::recover_cameras`]: each context frame's camera recovered by photometric alignment |
//! | [`tracks`] | [`Client::tracks`]: where points seen in the input frames go at other times, by their Gaussians or by feature matching |
//! | [`segment`] | [`Client::segment`]: the Gaussians whose lifted feature is like a clicked pixel's, and their masks |
//! | [`stream`] | [`Client::stream`]: Gaussian sets over a time range, over gRPC |
//! | [`jobs`] | [`RefineRequest`], [`Client::refine`] and [`Job`]: refinement jobs, and every job followed as server-sent events |
//! | [`fit`] | [`FitRequest`] and [`Client::fit`]: a clip's scene fitted to its own frames; [`FittedSummary`], the clip's record of it |
//! | [`sse`] | [`SseDecoder`]: the `text/event-stream` format, chunk by chunk |
//!
//! Gaussian sets arrive as [`c4g_scene::GaussianSet`], so they write straight to `.ply` or
//! `.splat` with [`c4g_formats`] and render with the renderer's rasterizers.

pub mod cameras;
pub mod client;
pub mod clips;
pub mod error;
pub mod export;
pub mod fit;
pub mod gaussians;
pub mod jobs;
pub mod keyframes;
pub mod model;
pub mod quality;
pub mod render;
pub mod segment;
pub mod sse;
pub mod stream;
pub mod tracks;
pub mod upload;
pub mod wire;

pub use c4g_scene::GaussianSet;
pub use cameras::{FrameFit, RecoveredCameras};
pub use client::Client;
pub use clips::{Clip, ClipSource};
pub use error::Error;
pub use export::{Export, ExportFormat, ExportOptions};
pub use fit::{FitPreset, FitRequest, FittedSummary};
pub use gaussians::{GaussianFormat, GaussianFrame, Precision};
pub use jobs::{Job, JobEvents, JobProgress, RefineRequest, Sampler, job_event_stream};
pub use keyframes::Keyframes;
pub use model::{InputSize, Model};
pub use quality::{Approximation, Prune, Quality, Scene};
pub use render::{
    CameraSpec, IntrinsicsSpec, RenderFormat, RenderRequest, Rendered, TrajectoryPreset,
};
pub use segment::{Mask, Segment, SegmentRequest, Selection};
pub use sse::{SseDecoder, SseEvent};
pub use stream::{Compact, GaussianStream, Spacing, StreamOptions};
pub use tracks::{Track, TrackPoint, TrackQuery, TrackRequest, Tracker, Tracks};
pub use upload::{UploadCameras, UploadOptions, UploadSource, content_type_for};
