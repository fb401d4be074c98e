//! Streaming over gRPC against a fake `c4g.v1.C4G` service (h2c on loopback) that answers
//! `StreamGaussians` with hand-packed sets: the request the client sends, the API key in the
//! metadata, unpacking, errors, and the `c4g stream` command's files and lines.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::net::SocketAddr;

use c4g_client::{Approximation, Client, Error, Precision, Scene, Spacing, StreamOptions};
use c4g_proto::v1 as proto;
use c4g_proto::v1::c4g_server::{C4g, C4gServer};
use futures_util::StreamExt;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::{Request, Response, Status, Streaming};

const KEY: &str = "s3cret";

/// Streams one set of one Gaussian per time from `start` (default 0) every `step` (default 0.5)
/// up to `end` (default 1), after checking the API key; clip `missing` is not found.
struct Fake;

fn set(x: f32, precision: proto::Precision) -> proto::GaussianSet {
    let pack = |values: &[f32]| -> Vec<u8> {
        match precision {
            proto::Precision::F16 => values
                .iter()
                .flat_map(|&v| half::f16::from_f32(v).to_le_bytes())
                .collect(),
            _ => values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    };
    proto::GaussianSet {
        count: 1,
        precision: precision.into(),
        means: pack(&[x, 0.0, 2.0]),
        scales: pack(&[0.125, 0.125, 0.125]),
        rotations: pack(&[1.0, 0.0, 0.0, 0.0]),
        opacities: pack(&[0.5]),
        colors: pack(&[1.0, 0.5, 0.25]),
        ..Default::default()
    }
}

#[tonic::async_trait]
impl C4g for Fake {
    type StreamGaussiansStream =
        futures_util::stream::BoxStream<'static, Result<proto::GaussianFrame, Status>>;
    type RenderTrajectoryStream =
        futures_util::stream::BoxStream<'static, Result<proto::RenderedImage, Status>>;

    async fn stream_gaussians(
        &self,
        request: Request<proto::StreamGaussiansRequest>,
    ) -> Result<Response<Self::StreamGaussiansStream>, Status> {
        let authorized = request
            .metadata()
            .get("authorization")
            .is_some_and(|v| v == format!("Bearer {KEY}").as_str());
        if !authorized {
            return Err(Status::unauthenticated("missing or wrong API key"));
        }
        let request = request.into_inner();
        if request.clip_id == "missing" {
            return Err(Status::not_found("no clip missing"));
        }
        // The scene the request names, told back by the sign of the set's x: fitted is -1.
        if request.clip_id == "scenes" {
            let x = if request.scene == "fitted" { -1.0 } else { 1.0 };
            let frame = proto::GaussianFrame {
                time: 0.0,
                gaussians: Some(set(x, request.precision())),
                scene: request.scene.clone(),
                ..Default::default()
            };
            return Ok(Response::new(
                futures_util::stream::iter([Ok(frame)]).boxed(),
            ));
        }
        let step = match request.spacing {
            Some(proto::stream_gaussians_request::Spacing::Step(step)) => step,
            Some(proto::stream_gaussians_request::Spacing::Fps(fps)) => 1.0 / fps,
            None => 0.5,
        };
        let (start, end) = (request.start.unwrap_or(0.0), request.end.unwrap_or(1.0));
        let precision = request.precision();
        let count = ((end - start) / step).round() as usize + 1;
        let frames = (0..count).map(move |i| {
            let time = start + i as f64 * step;
            Ok(proto::GaussianFrame {
                time,
                gaussians: Some(set(time as f32, precision)),
                ..Default::default()
            })
        });
        Ok(Response::new(futures_util::stream::iter(frames).boxed()))
    }

    async fn upload(
        &self,
        _: Request<Streaming<proto::UploadRequest>>,
    ) -> Result<Response<proto::Clip>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn get_clip(&self, _: Request<proto::ClipRef>) -> Result<Response<proto::Clip>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn list_clips(
        &self,
        _: Request<proto::ListClipsRequest>,
    ) -> Result<Response<proto::ListClipsResponse>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn delete_clip(
        &self,
        _: Request<proto::ClipRef>,
    ) -> Result<Response<proto::DeleteClipResponse>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn decode(
        &self,
        _: Request<proto::DecodeRequest>,
    ) -> Result<Response<proto::DecodeResponse>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn render(
        &self,
        _: Request<proto::RenderRequest>,
    ) -> Result<Response<proto::RenderedImage>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn render_trajectory(
        &self,
        _: Request<proto::RenderTrajectoryRequest>,
    ) -> Result<Response<Self::RenderTrajectoryStream>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn tracks(
        &self,
        _: Request<proto::TracksRequest>,
    ) -> Result<Response<proto::TracksResponse>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn segment(
        &self,
        _: Request<proto::SegmentRequest>,
    ) -> Result<Response<proto::SegmentResponse>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn recover_cameras(
        &self,
        _: Request<proto::RecoverCamerasRequest>,
    ) -> Result<Response<proto::RecoveredCameras>, Status> {
        Err(Status::unimplemented("fake"))
    }
    async fn list_models(
        &self,
        _: Request<proto::ListModelsRequest>,
    ) -> Result<Response<proto::ListModelsResponse>, Status> {
        Err(Status::unimplemented("fake"))
    }
}

/// Serves the fake on a free loopback port, on a runtime of its own thread so a test can also
/// run the `c4g` binary synchronously.
fn serve() -> SocketAddr {
    let (sender, receiver) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Runtime::new().unwrap();
        runtime.block_on(async move {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            sender.send(listener.local_addr().unwrap()).unwrap();
            tonic::transport::Server::builder()
                .add_service(C4gServer::new(Fake))
                .serve_with_incoming(TcpListenerStream::new(listener))
                .await
                .unwrap();
        });
    });
    receiver.recv().unwrap()
}

