//! The REST calls against a fake HTTP server that records one request and answers a canned
//! response: what the client sends (method, path, query, headers, body) and how it reads the
//! answer.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::sync::{Arc, Mutex};

use c4g_client::{
    Approximation, Client, ExportFormat, ExportOptions, FitPreset, FitRequest, GaussianFormat,
    Precision, RefineRequest, RenderRequest, Sampler, Scene, TrackQuery, TrackRequest,
    TrajectoryPreset, UploadOptions, UploadSource,
};
use futures_util::StreamExt;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::task::JoinHandle;

/// One request as the fake received it.
struct Recorded {
    head: String,
    body: Vec<u8>,
}

impl Recorded {
    fn request_line(&self) -> &str {
        self.head.lines().next().unwrap()
    }

    fn header(&self, name: &str) -> Option<String> {
        self.head.lines().skip(1).find_map(|line| {
            let (key, value) = line.split_once(':')?;
            key.eq_ignore_ascii_case(name)
                .then(|| value.trim().to_owned())
        })
    }
}

/// Serves one request with `status`, `headers` and `body`; resolves to the request.
async fn fake(
    status: &'static str,
    headers: &'static [(&'static str, &'static str)],
    body: Vec<u8>,
) -> (Client, JoinHandle<Recorded>) {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let client = Client::new(&listener.local_addr().unwrap().to_string(), None).unwrap();
    let handle = tokio::spawn(async move {
        let (mut socket, _) = listener.accept().await.unwrap();
        let mut received = Vec::new();
        let mut buffer = [0u8; 64 * 1024];
        let head_end = loop {
            let n = socket.read(&mut buffer).await.unwrap();
            received.extend_from_slice(&buffer[..n]);
            if let Some(i) = received.windows(4).position(|w| w == b"\r\n\r\n") {
                break i + 4;
            }
        };
        let head = String::from_utf8(received[..head_end].to_vec()).unwrap();
        let mut recorded = Recorded {
            head,
            body: received[head_end..].to_vec(),
        };
        let length: usize = recorded
            .header("content-length")
            .map_or(0, |v| v.parse().unwrap());
        while recorded.body.len() < length {
            let n = socket.read(&mut buffer).await.unwrap();
            recorded.body.extend_from_slice(&buffer[..n]);
        }
        let mut response = format!(
            "HTTP/1.1 {status}\r\ncontent-length: {}\r\nconnection: close\r\n",
            body.len()
        );
        for (name, value) in headers {
            response.push_str(&format!("{name}: {value}\r\n"));
        }
        response.push_str("\r\n");
        socket.write_all(response.as_bytes()).await.unwrap();
        socket.write_all(&body).await.unwrap();
        socket.shutdown().await.unwrap();
        recorded
    });
    (client, handle)
}

const CLIP: &str = r#"{"id": "3f2a", "model": "c4g-tiny", "state": "ready",
 "context_times": [0.0, 0.5, 1.0], "span": [0.0, 1.0],
 "source": {"kind": "video", "frames": 30, "width": 96, "height": 64, "duration": 1.0, "fps": 30.0},
 "feature_bytes": 4096, "created": true, "options": {"max_frames": 3}}"#;

