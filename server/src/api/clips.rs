//! `/v1/clips`: upload (a video, an image archive, or multipart frames), list, describe, delete,
//! and a clip's context frames.

use axum::Json;
use axum::body::Body;
use axum::extract::{FromRequest, Multipart, Request, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::{Bytes, BytesMut};
use http_body_util::{BodyExt, LengthLimitError, Limited};
use serde_json::{Value, json};

use super::json::{ClipId, FrameIndex, query_pairs};
use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::ServiceError;
use c4g_service::clips::intake::cameras::{CameraInput, parse_names};
use c4g_service::clips::intake::{IntakeOptions, Media, MediaKind};
use c4g_service::clips::record::ClipRecord;
use c4g_service::quoted;

/// A clip as the API shows it.
pub fn clip_json(record: &ClipRecord, created: Option<bool>) -> Value {
    let (first, last) = record.span();
    let mut value = json!({
        "id": record.id,
        "model": record.model,
        "state": "ready",
        "context_times": record.context_times,
        "span": [first, last],
        "source": record.source,
        "options": record.options,
        "feature_bytes": record.feature_bytes(),
        "created_at": record.created_at,
    });
    if let Some(cameras) = &record.cameras {
        value["cameras"] = json!(cameras);
    }
    if let Some(created) = created {
        value["created"] = json!(created);
    }
    value
}

pub async fn upload(
    State(state): State<AppState>,
    request: Request,
) -> Result<Response, ErrorReply> {
    let service = state.service()?.clone();
    let limit = service.limits.max_body_bytes;
    let mut fields = query_pairs(request.uri().query())?;
    let content_type = request
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase();
    let media = if content_type.starts_with("multipart/form-data") {
        let multipart = Multipart::from_request(request, &())
            .await
            .map_err(|e| ServiceError::invalid(format!("not a readable multipart body: {e}")))?;
        read_multipart(multipart, limit, &mut fields).await?
    } else {
        let kind = match content_type.split(';').next().unwrap_or("").trim() {
            "application/zip" | "application/x-zip-compressed" => Some(MediaKind::Zip),
            "application/x-tar" => Some(MediaKind::Tar),
            _ => None,
        };
        Media::File {
            data: read_body(request.into_body(), limit).await?,
            kind,
        }
    };
    let options = parse_options(&fields)?;
    let (record, created) = service.upload(media, options).await?;
    let status = if created {
        StatusCode::CREATED
    } else {
        StatusCode::OK
    };
    Ok((status, Json(clip_json(&record, Some(created)))).into_response())
}

async fn read_body(body: Body, limit: usize) -> Result<Bytes, ServiceError> {
    match Limited::new(body, limit).collect().await {
        Ok(collected) => Ok(collected.to_bytes()),
        Err(e) if e.downcast_ref::<LengthLimitError>().is_some() => Err(too_large(limit)),
        Err(e) => Err(ServiceError::invalid(format!(
            "the upload was cut off: {e}"
        ))),
    }
}

fn too_large(limit: usize) -> ServiceError {
    ServiceError::TooLarge(format!(
        "the upload is over {limit} bytes (C4G_MAX_BODY_MIB)"
    ))
}

async fn read_multipart(
    mut multipart: Multipart,
    limit: usize,
    fields: &mut Vec<(String, String)>,
) -> Result<Media, ServiceError> {
    let mut file: Option<Bytes> = None;
    let mut frames = Vec::new();
    let mut total = 0usize;
    let map = |e: axum::extract::multipart::MultipartError| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            too_large(limit)
        } else {
            ServiceError::invalid(format!(
                "the multipart body cannot be read: {}",
                e.body_text()
            ))
        }
    };
    while let Some(mut field) = multipart.next_field().await.map_err(map)? {
        let name = field.name().unwrap_or("").to_owned();
        let mut data = BytesMut::new();
        while let Some(chunk) = field.chunk().await.map_err(map)? {
            total += chunk.len();
            if total > limit {
                return Err(too_large(limit));
            }
            data.extend_from_slice(&chunk);
        }
        match name.as_str() {
            "file" if file.is_none() => file = Some(data.freeze()),
            "file" => return Err(ServiceError::invalid("send one `file` part")),
            "frame" => frames.push(data.freeze()),
            option => {
                let text = String::from_utf8(data.to_vec()).map_err(|_| {
                    ServiceError::invalid(format!("the `{option}` field is not text"))
                })?;
                fields.push((option.to_owned(), text));
            }
        }
    }
    match (file, frames.is_empty()) {
        (Some(_), false) => Err(ServiceError::invalid(
            "send either one `file` part or `frame` parts, not both",
        )),
        (Some(data), true) => Ok(Media::File { data, kind: None }),
        (None, false) => Ok(Media::Frames(frames)),
        (None, true) => Err(ServiceError::invalid(
            "the multipart body has no `file` or `frame` part",
        )),
    }
}

