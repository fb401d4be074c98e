//! Point tracks, whatever the transport: query points in an input frame at a time, answered
//! with where each point is at other times, in the input camera at those times.
//!
//! The sets of a clip are its Gaussians' trajectories (query `i` is the same Gaussian at every
//! time), so a track is read off them: a point follows the Gaussians that explain its pixel at the
//! query time, by their rasterizer weights (`c4g_analysis::tracking`, where the rule is stated).
//! Positions are in the input camera at each time (the clip's given or recovered cameras,
//! interpolated between its context cameras; the identity without them, the static camera of the
//! public C4G code);
//! visibility is a depth test against the render's depth there. The sets are decoded as any
//! decode is (exact by default, or approximated as `quality` asks), all times in one request.
//!
//! A package with a feature decoder offers a second tracker, **feature matching** (`"tracker":
//! "features"`), which follows what a point looks like in the feature field rather than which
//! Gaussians carry it:
//! - the query's feature is the rendered feature image's vector at its pixel at the query time
//!   (input camera; a pixel showing too little, alpha under
//!   [`MIN_COVERAGE`](c4g_analysis::tracking::MIN_COVERAGE), anchors nothing);
//! - at each answered time the point is where the rendered feature image (input camera at that
//!   time) matches it best: the pixel of largest cosine similarity, refined per axis by a
//!   parabola through its neighbours (`c4g_analysis::features::best_match`; ties go to the pixel
//!   nearest the query point); its depth is the render's expected depth there, its 3D point the
//!   pixel's ray at that depth;
//! - it is visible when the match is good, similarity at least [`MATCH_SIMILARITY`], and what
//!   matches lies on the rendered surface: the depth of the pixel's Gaussians weighted by their
//!   blending weight times their own positive similarity to the query is at most the expected
//!   depth by the point tracker's occlusion rule (a feature seen only through the front surface's
//!   gaps, or a blend that no Gaussian there has, is occluded).

use std::sync::Arc;

use c4g_analysis::features::{best_match_near, cosine};
use c4g_analysis::tracking::{
    MIN_COVERAGE, OCCLUSION_ABSOLUTE, OCCLUSION_RELATIVE, Observation, PointAnchor, anchor, observe,
};
use c4g_renderer::{CpuRasterizer, Image, RenderOptions};
use c4g_scene::{Camera, GaussianSet};
use serde::{Deserialize, Serialize};

use crate::ServiceError;
use crate::clips::intake::cameras::ClipCameras;
use crate::sets::quality::QualitySpec;
use crate::views::camera::{CameraSpec, InputSpec};
use crate::views::render::Views;

/// A point to track: where it is seen, at which time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackQuery {
    /// Media time, seconds.
    pub t: f64,
    /// Pixel coordinates in the request's image size: pixel `(i, j)` covers `[i, i+1) × [j, j+1)`.
    pub x: f32,
    /// Rows, likewise.
    pub y: f32,
}

/// The cosine similarity at which a feature-matched point counts as seen.
pub const MATCH_SIMILARITY: f32 = 0.8;

/// Which tracker follows the points.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Tracker {
    /// The Gaussians that explain the query pixel carry the point (the default).
    #[default]
    Gaussians,
    /// The point is where the rendered feature field matches its feature best.
    Features,
}

/// A track request.
#[derive(Debug, Clone, Default)]
pub struct TrackRequest {
    /// Which tracker follows the points.
    pub tracker: Tracker,
    /// The points.
    pub queries: Vec<TrackQuery>,
    /// Where to answer (default: the clip's context times).
    pub times: Option<Vec<f64>>,
    /// The image size the points are in (default: the model's input size).
    pub width: Option<u32>,
    /// Likewise.
    pub height: Option<u32>,
    /// How the sets are decoded.
    pub quality: QualitySpec,
}

/// One point at one time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TrackPoint {
    /// Media time, seconds.
    pub t: f64,
    /// Pixel coordinates in the input camera at `t`.
    pub x: f32,
    /// Likewise, rows.
    pub y: f32,
    /// In front of the camera, inside the image and not behind the rendered surface.
    pub visible: bool,
    /// Camera-space depth.
    pub depth: f32,
    /// The 3D point in the model's frame (the first context camera's).
    pub position: [f32; 3],
    /// The feature tracker's: the match's cosine similarity with the query's feature.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub similarity: Option<f32>,
}

/// One query's track.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Track {
    /// The query as asked.
    pub query: TrackQuery,
    /// False when the query pixel shows nothing to follow (no Gaussian covers it): then `points`
    /// is empty.
    pub anchored: bool,
    /// The point at each answered time, in time order as asked.
    pub points: Vec<TrackPoint>,
}

/// The answer.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Tracks {
    /// The tracker that followed the points.
    pub tracker: Tracker,
    /// The image size the positions are in.
    pub width: u32,
    /// Likewise.
    pub height: u32,
    /// The answered times.
    pub times: Vec<f64>,
    /// One per query, in order.
    pub tracks: Vec<Track>,
}

