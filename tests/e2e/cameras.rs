//! Given cameras through the running service: an upload over REST (COLMAP text as multipart
//! fields), gRPC (`UploadHeader.cameras`) or the CLI (`c4g upload --colmap`) carries per-frame
//! cameras, the clip stores its context frames' cameras in the model's frame and
//! `GET /v1/clips/{id}` shows them; other cameras make another clip; a camera count that does not
//! match the frames, or a bad camera file, is a 400 that says what is wrong. Renders follow the
//! input camera path: views, bullet time and the same path at a new time. Cameras that move are
//! fitted to the model's depth scale, and held-out views match better for it.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::PathBuf;

use c4g_e2e::{
    Server, binary, expect_error, expect_invalid, frames_form, json_of, ort_available, post_upload,
    synthetic_clip, upload_synthetic,
};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use reqwest::blocking::Client;
use serde_json::Value;

/// Camera i of a made-up capture in a COLMAP world: centre moving on a curve (in metres, far
/// from the origin), a turn about the vertical growing with i. World-to-camera: `R (x - c)`.
fn camera(i: usize) -> ([[f64; 3]; 3], [f64; 3]) {
    let f = i as f64;
    let angle = 0.05 * f;
    let (s, c) = angle.sin_cos();
    // A rotation about y.
    let r = [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]];
    let centre = [50.0 + 0.3 * f, 2.0 - 0.01 * f * f, -7.0 + 0.1 * f];
    let t: [f64; 3] =
        std::array::from_fn(|row| -(0..3).map(|k| r[row][k] * centre[k]).sum::<f64>());
    (r, t)
}

/// COLMAP text for `n` frames of that capture. The matrix above turns by −angle about y, so its
/// quaternion (w, x, y, z) is (cos(angle/2), 0, −sin(angle/2), 0).
fn colmap(n: usize) -> (String, String) {
    let cameras = "1 PINHOLE 256 256 224.4352 224.4352 128 128\n".to_owned();
    let mut images = String::new();
    for i in 0..n {
        let half = 0.05 * i as f64 / 2.0;
        let (_, t) = camera(i);
        images += &format!(
            "{} {} 0 {} 0 {} {} {} 1 frame-{i:02}.png\n\n",
            i + 1,
            half.cos(),
            -half.sin(),
            t[0],
            t[1],
            t[2]
        );
    }
    (cameras, images)
}

fn upload(server: &Server, cameras: &str, images: &str) -> reqwest::blocking::Response {
    let (frames, times) = synthetic_clip();
    let form = frames_form(&frames, &times)
        .text("max_frames", "4")
        .text("colmap_cameras", cameras.to_owned())
        .text("colmap_images", images.to_owned());
    Client::new()
        .post(server.at("/v1/clips"))
        .multipart(form)
        .send()
        .unwrap()
}

