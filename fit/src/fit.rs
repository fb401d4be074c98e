//! The fit: keyframe sets optimised against a clip's own frames at their cameras.
//!
//! Each step renders the scene at one training frame's time ([`FittedScene::at`], the engine's
//! rules) with the CPU rasterizer, scores it with 3DGS's `(1 − λ)·L1 + λ·D-SSIM`
//! (`c4g_optim::loss`), differentiates the render, chains that to every keyframe's parameters
//! ([`crate::backward`]), adds two regularisers and takes one Adam step with a learning rate per
//! group (`c4g_optim`):
//! - **temporal smoothness** on keyframe positions: the squared change of velocity at every inner
//!   keyframe, `|h̄·(v_k − v_{k−1})|²` with `v_k` the velocity from keyframe `k` to `k + 1` and `h̄`
//!   the mean keyframe interval (so it is in scene units and zero for uniform motion), weighted by
//!   [`FitOptions::smoothness`] and averaged over Gaussians: a frame seen only by one keyframe pair
//!   must not bend the others;
//! - a **prior toward the start** (the feed-forward answer), `w·|θ − θ₀|²` over every parameter,
//!   averaged over Gaussians, whose weight `w` fades linearly from [`FitOptions::prior`] to 0 over
//!   [`FitOptions::prior_fade_steps`]: early steps from a few frames cannot drag the scene away
//!   from what the model predicted, later ones are free to.
//!
//! Every `holdout_every`-th frame (indices `holdout_every − 1`, `2·holdout_every − 1`, …) is never
//! trained on and is scored before and after, so every fit says how well it does on frames it did
//! not see. Densification (optional) is 3DGS's, run by `c4g_optim::densify` on one representative
//! row per Gaussian (`densify_keyframes`) whose decisions every keyframe then follows, so N stays
//! shared and never exceeds [`FitOptions::max_gaussians`].
//!
//! **Static Gaussians** are decided during the fit, not after it: each keyframe's copy of a
//! Gaussian sees only the frames near it, and Adam moves every copy by about its learning rate a
//! step, so copies of a still Gaussian drift apart by more than a pixel within a hundred steps
//! and a tolerance applied at the end finds nothing static. Before the first step and every
//! [`FitOptions::static_every`] steps, a Gaussian whose keyframe positions lie in a ball
//! [`FitOptions::static_pixels`] pixels wide at its depth (at least
//! [`FitOptions::static_tolerance`]), or, when the frames come from one still camera, one that
//! stays on still pixels at every keyframe (`crate::still`: the frames themselves say that
//! nothing there moves, whatever the start's jitter), is **tied**: its keyframes take their
//! mean, and from then on they share one gradient (the sum of theirs) and, after every step, one
//! value, so it cannot drift. Tying before the first step trusts the start's motion, which a weak feed-forward answer
//! underestimates (a panning camera seen as still moves the whole scene); so the frames get the
//! last word: a tied Gaussian whose keyframes the frames keep pulling apart, consistently in one
//! direction (`untie_moving`), is untied for good. Copies made by densification inherit their
//! parent's state. A fit with one keyframe has every Gaussian static.
//!
//! **Cameras** ([`FitOptions::refine_cameras`], `crate::cameras`): each training frame's camera
//! gets the renderer's seven camera parameters, stepped by their own Adam when the frame is
//! trained on, with a prior toward the given camera; held-out frames keep their given cameras, so
//! their score is never bought by moving a camera toward the frame it is scored on.
//!
//! After every step the parameters are kept inside a box (positions within ±1e4·extent, scales
//! up to 100·extent, colours in [0, 1], logits within the optimiser's limits) and non-finite
//! gradient entries are dropped: a learning rate far too high then ends in a poor scene, never a
//! non-finite one. Everything is deterministic for a seed (the frame order and the split children
//! are drawn from it; the renderer's sums have a fixed order).

use std::time::{Duration, Instant};

use c4g_optim::densify::{DensifyStats, densify};
use c4g_optim::loss::l1_dssim;
use c4g_optim::params::{LOG_SCALE_MIN, LOGIT_LIMIT};
use c4g_optim::{Adam, AdamConfig, DensifySchedule, Group, LearningRates, Params};
use c4g_renderer::fidelity::{SSIM_WINDOW, psnr};
use c4g_renderer::{
    BackwardOptions, CpuRasterizer, DifferentiableRasterizer, Rasterizer, RenderGradients,
    RenderOptions,
};
use c4g_scene::{Camera, GaussianSet};
use rayon::prelude::*;

use crate::backward::{Blend, chain};
use crate::cameras::CameraRefinement;
use crate::error::FitError;
use crate::keyframe_params::KeyframeParams;
use crate::scene::FittedScene;
use crate::still::StillPixels;

/// Values a thread takes at a time in the per-step passes over every parameter. Those passes
/// (Adam's step, the regularisers, ties, the box) touch every keyframe's copy of every Gaussian;
/// run on one thread they took about as long as the threaded render and backward. Each is element
/// by element or Gaussian by Gaussian, so the split cannot change a bit of the result.
const CHUNK: usize = 1 << 14;
/// Gaussians a thread takes at a time in the per-Gaussian passes.
const GAUSSIANS_A_TASK: usize = 256;

/// One source frame of the clip.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Its time, seconds (inside the keyframes' span).
    pub time: f64,
    /// RGB, 3 floats a pixel, the camera's size, row-major.
    pub rgb: Vec<f32>,
    /// The camera it was taken from.
    pub camera: Camera,
}

