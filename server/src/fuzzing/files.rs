//! The readers of Gaussian files and payloads: 3DGS `.ply`, `.splat`, the `C4GS` codec, the
//! compact 4D stream `C4GV`, and the 4D exports' `.spz`, frames zip and `.splatv`. Input:
//! `[format]bytes`, the format byte taken modulo 8.
//!
//! `.ply` and `.splat` files come from other tools, so their readers return what a file holds
//! (activated), which need not meet the canonical invariants (3DGS colours from negative SH
//! coefficients are below 0, a huge log-scale is an infinite scale). What is held of them: a set
//! that decodes renders with the CPU rasterizer to finite pixels, and the writer's bytes read
//! back (`.splat` leaves out what it cannot write). `C4GS` is our own: its f32 round trip is
//! exact, bit for bit. A `.spz` that decodes writes again (its values are inside what SPZ holds)
//! and renders; a frames zip's sets render; a `.splatv` that decodes evaluates at any time
//! and writes back to bytes that decode.

use c4g_formats::{c4gs, c4gv, frames_zip, ply, splat, splatv, spz};
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};

/// `Err` with `message` unless `holds`.
fn check(holds: bool, message: impl FnOnce() -> String) -> Result<(), String> {
    if holds { Ok(()) } else { Err(message()) }
}

fn renders_finite(set: &GaussianSet) -> Result<(), String> {
    let camera = Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        16,
        16,
        Default::default(),
    )
    .map_err(|e| format!("the probe camera: {e}"))?;
    let image = CpuRasterizer::new()
        .render(set, &camera, &RenderOptions::default())
        .map_err(|e| format!("a decoded set does not render: {e}"))?;
    for (name, values) in [
        ("rgb", &image.rgb),
        ("alpha", &image.alpha),
        ("depth", &image.depth),
    ] {
        check(values.iter().all(|v| v.is_finite()), || {
            format!("{name} is not finite")
        })?;
    }
    Ok(())
}

/// A Gaussian file or payload, `[format]bytes`.
pub fn gaussian_files(input: &[u8]) -> Result<(), String> {
    let Some((&format, bytes)) = input.split_first() else {
        return Ok(());
    };
    match format % 8 {
        0 => {
            if let Ok(set) = ply::decode(bytes) {
                renders_finite(&set)?;
                let again =
                    ply::decode(&ply::encode(&set)).map_err(|e| format!("ply round trip: {e}"))?;
                check(again.len() == set.len(), || "ply round trip length".into())?;
            }
        }
        1 => {
            if let Ok(set) = splat::decode(bytes) {
                renders_finite(&set)?;
                let again = splat::decode(&splat::encode(&set))
                    .map_err(|e| format!("splat round trip: {e}"))?;
                check(again.len() <= set.len(), || "splat round trip grew".into())?;
            }
        }
        3 => c4gv_stream(bytes)?,
        4 => {
            if let Ok(set) = spz::decode(bytes) {
                renders_finite(&set)?;
                let written = spz::encode(&set).map_err(|e| format!("a decoded .spz: {e}"))?;
                let again = spz::decode(&written).map_err(|e| format!("spz round trip: {e}"))?;
                check(again.len() == set.len(), || "spz round trip length".into())?;
            }
        }
        5 => {
            if let Ok((_, frames)) = frames_zip::decode(bytes, 1 << 20) {
                for (time, set) in &frames {
                    check(time.is_finite(), || format!("frames zip time {time}"))?;
                    renders_finite(set)?;
                }
            }
        }
        6 => {
            if let Ok(model) = splatv::decode(bytes) {
                for t in [-1.0, 0.0, 0.5, 1e9] {
                    check(model.at(t).len() == model.len(), || {
                        format!("splatv at {t} changes the count")
                    })?;
                }
                splatv::decode(&model.encode()).map_err(|e| format!("splatv round trip: {e}"))?;
            }
        }
        _ => c4gs_exact(bytes)?,
    }
    Ok(())
}

/// Fed byte by byte, a C4GV reader sees the same frames (and fails where the whole fails).
fn c4gv_stream(bytes: &[u8]) -> Result<(), String> {
    let whole = c4gv::decode(bytes);
    let mut decoder = c4gv::Decoder::new();
    let mut trickled = Vec::new();
    let mut failed = false;
    for byte in bytes {
        decoder.feed(std::slice::from_ref(byte));
        loop {
            match decoder.next_frame() {
                Ok(Some(frame)) => trickled.push(frame),
                Ok(None) => break,
                Err(_) => {
                    failed = true;
                    break;
                }
            }
        }
        if failed {
            break;
        }
    }
    if let Ok(frames) = whole {
        check(!failed, || "whole it decodes, byte by byte it fails".into())?;
        check(frames.len() == trickled.len(), || {
            format!(
                "{} frames whole, {} byte by byte",
                frames.len(),
                trickled.len()
            )
        })?;
        for (time, set) in &frames {
            set.validate()
                .map_err(|e| format!("C4GV yields an invalid set: {e}"))?;
            renders_finite(set)?;
            check(time.is_finite(), || format!("C4GV time {time}"))?;
        }
    }
    Ok(())
}

/// `C4GS` at f32 reads back bit for bit.
fn c4gs_exact(bytes: &[u8]) -> Result<(), String> {
    let Ok(frames) = c4gs::decode(bytes) else {
        return Ok(());
    };
    let refs = frames.iter().map(|(t, s)| (*t, s));
    let written =
        c4gs::encode(refs, c4gs::Precision::F32).map_err(|e| format!("c4gs encode: {e}"))?;
    let again = c4gs::decode(&written).map_err(|e| format!("c4gs round trip: {e}"))?;
    check(again.len() == frames.len(), || {
        "c4gs round trip length".into()
    })?;
    let bits =
        |s: &GaussianSet| -> Vec<u32> { s.to_canonical().iter().map(|v| v.to_bits()).collect() };
    for ((t0, a), (t1, b)) in frames.iter().zip(&again) {
        check(t0.to_bits() == t1.to_bits(), || {
            "C4GS time is not exact".into()
        })?;
        check(bits(a) == bits(b), || "C4GS f32 is not exact".into())?;
    }
    Ok(())
}
