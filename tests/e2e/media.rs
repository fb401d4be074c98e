//! Media as it really is, uploaded to a live `c4g-server`: a container that over-states its
//! frames, variable frame rate, B-frames, a display rotation, odd sizes, 10-bit 4:2:2, GIF, a
//! file without video, one without frames, a corrupt frame in the middle, a frame count past the
//! limit. FFmpeg makes every clip inside the test (nothing binary is committed), and ffprobe
//! confirms that each clip is the case it stands for before it is uploaded.
//!
//! Most clips carry their frame number in their brightness (luma 16 + 5 n), so a test can tell
//! which source frame the server chose for each context frame and hold it to the time the
//! server reports. Outside CI, a machine without FFmpeg or one of its encoders skips, saying
//! why; in CI every case runs. The real clips in `../shared/data` are uploaded by `service.rs`
//! (bedroom: frames, size, times) and `cli.rs` (dog: frames, a window and a stride).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::Path;
use std::process::Command;

use c4g_e2e::{Server, ort_available};
use image::RgbImage;
use reqwest::blocking::Client;
use serde_json::Value;

/// Brightness ramp: frame `n` has luma `16 + 5 n` (neutral chroma), so up to 43 frames.
const NUMBERED: &str = "format=yuv420p,geq=lum='16+5*N':cb=128:cr=128";

/// A lavfi source of numbered frames.
fn numbered(size: &str, rate: u32, seconds: f64) -> String {
    format!("color=c=black:s={size}:r={rate}:d={seconds},{NUMBERED}")
}

fn in_ci() -> bool {
    std::env::var_os("CI").is_some()
}

/// True when ONNX Runtime, ffmpeg and ffprobe are all here (outside CI a test may skip).
fn ready() -> bool {
    if !ort_available() {
        return false;
    }
    let runs = |tool: &str| {
        Command::new(tool)
            .arg("-version")
            .output()
            .is_ok_and(|o| o.status.success())
    };
    let ok = runs("ffmpeg") && runs("ffprobe");
    if !ok {
        assert!(!in_ci(), "in CI ffmpeg and ffprobe must be on PATH");
        eprintln!("skipped: ffmpeg or ffprobe is not on PATH");
    }
    ok
}

/// True when this FFmpeg has `encoder` (outside CI a test may skip without it).
fn has_encoder(encoder: &str) -> bool {
    let out = Command::new("ffmpeg")
        .args(["-hide_banner", "-encoders"])
        .output()
        .unwrap();
    let listed = String::from_utf8_lossy(&out.stdout)
        .lines()
        .any(|l| l.split_whitespace().nth(1) == Some(encoder));
    if !listed {
        assert!(!in_ci(), "in CI FFmpeg must have the {encoder} encoder");
        eprintln!("skipped: this FFmpeg has no {encoder} encoder");
    }
    listed
}

/// Runs ffmpeg in `dir` (quiet, overwriting): its stderr when it fails.
fn try_ffmpeg(dir: &Path, args: &[&str]) -> Result<(), String> {
    let out = Command::new("ffmpeg")
        .current_dir(dir)
        .args(["-v", "error", "-nostdin", "-y"])
        .args(args)
        .output()
        .unwrap();
    if out.status.success() {
        Ok(())
    } else {
        Err(String::from_utf8_lossy(&out.stderr).into_owned())
    }
}

/// Runs ffmpeg in `dir`, and insists that it succeeds.
fn ffmpeg(dir: &Path, args: &[&str]) {
    if let Err(stderr) = try_ffmpeg(dir, args) {
        panic!("ffmpeg {args:?}: {stderr}");
    }
}

