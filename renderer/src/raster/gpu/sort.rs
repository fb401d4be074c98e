//! Host side of the two GPU primitives the frame is built on: exclusive prefix sums
//! (`scan.wgsl`) and a stable radix sort of (key, value) pairs (`sort.wgsl`).
//!
//! The sort is least-significant digit first, 4 bits a pass, and only over the bits the keys can
//! use: depth keys are offsets from the near plane's bit pattern (27 bits for the default 0.01 to
//! 100), tile keys count the tiles of one band. Stability is the point: sorting the (tile,
//! Gaussian) pairs by tile alone keeps the depth order they were emitted in.

use c4g_scene::SceneError;

use super::recorder::{Use, Work};

/// Elements one workgroup of `scan.wgsl` handles.
const SCAN_BLOCK: u32 = 1024;
/// Elements one workgroup of `sort.wgsl` handles.
const SORT_BLOCK: u32 = 2048;
/// Bits a radix sort pass handles.
const DIGIT_BITS: u32 = 4;
/// Names of the per-level block sums of a scan (1024^8 elements is more than u32 counts).
const SCAN_LEVELS: [&str; 8] = [
    "scan sums 0",
    "scan sums 1",
    "scan sums 2",
    "scan sums 3",
    "scan sums 4",
    "scan sums 5",
    "scan sums 6",
    "scan sums 7",
];

/// Where a scan left its total: one u32 at the start of this buffer.
pub(super) struct Total(pub wgpu::Buffer);

/// Scans `data[..len]` in place to its exclusive prefix sums (saturating at u32::MAX).
pub(super) fn scan(work: &mut Work, data: &wgpu::Buffer, len: u32) -> Result<Total, SceneError> {
    scan_level(work, data, len, 0)
}

fn scan_level(
    work: &mut Work,
    data: &wgpu::Buffer,
    len: u32,
    level: usize,
) -> Result<Total, SceneError> {
    let blocks = len.div_ceil(SCAN_BLOCK).max(1);
    let name = SCAN_LEVELS.get(level).ok_or_else(|| {
        SceneError::Gpu(format!("a scan of {len} elements is deeper than expected"))
    })?;
    let sums = work.buffer(name, 0, u64::from(blocks) * 4, Use::Storage)?;
    let grid = work.gpu.grid(blocks)?;
    let params = [len, blocks, grid.x, 0];
    let kernels = work.kernels;
    work.dispatch(&kernels.scan_blocks, &params, &[data, &sums], grid);
    if blocks == 1 {
        return Ok(Total(sums));
    }
    let total = scan_level(work, &sums, blocks, level + 1)?;
    work.dispatch(&kernels.add_block_sums, &params, &[data, &sums], grid);
    Ok(total)
}

/// A pair of key and value buffers.
#[derive(Clone)]
pub(super) struct Pairs {
    pub keys: wgpu::Buffer,
    pub values: wgpu::Buffer,
}

/// Sorts `len` pairs of `data` by the low `bits` bits of their keys, stably, using `spare` as the
/// other half of each pass; returns whichever of the two holds the result.
pub(super) fn radix_sort(
    work: &mut Work,
    data: Pairs,
    spare: Pairs,
    len: u32,
    bits: u32,
) -> Result<Pairs, SceneError> {
    let (mut from, mut to) = (data, spare);
    if len < 2 {
        return Ok(from);
    }
    let blocks = len.div_ceil(SORT_BLOCK);
    let counts = work.buffer("radix counts", 0, u64::from(blocks) * 16 * 4, Use::Storage)?;
    let grid = work.gpu.grid(blocks)?;
    let kernels = work.kernels;
    for pass in 0..bits.div_ceil(DIGIT_BITS) {
        let params = [len, pass * DIGIT_BITS, blocks, grid.x];
        work.dispatch(&kernels.histogram, &params, &[&from.keys, &counts], grid);
        scan(work, &counts, blocks * 16)?;
        work.dispatch(
            &kernels.scatter,
            &params,
            &[&from.keys, &from.values, &counts, &to.keys, &to.values],
            grid,
        );
        std::mem::swap(&mut from, &mut to);
    }
    Ok(from)
}

/// Bits needed to write every number up to `max`.
pub(super) fn bits_for(max: u32) -> u32 {
    u32::BITS - max.leading_zeros()
}

#[cfg(test)]
mod tests {
    use super::bits_for;

    #[test]
    fn key_widths_cover_their_largest_key() {
        assert_eq!(bits_for(0), 0);
        assert_eq!(bits_for(1), 1);
        assert_eq!(bits_for(15), 4);
        assert_eq!(bits_for(16), 5);
        assert_eq!(bits_for(u32::MAX), 32);
        let depth_range = 100f32.to_bits() - 0.01f32.to_bits() + 1;
        assert_eq!(bits_for(depth_range), 27);
    }
}