/// How to fit.
#[derive(Debug, Clone, PartialEq)]
pub struct FitOptions {
    /// Optimisation steps, one training frame each.
    pub steps: u64,
    /// Most Gaussians per keyframe (the start must not hold more).
    pub max_gaussians: usize,
    /// Every `holdout_every`-th frame is held out (0: none).
    pub holdout_every: usize,
    /// Seeds the frame order and densification.
    pub seed: u64,
    /// Learning rates per group over steps (a schedule's length is its own: set it for `steps`).
    pub rates: LearningRates,
    /// Adam's constants.
    pub adam: AdamConfig,
    /// λ of `(1 − λ)·L1 + λ·D-SSIM` (3DGS: 0.2; frames under 11×11 pixels, SSIM's window, are
    /// scored by L1 alone).
    pub lambda_dssim: f64,
    /// Weight of the temporal smoothness of keyframe positions.
    pub smoothness: f64,
    /// Initial weight of the prior toward the start.
    pub prior: f64,
    /// Steps over which the prior fades to 0.
    pub prior_fade_steps: u64,
    /// A Gaussian whose keyframe positions all lie in a ball this wide (scene units) around
    /// their mean is static (the floor under [`static_pixels`](Self::static_pixels)' tolerance).
    pub static_tolerance: f64,
    /// … or this many pixels wide at its depth, as the first training frame's camera sees it
    /// (0: `static_tolerance` alone).
    pub static_pixels: f64,
    /// Frames from one still camera: a pixel whose colour's standard deviation over the
    /// training frames is under this in every channel is still, and a Gaussian that stays on
    /// still pixels at every keyframe is tied whatever its motion (`crate::still`; 0: off).
    pub still_threshold: f64,
    /// Look for static Gaussians before the first step and every this many steps (0: only at
    /// the end). One found is tied for the rest of the fit: its keyframes share one value and
    /// one gradient (the sum of theirs), so it cannot drift apart again.
    pub static_every: u64,
    /// Score the held-out frames every this many steps for the curve (0: only before and after).
    pub eval_every: u64,
    /// Densification and pruning (its budget is replaced by `max_gaussians`), if any.
    pub densify: Option<DensifySchedule>,
    /// The scene's size (3DGS's `spatial_lr_scale` and clone/split boundary).
    pub extent: f64,
    /// Clip the gradient's norm to this, if set.
    pub clip_norm: Option<f64>,
    /// Stop after this long, if set.
    pub time_budget: Option<Duration>,
    /// What the renders vary (background, footprint).
    pub render: RenderOptions,
    /// Refine the training frames' cameras with the scene (`crate::cameras`); held-out frames
    /// keep theirs.
    pub refine_cameras: bool,
    /// The cameras' learning rates: rotation (radians), translation (times `extent`), log focal.
    pub camera_rates: [f64; 3],
    /// Weight of the prior `w·|offset|²` that pulls a refined camera back toward its given one.
    pub camera_prior: f64,
}

impl Default for FitOptions {
    /// 300 steps, 3DGS's rates over them (extent 1), no densification, holdout every 8th frame.
    fn default() -> Self {
        Self {
            steps: 300,
            max_gaussians: 100_000,
            holdout_every: 8,
            seed: 0,
            rates: LearningRates::gaussian_splatting(1.0, 300),
            adam: AdamConfig::default(),
            lambda_dssim: 0.2,
            smoothness: 1e-3,
            prior: 1e-4,
            prior_fade_steps: 100,
            static_tolerance: 1e-3,
            static_pixels: 1.0,
            still_threshold: 0.02,
            static_every: 50,
            eval_every: 0,
            densify: None,
            extent: 1.0,
            clip_norm: None,
            time_budget: None,
            render: RenderOptions {
                features: false,
                ..RenderOptions::default()
            },
            refine_cameras: false,
            camera_rates: [1e-3, 1e-3, 1e-4],
            camera_prior: 1.0,
        }
    }
}

/// What a progress callback sees after each step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Progress {
    /// Steps done.
    pub step: u64,
    /// Steps asked for.
    pub steps: u64,
    /// The step's photometric loss.
    pub loss: f64,
    /// Gaussians per keyframe now.
    pub gaussians: usize,
    /// Seconds since the fit started.
    pub seconds: f64,
    /// Mean PSNR of the held-out frames, when this step scored them.
    pub holdout_psnr: Option<f64>,
}

/// What a progress callback answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Control {
    /// Go on.
    Continue,
    /// Stop now and return the scene as it is.
    Stop,
}

/// One point of the loss curve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurvePoint {
    /// The step (from 0).
    pub step: u64,
    /// Its photometric loss (of the training frame it rendered, before its update).
    pub loss: f64,
    /// Mean held-out PSNR after the step, when scored.
    pub holdout_psnr: Option<f64>,
}

/// What a fit did and how well it does.
#[derive(Debug, Clone, PartialEq)]
pub struct FitReport {
    /// Steps taken.
    pub steps: u64,
    /// Wall-clock seconds.
    pub seconds: f64,
    /// Gaussians per keyframe at the end.
    pub gaussians: usize,
    /// Gaussians that ended static.
    pub static_count: usize,
    /// Indices of the source frames held out (never trained on).
    pub holdout_frames: Vec<usize>,
    /// Mean PSNR (dB) of the held-out frames from the start (None without held-out frames;
    /// infinite where every one is matched exactly).
    pub holdout_psnr_before: Option<f64>,
    /// The same after the fit.
    pub holdout_psnr_after: Option<f64>,
    /// Mean PSNR of the training frames after the fit.
    pub train_psnr_after: f64,
    /// The loss curve, one point a step.
    pub curve: Vec<CurvePoint>,
    /// True when the callback or the time budget stopped the fit early.
    pub stopped: bool,
    /// Every frame's camera as the fit ended: the given one, or for a training frame of a fit
    /// that refines cameras, the refined one.
    pub cameras: Vec<Camera>,
    /// When every training frame has one camera: the share of its pixels that stayed still over
    /// them (`crate::still`). Near 0 for a camera that moved (bedroom's handheld pan: 2 %), well
    /// above it for a tripod (dog: 60 %); so a clip with no cameras that scores near 0 was
    /// probably not filmed from the still camera it was fitted at.
    pub still_share: Option<f64>,
}

/// The indices of the frames held out of `frames` frames: every `every`-th (none for 0).
pub fn holdout_frames(frames: usize, every: usize) -> Vec<usize> {
    if every == 0 {
        return Vec::new();
    }
    (0..frames).filter(|i| (i + 1) % every == 0).collect()
}

