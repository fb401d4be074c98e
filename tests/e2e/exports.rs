//! The 4D exports (`POST /v1/clips/{id}/export`) read back by readers that are not ours, against
//! the exact sets the service decodes at the same times.
//!
//! - `.ply.zip`: Python's `zipfile` and `plyfile` (PyPI), `models/python/c4g/formats/frames_zip.py`. The
//!   PLY columns are f32 (positions as they are; opacity as a logit, scales as logarithms, colour
//!   as SH DC): the only error is f32 rounding of those transforms, within [`PLY_SLACK`].
//! - `.spz.zip`: the archive opened with the `zip` crate (a container only), each `.spz` read by
//!   Niantic's reference library, `@adobe/spz` (npm, the WebAssembly build of nianticlabs/spz), in
//!   `tests/browser/spz.mjs`. Tolerances: the quantisation bounds `formats/src/spz.rs`
//!   states, per attribute.
//! - `.splatv`: `models/python/c4g/formats/splatv.py`, a reader written from the format's specification
//!   (splaTV's viewer) apart from the Rust writer, evaluated at each exported time. The file is a
//!   fit (a cubic path, a linear spin, one opacity bump per Gaussian), so the reference is the fit
//!   error the server states with the file (`X-C4G-Fit-Position-Error`), and the render PSNR of
//!   what the reader evaluates against the exact set, from the first context camera.
//!
//! Sizes (bytes a set, against C4GS f32) are printed for `docs/benchmarks.md`.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::io::Read;
use std::process::Command;

use c4g_e2e::{
    Server, node_packages, ort_available, post_json, upload_synthetic, venv_python, workspace,
};
use c4g_formats::{c4gs, ply, splatv, spz};
use c4g_renderer::fidelity::psnr;
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};
use glam::Affine3A;
use serde_json::{Value, json};

/// `.ply.zip` against the exact sets: f32 storage of positions, and of `ln`, `logit` and the SH
/// DC transform of the rest, read back in float64 (relative error of a few f32 ulps).
const PLY_SLACK: f64 = 1e-5;

/// Render PSNR of the `.splatv` a reader evaluates against the exact sets, at 128² from the
/// first context camera, the least over the exported times. The fit is an approximation: on
/// c4g-tiny's moving clip (7 sets, 0 to 0.6 s) it stated max 0.053, rms 0.0046 scene units, and
/// rendered at 38.0 dB; most of the error is at 0 s, where c4g-tiny's set stands apart from the
/// rest (tests/e2e/viewer.rs), which no smooth path follows. 4 dB of margin.
const SPLATV_MIN_DB: f64 = 34.0;

/// Render PSNR of the `.spz` sets the reference library reads against the exact sets. Measured
/// 55.4 dB (its 8-bit scales, 3 % apart, cost the most); 7 dB of margin, well above what a
/// wrong axis or a swapped component costs (tens of dB).
const SPZ_MIN_DB: f64 = 48.0;

const SIDE: u32 = 128;

fn post(server: &Server, path: &str, body: Value) -> reqwest::blocking::Response {
    post_json(server, path, &body)
}

fn export(server: &Server, clip: &str, body: Value) -> (Vec<u8>, reqwest::header::HeaderMap) {
    let response = post(server, &format!("/v1/clips/{clip}/export"), body.clone());
    let status = response.status();
    let headers = response.headers().clone();
    let bytes = response.bytes().unwrap().to_vec();
    assert_eq!(status, 200, "{body}: {}", String::from_utf8_lossy(&bytes));
    (bytes, headers)
}

fn exact(server: &Server, clip: &str, times: &[f64]) -> Vec<(f64, GaussianSet)> {
    let response = post(
        server,
        &format!("/v1/clips/{clip}/gaussians"),
        json!({"times": times, "format": "binary"}),
    );
    assert_eq!(response.status(), 200);
    c4gs::decode(&response.bytes().unwrap()).unwrap()
}

