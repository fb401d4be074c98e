//! One graph's session behind a mutex, and its runs.
//!
//! ONNX Runtime's sessions run through `&mut` in `ort` 2.0, so a model that is shared between
//! threads keeps each session behind a mutex: the model is `Send + Sync` and runs of one graph are
//! serialised (ONNX Runtime already uses every core inside one run; more throughput means more
//! models or a GPU). A run's outputs borrow the session, so [`Graph::run`] hands them to a closure
//! while it still holds the lock; the closure copies out what it needs.

use std::sync::{Mutex, PoisonError};

use ort::session::{Session, SessionInputs};

use crate::output::RunOutputs;
use crate::{Result, RuntimeError};

/// A named graph's session, run by one caller at a time.
pub struct Graph {
    name: String,
    session: Mutex<Session>,
}

impl std::fmt::Debug for Graph {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Graph")
            .field("name", &self.name)
            .finish_non_exhaustive()
    }
}

impl Graph {
    /// `session` under `name`, the graph's name in error messages ("encoder", "VAE decoder").
    pub fn new(name: impl Into<String>, session: Session) -> Self {
        Self {
            name: name.into(),
            session: Mutex::new(session),
        }
    }

    /// The graph's name in error messages.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Runs the graph on `inputs` and hands its outputs to `read`, under the lock.
    ///
    /// A failed run is [`RuntimeError::Ort`] with the context "running the {name}". A panic while
    /// a run held the lock leaves the session itself intact, so a poisoned lock is taken over
    /// rather than failing every later run.
    pub fn run<'i, 'v: 'i, const N: usize, T>(
        &self,
        inputs: impl Into<SessionInputs<'i, 'v, N>>,
        read: impl FnOnce(&RunOutputs<'_, '_>) -> Result<T>,
    ) -> Result<T> {
        let mut session = self.session.lock().unwrap_or_else(PoisonError::into_inner);
        let outputs = session
            .run(inputs)
            .map_err(RuntimeError::ort(format!("running the {}", self.name)))?;
        read(&RunOutputs::new(&self.name, &outputs))
    }
}
