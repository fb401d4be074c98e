//! Contributions and pruning (`c4g_analysis::pruning`), against what they claim:
//! - the contributions of one render sum to its alpha summed over the pixels (every pixel's
//!   weights add up to 1 − transmittance): 1e-3 relative, f32 sums of ~10⁴ terms;
//! - removing one Gaussian changes a render's summed absolute difference, per channel, by no more
//!   than its contribution (colours and background in [0, 1]); slack 1e-3 pixels plus 1e-4 per
//!   pixel for the transmittance floor's early stop, which the bound does not cover;
//! - a hidden or transparent Gaussian is pruned and its removal changes nothing visible;
//! - the extremes: all but one Gaussian pruned, an empty set, a scene that does not move.
#![allow(clippy::unwrap_used, clippy::expect_used)]

// The renderer's test helpers (fixture scenes, cameras, random sets), shared rather than copied.
#[path = "../../renderer/tests/common/mod.rs"]
mod common;

use c4g_analysis::pruning::{PruneOptions, SceneAnalysis};
use c4g_renderer::{CpuRasterizer, Image, Rasterizer, RenderOptions};
use c4g_scene::GaussianSet;
use common::*;

fn summed_difference(a: &Image, b: &Image) -> [f32; 3] {
    let mut sums = [0.0f32; 3];
    for (pa, pb) in a.rgb.chunks_exact(3).zip(b.rgb.chunks_exact(3)) {
        for c in 0..3 {
            sums[c] += (pa[c] - pb[c]).abs();
        }
    }
    sums
}

fn without(set: &GaussianSet, index: usize) -> GaussianSet {
    let keep: Vec<bool> = (0..set.len()).map(|i| i != index).collect();
    set.select(&keep).unwrap()
}

#[test]
fn contributions_sum_to_the_rendered_alpha() {
    let rasterizer = CpuRasterizer::new();
    let camera = camera(96, 64, 80.0);
    for seed in 0..4 {
        let set = random_set(200, seed, 1.0, 0.08);
        let (image, contributions) = rasterizer
            .render_with_contributions(&set, &camera, &RenderOptions::default())
            .unwrap();
        assert_eq!(contributions.len(), set.len());
        assert!(contributions.iter().all(|c| c.is_finite() && *c >= 0.0));
        let total: f32 = contributions.iter().sum();
        let alpha: f32 = image.alpha.iter().sum();
        assert!(
            (total - alpha).abs() <= 1e-3 * alpha.max(1.0),
            "seed {seed}: contributions {total}, alpha {alpha}"
        );
        // The image itself is the plain render's.
        assert_eq!(
            image,
            rasterizer
                .render(&set, &camera, &RenderOptions::default())
                .unwrap()
        );
    }
}

#[test]
fn removing_a_gaussian_changes_a_render_by_at_most_its_contribution() {
    let rasterizer = CpuRasterizer::new();
    let camera = camera(64, 48, 60.0);
    let options = RenderOptions {
        background: [0.3, 0.6, 0.9],
        ..RenderOptions::default()
    };
    let pixels = 64.0 * 48.0;
    for seed in 0..3 {
        let set = random_set(60, 100 + seed, 1.0, 0.12);
        let (full, contributions) = rasterizer
            .render_with_contributions(&set, &camera, &options)
            .unwrap();
        for index in (0..set.len()).step_by(7) {
            let image = rasterizer
                .render(&without(&set, index), &camera, &options)
                .unwrap();
            let bound = contributions[index] + 1e-3 + 1e-4 * pixels;
            for (c, change) in summed_difference(&full, &image).into_iter().enumerate() {
                assert!(
                    change <= bound,
                    "seed {seed}, Gaussian {index}, channel {c}: changed by {change}, bound {bound}"
                );
            }
        }
    }
}

