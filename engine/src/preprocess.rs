//! Frame preprocessing: an 8-bit RGB frame becomes the encoder's `[3, H, W]` input.
//!
//! The reference pipeline, which the weights were trained with, and therefore ours:
//! 1. centre-crop to a square of the short side S, `left = (W - S) / 2`, `top = (H - S) / 2`
//!    (integer division; a 960x540 frame keeps columns 210..750);
//! 2. Lanczos-3 resize of the 8-bit crop to the package's input size, as Pillow's
//!    `Image.resize(..., LANCZOS)` does it: fixed-point convolution with the horizontal pass first
//!    and an 8-bit image between the passes. `fast_image_resize` implements Pillow's convolution;
//!    we run its two passes as separate resizes so that their order (and the rounding between
//!    them) matches Pillow's. The remaining difference to Pillow is bounded by a test against
//!    the reference's own output (`preprocess.npz`);
//! 3. RGB / 255 in f32, mapped linearly so that 0 and 1 land on the package's `value_range`
//!    (for `[-1, 1]` this is `(x - 0.5) / 0.5`, bit for bit), laid out channel-first.

use fast_image_resize::images::Image;
use fast_image_resize::{FilterType, PixelType, ResizeAlg, ResizeOptions, Resizer};
use image::RgbImage;

use crate::package::InputSpec;
use crate::{EngineError, Result};

/// A crop rectangle in pixels, Pillow style: `left..right` columns, `top..bottom` rows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct CropBox {
    /// First column kept.
    pub left: u32,
    /// First row kept.
    pub top: u32,
    /// One past the last column kept.
    pub right: u32,
    /// One past the last row kept.
    pub bottom: u32,
}

impl CropBox {
    /// Width of the box.
    pub fn width(&self) -> u32 {
        self.right - self.left
    }

    /// Height of the box.
    pub fn height(&self) -> u32 {
        self.bottom - self.top
    }
}

/// The centred square of side `min(width, height)`.
pub fn center_square_crop(width: u32, height: u32) -> CropBox {
    let side = width.min(height);
    let left = (width - side) / 2;
    let top = (height - side) / 2;
    CropBox {
        left,
        top,
        right: left + side,
        bottom: top + side,
    }
}

/// Decodes a JPEG or PNG file's bytes into an 8-bit RGB frame.
pub fn decode_frame(bytes: &[u8]) -> Result<RgbImage> {
    image::load_from_memory(bytes)
        .map(|img| img.to_rgb8())
        .map_err(|e| EngineError::Image(format!("cannot decode frame: {e}")))
}

/// Crops the centred square of `frame` and Lanczos-resizes it to `width` × `height`, on 8-bit data.
pub fn crop_and_resize(frame: &RgbImage, width: u32, height: u32) -> Result<RgbImage> {
    if frame.width() == 0 || frame.height() == 0 {
        return Err(EngineError::Image(format!(
            "frame is empty ({}x{})",
            frame.width(),
            frame.height()
        )));
    }
    if width == 0 || height == 0 {
        return Err(EngineError::Image(format!(
            "cannot resize to an empty {width}x{height} image"
        )));
    }
    let b = center_square_crop(frame.width(), frame.height());
    let crop = image::imageops::crop_imm(frame, b.left, b.top, b.width(), b.height()).to_image();
    let src = u8x3_image(crop.width(), crop.height(), crop.into_raw())?;
    // Pillow resamples horizontally first and rounds to 8 bits in between; a resize that changes
    // only one axis runs only that axis' pass, so two resizes reproduce Pillow's order.
    let wide = resize_lanczos(&src, width, src.height())?;
    let out = resize_lanczos(&wide, width, height)?;
    RgbImage::from_raw(width, height, out.into_vec())
        .ok_or_else(|| EngineError::Image("resized buffer has the wrong size".to_owned()))
}

/// RGB / 255 mapped onto `value_range`, channel-first: `[3, H, W]` row-major.
pub fn to_model_input(frame: &RgbImage, value_range: [f32; 2]) -> Vec<f32> {
    let [low, high] = value_range;
    let scale = high - low;
    let plane = frame.width() as usize * frame.height() as usize;
    let mut out = vec![0.0f32; 3 * plane];
    for (i, pixel) in frame.pixels().enumerate() {
        for (c, &v) in pixel.0.iter().enumerate() {
            out[c * plane + i] = low + (f32::from(v) / 255.0) * scale;
        }
    }
    out
}

/// The whole reference preprocessing for a package's input: crop, resize, map to values.
pub fn preprocess(frame: &RgbImage, input: &InputSpec) -> Result<Vec<f32>> {
    let resized = crop_and_resize(frame, input.width, input.height)?;
    Ok(to_model_input(&resized, input.value_range))
}

fn u8x3_image(width: u32, height: u32, pixels: Vec<u8>) -> Result<Image<'static>> {
    Image::from_vec_u8(width, height, pixels, PixelType::U8x3)
        .map_err(|e| EngineError::Image(format!("cannot wrap frame for resizing: {e}")))
}