#[tokio::test]
async fn streamed_sets_arrive_in_order_and_unpacked() {
    let address = serve();
    let client = Client::new(&format!("http://{address}"), Some(KEY)).unwrap();
    for precision in [Precision::F32, Precision::F16] {
        let options = StreamOptions {
            start: Some(0.25),
            end: Some(1.25),
            spacing: Some(Spacing::Step(0.25)),
            precision,
            approximation: Approximation::default(),
            compact: None,
        };
        let frames: Vec<_> = client
            .stream("clip", &options)
            .await
            .unwrap()
            .collect()
            .await;
        let frames: Vec<_> = frames.into_iter().map(Result::unwrap).collect();
        let times: Vec<f64> = frames.iter().map(|f| f.time).collect();
        assert_eq!(times, [0.25, 0.5, 0.75, 1.0, 1.25], "{precision}");
        let last = &frames[4].gaussians;
        assert_eq!(last.positions(), &[[1.25, 0.0, 2.0]]);
        assert_eq!(last.colors(), &[[1.0, 0.5, 0.25]]);
        assert_eq!(last.opacities(), &[0.5]);
    }
}

#[tokio::test]
async fn a_stream_sends_the_scene_it_asks_for() {
    let address = serve();
    let client = Client::new(&format!("http://{address}"), Some(KEY)).unwrap();
    for (scene, x) in [
        (None, 1.0),
        (Some(Scene::FeedForward), 1.0),
        (Some(Scene::Fitted), -1.0),
    ] {
        let options = StreamOptions {
            approximation: Approximation {
                scene,
                ..Approximation::default()
            },
            ..StreamOptions::default()
        };
        let frames: Vec<_> = client
            .stream("scenes", &options)
            .await
            .unwrap()
            .collect()
            .await;
        let set = &frames[0].as_ref().unwrap().gaussians;
        assert_eq!(set.positions()[0][0], x, "{scene:?}");
    }
}

#[tokio::test]
async fn grpc_errors_keep_their_code_and_message() {
    let address = serve();
    let client = Client::new(&format!("http://{address}"), Some(KEY)).unwrap();
    let err = client
        .stream("missing", &StreamOptions::default())
        .await
        .err()
        .unwrap();
    assert!(
        matches!(
            err,
            Error::Grpc {
                code: tonic::Code::NotFound,
                ..
            }
        ),
        "{err}"
    );
    assert_eq!(err.kind(), Some("not_found"));
    assert_eq!(err.to_string(), "grpc not_found: no clip missing");

    let anonymous = Client::new(&format!("http://{address}"), None).unwrap();
    let err = anonymous
        .stream("clip", &StreamOptions::default())
        .await
        .err()
        .unwrap();
    assert_eq!(err.kind(), Some("unauthenticated"));
}

#[test]
fn the_stream_command_writes_one_ply_per_set() {
    let address = serve();
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_c4g"))
        .args([
            "--server",
            &format!("http://{address}"),
            "--json",
            "stream",
            "clip",
        ])
        .args(["--fps", "2", "--precision", "f16", "-o"])
        .arg(dir.path())
        .env("C4G_API_KEY", KEY)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<serde_json::Value> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|line| serde_json::from_str(line).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    assert_eq!(lines[1]["t"], 0.5);
    assert_eq!(lines[1]["count"], 1);

    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "frame-00000-t0.000.ply",
            "frame-00001-t0.500.ply",
            "frame-00002-t1.000.ply"
        ]
    );
    let set = c4g_formats::ply::read(&dir.path().join(&names[2])).unwrap();
    assert_eq!(set.len(), 1);
    assert_eq!(set.positions()[0], [1.0, 0.0, 2.0]);
}
