//! Refinement end to end: `c4g-server` and `c4g-refiner` as processes on loopback, with the tiny
//! Wan-VACE fixture package. A rendered trajectory of a clip is refined; a worker killed mid-job
//! leaves the job queued for another attempt (never stuck in `running`), a worker sent SIGTERM
//! hands its job back without spending an attempt, a cancelled job stops at its worker's next
//! step, and jobs that ended are deleted once their retention has passed. A worker on the
//! C4G-layout fixture gets exactly its keyframes and refines only the novel views.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::io::{BufRead, BufReader};
use std::process::Command;
use std::time::{Duration, Instant};

use c4g_e2e::{RefinerWorker, Server, binary, ort_available, upload_synthetic, workspace};
use reqwest::blocking::Client;
use serde_json::{Value, json};

fn worker(server: &Server, name: &str) -> RefinerWorker {
    RefinerWorker::start(&server.url(), name)
}

fn job(client: &Client, server: &Server, id: &str) -> Value {
    client
        .get(server.at(&format!("/v1/jobs/{id}")))
        .send()
        .unwrap()
        .json()
        .unwrap()
}

/// Polls job `id` until `done` says so, or panics after `limit`.
fn wait_for(
    client: &Client,
    server: &Server,
    id: &str,
    limit: Duration,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + limit;
    loop {
        let record = job(client, server, id);
        if done(&record) {
            return record;
        }
        assert!(Instant::now() < deadline, "job never got there: {record:#}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn a_worker_refines_a_rendered_trajectory_and_reports_every_step() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let clip = upload_synthetic(&server);
    let client = Client::new();
    let _worker = worker(&server, "w1");
    let submitted = client
        .post(server.at(&format!("/v1/clips/{clip}/refine")))
        .json(&json!({"trajectory": {"kind": "orbit", "depth": 2.0, "angle_degrees": 10}, "steps": 3, "seed": 7,
                      "caption": "a red cube slides across a table", "negative_prompt": "blurry"}))
        .send()
        .unwrap();
    assert_eq!(submitted.status(), 202);
    let location = submitted.headers()["location"].to_str().unwrap().to_owned();
    let id = submitted.json::<Value>().unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned();
    assert_eq!(location, format!("/v1/jobs/{id}"));

    // Progress as server-sent events: every step, then the terminal state, then the end.
    let events = client
        .get(server.at(&format!("/v1/jobs/{id}/events")))
        .send()
        .unwrap();
    let mut steps = Vec::new();
    let mut last = Value::Null;
    for line in BufReader::new(events).lines() {
        let line = line.unwrap();
        if let Some(data) = line.strip_prefix("data: ") {
            last = serde_json::from_str(data).unwrap();
            if let Some(step) = last["progress"]["step"].as_u64() {
                steps.push(step);
            }
        }
    }
    assert_eq!(last["state"], "done", "{last:#}");
    steps.dedup();
    assert!(steps.contains(&3), "{steps:?}");
    assert_eq!(last["worker"], "w1");

    let frames = last["result_frames"].as_u64().unwrap();
    assert!(frames >= 1);
    let png = client
        .get(server.at(&format!("/v1/jobs/{id}/result?frame=0")))
        .send()
        .unwrap();
    assert_eq!(png.headers()["content-type"], "image/png");
    let image = image::load_from_memory(&png.bytes().unwrap()).unwrap();
    let package: Value = serde_json::from_slice(
        &std::fs::read(workspace().join("models/fixtures/wan-vace-tiny/refiner.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(u64::from(image.width()), package["width"].as_u64().unwrap());
    let video = client
        .get(server.at(&format!("/v1/jobs/{id}/result")))
        .send()
        .unwrap();
    assert_eq!(video.headers()["content-type"], "video/mp4");
    assert_eq!(&video.bytes().unwrap()[4..8], b"ftyp");
}

/// Submits a 2-step refinement of `clip` with `prompt` merged into the request, and returns the
/// first refined frame once the job is done.
fn refined_frame(client: &Client, server: &Server, clip: &str, prompt: Value) -> Vec<u8> {
    let mut request = json!({"trajectory": {"kind": "orbit", "depth": 2.0, "angle_degrees": 10}, "steps": 2, "seed": 3});
    request
        .as_object_mut()
        .unwrap()
        .extend(prompt.as_object().unwrap().clone());
    let submitted = client
        .post(server.at(&format!("/v1/clips/{clip}/refine")))
        .json(&request)
        .send()
        .unwrap();
    assert_eq!(submitted.status(), 202);
    let id = submitted.json::<Value>().unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned();
    let record = wait_for(client, server, &id, Duration::from_secs(120), |j| {
        j["state"] != "queued" && j["state"] != "running"
    });
    assert_eq!(record["state"], "done", "{record:#}");
    client
        .get(server.at(&format!("/v1/jobs/{id}/result?frame=0")))
        .send()
        .unwrap()
        .bytes()
        .unwrap()
        .to_vec()
}

#[test]
fn the_caption_and_negative_prompt_steer_the_result_and_bad_prompts_are_refused() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let clip = upload_synthetic(&server);
    let client = Client::new();
    let _worker = worker(&server, "w-text");
    let cube = refined_frame(&client, &server, &clip, json!({"caption": "a red cube"}));
    // Text is cleaned as the reference pipeline cleans it: the same prompt, the same frame.
    let spaced = refined_frame(
        &client,
        &server,
        &clip,
        json!({"caption": "  a red\n cube  "}),
    );
    let dog = refined_frame(
        &client,
        &server,
        &clip,
        json!({"caption": "a dog runs on the lawn"}),
    );
    let negative = refined_frame(
        &client,
        &server,
        &clip,
        json!({"caption": "a red cube", "negative_prompt": "blurry"}),
    );
    assert_eq!(cube, spaced);
    assert_ne!(cube, dog);
    assert_ne!(cube, negative);

    for (body, says) in [
        (
            json!({"caption": "a", "text_embedding": vec![0.0; 32], "text_tokens": 1}),
            "not both",
        ),
        (
            json!({"negative_prompt": "x".repeat(10_001)}),
            "at most 10000",
        ),
        (
            json!({"negative_embedding": vec![0.0; 32]}),
            "needs text_embedding",
        ),
    ] {
        let answer = client
            .post(server.at(&format!("/v1/clips/{clip}/refine")))
            .json(&body)
            .send()
            .unwrap();
        assert_eq!(answer.status(), 400);
        let text = answer.text().unwrap();
        assert!(text.contains(says), "{text}");
    }
}

#[test]
fn the_cli_refines_with_a_progress_report_and_downloads_the_video() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let clip = upload_synthetic(&server);
    let _worker = worker(&server, "w-cli");
    let out = tempfile::tempdir().unwrap();
    let video = out.path().join("refined.mp4");
    let output = Command::new(binary("c4g"))
        .args([
            "--server",
            &server.url(),
            "refine",
            &clip,
            "--orbit",
            "10",
            "--steps",
            "2",
            "--caption",
            "a red cube slides across a table",
            "--negative-prompt",
            "blurry",
            "-o",
        ])
        .arg(&video)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(stdout.contains("wrote"), "{stdout}");
    assert_eq!(&std::fs::read(&video).unwrap()[4..8], b"ftyp");
}

#[test]
fn a_c4g_layout_worker_takes_exactly_its_keyframes_and_returns_the_novel_views_only() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let clip = upload_synthetic(&server);
    let client = Client::new();
    let package = "models/fixtures/wan-vace-tiny-c4g";
    let _worker = RefinerWorker::start_with(&server.url(), "w-c4g", &["--package", package]);
    let manifest: Value = serde_json::from_slice(
        &std::fs::read(workspace().join(package).join("refiner.json")).unwrap(),
    )
    .unwrap();
    let novel = manifest["frames"].as_u64().unwrap();

    // From the CLI, with the layout's defaults but for the steps: every novel view comes back.
    let out = tempfile::tempdir().unwrap();
    let video = out.path().join("refined.mp4");
    let output = Command::new(binary("c4g"))
        .args([
            "--server",
            &server.url(),
            "refine",
            &clip,
            "--orbit",
            "10",
            "--steps",
            "2",
            "-o",
        ])
        .arg(&video)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert_eq!(&std::fs::read(&video).unwrap()[4..8], b"ftyp");
    let jobs: Value = client
        .get(server.at("/v1/jobs"))
        .send()
        .unwrap()
        .json()
        .unwrap();
    let done = &jobs["jobs"][0];
    assert_eq!(done["state"], "done", "{jobs:#}");
    assert_eq!(done["result_frames"].as_u64(), Some(novel), "{done:#}");
    assert_eq!(done["progress"]["steps"], 2, "{done:#}");

    // Fewer cameras than the model's frames: padded for the model, only the asked ones back.
    let submit = |body: Value| -> String {
        let answer = client
            .post(server.at(&format!("/v1/clips/{clip}/refine")))
            .json(&body)
            .send()
            .unwrap();
        assert_eq!(answer.status(), 202);
        answer.json::<Value>().unwrap()["id"]
            .as_str()
            .unwrap()
            .to_owned()
    };
    let ended = |record: &Value| matches!(record["state"].as_str(), Some("done" | "failed"));
    let id = submit(json!({"cameras": [{}, {}], "steps": 1}));
    let record = wait_for(&client, &server, &id, Duration::from_secs(120), ended);
    assert_eq!(record["state"], "done", "{record:#}");
    assert_eq!(record["result_frames"], 2, "{record:#}");

    // Another keyframe count than the model's fails the job with a reason.
    let id = submit(json!({"context_frames": 2, "steps": 1}));
    let record = wait_for(&client, &server, &id, Duration::from_secs(120), ended);
    assert_eq!(record["state"], "failed", "{record:#}");
    assert!(
        record["error"].as_str().unwrap().contains("exactly 3"),
        "{record:#}"
    );
}

#[test]
fn a_killed_worker_leaves_its_job_queued_for_another_attempt_and_cancelling_stops_it() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&["--job-lease-s", "2", "--job-attempts", "3"]);
    let clip = upload_synthetic(&server);
    let client = Client::new();
    let mut first = worker(&server, "doomed");
    // Many steps: the job is still running when the worker is killed.
    let submitted: Value = client
        .post(server.at(&format!("/v1/clips/{clip}/refine")))
        .json(&json!({"steps": 1000}))
        .send()
        .unwrap()
        .json()
        .unwrap();
    let id = submitted["id"].as_str().unwrap().to_owned();
    wait_for(&client, &server, &id, Duration::from_secs(120), |j| {
        j["state"] == "running" && j["progress"]["step"].as_u64().unwrap_or(0) >= 1
    });
    first.0.kill().unwrap();
    first.0.wait().unwrap();

    // The lease runs out: queued again, on its second attempt, with the reason recorded.
    let requeued = wait_for(&client, &server, &id, Duration::from_secs(30), |j| {
        j["state"] != "running"
    });
    assert_eq!(requeued["state"], "queued", "{requeued:#}");
    assert_eq!(requeued["attempt"], 2);
    assert!(
        requeued["history"][0]
            .as_str()
            .unwrap()
            .contains("doomed stopped responding"),
        "{requeued:#}"
    );

    // Another worker takes it; a cancellation stops it at its next step.
    let _second = worker(&server, "survivor");
    wait_for(&client, &server, &id, Duration::from_secs(120), |j| {
        j["state"] == "running"
            && j["worker"] == "survivor"
            && j["progress"]["step"].as_u64().unwrap_or(0) >= 1
    });
    let cancelled = client
        .post(server.at(&format!("/v1/jobs/{id}/cancel")))
        .send()
        .unwrap();
    assert_eq!(cancelled.status(), 200);
    let done = wait_for(&client, &server, &id, Duration::from_secs(60), |j| {
        j["state"] != "running"
    });
    assert_eq!(done["state"], "cancelled", "{done:#}");
    let result = client
        .get(server.at(&format!("/v1/jobs/{id}/result")))
        .send()
        .unwrap();
    assert_eq!(result.status(), 400);
}

