//! `c4g upload`: send a clip, with a progress bar while the bytes go out and a spinner while the
//! server encodes.

use std::io::IsTerminal as _;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use c4g_client::UploadOptions;
use indicatif::{ProgressBar, ProgressStyle};

use super::{Context, clip_summary, emit, emit_json};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// A video (.mp4, .mov, .mkv, .webm, .avi), an image archive (.zip, .tar), an image, or a
    /// directory of PNG/JPEG frames (uploaded in name order).
    path: PathBuf,
    /// Frame rate of image frames without timestamps (server default 10).
    #[arg(long)]
    fps: Option<f64>,
    /// Explicit times of image frames, seconds, comma-separated and strictly increasing.
    #[arg(long, value_delimiter = ',')]
    timestamps: Vec<f64>,
    /// At most this many context frames, spread evenly.
    #[arg(long)]
    max_frames: Option<u32>,
    /// Take every STRIDE-th frame instead of spreading evenly.
    #[arg(long)]
    stride: Option<u32>,
    /// Only frames at or after this time (seconds).
    #[arg(long)]
    start: Option<f64>,
    /// Only frames at or before this time (seconds).
    #[arg(long)]
    end: Option<f64>,
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    let options = UploadOptions {
        fps: args.fps,
        timestamps: args.timestamps,
        max_frames: args.max_frames,
        stride: args.stride,
        start: args.start,
        end: args.end,
    };
    let bar = progress_bar(cx.json);
    let clip = {
        let bar = bar.clone();
        let encoding = AtomicBool::new(false);
        let progress = move |sent: u64, total: u64| {
            bar.set_length(total);
            bar.set_position(sent);
            if sent == total && total > 0 && !encoding.swap(true, Ordering::Relaxed) {
                bar.set_message("encoding on the server…");
                bar.enable_steady_tick(Duration::from_millis(120));
            }
        };
        cx.client
            .upload(args.path.as_path(), &options, progress)
            .await
    };
    bar.finish_and_clear();
    let clip = clip?;
    if cx.json {
        emit_json(&clip)
    } else {
        emit(&clip_summary(&clip))
    }
}

/// A byte progress bar on stderr, hidden when stderr is not a terminal (logs, pipes) or the
/// output is JSON (a script is reading).
fn progress_bar(json: bool) -> ProgressBar {
    if json || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(0);
    if let Ok(style) = ProgressStyle::with_template(
        "{spinner} uploading [{wide_bar}] {binary_bytes}/{binary_total_bytes} \
         {binary_bytes_per_sec} {msg}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar
}
