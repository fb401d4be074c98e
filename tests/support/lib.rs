//! What the end-to-end tests share: `c4g-server` started as a real process on a loopback port
//! (with the default model, from the repository root, as the quick start runs it), and paths to
//! the binaries and data.
//!
//! The binaries are the workspace's own build (`cargo build --bins`, which `scripts/test` runs
//! before the tests): found beside the test executable in the target directory.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub mod health;
pub mod postgres;

/// The repository root.
pub fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// A binary of the workspace's build (`c4g-server`, `c4g`).
pub fn binary(name: &str) -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    // target/<profile>/deps/<test> → target/<profile>/<name>
    let path = exe.parent().unwrap().parent().unwrap().join(name);
    assert!(
        path.exists(),
        "{} is missing: run `cargo build --workspace --bins` first (scripts/test does)",
        path.display()
    );
    path
}

/// The team's real clips (`../shared/data`), or `None` (allowed only outside CI).
pub fn shared_data() -> Option<PathBuf> {
    let dir = std::env::var_os("C4G_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join("../shared"))
        .join("data");
    if dir.is_dir() {
        Some(dir)
    } else {
        assert!(
            std::env::var_os("CI").is_none(),
            "in CI the team data must be beside the checkout"
        );
        eprintln!("skipped: no ../shared/data");
        None
    }
}

/// True when ONNX Runtime can load (outside CI a test may skip without it).
pub fn ort_available() -> bool {
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

/// A running `c4g-server`, killed on drop, with its own store directory.
pub struct Server {
    child: Child,
    /// Where it listens.
    pub addr: SocketAddr,
    /// Its store directory.
    pub store: tempfile::TempDir,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Server {
    /// Starts the server with the default model and `args`, and waits until it is ready.
    pub fn start(args: &[&str]) -> Server {
        Self::start_in(tempfile::tempdir().unwrap(), args)
    }

    /// Starts it on an existing store directory (to test what survives a restart).
    pub fn start_in(store: tempfile::TempDir, args: &[&str]) -> Server {
        Self::start_with(store, &[], args)
    }

    /// Starts it with settings given as environment variables (`C4G_*`) as well as `args`.
    pub fn start_env(env: &[(&str, &str)], args: &[&str]) -> Server {
        Self::start_with(tempfile::tempdir().unwrap(), env, args)
    }

    fn start_with(store: tempfile::TempDir, env: &[(&str, &str)], args: &[&str]) -> Server {
        let mut child = Command::new(binary("c4g-server"))
            .current_dir(workspace())
            .env_remove("C4G_MODEL")
            .env_remove("C4G_API_KEY")
            .envs(env.iter().copied())
            .args(["--listen", "127.0.0.1:0", "--store-dir"])
            .arg(store.path())
            .args(args)
            // Warnings and errors only, unless the caller asks for more.
            .env(
                "RUST_LOG",
                std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into()),
            )
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let stdout = child.stdout.take().unwrap();
        let mut line = String::new();
        BufReader::new(stdout).read_line(&mut line).unwrap();
        let addr: SocketAddr = line
            .trim()
            .strip_prefix("listening on ")
            .unwrap_or_else(|| panic!("unexpected first line: {line:?}"))
            .parse()
            .unwrap();
        let server = Server { child, addr, store };
        server.wait_ready();
        server
    }

    /// `http://addr`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// `http://addr/path`.
    pub fn at(&self, path: &str) -> String {
        format!("http://{}{}", self.addr, path)
    }

    fn wait_ready(&self) {
        let client = reqwest::blocking::Client::new();
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            if let Ok(r) = client.get(self.at("/ready")).send()
                && r.status().is_success()
            {
                return;
            }
            assert!(Instant::now() < deadline, "the server never became ready");
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// The process id (for memory readings).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// True while the process runs.
    pub fn alive(&mut self) -> bool {
        self.child.try_wait().unwrap().is_none()
    }

    /// Stops the server and gives back its store directory.
    pub fn stop(mut self) -> tempfile::TempDir {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let store = tempfile::tempdir().unwrap();
        std::mem::replace(&mut self.store, store)
    }
}

/// The synthetic test clip of the default model: its frames' paths and times.
pub fn synthetic_clip() -> (Vec<PathBuf>, Vec<f64>) {
    let dir = workspace().join("models/c4g-tiny/test-clips/seed-2000000");
    let clip: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("clip.json")).unwrap()).unwrap();
    let frames = clip["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| dir.join(f.as_str().unwrap()))
        .collect();
    let times = clip["times"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_f64().unwrap())
        .collect();
    (frames, times)
}

/// A multipart form of image frames with explicit timestamps.
pub fn frames_form(frames: &[PathBuf], times: &[f64]) -> reqwest::blocking::multipart::Form {
    let mut form = reqwest::blocking::multipart::Form::new().text(
        "timestamps",
        times
            .iter()
            .map(f64::to_string)
            .collect::<Vec<_>>()
            .join(","),
    );
    for path in frames {
        form = form.part("frame", file_part(path));
    }
    form
}

fn file_part(path: &Path) -> reqwest::blocking::multipart::Part {
    reqwest::blocking::multipart::Part::bytes(std::fs::read(path).unwrap())
        .file_name(path.file_name().unwrap().to_string_lossy().into_owned())
}

/// Peak resident memory of a process, bytes (Linux `VmHWM`).
pub fn peak_rss(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Latencies of a burst of concurrent requests.
#[derive(Debug, Clone)]
pub struct Burst {
    /// Seconds per request, sorted.
    pub latencies: Vec<f64>,
    /// Wall-clock seconds for the whole burst.
    pub wall: f64,
    /// Requests that did not answer 200.
    pub failures: Vec<String>,
}

impl Burst {
    /// The `q`-quantile latency (nearest rank).
    pub fn quantile(&self, q: f64) -> f64 {
        let n = self.latencies.len();
        if n == 0 {
            return f64::NAN;
        }
        let rank = ((q * n as f64).ceil() as usize).clamp(1, n);
        self.latencies[rank - 1]
    }

    /// Requests per second over the burst.
    pub fn throughput(&self) -> f64 {
        self.latencies.len() as f64 / self.wall
    }
}

/// Sends `requests` POSTs (path and JSON body) all at once, one thread each, and times them.
pub fn burst(server: &Server, requests: &[(String, serde_json::Value)]) -> Burst {
    let client = reqwest::blocking::Client::builder()
        .pool_max_idle_per_host(requests.len())
        .timeout(Duration::from_secs(600))
        .build()
        .unwrap();
    let start = std::sync::Barrier::new(requests.len());
    let begun = Instant::now();
    let results: Vec<Result<f64, String>> = std::thread::scope(|scope| {
        let handles: Vec<_> = requests
            .iter()
            .map(|(path, body)| {
                let (client, start, url) = (&client, &start, server.at(path));
                scope.spawn(move || {
                    start.wait();
                    let t0 = Instant::now();
                    let response = client
                        .post(&url)
                        .json(body)
                        .send()
                        .map_err(|e| e.to_string())?;
                    let status = response.status();
                    let bytes = response.bytes().map_err(|e| e.to_string())?;
                    if status.is_success() {
                        Ok(t0.elapsed().as_secs_f64())
                    } else {
                        Err(format!("{status}: {}", String::from_utf8_lossy(&bytes)))
                    }
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let wall = begun.elapsed().as_secs_f64();
    let mut latencies: Vec<f64> = results
        .iter()
        .filter_map(|r| r.as_ref().ok().copied())
        .collect();
    latencies.sort_by(f64::total_cmp);
    let failures = results.into_iter().filter_map(Result::err).collect();
    Burst {
        latencies,
        wall,
        failures,
    }
}

/// POSTs an upload form to `/v1/clips`: the response.
pub fn post_upload(
    server: &Server,
    form: reqwest::blocking::multipart::Form,
) -> reqwest::blocking::Response {
    reqwest::blocking::Client::new()
        .post(server.at("/v1/clips"))
        .multipart(form)
        .send()
        .unwrap()
}

/// Uploads the synthetic test clip and gives its id.
pub fn upload_synthetic(server: &Server) -> String {
    let (frames, times) = synthetic_clip();
    let response = post_upload(server, frames_form(&frames, &times));
    assert!(response.status().is_success());
    response.json::<serde_json::Value>().unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned()
}

/// 32 decodes and 32 renders (128²) at times spread over the synthetic clip's span.
pub fn mixed_requests(id: &str) -> Vec<(String, serde_json::Value)> {
    (0..64)
        .map(|i| {
            let t = 0.6 * f64::from(i % 32) / 31.0;
            if i % 2 == 0 {
                (
                    format!("/v1/clips/{id}/gaussians"),
                    serde_json::json!({"t": t, "format": "binary"}),
                )
            } else {
                (
                    format!("/v1/clips/{id}/render"),
                    serde_json::json!({"t": t, "width": 128, "height": 128}),
                )
            }
        })
        .collect()
}

/// A `c4g-server` process that a fault test controls: started on a store directory and address
/// of the test's choosing (so that a restart finds the same store, and workers the same port),
/// its log collected (and echoed to the test's stderr), killed with SIGKILL when asked or when
/// dropped.
pub struct ServerProcess {
    child: Child,
    /// Where it listens.
    pub addr: SocketAddr,
    log: std::sync::Arc<std::sync::Mutex<String>>,
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl ServerProcess {
    /// Starts the server (default model, from the repository root) with `--store-dir store`,
    /// `--listen listen` and `args`, with `env` set, once it prints its address; it may not be
    /// ready yet (or ever: see [`wait_exit`](Self::wait_exit)).
    pub fn spawn(store: &Path, listen: &str, args: &[&str], env: &[(&str, &str)]) -> Self {
        let mut child = Command::new(binary("c4g-server"))
            .current_dir(workspace())
            .env_remove("C4G_MODEL")
            .env_remove("C4G_API_KEY")
            .env_remove("C4G_FAULT_PAUSE")
            .env(
                "RUST_LOG",
                std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into()),
            )
            .envs(env.iter().copied())
            .args(["--listen", listen, "--store-dir"])
            .arg(store)
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let log = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
        let stderr = BufReader::new(child.stderr.take().unwrap());
        let pid = child.id();
        {
            let log = log.clone();
            std::thread::spawn(move || {
                for line in stderr.lines().map_while(Result::ok) {
                    eprintln!("[c4g-server {pid}] {line}");
                    let mut log = log.lock().unwrap();
                    log.push_str(&line);
                    log.push('\n');
                }
            });
        }
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        let mut line = String::new();
        stdout.read_line(&mut line).unwrap();
        // Drained, so that nothing the server prints later meets a closed pipe.
        std::thread::spawn(move || std::io::copy(&mut stdout, &mut std::io::sink()));
        let Some(addr) = line.trim().strip_prefix("listening on ") else {
            let status = child.wait().unwrap();
            std::thread::sleep(Duration::from_millis(200));
            panic!(
                "c4g-server did not start ({status}): {line:?}\n{}",
                log.lock().unwrap()
            );
        };
        ServerProcess {
            addr: addr.parse().unwrap(),
            child,
            log,
        }
    }

    /// [`spawn`](Self::spawn) without extra environment, then waits until it is ready.
    pub fn start(store: &Path, listen: &str, args: &[&str]) -> Self {
        let mut server = Self::spawn(store, listen, args, &[]);
        server.wait_ready();
        server
    }

    /// `http://addr`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// `http://addr/path`.
    pub fn at(&self, path: &str) -> String {
        format!("http://{}{}", self.addr, path)
    }

    /// Waits until `/ready` answers 200; panics with the log if the process ends first.
    pub fn wait_ready(&mut self) {
        let client = reqwest::blocking::Client::new();
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            if let Ok(r) = client.get(self.at("/ready")).send()
                && r.status().is_success()
            {
                return;
            }
            if let Some(status) = self.child.try_wait().unwrap() {
                panic!(
                    "c4g-server ended ({status}) before it was ready:\n{}",
                    self.log()
                );
            }
            assert!(Instant::now() < deadline, "the server never became ready");
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Everything the server logged so far.
    pub fn log(&self) -> String {
        self.log.lock().unwrap().clone()
    }

    /// Waits until the log holds `needle`; panics after `within`.
    pub fn wait_for_log(&self, needle: &str, within: Duration) {
        let deadline = Instant::now() + within;
        while !self.log().contains(needle) {
            assert!(
                Instant::now() < deadline,
                "the server never logged {needle:?}:\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Waits up to `within` for the process to end by itself, and gives its exit status.
    pub fn wait_exit(&mut self, within: Duration) -> std::process::ExitStatus {
        let deadline = Instant::now() + within;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                // The log thread reads what the process wrote last.
                std::thread::sleep(Duration::from_millis(200));
                return status;
            }
            assert!(
                Instant::now() < deadline,
                "c4g-server is still running:\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// True while the process runs.
    pub fn alive(&mut self) -> bool {
        self.child.try_wait().unwrap().is_none()
    }

    /// Sends SIGTERM: the server drains (`docs/deploy.md`), then exits by itself.
    pub fn terminate(&self) {
        let status = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .unwrap();
        assert!(status.success(), "kill -TERM failed: {status}");
    }

    /// Kills the process with SIGKILL (no shutdown of any kind runs) and reaps it.
    pub fn kill(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

/// The JSON body of a successful answer (fails the test, with the body, on any other).
pub fn json_of(response: reqwest::blocking::Response) -> serde_json::Value {
    let status = response.status();
    let text = response.text().unwrap();
    assert!(status.is_success(), "{status}: {text}");
    serde_json::from_str(&text).unwrap()
}

/// Asserts a 400 `invalid_input` answer whose message says `says`.
pub fn expect_invalid(response: reqwest::blocking::Response, says: &str) {
    assert_eq!(response.status(), 400);
    let body: serde_json::Value = response.json().unwrap();
    assert_eq!(body["kind"], "invalid_input", "{body}");
    let message = body["error"].as_str().unwrap();
    assert!(message.contains(says), "{message:?} should say {says:?}");
}

/// The sum of every series of the Prometheus metric `name` in a `/metrics` text (0 when absent).
pub fn metric(text: &str, name: &str) -> f64 {
    text.lines()
        .filter(|line| !line.starts_with('#'))
        .filter_map(|line| {
            let rest = line.strip_prefix(name)?;
            if !(rest.starts_with('{') || rest.starts_with(' ')) {
                return None;
            }
            line.rsplit(' ').next()?.parse::<f64>().ok()
        })
        .sum()
}

/// A multipart body of image frames with explicit timestamps, as raw bytes with `boundary`
/// (for clients that send it by hand: in parts, slowly, or not at all).
pub fn multipart_bytes(frames: &[PathBuf], times: &[f64], boundary: &str) -> Vec<u8> {
    let mut body = Vec::new();
    let stamps: Vec<String> = times.iter().map(f64::to_string).collect();
    body.extend_from_slice(
        format!(
            "--{boundary}\r\nContent-Disposition: form-data; name=\"timestamps\"\r\n\r\n{}\r\n",
            stamps.join(",")
        )
        .as_bytes(),
    );
    for path in frames {
        let name = path.file_name().unwrap().to_string_lossy();
        body.extend_from_slice(
            format!(
                "--{boundary}\r\nContent-Disposition: form-data; name=\"frame\"; \
                 filename=\"{name}\"\r\nContent-Type: image/png\r\n\r\n"
            )
            .as_bytes(),
        );
        body.extend_from_slice(&std::fs::read(path).unwrap());
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    body
}

/// A `c4g-refiner` worker on the tiny Wan-VACE fixture (or another package), pulling jobs from
/// the server at `url` (the process is in `.0`); killed when dropped.
pub struct RefinerWorker(pub Child);

impl RefinerWorker {
    /// Starts one named `name`, on one intra-op thread, logging at `RUST_LOG` (default warn).
    pub fn start(url: &str, name: &str) -> Self {
        Self::start_with(url, name, &[])
    }

    /// Like [`start`](Self::start), with more arguments (`--package DIR`, for one).
    pub fn start_with(url: &str, name: &str, args: &[&str]) -> Self {
        Self(
            Command::new(binary("c4g-refiner"))
                .current_dir(workspace())
                .args(["--server", url, "--name", name, "--intra-op-threads", "1"])
                .args(args)
                .env(
                    "RUST_LOG",
                    std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into()),
                )
                .stdout(Stdio::null())
                .stderr(Stdio::inherit())
                .spawn()
                .unwrap(),
        )
    }
}

impl Drop for RefinerWorker {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A `c4g-fitter` worker pulling fit jobs from the server at `url` (the process is in `.0`);
/// killed when dropped.
pub struct FitterWorker(pub Child);

impl FitterWorker {
    /// Starts one named `name`, logging at `RUST_LOG` (default warn).
    pub fn start(url: &str, name: &str) -> Self {
        Self(
            Command::new(binary("c4g-fitter"))
                .current_dir(workspace())
                .args(["--server", url, "--name", name])
                .env(
                    "RUST_LOG",
                    std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into()),
                )
                .stdout(Stdio::null())
                .stderr(Stdio::inherit())
                .spawn()
                .unwrap(),
        )
    }
}

impl Drop for FitterWorker {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Asserts the status, the kind and a fragment of the message of an error answer.
pub fn expect_error(
    response: reqwest::blocking::Response,
    status: u16,
    kind: &str,
    fragment: &str,
) {
    let got = response.status().as_u16();
    let text = response.text().unwrap();
    let body: serde_json::Value =
        serde_json::from_str(&text).unwrap_or_else(|_| panic!("not JSON: {text}"));
    assert_eq!(got, status, "{text}");
    assert_eq!(body["kind"], kind, "{text}");
    let message = body["error"].as_str().unwrap();
    assert!(message.contains(fragment), "{message:?} lacks {fragment:?}");
}

/// True under CI (`CI` set), where a missing tool fails a test instead of skipping it.
pub fn in_ci() -> bool {
    std::env::var_os("CI").is_some()
}

/// Skips (outside CI, saying so) or fails (in CI) for a missing tool.
pub fn missing<T>(what: &str) -> Option<T> {
    assert!(!in_ci(), "in CI {what} (scripts/setup installs it)");
    eprintln!("skipped: {what}");
    None
}

fn runs(program: &str) -> bool {
    Command::new(program)
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success())
}

/// `tests/browser` with its npm packages (playwright-core, @adobe/spz) installed from its
/// lockfile: `npm ci` runs there when `package` is missing.
pub fn node_packages(package: &str) -> Option<PathBuf> {
    let dir = workspace().join("tests/browser");
    if !runs("node") || !runs("npm") {
        return missing("node and npm must be installed (apt-get install nodejs npm)");
    }
    if !dir
        .join("node_modules")
        .join(package)
        .join("package.json")
        .is_file()
    {
        let status = Command::new("npm")
            .args(["ci", "--no-audit", "--no-fund"])
            .current_dir(&dir)
            .status();
        if !status.is_ok_and(|s| s.success()) {
            return missing(&format!("`npm ci` in tests/browser must install {package}"));
        }
    }
    Some(dir)
}

/// The Python with the repository's packages: `PYTHON` when set, else `.venv/bin/python`.
pub fn venv_python() -> PathBuf {
    std::env::var_os("PYTHON")
        .filter(|p| !p.is_empty())
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join(".venv/bin/python"))
}

/// `POST path` with a JSON body.
pub fn post_json(
    server: &Server,
    path: &str,
    body: &serde_json::Value,
) -> reqwest::blocking::Response {
    reqwest::blocking::Client::new()
        .post(server.at(path))
        .json(body)
        .send()
        .unwrap()
}
