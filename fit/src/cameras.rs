//! Refining the input cameras with the scene ([`crate::FitOptions::refine_cameras`]): every
//! training frame's camera gets seven extra parameters, the renderer's camera tangent (a left
//! se(3) increment `[ω, ν]` of world-to-camera and the log of a scale shared by `fx` and `fy`),
//! stepped by their own Adam each time the frame is trained on.
//!
//! Each step applies the increment `δ` to the frame's current camera (`exp([ω, ν]^)·W`, the
//! rotation exactly and the translation `ν` as is, which agree to first order; focal `·exp(δ₇)`)
//! and adds it to the frame's **offset**, the running sum of its increments: to first order the
//! camera's distance from the given one in the same coordinates. A prior `w·|offset|²` pulls
//! every camera back toward the given one, so a frame that sees little cannot wander and the
//! scene cannot slide away with the cameras. Translations and their rates are in scene units
//! (scaled by the extent like positions').
//!
//! Held-out frames keep their given cameras: they are scored as the clip gave them, so a held-out
//! PSNR is never bought by moving the camera toward the frame it is scored on.

use c4g_optim::AdamConfig;
use c4g_scene::{Camera, Intrinsics};
use glam::{Affine3A, Quat, Vec3};

use crate::error::FitError;

/// The renderer's camera parameters: `[ωx, ωy, ωz, νx, νy, νz, log focal]`.
const P: usize = 7;

/// One frame's camera as refined so far.
#[derive(Debug, Clone)]
struct Refined {
    camera: Camera,
    offset: [f64; P],
    m: [f64; P],
    v: [f64; P],
    steps: u64,
}

/// The refined cameras of a fit's frames.
#[derive(Debug, Clone)]
pub(crate) struct CameraRefinement {
    frames: Vec<Refined>,
    adam: AdamConfig,
}

impl CameraRefinement {
    /// Every frame starting at its given camera.
    pub(crate) fn new(cameras: impl IntoIterator<Item = Camera>, adam: AdamConfig) -> Self {
        let frames = cameras
            .into_iter()
            .map(|camera| Refined {
                camera,
                offset: [0.0; P],
                m: [0.0; P],
                v: [0.0; P],
                steps: 0,
            })
            .collect();
        Self { frames, adam }
    }

    /// Frame `i`'s camera now.
    pub(crate) fn camera(&self, i: usize) -> &Camera {
        &self.frames[i].camera
    }

    /// Every frame's camera now, in frame order.
    pub(crate) fn cameras(&self) -> Vec<Camera> {
        self.frames.iter().map(|f| f.camera).collect()
    }

    /// One Adam step of frame `i`'s camera down `tangent` (the renderer's camera gradient at its
    /// current camera) plus the prior's `2·prior·offset`; `rates` are the rotation's (radians),
    /// the translation's (scene units) and the log focal's. Non-finite gradients are dropped; a
    /// step that would make the camera invalid is not taken.
    pub(crate) fn step(
        &mut self,
        i: usize,
        tangent: &[f64; P],
        rates: [f64; 3],
        prior: f64,
    ) -> Result<(), FitError> {
        let AdamConfig { beta1, beta2, eps } = self.adam;
        let f = &mut self.frames[i];
        f.steps += 1;
        let (c1, c2) = (
            1.0 - beta1.powf(f.steps as f64),
            1.0 - beta2.powf(f.steps as f64),
        );
        let mut delta = [0.0; P];
        for j in 0..P {
            let mut g = tangent[j] + 2.0 * prior * f.offset[j];
            if !g.is_finite() {
                g = 0.0;
            }
            f.m[j] = beta1 * f.m[j] + (1.0 - beta1) * g;
            f.v[j] = beta2 * f.v[j] + (1.0 - beta2) * g * g;
            let rate = rates[match j {
                0..3 => 0,
                3..6 => 1,
                _ => 2,
            }];
            delta[j] = -rate * (f.m[j] / c1) / ((f.v[j] / c2).sqrt() + eps);
        }
        if let Ok(moved) = apply(&f.camera, &delta) {
            f.camera = moved;
            for (o, d) in f.offset.iter_mut().zip(delta) {
                *o += d;
            }
        }
        Ok(())
    }
}

/// `camera` moved by the tangent `delta` (`[ω, ν, log focal]`, the module documentation).
pub(crate) fn apply(camera: &Camera, delta: &[f64; P]) -> Result<Camera, FitError> {
    let v = |j: usize| delta[j] as f32;
    let increment = Affine3A::from_rotation_translation(
        Quat::from_scaled_axis(Vec3::new(v(0), v(1), v(2))),
        Vec3::new(v(3), v(4), v(5)),
    );
    let scale = delta[6].exp() as f32;
    let k = camera.intrinsics();
    let intrinsics = Intrinsics {
        fx: k.fx * scale,
        fy: k.fy * scale,
        ..*k
    };
    Ok(Camera::new(
        intrinsics,
        increment * camera.world_to_camera(),
    )?)
}
