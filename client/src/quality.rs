//! How a request trades accuracy for speed (`docs/api.md`, "Quality"): a named preset, and the
//! knobs it stands for, keyframes and pruning, which a request may set itself (an explicit knob
//! overrides the preset's). The default everywhere is exact: what the model computes.

use c4g_proto::v1 as proto;
use serde::{Deserialize, Serialize};

use crate::Keyframes;

/// A named point of the speed/accuracy trade, as `docs/tradeoffs.md` measures them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Quality {
    /// Every set decoded exactly, every Gaussian.
    #[default]
    Exact,
    /// Adaptive keyframes at a tight tolerance and light pruning: within 0.1 dB of exact on the
    /// measured scenes.
    Balanced,
    /// Looser keyframes and pruning: within 0.5 dB of exact on the measured scenes.
    Fast,
}

impl Quality {
    /// The gRPC enum value.
    pub fn to_proto(self) -> proto::Quality {
        match self {
            Self::Exact => proto::Quality::Exact,
            Self::Balanced => proto::Quality::Balanced,
            Self::Fast => proto::Quality::Fast,
        }
    }
}

/// Which scene serves a request (`docs/api.md`, "Fitting"): `Auto` (the server's default) is the
/// clip's fitted scene when it has one and nothing asks for an approximation, else the
/// feed-forward one.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum Scene {
    /// The fitted scene when there is one, else the feed-forward one.
    #[default]
    #[serde(rename = "auto")]
    Auto,
    /// The model's answer.
    #[serde(rename = "feed-forward")]
    FeedForward,
    /// The clip's fitted scene (refused when it has none).
    #[serde(rename = "fitted")]
    Fitted,
}

impl Scene {
    /// The name requests and answers use.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::FeedForward => "feed-forward",
            Self::Fitted => "fitted",
        }
    }

    /// The scene named `name` (as requests and the `X-C4G-Scene` header name them).
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Auto, Self::FeedForward, Self::Fitted]
            .into_iter()
            .find(|scene| scene.name() == name)
    }
}

/// The scene an answer says served it (`X-C4G-Scene`; `None` from a server that does not say).
pub(crate) fn served_scene(headers: &reqwest::header::HeaderMap) -> Option<Scene> {
    Scene::from_name(headers.get("x-c4g-scene")?.to_str().ok()?)
}

/// Drop the Gaussians that change nothing visible: measured once per clip by the server, the
/// same Gaussians at every time. `Prune::default()` takes the server's floors.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Prune {
    /// Largest summed blending weight, in pixels, of a dropped Gaussian in any analysed view
    /// (server default 0.5).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub contribution_px: Option<f32>,
    /// Largest opacity of a dropped Gaussian at any analysed time (server default 1/255).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opacity: Option<f32>,
    /// Also drop the pruned Gaussians' query tokens from the decoder itself (server default
    /// false): cheaper decodes, but the kept Gaussians change (queries attend to each other).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drop_queries: Option<bool>,
}

impl Prune {
    /// The gRPC message.
    pub fn to_proto(&self) -> proto::Prune {
        proto::Prune {
            contribution_px: self.contribution_px,
            opacity: self.opacity,
            drop_queries: self.drop_queries,
        }
    }
}

/// The trade a request asks for; every field unset (the default) is exact. Serialises as the
/// request fields `quality`, `keyframes` and `prune`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Approximation {
    /// A named preset.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub quality: Option<Quality>,
    /// Keyframes, overriding the preset's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub keyframes: Option<Keyframes>,
    /// Pruning, overriding the preset's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub prune: Option<Prune>,
    /// Which scene (the server's default: auto).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scene: Option<Scene>,
}

impl Approximation {
    /// The preset `quality`, nothing overridden.
    pub fn preset(quality: Quality) -> Self {
        Self {
            quality: Some(quality),
            ..Self::default()
        }
    }

    /// Only `keyframes`.
    pub fn keyframes(keyframes: Keyframes) -> Self {
        Self {
            keyframes: Some(keyframes),
            ..Self::default()
        }
    }

    /// The gRPC `quality` value (unspecified: the server's default, exact).
    pub fn proto_quality(&self) -> i32 {
        self.quality
            .map_or(proto::Quality::Unspecified, Quality::to_proto)
            .into()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn serialises_as_the_request_fields() {
        assert_eq!(
            serde_json::to_value(Approximation::default()).unwrap(),
            json!({})
        );
        let approximation = Approximation {
            quality: Some(Quality::Fast),
            keyframes: Some(Keyframes::Count { count: 4 }),
            prune: Some(Prune {
                contribution_px: Some(1.0),
                drop_queries: Some(true),
                opacity: None,
            }),
            scene: Some(Scene::FeedForward),
        };
        assert_eq!(
            serde_json::to_value(approximation).unwrap(),
            json!({"quality": "fast", "keyframes": {"count": 4}, "prune": {"contribution_px": 1.0, "drop_queries": true}, "scene": "feed-forward"})
        );
        assert_eq!(approximation.proto_quality(), proto::Quality::Fast as i32);
    }

    #[test]
    fn scenes_are_read_back_by_the_names_they_are_sent_as() {
        for scene in [Scene::Auto, Scene::FeedForward, Scene::Fitted] {
            assert_eq!(Scene::from_name(scene.name()), Some(scene));
            assert_eq!(
                serde_json::to_value(scene).unwrap(),
                json!(scene.name()),
                "{scene:?}"
            );
        }
        assert_eq!(Scene::from_name("feedforward"), None);
    }
}
