//! Projection with derivatives: each Gaussian, in f64, to the splat the pixels see (centre,
//! conic, opacity, pixel box) together with the derivatives of its centre and 2D covariance with
//! respect to the seven camera parameters ([`super::CAMERA_PARAMETERS`]).
//!
//! The forward half is the CPU rasterizer's projection (`raster/cpu/project.rs`) restated in f64:
//! the same skips (non-finite parameters, zero rotation, opacity under 1/255, depth outside
//! `[near, far]`, a covariance that is not positive definite), the same EWA covariance and the
//! same pixel boxes (the 3DGS tiles through the rasterizer's own rule). The derivative half is the
//! chain rule through `p_cam = W p + t`, `(u, v) = (fx·x/z + cx, fy·y/z + cy)` and
//! `Σ2D = J Σcam Jᵀ + 0.3·I`, with `Σcam = W Σ Wᵀ`, for a left-multiplied perturbation
//! `exp([ω, ν]^)` of world-to-camera and a focal scale `e^s`:
//! - `dp_cam = ω × p_cam + ν` and `dΣcam = [ω]× Σcam − Σcam [ω]×` (the rotation turns the
//!   Gaussian's axes too), `dfx = fx·ds`, `dfy = fy·ds`;
//! - `J`'s x/z and y/z are clamped to ±1.3 × the half-FOV tangent: through a clamped coordinate
//!   the pose's derivative is zero, but the clamp's limit `1.3·W / 2fx` moves with the focal
//!   length, so `d(clamped x/z) = −(clamped x/z)·ds` there;
//! - `u, v` use the unclamped x/z, y/z, as the forward model does.
//!
//! Which pixels a splat reaches (its box, and the cuts the pixels apply) is held fixed under the
//! derivative: the render is piecewise smooth in the camera, and these are its pieces.

use glam::{DMat3, DQuat, DVec3};

use super::adjustment::{CAMERA_PARAMETERS, CameraAdjustment, skew};
use c4g_renderer::raster::{ALPHA_MIN, EPS2D, FOV_CLAMP, RenderOptions, SIGMA_EXTENT, tiles_3dgs};
use c4g_scene::Footprint;
use c4g_scene::{Camera, GaussianSet};

const P: usize = CAMERA_PARAMETERS;

/// The camera in f64, adjusted, with what projection needs.
pub(super) struct View {
    rotation: DMat3,
    translation: DVec3,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    lim_x: f64,
    lim_y: f64,
    near: f64,
    far: f64,
    footprint: Footprint,
    pub(super) width: u32,
    pub(super) height: u32,
}

