//! Recovered cameras (`POST /v1/clips/{id}/cameras/recover`): each context frame's camera found
//! by photometric alignment of the model's own Gaussians, kept with the clip.

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::client::json;
use crate::{Client, Error};

/// A clip's recovered cameras, as the server answers them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecoveredCameras {
    /// The cameras in the given cameras' form (`format` "recovered", `scale` 1, one `frames`
    /// entry per context frame with `t`, row-major `world_to_camera` and `intrinsics`).
    pub cameras: Value,
    /// How each was found, in the same order.
    pub fits: Vec<FrameFit>,
    /// The options they were recovered with.
    #[serde(default)]
    pub options: Value,
}

/// How one context frame's camera was found.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FrameFit {
    /// The frame's time, seconds.
    pub t: f64,
    /// Mean robust residual per colour channel at the starting camera.
    pub initial_residual: f64,
    /// The same at the recovered camera.
    pub residual: f64,
    /// How far to trust the camera, 0 to 1.
    pub confidence: f64,
    /// Mean rendered alpha at the recovered camera.
    pub coverage: f64,
    /// Smallest over largest eigenvalue of the normalised Gauss–Newton matrix.
    pub conditioning: f64,
    /// Levenberg–Marquardt steps.
    pub iterations: usize,
    /// Whether the finest level stopped by its tolerance.
    pub converged: bool,
}

impl Client {
    /// Recovers (again) the cameras of clip `clip_id`, refining one focal length for the clip
    /// too when `refine_focal`.
    pub async fn recover_cameras(
        &self,
        clip_id: &str,
        refine_focal: bool,
    ) -> Result<RecoveredCameras, Error> {
        let url = self.url(&["v1", "clips", clip_id, "cameras", "recover"]);
        let body = json!({ "refine_focal": refine_focal });
        json(self.send(self.http().post(url).json(&body)).await?).await
    }
}
