//! One frame on the GPU, from a Gaussian set to an [`Image`].
//!
//! 1. Upload the canonical parameters (and feature groups of 4 channels), **project** every
//!    Gaussian and **sort** all of them once by depth (ties by index: the sort is stable and the
//!    values start in index order).
//! 2. The image is cut into **bands** of tile rows small enough that one band's per-pixel state
//!    fits the device's largest storage binding (one band for ordinary sizes; several for a
//!    4096² image on a device that binds 128 MiB).
//! 3. Per band: **count** each splat's tiles in depth order, scan the counts into offsets and read
//!    the total back. If the (tile, splat) pairs fit in one buffer, one **chunk** takes every
//!    splat; otherwise the offsets come back too and the depth-ordered splats are cut into
//!    chunks that fit. Per chunk: **emit** the pairs, sort them stably by tile, find each tile's
//!    range, **blend**. A chunk continues from the state the previous one left, so chunking
//!    changes nothing in the result.
//! 4. Read the band's state back and finish the pixels on the host (background, alpha, expected
//!    depth): that is a pass over memory the host has to touch anyway.

use rayon::prelude::*;

use c4g_scene::{Camera, GaussianSet, SceneError};

use c4g_scene::Footprint;

use super::super::{FOV_CLAMP, FeatureImage, Image, RenderOptions};
use super::recorder::{Use, Work};
use super::sort::{Pairs, bits_for, radix_sort, scan};

/// Tile edge in pixels (the blend's workgroup is one tile).
const TILE: u32 = 16;
/// Invocations per workgroup of the one-dimensional kernels.
const GROUP: u32 = 256;
/// Floats per Gaussian in the canonical layout.
const PARAMS: u64 = c4g_scene::CANONICAL_CHANNELS as u64;
/// Bytes per Gaussian of the projected splat (3 vec4).
const SPLAT_BYTES: u64 = 48;
/// How the kernels (`project.wgsl`'s `cam.keys.w`, `blend.wgsl`'s `p.footprint`) name a footprint.
fn footprint_code(footprint: Footprint) -> u32 {
    match footprint {
        Footprint::Ellipse => 0,
        Footprint::Tiles3dgs => 1,
    }
}

/// Pixels a thread finishes at a time when a band's state comes back.
const FINISH_CHUNK: usize = 4096;
/// Bytes of band state per pixel: transmittance and (r, g, b, depth), plus 16 per feature group.
const STATE_BYTES: u64 = 4 + 16;
const FEATURE_GROUP_BYTES: u64 = 16;

/// How a frame is cut to fit the device.
#[derive(Debug, Clone, Copy)]
struct Plan {
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    /// Tile rows per band.
    band_rows: u32,
    /// Feature channels rendered, and groups of 4 holding them.
    channels: usize,
    groups: u32,
    /// Most (tile, splat) pairs one chunk may hold.
    pair_cap: u32,
}

impl Plan {
    /// Cuts a `width` × `height` frame with `channels` feature channels for a device whose
    /// buffers hold `cap` bytes and whose dispatches have at most `max_groups` workgroups a side.
    fn new(
        width: u32,
        height: u32,
        channels: usize,
        cap: u64,
        max_groups: u32,
    ) -> Result<Self, SceneError> {
        let (tiles_x, tiles_y) = (width.div_ceil(TILE), height.div_ceil(TILE));
        let groups = u32::try_from(channels.div_ceil(4))
            .map_err(|_| SceneError::Gpu(format!("{channels} feature channels")))?;
        // Read-back packs the band's buffers with padding of up to 16 bytes each.
        let per_row = u64::from(width)
            * u64::from(TILE)
            * (STATE_BYTES + FEATURE_GROUP_BYTES * u64::from(groups));
        let fitting_rows = cap.saturating_sub(64) / per_row;
        let band_rows = fitting_rows
            .min(u64::from(tiles_y))
            .min(u64::from(max_groups)) as u32;
        if tiles_x > max_groups {
            return Err(SceneError::Gpu(format!(
                "a {width}-pixel-wide image has {tiles_x} tiles a row, more than the {max_groups} \
                 workgroups this device dispatches along one side"
            )));
        }
        if band_rows == 0 {
            return Err(SceneError::Gpu(format!(
                "a {width}-pixel-wide image with {channels} feature channels needs {per_row} bytes \
                 per row of tiles, more than the {cap} this device binds"
            )));
        }
        Ok(Self {
            width,
            height,
            tiles_x,
            tiles_y,
            band_rows,
            channels,
            groups,
            pair_cap: u32::try_from(cap / 4).unwrap_or(u32::MAX),
        })
    }

