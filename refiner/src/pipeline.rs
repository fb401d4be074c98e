//! The refinement pipeline: video and mask in, refined video out.
//!
//! One [`Pipeline::refine`] run is:
//! 1. frames `[H, W, 3]` in [0, 1] → video `[3, F, H, W]` in [-1, 1];
//! 2. the control tensor (`control`): the video split by the mask, both halves VAE-encoded and
//!    normalised, plus the unshuffled mask;
//! 3. noise (seeded, or given) denoised over the schedule: each step one transformer run
//!    (two with classifier-free guidance: `v = v_u + g·(v_c − v_u)`), then the sampler;
//! 4. the final latents un-normalised and VAE-decoded, back to frames in [0, 1].
//!
//! In C4G's layout (`layout`) step 2 encodes each keyframe alone and the rendered frames, padded,
//! as one chunk; every transformer run gets the latent frames' temporal positions; and step 4
//! decodes the rendered part only.
//!
//! The graphs' sessions are created once at [`Pipeline::load`], the transformer's with the LoRA
//! already merged into its weights.

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use c4g_runtime::{Graph, RuntimeError, SessionOptions, create_session};
use ort::value::TensorRef;

use crate::control::{self, LatentStats, Mask};
use crate::layout::{self, Keyframe};
use crate::lora::{Lora, LoraSpec};
use crate::noise::gaussian_noise;
use crate::onnx::OnnxWeights;
use crate::package::{KeyframeLayout, Layout, RefinerManifest, RefinerPackage};
use crate::sampler::{Sampler, Schedule, Solver};
use crate::text::TextEncoder;
use crate::weights_session::create_session_with_lora;
use crate::{RefinerError, Result};

/// How a [`Pipeline`] is built.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PipelineOptions {
    /// A LoRA merged into the transformer at load.
    pub lora: Option<LoraSpec>,
    /// Where the merge writes its copy of the transformer's external data (the system's
    /// temporary folder when `None`): it needs room for that data (8.6 GB at the 1.3B size in
    /// f32) until the worker has started, and on a RAM-backed file system that room is memory.
    pub merge_dir: Option<PathBuf>,
    /// How the graphs' sessions are configured: threads, execution provider, CPU arena.
    pub session: SessionOptions,
    /// Leave the package's text encoder unloaded (umT5-XXL is ~23 GB): prompts must then come
    /// as precomputed embeddings.
    pub skip_text_encoder: bool,
}

/// One refinement.
#[derive(Debug, Clone, PartialEq)]
pub struct RefineRequest {
    /// `F` frames, each `[H, W, 3]` RGB in [0, 1], row-major: context frames first, then the
    /// rendered frames to regenerate. In C4G's layout: the rendered frames only, 1 to `F` (padded
    /// by repeating the last).
    pub video: Vec<Vec<f32>>,
    /// Which frames (or pixels) to regenerate; in C4G's layout every rendered frame.
    pub mask: Mask,
    /// C4G's layout: the keyframes, as many as the package has slots (empty in VACE's).
    pub keyframes: Vec<Keyframe>,
    /// The prompt's text embedding, `[L, D]` (zero-padded to L tokens).
    pub text_embeddings: Vec<f32>,
    /// The negative prompt's embedding, `[L, D]`; needed when `guidance != 1`.
    pub negative_embeddings: Option<Vec<f32>>,
    /// Denoising steps.
    pub steps: usize,
    /// Timestep shift of the schedule.
    pub shift: f64,
    /// Classifier-free guidance scale: any value but 1 runs the transformer twice per step
    /// (diffusers skips guidance for every value ≤ 1; we apply the formula as given).
    pub guidance: f32,
    /// Scale of the VACE hints, the same for every VACE layer.
    pub control_scale: f32,
    /// The solver, on the schedule the reference pipeline gives it
    /// ([`Schedule::for_sampler`]).
    pub sampler: Sampler,
    /// Seed of the initial noise (see [`gaussian_noise`](crate::gaussian_noise)).
    pub seed: u64,
    /// Initial noise `[16, F', h, w]` to use instead of the seeded noise.
    pub initial_noise: Option<Vec<f32>>,
}

