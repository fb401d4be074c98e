//! Point tracks through the running service: `POST /v1/clips/{id}/tracks`, gRPC `Tracks` and
//! `c4g track` answer the same tracks; a point starts where it was asked at its query time,
//! whether that is a context time or one between them; every answered time has a point, in
//! the image, with the depth its 3D position has in the (static) input camera; bad requests are
//! 400s (413 past the query limit) that say what is wrong. How well tracks follow the scene is
//! measured, not asserted here (`docs/benchmarks.md`, "Tracking"): that is the model's accuracy.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_e2e::{
    Server, binary, expect_invalid, json_of, ort_available, post_json, upload_synthetic,
};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use serde_json::{Value, json};

/// The synthetic clip's seven frame times.
const TIMES: [f64; 7] = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6];

/// Points on the moving object and on the room, at a context time and between context times.
fn queries() -> Value {
    json!([
        {"t": 0.0, "x": 30.5, "y": 33.1},
        {"t": 0.0, "x": 5.5, "y": 50.25},
        {"t": 0.3, "x": 26.0, "y": 30.0},
        {"t": 0.6, "x": 60.9, "y": 2.2}
    ])
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

#[test]
fn tracks_start_where_asked_and_rest_grpc_and_the_cli_agree() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    let body = json!({"queries": queries(), "times": TIMES});
    let rest = json_of(post_json(&server, &format!("/v1/clips/{id}/tracks"), &body));
    assert_eq!(
        (rest["width"].as_u64(), rest["height"].as_u64()),
        (Some(64), Some(64))
    );
    let tracks = rest["tracks"].as_array().unwrap();
    assert_eq!(tracks.len(), 4);
    // The clip has no given cameras: the input camera is the identity with C4G's intrinsics.
    let focal = 0.8767 * 64.0;
    for (track, query) in tracks.iter().zip(queries().as_array().unwrap()) {
        assert_eq!(&track["query"], query);
        assert_eq!(
            track["anchored"], true,
            "the room covers every pixel: {track}"
        );
        let points = track["points"].as_array().unwrap();
        assert_eq!(points.len(), TIMES.len());
        for (p, t) in points.iter().zip(TIMES) {
            assert_eq!(f(&p["t"]), t);
            let [x, y, z] = [0, 1, 2].map(|k| f(&p["position"][k]));
            assert!((f(&p["depth"]) - z).abs() < 1e-4, "{p}");
            assert!((focal * x / z + 32.0 - f(&p["x"])).abs() < 1e-2, "{p}");
            assert!((focal * y / z + 32.0 - f(&p["y"])).abs() < 1e-2, "{p}");
            if t == f(&query["t"]) {
                assert!((f(&p["x"]) - f(&query["x"])).abs() < 1e-3, "{p} vs {query}");
                assert!((f(&p["y"]) - f(&query["y"])).abs() < 1e-3, "{p} vs {query}");
                assert_eq!(p["visible"], true, "a point is seen where it is asked: {p}");
            }
        }
    }
    // Without times: the clip's context times.
    let at_context = json_of(post_json(
        &server,
        &format!("/v1/clips/{id}/tracks"),
        &json!({"queries": queries()}),
    ));
    assert_eq!(at_context["times"], json!([0.0, 0.2, 0.4, 0.6]));

    let runtime = tokio::runtime::Runtime::new().unwrap();
    let grpc = runtime.block_on(async {
        let mut client = C4gClient::connect(server.url()).await.unwrap();
        let request = pb::TracksRequest {
            clip_id: id.clone(),
            queries: queries()
                .as_array()
                .unwrap()
                .iter()
                .map(|q| pb::TrackQuery {
                    time: f(&q["t"]),
                    x: f(&q["x"]) as f32,
                    y: f(&q["y"]) as f32,
                })
                .collect(),
            times: TIMES.to_vec(),
            ..pb::TracksRequest::default()
        };
        client.tracks(request).await.unwrap().into_inner()
    });
    assert_eq!(grpc.tracks.len(), tracks.len());
    for (g, r) in grpc.tracks.iter().zip(tracks) {
        assert!(g.anchored);
        for (gp, rp) in g.points.iter().zip(r["points"].as_array().unwrap()) {
            // The same sets may be decoded in other batches: rounding, not a different answer.
            assert!(
                (f64::from(gp.x) - f(&rp["x"])).abs() < 1e-3,
                "{gp:?} vs {rp}"
            );
            assert!(
                (f64::from(gp.y) - f(&rp["y"])).abs() < 1e-3,
                "{gp:?} vs {rp}"
            );
            assert_eq!(gp.visible, rp["visible"].as_bool().unwrap());
            assert_eq!(gp.position.len(), 3);
        }
    }

    let cli = std::process::Command::new(binary("c4g"))
        .args([
            "--server",
            &server.url(),
            "--json",
            "track",
            &id,
            "--at",
            "0",
        ])
        .args([
            "--point",
            "30.5,33.1",
            "--point",
            "5.5,50.25",
            "--t",
            "0,0.1,0.2,0.3,0.4,0.5,0.6",
        ])
        .env_remove("C4G_API_KEY")
        .output()
        .unwrap();
    assert!(
        cli.status.success(),
        "{}",
        String::from_utf8_lossy(&cli.stderr)
    );
    let cli: Value = serde_json::from_slice(&cli.stdout).unwrap();
    for (c, r) in cli["tracks"].as_array().unwrap().iter().zip(&tracks[..2]) {
        for (cp, rp) in c["points"]
            .as_array()
            .unwrap()
            .iter()
            .zip(r["points"].as_array().unwrap())
        {
            assert!((f(&cp["x"]) - f(&rp["x"])).abs() < 1e-3, "{cp} vs {rp}");
            assert!((f(&cp["y"]) - f(&rp["y"])).abs() < 1e-3, "{cp} vs {rp}");
        }
    }
}

