//! A fitted scene as bytes, stored with its clip: [`to_bytes`] and [`from_bytes`].
//!
//! The format (version 1), every number little-endian:
//!
//! | bytes | what |
//! |---|---|
//! | 4 | magic `C4GF` |
//! | 4 | version, u32 (1) |
//! | 4 | keyframes `K`, u32 (≥ 1) |
//! | 4 | Gaussians `N`, u32 |
//! | 8·K | keyframe times, f64 seconds, finite and strictly increasing |
//! | N | static mask, one byte a Gaussian: 0 or 1 |
//! | K · 56·N | each keyframe's set as columns of f32: positions (3·N), scales (3·N), rotations `w, x, y, z` (4·N), opacities (N), colours (3·N) |
//!
//! Nothing follows: the length is exactly `16 + 8·K + N + 56·K·N`, which is checked before
//! anything is allocated, so a header that claims absurd counts costs nothing. Columns are
//! written directly rather than through `c4g-formats`' C4GS packing: the fit crate would otherwise
//! pull in the formats crate's zip, zstd and JSON for five loops, and C4GS carries per-time
//! metadata a fitted scene does not have.
//!
//! Feature vectors (a [`GaussianSet`]'s optional block) are not stored: fitted scenes carry none
//! (the fit's sets are built from its parameters), and a scene read back has none. The values
//! read must satisfy [`GaussianSet::validate`] (finite, scales ≥ 0, unit rotations, opacities in
//! [0, 1], colours ≥ 0): no NaN reaches a served scene from a stored one.

use c4g_scene::GaussianSet;

use crate::error::FitError;
use crate::scene::FittedScene;

/// The first four bytes of a stored fitted scene.
pub const MAGIC: [u8; 4] = *b"C4GF";
/// The version [`to_bytes`] writes and [`from_bytes`] reads.
pub const VERSION: u32 = 1;

const HEADER: usize = 16;
/// f32 values a Gaussian at one keyframe: 3 + 3 + 4 + 1 + 3.
const FLOATS: usize = 14;

/// The scene's bytes. A scene whose sets differ in length (its fields are public; [`FittedScene::new`]
/// refuses one) writes bytes that [`from_bytes`] refuses rather than a silently different scene.
pub fn to_bytes(scene: &FittedScene) -> Vec<u8> {
    let (k, n) = (scene.times.len(), scene.len());
    let mut out = Vec::with_capacity(HEADER + 8 * k + n + 4 * FLOATS * k * n);
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&count(k).to_le_bytes());
    out.extend_from_slice(&count(n).to_le_bytes());
    for t in &scene.times {
        out.extend_from_slice(&t.to_le_bytes());
    }
    out.extend(scene.static_mask.iter().map(|&s| u8::from(s)));
    let mut put = |v: f32| out.extend_from_slice(&v.to_le_bytes());
    for set in &scene.sets {
        set.positions().iter().flatten().for_each(|&v| put(v));
        set.scales().iter().flatten().for_each(|&v| put(v));
        set.rotations().iter().flatten().for_each(|&v| put(v));
        set.opacities().iter().for_each(|&v| put(v));
        set.colors().iter().flatten().for_each(|&v| put(v));
    }
    out
}

