//! `c4g track`: where points seen in an input frame go at other times (the clip's Gaussian
//! trajectories, `POST /v1/clips/{id}/tracks`).

use anyhow::{Context as _, bail};
use c4g_client::{TrackQuery, TrackRequest, Tracker};

use super::decode::ApproximationArgs;
use super::{Context, emit, emit_json, secs};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The clip id.
    clip: String,
    /// The time, seconds, of the input frame the points are seen in.
    #[arg(long = "at", value_name = "T", allow_negative_numbers = true)]
    at: f64,
    /// A point X,Y in pixels of that frame (pixel (i, j) covers [i, i+1) x [j, j+1)); repeat
    /// for several.
    #[arg(long = "point", value_name = "X,Y", required = true)]
    points: Vec<String>,
    /// Times to answer at, seconds (comma-separated; default: the clip's context times).
    #[arg(
        long = "t",
        value_name = "T",
        value_delimiter = ',',
        allow_negative_numbers = true
    )]
    times: Vec<f64>,
    /// The image size the points are in, WxH (default: the model's input size).
    #[arg(long, value_name = "WxH")]
    size: Option<String>,
    /// Which tracker follows the points: gaussians (the server's default: the Gaussians that
    /// explain each point's pixel carry it) or features (the rendered feature field's best match;
    /// a package with a feature decoder).
    #[arg(long, value_enum)]
    tracker: Option<TrackerArg>,
    #[command(flatten)]
    approximation: ApproximationArgs,
}

/// The trackers of `--tracker`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum TrackerArg {
    Gaussians,
    Features,
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    let queries = args
        .points
        .iter()
        .map(|p| {
            let (x, y) = parse_pair(p, ',')
                .with_context(|| format!("--point {p}: give X,Y in pixels, like 31.5,12"))?;
            Ok(TrackQuery { t: args.at, x, y })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let size = args
        .size
        .as_deref()
        .map(|s| {
            let (w, h) = parse_pair::<u32>(s, 'x')
                .with_context(|| format!("--size {s}: give WxH in pixels, like 64x64"))?;
            Ok::<_, anyhow::Error>((w, h))
        })
        .transpose()?;
    let request = TrackRequest {
        tracker: args.tracker.map(|t| match t {
            TrackerArg::Gaussians => Tracker::Gaussians,
            TrackerArg::Features => Tracker::Features,
        }),
        queries,
        times: args.times,
        size,
        approximation: args.approximation.approximation(),
    };
    let tracks = cx.client.tracks(&args.clip, &request).await?;
    if cx.json {
        return emit_json(&tracks);
    }
    let mut text = String::new();
    for (k, track) in tracks.tracks.iter().enumerate() {
        let q = track.query;
        text += &format!("point {k} at t={} ({}, {})", secs(q.t), q.x, q.y);
        if !track.anchored {
            text += ": nothing covers this pixel\n";
            continue;
        }
        text += "\n";
        for p in &track.points {
            let seen = if p.visible { "visible" } else { "hidden" };
            text += &format!(
                "  t={}  x={:.2}  y={:.2}  depth={:.3}  {seen}",
                secs(p.t),
                p.x,
                p.y,
                p.depth
            );
            if let Some(s) = p.similarity {
                text += &format!("  similarity={s:.3}");
            }
            text += "\n";
        }
    }
    emit(&text)
}

pub(super) fn parse_pair<T: std::str::FromStr>(
    text: &str,
    separator: char,
) -> anyhow::Result<(T, T)> {
    let Some((a, b)) = text.split_once(separator) else {
        bail!("expected two numbers separated by '{separator}'");
    };
    let number = |s: &str| {
        s.trim()
            .parse::<T>()
            .map_err(|_| anyhow::anyhow!("'{s}' is not a number"))
    };
    Ok((number(a)?, number(b)?))
}