#[test]
fn an_upload_with_colmap_cameras_stores_its_context_cameras_in_the_model_frame() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let (cameras, images) = colmap(7);
    let response = upload(&server, &cameras, &images);
    assert_eq!(response.status(), 201);
    let clip = json_of(response);
    let id = clip["id"].as_str().unwrap().to_owned();
    let shown = json_of(
        Client::new()
            .get(server.at(&format!("/v1/clips/{id}")))
            .send()
            .unwrap(),
    );
    let stored = &shown["cameras"];
    assert_eq!(stored, &clip["cameras"]);
    assert_eq!(stored["format"], "colmap");
    let context: Vec<f64> = shown["context_times"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_f64().unwrap())
        .collect();
    // Frames 0, 2, 4, 6 of seven at 0.1 s are the four context frames.
    let frames = stored["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 4);
    let picked = [0, 2, 4, 6];
    // The independent computation: relative pose R_i R_0ᵀ, translation t_i − R_rel t_0, divided
    // by the largest distance of a context camera's centre from the first's.
    let centre = |i: usize| {
        let (r, t) = camera(i);
        std::array::from_fn::<f64, 3, _>(|k| -(0..3).map(|j| r[j][k] * t[j]).sum::<f64>())
    };
    let c0 = centre(0);
    let scale = picked
        .iter()
        .map(|&i| {
            let c = centre(i);
            (0..3).map(|k| (c[k] - c0[k]).powi(2)).sum::<f64>().sqrt()
        })
        .fold(0.0, f64::max);
    // The convention's scale, then fitted to the model's depth scale (the test below).
    let factor = stored["scale_fit"]["factor"].as_f64().unwrap();
    assert!((stored["scale_fit"]["convention_scale"].as_f64().unwrap() - scale).abs() < 1e-9);
    assert!((stored["scale"].as_f64().unwrap() * factor - scale).abs() < 1e-9);
    let (r0, t0) = camera(0);
    for (frame, (&i, &t)) in frames.iter().zip(picked.iter().zip(&context)) {
        assert_eq!(frame["t"].as_f64().unwrap(), t);
        let (r, ti) = camera(i);
        let rel: [[f64; 3]; 3] = std::array::from_fn(|a| {
            std::array::from_fn(|b| (0..3).map(|k| r[a][k] * r0[b][k]).sum())
        });
        let m: Vec<f64> = frame["world_to_camera"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        for a in 0..3 {
            let translation =
                (ti[a] - (0..3).map(|k| rel[a][k] * t0[k]).sum::<f64>()) / scale * factor;
            // 1e-9: the same arithmetic in another order (and a quaternion round trip) on
            // numbers of size 50, times the factor.
            assert!(
                (m[a * 4 + 3] - translation).abs() < 1e-9 * factor.max(1.0),
                "frame {i} row {a}"
            );
            for b in 0..3 {
                assert!(
                    (m[a * 4 + b] - rel[a][b]).abs() < 1e-9,
                    "frame {i} R[{a}][{b}]"
                );
            }
        }
        // Pixels over the size: 224.4352 / 256 is the model's 0.8767.
        assert!((frame["intrinsics"]["fx"].as_f64().unwrap() - 0.8767).abs() < 1e-12);
    }

    // The same upload with the same cameras is the same clip; other cameras make another.
    let again = upload(&server, &cameras, &images);
    assert_eq!(again.status(), 200);
    assert_eq!(json_of(again)["id"], clip["id"]);
    let other = json_of(upload(
        &server,
        &cameras,
        &images.replace(" 1 frame-06", " 1 frame-07"),
    ));
    assert_ne!(other["id"], clip["id"]);
    let plain = Client::new()
        .post(server.at("/v1/clips"))
        .multipart({
            let (frames, times) = synthetic_clip();
            frames_form(&frames, &times).text("max_frames", "4")
        })
        .send()
        .unwrap();
    let plain: Value = json_of(plain);
    assert_ne!(plain["id"], clip["id"]);
    assert!(plain.get("cameras").is_none());

    // `c4g upload --colmap DIR` sends the same frames with the same cameras: the same clip.
    let work = tempfile::tempdir().unwrap();
    let (frames, times) = synthetic_clip();
    let (model, dir) = (work.path().join("sparse"), work.path().join("frames"));
    std::fs::create_dir(&model).unwrap();
    std::fs::create_dir(&dir).unwrap();
    std::fs::write(model.join("cameras.txt"), &cameras).unwrap();
    std::fs::write(model.join("images.txt"), &images).unwrap();
    for frame in &frames {
        std::fs::copy(frame, dir.join(frame.file_name().unwrap())).unwrap();
    }
    let stamps: Vec<String> = times.iter().map(f64::to_string).collect();
    let output = std::process::Command::new(binary("c4g"))
        .args(["--server", &server.url(), "--json", "upload"])
        .arg(&dir)
        .args([
            "--timestamps",
            &stamps.join(","),
            "--max-frames",
            "4",
            "--colmap",
        ])
        .arg(&model)
        .env_remove("C4G_API_KEY")
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let uploaded: Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(uploaded["id"], clip["id"]);
    assert_eq!(uploaded["cameras"], clip["cameras"]);
}

#[test]
fn camera_counts_that_do_not_match_and_bad_camera_files_are_400() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let (cameras, images) = colmap(6);
    expect_invalid(upload(&server, &cameras, &images), "6 cameras for 7 frames");
    let (cameras, images) = colmap(7);
    expect_invalid(
        upload(
            &server,
            &cameras,
            &images.replace("frame-03.png", "frame-02.png"),
        ),
        "names the image \"frame-02.png\" twice",
    );
    expect_invalid(
        upload(
            &server,
            &cameras.replace("224.4352 224.4352", "224.4352 nan"),
            &images,
        ),
        "cameras.txt line 1: a parameter must be a finite number",
    );
    expect_invalid(
        upload(&server, &cameras.replace("256 256", "256 192"), &images),
        "estimated on 256x192 images but the frames are 64x64",
    );
    expect_invalid(
        upload(&server, "", &images),
        "uses camera 1, which cameras.txt does not list",
    );
    let (frames, times) = synthetic_clip();
    let only_cameras = frames_form(&frames, &times).text("colmap_cameras", cameras);
    expect_invalid(
        Client::new()
            .post(server.at("/v1/clips"))
            .multipart(only_cameras)
            .send()
            .unwrap(),
        "need both `colmap_cameras` (cameras.txt) and `colmap_images`",
    );
    let skewed = "[".to_owned()
        + &["{\"world_to_camera\": [1,0,0,0, 0,1,0.5,0, 0,0,1,0, 0,0,0,1]}"; 7].join(",")
        + "]";
    let form = frames_form(&frames, &times).text("cameras", skewed);
    expect_invalid(
        Client::new()
            .post(server.at("/v1/clips"))
            .multipart(form)
            .send()
            .unwrap(),
        "cameras[0]: the pose's 3x3 part is not a rotation",
    );
}

