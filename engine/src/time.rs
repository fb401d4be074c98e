//! The TimePolicy: how raw timestamps become the normalised times the decoder is conditioned on.
//!
//! Times are seconds (or frame indices) as `f64` at the edges of the service; the decoder takes,
//! for each target `b`, the normalised context times `context_times[b]` (`[T]`) and the
//! normalised target time `target_times[b]`, both `f32`.
//!
//! # The reference and its flaw
//! The reference code normalises against the first context frame and the *target*:
//! `rel(t) = (t - min(context)) / (target - min(context) + 1e-8)`, so the target always maps to
//! ~1 and the context frames to multiples of their distance from the target. When the target
//! approaches the first frame the denominator collapses to 1e-8: a target *at* the first frame
//! sends every other context time to ~1e8, and the sinusoidal embedding of such arguments is
//! noise. The reference script hits exactly that case.
//!
//! # What training saw
//! C4G was trained with raw integer source-frame indices as timestamps, so every target it
//! learned from was at least one source frame after the first context frame `m` (or at `m`
//! itself, where the reference feeds rounding noise of magnitude 1e8 to sin/cos: nothing a policy
//! can or should reproduce). The reference is well conditioned on all of that; it only breaks on
//! `[m, m + s)`, `s` the source's frame step, where training had no sound input.
//!
//! # The frame-step policy (the default)
//! With `m = min(context)`, `M = max(context)` and `s` the clip's source frame step (seconds
//! between source frames, carried by the [`Encoding`](crate::Encoding)):
//!
//! `rel(t) = (t - m) / max(target - m, s)`, computed in f64 and cast to f32,
//!
//! and every normalised time is 0 when the context is a single instant (`M == m`).
//! - **It is the reference wherever training was.** For every target at least one source frame
//!   after `m` the denominator is `target - m`, the reference's own: bit-identical with frame
//!   indices as times (the reference's `+ 1e-8` vanishes in f32), equal to float rounding with
//!   seconds. It deviates only on `[m, m + s)`.
//! - **It cannot blow up, and the neighbourhood cannot be smaller.** No normalised time exceeds
//!   `(M - m) / s`, the number of source frames in the span: the largest value training itself
//!   produced (target one frame after `m`, context frame at `M`). Any policy equal to the
//!   reference on `[m + ε, M]` reaches `(M - m) / ε` there, so a floor below `s` would feed the
//!   model values training never produced.
//! - **At `target == m`** the context times are what training saw for the target one source
//!   frame later (`(t - m) / s`, whole frame offsets), and the target maps to 0: the limit from
//!   the right, so the policy stays continuous.
//! - **Unknown frame step.** An encoding without source information (an engine caller that
//!   passes none) falls back to the smallest positive gap between distinct context times. The
//!   context frames are source frames, so that gap bounds `s` from above: still bounded, still
//!   continuous, deviating on the larger `[m, m + gap)`. For evenly spaced context frames the gap
//!   is the mean spacing and the result is exactly the stable policy's.
//! - **It is continuous in the target** (the branches of the `max` meet at `target = m + s`),
//!   **ignores the order of the context times** and **is defined for one context frame and for
//!   duplicate times** (duplicates do not shrink the fallback gap).
//!
//! # The stable policy (what c4g-tiny was trained with)
//! With `n` distinct context times and their mean spacing `h = (M - m) / (n - 1)`:
//! `rel(t) = (t - m) / max(target - m, h)` (0 for a single instant). Bounded by `n - 1`, but it
//! deviates from the reference on the whole first interval `[m, m + h)`, where the reference is
//! sound for every target a source frame after `m`: for the official weights it is the wrong
//! default. Packages trained with it (ours) declare it in `model.json`.
//!
//! [`TimePolicy::Reference`] reproduces the reference bit for bit (computed in f32 as the
//! reference does) for parity tests against it.
//!
//! # What every policy refuses
//! An empty context, a NaN or infinite time, a frame step that is not a positive finite number,
//! and a target outside `[m, M]`: the model interpolates between context frames and was never
//! trained to extrapolate, so the engine says so instead of returning plausible-looking garbage.
//! A span so wide (or a step so small) that the arithmetic overflows is refused too: every value
//! handed to the decoder is finite.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::{EngineError, Result};

