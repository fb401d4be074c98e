//! Faults, each on real processes: `c4g-server` (and `c4g-refiner`) on loopback, killed with
//! SIGKILL at the worst moments, given a disk that fills up, clients that vanish or crawl, and
//! model packages that do not load or fail mid-run. What each promises is in
//! `docs/reliability.md`, which names these tests.
//!
//! Crashes in windows too narrow to hit by timing (inside an encode, between writing a clip's
//! features and its rename, between storing a job's result and its record) use the server's
//! fault points (`--fault-pause`, `service/src/faults.rs`): the server stops there, logs it, and
//! the test kills it.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::collections::BTreeSet;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use c4g_e2e::{
    RefinerWorker, ServerProcess, frames_form, metric, multipart_bytes, ort_available,
    synthetic_clip, workspace,
};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use reqwest::blocking::Client;
use serde_json::{Value, json};
use tokio_stream::StreamExt;

const BOUNDARY: &str = "c4g-faults-boundary";
const ANY_PORT: &str = "127.0.0.1:0";

// ---- clips, requests and metrics ----------------------------------------------------------------

/// The synthetic clip with its times scaled by `scale`: the times are part of what an upload
/// is, so each scale is another clip.
fn clip(scale: f64) -> (Vec<PathBuf>, Vec<f64>) {
    let (frames, times) = synthetic_clip();
    (frames, times.iter().map(|t| t * scale).collect())
}

fn upload(server: &ServerProcess, scale: f64) -> reqwest::blocking::Response {
    let (frames, times) = clip(scale);
    Client::new()
        .post(server.at("/v1/clips"))
        .multipart(frames_form(&frames, &times))
        .timeout(Duration::from_secs(120))
        .send()
        .unwrap()
}

fn json_of(response: reqwest::blocking::Response) -> Value {
    let status = response.status();
    let text = response.text().unwrap();
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{status}: {text:?}: {e}"))
}

/// Uploads the clip of `scale`, which must be new, and gives its id.
fn upload_new(server: &ServerProcess, scale: f64) -> String {
    let response = upload(server, scale);
    assert_eq!(response.status(), 201);
    json_of(response)["id"].as_str().unwrap().to_owned()
}

fn get(server: &ServerProcess, path: &str) -> reqwest::blocking::Response {
    Client::new()
        .get(server.at(path))
        .timeout(Duration::from_secs(60))
        .send()
        .unwrap()
}

fn post(server: &ServerProcess, path: &str, body: Value) -> reqwest::blocking::Response {
    Client::new()
        .post(server.at(path))
        .json(&body)
        .timeout(Duration::from_secs(120))
        .send()
        .unwrap()
}

/// Asserts that `response` is the error `status` of `kind`, and gives its message.
fn expect_error(response: reqwest::blocking::Response, status: u16, kind: &str) -> String {
    let got = response.status();
    let body = json_of(response);
    assert_eq!(
        (got.as_u16(), body["kind"].as_str()),
        (status, Some(kind)),
        "{body}"
    );
    body["error"].as_str().unwrap().to_owned()
}

fn decode_ok(server: &ServerProcess, id: &str) {
    let response = post(
        server,
        &format!("/v1/clips/{id}/gaussians"),
        json!({"t": 0.0, "format": "binary"}),
    );
    assert_eq!(response.status(), 200, "{}", response.text().unwrap());
}

fn scrape(server: &ServerProcess) -> String {
    get(server, "/metrics").text().unwrap()
}