/// A count as the header's u32 (saturating: a count that large cannot match the length check).
fn count(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

/// The scene stored in `bytes`. Refuses (never panics on) anything that is not exactly a scene
/// [`to_bytes`] could have written from a valid one: a wrong magic or version, a length that does
/// not match the counts, no keyframe, times not finite or not strictly increasing, a static mask
/// byte other than 0 or 1, or a value [`GaussianSet::validate`] refuses.
pub fn from_bytes(bytes: &[u8]) -> Result<FittedScene, FitError> {
    let bad = |why: String| FitError::Invalid(format!("not a stored fitted scene: {why}"));
    if bytes.len() < HEADER {
        return Err(bad(format!(
            "{} bytes, shorter than the {HEADER}-byte header",
            bytes.len()
        )));
    }
    if bytes[..4] != MAGIC {
        return Err(bad("it does not start with C4GF".into()));
    }
    let word =
        |at: usize| u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
    let version = word(4);
    if version != VERSION {
        return Err(bad(format!(
            "version {version}; this build reads version {VERSION}"
        )));
    }
    let (k, n) = (u64::from(word(8)), u64::from(word(12)));
    if k == 0 {
        return Err(bad("it holds no keyframe".into()));
    }
    // With k and n up to 2³², 56·k·n can pass u64's range: u128 holds it.
    let expected =
        HEADER as u128 + 8 * u128::from(k) + u128::from(n) + 56 * u128::from(k) * u128::from(n);
    if expected != bytes.len() as u128 {
        return Err(bad(format!(
            "{k} keyframes of {n} Gaussians take {expected} bytes, not {}",
            bytes.len()
        )));
    }
    // The length matched, so both counts fit in memory the caller already holds.
    let (k, n) = (k as usize, n as usize);
    let mut at = HEADER;
    let mut times = Vec::with_capacity(k);
    for _ in 0..k {
        let mut b = [0u8; 8];
        b.copy_from_slice(&bytes[at..at + 8]);
        times.push(f64::from_le_bytes(b));
        at += 8;
    }
    if times.iter().any(|t| !t.is_finite()) || times.windows(2).any(|w| w[0] >= w[1]) {
        return Err(bad(format!(
            "keyframe times {times:?} are not finite and strictly increasing"
        )));
    }
    let mask = &bytes[at..at + n];
    if let Some(b) = mask.iter().find(|&&b| b > 1) {
        return Err(bad(format!("a static mask byte is {b}, not 0 or 1")));
    }
    let static_mask = mask.iter().map(|&b| b == 1).collect();
    at += n;
    let mut floats = bytes[at..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]));
    let mut sets = Vec::with_capacity(k);
    for key in 0..k {
        let set = read_set(&mut floats, n)?;
        set.validate()
            .map_err(|e| bad(format!("keyframe {key}: {e}")))?;
        sets.push(set);
    }
    Ok(FittedScene {
        times,
        sets,
        static_mask,
    })
}

