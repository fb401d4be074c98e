//! Bad input, each with its expected status, kind and message, against a live `c4g-server`;
//! after each the server must still serve the next request (a decode of a good clip).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::io::{Cursor, Write};

use c4g_e2e::{Server, expect_error, frames_form, ort_available, shared_data, synthetic_clip};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use reqwest::blocking::Client;
use serde_json::{Value, json};

/// The server still answers, and still decodes a good clip.
fn still_serves(server: &mut Server, client: &Client, good: &str) {
    assert!(server.alive(), "the server process died");
    assert_eq!(
        client.get(server.at("/ready")).send().unwrap().status(),
        200
    );
    let decoded = client
        .post(server.at(&format!("/v1/clips/{good}/gaussians")))
        .json(&json!({"t": 0.3}))
        .send()
        .unwrap();
    assert_eq!(decoded.status(), 200);
}

fn png(width: u32, height: u32) -> Vec<u8> {
    let mut bytes = Vec::new();
    image::RgbImage::from_pixel(width, height, image::Rgb([90, 120, 200]))
        .write_to(&mut Cursor::new(&mut bytes), image::ImageFormat::Png)
        .unwrap();
    bytes
}

/// A PNG whose header says `width` × `height` (valid signature and IHDR, an empty IDAT): what an
/// attacker sends to make a server allocate gigabytes.
fn png_header_only(width: u32, height: u32) -> Vec<u8> {
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend_from_slice(&width.to_be_bytes());
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    out.extend_from_slice(&13u32.to_be_bytes());
    out.extend_from_slice(&ihdr);
    out.extend_from_slice(&crc32fast::hash(&ihdr).to_be_bytes());
    for chunk in [b"IDAT", b"IEND"] {
        out.extend_from_slice(&[0, 0, 0, 0]);
        out.extend_from_slice(chunk);
        out.extend_from_slice(&crc32fast::hash(chunk).to_be_bytes());
    }
    out
}

fn zip_of(entries: impl IntoIterator<Item = (String, Vec<u8>)>) -> Vec<u8> {
    let mut writer = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .large_file(true);
    for (name, data) in entries {
        writer.start_file(name, options).unwrap();
        writer.write_all(&data).unwrap();
    }
    writer.finish().unwrap().into_inner()
}

fn multipart_frames(frames: Vec<Vec<u8>>) -> reqwest::blocking::multipart::Form {
    frames.into_iter().enumerate().fold(
        reqwest::blocking::multipart::Form::new(),
        |form, (i, bytes)| {
            form.part(
                "frame",
                reqwest::blocking::multipart::Part::bytes(bytes).file_name(format!("{i}.png")),
            )
        },
    )
}

fn upload_good(server: &Server, client: &Client) -> String {
    let (frames, times) = synthetic_clip();
    let response = client
        .post(server.at("/v1/clips"))
        .multipart(frames_form(&frames, &times))
        .send()
        .unwrap();
    assert!(response.status().is_success());
    response.json::<Value>().unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned()
}

