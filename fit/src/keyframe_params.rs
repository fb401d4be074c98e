//! Every keyframe set of a fitted scene in the optimiser's parametrisation, as one
//! [`c4g_optim::Params`] of K·N rows.
//!
//! One `Params` (not one per keyframe) so that one [`c4g_optim::Adam`] steps every keyframe with
//! one learning rate per group and one step count, and so that gradients, clipping and the prior
//! are plain operations on one column per group. The rows are **Gaussian-major** (Gaussian `i` at
//! keyframe `k` is row `i·K + k`): a Gaussian's K rows are contiguous, so the optimiser's
//! `select` (drop a Gaussian: its K rows) and `extend` (new Gaussians: K fresh rows each, at the
//! end) keep every keyframe holding the same Gaussians in the same order.

use c4g_optim::{Group, Params};
use c4g_scene::GaussianSet;

use crate::error::FitError;

/// K keyframe sets of N Gaussians in the optimiser's parametrisation.
#[derive(Debug, Clone, PartialEq)]
pub struct KeyframeParams {
    keyframes: usize,
    /// Row `i·K + k`: Gaussian `i` at keyframe `k`.
    pub params: Params,
}

impl KeyframeParams {
    /// The parameters of `sets` (one per keyframe, of one length).
    pub fn from_sets(sets: &[GaussianSet]) -> Result<Self, FitError> {
        let k = sets.len();
        let n = sets.first().map_or(0, GaussianSet::len);
        if k == 0 || sets.iter().any(|s| s.len() != n) {
            return Err(FitError::Invalid(
                "keyframe parameters need keyframes of one length".into(),
            ));
        }
        let per_key = sets
            .iter()
            .map(Params::from_set)
            .collect::<Result<Vec<_>, _>>()?;
        let mut params = Params::zeros(0);
        for i in 0..n {
            for p in &per_key {
                params.push(&p.row(i));
            }
        }
        Ok(Self {
            keyframes: k,
            params,
        })
    }

    /// Parameters already in this layout (`rows.len()` a multiple of `keyframes`, at least 1).
    pub fn from_rows(params: Params, keyframes: usize) -> Self {
        Self {
            keyframes: keyframes.max(1),
            params,
        }
    }

    /// Keyframes (K).
    pub fn keyframes(&self) -> usize {
        self.keyframes
    }

    /// Gaussians per keyframe (N).
    pub fn gaussians(&self) -> usize {
        self.params.len() / self.keyframes
    }

    /// The row of Gaussian `i` at keyframe `k`.
    pub fn row_index(&self, i: usize, k: usize) -> usize {
        i * self.keyframes + k
    }

    /// Keyframe `k`'s set (activated, rounded to f32, as [`Params::to_set`]).
    pub fn set(&self, k: usize) -> GaussianSet {
        let mut rows = Params::zeros(0);
        for i in 0..self.gaussians() {
            rows.push(&self.params.row(self.row_index(i, k)));
        }
        rows.to_set()
    }

    /// Every keyframe's set, in keyframe order.
    pub fn sets(&self) -> Vec<GaussianSet> {
        (0..self.keyframes).map(|k| self.set(k)).collect()
    }

    /// Value `j` of `group` of Gaussian `i` at keyframe `k`.
    pub fn value(&self, group: Group, i: usize, k: usize, j: usize) -> f64 {
        self.params.group(group)[self.row_index(i, k) * group.width() + j]
    }

    /// The same as a mutable reference.
    pub fn value_mut(&mut self, group: Group, i: usize, k: usize, j: usize) -> &mut f64 {
        let at = self.row_index(i, k) * group.width() + j;
        &mut self.params.group_mut(group)[at]
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_round_trip_through_keyframe_parameters_is_exact() {
        let set = |x: f32| {
            GaussianSet::new(
                vec![[x, 1.0, 2.0], [0.0, x, 3.0]],
                vec![[0.1, 0.2, 0.3]; 2],
                vec![[1.0, 0.0, 0.0, 0.0]; 2],
                vec![0.25, 0.75],
                vec![[0.1, 0.5, x]; 2],
            )
            .unwrap()
        };
        let sets = vec![set(0.0), set(0.5), set(1.0)];
        let p = KeyframeParams::from_sets(&sets).unwrap();
        assert_eq!((p.keyframes(), p.gaussians()), (3, 2));
        assert_eq!(p.sets(), sets);
        assert_eq!(p.value(Group::Position, 1, 2, 1), 1.0);
    }
}