impl RefineRequest {
    /// A request with the reference pipeline's defaults: 30 UniPC steps, shift 3, guidance 5,
    /// control scale 1, seed 0.
    pub fn new(video: Vec<Vec<f32>>, mask: Mask, text_embeddings: Vec<f32>) -> Self {
        Self {
            video,
            mask,
            keyframes: Vec::new(),
            text_embeddings,
            negative_embeddings: None,
            steps: 30,
            shift: 3.0,
            guidance: 5.0,
            control_scale: 1.0,
            sampler: Sampler::UniPc,
            seed: 0,
            initial_noise: None,
        }
    }

    /// A request in C4G's layout (`keyframes`, then `rendered` frames to regenerate), with the
    /// layout's sampler defaults: DiffSynth's Euler and the steps, shift and guidance `layout`
    /// declares (the public code's 50, 5 and 5).
    pub fn keyframed(
        layout: &KeyframeLayout,
        keyframes: Vec<Keyframe>,
        rendered: Vec<Vec<f32>>,
        text_embeddings: Vec<f32>,
    ) -> Self {
        let mask = Mask::Frames(vec![true; rendered.len()]);
        let defaults = &layout.sampler;
        Self {
            keyframes,
            steps: defaults.steps,
            shift: defaults.shift,
            guidance: defaults.guidance_scale,
            sampler: Sampler::DiffSynthEuler,
            ..Self::new(rendered, mask, text_embeddings)
        }
    }

    fn uses_guidance(&self) -> bool {
        self.guidance != 1.0
    }
}

/// What a refinement returns.
#[derive(Debug, Clone, PartialEq)]
pub struct RefineOutput {
    /// The refined frames, each `[H, W, 3]` RGB in [0, 1]: all `F` in VACE's layout, the
    /// rendered frames given (padding dropped) in C4G's.
    pub frames: Vec<Vec<f32>>,
    /// The final normalised latents `[16, F', h, w]`, before the VAE decoder (keyframe slots
    /// included in C4G's layout).
    pub latents: Vec<f32>,
}

/// A loaded package: three graphs (four with the text encoder) and the latent statistics.
pub struct Pipeline {
    package: RefinerPackage,
    stats: LatentStats,
    transformer: Graph,
    vae_encoder: Graph,
    vae_decoder: Graph,
    /// C4G's layout: the one-frame encoder of keyframes.
    vae_frame_encoder: Option<Graph>,
    /// Whether the transformer takes temporal positions (graphs exported before they did: no).
    positions_input: bool,
    text_encoder: Option<TextEncoder>,
    merged_weights: usize,
}

impl std::fmt::Debug for Pipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pipeline")
            .field("package", &self.package.dir())
            .field("merged_weights", &self.merged_weights)
            .finish_non_exhaustive()
    }
}

impl Pipeline {
    /// Opens the package in `dir`, merges the LoRA (if any) and creates the sessions.
    ///
    /// Fails naming the key when a LoRA tensor cannot be placed on the transformer.
    pub fn load(dir: impl AsRef<Path>, options: &PipelineOptions) -> Result<Self> {
        let package = RefinerPackage::open(dir)?;
        let m = package.manifest();
        let stats = LatentStats::new(m.latent.mean.clone(), &m.latent.std)?;
        let session = &options.session;
        let transformer_path = package.transformer_path();
        let (transformer, merged) = match &options.lora {
            Some(spec) => {
                let lora = Lora::load(&spec.path)?;
                let weights = OnnxWeights::open(&transformer_path)?;
                create_session_with_lora(
                    &transformer_path,
                    session,
                    &weights,
                    &lora,
                    spec.scale,
                    options.merge_dir.as_deref(),
                )?
            }
            None => (create_session(&transformer_path, session)?, 0),
        };
        let positions_input = transformer.inputs().iter().any(|i| i.name() == "positions");
        if matches!(m.layout, Layout::C4g(_)) && !positions_input {
            return Err(RefinerError::InvalidPackage {
                dir: package.dir().to_path_buf(),
                reason: "the c4g layout needs a transformer with a `positions` input (re-export it with c4g.wan.export)".to_owned(),
            });
        }
        let vae_encoder = create_session(&package.vae_encoder_path(), session)?;
        let vae_decoder = create_session(&package.vae_decoder_path(), session)?;
        let vae_frame_encoder = package
            .vae_frame_encoder_path()
            .map(|path| create_session(&path, session))
            .transpose()?
            .map(|s| Graph::new("VAE frame encoder", s));
        let text_encoder = match package.text_encoder_paths() {
            Some((tokenizer, graph)) if !options.skip_text_encoder => Some(TextEncoder::load(
                &tokenizer,
                &graph,
                m.text.tokens,
                m.text.dim,
                session,
            )?),
            _ => None,
        };
        Ok(Self {
            package,
            stats,
            transformer: Graph::new("transformer", transformer),
            vae_encoder: Graph::new("VAE encoder", vae_encoder),
            vae_decoder: Graph::new("VAE decoder", vae_decoder),
            vae_frame_encoder,
            positions_input,
            text_encoder,
            merged_weights: merged,
        })
    }

