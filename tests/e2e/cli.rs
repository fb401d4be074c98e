//! The `c4g` command-line tool against a live `c4g-server`: upload, info, decode, export,
//! render and stream, with readable and `--json` output, and errors a person can act on; a fit
//! on a `c4g-fitter` worker, whose scene the commands then serve.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::Path;
use std::process::{Command, Output};

use c4g_e2e::{
    FitterWorker, Server, binary, ort_available, shared_data, synthetic_clip, upload_synthetic,
};
use c4g_formats::{frames_zip, ply};
use reqwest::blocking::Client;
use serde_json::{Value, json};

fn c4g(server: &Server, args: &[&str]) -> Output {
    Command::new(binary("c4g"))
        .arg("--server")
        .arg(server.url())
        .args(args)
        .env_remove("C4G_API_KEY")
        .output()
        .unwrap()
}

fn ok(output: Output) -> String {
    let stdout = String::from_utf8(output.stdout).unwrap();
    assert!(
        output.status.success(),
        "stdout: {stdout}\nstderr: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    stdout
}

fn path(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn the_cli_uploads_decodes_exports_renders_and_streams() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let work = tempfile::tempdir().unwrap();

    // Upload a directory of frames with their timestamps; --json gives the clip.
    let (frames, times) = synthetic_clip();
    let dir = work.path().join("frames");
    std::fs::create_dir(&dir).unwrap();
    for frame in &frames {
        std::fs::copy(frame, dir.join(frame.file_name().unwrap())).unwrap();
    }
    let stamps: Vec<String> = times.iter().map(f64::to_string).collect();
    let clip: Value = serde_json::from_str(&ok(c4g(
        &server,
        &[
            "--json",
            "upload",
            path(&dir),
            "--timestamps",
            &stamps.join(","),
        ],
    )))
    .unwrap();
    let id = clip["id"].as_str().unwrap().to_owned();
    assert_eq!(clip["context_times"], json!([0.0, 0.2, 0.4, 0.6]));

    // Readable info names the model and the clip.
    let info = ok(c4g(&server, &["info"]));
    assert!(info.contains("c4g-tiny") && info.contains(&id), "{info}");

    // Decode as JSON equals the REST API's answer; export writes a PLY of the same set.
    let decoded: Value =
        serde_json::from_str(&ok(c4g(&server, &["--json", "decode", &id, "--t", "0.3"]))).unwrap();
    let rest: Value = Client::new()
        .post(server.at(&format!("/v1/clips/{id}/gaussians")))
        .json(&json!({"t": 0.3}))
        .send()
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(decoded["frames"], rest["frames"]);
    let exported = work.path().join("moment.ply");
    ok(c4g(
        &server,
        &["export", &id, "--t", "0.3", "-o", path(&exported)],
    ));
    let set = ply::read(&exported).unwrap();
    assert_eq!(set.len(), 512);
    let x = rest["frames"][0]["means"][0][0].as_f64().unwrap();
    assert!((f64::from(set.positions()[0][0]) - x).abs() < 1e-6);
    // A range as a zip of PLYs: the frames the export endpoint makes (tests/e2e/exports.rs reads
    // every format back), with the set at 0.3 s among them.
    let zipped = work.path().join("clip.ply.zip");
    let out = ok(c4g(
        &server,
        &[
            "--json",
            "export",
            &id,
            "--start",
            "0.1",
            "--end",
            "0.3",
            "--step",
            "0.1",
            "-o",
            path(&zipped),
        ],
    ));
    let line: Value = serde_json::from_str(&out).unwrap();
    assert_eq!(line["format"], "ply_zip", "{line}");
    assert_eq!(line["sets"], 3, "{line}");
    let (_, frames) = frames_zip::decode(&std::fs::read(&zipped).unwrap(), 1 << 24).unwrap();
    assert_eq!(frames.len(), 3);
    // Decoded in one batch of three rather than alone: equal up to the batch's f32 rounding.
    assert_eq!(frames[2].0, 0.3);
    for (a, b) in frames[2].1.positions().iter().zip(set.positions()) {
        assert!((a[0] - b[0]).abs() < 1e-4, "{a:?} {b:?}");
    }
    let refused = c4g(&server, &["export", &id, "--t", "0.3", "-o", "x.splatv"]);
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("time range"));

    // Render writes the PNG the server renders.
    let image = work.path().join("view.png");
    ok(c4g(
        &server,
        &["render", &id, "--t", "0.3", "-o", path(&image)],
    ));
    let served = Client::new()
        .post(server.at(&format!("/v1/clips/{id}/render")))
        .json(&json!({"t": 0.3}))
        .send()
        .unwrap()
        .bytes()
        .unwrap();
    assert_eq!(
        image::open(&image).unwrap().to_rgb8().into_raw(),
        image::load_from_memory(&served)
            .unwrap()
            .to_rgb8()
            .into_raw()
    );

    // Stream over gRPC: one PLY per set, 0 to 0.6 s at 10 sets a second.
    let out = work.path().join("stream");
    ok(c4g(
        &server,
        &["stream", &id, "--fps", "10", "-o", path(&out)],
    ));
    let mut written: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    written.sort();
    assert_eq!(written.len(), 7, "{written:?}");

    // An error names the status, the kind and what is wrong.
    let late = c4g(&server, &["decode", &id, "--t", "9"]);
    assert!(!late.status.success());
    let stderr = String::from_utf8_lossy(&late.stderr);
    assert!(
        stderr.contains("400 invalid_input") && stderr.contains("context span"),
        "{stderr}"
    );
}

