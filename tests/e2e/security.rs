//! Hostile requests against a live `c4g-server`, each refused with its kind and the server still
//! serving after: archive entries that name paths outside the archive or are links,
//! decompression bombs (zip entries, PNG headers), clip and job ids that try to leave the store,
//! JSON nested too deep, bodies and headers over their limits on REST and gRPC, and API keys
//! (checked on both transports, never written to the log).
//!
//! The pure parts have unit tests beside the code: archive names and links, bomb ratios and
//! bounded reads (`service/src/clips/intake/images.rs`), JSON depth and nulls, id shapes
//! (`server/src/api/json.rs`), the key comparison (`server/src/auth.rs`).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::io::{BufRead, BufReader, Cursor, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use c4g_e2e::health::{HealthClient, pb_health};
use c4g_e2e::{Server, binary, expect_error, ort_available, upload_synthetic, workspace};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use reqwest::blocking::{Client, Response};
use serde_json::{Value, json};

/// The server still answers and still decodes the good clip.
fn still_serves(server: &mut Server, client: &Client, good: &str) {
    assert!(server.alive(), "the server process died");
    let decoded = client
        .post(server.at(&format!("/v1/clips/{good}/gaussians")))
        .json(&json!({"t": 0.3}))
        .send()
        .unwrap();
    assert_eq!(decoded.status(), 200);
}

/// An upload of `body` as `content_type`.
fn post(client: &Client, server: &Server, body: Vec<u8>, content_type: &str) -> Response {
    client
        .post(server.at("/v1/clips"))
        .header("content-type", content_type)
        .body(body)
        .send()
        .unwrap()
}

/// One HTTP/1.1 request sent byte for byte (clients normalise `..` and `%2e%2e` away), and the
/// status and body of the answer.
fn raw(addr: SocketAddr, request: &[u8]) -> (u16, String) {
    let mut stream = TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    // The server may answer (and close) before it has read everything: that is the point.
    let _ = stream.write_all(request);
    let mut answer = Vec::new();
    let _ = stream.read_to_end(&mut answer);
    let text = String::from_utf8_lossy(&answer).into_owned();
    let status = text
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no HTTP answer: {text:?}"));
    let body = text
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_owned())
        .unwrap_or_default();
    (status, body)
}

fn request_line(method: &str, path: &str) -> Vec<u8> {
    format!("{method} {path} HTTP/1.1\r\nHost: c4g\r\nConnection: close\r\n\r\n").into_bytes()
}

fn png(width: u32, height: u32) -> Vec<u8> {
    let mut bytes = Vec::new();
    image::RgbImage::from_pixel(width, height, image::Rgb([90, 120, 200]))
        .write_to(&mut Cursor::new(&mut bytes), image::ImageFormat::Png)
        .unwrap();
    bytes
}

/// A real PNG whose header is rewritten to say `width` x `height`.
fn png_claiming(width: u32, height: u32) -> Vec<u8> {
    let mut bytes = png(16, 16);
    bytes[16..20].copy_from_slice(&width.to_be_bytes());
    bytes[20..24].copy_from_slice(&height.to_be_bytes());
    let crc = crc32fast::hash(&bytes[12..29]);
    bytes[29..33].copy_from_slice(&crc.to_be_bytes());
    bytes
}

fn zip_of(entries: &[(&str, &[u8])]) -> Vec<u8> {
    let mut writer = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    for (name, data) in entries {
        writer.start_file(*name, options).unwrap();
        writer.write_all(data).unwrap();
    }
    writer.finish().unwrap().into_inner()
}

/// A tar entry's type flag.
#[derive(Clone, Copy, Debug)]
enum Entry {
    File,
    HardLink,
    Symlink,
}