/// Upload options from query or multipart fields, every value checked.
fn parse_options(fields: &[(String, String)]) -> Result<IntakeOptions, ServiceError> {
    fn number<T: std::str::FromStr>(name: &str, value: &str) -> Result<T, ServiceError> {
        value.trim().parse().map_err(|_| {
            ServiceError::invalid(format!(
                "`{name}` must be a number, got {value_quoted}",
                value_quoted = quoted(value)
            ))
        })
    }
    let mut options = IntakeOptions::default();
    let mut cameras = CameraFields::default();
    for (name, value) in fields {
        match name.as_str() {
            "cameras" => cameras.json = Some(value.clone()),
            "colmap_cameras" => cameras.colmap_cameras = Some(value.clone()),
            "colmap_images" => cameras.colmap_images = Some(value.clone()),
            "transforms" => cameras.transforms = Some(value.clone()),
            "camera_names" => cameras.names = Some(parse_names(value)?),
            "fps" => options.fps = Some(number(name, value)?),
            "max_frames" => options.max_frames = Some(number(name, value)?),
            "stride" => options.stride = Some(number(name, value)?),
            "start" => options.start = Some(number(name, value)?),
            "end" => options.end = Some(number(name, value)?),
            "timestamps" => options.timestamps = Some(timestamps(value)?),
            other => {
                return Err(ServiceError::invalid(format!(
                    "unknown upload option `{other}`: use fps, timestamps, max_frames, stride, \
                     start, end, or cameras (cameras, colmap_cameras with colmap_images, or \
                     transforms; camera_names)"
                )));
            }
        }
    }
    options.cameras = cameras.input()?;
    Ok(options)
}

/// The upload fields that carry cameras, before they are known to make one form.
#[derive(Default)]
struct CameraFields {
    json: Option<String>,
    colmap_cameras: Option<String>,
    colmap_images: Option<String>,
    transforms: Option<String>,
    names: Option<Vec<String>>,
}

impl CameraFields {
    fn input(self) -> Result<Option<CameraInput>, ServiceError> {
        let Self {
            json,
            colmap_cameras,
            colmap_images,
            transforms,
            names,
        } = self;
        let forms = [
            json.is_some(),
            colmap_cameras.is_some() || colmap_images.is_some(),
            transforms.is_some(),
        ];
        if forms.iter().filter(|f| **f).count() > 1 {
            return Err(ServiceError::invalid(
                "give cameras in one form: `cameras` (JSON), `colmap_cameras` with \
                 `colmap_images`, or `transforms`",
            ));
        }
        match (json, colmap_cameras, colmap_images, transforms) {
            (Some(_), ..) if names.is_some() => Err(ServiceError::invalid(
                "camera_names matches COLMAP images or transforms.json frames to frames; the \
                 JSON list is already in frame order",
            )),
            (Some(json), ..) => Ok(Some(CameraInput::Json(json))),
            (_, Some(cameras), Some(images), _) => Ok(Some(CameraInput::Colmap {
                cameras,
                images,
                names,
            })),
            (_, Some(_), None, _) | (_, None, Some(_), _) => Err(ServiceError::invalid(
                "COLMAP cameras need both `colmap_cameras` (cameras.txt) and `colmap_images` \
                 (images.txt)",
            )),
            (_, _, _, Some(json)) => Ok(Some(CameraInput::Transforms { json, names })),
            (None, None, None, None) if names.is_some() => Err(ServiceError::invalid(
                "camera_names without cameras: add `colmap_cameras` and `colmap_images`, or \
                 `transforms`",
            )),
            _ => Ok(None),
        }
    }
}

/// `timestamps`: comma-separated decimal numbers (`0,0.1,0.25`, spaces allowed around the
/// commas), as `openapi.json`'s pattern states.
fn timestamps(value: &str) -> Result<Vec<f64>, ServiceError> {
    value
        .split(',')
        .map(|item| {
            let item = item.trim_matches(' ');
            match item.parse::<f64>() {
                Ok(t) if !t.is_finite() => Err(ServiceError::invalid(format!(
                    "timestamps must be finite, got {item}"
                ))),
                Ok(t) if is_decimal(item) => Ok(t),
                _ => Err(ServiceError::invalid(format!(
                    "timestamps must be comma-separated decimal numbers of seconds (0,0.1,0.25), \
                     got {item_quoted}",
                    item_quoted = quoted(item)
                ))),
            }
        })
        .collect()
}

