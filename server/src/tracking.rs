//! Point tracks, whatever the transport: query points in an input frame at a time, answered
//! with where each point is at other times, in the input camera at those times.
//!
//! The sets of a clip are its Gaussians' trajectories (query `i` is the same Gaussian at every
//! time), so a track is read off them: a point follows the Gaussians that explain its pixel at the
//! query time, by their rasterizer weights (`c4g_renderer::tracking`, where the rule is stated).
//! Positions are in the input camera at each time (the clip's given or recovered cameras,
//! interpolated between its context cameras; the identity without them, the static camera of the
//! public C4G code);
//! visibility is a depth test against the render's depth there. The sets are decoded as any
//! decode is (exact by default, or approximated as `quality` asks), all times in one request.

use std::sync::Arc;

use c4g_renderer::tracking::{Observation, PointAnchor, anchor, observe};
use c4g_renderer::{Camera, GaussianSet, RenderOptions};
use serde::{Deserialize, Serialize};

use crate::ServiceError;
use crate::camera::{CameraSpec, InputSpec};
use crate::intake::cameras::ClipCameras;
use crate::quality::QualitySpec;
use crate::service::Service;

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

/// A track request.
#[derive(Debug, Clone, Default)]
pub struct TrackRequest {
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
    /// The image size the positions are in.
    pub width: u32,
    /// Likewise.
    pub height: u32,
    /// The answered times.
    pub times: Vec<f64>,
    /// One per query, in order.
    pub tracks: Vec<Track>,
}

impl Service {
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
        self.check_times(&record, &times)?;
        let mut decoded: Vec<f64> = times.clone();
        decoded.extend(request.queries.iter().map(|q| q.t));
        decoded.sort_by(f64::total_cmp);
        decoded.dedup();
        let sets = self.decode(id, decoded, request.quality).await?;
        let queries = request.queries;
        let cameras = self.input_cameras(&record);
        self.work(move |service| {
            let footprint = service.renderer.footprint();
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
                width,
                height,
                times,
                tracks,
            })
        })
        .await
    }
}

fn track_point(t: f64, seen: Observation) -> TrackPoint {
    TrackPoint {
        t,
        x: seen.x,
        y: seen.y,
        visible: seen.visible,
        depth: seen.depth,
        position: seen.position.to_array(),
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
