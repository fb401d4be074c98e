//! What rendering a C4G scene tells about it: which camera saw a frame ([`align`]), where a point
//! goes ([`tracking`]), what lifted features show ([`features`]) and which Gaussians a scene needs
//! ([`pruning`]). Each is computed by rendering scenes with `c4g-renderer` and reading the pixels.
//! Nothing here knows about models, ONNX or networks.

/// Camera recovery by photometric alignment: a render's analytic camera Jacobian and the
/// coarse-to-fine Levenberg–Marquardt that finds the camera matching a frame, with a confidence;
/// and given cameras' translations fitted to the model's depth scale.
pub mod align;
/// Feature fields in images: cosine similarity, selection, a fixed PCA colouring, matching.
pub mod features;
/// Model only what a scene requires: invisible, negligible and static Gaussians of a clip.
pub mod pruning;
/// Point tracks from Gaussian trajectories: a pixel's Gaussians carry its point to other times.
pub mod tracking;

pub use align::{AlignOptions, Alignment, align_camera};
