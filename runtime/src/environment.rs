//! Loading the ONNX Runtime library once per process.
//!
//! The library is loaded at run time (`ort`'s `load-dynamic`) from the `onnxruntime` PyPI wheel's
//! `libonnxruntime.so`, found through `ORT_DYLIB_PATH` or given explicitly to [`init_runtime`].
//! ONNX Runtime allows one environment per process, so it lives in a static here and every session
//! of every model crate shares it: an engine and a refiner in one process run in the same
//! environment (named "c4g"). A failed load is not remembered: a later call may try again (for
//! example after the operator fixed the path).

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock, PoisonError};

use ort::environment::Environment;

use crate::{Result, RuntimeError};

/// The environment variable that names the ONNX Runtime library.
pub const ORT_DYLIB_PATH: &str = "ORT_DYLIB_PATH";

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
        .ok_or(RuntimeError::NotConfigured)?;
    environment_from(Path::new(&library))
}

fn environment_from(library: &Path) -> Result<&'static Environment> {
    let _guard = INIT.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some(env) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let load_error = |reason: String| RuntimeError::Load {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ErrorKind;

    #[test]
    fn a_missing_library_is_a_load_error_naming_the_path() {
        if runtime_initialized() {
            return; // the first successful load wins; nothing left to test here
        }
        let err = init_runtime(Path::new("/nonexistent/libonnxruntime.so")).unwrap_err();
        assert!(matches!(err, RuntimeError::Load { .. }), "{err}");
        assert!(err.to_string().contains("/nonexistent/libonnxruntime.so"));
        assert_eq!(err.kind(), ErrorKind::Runtime);
    }
}