/// Polls the metric `name` until `done` holds, and gives its value; panics after `within`.
fn wait_metric(
    server: &ServerProcess,
    name: &str,
    within: Duration,
    done: impl Fn(f64) -> bool,
) -> f64 {
    let deadline = Instant::now() + within;
    loop {
        let value = metric(&scrape(server), name);
        if done(value) {
            return value;
        }
        assert!(Instant::now() < deadline, "{name} stayed at {value}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Runtime::new().unwrap()
}

// ---- the store on disk --------------------------------------------------------------------------

/// `<store>/<model key>`: the one directory with clips in it.
fn model_dir(store: &Path) -> PathBuf {
    let dirs: Vec<PathBuf> = std::fs::read_dir(store)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.join("clips").is_dir())
        .collect();
    assert_eq!(dirs.len(), 1, "one model's store expected: {dirs:?}");
    dirs[0].clone()
}

fn names(dir: &Path) -> BTreeSet<String> {
    match std::fs::read_dir(dir) {
        Ok(entries) => entries
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect(),
        Err(_) => BTreeSet::new(),
    }
}

/// Asserts what a restart promises of the store: no leftover of an interrupted write, every clip
/// directory complete, listed and served (features and frames), nothing listed that is not on
/// disk, and the same of jobs. Gives the clip ids.
fn assert_store_agrees(server: &ServerProcess, store: &Path) -> BTreeSet<String> {
    let model = model_dir(store);
    let on_disk = names(&model.join("clips"));
    for name in &on_disk {
        assert!(
            !name.starts_with('.'),
            "a leftover survived a restart: {name}"
        );
        let dir = model.join("clips").join(name);
        for file in ["clip.json", "features.f32", "frames/000.png"] {
            assert!(dir.join(file).is_file(), "clip {name} lacks {file}");
        }
    }
    assert!(
        names(&model.join("damaged")).is_empty(),
        "clips were set aside as damaged: {:?}",
        names(&model.join("damaged"))
    );
    let listed: BTreeSet<String> = json_of(get(server, "/v1/clips"))["clips"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["id"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(listed, on_disk, "the index and the disk disagree");
    for id in &listed {
        decode_ok(server, id);
        let frame = get(server, &format!("/v1/clips/{id}/frames/0"));
        assert_eq!(frame.status(), 200);
    }
    let job_dirs = names(&model.join("jobs"));
    for name in &job_dirs {
        let dir = model.join("jobs").join(name);
        assert!(dir.join("job.json").is_file(), "job {name} has no record");
        let inside = names(&dir);
        assert!(
            inside.iter().all(|n| !n.starts_with('.')),
            "job {name} keeps leftovers: {inside:?}"
        );
    }
    let jobs: BTreeSet<String> = json_of(get(server, "/v1/jobs"))["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["id"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(jobs, job_dirs, "the job list and the disk disagree");
    listed
}

// ---- raw HTTP -----------------------------------------------------------------------------------

/// A connection that has sent the head of a multipart upload of `length` bytes, and no body.
fn upload_head(addr: SocketAddr, length: usize) -> TcpStream {
    let mut stream = TcpStream::connect(addr).unwrap();
    write!(
        stream,
        "POST /v1/clips HTTP/1.1\r\nHost: {addr}\r\nContent-Type: multipart/form-data; \
         boundary={BOUNDARY}\r\nContent-Length: {length}\r\n\r\n"
    )
    .unwrap();
    stream
}

/// Reads one HTTP/1.1 response: its status code and body.
fn read_response(stream: &mut TcpStream) -> (u16, String) {
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    let mut bytes = Vec::new();
    let mut buffer = [0u8; 4096];
    let head_end = loop {
        let n = stream.read(&mut buffer).unwrap();
        assert!(n > 0, "the connection closed without an answer");
        bytes.extend_from_slice(&buffer[..n]);
        if let Some(end) = bytes.windows(4).position(|w| w == b"\r\n\r\n") {
            break end + 4;
        }
    };
    let head = String::from_utf8_lossy(&bytes[..head_end]).to_lowercase();
    let status = head[9..12].parse().unwrap();
    let length: usize = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))
        .map_or(0, |v| v.trim().parse().unwrap());
    while bytes.len() < head_end + length {
        let n = stream.read(&mut buffer).unwrap();
        assert!(n > 0, "the connection closed mid-answer");
        bytes.extend_from_slice(&buffer[..n]);
    }
    let body = String::from_utf8_lossy(&bytes[head_end..head_end + length]).into_owned();
    (status, body)
}

// ---- gRPC ---------------------------------------------------------------------------------------

fn zip_of(frames: &[PathBuf]) -> Vec<u8> {
    let mut writer = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for path in frames {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        writer
            .start_file(name, zip::write::SimpleFileOptions::default())
            .unwrap();
        writer.write_all(&std::fs::read(path).unwrap()).unwrap();
    }
    writer.finish().unwrap().into_inner()
}

fn upload_header(times: Vec<f64>) -> pb::UploadRequest {
    pb::UploadRequest {
        part: Some(pb::upload_request::Part::Header(pb::UploadHeader {
            kind: pb::MediaKind::Zip as i32,
            filename: "frames.zip".into(),
            fps: None,
            timestamps: times,
            sampling: None,
            cameras: None,
        })),
    }
}

fn chunk(bytes: &[u8]) -> pb::UploadRequest {
    pb::UploadRequest {
        part: Some(pb::upload_request::Part::Chunk(bytes.to_vec())),
    }
}

fn kind_of(status: &tonic::Status) -> String {
    status
        .metadata()
        .get("c4g-error-kind")
        .map(|v| v.to_str().unwrap().to_owned())
        .unwrap_or_default()
}

/// Sets in a long stream: near the limit of one request (`C4G_MAX_TIMES`, 4096).
const LONG_STREAM: f64 = 4001.0;

/// Asks for a stream of [`LONG_STREAM`] sets of clip `id` of span `span` seconds.
fn long_stream(id: &str, span: f64) -> pb::StreamGaussiansRequest {
    pb::StreamGaussiansRequest {
        clip_id: id.to_owned(),
        spacing: Some(pb::stream_gaussians_request::Spacing::Step(
            span / (LONG_STREAM - 1.0),
        )),
        ..Default::default()
    }
}

/// Waits until no work slot is busy and no set has been decoded for a second, and gives the
/// sets decoded so far; panics if that never happens within `within`.
fn decoding_settles(server: &ServerProcess, within: Duration) -> f64 {
    let deadline = Instant::now() + within;
    let mut before = metric(&scrape(server), "c4g_decoded_sets_total");
    loop {
        std::thread::sleep(Duration::from_secs(1));
        let metrics = scrape(server);
        let now = metric(&metrics, "c4g_decoded_sets_total");
        if now == before && metric(&metrics, "c4g_work_slots_busy") == 0.0 {
            return now;
        }
        assert!(
            Instant::now() < deadline,
            "decoding never stopped: {now} sets, {} slots busy",
            metric(&metrics, "c4g_work_slots_busy")
        );
        before = now;
    }
}

// ---- refinement ---------------------------------------------------------------------------------

fn worker(url: &str, name: &str) -> RefinerWorker {
    RefinerWorker::start(url, name)
}

fn submit(server: &ServerProcess, clip: &str, steps: u32) -> String {
    let response = post(
        server,
        &format!("/v1/clips/{clip}/refine"),
        json!({"steps": steps}),
    );
    assert_eq!(response.status(), 202);
    json_of(response)["id"].as_str().unwrap().to_owned()
}

fn job(server: &ServerProcess, id: &str) -> Value {
    json_of(get(server, &format!("/v1/jobs/{id}")))
}

fn wait_job(
    server: &ServerProcess,
    id: &str,
    within: Duration,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + within;
    loop {
        let record = job(server, id);
        if done(&record) {
            return record;
        }
        assert!(Instant::now() < deadline, "job never got there: {record:#}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn finished(record: &Value) -> bool {
    !matches!(record["state"].as_str(), Some("queued" | "running"))
}

/// How many times the job's history says it was done.
fn completions(record: &Value) -> usize {
    record["history"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|h| h.as_str().unwrap().contains(": done on "))
        .count()
}

// ---- crashes ------------------------------------------------------------------------------------

#[test]
fn a_server_killed_mid_upload_keeps_every_stored_clip_and_none_of_the_cut_one() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(store.path(), ANY_PORT, &[]);
    let kept = upload_new(&server, 1.0);
    // Half of another upload's body is in when the server dies.
    let (frames, times) = clip(2.0);
    let body = multipart_bytes(&frames, &times, BOUNDARY);
    let mut connection = upload_head(server.addr, body.len());
    connection.write_all(&body[..body.len() / 2]).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    server.kill();
    drop(connection);

    let server = ServerProcess::start(store.path(), ANY_PORT, &[]);
    assert_eq!(assert_store_agrees(&server, store.path()), [kept].into());
    // The cut upload, sent whole, is stored as any new clip.
    upload_new(&server, 2.0);
    assert_eq!(assert_store_agrees(&server, store.path()).len(), 2);
}

/// What a crash at a fault point left: the store, the clip stored before, the store's clip
/// directory entries at the moment of the kill, and a server restarted on it.
struct Crash {
    store: tempfile::TempDir,
    kept: String,
    at_kill: BTreeSet<String>,
    server: ServerProcess,
}

/// Stores one clip, then uploads another to a server that stops at fault `point`, kills it
/// there with SIGKILL, and restarts it on the same store.
fn crash_uploading_at(point: &str) -> Crash {
    let store = tempfile::tempdir().unwrap();
    let first = ServerProcess::start(store.path(), ANY_PORT, &[]);
    let kept = upload_new(&first, 1.0);
    first.kill();
    let paused = ServerProcess::start(store.path(), ANY_PORT, &["--fault-pause", point]);
    let url = paused.at("/v1/clips");
    // Its answer never comes: the server dies first.
    std::thread::spawn(move || {
        let (frames, times) = clip(2.0);
        let _ = Client::new()
            .post(url)
            .multipart(frames_form(&frames, &times))
            .timeout(Duration::from_secs(300))
            .send();
    });
    paused.wait_for_log(
        &format!("fault point {point} reached"),
        Duration::from_secs(120),
    );
    let at_kill = names(&model_dir(store.path()).join("clips"));
    paused.kill();
    let server = ServerProcess::start(store.path(), ANY_PORT, &[]);
    Crash {
        store,
        kept,
        at_kill,
        server,
    }
}

#[test]
fn a_server_killed_while_reading_a_video_leaves_no_scratch_file_once_restarted() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    let video = store.path().join("clip.mp4");
    let made = Command::new("ffmpeg")
        .args(["-v", "error", "-f", "lavfi", "-i"])
        .arg("testsrc=size=64x64:rate=10:duration=1")
        .args(["-pix_fmt", "yuv420p"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(made.success());
    let scratch = store.path().join("scratch");
    let args = ["--fault-pause", "video-scratch-written"];
    for _ in 0..2 {
        let paused = ServerProcess::start(store.path(), ANY_PORT, &args);
        let (url, body) = (paused.at("/v1/clips"), std::fs::read(&video).unwrap());
        // Its answer never comes: the server dies first.
        std::thread::spawn(move || {
            let _ = Client::new()
                .post(url)
                .body(body)
                .timeout(Duration::from_secs(300))
                .send();
        });
        paused.wait_for_log(
            "fault point video-scratch-written reached",
            Duration::from_secs(120),
        );
        assert_eq!(names(&scratch).len(), 1, "the upload is in scratch space");
        paused.kill();
    }
    // Each killed read left its upload, and each start removed the one before: one is left.
    assert_eq!(
        names(&scratch).len(),
        1,
        "the second start kept the first kill's upload"
    );
    let server = ServerProcess::start(store.path(), ANY_PORT, &[]);
    assert!(names(&scratch).is_empty(), "{:?}", names(&scratch));
    upload_new(&server, 1.0);
}

#[test]
fn a_server_killed_while_encoding_keeps_the_stored_clips_and_nothing_of_the_new_one() {
    if !ort_available() {
        return;
    }
    let crash = crash_uploading_at("encode");
    assert_eq!(crash.at_kill, [crash.kept.clone()].into());
    let clips = assert_store_agrees(&crash.server, crash.store.path());
    assert_eq!(clips, [crash.kept.clone()].into());
    upload_new(&crash.server, 2.0);
}

#[test]
fn a_server_killed_while_writing_features_leaves_no_half_clip_after_restart() {
    if !ort_available() {
        return;
    }
    let crash = crash_uploading_at("clip-features-written");
    // The kill hit mid-write: a temporary directory with the features and no frames yet.
    let clips_dir = model_dir(crash.store.path()).join("clips");
    let partial: Vec<&String> = crash
        .at_kill
        .iter()
        .filter(|n| n.starts_with(".tmp-"))
        .collect();
    assert_eq!(partial.len(), 1, "{:?}", crash.at_kill);
    let clips = assert_store_agrees(&crash.server, crash.store.path());
    assert!(
        !clips_dir.join(partial[0]).exists(),
        "the half clip is still there"
    );
    assert_eq!(clips, [crash.kept.clone()].into());
    upload_new(&crash.server, 2.0);
    assert_eq!(
        assert_store_agrees(&crash.server, crash.store.path()).len(),
        2
    );
}

#[test]
fn a_server_killed_after_storing_a_clip_but_before_answering_serves_it_after_restart() {
    if !ort_available() {
        return;
    }
    let crash = crash_uploading_at("clip-stored");
    let stored: Vec<&String> = crash.at_kill.iter().filter(|n| **n != crash.kept).collect();
    assert_eq!(stored.len(), 1, "{:?}", crash.at_kill);
    assert!(!stored[0].starts_with('.'), "{:?}", crash.at_kill);
    let clips = assert_store_agrees(&crash.server, crash.store.path());
    assert_eq!(clips.len(), 2);
    // The client never heard; sending it again finds it stored, not encoded again.
    let again = upload(&crash.server, 2.0);
    assert_eq!(again.status(), 200);
    let again = json_of(again);
    assert_eq!(again["created"], false);
    assert_eq!(again["id"].as_str(), Some(stored[0].as_str()));
}

#[test]
fn a_server_killed_during_a_refinement_job_runs_it_again_once_and_loses_no_queued_job() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    // A long lease: the job comes back because of the restart, not because a lease ran out.
    let args = ["--job-lease-s", "120"];
    let first = ServerProcess::start(store.path(), ANY_PORT, &args);
    let clip = upload_new(&first, 1.0);
    let running = submit(&first, &clip, 30);
    let waiting = submit(&first, &clip, 2);
    // The worker outlives the server and finds it again on the same port.
    let _worker = worker(&first.url(), "w1");
    wait_job(&first, &running, Duration::from_secs(120), |j| {
        j["state"] == "running" && j["progress"]["step"].as_u64().unwrap_or(0) >= 2
    });
    let addr = first.addr.to_string();
    first.kill();

    let server = ServerProcess::start(store.path(), &addr, &args);
    let after = job(&server, &running);
    assert_eq!(after["attempt"], 2, "{after:#}");
    assert!(
        after["history"][0]
            .as_str()
            .unwrap()
            .contains("the server restarted while it ran"),
        "{after:#}"
    );
    // The worker may have taken it already: it was queued, so it is on its first attempt.
    let queued = job(&server, &waiting);
    assert!(
        matches!(queued["state"].as_str(), Some("queued" | "running")),
        "{queued:#}"
    );
    assert_eq!(queued["attempt"], 1, "{queued:#}");
    assert_store_agrees(&server, store.path());

    let done = wait_job(&server, &running, Duration::from_secs(180), finished);
    assert_eq!(done["state"], "done", "{done:#}");
    assert_eq!((done["attempt"].as_u64(), completions(&done)), (Some(2), 1));
    let other = wait_job(&server, &waiting, Duration::from_secs(120), finished);
    assert_eq!(other["state"], "done", "{other:#}");
    assert_eq!(
        (other["attempt"].as_u64(), completions(&other)),
        (Some(1), 1)
    );
    let frame = get(&server, &format!("/v1/jobs/{running}/result?frame=0"));
    assert_eq!(frame.headers()["content-type"], "image/png");
    assert_store_agrees(&server, store.path());
}

#[test]
fn a_server_killed_after_storing_a_result_marks_the_job_done_and_never_runs_it_again() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    let first = ServerProcess::start(
        store.path(),
        ANY_PORT,
        &["--fault-pause", "job-result-stored"],
    );
    let clip = upload_new(&first, 1.0);
    let id = submit(&first, &clip, 2);
    let _worker = worker(&first.url(), "w1");
    first.wait_for_log(
        "fault point job-result-stored reached",
        Duration::from_secs(180),
    );
    let job_dir = model_dir(store.path()).join("jobs").join(&id);
    let on_disk: Value =
        serde_json::from_slice(&std::fs::read(job_dir.join("job.json")).unwrap()).unwrap();
    assert_eq!(
        on_disk["state"], "running",
        "the kill comes before the record says done"
    );
    assert!(job_dir.join("result/result.json").is_file());
    let addr = first.addr.to_string();
    first.kill();

    let server = ServerProcess::start(store.path(), &addr, &[]);
    let record = job(&server, &id);
    assert_eq!(record["state"], "done", "{record:#}");
    assert_eq!(
        (record["attempt"].as_u64(), completions(&record)),
        (Some(1), 1)
    );
    assert!(record["result_frames"].as_u64().unwrap() >= 1);
    let frame = get(&server, &format!("/v1/jobs/{id}/result?frame=0"));
    assert_eq!(frame.headers()["content-type"], "image/png");
    // The worker is still there, asking for work: it gets none.
    std::thread::sleep(Duration::from_secs(3));
    let later = job(&server, &id);
    assert_eq!(later, record, "the job changed after it was done");
    assert_store_agrees(&server, store.path());
}

// ---- a full disk --------------------------------------------------------------------------------

/// A small tmpfs mounted for a test, unmounted when dropped.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(dir: &Path, size: &str) -> Result<Self, String> {
        let output = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir)
            .output()
            .map_err(|e| format!("cannot run mount: {e}"))?;
        if !output.status.success() {
            return Err(String::from_utf8_lossy(&output.stderr).trim().to_owned());
        }
        Ok(Self(dir.to_path_buf()))
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(&self.0).status();
    }
}

