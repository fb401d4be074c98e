//! Every committed fuzz input, replayed through the fuzz targets' entry points in the ordinary
//! test build: `fuzz/regressions/TARGET` (inputs that once failed) and `fuzz/corpus/TARGET`
//! (inputs that reach new code). This is CI's check of the fuzz targets: it replays what a brief
//! `cargo fuzz` run replays, without the instrumented build (about 8 minutes on two cores, where
//! this takes under a minute). `scripts/fuzz` does the fuzzing, and finds new inputs.
//!
//! Every input must be answered without a bug (`c4g_server::fuzzing` says what a bug is for each
//! target); a failure names the input's file.
#![cfg(feature = "fuzzing")]
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};

use c4g_server::fuzzing;

/// The committed inputs of `target`, regressions first.
fn inputs(target: &str) -> Vec<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let mut paths = Vec::new();
    for dir in ["regressions", "corpus"] {
        let Ok(entries) = std::fs::read_dir(root.join(dir).join(target)) else {
            continue;
        };
        let mut files: Vec<PathBuf> = entries.map(|e| e.unwrap().path()).collect();
        files.sort();
        paths.extend(files);
    }
    paths
}

fn replay(target: &str, run: impl Fn(&[u8]) -> Result<(), String>) {
    let paths = inputs(target);
    // The corpora are committed: an empty one means the replay lost its way, not a pass.
    assert!(
        paths.len() > 10,
        "{target}: only {} inputs found",
        paths.len()
    );
    for path in paths {
        let bytes = std::fs::read(&path).unwrap();
        if let Err(bug) = run(&bytes) {
            panic!("{target}: {}: {bug}", path.display());
        }
    }
}

#[test]
fn upload_inputs_find_no_bug() {
    replay("upload", fuzzing::upload);
}

#[test]
fn gaussian_file_inputs_find_no_bug() {
    replay("gaussian_files", fuzzing::gaussian_files);
}

#[test]
fn time_policy_inputs_find_no_bug() {
    replay("time_policy", fuzzing::time_policy);
}

#[test]
fn rest_inputs_find_no_bug() {
    replay("rest", |input| fuzzing::Edge::get().rest(input));
}

#[test]
fn grpc_inputs_find_no_bug() {
    replay("grpc", |input| fuzzing::Edge::get().grpc(input));
}
