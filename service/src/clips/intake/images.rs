//! Image frames: from a zip or tar archive (in name order), as separate uploads, or one image.
//!
//! Archives are untrusted: entry counts and declared sizes are checked before anything is
//! inflated, an entry that claims more than [`MAX_INFLATION`] times its compressed size is
//! refused as a decompression bomb, and reads stop at the declared size whatever the archive
//! claims. Nothing of an archive is ever written to disk, and an archive that names a path
//! outside itself (`../x.png`, `/etc/x.png`, `C:\x.png`) or holds a link (a tar's symbolic or
//! hard link, a zip's symbolic link) is refused whole: such an archive was made to escape, not to
//! carry frames. Image headers are read for sizes before pixels are decoded, and decoding is held
//! to the largest frame allowed.

use std::io::{Cursor, Read};

use bytes::Bytes;
use image::{ImageReader, RgbImage};

use super::kept::Keep;
use super::limits::{check_duration, check_frame_count, check_frame_size};
use super::media::{
    DEFAULT_IMAGE_FPS, Intake, IntakeOptions, Media, SourceInfo, TimedFrame, frame_step,
};
use super::sampling::select;
use super::sniff::MediaKind;
use crate::ServiceError;
use crate::config::Limits;
use crate::quoted;

/// Largest ratio of inflated to compressed size an archive entry may claim. Image files are
/// already compressed: real frames inflate by a few percent, bombs by thousands of times.
const MAX_INFLATION: u64 = 100;

/// Reads image frames and picks the context frames (blocking: image decoding is CPU work).
pub fn read(
    media: Media,
    kind: MediaKind,
    options: &IntakeOptions,
    limits: &Limits,
    keep: Keep,
) -> Result<Intake, ServiceError> {
    let files = match (kind, media) {
        (_, Media::Frames(frames)) => frames,
        (MediaKind::Zip, Media::File { data, .. }) => unzip(&data, limits)?,
        (MediaKind::Tar, Media::File { data, .. }) => untar(&data, limits)?,
        (MediaKind::Image, Media::File { data, .. }) => vec![data],
        (_, Media::File { .. }) => {
            return Err(ServiceError::UnsupportedMedia(
                "the upload is not a video, an image archive or an image".into(),
            ));
        }
    };
    if files.is_empty() {
        return Err(ServiceError::invalid(
            "the archive holds no PNG or JPEG frames",
        ));
    }
    check_frame_count(files.len(), limits)?;
    let times = frame_times(files.len(), options)?;
    check_duration(times.last().copied().unwrap_or(0.0), limits)?;

    // Every frame's header is checked (sizes agree, within limits) before any is decoded.
    let mut size = None;
    for (i, file) in files.iter().enumerate() {
        let (w, h) = dimensions(file).map_err(|e| {
            ServiceError::UnreadableMedia(format!("frame {i} is not a readable PNG or JPEG: {e}"))
        })?;
        check_frame_size(w, h, limits)?;
        match size {
            None => size = Some((w, h)),
            Some((w0, h0)) if (w0, h0) != (w, h) => {
                return Err(ServiceError::UnreadableMedia(format!(
                    "frames differ in size: frame 0 is {w0}x{h0}, frame {i} is {w}x{h}; \
                     every frame of a clip must have the same size"
                )));
            }
            Some(_) => {}
        }
    }
    let (width, height) = size.unwrap_or((0, 0));
    let chosen = select(&times, options, limits)?;
    let decoded = |i: usize| {
        decode(&files[i], limits)
            .map_err(|e| ServiceError::UnreadableMedia(format!("frame {i} cannot be decoded: {e}")))
    };
    let frames = chosen
        .iter()
        .map(|&i| {
            Ok(TimedFrame {
                source_index: i,
                time: times[i],
                image: decoded(i)?,
            })
        })
        .collect::<Result<Vec<_>, ServiceError>>()?;
    // Kept frames are decoded one at a time and shrunk at once (a context frame is not decoded
    // twice).
    let kept = keep
        .pick(&times, options, width, height)
        .into_iter()
        .map(|i| {
            let image = match chosen.iter().position(|&c| c == i) {
                Some(k) => keep.shrink(&frames[k].image),
                None => keep.shrink(&decoded(i)?),
            };
            Ok(TimedFrame {
                source_index: i,
                time: times[i],
                image,
            })
        })
        .collect::<Result<Vec<_>, ServiceError>>()?;
    // The rate the frames' times say: the stated fps, else the timestamps' own (one over their
    // median step), else the default for untimed frames.
    let fps = match (options.fps, &options.timestamps) {
        (Some(fps), _) => fps,
        (None, Some(_)) => frame_step(&times, 0.0).map_or(DEFAULT_IMAGE_FPS, |step| 1.0 / step),
        (None, None) => DEFAULT_IMAGE_FPS,
    };
    Ok(Intake {
        frames,
        kept,
        source: SourceInfo {
            kind: "images".into(),
            frames: files.len(),
            width,
            height,
            duration: times.last().copied().unwrap_or(0.0),
            fps,
            warnings: Vec::new(),
        },
        frame_step: frame_step(&times, fps),
    })
}

