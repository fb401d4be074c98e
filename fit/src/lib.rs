//! Fitting a clip's 4D scene to its own frames (issue 38): the same N Gaussians at K keyframe
//! times, interpolated by the engine's keyframe rules, optimised on the renderer's gradients with
//! `c4g-optim`'s toolkit.
//!
//! - [`scene`]: [`FittedScene`], the keyframe sets and [`FittedScene::at`] (the engine's rules);
//! - [`keyframe_params`]: every keyframe set as one optimiser parameter block (Gaussian-major);
//! - [`backward`]: the gradient of `at(t)` with respect to the keyframe parameters;
//! - [`fit`](mod@fit): the loop ([`fit()`]): frames, holdout, loss, regularisers, Adam,
//!   densification, static Gaussians, the report and progress;
//! - `still`: the pixels a still camera's frames never change, whose Gaussians are static;
//! - `cameras`: refining the training frames' cameras with the scene
//!   ([`FitOptions::refine_cameras`]);
//! - [`cover`]: [`cover_frame`], Gaussians for the part of the source frame outside the model's
//!   centre crop;
//! - [`preset`]: what a job asks ([`FitSettings`], the [`Preset`]s `fast`, `default`, `best`),
//!   where the keyframes go ([`keyframe_times`]) and the loop's options from the settings;
//! - [`file`](mod@file): a fitted scene as bytes for storage with its clip ([`to_bytes`], [`from_bytes`]);
//! - [`error`]: the crate's one error, [`FitError`].
//!
//! `examples/fit_frames.rs` fits a folder of frames seen by a static camera from a grid start and
//! prints the held-out PSNR against time (`cargo run --release -p c4g-fit --example fit_frames`).
//! `examples/fit_clip.rs` measures the presets on a real clip from the feed-forward start
//! (docs/tradeoffs.md, "Fitting a clip"). The Fit job, serving fitted scenes and their clients
//! live in the service and its edges.

pub mod backward;
mod cameras;
pub mod cover;
pub mod error;
pub mod file;
pub mod fit;
pub mod keyframe_params;
pub mod preset;
pub mod scene;
mod still;

pub use backward::{Blend, chain};
pub use cover::cover_frame;
pub use error::FitError;
pub use file::{from_bytes, to_bytes};
pub use fit::{Control, CurvePoint, FitOptions, FitReport, Frame, Progress, fit, holdout_frames};
pub use keyframe_params::KeyframeParams;
pub use preset::{FitSettings, Preset, keyframe_times, working_size};
pub use scene::FittedScene;
