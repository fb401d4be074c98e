//! antimatter15's `.splat`: 32 bytes a Gaussian, what its WebGL viewer (and those derived from it)
//! stream.
//!
//! Per Gaussian, little endian: position `3 × f32`, scale `3 × f32` (linear), colour and opacity
//! `4 × u8` (`round(255 · clamp(v, 0, 1))`), rotation `4 × u8` as `round(128 · q + 128)` clamped
//! to 0..=255, `w, x, y, z` of the normalised quaternion. No header: the count is the length / 32.
//! Gaussians are written largest first, by `scale_x · scale_y · scale_z · opacity` (the order the
//! viewer's converter produces, which it relies on to show something useful while loading; ties
//! keep the set's order). Gaussians with a non-finite parameter or a zero rotation are left out;
//! features are not part of the format.
//!
//! Decoding inverts the quantisation: colours and opacity come back within 1/510, rotation
//! components within about 1/128 (before normalisation), positions and scales exactly.

use std::path::Path;

use c4g_scene::{GaussianSet, SceneError};

/// Bytes per Gaussian.
pub const RECORD: usize = 32;

/// Writes `set` to a `.splat` file.
pub fn write(path: &Path, set: &GaussianSet) -> Result<(), SceneError> {
    super::write_file(path, &encode(set))
}

/// Reads a `.splat` file.
pub fn read(path: &Path) -> Result<GaussianSet, SceneError> {
    decode(&super::read_file(path)?)
}

/// The `.splat` bytes of `set`.
pub fn encode(set: &GaussianSet) -> Vec<u8> {
    let mut order: Vec<(usize, f32)> = (0..set.len())
        .filter(|&i| writable(set, i))
        .map(|i| {
            let [sx, sy, sz] = set.scales()[i];
            (i, sx * sy * sz * set.opacities()[i])
        })
        .collect();
    // Stable: equal keys keep the set's order.
    order.sort_by(|a, b| b.1.total_cmp(&a.1));

    let mut out = Vec::with_capacity(order.len() * RECORD);
    for (i, _) in order {
        for v in set.positions()[i].into_iter().chain(set.scales()[i]) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let [r, g, b] = set.colors()[i];
        out.extend([r, g, b, set.opacities()[i]].map(unit_to_byte));
        let q = set.rotations()[i];
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        out.extend(q.map(|v| (v / norm * 128.0 + 128.0).round().clamp(0.0, 255.0) as u8));
    }
    out
}

/// Parses `.splat` bytes.
pub fn decode(bytes: &[u8]) -> Result<GaussianSet, SceneError> {
    if !bytes.len().is_multiple_of(RECORD) {
        return Err(SceneError::Format {
            format: "splat",
            reason: format!(
                "{} bytes is not a whole number of {RECORD}-byte Gaussians",
                bytes.len()
            ),
        });
    }
    let n = bytes.len() / RECORD;
    let (mut positions, mut scales, mut rotations, mut opacities, mut colors) = (
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
    );
    for record in bytes.chunks_exact(RECORD) {
        let f = |k: usize| {
            let mut b = [0u8; 4];
            b.copy_from_slice(&record[k * 4..k * 4 + 4]);
            f32::from_le_bytes(b)
        };
        positions.push([f(0), f(1), f(2)]);
        scales.push([f(3), f(4), f(5)]);
        colors.push([24, 25, 26].map(|k| f32::from(record[k]) / 255.0));
        opacities.push(f32::from(record[27]) / 255.0);
        let q = [28, 29, 30, 31].map(|k| (f32::from(record[k]) - 128.0) / 128.0);
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        rotations.push(if norm > 0.0 { q.map(|v| v / norm) } else { q });
    }
    GaussianSet::new(positions, scales, rotations, opacities, colors)
}

fn writable(set: &GaussianSet, i: usize) -> bool {
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    let q = set.rotations()[i];
    finite(&set.positions()[i])
        && finite(&set.scales()[i])
        && finite(&q)
        && q.iter().any(|v| *v != 0.0)
        && set.opacities()[i].is_finite()
        && finite(&set.colors()[i])
}

fn unit_to_byte(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> GaussianSet {
        GaussianSet::new(
            vec![
                [1.0, 2.0, 3.0],
                [-1.0, 0.5, 2.0],
                [0.0, 0.0, 1.0],
                [f32::NAN, 0.0, 0.0],
            ],
            vec![
                [0.1, 0.1, 0.1],
                [1.0, 2.0, 0.5],
                [0.01, 0.02, 0.03],
                [1.0; 3],
            ],
            vec![
                [1.0, 0.0, 0.0, 0.0],
                [0.5, 0.5, -0.5, 0.5],
                [0.0, 0.6, 0.0, 0.8],
                [1.0, 0.0, 0.0, 0.0],
            ],
            vec![0.9, 0.5, 1.0, 1.0],
            vec![[1.0, 0.0, 0.5], [0.2, 0.4, 0.6], [2.0, -1.0, 0.0], [0.0; 3]],
        )
        .unwrap()
    }

    #[test]
    fn records_are_32_bytes_largest_first_without_invalid_gaussians() {
        let bytes = encode(&sample());
        assert_eq!(bytes.len(), 3 * RECORD);
        let back = decode(&bytes).unwrap();
        // Sizes · opacity: 1.0 · 0.5, 0.001 · 0.9, 6e-6 · 1.
        assert_eq!(
            back.positions(),
            &[[-1.0, 0.5, 2.0], [1.0, 2.0, 3.0], [0.0, 0.0, 1.0]]
        );
        assert_eq!(back.scales()[0], [1.0, 2.0, 0.5]);
    }

    #[test]
    fn quantised_fields_decode_within_a_step() {
        let back = decode(&encode(&sample())).unwrap();
        let step = 1.0 / 510.0 + 1e-6;
        assert_eq!(back.colors()[2], [1.0, 0.0, 0.0]); // clamped from (2, -1, 0)
        assert!((back.opacities()[0] - 0.5).abs() <= step);
        assert!((back.colors()[0][1] - 0.4).abs() <= step);
        for (got, want) in back.rotations()[0].iter().zip([0.5, 0.5, -0.5, 0.5]) {
            assert!((got - want).abs() < 1.0 / 128.0);
        }
        // Byte layout of the first record's rotation: round(q · 128 + 128).
        let bytes = encode(&sample());
        assert_eq!(&bytes[28..32], &[192, 192, 64, 192]);
        assert_eq!(&bytes[24..28], &[51, 102, 153, 128]);
    }

    #[test]
    fn a_length_that_is_not_whole_records_is_an_error() {
        let err = decode(&[0u8; 33]).unwrap_err();
        assert!(err.to_string().contains("33 bytes"), "{err}");
        assert!(decode(&[]).unwrap().is_empty());
    }
}
