//! Feature fields seen in images: per-Gaussian feature vectors (the feature-lifting decoder's),
//! compared, coloured and matched.
//!
//! A set's feature vectors are composited like colour ([`RenderOptions::features`]): a pixel holds
//! `s = Σ wᵢ fᵢ` with the blending weights `wᵢ = Tᵢ·αᵢ`, and no background, so `s / alpha` is the
//! weighted mean feature of the Gaussians it shows. Everything here compares *directions* of
//! features (cosine similarity), which `s` and `s / alpha` share, so a half-covered pixel is as
//! good a sample of its surface's feature as a covered one.
//!
//! - [`cosine`]: the similarity of two feature vectors, in float64.
//! - [`select_similar`]: the Gaussians of a set whose feature is within a cosine threshold of one.
//! - [`pixel_feature`]: the feature a pixel shows, from the surface its Gaussians make
//!   ([`tracking::surface`], the point tracker's rule), for a click.
//! - [`FeaturePca`]: a fixed colouring of features (3 principal components of a sample, each
//!   mapped to a colour channel through a fixed range), so a colour means the same feature in
//!   every image coloured with one basis.
//! - [`best_match`]: where a feature image shows a feature best, to a sub-pixel position.

use c4g_renderer::raster::{FeatureImage, Image, PixelWeight, RenderOptions};
use c4g_scene::{GaussianSet, SceneError};

use crate::tracking;
use eigen::{covariance_times, dot, orthonormalise, rayleigh_ritz};

/// The PCA's linear algebra: subspace iteration's pieces and a small symmetric eigensolver.
mod eigen;

/// Principal components a [`FeaturePca`] keeps: one per colour channel.
pub const PCA_COMPONENTS: usize = 3;

/// The fraction of samples below the low end (and above the high end) of each component's colour
/// range: a few outlying Gaussians must not wash out every other colour.
pub const PCA_RANGE_QUANTILE: f64 = 0.01;

/// Samples a [`FeaturePca`] is fitted on at most (taken at an even stride beyond it): the colouring
/// needs the main directions of the features, not every Gaussian at every time.
pub const PCA_MAX_SAMPLES: usize = 8192;

/// Block power iterations of the fit at most; it stops earlier once the leading eigenvalues agree
/// with the previous iteration's to [`PCA_TOLERANCE`] (relative). Each costs one pass over the
/// samples per block vector: at the official size (8192 samples of 2048) about 0.3 GFLOP.
const PCA_MAX_ITERATIONS: usize = 300;

/// See [`PCA_MAX_ITERATIONS`].
const PCA_TOLERANCE: f64 = 1e-12;

/// Vectors iterated beside the three kept (oversampling): the block converges at the rate of the
/// gap to the eigenvalue after the block, not after the third.
const PCA_OVERSAMPLING: usize = 5;

