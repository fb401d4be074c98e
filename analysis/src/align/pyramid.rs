//! The coarse-to-fine pyramid alignment runs on: the target frame box-downsampled by 2 per level
//! and, with it, the camera's intrinsics.
//!
//! Level `l` has pixels `2^l` times the size: pixel `(i, j)` is the mean of the frame's pixels
//! `[2^l·i, 2^l·(i + 1)) × [2^l·j, 2^l·(j + 1))` (a row or column left over at an odd size is
//! dropped), so pixel coordinates divide by `2^l` exactly and so do `fx, fy, cx, cy`. Why coarse
//! to fine: a splat a few pixels wide gives a gradient only within its own width, so a start
//! several pixels off sees little; at a coarser level the same error is a fraction of a pixel
//! and the blur of the box widens every basin. The coarse render is the forward model at the
//! coarse camera (its 0.3 px² dilation in coarse pixels, a little blurrier than the box-filtered
//! frame), which only coarse levels see: the finest level is the frame itself.

use c4g_scene::{Camera, Intrinsics, SceneError};

/// The smallest image side a level may have: below it a level holds too few pixels to constrain
/// six parameters.
pub(super) const MIN_LEVEL_SIDE: u32 = 16;

/// One level: the camera at its size and the target's RGB there (f64, 3 a pixel).
pub(super) struct Level {
    pub(super) camera: Camera,
    pub(super) target: Vec<f64>,
}

/// How many levels a `width` × `height` frame gets by default: every halving whose smaller side
/// stays at least [`MIN_LEVEL_SIDE`] (3 at 64², 4 at 224²), at least one.
pub(super) fn default_levels(width: u32, height: u32) -> usize {
    let mut side = width.min(height);
    let mut levels = 1;
    while side / 2 >= MIN_LEVEL_SIDE {
        side /= 2;
        levels += 1;
    }
    levels
}

/// Levels `0..levels`, finest first. `target` is RGB at the camera's size (checked by the
/// caller).
pub(super) fn build(
    target: &[f32],
    camera: &Camera,
    levels: usize,
) -> Result<Vec<Level>, SceneError> {
    let mut out = vec![Level {
        camera: *camera,
        target: target.iter().map(|&v| f64::from(v)).collect(),
    }];
    for _ in 1..levels {
        let Some(last) = out.last() else { break };
        let (w, h) = (last.camera.width(), last.camera.height());
        let (w2, h2) = (w / 2, h / 2);
        if w2 == 0 || h2 == 0 {
            break;
        }
        let mut rgb = vec![0.0; (w2 * h2 * 3) as usize];
        let (w, w2) = (w as usize, w2 as usize);
        for j in 0..h2 as usize {
            for i in 0..w2 {
                for c in 0..3 {
                    let at = |x: usize, y: usize| last.target[3 * (y * w + x) + c];
                    rgb[3 * (j * w2 + i) + c] = 0.25
                        * (at(2 * i, 2 * j)
                            + at(2 * i + 1, 2 * j)
                            + at(2 * i, 2 * j + 1)
                            + at(2 * i + 1, 2 * j + 1));
                }
            }
        }
        let k = last.camera.intrinsics();
        let intrinsics = Intrinsics {
            fx: k.fx / 2.0,
            fy: k.fy / 2.0,
            cx: k.cx / 2.0,
            cy: k.cy / 2.0,
            width: w2 as u32,
            height: h2,
        };
        let camera = Camera::new(intrinsics, last.camera.world_to_camera())?;
        out.push(Level {
            camera,
            target: rgb,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use glam::Affine3A;

    use super::*;
    use c4g_scene::NormalizedIntrinsics;

    #[test]
    fn default_levels_keep_the_smallest_side_at_sixteen_pixels() {
        assert_eq!(default_levels(64, 64), 3);
        assert_eq!(default_levels(224, 224), 4);
        assert_eq!(default_levels(20, 300), 1);
        assert_eq!(default_levels(8, 8), 1);
    }

    #[test]
    fn each_level_averages_two_by_two_and_halves_the_intrinsics() {
        let k = NormalizedIntrinsics::C4G_DEFAULT.to_pixels(5, 4);
        let camera = Camera::new(k, Affine3A::IDENTITY).unwrap_or_else(|e| panic!("{e}"));
        let target: Vec<f32> = (0..5 * 4 * 3).map(|v| v as f32).collect();
        let levels = build(&target, &camera, 3).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(levels.len(), 3);
        let l1 = &levels[1];
        assert_eq!((l1.camera.width(), l1.camera.height()), (2, 2));
        // Pixel (1, 1) of level 1 is the mean of pixels (2..4, 2..4), red channel.
        let red = |x: usize, y: usize| f64::from(target[3 * (y * 5 + x)]);
        let want = 0.25 * (red(2, 2) + red(3, 2) + red(2, 3) + red(3, 3));
        assert_eq!(l1.target[3 * 3], want);
        assert_eq!(l1.camera.intrinsics().cx, k.cx / 2.0);
        assert_eq!(levels[2].camera.intrinsics().fx, k.fx / 4.0);
        assert_eq!(
            (levels[2].camera.width(), levels[2].camera.height()),
            (1, 1)
        );
    }
}
