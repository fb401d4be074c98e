//! Stage 1, projection: each Gaussian, in f64, to the `Splat` the pixels see (pixel centre, a
//! cancellation-free form of its 2D covariance, depth, its pixel box), or to nothing when the
//! forward model skips it or it reaches no pixel. The box is the footprint's: for
//! [`Footprint::Ellipse`] a conservative box around the pixels its exact test can reach, for
//! [`Footprint::Tiles3dgs`] the pixels of its 3DGS tiles (clipped to the image). Apart from binning
//! and blending because it is the only stage that reads the camera and the Gaussians' parameters.

use glam::{DMat3, DQuat, DVec3};

use super::tiling::TILE;
use crate::raster::{
    ALPHA_MIN, DISCRIMINANT_FLOOR_3DGS, EPS2D, FOV_CLAMP, RenderOptions, SIGMA_EXTENT, TILE_3DGS,
};
use c4g_scene::Footprint;

// The 3DGS footprint's tiles are binned as they are: one of ours is one of theirs.
const _: () = assert!(TILE == TILE_3DGS);
use c4g_scene::{Camera, GaussianSet};

/// A Gaussian as the pixels see it.
#[derive(Debug, Clone, Copy)]
pub(super) struct Splat {
    /// Pixel coordinates of the centre relative to the box corner `(x0, y0)`: pixel offsets are
    /// then exact in f32 however far from the image origin the box is.
    pub(super) u: f32,
    pub(super) v: f32,
    /// The Mahalanobis distance in the form `d² = a·(dx − k·dy)² + dy²·inv_syy`, a sum of two
    /// non-negative terms (no cancellation however thin the ellipse): with Σ2D =
    /// `[[sxx, sxy], [sxy, syy]]`, `a = syy / det`, `k = sxy / syy`, `inv_syy = 1 / syy`.
    pub(super) a: f32,
    pub(super) k: f32,
    pub(super) inv_syy: f32,
    /// Squared reach: `d²` beyond this cannot contribute (for the ellipse 3 sigma, or less for
    /// faint splats; for the 3DGS tiles where alpha falls below `ALPHA_MIN`).
    pub(super) reach2: f32,
    pub(super) opacity: f32,
    pub(super) depth: f32,
    pub(super) color: [f32; 3],
    /// Index in the Gaussian set.
    pub(super) index: u32,
    /// Inclusive pixel box, inside the image: no pixel outside it is evaluated.
    pub(super) x0: u32,
    pub(super) y0: u32,
    pub(super) x1: u32,
    pub(super) y1: u32,
}

impl Splat {
    pub(super) fn tiles(&self) -> (u32, u32, u32, u32) {
        (
            self.x0 / TILE,
            self.y0 / TILE,
            self.x1 / TILE,
            self.y1 / TILE,
        )
    }
}

/// The f64 intermediates of one Gaussian's EWA projection ([`View::ewa`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct Ewa {
    /// Camera-space centre.
    pub(super) p_cam: DVec3,
    /// The rotation, normalised, and the norm it had.
    pub(super) unit: DQuat,
    pub(super) norm: f64,
    /// Camera-space x and y with x/z, y/z clamped to the FOV limits (what `J` sees).
    pub(super) tx: f64,
    pub(super) ty: f64,
    /// The rows of the projection's Jacobian `J`.
    pub(super) j0: DVec3,
    pub(super) j1: DVec3,
    /// `W R S`.
    pub(super) wrs: DMat3,
    /// The rows of `M = J W R S`.
    pub(super) m0: DVec3,
    pub(super) m1: DVec3,
    /// `|m0|²`, `|m1|²`.
    pub(super) mxx: f64,
    pub(super) myy: f64,
    /// `Σ2D = [[sxx, sxy], [sxy, syy]]` and its determinant.
    pub(super) sxx: f64,
    pub(super) sxy: f64,
    pub(super) syy: f64,
    pub(super) det: f64,
}

/// What projection needs of the camera, in f64.
pub(super) struct View {
    pub(super) rotation: DMat3,
    translation: DVec3,
    pub(super) fx: f64,
    pub(super) fy: f64,
    cx: f64,
    cy: f64,
    pub(super) lim_x: f64,
    pub(super) lim_y: f64,
    near: f64,
    far: f64,
    footprint: Footprint,
    pub(super) width: u32,
    pub(super) height: u32,
}

