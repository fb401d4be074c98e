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
//! shared and never exceeds [`FitOptions::max_gaussians`]. At the end, Gaussians whose keyframe
//! positions stay within [`FitOptions::static_tolerance`] of the first keyframe's share one value.
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
use c4g_scene::Camera;

use crate::backward::{Blend, chain};
use crate::error::FitError;
use crate::keyframe_params::KeyframeParams;
use crate::scene::FittedScene;

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
    /// A Gaussian whose keyframe positions all stay within this distance (scene units) of its
    /// first keyframe's is static.
    pub static_tolerance: f64,
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
            eval_every: 0,
            densify: None,
            extent: 1.0,
            clip_norm: None,
            time_budget: None,
            render: RenderOptions {
                features: false,
                ..RenderOptions::default()
            },
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
    let score =
        |scene: &FittedScene, which: &[usize]| mean_psnr(&raster, scene, frames, which, options);
    let holdout_psnr_before = score(start, &holdout)?;
    let mut fitting = Fitting::new(start, options)?;
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
        let loss = fitting.step(&raster, &frames[index], step, &mut rng)?;
        let scored = options.eval_every > 0 && (step + 1).is_multiple_of(options.eval_every);
        let holdout_psnr = if scored {
            score(&fitting.scene(start.times.clone(), false), &holdout)?
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
        holdout_psnr_after: score(&scene, &holdout)?,
        train_psnr_after: score(&scene, &train)?.unwrap_or(f64::NAN),
        holdout_frames: holdout,
        curve,
        stopped,
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
        let image = raster.render(&track.at(f.time)?, &f.camera, &options.render)?;
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
}

impl<'o> Fitting<'o> {
    fn new(start: &FittedScene, options: &'o FitOptions) -> Result<Self, FitError> {
        let params = KeyframeParams::from_sets(&start.sets)?;
        Ok(Self {
            prior: params.params.clone(),
            adam: Adam::new(options.adam, params.params.len()),
            stats: DensifyStats::new(params.gaussians()),
            params,
            times: start.times.clone(),
            options,
        })
    }

    /// One step on `frame`; returns its photometric loss.
    fn step(
        &mut self,
        raster: &CpuRasterizer,
        frame: &Frame,
        step: u64,
        rng: &mut SplitMix,
    ) -> Result<f64, FitError> {
        let o = self.options;
        let scene = self.scene(self.times.clone(), false);
        let set = scene.at(frame.time)?;
        let (w, h) = (frame.camera.width(), frame.camera.height());
        let (image, saved) = raster.render_saved(&set, &frame.camera, &o.render)?;
        // SSIM's window needs 11×11 pixels: a smaller frame is scored by L1 alone.
        let small = (w as usize) < SSIM_WINDOW || (h as usize) < SSIM_WINDOW;
        let lambda = if small { 0.0 } else { o.lambda_dssim };
        let loss = l1_dssim(&image.rgb, &frame.rgb, w, h, lambda)?;
        let grads = raster.backward(
            &saved,
            &RenderGradients::rgb(&loss.gradient),
            BackwardOptions::default(),
        )?;
        self.stats.accumulate(&grads.gaussians.means2d, w, h);
        let mut g = zeros_like(&self.params);
        let blend = Blend::new(&self.times, frame.time)?;
        chain(&blend, &self.params, &set, &grads.gaussians, &mut g);
        add_smoothness(&self.params, &self.times, o.smoothness, &mut g);
        let fade = if o.prior_fade_steps == 0 {
            0.0
        } else {
            (1.0 - step as f64 / o.prior_fade_steps as f64).max(0.0)
        };
        add_prior(&self.params, &self.prior, o.prior * fade, &mut g);
        for group in Group::ALL {
            for v in g.params.group_mut(group) {
                if !v.is_finite() {
                    *v = 0.0;
                }
            }
        }
        if let Some(max) = o.clip_norm {
            g.params.clip_norm(max);
        }
        self.adam
            .step(&mut self.params.params, &g.params, o.rates.at(step))?;
        self.params.params.normalize_rotations();
        keep_in_box(&mut self.params.params, o.extent);
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
        Ok(loss.value)
    }

