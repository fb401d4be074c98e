//! Lifted features, whatever the transport: what a request for the 4D feature field means.
//!
//! A package with a feature decoder (`docs/package.md`, "The feature decoder") lifts 2D feature
//! maps of the context frames onto its Gaussians: each decoded set then carries one F-wide vector
//! per Gaussian, composited into images like colour. From that this module serves
//! - **decodes with features** ([`Service::decode_features`]): the sets with their vectors, exact
//!   or approximated as any decode (keyframes interpolate features linearly; pruning keeps the
//!   kept Gaussians' rows), for JSON, `C4GS` version 2 and `.ply` alike;
//! - **feature images** ([`Service::render_features`]): the raw composited channels, or a colouring
//!   by the clip's [`FeaturePca`] basis, fitted once per clip on its Gaussians' features at its
//!   context times and kept in memory (forgotten with the clip), so that a colour means the same
//!   feature at every time and from every camera;
//! - **segments** ([`Service::segment`]): the Gaussians whose feature is within a cosine threshold
//!   of a clicked pixel's or a given one, and their mask at any time.
//!
//! Which maps the decoder lifts is the package's `feature_decoder.kind`. `encoder` (and a package
//! that declares no kind, when the maps' width is the encoder's): the encoding's own features,
//! which the store already holds, so every clip has them. `object-id`: per-patch object masks of
//! each context frame, which only the client can give. This server takes none and refuses such a
//! package's feature requests (422 `unsupported`, saying what is missing): accepting them means an
//! upload option carrying per-frame masks that must be cropped, resized and sampled exactly as the
//! frames are, be part of the clip's content address and live in the store beside the features;
//! that is an intake feature of its own, and the default package does not need it (c4g-tiny lifts
//! its encoder's features; `models/c4g-tiny-objects`, which lifts object ids, is scored offline by
//! `c4g.eval.segmentation`).

use std::sync::Arc;

use c4g_analysis::features::{FeaturePca, cosine, pixel_feature, select_similar};
use c4g_engine::{Encoding, EngineError, Keyframes};
use c4g_renderer::{CpuRasterizer, Image, RenderOptions};
use c4g_scene::GaussianSet;
use serde::{Deserialize, Serialize};

use crate::ServiceError;
use crate::sets::quality::{Approximation, QualitySpec};
use crate::sets::scene::Scene;
use crate::views::camera::{CameraSpec, InputSpec};
use crate::views::feature_field::MapsKind;
use crate::views::image_formats::{ImageFormat, encode_image, le_bytes};
use crate::views::render::{ViewRequest, Views};

/// The cosine similarity a Gaussian's feature must reach to join a segment, unless the request
/// sets its own: close enough that one object's Gaussians share a segment and a neighbouring
/// object's mostly do not, for features that separate objects (a starting point: the right value
/// is the feature's, and a client tunes it).
pub const DEFAULT_SEGMENT_THRESHOLD: f32 = 0.8;

/// Rendered alpha of the selected Gaussians at which a mask pixel is set.
pub const MASK_ALPHA: f32 = 0.5;

/// A feature image's form: the raw channels, or the clip's PCA colouring.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FeatureRender {
    /// Little-endian f32, `[H, W, F]`.
    Raw,
    /// RGB PNG.
    Pca,
}

impl FeatureRender {
    /// The feature image a render format asks for, if it asks for one.
    pub fn of_format(format: ImageFormat) -> Option<Self> {
        match format {
            ImageFormat::Features => Some(Self::Raw),
            ImageFormat::FeaturesPca => Some(Self::Pca),
            _ => None,
        }
    }
}

/// A rendered feature image, encoded.
#[derive(Debug, Clone)]
pub struct FeatureView {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Floats a pixel (raw), or 3 (the colouring).
    pub channels: usize,
    /// The bytes.
    pub bytes: Vec<u8>,
}

/// A pixel clicked at a time: pixel `(i, j)` covers `[i, i+1) × [j, j+1)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Click {
    /// Media time, seconds.
    pub t: f64,
    /// Pixel coordinates in the request's image size and camera.
    pub x: f32,
    /// Rows, likewise.
    pub y: f32,
}

/// What a segment is made of.
#[derive(Debug, Clone, PartialEq)]
pub enum Selection {
    /// The feature a pixel shows at a time.
    Click(Click),
    /// A feature vector (F floats), compared with the Gaussians' features at `t` (default: the
    /// clip's first context time).
    Feature {
        /// The vector.
        feature: Vec<f32>,
        /// When the Gaussians' features are compared with it.
        t: Option<f64>,
    },
}