/// Writes `path` until the disk refuses another byte.
fn fill(path: &Path) {
    let mut file = std::fs::File::create(path).unwrap();
    let block = vec![0u8; 64 << 10];
    for size in [block.len(), 4096, 1] {
        while let Ok(n) = file.write(&block[..size]) {
            if n == 0 {
                break;
            }
        }
    }
    let _ = file.sync_all();
}

#[test]
fn a_full_disk_refuses_uploads_with_507_keeps_serving_and_recovers_when_space_returns() {
    if !ort_available() {
        return;
    }
    let root = tempfile::tempdir().unwrap();
    let disk = root.path().join("disk");
    std::fs::create_dir(&disk).unwrap();
    let _mount = match Tmpfs::mount(&disk, "8m") {
        Ok(mount) => mount,
        Err(e) => {
            eprintln!(
                "skipped: a full disk needs a small filesystem to fill, and mounting an 8 MiB \
                 tmpfs failed (it needs root with CAP_SYS_ADMIN): {e}"
            );
            return;
        }
    };
    let mut server = ServerProcess::start(&disk, ANY_PORT, &[]);
    let kept = upload_new(&server, 1.0);
    let filler = disk.join("filler");
    fill(&filler);

    let message = expect_error(upload(&server, 2.0), 507, "insufficient_storage");
    assert!(message.contains("disk is full"), "{message}");
    let message = expect_error(
        post(
            &server,
            &format!("/v1/clips/{kept}/refine"),
            json!({"steps": 2}),
        ),
        507,
        "insufficient_storage",
    );
    assert!(message.contains("disk is full"), "{message}");
    let (frames, times) = clip(3.0);
    let archive = zip_of(&frames);
    let status = runtime().block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let messages = vec![upload_header(times.clone()), chunk(&archive)];
        grpc.upload(tokio_stream::iter(messages)).await.unwrap_err()
    });
    assert_eq!(status.code(), tonic::Code::ResourceExhausted, "{status:?}");
    assert_eq!(kind_of(&status), "insufficient_storage");
    // A video goes through scratch space on the store's disk (FFmpeg needs a seekable file), and
    // so does an MP4 render: the same 507, not a 500.
    let video = root.path().join("clip.mp4");
    let made = std::process::Command::new("ffmpeg")
        .args([
            "-v",
            "error",
            "-f",
            "lavfi",
            "-i",
            "testsrc=size=64x64:rate=10:duration=1",
        ])
        .args(["-pix_fmt", "yuv420p"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(made.success());
    let response = reqwest::blocking::Client::new()
        .post(server.at("/v1/clips"))
        .body(std::fs::read(&video).unwrap())
        .send()
        .unwrap();
    let message = expect_error(response, 507, "insufficient_storage");
    assert!(message.contains("scratch"), "{message}");
    let trajectory = json!({"trajectory": {"kind": "orbit", "depth": 2.0, "angle_degrees": 10},
                            "frames": 2, "width": 32, "height": 32, "format": "mp4"});
    let render = post(&server, &format!("/v1/clips/{kept}/render"), trajectory);
    expect_error(render, 507, "insufficient_storage");
    // Nothing half-written stays to keep the disk full, and what was stored is served.
    let model = model_dir(&disk);
    assert_eq!(names(&model.join("clips")), [kept.clone()].into());
    assert!(names(&model.join("jobs")).is_empty());
    decode_ok(&server, &kept);
    let render = post(
        &server,
        &format!("/v1/clips/{kept}/render"),
        json!({"t": 0.3}),
    );
    assert_eq!(render.status(), 200);
    assert_eq!(get(&server, "/ready").status(), 200);
    assert!(server.alive());

    // Space returns: the same uploads succeed, without a restart.
    std::fs::remove_file(&filler).unwrap();
    upload_new(&server, 2.0);
    let job = submit(&server, &kept, 2);
    let cancelled = post(&server, &format!("/v1/jobs/{job}/cancel"), json!({}));
    assert_eq!(cancelled.status(), 200);
    assert_eq!(assert_store_agrees(&server, &disk).len(), 2);
    server.kill();
}

// ---- clients that go away -----------------------------------------------------------------------

#[test]
fn a_client_gone_mid_upload_or_mid_encode_leaves_nothing_stored_half_written_or_held() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    // Encodes stop at the fault point: an upload can be left mid-encode, for as long as needed.
    let args = ["--fault-pause", "encode", "--max-concurrent-encodes", "1"];
    let server = ServerProcess::start(store.path(), ANY_PORT, &args);
    // REST: half the body, then the connection closes.
    let (frames, times) = clip(1.0);
    let body = multipart_bytes(&frames, &times, BOUNDARY);
    let mut connection = upload_head(server.addr, body.len());
    connection.write_all(&body[..body.len() / 2]).unwrap();
    std::thread::sleep(Duration::from_millis(200));
    drop(connection);
    // gRPC: a header and one chunk, then the call is dropped.
    let archive = zip_of(&frames);
    runtime().block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let messages =
            tokio_stream::iter(vec![upload_header(times.clone()), chunk(&archive[..100])])
                .chain(tokio_stream::pending());
        let call = tokio::time::timeout(Duration::from_millis(500), grpc.upload(messages)).await;
        assert!(
            call.is_err(),
            "the upload cannot end: its stream never does"
        );
    });
    // A failed upload leaves no trace either.
    let broken = reqwest::blocking::multipart::Form::new()
        .text("timestamps", "0,0.1,0.2,0.3")
        .part(
            "frame",
            reqwest::blocking::multipart::Part::bytes(b"not an image".to_vec())
                .file_name("frame.png"),
        );
    let refused = Client::new()
        .post(server.at("/v1/clips"))
        .multipart(broken)
        .send()
        .unwrap();
    assert!(refused.status().is_client_error(), "{}", refused.status());
    // A whole upload whose client gives up while it is encoded.
    let gone = Client::new()
        .post(server.at("/v1/clips"))
        .multipart(frames_form(&frames, &times))
        .timeout(Duration::from_secs(2))
        .send();
    assert!(gone.is_err(), "the paused encode cannot have answered");
    server.wait_for_log("fault point encode reached", Duration::from_secs(10));

    wait_metric(
        &server,
        "c4g_clips_in_progress",
        Duration::from_secs(10),
        |v| v == 0.0,
    );
    let metrics = scrape(&server);
    assert_eq!(metric(&metrics, "c4g_work_slots_busy"), 0.0);
    assert_eq!(metric(&metrics, "c4g_clips"), 0.0);
    assert!(names(&model_dir(store.path()).join("clips")).is_empty());
    // An encode cannot be interrupted: the one its client left still runs, and still holds its
    // encode slot, so clients that leave cannot pile up encodes past the limit.
    expect_error(upload(&server, 2.0), 429, "busy");

    server.kill();
    let server = ServerProcess::start(store.path(), ANY_PORT, &[]);
    assert!(assert_store_agrees(&server, store.path()).is_empty());
    upload_new(&server, 1.0);
}

