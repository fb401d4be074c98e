//! The VACE control input: what the control branch sees besides the noisy latents.
//!
//! For a video `V` in [-1, 1] and a mask `M` (1 = regenerate, 0 = keep), the control tensor is
//! 96 channels at latent resolution: `[inactive 16; reactive 16; mask 64]`, where
//! - inactive = VAE(V·(1 − B)), reactive = VAE(V·B), with `B` the mask binarised at 0.5, both
//!   latents normalised per channel (`(x − mean) / std`);
//! - the mask is pixel-unshuffled 8 × 8 into 64 channels (channel `dy·8 + dx`) and resampled in
//!   time to `(F + 3) / 4` frames with nearest-exact sampling.
//!
//! The 64 mask channels carry the mask as given (clamped to [0, 1]), not binarised: the reference
//! pipelines (diffusers' WanVACEPipeline and the original VACE code) binarise only the copy used
//! to split the video. For the 0/1 masks C4G sends the two readings agree.
//!
//! Everything here is plain array work; the VAE runs in [`crate::Pipeline`].

use crate::{RefinerError, Result};

/// Spatial compression of the VAE (and the mask unshuffle factor).
pub const SPATIAL_FACTOR: usize = 8;
/// Temporal compression of the VAE.
pub const TEMPORAL_FACTOR: usize = 4;
/// Latent channels of the VAE.
pub const LATENT_CHANNELS: usize = 16;
/// Mask channels after the 8 × 8 unshuffle.
pub const MASK_CHANNELS: usize = SPATIAL_FACTOR * SPATIAL_FACTOR;
/// Channels of the control tensor: inactive, reactive, mask.
pub const CONTROL_CHANNELS: usize = 2 * LATENT_CHANNELS + MASK_CHANNELS;

/// Which pixels to regenerate, per frame.
#[derive(Debug, Clone, PartialEq)]
pub enum Mask {
    /// One flag per frame: `true` regenerates the whole frame (a rendered frame), `false` keeps it
    /// (a context frame).
    Frames(Vec<bool>),
    /// One `[H, W]` plane per frame, values in [0, 1] (1 = regenerate).
    Pixels(Vec<Vec<f32>>),
}

impl Mask {
    /// The mask as `[F, H, W]` values in [0, 1], checked against the video's size.
    pub fn to_pixels(&self, frames: usize, height: usize, width: usize) -> Result<Vec<f32>> {
        let plane = height * width;
        match self {
            Self::Frames(flags) => {
                check_count("mask", flags.len(), frames)?;
                Ok(flags
                    .iter()
                    .flat_map(|&on| std::iter::repeat_n(if on { 1.0 } else { 0.0 }, plane))
                    .collect())
            }
            Self::Pixels(planes) => {
                check_count("mask", planes.len(), frames)?;
                let mut out = Vec::with_capacity(frames * plane);
                for (i, p) in planes.iter().enumerate() {
                    if p.len() != plane {
                        return Err(RefinerError::InvalidRequest(format!(
                            "mask frame {i} has {} values, expected {height} x {width} = {plane}",
                            p.len()
                        )));
                    }
                    if let Some(v) = p.iter().find(|v| !v.is_finite()) {
                        return Err(RefinerError::InvalidRequest(format!(
                            "mask frame {i} holds the non-finite value {v}"
                        )));
                    }
                    out.extend(p.iter().map(|v| v.clamp(0.0, 1.0)));
                }
                Ok(out)
            }
        }
    }
}

fn check_count(what: &str, got: usize, expected: usize) -> Result<()> {
    if got == expected {
        Ok(())
    } else {
        Err(RefinerError::InvalidRequest(format!(
            "{what} has {got} frames, the package takes {expected}"
        )))
    }
}

/// Latent frames for `frames` video frames: the first frame alone, then groups of four.
pub fn latent_frames(frames: usize) -> usize {
    frames.div_ceil(TEMPORAL_FACTOR)
}

/// The source index nearest-exact resampling picks for each of `output` positions out of
/// `input`: `floor((j + ½)·input/output)`, clamped, in f32 as PyTorch computes it.
pub fn nearest_exact_indices(input: usize, output: usize) -> Vec<usize> {
    let scale = input as f32 / output as f32;
    (0..output)
        .map(|j| (((j as f32 + 0.5) * scale).floor() as usize).min(input.saturating_sub(1)))
        .collect()
}

/// Pixel-unshuffles `[F, H, W]` into `[64, F, H/8, W/8]`, channel `dy·8 + dx`.
pub fn unshuffle_mask(mask: &[f32], frames: usize, height: usize, width: usize) -> Vec<f32> {
    let f = SPATIAL_FACTOR;
    let (h, w) = (height / f, width / f);
    let mut out = vec![0.0; MASK_CHANNELS * frames * h * w];
    for t in 0..frames {
        for y in 0..h * f {
            let (ly, dy) = (y / f, y % f);
            for x in 0..w * f {
                let (lx, dx) = (x / f, x % f);
                let channel = dy * f + dx;
                out[((channel * frames + t) * h + ly) * w + lx] =
                    mask[(t * height + y) * width + x];
            }
        }
    }
    out
}