impl Views {
    /// Tracks `request`'s points through clip `id`.
    pub async fn tracks(
        self: &Arc<Self>,
        id: &str,
        request: TrackRequest,
    ) -> Result<Tracks, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        let (width, height) = self.image_size(request.width, request.height)?;
        check_queries(
            &request.queries,
            width,
            height,
            self.limits.max_track_queries,
        )?;
        let times = request
            .times
            .unwrap_or_else(|| record.context_times.clone());
        self.sets.check_times(&record, &times)?;
        let mut decoded: Vec<f64> = times.clone();
        decoded.extend(request.queries.iter().map(|q| q.t));
        decoded.sort_by(f64::total_cmp);
        decoded.dedup();
        let cameras = self.input_cameras(&record);
        if request.tracker == Tracker::Features {
            self.check_features()?;
            let sets = self.decode_features(id, decoded, request.quality).await?;
            let queries = request.queries;
            return self
                .work(move |views| {
                    let frames =
                        FeatureFrames::render(views, &sets, cameras.as_ref(), width, height)?;
                    let tracks = queries
                        .iter()
                        .map(|&query| frames.track(query, &times))
                        .collect::<Result<_, ServiceError>>()?;
                    Ok(Tracks {
                        tracker: Tracker::Features,
                        width,
                        height,
                        times,
                        tracks,
                    })
                })
                .await;
        }
        let sets = self.sets.decode(id, decoded, request.quality).await?;
        let queries = request.queries;
        self.work(move |views| {
            let footprint = views.renderer.footprint();
            let options = RenderOptions {
                footprint,
                ..RenderOptions::default()
            };
            let at = |t: f64| -> Result<(&GaussianSet, Camera), ServiceError> {
                let i = sets
                    .binary_search_by(|(s, _)| s.total_cmp(&t))
                    .map_err(|_| ServiceError::Internal(format!("no set decoded at {t} s")))?;
                Ok((
                    &sets[i].1,
                    input_camera(cameras.as_ref(), t, width, height)?,
                ))
            };
            // Queries at one time share one projection of its set.
            let mut anchors: Vec<Option<PointAnchor>> = vec![None; queries.len()];
            let mut query_times: Vec<f64> = queries.iter().map(|q| q.t).collect();
            query_times.sort_by(f64::total_cmp);
            query_times.dedup();
            for t in query_times {
                let (set, camera) = at(t)?;
                let (who, pixels): (Vec<usize>, Vec<(f32, f32)>) = queries
                    .iter()
                    .enumerate()
                    .filter(|(_, q)| q.t == t)
                    .map(|(k, q)| (k, (q.x, q.y)))
                    .unzip();
                for (k, found) in who
                    .into_iter()
                    .zip(anchor(set, &camera, &options, &pixels)?)
                {
                    anchors[k] = found;
                }
            }
            let mut points: Vec<Vec<TrackPoint>> = vec![Vec::new(); queries.len()];
            for &t in &times {
                let (set, camera) = at(t)?;
                // A point whose Gaussians are all gone from this set (non-finite) is not seen.
                let (who, positions): (Vec<usize>, Vec<_>) = anchors
                    .iter()
                    .enumerate()
                    .filter_map(|(k, a)| Some((k, a.as_ref()?.position(set)?)))
                    .unzip();
                for (k, seen) in who
                    .into_iter()
                    .zip(observe(set, &camera, &options, &positions)?)
                {
                    points[k].push(track_point(t, seen));
                }
            }
            let tracks = queries
                .iter()
                .zip(anchors)
                .zip(points)
                .map(|((&query, anchor), points)| Track {
                    query,
                    anchored: anchor.is_some(),
                    points,
                })
                .collect();
            Ok(Tracks {
                tracker: Tracker::Gaussians,
                width,
                height,
                times,
                tracks,
            })
        })
        .await
    }
}

/// Each decoded time's set, input camera and rendered feature image, for the feature tracker.
struct FeatureFrames<'a> {
    frames: Vec<(f64, &'a GaussianSet, Camera, Image)>,
    options: RenderOptions,
}

impl<'a> FeatureFrames<'a> {
    fn render(
        views: &Views,
        sets: &'a [(f64, GaussianSet)],
        cameras: Option<&ClipCameras>,
        width: u32,
        height: u32,
    ) -> Result<Self, ServiceError> {
        let frames = sets
            .iter()
            .map(|(t, set)| {
                crate::work::stop_if_cancelled()?;
                let camera = input_camera(cameras, *t, width, height)?;
                let image = views.renderer.render_features(set, &camera, [0.0; 3])?;
                Ok((*t, set, camera, image))
            })
            .collect::<Result<_, ServiceError>>()?;
        let options = RenderOptions {
            footprint: views.renderer.footprint(),
            ..RenderOptions::default()
        };
        Ok(Self { frames, options })
    }

    fn at(&self, t: f64) -> Result<&(f64, &'a GaussianSet, Camera, Image), ServiceError> {
        let i = self
            .frames
            .binary_search_by(|(s, ..)| s.total_cmp(&t))
            .map_err(|_| ServiceError::Internal(format!("no set decoded at {t} s")))?;
        Ok(&self.frames[i])
    }