#[test]
fn a_client_gone_mid_stream_stops_the_stream_and_frees_its_work_slot() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(store.path(), ANY_PORT, &["--max-concurrent-work", "1"]);
    let id = upload_new(&server, 1.0);
    runtime().block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let mut stream = grpc
            .stream_gaussians(long_stream(&id, 0.6))
            .await
            .unwrap()
            .into_inner();
        for _ in 0..2 {
            assert!(stream.message().await.unwrap().is_some());
        }
        // Gone: the stream, its call and (with the runtime) its connection.
    });
    let decoded = decoding_settles(&server, Duration::from_secs(60));
    assert!(
        decoded < LONG_STREAM / 4.0,
        "{decoded} of {LONG_STREAM} sets decoded for a client that left"
    );
    assert_eq!(metric(&scrape(&server), "c4g_work_queued"), 0.0);
    decode_ok(&server, &id);
    eprintln!("{decoded} of {LONG_STREAM} sets decoded before the stream stopped");
}

#[test]
fn a_client_gone_mid_trajectory_render_cancels_it_and_frees_its_slot_and_queue_place() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(store.path(), ANY_PORT, &["--max-concurrent-work", "1"]);
    let id = upload_new(&server, 1.0);
    let frames = 600u64;
    // Keyframes: the sets come quickly, the 600 renders are the long part.
    let trajectory = json!({
        "trajectory": {"kind": "orbit", "depth": 2.0, "angle_degrees": 30},
        "frames": frames, "width": 256, "height": 256, "keyframes": {"count": 2},
    });
    let render_url = server.at(&format!("/v1/clips/{id}/render"));
    let long = {
        let url = render_url.clone();
        std::thread::spawn(move || {
            Client::new()
                .post(url)
                .json(&trajectory)
                .timeout(Duration::from_secs(6))
                .send()
                .map(|r| r.status())
        })
    };
    wait_metric(
        &server,
        "c4g_work_slots_busy",
        Duration::from_secs(30),
        |v| v == 1.0,
    );
    // A render behind it waits in the queue, and its client gives up too.
    let queued = {
        let url = render_url.clone();
        std::thread::spawn(move || {
            Client::new()
                .post(url)
                .json(&json!({"t": 0.3}))
                .timeout(Duration::from_secs(2))
                .send()
                .map(|r| r.status())
        })
    };
    wait_metric(&server, "c4g_work_queued", Duration::from_secs(10), |v| {
        v == 1.0
    });
    assert!(
        queued.join().unwrap().is_err(),
        "the queued render should have timed out"
    );
    wait_metric(&server, "c4g_work_queued", Duration::from_secs(10), |v| {
        v == 0.0
    });
    assert!(
        long.join().unwrap().is_err(),
        "the trajectory should have timed out"
    );

    wait_metric(
        &server,
        "c4g_work_slots_busy",
        Duration::from_secs(60),
        |v| v == 0.0,
    );
    let metrics = scrape(&server);
    let rendered = metric(&metrics, "c4g_render_duration_seconds_count");
    assert!(
        rendered < frames as f64,
        "all {frames} frames were rendered for a client that left"
    );
    assert!(metric(&metrics, "c4g_work_cancelled_total") >= 1.0);
    let render = post(
        &server,
        &format!("/v1/clips/{id}/render"),
        json!({"t": 0.3}),
    );
    assert_eq!(render.status(), 200);
    eprintln!("cancelled after {rendered} of {frames} frames");
}

