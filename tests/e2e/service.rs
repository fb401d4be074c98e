//! A real clip and a synthetic test clip through the whole service, as a client sees it:
//! upload → decode → render → stream, over raw HTTP and over gRPC, against `c4g-server` running
//! the default model as a process on loopback. What the server renders must equal what the
//! engine and the renderer produce in this process from the same context frames.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::Path;

use c4g_e2e::health::{HealthClient, pb_health};
use c4g_e2e::{
    Server, frames_form, json_of, metric, ort_available, shared_data, synthetic_clip, workspace,
};
use c4g_engine::{ContextFrame, Engine, EngineOptions};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::{Camera, NormalizedIntrinsics};
use glam::{Affine3A, Mat4};
use reqwest::blocking::Client;
use serde_json::{Value, json};

fn post_json(client: &Client, url: String, body: Value) -> reqwest::blocking::Response {
    client.post(url).json(&body).send().unwrap()
}

/// What this process computes for clip `clip` at `t` seen by `world_to_camera` at `size`:
/// the server's own context frames, preprocessed, encoded, decoded and rasterized here.
fn render_in_process(
    server: &Server,
    clip: &Value,
    t: f64,
    world_to_camera: Mat4,
    size: u32,
) -> Vec<u8> {
    let engine = Engine::load(
        workspace().join("models/c4g-tiny"),
        EngineOptions::default(),
    )
    .unwrap();
    let client = Client::new();
    let id = clip["id"].as_str().unwrap();
    let times = clip["context_times"].as_array().unwrap();
    let frames: Vec<ContextFrame> = times
        .iter()
        .enumerate()
        .map(|(k, time)| {
            let png = client
                .get(server.at(&format!("/v1/clips/{id}/frames/{k}")))
                .send()
                .unwrap()
                .bytes()
                .unwrap();
            let image = image::load_from_memory(&png).unwrap().to_rgb8();
            ContextFrame::new(time.as_f64().unwrap(), engine.preprocess(&image).unwrap())
        })
        .collect();
    let encoding = engine.encode(&frames).unwrap();
    let set = engine.decode(&encoding, &[t]).unwrap().remove(0);
    let camera = Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        size,
        size,
        Affine3A::from_mat4(world_to_camera),
    )
    .unwrap();
    let image = CpuRasterizer::new()
        .render(
            &set,
            &camera,
            &RenderOptions {
                features: false,
                ..RenderOptions::default()
            },
        )
        .unwrap();
    image
        .rgb
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

/// Largest per-channel difference and the fraction of channels that differ.
fn compare(a: &[u8], b: &[u8]) -> (u8, f64) {
    assert_eq!(a.len(), b.len());
    let max = a
        .iter()
        .zip(b)
        .map(|(x, y)| x.abs_diff(*y))
        .max()
        .unwrap_or(0);
    let differing = a.iter().zip(b).filter(|(x, y)| x != y).count();
    (max, differing as f64 / a.len() as f64)
}

fn png_rgb(bytes: &[u8]) -> image::RgbImage {
    image::load_from_memory(bytes).unwrap().to_rgb8()
}

