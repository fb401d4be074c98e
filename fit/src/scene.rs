//! The fitted scene: a clip's 4D scene as the same N Gaussians at K keyframe times, served at any
//! time inside the keyframes' span by the engine's keyframe rules.
//!
//! The interpolation is not re-implemented here: [`FittedScene::at`] builds a
//! [`c4g_engine::KeyframeTrack`] through the keyframe sets, so a fitted scene is served exactly as
//! a keyframed decode is (positions on a cubic Hermite with Bessel tangents, rotations by slerp on
//! the short arc, scales in log space, opacity and colour linearly), and everything that serves
//! keyframed decodes serves fitted scenes. A fitted scene has no breaks: its keyframes are where
//! the fit put them, not context frames the decoder's motion may turn a corner at.

use c4g_engine::KeyframeTrack;
use c4g_scene::GaussianSet;

use crate::error::FitError;

/// A clip's scene as keyframe sets: the same Gaussians (by index) at every keyframe time.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FittedScene {
    /// Keyframe times, seconds, strictly increasing.
    pub times: Vec<f64>,
    /// One set per keyframe, all of the same length.
    pub sets: Vec<GaussianSet>,
    /// One entry per Gaussian: true when it shares one value across the keyframes (it does not
    /// move more than the fit's static tolerance).
    pub static_mask: Vec<bool>,
}

impl FittedScene {
    /// A scene through `keyframes` (times strictly increasing, finite; sets of one length); no
    /// Gaussian is marked static.
    pub fn new(keyframes: Vec<(f64, GaussianSet)>) -> Result<Self, FitError> {
        if keyframes.is_empty() {
            return Err(FitError::Invalid("a fitted scene needs a keyframe".into()));
        }
        let increasing = keyframes.windows(2).all(|w| w[0].0 < w[1].0);
        if !increasing || keyframes.iter().any(|(t, _)| !t.is_finite()) {
            return Err(FitError::Invalid(
                "keyframe times must be finite and strictly increasing".into(),
            ));
        }
        let n = keyframes[0].1.len();
        if keyframes.iter().any(|(_, s)| s.len() != n) {
            return Err(FitError::Invalid(
                "every keyframe must hold the same Gaussians".into(),
            ));
        }
        let (times, sets) = keyframes.into_iter().unzip();
        Ok(Self {
            times,
            sets,
            static_mask: vec![false; n],
        })
    }

    /// Gaussians per keyframe.
    pub fn len(&self) -> usize {
        self.sets.first().map_or(0, GaussianSet::len)
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The first and last keyframe time: where [`at`](Self::at) is defined.
    pub fn span(&self) -> Option<(f64, f64)> {
        Some((*self.times.first()?, *self.times.last()?))
    }

    /// The engine's track through the keyframes (what [`at`](Self::at) reads).
    pub fn track(&self) -> Result<KeyframeTrack, FitError> {
        let keyframes = self.times.iter().copied().zip(self.sets.clone()).collect();
        Ok(KeyframeTrack::new(keyframes)?)
    }

    /// The set at `t`: a keyframe's own set at its time, else the engine's interpolation. Fails
    /// outside [`span`](Self::span) or for a non-finite `t`.
    pub fn at(&self, t: f64) -> Result<GaussianSet, FitError> {
        Ok(self.track()?.at(t)?)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn set(n: usize, phase: f32) -> GaussianSet {
        let f = |i: usize, k: f32| ((i as f32 + 1.0) * k + phase).sin();
        GaussianSet::new(
            (0..n)
                .map(|i| [f(i, 1.0), f(i, 2.0), 2.0 + f(i, 3.0)])
                .collect(),
            (0..n).map(|i| [0.1 + 0.05 * f(i, 4.0); 3]).collect(),
            (0..n)
                .map(|i| {
                    let a = 0.5 * f(i, 5.0);
                    [a.cos(), a.sin(), 0.0, 0.0]
                })
                .collect(),
            (0..n).map(|i| 0.5 + 0.4 * f(i, 6.0)).collect(),
            (0..n).map(|i| [0.5 + 0.5 * f(i, 7.0); 3]).collect(),
        )
        .unwrap()
    }

    fn scene() -> FittedScene {
        let times = [0.0, 0.4, 1.1, 1.5];
        FittedScene::new(
            times
                .iter()
                .enumerate()
                .map(|(k, &t)| (t, set(6, k as f32 * 0.3)))
                .collect(),
        )
        .unwrap()
    }

    /// The rules are the engine's: the same sets through the engine's track give the same bits.
    #[test]
    fn at_is_the_engines_keyframe_interpolation_bit_for_bit() {
        let scene = scene();
        let track = KeyframeTrack::new(
            scene
                .times
                .iter()
                .copied()
                .zip(scene.sets.clone())
                .collect(),
        )
        .unwrap();
        for t in [0.0, 0.1, 0.39, 0.7, 1.2, 1.49, 1.5] {
            assert_eq!(scene.at(t).unwrap(), track.at(t).unwrap(), "t = {t}");
        }
    }

    #[test]
    fn at_a_keyframe_time_is_that_keyframes_set_exactly() {
        let scene = scene();
        for (t, s) in scene.times.iter().zip(&scene.sets) {
            assert_eq!(&scene.at(*t).unwrap(), s);
        }
    }

    #[test]
    fn outside_the_span_and_bad_keyframes_are_refused() {
        let scene = scene();
        assert!(scene.at(-0.1).is_err() && scene.at(f64::NAN).is_err());
        assert!(FittedScene::new(vec![]).is_err());
        assert!(FittedScene::new(vec![(1.0, set(2, 0.0)), (0.5, set(2, 0.0))]).is_err());
        assert!(FittedScene::new(vec![(0.0, set(2, 0.0)), (1.0, set(3, 0.0))]).is_err());
    }
}
