//! A soak: mixed traffic against the real `c4g-server` (release build, default model c4g-tiny,
//! a temporary store) and one `c4g-refiner` worker (the tiny Wan-VACE fixture) for
//! `C4G_SOAK_S` seconds (default 120), to find what only time shows: memory or file
//! descriptors that creep up, answers that go wrong after many requests, a store or a job list
//! that drifts from what was done to it (docs/reliability.md, "Soak").
//!
//! Traffic, from a few client threads with short random pauses:
//! - two uploaders: new clips (the synthetic test clip varied in frame content, frame count and
//!   timestamps, so every upload is a clip never seen before), re-uploads of stored ones (they
//!   must deduplicate: `200`, `"created": false`, the same id) and deletes of their own older
//!   clips, so the store stays small while thousands of distinct clips pass through it;
//! - two readers: decodes (REST JSON and binary, f32 and f16, presets exact / balanced / fast),
//!   single PNG renders and small MP4 trajectory renders, of any stored clip;
//! - one streamer: gRPC `StreamGaussians`, half read to the end (the set count checked), half
//!   dropped after a few sets;
//! - one refiner: 2-step refinement jobs followed until they end, some cancelled at once, some
//!   on a clip deleted right after the job was submitted, and done jobs' results fetched.
//!
//! Every answer must be a success with a well-formed body or a documented refusal: `429 busy`
//! or `503 overloaded` / `not_ready` with `Retry-After` (which the client then honours), or
//! `404` for a clip another thread deleted (gRPC: the same kinds). Anything else (a 500, another
//! 4xx, a malformed body, a transport error) is a failure: counted, the first ones printed, and
//! the bench exits with status 1.
//!
//! Every 10 s (and at the start and the end) it samples the resident memory (`VmRSS`) and the
//! open file descriptors (`/proc/PID/fd`) of the server and of the worker. **Level-off
//! criterion**: the mean of the last third of the samples against the mean of the middle third
//! (the first third is warm-up: caches, the allocator's pools, connection pools); the soak
//! fails if either process's RSS grows by more than 20 % or its descriptors by more than 10
//! between them. A leak proportional to traffic shows as growth between those thirds; a bounded
//! cache filling up does not, once it is full. RSS also counts memory the allocator keeps after
//! it is freed (glibc's malloc keeps a lot: docs/reliability.md, "Soak").
//!
//! At the end, once traffic has stopped: `GET /v1/clips` must list exactly the clips that should
//! be stored (none deleted, none missing), each read back (`GET`, a decode at its first context
//! time) agreeing with what its upload answered; every job submitted must be in a final state
//! that fits what was done to it, and every done job's result must be fetchable.
//!
//! Prints a summary table (per operation: ok / refused / failed, p50 / p99 latency of the
//! successes; RSS and descriptors at the start, middle and end, and their growth); writes the
//! samples as CSV to `C4G_SOAK_CSV` when set. `C4G_SOAK_SEED` picks another (reproducible)
//! mix. Run: `scripts/soak [SECONDS]` (it builds the release binaries first).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::collections::{BTreeMap, BTreeSet};
use std::io::Cursor;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use c4g_e2e::{RefinerWorker, Server, peak_rss, synthetic_clip};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use reqwest::StatusCode;
use reqwest::blocking::{Client, RequestBuilder, multipart};
use reqwest::header::HeaderMap;
use serde_json::{Value, json};

/// How often memory and descriptors are sampled.
const SAMPLE_EVERY: Duration = Duration::from_secs(10);
/// Largest RSS growth allowed from the middle third of the samples to the last.
const RSS_GROWTH_LIMIT: f64 = 0.20;
/// Largest growth in open descriptors allowed from the middle third to the last.
const FD_GROWTH_LIMIT: f64 = 10.0;
/// Clips uploaded first and never deleted (every reader always has something to read).
const KEPT_CLIPS: u64 = 3;
/// Clips an uploader keeps at most before it deletes its oldest.
const LIVE_PER_UPLOADER: usize = 4;
/// Longest a Retry-After is honoured (a refusal asking for more is waited on this long).
const MAX_BACKOFF: Duration = Duration::from_secs(5);
/// Longest a job is followed before the soak calls it stuck.
const JOB_PATIENCE: Duration = Duration::from_secs(300);
/// Failures printed in full (all are counted).
const FAILURES_SHOWN: usize = 30;
const QUALITIES: [&str; 3] = ["exact", "balanced", "fast"];

/// A small deterministic generator (xorshift64*): the mix is reproducible from `C4G_SOAK_SEED`
/// without a dependency.
struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Self {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }

    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// Uniform in `[0, 1)`.
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }

    fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len())]
    }
}

/// A stored clip as its upload answered.
#[derive(Clone, Debug)]
struct Clip {
    id: String,
    context_times: Vec<f64>,
    /// Which variant of the synthetic clip it is (to upload the same bytes again).
    variant: u64,
}

impl Clip {
    fn span(&self) -> (f64, f64) {
        (self.context_times[0], *self.context_times.last().unwrap())
    }

    fn time(&self, rng: &mut Rng) -> f64 {
        let (a, b) = self.span();
        a + (b - a) * rng.unit()
    }
}

