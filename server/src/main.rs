//! `c4g-server`: loads the model package and serves it.

use std::future::IntoFuture;
use std::io::IsTerminal;
use std::process::ExitCode;

use c4g_engine::Engine;
use c4g_server::{AppState, router};
use c4g_service::config::Config;
use c4g_service::service::Service;
use clap::Parser;
use tracing_subscriber::EnvFilter;

/// glibc's malloc setting that keeps the resident set near the live data: blocks from 128 KiB
/// up (features, sets, images) are mapped and unmapped on their own instead of being carved out
/// of per-thread arenas. Under mixed traffic the default (a threshold that rises to 32 MiB after
/// the first large free) left the arenas fragmented: the soak saw 1 GiB resident holding 35 MB of
/// live data, and 60-90 MiB with this (`docs/reliability.md`, Soak).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD: (&str, &str) = ("MALLOC_MMAP_THRESHOLD_", "131072");

/// glibc reads its malloc settings from the environment once, at start, and setting them from
/// Rust would need `unsafe` (`mallopt`): so the server starts itself again, once, with the
/// setting in its environment, unless the operator chose one (same process id, same
/// arguments). Where that cannot be done it carries on as it is.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn restart_with_malloc_settings() {
    use std::os::unix::process::CommandExt;
    let (name, value) = MMAP_THRESHOLD;
    if std::env::var_os(name).is_some() {
        return;
    }
    let Ok(exe) = std::env::current_exe() else {
        return;
    };
    let error = std::process::Command::new(exe)
        .args(std::env::args_os().skip(1))
        .env(name, value)
        .exec();
    eprintln!("c4g-server: could not restart with {name}={value} ({error}); going on without it");
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn restart_with_malloc_settings() {}

fn main() -> ExitCode {
    // Before the runtime's threads start: the restart replaces this process image.
    restart_with_malloc_settings();
    match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => runtime.block_on(serve()),
        Err(e) => {
            eprintln!("c4g-server: cannot start the async runtime: {e}");
            ExitCode::FAILURE
        }
    }
}

async fn serve() -> ExitCode {
    let config = Config::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .init();
    match run(config).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e}");
            ExitCode::FAILURE
        }
    }
}

