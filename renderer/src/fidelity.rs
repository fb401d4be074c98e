//! Image quality metrics: how close a render is to a target frame.
//!
//! Both take interleaved RGB planes (3 floats a pixel, row-major, values nominally in 0..1) and an
//! optional per-pixel mask (`true`: the pixel counts), and compute in f64.
//! - [`psnr`]: `10 · log10(1 / MSE)` (peak value 1) over the masked pixels and all three channels;
//!   identical images give `+∞`.
//! - [`ssim`]: the standard SSIM of Wang et al. with an 11×11 Gaussian window (σ = 1.5,
//!   normalised), K1 = 0.01, K2 = 0.03 and dynamic range 1, computed per channel on the "valid"
//!   window positions (the image shrinks by 5 pixels on each side) and averaged over positions
//!   and channels. With a mask, the positions averaged are those whose window *centre* is masked.
//!
//! The float64 NumPy version these are checked against is `models/python/c4g/raster/metrics.py`.

use c4g_scene::SceneError;

/// Side of the SSIM window.
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM window's Gaussian, in pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM's luminance constant factor (C1 = (K1 · L)², L = 1).
pub const SSIM_K1: f64 = 0.01;
/// SSIM's contrast constant factor (C2 = (K2 · L)², L = 1).
pub const SSIM_K2: f64 = 0.03;

/// Peak signal-to-noise ratio in dB of `a` against `b` with peak value 1.
pub fn psnr(
    a: &[f32],
    b: &[f32],
    width: u32,
    height: u32,
    mask: Option<&[bool]>,
) -> Result<f64, SceneError> {
    let (w, h) = check(a, b, width, height, mask)?;
    let mut sum = 0.0f64;
    let mut count = 0usize;
    for p in 0..w * h {
        if mask.is_none_or(|m| m[p]) {
            for c in 0..3 {
                let d = f64::from(a[3 * p + c]) - f64::from(b[3 * p + c]);
                sum += d * d;
            }
            count += 3;
        }
    }
    if count == 0 {
        return Err(invalid("the mask selects no pixel"));
    }
    Ok(-10.0 * (sum / count as f64).log10())
}

/// Structural similarity of `a` and `b`, averaged over the three channels.
pub fn ssim(
    a: &[f32],
    b: &[f32],
    width: u32,
    height: u32,
    mask: Option<&[bool]>,
) -> Result<f64, SceneError> {
    let (w, h) = check(a, b, width, height, mask)?;
    if w < SSIM_WINDOW || h < SSIM_WINDOW {
        return Err(invalid(format!(
            "SSIM needs at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {w}x{h}"
        )));
    }
    let half = SSIM_WINDOW / 2;
    let (vw, vh) = (w - 2 * half, h - 2 * half);
    let counted: Vec<bool> = (0..vw * vh)
        .map(|k| mask.is_none_or(|m| m[(k / vw + half) * w + k % vw + half]))
        .collect();
    let positions = counted.iter().filter(|c| **c).count();
    if positions == 0 {
        return Err(invalid("the mask selects no SSIM window centre"));
    }
    let c1 = (SSIM_K1 * 1.0).powi(2);
    let c2 = (SSIM_K2 * 1.0).powi(2);
    let kernel = ssim_window();
    let mut total = 0.0;
    for channel in 0..3 {
        let x: Vec<f64> = (0..w * h).map(|p| f64::from(a[3 * p + channel])).collect();
        let y: Vec<f64> = (0..w * h).map(|p| f64::from(b[3 * p + channel])).collect();
        let blur = |f: &dyn Fn(usize) -> f64| filter_valid(&kernel, w, h, f);
        let mu_x = blur(&|p| x[p]);
        let mu_y = blur(&|p| y[p]);
        let xx = blur(&|p| x[p] * x[p]);
        let yy = blur(&|p| y[p] * y[p]);
        let xy = blur(&|p| x[p] * y[p]);
        for k in (0..vw * vh).filter(|&k| counted[k]) {
            let (mx, my) = (mu_x[k], mu_y[k]);
            let (sxx, syy, sxy) = (xx[k] - mx * mx, yy[k] - my * my, xy[k] - mx * my);
            total += ((2.0 * mx * my + c1) * (2.0 * sxy + c2))
                / ((mx * mx + my * my + c1) * (sxx + syy + c2));
        }
    }
    Ok(total / (3 * positions) as f64)
}

