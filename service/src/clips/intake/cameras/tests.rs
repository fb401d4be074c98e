//! The three forms give the same stored cameras; bad files are refused naming the problem.

#![allow(clippy::unwrap_used)]

use glam::{DMat3, DQuat, DVec3};

use super::*;

const W: f64 = 640.0;
const H: f64 = 480.0;

/// A capture in some world frame: world-to-camera poses and pixel intrinsics of a W × H image.
struct Capture {
    poses: Vec<(DMat3, DVec3)>,
    pixels: Vec<[f64; 4]>,
}

fn capture() -> Capture {
    let poses = (0..5)
        .map(|i| {
            let f = f64::from(i);
            let r = DMat3::from_quat(
                DQuat::from_axis_angle(DVec3::new(0.3, 1.0, 0.2 * f).normalize(), 0.4 + 0.3 * f)
                    .normalize(),
            );
            // Far from the origin, in metres: the mapping must not care where the world is.
            let centre = DVec3::new(100.0 + 0.7 * f, -20.0 + 0.2 * f * f, 5.0 - 0.4 * f);
            (r, -(r * centre))
        })
        .collect();
    let pixels = (0..5)
        .map(|i| {
            let f = f64::from(i);
            [500.0 + 10.0 * f, 505.0 + 10.0 * f, 320.0 + f, 240.0 - f]
        })
        .collect();
    Capture { poses, pixels }
}

fn rows(r: &DMat3, t: DVec3) -> Vec<f64> {
    model_frame::row_major(r, t)
}

fn as_json(c: &Capture) -> String {
    let list: Vec<serde_json::Value> = c
        .poses
        .iter()
        .zip(&c.pixels)
        .map(|((r, t), k)| {
            serde_json::json!({
                "world_to_camera": rows(r, *t),
                "intrinsics": {"fx": k[0] / W, "fy": k[1] / H, "cx": k[2] / W, "cy": k[3] / H},
            })
        })
        .collect();
    serde_json::to_string(&list).unwrap()
}

/// COLMAP text: images listed out of order (frames follow their names), one camera each.
fn as_colmap(c: &Capture) -> (String, String) {
    let mut cameras = String::from("# Camera list\n");
    let mut images = String::from("# Image list with two lines of data per image:\n");
    for i in (0..c.poses.len()).rev() {
        let k = c.pixels[i];
        cameras += &format!(
            "{} PINHOLE {W} {H} {} {} {} {}\n",
            i + 7,
            k[0],
            k[1],
            k[2],
            k[3]
        );
        let (r, t) = c.poses[i];
        let q = DQuat::from_mat3(&r);
        images += &format!(
            "{} {} {} {} {} {} {} {} {} frame_{i:03}.png\n",
            i + 1,
            q.w,
            q.x,
            q.y,
            q.z,
            t.x,
            t.y,
            t.z,
            i + 7
        );
        images += if i % 2 == 0 {
            "\n"
        } else {
            "10.5 20.5 -1 11 12 3\n"
        };
    }
    (cameras, images)
}

/// transforms.json in another world frame (rotated, scaled by 3, moved), OpenGL axes.
fn as_transforms(c: &Capture) -> String {
    let q = DMat3::from_quat(DQuat::from_rotation_z(0.9) * DQuat::from_rotation_x(-1.2));
    let (s, d) = (3.0, DVec3::new(-4.0, 9.0, 1.5));
    let flip = DMat3::from_diagonal(DVec3::new(1.0, -1.0, -1.0));
    let frames: Vec<serde_json::Value> = c
        .poses
        .iter()
        .zip(&c.pixels)
        .enumerate()
        .map(|(i, ((r, t), k))| {
            let centre = -(r.transpose() * *t);
            let c2w = q * r.transpose() * flip;
            let m = rows(&c2w, s * (q * centre) + d);
            serde_json::json!({
                "file_path": format!("images/frame_{i:03}.png"),
                "transform_matrix": [&m[0..4], &m[4..8], &m[8..12], &m[12..16]],
                "fl_x": k[0], "fl_y": k[1], "cx": k[2], "cy": k[3],
            })
        })
        .rev()
        .collect();
    serde_json::json!({"w": W, "h": H, "camera_model": "OPENCV", "frames": frames}).to_string()
}

