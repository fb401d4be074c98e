//! The Gaussian sets of a clip at any times, under any options: the one seam everything that
//! needs sets goes through. It asks only the clips layer below it (for records and encodings).

pub mod batching;
pub mod keyframes;
pub mod pruning;
pub mod quality;
pub mod streaming;
