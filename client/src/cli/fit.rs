//! `c4g fit`: fit a clip's scene to its own frames: submit the job, follow it with a progress
//! bar, and print what the fit made (the clip's fitted scene, which requests then serve).

use std::fmt::Write as _;

use anyhow::Context as _;
use c4g_client::{Clip, FitPreset, FitRequest, FittedSummary};
use serde_json::json;

use super::jobs::job_summary;
use super::{Context, emit, emit_json, follow, secs};

/// The values of `--preset`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum PresetArg {
    /// About a minute on two cores.
    Fast,
    /// About five minutes on two cores.
    Default,
    /// More steps and Gaussians.
    Best,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The clip id.
    clip: String,
    /// Where the fit starts; the flags below override its values (server default: default).
    #[arg(long, value_enum)]
    preset: Option<PresetArg>,
    /// Optimisation steps, one training frame each (0: the feed-forward sets at the keyframes).
    #[arg(long, value_name = "N")]
    steps: Option<u64>,
    /// Long side of the working frames, pixels (never above the kept frames').
    #[arg(long, value_name = "PX")]
    resolution: Option<u32>,
    /// Most Gaussians per keyframe: densification grows the scene up to it.
    #[arg(long, value_name = "N")]
    max_gaussians: Option<u64>,
    /// A keyframe every N kept source frames between the context times (0: the context times
    /// alone).
    #[arg(long, value_name = "N")]
    keyframe_every: Option<u64>,
    /// Hold out every N-th frame: never trained on, scored before and after (0: none).
    #[arg(long, value_name = "N")]
    holdout_every: Option<u64>,
    /// Refine the input cameras jointly.
    #[arg(long)]
    refine_cameras: bool,
    /// Stop after S seconds, wherever the steps are.
    #[arg(long, value_name = "S")]
    time_budget: Option<f64>,
    /// Seeds the frame order and densification: the same seed, the same fit.
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// Most source frames to supervise with (spread evenly over the kept frames).
    #[arg(long, value_name = "N")]
    max_frames: Option<u64>,
    /// Print the queued job and return instead of following it (`c4g job ID` describes it
    /// later).
    #[arg(long)]
    no_wait: bool,
}

impl Args {
    fn request(&self) -> FitRequest {
        FitRequest {
            preset: self.preset.map(|preset| match preset {
                PresetArg::Fast => FitPreset::Fast,
                PresetArg::Default => FitPreset::Default,
                PresetArg::Best => FitPreset::Best,
            }),
            steps: self.steps,
            resolution: self.resolution,
            max_gaussians: self.max_gaussians,
            keyframe_every: self.keyframe_every,
            holdout_every: self.holdout_every,
            refine_cameras: self.refine_cameras.then_some(true),
            time_budget_s: self.time_budget,
            seed: self.seed,
            max_frames: self.max_frames,
        }
    }
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    let job = cx.client.fit(&args.clip, &args.request()).await?;
    if args.no_wait {
        return if cx.json {
            emit_json(&job)
        } else {
            emit(&job_summary(&job))
        };
    }
    let job = follow::to_end(cx, job).await?;
    if !job.is_done() {
        return follow::unfinished(cx, &job);
    }
    let clip = cx.client.clip(&job.clip_id).await?;
    let fitted = clip.fitted.as_ref().with_context(|| {
        format!(
            "job {} is done, but clip {} lists no fitted scene",
            job.id, clip.id
        )
    })?;
    if cx.json {
        return emit_json(&json!({ "clip": clip.id, "job": job, "fitted": fitted }));
    }
    let mut text = fitted_summary(&clip, fitted);
    if fitted.job_id != job.id {
        let _ = writeln!(
            text,
            "  note      a later fit ({}) replaced this one's scene",
            fitted.job_id
        );
    }
    emit(&text)
}

