//! The served model package, as `GET /v1/models` describes it.

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

/// One served model package. Fields the client does not name are kept in
/// [`extra`](Self::extra), so printing a model shows everything the server said.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Model {
    /// The package's name (`c4g-tiny`).
    pub name: String,
    /// The package's version.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub version: Option<String>,
    /// What the package is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    /// The model's input size (frames are resized to it; renders default to it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input: Option<InputSize>,
    /// Gaussians in every decoded set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gaussians_per_set: Option<u32>,
    /// Everything else the server reported.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// A width and height in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputSize {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}
