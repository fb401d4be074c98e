//! What is seen of a clip's sets: renders (one view, or a camera path for both transports),
//! the images' formats, 4D exports, feature images and segments, point tracks, and the cameras
//! found by rendering (recovered cameras, the scale fit of given cameras). Views ask the sets
//! layer for sets and the clips layer for records and frames.

pub mod camera;
pub mod camera_scale;
pub mod exports;
pub mod features;
pub mod image_formats;
pub mod rasterizer;
pub mod recovery;
pub mod tracking;
