//! Videos, read by FFmpeg in child processes: hostile media can crash or hang only the child,
//! which a time limit kills. Three steps:
//! 1. `ffprobe` reads the stream header: size, declared frame count and duration are checked
//!    before anything is decoded;
//! 2. `ffprobe` lists every packet's presentation time without decoding (sorted, these are the
//!    frames' times, so the context frames can be chosen by time; a clip with too many frames
//!    stops the listing);
//! 3. `ffmpeg` decodes, and only the chosen frames come out, as raw RGB.

use std::path::Path;
use std::process::Stdio;

use bytes::Bytes;
use image::RgbImage;
use serde::Deserialize;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, BufReader};
use tokio::process::Command;

use super::sampling::select;
use super::{
    Intake, IntakeOptions, IntakeTools, MediaKind, SourceInfo, TimedFrame, check_duration,
    check_frame_count, check_frame_size, frame_step,
};
use crate::ServiceError;
use crate::config::Limits;

/// Reads a video upload.
pub async fn read(
    data: Bytes,
    kind: MediaKind,
    options: &IntakeOptions,
    limits: &Limits,
    tools: &IntakeTools,
) -> Result<Intake, ServiceError> {
    std::fs::create_dir_all(&tools.scratch)
        .map_err(|e| ServiceError::Internal(format!("cannot create the scratch directory: {e}")))?;
    let file = tempfile::NamedTempFile::new_in(&tools.scratch)
        .map_err(|e| ServiceError::Internal(format!("cannot create a scratch file: {e}")))?;
    tokio::fs::write(file.path(), &data)
        .await
        .map_err(|e| ServiceError::Internal(format!("cannot write a scratch file: {e}")))?;
    let deadline = tokio::time::Instant::now() + limits.intake_timeout;
    let work = async {
        let stream = probe(file.path(), kind, tools).await?;
        let (width, height) = stream.display_size();
        check_frame_size(width, height, limits)?;
        if let Some(declared) = stream.declared_frames() {
            check_frame_count(declared, limits)?;
        }
        if let Some(duration) = stream.duration {
            check_duration(duration, limits)?;
        }
        let times = frame_times(file.path(), tools, limits).await?;
        if times.is_empty() {
            return Err(ServiceError::UnreadableMedia(
                "the video has no decodable frames (truncated or corrupt?)".into(),
            ));
        }
        let duration = times.last().copied().unwrap_or(0.0);
        check_duration(duration, limits)?;
        let chosen = select(&times, options, limits)?;
        let images = decode_frames(file.path(), tools, width, height, &chosen).await?;
        let frames = chosen
            .iter()
            .zip(images)
            .map(|(&i, image)| TimedFrame {
                time: times[i],
                image,
            })
            .collect();
        let fps = stream.frame_rate().unwrap_or_else(|| {
            if duration > 0.0 {
                (times.len() - 1) as f64 / duration
            } else {
                0.0
            }
        });
        Ok(Intake {
            frames,
            source: SourceInfo {
                kind: "video".into(),
                frames: times.len(),
                width,
                height,
                duration,
                fps,
            },
            frame_step: frame_step(&times, fps),
        })
    };
    match tokio::time::timeout_at(deadline, work).await {
        Ok(result) => result,
        Err(_) => Err(ServiceError::UnreadableMedia(format!(
            "reading the video took longer than {} s (C4G_INTAKE_TIMEOUT_S)",
            limits.intake_timeout.as_secs()
        ))),
    }
}

#[derive(Debug, Deserialize)]
struct Probe {
    #[serde(default)]
    streams: Vec<Stream>,
}

#[derive(Debug, Deserialize)]
struct Stream {
    width: Option<u32>,
    height: Option<u32>,
    nb_frames: Option<String>,
    avg_frame_rate: Option<String>,
    #[serde(default, deserialize_with = "number_from_string")]
    duration: Option<f64>,
    #[serde(default)]
    side_data_list: Vec<SideData>,
}

#[derive(Debug, Deserialize)]
struct SideData {
    rotation: Option<f64>,
}

fn number_from_string<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
    let s: Option<String> = Option::deserialize(d)?;
    Ok(s.and_then(|s| s.parse().ok()))
}

