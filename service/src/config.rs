//! The server's settings. Every flag also reads an environment variable, and every default works
//! on a laptop.

use std::fmt;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use c4g_engine::{EngineOptions, ExecutionProvider, TimePolicy};
use c4g_scene::Footprint;
use clap::{Parser, ValueEnum};

/// A setting that never appears in logs or debug output: the API key. Read it with
/// [`expose`](Self::expose), where it is compared.
#[derive(Clone, PartialEq, Eq)]
pub struct Secret(String);

impl Secret {
    /// The secret itself.
    pub fn expose(&self) -> &str {
        &self.0
    }
}

impl fmt::Debug for Secret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("Secret(redacted)")
    }
}

impl std::str::FromStr for Secret {
    type Err = std::convert::Infallible;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Ok(Self(s.to_owned()))
    }
}

/// Serve a C4G model package over HTTP.
#[derive(Debug, Clone, Parser)]
#[command(name = "c4g-server", version)]
pub struct Config {
    /// Address to listen on (port 0 picks a free port; the chosen address is printed).
    #[arg(long, env = "C4G_LISTEN", default_value = "127.0.0.1:8080")]
    pub listen: SocketAddr,
    /// The model package directory (model.json + ONNX graphs). The default, c4g-tiny, is the
    /// small trained model embedded in the repository (models/c4g-tiny/README.md).
    #[arg(long, env = "C4G_MODEL", default_value = "models/c4g-tiny")]
    pub model: PathBuf,
    /// ONNX Runtime intra-op threads (0: ONNX Runtime's default, one per core).
    #[arg(long, env = "C4G_INTRA_OP_THREADS", default_value_t = 0)]
    pub intra_op_threads: usize,
    /// Keep ONNX Runtime's CPU memory arena: buffers are reused across decodes (faster at every
    /// size measured: docs/benchmarks.md, "Session defaults") but the largest run's memory stays
    /// held; `false` gives it back after each run.
    #[arg(long, env = "C4G_CPU_ARENA", default_value_t = true, action = clap::ArgAction::Set)]
    pub cpu_arena: bool,
    /// Let ONNX Runtime's threads spin while waiting for work (ONNX Runtime's own default; off
    /// here: the spinning threads take the cores the rasterizer and the other sessions need).
    #[arg(long, env = "C4G_INTRA_OP_SPINNING", default_value_t = false, action = clap::ArgAction::Set)]
    pub intra_op_spinning: bool,
    /// Where the model runs. `cuda` needs c4g-server built with `--features cuda` and the
    /// onnxruntime-gpu library, and refuses to start without them (saying what is missing);
    /// `auto` uses CUDA when it works and the CPU otherwise, and logs which.
    #[arg(long, env = "C4G_DEVICE", value_enum, default_value_t = DeviceArg::Cpu)]
    pub device: DeviceArg,
    /// CUDA device ordinal (with `--device cuda`).
    #[arg(long, env = "C4G_CUDA_DEVICE", default_value_t = 0)]
    pub cuda_device: i32,
    /// How timestamps are normalised before the decoder (docs/time-policy.md): `package` uses
    /// the policy the model declares (frame-step when it declares none).
    #[arg(long, env = "C4G_TIME_POLICY", value_enum, default_value_t = PolicyArg::Package)]
    pub time_policy: PolicyArg,
    /// Where clips live on disk (metadata, encoder features, context frames), so that a restart
    /// serves them without encoding again.
    #[arg(long, env = "C4G_STORE_DIR", default_value = "c4g-data")]
    pub store_dir: PathBuf,
    /// Object storage the replicas share clips through: `s3://bucket/prefix` (with the `AWS_*`
    /// variables: endpoint, keys, region, `AWS_ALLOW_HTTP`) or `file:///shared/dir`. Unset: this
    /// server's clips are its own.
    #[arg(long, env = "C4G_SHARED_STORE")]
    pub shared_store: Option<String>,
    /// Memory for cached encoder features, in MiB; the least recently used clips are evicted
    /// (they stay on disk and reload on their next request).
    #[arg(long, env = "C4G_CACHE_MIB", default_value_t = 1024)]
    pub cache_mib: u64,
    /// Execution-provider memory for device-resident encodings, in MiB: a clip's features stay
    /// there and decodes bind them instead of copying them host-to-device each run (least
    /// recently used clips spill back to host memory, then disk). Unset: 4096 on CUDA, off on
    /// the CPU (no copy to save); 0: off.
    #[arg(long, env = "C4G_DEVICE_CACHE_MIB")]
    pub device_cache_mib: Option<u64>,
    /// Context frames per clip when the upload does not ask for a number.
    #[arg(long, env = "C4G_CONTEXT_FRAMES", default_value_t = 4)]
    pub context_frames: usize,
    /// The most context frames an upload may ask for.
    #[arg(long, env = "C4G_MAX_CONTEXT_FRAMES", default_value_t = 32)]
    pub max_context_frames: usize,
    /// Source frames kept with each clip (spread over its window, small) for fits to supervise
    /// with; 0 keeps none, and fits then see the context frames alone.
    #[arg(long, env = "C4G_KEPT_FRAMES", default_value_t = 300)]
    pub kept_frames: usize,
    /// Long side, pixels, of the kept source frames (the sharpest a fit can work at).
    #[arg(long, env = "C4G_KEPT_FRAME_SIDE", default_value_t = 256)]
    pub kept_frame_side: u32,
    /// Largest request body (an upload), in MiB.
    #[arg(long, env = "C4G_MAX_BODY_MIB", default_value_t = 512)]
    pub max_body_mib: u64,
    /// Most frames a source clip (video or image archive) may have.
    #[arg(long, env = "C4G_MAX_SOURCE_FRAMES", default_value_t = 20_000)]
    pub max_source_frames: usize,
    /// Longest clip, in seconds.
    #[arg(long, env = "C4G_MAX_DURATION_S", default_value_t = 600.0)]
    pub max_duration_s: f64,
    /// Largest frame side, in pixels (uploads and renders).
    #[arg(long, env = "C4G_MAX_SIDE", default_value_t = 8192)]
    pub max_side: u32,
    /// Most pixels one rendered image may have.
    #[arg(long, env = "C4G_MAX_RENDER_PIXELS", default_value_t = 4096 * 4096)]
    pub max_render_pixels: u64,
    /// Smallest frame side of an upload, in pixels.
    #[arg(long, env = "C4G_MIN_SIDE", default_value_t = 16)]
    pub min_side: u32,
    /// Largest total of decompressed bytes an image archive may expand to, in MiB.
    #[arg(long, env = "C4G_MAX_ARCHIVE_MIB", default_value_t = 2048)]
    pub max_archive_mib: u64,
    /// Encodes (intake + encoder) at once; more are refused at once with 429 and Retry-After.
    #[arg(long, env = "C4G_MAX_CONCURRENT_ENCODES", default_value_t = 2)]
    pub max_concurrent_encodes: usize,
    /// Decodes and renders running at once, each on a work slot (0: one per core).
    #[arg(long, env = "C4G_MAX_CONCURRENT_WORK")]
    pub max_concurrent_work: Option<usize>,
    /// Decodes and renders that may wait for a work slot; more are refused with 503 and
    /// Retry-After. Default 256.
    #[arg(long, env = "C4G_MAX_QUEUED_WORK")]
    pub max_queued_work: Option<usize>,
    /// The old name of `--max-concurrent-work` (work slots were once called jobs, a name that
    /// now means refinement jobs only); used when the new one is not set.
    #[arg(long, env = "C4G_MAX_CONCURRENT_JOBS", hide = true)]
    pub max_concurrent_jobs: Option<usize>,
    /// The old name of `--max-queued-work`; used when the new one is not set.
    #[arg(long, env = "C4G_MAX_QUEUED_JOBS", hide = true)]
    pub max_queued_jobs: Option<usize>,
    /// Longest a request body (an upload, a worker's result) may take to arrive, in seconds,
    /// from its request's headers on: a slower client is answered 408 (gRPC DEADLINE_EXCEEDED)
    /// and its connection freed.
    #[arg(long, env = "C4G_BODY_TIMEOUT_S", default_value_t = 300.0)]
    pub body_timeout_s: f64,
    /// On SIGTERM or Ctrl-C, how long requests in flight may take to finish, in seconds: `/ready`
    /// answers 503 `draining` at once, no new connection is taken, and what is still open when
    /// the time is up is cut.
    #[arg(long, env = "C4G_DRAIN_TIMEOUT_S", default_value_t = 30.0)]
    pub drain_timeout_s: f64,
    /// Time limit for reading media with FFmpeg and for one encode, in seconds.
    #[arg(long, env = "C4G_INTAKE_TIMEOUT_S", default_value_t = 120)]
    pub intake_timeout_s: u64,
    /// Most Gaussian sets one request may decode (times in a decode, frames of a stream or video).
    #[arg(long, env = "C4G_MAX_TIMES", default_value_t = 4096)]
    pub max_times: usize,
    /// Most query points one track request may follow (`POST /v1/clips/{id}/tracks`).
    #[arg(long, env = "C4G_MAX_TRACK_QUERIES", default_value_t = 4096)]
    pub max_track_queries: usize,
    /// Largest 4D export (`POST /v1/clips/{id}/export`), in MiB: what the file, or for `.splatv`
    /// the sets it is fitted from, may hold in memory while it is made.
    #[arg(long, env = "C4G_MAX_EXPORT_MIB", default_value_t = 512)]
    pub max_export_mib: u64,
    /// Largest gRPC message, in MiB (an upload arrives in chunks below this).
    #[arg(long, env = "C4G_MAX_GRPC_MESSAGE_MIB", default_value_t = 16)]
    pub max_grpc_message_mib: usize,
    /// When set, every /v1 request and gRPC call needs `Authorization: Bearer <key>`.
    #[arg(long, env = "C4G_API_KEY", hide_env_values = true)]
    pub api_key: Option<Secret>,
    /// The rasterizer: `cpu`, or with the `gpu` build feature `gpu` (wgpu) or `auto` (wgpu on a
    /// hardware GPU, the CPU rasterizer otherwise: Mesa's software Vulkan is slower than it).
    #[arg(long, env = "C4G_RENDERER", value_enum, default_value_t = RendererArg::Auto)]
    pub renderer: RendererArg,
    /// Which pixels a Gaussian reaches in renders: `package` (the footprint the package's
    /// model.json declares, `ellipse` when it declares none), `ellipse` (3 sigma) or `3dgs` (every
    /// pixel of the original 3DGS rasterizer's tiles, what the official weights were trained with).
    #[arg(long, env = "C4G_FOOTPRINT", value_enum, default_value_t = FootprintArg::Package)]
    pub footprint: FootprintArg,
    /// Seconds a refinement worker may go without reporting progress before its job is taken
    /// back (retried, or failed when out of attempts).
    #[arg(long, env = "C4G_JOB_LEASE_S", default_value_t = 60.0)]
    pub job_lease_s: f64,
    /// How long an exact decode waits for other requests' decodes of the same clip to share its
    /// decoder run, in milliseconds (`service/src/sets/batching.rs`); 0 turns batching off. Unset: 2
    /// with `--device cuda`, where one target leaves the GPU idle; 0 on the CPU, where a batch
    /// costs about as much per target as one at a time (and more at the official size) and the
    /// wait would only add latency.
    #[arg(long, env = "C4G_BATCH_WAIT_MS")]
    pub batch_wait_ms: Option<u64>,
    /// Where refinement jobs are kept: unset, this server's store directory; a PostgreSQL URL
    /// (`postgres://user:password@host/db`, or `?host=/run/postgresql` for a Unix socket), a
    /// database every replica shares: any replica hands jobs to workers and serves their
    /// results (`service/src/jobs/postgres.rs`).
    #[arg(long, env = "C4G_JOB_DATABASE", hide_env_values = true)]
    pub job_database: Option<Secret>,
    /// Hours a job that ended (done, failed, cancelled) is kept, with its result, after its last
    /// change; then it is deleted, so the job list and the stored results do not grow without
    /// end. 0 keeps every job.
    #[arg(long, env = "C4G_JOB_RETENTION_H", default_value_t = 168.0)]
    pub job_retention_h: f64,
    /// Attempts a refinement job gets (a lost worker or a retryable failure uses one).
    #[arg(long, env = "C4G_JOB_ATTEMPTS", default_value_t = 2)]
    pub job_attempts: u32,
    /// The FFmpeg binary (ffprobe is looked up beside it, or on PATH).
    #[arg(long, env = "C4G_FFMPEG", default_value = "ffmpeg")]
    pub ffmpeg: PathBuf,
    /// For tests only: fault points (comma-separated) where the server stops until it is
    /// killed (`service/src/faults.rs` lists them).
    #[arg(long, env = "C4G_FAULT_PAUSE", hide = true, value_delimiter = ',')]
    pub fault_pause: Vec<String>,
}