/// The clip's id on the first line (scripts take it with `head -1`), then what the fit made:
/// held-out PSNR beside the feed-forward answer's, the Gaussians, the work, and the fit's notes.
pub(super) fn fitted_summary(clip: &Clip, fitted: &FittedSummary) -> String {
    let mut text = format!("{}\n", clip.id);
    let _ = writeln!(text, "  held-out  {}", held_out_text(fitted));
    let _ = writeln!(
        text,
        "  scene     {} Gaussians ({} static) at {} keyframes",
        fitted.gaussians,
        fitted.static_gaussians,
        fitted.keyframes.len()
    );
    let [width, height] = fitted.resolution;
    let mut work = format!(
        "{} steps in {} s, {} frames at {width}x{height}",
        fitted.steps,
        secs(fitted.seconds),
        fitted.frames
    );
    if !fitted.preset.is_empty() {
        let _ = write!(work, ", preset {}", fitted.preset);
    }
    if fitted.stopped_early {
        work.push_str(", stopped early (time budget)");
    }
    let _ = writeln!(text, "  fit       {work}");
    if !fitted.job_id.is_empty() {
        let _ = writeln!(text, "  job       {}", fitted.job_id);
    }
    for note in &fitted.notes {
        let _ = writeln!(text, "  note      {note}");
    }
    text
}

/// `24.13 dB PSNR fitted, 16.70 feed-forward (+7.43 dB) on 2 frames`, or why there is none.
pub(super) fn held_out_text(fitted: &FittedSummary) -> String {
    let frames = fitted.holdout_frames.len();
    let on = format!("on {frames} frame{}", if frames == 1 { "" } else { "s" });
    match (fitted.holdout_psnr, fitted.holdout_psnr_feed_forward) {
        (Some(after), Some(before)) => format!(
            "{after:.2} dB PSNR fitted, {before:.2} feed-forward ({:+.2} dB) {on}",
            after - before
        ),
        (Some(after), None) => format!("{after:.2} dB PSNR fitted {on}"),
        _ => "none held out (holdout_every 0, or too few frames)".to_owned(),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn summary(fields: serde_json::Value) -> FittedSummary {
        serde_json::from_value(fields).unwrap()
    }

    #[test]
    fn held_out_psnr_is_shown_beside_the_feed_forward_answers() {
        let both = summary(json!({"holdout_frames": [3, 7], "holdout_psnr": 24.13,
                                  "holdout_psnr_feed_forward": 16.7}));
        assert_eq!(
            held_out_text(&both),
            "24.13 dB PSNR fitted, 16.70 feed-forward (+7.43 dB) on 2 frames"
        );
        let none = summary(json!({"holdout_frames": [], "holdout_psnr": null}));
        assert!(held_out_text(&none).starts_with("none held out"));
    }

    #[test]
    fn the_summary_starts_with_the_clip_id() {
        let clip: Clip = serde_json::from_value(json!({"id": "3f2a"})).unwrap();
        let fitted = summary(json!({
            "job_id": "job-1", "preset": "fast", "gaussians": 900, "static_gaussians": 600,
            "keyframes": [0.0, 0.6], "steps": 8, "seconds": 1.5, "frames": 8,
            "resolution": [32, 24], "holdout_frames": [3], "holdout_psnr": 20.0,
            "holdout_psnr_feed_forward": 15.0, "stopped_early": true
        }));
        let text = fitted_summary(&clip, &fitted);
        assert_eq!(
            text,
            "3f2a\n  held-out  20.00 dB PSNR fitted, 15.00 feed-forward (+5.00 dB) on 1 frame\n  \
             scene     900 Gaussians (600 static) at 2 keyframes\n  \
             fit       8 steps in 1.500 s, 8 frames at 32x24, preset fast, stopped early (time budget)\n  \
             job       job-1\n"
        );
        let noted = summary(json!({"notes": ["only 2 % of the frame stayed still"]}));
        assert!(
            fitted_summary(&clip, &noted)
                .ends_with("  note      only 2 % of the frame stayed still\n")
        );
    }
}
