//! The 4D feature field through the running service, on `models/fixtures/feature-stream` (random
//! weights, 28 x 28 input, 32 Gaussians, a feature decoder lifting its encoder's features):
//! decodes with features agree across JSON, `C4GS` version 2 and `.ply`, and with the engine's
//! own decode of the same frames; keyframed decodes interpolate them linearly; feature images
//! composite the per-Gaussian features by the rasterizer's weights; the PCA colouring is the one
//! basis fitted on the context times' features, at every time; a click's segment holds the
//! clicked pixel's main Gaussian and its mask covers the pixel; the feature tracker answers over
//! REST and gRPC alike; a package without a feature decoder refuses each of them with 422
//! `unsupported` (gRPC `INVALID_ARGUMENT`, kind `unsupported`), and so does one whose feature
//! decoder lifts object ids (`models/c4g-tiny-objects`), which need masks no upload carries.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_analysis::features::FeaturePca;
use c4g_e2e::{Server, binary, json_of, ort_available, post_json, upload_synthetic, workspace};
use c4g_engine::{ContextFrame, Engine, EngineOptions};
use c4g_formats::{c4gs, ply};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use c4g_renderer::{CpuRasterizer, RenderOptions};
use c4g_scene::Footprint;
use c4g_scene::{Camera, FeatureBlock, GaussianSet, NormalizedIntrinsics};
use serde_json::{Value, json};

const MODEL: &str = "models/fixtures/feature-stream";
/// The fixture's input size and feature width.
const SIDE: u32 = 28;
const WIDTH: usize = 32;

fn feature_server() -> Server {
    Server::start(&["--model", MODEL])
}

/// The sets of a JSON decode with features, as the renderer's sets.
fn sets_of(answer: &Value) -> Vec<(f64, GaussianSet)> {
    answer["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|frame| {
            let rows = |key: &str| -> Vec<Vec<f32>> {
                frame[key]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|row| match row {
                        Value::Array(values) => {
                            values.iter().map(|v| v.as_f64().unwrap() as f32).collect()
                        }
                        v => vec![v.as_f64().unwrap() as f32],
                    })
                    .collect()
            };
            let arr = |r: &Vec<f32>, k: usize| -> Vec<f32> { r[..k].to_vec() };
            let means: Vec<[f32; 3]> = rows("means")
                .iter()
                .map(|r| arr(r, 3).try_into().unwrap())
                .collect();
            let scales: Vec<[f32; 3]> = rows("scales")
                .iter()
                .map(|r| arr(r, 3).try_into().unwrap())
                .collect();
            let rotations: Vec<[f32; 4]> = rows("rotations")
                .iter()
                .map(|r| arr(r, 4).try_into().unwrap())
                .collect();
            let opacities: Vec<f32> = rows("opacities").iter().map(|r| r[0]).collect();
            let colors: Vec<[f32; 3]> = rows("colors")
                .iter()
                .map(|r| arr(r, 3).try_into().unwrap())
                .collect();
            let features: Vec<f32> = rows("features").into_iter().flatten().collect();
            let set = GaussianSet::new(means, scales, rotations, opacities, colors)
                .unwrap()
                .with_features(FeatureBlock::new(WIDTH, features).unwrap())
                .unwrap();
            (frame["t"].as_f64().unwrap(), set)
        })
        .collect()
}

fn bytes_of(response: reqwest::blocking::Response) -> (reqwest::header::HeaderMap, Vec<u8>) {
    assert!(response.status().is_success(), "{:?}", response.status());
    let headers = response.headers().clone();
    (headers, response.bytes().unwrap().to_vec())
}

fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

/// The input camera of a clip without cameras: the identity with C4G's intrinsics.
fn input_camera() -> Camera {
    Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        SIDE,
        SIDE,
        glam::Affine3A::IDENTITY,
    )
    .unwrap()
}

fn options() -> RenderOptions {
    // The fixture declares the 3DGS footprint; the server renders with the package's.
    RenderOptions {
        footprint: Footprint::Tiles3dgs,
        ..RenderOptions::default()
    }
}

fn decode(server: &Server, id: &str, body: Value) -> Value {
    json_of(post_json(
        server,
        &format!("/v1/clips/{id}/gaussians"),
        &body,
    ))
}