/// Decodes and renders that may wait for a work slot when no setting says.
pub const DEFAULT_MAX_QUEUED_WORK: usize = 256;

/// Which rasterizer renders.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum RendererArg {
    /// wgpu on a hardware GPU when built with `gpu` and one is present; the CPU otherwise.
    Auto,
    /// The tiled CPU rasterizer.
    Cpu,
    /// The wgpu rasterizer on whatever adapter `C4G_WGPU_ADAPTER` picks (needs the `gpu` feature).
    Gpu,
}

/// The rasterizer [`Footprint`] as a command-line value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FootprintArg {
    /// What the package declares (`rasterizer.footprint` in model.json; absent: the ellipse).
    Package,
    /// The pixels within 3 sigma.
    Ellipse,
    /// Every pixel of the original 3DGS rasterizer's tiles.
    #[value(name = "3dgs")]
    Tiles3dgs,
}

/// [`ExecutionProvider`] as a command-line value.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum DeviceArg {
    /// ONNX Runtime's CPU kernels.
    Cpu,
    /// NVIDIA CUDA: the server does not start without it.
    Cuda,
    /// CUDA when it works (a `cuda` build, ONNX Runtime's GPU library and a GPU), else the CPU;
    /// the log says which was chosen and why.
    Auto,
}

