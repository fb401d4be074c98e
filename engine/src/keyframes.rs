//! Keyframed decoding: exact Gaussian sets at a few keyframe times, interpolated per Gaussian in
//! between, so that many output times cost a few decoder runs.
//!
//! Query `i` of the decoder is the same Gaussian at every time, so the set at a time between two
//! keyframes is interpolated attribute by attribute from the exact sets around it:
//!
//! | attribute | interpolation | why |
//! |---|---|---|
//! | position | piecewise cubic Hermite with Bessel tangents, C1 between context times | smooth motion, exact at every keyframe |
//! | rotation | slerp on the shorter arc | stays a unit quaternion; `q` and `-q` are one rotation |
//! | scale | linear in log space (geometric); linear from or to 0 | stays positive; doubling and halving are symmetric |
//! | opacity, colour, lifted features | linear, within the two keyframes' values | opacity stays in \[0, 1\], colour ≥ 0 |
//!
//! **Which cubic.** Each interval is a cubic Hermite segment between its two keyframes, so the
//! curve passes through every keyframe exactly and its velocity is continuous (C1). The tangent at
//! a keyframe is the slope there of the parabola through it and its two neighbours (Bessel's
//! tangent, `(h₁·d₀ + h₀·d₁) / (h₀ + h₁)` for the neighbouring intervals' lengths `h` and secant
//! slopes `d`; at the ends, the same parabola's slope at its end). That is Catmull-Rom
//! generalised to uneven spacing in the way that stays accurate: Catmull-Rom's own tangent
//! `(p₊ − p₋) / (t₊ − t₋)` is exact for quadratic motion only when both intervals are equally
//! long, and adaptive refinement makes neighbours differ by factors of two and more. With Bessel
//! tangents the whole curve reproduces constant-acceleration motion exactly on any spacing. With
//! two keyframes both tangents are the secant, and the segment is the straight line between them.
//!
//! **Corners at context times.** The decoder's motion bends sharply at the context frames' times
//! (what it attends to changes there: on c4g-tiny a Gaussian's depth falls and then rises with a
//! corner at a context time), and a cubic smoothed across a corner overshoots on both sides. So the
//! engine gives the encoding's context times to the track as breaks: at a keyframe on one, each
//! side takes its tangent from its own keyframes alone, and the curve is C1 between context times
//! and continuous at them.
//!
//! **Where keyframes go** ([`Keyframes`]): nowhere (exact decodes, the default), evenly over the
//! requested range (both ends included), or adaptively: start from the range's ends and the
//! context times inside it and, for every interval between keyframes that still holds requested
//! times, decode exactly the requested times nearest its thirds and compare them with the
//! interpolation; where the largest position error (or the colour / opacity error, when a
//! tolerance for it is given) exceeds the tolerance, split there and check the pieces. Every
//! exact decode made, checks included, is a keyframe of the final interpolation. Why thirds and
//! not the midpoint: see `check_times`. All the checks of one round go to the decoder as one
//! call, which batches them.
//!
//! Uniform keyframes never cost more decodes than decoding every requested time: at least as many
//! keyframes as distinct targets decode the targets themselves, as an adaptive tolerance of 0
//! does. Every adaptive check is a requested time, so at worst (a tolerance below what the
//! model's motion allows) the adaptive mode decodes every target plus the context times inside
//! the range, in a few batched rounds.

use c4g_scene::{FeatureBlock, GaussianSet};

use crate::encoding::Encoding;
use crate::engine::Engine;
use crate::{EngineError, QuerySubset, Result};

/// How a decode of many times is computed: exactly at every time, or exactly at keyframes and
/// interpolated between them.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Keyframes {
    /// Decode every requested time (the decoder runs once per time, batched).
    #[default]
    Exact,
    /// Keyframes every `seconds` from the first requested time, and one at the last.
    Every {
        /// Spacing of the keyframes, seconds (> 0).
        seconds: f64,
    },
    /// `n` keyframes spread evenly over the requested range, both ends included.
    Count {
        /// Number of keyframes (≥ 2).
        n: usize,
    },
    /// Keyframes placed by refinement until every interval's checks (at the requested times
    /// nearest its thirds) pass.
    Adaptive {
        /// Largest position error allowed at a check, scene units (≥ 0; 0 decodes exactly).
        tolerance: f64,
        /// Largest colour or opacity error allowed at a check (absolute, in their 0..1 units);
        /// `None` checks positions only.
        color_tolerance: Option<f64>,
        /// Most exact decodes in all, the range's ends and every check included (≥ 2).
        max_keyframes: usize,
        /// No check closer than this to a keyframe, so no two keyframes closer than this
        /// (seconds, ≥ 0; 0: no bound but the count).
        min_interval: f64,
    },
}

impl Keyframes {
    /// Exact decodes an adaptive plan may make when the caller does not say.
    pub const DEFAULT_MAX_KEYFRAMES: usize = 64;

    /// Adaptive keyframes checking positions only, with no bound on interval length.
    pub fn adaptive(tolerance: f64, max_keyframes: usize) -> Self {
        Self::Adaptive {
            tolerance,
            color_tolerance: None,
            max_keyframes,
            min_interval: 0.0,
        }
    }

    /// True when this plan decodes every requested time exactly: [`Exact`](Self::Exact), or an
    /// adaptive tolerance of 0.
    pub fn is_exact(&self) -> bool {
        match *self {
            Self::Exact => true,
            Self::Adaptive {
                tolerance,
                color_tolerance,
                ..
            } => tolerance == 0.0 || color_tolerance == Some(0.0),
            Self::Every { .. } | Self::Count { .. } => false,
        }
    }

    /// True when a keyframed decode of `targets` interpolates some of them; false when it
    /// decodes every target exactly (the exact mode, a tolerance of 0, as many uniform keyframes
    /// as distinct targets or more, or at most two targets).
    pub fn interpolates(&self, targets: &[f64]) -> bool {
        let Ok(distinct) = distinct_times(targets) else {
            return false;
        };
        let Some((&start, &end)) = distinct.first().zip(distinct.last()) else {
            return false;
        };
        match *self {
            _ if self.is_exact() => false,
            Self::Every { .. } | Self::Count { .. } => self
                .max_keyframes(start, end)
                .is_some_and(|n| n < distinct.len()),
            Self::Adaptive { .. } => distinct.len() > 2,
            Self::Exact => false,
        }
    }

