//! Replicas sharing their clips through object storage (`C4G_SHARED_STORE`,
//! `service/src/clips/shared.rs`): `c4g-server` processes with stores of their own and one shared
//! store, run twice: a directory (`file://`, `object_store`'s local backend), and an S3 bucket on
//! moto's S3-compatible server (`moto_server` from PyPI, on loopback: the `aws` backend with its
//! conditional puts, as against a real bucket).
//!
//! Checked: a clip uploaded to one replica is served by the other (fetched, decoded to the same
//! bytes); an upload of a clip another replica already has is not encoded again; two replicas
//! given the same new clip at once encode it once between them (the encode claim); every replica
//! lists the cluster's clips; a delete removes the clip from the shared store, so a replica that
//! never held it answers 404 and one that fetched it stops serving it within seconds. And the
//! deployment as a whole, on one machine: nginx with `deploy/nginx/nginx.conf` (hashing on the
//! clip id) in front of two replicas on the S3 bucket and one PostgreSQL job database, with a
//! refiner worker each; one replica killed mid-traffic while its worker runs a job: every clip is
//! still served, through the other, no clip was encoded twice, and every job finishes once.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use c4g_e2e::{
    RefinerWorker, ServerProcess, frames_form, metric, missing, ort_available, synthetic_clip,
    venv_python,
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
    upload_to(&server.url(), scale)
}

/// [`upload`] to the server at `base`.
fn upload_to(base: &str, scale: f64) -> (u16, Value) {
    let (frames, times) = synthetic_clip();
    let times: Vec<f64> = times.iter().map(|t| t * scale).collect();
    let response = Client::new()
        .post(format!("{base}/v1/clips"))
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

    // A third replica, holding nothing, lists both clips from the shared store.
    let other = both_a.1["id"].as_str().unwrap();
    let store_c = tempfile::tempdir().unwrap();
    let c = replica(store_c.path(), shared);
    let mut both = vec![id.clone(), other.to_owned()];
    both.sort();
    let mut on_c = listed(&c);
    on_c.sort();
    assert_eq!(on_c, both);
    // Deleted on A: gone from the shared store, so C never finds it nor lists it again, and B,
    // which fetched it, stops serving it once it looks again (RECHECK, 5 s).
    let deleted = Client::new()
        .delete(a.at(&format!("/v1/clips/{id}")))
        .send()
        .unwrap();
    assert_eq!(deleted.status(), 204);
    let (status, _) = decode(&c, &id);
    assert_eq!(status, 404);
    let deadline = Instant::now() + Duration::from_secs(15);
    while decode(&b, &id).0 != 404 {
        assert!(
            Instant::now() < deadline,
            "B still serves a clip A deleted, 15 s later"
        );
        std::thread::sleep(Duration::from_millis(250));
    }
    let gone = Client::new()
        .get(b.at(&format!("/v1/clips/{id}")))
        .send()
        .unwrap();
    assert_eq!(gone.status(), 404);
    // The other clip is still everyone's, and every replica lists it, also C, which holds
    // nothing yet.
    for replica in [&a, &b, &c] {
        assert_eq!(listed(replica), [other.to_owned()]);
    }
    assert_eq!(decode(&c, other).0, 200);
}

/// The ids `GET /v1/clips` lists.
fn listed(server: &ServerProcess) -> Vec<String> {
    let body: Value = Client::new()
        .get(server.at("/v1/clips"))
        .send()
        .unwrap()
        .json()
        .unwrap();
    body["clips"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["id"].as_str().unwrap().to_owned())
        .collect()
}

/// nginx with deploy/nginx/nginx.conf, its upstreams and listening port replaced; killed when
/// dropped.
struct Proxy {
    child: Child,
    port: u16,
    _dir: tempfile::TempDir,
}