#[test]
fn bad_track_requests_say_what_is_wrong() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&["--max-track-queries", "2"]);
    let id = upload_synthetic(&server);
    let path = format!("/v1/clips/{id}/tracks");
    let post = |body: Value| post_json(&server, &path, &body);
    expect_invalid(post(json!({"queries": []})), "at least one query point");
    expect_invalid(
        post(json!({"queries": [{"t": 0.0, "x": 64.0, "y": 3.0}]})),
        "outside the 64x64 image",
    );
    expect_invalid(
        post(json!({"queries": [{"t": 0.0, "x": 40.0, "y": 3.0}], "width": 32, "height": 32})),
        "outside the 32x32 image",
    );
    expect_invalid(
        post(json!({"queries": [{"t": 0.9, "x": 3.0, "y": 3.0}]})),
        "outside the clip's context span",
    );
    expect_invalid(
        post(json!({"queries": [{"t": 0.0, "x": 3.0, "y": 3.0}], "times": [-0.1]})),
        "outside the clip's context span",
    );
    expect_invalid(
        post(json!({"queries": [{"t": 0.0, "x": 3.0, "y": 3.0, "z": 1.0}]})),
        "z",
    );
    let too_many = post(json!({"queries": [
        {"t": 0.0, "x": 1.0, "y": 1.0}, {"t": 0.0, "x": 2.0, "y": 1.0}, {"t": 0.0, "x": 3.0, "y": 1.0}
    ]}));
    assert_eq!(too_many.status(), 413);
    let message = json_of_error(too_many);
    assert!(message.contains("C4G_MAX_TRACK_QUERIES"), "{message}");
    assert_eq!(
        post_json(
            &server,
            "/v1/clips/000000000000000000000000/tracks",
            &json!({"queries": [{"t": 0.0, "x": 1.0, "y": 1.0}]})
        )
        .status(),
        404
    );
}

fn json_of_error(response: reqwest::blocking::Response) -> String {
    let body: Value = response.json().unwrap();
    body["error"].as_str().unwrap().to_owned()
}
