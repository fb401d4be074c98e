//! What goes into the encoder ([`ContextFrame`]) and what comes out of it ([`Encoding`]).
//!
//! An encoding is computed once per clip and cached; every decode reads it. It keeps its frames in
//! time order (the encoder treats the first frame specially and the scene lives in the first
//! frame's camera, so the order is part of the result) and remembers where each came from in the
//! caller's list, so that per-frame inputs given later in the caller's order (2D feature maps for
//! lifting) can be matched to the encoded frames. It also carries, when the caller knows it, the
//! source's frame step: the time policy's floor near the first frame (see [`crate::time`]).
//!
//! For a package in the precomputed decoder form it also keeps the context projection (the first
//! decoder layer's projection of the features, which no target changes): [`Engine::encode`]
//! computes it, and an encoding rebuilt from its parts gets it on its first decode. It is derived
//! from the features by one package's weights, so it remembers which engine made it, and an
//! encoding compares equal to another with the same parts whether or not either holds one.
//!
//! [`Engine::encode`]: crate::Engine::encode

use std::borrow::Cow;
use std::sync::OnceLock;

use crate::time::check_frame_step;
use crate::{EngineError, Result};

/// One context frame: its time and its preprocessed pixels (`[3, H, W]` at the package's input
/// size, values in the package's `value_range`; see [`crate::preprocess`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ContextFrame {
    /// Timestamp, seconds or frame index (any unit, as long as targets use the same one).
    pub time: f64,
    /// Channel-first pixels.
    pub pixels: Vec<f32>,
}

impl ContextFrame {
    /// A frame at `time` with preprocessed `pixels`.
    pub fn new(time: f64, pixels: Vec<f32>) -> Self {
        Self { time, pixels }
    }
}

/// The encoder's output for a set of context frames, with what decoding needs to know about them.
#[derive(Debug, Clone)]
pub struct Encoding {
    times: Vec<f64>,
    frame_order: Vec<usize>,
    features: Vec<f32>,
    shape: [usize; 3],
    frame_step: Option<f64>,
    context_projection: OnceLock<ContextProjection>,
    /// This encoding's number in the process (clones share it: they hold the same values), what
    /// a device-resident copy of it is kept under (`crate::resident`).
    serial: u64,
}

/// The next encoding's [`Encoding::serial`].
static SERIALS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// The first decoder layer's projection of an encoding's features, `[T, P, 3C]`, and the engine
/// whose package's weights made it.
#[derive(Clone)]
struct ContextProjection {
    engine: u64,
    values: Vec<f32>,
}

impl std::fmt::Debug for ContextProjection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ContextProjection")
            .field("engine", &self.engine)
            .field("values", &self.values.len())
            .finish()
    }
}

/// Equal parts make equal encodings: a context projection is derived from them.
impl PartialEq for Encoding {
    fn eq(&self, other: &Self) -> bool {
        self.times == other.times
            && self.frame_order == other.frame_order
            && self.features == other.features
            && self.shape == other.shape
            && self.frame_step == other.frame_step
    }
}

impl Encoding {
    /// Assembles an encoding from its parts (a cached or reference encoding, for example).
    ///
    /// `times` are the encoded frames' times in encoded order (finite, non-decreasing);
    /// `frame_order[k]` is the position, in the caller's original list, of encoded frame `k`
    /// (a permutation of `0..T`); `features` is `[T, P, C]` row-major with `shape = [T, P, C]`.
    pub fn from_parts(
        times: Vec<f64>,
        frame_order: Vec<usize>,
        features: Vec<f32>,
        shape: [usize; 3],
    ) -> Result<Self> {
        let [t, p, c] = shape;
        if t == 0 {
            return Err(EngineError::InvalidInput(
                "an encoding needs at least one frame".to_owned(),
            ));
        }
        if times.len() != t || frame_order.len() != t {
            return Err(EngineError::InvalidInput(format!(
                "an encoding of {t} frames needs {t} times and {t} frame positions, got {} and {}",
                times.len(),
                frame_order.len()
            )));
        }
        if let Some(&value) = times.iter().find(|v| !v.is_finite()) {
            return Err(EngineError::NonFiniteTime {
                what: "context",
                value,
            });
        }
        if times.windows(2).any(|w| w[0] > w[1]) {
            return Err(EngineError::InvalidInput(format!(
                "encoded frame times must be in increasing order, got {times:?}"
            )));
        }
        let mut seen = vec![false; t];
        for &i in &frame_order {
            if i >= t || std::mem::replace(&mut seen[i], true) {
                return Err(EngineError::InvalidInput(format!(
                    "frame order {frame_order:?} is not a permutation of 0..{t}"
                )));
            }
        }
        let expected = t.checked_mul(p).and_then(|tp| tp.checked_mul(c));
        if expected != Some(features.len()) {
            return Err(EngineError::InvalidInput(format!(
                "features hold {} values, shape {shape:?} needs {}",
                features.len(),
                expected.map_or_else(|| "more than fit in memory".to_owned(), |n| n.to_string())
            )));
        }
        Ok(Self {
            times: times.into_iter().map(|t| t + 0.0).collect(),
            frame_order,
            features,
            shape,
            frame_step: None,
            context_projection: OnceLock::new(),
            serial: SERIALS.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
        })
    }