/// How timestamps are normalised before they condition the decoder. See the module docs.
///
/// Serialised (in `model.json`, on the command line) in kebab case: `frame-step`, `stable`,
/// `reference`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TimePolicy {
    /// The reference code's normalisation, bit for bit (f32 arithmetic). Blows up for targets
    /// near the first context frame; for parity tests.
    Reference,
    /// The reference's normalisation with the denominator floored at the mean spacing of the
    /// context times: bounded, continuous, order-independent. What c4g-tiny was trained with.
    Stable,
    /// The reference's normalisation with the denominator floored at the source's frame step:
    /// equal to the reference for every target a source frame or more after the first context
    /// frame, bounded, continuous, order-independent. The default.
    #[default]
    FrameStep,
}

/// The normalised times for one target: one row of `context_times` and one `target_times` entry.
#[derive(Debug, Clone, PartialEq)]
pub struct NormalizedTimes {
    /// Normalised context times, in the order the context times were given.
    pub context: Vec<f32>,
    /// Normalised target time.
    pub target: f32,
}

/// The reference's guard against division by zero, in the precision it is added in.
const REFERENCE_EPSILON: f32 = 1e-8;

impl TimePolicy {
    /// Every policy, for listings and tests.
    pub const ALL: [TimePolicy; 3] = [Self::FrameStep, Self::Stable, Self::Reference];

    /// The policy's name in `model.json` and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Self::Reference => "reference",
            Self::Stable => "stable",
            Self::FrameStep => "frame-step",
        }
    }

    /// Normalises `context` for one `target`, the source frame step unknown.
    pub fn normalize(self, context: &[f64], target: f64) -> Result<NormalizedTimes> {
        self.normalize_with_step(context, None, target)
    }

    /// Normalises `context` once per target, in the order of `targets`, the source frame step
    /// unknown.
    pub fn normalize_all(self, context: &[f64], targets: &[f64]) -> Result<Vec<NormalizedTimes>> {
        self.normalize_all_with_step(context, None, targets)
    }

    /// Normalises `context` for one `target`; `frame_step` is the source's seconds between frames
    /// when known (only [`TimePolicy::FrameStep`] reads it).
    pub fn normalize_with_step(
        self,
        context: &[f64],
        frame_step: Option<f64>,
        target: f64,
    ) -> Result<NormalizedTimes> {
        let span = Span::of(context, frame_step)?;
        self.normalize_in(&span, context, target)
    }

    /// [`normalize_with_step`](Self::normalize_with_step) once per target, in the order of
    /// `targets`.
    pub fn normalize_all_with_step(
        self,
        context: &[f64],
        frame_step: Option<f64>,
        targets: &[f64],
    ) -> Result<Vec<NormalizedTimes>> {
        let span = Span::of(context, frame_step)?;
        targets
            .iter()
            .map(|&target| self.normalize_in(&span, context, target))
            .collect()
    }

    fn normalize_in(self, span: &Span, context: &[f64], target: f64) -> Result<NormalizedTimes> {
        let target = span.admit(target)?;
        if !(span.last - span.first).is_finite() {
            return Err(span.overflow());
        }
        let times = match self {
            Self::Reference => reference(span, context, target),
            Self::Stable => stable(span, context, target),
            Self::FrameStep => frame_step(span, context, target),
        };
        let all_finite = times.target.is_finite() && times.context.iter().all(|v| v.is_finite());
        if all_finite {
            Ok(times)
        } else {
            Err(span.overflow())
        }
    }
}

impl fmt::Display for TimePolicy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for TimePolicy {
    type Err = EngineError;

    fn from_str(s: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| {
                EngineError::InvalidInput(format!(
                    "unknown time policy {s:?} (known: frame-step, stable, reference)"
                ))
            })
    }
}

/// Checks a source frame step: `None` (unknown) or a positive finite number of seconds.
pub(crate) fn check_frame_step(frame_step: Option<f64>) -> Result<Option<f64>> {
    match frame_step {
        Some(s) if !(s.is_finite() && s > 0.0) => Err(EngineError::InvalidInput(format!(
            "a source frame step must be a positive, finite number of seconds, got {s}"
        ))),
        step => Ok(step),
    }
}

/// What the policies need to know about the context times.
struct Span {
    first: f64,
    last: f64,
    distinct: usize,
    /// The source's frame step when given, else the smallest gap between distinct context times
    /// (`None` for a single instant).
    step: Option<f64>,
}

impl Span {
    fn of(context: &[f64], frame_step: Option<f64>) -> Result<Self> {
        if context.is_empty() {
            return Err(EngineError::EmptyContext);
        }
        if let Some(&value) = context.iter().find(|t| !t.is_finite()) {
            return Err(EngineError::NonFiniteTime {
                what: "context",
                value,
            });
        }
        let frame_step = check_frame_step(frame_step)?;
        let mut sorted: Vec<f64> = context.iter().map(|&t| canonical(t)).collect();
        sorted.sort_by(f64::total_cmp);
        sorted.dedup();
        let smallest_gap = sorted.windows(2).map(|w| w[1] - w[0]).reduce(f64::min);
        Ok(Self {
            first: sorted[0],
            last: sorted[sorted.len() - 1],
            distinct: sorted.len(),
            step: frame_step.or(smallest_gap),
        })
    }