/// `ffprobe -show_entries entries` of the first video stream: a line per stream, packet or
/// frame, its values separated by commas.
fn probe(path: &Path, entries: &str, extra: &[&str]) -> Vec<String> {
    let out = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "V:0"])
        .args(extra)
        .args(["-show_entries", entries, "-of", "csv=p=0:nk=1"])
        .arg(path)
        .output()
        .unwrap();
    assert!(out.status.success(), "ffprobe {entries} {}", path.display());
    String::from_utf8_lossy(&out.stdout)
        .lines()
        // A frame with side data ends in a comma (the side data's empty section).
        .map(|l| l.trim().trim_end_matches(','))
        .filter(|l| !l.is_empty())
        .map(str::to_owned)
        .collect()
}

/// Frames the container declares (`nb_frames`), if it declares them.
fn declared_frames(path: &Path) -> Option<usize> {
    probe(path, "stream=nb_frames", &[]).first()?.parse().ok()
}

/// Frames that decode, counted by ffprobe (which says N/A for none).
fn decoded_frames(path: &Path) -> usize {
    let counted = probe(path, "stream=nb_read_frames", &["-count_frames"]);
    match counted[0].as_str() {
        "N/A" => 0,
        n => n.parse().unwrap(),
    }
}

fn upload(server: &Server, path: &Path, query: &str) -> (u16, Value) {
    let response = Client::new()
        .post(server.at(&format!("/v1/clips?{query}")))
        .body(std::fs::read(path).unwrap())
        .send()
        .unwrap();
    let status = response.status().as_u16();
    let text = response.text().unwrap();
    let body = serde_json::from_str(&text).unwrap_or_else(|_| panic!("not JSON: {text}"));
    (status, body)
}

/// Uploads and insists on 201.
fn upload_ok(server: &Server, path: &Path, query: &str) -> Value {
    let (status, clip) = upload(server, path, query);
    assert_eq!(status, 201, "{clip}");
    clip
}

fn times(clip: &Value) -> Vec<f64> {
    clip["context_times"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_f64().unwrap())
        .collect()
}

fn warnings(clip: &Value) -> Vec<String> {
    clip["source"]["warnings"]
        .as_array()
        .map(|w| w.iter().map(|s| s.as_str().unwrap().to_owned()).collect())
        .unwrap_or_default()
}

/// The clip's context frames, in time order, as the server kept them.
fn context_frames(server: &Server, clip: &Value) -> Vec<RgbImage> {
    let id = clip["id"].as_str().unwrap();
    (0..times(clip).len())
        .map(|k| {
            let png = Client::new()
                .get(server.at(&format!("/v1/clips/{id}/frames/{k}")))
                .send()
                .unwrap();
            assert_eq!(png.status(), 200);
            image::load_from_memory(&png.bytes().unwrap())
                .unwrap()
                .to_rgb8()
        })
        .collect()
}

fn mean_rgb(image: &RgbImage) -> [f64; 3] {
    let mut sum = [0.0; 3];
    for p in image.pixels() {
        for c in 0..3 {
            sum[c] += f64::from(p[c]);
        }
    }
    sum.map(|s| s / f64::from(image.width() * image.height()))
}

/// Which numbered frame an image is: luma 16 + 5 n is grey 5 n · 255/219 in RGB. Compression
/// moves it by well under half a step (measured: at most 0.2 of one).
fn frame_number(image: &RgbImage) -> usize {
    let grey = mean_rgb(image).iter().sum::<f64>() / 3.0;
    let n = grey / (5.0 * 255.0 / 219.0);
    assert!(
        (n - n.round()).abs() < 0.4,
        "grey {grey} is no numbered frame"
    );
    n.round() as usize
}

fn assert_close(got: &[f64], want: &[f64], tolerance: f64) {
    assert_eq!(got.len(), want.len(), "{got:?} against {want:?}");
    for (g, w) in got.iter().zip(want) {
        assert!((g - w).abs() <= tolerance, "{got:?} against {want:?}");
    }
}

