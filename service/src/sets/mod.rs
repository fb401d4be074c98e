//! The Gaussian sets of a clip at any times, under any options: the one seam everything that
//! needs sets goes through ([`SetSource`]). It asks only the clips layer below it (for records
//! and encodings).
//!
//! | module | holds |
//! |---|---|
//! | [`source`] | [`SetSource`]: checks, exact and approximated decodes, plans, on work slots |
//! | [`plan`] | what a request keeps of a clip's Gaussians, and where a multi-time request's sets come from |
//! | [`decoder`] | the engine's decodes on the calling thread, timed and counted |
//! | [`batching`] | exact decodes of one clip from concurrent requests gathered into shared decoder runs |
//! | [`keyframes`] | keyframed decoding as clients ask for it, checked against the limits |
//! | [`scene`] | which scene serves a request: the feed-forward one or the clip's fitted one |
//! | [`quality`] | the speed/accuracy presets (exact, balanced, fast) and pruning as clients ask for it |
//! | [`pruning`] | which Gaussians a pruned request keeps: each clip's scene analysis, cached |
//! | [`streaming`] | streams of sets over a time range, planned once, decoded ahead of the reader, as sets or `C4GV` |

pub mod batching;
pub mod decoder;
pub mod keyframes;
pub mod plan;
pub mod pruning;
pub mod quality;
pub mod scene;
pub mod source;
pub mod streaming;

pub use source::SetSource;
