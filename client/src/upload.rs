//! Uploading a clip (`POST /v1/clips`): a video or an image archive as the raw body, or image
//! frames as a multipart form.
//!
//! Bodies are streamed in chunks, never read whole into memory, and every chunk handed to the
//! connection advances the caller's progress callback: a progress bar moves during the upload,
//! then waits at 100% while the server encodes (the answer comes once the clip is ready).

use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use bytes::Bytes;
use futures_util::{Stream, StreamExt};
use reqwest::header::{CONTENT_LENGTH, CONTENT_TYPE};
use reqwest::multipart::{Form, Part};
use reqwest::{Body, StatusCode, Url};
use tokio::io::AsyncReadExt;

use crate::client::json;
use crate::{Client, Clip, Error};

/// Bytes per chunk of an upload body: small enough that progress moves smoothly, large enough
/// that per-chunk overhead does not matter.
const CHUNK: usize = 256 * 1024;

/// How the server turns an upload into context frames. Every field is optional; the server's
/// defaults apply to what is left out.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct UploadOptions {
    /// Frame rate of image frames without timestamps (server default 10); ignored for videos.
    pub fps: Option<f64>,
    /// Explicit times of image frames, seconds, strictly increasing (empty: none).
    pub timestamps: Vec<f64>,
    /// At most this many context frames, spread evenly.
    pub max_frames: Option<u32>,
    /// Take every `stride`-th frame of the window instead of spreading evenly.
    pub stride: Option<u32>,
    /// Only frames at or after this time (seconds).
    pub start: Option<f64>,
    /// Only frames at or before this time (seconds).
    pub end: Option<f64>,
    /// One camera per frame, stored with the clip in the model's frame (`docs/api.md`, "Given
    /// cameras"). With cameras a file goes as a multipart `file` part: camera files are too
    /// large for a query string.
    pub cameras: Option<UploadCameras>,
}

/// Per-frame cameras in one of the forms the server reads, as file contents.
#[derive(Debug, Clone, PartialEq)]
pub enum UploadCameras {
    /// A JSON list, one object per frame (`world_to_camera` or `camera_to_world`, `intrinsics`).
    Json(String),
    /// COLMAP's text model, its images matched to frames by name order or by `names`.
    Colmap {
        /// `cameras.txt`.
        cameras: String,
        /// `images.txt`.
        images: String,
        /// Image names in frame order (empty: sorted by name).
        names: Vec<String>,
    },
    /// nerfstudio's `transforms.json`, its frames matched by `file_path` order or by `names`.
    Transforms {
        /// The file.
        json: String,
        /// File paths in frame order (empty: sorted).
        names: Vec<String>,
    },
}

impl UploadCameras {
    /// The multipart fields that carry them.
    fn pairs(&self) -> Vec<(&'static str, String)> {
        let names =
            |names: &[String]| (!names.is_empty()).then(|| ("camera_names", names.join("\n")));
        match self {
            Self::Json(json) => vec![("cameras", json.clone())],
            Self::Colmap {
                cameras,
                images,
                names: n,
            } => [
                Some(("colmap_cameras", cameras.clone())),
                Some(("colmap_images", images.clone())),
                names(n),
            ]
            .into_iter()
            .flatten()
            .collect(),
            Self::Transforms { json, names: n } => [Some(("transforms", json.clone())), names(n)]
                .into_iter()
                .flatten()
                .collect(),
        }
    }
}

impl UploadOptions {
    /// The options as name-value pairs, as the query string and the multipart fields carry them.
    fn pairs(&self) -> Vec<(&'static str, String)> {
        let mut pairs = Vec::new();
        if let Some(fps) = self.fps {
            pairs.push(("fps", fps.to_string()));
        }
        if !self.timestamps.is_empty() {
            let times: Vec<String> = self.timestamps.iter().map(f64::to_string).collect();
            pairs.push(("timestamps", times.join(",")));
        }
        if let Some(max_frames) = self.max_frames {
            pairs.push(("max_frames", max_frames.to_string()));
        }
        if let Some(stride) = self.stride {
            pairs.push(("stride", stride.to_string()));
        }
        if let Some(start) = self.start {
            pairs.push(("start", start.to_string()));
        }
        if let Some(end) = self.end {
            pairs.push(("end", end.to_string()));
        }
        if let Some(cameras) = &self.cameras {
            pairs.extend(cameras.pairs());
        }
        pairs
    }
}

