//! The REST contract is exact: schemathesis, with every check it has, against a live
//! `c4g-server` and the `/openapi.json` that server serves, finds no failure.
//!
//! The server starts with small limits (so that the largest renders and trajectories the schema
//! admits are cheap) and the synthetic clip uploaded, and schemathesis gets real identifiers for
//! the path parameters: the clip for every `/v1/clips/{id}/...` operation, a second clip for
//! `DELETE /v1/clips/{id}` to delete, a queued job to cancel and a cancelled one to read (its
//! event stream ends). One check is ours (`refusals_are_stated`, in [`HOOKS`]): schemathesis
//! expects a server to accept every request its schema admits, and a few refusals depend on what
//! no JSON Schema can state (the clip's context span, an invertible camera pose, what the bytes of
//! an upload hold); those are accepted only with the message that names them, which each
//! operation's description in `openapi.json` also states in words.
//!
//! Briefly in CI (a fixed seed, 10 examples per operation, renders' boundary cases negative only:
//! tens of seconds); at length with `scripts/contract` (`C4G_CONTRACT_SECONDS`, default 600, a
//! random seed, every phase in full). Settings:
//! `C4G_CONTRACT_SEED`, `C4G_CONTRACT_EXAMPLES`, `C4G_CONTRACT_SECONDS`. Without `PYTHON` (or the
//! repository's `.venv`) and schemathesis the test skips outside CI, saying why, and fails in CI.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;

use c4g_e2e::{Server, frames_form, ort_available, synthetic_clip, upload_synthetic, venv_python};
use reqwest::blocking::Client;
use serde_json::{Value, json};

/// The limits the server runs under: the smallest that take the synthetic clip (64 x 64, 0.6 s)
/// and a refinement request (whose path is checked at 8 frames), so that the largest render and
/// trajectory the schema admits are cheap, and most times it admits are inside the clip.
const SERVER_ARGS: &[&str] = &[
    "--max-side",
    "64",
    "--max-render-pixels",
    "4096",
    "--max-times",
    "8",
    "--max-duration-s",
    "1",
];

/// schemathesis hooks: our check, and the refusals it accepts with their operation, status and
/// message.
const HOOKS: &str = r#"
"""c4g's own schemathesis check (written by tests/e2e/contract.rs)."""
import re

import schemathesis

# (operation, status, message) of every refusal of a request its schema admits: what JSON
# Schema cannot state. Each operation's description in openapi.json says it in words too.
STATED_IN_WORDS = [
    (r"POST /v1/clips/\{id\}/(gaussians|render|refine)", 400, r"outside the clip's context span"),
    (r"POST /v1/clips/\{id\}/(render|refine|segment)", 400, r"invertible|rigid pose|view direction is undefined"),
    (r"POST /v1/clips/\{id\}/(render|refine)", 400, r"reaches past the focus depth|would reach the subject"),
    (r"POST /v1/clips/\{id\}/render", 400, r"frame count is the number of cameras"),
    (r"POST /v1/clips/\{id\}/render", 413, r"pixels in all"),
    (r"POST /v1/clips/\{id\}/(gaussians|render)", 400, r"make \d+ keyframes"),
    (r"POST /v1/clips/\{id\}/tracks", 400, r"outside the clip's context span|outside the \d+x\d+ image|make \d+ keyframes"),
    (r"POST /v1/clips/\{id\}/tracks", 413, r"times in one request|C4G_MAX_TRACK_QUERIES|pixels in all"),
    (r"POST /v1/clips/\{id\}/segment", 400, r"outside the clip's context span|outside the \d+x\d+ image|shows nothing to select|the feature has \d+ values|not all zeros"),
    (r"POST /v1/clips/\{id\}/segment", 413, r"times in one request|pixels in all"),
    (r"POST /v1/clips/\{id\}/(gaussians|render|tracks|segment)", 422, r"no feature decoder|do not go together: the feature decoder decodes every query"),
    (r"POST /v1/clips/\{id\}/(stream|export)", 400, r"outside the clip's context span|is after end|make \d+ keyframes|beyond C4GV's range"),
    (r"POST /v1/clips/\{id\}/(stream|export)", 413, r"sets in one stream|C4G_MAX_EXPORT_MIB|frames in one zip"),
    (r"POST /v1/clips/\{id\}/refine", 400, r"a divisor of that|shape of text_embedding"),
    (r"GET /v1/jobs/\{id\}/result", 400, r"its result exists once it is done"),
    (r"POST /v1/clips", 415, r"."),
    (r"POST /v1/clips", 422, r"."),
    (r"POST /v1/clips", 413, r"."),
    (
        r"POST /v1/clips",
        400,
        r"strictly increasing|timestamps for \d+ frames|no frames in the window|picks \d+ frames"
        r"|is after its end|holds no PNG or JPEG|camera|images\.txt|transforms\.json",
    ),
]


