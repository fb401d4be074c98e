//! The refiner package: `refiner.json` and the three graphs it names.
//!
//! A package is a directory made by the Python export (`models/python`): the VACE transformer,
//! the VAE encoder and decoder, and the manifest that fixes the video size, the latent grid and
//! the latent normalisation. Sizes are fixed per package: the graphs are exported for one
//! `frames × height × width`.
//!
//! A package also declares its [`Layout`]: how a run's latent frames are laid out. VACE's (the
//! default) is one video, context and rendered frames together; C4G's puts keyframes, each
//! encoded alone through a one-frame VAE encoder, before the rendered frames, and gives every
//! latent frame an explicit temporal position (see `c4g/wan/c4g_layout.py`).

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::control::{LATENT_CHANNELS, SPATIAL_FACTOR, latent_frames};
use crate::{RefinerError, Result};

/// The `format` value of `refiner.json`.
pub const FORMAT: &str = "c4g-refiner-package";
/// The `format_version` this crate reads.
pub const FORMAT_VERSION: u32 = 1;
/// The manifest's file name.
pub const MANIFEST_FILE: &str = "refiner.json";

/// `refiner.json`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct RefinerManifest {
    /// Always [`FORMAT`].
    pub format: String,
    /// Always [`FORMAT_VERSION`].
    pub format_version: u32,
    /// The package's name.
    pub name: String,
    /// Video frames per run: context frames first, then rendered frames (VACE's layout); the
    /// rendered frames only (C4G's layout, whose keyframes come on their own).
    pub frames: usize,
    /// Frame height in pixels.
    pub height: usize,
    /// Frame width in pixels.
    pub width: usize,
    /// Frame rate the model was trained at.
    #[serde(default)]
    pub fps: Option<f64>,
    /// The latent grid and its normalisation.
    pub latent: LatentSpec,
    /// Main-transformer layers that receive a VACE hint; one control scale per entry.
    pub vace_layers: Vec<usize>,
    /// How a run's latent frames are laid out (VACE's when the manifest predates layouts).
    #[serde(default)]
    pub layout: Layout,
    /// The text-embedding input.
    pub text: TextSpec,
    /// The graphs, relative to the package directory.
    pub files: Files,
}

/// How a run's latent frames are laid out.
#[derive(Debug, Clone, PartialEq, Default, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Layout {
    /// diffusers' WanVACEPipeline: one `frames`-frame video (context frames kept by the mask),
    /// encoded as one chunk; temporal positions 0, 1, 2, ...
    #[default]
    Vace,
    /// C4G's own pipeline (its DiffSynth-Studio fork), which its published LoRA was trained with.
    C4g(KeyframeLayout),
}

/// C4G's layout: `keyframes` latent slots, then the rendered video's latent frames.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct KeyframeLayout {
    /// Keyframe slots: exactly this many context frames per run.
    pub keyframes: usize,
    /// A keyframe's temporal position is its source-frame index plus this (500).
    pub keyframe_position_offset: i64,
    /// Rows of the transformer's RoPE table: every position must be below this.
    pub rope_positions: i64,
    /// The public code's sampler defaults.
    pub sampler: LayoutSampler,
}

/// Sampler defaults a layout declares.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct LayoutSampler {
    /// Denoising steps.
    pub steps: usize,
    /// Timestep shift.
    pub shift: f64,
    /// Classifier-free guidance.
    pub guidance_scale: f32,
}

/// The latent grid.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct LatentSpec {
    /// Latent channels (16).
    pub channels: usize,
    /// Latent frames the transformer takes: `(frames + 3) / 4`, after the keyframe slots in
    /// C4G's layout.
    pub frames: usize,
    /// `height / 8`.
    pub height: usize,
    /// `width / 8`.
    pub width: usize,
    /// Per-channel mean of the VAE's latents.
    pub mean: Vec<f32>,
    /// Per-channel standard deviation of the VAE's latents.
    pub std: Vec<f32>,
}

/// The text-embedding input: `[tokens, dim]` per prompt.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub struct TextSpec {
    /// Tokens (padded with zeros to this length).
    pub tokens: usize,
    /// Embedding width.
    pub dim: usize,
}

