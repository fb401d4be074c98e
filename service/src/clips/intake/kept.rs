//! Source frames kept for fits: a fit supervises a clip's scene with its own frames, many more
//! than the context frames the model encodes. They come out of the same reading of the upload as
//! the context frames (the video's one decoding pass, the archive's one read), spread evenly over
//! the window (every frame of a shorter clip), and are kept small: at most `count` of them, at
//! most `side` pixels on the long side. A kept frame is held at source size only until it is
//! shrunk, which is as it is decoded (the context frames alone are held at source size together);
//! their count is bounded by [`HELD_BYTES`] of shrunk frames. On disk they cost a PNG each (the
//! dog clip's at 256×144, measured once with `du`: 73 KB, 21 MB for its 289).

use image::{DynamicImage, RgbImage};

use super::media::IntakeOptions;
use super::sampling::window;

/// Most bytes of shrunk frames kept at once (2,427 frames at 256×144).
pub const HELD_BYTES: u64 = 256 << 20;

/// How many source frames to keep, and how small.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Keep {
    /// At most this many (0: none).
    pub count: usize,
    /// Long side, pixels.
    pub side: u32,
}

impl Keep {
    /// Keeps nothing.
    pub const NONE: Keep = Keep { count: 0, side: 0 };

    /// Indices into `times` of the frames to keep from a source of `width` × `height` frames.
    pub fn pick(
        &self,
        times: &[f64],
        options: &IntakeOptions,
        width: u32,
        height: u32,
    ) -> Vec<usize> {
        let (w, h) = c4g_fit::working_size(width, height, self.side.max(1));
        let frame_bytes = u64::from(w) * u64::from(h) * 3;
        let held = usize::try_from(HELD_BYTES / frame_bytes.max(1)).unwrap_or(usize::MAX);
        let count = self.count.min(held);
        if count == 0 || self.side == 0 {
            return Vec::new();
        }
        let frames = window(times, options);
        spread(&frames, count)
    }

    /// `image` shrunk (never enlarged) to at most `side` on the long side, by area averaging
    /// (`thumbnail`: what a shrink wants, and several times cheaper than a filtered resize, which
    /// matters for an upload that keeps dozens of frames). Through `DynamicImage`, whose methods
    /// are compiled in the `image` crate (optimised even in debug builds, see the workspace's
    /// `Cargo.toml`); the generic `imageops::thumbnail` compiles into this crate and ran at 87 ms
    /// a 720p frame in a debug server, enough to make an upload of a real video outlast a client.
    pub fn shrink(&self, image: &RgbImage) -> RgbImage {
        let (w, h) = c4g_fit::working_size(image.width(), image.height(), self.side);
        if (image.width(), image.height()) == (w, h) {
            return image.clone();
        }
        DynamicImage::ImageRgb8(image.clone())
            .thumbnail_exact(w, h)
            .into_rgb8()
    }
}

/// `k` of `items` spread evenly, both ends included (all of them when `k ≥ len`).
fn spread(items: &[usize], k: usize) -> Vec<usize> {
    let n = items.len();
    if k >= n || n <= 1 {
        return items.to_vec();
    }
    if k <= 1 {
        return items[..1].to_vec();
    }
    let mut picked: Vec<usize> = (0..k)
        .map(|i| items[(i * (n - 1) + (k - 1) / 2) / (k - 1)])
        .collect();
    picked.dedup();
    picked
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_shrink_to_the_long_side_keeping_the_aspect_and_never_grow() {
        let keep = Keep {
            count: 1,
            side: 256,
        };
        let size = |w, h| {
            let small = keep.shrink(&RgbImage::new(w, h));
            (small.width(), small.height())
        };
        assert_eq!(size(1920, 1080), (256, 144));
        assert_eq!(size(1080, 1920), (144, 256));
        assert_eq!(size(100, 50), (100, 50));
        assert_eq!(size(5000, 1), (256, 1));
    }

    #[test]
    fn a_shrink_averages_areas() {
        // Columns alternate black and white: each kept pixel averages a pair, so mid grey.
        let stripes = RgbImage::from_fn(512, 8, |x, _| image::Rgb([(x % 2 * 255) as u8; 3]));
        let keep = Keep {
            count: 1,
            side: 256,
        };
        let small = keep.shrink(&stripes);
        assert_eq!((small.width(), small.height()), (256, 4));
        assert!(
            small
                .pixels()
                .all(|p| p.0.iter().all(|&v| v.abs_diff(128) <= 1))
        );
    }

    #[test]
    fn kept_frames_spread_over_the_window_within_the_held_bytes() {
        let times: Vec<f64> = (0..100).map(|i| f64::from(i) * 0.1).collect();
        let keep = Keep { count: 5, side: 64 };
        let all = IntakeOptions::default();
        assert_eq!(keep.pick(&times, &all, 64, 64), vec![0, 25, 50, 74, 99]);
        let window = IntakeOptions {
            start: Some(1.0),
            end: Some(2.0),
            ..IntakeOptions::default()
        };
        let picked = keep.pick(&times, &window, 64, 64);
        assert!(picked.iter().all(|&i| (10..=20).contains(&i)), "{picked:?}");
        // The bound counts frames as kept (shrunk): 48 4K frames shrunk to 64 px fit …
        let many = Keep {
            count: 48,
            side: 64,
        };
        assert_eq!(many.pick(&times, &all, 4096, 2160).len(), 48);
        // … and 256 MiB holds 10 of them kept at 4K.
        let large = Keep {
            count: 48,
            side: 4096,
        };
        assert_eq!(large.pick(&times, &all, 4096, 2160).len(), 10);
        assert!(Keep::NONE.pick(&times, &all, 64, 64).is_empty());
    }
}