/// A ustar archive written header by header (the `tar` crate's builder refuses the names this
/// test needs): (name, type, data, link target) per entry.
fn tar_of(entries: &[(&str, Entry, &[u8], &str)]) -> Vec<u8> {
    let mut out = Vec::new();
    for (name, kind, data, link) in entries {
        let mut header = [0u8; 512];
        header[..name.len()].copy_from_slice(name.as_bytes());
        header[100..108].copy_from_slice(b"0000644\0");
        header[108..116].copy_from_slice(b"0000000\0");
        header[116..124].copy_from_slice(b"0000000\0");
        header[124..136].copy_from_slice(format!("{:011o}\0", data.len()).as_bytes());
        header[136..148].copy_from_slice(b"00000000000\0");
        header[156] = match kind {
            Entry::File => b'0',
            Entry::HardLink => b'1',
            Entry::Symlink => b'2',
        };
        header[157..157 + link.len()].copy_from_slice(link.as_bytes());
        header[257..265].copy_from_slice(b"ustar\x0000");
        // The checksum is the byte sum with its own field read as spaces.
        header[148..156].fill(b' ');
        let sum: u32 = header.iter().map(|&b| u32::from(b)).sum();
        header[148..156].copy_from_slice(format!("{sum:06o}\0 ").as_bytes());
        out.extend_from_slice(&header);
        out.extend_from_slice(data);
        out.resize(out.len().div_ceil(512) * 512, 0);
    }
    out.resize(out.len() + 1024, 0);
    out
}

/// Every file under `dir`, recursively.
fn files_under(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let path = entry.path();
        if path.is_dir() {
            out.extend(files_under(&path));
        } else {
            out.push(path);
        }
    }
    out
}

#[test]
fn archive_entries_that_escape_the_archive_or_are_links_are_refused_and_nothing_is_written() {
    if !ort_available() {
        return;
    }
    let parent = tempfile::tempdir().unwrap();
    let store = tempfile::tempdir_in(parent.path()).unwrap();
    let store_path = store.path().to_path_buf();
    let mut server = Server::start_in(store, &[]);
    let client = Client::new();
    let good = upload_synthetic(&server);
    let before = files_under(&store_path);
    let frame = png(64, 64);
    let file = Entry::File;

    for name in [
        "../../escaped.png",
        "frames/../../../escaped.png",
        "/tmp/escaped.png",
    ] {
        let zip = zip_of(&[("000.png", &frame), (name, &frame)]);
        expect_error(
            post(&client, &server, zip, "application/zip"),
            422,
            "unreadable_media",
            "names a path outside the archive",
        );
        let tar = tar_of(&[("000.png", file, &frame, ""), (name, file, &frame, "")]);
        expect_error(
            post(&client, &server, tar, "application/x-tar"),
            422,
            "unreadable_media",
            "names a path outside the archive",
        );
    }
    still_serves(&mut server, &client, &good);

    for kind in [Entry::Symlink, Entry::HardLink] {
        let tar = tar_of(&[
            ("000.png", file, &frame, ""),
            ("001.png", kind, b"", "/etc/passwd"),
        ]);
        expect_error(
            post(&client, &server, tar, "application/x-tar"),
            422,
            "unreadable_media",
            "is a link",
        );
    }
    let mut writer = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default();
    writer.start_file("000.png", options).unwrap();
    writer.write_all(&frame).unwrap();
    writer
        .add_symlink("001.png", "/etc/passwd", options)
        .unwrap();
    let zip = writer.finish().unwrap().into_inner();
    expect_error(
        post(&client, &server, zip, "application/zip"),
        422,
        "unreadable_media",
        "is a link",
    );
    still_serves(&mut server, &client, &good);

    // Nothing was written anywhere: not beside the store, not in it, not in the working directory.
    assert_eq!(files_under(&store_path), before);
    let escaped: Vec<_> = files_under(parent.path())
        .into_iter()
        .filter(|p| p.file_name().is_some_and(|n| n == "escaped.png"))
        .collect();
    assert!(escaped.is_empty(), "{escaped:?}");
    assert!(!workspace().join("escaped.png").exists());
    assert!(!Path::new("/tmp/escaped.png").exists());
}

