//! The header: the grid steps, the static mask, and the index entries a trailer lists.

use c4g_scene::SceneError;

use super::*;

/// The grid steps, as the header carries them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Steps {
    /// Of positions, scene units.
    pub position: f64,
    /// Of the natural logarithm of scales.
    pub log_scale: f64,
    /// Of each rotation component.
    pub rotation: f64,
    /// Of opacities.
    pub opacity: f64,
    /// Of colour channels.
    pub color: f64,
}

impl Steps {
    /// This encoder's steps for a position error.
    pub(super) fn for_error(position_error: f64) -> Self {
        Self {
            position: POSITION_STEP_PER_ERROR * position_error,
            log_scale: LOG_SCALE_STEP,
            rotation: ROTATION_STEP,
            opacity: OPACITY_STEP,
            color: COLOR_STEP,
        }
    }

    pub(super) fn as_array(&self) -> [f64; 5] {
        [
            self.position,
            self.log_scale,
            self.rotation,
            self.opacity,
            self.color,
        ]
    }
}

/// One frame in the index.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndexEntry {
    /// The frame's time, seconds.
    pub time: f64,
    /// Where its record starts, from the stream's first byte.
    pub offset: u64,
    /// Whether it is a keyframe (a reader may start there).
    pub keyframe: bool,
}

/// What a stream's header says.
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    /// Gaussians per frame.
    pub gaussians: usize,
    /// Per Gaussian, whether it is static.
    pub static_mask: Vec<bool>,
    /// The grid steps.
    pub steps: Steps,
}

impl Header {
    pub(super) fn to_bytes(&self) -> Vec<u8> {
        let statics = self.static_mask.iter().filter(|&&s| s).count();
        let mut out = Vec::with_capacity(HEADER_BYTES + self.gaussians.div_ceil(8));
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.push(0);
        out.push(0);
        // Both fit: the encoder checked N against u32.
        out.extend_from_slice(&(self.gaussians as u32).to_le_bytes());
        out.extend_from_slice(&(statics as u32).to_le_bytes());
        for step in self.steps.as_array() {
            out.extend_from_slice(&step.to_le_bytes());
        }
        let mut mask = vec![0u8; self.gaussians.div_ceil(8)];
        for (i, _) in self.static_mask.iter().enumerate().filter(|(_, s)| **s) {
            mask[i / 8] |= 1 << (i % 8);
        }
        out.extend_from_slice(&mask);
        out
    }

    /// The header at the start of `bytes`, and its length; `None` while it is incomplete.
    pub(super) fn parse(bytes: &[u8]) -> Result<Option<(Self, usize)>, SceneError> {
        let prefix = &bytes[..bytes.len().min(MAGIC.len())];
        if prefix != &MAGIC[..prefix.len()] {
            return Err(format_error(format!(
                "not a C4GV stream (starts with {prefix:?})"
            )));
        }
        let Some(fixed) = bytes.get(..HEADER_BYTES) else {
            return Ok(None);
        };
        let version = u16::from_le_bytes([fixed[4], fixed[5]]);
        if version != VERSION {
            return Err(format_error(format!(
                "C4GV version {version}; this reader reads version {VERSION} only"
            )));
        }
        if fixed[6] != 0 {
            return Err(format_error(format!(
                "unknown C4GV predictor {} (version 1 has 0 only)",
                fixed[6]
            )));
        }
        // fixed[7] is reserved.
        let gaussians = read_u32(&fixed[8..]) as usize;
        let statics = read_u32(&fixed[12..]) as usize;
        let step = |k: usize| read_f64(&fixed[16 + 8 * k..]);
        let steps = Steps {
            position: step(0),
            log_scale: step(1),
            rotation: step(2),
            opacity: step(3),
            color: step(4),
        };
        if let Some(bad) = steps
            .as_array()
            .into_iter()
            .find(|s| !(s.is_finite() && *s > 0.0))
        {
            return Err(format_error(format!(
                "C4GV grid steps must be finite and positive; the header has {bad}"
            )));
        }
        if statics > gaussians {
            return Err(format_error(format!(
                "C4GV header claims {statics} static Gaussians of {gaussians}"
            )));
        }
        let length = HEADER_BYTES + gaussians.div_ceil(8);
        let Some(mask) = bytes.get(HEADER_BYTES..length) else {
            return Ok(None);
        };
        // The mask is here, so everything sized by N below is bounded by bytes received.
        let static_mask: Vec<bool> = (0..gaussians)
            .map(|i| mask[i / 8] & (1 << (i % 8)) != 0)
            .collect();
        let padding = gaussians % 8;
        if padding != 0 && mask[mask.len() - 1] >> padding != 0 {
            return Err(format_error(
                "C4GV static mask sets bits past the last Gaussian".into(),
            ));
        }
        let set = static_mask.iter().filter(|&&s| s).count();
        if set != statics {
            return Err(format_error(format!(
                "C4GV header claims {statics} static Gaussians; its mask marks {set}"
            )));
        }
        Ok(Some((
            Self {
                gaussians,
                static_mask,
                steps,
            },
            length,
        )))
    }

    pub(super) fn statics(&self) -> Vec<usize> {
        (0..self.gaussians)
            .filter(|&i| self.static_mask[i])
            .collect()
    }

    pub(super) fn movers(&self) -> Vec<usize> {
        (0..self.gaussians)
            .filter(|&i| !self.static_mask[i])
            .collect()
    }
}
