//! 4D exports (`POST /v1/clips/{id}/export`): a time range of a clip as one file other viewers
//! open: a zip of per-time `.ply` or `.spz` files, or a fitted `.splatv`.

use std::path::Path;

use bytes::Bytes;
use serde_json::json;

use crate::quality::served_scene;
use crate::{Approximation, Client, Error, Scene, Spacing};

/// The files an export can be.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExportFormat {
    /// A zip of per-time 3DGS `.ply` files (Brush plays these); `c4g_formats::frames_zip` reads it.
    PlyZip,
    /// A zip of per-time Niantic `.spz` files.
    SpzZip,
    /// One `.splatv` for splaTV-style web players, fitted from the sets (an approximation: see
    /// [`Export::fit_position_error`]).
    Splatv,
}

impl ExportFormat {
    /// The name the server knows the format by.
    pub fn name(self) -> &'static str {
        match self {
            Self::PlyZip => "ply_zip",
            Self::SpzZip => "spz_zip",
            Self::Splatv => "splatv",
        }
    }

    /// The format a file name asks for: `.ply.zip`, `.spz.zip` or `.splatv`.
    pub fn from_extension(path: &Path) -> Option<Self> {
        let name = path.file_name()?.to_str()?.to_ascii_lowercase();
        [
            (".ply.zip", Self::PlyZip),
            (".spz.zip", Self::SpzZip),
            (".splatv", Self::Splatv),
        ]
        .into_iter()
        .find(|(end, _)| name.ends_with(end))
        .map(|(_, format)| format)
    }
}

impl std::fmt::Display for ExportFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Which sets to export; every field defaults to the server's choice (the whole context span, at
/// the clip's frame rate, exact).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ExportOptions {
    /// First time, seconds.
    pub start: Option<f64>,
    /// Last time, seconds.
    pub end: Option<f64>,
    /// Spacing of the times.
    pub spacing: Option<Spacing>,
    /// A quality preset, keyframes, pruning (default: exact).
    pub approximation: Approximation,
}

/// An exported file.
#[derive(Debug, Clone)]
pub struct Export {
    /// The file's bytes.
    pub bytes: Bytes,
    /// Sets in the file (for `.splatv`, the sets it was fitted to).
    pub sets: usize,
    /// For `.splatv`: the fit's largest and RMS position error over those sets, scene units.
    pub fit_position_error: Option<(f64, f64)>,
    /// The scene the sets came from (`X-C4G-Scene`: feed-forward or fitted).
    pub scene: Option<Scene>,
}

impl Client {
    /// Exports the sets `options` ask of clip `clip_id` as one `format` file.
    pub async fn export(
        &self,
        clip_id: &str,
        format: ExportFormat,
        options: &ExportOptions,
    ) -> Result<Export, Error> {
        let url = self.url(&["v1", "clips", clip_id, "export"]);
        let mut body = json!(options.approximation);
        body["format"] = json!(format.name());
        for (key, value) in [("start", options.start), ("end", options.end)] {
            if let Some(value) = value {
                body[key] = json!(value);
            }
        }
        match options.spacing {
            Some(Spacing::Step(step)) => body["step"] = json!(step),
            Some(Spacing::Fps(fps)) => body["fps"] = json!(fps),
            None => {}
        }
        let response = self.send(self.http().post(url).json(&body)).await?;
        let header = |name: &str| {
            response
                .headers()
                .get(name)
                .and_then(|v| v.to_str().ok())
                .map(str::to_owned)
        };
        let sets = header("x-c4g-sets")
            .and_then(|v| v.parse().ok())
            .unwrap_or(0);
        let fit_position_error = header("x-c4g-fit-position-error").and_then(|v| parse_fit(&v));
        let scene = served_scene(response.headers());
        Ok(Export {
            bytes: response.bytes().await?,
            sets,
            fit_position_error,
            scene,
        })
    }
}

/// `max=…, rms=…` as the server states a fit's error.
fn parse_fit(value: &str) -> Option<(f64, f64)> {
    let mut max = None;
    let mut rms = None;
    for part in value.split(',') {
        let (key, number) = part.trim().split_once('=')?;
        let number: f64 = number.trim().parse().ok()?;
        match key {
            "max" => max = Some(number),
            "rms" => rms = Some(number),
            _ => {}
        }
    }
    Some((max?, rms?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_pick_the_format() {
        for (name, format) in [
            ("a/b.ply.zip", Some(ExportFormat::PlyZip)),
            ("B.SPZ.ZIP", Some(ExportFormat::SpzZip)),
            ("scene.splatv", Some(ExportFormat::Splatv)),
            ("scene.zip", None),
            ("scene.ply", None),
        ] {
            assert_eq!(
                ExportFormat::from_extension(Path::new(name)),
                format,
                "{name}"
            );
        }
    }

    #[test]
    fn the_fit_header_parses() {
        assert_eq!(parse_fit("max=1.5e-3, rms=2e-4"), Some((1.5e-3, 2e-4)));
        assert_eq!(parse_fit("max=1"), None);
        assert_eq!(parse_fit("nonsense"), None);
    }
}