/// One keyframe's columns; the length check guarantees the values are there.
fn read_set(floats: &mut impl Iterator<Item = f32>, n: usize) -> Result<GaussianSet, FitError> {
    let mut next = || floats.next().unwrap_or(f32::NAN);
    let positions = (0..n).map(|_| [next(), next(), next()]).collect();
    let scales = (0..n).map(|_| [next(), next(), next()]).collect();
    let rotations = (0..n).map(|_| [next(), next(), next(), next()]).collect();
    let opacities = (0..n).map(|_| next()).collect();
    let colors = (0..n).map(|_| [next(), next(), next()]).collect();
    Ok(GaussianSet::new(
        positions, scales, rotations, opacities, colors,
    )?)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn set(n: usize, phase: f32) -> GaussianSet {
        let f = |i: usize, k: f32| ((i as f32 + 1.0) * k + phase).sin();
        GaussianSet::new(
            (0..n)
                .map(|i| [f(i, 1.0), f(i, 2.0), 2.0 + f(i, 3.0)])
                .collect(),
            (0..n).map(|i| [0.1 + 0.05 * f(i, 4.0); 3]).collect(),
            (0..n)
                .map(|i| {
                    let a = 0.5 * f(i, 5.0);
                    [a.cos(), a.sin(), 0.0, 0.0]
                })
                .collect(),
            (0..n).map(|i| 0.5 + 0.4 * f(i, 6.0)).collect(),
            (0..n).map(|i| [0.5 + 0.5 * f(i, 7.0); 3]).collect(),
        )
        .unwrap()
    }

    fn scene(n: usize) -> FittedScene {
        let mut s = FittedScene::new(
            [0.0, 0.4, 1.1]
                .iter()
                .enumerate()
                .map(|(k, &t)| (t, set(n, k as f32 * 0.3)))
                .collect(),
        )
        .unwrap();
        for (i, m) in s.static_mask.iter_mut().enumerate() {
            *m = i % 3 == 0;
        }
        s
    }

    fn message(bytes: &[u8]) -> String {
        from_bytes(bytes).unwrap_err().to_string()
    }

    #[test]
    fn a_scene_round_trips_bit_for_bit() {
        for n in [0, 1, 7] {
            let s = scene(n);
            let bytes = to_bytes(&s);
            assert_eq!(bytes.len(), 16 + 8 * 3 + n + 56 * 3 * n);
            assert_eq!(&bytes[..4], b"C4GF");
            assert_eq!(from_bytes(&bytes).unwrap(), s);
        }
    }

    #[test]
    fn features_are_not_stored() {
        let mut s = scene(2);
        s.sets[0] = s.sets[0]
            .clone()
            .with_features(c4g_scene::FeatureBlock::new(1, vec![1.0, 2.0]).unwrap())
            .unwrap();
        let back = from_bytes(&to_bytes(&s)).unwrap();
        assert!(back.sets.iter().all(|set| set.features().is_none()));
        assert_eq!(back, scene(2));
    }

    #[test]
    fn a_wrong_magic_version_or_length_is_refused_with_its_reason() {
        let good = to_bytes(&scene(3));
        assert!(message(&good[..10]).contains("header"));
        let mut magic = good.clone();
        magic[0] = b'X';
        assert!(message(&magic).contains("C4GF"));
        let mut version = good.clone();
        version[4] = 2;
        assert!(message(&version).contains("version 2"));
        assert!(message(&good[..good.len() - 1]).contains("bytes"));
        let mut longer = good.clone();
        longer.push(0);
        assert!(message(&longer).contains("bytes"));
        assert!(message(b"garbage garbage garbage").contains("C4GF"));
    }

    #[test]
    fn absurd_counts_are_refused_before_allocating() {
        let mut bytes = b"C4GF".to_vec();
        bytes.extend_from_slice(&1u32.to_le_bytes());
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(message(&bytes).contains("bytes"));
        let mut none = b"C4GF".to_vec();
        none.extend_from_slice(&1u32.to_le_bytes());
        none.extend_from_slice(&[0; 8]);
        assert!(message(&none).contains("no keyframe"));
    }

    #[test]
    fn non_finite_values_and_bad_times_and_masks_are_refused() {
        let s = scene(2);
        let good = to_bytes(&s);
        let float_at = 16 + 8 * 3 + 2;
        for bad in [f32::NAN, f32::INFINITY] {
            let mut b = good.clone();
            b[float_at + 8..float_at + 12].copy_from_slice(&bad.to_le_bytes());
            assert!(message(&b).contains("keyframe 0"), "{}", message(&b));
        }
        let mut t = s.clone();
        t.times[1] = t.times[0];
        assert!(message(&to_bytes(&t)).contains("strictly increasing"));
        t.times[1] = f64::NAN;
        assert!(message(&to_bytes(&t)).contains("strictly increasing"));
        let mut mask = good.clone();
        mask[16 + 24] = 7;
        assert!(message(&mask).contains("mask"));
        let mut opacity = s.clone();
        opacity.sets[2] = GaussianSet::new(
            s.sets[2].positions().to_vec(),
            s.sets[2].scales().to_vec(),
            s.sets[2].rotations().to_vec(),
            vec![1.5, 0.5],
            s.sets[2].colors().to_vec(),
        )
        .unwrap();
        assert!(message(&to_bytes(&opacity)).contains("keyframe 2"));
    }

    #[test]
    fn sets_of_different_lengths_write_bytes_that_are_refused() {
        let mut s = scene(3);
        s.sets[1] = set(2, 0.0);
        assert!(from_bytes(&to_bytes(&s)).is_err());
    }

    /// Every truncation, and a few thousand single-byte corruptions, of a real scene's bytes: an
    /// error or a valid scene, never a panic, and never a non-finite value.
    #[test]
    fn truncated_or_corrupted_bytes_never_panic_nor_yield_non_finite_values() {
        let good = to_bytes(&scene(4));
        for len in 0..good.len() {
            assert!(from_bytes(&good[..len]).is_err(), "truncated to {len}");
        }
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..5000 {
            let mut b = good.clone();
            let at = (next() % b.len() as u64) as usize;
            b[at] = next() as u8;
            if let Ok(s) = from_bytes(&b) {
                for set in &s.sets {
                    assert!(set.validate().is_ok());
                }
                assert!(s.times.iter().all(|t| t.is_finite()));
            }
        }
        for len in 0..64 {
            let noise: Vec<u8> = (0..len).map(|_| next() as u8).collect();
            assert!(from_bytes(&noise).is_err());
        }
    }
}
