//! `c4g export`: the Gaussians at one time as a `.ply` or `.splat`, or a time range as one 4D
//! file other viewers open (`.ply.zip`, `.spz.zip`, `.splatv`). The output's extension picks the
//! format.

use std::path::PathBuf;

use anyhow::bail;
use c4g_client::{ExportFormat, ExportOptions, GaussianFormat};
use indicatif::HumanBytes;
use serde_json::json;

use super::decode::{ApproximationArgs, Fetch, fetch_to_file};
use super::stream::RangeArgs;
use super::{Context, emit_json, emit_line, write_file};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The clip id.
    clip: String,
    /// The file to write: OUT.ply or OUT.splat (one time: give --t), or OUT.ply.zip, OUT.spz.zip
    /// or OUT.splatv (a time range: --start, --end, --step or --fps).
    #[arg(short, long)]
    output: PathBuf,
    /// The time in seconds, for .ply and .splat.
    #[arg(long = "t", value_name = "T", allow_negative_numbers = true)]
    time: Option<f64>,
    #[command(flatten)]
    range: RangeArgs,
    #[command(flatten)]
    approximation: ApproximationArgs,
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    if let Some(format) = ExportFormat::from_extension(&args.output) {
        if args.time.is_some() {
            bail!("{format} holds a time range: give --start, --end, --step or --fps, not --t");
        }
        return export_range(cx, args, format).await;
    }
    let format = match GaussianFormat::from_extension(&args.output) {
        Some(format @ (GaussianFormat::Ply | GaussianFormat::Splat)) => format,
        _ => bail!(
            "cannot tell the format of {} from its extension: use .ply or .splat (one time), or \
             .ply.zip, .spz.zip or .splatv (a time range)",
            args.output.display()
        ),
    };
    let Some(time) = args.time else {
        bail!("{format} holds one set: give its time with --t (or write .ply.zip for a range)");
    };
    if args.range.given() {
        bail!(
            "{format} holds one set: --start, --end, --step and --fps are for .ply.zip, .spz.zip and .splatv"
        );
    }
    let approximation = args.approximation.approximation();
    let fetch = Fetch {
        clip: &args.clip,
        times: &[time],
        format,
        approximation: &approximation,
        features: false,
    };
    fetch_to_file(cx, &fetch, &args.output).await
}

async fn export_range(cx: &Context, args: Args, format: ExportFormat) -> anyhow::Result<()> {
    let options = ExportOptions {
        start: args.range.start,
        end: args.range.end,
        spacing: args.range.spacing(),
        approximation: args.approximation.approximation(),
    };
    let export = cx.client.export(&args.clip, format, &options).await?;
    write_file(&args.output, &export.bytes).await?;
    if cx.json {
        let mut line = json!({
            "path": args.output,
            "format": format.name(),
            "sets": export.sets,
            "bytes": export.bytes.len(),
            "scene": export.scene,
        });
        if let Some((max, rms)) = export.fit_position_error {
            line["fit_position_error"] = json!({ "max": max, "rms": rms });
        }
        emit_json(&line)
    } else {
        let fit = match export.fit_position_error {
            Some((max, rms)) => format!(", fitted: positions within {max:.2e} (rms {rms:.2e})"),
            None => String::new(),
        };
        let scene = match export.scene {
            Some(scene) => format!(", {} scene", scene.name()),
            None => String::new(),
        };
        emit_line(format!(
            "wrote {} ({format}, {} sets, {}{scene}{fit})",
            args.output.display(),
            export.sets,
            HumanBytes(export.bytes.len() as u64)
        ))
    }
}