/// A segment request.
#[derive(Debug, Clone)]
pub struct SegmentRequest {
    /// What to select by.
    pub selection: Selection,
    /// Cosine similarity a Gaussian must reach (default [`DEFAULT_SEGMENT_THRESHOLD`]).
    pub threshold: Option<f32>,
    /// Where to answer masks (default: the clip's context times).
    pub times: Option<Vec<f64>>,
    /// The camera of the click and the masks (default: the input camera at each time).
    pub camera: Option<CameraSpec>,
    /// The image size (default: the model's input size).
    pub width: Option<u32>,
    /// Likewise.
    pub height: Option<u32>,
}

/// A mask at one time, run-length encoded.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Mask {
    /// Media time, seconds.
    pub t: f64,
    /// Pixels set.
    pub area: u64,
    /// Alternating runs over the pixels in row-major order, starting with unset pixels (so the
    /// first run may be 0); they sum to width × height.
    pub counts: Vec<u32>,
}

/// A segment.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Segment {
    /// The masks' size.
    pub width: u32,
    /// Likewise.
    pub height: u32,
    /// When the Gaussians' features were compared (the click's time, or the feature's `t`).
    pub t: f64,
    /// The cosine threshold used.
    pub threshold: f32,
    /// The feature selected by (the click's, or the one given).
    pub feature: Vec<f32>,
    /// The selected Gaussians' indices (the same Gaussians at every time).
    pub gaussians: Vec<u32>,
    /// One mask per answered time, in order.
    pub masks: Vec<Mask>,
}

impl Views {
    /// Refuses, before any work, what this package cannot lift: no feature decoder, or maps
    /// this server cannot make.
    pub fn check_features(&self) -> Result<(), ServiceError> {
        let name = || self.engine.manifest().name.clone();
        if !self.engine.has_feature_decoder() {
            return Err(EngineError::NoFeatureDecoder { package: name() }.into());
        }
        let m = self.engine.manifest();
        let width = m.feature_decoder_width().unwrap_or(0);
        match &self.features.kind {
            MapsKind::Encoder => Ok(()),
            MapsKind::Undeclared if width == m.feature_width => Ok(()),
            MapsKind::Undeclared => Err(ServiceError::Unsupported(format!(
                "package {} lifts {width}-wide feature maps of an undeclared kind \
                 (feature_decoder.kind): this server lifts the encoder's own {}-wide features \
                 only, and takes no maps from clients",
                name(),
                m.feature_width
            ))),
            MapsKind::ObjectId => Err(ServiceError::Unsupported(format!(
                "package {} lifts object-id features (feature_decoder.kind \"object-id\"): its \
                 maps are per-context-frame object masks that only the client has, and this \
                 server takes no masks with an upload; serve a package whose feature decoder \
                 lifts its encoder's features (kind \"encoder\")",
                name()
            ))),
            MapsKind::Other(kind) => Err(ServiceError::Unsupported(format!(
                "package {} lifts feature maps of kind {kind:?}, which this server does not know \
                 (it makes \"encoder\" maps)",
                name()
            ))),
        }
    }

    /// The approximation a feature request asks for, checked: dropping queries is refused, since
    /// the feature decoder decodes every query; features are the feed-forward scene's (a fitted
    /// scene carries none).
    async fn feature_approximation(
        &self,
        record: &crate::clips::record::ClipRecord,
        quality: &QualitySpec,
        times: &[f64],
    ) -> Result<Approximation, ServiceError> {
        self.check_features()?;
        if quality.scene == Scene::Fitted {
            return Err(ServiceError::Unsupported(
                "lifted features are the feed-forward scene's: a fitted scene carries none (ask \
                 scene \"auto\" or \"feed-forward\" with features)"
                    .into(),
            ));
        }
        let quality = QualitySpec {
            scene: Scene::FeedForward,
            ..*quality
        };
        let approximation = self.sets.approximation(record, &quality, times).await?;
        if approximation.drop_queries {
            return Err(ServiceError::Unsupported(
                "features and prune.drop_queries do not go together: the feature decoder decodes \
                 every query (leave drop_queries out, or ask without features)"
                    .into(),
            ));
        }
        Ok(approximation)
    }