// ---- slow clients -------------------------------------------------------------------------------

#[test]
fn a_body_trickled_byte_by_byte_is_cut_off_at_the_body_timeout_while_others_are_served() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    let limit = 4.0;
    let server = ServerProcess::start(
        store.path(),
        ANY_PORT,
        &["--body-timeout-s", &limit.to_string()],
    );
    let kept = upload_new(&server, 1.0);
    let (frames, times) = clip(2.0);
    let body = multipart_bytes(&frames, &times, BOUNDARY);
    let started = Instant::now();
    let mut connection = upload_head(server.addr, body.len());
    let mut trickle = connection.try_clone().unwrap();
    let sender = std::thread::spawn(move || {
        let mut sent = 0;
        for byte in &body {
            if trickle.write_all(std::slice::from_ref(byte)).is_err() {
                break;
            }
            sent += 1;
            std::thread::sleep(Duration::from_millis(20));
        }
        (sent, body.len())
    });
    // While it crawls, others are served as usual.
    std::thread::sleep(Duration::from_millis(300));
    upload_new(&server, 3.0);
    decode_ok(&server, &kept);
    let others_done = started.elapsed();

    let (status, answer) = read_response(&mut connection);
    let cut_at = started.elapsed();
    assert_eq!(status, 408, "{answer}");
    let answer: Value = serde_json::from_str(&answer).unwrap();
    assert_eq!(answer["kind"], "timed_out");
    assert!(
        answer["error"]
            .as_str()
            .unwrap()
            .contains("C4G_BODY_TIMEOUT_S")
    );
    assert!(
        others_done < cut_at,
        "the other requests took {others_done:?}, past the slow one's end at {cut_at:?}"
    );
    assert!(cut_at >= Duration::from_secs_f64(limit - 0.5), "{cut_at:?}");
    assert!(cut_at < Duration::from_secs_f64(limit + 20.0), "{cut_at:?}");
    // Both handles share the socket: shutting it stops the sender whatever the server did.
    let _ = connection.shutdown(std::net::Shutdown::Both);
    let (sent, total) = sender.join().unwrap();
    assert!(sent < total, "the whole body went through");

    // gRPC: an upload whose stream stalls after its header is refused the same way.
    let status = runtime().block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let messages =
            tokio_stream::iter(vec![upload_header(times.clone())]).chain(tokio_stream::pending());
        tokio::time::timeout(Duration::from_secs(60), grpc.upload(messages))
            .await
            .expect("the stalled gRPC upload was never cut off")
            .unwrap_err()
    });
    assert_eq!(status.code(), tonic::Code::DeadlineExceeded, "{status:?}");
    assert_eq!(kind_of(&status), "timed_out");
    assert_eq!(assert_store_agrees(&server, store.path()).len(), 2);
    eprintln!("others served in {others_done:?}; the trickle cut off at {cut_at:?}");
}