#[test]
fn bad_uploads_and_requests_get_clear_errors_and_the_server_keeps_serving() {
    if !ort_available() {
        return;
    }
    let mut server = Server::start(&["--max-source-frames", "5000"]);
    let client = Client::new();
    let good = upload_good(&server, &client);
    let clips = server.at("/v1/clips");
    let post = |body: Vec<u8>| client.post(&clips).body(body).send().unwrap();

    expect_error(
        post(Vec::new()),
        400,
        "invalid_input",
        "the upload is empty",
    );
    still_serves(&mut server, &client, &good);

    expect_error(
        post(b"this is a text file, whatever its name says\n".repeat(20)),
        415,
        "unsupported_media",
        "not a video",
    );
    still_serves(&mut server, &client, &good);

    if let Some(data) = shared_data() {
        let video = std::fs::read(data.join("bedroom/bedroom.mp4")).unwrap();
        expect_error(
            post(video[..video.len() / 3].to_vec()),
            422,
            "unreadable_media",
            "truncated or corrupt",
        );
        still_serves(&mut server, &client, &good);
    }

    // 64 MiB of zeros in a few dozen KiB: refused from the archive's own numbers, unexpanded.
    let bomb = zip_of([("frame-000.png".to_owned(), vec![0u8; 64 << 20])]);
    assert!(bomb.len() < 1 << 20);
    expect_error(post(bomb), 413, "too_large", "decompression bomb");
    still_serves(&mut server, &client, &good);

    let one_frame = png(16, 16);
    let many = zip_of((0..100_000).map(|i| (format!("{i:06}.png"), one_frame.clone())));
    expect_error(post(many), 413, "too_large", "100000 frames");
    still_serves(&mut server, &client, &good);

    let tiny = client
        .post(&clips)
        .multipart(multipart_frames(vec![png(1, 1), png(1, 1)]))
        .send()
        .unwrap();
    expect_error(tiny, 422, "unreadable_media", "at least 16 pixels");
    still_serves(&mut server, &client, &good);

    let huge = client
        .post(&clips)
        .multipart(multipart_frames(vec![png_header_only(20_000, 20_000)]))
        .send()
        .unwrap();
    expect_error(huge, 413, "too_large", "20000x20000");
    still_serves(&mut server, &client, &good);

    let mixed = client
        .post(&clips)
        .multipart(multipart_frames(vec![png(64, 64), png(32, 32)]))
        .send()
        .unwrap();
    expect_error(mixed, 422, "unreadable_media", "frames differ in size");
    still_serves(&mut server, &client, &good);

    let nan_stamps = client
        .post(format!("{clips}?timestamps=0,NaN"))
        .multipart(multipart_frames(vec![png(64, 64), png(64, 64)]))
        .send()
        .unwrap();
    expect_error(
        nan_stamps,
        400,
        "invalid_input",
        "timestamps must be finite",
    );
    still_serves(&mut server, &client, &good);

    let gaussians = server.at(&format!("/v1/clips/{good}/gaussians"));
    let nan = client
        .post(&gaussians)
        .header("content-type", "application/json")
        .body(r#"{"t": NaN}"#)
        .send()
        .unwrap();
    expect_error(nan, 400, "invalid_input", "JSON body is not valid");
    let late = client
        .post(&gaussians)
        .json(&json!({"t": 0.61}))
        .send()
        .unwrap();
    expect_error(
        late,
        400,
        "invalid_input",
        "outside the clip's context span [0, 0.6]",
    );
    let early = client
        .post(&gaussians)
        .json(&json!({"times": [0.1, -0.01]}))
        .send()
        .unwrap();
    expect_error(
        early,
        400,
        "invalid_input",
        "outside the clip's context span",
    );
    still_serves(&mut server, &client, &good);

    let unknown = client
        .post(server.at("/v1/clips/0123456789abcdef01234567/gaussians"))
        .json(&json!({"t": 0.1}))
        .send()
        .unwrap();
    expect_error(unknown, 404, "not_found", "no clip");
    let render = server.at(&format!("/v1/clips/{good}/render"));
    let near = client
        .post(&render)
        .json(&json!({"t": 0.3, "camera": {"world_to_camera": [1,0,0,0, 0,1,0,0, 0,0,1,-1.999, 0,0,0,1]}}))
        .send()
        .unwrap();
    assert_eq!(
        near.status(),
        200,
        "a camera at the scene's near plane still renders"
    );
    let enormous = client
        .post(&render)
        .json(&json!({"t": 0.3, "width": 20000, "height": 20000}))
        .send()
        .unwrap();
    expect_error(enormous, 413, "too_large", "20000x20000");
    let one_pixel = client
        .post(&render)
        .json(&json!({"t": 0.3, "width": 1, "height": 1}))
        .send()
        .unwrap();
    assert_eq!(one_pixel.status(), 200);
    still_serves(&mut server, &client, &good);
}

#[test]
fn api_keys_and_grpc_limits_are_enforced_and_the_server_keeps_serving() {
    if !ort_available() {
        return;
    }
    let mut server = Server::start(&["--api-key", "open sesame", "--max-grpc-message-mib", "1"]);
    let client = Client::new();
    let (frames, times) = synthetic_clip();
    // Without the key, or with another: 401 with a message that says what to send.
    let bare = client.get(server.at("/v1/clips")).send().unwrap();
    expect_error(bare, 401, "unauthorized", "Authorization: Bearer");
    let wrong = client
        .get(server.at("/v1/clips"))
        .bearer_auth("open sesam")
        .send()
        .unwrap();
    expect_error(wrong, 401, "unauthorized", "API key");
    // Health, readiness and metrics stay open.
    assert_eq!(
        client.get(server.at("/ready")).send().unwrap().status(),
        200
    );
    assert_eq!(
        client.get(server.at("/metrics")).send().unwrap().status(),
        200
    );
    let clip: Value = client
        .post(server.at("/v1/clips"))
        .bearer_auth("open sesame")
        .multipart(frames_form(&frames, &times))
        .send()
        .unwrap()
        .json()
        .unwrap();
    let id = clip["id"].as_str().unwrap().to_owned();

    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let request = || pb::DecodeRequest {
            clip_id: id.clone(),
            times: vec![0.3],
            precision: 0,
            keyframes: None,
            quality: 0,
            prune: None,
            features: false,
            scene: String::new(),
        };
        let refused = grpc.decode(request()).await.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{refused:?}");

        let mut authorised = tonic::Request::new(request());
        authorised
            .metadata_mut()
            .insert("authorization", "Bearer open sesame".parse().unwrap());
        assert_eq!(
            grpc.decode(authorised)
                .await
                .unwrap()
                .into_inner()
                .frames
                .len(),
            1
        );

        // 200k times are 1.6 MB on the wire: over the 1 MiB message limit.
        let mut oversized = tonic::Request::new(pb::DecodeRequest {
            clip_id: id.clone(),
            times: vec![0.3; 200_000],
            precision: 0,
            keyframes: None,
            quality: 0,
            prune: None,
            features: false,
            scene: String::new(),
        });
        oversized
            .metadata_mut()
            .insert("authorization", "Bearer open sesame".parse().unwrap());
        let refused = grpc.decode(oversized).await.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::OutOfRange, "{refused:?}");
        assert!(
            refused.message().contains("message length too large"),
            "{refused:?}"
        );

        let mut after = tonic::Request::new(request());
        after
            .metadata_mut()
            .insert("authorization", "Bearer open sesame".parse().unwrap());
        assert_eq!(
            grpc.decode(after).await.unwrap().into_inner().frames.len(),
            1
        );
    });
    assert!(server.alive());
}