/// Cameras of the seven frames in the model's frame already (camera 0 the identity): a turn
/// about y and a slide along x, both growing with the frame.
fn moving_cameras() -> String {
    let list: Vec<String> = (0..7)
        .map(|i| {
            let angle = 0.04 * f64::from(i);
            let (s, c) = angle.sin_cos();
            let x = -0.01 * f64::from(i);
            format!(
                "{{\"world_to_camera\": [{c},0,{s},{x}, 0,1,0,0, {},0,{c},0, 0,0,0,1]}}",
                -s
            )
        })
        .collect();
    format!("[{}]", list.join(","))
}

/// Uploads `frames` at `times` with a JSON list of cameras, 4 context frames; the clip's JSON.
fn upload_with_cameras(server: &Server, frames: &[PathBuf], times: &[f64], cameras: &str) -> Value {
    let form = frames_form(frames, times)
        .text("max_frames", "4")
        .text("cameras", cameras.to_owned());
    json_of(post_upload(server, form))
}

fn pixels(png: &[u8]) -> Vec<u8> {
    image::load_from_memory(png).unwrap().to_rgb8().into_raw()
}

/// Largest difference of two renders, in 8-bit levels.
fn worst(a: &[u8], b: &[u8]) -> u8 {
    a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).max().unwrap()
}

/// Mean difference of two renders, in 8-bit levels.
fn mean(a: &[u8], b: &[u8]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| f64::from(x.abs_diff(*y)))
        .sum::<f64>()
        / a.len() as f64
}