    fn overflow(&self) -> EngineError {
        EngineError::TimeOverflow {
            first: self.first,
            last: self.last,
        }
    }

    /// The target, if it is finite and inside the span.
    fn admit(&self, target: f64) -> Result<f64> {
        if !target.is_finite() {
            return Err(EngineError::NonFiniteTime {
                what: "target",
                value: target,
            });
        }
        if target < self.first || target > self.last {
            return Err(EngineError::TargetOutsideContext {
                target,
                first: self.first,
                last: self.last,
            });
        }
        Ok(canonical(target))
    }
}

/// Folds -0.0 into +0.0, so that results never depend on which zero came first.
fn canonical(t: f64) -> f64 {
    t + 0.0
}

fn reference(span: &Span, context: &[f64], target: f64) -> NormalizedTimes {
    let first = span.first as f32;
    let denominator = (target as f32 - first) + REFERENCE_EPSILON;
    let rel = |t: f64| (t as f32 - first) / denominator;
    NormalizedTimes {
        context: context.iter().map(|&t| rel(t)).collect(),
        target: rel(target),
    }
}

fn stable(span: &Span, context: &[f64], target: f64) -> NormalizedTimes {
    if span.distinct == 1 {
        return NormalizedTimes {
            context: vec![0.0; context.len()],
            target: 0.0,
        };
    }
    let intervals = (span.distinct - 1) as f64;
    let spacing = (span.last - span.first) / intervals;
    let denominator = (target - span.first).max(spacing);
    // The clamp only bites where rounding (subnormal spans) would lift a value past the bound.
    let rel = |t: f64| (((canonical(t) - span.first) / denominator).min(intervals)) as f32;
    NormalizedTimes {
        context: context.iter().map(|&t| rel(t)).collect(),
        target: rel(target),
    }
}