/// [`TimePolicy`] as a command-line value.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum PolicyArg {
    /// The policy the package declares in model.json (frame-step when it declares none).
    Package,
    /// Equal to the reference from one source frame after the first context frame; bounded.
    FrameStep,
    /// Bounded and defined over the whole context span; equal to the reference past the first
    /// mean spacing (what c4g-tiny was trained with).
    Stable,
    /// The public reference's normalisation, exactly (for parity checks).
    Reference,
}

/// The limits a request is held to, in the units the code uses.
#[derive(Debug, Clone)]
pub struct Limits {
    /// Default context frames per clip.
    pub context_frames: usize,
    /// Most context frames an upload may ask for.
    pub max_context_frames: usize,
    /// Largest request body, bytes.
    pub max_body_bytes: usize,
    /// Most frames in a source clip.
    pub max_source_frames: usize,
    /// Longest clip, seconds.
    pub max_duration_s: f64,
    /// Largest frame side, pixels.
    pub max_side: u32,
    /// Smallest upload frame side, pixels.
    pub min_side: u32,
    /// Most pixels of a rendered image.
    pub max_render_pixels: u64,
    /// Largest decompressed archive, bytes.
    pub max_archive_bytes: u64,
    /// Time limit for media reading and encoding.
    pub intake_timeout: Duration,
    /// Most Gaussian sets per request.
    pub max_times: usize,
    /// Most query points per track request.
    pub max_track_queries: usize,
    /// Largest 4D export, bytes.
    pub max_export_bytes: u64,
    /// Largest gRPC message, bytes.
    pub max_grpc_message_bytes: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Config::parse_from(["c4g-server"]).limits()
    }
}

