//! Gaussian sets as bytes: on disk, in the formats other tools read, and on the service's wire.
//!
//! - [`ply`]: the 3D Gaussian splatting `.ply` (what trainers and most viewers exchange), read in
//!   any of its variations, written in the common binary layout, optionally with feature columns;
//! - [`splat`]: antimatter15's compact `.splat` (32 bytes a Gaussian), for web viewers;
//! - [`splatv`]: antimatter15's `.splatv` for the splaTV player: a time range of sets as one file,
//!   each Gaussian fitted with a motion model (cubic position, linear rotation, a temporal
//!   opacity bump) with the fit's measured error;
//! - [`spz`]: Niantic's SPZ (version 4): quantised to about 20 bytes a Gaussian, then zstd, for
//!   the viewers and tools built on its reference library;
//! - [`series`]: a time series of Gaussian sets: a directory of `.ply` files and a JSON index;
//! - [`frames_zip`]: a time series as one zip of per-time `.ply` or `.spz` files (what players
//!   of splat sequences open), the times in the archive's comment;
//! - [`c4gs`]: the service's packed `C4GS` frames (`f32` or `f16` columns), and the column
//!   packing the gRPC messages share with it;
//! - [`c4gv`]: `C4GV`, a compact stream of one clip's sets over a time range: quantised within
//!   stated error bounds, static Gaussians once, the rest as deltas with keyframes to seek to,
//!   decodable frame by frame as bytes arrive.
//!
//! Every reader fails with a [`SceneError::Format`](c4g_scene::SceneError::Format) that says
//! what is wrong and where, never with a panic, whatever the bytes.

pub mod c4gs;
pub mod c4gv;
pub mod frames_zip;
pub mod ply;
pub mod series;
pub mod splat;
pub mod splatv;
pub mod spz;

use std::path::Path;

use c4g_scene::SceneError;

/// Reads a whole file, with the path in the error.
fn read_file(path: &Path) -> Result<Vec<u8>, SceneError> {
    std::fs::read(path).map_err(|e| io_error(path, e))
}

/// Writes a whole file, with the path in the error.
fn write_file(path: &Path, bytes: &[u8]) -> Result<(), SceneError> {
    std::fs::write(path, bytes).map_err(|e| io_error(path, e))
}

fn io_error(path: &Path, e: std::io::Error) -> SceneError {
    SceneError::Io {
        path: path.display().to_string(),
        message: e.to_string(),
    }
}
