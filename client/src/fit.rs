//! Fit jobs: [`Client::fit`] submits one (`POST /v1/clips/{id}/fit`), a `c4g-fitter` worker
//! optimises the clip's scene against the clip's own frames, and the result is the clip's fitted
//! scene, which [`Clip::fitted`](crate::Clip::fitted) summarises ([`FittedSummary`]) and every
//! decode, render, stream, export and track then serves (`Scene::Auto`).
//!
//! A fit is followed like any job ([`Client::job_events`]); its progress carries the fit's
//! numbers ([`JobProgress::loss`](crate::JobProgress::loss) and the fields beside it).

use reqwest::StatusCode;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use crate::client::json;
use crate::{Client, Error, Job};

/// The named starting points of a fit (`fit/src/preset.rs` has their numbers;
/// `docs/tradeoffs.md` what each buys).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FitPreset {
    /// About a minute on two cores.
    Fast,
    /// About five minutes on two cores (the server's default).
    #[default]
    Default,
    /// More steps and Gaussians.
    Best,
}

impl FitPreset {
    /// The name the API knows it by.
    pub fn name(self) -> &'static str {
        match self {
            Self::Fast => "fast",
            Self::Default => "default",
            Self::Best => "best",
        }
    }
}

/// A fit request, as `docs/api.md` ("Fitting") describes its JSON. Every field is optional: the
/// preset's value stands for a field left out, and fields left `None` are not sent.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FitRequest {
    /// The preset (server default: `default`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub preset: Option<FitPreset>,
    /// Optimisation steps, one training frame each (0: the feed-forward sets at the keyframes,
    /// unchanged).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub steps: Option<u64>,
    /// Long side of the working frames, pixels (never above the kept frames').
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resolution: Option<u32>,
    /// Most Gaussians per keyframe: densification grows the scene up to it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_gaussians: Option<u64>,
    /// A keyframe every this many kept source frames between the context times (0: the context
    /// times alone).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub keyframe_every: Option<u64>,
    /// Every this-many-th frame is held out and scored, never trained on (0: none).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub holdout_every: Option<u64>,
    /// Refine the input cameras jointly.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub refine_cameras: Option<bool>,
    /// Stop after this many seconds, wherever the steps are.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time_budget_s: Option<f64>,
    /// Seeds the frame order and densification: the same seed, the same fit.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    /// Most source frames to supervise with (spread evenly over the kept frames).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_frames: Option<u64>,
}

/// A clip's fitted scene as its record lists it (`GET /v1/clips/{id}`, `fitted`). Fields the
/// client does not name are kept in [`extra`](Self::extra).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FittedSummary {
    /// The fit job that made it.
    #[serde(default)]
    pub job_id: String,
    /// The preset it started from.
    #[serde(default)]
    pub preset: String,
    /// Gaussians per keyframe.
    #[serde(default)]
    pub gaussians: u64,
    /// Of those, the ones that share one value across keyframes.
    #[serde(default)]
    pub static_gaussians: u64,
    /// Keyframe times, seconds.
    #[serde(default)]
    pub keyframes: Vec<f64>,
    /// Optimisation steps taken.
    #[serde(default)]
    pub steps: u64,
    /// Seconds the fit took on its worker.
    #[serde(default)]
    pub seconds: f64,
    /// Source frames it was supervised by (training and held out).
    #[serde(default)]
    pub frames: u64,
    /// Working resolution (width, height) of those frames.
    #[serde(default)]
    pub resolution: [u32; 2],
    /// Indices (among the fit's frames, in time order) of the frames never trained on.
    #[serde(default)]
    pub holdout_frames: Vec<u64>,
    /// Their times, seconds.
    #[serde(default)]
    pub holdout_times: Vec<f64>,
    /// Mean PSNR (dB) of the held-out frames at their input cameras, fitted.
    #[serde(default)]
    pub holdout_psnr: Option<f64>,
    /// The same frames' PSNR from the feed-forward scene the fit started from.
    #[serde(default)]
    pub holdout_psnr_feed_forward: Option<f64>,
    /// Mean PSNR of the training frames, fitted.
    #[serde(default)]
    pub train_psnr: Option<f64>,
    /// The fit stopped before its steps (its time budget ran out).
    #[serde(default)]
    pub stopped_early: bool,
    /// Unix seconds.
    #[serde(default)]
    pub created_at: u64,
    /// What a person should know about the fit beyond its numbers (a camera that probably
    /// moved); usually empty.
    #[serde(default)]
    pub notes: Vec<String>,
    /// Everything else the server reported.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

impl FittedSummary {
    /// What fitting gained on the held-out frames, dB (`None` without held-out frames).
    pub fn holdout_gain(&self) -> Option<f64> {
        Some(self.holdout_psnr? - self.holdout_psnr_feed_forward?)
    }
}

impl Client {
    /// Submits a fit of a clip (`POST /v1/clips/{id}/fit`); the server answers `202` with the
    /// queued job (`kind` `fit`). Takes a [`FitRequest`] or any serialisable request.
    pub async fn fit<R: Serialize + ?Sized>(
        &self,
        clip_id: &str,
        request: &R,
    ) -> Result<Job, Error> {
        let url = self.url(&["v1", "clips", clip_id, "fit"]);
        let response = self.send(self.http().post(url).json(request)).await?;
        if response.status() != StatusCode::ACCEPTED {
            return Err(Error::Malformed(format!(
                "a fit is answered 202 Accepted, not {}",
                response.status()
            )));
        }
        json(response).await
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn a_request_sends_only_the_fields_given() {
        assert_eq!(
            serde_json::to_value(FitRequest::default()).unwrap(),
            json!({})
        );
        let request = FitRequest {
            preset: Some(FitPreset::Fast),
            steps: Some(8),
            resolution: Some(32),
            time_budget_s: Some(1.5),
            ..FitRequest::default()
        };
        assert_eq!(
            serde_json::to_value(request).unwrap(),
            json!({"preset": "fast", "steps": 8, "resolution": 32, "time_budget_s": 1.5})
        );
    }

    #[test]
    fn a_summary_reads_the_servers_record_and_writes_it_back() {
        let record = json!({
            "job_id": "job-1", "preset": "fast", "gaussians": 900, "static_gaussians": 600,
            "keyframes": [0.0, 0.3, 0.6], "steps": 8, "seconds": 1.25, "frames": 8,
            "resolution": [32, 32], "holdout_frames": [3, 7], "holdout_times": [0.3, 0.7],
            "holdout_psnr": 21.5, "holdout_psnr_feed_forward": 15.0, "train_psnr": 22.0,
            "stopped_early": false, "created_at": 1, "notes": ["a note"], "new_field": "kept"
        });
        let summary: FittedSummary = serde_json::from_value(record.clone()).unwrap();
        assert_eq!((summary.gaussians, summary.static_gaussians), (900, 600));
        assert_eq!(summary.holdout_gain(), Some(6.5));
        assert_eq!(summary.notes, ["a note"]);
        assert_eq!(serde_json::to_value(&summary).unwrap(), record);
        let unscored: FittedSummary = serde_json::from_value(
            json!({"holdout_psnr": null, "holdout_psnr_feed_forward": null}),
        )
        .unwrap();
        assert_eq!(unscored.holdout_gain(), None);
    }
}