/// Times of `n` image frames: the explicit timestamps (shifted to start at 0) or `i / fps`.
fn frame_times(n: usize, options: &IntakeOptions) -> Result<Vec<f64>, ServiceError> {
    match &options.timestamps {
        Some(times) if times.len() != n => Err(ServiceError::invalid(format!(
            "{} timestamps for {n} frames: give one per frame",
            times.len()
        ))),
        Some(times) => Ok(times.iter().map(|t| t - times[0]).collect()),
        None => {
            let fps = options.fps.unwrap_or(DEFAULT_IMAGE_FPS);
            Ok((0..n).map(|i| i as f64 / fps).collect())
        }
    }
}

fn is_frame_name(name: &str) -> bool {
    let base = name.rsplit('/').next().unwrap_or(name);
    let lower = base.to_ascii_lowercase();
    !base.starts_with('.')
        && !name.starts_with("__MACOSX/")
        && [".png", ".jpg", ".jpeg"]
            .iter()
            .any(|ext| lower.ends_with(ext))
}

/// True when an archive entry's name stays inside the archive: relative, with no `..` component
/// (either slash separates), no drive and no NUL.
fn is_contained(name: &str) -> bool {
    let bytes = name.as_bytes();
    let drive = bytes.len() >= 2 && bytes[0].is_ascii_alphabetic() && bytes[1] == b':';
    !name.is_empty()
        && !name.starts_with(['/', '\\'])
        && !drive
        && !name.contains('\0')
        && !name.split(['/', '\\']).any(|part| part == "..")
}

fn escaping(kind: &str, name: &str) -> ServiceError {
    ServiceError::UnreadableMedia(format!(
        "{kind} entry {name_quoted} names a path outside the archive: refused",
        name_quoted = quoted(name)
    ))
}

fn link(kind: &str, name: &str) -> ServiceError {
    ServiceError::UnreadableMedia(format!(
        "{kind} entry {name_quoted} is a link: an archive of frames holds regular files only",
        name_quoted = quoted(name)
    ))
}

