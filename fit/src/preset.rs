//! What a person asks of a fit ([`FitSettings`]: steps, working resolution, Gaussian budget,
//! keyframe spacing, holdout, time budget, seed, frame cap), the three named presets
//! ([`Preset`]: `fast`, `default`, `best`), where the keyframes go ([`keyframe_times`]) and how the
//! settings become the loop's [`FitOptions`] ([`FitSettings::options`]).
//!
//! The settings are the job's vocabulary (what the API, CLI and clients send); the options are the
//! loop's (learning rates, densification schedule, regularisers). Keeping the mapping here means the
//! service never chooses a learning rate, and the presets are tuned in one place, against
//! `examples/fit_clip.rs`'s measurements (docs/tradeoffs.md, "Fitting a clip").

use std::time::Duration;

use c4g_optim::schedule::{LearningRate, Schedule};
use c4g_optim::{DensifyConfig, DensifySchedule, Group, LearningRates};

use crate::error::FitError;
use crate::fit::FitOptions;

/// A named choice of [`FitSettings`]: how much time a fit may spend for how much accuracy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Preset {
    /// About a minute on two cores.
    Fast,
    /// About five minutes on two cores.
    Default,
    /// About fifteen minutes on two cores.
    Best,
}

impl Preset {
    /// Every preset, fastest first.
    pub const ALL: [Preset; 3] = [Preset::Fast, Preset::Default, Preset::Best];

    /// The preset's settings (seed 0, cameras not refined).
    pub fn settings(self) -> FitSettings {
        let base = FitSettings {
            steps: 0,
            resolution: 0,
            max_gaussians: 0,
            keyframe_every: 8,
            holdout_every: 8,
            refine_cameras: false,
            time_budget_s: None,
            seed: 0,
            max_frames: 0,
        };
        match self {
            Preset::Fast => FitSettings {
                steps: 1600,
                resolution: 128,
                max_gaussians: 10_000,
                keyframe_every: 12,
                time_budget_s: Some(55.0),
                max_frames: 300,
                ..base
            },
            Preset::Default => FitSettings {
                steps: 4000,
                resolution: 256,
                max_gaussians: 30_000,
                time_budget_s: Some(280.0),
                max_frames: 300,
                ..base
            },
            Preset::Best => FitSettings {
                steps: 10_000,
                resolution: 256,
                max_gaussians: 100_000,
                keyframe_every: 6,
                time_budget_s: Some(900.0),
                max_frames: 600,
                ..base
            },
        }
    }

    /// The preset named `name` (`fast`, `default`, `best`; ASCII case ignored).
    pub fn parse(name: &str) -> Option<Preset> {
        Preset::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(name.trim()))
    }

    /// The preset's name, as [`parse`](Self::parse) reads it.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Fast => "fast",
            Preset::Default => "default",
            Preset::Best => "best",
        }
    }
}

/// How to fit a clip, in the job's terms.
#[derive(Debug, Clone, PartialEq)]
pub struct FitSettings {
    /// Optimisation steps, one training frame each.
    pub steps: u64,
    /// Long side of the working frames, pixels.
    pub resolution: u32,
    /// Most Gaussians per keyframe.
    pub max_gaussians: usize,
    /// Source frames between keyframes (0: the context times only).
    pub keyframe_every: usize,
    /// Every `holdout_every`-th source frame is held out and scored (0: none).
    pub holdout_every: usize,
    /// Refine the training frames' cameras with the scene (held-out frames keep theirs:
    /// [`FitOptions::refine_cameras`]).
    pub refine_cameras: bool,
    /// Stop after this many seconds, if set.
    pub time_budget_s: Option<f64>,
    /// Seeds the frame order and densification.
    pub seed: u64,
    /// Source frames used at most (spread evenly over the clip when it has more).
    pub max_frames: usize,
}

impl Default for FitSettings {
    fn default() -> Self {
        Preset::Default.settings()
    }
}

/// Runs of at least this many steps let colour's learning rate decay ([`FitSettings::options`]).
pub const COLOUR_DECAY_FROM: u64 = 3000;

/// The largest step count a fit may ask for.
pub const MAX_STEPS: u64 = 100_000;
/// The working resolution's bounds (long side, pixels).
pub const RESOLUTION: std::ops::RangeInclusive<u32> = 16..=1024;
/// The Gaussian budget's bounds.
pub const MAX_GAUSSIANS: std::ops::RangeInclusive<usize> = 1..=1_000_000;
/// The frame cap's bounds.
pub const MAX_FRAMES: std::ops::RangeInclusive<usize> = 1..=10_000;
/// The longest time budget, seconds (a day).
pub const MAX_TIME_BUDGET_S: f64 = 86_400.0;