fn resize_lanczos(src: &Image<'_>, width: u32, height: u32) -> Result<Image<'static>> {
    let mut dst = Image::new(width, height, PixelType::U8x3);
    let options = ResizeOptions::new().resize_alg(ResizeAlg::Convolution(FilterType::Lanczos3));
    Resizer::new()
        .resize(src, &mut dst, &options)
        .map_err(|e| EngineError::Image(format!("resize failed: {e}")))?;
    Ok(dst)
}

#[cfg(test)]
mod tests {
    use image::Rgb;

    use super::*;

    #[test]
    fn crop_box_of_a_landscape_frame_is_centred() {
        assert_eq!(
            center_square_crop(960, 540),
            CropBox {
                left: 210,
                top: 0,
                right: 750,
                bottom: 540
            }
        );
    }

    #[test]
    fn crop_box_rounds_odd_margins_down() {
        assert_eq!(
            center_square_crop(5, 8),
            CropBox {
                left: 0,
                top: 1,
                right: 5,
                bottom: 6
            }
        );
        assert_eq!(
            center_square_crop(7, 7),
            CropBox {
                left: 0,
                top: 0,
                right: 7,
                bottom: 7
            }
        );
    }

    #[test]
    fn values_map_to_the_reference_range_bit_for_bit() {
        let frame = RgbImage::from_fn(2, 1, |x, _| {
            if x == 0 {
                Rgb([0, 128, 255])
            } else {
                Rgb([1, 2, 3])
            }
        });
        let values = to_model_input(&frame, [-1.0, 1.0]);
        let expect = |v: u8| (f32::from(v) / 255.0 - 0.5) / 0.5;
        assert_eq!(
            values,
            vec![
                expect(0),
                expect(1),
                expect(128),
                expect(2),
                expect(255),
                expect(3)
            ]
        );
        assert_eq!(values[0], -1.0);
        assert_eq!(values[4], 1.0);
        // Every 8-bit value, not just a few.
        for v in 0..=255u8 {
            let frame = RgbImage::from_pixel(1, 1, Rgb([v, v, v]));
            assert_eq!(
                to_model_input(&frame, [-1.0, 1.0])[0].to_bits(),
                expect(v).to_bits()
            );
            assert_eq!(to_model_input(&frame, [0.0, 1.0])[0], f32::from(v) / 255.0);
        }
    }

    #[test]
    fn a_constant_frame_stays_constant_through_the_resize() {
        let frame = RgbImage::from_pixel(96, 54, Rgb([10, 200, 77]));
        let out = crop_and_resize(&frame, 32, 32).unwrap();
        assert_eq!((out.width(), out.height()), (32, 32));
        assert!(out.pixels().all(|p| p.0 == [10, 200, 77]));
    }

    #[test]
    fn a_frame_already_at_the_input_size_is_unchanged() {
        let frame = RgbImage::from_fn(16, 16, |x, y| Rgb([x as u8 * 15, y as u8 * 15, 7]));
        assert_eq!(crop_and_resize(&frame, 16, 16).unwrap(), frame);
    }

    #[test]
    fn the_cropped_away_margins_do_not_influence_the_result() {
        let centre = RgbImage::from_fn(20, 20, |x, y| Rgb([(x * 12) as u8, (y * 12) as u8, 99]));
        let mut wide = RgbImage::from_pixel(40, 20, Rgb([255, 0, 255]));
        image::imageops::replace(&mut wide, &centre, 10, 0);
        assert_eq!(
            crop_and_resize(&wide, 8, 8).unwrap(),
            crop_and_resize(&centre, 8, 8).unwrap()
        );
    }

    #[test]
    fn upscaling_small_frames_works() {
        let frame = RgbImage::from_pixel(3, 5, Rgb([1, 2, 3]));
        let out = crop_and_resize(&frame, 14, 14).unwrap();
        assert!(out.pixels().all(|p| p.0 == [1, 2, 3]));
    }

    #[test]
    fn empty_frames_and_sizes_are_rejected() {
        assert!(crop_and_resize(&RgbImage::new(0, 5), 4, 4).is_err());
        assert!(crop_and_resize(&RgbImage::new(5, 5), 0, 4).is_err());
    }

    #[test]
    fn preprocess_returns_channel_first_values_of_the_input_size() {
        let input = InputSpec {
            height: 28,
            width: 28,
            crop: "center-square".into(),
            resize: "lanczos3".into(),
            value_range: [-1.0, 1.0],
        };
        let frame = RgbImage::from_pixel(64, 48, Rgb([255, 0, 51]));
        let values = preprocess(&frame, &input).unwrap();
        assert_eq!(values.len(), 3 * 28 * 28);
        assert!(values[..784].iter().all(|&v| v == 1.0));
        assert!(values[784..1568].iter().all(|&v| v == -1.0));
        assert!(
            values[1568..]
                .iter()
                .all(|&v| (v - (0.2 - 0.5) / 0.5).abs() < 1e-6)
        );
    }

    #[test]
    fn png_bytes_decode_to_rgb() {
        let frame = RgbImage::from_pixel(3, 2, Rgb([9, 8, 7]));
        let mut bytes = std::io::Cursor::new(Vec::new());
        frame.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
        assert_eq!(decode_frame(bytes.get_ref()).unwrap(), frame);
        assert!(decode_frame(b"not an image").is_err());
    }
}