impl Stream {
    /// The size FFmpeg decodes to: rotated by a quarter turn when the stream says so, since
    /// FFmpeg applies the rotation.
    fn display_size(&self) -> (u32, u32) {
        let (w, h) = (self.width.unwrap_or(0), self.height.unwrap_or(0));
        let quarter = self
            .side_data_list
            .iter()
            .filter_map(|s| s.rotation)
            .any(|r| (r.abs() - 90.0).abs() < 1.0 || (r.abs() - 270.0).abs() < 1.0);
        if quarter { (h, w) } else { (w, h) }
    }

    fn declared_frames(&self) -> Option<usize> {
        self.nb_frames.as_deref()?.parse().ok()
    }

    fn frame_rate(&self) -> Option<f64> {
        let (num, den) = self.avg_frame_rate.as_deref()?.split_once('/')?;
        let (num, den): (f64, f64) = (num.parse().ok()?, den.parse().ok()?);
        (den > 0.0 && num > 0.0).then(|| num / den)
    }
}

async fn probe(path: &Path, kind: MediaKind, tools: &IntakeTools) -> Result<Stream, ServiceError> {
    let output = Command::new(&tools.ffprobe)
        .args(["-v", "error", "-select_streams", "v:0", "-show_entries"])
        .arg("stream=width,height,nb_frames,avg_frame_rate,duration:stream_side_data=rotation")
        .args(["-of", "json"])
        .arg(path)
        .stdin(Stdio::null())
        .kill_on_drop(true)
        .output()
        .await
        .map_err(|e| tool_missing(&tools.ffprobe, e))?;
    let unreadable = |detail: String| {
        if kind == MediaKind::Video {
            ServiceError::UnreadableMedia(format!(
                "the file looks like a video but cannot be read (truncated or corrupt?): {detail}"
            ))
        } else {
            ServiceError::UnsupportedMedia(format!(
                "the upload is not a video FFmpeg can read, an image archive (zip, tar) or an \
                 image: {detail}"
            ))
        }
    };
    if !output.status.success() {
        return Err(unreadable(first_line(&output.stderr)));
    }
    let probe: Probe = serde_json::from_slice(&output.stdout)
        .map_err(|e| ServiceError::Internal(format!("unexpected ffprobe output: {e}")))?;
    probe
        .streams
        .into_iter()
        .next()
        .filter(|s| s.width.is_some() && s.height.is_some())
        .ok_or_else(|| unreadable("it has no video stream".into()))
}

/// Presentation times of every frame, from the first frame's, in order, read from the packets
/// (demuxing only: decoding happens once, later). Stops (and refuses the clip) past the frame
/// limit.
async fn frame_times(
    path: &Path,
    tools: &IntakeTools,
    limits: &Limits,
) -> Result<Vec<f64>, ServiceError> {
    let mut child = Command::new(&tools.ffprobe)
        .args(["-v", "error", "-select_streams", "v:0", "-show_entries"])
        .arg("packet=pts_time")
        .args(["-of", "csv=p=0"])
        .arg(path)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .kill_on_drop(true)
        .spawn()
        .map_err(|e| tool_missing(&tools.ffprobe, e))?;
    let stdout = child
        .stdout
        .take()
        .ok_or_else(|| ServiceError::Internal("ffprobe has no stdout".into()))?;
    let mut lines = BufReader::new(stdout).lines();
    let mut raw: Vec<Option<f64>> = Vec::new();
    while let Some(line) = lines
        .next_line()
        .await
        .map_err(|e| ServiceError::Internal(format!("reading ffprobe: {e}")))?
    {
        // One frame a line; side data can add empty lines.
        let field = line.split(',').next().unwrap_or("").trim();
        if field.is_empty() {
            continue;
        }
        raw.push(field.parse::<f64>().ok().filter(|t| t.is_finite()));
        check_frame_count(raw.len(), limits)?;
    }
    let status = child
        .wait()
        .await
        .map_err(|e| ServiceError::Internal(format!("waiting for ffprobe: {e}")))?;
    if !status.success() && raw.is_empty() {
        return Err(ServiceError::UnreadableMedia(
            "the video's frames cannot be read (truncated or corrupt?)".into(),
        ));
    }
    // Packets come in decoding order; frames are shown in presentation order.
    raw.sort_by(|a, b| match (a, b) {
        (Some(a), Some(b)) => a.total_cmp(b),
        // Frames without a time go last, where the fill below gives them one.
        (Some(_), None) => std::cmp::Ordering::Less,
        (None, Some(_)) => std::cmp::Ordering::Greater,
        (None, None) => std::cmp::Ordering::Equal,
    });
    Ok(monotonic_times(&raw))
}

