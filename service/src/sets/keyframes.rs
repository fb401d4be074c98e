//! Keyframed decoding as clients ask for it: the `keyframes` option of REST decodes and
//! trajectory renders, and the `Keyframes` message of gRPC `Decode`, `StreamGaussians` and
//! `RenderTrajectory` (which `grpc` turns into a [`KeyframesSpec`]), checked against the limits
//! and turned into the engine's [`Keyframes`]. What the modes mean is `c4g_engine::keyframes`'.

use c4g_engine::Keyframes;
use serde::{Deserialize, Serialize};

use crate::ServiceError;

/// Keyframes as a client states them: exactly one of `every_s`, `count` and `tolerance`
/// (`{"every_s": 0.5}`, `{"count": 8}`, `{"tolerance": 0.005, "max": 64}`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeyframesSpec {
    /// A keyframe every this many seconds from the first requested time, and one at the last.
    pub every_s: Option<f64>,
    /// This many keyframes spread evenly over the requested times, both ends included.
    pub count: Option<usize>,
    /// Adaptive: the largest position error at a check, scene units.
    pub tolerance: Option<f64>,
    /// Adaptive: the largest colour or opacity error at a check.
    pub color_tolerance: Option<f64>,
    /// Adaptive: the most exact decodes, checks included.
    pub max: Option<usize>,
    /// Adaptive: no check (so no keyframe) closer than this many seconds to a keyframe.
    pub min_interval_s: Option<f64>,
}

/// The keyframes a request over `times` asks for (none: every time decoded exactly), checked:
/// one mode, values in range, and no more keyframes than `max_times` (`C4G_MAX_TIMES`) allows.
pub fn resolve(
    spec: Option<&KeyframesSpec>,
    times: &[f64],
    max_times: usize,
) -> Result<Keyframes, ServiceError> {
    let Some(spec) = spec else {
        return Ok(Keyframes::Exact);
    };
    let adaptive_only =
        spec.color_tolerance.is_some() || spec.max.is_some() || spec.min_interval_s.is_some();
    let keyframes = match (spec.every_s, spec.count, spec.tolerance) {
        (None, None, None) => {
            return Err(ServiceError::invalid(
                "keyframes needs one of \"every_s\" (seconds between keyframes), \"count\" \
                 (keyframes over the requested times) or \"tolerance\" (adaptive, scene units)",
            ));
        }
        (Some(_), Some(_), _) | (Some(_), _, Some(_)) | (_, Some(_), Some(_)) => {
            return Err(ServiceError::invalid(
                "keyframes takes one of \"every_s\", \"count\" and \"tolerance\", not several",
            ));
        }
        (None, None, Some(tolerance)) => adaptive(spec, tolerance, max_times)?,
        _ if adaptive_only => {
            return Err(ServiceError::invalid(
                "\"color_tolerance\", \"max\" and \"min_interval_s\" belong to adaptive \
                 keyframes: add a \"tolerance\"",
            ));
        }
        (Some(seconds), None, None) => {
            if !(seconds.is_finite() && seconds > 0.0) {
                return Err(ServiceError::invalid(format!(
                    "keyframes every_s must be a positive number of seconds, got {seconds}"
                )));
            }
            Keyframes::Every { seconds }
        }
        (None, Some(n), None) => {
            if n < 2 || n > max_times {
                return Err(ServiceError::invalid(format!(
                    "keyframes count must be between 2 (both ends of the range) and {max_times} \
                     (C4G_MAX_TIMES), got {n}"
                )));
            }
            Keyframes::Count { n }
        }
    };
    if let Keyframes::Every { seconds } = keyframes {
        let (start, end) = times
            .iter()
            .filter(|t| t.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &t| {
                (lo.min(t), hi.max(t))
            });
        if let Some(n) = keyframes.max_keyframes(start, end)
            && start <= end
            && n > max_times
        {
            return Err(ServiceError::invalid(format!(
                "keyframes every {seconds} s over {} s of requested times make {n} keyframes; at \
                 most {max_times} (C4G_MAX_TIMES): use a larger every_s",
                end - start
            )));
        }
    }
    keyframes.validate()?;
    Ok(keyframes)
}

