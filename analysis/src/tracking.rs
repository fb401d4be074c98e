//! Point tracks from Gaussian trajectories: where a point seen in one view goes at other times.
//!
//! C4G decodes the same N query tokens at every time, so Gaussian `i` of one set is Gaussian `i`
//! of every other set of the clip: the sets themselves are trajectories. A pixel is explained by
//! the Gaussians that the rasterizer blends there ([`CpuRasterizer::pixel_weights`]); a point
//! follows them.
//!
//! **Anchoring** ([`anchor`]), at the query time, in the query camera:
//! - the pixel containing the query point gives each Gaussian's blending weight `Tᵢ·αᵢ` and depth;
//! - the *surface* is the first Gaussians' depth where the accumulated weight reaches half of the
//!   pixel's alpha (the median depth: a silhouette pixel half over the background still picks
//!   the nearer surface rather than a depth between the two); the point follows the Gaussians
//!   within [`SURFACE_BAND`] of that depth, by their weights, so a Gaussian far behind (which
//!   the pixel shows only through the surface's gaps) does not pull the point along with it;
//! - the 3D point is the query ray at those Gaussians' weighted depth, so at the query time it
//!   projects back onto the query point exactly;
//! - each followed Gaussian keeps the point as an offset in its own rotating frame,
//!   `oᵢ = Rᵢᵀ (X − μᵢ)`. Scales are left out of the offset on purpose: C4G's scales are
//!   `0.001·softplus` of a raw value and change a lot from time to time on thin Gaussians, and an
//!   offset measured in them would amplify that noise along the thin axis.
//!
//! **Following** ([`PointAnchor::position`]): at any time `X(t) = Σ wᵢ (μᵢ(t) + Rᵢ(t) oᵢ) / Σ wᵢ`,
//! the weighted rigid motion of the point's Gaussians, which reproduces `X` at the query time.
//!
//! **Observing** ([`observe`]): `X(t)` in a camera gives its pixel position, its depth, and
//! whether it is *visible*: in front of the camera, inside the image, and not behind the
//! rendered surface there: its depth at most `(1 + `[`OCCLUSION_RELATIVE`]`)` times the pixel's
//! rendered expected depth plus [`OCCLUSION_ABSOLUTE`] (a pixel with almost no alpha occludes
//! nothing). The expected depth (`Σ zᵢ wᵢ / Σ wᵢ`) is the render's own depth output, so the test
//! is against exactly what a depth render shows.

use glam::{DQuat, DVec3, Vec3};

use c4g_renderer::raster::{CpuRasterizer, PixelWeight, RenderOptions};
use c4g_scene::{Camera, GaussianSet, SceneError};

/// Gaussians within this fraction of the surface depth move the point (see the module doc).
pub const SURFACE_BAND: f64 = 0.1;

/// A pixel whose alpha is below this shows nothing to anchor a point to.
pub const MIN_COVERAGE: f32 = 0.05;

/// A point behind the rendered depth by more than this fraction of it is occluded…
pub const OCCLUSION_RELATIVE: f32 = 0.05;

/// …plus this much, in scene units (C4G's: the first to last context camera is 1), for surfaces
/// seen almost edge on.
pub const OCCLUSION_ABSOLUTE: f32 = 0.02;

/// A point tied to the Gaussians that explain its pixel at the query time.
#[derive(Debug, Clone, PartialEq)]
pub struct PointAnchor {
    /// The 3D point at the query time (the set's frame).
    point: Vec3,
    members: Vec<Member>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Member {
    index: u32,
    weight: f64,
    /// The point in the Gaussian's rotating frame: `Rᵀ (X − μ)`.
    offset: DVec3,
}

/// A tracked point as one camera sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    /// Pixel coordinates (pixel `(i, j)` covers `[i, i+1) × [j, j+1)`).
    pub x: f32,
    /// Pixel coordinates, rows.
    pub y: f32,
    /// Camera-space depth.
    pub depth: f32,
    /// In front of the camera, inside the image and not behind the rendered surface.
    pub visible: bool,
    /// The 3D point (the set's frame).
    pub position: Vec3,
}