#[test]
fn a_stream_reader_that_never_reads_holds_no_work_slot_and_delays_nobody() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    // One slot: if the stalled stream held it, nothing else could decode.
    let server = ServerProcess::start(store.path(), ANY_PORT, &["--max-concurrent-work", "1"]);
    let id = upload_new(&server, 1.0);
    let runtime = runtime();
    // The client and its stream stay open, unread, until the end.
    let (client, stream) = runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let stream = grpc.stream_gaussians(long_stream(&id, 0.6)).await.unwrap();
        (grpc, stream)
    });
    // Backpressure: it decodes a bounded way ahead, then waits, holding no slot.
    let decoded = decoding_settles(&server, Duration::from_secs(60));
    assert!(
        decoded < LONG_STREAM / 10.0,
        "{decoded} of {LONG_STREAM} sets decoded ahead of a reader that reads nothing"
    );
    runtime.block_on(async {
        // Others are served while it hangs.
        let started = Instant::now();
        let response = reqwest::Client::new()
            .post(server.at(&format!("/v1/clips/{id}/gaussians")))
            .json(&json!({"t": 0.3, "format": "binary"}))
            .send()
            .await
            .unwrap();
        assert_eq!(response.status(), 200);
        eprintln!(
            "a decode took {:?} beside a stalled stream ({decoded} sets decoded ahead)",
            started.elapsed()
        );
        let stalled = metric(&scrape_async(&server).await, "c4g_decoded_sets_total");
        assert!(stalled <= decoded + 1.0, "{stalled} > {decoded} + 1");
    });
    drop((stream, client));
}