    /// The sets of clip `id` at `times` with each Gaussian's lifted feature vector, decoded
    /// exactly or approximated as `quality` asks.
    pub async fn decode_features(
        self: &Arc<Self>,
        id: &str,
        times: Vec<f64>,
        quality: QualitySpec,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        self.sets.check_times(&record, &times)?;
        let approximation = self
            .feature_approximation(&record, &quality, &times)
            .await?;
        let encoding = self.store.encoding(id).await?;
        let id = id.to_owned();
        self.work(move |views| views.feature_sets_now(&id, &encoding, &times, &approximation))
            .await
    }

    /// [`decode_features`](Self::decode_features) on the calling (blocking) thread, checked.
    pub fn feature_sets_now(
        &self,
        id: &str,
        encoding: &Encoding,
        times: &[f64],
        approximation: &Approximation,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let maps = self.context_feature_maps(encoding)?;
        let kept = self.sets.kept_now(id, encoding, approximation)?;
        let sets = self.lift_now(encoding, &maps, times, &approximation.keyframes)?;
        kept.select(sets)
    }

    /// The maps the feature decoder lifts for `encoding`, `[T, P, F]` in the order the frames
    /// were given (the engine's contract): the encoding's own features, taken back from its
    /// time order.
    fn context_feature_maps(&self, encoding: &Encoding) -> Result<Vec<f32>, ServiceError> {
        self.check_features()?;
        let [t, p, c] = encoding.shape();
        let per_frame = p * c;
        let features = encoding.features();
        let mut maps = vec![0.0; t * per_frame];
        for (k, &given) in encoding.frame_order().iter().enumerate() {
            maps[given * per_frame..(given + 1) * per_frame]
                .copy_from_slice(&features[k * per_frame..(k + 1) * per_frame]);
        }
        Ok(maps)
    }

    /// The feature decoder at `times`: exactly, or at keyframes and interpolated between them.
    fn lift_now(
        &self,
        encoding: &Encoding,
        maps: &[f32],
        times: &[f64],
        keyframes: &Keyframes,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let started = std::time::Instant::now();
        let decode = |ts: &[f64]| self.engine.decode_features(encoding, maps, ts);
        let sets = if keyframes.interpolates(times) {
            let (track, stats) =
                c4g_engine::keyframes::plan_keyframes(times, keyframes, encoding.times(), decode)?;
            let interpolated = times.iter().filter(|&&t| track.keyframe(t).is_none());
            crate::sets::decoder::count_sets(stats.exact_decodes, interpolated.count());
            times
                .iter()
                .map(|&t| Ok((t, track.at(t)?)))
                .collect::<Result<Vec<_>, ServiceError>>()?
        } else {
            crate::sets::decoder::count_sets(times.len(), 0);
            times.iter().copied().zip(decode(times)?).collect()
        };
        metrics::histogram!("c4g_decode_duration_seconds").record(started.elapsed().as_secs_f64());
        Ok(sets)
    }

    /// Clip `id`'s colouring basis: fitted on its Gaussians' features at its context times the
    /// first time (on the calling thread: one feature decode of every context time), then kept.
    pub fn feature_basis_now(
        &self,
        id: &str,
        encoding: &Encoding,
    ) -> Result<Arc<FeaturePca>, ServiceError> {
        if let Some(basis) = self.features.lock().get(id).cloned() {
            return Ok(basis);
        }
        let maps = self.context_feature_maps(encoding)?;
        let sets = self.lift_now(encoding, &maps, encoding.times(), &Keyframes::Exact)?;
        let width = self.engine.manifest().feature_decoder_width().unwrap_or(0);
        let samples: Vec<f32> = sets
            .iter()
            .filter_map(|(_, set)| set.features())
            .flat_map(|block| block.values().iter().copied())
            .collect();
        let basis = Arc::new(FeaturePca::fit(&samples, width)?);
        self.features.lock().put(id.to_owned(), basis.clone());
        metrics::counter!("c4g_feature_bases_total").increment(1);
        Ok(basis)
    }

