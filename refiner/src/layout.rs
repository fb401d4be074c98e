//! C4G's refinement layout: keyframes, the rendered frames' padding, and temporal positions.
//!
//! In C4G's own pipeline (its DiffSynth-Studio fork) a run is `K` keyframes followed by the
//! rendered frames padded to the package's `4k + 1` by repeating the last one. Each latent frame
//! carries an explicit temporal RoPE index: a keyframe its source-frame index plus 500, a rendered
//! latent frame its latent index 0, 1, 2, ... C4G trained on windows of 23 source frames, rendering
//! all 23 and taking every second one as a keyframe, so a keyframe's source index counts frames of
//! the rendered sequence: [`source_indices`] recovers it from times.

use crate::package::KeyframeLayout;
use crate::{RefinerError, Result};

/// A context frame conditioning a run in C4G's layout.
#[derive(Debug, Clone, PartialEq)]
pub struct Keyframe {
    /// `[H, W, 3]` RGB in [0, 1], row-major.
    pub frame: Vec<f32>,
    /// Its index in the rendered sequence's frame grid (may lie outside the rendered frames).
    pub source_index: i64,
}

/// Each keyframe's source-frame index: its time on the rendered frames' grid, counted from the
/// first rendered frame, `round((t_key − t_0) / Δ)`.
///
/// `Δ` is the rendered frames' mean spacing. Where the rendered frames do not advance in time (one
/// frame, or "bullet time" at one instant) there is no grid; then `Δ` is half the keyframes' mean
/// spacing, C4G's training ratio (a keyframe every second source frame), and 1 with a single
/// keyframe.
pub fn source_indices(key_times: &[f64], rendered_times: &[f64]) -> Vec<i64> {
    let mean_spacing = |times: &[f64]| match times {
        [first, .., last] if last > first => Some((last - first) / (times.len() - 1) as f64),
        _ => None,
    };
    let step = mean_spacing(rendered_times)
        .or_else(|| mean_spacing(key_times).map(|s| s / 2.0))
        .unwrap_or(1.0);
    let origin = rendered_times.first().copied().unwrap_or(0.0);
    key_times
        .iter()
        .map(|t| ((t - origin) / step).round() as i64)
        .collect()
}

/// Temporal positions of a run's latent frames: `offset + index` per keyframe, then `0..R`.
/// A position outside the transformer's RoPE table is an error naming the keyframe.
pub fn positions(
    layout: &KeyframeLayout,
    keyframes: &[Keyframe],
    rendered_latent_frames: usize,
) -> Result<Vec<i64>> {
    let mut out = Vec::with_capacity(keyframes.len() + rendered_latent_frames);
    for (i, k) in keyframes.iter().enumerate() {
        let p = layout
            .keyframe_position_offset
            .saturating_add(k.source_index);
        if !(0..layout.rope_positions).contains(&p) {
            return Err(RefinerError::InvalidRequest(format!(
                "keyframe {i} sits at source frame {} of the rendered sequence: the model's positions reach frames {}..={} (render a path closer to the keyframes' times)",
                k.source_index,
                -layout.keyframe_position_offset,
                layout.rope_positions - 1 - layout.keyframe_position_offset
            )));
        }
        out.push(p);
    }
    out.extend(0..rendered_latent_frames as i64);
    Ok(out)
}

/// The rendered frames padded to `count` by repeating the last; an error for none or too many.
pub fn pad_rendered(frames: &[Vec<f32>], count: usize) -> Result<Vec<Vec<f32>>> {
    let Some(last) = frames.last().filter(|_| frames.len() <= count) else {
        return Err(RefinerError::InvalidRequest(format!(
            "{} rendered frames given; this package refines 1 to {count}",
            frames.len()
        )));
    };
    let mut out = frames.to_vec();
    out.resize(count, last.clone());
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::package::LayoutSampler;

    fn layout() -> KeyframeLayout {
        KeyframeLayout {
            keyframes: 2,
            keyframe_position_offset: 500,
            rope_positions: 1024,
            sampler: LayoutSampler {
                steps: 50,
                shift: 5.0,
                guidance_scale: 5.0,
            },
        }
    }

    fn key(source_index: i64) -> Keyframe {
        Keyframe {
            frame: vec![],
            source_index,
        }
    }

    #[test]
    fn indices_count_rendered_frames_from_the_first() {
        // C4G's training window: 23 frames rendered, keyframes every second frame.
        let rendered: Vec<f64> = (0..23).map(|i| i as f64 / 10.0).collect();
        let keys: Vec<f64> = (0..12).map(|i| 2.0 * i as f64 / 10.0).collect();
        let expected: Vec<i64> = (0..12).map(|i| 2 * i).collect();
        assert_eq!(source_indices(&keys, &rendered), expected);
        // A path that starts later puts earlier keyframes at negative indices.
        assert_eq!(source_indices(&[0.0, 1.0], &[0.5, 0.75, 1.0]), vec![-2, 2]);
    }

    #[test]
    fn without_a_rendered_grid_keyframes_are_two_frames_apart() {
        assert_eq!(source_indices(&[0.0, 0.4, 0.8], &[0.4; 5]), vec![-2, 0, 2]);
        assert_eq!(source_indices(&[0.3], &[0.3]), vec![0]);
    }

    #[test]
    fn positions_are_offset_keyframes_then_latent_indices() {
        let p = positions(&layout(), &[key(0), key(4)], 3).unwrap();
        assert_eq!(p, vec![500, 504, 0, 1, 2]);
        let err = positions(&layout(), &[key(0), key(524)], 3).unwrap_err();
        assert!(err.to_string().contains("keyframe 1"), "{err}");
        assert!(positions(&layout(), &[key(-501), key(0)], 3).is_err());
        assert_eq!(
            positions(&layout(), &[key(-500), key(523)], 0).unwrap(),
            vec![0, 1023]
        );
    }

    #[test]
    fn rendered_frames_are_padded_with_the_last() {
        let frames = vec![vec![0.0], vec![1.0]];
        assert_eq!(
            pad_rendered(&frames, 5).unwrap(),
            vec![vec![0.0], vec![1.0], vec![1.0], vec![1.0], vec![1.0]]
        );
        assert!(pad_rendered(&frames, 1).is_err());
        assert!(pad_rendered(&[], 5).is_err());
    }
}
