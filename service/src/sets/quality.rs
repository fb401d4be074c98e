//! How much accuracy a request trades for speed, as clients state it: a named preset
//! (`"quality": "fast"`), and the knobs it stands for, `keyframes` and `prune`, which a request may
//! also give itself (an explicit knob overrides the preset's). Resolved into an [`Approximation`].
//! `prune`'s `drop_queries` goes further than any preset: the pruned Gaussians' query tokens leave
//! the decoder itself, which is cheaper and changes the kept Gaussians (`docs/tradeoffs.md`).
//!
//! The presets are points on the Pareto front that `cargo bench -p c4g-engine --bench tradeoffs`
//! measures (`docs/tradeoffs.md` has the table, the plot and the rule that chose them); the
//! default, `exact`, changes nothing.

use std::sync::Arc;

use c4g_analysis::pruning::PruneOptions;
use c4g_engine::Keyframes;
use serde::{Deserialize, Serialize};

use crate::ServiceError;
use crate::clips::fitted::Fitted;
use crate::sets::keyframes::{self, KeyframesSpec};
use crate::sets::scene::Scene;

/// A named point of the speed/accuracy trade.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// Every set decoded exactly, every Gaussian returned: what the model computes.
    #[default]
    Exact,
    /// A keyframe every context spacing (the model's own context frames, where the requested
    /// range starts on one), every Gaussian: within 0.1 dB of exact against ground truth and
    /// 53 dB against exact on the measured scenes.
    Balanced,
    /// A keyframe every 1.5 context spacings, and the Gaussians that change no analysed view by
    /// half a pixel dropped: within 0.5 dB of exact against ground truth and 47 dB against exact
    /// on the measured scenes, and cheap enough to stream at thousands of sets a second.
    Fast,
}

impl Preset {
    /// The preset's name on the wire.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Exact => "exact",
            Preset::Balanced => "balanced",
            Preset::Fast => "fast",
        }
    }

    /// The keyframes this preset decodes with, for a clip whose context frames are
    /// `context_spacing` seconds apart (`None`: every set exact; a clip of one context frame
    /// has nothing to interpolate).
    pub fn keyframes(self, context_spacing: Option<f64>) -> Option<KeyframesSpec> {
        let every = |spacings: f64| {
            context_spacing.map(|spacing| KeyframesSpec {
                every_s: Some(spacings * spacing),
                ..KeyframesSpec::default()
            })
        };
        match self {
            Preset::Exact => None,
            Preset::Balanced => every(BALANCED_SPACINGS),
            Preset::Fast => every(FAST_SPACINGS),
        }
    }

    /// The pruning this preset applies (`None`: every Gaussian returned).
    pub fn prune(self) -> Option<PruneSpec> {
        match self {
            Preset::Exact | Preset::Balanced => None,
            Preset::Fast => Some(PruneSpec {
                contribution_px: Some(FAST_CONTRIBUTION_PX),
                opacity: None,
                drop_queries: None,
            }),
        }
    }
}

// The presets' values, chosen by the rules of docs/tradeoffs.md from its measurement (on
// c4g-tiny's test clips, whose context frames are 0.2 s apart: every 0.2 s and every 0.3 s).
const BALANCED_SPACINGS: f64 = 1.0;
const FAST_SPACINGS: f64 = 1.5;
const FAST_CONTRIBUTION_PX: f32 = 0.5;

/// The median gap between a clip's distinct context times (`None` with fewer than two).
pub fn context_spacing(context_times: &[f64]) -> Option<f64> {
    let mut times = context_times.to_vec();
    times.sort_by(f64::total_cmp);
    times.dedup();
    let mut gaps: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    gaps.sort_by(f64::total_cmp);
    gaps.get(gaps.len() / 2).copied().filter(|g| *g > 0.0)
}

/// Pruning as a client states it: drop the Gaussians that change nothing visible
/// (`{"contribution_px": 0.5}`; `{}` takes the defaults).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PruneSpec {
    /// Drop a Gaussian whose blending weights, summed over the pixels of every analysed view, stay
    /// under this many pixels (default 0.5). 0 keeps every visible Gaussian.
    pub contribution_px: Option<f32>,
    /// Drop a Gaussian whose opacity stays under this at every analysed time (default 1/255,
    /// below which the rasterizer skips it anyway). 0 keeps every Gaussian however faint.
    pub opacity: Option<f32>,
    /// Also drop the pruned Gaussians' query tokens from the decoder itself (default false):
    /// every decode runs on the kept queries alone, which is cheaper, but the kept Gaussians
    /// change, since queries attend to each other (measured in `docs/tradeoffs.md`). Needs a
    /// package whose decoder takes query indices (`decoder_query_subset`).
    pub drop_queries: Option<bool>,
}

