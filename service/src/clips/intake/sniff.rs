//! What kind of media some bytes are, from their first bytes (clients' content types and file
//! names are hints at best).

use serde::{Deserialize, Serialize};

/// The kinds of upload the service reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MediaKind {
    /// A container with a known video signature (MP4/MOV, Matroska/WebM, AVI, MPEG-TS/PS, ...),
    /// or a GIF (animated or not: FFmpeg reads its frames and their delays).
    Video,
    /// A zip archive of image frames.
    Zip,
    /// A tar archive of image frames.
    Tar,
    /// A single image: a clip of one frame.
    Image,
    /// Image frames sent one by one (multipart).
    Frames,
    /// No known signature: FFmpeg gets to try, and a failure means "not media we read".
    Unknown,
}

/// The kind of `data`, from its signature.
pub fn sniff(data: &[u8]) -> MediaKind {
    let at = |offset: usize, magic: &[u8]| data.get(offset..offset + magic.len()) == Some(magic);
    if at(0, b"PK\x03\x04") || at(0, b"PK\x05\x06") {
        MediaKind::Zip
    } else if at(257, b"ustar") {
        MediaKind::Tar
    } else if at(0, b"GIF87a") || at(0, b"GIF89a") {
        // Before the image check: a GIF is a clip of frames with their own delays, which FFmpeg
        // reads (the image decoder here reads PNG and JPEG only, and one frame of each).
        MediaKind::Video
    } else if image::guess_format(data).is_ok() {
        MediaKind::Image
    } else if is_video(data) {
        MediaKind::Video
    } else {
        MediaKind::Unknown
    }
}

fn is_video(data: &[u8]) -> bool {
    let at = |offset: usize, magic: &[u8]| data.get(offset..offset + magic.len()) == Some(magic);
    // ISO BMFF (MP4, MOV, 3GP): a box size, then a top-level box type.
    let bmff = [b"ftyp", b"moov", b"mdat", b"free", b"wide", b"skip"]
        .iter()
        .any(|b| at(4, *b));
    let matroska = at(0, &[0x1a, 0x45, 0xdf, 0xa3]);
    let avi = at(0, b"RIFF") && at(8, b"AVI ");
    let transport_stream = data.len() > 188 && data[0] == 0x47 && data[188] == 0x47;
    let program_stream = at(0, &[0, 0, 1, 0xba]);
    let annex_b = at(0, &[0, 0, 0, 1]) || at(0, &[0, 0, 1]);
    bmff || matroska
        || avi
        || transport_stream
        || program_stream
        || annex_b
        || at(0, b"OggS")
        || at(0, b"FLV")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signatures_decide_the_kind() {
        assert_eq!(sniff(b"PK\x03\x04rest"), MediaKind::Zip);
        let mut tar = vec![0u8; 512];
        tar[257..262].copy_from_slice(b"ustar");
        assert_eq!(sniff(&tar), MediaKind::Tar);
        assert_eq!(sniff(b"\x00\x00\x00\x20ftypisom"), MediaKind::Video);
        assert_eq!(sniff(b"\x89PNG\r\n\x1a\n...."), MediaKind::Image);
        assert_eq!(sniff(b"GIF89a\x40\x00\x30\x00"), MediaKind::Video);
        assert_eq!(sniff(b"GIF87a\x40\x00\x30\x00"), MediaKind::Video);
        assert_eq!(sniff(b"hello, this is text"), MediaKind::Unknown);
        assert_eq!(sniff(b""), MediaKind::Unknown);
    }
}