/// What to upload.
#[derive(Debug, Clone)]
pub enum UploadSource {
    /// A file or a directory. A video or archive file is sent as the body, with the content type
    /// its extension names ([`content_type_for`]); a directory's PNG and JPEG images (or a single
    /// image file) are sent as `frame` parts of a multipart form, in name order.
    Path(PathBuf),
    /// Bytes already in memory, sent as the body.
    Bytes {
        /// The media.
        data: Bytes,
        /// Its content type (`video/mp4`, `application/zip`, or `application/octet-stream` to
        /// let the server sniff it).
        content_type: String,
    },
}

impl From<&Path> for UploadSource {
    fn from(path: &Path) -> Self {
        UploadSource::Path(path.to_owned())
    }
}

impl From<PathBuf> for UploadSource {
    fn from(path: PathBuf) -> Self {
        UploadSource::Path(path)
    }
}

/// The content type `POST /v1/clips` expects for a file, from its extension (case-insensitive):
/// videos `video/*`, `.zip` and `.tar` archives, and `application/octet-stream` (which the server
/// sniffs) for anything else.
pub fn content_type_for(path: &Path) -> &'static str {
    let extension = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match extension.as_deref() {
        Some("mp4" | "m4v") => "video/mp4",
        Some("mov") => "video/quicktime",
        Some("mkv") => "video/x-matroska",
        Some("webm") => "video/webm",
        Some("avi") => "video/x-msvideo",
        Some("zip") => "application/zip",
        Some("tar") => "application/x-tar",
        _ => "application/octet-stream",
    }
}

/// The content type of an image frame, or `None` when the file is not a PNG or JPEG by name.
fn image_type_for(path: &Path) -> Option<&'static str> {
    let extension = path.extension()?.to_str()?.to_ascii_lowercase();
    match extension.as_str() {
        "png" => Some("image/png"),
        "jpg" | "jpeg" => Some("image/jpeg"),
        _ => None,
    }
}

impl Client {
    /// Uploads a clip and waits until the server has encoded it.
    ///
    /// `progress(sent, total)` is called as body bytes go out (first with `sent = 0`); it runs on
    /// the connection's task, so it should be quick (a progress bar's `set_position`).
    pub async fn upload(
        &self,
        source: impl Into<UploadSource>,
        options: &UploadOptions,
        progress: impl Fn(u64, u64) + Send + Sync + 'static,
    ) -> Result<Clip, Error> {
        let progress: ProgressFn = Arc::new(progress);
        let mut url = self.url(&["v1", "clips"]);
        let request = match source.into() {
            UploadSource::Bytes { data, content_type } if options.cameras.is_some() => {
                let total = data.len() as u64;
                let body = Body::wrap_stream(bytes_chunks(data, Progress::new(total, progress)));
                let part = Part::stream_with_length(body, total).mime_str(&content_type)?;
                let form = options
                    .pairs()
                    .into_iter()
                    .fold(Form::new(), |form, (name, value)| form.text(name, value));
                self.http().post(url).multipart(form.part("file", part))
            }
            UploadSource::Bytes { data, content_type } => {
                add_query(&mut url, options);
                let total = data.len() as u64;
                let body = Body::wrap_stream(bytes_chunks(data, Progress::new(total, progress)));
                self.http()
                    .post(url)
                    .header(CONTENT_TYPE, content_type)
                    .header(CONTENT_LENGTH, total)
                    .body(body)
            }
            UploadSource::Path(path) => {
                let metadata = tokio::fs::metadata(&path).await.map_err(io_error(&path))?;
                if metadata.is_dir() {
                    let frames = image_files(&path).await?;
                    let form = frames_form(&frames, options, progress).await?;
                    self.http().post(url).multipart(form)
                } else if image_type_for(&path).is_some() {
                    let frames = [(path, metadata.len())];
                    let form = frames_form(&frames, options, progress).await?;
                    self.http().post(url).multipart(form)
                } else if options.cameras.is_some() {
                    let form = file_form(&path, metadata.len(), options, progress).await?;
                    self.http().post(url).multipart(form)
                } else {
                    add_query(&mut url, options);
                    let total = metadata.len();
                    let file = tokio::fs::File::open(&path)
                        .await
                        .map_err(io_error(&path))?;
                    let progress = Progress::new(total, progress);
                    self.http()
                        .post(url)
                        .header(CONTENT_TYPE, content_type_for(&path))
                        .header(CONTENT_LENGTH, total)
                        .body(Body::wrap_stream(file_chunks(file, progress)))
                }
            }
        };
        let response = self.send(request).await?;
        // 201 Created or 200 OK (stored before); the body says so too, but only the status is
        // promised by every version of the API.
        let created = response.status() == StatusCode::CREATED;
        let mut clip: Clip = json(response).await?;
        clip.created.get_or_insert(created);
        Ok(clip)
    }
}

