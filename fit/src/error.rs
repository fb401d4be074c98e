//! The one error of the fit crate: what a fit refuses, and the scene, engine and renderer errors it
//! passes on.

use c4g_engine::EngineError;
use c4g_scene::SceneError;

/// Why a fit (or a fitted scene) failed.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// Inputs that do not describe a fit (no keyframes, mismatched sets, bad options, frames
    /// outside the keyframes' span).
    #[error("invalid fit input: {0}")]
    Invalid(String),
    /// From the scene vocabulary, the renderer or the optimiser.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// From the engine's keyframe track.
    #[error(transparent)]
    Engine(#[from] EngineError),
}
