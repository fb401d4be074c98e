//! Model packages: a directory with `model.json` and ONNX graphs (contract: docs/package.md).
//!
//! [`Package::open`] reads the manifest and refuses anything the engine could not run correctly
//! (another format, an unknown version, a different Gaussian layout, missing files, inconsistent
//! sizes) so that every later stage can trust the numbers it reads here. Keys the engine does not
//! know are ignored, as the contract asks.

use std::fs;
use std::path::{Component, Path, PathBuf};

use c4g_scene::Footprint;
use serde::Deserialize;

use crate::time::TimePolicy;
use crate::{EngineError, Result};

/// The `format` every package declares.
pub const PACKAGE_FORMAT: &str = "c4g-package";
/// The `format_version` this engine reads.
pub const PACKAGE_FORMAT_VERSION: u32 = 1;
/// The precisions a package's graphs may compute in: f32, f16 (weights and activations, made by
/// `python -m c4g.package.precision`) and int8 (dynamic quantization of the large MatMuls).
pub const PRECISIONS: [&str; 3] = ["f32", "f16", "int8"];
/// The canonical Gaussian layout, channel by channel, as `gaussian_layout` must list it.
pub const CANONICAL_LAYOUT: [&str; 14] = [
    "x", "y", "z", "scale_x", "scale_y", "scale_z", "rot_w", "rot_x", "rot_y", "rot_z", "opacity",
    "r", "g", "b",
];

/// What the encoder expects its frames to be: `model.json`'s `input`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct InputSpec {
    /// Frame height in pixels after resizing.
    pub height: u32,
    /// Frame width in pixels after resizing.
    pub width: u32,
    /// The crop before resizing; this engine implements `"center-square"`.
    pub crop: String,
    /// The resampling filter; this engine implements `"lanczos3"`.
    pub resize: String,
    /// The values that RGB 0 and 1 map to (linearly).
    pub value_range: [f32; 2],
}

/// The optional feature-lifting decoder's settings: `model.json`'s `feature_decoder`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct FeatureDecoderSpec {
    /// Width F of the 2D feature maps it lifts (and of the per-Gaussian features it returns).
    pub feature_width: usize,
}

/// How the package's Gaussians were rendered in training: `model.json`'s `rasterizer`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub struct RasterizerSpec {
    /// Which pixels a Gaussian reaches (`"ellipse"` or `"3dgs"`); absent: the ellipse.
    #[serde(default)]
    pub footprint: Footprint,
}

/// The ONNX files of a package, relative to its directory: `model.json`'s `files`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct PackageFiles {
    /// frames → features.
    pub encoder: String,
    /// features + times → Gaussians (in the precomputed decoder form, the context projection too).
    pub decoder: String,
    /// features → the context projection, in the precomputed decoder form (see [`DecoderForm`]).
    #[serde(default)]
    pub context_projection: Option<String>,
    /// features + times + feature maps → per-Gaussian features, when the package lifts features.
    #[serde(default)]
    pub feature_decoder: Option<String>,
}

