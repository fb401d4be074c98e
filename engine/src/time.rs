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
//! # The stable policy (the default)
//! With `m = min(context)`, `M = max(context)`, `n` distinct context times and their mean spacing
//! `h = (M - m) / (n - 1)`:
//!
//! `rel(t) = (t - m) / max(target - m, h)`, computed in f64 and cast to f32,
//!
//! and every normalised time is 0 when the context is a single instant (`M == m`). Why this one:
//! - **It is the reference wherever the reference is sane.** For every target at least one mean
//!   spacing after the first frame the denominator is `target - m`, the reference's own. With
//!   frame indices as times (what the reference uses) the results are bit-identical, the
//!   reference's `+ 1e-8` vanishing in f32; with seconds they agree to float rounding (~1e-7
//!   relative). That covers every target the model was trained on except those in the first gap,
//!   so the model sees what it learned.
//! - **It cannot blow up.** In the first gap the denominator stops shrinking at `h`: the context
//!   times are spread over `[0, n - 1]` and the target over `[0, 1)`. No normalised time exceeds
//!   `n - 1` in magnitude, so sin/cos never see huge arguments.
//! - **It is continuous in the target** (the two branches of the `max` meet at `target = m + h`),
//!   so decoded Gaussians move smoothly as a client scrubs through time.
//! - **It ignores the order of the context times** (min, max and the distinct count do not care),
//!   so the same clip gives the same normalisation however its frames arrived; duplicates do not
//!   shrink the spacing.
//!
//! [`TimePolicy::Reference`] reproduces the reference bit for bit (computed in f32 as the
//! reference does) for parity tests against it.
//!
//! # What both policies refuse
//! An empty context, a NaN or infinite time, and a target outside `[m, M]`: the model interpolates
//! between context frames and was never trained to extrapolate, so the engine says so instead of
//! returning plausible-looking garbage. A span so wide that the arithmetic overflows is refused
//! too: every value handed to the decoder is finite.

use crate::{EngineError, Result};

/// How timestamps are normalised before they condition the decoder. See the module docs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum TimePolicy {
    /// The reference code's normalisation, bit for bit (f32 arithmetic). Blows up for targets
    /// near the first context frame; for parity tests.
    Reference,
    /// The reference's normalisation with the denominator floored at the mean spacing of the
    /// context times: bounded, continuous, order-independent.
    #[default]
    Stable,
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
    /// Normalises `context` for one `target`.
    pub fn normalize(self, context: &[f64], target: f64) -> Result<NormalizedTimes> {
        let span = Span::of(context)?;
        self.normalize_in(&span, context, target)
    }

    /// Normalises `context` once per target, in the order of `targets`.
    pub fn normalize_all(self, context: &[f64], targets: &[f64]) -> Result<Vec<NormalizedTimes>> {
        let span = Span::of(context)?;
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
        };
        let all_finite = times.target.is_finite() && times.context.iter().all(|v| v.is_finite());
        if all_finite {
            Ok(times)
        } else {
            Err(span.overflow())
        }
    }
}

/// What both policies need to know about the context times.
struct Span {
    first: f64,
    last: f64,
    distinct: usize,
}

impl Span {
    fn of(context: &[f64]) -> Result<Self> {
        if context.is_empty() {
            return Err(EngineError::EmptyContext);
        }
        if let Some(&value) = context.iter().find(|t| !t.is_finite()) {
            return Err(EngineError::NonFiniteTime {
                what: "context",
                value,
            });
        }
        let mut sorted: Vec<f64> = context.iter().map(|&t| canonical(t)).collect();
        sorted.sort_by(f64::total_cmp);
        sorted.dedup();
        Ok(Self {
            first: sorted[0],
            last: sorted[sorted.len() - 1],
            distinct: sorted.len(),
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

    #[test]
    fn stable_is_the_default() {
        assert_eq!(TimePolicy::default(), TimePolicy::Stable);
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
        for policy in [TimePolicy::Stable, TimePolicy::Reference] {
            let r = policy.normalize(&[5.0], 5.0).unwrap();
            assert_eq!(r.context, vec![0.0]);
            assert_eq!(r.target, 0.0);
        }
        let s = stable(&[3.0, 3.0, 3.0], 3.0);
        assert_eq!(s.context, vec![0.0; 3]);
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
    fn both_policies_refuse_to_extrapolate() {
        for policy in [TimePolicy::Stable, TimePolicy::Reference] {
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
    fn both_policies_refuse_empty_and_non_finite_input() {
        for policy in [TimePolicy::Stable, TimePolicy::Reference] {
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

    fn distinct(context: &[f64]) -> usize {
        let mut v: Vec<f64> = context.iter().map(|t| t + 0.0).collect();
        v.sort_by(f64::total_cmp);
        v.dedup();
        v.len()
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
        fn accepted_targets_lie_inside_the_context_span((context, target) in case()) {
            let accepted = TimePolicy::Stable.normalize(&context, target).is_ok();
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
            for policy in [TimePolicy::Stable, TimePolicy::Reference] {
                let a = policy.normalize(&context, target);
                let b = policy.normalize(&permuted, target);
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
    }
}
