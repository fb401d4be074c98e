//! The `c4g` binary as a process: help, and how it reports errors (against a fake server that
//! answers one canned HTTP response, not a c4g server).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::TcpListener;
use std::process::{Command, Output};

fn c4g(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_c4g"))
        .args(args)
        .env_remove("C4G_SERVER")
        .env_remove("C4G_API_KEY")
        .output()
        .unwrap()
}

#[test]
fn help_lists_every_command_and_the_global_flags() {
    let out = c4g(&["--help"]);
    assert!(out.status.success());
    let help = String::from_utf8(out.stdout).unwrap();
    for word in [
        "upload",
        "info",
        "clips",
        "delete",
        "decode",
        "export",
        "render",
        "stream",
        "fit",
        "refine",
        "job",
        "jobs",
        "cancel",
        "--server",
        "--api-key",
        "--json",
        "C4G_SERVER",
        "C4G_API_KEY",
    ] {
        assert!(help.contains(word), "--help lacks {word}:\n{help}");
    }
}

#[test]
fn every_subcommand_has_help() {
    for command in [
        "upload", "info", "clips", "delete", "decode", "export", "render", "stream", "fit",
        "refine", "job", "jobs", "cancel",
    ] {
        let out = c4g(&[command, "--help"]);
        assert!(out.status.success(), "{command} --help failed");
        assert!(!out.stdout.is_empty());
    }
}

#[test]
fn refine_help_names_its_options() {
    let out = c4g(&["refine", "--help"]);
    assert!(out.status.success());
    let help = String::from_utf8(out.stdout).unwrap();
    for word in [
        "<CLIP>",
        "--orbit <DEGREES>",
        "--depth <D>",
        "--trajectory <JSON>",
        "--start",
        "--end",
        "--steps <N>",
        "--guidance <G>",
        "--shift <S>",
        "--sampler",
        "unipc",
        "euler",
        "--seed <N>",
        "--caption <TEXT>",
        "--context-frames <N>",
        "--output <OUT.mp4>",
        "--no-wait",
        "--json",
    ] {
        assert!(help.contains(word), "refine --help lacks {word}:\n{help}");
    }
    for command in ["job", "cancel"] {
        let out = c4g(&[command, "--help"]);
        let help = String::from_utf8(out.stdout).unwrap();
        assert!(help.contains("<JOB>"), "{command} --help:\n{help}");
    }
}

#[test]
fn refine_usage_errors_exit_non_zero() {
    for args in [
        &["refine"][..],
        &[
            "refine",
            "clip",
            "--orbit",
            "20",
            "--trajectory",
            "{\"kind\": \"dolly\"}",
        ],
        &["refine", "clip", "--depth", "3"],
        &["refine", "clip", "--no-wait", "-o", "x.mp4"],
        &["refine", "clip", "--sampler", "ddim"],
        &["refine", "clip", "--steps", "-1"],
        &["job"],
        &["cancel"],
    ] {
        let out = c4g(args);
        assert_eq!(
            out.status.code(),
            Some(2),
            "{args:?} should be a usage error"
        );
    }
}

#[test]
fn usage_errors_exit_non_zero() {
    assert!(
        !c4g(&["decode", "clip"]).status.success(),
        "--t is required"
    );
    assert!(
        !c4g(&["stream", "clip", "--step", "0.1", "--fps", "10"])
            .status
            .success(),
        "--step and --fps conflict"
    );
    assert!(
        !c4g(&[
            "render", "clip", "--t", "0.5", "--orbit", "30", "-o", "x.mp4"
        ])
        .status
        .success(),
        "--t and a trajectory conflict"
    );
}

#[test]
fn an_api_error_prints_status_kind_and_message() {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let address = listener.local_addr().unwrap();
    let server = std::thread::spawn(move || {
        let (mut socket, _) = listener.accept().unwrap();
        let mut request = [0u8; 4096];
        let n = socket.read(&mut request).unwrap();
        let body =
            r#"{"error": "no clip abc; list clips with GET /v1/clips", "kind": "not_found"}"#;
        write!(
            socket,
            "HTTP/1.1 404 Not Found\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\
             connection: close\r\n\r\n{body}",
            body.len()
        )
        .unwrap();
        String::from_utf8_lossy(&request[..n]).into_owned()
    });
    let server_url = format!("http://{address}");
    let out = c4g(&["--server", &server_url, "--api-key", "k3y", "info", "abc"]);
    let request = server.join().unwrap();
    assert!(request.starts_with("GET /v1/clips/abc "), "{request}");
    assert!(
        request
            .to_ascii_lowercase()
            .contains("authorization: bearer k3y"),
        "{request}"
    );
    assert!(!out.status.success());
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert_eq!(
        stderr.trim(),
        "error: 404 not_found: no clip abc; list clips with GET /v1/clips"
    );
}