/// Times relative to the first frame, strictly increasing: a frame without a timestamp, or with
/// one that does not advance, is placed just after its predecessor by the median frame interval.
fn monotonic_times(raw: &[Option<f64>]) -> Vec<f64> {
    let mut steps: Vec<f64> = raw
        .windows(2)
        .filter_map(|w| Some(w[1]? - w[0]?))
        .filter(|d| *d > 0.0)
        .collect();
    steps.sort_by(f64::total_cmp);
    let step = steps.get(steps.len() / 2).copied().unwrap_or(1.0 / 30.0);
    let mut times = Vec::with_capacity(raw.len());
    for t in raw {
        let t = match (*t, times.last().copied()) {
            (Some(t), Some(prev)) if t > prev => t,
            (_, Some(prev)) => prev + step,
            (Some(t), None) => t,
            (None, None) => 0.0,
        };
        times.push(t);
    }
    let first = times.first().copied().unwrap_or(0.0);
    times.iter().map(|t| t - first).collect()
}

/// Decodes the video to RGB and keeps the frames at `chosen` (increasing indices).
async fn decode_frames(
    path: &Path,
    tools: &IntakeTools,
    width: u32,
    height: u32,
    chosen: &[usize],
) -> Result<Vec<RgbImage>, ServiceError> {
    // Only the chosen frames are converted to RGB and piped: `select` drops the rest right
    // after decoding, and decoding stops after the last one.
    let select: Vec<String> = chosen.iter().map(|i| format!("eq(n\\,{i})")).collect();
    let mut child = Command::new(&tools.ffmpeg)
        .args(["-v", "error", "-nostdin", "-threads", "2", "-i"])
        .arg(path)
        .args(["-map", "0:v:0", "-vf"])
        .arg(format!("select={}", select.join("+")))
        .args(["-fps_mode", "passthrough", "-frames:v"])
        .arg(chosen.len().to_string())
        .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "pipe:1"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .map_err(|e| tool_missing(&tools.ffmpeg, e))?;
    let mut stdout = child
        .stdout
        .take()
        .ok_or_else(|| ServiceError::Internal("ffmpeg has no stdout".into()))?;
    let frame_bytes = width as usize * height as usize * 3;
    let mut buffer = vec![0u8; frame_bytes];
    let mut images = Vec::with_capacity(chosen.len());
    while images.len() < chosen.len() {
        match stdout.read_exact(&mut buffer).await {
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => break,
            Err(e) => return Err(ServiceError::Internal(format!("reading ffmpeg: {e}"))),
        }
        let image = RgbImage::from_raw(width, height, buffer.clone())
            .ok_or_else(|| ServiceError::Internal("a decoded frame has the wrong size".into()))?;
        images.push(image);
    }
    drop(stdout);
    let output = child
        .wait_with_output()
        .await
        .map_err(|e| ServiceError::Internal(format!("waiting for ffmpeg: {e}")))?;
    if images.len() < chosen.len() {
        return Err(ServiceError::UnreadableMedia(format!(
            "the video ends before its frame {} (truncated or corrupt?){}",
            chosen.get(images.len()).copied().unwrap_or(0),
            match first_line(&output.stderr) {
                s if s.is_empty() => String::new(),
                s => format!(": {s}"),
            }
        )));
    }
    Ok(images)
}

fn tool_missing(tool: &Path, e: std::io::Error) -> ServiceError {
    ServiceError::Internal(format!(
        "cannot run {}: {e} (install FFmpeg, or point C4G_FFMPEG at it)",
        tool.display()
    ))
}

fn first_line(stderr: &[u8]) -> String {
    let text = String::from_utf8_lossy(stderr);
    let line = text.lines().find(|l| !l.trim().is_empty()).unwrap_or("");
    // The scratch file's path means nothing to the client.
    line.split_once(": ")
        .filter(|(head, _)| head.contains('/'))
        .map_or(line, |(_, tail)| tail)
        .chars()
        .take(300)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_and_stuck_timestamps_advance_by_the_median_step() {
        let raw = [
            Some(1.0),
            Some(1.1),
            Some(1.2),
            None,
            Some(1.4),
            Some(1.4),
            Some(1.6),
        ];
        let t = monotonic_times(&raw);
        let expected = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6];
        for (a, b) in t.iter().zip(expected) {
            assert!((a - b).abs() < 1e-9, "{t:?}");
        }
    }
}
