//! The optimiser's parametrisation of a scene, and gradients in the same layout.
//!
//! An optimiser steps unconstrained numbers; the canonical set's values are constrained (scales
//! ≥ 0, opacity in [0, 1], rotations of unit norm). So each Gaussian is stored as 3DGS stores it:
//! position as is, `log s` per scale axis, the quaternion unnormalised (the renderer normalises
//! it, and its gradient goes through the normalisation), opacity as its logit, colour as is. The
//! values are f64 (the optimiser's state; renders read them rounded to f32), so that the round
//! trip canonical → parameters → canonical is exact: `exp(ln s)` and `sigmoid(logit o)` in f64 are
//! within far less than half an f32 ulp of `s` and `o`, and rounding gives them back. The
//! exceptions are the constraints' edges, which have no finite parameter: a zero scale is stored as
//! [`LOG_SCALE_MIN`] and an opacity of 0 or 1 as ∓[`LOGIT_LIMIT`] (which round back to ~1e-13 and
//! exactly 1). Rotations are written back as stored, not normalised (the canonical layout allows
//! it; [`Params::normalize_rotations`] keeps their norm at 1 between steps).
//!
//! [`Params`] is one flat column per [`Group`]; a [`GaussianGradients`] becomes a `Params` of the
//! same layout ([`Params::from_gradients`]), which is what [`crate::Adam`] steps with.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use c4g_renderer::GaussianGradients;
use c4g_scene::{GaussianSet, SceneError};

/// The log scale a zero scale is stored as (`e^-30 ≈ 1e-13`: no pixel tells it from zero).
pub const LOG_SCALE_MIN: f64 = -30.0;
/// The logit an opacity of exactly 0 or 1 is stored as (negated for 0).
pub const LOGIT_LIMIT: f64 = 30.0;

/// A kind of parameter: its own learning rate, its own Adam moments.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Group {
    /// Centres, 3 a Gaussian.
    Position,
    /// `ln` of the scales, 3 a Gaussian.
    LogScale,
    /// The stored quaternion `w, x, y, z`, 4 a Gaussian.
    Rotation,
    /// `logit(opacity)`, 1 a Gaussian.
    OpacityLogit,
    /// RGB, 3 a Gaussian.
    Color,
}

impl Group {
    /// Every group, in the canonical layout's order.
    pub const ALL: [Group; 5] = [
        Group::Position,
        Group::LogScale,
        Group::Rotation,
        Group::OpacityLogit,
        Group::Color,
    ];

    /// Values a Gaussian.
    pub fn width(self) -> usize {
        match self {
            Group::Position | Group::LogScale | Group::Color => 3,
            Group::Rotation => 4,
            Group::OpacityLogit => 1,
        }
    }

    /// Position in [`Group::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }
}

/// Values per Gaussian, all groups: the canonical layout's 14.
pub const ROW: usize = 14;

/// A scene (or its gradient) in the optimiser's parametrisation: one flat column per group,
/// Gaussian `i` at `[i · width, (i + 1) · width)`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Params {
    columns: [Vec<f64>; 5],
}

