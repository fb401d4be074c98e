//! The command line: global flags, the subcommands (one file each), and the output helpers they
//! share. Results go to stdout (text, or JSON with `--json`); progress and notes go to stderr.

mod cameras;
mod decode;
mod delete;
mod export;
mod fit;
mod follow;
mod info;
mod jobs;
mod refine;
mod render;
mod segment;
mod stream;
mod track;
mod upload;

use std::fmt::Write as _;
use std::io::Write as _;

use anyhow::Context as _;
use c4g_client::{Client, Clip, Model};
use clap::{Parser, Subcommand};
use indicatif::HumanBytes;

/// Talk to a c4g server: upload a clip, then decode, render and stream its 3D Gaussians, fit its
/// scene to its own frames, and refine novel views of it.
#[derive(Debug, Parser)]
#[command(name = "c4g", version)]
pub struct Cli {
    /// The server's base URL.
    #[arg(
        long,
        global = true,
        env = "C4G_SERVER",
        default_value = "http://127.0.0.1:8080"
    )]
    server: String,
    /// API key, sent as `Authorization: Bearer <key>` (REST and gRPC).
    #[arg(long, global = true, env = "C4G_API_KEY", hide_env_values = true)]
    api_key: Option<String>,
    /// Machine-readable JSON on stdout instead of text.
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Upload a video, an image archive (.zip, .tar) or a directory of images; waits for the
    /// encode and prints the clip.
    Upload(upload::Args),
    /// The served model and the stored clips, or one clip.
    Info(info::InfoArgs),
    /// List the stored clips.
    Clips,
    /// Delete a clip.
    Delete(delete::Args),
    /// Decode the Gaussians at one or more times: a summary, or the server's bytes.
    Decode(decode::DecodeArgs),
    /// Write the Gaussians at one time to a .ply or .splat file, or a time range to one 4D file
    /// other viewers open (.ply.zip, .spz.zip, .splatv).
    Export(export::Args),
    /// Render an image, or a video along a camera trajectory.
    Render(render::Args),
    /// Stream Gaussian sets over a time range (gRPC), to .ply files or one line per set.
    Stream(stream::Args),
    /// A clip's cameras, given at upload or recovered; --recover recovers them by photometric
    /// alignment of the model's own Gaussians.
    Cameras(cameras::Args),
    /// Track points seen in an input frame: where each is at other times, and whether it is
    /// visible there.
    Track(track::Args),
    /// Select the Gaussians whose lifted feature is like a clicked pixel's (or a given feature),
    /// and their masks at other times (a package with a feature decoder).
    Segment(segment::Args),
    /// Fit the clip's scene to its own frames (a c4g-fitter worker runs it): submit a job,
    /// follow it, and print the fitted scene's held-out PSNR beside the feed-forward answer's.
    /// Requests then serve the fitted scene (--scene picks one).
    Fit(fit::Args),
    /// Refine novel views with the video diffusion model: submit a job, follow it, and download
    /// the refined video.
    Refine(refine::Args),
    /// Describe a job (a fit or a refinement).
    Job(jobs::JobArgs),
    /// List the jobs (fits and refinements).
    Jobs,
    /// Cancel a job (a running one stops at its worker's next step).
    Cancel(jobs::JobArgs),
}

/// What every command gets: the client and the output mode.
struct Context {
    client: Client,
    json: bool,
}

/// Runs the parsed command line.
pub async fn run(cli: Cli) -> anyhow::Result<()> {
    let client = Client::new(&cli.server, cli.api_key.as_deref())?;
    let cx = Context {
        client,
        json: cli.json,
    };
    match cli.command {
        Command::Upload(args) => upload::run(&cx, args).await,
        Command::Info(args) => info::run(&cx, args).await,
        Command::Clips => info::clips(&cx).await,
        Command::Delete(args) => delete::run(&cx, args).await,
        Command::Decode(args) => decode::run(&cx, args).await,
        Command::Export(args) => export::run(&cx, args).await,
        Command::Render(args) => render::run(&cx, args).await,
        Command::Stream(args) => stream::run(&cx, args).await,
        Command::Track(args) => track::run(&cx, args).await,
        Command::Segment(args) => segment::run(&cx, args).await,
        Command::Cameras(args) => cameras::run(&cx, args).await,
        Command::Fit(args) => fit::run(&cx, args).await,
        Command::Refine(args) => refine::run(&cx, args).await,
        Command::Job(args) => jobs::job(&cx, args).await,
        Command::Jobs => jobs::jobs(&cx).await,
        Command::Cancel(args) => jobs::cancel(&cx, args).await,
    }
}

/// Writes text to stdout.
fn emit(text: &str) -> anyhow::Result<()> {
    emit_bytes(text.as_bytes())
}