/// The graphs of the package.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
pub struct Files {
    /// The VACE transformer: velocity from latents, timestep, text and control.
    pub transformer: String,
    /// Video to (un-normalised) latents.
    pub vae_encoder: String,
    /// (Un-normalised) latents to video.
    pub vae_decoder: String,
    /// One frame to its (un-normalised) latent frame: how C4G's layout encodes keyframes.
    #[serde(default)]
    pub vae_frame_encoder: Option<String>,
    /// umT5's encoder: token ids and mask to hidden states (optional, with `tokenizer`).
    #[serde(default)]
    pub text_encoder: Option<String>,
    /// umT5's tokenizer, a Hugging Face `tokenizer.json` (optional, with `text_encoder`).
    #[serde(default)]
    pub tokenizer: Option<String>,
}

impl RefinerManifest {
    /// Values per `[16, F', h, w]` latent tensor.
    pub fn latent_len(&self) -> usize {
        let l = &self.latent;
        l.channels * l.frames * l.height * l.width
    }

    /// Latent frames of the `frames`-frame video (what the VAE graphs take and give).
    pub fn video_latent_frames(&self) -> usize {
        latent_frames(self.frames)
    }

    /// Keyframe slots before the video's latent frames (0 in VACE's layout).
    pub fn keyframe_slots(&self) -> usize {
        match &self.layout {
            Layout::Vace => 0,
            Layout::C4g(k) => k.keyframes,
        }
    }

    /// Values per `[H, W, 3]` frame.
    pub fn frame_len(&self) -> usize {
        self.height * self.width * 3
    }

    /// Values per `[L, D]` text embedding.
    pub fn text_len(&self) -> usize {
        self.text.tokens * self.text.dim
    }

    fn check(&self) -> std::result::Result<(), String> {
        if self.format != FORMAT || self.format_version != FORMAT_VERSION {
            return Err(format!(
                "format {:?} version {}, expected {FORMAT:?} version {FORMAT_VERSION}",
                self.format, self.format_version
            ));
        }
        // The transformer patchifies 2 x 2 latent cells: pixels must tile 16 x 16.
        let tile = 2 * SPATIAL_FACTOR;
        let tiles = |side: usize| side > 0 && side.is_multiple_of(tile);
        if self.frames == 0 || !tiles(self.height) || !tiles(self.width) {
            return Err(format!(
                "frames {} x {} x {} pixels: need at least one frame and sides divisible by {tile}",
                self.frames, self.height, self.width
            ));
        }
        let l = &self.latent;
        let expected = (
            LATENT_CHANNELS,
            self.keyframe_slots() + latent_frames(self.frames),
            self.height / SPATIAL_FACTOR,
            self.width / SPATIAL_FACTOR,
        );
        if (l.channels, l.frames, l.height, l.width) != expected {
            return Err(format!(
                "latent grid {:?} does not match the video (expected {expected:?})",
                (l.channels, l.frames, l.height, l.width)
            ));
        }
        if l.mean.len() != l.channels || l.std.len() != l.channels {
            return Err(format!(
                "latent mean and std need {} values each, have {} and {}",
                l.channels,
                l.mean.len(),
                l.std.len()
            ));
        }
        if l.std.iter().any(|s| !s.is_finite() || *s <= 0.0)
            || l.mean.iter().any(|m| !m.is_finite())
        {
            return Err("latent mean must be finite and std positive".to_owned());
        }
        if self.vace_layers.is_empty() || self.text.tokens == 0 || self.text.dim == 0 {
            return Err("vace_layers, text.tokens and text.dim must not be empty".to_owned());
        }
        if let Layout::C4g(k) = &self.layout {
            if k.keyframes == 0 || self.files.vae_frame_encoder.is_none() {
                return Err(
                    "the c4g layout needs at least one keyframe slot and files.vae_frame_encoder"
                        .to_owned(),
                );
            }
            // The rendered latents take positions 0..R-1 and keyframes offset + index.
            if k.keyframe_position_offset < latent_frames(self.frames) as i64
                || k.keyframe_position_offset >= k.rope_positions
            {
                return Err(format!(
                    "keyframe_position_offset {} must lie between the rendered latent frames ({}) and rope_positions ({})",
                    k.keyframe_position_offset,
                    latent_frames(self.frames),
                    k.rope_positions
                ));
            }
        }
        Ok(())
    }
}

