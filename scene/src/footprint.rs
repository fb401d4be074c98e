//! Which pixels a Gaussian reaches: the one rasterization choice a model package declares
//! (`rasterizer.footprint` in `model.json`), so it belongs to the scene's vocabulary and not to a
//! rasterizer. The rules themselves are written out in `c4g_renderer::raster`.

use serde::{Deserialize, Serialize};

/// Which pixels a Gaussian is evaluated at (the rules are in `c4g_renderer::raster`'s documentation).
///
/// In `model.json` and on the command line: `"ellipse"`, `"3dgs"`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
pub enum Footprint {
    /// The pixels within 3 sigma (Mahalanobis distance ≤ `c4g_renderer::raster::SIGMA_EXTENT`):
    /// gsplat's rule and the renderer's default, what c4g-tiny was trained with.
    #[default]
    #[serde(rename = "ellipse")]
    Ellipse,
    /// Every pixel of the 16×16 tiles that the original 3DGS rasterizer's square of radius
    /// `⌈3√λmax⌉` reaches: what the public C4G code renders (and trained) with.
    #[serde(rename = "3dgs")]
    Tiles3dgs,
}

impl Footprint {
    /// The name in `model.json` and on the command line.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ellipse => "ellipse",
            Self::Tiles3dgs => "3dgs",
        }
    }
}

impl std::fmt::Display for Footprint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}