/// Writes bytes to stdout. A closed pipe (`c4g clips | head -1`) ends the program quietly, as it
/// does for other command-line tools, instead of failing with an error.
fn emit_bytes(bytes: &[u8]) -> anyhow::Result<()> {
    let mut stdout = std::io::stdout().lock();
    match stdout.write_all(bytes).and_then(|()| stdout.flush()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => std::process::exit(0),
        other => other.context("writing to stdout"),
    }
}

/// Writes one line to stdout.
fn emit_line(line: impl std::fmt::Display) -> anyhow::Result<()> {
    emit(&format!("{line}\n"))
}

/// Writes a value as one line of compact JSON.
fn emit_json(value: &impl serde::Serialize) -> anyhow::Result<()> {
    emit_line(serde_json::to_string(value)?)
}

/// Writes bytes to a file, with the path in the error.
async fn write_file(path: &std::path::Path, data: &[u8]) -> anyhow::Result<()> {
    tokio::fs::write(path, data)
        .await
        .with_context(|| format!("writing {}", path.display()))
}

/// Seconds, as every command prints them.
fn secs(t: f64) -> String {
    format!("{t:.3}")
}

/// A clip's id on the first line (scripts take it with `head -1`), then what it holds.
fn clip_summary(clip: &Clip) -> String {
    let mut text = format!("{}\n", clip.id);
    let state = match clip.created {
        Some(true) => format!("{} (created)", clip.state),
        Some(false) => format!("{} (already uploaded; not encoded again)", clip.state),
        None => clip.state.clone(),
    };
    let _ = writeln!(text, "  state     {state}");
    if !clip.model.is_empty() {
        let _ = writeln!(text, "  model     {}", clip.model);
    }
    let _ = writeln!(
        text,
        "  context   {} frames at {} s",
        clip.context_times.len(),
        times_list(&clip.context_times)
    );
    if let Some((start, end)) = clip.context_span() {
        let _ = writeln!(text, "  span      {} .. {} s", secs(start), secs(end));
    }
    if let Some(source) = &clip.source {
        let mut parts = vec![source.kind.clone()];
        if let Some(frames) = source.frames {
            parts.push(format!("{frames} frames"));
        }
        if let (Some(w), Some(h)) = (source.width, source.height) {
            parts.push(format!("{w}x{h}"));
        }
        if let Some(duration) = source.duration {
            parts.push(format!("{} s", secs(duration)));
        }
        if let Some(fps) = source.fps {
            parts.push(format!("{fps:.2} fps"));
        }
        let _ = writeln!(text, "  source    {}", parts.join(", "));
    }
    if let Some(bytes) = clip.feature_bytes {
        let _ = writeln!(text, "  features  {}", HumanBytes(bytes));
    }
    if let Some(fitted) = &clip.fitted {
        let _ = writeln!(
            text,
            "  fitted    {} Gaussians at {} keyframes; held-out {}",
            fitted.gaussians,
            fitted.keyframes.len(),
            fit::held_out_text(fitted)
        );
    }
    text
}

/// One line per clip, for lists.
fn clip_line(clip: &Clip) -> String {
    let span = clip
        .context_span()
        .map(|(start, end)| format!("{} .. {} s", secs(start), secs(end)))
        .unwrap_or_else(|| "-".to_owned());
    let source = clip
        .source
        .as_ref()
        .map(|s| match (s.width, s.height) {
            (Some(w), Some(h)) => format!("{} {w}x{h}", s.kind),
            _ => s.kind.clone(),
        })
        .unwrap_or_default();
    format!(
        "{}  {}  {} context frames  {span}  {source}",
        clip.id,
        clip.state,
        clip.context_times.len()
    )
}

/// A model on one line.
fn model_line(model: &Model) -> String {
    let mut line = model.name.clone();
    if let Some(version) = &model.version {
        let _ = write!(line, " {version}");
    }
    let mut details = Vec::new();
    if let Some(input) = model.input {
        details.push(format!("{}x{} input", input.width, input.height));
    }
    if let Some(count) = model.gaussians_per_set {
        details.push(format!("{count} Gaussians per set"));
    }
    if !details.is_empty() {
        let _ = write!(line, " ({})", details.join(", "));
    }
    line
}

/// Times, elided in the middle when there are many.
fn times_list(times: &[f64]) -> String {
    const SHOWN: usize = 12;
    let all: Vec<String> = times.iter().map(|&t| secs(t)).collect();
    if all.len() <= SHOWN {
        return all.join(", ");
    }
    format!(
        "{}, …, {}",
        all[..SHOWN - 3].join(", "),
        all[all.len() - 2..].join(", ")
    )
}