impl PruneSpec {
    /// The floors, checked: finite and non-negative; an opacity floor at most 1.
    pub fn options(&self) -> Result<PruneOptions, ServiceError> {
        let defaults = PruneOptions::default();
        let contribution_floor = self.contribution_px.unwrap_or(defaults.contribution_floor);
        if !contribution_floor.is_finite() || contribution_floor < 0.0 {
            return Err(ServiceError::invalid(format!(
                "prune contribution_px must be a finite, non-negative number of pixels, got \
                 {contribution_floor}"
            )));
        }
        let opacity_floor = self.opacity.unwrap_or(defaults.opacity_floor);
        if !(0.0..=1.0).contains(&opacity_floor) {
            return Err(ServiceError::invalid(format!(
                "prune opacity must be between 0 and 1, got {opacity_floor}"
            )));
        }
        Ok(PruneOptions {
            opacity_floor,
            contribution_floor,
        })
    }
}

/// The trade a request asks for, as it states it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct QualitySpec {
    /// A named preset (default: exact).
    pub preset: Option<Preset>,
    /// Keyframes, overriding the preset's.
    pub keyframes: Option<KeyframesSpec>,
    /// Pruning, overriding the preset's.
    pub prune: Option<PruneSpec>,
    /// Which scene serves the request (default: auto).
    pub scene: Scene,
}

impl QualitySpec {
    /// Whether the request asks for an approximation of the model's answer (a preset other than
    /// exact, keyframes or pruning): what only the feed-forward scene serves.
    pub fn approximates(&self) -> bool {
        self.preset.is_some_and(|p| p != Preset::Exact)
            || self.keyframes.is_some()
            || self.prune.is_some()
    }
}

/// The trade a request gets, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct Approximation {
    /// Which sets are decoded exactly and which interpolated.
    pub keyframes: Keyframes,
    /// Which Gaussians are dropped (`None`: none).
    pub prune: Option<PruneOptions>,
    /// Whether the dropped Gaussians' queries leave the decoder too (only with `prune`).
    pub drop_queries: bool,
    /// The fitted scene that serves the request instead of the decoder (`None`: the model's).
    pub fitted: Option<Arc<Fitted>>,
}

impl Approximation {
    /// What the model computes: every set exact, every Gaussian.
    pub const EXACT: Approximation = Approximation {
        keyframes: Keyframes::Exact,
        prune: None,
        drop_queries: false,
        fitted: None,
    };

    /// Whether this is what the model computes (so it can be decoded in a batch with others'
    /// exact decodes).
    pub fn is_exact(&self) -> bool {
        matches!(self.keyframes, Keyframes::Exact) && self.prune.is_none() && self.fitted.is_none()
    }
}

