//! `c4g-refiner`: the refinement worker. Loads a refiner package (merging a LoRA when given) and
//! runs the jobs `c4g-server` queues, until stopped. SIGTERM or Ctrl-C drains: the job in hand goes
//! back to the queue at its next denoising step and the worker exits 0 (after
//! `--drain-timeout-s` it exits anyway; a second signal exits at once).

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use c4g_proto::worker::WorkerConfig;
use c4g_refiner::worker::run;
use c4g_refiner::{LoraSpec, Pipeline, PipelineOptions, SessionOptions};
use clap::Parser;
use tokio::signal::unix::{SignalKind, signal};
use tokio::sync::watch;
use tracing_subscriber::EnvFilter;

/// Refine rendered novel views with Wan2.1-VACE, for a c4g-server.
#[derive(Debug, Parser)]
#[command(name = "c4g-refiner", version)]
struct Args {
    /// The server whose jobs to run.
    #[arg(long, env = "C4G_SERVER", default_value = "http://127.0.0.1:8080")]
    server: String,
    /// The refiner package (refiner.json + ONNX graphs).
    #[arg(
        long,
        env = "C4G_REFINER_PACKAGE",
        default_value = "models/fixtures/wan-vace-tiny"
    )]
    package: PathBuf,
    /// A LoRA (.safetensors, PEFT/diffusers or original Wan naming) merged into the weights at load.
    #[arg(long, env = "C4G_REFINER_LORA")]
    lora: Option<PathBuf>,
    /// The LoRA's strength (multiplies its own alpha / rank scale).
    #[arg(long, env = "C4G_REFINER_LORA_SCALE", default_value_t = 1.0)]
    lora_scale: f32,
    /// Where merging the LoRA writes its copy of the transformer's external data (default: the
    /// system's temporary folder). It needs room for the transformer's weights (8.6 GB at the
    /// 1.3B size in f32) while the worker starts, and is emptied once it has; on a RAM-backed file
    /// system (tmpfs) that room is memory, so point it at a disk.
    #[arg(long, env = "C4G_REFINER_MERGE_DIR")]
    merge_dir: Option<PathBuf>,
    /// The server's API key, if it has one.
    #[arg(long, env = "C4G_API_KEY", hide_env_values = true)]
    api_key: Option<String>,
    /// This worker's name in job records (default: host and process id).
    #[arg(long, env = "C4G_WORKER_NAME")]
    name: Option<String>,
    /// ONNX Runtime intra-op threads (0: one per core).
    #[arg(long, env = "C4G_INTRA_OP_THREADS", default_value_t = 0)]
    intra_op_threads: usize,
    /// Leave the package's text encoder unloaded (it can be larger than the rest): jobs must then
    /// bring precomputed prompt embeddings, and jobs with text fail.
    #[arg(long, env = "C4G_REFINER_NO_TEXT_ENCODER")]
    no_text_encoder: bool,
    /// Seconds a stopping worker (SIGTERM, Ctrl-C) waits for its job to reach its next denoising
    /// step and go back to the queue; past them it exits anyway, and the server takes the job
    /// back when its lease runs out (counting the attempt). Keep it under the orchestrator's
    /// grace period before SIGKILL.
    #[arg(long, env = "C4G_DRAIN_TIMEOUT_S", default_value_t = 30)]
    drain_timeout_s: u64,
}

#[tokio::main]
async fn main() -> ExitCode {
    let args = Args::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .init();
    let options = PipelineOptions {
        lora: args.lora.clone().map(|path| LoraSpec {
            path,
            scale: args.lora_scale,
        }),
        merge_dir: args.merge_dir.clone(),
        session: SessionOptions {
            intra_op_threads: args.intra_op_threads,
            ..SessionOptions::default()
        },
        skip_text_encoder: args.no_text_encoder,
    };
    let package = args.package.clone();
    let pipeline =
        match tokio::task::spawn_blocking(move || Pipeline::load(&package, &options)).await {
            Ok(Ok(pipeline)) => Arc::new(pipeline),
            Ok(Err(e)) => {
                tracing::error!(
                    "cannot load the refiner package {}: {e}",
                    args.package.display()
                );
                return ExitCode::FAILURE;
            }
            Err(e) => {
                tracing::error!("loading panicked: {e}");
                return ExitCode::FAILURE;
            }
        };
    let name = args.name.unwrap_or_else(|| {
        let host = std::fs::read_to_string("/etc/hostname").unwrap_or_default();
        format!("{}-{}", host.trim(), std::process::id())
    });
    let config = WorkerConfig {
        server: args.server,
        api_key: args.api_key,
        name,
    };
    let mut terminate = match signal(SignalKind::terminate()) {
        Ok(terminate) => terminate,
        Err(e) => {
            tracing::error!("cannot listen for SIGTERM: {e}");
            return ExitCode::FAILURE;
        }
    };
    let (stop, shutdown) = watch::channel(false);
    let worker = run(config, pipeline, shutdown);
    tokio::pin!(worker);
    let signal = tokio::select! {
        result = &mut worker => return exit_code(result),
        _ = terminate.recv() => "SIGTERM",
        _ = tokio::signal::ctrl_c() => "Ctrl-C",
    };
    tracing::info!(
        drain_timeout_s = args.drain_timeout_s,
        "{signal}: stopping; a job in hand goes back to the queue at its next step"
    );
    stop.send_replace(true);
    let drain = Duration::from_secs(args.drain_timeout_s);
    tokio::select! {
        result = &mut worker => exit_code(result),
        () = tokio::time::sleep(drain) => {
            tracing::warn!(
                "the job did not stop within {} s: exiting without handing it back (the server \
                 takes it back when its lease runs out)",
                args.drain_timeout_s
            );
            // Not a return: dropping the runtime would wait for the pipeline's blocking thread.
            std::process::exit(0)
        }
        _ = terminate.recv() => {
            tracing::warn!("a second SIGTERM: exiting at once");
            std::process::exit(0)
        }
        _ = tokio::signal::ctrl_c() => {
            tracing::warn!("a second Ctrl-C: exiting at once");
            std::process::exit(0)
        }
    }
}

fn exit_code(result: Result<(), String>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e}");
            ExitCode::FAILURE
        }
    }
}