/// The cosine similarity of `a` and `b` (equal lengths), accumulated in float64; `None` when
/// either has no direction (a zero or non-finite norm) or the lengths differ.
pub fn cosine(a: &[f32], b: &[f32]) -> Option<f32> {
    if a.len() != b.len() {
        return None;
    }
    let (mut ab, mut aa, mut bb) = (0.0f64, 0.0f64, 0.0f64);
    for (&x, &y) in a.iter().zip(b) {
        let (x, y) = (f64::from(x), f64::from(y));
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    let norm = (aa * bb).sqrt();
    (norm > 0.0 && norm.is_finite()).then(|| (ab / norm).clamp(-1.0, 1.0) as f32)
}

/// The indices of the Gaussians of `set` whose feature vector has a cosine similarity of at least
/// `threshold` with `feature`, in index order. A Gaussian whose feature has no direction (zero)
/// is never selected. Fails when the set has no features or they are not `feature`'s width.
pub fn select_similar(
    set: &GaussianSet,
    feature: &[f32],
    threshold: f32,
) -> Result<Vec<u32>, SceneError> {
    let block = set.features().ok_or_else(|| {
        SceneError::InvalidRenderOptions("the set has no feature vectors to compare".into())
    })?;
    if block.width() != feature.len() {
        return Err(SceneError::LengthMismatch {
            field: "the feature compared with the set's",
            expected: block.width(),
            actual: feature.len(),
        });
    }
    Ok((0..set.len())
        .filter(|&i| {
            block
                .row(i)
                .and_then(|row| cosine(row, feature))
                .is_some_and(|s| s >= threshold)
        })
        .map(|i| i as u32)
        .collect())
}

/// The feature a pixel shows: the weighted mean feature of the Gaussians of its surface (those
/// within [`tracking::SURFACE_BAND`] of its median depth, as the point tracker anchors a point),
/// with their blending weights. `None` when the pixel shows too little (alpha under
/// [`tracking::MIN_COVERAGE`]) or `set` has no features.
pub fn pixel_feature(set: &GaussianSet, weights: &[PixelWeight]) -> Option<Vec<f32>> {
    let block = set.features()?;
    let alpha: f32 = weights.iter().map(|p| p.weight).sum();
    if alpha < tracking::MIN_COVERAGE {
        return None;
    }
    let surface = tracking::surface(weights);
    let mut sum = vec![0.0f64; block.width()];
    let mut total = 0.0f64;
    for p in &surface {
        let row = block.row(p.index as usize)?;
        let w = f64::from(p.weight);
        for (s, &v) in sum.iter_mut().zip(row) {
            *s += w * f64::from(v);
        }
        total += w;
    }
    (total > 0.0).then(|| sum.iter().map(|s| (s / total) as f32).collect())
}

/// A colouring of feature vectors: the mean of a sample, its first three principal components
/// (the eigenvectors of its covariance with the largest eigenvalues), and per component the range
/// of the sample's projections that spans the colour channel.
///
/// A feature `f` is coloured `cₖ = clamp((bₖ·(f − μ) − lowₖ) / (highₖ − lowₖ), 0, 1)` for
/// channel k (red, green, blue: components 1, 2, 3). Each component's sign is fixed (its largest
/// coefficient in absolute value is positive), so fitting the same sample twice gives the same
/// colours. The ranges are the sample's [`PCA_RANGE_QUANTILE`] and 1 − that quantile of each
/// projection; a component the sample does not vary along gives 0.5.
#[derive(Debug, Clone, PartialEq)]
pub struct FeaturePca {
    mean: Vec<f64>,
    components: [Vec<f64>; PCA_COMPONENTS],
    variances: [f64; PCA_COMPONENTS],
    low: [f64; PCA_COMPONENTS],
    high: [f64; PCA_COMPONENTS],
}

impl FeaturePca {
    /// Fits the colouring on `samples`, rows of `width` floats (non-finite rows are skipped; at
    /// most [`PCA_MAX_SAMPLES`], at an even stride). Components beyond the sample's rank (fewer
    /// distinct directions than three) are zero and colour 0.5.
    ///
    /// The eigenvectors come from block power iteration on the covariance, in float64, with a
    /// fixed start (so the fit is deterministic), then a Rayleigh–Ritz step to order them.
    pub fn fit(samples: &[f32], width: usize) -> Result<Self, SceneError> {
        if width == 0 {
            return Err(SceneError::ZeroFeatureWidth);
        }
        if !samples.len().is_multiple_of(width) {
            return Err(SceneError::LengthMismatch {
                field: "feature samples",
                expected: samples.len().div_ceil(width) * width,
                actual: samples.len(),
            });
        }
        let finite: Vec<&[f32]> = samples
            .chunks_exact(width)
            .filter(|row| row.iter().all(|v| v.is_finite()))
            .collect();
        if finite.is_empty() {
            return Err(SceneError::InvalidRenderOptions(
                "a feature colouring needs at least one finite feature vector".into(),
            ));
        }
        let stride = finite.len().div_ceil(PCA_MAX_SAMPLES);
        let rows: Vec<Vec<f64>> = finite
            .iter()
            .step_by(stride)
            .map(|row| row.iter().map(|&v| f64::from(v)).collect())
            .collect();
        let m = rows.len() as f64;
        let mut mean = vec![0.0; width];
        for row in &rows {
            for (s, v) in mean.iter_mut().zip(row) {
                *s += v / m;
            }
        }
        let centred: Vec<Vec<f64>> = rows
            .iter()
            .map(|row| row.iter().zip(&mean).map(|(v, mu)| v - mu).collect())
            .collect();
        let (components, variances) = leading_components(&centred, width);
        let mut low = [0.0; PCA_COMPONENTS];
        let mut high = [0.0; PCA_COMPONENTS];
        for k in 0..PCA_COMPONENTS {
            let mut projections: Vec<f64> =
                centred.iter().map(|x| dot(x, &components[k])).collect();
            projections.sort_by(f64::total_cmp);
            let at = |q: f64| {
                let i = (q * (projections.len() - 1) as f64).round() as usize;
                projections[i.min(projections.len() - 1)]
            };
            low[k] = at(PCA_RANGE_QUANTILE);
            high[k] = at(1.0 - PCA_RANGE_QUANTILE);
        }
        Ok(Self {
            mean,
            components,
            variances,
            low,
            high,
        })
    }

    /// The width of the features this colours.
    pub fn width(&self) -> usize {
        self.mean.len()
    }

    /// The sample mean.
    pub fn mean(&self) -> &[f64] {
        &self.mean
    }

    /// The three unit components, largest variance first (a zero vector past the sample's rank).
    pub fn components(&self) -> &[Vec<f64>; PCA_COMPONENTS] {
        &self.components
    }

    /// The sample's variance along each component.
    pub fn variances(&self) -> [f64; PCA_COMPONENTS] {
        self.variances
    }

    /// Each component's colour range: the projections that map to 0 and to 1.
    pub fn ranges(&self) -> [(f64, f64); PCA_COMPONENTS] {
        std::array::from_fn(|k| (self.low[k], self.high[k]))
    }

    /// `feature`'s coordinates along the components: `bₖ·(f − μ)` (float64).
    pub fn project(&self, feature: &[f32]) -> [f64; PCA_COMPONENTS] {
        std::array::from_fn(|k| {
            feature
                .iter()
                .zip(&self.mean)
                .zip(&self.components[k])
                .map(|((&f, mu), b)| (f64::from(f) - mu) * b)
                .sum()
        })
    }

    /// `feature`'s colour (see the type's documentation).
    pub fn colour(&self, feature: &[f32]) -> [f32; PCA_COMPONENTS] {
        let p = self.project(feature);
        std::array::from_fn(|k| {
            let span = self.high[k] - self.low[k];
            if span <= f64::EPSILON * (1.0 + self.high[k].abs()) {
                0.5
            } else {
                ((p[k] - self.low[k]) / span).clamp(0.0, 1.0) as f32
            }
        })
    }

    /// RGB, 3 floats a pixel, of a rendered feature image coloured with this basis: each pixel
    /// the colour of the mean feature it shows (`s / alpha`), composited over `background` by its
    /// alpha as a colour render is. Fails when the image has no features of this width.
    pub fn colour_image(
        &self,
        image: &Image,
        background: [f32; 3],
    ) -> Result<Vec<f32>, SceneError> {
        let features = image_features(image, self.width())?;
        let mut rgb = Vec::with_capacity(image.alpha.len() * 3);
        let mut mean = vec![0.0f32; self.width()];
        for (s, &a) in features
            .values
            .chunks_exact(features.channels)
            .zip(&image.alpha)
        {
            let colour = if a > 0.0 {
                for (m, &v) in mean.iter_mut().zip(s) {
                    *m = v / a;
                }
                self.colour(&mean)
            } else {
                [0.0; 3]
            };
            for k in 0..3 {
                rgb.push(a * colour[k] + (1.0 - a) * background[k]);
            }
        }
        Ok(rgb)
    }
}

/// The feature image of `image`, checked to hold `width` channels a pixel for every pixel.
fn image_features(image: &Image, width: usize) -> Result<&FeatureImage, SceneError> {
    let features = image.features.as_ref().ok_or_else(|| {
        SceneError::InvalidRenderOptions("the image has no feature channels".into())
    })?;
    if features.channels != width || features.values.len() != image.alpha.len() * width {
        return Err(SceneError::LengthMismatch {
            field: "feature image channels",
            expected: image.alpha.len() * width,
            actual: features.values.len(),
        });
    }
    Ok(features)
}

/// The three leading unit eigenvectors of the covariance of `centred` (rows of `width`), with
/// their eigenvalues, signs fixed (see [`FeaturePca`]).
fn leading_components(
    centred: &[Vec<f64>],
    width: usize,
) -> ([Vec<f64>; PCA_COMPONENTS], [f64; PCA_COMPONENTS]) {
    let k = (PCA_COMPONENTS + PCA_OVERSAMPLING).min(width);
    // A fixed start that no structured feature is orthogonal to in practice: a few low-discrepancy
    // sequences (a Weyl sequence per vector), centred.
    let mut block: Vec<Vec<f64>> = (0..k)
        .map(|j| {
            let step = 0.618_033_988_749_894_9 * (j as f64 + 1.0).sqrt();
            (0..width)
                .map(|i| ((i as f64 + 1.0) * step).fract() - 0.5)
                .collect()
        })
        .collect();
    orthonormalise(&mut block);
    // Each iteration multiplies the block by the covariance once: the product gives the block's
    // Ritz values (to test convergence) and, orthonormalised, the next block.
    let mut previous = [f64::NAN; PCA_COMPONENTS];
    let mut ritz = (block.clone(), vec![0.0; k]);
    for _ in 0..PCA_MAX_ITERATIONS {
        let product: Vec<Vec<f64>> = block.iter().map(|v| covariance_times(centred, v)).collect();
        ritz = rayleigh_ritz(&block, &product);
        let values: [f64; PCA_COMPONENTS] =
            std::array::from_fn(|i| ritz.1.get(i).copied().unwrap_or(0.0));
        let scale = values[0].abs().max(f64::MIN_POSITIVE);
        let settled = values
            .iter()
            .zip(&previous)
            .all(|(a, b)| (a - b).abs() <= PCA_TOLERANCE * scale);
        previous = values;
        if settled {
            break;
        }
        block = product;
        orthonormalise(&mut block);
    }
    let (vectors, values) = ritz;
    let components = std::array::from_fn(|i| {
        let mut v = vectors.get(i).cloned().unwrap_or_else(|| vec![0.0; width]);
        if values.get(i).is_none_or(|&l| l <= 0.0) {
            v.iter_mut().for_each(|a| *a = 0.0);
        }
        let largest = v
            .iter()
            .copied()
            .max_by(|a, b| a.abs().total_cmp(&b.abs()))
            .unwrap_or(0.0);
        if largest < 0.0 {
            v.iter_mut().for_each(|a| *a = -*a);
        }
        v
    });
    let variances = std::array::from_fn(|i| values.get(i).copied().unwrap_or(0.0).max(0.0));
    (components, variances)
}

/// Where a feature image shows a feature best.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureMatch {
    /// Pixel coordinates of the match (pixel `(i, j)` covers `[i, i+1) × [j, j+1)`).
    pub x: f32,
    /// Likewise, rows.
    pub y: f32,
    /// The pixel of the best similarity.
    pub pixel: (u32, u32),
    /// Its cosine similarity with the feature.
    pub similarity: f32,
}

