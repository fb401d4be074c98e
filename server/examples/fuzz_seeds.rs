//! Writes the seed inputs of the fuzz targets (`fuzz/corpus/<target>/seed-*`): one valid input
//! per shape each target reads, so that libFuzzer starts from what the server accepts.
//!
//! `cargo run -p c4g-server --features fuzzing --example fuzz_seeds -- fuzz/corpus`
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::io::{Cursor, Write};
use std::path::Path;

use c4g_formats::{c4gs, c4gv, frames_zip, ply, splat, splatv, spz};
use c4g_proto::v1 as pb;
use c4g_scene::{Gaussian, GaussianSet};
use c4g_server::fuzzing::CLIP_MARK;
use glam::{Quat, Vec3};
use prost::Message;

fn png(side: u32, shade: u8) -> Vec<u8> {
    let frame = image::RgbImage::from_fn(side, side, |x, y| image::Rgb([x as u8, y as u8, shade]));
    let mut out = Vec::new();
    frame
        .write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)
        .expect("png");
    out
}

fn tar(frames: &[Vec<u8>]) -> Vec<u8> {
    let mut archive = tar::Builder::new(Vec::new());
    for (i, frame) in frames.iter().enumerate() {
        let mut header = tar::Header::new_gnu();
        header.set_size(frame.len() as u64);
        header.set_mode(0o644);
        header.set_cksum();
        archive
            .append_data(&mut header, format!("{i:03}.png"), frame.as_slice())
            .expect("tar");
    }
    archive.into_inner().expect("tar")
}

fn zip(frames: &[Vec<u8>]) -> Vec<u8> {
    let mut archive = zip::ZipWriter::new(Cursor::new(Vec::new()));
    for (i, frame) in frames.iter().enumerate() {
        let options = zip::write::SimpleFileOptions::default();
        archive
            .start_file(format!("{i:03}.png"), options)
            .expect("zip");
        archive.write_all(frame).expect("zip");
    }
    archive.finish().expect("zip").into_inner()
}

fn with_options(options: &str, media: &[u8]) -> Vec<u8> {
    let mut out = vec![u8::try_from(options.len()).expect("short options")];
    out.extend_from_slice(options.as_bytes());
    out.extend_from_slice(media);
    out
}

fn tagged(tag: u8, body: &[u8]) -> Vec<u8> {
    let mut out = vec![tag];
    out.extend_from_slice(body);
    out
}

fn set() -> GaussianSet {
    GaussianSet::from_gaussians((0..3).map(|i| Gaussian {
        position: Vec3::new(i as f32 * 0.1, 0.0, 2.0),
        scale: Vec3::splat(0.05),
        rotation: Quat::IDENTITY,
        opacity: 0.8,
        color: Vec3::new(0.5, 0.2, 0.1),
    }))
}

/// `set` with a 2-wide feature vector per Gaussian (C4GS version 2).
fn with_features(set: &GaussianSet) -> GaussianSet {
    let values = (0..set.len() * 2).map(|i| i as f32 * 0.25).collect();
    set.clone()
        .with_features(c4g_scene::FeatureBlock::new(2, values).expect("features"))
        .expect("features")
}