#[tokio::test]
async fn a_video_streams_as_the_body_with_its_type_and_the_options_in_the_query() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("clip.webm");
    let video: Vec<u8> = (0..700_000u32).map(|i| (i % 251) as u8).collect();
    std::fs::write(&path, &video).unwrap();

    let (client, server) = fake(
        "201 Created",
        &[("content-type", "application/json")],
        CLIP.into(),
    )
    .await;
    let seen = Arc::new(Mutex::new(Vec::new()));
    let log = seen.clone();
    let options = UploadOptions {
        max_frames: Some(3),
        start: Some(0.25),
        ..UploadOptions::default()
    };
    let clip = client
        .upload(path.as_path(), &options, move |sent, total| {
            log.lock().unwrap().push((sent, total))
        })
        .await
        .unwrap();
    let request = server.await.unwrap();

    assert_eq!(
        request.request_line(),
        "POST /v1/clips?max_frames=3&start=0.25 HTTP/1.1"
    );
    assert_eq!(request.header("content-type").unwrap(), "video/webm");
    assert_eq!(request.header("content-length").unwrap(), "700000");
    assert_eq!(request.body, video);
    let seen = seen.lock().unwrap();
    assert_eq!(seen.first(), Some(&(0, 700_000)));
    assert_eq!(seen.last(), Some(&(700_000, 700_000)));
    assert!(seen.windows(2).all(|w| w[0].0 <= w[1].0));

    assert_eq!(clip.id, "3f2a");
    assert_eq!(clip.context_span(), Some((0.0, 1.0)));
    assert_eq!(clip.source.as_ref().unwrap().frames, Some(30));
    assert_eq!(clip.created, Some(true));
    assert!(
        clip.extra.contains_key("options"),
        "unknown fields are kept"
    );
}

#[tokio::test]
async fn a_directory_becomes_frame_parts_in_name_order_after_the_options() {
    let dir = tempfile::tempdir().unwrap();
    for (name, content) in [
        ("002.png", "second"),
        ("001.png", "first"),
        ("notes.txt", "x"),
    ] {
        std::fs::write(dir.path().join(name), content).unwrap();
    }
    let (client, server) = fake("200 OK", &[], CLIP.replace("true", "false").into()).await;
    let options = UploadOptions {
        fps: Some(5.0),
        ..UploadOptions::default()
    };
    let clip = client
        .upload(
            UploadSource::Path(dir.path().to_owned()),
            &options,
            |_, _| {},
        )
        .await
        .unwrap();
    let request = server.await.unwrap();

    assert_eq!(request.request_line(), "POST /v1/clips HTTP/1.1");
    assert!(
        request
            .header("content-type")
            .unwrap()
            .starts_with("multipart/form-data; boundary=")
    );
    let body = String::from_utf8(request.body).unwrap();
    let fps = body.find("name=\"fps\"").unwrap();
    let first = body.find("first").unwrap();
    let second = body.find("second").unwrap();
    assert!(fps < first && first < second, "{body}");
    assert_eq!(body.matches("name=\"frame\"").count(), 2);
    assert!(body.contains("filename=\"001.png\""));
    assert!(body.contains("image/png"));
    assert!(!body.contains("notes.txt"));
    assert_eq!(clip.created, Some(false));
}

#[tokio::test]
async fn gaussians_ask_for_the_binary_format_and_parse_it() {
    let mut payload = b"C4GS".to_vec();
    payload.extend_from_slice(&1u16.to_le_bytes());
    payload.extend_from_slice(&[0, 0]);
    payload.extend_from_slice(&1u32.to_le_bytes());
    payload.extend_from_slice(&1u32.to_le_bytes());
    payload.extend_from_slice(&0.5f64.to_le_bytes());
    let row = [
        1.0f32, 2.0, 3.0, 0.1, 0.1, 0.1, 1.0, 0.0, 0.0, 0.0, 0.9, 0.2, 0.3, 0.4,
    ];
    payload.extend(row.iter().flat_map(|v| v.to_le_bytes()));

    let (client, server) = fake(
        "200 OK",
        &[("content-type", "application/x-c4g-gaussians")],
        payload,
    )
    .await;
    let frames = client
        .gaussians("3f2a", &[0.5], Precision::F32)
        .await
        .unwrap();
    let request = server.await.unwrap();

    assert_eq!(
        request.request_line(),
        "POST /v1/clips/3f2a/gaussians HTTP/1.1"
    );
    assert_eq!(
        request.header("accept").unwrap(),
        "application/x-c4g-gaussians"
    );
    let body: serde_json::Value = serde_json::from_slice(&request.body).unwrap();
    assert_eq!(
        body,
        serde_json::json!({"times": [0.5], "format": "binary", "precision": "f32"})
    );
    assert_eq!(frames.len(), 1);
    assert_eq!(frames[0].time, 0.5);
    assert_eq!(frames[0].gaussians.to_canonical(), row);
}