/// `-?digits(.digits)?(e[+-]?d{1,2})?`: a number as JSON writes it (leading zeros allowed), its
/// exponent short enough that it is always finite.
fn is_decimal(text: &str) -> bool {
    fn digits(s: &str) -> (&str, bool) {
        let end = s.find(|c: char| !c.is_ascii_digit()).unwrap_or(s.len());
        (&s[end..], end > 0)
    }
    let (rest, whole) = digits(text.strip_prefix('-').unwrap_or(text));
    if !whole {
        return false;
    }
    let rest = match rest.strip_prefix('.') {
        Some(fraction) => match digits(fraction) {
            (rest, true) => rest,
            _ => return false,
        },
        None => rest,
    };
    match rest.strip_prefix(['e', 'E']) {
        Some(exponent) => {
            let exponent = exponent.strip_prefix(['+', '-']).unwrap_or(exponent);
            matches!(digits(exponent), ("", true)) && exponent.len() <= 2
        }
        None => rest.is_empty(),
    }
}

pub async fn list(State(state): State<AppState>) -> Result<Json<Value>, ErrorReply> {
    let clips: Vec<Value> = state
        .service()?
        .store
        .list_all()
        .await?
        .iter()
        .map(|r| clip_json(r, None))
        .collect();
    Ok(Json(json!({ "clips": clips })))
}

pub async fn get(
    State(state): State<AppState>,
    ClipId(id): ClipId,
) -> Result<Json<Value>, ErrorReply> {
    let service = state.service()?;
    let record = service.store.get_or_fetch(&id).await?;
    let mut clip = clip_json(&record, None);
    if let Some(recovered) = service.views.recovered_cameras(&id) {
        clip["recovered_cameras"] = json!(recovered);
    }
    if let Some(fitted) = service.sets.fitted.get(&id).await? {
        clip["fitted"] = json!(fitted.summary);
    }
    Ok(Json(clip))
}

pub async fn delete(
    State(state): State<AppState>,
    ClipId(id): ClipId,
) -> Result<StatusCode, ErrorReply> {
    state.service()?.delete(&id).await?;
    Ok(StatusCode::NO_CONTENT)
}

pub async fn frame(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    FrameIndex(index): FrameIndex,
) -> Result<Response, ErrorReply> {
    let png = state.service()?.store.context_frame_png(&id, index).await?;
    Ok(([(header::CONTENT_TYPE, "image/png")], png).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pairs(list: &[(&str, &str)]) -> Vec<(String, String)> {
        list.iter()
            .map(|(a, b)| (a.to_string(), b.to_string()))
            .collect()
    }

    #[test]
    fn options_parse_and_refuse_what_they_do_not_know() {
        let options = parse_options(&pairs(&[
            ("fps", "12.5"),
            ("timestamps", "0,0.5, 1.25"),
            ("max_frames", "3"),
        ]))
        .unwrap();
        assert_eq!(options.fps, Some(12.5));
        assert_eq!(options.timestamps, Some(vec![0.0, 0.5, 1.25]));
        assert_eq!(options.max_frames, Some(3));
        assert!(parse_options(&pairs(&[("fsp", "3")])).is_err());
        assert!(parse_options(&pairs(&[("fps", "fast")])).is_err());
        assert!(query_pairs(Some("fps=10&start=0.5")).unwrap().len() == 2);
    }

    #[test]
    fn timestamps_are_comma_separated_decimals_as_the_contract_states() {
        assert_eq!(timestamps("0").unwrap(), vec![0.0]);
        assert_eq!(
            timestamps(" 0 ,1e-3, -2.5E+1 ").unwrap(),
            vec![0.0, 0.001, -25.0]
        );
        for bad in [
            "", "0,", ",0", "0,,1", "[0,1]", "+1", "1.", ".5", "0x1", "1e", "0;1", "\t1", "1e400",
        ] {
            assert!(timestamps(bad).is_err(), "{bad:?}");
        }
        assert!(
            timestamps("0,NaN")
                .unwrap_err()
                .to_string()
                .contains("timestamps must be finite")
        );
        assert!(
            timestamps("inf")
                .unwrap_err()
                .to_string()
                .contains("must be finite")
        );
        assert_eq!(timestamps("1e99").unwrap(), vec![1e99]);
    }
}