#[test]
fn a_full_work_queue_is_refused_over_rest_and_grpc_with_its_kind_and_the_old_setting_names_work() {
    if !ort_available() {
        return;
    }
    // The old name of C4G_MAX_QUEUED_WORK; a queue of 0 refuses every decode and render at once,
    // while uploads (which take encode slots, not work slots) still go through.
    let mut server = Server::start_env(&[("C4G_MAX_QUEUED_JOBS", "0")], &[]);
    let client = Client::new();
    let (frames, times) = synthetic_clip();
    let clip: Value = client
        .post(server.at("/v1/clips"))
        .multipart(frames_form(&frames, &times))
        .send()
        .unwrap()
        .json()
        .unwrap();
    let id = clip["id"].as_str().unwrap().to_owned();
    let refused = client
        .post(server.at(&format!("/v1/clips/{id}/gaussians")))
        .json(&json!({"t": 0.3}))
        .send()
        .unwrap();
    assert!(refused.headers().contains_key("retry-after"));
    expect_error(refused, 503, "overloaded", "overloaded");

    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let refused = grpc
            .decode(pb::DecodeRequest {
                clip_id: id.clone(),
                times: vec![0.3],
                precision: 0,
                keyframes: None,
                quality: 0,
                prune: None,
                features: false,
                scene: String::new(),
            })
            .await
            .unwrap_err();
        assert_eq!(refused.code(), tonic::Code::Unavailable, "{refused:?}");
        assert_eq!(
            refused.metadata().get("c4g-error-kind").unwrap(),
            "overloaded"
        );
        assert!(
            refused.metadata().get("retry-after").is_some(),
            "{refused:?}"
        );
        // A refusal the gRPC handler itself makes carries its kind too.
        let bad = grpc
            .render(pb::RenderRequest {
                clip_id: id.clone(),
                time: 0.3,
                background: vec![0.0, 1.0],
                ..Default::default()
            })
            .await
            .unwrap_err();
        assert_eq!(bad.code(), tonic::Code::InvalidArgument, "{bad:?}");
        assert_eq!(
            bad.metadata().get("c4g-error-kind").unwrap(),
            "invalid_input"
        );
        assert!(
            bad.message().contains("background needs 3 values"),
            "{bad:?}"
        );
        let missing = grpc
            .get_clip(pb::ClipRef {
                clip_id: "no-such-clip".into(),
            })
            .await
            .unwrap_err();
        assert_eq!(missing.code(), tonic::Code::NotFound);
        assert_eq!(
            missing.metadata().get("c4g-error-kind").unwrap(),
            "not_found"
        );
    });
    assert!(server.alive());
}

/// Bytes that are not the method's request message: a field of `DecodeRequest` (times, doubles)
/// sent as a varint.
#[derive(Clone, PartialEq, prost::Message)]
struct NotADecodeRequest {
    #[prost(uint64, tag = "2")]
    times: u64,
}

#[test]
fn a_grpc_message_that_does_not_decode_is_invalid_argument_and_says_so() {
    if !ort_available() {
        return;
    }
    let mut server = Server::start(&[]);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let channel = tonic::transport::Channel::from_shared(server.url())
            .unwrap()
            .connect()
            .await
            .unwrap();
        let mut grpc = tonic::client::Grpc::new(channel);
        grpc.ready().await.unwrap();
        let refused = grpc
            .unary(
                tonic::Request::new(NotADecodeRequest { times: 7 }),
                tonic::codegen::http::uri::PathAndQuery::from_static("/c4g.v1.C4G/Decode"),
                tonic_prost::ProstCodec::<NotADecodeRequest, pb::DecodeResponse>::default(),
            )
            .await
            .unwrap_err();
        // gRPC's own table says INTERNAL; ours says it is the caller's to fix (proto/src/codec.rs).
        assert_eq!(refused.code(), tonic::Code::InvalidArgument, "{refused:?}");
        assert!(
            refused.message().contains("not a valid protobuf"),
            "{refused:?}"
        );
    });
    assert!(server.alive());
}