fn unzip(data: &[u8], limits: &Limits) -> Result<Vec<Bytes>, ServiceError> {
    let mut archive = zip::ZipArchive::new(Cursor::new(data)).map_err(|e| {
        ServiceError::UnreadableMedia(format!("the zip archive cannot be read: {e}"))
    })?;
    check_frame_count(archive.len(), limits)?;
    let mut entries = Vec::new();
    let mut declared = 0u64;
    for i in 0..archive.len() {
        let entry = archive.by_index_raw(i).map_err(|e| {
            ServiceError::UnreadableMedia(format!("zip entry {i} cannot be read: {e}"))
        })?;
        let name = entry
            .name()
            .map_err(|e| {
                ServiceError::UnreadableMedia(format!("zip entry {i} has a bad name: {e}"))
            })?
            .into_owned();
        if !is_contained(&name) {
            return Err(escaping("zip", &name));
        }
        if entry.is_symlink() {
            return Err(link("zip", &name));
        }
        if entry.is_dir() || !is_frame_name(&name) {
            continue;
        }
        let (size, packed) = (entry.size(), entry.compressed_size());
        if size > packed.max(1).saturating_mul(MAX_INFLATION) && size > (1 << 20) {
            return Err(ServiceError::TooLarge(format!(
                "zip entry {name} inflates {packed} bytes to {size}: refused as a decompression bomb"
            )));
        }
        declared = declared.saturating_add(size);
        entries.push((name, i, size));
    }
    if declared > limits.max_archive_bytes {
        return Err(ServiceError::TooLarge(format!(
            "the archive expands to {declared} bytes; at most {} are accepted (C4G_MAX_ARCHIVE_MIB)",
            limits.max_archive_bytes
        )));
    }
    entries.sort();
    entries
        .into_iter()
        .map(|(name, i, size)| {
            let entry = archive.by_index(i).map_err(|e| {
                ServiceError::UnreadableMedia(format!("zip entry {name} cannot be read: {e}"))
            })?;
            // The declared size bounds the read, whatever the stream inside claims.
            let mut bytes = Vec::with_capacity(size.min(1 << 26) as usize);
            entry
                .take(size)
                .read_to_end(&mut bytes)
                .map_err(|e| ServiceError::UnreadableMedia(format!("zip entry {name}: {e}")))?;
            Ok(Bytes::from(bytes))
        })
        .collect()
}

fn untar(data: &[u8], limits: &Limits) -> Result<Vec<Bytes>, ServiceError> {
    let mut archive = tar::Archive::new(Cursor::new(data));
    let entries = archive.entries().map_err(|e| {
        ServiceError::UnreadableMedia(format!("the tar archive cannot be read: {e}"))
    })?;
    let mut frames = Vec::new();
    for entry in entries {
        let mut entry = entry.map_err(|e| {
            ServiceError::UnreadableMedia(format!("a tar entry cannot be read: {e}"))
        })?;
        // The raw name: `path()` would refuse a `..` component before we could say why.
        let name = String::from_utf8_lossy(&entry.path_bytes()).into_owned();
        if !is_contained(&name) {
            return Err(escaping("tar", &name));
        }
        let kind = entry.header().entry_type();
        if kind.is_symlink() || kind.is_hard_link() {
            return Err(link("tar", &name));
        }
        if !kind.is_file() || !is_frame_name(&name) {
            continue;
        }
        check_frame_count(frames.len() + 1, limits)?;
        // A tar is not compressed: an entry's bytes are inside the (already limited) body.
        let mut bytes = Vec::new();
        entry
            .read_to_end(&mut bytes)
            .map_err(|e| ServiceError::UnreadableMedia(format!("tar entry {name}: {e}")))?;
        frames.push((name, Bytes::from(bytes)));
    }
    frames.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(frames.into_iter().map(|(_, b)| b).collect())
}

fn reader(bytes: &[u8]) -> std::io::Result<ImageReader<Cursor<&[u8]>>> {
    ImageReader::new(Cursor::new(bytes)).with_guessed_format()
}

fn dimensions(bytes: &[u8]) -> Result<(u32, u32), image::ImageError> {
    reader(bytes)?.into_dimensions()
}

/// Decodes a frame whole or not at all. PNG's decoder refuses a file cut short; JPEG's fills
/// the missing rows with grey and succeeds, so a JPEG is first held to its own end: the
/// end-of-image marker after its last scan (a thumbnail's markers come before the main
/// image's scans, and a scan's data never holds `FF D9`, since JPEG stuffs every `FF` in it).
fn decode(bytes: &[u8], limits: &Limits) -> Result<RgbImage, image::ImageError> {
    let mut reader = reader(bytes)?;
    if reader.format() == Some(image::ImageFormat::Jpeg) && !jpeg_is_whole(bytes) {
        return Err(image::ImageError::Decoding(
            image::error::DecodingError::new(
                image::error::ImageFormatHint::Exact(image::ImageFormat::Jpeg),
                "the JPEG is cut short (no end-of-image marker after its last scan): truncated or \
             corrupt",
            ),
        ));
    }
    let mut image_limits = image::Limits::default();
    image_limits.max_image_width = Some(limits.max_side);
    image_limits.max_image_height = Some(limits.max_side);
    image_limits.max_alloc = Some(u64::from(limits.max_side).pow(2) * 8);
    reader.limits(image_limits);
    Ok(reader.decode()?.to_rgb8())
}

