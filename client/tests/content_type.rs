//! Content types of uploads and Gaussian formats, from file names.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;

use c4g_client::{GaussianFormat, content_type_for};

#[test]
fn videos_and_archives_get_their_media_types() {
    let cases = [
        ("clip.mp4", "video/mp4"),
        ("clip.MOV", "video/quicktime"),
        ("dir/clip.mkv", "video/x-matroska"),
        ("clip.webm", "video/webm"),
        ("clip.avi", "video/x-msvideo"),
        ("frames.zip", "application/zip"),
        ("frames.tar", "application/x-tar"),
    ];
    for (name, expected) in cases {
        assert_eq!(content_type_for(Path::new(name)), expected, "{name}");
    }
}

#[test]
fn anything_else_is_left_for_the_server_to_sniff() {
    for name in ["clip", "clip.bin", "frames.tar.gz", "clip.mp4.part"] {
        assert_eq!(
            content_type_for(Path::new(name)),
            "application/octet-stream",
            "{name}"
        );
    }
}

#[test]
fn gaussian_formats_follow_the_file_extension() {
    let cases = [
        ("a.ply", Some(GaussianFormat::Ply)),
        ("a.SPLAT", Some(GaussianFormat::Splat)),
        ("a.json", Some(GaussianFormat::Json)),
        ("a.c4gs", Some(GaussianFormat::Binary)),
        ("a.png", None),
        ("a", None),
    ];
    for (name, expected) in cases {
        assert_eq!(
            GaussianFormat::from_extension(Path::new(name)),
            expected,
            "{name}"
        );
    }
    assert_eq!(
        GaussianFormat::Binary.content_type(),
        "application/x-c4g-gaussians"
    );
    assert_eq!(
        "splat".parse::<GaussianFormat>().unwrap(),
        GaussianFormat::Splat
    );
    assert!("obj".parse::<GaussianFormat>().is_err());
}
