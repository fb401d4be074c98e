//! Videos, read by FFmpeg in child processes: hostile media can crash or hang only the child,
//! which a time limit kills. Three steps:
//! 1. `ffprobe` reads the stream headers and picks the video stream FFmpeg will decode (the
//!    first that is not a cover picture); its declared size, frame count and duration are
//!    checked before anything is decoded;
//! 2. `ffprobe` decodes that stream and lists every frame that comes out, in display order,
//!    with its timestamp and size (a clip with too many frames, or too large a frame, stops the
//!    listing). These are the clip's frames: what the container declares (frame counts,
//!    durations, average rates) is a hint, never a promise, since edit lists hide packets,
//!    decoders drop frames they cannot decode and frame rates vary;
//! 3. `ffmpeg` decodes the stream again, and only the chosen frames come out, as raw RGB at one
//!    size. Frame `n` of this pass is frame `n` of the listing: both run the same decoder, with
//!    the same threads, on the same stream, and the filter graph is never rebuilt mid-stream
//!    (which would restart its frame count).
//!
//! What the listing saw but the clip still reads past goes into the source's warnings: frames
//! that did not decode (they are skipped: the context frames come from the frames that did), a
//! frame size that changes mid-stream (later frames are scaled to the first size), and a second
//! pass that ends early (the context frames are chosen again from the frames it did give).

use std::path::Path;
use std::process::Stdio;

use bytes::Bytes;
use image::RgbImage;
use serde::Deserialize;
use tokio::io::{AsyncBufReadExt, AsyncRead, AsyncReadExt, BufReader};
use tokio::process::Command;

use super::kept::Keep;
use super::limits::{check_duration, check_frame_count, check_frame_size};
use super::media::{Intake, IntakeOptions, IntakeTools, SourceInfo, TimedFrame, frame_step};
use super::sampling::select;
use super::sniff::MediaKind;
use crate::ServiceError;
use crate::config::Limits;

/// The stream both FFmpeg passes read: the first video stream that is not an attached picture
/// (cover art), as `-map 0:V:0` and `-select_streams V:0` mean.
const VIDEO_STREAM: &str = "V:0";

/// Decoder threads, the same in both passes (so that they give the same frames).
const DECODER_THREADS: &str = "2";