impl Config {
    /// The request limits these settings ask for.
    pub fn limits(&self) -> Limits {
        const MIB: u64 = 1 << 20;
        Limits {
            context_frames: self.context_frames.clamp(1, self.max_context_frames.max(1)),
            max_context_frames: self.max_context_frames.max(1),
            max_body_bytes: usize::try_from(self.max_body_mib.saturating_mul(MIB))
                .unwrap_or(usize::MAX),
            max_source_frames: self.max_source_frames,
            max_duration_s: self.max_duration_s,
            max_side: self.max_side,
            min_side: self.min_side,
            max_render_pixels: self.max_render_pixels,
            max_archive_bytes: self.max_archive_mib.saturating_mul(MIB),
            intake_timeout: Duration::from_secs(self.intake_timeout_s.max(1)),
            max_times: self.max_times.max(1),
            max_track_queries: self.max_track_queries.max(1),
            max_export_bytes: self.max_export_mib.saturating_mul(MIB),
            max_grpc_message_bytes: self.max_grpc_message_mib.saturating_mul(1 << 20),
        }
    }

    /// How long a request body may take to arrive (at least a millisecond).
    pub fn body_timeout(&self) -> Duration {
        Duration::try_from_secs_f64(self.body_timeout_s)
            .unwrap_or(Duration::MAX)
            .max(Duration::from_millis(1))
    }

