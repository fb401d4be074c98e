//! Keyframed decoding through the running service: REST decodes and gRPC streams with a
//! `keyframes` option return sets close to the exact ones, trajectories render from keyframes,
//! the metrics count both kinds of set, and a bad option is a 400 (INVALID_ARGUMENT) that says
//! what to change.
//!
//! The tolerance is the one the requests ask for: the adaptive mode holds the largest position
//! error at every interval's checks to it, and on this model (c4g-tiny, this very clip) the error
//! at the times it never checked measured under 40% of it (`docs/benchmarks.md`); 1e-5 more
//! covers the rounding of two decoder runs of different batches.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_e2e::{
    Server, expect_invalid, frames_form, json_of, metric, ort_available, synthetic_clip,
};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use reqwest::blocking::Client;
use serde_json::{Value, json};

/// Position tolerance the keyframed requests ask for, scene units.
const TOLERANCE: f64 = 0.005;
/// Two decoder runs of one time in different batches: float rounding only.
const RUN_TO_RUN: f64 = 1e-5;

/// Every frame's means from a JSON decode.
fn means(decoded: &Value) -> Vec<Vec<[f64; 3]>> {
    decoded["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|frame| {
            frame["means"]
                .as_array()
                .unwrap()
                .iter()
                .map(|m| std::array::from_fn(|k| m[k].as_f64().unwrap()))
                .collect()
        })
        .collect()
}

/// The means of a gRPC set in f32.
fn proto_means(set: &pb::GaussianSet) -> Vec<[f64; 3]> {
    let values: Vec<f64> = set
        .means
        .chunks_exact(4)
        .map(|b| f64::from(f32::from_le_bytes(b.try_into().unwrap())))
        .collect();
    values.chunks_exact(3).map(|m| [m[0], m[1], m[2]]).collect()
}

/// Largest distance between paired means of one frame.
fn largest_distance(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>().sqrt())
        .fold(0.0, f64::max)
}

