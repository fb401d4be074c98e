//! Which scene serves a request: the feed-forward one (the model's answer, decoded from the
//! clip's features) or the fitted one (what a fit job made of the clip's own frames, kept with
//! the clip: [`crate::clips::fitted`]).
//!
//! Every request that takes sets (decodes, renders, paths, streams, exports, tracks, segments)
//! names one as `"scene"`: `auto` (the default) serves the fitted scene when the clip has one and
//! the request asks for what it can serve, `feed-forward` and `fitted` ask outright. The fitted
//! scene is already keyframes, carries no lifted features and is the whole scene the fit kept,
//! so a request that asks for a quality preset, keyframes, pruning or features gets the
//! feed-forward scene under `auto`, and is refused with `fitted`. The edge resolves the choice
//! once ([`SetSource::resolve_scene`](crate::sets::SetSource::resolve_scene)) and says which scene
//! served (REST `X-C4G-Scene`, a gRPC field), so the answer and its label cannot disagree.

use serde::{Deserialize, Serialize};

/// A request's choice of scene.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Scene {
    /// The fitted scene when there is one and the request can be served from it, else the
    /// feed-forward one.
    #[default]
    #[serde(rename = "auto")]
    Auto,
    /// The model's answer.
    #[serde(rename = "feed-forward")]
    FeedForward,
    /// The fitted scene (refused when the clip has none).
    #[serde(rename = "fitted")]
    Fitted,
}

impl Scene {
    /// The name requests and answers use.
    pub fn name(self) -> &'static str {
        match self {
            Scene::Auto => "auto",
            Scene::FeedForward => "feed-forward",
            Scene::Fitted => "fitted",
        }
    }

    /// The choice named `name`, or a message listing the names.
    pub fn parse(name: &str) -> Result<Self, String> {
        match name {
            "" | "auto" => Ok(Scene::Auto),
            "feed-forward" => Ok(Scene::FeedForward),
            "fitted" => Ok(Scene::Fitted),
            other => Err(format!(
                "scene must be \"auto\", \"feed-forward\" or \"fitted\", got {}",
                crate::quoted(other)
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn names_round_trip_through_serde_and_parse() {
        for scene in [Scene::Auto, Scene::FeedForward, Scene::Fitted] {
            let json = serde_json::to_string(&scene).unwrap();
            assert_eq!(json, format!("\"{}\"", scene.name()));
            assert_eq!(serde_json::from_str::<Scene>(&json).unwrap(), scene);
            assert_eq!(Scene::parse(scene.name()).unwrap(), scene);
        }
        assert_eq!(Scene::parse("").unwrap(), Scene::Auto);
        assert!(
            Scene::parse("feedforward")
                .unwrap_err()
                .contains("feed-forward")
        );
    }
}
