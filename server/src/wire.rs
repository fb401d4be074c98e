//! Gaussian sets on the wire: JSON, and the gRPC messages' precision and packed arrays. The packed
//! binary format of `docs/api.md` (`C4GS`) and the column packing both share are the renderer's
//! [`c4gs`] codec, which the client reads with.

use c4g_formats::c4gs;
pub use c4g_formats::c4gs::Precision;
use c4g_proto::v1 as pb;
use c4g_scene::GaussianSet;
use serde_json::{Value, json};

use c4g_service::ServiceError;

/// The precision a gRPC request asks for; unspecified means `f32`.
pub fn precision_from_proto(p: pb::Precision) -> Precision {
    match p {
        pb::Precision::F16 => Precision::F16,
        pb::Precision::F32 | pb::Precision::Unspecified => Precision::F32,
    }
}

/// The binary format: a header, then per frame its time and the five arrays.
pub fn binary(
    frames: &[(f64, GaussianSet)],
    precision: Precision,
) -> Result<Vec<u8>, ServiceError> {
    // The decoder gives every set of a clip the same size, so a failure is the server's own.
    c4gs::encode(frames.iter().map(|(t, set)| (*t, set)), precision)
        .map_err(|e| ServiceError::Internal(format!("writing C4GS: {e}")))
}

/// The JSON form; a set with lifted features also has `features`, one array per Gaussian.
pub fn json(frames: &[(f64, GaussianSet)]) -> Value {
    let frames: Vec<Value> = frames
        .iter()
        .map(|(t, set)| {
            let mut frame = json!({
                "t": t,
                "count": set.len(),
                "means": set.positions(),
                "scales": set.scales(),
                "rotations": set.rotations(),
                "opacities": set.opacities(),
                "colors": set.colors(),
            });
            if let Some(block) = set.features() {
                let rows: Vec<&[f32]> = block.values().chunks_exact(block.width()).collect();
                frame["features"] = json!(rows);
            }
            frame
        })
        .collect();
    json!({ "frames": frames })
}

/// One set as the gRPC message (its lifted features, when it has them, packed like the columns).
pub fn proto(set: &GaussianSet, precision: Precision) -> pb::GaussianSet {
    let [means, scales, rotations, opacities, colors] = c4gs::pack_columns(set, precision);
    let (feature_width, features) = set.features().map_or((0, Vec::new()), |block| {
        (
            block.width() as u32,
            c4gs::pack_values(block.values(), precision),
        )
    });
    pb::GaussianSet {
        feature_width,
        features,
        count: set.len() as u32,
        precision: match precision {
            Precision::F32 => pb::Precision::F32,
            Precision::F16 => pb::Precision::F16,
        } as i32,
        means,
        scales,
        rotations,
        opacities,
        colors,
    }
}
