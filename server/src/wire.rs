//! Gaussian sets on the wire: JSON, the packed binary format of `docs/api.md`, and the packed
//! little-endian arrays of the gRPC messages, in f32 or f16.

use c4g_proto::v1 as pb;
use c4g_renderer::GaussianSet;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

/// Numbers in a packed payload.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// 32-bit floats.
    #[default]
    F32,
    /// 16-bit floats: half the bytes, about three significant digits.
    F16,
}

impl Precision {
    fn code(self) -> u8 {
        match self {
            Precision::F32 => 0,
            Precision::F16 => 1,
        }
    }
}

impl From<pb::Precision> for Precision {
    fn from(p: pb::Precision) -> Self {
        match p {
            pb::Precision::F16 => Precision::F16,
            pb::Precision::F32 | pb::Precision::Unspecified => Precision::F32,
        }
    }
}

/// Magic bytes of the binary format.
pub const BINARY_MAGIC: &[u8; 4] = b"C4GS";
/// Its version.
pub const BINARY_VERSION: u16 = 1;

fn push(out: &mut Vec<u8>, values: impl Iterator<Item = f32>, precision: Precision) {
    match precision {
        Precision::F32 => values.for_each(|v| out.extend_from_slice(&v.to_le_bytes())),
        Precision::F16 => {
            values.for_each(|v| out.extend_from_slice(&half::f16::from_f32(v).to_le_bytes()))
        }
    }
}

fn packed(values: impl Iterator<Item = f32>, precision: Precision) -> Vec<u8> {
    let mut out = Vec::new();
    push(&mut out, values, precision);
    out
}

/// The binary format: a header, then per frame its time and the five arrays.
pub fn binary(frames: &[(f64, GaussianSet)], precision: Precision) -> Vec<u8> {
    let count = frames.first().map_or(0, |(_, s)| s.len());
    let mut out = Vec::new();
    out.extend_from_slice(BINARY_MAGIC);
    out.extend_from_slice(&BINARY_VERSION.to_le_bytes());
    out.push(precision.code());
    out.push(0);
    out.extend_from_slice(&(frames.len() as u32).to_le_bytes());
    out.extend_from_slice(&(count as u32).to_le_bytes());
    for (t, set) in frames {
        out.extend_from_slice(&t.to_le_bytes());
        push(
            &mut out,
            set.positions().iter().flatten().copied(),
            precision,
        );
        push(&mut out, set.scales().iter().flatten().copied(), precision);
        push(
            &mut out,
            set.rotations().iter().flatten().copied(),
            precision,
        );
        push(&mut out, set.opacities().iter().copied(), precision);
        push(&mut out, set.colors().iter().flatten().copied(), precision);
    }
    out
}

/// The JSON form.
pub fn json(frames: &[(f64, GaussianSet)]) -> Value {
    let frames: Vec<Value> = frames
        .iter()
        .map(|(t, set)| {
            json!({
                "t": t,
                "count": set.len(),
                "means": set.positions(),
                "scales": set.scales(),
                "rotations": set.rotations(),
                "opacities": set.opacities(),
                "colors": set.colors(),
            })
        })
        .collect();
    json!({ "frames": frames })
}

/// One set as the gRPC message.
pub fn proto(set: &GaussianSet, precision: Precision) -> pb::GaussianSet {
    pb::GaussianSet {
        count: set.len() as u32,
        precision: match precision {
            Precision::F32 => pb::Precision::F32,
            Precision::F16 => pb::Precision::F16,
        } as i32,
        means: packed(set.positions().iter().flatten().copied(), precision),
        scales: packed(set.scales().iter().flatten().copied(), precision),
        rotations: packed(set.rotations().iter().flatten().copied(), precision),
        opacities: packed(set.opacities().iter().copied(), precision),
        colors: packed(set.colors().iter().flatten().copied(), precision),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use c4g_renderer::Gaussian;
    use glam::{Quat, Vec3};

    fn set() -> GaussianSet {
        GaussianSet::from_gaussians([Gaussian {
            position: Vec3::new(1.0, -2.0, 3.5),
            scale: Vec3::new(0.1, 0.2, 0.3),
            rotation: Quat::IDENTITY,
            opacity: 0.75,
            color: Vec3::new(0.25, 0.5, 1.0),
        }])
    }

    #[test]
    fn binary_layout_is_as_documented() {
        let bytes = binary(&[(0.5, set())], Precision::F32);
        assert_eq!(&bytes[..4], b"C4GS");
        assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), 1);
        assert_eq!((bytes[6], bytes[7]), (0, 0));
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 1);
        assert_eq!(u32::from_le_bytes(bytes[12..16].try_into().unwrap()), 1);
        assert_eq!(f64::from_le_bytes(bytes[16..24].try_into().unwrap()), 0.5);
        let floats: Vec<f32> = bytes[24..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(
            floats,
            [
                1.0, -2.0, 3.5, 0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 0.75, 0.25, 0.5, 1.0
            ]
        );
        let half = binary(&[(0.5, set())], Precision::F16);
        assert_eq!(half.len(), 24 + 14 * 2);
        assert_eq!(half[6], 1);
    }
}
