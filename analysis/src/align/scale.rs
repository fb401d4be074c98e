//! Given cameras at the model's depth scale: the one factor on every camera's translation that
//! makes the model's own renders match the frames.
//!
//! C4G predicts no cameras and its depths are in units it chose (by its training convention the
//! first-to-last context camera distance is 1, which it must read from parallax); cameras given
//! with a clip come in the clip's own units, mapped to that convention by their own distances. A
//! model that misjudges its depth (c4g-tiny puts every scene at about the same depth, see
//! `models/c4g-tiny/README.md`) then draws each later context frame's Gaussians where its camera
//! does not see them. Scaling every camera's translation by `s` (camera centres about the first
//! camera, the model's frame) is the same as scaling the Gaussians' positions and sizes by 1/s,
//! which leaves the first camera's image as it is and changes only the parallax: so one number,
//! found from the context frames alone, puts the cameras at the model's scale.
//!
//! The search is on `log2 s`: every quarter octave in [`STEPS`] (the cost is not convex in `s`: a
//! wrong scale can line up a repeating texture), then a golden-section search between the best
//! step's neighbours ([`REFINEMENTS`] steps: a bracket of half an octave narrowed to about 0.002
//! octave). The cost is the mean squared RGB error of the renders over every view's pixels (the
//! background where nothing is drawn: a Gaussian moved off the frame costs what it uncovers). A
//! best factor that lowers the cost by less than [`EVIDENCE`] of factor 1's is no evidence: the
//! factor stays 1 (cameras that do not move fit every factor alike).
//!
//! The mirror of this search is `models/python/c4g/eval/generalisation.py`'s `fit_camera_scale`, which
//! scores it on two procedural worlds.

use glam::Affine3A;
use rayon::prelude::*;

use super::target::check_target;
use c4g_renderer::CpuRasterizer;
use c4g_renderer::raster::{Rasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, SceneError};

/// Quarter octaves of `log2 s` tried first: factors from 1/64 to 64.
pub const STEPS: std::ops::RangeInclusive<i32> = -24..=24;
/// Golden-section steps after the grid.
pub const REFINEMENTS: usize = 12;
/// Least fraction of factor 1's cost that the best factor must save to be taken.
pub const EVIDENCE: f64 = 1e-3;

/// One view of the fit: the set decoded at a frame's time, the frame (RGB, 3 floats a pixel,
/// row-major, at the camera's size, colours in 0..1) and the frame's given camera.
pub struct ScaleView<'a> {
    /// The model's Gaussians at the frame's time.
    pub set: &'a GaussianSet,
    /// The frame as the model saw it.
    pub target: &'a [f32],
    /// The frame's given camera, in the model's frame (the first context camera the identity).
    pub camera: Camera,
}

/// The outcome of [`fit_translation_scale`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScaleFit {
    /// The factor on every camera's translation.
    pub factor: f64,
    /// Mean squared RGB error at factor 1.
    pub initial_error: f64,
    /// The same at `factor`.
    pub error: f64,
    /// Renders of every view made, all factors together.
    pub evaluations: usize,
}

/// The translation factor that best matches `views`' renders to their frames.
///
/// Fails when a target is not its camera's size or not finite (`InvalidImage`) and on invalid
/// render options; views with no Gaussians render the background and count as such.
pub fn fit_translation_scale(
    views: &[ScaleView<'_>],
    options: &RenderOptions,
) -> Result<ScaleFit, SceneError> {
    options.validate()?;
    for view in views {
        check_target(view.target, &view.camera)?;
    }
    let rasterizer = CpuRasterizer::new();
    let options = RenderOptions {
        features: false,
        ..options.clone()
    };
    let cost = |log2: f64| -> Result<f64, SceneError> {
        let factor = log2.exp2() as f32;
        let (mut sum, mut count) = (0.0_f64, 0_usize);
        for view in views {
            let pose = view.camera.world_to_camera();
            let scaled = Affine3A::from_mat3_translation(
                pose.matrix3.into(),
                glam::Vec3::from(pose.translation) * factor,
            );
            let camera = Camera::new(*view.camera.intrinsics(), scaled)?;
            let image = rasterizer.render(view.set, &camera, &options)?;
            sum += image
                .rgb
                .iter()
                .zip(view.target)
                .map(|(&a, &b)| f64::from(a - b).powi(2))
                .sum::<f64>();
            count += image.rgb.len();
        }
        Ok(if count == 0 { 0.0 } else { sum / count as f64 })
    };

    // The grid's factors are independent: evaluated in parallel (a 64² render alone keeps few
    // of the pool's threads busy), each the same number whichever thread computes it.
    let mut tried: Vec<(f64, f64)> = STEPS
        .into_par_iter()
        .map(|k| {
            let log2 = f64::from(k) / 4.0;
            cost(log2).map(|c| (log2, c))
        })
        .collect::<Result<_, _>>()?;
    let best = |tried: &[(f64, f64)]| {
        tried
            .iter()
            .copied()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((0.0, 0.0))
    };
    let (centre, _) = best(&tried);
    let (first, last) = (
        f64::from(*STEPS.start()) / 4.0,
        f64::from(*STEPS.end()) / 4.0,
    );
    let (mut lo, mut hi) = ((centre - 0.25).max(first), (centre + 0.25).min(last));
    let golden = (5.0_f64.sqrt() - 1.0) / 2.0;
    let (mut a, mut b) = (hi - golden * (hi - lo), lo + golden * (hi - lo));
    let (mut fa, mut fb) = (cost(a)?, cost(b)?);
    tried.extend([(a, fa), (b, fb)]);
    for _ in 0..REFINEMENTS {
        if fa <= fb {
            (hi, b, fb) = (b, a, fa);
            a = hi - golden * (hi - lo);
            fa = cost(a)?;
            tried.push((a, fa));
        } else {
            (lo, a, fa) = (a, b, fb);
            b = lo + golden * (hi - lo);
            fb = cost(b)?;
            tried.push((b, fb));
        }
    }
    let initial_error = tried
        .iter()
        .find(|(log2, _)| *log2 == 0.0)
        .map_or(0.0, |t| t.1);
    let (log2, error) = best(&tried);
    let (factor, error) = if error >= initial_error * (1.0 - EVIDENCE) {
        (1.0, initial_error)
    } else {
        (log2.exp2(), error)
    };
    Ok(ScaleFit {
        factor,
        initial_error,
        error,
        evaluations: tried.len() * views.len(),
    })
}
