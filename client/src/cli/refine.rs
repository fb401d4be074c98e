//! `c4g refine`: submit a refinement job, follow it with a progress bar, and download the result.

use std::path::PathBuf;

use c4g_client::{RefineRequest, Sampler};

use super::jobs::job_summary;
use super::render::trajectory_arg;
use super::{Context, emit, emit_json, emit_line, follow, write_file};

/// The values of `--sampler`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum SamplerArg {
    /// UniPC, order 2 (VACE-layout workers' default).
    Unipc,
    /// Euler on diffusers' schedule.
    Euler,
    /// Euler on DiffSynth's schedule, as C4G's own pipeline runs it (C4G-layout workers' default).
    DiffsynthEuler,
}

#[derive(Debug, clap::Args)]
#[command(group = clap::ArgGroup::new("path").args(["orbit", "trajectory"]))]
pub struct Args {
    /// The clip id.
    clip: String,
    /// Orbit by up to DEGREES around a point --depth ahead of the camera (default: the first
    /// context camera, still).
    #[arg(long, value_name = "DEGREES", allow_negative_numbers = true)]
    orbit: Option<f64>,
    /// Distance of the orbited point, scene units.
    #[arg(long, value_name = "D", requires = "orbit", default_value_t = 2.0)]
    depth: f64,
    /// A trajectory preset given as JSON, or @FILE holding it, e.g.
    /// '{"kind": "dolly", "distance": 0.5}'.
    #[arg(long, value_name = "JSON")]
    trajectory: Option<String>,
    /// First time of the novel views, seconds (default: the context span's start).
    #[arg(long, allow_negative_numbers = true)]
    start: Option<f64>,
    /// Last time of the novel views, seconds (default: the context span's end).
    #[arg(long, allow_negative_numbers = true)]
    end: Option<f64>,
    /// Denoising steps (default: the worker's layout's, 30 for VACE's, 50 for C4G's): the main
    /// speed / quality trade.
    #[arg(long, value_name = "N")]
    steps: Option<u32>,
    /// Classifier-free guidance (server default 5; 1 skips the unconditional pass).
    #[arg(long, value_name = "G")]
    guidance: Option<f64>,
    /// Flow shift (default 3 for VACE's layout, 5 for C4G's).
    #[arg(long, value_name = "S")]
    shift: Option<f64>,
    /// The sampler (default unipc for VACE's layout, diffsynth-euler for C4G's).
    #[arg(long, value_enum)]
    sampler: Option<SamplerArg>,
    /// Noise seed (server default 0).
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// A caption of the scene (the prompt).
    #[arg(long, value_name = "TEXT")]
    caption: Option<String>,
    /// What the result should not look like (the negative prompt; default empty).
    #[arg(long, value_name = "TEXT")]
    negative_prompt: Option<String>,
    /// Context frames to condition on (default: all of the clip's, as many as fit; a C4G-layout
    /// worker takes exactly its keyframe count).
    #[arg(long, value_name = "N")]
    context_frames: Option<usize>,
    /// Where to write the refined video (default: `<job-id>.mp4`).
    #[arg(short, long, value_name = "OUT.mp4", conflicts_with = "no_wait")]
    output: Option<PathBuf>,
    /// Print the queued job and return instead of following it (`c4g job ID` describes it
    /// later).
    #[arg(long)]
    no_wait: bool,
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    let trajectory = trajectory_arg(args.orbit, args.depth, args.trajectory.as_deref())?;
    let request = RefineRequest {
        trajectory,
        start: args.start,
        end: args.end,
        steps: args.steps,
        guidance: args.guidance,
        shift: args.shift,
        sampler: args.sampler.map(|sampler| match sampler {
            SamplerArg::Unipc => Sampler::Unipc,
            SamplerArg::Euler => Sampler::Euler,
            SamplerArg::DiffsynthEuler => Sampler::DiffsynthEuler,
        }),
        seed: args.seed,
        caption: args.caption,
        negative_prompt: args.negative_prompt,
        context_frames: args.context_frames,
        ..RefineRequest::default()
    };
    let job = cx.client.refine(&args.clip, &request).await?;
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
    let output = args
        .output
        .unwrap_or_else(|| PathBuf::from(format!("{}.mp4", job.id)));
    let video = cx.client.job_result(&job.id).await?;
    write_file(&output, &video).await?;
    if cx.json {
        emit_json(&job)
    } else {
        emit_line(format!("wrote {}", output.display()))
    }
}