impl Drop for Proxy {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn proxy(upstreams: [std::net::SocketAddr; 2]) -> Option<Proxy> {
    if Command::new("nginx").arg("-v").output().is_err() {
        return missing("nginx must be installed (scripts/setup: nginx-light)");
    }
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let config = std::fs::read_to_string(c4g_e2e::workspace().join("deploy/nginx/nginx.conf"))
        .unwrap()
        .replace("127.0.0.1:8081", &upstreams[0].to_string())
        .replace("127.0.0.1:8082", &upstreams[1].to_string())
        .replace("listen 127.0.0.1:8080", &format!("listen 127.0.0.1:{port}"));
    let path = dir.path().join("nginx.conf");
    std::fs::write(&path, config).unwrap();
    let child = Command::new("nginx")
        .arg("-p")
        .arg(dir.path())
        .arg("-c")
        .arg(&path)
        // One process (no workers to orphan when the test kills it), in the foreground.
        .args(["-g", "daemon off; master_process off;"])
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "nginx did not start");
        std::thread::sleep(Duration::from_millis(50));
    }
    Some(Proxy {
        child,
        port,
        _dir: dir,
    })
}

/// A decode through the proxy; its status (0: no answer).
fn decode_via(port: u16, id: &str) -> u16 {
    Client::new()
        .post(format!("http://127.0.0.1:{port}/v1/clips/{id}/gaussians"))
        .json(&json!({"t": 0.3, "format": "binary"}))
        .timeout(Duration::from_secs(60))
        .send()
        .map_or(0, |r| r.status().as_u16())
}

/// A refinement job through the proxy.
fn submit_via(port: u16, clip: &str) -> String {
    let response = Client::new()
        .post(format!("http://127.0.0.1:{port}/v1/clips/{clip}/refine"))
        // 120 steps: long enough (seconds) that the victim's worker is still inside a job
        // when it is killed; at 12 a job took 0.3 s once the image crates were optimised in
        // debug builds, and the kill could find none running.
        .json(
            &json!({"trajectory": {"kind": "orbit", "depth": 2.0, "angle_degrees": 10},
                      "steps": 120, "seed": 7}),
        )
        .send()
        .unwrap();
    assert_eq!(response.status(), 202);
    let job: Value = response.json().unwrap();
    job["id"].as_str().unwrap().to_owned()
}

/// Every job, as the cluster sees it (through the proxy: any replica answers).
fn jobs_via(port: u16) -> Vec<Value> {
    let listed: Value = Client::new()
        .get(format!("http://127.0.0.1:{port}/v1/jobs"))
        .timeout(Duration::from_secs(30))
        .send()
        .unwrap()
        .json()
        .unwrap();
    listed["jobs"].as_array().unwrap().clone()
}

