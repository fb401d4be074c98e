//! Cameras as clients state them: a row-major world-to-camera matrix and intrinsics as
//! fractions of the image size, turned into the renderer's [`Camera`] at a request's image size.
//! REST bodies and gRPC messages both arrive here.

use c4g_renderer::{Camera, NormalizedIntrinsics};
use glam::{Affine3A, Mat4};
use serde::{Deserialize, Serialize};

use crate::ServiceError;

/// A camera as a client states it: a row-major 4×4 world-to-camera matrix (OpenCV axes) and
/// intrinsics as fractions of the image size. Both default to the first context camera's.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// 16 numbers, row-major, last row 0 0 0 1.
    pub world_to_camera: Option<Vec<f32>>,
    /// Normalised intrinsics.
    pub intrinsics: Option<IntrinsicsSpec>,
}

/// Intrinsics as fractions of the image size.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntrinsicsSpec {
    /// Focal length over width.
    pub fx: f32,
    /// Focal length over height.
    pub fy: f32,
    /// Principal point x over width.
    #[serde(default = "half")]
    pub cx: f32,
    /// Principal point y over height.
    #[serde(default = "half")]
    pub cy: f32,
}

fn half() -> f32 {
    0.5
}

impl CameraSpec {
    /// The camera at `width` × `height`.
    pub fn camera(&self, width: u32, height: u32) -> Result<Camera, ServiceError> {
        let pose = match &self.world_to_camera {
            None => Affine3A::IDENTITY,
            Some(m) if m.len() == 16 => {
                let rows = Mat4::from_cols_slice(m).transpose();
                if rows.row(3) != glam::Vec4::W {
                    return Err(ServiceError::invalid(format!(
                        "world_to_camera must end in the row 0 0 0 1, got {:?}",
                        &m[12..]
                    )));
                }
                Affine3A::from_mat4(rows)
            }
            Some(m) => {
                return Err(ServiceError::invalid(format!(
                    "world_to_camera needs 16 numbers (row-major 4x4), got {}",
                    m.len()
                )));
            }
        };
        let intrinsics = self
            .intrinsics
            .map(|i| NormalizedIntrinsics {
                fx: i.fx,
                fy: i.fy,
                cx: i.cx,
                cy: i.cy,
            })
            .unwrap_or(NormalizedIntrinsics::C4G_DEFAULT);
        Ok(Camera::from_normalized(intrinsics, width, height, pose)?)
    }
}
