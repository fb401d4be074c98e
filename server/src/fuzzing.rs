//! Entry points for the fuzz targets in `fuzz/` (feature `fuzzing`; nothing else uses it).
//!
//! Each takes untrusted bytes the way the server takes them and says whether the answer was a
//! bug. A fuzz target holds everything it feeds in to two rules: the process survives (no panic,
//! no arithmetic overflow with debug assertions on, no allocation past the limits), and no answer
//! is an internal error (HTTP 500, gRPC `INTERNAL` or `UNKNOWN`): bad input is the client's
//! error, refused with a message. Busy, overloaded and full-disk answers are documented
//! refusals, not bugs.
//!
//! - [`upload`]: the sniffer, then, for archives and images, the whole image intake (zip and
//!   tar reading, decompression and size limits, frame times, context sampling) with options.
//!   Videos go to FFmpeg in a child process, which is FFmpeg's parser, not ours: not fuzzed here.
//! - [`Edge`]: the real router (REST and gRPC on one service, as `c4g-server` serves them) over
//!   a real model and store, with one clip uploaded; requests go through the handlers'
//!   extractors, the JSON rules, camera, trajectory, quality and time checks, and the decoder.
//! - [`gaussian_files`] (`files`): the readers and writers of Gaussian files and payloads.
//! - [`time_policy`]: the time policies on any context and target.
//!
//! The fuzz targets call these; so does `server/tests/fuzz_corpora.rs`, which replays every
//! committed corpus and regression input through the ordinary test build (CI's check of them,
//! with no instrumented build); `scripts/fuzz` does the fuzzing.

mod files;
mod time_policy;

pub use files::gaussian_files;
pub use time_policy::time_policy;

use std::path::PathBuf;
use std::sync::OnceLock;

use axum::Router;
use axum::body::Body;
use axum::http::{Method, Request, StatusCode, Uri};
use bytes::Bytes;
use c4g_engine::Engine;
use clap::Parser;
use http_body_util::BodyExt;
use prost::Message;
use tower::ServiceExt;

use crate::AppState;
use c4g_service::clips::intake::{
    IntakeOptions, Media, MediaKind, images, sniff, validate_options,
};
use c4g_service::config::{Config, Limits};
use c4g_service::service::Service;
use c4g_service::{ServiceError, ServiceErrorKind};

/// Limits small enough that one input is cheap, as an operator would set them on a small box.
const SETTINGS: [&str; 16] = [
    "--max-side",
    "256",
    "--min-side",
    "8",
    "--max-render-pixels",
    "4096",
    "--max-times",
    "8",
    "--max-source-frames",
    "64",
    "--max-archive-mib",
    "4",
    "--context-frames",
    "4",
    "--intra-op-threads",
    "1",
];

fn limits() -> Limits {
    Config::parse_from(std::iter::once("c4g-server").chain(SETTINGS)).limits()
}

/// An internal error is a bug; every other refusal is an answer.
fn judge(result: Result<(), ServiceError>) -> Result<(), String> {
    match result {
        Err(e) if e.kind() == ServiceErrorKind::Internal => Err(e.to_string()),
        _ => Ok(()),
    }
}

/// An upload as the image intake reads it. The input is `[n][n bytes of options JSON][media]`:
/// options that are not valid JSON for [`IntakeOptions`] are left at their defaults.
pub fn upload(input: &[u8]) -> Result<(), String> {
    let Some((&n, rest)) = input.split_first() else {
        return Ok(());
    };
    let (options, data) = rest.split_at(usize::from(n).min(rest.len()));
    let options: IntakeOptions = serde_json::from_slice(options).unwrap_or_default();
    let limits = limits();
    let kind = sniff::sniff(data);
    judge(validate_options(&options, &limits).and_then(|()| {
        match kind {
            MediaKind::Zip | MediaKind::Tar | MediaKind::Image => {
                let media = Media::File {
                    data: Bytes::copy_from_slice(data),
                    kind: None,
                };
                // A few small kept frames, so the fuzzer reaches their path too.
                let keep = c4g_service::clips::intake::kept::Keep { count: 4, side: 16 };
                images::read(media, kind, &options, &limits, keep).map(drop)
            }
            // FFmpeg's to read, in a child process.
            _ => Ok(()),
        }
    }))
}

