//! The transformer's session with the LoRA-merged weights in place of the package's own.
//!
//! Everything else about sessions (the one ONNX Runtime environment, execution providers,
//! session options) is `c4g-runtime`'s; this file only swaps weights in before the builder
//! commits the model.
//!
//! The replacement has to happen before ONNX Runtime optimises the graph: the exported graph
//! feeds each Linear weight through a Transpose that constant folding bakes into a new
//! initializer, so `AddInitializer`, which swaps values in after that, would leave the model's
//! own weights in use. And it has to cost one copy of the weights, not two: ONNX Runtime copies
//! initializers handed to it in memory (`AddExternalInitializers`) and requires the caller's
//! buffers to outlive the session as well, which held every merged weight twice (at the 1.3B
//! size +5.6 GB for the worker's life, +10 GB at the start-up peak: docs/benchmarks.md). So:
//! - weights stored in the model file are written over their bytes in an in-memory copy of it
//!   (such models are under 2 GiB);
//! - weights in external data (every real-size export) are written, one batch at a time as they
//!   are merged, over their bytes in a copy of the external-data file made in a scratch folder
//!   (`merge_dir`), and ONNX Runtime reads them from there as it reads any package: on the CPU
//!   it maps aligned external data instead of copying it. External files that hold no merged
//!   weight are hard-linked into the folder (copied where a link cannot be made). The folder is
//!   deleted once the session exists: what ONNX Runtime mapped stays valid until it unmaps it.

use std::fs::{File, OpenOptions};
use std::os::unix::fs::FileExt;
use std::path::Path;

use c4g_runtime::{RuntimeError, SessionOptions, session_builder};
use ort::session::Session;

use crate::lora::Lora;
use crate::lora::merge::{MergedWeight, merge_each};
use crate::onnx::{OnnxWeights, external_path};
use crate::{RefinerError, Result};

/// ONNX Runtime's session option naming the folder of external data for in-memory models.
const EXTERNAL_DATA_FOLDER: &str = "session.model_external_initializers_file_folder_path";

/// Opens `model` (whose initializers `weights` describes) with `lora` merged at `scale` into the
/// initializers it adapts. External data is copied into a scratch folder made in `merge_dir`
/// (the system's temporary folder when `None`; it needs room for the model's external data, and
/// on a RAM-backed file system that room is memory). Returns the session and how many weights
/// were merged.
pub(crate) fn create_session_with_lora(
    model: &Path,
    options: &SessionOptions,
    weights: &OnnxWeights,
    lora: &Lora,
    scale: f32,
    merge_dir: Option<&Path>,
) -> Result<(Session, usize)> {
    let locations = weights.external_locations();
    let scratch = if locations.is_empty() {
        None
    } else {
        let parent = merge_dir.map_or_else(std::env::temp_dir, Path::to_path_buf);
        let dir = tempfile::Builder::new()
            .prefix("c4g-refiner-merge-")
            .tempdir_in(&parent)
            .map_err(RefinerError::io(&parent))?;
        Some(dir)
    };
    let mut external = ExternalCopies::default();
    let mut embedded: Vec<MergedWeight> = Vec::new();
    let count = merge_each(lora, weights, scale, |weight| {
        let location = weights
            .get(&weight.name)
            .and_then(|init| init.external_location());
        match (location, &scratch) {
            (Some((location, offset)), Some(dir)) => {
                external.write(model, dir.path(), location, offset, &weight)
            }
            _ => {
                embedded.push(weight);
                Ok(())
            }
        }
    })?;
    if count == 0 {
        // Scale 0: every module was placed and checked, nothing changed; the package as it is.
        let session = session_builder(model, options)?
            .commit_from_file(model)
            .map_err(RuntimeError::ort(loading(model)))?;
        return Ok((session, 0));
    }
    let folder = match &scratch {
        Some(dir) => {
            for location in locations {
                external.link_untouched(model, dir.path(), location)?;
            }
            dir.path().to_path_buf()
        }
        None => model.parent().unwrap_or(Path::new(".")).to_path_buf(),
    };
    let patched = weights.patched(
        embedded
            .iter()
            .map(|w| (w.name.as_str(), w.values.to_le_bytes())),
    )?;
    drop(embedded);
    // A model read from memory has no directory for its external data: give it the one with the
    // merged copies.
    let session = session_builder(model, options)?
        .with_config_entry(EXTERNAL_DATA_FOLDER, folder.to_string_lossy())
        .map_err(RuntimeError::ort(loading(model)))?
        .commit_from_memory(&patched)
        .map_err(RuntimeError::ort(loading(model)))?;
    drop(scratch);
    Ok((session, count))
}

fn loading(model: &Path) -> String {
    format!("loading {}", model.display())
}

/// The external-data files copied into the scratch folder so far, open for writing.
#[derive(Default)]
struct ExternalCopies {
    open: Vec<(String, File)>,
}

impl ExternalCopies {
    /// Writes `weight` over its bytes at `offset` in the scratch copy of `location`, copying the
    /// package's file there first.
    fn write(
        &mut self,
        model: &Path,
        dir: &Path,
        location: &str,
        offset: u64,
        weight: &MergedWeight,
    ) -> Result<()> {
        let index = match self.open.iter().position(|(l, _)| l == location) {
            Some(i) => i,
            None => {
                let (source, target) = paths(model, dir, location)?;
                std::fs::copy(&source, &target).map_err(RefinerError::io(&target))?;
                let file = OpenOptions::new()
                    .write(true)
                    .open(&target)
                    .map_err(RefinerError::io(&target))?;
                self.open.push((location.to_owned(), file));
                self.open.len() - 1
            }
        };
        let (_, file) = &self.open[index];
        file.write_all_at(&weight.values.to_le_bytes(), offset)
            .map_err(RefinerError::io(dir.join(location)))
    }

    /// Makes `location` readable in the scratch folder when no merged weight lives in it.
    fn link_untouched(&self, model: &Path, dir: &Path, location: &str) -> Result<()> {
        if self.open.iter().any(|(l, _)| l == location) {
            return Ok(());
        }
        let (source, target) = paths(model, dir, location)?;
        if std::fs::hard_link(&source, &target).is_err() {
            std::fs::copy(&source, &target).map_err(RefinerError::io(&target))?;
        }
        Ok(())
    }
}

/// The package's file for `location` and its place in the scratch folder (parent folders made).
fn paths(
    model: &Path,
    dir: &Path,
    location: &str,
) -> Result<(std::path::PathBuf, std::path::PathBuf)> {
    let relative = external_path(model, location)?;
    let source = model.parent().unwrap_or(Path::new(".")).join(&relative);
    let target = dir.join(&relative);
    if let Some(parent) = target.parent() {
        std::fs::create_dir_all(parent).map_err(RefinerError::io(parent))?;
    }
    Ok((source, target))
}