impl PointAnchor {
    /// The point at pixel coordinates `(x, y)` of `camera` whose pixel has `weights`.
    fn from_weights(
        set: &GaussianSet,
        camera: &Camera,
        (x, y): (f32, f32),
        weights: &[PixelWeight],
    ) -> Option<Self> {
        let followed = surface(weights);
        let total: f64 = followed.iter().map(|p| f64::from(p.weight)).sum();
        let alpha: f32 = weights.iter().map(|p| p.weight).sum();
        if alpha < MIN_COVERAGE || total <= 0.0 {
            return None;
        }
        let depth = followed
            .iter()
            .map(|p| f64::from(p.weight) * f64::from(p.depth))
            .sum::<f64>()
            / total;
        let k = camera.intrinsics();
        let ray = DVec3::new(
            (f64::from(x) - f64::from(k.cx)) / f64::from(k.fx),
            (f64::from(y) - f64::from(k.cy)) / f64::from(k.fy),
            1.0,
        );
        let to_world = camera.camera_to_world();
        let point = to_world.transform_point3((ray * depth).as_vec3());
        let members = followed
            .iter()
            .map(|p| {
                let (mean, rotation) = frame(set, p.index as usize);
                Member {
                    index: p.index,
                    weight: f64::from(p.weight),
                    offset: rotation.inverse() * (point.as_dvec3() - mean),
                }
            })
            .collect();
        Some(Self { point, members })
    }

    /// The 3D point at the query time.
    pub fn point(&self) -> Vec3 {
        self.point
    }

    /// How many Gaussians move the point.
    pub fn gaussians(&self) -> usize {
        self.members.len()
    }

    /// The point carried by its Gaussians into `set` (the same clip's set at another time);
    /// `None` when none of them is there with finite parameters (a set pruned differently).
    pub fn position(&self, set: &GaussianSet) -> Option<Vec3> {
        let mut sum = DVec3::ZERO;
        let mut weights = 0.0;
        for m in &self.members {
            let i = m.index as usize;
            if i >= set.len() {
                continue;
            }
            let (mean, rotation) = frame(set, i);
            let moved = mean + rotation * m.offset;
            if moved.is_finite() {
                sum += m.weight * moved;
                weights += m.weight;
            }
        }
        (weights > 0.0).then(|| (sum / weights).as_vec3())
    }
}

/// Anchors each of `points` (pixel coordinates of `camera`'s view of `set`, inside the image):
/// `None` for a point whose pixel shows nothing (alpha below [`MIN_COVERAGE`]). One projection of
/// the set serves them all.
pub fn anchor(
    set: &GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
    points: &[(f32, f32)],
) -> Result<Vec<Option<PointAnchor>>, SceneError> {
    let (w, h) = (camera.width() as f32, camera.height() as f32);
    for &(x, y) in points {
        if !(x.is_finite() && y.is_finite() && (0.0..w).contains(&x) && (0.0..h).contains(&y)) {
            return Err(SceneError::InvalidRenderOptions(format!(
                "a tracked point ({x}, {y}) must lie inside the {w}x{h} image"
            )));
        }
    }
    let pixels: Vec<(u32, u32)> = points
        .iter()
        .map(|&(x, y)| (x.floor() as u32, y.floor() as u32))
        .collect();
    let weights = CpuRasterizer::new().pixel_weights(set, camera, options, &pixels)?;
    Ok(points
        .iter()
        .zip(&weights)
        .map(|(&point, weights)| PointAnchor::from_weights(set, camera, point, weights))
        .collect())
}