/// `model.json`, as far as the engine reads it.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct Manifest {
    /// Always [`PACKAGE_FORMAT`].
    pub format: String,
    /// Always [`PACKAGE_FORMAT_VERSION`].
    pub format_version: u32,
    /// Package name, e.g. `"c4g-small"`.
    pub name: String,
    /// Package version.
    pub version: String,
    /// Free text.
    #[serde(default)]
    pub description: Option<String>,
    /// Where the weights come from (checkpoint hash, or training recipe and seed); kept verbatim.
    #[serde(default)]
    pub provenance: serde_json::Value,
    /// Frame size and preprocessing.
    pub input: InputSpec,
    /// Patch size of the encoder, in pixels.
    pub patch_size: u32,
    /// Feature tokens per frame, P.
    pub tokens_per_frame: usize,
    /// Width of the encoder features, C.
    pub feature_width: usize,
    /// Gaussians per decoded moment, N.
    pub gaussian_count: usize,
    /// Channel names of the decoder's output; must be [`CANONICAL_LAYOUT`].
    pub gaussian_layout: Vec<String>,
    /// The precision the graphs compute in (one of [`PRECISIONS`]); their inputs and outputs are
    /// f32 whatever it is. Each graph carries the same value in its `c4g.precision` metadata.
    pub precision: String,
    /// How the graphs compute attention; decides how decoder memory grows with tokens.
    #[serde(default)]
    pub attention: AttentionKind,
    /// Whether the decoder takes the context projection, computed once per clip; absent: plain.
    #[serde(default)]
    pub decoder_form: DecoderForm,
    /// Whether the decoder takes `query_indices` (int64 `[Q]`) and decodes those queries alone
    /// (see [`QuerySubset`](crate::QuerySubset)); absent: false, the decoder decodes all N.
    #[serde(default)]
    pub decoder_query_subset: bool,
    /// The time policy the weights were trained with (`"frame-step"`, `"stable"`,
    /// `"reference"`); absent: frame-step, right for the official weights (see
    /// [`declared_time_policy`](Self::declared_time_policy)).
    #[serde(default)]
    pub time_policy: Option<TimePolicy>,
    /// The rasterizer the weights were trained with; absent: the ellipse footprint, what every
    /// package made before the key existed was rendered with (see [`footprint`](Self::footprint)).
    #[serde(default)]
    pub rasterizer: Option<RasterizerSpec>,
    /// The ONNX files.
    pub files: PackageFiles,
    /// Present when the package can lift 2D features onto its Gaussians.
    #[serde(default)]
    pub feature_decoder: Option<FeatureDecoderSpec>,
    /// Every size of the network, as the PyTorch mirror's config; kept verbatim.
    #[serde(default)]
    pub architecture: serde_json::Value,
    /// How the weights were trained (recipe, data, seeds) when the package records it; kept verbatim.
    #[serde(default)]
    pub training: serde_json::Value,
}

impl Manifest {
    /// The time policy the package asks decodes to use: the one it declares, else frame-step,
    /// which equals the reference normalisation wherever the official weights were trained.
    pub fn declared_time_policy(&self) -> TimePolicy {
        self.time_policy.unwrap_or_default()
    }

    /// The footprint the package's Gaussians are meant to be rendered with: the one it declares,
    /// else [`Footprint::Ellipse`].
    pub fn footprint(&self) -> Footprint {
        self.rasterizer.map(|r| r.footprint).unwrap_or_default()
    }

    /// Width F of the feature decoder's feature maps, when the package has one.
    pub fn feature_decoder_width(&self) -> Option<usize> {
        self.feature_decoder.as_ref().map(|f| f.feature_width)
    }

    /// Attention heads of the Gaussian decoder (`architecture.decoder_heads`), when declared.
    pub fn decoder_heads(&self) -> Option<usize> {
        self.architecture
            .get("decoder_heads")
            .and_then(serde_json::Value::as_u64)
            .and_then(|h| usize::try_from(h).ok())
            .filter(|&h| h > 0)
    }
}

/// How a package's graphs compute attention (`model.json` key `attention`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AttentionKind {
    /// MatMul / Softmax / MatMul: every score matrix (heads × L × L floats) is materialised.
    /// Packages that do not say are taken to be plain.
    #[default]
    Plain,
    /// ONNX Runtime's `com.microsoft.MultiHeadAttention`: flash attention on the CPU, fused
    /// kernels on CUDA; memory grows linearly with the token count.
    Fused,
}

/// How a package's decoder gets its first layer's qkv projection of the context features
/// (`model.json` key `decoder_form`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DecoderForm {
    /// `decoder.onnx` takes the features and the times, and projects every token for every
    /// target. Packages that do not say are plain.
    #[default]
    Plain,
    /// `context_projection.onnx` projects the context features once per clip (the projection of
    /// the centred features by the first layer's weights, which depends on no time); `decoder.onnx`
    /// takes that as an input and adds only what the time embeddings change. The same Gaussians
    /// up to float rounding, without the first layer's projection in the per-target cost.
    Precomputed,
}