fn add_query(url: &mut Url, options: &UploadOptions) {
    let pairs = options.pairs();
    if !pairs.is_empty() {
        url.query_pairs_mut().extend_pairs(pairs);
    }
}

/// The PNG and JPEG files of a directory, in name order, with their sizes.
async fn image_files(dir: &Path) -> Result<Vec<(PathBuf, u64)>, Error> {
    let mut entries = tokio::fs::read_dir(dir).await.map_err(io_error(dir))?;
    let mut frames = Vec::new();
    while let Some(entry) = entries.next_entry().await.map_err(io_error(dir))? {
        let path = entry.path();
        if image_type_for(&path).is_none() {
            continue;
        }
        let metadata = tokio::fs::metadata(&path).await.map_err(io_error(&path))?;
        if metadata.is_file() {
            frames.push((path, metadata.len()));
        }
    }
    if frames.is_empty() {
        return Err(Error::InvalidInput(format!(
            "{} holds no .png or .jpg images to upload as frames",
            dir.display()
        )));
    }
    frames.sort_by(|a, b| a.0.file_name().cmp(&b.0.file_name()));
    Ok(frames)
}

/// A multipart form: the options as text fields (first, so a streaming parser has them before
/// the frames), then one `frame` part per image, each streamed from its file.
async fn frames_form(
    frames: &[(PathBuf, u64)],
    options: &UploadOptions,
    progress: ProgressFn,
) -> Result<Form, Error> {
    let total = frames.iter().map(|(_, len)| len).sum();
    let progress = Progress::new(total, progress);
    let mut form = Form::new();
    for (name, value) in options.pairs() {
        form = form.text(name, value);
    }
    for (path, len) in frames {
        let file = tokio::fs::File::open(path).await.map_err(io_error(path))?;
        let body = Body::wrap_stream(file_chunks(file, progress.clone()));
        let file_name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let part = Part::stream_with_length(body, *len)
            .file_name(file_name)
            .mime_str(image_type_for(path).unwrap_or("application/octet-stream"))?;
        form = form.part("frame", part);
    }
    Ok(form)
}

/// A multipart form of the options as text fields, then the file as the `file` part.
async fn file_form(
    path: &Path,
    len: u64,
    options: &UploadOptions,
    progress: ProgressFn,
) -> Result<Form, Error> {
    let mut form = Form::new();
    for (name, value) in options.pairs() {
        form = form.text(name, value);
    }
    let file = tokio::fs::File::open(path).await.map_err(io_error(path))?;
    let body = Body::wrap_stream(file_chunks(file, Progress::new(len, progress)));
    let part = Part::stream_with_length(body, len).mime_str(content_type_for(path))?;
    Ok(form.part("file", part))
}

type ProgressFn = Arc<dyn Fn(u64, u64) + Send + Sync>;

/// Bytes sent so far of one upload, shared by every stream of its body.
#[derive(Clone)]
struct Progress {
    sent: Arc<AtomicU64>,
    total: u64,
    callback: ProgressFn,
}

impl Progress {
    fn new(total: u64, callback: ProgressFn) -> Self {
        callback(0, total);
        Self {
            sent: Arc::new(AtomicU64::new(0)),
            total,
            callback,
        }
    }

