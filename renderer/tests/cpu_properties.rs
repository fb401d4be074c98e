//! Invariants of the CPU rasterizer over random scenes (proptest).
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_renderer::{CpuRasterizer, Image, Rasterizer, RenderOptions};
use c4g_scene::{FeatureBlock, GaussianSet};
use common::*;
use proptest::prelude::*;

fn render(set: &GaussianSet, options: &RenderOptions) -> Image {
    CpuRasterizer::new()
        .render(set, &camera(48, 40, 40.0), options)
        .unwrap()
}

/// A random scene: `n` Gaussians with 3 feature channels.
fn scene(n: usize, seed: u64) -> GaussianSet {
    let set = random_set(n, seed, 1.2, 0.15);
    let mut rng = SplitMix(seed ^ 0xFEA7);
    let features = (0..n * 3).map(|_| rng.unit() * 2.0 - 1.0).collect();
    set.with_features(FeatureBlock::new(3, features).unwrap())
        .unwrap()
}

/// `set` with its Gaussians in the order `perm` (a permutation of its indices).
fn permuted(set: &GaussianSet, perm: &[usize]) -> GaussianSet {
    let pick3 = |v: &[[f32; 3]]| perm.iter().map(|&i| v[i]).collect::<Vec<_>>();
    let features = set.features().unwrap();
    let rows = perm
        .iter()
        .flat_map(|&i| features.row(i).unwrap().to_vec())
        .collect();
    GaussianSet::new(
        pick3(set.positions()),
        pick3(set.scales()),
        perm.iter().map(|&i| set.rotations()[i]).collect(),
        perm.iter().map(|&i| set.opacities()[i]).collect(),
        pick3(set.colors()),
    )
    .unwrap()
    .with_features(FeatureBlock::new(features.width(), rows).unwrap())
    .unwrap()
}

fn options(background: [f32; 3]) -> RenderOptions {
    RenderOptions {
        background,
        ..RenderOptions::default()
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn the_same_input_renders_the_same_image(n in 0usize..120, seed in any::<u64>()) {
        let set = scene(n, seed);
        let a = render(&set, &RenderOptions::default());
        let b = CpuRasterizer::with_threads(3)
            .unwrap()
            .render(&set, &camera(48, 40, 40.0), &RenderOptions::default())
            .unwrap();
        prop_assert_eq!(&a, &b);
        prop_assert_eq!(a, render(&set, &RenderOptions::default()));
    }

    #[test]
    fn a_gaussian_with_opacity_zero_changes_nothing(
        n in 1usize..80,
        seed in any::<u64>(),
        at in any::<prop::sample::Index>(),
    ) {
        let set = scene(n, seed);
        let mut opacities = set.opacities().to_vec();
        let k = at.index(n);
        opacities[k] = 0.0;
        let hidden = GaussianSet::new(
            set.positions().to_vec(),
            set.scales().to_vec(),
            set.rotations().to_vec(),
            opacities,
            set.colors().to_vec(),
        )
        .unwrap()
        .with_features(set.features().unwrap().clone())
        .unwrap();
        let keep: Vec<usize> = (0..n).filter(|&i| i != k).collect();
        prop_assert_eq!(
            render(&hidden, &RenderOptions::default()),
            render(&permuted(&set, &keep), &RenderOptions::default())
        );
    }

    #[test]
    fn zero_gaussians_give_the_background(r in 0f32..1.0, g in 0f32..1.0, b in 0f32..1.0) {
        let image = render(&GaussianSet::default(), &options([r, g, b]));
        prop_assert!(image.rgb.chunks_exact(3).all(|px| px == [r, g, b]));
        prop_assert!(image.alpha.iter().all(|a| *a == 0.0));
        prop_assert!(image.depth.iter().chain(&image.expected_depth).all(|d| *d == 0.0));
        prop_assert!(image.features.is_none());
    }

    #[test]
    fn input_order_does_not_matter(
        n in 1usize..100,
        seed in any::<u64>(),
        shuffle in any::<u64>(),
    ) {
        // Random depths never tie exactly, so (depth, index) order is depth order alone.
        let set = scene(n, seed);
        let mut perm: Vec<usize> = (0..n).collect();
        let mut rng = SplitMix(shuffle);
        for i in (1..n).rev() {
            perm.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
        }
        let bg = options([0.1, 0.2, 0.3]);
        prop_assert_eq!(render(&set, &bg), render(&permuted(&set, &perm), &bg));
    }
}