#[test]
fn a_container_that_over_states_its_frames_uploads_the_frames_that_decode() {
    if !ready() || !has_encoder("libx264") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // 2 s at 20 fps, a keyframe every second; a stream copy from 0.5 s starts at the keyframe
    // at 0 and writes an edit list that hides the first 10 frames, which the container still
    // counts.
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            &numbered("64x48", 20, 2.0),
            "-c:v",
            "libx264",
            "-crf",
            "12",
            "-g",
            "20",
            "-keyint_min",
            "20",
            "-sc_threshold",
            "0",
            "full.mp4",
        ],
    );
    ffmpeg(
        dir.path(),
        &["-ss", "0.5", "-i", "full.mp4", "-c", "copy", "cut.mp4"],
    );
    let cut = dir.path().join("cut.mp4");
    let (declared, decoded) = (declared_frames(&cut).unwrap(), decoded_frames(&cut));
    assert!(declared > decoded, "nb_frames {declared}, {decoded} decode");
    assert_eq!(decoded, 30);

    let server = Server::start(&[]);
    let clip = upload_ok(&server, &cut, "max_frames=32");
    assert_eq!(clip["source"]["frames"], 30, "{clip}");
    assert!(
        warnings(&clip).is_empty(),
        "an edit list is ordinary: {clip}"
    );
    let expected: Vec<f64> = (0..30).map(|i| f64::from(i) * 0.05).collect();
    assert_close(&times(&clip), &expected, 1e-6);
    assert!((clip["source"]["duration"].as_f64().unwrap() - 1.45).abs() < 1e-6);
    // Context frame i is the frame shown at 0.05 i: source frame 10 + i.
    let numbers: Vec<usize> = context_frames(&server, &clip)
        .iter()
        .map(frame_number)
        .collect();
    assert_eq!(numbers, (10..40).collect::<Vec<_>>());
}

#[test]
fn variable_frame_rate_and_b_frames_keep_each_frame_with_its_own_time() {
    if !ready() || !has_encoder("libx264") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // Variable rate: frame n at 0.05 n + 0.004 n² s (gaps from 54 to 202 ms), in milliseconds.
    let vfr_time = |n: u32| (f64::from(n) * 50.0 + 4.0 * f64::from(n * n)).round() / 1000.0;
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            &format!(
                "{},settb=1/1000,setpts='round((0.05*N+0.004*N*N)*1000)'",
                numbered("64x48", 20, 1.0)
            ),
            "-c:v",
            "libx264",
            "-crf",
            "12",
            "-fps_mode",
            "passthrough",
            "-enc_time_base",
            "1/1000",
            "vfr.mp4",
        ],
    );
    let vfr = dir.path().join("vfr.mp4");
    let listed: Vec<f64> = probe(&vfr, "frame=best_effort_timestamp_time", &[])
        .iter()
        .map(|t| t.parse().unwrap())
        .collect();
    assert_close(&listed, &(0..20).map(vfr_time).collect::<Vec<_>>(), 1e-6);

    // B-frames with reordering (x264's defaults): packets arrive out of presentation order.
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            &numbered("64x48", 20, 2.0),
            "-c:v",
            "libx264",
            "-crf",
            "12",
            "bframes.mp4",
        ],
    );
    let bframes = dir.path().join("bframes.mp4");
    assert!(probe(&bframes, "frame=pict_type", &[]).contains(&"B".to_owned()));
    let packet_times: Vec<f64> = probe(&bframes, "packet=pts_time", &[])
        .iter()
        .map(|t| t.parse().unwrap())
        .collect();
    assert!(
        packet_times.windows(2).any(|w| w[1] < w[0]),
        "no reordering"
    );

    let server = Server::start(&[]);
    let clip = upload_ok(&server, &vfr, "max_frames=20");
    assert_eq!(clip["source"]["frames"], 20, "{clip}");
    let got = times(&clip);
    let numbers: Vec<usize> = context_frames(&server, &clip)
        .iter()
        .map(frame_number)
        .collect();
    assert_eq!(numbers, (0..20).collect::<Vec<_>>());
    assert_close(&got, &(0..20).map(vfr_time).collect::<Vec<_>>(), 1e-6);
    let fps = clip["source"]["fps"].as_f64().unwrap();
    assert!((fps - 19.0 / 2.394).abs() < 1e-6, "{fps}");

    let clip = upload_ok(&server, &bframes, "stride=2");
    assert_eq!(clip["source"]["frames"], 40, "{clip}");
    let expected: Vec<f64> = (0..20).map(|k| f64::from(k) * 0.1).collect();
    assert_close(&times(&clip), &expected, 1e-6);
    let numbers: Vec<usize> = context_frames(&server, &clip)
        .iter()
        .map(frame_number)
        .collect();
    assert_eq!(numbers, (0..40).step_by(2).collect::<Vec<_>>());
}