/// A rolling update sends every worker SIGTERM: the worker must not cost its job an attempt nor
/// leave it for the lease to take back. Checks that a worker sent SIGTERM mid-job (1) exits 0
/// within seconds, well under the lease (60 s here: the lease running out cannot be what
/// requeues the job), (2) has by then handed the job back (`Release`): `queued` on its first
/// attempt still, the history saying why, (3) that the job runs anew and finishes on a worker
/// started afterwards, and (4) that an idle worker (waiting in `Take`) exits 0 at once too.
#[test]
fn a_worker_sent_sigterm_hands_its_job_back_without_spending_an_attempt_and_exits() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&["--job-lease-s", "60", "--job-attempts", "3"]);
    let clip = upload_synthetic(&server);
    let client = Client::new();
    let mut first = worker(&server, "rolled");
    // Enough steps that the job is still running when the signal lands (a step of the tiny
    // fixture takes ~10 ms); few enough that the second worker finishes it in seconds.
    let submitted: Value = client
        .post(server.at(&format!("/v1/clips/{clip}/refine")))
        .json(&json!({"steps": 300, "seed": 5}))
        .send()
        .unwrap()
        .json()
        .unwrap();
    let id = submitted["id"].as_str().unwrap().to_owned();
    wait_for(&client, &server, &id, Duration::from_secs(120), |j| {
        j["state"] == "running"
            && j["worker"] == "rolled"
            && j["progress"]["step"].as_u64().unwrap_or(0) >= 1
    });
    let took = terminate(&mut first);
    eprintln!("the busy worker exited {took:?} after SIGTERM");

    // Handed back before the worker exited: queued, on the same attempt, saying why.
    let released = job(&client, &server, &id);
    assert_eq!(released["state"], "queued", "{released:#}");
    assert_eq!(released["attempt"], 1, "{released:#}");
    assert!(released["worker"].is_null(), "{released:#}");
    let history = released["history"][0].as_str().unwrap();
    assert!(
        history.contains("rolled") && history.contains("the worker is stopping"),
        "{released:#}"
    );

    // Another worker runs it from the start, to the end.
    let mut second = worker(&server, "successor");
    let done = wait_for(&client, &server, &id, Duration::from_secs(120), |j| {
        j["state"] != "queued" && j["state"] != "running"
    });
    assert_eq!(done["state"], "done", "{done:#}");
    assert_eq!(done["worker"], "successor", "{done:#}");
    assert_eq!(done["attempt"], 1, "{done:#}");
    assert!(done["result_frames"].as_u64().unwrap() >= 1, "{done:#}");

    let took = terminate(&mut second);
    eprintln!("the idle worker exited {took:?} after SIGTERM");
}