fn frame_step(span: &Span, context: &[f64], target: f64) -> NormalizedTimes {
    let Some(step) = span.step.filter(|_| span.distinct > 1) else {
        return NormalizedTimes {
            context: vec![0.0; context.len()],
            target: 0.0,
        };
    };
    // Division is monotone in both operands, so no value exceeds (M - m) / step: no clamp needed.
    let denominator = (target - span.first).max(step);
    let rel = |t: f64| ((canonical(t) - span.first) / denominator) as f32;
    NormalizedTimes {
        context: context.iter().map(|&t| rel(t)).collect(),
        target: rel(target),
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn stable(context: &[f64], target: f64) -> NormalizedTimes {
        TimePolicy::Stable.normalize(context, target).unwrap()
    }

    fn reference(context: &[f64], target: f64) -> NormalizedTimes {
        TimePolicy::Reference.normalize(context, target).unwrap()
    }

    fn frame_step(context: &[f64], step: Option<f64>, target: f64) -> NormalizedTimes {
        TimePolicy::FrameStep
            .normalize_with_step(context, step, target)
            .unwrap()
    }

    #[test]
    fn frame_step_is_the_default() {
        assert_eq!(TimePolicy::default(), TimePolicy::FrameStep);
    }

    #[test]
    fn policies_have_kebab_case_names_in_json_and_text() {
        for (policy, name) in [
            (TimePolicy::FrameStep, "frame-step"),
            (TimePolicy::Stable, "stable"),
            (TimePolicy::Reference, "reference"),
        ] {
            assert_eq!(policy.name(), name);
            assert_eq!(policy.to_string(), name);
            assert_eq!(name.parse::<TimePolicy>().unwrap(), policy);
            let json = serde_json::to_string(&policy).unwrap();
            assert_eq!(json, format!("{name:?}"));
            assert_eq!(serde_json::from_str::<TimePolicy>(&json).unwrap(), policy);
        }
        assert!("framestep".parse::<TimePolicy>().is_err());
        assert!(serde_json::from_str::<TimePolicy>("\"FrameStep\"").is_err());
    }

    #[test]
    fn reference_divides_by_the_distance_to_the_target() {
        let r = reference(&[0.0, 2.0, 4.0, 6.0], 1.0);
        let d = 1.0f32 + 1e-8;
        assert_eq!(r.context, vec![0.0, 2.0 / d, 4.0 / d, 6.0 / d]);
        assert_eq!(r.context, vec![0.0, 2.0, 4.0, 6.0]);
        assert_eq!(r.target, 1.0);

        let r = reference(&[0.0, 2.0, 4.0, 6.0], 6.0);
        assert_eq!(r.context, vec![0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0]);
        assert_eq!(r.target, 1.0);
    }

    #[test]
    fn reference_blows_up_at_the_first_frame_and_stable_does_not() {
        let r = reference(&[0.0, 2.0, 4.0, 6.0], 0.0);
        assert_eq!(r.context[1], 2.0 / 1e-8f32);
        assert!(r.context[3] > 5e8);
        assert_eq!(r.target, 0.0);

        let s = stable(&[0.0, 2.0, 4.0, 6.0], 0.0);
        assert_eq!(s.context, vec![0.0, 1.0, 2.0, 3.0]);
        assert_eq!(s.target, 0.0);
    }

    #[test]
    fn stable_matches_the_reference_from_one_spacing_after_the_first_frame() {
        let context = [0.0, 2.0, 4.0, 6.0];
        for target in [2.0, 3.0, 4.5, 6.0] {
            assert_eq!(
                stable(&context, target),
                reference(&context, target),
                "t={target}"
            );
        }
    }

    #[test]
    fn stable_floors_the_denominator_at_the_mean_spacing_in_the_first_gap() {
        let s = stable(&[0.0, 2.0, 4.0, 6.0], 1.0);
        assert_eq!(s.context, vec![0.0, 1.0, 2.0, 3.0]);
        assert_eq!(s.target, 0.5);
    }

    #[test]
    fn stable_is_continuous_where_its_branches_meet() {
        let context = [10.0, 12.0, 14.0, 16.0];
        let below = stable(&context, 12.0 - 1e-9);
        let at = stable(&context, 12.0);
        for (a, b) in below.context.iter().zip(&at.context) {
            assert!((a - b).abs() < 1e-6);
        }
        assert!((below.target - at.target).abs() < 1e-6);
    }

    #[test]
    fn a_single_frame_normalises_to_zero() {
        for policy in TimePolicy::ALL {
            for step in [None, Some(1.0 / 30.0)] {
                let r = policy.normalize_with_step(&[5.0], step, 5.0).unwrap();
                assert_eq!(r.context, vec![0.0]);
                assert_eq!(r.target, 0.0);
            }
        }
        let s = stable(&[3.0, 3.0, 3.0], 3.0);
        assert_eq!(s.context, vec![0.0; 3]);
        let f = frame_step(&[3.0, 3.0, 3.0], Some(0.5), 3.0);
        assert_eq!(f.context, vec![0.0; 3]);
    }

    #[test]
    fn target_at_the_last_frame_maps_to_one() {
        let s = stable(&[0.5, 1.0, 1.5, 2.5], 2.5);
        assert_eq!(s.target, 1.0);
        assert_eq!(s.context[3], 1.0);
        assert_eq!(s.context[0], 0.0);
    }

    #[test]
    fn duplicates_do_not_shrink_the_spacing() {
        // Distinct {0, 2, 4, 6}: spacing 2, as without the duplicates.
        let s = stable(&[0.0, 0.0, 2.0, 4.0, 4.0, 6.0], 1.0);
        assert_eq!(s.context, vec![0.0, 0.0, 1.0, 2.0, 2.0, 3.0]);
        assert_eq!(s.target, 0.5);
    }

    #[test]
    fn unsorted_context_keeps_its_order_and_its_values() {
        let s = stable(&[6.0, 0.0, 4.0, 2.0], 3.0);
        assert_eq!(s.context, vec![2.0, 0.0, 4.0 / 3.0, 2.0 / 3.0]);
        assert_eq!(s.target, 1.0);
    }

    #[test]
    fn negative_and_fractional_seconds_work() {
        let s = stable(&[-1.5, -0.5, 0.5], 0.0);
        assert_eq!(s.context, vec![0.0, 1.0 / 1.5, 2.0 / 1.5]);
        assert_eq!(s.target, 1.0);
    }

    #[test]
    fn every_policy_refuses_to_extrapolate() {
        for policy in TimePolicy::ALL {
            for target in [-0.5, 6.5] {
                let err = policy.normalize(&[0.0, 2.0, 4.0, 6.0], target).unwrap_err();
                assert!(
                    matches!(
                        err,
                        EngineError::TargetOutsideContext {
                            first: 0.0,
                            last: 6.0,
                            ..
                        }
                    ),
                    "{err}"
                );
                assert!(err.to_string().contains("cannot extrapolate"));
            }
        }
    }

    #[test]
    fn every_policy_refuses_empty_and_non_finite_input() {
        for policy in TimePolicy::ALL {
            assert!(matches!(
                policy.normalize(&[], 0.0),
                Err(EngineError::EmptyContext)
            ));
            assert!(matches!(
                policy.normalize(&[0.0, f64::NAN], 0.0),
                Err(EngineError::NonFiniteTime {
                    what: "context",
                    ..
                })
            ));
            assert!(matches!(
                policy.normalize(&[0.0, f64::INFINITY], 1.0),
                Err(EngineError::NonFiniteTime {
                    what: "context",
                    ..
                })
            ));
            assert!(matches!(
                policy.normalize(&[0.0, 1.0], f64::NAN),
                Err(EngineError::NonFiniteTime { what: "target", .. })
            ));
        }
    }

    #[test]
    fn overflowing_spans_are_refused() {
        let err = TimePolicy::Stable
            .normalize(&[-f64::MAX, f64::MAX], 0.0)
            .unwrap_err();
        assert!(matches!(err, EngineError::TimeOverflow { .. }), "{err}");
        let err = TimePolicy::FrameStep
            .normalize_with_step(&[0.0, 1e300], Some(1e-300), 0.0)
            .unwrap_err();
        assert!(matches!(err, EngineError::TimeOverflow { .. }), "{err}");
        let err = TimePolicy::Reference
            .normalize(&[0.0, 1e300], 1e300)
            .unwrap_err();
        assert!(matches!(err, EngineError::TimeOverflow { .. }), "{err}");
    }

    #[test]
    fn normalize_all_gives_one_row_per_target_in_order() {
        let rows = TimePolicy::Stable
            .normalize_all(&[0.0, 2.0, 4.0, 6.0], &[6.0, 0.0, 3.0])
            .unwrap();
        assert_eq!(rows.len(), 3);
        assert_eq!(rows[0].target, 1.0);
        assert_eq!(rows[1].target, 0.0);
        assert_eq!(rows[2].context[3], 2.0);
        assert!(
            TimePolicy::Stable
                .normalize_all(&[0.0, 1.0], &[0.5, 2.0])
                .is_err()
        );
    }

    #[test]
    fn frame_step_is_the_reference_from_one_source_frame_after_the_first() {
        // Seconds at 30 fps, context every 2 s: the reference is sound from 1/30 s on.
        let context = [0.0, 2.0, 4.0, 6.0];
        for target in [1.0, 0.5, 2.0, 3.0, 6.0] {
            let f = frame_step(&context, Some(1.0 / 30.0), target);
            let r = reference(&context, target);
            assert_eq!(f, r, "t={target}");
        }
        // Frame indices, step 1: every target from m + 1 on, bit for bit.
        for target in 1..=6 {
            let target = f64::from(target);
            assert_eq!(
                frame_step(&context, Some(1.0), target),
                reference(&context, target)
            );
        }
        // Where stable deviates (the whole first interval), frame-step does not.
        assert_ne!(stable(&context, 1.0), reference(&context, 1.0));
    }

    #[test]
    fn frame_step_floors_the_denominator_at_the_step_inside_the_first_source_frame() {
        let f = frame_step(&[0.0, 2.0, 4.0, 6.0], Some(0.5), 0.25);
        assert_eq!(f.context, vec![0.0, 4.0, 8.0, 12.0]);
        assert_eq!(f.target, 0.5);
    }

    #[test]
    fn frame_step_at_the_first_frame_sees_the_next_source_frames_context() {
        let step = 1.0 / 30.0;
        let context = [0.0, 2.0, 4.0, 6.0];
        let at = frame_step(&context, Some(step), 0.0);
        let next = frame_step(&context, Some(step), step);
        assert_eq!(at.context, next.context);
        assert_eq!(at.context, vec![0.0, 60.0, 120.0, 180.0]);
        assert_eq!((at.target, next.target), (0.0, 1.0));
    }

    #[test]
    fn frame_step_is_continuous_where_its_branches_meet() {
        let context = [10.0, 12.0, 14.0, 16.0];
        let step = 0.25;
        let below = frame_step(&context, Some(step), 10.25 - 1e-9);
        let at = frame_step(&context, Some(step), 10.25);
        for (a, b) in below.context.iter().zip(&at.context) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
        assert!((below.target - at.target).abs() < 1e-6);
    }

    #[test]
    fn an_unknown_step_falls_back_to_the_smallest_context_gap() {
        // Uneven context: gap 0.5 (between 2 and 2.5), mean spacing 2.
        let context = [0.0, 2.0, 2.5, 6.0];
        for target in [0.0, 0.25, 0.5, 1.0, 3.0, 6.0] {
            assert_eq!(
                frame_step(&context, None, target),
                frame_step(&context, Some(0.5), target)
            );
        }
        assert_eq!(
            frame_step(&context, None, 1.0),
            reference(&context, 1.0),
            "past the smallest gap, the reference"
        );
        // Evenly spaced frames: the smallest gap is the mean spacing, so it is the stable policy.
        let even = [0.0, 2.0, 4.0, 6.0];
        for target in [0.0, 0.5, 1.0, 2.0, 5.0] {
            assert_eq!(frame_step(&even, None, target), stable(&even, target));
        }
        // Duplicates do not shrink the gap.
        assert_eq!(
            frame_step(&[0.0, 0.0, 2.0, 4.0, 4.0, 6.0], None, 1.0).context,
            vec![0.0, 0.0, 1.0, 2.0, 2.0, 3.0]
        );
    }

    #[test]
    fn frame_step_keeps_unsorted_context_in_its_order() {
        let f = frame_step(&[6.0, 0.0, 4.0, 2.0], Some(1.0), 0.5);
        assert_eq!(f.context, vec![6.0, 0.0, 4.0, 2.0]);
        assert_eq!(f.target, 0.5);
    }

    #[test]
    fn a_frame_step_that_is_not_a_positive_finite_number_is_refused() {
        for bad in [0.0, -1.0 / 30.0, f64::NAN, f64::INFINITY] {
            for policy in TimePolicy::ALL {
                let err = policy
                    .normalize_with_step(&[0.0, 1.0], Some(bad), 0.5)
                    .unwrap_err();
                assert!(matches!(err, EngineError::InvalidInput(_)), "{err}");
            }
        }
    }

    #[test]
    fn only_frame_step_reads_the_frame_step() {
        let context = [0.0, 2.0, 4.0, 6.0];
        for policy in [TimePolicy::Stable, TimePolicy::Reference] {
            assert_eq!(
                policy
                    .normalize_with_step(&context, Some(0.1), 1.0)
                    .unwrap(),
                policy.normalize(&context, 1.0).unwrap()
            );
        }
    }

    /// One case of the table the Python mirror wrote (models/fixtures/time-policy-cases.json).
    /// Numbers travel as IEEE bit patterns (f64 inputs, f32 outputs), so that no decimal
    /// parsing stands between the two implementations.
    #[derive(serde::Deserialize)]
    struct CrossCase {
        policy: TimePolicy,
        context_bits: Vec<u64>,
        frame_step_bits: Option<u64>,
        target_bits: u64,
        /// `None` when the mirror refused the input.
        expected: Option<CrossExpected>,
    }

    #[derive(serde::Deserialize)]
    struct CrossExpected {
        context_bits: Vec<u32>,
        target_bits: u32,
    }

    #[test]
    fn every_policy_agrees_exactly_with_the_python_mirror() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../models/fixtures/time-policy-cases.json"
        );
        let text = std::fs::read_to_string(path).unwrap();
        let table: serde_json::Value = serde_json::from_str(&text).unwrap();
        let cases: Vec<CrossCase> = serde_json::from_value(table["cases"].clone()).unwrap();
        assert!(cases.len() >= 300, "{} cases", cases.len());
        let mut refused = 0;
        for (i, case) in cases.iter().enumerate() {
            let context: Vec<f64> = case
                .context_bits
                .iter()
                .map(|&b| f64::from_bits(b))
                .collect();
            let step = case.frame_step_bits.map(f64::from_bits);
            let target = f64::from_bits(case.target_bits);
            let got = case.policy.normalize_with_step(&context, step, target);
            let what = format!(
                "case {i}: {} {context:?} step {step:?} target {target}",
                case.policy
            );
            match (&case.expected, got) {
                (None, Err(_)) => refused += 1,
                (Some(e), Ok(r)) => {
                    // Values, not bits: the mirror does not fold -0 into +0 everywhere.
                    let expected: Vec<f32> =
                        e.context_bits.iter().map(|&b| f32::from_bits(b)).collect();
                    assert_eq!(r.context, expected, "{what}");
                    assert_eq!(r.target, f32::from_bits(e.target_bits), "{what}");
                }
                (e, r) => panic!(
                    "{what}: the mirror accepted it: {}, the engine gave {r:?}",
                    e.is_some()
                ),
            }
        }
        assert!(
            refused > 0 && refused < cases.len() / 4,
            "{refused} refused"
        );
    }

    /// f64 values that exercise the extremes, drawn from a small pool so duplicates are common.
    fn time() -> impl Strategy<Value = f64> {
        prop_oneof![
            3 => (-20i32..20).prop_map(|i| f64::from(i) * 0.5),
            1 => any::<f64>(),
            1 => prop::sample::select(vec![
                0.0, -0.0, f64::NAN, f64::INFINITY, f64::NEG_INFINITY, f64::MAX, -f64::MAX,
                f64::MIN_POSITIVE, 5e-324, -5e-324, 1e-300, 1e300, 1e8, 1e-8, 16_777_217.0,
            ]),
        ]
    }

    /// A context and a target that is often inside it (a context value or a blend of two).
    fn case() -> impl Strategy<Value = (Vec<f64>, f64)> {
        (
            prop::collection::vec(time(), 0..10),
            time(),
            0usize..10,
            0usize..10,
            0.0..=1.0f64,
        )
            .prop_map(|(context, free, i, j, a)| {
                let target = match (context.get(i), context.get(j)) {
                    (Some(&x), Some(&y)) if i % 3 != 0 => x + a * (y - x),
                    (Some(&x), _) if i % 3 == 0 => x,
                    _ => free,
                };
                (context, target)
            })
    }

    /// A frame step: unknown, typical, extreme, or one the policies refuse.
    fn step() -> impl Strategy<Value = Option<f64>> {
        prop_oneof![
            2 => Just(None),
            2 => prop::sample::select(vec![1.0 / 30.0, 0.5, 1.0, 2.0, 1e-6, 1e6, 5e-324, 1e300])
                .prop_map(Some),
            1 => prop::sample::select(vec![0.0, -1.0, f64::NAN, f64::INFINITY]).prop_map(Some),
        ]
    }

    fn sorted_distinct(context: &[f64]) -> Vec<f64> {
        let mut v: Vec<f64> = context.iter().map(|t| t + 0.0).collect();
        v.sort_by(f64::total_cmp);
        v.dedup();
        v
    }

    fn distinct(context: &[f64]) -> usize {
        sorted_distinct(context).len()
    }

    fn smallest_gap(sorted: &[f64]) -> Option<f64> {
        sorted.windows(2).map(|w| w[1] - w[0]).reduce(f64::min)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2048))]

        #[test]
        fn stable_output_is_an_error_or_finite_and_bounded((context, target) in case()) {
            if let Ok(r) = TimePolicy::Stable.normalize(&context, target) {
                let bound = (distinct(&context) - 1) as f32;
                prop_assert_eq!(r.context.len(), context.len());
                prop_assert!(r.target.is_finite() && (0.0..=1.0).contains(&r.target));
                for v in r.context {
                    prop_assert!(v.is_finite() && v.abs() <= bound, "{} > {}", v, bound);
                }
            }
        }

        #[test]
        fn reference_output_is_an_error_or_finite((context, target) in case()) {
            if let Ok(r) = TimePolicy::Reference.normalize(&context, target) {
                prop_assert!(r.target.is_finite());
                prop_assert!(r.context.iter().all(|v| v.is_finite()));
            }
        }

        #[test]
        fn accepted_targets_lie_inside_the_context_span((context, target) in case(), step in step()) {
            let accepted = TimePolicy::Stable.normalize(&context, target).is_ok()
                || TimePolicy::FrameStep.normalize_with_step(&context, step, target).is_ok();
            let finite: Vec<f64> = context.iter().copied().filter(|t| t.is_finite()).collect();
            let inside = !context.is_empty()
                && finite.len() == context.len()
                && finite.iter().any(|&t| t <= target)
                && finite.iter().any(|&t| t >= target);
            if accepted {
                prop_assert!(inside);
            }
        }

        #[test]
        fn permuting_the_context_permutes_the_output(
            ((context, target), order) in case().prop_flat_map(|c| {
                let n = c.0.len();
                (Just(c), Just((0..n).collect::<Vec<usize>>()).prop_shuffle())
            })
        ) {
            let permuted: Vec<f64> = order.iter().map(|&i| context[i]).collect();
            for (policy, step) in TimePolicy::ALL
                .into_iter()
                .flat_map(|p| [(p, None), (p, Some(0.25))])
            {
                let a = policy.normalize_with_step(&context, step, target);
                let b = policy.normalize_with_step(&permuted, step, target);
                prop_assert_eq!(a.is_ok(), b.is_ok());
                if let (Ok(a), Ok(b)) = (a, b) {
                    prop_assert_eq!(a.target.to_bits(), b.target.to_bits());
                    for (k, &i) in order.iter().enumerate() {
                        prop_assert_eq!(a.context[i].to_bits(), b.context[k].to_bits());
                    }
                }
            }
        }

        #[test]
        fn stable_equals_reference_for_frame_indices_past_the_first_gap(
            mut frames in prop::collection::vec(0u32..100_000, 2..20),
            pick in 0.0..=1.0f64,
        ) {
            frames.sort_unstable();
            frames.dedup();
            prop_assume!(frames.len() >= 2);
            let context: Vec<f64> = frames.iter().map(|&f| f64::from(f)).collect();
            let (m, big_m) = (context[0], context[context.len() - 1]);
            let spacing = (big_m - m) / (context.len() - 1) as f64;
            let target = (m + spacing + pick * (big_m - m - spacing)).round().clamp(m + spacing.ceil(), big_m);
            let s = TimePolicy::Stable.normalize(&context, target).unwrap();
            let r = TimePolicy::Reference.normalize(&context, target).unwrap();
            prop_assert_eq!(s, r);
        }

        #[test]
        fn frame_step_output_is_an_error_or_finite_and_bounded(
            (context, target) in case(),
            step in step(),
        ) {
            if let Ok(r) = TimePolicy::FrameStep.normalize_with_step(&context, step, target) {
                let sorted = sorted_distinct(&context);
                let span = sorted[sorted.len() - 1] - sorted[0];
                let used = step.or_else(|| smallest_gap(&sorted));
                let bound = used.map_or(0.0, |s| (span / s) as f32);
                prop_assert_eq!(r.context.len(), context.len());
                prop_assert!(r.target.is_finite() && (0.0..=1.0).contains(&r.target));
                for v in r.context {
                    prop_assert!(v.is_finite() && (0.0..=bound).contains(&v), "{} > {}", v, bound);
                }
            }
        }

        #[test]
        fn frame_step_without_a_step_is_frame_step_with_the_smallest_gap(
            (context, target) in case(),
        ) {
            let gap = smallest_gap(&sorted_distinct(&context));
            let a = TimePolicy::FrameStep.normalize(&context, target);
            let b = TimePolicy::FrameStep.normalize_with_step(&context, gap, target);
            prop_assert_eq!(a.ok(), b.ok());
        }

        #[test]
        fn frame_step_equals_reference_for_frame_indices_from_one_frame_after_the_first(
            mut frames in prop::collection::vec(0u32..100_000, 2..20),
            pick in 0.0..=1.0f64,
        ) {
            frames.sort_unstable();
            frames.dedup();
            prop_assume!(frames.len() >= 2);
            let context: Vec<f64> = frames.iter().map(|&f| f64::from(f)).collect();
            let (m, big_m) = (context[0], context[context.len() - 1]);
            let target = (m + 1.0 + pick * (big_m - m - 1.0)).round().clamp(m + 1.0, big_m);
            let f = TimePolicy::FrameStep.normalize_with_step(&context, Some(1.0), target).unwrap();
            let r = TimePolicy::Reference.normalize(&context, target).unwrap();
            prop_assert_eq!(f, r);
        }

        #[test]
        fn frame_step_moves_little_when_the_target_moves_little(
            mut frames in prop::collection::vec(0u32..1000, 2..12),
            steps in 1u32..60,
            pick in 0.0..=1.0f64,
        ) {
            frames.sort_unstable();
            frames.dedup();
            prop_assume!(frames.len() >= 2);
            let context: Vec<f64> = frames.iter().map(|&f| f64::from(f) / 30.0).collect();
            let (m, big_m) = (context[0], context[context.len() - 1]);
            let step = f64::from(steps) / 30.0;
            let delta = 1e-9;
            let target = (m + pick * (big_m - m)).min(big_m - delta);
            let a = TimePolicy::FrameStep.normalize_with_step(&context, Some(step), target).unwrap();
            let b = TimePolicy::FrameStep
                .normalize_with_step(&context, Some(step), target + delta)
                .unwrap();
            // |d rel / d target| <= span / step^2; plus f32 rounding of values up to span / step.
            let bound = (big_m - m) / step;
            let tolerance = (bound / step * delta + bound * 1e-6) as f32;
            for (x, y) in a.context.iter().zip(&b.context) {
                prop_assert!((x - y).abs() <= tolerance, "{} vs {}", x, y);
            }
            prop_assert!((a.target - b.target).abs() <= tolerance);
        }
    }
}
