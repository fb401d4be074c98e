//! Fitting a clip's 4D scene to its own frames (issue 38): the same N Gaussians at K keyframe
//! times, interpolated by the engine's keyframe rules, optimised on the renderer's gradients with
//! `c4g-optim`'s toolkit.
//!
//! - [`scene`]: [`FittedScene`], the keyframe sets and [`FittedScene::at`] (the engine's rules);
//! - [`keyframe_params`]: every keyframe set as one optimiser parameter block (Gaussian-major);
//! - [`backward`]: the gradient of `at(t)` with respect to the keyframe parameters;
//! - [`fit`](mod@fit): the loop ([`fit()`]): frames, holdout, loss, regularisers, Adam,
//!   densification, static Gaussians, the report and progress;
//! - [`error`]: the crate's one error, [`FitError`].
//!
//! `examples/fit_frames.rs` fits a folder of frames seen by a static camera from a grid start and
//! prints the held-out PSNR against time (`cargo run --release -p c4g-fit --example fit_frames`).
//! What is not here yet: the Fit job, serving fitted scenes through the service's set source,
//! their storage, and the CLI, viewer and Python client.

pub mod backward;
pub mod error;
pub mod fit;
pub mod keyframe_params;
pub mod scene;

pub use backward::{Blend, chain};
pub use error::FitError;
pub use fit::{Control, CurvePoint, FitOptions, FitReport, Frame, Progress, fit, holdout_frames};
pub use keyframe_params::KeyframeParams;
pub use scene::FittedScene;
