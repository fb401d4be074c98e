//! How much to trust an alignment: one number in `[0, 1]` from three things a wrong camera
//! cannot fake all at once.
//!
//! `confidence = coverage term · fit term · conditioning term`, each in `[0, 1]`:
//! - **coverage**: the mean rendered alpha over the frame at the recovered camera, saturating at
//!   [`FULL_COVERAGE`]. A set that covers nothing of the frame says nothing about the camera
//!   (every Gaussian out of view gives 0);
//! - **fit**: `1 / (1 + (e / FIT_SCALE)²)`, with `e = √(2·residual)` the RMS-equivalent of the
//!   final alpha-weighted Huber residual (exactly the RMS colour error where every residual is
//!   within Huber's δ). A camera that leaves the render far from the frame has not explained it;
//! - **conditioning**: the Gauss–Newton matrix's smallest eigenvalue over its largest, each
//!   parameter scaled to a unit diagonal, mapped by `c / (c + CONDITIONING_HALF)` (one half at
//!   [`CONDITIONING_HALF`]). A view in which some motion of the camera does not change the image
//!   (a single round splat, which cannot tell a turn from a shift) has a direction the data do not
//!   determine, and the recovered camera is then one of many.
//!
//! Not the residual's drop from the start: an alignment started at the right camera drops
//! nothing and is as trustworthy as one that travelled. Convergence is reported beside it, not
//! folded in: an alignment that ran out of iterations may still be close.
//!
//! Measured on the tests' synthetic scenes (`tests/alignment.rs`, `tests/timing.rs`): recovered
//! cameras 0.93 to 0.96; with a 14×14 patch the set does not explain pasted over the frame (5% of
//! it) 0.53, the camera still within 0.02°; a start that stopped in a local minimum about 0.25;
//! a single round splat 1e-13; nothing in view 0. A real frame's reconstruction error
//! lowers the fit term of every alignment alike: compare confidences within a clip.

/// Mean alpha at which the coverage term reaches 1: a tenth of the frame fully covered.
pub const FULL_COVERAGE: f64 = 0.1;
/// RMS-equivalent colour residual at which the fit term is one half (about 20 dB PSNR).
pub const FIT_SCALE: f64 = 0.1;
/// Conditioning at which its term is one half: random scenes that pin the camera down measure
/// 0.016 to 0.023, a single round splat 1e-16.
pub const CONDITIONING_HALF: f64 = 1e-3;

/// The confidence of an alignment (module documentation) from its final coverage (mean alpha),
/// residual (mean Huber cost per weighted channel) and conditioning.
pub(super) fn confidence(coverage: f64, residual: f64, conditioning: f64) -> f64 {
    let coverage_term = (coverage / FULL_COVERAGE).clamp(0.0, 1.0);
    let rms = (2.0 * residual.max(0.0)).sqrt();
    let fit_term = 1.0 / (1.0 + (rms / FIT_SCALE).powi(2));
    let c = conditioning.clamp(0.0, 1.0);
    let conditioning_term = c / (c + CONDITIONING_HALF);
    let value = coverage_term * fit_term * conditioning_term;
    if value.is_finite() {
        value.clamp(0.0, 1.0)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn confidence_is_high_only_when_all_three_terms_are() {
        let good = confidence(0.5, 1e-6, 0.05);
        assert!(good > 0.9, "{good}");
        assert_eq!(confidence(0.0, 0.0, 0.05), 0.0, "nothing covered");
        assert!(confidence(0.5, 0.5, 0.05) < 0.05, "a poor fit");
        assert!(confidence(0.5, 1e-6, 1e-6) < 0.01, "a degenerate view");
        assert_eq!(confidence(f64::NAN, 0.0, 0.5), 0.0);
    }
}
