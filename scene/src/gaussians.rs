//! Gaussian sets: the scene at one moment of a clip, as the decoder produces it.
//!
//! A [`GaussianSet`] is a struct of arrays in the service's canonical layout (activated values:
//! linear scales, unit quaternions scalar first, opacity in 0..1, RGB colour). Arrays rather than
//! a `Vec` of structs because every consumer streams one attribute at a time (sorting by depth,
//! uploading positions to a GPU buffer, writing a PLY column) and because the ONNX decoder hands us
//! one packed `[N, 14]` buffer that splits cheaply into columns.
//!
//! The packed layout (`from_canonical` / `to_canonical`), 14 floats per Gaussian:
//!
//! | channels | meaning |
//! |---|---|
//! | 0..3 | position x, y, z (first context camera's frame, OpenCV axes) |
//! | 3..6 | scale x, y, z (linear, world units) |
//! | 6..10 | rotation quaternion w, x, y, z (scalar first, unit norm) |
//! | 10 | opacity in \[0, 1\] |
//! | 11..14 | colour R, G, B (≥ 0, usually ≤ 1) |
//!
//! Optional per-Gaussian feature vectors (the feature-lifting decoder's output) ride along in a
//! [`FeatureBlock`] of any width.

use glam::{Quat, Vec3};

use crate::SceneError;

/// Floats per Gaussian in the packed canonical layout.
pub const CANONICAL_CHANNELS: usize = 14;

/// One Gaussian, gathered from the columns of a [`GaussianSet`] for code that wants a whole one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gaussian {
    /// Centre, in the first context camera's frame (OpenCV: x right, y down, z forward).
    pub position: Vec3,
    /// Standard deviations along the Gaussian's own axes (linear, world units).
    pub scale: Vec3,
    /// Orientation of the Gaussian's axes (unit quaternion).
    pub rotation: Quat,
    /// Opacity in \[0, 1\].
    pub opacity: f32,
    /// RGB colour, ≥ 0 and usually ≤ 1.
    pub color: Vec3,
}

/// Per-Gaussian feature vectors of one width, row-major (`values[i * width..(i + 1) * width]`
/// belongs to Gaussian `i`).
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureBlock {
    width: usize,
    values: Vec<f32>,
}

impl FeatureBlock {
    /// Wraps `values` as rows of `width` floats.
    ///
    /// Fails when `width` is zero or `values` is not a whole number of rows.
    pub fn new(width: usize, values: Vec<f32>) -> Result<Self, SceneError> {
        if width == 0 {
            return Err(SceneError::ZeroFeatureWidth);
        }
        if !values.len().is_multiple_of(width) {
            return Err(SceneError::LengthMismatch {
                field: "feature values",
                expected: values.len().div_ceil(width) * width,
                actual: values.len(),
            });
        }
        Ok(Self { width, values })
    }

    /// Floats per Gaussian.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Number of rows (Gaussians).
    pub fn len(&self) -> usize {
        self.values.len() / self.width
    }

    /// True when the block has no rows.
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// All values, row-major.
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// The feature vector of Gaussian `index`, if there is one.
    pub fn row(&self, index: usize) -> Option<&[f32]> {
        let start = index.checked_mul(self.width)?;
        self.values.get(start..start + self.width)
    }

    /// Gives the values back, row-major.
    pub fn into_values(self) -> Vec<f32> {
        self.values
    }
}

/// The Gaussians of one moment: columns of equal length, plus optional feature vectors.
///
/// Construction checks only structure (equal column lengths); [`GaussianSet::validate`] checks
/// the values against the canonical layout's invariants.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct GaussianSet {
    positions: Vec<[f32; 3]>,
    scales: Vec<[f32; 3]>,
    rotations: Vec<[f32; 4]>,
    opacities: Vec<f32>,
    colors: Vec<[f32; 3]>,
    features: Option<FeatureBlock>,
}

impl GaussianSet {
    /// How far a rotation's norm may stray from 1 before [`validate`](Self::validate) rejects it.
    /// Float32 normalisation lands within ~1e-7; the slack admits models that normalise as
    /// `q / (|q| + 1e-8)` and quaternions that went through a lossy file format.
    pub const ROTATION_NORM_TOLERANCE: f32 = 1e-3;