#[test]
fn the_cli_uploads_a_real_video_with_a_window_and_a_stride() {
    if !ort_available() {
        return;
    }
    let Some(data) = shared_data() else { return };
    let server = Server::start(&[]);
    let video = data.join("dog/01_dog.mp4");
    let clip: Value = serde_json::from_str(&ok(c4g(
        &server,
        &[
            "--json",
            "upload",
            path(&video),
            "--start",
            "1",
            "--end",
            "3",
            "--stride",
            "15",
        ],
    )))
    .unwrap();
    let times: Vec<f64> = clip["context_times"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_f64().unwrap())
        .collect();
    // 29.97 fps: frames 30 (1.001 s) to 89 (2.970 s) lie in [1, 3] s; every 15th is 30, 45, 60, 75.
    assert_eq!(times.len(), 4, "{times:?}");
    assert!((times[0] - 1.001).abs() < 1e-3, "{times:?}");
    assert!(times.iter().all(|t| (1.0..=3.0).contains(t)), "{times:?}");
    assert_eq!(clip["source"]["frames"], 289);
}

/// The server's decode at `t` from `scene`: the scene that served it (`X-C4G-Scene`), and the sets.
fn rest_decode(server: &Server, id: &str, t: f64, scene: &str) -> (String, Value) {
    let response = Client::new()
        .post(server.at(&format!("/v1/clips/{id}/gaussians")))
        .json(&json!({"t": t, "scene": scene}))
        .send()
        .unwrap();
    assert_eq!(response.status(), 200);
    let served = response.headers()["x-c4g-scene"]
        .to_str()
        .unwrap()
        .to_owned();
    (served, response.json().unwrap())
}

#[test]
fn the_cli_fits_a_clip_and_then_serves_the_fitted_scene() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    let work = tempfile::tempdir().unwrap();
    let _worker = FitterWorker::start(&server.url(), "f1");

    // A tiny fit, followed to its end; the summary is the clip's record of the fitted scene. The
    // synthetic clip keeps 7 frames: every 4th is held out, so the fit scores one.
    let summary = ok(c4g(
        &server,
        &[
            "fit",
            &id,
            "--preset",
            "fast",
            "--steps",
            "8",
            "--resolution",
            "32",
            "--max-frames",
            "8",
            "--holdout-every",
            "4",
        ],
    ));
    let record: Value = Client::new()
        .get(server.at(&format!("/v1/clips/{id}")))
        .send()
        .unwrap()
        .json()
        .unwrap();
    let fitted = &record["fitted"];
    assert_eq!(fitted["steps"], 8, "{record:#}");
    assert_eq!(fitted["preset"], "fast");
    assert_eq!(fitted["holdout_frames"], json!([3]), "{record:#}");
    assert!(summary.starts_with(&format!("{id}\n")), "{summary}");
    let psnr = |key: &str| fitted[key].as_f64().unwrap();
    for part in [
        format!(
            "held-out  {:.2} dB PSNR fitted, {:.2} feed-forward ({:+.2} dB) on 1 frame\n",
            psnr("holdout_psnr"),
            psnr("holdout_psnr_feed_forward"),
            psnr("holdout_psnr") - psnr("holdout_psnr_feed_forward")
        ),
        format!(
            "{} Gaussians ({} static) at {} keyframes",
            fitted["gaussians"],
            fitted["static_gaussians"],
            fitted["keyframes"].as_array().unwrap().len()
        ),
        format!("8 steps in {:.3} s", fitted["seconds"].as_f64().unwrap()),
        format!("job       {}", fitted["job_id"].as_str().unwrap()),
    ] {
        assert!(summary.contains(&part), "{part:?} not in\n{summary}");
    }
    let info = ok(c4g(&server, &["info", &id]));
    assert!(info.contains("fitted    "), "{info}");

    // `--scene fitted` decodes the fitted scene, as the server serves it; `feed-forward` the
    // model's answer, which differs.
    let decode = |scene: &str| -> Value {
        serde_json::from_str(&ok(c4g(
            &server,
            &["--json", "decode", &id, "--t", "0.3", "--scene", scene],
        )))
        .unwrap()
    };
    let (served, rest) = rest_decode(&server, &id, 0.3, "fitted");
    assert_eq!(served, "fitted");
    assert_eq!(decode("fitted")["frames"], rest["frames"]);
    let (served, model) = rest_decode(&server, &id, 0.3, "feed-forward");
    assert_eq!(served, "feed-forward");
    assert_eq!(decode("feed-forward")["frames"], model["frames"]);
    assert_ne!(rest["frames"], model["frames"]);
    let summary = ok(c4g(
        &server,
        &["decode", &id, "--t", "0.3", "--scene", "fitted"],
    ));
    assert!(
        summary.contains(&format!("{} Gaussians", fitted["gaussians"])),
        "{summary}"
    );

    // A render says which scene served it: auto is the fitted one now.
    let image = work.path().join("view.png");
    let line: Value = serde_json::from_str(&ok(c4g(
        &server,
        &[
            "--json",
            "render",
            &id,
            "--t",
            "0.3",
            "--width",
            "32",
            "--height",
            "32",
            "-o",
            path(&image),
        ],
    )))
    .unwrap();
    assert_eq!(line["scene"], "fitted", "{line}");
}
