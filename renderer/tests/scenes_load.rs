//! The fixture scenes load into the renderer's types and compare equal to themselves.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_scene::Footprint;
use common::*;

#[test]
fn every_fixture_scene_loads_with_consistent_shapes() {
    for name in SCENES.into_iter().chain(SCENES_3DGS) {
        let s = load_scene(name);
        let (w, h) = (s.camera.width() as usize, s.camera.height() as usize);
        assert_eq!(s.expected.rgb.len(), w * h * 3, "{name}");
        assert_eq!(s.expected.alpha.len(), w * h, "{name}");
        assert!(!s.gaussians.is_empty(), "{name}");
        if let (Some(img), Some(block)) = (&s.expected.features, s.gaussians.features()) {
            assert_eq!(img.channels, block.width(), "{name}");
            assert_eq!(img.values.len(), w * h * img.channels, "{name}");
        }
        let footprint = if name.ends_with("-3dgs") {
            Footprint::Tiles3dgs
        } else {
            Footprint::Ellipse
        };
        assert_eq!(s.options.footprint, footprint, "{name}");
        let d = compare(&s.expected, &s.expected);
        assert_eq!(d.rgb_max_abs, 0.0);
        assert_eq!(d.features_max_abs, 0.0);
    }
}
