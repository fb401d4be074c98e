//! The transformer's session with the LoRA-merged weights in place of the package's own.
//!
//! Everything else about sessions (the one ONNX Runtime environment, execution providers,
//! session options) is `c4g-runtime`'s; this file only swaps initializers in before the builder
//! commits the model.

use std::path::Path;
use std::sync::Arc;

use c4g_runtime::{RuntimeError, SessionOptions, session_builder};
use ort::session::Session;
use ort::value::{DynValue, Tensor};

use crate::Result;
use crate::lora::merge::{MergedWeight, WeightValues};
use crate::onnx::OnnxWeights;

/// ONNX Runtime's session option naming the folder of external data for in-memory models.
const EXTERNAL_DATA_FOLDER: &str = "session.model_external_initializers_file_folder_path";

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
    options: &SessionOptions,
    weights: &OnnxWeights,
    merged: Vec<MergedWeight>,
) -> Result<Session> {
    let (external, embedded): (Vec<MergedWeight>, Vec<MergedWeight>) = merged
        .into_iter()
        .partition(|w| weights.get(&w.name).is_some_and(|i| i.is_external()));
    let mut builder = session_builder(model, options)?;
    for weight in external {
        let name = weight.name.clone();
        let value = weight_value(weight)?;
        builder = builder
            .with_external_initializer(&name, value)
            .map_err(RuntimeError::ort(format!("replacing initializer {name:?}")))?;
    }
    if embedded.is_empty() {
        return Ok(builder
            .commit_from_file(model)
            .map_err(RuntimeError::ort(loading(model)))?);
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
        .map_err(RuntimeError::ort(loading(model)))?;
    Ok(builder
        .commit_from_memory(&patched)
        .map_err(RuntimeError::ort(loading(model)))?)
}

fn loading(model: &Path) -> String {
    format!("loading {}", model.display())
}

fn weight_value(weight: MergedWeight) -> Result<Arc<DynValue>> {
    let context = || format!("preparing the merged weight {:?}", weight.name);
    let dims = weight.dims;
    let value = match weight.values {
        WeightValues::F32(v) => Tensor::from_array((dims, v)).map(Tensor::into_dyn),
        WeightValues::F16(v) => Tensor::from_array((dims, v)).map(Tensor::into_dyn),
        WeightValues::Bf16(v) => Tensor::from_array((dims, v)).map(Tensor::into_dyn),
    }
    .map_err(RuntimeError::ort(context()))?;
    Ok(Arc::new(value))
}