    /// Checks the option's own values (positive spacing, at least two keyframes, finite
    /// non-negative tolerances).
    pub fn validate(&self) -> Result<()> {
        let invalid = |message: String| Err(EngineError::InvalidInput(message));
        match *self {
            Self::Exact => Ok(()),
            Self::Every { seconds } if !(seconds.is_finite() && seconds > 0.0) => invalid(format!(
                "keyframe spacing must be a positive number of seconds, got {seconds}"
            )),
            Self::Every { .. } => Ok(()),
            Self::Count { n } if n < 2 => invalid(format!(
                "a keyframe count needs at least 2 keyframes (both ends of the range), got {n}"
            )),
            Self::Count { .. } => Ok(()),
            Self::Adaptive {
                tolerance,
                color_tolerance,
                max_keyframes,
                min_interval,
            } => {
                if !(tolerance.is_finite() && tolerance >= 0.0) {
                    return invalid(format!(
                        "the keyframe tolerance must be a finite, non-negative distance, got {tolerance}"
                    ));
                }
                if let Some(c) = color_tolerance
                    && !(c.is_finite() && c >= 0.0)
                {
                    return invalid(format!(
                        "the keyframe colour tolerance must be finite and non-negative, got {c}"
                    ));
                }
                if max_keyframes < 2 {
                    return invalid(format!(
                        "adaptive keyframes need a maximum of at least 2 (both ends of the range), got {max_keyframes}"
                    ));
                }
                if !(min_interval.is_finite() && min_interval >= 0.0) {
                    return invalid(format!(
                        "the minimum keyframe interval must be finite and non-negative, got {min_interval}"
                    ));
                }
                Ok(())
            }
        }
    }

    /// The most keyframes this option can decode over `[start, end]`; `None` for
    /// [`Exact`](Self::Exact), which decodes every requested time. Call after
    /// [`validate`](Self::validate).
    pub fn max_keyframes(&self, start: f64, end: f64) -> Option<usize> {
        match *self {
            Self::Exact => None,
            Self::Every { seconds } => Some(every_count(start, end, seconds)),
            Self::Count { n } => Some(n),
            Self::Adaptive { max_keyframes, .. } => Some(max_keyframes),
        }
    }
}

/// What a keyframed decode cost.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeyframeStats {
    /// Sets the decoder computed: keyframes, adaptive checks included.
    pub exact_decodes: usize,
    /// Decoder runs those took (each run decodes up to the engine's batch of targets).
    pub decoder_runs: usize,
    /// Times decoded exactly, increasing: the keyframes the interpolation used.
    pub keyframe_times: Vec<f64>,
    /// Output sets that were interpolated rather than decoded (0 from a plan alone).
    pub interpolated: usize,
    /// Adaptive refinement rounds (each one decoder call, batched).
    pub rounds: usize,
}

/// How far one set is from another, Gaussian by Gaussian: the largest difference of each kind.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Deviation {
    /// Largest distance between the two positions of one Gaussian, scene units.
    pub position: f64,
    /// Largest absolute difference of a colour channel or the opacity.
    pub appearance: f64,
    /// Largest angle between the two rotations of one Gaussian, radians.
    pub rotation: f64,
    /// Largest absolute log-ratio of two scales of one Gaussian along one axis, scales under
    /// [`Deviation::SCALE_FLOOR`] counted as the floor (against 0 a ratio is infinite, and means
    /// nothing visible).
    pub log_scale: f64,
}

impl Deviation {
    /// The smallest scale [`log_scale`](Self::log_scale) tells apart, scene units.
    pub const SCALE_FLOOR: f64 = 1e-6;
}

/// How far `b` is from `a`. Fails when the sets hold different numbers of Gaussians.
pub fn deviation(a: &GaussianSet, b: &GaussianSet) -> Result<Deviation> {
    if a.len() != b.len() {
        return Err(EngineError::InvalidInput(format!(
            "cannot compare a set of {} Gaussians with one of {}",
            a.len(),
            b.len()
        )));
    }
    let mut d = Deviation::default();
    for i in 0..a.len() {
        let (pa, pb) = (a.positions()[i], b.positions()[i]);
        let distance = (0..3)
            .map(|k| (f64::from(pa[k]) - f64::from(pb[k])).powi(2))
            .sum::<f64>()
            .sqrt();
        d.position = d.position.max(distance);
        let (ca, cb) = (a.colors()[i], b.colors()[i]);
        let opacity = (f64::from(a.opacities()[i]) - f64::from(b.opacities()[i])).abs();
        let color = (0..3)
            .map(|k| (f64::from(ca[k]) - f64::from(cb[k])).abs())
            .fold(opacity, f64::max);
        d.appearance = d.appearance.max(color);
        if a.rotations()[i] != b.rotations()[i] {
            let (qa, qb) = (unit(a.rotations()[i]), unit(b.rotations()[i]));
            let dot = (0..4).map(|k| qa[k] * qb[k]).sum::<f64>().abs().min(1.0);
            d.rotation = d.rotation.max(2.0 * dot.acos());
        }
        let (sa, sb) = (a.scales()[i], b.scales()[i]);
        for k in 0..3 {
            let floor = |v: f32| f64::from(v).max(Deviation::SCALE_FLOOR).ln();
            d.log_scale = d.log_scale.max((floor(sa[k]) - floor(sb[k])).abs());
        }
    }
    Ok(d)
}

/// Exact sets at keyframe times, and the interpolation between them ([`at`](Self::at)).
#[derive(Debug, Clone, Default)]
pub struct KeyframeTrack {
    times: Vec<f64>,
    sets: Vec<GaussianSet>,
    /// Times where the motion may turn a corner (the context frames' times).
    breaks: Vec<f64>,
    /// Position derivative of every Gaussian leaving each keyframe, scene units per second.
    out_tangents: Vec<Vec<[f64; 3]>>,
    /// The same, arriving at each keyframe (another only at a break).
    in_tangents: Vec<Vec<[f64; 3]>>,
}

impl KeyframeTrack {
    /// A track through `keyframes` (any order; of two at one time the first is kept).
    ///
    /// Fails when there are none, a time is not finite, or the sets differ in size or in the
    /// width of their feature vectors.
    pub fn new(keyframes: Vec<(f64, GaussianSet)>) -> Result<Self> {
        Self::with_breaks(keyframes, &[])
    }

    /// A track through `keyframes` whose positions may turn a corner at a keyframe on one of
    /// `breaks`: the curve is C1 between breaks and only continuous at them (tangents are taken
    /// from each side alone). The decoder's motion bends sharply at context frame times, where
    /// what it attends to changes; a cubic smoothed across such a corner overshoots on both sides.
    pub fn with_breaks(keyframes: Vec<(f64, GaussianSet)>, breaks: &[f64]) -> Result<Self> {
        if keyframes.is_empty() {
            return Err(EngineError::InvalidInput(
                "a keyframe track needs at least one keyframe".to_owned(),
            ));
        }
        let mut breaks: Vec<f64> = breaks.iter().copied().filter(|t| t.is_finite()).collect();
        breaks.sort_by(f64::total_cmp);
        let mut track = Self {
            breaks,
            ..Self::default()
        };
        track.insert(keyframes)?;
        Ok(track)
    }