/// Sends `worker` SIGTERM and waits for it to exit, at most 15 s; asserts it exited 0, and
/// returns how long it took.
fn terminate(worker: &mut RefinerWorker) -> Duration {
    let signalled = Instant::now();
    let kill = Command::new("kill")
        .args(["-TERM", &worker.0.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let status = loop {
        if let Some(status) = worker.0.try_wait().unwrap() {
            break status;
        }
        assert!(
            signalled.elapsed() < Duration::from_secs(15),
            "the worker did not exit within 15 s of SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(10));
    };
    assert!(status.success(), "{status:?}");
    signalled.elapsed()
}

/// `C4G_JOB_RETENTION_H`: a job that ended is deleted once its retention has passed (the server
/// looks when it starts and once a minute), a queued one never; the default keeps it a week.
#[test]
fn jobs_that_ended_are_deleted_after_their_retention_and_queued_ones_are_kept() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let clip = upload_synthetic(&server);
    let client = Client::new();
    let submit = || -> String {
        let job: Value = client
            .post(server.at(&format!("/v1/clips/{clip}/refine")))
            .json(&json!({"steps": 2}))
            .send()
            .unwrap()
            .json()
            .unwrap();
        job["id"].as_str().unwrap().to_owned()
    };
    let (ended, queued) = (submit(), submit());
    let cancelled = client
        .post(server.at(&format!("/v1/jobs/{ended}/cancel")))
        .send()
        .unwrap();
    assert_eq!(cancelled.status(), 200);
    let store = server.stop();
    // A week's retention (the default) keeps it across a restart.
    let server = Server::start_in(store, &[]);
    assert_eq!(job(&client, &server, &ended)["state"], "cancelled");
    std::thread::sleep(Duration::from_millis(1500));
    let store = server.stop();
    // A second's retention: deleted when the server starts; the queued job stays.
    let server = Server::start_in(store, &["--job-retention-h", "0.0002"]);
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let status = client
            .get(server.at(&format!("/v1/jobs/{ended}")))
            .send()
            .unwrap()
            .status();
        if status == 404 {
            break;
        }
        assert!(Instant::now() < deadline, "the ended job was not deleted");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(job(&client, &server, &queued)["state"], "queued");
}