#[test]
fn a_real_video_goes_through_upload_decode_render_and_stream_over_http_and_grpc() {
    if !ort_available() {
        return;
    }
    let Some(data) = shared_data() else { return };
    let video = std::fs::read(data.join("bedroom/bedroom.mp4")).unwrap();
    let server = Server::start(&[]);
    let client = Client::new();

    // Upload: encoded once; the same bytes again are the same clip.
    let upload = |video: Vec<u8>| {
        client
            .post(server.at("/v1/clips?max_frames=4"))
            .header("content-type", "video/mp4")
            .body(video)
            .send()
            .unwrap()
    };
    let first = upload(video.clone());
    assert_eq!(first.status(), 201);
    let clip = json_of(first);
    let again = upload(video);
    assert_eq!(again.status(), 200);
    let again = json_of(again);
    assert_eq!(
        (again["id"].clone(), again["created"].clone()),
        (clip["id"].clone(), json!(false))
    );
    let id = clip["id"].as_str().unwrap().to_owned();
    assert_eq!(clip["source"]["frames"], 200);
    assert_eq!(
        (
            clip["source"]["width"].clone(),
            clip["source"]["height"].clone()
        ),
        (json!(960), json!(540))
    );
    let times: Vec<f64> = clip["context_times"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_f64().unwrap())
        .collect();
    assert_eq!(times.len(), 4);
    assert_eq!(times[0], 0.0);
    assert!((times[3] - 199.0 / 30.0).abs() < 1e-3, "{times:?}");

    // Decode, as JSON and as packed binary.
    let decoded = json_of(post_json(
        &client,
        server.at(&format!("/v1/clips/{id}/gaussians")),
        json!({"times": [1.0, 2.5]}),
    ));
    let frames = decoded["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 2);
    assert_eq!(frames[0]["count"], 512);
    let binary = client
        .post(server.at(&format!("/v1/clips/{id}/gaussians")))
        .json(&json!({"t": 1.0, "format": "binary"}))
        .send()
        .unwrap()
        .bytes()
        .unwrap();
    assert_eq!(&binary[..4], b"C4GS");
    assert_eq!(binary.len(), 24 + 512 * 14 * 4);
    let first_x = f32::from_le_bytes(binary[24..28].try_into().unwrap());
    assert_eq!(
        f64::from(first_x),
        frames[0]["means"][0][0].as_f64().unwrap()
    );

    // Render: the server's PNG equals this process's engine + rasterizer on the same frames.
    let png = client
        .post(server.at(&format!("/v1/clips/{id}/render")))
        .json(&json!({"t": 1.0, "width": 96, "height": 96}))
        .send()
        .unwrap();
    assert_eq!(png.status(), 200);
    assert_eq!(png.headers()["content-type"], "image/png");
    let served = png_rgb(&png.bytes().unwrap());
    let ours = render_in_process(&server, &clip, 1.0, Mat4::IDENTITY, 96);
    let (max, fraction) = compare(served.as_raw(), &ours);
    // Same code on the same inputs; ONNX Runtime may order float sums differently per run, so
    // allow a one-level rounding flip in a few channels.
    assert!(
        max <= 1 && fraction < 0.01,
        "max diff {max}, {fraction} of channels differ"
    );

    // Depth: raw f32, positive where something was drawn.
    let depth = client
        .post(server.at(&format!("/v1/clips/{id}/render")))
        .json(&json!({"t": 1.0, "width": 32, "height": 24, "format": "depth"}))
        .send()
        .unwrap();
    assert_eq!(depth.headers()["x-c4g-width"], "32");
    let depth = depth.bytes().unwrap();
    assert_eq!(depth.len(), 32 * 24 * 4);
    let values: Vec<f32> = depth
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert!(values.iter().all(|v| v.is_finite() && *v >= 0.0));
    assert!(values.iter().any(|v| *v > 0.0));

    // A trajectory video: an MP4 with the asked-for frames.
    let video = client
        .post(server.at(&format!("/v1/clips/{id}/render")))
        .json(&json!({"trajectory": {"kind": "orbit", "depth": 2.0, "angle_degrees": 20}, "frames": 6, "width": 64, "height": 48}))
        .send()
        .unwrap();
    assert_eq!(video.status(), 200);
    assert_eq!(video.headers()["content-type"], "video/mp4");
    let video = video.bytes().unwrap();
    assert_eq!(&video[4..8], b"ftyp");

    // gRPC on the same port: the same Gaussians, the same image, and a stream over the span.
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let decoded = grpc
            .decode(pb::DecodeRequest {
                clip_id: id.clone(),
                times: vec![1.0],
                precision: 0,
                keyframes: None,
                quality: 0,
                prune: None,
                features: false,
                scene: String::new(),
            })
            .await
            .unwrap()
            .into_inner();
        let set = decoded.frames[0].gaussians.as_ref().unwrap();
        assert_eq!(set.count, 512);
        assert_eq!(set.means[..4], binary[24..28]);

        let rendered = grpc
            .render(pb::RenderRequest {
                clip_id: id.clone(),
                time: 1.0,
                width: 96,
                height: 96,
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner();
        let (max, fraction) = compare(png_rgb(&rendered.data).as_raw(), served.as_raw());
        assert!(max <= 1 && fraction < 0.01);

        let mut stream = grpc
            .stream_gaussians(pb::StreamGaussiansRequest {
                clip_id: id.clone(),
                start: Some(0.0),
                end: Some(2.0),
                spacing: Some(pb::stream_gaussians_request::Spacing::Fps(2.0)),
                precision: pb::Precision::F16 as i32,
                keyframes: None,
                quality: 0,
                prune: None,
                compact: None,
                scene: String::new(),
            })
            .await
            .unwrap()
            .into_inner();
        let mut streamed = Vec::new();
        while let Some(frame) = stream.message().await.unwrap() {
            let set = frame.gaussians.unwrap();
            assert_eq!(set.means.len(), 512 * 3 * 2, "f16: two bytes a number");
            streamed.push(frame.time);
        }
        assert_eq!(streamed, vec![0.0, 0.5, 1.0, 1.5, 2.0]);

        let mut health = HealthClient::connect(&server.url()).await;
        let status = health
            .check(pb_health::HealthCheckRequest {
                service: "c4g.v1.C4G".into(),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(
            status.status,
            pb_health::health_check_response::ServingStatus::Serving as i32
        );
    });

    // Delete: gone from listings and lookups.
    let deleted = client
        .delete(server.at(&format!("/v1/clips/{id}")))
        .send()
        .unwrap();
    assert_eq!(deleted.status(), 204);
    assert_eq!(
        client
            .get(server.at(&format!("/v1/clips/{id}")))
            .send()
            .unwrap()
            .status(),
        404
    );
    let listed = json_of(client.get(server.at("/v1/clips")).send().unwrap());
    assert_eq!(listed["clips"].as_array().unwrap().len(), 0);
}

fn ground_truth(dir: &Path, name: &str) -> Vec<f32> {
    image::open(dir.join(name))
        .unwrap()
        .to_rgb8()
        .into_raw()
        .iter()
        .map(|v| f32::from(*v) / 255.0)
        .collect()
}

#[test]
fn the_synthetic_test_clip_reconstructs_as_the_model_card_says_and_survives_a_restart() {
    if !ort_available() {
        return;
    }
    let (frames, times) = synthetic_clip();
    let dir = frames[0].parent().unwrap().to_path_buf();
    let meta: Value =
        serde_json::from_slice(&std::fs::read(dir.join("clip.json")).unwrap()).unwrap();
    let server = Server::start(&[]);
    let client = Client::new();
    let clip = json_of(
        client
            .post(server.at("/v1/clips"))
            .multipart(frames_form(&frames, &times).text("max_frames", "4"))
            .send()
            .unwrap(),
    );
    // Four of seven frames spread evenly: the evaluation's context frames 0, 2, 4, 6.
    assert_eq!(clip["context_times"], json!([0.0, 0.2, 0.4, 0.6]));
    let id = clip["id"].as_str().unwrap().to_owned();

    // At each held-out time, from the held-out frame's camera, the served render scores the
    // PSNR the Python evaluation measured (the model card's number), within 8-bit rounding.
    let poses = &meta["world_to_camera_model"];
    for (k, target) in meta["targets"].as_array().unwrap().iter().enumerate() {
        let frame = target.as_u64().unwrap() as usize;
        let w2c: Vec<f64> = poses[frame]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|row| row.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()))
            .collect();
        let png = client
            .post(server.at(&format!("/v1/clips/{id}/render")))
            .json(&json!({"t": times[frame], "camera": {"world_to_camera": w2c}}))
            .send()
            .unwrap();
        assert_eq!(png.status(), 200);
        let served = png_rgb(&png.bytes().unwrap());
        let served: Vec<f32> = served
            .as_raw()
            .iter()
            .map(|v| f32::from(*v) / 255.0)
            .collect();
        let truth = ground_truth(&dir, &format!("frame-{frame:02}.png"));
        let psnr = c4g_renderer::fidelity::psnr(&served, &truth, 64, 64, None).unwrap();
        let python = meta["python_psnr"]["interpolated"][k].as_f64().unwrap();
        assert!(
            (psnr - python).abs() < 0.15,
            "frame {frame}: served {psnr:.3} dB, evaluation {python:.3} dB"
        );
    }

    // A restart serves the stored clip without encoding it again.
    let store = server.stop();
    let server = Server::start_in(store, &[]);
    let listed = json_of(client.get(server.at("/v1/clips")).send().unwrap());
    assert_eq!(listed["clips"][0]["id"], json!(id));
    let decoded = json_of(post_json(
        &client,
        server.at(&format!("/v1/clips/{id}/gaussians")),
        json!({"t": 0.3}),
    ));
    assert_eq!(decoded["frames"][0]["count"], 512);
    let metrics = client
        .get(server.at("/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    assert!(
        !metrics.contains("c4g_encode_duration_seconds_count"),
        "re-encoded after a restart"
    );
    assert!(metrics.contains("c4g_cache_misses_total 1"), "{metrics}");
}

fn zip_of_frames(frames: &[std::path::PathBuf]) -> Vec<u8> {
    use std::io::Write;
    let mut writer = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for frame in frames {
        writer
            .start_file(
                frame.file_name().unwrap().to_string_lossy(),
                zip::write::SimpleFileOptions::default(),
            )
            .unwrap();
        writer.write_all(&std::fs::read(frame).unwrap()).unwrap();
    }
    writer.finish().unwrap().into_inner()
}

#[test]
fn concurrent_uploads_of_one_clip_encode_once_and_evicted_features_reload_from_disk() {
    if !ort_available() {
        return;
    }
    // No memory for features: every clip but the newest is evicted, and reads come from disk.
    let server = Server::start(&["--cache-mib", "0"]);
    let (frames, times) = synthetic_clip();
    let archive = zip_of_frames(&frames);

    // Four gRPC uploads of the same zip at once: one clip, encoded once.
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let clips: Vec<pb::Clip> = runtime.block_on(async {
        let uploads = (0..4).map(|_| {
            let (url, archive, times) = (server.url(), archive.clone(), times.clone());
            tokio::spawn(async move {
                let mut grpc = C4gClient::connect(url).await.unwrap();
                let header = pb::UploadRequest {
                    part: Some(pb::upload_request::Part::Header(pb::UploadHeader {
                        kind: pb::MediaKind::Zip as i32,
                        timestamps: times,
                        ..Default::default()
                    })),
                };
                let chunks = archive.chunks(4096).map(|c| pb::UploadRequest {
                    part: Some(pb::upload_request::Part::Chunk(c.to_vec())),
                });
                let messages: Vec<_> = std::iter::once(header).chain(chunks).collect();
                grpc.upload(tokio_stream::iter(messages))
                    .await
                    .unwrap()
                    .into_inner()
            })
        });
        let mut clips = Vec::new();
        for upload in uploads {
            clips.push(upload.await.unwrap());
        }
        clips
    });
    assert!(clips.iter().all(|c| c.clip_id == clips[0].clip_id));
    assert_eq!(clips.iter().filter(|c| c.created).count(), 1);
    assert_eq!(clips[0].context_times, vec![0.0, 0.2, 0.4, 0.6]);
    let client = Client::new();
    let metrics = client
        .get(server.at("/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    assert_eq!(metric(&metrics, "c4g_encode_duration_seconds_count"), 1.0);

    // A second clip (the same frames at another rate) evicts the first; decoding the first reads
    // its features back from disk and gives the same Gaussians.
    let first = &clips[0].clip_id;
    let before = json_of(post_json(
        &client,
        server.at(&format!("/v1/clips/{first}/gaussians")),
        json!({"t": 0.3}),
    ));
    let second = json_of(
        client
            .post(server.at("/v1/clips?fps=5"))
            .header("content-type", "application/zip")
            .body(archive)
            .send()
            .unwrap(),
    );
    assert_ne!(second["id"], json!(first));
    let after = json_of(post_json(
        &client,
        server.at(&format!("/v1/clips/{first}/gaussians")),
        json!({"t": 0.3}),
    ));
    assert_eq!(before, after);
    let metrics = client
        .get(server.at("/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    assert!(
        metric(&metrics, "c4g_cache_evictions_total") >= 1.0,
        "{metrics}"
    );
    assert!(
        metric(&metrics, "c4g_cache_misses_total") >= 1.0,
        "{metrics}"
    );
}

#[test]
fn a_full_encode_pool_refuses_at_once_with_retry_after() {
    if !ort_available() {
        return;
    }
    let Some(data) = shared_data() else { return };
    let server = Server::start(&["--max-concurrent-encodes", "1"]);
    let video = std::fs::read(data.join("dog/01_dog.mp4")).unwrap();
    let (frames, times) = synthetic_clip();
    std::thread::scope(|scope| {
        let slow = scope.spawn(|| {
            // Slow on purpose: a busy CI machine reading a real video in a debug server may
            // take longer than a client's default 30 s.
            Client::builder()
                .timeout(std::time::Duration::from_secs(180))
                .build()
                .unwrap()
                .post(server.at("/v1/clips?max_frames=8"))
                .body(video)
                .send()
                .unwrap()
                .status()
        });
        // While the video is read (seconds), another upload finds no free slot.
        std::thread::sleep(std::time::Duration::from_millis(400));
        let refused = Client::new()
            .post(server.at("/v1/clips"))
            .multipart(frames_form(&frames, &times))
            .send()
            .unwrap();
        assert_eq!(refused.status(), 429);
        assert_eq!(refused.headers()["retry-after"], "5");
        let body: Value = refused.json().unwrap();
        assert_eq!(body["kind"], "busy");
        assert_eq!(slow.join().unwrap(), 201);
    });
    // Once the slot is free the same upload goes through.
    let ok = Client::new()
        .post(server.at("/v1/clips"))
        .multipart(frames_form(&frames, &times))
        .send()
        .unwrap();
    assert_eq!(ok.status(), 201);
}

/// Device-resident encodings asked for on the CPU (`C4G_DEVICE_CACHE_MIB`; off there by
/// default): decodes bind the clip's features through ONNX Runtime's I/O binding and answer
/// exactly what a server without them answers; the gauges show the clip resident.
#[test]
fn resident_encodings_change_no_answer_and_show_in_the_metrics() {
    if !ort_available() {
        return;
    }
    let plain = Server::start(&[]);
    let resident = Server::start(&["--device-cache-mib", "64"]);
    let client = Client::new();
    let (frames, times) = synthetic_clip();
    let upload = |server: &Server| {
        let response = client
            .post(server.at("/v1/clips"))
            .multipart(frames_form(&frames, &times))
            .send()
            .unwrap();
        json_of(response)["id"].as_str().unwrap().to_owned()
    };
    let body = json!({"times": [0.1, 0.35, 0.6]});
    let decode = |server: &Server, id: &str| {
        json_of(post_json(
            &client,
            server.at(&format!("/v1/clips/{id}/gaussians")),
            body.clone(),
        ))
    };
    let (a, b) = (upload(&plain), upload(&resident));
    assert_eq!(
        decode(&plain, &a)["frames"],
        decode(&resident, &b)["frames"]
    );
    decode(&resident, &b);
    let text = client
        .get(resident.at("/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    assert_eq!(metric(&text, "c4g_device_cache_clips"), 1.0, "{text}");
    assert!(metric(&text, "c4g_device_cache_bytes") > 0.0);
    assert_eq!(metric(&text, "c4g_device_cache_placements_total"), 1.0);
    let text = client
        .get(plain.at("/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    assert_eq!(
        metric(&text, "c4g_device_cache_clips"),
        0.0,
        "off on the CPU by default"
    );
}