fn stored(input: CameraInput) -> ClipCameras {
    let parsed = input.parse().unwrap();
    let times: Vec<f64> = (0..parsed.cameras.len()).map(|i| i as f64 * 0.1).collect();
    ClipCameras::new(&parsed.cameras, &times, parsed.format, parsed.notes)
}

fn largest_difference(a: &ClipCameras, b: &ClipCameras) -> f64 {
    assert_eq!(a.frames.len(), b.frames.len());
    a.frames
        .iter()
        .zip(&b.frames)
        .flat_map(|(x, y)| {
            let k = |c: &ContextCamera| {
                [
                    c.intrinsics.fx,
                    c.intrinsics.fy,
                    c.intrinsics.cx,
                    c.intrinsics.cy,
                ]
            };
            let poses = x
                .world_to_camera
                .iter()
                .zip(&y.world_to_camera)
                .map(|(p, q)| (p - q).abs());
            let intrinsics = k(x).into_iter().zip(k(y)).map(|(p, q)| (p - q).abs());
            poses.chain(intrinsics).collect::<Vec<_>>()
        })
        .fold(0.0, f64::max)
}

/// 1e-6: the files carry the numbers at full f64 precision (Rust's shortest round-trip
/// formatting), so what separates the forms is the arithmetic of each path (quaternion to
/// matrix, OpenGL flips, the moved world), some 1e-13 on numbers of size 100.
#[test]
fn json_colmap_and_transforms_json_give_the_same_stored_cameras() {
    let c = capture();
    let json = stored(CameraInput::Json(as_json(&c)));
    let (cameras, images) = as_colmap(&c);
    let colmap = stored(CameraInput::Colmap {
        cameras,
        images,
        names: None,
    });
    let transforms = stored(CameraInput::Transforms {
        json: as_transforms(&c),
        names: None,
    });
    assert!(
        largest_difference(&json, &colmap) < 1e-6,
        "{}",
        largest_difference(&json, &colmap)
    );
    assert!(
        largest_difference(&json, &transforms) < 1e-6,
        "{}",
        largest_difference(&json, &transforms)
    );
    assert!((json.scale - colmap.scale).abs() < 1e-9);
    // The transforms' world was scaled by 3: so was the factor the translations were divided by.
    assert!((transforms.scale - 3.0 * json.scale).abs() < 1e-9);
    assert_eq!(
        (json.format.as_str(), colmap.format.as_str()),
        ("json", "colmap")
    );
}

/// Checked against the definition, computed another way: for any world point X, camera i sees
/// `W_i X`; in the model's frame the first camera sees `W_0 X / s`, and camera i's stored pose
/// must carry that to `W_i X / s`, with s the largest distance of a camera centre from the first.
#[test]
fn stored_cameras_are_relative_to_the_first_and_scaled_by_the_largest_distance_from_it() {
    let c = capture();
    let json = stored(CameraInput::Json(as_json(&c)));
    let centres: Vec<DVec3> = c.poses.iter().map(|(r, t)| -(r.transpose() * *t)).collect();
    let s = centres
        .iter()
        .map(|p| (*p - centres[0]).length())
        .fold(0.0, f64::max);
    assert!((json.scale - s).abs() < 1e-12 * s.max(1.0));
    let identity = rows(&DMat3::IDENTITY, DVec3::ZERO);
    for (a, b) in json.frames[0].world_to_camera.iter().zip(&identity) {
        assert!((a - b).abs() < 1e-12);
    }
    let (r0, t0) = c.poses[0];
    for x in [DVec3::new(101.0, -19.0, 7.0), DVec3::new(95.0, -25.0, 2.0)] {
        let in_first = (r0 * x + t0) / s;
        for ((r, t), stored) in c.poses.iter().zip(&json.frames) {
            let (sr, st) = stored.pose();
            let expected = (*r * x + *t) / s;
            assert!((sr * in_first + st - expected).length() < 1e-9);
        }
    }
    let farthest = json
        .frames
        .iter()
        .map(|f| f.rotation_and_centre().1.length())
        .fold(0.0, f64::max);
    assert!((farthest - 1.0).abs() < 1e-9, "{farthest}");
}