/// Fits `start` (the feed-forward keyframe sets) to `frames`; `progress` sees every step and may
/// stop the fit. With 0 steps the start is returned unchanged (its static mask marks the Gaussians
/// already identical at every keyframe).
pub fn fit(
    start: &FittedScene,
    frames: &[Frame],
    options: &FitOptions,
    mut progress: impl FnMut(&Progress) -> Control,
) -> Result<(FittedScene, FitReport), FitError> {
    let began = Instant::now();
    validate(start, frames, options)?;
    let holdout = holdout_frames(frames.len(), options.holdout_every);
    let train: Vec<usize> = (0..frames.len()).filter(|i| !holdout.contains(i)).collect();
    if train.is_empty() {
        return Err(FitError::Invalid(
            "every frame is held out: nothing to train on".into(),
        ));
    }
    let raster = CpuRasterizer::new();
    let given: Vec<Camera> = frames.iter().map(|f| f.camera).collect();
    let score = |scene: &FittedScene, which: &[usize], cameras: &[Camera]| {
        mean_psnr(&raster, scene, frames, cameras, which, options)
    };
    let holdout_psnr_before = score(start, &holdout, &given)?;
    let mut fitting = Fitting::new(start, options, &frames[train[0]].camera)?;
    if options.refine_cameras {
        fitting.cameras = Some(CameraRefinement::new(given.clone(), options.adam));
    }
    if options.static_every > 0 && options.steps > 0 {
        let seen: Vec<(Camera, &[f32])> = train
            .iter()
            .map(|&i| (frames[i].camera, frames[i].rgb.as_slice()))
            .collect();
        fitting.still = StillPixels::measure(&seen, options.still_threshold);
        fitting.tie_static();
    }
    let mut rng = SplitMix(options.seed);
    let mut order = Vec::new();
    let mut curve = Vec::new();
    let mut stopped = false;
    for step in 0..options.steps {
        if options.time_budget.is_some_and(|b| began.elapsed() >= b) {
            stopped = true;
            break;
        }
        if order.is_empty() {
            order = train.clone();
            rng.shuffle(&mut order);
        }
        let Some(index) = order.pop() else { break };
        let loss = fitting.step(&raster, frames, index, step, &mut rng)?;
        let scored = options.eval_every > 0 && (step + 1).is_multiple_of(options.eval_every);
        let holdout_psnr = if scored {
            score(&fitting.scene(start.times.clone(), false), &holdout, &given)?
        } else {
            None
        };
        curve.push(CurvePoint {
            step,
            loss,
            holdout_psnr,
        });
        let report = Progress {
            step: step + 1,
            steps: options.steps,
            loss,
            gaussians: fitting.params.gaussians(),
            seconds: began.elapsed().as_secs_f64(),
            holdout_psnr,
        };
        if progress(&report) == Control::Stop {
            stopped = true;
            break;
        }
    }
    let steps = curve.len() as u64;
    let cameras = fitting
        .cameras
        .as_ref()
        .map_or_else(|| given.clone(), CameraRefinement::cameras);
    let scene = if steps == 0 {
        let mut same = start.clone();
        same.static_mask = exactly_static(&fitting.params);
        same
    } else {
        fitting.scene(start.times.clone(), true)
    };
    let report = FitReport {
        steps,
        seconds: began.elapsed().as_secs_f64(),
        gaussians: scene.len(),
        static_count: scene.static_mask.iter().filter(|s| **s).count(),
        holdout_psnr_before,
        holdout_psnr_after: score(&scene, &holdout, &given)?,
        train_psnr_after: score(&scene, &train, &cameras)?.unwrap_or(f64::NAN),
        holdout_frames: holdout,
        curve,
        stopped,
        cameras,
        still_share: fitting.still.as_ref().map(StillPixels::fraction),
    };
    Ok((scene, report))
}

fn validate(start: &FittedScene, frames: &[Frame], options: &FitOptions) -> Result<(), FitError> {
    let (first, last) = start
        .span()
        .ok_or_else(|| FitError::Invalid("the start has no keyframes".into()))?;
    if frames.is_empty() {
        return Err(FitError::Invalid("a fit needs at least one frame".into()));
    }
    for (i, f) in frames.iter().enumerate() {
        let pixels = f.camera.width() as usize * f.camera.height() as usize;
        if f.rgb.len() != 3 * pixels || f.rgb.iter().any(|v| !v.is_finite()) {
            return Err(FitError::Invalid(format!(
                "frame {i}: {} finite RGB values needed, the camera sees {pixels} pixels",
                3 * pixels
            )));
        }
        if !(f.time >= first && f.time <= last) {
            return Err(FitError::Invalid(format!(
                "frame {i} at {} s is outside the keyframes' span [{first}, {last}]",
                f.time
            )));
        }
    }
    if start.len() > options.max_gaussians {
        return Err(FitError::Invalid(format!(
            "the start holds {} Gaussians, over the budget of {}",
            start.len(),
            options.max_gaussians
        )));
    }
    if !(options.extent.is_finite() && options.extent > 0.0) {
        return Err(FitError::Invalid("the extent must be positive".into()));
    }
    Ok(())
}

/// Mean PSNR of `scene` against the frames `which` (None when there are none).
fn mean_psnr(
    raster: &CpuRasterizer,
    scene: &FittedScene,
    frames: &[Frame],
    cameras: &[Camera],
    which: &[usize],
    options: &FitOptions,
) -> Result<Option<f64>, FitError> {
    if which.is_empty() {
        return Ok(None);
    }
    let track = scene.track()?;
    let mut total = 0.0;
    for &i in which {
        let f = &frames[i];
        let image = raster.render(&track.at(f.time)?, &cameras[i], &options.render)?;
        total += psnr(
            &image.rgb,
            &f.rgb,
            f.camera.width(),
            f.camera.height(),
            None,
        )?;
    }
    Ok(Some(total / which.len() as f64))
}