/// "The input camera at time t" renders what the given cameras render at the context times and
/// something between at other times; "bullet time" (an orbit about the input camera at a fixed
/// time) and "the same path at a new time" (the input path swept while time stands) are one
/// request each.
///
/// Tolerance 1 level: a stored camera reaches the renderer through f64 → f32 either directly
/// (the input camera) or through its JSON digits (the stated camera), which may round one ulp
/// apart.
#[test]
fn renders_follow_the_input_camera_path_in_views_bullet_time_and_new_times() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let (frames, times) = synthetic_clip();
    let clip = upload_with_cameras(&server, &frames, &times, &moving_cameras());
    let id = clip["id"].as_str().unwrap().to_owned();
    let stored = clip["cameras"]["frames"].as_array().unwrap().clone();
    let render = |body: Value| {
        let response = Client::new()
            .post(server.at(&format!("/v1/clips/{id}/render")))
            .json(&body)
            .send()
            .unwrap();
        let status = response.status();
        let bytes = response.bytes().unwrap();
        assert_eq!(status, 200, "{body}: {}", String::from_utf8_lossy(&bytes));
        pixels(&bytes)
    };
    let size = |mut body: Value| {
        body["width"] = 48.into();
        body["height"] = 48.into();
        body
    };
    let stated = |k: usize, t: f64| {
        render(size(serde_json::json!({"t": t, "camera": {
            "world_to_camera": stored[k]["world_to_camera"],
            "intrinsics": stored[k]["intrinsics"]}})))
    };
    let input = |input: Value, t: f64| {
        render(size(
            serde_json::json!({"t": t, "camera": {"input": input}}),
        ))
    };
    for (k, camera) in stored.iter().enumerate() {
        let t = camera["t"].as_f64().unwrap();
        let own = input(serde_json::json!({}), t);
        assert!(worst(&own, &stated(k, t)) <= 1, "context camera {k}");
        assert_eq!(own, input(serde_json::json!({"at": t}), t));
    }
    // Between context frames 0 and 1 the input camera is neither.
    let between = input(serde_json::json!({"at": 0.1}), 0.1);
    for k in [0, 1] {
        assert!(mean(&between, &stated(k, 0.1)) > 0.5, "context camera {k}");
    }
    // Past the span's end: the last camera.
    assert_eq!(
        input(serde_json::json!({"at": 9.0}), 0.6),
        input(serde_json::json!({}), 0.6)
    );

    let runtime = tokio::runtime::Runtime::new().unwrap();
    let trajectory = |request: pb::RenderTrajectoryRequest| {
        runtime.block_on(async {
            let mut grpc = C4gClient::connect(server.url()).await.unwrap();
            let mut stream = grpc.render_trajectory(request).await.unwrap().into_inner();
            let mut frames = Vec::new();
            while let Some(frame) = stream.message().await.unwrap() {
                frames.push((frame.time, pixels(&frame.data)));
            }
            frames
        })
    };
    let input_camera = |at: Option<f64>, start: Option<f64>, end: Option<f64>| pb::Camera {
        input: Some(pb::InputCamera { at, start, end }),
        ..Default::default()
    };

    // Bullet time: time stands at 0.2 while the camera orbits the input camera at 0.2; the
    // middle of three frames is that camera itself.
    let bullet = trajectory(pb::RenderTrajectoryRequest {
        clip_id: id.clone(),
        start: Some(0.2),
        end: Some(0.2),
        frames: 3,
        preset_json: r#"{"kind": "orbit", "depth": 2.0, "angle_degrees": 40}"#.into(),
        camera: Some(input_camera(Some(0.2), None, None)),
        width: 48,
        height: 48,
        ..Default::default()
    });
    let at_02 = input(serde_json::json!({"at": 0.2}), 0.2);
    assert!(bullet.iter().all(|(t, _)| *t == 0.2));
    assert_eq!(bullet[1].1, at_02);
    assert!(mean(&bullet[0].1, &at_02) > 0.5 && mean(&bullet[2].1, &at_02) > 0.5);

    // The same path at a new time: the input path from 0 to 0.6 over four frames, time standing
    // at 0.3. Frame k is the input camera at 0.2 k, at time 0.3.
    let sweep = |start, end| pb::RenderTrajectoryRequest {
        clip_id: id.clone(),
        start: Some(start),
        end: Some(end),
        frames: 4,
        camera: Some(input_camera(None, Some(0.0), Some(0.6))),
        width: 48,
        height: 48,
        ..Default::default()
    };
    let frozen = trajectory(sweep(0.3, 0.3));
    let replay = trajectory(sweep(0.0, 0.6));
    assert_eq!(frozen.len(), 4);
    for (k, ((t, image), (t_replay, replayed))) in frozen.iter().zip(&replay).enumerate() {
        // As the server sweeps: start + (end − start) · k / (frames − 1).
        let camera_time = 0.6 * (k as f64 / 3.0);
        assert_eq!(*t, 0.3);
        assert_eq!(image, &input(serde_json::json!({"at": camera_time}), 0.3));
        // Replayed at its own times the input path is the input video's cameras.
        assert!((t_replay - camera_time).abs() < 1e-12);
        assert_eq!(replayed, &input(serde_json::json!({}), *t_replay));
    }
    // Time moved the scene: the frozen frames are not the replay's (but for the one at 0.3's
    // neighbourhood, frames 0 and 3 are far enough).
    assert!(mean(&frozen[0].1, &replay[0].1) > 0.1);
    assert!(mean(&frozen[3].1, &replay[3].1) > 0.1);

    // A sweep is for paths; a stated camera is not also an input camera.
    expect_invalid(
        Client::new()
            .post(server.at(&format!("/v1/clips/{id}/render")))
            .json(&serde_json::json!({"camera": {"input": {"start": 0.0, "end": 0.6}}, "t": 0.1}))
            .send()
            .unwrap(),
        "\"start\" to \"end\"",
    );
    expect_invalid(
        Client::new()
            .post(server.at(&format!("/v1/clips/{id}/render")))
            .json(&serde_json::json!({"camera": {"input": {}, "intrinsics": {"fx": 1, "fy": 1}}}))
            .send()
            .unwrap(),
        "not both",
    );
}