/// Picks `indices` frames out of `[C, F, P]` (P values per frame) into `[C, indices.len(), P]`.
pub fn pick_frames(x: &[f32], channels: usize, frames: usize, indices: &[usize]) -> Vec<f32> {
    let plane = x.len() / (channels * frames).max(1);
    let mut out = Vec::with_capacity(channels * indices.len() * plane);
    for c in 0..channels {
        for &t in indices {
            let start = (c * frames + t) * plane;
            out.extend_from_slice(&x[start..start + plane]);
        }
    }
    out
}

/// The 64 mask channels of the control tensor: `[64, (F + 3) / 4, H/8, W/8]` from `[F, H, W]`.
pub fn latent_mask(mask: &[f32], frames: usize, height: usize, width: usize) -> Vec<f32> {
    let unshuffled = unshuffle_mask(mask, frames, height, width);
    let indices = nearest_exact_indices(frames, latent_frames(frames));
    pick_frames(&unshuffled, MASK_CHANNELS, frames, &indices)
}

/// Splits a `[3, F, H, W]` video by a `[F, H, W]` mask binarised at 0.5: (inactive, reactive) =
/// (video where the mask keeps, zero elsewhere; video where it regenerates, zero elsewhere).
pub fn split_video(video: &[f32], mask: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let mut inactive = Vec::with_capacity(video.len());
    let mut reactive = Vec::with_capacity(video.len());
    for (v, &m) in video.iter().zip(mask.iter().cycle()) {
        // `mask.cycle()` repeats the [F, H, W] plane for each of the three colour channels.
        let b = if m > 0.5 { 1.0 } else { 0.0 };
        inactive.push(v * (1.0 - b));
        reactive.push(v * b);
    }
    (inactive, reactive)
}

/// Per-channel statistics of the VAE's latent space.
#[derive(Debug, Clone, PartialEq)]
pub struct LatentStats {
    mean: Vec<f32>,
    inv_std: Vec<f32>,
}

impl LatentStats {
    /// From the package's `mean` and `std` (one value per latent channel).
    pub fn new(mean: Vec<f32>, std: &[f32]) -> Result<Self> {
        if mean.len() != std.len() || std.iter().any(|s| !s.is_finite() || *s <= 0.0) {
            return Err(RefinerError::InvalidRequest(format!(
                "latent statistics need one mean and one positive std per channel, got {} means and stds {std:?}",
                mean.len()
            )));
        }
        // The reference multiplies by 1/std (and divides by it to undo); doing the same keeps our
        // rounding identical to theirs.
        let inv_std = std.iter().map(|s| 1.0 / s).collect();
        Ok(Self { mean, inv_std })
    }

    /// Channels described.
    pub fn channels(&self) -> usize {
        self.mean.len()
    }

    /// `(x − mean) / std` per channel of `[C, …]`, in place: VAE latents to model latents.
    pub fn normalize(&self, x: &mut [f32]) {
        let per_channel = x.len() / self.channels().max(1);
        for (c, chunk) in x.chunks_mut(per_channel.max(1)).enumerate() {
            let (m, s) = (self.mean[c], self.inv_std[c]);
            chunk.iter_mut().for_each(|v| *v = (*v - m) * s);
        }
    }

    /// `x·std + mean` per channel of `[C, …]`, in place: model latents to VAE latents.
    pub fn denormalize(&self, x: &mut [f32]) {
        let per_channel = x.len() / self.channels().max(1);
        for (c, chunk) in x.chunks_mut(per_channel.max(1)).enumerate() {
            let (m, s) = (self.mean[c], self.inv_std[c]);
            chunk.iter_mut().for_each(|v| *v = *v / s + m);
        }
    }
}

/// Concatenates normalised inactive and reactive latents (`[16, F', h, w]` each) and the latent
/// mask (`[64, F', h, w]`) into the `[96, F', h, w]` control tensor.
pub fn assemble(inactive: &[f32], reactive: &[f32], mask: &[f32]) -> Vec<f32> {
    let mut out = Vec::with_capacity(inactive.len() + reactive.len() + mask.len());
    out.extend_from_slice(inactive);
    out.extend_from_slice(reactive);
    out.extend_from_slice(mask);
    out
}