/// What should be stored, as the client threads have made it.
#[derive(Default)]
struct Clips {
    kept: Vec<Clip>,
    /// Uploaded and not deleted (the kept ones excluded).
    live: BTreeMap<String, Clip>,
    /// Deleted, or being deleted: a 404 for one of these is a refusal, not a failure.
    gone: BTreeSet<String>,
    /// A delete that failed: stored or not, either is accepted at the end.
    uncertain: BTreeSet<String>,
}

/// A refinement job as submitted.
struct Job {
    id: String,
    /// A cancel was sent: `cancelled` (or `done`, when it finished first) is expected.
    cancelled: bool,
    /// Its clip was deleted right after: `failed` for the missing clip is accepted too.
    doomed: bool,
}

#[derive(Default)]
struct OpStats {
    ok: u64,
    refused: u64,
    failed: u64,
    /// Refusals by kind (`busy`, `overloaded`, `not_ready`, `gone`: the clip was deleted).
    refusals: BTreeMap<&'static str, u64>,
    /// Seconds, successes only.
    latencies: Vec<f64>,
}

enum Outcome {
    Ok,
    /// A documented refusal: its kind, and the wait it asked for.
    Refused(&'static str, Option<Duration>),
    Failed(String),
}

/// One sample of both processes.
#[derive(Clone, Copy)]
struct Sample {
    t_s: f64,
    server_rss_kib: u64,
    server_fds: u64,
    worker_rss_kib: u64,
    worker_fds: u64,
}

/// What every thread shares.
struct Soak {
    server: String,
    deadline: Instant,
    stats: Mutex<BTreeMap<&'static str, OpStats>>,
    failures: Mutex<Vec<String>>,
    failure_count: AtomicU64,
    clips: Mutex<Clips>,
    jobs: Mutex<Vec<Job>>,
    /// The next variant of the synthetic clip to upload (every one is a new clip).
    variants: AtomicU64,
    frames: Variants,
}

/// The synthetic test clip's frames in three contents (as is, mirrored, brightened), as PNG.
struct Variants {
    contents: [Vec<Vec<u8>>; 3],
    times: Vec<f64>,
}

impl Variants {
    fn load() -> Self {
        let (paths, times) = synthetic_clip();
        let images: Vec<image::RgbImage> = paths
            .iter()
            .map(|p| image::open(p).unwrap().to_rgb8())
            .collect();
        let png = |image: &image::RgbImage| {
            let mut bytes = Vec::new();
            image
                .write_to(&mut Cursor::new(&mut bytes), image::ImageFormat::Png)
                .unwrap();
            bytes
        };
        let plain = images.iter().map(png).collect();
        let mirrored = images
            .iter()
            .map(|i| png(&image::imageops::flip_horizontal(i)))
            .collect();
        let brighter = images
            .iter()
            .map(|i| png(&image::imageops::colorops::brighten(i, 24)))
            .collect();
        Variants {
            contents: [plain, mirrored, brighter],
            times,
        }
    }

    /// Variant `n`: content `n % 3`, all 7 frames or the first 5, times stretched by 1 to 1.75
    /// and shifted by `n` ms. The timestamps differ for every `n`, so every variant is a clip of
    /// its own (ids address the bytes and the options).
    fn form(&self, n: u64) -> multipart::Form {
        let frames = &self.contents[(n % 3) as usize];
        let count = if n.is_multiple_of(2) { frames.len() } else { 5 };
        let stretch = 1.0 + 0.25 * ((n / 3) % 4) as f64;
        let times: Vec<String> = self.times[..count]
            .iter()
            .map(|t| format!("{}", t * stretch + 0.001 * n as f64))
            .collect();
        let mut form = multipart::Form::new().text("timestamps", times.join(","));
        for (k, bytes) in frames[..count].iter().enumerate() {
            form = form.part(
                "frame",
                multipart::Part::bytes(bytes.clone()).file_name(format!("frame-{k:02}.png")),
            );
        }
        form
    }
}

fn client() -> Client {
    Client::builder()
        .timeout(Duration::from_secs(300))
        .build()
        .unwrap()
}

fn retry_after(headers: &HeaderMap) -> Option<Duration> {
    let seconds: f64 = headers
        .get("retry-after")?
        .to_str()
        .ok()?
        .trim()
        .parse()
        .ok()?;
    Some(Duration::from_secs_f64(seconds.max(0.0)))
}

fn kind_of(body: &[u8]) -> String {
    serde_json::from_slice::<Value>(body)
        .ok()
        .and_then(|v| v["kind"].as_str().map(str::to_owned))
        .unwrap_or_default()
}

fn shorten(text: &str) -> String {
    text.chars().take(300).collect()
}

impl Soak {
    fn running(&self) -> bool {
        Instant::now() < self.deadline
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.server)
    }

    fn gone(&self, id: &str) -> bool {
        self.clips.lock().unwrap().gone.contains(id)
    }

