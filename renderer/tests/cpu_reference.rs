//! The CPU rasterizer against the float64 reference's renders of the fixture scenes, with both
//! footprints.
//!
//! Tolerances (the fixture scenes keep clear of the forward model's steps, so f32 arithmetic is
//! the only difference): RGB, alpha and features within 2e-3 absolute; alpha-weighted and expected
//! depth within 1e-3 relative where the reference alpha exceeds 0.5. The same for the 3DGS
//! footprint: its scenes also keep clear of its own steps (a tile range within 1e-3 pixels of
//! moving, a quadratic form near rounding negative), and the CPU rasterizer computes the tile range
//! in f64 like the reference.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_renderer::{CpuRasterizer, Rasterizer};
use common::*;

fn check(name: &str) {
    let scene = load_scene(name);
    let got = CpuRasterizer::new()
        .render(&scene.gaussians, &scene.camera, &scene.options)
        .unwrap();
    let d = compare(&got, &scene.expected);
    println!("{name}: {d:?}");
    d.assert_within_reference_tolerance(name);
}

#[test]
fn cloud_matches_the_reference() {
    check("cloud");
}

#[test]
fn extremes_match_the_reference() {
    check("extremes");
}

#[test]
fn fullscreen_matches_the_reference() {
    check("fullscreen");
}

#[test]
fn stack_matches_the_reference() {
    check("stack");
}

#[test]
fn background_matches_the_reference() {
    check("background");
}

#[test]
fn large_matches_the_reference() {
    check("large");
}

#[test]
fn every_scene_matches_the_reference_with_the_3dgs_footprint() {
    for name in SCENES_3DGS {
        check(name);
    }
}

#[test]
fn a_single_thread_renders_the_same_image_as_many() {
    let scene = load_scene("cloud");
    let one = CpuRasterizer::with_threads(1).unwrap();
    let many = CpuRasterizer::with_threads(4).unwrap();
    assert_eq!(one.threads(), 1);
    let a = one
        .render(&scene.gaussians, &scene.camera, &scene.options)
        .unwrap();
    let b = many
        .render(&scene.gaussians, &scene.camera, &scene.options)
        .unwrap();
    assert_eq!(a, b);
}
