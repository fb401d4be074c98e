//! Replicas sharing their clips through object storage (`C4G_SHARED_STORE`,
//! `server/src/shared_clips.rs`): `c4g-server` processes with stores of their own and one shared
//! store, run twice: a directory (`file://`, `object_store`'s local backend), and an S3 bucket on
//! moto's S3-compatible server (`moto_server` from PyPI, on loopback: the `aws` backend with its
//! conditional puts, as against a real bucket).
//!
//! Checked: a clip uploaded to one replica is served by the other (fetched, decoded to the same
//! bytes); an upload of a clip another replica already has is not encoded again; two replicas
//! given the same new clip at once encode it once between them (the encode claim); a delete
//! removes the clip from the shared store, so a replica that never held it answers 404.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use c4g_e2e::{
    ServerProcess, frames_form, metric, missing, ort_available, synthetic_clip, venv_python,
};
use reqwest::blocking::Client;
use serde_json::{Value, json};

const ANY_PORT: &str = "127.0.0.1:0";

/// Where the replicas share clips: `C4G_SHARED_STORE` and the variables it needs.
struct Shared {
    env: Vec<(String, String)>,
}

fn replica(store: &Path, shared: &Shared) -> ServerProcess {
    let mut env: Vec<(&str, &str)> = shared
        .env
        .iter()
        .map(|(k, v)| (k.as_str(), v.as_str()))
        .collect();
    env.push(("RUST_LOG", "info"));
    let mut server = ServerProcess::spawn(store, ANY_PORT, &[], &env);
    server.wait_ready();
    server
}

/// moto's S3 server on a free loopback port, killed when dropped.
struct Moto(Child);

impl Drop for Moto {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// An S3 bucket on moto, or why there is none (skipped outside CI).
fn moto_bucket() -> Option<(Moto, Shared)> {
    let python = venv_python();
    let server = python.with_file_name("moto_server");
    if !server.is_file() {
        return missing("moto_server must be installed (scripts/setup: moto[server])");
    }
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let child = Command::new(&server)
        .args(["-H", "127.0.0.1", "-p", &port.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let moto = Moto(child);
    let endpoint = format!("http://127.0.0.1:{port}");
    let deadline = Instant::now() + Duration::from_secs(30);
    // The bucket, once moto answers.
    loop {
        if let Ok(r) = Client::new().put(format!("{endpoint}/c4g-clips")).send()
            && r.status().is_success()
        {
            break;
        }
        assert!(Instant::now() < deadline, "moto_server did not start");
        std::thread::sleep(Duration::from_millis(100));
    }
    let env = [
        ("C4G_SHARED_STORE", "s3://c4g-clips/cluster".to_owned()),
        ("AWS_ENDPOINT", endpoint),
        ("AWS_ALLOW_HTTP", "true".to_owned()),
        ("AWS_ACCESS_KEY_ID", "test".to_owned()),
        ("AWS_SECRET_ACCESS_KEY", "test".to_owned()),
        ("AWS_REGION", "us-east-1".to_owned()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_owned(), v))
    .collect();
    Some((moto, Shared { env }))
}

/// Uploads the synthetic clip with its times scaled by `scale` (another scale, another clip).
fn upload(server: &ServerProcess, scale: f64) -> (u16, Value) {
    let (frames, times) = synthetic_clip();
    let times: Vec<f64> = times.iter().map(|t| t * scale).collect();
    let response = Client::new()
        .post(server.at("/v1/clips"))
        .multipart(frames_form(&frames, &times))
        .send()
        .unwrap();
    let status = response.status().as_u16();
    (status, response.json().unwrap())
}

fn decode(server: &ServerProcess, id: &str) -> (u16, Vec<u8>) {
    let response = Client::new()
        .post(server.at(&format!("/v1/clips/{id}/gaussians")))
        .json(&json!({"times": [0.1, 0.3], "format": "binary"}))
        .send()
        .unwrap();
    (
        response.status().as_u16(),
        response.bytes().unwrap().to_vec(),
    )
}

fn encodes(server: &ServerProcess) -> f64 {
    let text = Client::new()
        .get(server.at("/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    metric(&text, "c4g_encode_duration_seconds_count")
}

#[test]
fn replicas_on_a_shared_directory_serve_each_other_s_clips_and_encode_each_once() {
    if !ort_available() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let url = format!("file://{}", dir.path().display());
    share_and_check(&Shared {
        env: vec![("C4G_SHARED_STORE".to_owned(), url)],
    });
}

#[test]
fn replicas_on_an_s3_bucket_serve_each_other_s_clips_and_encode_each_once() {
    if !ort_available() {
        return;
    }
    let Some((_moto, shared)) = moto_bucket() else {
        return;
    };
    share_and_check(&shared);
}

fn share_and_check(shared: &Shared) {
    let (store_a, store_b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let a = replica(store_a.path(), shared);
    let b = replica(store_b.path(), shared);

    // Uploaded to A, served by B.
    let (status, clip) = upload(&a, 1.0);
    assert_eq!(status, 201, "{clip}");
    let id = clip["id"].as_str().unwrap().to_owned();
    let got = Client::new()
        .get(b.at(&format!("/v1/clips/{id}")))
        .send()
        .unwrap();
    assert_eq!(got.status(), 200);
    let (sa, from_a) = decode(&a, &id);
    let (sb, from_b) = decode(&b, &id);
    assert_eq!((sa, sb), (200, 200));
    assert_eq!(
        from_a, from_b,
        "the replicas decode the same clip to different sets"
    );
    // B holds it now and was never asked to encode it; an upload of it to B is no new clip.
    let (status, again) = upload(&b, 1.0);
    assert_eq!(status, 200, "{again}");
    assert_eq!(again["created"], false);
    assert_eq!(encodes(&b), 0.0, "B encoded a clip A had published");

    // The same new clip to both at once: one encode between them.
    let before = encodes(&a) + encodes(&b);
    let (both_a, both_b) = std::thread::scope(|s| {
        let first = s.spawn(|| upload(&a, 2.0));
        let second = s.spawn(|| upload(&b, 2.0));
        (first.join().unwrap(), second.join().unwrap())
    });
    assert_eq!(both_a.1["id"], both_b.1["id"]);
    let mut statuses = [both_a.0, both_b.0];
    statuses.sort_unstable();
    assert_eq!(statuses, [200, 201], "{both_a:?} {both_b:?}");
    assert_eq!(
        encodes(&a) + encodes(&b) - before,
        1.0,
        "two replicas encoded one clip"
    );

    // Deleted on A: gone from the shared store, so a third replica never finds it.
    let deleted = Client::new()
        .delete(a.at(&format!("/v1/clips/{id}")))
        .send()
        .unwrap();
    assert_eq!(deleted.status(), 204);
    let store_c = tempfile::tempdir().unwrap();
    let c = replica(store_c.path(), shared);
    let (status, _) = decode(&c, &id);
    assert_eq!(status, 404);
    // The other clip is still everyone's.
    let other = both_a.1["id"].as_str().unwrap();
    assert_eq!(decode(&c, other).0, 200);
}