@schemathesis.check
def refusals_are_stated(ctx, response, case):
    """A request the schema admits is refused only for a reason its operation states in words."""
    meta = case.meta
    if meta is None or not meta.generation.mode.is_positive:
        return None
    status = response.status_code
    if status not in (400, 413, 415, 422):
        return None
    try:
        message = response.json().get("error", "")
    except Exception:
        message = response.text
    label = case.operation.label
    for operation, code, pattern in STATED_IN_WORDS:
        if code == status and re.fullmatch(operation, label) and re.search(pattern, message):
            return None
    raise AssertionError(
        f"{label} refused a request its schema admits ({status}: {message}): state the "
        "constraint in openapi.json, or accept the request"
    )
"#;

/// The Python that has schemathesis, or why there is none.
fn python() -> Result<PathBuf, String> {
    let python = venv_python();
    let found = Command::new(&python)
        .args([
            "-c",
            "import schemathesis, sys; print(schemathesis.__version__)",
        ])
        .output();
    match found {
        Ok(out) if out.status.success() => {
            eprintln!(
                "schemathesis {} ({})",
                String::from_utf8_lossy(&out.stdout).trim(),
                python.display()
            );
            Ok(python)
        }
        Ok(out) => Err(format!(
            "{} has no schemathesis ({}): scripts/setup installs it",
            python.display(),
            String::from_utf8_lossy(&out.stderr).trim()
        )),
        Err(e) => Err(format!(
            "no Python at {} ({e}): set PYTHON (source scripts/env.sh)",
            python.display()
        )),
    }
}

fn setting(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .map(|v| {
            v.parse()
                .unwrap_or_else(|_| panic!("{name} must be a number"))
        })
        .unwrap_or(default)
}

/// A second clip (the synthetic frames given a rate instead of their times: other options, so
/// another id), for `DELETE /v1/clips/{id}` to delete.
fn upload_doomed(server: &Server, client: &Client) -> String {
    let (frames, _) = synthetic_clip();
    let form = frames.iter().fold(
        reqwest::blocking::multipart::Form::new().text("fps", "10"),
        |form, path| {
            form.part(
                "frame",
                reqwest::blocking::multipart::Part::bytes(std::fs::read(path).unwrap())
                    .file_name("frame.png"),
            )
        },
    );
    let response = client
        .post(server.at("/v1/clips"))
        .multipart(form)
        .send()
        .unwrap();
    assert_eq!(response.status(), 201);
    response.json::<Value>().unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned()
}

fn refine(server: &Server, client: &Client, clip: &str, steps: u32) -> String {
    let response = client
        .post(server.at(&format!("/v1/clips/{clip}/refine")))
        .json(&json!({ "steps": steps }))
        .send()
        .unwrap();
    assert_eq!(response.status(), 202);
    response.json::<Value>().unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned()
}

