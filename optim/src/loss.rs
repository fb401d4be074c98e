//! Photometric losses of a render against a target frame, with their gradients with respect to the
//! render (what [`c4g_renderer::RenderGradients::rgb`] takes): L1, D-SSIM and 3DGS's blend of the
//! two, `(1 − λ)·L1 + λ·(1 − SSIM)` (λ = 0.2 in 3DGS).
//!
//! SSIM is exactly the renderer's [`c4g_renderer::fidelity::ssim`] (11×11 Gaussian window,
//! σ = 1.5, K1 = 0.01, K2 = 0.03, the "valid" window positions, averaged over positions and
//! channels), so the loss optimised is the metric reported. Its gradient: with the local moments
//! `μx = G∗X`, `m2 = G∗X²`, `m12 = G∗(X·Y)` (σx² = m2 − μx², σxy = m12 − μx·μy) and
//! `S = A1·A2 / (B1·B2)` (`A1 = 2μxμy + C1`, `A2 = 2σxy + C2`, `B1 = μx² + μy² + C1`,
//! `B2 = σx² + σy² + C2`), `∂L/∂X = Gᵀ∗(g·∂S/∂μx) + 2X·Gᵀ∗(g·∂S/∂m2) + Y·Gᵀ∗(g·∂S/∂m12)`, where
//! `Gᵀ∗` is the valid filter's adjoint (scattering each window back over its pixels). All in f64.

use rayon::prelude::*;

use c4g_renderer::fidelity::{SSIM_K1, SSIM_K2, SSIM_WINDOW, filter_valid, ssim_window};
use c4g_scene::SceneError;

/// A loss's value and its gradient with respect to the render's RGB (3 floats a pixel).
#[derive(Debug, Clone, PartialEq)]
pub struct Loss {
    /// The loss.
    pub value: f64,
    /// `∂loss/∂rgb`, interleaved like the render.
    pub gradient: Vec<f32>,
}

fn check(rendered: &[f32], target: &[f32], width: u32, height: u32) -> Result<(), SceneError> {
    let n = 3 * width as usize * height as usize;
    if rendered.len() != n || target.len() != n {
        return Err(SceneError::InvalidImage(format!(
            "a loss compares two {width}x{height} RGB images ({n} values), got {} and {}",
            rendered.len(),
            target.len()
        )));
    }
    if rendered.iter().chain(target).any(|v| !v.is_finite()) {
        return Err(SceneError::InvalidImage(
            "a loss's images must be finite".into(),
        ));
    }
    Ok(())
}

/// Mean absolute difference over every value; its gradient is `sign(r − t) / n` (0 where they
/// are equal).
pub fn l1(rendered: &[f32], target: &[f32], width: u32, height: u32) -> Result<Loss, SceneError> {
    check(rendered, target, width, height)?;
    let n = rendered.len() as f64;
    let mut value = 0.0;
    let gradient = rendered
        .iter()
        .zip(target)
        .map(|(r, t)| {
            let d = f64::from(*r) - f64::from(*t);
            value += d.abs();
            (d.signum() * f64::from(d != 0.0) / n) as f32
        })
        .collect();
    Ok(Loss {
        value: value / n,
        gradient,
    })
}

/// `1 − SSIM(rendered, target)` and its gradient.
pub fn dssim(
    rendered: &[f32],
    target: &[f32],
    width: u32,
    height: u32,
) -> Result<Loss, SceneError> {
    check(rendered, target, width, height)?;
    let (w, h) = (width as usize, height as usize);
    if w < SSIM_WINDOW || h < SSIM_WINDOW {
        return Err(SceneError::InvalidImage(format!(
            "SSIM needs at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {w}x{h}"
        )));
    }
    let (vw, vh) = (w + 1 - SSIM_WINDOW, h + 1 - SSIM_WINDOW);
    let kernel = ssim_window();
    let positions = (3 * vw * vh) as f64;
    let per_channel: Vec<(f64, Vec<f64>)> = (0..3)
        .into_par_iter()
        .map(|c| {
            let x: Vec<f64> = (0..w * h).map(|p| f64::from(rendered[3 * p + c])).collect();
            let y: Vec<f64> = (0..w * h).map(|p| f64::from(target[3 * p + c])).collect();
            ssim_channel(&kernel, w, h, &x, &y, -1.0 / positions)
        })
        .collect();
    let mut value = 1.0;
    let mut gradient = vec![0.0f32; 3 * w * h];
    for (c, (sum, grad)) in per_channel.into_iter().enumerate() {
        value -= sum / positions;
        for (p, g) in grad.into_iter().enumerate() {
            gradient[3 * p + c] = g as f32;
        }
    }
    Ok(Loss { value, gradient })
}

