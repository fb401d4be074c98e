//! Camera recovery by photometric alignment: given a Gaussian set (the model's own, decoded at a
//! context frame's time), the frame, and a camera to start from (the previous frame's), find the
//! camera whose render of the set matches the frame, with a confidence in the answer. And for
//! cameras that are given, not recovered: the one factor on their translations that puts them at
//! the model's depth scale ([`fit_translation_scale`], `scale.rs`).
//!
//! [`align_camera`] is Levenberg–Marquardt on 6 numbers (a left-multiplied se(3) change of
//! world-to-camera), or 7 with a shared focal scale, over a coarse-to-fine pyramid of the frame
//! (`pyramid.rs`), minimising an alpha-weighted Huber loss of the RGB residual (`normal.rs`).
//! The per-pixel Jacobian of the render with respect to those parameters comes analytically
//! from [`camera_jacobian`](crate::align::camera_jacobian) (`jacobian.rs`, `splat.rs`):
//! forward-mode derivatives of the CPU rasterizer's forward model, checked against finite
//! differences in the tests.
//!
//! Why Gauss–Newton and not Adam (what the public C4G code runs: lr 0.005 on a 3 + 3 delta, up to
//! 1,000 steps, stopping after 10 without improvement): with 6 or 7 unknowns the normal matrix
//! `JᵀJ` is tiny and exact second-order steps converge in a handful of iterations where a
//! first-order method with a fixed learning rate needs hundreds and a scale per parameter; the
//! matrix is also what the confidence reads the view's degeneracy from. Levenberg's damping
//! (Marquardt's, on `diag(JᵀJ)`, which makes the step independent of the parameters' units)
//! keeps a step that would leave the linearisation's reach from being taken.
//!
//! Each level starts from the adjustment the coarser one reached, unless this level's own cost
//! says the coarser level made things worse than where it started (a coarse render is not the
//! box-filtered fine one: the 0.3 px² dilation is in coarse pixels there, so a coarse level's
//! minimum can lie beside the true camera; its answer is then dropped). A level runs until an
//! accepted step lowers its cost by less than [`AlignOptions::tolerance`] (relatively), its
//! residual is below an RMS of 1e-4, no damped step lowers it at all, or
//! [`AlignOptions::max_iterations`] steps have been tried.
//!
//! Its reach, measured (`tests/timing.rs`, random-colour scenes, the defaults): from 3° and 5% of
//! the depth every start is recovered at 64² and 224²; from 6° and 10%, 7 in 8 at 64² and 2 in 8
//! at 224²; from 10° and 15%, few. A start as far as the previous frame's camera usually is
//! converges; a farther one can stop in a local minimum, with a confidence that says so (about
//! 0.25 where the recovered ones score 0.95).
//!
//! What is not modelled: lens distortion (a pinhole, as the renderer is); the principal point
//! (fixed; only a focal scale shared by fx and fy is refined, as C4G's cameras have fx = fy in
//! normalised units); a moving scene (the set is the one decoded at the frame's time); the
//! depth order's and the footprints' jumps as the camera moves (the render is piecewise smooth,
//! and the Jacobian that of the current piece); anything the set does not explain (the Huber loss
//! and the alpha weights bound its pull, nothing removes it).

mod adjustment;
mod confidence;
mod jacobian;
mod normal;
mod pyramid;
mod scale;
mod splat;
mod target;
#[cfg(test)]
mod tests;

pub use adjustment::{CAMERA_PARAMETER_NAMES, CAMERA_PARAMETERS, CameraAdjustment};
pub use confidence::{CONDITIONING_HALF, FIT_SCALE, FULL_COVERAGE};
pub use jacobian::{CameraJacobian, camera_jacobian};
pub use scale::{EVIDENCE, REFINEMENTS, STEPS, ScaleFit, ScaleView, fit_translation_scale};

use c4g_renderer::raster::RenderOptions;
use c4g_scene::{Camera, GaussianSet, SceneError};
use normal::{Normal, conditioning, cost, damped_step, normal_equations};
use pyramid::Level;
use target::check_target;

/// Levenberg–Marquardt's first damping.
const LAMBDA_START: f64 = 1e-3;
/// The least damping. A direction the view barely determines (an eigenvalue of the unit-diagonal
/// normal matrix well under this) then moves by damped steps rather than a near-singular solve's;
/// on the tests' scenes it also took a fifth fewer steps than a floor of 1e-9.
const LAMBDA_MIN: f64 = 1e-4;
/// Damping past which no step is tried: no step of any size lowered the cost.
const LAMBDA_MAX: f64 = 1e8;
/// A level is done once its mean robust residual per weighted channel is below this: an RMS
/// colour error of 1e-4, a tenth of an 8-bit frame's quantisation noise (1/255/√12 ≈ 1.1e-3).
/// Only a synthetic target gets there (a real frame stops by the tolerance first), and with
/// image gradients of ~0.1 a pixel it means a pose within ~1e-3 pixels.
const RESIDUAL_FLOOR: f64 = 0.5e-8;