    /// How long a drain may last (at least a millisecond).
    pub fn drain_timeout(&self) -> Duration {
        Duration::try_from_secs_f64(self.drain_timeout_s)
            .unwrap_or(Duration::MAX)
            .max(Duration::from_millis(1))
    }

    /// Work slots for decodes and renders (0: one per core), by the new name or the old.
    pub fn max_concurrent_work(&self) -> usize {
        self.max_concurrent_work
            .or(self.max_concurrent_jobs)
            .unwrap_or(0)
    }

    /// Decodes and renders that may wait for a slot, by the new name or the old.
    pub fn max_queued_work(&self) -> usize {
        self.max_queued_work
            .or(self.max_queued_jobs)
            .unwrap_or(DEFAULT_MAX_QUEUED_WORK)
    }

    /// The footprint renders use: `declared` (the package's) unless `--footprint` names one.
    pub fn footprint(&self, declared: Footprint) -> Footprint {
        match self.footprint {
            FootprintArg::Package => declared,
            FootprintArg::Ellipse => Footprint::Ellipse,
            FootprintArg::Tiles3dgs => Footprint::Tiles3dgs,
        }
    }

    /// How long a job that ended is kept (`None`: for ever).
    pub fn job_retention(&self) -> Option<Duration> {
        (self.job_retention_h > 0.0).then(|| {
            Duration::try_from_secs_f64(self.job_retention_h * 3600.0).unwrap_or(Duration::MAX)
        })
    }

    /// How long an exact decode waits for company (`C4G_BATCH_WAIT_MS`; its default depends on
    /// the device the model runs on).
    pub fn batch_wait(&self) -> Duration {
        let ms = self.batch_wait_ms.unwrap_or(match self.device {
            DeviceArg::Cuda => 2,
            DeviceArg::Cpu | DeviceArg::Auto => 0,
        });
        Duration::from_millis(ms)
    }

