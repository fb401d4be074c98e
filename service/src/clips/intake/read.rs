//! Reading an upload: a video through FFmpeg, or image frames and archives, into timed context
//! frames, holding it to the limits.

use crate::ServiceError;
use crate::clips::intake::kept::Keep;
use crate::clips::intake::limits::validate_options;
use crate::clips::intake::media::{Intake, IntakeOptions, IntakeTools, Media};
use crate::clips::intake::sniff::MediaKind;
use crate::clips::intake::{images, video};
use crate::config::Limits;

/// Reads an upload into context frames (and the source frames `keep` asks for), holding it to
/// `limits`.
pub async fn read(
    media: Media,
    options: &IntakeOptions,
    limits: &Limits,
    tools: &IntakeTools,
    keep: Keep,
) -> Result<Intake, ServiceError> {
    validate_options(options, limits)?;
    if media.is_empty() {
        return Err(ServiceError::invalid(
            "the upload is empty: send a video file, an image archive (zip, tar) or image frames",
        ));
    }
    let kind = match &media {
        Media::Frames(_) => MediaKind::Frames,
        Media::File { data, kind } => match kind {
            Some(kind) => *kind,
            None => crate::clips::intake::sniff::sniff(data),
        },
    };
    match (kind, media) {
        (MediaKind::Video | MediaKind::Unknown, Media::File { data, .. }) => {
            video::read(data, kind, options, limits, tools, keep).await
        }
        (kind, media) => {
            let (options, limits) = (options.clone(), limits.clone());
            tokio::task::spawn_blocking(move || images::read(media, kind, &options, &limits, keep))
                .await
                .map_err(|e| ServiceError::Internal(format!("image intake panicked: {e}")))?
        }
    }
}