/// What [`align_camera`] may vary.
#[derive(Debug, Clone, PartialEq)]
pub struct AlignOptions {
    /// How the set is rendered to compare with the frame (background, near and far, footprint:
    /// the model's own). Features are never rendered.
    pub render: RenderOptions,
    /// Most Levenberg–Marquardt steps tried per pyramid level (each costs one render of its
    /// level); at least 1.
    pub max_iterations: usize,
    /// Pyramid levels, the frame itself included; `None`: every halving whose smaller side stays
    /// at least 16 pixels (3 at 64², 4 at 224²).
    pub levels: Option<usize>,
    /// Refine a focal scale shared by fx and fy as well as the pose.
    pub refine_focal: bool,
    /// Huber's δ on each colour residual (colours in 0..1): residuals beyond it pull linearly.
    pub huber_delta: f64,
    /// A level ends when an accepted step lowers its cost by less than this fraction.
    pub tolerance: f64,
}

impl Default for AlignOptions {
    /// Defaults that work from 64² to 224² (the tests hold them to it): 50 steps a level, the
    /// automatic pyramid, the pose only, δ = 0.1 (a tenth of the colour range: the residuals of
    /// a well-aligned render of a good reconstruction are well within it), tolerance 1e-5 (on the
    /// tests' scenes the finest level then ends within 1e-3° and 1e-4 scene units of the truth).
    fn default() -> Self {
        Self {
            render: RenderOptions::default(),
            max_iterations: 50,
            levels: None,
            refine_focal: false,
            huber_delta: 0.1,
            tolerance: 1e-5,
        }
    }
}

impl AlignOptions {
    fn validate(&self) -> Result<(), SceneError> {
        self.render.validate()?;
        let invalid = |what: String| Err(SceneError::InvalidRenderOptions(what));
        if self.max_iterations == 0 {
            return invalid("alignment needs max_iterations of at least 1".to_owned());
        }
        if self.levels == Some(0) {
            return invalid("alignment needs at least one pyramid level (the frame)".to_owned());
        }
        if !(self.huber_delta.is_finite() && self.huber_delta > 0.0) {
            return invalid(format!(
                "Huber delta {} must be positive and finite (0.1 suits colours in 0..1)",
                self.huber_delta
            ));
        }
        if !(self.tolerance.is_finite() && self.tolerance >= 0.0) {
            return invalid(format!(
                "tolerance {} must be finite and not negative",
                self.tolerance
            ));
        }
        Ok(())
    }
}

/// The outcome of [`align_camera`].
#[derive(Debug, Clone, PartialEq)]
pub struct Alignment {
    /// The recovered camera.
    pub camera: Camera,
    /// What turns the initial camera into the recovered one (in f64).
    pub adjustment: CameraAdjustment,
    /// The alpha-weighted mean Huber residual per colour channel at the initial camera, at full
    /// resolution (`Σ α ρ(r) / 3Σα`; `ρ(r) = r²/2` within δ; 0 where the render covers nothing).
    pub initial_residual: f64,
    /// The same at the recovered camera.
    pub residual: f64,
    /// Levenberg–Marquardt steps tried, all levels together.
    pub iterations: usize,
    /// Whether the finest level stopped by its tolerance, its residual floor or because no step
    /// lowered its cost, rather than by running out of iterations (or a step that was not
    /// finite). Converged is not correct: a local minimum converges too (see `confidence`).
    pub converged: bool,
    /// How far to trust the camera, in `[0, 1]` (its definition: [`FULL_COVERAGE`],
    /// [`FIT_SCALE`], [`CONDITIONING_HALF`] and the `confidence` module's documentation):
    /// coverage × fit × conditioning.
    pub confidence: f64,
    /// Mean rendered alpha over the frame at the recovered camera.
    pub coverage: f64,
    /// Smallest over largest eigenvalue of the unit-diagonal Gauss–Newton matrix at the recovered
    /// camera: near 0 when some camera motion leaves the render unchanged.
    pub conditioning: f64,
}