#[test]
fn a_file_name_list_orders_colmap_images_and_names_what_is_missing() {
    let c = capture();
    let (cameras, images) = as_colmap(&c);
    let names: Vec<String> = [4, 3, 2, 1, 0]
        .iter()
        .map(|i| format!("frame_{i:03}.png"))
        .collect();
    let reversed = stored(CameraInput::Colmap {
        cameras: cameras.clone(),
        images: images.clone(),
        names: Some(names),
    });
    let forward = stored(CameraInput::Colmap {
        cameras: cameras.clone(),
        images: images.clone(),
        names: None,
    });
    // Both start at the identity; the reversed list's last camera is the forward list's first,
    // seen from the forward list's last.
    assert_ne!(
        reversed.frames[1].world_to_camera,
        forward.frames[1].world_to_camera
    );
    let missing = CameraInput::Colmap {
        cameras,
        images,
        names: Some(vec!["frame_000.png".into(), "frame_009.png".into()]),
    }
    .parse()
    .unwrap_err()
    .to_string();
    assert!(
        missing.contains("camera_names[1] is \"frame_009.png\""),
        "{missing}"
    );
}

fn refusal(input: CameraInput) -> String {
    let error = input.parse().unwrap_err();
    assert_eq!(error.kind(), crate::ServiceErrorKind::InvalidInput);
    error.to_string()
}

fn colmap(cameras: &str, images: &str) -> CameraInput {
    CameraInput::Colmap {
        cameras: cameras.into(),
        images: images.into(),
        names: None,
    }
}

const ONE_CAMERA: &str = "1 PINHOLE 640 480 500 500 320 240\n";

