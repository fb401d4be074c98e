//! Optimising C4G scenes from images: what improves a Gaussian set from its own frames (fitting,
//! camera refinement, distillation) builds on these, with the gradients of
//! `c4g_renderer::raster::grad`.
//!
//! - [`params`]: the optimiser's parametrisation of a scene (log scale, logit opacity, the stored
//!   quaternion) and its exact round trip to the canonical [`GaussianSet`](c4g_scene::GaussianSet);
//!   gradients in the same layout, and their clipping;
//! - [`adam`]: Adam with one learning rate per parameter group, its state saved and resumed;
//! - [`schedule`]: learning rates over steps (constant, exponential decay, warm-up) and 3DGS's
//!   defaults;
//! - [`loss`]: L1 and D-SSIM (1 − SSIM, the renderer's SSIM) of a render against a target, with
//!   their gradients with respect to the render;
//! - [`densify`]: 3DGS's adaptive density control (clone, split, prune) under a Gaussian budget;
//! - [`fit`]: the loop that puts these together for one image (what `examples/fit_image.rs`
//!   runs).

pub mod adam;
pub mod densify;
pub mod fit;
pub mod loss;
pub mod params;
pub mod schedule;

pub use adam::{Adam, AdamConfig};
pub use densify::{DensifyConfig, DensifyReport, DensifyStats};
pub use fit::{DensifySchedule, FitConfig, ImageFit, StepReport};
pub use params::{Group, Params};
pub use schedule::{LearningRate, LearningRates, Schedule, Warmup};
