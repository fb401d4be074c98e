//! What a c4g request means, whatever the transport: the server's core. `c4g-server` (the edge)
//! turns REST and gRPC requests into calls here and answers back; nothing here knows about axum,
//! tonic, hyper or tower, so every behaviour is testable in-process, without a port.
//!
//! The core is in layers; a layer uses those below it and never one above:
//!
//! | layer | holds |
//! |---|---|
//! | [`service`] | [`Service`]: the loaded model and the layers below, and what spans them (upload, delete) |
//! | [`jobs`] | refinement jobs: durable records, the queue, worker leases (on disk or in PostgreSQL); what a refinement asks for and the video a worker gets |
//! | [`views`] | what is seen of a clip's sets: renders and camera paths, image formats, exports, feature images and segments, point tracks, recovered cameras and the scale fit of given cameras |
//! | [`sets`] | [`SetSource`](sets::SetSource): the Gaussian sets of a clip at any times, under any options (exact decodes batched across requests, keyframes, quality presets, pruning, stream plans) |
//! | [`clips`] | what was uploaded: intake (FFmpeg, archives, given cameras), the clip store, clips shared by replicas, crash-safe writes |
//! | base | [`config`] (every setting and limit), [`ServiceError`] (`error.rs`), [`work`] (work slots), [`faults`] (fault points for crash tests) |

pub mod clips;
pub mod config;
/// [`ServiceError`]: what went wrong, in domain words, and its kinds.
mod error;
pub mod faults;
pub mod jobs;
pub mod service;
pub mod sets;
pub mod views;
pub mod work;

pub use error::{QUOTED_CHARS, ServiceError, ServiceErrorKind, quoted};
pub use service::Service;