#[test]
fn bad_camera_files_are_refused_saying_where_and_what() {
    let image = |pose: &str| format!("1 {pose} 1 a.png\n\n");
    for (input, expected) in [
        (colmap(ONE_CAMERA, &image("1 0 0 0 0 0 x")), "images.txt line 1: TZ must be a finite number, got \"x\""),
        (colmap(ONE_CAMERA, &image("1 0 0 0 0 0 NaN")), "TZ must be a finite number"),
        (colmap(ONE_CAMERA, &image("0 0 0 0 0 0 0")), "quaternion must be finite and not zero"),
        (colmap(ONE_CAMERA, "1 1 0 0 0 0 0 0 2 a.png\n\n"), "uses camera 2, which cameras.txt does not list"),
        (colmap("1 PINHOLE 640 480 500 500 320\n", &image("1 0 0 0 0 0 0")), "a PINHOLE camera has 4 parameters, got 3"),
        (colmap("1 OPENCV_FISHEYE 640 480 1 2 3 4 5 6 7 8\n", &image("1 0 0 0 0 0 0")), "OPENCV_FISHEYE is not supported"),
        (colmap(ONE_CAMERA, "1 1 0 0 0 0 0 0 1 a.png\n2 1 0 0 0 0 0 0 1 b.png\n"), "line 2: expected the 2D points of image \"a.png\""),
        (colmap(ONE_CAMERA, ""), "images.txt lists no image"),
        (CameraInput::Json("[{\"world_to_camera\": [1,0,0,0, 0,2,0,0, 0,0,1,0, 0,0,0,1]}]".into()), "cameras[0]: the pose's 3x3 part is not a rotation"),
        (CameraInput::Json("[{\"world_to_camera\": [1,0,0,0, 0,-1,0,0, 0,0,1,0, 0,0,0,1]}]".into()), "is a reflection"),
        (CameraInput::Json("[{\"world_to_camera\": [1,0,0,0, 0,1,0,0, 0,0,1,0]}]".into()), "needs 16 numbers"),
        (CameraInput::Json("[{\"world_to_camera\": [1,0,0,0, 0,1,0,0, 0,0,1,NaN, 0,0,0,1]}]".into()), "not a JSON list of cameras"),
        (CameraInput::Json("[{\"camera_to_world\": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,1,1]}]".into()), "must end in the row 0 0 0 1"),
        (CameraInput::Json("[{}]".into()), "exactly one of world_to_camera and camera_to_world"),
        (CameraInput::Json("[]".into()), "no camera"),
        (CameraInput::Json("[{\"world_to_camera\": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], \"intrinsics\": {\"fx\": 0, \"fy\": 1}}]".into()), "intrinsics fx must be between"),
        (CameraInput::Transforms { json: "{\"frames\": []}".into(), names: None }, "non-empty `frames`"),
        (CameraInput::Transforms { json: "{\"fl_x\": 500, \"frames\": [{\"file_path\": \"a\", \"transform_matrix\": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}".into(), names: None }, "`w` and `h` is needed"),
        (CameraInput::Transforms { json: "{\"w\": 64, \"h\": 48, \"fl_x\": 50, \"frames\": [{\"file_path\": \"a\", \"transform_matrix\": [[1,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}".into(), names: None }, "transform_matrix must be 4 rows of 4 numbers"),
    ] {
        let message = refusal(input);
        assert!(message.contains(expected), "{message:?} should say {expected:?}");
    }
}

#[test]
fn distortion_is_ignored_with_a_note_and_only_when_it_is_there() {
    let images = "1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 1 0 0 2 b.png\n\n";
    let cameras =
        "1 OPENCV 640 480 500 500 320 240 0.1 0 0 0\n2 SIMPLE_RADIAL 640 480 500 320 240 0\n";
    let parsed = colmap(cameras, images).parse().unwrap();
    assert_eq!(parsed.notes.len(), 1, "{:?}", parsed.notes);
    assert!(parsed.notes[0].contains("COLMAP camera 1 is OPENCV"));
    // The pinhole part is read as it is: fx / W, cx / W.
    let k = parsed.cameras[1].intrinsics;
    assert_eq!(
        (k.fx, k.fy, k.cx, k.cy),
        (500.0 / 640.0, 500.0 / 480.0, 0.5, 0.5)
    );
}

#[test]
fn cameras_that_do_not_move_keep_their_units() {
    let input = CameraInput::Json(
        "[{\"world_to_camera\": [1,0,0,2, 0,1,0,0, 0,0,1,0, 0,0,0,1]}, \
          {\"world_to_camera\": [0,-1,0,0, 1,0,0,2, 0,0,1,0, 0,0,0,1]}]"
            .into(),
    );
    let cameras = stored(input);
    assert_eq!(cameras.scale, 1.0);
    assert!(cameras.notes[0].contains("do not move"));
}

#[test]
fn the_content_address_changes_with_the_cameras_and_not_without_them() {
    use crate::clips::intake::{IntakeOptions, Media, clip_id};
    let media = Media::Frames(vec![bytes::Bytes::from_static(b"frame")]);
    let plain = IntakeOptions::default();
    let with = |json: &str| IntakeOptions {
        cameras: Some(CameraInput::Json(json.into())),
        ..IntakeOptions::default()
    };
    let a = clip_id("m", &media, &with("[1]"));
    assert_ne!(a, clip_id("m", &media, &with("[2]")));
    assert_ne!(a, clip_id("m", &media, &plain));
    // The id of an upload without cameras is what it was before cameras existed (computed
    // independently: SHA-256 of the model, the options as JSON and the frame, first 12 bytes).
    assert_eq!(clip_id("m", &media, &plain), "f974787d9f150738f7ca744e");
}

