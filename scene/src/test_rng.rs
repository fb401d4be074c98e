//! What the crate's unit tests share: a small deterministic generator (splitmix64), so that the
//! scenes and clips they make are the same every run, and quaternion normalisation.

/// splitmix64: uniform in [0, 1) from a 64-bit state.
pub struct Rng(pub u64);

impl Rng {
    /// The next value in [0, 1).
    // A generator of floats for tests, not an iterator: `next` reads as what it is.
    #[allow(clippy::should_implement_trait)]
    pub fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [lo, hi), as f32.
    pub fn range(&mut self, lo: f64, hi: f64) -> f32 {
        (lo + (hi - lo) * self.next()) as f32
    }
}

/// `q` normalised, as f32.
pub fn unit(q: [f64; 4]) -> [f32; 4] {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    q.map(|v| (v / n) as f32)
}