    /// Counts an outcome, and waits as long as a refusal asked (bounded).
    fn record(&self, op: &'static str, started: Instant, outcome: Outcome) {
        let elapsed = started.elapsed().as_secs_f64();
        let wait = {
            let mut stats = self.stats.lock().unwrap();
            let entry = stats.entry(op).or_default();
            match outcome {
                Outcome::Ok => {
                    entry.ok += 1;
                    entry.latencies.push(elapsed);
                    None
                }
                Outcome::Refused(kind, wait) => {
                    entry.refused += 1;
                    *entry.refusals.entry(kind).or_default() += 1;
                    wait
                }
                Outcome::Failed(why) => {
                    entry.failed += 1;
                    self.fail(format!("{op}: {why}"));
                    None
                }
            }
        };
        if let Some(wait) = wait {
            std::thread::sleep(wait.min(MAX_BACKOFF));
        }
    }

    fn fail(&self, why: String) {
        self.failure_count.fetch_add(1, Ordering::Relaxed);
        let mut failures = self.failures.lock().unwrap();
        if failures.len() < FAILURES_SHOWN {
            eprintln!("FAILURE: {why}");
            failures.push(why);
        }
    }

    /// What a non-success answer means: a documented refusal, or a failure.
    fn refusal(
        &self,
        status: StatusCode,
        headers: &HeaderMap,
        body: &[u8],
        clip: Option<&str>,
    ) -> Outcome {
        let kind = kind_of(body);
        let wait = retry_after(headers);
        match (status.as_u16(), kind.as_str(), wait) {
            (429, "busy", Some(_)) => Outcome::Refused("busy", wait),
            (503, "overloaded", Some(_)) => Outcome::Refused("overloaded", wait),
            (503, "not_ready", Some(_)) => Outcome::Refused("not_ready", wait),
            (404, "not_found", _) if clip.is_some_and(|id| self.gone(id)) => {
                Outcome::Refused("gone", None)
            }
            _ => Outcome::Failed(format!(
                "{status}: {}",
                shorten(&String::from_utf8_lossy(body))
            )),
        }
    }

    /// Sends `request`; an answer with a status in `expect` goes to `check` (which judges its
    /// body); anything else is a refusal or a failure. Gives what `check` made on success.
    fn call<T>(
        &self,
        op: &'static str,
        clip: Option<&str>,
        request: RequestBuilder,
        expect: &[u16],
        check: impl FnOnce(StatusCode, &HeaderMap, &[u8]) -> Result<T, String>,
    ) -> Option<T> {
        let started = Instant::now();
        let mut value = None;
        let outcome = match request.send() {
            Err(e) => Outcome::Failed(format!("transport: {e}")),
            Ok(response) => {
                let status = response.status();
                let headers = response.headers().clone();
                match response.bytes() {
                    Err(e) => Outcome::Failed(format!("{status}, reading the body: {e}")),
                    Ok(body) if expect.contains(&status.as_u16()) => {
                        match check(status, &headers, &body) {
                            Ok(v) => {
                                value = Some(v);
                                Outcome::Ok
                            }
                            Err(why) => Outcome::Failed(why),
                        }
                    }
                    Ok(body) => self.refusal(status, &headers, &body, clip),
                }
            }
        };
        self.record(op, started, outcome);
        value
    }

    /// Uploads variant `n`; `again` says it was stored before (and must deduplicate).
    fn upload(&self, http: &Client, n: u64, again: Option<&Clip>) -> Option<Clip> {
        let op = if again.is_some() {
            "re-upload"
        } else {
            "upload"
        };
        self.call(
            op,
            None,
            http.post(self.url("/v1/clips"))
                .multipart(self.frames.form(n)),
            &[200, 201],
            |status, _, body| {
                let clip: Value = serde_json::from_slice(body).map_err(|e| e.to_string())?;
                let made = Clip {
                    id: clip["id"].as_str().ok_or("no id")?.to_owned(),
                    context_times: clip["context_times"]
                        .as_array()
                        .ok_or("no context_times")?
                        .iter()
                        .filter_map(Value::as_f64)
                        .collect(),
                    variant: n,
                };
                let created = clip["created"] == true;
                match again {
                    None if status != 201 || !created => Err(format!(
                        "a new clip (variant {n}) answered {status}, created {}",
                        clip["created"]
                    )),
                    Some(before) if status != 200 || created => Err(format!(
                        "a stored clip {} (variant {n}) answered {status}, created {}",
                        before.id, clip["created"]
                    )),
                    Some(before)
                        if before.id != made.id || before.context_times != made.context_times =>
                    {
                        Err(format!("re-upload of {before:?} answered {made:?}"))
                    }
                    _ if made.context_times.len() < 2 => {
                        Err(format!("context times {:?}", made.context_times))
                    }
                    _ => Ok(made),
                }
            },
        )
    }

    fn delete(&self, http: &Client, clip: &Clip) {
        self.clips.lock().unwrap().gone.insert(clip.id.clone());
        let deleted = self.call(
            "delete",
            None,
            http.delete(self.url(&format!("/v1/clips/{}", clip.id))),
            &[204],
            |_, _, _| Ok(()),
        );
        if deleted.is_none() {
            self.clips.lock().unwrap().uncertain.insert(clip.id.clone());
        }
    }