/// Reads a video upload.
pub async fn read(
    data: Bytes,
    kind: MediaKind,
    options: &IntakeOptions,
    limits: &Limits,
    tools: &IntakeTools,
    keep: Keep,
) -> Result<Intake, ServiceError> {
    std::fs::create_dir_all(&tools.scratch)
        .map_err(|e| ServiceError::storage("cannot create the scratch directory", &e))?;
    let file = tempfile::NamedTempFile::new_in(&tools.scratch)
        .map_err(|e| ServiceError::storage("cannot create a scratch file", &e))?;
    tokio::fs::write(file.path(), &data)
        .await
        .map_err(|e| ServiceError::storage("cannot write the upload to a scratch file", &e))?;
    crate::faults::pause("video-scratch-written");
    let deadline = tokio::time::Instant::now() + limits.intake_timeout;
    let work = async {
        let stream = probe(file.path(), kind, tools).await?;
        let (width, height) =
            stream.display_size(stream.width.unwrap_or(0), stream.height.unwrap_or(0));
        check_frame_size(width, height, limits)?;
        if let Some(declared) = stream.declared_frames() {
            check_frame_count(declared, limits)?;
        }
        if let Some(duration) = stream.duration {
            check_duration(duration, limits)?;
        }
        let listing = list_frames(file.path(), tools, limits).await?;
        let Some(first) = listing.frames.first() else {
            return Err(ServiceError::UnreadableMedia(format!(
                "the video has no frames that decode (empty, truncated or corrupt?){}",
                detail(listing.log.first.as_deref())
            )));
        };
        // The decoded frames' size, not the header's, is what comes out.
        let (width, height) = stream.display_size(first.width, first.height);
        check_frame_size(width, height, limits)?;
        let raw: Vec<Option<f64>> = listing.frames.iter().map(|f| f.time).collect();
        let mut times = monotonic_times(&raw);
        let mut warnings = listing.warnings(&times, stream.declared_frames());
        check_duration(times.last().copied().unwrap_or(0.0), limits)?;

        let kept_indices = keep.pick(&times, options, width, height);
        let (chosen, images, kept) = decode_context(
            file.path(),
            tools,
            (width, height),
            &mut times,
            options,
            limits,
            &mut warnings,
            (keep, &kept_indices),
        )
        .await?;
        for warning in &warnings {
            tracing::warn!(%warning, "video intake");
        }
        let duration = times.last().copied().unwrap_or(0.0);
        let frames = chosen
            .iter()
            .zip(images)
            .map(|(&i, image)| TimedFrame {
                source_index: i,
                time: times[i],
                image,
            })
            .collect();
        let fps = frame_rate(&times, stream.frame_rate());
        let kept = kept
            .into_iter()
            .map(|(i, image)| TimedFrame {
                source_index: i,
                time: times[i],
                image,
            })
            .collect();
        Ok(Intake {
            frames,
            kept,
            source: SourceInfo {
                kind: "video".into(),
                frames: times.len(),
                width,
                height,
                duration,
                fps,
                warnings,
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
    codec_type: Option<String>,
    codec_name: Option<String>,
    width: Option<u32>,
    height: Option<u32>,
    nb_frames: Option<String>,
    avg_frame_rate: Option<String>,
    #[serde(default, deserialize_with = "number_from_string")]
    duration: Option<f64>,
    #[serde(default)]
    disposition: Disposition,
    #[serde(default)]
    side_data_list: Vec<SideData>,
}

#[derive(Debug, Default, Deserialize)]
struct Disposition {
    #[serde(default)]
    attached_pic: u8,
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
    /// True for the stream [`VIDEO_STREAM`] selects (among the streams in order, the first).
    fn is_video(&self) -> bool {
        self.codec_type.as_deref() == Some("video") && self.disposition.attached_pic == 0
    }

    /// The size FFmpeg decodes frames of `width` × `height` to: rotated by a quarter turn when
    /// the stream's display matrix says so, since FFmpeg applies the rotation.
    fn display_size(&self, w: u32, h: u32) -> (u32, u32) {
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
        .args(["-v", "error", "-show_entries"])
        .arg(
            "stream=codec_type,codec_name,width,height,nb_frames,avg_frame_rate,duration\
             :stream_disposition=attached_pic:stream_side_data=rotation",
        )
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
    let audio: Vec<String> = probe
        .streams
        .iter()
        .filter(|s| s.codec_type.as_deref() == Some("audio"))
        .map(|s| {
            s.codec_name
                .clone()
                .unwrap_or_else(|| "unknown codec".into())
        })
        .collect();
    let Some(stream) = probe.streams.into_iter().find(Stream::is_video) else {
        if !audio.is_empty() {
            return Err(ServiceError::UnsupportedMedia(format!(
                "the file holds audio only ({}) and no video stream: upload a video",
                audio.join(", ")
            )));
        }
        return Err(if kind == MediaKind::Video {
            ServiceError::UnreadableMedia(
                "the file is a media container without a video stream: upload a video".into(),
            )
        } else {
            unreadable("it has no video stream".into())
        });
    };
    if stream.width.is_none() || stream.height.is_none() {
        return Err(ServiceError::UnsupportedMedia(format!(
            "FFmpeg cannot decode the video stream (codec {}): it finds no frame size",
            stream.codec_name.as_deref().unwrap_or("unknown")
        )));
    }
    Ok(stream)
}

/// One decoded frame, as the listing saw it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct ListedFrame {
    /// Its timestamp, seconds (`None` when the decoder gave it none).
    time: Option<f64>,
    /// Its decoded size (before any rotation), pixels.
    width: u32,
    height: u32,
}

/// The first frame whose size differs from the first frame's.
#[derive(Debug, Clone, Copy, PartialEq)]
struct SizeChange {
    index: usize,
    width: u32,
    height: u32,
}

/// What the listing pass saw.
#[derive(Debug, Default)]
struct Listing {
    /// Every frame that decoded, in display order.
    frames: Vec<ListedFrame>,
    /// Packets the demuxer gave the decoder (those an edit list discards not counted).
    packets: usize,
    /// The first size change, if any.
    size_change: Option<SizeChange>,
    /// What FFmpeg logged at error level.
    log: Log,
}

impl Listing {
    /// Adds a frame, noting the first size change.
    fn push(&mut self, frame: ListedFrame) {
        if let Some(first) = self.frames.first()
            && self.size_change.is_none()
            && (first.width, first.height) != (frame.width, frame.height)
        {
            self.size_change = Some(SizeChange {
                index: self.frames.len(),
                width: frame.width,
                height: frame.height,
            });
        }
        self.frames.push(frame);
    }

    /// What the client should know about how the video was read; `times` are the frames'
    /// ([`monotonic_times`]), `declared` the container's frame count.
    fn warnings(&self, times: &[f64], declared: Option<usize>) -> Vec<String> {
        let mut warnings = Vec::new();
        if let Some(error) = &self.log.first {
            let lost = self.packets.saturating_sub(self.frames.len());
            let skipped = match lost {
                0 => "frames FFmpeg concealed may show damage".to_owned(),
                1 => "1 packet decoded to no frame and was skipped".to_owned(),
                n => format!("{n} packets decoded to no frame and were skipped"),
            };
            let listed = match declared {
                Some(n) if n != self.frames.len() => format!(" (the container lists {n})"),
                _ => String::new(),
            };
            warnings.push(format!(
                "FFmpeg reported {} while decoding the video (the first: \"{error}\"): {skipped}; \
                 the context frames come from the {} frames that decoded{listed}",
                plural(self.log.count, "error"),
                self.frames.len()
            ));
        }
        if let (Some(change), Some(first)) = (self.size_change, self.frames.first()) {
            let at = times
                .get(change.index)
                .map(|t| format!(" ({t:.3} s)"))
                .unwrap_or_default();
            warnings.push(format!(
                "the frame size changes from {}x{} to {}x{} at frame {}{at}: frames of another \
                 size are scaled to the first size",
                first.width, first.height, change.width, change.height, change.index
            ));
        }
        warnings
    }
}

/// One line of the listing (`ffprobe -of compact`).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Entry {
    /// A packet read from the stream; `discard` when an edit list hides it.
    Packet { discard: bool },
    /// A decoded frame.
    Frame(ListedFrame),
}

/// Parses one line of `ffprobe -of compact` output for `packet=flags` and
/// `frame=best_effort_timestamp_time,width,height`: `section|key=value|...`, where a field
/// without `=` opens a nested section (side data) whose fields are not the frame's.
fn parse_entry(line: &str) -> Option<Entry> {
    let mut fields = line.trim_end().split('|');
    let section = fields.next()?;
    let value = {
        let pairs: Vec<(&str, &str)> = fields.map_while(|f| f.split_once('=')).collect();
        move |key: &str| pairs.iter().find(|(k, _)| *k == key).map(|(_, v)| *v)
    };
    match section {
        "packet" => Some(Entry::Packet {
            discard: value("flags").is_some_and(|f| f.contains('D')),
        }),
        "frame" => Some(Entry::Frame(ListedFrame {
            time: value("best_effort_timestamp_time")
                .and_then(|t| t.parse::<f64>().ok())
                .filter(|t| t.is_finite()),
            width: value("width")?.parse().ok()?,
            height: value("height")?.parse().ok()?,
        })),
        _ => None,
    }
}

/// Decodes the video stream and lists its frames (see the module documentation). Stops, and
/// refuses the clip, past the frame limit or at a frame larger than the size limit.
async fn list_frames(
    path: &Path,
    tools: &IntakeTools,
    limits: &Limits,
) -> Result<Listing, ServiceError> {
    let mut child = Command::new(&tools.ffprobe)
        .args(["-v", "error", "-threads", DECODER_THREADS])
        .args(["-select_streams", VIDEO_STREAM, "-show_entries"])
        .arg("packet=flags:frame=best_effort_timestamp_time,width,height")
        .args(["-of", "compact"])
        .arg(path)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .map_err(|e| tool_missing(&tools.ffprobe, e))?;
    let stdout = child
        .stdout
        .take()
        .ok_or_else(|| ServiceError::Internal("ffprobe has no stdout".into()))?;
    let log = child.stderr.take().map(drain_log);
    let mut lines = BufReader::new(stdout).lines();
    let mut listing = Listing::default();
    while let Some(line) = lines
        .next_line()
        .await
        .map_err(|e| ServiceError::Internal(format!("reading ffprobe: {e}")))?
    {
        match parse_entry(&line) {
            Some(Entry::Packet { discard }) => listing.packets += usize::from(!discard),
            Some(Entry::Frame(frame)) => {
                check_frame_count(listing.frames.len() + 1, limits)?;
                if frame.width > limits.max_side || frame.height > limits.max_side {
                    check_frame_size(frame.width, frame.height, limits)?;
                }
                listing.push(frame);
            }
            None => {}
        }
    }
    let status = child
        .wait()
        .await
        .map_err(|e| ServiceError::Internal(format!("waiting for ffprobe: {e}")))?;
    if let Some(log) = log {
        listing.log = log.await.unwrap_or_default();
    }
    if !status.success() && listing.log.first.is_none() {
        listing.log = Log {
            count: 1,
            first: Some(format!("ffprobe exited with {status}")),
        };
    }
    Ok(listing)
}

/// Times relative to the first frame, in microseconds, strictly increasing, in the order given:
/// a frame without a timestamp, or with one that does not advance, is placed just after its
/// predecessor by the median frame interval.
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
    // ffprobe prints microseconds: rounding to them drops the subtraction's float noise.
    times
        .iter()
        .map(|t| ((t - first) * 1e6).round() / 1e6)
        .collect()
}

/// The rate of frames at `times`: frames after the first over the time of the last. The
/// container's average rate stands in when it agrees within 1% (it is exact, where the
/// measured rate carries the timestamps' rounding: 30.0000015 for 30) or when a single frame
/// measures nothing.
fn frame_rate(times: &[f64], declared: Option<f64>) -> f64 {
    let duration = times.last().copied().unwrap_or(0.0);
    if times.len() < 2 || duration <= 0.0 {
        return declared.unwrap_or(0.0);
    }
    let measured = (times.len() - 1) as f64 / duration;
    match declared {
        Some(rate) if (rate - measured).abs() <= 0.01 * measured => rate,
        _ => measured,
    }
}

/// Chooses the context frames among `times` and decodes them at `size`. When the decode ends
/// before the last of them, chooses again among the frames it reached (cutting `times` to
/// those, and saying so in `warnings`) and decodes those if they differ.
#[allow(clippy::too_many_arguments)]
async fn decode_context(
    path: &Path,
    tools: &IntakeTools,
    (width, height): (u32, u32),
    times: &mut Vec<f64>,
    options: &IntakeOptions,
    limits: &Limits,
    warnings: &mut Vec<String>,
    (keep, kept_indices): (Keep, &[usize]),
) -> Result<ContextAndKept, ServiceError> {
    let chosen = select(times, options, limits)?;
    // One decoding pass gives the context frames and the kept ones; those the video did not
    // reach are left out.
    let mut wanted: Vec<usize> = chosen.iter().chain(kept_indices).copied().collect();
    wanted.sort_unstable();
    wanted.dedup();
    // A frame kept and not a context frame is shrunk as it comes out of the pipe, so only the
    // context frames are ever held at source size together (`Keep::pick`'s bound).
    let only_kept = |k: usize| !chosen.contains(&wanted[k]);
    let decoded = decode_frames(path, tools, width, height, &wanted, &|k, image| {
        if only_kept(k) {
            keep.shrink(&image)
        } else {
            image
        }
    })
    .await?;
    let reached = wanted.get(decoded.len()).copied().unwrap_or(usize::MAX);
    let mut kept: Vec<(usize, RgbImage)> = Vec::new();
    let mut images: Vec<RgbImage> = Vec::new();
    for (&i, image) in wanted.iter().zip(decoded) {
        let is_kept = kept_indices.contains(&i);
        if chosen.contains(&i) {
            if is_kept {
                kept.push((i, keep.shrink(&image)));
            }
            images.push(image);
        } else if is_kept {
            // Shrunk as it came out of the pipe.
            kept.push((i, image));
        }
    }
    if chosen.iter().all(|&i| i < reached) {
        return Ok((chosen, images, kept));
    }
    let kept: Vec<(usize, RgbImage)> = kept.into_iter().filter(|(i, _)| *i < reached).collect();
    images.truncate(chosen.iter().take_while(|&&i| i < reached).count());
    let plan = replan(times, &chosen, images.len(), options, limits)?;
    warnings.push(format!(
        "the second decoding pass ended before frame {} of the {} frames the first listed; the \
         context frames were chosen again from the first {} frames",
        chosen[images.len()],
        times.len(),
        plan.readable
    ));
    times.truncate(plan.readable);
    let kept: Vec<(usize, RgbImage)> = kept
        .into_iter()
        .filter(|(i, _)| *i < plan.readable)
        .collect();
    if plan.reuses_decoded {
        return Ok((plan.chosen, images, kept));
    }
    let images = decode_frames(path, tools, width, height, &plan.chosen, &|_, image| image).await?;
    if images.len() < plan.chosen.len() {
        return Err(ends_before(plan.chosen[images.len()], None));
    }
    Ok((plan.chosen, images, kept))
}

/// The context frames' indices and images, and the kept frames (index, shrunk image).
type ContextAndKept = (Vec<usize>, Vec<RgbImage>, Vec<(usize, RgbImage)>);

/// The context frames chosen again after a decode gave only the first `decoded` of `chosen`.
#[derive(Debug, PartialEq)]
struct Replan {
    /// Source frames known to decode: every frame up to the last one that came out.
    readable: usize,
    /// The context frames among those.
    chosen: Vec<usize>,
    /// True when they are the frames already decoded (no further pass is needed).
    reuses_decoded: bool,
}

/// Chooses the context frames again among the frames a short decode reached, with the same
/// options; refuses the clip when the decode gave no frame at all.
fn replan(
    times: &[f64],
    chosen: &[usize],
    decoded: usize,
    options: &IntakeOptions,
    limits: &Limits,
) -> Result<Replan, ServiceError> {
    let Some(last) = decoded.checked_sub(1).and_then(|i| chosen.get(i)) else {
        return Err(ends_before(chosen.first().copied().unwrap_or(0), None));
    };
    let readable = (last + 1).min(times.len());
    let again = select(&times[..readable], options, limits)?;
    Ok(Replan {
        readable,
        reuses_decoded: again.as_slice() == &chosen[..decoded],
        chosen: again,
    })
}

fn ends_before(frame: usize, detail_text: Option<&str>) -> ServiceError {
    ServiceError::UnreadableMedia(format!(
        "the video ends before its frame {frame} (truncated or corrupt?){}",
        detail(detail_text)
    ))
}

/// Decodes the video to RGB at `width` × `height` and gives the frames at `chosen` (increasing
/// indices into the listing), or the first of them when the video ends early, each passed through
/// `shape` (its position in `chosen`, the frame) as it is read.
async fn decode_frames(
    path: &Path,
    tools: &IntakeTools,
    width: u32,
    height: u32,
    chosen: &[usize],
    shape: &(dyn Fn(usize, RgbImage) -> RgbImage + Sync),
) -> Result<Vec<RgbImage>, ServiceError> {
    // Only the chosen frames are converted to RGB and piped: `select` drops the rest right
    // after decoding, and decoding stops after the last one. With `-reinit_filter 0` a size
    // change mid-stream does not rebuild the graph (which would restart `n`); `scale` brings
    // such frames to the first size.
    let mut child = Command::new(&tools.ffmpeg)
        .args(["-v", "error", "-nostdin", "-threads", DECODER_THREADS])
        .args(["-reinit_filter", "0", "-i"])
        .arg(path)
        .args(["-map", &format!("0:{VIDEO_STREAM}"), "-vf"])
        .arg(format!(
            "select={},scale={width}:{height}",
            select_expression(chosen)
        ))
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
    // Drained while the frames are read: a full stderr pipe would stall FFmpeg.
    let log = child.stderr.take().map(drain_log);
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
        images.push(shape(images.len(), image));
    }
    drop(stdout);
    child
        .wait()
        .await
        .map_err(|e| ServiceError::Internal(format!("waiting for ffmpeg: {e}")))?;
    if images.is_empty() && !chosen.is_empty() {
        let log = match log {
            Some(log) => log.await.unwrap_or_default(),
            None => Log::default(),
        };
        return Err(ends_before(chosen[0], log.first.as_deref()));
    }
    Ok(images)
}

/// FFmpeg's `select` expression true at the frame numbers `chosen` (increasing): a run of
/// consecutive numbers is one `between`, and the terms are summed as a balanced tree. FFmpeg's
/// expression parser refuses a flat sum of more than about a hundred terms ("Error while parsing
/// expression"), which 300 kept frames and the context frames make; the tree's depth is the
/// logarithm of the count (2,000 terms parse).
fn select_expression(chosen: &[usize]) -> String {
    let mut terms = Vec::new();
    let mut k = 0;
    while k < chosen.len() {
        let mut end = k;
        while end + 1 < chosen.len() && chosen[end + 1] == chosen[end] + 1 {
            end += 1;
        }
        terms.push(if end == k {
            format!("eq(n\\,{})", chosen[k])
        } else {
            format!("between(n\\,{}\\,{})", chosen[k], chosen[end])
        });
        k = end + 1;
    }
    fn sum(terms: &[String]) -> String {
        match terms {
            [] => "0".into(),
            [one] => one.clone(),
            _ => {
                let (a, b) = terms.split_at(terms.len() / 2);
                format!("({}+{})", sum(a), sum(b))
            }
        }
    }
    sum(&terms)
}

/// What a child logged on stderr: how many lines, and the first, cleaned for the client.
#[derive(Debug, Default, Clone, PartialEq)]
struct Log {
    count: usize,
    first: Option<String>,
}

/// Reads a child's stderr to its end (so that the child never blocks on a full pipe), keeping
/// the count of non-empty lines and the first.
fn drain_log(stderr: impl AsyncRead + Unpin + Send + 'static) -> tokio::task::JoinHandle<Log> {
    tokio::spawn(async move {
        let mut lines = BufReader::new(stderr).lines();
        let mut log = Log::default();
        while let Ok(Some(line)) = lines.next_line().await {
            if line.trim().is_empty() {
                continue;
            }
            log.count += 1;
            if log.first.is_none() {
                log.first = Some(clean_log_line(&line));
            }
        }
        log
    })
}

fn detail(text: Option<&str>) -> String {
    match text {
        Some(s) if !s.is_empty() => format!(": {s}"),
        _ => String::new(),
    }
}

fn plural(n: usize, noun: &str) -> String {
    if n == 1 {
        format!("1 {noun}")
    } else {
        format!("{n} {noun}s")
    }
}

fn tool_missing(tool: &Path, e: std::io::Error) -> ServiceError {
    ServiceError::Internal(format!(
        "cannot run {}: {e} (install FFmpeg, or point C4G_FFMPEG at it)",
        tool.display()
    ))
}

fn first_line(stderr: &[u8]) -> String {
    let text = String::from_utf8_lossy(stderr);
    clean_log_line(text.lines().find(|l| !l.trim().is_empty()).unwrap_or(""))
}

/// An FFmpeg log line as the client sees it: without the scratch file's path (which means
/// nothing to the client) or the component's memory address (`[h264 @ 0x55d1…] x` → `h264: x`),
/// at most 300 characters.
fn clean_log_line(line: &str) -> String {
    let line = line.trim();
    let line = line
        .split_once(": ")
        .filter(|(head, _)| head.contains('/'))
        .map_or(line, |(_, tail)| tail);
    let line = match line
        .strip_prefix('[')
        .and_then(|rest| rest.split_once("] "))
        .and_then(|(tag, tail)| Some((tag.split_once(" @ ")?.0, tail)))
    {
        // A parser without a codec context logs as NULL.
        Some(("NULL", tail)) => tail.to_owned(),
        Some((component, tail)) => format!("{component}: {tail}"),
        None => line.to_owned(),
    };
    line.chars().take(300).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_select_expression_joins_runs_and_nests_as_a_balanced_tree() {
        assert_eq!(select_expression(&[4]), "eq(n\\,4)");
        assert_eq!(
            select_expression(&[0, 1, 2, 7, 9, 10]),
            "(between(n\\,0\\,2)+(eq(n\\,7)+between(n\\,9\\,10)))"
        );
        assert_eq!(select_expression(&[]), "0");
        // 1,000 separate frames nest ten deep, where a flat sum of over a hundred is refused.
        let spread: Vec<usize> = (0..1000).map(|i| 2 * i).collect();
        let expression = select_expression(&spread);
        let mut depth = 0;
        let mut deepest = 0;
        for c in expression.chars() {
            match c {
                '(' => depth += 1,
                ')' => depth -= 1,
                _ => {}
            }
            deepest = deepest.max(depth);
        }
        assert!(deepest <= 12, "{deepest}");
        assert_eq!(expression.matches("eq(").count(), 1000);
    }

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

    #[test]
    fn a_timestamp_that_jumps_back_keeps_the_display_order() {
        // Two concatenated streams whose timestamps overlap: frames stay in the order they were
        // shown, each after its predecessor.
        let raw = [Some(2.0), Some(2.1), Some(2.2), Some(2.1), Some(2.2)];
        // Microseconds, without the float noise of 2.1 - 2.0.
        assert_eq!(monotonic_times(&raw), [0.0, 0.1, 0.2, 0.3, 0.4]);
    }

    #[test]
    fn listing_lines_parse_into_packets_and_frames() {
        assert_eq!(
            parse_entry("packet|flags=K_"),
            Some(Entry::Packet { discard: false })
        );
        assert_eq!(
            parse_entry("packet|flags=_D"),
            Some(Entry::Packet { discard: true })
        );
        let frame = |time, width, height| {
            Some(Entry::Frame(ListedFrame {
                time,
                width,
                height,
            }))
        };
        assert_eq!(
            parse_entry("frame|best_effort_timestamp_time=0.050000|width=368|height=480"),
            frame(Some(0.05), 368, 480)
        );
        // Side data opens a nested section whose fields are not the frame's.
        assert_eq!(
            parse_entry(
                "frame|best_effort_timestamp_time=N/A|width=64|height=48|side_data|width=1\r"
            ),
            frame(None, 64, 48)
        );
        assert_eq!(parse_entry("frame|best_effort_timestamp_time=1.0"), None);
        assert_eq!(parse_entry("side_data|"), None);
        assert_eq!(parse_entry(""), None);
    }

    fn frame(time: f64, width: u32, height: u32) -> ListedFrame {
        ListedFrame {
            time: Some(time),
            width,
            height,
        }
    }

    #[test]
    fn a_listing_warns_of_decode_errors_and_of_a_size_change_only() {
        let mut clean = Listing::default();
        for i in 0..3 {
            clean.push(frame(f64::from(i) / 10.0, 64, 48));
        }
        // Nothing logged and the size holds: nothing to say, whatever the container declares.
        clean.packets = 3;
        assert!(clean.warnings(&[0.0, 0.1, 0.2], Some(13)).is_empty());

        let mut damaged = Listing {
            packets: 4,
            log: Log {
                count: 2,
                first: Some("mjpeg: huffman table decode error".into()),
            },
            ..Listing::default()
        };
        for (t, w) in [(1.0, 64), (1.1, 64), (1.3, 80)] {
            damaged.push(frame(t, w, 48));
        }
        assert_eq!(
            damaged.size_change,
            Some(SizeChange {
                index: 2,
                width: 80,
                height: 48
            })
        );
        let warnings = damaged.warnings(&[0.0, 0.1, 0.3], Some(4));
        assert_eq!(warnings.len(), 2, "{warnings:?}");
        assert!(
            warnings[0].contains("2 errors")
                && warnings[0].contains("huffman table decode error")
                && warnings[0].contains("1 packet decoded to no frame")
                && warnings[0].contains("the 3 frames that decoded (the container lists 4)"),
            "{warnings:?}"
        );
        assert!(
            warnings[1].contains("from 64x48 to 80x48 at frame 2 (0.300 s)"),
            "{warnings:?}"
        );
    }

    #[test]
    fn the_frame_rate_is_measured_and_the_declared_one_kept_only_where_it_agrees() {
        let at_30: Vec<f64> = (0..200)
            .map(|i| (f64::from(i) / 30.0 * 1e6).round() / 1e6)
            .collect();
        assert_eq!(frame_rate(&at_30, Some(30.0)), 30.0);
        let measured = frame_rate(&at_30, None);
        assert!((measured - 30.0).abs() < 1e-5, "{measured}");
        // Variable rate: the container's average (nb_frames / duration) is not what decodes.
        let vfr = [0.0, 0.1, 0.3, 0.6, 1.0];
        assert_eq!(frame_rate(&vfr, Some(9.42)), 4.0);
        // One frame measures nothing.
        assert_eq!(frame_rate(&[0.0], Some(25.0)), 25.0);
        assert_eq!(frame_rate(&[0.0], None), 0.0);
    }

    #[test]
    fn a_short_decode_replans_over_the_frames_it_reached() {
        let limits = Limits::default();
        let times: Vec<f64> = (0..10).map(|i| f64::from(i) / 10.0).collect();
        let spread = IntakeOptions {
            max_frames: Some(4),
            ..Default::default()
        };
        // [0, 3, 6, 9] planned, two came out: frames 0..=3 are known to decode.
        let plan = replan(&times, &[0, 3, 6, 9], 2, &spread, &limits).unwrap();
        assert_eq!(
            plan,
            Replan {
                readable: 4,
                chosen: vec![0, 1, 2, 3],
                reuses_decoded: false
            }
        );
        // A stride picks the same frames again: what was decoded is kept.
        let stride = IntakeOptions {
            stride: Some(3),
            ..Default::default()
        };
        let plan = replan(&times, &[0, 3, 6, 9], 3, &stride, &limits).unwrap();
        assert_eq!(
            plan,
            Replan {
                readable: 7,
                chosen: vec![0, 3, 6],
                reuses_decoded: true
            }
        );
        // Nothing came out: refused, naming the frame.
        let none = replan(&times, &[2, 5], 0, &spread, &limits).unwrap_err();
        assert!(none.to_string().contains("before its frame 2"), "{none}");
    }

    #[test]
    fn log_lines_lose_paths_and_addresses() {
        assert_eq!(
            clean_log_line("[mjpeg @ 0x55e092f6dc00] huffman table decode error"),
            "mjpeg: huffman table decode error"
        );
        assert_eq!(
            clean_log_line("/tmp/scratch/.tmpAb12: Invalid data found when processing input"),
            "Invalid data found when processing input"
        );
        assert_eq!(
            clean_log_line("[NULL @ 0x5564ef5fdbb40] Invalid NAL unit size (0 > 8)."),
            "Invalid NAL unit size (0 > 8)."
        );
        assert_eq!(clean_log_line("plain words"), "plain words");
        assert_eq!(clean_log_line(&"x".repeat(400)).len(), 300);
    }
}
