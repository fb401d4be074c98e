//! `c4g segment`: the Gaussians whose lifted feature is like a clicked pixel's (or a given
//! feature), and their masks at other times (`POST /v1/clips/{id}/segment`).

use std::path::PathBuf;

use anyhow::{Context as _, bail};
use c4g_client::{Mask, SegmentRequest, Selection};

use super::track::parse_pair;
use super::{Context, emit, emit_json, secs, write_file};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The clip id.
    clip: String,
    /// The time of the click, seconds (with --point), or when the Gaussians' features are
    /// compared with --feature (default: the clip's first context time).
    #[arg(long = "at", value_name = "T", allow_negative_numbers = true)]
    at: Option<f64>,
    /// The clicked pixel X,Y (pixel (i, j) covers [i, i+1) x [j, j+1)) in the input camera at
    /// --at.
    #[arg(
        long = "point",
        value_name = "X,Y",
        conflicts_with = "feature",
        requires = "at"
    )]
    point: Option<String>,
    /// A feature vector to select by: comma-separated numbers, or @FILE holding a JSON array.
    #[arg(long, value_name = "V1,V2,..|@FILE", allow_hyphen_values = true)]
    feature: Option<String>,
    /// The cosine similarity a Gaussian must reach (server default 0.8).
    #[arg(long, allow_negative_numbers = true)]
    threshold: Option<f32>,
    /// Times to answer masks at, seconds (comma-separated; default: the clip's context times).
    #[arg(
        long = "t",
        value_name = "T",
        value_delimiter = ',',
        allow_negative_numbers = true
    )]
    times: Vec<f64>,
    /// The image size, WxH (default: the model's input size).
    #[arg(long, value_name = "WxH")]
    size: Option<String>,
    /// Write each mask as a binary PGM (portable greymap, which image viewers open): PREFIX-<t>.pgm,
    /// white where set.
    #[arg(short, long, value_name = "PREFIX")]
    output: Option<PathBuf>,
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    let selection = match (&args.point, &args.feature) {
        (Some(point), None) => {
            let (x, y) = parse_pair(point, ',')
                .with_context(|| format!("--point {point}: give X,Y in pixels, like 14.5,9"))?;
            let t = args.at.context("--point needs --at T, the click's time")?;
            Selection::Click { t, x, y }
        }
        (None, Some(feature)) => Selection::Feature {
            feature: parse_feature(feature)?,
            t: args.at,
        },
        _ => bail!("select by --point X,Y (with --at T) or by --feature V1,V2,..."),
    };
    let size = args
        .size
        .as_deref()
        .map(|s| {
            parse_pair::<u32>(s, 'x')
                .with_context(|| format!("--size {s}: give WxH in pixels, like 64x64"))
        })
        .transpose()?;
    let request = SegmentRequest {
        selection,
        threshold: args.threshold,
        times: args.times,
        camera: None,
        size,
    };
    let segment = cx.client.segment(&args.clip, &request).await?;
    if let Some(prefix) = &args.output {
        for mask in &segment.masks {
            let path = PathBuf::from(format!("{}-{}.pgm", prefix.display(), secs(mask.t)));
            write_file(&path, &mask_pgm(mask, segment.width, segment.height)?).await?;
        }
    }
    if cx.json {
        return emit_json(&segment);
    }
    let mut text = format!(
        "{} Gaussians with cosine >= {} at t={}\n",
        segment.gaussians.len(),
        segment.threshold,
        secs(segment.t)
    );
    for mask in &segment.masks {
        let share = mask.area as f64 / f64::from(segment.width * segment.height).max(1.0);
        text += &format!(
            "  t={}  {} pixels ({:.1}%)\n",
            secs(mask.t),
            mask.area,
            100.0 * share
        );
    }
    emit(&text)
}

fn parse_feature(text: &str) -> anyhow::Result<Vec<f32>> {
    if let Some(path) = text.strip_prefix('@') {
        let json = std::fs::read_to_string(path).with_context(|| format!("reading {path}"))?;
        return serde_json::from_str(&json)
            .with_context(|| format!("{path} must hold a JSON array of numbers"));
    }
    text.split(',')
        .map(|v| {
            v.trim()
                .parse::<f32>()
                .with_context(|| format!("--feature: '{v}' is not a number"))
        })
        .collect()
}

/// The mask as an 8-bit binary PGM, white where set.
fn mask_pgm(mask: &Mask, width: u32, height: u32) -> anyhow::Result<Vec<u8>> {
    let pixels = mask.pixels();
    if pixels.len() != width as usize * height as usize {
        bail!(
            "the server's mask at t={} holds {} pixels, not {width}x{height}",
            secs(mask.t),
            pixels.len()
        );
    }
    let mut bytes = format!("P5\n{width} {height}\n255\n").into_bytes();
    bytes.extend(pixels.into_iter().map(|set| if set { 255u8 } else { 0 }));
    Ok(bytes)
}