    /// Any stored clip (kept or live).
    fn any_clip(&self, rng: &mut Rng) -> Clip {
        let clips = self.clips.lock().unwrap();
        let k = rng.below(clips.kept.len() + clips.live.len());
        match k.checked_sub(clips.kept.len()) {
            None => clips.kept[k].clone(),
            Some(i) => clips.live.values().nth(i).unwrap().clone(),
        }
    }
}

/// Uploads, re-uploads and deletes its own clips.
fn uploader(soak: &Soak, seed: u64) {
    let http = client();
    let mut rng = Rng::new(seed);
    let mut own: Vec<Clip> = Vec::new();
    while soak.running() {
        let r = rng.unit();
        if (r < 0.3 && !own.is_empty()) || own.len() >= LIVE_PER_UPLOADER {
            let clip = own.remove(0);
            soak.clips.lock().unwrap().live.remove(&clip.id);
            soak.delete(&http, &clip);
        } else if r < 0.6 {
            let stored = if own.is_empty() || rng.unit() < 0.3 {
                rng.pick(&soak.clips.lock().unwrap().kept).clone()
            } else {
                rng.pick(&own).clone()
            };
            soak.upload(&http, stored.variant, Some(&stored));
        } else {
            let n = soak.variants.fetch_add(1, Ordering::Relaxed);
            if let Some(clip) = soak.upload(&http, n, None) {
                soak.clips
                    .lock()
                    .unwrap()
                    .live
                    .insert(clip.id.clone(), clip.clone());
                own.push(clip);
            }
        }
        pause(&mut rng);
    }
}

/// The C4GS header's frame count and Gaussians, checked against the body's length.
fn check_binary(body: &[u8], times: usize, f16: bool) -> Result<(), String> {
    if body.len() < 16 || &body[..4] != b"C4GS" {
        return Err(format!("not C4GS ({} bytes)", body.len()));
    }
    let frames = u32::from_le_bytes(body[8..12].try_into().unwrap()) as usize;
    let n = u32::from_le_bytes(body[12..16].try_into().unwrap()) as usize;
    let scalar = if f16 { 2 } else { 4 };
    let want = 16 + frames * (8 + n * 14 * scalar);
    if frames != times || n == 0 || body[6] != u8::from(f16) || body.len() != want {
        return Err(format!(
            "C4GS of {frames} frames of {n}, precision {}, {} bytes (want {want})",
            body[6],
            body.len()
        ));
    }
    Ok(())
}

/// Decodes and renders any stored clip.
fn reader(soak: &Soak, seed: u64) {
    let http = client();
    let mut rng = Rng::new(seed);
    while soak.running() {
        let clip = soak.any_clip(&mut rng);
        let quality = *rng.pick(&QUALITIES);
        let r = rng.unit();
        if r < 0.35 {
            let times: Vec<f64> = (0..1 + rng.below(3)).map(|_| clip.time(&mut rng)).collect();
            soak.call(
                "decode json",
                Some(&clip.id),
                http.post(soak.url(&format!("/v1/clips/{}/gaussians", clip.id)))
                    .json(&json!({"times": times, "quality": quality})),
                &[200],
                |_, _, body| {
                    let decoded: Value = serde_json::from_slice(body).map_err(|e| e.to_string())?;
                    let frames = decoded["frames"].as_array().ok_or("no frames")?;
                    let well_formed = frames.iter().all(|f| {
                        f["count"].as_u64().is_some_and(|n| {
                            n > 0 && f["means"].as_array().map(Vec::len) == Some(n as usize)
                        })
                    });
                    if frames.len() == times.len() && well_formed {
                        Ok(())
                    } else {
                        Err(format!("{} frames for {} times", frames.len(), times.len()))
                    }
                },
            );
        } else if r < 0.65 {
            let f16 = rng.unit() < 0.5;
            soak.call(
                "decode binary",
                Some(&clip.id),
                http.post(soak.url(&format!("/v1/clips/{}/gaussians", clip.id)))
                    .json(&json!({"t": clip.time(&mut rng), "format": "binary",
                                  "precision": if f16 { "f16" } else { "f32" }, "quality": quality})),
                &[200],
                |_, _, body| check_binary(body, 1, f16),
            );
        } else if r < 0.93 {
            let size = 64 + 32 * rng.below(3);
            soak.call(
                "render png",
                Some(&clip.id),
                http.post(soak.url(&format!("/v1/clips/{}/render", clip.id)))
                    .json(
                        &json!({"t": clip.time(&mut rng), "width": size, "height": size,
                                  "quality": quality}),
                    ),
                &[200],
                |_, headers, body| {
                    let width = headers.get("x-c4g-width").and_then(|v| v.to_str().ok());
                    if body.starts_with(b"\x89PNG") && width == Some(&size.to_string()) {
                        Ok(())
                    } else {
                        Err(format!("not a {size}-wide PNG ({} bytes)", body.len()))
                    }
                },
            );
        } else {
            soak.call(
                "render mp4",
                Some(&clip.id),
                http.post(soak.url(&format!("/v1/clips/{}/render", clip.id)))
                    .json(
                        &json!({"trajectory": {"kind": "orbit", "depth": 2.0, "angle_degrees": 20},
                                  "frames": 4, "width": 64, "height": 64, "quality": quality}),
                    ),
                &[200],
                |_, headers, body| {
                    let mp4 = headers.get("content-type").and_then(|v| v.to_str().ok())
                        == Some("video/mp4");
                    if mp4 && body.len() > 8 && &body[4..8] == b"ftyp" {
                        Ok(())
                    } else {
                        Err(format!("not an MP4 ({} bytes)", body.len()))
                    }
                },
            );
        }
        pause(&mut rng);
    }
}