#[tokio::test]
async fn render_sends_only_the_fields_given_and_reads_the_size_headers() {
    let (client, server) = fake(
        "200 OK",
        &[
            ("content-type", "application/octet-stream"),
            ("x-c4g-width", "2"),
            ("x-c4g-height", "1"),
        ],
        vec![0; 8],
    )
    .await;
    let request = RenderRequest {
        t: Some(0.5),
        width: Some(2),
        height: Some(1),
        format: Some(c4g_client::RenderFormat::Depth),
        ..RenderRequest::default()
    };
    let rendered = client.render("3f2a", &request).await.unwrap();
    let recorded = server.await.unwrap();

    let body: serde_json::Value = serde_json::from_slice(&recorded.body).unwrap();
    assert_eq!(
        body,
        serde_json::json!({"t": 0.5, "width": 2, "height": 1, "format": "depth"})
    );
    assert_eq!((rendered.width, rendered.height), (Some(2), Some(1)));
    assert_eq!(rendered.content_type, "application/octet-stream");
    assert_eq!(rendered.data.len(), 8);
}

#[tokio::test]
async fn error_bodies_that_are_not_the_apis_still_give_status_and_text() {
    let (client, server) = fake(
        "503 Service Unavailable",
        &[("retry-after", "7")],
        b"upstream down".to_vec(),
    )
    .await;
    let err = client.clips().await.unwrap_err();
    server.await.unwrap();
    match err {
        c4g_client::Error::Api {
            status,
            kind,
            message,
            retry_after,
        } => {
            assert_eq!(status, 503);
            assert_eq!(kind, "service_unavailable");
            assert_eq!(message, "upstream down");
            assert_eq!(retry_after, Some(7));
        }
        other => panic!("expected Api, got {other:?}"),
    }
}

const JOB: &str = r#"{"id": "job-01", "clip_id": "3f2a", "state": "queued", "attempt": 1,
 "max_attempts": 3, "worker": null, "progress": null, "error": null, "history": [],
 "request": {"steps": 4}, "result_frames": 0, "seconds": null, "created_at": 1, "updated_at": 1,
 "cancel_requested": false}"#;

#[tokio::test]
async fn refine_posts_the_request_and_reads_the_queued_job() {
    let (client, server) = fake(
        "202 Accepted",
        &[
            ("content-type", "application/json"),
            ("location", "/v1/jobs/job-01"),
        ],
        JOB.into(),
    )
    .await;
    let request = RefineRequest {
        trajectory: Some(
            TrajectoryPreset::Orbit {
                depth: 2.0,
                angle_degrees: 20.0,
            }
            .to_json(),
        ),
        steps: Some(4),
        sampler: Some(Sampler::Euler),
        caption: Some("a bed".into()),
        ..RefineRequest::default()
    };
    let job = client.refine("3f2a", &request).await.unwrap();
    let recorded = server.await.unwrap();

    assert_eq!(
        recorded.request_line(),
        "POST /v1/clips/3f2a/refine HTTP/1.1"
    );
    let body: serde_json::Value = serde_json::from_slice(&recorded.body).unwrap();
    assert_eq!(
        body,
        serde_json::json!({
            "trajectory": {"kind": "orbit", "depth": 2.0, "angle_degrees": 20.0},
            "steps": 4, "sampler": "euler", "caption": "a bed"
        })
    );
    assert_eq!(job.id, "job-01");
    assert_eq!(job.state, "queued");
    assert_eq!((job.attempt, job.max_attempts), (1, 3));
    assert!(job.progress.is_none() && !job.is_terminal());
    // The record re-serialises as the server sent it, nulls and unknown fields included.
    let original: serde_json::Value = serde_json::from_str(JOB).unwrap();
    assert_eq!(serde_json::to_value(&job).unwrap(), original);
}

