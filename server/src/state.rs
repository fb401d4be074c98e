//! What every handler shares. The engine loads in the background, so `/health` answers at once
//! and `/ready` tells when the model can serve.

use std::sync::{Arc, OnceLock};

use c4g_engine::Engine;

/// Shared, cheaply cloned state of the service.
#[derive(Clone, Default)]
pub struct AppState {
    engine: Arc<OnceLock<Engine>>,
}

impl AppState {
    /// State with no model loaded yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Installs the loaded engine; later calls are ignored.
    pub fn set_engine(&self, engine: Engine) {
        let _ = self.engine.set(engine);
    }

    /// The engine, once it has loaded.
    pub fn engine(&self) -> Option<&Engine> {
        self.engine.get()
    }
}