    /// Adds keyframes (a time already present keeps its set) and recomputes the tangents.
    pub fn insert(&mut self, keyframes: Vec<(f64, GaussianSet)>) -> Result<()> {
        for (t, set) in keyframes {
            if !t.is_finite() {
                return Err(EngineError::NonFiniteTime {
                    what: "keyframe",
                    value: t,
                });
            }
            let t = t + 0.0;
            if let Some(first) = self.sets.first() {
                let width = |s: &GaussianSet| s.features().map(FeatureBlock::width);
                if set.len() != first.len() || width(&set) != width(first) {
                    return Err(EngineError::InvalidInput(format!(
                        "keyframes must hold the same Gaussians: {} with features {:?} against {} with {:?}",
                        set.len(),
                        width(&set),
                        first.len(),
                        width(first)
                    )));
                }
            }
            let at = self.times.partition_point(|&x| x < t);
            if self.times.get(at) != Some(&t) {
                self.times.insert(at, t);
                self.sets.insert(at, set);
            }
        }
        (self.out_tangents, self.in_tangents) =
            position_tangents(&self.times, &self.sets, &self.breaks);
        Ok(())
    }

    /// Keyframe times, increasing.
    pub fn times(&self) -> &[f64] {
        &self.times
    }

    /// The exact sets, in the order of [`times`](Self::times).
    pub fn sets(&self) -> &[GaussianSet] {
        &self.sets
    }

    /// Number of keyframes.
    pub fn len(&self) -> usize {
        self.times.len()
    }

    /// True when the track has no keyframes.
    pub fn is_empty(&self) -> bool {
        self.times.is_empty()
    }

    /// The first and last keyframe time: where [`at`](Self::at) is defined.
    pub fn span(&self) -> Option<(f64, f64)> {
        Some((*self.times.first()?, *self.times.last()?))
    }

    /// The exact set at `t`, when `t` is a keyframe time.
    pub fn keyframe(&self, t: f64) -> Option<&GaussianSet> {
        let t = t + 0.0;
        let at = self.times.partition_point(|&x| x < t);
        (self.times.get(at) == Some(&t)).then(|| &self.sets[at])
    }

    /// The set at `t`: the keyframe's own at a keyframe time, else interpolated from the two
    /// keyframes around it. Fails outside [`span`](Self::span).
    pub fn at(&self, t: f64) -> Result<GaussianSet> {
        if !t.is_finite() {
            return Err(EngineError::NonFiniteTime {
                what: "target",
                value: t,
            });
        }
        let Some((first, last)) = self.span() else {
            return Err(EngineError::InvalidInput(
                "the keyframe track is empty".to_owned(),
            ));
        };
        if t < first || t > last {
            return Err(EngineError::InvalidInput(format!(
                "t = {t} is outside the keyframes' span [{first}, {last}]"
            )));
        }
        if let Some(set) = self.keyframe(t) {
            return Ok(set.clone());
        }
        // first < t < last and t is no keyframe: keyframes k and k + 1 bracket it.
        let k = self.times.partition_point(|&x| x < t) - 1;
        let h = self.times[k + 1] - self.times[k];
        let s = (t - self.times[k]) / h;
        interpolate(
            [&self.sets[k], &self.sets[k + 1]],
            [&self.out_tangents[k], &self.in_tangents[k + 1]],
            h,
            s,
        )
    }
}

/// Decides the keyframes for `targets` (seconds, any order), decodes them exactly with `decode`
/// (called once per batch of times it wants, each call answering one set per time in order), and
/// returns the track through them. The track spans every target. `breaks` are the times where
/// the motion may turn a corner (the encoding's context times, for a decoder): the track does
/// not smooth across a keyframe on one ([`KeyframeTrack::with_breaks`]), and the adaptive mode
/// starts from the breaks inside the range as well as its ends.
///
/// For [`Keyframes::Exact`] the keyframes are the distinct targets themselves.
pub fn plan_keyframes(
    targets: &[f64],
    keyframes: &Keyframes,
    breaks: &[f64],
    mut decode: impl FnMut(&[f64]) -> Result<Vec<GaussianSet>>,
) -> Result<(KeyframeTrack, KeyframeStats)> {
    keyframes.validate()?;
    let distinct = distinct_times(targets)?;
    let Some((&start, &end)) = distinct.first().zip(distinct.last()) else {
        return Err(EngineError::InvalidInput(
            "keyframed decoding needs at least one target time".to_owned(),
        ));
    };
    let mut run = Decodes {
        decode: &mut decode,
        stats: KeyframeStats::default(),
    };
    let mut through = |times: &[f64]| KeyframeTrack::with_breaks(run.decode(times)?, breaks);
    let track = match *keyframes {
        _ if !keyframes.interpolates(&distinct) => through(&distinct)?,
        Keyframes::Every { seconds } => {
            through(&snap(every_times(start, end, seconds), &distinct))?
        }
        Keyframes::Count { n } => through(&snap(count_times(start, end, n), &distinct))?,
        Keyframes::Adaptive {
            tolerance,
            color_tolerance,
            max_keyframes,
            min_interval,
        } => {
            // The range's ends and the breaks inside it: the corners are where a smooth curve
            // fails first, and no check between two keyframes would find one.
            let mut initial = vec![start, end];
            initial.extend(breaks.iter().copied().filter(|&t| start < t && t < end));
            let initial = snap(distinct_times(&initial)?, &distinct);
            if initial.len() >= distinct.len() || initial.len() > max_keyframes {
                through(&distinct)?
            } else {
                let check = Check {
                    tolerance,
                    color_tolerance,
                    max_keyframes,
                    min_interval,
                };
                let track = through(&initial)?;
                refine(track, &distinct, &check, &mut run)?
            }
        }
        Keyframes::Exact => through(&distinct)?,
    };
    let mut stats = run.stats;
    stats.keyframe_times = track.times().to_vec();
    Ok((track, stats))
}

impl Engine {
    /// Decodes the Gaussians at each target time (any order, as [`decode`](Self::decode)): with
    /// [`Keyframes::Exact`] exactly as `decode` does; otherwise exactly at keyframes chosen by
    /// `keyframes` and interpolated per Gaussian in between (see [`crate::keyframes`]).
    pub fn decode_keyframed(
        &self,
        encoding: &Encoding,
        targets: &[f64],
        keyframes: &Keyframes,
    ) -> Result<(Vec<GaussianSet>, KeyframeStats)> {
        self.decode_keyframed_on(encoding, targets, keyframes, None)
    }