/// Runs a reader; its JSON output.
fn read_with(command: &mut Command) -> Value {
    let out = command.output().unwrap();
    assert!(
        out.status.success(),
        "{command:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

fn rows(value: &Value) -> Vec<Vec<f64>> {
    value
        .as_array()
        .unwrap()
        .iter()
        .map(|row| match row {
            Value::Array(xs) => xs.iter().map(|x| x.as_f64().unwrap()).collect(),
            x => vec![x.as_f64().unwrap()],
        })
        .collect()
}

/// A set from a reader's JSON frame (`positions`, `scales`, `rotations`, `opacities`, `colors`).
fn set_of(frame: &Value) -> GaussianSet {
    let f32s = |key: &str| rows(&frame[key]);
    let p = f32s("positions");
    let s = f32s("scales");
    let r = f32s("rotations");
    let o = f32s("opacities");
    let c = f32s("colors");
    GaussianSet::new(
        p.iter()
            .map(|v| [v[0] as f32, v[1] as f32, v[2] as f32])
            .collect(),
        s.iter()
            .map(|v| [v[0] as f32, v[1] as f32, v[2] as f32])
            .collect(),
        r.iter()
            .map(|v| [v[0] as f32, v[1] as f32, v[2] as f32, v[3] as f32])
            .collect(),
        o.iter().map(|v| v[0] as f32).collect(),
        c.iter()
            .map(|v| [v[0] as f32, v[1] as f32, v[2] as f32])
            .collect(),
    )
    .unwrap()
}

fn render(set: &GaussianSet) -> Vec<f32> {
    let camera = Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        SIDE,
        SIDE,
        Affine3A::IDENTITY,
    )
    .unwrap();
    CpuRasterizer::new()
        .render(
            set,
            &camera,
            &RenderOptions {
                features: false,
                ..RenderOptions::default()
            },
        )
        .unwrap()
        .rgb
}

fn render_psnr(a: &GaussianSet, b: &GaussianSet) -> f64 {
    psnr(&render(a), &render(b), SIDE, SIDE, None).unwrap()
}

/// The largest differences between two sets: position (per coordinate), `ln` of the scales,
/// rotation angle (radians), opacity, colour (per channel).
fn worst(a: &GaussianSet, b: &GaussianSet) -> [f64; 5] {
    let mut w = [0f64; 5];
    let d = |x: &[f32], y: &[f32]| {
        x.iter()
            .zip(y)
            .map(|(x, y)| f64::from((x - y).abs()))
            .fold(0.0, f64::max)
    };
    for i in 0..a.len() {
        w[0] = w[0].max(d(&a.positions()[i], &b.positions()[i]));
        // Floored as the PLY writer floors them (a scale of 0 has no logarithm).
        let floor = |v: f32| f64::from(v).max(ply::SCALE_MIN);
        for (x, y) in a.scales()[i].iter().zip(&b.scales()[i]) {
            w[1] = w[1].max((floor(*x) / floor(*y)).ln().abs());
        }
        w[2] = w[2].max(angle(a.rotations()[i], b.rotations()[i]));
        w[3] = w[3].max(f64::from((a.opacities()[i] - b.opacities()[i]).abs()));
        w[4] = w[4].max(d(&a.colors()[i], &b.colors()[i]));
    }
    w
}

/// The angle of the rotation between two quaternions, from the chord between the unit
/// quaternions (|q1 − q2| = 2 sin(θ/4), q2 signed to the same side): unlike `acos` of their dot
/// product it keeps its precision for small angles.
fn angle(a: [f32; 4], b: [f32; 4]) -> f64 {
    let unit = |q: [f32; 4]| {
        let q = q.map(f64::from);
        let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        q.map(|v| v / n)
    };
    let (a, b) = (unit(a), unit(b));
    let sign = if a.iter().zip(&b).map(|(x, y)| x * y).sum::<f64>() < 0.0 {
        -1.0
    } else {
        1.0
    };
    let chord = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - sign * y).powi(2))
        .sum::<f64>()
        .sqrt();
    4.0 * (chord / 2.0).min(1.0).asin()
}