/// Polls the cluster's jobs until `done` says so, or panics after `limit`.
fn wait_for_jobs(port: u16, limit: Duration, done: impl Fn(&[Value]) -> bool) -> Vec<Value> {
    let deadline = Instant::now() + limit;
    loop {
        let jobs = jobs_via(port);
        if done(&jobs) {
            return jobs;
        }
        assert!(
            Instant::now() < deadline,
            "the jobs never got there: {jobs:#?}"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// The deployment as a whole, on one machine: PostgreSQL, an S3 bucket on moto, nginx with
/// `deploy/nginx/nginx.conf`, two replicas and a refiner worker on each. Clips are uploaded and
/// refined through the proxy; the replica that encoded the clips is killed while its worker runs
/// a job and decodes go on: every clip is still served (encoded once in all), and every job
/// finishes once, the killed replica's by the other side after its lease ran out.
#[test]
fn the_cluster_on_one_machine_loses_no_clip_and_no_job_when_a_replica_is_killed() {
    if !ort_available() {
        return;
    }
    let Some((_moto, mut shared)) = moto_bucket() else {
        return;
    };
    let Some(db) = c4g_e2e::postgres::TempPostgres::start() else {
        return;
    };
    shared.env.extend([
        ("C4G_JOB_DATABASE".to_owned(), db.url()),
        // Short, so that the killed replica's job is found lost within seconds.
        ("C4G_JOB_LEASE_S".to_owned(), "3".to_owned()),
        ("C4G_JOB_ATTEMPTS".to_owned(), "3".to_owned()),
    ]);
    let (store_a, store_b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let a = replica(store_a.path(), &shared);
    let b = replica(store_b.path(), &shared);
    let Some(proxy) = proxy([a.addr, b.addr]) else {
        return;
    };
    let base = format!("http://127.0.0.1:{}", proxy.port);
    let mut ids = Vec::new();
    for scale in [1.0, 2.0, 3.0, 4.0] {
        let (status, clip) = upload_to(&base, scale);
        assert_eq!(status, 201, "{clip}");
        ids.push(clip["id"].as_str().unwrap().to_owned());
    }
    for id in &ids {
        assert_eq!(decode_via(proxy.port, id), 200, "{id}");
    }
    let encoded = encodes(&a) + encodes(&b);
    assert_eq!(encoded, ids.len() as f64, "a clip was encoded twice");
    // Uploads hash on their one path, so one replica encoded them all: that one is killed.
    let a_encoded = encodes(&a) > 0.0;
    let (victim, survivor) = if a_encoded { (a, b) } else { (b, a) };
    let survivor_encodes = encodes(&survivor);

    // A worker on each replica, and a job for each clip, in the one queue.
    let _victim_worker = RefinerWorker::start(&victim.url(), "victim-worker");
    let _survivor_worker = RefinerWorker::start(&survivor.url(), "survivor-worker");
    let jobs: Vec<String> = ids.iter().map(|id| submit_via(proxy.port, id)).collect();
    wait_for_jobs(proxy.port, Duration::from_secs(120), |all| {
        all.iter()
            .any(|j| j["state"] == "running" && j["worker"] == "victim-worker")
    });

    // Traffic on every clip while the victim is killed: answers may fail only while nginx
    // finds it gone (requests it had in flight).
    let stop = std::sync::atomic::AtomicBool::new(false);
    let (failed_during, after) = std::thread::scope(|s| {
        let traffic = s.spawn(|| {
            let mut failed = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                for id in &ids {
                    if decode_via(proxy.port, id) != 200 {
                        failed += 1;
                    }
                }
            }
            failed
        });
        std::thread::sleep(Duration::from_millis(500));
        victim.kill();
        std::thread::sleep(Duration::from_millis(1500));
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        let failed = traffic.join().unwrap();
        let after: Vec<u16> = ids.iter().map(|id| decode_via(proxy.port, id)).collect();
        (failed, after)
    });
    assert!(after.iter().all(|&s| s == 200), "after the kill: {after:?}");
    assert_eq!(
        encodes(&survivor),
        survivor_encodes,
        "the survivor encoded a clip the killed replica had published"
    );

    // Every job ends, done, once; the one the killed replica's worker held was taken for lost
    // and run again on the survivor's side.
    let ended = wait_for_jobs(proxy.port, Duration::from_secs(240), |all| {
        all.len() == jobs.len()
            && all
                .iter()
                .all(|j| j["state"] != "queued" && j["state"] != "running")
    });
    let mut retried = 0;
    for job in &ended {
        assert_eq!(job["state"], "done", "{job:#}");
        let history: Vec<&str> = job["history"]
            .as_array()
            .unwrap()
            .iter()
            .map(|h| h.as_str().unwrap())
            .collect();
        let finished = history.iter().filter(|h| h.contains(": done on ")).count();
        assert_eq!(finished, 1, "a job finished {finished} times: {history:?}");
        retried += usize::from(history.iter().any(|h| h.contains("stopped responding")));
        // Its result, from the database, through whichever replica the proxy picks.
        let frame = Client::new()
            .get(format!(
                "http://127.0.0.1:{}/v1/jobs/{}/result?frame=0",
                proxy.port,
                job["id"].as_str().unwrap()
            ))
            .send()
            .unwrap();
        assert_eq!(frame.status(), 200);
        assert!(image::load_from_memory(&frame.bytes().unwrap()).is_ok());
    }
    assert!(
        retried >= 1,
        "no job was lost with the killed replica: {ended:#?}"
    );
    eprintln!(
        "cluster: {} clips, {encoded} encodes in all; {failed_during} answers failed while a \
         replica was killed; every clip served by the other afterwards; {} jobs done once each, \
         {retried} of them taken back from the killed replica's worker",
        ids.len(),
        ended.len()
    );
}