/// The approximation `spec` asks for over `times` of a clip whose context frames are
/// `context_spacing` apart, checked against `max_times` (`C4G_MAX_TIMES`, which bounds the
/// keyframes).
pub fn resolve(
    spec: &QualitySpec,
    times: &[f64],
    max_times: usize,
    context_spacing: Option<f64>,
) -> Result<Approximation, ServiceError> {
    let preset = spec.preset.unwrap_or_default();
    let keyframes = spec.keyframes.or_else(|| preset.keyframes(context_spacing));
    let keyframes = keyframes::resolve(keyframes.as_ref(), times, max_times)?;
    let prune_spec = spec.prune.or_else(|| preset.prune());
    let prune = prune_spec.map(|p| p.options()).transpose()?;
    let drop_queries = prune_spec.and_then(|p| p.drop_queries).unwrap_or(false);
    Ok(Approximation {
        keyframes,
        prune,
        drop_queries,
        fitted: None,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    const TIMES: [f64; 5] = [0.0, 0.1, 0.25, 0.4, 0.5];
    const SPACING: Option<f64> = Some(0.2);

    #[test]
    fn no_preset_is_exact() {
        let approx = resolve(&QualitySpec::default(), &TIMES, 64, SPACING).unwrap();
        assert_eq!(approx, Approximation::EXACT);
        let exact = QualitySpec {
            preset: Some(Preset::Exact),
            ..QualitySpec::default()
        };
        assert_eq!(
            resolve(&exact, &TIMES, 64, SPACING).unwrap(),
            Approximation::EXACT
        );
    }

    #[test]
    fn presets_space_keyframes_by_the_context_and_fast_also_prunes() {
        for (preset, seconds) in [(Preset::Balanced, 0.2), (Preset::Fast, 0.3)] {
            let spec = QualitySpec {
                preset: Some(preset),
                ..QualitySpec::default()
            };
            let approx = resolve(&spec, &TIMES, 64, SPACING).unwrap();
            match approx.keyframes {
                Keyframes::Every { seconds: s } => assert!((s - seconds).abs() < 1e-12),
                other => panic!("{}: {other:?}", preset.name()),
            }
            assert_eq!(approx.prune.is_some(), preset == Preset::Fast);
        }
        // One context frame: nothing to interpolate, every set exact.
        let fast = QualitySpec {
            preset: Some(Preset::Fast),
            ..QualitySpec::default()
        };
        assert!(
            resolve(&fast, &TIMES, 64, None)
                .unwrap()
                .keyframes
                .is_exact()
        );
    }

    #[test]
    fn the_context_spacing_is_the_median_gap() {
        assert_eq!(context_spacing(&[0.0]), None);
        assert_eq!(context_spacing(&[0.6, 0.0, 0.2, 0.4]), Some(0.2));
        let uneven = context_spacing(&[0.0, 0.1, 0.3, 1.0, 1.0]).unwrap();
        assert!((uneven - 0.2).abs() < 1e-12, "{uneven}");
    }

    #[test]
    fn explicit_knobs_override_the_preset() {
        let spec = QualitySpec {
            preset: Some(Preset::Fast),
            keyframes: Some(KeyframesSpec {
                count: Some(2),
                ..KeyframesSpec::default()
            }),
            prune: Some(PruneSpec {
                contribution_px: Some(0.0),
                opacity: Some(0.0),
                drop_queries: None,
            }),
            scene: Scene::Auto,
        };
        assert!(spec.approximates());
        assert!(!QualitySpec::default().approximates());
        let approx = resolve(&spec, &TIMES, 64, SPACING).unwrap();
        assert_eq!(approx.keyframes, Keyframes::Count { n: 2 });
        let prune = approx.prune.unwrap();
        assert_eq!((prune.contribution_floor, prune.opacity_floor), (0.0, 0.0));
    }

    #[test]
    fn only_a_requests_own_prune_drops_queries() {
        let with = |preset, drop_queries: Option<bool>| QualitySpec {
            preset,
            prune: drop_queries.map(|d| PruneSpec {
                drop_queries: Some(d),
                ..PruneSpec::default()
            }),
            ..QualitySpec::default()
        };
        for (spec, drops) in [
            (with(None, Some(true)), true),
            (with(None, Some(false)), false),
            (with(Some(Preset::Fast), None), false),
            (with(Some(Preset::Fast), Some(true)), true),
        ] {
            let approx = resolve(&spec, &TIMES, 64, SPACING).unwrap();
            assert_eq!(approx.drop_queries, drops, "{spec:?}");
            assert!(approx.prune.is_some() || !approx.drop_queries);
            assert!(!approx.is_exact() || !drops);
        }
    }

    #[test]
    fn bad_floors_are_refused_with_their_name() {
        for (spec, name) in [
            (
                PruneSpec {
                    contribution_px: Some(-1.0),
                    opacity: None,
                    drop_queries: None,
                },
                "contribution_px",
            ),
            (
                PruneSpec {
                    contribution_px: Some(f32::NAN),
                    opacity: None,
                    drop_queries: None,
                },
                "contribution_px",
            ),
            (
                PruneSpec {
                    contribution_px: None,
                    opacity: Some(1.5),
                    drop_queries: None,
                },
                "opacity",
            ),
        ] {
            let error = spec.options().unwrap_err().to_string();
            assert!(error.contains(name), "{error}");
        }
    }
}