    /// One feature image of clip `id`: the raw channels or the clip's colouring of them.
    pub async fn render_features(
        self: &Arc<Self>,
        id: &str,
        view: ViewRequest,
        quality: QualitySpec,
        render: FeatureRender,
    ) -> Result<FeatureView, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        let camera = self.view_camera(&record, &view)?;
        let approximation = self
            .feature_approximation(&record, &quality, &[view.t])
            .await?;
        let encoding = self.store.encoding(id).await?;
        let id = id.to_owned();
        self.work(move |views| {
            let (_, set) = views
                .feature_sets_now(&id, &encoding, &[view.t], &approximation)?
                .pop()
                .ok_or_else(|| ServiceError::Internal("the decoder returned no set".into()))?;
            let image = views
                .renderer
                .render_features(&set, &camera, view.background)?;
            match render {
                FeatureRender::Raw => raw_view(&image),
                FeatureRender::Pca => {
                    let basis = views.feature_basis_now(&id, &encoding)?;
                    let rgb = basis.colour_image(&image, view.background)?;
                    let coloured = Image { rgb, ..image };
                    Ok(FeatureView {
                        width: coloured.width,
                        height: coloured.height,
                        channels: 3,
                        bytes: encode_image(&coloured, ImageFormat::Png)?,
                    })
                }
            }
        })
        .await
    }

    /// The segment `request` asks for in clip `id`.
    pub async fn segment(
        self: &Arc<Self>,
        id: &str,
        request: SegmentRequest,
    ) -> Result<Segment, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        self.check_features()?;
        let (width, height) = self.image_size(request.width, request.height)?;
        let threshold = request.threshold.unwrap_or(DEFAULT_SEGMENT_THRESHOLD);
        if !(threshold.is_finite() && (-1.0..=1.0).contains(&threshold)) {
            return Err(ServiceError::invalid(format!(
                "threshold is a cosine similarity, from -1 to 1; got {threshold}"
            )));
        }
        let at = match &request.selection {
            Selection::Click(click) => click.t,
            Selection::Feature { t, .. } => t.unwrap_or(record.span().0),
        };
        self.sets.check_times(&record, &[at])?;
        let times = request
            .times
            .clone()
            .unwrap_or_else(|| record.context_times.clone());
        self.sets.check_times(&record, &times)?;
        let camera = request.camera.clone().unwrap_or_else(|| CameraSpec {
            input: Some(InputSpec::default()),
            ..CameraSpec::default()
        });
        let cameras = self.input_cameras_for(&record, [&camera]);
        let resolve = |t: f64| -> Result<c4g_scene::Camera, ServiceError> {
            camera
                .resolve(cameras.as_ref(), t, None)?
                .camera(width, height)
        };
        let width_f = self.engine.manifest().feature_decoder_width().unwrap_or(0);
        match &request.selection {
            Selection::Click(click) => check_click(click, width, height)?,
            Selection::Feature { feature, .. } => check_feature(feature, width_f)?,
        }
        let click_camera = resolve(at)?;
        let mask_cameras = times
            .iter()
            .map(|&t| resolve(t))
            .collect::<Result<Vec<_>, _>>()?;
        let (_, lifted) = self
            .decode_features(id, vec![at], QualitySpec::default())
            .await?
            .pop()
            .ok_or_else(|| ServiceError::Internal("the decoder returned no set".into()))?;
        let sets = self
            .sets
            .decode(id, times.clone(), QualitySpec::default())
            .await?;
        let selection = request.selection;
        self.work(move |views| {
            let options = RenderOptions {
                footprint: views.renderer.footprint(),
                ..RenderOptions::default()
            };
            let feature = match selection {
                Selection::Feature { feature, .. } => feature,
                Selection::Click(click) => {
                    clicked_feature(&lifted, &click_camera, &options, click)?
                }
            };
            let gaussians = select_similar(&lifted, &feature, threshold)?;
            let mut keep = vec![false; lifted.len()];
            for &i in &gaussians {
                keep[i as usize] = true;
            }
            let masks = sets
                .iter()
                .zip(&mask_cameras)
                .map(|((t, set), camera)| {
                    crate::work::stop_if_cancelled()?;
                    let image = views.render_now(&set.select(&keep)?, camera, [0.0; 3])?;
                    Ok(run_lengths(*t, &image.alpha))
                })
                .collect::<Result<Vec<_>, ServiceError>>()?;
            Ok(Segment {
                width,
                height,
                t: at,
                threshold,
                feature,
                gaussians,
                masks,
            })
        })
        .await
    }
}

/// The raw channels of a rendered feature image.
fn raw_view(image: &Image) -> Result<FeatureView, ServiceError> {
    let features = image
        .features
        .as_ref()
        .ok_or_else(|| ServiceError::Internal("the render has no feature channels".into()))?;
    Ok(FeatureView {
        width: image.width,
        height: image.height,
        channels: features.channels,
        bytes: le_bytes(&features.values),
    })
}