/// 3DGS's photometric loss, `(1 − λ)·L1 + λ·D-SSIM`.
pub fn l1_dssim(
    rendered: &[f32],
    target: &[f32],
    width: u32,
    height: u32,
    lambda: f64,
) -> Result<Loss, SceneError> {
    let a = l1(rendered, target, width, height)?;
    if lambda == 0.0 {
        return Ok(a);
    }
    let b = dssim(rendered, target, width, height)?;
    Ok(Loss {
        value: (1.0 - lambda) * a.value + lambda * b.value,
        gradient: a
            .gradient
            .iter()
            .zip(&b.gradient)
            .map(|(ga, gb)| ((1.0 - lambda) * f64::from(*ga) + lambda * f64::from(*gb)) as f32)
            .collect(),
    })
}

/// The valid filter's adjoint: each window value scattered back over its window's pixels.
fn scatter(k: &[f64; SSIM_WINDOW], w: usize, h: usize, g: &[f64]) -> Vec<f64> {
    let (vw, vh) = (w + 1 - SSIM_WINDOW, h + 1 - SSIM_WINDOW);
    let mut rows = vec![0.0; vw * h];
    for y in 0..vh {
        for x in 0..vw {
            for i in 0..SSIM_WINDOW {
                rows[(y + i) * vw + x] += k[i] * g[y * vw + x];
            }
        }
    }
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..vw {
            for i in 0..SSIM_WINDOW {
                out[y * w + x + i] += k[i] * rows[y * vw + x];
            }
        }
    }
    out
}

/// One channel: the sum of its SSIM map, and `scale ·` the gradient of that sum.
fn ssim_channel(
    k: &[f64; SSIM_WINDOW],
    w: usize,
    h: usize,
    x: &[f64],
    y: &[f64],
    scale: f64,
) -> (f64, Vec<f64>) {
    let (c1, c2) = (SSIM_K1 * SSIM_K1, SSIM_K2 * SSIM_K2);
    let mu_x = filter_valid(k, w, h, &|i| x[i]);
    let mu_y = filter_valid(k, w, h, &|i| y[i]);
    let xx = filter_valid(k, w, h, &|i| x[i] * x[i]);
    let yy = filter_valid(k, w, h, &|i| y[i] * y[i]);
    let xy = filter_valid(k, w, h, &|i| x[i] * y[i]);
    let n = mu_x.len();
    let (mut d_mu, mut d_xx, mut d_xy) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    let mut sum = 0.0;
    for p in 0..n {
        let (mx, my) = (mu_x[p], mu_y[p]);
        let (sxx, syy, sxy) = (xx[p] - mx * mx, yy[p] - my * my, xy[p] - mx * my);
        let (a1, a2) = (2.0 * mx * my + c1, 2.0 * sxy + c2);
        let (b1, b2) = (mx * mx + my * my + c1, sxx + syy + c2);
        let s = (a1 * a2) / (b1 * b2);
        sum += s;
        // Through μx: A1 by 2μy, A2 by −2μy (σxy), B1 by 2μx, B2 by −2μx (σx²).
        d_mu[p] = scale
            * ((2.0 * my * a2 - 2.0 * my * a1) / (b1 * b2) - s * (2.0 * mx / b1 - 2.0 * mx / b2));
        d_xx[p] = scale * (-s / b2);
        d_xy[p] = scale * (2.0 * a1 / (b1 * b2));
    }
    let (g_mu, g_xx, g_xy) = (
        scatter(k, w, h, &d_mu),
        scatter(k, w, h, &d_xx),
        scatter(k, w, h, &d_xy),
    );
    let grad = (0..w * h)
        .map(|q| g_mu[q] + 2.0 * x[q] * g_xx[q] + y[q] * g_xy[q])
        .collect();
    (sum, grad)
}