    /// The same encoding with the source's frame step (seconds between consecutive source
    /// frames; `None`: unknown, the time policy falls back to the smallest context gap).
    /// Refuses a step that is not a positive, finite number.
    pub fn with_frame_step(self, frame_step: Option<f64>) -> Result<Self> {
        Ok(Self {
            frame_step: check_frame_step(frame_step)?,
            ..self
        })
    }

    /// The source's frame step in seconds, when known.
    pub fn frame_step(&self) -> Option<f64> {
        self.frame_step
    }

    /// This encoding's number in the process (see the field).
    pub(crate) fn serial(&self) -> u64 {
        self.serial
    }

    /// Times of the encoded frames, in encoded (increasing) order.
    pub fn times(&self) -> &[f64] {
        &self.times
    }

    /// `frame_order()[k]` is the position of encoded frame `k` in the list given to `encode`.
    pub fn frame_order(&self) -> &[usize] {
        &self.frame_order
    }

    /// Encoder features, `[T, P, C]` row-major, in encoded order.
    pub fn features(&self) -> &[f32] {
        &self.features
    }

    /// `[T, P, C]`: frames, tokens per frame, feature width.
    pub fn shape(&self) -> [usize; 3] {
        self.shape
    }

    /// Number of encoded frames, T.
    pub fn frame_count(&self) -> usize {
        self.shape[0]
    }

    /// The earliest and latest context time: the span a target must lie in.
    pub fn time_span(&self) -> (f64, f64) {
        (self.times[0], self.times[self.times.len() - 1])
    }

    /// The context projection `[T, P, 3C]`, once an engine of a package in the precomputed decoder
    /// form has encoded or decoded this encoding (see the module documentation).
    pub fn context_projection(&self) -> Option<&[f32]> {
        self.context_projection.get().map(|p| p.values.as_slice())
    }

    /// Bytes this encoding holds: its features and, once computed, its context projection
    /// (three times the features' size), plus its times. What a cache of encodings should count.
    pub fn memory_bytes(&self) -> usize {
        let projection = self.context_projection().map_or(0, <[f32]>::len);
        (self.features.len() + projection) * std::mem::size_of::<f32>()
            + self.times.len() * std::mem::size_of::<f64>()
            + self.frame_order.len() * std::mem::size_of::<usize>()
    }

    /// The context projection made by `engine`, if this encoding holds that one.
    pub(crate) fn context_projection_by(&self, engine: u64) -> Option<&[f32]> {
        self.context_projection
            .get()
            .filter(|p| p.engine == engine)
            .map(|p| p.values.as_slice())
    }

    /// Keeps `values`, `engine`'s context projection of these features, unless the encoding already
    /// holds one, and returns `engine`'s projection: the one kept (an engine makes the same one
    /// twice), or `values` themselves when the encoding holds another engine's.
    pub(crate) fn keep_context_projection(&self, engine: u64, values: Vec<f32>) -> Cow<'_, [f32]> {
        let mut values = Some(values);
        let kept = self.context_projection.get_or_init(|| ContextProjection {
            engine,
            values: values.take().unwrap_or_default(),
        });
        if kept.engine == engine {
            Cow::Borrowed(&kept.values)
        } else {
            Cow::Owned(values.unwrap_or_default())
        }
    }

    /// Takes the encoding apart into `(times, frame_order, features, shape)` (the frame step,
    /// [`frame_step`](Self::frame_step), and the context projection are not among them).
    pub fn into_parts(self) -> (Vec<f64>, Vec<usize>, Vec<f32>, [usize; 3]) {
        (self.times, self.frame_order, self.features, self.shape)
    }
}

/// The order in which `frames` are encoded: by time, ties broken by the pixel data compared
/// bitwise and lexicographically, so the result does not depend on the order they were given in
/// (identical frames at the same time are interchangeable). Times must be finite.
pub(crate) fn encoding_order(frames: &[ContextFrame]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..frames.len()).collect();
    order.sort_by(|&a, &b| {
        let (fa, fb) = (&frames[a], &frames[b]);
        (fa.time + 0.0)
            .total_cmp(&(fb.time + 0.0))
            .then_with(|| compare_bits(&fa.pixels, &fb.pixels))
    });
    order
}

