//! Learning rates over steps: one [`LearningRate`] per parameter group ([`LearningRates`]), each a
//! [`Schedule`] (constant, or exponential decay as 3DGS decays its positions') optionally under a
//! [`Warmup`]. Apart from Adam because a schedule is a pure function of the step: saving the step
//! saves the schedule.

use serde::{Deserialize, Serialize};

use crate::params::Group;

/// A learning rate as a function of the step, before any warm-up.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Schedule {
    /// The same rate at every step.
    Constant(f64),
    /// `start` at step 0 to `end` at step `steps`, log-linearly (constant `end` after).
    Exponential {
        /// Rate at step 0.
        start: f64,
        /// Rate at step `steps` and after.
        end: f64,
        /// Steps of the decay.
        steps: u64,
    },
}

impl Schedule {
    /// The rate at `step`.
    pub fn at(&self, step: u64) -> f64 {
        match *self {
            Schedule::Constant(lr) => lr,
            Schedule::Exponential { start, end, steps } => {
                let t = if steps == 0 {
                    1.0
                } else {
                    (step as f64 / steps as f64).min(1.0)
                };
                (start.ln() * (1.0 - t) + end.ln() * t).exp()
            }
        }
    }
}

/// A warm-up: the rate is multiplied by a factor rising from `start_factor` at step 0 to 1 at
/// step `steps`, along a quarter sine (3DGS's "delay" of its position rate).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Warmup {
    /// Steps to full rate.
    pub steps: u64,
    /// Factor at step 0.
    pub start_factor: f64,
}

impl Warmup {
    /// The factor at `step`.
    pub fn factor(&self, step: u64) -> f64 {
        if self.steps == 0 || step >= self.steps {
            return 1.0;
        }
        let t = step as f64 / self.steps as f64;
        self.start_factor + (1.0 - self.start_factor) * (0.5 * std::f64::consts::PI * t).sin()
    }
}

/// One group's learning rate: a schedule and an optional warm-up.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LearningRate {
    /// The rate before warm-up.
    pub schedule: Schedule,
    /// The warm-up, if any.
    pub warmup: Option<Warmup>,
}

impl LearningRate {
    /// A constant rate.
    pub fn constant(lr: f64) -> Self {
        Self {
            schedule: Schedule::Constant(lr),
            warmup: None,
        }
    }

    /// The rate at `step`.
    pub fn at(&self, step: u64) -> f64 {
        self.schedule.at(step) * self.warmup.map_or(1.0, |w| w.factor(step))
    }
}

/// The learning rate of every group, indexed by [`Group::index`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LearningRates {
    /// One per group, in [`Group::ALL`]'s order.
    pub groups: [LearningRate; 5],
}

impl LearningRates {
    /// 3DGS's defaults (`OptimizationParams`) over a run of `steps`: position 1.6e-4 → 1.6e-6
    /// times the scene `extent`, with a warm-up from 0.01 (3DGS's delay factor; here over the
    /// first 1 % of the run), log scale 5e-3, rotation 1e-3, opacity logit 0.05, colour 2.5e-3
    /// (3DGS's rate for its degree-0 SH coefficient, which is colour over 0.282: colour's own rate
    /// is that times 0.282, about 7e-4; this uses 2.5e-3 for colour directly, faster on the small
    /// scenes this crate fits).
    pub fn gaussian_splatting(extent: f64, steps: u64) -> Self {
        let mut groups = [LearningRate::constant(0.0); 5];
        groups[Group::Position.index()] = LearningRate {
            schedule: Schedule::Exponential {
                start: 1.6e-4 * extent,
                end: 1.6e-6 * extent,
                steps,
            },
            warmup: Some(Warmup {
                steps: steps / 100,
                start_factor: 0.01,
            }),
        };
        groups[Group::LogScale.index()] = LearningRate::constant(5e-3);
        groups[Group::Rotation.index()] = LearningRate::constant(1e-3);
        groups[Group::OpacityLogit.index()] = LearningRate::constant(0.05);
        groups[Group::Color.index()] = LearningRate::constant(2.5e-3);
        Self { groups }
    }

    /// Every group's rate at `step`.
    pub fn at(&self, step: u64) -> [f64; 5] {
        self.groups.map(|g| g.at(step))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exponential_decay_is_log_linear_between_its_ends() {
        let s = Schedule::Exponential {
            start: 1e-2,
            end: 1e-4,
            steps: 100,
        };
        assert!((s.at(0) - 1e-2).abs() < 1e-15);
        assert!(
            (s.at(50) - 1e-3).abs() < 1e-15,
            "the geometric mean halfway"
        );
        assert!((s.at(100) - 1e-4).abs() < 1e-17);
        assert_eq!(s.at(1000), s.at(100), "constant after");
    }

    #[test]
    fn warmup_rises_from_its_start_factor_to_one() {
        let w = Warmup {
            steps: 10,
            start_factor: 0.01,
        };
        assert!((w.factor(0) - 0.01).abs() < 1e-15);
        assert!((1..10).all(|s| w.factor(s) > w.factor(s - 1)));
        assert_eq!(w.factor(10), 1.0);
        let lr = LearningRate {
            schedule: Schedule::Constant(2.0),
            warmup: Some(w),
        };
        assert!((lr.at(0) - 0.02).abs() < 1e-15);
        assert_eq!(lr.at(25), 2.0);
    }

    #[test]
    fn gaussian_splatting_scales_positions_by_the_extent() {
        let a = LearningRates::gaussian_splatting(1.0, 1000).at(500);
        let b = LearningRates::gaussian_splatting(3.0, 1000).at(500);
        assert!((b[0] - 3.0 * a[0]).abs() < 1e-18);
        assert_eq!(a[1..], b[1..]);
    }
}