    /// The package.
    pub fn package(&self) -> &RefinerPackage {
        &self.package
    }

    /// The package's manifest.
    pub fn manifest(&self) -> &RefinerManifest {
        self.package.manifest()
    }

    /// The text encoder, when the package has one and it was loaded.
    pub fn text_encoder(&self) -> Option<&TextEncoder> {
        self.text_encoder.as_ref()
    }

    /// A caption's prompt embedding `[L, D]`; an error naming the way out when this pipeline has
    /// no text encoder.
    pub fn embed_caption(&self, caption: &str) -> Result<Vec<f32>> {
        self.text_encoder
            .as_ref()
            .ok_or_else(|| {
                RefinerError::InvalidRequest(
                    "this refiner has no text encoder (its package has none, or it was started without one): send a precomputed text embedding instead of a caption".to_owned(),
                )
            })?
            .embed(caption)
    }

    /// How many transformer weights the LoRA replaced (0 without a LoRA or at scale 0).
    pub fn merged_weight_count(&self) -> usize {
        self.merged_weights
    }

    /// Refines `request.video`, calling `progress(done, total)` with `done = 0` once the control
    /// input is ready and after each denoising step; `ControlFlow::Break` stops the run with
    /// [`RefinerError::Cancelled`].
    pub fn refine(
        &self,
        request: &RefineRequest,
        progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    ) -> Result<RefineOutput> {
        self.check_request(request)?;
        let schedule = Schedule::for_sampler(request.sampler, request.steps, request.shift)?;
        let total = schedule.steps();
        let (control, positions) = match &self.manifest().layout {
            Layout::Vace => (
                self.control(&request.video, &request.mask)?,
                self.default_positions(),
            ),
            Layout::C4g(k) => (
                self.keyframe_control(&request.keyframes, &request.video)?,
                layout::positions(k, &request.keyframes, self.manifest().video_latent_frames())?,
            ),
        };
        if progress(0, total).is_break() {
            return Err(RefinerError::Cancelled {
                completed: 0,
                total,
            });
        }
        let mut latents = match &request.initial_noise {
            Some(noise) => noise.clone(),
            None => gaussian_noise(request.seed, self.manifest().latent_len()),
        };
        let scales = vec![request.control_scale; self.manifest().vace_layers.len()];
        let timesteps = schedule.timesteps().to_vec();
        let mut solver = Solver::new(request.sampler, schedule);
        for (i, &t) in timesteps.iter().enumerate() {
            let velocity =
                self.guided_velocity(request, &latents, t, &control, &scales, &positions)?;
            latents = solver.step(&velocity, &latents)?;
            if progress(i + 1, total).is_break() {
                return Err(RefinerError::Cancelled {
                    completed: i + 1,
                    total,
                });
            }
        }
        let mut frames = self.decode(&latents)?;
        if matches!(self.manifest().layout, Layout::C4g(_)) {
            frames.truncate(request.video.len());
        }
        Ok(RefineOutput { frames, latents })
    }