/// The normalised 1D Gaussian whose outer product is the SSIM window (the D-SSIM loss's
/// gradient in `c4g-optim` filters with the same one).
pub fn ssim_window() -> [f64; SSIM_WINDOW] {
    let half = (SSIM_WINDOW / 2) as f64;
    let mut k = [0.0; SSIM_WINDOW];
    for (i, v) in k.iter_mut().enumerate() {
        let d = i as f64 - half;
        *v = (-d * d / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let sum: f64 = k.iter().sum();
    k.map(|v| v / sum)
}

/// `f` (a plane given pixel by pixel) filtered by the separable window, valid positions only:
/// `(w − 10) · (h − 10)` values, row-major.
pub fn filter_valid(
    kernel: &[f64; SSIM_WINDOW],
    w: usize,
    h: usize,
    f: &dyn Fn(usize) -> f64,
) -> Vec<f64> {
    let vw = w - SSIM_WINDOW + 1;
    let vh = h - SSIM_WINDOW + 1;
    let mut rows = vec![0.0; vw * h];
    for y in 0..h {
        for x in 0..vw {
            rows[y * vw + x] = (0..SSIM_WINDOW).map(|i| kernel[i] * f(y * w + x + i)).sum();
        }
    }
    let mut out = vec![0.0; vw * vh];
    for y in 0..vh {
        for x in 0..vw {
            out[y * vw + x] = (0..SSIM_WINDOW)
                .map(|i| kernel[i] * rows[(y + i) * vw + x])
                .sum();
        }
    }
    out
}

/// Checks sizes and values; gives the size as `usize`.
fn check(
    a: &[f32],
    b: &[f32],
    width: u32,
    height: u32,
    mask: Option<&[bool]>,
) -> Result<(usize, usize), SceneError> {
    let (w, h) = (width as usize, height as usize);
    let pixels = w
        .checked_mul(h)
        .filter(|p| *p > 0)
        .ok_or_else(|| invalid(format!("image size {width}x{height} is empty")))?;
    for (name, plane) in [("first", a), ("second", b)] {
        if plane.len() != pixels * 3 {
            return Err(invalid(format!(
                "the {name} image holds {} values, a {w}x{h} RGB image {}",
                plane.len(),
                pixels * 3
            )));
        }
        if !plane.iter().all(|v| v.is_finite()) {
            return Err(invalid(format!("the {name} image has non-finite values")));
        }
    }
    if let Some(m) = mask
        && m.len() != pixels
    {
        return Err(invalid(format!(
            "the mask holds {} values for {pixels} pixels",
            m.len()
        )));
    }
    Ok((w, h))
}

fn invalid(reason: impl Into<String>) -> SceneError {
    SceneError::InvalidImage(reason.into())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: usize, h: usize, phase: f32) -> Vec<f32> {
        (0..w * h * 3)
            .map(|i| (((i * 7919) % 101) as f32 / 100.0 + phase).fract())
            .collect()
    }

    #[test]
    fn identical_images_score_infinite_psnr_and_ssim_one() {
        let a = ramp(32, 24, 0.0);
        assert_eq!(psnr(&a, &a, 32, 24, None).unwrap(), f64::INFINITY);
        assert!((ssim(&a, &a, 32, 24, None).unwrap() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn a_uniform_error_gives_its_psnr() {
        // MSE = 0.1² ⇒ PSNR = 20 dB exactly; with half the pixels off by 0.1 and a mask on the
        // other half, the error is 0 again.
        let a = vec![0.5f32; 16 * 16 * 3];
        let b: Vec<f32> = a.iter().map(|v| v + 0.1).collect();
        assert!((psnr(&a, &b, 16, 16, None).unwrap() - 20.0).abs() < 1e-5);
        let mut half = a.clone();
        half[..8 * 16 * 3].iter_mut().for_each(|v| *v += 0.1);
        let bottom: Vec<bool> = (0..256).map(|p| p >= 128).collect();
        assert_eq!(
            psnr(&a, &half, 16, 16, Some(&bottom)).unwrap(),
            f64::INFINITY
        );
        // Half the pixels off: MSE = 0.01 / 2.
        let want = -10.0 * (0.01f64 / 2.0).log10();
        assert!((psnr(&a, &half, 16, 16, None).unwrap() - want).abs() < 1e-4);
    }

    #[test]
    fn ssim_of_flat_images_is_the_luminance_term() {
        // σ = 0 everywhere: SSIM = (2ab + C1) / (a² + b² + C1).
        let (x, y) = (0.3f32, 0.6f32);
        let a = vec![x; 20 * 15 * 3];
        let b = vec![y; 20 * 15 * 3];
        let (x, y) = (f64::from(x), f64::from(y));
        let c1 = 1e-4;
        let want = (2.0 * x * y + c1) / (x * x + y * y + c1);
        assert!((ssim(&a, &b, 20, 15, None).unwrap() - want).abs() < 1e-9);
    }

    #[test]
    fn the_window_is_a_normalised_gaussian_of_sigma_one_and_a_half() {
        let k = ssim_window();
        assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        assert!((k[5] / k[6] - (1.0f64 / (2.0 * 2.25)).exp()).abs() < 1e-12);
        assert_eq!(k[0], k[10]);
    }

    #[test]
    fn mismatched_or_degenerate_inputs_are_errors() {
        let a = ramp(16, 16, 0.0);
        assert!(psnr(&a, &a[..30], 16, 16, None).is_err());
        assert!(psnr(&a, &a, 16, 16, Some(&[true; 3])).is_err());
        assert!(psnr(&a, &a, 16, 16, Some(&[false; 256])).is_err());
        assert!(ssim(&a[..10 * 10 * 3], &a[..10 * 10 * 3], 10, 10, None).is_err());
        let mut nan = a.clone();
        nan[5] = f32::NAN;
        assert!(ssim(&a, &nan, 16, 16, None).is_err());
        assert!(psnr(&[], &[], 0, 5, None).is_err());
    }
}
