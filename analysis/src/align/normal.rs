//! The robust loss and its Gauss–Newton normal equations: per pixel and channel the residual
//! `r = render − target`, Huber's `ρ` of it weighted by the pixel's rendered alpha, accumulated
//! into `H = Σ w ρ''(r) JᵀJ` (iteratively reweighted: `ρ''` is Huber's weight `ψ(r)/r`) and
//! `g = Σ w ψ(r) J`; the damped step that solves them; and how well they pin the camera down.
//!
//! Why Huber: a frame is never the model's render (moving things the set does not explain,
//! its reconstruction error, exposure); a quadratic loss lets those pixels outvote the rest.
//! Huber is quadratic near zero, where Gauss–Newton converges fast, and linear beyond `δ`. Why
//! weight by the rendered alpha: where the set covers nothing the render is the background, and
//! how far that is from the frame says nothing about the camera. The weights are frozen at the
//! current camera while a step is judged, so a step cannot lower the cost by moving the set out
//! of view.

use rayon::prelude::*;

use super::adjustment::CAMERA_PARAMETERS;
use super::jacobian::CameraJacobian;

const P: usize = CAMERA_PARAMETERS;

/// Pixels per parallel chunk of the accumulation.
const CHUNK: usize = 1024;

/// Huber's loss `ρ` (`r²/2` within `δ`, `δ(|r| − δ/2)` beyond), its derivative `ψ` and the
/// reweighting `ψ(r)/r`.
pub(super) fn huber(r: f64, delta: f64) -> (f64, f64, f64) {
    let a = r.abs();
    if a <= delta {
        (0.5 * r * r, r, 1.0)
    } else {
        (delta * (a - 0.5 * delta), delta * r.signum(), delta / a)
    }
}

/// The normal equations of the first `n` parameters at one render (the rest stay zero).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Normal {
    pub(super) h: [[f64; P]; P],
    pub(super) g: [f64; P],
    /// `Σ w ρ(r)`.
    pub(super) cost: f64,
    /// `Σ w` over pixels (each pixel's three channels share its weight once).
    pub(super) weight: f64,
}

impl Normal {
    const ZERO: Self = Self {
        h: [[0.0; P]; P],
        g: [0.0; P],
        cost: 0.0,
        weight: 0.0,
    };

    fn add(mut self, other: Self) -> Self {
        for (a, b) in self.h.iter_mut().flatten().zip(other.h.iter().flatten()) {
            *a += b;
        }
        for (a, b) in self.g.iter_mut().zip(other.g) {
            *a += b;
        }
        self.cost += other.cost;
        self.weight += other.weight;
        self
    }

    /// `Σ w ρ / (3 Σ w)`: the mean robust residual per weighted channel (0 where nothing is
    /// weighted).
    pub(super) fn mean_cost(&self) -> f64 {
        if self.weight > 0.0 {
            self.cost / (3.0 * self.weight)
        } else {
            0.0
        }
    }
}

/// Accumulates the normal equations of the first `n` parameters of `render` against `target`
/// (RGB, as `render.rgb`), each pixel weighted by `weights` (one a pixel).
pub(super) fn normal_equations(
    render: &CameraJacobian,
    target: &[f64],
    weights: &[f64],
    delta: f64,
    n: usize,
) -> Normal {
    let mut total = accumulate(render, target, weights, |acc, w, r, row| {
        let (rho, psi, reweight) = huber(r, delta);
        acc.cost += w * rho;
        let (wg, wh) = (w * psi, w * reweight);
        for i in 0..n {
            acc.g[i] += wg * row[i];
            for j in i..n {
                acc.h[i][j] += wh * row[i] * row[j];
            }
        }
    });
    for i in 0..n {
        for j in 0..i {
            total.h[i][j] = total.h[j][i];
        }
    }
    total
}

/// `Σ w ρ(render − target)` and `Σ w`: the cost [`normal_equations`] would report.
pub(super) fn cost(render: &CameraJacobian, target: &[f64], weights: &[f64], delta: f64) -> Normal {
    accumulate(render, target, weights, |acc, w, r, _| {
        acc.cost += w * huber(r, delta).0;
    })
}