/// What a gRPC error means: a documented refusal, or a failure.
fn grpc_refusal(soak: &Soak, status: &tonic::Status, clip: &str) -> Outcome {
    let kind = status
        .metadata()
        .get("c4g-error-kind")
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default();
    let wait = status
        .metadata()
        .get("retry-after")
        .and_then(|v| v.to_str().ok()?.trim().parse::<f64>().ok())
        .map(|s| Duration::from_secs_f64(s.max(0.0)));
    match (status.code(), kind, wait) {
        (tonic::Code::ResourceExhausted, "busy", Some(_)) => Outcome::Refused("busy", wait),
        (tonic::Code::Unavailable, "overloaded", Some(_)) => Outcome::Refused("overloaded", wait),
        (tonic::Code::Unavailable, "not_ready", Some(_)) => Outcome::Refused("not_ready", wait),
        (tonic::Code::NotFound, _, _) if soak.gone(clip) => Outcome::Refused("gone", None),
        _ => Outcome::Failed(format!(
            "{:?} ({kind}): {}",
            status.code(),
            status.message()
        )),
    }
}

/// Streams sets over gRPC: half read to the end, half dropped after a few.
fn streamer(soak: &Soak, seed: u64) {
    let mut rng = Rng::new(seed);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(async {
        let mut grpc = C4gClient::connect(soak.server.clone()).await.unwrap();
        while soak.running() {
            let clip = soak.any_clip(&mut rng);
            let (start, end) = clip.span();
            let whole = rng.unit() < 0.5;
            // Read to the end: 30 sets a second. Dropped: 2,000 sets, so that the server is
            // still decoding when the client goes.
            let step = if whole {
                1.0 / 30.0
            } else {
                (end - start) / 1999.0
            };
            let want = ((end - start) / step + 1e-9).floor() as usize + 1;
            let quality = match rng.below(3) {
                0 => pb::Quality::Exact,
                1 => pb::Quality::Balanced,
                _ => pb::Quality::Fast,
            };
            let precision = if rng.unit() < 0.5 {
                pb::Precision::F32
            } else {
                pb::Precision::F16
            };
            let op = if whole {
                "stream whole"
            } else {
                "stream dropped"
            };
            let started = Instant::now();
            let request = pb::StreamGaussiansRequest {
                clip_id: clip.id.clone(),
                spacing: Some(pb::stream_gaussians_request::Spacing::Step(step)),
                quality: quality as i32,
                precision: precision as i32,
                ..Default::default()
            };
            let outcome = match grpc.stream_gaussians(request).await {
                Err(status) => grpc_refusal(soak, &status, &clip.id),
                Ok(response) => {
                    let mut frames = response.into_inner();
                    let limit = if whole { want } else { 3 };
                    let mut got = 0usize;
                    let mut last = f64::NEG_INFINITY;
                    let mut outcome = Outcome::Ok;
                    while got < limit {
                        match frames.message().await {
                            Ok(Some(frame)) => {
                                let count = frame.gaussians.map_or(0, |g| g.count);
                                if count == 0 || frame.time < last || frame.time > end + 1e-9 {
                                    outcome = Outcome::Failed(format!(
                                        "set {got}: {count} Gaussians at {} after {last}",
                                        frame.time
                                    ));
                                    break;
                                }
                                last = frame.time;
                                got += 1;
                            }
                            Ok(None) => {
                                outcome = Outcome::Failed(format!(
                                    "the stream ended after {got} of {want} sets"
                                ));
                                break;
                            }
                            Err(status) => {
                                outcome = grpc_refusal(soak, &status, &clip.id);
                                break;
                            }
                        }
                    }
                    if whole && matches!(outcome, Outcome::Ok) {
                        // Nothing after the last set.
                        match frames.message().await {
                            Ok(None) => {}
                            Ok(Some(_)) => {
                                outcome = Outcome::Failed(format!("more than {want} sets"));
                            }
                            Err(status) => outcome = grpc_refusal(soak, &status, &clip.id),
                        }
                    }
                    // Dropped here: mid-stream for the dropped ones.
                    outcome
                }
            };
            soak.record(op, started, outcome);
            tokio::time::sleep(Duration::from_millis(20 + rng.below(80) as u64)).await;
        }
    });
}

