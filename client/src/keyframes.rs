//! Keyframed decoding, as requests carry it: the server decodes exact sets at keyframes only and
//! interpolates the sets between them per Gaussian (`docs/api.md`, "Keyframes"), so many times
//! cost a few decoder runs. A set that falls on a keyframe is exact.

use c4g_proto::v1 as proto;
use serde::{Deserialize, Serialize};

/// Where the server puts keyframes over a request's times; without one, every time is decoded
/// exactly. Serialises as the API's `keyframes` object (`{"every_s": 0.5}`, `{"count": 8}`,
/// `{"tolerance": 0.005, "max": 64}`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Keyframes {
    /// A keyframe every `seconds` from the first requested time, and one at the last.
    Every {
        /// Spacing, seconds.
        #[serde(rename = "every_s")]
        seconds: f64,
    },
    /// `count` keyframes spread evenly over the requested times, both ends included (≥ 2).
    Count {
        /// Number of keyframes.
        count: u32,
    },
    /// Keyframes placed by refinement until the interpolation is within `tolerance` at every
    /// interval's checks (the requested times nearest its thirds).
    Adaptive {
        /// Largest position error at a check, scene units (0: every time exact).
        tolerance: f64,
        /// Largest colour or opacity error at a check; `None`: positions only.
        #[serde(skip_serializing_if = "Option::is_none")]
        color_tolerance: Option<f64>,
        /// Most exact decodes, checks included (`None`: the server's default, 64).
        #[serde(skip_serializing_if = "Option::is_none")]
        max: Option<u32>,
        /// No check (so no keyframe) closer than this many seconds to a keyframe.
        #[serde(skip_serializing_if = "Option::is_none")]
        min_interval_s: Option<f64>,
    },
}

impl Keyframes {
    /// Adaptive keyframes within `tolerance` scene units, the server's other defaults.
    pub fn adaptive(tolerance: f64) -> Self {
        Self::Adaptive {
            tolerance,
            color_tolerance: None,
            max: None,
            min_interval_s: None,
        }
    }

    /// The gRPC message.
    pub fn to_proto(&self) -> proto::Keyframes {
        use proto::keyframes::Mode;
        let mode = match *self {
            Self::Every { seconds } => Mode::EveryS(seconds),
            Self::Count { count } => Mode::Count(count),
            Self::Adaptive {
                tolerance,
                color_tolerance,
                max,
                min_interval_s,
            } => Mode::Adaptive(proto::AdaptiveKeyframes {
                tolerance,
                color_tolerance,
                max: max.unwrap_or(0),
                min_interval_s: min_interval_s.unwrap_or(0.0),
            }),
        };
        proto::Keyframes { mode: Some(mode) }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use serde_json::json;

    use super::*;

    #[test]
    fn each_mode_is_the_apis_json_object() {
        let cases = [
            (Keyframes::Every { seconds: 0.5 }, json!({"every_s": 0.5})),
            (Keyframes::Count { count: 8 }, json!({"count": 8})),
            (Keyframes::adaptive(0.005), json!({"tolerance": 0.005})),
            (
                Keyframes::Adaptive {
                    tolerance: 0.01,
                    color_tolerance: Some(0.02),
                    max: Some(32),
                    min_interval_s: None,
                },
                json!({"tolerance": 0.01, "color_tolerance": 0.02, "max": 32}),
            ),
        ];
        for (keyframes, want) in cases {
            assert_eq!(serde_json::to_value(keyframes).unwrap(), want);
            assert_eq!(
                serde_json::from_value::<Keyframes>(want).unwrap(),
                keyframes
            );
        }
        let proto = Keyframes::adaptive(0.1).to_proto();
        assert_eq!(
            proto.mode,
            Some(proto::keyframes::Mode::Adaptive(proto::AdaptiveKeyframes {
                tolerance: 0.1,
                ..Default::default()
            }))
        );
    }
}