/// Recovers the camera that sees `set` as the frame `target` shows it, starting from `initial`.
///
/// `target` is the frame's RGB, 3 floats a pixel, row-major, at the initial camera's size
/// (colours in 0..1, as the renderer's). The render is compared over `options.render`'s
/// background; each pixel counts by the set's rendered alpha there. Runs on the current rayon
/// pool.
///
/// Fails on an empty set (`InvalidGaussian`: there is nothing to align), a target that is not
/// the camera's size or has non-finite values (`InvalidImage`), invalid options
/// (`InvalidRenderOptions`), and a recovered camera that is not one (`InvalidCamera`). A
/// non-finite initial camera cannot reach it: [`Camera`]'s constructors refuse one.
///
/// Errors use the crate's existing variants, so that the server's exhaustive mapping of them
/// still compiles; an empty set is `InvalidGaussian` (the server's own problem, a 500) because
/// the set is the model's decode, not the client's input.
pub fn align_camera(
    set: &GaussianSet,
    target: &[f32],
    initial: &Camera,
    options: &AlignOptions,
) -> Result<Alignment, SceneError> {
    options.validate()?;
    check_inputs(set, target, initial)?;
    let n = if options.refine_focal {
        CAMERA_PARAMETERS
    } else {
        CAMERA_PARAMETERS - 1
    };
    let levels = options
        .levels
        .unwrap_or_else(|| pyramid::default_levels(initial.width(), initial.height()));
    let pyramid = pyramid::build(target, initial, levels)?;
    let finest = &pyramid[0];

    let start = render_level(set, finest, &CameraAdjustment::IDENTITY, options);
    let initial_residual = level_cost(&start, finest, options);

    let mut adjustment = CameraAdjustment::IDENTITY;
    // Where the coarser level started, to hold its answer to the finer level's judgement.
    let mut entry = None;
    let mut iterations = 0;
    let mut outcome = None;
    for level in pyramid.iter().rev() {
        let mut render = render_level(set, level, &adjustment, options);
        if let Some(entry) = entry {
            let before = render_level(set, level, &entry, options);
            if level_cost(&before, level, options) < level_cost(&render, level, options) {
                (adjustment, render) = (entry, before);
            }
        }
        entry = Some(adjustment);
        let result = refine_level(set, level, adjustment, render, options, n);
        adjustment = result.adjustment;
        iterations += result.steps;
        outcome = Some(result);
    }
    let Some(last) = outcome else {
        return Err(SceneError::InvalidRenderOptions(
            "the pyramid has no level".to_owned(),
        ));
    };
    let at_end = normal_equations(
        &last.render,
        &finest.target,
        &last.render.alpha,
        options.huber_delta,
        n,
    );
    let residual = at_end.mean_cost();
    let coverage = last.render.alpha.iter().sum::<f64>() / last.render.alpha.len() as f64;
    let conditioning = conditioning(&at_end.h, n);
    Ok(Alignment {
        camera: adjustment.apply(initial)?,
        adjustment,
        initial_residual,
        residual,
        iterations,
        converged: last.converged,
        confidence: confidence::confidence(coverage, residual, conditioning),
        coverage,
        conditioning,
    })
}

fn check_inputs(set: &GaussianSet, target: &[f32], camera: &Camera) -> Result<(), SceneError> {
    if set.is_empty() {
        return Err(SceneError::InvalidGaussian {
            index: 0,
            reason: "the set is empty: a camera is aligned by rendering the set's own Gaussians, \
                     so it needs at least one"
                .to_owned(),
        });
    }
    check_target(target, camera)
}

/// Where one level's refinement ended.
struct LevelResult {
    adjustment: CameraAdjustment,
    /// The render at `adjustment`, at this level's size.
    render: CameraJacobian,
    steps: usize,
    converged: bool,
}

/// The render (with its Jacobian) of `set` at one level's camera, adjusted.
fn render_level(
    set: &GaussianSet,
    level: &Level,
    adjustment: &CameraAdjustment,
    options: &AlignOptions,
) -> CameraJacobian {
    jacobian::render(set, &level.camera, adjustment, &options.render)
}

/// A render's alpha-weighted mean robust residual against a level's target.
fn level_cost(render: &CameraJacobian, level: &Level, options: &AlignOptions) -> f64 {
    cost(render, &level.target, &render.alpha, options.huber_delta).mean_cost()
}

/// Levenberg–Marquardt at one pyramid level, from `adjustment`, whose render is `render`.
fn refine_level(
    set: &GaussianSet,
    level: &Level,
    mut adjustment: CameraAdjustment,
    mut render: CameraJacobian,
    options: &AlignOptions,
    n: usize,
) -> LevelResult {
    let delta = options.huber_delta;
    let mut lambda = LAMBDA_START;
    let mut steps = 0;
    let converged = 'level: loop {
        // The weights of this linearisation, frozen while its steps are judged.
        let weights = render.alpha.clone();
        let normal: Normal = normal_equations(&render, &level.target, &weights, delta, n);
        if normal.mean_cost() <= RESIDUAL_FLOOR {
            break 'level true;
        }
        loop {
            if steps >= options.max_iterations {
                break 'level false;
            }
            let Some(step) = damped_step(&normal, lambda, n) else {
                // Nothing this render sees moves with the camera.
                break 'level true;
            };
            steps += 1;
            let trial_adjustment = adjustment.then(&CameraAdjustment::exp(step));
            if !trial_adjustment.is_finite() {
                break 'level false;
            }
            let trial = render_level(set, level, &trial_adjustment, options);
            let trial_cost = cost(&trial, &level.target, &weights, delta).cost;
            if trial_cost < normal.cost {
                let decrease = (normal.cost - trial_cost) / normal.cost;
                adjustment = trial_adjustment;
                render = trial;
                lambda = (lambda / 3.0).max(LAMBDA_MIN);
                if decrease < options.tolerance {
                    break 'level true;
                }
                continue 'level;
            }
            lambda *= 4.0;
            if lambda > LAMBDA_MAX {
                break 'level true;
            }
        }
    };
    LevelResult {
        adjustment,
        render,
        steps,
        converged,
    }
}