#[tokio::test]
async fn a_refinement_answered_other_than_202_is_malformed() {
    let (client, server) = fake("200 OK", &[], JOB.into()).await;
    let err = client
        .refine("3f2a", &serde_json::json!({}))
        .await
        .unwrap_err();
    server.await.unwrap();
    assert!(matches!(err, c4g_client::Error::Malformed(_)), "{err}");
}

#[tokio::test]
async fn cancel_posts_to_the_jobs_cancel_path() {
    let (client, server) = fake(
        "200 OK",
        &[],
        JOB.replace("\"queued\"", "\"cancelled\"").into(),
    )
    .await;
    let job = client.cancel("job-01").await.unwrap();
    let recorded = server.await.unwrap();
    assert_eq!(
        recorded.request_line(),
        "POST /v1/jobs/job-01/cancel HTTP/1.1"
    );
    assert!(job.is_terminal());
}

#[tokio::test]
async fn jobs_list_and_result_frames_by_query() {
    let (client, server) = fake("200 OK", &[], format!("{{\"jobs\": [{JOB}]}}").into()).await;
    let jobs = client.jobs().await.unwrap();
    assert_eq!(
        server.await.unwrap().request_line(),
        "GET /v1/jobs HTTP/1.1"
    );
    assert_eq!(jobs.len(), 1);

    let (client, server) = fake(
        "200 OK",
        &[("content-type", "image/png")],
        b"\x89PNG".to_vec(),
    )
    .await;
    let png = client.job_result_frame("job-01", 7).await.unwrap();
    assert_eq!(
        server.await.unwrap().request_line(),
        "GET /v1/jobs/job-01/result?frame=7 HTTP/1.1"
    );
    assert_eq!(&png[..], b"\x89PNG");

    let (client, server) = fake("200 OK", &[("content-type", "video/mp4")], vec![1, 2]).await;
    let mp4 = client.job_result("job-01").await.unwrap();
    assert_eq!(
        server.await.unwrap().request_line(),
        "GET /v1/jobs/job-01/result HTTP/1.1"
    );
    assert_eq!(&mp4[..], [1, 2]);
}

#[tokio::test]
async fn job_events_ask_for_an_event_stream_and_end_with_the_job() {
    let running = JOB.replace("\"queued\"", "\"running\"").replace('\n', "");
    let done = JOB.replace("\"queued\"", "\"done\"").replace('\n', "");
    let body = format!(
        "event: job\ndata: {running}\n\n:\n\nevent: job\ndata: {done}\n\nevent: job\ndata: {running}\n\n"
    );
    let (client, server) = fake(
        "200 OK",
        &[("content-type", "text/event-stream")],
        body.into(),
    )
    .await;
    let states: Vec<String> = client
        .job_events("job-01")
        .map(|job| job.unwrap().state)
        .collect()
        .await;
    let recorded = server.await.unwrap();
    assert_eq!(
        recorded.request_line(),
        "GET /v1/jobs/job-01/events HTTP/1.1"
    );
    assert_eq!(recorded.header("accept").unwrap(), "text/event-stream");
    assert_eq!(states, ["running", "done"]);
}

#[tokio::test]
async fn job_events_of_an_unknown_job_are_one_error() {
    let (client, server) = fake(
        "404 Not Found",
        &[("content-type", "application/json")],
        br#"{"error": "no job x", "kind": "not_found"}"#.to_vec(),
    )
    .await;
    let items: Vec<_> = client.job_events("x").collect().await;
    server.await.unwrap();
    assert_eq!(items.len(), 1);
    let err = items.into_iter().next().unwrap().unwrap_err();
    assert_eq!(err.kind(), Some("not_found"));
}

