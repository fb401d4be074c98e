//! Fits end to end: `c4g-server` and `c4g-fitter` as processes on loopback, on the synthetic
//! clip with tiny settings (a few steps at 32 px). A fit job reports its progress as events and
//! its scene is then served in place of the feed-forward one over REST and gRPC alike (the same
//! values, each labelled `fitted`); a fit of 0 steps serves exactly the feed-forward sets at its
//! keyframes; a worker killed mid-fit leaves the job to another, which finishes it; a cancelled
//! fit leaves the earlier fitted scene as it was.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::io::{BufRead, BufReader};
use std::time::{Duration, Instant};

use c4g_e2e::{FitterWorker, Server, expect_error, ort_available, upload_synthetic};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use reqwest::blocking::Client;
use serde_json::{Value, json};

/// A fit small enough for a test: a few steps at 32 px on 8 frames.
fn tiny(steps: u64) -> Value {
    json!({"preset": "fast", "steps": steps, "resolution": 32, "max_frames": 8,
           "keyframe_every": 4, "holdout_every": 4, "seed": 1, "max_gaussians": 4000})
}

fn submit(client: &Client, server: &Server, clip: &str, request: Value) -> String {
    let response = client
        .post(server.at(&format!("/v1/clips/{clip}/fit")))
        .json(&request)
        .send()
        .unwrap();
    assert_eq!(response.status(), 202);
    let job: Value = response.json().unwrap();
    assert_eq!(job["kind"], "fit", "{job:#}");
    job["id"].as_str().unwrap().to_owned()
}

fn job(client: &Client, server: &Server, id: &str) -> Value {
    client
        .get(server.at(&format!("/v1/jobs/{id}")))
        .send()
        .unwrap()
        .json()
        .unwrap()
}