    fn advance(&self, bytes: usize) {
        let sent = self.sent.fetch_add(bytes as u64, Ordering::Relaxed) + bytes as u64;
        (self.callback)(sent.min(self.total), self.total);
    }
}

/// A file as a stream of chunks, reporting each one.
fn file_chunks(
    file: tokio::fs::File,
    progress: Progress,
) -> impl Stream<Item = io::Result<Bytes>> + Send + 'static {
    futures_util::stream::try_unfold((file, progress), |(mut file, progress)| async move {
        let mut buffer = vec![0; CHUNK];
        let n = file.read(&mut buffer).await?;
        if n == 0 {
            return Ok(None);
        }
        buffer.truncate(n);
        progress.advance(n);
        Ok(Some((Bytes::from(buffer), (file, progress))))
    })
}

/// Bytes in memory as a stream of chunks (slices of the one buffer), reporting each one.
fn bytes_chunks(
    data: Bytes,
    progress: Progress,
) -> impl Stream<Item = io::Result<Bytes>> + Send + 'static {
    let chunks: Vec<Bytes> = (0..data.len())
        .step_by(CHUNK)
        .map(|start| data.slice(start..(start + CHUNK).min(data.len())))
        .collect();
    futures_util::stream::iter(chunks).map(move |chunk| {
        progress.advance(chunk.len());
        Ok(chunk)
    })
}

fn io_error(path: &Path) -> impl FnOnce(io::Error) -> Error + '_ {
    move |source| Error::Io {
        path: path.to_owned(),
        source,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use futures_util::TryStreamExt;

    use super::*;

    #[test]
    fn options_become_the_api_names_and_comma_separated_timestamps() {
        let options = UploadOptions {
            fps: Some(24.0),
            timestamps: vec![0.0, 0.5, 1.25],
            max_frames: Some(8),
            stride: None,
            start: Some(0.5),
            end: Some(2.0),
            cameras: Some(UploadCameras::Colmap {
                cameras: "c".into(),
                images: "i".into(),
                names: vec!["b.png".into(), "a.png".into()],
            }),
        };
        assert_eq!(
            options.pairs(),
            [
                ("fps", "24".to_owned()),
                ("timestamps", "0,0.5,1.25".to_owned()),
                ("max_frames", "8".to_owned()),
                ("start", "0.5".to_owned()),
                ("end", "2".to_owned()),
                ("colmap_cameras", "c".to_owned()),
                ("colmap_images", "i".to_owned()),
                ("camera_names", "b.png\na.png".to_owned()),
            ]
        );
        assert!(UploadOptions::default().pairs().is_empty());
    }

    #[tokio::test]
    async fn chunks_report_progress_up_to_the_total() {
        let seen = Arc::new(std::sync::Mutex::new(Vec::new()));
        let log = seen.clone();
        let progress = Progress::new(
            (CHUNK + 10) as u64,
            Arc::new(move |sent, total| log.lock().unwrap().push((sent, total))),
        );
        let data = Bytes::from(vec![7u8; CHUNK + 10]);
        let chunks: Vec<Bytes> = bytes_chunks(data, progress).try_collect().await.unwrap();
        assert_eq!(
            chunks.iter().map(Bytes::len).collect::<Vec<_>>(),
            [CHUNK, 10]
        );
        let total = (CHUNK + 10) as u64;
        assert_eq!(
            *seen.lock().unwrap(),
            [(0, total), (CHUNK as u64, total), (total, total)]
        );
    }

    #[tokio::test]
    async fn a_directory_uploads_its_images_in_name_order() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["b.png", "a.JPG", "c.txt", "a0.jpeg"] {
            std::fs::write(dir.path().join(name), b"x").unwrap();
        }
        let frames = image_files(dir.path()).await.unwrap();
        let names: Vec<_> = frames
            .iter()
            .map(|(p, _)| p.file_name().unwrap().to_str().unwrap().to_owned())
            .collect();
        assert_eq!(names, ["a.JPG", "a0.jpeg", "b.png"]);

        let empty = tempfile::tempdir().unwrap();
        assert!(matches!(
            image_files(empty.path()).await,
            Err(Error::InvalidInput(_))
        ));
    }
}