const FIT_JOB: &str = r#"{"id": "job-02", "kind": "fit", "clip_id": "3f2a", "state": "running",
 "attempt": 1, "max_attempts": 3, "worker": "f1", "error": null, "history": [],
 "progress": {"step": 4, "steps": 8, "stage": "fitting", "loss": 0.25, "holdout_psnr": 19.5,
  "gaussians": 900, "elapsed_s": 1.5},
 "request": {"preset": "fast"}, "result_frames": 0, "seconds": null, "created_at": 1,
 "updated_at": 1, "cancel_requested": false}"#;

#[tokio::test]
async fn fit_posts_the_request_and_reads_the_fit_job_with_its_progress() {
    let (client, server) = fake(
        "202 Accepted",
        &[
            ("content-type", "application/json"),
            ("location", "/v1/jobs/job-02"),
        ],
        FIT_JOB.into(),
    )
    .await;
    let request = FitRequest {
        preset: Some(FitPreset::Fast),
        steps: Some(8),
        resolution: Some(32),
        max_frames: Some(8),
        refine_cameras: Some(false),
        ..FitRequest::default()
    };
    let job = client.fit("3f2a", &request).await.unwrap();
    let recorded = server.await.unwrap();

    assert_eq!(recorded.request_line(), "POST /v1/clips/3f2a/fit HTTP/1.1");
    let body: serde_json::Value = serde_json::from_slice(&recorded.body).unwrap();
    assert_eq!(
        body,
        serde_json::json!({"preset": "fast", "steps": 8, "resolution": 32, "max_frames": 8,
                           "refine_cameras": false})
    );
    assert!(job.is_fit() && !job.is_terminal());
    let progress = job.progress.clone().unwrap();
    assert_eq!((progress.step, progress.steps), (4, 8));
    assert_eq!(progress.loss, Some(0.25));
    assert_eq!(progress.holdout_psnr, Some(19.5));
    assert_eq!(progress.gaussians, Some(900));
    assert_eq!(progress.elapsed_s, Some(1.5));
    let original: serde_json::Value = serde_json::from_str(FIT_JOB).unwrap();
    assert_eq!(serde_json::to_value(&job).unwrap(), original);
}

#[tokio::test]
async fn a_fit_answered_other_than_202_is_malformed() {
    let (client, server) = fake("200 OK", &[], FIT_JOB.into()).await;
    let err = client
        .fit("3f2a", &FitRequest::default())
        .await
        .unwrap_err();
    server.await.unwrap();
    assert!(matches!(err, c4g_client::Error::Malformed(_)), "{err}");
}

#[tokio::test]
async fn a_clip_lists_its_fitted_scene_and_none_without_one() {
    let record = serde_json::json!({
        "id": "3f2a", "model": "c4g-tiny", "state": "ready", "context_times": [0.0, 0.6],
        "fitted": {"job_id": "job-02", "preset": "fast", "gaussians": 900,
                   "static_gaussians": 700, "keyframes": [0.0, 0.3, 0.6], "steps": 8,
                   "seconds": 2.5, "frames": 8, "resolution": [32, 32],
                   "holdout_frames": [3, 7], "holdout_times": [0.3, 0.7],
                   "holdout_psnr": 21.0, "holdout_psnr_feed_forward": 16.0,
                   "train_psnr": 22.0, "stopped_early": false, "created_at": 5,
                   "notes": []}
    });
    let (client, server) = fake("200 OK", &[], record.to_string().into()).await;
    let clip = client.clip("3f2a").await.unwrap();
    server.await.unwrap();
    let fitted = clip.fitted.clone().unwrap();
    assert_eq!(fitted.job_id, "job-02");
    assert_eq!(fitted.keyframes, [0.0, 0.3, 0.6]);
    assert_eq!(fitted.holdout_gain(), Some(5.0));
    assert_eq!(serde_json::to_value(&clip).unwrap(), record);

    let (client, server) = fake(
        "200 OK",
        &[],
        br#"{"id": "3f2a", "context_times": [0.0]}"#.to_vec(),
    )
    .await;
    let clip = client.clip("3f2a").await.unwrap();
    server.await.unwrap();
    assert!(clip.fitted.is_none());
    assert!(serde_json::to_value(&clip).unwrap().get("fitted").is_none());
}