/// Polls job `id` until `done` says so, or panics after `limit`.
fn wait_for(
    client: &Client,
    server: &Server,
    id: &str,
    limit: Duration,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + limit;
    loop {
        let record = job(client, server, id);
        if done(&record) {
            return record;
        }
        assert!(Instant::now() < deadline, "job never got there: {record:#}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn decode(client: &Client, server: &Server, clip: &str, body: Value) -> (String, Value) {
    let response = client
        .post(server.at(&format!("/v1/clips/{clip}/gaussians")))
        .json(&body)
        .send()
        .unwrap();
    assert_eq!(response.status(), 200);
    let scene = response.headers()["x-c4g-scene"]
        .to_str()
        .unwrap()
        .to_owned();
    (scene, response.json().unwrap())
}

fn clip_record(client: &Client, server: &Server, clip: &str) -> Value {
    client
        .get(server.at(&format!("/v1/clips/{clip}")))
        .send()
        .unwrap()
        .json()
        .unwrap()
}

#[test]
fn a_fit_reports_progress_and_its_scene_is_served_over_rest_and_grpc_alike() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let clip = upload_synthetic(&server);
    let client = Client::new();
    // Before any fit: auto is the feed-forward scene, and fitted is not there to ask for.
    let (scene, _) = decode(&client, &server, &clip, json!({"t": 0.3}));
    assert_eq!(scene, "feed-forward");
    expect_error(
        client
            .post(server.at(&format!("/v1/clips/{clip}/gaussians")))
            .json(&json!({"t": 0.3, "scene": "fitted"}))
            .send()
            .unwrap(),
        404,
        "not_found",
        "no fitted scene",
    );

    let _worker = FitterWorker::start(&server.url(), "f1");
    let id = submit(&client, &server, &clip, tiny(24));
    let events = client
        .get(server.at(&format!("/v1/jobs/{id}/events")))
        .send()
        .unwrap();
    let (mut fitting, mut last) = (Vec::new(), Value::Null);
    for line in BufReader::new(events).lines() {
        if let Some(data) = line.unwrap().strip_prefix("data: ") {
            last = serde_json::from_str(data).unwrap();
            if last["progress"]["stage"] == "fitting" {
                fitting.push(last["progress"].clone());
            }
        }
    }
    assert_eq!(last["state"], "done", "{last:#}");
    assert_eq!(last["kind"], "fit");
    let seen = fitting.last().expect("progress while fitting");
    assert!(seen["loss"].as_f64().unwrap().is_finite(), "{seen:#}");
    assert!(seen["gaussians"].as_u64().unwrap() > 0, "{seen:#}");
    assert!(seen["elapsed_s"].as_f64().unwrap() > 0.0, "{seen:#}");

    // The clip's record lists the fitted scene, with its held-out frames.
    let record = clip_record(&client, &server, &clip);
    let fitted = &record["fitted"];
    assert_eq!(fitted["job_id"], id.as_str(), "{record:#}");
    assert_eq!(fitted["steps"], 24);
    let frames = fitted["frames"].as_u64().unwrap();
    assert!(frames >= 4, "{fitted:#}");
    let every_fourth: Vec<u64> = (3..frames).step_by(4).collect();
    assert_eq!(fitted["holdout_frames"], json!(every_fourth));
    assert!(fitted["gaussians"].as_u64().unwrap() <= 4000);
    assert!(fitted["holdout_psnr"].as_f64().unwrap().is_finite());

    // auto serves it; feed-forward still serves the model's answer; an approximation of the
    // fitted scene is refused.
    let t = 0.25;
    let (scene, rest) = decode(&client, &server, &clip, json!({"t": t}));
    assert_eq!(scene, "fitted");
    let (scene, feed_forward) = decode(
        &client,
        &server,
        &clip,
        json!({"t": t, "scene": "feed-forward"}),
    );
    assert_eq!(scene, "feed-forward");
    assert_ne!(rest, feed_forward);
    expect_error(
        client
            .post(server.at(&format!("/v1/clips/{clip}/gaussians")))
            .json(&json!({"t": t, "scene": "fitted", "quality": "fast"}))
            .send()
            .unwrap(),
        400,
        "invalid_input",
        "fitted scene",
    );
    let render = client
        .post(server.at(&format!("/v1/clips/{clip}/render")))
        .json(&json!({"t": t, "width": 32, "height": 32}))
        .send()
        .unwrap();
    assert_eq!(render.status(), 200);
    assert_eq!(render.headers()["x-c4g-scene"], "fitted");

    // gRPC: the same set, labelled the same.
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let (label, positions) = runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let answer = grpc
            .decode(pb::DecodeRequest {
                clip_id: clip.clone(),
                times: vec![t],
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner();
        let set = answer.frames[0].gaussians.clone().unwrap();
        (answer.scene, set)
    });
    assert_eq!(label, "fitted");
    let rest_means: Vec<f32> = rest["frames"][0]["means"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|m| {
            m.as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap() as f32)
        })
        .collect();
    let grpc_means: Vec<f32> = positions
        .means
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    assert_eq!(
        grpc_means, rest_means,
        "REST and gRPC serve the same fitted set"
    );

    // Tracks read the fitted scene too, over both transports alike, and say so.
    let tracks = |body: Value| {
        client
            .post(server.at(&format!("/v1/clips/{clip}/tracks")))
            .json(&body)
            .send()
            .unwrap()
    };
    let query = json!([{"t": 0.0, "x": 32.0, "y": 32.0}]);
    let rest_tracks = tracks(json!({"queries": query, "times": [t]}));
    assert_eq!(rest_tracks.status(), 200);
    assert_eq!(rest_tracks.headers()["x-c4g-scene"], "fitted");
    let rest_tracks: Value = rest_tracks.json().unwrap();
    let grpc_tracks = runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        grpc.tracks(pb::TracksRequest {
            clip_id: clip.clone(),
            queries: vec![pb::TrackQuery {
                time: 0.0,
                x: 32.0,
                y: 32.0,
            }],
            times: vec![t],
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner()
    });
    assert_eq!(grpc_tracks.scene, "fitted");
    let rest_point = &rest_tracks["tracks"][0]["points"][0];
    let grpc_point = &grpc_tracks.tracks[0].points[0];
    assert_eq!(
        (grpc_point.x, grpc_point.y),
        (
            rest_point["x"].as_f64().unwrap() as f32,
            rest_point["y"].as_f64().unwrap() as f32
        ),
        "REST and gRPC follow the point alike"
    );
    // The feature tracker reads the feed-forward scene's lifted features: auto serves it, and
    // says so; fitted is refused as any feature request is.
    let features = tracks(json!({"queries": query, "times": [t], "tracker": "features"}));
    assert_eq!(features.status(), 200);
    assert_eq!(features.headers()["x-c4g-scene"], "feed-forward");
    expect_error(
        tracks(json!({"queries": query, "tracker": "features", "scene": "fitted"})),
        422,
        "unsupported",
        "features",
    );
}