    /// `query` followed through `times` by feature matching (the rule is the module's).
    fn track(&self, query: TrackQuery, times: &[f64]) -> Result<Track, ServiceError> {
        let (_, _, _, image) = self.at(query.t)?;
        let Some(feature) = pixel_vector(image, query.x, query.y) else {
            return Ok(Track {
                query,
                anchored: false,
                points: Vec::new(),
            });
        };
        let points = times
            .iter()
            .map(|&t| self.point(t, &feature, query))
            .collect::<Result<_, ServiceError>>()?;
        Ok(Track {
            query,
            anchored: true,
            points,
        })
    }

    fn point(
        &self,
        t: f64,
        feature: &[f32],
        query: TrackQuery,
    ) -> Result<TrackPoint, ServiceError> {
        let (_, set, camera, image) = self.at(t)?;
        let Some(found) = best_match_near(image, feature, Some((query.x, query.y)))? else {
            // Nothing shows at all: the point is not seen, and stays where it was asked.
            return Ok(TrackPoint {
                t,
                x: query.x,
                y: query.y,
                visible: false,
                depth: 0.0,
                position: [0.0; 3],
                similarity: None,
            });
        };
        let (i, j) = found.pixel;
        let p = (j * image.width + i) as usize;
        let depth = image.expected_depth[p];
        let k = camera.intrinsics();
        let ray = glam::Vec3::new((found.x - k.cx) / k.fx, (found.y - k.cy) / k.fy, 1.0);
        let position = camera.camera_to_world().transform_point3(ray * depth);
        let weights = CpuRasterizer::new()
            .pixel_weights(set, camera, &self.options, &[found.pixel])?
            .pop()
            .unwrap_or_default();
        let (mut weighted, mut total) = (0.0f64, 0.0f64);
        for w in &weights {
            let row = set.features().and_then(|f| f.row(w.index as usize));
            let similarity = row.and_then(|r| cosine(r, feature)).unwrap_or(0.0).max(0.0);
            let weight = f64::from(w.weight) * f64::from(similarity);
            weighted += weight * f64::from(w.depth);
            total += weight;
        }
        let on_surface = total > 0.0
            && weighted / total
                <= f64::from(depth) * (1.0 + f64::from(OCCLUSION_RELATIVE))
                    + f64::from(OCCLUSION_ABSOLUTE);
        Ok(TrackPoint {
            t,
            x: found.x,
            y: found.y,
            visible: found.similarity >= MATCH_SIMILARITY && on_surface,
            depth,
            position: position.to_array(),
            similarity: Some(found.similarity),
        })
    }
}

/// The feature image's vector at the pixel containing `(x, y)`, when the pixel shows enough.
fn pixel_vector(image: &Image, x: f32, y: f32) -> Option<Vec<f32>> {
    let features = image.features.as_ref()?;
    let p = (y.floor() as usize) * image.width as usize + x.floor() as usize;
    if image.alpha.get(p).is_none_or(|&a| a < MIN_COVERAGE) {
        return None;
    }
    let c = features.channels;
    features.values.get(p * c..(p + 1) * c).map(<[f32]>::to_vec)
}

fn track_point(t: f64, seen: Observation) -> TrackPoint {
    TrackPoint {
        t,
        x: seen.x,
        y: seen.y,
        visible: seen.visible,
        depth: seen.depth,
        position: seen.position.to_array(),
        similarity: None,
    }
}

/// The input camera of a clip following `cameras` at time `t`, at `width` × `height`.
fn input_camera(
    cameras: Option<&ClipCameras>,
    t: f64,
    width: u32,
    height: u32,
) -> Result<Camera, ServiceError> {
    let spec = CameraSpec {
        input: Some(InputSpec {
            at: Some(t),
            ..InputSpec::default()
        }),
        ..CameraSpec::default()
    };
    spec.resolve(cameras, t, None)?.camera(width, height)
}

fn check_queries(
    queries: &[TrackQuery],
    width: u32,
    height: u32,
    max: usize,
) -> Result<(), ServiceError> {
    if queries.is_empty() {
        return Err(ServiceError::invalid(
            "give at least one query point: \"queries\": [{\"t\": seconds, \"x\": px, \"y\": px}]",
        ));
    }
    if queries.len() > max {
        return Err(ServiceError::TooLarge(format!(
            "{} query points in one request; at most {max} (C4G_MAX_TRACK_QUERIES)",
            queries.len()
        )));
    }
    for (i, q) in queries.iter().enumerate() {
        let inside = |v: f32, size: u32| v.is_finite() && v >= 0.0 && v < size as f32;
        if !(inside(q.x, width) && inside(q.y, height)) {
            return Err(ServiceError::invalid(format!(
                "query {i} at ({}, {}) is outside the {width}x{height} image it is stated in \
                 (pixel coordinates from 0 up to the width and height; \"width\" and \"height\" \
                 set the size, by default the model's input size)",
                q.x, q.y
            )));
        }
    }
    Ok(())
}
