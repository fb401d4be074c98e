//! Adaptive density control, 3DGS's: Gaussians whose projected centre the loss keeps pulling on
//! are where the scene is under-reconstructed, so they are **cloned** (small ones: a copy at the
//! same place) or **split** (large ones: two children drawn from the parent, scales divided by
//! 1.6); nearly transparent ones are **pruned**. A Gaussian **budget** caps the count: when there is
//! not room for every candidate, those pulled hardest go first (what a fixed-size scene needs).
//! Adam's state follows: new Gaussians start with zero moments, pruned ones take theirs along.
//!
//! The signal ([`DensifyStats`]) is 3DGS's: the mean, over the steps where a Gaussian was
//! visible (got a gradient), of the norm of `∂L/∂(u, v)` in NDC units (pixels times `W/2`,
//! `H/2`), against a threshold of 2e-4.

use crate::adam::Adam;
use crate::params::{Group, Params};

/// What densification does and when.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DensifyConfig {
    /// Mean NDC gradient norm above which a Gaussian is densified (3DGS: 2e-4).
    pub grad_threshold: f64,
    /// A Gaussian whose largest scale is at most this times the scene extent is cloned, a larger
    /// one split (3DGS: 0.01).
    pub clone_scale_fraction: f64,
    /// A split child's scales are its parent's divided by this (3DGS: 0.8 · 2 = 1.6).
    pub split_scale_divisor: f64,
    /// Gaussians with opacity under this are pruned (3DGS: 0.005).
    pub prune_opacity: f64,
    /// Most Gaussians after densifying.
    pub budget: usize,
}

impl Default for DensifyConfig {
    fn default() -> Self {
        Self {
            grad_threshold: 2e-4,
            clone_scale_fraction: 0.01,
            split_scale_divisor: 1.6,
            prune_opacity: 0.005,
            budget: 100_000,
        }
    }
}

/// The densification signal accumulated over steps.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DensifyStats {
    sum: Vec<f64>,
    count: Vec<u32>,
}

impl DensifyStats {
    /// Nothing accumulated, for `n` Gaussians.
    pub fn new(n: usize) -> Self {
        Self {
            sum: vec![0.0; n],
            count: vec![0; n],
        }
    }

    /// Adds one step's `∂L/∂(u, v)` (pixels, from `GaussianGradients::means2d`) of a
    /// `width × height` render; Gaussians with a zero gradient were not visible and do not count.
    pub fn accumulate(&mut self, means2d: &[[f32; 2]], width: u32, height: u32) {
        let (hw, hh) = (0.5 * f64::from(width), 0.5 * f64::from(height));
        for ((sum, count), g) in self.sum.iter_mut().zip(&mut self.count).zip(means2d) {
            if g[0] != 0.0 || g[1] != 0.0 {
                *sum += (f64::from(g[0]) * hw).hypot(f64::from(g[1]) * hh);
                *count += 1;
            }
        }
    }

    /// Gaussian `i`'s mean NDC gradient norm (0 if never visible).
    pub fn mean(&self, i: usize) -> f64 {
        if self.count[i] == 0 {
            0.0
        } else {
            self.sum[i] / f64::from(self.count[i])
        }
    }
}

/// What one densification did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DensifyReport {
    /// Gaussians cloned.
    pub cloned: usize,
    /// Gaussians split (each replaced by two).
    pub split: usize,
    /// Gaussians pruned for their opacity.
    pub pruned: usize,
    /// Gaussians after.
    pub total: usize,
}

/// Densifies and prunes `params` (and `adam`'s state with them) by `stats`, which restarts.
/// `extent` is the scene's size (3DGS: the radius of the camera centres × 1.1); `seed` draws the
/// split children.
pub fn densify(
    params: &mut Params,
    adam: &mut Adam,
    stats: &mut DensifyStats,
    config: &DensifyConfig,
    extent: f64,
    seed: u64,
) -> DensifyReport {
    let n = params.len();
    let mut candidates: Vec<usize> = (0..n)
        .filter(|&i| stats.mean(i) >= config.grad_threshold)
        .collect();
    candidates.sort_by(|&a, &b| stats.mean(b).total_cmp(&stats.mean(a)));
    // Clones and splits each add one Gaussian.
    candidates.truncate(config.budget.saturating_sub(n));
    let mut rng = Normal(seed);
    let mut keep = vec![true; n];
    let mut report = DensifyReport::default();
    let mut added = Vec::new();
    for &i in &candidates {
        let row = params.row(i);
        let largest = row[3..6].iter().fold(f64::MIN, |m, v| m.max(*v)).exp();
        if largest <= config.clone_scale_fraction * extent {
            added.push(row);
            report.cloned += 1;
            continue;
        }
        let rotation = rotation_matrix([row[6], row[7], row[8], row[9]]);
        for _ in 0..2 {
            let local = [0, 1, 2].map(|k| row[3 + k].exp() * rng.next());
            let mut child = row;
            for (a, r) in rotation.iter().enumerate() {
                child[a] += r[0] * local[0] + r[1] * local[1] + r[2] * local[2];
            }
            for v in &mut child[3..6] {
                *v -= config.split_scale_divisor.ln();
            }
            added.push(child);
        }
        keep[i] = false;
        report.split += 1;
    }
    adam.extend(added.len());
    for row in &added {
        params.push(row);
        keep.push(true);
    }
    let limit = (config.prune_opacity / (1.0 - config.prune_opacity)).ln();
    for (k, logit) in keep.iter_mut().zip(params.group(Group::OpacityLogit)) {
        if *k && *logit < limit {
            *k = false;
            report.pruned += 1;
        }
    }
    *params = params.select(&keep);
    adam.select(&keep);
    *stats = DensifyStats::new(params.len());
    report.total = params.len();
    report
}

