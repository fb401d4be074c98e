//! The CPU rasterizer's tiling: the image is cut into square tiles, each blended on one thread
//! from the splats that reach it, and (tile, splat) pairs are held in bands of bounded size.

/// Tile edge in pixels.
pub const TILE: u32 = 16;
/// Most (tile, splat) pairs held at once; more are processed in successive bands of tiles.
pub const PAIR_BUDGET: usize = 1 << 24;