#[test]
fn zero_steps_serve_exactly_the_feed_forward_sets_at_the_keyframes() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let clip = upload_synthetic(&server);
    let client = Client::new();
    let _worker = FitterWorker::start(&server.url(), "f1");
    let id = submit(&client, &server, &clip, tiny(0));
    wait_for(&client, &server, &id, Duration::from_secs(120), |r| {
        r["state"] == "done"
    });
    let fitted = clip_record(&client, &server, &clip)["fitted"].clone();
    assert_eq!(fitted["steps"], 0);
    for t in fitted["keyframes"].as_array().unwrap() {
        let (scene, served) = decode(&client, &server, &clip, json!({"t": t}));
        assert_eq!(scene, "fitted");
        let (_, model) = decode(
            &client,
            &server,
            &clip,
            json!({"t": t, "scene": "feed-forward"}),
        );
        assert_eq!(served["frames"], model["frames"], "t = {t}");
    }
}

#[test]
fn a_worker_killed_mid_fit_leaves_the_job_to_another_and_a_cancelled_fit_keeps_the_earlier_scene() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&["--job-lease-s", "1", "--job-attempts", "3"]);
    let clip = upload_synthetic(&server);
    let client = Client::new();

    // Killed mid-fit: the lease runs out, and another worker fits the job on its next attempt.
    let mut doomed = FitterWorker::start(&server.url(), "doomed");
    let id = submit(&client, &server, &clip, tiny(100_000));
    wait_for(&client, &server, &id, Duration::from_secs(120), |r| {
        r["progress"]["stage"] == "fitting" && r["worker"] == "doomed"
    });
    doomed.0.kill().unwrap();
    doomed.0.wait().unwrap();
    let again = wait_for(&client, &server, &id, Duration::from_secs(60), |r| {
        r["state"] == "queued" && r["attempt"] == 2
    });
    assert!(
        again["history"][0].as_str().unwrap().contains("doomed"),
        "{again:#}"
    );
    // The second worker stops it by cancellation this time, once it is fitting.
    let _worker = FitterWorker::start(&server.url(), "f2");
    wait_for(&client, &server, &id, Duration::from_secs(120), |r| {
        r["progress"]["stage"] == "fitting" && r["worker"] == "f2"
    });
    let cancelled = client
        .post(server.at(&format!("/v1/jobs/{id}/cancel")))
        .send()
        .unwrap();
    assert_eq!(cancelled.status(), 200);
    wait_for(&client, &server, &id, Duration::from_secs(60), |r| {
        r["state"] == "cancelled"
    });
    assert!(clip_record(&client, &server, &clip).get("fitted").is_none());

    // A short fit finishes on the surviving worker; a later fit cancelled mid-way leaves it.
    let first = submit(&client, &server, &clip, tiny(6));
    wait_for(&client, &server, &first, Duration::from_secs(120), |r| {
        r["state"] == "done"
    });
    let long = submit(&client, &server, &clip, tiny(100_000));
    wait_for(&client, &server, &long, Duration::from_secs(120), |r| {
        r["progress"]["stage"] == "fitting"
    });
    client
        .post(server.at(&format!("/v1/jobs/{long}/cancel")))
        .send()
        .unwrap();
    wait_for(&client, &server, &long, Duration::from_secs(60), |r| {
        r["state"] == "cancelled"
    });
    let fitted = clip_record(&client, &server, &clip)["fitted"].clone();
    assert_eq!(fitted["job_id"], first.as_str(), "{fitted:#}");
}
