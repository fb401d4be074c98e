//! `c4g decode`: the Gaussians at given times, summarised or written out.

use std::io::IsTerminal as _;
use std::path::{Path, PathBuf};

use anyhow::bail;
use c4g_client::{
    Approximation, GaussianFormat, GaussianFrame, Keyframes, Precision, Prune, Quality, Scene,
};
use indicatif::HumanBytes;
use serde_json::json;

use super::{Context, emit, emit_json, emit_line, secs, write_file};

/// The formats of `--format`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum Format {
    Json,
    Binary,
    Ply,
    Splat,
}

impl From<Format> for GaussianFormat {
    fn from(format: Format) -> Self {
        match format {
            Format::Json => GaussianFormat::Json,
            Format::Binary => GaussianFormat::Binary,
            Format::Ply => GaussianFormat::Ply,
            Format::Splat => GaussianFormat::Splat,
        }
    }
}

/// The speed/accuracy trade (decode, export, render, stream, track): a quality preset, and the
/// knobs it stands for, which the flags below override. Keyframes: the server decodes exact sets
/// at keyframes and interpolates the rest, for fewer decoder runs (at most one mode). Pruning: it
/// drops the Gaussians that change nothing visible. And which scene serves the request: the
/// model's feed-forward answer or the clip's fitted scene.
#[derive(Debug, Clone, clap::Args)]
pub(super) struct ApproximationArgs {
    /// A named trade: exact (the server's default), balanced (within 0.1 dB of exact on the
    /// measured scenes) or fast (within 0.5 dB).
    #[arg(long, value_enum, value_name = "PRESET")]
    quality: Option<QualityArg>,
    /// Drop the Gaussians whose summed blending weight stays under PX pixels in every view the
    /// server analyses (0.5 is its default floor; 0 keeps every visible Gaussian).
    #[arg(long, value_name = "PX")]
    prune: Option<f32>,
    /// With --prune: also drop the pruned Gaussians' query tokens from the decoder itself
    /// (cheaper decodes; the kept Gaussians change, since queries attend to each other).
    #[arg(long, requires = "prune")]
    drop_queries: bool,
    /// Decode N keyframes spread evenly over the times and interpolate the sets between them.
    #[arg(
        long = "keyframes",
        value_name = "N",
        conflicts_with_all = ["keyframe_every", "keyframe_tolerance"]
    )]
    keyframes: Option<u32>,
    /// Decode a keyframe every S seconds (and at the last time) and interpolate between them.
    #[arg(long, value_name = "S", conflicts_with = "keyframe_tolerance")]
    keyframe_every: Option<f64>,
    /// Place keyframes adaptively until the interpolated positions are within X scene units at
    /// every interval's checks.
    #[arg(long, value_name = "X")]
    keyframe_tolerance: Option<f64>,
    /// With --keyframe-tolerance: at most N exact decodes (server default 64).
    #[arg(long, value_name = "N", requires = "keyframe_tolerance")]
    keyframe_max: Option<u32>,
    /// Which scene: auto (the server's default: the clip's fitted scene when it has one),
    /// feed-forward or fitted (`c4g fit` makes one).
    #[arg(long, value_enum, value_name = "SCENE")]
    scene: Option<SceneArg>,
}

/// The choices of `--scene`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum SceneArg {
    Auto,
    FeedForward,
    Fitted,
}

/// The presets of `--quality`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum QualityArg {
    Exact,
    Balanced,
    Fast,
}

impl ApproximationArgs {
    /// The trade the flags ask for; every flag unset: exact.
    pub(super) fn approximation(&self) -> Approximation {
        Approximation {
            quality: self.quality.map(|q| match q {
                QualityArg::Exact => Quality::Exact,
                QualityArg::Balanced => Quality::Balanced,
                QualityArg::Fast => Quality::Fast,
            }),
            keyframes: self.keyframes(),
            prune: self.prune.map(|px| Prune {
                contribution_px: Some(px),
                opacity: None,
                drop_queries: self.drop_queries.then_some(true),
            }),
            scene: self.scene.map(|s| match s {
                SceneArg::Auto => Scene::Auto,
                SceneArg::FeedForward => Scene::FeedForward,
                SceneArg::Fitted => Scene::Fitted,
            }),
        }
    }

    /// The keyframes the flags ask for; `None`: the preset's.
    fn keyframes(&self) -> Option<Keyframes> {
        match (self.keyframes, self.keyframe_every, self.keyframe_tolerance) {
            (Some(count), _, _) => Some(Keyframes::Count { count }),
            (None, Some(seconds), _) => Some(Keyframes::Every { seconds }),
            (None, None, Some(tolerance)) => Some(Keyframes::Adaptive {
                tolerance,
                color_tolerance: None,
                max: self.keyframe_max,
                min_interval_s: None,
            }),
            (None, None, None) => None,
        }
    }
}

#[derive(Debug, clap::Args)]
pub struct DecodeArgs {
    /// The clip id.
    clip: String,
    /// A time in seconds, inside the clip's context span; repeat it or give a comma-separated
    /// list for several.
    #[arg(
        long = "t",
        value_name = "T",
        required = true,
        value_delimiter = ',',
        allow_negative_numbers = true
    )]
    times: Vec<f64>,
    /// The server's format to write (default: from -o's extension, else json). PLY and .splat
    /// hold one time.
    #[arg(long, value_enum)]
    format: Option<Format>,
    /// Write the server's bytes here.
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Each Gaussian's lifted feature vector too (JSON `features`, binary C4GS version 2, PLY
    /// `feat_*` properties; a package with a feature decoder only).
    #[arg(long)]
    features: bool,
    #[command(flatten)]
    approximation: ApproximationArgs,
}

