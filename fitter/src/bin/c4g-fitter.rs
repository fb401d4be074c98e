//! `c4g-fitter`: runs the fit jobs a `c4g-server` queues, until stopped. SIGTERM or Ctrl-C stops
//! the fit in hand at its next step and hands the job back to the queue.

use std::io::IsTerminal;
use std::process::ExitCode;

use c4g_fitter::worker::run;
use c4g_proto::worker::WorkerConfig;
use clap::Parser;
use tokio::signal::unix::{SignalKind, signal};
use tokio::sync::watch;
use tracing_subscriber::EnvFilter;

/// Fit clips' scenes to their own frames, for a c4g-server.
#[derive(Debug, Parser)]
#[command(name = "c4g-fitter", version)]
struct Args {
    /// The server whose fit jobs to run.
    #[arg(long, env = "C4G_SERVER", default_value = "http://127.0.0.1:8080")]
    server: String,
    /// The server's API key, if it has one.
    #[arg(long, env = "C4G_API_KEY", hide_env_values = true)]
    api_key: Option<String>,
    /// This worker's name in job records (default: host and process id).
    #[arg(long, env = "C4G_WORKER_NAME")]
    name: Option<String>,
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
    let name = args.name.unwrap_or_else(|| {
        let host = std::fs::read_to_string("/etc/hostname").unwrap_or_default();
        format!("fitter-{}-{}", host.trim(), std::process::id())
    });
    let (stop, shutdown) = watch::channel(false);
    tokio::spawn(async move {
        let (Ok(mut term), Ok(mut int)) = (
            signal(SignalKind::terminate()),
            signal(SignalKind::interrupt()),
        ) else {
            return;
        };
        tokio::select! {
            _ = term.recv() => {}
            _ = int.recv() => {}
        }
        tracing::info!("stopping: the fit in hand goes back to the queue");
        let _ = stop.send(true);
        tokio::select! {
            _ = term.recv() => {}
            _ = int.recv() => {}
        }
        std::process::exit(1);
    });
    let config = WorkerConfig {
        server: args.server,
        api_key: args.api_key,
        name,
    };
    match run(config, shutdown).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e}");
            ExitCode::FAILURE
        }
    }
}