    /// `v_u + g·(v_c − v_u)`, or just `v_c` at `g = 1`.
    fn guided_velocity(
        &self,
        request: &RefineRequest,
        latents: &[f32],
        timestep: f32,
        control: &[f32],
        scales: &[f32],
        positions: &[i64],
    ) -> Result<Vec<f32>> {
        let velocity =
            |text: &[f32]| self.velocity_at(latents, timestep, text, control, scales, positions);
        let cond = velocity(&request.text_embeddings)?;
        let Some(negative) = request
            .negative_embeddings
            .as_deref()
            .filter(|_| request.uses_guidance())
        else {
            return Ok(cond);
        };
        let uncond = velocity(negative)?;
        let g = request.guidance;
        Ok(uncond
            .iter()
            .zip(&cond)
            .map(|(&u, &c)| u + g * (c - u))
            .collect())
    }

    /// The `[96, F', h, w]` control tensor for `video` (frames `[H, W, 3]` in [0, 1]) and `mask`.
    pub fn control(&self, video: &[Vec<f32>], mask: &Mask) -> Result<Vec<f32>> {
        let m = self.manifest();
        let (f, h, w) = (m.frames, m.height, m.width);
        let video = to_model_video(video, f, h, w)?;
        let mask = mask.to_pixels(f, h, w)?;
        let (inactive, reactive) = control::split_video(&video, &mask);
        let mut inactive = self.vae_encode(&inactive)?;
        let mut reactive = self.vae_encode(&reactive)?;
        self.stats.normalize(&mut inactive);
        self.stats.normalize(&mut reactive);
        let mask = control::latent_mask(&mask, f, h, w);
        Ok(control::assemble(&inactive, &reactive, &mask))
    }

    /// C4G's layout: the `[96, K + R, h, w]` control tensor for `keyframes` and the `rendered`
    /// frames (`[H, W, 3]` in [0, 1]). Each keyframe goes through the one-frame encoder (its mask
    /// is 0, so its reactive half is a blank frame's encoding); the rendered frames, padded to
    /// `F`, go through the chunk encoder with a mask of 1. Keyframe slots come first.
    pub fn keyframe_control(
        &self,
        keyframes: &[Keyframe],
        rendered: &[Vec<f32>],
    ) -> Result<Vec<f32>> {
        let m = self.manifest();
        let (f, h, w) = (m.frames, m.height, m.width);
        let padded = layout::pad_rendered(rendered, f)?;
        let video = to_model_video(&padded, f, h, w)?;
        let ones = vec![1.0; f * h * w];
        let (inactive, reactive) = control::split_video(&video, &ones);
        let encode = |x: &[f32]| -> Result<Vec<f32>> {
            let mut latents = self.vae_encode(x)?;
            self.stats.normalize(&mut latents);
            Ok(latents)
        };
        let encode_frame = |x: &[f32]| -> Result<Vec<f32>> {
            let mut latents = self.vae_encode_frame(x)?;
            self.stats.normalize(&mut latents);
            Ok(latents)
        };
        let blank = encode_frame(&vec![0.0; 3 * h * w])?;
        let mut inactive_parts = Vec::with_capacity(keyframes.len() + 1);
        for (i, k) in keyframes.iter().enumerate() {
            let frame = to_model_video(std::slice::from_ref(&k.frame), 1, h, w)
                .map_err(|e| RefinerError::InvalidRequest(format!("keyframe {i}: {e}")))?;
            inactive_parts.push(encode_frame(&frame)?);
        }
        let r = m.video_latent_frames();
        let mut frames_of = vec![1; keyframes.len()];
        frames_of.push(r);
        inactive_parts.push(encode(&inactive)?);
        let mut reactive_parts = vec![blank; keyframes.len()];
        reactive_parts.push(encode(&reactive)?);
        let plane = m.latent.height * m.latent.width;
        let channels = control::LATENT_CHANNELS;
        let inactive = control::concat_frames(&inactive_parts, &frames_of, channels, plane);
        let reactive = control::concat_frames(&reactive_parts, &frames_of, channels, plane);
        let mask = control::concat_frames(
            &[
                vec![0.0; control::MASK_CHANNELS * keyframes.len() * plane],
                control::latent_mask(&ones, f, h, w),
            ],
            &[keyframes.len(), r],
            control::MASK_CHANNELS,
            plane,
        );
        Ok(control::assemble(&inactive, &reactive, &mask))
    }

