//! Which source frames become context frames: those in the window, then either every
//! `stride`-th or `max_frames` spread evenly (first and last always included).

use super::media::IntakeOptions;
use crate::ServiceError;
use crate::config::Limits;

/// Indices into `times` (increasing) of the context frames `options` ask for.
pub fn select(
    times: &[f64],
    options: &IntakeOptions,
    limits: &Limits,
) -> Result<Vec<usize>, ServiceError> {
    let window = window(times, options);
    if window.is_empty() {
        let last = times.last().copied().unwrap_or(0.0);
        return Err(ServiceError::invalid(format!(
            "no frames in the window [{}, {}]: the clip's frames span [0, {last:.3}] s",
            options.start.unwrap_or(0.0),
            options.end.unwrap_or(last),
        )));
    }
    if let Some(stride) = options.stride {
        let picked: Vec<usize> = window.iter().copied().step_by(stride.max(1)).collect();
        let cap = options.max_frames.unwrap_or(limits.max_context_frames);
        if picked.len() > cap {
            return Err(ServiceError::invalid(format!(
                "stride {stride} picks {} frames; at most {cap} context frames are allowed: \
                 raise the stride or narrow the window",
                picked.len()
            )));
        }
        return Ok(picked);
    }
    let wanted = options
        .max_frames
        .unwrap_or(limits.context_frames)
        .min(window.len());
    Ok(spread(&window, wanted))
}

/// Indices into `times` (increasing) of the frames inside the options' window.
pub fn window(times: &[f64], options: &IntakeOptions) -> Vec<usize> {
    let start = options.start.unwrap_or(f64::NEG_INFINITY);
    let end = options.end.unwrap_or(f64::INFINITY);
    (0..times.len())
        .filter(|&i| start <= times[i] && times[i] <= end)
        .collect()
}

/// `k` of `items` spread evenly, the first and the last included.
fn spread(items: &[usize], k: usize) -> Vec<usize> {
    if k <= 1 || items.len() <= 1 {
        return items.iter().copied().take(k.max(1)).collect();
    }
    let n = items.len();
    let mut picked: Vec<usize> = (0..k)
        .map(|i| items[(i * (n - 1) + (k - 1) / 2) / (k - 1)])
        .collect();
    picked.dedup();
    picked
}

#[cfg(test)]
mod tests {
    use super::*;

    fn times(n: usize) -> Vec<f64> {
        (0..n).map(|i| i as f64 / 10.0).collect()
    }

    #[test]
    fn spreads_evenly_with_both_ends() {
        let limits = Limits::default();
        let options = IntakeOptions {
            max_frames: Some(4),
            ..Default::default()
        };
        assert_eq!(
            select(&times(10), &options, &limits).unwrap(),
            vec![0, 3, 6, 9]
        );
        assert_eq!(select(&times(3), &options, &limits).unwrap(), vec![0, 1, 2]);
        let one = IntakeOptions {
            max_frames: Some(1),
            ..Default::default()
        };
        assert_eq!(select(&times(10), &one, &limits).unwrap(), vec![0]);
    }

    #[test]
    fn windows_and_strides() {
        let limits = Limits::default();
        let options = IntakeOptions {
            start: Some(0.25),
            end: Some(0.75),
            stride: Some(2),
            ..Default::default()
        };
        assert_eq!(
            select(&times(10), &options, &limits).unwrap(),
            vec![3, 5, 7]
        );
        let empty = IntakeOptions {
            start: Some(5.0),
            ..Default::default()
        };
        assert!(select(&times(10), &empty, &limits).is_err());
        let too_many = IntakeOptions {
            stride: Some(1),
            max_frames: Some(4),
            ..Default::default()
        };
        assert!(select(&times(10), &too_many, &limits).is_err());
    }
}
