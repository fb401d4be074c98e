//! The time policies on any context and target: every policy either refuses (an input error) or
//! hands the decoder finite times, and the bounded policies stay within their stated bounds
//! (`engine/src/time.rs`). Input: little-endian `f64`s: frame step, target, then context times.

use c4g_engine::TimePolicy;

/// Any context and target through every time policy.
pub fn time_policy(input: &[u8]) -> Result<(), String> {
    let values: Vec<f64> = input
        .chunks_exact(8)
        .map(|c| {
            let mut bytes = [0u8; 8];
            bytes.copy_from_slice(c);
            f64::from_le_bytes(bytes)
        })
        .collect();
    let [step, target, context @ ..] = values.as_slice() else {
        return Ok(());
    };
    let step = (*step != 0.0).then_some(*step);
    for policy in TimePolicy::ALL {
        let Ok(times) = policy.normalize_with_step(context, step, *target) else {
            continue;
        };
        if times.context.len() != context.len() {
            return Err(format!(
                "{policy}: {} context times in, {} out",
                context.len(),
                times.context.len()
            ));
        }
        if !(times.target.is_finite() && times.context.iter().all(|v| v.is_finite())) {
            return Err(format!("{policy}: a time is not finite"));
        }
        if policy == TimePolicy::Reference {
            continue;
        }
        // Bounded: the target in [0, 1] and no context time past the span over the floor.
        if !(0.0..=1.0).contains(&times.target) {
            return Err(format!("{policy}: target {}", times.target));
        }
        let (m, big_m) = context
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &t| {
                (lo.min(t), hi.max(t))
            });
        let mut distinct: Vec<f64> = context.to_vec();
        distinct.sort_by(f64::total_cmp);
        distinct.dedup();
        let floor = match (policy, step) {
            (TimePolicy::FrameStep, Some(s)) => s,
            (TimePolicy::FrameStep, None) => distinct
                .windows(2)
                .map(|w| w[1] - w[0])
                .fold(f64::INFINITY, f64::min),
            _ => (big_m - m) / (distinct.len().max(2) - 1) as f64,
        };
        if floor.is_finite() && floor > 0.0 {
            let bound = ((big_m - m) / floor).max(1.0) * (1.0 + 1e-6);
            for &v in &times.context {
                if !(f64::from(v) >= -1e-6 && f64::from(v) <= bound) {
                    return Err(format!("{policy}: {v} > {bound}"));
                }
            }
        }
    }
    Ok(())
}