    /// VAE-encodes one frame `[3, 1, H, W]` in [-1, 1] to its un-normalised latent frame
    /// `[16, 1, h, w]` (C4G's layout; an error for a package without the frame encoder).
    pub fn vae_encode_frame(&self, frame: &[f32]) -> Result<Vec<f32>> {
        let m = self.manifest();
        let encoder = self.vae_frame_encoder.as_ref().ok_or_else(|| {
            RefinerError::InvalidRequest("this package has no one-frame VAE encoder".to_owned())
        })?;
        let shape = [1, 3, 1, m.height, m.width];
        check_len("frame", frame.len(), &shape)?;
        let input = tensor("video", &shape, frame)?;
        let latent_shape = [1, m.latent.channels, 1, m.latent.height, m.latent.width];
        Ok(encoder.run(ort::inputs!["video" => input], |outputs| {
            Ok(outputs.f32("latents", &latent_shape)?.to_vec())
        })?)
    }

    /// VAE-encodes a `[3, F, H, W]` video in [-1, 1] to un-normalised latents `[16, F', h, w]`
    /// (the posterior mode; `F'` the video's latent frames).
    pub fn vae_encode(&self, video: &[f32]) -> Result<Vec<f32>> {
        let m = self.manifest();
        let shape = [1, 3, m.frames, m.height, m.width];
        check_len("video", video.len(), &shape)?;
        let input = tensor("video", &shape, video)?;
        let latent_shape = self.video_latent_shape();
        Ok(self
            .vae_encoder
            .run(ort::inputs!["video" => input], |outputs| {
                Ok(outputs.f32("latents", &latent_shape)?.to_vec())
            })?)
    }

    /// One transformer run: the velocity at `latents` (normalised, `[16, F', h, w]`) and
    /// `timestep`, for one text embedding `[L, D]`, the control tensor and one scale per VACE
    /// layer, at temporal positions 0..F' (VACE's layout).
    pub fn velocity(
        &self,
        latents: &[f32],
        timestep: f32,
        text_embeddings: &[f32],
        control: &[f32],
        control_scales: &[f32],
    ) -> Result<Vec<f32>> {
        let positions = self.default_positions();
        self.velocity_at(
            latents,
            timestep,
            text_embeddings,
            control,
            control_scales,
            &positions,
        )
    }

    /// [`velocity`](Self::velocity) with each latent frame's temporal position given (C4G's
    /// layout); a transformer without a `positions` input takes only 0..F'.
    pub fn velocity_at(
        &self,
        latents: &[f32],
        timestep: f32,
        text_embeddings: &[f32],
        control: &[f32],
        control_scales: &[f32],
        positions: &[i64],
    ) -> Result<Vec<f32>> {
        let m = self.manifest();
        let latent_shape = self.latent_shape();
        let text_shape = [1, m.text.tokens, m.text.dim];
        let l = &m.latent;
        let control_shape = [1, control::CONTROL_CHANNELS, l.frames, l.height, l.width];
        let scale_shape = [m.vace_layers.len()];
        check_len("latents", latents.len(), &latent_shape)?;
        check_len("text embedding", text_embeddings.len(), &text_shape)?;
        check_len("control", control.len(), &control_shape)?;
        check_len("control scales", control_scales.len(), &scale_shape)?;
        if positions.len() != l.frames {
            return Err(RefinerError::InvalidRequest(format!(
                "{} temporal positions for {} latent frames",
                positions.len(),
                l.frames
            )));
        }
        let timestep = [timestep];
        let mut inputs = ort::inputs![
            "latents" => tensor("latents", &latent_shape, latents)?,
            "timestep" => tensor("timestep", &[1], &timestep)?,
            "text_embeddings" => tensor("text_embeddings", &text_shape, text_embeddings)?,
            "control" => tensor("control", &control_shape, control)?,
            "control_scale" => tensor("control_scale", &scale_shape, control_scales)?,
        ];
        if self.positions_input {
            let positions = TensorRef::from_array_view(([positions.len()], positions))
                .map_err(RuntimeError::ort("preparing the positions tensor"))?;
            inputs.push(("positions".into(), positions.into()));
        } else if positions.iter().zip(0..).any(|(&p, i)| p != i) {
            return Err(RefinerError::InvalidRequest(
                "this package's transformer takes no temporal positions (only VACE's 0, 1, 2, ...)"
                    .to_owned(),
            ));
        }
        Ok(self.transformer.run(inputs, |outputs| {
            Ok(outputs.f32("velocity", &latent_shape)?.to_vec())
        })?)
    }