    /// Builds a set from its columns. Rotations are `[w, x, y, z]`.
    ///
    /// Fails when the columns differ in length.
    pub fn new(
        positions: Vec<[f32; 3]>,
        scales: Vec<[f32; 3]>,
        rotations: Vec<[f32; 4]>,
        opacities: Vec<f32>,
        colors: Vec<[f32; 3]>,
    ) -> Result<Self, SceneError> {
        let expected = positions.len();
        check_len("scales", expected, scales.len())?;
        check_len("rotations", expected, rotations.len())?;
        check_len("opacities", expected, opacities.len())?;
        check_len("colors", expected, colors.len())?;
        Ok(Self {
            positions,
            scales,
            rotations,
            opacities,
            colors,
            features: None,
        })
    }

    /// Gathers whole Gaussians into columns.
    pub fn from_gaussians(gaussians: impl IntoIterator<Item = Gaussian>) -> Self {
        let mut set = Self::default();
        for g in gaussians {
            set.positions.push(g.position.to_array());
            set.scales.push(g.scale.to_array());
            let [x, y, z, w] = g.rotation.to_array();
            set.rotations.push([w, x, y, z]);
            set.opacities.push(g.opacity);
            set.colors.push(g.color.to_array());
        }
        set
    }

    /// Splits a packed `[N * 14]` buffer in the canonical layout into columns.
    ///
    /// Fails when the length is not a multiple of 14. Values are taken as they are; call
    /// [`validate`](Self::validate) to check them.
    pub fn from_canonical(packed: &[f32]) -> Result<Self, SceneError> {
        if !packed.len().is_multiple_of(CANONICAL_CHANNELS) {
            return Err(SceneError::CanonicalLength {
                len: packed.len(),
                channels: CANONICAL_CHANNELS,
            });
        }
        let n = packed.len() / CANONICAL_CHANNELS;
        let mut set = Self {
            positions: Vec::with_capacity(n),
            scales: Vec::with_capacity(n),
            rotations: Vec::with_capacity(n),
            opacities: Vec::with_capacity(n),
            colors: Vec::with_capacity(n),
            features: None,
        };
        for g in packed.chunks_exact(CANONICAL_CHANNELS) {
            set.positions.push([g[0], g[1], g[2]]);
            set.scales.push([g[3], g[4], g[5]]);
            set.rotations.push([g[6], g[7], g[8], g[9]]);
            set.opacities.push(g[10]);
            set.colors.push([g[11], g[12], g[13]]);
        }
        Ok(set)
    }

    /// Packs the set into the canonical `[N * 14]` layout (features are not part of it).
    pub fn to_canonical(&self) -> Vec<f32> {
        let mut packed = Vec::with_capacity(self.len() * CANONICAL_CHANNELS);
        for i in 0..self.len() {
            packed.extend_from_slice(&self.positions[i]);
            packed.extend_from_slice(&self.scales[i]);
            packed.extend_from_slice(&self.rotations[i]);
            packed.push(self.opacities[i]);
            packed.extend_from_slice(&self.colors[i]);
        }
        packed
    }

    /// Attaches one feature vector per Gaussian, replacing any attached before.
    ///
    /// Fails when the block's row count differs from the number of Gaussians.
    pub fn with_features(mut self, features: FeatureBlock) -> Result<Self, SceneError> {
        check_len("feature rows", self.len(), features.len())?;
        self.features = Some(features);
        Ok(self)
    }

    /// Detaches and returns the feature vectors, if any.
    pub fn take_features(&mut self) -> Option<FeatureBlock> {
        self.features.take()
    }

