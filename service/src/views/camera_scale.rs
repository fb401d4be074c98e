//! Given cameras at the model's depth scale, fitted once at upload.
//!
//! Given cameras are mapped into the model's frame by C4G's convention (translations divided by
//! the largest distance of a context camera from the first), which is the scale the model was
//! trained to predict but not necessarily the one it predicts: a model that misjudges the depth
//! draws each later context frame's Gaussians where that frame's camera does not see them, and
//! every render at the input camera is off by the same amount (c4g-tiny puts every scene at
//! about one depth; on the evaluation-only world the fit is worth 0.9-1.4 dB at interpolated
//! times: `models/c4g-tiny/README.md`). So after the encode, the Gaussians decoded at the later context
//! frames' times are rendered at their given cameras, and the one factor on the translations
//! that best matches the frames as the model saw them is kept with the cameras
//! (`c4g_analysis::align::fit_translation_scale`; `ClipCameras::scale_fit`). Decoded Gaussians,
//! exports and stated cameras are untouched: only the given cameras move to the model's scale.
//!
//! The fit is deterministic (the same upload gives the same clip record, as content addressing
//! needs) and costs 63 renders of each later context frame at the model's input size (49 grid
//! factors, 14 golden-section ones).

use c4g_analysis::align::{ScaleView, fit_translation_scale};
use c4g_engine::Encoding;
use c4g_renderer::RenderOptions;
use image::RgbImage;

use crate::ServiceError;
use crate::clips::intake::cameras::{ClipCameras, ScaleFit};
use crate::views::camera::{CameraSpec, InputSpec};
use crate::views::render::Views;

impl Views {
    /// `cameras` (one per context frame, in the encoding's order) fitted to the model's depth
    /// scale; as they are when no context camera moves. `frames` are the intake's frames, which
    /// the encoding's `frame_order` indexes.
    pub(crate) fn fit_camera_scale(
        &self,
        cameras: ClipCameras,
        encoding: &Encoding,
        frames: &[RgbImage],
    ) -> Result<ClipCameras, ServiceError> {
        if !cameras.moves() {
            return Ok(cameras);
        }
        let input = &self.engine.manifest().input;
        let (w, h) = (input.width, input.height);
        // The first context camera is the model's frame at any scale: the later ones carry it.
        let later = 1..cameras.frames.len();
        let times: Vec<f64> = cameras.frames[later.clone()].iter().map(|f| f.t).collect();
        let sets = self.sets.decode_now(encoding, &times)?;
        let mut targets = Vec::with_capacity(times.len());
        let mut poses = Vec::with_capacity(times.len());
        for k in later {
            targets.push(self.seen_by_model(&frames[encoding.frame_order()[k]])?);
            // The camera exactly as renders at the input camera will take it.
            let t = cameras.frames[k].t;
            let input = CameraSpec {
                input: Some(InputSpec {
                    at: Some(t),
                    ..InputSpec::default()
                }),
                ..CameraSpec::default()
            };
            poses.push(input.resolve(Some(&cameras), t, None)?.camera(w, h)?);
        }
        let views: Vec<ScaleView<'_>> = sets
            .iter()
            .zip(&targets)
            .zip(poses)
            .map(|(((_, set), target), camera)| ScaleView {
                set,
                target,
                camera,
            })
            .collect();
        // The package's footprint, not the server's `--footprint`: the stored record must be a
        // function of the model and the upload alone (the clip's id is).
        let options = RenderOptions {
            footprint: self.engine.manifest().footprint(),
            ..RenderOptions::default()
        };
        let fit = fit_translation_scale(&views, &options)?;
        let convention_scale = cameras.scale;
        Ok(cameras.fitted(ScaleFit {
            factor: fit.factor,
            convention_scale,
            initial_error: fit.initial_error,
            error: fit.error,
        }))
    }
}