#[test]
fn a_rotated_video_comes_out_upright_at_its_displayed_size() {
    if !ready() || !has_encoder("libx264") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // Coded 64x48: blue, with the left 16 columns red; then a display matrix on stream copy.
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            "color=c=blue:s=64x48:r=10:d=1,drawbox=x=0:y=0:w=16:h=48:color=red:t=fill",
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
            "coded.mp4",
        ],
    );
    // FFmpeg 5 turns a `rotate` tag into a display matrix; FFmpeg 6 and later take
    // `-display_rotation` instead.
    let rotated = dir.path().join("rotated.mp4");
    let rotation = || -> Option<f64> {
        let r: f64 = probe(&rotated, "stream_side_data=rotation", &[])
            .first()?
            .parse()
            .ok()?;
        ((r.abs() - 90.0).abs() < 1.0).then_some(r)
    };
    let tag = ["-i", "coded.mp4", "-c", "copy"];
    ffmpeg(
        dir.path(),
        &[&tag[..], &["-metadata:s:v", "rotate=90", "rotated.mp4"]].concat(),
    );
    let mut found = rotation();
    if found.is_none()
        && try_ffmpeg(
            dir.path(),
            &[&["-display_rotation:v:0", "90"], &tag[..], &["rotated.mp4"]].concat(),
        )
        .is_ok()
    {
        found = rotation();
    }
    let Some(rotation) = found else {
        assert!(!in_ci(), "in CI FFmpeg must write a display matrix");
        eprintln!("skipped: this FFmpeg writes no display matrix (rotate=90, -display_rotation)");
        return;
    };

    let server = Server::start(&[]);
    let clip = upload_ok(&server, &rotated, "max_frames=2");
    assert_eq!(
        (
            clip["source"]["width"].clone(),
            clip["source"]["height"].clone()
        ),
        (48.into(), 64.into()),
        "{clip}"
    );
    let frame = &context_frames(&server, &clip)[0];
    assert_eq!(frame.dimensions(), (48, 64));
    // libavutil's rotation is counter-clockwise: +90 turns the coded left edge to the bottom,
    // -90 to the top.
    let (red_row, blue_row) = if rotation > 0.0 { (58, 6) } else { (6, 58) };
    let red = frame.get_pixel(24, red_row);
    let blue = frame.get_pixel(24, blue_row);
    assert!(red[0] > 200 && red[2] < 60, "rotation {rotation}: {red:?}");
    assert!(
        blue[2] > 200 && blue[0] < 60,
        "rotation {rotation}: {blue:?}"
    );
}

