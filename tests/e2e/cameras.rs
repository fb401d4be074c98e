//! Given cameras through the running service: an upload over REST carries per-frame cameras
//! (COLMAP text as multipart fields), the clip stores its context frames' cameras in the model's
//! frame and `GET /v1/clips/{id}` shows them; other cameras make another clip; a camera count
//! that does not match the frames, or a bad camera file, is a 400 that says what is wrong.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_e2e::{Server, expect_invalid, frames_form, json_of, ort_available, synthetic_clip};
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
    assert!((stored["scale"].as_f64().unwrap() - scale).abs() < 1e-9);
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
            let translation = (ti[a] - (0..3).map(|k| rel[a][k] * t0[k]).sum::<f64>()) / scale;
            // 1e-9: the same arithmetic in another order (and a quaternion round trip) on
            // numbers of size 50.
            assert!(
                (m[a * 4 + 3] - translation).abs() < 1e-9,
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