/// Sums `add(acc, weight, residual, ∂rgb row)` over every colour value of every weighted pixel,
/// chunks of pixels in parallel.
fn accumulate(
    render: &CameraJacobian,
    target: &[f64],
    weights: &[f64],
    add: impl Fn(&mut Normal, f64, f64, &[f64; P]) + Sync,
) -> Normal {
    weights
        .par_chunks(CHUNK)
        .zip(render.rgb.par_chunks(3 * CHUNK))
        .zip(render.d_rgb.par_chunks(3 * CHUNK))
        .zip(target.par_chunks(3 * CHUNK))
        .map(|(((weights, rgb), d_rgb), target)| {
            let mut acc = Normal::ZERO;
            for (p, &w) in weights.iter().enumerate() {
                if w <= 0.0 {
                    continue;
                }
                acc.weight += w;
                for c in 3 * p..3 * p + 3 {
                    add(&mut acc, w, rgb[c] - target[c], &d_rgb[c]);
                }
            }
            acc
        })
        .reduce(|| Normal::ZERO, Normal::add)
}

/// Levenberg–Marquardt's step on the first `n` parameters: `(H + λ·diag(H)) δ = −g`, the
/// diagonal floored at `1e-12` of its largest entry so that a parameter the render does not see
/// takes no step instead of an infinite one; `None` when `H` is zero or the system is not
/// positive definite (non-finite numbers).
pub(super) fn damped_step(normal: &Normal, lambda: f64, n: usize) -> Option<[f64; P]> {
    let largest = (0..n).map(|i| normal.h[i][i]).fold(0.0, f64::max);
    if !(largest > 0.0 && largest.is_finite()) {
        return None;
    }
    let mut a = normal.h;
    for (i, row) in a.iter_mut().enumerate().take(n) {
        row[i] += lambda * normal.h[i][i].max(1e-12 * largest);
    }
    let rhs: Vec<f64> = normal.g[..n].iter().map(|v| -v).collect();
    let x = cholesky_solve(&a, &rhs, n)?;
    let mut step = [0.0; P];
    step[..n].copy_from_slice(&x);
    Some(step)
}