    /// The scene as fitted so far; `finish` makes the static Gaussians share one value.
    fn scene(&self, times: Vec<f64>, finish: bool) -> FittedScene {
        let mut params = self.params.clone();
        let static_mask = if finish {
            share_static(&mut params, self.options.static_tolerance)
        } else {
            vec![false; params.gaussians()]
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
    for i in 0..n {
        for j in 0..3 {
            let p = |key: usize| params.value(Group::Position, i, key, j);
            for key in 1..k - 1 {
                let (hl, hr) = (h[key - 1], h[key]);
                let a = mean_h * ((p(key + 1) - p(key)) / hr - (p(key) - p(key - 1)) / hl);
                let c = scale * a * mean_h;
                *out.value_mut(Group::Position, i, key + 1, j) += c / hr;
                *out.value_mut(Group::Position, i, key, j) -= c * (1.0 / hr + 1.0 / hl);
                *out.value_mut(Group::Position, i, key - 1, j) += c / hl;
            }
        }
    }
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
        for ((o, v), v0) in out.params.group_mut(g).iter_mut().zip(p).zip(p0) {
            *o += scale * (v - v0);
        }
    }
}

/// Keeps every parameter where it renders finitely (the module documentation).
fn keep_in_box(params: &mut Params, extent: f64) {
    let reach = 1e4 * extent;
    let largest = (100.0 * extent).ln();
    let clamp = |p: &mut Params, g: Group, lo: f64, hi: f64| {
        for v in p.group_mut(g) {
            *v = if v.is_finite() { v.clamp(lo, hi) } else { 0.0 };
        }
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
    for r in 0..proxy.len() {
        let out = proxy.row(r);
        let parent = out[11] as usize;
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
}

/// Marks (and makes share one value) the Gaussians whose positions stay within `tolerance` of the
/// first keyframe's; with one keyframe every Gaussian is static.
fn share_static(params: &mut KeyframeParams, tolerance: f64) -> Vec<bool> {
    let (n, kf) = (params.gaussians(), params.keyframes());
    let mut mask = vec![false; n];
    for (i, m) in mask.iter_mut().enumerate() {
        let moved = (1..kf).map(|k| distance(params, i, k)).fold(0.0, f64::max);
        if moved <= tolerance {
            *m = true;
            share(params, i);
        }
    }
    mask
}

fn distance(params: &KeyframeParams, i: usize, k: usize) -> f64 {
    (0..3)
        .map(|j| params.value(Group::Position, i, k, j) - params.value(Group::Position, i, 0, j))
        .map(|d| d * d)
        .sum::<f64>()
        .sqrt()
}

/// Gaussian `i`'s keyframe values replaced by their mean (quaternions on keyframe 0's side,
/// renormalised); written as `x₀ + mean(x_k − x₀)` so values already equal stay bit for bit.
fn share(params: &mut KeyframeParams, i: usize) {
    let kf = params.keyframes();
    let q0: Vec<f64> = (0..4)
        .map(|j| params.value(Group::Rotation, i, 0, j))
        .collect();
    for k in 1..kf {
        let dot: f64 = (0..4)
            .map(|j| q0[j] * params.value(Group::Rotation, i, k, j))
            .sum();
        if dot < 0.0 {
            for j in 0..4 {
                *params.value_mut(Group::Rotation, i, k, j) *= -1.0;
            }
        }
    }
    for g in Group::ALL {
        for j in 0..g.width() {
            let x0 = params.value(g, i, 0, j);
            let mean = x0 + (0..kf).map(|k| params.value(g, i, k, j) - x0).sum::<f64>() / kf as f64;
            for k in 0..kf {
                *params.value_mut(g, i, k, j) = mean;
            }
        }
    }
    let norm = (0..4)
        .map(|j| params.value(Group::Rotation, i, 0, j).powi(2))
        .sum::<f64>()
        .sqrt();
    if norm > 0.0 && (norm - 1.0).abs() > 1e-12 {
        for k in 0..kf {
            for j in 0..4 {
                *params.value_mut(Group::Rotation, i, k, j) /= norm;
            }
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
    use c4g_scene::GaussianSet;

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
        let mut fitting = Fitting::new(&start, &options).unwrap();
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
