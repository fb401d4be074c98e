//! The linear algebra of the feature PCA, written for its one job: the few leading eigenpairs of
//! a sample covariance too wide to form (subspace iteration's pieces: covariance products, Gram–
//! Schmidt, Rayleigh–Ritz) and the small symmetric eigenproblem at its core (cyclic Jacobi).
//! Hand-written rather than a linear-algebra dependency because it needs these four operations on
//! matrices of a few dozen rows, and its tests hold it to a dense float64 decomposition.

pub(super) fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// `Xᵀ (X v) / m`: the sample covariance times `v`, without forming the covariance.
pub(super) fn covariance_times(centred: &[Vec<f64>], v: &[f64]) -> Vec<f64> {
    let m = centred.len() as f64;
    let mut out = vec![0.0; v.len()];
    for x in centred {
        let p = dot(x, v) / m;
        for (o, xi) in out.iter_mut().zip(x) {
            *o += p * xi;
        }
    }
    out
}

/// Orthonormalises `block` in place (modified Gram–Schmidt); a vector dependent on those before
/// it becomes zero.
pub(super) fn orthonormalise(block: &mut [Vec<f64>]) {
    for i in 0..block.len() {
        for j in 0..i {
            let (done, rest) = block.split_at_mut(i);
            let p = dot(&rest[0], &done[j]);
            for (a, b) in rest[0].iter_mut().zip(&done[j]) {
                *a -= p * b;
            }
        }
        let norm = dot(&block[i], &block[i]).sqrt();
        if norm > 1e-300 {
            block[i].iter_mut().for_each(|a| *a /= norm);
        } else {
            block[i].iter_mut().for_each(|a| *a = 0.0);
        }
    }
}

/// The Ritz vectors and values of the covariance on the span of the orthonormal `block`, given
/// `product`, the covariance times each of its vectors; largest value first: the eigenpairs of
/// the small matrix `Bᵀ C B` (by Jacobi rotations) taken back.
pub(super) fn rayleigh_ritz(block: &[Vec<f64>], product: &[Vec<f64>]) -> (Vec<Vec<f64>>, Vec<f64>) {
    let k = block.len();
    let mut small: Vec<Vec<f64>> = (0..k)
        .map(|i| (0..k).map(|j| dot(&block[i], &product[j])).collect())
        .collect();
    // Symmetric up to rounding; made exactly so for the rotations.
    #[allow(clippy::needless_range_loop)]
    for i in 0..k {
        for j in 0..i {
            let s = 0.5 * (small[i][j] + small[j][i]);
            small[i][j] = s;
            small[j][i] = s;
        }
    }
    let (values, vectors) = jacobi_eigen(small);
    let mut order: Vec<usize> = (0..k).collect();
    order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
    let width = block.first().map_or(0, Vec::len);
    let ritz_vectors = order
        .iter()
        .map(|&c| {
            let mut v = vec![0.0; width];
            for (r, b) in block.iter().enumerate() {
                for (o, x) in v.iter_mut().zip(b) {
                    *o += vectors[r][c] * x;
                }
            }
            v
        })
        .collect();
    (ritz_vectors, order.iter().map(|&c| values[c]).collect())
}

/// The eigenvalues and eigenvectors (as the columns of the second result) of the symmetric
/// `matrix`, by cyclic Jacobi rotations.
pub(super) fn jacobi_eigen(mut a: Vec<Vec<f64>>) -> (Vec<f64>, Vec<Vec<f64>>) {
    let n = a.len();
    let mut v: Vec<Vec<f64>> = (0..n)
        .map(|i| (0..n).map(|j| if i == j { 1.0 } else { 0.0 }).collect())
        .collect();
    for _ in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        let diagonal: f64 = (0..n).map(|i| a[i][i] * a[i][i]).sum();
        if off <= 1e-30 * diagonal.max(f64::MIN_POSITIVE) {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for row in a.iter_mut() {
                    let (arp, arq) = (row[p], row[q]);
                    row[p] = c * arp - s * arq;
                    row[q] = s * arp + c * arq;
                }
                let (top, bottom) = a.split_at_mut(q);
                for (apr, aqr) in top[p].iter_mut().zip(bottom[0].iter_mut()) {
                    let (x, y) = (*apr, *aqr);
                    *apr = c * x - s * y;
                    *aqr = s * x + c * y;
                }
                for row in v.iter_mut() {
                    let (vp, vq) = (row[p], row[q]);
                    row[p] = c * vp - s * vq;
                    row[q] = s * vp + c * vq;
                }
            }
        }
    }
    ((0..n).map(|i| a[i][i]).collect(), v)
}