    /// The engine options these settings ask for (with `auto`, CUDA's: see [`DeviceArg::Auto`]).
    pub fn engine_options(&self) -> EngineOptions {
        EngineOptions {
            session: c4g_engine::SessionOptions {
                intra_op_threads: self.intra_op_threads,
                execution_provider: match self.device {
                    DeviceArg::Cpu => ExecutionProvider::Cpu,
                    // `auto` tries CUDA first (the server falls back when it fails).
                    DeviceArg::Cuda | DeviceArg::Auto => ExecutionProvider::Cuda {
                        device_id: self.cuda_device,
                    },
                },
                cpu_arena: self.cpu_arena,
                intra_op_spinning: self.intra_op_spinning,
            },
            time_policy: match self.time_policy {
                PolicyArg::Package => None,
                PolicyArg::FrameStep => Some(TimePolicy::FrameStep),
                PolicyArg::Stable => Some(TimePolicy::Stable),
                PolicyArg::Reference => Some(TimePolicy::Reference),
            },
            resident_budget: self
                .device_cache_mib
                .map(|mib| usize::try_from(mib.saturating_mul(1 << 20)).unwrap_or(usize::MAX)),
            ..EngineOptions::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Config {
        Config::try_parse_from(std::iter::once("c4g-server").chain(args.iter().copied())).unwrap()
    }

    #[test]
    fn the_api_key_never_appears_in_debug_output() {
        let config = parse(&["--api-key", "hunter2-very-secret"]);
        assert_eq!(
            config.api_key.as_ref().map(Secret::expose),
            Some("hunter2-very-secret")
        );
        let shown = format!("{config:?}");
        assert!(!shown.contains("hunter2"), "{shown}");
        assert!(shown.contains("redacted"), "{shown}");
    }

    #[test]
    fn the_footprint_is_the_package_s_unless_a_flag_names_one() {
        for declared in [Footprint::Ellipse, Footprint::Tiles3dgs] {
            let package = parse(&["--footprint", "package"]);
            assert_eq!(package.footprint(declared), declared);
            let ellipse = parse(&["--footprint", "ellipse"]);
            assert_eq!(ellipse.footprint(declared), Footprint::Ellipse);
            let tiles = parse(&["--footprint", "3dgs"]);
            assert_eq!(tiles.footprint(declared), Footprint::Tiles3dgs);
        }
        if std::env::var_os("C4G_FOOTPRINT").is_none() {
            assert_eq!(parse(&[]).footprint, FootprintArg::Package);
        }
        assert!(
            Config::try_parse_from(["c4g-server", "--footprint", "tiles"]).is_err(),
            "an unknown footprint is refused"
        );
    }

    #[test]
    fn work_slots_default_to_one_per_core_and_a_queue_of_256() {
        // Only the flags are under test here: the environment of the test process is not.
        let config = parse(&[]);
        if std::env::vars().any(|(k, _)| k.starts_with("C4G_MAX_")) {
            return;
        }
        assert_eq!(config.max_concurrent_work(), 0);
        assert_eq!(config.max_queued_work(), DEFAULT_MAX_QUEUED_WORK);
    }

    #[test]
    fn the_time_policy_defaults_to_the_packages_and_can_be_named() {
        if std::env::var_os("C4G_TIME_POLICY").is_none() {
            assert_eq!(parse(&[]).engine_options().time_policy, None);
        }
        for (arg, policy) in [
            ("package", None),
            ("frame-step", Some(TimePolicy::FrameStep)),
            ("stable", Some(TimePolicy::Stable)),
            ("reference", Some(TimePolicy::Reference)),
        ] {
            let options = parse(&["--time-policy", arg]).engine_options();
            assert_eq!(options.time_policy, policy, "{arg}");
        }
    }

    #[test]
    fn the_old_job_names_still_set_the_work_slots_and_the_new_names_win() {
        let old = parse(&["--max-concurrent-jobs", "3", "--max-queued-jobs", "7"]);
        assert_eq!((old.max_concurrent_work(), old.max_queued_work()), (3, 7));
        let both = parse(&[
            "--max-concurrent-jobs",
            "3",
            "--max-concurrent-work",
            "5",
            "--max-queued-jobs",
            "7",
            "--max-queued-work",
            "9",
        ]);
        assert_eq!((both.max_concurrent_work(), both.max_queued_work()), (5, 9));
    }
}