/// Whether a JPEG's last scan is followed by its end-of-image marker (`FF DA` starts a scan,
/// `FF D9` ends the image).
fn jpeg_is_whole(bytes: &[u8]) -> bool {
    let last_scan = bytes.windows(2).rposition(|w| w == [0xFF, 0xDA]);
    last_scan.is_some_and(|at| bytes[at..].windows(2).any(|w| w == [0xFF, 0xD9]))
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use super::*;

    fn png(width: u32, height: u32) -> Vec<u8> {
        let mut bytes = Vec::new();
        RgbImage::from_pixel(width, height, image::Rgb([90, 120, 200]))
            .write_to(&mut Cursor::new(&mut bytes), image::ImageFormat::Png)
            .unwrap();
        bytes
    }

    /// A 1x1 PNG whose header says `width` x `height`: what a decompression bomb sends.
    fn png_header_only(width: u32, height: u32) -> Vec<u8> {
        let mut bytes = png(1, 1);
        // IHDR's width and height sit at bytes 16..24, its CRC at 29..33.
        bytes[16..20].copy_from_slice(&width.to_be_bytes());
        bytes[20..24].copy_from_slice(&height.to_be_bytes());
        let crc = crc32fast::hash(&bytes[12..29]);
        bytes[29..33].copy_from_slice(&crc.to_be_bytes());
        bytes
    }

    fn zip_of(entries: &[(&str, &[u8])]) -> Vec<u8> {
        let mut writer = zip::ZipWriter::new(Cursor::new(Vec::new()));
        let options = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Deflated);
        for (name, data) in entries {
            writer.start_file(*name, options).unwrap();
            writer.write_all(data).unwrap();
        }
        writer.finish().unwrap().into_inner()
    }

    /// A tar entry with a raw `name` (the tar crate's builder refuses `..`) and `kind`.
    fn tar_entry(out: &mut Vec<u8>, name: &[u8], kind: tar::EntryType, data: &[u8], link: &[u8]) {
        let mut header = tar::Header::new_ustar();
        header.as_old_mut().name[..name.len()].copy_from_slice(name);
        header.as_old_mut().linkname[..link.len()].copy_from_slice(link);
        header.set_entry_type(kind);
        header.set_size(data.len() as u64);
        header.set_mode(0o644);
        header.set_cksum();
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(data);
        out.resize(out.len().div_ceil(512) * 512, 0);
    }

    /// A tar entry: raw name, type, data, link target.
    type TarEntry<'a> = (&'a [u8], tar::EntryType, &'a [u8], &'a [u8]);

    fn tar_of(entries: &[TarEntry<'_>]) -> Vec<u8> {
        let mut out = Vec::new();
        for (name, kind, data, link) in entries {
            tar_entry(&mut out, name, *kind, data, link);
        }
        out.resize(out.len() + 1024, 0);
        out
    }

    fn refusal<T: std::fmt::Debug>(result: Result<T, ServiceError>) -> (String, ServiceError) {
        let e = result.unwrap_err();
        (e.to_string(), e)
    }

    fn jpeg(width: u32, height: u32) -> Vec<u8> {
        let mut bytes = Vec::new();
        RgbImage::from_fn(width, height, |x, y| {
            image::Rgb([(x * 6) as u8, (y * 8) as u8, ((x * y) % 251) as u8])
        })
        .write_to(&mut Cursor::new(&mut bytes), image::ImageFormat::Jpeg)
        .unwrap();
        bytes
    }

    #[test]
    fn a_frame_cut_short_is_refused_whatever_its_format() {
        let limits = Limits::default();
        // Large enough that most of either file is pixel data, after the headers.
        for (format, whole) in [("PNG", png(200, 150)), ("JPEG", jpeg(200, 150))] {
            assert!(decode(&whole, &limits).is_ok(), "{format}");
            // Cut after its header: the sizes still read, the pixels do not all arrive.
            let cut = &whole[..whole.len() * 2 / 3];
            assert!(dimensions(cut).is_ok(), "{format}");
            assert!(decode(cut, &limits).is_err(), "{format}");
        }
        let cut = jpeg(40, 30);
        let e = decode(&cut[..cut.len() - 2], &limits)
            .unwrap_err()
            .to_string();
        assert!(e.contains("cut short"), "{e}");
        // Bytes after the end-of-image marker are not a cut.
        let mut padded = jpeg(40, 30);
        padded.extend_from_slice(&[0; 64]);
        assert!(decode(&padded, &limits).is_ok());
    }

    #[test]
    fn the_source_rate_is_what_the_frames_times_say() {
        let frames = || Media::Frames((0..3).map(|_| Bytes::from(png(16, 16))).collect());
        let read_with = |options: IntakeOptions| {
            read(
                frames(),
                MediaKind::Image,
                &options,
                &Limits::default(),
                Keep::NONE,
            )
            .unwrap()
        };
        let timed = read_with(IntakeOptions {
            timestamps: Some(vec![0.0, 1.0, 2.0]),
            ..IntakeOptions::default()
        });
        assert_eq!(timed.source.fps, 1.0);
        assert_eq!(timed.frame_step, Some(1.0));
        let stated = read_with(IntakeOptions {
            fps: Some(25.0),
            ..IntakeOptions::default()
        });
        assert_eq!(stated.source.fps, 25.0);
        assert_eq!(
            read_with(IntakeOptions::default()).source.fps,
            DEFAULT_IMAGE_FPS
        );
    }

    #[test]
    fn names_that_leave_the_archive_are_told_apart_from_frames_in_folders() {
        for good in [
            "frame-000.png",
            "clip/frames/001.png",
            "./002.png",
            "a..b.png",
            "x\\y.png",
        ] {
            assert!(is_contained(good), "{good}");
        }
        for bad in [
            "../escape.png",
            "frames/../../escape.png",
            "frames\\..\\escape.png",
            "/etc/escape.png",
            "\\\\server\\share\\x.png",
            "C:\\escape.png",
            "c:escape.png",
            "frame\0.png",
            "",
        ] {
            assert!(!is_contained(bad), "{bad:?}");
        }
    }

    #[test]
    fn an_archive_that_names_a_path_outside_itself_is_refused_whole() {
        let frame = png(16, 16);
        let limits = Limits::default();
        let zip = zip_of(&[("000.png", &frame), ("../../escape.png", &frame)]);
        let (message, e) = refusal(unzip(&zip, &limits));
        assert!(matches!(e, ServiceError::UnreadableMedia(_)), "{e:?}");
        assert!(
            message.contains("\"../../escape.png\" names a path outside"),
            "{message}"
        );
        let zip = zip_of(&[("/tmp/escape.png", &frame)]);
        assert!(
            refusal(unzip(&zip, &limits))
                .0
                .contains("outside the archive")
        );

        let file = tar::EntryType::Regular;
        let tar = tar_of(&[
            (b"000.png", file, &frame, b""),
            (b"a/../../x.png", file, &frame, b""),
        ]);
        let (message, e) = refusal(untar(&tar, &limits));
        assert!(matches!(e, ServiceError::UnreadableMedia(_)), "{e:?}");
        assert!(
            message.contains("tar entry \"a/../../x.png\" names a path outside"),
            "{message}"
        );
        let tar = tar_of(&[(b"/etc/x.png", file, &frame, b"")]);
        assert!(
            refusal(untar(&tar, &limits))
                .0
                .contains("outside the archive")
        );
        // The same frames, contained, read.
        let tar = tar_of(&[
            (b"clip/000.png", file, &frame, b""),
            (b"clip/001.png", file, &frame, b""),
        ]);
        assert_eq!(untar(&tar, &limits).unwrap().len(), 2);
    }

    #[test]
    fn links_in_archives_are_refused_and_never_followed() {
        let frame = png(16, 16);
        let limits = Limits::default();
        let file = tar::EntryType::Regular;
        for kind in [tar::EntryType::Symlink, tar::EntryType::Link] {
            let tar = tar_of(&[
                (b"000.png", file, &frame, b""),
                (b"001.png", kind, b"", b"/etc/passwd"),
            ]);
            let (message, e) = refusal(untar(&tar, &limits));
            assert!(matches!(e, ServiceError::UnreadableMedia(_)), "{e:?}");
            assert!(
                message.contains("\"001.png\" is a link"),
                "{kind:?}: {message}"
            );
        }
        let mut writer = zip::ZipWriter::new(Cursor::new(Vec::new()));
        let options = zip::write::SimpleFileOptions::default();
        writer.start_file("000.png", options).unwrap();
        writer.write_all(&frame).unwrap();
        writer
            .add_symlink("001.png", "/etc/passwd", options)
            .unwrap();
        let zip = writer.finish().unwrap().into_inner();
        assert!(
            refusal(unzip(&zip, &limits))
                .0
                .contains("\"001.png\" is a link")
        );
    }

    #[test]
    fn a_zip_entry_is_refused_as_a_bomb_from_its_own_numbers_and_read_only_as_far_as_it_says() {
        let limits = Limits::default();
        let zeros = vec![0u8; 32 << 20];
        let bomb = zip_of(&[("000.png", &zeros)]);
        assert!(bomb.len() < 1 << 20);
        let (message, e) = refusal(unzip(&bomb, &limits));
        assert!(matches!(e, ServiceError::TooLarge(_)), "{e:?}");
        assert!(message.contains("decompression bomb"), "{message}");

        // The same entry, its declared size rewritten to 1000 bytes in both headers: it passes the
        // ratio check, and exactly 1000 bytes are inflated, whatever the stream holds.
        let mut liar = bomb.clone();
        let local = 22; // a local header's uncompressed size
        liar[local..local + 4].copy_from_slice(&1000u32.to_le_bytes());
        let central = liar.windows(4).position(|w| w == b"PK\x01\x02").unwrap();
        liar[central + 24..central + 28].copy_from_slice(&1000u32.to_le_bytes());
        let frames = unzip(&liar, &limits).unwrap();
        assert_eq!(frames.len(), 1);
        assert_eq!(frames[0].len(), 1000);

        // Declared sizes add up against C4G_MAX_ARCHIVE_MIB before anything is inflated.
        let small = Limits {
            max_archive_bytes: 1 << 20,
            ..Limits::default()
        };
        let half = vec![7u8; 600 << 10];
        let two = zip_of(&[("000.png", &half), ("001.png", &half)]);
        let (message, e) = refusal(unzip(&two, &small));
        assert!(matches!(e, ServiceError::TooLarge(_)), "{e:?}");
        assert!(message.contains("C4G_MAX_ARCHIVE_MIB"), "{message}");
    }

    #[test]
    fn a_png_header_that_claims_gigapixels_is_refused_before_any_pixel_is_decoded() {
        let limits = Limits::default();
        let bomb = png_header_only(100_000, 100_000);
        assert_eq!(dimensions(&bomb).unwrap(), (100_000, 100_000));
        let (message, e) = refusal(read(
            Media::Frames(vec![Bytes::from(bomb)]),
            MediaKind::Frames,
            &IntakeOptions::default(),
            &limits,
            Keep::NONE,
        ));
        assert!(matches!(e, ServiceError::TooLarge(_)), "{e:?}");
        assert!(message.contains("100000x100000"), "{message}");
        // Decoding itself is held to the largest side too, whatever a header said before.
        let small = Limits {
            max_side: 32,
            ..Limits::default()
        };
        assert!(decode(&png(64, 64), &small).is_err());
        assert_eq!(decode(&png(32, 32), &small).unwrap().dimensions(), (32, 32));
    }
}
