//! Load on loopback: bursts of concurrent decode and render requests against one clip of the
//! default model, reporting p50 / p99 latency and throughput (docs/benchmarks.md).
//! Run: `cargo build --release --bins && cargo bench -p c4g-e2e --bench load` (the bench starts
//! the release `c4g-server` beside it in the target directory).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_e2e::{Server, burst, mixed_requests, peak_rss, upload_synthetic};

fn main() {
    if std::env::var_os("ORT_DYLIB_PATH").is_none() {
        eprintln!("set ORT_DYLIB_PATH (scripts/env.sh)");
        return;
    }
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    let requests = mixed_requests(&id);
    println!("| concurrency | requests | p50 ms | p99 ms | throughput req/s | failures |");
    println!("|---|---|---|---|---|---|");
    for concurrency in [1usize, 8, 64] {
        // Warm-up, then the measured round.
        let batch: Vec<_> = requests.iter().take(concurrency).cloned().collect();
        let _ = burst(&server, &batch);
        let mut all = Vec::new();
        let mut wall = 0.0;
        let mut failures = 0;
        for _ in 0..(64 / concurrency).max(1) {
            let round = burst(&server, &batch);
            all.extend(round.latencies.iter().copied());
            wall += round.wall;
            failures += round.failures.len();
        }
        all.sort_by(f64::total_cmp);
        let summary = c4g_e2e::Burst {
            latencies: all,
            wall,
            failures: Vec::new(),
        };
        println!(
            "| {concurrency} | {} | {:.1} | {:.1} | {:.1} | {failures} |",
            summary.latencies.len(),
            summary.quantile(0.5) * 1e3,
            summary.quantile(0.99) * 1e3,
            summary.throughput(),
        );
    }
    println!(
        "peak server RSS: {} MiB",
        peak_rss(server.pid()).unwrap_or(0) >> 20
    );
}