#[test]
fn odd_sizes_and_10_bit_4_2_2_upload_at_their_size_with_their_colour() {
    if !ready() || !has_encoder("libx264") || !has_encoder("ffv1") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let colour = "color=c=0x3366cc:r=10:d=1";
    // 367x481: H.264 4:4:4 (4:2:0 needs even sides) and FFV1 RGB; a 10-bit 4:2:2 H.264 when
    // this x264 has high bit depth, else 10-bit 4:2:2 ProRes.
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            &format!("{colour}:s=367x481,format=yuv444p"),
            "-c:v",
            "libx264",
            "-crf",
            "12",
            "odd444.mp4",
        ],
    );
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            &format!("{colour}:s=367x481,format=bgr0"),
            "-c:v",
            "ffv1",
            "odd.mkv",
        ],
    );
    let x264_10bit = String::from_utf8_lossy(
        &Command::new("ffmpeg")
            .args(["-hide_banner", "-h", "encoder=libx264"])
            .output()
            .unwrap()
            .stdout,
    )
    .contains("yuv422p10le");
    let (codec, file) = if x264_10bit {
        ("libx264", "p10.mp4")
    } else {
        ("prores_ks", "p10.mov")
    };
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            &format!("{colour}:s=64x48"),
            "-c:v",
            codec,
            "-pix_fmt",
            "yuv422p10le",
            file,
        ],
    );
    let cases = [
        ("odd444.mp4", (367, 481), "yuv444p"),
        ("odd.mkv", (367, 481), "bgr0"),
        (file, (64, 48), "yuv422p10le"),
    ];
    let server = Server::start(&[]);
    for (name, (width, height), pix_fmt) in cases {
        let path = dir.path().join(name);
        assert_eq!(
            probe(&path, "stream=width,height,pix_fmt", &[]),
            [format!("{width},{height},{pix_fmt}")],
            "{name}"
        );
        let clip = upload_ok(&server, &path, "max_frames=2");
        assert_eq!(
            (
                clip["source"]["width"].clone(),
                clip["source"]["height"].clone()
            ),
            (width.into(), height.into()),
            "{name}: {clip}"
        );
        assert_eq!(clip["source"]["frames"], 10, "{name}: {clip}");
        for frame in context_frames(&server, &clip) {
            assert_eq!(frame.dimensions(), (width, height), "{name}");
            // 0x3366cc through YUV and back, within a few levels.
            let mean = mean_rgb(&frame);
            for (got, want) in mean.iter().zip([51.0, 102.0, 204.0]) {
                assert!((got - want).abs() < 4.0, "{name}: {mean:?}");
            }
        }
    }
}

#[test]
fn an_animated_gif_uploads_every_frame_with_its_delay() {
    if !ready() || !has_encoder("gif") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            &numbered("64x48", 10, 1.2),
            "-f",
            "gif",
            "clip.gif",
        ],
    );
    let gif = dir.path().join("clip.gif");
    assert_eq!(&std::fs::read(&gif).unwrap()[..6], b"GIF89a");

    let server = Server::start(&[]);
    let response = Client::new()
        .post(server.at("/v1/clips?max_frames=12"))
        .header("content-type", "image/gif")
        .body(std::fs::read(&gif).unwrap())
        .send()
        .unwrap();
    assert_eq!(response.status(), 201);
    let clip: Value = response.json().unwrap();
    assert_eq!(clip["source"]["kind"], "video", "{clip}");
    assert_eq!(clip["source"]["frames"], 12, "{clip}");
    let expected: Vec<f64> = (0..12).map(|k| f64::from(k) / 10.0).collect();
    assert_close(&times(&clip), &expected, 1e-6);
    let frames = context_frames(&server, &clip);
    assert!(frames.iter().all(|f| f.dimensions() == (64, 48)));
    // The palette blurs the ramp, but the frames are not all the first one.
    assert!(mean_rgb(&frames[11])[0] > mean_rgb(&frames[0])[0] + 30.0);
}