/// The server's router over a real model and store, with one clip uploaded.
pub struct Edge {
    runtime: tokio::runtime::Runtime,
    router: Router,
    /// The uploaded clip's id (a content address: the same in every run).
    pub clip_id: String,
    _store: tempfile::TempDir,
}

/// The placeholder a fuzz input uses for the uploaded clip's id (in paths and gRPC messages).
pub const CLIP_MARK: &str = "@";

impl Edge {
    /// The edge, started once per process. The model is `C4G_FUZZ_MODEL` or the repository's
    /// `models/fixtures/c4g-small`; ONNX Runtime comes from `ORT_DYLIB_PATH`.
    pub fn get() -> &'static Edge {
        static EDGE: OnceLock<Edge> = OnceLock::new();
        EDGE.get_or_init(|| Edge::start().unwrap_or_else(|e| panic!("the fuzz edge: {e}")))
    }

    fn start() -> Result<Edge, String> {
        let model = std::env::var_os("C4G_FUZZ_MODEL").map_or_else(
            || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../models/fixtures/c4g-small"),
            PathBuf::from,
        );
        let store = tempfile::tempdir().map_err(|e| e.to_string())?;
        let (model, store_dir) = (model.to_string_lossy(), store.path().to_string_lossy());
        let args = ["c4g-server", "--model", &model, "--store-dir", &store_dir];
        let config = Config::parse_from(args.into_iter().chain(SETTINGS));
        let engine = Engine::load(&config.model, config.engine_options()).map_err(|e| {
            format!(
                "cannot load {}: {e} (is ORT_DYLIB_PATH set?)",
                config.model.display()
            )
        })?;
        let state = AppState::new(config.clone(), None);
        state.set_service(Service::new(engine, &config)?);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .map_err(|e| e.to_string())?;
        // The gRPC routes start tasks of their own (health): they are made inside the runtime.
        let router = {
            let _entered = runtime.enter();
            crate::router(state)
        };
        let mut edge = Edge {
            runtime,
            router,
            clip_id: String::new(),
            _store: store,
        };
        let (status, body) = edge.call(
            Method::POST,
            "/v1/clips?max_frames=4",
            "application/x-tar",
            seed_clip()?,
        );
        let clip: serde_json::Value = serde_json::from_slice(&body).map_err(|e| e.to_string())?;
        edge.clip_id = clip["id"]
            .as_str()
            .ok_or_else(|| format!("the seed upload answered {status}: {clip}"))?
            .to_owned();
        Ok(edge)
    }

    fn call(
        &self,
        method: Method,
        uri: &str,
        content_type: &str,
        body: Vec<u8>,
    ) -> (StatusCode, Bytes) {
        let Ok(uri) = uri.parse::<Uri>() else {
            return (StatusCode::BAD_REQUEST, Bytes::new());
        };
        let request = Request::builder()
            .method(method)
            .uri(uri)
            .header("content-type", content_type)
            .body(Body::from(body));
        let Ok(request) = request else {
            return (StatusCode::BAD_REQUEST, Bytes::new());
        };
        self.runtime.block_on(async {
            let Ok(response) = self.router.clone().oneshot(request).await;
            let status = response.status();
            let body = response.into_body().collect().await;
            (status, body.map(|b| b.to_bytes()).unwrap_or_default())
        })
    }

    /// A REST request: `input[0]` picks the route, the rest is its body (and for routes that
    /// take them, a path segment or query string before the first newline).
    pub fn rest(&self, input: &[u8]) -> Result<(), String> {
        let Some((&route, rest)) = input.split_first() else {
            return Ok(());
        };
        let (head, body) = match rest.iter().position(|&b| b == b'\n') {
            Some(i) => (&rest[..i], &rest[i + 1..]),
            None => (&rest[..0], rest),
        };
        let head = String::from_utf8_lossy(head).replace(CLIP_MARK, &self.clip_id);
        let id = &self.clip_id;
        // Routes 9 (export), 10 (tracks), 11 (camera recovery) and 12 (segment) came later;
        // every other byte picks among the first nine routes as it did before those came, so the
        // corpora keep their meaning.
        let route = if (9..=12).contains(&route) {
            route
        } else {
            route % 9
        };
        let (method, uri, content_type, body) = match route {
            0 => (
                Method::POST,
                format!("/v1/clips/{id}/gaussians"),
                "application/json",
                rest,
            ),
            1 => (
                Method::POST,
                format!("/v1/clips/{id}/render"),
                "application/json",
                rest,
            ),
            2 => (
                Method::POST,
                format!("/v1/clips/{id}/refine"),
                "application/json",
                rest,
            ),
            // An archive is read as one whatever its bytes: no FFmpeg for a fuzz input.
            3 => (
                Method::POST,
                format!("/v1/clips?{head}"),
                "application/x-tar",
                body,
            ),
            4 => (
                Method::GET,
                format!("/v1/clips/{id}/frames/{head}"),
                "",
                body,
            ),
            5 => (Method::GET, format!("/v1/clips/{head}"), "", body),
            6 => (Method::GET, format!("/v1/jobs?{head}"), "", body),
            8 => (
                Method::POST,
                format!("/v1/clips/{id}/stream"),
                "application/json",
                rest,
            ),
            9 => (
                Method::POST,
                format!("/v1/clips/{id}/export"),
                "application/json",
                rest,
            ),
            10 => (
                Method::POST,
                format!("/v1/clips/{id}/tracks"),
                "application/json",
                rest,
            ),
            11 => (
                Method::POST,
                format!("/v1/clips/{id}/cameras/recover"),
                "application/json",
                rest,
            ),
            12 => (
                Method::POST,
                format!("/v1/clips/{id}/segment"),
                "application/json",
                rest,
            ),
            _ => (Method::GET, format!("/v1/jobs/{head}"), "", body),
        };
        let (status, answer) = self.call(method, &uri, content_type, body.to_vec());
        if status == StatusCode::INTERNAL_SERVER_ERROR {
            return Err(format!(
                "{uri} answered 500: {}",
                String::from_utf8_lossy(&answer)
            ));
        }
        Ok(())
    }

    /// A gRPC request: `input[0]` picks the method, the rest is its message. A message that
    /// decodes as the method's request and names the clip [`CLIP_MARK`] is sent naming the
    /// uploaded clip; any other bytes are sent as they are.
    pub fn grpc(&self, input: &[u8]) -> Result<(), String> {
        use c4g_proto::v1 as pb;
        let Some((&method, message)) = input.split_first() else {
            return Ok(());
        };
        let id = self.clip_id.clone();
        let mark = |clip_id: &mut String| {
            if clip_id == CLIP_MARK {
                clip_id.clone_from(&id);
            }
        };
        fn patched<M: Message + Default>(bytes: &[u8], patch: impl FnOnce(&mut M)) -> Vec<u8> {
            match M::decode(bytes) {
                Ok(mut m) => {
                    patch(&mut m);
                    m.encode_to_vec()
                }
                Err(_) => bytes.to_vec(),
            }
        }
        // Methods 9 (Tracks), 10 (RecoverCameras) and 11 (Segment) came later; every other byte
        // picks as it did before them.
        let method = if (9..=11).contains(&method) {
            method
        } else {
            method % 9
        };
        let (path, message) = match method {
            0 => (
                "c4g.v1.C4G/GetClip",
                patched(message, |m: &mut pb::ClipRef| mark(&mut m.clip_id)),
            ),
            1 => ("c4g.v1.C4G/ListClips", message.to_vec()),
            2 => (
                "c4g.v1.C4G/Decode",
                patched(message, |m: &mut pb::DecodeRequest| mark(&mut m.clip_id)),
            ),
            3 => (
                "c4g.v1.C4G/StreamGaussians",
                patched(message, |m: &mut pb::StreamGaussiansRequest| {
                    mark(&mut m.clip_id)
                }),
            ),
            4 => (
                "c4g.v1.C4G/Render",
                patched(message, |m: &mut pb::RenderRequest| mark(&mut m.clip_id)),
            ),
            5 => (
                "c4g.v1.C4G/RenderTrajectory",
                patched(message, |m: &mut pb::RenderTrajectoryRequest| {
                    mark(&mut m.clip_id)
                }),
            ),
            6 => ("c4g.v1.C4G/ListModels", message.to_vec()),
            7 => ("c4g.v1.Jobs/Progress", message.to_vec()),
            9 => (
                "c4g.v1.C4G/Tracks",
                patched(message, |m: &mut pb::TracksRequest| mark(&mut m.clip_id)),
            ),
            10 => (
                "c4g.v1.C4G/RecoverCameras",
                patched(message, |m: &mut pb::RecoverCamerasRequest| {
                    mark(&mut m.clip_id)
                }),
            ),
            11 => (
                "c4g.v1.C4G/Segment",
                patched(message, |m: &mut pb::SegmentRequest| mark(&mut m.clip_id)),
            ),
            _ => ("c4g.v1.Jobs/Fail", message.to_vec()),
        };
        let mut framed = Vec::with_capacity(message.len() + 5);
        framed.push(0);
        framed.extend_from_slice(
            &u32::try_from(message.len())
                .unwrap_or(u32::MAX)
                .to_be_bytes(),
        );
        framed.extend_from_slice(&message);
        let request = Request::builder()
            .method(Method::POST)
            .uri(format!("/{path}"))
            .header("content-type", "application/grpc")
            .header("te", "trailers")
            .body(Body::from(framed))
            .map_err(|e| e.to_string())?;
        let status = self.runtime.block_on(async {
            let Ok(response) = self.router.clone().oneshot(request).await;
            let headers = response.headers().clone();
            let collected = response.into_body().collect().await.ok();
            let trailers = collected.as_ref().and_then(|c| c.trailers()).cloned();
            let status = |map: Option<&axum::http::HeaderMap>| {
                map.and_then(|m| m.get("grpc-status"))
                    .and_then(|v| v.to_str().ok().map(str::to_owned))
            };
            let message = |map: Option<&axum::http::HeaderMap>| {
                map.and_then(|m| m.get("grpc-message"))
                    .and_then(|v| v.to_str().ok().map(str::to_owned))
            };
            status(trailers.as_ref())
                .zip(message(trailers.as_ref()).or(Some(String::new())))
                .or_else(|| {
                    status(Some(&headers)).zip(message(Some(&headers)).or(Some(String::new())))
                })
        });
        match status {
            // INTERNAL and UNKNOWN are the server's failures; every other code is an answer.
            Some((code, message)) if code == "13" || code == "2" => {
                Err(format!("{path} answered gRPC status {code}: {message}"))
            }
            _ => Ok(()),
        }
    }
}

/// Four 32 x 32 PNG frames in a tar: the clip every edge input is about.
fn seed_clip() -> Result<Vec<u8>, String> {
    let mut archive = tar::Builder::new(Vec::new());
    for i in 0..4u8 {
        let frame = image::RgbImage::from_fn(32, 32, |x, y| {
            image::Rgb([(x * 8) as u8, (y * 8) as u8, i.wrapping_mul(60)])
        });
        let mut png = Vec::new();
        frame
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .map_err(|e| e.to_string())?;
        let mut header = tar::Header::new_gnu();
        header.set_size(png.len() as u64);
        header.set_mode(0o644);
        header.set_cksum();
        archive
            .append_data(&mut header, format!("frame{i}.png"), png.as_slice())
            .map_err(|e| e.to_string())?;
    }
    archive.into_inner().map_err(|e| e.to_string())
}
