//! Decoding Gaussians at times (`POST /v1/clips/{id}/gaussians`): parsed into
//! [`GaussianSet`]s, or the server's bytes in any of its formats.

use std::fmt;
use std::str::FromStr;

use bytes::Bytes;
use c4g_scene::GaussianSet;
use reqwest::header::ACCEPT;
use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::{Approximation, Client, Error, wire};

/// The Gaussians of a clip at one time.
#[derive(Debug, Clone, PartialEq)]
pub struct GaussianFrame {
    /// Media time, seconds.
    pub time: f64,
    /// The scene at that time, in the canonical layout.
    pub gaussians: GaussianSet,
}

/// Float width of the values in a Gaussian payload: the renderer's `C4GS` codec's, so both ends
/// name it alike. Half precision halves the bytes on the wire at about three decimal digits,
/// plenty for viewing; the values arrive here as `f32` either way.
pub use c4g_formats::c4gs::Precision;

/// The formats `POST /v1/clips/{id}/gaussians` answers in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GaussianFormat {
    /// `{"frames": [{"t", "count", "means", ...}]}`.
    Json,
    /// The little-endian `C4GS` layout ([`wire::parse_binary`]).
    Binary,
    /// The 3DGS PLY layout; one time only.
    Ply,
    /// antimatter15's 32-byte rows; one time only.
    Splat,
}

impl GaussianFormat {
    /// The API's name (`json`, `binary`, `ply`, `splat`).
    pub fn as_str(self) -> &'static str {
        match self {
            GaussianFormat::Json => "json",
            GaussianFormat::Binary => "binary",
            GaussianFormat::Ply => "ply",
            GaussianFormat::Splat => "splat",
        }
    }

    /// The media type the server answers with.
    pub fn content_type(self) -> &'static str {
        match self {
            GaussianFormat::Json => "application/json",
            GaussianFormat::Binary => wire::BINARY_CONTENT_TYPE,
            GaussianFormat::Ply => "application/x-ply",
            GaussianFormat::Splat => "application/x-splat",
        }
    }

    /// The format a file name's extension names: `.json`, `.ply`, `.splat`, and `.c4gs` or
    /// `.bin` for binary.
    pub fn from_extension(path: &std::path::Path) -> Option<Self> {
        let extension = path.extension()?.to_str()?.to_ascii_lowercase();
        match extension.as_str() {
            "json" => Some(GaussianFormat::Json),
            "c4gs" | "bin" => Some(GaussianFormat::Binary),
            "ply" => Some(GaussianFormat::Ply),
            "splat" => Some(GaussianFormat::Splat),
            _ => None,
        }
    }
}

impl fmt::Display for GaussianFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for GaussianFormat {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self, Error> {
        match s {
            "json" => Ok(GaussianFormat::Json),
            "binary" => Ok(GaussianFormat::Binary),
            "ply" => Ok(GaussianFormat::Ply),
            "splat" => Ok(GaussianFormat::Splat),
            other => Err(Error::InvalidInput(format!(
                "unknown Gaussian format {other:?} (json, binary, ply or splat)"
            ))),
        }
    }
}

impl Client {
    /// The Gaussians of a clip at `times` (seconds, inside the context span), one frame per time
    /// in the server's order. Fetched in the binary format and parsed, so `f16` halves the
    /// transfer without changing what the caller gets.
    pub async fn gaussians(
        &self,
        clip_id: &str,
        times: &[f64],
        precision: Precision,
    ) -> Result<Vec<GaussianFrame>, Error> {
        self.gaussians_approximated(clip_id, times, precision, &Approximation::default())
            .await
    }

    /// [`gaussians`](Self::gaussians), approximated as `approximation` asks (a quality preset,
    /// keyframes, pruning; the default is exact).
    pub async fn gaussians_approximated(
        &self,
        clip_id: &str,
        times: &[f64],
        precision: Precision,
        approximation: &Approximation,
    ) -> Result<Vec<GaussianFrame>, Error> {
        let bytes = self
            .decode_request(
                clip_id,
                times,
                GaussianFormat::Binary,
                precision,
                approximation,
                false,
            )
            .await?;
        wire::parse_binary(&bytes)
    }

    /// The server's bytes for the Gaussians at `times`, in `format` (values in `f32`). PLY and
    /// `.splat` hold one time only.
    pub async fn gaussians_raw(
        &self,
        clip_id: &str,
        times: &[f64],
        format: GaussianFormat,
    ) -> Result<Bytes, Error> {
        self.gaussians_raw_approximated(clip_id, times, format, &Approximation::default())
            .await
    }

    /// [`gaussians_raw`](Self::gaussians_raw), approximated as `approximation` asks.
    pub async fn gaussians_raw_approximated(
        &self,
        clip_id: &str,
        times: &[f64],
        format: GaussianFormat,
        approximation: &Approximation,
    ) -> Result<Bytes, Error> {
        self.decode_request(clip_id, times, format, Precision::F32, approximation, false)
            .await
    }

    /// The Gaussians at `times` with each one's lifted feature vector
    /// ([`GaussianSet::features`]): a package with a feature decoder only (others answer 422
    /// `unsupported`).
    pub async fn gaussians_with_features(
        &self,
        clip_id: &str,
        times: &[f64],
        precision: Precision,
        approximation: &Approximation,
    ) -> Result<Vec<GaussianFrame>, Error> {
        let bytes = self
            .decode_request(
                clip_id,
                times,
                GaussianFormat::Binary,
                precision,
                approximation,
                true,
            )
            .await?;
        wire::parse_binary(&bytes)
    }

    /// [`gaussians_raw_approximated`](Self::gaussians_raw_approximated) with each Gaussian's lifted
    /// feature vector (JSON `features`, `C4GS` version 2, `.ply` `feat_*` properties; `.splat`
    /// has no room for them and is refused).
    pub async fn gaussians_raw_with_features(
        &self,
        clip_id: &str,
        times: &[f64],
        format: GaussianFormat,
        approximation: &Approximation,
    ) -> Result<Bytes, Error> {
        self.decode_request(clip_id, times, format, Precision::F32, approximation, true)
            .await
    }

    async fn decode_request(
        &self,
        clip_id: &str,
        times: &[f64],
        format: GaussianFormat,
        precision: Precision,
        approximation: &Approximation,
        features: bool,
    ) -> Result<Bytes, Error> {
        let url = self.url(&["v1", "clips", clip_id, "gaussians"]);
        let mut body = json!(approximation);
        body["times"] = json!(times);
        body["format"] = json!(format);
        body["precision"] = json!(precision);
        if features {
            body["features"] = json!(true);
        }
        let request = self
            .http()
            .post(url)
            .header(ACCEPT, format.content_type())
            .json(&body);
        Ok(self.send(request).await?.bytes().await?)
    }
}
