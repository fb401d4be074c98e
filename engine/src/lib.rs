//! The C4G engine: model packages on ONNX Runtime.
//!
//! A clip's context frames are preprocessed ([`preprocess`]), encoded once ([`Engine::encode`]
//! → [`Encoding`]), and decoded at any target time inside their span ([`Engine::decode`] →
//! [`GaussianSet`](c4g_scene::GaussianSet)), with timestamps normalised by a [`TimePolicy`].
//! A package with a feature decoder also lifts 2D feature maps onto the Gaussians
//! ([`Engine::decode_features`]). Many times decode cheaper through [`keyframes`]: exact sets at a
//! few keyframes, interpolated per Gaussian in between ([`Engine::decode_keyframed`]). A package
//! in the precomputed decoder form ([`package::DecoderForm`]) also projects the features once per
//! encoding, which every decode of it reuses. A package whose decoder takes query indices also
//! decodes a [`QuerySubset`] of its queries alone ([`Engine::decode_subset`]), dropping the
//! others' tokens from the decoder: cheaper, and an approximation.
//!
//! | module | holds |
//! |---|---|
//! | [`package`] | `model.json` and the package contract |
//! | [`preprocess`] | centre crop, Lanczos resize, value mapping |
//! | [`time`] | the TimePolicy |
//! | `options` | engine options: the sessions' ([`SessionOptions`]), the time policy, batching |
//! | `encoding` | context frames in, encodings out |
//! | `engine` | encode and decode |
//! | [`keyframes`] | keyframed decoding: where keyframes go, and the interpolation between them |
//! | `query_subset` | which queries a decode runs: all, or a checked subset |
//! | `resident` | device-resident encodings: a clip's decoder inputs kept in the execution provider's memory, bound by every decode |
//! | `graph` | each ONNX graph's inputs and outputs, checked at load |
//! | `error` | the crate's error type |
//!
//! ONNX Runtime itself (loading it once per process, sessions, locked runs, checked outputs, the
//! [`ErrorKind`] this crate shares with `c4g-refiner`) is `c4g-runtime`'s; its names used here
//! are re-exported.

mod encoding;
mod engine;
mod error;
mod graph;
pub mod keyframes;
mod options;
pub mod package;
pub mod preprocess;
mod query_subset;
mod resident;
pub mod time;

pub use c4g_runtime::{
    ErrorKind, ExecutionProvider, ORT_DYLIB_PATH, RuntimeError, SessionOptions, init_runtime,
    runtime_initialized,
};
pub use encoding::{ContextFrame, Encoding};
pub use engine::Engine;
pub use error::{EngineError, Result};
pub use keyframes::{KeyframeStats, KeyframeTrack, Keyframes};
pub use options::{DEFAULT_RESIDENT_BUDGET, EngineOptions};
pub use package::{Manifest, Package};
pub use query_subset::QuerySubset;
pub use resident::ResidentStats;
pub use time::{NormalizedTimes, TimePolicy};
