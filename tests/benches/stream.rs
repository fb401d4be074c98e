//! Gaussian sets a second through gRPC `StreamGaussians`, per quality preset and wire precision,
//! and what each preset costs in quality against the exact stream (docs/benchmarks.md).
//!
//! One clip of the default model (the synthetic test clip, 4 context frames over 0.6 s), streamed
//! over its whole span at a step of 1 ms (601 sets) on loopback: the rate is sets received over
//! the time from the request to the last set, so it includes the keyframe decodes and the scene
//! analysis a preset makes before its first set (the analysis runs once per clip: the first
//! pruned stream pays it, so each preset is streamed twice and the second is reported). Quality:
//! every 25th set of an f32 stream rendered at 64 × 64 from the first context camera (the CPU
//! rasterizer, c4g-tiny's footprint), PSNR against the exact stream's render at the same time.
//!
//! Run: `cargo build --release --bins && cargo bench -p c4g-e2e --bench stream`.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::time::Instant;

use c4g_e2e::{Server, upload_synthetic};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions, fidelity};
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};
use glam::Affine3A;

const STEP_S: f64 = 0.001;
const SIZE: u32 = 64;
const COMPARE_EVERY: usize = 25;

fn f32s(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect()
}

fn triples<const N: usize>(values: &[f32]) -> Vec<[f32; N]> {
    values
        .chunks_exact(N)
        .map(|c| std::array::from_fn(|k| c[k]))
        .collect()
}

/// An f32 set off the wire.
fn set_of(set: &pb::GaussianSet) -> GaussianSet {
    GaussianSet::new(
        triples::<3>(&f32s(&set.means)),
        triples::<3>(&f32s(&set.scales)),
        triples::<4>(&f32s(&set.rotations)),
        f32s(&set.opacities),
        triples::<3>(&f32s(&set.colors)),
    )
    .unwrap()
}

struct Streamed {
    sets_per_s: f64,
    first_set_ms: f64,
    gaussians: u32,
    bytes_per_set: usize,
    sampled: Vec<GaussianSet>,
}

async fn stream(
    grpc: &mut C4gClient<tonic::transport::Channel>,
    id: &str,
    quality: pb::Quality,
    precision: pb::Precision,
) -> Streamed {
    let started = Instant::now();
    let mut frames = grpc
        .stream_gaussians(pb::StreamGaussiansRequest {
            clip_id: id.to_owned(),
            spacing: Some(pb::stream_gaussians_request::Spacing::Step(STEP_S)),
            quality: quality as i32,
            precision: precision as i32,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let (mut count, mut bytes, mut gaussians) = (0usize, 0usize, 0u32);
    let mut first_set_ms = 0.0;
    let mut sampled = Vec::new();
    while let Some(frame) = frames.message().await.unwrap() {
        if count == 0 {
            first_set_ms = started.elapsed().as_secs_f64() * 1e3;
        }
        let set = frame.gaussians.unwrap();
        gaussians = set.count;
        bytes += set.means.len()
            + set.scales.len()
            + set.rotations.len()
            + set.opacities.len()
            + set.colors.len();
        if precision == pb::Precision::F32 && count % COMPARE_EVERY == 0 {
            sampled.push(set_of(&set));
        }
        count += 1;
    }
    Streamed {
        sets_per_s: count as f64 / started.elapsed().as_secs_f64(),
        first_set_ms,
        gaussians,
        bytes_per_set: bytes / count.max(1),
        sampled,
    }
}

fn main() {
    if std::env::var_os("ORT_DYLIB_PATH").is_none() {
        eprintln!("set ORT_DYLIB_PATH (scripts/env.sh)");
        return;
    }
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    let camera = Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        SIZE,
        SIZE,
        Affine3A::IDENTITY,
    )
    .unwrap();
    let rasterizer = CpuRasterizer::new();
    let render = |set: &GaussianSet| {
        rasterizer
            .render(set, &camera, &RenderOptions::default())
            .unwrap()
            .rgb
    };
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let exact = stream(&mut grpc, &id, pb::Quality::Exact, pb::Precision::F32).await;
        let exact_renders: Vec<Vec<f32>> = exact.sampled.iter().map(render).collect();
        println!(
            "| quality | precision | sets/s | first set | Gaussians | bytes/set | worst PSNR vs exact |"
        );
        println!("|---|---|---|---|---|---|---|");
        for quality in [pb::Quality::Exact, pb::Quality::Balanced, pb::Quality::Fast] {
            for precision in [pb::Precision::F32, pb::Precision::F16] {
                // The first pruned stream of the clip also analyses it: stream once unmeasured.
                let _ = stream(&mut grpc, &id, quality, precision).await;
                let run = stream(&mut grpc, &id, quality, precision).await;
                let worst = (precision == pb::Precision::F32).then(|| {
                    run.sampled
                        .iter()
                        .zip(&exact_renders)
                        .map(|(set, reference)| {
                            fidelity::psnr(reference, &render(set), SIZE, SIZE, None).unwrap()
                        })
                        .fold(f64::INFINITY, f64::min)
                });
                println!(
                    "| {} | {} | {:.0} | {:.0} ms | {} | {} | {} |",
                    quality.as_str_name(),
                    precision.as_str_name(),
                    run.sets_per_s,
                    run.first_set_ms,
                    run.gaussians,
                    run.bytes_per_set,
                    worst.map_or("—".to_owned(), |db| if db.is_infinite() {
                        "identical".to_owned()
                    } else {
                        format!("{db:.1} dB")
                    }),
                );
            }
        }
    });
}
