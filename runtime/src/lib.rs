//! ONNX Runtime for c4g's model crates.
//!
//! `c4g-engine` and `c4g-refiner` run ONNX graphs the same way: the library is loaded once per
//! process ([`init_runtime`], or `ORT_DYLIB_PATH` on first use), each graph is opened as a session
//! configured by [`SessionOptions`] and kept behind a lock as a [`Graph`], and each run's f32
//! outputs are checked against the shapes the caller expects ([`RunOutputs::f32`]). What can go
//! wrong on the way is a [`RuntimeError`]; [`ErrorKind`], who can fix an error, is the one both
//! model crates report.
//!
//! | module | holds |
//! |---|---|
//! | `environment` | loading the library once per process, the one environment every session shares |
//! | `session` | execution providers, session options, creating sessions |
//! | `graph` | one graph's session behind a mutex, and its runs |
//! | `output` | a run's named f32 outputs, checked against their expected shapes |
//! | `error` | the crate's error type, and the error kind of every model crate |

mod environment;
mod error;
mod graph;
mod output;
mod session;

pub use environment::{ORT_DYLIB_PATH, init_runtime, runtime_initialized};
pub use error::{ErrorKind, Result, RuntimeError};
pub use graph::Graph;
pub use output::RunOutputs;
pub use session::{ExecutionProvider, SessionOptions, create_session, session_builder};
