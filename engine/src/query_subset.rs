//! Which of the decoder's queries to run: all N, or a subset that drops the others' tokens from
//! the decoder itself.
//!
//! Query i is Gaussian i at every time. A package whose decoder takes `query_indices`
//! (`model.json`: `decoder_query_subset`) decodes the kept queries alone: a shorter sequence, so
//! every decode is cheaper, but an approximation, because queries attend to each other and the
//! kept Gaussians come out of an attention without the dropped tokens (`docs/tradeoffs.md`
//! measures by how much). With every index kept, the decode is the full one.
//!
//! Indices are checked here, before they reach ONNX Runtime: its Gather takes negative indices
//! (counted from the end) and repeats without complaint, and either would quietly decode another
//! scene than the one asked for. They must be strictly increasing, so the Gaussians of a subset
//! come out in the full set's order.

use crate::{EngineError, Result};

/// The queries a decode runs, as the decoder's `query_indices` input: a non-empty, strictly
/// increasing list of indices below the package's Gaussian count.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct QuerySubset {
    indices: Vec<i64>,
}

impl QuerySubset {
    /// Every query of a package with `gaussian_count` Gaussians.
    pub fn all(gaussian_count: usize) -> Self {
        Self {
            indices: (0..gaussian_count as i64).collect(),
        }
    }

    /// The queries `indices` of a package with `gaussian_count` Gaussians, checked.
    pub fn new(indices: &[usize], gaussian_count: usize) -> Result<Self> {
        if indices.is_empty() {
            return Err(EngineError::InvalidInput(
                "a query subset needs at least one query index".to_owned(),
            ));
        }
        if let Some(&bad) = indices.iter().find(|&&i| i >= gaussian_count) {
            return Err(EngineError::InvalidInput(format!(
                "query index {bad} is out of range: the package decodes {gaussian_count} queries (0 to {})",
                gaussian_count - 1
            )));
        }
        if let Some(w) = indices.windows(2).find(|w| w[0] >= w[1]) {
            return Err(EngineError::InvalidInput(format!(
                "query indices must be strictly increasing (no repeats): {} is followed by {}",
                w[0], w[1]
            )));
        }
        Ok(Self {
            indices: indices.iter().map(|&i| i as i64).collect(),
        })
    }

    /// The queries kept by a mask over all of a package's Gaussians (`keep[i]`: keep query i),
    /// such as a pruning analysis gives.
    pub fn from_mask(keep: &[bool]) -> Result<Self> {
        let indices: Vec<usize> = (0..keep.len()).filter(|&i| keep[i]).collect();
        Self::new(&indices, keep.len())
    }

    /// How many queries it runs (Q).
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    /// Never true: a subset holds at least one query. (For clippy's `len_without_is_empty`.)
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// The indices, as the decoder's int64 input.
    pub fn indices(&self) -> &[i64] {
        &self.indices
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_subset_is_non_empty_in_range_and_strictly_increasing() {
        assert_eq!(
            QuerySubset::new(&[0, 3, 7], 8).unwrap().indices(),
            &[0, 3, 7]
        );
        assert_eq!(QuerySubset::new(&[5], 8).unwrap().len(), 1);
        assert_eq!(QuerySubset::all(3).indices(), &[0, 1, 2]);
        for (bad, says) in [
            (vec![], "at least one"),
            (vec![8], "out of range"),
            (vec![1, 1], "strictly increasing"),
            (vec![3, 2], "strictly increasing"),
        ] {
            let e = QuerySubset::new(&bad, 8).unwrap_err();
            assert_eq!(e.kind(), crate::ErrorKind::InvalidInput);
            assert!(e.to_string().contains(says), "{bad:?}: {e}");
        }
    }

    #[test]
    fn a_mask_keeps_the_marked_queries_and_must_keep_one() {
        let subset = QuerySubset::from_mask(&[true, false, false, true]).unwrap();
        assert_eq!(subset.indices(), &[0, 3]);
        assert!(QuerySubset::from_mask(&[false, false]).is_err());
    }
}