/// Joins `[C, f_i, P]` parts (`frames_of[i]` frames of `plane` values each) along time into
/// `[C, Σ f_i, P]`: how C4G's layout lays keyframe slots before the rendered part.
pub fn concat_frames(
    parts: &[Vec<f32>],
    frames_of: &[usize],
    channels: usize,
    plane: usize,
) -> Vec<f32> {
    let total: usize = frames_of.iter().sum();
    let mut out = Vec::with_capacity(channels * total * plane);
    for c in 0..channels {
        for (part, &f) in parts.iter().zip(frames_of) {
            out.extend_from_slice(&part[c * f * plane..(c + 1) * f * plane]);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_join_along_time_channel_by_channel() {
        // Two channels, one value a frame: a one-frame part [a0; a1] and a two-frame part
        // [b00 b01; b10 b11].
        let joined = concat_frames(&[vec![1.0, 2.0], vec![3.0, 4.0, 5.0, 6.0]], &[1, 2], 2, 1);
        assert_eq!(joined, vec![1.0, 3.0, 4.0, 2.0, 5.0, 6.0]);
    }

    #[test]
    fn eighty_one_frames_resample_to_the_documented_twenty_one() {
        assert_eq!(latent_frames(81), 21);
        assert_eq!(
            nearest_exact_indices(81, 21),
            vec![
                1, 5, 9, 13, 17, 21, 25, 28, 32, 36, 40, 44, 48, 52, 55, 59, 63, 67, 71, 75, 79
            ]
        );
    }

    #[test]
    fn latent_frame_counts_follow_the_causal_vae() {
        assert_eq!(
            [1, 2, 4, 5, 8, 9, 13].map(latent_frames),
            [1, 1, 1, 2, 2, 3, 4]
        );
        assert_eq!(nearest_exact_indices(1, 1), vec![0]);
        assert_eq!(nearest_exact_indices(5, 2), vec![1, 3]);
        assert_eq!(nearest_exact_indices(9, 3), vec![1, 4, 7]);
    }

    #[test]
    fn unshuffle_puts_pixel_dy_dx_in_channel_dy_times_8_plus_dx() {
        // Two frames of 16 x 24: every pixel holds a value naming its position.
        let (f, h, w) = (2, 16, 24);
        let mask: Vec<f32> = (0..f * h * w).map(|i| i as f32).collect();
        let out = unshuffle_mask(&mask, f, h, w);
        let (lh, lw) = (h / 8, w / 8);
        assert_eq!(out.len(), 64 * f * lh * lw);
        for t in 0..f {
            for y in 0..h {
                for x in 0..w {
                    let c = (y % 8) * 8 + x % 8;
                    let got = out[((c * f + t) * lh + y / 8) * lw + x / 8];
                    assert_eq!(got, ((t * h + y) * w + x) as f32);
                }
            }
        }
    }

    #[test]
    fn the_latent_mask_keeps_the_picked_frames() {
        // Five 8 x 8 frames, frame t filled with t: frames 1 and 3 survive, in every channel.
        let mask: Vec<f32> = (0..5).flat_map(|t| vec![t as f32; 64]).collect();
        let out = latent_mask(&mask, 5, 8, 8);
        assert_eq!(out.len(), 64 * 2);
        for c in 0..64 {
            assert_eq!(&out[c * 2..c * 2 + 2], &[1.0, 3.0]);
        }
    }

    #[test]
    fn the_video_splits_at_half_into_inactive_and_reactive() {
        // 3 channels, 1 frame, 2 pixels: pixel 0 kept (mask 0.5), pixel 1 regenerated (0.51).
        let video = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6];
        let (inactive, reactive) = split_video(&video, &[0.5, 0.51]);
        assert_eq!(inactive, vec![0.1, 0.0, 0.3, 0.0, 0.5, 0.0]);
        assert_eq!(reactive, vec![0.0, 0.2, 0.0, 0.4, 0.0, 0.6]);
    }

    #[test]
    fn frame_flags_expand_to_planes_and_pixel_masks_are_checked() {
        let m = Mask::Frames(vec![false, true]).to_pixels(2, 1, 2).unwrap();
        assert_eq!(m, vec![0.0, 0.0, 1.0, 1.0]);
        assert!(Mask::Frames(vec![true]).to_pixels(2, 1, 2).is_err());
        let m = Mask::Pixels(vec![vec![-1.0, 2.0]])
            .to_pixels(1, 1, 2)
            .unwrap();
        assert_eq!(m, vec![0.0, 1.0]);
        assert!(Mask::Pixels(vec![vec![0.0]]).to_pixels(1, 1, 2).is_err());
        assert!(
            Mask::Pixels(vec![vec![0.0, f32::NAN]])
                .to_pixels(1, 1, 2)
                .is_err()
        );
    }

    #[test]
    fn normalisation_round_trips_per_channel() {
        let stats = LatentStats::new(vec![1.0, -2.0], &[2.0, 0.5]).unwrap();
        let mut x = vec![3.0, 5.0, -2.0, 0.0];
        stats.normalize(&mut x);
        assert_eq!(x, vec![1.0, 2.0, 0.0, 4.0]);
        stats.denormalize(&mut x);
        assert_eq!(x, vec![3.0, 5.0, -2.0, 0.0]);
        assert!(LatentStats::new(vec![0.0], &[0.0]).is_err());
    }

    #[test]
    fn the_control_tensor_stacks_inactive_reactive_mask() {
        let out = assemble(&[1.0], &[2.0], &[3.0, 4.0]);
        assert_eq!(out, vec![1.0, 2.0, 3.0, 4.0]);
        assert_eq!(CONTROL_CHANNELS, 96);
    }
}
