//! Clip intake: untrusted uploads in, timed context frames out.
//!
//! An upload is a video (read by FFmpeg in a child process, so that hostile media can at worst
//! crash that process), an image archive (zip or tar), or a list of image frames. Every limit is
//! checked on what the media declares before anything large is decoded, and again on what is
//! actually read. Then [`sampling`] picks the context frames.
//!
//! | module | holds |
//! |---|---|
//! | `sniff` | what kind of media some bytes are |
//! | `video` | FFmpeg / ffprobe as subprocesses with time limits |
//! | `images` | zip and tar archives, image frames, decompression limits |
//! | `sampling` | which frames become context frames |
//! | `media` | what an upload is, how to read it, what the source was, the timed frames, the clip id |
//! | `limits` | the intake's limits on options, frame sizes, counts and durations |
//! | `read` | an upload read into timed context frames |
//! | [`kept`] | source frames kept small for fits: a second pass over the upload |
//! | [`cameras`] | given cameras (a JSON list, COLMAP text, nerfstudio's `transforms.json`) |

pub mod cameras;
pub mod images;
pub mod kept;
mod limits;
mod media;
mod read;
mod sampling;
pub mod sniff;
mod video;

pub use limits::validate_options;
pub use media::{
    DEFAULT_IMAGE_FPS, Intake, IntakeOptions, IntakeTools, Media, SourceInfo, TimedFrame, clip_id,
    frame_step,
};
pub use read::read;
pub use sniff::MediaKind;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_frame_step_is_the_median_gap_between_source_frames_else_the_frame_period() {
        let at_30fps: Vec<f64> = (0..10).map(|i| f64::from(i) / 30.0).collect();
        let step = frame_step(&at_30fps, 25.0).unwrap();
        assert!((step - 1.0 / 30.0).abs() < 1e-12, "{step}");
        // A near-duplicate timestamp and a dropped frame do not set the step.
        let step = frame_step(&[0.0, 0.1, 0.100_001, 0.2, 0.3, 0.5], 10.0).unwrap();
        assert!((step - 0.1).abs() < 1e-9, "{step}");
        // One frame: the declared rate; no rate either: unknown.
        assert_eq!(frame_step(&[0.0], 10.0), Some(0.1));
        assert_eq!(frame_step(&[0.0], 0.0), None);
        assert_eq!(frame_step(&[], f64::NAN), None);
    }

    #[test]
    fn a_source_stored_before_warnings_were_recorded_loads_and_an_empty_list_is_not_written() {
        let old: SourceInfo = serde_json::from_value(serde_json::json!({
            "kind": "video", "frames": 141, "width": 368, "height": 480, "duration": 7.0, "fps": 20.0,
        }))
        .unwrap();
        assert!(old.warnings.is_empty());
        assert!(
            serde_json::to_value(&old)
                .unwrap()
                .get("warnings")
                .is_none()
        );
        let warned = SourceInfo {
            warnings: vec!["skipped".into()],
            ..old
        };
        assert_eq!(
            serde_json::to_value(&warned).unwrap()["warnings"][0],
            "skipped"
        );
    }
}