    /// [`decode_keyframed`](Self::decode_keyframed) on the queries `queries` alone, when given
    /// (every exact decode is [`decode_subset`](Self::decode_subset)'s).
    pub fn decode_keyframed_on(
        &self,
        encoding: &Encoding,
        targets: &[f64],
        keyframes: &Keyframes,
        queries: Option<&QuerySubset>,
    ) -> Result<(Vec<GaussianSet>, KeyframeStats)> {
        keyframes.validate()?;
        let batch = self.decode_batch_size(encoding.frame_count()).max(1);
        let distinct = distinct_times(targets)?;
        if !keyframes.interpolates(targets) {
            let sets = self.decode_on(encoding, targets, queries)?;
            let stats = KeyframeStats {
                exact_decodes: targets.len(),
                decoder_runs: targets.len().div_ceil(batch),
                keyframe_times: distinct,
                ..KeyframeStats::default()
            };
            return Ok((sets, stats));
        }
        let (track, mut stats) = self.keyframe_track_on(encoding, targets, keyframes, queries)?;
        let sets = targets
            .iter()
            .map(|&t| track.at(t))
            .collect::<Result<Vec<_>>>()?;
        stats.interpolated = targets
            .iter()
            .filter(|&&t| track.keyframe(t).is_none())
            .count();
        Ok((sets, stats))
    }

    /// The keyframes `keyframes` chooses for `targets`, decoded exactly, as a track to
    /// interpolate from ([`KeyframeTrack::at`]): for callers that interpolate later or piece by
    /// piece, such as a stream. With [`Keyframes::Exact`] the keyframes are the distinct targets.
    pub fn keyframe_track(
        &self,
        encoding: &Encoding,
        targets: &[f64],
        keyframes: &Keyframes,
    ) -> Result<(KeyframeTrack, KeyframeStats)> {
        self.keyframe_track_on(encoding, targets, keyframes, None)
    }

    /// [`keyframe_track`](Self::keyframe_track) on the queries `queries` alone, when given.
    pub fn keyframe_track_on(
        &self,
        encoding: &Encoding,
        targets: &[f64],
        keyframes: &Keyframes,
        queries: Option<&QuerySubset>,
    ) -> Result<(KeyframeTrack, KeyframeStats)> {
        let batch = self.decode_batch_size(encoding.frame_count()).max(1);
        let mut runs = 0;
        let (track, mut stats) = plan_keyframes(targets, keyframes, encoding.times(), |times| {
            runs += times.len().div_ceil(batch);
            self.decode_on(encoding, times, queries)
        })?;
        stats.decoder_runs = runs;
        Ok((track, stats))
    }
}

/// The caller's decoder and what it has cost so far.
struct Decodes<'a, F> {
    decode: &'a mut F,
    stats: KeyframeStats,
}

impl<F: FnMut(&[f64]) -> Result<Vec<GaussianSet>>> Decodes<'_, F> {
    fn decode(&mut self, times: &[f64]) -> Result<Vec<(f64, GaussianSet)>> {
        if times.is_empty() {
            return Ok(Vec::new());
        }
        let sets = (self.decode)(times)?;
        if sets.len() != times.len() {
            return Err(EngineError::ModelOutput(format!(
                "asked for {} sets, the decoder gave {}",
                times.len(),
                sets.len()
            )));
        }
        self.stats.exact_decodes += times.len();
        Ok(times.iter().copied().zip(sets).collect())
    }
}

/// The adaptive mode's settings.
struct Check {
    tolerance: f64,
    color_tolerance: Option<f64>,
    max_keyframes: usize,
    min_interval: f64,
}

/// An interval between two keyframes still to be checked, and how badly its parent failed (the
/// order in which a short budget is spent).
#[derive(Debug, Clone, Copy)]
struct Interval {
    a: f64,
    b: f64,
    priority: f64,
}

/// Adaptive refinement of `track` (its keyframes adjacent times of `distinct`, sorted, or
/// breaks) until every interval between keyframes that holds targets passes its check.
fn refine<F: FnMut(&[f64]) -> Result<Vec<GaussianSet>>>(
    mut track: KeyframeTrack,
    distinct: &[f64],
    check: &Check,
    run: &mut Decodes<'_, F>,
) -> Result<KeyframeTrack> {
    let inside = |a: f64, b: f64| {
        let lo = distinct.partition_point(|&x| x <= a);
        let hi = distinct.partition_point(|&x| x < b);
        &distinct[lo..hi.max(lo)]
    };
    let mut pending: Vec<Interval> = track
        .times()
        .windows(2)
        .filter(|w| !inside(w[0], w[1]).is_empty())
        .map(|w| Interval {
            a: w[0],
            b: w[1],
            priority: f64::INFINITY,
        })
        .collect();
    while !pending.is_empty() {
        let mut room = check.max_keyframes.saturating_sub(track.len());
        if room == 0 {
            break;
        }
        // The worst intervals first, where the budget runs short.
        pending.sort_by(|x, y| y.priority.total_cmp(&x.priority));
        let mut next = Vec::new();
        let mut probes: Vec<(Interval, Vec<f64>)> = Vec::new();
        for iv in pending.drain(..) {
            let mut times = check_times(iv, inside(iv.a, iv.b), check.min_interval);
            if times.is_empty() {
                continue;
            }
            if room == 0 {
                next.push(iv);
                continue;
            }
            times.truncate(room);
            room -= times.len();
            probes.push((iv, times));
        }
        if probes.is_empty() {
            break;
        }
        let times: Vec<f64> = probes.iter().flat_map(|(_, t)| t.iter().copied()).collect();
        let decoded = run.decode(&times)?;
        run.stats.rounds += 1;
        let mut exact = decoded.iter().map(|(_, set)| set);
        for (iv, times) in &probes {
            // How many times over its tolerance the worst check's worse error is.
            let mut score = 0.0f64;
            for &t in times {
                let Some(set) = exact.next() else {
                    break;
                };
                let d = deviation(&track.at(t)?, set)?;
                score = score
                    .max(d.position / check.tolerance)
                    .max(check.color_tolerance.map_or(0.0, |c| d.appearance / c));
            }
            if score > 1.0 {
                let cuts: Vec<f64> = std::iter::once(iv.a)
                    .chain(times.iter().copied())
                    .chain(std::iter::once(iv.b))
                    .collect();
                for w in cuts.windows(2) {
                    if !inside(w[0], w[1]).is_empty() {
                        next.push(Interval {
                            a: w[0],
                            b: w[1],
                            priority: score,
                        });
                    }
                }
            }
        }
        track.insert(decoded)?;
        pending = next;
    }
    Ok(track)
}