/// The state of a fit between steps.
struct Fitting<'o> {
    params: KeyframeParams,
    /// θ₀: where the prior pulls (the start; new Gaussians where they were born).
    prior: Params,
    adam: Adam,
    stats: DensifyStats,
    times: Vec<f64>,
    options: &'o FitOptions,
    /// One entry per Gaussian: tied static (its keyframes share one value and one gradient).
    tied: Vec<bool>,
    /// The camera whose pixel at a Gaussian's depth is the static tolerance.
    view: Camera,
    /// The still camera's still pixels, if the frames come from one.
    still: Option<StillPixels>,
    /// The gradient, reused from step to step.
    grad: KeyframeParams,
    /// Per row of a tied Gaussian: what its keyframe's position was pulled by since the tie
    /// ([`Evidence`]); cleared by densification.
    evidence: Vec<Evidence>,
    /// Gaussians untied once (the frames moved them): never tied again.
    moving: Vec<bool>,
    /// The frames' refined cameras, when the fit refines them.
    cameras: Option<CameraRefinement>,
}

/// The frames' pull on one keyframe of a tied Gaussian, to tell a Gaussian that only looks still
/// (tied because its start barely moved) from one the frames want to move: the sum of the
/// position gradients this keyframe's copy received, the sum of their norms, the sum of its blend
/// weights, and how many frames it carried much of.
#[derive(Debug, Clone, Copy, Default)]
struct Evidence {
    sum: [f64; 3],
    norms: f64,
    weight: f64,
    frames: u32,
}

/// A tied Gaussian is untied when some keyframe's pull, less its share of the Gaussian's common
/// pull, is this consistent (its norm over the sum of the pulls' norms: near `1/√n` for `n` pulls
/// in random directions, near 1 for pulls in one direction) …
const UNTIE_CONSISTENCY: f64 = 0.95;
/// … over at least this many frames carried by that keyframe (blend weight over a quarter).
const UNTIE_FRAMES: u32 = 20;

impl<'o> Fitting<'o> {
    fn new(start: &FittedScene, options: &'o FitOptions, view: &Camera) -> Result<Self, FitError> {
        let params = KeyframeParams::from_sets(&start.sets)?;
        Ok(Self {
            prior: params.params.clone(),
            adam: Adam::new(options.adam, params.params.len()),
            stats: DensifyStats::new(params.gaussians()),
            tied: vec![false; params.gaussians()],
            grad: zeros_like(&params),
            evidence: vec![Evidence::default(); params.params.len()],
            moving: vec![false; params.gaussians()],
            cameras: None,
            params,
            times: start.times.clone(),
            options,
            view: *view,
            still: None,
        })
    }

    /// The set at `t`, built from the keyframes its interpolation reads (the bracketing pair and
    /// one on each side, for the Bessel tangents): the same bits as the whole track's `at(t)`,
    /// without building every keyframe's set.
    fn set_at(&self, t: f64) -> Result<GaussianSet, FitError> {
        let k = self.times.len();
        let at = self.times.partition_point(|&x| x < t);
        if at < k && self.times[at] == t {
            return Ok(self.params.set(at));
        }
        if at == 0 || at >= k {
            return Err(FitError::Invalid(format!(
                "t = {t} is outside the keyframes' span"
            )));
        }
        let (lo, hi) = ((at - 1).saturating_sub(1), (at + 1).min(k - 1));
        let keyframes = (lo..=hi)
            .map(|key| (self.times[key], self.params.set(key)))
            .collect();
        FittedScene::new(keyframes)?.at(t)
    }

    /// Ties every Gaussian static now that the frames have not shown to move ([`tie_static`])
    /// or that stays on still pixels at every keyframe ([`StillPixels`]), each with its
    /// evidence cleared.
    fn tie_static(&mut self) {
        let before = self.tied.clone();
        tie_static(
            &mut self.params,
            &mut self.tied,
            &self.moving,
            &self.view,
            self.options,
        );
        if let Some(still) = &self.still {
            let kf = self.params.keyframes();
            // One the frames untied stays free: tying it again on still pixels was measured
            // (dog, `default`): 41 % static where 35 %, and 0.15 dB lower.
            for i in 0..self.tied.len() {
                if self.tied[i] || self.moving[i] {
                    continue;
                }
                let on_still = (0..kf).all(|k| {
                    still.holds(std::array::from_fn(|j| {
                        self.params.value(Group::Position, i, k, j)
                    }))
                });
                if on_still {
                    self.tied[i] = true;
                    share(&mut self.params, i);
                }
            }
        }
        let kf = self.params.keyframes();
        for (i, _) in before
            .iter()
            .zip(&self.tied)
            .enumerate()
            .filter(|(_, (a, b))| !**a && **b)
        {
            for k in 0..kf {
                self.evidence[self.params.row_index(i, k)] = Evidence::default();
            }
        }
    }

    /// Adds this step's position gradients (`g`, from the frame alone) to the tied Gaussians'
    /// evidence; `blend` is how the frame's set was made from the keyframes.
    fn gather_evidence(&mut self, g: &KeyframeParams, blend: &Blend) {
        let keys: Vec<(usize, f64)> = blend
            .position
            .iter()
            .copied()
            .enumerate()
            .filter(|(_, c)| *c != 0.0)
            .collect();
        let kf = self.params.keyframes();
        self.evidence
            .par_chunks_mut(kf)
            .zip(g.params.group(Group::Position).par_chunks(3 * kf))
            .zip(self.tied.par_iter())
            .with_min_len(GAUSSIANS_A_TASK)
            .filter(|(_, tied)| **tied)
            .for_each(|((evidence, position), _)| {
                for &(k, c) in &keys {
                    let pull = &position[3 * k..3 * k + 3];
                    let e = &mut evidence[k];
                    for (s, p) in e.sum.iter_mut().zip(pull) {
                        *s += p;
                    }
                    e.norms += pull.iter().map(|p| p * p).sum::<f64>().sqrt();
                    e.weight += c;
                    e.frames += u32::from(c.abs() > 0.25);
                }
            });
    }

