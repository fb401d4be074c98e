//! The C4G engine: model packages on ONNX Runtime.
//!
//! A clip's context frames are preprocessed ([`preprocess`]), encoded once ([`Engine::encode`]
//! → [`Encoding`]), and decoded at any target time inside their span ([`Engine::decode`] →
//! [`GaussianSet`](c4g_renderer::GaussianSet)), with timestamps normalised by a [`TimePolicy`].
//! A package with a feature decoder also lifts 2D feature maps onto the Gaussians
//! ([`Engine::decode_features`]).
//!
//! | module | holds |
//! |---|---|
//! | [`package`] | `model.json` and the package contract |
//! | [`preprocess`] | centre crop, Lanczos resize, value mapping |
//! | [`time`] | the TimePolicy |
//! | `runtime` | loading ONNX Runtime, engine options, sessions |
//! | `encoding` | context frames in, encodings out |
//! | `engine` | encode and decode |
//! | `graph` | each ONNX graph's inputs and outputs, checked at load |
//! | `error` | the crate's error type |

mod encoding;
mod engine;
mod error;
mod graph;
pub mod package;
pub mod preprocess;
mod runtime;
pub mod time;

pub use encoding::{ContextFrame, Encoding};
pub use engine::Engine;
pub use error::{EngineError, ErrorKind, Result};
pub use package::{Manifest, Package};
pub use runtime::{
    EngineOptions, ExecutionProvider, ORT_DYLIB_PATH, init_runtime, runtime_initialized,
};
pub use time::{NormalizedTimes, TimePolicy};