impl FitSettings {
    /// Refuses settings outside their bounds, saying which and what is allowed.
    pub fn check(&self) -> Result<(), FitError> {
        let refuse = |what: String| Err(FitError::Invalid(what));
        if self.steps > MAX_STEPS {
            return refuse(format!(
                "steps is {}; at most {MAX_STEPS} (use time_budget_s to bound a long fit)",
                self.steps
            ));
        }
        if !RESOLUTION.contains(&self.resolution) {
            return refuse(format!(
                "resolution is {} px; the working frames' long side must be {} to {} px",
                self.resolution,
                RESOLUTION.start(),
                RESOLUTION.end()
            ));
        }
        if !MAX_GAUSSIANS.contains(&self.max_gaussians) {
            return refuse(format!(
                "max_gaussians is {}; it must be {} to {}",
                self.max_gaussians,
                MAX_GAUSSIANS.start(),
                MAX_GAUSSIANS.end()
            ));
        }
        if self.keyframe_every > *MAX_FRAMES.end() {
            return refuse(format!(
                "keyframe_every is {}; at most {} source frames (0: keyframes at the context times only)",
                self.keyframe_every,
                MAX_FRAMES.end()
            ));
        }
        if self.holdout_every == 1 {
            return refuse(
                "holdout_every is 1, which holds out every frame; use 0 (none) or 2 and up".into(),
            );
        }
        if self.holdout_every > *MAX_FRAMES.end() {
            return refuse(format!(
                "holdout_every is {}; at most {} (0: no held-out frames)",
                self.holdout_every,
                MAX_FRAMES.end()
            ));
        }
        if let Some(b) = self.time_budget_s
            && !(b.is_finite() && b > 0.0 && b <= MAX_TIME_BUDGET_S)
        {
            return refuse(format!(
                "time_budget_s is {b}; it must be more than 0 and at most {MAX_TIME_BUDGET_S} s"
            ));
        }
        if !MAX_FRAMES.contains(&self.max_frames) {
            return refuse(format!(
                "max_frames is {}; it must be {} to {}",
                self.max_frames,
                MAX_FRAMES.start(),
                MAX_FRAMES.end()
            ));
        }
        Ok(())
    }

    /// The loop's options for a scene of size `extent` (3DGS's `spatial_lr_scale`: the distance
    /// scale positions move on; for a clip seen from one camera, the median depth of the start).
    ///
    /// Learning rates are those `examples/fit_frames.rs` and `examples/fit_clip.rs` found to
    /// work on our short runs rather than 3DGS's (tuned for 30,000 steps): positions from 1e-3 to
    /// 1e-5 times the extent, colour 1e-2, opacity 0.05, log scale 5e-3, rotation 1e-3. A run of
    /// [`COLOUR_DECAY_FROM`] steps or more lets colour's rate fall tenfold over the run, as
    /// positions' does: measured on bedroom at `default`, +0.41 dB held out (the constant rate's
    /// last steps jitter colours a frame at a time); at 1300 steps (`fast`'s then) the same decay cost
    /// 0.34 dB on bedroom and 0.50 on dog (colours had not settled), so shorter runs keep it.
    /// Densification runs from a tenth to three quarters of the run, every eighth of it (at least
    /// 100 steps: denser rounds grew the count faster than a time budget can afford), within
    /// `max_gaussians`; the held-out frames are scored about ten times a run for the progress
    /// events.
    pub fn options(&self, extent: f64) -> FitOptions {
        let extent = if extent.is_finite() && extent > 0.0 {
            extent
        } else {
            1.0
        };
        let steps = self.steps;
        let mut rates = LearningRates::gaussian_splatting(extent, steps);
        rates.groups[Group::Position.index()] = LearningRate {
            schedule: Schedule::Exponential {
                start: 1e-3 * extent,
                end: 1e-5 * extent,
                steps,
            },
            warmup: None,
        };
        rates.groups[Group::Color.index()] = if steps >= COLOUR_DECAY_FROM {
            LearningRate {
                schedule: Schedule::Exponential {
                    start: 1e-2,
                    end: 1e-3,
                    steps,
                },
                warmup: None,
            }
        } else {
            LearningRate::constant(1e-2)
        };
        let every = (steps / 8).max(100);
        let densify = (steps >= 4 * every).then_some(DensifySchedule {
            config: DensifyConfig {
                budget: self.max_gaussians,
                ..DensifyConfig::default()
            },
            from: steps / 10,
            until: steps * 3 / 4,
            every,
        });
        FitOptions {
            steps,
            max_gaussians: self.max_gaussians,
            holdout_every: self.holdout_every,
            seed: self.seed,
            rates,
            eval_every: (steps / 10).max(1),
            densify,
            extent,
            refine_cameras: self.refine_cameras,
            time_budget: self
                .time_budget_s
                .filter(|b| b.is_finite() && *b > 0.0)
                .map(|b| Duration::from_secs_f64(b.min(MAX_TIME_BUDGET_S))),
            ..FitOptions::default()
        }
    }
}