#[test]
fn decompression_bombs_are_refused_from_their_own_numbers_and_lies_are_read_only_as_far_as_they_say()
 {
    if !ort_available() {
        return;
    }
    let mut server = Server::start(&[]);
    let client = Client::new();
    let good = upload_synthetic(&server);

    // 64 MiB of zeros in one entry: refused from the archive's numbers, never inflated.
    let zeros = vec![0u8; 64 << 20];
    let bomb = zip_of(&[("000.png", &zeros)]);
    assert!(bomb.len() < 1 << 20);
    expect_error(
        post(&client, &server, bomb.clone(), "application/zip"),
        413,
        "too_large",
        "decompression bomb",
    );
    still_serves(&mut server, &client, &good);

    // The same entry declaring 1000 bytes (in both of its headers): it passes the ratio check and
    // 1000 bytes are read, which are no PNG.
    let mut liar = bomb;
    liar[22..26].copy_from_slice(&1000u32.to_le_bytes());
    let central = liar.windows(4).position(|w| w == b"PK\x01\x02").unwrap();
    liar[central + 24..central + 28].copy_from_slice(&1000u32.to_le_bytes());
    let answer = post(&client, &server, liar, "application/zip");
    assert_eq!(answer.status(), 422, "{}", answer.text().unwrap());
    still_serves(&mut server, &client, &good);

    // A PNG whose header claims 10 gigapixels: refused from the header, alone or in an archive.
    let claims = png_claiming(100_000, 100_000);
    expect_error(
        post(&client, &server, claims.clone(), "application/octet-stream"),
        413,
        "too_large",
        "100000x100000",
    );
    let archive = zip_of(&[("000.png", &png(64, 64)), ("001.png", &claims)]);
    expect_error(
        post(&client, &server, archive, "application/zip"),
        413,
        "too_large",
        "100000x100000",
    );
    let frames = reqwest::blocking::multipart::Form::new().part(
        "frame",
        reqwest::blocking::multipart::Part::bytes(claims).file_name("0.png"),
    );
    expect_error(
        client
            .post(server.at("/v1/clips"))
            .multipart(frames)
            .send()
            .unwrap(),
        413,
        "too_large",
        "100000x100000",
    );
    still_serves(&mut server, &client, &good);
}

#[test]
fn clip_and_job_ids_that_try_to_leave_the_store_name_nothing_and_touch_nothing() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    let root = store.path().to_path_buf();
    let mut server = Server::start_in(store, &[]);
    let client = Client::new();
    let good = upload_synthetic(&server);
    // Files a traversal would reach: beside the clips, in the store's root, and the good clip's.
    let models: Value = client
        .get(server.at("/v1/models"))
        .send()
        .unwrap()
        .json()
        .unwrap();
    let key = models["models"][0]["store_key"].as_str().unwrap();
    let canaries = [root.join("canary"), root.join(key).join("canary")];
    for canary in &canaries {
        std::fs::write(canary, b"still here").unwrap();
    }
    let clip_json = root.join(key).join("clips").join(&good).join("clip.json");
    assert!(clip_json.exists());

    let attempts = [
        "/v1/clips/..%2Fcanary".to_owned(),
        "/v1/clips/..%2F..%2Fcanary".to_owned(),
        "/v1/clips/%2e%2e".to_owned(),
        "/v1/clips/%2E%2E%2F%2E%2E%2Fcanary".to_owned(),
        "/v1/clips/..%5C..%5Ccanary".to_owned(),
        format!("/v1/clips/{good}%2F..%2F..%2Fcanary"),
        format!("/v1/clips/{good}%00"),
        format!("/v1/clips/{}", good.to_uppercase()),
        "/v1/clips/%2Fetc%2Fpasswd".to_owned(),
    ];
    for path in &attempts {
        for method in ["GET", "DELETE"] {
            let (status, body) = raw(server.addr, &request_line(method, path));
            assert_eq!(status, 404, "{method} {path}: {body}");
            let error: Value = serde_json::from_str(&body).unwrap();
            assert_eq!(error["kind"], "not_found", "{method} {path}: {body}");
        }
        let (status, _) = raw(
            server.addr,
            &request_line("GET", &format!("{path}/frames/0")),
        );
        assert_eq!(status, 404, "{path}/frames/0");
    }
    for path in [
        format!("/v1/clips/{good}/frames/..%2F..%2Fclip.json"),
        format!("/v1/clips/{good}/frames/-1"),
        format!("/v1/clips/{good}/frames/%2e%2e"),
        format!("/v1/clips/{good}/frames/99999999999999999999999"),
    ] {
        let (status, body) = raw(server.addr, &request_line("GET", &path));
        assert_eq!(status, 404, "{path}: {body}");
        assert!(
            !body.contains("\"context_times\""),
            "{path} read clip.json: {body}"
        );
    }
    for path in [
        "/v1/jobs/..%2F..%2Fcanary",
        "/v1/jobs/job-..%2F..%2Fcanary",
        "/v1/jobs/%2e%2e/result",
        "/v1/jobs/..%2Fcanary/events",
    ] {
        let (status, body) = raw(server.addr, &request_line("GET", path));
        assert_eq!(status, 404, "{path}: {body}");
        let (status, body) = raw(
            server.addr,
            &request_line("POST", &format!("{path}/cancel")),
        );
        assert!(status == 404, "{path}/cancel: {status} {body}");
    }
    for canary in &canaries {
        assert_eq!(std::fs::read(canary).unwrap(), b"still here");
    }
    assert!(clip_json.exists());
    assert_eq!(
        client
            .get(server.at(&format!("/v1/clips/{good}")))
            .send()
            .unwrap()
            .status(),
        200
    );
    still_serves(&mut server, &client, &good);
}

