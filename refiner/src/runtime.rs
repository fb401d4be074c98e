//! ONNX Runtime: loading the library once per process, pipeline options, and sessions.
//!
//! As in `c4g-engine`, the library is loaded at run time from `ORT_DYLIB_PATH` (the `onnxruntime`
//! wheel's `libonnxruntime.so`) and the one environment a process may have lives in a static.
//! The refiner runs in its own worker process, so it owns that environment; a process that also
//! hosts the engine would have to share the engine's instead (ONNX Runtime refuses a second).

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

use ort::environment::Environment;
use ort::session::Session;
use ort::session::builder::SessionBuilder;
use ort::value::{DynValue, Tensor};

use crate::lora::merge::{MergedWeight, WeightValues};
use crate::onnx::OnnxWeights;
use crate::{RefinerError, Result};

/// The environment variable that names the ONNX Runtime library.
pub const ORT_DYLIB_PATH: &str = "ORT_DYLIB_PATH";

/// Where the graphs run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum ExecutionProvider {
    /// ONNX Runtime's CPU kernels.
    #[default]
    Cpu,
    /// NVIDIA CUDA on the given device. Needs this crate's `cuda` feature and an ONNX Runtime
    /// built with CUDA; loading fails with a clear error otherwise.
    Cuda {
        /// CUDA device ordinal.
        device_id: i32,
    },
}

static ENVIRONMENT: OnceLock<Environment> = OnceLock::new();
static INIT: Mutex<()> = Mutex::new(());

/// Loads ONNX Runtime from `library` for this process; the first successful load wins.
pub fn init_runtime(library: &Path) -> Result<()> {
    environment_from(library).map(|_| ())
}

/// True once ONNX Runtime has been loaded by this crate in this process.
pub fn runtime_initialized() -> bool {
    ENVIRONMENT.get().is_some()
}

fn environment() -> Result<&'static Environment> {
    if let Some(env) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let library = std::env::var_os(ORT_DYLIB_PATH)
        .filter(|p| !p.is_empty())
        .ok_or(RefinerError::RuntimeNotConfigured)?;
    environment_from(Path::new(&library))
}

fn environment_from(library: &Path) -> Result<&'static Environment> {
    let _guard = INIT.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some(env) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let load_error = |reason: String| RefinerError::RuntimeLoad {
        path: library.to_path_buf(),
        reason,
    };
    // An absolute path keeps ort from resolving it against the executable's directory.
    let absolute: PathBuf = std::fs::canonicalize(library)
        .map_err(|e| load_error(format!("{e} (check {ORT_DYLIB_PATH})")))?;
    let env = ort::init_from(&absolute)
        .map_err(|e| load_error(e.to_string()))?
        .with_name("c4g-refiner")
        .with_telemetry(false)
        .build()
        .map_err(|e| load_error(e.to_string()))?;
    Ok(ENVIRONMENT.get_or_init(|| env))
}

/// How sessions are configured.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct SessionConfig {
    pub(crate) intra_op_threads: usize,
    pub(crate) execution_provider: ExecutionProvider,
    pub(crate) cpu_arena: bool,
}

/// Opens `model` as it is on disk.
pub(crate) fn create_session(model: &Path, config: SessionConfig) -> Result<Session> {
    builder(model, config)?
        .commit_from_file(model)
        .map_err(RefinerError::ort(loading(model)))
}

/// Opens `model` (whose initializers `weights` describes) with `merged` in place of the
/// initializers of the same names, before ONNX Runtime optimises the graph.
///
/// The replacement has to happen before optimisation: the exported graph feeds each Linear weight
/// through a Transpose that constant folding bakes into a new initializer, so ONNX Runtime's
/// `AddInitializer`, which swaps values in after that, would leave the model's own weights in
/// use. Weights stored in the model file are therefore written over their bytes in an in-memory
/// copy of it (no model is written to disk); weights in external data (models over 2 GiB) go in
/// through `AddExternalInitializers`, which ONNX Runtime applies at load, and cost no copy.
pub(crate) fn create_session_with_weights(
    model: &Path,
    config: SessionConfig,
    weights: &OnnxWeights,
    merged: Vec<MergedWeight>,
) -> Result<Session> {
    let (external, embedded): (Vec<MergedWeight>, Vec<MergedWeight>) = merged
        .into_iter()
        .partition(|w| weights.get(&w.name).is_some_and(|i| i.is_external()));
    let mut builder = builder(model, config)?;
    for weight in external {
        let name = weight.name.clone();
        let value = weight_value(weight)?;
        builder = builder
            .with_external_initializer(&name, value)
            .map_err(RefinerError::ort(format!("replacing initializer {name:?}")))?;
    }
    if embedded.is_empty() {
        return builder
            .commit_from_file(model)
            .map_err(RefinerError::ort(loading(model)));
    }
    let patched = weights.patched(
        embedded
            .iter()
            .map(|w| (w.name.as_str(), w.values.to_le_bytes())),
    )?;
    drop(embedded);
    // A model read from memory has no directory for its external data: give it the file's.
    let dir = model.parent().unwrap_or(Path::new("."));
    builder = builder
        .with_config_entry(EXTERNAL_DATA_FOLDER, dir.to_string_lossy())
        .map_err(RefinerError::ort(loading(model)))?;
    builder
        .commit_from_memory(&patched)
        .map_err(RefinerError::ort(loading(model)))
}

/// ONNX Runtime's session option naming the folder of external data for in-memory models.
const EXTERNAL_DATA_FOLDER: &str = "session.model_external_initializers_file_folder_path";

fn loading(model: &Path) -> String {
    format!("loading {}", model.display())
}

fn builder(model: &Path, config: SessionConfig) -> Result<SessionBuilder> {
    let env = environment()?;
    let mut builder = Session::builder(env).map_err(RefinerError::ort(loading(model)))?;
    if config.intra_op_threads > 0 {
        builder = builder
            .with_intra_threads(config.intra_op_threads)
            .map_err(RefinerError::ort(loading(model)))?;
    }
    register_provider(builder, config)
}

fn weight_value(weight: MergedWeight) -> Result<Arc<DynValue>> {
    let context = || format!("preparing the merged weight {:?}", weight.name);
    let dims = weight.dims;
    let value = match weight.values {
        WeightValues::F32(v) => Tensor::from_array((dims, v)).map(Tensor::into_dyn),
        WeightValues::F16(v) => Tensor::from_array((dims, v)).map(Tensor::into_dyn),
        WeightValues::Bf16(v) => Tensor::from_array((dims, v)).map(Tensor::into_dyn),
    }
    .map_err(RefinerError::ort(context()))?;
    Ok(Arc::new(value))
}

fn register_provider(builder: SessionBuilder, config: SessionConfig) -> Result<SessionBuilder> {
    match config.execution_provider {
        ExecutionProvider::Cpu => {
            let cpu = ort::ep::CPU::default()
                .with_arena_allocator(config.cpu_arena)
                .build()
                .error_on_failure();
            builder
                .with_execution_providers([cpu])
                .map_err(RefinerError::ort("configuring the CPU execution provider"))
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
        RefinerError::ExecutionProviderUnavailable {
            provider: format!("CUDA (device {device_id})"),
            reason: e.to_string(),
        }
    })
}

#[cfg(not(feature = "cuda"))]
fn register_cuda(_builder: SessionBuilder, device_id: i32) -> Result<SessionBuilder> {
    Err(RefinerError::ExecutionProviderUnavailable {
        provider: format!("CUDA (device {device_id})"),
        reason: "c4g-refiner was built without its `cuda` feature".to_owned(),
    })
}