/// Where an interval is checked: the requested times nearest its thirds (one when they are the
/// same), none closer than `min_interval` to its ends.
///
/// Not its midpoint: with three-point tangents the leading error of a Hermite segment is the
/// tangents' own error, `h·s(1−s)·(δ₀(1−s) − δ₁s)`, and on smooth motion the tangents at both
/// ends err alike (δ₀ ≈ δ₁), which leaves `h·δ·s(1−s)(1−2s)`: zero at the midpoint, largest near
/// s = 0.21 and 0.79. A midpoint check passed intervals whose error elsewhere was over the
/// tolerance (on c4g-tiny, and on a smooth synthetic scene); so did one check at a third, where a
/// mix of that term with the symmetric ones can cancel. Checks at both thirds see at least 77% of
/// the peak of every term (s(1−s), s(1−s)(1−2s), s²(1−s)²) and cannot both cancel. Requested
/// times rather than the exact thirds: the error is measured where a caller gets it, and every
/// check is a set the caller receives exactly, so no check is a wasted decode.
fn check_times(iv: Interval, inner: &[f64], min_interval: f64) -> Vec<f64> {
    let h = iv.b - iv.a;
    let mut times: Vec<f64> = [iv.a + h / 3.0, iv.a + 2.0 * h / 3.0]
        .into_iter()
        .filter_map(|aim| {
            let at = inner.partition_point(|&x| x < aim);
            [at.checked_sub(1), Some(at)]
                .into_iter()
                .flatten()
                .filter_map(|i| inner.get(i).copied())
                .min_by(|x, y| (x - aim).abs().total_cmp(&(y - aim).abs()))
        })
        .filter(|&t| t - iv.a >= min_interval && iv.b - t >= min_interval)
        .collect();
    times.dedup();
    times
}

/// The finite targets, sorted, without repeats (`-0` is `0`).
fn distinct_times(targets: &[f64]) -> Result<Vec<f64>> {
    if let Some(&value) = targets.iter().find(|t| !t.is_finite()) {
        return Err(EngineError::NonFiniteTime {
            what: "target",
            value,
        });
    }
    let mut times: Vec<f64> = targets.iter().map(|t| t + 0.0).collect();
    times.sort_by(f64::total_cmp);
    times.dedup();
    Ok(times)
}

/// Keyframes every `seconds` over `[start, end]`, counted: the intervals the range needs (a
/// rounding hair over a whole number does not add one), plus one.
fn every_count(start: f64, end: f64, seconds: f64) -> usize {
    let intervals = ((end - start) / seconds * (1.0 - 1e-12)).ceil();
    if intervals >= (usize::MAX / 2) as f64 {
        usize::MAX
    } else {
        intervals as usize + 1
    }
}

/// Keyframes every `seconds` from `start`, and `end` itself last.
fn every_times(start: f64, end: f64, seconds: f64) -> Vec<f64> {
    let n = every_count(start, end, seconds);
    let mut times: Vec<f64> = (0..n.saturating_sub(1))
        .map(|k| start + seconds * k as f64)
        .filter(|&t| t < end)
        .collect();
    times.push(end);
    times
}

/// `n` keyframes spread evenly over `[start, end]`, both ends exact.
fn count_times(start: f64, end: f64, n: usize) -> Vec<f64> {
    if start == end {
        return vec![start];
    }
    (0..n)
        .map(|i| match i {
            0 => start,
            _ if i == n - 1 => end,
            _ => (start + (end - start) * i as f64 / (n - 1) as f64).min(end),
        })
        .collect()
}

/// Moves each keyframe onto a target within rounding of it, so that the target gets the exact
/// set (evenly spaced targets and keyframes meet at such times).
fn snap(mut times: Vec<f64>, targets: &[f64]) -> Vec<f64> {
    let (start, end) = (targets[0], targets[targets.len() - 1]);
    let eps = 1e-9 * (end - start).abs().max(f64::MIN_POSITIVE);
    for t in &mut times {
        let at = targets.partition_point(|&x| x < *t);
        let nearest = [at.checked_sub(1), Some(at)]
            .into_iter()
            .flatten()
            .filter_map(|i| targets.get(i).copied())
            .min_by(|a, b| (a - *t).abs().total_cmp(&(b - *t).abs()));
        if let Some(target) = nearest
            && (target - *t).abs() <= eps
        {
            *t = target;
        }
    }
    times.dedup();
    times
}

/// Tangents leaving and arriving at every keyframe: Bessel tangents within each piece between
/// keyframes on breaks.
type Tangents = Vec<Vec<[f64; 3]>>;

fn position_tangents(times: &[f64], sets: &[GaussianSet], breaks: &[f64]) -> (Tangents, Tangents) {
    let k = times.len();
    let Some((&first, &last)) = times.first().zip(times.last()) else {
        return (Vec::new(), Vec::new());
    };
    let eps = 1e-9 * (last - first).abs().max(1e-300);
    let on_break = |t: f64| {
        let at = breaks.partition_point(|&b| b < t - eps);
        breaks.get(at).is_some_and(|&b| (b - t).abs() <= eps)
    };
    let mut cuts: Vec<usize> = (1..k.saturating_sub(1))
        .filter(|&i| on_break(times[i]))
        .collect();
    cuts.insert(0, 0);
    cuts.push(k - 1);
    let mut out_tangents = vec![Vec::new(); k];
    let mut in_tangents = vec![Vec::new(); k];
    for piece in cuts.windows(2) {
        let (i0, i1) = (piece[0], piece[1]);
        let tangents = bessel_tangents(&times[i0..=i1], &sets[i0..=i1]);
        for (j, m) in tangents.into_iter().enumerate() {
            let i = i0 + j;
            if i > i0 || i0 == i1 {
                in_tangents[i] = m.clone();
            }
            if i < i1 || i0 == i1 {
                out_tangents[i] = m;
            }
        }
    }
    (out_tangents, in_tangents)
}

/// Bessel tangents of every Gaussian's position at every keyframe of one smooth piece.
fn bessel_tangents(times: &[f64], sets: &[GaussianSet]) -> Vec<Vec<[f64; 3]>> {
    let k = times.len();
    let n = sets.first().map_or(0, GaussianSet::len);
    if k < 2 {
        return vec![vec![[0.0; 3]; n]; k];
    }
    let h: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    let slope = |j: usize, i: usize, axis: usize| {
        let (a, b) = (
            sets[j].positions()[i][axis],
            sets[j + 1].positions()[i][axis],
        );
        (f64::from(b) - f64::from(a)) / h[j]
    };
    (0..k)
        .map(|key| {
            (0..n)
                .map(|i| {
                    std::array::from_fn(|axis| {
                        let d = |j: usize| slope(j, i, axis);
                        match key {
                            _ if k == 2 => d(0),
                            0 => ((2.0 * h[0] + h[1]) * d(0) - h[0] * d(1)) / (h[0] + h[1]),
                            _ if key == k - 1 => {
                                let (l, p) = (k - 2, k - 3);
                                ((2.0 * h[l] + h[p]) * d(l) - h[l] * d(p)) / (h[l] + h[p])
                            }
                            _ => {
                                let (l, r) = (key - 1, key);
                                (h[r] * d(l) + h[l] * d(r)) / (h[l] + h[r])
                            }
                        }
                    })
                })
                .collect()
        })
        .collect()
}