    /// The Gaussians whose entry in `keep` is true, in order, with their feature vectors.
    ///
    /// Fails when `keep` does not hold one entry per Gaussian.
    pub fn select(&self, keep: &[bool]) -> Result<Self, SceneError> {
        check_len("the selection", self.len(), keep.len())?;
        fn pick<T: Copy>(column: &[T], keep: &[bool]) -> Vec<T> {
            column
                .iter()
                .zip(keep)
                .filter_map(|(v, &k)| k.then_some(*v))
                .collect()
        }
        let mut set = Self::new(
            pick(&self.positions, keep),
            pick(&self.scales, keep),
            pick(&self.rotations, keep),
            pick(&self.opacities, keep),
            pick(&self.colors, keep),
        )?;
        if let Some(features) = &self.features {
            let width = features.width();
            let rows: Vec<f32> = features
                .values()
                .chunks_exact(width)
                .zip(keep)
                .filter(|(_, k)| **k)
                .flat_map(|(row, _)| row.iter().copied())
                .collect();
            set = set.with_features(FeatureBlock::new(width, rows)?)?;
        }
        Ok(set)
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when the set holds no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Centres, `[x, y, z]`.
    pub fn positions(&self) -> &[[f32; 3]] {
        &self.positions
    }

    /// Linear scales, `[x, y, z]`.
    pub fn scales(&self) -> &[[f32; 3]] {
        &self.scales
    }

    /// Unit quaternions, `[w, x, y, z]`.
    pub fn rotations(&self) -> &[[f32; 4]] {
        &self.rotations
    }

    /// Opacities in \[0, 1\].
    pub fn opacities(&self) -> &[f32] {
        &self.opacities
    }

    /// RGB colours.
    pub fn colors(&self) -> &[[f32; 3]] {
        &self.colors
    }

    /// The attached feature vectors, if any.
    pub fn features(&self) -> Option<&FeatureBlock> {
        self.features.as_ref()
    }

    /// Gaussian `index` as a whole, if there is one.
    pub fn get(&self, index: usize) -> Option<Gaussian> {
        (index < self.len()).then(|| self.gather(index))
    }

    /// Every Gaussian, in order.
    pub fn iter(&self) -> impl ExactSizeIterator<Item = Gaussian> + '_ {
        (0..self.len()).map(|i| self.gather(i))
    }

    /// Gathers Gaussian `i`, which must be in range.
    fn gather(&self, i: usize) -> Gaussian {
        let [w, x, y, z] = self.rotations[i];
        Gaussian {
            position: Vec3::from_array(self.positions[i]),
            scale: Vec3::from_array(self.scales[i]),
            rotation: Quat::from_xyzw(x, y, z, w),
            opacity: self.opacities[i],
            color: Vec3::from_array(self.colors[i]),
        }
    }

    /// Checks the canonical layout's invariants: every value finite, scales ≥ 0, rotations of unit
    /// norm (within [`ROTATION_NORM_TOLERANCE`](Self::ROTATION_NORM_TOLERANCE)), opacities in
    /// \[0, 1\], colours ≥ 0. Reports the first offending Gaussian.
    pub fn validate(&self) -> Result<(), SceneError> {
        for i in 0..self.len() {
            if let Some(reason) = self.violation(i) {
                return Err(SceneError::InvalidGaussian { index: i, reason });
            }
        }
        Ok(())
    }

    fn violation(&self, i: usize) -> Option<String> {
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        let (p, s, q, o, c) = (
            &self.positions[i],
            &self.scales[i],
            &self.rotations[i],
            self.opacities[i],
            &self.colors[i],
        );
        if !finite(p) {
            return Some(format!("position {p:?} is not finite"));
        }
        if !finite(s) || s.iter().any(|&v| v < 0.0) {
            return Some(format!("scale {s:?} is not finite and non-negative"));
        }
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        if !finite(q) || (norm - 1.0).abs() > Self::ROTATION_NORM_TOLERANCE {
            return Some(format!(
                "rotation {q:?} is not a unit quaternion (norm {norm})"
            ));
        }
        if !(0.0..=1.0).contains(&o) {
            return Some(format!("opacity {o} is outside [0, 1]"));
        }
        if !finite(c) || c.iter().any(|&v| v < 0.0) {
            return Some(format!("color {c:?} is not finite and non-negative"));
        }
        let row = self.features.as_ref().and_then(|f| f.row(i));
        if row.is_some_and(|row| !finite(row)) {
            return Some("feature vector is not finite".to_owned());
        }
        None
    }
}

fn check_len(field: &'static str, expected: usize, actual: usize) -> Result<(), SceneError> {
    if expected == actual {
        Ok(())
    } else {
        Err(SceneError::LengthMismatch {
            field,
            expected,
            actual,
        })
    }
}

#[cfg(test)]
mod tests {
    use proptest::strategy::Strategy;

    use super::*;

    fn packed_pair() -> Vec<f32> {
        vec![
            // x y z, scale, rot w x y z, opacity, rgb
            0.1, 0.2, 1.3, 0.01, 0.02, 0.03, 1.0, 0.0, 0.0, 0.0, 0.5, 0.9, 0.8, 0.7, //
            -0.4, 0.5, 2.0, 0.1, 0.1, 0.2, 0.0, 0.6, 0.0, 0.8, 1.0, 0.0, 0.25, 1.0,
        ]
    }