    /// Unties the tied Gaussians the frames want to move: some keyframe pulled, beyond its share
    /// of the Gaussian's common pull, consistently in one direction ([`UNTIE_CONSISTENCY`] over
    /// at least [`UNTIE_FRAMES`] frames). Such a one was tied on its start's say and is not
    /// static: it is marked moving and never tied again.
    fn untie_moving(&mut self) {
        let kf = self.params.keyframes();
        for i in 0..self.tied.len() {
            if !self.tied[i] {
                continue;
            }
            let rows = &self.evidence[self.params.row_index(i, 0)..self.params.row_index(i, kf)];
            let weight: f64 = rows.iter().map(|e| e.weight).sum();
            let common: [f64; 3] = std::array::from_fn(|j| rows.iter().map(|e| e.sum[j]).sum());
            let pulled = rows.iter().any(|e| {
                if e.frames < UNTIE_FRAMES || e.norms <= 0.0 || weight == 0.0 {
                    return false;
                }
                let own = (0..3)
                    .map(|j| (e.sum[j] - common[j] * e.weight / weight).powi(2))
                    .sum::<f64>()
                    .sqrt();
                own > UNTIE_CONSISTENCY * e.norms
            });
            if pulled {
                self.tied[i] = false;
                self.moving[i] = true;
            }
        }
    }

    /// A tied Gaussian's gradient: the sum of its keyframes', given to each.
    fn tie_gradient(&self, g: &mut KeyframeParams) {
        let kf = self.params.keyframes();
        if kf < 2 {
            return;
        }
        for group in Group::ALL {
            let w = group.width();
            g.params
                .group_mut(group)
                .par_chunks_mut(kf * w)
                .zip(self.tied.par_iter())
                .with_min_len(GAUSSIANS_A_TASK)
                .filter(|(_, tied)| **tied)
                .for_each(|(rows, _)| {
                    for j in 0..w {
                        let sum: f64 = (0..kf).map(|k| rows[k * w + j]).sum();
                        for k in 0..kf {
                            rows[k * w + j] = sum;
                        }
                    }
                });
        }
    }

    /// A tied Gaussian's keyframes after Adam's step: one value, their mean (Adam's moments of
    /// the rows may differ from before the tie).
    fn tie_values(&mut self) {
        let kf = self.params.keyframes();
        if kf < 2 {
            return;
        }
        for group in Group::ALL {
            let w = group.width();
            self.params
                .params
                .group_mut(group)
                .par_chunks_mut(kf * w)
                .zip(self.tied.par_iter())
                .with_min_len(GAUSSIANS_A_TASK)
                .filter(|(_, tied)| **tied)
                .for_each(|(rows, _)| share_rows(group, rows, kf));
        }
    }

    /// One step on `frames[index]`; returns its photometric loss.
    fn step(
        &mut self,
        raster: &CpuRasterizer,
        frames: &[Frame],
        index: usize,
        step: u64,
        rng: &mut SplitMix,
    ) -> Result<f64, FitError> {
        let o = self.options;
        let frame = &frames[index];
        let set = self.set_at(frame.time)?;
        let camera = self
            .cameras
            .as_ref()
            .map_or(frame.camera, |c| *c.camera(index));
        let (w, h) = (camera.width(), camera.height());
        let (image, saved) = raster.render_saved(&set, &camera, &o.render)?;
        // SSIM's window needs 11×11 pixels: a smaller frame is scored by L1 alone.
        let small = (w as usize) < SSIM_WINDOW || (h as usize) < SSIM_WINDOW;
        let lambda = if small { 0.0 } else { o.lambda_dssim };
        let loss = l1_dssim(&image.rgb, &frame.rgb, w, h, lambda)?;
        let grads = raster.backward(
            &saved,
            &RenderGradients::rgb(&loss.gradient),
            BackwardOptions {
                camera: self.cameras.is_some(),
            },
        )?;
        self.stats.accumulate(&grads.gaussians.means2d, w, h);
        let mut g = std::mem::replace(
            &mut self.grad,
            KeyframeParams::from_rows(Params::zeros(0), 1),
        );
        if g.params.len() == self.params.params.len() && g.keyframes() == self.params.keyframes() {
            for group in Group::ALL {
                g.params
                    .group_mut(group)
                    .par_chunks_mut(CHUNK)
                    .for_each(|c| c.fill(0.0));
            }
        } else {
            g = zeros_like(&self.params);
        }
        let blend = Blend::new(&self.times, frame.time)?;
        chain(&blend, &self.params, &set, &grads.gaussians, &mut g);
        self.gather_evidence(&g, &blend);
        add_smoothness(&self.params, &self.times, o.smoothness, &mut g);
        let fade = if o.prior_fade_steps == 0 {
            0.0
        } else {
            (1.0 - step as f64 / o.prior_fade_steps as f64).max(0.0)
        };
        add_prior(&self.params, &self.prior, o.prior * fade, &mut g);
        for group in Group::ALL {
            g.params
                .group_mut(group)
                .par_chunks_mut(CHUNK)
                .for_each(|c| {
                    c.iter_mut()
                        .filter(|v| !v.is_finite())
                        .for_each(|v| *v = 0.0)
                });
        }
        self.tie_gradient(&mut g);
        if let Some(max) = o.clip_norm {
            g.params.clip_norm(max);
        }
        self.adam
            .step(&mut self.params.params, &g.params, o.rates.at(step))?;
        self.grad = g;
        if let Some(cameras) = self.cameras.as_mut() {
            let r = o.camera_rates;
            let rates = [r[0], r[1] * o.extent, r[2]];
            cameras.step(index, &grads.camera.tangent, rates, o.camera_prior)?;
        }
        self.params.params.normalize_rotations();
        keep_in_box(&mut self.params.params, o.extent);
        self.tie_values();
        if let Some(d) = o.densify
            && step > 0
            && step >= d.from
            && step <= d.until
            && d.every > 0
            && step.is_multiple_of(d.every)
        {
            let mut config = d.config;
            config.budget = o.max_gaussians;
            densify_keyframes(self, &config, rng.next_u64());
        }
        if o.static_every > 0 && (step + 1).is_multiple_of(o.static_every) {
            self.untie_moving();
            self.tie_static();
        }
        Ok(loss.value)
    }

    /// The scene as fitted so far; `finish` also ties the Gaussians static at the end and marks
    /// every tied one static.
    fn scene(&self, times: Vec<f64>, finish: bool) -> FittedScene {
        let (params, static_mask) = if finish {
            let (mut params, mut tied) = (self.params.clone(), self.tied.clone());
            tie_static(
                &mut params,
                &mut tied,
                &self.moving,
                &self.view,
                self.options,
            );
            (params, tied)
        } else {
            (self.params.clone(), vec![false; self.params.gaussians()])
        };
        FittedScene {
            times,
            sets: params.sets(),
            static_mask,
        }
    }
}