impl View {
    pub(super) fn new(camera: &Camera, options: &RenderOptions) -> Self {
        let pose = camera.world_to_camera();
        let k = camera.intrinsics();
        let (fx, fy) = (f64::from(k.fx), f64::from(k.fy));
        let fov_clamp = f64::from(FOV_CLAMP);
        Self {
            rotation: DMat3::from_cols(
                pose.matrix3.x_axis.as_dvec3(),
                pose.matrix3.y_axis.as_dvec3(),
                pose.matrix3.z_axis.as_dvec3(),
            ),
            translation: pose.translation.as_dvec3(),
            fx,
            fy,
            cx: f64::from(k.cx),
            cy: f64::from(k.cy),
            lim_x: fov_clamp * f64::from(k.width) / (2.0 * fx),
            lim_y: fov_clamp * f64::from(k.height) / (2.0 * fy),
            near: f64::from(options.near),
            far: f64::from(options.far),
            footprint: options.footprint,
            width: k.width,
            height: k.height,
        }
    }

    /// The splat of Gaussian `i`, or `None` when it is skipped or reaches no pixel.
    pub(super) fn project(&self, set: &GaussianSet, i: usize) -> Option<Splat> {
        let Ewa {
            p_cam,
            mxx,
            myy,
            sxx,
            sxy,
            syy,
            det,
            ..
        } = self.ewa(set, i)?;
        let (o, c) = (set.opacities()[i], &set.colors()[i]);
        let z = p_cam.z;
        // syy ≥ EPS2D and the Schur complement det / syy ≥ EPS2D: all three are finite.
        let (a, k, inv_syy) = ((syy / det) as f32, (sxy / syy) as f32, (1.0 / syy) as f32);
        if !(a.is_finite() && k.is_finite() && inv_syy.is_finite()) {
            return None;
        }
        let eps = f64::from(EPS2D);

        let u = self.fx * p_cam.x / z + self.cx;
        let v = self.fy * p_cam.y / z + self.cy;
        // Alpha is at least 1/255 only where opacity · exp(-d²/2) is.
        let alpha_reach2 = 2.0 * (f64::from(o) / f64::from(ALPHA_MIN)).ln();
        let (reach2, (x0, x1), (y0, y1)) = match self.footprint {
            Footprint::Ellipse => {
                // Pixels can be reached only where d² ≤ 9 as well; along x the ellipse d² ≤ r²
                // spans u ± r·√Σxx (and likewise along y).
                let reach2 = f64::from(SIGMA_EXTENT * SIGMA_EXTENT).min(alpha_reach2);
                let extent = reach2.sqrt();
                (
                    reach2,
                    pixel_span(u, extent * sxx.sqrt(), self.width)?,
                    pixel_span(v, extent * syy.sqrt(), self.height)?,
                )
            }
            Footprint::Tiles3dgs => {
                let [x, y] = tiles_3dgs([u, v], [mxx, sxy, myy], eps, [self.width, self.height])?;
                (alpha_reach2, x, y)
            }
        };
        Some(Splat {
            u: (u - f64::from(x0)) as f32,
            v: (v - f64::from(y0)) as f32,
            a,
            k,
            inv_syy,
            reach2: reach2 as f32,
            opacity: o,
            depth: z as f32,
            color: *c,
            index: i as u32,
            x0,
            y0,
            x1,
            y1,
        })
    }