#[tokio::test]
async fn renders_exports_and_tracks_send_the_scene_and_read_which_served() {
    let fitted = Approximation {
        scene: Some(Scene::Fitted),
        ..Approximation::default()
    };
    let (client, server) = fake(
        "200 OK",
        &[("content-type", "image/png"), ("x-c4g-scene", "fitted")],
        b"\x89PNG".to_vec(),
    )
    .await;
    let request = RenderRequest {
        t: Some(0.5),
        approximation: fitted,
        ..RenderRequest::default()
    };
    let rendered = client.render("3f2a", &request).await.unwrap();
    let body: serde_json::Value = serde_json::from_slice(&server.await.unwrap().body).unwrap();
    assert_eq!(body, serde_json::json!({"t": 0.5, "scene": "fitted"}));
    assert_eq!(rendered.scene, Some(Scene::Fitted));

    let (client, server) = fake(
        "200 OK",
        &[("x-c4g-sets", "2"), ("x-c4g-scene", "feed-forward")],
        b"PK".to_vec(),
    )
    .await;
    let options = ExportOptions {
        approximation: Approximation {
            scene: Some(Scene::FeedForward),
            ..Approximation::default()
        },
        ..ExportOptions::default()
    };
    let export = client
        .export("3f2a", ExportFormat::PlyZip, &options)
        .await
        .unwrap();
    let body: serde_json::Value = serde_json::from_slice(&server.await.unwrap().body).unwrap();
    assert_eq!(
        body,
        serde_json::json!({"format": "ply_zip", "scene": "feed-forward"})
    );
    assert_eq!((export.sets, export.scene), (2, Some(Scene::FeedForward)));

    let answer = serde_json::json!({"tracker": "gaussians", "width": 4, "height": 4,
                                    "times": [0.5], "tracks": []});
    let (client, server) = fake(
        "200 OK",
        &[
            ("content-type", "application/json"),
            ("x-c4g-scene", "fitted"),
        ],
        answer.to_string().into(),
    )
    .await;
    let request = TrackRequest {
        queries: vec![TrackQuery {
            t: 0.5,
            x: 1.0,
            y: 2.0,
        }],
        approximation: fitted,
        ..TrackRequest::default()
    };
    let tracks = client.tracks("3f2a", &request).await.unwrap();
    let body: serde_json::Value = serde_json::from_slice(&server.await.unwrap().body).unwrap();
    assert_eq!(body["scene"], "fitted");
    assert_eq!(tracks.scene, Some(Scene::Fitted));

    // A server that does not say leaves it unknown.
    let (client, server) = fake("200 OK", &[("content-type", "image/png")], vec![]).await;
    let rendered = client
        .render("3f2a", &RenderRequest::default())
        .await
        .unwrap();
    server.await.unwrap();
    assert_eq!(rendered.scene, None);
}

#[tokio::test]
async fn decodes_send_the_scene_they_ask_for() {
    let (client, server) = fake(
        "200 OK",
        &[("x-c4g-scene", "fitted")],
        br#"{"frames": []}"#.to_vec(),
    )
    .await;
    let approximation = Approximation {
        scene: Some(Scene::Fitted),
        ..Approximation::default()
    };
    client
        .gaussians_raw_approximated("3f2a", &[0.5], GaussianFormat::Json, &approximation)
        .await
        .unwrap();
    let body: serde_json::Value = serde_json::from_slice(&server.await.unwrap().body).unwrap();
    assert_eq!(
        body,
        serde_json::json!({"times": [0.5], "format": "json", "precision": "f32", "scene": "fitted"})
    );
}