/// The best match of `feature` in a rendered feature image: the pixel of largest cosine
/// similarity among those that show something (alpha at least [`tracking::MIN_COVERAGE`]), then
/// refined to a sub-pixel position per axis by the vertex of the parabola through its own and its
/// two neighbours' similarities (when both neighbours show something and the three make a
/// maximum), at most half a pixel from its centre. `None` when no pixel shows anything.
///
/// Cosine similarity sees directions only, so a feature that is the same over a region (one large
/// Gaussian's, say) matches that whole region equally: the first of its pixels in row-major order
/// wins ([`best_match_near`] breaks the tie by distance instead). Lifted features vary over a surface, which is what gives the match its place.
pub fn best_match(image: &Image, feature: &[f32]) -> Result<Option<FeatureMatch>, SceneError> {
    best_match_near(image, feature, None)
}

/// [`best_match`], with ties (a region of one feature) going to the pixel whose centre is nearest
/// `near` (pixel coordinates) when it is given.
pub fn best_match_near(
    image: &Image,
    feature: &[f32],
    near: Option<(f32, f32)>,
) -> Result<Option<FeatureMatch>, SceneError> {
    let features = image_features(image, feature.len())?;
    let (w, h) = (image.width as usize, image.height as usize);
    let similarity: Vec<Option<f32>> = features
        .values
        .chunks_exact(features.channels)
        .zip(&image.alpha)
        .map(|(s, &a)| {
            (a >= tracking::MIN_COVERAGE)
                .then(|| cosine(s, feature))
                .flatten()
        })
        .collect();
    let distance = |p: usize| {
        near.map_or(0.0, |(x, y)| {
            let (dx, dy) = ((p % w) as f32 + 0.5 - x, (p / w) as f32 + 0.5 - y);
            dx * dx + dy * dy
        })
    };
    let Some((best, score)) = similarity
        .iter()
        .enumerate()
        .filter_map(|(i, s)| s.map(|s| (i, s)))
        .max_by(|a, b| {
            a.1.total_cmp(&b.1)
                .then(distance(b.0).total_cmp(&distance(a.0)))
                .then(b.0.cmp(&a.0))
        })
    else {
        return Ok(None);
    };
    let (i, j) = (best % w, best / w);
    let at = |x: isize, y: isize| -> Option<f32> {
        if x < 0 || y < 0 || x as usize >= w || y as usize >= h {
            return None;
        }
        similarity[y as usize * w + x as usize]
    };
    let (ii, jj) = (i as isize, j as isize);
    let dx = vertex(at(ii - 1, jj), score, at(ii + 1, jj));
    let dy = vertex(at(ii, jj - 1), score, at(ii, jj + 1));
    Ok(Some(FeatureMatch {
        x: i as f32 + 0.5 + dx,
        y: j as f32 + 0.5 + dy,
        pixel: (i as u32, j as u32),
        similarity: score,
    }))
}