fn zeros_like(p: &KeyframeParams) -> KeyframeParams {
    let mut z = p.clone();
    for g in Group::ALL {
        z.params.group_mut(g).fill(0.0);
    }
    z
}

/// Adds the gradient of `weight/N · Σ_i Σ_k |h̄·(v_k − v_{k−1})|²` over keyframe positions.
pub(crate) fn add_smoothness(
    params: &KeyframeParams,
    times: &[f64],
    weight: f64,
    out: &mut KeyframeParams,
) {
    let k = times.len();
    let n = params.gaussians();
    if weight == 0.0 || k < 3 || n == 0 {
        return;
    }
    let h: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    let mean_h = h.iter().sum::<f64>() / h.len() as f64;
    let scale = 2.0 * weight / n as f64;
    out.params
        .group_mut(Group::Position)
        .par_chunks_mut(3 * k)
        .zip(params.params.group(Group::Position).par_chunks(3 * k))
        .with_min_len(GAUSSIANS_A_TASK)
        .for_each(|(out, position)| {
            for j in 0..3 {
                let p = |key: usize| position[3 * key + j];
                for key in 1..k - 1 {
                    let (hl, hr) = (h[key - 1], h[key]);
                    let a = mean_h * ((p(key + 1) - p(key)) / hr - (p(key) - p(key - 1)) / hl);
                    let c = scale * a * mean_h;
                    out[3 * (key + 1) + j] += c / hr;
                    out[3 * key + j] -= c * (1.0 / hr + 1.0 / hl);
                    out[3 * (key - 1) + j] += c / hl;
                }
            }
        });
}

/// Adds the gradient of `weight/N · |θ − θ₀|²` over every parameter.
fn add_prior(params: &KeyframeParams, prior: &Params, weight: f64, out: &mut KeyframeParams) {
    let n = params.gaussians();
    if weight == 0.0 || n == 0 {
        return;
    }
    let scale = 2.0 * weight / n as f64;
    for g in Group::ALL {
        let (p, p0) = (params.params.group(g), prior.group(g));
        out.params
            .group_mut(g)
            .par_chunks_mut(CHUNK)
            .zip(p.par_chunks(CHUNK).zip(p0.par_chunks(CHUNK)))
            .for_each(|(o, (p, p0))| {
                for ((o, v), v0) in o.iter_mut().zip(p).zip(p0) {
                    *o += scale * (v - v0);
                }
            });
    }
}

/// Keeps every parameter where it renders finitely (the module documentation).
fn keep_in_box(params: &mut Params, extent: f64) {
    let reach = 1e4 * extent;
    let largest = (100.0 * extent).ln();
    let clamp = |p: &mut Params, g: Group, lo: f64, hi: f64| {
        p.group_mut(g).par_chunks_mut(CHUNK).for_each(|c| {
            for v in c {
                *v = if v.is_finite() { v.clamp(lo, hi) } else { 0.0 };
            }
        });
    };
    clamp(params, Group::Position, -reach, reach);
    clamp(params, Group::LogScale, LOG_SCALE_MIN, largest);
    clamp(params, Group::OpacityLogit, -LOGIT_LIMIT, LOGIT_LIMIT);
    clamp(params, Group::Color, 0.0, 1.0);
    clamp(params, Group::Rotation, -1.0, 1.0);
}

/// Densifies every keyframe alike: `c4g_optim::densify` decides on one representative row per
/// Gaussian (the first keyframe's, with its largest log scale and opacity logit over the
/// keyframes, so a Gaussian is pruned only when faint at every keyframe), its colour's first value
/// replaced by the Gaussian's index so every row it returns names its parent. A copy (kept or
/// cloned) takes its parent's rows at every keyframe; a split child takes them moved by the
/// child's offset and with the child's change of log scale.
fn densify_keyframes(fitting: &mut Fitting<'_>, config: &c4g_optim::DensifyConfig, seed: u64) {
    let params = &fitting.params;
    let (n, kf) = (params.gaussians(), params.keyframes());
    let mut proxy = Params::zeros(0);
    for i in 0..n {
        let mut row = params.params.row(params.row_index(i, 0));
        for k in 1..kf {
            let other = params.params.row(params.row_index(i, k));
            for j in 3..6 {
                row[j] = row[j].max(other[j]);
            }
            row[10] = row[10].max(other[10]);
        }
        row[11] = i as f64;
        proxy.push(&row);
    }
    let before = proxy.clone();
    let mut scratch = Adam::new(fitting.options.adam, n);
    densify(
        &mut proxy,
        &mut scratch,
        &mut fitting.stats,
        config,
        fitting.options.extent,
        seed,
    );
    let mut first_copy = vec![false; n];
    let mut rows = Params::zeros(0);
    let mut prior = Params::zeros(0);
    let mut added_prior = Params::zeros(0);
    let mut kept = Vec::new();
    let mut tied = Vec::with_capacity(proxy.len());
    let mut moving = Vec::with_capacity(proxy.len());
    for r in 0..proxy.len() {
        let out = proxy.row(r);
        let parent = out[11] as usize;
        tied.push(fitting.tied[parent]);
        moving.push(fitting.moving[parent]);
        let base = before.row(parent);
        let copy = out == base;
        let original = copy && !first_copy[parent];
        if original {
            first_copy[parent] = true;
            kept.push(parent);
        }
        for k in 0..kf {
            let at = params.row_index(parent, k);
            let mut row = params.params.row(at);
            for j in 0..6 {
                row[j] += out[j] - base[j];
            }
            rows.push(&row);
            if original {
                prior.push(&fitting.prior.row(at));
            } else {
                added_prior.push(&row);
            }
        }
    }
    // The originals come first in densify's output, in order: Adam keeps their moments and
    // starts every added row afresh; the prior holds new Gaussians where they were born.
    let keep: Vec<bool> = (0..n * kf).map(|r| first_copy[r / kf]).collect();
    fitting.adam.select(&keep);
    fitting.adam.extend(rows.len() - kept.len() * kf);
    for r in 0..added_prior.len() {
        prior.push(&added_prior.row(r));
    }
    fitting.prior = prior;
    fitting.params = KeyframeParams::from_rows(rows, kf);
    // A copy of a tied Gaussian is tied: its rows, moved alike, are still one value. Evidence
    // starts afresh.
    fitting.tied = tied;
    fitting.moving = moving;
    fitting.evidence = vec![Evidence::default(); fitting.params.params.len()];
}

