//! `c4g cameras`: a clip's cameras (given at upload, or recovered), and `--recover` to recover
//! them by photometric alignment of the model's own Gaussians.

use serde_json::Value;

use super::{Context, emit, emit_json, secs};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The clip id.
    clip: String,
    /// Recover each context frame's camera now (again, if it was), and keep them with the clip.
    #[arg(long)]
    recover: bool,
    /// With --recover: refine one focal length for the clip as well as the poses.
    #[arg(long, requires = "recover")]
    refine_focal: bool,
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    let (cameras, fits) = if args.recover {
        let recovered = cx
            .client
            .recover_cameras(&args.clip, args.refine_focal)
            .await?;
        if cx.json {
            return emit_json(&recovered);
        }
        let fits = serde_json::to_value(&recovered.fits)?;
        (recovered.cameras, Some(fits))
    } else {
        let clip = cx.client.clip(&args.clip).await?;
        let given = clip.extra.get("cameras").cloned();
        let recovered = clip.extra.get("recovered_cameras").cloned();
        if cx.json {
            return emit_json(
                &serde_json::json!({ "cameras": given, "recovered_cameras": recovered }),
            );
        }
        match (given, recovered) {
            (Some(given), _) => (given, None),
            (None, Some(r)) => (r["cameras"].clone(), Some(r["fits"].clone())),
            (None, None) => {
                return emit(&format!(
                    "clip {} has no cameras: renders use the first context camera at every time \
                     (recover them with `c4g cameras {} --recover`)\n",
                    args.clip, args.clip
                ));
            }
        }
    };
    emit(&describe(&cameras, fits.as_ref()))
}

/// One line per context camera: its time, how far it turned from the first, its centre, and
/// for recovered ones the fit.
fn describe(cameras: &Value, fits: Option<&Value>) -> String {
    let mut text = format!(
        "{} cameras (scale {})\n",
        cameras["format"].as_str().unwrap_or("?"),
        cameras["scale"]
    );
    let frames = cameras["frames"].as_array().cloned().unwrap_or_default();
    for (k, frame) in frames.iter().enumerate() {
        let m: Vec<f64> = frame["world_to_camera"]
            .as_array()
            .map(|a| a.iter().filter_map(Value::as_f64).collect())
            .unwrap_or_default();
        if m.len() != 16 {
            continue;
        }
        // Row-major [R | t]: the rotation's angle from its trace, the centre −Rᵀt.
        let trace = m[0] + m[5] + m[10];
        let angle = ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees();
        let centre: [f64; 3] =
            std::array::from_fn(|c| -(0..3).map(|r| m[4 * r + c] * m[4 * r + 3]).sum::<f64>());
        let t = frame["t"].as_f64().unwrap_or(f64::NAN);
        text += &format!(
            "  t={}  turned {angle:6.2}°  centre ({:+.3}, {:+.3}, {:+.3})",
            secs(t),
            centre[0],
            centre[1],
            centre[2]
        );
        if let Some(fit) = fits.and_then(|f| f.get(k)) {
            text += &format!(
                "  residual {:.2e} (from {:.2e})  confidence {:.2}",
                fit["residual"].as_f64().unwrap_or(f64::NAN),
                fit["initial_residual"].as_f64().unwrap_or(f64::NAN),
                fit["confidence"].as_f64().unwrap_or(f64::NAN)
            );
        }
        text += "\n";
    }
    text
}
