//! `c4g job`, `c4g jobs` and `c4g cancel`: jobs (refinements and fits), described, listed and
//! cancelled.

use std::fmt::Write as _;

use c4g_client::{Job, JobProgress};
use serde_json::json;

use super::{Context, emit, emit_json, emit_line};

#[derive(Debug, clap::Args)]
pub struct JobArgs {
    /// The job id.
    job: String,
}

pub async fn job(cx: &Context, args: JobArgs) -> anyhow::Result<()> {
    let job = cx.client.job(&args.job).await?;
    if cx.json {
        emit_json(&job)
    } else {
        emit(&job_summary(&job))
    }
}

pub async fn jobs(cx: &Context) -> anyhow::Result<()> {
    let jobs = cx.client.jobs().await?;
    if cx.json {
        return emit_json(&json!({ "jobs": jobs }));
    }
    if jobs.is_empty() {
        return emit_line("no jobs");
    }
    let text: String = jobs.iter().map(|j| job_line(j) + "\n").collect();
    emit(&text)
}

pub async fn cancel(cx: &Context, args: JobArgs) -> anyhow::Result<()> {
    let job = cx.client.cancel(&args.job).await?;
    if cx.json {
        return emit_json(&job);
    }
    match job.state.as_str() {
        "cancelled" => emit_line(format!("cancelled {}", job.id)),
        "running" => emit_line(format!(
            "cancelling {}: it stops at its worker's next step",
            job.id
        )),
        state => emit_line(format!("{} is already {state}", job.id)),
    }
}

/// The state with what qualifies it: the attempt, the worker.
fn state_text(job: &Job) -> String {
    let mut details = Vec::new();
    if job.max_attempts > 1 || job.attempt > 1 {
        details.push(format!("attempt {} of {}", job.attempt, job.max_attempts));
    }
    if let Some(worker) = &job.worker {
        details.push(format!("worker {worker}"));
    }
    if job.extra.get("cancel_requested") == Some(&serde_json::Value::Bool(true))
        && !job.is_terminal()
    {
        details.push("cancelling".to_owned());
    }
    if details.is_empty() {
        job.state.clone()
    } else {
        format!("{} ({})", job.state, details.join(", "))
    }
}

/// A job's progress as `step k/n stage`, and a fit's numbers after it.
fn progress_text(job: &Job) -> Option<String> {
    let progress = job.progress.as_ref()?;
    let mut text = format!("step {}/{}", progress.step, progress.steps);
    if !progress.stage.is_empty() {
        let _ = write!(text, " {}", progress.stage);
    }
    if let Some(numbers) = progress_numbers(progress) {
        let _ = write!(text, "  {numbers}");
    }
    Some(text)
}

/// A fit's numbers at its latest step (`loss 0.0412  held-out 22.71 dB  3812 Gaussians
/// 41.2 s`), those it reported; `None` for a job that reports none (a refinement).
pub(super) fn progress_numbers(progress: &JobProgress) -> Option<String> {
    let parts: Vec<String> = [
        progress.loss.map(|loss| format!("loss {loss:.4}")),
        progress
            .holdout_psnr
            .map(|psnr| format!("held-out {psnr:.2} dB")),
        progress.gaussians.map(|n| format!("{n} Gaussians")),
        progress.elapsed_s.map(|s| format!("{s:.1} s")),
    ]
    .into_iter()
    .flatten()
    .collect();
    (!parts.is_empty()).then(|| parts.join("  "))
}

/// A job's id on the first line (scripts take it with `head -1`), then where it is.
pub(super) fn job_summary(job: &Job) -> String {
    let mut text = format!("{}\n", job.id);
    if !job.kind.is_empty() {
        let _ = writeln!(text, "  kind      {}", job.kind);
    }
    let _ = writeln!(text, "  clip      {}", job.clip_id);
    let _ = writeln!(text, "  state     {}", state_text(job));
    if let Some(progress) = progress_text(job) {
        let _ = writeln!(text, "  progress  {progress}");
    }
    if let Some(error) = &job.error {
        let _ = writeln!(text, "  error     {error}");
    }
    if job.is_done() && job.is_fit() {
        let mut result = "the clip's fitted scene".to_owned();
        if let Some(seconds) = job.seconds {
            let _ = write!(result, ", fitted in {seconds:.1} s");
        }
        let _ = writeln!(text, "  result    {result} (c4g info {})", job.clip_id);
    } else if job.is_done() {
        let mut result = format!("{} frames", job.result_frames);
        if let Some(seconds) = job.seconds {
            let _ = write!(result, " in {seconds:.1} s");
        }
        let _ = writeln!(text, "  result    {result}");
    }
    for (i, line) in job.history.iter().enumerate() {
        let label = if i == 0 { "history" } else { "" };
        let _ = writeln!(text, "  {label:<9} {line}");
    }
    text
}

/// One line per job, for lists.
fn job_line(job: &Job) -> String {
    let mut line = job.id.clone();
    if !job.kind.is_empty() {
        let _ = write!(line, "  {}", job.kind);
    }
    let _ = write!(line, "  {}  clip {}", state_text(job), job.clip_id);
    if let Some(progress) = progress_text(job) {
        let _ = write!(line, "  {progress}");
    }
    if let Some(error) = &job.error {
        let _ = write!(line, "  {error}");
    }
    line
}