#[test]
fn decoded_features_agree_across_formats_and_with_the_engine() {
    if !ort_available() {
        return;
    }
    let server = feature_server();
    let id = upload_synthetic(&server);
    let times = [0.1, 0.3];
    let answer = decode(&server, &id, json!({"times": times, "features": true}));
    let from_json = sets_of(&answer);
    assert_eq!(from_json.len(), 2);
    for (_, set) in &from_json {
        assert_eq!(set.len(), 32);
        assert_eq!(set.features().unwrap().width(), WIDTH);
    }
    // A decode without features has none, as before.
    let plain = decode(&server, &id, json!({"times": times}));
    assert!(plain["frames"][0].get("features").is_none());

    let (headers, binary) = bytes_of(post_json(
        &server,
        &format!("/v1/clips/{id}/gaussians"),
        &json!({"times": times, "features": true, "format": "binary"}),
    ));
    assert_eq!(headers["content-type"], "application/x-c4g-gaussians");
    assert_eq!(
        u16::from_le_bytes([binary[4], binary[5]]),
        2,
        "features make C4GS version 2"
    );
    let from_binary = c4gs::decode(&binary).unwrap();
    for ((tj, a), (tb, b)) in from_json.iter().zip(&from_binary) {
        assert_eq!(tj, tb);
        // JSON writes each f32 in its shortest round-tripping form: the very same floats.
        assert_eq!(a.features(), b.features());
        assert_eq!(a.positions(), b.positions());
    }
    let (_, ply_bytes) = bytes_of(post_json(
        &server,
        &format!("/v1/clips/{id}/gaussians"),
        &json!({"t": 0.1, "features": true, "format": "ply"}),
    ));
    let header = String::from_utf8_lossy(&ply_bytes[..ply_bytes.len().min(2000)]).to_string();
    assert!(header.contains("property float feat_31"), "{header}");
    assert_eq!(
        ply::decode(&ply_bytes).unwrap().features(),
        from_json[0].1.features()
    );
    let splat = post_json(
        &server,
        &format!("/v1/clips/{id}/gaussians"),
        &json!({"t": 0.1, "features": true, "format": "splat"}),
    );
    assert_eq!(splat.status(), 400);

    // The engine's own decode of the same context frames (as the server stored them).
    let engine = Engine::load(workspace().join(MODEL), EngineOptions::default()).unwrap();
    let clip = json_of(
        reqwest::blocking::Client::new()
            .get(server.at(&format!("/v1/clips/{id}")))
            .send()
            .unwrap(),
    );
    let context: Vec<f64> = clip["context_times"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_f64().unwrap())
        .collect();
    let frames: Vec<ContextFrame> = context
        .iter()
        .enumerate()
        .map(|(k, &t)| {
            let png = reqwest::blocking::get(server.at(&format!("/v1/clips/{id}/frames/{k}")))
                .unwrap()
                .bytes()
                .unwrap();
            let image = image::load_from_memory(&png).unwrap().to_rgb8();
            ContextFrame::new(t, engine.preprocess(&image).unwrap())
        })
        .collect();
    // The synthetic clip's source frames are 0.1 s apart: the frame step the fixture's
    // `frame-step` time policy normalises by (measured at intake, not shown by GET).
    let encoding = engine
        .encode(&frames)
        .unwrap()
        .with_frame_step(Some(0.1))
        .unwrap();
    // An encoder-kind package lifts the encoding's own features (frames given in time order).
    let sets = engine
        .decode_features(&encoding, encoding.features(), &times)
        .unwrap();
    for (own, (_, served)) in sets.iter().zip(&from_json) {
        let (a, b) = (
            own.features().unwrap().values(),
            served.features().unwrap().values(),
        );
        let scale = a.iter().fold(1.0f32, |m, v| m.max(v.abs()));
        for (x, y) in a.iter().zip(b) {
            // Float rounding: the server's runs may batch and thread differently.
            assert!((x - y).abs() <= 1e-4 * scale, "{x} vs {y}");
        }
    }

    // Keyframed decodes interpolate features linearly between exact keyframes.
    let keyed = sets_of(&decode(
        &server,
        &id,
        json!({"times": [0.0, 0.1, 0.2], "keyframes": {"count": 2}, "features": true}),
    ));
    let exact = sets_of(&decode(
        &server,
        &id,
        json!({"times": [0.0, 0.2], "features": true}),
    ));
    let (a, b) = (
        exact[0].1.features().unwrap(),
        exact[1].1.features().unwrap(),
    );
    for (k, v) in keyed[1].1.features().unwrap().values().iter().enumerate() {
        let expected = 0.5 * (a.values()[k] + b.values()[k]);
        assert!((v - expected).abs() < 1e-5, "{v} vs {expected}");
    }

    // gRPC answers the same features, packed like the columns.
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let grpc = runtime.block_on(async {
        let mut client = C4gClient::connect(server.url()).await.unwrap();
        client
            .decode(pb::DecodeRequest {
                clip_id: id.clone(),
                times: times.to_vec(),
                features: true,
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner()
    });
    let set = grpc.frames[0].gaussians.as_ref().unwrap();
    assert_eq!(set.feature_width as usize, WIDTH);
    assert_eq!(
        floats(&set.features),
        from_json[0].1.features().unwrap().values()
    );
}

#[test]
fn feature_images_composite_features_and_the_colouring_is_one_basis_per_clip() {
    if !ort_available() {
        return;
    }
    let server = feature_server();
    let id = upload_synthetic(&server);
    let render =
        |body: Value| bytes_of(post_json(&server, &format!("/v1/clips/{id}/render"), &body));
    let t = 0.1;
    let (headers, raw) = render(json!({"t": t, "format": "features"}));
    assert_eq!(headers["x-c4g-channels"], WIDTH.to_string().as_str());
    assert_eq!(headers["x-c4g-width"], SIDE.to_string().as_str());
    let raw = floats(&raw);
    assert_eq!(raw.len(), (SIDE * SIDE) as usize * WIDTH);
    let (_, alpha) = render(json!({"t": t, "format": "alpha"}));
    let alpha = floats(&alpha);

    // One pixel against the rasterizer's weights: Σ wᵢ fᵢ.
    let set = sets_of(&decode(&server, &id, json!({"t": t, "features": true})))
        .remove(0)
        .1;
    let p = (0..alpha.len())
        .max_by(|&a, &b| alpha[a].total_cmp(&alpha[b]))
        .unwrap();
    assert!(alpha[p] > 0.05, "the clip shows something");
    let pixel = ((p as u32) % SIDE, (p as u32) / SIDE);
    let weights = CpuRasterizer::new()
        .pixel_weights(&set, &input_camera(), &options(), &[pixel])
        .unwrap()
        .remove(0);
    let block = set.features().unwrap();
    for c in 0..WIDTH {
        let expected: f32 = weights
            .iter()
            .map(|w| w.weight * block.row(w.index as usize).unwrap()[c])
            .sum();
        let got = raw[p * WIDTH + c];
        assert!(
            (got - expected).abs() < 1e-4 * (1.0 + expected.abs()),
            "{c}: {got} vs {expected}"
        );
    }

    // The colouring's basis is fitted on the Gaussians' features at the context times, once: the
    // PNG at two times (neither a context time) is that basis's colour of each pixel's feature.
    let clip = json_of(
        reqwest::blocking::Client::new()
            .get(server.at(&format!("/v1/clips/{id}")))
            .send()
            .unwrap(),
    );
    let context = clip["context_times"].clone();
    let samples: Vec<f32> = sets_of(&decode(
        &server,
        &id,
        json!({"times": context, "features": true}),
    ))
    .iter()
    .flat_map(|(_, s)| s.features().unwrap().values().to_vec())
    .collect();
    let basis = FeaturePca::fit(&samples, WIDTH).unwrap();
    for t in [0.1, 0.5] {
        let (headers, png) = render(json!({"t": t, "format": "features_pca"}));
        assert_eq!(headers["content-type"], "image/png");
        let coloured = image::load_from_memory(&png).unwrap().to_rgb8();
        let (_, raw) = render(json!({"t": t, "format": "features"}));
        let raw = floats(&raw);
        let (_, alpha) = render(json!({"t": t, "format": "alpha"}));
        let alpha = floats(&alpha);
        let mut compared = 0;
        for (p, &a) in alpha.iter().enumerate() {
            if a < 0.05 {
                continue;
            }
            let mean: Vec<f32> = raw[p * WIDTH..(p + 1) * WIDTH]
                .iter()
                .map(|v| v / a)
                .collect();
            let colour = basis.colour(&mean);
            let got = coloured.get_pixel(p as u32 % SIDE, p as u32 / SIDE).0;
            for k in 0..3 {
                let expected = (a * colour[k] * 255.0).round();
                assert!(
                    (f32::from(got[k]) - expected).abs() <= 1.0,
                    "t = {t}, pixel {p}, channel {k}: {} vs {expected}",
                    got[k]
                );
            }
            compared += 1;
        }
        assert!(compared > 10, "only {compared} pixels show anything at {t}");
        // A colour means a feature: one Gaussian's feature has one colour, whatever the time.
        assert_eq!(
            basis.colour(block.row(0).unwrap()),
            basis.colour(block.row(0).unwrap())
        );
    }
    // Feature images are single views.
    let refused = post_json(
        &server,
        &format!("/v1/clips/{id}/render"),
        &json!({"format": "features", "trajectory": {"kind": "dolly", "distance": 0.5}, "frames": 2}),
    );
    assert_eq!(refused.status(), 400);
}

#[test]
fn a_click_segments_its_gaussians_and_the_feature_tracker_answers_on_both_transports() {
    if !ort_available() {
        return;
    }
    let server = feature_server();
    let id = upload_synthetic(&server);
    let t = 0.2;
    let set = sets_of(&decode(&server, &id, json!({"t": t, "features": true})))
        .remove(0)
        .1;
    // A pixel one Gaussian dominates: its feature is (nearly) that Gaussian's.
    let pixels: Vec<(u32, u32)> = (0..SIDE)
        .flat_map(|y| (0..SIDE).map(move |x| (x, y)))
        .collect();
    let weights = CpuRasterizer::new()
        .pixel_weights(&set, &input_camera(), &options(), &pixels)
        .unwrap();
    let (pixel, main) = pixels
        .iter()
        .zip(&weights)
        .filter_map(|(&p, w)| {
            let alpha: f32 = w.iter().map(|w| w.weight).sum();
            let top = w.iter().max_by(|a, b| a.weight.total_cmp(&b.weight))?;
            (top.weight >= 0.5 && top.weight >= 0.9 * alpha).then_some((p, top.weight, top.index))
        })
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(p, _, i)| (p, i))
        .expect("some pixel is mostly one Gaussian");
    let (x, y) = (pixel.0 as f32 + 0.5, pixel.1 as f32 + 0.5);
    let body = json!({"click": {"t": t, "x": x, "y": y}, "threshold": 0.9, "times": [t, 0.4]});
    let segment = json_of(post_json(
        &server,
        &format!("/v1/clips/{id}/segment"),
        &body,
    ));
    let selected: Vec<u64> = segment["gaussians"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .collect();
    assert!(selected.contains(&u64::from(main)), "{segment}");
    assert_eq!(segment["t"], t);
    let masks = segment["masks"].as_array().unwrap();
    assert_eq!(masks.len(), 2);
    // The mask at the click's time covers the clicked pixel.
    let mut set_pixels = Vec::new();
    for (k, run) in masks[0]["counts"].as_array().unwrap().iter().enumerate() {
        set_pixels.extend(std::iter::repeat_n(
            k % 2 == 1,
            run.as_u64().unwrap() as usize,
        ));
    }
    assert_eq!(set_pixels.len(), (SIDE * SIDE) as usize);
    assert!(set_pixels[(pixel.1 * SIDE + pixel.0) as usize], "{segment}");
    assert_eq!(
        set_pixels.iter().filter(|s| **s).count() as u64,
        masks[0]["area"].as_u64().unwrap()
    );
    // The same feature, given, selects the same Gaussians.
    let by_feature = json_of(post_json(
        &server,
        &format!("/v1/clips/{id}/segment"),
        &json!({"feature": segment["feature"], "t": t, "threshold": 0.9, "times": [t]}),
    ));
    assert_eq!(by_feature["gaussians"], segment["gaussians"]);
    for bad in [
        json!({"click": {"t": t, "x": 28.0, "y": 1.0}}),
        json!({"feature": [1.0, 2.0]}),
        json!({"click": {"t": t, "x": x, "y": y}, "threshold": 1.5}),
        json!({"times": [t]}),
    ] {
        let refused = post_json(&server, &format!("/v1/clips/{id}/segment"), &bad);
        assert_eq!(refused.status(), 400, "{bad}");
    }
    let cli = std::process::Command::new(binary("c4g"))
        .args([
            "--server",
            &server.url(),
            "--json",
            "segment",
            &id,
            "--at",
            "0.2",
        ])
        .args([
            "--point",
            &format!("{x},{y}"),
            "--threshold",
            "0.9",
            "--t",
            "0.2",
        ])
        .output()
        .unwrap();
    assert!(
        cli.status.success(),
        "{}",
        String::from_utf8_lossy(&cli.stderr)
    );
    let from_cli: Value = serde_json::from_slice(&cli.stdout).unwrap();
    assert_eq!(from_cli["gaussians"], segment["gaussians"]);

    // The feature tracker: the point starts in its own pixel, and gRPC answers the same.
    let queries = json!([{"t": t, "x": x, "y": y}]);
    let times = [0.0, 0.2, 0.4];
    let rest = json_of(post_json(
        &server,
        &format!("/v1/clips/{id}/tracks"),
        &json!({"queries": queries, "times": times, "tracker": "features"}),
    ));
    assert_eq!(rest["tracker"], "features");
    let track = &rest["tracks"][0];
    assert_eq!(track["anchored"], true);
    let points = track["points"].as_array().unwrap();
    assert_eq!(points.len(), 3);
    let own = &points[1];
    assert!(
        (own["x"].as_f64().unwrap() - f64::from(x)).abs() <= 1.0,
        "{own}"
    );
    assert!(
        (own["y"].as_f64().unwrap() - f64::from(y)).abs() <= 1.0,
        "{own}"
    );
    assert!(own["similarity"].as_f64().unwrap() > 0.999, "{own}");
    let default = json_of(post_json(
        &server,
        &format!("/v1/clips/{id}/tracks"),
        &json!({"queries": queries, "times": times}),
    ));
    assert_eq!(default["tracker"], "gaussians");
    assert!(
        default["tracks"][0]["points"][0]
            .get("similarity")
            .is_none()
    );
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let grpc = runtime.block_on(async {
        let mut client = C4gClient::connect(server.url()).await.unwrap();
        client
            .tracks(pb::TracksRequest {
                clip_id: id.clone(),
                queries: vec![pb::TrackQuery { time: t, x, y }],
                times: times.to_vec(),
                tracker: pb::Tracker::Features as i32,
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner()
    });
    assert_eq!(grpc.tracker, pb::Tracker::Features as i32);
    for (g, r) in grpc.tracks[0].points.iter().zip(points) {
        assert!(
            (f64::from(g.x) - r["x"].as_f64().unwrap()).abs() < 1e-3,
            "{g:?} vs {r}"
        );
        assert!(
            (f64::from(g.y) - r["y"].as_f64().unwrap()).abs() < 1e-3,
            "{g:?} vs {r}"
        );
        assert_eq!(g.visible, r["visible"].as_bool().unwrap());
        assert!(g.similarity.is_some());
    }
    let grpc_segment = runtime.block_on(async {
        let mut client = C4gClient::connect(server.url()).await.unwrap();
        client
            .segment(pb::SegmentRequest {
                clip_id: id.clone(),
                selection: Some(pb::segment_request::Selection::Click(pb::SegmentClick {
                    time: t,
                    x,
                    y,
                })),
                threshold: Some(0.9),
                times: vec![t, 0.4],
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner()
    });
    let rest_gaussians: Vec<u32> = selected.iter().map(|&i| i as u32).collect();
    assert_eq!(grpc_segment.gaussians, rest_gaussians);
    assert_eq!(grpc_segment.masks.len(), 2);
}

/// A copy of the plain decoder-forms fixture with its feature decoder taken out, in `dir`.
fn package_without_feature_decoder(dir: &std::path::Path) -> String {
    let source = workspace().join("models/fixtures/decoder-forms/plain");
    for file in ["encoder.onnx", "decoder.onnx"] {
        std::fs::copy(source.join(file), dir.join(file)).unwrap();
    }
    let mut manifest: Value =
        serde_json::from_slice(&std::fs::read(source.join("model.json")).unwrap()).unwrap();
    manifest["files"]
        .as_object_mut()
        .unwrap()
        .remove("feature_decoder");
    manifest.as_object_mut().unwrap().remove("feature_decoder");
    std::fs::write(dir.join("model.json"), manifest.to_string()).unwrap();
    dir.to_str().unwrap().to_owned()
}

#[test]
fn a_package_without_a_feature_decoder_refuses_each_feature_request() {
    if !ort_available() {
        return;
    }
    let package = tempfile::tempdir().unwrap();
    let server = Server::start(&["--model", &package_without_feature_decoder(package.path())]);
    let id = upload_synthetic(&server);
    let refusals = [
        ("gaussians", json!({"t": 0.1, "features": true})),
        ("render", json!({"t": 0.1, "format": "features"})),
        ("render", json!({"t": 0.1, "format": "features_pca"})),
        (
            "segment",
            json!({"click": {"t": 0.1, "x": 10.0, "y": 10.0}}),
        ),
        (
            "tracks",
            json!({"queries": [{"t": 0.1, "x": 10.0, "y": 10.0}], "tracker": "features"}),
        ),
    ];
    for (route, body) in refusals {
        let response = post_json(&server, &format!("/v1/clips/{id}/{route}"), &body);
        assert_eq!(response.status(), 422, "{route} {body}");
        let error: Value = response.json().unwrap();
        assert_eq!(error["kind"], "unsupported", "{error}");
        assert!(
            error["error"]
                .as_str()
                .unwrap()
                .contains("no feature decoder"),
            "{error}"
        );
    }
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut client = C4gClient::connect(server.url()).await.unwrap();
        let decode = client
            .decode(pb::DecodeRequest {
                clip_id: id.clone(),
                times: vec![0.1],
                features: true,
                ..Default::default()
            })
            .await
            .unwrap_err();
        let segment = client
            .segment(pb::SegmentRequest {
                clip_id: id.clone(),
                selection: Some(pb::segment_request::Selection::Feature(
                    pb::FeatureSelection {
                        feature: vec![1.0; 8],
                        time: None,
                    },
                )),
                ..Default::default()
            })
            .await
            .unwrap_err();
        let tracks = client
            .tracks(pb::TracksRequest {
                clip_id: id.clone(),
                queries: vec![pb::TrackQuery {
                    time: 0.1,
                    x: 3.0,
                    y: 3.0,
                }],
                tracker: pb::Tracker::Features as i32,
                ..Default::default()
            })
            .await
            .unwrap_err();
        let render = client
            .render(pb::RenderRequest {
                clip_id: id.clone(),
                time: 0.1,
                format: pb::ImageFormat::FeaturesPcaPng as i32,
                ..Default::default()
            })
            .await
            .unwrap_err();
        for status in [decode, segment, tracks, render] {
            assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
            assert_eq!(
                status.metadata().get("c4g-error-kind").unwrap(),
                "unsupported"
            );
        }
    });
}

#[test]
fn a_package_that_lifts_object_ids_refuses_feature_requests_and_says_why() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&["--model", "models/c4g-tiny-objects"]);
    let id = upload_synthetic(&server);
    let response = post_json(
        &server,
        &format!("/v1/clips/{id}/render"),
        &json!({"t": 0.1, "format": "features_pca"}),
    );
    assert_eq!(response.status(), 422);
    let error: Value = response.json().unwrap();
    assert_eq!(error["kind"], "unsupported", "{error}");
    assert!(
        error["error"].as_str().unwrap().contains("object-id"),
        "{error}"
    );
    // Its Gaussians are served as any package's.
    let decode = post_json(
        &server,
        &format!("/v1/clips/{id}/gaussians"),
        &json!({"t": 0.1}),
    );
    assert_eq!(decode.status(), 200);
}
