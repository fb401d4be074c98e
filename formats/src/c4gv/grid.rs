//! Values on the grid and back: quantising a set, reconstructing cells, the error bounds checked.

use c4g_scene::{GaussianSet, SceneError};

use super::*;

/// Gaussian `i` of a validated set on the grid; refuses values outside the encoder's ranges.
pub(super) fn quantise(
    set: &GaussianSet,
    i: usize,
    steps: &Steps,
    range: f64,
) -> Result<Cells, String> {
    let mut cells = [0i64; CHANNELS];
    let cell = |v: f64, step: f64| (v / step).round() as i64;
    for (k, &x) in set.positions()[i].iter().enumerate() {
        if f64::from(x).abs() > range {
            return Err(format!(
                "position {:?} is beyond C4GV's range at this position error (±{range} scene \
                 units: a million times the error)",
                set.positions()[i]
            ));
        }
        cells[k] = cell(f64::from(x), steps.position);
    }
    for (k, &s) in set.scales()[i].iter().enumerate() {
        cells[3 + k] = cell(f64::from(s.max(SCALE_FLOOR)).ln(), steps.log_scale);
    }
    let q = set.rotations()[i].map(f64::from);
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    for (k, v) in q.iter().enumerate() {
        cells[6 + k] = cell(v / norm, steps.rotation);
    }
    cells[10] = cell(f64::from(set.opacities()[i]), steps.opacity);
    for (k, &c) in set.colors()[i].iter().enumerate() {
        if c > COLOR_MAX {
            return Err(format!(
                "color {:?} is beyond C4GV's range (0 to {COLOR_MAX})",
                set.colors()[i]
            ));
        }
        cells[11 + k] = cell(f64::from(c), steps.color);
    }
    Ok(cells)
}

/// Every Gaussian of `set` on the grid, after checking it against the canonical layout.
pub(super) fn quantise_set(
    set: &GaussianSet,
    steps: &Steps,
    range: f64,
) -> Result<Vec<Cells>, SceneError> {
    set.validate()?;
    (0..set.len())
        .map(|i| {
            quantise(set, i, steps, range)
                .map_err(|reason| SceneError::InvalidGaussian { index: i, reason })
        })
        .collect()
}

/// One Gaussian's decoded values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Values {
    pub(super) position: [f32; 3],
    pub(super) scale: [f32; 3],
    pub(super) rotation: [f32; 4],
    pub(super) opacity: f32,
    pub(super) color: [f32; 3],
}

/// The values of `cells`; `None` for a rotation of zero norm (only a corrupt stream has one).
pub(super) fn reconstruct(cells: &Cells, steps: &Steps) -> Option<Values> {
    let value = |k: usize, step: f64| (cells[k] as f64 * step) as f32;
    let q: [f64; 4] = std::array::from_fn(|k| cells[6 + k] as f64 * steps.rotation);
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm == 0.0 || !norm.is_finite() {
        return None;
    }
    Some(Values {
        position: std::array::from_fn(|k| value(k, steps.position)),
        scale: std::array::from_fn(|k| (cells[3 + k] as f64 * steps.log_scale).exp() as f32),
        rotation: q.map(|v| (v / norm) as f32),
        opacity: value(10, steps.opacity),
        color: std::array::from_fn(|k| value(11 + k, steps.color)),
    })
}

/// Why Gaussian `i` of `set` is not within the bounds of `held` (its decoded values), if it
/// is not.
pub(super) fn out_of_bounds(
    set: &GaussianSet,
    i: usize,
    held: &Values,
    position_error: f64,
) -> Option<String> {
    let (p, s, q, o, c) = (
        set.positions()[i],
        set.scales()[i],
        set.rotations()[i],
        set.opacities()[i],
        set.colors()[i],
    );
    let worst = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs())
            .fold(0.0, f64::max)
    };
    let dp = worst(&p, &held.position);
    if dp > position_error {
        return Some(format!("its position moved {dp} (bound {position_error})"));
    }
    let ds = s
        .iter()
        .zip(held.scale)
        .map(|(&s, h)| scale_error(s, h))
        .fold(0.0, f64::max);
    if ds > SCALE_ERROR {
        return Some(format!(
            "its scale changed by a factor of {ds} (bound {SCALE_ERROR})"
        ));
    }
    let dq = rotation_angle(q, held.rotation);
    if dq > ROTATION_ERROR {
        return Some(format!(
            "its rotation turned {dq} rad (bound {ROTATION_ERROR})"
        ));
    }
    let d = (f64::from(o) - f64::from(held.opacity)).abs();
    if d > OPACITY_ERROR {
        return Some(format!("its opacity changed {d} (bound {OPACITY_ERROR})"));
    }
    let d = worst(&c, &held.color);
    if d > COLOR_ERROR {
        return Some(format!("its colour changed {d} (bound {COLOR_ERROR})"));
    }
    None
}

/// How far a decoded scale is from the scale it stands for: relative at or above
/// [`SCALE_FLOOR`], else absolute (then under 6e-20).
pub fn scale_error(original: f32, decoded: f32) -> f64 {
    let (a, b) = (f64::from(original), f64::from(decoded));
    if original < SCALE_FLOOR {
        (a - b).abs()
    } else {
        (b / a - 1.0).abs()
    }
}

/// The angle, in radians, of the rotation between two quaternions `[w, x, y, z]` (of any norm).
pub fn rotation_angle(a: [f32; 4], b: [f32; 4]) -> f64 {
    let norm = |q: [f32; 4]| q.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>().sqrt();
    let dot: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, y)| f64::from(x) * f64::from(y))
        .sum::<f64>()
        / (norm(a) * norm(b));
    2.0 * dot.abs().min(1.0).acos()
}