/// A validated model package on disk.
#[derive(Debug, Clone)]
pub struct Package {
    dir: PathBuf,
    manifest: Manifest,
}

impl Package {
    /// Reads `dir/model.json` and checks it against the package contract.
    pub fn open(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref().to_path_buf();
        let path = dir.join("model.json");
        let text = fs::read_to_string(&path).map_err(|source| EngineError::Io {
            path: path.clone(),
            source,
        })?;
        let manifest: Manifest =
            serde_json::from_str(&text).map_err(|source| EngineError::Manifest { path, source })?;
        let package = Self { dir, manifest };
        package.validate()?;
        Ok(package)
    }

    /// The package directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Path of `encoder.onnx`.
    pub fn encoder_path(&self) -> PathBuf {
        self.dir.join(&self.manifest.files.encoder)
    }

    /// Path of `decoder.onnx`.
    pub fn decoder_path(&self) -> PathBuf {
        self.dir.join(&self.manifest.files.decoder)
    }

    /// Path of `context_projection.onnx`, when the package is in the precomputed decoder form.
    pub fn context_projection_path(&self) -> Option<PathBuf> {
        self.manifest
            .files
            .context_projection
            .as_ref()
            .map(|f| self.dir.join(f))
    }

    /// Path of `feature_decoder.onnx`, when the package has one.
    pub fn feature_decoder_path(&self) -> Option<PathBuf> {
        self.manifest
            .files
            .feature_decoder
            .as_ref()
            .map(|f| self.dir.join(f))
    }

    fn invalid(&self, reason: impl Into<String>) -> EngineError {
        EngineError::InvalidPackage {
            dir: self.dir.clone(),
            reason: reason.into(),
        }
    }

    fn validate(&self) -> Result<()> {
        let m = &self.manifest;
        if m.format != PACKAGE_FORMAT {
            return Err(self.invalid(format!(
                "format is {:?}, expected {PACKAGE_FORMAT:?}",
                m.format
            )));
        }
        if m.format_version != PACKAGE_FORMAT_VERSION {
            return Err(self.invalid(format!(
                "format_version {} is not supported (this engine reads version {PACKAGE_FORMAT_VERSION})",
                m.format_version
            )));
        }
        if m.gaussian_layout != CANONICAL_LAYOUT {
            return Err(self.invalid(format!(
                "gaussian_layout {:?} is not the canonical 14-channel layout {CANONICAL_LAYOUT:?}",
                m.gaussian_layout
            )));
        }
        if !PRECISIONS.contains(&m.precision.as_str()) {
            return Err(self.invalid(format!(
                "precision {:?} is not supported (one of {PRECISIONS:?})",
                m.precision
            )));
        }
        self.validate_input()?;
        self.validate_sizes()?;
        self.validate_files()
    }

    fn validate_input(&self) -> Result<()> {
        let input = &self.manifest.input;
        if input.crop != "center-square" {
            return Err(self.invalid(format!(
                "input.crop {:?} is not supported (only \"center-square\")",
                input.crop
            )));
        }
        if input.resize != "lanczos3" {
            return Err(self.invalid(format!(
                "input.resize {:?} is not supported (only \"lanczos3\")",
                input.resize
            )));
        }
        let [low, high] = input.value_range;
        if !(low.is_finite() && high.is_finite() && low < high) {
            return Err(self.invalid(format!(
                "input.value_range {:?} must be two finite, increasing numbers",
                input.value_range
            )));
        }
        Ok(())
    }