#[test]
fn hidden_and_transparent_gaussians_are_pruned_and_nothing_visible_changes() {
    // An opaque wall at depth 2 hides a Gaussian at depth 4 behind it; one more is transparent;
    // one is outside the view.
    let set = set_of(&[
        ([0.0, 0.0, 2.0], [2.0, 2.0, 0.05], 0.999, [0.8, 0.2, 0.2]),
        ([0.0, 0.0, 4.0], [0.1, 0.1, 0.1], 0.9, [0.1, 0.9, 0.1]),
        ([0.2, 0.1, 3.0], [0.1, 0.1, 0.1], 0.001, [0.1, 0.1, 0.9]),
        ([50.0, 0.0, 3.0], [0.1, 0.1, 0.1], 0.9, [0.9, 0.9, 0.9]),
    ]);
    let cameras = [camera(48, 48, 40.0)];
    let rasterizer = CpuRasterizer::new();
    let options = RenderOptions::default();
    let analysis =
        SceneAnalysis::measure(std::slice::from_ref(&set), &cameras, &rasterizer, &options)
            .unwrap();
    let prune = PruneOptions::default();
    assert_eq!(analysis.keep(&prune), [true, false, false, false]);
    assert!(analysis.dropped_contribution(&prune) < prune.contribution_floor * 3.0);
    let pruned = set.select(&analysis.keep(&prune)).unwrap();
    let (a, b) = (
        rasterizer.render(&set, &cameras[0], &options).unwrap(),
        rasterizer.render(&pruned, &cameras[0], &options).unwrap(),
    );
    let change = summed_difference(&a, &b);
    assert!(
        change
            .iter()
            .all(|&c| c <= analysis.dropped_contribution(&prune) + 1e-3),
        "{change:?}"
    );
}

#[test]
fn the_extremes_all_but_one_pruned_an_empty_set_and_a_static_scene() {
    let rasterizer = CpuRasterizer::new();
    let cameras = [camera(32, 32, 30.0)];
    let options = RenderOptions::default();
    // All but one: every other Gaussian has opacity 0.
    let mut gaussians = vec![([0.0, 0.0, 3.0], [0.3, 0.3, 0.3], 0.8, [1.0, 1.0, 1.0])];
    gaussians.extend((0..9).map(|i| ([0.1 * i as f32, 0.0, 3.0], [0.2, 0.2, 0.2], 0.0, [0.5; 3])));
    let set = set_of(&gaussians);
    let analysis =
        SceneAnalysis::measure(&[set.clone(), set.clone()], &cameras, &rasterizer, &options)
            .unwrap();
    let keep = analysis.keep(&PruneOptions::default());
    assert_eq!(keep.iter().filter(|k| **k).count(), 1);
    assert!(keep[0]);
    assert_eq!(analysis.renders, 2);
    // The same set twice: nothing moves at any tolerance, even 0.
    assert!(analysis.moving(0.0).iter().all(|m| !m));
    // An empty set analyses to nothing.
    let empty =
        SceneAnalysis::measure(&[GaussianSet::default()], &cameras, &rasterizer, &options).unwrap();
    assert!(empty.keep(&PruneOptions::default()).is_empty());
    // Sets of different sizes are not one clip's, and an analysis needs sets and cameras.
    assert!(
        SceneAnalysis::measure(
            &[set.clone(), GaussianSet::default()],
            &cameras,
            &rasterizer,
            &options
        )
        .is_err()
    );
    assert!(SceneAnalysis::measure(&[], &cameras, &rasterizer, &options).is_err());
    assert!(SceneAnalysis::measure(&[set], &[], &rasterizer, &options).is_err());
}

#[test]
fn motion_is_the_largest_distance_from_the_first_time() {
    let at = |x: f32| {
        set_of(&[
            ([x, 0.0, 3.0], [0.2; 3], 0.8, [1.0; 3]),
            ([0.0, 0.5, 3.0], [0.2; 3], 0.8, [1.0; 3]),
        ])
    };
    let analysis = SceneAnalysis::measure(
        &[at(0.0), at(0.3), at(0.1)],
        &[camera(32, 32, 30.0)],
        &CpuRasterizer::new(),
        &RenderOptions::default(),
    )
    .unwrap();
    assert!((analysis.motion[0] - 0.3).abs() < 1e-6);
    assert_eq!(analysis.motion[1], 0.0);
    assert_eq!(analysis.moving(0.1), [true, false]);
}

#[test]
fn selecting_keeps_order_and_feature_rows() {
    let set = random_set(5, 7, 1.0, 0.1)
        .with_features(
            c4g_scene::FeatureBlock::new(2, (0..10).map(|v| v as f32).collect()).unwrap(),
        )
        .unwrap();
    let picked = set.select(&[true, false, true, false, true]).unwrap();
    assert_eq!(picked.len(), 3);
    assert_eq!(picked.positions()[1], set.positions()[2]);
    assert_eq!(
        picked.features().unwrap().values(),
        &[0.0, 1.0, 4.0, 5.0, 8.0, 9.0]
    );
    assert!(set.select(&[true]).is_err());
}
