//! `c4g stream`: Gaussian sets over a time range, over gRPC, to `.ply` files or one line each.

use std::path::PathBuf;

use anyhow::Context as _;
use c4g_client::{Compact, Precision, Spacing, StreamOptions};
use futures_util::StreamExt;
use serde_json::json;

use super::decode::ApproximationArgs;
use super::{Context, emit_json, emit_line, secs};

/// The values of `--precision`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum PrecisionArg {
    F32,
    F16,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The clip id.
    clip: String,
    #[command(flatten)]
    range: RangeArgs,
    /// Precision on the wire; f16 halves the transfer.
    #[arg(long, value_enum, default_value = "f32")]
    precision: PrecisionArg,
    /// Receive the compact 4D stream (C4GV) with positions within this many scene units (1e-5
    /// to 1; e.g. 1e-3), a fraction of the bytes of f32 sets.
    #[arg(long, value_name = "UNITS")]
    compact: Option<f64>,
    /// Write one .ply per set into this directory (frame-00000-t0.500.ply, ...).
    #[arg(short, long, value_name = "DIR")]
    output: Option<PathBuf>,
    #[command(flatten)]
    approximation: ApproximationArgs,
}

/// A time range and its spacing (stream, export).
#[derive(Debug, clap::Args)]
pub(super) struct RangeArgs {
    /// First time, seconds (default: the context span's start).
    #[arg(long, allow_negative_numbers = true)]
    pub(super) start: Option<f64>,
    /// Last time, seconds (default: the context span's end).
    #[arg(long, allow_negative_numbers = true)]
    pub(super) end: Option<f64>,
    /// One set every STEP seconds.
    #[arg(long, conflicts_with = "fps")]
    pub(super) step: Option<f64>,
    /// FPS sets per second (default: the clip's frame rate).
    #[arg(long)]
    pub(super) fps: Option<f64>,
}

impl RangeArgs {
    /// The spacing the flags ask for (none: the server's choice).
    pub(super) fn spacing(&self) -> Option<Spacing> {
        match (self.step, self.fps) {
            (Some(step), _) => Some(Spacing::Step(step)),
            (None, Some(fps)) => Some(Spacing::Fps(fps)),
            (None, None) => None,
        }
    }

    /// Whether any of the flags is given.
    pub(super) fn given(&self) -> bool {
        self.start.is_some() || self.end.is_some() || self.spacing().is_some()
    }
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    let options = StreamOptions {
        start: args.range.start,
        end: args.range.end,
        spacing: args.range.spacing(),
        precision: match args.precision {
            PrecisionArg::F32 => Precision::F32,
            PrecisionArg::F16 => Precision::F16,
        },
        approximation: args.approximation.approximation(),
        compact: args.compact.map(|position_error| Compact {
            position_error,
            ..Compact::default()
        }),
    };
    if let Some(dir) = &args.output {
        tokio::fs::create_dir_all(dir)
            .await
            .with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut frames = cx.client.stream(&args.clip, &options).await?;
    let mut index = 0usize;
    while let Some(frame) = frames.next().await {
        let frame = frame?;
        let path = match &args.output {
            Some(dir) => {
                let path = dir.join(format!("frame-{index:05}-t{}.ply", secs(frame.time)));
                let (set, file) = (frame.gaussians.clone(), path.clone());
                // The PLY writer is synchronous; keep it off the runtime's thread.
                tokio::task::spawn_blocking(move || c4g_formats::ply::write(&file, &set)).await??;
                Some(path)
            }
            None => None,
        };
        let count = frame.gaussians.len();
        if cx.json {
            let mut line = json!({ "t": frame.time, "count": count });
            if let Some(path) = &path {
                line["path"] = json!(path);
            }
            emit_json(&line)?;
        } else {
            match &path {
                Some(path) => emit_line(format!(
                    "t={}  {count} Gaussians  {}",
                    secs(frame.time),
                    path.display()
                ))?,
                None => emit_line(format!("t={}  {count} Gaussians", secs(frame.time)))?,
            }
        }
        index += 1;
    }
    Ok(())
}