/// Follows job `id` until it ends (or [`JOB_PATIENCE`] runs out); gives its last record.
fn follow(soak: &Soak, http: &Client, id: &str) -> Option<Value> {
    let deadline = Instant::now() + JOB_PATIENCE;
    while Instant::now() < deadline {
        let record = soak.call(
            "job status",
            None,
            http.get(soak.url(&format!("/v1/jobs/{id}"))),
            &[200],
            |_, _, body| serde_json::from_slice::<Value>(body).map_err(|e| e.to_string()),
        );
        if let Some(record) = record
            && !matches!(record["state"].as_str(), Some("queued" | "running"))
        {
            return Some(record);
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    None
}

/// Fetches a done job's result: the MP4 and its first frame as PNG.
fn fetch_result(soak: &Soak, http: &Client, op: &'static str, id: &str) -> bool {
    let video = soak.call(
        op,
        None,
        http.get(soak.url(&format!("/v1/jobs/{id}/result"))),
        &[200],
        |_, _, body| {
            if body.len() > 8 && &body[4..8] == b"ftyp" {
                Ok(())
            } else {
                Err(format!("job {id}'s result is not an MP4"))
            }
        },
    );
    let frame = soak.call(
        op,
        None,
        http.get(soak.url(&format!("/v1/jobs/{id}/result?frame=0"))),
        &[200],
        |_, _, body| {
            if body.starts_with(b"\x89PNG") {
                Ok(())
            } else {
                Err(format!("job {id}'s frame 0 is not a PNG"))
            }
        },
    );
    video.is_some() && frame.is_some()
}

/// Submits 2-step refinement jobs and follows each until it ends.
fn refiner(soak: &Soak, seed: u64) {
    let http = client();
    let mut rng = Rng::new(seed);
    let mut submitted = 0u64;
    while soak.running() {
        submitted += 1;
        let doomed = submitted.is_multiple_of(6);
        let cancelled = !doomed && submitted.is_multiple_of(5);
        let clip = if doomed {
            let n = soak.variants.fetch_add(1, Ordering::Relaxed);
            let Some(clip) = soak.upload(&http, n, None) else {
                continue;
            };
            clip
        } else {
            rng.pick(&soak.clips.lock().unwrap().kept).clone()
        };
        let job = soak.call(
            "refine submit",
            Some(&clip.id),
            http.post(soak.url(&format!("/v1/clips/{}/refine", clip.id)))
                .json(&json!({"steps": 2, "seed": submitted})),
            &[202],
            |_, _, body| {
                let record: Value = serde_json::from_slice(body).map_err(|e| e.to_string())?;
                Ok(record["id"].as_str().ok_or("no job id")?.to_owned())
            },
        );
        if doomed {
            soak.delete(&http, &clip);
        }
        let Some(id) = job else {
            continue;
        };
        if cancelled {
            soak.call(
                "refine cancel",
                None,
                http.post(soak.url(&format!("/v1/jobs/{id}/cancel"))),
                &[200],
                |_, _, _| Ok(()),
            );
        }
        soak.jobs.lock().unwrap().push(Job {
            id: id.clone(),
            cancelled,
            doomed,
        });
        if let Some(record) = follow(soak, &http, &id)
            && record["state"] == "done"
        {
            fetch_result(soak, &http, "refine result", &id);
        }
        pause(&mut rng);
    }
}

/// A short random think time between one thread's requests.
fn pause(rng: &mut Rng) {
    std::thread::sleep(Duration::from_millis(20 + rng.below(80) as u64));
}

/// Resident memory (KiB) and open descriptors of process `pid` (0 when it is gone).
fn usage(pid: u32) -> (u64, u64) {
    let rss = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|status| {
            let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
            line.split_whitespace().nth(1)?.parse().ok()
        })
        .unwrap_or(0);
    let fds = std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count() as u64);
    (rss, fds)
}

fn sample(begun: Instant, server: u32, worker: u32) -> Sample {
    let (server_rss_kib, server_fds) = usage(server);
    let (worker_rss_kib, worker_fds) = usage(worker);
    Sample {
        t_s: begun.elapsed().as_secs_f64(),
        server_rss_kib,
        server_fds,
        worker_rss_kib,
        worker_fds,
    }
}

/// The `q`-quantile (nearest rank) of sorted `values`.
fn quantile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let rank = ((q * values.len() as f64).ceil() as usize).clamp(1, values.len());
    values[rank - 1]
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    sum / n as f64
}

/// Growth from the middle third of the samples to the last third, by `field`: (ratio − 1, and
/// the difference of the means).
fn growth(samples: &[Sample], field: impl Fn(&Sample) -> u64) -> (f64, f64) {
    let n = samples.len();
    let middle = mean(samples[n / 3..2 * n / 3].iter().map(|s| field(s) as f64));
    let last = mean(samples[2 * n / 3..].iter().map(|s| field(s) as f64));
    (last / middle - 1.0, last - middle)
}

