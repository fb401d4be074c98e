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
//! without a panic and writes back to bytes that decode.
#![no_main]

use c4g_formats::{c4gs, c4gv, frames_zip, ply, splat, splatv, spz};
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};

fn renders_finite(set: &GaussianSet) {
    let camera = Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        16,
        16,
        Default::default(),
    )
    .expect("camera");
    let image = CpuRasterizer::new()
        .render(set, &camera, &RenderOptions::default())
        .expect("a decoded set renders");
    for (name, values) in [
        ("rgb", &image.rgb),
        ("alpha", &image.alpha),
        ("depth", &image.depth),
    ] {
        assert!(values.iter().all(|v| v.is_finite()), "{name} is not finite");
    }
}

libfuzzer_sys::fuzz_target!(|input: &[u8]| {
    let Some((&format, bytes)) = input.split_first() else {
        return;
    };
    match format % 8 {
        0 => {
            if let Ok(set) = ply::decode(bytes) {
                renders_finite(&set);
                let again = ply::decode(&ply::encode(&set)).expect("ply round trip");
                assert_eq!(again.len(), set.len());
            }
        }
        1 => {
            if let Ok(set) = splat::decode(bytes) {
                renders_finite(&set);
                let again = splat::decode(&splat::encode(&set)).expect("splat round trip");
                assert!(again.len() <= set.len());
            }
        }
        3 => {
            let whole = c4gv::decode(bytes);
            // Fed byte by byte, a reader sees the same frames (and fails where the whole fails).
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
                assert!(!failed, "whole it decodes, byte by byte it fails");
                assert_eq!(frames.len(), trickled.len());
                for (time, set) in &frames {
                    set.validate().expect("C4GV yields valid sets");
                    renders_finite(set);
                    assert!(time.is_finite());
                }
            }
        }
        4 => {
            if let Ok(set) = spz::decode(bytes) {
                renders_finite(&set);
                let again = spz::decode(&spz::encode(&set).expect("a decoded .spz writes"))
                    .expect("spz round trip");
                assert_eq!(again.len(), set.len());
            }
        }
        5 => {
            if let Ok((_, frames)) = frames_zip::decode(bytes, 1 << 20) {
                for (time, set) in &frames {
                    assert!(time.is_finite());
                    renders_finite(set);
                }
            }
        }
        6 => {
            if let Ok(model) = splatv::decode(bytes) {
                for t in [-1.0, 0.0, 0.5, 1e9] {
                    assert_eq!(model.at(t).len(), model.len());
                }
                splatv::decode(&model.encode()).expect("splatv round trip");
            }
        }
        _ => {
            if let Ok(frames) = c4gs::decode(bytes) {
                let refs = frames.iter().map(|(t, s)| (*t, s));
                let written = c4gs::encode(refs, c4gs::Precision::F32).expect("c4gs encode");
                let again = c4gs::decode(&written).expect("c4gs round trip");
                assert_eq!(again.len(), frames.len());
                let bits = |s: &GaussianSet| -> Vec<u32> {
                    s.to_canonical().iter().map(|v| v.to_bits()).collect()
                };
                for ((t0, a), (t1, b)) in frames.iter().zip(&again) {
                    assert_eq!(t0.to_bits(), t1.to_bits());
                    assert_eq!(bits(a), bits(b), "C4GS f32 is not exact");
                }
            }
        }
    }
});