/// The offset in `[-0.5, 0.5]` of the vertex of the parabola through `(-1, before)`, `(0, at)`
/// and `(1, after)`; 0 without both neighbours or where the three are not a maximum.
fn vertex(before: Option<f32>, at: f32, after: Option<f32>) -> f32 {
    let (Some(before), Some(after)) = (before, after) else {
        return 0.0;
    };
    let (l, c, r) = (f64::from(before), f64::from(at), f64::from(after));
    let curvature = l - 2.0 * c + r;
    if curvature >= 0.0 {
        return 0.0;
    }
    (0.5 * (l - r) / curvature).clamp(-0.5, 0.5) as f32
}

/// Render options that composite features: `options` with [`RenderOptions::features`] on.
pub fn with_features(options: &RenderOptions) -> RenderOptions {
    RenderOptions {
        features: true,
        ..options.clone()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use glam::{Affine3A, Quat, Vec3};

    use super::eigen::jacobi_eigen;
    use super::*;
    use c4g_renderer::CpuRasterizer;
    use c4g_renderer::raster::Rasterizer;
    use c4g_scene::{Camera, FeatureBlock, Gaussian, NormalizedIntrinsics};

    fn rng(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        }
    }

    /// Samples with a known covariance: three directions of decreasing spread, plus noise.
    fn samples(rows: usize, width: usize) -> Vec<f32> {
        let mut next = rng(3);
        let directions: Vec<Vec<f64>> = (0..3)
            .map(|_| (0..width).map(|_| next()).collect())
            .collect();
        (0..rows)
            .flat_map(|_| {
                let a = [4.0 * next(), 2.0 * next(), 1.0 * next()];
                let noise: Vec<f64> = (0..width).map(|_| 0.05 * next()).collect();
                (0..width)
                    .map(|i| {
                        (0.3 + noise[i] + (0..3).map(|k| a[k] * directions[k][i]).sum::<f64>())
                            as f32
                    })
                    .collect::<Vec<_>>()
            })
            .collect()
    }

    /// The float64 reference: the covariance's full eigen-decomposition by Jacobi rotations.
    fn reference(samples: &[f32], width: usize) -> (Vec<f64>, Vec<Vec<f64>>, Vec<f64>) {
        let rows: Vec<Vec<f64>> = samples
            .chunks_exact(width)
            .map(|r| r.iter().map(|&v| f64::from(v)).collect())
            .collect();
        let m = rows.len() as f64;
        let mean: Vec<f64> = (0..width)
            .map(|i| rows.iter().map(|r| r[i]).sum::<f64>() / m)
            .collect();
        let cov: Vec<Vec<f64>> = (0..width)
            .map(|i| {
                (0..width)
                    .map(|j| {
                        rows.iter()
                            .map(|r| (r[i] - mean[i]) * (r[j] - mean[j]))
                            .sum::<f64>()
                            / m
                    })
                    .collect()
            })
            .collect();
        let (values, vectors) = jacobi_eigen(cov);
        let mut order: Vec<usize> = (0..width).collect();
        order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
        let components = order
            .iter()
            .take(3)
            .map(|&c| (0..width).map(|r| vectors[r][c]).collect())
            .collect();
        (
            mean,
            components,
            order.iter().take(3).map(|&c| values[c]).collect(),
        )
    }

    #[test]
    fn the_basis_and_projection_match_a_float64_eigen_decomposition() {
        let width = 12;
        let data = samples(400, width);
        let pca = FeaturePca::fit(&data, width).unwrap();
        let (mean, components, values) = reference(&data, width);
        for (a, b) in pca.mean().iter().zip(&mean) {
            assert!((a - b).abs() < 1e-12);
        }
        for k in 0..3 {
            // Up to sign: the fit fixes its own.
            let agreement = dot(&pca.components()[k], &components[k]).abs();
            assert!(agreement > 1.0 - 1e-9, "component {k}: |cos| = {agreement}");
            assert!(
                (pca.variances()[k] - values[k]).abs() < 1e-9 * values[0],
                "{k}"
            );
        }
        // The projection of a feature: the reference components dotted with it, centred.
        let feature: Vec<f32> = data[5 * width..6 * width].to_vec();
        let projected = pca.project(&feature);
        for k in 0..3 {
            let sign = dot(&pca.components()[k], &components[k]).signum();
            let expected: f64 = feature
                .iter()
                .zip(&mean)
                .zip(&components[k])
                .map(|((&f, m), b)| (f64::from(f) - m) * b)
                .sum();
            assert!((projected[k] - sign * expected).abs() < 1e-9, "{k}");
        }
    }

    #[test]
    fn one_basis_gives_one_feature_one_colour_and_refitting_gives_the_same_basis() {
        let width = 8;
        let data = samples(200, width);
        let a = FeaturePca::fit(&data, width).unwrap();
        let b = FeaturePca::fit(&data, width).unwrap();
        assert_eq!(a, b);
        let feature = &data[..width];
        assert_eq!(a.colour(feature), b.colour(feature));
        for c in a.colour(feature) {
            assert!((0.0..=1.0).contains(&c));
        }
        // Constant features do not vary: mid-grey, not a division by zero.
        let flat = vec![0.25f32; width * 10];
        let pca = FeaturePca::fit(&flat, width).unwrap();
        assert_eq!(pca.colour(&flat[..width]), [0.5; 3]);
        assert!(FeaturePca::fit(&[f32::NAN; 8], width).is_err());
        assert!(FeaturePca::fit(&[0.0; 7], width).is_err());
    }

    fn camera() -> Camera {
        Camera::from_normalized(
            NormalizedIntrinsics::C4G_DEFAULT,
            32,
            32,
            Affine3A::IDENTITY,
        )
        .unwrap()
    }

    /// Two blobs at depth 2 with orthogonal features; the second at `x` (scene units).
    fn scene(x: f32) -> GaussianSet {
        let blob = |position: Vec3| Gaussian {
            position,
            scale: Vec3::new(0.06, 0.06, 0.02),
            rotation: Quat::IDENTITY,
            opacity: 0.95,
            color: Vec3::splat(0.5),
        };
        let set = GaussianSet::from_gaussians([
            blob(Vec3::new(-0.4, 0.0, 2.0)),
            blob(Vec3::new(x, 0.1, 2.0)),
        ]);
        set.with_features(FeatureBlock::new(3, vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.2]).unwrap())
            .unwrap()
    }

    fn projected(camera: &Camera, p: Vec3) -> (f32, f32) {
        let k = camera.intrinsics();
        (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy)
    }

    /// A grid of small Gaussians at depth 2 whose features turn smoothly across it (in x and in y),
    /// shifted by `shift` scene units.
    fn field(shift: Vec3) -> GaussianSet {
        let mut gaussians = Vec::new();
        let mut features = Vec::new();
        for j in -4..=4 {
            for i in -4..=4 {
                gaussians.push(Gaussian {
                    position: Vec3::new(i as f32 * 0.05, j as f32 * 0.05, 2.0) + shift,
                    scale: Vec3::new(0.05, 0.05, 0.01),
                    rotation: Quat::IDENTITY,
                    opacity: 0.9,
                    color: Vec3::splat(0.5),
                });
                let a = 0.35 * i as f32;
                features.extend([a.cos(), a.sin(), 0.3 * j as f32]);
            }
        }
        GaussianSet::from_gaussians(gaussians)
            .with_features(FeatureBlock::new(3, features).unwrap())
            .unwrap()
    }

    #[test]
    fn a_feature_is_matched_where_its_surface_moved_to_a_sub_pixel_position() {
        let cam = camera();
        let options = with_features(&RenderOptions::default());
        let rasterizer = CpuRasterizer::new();
        let before = rasterizer
            .render(&field(Vec3::ZERO), &cam, &options)
            .unwrap();
        let (qi, qj) = (17usize, 15usize);
        let q = (qj * 32 + qi) * 3;
        let query = before.features.as_ref().unwrap().values[q..q + 3].to_vec();
        let start = best_match(&before, &query).unwrap().unwrap();
        assert_eq!(start.pixel, (qi as u32, qj as u32));
        // Where the similarity is not symmetric about its peak the parabola's vertex is off the
        // pixel's centre (by about a quarter pixel here): a bias of the field, the same wherever
        // it moves, so displacements come out finer than positions.
        assert!(
            (start.x - 17.5).abs() < 0.3 && (start.y - 15.5).abs() < 0.3,
            "{start:?}"
        );
        // The field moves by fractions of a pixel and by more: the match follows it.
        let px = cam.intrinsics().fx / 2.0;
        for (dx, dy) in [(0.3, 0.0), (0.0, -0.45), (1.6, 0.7), (-2.2, 1.3)] {
            let shift = Vec3::new(dx / px, dy / px, 0.0);
            let after = rasterizer.render(&field(shift), &cam, &options).unwrap();
            let found = best_match(&after, &query).unwrap().unwrap();
            let (mx, my) = (found.x - start.x, found.y - start.y);
            assert!(
                (mx - dx).abs() < 0.2 && (my - dy).abs() < 0.2,
                "moved by ({dx}, {dy}) px: the match moved by ({mx}, {my})"
            );
            assert!(found.similarity > 0.98, "{found:?}");
        }
        // An empty image has no match.
        let nothing = GaussianSet::default()
            .with_features(FeatureBlock::new(3, vec![]).unwrap())
            .unwrap();
        let empty = rasterizer.render(&nothing, &cam, &options).unwrap();
        assert_eq!(best_match(&empty, &query).unwrap(), None);
        assert!(best_match(&before, &[1.0, 0.0]).is_err());
    }

    #[test]
    fn similar_gaussians_are_selected_by_cosine_and_a_pixel_shows_its_surface_feature() {
        let set = scene(0.3);
        assert_eq!(
            select_similar(&set, &[2.0, 0.0, 0.0], 0.9).unwrap(),
            vec![0]
        );
        assert_eq!(
            select_similar(&set, &[0.0, 1.0, 0.2], 0.9).unwrap(),
            vec![1]
        );
        // cos((1,1,0), (1,0,0)) = 0.707; cos((1,1,0), (0,1,.2)) = 0.693.
        assert_eq!(
            select_similar(&set, &[1.0, 1.0, 0.0], 0.7).unwrap(),
            vec![0]
        );
        assert_eq!(
            select_similar(&set, &[1.0, 1.0, 0.0], 0.69).unwrap(),
            vec![0, 1]
        );
        assert!(
            select_similar(&set, &[0.0, 0.0, 0.0], -1.0)
                .unwrap()
                .is_empty()
        );
        assert!(select_similar(&set, &[1.0, 0.0], 0.5).is_err());
        assert_eq!(cosine(&[1.0, 0.0], &[-3.0, 0.0]), Some(-1.0));
        assert_eq!(cosine(&[1.0, 0.0], &[0.0, 0.0]), None);

        let cam = camera();
        let (x, y) = projected(&cam, Vec3::new(0.3, 0.1, 2.0));
        let weights = CpuRasterizer::new()
            .pixel_weights(
                &set,
                &cam,
                &RenderOptions::default(),
                &[(x as u32, y as u32)],
            )
            .unwrap()
            .remove(0);
        let feature = pixel_feature(&set, &weights).unwrap();
        assert!((cosine(&feature, &[0.0, 1.0, 0.2]).unwrap() - 1.0).abs() < 1e-6);
        assert_eq!(pixel_feature(&set, &[]), None);
    }

    #[test]
    fn a_coloured_feature_image_is_each_pixels_feature_colour_over_the_background() {
        let set = scene(0.3);
        let cam = camera();
        let options = with_features(&RenderOptions::default());
        let image = CpuRasterizer::new().render(&set, &cam, &options).unwrap();
        let block = set.features().unwrap();
        let pca = FeaturePca::fit(block.values(), 3).unwrap();
        let background = [0.2, 0.4, 0.6];
        let rgb = pca.colour_image(&image, background).unwrap();
        let (x, y) = projected(&cam, Vec3::new(0.3, 0.1, 2.0));
        let p = y as usize * 32 + x as usize;
        let a = image.alpha[p];
        let colour = pca.colour(block.row(1).unwrap());
        for k in 0..3 {
            let expected = a * colour[k] + (1.0 - a) * background[k];
            assert!((rgb[3 * p + k] - expected).abs() < 1e-5, "{k}");
        }
        // A pixel nothing covers is the background.
        assert_eq!(&rgb[..3], &background);
    }
}
