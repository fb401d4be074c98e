//! Batching across requests on the CPU: bursts of N concurrent single-target exact decodes of one
//! clip of the default model, against two servers in one run, one without batching and one with
//! `C4G_BATCH_WAIT_MS` (default 2, `C4G_BENCH_BATCH_WAIT_MS`), rounds alternating so that a busy
//! machine weighs on both alike. Reports p50 latency and throughput of each, and their ratio
//! (docs/benchmarks.md, "Batching across requests"; it decided the CPU default, off).
//!
//!     cargo build --release --bins && cargo bench -p c4g-e2e --bench batching
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_e2e::{Burst, Server, burst, upload_synthetic};
use serde_json::json;

fn requests(id: &str, n: usize) -> Vec<(String, serde_json::Value)> {
    (0..n)
        .map(|k| {
            let t = 0.6 * (k as f64 + 0.5) / n as f64;
            (
                format!("/v1/clips/{id}/gaussians"),
                json!({"t": t, "format": "binary"}),
            )
        })
        .collect()
}

fn merged(rounds: &[Burst]) -> Burst {
    let mut latencies: Vec<f64> = rounds.iter().flat_map(|b| b.latencies.clone()).collect();
    latencies.sort_by(f64::total_cmp);
    Burst {
        latencies,
        wall: rounds.iter().map(|b| b.wall).sum(),
        failures: rounds.iter().flat_map(|b| b.failures.clone()).collect(),
    }
}

fn main() {
    if std::env::var_os("ORT_DYLIB_PATH").is_none() {
        eprintln!("set ORT_DYLIB_PATH (scripts/env.sh)");
        return;
    }
    let wait = std::env::var("C4G_BENCH_BATCH_WAIT_MS").unwrap_or_else(|_| "2".into());
    let plain = Server::start_env(&[("C4G_BATCH_WAIT_MS", "0")], &[]);
    let batched = Server::start_env(&[("C4G_BATCH_WAIT_MS", &wait)], &[]);
    let ids = [upload_synthetic(&plain), upload_synthetic(&batched)];
    println!(
        "c4g-tiny, {} cores; exact single-target decodes; batching wait {wait} ms",
        std::thread::available_parallelism().map_or(0, usize::from)
    );
    println!(
        "| concurrent | p50 ms off | p50 ms on | req/s off | req/s on | on / off throughput |"
    );
    println!("|---|---|---|---|---|---|");
    for n in [1usize, 4, 16, 64] {
        let servers = [&plain, &batched];
        for (server, id) in servers.iter().zip(&ids) {
            let _ = burst(server, &requests(id, n));
        }
        let mut rounds: [Vec<Burst>; 2] = [Vec::new(), Vec::new()];
        for _ in 0..(128 / n).clamp(2, 16) {
            for (k, (server, id)) in servers.iter().zip(&ids).enumerate() {
                rounds[k].push(burst(server, &requests(id, n)));
            }
        }
        let [off, on] = rounds.map(|r| merged(&r));
        assert!(off.failures.is_empty() && on.failures.is_empty());
        println!(
            "| {n} | {:.1} | {:.1} | {:.0} | {:.0} | {:.2} |",
            off.quantile(0.5) * 1e3,
            on.quantile(0.5) * 1e3,
            off.throughput(),
            on.throughput(),
            on.throughput() / off.throughput()
        );
    }
}