#[test]
fn an_unreachable_server_is_an_error_not_a_panic() {
    // Bind then drop: the port is (almost certainly) closed.
    let address = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let out = c4g(&["--server", &format!("http://{address}"), "clips"]);
    assert!(!out.status.success());
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(
        stderr.starts_with("error: request to the server failed"),
        "{stderr}"
    );
}

/// A fake server for whole commands: answers each request (one per connection) with the body
/// `route` gives its request line; returns its address and the request lines it served.
fn serve(
    route: impl Fn(&str) -> (&'static str, &'static str, Vec<u8>) + Send + 'static,
    requests: usize,
) -> (String, std::thread::JoinHandle<Vec<String>>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let address = format!("http://{}", listener.local_addr().unwrap());
    let server = std::thread::spawn(move || {
        let mut lines = Vec::new();
        for _ in 0..requests {
            let (mut socket, _) = listener.accept().unwrap();
            let mut received = Vec::new();
            let mut buffer = [0u8; 4096];
            let head_end = loop {
                let n = socket.read(&mut buffer).unwrap();
                received.extend_from_slice(&buffer[..n]);
                if let Some(i) = received.windows(4).position(|w| w == b"\r\n\r\n") {
                    break i + 4;
                }
            };
            let head = String::from_utf8_lossy(&received[..head_end]).into_owned();
            let length: usize = head
                .lines()
                .find_map(|l| {
                    l.to_ascii_lowercase()
                        .strip_prefix("content-length:")
                        .map(|v| v.trim().parse().unwrap())
                })
                .unwrap_or(0);
            while received.len() < head_end + length {
                let n = socket.read(&mut buffer).unwrap();
                received.extend_from_slice(&buffer[..n]);
            }
            let line = head.lines().next().unwrap().to_owned();
            let (status, content_type, body) = route(&line);
            write!(
                socket,
                "HTTP/1.1 {status}\r\ncontent-type: {content_type}\r\ncontent-length: {}\r\n\
                 connection: close\r\n\r\n",
                body.len()
            )
            .unwrap();
            socket.write_all(&body).unwrap();
            lines.push(line);
        }
        lines
    });
    (address, server)
}

fn job_json(state: &str, fields: serde_json::Value) -> String {
    let mut job = serde_json::json!({
        "id": "job-01", "clip_id": "3f2a", "state": state, "attempt": 1, "max_attempts": 3,
        "worker": null, "progress": null, "error": null, "history": [], "result_frames": 2,
        "seconds": null,
    });
    for (key, value) in fields.as_object().unwrap() {
        job[key] = value.clone();
    }
    job.to_string()
}

fn events(records: &[String]) -> Vec<u8> {
    records
        .iter()
        .map(|r| format!("event: job\ndata: {r}\n\n:\n\n"))
        .collect::<String>()
        .into_bytes()
}

#[test]
fn refine_follows_the_job_and_writes_the_result() {
    let dir = tempfile::tempdir().unwrap();
    let output = dir.path().join("out.mp4");
    let (server, handle) = serve(
        |line| match line.split(' ').nth(1).unwrap() {
            "/v1/clips/3f2a/refine" => (
                "202 Accepted",
                "application/json",
                job_json("queued", serde_json::json!({})).into(),
            ),
            "/v1/jobs/job-01/events" => (
                "200 OK",
                "text/event-stream",
                events(&[
                    job_json("queued", serde_json::json!({})),
                    job_json(
                        "running",
                        serde_json::json!({"progress": {"step": 1, "steps": 4, "stage": "denoising"}}),
                    ),
                    job_json("done", serde_json::json!({})),
                ]),
            ),
            "/v1/jobs/job-01/result" => ("200 OK", "video/mp4", b"mp4 bytes".to_vec()),
            other => panic!("unexpected {other}"),
        },
        3,
    );
    let out = c4g(&[
        "--server",
        &server,
        "refine",
        "3f2a",
        "--orbit",
        "20",
        "--steps",
        "4",
        "-o",
        output.to_str().unwrap(),
    ]);
    let lines = handle.join().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        lines,
        [
            "POST /v1/clips/3f2a/refine HTTP/1.1",
            "GET /v1/jobs/job-01/events HTTP/1.1",
            "GET /v1/jobs/job-01/result HTTP/1.1",
        ]
    );
    assert_eq!(
        String::from_utf8(out.stdout).unwrap(),
        format!("wrote {}\n", output.display())
    );
    assert_eq!(std::fs::read(&output).unwrap(), b"mp4 bytes");
}

