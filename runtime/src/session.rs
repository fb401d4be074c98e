//! Sessions: where a graph runs, how it is configured, and opening it.
//!
//! Every session is created in the process's one environment (`environment`) with the options
//! of [`SessionOptions`]. An execution provider that cannot be had is an error, never a silent
//! fall-back to the CPU.

use std::path::Path;

use ort::session::Session;
use ort::session::builder::SessionBuilder;

use crate::environment::environment;
use crate::{Result, RuntimeError};

/// Where the graphs run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum ExecutionProvider {
    /// ONNX Runtime's CPU kernels.
    #[default]
    Cpu,
    /// NVIDIA CUDA, on the given device. Needs the `cuda` feature (of this crate, which the model
    /// crates' and the server's `cuda` features turn on) and an ONNX Runtime built with CUDA (the
    /// `onnxruntime-gpu` wheel); creating a session fails with a clear error otherwise, rather
    /// than silently running on the CPU.
    Cuda {
        /// CUDA device ordinal.
        device_id: i32,
    },
}

/// How the sessions of a model are configured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SessionOptions {
    /// Threads ONNX Runtime may use inside one operator; 0 leaves ONNX Runtime's default
    /// (one per physical core).
    pub intra_op_threads: usize,
    /// Where the graphs run.
    pub execution_provider: ExecutionProvider,
    /// Use ONNX Runtime's CPU memory arena. The arena reuses buffers across runs but holds on to
    /// the peak allocation of the largest run for the life of the session (gigabytes, for the
    /// engine's decoder at 16 frames); off (the default), memory goes back to the allocator after
    /// each run.
    pub cpu_arena: bool,
    /// Let ONNX Runtime's intra-op threads spin while they wait for work (its own default, on).
    /// Spinning trades CPU for latency between operators; on a machine with few cores that also
    /// runs other work (the rasterizer, the network) it can cost more than it saves: measure
    /// (`python -m c4g.bench.decoder`, docs/benchmarks.md).
    pub intra_op_spinning: bool,
}

impl Default for SessionOptions {
    fn default() -> Self {
        Self {
            intra_op_threads: 0,
            execution_provider: ExecutionProvider::Cpu,
            cpu_arena: false,
            intra_op_spinning: true,
        }
    }
}

/// Opens the ONNX graph `model` as it is on disk, as a session configured by `options`.
pub fn create_session(model: &Path, options: &SessionOptions) -> Result<Session> {
    session_builder(model, options)?
        .commit_from_file(model)
        .map_err(RuntimeError::ort(loading(model)))
}

/// A session builder configured by `options`, for a caller that commits `model` itself (the
/// refiner, which swaps merged weights in before committing).
pub fn session_builder(model: &Path, options: &SessionOptions) -> Result<SessionBuilder> {
    let env = environment()?;
    let mut builder = Session::builder(env).map_err(RuntimeError::ort(loading(model)))?;
    if options.intra_op_threads > 0 {
        builder = builder
            .with_intra_threads(options.intra_op_threads)
            .map_err(RuntimeError::ort(loading(model)))?;
    }
    if !options.intra_op_spinning {
        builder = builder
            .with_intra_op_spinning(false)
            .map_err(RuntimeError::ort(loading(model)))?;
    }
    register_provider(builder, options)
}

fn loading(model: &Path) -> String {
    format!("loading {}", model.display())
}

fn register_provider(builder: SessionBuilder, options: &SessionOptions) -> Result<SessionBuilder> {
    match options.execution_provider {
        ExecutionProvider::Cpu => {
            let cpu = ort::ep::CPU::default()
                .with_arena_allocator(options.cpu_arena)
                .build()
                .error_on_failure();
            builder
                .with_execution_providers([cpu])
                .map_err(RuntimeError::ort("configuring the CPU execution provider"))
        }
        ExecutionProvider::Cuda { device_id } => register_cuda(builder, device_id),
    }
}

#[cfg(feature = "cuda")]
fn register_cuda(builder: SessionBuilder, device_id: i32) -> Result<SessionBuilder> {
    let cuda = ort::ep::CUDA::default()
        .with_device_id(device_id)
        .build()
        .error_on_failure();
    builder.with_execution_providers([cuda]).map_err(|e| {
        RuntimeError::ExecutionProviderUnavailable {
            provider: format!("CUDA (device {device_id})"),
            reason: e.to_string(),
        }
    })
}

#[cfg(not(feature = "cuda"))]
fn register_cuda(_builder: SessionBuilder, device_id: i32) -> Result<SessionBuilder> {
    Err(RuntimeError::ExecutionProviderUnavailable {
        provider: format!("CUDA (device {device_id})"),
        reason:
            "c4g was built without the `cuda` feature (of c4g-server, c4g-engine or c4g-refiner)"
                .to_owned(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_options_run_on_the_cpu_with_default_threads_and_no_arena() {
        let o = SessionOptions::default();
        assert_eq!(o.execution_provider, ExecutionProvider::Cpu);
        assert_eq!(o.intra_op_threads, 0);
        assert!(!o.cpu_arena);
        assert!(o.intra_op_spinning);
    }
}