#[test]
fn files_without_video_or_without_frames_are_refused_naming_the_problem() {
    if !ready() || !has_encoder("aac") || !has_encoder("mjpeg") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    ffmpeg(
        dir.path(),
        &["-f", "lavfi", "-i", "sine=d=1", "-c:a", "aac", "audio.m4a"],
    );
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            "testsrc2=s=64x48:r=10:d=1",
            "-frames:v",
            "0",
            "-c:v",
            "mjpeg",
            "empty.avi",
        ],
    );
    let empty = dir.path().join("empty.avi");
    // A video stream, with a size, and no frames.
    assert_eq!(probe(&empty, "stream=width,height", &[]), ["64,48"]);
    assert_eq!(decoded_frames(&empty), 0);

    let server = Server::start(&[]);
    let refused = |path: &Path, status: u16, kind: &str, fragment: &str| {
        let (got, body) = upload(&server, path, "");
        assert_eq!(got, status, "{body}");
        assert_eq!(body["kind"], kind, "{body}");
        let message = body["error"].as_str().unwrap();
        assert!(message.contains(fragment), "{message:?} lacks {fragment:?}");
    };
    refused(
        &dir.path().join("audio.m4a"),
        415,
        "unsupported_media",
        "audio only (aac) and no video stream",
    );
    refused(&empty, 422, "unreadable_media", "no frames that decode");
}

#[test]
fn a_corrupt_frame_in_the_middle_is_skipped_with_a_warning() {
    if !ready() || !has_encoder("mjpeg") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            &numbered("64x48", 10, 3.0),
            "-c:v",
            "mjpeg",
            "-q:v",
            "2",
            "good.avi",
        ],
    );
    let good = dir.path().join("good.avi");
    // Zero frame 14's JPEG after its first 10 bytes (its start marker and the start of its
    // header survive; its tables and data are lost, as on a damaged disk).
    let packet = |entry: &str| -> usize { probe(&good, entry, &[])[14].parse().unwrap() };
    let (pos, size) = (packet("packet=pos"), packet("packet=size"));
    let mut bytes = std::fs::read(&good).unwrap();
    assert_eq!(&bytes[pos..pos + 2], [0xff, 0xd8], "a JPEG starts here");
    bytes[pos + 10..pos + size].fill(0);
    let corrupt = dir.path().join("corrupt.avi");
    std::fs::write(&corrupt, bytes).unwrap();
    assert_eq!(decoded_frames(&good), 30);
    assert_eq!(decoded_frames(&corrupt), 29);

    let server = Server::start(&[]);
    let clip = upload_ok(&server, &corrupt, "max_frames=32");
    assert_eq!(clip["source"]["frames"], 29, "{clip}");
    let warnings = warnings(&clip);
    assert_eq!(warnings.len(), 1, "{clip}");
    assert!(
        warnings[0].contains("1 packet decoded to no frame and was skipped")
            && warnings[0].contains("mjpeg")
            && warnings[0].contains("the 29 frames that decoded (the container lists 30)"),
        "{warnings:?}"
    );
    // Every frame but 14, each at its own time.
    let expected: Vec<usize> = (0..30).filter(|&n| n != 14).collect();
    let numbers: Vec<usize> = context_frames(&server, &clip)
        .iter()
        .map(frame_number)
        .collect();
    assert_eq!(numbers, expected);
    let want: Vec<f64> = expected.iter().map(|&n| n as f64 / 10.0).collect();
    assert_close(&times(&clip), &want, 1e-6);
}

#[test]
fn a_clip_past_the_frame_limit_is_refused_while_its_frames_are_listed() {
    if !ready() || !has_encoder("ffv1") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    ffmpeg(
        dir.path(),
        &[
            "-f",
            "lavfi",
            "-i",
            &numbered("64x48", 10, 2.0),
            "-c:v",
            "ffv1",
            "long.mkv",
        ],
    );
    let long = dir.path().join("long.mkv");
    // Matroska declares no frame count: only the listing can find 20 frames.
    assert_eq!(declared_frames(&long), None);
    let server = Server::start(&["--max-source-frames", "10"]);
    let (status, body) = upload(&server, &long, "");
    assert_eq!(status, 413, "{body}");
    assert_eq!(body["kind"], "too_large");
    let message = body["error"].as_str().unwrap();
    assert!(
        message.contains("the clip has 11 frames; at most 10"),
        "{message}"
    );
}
