//! The intake's limits, checked on what media declares before anything large is decoded, and
//! again on what is read: options, frame sizes, frame counts, durations.

use crate::ServiceError;
use crate::clips::intake::media::IntakeOptions;
use crate::config::Limits;

/// Checks an upload's options against the limits before any media is read (the fuzz targets
/// call it on their own).
pub fn validate_options(options: &IntakeOptions, limits: &Limits) -> Result<(), ServiceError> {
    for (name, value) in [
        ("fps", options.fps),
        ("start", options.start),
        ("end", options.end),
    ] {
        if let Some(v) = value
            && !v.is_finite()
        {
            return Err(ServiceError::invalid(format!(
                "{name} must be a finite number, got {v}"
            )));
        }
    }
    if let Some(fps) = options.fps
        && fps <= 0.0
    {
        return Err(ServiceError::invalid(format!(
            "fps must be positive, got {fps}"
        )));
    }
    if let (Some(start), Some(end)) = (options.start, options.end)
        && start > end
    {
        return Err(ServiceError::invalid(format!(
            "the window start {start} is after its end {end}"
        )));
    }
    if let Some(n) = options.max_frames
        && (n == 0 || n > limits.max_context_frames)
    {
        return Err(ServiceError::invalid(format!(
            "max_frames must be between 1 and {} (C4G_MAX_CONTEXT_FRAMES), got {n}",
            limits.max_context_frames
        )));
    }
    if let Some(stride) = options.stride
        && (stride == 0 || stride > limits.max_source_frames)
    {
        return Err(ServiceError::invalid(format!(
            "stride must be between 1 and {} (C4G_MAX_SOURCE_FRAMES), got {stride}",
            limits.max_source_frames
        )));
    }
    if let Some(times) = &options.timestamps {
        if let Some(t) = times.iter().find(|t| !t.is_finite()) {
            return Err(ServiceError::invalid(format!(
                "timestamps must be finite, got {t}"
            )));
        }
        if times.windows(2).any(|w| w[0] >= w[1]) {
            return Err(ServiceError::invalid(
                "timestamps must be strictly increasing",
            ));
        }
    }
    Ok(())
}

/// Frame-size checks shared by videos and images.
pub(crate) fn check_frame_size(
    width: u32,
    height: u32,
    limits: &Limits,
) -> Result<(), ServiceError> {
    if width > limits.max_side || height > limits.max_side {
        return Err(ServiceError::TooLarge(format!(
            "frames are {width}x{height}; the largest side allowed is {} pixels (C4G_MAX_SIDE)",
            limits.max_side
        )));
    }
    if width < limits.min_side || height < limits.min_side {
        return Err(ServiceError::UnreadableMedia(format!(
            "frames are {width}x{height}; both sides must be at least {} pixels (C4G_MIN_SIDE)",
            limits.min_side
        )));
    }
    Ok(())
}

pub(crate) fn check_frame_count(frames: usize, limits: &Limits) -> Result<(), ServiceError> {
    if frames > limits.max_source_frames {
        return Err(ServiceError::TooLarge(format!(
            "the clip has {frames} frames; at most {} are accepted (C4G_MAX_SOURCE_FRAMES)",
            limits.max_source_frames
        )));
    }
    Ok(())
}

pub(crate) fn check_duration(duration: f64, limits: &Limits) -> Result<(), ServiceError> {
    if duration > limits.max_duration_s {
        return Err(ServiceError::TooLarge(format!(
            "the clip lasts {duration:.1} s; at most {} s are accepted (C4G_MAX_DURATION_S)",
            limits.max_duration_s
        )));
    }
    Ok(())
}