    fn validate_sizes(&self) -> Result<()> {
        let m = &self.manifest;
        let (h, w, p) = (m.input.height, m.input.width, m.patch_size);
        if h == 0 || w == 0 || p == 0 || h % p != 0 || w % p != 0 {
            return Err(self.invalid(format!(
                "input {w}x{h} must be a non-empty whole number of {p}-pixel patches"
            )));
        }
        let patches = (h / p) as usize * (w / p) as usize;
        if m.tokens_per_frame != patches {
            return Err(self.invalid(format!(
                "tokens_per_frame {} does not match the {}x{} patch grid ({patches})",
                m.tokens_per_frame,
                w / p,
                h / p
            )));
        }
        if m.feature_width == 0 || m.gaussian_count == 0 {
            return Err(self.invalid("feature_width and gaussian_count must be positive"));
        }
        match (m.decoder_form, &m.files.context_projection) {
            (DecoderForm::Precomputed, None) => {
                return Err(self.invalid(
                    "decoder_form is \"precomputed\" but files.context_projection is missing",
                ));
            }
            (DecoderForm::Plain, Some(_)) => {
                return Err(self.invalid(
                    "files.context_projection is given but decoder_form is not \"precomputed\"",
                ));
            }
            _ => {}
        }
        match (&m.files.feature_decoder, &m.feature_decoder) {
            (Some(_), Some(spec)) if spec.feature_width == 0 => {
                Err(self.invalid("feature_decoder.feature_width must be positive"))
            }
            (Some(_), Some(_)) | (None, None) => Ok(()),
            (Some(_), None) => Err(self.invalid(
                "files.feature_decoder is given but the feature_decoder settings are missing",
            )),
            (None, Some(_)) => Err(self.invalid(
                "feature_decoder settings are given but files.feature_decoder is missing",
            )),
        }
    }

