//! ONNX Runtime: loading the library once per process, engine options, and sessions.
//!
//! The library is loaded at run time (`ort`'s `load-dynamic`) from the `onnxruntime` PyPI wheel's
//! `libonnxruntime.so`, found through `ORT_DYLIB_PATH` or given explicitly to [`init_runtime`].
//! ONNX Runtime allows one environment per process, so it lives in a static and every session of
//! every engine shares it. A failed load is not remembered: a later call may try again (for
//! example after the operator fixed the path).

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock, PoisonError};

use ort::environment::Environment;
use ort::session::Session;

use crate::time::TimePolicy;
use crate::{EngineError, Result};

/// The environment variable that names the ONNX Runtime library.
pub const ORT_DYLIB_PATH: &str = "ORT_DYLIB_PATH";

/// Where the model runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum ExecutionProvider {
    /// ONNX Runtime's CPU kernels.
    #[default]
    Cpu,
    /// NVIDIA CUDA, on the given device. Needs this crate's `cuda` feature and an ONNX Runtime
    /// built with CUDA (the `onnxruntime-gpu` wheel); loading fails with a clear error otherwise,
    /// rather than silently running on the CPU.
    Cuda {
        /// CUDA device ordinal.
        device_id: i32,
    },
}

/// How an [`Engine`](crate::Engine) runs its package.
#[derive(Debug, Clone, PartialEq)]
pub struct EngineOptions {
    /// Threads ONNX Runtime may use inside one operator; 0 leaves ONNX Runtime's default
    /// (one per physical core).
    pub intra_op_threads: usize,
    /// Where the graphs run.
    pub execution_provider: ExecutionProvider,
    /// How timestamps are normalised for the decoder.
    pub time_policy: TimePolicy,
    /// Most targets decoded in one decoder run; larger requests are split into chunks.
    pub max_batch: usize,
    /// Bytes of working memory one decoder run may need; batches shrink (down to one target) to
    /// stay under it. With fused attention a target costs about `8 · C · (T·P + N) · 4` bytes
    /// (~350 MB for the official model at T = 16); a package exported with plain attention
    /// materialises every score matrix, `2 · heads · (T·P + N)² · 4` bytes (~5 GB). 0 disables
    /// the limit (only `max_batch` applies). See [`Engine::decode_batch_size`](crate::Engine::decode_batch_size).
    pub decoder_memory_budget: usize,
    /// Use ONNX Runtime's CPU memory arena. The arena reuses buffers across runs but holds on to
    /// the peak allocation of the largest request for the life of the session (gigabytes, for
    /// the decoder at 16 frames); off (the default), memory goes back to the allocator after
    /// each run.
    pub cpu_arena: bool,
}

impl Default for EngineOptions {
    fn default() -> Self {
        Self {
            intra_op_threads: 0,
            execution_provider: ExecutionProvider::Cpu,
            time_policy: TimePolicy::Stable,
            max_batch: 16,
            decoder_memory_budget: 4 << 30,
            cpu_arena: false,
        }
    }
}

static ENVIRONMENT: OnceLock<Environment> = OnceLock::new();
static INIT: Mutex<()> = Mutex::new(());

/// Loads ONNX Runtime from `library` (a `libonnxruntime.so`) for this process.
///
/// The first successful load wins: later calls, with any path, return `Ok` and change nothing.
pub fn init_runtime(library: &Path) -> Result<()> {
    environment_from(library).map(|_| ())
}

/// True once ONNX Runtime has been loaded in this process.
pub fn runtime_initialized() -> bool {
    ENVIRONMENT.get().is_some()
}

/// The process's ONNX Runtime environment, loading the library named by `ORT_DYLIB_PATH` if no
/// library was loaded yet.
pub(crate) fn environment() -> Result<&'static Environment> {
    if let Some(env) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let library = std::env::var_os(ORT_DYLIB_PATH)
        .filter(|p| !p.is_empty())
        .ok_or(EngineError::RuntimeNotConfigured)?;
    environment_from(Path::new(&library))
}