/// The feature the clicked pixel shows (its surface's, by the rasterizer's weights).
fn clicked_feature(
    set: &GaussianSet,
    camera: &c4g_scene::Camera,
    options: &RenderOptions,
    click: Click,
) -> Result<Vec<f32>, ServiceError> {
    let pixel = (click.x.floor() as u32, click.y.floor() as u32);
    let weights = CpuRasterizer::new()
        .pixel_weights(set, camera, options, &[pixel])?
        .pop()
        .unwrap_or_default();
    pixel_feature(set, &weights).ok_or_else(|| {
        ServiceError::invalid(format!(
            "the clicked pixel ({}, {}) at t = {} s shows nothing to select (alpha under {}): \
             click on the scene",
            click.x,
            click.y,
            click.t,
            c4g_analysis::tracking::MIN_COVERAGE
        ))
    })
}

fn check_click(click: &Click, width: u32, height: u32) -> Result<(), ServiceError> {
    let inside = |v: f32, size: u32| v.is_finite() && v >= 0.0 && v < size as f32;
    if inside(click.x, width) && inside(click.y, height) {
        return Ok(());
    }
    Err(ServiceError::invalid(format!(
        "the click at ({}, {}) is outside the {width}x{height} image it is stated in (pixel \
         coordinates from 0 up to the width and height; \"width\" and \"height\" set the size, \
         by default the model's input size)",
        click.x, click.y
    )))
}

fn check_feature(feature: &[f32], width: usize) -> Result<(), ServiceError> {
    if feature.len() != width {
        return Err(ServiceError::invalid(format!(
            "the feature has {} values; the model's lifted features have {width} \
             (feature_lifting in GET /v1/models)",
            feature.len()
        )));
    }
    if cosine(feature, feature).is_none() {
        return Err(ServiceError::invalid(
            "the feature must be finite and not all zeros: a cosine similarity needs a direction",
        ));
    }
    Ok(())
}

/// The mask of `alpha` at [`MASK_ALPHA`], run-length encoded (see [`Mask`]).
fn run_lengths(t: f64, alpha: &[f32]) -> Mask {
    let mut counts = Vec::new();
    let (mut current, mut run, mut area) = (false, 0u32, 0u64);
    for &a in alpha {
        let set = a >= MASK_ALPHA;
        if set != current {
            counts.push(run);
            (current, run) = (set, 0);
        }
        run += 1;
        area += u64::from(set);
    }
    counts.push(run);
    Mask { t, area, counts }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masks_are_runs_from_unset_pixels_in_row_major_order() {
        let mask = run_lengths(0.5, &[0.6, 0.7, 0.1, 0.0, 0.5, 0.49]);
        assert_eq!(mask.counts, vec![0, 2, 2, 1, 1]);
        assert_eq!(mask.area, 3);
        assert_eq!(run_lengths(0.0, &[0.0; 4]).counts, vec![4]);
        assert_eq!(run_lengths(0.0, &[]).counts, vec![0]);
        let counts = run_lengths(0.0, &[0.1, 0.9, 0.9, 0.2]).counts;
        assert_eq!(counts.iter().sum::<u32>(), 4);
    }

    #[test]
    fn a_feature_needs_the_models_width_and_a_direction() {
        assert!(check_feature(&[1.0, 0.0], 2).is_ok());
        let short = check_feature(&[1.0], 2).unwrap_err().to_string();
        assert!(
            short.contains("has 1 values; the model's lifted features have 2"),
            "{short}"
        );
        assert!(check_feature(&[0.0, 0.0], 2).is_err());
        assert!(check_feature(&[f32::NAN, 1.0], 2).is_err());
        let click = Click {
            t: 0.0,
            x: 28.0,
            y: 1.0,
        };
        assert!(check_click(&click, 28, 28).is_err());
        assert!(check_click(&Click { x: 27.9, ..click }, 28, 28).is_ok());
    }

    #[test]
    fn a_packages_feature_kind_is_read_from_its_manifest() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let kind = |json: &str| {
            std::fs::write(dir.path().join("model.json"), json).unwrap_or_else(|e| panic!("{e}"));
            MapsKind::of_package(dir.path())
        };
        assert_eq!(
            kind(r#"{"feature_decoder": {"kind": "encoder"}}"#),
            MapsKind::Encoder
        );
        assert_eq!(
            kind(r#"{"feature_decoder": {"kind": "object-id"}}"#),
            MapsKind::ObjectId
        );
        assert_eq!(
            kind(r#"{"feature_decoder": {"feature_width": 8}}"#),
            MapsKind::Undeclared
        );
        assert_eq!(
            kind(r#"{"feature_decoder": {"kind": "clip"}}"#),
            MapsKind::Other("clip".into())
        );
    }
}