/// The end-of-run checks: the store as listed agrees with what was done to it, every clip reads
/// back as its upload answered, every job ended as it should and done jobs' results are there.
fn final_check(soak: &Soak) {
    let http = client();
    let listed: Option<Vec<String>> = soak.call(
        "final list",
        None,
        http.get(soak.url("/v1/clips")),
        &[200],
        |_, _, body| {
            let list: Value = serde_json::from_slice(body).map_err(|e| e.to_string())?;
            Ok(list["clips"]
                .as_array()
                .ok_or("no clips")?
                .iter()
                .filter_map(|c| c["id"].as_str().map(str::to_owned))
                .collect())
        },
    );
    let listed: BTreeSet<String> = listed.unwrap_or_default().into_iter().collect();
    let expected: BTreeMap<String, Clip> = {
        let clips = soak.clips.lock().unwrap();
        let mut expected = clips.live.clone();
        for clip in &clips.kept {
            expected.insert(clip.id.clone(), clip.clone());
        }
        for id in &listed {
            if !expected.contains_key(id) && !clips.uncertain.contains(id) {
                soak.fail(format!(
                    "final list: {id} is listed but {}",
                    if clips.gone.contains(id) {
                        "was deleted"
                    } else {
                        "was never uploaded"
                    }
                ));
            }
        }
        expected
    };
    println!(
        "final check: {} clips listed, {} expected",
        listed.len(),
        expected.len()
    );
    for (id, clip) in &expected {
        if !listed.contains(id) {
            soak.fail(format!("final list: {id} is stored but not listed"));
        }
        soak.call(
            "final get",
            None,
            http.get(soak.url(&format!("/v1/clips/{id}"))),
            &[200],
            |_, _, body| {
                let got: Value = serde_json::from_slice(body).map_err(|e| e.to_string())?;
                let times: Vec<f64> = got["context_times"]
                    .as_array()
                    .ok_or("no context_times")?
                    .iter()
                    .filter_map(Value::as_f64)
                    .collect();
                if got["id"] == id.as_str() && times == clip.context_times {
                    Ok(())
                } else {
                    Err(format!("{id} reads back as {got}, uploaded as {clip:?}"))
                }
            },
        );
        soak.call(
            "final decode",
            None,
            http.post(soak.url(&format!("/v1/clips/{id}/gaussians")))
                .json(&json!({"t": clip.context_times[0], "format": "binary"})),
            &[200],
            |_, _, body| check_binary(body, 1, false),
        );
    }
    let jobs = std::mem::take(&mut *soak.jobs.lock().unwrap());
    let mut states: BTreeMap<String, u64> = BTreeMap::new();
    for job in &jobs {
        let Some(record) = follow(soak, &http, &job.id) else {
            soak.fail(format!("job {} never ended", job.id));
            continue;
        };
        let state = record["state"].as_str().unwrap_or_default().to_owned();
        let error = record["error"].as_str().unwrap_or_default();
        let fits = match state.as_str() {
            "done" => fetch_result(soak, &http, "final result", &job.id),
            "cancelled" => job.cancelled,
            // The clip went before a worker took the job: the job says so.
            "failed" => job.doomed && error.contains("no clip"),
            _ => false,
        };
        if !fits {
            soak.fail(format!(
                "job {} (cancel sent: {}, clip deleted: {}) ended {state}: {}",
                job.id,
                job.cancelled,
                job.doomed,
                shorten(&record.to_string())
            ));
        }
        *states.entry(state).or_default() += 1;
    }
    println!("jobs: {} submitted, ended {states:?}", jobs.len());
}