/// Lexicographic order of the values' bit patterns.
fn compare_bits(a: &[f32], b: &[f32]) -> std::cmp::Ordering {
    a.iter()
        .map(|v| v.to_bits())
        .cmp(b.iter().map(|v| v.to_bits()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(time: f64, first: f32) -> ContextFrame {
        ContextFrame::new(time, vec![first, 0.5, -0.5])
    }

    #[test]
    fn frames_are_ordered_by_time() {
        let frames = [frame(4.0, 0.0), frame(0.0, 0.0), frame(2.0, 0.0)];
        assert_eq!(encoding_order(&frames), vec![1, 2, 0]);
    }

    #[test]
    fn frames_at_the_same_time_are_ordered_by_content() {
        let a = [frame(1.0, 0.25), frame(1.0, 0.125), frame(0.0, 0.9)];
        let b = [frame(1.0, 0.125), frame(0.0, 0.9), frame(1.0, 0.25)];
        let content = |frames: &[ContextFrame]| {
            encoding_order(frames)
                .into_iter()
                .map(|i| frames[i].clone())
                .collect::<Vec<_>>()
        };
        assert_eq!(content(&a), content(&b));
        assert_eq!(content(&a)[0].time, 0.0);
        assert_eq!(content(&a)[1].pixels[0], 0.125);
    }

    #[test]
    fn negative_zero_and_zero_are_the_same_time() {
        let frames = [frame(0.0, 0.5), frame(-0.0, 0.25)];
        assert_eq!(encoding_order(&frames), vec![1, 0]);
    }

    #[test]
    fn from_parts_accepts_a_consistent_encoding() {
        let e = Encoding::from_parts(vec![0.0, 2.0], vec![1, 0], vec![0.0; 2 * 3 * 4], [2, 3, 4])
            .unwrap();
        assert_eq!(e.time_span(), (0.0, 2.0));
        assert_eq!(e.frame_order(), &[1, 0]);
        assert_eq!(e.frame_count(), 2);
        assert_eq!(e.frame_step(), None);
    }

    #[test]
    fn the_frame_step_rides_along_and_must_be_a_positive_finite_number() {
        let e =
            || Encoding::from_parts(vec![0.0, 2.0], vec![0, 1], vec![0.0; 2 * 3 * 4], [2, 3, 4]);
        let stepped = e().unwrap().with_frame_step(Some(1.0 / 30.0)).unwrap();
        assert_eq!(stepped.frame_step(), Some(1.0 / 30.0));
        assert_eq!(stepped.with_frame_step(None).unwrap().frame_step(), None);
        for bad in [0.0, -0.5, f64::NAN, f64::INFINITY] {
            let err = e().unwrap().with_frame_step(Some(bad)).unwrap_err();
            assert!(matches!(err, EngineError::InvalidInput(_)), "{err}");
        }
    }

    #[test]
    fn a_context_projection_is_kept_once_and_only_read_back_by_its_engine() {
        let e = Encoding::from_parts(vec![0.0], vec![0], vec![1.0; 3 * 4], [1, 3, 4]).unwrap();
        let bare = e.clone();
        assert_eq!(e.context_projection(), None);
        assert_eq!(e.memory_bytes(), 12 * 4 + 8 + std::mem::size_of::<usize>());
        assert!(matches!(
            e.keep_context_projection(7, vec![2.0; 36]),
            Cow::Borrowed(v) if v == [2.0; 36]
        ));
        assert!(matches!(
            e.keep_context_projection(7, vec![3.0; 36]),
            Cow::Borrowed(v) if v == [2.0; 36]
        ));
        assert!(matches!(
            e.keep_context_projection(8, vec![4.0; 36]),
            Cow::Owned(v) if v == [4.0; 36]
        ));
        assert_eq!(e.context_projection(), Some(&[2.0; 36][..]));
        assert_eq!(e.context_projection_by(7), Some(&[2.0; 36][..]));
        assert_eq!(e.context_projection_by(8), None);
        assert_eq!(e.memory_bytes(), 48 * 4 + 8 + std::mem::size_of::<usize>());
        assert_eq!(
            e, bare,
            "a projection is derived data, not part of what an encoding is"
        );
        let stepped = e.with_frame_step(Some(0.5)).unwrap();
        assert_eq!(stepped.context_projection_by(7).map(<[f32]>::len), Some(36));
    }

    #[test]
    fn from_parts_rejects_inconsistent_parts() {
        let f = || vec![0.0; 2 * 3 * 4];
        assert!(Encoding::from_parts(vec![2.0, 0.0], vec![0, 1], f(), [2, 3, 4]).is_err());
        assert!(Encoding::from_parts(vec![0.0, f64::NAN], vec![0, 1], f(), [2, 3, 4]).is_err());
        assert!(Encoding::from_parts(vec![0.0, 1.0], vec![0, 0], f(), [2, 3, 4]).is_err());
        assert!(Encoding::from_parts(vec![0.0, 1.0], vec![0, 2], f(), [2, 3, 4]).is_err());
        assert!(Encoding::from_parts(vec![0.0, 1.0], vec![0, 1], vec![0.0; 5], [2, 3, 4]).is_err());
        assert!(Encoding::from_parts(vec![0.0], vec![0], f(), [1, usize::MAX, 2]).is_err());
        assert!(Encoding::from_parts(vec![], vec![], vec![], [0, 3, 4]).is_err());
    }
}