#[test]
fn every_export_reads_back_with_an_independent_reader() {
    if !ort_available() {
        return;
    }
    let Some(node) = node_packages("@adobe/spz") else {
        return;
    };
    let python = venv_python();
    let server = Server::start(&[]);
    let clip = upload_synthetic(&server);
    let out = tempfile::tempdir().unwrap();
    let range = json!({"fps": 10});

    // .ply.zip, with zipfile and plyfile.
    let mut body = range.clone();
    body["format"] = json!("ply_zip");
    let (ply_zip, headers) = export(&server, &clip, body);
    assert_eq!(headers["content-type"], "application/zip");
    assert!(
        headers["content-disposition"]
            .to_str()
            .unwrap()
            .ends_with(".ply.zip\""),
        "{headers:?}"
    );
    let ply_path = out.path().join("clip.ply.zip");
    std::fs::write(&ply_path, &ply_zip).unwrap();
    let read = read_with(
        Command::new(&python)
            .args(["-m", "c4g.formats.frames_zip"])
            .arg(&ply_path)
            .current_dir(workspace().join("models/python")),
    );
    let times: Vec<f64> = rows(&read["times"]).into_iter().map(|v| v[0]).collect();
    assert!(times.len() >= 3, "{times:?}");
    assert_eq!(headers["x-c4g-sets"], times.len().to_string().as_str());
    let want = exact(&server, &clip, &times);
    let n = want[0].1.len();
    for ((t, set), frame) in want.iter().zip(read["frames"].as_array().unwrap()) {
        assert_eq!(frame["time"].as_f64().unwrap(), *t);
        let got = set_of(frame);
        assert_eq!(got.len(), n);
        let w = worst(&got, set);
        assert_eq!(w[0], 0.0, "positions are stored as they are");
        for (k, v) in w.iter().enumerate().skip(1) {
            assert!(*v <= PLY_SLACK, "column {k} off by {v} at {t} s");
        }
    }

    // .spz.zip: each entry read by the reference library.
    let mut body = range.clone();
    body["format"] = json!("spz_zip");
    let (spz_zip, _) = export(&server, &clip, body);
    let mut archive = zip::ZipArchive::new(std::io::Cursor::new(&spz_zip[..])).unwrap();
    let mut files = Vec::new();
    let mut fractional_bits = Vec::new();
    let mut spz_bytes = 0;
    for i in 0..archive.len() {
        let mut entry = archive.by_index(i).unwrap();
        assert_eq!(entry.name().unwrap(), format!("frame_{i:06}.spz"));
        let mut data = Vec::new();
        entry.read_to_end(&mut data).unwrap();
        spz_bytes += data.len();
        // The header's fractional bits (byte 13, spz.rs's layout table): the file's own step.
        fractional_bits.push(data[13]);
        let path = out.path().join(format!("{i}.spz"));
        std::fs::write(&path, data).unwrap();
        files.push(path);
    }
    assert_eq!(files.len(), times.len());
    let read = read_with(
        Command::new("node")
            .arg(node.join("spz.mjs"))
            .args(&files)
            .current_dir(&node),
    );
    eprintln!("spz read by {}", read["library"]);
    let mut spz_db = f64::INFINITY;
    let files_read = read["files"].as_array().unwrap();
    for (((t, set), file), bits) in want.iter().zip(files_read).zip(&fractional_bits) {
        let got = set_of(file);
        let w = worst(&got, &spz_range(set));
        let bounds = spz_bounds(*bits);
        for (k, (v, bound)) in w.iter().zip(bounds).enumerate() {
            assert!(
                *v <= bound,
                "spz column {k} off by {v} (bound {bound}) at {t} s"
            );
        }
        spz_db = spz_db.min(render_psnr(&got, set));
    }

    // .splatv, with the reader written from its specification.
    let mut body = range.clone();
    body["format"] = json!("splatv");
    let (splatv, headers) = export(&server, &clip, body);
    let fit = headers["x-c4g-fit-position-error"]
        .to_str()
        .unwrap()
        .to_owned();
    let max_fit: f64 = fit
        .split(',')
        .find_map(|p| p.trim().strip_prefix("max="))
        .unwrap()
        .parse()
        .unwrap();
    let splatv_path = out.path().join("clip.splatv");
    std::fs::write(&splatv_path, &splatv).unwrap();
    let list = times
        .iter()
        .map(|t| t.to_string())
        .collect::<Vec<_>>()
        .join(",");
    let read = read_with(
        Command::new(&python)
            .args(["-m", "c4g.formats.splatv"])
            .arg(&splatv_path)
            .args(["--times", &list])
            .current_dir(workspace().join("models/python")),
    );
    let model = splatv::decode(&splatv).unwrap();
    let mut splatv_db = f64::INFINITY;
    let mut splatv_worst = 0f64;
    for ((t, set), frame) in want.iter().zip(read["frames"].as_array().unwrap()) {
        let got = set_of(frame);
        assert_eq!(got.len(), n);
        // The spec-written reader evaluates the file as the Rust model does, to f32 rounding
        // (two implementations of exp and the normalisation: a few ulps).
        let ours = worst(&got, &model.at(*t));
        for (k, v) in ours.iter().enumerate() {
            assert!(
                *v <= 1e-5,
                "the readers differ in column {k} by {v} at {t} s"
            );
        }
        splatv_worst = splatv_worst.max(worst(&got, set)[0]);
        splatv_db = splatv_db.min(render_psnr(&got, set));
    }
    // What the reader evaluates strays no further than the server says (f32 slack).
    assert!(
        splatv_worst <= max_fit * (1.0 + 1e-3) + 1e-5,
        "the reader's positions are off by {splatv_worst}, the server stated {fit}"
    );

    let f32_bytes = (56 * n) as f64;
    let per_set = |bytes: usize| bytes as f64 / times.len() as f64;
    eprintln!(
        "{} sets of {n} Gaussians; bytes a set (fraction of C4GS f32, {f32_bytes}): ply.zip {:.0} \
         ({:.2}), spz.zip {:.0} ({:.2}; entries {:.0}), splatv {:.0} ({:.3}); spz render {spz_db:.1} \
         dB; splatv fit {fit}, reader off by {splatv_worst:.2e}, render {splatv_db:.1} dB",
        times.len(),
        per_set(ply_zip.len()),
        per_set(ply_zip.len()) / f32_bytes,
        per_set(spz_zip.len()),
        per_set(spz_zip.len()) / f32_bytes,
        per_set(spz_bytes),
        per_set(splatv.len()),
        per_set(splatv.len()) / f32_bytes,
    );
    assert!(spz_db >= SPZ_MIN_DB, "spz render {spz_db} dB");
    assert!(splatv_db >= SPLATV_MIN_DB, "splatv render {splatv_db} dB");
}

