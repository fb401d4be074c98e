//! A run's named f32 outputs, checked against the shapes their caller expects.
//!
//! A graph that returns the wrong tensor, or the right one with a wrong shape, is a broken
//! package or export; checking every output here turns it into an error naming the graph and the
//! output instead of an index out of bounds or a silently wrong result further on.

use ort::session::SessionOutputs;

use crate::{Result, RuntimeError};

/// The outputs of one run of a [`Graph`](crate::Graph), borrowed from its session.
pub struct RunOutputs<'a, 's> {
    graph: &'a str,
    outputs: &'a SessionOutputs<'s>,
}

impl<'a, 's> RunOutputs<'a, 's> {
    pub(crate) fn new(graph: &'a str, outputs: &'a SessionOutputs<'s>) -> Self {
        Self { graph, outputs }
    }

    /// The f32 output `name`, which must have exactly the shape `expected` (rank, each
    /// dimension, and so its element count); [`RuntimeError::ModelOutput`] otherwise.
    pub fn f32(&self, name: &str, expected: &[usize]) -> Result<&'a [f32]> {
        let graph = self.graph;
        let value = self.outputs.get(name).ok_or_else(|| {
            RuntimeError::ModelOutput(format!("the {graph} returned no {name:?}"))
        })?;
        let (shape, data) = value
            .try_extract_tensor::<f32>()
            .map_err(RuntimeError::ort(format!("reading the {graph}'s {name:?}")))?;
        if !has_shape(shape, data.len(), expected) {
            return Err(RuntimeError::ModelOutput(format!(
                "the {graph}'s {name:?} has shape {:?}, expected {expected:?}",
                &**shape
            )));
        }
        Ok(data)
    }
}

/// True when a tensor of `shape` holding `len` values has exactly the shape `expected`: the same
/// rank, every dimension equal, and as many values as that shape holds.
fn has_shape(shape: &[i64], len: usize, expected: &[usize]) -> bool {
    shape.len() == expected.len()
        && shape
            .iter()
            .zip(expected)
            .all(|(&d, &e)| usize::try_from(d) == Ok(e))
        && len == expected.iter().product::<usize>()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_expected_shape_with_its_values_matches() {
        assert!(has_shape(&[2, 3, 4], 24, &[2, 3, 4]));
        assert!(has_shape(&[], 1, &[]));
        assert!(has_shape(&[0, 5], 0, &[0, 5]));
    }

    #[test]
    fn another_rank_does_not_match() {
        assert!(!has_shape(&[2, 3], 6, &[2, 3, 1]));
        assert!(!has_shape(&[6], 6, &[2, 3]));
    }

    #[test]
    fn another_dimension_does_not_match() {
        assert!(!has_shape(&[2, 4], 8, &[2, 3]));
        assert!(!has_shape(&[3, 2], 6, &[2, 3]));
        // A dynamic (-1) dimension left in an output's shape is never an expected size.
        assert!(!has_shape(&[-1, 3], 6, &[2, 3]));
    }

    #[test]
    fn another_element_count_does_not_match() {
        assert!(!has_shape(&[2, 3], 5, &[2, 3]));
        assert!(!has_shape(&[2, 3], 7, &[2, 3]));
    }
}