/// Each of `points` (the set's frame) as `camera` sees it in its view of `set`.
pub fn observe(
    set: &GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
    points: &[Vec3],
) -> Result<Vec<Observation>, SceneError> {
    let (w, h) = (camera.width(), camera.height());
    let k = *camera.intrinsics();
    let seen: Vec<(Vec3, Option<(u32, u32)>)> = points
        .iter()
        .map(|&p| {
            let c = camera.to_camera(p);
            let (u, v) = (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy);
            let in_front = c.z >= options.near && c.z <= options.far;
            let inside = (0.0..w as f32).contains(&u) && (0.0..h as f32).contains(&v);
            let pixel = (in_front && inside).then(|| (u.floor() as u32, v.floor() as u32));
            (Vec3::new(u, v, c.z), pixel)
        })
        .collect();
    let pixels: Vec<(u32, u32)> = seen.iter().filter_map(|(_, p)| *p).collect();
    let mut weights = CpuRasterizer::new()
        .pixel_weights(set, camera, options, &pixels)?
        .into_iter();
    Ok(points
        .iter()
        .zip(seen)
        .map(|(&position, (uvz, pixel))| {
            let visible = pixel.is_some() && {
                let at = weights.next().unwrap_or_default();
                unoccluded(&at, uvz.z)
            };
            Observation {
                x: uvz.x,
                y: uvz.y,
                depth: uvz.z,
                visible,
                position,
            }
        })
        .collect())
}

/// The pixel's Gaussians around its median depth (see the module doc), front to back: the ones a
/// point anchored there follows, and whose features a click there shows (`crate::features`).
pub fn surface(weights: &[PixelWeight]) -> Vec<PixelWeight> {
    let alpha: f32 = weights.iter().map(|p| p.weight).sum();
    let mut accumulated = 0.0;
    let Some(median) = weights.iter().find(|p| {
        accumulated += p.weight;
        accumulated >= 0.5 * alpha
    }) else {
        return Vec::new();
    };
    let band = SURFACE_BAND * f64::from(median.depth);
    weights
        .iter()
        .filter(|p| (f64::from(p.depth) - f64::from(median.depth)).abs() <= band)
        .copied()
        .collect()
}

/// True when a point at camera depth `depth` is not behind the surface the weights render.
fn unoccluded(weights: &[PixelWeight], depth: f32) -> bool {
    let alpha: f32 = weights.iter().map(|p| p.weight).sum();
    if alpha < MIN_COVERAGE {
        return true;
    }
    let expected = weights.iter().map(|p| p.weight * p.depth).sum::<f32>() / alpha;
    depth <= expected * (1.0 + OCCLUSION_RELATIVE) + OCCLUSION_ABSOLUTE
}