/// The bounds `formats/src/spz.rs` states for a file of `bits` fractional bits:
/// position (half a step), `ln` scale, rotation angle, opacity, colour; each with 1e-6 of slack
/// for the f32 rounding of the values compared.
fn spz_bounds(bits: u8) -> [f64; 5] {
    let slack = 1e-6;
    [
        0.5 / f64::from(1u32 << bits) + slack,
        f64::from(spz::LOG_SCALE_ERROR) + slack,
        f64::from(spz::ROTATION_ERROR) + slack,
        f64::from(spz::OPACITY_ERROR) + slack,
        f64::from(spz::COLOR_ERROR) + slack,
    ]
}

/// `set` with its scales clamped to what SPZ stores (`e^−10` to `e^5.9375`; the module doc).
fn spz_range(set: &GaussianSet) -> GaussianSet {
    let (lo, hi) = ((-10f32).exp(), 5.9375f32.exp());
    GaussianSet::new(
        set.positions().to_vec(),
        set.scales()
            .iter()
            .map(|s| s.map(|v| v.clamp(lo, hi)))
            .collect(),
        set.rotations().to_vec(),
        set.opacities().to_vec(),
        set.colors().to_vec(),
    )
    .unwrap()
}

#[test]
fn exports_refuse_what_they_cannot_make() {
    if !ort_available() {
        return;
    }
    let server = Server::start_env(&[("C4G_MAX_EXPORT_MIB", "0")], &[]);
    let clip = upload_synthetic(&server);
    let path = format!("/v1/clips/{clip}/export");
    for (body, status, says) in [
        (json!({"format": "obj"}), 400, "unknown variant `obj`"),
        (json!({"fps": 10}), 400, "missing field `format`"),
        (
            json!({"format": "splatv", "start": 0.5, "end": 0.1}),
            400,
            "after end",
        ),
        (
            json!({"format": "ply_zip", "step": 0.1, "fps": 10}),
            400,
            "not both",
        ),
        (
            json!({"format": "ply_zip", "fps": 1e6}),
            413,
            "sets in one stream",
        ),
        (
            json!({"format": "spz_zip", "fps": 5000}),
            413,
            "frames in one zip",
        ),
        (json!({"format": "ply_zip"}), 413, "C4G_MAX_EXPORT_MIB"),
        (json!({"format": "splatv"}), 413, "C4G_MAX_EXPORT_MIB"),
    ] {
        let response = post(&server, &path, body.clone());
        let got = response.status().as_u16();
        let text = response.text().unwrap();
        assert_eq!(got, status, "{body}: {text}");
        assert!(text.contains(says), "{body}: {text}");
    }
    let response = post(
        &server,
        "/v1/clips/000000000000000000000000/export",
        json!({"format": "splatv"}),
    );
    assert_eq!(response.status(), 404);
}