async fn scrape_async(server: &ServerProcess) -> String {
    reqwest::get(server.at("/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap()
}

// ---- the model ----------------------------------------------------------------------------------

/// A copy of the default package (its manifest and graphs) to break.
fn package_copy(dir: &Path) -> PathBuf {
    let package = dir.join("package");
    std::fs::create_dir(&package).unwrap();
    let source = workspace().join("models/c4g-tiny");
    for file in ["model.json", "encoder.onnx", "decoder.onnx"] {
        std::fs::copy(source.join(file), package.join(file)).unwrap();
    }
    package
}

/// Starts a server that cannot load its model, and gives its log once it has ended with the
/// failure status (an exit, not a crash).
fn refused_start(args: &[&str], env: &[(&str, &str)]) -> String {
    let store = tempfile::tempdir().unwrap();
    let mut server = ServerProcess::spawn(store.path(), ANY_PORT, args, env);
    let status = server.wait_exit(Duration::from_secs(120));
    assert_eq!(status.code(), Some(1), "{status}: {}", server.log());
    server.log()
}

#[test]
fn a_corrupt_or_missing_model_file_stops_the_server_at_start_with_the_reason() {
    if !ort_available() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let package = package_copy(dir.path());
    let model = package.to_str().unwrap();

    // A truncated graph: ONNX Runtime cannot parse it.
    let decoder = package.join("decoder.onnx");
    let bytes = std::fs::read(&decoder).unwrap();
    std::fs::write(&decoder, &bytes[..bytes.len() / 3]).unwrap();
    let log = refused_start(&["--model", model], &[]);
    assert!(log.contains("cannot load the model"), "{log}");
    assert!(log.contains("decoder.onnx"), "{log}");
    std::fs::write(&decoder, &bytes).unwrap();

    // A missing graph.
    std::fs::remove_file(package.join("encoder.onnx")).unwrap();
    let log = refused_start(&["--model", model], &[]);
    assert!(log.contains("encoder.onnx"), "{log}");
    assert!(log.contains("does not exist"), "{log}");

    // No ONNX Runtime library at all.
    let log = refused_start(&[], &[("ORT_DYLIB_PATH", "/nonexistent/libonnxruntime.so")]);
    assert!(log.contains("cannot load ONNX Runtime"), "{log}");
    assert!(log.contains("ORT_DYLIB_PATH"), "{log}");
}

/// No GPU here: `C4G_DEVICE=cuda` refuses to start and says what is missing (this build has no
/// `cuda` feature; a `cuda` build on a CPU-only ONNX Runtime or a machine without a GPU says
/// that instead, checked by hand with the CUDA image's binary: docs/deploy.md), while `auto`
/// starts on the CPU and says why.
#[test]
fn cuda_without_a_gpu_is_refused_at_start_and_auto_falls_back_to_the_cpu_saying_so() {
    if !ort_available() {
        return;
    }
    let log = refused_start(&[], &[("C4G_DEVICE", "cuda")]);
    assert!(log.contains("cannot load the model"), "{log}");
    assert!(log.contains("CUDA"), "{log}");
    assert!(log.contains("cuda` feature"), "{log}");

    let store = tempfile::tempdir().unwrap();
    let mut server = ServerProcess::spawn(
        store.path(),
        ANY_PORT,
        &[],
        &[("C4G_DEVICE", "auto"), ("RUST_LOG", "info")],
    );
    server.wait_ready();
    server.wait_for_log("CUDA is not available", Duration::from_secs(30));
    server.wait_for_log("the model runs on the CPU", Duration::from_secs(5));
    let id = upload_new(&server, 1.0);
    let decode = post(
        &server,
        &format!("/v1/clips/{id}/gaussians"),
        json!({"t": 0.3}),
    );
    assert_eq!(decode.status(), 200);
}

#[test]
fn a_model_run_that_fails_mid_request_answers_500_and_the_server_keeps_serving() {
    if !ort_available() {
        return;
    }
    let store = tempfile::tempdir().unwrap();
    let first = ServerProcess::start(store.path(), ANY_PORT, &[]);
    let good = upload_new(&first, 1.0);
    let bad = upload_new(&first, 2.0);
    first.kill();
    // Features of the right size that are all NaN: they load, and the decoder (a real ONNX
    // Runtime run) turns them into Gaussians the engine refuses.
    let features = model_dir(store.path())
        .join("clips")
        .join(&bad)
        .join("features.f32");
    let size = std::fs::metadata(&features).unwrap().len() as usize;
    let nan: Vec<u8> = f32::NAN
        .to_le_bytes()
        .into_iter()
        .cycle()
        .take(size)
        .collect();
    std::fs::write(&features, nan).unwrap();

    let mut server = ServerProcess::start(store.path(), ANY_PORT, &[]);
    let decode = post(
        &server,
        &format!("/v1/clips/{bad}/gaussians"),
        json!({"t": 0.3}),
    );
    let message = expect_error(decode, 500, "internal");
    assert!(
        message.contains("the model produced invalid output"),
        "{message}"
    );
    let render = post(
        &server,
        &format!("/v1/clips/{bad}/render"),
        json!({"t": 0.3}),
    );
    expect_error(render, 500, "internal");
    runtime().block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let status = grpc
            .decode(pb::DecodeRequest {
                clip_id: bad.clone(),
                times: vec![0.3],
                ..Default::default()
            })
            .await
            .unwrap_err();
        assert_eq!(status.code(), tonic::Code::Internal, "{status:?}");
        assert_eq!(kind_of(&status), "internal");
        let mut stream = grpc
            .stream_gaussians(long_stream(&bad, 1.2))
            .await
            .unwrap()
            .into_inner();
        let status = stream.message().await.unwrap_err();
        assert_eq!(status.code(), tonic::Code::Internal, "{status:?}");
    });
    // A failed run is that request's: the model stays loaded and serves the other clips.
    assert!(server.alive());
    assert_eq!(get(&server, "/ready").status(), 200);
    decode_ok(&server, &good);
    assert!(server.log().contains("the model produced invalid output"));
}