/// The cubic Hermite segment from `p0` (tangent `m0`) to `p1` (tangent `m1`) over an interval of
/// length `h`, at fraction `s`: `p0` at 0 and `p1` at 1.
pub fn hermite(p0: f64, m0: f64, p1: f64, m1: f64, h: f64, s: f64) -> f64 {
    let (s2, r) = (s * s, 1.0 - s);
    let r2 = r * r;
    (1.0 + 2.0 * s) * r2 * p0
        + s * r2 * h * m0
        + s2 * (3.0 - 2.0 * s) * p1
        + s2 * (s - 1.0) * h * m1
}

/// Spherical linear interpolation of unit quaternions (`[w, x, y, z]`) along the shorter arc,
/// normalised; `a` at 0, `b` (or `-b`) at 1.
pub fn slerp(a: [f32; 4], b: [f32; 4], s: f64) -> [f32; 4] {
    if a == b {
        return a;
    }
    let (a, mut b) = (unit(a), unit(b));
    let mut dot: f64 = (0..4).map(|k| a[k] * b[k]).sum();
    if dot < 0.0 {
        b = b.map(|v| -v);
        dot = -dot;
    }
    let (wa, wb) = if dot > 0.9995 {
        // Nearly parallel: sin θ is too small to divide by, and the arc is a straight line.
        (1.0 - s, s)
    } else {
        let theta = dot.min(1.0).acos();
        let sin = theta.sin();
        (((1.0 - s) * theta).sin() / sin, (s * theta).sin() / sin)
    };
    let q: [f64; 4] = std::array::from_fn(|k| wa * a[k] + wb * b[k]);
    unit_f64(q).map(|v| v as f32)
}

/// Geometric interpolation of two non-negative scales (linear in log space), within the two
/// values; linear where one of them is 0 (models flatten Gaussians to exactly 0 along an axis, and
/// 0 has no logarithm).
pub fn log_lerp(a: f32, b: f32, s: f64) -> f32 {
    if a == b {
        return a;
    }
    if a <= 0.0 || b <= 0.0 {
        return lerp(a, b, s);
    }
    let (lo, hi) = (a.min(b), a.max(b));
    let v = ((1.0 - s) * f64::from(a).ln() + s * f64::from(b).ln()).exp();
    (v as f32).clamp(lo, hi)
}

/// Linear interpolation, kept within the two values (rounding must not push an opacity past 1).
pub fn lerp(a: f32, b: f32, s: f64) -> f32 {
    if a == b {
        return a;
    }
    let (lo, hi) = (a.min(b), a.max(b));
    let v = f64::from(a) + s * (f64::from(b) - f64::from(a));
    (v as f32).clamp(lo, hi)
}

/// The set between keyframes `sets[0]` and `sets[1]` (with their position tangents), `h` apart,
/// at fraction `s`.
fn interpolate(
    sets: [&GaussianSet; 2],
    tangents: [&[[f64; 3]]; 2],
    h: f64,
    s: f64,
) -> Result<GaussianSet> {
    let [a, b] = sets;
    let n = a.len();
    let mut positions = Vec::with_capacity(n);
    let mut scales = Vec::with_capacity(n);
    let mut rotations = Vec::with_capacity(n);
    let mut opacities = Vec::with_capacity(n);
    let mut colors = Vec::with_capacity(n);
    for (i, (ma, mb)) in tangents[0].iter().zip(tangents[1]).enumerate() {
        let (pa, pb) = (a.positions()[i], b.positions()[i]);
        positions.push(std::array::from_fn(|k| {
            if pa[k] == pb[k] && ma[k] == 0.0 && mb[k] == 0.0 {
                return pa[k];
            }
            hermite(f64::from(pa[k]), ma[k], f64::from(pb[k]), mb[k], h, s) as f32
        }));
        let (sa, sb) = (a.scales()[i], b.scales()[i]);
        scales.push(std::array::from_fn(|k| log_lerp(sa[k], sb[k], s)));
        rotations.push(slerp(a.rotations()[i], b.rotations()[i], s));
        opacities.push(lerp(a.opacities()[i], b.opacities()[i], s));
        let (ca, cb) = (a.colors()[i], b.colors()[i]);
        colors.push(std::array::from_fn(|k| lerp(ca[k], cb[k], s)));
    }
    let invalid = |e: c4g_scene::SceneError| EngineError::ModelOutput(e.to_string());
    let set = GaussianSet::new(positions, scales, rotations, opacities, colors).map_err(invalid)?;
    match (a.features(), b.features()) {
        (Some(fa), Some(fb)) => {
            let values = fa
                .values()
                .iter()
                .zip(fb.values())
                .map(|(&x, &y)| lerp(x, y, s))
                .collect();
            let block = FeatureBlock::new(fa.width(), values).map_err(invalid)?;
            set.with_features(block).map_err(invalid)
        }
        _ => Ok(set),
    }
}

fn unit(q: [f32; 4]) -> [f64; 4] {
    unit_f64(q.map(f64::from))
}

