//! The frames renders are compared with: checked once, the same way for camera recovery and for
//! the scale fit of given cameras.

use c4g_scene::{Camera, SceneError};

/// A frame to compare renders with: RGB floats at `camera`'s size, all finite.
pub(crate) fn check_target(target: &[f32], camera: &Camera) -> Result<(), SceneError> {
    let (w, h) = (camera.width() as usize, camera.height() as usize);
    if target.len() != w * h * 3 {
        return Err(SceneError::InvalidImage(format!(
            "the target frame holds {} floats, but the camera renders {w}x{h} pixels, which is \
             {} RGB floats: give the frame at the camera's size (or the camera at the frame's)",
            target.len(),
            w * h * 3
        )));
    }
    if let Some(i) = target.iter().position(|v| !v.is_finite()) {
        return Err(SceneError::InvalidImage(format!(
            "the target frame has a non-finite value {} at pixel {} (channel {})",
            target[i],
            i / 3,
            i % 3
        )));
    }
    Ok(())
}