/// Ties every Gaussian neither `tied` nor `moving` whose keyframe positions all lie in a ball as wide as its
/// tolerance ([`tolerance`]) around their mean (its whole motion spans no more): marks it and
/// makes its keyframes share one value ([`share`]).
/// With one keyframe every Gaussian is static. Returns how many it tied.
fn tie_static(
    params: &mut KeyframeParams,
    tied: &mut [bool],
    moving: &[bool],
    view: &Camera,
    options: &FitOptions,
) -> usize {
    let mut count = 0;
    for (i, t) in tied.iter_mut().enumerate() {
        if *t || moving[i] {
            continue;
        }
        let (mean, farthest) = spread(params, i);
        if 2.0 * farthest <= tolerance(view, options, mean) {
            *t = true;
            share(params, i);
            count += 1;
        }
    }
    count
}

/// How far a Gaussian's keyframe positions (mean `mean`) may stray for it to be static:
/// [`FitOptions::static_pixels`] pixels at its depth as `view` sees it, at least
/// [`FitOptions::static_tolerance`].
fn tolerance(view: &Camera, options: &FitOptions, mean: [f64; 3]) -> f64 {
    let floor = options.static_tolerance;
    if options.static_pixels <= 0.0 {
        return floor;
    }
    let p = glam::Vec3::new(mean[0] as f32, mean[1] as f32, mean[2] as f32);
    let depth = f64::from(view.to_camera(p).z.abs());
    let k = view.intrinsics();
    let focal = f64::from(k.fx.max(k.fy));
    if focal > 0.0 && depth.is_finite() {
        floor.max(options.static_pixels * depth / focal)
    } else {
        floor
    }
}