#[test]
fn a_failed_refinement_exits_1_with_the_jobs_error() {
    let (server, handle) = serve(
        |line| match line.split(' ').nth(1).unwrap() {
            "/v1/clips/3f2a/refine" => (
                "202 Accepted",
                "application/json",
                job_json("queued", serde_json::json!({})).into(),
            ),
            "/v1/jobs/job-01/events" => (
                "200 OK",
                "text/event-stream",
                events(&[job_json(
                    "failed",
                    serde_json::json!({
                        "error": "out of memory (attempt 3 of 3)",
                        "history": ["attempt 1: worker w1 stopped responding"]
                    }),
                )]),
            ),
            other => panic!("unexpected {other}"),
        },
        2,
    );
    let out = c4g(&["--server", &server, "--json", "refine", "3f2a"]);
    handle.join().unwrap();
    assert_eq!(out.status.code(), Some(1));
    let stdout = String::from_utf8(out.stdout).unwrap();
    let record: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(record["state"], "failed");
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(
        stderr.contains("job job-01: attempt 1: worker w1 stopped responding"),
        "{stderr}"
    );
    assert!(
        stderr.ends_with("error: job job-01 failed: out of memory (attempt 3 of 3)\n"),
        "{stderr}"
    );
}

#[test]
fn job_jobs_cancel_and_no_wait_print_the_records() {
    let running = job_json(
        "running",
        serde_json::json!({
            "worker": "w1",
            "progress": {"step": 3, "steps": 30, "stage": "denoising"},
            "history": ["attempt 1: worker w0 stopped responding"],
            "attempt": 2,
        }),
    );
    let list = format!(r#"{{"jobs": [{running}]}}"#);
    let cancelled = job_json("cancelled", serde_json::json!({}));
    let queued = job_json("queued", serde_json::json!({}));
    let (server, handle) = serve(
        move |line| match line {
            "GET /v1/jobs/job-01 HTTP/1.1" => {
                ("200 OK", "application/json", running.clone().into())
            }
            "GET /v1/jobs HTTP/1.1" => ("200 OK", "application/json", list.clone().into()),
            "POST /v1/jobs/job-01/cancel HTTP/1.1" => {
                ("200 OK", "application/json", cancelled.clone().into())
            }
            "POST /v1/clips/3f2a/refine HTTP/1.1" => {
                ("202 Accepted", "application/json", queued.clone().into())
            }
            other => panic!("unexpected {other}"),
        },
        5,
    );
    let text = |args: &[&str]| {
        let mut all = vec!["--server", &server];
        all.extend_from_slice(args);
        let out = c4g(&all);
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8(out.stdout).unwrap()
    };
    let job = text(&["job", "job-01"]);
    assert!(job.starts_with("job-01\n"), "{job}");
    for part in [
        "running (attempt 2 of 3, worker w1)",
        "step 3/30 denoising",
        "history   attempt 1: worker w0 stopped responding",
    ] {
        assert!(job.contains(part), "{job}");
    }
    let jobs: serde_json::Value = serde_json::from_str(&text(&["--json", "jobs"])).unwrap();
    assert_eq!(jobs["jobs"][0]["progress"]["step"], 3);
    assert_eq!(text(&["cancel", "job-01"]), "cancelled job-01\n");
    let queued: serde_json::Value =
        serde_json::from_str(&text(&["--json", "refine", "3f2a", "--no-wait"])).unwrap();
    assert_eq!(queued["state"], "queued");
    let summary = text(&["refine", "3f2a", "--no-wait"]);
    assert!(
        summary.starts_with("job-01\n  clip      3f2a\n  state     queued"),
        "{summary}"
    );
    handle.join().unwrap();
}

#[test]
fn fit_help_names_its_options_and_every_set_command_takes_a_scene() {
    let out = c4g(&["fit", "--help"]);
    assert!(out.status.success());
    let help = String::from_utf8(out.stdout).unwrap();
    for word in [
        "<CLIP>",
        "--preset",
        "fast",
        "best",
        "--steps <N>",
        "--resolution <PX>",
        "--max-gaussians <N>",
        "--keyframe-every <N>",
        "--holdout-every <N>",
        "--refine-cameras",
        "--time-budget <S>",
        "--seed <N>",
        "--max-frames <N>",
        "--no-wait",
        "--json",
    ] {
        assert!(help.contains(word), "fit --help lacks {word}:\n{help}");
    }
    for command in ["decode", "export", "render", "stream", "track"] {
        let help = String::from_utf8(c4g(&[command, "--help"]).stdout).unwrap();
        assert!(
            help.contains("--scene <SCENE>") && help.contains("feed-forward"),
            "{command} --help:\n{help}"
        );
    }
}

#[test]
fn fit_usage_errors_exit_non_zero() {
    for args in [
        &["fit"][..],
        &["fit", "clip", "--preset", "quick"],
        &["fit", "clip", "--steps", "-1"],
        &["fit", "clip", "--time-budget", "soon"],
        &["decode", "clip", "--t", "0.5", "--scene", "fit"],
    ] {
        assert_eq!(c4g(args).status.code(), Some(2), "{args:?}");
    }
}

fn fit_job_json(state: &str, fields: serde_json::Value) -> String {
    let mut job: serde_json::Value = serde_json::from_str(&job_json(state, fields)).unwrap();
    job["kind"] = "fit".into();
    job["result_frames"] = 0.into();
    job.to_string()
}

#[test]
fn fit_follows_the_job_and_prints_what_the_fit_made() {
    let clip = serde_json::json!({
        "id": "3f2a", "state": "ready", "context_times": [0.0, 0.6],
        "fitted": {"job_id": "job-01", "preset": "fast", "gaussians": 900,
                   "static_gaussians": 700, "keyframes": [0.0, 0.3, 0.6], "steps": 8,
                   "seconds": 2.5, "frames": 8, "resolution": [32, 32],
                   "holdout_frames": [3, 7], "holdout_times": [0.3, 0.7],
                   "holdout_psnr": 21.0, "holdout_psnr_feed_forward": 16.0,
                   "train_psnr": 22.0, "stopped_early": false, "created_at": 5}
    })
    .to_string();
    let route = move |line: &str| match line.split(' ').nth(1).unwrap() {
        "/v1/clips/3f2a/fit" => (
            "202 Accepted",
            "application/json",
            fit_job_json("queued", serde_json::json!({})).into(),
        ),
        "/v1/jobs/job-01/events" => (
            "200 OK",
            "text/event-stream",
            events(&[
                fit_job_json("queued", serde_json::json!({})),
                fit_job_json(
                    "running",
                    serde_json::json!({"progress": {"step": 4, "steps": 8, "stage": "fitting",
                        "loss": 0.2, "holdout_psnr": 18.0, "gaussians": 900, "elapsed_s": 1.0}}),
                ),
                fit_job_json("done", serde_json::json!({"seconds": 2.5})),
            ]),
        ),
        "/v1/clips/3f2a" => ("200 OK", "application/json", clip.clone().into()),
        other => panic!("unexpected {other}"),
    };
    let (server, handle) = serve(route.clone(), 3);
    let out = c4g(&[
        "--server", &server, "fit", "3f2a", "--preset", "fast", "--steps", "8",
    ]);
    let lines = handle.join().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        lines,
        [
            "POST /v1/clips/3f2a/fit HTTP/1.1",
            "GET /v1/jobs/job-01/events HTTP/1.1",
            "GET /v1/clips/3f2a HTTP/1.1",
        ]
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.starts_with("3f2a\n"), "{text}");
    for part in [
        "held-out  21.00 dB PSNR fitted, 16.00 feed-forward (+5.00 dB) on 2 frames",
        "900 Gaussians (700 static) at 3 keyframes",
        "8 steps in 2.500 s, 8 frames at 32x32, preset fast",
    ] {
        assert!(text.contains(part), "{text}");
    }

    let (server, handle) = serve(route, 3);
    let out = c4g(&["--server", &server, "--json", "fit", "3f2a"]);
    handle.join().unwrap();
    assert!(out.status.success());
    let line: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(line["clip"], "3f2a");
    assert_eq!(line["job"]["state"], "done");
    assert_eq!(line["fitted"]["holdout_psnr"], 21.0);
}

#[test]
fn a_cancelled_fit_exits_1_and_no_wait_prints_the_queued_job() {
    let (server, handle) = serve(
        |line| match line.split(' ').nth(1).unwrap() {
            "/v1/clips/3f2a/fit" => (
                "202 Accepted",
                "application/json",
                fit_job_json("queued", serde_json::json!({})).into(),
            ),
            "/v1/jobs/job-01/events" => (
                "200 OK",
                "text/event-stream",
                events(&[fit_job_json("cancelled", serde_json::json!({}))]),
            ),
            other => panic!("unexpected {other}"),
        },
        3,
    );
    let out = c4g(&["--server", &server, "fit", "3f2a"]);
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(
        stderr.ends_with("error: job job-01 was cancelled\n"),
        "{stderr}"
    );
    let out = c4g(&["--server", &server, "fit", "3f2a", "--no-wait"]);
    handle.join().unwrap();
    let summary = String::from_utf8(out.stdout).unwrap();
    assert!(
        summary.starts_with("job-01\n  kind      fit\n  clip      3f2a\n  state     queued"),
        "{summary}"
    );
}