fn main() {
    let root = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "fuzz/corpus".into());
    let write = |target: &str, seeds: Vec<Vec<u8>>| {
        let dir = Path::new(&root).join(target);
        std::fs::create_dir_all(&dir).expect("corpus dir");
        for (i, seed) in seeds.iter().enumerate() {
            std::fs::write(dir.join(format!("seed-{i:02}")), seed).expect("seed");
        }
    };
    let frames = [png(16, 0), png(16, 90), png(16, 180)];
    let mut jpeg = Vec::new();
    image::RgbImage::from_pixel(16, 16, image::Rgb([9, 99, 199]))
        .write_to(&mut Cursor::new(&mut jpeg), image::ImageFormat::Jpeg)
        .expect("jpeg");
    write(
        "upload",
        vec![
            with_options("", &tar(&frames)),
            with_options("", &zip(&frames)),
            with_options(r#"{"max_frames":2,"fps":5}"#, &tar(&frames)),
            with_options(r#"{"timestamps":[0,0.5,2],"start":0.2}"#, &zip(&frames)),
            with_options(r#"{"stride":2,"end":1}"#, &tar(&frames)),
            with_options("", &frames[0]),
            with_options("", &jpeg),
        ],
    );

    let one = set();
    write(
        "gaussian_files",
        vec![
            tagged(0, &ply::encode(&one)),
            tagged(1, &splat::encode(&one)),
            tagged(
                2,
                &c4gs::encode([(0.0, &one), (0.5, &one)], c4gs::Precision::F32).expect("c4gs"),
            ),
            tagged(
                2,
                &c4gs::encode([(0.25, &one)], c4gs::Precision::F16).expect("c4gs"),
            ),
            tagged(
                2,
                &c4gs::encode([(0.25, &with_features(&one))], c4gs::Precision::F16).expect("c4gs"),
            ),
            tagged(
                3,
                &c4gv::encode([(0.0, &one), (0.1, &one), (0.2, &one)], &Default::default())
                    .expect("c4gv"),
            ),
            tagged(
                3,
                &c4gv::encode(
                    [(0.0, &one), (0.5, &one)],
                    &c4gv::EncodeOptions {
                        deflate: false,
                        detect_static: false,
                        keyframe_interval: 1,
                        ..Default::default()
                    },
                )
                .expect("c4gv"),
            ),
            tagged(4, &spz::encode(&one).expect("spz")),
            tagged(
                5,
                &frames_zip::encode(
                    &[(0.0, one.clone()), (0.5, one.clone())],
                    frames_zip::FrameFormat::Spz,
                )
                .expect("frames zip"),
            ),
            tagged(
                5,
                &frames_zip::encode(&[(0.25, one.clone())], frames_zip::FrameFormat::Ply)
                    .expect("frames zip"),
            ),
            tagged(
                6,
                &splatv::fit(
                    &[(0.0, one.clone()), (0.5, one.clone()), (1.0, one.clone())],
                    &splatv::Camera::first_context(64, 64),
                )
                .expect("splatv")
                .encode(),
            ),
        ],
    );

    let camera = r#"{"world_to_camera":[1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1],"intrinsics":{"fx":0.8767,"fy":0.8767,"cx":0.5,"cy":0.5}}"#;
    let rest = [
        (0, "", r#"{"t":0.1}"#.to_owned()),
        (0, "", r#"{"times":[0,0.1,0.2],"format":"binary","precision":"f16"}"#.to_owned()),
        (0, "", r#"{"times":[0,0.1,0.3],"keyframes":{"tolerance":0.005,"max":4}}"#.to_owned()),
        (0, "", r#"{"times":[0,0.2],"quality":"fast","prune":{"contribution_px":0.5}}"#.to_owned()),
        (0, "", r#"{"t":0.2,"format":"ply"}"#.to_owned()),
        (1, "", format!(r#"{{"t":0.1,"camera":{camera},"width":32,"height":32,"format":"png"}}"#)),
        (1, "", r#"{"t":0.1,"width":16,"height":16,"format":"depth","background":[1,1,1]}"#.to_owned()),
        (1, "", r#"{"trajectory":{"kind":"orbit","depth":2.0,"angle_degrees":30},"frames":3,"width":16,"height":16,"format":"png"}"#.to_owned()),
        (1, "", r#"{"trajectory":{"kind":"spiral","radii":[0.1,0.1,0.05],"focus_depth":2,"rotations":2,"z_rate":0.5},"frames":2,"width":16,"height":16}"#.to_owned()),
        (1, "", format!(r#"{{"cameras":[{camera},{camera}],"width":16,"height":16,"format":"alpha","keyframes":{{"count":2}}}}"#)),
        (2, "", r#"{"trajectory":{"kind":"dolly","distance":0.5},"steps":2,"seed":0,"caption":"a scene"}"#.to_owned()),
        (8, "", r#"{"step":0.1,"position_error":0.001}"#.to_owned()),
        (8, "", r#"{"fps":20,"quality":"fast","keyframe_interval":4}"#.to_owned()),
        (9, "", r#"{"format":"spz_zip","step":0.2}"#.to_owned()),
        (9, "", r#"{"format":"splatv","start":0.1,"end":0.3,"fps":10,"quality":"fast"}"#.to_owned()),
        (10, "", r#"{"queries":[{"t":0.1,"x":3.5,"y":4.0},{"t":0.0,"x":0.0,"y":63.9}],"times":[0,0.2]}"#.to_owned()),
        (10, "", r#"{"queries":[{"t":0.2,"x":8,"y":8}],"width":16,"height":16,"quality":"fast"}"#.to_owned()),
        (11, "", r#"{"refine_focal":true}"#.to_owned()),
        (0, "", r#"{"times":[0,0.2],"features":true,"format":"binary"}"#.to_owned()),
        (1, "", r#"{"t":0.1,"width":16,"height":16,"format":"features_pca"}"#.to_owned()),
        (10, "", r#"{"queries":[{"t":0.1,"x":3.5,"y":4.0}],"tracker":"features"}"#.to_owned()),
        (12, "", r#"{"click":{"t":0.1,"x":8.5,"y":8.5},"threshold":0.7,"times":[0,0.2]}"#.to_owned()),
        (12, "", r#"{"feature":[1,0,0,0],"t":0.2,"width":16,"height":16}"#.to_owned()),
        (3, "max_frames=2&fps=4", String::new()),
        (4, "0", String::new()),
        (5, CLIP_MARK, String::new()),
        (6, "", String::new()),
        (7, "00000000/result?frame=0", String::new()),
    ];
    write(
        "rest",
        rest.iter()
            .map(|(route, head, body)| {
                let mut input = vec![*route];
                if !head.is_empty() || (3..8).contains(route) {
                    input.extend_from_slice(head.as_bytes());
                    input.push(b'\n');
                }
                input.extend_from_slice(body.as_bytes());
                if *route == 3 {
                    input.extend_from_slice(&tar(&frames));
                }
                input
            })
            .collect(),
    );

    let clip_id = CLIP_MARK.to_owned();
    let camera = pb::Camera {
        world_to_camera: vec![
            1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.,
        ],
        intrinsics: Some(pb::Intrinsics {
            fx: 0.8767,
            fy: 0.8767,
            cx: 0.5,
            cy: 0.5,
        }),
        input: None,
    };
    let keyframes = pb::Keyframes {
        mode: Some(pb::keyframes::Mode::Adaptive(pb::AdaptiveKeyframes {
            tolerance: 0.005,
            color_tolerance: None,
            max: 4,
            min_interval_s: 0.0,
        })),
    };
    write(
        "grpc",
        vec![
            tagged(
                0,
                &pb::ClipRef {
                    clip_id: clip_id.clone(),
                }
                .encode_to_vec(),
            ),
            tagged(1, &[]),
            tagged(
                2,
                &pb::DecodeRequest {
                    clip_id: clip_id.clone(),
                    times: vec![0.0, 0.1, 0.2],
                    keyframes: Some(keyframes),
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
            tagged(
                3,
                &pb::StreamGaussiansRequest {
                    clip_id: clip_id.clone(),
                    start: Some(0.0),
                    end: Some(0.2),
                    spacing: Some(pb::stream_gaussians_request::Spacing::Step(0.05)),
                    quality: pb::Quality::Fast as i32,
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
            tagged(
                4,
                &pb::RenderRequest {
                    clip_id: clip_id.clone(),
                    time: 0.1,
                    camera: Some(camera.clone()),
                    width: 16,
                    height: 16,
                    prune: Some(pb::Prune {
                        contribution_px: Some(0.5),
                        opacity: None,
                        drop_queries: None,
                    }),
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
            tagged(
                5,
                &pb::RenderTrajectoryRequest {
                    clip_id: clip_id.clone(),
                    frames: 3,
                    preset_json: r#"{"kind":"orbit","depth":2.0,"angle_degrees":20}"#.into(),
                    width: 16,
                    height: 16,
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
            tagged(
                5,
                &pb::RenderTrajectoryRequest {
                    clip_id: clip_id.clone(),
                    cameras: vec![camera.clone(), camera],
                    width: 16,
                    height: 16,
                    format: pb::ImageFormat::DepthF32 as i32,
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
            tagged(6, &[]),
            tagged(
                10,
                &pb::RecoverCamerasRequest {
                    clip_id: clip_id.clone(),
                    refine_focal: false,
                }
                .encode_to_vec(),
            ),
            tagged(
                11,
                &pb::SegmentRequest {
                    clip_id: clip_id.clone(),
                    selection: Some(pb::segment_request::Selection::Click(pb::SegmentClick {
                        time: 0.1,
                        x: 8.5,
                        y: 8.5,
                    })),
                    threshold: Some(0.7),
                    times: vec![0.0, 0.2],
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
            tagged(
                2,
                &pb::DecodeRequest {
                    clip_id: clip_id.clone(),
                    times: vec![0.1],
                    features: true,
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
            tagged(
                9,
                &pb::TracksRequest {
                    clip_id,
                    queries: vec![pb::TrackQuery {
                        time: 0.1,
                        x: 3.5,
                        y: 4.0,
                    }],
                    times: vec![0.0, 0.2],
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
            tagged(
                7,
                &pb::ProgressRequest {
                    job_id: "00000000".into(),
                    worker: "w".into(),
                    step: 1,
                    steps: 2,
                    stage: "denoise".into(),
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
            tagged(
                8,
                &pb::FailRequest {
                    job_id: "00000000".into(),
                    worker: "w".into(),
                    ..Default::default()
                }
                .encode_to_vec(),
            ),
        ],
    );

    let floats = |v: &[f64]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    write(
        "time_policy",
        vec![
            floats(&[0.0, 1.0, 0.0, 2.0, 4.0, 6.0]),
            floats(&[1.0, 0.0, 0.0, 2.0, 4.0, 6.0]),
            floats(&[0.1, 0.35, 0.0, 0.5, 1.0]),
            floats(&[0.0, 3.0, 3.0]),
            floats(&[0.04, 1e-9, 0.0, 0.0, 0.4]),
        ],
    );
}