    fn validate_files(&self) -> Result<()> {
        let files = &self.manifest.files;
        let declared = [
            ("encoder", Some(&files.encoder)),
            ("decoder", Some(&files.decoder)),
            ("context_projection", files.context_projection.as_ref()),
            ("feature_decoder", files.feature_decoder.as_ref()),
        ];
        for (role, file) in declared {
            let Some(file) = file else { continue };
            let relative = Path::new(file);
            let inside = relative
                .components()
                .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
            if file.is_empty() || !inside {
                return Err(self.invalid(format!(
                    "files.{role} {file:?} must be a relative path inside the package"
                )));
            }
            if !self.dir.join(relative).is_file() {
                return Err(self.invalid(format!(
                    "files.{role} {file:?} does not exist in the package"
                )));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use serde_json::{Value, json};

    use super::*;

    /// A throwaway package directory under the system temp dir, removed on drop.
    struct TempPackage(PathBuf);

    impl TempPackage {
        fn new(name: &str, manifest: &Value, files: &[&str]) -> Self {
            let dir = std::env::temp_dir()
                .join(format!("c4g-engine-package-{name}-{}", std::process::id()));
            let _ = fs::remove_dir_all(&dir);
            fs::create_dir_all(&dir).unwrap();
            fs::write(dir.join("model.json"), manifest.to_string()).unwrap();
            for f in files {
                fs::write(dir.join(f), b"onnx").unwrap();
            }
            Self(dir)
        }
    }

    impl Drop for TempPackage {
        fn drop(&mut self) {
            let _ = fs::remove_dir_all(&self.0);
        }
    }

    fn manifest() -> Value {
        json!({
            "format": "c4g-package",
            "format_version": 1,
            "name": "c4g-test",
            "version": "0.1.0",
            "description": "unit test",
            "provenance": {"kind": "random-init", "seed": 7},
            "input": {"height": 224, "width": 224, "crop": "center-square", "resize": "lanczos3", "value_range": [-1.0, 1.0]},
            "patch_size": 14,
            "tokens_per_frame": 256,
            "feature_width": 128,
            "gaussian_count": 256,
            "gaussian_layout": CANONICAL_LAYOUT,
            "time": {"embedding_dim": 256},
            "precision": "f32",
            "files": {"encoder": "encoder.onnx", "decoder": "decoder.onnx", "feature_decoder": "feature_decoder.onnx"},
            "feature_decoder": {"feature_width": 32},
            "architecture": {"decoder_depth": 2, "decoder_heads": 16},
            "a_key_from_the_future": [1, 2, 3]
        })
    }

    const ALL_FILES: [&str; 3] = ["encoder.onnx", "decoder.onnx", "feature_decoder.onnx"];

    fn open_with(name: &str, edit: impl FnOnce(&mut Value), files: &[&str]) -> Result<Package> {
        let mut m = manifest();
        edit(&mut m);
        let tmp = TempPackage::new(name, &m, files);
        Package::open(&tmp.0)
    }

    fn reason(result: Result<Package>) -> String {
        match result {
            Err(EngineError::InvalidPackage { reason, .. }) => reason,
            other => panic!("expected an invalid package, got {other:?}"),
        }
    }

    #[test]
    fn a_valid_manifest_opens_and_exposes_its_numbers() {
        let tmp = TempPackage::new("valid", &manifest(), &ALL_FILES);
        let package = Package::open(&tmp.0).unwrap();
        let m = package.manifest();
        assert_eq!((m.name.as_str(), m.version.as_str()), ("c4g-test", "0.1.0"));
        assert_eq!((m.input.width, m.input.height), (224, 224));
        assert_eq!(m.input.value_range, [-1.0, 1.0]);
        assert_eq!(
            (m.tokens_per_frame, m.feature_width, m.gaussian_count),
            (256, 128, 256)
        );
        assert_eq!(m.feature_decoder_width(), Some(32));
        assert_eq!(m.provenance["seed"], 7);
        assert_eq!(m.decoder_heads(), Some(16));
        assert_eq!(m.time_policy, None);
        assert_eq!(m.declared_time_policy(), TimePolicy::FrameStep);
        assert_eq!(package.decoder_path(), tmp.0.join("decoder.onnx"));
        assert_eq!(
            package.feature_decoder_path(),
            Some(tmp.0.join("feature_decoder.onnx"))
        );
    }

    #[test]
    fn a_package_without_feature_decoder_opens() {
        let package = open_with(
            "nofeat",
            |m| {
                m["files"]
                    .as_object_mut()
                    .unwrap()
                    .remove("feature_decoder");
                m["feature_decoder"] = Value::Null;
            },
            &ALL_FILES[..2],
        )
        .unwrap();
        assert_eq!(package.manifest().feature_decoder_width(), None);
        assert_eq!(package.feature_decoder_path(), None);
    }

    #[test]
    fn a_package_declares_the_time_policy_it_was_trained_with() {
        for (name, policy) in [
            ("stable", TimePolicy::Stable),
            ("frame-step", TimePolicy::FrameStep),
            ("reference", TimePolicy::Reference),
        ] {
            let package = open_with(
                &format!("policy-{name}"),
                |m| m["time_policy"] = json!(name),
                &ALL_FILES,
            )
            .unwrap();
            assert_eq!(package.manifest().time_policy, Some(policy));
            assert_eq!(package.manifest().declared_time_policy(), policy);
        }
        let err = open_with(
            "policy-unknown",
            |m| m["time_policy"] = json!("blurry"),
            &ALL_FILES,
        )
        .unwrap_err();
        assert!(matches!(err, EngineError::Manifest { .. }), "{err}");
    }

    #[test]
    fn a_package_declares_the_footprint_it_was_trained_with() {
        let declared = |name: &str, rasterizer: Option<Value>| {
            let package = open_with(
                &format!("footprint-{name}"),
                |m| {
                    if let Some(r) = rasterizer {
                        m["rasterizer"] = r;
                    }
                },
                &ALL_FILES,
            );
            package.map(|p| p.manifest().footprint())
        };
        assert_eq!(declared("absent", None).unwrap(), Footprint::Ellipse);
        assert_eq!(
            declared("empty", Some(json!({}))).unwrap(),
            Footprint::Ellipse
        );
        assert_eq!(
            declared("ellipse", Some(json!({"footprint": "ellipse"}))).unwrap(),
            Footprint::Ellipse
        );
        assert_eq!(
            declared(
                "3dgs",
                Some(json!({"footprint": "3dgs", "note": "ignored"}))
            )
            .unwrap(),
            Footprint::Tiles3dgs
        );
        let err = declared("unknown", Some(json!({"footprint": "gsplat"}))).unwrap_err();
        assert!(matches!(err, EngineError::Manifest { .. }), "{err}");
    }

    #[test]
    fn a_package_declares_its_decoder_form_and_the_precomputed_form_needs_its_projection_graph() {
        let plain = open_with("form-absent", |_| {}, &ALL_FILES).unwrap();
        assert_eq!(plain.manifest().decoder_form, DecoderForm::Plain);
        assert_eq!(plain.context_projection_path(), None);
        let precomputed = |m: &mut Value| {
            m["decoder_form"] = json!("precomputed");
            m["files"]["context_projection"] = json!("context_projection.onnx");
        };
        let mut files = ALL_FILES.to_vec();
        files.push("context_projection.onnx");
        let package = open_with("form-precomputed", precomputed, &files).unwrap();
        assert_eq!(package.manifest().decoder_form, DecoderForm::Precomputed);
        assert!(
            package
                .context_projection_path()
                .unwrap()
                .ends_with("context_projection.onnx")
        );
        let missing_file = reason(open_with("form-no-file", precomputed, &ALL_FILES));
        assert!(
            missing_file.contains("context_projection.onnx"),
            "{missing_file}"
        );
        let undeclared = reason(open_with(
            "form-no-graph",
            |m| m["decoder_form"] = json!("precomputed"),
            &files,
        ));
        assert!(
            undeclared.contains("files.context_projection is missing"),
            "{undeclared}"
        );
        let stray = reason(open_with(
            "form-stray-graph",
            |m| m["files"]["context_projection"] = json!("context_projection.onnx"),
            &files,
        ));
        assert!(stray.contains("decoder_form"), "{stray}");
        let unknown = open_with(
            "form-unknown",
            |m| m["decoder_form"] = json!("cached"),
            &ALL_FILES,
        )
        .unwrap_err();
        assert!(matches!(unknown, EngineError::Manifest { .. }), "{unknown}");
    }

    #[test]
    fn a_missing_directory_is_an_io_error_naming_the_manifest() {
        let err = Package::open("/nonexistent/c4g-package").unwrap_err();
        assert!(matches!(err, EngineError::Io { .. }));
        assert!(
            err.to_string()
                .contains("/nonexistent/c4g-package/model.json")
        );
    }

    #[test]
    fn malformed_json_is_a_manifest_error() {
        let err =
            open_with("typo", |m| m["feature_width"] = json!("wide"), &ALL_FILES).unwrap_err();
        assert!(matches!(err, EngineError::Manifest { .. }), "{err}");
    }

    #[test]
    fn contract_violations_are_named() {
        // (JSON pointer to change, new value, words the reason must contain)
        let cases = [
            ("/format", json!("onnx"), "format"),
            ("/format_version", json!(2), "format_version 2"),
            ("/gaussian_layout/6", json!("rot_x"), "gaussian_layout"),
            ("/precision", json!("f64"), "precision"),
            ("/input/crop", json!("pad"), "input.crop"),
            ("/input/resize", json!("bilinear"), "input.resize"),
            ("/input/value_range", json!([1.0, -1.0]), "value_range"),
            ("/tokens_per_frame", json!(100), "tokens_per_frame"),
            ("/patch_size", json!(15), "patches"),
            ("/feature_decoder", Value::Null, "settings are missing"),
            ("/files/decoder", json!("../decoder.onnx"), "inside"),
            ("/files/encoder", json!("/etc/passwd"), "inside"),
        ];
        for (i, (pointer, value, expected)) in cases.into_iter().enumerate() {
            let edit = |m: &mut Value| *m.pointer_mut(pointer).unwrap() = value;
            let reason = reason(open_with(&format!("case{i}"), edit, &ALL_FILES));
            assert!(reason.contains(expected), "{pointer}: {reason}");
        }
    }

    #[test]
    fn declared_files_must_exist() {
        let reason = reason(open_with("missing", |_| {}, &ALL_FILES[..2]));
        assert!(reason.contains("feature_decoder.onnx") && reason.contains("does not exist"));
    }
}