fn unit_f64(q: [f64; 4]) -> [f64; 4] {
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm > 0.0 && norm.is_finite() {
        q.map(|v| v / norm)
    } else {
        [1.0, 0.0, 0.0, 0.0]
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use super::*;

    const N: usize = 6;

    /// A scene that moves smoothly and in every attribute: Gaussian `i` at time `t`.
    fn scene(t: f64) -> GaussianSet {
        let (mut p, mut sc, mut q, mut o, mut c) = (vec![], vec![], vec![], vec![], vec![]);
        for i in 0..N {
            let f = i as f64;
            p.push([(t + f).sin(), (2.0 * t).cos() + f, 2.0 + 0.1 * t * t].map(|v| v as f32));
            sc.push([0.01 * (1.0 + f), 0.05 * (0.3 * t).exp(), 0.02].map(|v| v as f32));
            let half = 0.5 * (t + 0.2 * f);
            q.push([half.cos(), 0.0, 0.0, half.sin()].map(|v| v as f32));
            o.push((0.5 + 0.4 * (t + f).sin()) as f32);
            c.push([0.5 + 0.3 * t.sin(), 0.2, 0.8 - 0.1 * t].map(|v| v as f32));
        }
        GaussianSet::new(p, sc, q, o, c).unwrap()
    }

    /// A scene whose positions follow `p(t) = a + v t + g t² / 2` and nothing else changes.
    fn accelerating(t: f64) -> GaussianSet {
        let positions = (0..N)
            .map(|i| {
                let f = i as f64;
                [1.0 + 0.5 * t - 0.3 * t * t, f - 0.25 * t, 2.0 + 0.8 * t * t].map(|v| v as f32)
            })
            .collect();
        GaussianSet::new(
            positions,
            vec![[0.1; 3]; N],
            vec![[1.0, 0.0, 0.0, 0.0]; N],
            vec![0.5; N],
            vec![[0.2, 0.4, 0.6]; N],
        )
        .unwrap()
    }

    fn track(times: &[f64], scene: fn(f64) -> GaussianSet) -> KeyframeTrack {
        KeyframeTrack::new(times.iter().map(|&t| (t, scene(t))).collect()).unwrap()
    }

    fn decoder(scene: fn(f64) -> GaussianSet) -> impl FnMut(&[f64]) -> Result<Vec<GaussianSet>> {
        move |times| Ok(times.iter().map(|&t| scene(t)).collect())
    }

    fn even(lo: f64, hi: f64, n: usize) -> Vec<f64> {
        (0..n)
            .map(|i| lo + (hi - lo) * i as f64 / (n - 1) as f64)
            .collect()
    }

    #[test]
    fn the_ends_of_the_span_are_the_keyframes_and_outside_it_is_an_error() {
        let track = track(&[0.0, 0.4, 1.5, 2.0], scene);
        assert_eq!(track.at(0.0).unwrap(), scene(0.0));
        assert_eq!(track.at(2.0).unwrap(), scene(2.0));
        assert_eq!(track.at(0.4).unwrap(), scene(0.4));
        assert_eq!(track.at(-0.0).unwrap(), scene(0.0));
        assert!(track.at(-1e-9).is_err());
        assert!(track.at(2.0 + 1e-9).is_err());
        assert!(track.at(f64::NAN).is_err());
        assert_eq!(track.span(), Some((0.0, 2.0)));
    }

    #[test]
    fn two_keyframes_interpolate_linearly() {
        let track = track(&[1.0, 3.0], accelerating);
        let (a, b) = (accelerating(1.0), accelerating(3.0));
        for s in [0.1, 0.25, 0.5, 0.9] {
            let set = track.at(1.0 + 2.0 * s).unwrap();
            for i in 0..N {
                for k in 0..3 {
                    let (pa, pb) = (
                        f64::from(a.positions()[i][k]),
                        f64::from(b.positions()[i][k]),
                    );
                    let linear = pa + s * (pb - pa);
                    assert!((f64::from(set.positions()[i][k]) - linear).abs() < 1e-6);
                }
            }
        }
    }

    #[test]
    fn a_set_that_does_not_change_interpolates_to_itself_exactly() {
        let still = |_: f64| scene(0.7);
        let track =
            KeyframeTrack::new([0.0, 0.3, 1.7, 2.0].map(|t| (t, still(t))).to_vec()).unwrap();
        for t in [0.01, 0.15, 0.31, 1.0, 1.99] {
            assert_eq!(track.at(t).unwrap(), scene(0.7), "t = {t}");
        }
    }

    #[test]
    fn positions_pass_through_every_keyframe_and_reproduce_constant_acceleration() {
        // Uneven spacing, as adaptive refinement leaves it.
        let track = track(&[0.0, 0.3, 1.0, 1.1, 2.0], accelerating);
        for t in [0.05, 0.2, 0.3, 0.64, 1.05, 1.5, 1.97] {
            let d = deviation(&track.at(t).unwrap(), &accelerating(t)).unwrap();
            assert!(d.position < 2e-6, "t = {t}: {d:?}");
        }
        for (p0, m0, p1, m1, h) in [(1.5, -3.0, 2.0, 7.0, 0.1), (-4.0, 0.0, 1e3, 1e-3, 5.0)] {
            assert_eq!(hermite(p0, m0, p1, m1, h, 0.0), p0);
            assert_eq!(hermite(p0, m0, p1, m1, h, 1.0), p1);
        }
    }

    #[test]
    fn a_corner_on_a_break_is_kept_and_not_smoothed_over() {
        // Depth falls until t = 1, then rises: a V, as the decoder moves Gaussians around a
        // context time.
        let v = |t: f64| {
            let set = accelerating(0.0);
            let depth = (2.0 + (t - 1.0).abs()) as f32;
            GaussianSet::new(
                set.positions()
                    .iter()
                    .map(|p| [p[0], p[1], depth])
                    .collect(),
                set.scales().to_vec(),
                set.rotations().to_vec(),
                set.opacities().to_vec(),
                set.colors().to_vec(),
            )
            .unwrap()
        };
        let keys = || [0.0, 0.5, 1.0, 1.5, 2.0].map(|t| (t, v(t))).to_vec();
        let broken = KeyframeTrack::with_breaks(keys(), &[1.0]).unwrap();
        let smooth = KeyframeTrack::new(keys()).unwrap();
        for t in [0.2, 0.75, 0.9, 1.1, 1.6] {
            let d = deviation(&broken.at(t).unwrap(), &v(t)).unwrap();
            assert!(d.position < 1e-6, "t = {t}: {d:?}");
        }
        let overshoot = deviation(&smooth.at(0.9).unwrap(), &v(0.9)).unwrap();
        assert!(overshoot.position > 0.01, "{overshoot:?}");
    }

    #[test]
    fn slerp_takes_the_short_arc_across_a_sign_flip() {
        let about_z = |degrees: f64| {
            let half = degrees.to_radians() / 2.0;
            [half.cos(), 0.0, 0.0, half.sin()].map(|v| v as f32)
        };
        // -q is the same rotation as q: the way from 10° to 30° is 20° long, not 340°.
        let a = about_z(10.0);
        let b = about_z(30.0).map(|v| -v);
        let mid = slerp(a, b, 0.5);
        let want = about_z(20.0);
        let dot: f32 = (0..4).map(|k| mid[k] * want[k]).sum();
        assert!(dot.abs() > 1.0 - 1e-6, "{mid:?}");
        assert!(dot > 0.0, "slerp keeps the first quaternion's hemisphere");
        let norm: f32 = mid.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-6);
        assert_eq!(slerp(a, b, 0.0), a);
        // Nearly equal rotations take the normalised-lerp path, still unit.
        let close = slerp(about_z(10.0), about_z(10.001), 0.5);
        assert!((close.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn log_space_scales_stay_positive_and_meet_at_the_geometric_mean() {
        let mid = log_lerp(1e-6, 10.0, 0.5);
        assert!((f64::from(mid) - 1e-5f64.sqrt()).abs() < 1e-8, "{mid}");
        for s in [1e-9, 0.3, 0.999_999] {
            let v = log_lerp(1e-30, 1e3, s);
            assert!(v > 0.0 && v.is_finite(), "{s}: {v}");
        }
        // From or to exactly 0 (a flattened axis): linear, never negative.
        assert_eq!(log_lerp(0.0, 0.2, 0.5), 0.1);
        assert_eq!(log_lerp(0.0, 0.0, 0.5), 0.0);
    }

    #[test]
    fn interpolated_sets_are_valid_and_features_are_linear() {
        let with = |t: f64| {
            let values = (0..N * 2).map(|k| k as f32 * t as f32).collect();
            scene(t)
                .with_features(FeatureBlock::new(2, values).unwrap())
                .unwrap()
        };
        let track = KeyframeTrack::new(vec![(0.0, with(0.0)), (2.0, with(2.0))]).unwrap();
        let set = track.at(0.5).unwrap();
        set.validate().unwrap();
        assert_eq!(set.features().unwrap().row(3), Some(&[3.0, 3.5][..]));
        let mixed = KeyframeTrack::new(vec![(0.0, with(0.0)), (1.0, scene(1.0))]);
        assert!(mixed.is_err());
    }

    #[test]
    fn uniform_plans_decode_their_keyframes_once_each() {
        let targets = even(0.0, 2.0, 41);
        let (track, stats) =
            plan_keyframes(&targets, &Keyframes::Count { n: 5 }, &[], decoder(scene)).unwrap();
        assert_eq!(track.times(), &[0.0, 0.5, 1.0, 1.5, 2.0]);
        assert_eq!(stats.exact_decodes, 5);
        let (track, _) = plan_keyframes(
            &targets,
            &Keyframes::Every { seconds: 0.3 },
            &[],
            decoder(scene),
        )
        .unwrap();
        assert_eq!(track.len(), 8);
        assert_eq!(track.span(), Some((0.0, 2.0)));
        assert!((track.times()[6] - 1.8).abs() < 1e-12);
        // As many keyframes as targets or more: the targets themselves.
        let (track, stats) = plan_keyframes(
            &[0.5, 0.1, 0.5],
            &Keyframes::Count { n: 8 },
            &[],
            decoder(scene),
        )
        .unwrap();
        assert_eq!((track.times(), stats.exact_decodes), (&[0.1, 0.5][..], 2));
    }

    #[test]
    fn adaptive_plans_meet_their_tolerance_with_fewer_decodes() {
        let targets = even(0.0, 3.0, 200);
        for tolerance in [0.05, 0.01, 0.001] {
            let keyframes = Keyframes::adaptive(tolerance, 200);
            let (track, stats) = plan_keyframes(&targets, &keyframes, &[], decoder(scene)).unwrap();
            let worst = targets
                .iter()
                .map(|&t| {
                    deviation(&track.at(t).unwrap(), &scene(t))
                        .unwrap()
                        .position
                })
                .fold(0.0, f64::max);
            assert!(worst <= tolerance, "{tolerance}: {worst}");
            assert!(
                stats.exact_decodes < targets.len() / 2,
                "{tolerance}: {stats:?}"
            );
            assert_eq!(stats.keyframe_times, track.times());
        }
        // A colour tolerance refines further than positions alone.
        let loose = plan_keyframes(
            &targets,
            &Keyframes::adaptive(1.0, 200),
            &[],
            decoder(scene),
        );
        let colored = Keyframes::Adaptive {
            tolerance: 1.0,
            color_tolerance: Some(0.001),
            max_keyframes: 200,
            min_interval: 0.0,
        };
        let strict = plan_keyframes(&targets, &colored, &[], decoder(scene));
        assert!(strict.unwrap().1.exact_decodes > loose.unwrap().1.exact_decodes);
    }

    #[test]
    fn adaptive_checks_are_requested_times_so_they_never_cost_more_than_exact() {
        // Sparse, uneven targets and a tolerance the motion cannot meet.
        let targets = [0.0, 0.05, 0.4, 0.45, 1.3, 2.0, 2.1, 2.95, 3.0];
        let (track, stats) = plan_keyframes(
            &targets,
            &Keyframes::adaptive(1e-12, 64),
            &[],
            decoder(scene),
        )
        .unwrap();
        assert_eq!(track.times(), targets);
        assert_eq!(stats.exact_decodes, targets.len());
        for &t in &targets {
            assert_eq!(track.at(t).unwrap(), scene(t));
        }
    }

    #[test]
    fn adaptive_plans_stop_at_their_bounds() {
        let targets = even(0.0, 3.0, 200);
        let capped = Keyframes::adaptive(1e-9, 9);
        let (_, stats) = plan_keyframes(&targets, &capped, &[], decoder(scene)).unwrap();
        assert_eq!(stats.exact_decodes, 9);
        let coarse = Keyframes::Adaptive {
            tolerance: 1e-9,
            color_tolerance: None,
            max_keyframes: 200,
            min_interval: 0.5,
        };
        let (track, _) = plan_keyframes(&targets, &coarse, &[], decoder(scene)).unwrap();
        assert!(
            track.times().windows(2).all(|w| w[1] - w[0] >= 0.5),
            "{:?}",
            track.times()
        );
        let still = |_: f64| scene(1.0);
        let (_, stats) = plan_keyframes(
            &targets,
            &Keyframes::adaptive(1e-6, 64),
            &[],
            decoder(still),
        )
        .unwrap();
        // A motionless scene passes its first checks: the ends and the two thirds.
        assert_eq!(stats.exact_decodes, 4);
    }

    #[test]
    fn bad_options_and_times_are_refused() {
        for bad in [
            Keyframes::Every { seconds: 0.0 },
            Keyframes::Every { seconds: f64::NAN },
            Keyframes::Count { n: 1 },
            Keyframes::adaptive(-1.0, 8),
            Keyframes::adaptive(f64::INFINITY, 8),
            Keyframes::adaptive(0.1, 1),
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
            assert!(plan_keyframes(&[0.0, 1.0], &bad, &[], decoder(scene)).is_err());
        }
        let nan = plan_keyframes(
            &[0.0, f64::NAN],
            &Keyframes::Count { n: 2 },
            &[],
            decoder(scene),
        );
        assert!(matches!(nan, Err(EngineError::NonFiniteTime { .. })));
        assert_eq!(
            Keyframes::Every { seconds: 0.5 }.max_keyframes(0.0, 2.0),
            Some(5)
        );
        assert_eq!(
            Keyframes::Every { seconds: 0.5 }.max_keyframes(0.0, 2.1),
            Some(6)
        );
        assert_eq!(Keyframes::Exact.max_keyframes(0.0, 2.0), None);
        assert!(Keyframes::adaptive(0.0, 8).is_exact());
    }
}