    /// Un-normalises `latents` (`[16, F', h, w]`), VAE-decodes them and returns `F` frames
    /// `[H, W, 3]` in [0, 1]. In C4G's layout only the rendered part is decoded: each keyframe
    /// slot would decode alone, to a frame that is discarded.
    pub fn decode(&self, latents: &[f32]) -> Result<Vec<Vec<f32>>> {
        check_len("latents", latents.len(), &self.latent_shape())?;
        let m = self.manifest();
        let plane = m.latent.height * m.latent.width;
        let (slots, r) = (m.keyframe_slots(), m.video_latent_frames());
        let mut raw: Vec<f32> = latents
            .chunks_exact(m.latent.frames * plane)
            .flat_map(|channel| &channel[slots * plane..(slots + r) * plane])
            .copied()
            .collect();
        self.stats.denormalize(&mut raw);
        let video = self.vae_decode(&raw)?;
        let m = self.manifest();
        Ok(to_frames(&video, m.frames, m.height, m.width))
    }

    /// VAE-decodes un-normalised latents `[16, F', h, w]` (the video's latent frames) to a
    /// `[3, F, H, W]` video (about [-1, 1], not clamped).
    pub fn vae_decode(&self, latents: &[f32]) -> Result<Vec<f32>> {
        let m = self.manifest();
        let latent_shape = self.video_latent_shape();
        check_len("latents", latents.len(), &latent_shape)?;
        let input = tensor("latents", &latent_shape, latents)?;
        let shape = [1, 3, m.frames, m.height, m.width];
        Ok(self
            .vae_decoder
            .run(ort::inputs!["latents" => input], |outputs| {
                Ok(outputs.f32("video", &shape)?.to_vec())
            })?)
    }

    fn latent_shape(&self) -> [usize; 5] {
        let l = &self.manifest().latent;
        [1, l.channels, l.frames, l.height, l.width]
    }

    /// The VAE graphs' latents: the video's latent frames, without keyframe slots.
    fn video_latent_shape(&self) -> [usize; 5] {
        let m = self.manifest();
        let l = &m.latent;
        [1, l.channels, m.video_latent_frames(), l.height, l.width]
    }

    /// VACE's temporal positions: 0, 1, 2, ... per latent frame.
    fn default_positions(&self) -> Vec<i64> {
        (0..self.manifest().latent.frames as i64).collect()
    }

    fn check_request(&self, r: &RefineRequest) -> Result<()> {
        let m = self.manifest();
        let invalid = |reason: String| Err(RefinerError::InvalidRequest(reason));
        match &m.layout {
            Layout::Vace if !r.keyframes.is_empty() => {
                return invalid(
                    "keyframes are C4G's layout; this package has VACE's (put context frames in the video, masked 0)".to_owned(),
                );
            }
            Layout::C4g(k) if r.keyframes.len() != k.keyframes => {
                return invalid(format!(
                    "{} keyframes given; this package's layout takes exactly {}",
                    r.keyframes.len(),
                    k.keyframes
                ));
            }
            Layout::C4g(_) if r.mask != Mask::Frames(vec![true; r.video.len()]) => {
                return invalid(
                    "in C4G's layout every rendered frame is regenerated: the mask must be all frames"
                        .to_owned(),
                );
            }
            _ => {}
        }
        if r.text_embeddings.len() != m.text_len() {
            return invalid(format!(
                "text_embeddings has {} values, the package takes [{}, {}]",
                r.text_embeddings.len(),
                m.text.tokens,
                m.text.dim
            ));
        }
        match &r.negative_embeddings {
            Some(n) if n.len() != m.text_len() => {
                return invalid(format!(
                    "negative_embeddings has {} values, the package takes [{}, {}]",
                    n.len(),
                    m.text.tokens,
                    m.text.dim
                ));
            }
            None if r.uses_guidance() => {
                return invalid(format!(
                    "guidance {} needs negative_embeddings (the text encoder's output for the negative prompt); use guidance 1 to run without",
                    r.guidance
                ));
            }
            _ => {}
        }
        if !r.guidance.is_finite() || !r.control_scale.is_finite() {
            return invalid("guidance and control_scale must be finite".to_owned());
        }
        if let Some(noise) = &r.initial_noise
            && noise.len() != m.latent_len()
        {
            return invalid(format!(
                "initial_noise has {} values, the latents are [{}, {}, {}, {}]",
                noise.len(),
                m.latent.channels,
                m.latent.frames,
                m.latent.height,
                m.latent.width
            ));
        }
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        if !finite(&r.text_embeddings)
            || !r.negative_embeddings.as_deref().is_none_or(finite)
            || !r.initial_noise.as_deref().is_none_or(finite)
        {
            return invalid("embeddings and noise must be finite".to_owned());
        }
        Ok(())
    }
}

