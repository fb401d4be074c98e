//! `c4g upload`: send a clip, with a progress bar while the bytes go out and a spinner while the
//! server encodes.

use std::io::IsTerminal as _;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::Context as _;
use c4g_client::{UploadCameras, UploadOptions};
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
    /// Per-frame cameras as a JSON list (one object per frame: world_to_camera or
    /// camera_to_world, row-major, OpenCV axes; intrinsics as fractions of the image size).
    #[arg(long, value_name = "FILE", group = "given_cameras")]
    cameras: Option<PathBuf>,
    /// Per-frame cameras from a COLMAP text model: a directory holding cameras.txt and
    /// images.txt (images matched to frames by name order, or by --camera-names).
    #[arg(long, value_name = "DIR", group = "given_cameras")]
    colmap: Option<PathBuf>,
    /// Per-frame cameras from nerfstudio's transforms.json (frames matched by file_path order,
    /// or by --camera-names).
    #[arg(long, value_name = "FILE", group = "given_cameras")]
    transforms: Option<PathBuf>,
    /// The COLMAP image names or transforms.json file paths of the frames, in frame order.
    #[arg(long, value_delimiter = ',', requires = "given_cameras")]
    camera_names: Vec<String>,
}

/// The cameras the arguments name, read from their files.
fn cameras(args: &Args) -> anyhow::Result<Option<UploadCameras>> {
    let read = |path: &std::path::Path| {
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))
    };
    let names = args.camera_names.clone();
    Ok(match (&args.cameras, &args.colmap, &args.transforms) {
        (Some(file), _, _) => {
            anyhow::ensure!(
                names.is_empty(),
                "--camera-names is for --colmap and --transforms: a JSON list is in frame order"
            );
            Some(UploadCameras::Json(read(file)?))
        }
        (_, Some(dir), _) => Some(UploadCameras::Colmap {
            cameras: read(&dir.join("cameras.txt"))?,
            images: read(&dir.join("images.txt"))?,
            names,
        }),
        (_, _, Some(file)) => Some(UploadCameras::Transforms {
            json: read(file)?,
            names,
        }),
        _ => None,
    })
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    let cameras = cameras(&args)?;
    let options = UploadOptions {
        fps: args.fps,
        timestamps: args.timestamps,
        max_frames: args.max_frames,
        stride: args.stride,
        start: args.start,
        end: args.end,
        cameras,
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
