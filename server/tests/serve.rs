//! `c4g-server` as a real process on loopback, with the fixture model and with the default one.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

struct Server {
    child: Child,
    addr: SocketAddr,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start(model: Option<PathBuf>) -> Server {
    let mut command = Command::new(env!("CARGO_BIN_EXE_c4g-server"));
    command.args(["--listen", "127.0.0.1:0"]);
    match model {
        Some(model) => command.arg("--model").arg(model),
        // The quick start runs from the repository root with no flags: the default model.
        None => command.current_dir(workspace()).env_remove("C4G_MODEL"),
    };
    let mut child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
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
    Server { child, addr }
}

fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// (status, body) of a plain HTTP/1.1 GET.
fn get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut stream = TcpStream::connect(addr).unwrap();
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let status = response.split_whitespace().nth(1).unwrap().parse().unwrap();
    let body = response
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_owned())
        .unwrap_or_default();
    (status, body)
}

fn wait_ready(addr: SocketAddr) -> String {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let (status, body) = get(addr, "/ready");
        if status == 200 {
            return body;
        }
        assert_eq!(status, 503, "{body}");
        assert!(Instant::now() < deadline, "not ready: {body}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn ort_available() -> bool {
    let ok = std::env::var_os("ORT_DYLIB_PATH").is_some_and(|p| !p.is_empty());
    if !ok {
        assert!(
            std::env::var_os("CI").is_none(),
            "in CI ORT_DYLIB_PATH must be set"
        );
        eprintln!("skipped: ORT_DYLIB_PATH is not set");
    }
    ok
}

#[test]
fn serves_health_readiness_and_the_model_description() {
    if !ort_available() {
        return;
    }
    let server = start(Some(workspace().join("models/fixtures/c4g-small")));
    let (status, body) = get(server.addr, "/health");
    assert_eq!((status, body.contains("ok")), (200, true));
    assert!(wait_ready(server.addr).contains("c4g-small"));
    let (status, body) = get(server.addr, "/v1/models");
    assert_eq!(status, 200);
    let models: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(models["models"][0]["name"], "c4g-small");
    assert_eq!(models["models"][0]["gaussians_per_set"], 256);
    // The fixture declares no policy: the package default, frame-step.
    assert_eq!(models["models"][0]["time_policy"], "frame-step");
}

#[test]
fn a_model_that_cannot_load_ends_the_process_with_an_error() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_c4g-server"))
        .args(["--listen", "127.0.0.1:0", "--model", "/nonexistent/package"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let status = child.wait().unwrap();
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    assert!(!status.success());
    assert!(err.contains("/nonexistent/package"), "{err}");
}

#[test]
fn without_flags_it_serves_the_trained_default_model() {
    if !ort_available() {
        return;
    }
    let server = start(None);
    assert!(wait_ready(server.addr).contains("c4g-tiny"));
    let (_, body) = get(server.addr, "/v1/models");
    let models: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(models["models"][0]["name"], "c4g-tiny");
    assert_eq!(models["models"][0]["gaussians_per_set"], 512);
    assert_eq!(models["models"][0]["training"]["steps"], 900);
}
