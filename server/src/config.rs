//! The server's settings. Every flag also reads an environment variable, and every default works
//! on a laptop.

use std::net::SocketAddr;
use std::path::PathBuf;

use c4g_engine::{EngineOptions, ExecutionProvider, TimePolicy};
use clap::{Parser, ValueEnum};

/// Serve a C4G model package over HTTP.
#[derive(Debug, Clone, Parser)]
#[command(name = "c4g-server", version)]
pub struct Config {
    /// Address to listen on (port 0 picks a free port; the chosen address is printed).
    #[arg(long, env = "C4G_LISTEN", default_value = "127.0.0.1:8080")]
    pub listen: SocketAddr,
    /// The model package directory (model.json + ONNX graphs).
    #[arg(long, env = "C4G_MODEL", default_value = "models/fixtures/c4g-small")]
    pub model: PathBuf,
    /// ONNX Runtime intra-op threads (0: ONNX Runtime's default, one per core).
    #[arg(long, env = "C4G_INTRA_OP_THREADS", default_value_t = 0)]
    pub intra_op_threads: usize,
    /// Where the model runs. `cuda` needs c4g-server built with `--features cuda` and the
    /// onnxruntime-gpu library; it never falls back to the CPU silently.
    #[arg(long, env = "C4G_DEVICE", value_enum, default_value_t = DeviceArg::Cpu)]
    pub device: DeviceArg,
    /// CUDA device ordinal (with `--device cuda`).
    #[arg(long, env = "C4G_CUDA_DEVICE", default_value_t = 0)]
    pub cuda_device: i32,
    /// How timestamps are normalised before the decoder (docs/time-policy.md).
    #[arg(long, env = "C4G_TIME_POLICY", value_enum, default_value_t = PolicyArg::Stable)]
    pub time_policy: PolicyArg,
}

/// [`ExecutionProvider`] as a command-line value.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum DeviceArg {
    /// ONNX Runtime's CPU kernels.
    Cpu,
    /// NVIDIA CUDA.
    Cuda,
}

/// [`TimePolicy`] as a command-line value.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum PolicyArg {
    /// Bounded and defined over the whole context span; equal to the reference past the first gap.
    Stable,
    /// The public reference's normalisation, exactly (for parity checks).
    Reference,
}

impl Config {
    /// The engine options these settings ask for.
    pub fn engine_options(&self) -> EngineOptions {
        EngineOptions {
            intra_op_threads: self.intra_op_threads,
            execution_provider: match self.device {
                DeviceArg::Cpu => ExecutionProvider::Cpu,
                DeviceArg::Cuda => ExecutionProvider::Cuda {
                    device_id: self.cuda_device,
                },
            },
            time_policy: match self.time_policy {
                PolicyArg::Stable => TimePolicy::Stable,
                PolicyArg::Reference => TimePolicy::Reference,
            },
            ..EngineOptions::default()
        }
    }
}