fn environment_from(library: &Path) -> Result<&'static Environment> {
    let _guard = INIT.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some(env) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let load_error = |reason: String| EngineError::RuntimeLoad {
        path: library.to_path_buf(),
        reason,
    };
    // An absolute path keeps ort from resolving it against the executable's directory.
    let absolute: PathBuf = std::fs::canonicalize(library)
        .map_err(|e| load_error(format!("{e} (check {ORT_DYLIB_PATH})")))?;
    let env = ort::init_from(&absolute)
        .map_err(|e| load_error(e.to_string()))?
        .with_name("c4g")
        .with_telemetry(false)
        .build()
        .map_err(|e| load_error(e.to_string()))?;
    Ok(ENVIRONMENT.get_or_init(|| env))
}

/// Opens one ONNX graph as a session configured by `options`.
pub(crate) fn create_session(model: &Path, options: &EngineOptions) -> Result<Session> {
    let env = environment()?;
    let what = || format!("loading {}", model.display());
    let mut builder = Session::builder(env).map_err(EngineError::ort(what()))?;
    if options.intra_op_threads > 0 {
        builder = builder
            .with_intra_threads(options.intra_op_threads)
            .map_err(|e| EngineError::ort(what())(e.into()))?;
    }
    builder = register_provider(builder, options)?;
    builder
        .commit_from_file(model)
        .map_err(EngineError::ort(what()))
}

fn register_provider(
    builder: ort::session::builder::SessionBuilder,
    options: &EngineOptions,
) -> Result<ort::session::builder::SessionBuilder> {
    match options.execution_provider {
        ExecutionProvider::Cpu => {
            let cpu = ort::ep::CPU::default()
                .with_arena_allocator(options.cpu_arena)
                .build()
                .error_on_failure();
            builder
                .with_execution_providers([cpu])
                .map_err(|e| EngineError::ort("configuring the CPU execution provider")(e.into()))
        }
        ExecutionProvider::Cuda { device_id } => register_cuda(builder, device_id),
    }
}

#[cfg(feature = "cuda")]
fn register_cuda(
    builder: ort::session::builder::SessionBuilder,
    device_id: i32,
) -> Result<ort::session::builder::SessionBuilder> {
    let cuda = ort::ep::CUDA::default()
        .with_device_id(device_id)
        .build()
        .error_on_failure();
    builder.with_execution_providers([cuda]).map_err(|e| {
        EngineError::ExecutionProviderUnavailable {
            provider: format!("CUDA (device {device_id})"),
            reason: e.to_string(),
        }
    })
}

#[cfg(not(feature = "cuda"))]
fn register_cuda(
    _builder: ort::session::builder::SessionBuilder,
    device_id: i32,
) -> Result<ort::session::builder::SessionBuilder> {
    Err(EngineError::ExecutionProviderUnavailable {
        provider: format!("CUDA (device {device_id})"),
        reason: "c4g-engine was built without its `cuda` feature".to_owned(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_options_run_on_the_cpu_with_the_stable_policy() {
        let o = EngineOptions::default();
        assert_eq!(o.execution_provider, ExecutionProvider::Cpu);
        assert_eq!(o.time_policy, TimePolicy::Stable);
        assert_eq!((o.intra_op_threads, o.max_batch), (0, 16));
        assert_eq!(o.decoder_memory_budget, 4 << 30);
        assert!(!o.cpu_arena);
    }

    #[test]
    fn a_missing_library_is_a_load_error_naming_the_path() {
        if runtime_initialized() {
            return; // the first successful load wins; nothing left to test here
        }
        let err = init_runtime(Path::new("/nonexistent/libonnxruntime.so")).unwrap_err();
        assert!(matches!(err, EngineError::RuntimeLoad { .. }), "{err}");
        assert!(err.to_string().contains("/nonexistent/libonnxruntime.so"));
    }
}
