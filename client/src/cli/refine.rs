//! `c4g refine`: submit a refinement job, follow it with a progress bar, and download the result.

use std::io::IsTerminal as _;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::bail;
use c4g_client::{Error, Job, RefineRequest, Sampler};
use futures_util::StreamExt;
use indicatif::{ProgressBar, ProgressStyle};

use super::jobs::job_summary;
use super::render::trajectory_arg;
use super::{Context, emit, emit_json, emit_line, write_file};

/// How often in a row a lost event stream is followed again before giving up.
const RECONNECTS: u32 = 5;

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

    let mut watch = Watch::new(&job, cx.json);
    let followed = follow(cx, job, &mut watch).await;
    watch.bar.finish_and_clear();
    let job = followed?;

    match job.state.as_str() {
        "done" => {
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
        state => {
            if cx.json {
                emit_json(&job)?;
            }
            if state == "failed" {
                let error = job.error.as_deref().unwrap_or("no reason given");
                bail!("job {} failed: {error}", job.id);
            }
            bail!("job {} was {state}", job.id)
        }
    }
}

/// Follows the job's events until it ends, showing each change; a lost event stream (a server
/// restart, a dropped connection) is followed again, with a pause, a few times in a row.
async fn follow(cx: &Context, mut job: Job, watch: &mut Watch) -> anyhow::Result<Job> {
    let mut failures = 0;
    loop {
        let mut events = cx.client.job_events(&job.id);
        let error = loop {
            match events.next().await {
                Some(Ok(update)) => {
                    failures = 0;
                    watch.update(&update);
                    job = update;
                    if job.is_terminal() {
                        return Ok(job);
                    }
                }
                Some(Err(error)) => break error,
                None => {
                    break Error::Interrupted("the job's event stream ended early".to_owned());
                }
            }
        };
        // A lost connection, or a server restarting, is worth following again; an error answer
        // (404: the job is gone) or a record of another shape will not change by asking again.
        let transient = match &error {
            Error::Http(_) | Error::Interrupted(_) => true,
            other => matches!(other.status(), Some(500..=599)),
        };
        if !transient || failures >= RECONNECTS {
            return Err(error.into());
        }
        failures += 1;
        watch.note(&format!(
            "lost the job's events ({}); following again",
            with_causes(&error)
        ));
        tokio::time::sleep(Duration::from_secs(u64::from(failures))).await;
    }
}

/// What the terminal shows of a job: a line with its progress (`[====>   ] step k/n stage`, or
/// its state while it has none), and a line above it for each new history entry or attempt.
struct Watch {
    bar: ProgressBar,
    id: String,
    attempt: u32,
    history: usize,
}

impl Watch {
    /// A watch of a job just submitted; the bar is hidden for `--json` and when stderr is not a
    /// terminal.
    fn new(job: &Job, json: bool) -> Self {
        let bar = if json || !std::io::stderr().is_terminal() {
            ProgressBar::hidden()
        } else {
            // One style throughout, the step bar drawn into the message: a change of state is
            // one message, never a frame with the old values in a new style.
            let style = ProgressStyle::with_template("{spinner} {prefix} {wide_msg} {elapsed}")
                .unwrap_or_else(|_| ProgressStyle::default_spinner());
            let bar = ProgressBar::new_spinner()
                .with_style(style)
                .with_prefix(job.id.clone())
                .with_message(job.state.clone());
            bar.enable_steady_tick(Duration::from_millis(120));
            bar
        };
        let mut watch = Self {
            bar,
            id: job.id.clone(),
            attempt: job.attempt,
            history: 0,
        };
        watch.update(job);
        watch
    }

    /// A line above the bar (on stderr, bar or not).
    fn note(&self, line: &str) {
        self.bar.suspend(|| eprintln!("job {}: {line}", self.id));
    }

    fn update(&mut self, job: &Job) {
        for line in job.history.iter().skip(self.history) {
            self.note(line);
        }
        self.history = self.history.max(job.history.len());
        if job.attempt != self.attempt {
            self.attempt = job.attempt;
            self.note(&format!("attempt {} of {}", job.attempt, job.max_attempts));
        }
        let message = match (&job.progress, &job.worker) {
            (Some(progress), _) if job.state == "running" => {
                let mut text = format!(
                    "{} step {}/{}",
                    step_bar(progress.step, progress.steps),
                    progress.step,
                    progress.steps
                );
                if !progress.stage.is_empty() {
                    text.push(' ');
                    text.push_str(&progress.stage);
                }
                text
            }
            (_, Some(worker)) if job.state == "running" => format!("running on {worker}"),
            _ => job.state.clone(),
        };
        self.bar.set_message(message);
    }
}

/// `[=====>      ]`: `step` of `steps`, 30 characters inside the brackets.
fn step_bar(step: u32, steps: u32) -> String {
    const WIDTH: usize = 30;
    let done = if steps == 0 {
        0
    } else {
        (u64::from(step.min(steps)) * WIDTH as u64 / u64::from(steps)) as usize
    };
    let mut bar = "=".repeat(done);
    if done < WIDTH {
        bar.push('>');
        bar.push_str(&" ".repeat(WIDTH - done - 1));
    }
    format!("[{bar}]")
}

/// An error with its causes, as `main` prints errors: "request to the server failed: ...".
fn with_causes(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        text.push_str(": ");
        text.push_str(&cause.to_string());
        source = cause.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::step_bar;

    #[test]
    fn step_bars_fill_in_proportion() {
        assert_eq!(step_bar(0, 4), format!("[>{}]", " ".repeat(29)));
        assert_eq!(
            step_bar(2, 4),
            format!("[{}>{}]", "=".repeat(15), " ".repeat(14))
        );
        assert_eq!(step_bar(4, 4), format!("[{}]", "=".repeat(30)));
        assert_eq!(step_bar(9, 4), step_bar(4, 4));
        assert_eq!(step_bar(0, 0), step_bar(0, 1));
    }
}