/// Solves `A x = b` for symmetric positive definite `A` (its first `n` rows and columns).
fn cholesky_solve(a: &[[f64; P]; P], b: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = [[0.0; P]; P];
    for i in 0..n {
        for j in 0..=i {
            let sum: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
            if i == j {
                let d = a[i][i] - sum;
                if !(d > 0.0 && d.is_finite()) {
                    return None;
                }
                l[i][i] = d.sqrt();
            } else {
                l[i][j] = (a[i][j] - sum) / l[j][j];
            }
        }
    }
    let mut y = vec![0.0; n];
    for i in 0..n {
        let sum: f64 = (0..i).map(|k| l[i][k] * y[k]).sum();
        y[i] = (b[i] - sum) / l[i][i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        let sum: f64 = (i + 1..n).map(|k| l[k][i] * x[k]).sum();
        x[i] = (y[i] - sum) / l[i][i];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// How well the first `n` parameters are determined: the smallest eigenvalue of `H` over its
/// largest after scaling every parameter to a unit diagonal (`D^-½ H D^-½`, so that radians,
/// scene units and the log focal compare). 1 when every parameter moves the image in its own
/// way, 0 when some combination of them does not move it at all (a single round splat, a
/// render that covers nothing, a focal length and a dolly the scene's depth cannot tell apart).
pub(super) fn conditioning(h: &[[f64; P]; P], n: usize) -> f64 {
    let diag: Vec<f64> = (0..n).map(|i| h[i][i]).collect();
    let largest = diag.iter().copied().fold(0.0, f64::max);
    if !(largest > 0.0 && largest.is_finite()) || diag.iter().any(|&d| d <= 1e-300) {
        return 0.0;
    }
    let mut m = vec![vec![0.0; n]; n];
    for i in 0..n {
        for j in 0..n {
            m[i][j] = h[i][j] / (diag[i] * diag[j]).sqrt();
        }
    }
    let eigen = symmetric_eigenvalues(m);
    let (lo, hi) = eigen.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &e| {
        (lo.min(e), hi.max(e))
    });
    if hi > 0.0 {
        (lo / hi).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// Eigenvalues of a small symmetric matrix by cyclic Jacobi rotations (to 1e-15 of its norm).
fn symmetric_eigenvalues(mut m: Vec<Vec<f64>>) -> Vec<f64> {
    let n = m.len();
    let norm: f64 = m.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
    for _sweep in 0..64 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| m[i][j] * m[i][j])
            .sum::<f64>()
            .sqrt();
        if off <= 1e-15 * norm {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                if m[p][q] == 0.0 {
                    continue;
                }
                let theta = (m[q][q] - m[p][p]) / (2.0 * m[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for row in m.iter_mut() {
                    let (a, b) = (row[p], row[q]);
                    row[p] = c * a - s * b;
                    row[q] = s * a + c * b;
                }
                let (above, below) = m.split_at_mut(q);
                for (a, b) in above[p].iter_mut().zip(below[0].iter_mut()) {
                    (*a, *b) = (c * *a - s * *b, s * *a + c * *b);
                }
            }
        }
    }
    (0..n).map(|i| m[i][i]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn huber_is_quadratic_within_delta_and_linear_beyond() {
        let (rho, psi, w) = huber(0.05, 0.1);
        assert!((rho - 0.00125).abs() < 1e-15);
        assert_eq!((psi, w), (0.05, 1.0));
        let (rho, psi, w) = huber(-0.3, 0.1);
        assert!((rho - 0.1 * (0.3 - 0.05)).abs() < 1e-15);
        assert_eq!(psi, -0.1);
        assert!((w - 1.0 / 3.0).abs() < 1e-15);
    }

    #[test]
    fn cholesky_solves_a_positive_definite_system_and_refuses_an_indefinite_one() {
        let mut a = [[0.0; P]; P];
        a[0] = [4.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        a[1] = [1.0, 3.0, 0.5, 0.0, 0.0, 0.0, 0.0];
        a[2] = [0.0, 0.5, 2.0, 0.0, 0.0, 0.0, 0.0];
        let x = cholesky_solve(&a, &[1.0, 2.0, 3.0], 3).unwrap_or_default();
        let back: Vec<f64> = (0..3)
            .map(|i| (0..3).map(|j| a[i][j] * x[j]).sum())
            .collect();
        for (b, e) in back.iter().zip([1.0, 2.0, 3.0]) {
            assert!((b - e).abs() < 1e-12, "{back:?}");
        }
        a[2][2] = -1.0;
        assert!(cholesky_solve(&a, &[1.0, 2.0, 3.0], 3).is_none());
    }

    #[test]
    fn eigenvalues_of_a_known_matrix() {
        // [[2, 1], [1, 2]] has eigenvalues 1 and 3; diag(5) adds one of 5.
        let mut e = symmetric_eigenvalues(vec![
            vec![2.0, 1.0, 0.0],
            vec![1.0, 2.0, 0.0],
            vec![0.0, 0.0, 5.0],
        ]);
        e.sort_by(f64::total_cmp);
        for (got, want) in e.iter().zip([1.0, 3.0, 5.0]) {
            assert!((got - want).abs() < 1e-12, "{e:?}");
        }
    }

    #[test]
    fn conditioning_is_one_for_independent_parameters_and_zero_for_a_null_direction() {
        let mut h = [[0.0; P]; P];
        for (i, row) in h.iter_mut().enumerate() {
            row[i] = 10f64.powi(i as i32);
        }
        assert!(
            (conditioning(&h, P) - 1.0).abs() < 1e-12,
            "units do not matter"
        );
        // Parameters 0 and 1 move the image identically: H has a null direction.
        h[0] = [1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        h[1] = [1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert!(conditioning(&h, P) < 1e-12);
        assert_eq!(conditioning(&[[0.0; P]; P], 6), 0.0);
    }
}