async fn run(config: Config) -> Result<(), Box<dyn std::error::Error>> {
    c4g_service::faults::arm(&config.fault_pause)?;
    let state = AppState::new(config.clone(), c4g_server::metrics::install());
    let listener = tokio::net::TcpListener::bind(config.listen).await?;
    // Printed on stdout so scripts and tests can find a port chosen by the OS.
    println!("listening on {}", listener.local_addr()?);

    // Loading runs off the async threads: /health answers while the model loads.
    let loading = {
        let (state, config) = (state.clone(), config.clone());
        tokio::task::spawn_blocking(move || -> Result<(), String> {
            let (engine, config) = load_engine(config)?;
            tracing::info!(model = %engine.manifest().name, "model loaded");
            state.set_service(Service::new(engine, &config)?);
            Ok(())
        })
    };
    let app = c4g_server::body_deadline::layer(router(state.clone()), config.body_timeout());
    // Small answers go out at once: without TCP_NODELAY a gRPC reply waits on the client's
    // delayed acknowledgement (about 40 ms a call on loopback).
    let listener = axum::serve::ListenerExt::tap_io(listener, |tcp| {
        if let Err(e) = tcp.set_nodelay(true) {
            tracing::debug!("cannot set TCP_NODELAY: {e}");
        }
    });
    let server = tokio::spawn(
        axum::serve(listener, app)
            .with_graceful_shutdown(shutdown_signal(state.clone()))
            .into_future(),
    );
    // The drain's deadline: what is still open when it passes is cut (the process exits).
    let deadline = {
        let (drained, timeout) = (state.drained(), config.drain_timeout());
        async move {
            drained.await;
            tokio::time::sleep(timeout).await;
            timeout
        }
    };
    // A model that cannot load (a missing or corrupt graph, no ONNX Runtime) ends the process
    // with the reason: a server that can never be ready helps nobody, and an orchestrator sees
    // the failed start. Until then /health answers and /ready says 503 not_ready.
    loading.await??;
    // Jobs (refinements and fits) whose worker went quiet go back to their queue (or fail) within
    // a second of their lease; each queue's depth is counted anew (for a shared store, the cluster's: what a worker
    // autoscaler reads); jobs past their retention are deleted.
    if let Ok(service) = state.service() {
        let (service, retention) = (service.clone(), config.job_retention());
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(std::time::Duration::from_millis(500));
            let mut failing = false;
            for round in 0u64.. {
                tick.tick().await;
                // Once a minute: jobs that ended longer ago than C4G_JOB_RETENTION_H, and the
                // videos made of them, are deleted.
                if let Some(age) = retention
                    && round % 120 == 0
                {
                    for queue in [&service.jobs, &service.fits] {
                        match queue.prune(age).await {
                            Ok(0) => {}
                            Ok(n) => tracing::info!(jobs = n, "deleted jobs past their retention"),
                            Err(e) => tracing::warn!("cannot delete old jobs: {e}"),
                        }
                    }
                    let videos = c4g_service::jobs::prune_videos(&service.job_videos, age);
                    if videos > 0 {
                        tracing::info!(videos, "deleted refined videos past the job retention");
                    }
                }
                // Said once when it starts failing and once when it recovers, not twice a second.
                let reaped = match service.jobs.reap().await {
                    Ok(n) => service.fits.reap().await.map(|m| n + m),
                    Err(e) => Err(e),
                };
                match reaped {
                    Err(e) if !failing => {
                        tracing::warn!("cannot look for lost jobs: {e}");
                        failing = true;
                    }
                    Ok(_) if failing => {
                        tracing::info!("looking for lost jobs again");
                        failing = false;
                    }
                    _ => {}
                }
                if let Ok(queued) = service.jobs.queued().await {
                    metrics::gauge!("c4g_jobs_queued").set(queued as f64);
                }
                if let Ok(queued) = service.fits.queued().await {
                    metrics::gauge!("c4g_fit_jobs_queued").set(queued as f64);
                }
            }
        });
    }
    tokio::select! {
        served = server => served??,
        timeout = deadline => tracing::warn!(
            "the drain took longer than {timeout:?} (C4G_DRAIN_TIMEOUT_S): cutting the requests still open"
        ),
    }
    tracing::info!("stopped");
    Ok(())
}

/// The model on the device the configuration asks for: with `auto`, CUDA when it loads there,
/// else the CPU; the configuration returned names the device it runs on.
fn load_engine(mut config: Config) -> Result<(Engine, Config), String> {
    use c4g_service::config::DeviceArg;
    let cannot = |e: &dyn std::fmt::Display, config: &Config| {
        format!("cannot load the model {}: {e}", config.model.display())
    };
    match Engine::load(&config.model, config.engine_options()) {
        Ok(engine) => {
            if matches!(config.device, DeviceArg::Auto) {
                config.device = DeviceArg::Cuda;
            }
            tracing::info!(device = ?config.device, "the model runs on {:?}", config.device);
            Ok((engine, config))
        }
        // Whatever stopped CUDA (no cuda build, a CPU-only ONNX Runtime, no GPU, a driver that
        // fails): the CPU is tried, and a package fault fails there too, with its own words.
        Err(e) if matches!(config.device, DeviceArg::Auto) => {
            tracing::info!("device auto: CUDA is not available ({e}); the model runs on the CPU");
            config.device = DeviceArg::Cpu;
            let engine = Engine::load(&config.model, config.engine_options())
                .map_err(|e| cannot(&e, &config))?;
            Ok((engine, config))
        }
        Err(e) => Err(cannot(&e, &config)),
    }
}

/// Resolves on SIGTERM or Ctrl-C, having started the drain.
async fn shutdown_signal(state: AppState) {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending().await,
        }
    };
    tokio::select! { _ = ctrl_c => {}, _ = terminate => {} }
    state.begin_drain();
    tracing::info!(
        "draining: /ready answers 503, no new connections, requests in flight finish within {:?}",
        state.config().drain_timeout()
    );
}