/// Gaussian `i`'s mean and rotation (its quaternion normalised; the identity when it has none).
fn frame(set: &GaussianSet, i: usize) -> (DVec3, DQuat) {
    let p = set.positions()[i];
    let [w, x, y, z] = set.rotations()[i].map(f64::from);
    let q = DQuat::from_xyzw(x, y, z, w);
    let norm = q.length();
    let rotation = if norm > 0.0 && norm.is_finite() {
        q / norm
    } else {
        DQuat::IDENTITY
    };
    (DVec3::new(p[0].into(), p[1].into(), p[2].into()), rotation)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use glam::{Affine3A, Quat};

    use super::*;
    use c4g_scene::{Gaussian, NormalizedIntrinsics};

    fn camera(pose: Affine3A) -> Camera {
        Camera::from_normalized(NormalizedIntrinsics::C4G_DEFAULT, 64, 64, pose).unwrap()
    }

    /// The anchor of one point (default render options).
    fn one(set: &GaussianSet, cam: &Camera, x: f32, y: f32) -> Option<PointAnchor> {
        anchor(set, cam, &RenderOptions::default(), &[(x, y)])
            .unwrap()
            .pop()
            .unwrap()
    }

    /// A wall of overlapping Gaussians at depth `z`, moved by `shift` and turned by `turn`.
    fn wall(z: f32, shift: Vec3, turn: Quat) -> GaussianSet {
        let mut out = Vec::new();
        for i in -6..=6 {
            for j in -6..=6 {
                let local = Vec3::new(i as f32 * 0.08, j as f32 * 0.08, 0.0);
                let p = turn * local + Vec3::new(0.0, 0.0, z) + shift;
                out.push(Gaussian {
                    position: p,
                    scale: Vec3::new(0.06, 0.06, 0.01),
                    rotation: turn,
                    opacity: 0.9,
                    color: Vec3::splat(0.5),
                });
            }
        }
        GaussianSet::from_gaussians(out)
    }

    #[test]
    fn a_point_projects_back_onto_its_query_at_the_query_time() {
        let set = wall(2.0, Vec3::ZERO, Quat::IDENTITY);
        let cam = camera(Affine3A::IDENTITY);
        let options = RenderOptions::default();
        let anchor = one(&set, &cam, 30.3, 35.8).unwrap();
        assert!(anchor.gaussians() >= 1);
        let p = anchor.position(&set).unwrap();
        assert!((p - anchor.point()).length() < 1e-5);
        let seen = observe(&set, &cam, &options, &[p]).unwrap()[0];
        assert!(
            (seen.x - 30.3).abs() < 1e-3 && (seen.y - 35.8).abs() < 1e-3,
            "{seen:?}"
        );
        assert!(seen.visible);
        assert!((seen.depth - 2.0).abs() < 0.05, "{seen:?}");
    }

    #[test]
    fn a_point_moves_and_turns_with_its_gaussians() {
        let cam = camera(Affine3A::IDENTITY);
        let before = wall(2.0, Vec3::ZERO, Quat::IDENTITY);
        let anchor = one(&before, &cam, 40.5, 30.5).unwrap();
        let shift = Vec3::new(0.1, -0.05, 0.2);
        let turn = Quat::from_rotation_y(0.3);
        let after = wall(2.0, shift, turn);
        // The whole wall is one rigid body: the point moves as its points do.
        let centre = Vec3::new(0.0, 0.0, 2.0);
        let expected = turn * (anchor.point() - centre) + centre + shift;
        let got = anchor.position(&after).unwrap();
        assert!((got - expected).length() < 2e-3, "{got} vs {expected}");
    }

    #[test]
    fn an_empty_pixel_anchors_nothing_and_a_point_outside_is_refused() {
        let set = wall(2.0, Vec3::ZERO, Quat::IDENTITY);
        let cam = camera(Affine3A::IDENTITY);
        let options = RenderOptions::default();
        // The wall covers the centre only: the corner pixel is empty.
        assert!(one(&set, &cam, 0.5, 0.5).is_none());
        assert!(anchor(&set, &cam, &options, &[(3.0, 3.0), (64.0, 3.0)]).is_err());
        assert!(anchor(&set, &cam, &options, &[(f32::NAN, 3.0)]).is_err());
        assert!(one(&GaussianSet::default(), &cam, 3.0, 3.0).is_none());
        // Many points at once answer as each alone.
        let many = anchor(
            &set,
            &cam,
            &options,
            &[(30.3, 35.8), (0.5, 0.5), (40.5, 30.5)],
        )
        .unwrap();
        assert_eq!(many[0], one(&set, &cam, 30.3, 35.8));
        assert_eq!(many[1], None);
        assert_eq!(many[2], one(&set, &cam, 40.5, 30.5));
    }

    #[test]
    fn a_point_behind_a_nearer_wall_is_occluded_and_outside_the_image_unseen() {
        let back = wall(3.0, Vec3::ZERO, Quat::IDENTITY);
        let cam = camera(Affine3A::IDENTITY);
        let options = RenderOptions::default();
        let anchor = one(&back, &cam, 32.5, 32.5).unwrap();
        let point = anchor.position(&back).unwrap();
        let front = wall(1.5, Vec3::ZERO, Quat::IDENTITY);
        let both = GaussianSet::from_gaussians(back.iter().chain(front.iter()));
        let seen = observe(&both, &cam, &options, &[point]).unwrap()[0];
        assert!(!seen.visible, "{seen:?}");
        assert!((seen.x - 32.5).abs() < 1e-3);
        let far_left = Vec3::new(-10.0, 0.0, 2.0);
        let behind = Vec3::new(0.0, 0.0, -1.0);
        let seen = observe(&back, &cam, &options, &[point, far_left, behind]).unwrap();
        assert!(seen[0].visible && !seen[1].visible && !seen[2].visible);
    }

    #[test]
    fn a_silhouette_pixel_follows_the_nearer_surface() {
        // Half the pixel's weight on a near wall, the rest on a far one behind it.
        let near = PixelWeight {
            index: 0,
            weight: 0.5,
            depth: 1.0,
        };
        let far = PixelWeight {
            index: 1,
            weight: 0.45,
            depth: 5.0,
        };
        let chosen = surface(&[near, far]);
        assert_eq!(chosen, vec![near]);
    }
}