#[test]
fn json_depth_body_and_header_limits_hold_on_rest_and_grpc() {
    if !ort_available() {
        return;
    }
    let mut server = Server::start(&["--max-body-mib", "1", "--max-grpc-message-mib", "1"]);
    let client = Client::new();
    let good = upload_synthetic(&server);
    let gaussians = server.at(&format!("/v1/clips/{good}/gaussians"));
    let post_json = |body: String| {
        client
            .post(&gaussians)
            .header("content-type", "application/json")
            .body(body)
            .send()
            .unwrap()
    };

    // Nesting: 17 levels is refused by the service's own limit, 100,000 by the parser's; neither
    // reaches a handler, and neither overflows a stack.
    let deep = format!(
        "{{\"t\": 0.3, \"keyframes\": {}{}}}",
        "[".repeat(16),
        "]".repeat(16)
    );
    expect_error(
        post_json(deep),
        400,
        "invalid_input",
        "nests deeper than 16",
    );
    let abyss = format!(
        "{{\"t\": 0.3, \"x\": {}{}}}",
        "[".repeat(100_000),
        "]".repeat(100_000)
    );
    expect_error(
        post_json(abyss),
        400,
        "invalid_input",
        "JSON body is not valid",
    );
    expect_error(
        post_json(r#"{"t": 0.3, "times": null}"#.into()),
        400,
        "invalid_input",
        "null at /times",
    );
    still_serves(&mut server, &client, &good);

    // Bodies: JSON over 2 MiB, uploads over C4G_MAX_BODY_MIB (raw and multipart). Each one
    // byte over, so the server has read every byte when it refuses (a client still sending when
    // the server answers and closes may see a reset instead of the answer), and each on a
    // connection of its own (the server closes one whose body it did not take).
    let fresh = || Client::builder().pool_max_idle_per_host(0).build().unwrap();
    let mut json_body = b"{\"times\": [0.3".to_vec();
    json_body.resize((2 << 20) + 1 - 2, b' ');
    json_body.extend_from_slice(b"]}");
    expect_error(
        fresh()
            .post(&gaussians)
            .header("content-type", "application/json")
            .body(json_body)
            .send()
            .unwrap(),
        413,
        "too_large",
        "JSON body is over",
    );
    let limit = 1 << 20;
    expect_error(
        fresh()
            .post(server.at("/v1/clips"))
            .body(vec![7u8; limit + 1])
            .send()
            .unwrap(),
        413,
        "too_large",
        "C4G_MAX_BODY_MIB",
    );
    let head =
        b"--b\r\nContent-Disposition: form-data; name=\"file\"; filename=\"clip.mp4\"\r\n\r\n";
    let tail = b"\r\n--b--\r\n";
    let mut form = head.to_vec();
    form.resize(limit + 1 - tail.len(), 7);
    form.extend_from_slice(tail);
    expect_error(
        fresh()
            .post(server.at("/v1/clips"))
            .header("content-type", "multipart/form-data; boundary=b")
            .body(form)
            .send()
            .unwrap(),
        413,
        "too_large",
        "C4G_MAX_BODY_MIB",
    );
    still_serves(&mut server, &client, &good);

    // Headers (HTTP/1.1): more than 100, or more than hyper's buffer, is a 431.
    let mut many = b"GET /v1/clips HTTP/1.1\r\nHost: c4g\r\nConnection: close\r\n".to_vec();
    for i in 0..200 {
        many.extend_from_slice(format!("x-h{i}: v\r\n").as_bytes());
    }
    many.extend_from_slice(b"\r\n");
    assert_eq!(raw(server.addr, &many).0, 431);
    let mut long = b"GET /v1/clips HTTP/1.1\r\nHost: c4g\r\nConnection: close\r\nx-long: ".to_vec();
    long.extend(std::iter::repeat_n(b'a', 1 << 20));
    long.extend_from_slice(b"\r\n\r\n");
    assert_eq!(raw(server.addr, &long).0, 431);
    still_serves(&mut server, &client, &good);

    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        // A message over C4G_MAX_GRPC_MESSAGE_MIB.
        let chunk = |n: usize| pb::UploadRequest {
            part: Some(pb::upload_request::Part::Chunk(vec![7u8; n])),
        };
        let header = pb::UploadRequest {
            part: Some(pb::upload_request::Part::Header(pb::UploadHeader::default())),
        };
        let refused = grpc
            .upload(tokio_stream::iter(vec![header.clone(), chunk(2 << 20)]))
            .await
            .unwrap_err();
        assert_eq!(refused.code(), tonic::Code::OutOfRange, "{refused:?}");
        // Messages under it that add up to more than C4G_MAX_BODY_MIB.
        let mut parts = vec![header];
        parts.extend((0..3).map(|_| chunk(512 << 10)));
        let refused = grpc.upload(tokio_stream::iter(parts)).await.unwrap_err();
        assert_eq!(
            refused.code(),
            tonic::Code::ResourceExhausted,
            "{refused:?}"
        );
        assert!(
            refused.message().contains("C4G_MAX_BODY_MIB"),
            "{refused:?}"
        );
        // Metadata past HTTP/2's header list limit (16 KiB) never reaches a handler.
        let mut request = tonic::Request::new(pb::ClipRef {
            clip_id: good.clone(),
        });
        request
            .metadata_mut()
            .insert("x-long", "a".repeat(64 << 10).parse().unwrap());
        assert!(grpc.get_clip(request).await.is_err());
        // And the connection's service still answers.
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let clip = grpc
            .get_clip(pb::ClipRef {
                clip_id: good.clone(),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(clip.clip_id, good);
    });
    still_serves(&mut server, &client, &good);
}

/// `c4g-server` with an API key and every log line at `trace`, its log kept in `log`.
struct LoggedServer {
    child: std::process::Child,
    addr: SocketAddr,
    _store: tempfile::TempDir,
}

impl Drop for LoggedServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl LoggedServer {
    fn start(key: &str, log: &Path) -> LoggedServer {
        let store = tempfile::tempdir().unwrap();
        let mut child = Command::new(binary("c4g-server"))
            .current_dir(workspace())
            .env_remove("C4G_MODEL")
            .env("RUST_LOG", "trace")
            .env("C4G_API_KEY", key)
            .args(["--listen", "127.0.0.1:0", "--store-dir"])
            .arg(store.path())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let addr = line
            .trim()
            .strip_prefix("listening on ")
            .unwrap()
            .parse()
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(120);
        while Client::new()
            .get(format!("http://{addr}/ready"))
            .send()
            .map_or(true, |r| !r.status().is_success())
        {
            assert!(Instant::now() < deadline, "the server never became ready");
            std::thread::sleep(Duration::from_millis(100));
        }
        LoggedServer {
            child,
            addr,
            _store: store,
        }
    }
}

#[test]
fn api_keys_guard_both_transports_and_no_key_reaches_the_log() {
    if !ort_available() {
        return;
    }
    let key = "c4g-test-key-9f86d081884c7d65";
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("server.log");
    let server = LoggedServer::start(key, &log);
    let url = |path: &str| format!("http://{}{path}", server.addr);
    let client = Client::new();
    let status = |request: reqwest::blocking::RequestBuilder| request.send().unwrap().status();

    assert_eq!(status(client.get(url("/v1/clips")).bearer_auth(key)), 200);
    // The scheme is case-insensitive (RFC 9110 §11.1), the key is not.
    for scheme in ["bearer", "BEARER", "BeArEr"] {
        let header = format!("{scheme} {key}");
        assert_eq!(
            status(client.get(url("/v1/clips")).header("authorization", header)),
            200,
            "{scheme}"
        );
    }
    assert_eq!(
        status(client.get(url("/v1/clips")).header("x-api-key", key)),
        200
    );
    let near_misses = [
        key[..key.len() - 1].to_owned(),
        format!("{key}0"),
        key.to_uppercase(),
        String::new(),
    ];
    for wrong in &near_misses {
        assert_eq!(
            status(client.get(url("/v1/clips")).bearer_auth(wrong)),
            401,
            "{wrong:?}"
        );
        assert_eq!(
            status(client.get(url("/v1/clips")).header("x-api-key", wrong)),
            401,
            "{wrong:?}"
        );
    }
    assert_eq!(
        status(client.get(url("/v1/clips")).basic_auth(key, Some(key))),
        401
    );
    assert_eq!(status(client.get(url("/v1/clips"))), 401);
    // The open endpoints stay open, and the contract shows no key.
    assert_eq!(status(client.get(url("/ready"))), 200);
    let contract = client
        .get(url("/openapi.json"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    assert!(!contract.contains(key));

    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut grpc = C4gClient::connect(format!("http://{}", server.addr))
            .await
            .unwrap();
        let call = |value: Option<String>| {
            let mut request = tonic::Request::new(pb::ListClipsRequest {});
            if let Some(value) = value {
                request
                    .metadata_mut()
                    .insert("authorization", value.parse().unwrap());
            }
            request
        };
        assert!(
            grpc.list_clips(call(Some(format!("Bearer {key}"))))
                .await
                .is_ok()
        );
        for wrong in &near_misses {
            let refused = grpc
                .list_clips(call(Some(format!("Bearer {wrong}"))))
                .await
                .unwrap_err();
            assert_eq!(refused.code(), tonic::Code::Unauthenticated);
            assert!(!refused.message().contains(key));
        }
        let refused = grpc.list_clips(call(None)).await.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::Unauthenticated);
        assert!(
            grpc.list_clips(call(Some(format!("bearer {key}"))))
                .await
                .is_ok()
        );
        // Reflection, both versions, lists the services to the key holder and to no one else.
        let url = format!("http://{}", server.addr);
        let bearer = format!("Bearer {key}");
        for version in ["v1", "v1alpha"] {
            let listed = list_services(&url, version, Some(&bearer)).await.unwrap();
            for service in ["c4g.v1.C4G", "c4g.v1.Jobs", "grpc.health.v1.Health"] {
                assert!(listed.iter().any(|s| s == service), "{version}: {listed:?}");
            }
            let refused = list_services(&url, version, None).await.unwrap_err();
            assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{version}");
        }
        // Health is open to probes without the key; everything else on gRPC is not.
        let mut health = HealthClient::connect(&format!("http://{}", server.addr)).await;
        let serving = health
            .check(pb_health::HealthCheckRequest {
                service: "c4g.v1.C4G".into(),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(
            serving.status,
            pb_health::health_check_response::ServingStatus::Serving as i32
        );
    });
    drop(server);

    let log = std::fs::read_to_string(&log).unwrap();
    assert!(
        log.lines().count() > 20,
        "the server logged nothing at trace:\n{log}"
    );
    assert!(!log.contains(key), "the API key reached the log");
    assert!(
        !log.contains(&key[..key.len() - 1]),
        "a near miss of the key reached the log"
    );
}

/// The services reflection `version` ("v1" or "v1alpha") lists, asked with `authorization`.
async fn list_services(
    url: &str,
    version: &str,
    authorization: Option<&str>,
) -> Result<Vec<String>, tonic::Status> {
    let channel = tonic::transport::Endpoint::from_shared(url.to_owned())
        .unwrap()
        .connect()
        .await
        .unwrap();
    // The two versions are the same protocol under two package names.
    macro_rules! list {
        ($pb:path) => {{
            use $pb as pb;
            let ask = pb::ServerReflectionRequest {
                host: String::new(),
                message_request: Some(pb::server_reflection_request::MessageRequest::ListServices(
                    String::new(),
                )),
            };
            let mut request = tonic::Request::new(tokio_stream::iter([ask]));
            if let Some(value) = authorization {
                request
                    .metadata_mut()
                    .insert("authorization", value.parse().unwrap());
            }
            let mut client = pb::server_reflection_client::ServerReflectionClient::new(channel);
            let mut answers = client.server_reflection_info(request).await?.into_inner();
            match answers.message().await?.and_then(|a| a.message_response) {
                Some(pb::server_reflection_response::MessageResponse::ListServicesResponse(
                    list,
                )) => Ok(list.service.into_iter().map(|s| s.name).collect()),
                other => panic!("reflection {version} answered {other:?}"),
            }
        }};
    }
    match version {
        "v1" => list!(tonic_reflection::pb::v1),
        _ => list!(tonic_reflection::pb::v1alpha),
    }
}