/// `schemathesis.toml`: the identifiers, and the statuses schemathesis accepts besides its own
/// (too large is a refusal of data a schema bounds; the positive refusals `refusals_are_stated`
/// holds to their messages).
fn config(clip: &str, doomed: &str, queued_job: &str, ended_job: &str, brief: bool) -> String {
    // Briefly, renders get only the coverage phase's negative cases (refused in microseconds):
    // its positive ones are trajectories encoded by FFmpeg, a third of a second each, most of a
    // long run's time. Their positive cases still come from the fuzzing phase.
    let brief_render = if brief {
        r#"
[[operations]]
include-path = "/v1/clips/{id}/render"
phases.coverage.generation.mode = "negative"
"#
    } else {
        ""
    };
    format!(
        r#"
# Nothing carried over from an earlier run.
[cache]
enabled = false

# Seconds: a debug build on a busy machine renders a trajectory in a few, not in the 10
# schemathesis expects; this check is for answers that never come.
[checks]
max_response_time = 60

[checks.positive_data_acceptance]
expected-statuses = ["2xx", "3xx", "400", "401", "403", "404", "409", "413", "415", "422", "429", "5xx"]

[checks.negative_data_rejection]
expected-statuses = ["400", "401", "403", "404", "405", "406", "409", "413", "415", "422", "428", "429", "5xx"]

[[operations]]
include-path-regex = '^/v1/clips/\{{id\}}'
exclude-method = "DELETE"
parameters = {{ id = "{clip}" }}

[[operations]]
include-path = "/v1/clips/{{id}}"
include-method = "DELETE"
parameters = {{ id = "{doomed}" }}

[[operations]]
include-path-regex = '^/v1/jobs/\{{id\}}'
exclude-path = "/v1/jobs/{{id}}/cancel"
parameters = {{ id = "{ended_job}" }}

[[operations]]
include-path = "/v1/jobs/{{id}}/cancel"
parameters = {{ id = "{queued_job}" }}
{brief_render}"#
    )
}

fn schemathesis(python: &Path, dir: &Path, server: &Server) -> std::process::Output {
    let seed = setting("C4G_CONTRACT_SEED", 1);
    let examples = setting("C4G_CONTRACT_EXAMPLES", 10);
    let seconds = setting("C4G_CONTRACT_SECONDS", 0);
    let mut command = Command::new(python);
    command
        .current_dir(dir)
        .env("SCHEMATHESIS_HOOKS", dir.join("c4g_hooks.py"))
        .args([
            "-c",
            "import sys; from schemathesis.cli import schemathesis; sys.exit(schemathesis())",
        ])
        .arg("--config-file")
        .arg(dir.join("schemathesis.toml"))
        .arg("run")
        .arg(server.at("/openapi.json"))
        .args(["--checks", "all", "--workers", "1", "--no-color"])
        .args([
            "--output-sanitize",
            "false",
            "--generation-database",
            "none",
        ])
        .args(["--request-timeout", "60", "--seed", &seed.to_string()]);
    if seconds > 0 {
        command.args(["--max-time", &seconds.to_string()]);
        command.args([
            "--max-examples",
            &setting("C4G_CONTRACT_EXAMPLES", 1000).to_string(),
        ]);
    } else {
        command.args(["--max-examples", &examples.to_string()]);
    }
    eprintln!("running {command:?}");
    command.output().unwrap()
}

#[test]
fn schemathesis_with_every_check_finds_no_failure_against_the_served_contract() {
    let python = match python() {
        Ok(python) => python,
        Err(why) => {
            assert!(std::env::var_os("CI").is_none(), "in CI: {why}");
            eprintln!("skipped: {why}");
            return;
        }
    };
    if !ort_available() {
        return;
    }
    let mut server = Server::start(SERVER_ARGS);
    let client = Client::new();
    let clip = upload_synthetic(&server);
    let doomed = upload_doomed(&server, &client);
    let queued_job = refine(&server, &client, &clip, 30);
    let ended_job = refine(&server, &client, &clip, 2);
    let cancelled = client
        .post(server.at(&format!("/v1/jobs/{ended_job}/cancel")))
        .send()
        .unwrap();
    assert_eq!(cancelled.json::<Value>().unwrap()["state"], "cancelled");

    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("c4g_hooks.py"), HOOKS).unwrap();
    std::fs::write(
        dir.path().join("schemathesis.toml"),
        config(
            &clip,
            &doomed,
            &queued_job,
            &ended_job,
            setting("C4G_CONTRACT_SECONDS", 0) == 0,
        ),
    )
    .unwrap();
    let out = schemathesis(&python, dir.path(), &server);
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    // The failures (if any) and the summary: everything from the first report section on.
    let report = stdout
        .find("=====")
        .map_or(stdout.as_ref(), |at| &stdout[at..]);
    println!("{report}");
    assert!(server.alive(), "the server died under schemathesis");
    assert!(
        out.status.success(),
        "schemathesis found failures (exit {:?}):\n{stdout}\n{stderr}",
        out.status.code()
    );
    // And it still takes an upload.
    let (frames, times) = synthetic_clip();
    let again = client
        .post(server.at("/v1/clips"))
        .multipart(frames_form(&frames, &times))
        .send()
        .unwrap();
    assert!(again.status().is_success());
}
