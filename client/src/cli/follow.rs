//! Following a job to its end (`c4g refine`, `c4g fit`): its server-sent events, followed again
//! when the connection drops, drawn as one progress line on stderr with a line above it for each
//! new history entry or attempt.

use std::io::IsTerminal as _;
use std::time::Duration;

use anyhow::bail;
use c4g_client::{Error, Job, JobProgress};
use futures_util::StreamExt;
use indicatif::{ProgressBar, ProgressStyle};

use super::jobs::progress_numbers;
use super::{Context, emit_json};

/// How often in a row a lost event stream is followed again before giving up.
const RECONNECTS: u32 = 5;

/// Follows `job` until it ends, with a progress line (hidden for `--json` and when stderr is
/// not a terminal); returns its last record.
pub(super) async fn to_end(cx: &Context, job: Job) -> anyhow::Result<Job> {
    let mut watch = Watch::new(&job, cx.json);
    let followed = follow(cx, job, &mut watch).await;
    watch.bar.finish_and_clear();
    followed
}

/// The error of a job that ended without its result (failed or cancelled), its record printed
/// first for `--json`.
pub(super) fn unfinished(cx: &Context, job: &Job) -> anyhow::Result<()> {
    if cx.json {
        emit_json(job)?;
    }
    if job.state == "failed" {
        let error = job.error.as_deref().unwrap_or("no reason given");
        bail!("job {} failed: {error}", job.id);
    }
    bail!("job {} was {}", job.id, job.state)
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

/// What the terminal shows of a job: a line with its progress (`[====>   ] step k/n stage`, and
/// a fit's numbers, or its state while it has none), and a line above it for each new history
/// entry or attempt.
struct Watch {
    bar: ProgressBar,
    id: String,
    attempt: u32,
    history: usize,
    /// A fit's latest held-out PSNR: its progress reports it only at the steps that score it.
    holdout_psnr: Option<f64>,
}

impl Watch {
    /// A watch of a job just submitted; the bar is hidden for `--json` and when stderr is not a
    /// terminal.
    fn new(job: &Job, json: bool) -> Self {
        let shown = !json && std::io::stderr().is_terminal();
        let bar = if shown {
            // One style throughout, the step bar drawn into the message: a change of state is
            // one message, never a frame with the old values in a new style. The job's id is a
            // line above it, not its prefix, so an 80-column line has room for a fit's numbers.
            let style = ProgressStyle::with_template("{spinner} {wide_msg} {elapsed}")
                .unwrap_or_else(|_| ProgressStyle::default_spinner());
            let bar = ProgressBar::new_spinner()
                .with_style(style)
                .with_message(job.state.clone());
            bar.enable_steady_tick(Duration::from_millis(120));
            bar
        } else {
            ProgressBar::hidden()
        };
        let mut watch = Self {
            bar,
            id: job.id.clone(),
            attempt: job.attempt,
            history: 0,
            holdout_psnr: None,
        };
        if shown {
            let what = match job.kind.as_str() {
                "fit" => "a fit",
                "refine" => "a refinement",
                _ => "a job",
            };
            watch.note(&format!("{what} of clip {}", job.clip_id));
        }
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
            (Some(progress), _) if job.state == "running" => self.progress_line(progress),
            (_, Some(worker)) if job.state == "running" => format!("running on {worker}"),
            _ => job.state.clone(),
        };
        self.bar.set_message(message);
    }

    /// `[====>   ] step k/n`, then the stage, or a fit's numbers while it fits: its loss, the
    /// latest held-out PSNR and the Gaussians (the bar's own clock stands for the worker's).
    fn progress_line(&mut self, progress: &JobProgress) -> String {
        let mut text = format!(
            "{} step {}/{}",
            step_bar(progress.step, progress.steps),
            progress.step,
            progress.steps
        );
        self.holdout_psnr = progress.holdout_psnr.or(self.holdout_psnr);
        let numbers = progress.loss.is_some().then(|| JobProgress {
            holdout_psnr: self.holdout_psnr,
            elapsed_s: None,
            ..progress.clone()
        });
        match numbers.as_ref().and_then(progress_numbers) {
            Some(numbers) => {
                text.push_str("  ");
                text.push_str(&numbers);
            }
            None if !progress.stage.is_empty() => {
                text.push(' ');
                text.push_str(&progress.stage);
            }
            None => {}
        }
        text
    }
}

/// `[=====>      ]`: `step` of `steps`, 20 characters inside the brackets.
fn step_bar(step: u32, steps: u32) -> String {
    const WIDTH: usize = 20;
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
        assert_eq!(step_bar(0, 4), format!("[>{}]", " ".repeat(19)));
        assert_eq!(
            step_bar(2, 4),
            format!("[{}>{}]", "=".repeat(10), " ".repeat(9))
        );
        assert_eq!(step_bar(4, 4), format!("[{}]", "=".repeat(20)));
        assert_eq!(step_bar(9, 4), step_bar(4, 4));
        assert_eq!(step_bar(0, 0), step_bar(0, 1));
    }
}
