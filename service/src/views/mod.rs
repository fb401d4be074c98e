//! What is seen of a clip's sets: renders (one view, or a camera path for both transports),
//! the images' formats, 4D exports, feature images and segments, point tracks, and the cameras
//! found by rendering (recovered cameras, the scale fit of given cameras). Views ask the sets
//! layer for sets and the clips layer for records and frames.
//!
//! | module | holds |
//! |---|---|
//! | [`render`] | [`Views`](render::Views), one view of a clip at a time, a camera path frame by frame |
//! | [`camera`] | cameras as clients state them, or the input camera at a time |
//! | [`rasterizer`] | the rasterizer choice and the footprint it renders with |
//! | [`image_formats`] | what renders answer with: PNG, raw depth, alpha and features, MP4 |
//! | [`exports`] | 4D exports: a time range as a zip of `.ply` or `.spz` files, or a fitted `.splatv` |
//! | [`feature_field`] | what a package lifts, and each clip's PCA colouring basis, cached |
//! | [`features`] | the 4D feature field: decodes with lifted features, feature images, segments |
//! | [`tracking`] | point tracks through a clip, by Gaussians or by lifted features |
//! | [`recovery`] | recovered cameras: each context frame's camera by photometric alignment |
//! | [`camera_scale`] | given cameras fitted to the model's depth scale at upload |
//! | [`camera_files`] | the clip's input cameras as files other tools open (JSON, COLMAP, transforms.json) |

pub mod camera;
pub mod camera_files;
pub mod camera_scale;
pub mod exports;
pub mod feature_field;
pub mod features;
pub mod image_formats;
pub mod rasterizer;
pub mod recovery;
pub mod render;
pub mod tracking;