fn logit(o: f64) -> f64 {
    (o / (1.0 - o)).ln().clamp(-LOGIT_LIMIT, LOGIT_LIMIT)
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

impl Params {
    /// All zero, for `n` Gaussians (a gradient's or a moment's starting value).
    pub fn zeros(n: usize) -> Self {
        Self {
            columns: Group::ALL.map(|g| vec![0.0; n * g.width()]),
        }
    }

    /// The parameters of `set`. Refuses values that are not finite, negative scales and
    /// opacities outside [0, 1].
    pub fn from_set(set: &GaussianSet) -> Result<Self, SceneError> {
        let mut out = Self::zeros(0);
        for i in 0..set.len() {
            let (p, s, q, o, c) = (
                set.positions()[i],
                set.scales()[i],
                set.rotations()[i],
                set.opacities()[i],
                set.colors()[i],
            );
            let finite = p
                .iter()
                .chain(&s)
                .chain(&q)
                .chain(&c)
                .all(|v| v.is_finite());
            if !finite || s.iter().any(|&v| v < 0.0) || !(0.0..=1.0).contains(&o) {
                return Err(SceneError::InvalidGaussian {
                    index: i,
                    reason: "parameters must be finite, scales ≥ 0 and opacity in [0, 1]".into(),
                });
            }
            let mut row = [0.0; ROW];
            row[0..3].copy_from_slice(&p.map(f64::from));
            row[3..6].copy_from_slice(&s.map(|v| f64::from(v).ln().max(LOG_SCALE_MIN)));
            row[6..10].copy_from_slice(&q.map(f64::from));
            row[10] = logit(f64::from(o));
            row[11..14].copy_from_slice(&c.map(f64::from));
            out.push(&row);
        }
        Ok(out)
    }

    /// The canonical set these parameters describe (activated, rounded to f32; rotations as
    /// stored).
    pub fn to_set(&self) -> GaussianSet {
        let n = self.len();
        let mut cols = (
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        );
        for i in 0..n {
            let r = self.row(i);
            cols.0.push([r[0], r[1], r[2]].map(|v| v as f32));
            cols.1.push([r[3], r[4], r[5]].map(|v| v.exp() as f32));
            cols.2.push([r[6], r[7], r[8], r[9]].map(|v| v as f32));
            cols.3.push(sigmoid(r[10]) as f32);
            cols.4.push([r[11], r[12], r[13]].map(|v| v as f32));
        }
        // Every column has n entries, so this cannot fail.
        GaussianSet::new(cols.0, cols.1, cols.2, cols.3, cols.4).unwrap_or_default()
    }

    /// A gradient from the renderer in this layout.
    pub fn from_gradients(g: &GaussianGradients) -> Self {
        let mut out = Self::zeros(0);
        for i in 0..g.len() {
            out.push(&g.row(i).map(f64::from));
        }
        out
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.columns[0].len() / 3
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// One group's column.
    pub fn group(&self, g: Group) -> &[f64] {
        &self.columns[g.index()]
    }

    /// One group's column, to write.
    pub fn group_mut(&mut self, g: Group) -> &mut [f64] {
        &mut self.columns[g.index()]
    }

    /// Gaussian `i`'s 14 values in the canonical layout's order.
    pub fn row(&self, i: usize) -> [f64; ROW] {
        let mut out = [0.0; ROW];
        let mut at = 0;
        for g in Group::ALL {
            let w = g.width();
            out[at..at + w].copy_from_slice(&self.columns[g.index()][i * w..(i + 1) * w]);
            at += w;
        }
        out
    }

    /// Appends a Gaussian (14 values in the canonical layout's order).
    pub fn push(&mut self, row: &[f64; ROW]) {
        let mut at = 0;
        for g in Group::ALL {
            let w = g.width();
            self.columns[g.index()].extend_from_slice(&row[at..at + w]);
            at += w;
        }
    }

    /// The Gaussians whose entry in `keep` is true, in order (`keep` has one entry per Gaussian).
    pub fn select(&self, keep: &[bool]) -> Self {
        let mut out = Self::zeros(0);
        for (i, _) in keep.iter().enumerate().filter(|(_, k)| **k) {
            out.push(&self.row(i));
        }
        out
    }

    /// Rescales every stored quaternion to unit norm (a zero one is left alone): the rendered set
    /// does not change, and the norms stay where the gradient's `1/|q|` scale is 1.
    pub fn normalize_rotations(&mut self) {
        self.columns[Group::Rotation.index()]
            .par_chunks_exact_mut(4)
            .with_min_len(1 << 12)
            .for_each(|q| {
                let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
                if n > 0.0 {
                    q.iter_mut().for_each(|v| *v /= n);
                }
            });
    }

    /// The L2 norm over every value of every group.
    pub fn norm(&self) -> f64 {
        self.columns
            .iter()
            .flatten()
            .map(|v| v * v)
            .sum::<f64>()
            .sqrt()
    }

    /// Gradient clipping: scales every value so that the norm is at most `max_norm`; returns the
    /// norm before.
    pub fn clip_norm(&mut self, max_norm: f64) -> f64 {
        let norm = self.norm();
        if norm > max_norm && norm > 0.0 {
            let k = max_norm / norm;
            self.columns.iter_mut().flatten().for_each(|v| *v *= k);
        }
        norm
    }

    /// Every value of every group, group by group.
    pub fn values(&self) -> impl Iterator<Item = &f64> {
        self.columns.iter().flatten()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(n: usize, seed: u64) -> GaussianSet {
        let mut s = seed;
        let mut unit = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut cols = (vec![], vec![], vec![], vec![], vec![]);
        for _ in 0..n {
            cols.0.push([unit() - 0.5, unit() * 10.0, -unit()]);
            // Scales across many decades.
            cols.1.push([0; 3].map(|_| 10f32.powf(unit() * 8.0 - 6.0)));
            let q = [0; 4].map(|_| unit() - 0.5);
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            cols.2.push(q.map(|v| v / n));
            cols.3.push(unit());
            cols.4.push([unit(), unit(), unit()]);
        }
        GaussianSet::new(cols.0, cols.1, cols.2, cols.3, cols.4).unwrap()
    }

    #[test]
    fn the_round_trip_to_the_canonical_set_is_exact() {
        let original = set(20_000, 3);
        let back = Params::from_set(&original).unwrap().to_set();
        assert_eq!(back, original);
    }

    #[test]
    fn the_edges_of_the_constraints_map_to_finite_parameters() {
        let edge = GaussianSet::new(
            vec![[0.0; 3]; 2],
            vec![[0.0, 1.0, 2.0]; 2],
            vec![[0.0, 0.0, 0.0, 2.0]; 2],
            vec![0.0, 1.0],
            vec![[0.0; 3]; 2],
        )
        .unwrap();
        let p = Params::from_set(&edge).unwrap();
        assert!(p.values().all(|v| v.is_finite()));
        let back = p.to_set();
        assert_eq!(
            back.opacities()[1],
            1.0,
            "an opacity of 1 comes back exactly"
        );
        assert!(back.opacities()[0] < 1e-12 && back.scales()[0][0] < 1e-12);
        assert_eq!(
            back.rotations()[0],
            [0.0, 0.0, 0.0, 2.0],
            "rotations as stored"
        );
    }

    #[test]
    fn invalid_sets_are_refused() {
        for (s, o) in [
            ([-1.0, 1.0, 1.0], 0.5),
            ([1.0; 3], 1.5),
            ([f32::NAN; 3], 0.5),
        ] {
            let bad = GaussianSet::new(
                vec![[0.0; 3]],
                vec![s],
                vec![[1.0, 0.0, 0.0, 0.0]],
                vec![o],
                vec![[0.0; 3]],
            )
            .unwrap();
            assert!(Params::from_set(&bad).is_err());
        }
    }

    #[test]
    fn clipping_bounds_the_norm_and_keeps_the_direction() {
        let mut g = Params::from_set(&set(10, 4)).unwrap();
        let before = g.clone();
        let norm = g.clip_norm(0.5);
        assert!((g.norm() - 0.5).abs() < 1e-12);
        for (a, b) in g.values().zip(before.values()) {
            assert!((a - b * 0.5 / norm).abs() < 1e-12);
        }
        let mut small = before.clone();
        small.clip_norm(1e9);
        assert_eq!(small, before, "under the limit nothing changes");
    }

    #[test]
    fn rows_select_and_normalise() {
        let mut p = Params::from_set(&set(5, 5)).unwrap();
        let picked = p.select(&[true, false, true, false, false]);
        assert_eq!(picked.len(), 2);
        assert_eq!(picked.row(1), p.row(2));
        p.group_mut(Group::Rotation)[0..4].copy_from_slice(&[2.0, 0.0, 0.0, 0.0]);
        p.normalize_rotations();
        assert_eq!(&p.group(Group::Rotation)[0..4], &[1.0, 0.0, 0.0, 0.0]);
    }
}