impl View {
    pub(super) fn new(
        camera: &Camera,
        adjustment: &CameraAdjustment,
        options: &RenderOptions,
    ) -> Self {
        let (rotation, translation, [fx, fy]) = adjustment.apply_f64(camera);
        let k = camera.intrinsics();
        let fov_clamp = f64::from(FOV_CLAMP);
        Self {
            rotation,
            translation,
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
}

/// A Gaussian as the pixels see it, with the derivatives of its centre and covariance.
#[derive(Debug, Clone)]
pub(super) struct Splat {
    /// Pixel coordinates of the centre.
    pub(super) u: f64,
    pub(super) v: f64,
    /// The conic `Σ2D⁻¹ = [[qa, qb], [qb, qc]]`.
    pub(super) qa: f64,
    pub(super) qb: f64,
    pub(super) qc: f64,
    /// `d²` beyond which no pixel is evaluated: 9 for the ellipse, none for the 3DGS tiles.
    pub(super) cut: f64,
    pub(super) opacity: f64,
    pub(super) color: [f64; 3],
    /// The render's order: camera-space depth as f32 bits, then index (the CPU rasterizer's key).
    pub(super) key: u64,
    /// Inclusive pixel box, inside the image.
    pub(super) x0: u32,
    pub(super) y0: u32,
    pub(super) x1: u32,
    pub(super) y1: u32,
    /// `∂(u, v) / ∂θₖ`.
    pub(super) d_centre: [[f64; 2]; P],
    /// `∂(Σxx, Σxy, Σyy) / ∂θₖ` of the 2D covariance.
    pub(super) d_cov: [[f64; 3]; P],
}

impl Splat {
    /// `d²` of the pixel centre `(x, y)` and, with it, `∂d²/∂θₖ`: with `Δ = (x, y) − (u, v)` and
    /// `g = Σ2D⁻¹ Δ`, `d² = Δ·g` and `∂d² = −2 g·∂(u, v) − gᵀ ∂Σ2D g`.
    pub(super) fn mahalanobis(&self, x: f64, y: f64) -> (f64, [f64; P]) {
        let (dx, dy) = (x - self.u, y - self.v);
        let (gx, gy) = (self.qa * dx + self.qb * dy, self.qb * dx + self.qc * dy);
        let d2 = dx * gx + dy * gy;
        let (gxx, gxy, gyy) = (gx * gx, 2.0 * gx * gy, gy * gy);
        let mut d = [0.0; P];
        for (k, out) in d.iter_mut().enumerate() {
            let [du, dv] = self.d_centre[k];
            let [da, db, dc] = self.d_cov[k];
            *out = -2.0 * (gx * du + gy * dv) - (gxx * da + gxy * db + gyy * dc);
        }
        (d2, d)
    }

    /// `d²` alone.
    pub(super) fn d2(&self, x: f64, y: f64) -> f64 {
        let (dx, dy) = (x - self.u, y - self.v);
        dx * (self.qa * dx + self.qb * dy) + dy * (self.qb * dx + self.qc * dy)
    }
}

/// The splat of Gaussian `i`, or `None` when the forward model skips it or it reaches no pixel.
pub(super) fn project(view: &View, set: &GaussianSet, i: usize) -> Option<Splat> {
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
    if o < ALPHA_MIN {
        return None;
    }
    let q = DQuat::from_xyzw(q[1].into(), q[2].into(), q[3].into(), q[0].into());
    let norm = q.length();
    if norm == 0.0 {
        return None;
    }
    let pc = view.rotation * DVec3::new(p[0].into(), p[1].into(), p[2].into()) + view.translation;
    let z = pc.z;
    if !(z >= view.near && z <= view.far) {
        return None;
    }
    let (fx, fy) = (view.fx, view.fy);
    let (xz, yz) = (pc.x / z, pc.y / z);
    let (cxz, cyz) = (
        xz.clamp(-view.lim_x, view.lim_x),
        yz.clamp(-view.lim_y, view.lim_y),
    );
    let (clamped_x, clamped_y) = (cxz != xz, cyz != yz);
    let j0 = DVec3::new(fx / z, 0.0, -fx * cxz / z);
    let j1 = DVec3::new(0.0, fy / z, -fy * cyz / z);

    // The covariance as the rasterizer forms it: M = J W R S, Σ2D = M Mᵀ + EPS2D·I.
    let rs = DMat3::from_quat(q / norm)
        * DMat3::from_diagonal(DVec3::new(s[0].into(), s[1].into(), s[2].into()));
    let wrs = view.rotation * rs;
    let (m0, m1) = (wrs.transpose() * j0, wrs.transpose() * j1);
    let eps = f64::from(EPS2D);
    let (mxx, myy, mxy) = (m0.length_squared(), m1.length_squared(), m0.dot(m1));
    let (sxx, sxy, syy) = (mxx + eps, mxy, myy + eps);
    let det = m0.cross(m1).length_squared() + eps * (mxx + myy) + eps * eps;
    if !(det.is_finite() && det > 0.0) {
        return None;
    }
    let u = fx * xz + view.cx;
    let v = fy * yz + view.cy;

    let alpha_reach2 = 2.0 * (f64::from(o) / f64::from(ALPHA_MIN)).ln();
    let (cut, (x0, x1), (y0, y1)) = match view.footprint {
        Footprint::Ellipse => {
            let reach2 = f64::from(SIGMA_EXTENT * SIGMA_EXTENT).min(alpha_reach2);
            let extent = reach2.sqrt();
            (
                f64::from(SIGMA_EXTENT * SIGMA_EXTENT),
                pixel_span(u, extent * sxx.sqrt(), view.width)?,
                pixel_span(v, extent * syy.sqrt(), view.height)?,
            )
        }
        Footprint::Tiles3dgs => {
            let [x, y] = tiles_3dgs([u, v], [mxx, mxy, myy], eps, [view.width, view.height])?;
            (f64::INFINITY, x, y)
        }
    };

    // Derivatives. Σcam = (W R S)(W R S)ᵀ; P0 = Σcam j0 and P1 = Σcam j1 are the rows of J Σcam.
    let sigma_cam = wrs * wrs.transpose();
    let (p0, p1) = (sigma_cam * j0, sigma_cam * j1);
    let mut d_centre = [[0.0; 2]; P];
    let mut d_cov = [[0.0; 3]; P];
    for k in 0..P {
        let (dpc, d_sigma, ds) = match k {
            0..=2 => {
                let axis = DVec3::AXES[k];
                let a = skew(axis);
                (axis.cross(pc), a * sigma_cam - sigma_cam * a, 0.0)
            }
            3..=5 => (DVec3::AXES[k - 3], DMat3::ZERO, 0.0),
            _ => (DVec3::ZERO, DMat3::ZERO, 1.0),
        };
        let (dfx, dfy) = (fx * ds, fy * ds);
        let dz = dpc.z;
        let dxz = (dpc.x * z - pc.x * dz) / (z * z);
        let dyz = (dpc.y * z - pc.y * dz) / (z * z);
        let dcxz = if clamped_x { -cxz * ds } else { dxz };
        let dcyz = if clamped_y { -cyz * ds } else { dyz };
        let dj0 = DVec3::new(
            dfx / z - fx * dz / (z * z),
            0.0,
            -(dfx * cxz + fx * dcxz) / z + fx * cxz * dz / (z * z),
        );
        let dj1 = DVec3::new(
            0.0,
            dfy / z - fy * dz / (z * z),
            -(dfy * cyz + fy * dcyz) / z + fy * cyz * dz / (z * z),
        );
        let (ds0, ds1) = (d_sigma * j0, d_sigma * j1);
        d_cov[k] = [
            2.0 * dj0.dot(p0) + j0.dot(ds0),
            dj0.dot(p1) + p0.dot(dj1) + j0.dot(ds1),
            2.0 * dj1.dot(p1) + j1.dot(ds1),
        ];
        d_centre[k] = [dfx * xz + fx * dxz, dfy * yz + fy * dyz];
    }

    Some(Splat {
        u,
        v,
        qa: syy / det,
        qb: -sxy / det,
        qc: sxx / det,
        cut,
        opacity: f64::from(o),
        color: c.map(f64::from),
        key: (u64::from((z as f32).to_bits()) << 32) | i as u64,
        x0,
        y0,
        x1,
        y1,
        d_centre,
        d_cov,
    })
}

/// Pixels `i` (inclusive, inside `0..size`) whose centre `i + 0.5` may lie within `radius` of
/// `centre`, with a pixel of slack; the exact test at each pixel decides. The rasterizer's rule.
fn pixel_span(centre: f64, radius: f64, size: u32) -> Option<(u32, u32)> {
    let lo = (centre - radius - 0.5).floor() - 1.0;
    let hi = (centre + radius - 0.5).ceil() + 1.0;
    if !(lo.is_finite() && hi.is_finite()) || hi < 0.0 || lo > f64::from(size - 1) {
        return None;
    }
    // Both are within [0, size - 1] after clamping, so the casts are exact.
    Some((lo.max(0.0) as u32, hi.min(f64::from(size - 1)) as u32))
}