pub async fn run(cx: &Context, args: DecodeArgs) -> anyhow::Result<()> {
    let explicit = args.format.map(GaussianFormat::from);
    let approximation = args.approximation.approximation();
    let approximation = &approximation;
    if let Some(path) = &args.output {
        let format = explicit
            .or_else(|| GaussianFormat::from_extension(path))
            .unwrap_or(GaussianFormat::Json);
        let fetch = Fetch {
            clip: &args.clip,
            times: &args.times,
            format,
            approximation,
            features: args.features,
        };
        return fetch_to_file(cx, &fetch, path).await;
    }
    let raw = |format| Fetch {
        clip: &args.clip,
        times: &args.times,
        format,
        approximation,
        features: args.features,
    };
    match explicit {
        // Without a format, a person gets a summary and a script (`--json`) the server's JSON.
        None if !cx.json => {
            summarise(cx, &args.clip, &args.times, approximation, args.features).await
        }
        None | Some(GaussianFormat::Json) => {
            let bytes = raw(GaussianFormat::Json).bytes(cx).await?;
            emit(&String::from_utf8_lossy(&bytes))?;
            if !bytes.ends_with(b"\n") {
                emit("\n")?;
            }
            Ok(())
        }
        Some(format) => {
            if std::io::stdout().is_terminal() {
                bail!("{format} is binary: write it to a file with -o, or pipe stdout");
            }
            let bytes = raw(format).bytes(cx).await?;
            super::emit_bytes(&bytes)
        }
    }
}

/// One decode whose bytes are written as the server sends them.
pub(super) struct Fetch<'a> {
    pub clip: &'a str,
    pub times: &'a [f64],
    pub format: GaussianFormat,
    pub approximation: &'a Approximation,
    pub features: bool,
}

impl Fetch<'_> {
    async fn bytes(&self, cx: &Context) -> anyhow::Result<bytes::Bytes> {
        let client = &cx.client;
        let (clip, times, format, approximation) =
            (self.clip, self.times, self.format, self.approximation);
        Ok(if self.features {
            client
                .gaussians_raw_with_features(clip, times, format, approximation)
                .await?
        } else {
            client
                .gaussians_raw_approximated(clip, times, format, approximation)
                .await?
        })
    }
}

pub(super) async fn fetch_to_file(
    cx: &Context,
    fetch: &Fetch<'_>,
    path: &Path,
) -> anyhow::Result<()> {
    let (times, format) = (fetch.times, fetch.format);
    let bytes = fetch.bytes(cx).await?;
    write_file(path, &bytes).await?;
    if cx.json {
        emit_json(&json!({
            "path": path,
            "format": format,
            "times": times,
            "bytes": bytes.len(),
        }))
    } else {
        emit_line(format!(
            "wrote {} ({format}, {} time{}, {})",
            path.display(),
            times.len(),
            if times.len() == 1 { "" } else { "s" },
            HumanBytes(bytes.len() as u64)
        ))
    }
}

/// One line per time: how many Gaussians, where their means lie, how opaque they are.
async fn summarise(
    cx: &Context,
    clip: &str,
    times: &[f64],
    approximation: &Approximation,
    features: bool,
) -> anyhow::Result<()> {
    let client = &cx.client;
    let frames = if features {
        client
            .gaussians_with_features(clip, times, Precision::F32, approximation)
            .await?
    } else {
        client
            .gaussians_approximated(clip, times, Precision::F32, approximation)
            .await?
    };
    let text: String = frames.iter().map(|f| frame_summary(f) + "\n").collect();
    emit(&text)
}

fn frame_summary(frame: &GaussianFrame) -> String {
    let set = &frame.gaussians;
    let mut line = format!("t={}  {} Gaussians", secs(frame.time), set.len());
    if set.is_empty() {
        return line;
    }
    let mut low = [f32::INFINITY; 3];
    let mut high = [f32::NEG_INFINITY; 3];
    for position in set.positions() {
        for axis in 0..3 {
            low[axis] = low[axis].min(position[axis]);
            high[axis] = high[axis].max(position[axis]);
        }
    }
    let opacity = set.opacities().iter().map(|&o| f64::from(o)).sum::<f64>() / set.len() as f64;
    let point = |p: [f32; 3]| format!("[{:.3}, {:.3}, {:.3}]", p[0], p[1], p[2]);
    line.push_str(&format!(
        "  means in {} .. {}  mean opacity {opacity:.3}",
        point(low),
        point(high)
    ));
    if let Some(features) = set.features() {
        line.push_str(&format!("  features of {}", features.width()));
    }
    line
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct Flags {
        #[command(flatten)]
        approximation: ApproximationArgs,
    }

    fn prune(args: &[&str]) -> Result<Option<Prune>, clap::Error> {
        let flags = Flags::try_parse_from(std::iter::once("c4g").chain(args.iter().copied()))?;
        Ok(flags.approximation.approximation().prune)
    }

    #[test]
    fn drop_queries_is_an_option_of_pruning() {
        let dropped = prune(&["--prune", "0.5", "--drop-queries"])
            .unwrap()
            .unwrap();
        assert_eq!(dropped.drop_queries, Some(true));
        assert_eq!(dropped.contribution_px, Some(0.5));
        // Left out, the request says nothing of it (the server's default: keep the queries).
        assert_eq!(
            prune(&["--prune", "0.5"]).unwrap().unwrap().drop_queries,
            None
        );
        let error = prune(&["--drop-queries"]).unwrap_err().to_string();
        assert!(error.contains("--prune"), "{error}");
    }
}