#[cfg(test)]
mod tests {
    use super::*;
    use c4g_renderer::fidelity;

    fn image(w: usize, h: usize, seed: u64) -> Vec<f32> {
        let mut s = seed;
        (0..3 * w * h)
            .map(|i| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                // Smooth structure plus noise, so SSIM is neither 0 nor 1.
                let smooth = ((i / 3 % w) as f32 * 0.3).sin() * 0.3 + 0.5;
                smooth + 0.2 * ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5)
            })
            .collect()
    }

    /// Central differences of `f` at every value of `a`, the step's actual size as rounded to f32
    /// in the denominator (so f32 inputs cost no accuracy): `(L(a + h) − L(a − h)) / (a⁺ − a⁻)`.
    fn finite_differences(a: &[f32], f: impl Fn(&[f32]) -> f64) -> Vec<f64> {
        let h = 1e-3f32;
        (0..a.len())
            .map(|i| {
                let (mut p, mut m) = (a.to_vec(), a.to_vec());
                p[i] += h;
                m[i] -= h;
                (f(&p) - f(&m)) / (f64::from(p[i]) - f64::from(m[i]))
            })
            .collect()
    }

    #[test]
    fn dssim_is_one_minus_the_renderers_ssim() {
        let (a, b) = (image(23, 17, 1), image(23, 17, 2));
        let loss = dssim(&a, &b, 23, 17).unwrap();
        let ssim = fidelity::ssim(&a, &b, 23, 17, None).unwrap();
        assert!((loss.value - (1.0 - ssim)).abs() < 1e-12);
        assert!(dssim(&a, &a, 23, 17).unwrap().value.abs() < 1e-12);
    }

    #[test]
    fn the_dssim_gradient_is_its_finite_differences() {
        // Tolerance 1e-6 of the largest entry: the differences are of an f64 loss with steps of
        // 1e-3, whose truncation error (h²·S''') is ~1e-7 of the gradient here.
        let (w, h) = (14, 12);
        let (a, b) = (image(w, h, 3), image(w, h, 4));
        let loss = dssim(&a, &b, w as u32, h as u32).unwrap();
        let fd = finite_differences(&a, |x| dssim(x, &b, w as u32, h as u32).unwrap().value);
        let scale = fd.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (i, (g, d)) in loss.gradient.iter().zip(&fd).enumerate() {
            assert!(
                (f64::from(*g) - d).abs() <= 1e-6 * scale + 1e-4 * d.abs(),
                "{i}: {g} vs {d}"
            );
        }
    }

    #[test]
    fn the_l1_gradient_is_its_finite_differences_away_from_ties() {
        let (a, b) = (image(12, 11, 5), image(12, 11, 6));
        let loss = l1(&a, &b, 12, 11).unwrap();
        let fd = finite_differences(&a, |x| l1(x, &b, 12, 11).unwrap().value);
        for ((g, d), (x, y)) in loss.gradient.iter().zip(&fd).zip(a.iter().zip(&b)) {
            // Within a step of a tie the difference straddles the kink.
            if (x - y).abs() > 2e-3 {
                assert!((f64::from(*g) - d).abs() < 1e-9);
            }
        }
        let blend = l1_dssim(&a, &b, 12, 11, 0.2).unwrap();
        let ds = dssim(&a, &b, 12, 11).unwrap();
        assert!((blend.value - (0.8 * loss.value + 0.2 * ds.value)).abs() < 1e-12);
    }

    #[test]
    fn mismatched_or_non_finite_images_are_refused() {
        let a = image(12, 12, 1);
        assert!(l1(&a, &a[..10], 12, 12).is_err());
        assert!(dssim(&a, &a, 12, 13).is_err());
        let mut bad = a.clone();
        bad[5] = f32::NAN;
        assert!(dssim(&bad, &a, 12, 12).is_err());
        assert!(dssim(&image(8, 8, 1), &image(8, 8, 2), 8, 8).is_err());
    }
}