fn adaptive(
    spec: &KeyframesSpec,
    tolerance: f64,
    max_times: usize,
) -> Result<Keyframes, ServiceError> {
    if !(tolerance.is_finite() && tolerance >= 0.0) {
        return Err(ServiceError::invalid(format!(
            "keyframes tolerance must be a finite, non-negative distance in scene units, got \
             {tolerance}"
        )));
    }
    if let Some(c) = spec.color_tolerance
        && !(c.is_finite() && c >= 0.0)
    {
        return Err(ServiceError::invalid(format!(
            "keyframes color_tolerance must be finite and non-negative, got {c}"
        )));
    }
    let default_max = Keyframes::DEFAULT_MAX_KEYFRAMES.min(max_times).max(2);
    let max_keyframes = spec.max.unwrap_or(default_max);
    if max_keyframes < 2 || max_keyframes > max_times.max(2) {
        return Err(ServiceError::invalid(format!(
            "keyframes max must be between 2 (both ends of the range) and {} (C4G_MAX_TIMES), \
             got {max_keyframes}",
            max_times.max(2)
        )));
    }
    let min_interval = spec.min_interval_s.unwrap_or(0.0);
    if !(min_interval.is_finite() && min_interval >= 0.0) {
        return Err(ServiceError::invalid(format!(
            "keyframes min_interval_s must be a finite, non-negative number of seconds, got \
             {min_interval}"
        )));
    }
    Ok(Keyframes::Adaptive {
        tolerance,
        color_tolerance: spec.color_tolerance,
        max_keyframes,
        min_interval,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use super::*;

    fn spec(json: &str) -> KeyframesSpec {
        serde_json::from_str(json).unwrap()
    }

    fn message(json: &str, times: &[f64]) -> String {
        resolve(Some(&spec(json)), times, 100)
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn each_mode_reads_from_its_json() {
        let times = [0.0, 1.0, 2.0];
        let resolve = |json: &str| resolve(Some(&spec(json)), &times, 100).unwrap();
        assert_eq!(
            resolve(r#"{"every_s": 0.5}"#),
            Keyframes::Every { seconds: 0.5 }
        );
        assert_eq!(resolve(r#"{"count": 8}"#), Keyframes::Count { n: 8 });
        assert_eq!(
            resolve(r#"{"tolerance": 0.005, "max": 16}"#),
            Keyframes::adaptive(0.005, 16)
        );
        assert_eq!(
            resolve(r#"{"tolerance": 0.01, "color_tolerance": 0.02, "min_interval_s": 0.1}"#),
            Keyframes::Adaptive {
                tolerance: 0.01,
                color_tolerance: Some(0.02),
                max_keyframes: 64,
                min_interval: 0.1
            }
        );
        assert_eq!(super::resolve(None, &times, 100).unwrap(), Keyframes::Exact);
        // The default maximum never exceeds the server's limit.
        assert_eq!(
            super::resolve(Some(&spec(r#"{"tolerance": 0.01}"#)), &times, 10).unwrap(),
            Keyframes::adaptive(0.01, 10)
        );
    }

    #[test]
    fn bad_options_are_refused_with_what_to_change() {
        let times = [0.0, 10.0];
        for (json, says) in [
            ("{}", "needs one of"),
            (r#"{"count": 4, "tolerance": 0.1}"#, "not several"),
            (r#"{"every_s": 1, "count": 4}"#, "not several"),
            (r#"{"count": 1}"#, "between 2"),
            (r#"{"count": 101}"#, "C4G_MAX_TIMES"),
            (r#"{"every_s": 0}"#, "positive"),
            (r#"{"every_s": -1}"#, "positive"),
            (r#"{"every_s": 0.01}"#, "1001 keyframes"),
            (r#"{"tolerance": -0.1}"#, "non-negative"),
            (r#"{"tolerance": 0.1, "max": 1}"#, "between 2"),
            (r#"{"tolerance": 0.1, "max": 1000}"#, "C4G_MAX_TIMES"),
            (
                r#"{"tolerance": 0.1, "color_tolerance": -1}"#,
                "color_tolerance",
            ),
            (
                r#"{"tolerance": 0.1, "min_interval_s": -1}"#,
                "min_interval_s",
            ),
            (r#"{"count": 4, "max": 8}"#, "belong to adaptive"),
        ] {
            let text = message(json, &times);
            assert!(text.contains(says), "{json}: {text}");
        }
        assert!(serde_json::from_str::<KeyframesSpec>(r#"{"counts": 4}"#).is_err());
        assert!(serde_json::from_str::<KeyframesSpec>(r#"{"count": -4}"#).is_err());
        let err = resolve(Some(&spec("{}")), &times, 100).unwrap_err();
        assert_eq!(err.kind(), crate::ServiceErrorKind::InvalidInput);
    }
}