    #[test]
    fn canonical_round_trip_preserves_every_value_and_column() {
        let packed = packed_pair();
        let set = GaussianSet::from_canonical(&packed).unwrap();
        assert_eq!(set.len(), 2);
        assert_eq!(set.positions()[1], [-0.4, 0.5, 2.0]);
        assert_eq!(set.scales()[0], [0.01, 0.02, 0.03]);
        assert_eq!(set.rotations()[1], [0.0, 0.6, 0.0, 0.8]);
        assert_eq!(set.opacities(), &[0.5, 1.0]);
        assert_eq!(set.colors()[1], [0.0, 0.25, 1.0]);
        assert_eq!(set.to_canonical(), packed);
        set.validate().unwrap();
    }

    #[test]
    fn canonical_length_must_be_a_multiple_of_14() {
        let err = GaussianSet::from_canonical(&[0.0; 15]).unwrap_err();
        assert_eq!(
            err,
            SceneError::CanonicalLength {
                len: 15,
                channels: 14
            }
        );
        assert!(GaussianSet::from_canonical(&[]).unwrap().is_empty());
    }

    #[test]
    fn columns_of_different_lengths_are_rejected() {
        let err = GaussianSet::new(
            vec![[0.0; 3]; 2],
            vec![[0.0; 3]; 2],
            vec![[1.0, 0.0, 0.0, 0.0]; 1],
            vec![0.5; 2],
            vec![[0.0; 3]; 2],
        )
        .unwrap_err();
        assert!(matches!(
            err,
            SceneError::LengthMismatch {
                field: "rotations",
                expected: 2,
                actual: 1
            }
        ));
    }

    #[test]
    fn get_reads_the_scalar_first_quaternion_into_glam_order() {
        let set = GaussianSet::from_canonical(&packed_pair()).unwrap();
        let g = set.get(1).unwrap();
        assert_eq!(g.rotation, Quat::from_xyzw(0.6, 0.0, 0.8, 0.0));
        assert_eq!(g.position, Vec3::new(-0.4, 0.5, 2.0));
        assert!(set.get(2).is_none());
        assert_eq!(GaussianSet::from_gaussians(set.iter()), set);
    }

    #[test]
    fn features_attach_only_with_one_row_per_gaussian() {
        let set = GaussianSet::from_canonical(&packed_pair()).unwrap();
        let block = FeatureBlock::new(3, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]).unwrap();
        let with = set.clone().with_features(block).unwrap();
        assert_eq!(with.features().unwrap().row(1), Some(&[4.0, 5.0, 6.0][..]));
        assert_eq!(with.features().unwrap().row(2), None);
        let wrong = FeatureBlock::new(2, vec![0.0; 2]).unwrap();
        assert!(set.with_features(wrong).is_err());
        assert_eq!(
            FeatureBlock::new(0, vec![]),
            Err(SceneError::ZeroFeatureWidth)
        );
        assert!(FeatureBlock::new(4, vec![0.0; 6]).is_err());
    }

    #[test]
    fn validate_names_the_first_gaussian_that_breaks_an_invariant() {
        let cases: [(usize, f32, &str); 6] = [
            (0, f32::NAN, "position"),
            (4, -0.1, "scale"),
            (6, 0.5, "rotation"),
            (10, 1.5, "opacity"),
            (12, -0.2, "color"),
            (13, f32::INFINITY, "color"),
        ];
        for (channel, value, what) in cases {
            let mut packed = packed_pair();
            packed[14 + channel] = value;
            let err = GaussianSet::from_canonical(&packed)
                .unwrap()
                .validate()
                .unwrap_err();
            match err {
                SceneError::InvalidGaussian { index, reason } => {
                    assert_eq!(index, 1);
                    assert!(reason.starts_with(what), "{reason}");
                }
                other => panic!("unexpected {other:?}"),
            }
        }
    }

    #[test]
    fn validate_rejects_non_finite_features() {
        let set = GaussianSet::from_canonical(&packed_pair())
            .unwrap()
            .with_features(FeatureBlock::new(1, vec![0.0, f32::NAN]).unwrap())
            .unwrap();
        assert!(matches!(
            set.validate(),
            Err(SceneError::InvalidGaussian { index: 1, .. })
        ));
    }

    proptest::proptest! {
        #[test]
        fn any_packed_buffer_round_trips_bit_for_bit(
            packed in (0usize..6).prop_flat_map(|n| {
                proptest::collection::vec(proptest::num::f32::ANY, n * CANONICAL_CHANNELS)
            })
        ) {
            let back = GaussianSet::from_canonical(&packed).unwrap().to_canonical();
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            proptest::prop_assert_eq!(bits(&back), bits(&packed));
        }
    }
}