/// Gaussian `i`'s mean keyframe position and the farthest any keyframe strays from it.
fn spread(params: &KeyframeParams, i: usize) -> ([f64; 3], f64) {
    let kf = params.keyframes();
    let mean: [f64; 3] = std::array::from_fn(|j| {
        (0..kf)
            .map(|k| params.value(Group::Position, i, k, j))
            .sum::<f64>()
            / kf as f64
    });
    let farthest = (0..kf)
        .map(|k| {
            (0..3)
                .map(|j| (params.value(Group::Position, i, k, j) - mean[j]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .fold(0.0, f64::max);
    (mean, farthest)
}

/// Gaussian `i`'s keyframes as one value ([`share_rows`] in every group).
fn share(params: &mut KeyframeParams, i: usize) {
    let kf = params.keyframes();
    for group in Group::ALL {
        let w = group.width();
        let rows = &mut params.params.group_mut(group)[i * kf * w..(i + 1) * kf * w];
        share_rows(group, rows, kf);
    }
}

/// One Gaussian's `kf` keyframe rows of `group` (`rows`, keyframe-major) replaced by their mean
/// (quaternions first turned to keyframe 0's side, the mean renormalised); written as
/// `x₀ + mean(x_k − x₀)` so values already equal stay bit for bit.
fn share_rows(group: Group, rows: &mut [f64], kf: usize) {
    let w = group.width();
    if group == Group::Rotation {
        for k in 1..kf {
            let dot: f64 = (0..4).map(|j| rows[j] * rows[k * w + j]).sum();
            if dot < 0.0 {
                rows[k * w..k * w + w].iter_mut().for_each(|v| *v *= -1.0);
            }
        }
    }
    for j in 0..w {
        let x0 = rows[j];
        let mean = x0 + (0..kf).map(|k| rows[k * w + j] - x0).sum::<f64>() / kf as f64;
        for k in 0..kf {
            rows[k * w + j] = mean;
        }
    }
    if group == Group::Rotation {
        let norm = (0..4).map(|j| rows[j].powi(2)).sum::<f64>().sqrt();
        if norm > 0.0 && (norm - 1.0).abs() > 1e-12 {
            rows.iter_mut().for_each(|v| *v /= norm);
        }
    }
}

/// Gaussians identical at every keyframe.
fn exactly_static(params: &KeyframeParams) -> Vec<bool> {
    let kf = params.keyframes();
    (0..params.gaussians())
        .map(|i| {
            let first = params.params.row(params.row_index(i, 0));
            (1..kf).all(|k| params.params.row(params.row_index(i, k)) == first)
        })
        .collect()
}

/// splitmix64: the frame order and densification seeds.
struct SplitMix(u64);

impl SplitMix {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Fisher–Yates.
    fn shuffle(&mut self, v: &mut [usize]) {
        for i in (1..v.len()).rev() {
            let j = (self.next_u64() % (i as u64 + 1)) as usize;
            v.swap(i, j);
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use c4g_scene::Intrinsics;

    fn view() -> Camera {
        let k = Intrinsics {
            fx: 40.0,
            fy: 40.0,
            cx: 20.0,
            cy: 20.0,
            width: 40,
            height: 40,
        };
        Camera::from_world_to_camera_matrix(k, Default::default()).unwrap()
    }

    #[test]
    fn every_nth_frame_is_held_out() {
        assert_eq!(holdout_frames(20, 8), vec![7, 15]);
        assert_eq!(holdout_frames(1, 8), Vec::<usize>::new());
        assert!(holdout_frames(5, 0).is_empty());
    }

    /// Gaussian 0 is small (cloned), 1 large (split), 2 faint at one keyframe only (kept: pruning
    /// needs it faint at every keyframe), 3 faint at both (pruned). Every keyframe follows the
    /// same decisions: a clone repeats its parent's rows, a split child's rows are its parent's
    /// moved by one offset with scales divided by 1.6, at every keyframe.
    #[test]
    fn densification_acts_alike_on_every_keyframe() {
        let set = |shift: f32, faint: [f32; 2]| {
            GaussianSet::new(
                vec![
                    [shift, 0.0, 2.0],
                    [0.1, shift, 2.0],
                    [0.2, 0.0, 2.0],
                    [0.3, 0.0, 2.0],
                ],
                vec![[0.001; 3], [0.5; 3], [0.001; 3], [0.001; 3]],
                vec![[1.0, 0.0, 0.0, 0.0]; 4],
                vec![0.5, 0.5, faint[0], faint[1]],
                vec![[0.2, 0.4, 0.6]; 4],
            )
            .unwrap()
        };
        let start = FittedScene::new(vec![
            (0.0, set(0.0, [0.5, 0.001])),
            (1.0, set(0.3, [0.001, 0.001])),
        ])
        .unwrap();
        let options = FitOptions::default();
        let mut fitting = Fitting::new(&start, &options, &view()).unwrap();
        fitting.stats.accumulate(
            &[[1e-5, 0.0], [1e-5, 0.0], [0.0, 0.0], [0.0, 0.0]],
            128,
            128,
        );
        let config = c4g_optim::DensifyConfig::default();
        densify_keyframes(&mut fitting, &config, 5);
        let p = &fitting.params;
        assert_eq!(
            (p.gaussians(), p.keyframes()),
            (5, 2),
            "0, 2, clone of 0, two children of 1"
        );
        assert_eq!((fitting.adam.len(), fitting.prior.len()), (10, 10));
        let row = |i: usize, k: usize| p.params.row(p.row_index(i, k));
        let before = KeyframeParams::from_sets(&start.sets).unwrap();
        let parent = |i: usize, k: usize| before.params.row(before.row_index(i, k));
        for k in 0..2 {
            assert_eq!(row(0, k), parent(0, k));
            assert_eq!(row(1, k), parent(2, k));
            assert_eq!(row(2, k), parent(0, k), "the clone");
        }
        for child in [3, 4] {
            let offset: Vec<f64> = (0..3).map(|j| row(child, 0)[j] - parent(1, 0)[j]).collect();
            for k in 0..2 {
                for (j, expected) in offset.iter().enumerate() {
                    let moved = row(child, k)[j] - parent(1, k)[j];
                    assert!(
                        (moved - expected).abs() < 1e-12,
                        "one offset at every keyframe"
                    );
                    let scale = (row(child, k)[3 + j] - parent(1, k)[3 + j]).exp();
                    assert!((scale - 1.0 / 1.6).abs() < 1e-12);
                }
                assert_eq!(row(child, k)[6..], parent(1, k)[6..]);
            }
        }
    }

    /// The set a step renders, built from the keyframes around `t` alone, is the whole track's
    /// `at(t)` bit for bit, at keyframe times, inside the first and last intervals and between.
    #[test]
    fn the_set_a_step_renders_is_the_whole_tracks_bit_for_bit() {
        let times = [0.0, 0.2, 0.5, 0.6, 0.9, 1.0];
        let sets: Vec<GaussianSet> = (0..times.len())
            .map(|k| {
                let x = (k as f32 * 0.7).sin();
                GaussianSet::new(
                    vec![[x, x * x, 2.0 + 0.1 * k as f32], [0.5, -x, 3.0]],
                    vec![[0.1 + 0.01 * k as f32; 3]; 2],
                    vec![[1.0, 0.1 * x, 0.0, 0.0]; 2],
                    vec![0.5, 0.2 + 0.1 * k as f32],
                    vec![[0.5, x.abs(), 0.1]; 2],
                )
                .unwrap()
            })
            .collect();
        let start = FittedScene::new(times.iter().copied().zip(sets).collect()).unwrap();
        let options = FitOptions::default();
        let fitting = Fitting::new(&start, &options, &view()).unwrap();
        let whole = fitting.scene(start.times.clone(), false);
        for t in [0.0, 0.05, 0.2, 0.33, 0.55, 0.6, 0.75, 0.95, 1.0] {
            assert_eq!(fitting.set_at(t).unwrap(), whole.at(t).unwrap(), "t = {t}");
        }
        assert!(fitting.set_at(1.1).is_err());
    }

    /// The smoothness gradient against central differences of its energy (quadratic: exact up to
    /// rounding, so 1e-9).
    #[test]
    fn the_smoothness_gradient_matches_finite_differences() {
        let times = [0.0, 0.2, 0.5, 0.6, 1.0];
        let sets: Vec<GaussianSet> = (0..5)
            .map(|k| {
                let x = (k as f32 * 1.3).sin();
                GaussianSet::new(
                    vec![[x, x * x, 1.0 + 0.1 * k as f32], [0.5, -x, 2.0]],
                    vec![[0.1; 3]; 2],
                    vec![[1.0, 0.0, 0.0, 0.0]; 2],
                    vec![0.5; 2],
                    vec![[0.5; 3]; 2],
                )
                .unwrap()
            })
            .collect();
        let params = KeyframeParams::from_sets(&sets).unwrap();
        let energy = |p: &KeyframeParams| {
            let h: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
            let mean_h = h.iter().sum::<f64>() / 4.0;
            let mut e = 0.0;
            for i in 0..2 {
                for j in 0..3 {
                    let x = |k: usize| p.value(Group::Position, i, k, j);
                    for k in 1..4 {
                        let a = mean_h * ((x(k + 1) - x(k)) / h[k] - (x(k) - x(k - 1)) / h[k - 1]);
                        e += 0.3 / 2.0 * a * a;
                    }
                }
            }
            e
        };
        let mut g = zeros_like(&params);
        add_smoothness(&params, &times, 0.3, &mut g);
        for at in 0..params.params.group(Group::Position).len() {
            let eval = |d: f64| {
                let mut p = params.clone();
                p.params.group_mut(Group::Position)[at] += d;
                energy(&p)
            };
            let numeric = (eval(1e-5) - eval(-1e-5)) / 2e-5;
            let a = g.params.group(Group::Position)[at];
            assert!((a - numeric).abs() < 1e-9, "{at}: {a} against {numeric}");
        }
    }
}
