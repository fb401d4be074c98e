//! `c4g render`: an image at one time, or a video along a camera trajectory.

use std::path::PathBuf;

use anyhow::{Context as _, bail};
use c4g_client::{RenderFormat, RenderRequest, TrajectoryPreset};
use indicatif::HumanBytes;
use serde_json::json;

use super::decode::ApproximationArgs;
use super::{Context, emit_json, emit_line, secs, write_file};

/// The formats of `--format`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum Format {
    /// RGB PNG.
    Png,
    /// Raw little-endian f32 expected depth, row-major.
    Depth,
    /// Raw little-endian f32 accumulated opacity, row-major.
    Alpha,
    /// H.264 video (trajectories).
    Mp4,
    /// Raw little-endian f32 lifted features, [H, W, F] (a package with a feature decoder).
    Features,
    /// The lifted features coloured by the clip's fixed PCA basis, RGB PNG.
    FeaturesPca,
}

impl From<Format> for RenderFormat {
    fn from(format: Format) -> Self {
        match format {
            Format::Png => RenderFormat::Png,
            Format::Depth => RenderFormat::Depth,
            Format::Alpha => RenderFormat::Alpha,
            Format::Mp4 => RenderFormat::Mp4,
            Format::Features => RenderFormat::Features,
            Format::FeaturesPca => RenderFormat::FeaturesPca,
        }
    }
}

#[derive(Debug, clap::Args)]
#[command(group = clap::ArgGroup::new("path").args(["orbit", "trajectory"]))]
pub struct Args {
    /// The clip id.
    clip: String,
    /// Time of a single image, seconds (default: the start of the clip's context span).
    #[arg(
        long = "t",
        value_name = "T",
        conflicts_with = "path",
        allow_negative_numbers = true
    )]
    time: Option<f64>,
    /// Image width in pixels (default: the model's input width).
    #[arg(long)]
    width: Option<u32>,
    /// Image height in pixels (default: the model's input height).
    #[arg(long)]
    height: Option<u32>,
    /// Render a video orbiting by up to DEGREES around a point --depth ahead of the camera.
    #[arg(long, value_name = "DEGREES", allow_negative_numbers = true)]
    orbit: Option<f64>,
    /// Distance of the orbited point, scene units.
    #[arg(long, requires = "orbit", default_value_t = 2.0)]
    depth: f64,
    /// Render a video along a trajectory preset given as JSON, or @FILE holding it, e.g.
    /// '{"kind": "spiral", "radii": [0.1, 0.1, 0.05], "focus_depth": 2.0, "rotations": 2, "z_rate": 0.5}'.
    #[arg(long, value_name = "JSON")]
    trajectory: Option<String>,
    /// Frames of the video (server default 24).
    #[arg(long, requires = "path")]
    frames: Option<u32>,
    /// Frame rate of the video (server default 12).
    #[arg(long, requires = "path")]
    fps: Option<f64>,
    /// First time of the video (default: the context span's start).
    #[arg(long, requires = "path", allow_negative_numbers = true)]
    start: Option<f64>,
    /// Last time of the video (default: the context span's end).
    #[arg(long, requires = "path", allow_negative_numbers = true)]
    end: Option<f64>,
    /// Output format (default: from -o's extension, .png or .mp4, else the server's: png for
    /// an image, mp4 for a video).
    #[arg(long, value_enum)]
    format: Option<Format>,
    /// The file to write.
    #[arg(short, long)]
    output: PathBuf,
    /// Quality, pruning, and keyframes for a video's sets (the server refuses keyframes for a
    /// single image).
    #[command(flatten)]
    approximation: ApproximationArgs,
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    let trajectory = trajectory_arg(args.orbit, args.depth, args.trajectory.as_deref())?;
    let time = match (args.time, &trajectory) {
        (Some(t), _) => Some(t),
        (None, Some(_)) => None,
        (None, None) => {
            let clip = cx.client.clip(&args.clip).await?;
            let (start, _) = clip
                .context_span()
                .context("the clip has no context span; give --t")?;
            Some(start)
        }
    };
    let format = args.format.map(RenderFormat::from).or_else(|| {
        let extension = args.output.extension()?.to_str()?.to_ascii_lowercase();
        match extension.as_str() {
            "png" => Some(RenderFormat::Png),
            "mp4" => Some(RenderFormat::Mp4),
            _ => None,
        }
    });
    let request = RenderRequest {
        t: time,
        width: args.width,
        height: args.height,
        format,
        trajectory,
        frames: args.frames,
        start: args.start,
        end: args.end,
        fps: args.fps,
        approximation: args.approximation.approximation(),
        ..RenderRequest::default()
    };
    let rendered = cx.client.render(&args.clip, &request).await?;
    write_file(&args.output, &rendered.data).await?;
    if cx.json {
        return emit_json(&json!({
            "path": args.output,
            "content_type": rendered.content_type,
            "bytes": rendered.data.len(),
            "width": rendered.width,
            "height": rendered.height,
            "channels": rendered.channels,
            "t": time,
            "scene": rendered.scene,
        }));
    }
    let mut details = vec![rendered.content_type.clone()];
    if let Some(scene) = rendered.scene {
        details.push(format!("{} scene", scene.name()));
    }
    if let (Some(w), Some(h)) = (rendered.width, rendered.height) {
        details.push(format!("{w}x{h}"));
    }
    if let Some(c) = rendered.channels {
        details.push(format!("{c} channels"));
    }
    if let Some(t) = time {
        details.push(format!("t={}", secs(t)));
    }
    details.push(HumanBytes(rendered.data.len() as u64).to_string());
    emit_line(format!(
        "wrote {} ({})",
        args.output.display(),
        details.join(", ")
    ))
}

/// The path `--orbit DEGREES [--depth D]` or `--trajectory` asks for (clap lets only one through).
pub(super) fn trajectory_arg(
    orbit: Option<f64>,
    depth: f64,
    trajectory: Option<&str>,
) -> anyhow::Result<Option<serde_json::Value>> {
    Ok(match (orbit, trajectory) {
        (Some(angle_degrees), _) => Some(
            TrajectoryPreset::Orbit {
                depth,
                angle_degrees,
            }
            .to_json(),
        ),
        (None, Some(text)) => Some(parse_trajectory(text)?),
        (None, None) => None,
    })
}

/// A trajectory preset from `--trajectory`: JSON, or `@FILE`. Only its shape is checked here
/// (an object with a `kind`); the server judges the preset.
pub(super) fn parse_trajectory(text: &str) -> anyhow::Result<serde_json::Value> {
    let (json, origin) = match text.strip_prefix('@') {
        Some(path) => (
            std::fs::read_to_string(path).with_context(|| format!("reading {path}"))?,
            path.to_owned(),
        ),
        None => (text.to_owned(), "--trajectory".to_owned()),
    };
    let value: serde_json::Value =
        serde_json::from_str(&json).with_context(|| format!("{origin} is not JSON"))?;
    if value.get("kind").and_then(|k| k.as_str()).is_none() {
        bail!(
            "{origin} must be a JSON object with a \"kind\" (orbit, spiral or dolly), e.g. \
             {{\"kind\": \"orbit\", \"depth\": 2.0, \"angle_degrees\": 30}}"
        );
    }
    Ok(value)
}