// ---- draining -----------------------------------------------------------------------------------

/// Opens `GET /v1/jobs/{id}/events` on its own connection and reads until the first event.
fn events_stream(addr: SocketAddr, id: &str) -> TcpStream {
    let mut stream = TcpStream::connect(addr).unwrap();
    write!(
        stream,
        "GET /v1/jobs/{id}/events HTTP/1.1\r\nHost: {addr}\r\nAccept: text/event-stream\r\n\r\n"
    )
    .unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    let mut seen = Vec::new();
    let mut buffer = [0u8; 4096];
    while !String::from_utf8_lossy(&seen).contains("event: job") {
        let n = stream.read(&mut buffer).unwrap();
        assert!(n > 0, "the event stream closed before its first event");
        seen.extend_from_slice(&buffer[..n]);
    }
    stream
}

/// A ready server on a new store that logs at info (where the drain is told) and drains within
/// `timeout` seconds.
fn draining_server(timeout: &str) -> (tempfile::TempDir, ServerProcess) {
    let store = tempfile::tempdir().unwrap();
    let mut server = ServerProcess::spawn(
        store.path(),
        ANY_PORT,
        &[],
        &[("RUST_LOG", "info"), ("C4G_DRAIN_TIMEOUT_S", timeout)],
    );
    server.wait_ready();
    (store, server)
}

/// Reads until the server closes the connection; how long that took.
fn until_closed(stream: &mut TcpStream, within: Duration) -> Duration {
    let started = Instant::now();
    stream.set_read_timeout(Some(within)).unwrap();
    let mut buffer = [0u8; 4096];
    loop {
        match stream.read(&mut buffer) {
            Ok(0) => return started.elapsed(),
            Ok(_) => {}
            Err(e) => panic!("the connection was still open after {within:?}: {e}"),
        }
    }
}

/// SIGTERM drains (`docs/deploy.md`, "Draining"): an upload whose body is still arriving
/// finishes and is stored, a job's event stream (which would otherwise last as long as the job)
/// ends at once, no new connection is taken, and the process exits 0 as soon as the upload has
/// been answered, well inside its 30 s deadline.
#[test]
fn sigterm_lets_requests_in_flight_finish_ends_event_streams_and_exits_0() {
    if !ort_available() {
        return;
    }
    let (store, mut server) = draining_server("30");
    // A queued job (no worker runs) and its event stream.
    let queued_clip = upload_new(&server, 1.0);
    let job_id = submit(&server, &queued_clip, 2);
    let mut events = events_stream(server.addr, &job_id);
    // An upload of another clip, half its body sent.
    let (frames, times) = clip(2.0);
    let body = multipart_bytes(&frames, &times, BOUNDARY);
    let mut uploading = upload_head(server.addr, body.len());
    uploading.write_all(&body[..body.len() / 2]).unwrap();
    std::thread::sleep(Duration::from_millis(300));

    server.terminate();
    server.wait_for_log("draining", Duration::from_secs(10));
    let ended = until_closed(&mut events, Duration::from_secs(10));
    assert!(
        TcpStream::connect_timeout(&server.addr, Duration::from_secs(2)).is_err(),
        "a new connection was taken while draining"
    );
    // The rest of the body, after the drain began: the upload is answered and stored.
    uploading.write_all(&body[body.len() / 2..]).unwrap();
    let (status, text) = read_response(&mut uploading);
    assert_eq!(status, 201, "{text}");
    let stored: Value = serde_json::from_str(&text).unwrap();
    let started = Instant::now();
    let exit = server.wait_exit(Duration::from_secs(25));
    assert!(exit.success(), "{exit}:\n{}", server.log());
    eprintln!(
        "drain: the event stream closed {ended:?} after the server logged the drain; it exited {:?} after \
         the upload was answered",
        started.elapsed()
    );
    assert!(
        !server.log().contains("took longer than"),
        "{}",
        server.log()
    );

    // Both clips are there after a restart, and the job is still queued.
    let again = ServerProcess::start(store.path(), ANY_PORT, &[]);
    for id in [queued_clip.as_str(), stored["id"].as_str().unwrap()] {
        assert_eq!(
            get(&again, &format!("/v1/clips/{id}")).status(),
            200,
            "{id}"
        );
    }
    assert_eq!(job(&again, &job_id)["state"], "queued");
}

/// A request that never finishes (a body that stops arriving) holds a drain only until
/// `C4G_DRAIN_TIMEOUT_S`: then it is cut, the process says so and exits, far before the body
/// timeout (300 s) would have ended the request.
#[test]
fn a_drain_that_outlasts_its_deadline_is_cut_when_the_deadline_passes() {
    if !ort_available() {
        return;
    }
    let (_store, mut server) = draining_server("1");
    let (frames, times) = clip(3.0);
    let body = multipart_bytes(&frames, &times, BOUNDARY);
    let mut stuck = upload_head(server.addr, body.len());
    stuck.write_all(&body[..body.len() / 3]).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let started = Instant::now();
    server.terminate();
    let exit = server.wait_exit(Duration::from_secs(15));
    let took = started.elapsed();
    assert!(exit.success(), "{exit}:\n{}", server.log());
    assert!(
        server.log().contains("took longer than"),
        "{}",
        server.log()
    );
    assert!(
        took >= Duration::from_secs(1),
        "exited after {took:?}, before its deadline"
    );
    eprintln!("drain cut at its 1 s deadline: exited {took:?} after SIGTERM");
}