#[test]
fn cameras_must_be_one_per_source_frame_and_of_the_frames_shape() {
    let (cameras, images) = as_colmap(&capture());
    let parsed = colmap(&cameras, &images).parse().unwrap();
    assert_eq!(parsed.image_sizes, vec![(W, H)]);
    // Twice the size, same shape: intrinsics are fractions of the size, so they still fit.
    parsed.check_against(5, 1280, 960).unwrap();
    let count = parsed.check_against(4, 1280, 960).unwrap_err().to_string();
    assert!(count.contains("5 cameras for 4 frames"), "{count}");
    let cropped = parsed.check_against(5, 1280, 720).unwrap_err().to_string();
    assert!(
        cropped.contains("estimated on 640x480 images but the frames are 1280x720"),
        "{cropped}"
    );
    // The JSON form states no image size: nothing to hold it to.
    let json = CameraInput::Json(as_json(&capture())).parse().unwrap();
    json.check_against(5, 1280, 720).unwrap();
}

/// What goes out reads back: each form written from a clip's cameras and read by the upload's
/// reader gives the same stored cameras (1e-9: the numbers are written in full; only the
/// quaternion and OpenGL round trips' arithmetic separates them).
#[test]
fn every_form_written_reads_back_as_the_same_cameras() {
    let c = capture();
    let given = CameraInput::Json(as_json(&c)).parse().unwrap().cameras;
    let names: Vec<String> = (0..given.len()).map(|k| format!("{k:03}.png")).collect();
    let before = stored(CameraInput::Json(as_json(&c)));
    for format in [
        CameraFormat::Json,
        CameraFormat::Colmap,
        CameraFormat::Transforms,
    ] {
        let files = write(format, &given, &names, W as u32, H as u32);
        let file = |name: &str| {
            files
                .iter()
                .find(|(n, _)| *n == name)
                .map(|(_, text)| text.clone())
                .unwrap()
        };
        let input = match format {
            CameraFormat::Json => CameraInput::Json(file("cameras.json")),
            CameraFormat::Colmap => CameraInput::Colmap {
                cameras: file("cameras.txt"),
                images: file("images.txt"),
                names: Some(names.clone()),
            },
            CameraFormat::Transforms => CameraInput::Transforms {
                json: file("transforms.json"),
                names: Some(names.clone()),
            },
        };
        let parsed = input.parse().unwrap();
        if format != CameraFormat::Json {
            assert_eq!(parsed.image_sizes[0], (W, H), "{format:?}");
        }
        let after = stored(input);
        assert!(
            largest_difference(&before, &after) < 1e-9,
            "{format:?}: {}",
            largest_difference(&before, &after)
        );
    }
}

/// Whole-frame and crop fractions describe one camera: there and back is the identity, and the
/// crop of a wide frame sees its centre where the frame does.
#[test]
fn crop_and_frame_fractions_convert_both_ways() {
    let k = Intrinsics {
        fx: 0.5,
        fy: 0.9,
        cx: 0.3,
        cy: 0.55,
    };
    let crop = k.frame_to_crop(200, 100);
    // 200×100: the crop is x in [50, 150): fx 0.5·200 = 100 px = 1.0 of the crop.
    assert!(
        (crop.fx - 1.0).abs() < 1e-12 && (crop.cx - 0.1).abs() < 1e-12,
        "{crop:?}"
    );
    let back = crop.crop_to_frame(200, 100);
    for (a, b) in [
        (k.fx, back.fx),
        (k.fy, back.fy),
        (k.cx, back.cx),
        (k.cy, back.cy),
    ] {
        assert!((a - b).abs() < 1e-12);
    }
}