/// gRPC `Upload` carries the same cameras (`UploadHeader.cameras`) and refuses bad ones with
/// INVALID_ARGUMENT naming the problem.
#[test]
fn a_grpc_upload_carries_cameras_and_bad_ones_are_invalid_argument() {
    if !ort_available() {
        return;
    }
    use std::io::Write as _;
    let server = Server::start(&[]);
    let (frames, times) = synthetic_clip();
    let mut writer = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for path in &frames {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        writer
            .start_file(name, zip::write::SimpleFileOptions::default())
            .unwrap();
        writer.write_all(&std::fs::read(path).unwrap()).unwrap();
    }
    let archive = writer.finish().unwrap().into_inner();
    let upload = |cameras: pb::GivenCameras| {
        let header = pb::UploadRequest {
            part: Some(pb::upload_request::Part::Header(pb::UploadHeader {
                kind: pb::MediaKind::Zip as i32,
                timestamps: times.clone(),
                sampling: Some(pb::ClipSampling {
                    max_frames: Some(4),
                    ..Default::default()
                }),
                cameras: Some(cameras),
                ..Default::default()
            })),
        };
        let chunk = pb::UploadRequest {
            part: Some(pb::upload_request::Part::Chunk(archive.clone())),
        };
        tokio::runtime::Runtime::new().unwrap().block_on(async {
            let mut grpc = C4gClient::connect(server.url()).await.unwrap();
            grpc.upload(tokio_stream::iter([header, chunk])).await
        })
    };
    let (cameras_txt, images_txt) = colmap(7);
    let clip = upload(pb::GivenCameras {
        form: Some(pb::given_cameras::Form::Colmap(pb::ColmapText {
            cameras_txt,
            images_txt,
        })),
        names: Vec::new(),
    })
    .unwrap()
    .into_inner();
    let shown = json_of(
        Client::new()
            .get(server.at(&format!("/v1/clips/{}", clip.clip_id)))
            .send()
            .unwrap(),
    );
    assert_eq!(shown["cameras"]["frames"].as_array().unwrap().len(), 4);
    assert_eq!(shown["cameras"]["format"], "colmap");
    // The gRPC clip shows what REST shows.
    let cameras = clip.cameras.unwrap();
    assert_eq!(cameras.scale, shown["cameras"]["scale"].as_f64().unwrap());
    for (frame, rest) in cameras
        .frames
        .iter()
        .zip(shown["cameras"]["frames"].as_array().unwrap())
    {
        assert_eq!(frame.time, rest["t"].as_f64().unwrap());
        let matrix: Vec<f64> = rest["world_to_camera"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(frame.world_to_camera, matrix);
        assert_eq!(frame.fx, rest["intrinsics"]["fx"].as_f64().unwrap());
    }
    let refused = upload(pb::GivenCameras {
        form: Some(pb::given_cameras::Form::Json("[{}]".into())),
        names: Vec::new(),
    })
    .unwrap_err();
    assert_eq!(refused.code(), tonic::Code::InvalidArgument);
    assert!(
        refused
            .message()
            .contains("exactly one of world_to_camera and camera_to_world"),
        "{refused:?}"
    );
}

/// A pose relative to the first context camera's, in the model's frame, with the translation
/// divided by `scale` (row-major 4×4 both ways).
fn in_model_frame(pose: &[f64], first: &[f64], scale: f64) -> Vec<f64> {
    let r = |m: &[f64], a: usize, b: usize| m[a * 4 + b];
    let mut out = vec![0.0; 16];
    for a in 0..3 {
        for b in 0..3 {
            out[a * 4 + b] = (0..3).map(|k| r(pose, a, k) * r(first, b, k)).sum();
        }
    }
    for a in 0..3 {
        let turned: f64 = (0..3).map(|k| out[a * 4 + k] * first[k * 4 + 3]).sum();
        out[a * 4 + 3] = (pose[a * 4 + 3] - turned) / scale;
    }
    out[15] = 1.0;
    out
}

/// Given cameras that move are fitted to the model's depth scale at upload (`docs/api.md`,
/// "Given cameras"): the evaluation fixtures (11 frames, 4 context frames, cameras known) keep
/// their convention's scale in `scale_fit`, the fit lowers the error of the model's renders of
/// its context frames, and renders at the held-out frames' true cameras at the fitted scale match
/// those frames better than at the convention's, clip by clip. (The fixtures' clips never
/// trained on; c4g-tiny puts every scene at about one depth, so the convention's scale is off by
/// a factor of 2 to 30 on them: `models/c4g-tiny/README.md`.)
#[test]
fn given_cameras_are_fitted_to_the_model_depth_scale_and_held_out_views_match_better() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let fixtures = c4g_e2e::workspace().join("models/fixtures/eval");
    for name in ["eval-1", "eval-3", "world1-2000015"] {
        let dir = fixtures.join(name);
        let frames: Vec<_> = (0..11)
            .map(|i| dir.join(format!("frames/{i:02}.png")))
            .collect();
        let times: Vec<f64> = (0..11).map(|i| f64::from(i) / 10.0).collect();
        let cameras: Value =
            serde_json::from_slice(&std::fs::read(dir.join("cameras.json")).unwrap()).unwrap();
        let clip = upload_with_cameras(&server, &frames, &times, &cameras.to_string());
        let stored = &clip["cameras"];
        let fit = &stored["scale_fit"];
        let number = |v: &Value| v.as_f64().unwrap();
        let (factor, convention) = (number(&fit["factor"]), number(&fit["convention_scale"]));
        assert!(
            number(&fit["error"]) < number(&fit["initial_error"]),
            "{name}: {fit}"
        );
        assert!((number(&stored["scale"]) * factor - convention).abs() < 1e-9 * convention);
        let context: Vec<usize> = clip["context_times"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| (number(t) * 10.0).round() as usize)
            .collect();
        let pose = |i: usize| -> Vec<f64> {
            cameras[i]["world_to_camera"]
                .as_array()
                .unwrap()
                .iter()
                .map(number)
                .collect()
        };
        let first = pose(context[0]);
        // The stored cameras are the convention's, translations times the factor.
        for (k, &i) in context.iter().enumerate() {
            let want = in_model_frame(&pose(i), &first, convention / factor);
            for (got, want) in stored["frames"][k]["world_to_camera"]
                .as_array()
                .unwrap()
                .iter()
                .zip(&want)
            {
                assert!((number(got) - want).abs() < 1e-9, "{name} frame {i}");
            }
        }
        let id = clip["id"].as_str().unwrap();
        let held_out: Vec<usize> = (context[0]..=context[3])
            .filter(|i| !context.contains(i))
            .collect();
        let score = |scale: f64| -> f64 {
            held_out
                .iter()
                .map(|&i| {
                    let camera = serde_json::json!({
                        "world_to_camera": in_model_frame(&pose(i), &first, scale),
                        "intrinsics": cameras[i]["intrinsics"],
                    });
                    let response = Client::new()
                        .post(server.at(&format!("/v1/clips/{id}/render")))
                        .json(&serde_json::json!({"t": times[i], "camera": camera}))
                        .send()
                        .unwrap();
                    assert_eq!(response.status(), 200);
                    let image = pixels(&response.bytes().unwrap());
                    let truth = image::open(&frames[i]).unwrap().to_rgb8().into_raw();
                    let mse = image
                        .iter()
                        .zip(&truth)
                        .map(|(a, b)| (f64::from(*a) - f64::from(*b)).powi(2))
                        .sum::<f64>()
                        / truth.len() as f64;
                    10.0 * (255.0_f64.powi(2) / mse).log10()
                })
                .sum::<f64>()
                / held_out.len() as f64
        };
        let (fitted, unfitted) = (score(convention / factor), score(convention));
        eprintln!("{name}: factor {factor:.3}, held-out PSNR {unfitted:.2} -> {fitted:.2} dB");
        assert!(fitted > unfitted, "{name}: {unfitted:.2} -> {fitted:.2} dB");
    }
}