/// A `width` × `height` frame brought to at most `side` pixels on its long side (never enlarged),
/// its aspect kept: the size kept frames are stored at and fits work at.
pub fn working_size(width: u32, height: u32, side: u32) -> (u32, u32) {
    let long = width.max(height).max(1);
    if long <= side {
        return (width.max(1), height.max(1));
    }
    let scale = f64::from(side) / f64::from(long);
    let shrink = |v: u32| ((f64::from(v) * scale).round() as u32).max(1);
    (shrink(width), shrink(height))
}

/// The keyframe times of a fit: the context times, plus every `every`-th source time (source
/// indices 0, `every`, 2·`every`, …) between the first and last context time, sorted, with times
/// closer than 1e-9 s merged (the earlier kept); `every == 0` gives the context times alone.
/// Non-finite times are ignored. Keyframes stay inside the context span because that is where
/// the feed-forward answer (the start) is decoded.
pub fn keyframe_times(context_times: &[f64], source_times: &[f64], every: usize) -> Vec<f64> {
    let finite = |t: &&f64| t.is_finite();
    let mut times: Vec<f64> = context_times.iter().filter(finite).copied().collect();
    let (Some(first), Some(last)) = (
        times.iter().copied().reduce(f64::min),
        times.iter().copied().reduce(f64::max),
    ) else {
        return Vec::new();
    };
    if every > 0 {
        times.extend(
            source_times
                .iter()
                .step_by(every)
                .filter(finite)
                .filter(|&&t| t >= first && t <= last),
        );
    }
    times.sort_by(f64::total_cmp);
    let mut merged: Vec<f64> = Vec::with_capacity(times.len());
    for t in times {
        if merged.last().is_none_or(|&m| t - m >= 1e-9) {
            merged.push(t);
        }
    }
    merged
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn presets_parse_by_name_and_their_settings_pass_the_check() {
        for p in Preset::ALL {
            assert_eq!(Preset::parse(p.name()), Some(p));
            p.settings().check().unwrap();
        }
        assert_eq!(Preset::parse("FAST"), Some(Preset::Fast));
        assert_eq!(Preset::parse("quick"), None);
        assert_eq!(FitSettings::default(), Preset::Default.settings());
    }

    #[test]
    fn presets_spend_more_for_more() {
        let [f, d, b] = Preset::ALL.map(Preset::settings);
        assert!(f.steps < d.steps && d.steps < b.steps);
        assert!(f.resolution <= d.resolution && d.resolution <= b.resolution);
        let budget = |s: &FitSettings| s.time_budget_s.unwrap();
        assert!(budget(&f) <= 60.0 && budget(&d) <= 300.0 && budget(&b) <= 900.0);
    }

    #[test]
    fn settings_outside_their_bounds_are_refused_saying_which() {
        let ok = Preset::Fast.settings();
        let cases: Vec<(FitSettings, &str)> = vec![
            (
                FitSettings {
                    steps: 100_001,
                    ..ok.clone()
                },
                "steps",
            ),
            (
                FitSettings {
                    resolution: 15,
                    ..ok.clone()
                },
                "resolution",
            ),
            (
                FitSettings {
                    resolution: 1025,
                    ..ok.clone()
                },
                "resolution",
            ),
            (
                FitSettings {
                    max_gaussians: 0,
                    ..ok.clone()
                },
                "max_gaussians",
            ),
            (
                FitSettings {
                    max_gaussians: 1_000_001,
                    ..ok.clone()
                },
                "max_gaussians",
            ),
            (
                FitSettings {
                    holdout_every: 1,
                    ..ok.clone()
                },
                "holdout_every",
            ),
            (
                FitSettings {
                    time_budget_s: Some(f64::NAN),
                    ..ok.clone()
                },
                "time_budget_s",
            ),
            (
                FitSettings {
                    time_budget_s: Some(0.0),
                    ..ok.clone()
                },
                "time_budget_s",
            ),
            (
                FitSettings {
                    time_budget_s: Some(1e9),
                    ..ok.clone()
                },
                "time_budget_s",
            ),
            (
                FitSettings {
                    max_frames: 0,
                    ..ok.clone()
                },
                "max_frames",
            ),
            (
                FitSettings {
                    keyframe_every: usize::MAX,
                    ..ok.clone()
                },
                "keyframe_every",
            ),
        ];
        for (s, field) in cases {
            let e = s.check().unwrap_err().to_string();
            assert!(e.contains(field), "{field}: {e}");
        }
        let edges = FitSettings {
            steps: 0,
            resolution: 16,
            max_gaussians: 1,
            keyframe_every: 0,
            holdout_every: 0,
            time_budget_s: None,
            max_frames: 1,
            ..ok
        };
        edges.check().unwrap();
        let refining = FitSettings {
            refine_cameras: true,
            ..Preset::Fast.settings()
        };
        refining.check().unwrap();
        assert!(refining.options(1.0).refine_cameras);
    }

    #[test]
    fn options_carry_the_settings_and_keep_densification_within_the_budget() {
        let s = Preset::Default.settings();
        let o = s.options(2.0);
        assert_eq!(o.steps, s.steps);
        assert_eq!(o.max_gaussians, s.max_gaussians);
        assert_eq!(o.holdout_every, s.holdout_every);
        assert_eq!(o.extent, 2.0);
        assert_eq!(o.time_budget, Some(Duration::from_secs_f64(280.0)));
        assert!(o.eval_every > 0 && o.eval_every <= s.steps);
        let d = o.densify.unwrap();
        assert_eq!(d.config.budget, s.max_gaussians);
        assert!(d.from > 0 && d.until < s.steps && d.every > 0);
        let position = o.rates.groups[Group::Position.index()];
        assert!(
            (position.at(0) - 2e-3).abs() < 1e-12,
            "scaled by the extent"
        );
        let colour = |s: &FitSettings| {
            let rate = s.options(1.0).rates.groups[Group::Color.index()];
            (rate.at(0), rate.at(s.steps))
        };
        let (start, end) = colour(&s);
        assert!((start - 1e-2).abs() < 1e-15 && (end - 1e-3).abs() < 1e-15);
        let short = FitSettings {
            steps: COLOUR_DECAY_FROM - 1,
            ..s.clone()
        };
        assert_eq!(
            colour(&short),
            (1e-2, 1e-2),
            "a short run keeps colour's rate"
        );
        let zero = FitSettings {
            steps: 0,
            ..s.clone()
        }
        .options(f64::NAN);
        assert_eq!((zero.steps, zero.extent), (0, 1.0));
        assert!(zero.densify.is_none());
    }

    #[test]
    fn keyframes_are_the_context_times_plus_every_nth_source_time_inside_them() {
        let source: Vec<f64> = (0..10).map(|i| i as f64 * 0.1).collect();
        let context = [0.1, 0.8, 0.4];
        assert_eq!(keyframe_times(&context, &source, 0), vec![0.1, 0.4, 0.8]);
        // Source indices 0, 3, 6, 9: 0.0 and 0.9 lie outside [0.1, 0.8].
        let k = keyframe_times(&context, &source, 3);
        assert_eq!(k.len(), 5);
        for (a, b) in k.iter().zip([0.1, 0.3, 0.4, 0.6, 0.8]) {
            assert!((a - b).abs() < 1e-12, "{k:?}");
        }
        // every = 1: every source time inside, with the context's own times merged.
        let all = keyframe_times(&[0.1, 0.8000000000001], &source, 1);
        assert_eq!(all.len(), 8, "{all:?}");
        assert!(all.windows(2).all(|w| w[1] - w[0] >= 1e-9));
        assert!(keyframe_times(&[], &source, 1).is_empty());
        assert_eq!(
            keyframe_times(&[0.5, f64::NAN], &[f64::NAN, 0.5], 1),
            vec![0.5]
        );
    }
}
