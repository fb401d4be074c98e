//! Crash-safe writes: a file written whole and synced, and a directory synced after entries are
//! created or renamed in it, so that what a crash (even of the machine) leaves is the old state or
//! the new one. The store, the shared store and the job store write through these.

use std::io::Write;
use std::path::Path;

/// Writes `bytes` to a new file at `path` and syncs it to the disk.
pub fn write_synced(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut file = std::fs::File::create(path)?;
    file.write_all(bytes)?;
    file.sync_all()
}

/// Syncs a directory, so that the entries just created or renamed in it survive a crash of the
/// machine.
pub fn sync_dir(dir: &Path) -> std::io::Result<()> {
    std::fs::File::open(dir)?.sync_all()
}
