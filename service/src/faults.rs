//! Fault points: named places in the middle of writing a clip, encoding or storing a job's
//! result, where the server can be told to stop so that a test kills it exactly there
//! (`tests/e2e/faults.rs`). Without a crash in those windows, "a crash never leaves half a clip"
//! would be a claim, not a tested fact; the windows are microseconds wide, so a test cannot hit
//! them by timing.
//!
//! Off unless the hidden `--fault-pause` (`C4G_FAULT_PAUSE`) names points. At a named point the
//! thread logs `fault point <name> reached` and sleeps until the process is killed: the server
//! keeps answering everything else, as it would while a slow disk holds that thread.

use std::sync::OnceLock;
use std::time::Duration;

/// Every fault point, where it is:
/// - `video-scratch-written`: an uploaded video is in scratch space, FFmpeg has not read it
///   (`clips::intake::video`);
/// - `encode`: an upload's frames are preprocessed, the encoder has not run (`service`);
/// - `clip-features-written`: a clip's temporary directory holds its record and features, not
///   its frames (`store`);
/// - `clip-stored`: the clip is in place on disk, not yet in the index or answered (`store`);
/// - `job-result-stored`: a job's refined frames are in place, its record still says running
///   (`jobs`).
pub const POINTS: [&str; 5] = [
    "video-scratch-written",
    "encode",
    "clip-features-written",
    "clip-stored",
    "job-result-stored",
];

static ARMED: OnceLock<Vec<String>> = OnceLock::new();

/// Arms `points` for the life of the process (the first call wins). Unknown names are refused.
pub fn arm(points: &[String]) -> Result<(), String> {
    if let Some(unknown) = points.iter().find(|p| !POINTS.contains(&p.as_str())) {
        return Err(format!(
            "unknown fault point {unknown:?}: one of {}",
            POINTS.join(", ")
        ));
    }
    if !points.is_empty() {
        tracing::warn!(
            points = points.join(","),
            "fault points armed: the server stops at them until it is killed (for tests only)"
        );
    }
    let _ = ARMED.set(points.to_vec());
    Ok(())
}

/// Stops this thread for good when `point` is armed; returns at once otherwise. Called only on
/// blocking threads.
pub fn pause(point: &str) {
    if ARMED
        .get()
        .is_some_and(|armed| armed.iter().any(|p| p == point))
    {
        tracing::error!("fault point {point} reached: paused until the process is killed");
        loop {
            std::thread::sleep(Duration::from_secs(3600));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_points_are_refused_and_nothing_pauses_unarmed() {
        let err = arm(&["nowhere".to_owned()]).unwrap_err();
        assert!(err.contains("clip-features-written"), "{err}");
        // Not armed in this process: returns at once.
        for point in POINTS {
            pause(point);
        }
    }
}