    /// Pixels of the largest band.
    fn band_pixels(&self) -> u64 {
        u64::from(self.width) * u64::from((self.band_rows * TILE).min(self.height))
    }
}

/// One band of tile rows.
#[derive(Debug, Clone, Copy)]
struct Band {
    /// First tile row and tile rows.
    row0: u32,
    rows: u32,
    /// First pixel row and pixel rows.
    y0: u32,
    height: u32,
}

impl Band {
    fn all(plan: &Plan) -> impl Iterator<Item = Band> + '_ {
        (0..plan.tiles_y)
            .step_by(plan.band_rows as usize)
            .map(|row0| {
                let rows = plan.band_rows.min(plan.tiles_y - row0);
                let y0 = row0 * TILE;
                Band {
                    row0,
                    rows,
                    y0,
                    height: (rows * TILE).min(plan.height - y0),
                }
            })
    }

    fn tiles(&self, plan: &Plan) -> u32 {
        self.rows * plan.tiles_x
    }

    fn pixels(&self, plan: &Plan) -> u64 {
        u64::from(self.height) * u64::from(plan.width)
    }
}

/// The buffers every band uses, sized for the frame.
struct FrameBuffers {
    splats: wgpu::Buffer,
    rects: wgpu::Buffer,
    /// Gaussian indices in depth order.
    order: wgpu::Buffer,
    counts: wgpu::Buffer,
    ranges: wgpu::Buffer,
    transmittance: wgpu::Buffer,
    color: wgpu::Buffer,
    features: Option<wgpu::Buffer>,
    feature_groups: Vec<wgpu::Buffer>,
}