/// Frames `[H, W, 3]` in [0, 1] → `[3, F, H, W]` in [-1, 1].
fn to_model_video(frames: &[Vec<f32>], f: usize, h: usize, w: usize) -> Result<Vec<f32>> {
    if frames.len() != f {
        return Err(RefinerError::InvalidRequest(format!(
            "video has {} frames, the package takes {f}",
            frames.len()
        )));
    }
    let plane = h * w;
    let mut out = vec![0.0; 3 * f * plane];
    for (t, frame) in frames.iter().enumerate() {
        if frame.len() != 3 * plane {
            return Err(RefinerError::InvalidRequest(format!(
                "frame {t} has {} values, expected {h} x {w} x 3",
                frame.len()
            )));
        }
        if let Some(v) = frame.iter().find(|v| !v.is_finite()) {
            return Err(RefinerError::InvalidRequest(format!(
                "frame {t} holds the non-finite value {v}"
            )));
        }
        for (p, rgb) in frame.chunks_exact(3).enumerate() {
            for (c, &v) in rgb.iter().enumerate() {
                out[(c * f + t) * plane + p] = v * 2.0 - 1.0;
            }
        }
    }
    Ok(out)
}

/// `[3, F, H, W]` in [-1, 1] → frames `[H, W, 3]` in [0, 1], clamped.
fn to_frames(video: &[f32], f: usize, h: usize, w: usize) -> Vec<Vec<f32>> {
    let plane = h * w;
    (0..f)
        .map(|t| {
            (0..plane)
                .flat_map(|p| {
                    (0..3)
                        .map(move |c| (video[(c * f + t) * plane + p] * 0.5 + 0.5).clamp(0.0, 1.0))
                })
                .collect()
        })
        .collect()
}

fn check_len(what: &str, len: usize, shape: &[usize]) -> Result<()> {
    if len == shape.iter().product::<usize>() {
        Ok(())
    } else {
        Err(RefinerError::InvalidRequest(format!(
            "{what} has {len} values, expected shape {shape:?}"
        )))
    }
}

fn tensor<'a>(what: &str, shape: &[usize], data: &'a [f32]) -> Result<TensorRef<'a, f32>> {
    Ok(TensorRef::from_array_view((shape.to_vec(), data))
        .map_err(RuntimeError::ort(format!("preparing the {what} tensor")))?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_go_to_channel_first_minus_one_to_one_and_back() {
        let (f, h, w) = (2, 1, 2);
        let frames = vec![
            vec![0.0, 0.5, 1.0, 0.25, 0.75, 0.5],
            vec![1.0, 1.0, 1.0, 0.0, 0.0, 0.0],
        ];
        let video = to_model_video(&frames, f, h, w).unwrap();
        // Channel 0 (R) of frame 0, then of frame 1, then G, then B.
        assert_eq!(
            video,
            vec![
                -1.0, -0.5, 1.0, -1.0, 0.0, 0.5, 1.0, -1.0, 1.0, 0.0, 1.0, -1.0
            ]
        );
        assert_eq!(to_frames(&video, f, h, w), frames);
        assert!(to_model_video(&frames[..1], f, h, w).is_err());
        assert!(to_model_video(&[vec![f32::NAN; 6], vec![0.0; 6]], f, h, w).is_err());
    }

    #[test]
    fn decoded_values_are_clamped_to_the_unit_range() {
        let frames = to_frames(&[-3.0, 3.0, 0.0], 1, 1, 1);
        assert_eq!(frames, vec![vec![0.0, 1.0, 0.5]]);
    }
}