/// A package on disk: its directory and manifest, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct RefinerPackage {
    dir: PathBuf,
    manifest: RefinerManifest,
}

impl RefinerPackage {
    /// Reads and checks `dir/refiner.json` and that the graphs it names exist.
    pub fn open(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref().to_path_buf();
        let path = dir.join(MANIFEST_FILE);
        let text = std::fs::read_to_string(&path).map_err(RefinerError::io(&path))?;
        let manifest: RefinerManifest =
            serde_json::from_str(&text).map_err(|source| RefinerError::Json {
                path: path.clone(),
                source,
            })?;
        let invalid = |reason: String| RefinerError::InvalidPackage {
            dir: dir.clone(),
            reason,
        };
        manifest.check().map_err(invalid)?;
        let files = &manifest.files;
        if files.text_encoder.is_some() != files.tokenizer.is_some() {
            return Err(invalid(
                "files.text_encoder and files.tokenizer come together: a caption needs both"
                    .to_owned(),
            ));
        }
        let required = [&files.transformer, &files.vae_encoder, &files.vae_decoder];
        let optional = [
            &files.text_encoder,
            &files.tokenizer,
            &files.vae_frame_encoder,
        ];
        for file in required.into_iter().chain(optional.into_iter().flatten()) {
            if !dir.join(file).is_file() {
                return Err(invalid(format!("{file} is missing")));
            }
        }
        Ok(Self { dir, manifest })
    }

    /// The package directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The manifest.
    pub fn manifest(&self) -> &RefinerManifest {
        &self.manifest
    }

    /// Path of the transformer graph.
    pub fn transformer_path(&self) -> PathBuf {
        self.dir.join(&self.manifest.files.transformer)
    }

    /// Path of the VAE encoder graph.
    pub fn vae_encoder_path(&self) -> PathBuf {
        self.dir.join(&self.manifest.files.vae_encoder)
    }

    /// Path of the VAE decoder graph.
    pub fn vae_decoder_path(&self) -> PathBuf {
        self.dir.join(&self.manifest.files.vae_decoder)
    }

    /// Path of the one-frame VAE encoder graph (C4G's layout).
    pub fn vae_frame_encoder_path(&self) -> Option<PathBuf> {
        Some(
            self.dir
                .join(self.manifest.files.vae_frame_encoder.as_ref()?),
        )
    }