/// Cameras go out as they came in: the clip's cameras as the JSON list, COLMAP's text model and
/// transforms.json read back, with the upload's own readers, as the stored cameras (1e-9: full
/// precision in every file); a clip without cameras is 404 and an unknown format 400.
#[test]
fn a_clips_cameras_go_out_in_every_form_and_read_back_as_stored() {
    use c4g_service::clips::intake::cameras::CameraInput;
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let (cameras, images) = colmap(7);
    let clip = json_of(upload(&server, &cameras, &images));
    let id = clip["id"].as_str().unwrap().to_owned();
    let stored: Vec<Vec<f64>> = clip["cameras"]["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            let k = &f["intrinsics"];
            let mut v: Vec<f64> = f["world_to_camera"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            v.extend(["fx", "fy", "cx", "cy"].map(|n| k[n].as_f64().unwrap()));
            v
        })
        .collect();
    let names: Vec<String> = (0..stored.len()).map(|k| format!("{k:03}.png")).collect();
    let get = |format: &str| {
        Client::new()
            .get(server.at(&format!("/v1/clips/{id}/cameras?format={format}")))
            .send()
            .unwrap()
    };
    for format in ["json", "colmap", "transforms"] {
        let response = get(format);
        assert_eq!(response.status(), 200, "{format}");
        let bytes = response.bytes().unwrap();
        let input = match format {
            "json" => CameraInput::Json(String::from_utf8(bytes.to_vec()).unwrap()),
            "transforms" => CameraInput::Transforms {
                json: String::from_utf8(bytes.to_vec()).unwrap(),
                names: Some(names.clone()),
            },
            _ => {
                let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes.to_vec())).unwrap();
                let mut read = |name: &str| {
                    let mut text = String::new();
                    std::io::Read::read_to_string(&mut zip.by_name(name).unwrap(), &mut text)
                        .unwrap();
                    text
                };
                assert_eq!(read("points3D.txt"), "");
                CameraInput::Colmap {
                    cameras: read("cameras.txt"),
                    images: read("images.txt"),
                    names: Some(names.clone()),
                }
            }
        };
        let parsed = input.parse().unwrap();
        assert_eq!(parsed.cameras.len(), stored.len(), "{format}");
        for (given, want) in parsed.cameras.iter().zip(&stored) {
            let i = given.intrinsics;
            let mut got = given.world_to_camera_rows();
            got.extend([i.fx, i.fy, i.cx, i.cy]);
            let worst = got
                .iter()
                .zip(want)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(worst < 1e-9, "{format}: {worst}");
        }
    }
    expect_error(
        get("ply"),
        400,
        "invalid_input",
        "json, colmap or transforms",
    );
    let plain = upload_synthetic(&server);
    let none = Client::new()
        .get(server.at(&format!("/v1/clips/{plain}/cameras")))
        .send()
        .unwrap();
    expect_error(none, 404, "not_found", "cameras/recover");
}