fn main() {
    if std::env::var_os("ORT_DYLIB_PATH").is_none() {
        eprintln!("set ORT_DYLIB_PATH (scripts/env.sh)");
        std::process::exit(2);
    }
    let seconds: f64 = std::env::var("C4G_SOAK_S")
        .ok()
        .map_or(120.0, |s| s.parse().expect("C4G_SOAK_S: seconds"));
    let seed: u64 = std::env::var("C4G_SOAK_SEED")
        .ok()
        .map_or(1, |s| s.parse().expect("C4G_SOAK_SEED: an integer"));

    let mut server = Server::start(&[]);
    let mut worker = RefinerWorker::start(&server.url(), "soak");
    let (server_pid, worker_pid) = (server.pid(), worker.0.id());

    let soak = Arc::new(Soak {
        server: server.url(),
        deadline: Instant::now() + Duration::from_secs_f64(seconds),
        stats: Mutex::default(),
        failures: Mutex::default(),
        failure_count: AtomicU64::new(0),
        clips: Mutex::default(),
        jobs: Mutex::default(),
        variants: AtomicU64::new(KEPT_CLIPS),
        frames: Variants::load(),
    });
    let http = client();
    for n in 0..KEPT_CLIPS {
        let clip = soak
            .upload(&http, n, None)
            .expect("the kept clips must upload");
        soak.clips.lock().unwrap().kept.push(clip);
    }
    println!(
        "soak: {seconds} s against {} (server pid {server_pid}, worker pid {worker_pid}), seed {seed}",
        soak.server
    );

    let begun = Instant::now();
    let samples = Arc::new(Mutex::new(vec![sample(begun, server_pid, worker_pid)]));
    let stop = Arc::new(AtomicBool::new(false));
    let sampler = {
        let (samples, stop) = (samples.clone(), stop.clone());
        std::thread::spawn(move || {
            let mut next = begun + SAMPLE_EVERY;
            while !stop.load(Ordering::Relaxed) {
                if Instant::now() >= next {
                    let s = sample(begun, server_pid, worker_pid);
                    println!(
                        "t={:>5.0} s  server {} MiB, {} fds; worker {} MiB, {} fds",
                        s.t_s,
                        s.server_rss_kib >> 10,
                        s.server_fds,
                        s.worker_rss_kib >> 10,
                        s.worker_fds
                    );
                    samples.lock().unwrap().push(s);
                    next += SAMPLE_EVERY;
                }
                std::thread::sleep(Duration::from_millis(200));
            }
        })
    };

    std::thread::scope(|scope| {
        let s = &*soak;
        scope.spawn(move || uploader(s, seed ^ 0x11));
        scope.spawn(move || uploader(s, seed ^ 0x22));
        scope.spawn(move || reader(s, seed ^ 0x33));
        scope.spawn(move || reader(s, seed ^ 0x44));
        scope.spawn(move || streamer(s, seed ^ 0x55));
        scope.spawn(move || refiner(s, seed ^ 0x66));
    });
    stop.store(true, Ordering::Relaxed);
    sampler.join().unwrap();
    let traffic_s = begun.elapsed().as_secs_f64();
    samples
        .lock()
        .unwrap()
        .push(sample(begun, server_pid, worker_pid));

    if !server.alive() {
        soak.fail("the server died".into());
    }
    if worker.0.try_wait().unwrap().is_some() {
        soak.fail("the worker died".into());
    }
    final_check(&soak);

    // The summary.
    let stats = soak.stats.lock().unwrap();
    let total: u64 = stats.values().map(|s| s.ok + s.refused + s.failed).sum();
    println!(
        "\n{total} requests in {traffic_s:.0} s of traffic ({:.1}/s), {} distinct clips uploaded",
        total as f64 / traffic_s,
        soak.variants.load(Ordering::Relaxed)
    );
    println!("| operation | ok | refused | failed | p50 | p99 |");
    println!("|---|---|---|---|---|---|");
    for (op, s) in stats.iter() {
        let mut latencies = s.latencies.clone();
        latencies.sort_by(f64::total_cmp);
        println!(
            "| {op} | {} | {} | {} | {:.0} ms | {:.0} ms |",
            s.ok,
            s.refused,
            s.failed,
            quantile(&latencies, 0.5) * 1e3,
            quantile(&latencies, 0.99) * 1e3
        );
    }
    let refusals: Vec<String> = stats
        .iter()
        .flat_map(|(op, s)| {
            s.refusals
                .iter()
                .map(move |(kind, count)| format!("{op}: {kind} {count}"))
        })
        .collect();
    if !refusals.is_empty() {
        println!("refusals: {}", refusals.join("; "));
    }
    let samples = samples.lock().unwrap().clone();
    let n = samples.len();
    println!("\n{n} samples, every {} s", SAMPLE_EVERY.as_secs());
    println!("| process | measure | start | middle | end | growth (last third / middle third) |");
    println!("|---|---|---|---|---|---|");
    let mut leaks = Vec::new();
    type Field = fn(&Sample) -> u64;
    let measures: [(&str, &str, Field, bool); 4] = [
        ("server", "RSS MiB", |s| s.server_rss_kib, true),
        ("server", "fds", |s| s.server_fds, false),
        ("worker", "RSS MiB", |s| s.worker_rss_kib, true),
        ("worker", "fds", |s| s.worker_fds, false),
    ];
    for (process, measure, field, memory) in measures {
        let shown = |s: &Sample| {
            if memory {
                format!("{:.1}", field(s) as f64 / 1024.0)
            } else {
                field(s).to_string()
            }
        };
        let judged = if n >= 6 {
            let (ratio, difference) = growth(&samples, field);
            let over = if memory {
                ratio > RSS_GROWTH_LIMIT
            } else {
                difference > FD_GROWTH_LIMIT
            };
            if over {
                leaks.push(format!("{process} {measure}"));
            }
            if memory {
                format!("{:+.1} %", ratio * 100.0)
            } else {
                format!("{difference:+.1}")
            }
        } else {
            "too few samples to judge".into()
        };
        println!(
            "| {process} | {measure} | {} | {} | {} | {judged} |",
            shown(&samples[0]),
            shown(&samples[n / 2]),
            shown(&samples[n - 1]),
        );
    }
    println!(
        "server peak RSS {} MiB",
        peak_rss(server_pid).unwrap_or(0) >> 20
    );
    if let Some(path) = std::env::var_os("C4G_SOAK_CSV") {
        let mut csv = String::from("t_s,server_rss_kib,server_fds,worker_rss_kib,worker_fds\n");
        for s in &samples {
            csv.push_str(&format!(
                "{:.1},{},{},{},{}\n",
                s.t_s, s.server_rss_kib, s.server_fds, s.worker_rss_kib, s.worker_fds
            ));
        }
        std::fs::write(&path, csv).unwrap();
        println!("samples written to {}", path.to_string_lossy());
    }

    let failures = soak.failure_count.load(Ordering::Relaxed);
    for leak in &leaks {
        println!(
            "LEVEL-OFF FAILED: {leak} grew past the limit (RSS {:.0} %, fds {FD_GROWTH_LIMIT})",
            RSS_GROWTH_LIMIT * 100.0
        );
    }
    if failures > 0 || !leaks.is_empty() {
        println!("soak FAILED: {failures} failures, {} leaks", leaks.len());
        for why in soak.failures.lock().unwrap().iter() {
            println!("  {why}");
        }
        drop(stats);
        drop(worker);
        drop(server);
        std::process::exit(1);
    }
    println!("soak passed: no failures, memory and descriptors level off");
}