/// 3DGS's opacity reset: every opacity to at most `max`, and the opacity moments zeroed.
pub fn reset_opacity(params: &mut Params, adam: &mut Adam, max: f64) {
    let limit = (max / (1.0 - max)).ln();
    for v in params.group_mut(Group::OpacityLogit) {
        *v = v.min(limit);
    }
    adam.reset_group(Group::OpacityLogit);
}

/// Rows of the rotation of a (possibly unnormalised) quaternion `w, x, y, z`.
fn rotation_matrix(q: [f64; 4]) -> [[f64; 3]; 3] {
    let n = q
        .iter()
        .map(|v| v * v)
        .sum::<f64>()
        .sqrt()
        .max(f64::MIN_POSITIVE);
    let [w, x, y, z] = q.map(|v| v / n);
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// Standard normal draws: splitmix64 and Box–Muller.
struct Normal(u64);

impl Normal {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn next(&mut self) -> f64 {
        let u = self.uniform().max(f64::MIN_POSITIVE);
        let v = self.uniform();
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::adam::AdamConfig;

    /// Gaussian 0 small, 1 large, 2 nearly transparent, 3 quiet.
    fn scene() -> Params {
        let mut p = Params::zeros(0);
        for (scale, opacity) in [(0.001f64, 0.5f64), (0.5, 0.5), (0.001, 0.001), (0.001, 0.5)] {
            let mut row = [0.0; 14];
            row[2] = 2.0;
            row[3..6].copy_from_slice(&[scale.ln(); 3]);
            row[6] = 1.0;
            row[10] = (opacity / (1.0 - opacity)).ln();
            p.push(&row);
        }
        p
    }

    fn pulled() -> DensifyStats {
        let mut stats = DensifyStats::new(4);
        // 1e-5 pixels · 64 = 6.4e-4 NDC for the first three; the last quiet.
        stats.accumulate(
            &[[1e-5, 0.0], [1e-5, 0.0], [1e-5, 0.0], [1e-7, 0.0]],
            128,
            128,
        );
        stats
    }

    #[test]
    fn small_ones_clone_large_ones_split_faint_ones_go() {
        let mut p = scene();
        let mut adam = Adam::new(AdamConfig::default(), 4);
        let r = densify(
            &mut p,
            &mut adam,
            &mut pulled(),
            &DensifyConfig::default(),
            1.0,
            1,
        );
        assert_eq!(
            (r.cloned, r.split),
            (2, 1),
            "0 and 2 clone (2 is faint but pulled), 1 splits"
        );
        // 4 + 2 clones + 2 children − 1 split parent − faint 2 and its clone.
        assert_eq!((r.pruned, r.total), (2, 5));
        assert_eq!(adam.len(), 5);
        // The split children: scales / 1.6 of the parent's 0.5.
        let children: Vec<f64> = (0..5)
            .map(|i| p.row(i)[3].exp())
            .filter(|s| (s - 0.5 / 1.6).abs() < 1e-12)
            .collect();
        assert_eq!(children.len(), 2);
    }

    #[test]
    fn the_budget_keeps_the_hardest_pulled() {
        let mut p = scene();
        let mut adam = Adam::new(AdamConfig::default(), 4);
        let mut stats = DensifyStats::new(4);
        stats.accumulate(
            &[[1e-5, 0.0], [2e-5, 0.0], [0.0, 0.0], [0.0, 0.0]],
            128,
            128,
        );
        let config = DensifyConfig {
            budget: 5,
            ..DensifyConfig::default()
        };
        let r = densify(&mut p, &mut adam, &mut stats, &config, 1.0, 1);
        assert_eq!((r.cloned, r.split), (0, 1), "room for one: the larger pull");
        assert!(r.total <= 5);
    }

    #[test]
    fn opacity_reset_caps_opacities() {
        let mut p = scene();
        let mut adam = Adam::new(AdamConfig::default(), 4);
        reset_opacity(&mut p, &mut adam, 0.01);
        let set = p.to_set();
        assert!(set.opacities().iter().all(|&o| o <= 0.01 + 1e-9));
        assert!((set.opacities()[2] - 0.001).abs() < 1e-9, "lower ones stay");
    }
}