    /// Paths of the tokenizer and the text-encoder graph, when the package has them.
    pub fn text_encoder_paths(&self) -> Option<(PathBuf, PathBuf)> {
        let files = &self.manifest.files;
        Some((
            self.dir.join(files.tokenizer.as_ref()?),
            self.dir.join(files.text_encoder.as_ref()?),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest_json(frames: usize, latent_frames: usize) -> String {
        format!(
            r#"{{"format": "c4g-refiner-package", "format_version": 1, "name": "t",
                "frames": {frames}, "height": 32, "width": 48, "fps": 16,
                "latent": {{"channels": 16, "frames": {latent_frames}, "height": 4, "width": 6,
                           "mean": {mean:?}, "std": {std:?}}},
                "vace_layers": [0, 2], "text": {{"tokens": 8, "dim": 32}},
                "files": {{"transformer": "transformer.onnx", "vae_encoder": "vae_encoder.onnx",
                          "vae_decoder": "vae_decoder.onnx"}},
                "weight_names": "diffusers", "extra": true}}"#,
            mean = vec![0.0f32; 16],
            std = vec![1.0f32; 16]
        )
    }

    fn write_package(json: &str) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(MANIFEST_FILE), json).unwrap();
        for f in ["transformer.onnx", "vae_encoder.onnx", "vae_decoder.onnx"] {
            std::fs::write(dir.path().join(f), b"").unwrap();
        }
        dir
    }

    #[test]
    fn a_consistent_manifest_opens() {
        let dir = write_package(&manifest_json(9, 3));
        let p = RefinerPackage::open(dir.path()).unwrap();
        let m = p.manifest();
        assert_eq!(
            (m.frames, m.latent.frames, m.latent_len()),
            (9, 3, 16 * 3 * 4 * 6)
        );
        assert_eq!(m.text_len(), 256);
        assert!(p.transformer_path().ends_with("transformer.onnx"));
    }

    #[test]
    fn a_latent_grid_that_does_not_match_the_video_is_refused() {
        let dir = write_package(&manifest_json(9, 2));
        let err = RefinerPackage::open(dir.path()).unwrap_err();
        assert!(matches!(err, RefinerError::InvalidPackage { .. }), "{err}");
        assert!(err.to_string().contains("latent grid"), "{err}");
    }

    #[test]
    fn a_text_encoder_without_its_tokenizer_is_refused() {
        let json = manifest_json(9, 3).replace(
            r#""vae_decoder": "vae_decoder.onnx"}"#,
            r#""vae_decoder": "vae_decoder.onnx", "text_encoder": "text_encoder.onnx"}"#,
        );
        let dir = write_package(&json);
        std::fs::write(dir.path().join("text_encoder.onnx"), b"").unwrap();
        let err = RefinerPackage::open(dir.path()).unwrap_err();
        assert!(err.to_string().contains("tokenizer"), "{err}");
        let p = RefinerPackage::open(write_package(&manifest_json(9, 3)).path()).unwrap();
        assert_eq!(p.text_encoder_paths(), None);
    }

    #[test]
    fn a_c4g_layout_counts_its_keyframe_slots_and_needs_a_frame_encoder() {
        let layout = r#""layout": {"kind": "c4g", "keyframes": 3, "keyframe_position_offset": 500,
            "rope_positions": 1024, "sequence": "ignored",
            "sampler": {"solver": "euler", "schedule": "diffsynth", "steps": 50, "shift": 5.0, "guidance_scale": 5.0}},"#;
        let json =
            manifest_json(5, 5).replace(r#""vace_layers""#, &format!(r#"{layout} "vace_layers""#));
        let err = RefinerPackage::open(write_package(&json).path()).unwrap_err();
        assert!(err.to_string().contains("vae_frame_encoder"), "{err}");
        let json = json.replace(
            r#""vae_decoder": "vae_decoder.onnx"}"#,
            r#""vae_decoder": "vae_decoder.onnx", "vae_frame_encoder": "frame.onnx"}"#,
        );
        let dir = write_package(&json);
        std::fs::write(dir.path().join("frame.onnx"), b"").unwrap();
        let p = RefinerPackage::open(dir.path()).unwrap();
        let m = p.manifest();
        assert_eq!(
            (m.keyframe_slots(), m.video_latent_frames(), m.latent.frames),
            (3, 2, 5)
        );
        let Layout::C4g(k) = &m.layout else {
            panic!("{:?}", m.layout)
        };
        assert_eq!((k.sampler.steps, k.sampler.shift), (50, 5.0));
        // Without the keyframe slots the grid no longer matches.
        let dir = write_package(
            &json.replace(r#""frames": 5, "height": 4"#, r#""frames": 2, "height": 4"#),
        );
        std::fs::write(dir.path().join("frame.onnx"), b"").unwrap();
        assert!(
            RefinerPackage::open(dir.path())
                .unwrap_err()
                .to_string()
                .contains("latent grid")
        );
        assert_eq!(
            RefinerPackage::open(write_package(&manifest_json(9, 3)).path())
                .unwrap()
                .manifest()
                .layout,
            Layout::Vace
        );
    }

    #[test]
    fn a_missing_graph_is_named() {
        let dir = write_package(&manifest_json(9, 3));
        std::fs::remove_file(dir.path().join("vae_decoder.onnx")).unwrap();
        let err = RefinerPackage::open(dir.path()).unwrap_err();
        assert!(err.to_string().contains("vae_decoder.onnx"), "{err}");
    }
}