#[test]
fn keyframed_decodes_and_streams_stay_close_to_exact_and_bad_options_are_400() {
    if !ort_available() {
        return;
    }
    let (frames, times) = synthetic_clip();
    let server = Server::start(&[]);
    let client = Client::new();
    let clip = json_of(
        client
            .post(server.at("/v1/clips"))
            .multipart(frames_form(&frames, &times).text("max_frames", "4"))
            .send()
            .unwrap(),
    );
    let id = clip["id"].as_str().unwrap().to_owned();
    let url = server.at(&format!("/v1/clips/{id}/gaussians"));
    // 33 times over the span [0, 0.6].
    let targets: Vec<f64> = (0..33).map(|i| 0.6 * f64::from(i) / 32.0).collect();

    // REST: adaptive keyframes within the tolerance of the exact sets, at every time.
    let exact = means(&json_of(
        client
            .post(&url)
            .json(&json!({"times": targets}))
            .send()
            .unwrap(),
    ));
    let keyframed = means(&json_of(
        client
            .post(&url)
            .json(&json!({"times": targets, "keyframes": {"tolerance": TOLERANCE}}))
            .send()
            .unwrap(),
    ));
    assert_eq!(keyframed.len(), targets.len());
    let mut worst = 0.0f64;
    for (k, (a, b)) in exact.iter().zip(&keyframed).enumerate() {
        let d = largest_distance(a, b);
        assert!(d <= TOLERANCE + RUN_TO_RUN, "t = {}: {d}", targets[k]);
        worst = worst.max(d);
    }
    // The ends of the range are keyframes: exact sets.
    assert!(largest_distance(&exact[0], &keyframed[0]) <= RUN_TO_RUN);
    assert!(largest_distance(&exact[32], &keyframed[32]) <= RUN_TO_RUN);
    let metrics = client
        .get(server.at("/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    let exact_sets = metric(&metrics, "c4g_decoded_sets_total{how=\"exact\"}");
    let interpolated = metric(&metrics, "c4g_decoded_sets_total{how=\"interpolated\"}");
    eprintln!(
        "REST, 33 times: {} exact decodes, {interpolated} interpolated, largest position error {worst:.2e}",
        exact_sets - 33.0
    );
    assert!(interpolated > 0.0, "{metrics}");
    // 33 for the exact request, fewer than 33 for the keyframed one.
    assert!(exact_sets < 66.0, "{metrics}");

    // Bad options: 400 with what to change.
    let bad = |body: Value| client.post(&url).json(&body).send().unwrap();
    expect_invalid(
        bad(json!({"times": [0.1, 0.2], "keyframes": {"count": 1}})),
        "between 2",
    );
    expect_invalid(bad(json!({"t": 0.1, "keyframes": {}})), "needs one of");
    expect_invalid(
        bad(json!({"t": 0.1, "keyframes": {"count": 4, "tolerance": 0.1}})),
        "not several",
    );
    expect_invalid(
        bad(json!({"t": 0.1, "keyframes": {"tolerance": 0.1, "max": 100000}})),
        "C4G_MAX_TIMES",
    );
    expect_invalid(bad(json!({"t": 0.1, "keyframes": {"every": 1}})), "every");
    expect_invalid(
        client
            .post(server.at(&format!("/v1/clips/{id}/render")))
            .json(&json!({"t": 0.1, "keyframes": {"count": 2}}))
            .send()
            .unwrap(),
        "trajectory",
    );

    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let stream = |keyframes: Option<pb::Keyframes>| pb::StreamGaussiansRequest {
            clip_id: id.clone(),
            start: Some(0.0),
            end: Some(0.6),
            spacing: Some(pb::stream_gaussians_request::Spacing::Step(0.025)),
            precision: pb::Precision::F32 as i32,
            keyframes,
            ..Default::default()
        };
        let mut collect = async |request| {
            let mut frames = grpc.stream_gaussians(request).await.unwrap().into_inner();
            let mut sets = Vec::new();
            while let Some(frame) = frames.message().await.unwrap() {
                sets.push((frame.time, proto_means(&frame.gaussians.unwrap())));
            }
            sets
        };
        // gRPC: a keyframed stream, the keyframes decoded first and each chunk interpolated.
        let exact = collect(stream(None)).await;
        let adaptive = pb::Keyframes {
            mode: Some(pb::keyframes::Mode::Adaptive(pb::AdaptiveKeyframes {
                tolerance: TOLERANCE,
                ..Default::default()
            })),
        };
        let keyframed = collect(stream(Some(adaptive))).await;
        assert_eq!(exact.len(), 25);
        assert_eq!(
            keyframed.iter().map(|f| f.0).collect::<Vec<_>>(),
            exact.iter().map(|f| f.0).collect::<Vec<_>>()
        );
        let mut worst = 0.0f64;
        for ((t, a), (_, b)) in exact.iter().zip(&keyframed) {
            let d = largest_distance(a, b);
            assert!(d <= TOLERANCE + RUN_TO_RUN, "t = {t}: {d}");
            worst = worst.max(d);
        }
        eprintln!("gRPC stream, 25 sets: largest position error {worst:.2e}");

        // A trajectory rendered from 3 keyframes: every frame; frames 0, 2 and 4 from exact sets.
        let trajectory = |keyframes| pb::RenderTrajectoryRequest {
            clip_id: id.clone(),
            frames: 5,
            preset_json: r#"{"kind": "orbit", "depth": 2.0, "angle_degrees": 10}"#.into(),
            width: 32,
            height: 32,
            keyframes,
            ..Default::default()
        };
        let mut images = Vec::new();
        for keyframes in [None, Some(pb::keyframes::Mode::Count(3))] {
            let request = trajectory(keyframes.map(|mode| pb::Keyframes { mode: Some(mode) }));
            let mut frames = grpc.render_trajectory(request).await.unwrap().into_inner();
            let mut pngs = Vec::new();
            while let Some(frame) = frames.message().await.unwrap() {
                pngs.push(image::load_from_memory(&frame.data).unwrap().to_rgb8());
            }
            images.push(pngs);
        }
        assert_eq!((images[0].len(), images[1].len()), (5, 5));
        for k in [0, 2, 4] {
            let (a, b) = (images[0][k].as_raw(), images[1][k].as_raw());
            let worst = a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).max();
            assert!(worst <= Some(1), "frame {k}: {worst:?}");
        }

        // A Keyframes message without a mode is refused.
        let refused = grpc
            .stream_gaussians(stream(Some(pb::Keyframes { mode: None })))
            .await
            .unwrap_err();
        assert_eq!(refused.code(), tonic::Code::InvalidArgument, "{refused:?}");
        assert!(refused.message().contains("every_s"), "{refused:?}");
        let refused = grpc
            .decode(pb::DecodeRequest {
                clip_id: id.clone(),
                times: vec![0.1, 0.2],
                precision: 0,
                keyframes: Some(pb::Keyframes {
                    mode: Some(pb::keyframes::Mode::EveryS(-1.0)),
                }),
                ..Default::default()
            })
            .await
            .unwrap_err();
        assert_eq!(refused.code(), tonic::Code::InvalidArgument, "{refused:?}");
    });
}