/// Renders `set` as `camera` sees it.
pub(super) fn render(
    work: &mut Work,
    set: &GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<Image, SceneError> {
    let features = set.features().filter(|_| options.features);
    let plan = Plan::new(
        camera.width(),
        camera.height(),
        features.map_or(0, |f| f.width()),
        work.gpu.buffer_cap,
        work.gpu.max_groups,
    )?;
    let mut image = background(&plan, options);
    if set.is_empty() {
        return Ok(image);
    }
    let n = gaussian_count(work, set)?;
    let buffers = project_and_sort(work, set, camera, options, &plan, n)?;
    for band in Band::all(&plan) {
        if blend_band(work, &plan, &band, &buffers, n, options.footprint)? {
            read_band(work, &plan, &band, &buffers, options, &mut image)?;
        }
    }
    Ok(image)
}

/// The set's size, checked against what the device can hold.
fn gaussian_count(work: &Work, set: &GaussianSet) -> Result<u32, SceneError> {
    let cap = work.gpu.buffer_cap;
    // The canonical parameters are the largest per-Gaussian buffer.
    let most = cap / (PARAMS * 4).max(SPLAT_BYTES);
    match u32::try_from(set.len()) {
        Ok(n) if u64::from(n) <= most => Ok(n),
        _ => Err(SceneError::Gpu(format!(
            "{} Gaussians are more than the {most} this device holds in one buffer of {cap} bytes",
            set.len()
        ))),
    }
}

/// Uploads the set, projects it and sorts it by depth; allocates the per-band buffers.
fn project_and_sort(
    work: &mut Work,
    set: &GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
    plan: &Plan,
    n: u32,
) -> Result<FrameBuffers, SceneError> {
    let count = u64::from(n);
    let params = work.buffer("gaussians", 0, count * PARAMS * 4, Use::Storage)?;
    work.gpu
        .queue
        .write_buffer(&params, 0, bytemuck::cast_slice(&pack_parameters(set)));
    let mut feature_groups = Vec::with_capacity(plan.groups as usize);
    if let Some(block) = set.features().filter(|_| plan.groups > 0) {
        for g in 0..plan.groups as usize {
            let buffer = work.buffer(
                "feature group",
                g,
                count * FEATURE_GROUP_BYTES,
                Use::Storage,
            )?;
            let group = pack_feature_group(block.width(), block.values(), g);
            work.gpu
                .queue
                .write_buffer(&buffer, 0, bytemuck::cast_slice(&group));
            feature_groups.push(buffer);
        }
    }

    let splats = work.buffer("splats", 0, count * SPLAT_BYTES, Use::Storage)?;
    let rects = work.buffer("rects", 0, count * 16, Use::Storage)?;
    let depth = Pairs {
        keys: work.buffer("depth keys", 0, count * 4, Use::Storage)?,
        values: work.buffer("depth values", 0, count * 4, Use::Storage)?,
    };
    let spare = Pairs {
        keys: work.buffer("depth keys", 1, count * 4, Use::Storage)?,
        values: work.buffer("depth values", 1, count * 4, Use::Storage)?,
    };
    let grid = work.gpu.grid(n.div_ceil(GROUP))?;
    let skipped_key = options.far.to_bits() - options.near.to_bits() + 1;
    let uniform = camera_uniform(camera, options, plan, n, grid.x, skipped_key);
    let kernels = work.kernels;
    work.dispatch(
        &kernels.project,
        &uniform,
        &[&params, &splats, &rects, &depth.keys, &depth.values],
        grid,
    );
    let sorted = radix_sort(work, depth, spare, n, bits_for(skipped_key))?;

    let band_pixels = plan.band_pixels();
    let features = if plan.groups > 0 {
        let bytes = band_pixels * FEATURE_GROUP_BYTES * u64::from(plan.groups);
        Some(work.buffer("feature state", 0, bytes, Use::Storage)?)
    } else {
        None
    };
    Ok(FrameBuffers {
        splats,
        rects,
        order: sorted.values,
        counts: work.buffer("tile counts", 0, count * 4, Use::Storage)?,
        ranges: work.buffer(
            "tile ranges",
            0,
            u64::from(plan.band_rows * plan.tiles_x) * 8,
            Use::Storage,
        )?,
        transmittance: work.buffer("transmittance", 0, band_pixels * 4, Use::Storage)?,
        color: work.buffer("color state", 0, band_pixels * 16, Use::Storage)?,
        features,
        feature_groups,
    })
}

/// Blends every splat that reaches `band`, in as many chunks as the pair buffers need. False
/// when none reaches it (its state was never written).
fn blend_band(
    work: &mut Work,
    plan: &Plan,
    band: &Band,
    buffers: &FrameBuffers,
    n: u32,
    footprint: Footprint,
) -> Result<bool, SceneError> {
    let mut first = 0;
    let mut blended = false;
    while first < n {
        let len = n - first;
        let (total, params) = count_pairs(work, plan, band, buffers, first, len)?;
        if total == 0 {
            break;
        }
        let (take, pairs) = if total <= plan.pair_cap {
            (len, total)
        } else {
            chunk_that_fits(work, buffers, len, plan.pair_cap)?
        };
        let sorted = bin_chunk(work, plan, band, buffers, params, take, pairs)?;
        blend_chunk(work, plan, band, buffers, &sorted, !blended, footprint)?;
        blended = true;
        first += take;
    }
    Ok(blended)
}

/// Counts the band's tiles of splats `first..first + len` (depth order) and scans the counts
/// into offsets; returns the total and the parameters `emit` shares with `count`.
fn count_pairs(
    work: &mut Work,
    plan: &Plan,
    band: &Band,
    buffers: &FrameBuffers,
    first: u32,
    len: u32,
) -> Result<(u32, [u32; 8]), SceneError> {
    let grid = work.gpu.grid(len.div_ceil(GROUP))?;
    let params = [first, len, band.row0, band.rows, plan.tiles_x, 0, grid.x, 0];
    let kernels = work.kernels;
    work.dispatch(
        &kernels.count,
        &params,
        &[&buffers.order, &buffers.rects, &buffers.counts],
        grid,
    );
    let total = scan(work, &buffers.counts, len)?;
    let total = work.read(&[(&total.0, 4)], |bytes| first_u32(bytes[0]))??;
    Ok((total, params))
}

/// The longest run of splats whose pairs fit in `pair_cap`, from the scanned counts: how many
/// splats and how many pairs.
fn chunk_that_fits(
    work: &mut Work,
    buffers: &FrameBuffers,
    len: u32,
    pair_cap: u32,
) -> Result<(u32, u32), SceneError> {
    let offsets = work.read(&[(&buffers.counts, u64::from(len) * 4)], |bytes| {
        u32s(bytes[0])
    })??;
    // offsets[k] pairs come before splat k, and offsets[0] = 0 fits, so k ≥ 1 splats fit; a
    // single splat never has more pairs than a band has tiles, which is below the cap.
    let fits = offsets.partition_point(|&o| o <= pair_cap);
    let take = fits.saturating_sub(1).max(1);
    let pairs = offsets.get(take).copied().unwrap_or(pair_cap);
    Ok((take as u32, pairs))
}

/// Emits the pairs of `take` splats and sorts them by tile; returns the sorted pairs.
fn bin_chunk(
    work: &mut Work,
    plan: &Plan,
    band: &Band,
    buffers: &FrameBuffers,
    count_params: [u32; 8],
    take: u32,
    pairs: u32,
) -> Result<Pairs, SceneError> {
    let bytes = u64::from(pairs) * 4;
    let emitted = Pairs {
        keys: work.buffer("pair tiles", 0, bytes, Use::Storage)?,
        values: work.buffer("pair splats", 0, bytes, Use::Storage)?,
    };
    let spare = Pairs {
        keys: work.buffer("pair tiles", 1, bytes, Use::Storage)?,
        values: work.buffer("pair splats", 1, bytes, Use::Storage)?,
    };
    let grid = work.gpu.grid(take.div_ceil(GROUP))?;
    let mut params = count_params;
    params[1] = take;
    params[6] = grid.x;
    let kernels = work.kernels;
    work.dispatch(
        &kernels.emit,
        &params,
        &[
            &buffers.order,
            &buffers.rects,
            &buffers.counts,
            &emitted.keys,
            &emitted.values,
        ],
        grid,
    );
    let tiles = band.tiles(plan);
    let sorted = radix_sort(work, emitted, spare, pairs, bits_for(tiles - 1))?;

    work.clear(&buffers.ranges, u64::from(tiles) * 8);
    let grid = work.gpu.grid(pairs.div_ceil(GROUP))?;
    params[5] = pairs;
    params[6] = grid.x;
    work.dispatch(
        &kernels.ranges,
        &params,
        &[&sorted.keys, &buffers.ranges],
        grid,
    );
    Ok(sorted)
}

/// Blends one chunk of sorted pairs into the band's state: feature groups first (they replay the
/// transmittance the colour pass is about to advance), then colour and depth.
fn blend_chunk(
    work: &mut Work,
    plan: &Plan,
    band: &Band,
    buffers: &FrameBuffers,
    sorted: &Pairs,
    first_chunk: bool,
    footprint: Footprint,
) -> Result<(), SceneError> {
    let grid = super::device::Grid {
        x: plan.tiles_x,
        y: band.rows,
    };
    let kernels = work.kernels;
    let params = |group: u32| {
        [
            plan.width,
            band.y0,
            band.height,
            plan.tiles_x,
            u32::from(first_chunk),
            group,
            plan.groups,
            footprint_code(footprint),
        ]
    };
    if let Some(features) = &buffers.features {
        for (g, group) in buffers.feature_groups.iter().enumerate() {
            work.dispatch(
                &kernels.blend_features,
                &params(g as u32),
                &[
                    &buffers.splats,
                    &sorted.values,
                    &buffers.ranges,
                    &buffers.transmittance,
                    group,
                    features,
                ],
                grid,
            );
        }
    }
    work.dispatch(
        &kernels.blend_color,
        &params(0),
        &[
            &buffers.splats,
            &sorted.values,
            &buffers.ranges,
            &buffers.transmittance,
            &buffers.color,
        ],
        grid,
    );
    Ok(())
}

/// Reads the band's state back into its rows of `image`.
fn read_band(
    work: &mut Work,
    plan: &Plan,
    band: &Band,
    buffers: &FrameBuffers,
    options: &RenderOptions,
    image: &mut Image,
) -> Result<(), SceneError> {
    let pixels = band.pixels(plan);
    let groups = plan.groups as usize;
    let mut sources = vec![
        (&buffers.transmittance, pixels * 4),
        (&buffers.color, pixels * 16),
    ];
    if let Some(features) = &buffers.features {
        sources.push((features, pixels * FEATURE_GROUP_BYTES * groups as u64));
    }
    let offset = band.y0 as usize * plan.width as usize;
    let end = offset + pixels as usize;
    work.read(&sources, |bytes| {
        // Straight from the mapped read-back buffer (no copy), in parallel: at 1080p the band's
        // state is about 41 MB, and finishing it on one thread cost most of a frame on a GPU.
        let transmittance = floats(bytes[0])?;
        let color = floats(bytes[1])?;
        let [r, g, b] = options.background;
        image.rgb[offset * 3..end * 3]
            .par_chunks_mut(3 * FINISH_CHUNK)
            .zip(image.alpha[offset..end].par_chunks_mut(FINISH_CHUNK))
            .zip(image.depth[offset..end].par_chunks_mut(FINISH_CHUNK))
            .zip(image.expected_depth[offset..end].par_chunks_mut(FINISH_CHUNK))
            .zip(transmittance.par_chunks(FINISH_CHUNK))
            .zip(color.par_chunks(4 * FINISH_CHUNK))
            .for_each(|(((((rgb, alpha), depth), expected), t), c)| {
                for (p, (&t, c)) in t.iter().zip(c.chunks_exact(4)).enumerate() {
                    // A negative transmittance marks a pixel that stopped; its value is the magnitude.
                    let t = t.abs();
                    let a = 1.0 - t;
                    rgb[p * 3..p * 3 + 3].copy_from_slice(&[
                        c[0] + t * r,
                        c[1] + t * g,
                        c[2] + t * b,
                    ]);
                    alpha[p] = a;
                    depth[p] = c[3];
                    expected[p] = if a > 0.0 { c[3] / a } else { 0.0 };
                }
            });
        if let (Some(out), Some(state)) = (image.features.as_mut(), bytes.get(2)) {
            let state = floats(state)?;
            let channels = plan.channels;
            out.values[offset * channels..end * channels]
                .par_chunks_mut(channels * FINISH_CHUNK)
                .zip(state.par_chunks(4 * groups * FINISH_CHUNK))
                .for_each(|(out, state)| {
                    for (pixel, state) in out
                        .chunks_exact_mut(channels)
                        .zip(state.chunks_exact(4 * groups))
                    {
                        pixel.copy_from_slice(&state[..channels]);
                    }
                });
        }
        Ok(())
    })?
}

/// The image nothing has been drawn on: every pixel shows the background.
fn background(plan: &Plan, options: &RenderOptions) -> Image {
    let pixels = plan.width as usize * plan.height as usize;
    Image {
        width: plan.width,
        height: plan.height,
        rgb: options.background.repeat(pixels),
        alpha: vec![0.0; pixels],
        depth: vec![0.0; pixels],
        expected_depth: vec![0.0; pixels],
        features: (plan.channels > 0).then(|| FeatureImage {
            channels: plan.channels,
            values: vec![0.0; pixels * plan.channels],
        }),
    }
}

/// The canonical layout, 14 floats a Gaussian. A Gaussian whose feature vector is not finite is
/// skipped (as the forward model says, whether or not features are rendered): its position is
/// made NaN, which the projection rejects.
fn pack_parameters(set: &GaussianSet) -> Vec<f32> {
    let mut packed = set.to_canonical();
    if let Some(block) = set.features() {
        let width = block.width();
        for (i, row) in block.values().chunks_exact(width).enumerate() {
            if !row.iter().all(|v| v.is_finite()) {
                packed[i * PARAMS as usize] = f32::NAN;
            }
        }
    }
    packed
}

/// Channels `4g..4g + 4` of every feature vector (zero past the width), 4 floats a Gaussian.
fn pack_feature_group(width: usize, values: &[f32], g: usize) -> Vec<f32> {
    let lo = 4 * g;
    let hi = (lo + 4).min(width);
    let mut group = Vec::with_capacity(values.len() / width * 4);
    for row in values.chunks_exact(width) {
        let taken = &row[lo..hi];
        group.extend_from_slice(taken);
        group.extend(std::iter::repeat_n(0.0, 4 - taken.len()));
    }
    group
}

/// The `Camera` uniform of `project.wgsl`.
fn camera_uniform(
    camera: &Camera,
    options: &RenderOptions,
    plan: &Plan,
    n: u32,
    groups_x: u32,
    skipped_key: u32,
) -> [u32; 28] {
    let pose = camera.world_to_camera();
    let (m, t) = (pose.matrix3, pose.translation);
    let k = camera.intrinsics();
    let tan = k.tan_half_fov();
    let floats = [
        [m.x_axis.x, m.y_axis.x, m.z_axis.x, t.x],
        [m.x_axis.y, m.y_axis.y, m.z_axis.y, t.y],
        [m.x_axis.z, m.y_axis.z, m.z_axis.z, t.z],
        [k.fx, k.fy, k.cx, k.cy],
        [
            FOV_CLAMP * tan.x,
            FOV_CLAMP * tan.y,
            options.near,
            options.far,
        ],
    ];
    let mut words = [0u32; 28];
    for (word, value) in words.iter_mut().zip(floats.iter().flatten()) {
        *word = value.to_bits();
    }
    words[20..28].copy_from_slice(&[
        plan.width,
        plan.height,
        n,
        groups_x,
        options.near.to_bits(),
        skipped_key,
        plan.tiles_x,
        footprint_code(options.footprint),
    ]);
    words
}

fn floats(bytes: &[u8]) -> Result<&[f32], SceneError> {
    bytemuck::try_cast_slice(bytes)
        .map_err(|e| SceneError::Gpu(format!("read-back of {} bytes: {e}", bytes.len())))
}

fn u32s(bytes: &[u8]) -> Result<Vec<u32>, SceneError> {
    bytemuck::try_cast_slice(bytes)
        .map(<[u32]>::to_vec)
        .map_err(|e| SceneError::Gpu(format!("read-back of {} bytes: {e}", bytes.len())))
}

fn first_u32(bytes: &[u8]) -> Result<u32, SceneError> {
    u32s(bytes)?
        .first()
        .copied()
        .ok_or_else(|| SceneError::Gpu("empty read-back".to_owned()))
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIB: u64 = 1 << 20;

    fn bands(plan: &Plan) -> Vec<(u32, u32)> {
        Band::all(plan).map(|b| (b.y0, b.height)).collect()
    }

    #[test]
    fn ordinary_frames_are_one_band() {
        let plan = Plan::new(1920, 1080, 0, 128 * MIB, 65535).unwrap();
        assert_eq!(bands(&plan), [(0, 1080)]);
        assert_eq!(plan.pair_cap, 32 << 20);
    }

    #[test]
    fn a_4096_square_frame_on_128_mib_buffers_takes_three_bands() {
        // 4096 × 16 pixels × 20 bytes = 1.25 MiB a tile row: 102 rows fit in 128 MiB.
        let plan = Plan::new(4096, 4096, 0, 128 * MIB, 65535).unwrap();
        assert_eq!(bands(&plan), [(0, 1632), (1632, 1632), (3264, 832)]);
        // Feature groups make rows heavier, so bands thinner.
        let plan = Plan::new(4096, 4096, 64, 128 * MIB, 65535).unwrap();
        assert_eq!(plan.groups, 16);
        assert_eq!(bands(&plan).len(), 37);
    }

    #[test]
    fn a_row_of_tiles_that_cannot_fit_is_an_error() {
        assert!(Plan::new(4096, 16, 0, MIB, 65535).is_err());
        assert!(Plan::new(65535 * 16 + 1, 16, 0, u64::MAX, 65535).is_err());
    }

    #[test]
    fn feature_groups_hold_four_channels_zero_padded() {
        let values = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0];
        assert_eq!(
            pack_feature_group(5, &values, 0),
            [1.0, 2.0, 3.0, 4.0, 6.0, 7.0, 8.0, 9.0]
        );
        assert_eq!(
            pack_feature_group(5, &values, 1),
            [5.0, 0.0, 0.0, 0.0, 10.0, 0.0, 0.0, 0.0]
        );
    }
}