    /// Everything projection computes before the pixel box, in f64, for Gaussian `i`; `None` when
    /// the forward model skips it (non-finite parameters, opacity under 1/255, zero rotation,
    /// depth outside `[near, far]`, a 2D covariance that is not positive definite). The backward
    /// pass differentiates exactly this.
    pub(super) fn ewa(&self, set: &GaussianSet, i: usize) -> Option<Ewa> {
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        let (p, s, q, o, c) = (
            &set.positions()[i],
            &set.scales()[i],
            &set.rotations()[i],
            set.opacities()[i],
            &set.colors()[i],
        );
        let features_ok = set.features().and_then(|f| f.row(i)).is_none_or(finite);
        if !(finite(p) && finite(s) && finite(q) && o.is_finite() && finite(c) && features_ok) {
            return None;
        }
        // Alpha never exceeds the opacity: a Gaussian this faint reaches no pixel.
        if o < ALPHA_MIN {
            return None;
        }
        let q = DQuat::from_xyzw(q[1].into(), q[2].into(), q[3].into(), q[0].into());
        let norm = q.length();
        if norm == 0.0 {
            return None;
        }
        let p_cam =
            self.rotation * DVec3::new(p[0].into(), p[1].into(), p[2].into()) + self.translation;
        let z = p_cam.z;
        if !(z >= self.near && z <= self.far) {
            return None;
        }

        // EWA: Σ2D = M Mᵀ + EPS2D·I with M = J W R S (2×3). Through M the covariance is positive
        // semi-definite by construction, and its determinant is |m0 × m1|² (Cauchy–Binet) with no
        // cancellation, even for a zero scale or a needle seen end on.
        let tx = (p_cam.x / z).clamp(-self.lim_x, self.lim_x) * z;
        let ty = (p_cam.y / z).clamp(-self.lim_y, self.lim_y) * z;
        let j0 = DVec3::new(self.fx / z, 0.0, -self.fx * tx / (z * z));
        let j1 = DVec3::new(0.0, self.fy / z, -self.fy * ty / (z * z));
        let unit = q / norm;
        let rs = DMat3::from_quat(unit)
            * DMat3::from_diagonal(DVec3::new(s[0].into(), s[1].into(), s[2].into()));
        let wrs = self.rotation * rs;
        // Row r of J·W·R·S is (J·W·R·S)ᵀ's column r = (W R S)ᵀ j_r.
        let m0 = wrs.transpose() * j0;
        let m1 = wrs.transpose() * j1;
        let eps = f64::from(EPS2D);
        let (mxx, myy) = (m0.length_squared(), m1.length_squared());
        let sxx = mxx + eps;
        let sxy = m0.dot(m1);
        let syy = myy + eps;
        let det = m0.cross(m1).length_squared() + eps * (mxx + myy) + eps * eps;
        if !(det.is_finite() && det > 0.0) {
            return None;
        }
        Some(Ewa {
            p_cam,
            unit,
            norm,
            tx,
            ty,
            j0,
            j1,
            wrs,
            m0,
            m1,
            mxx,
            myy,
            sxx,
            sxy,
            syy,
            det,
        })
    }
}

/// The pixels (inclusive ranges along x and y, inside the image) of the 3DGS tiles of a splat
/// centred at `centre` whose covariance is `[[mxx + eps, mxy], [mxy, myy + eps]]`, in f64;
/// `None` when the tile range is empty. The rule is `super::super`'s (`Footprint::Tiles3dgs`);
/// camera alignment's differentiable render (`c4g_analysis::align`) reaches pixels by it too.
pub fn tiles_3dgs(
    centre: [f64; 2],
    [mxx, mxy, myy]: [f64; 3],
    eps: f64,
    size: [u32; 2],
) -> Option<[(u32, u32); 2]> {
    let mid = 0.5 * (mxx + myy) + eps;
    // 3DGS's `mid² − det`, as a sum of squares (the dilation cancels in the difference).
    let half_gap = 0.5 * (mxx - myy);
    let discriminant = half_gap * half_gap + mxy * mxy;
    let lambda = mid + discriminant.max(f64::from(DISCRIMINANT_FLOOR_3DGS)).sqrt();
    let radius = (f64::from(SIGMA_EXTENT) * lambda.sqrt()).ceil();
    let tile = f64::from(TILE_3DGS);
    let span = |c: f64, size: u32| {
        // 3DGS's pixel coordinates put pixel i at i, ours at i + 0.5.
        let p = c - 0.5;
        let tiles = f64::from(size.div_ceil(TILE_3DGS));
        let first = ((p - radius) / tile).floor().clamp(0.0, tiles);
        let end = ((p + radius + tile - 1.0) / tile).floor().clamp(0.0, tiles);
        // False for NaN too. Both are whole numbers within [0, tiles], so the casts are exact.
        (first < end).then(|| {
            let x0 = first as u32 * TILE_3DGS;
            (x0, (end as u32 * TILE_3DGS).min(size) - 1)
        })
    };
    Some([span(centre[0], size[0])?, span(centre[1], size[1])?])
}

/// Pixels `i` (inclusive range, inside `0..size`) whose centre `i + 0.5` may lie within `radius` of
/// `centre`, with a pixel of slack for the f32 test that decides; `None` when there are none.
fn pixel_span(centre: f64, radius: f64, size: u32) -> Option<(u32, u32)> {
    let lo = (centre - radius - 0.5).floor() - 1.0;
    let hi = (centre + radius - 0.5).ceil() + 1.0;
    if !(lo.is_finite() && hi.is_finite()) || hi < 0.0 || lo > f64::from(size - 1) {
        return None;
    }
    // Both are within [0, size - 1] after clamping, so the casts are exact.
    Some((lo.max(0.0) as u32, hi.min(f64::from(size - 1)) as u32))
}
