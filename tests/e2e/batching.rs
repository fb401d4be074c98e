//! Batching across requests (`server/src/batching.rs`): concurrent exact decodes and renders of
//! one clip share decoder runs, and each request still gets what it would have got alone.
//!
//! The server runs on the CPU with a wait long enough (`C4G_BATCH_WAIT_MS=100`) for requests sent
//! together by threads to meet, and work slots for all of them. Checked: twelve concurrent
//! single-target requests (eight decodes, four renders) are answered by fewer decoder runs than
//! requests (`c4g_decode_duration_seconds_count`, one sample a decoder call); the batch metrics
//! add up; each decoded set equals the set decoded alone, and each render the render made alone.
//!
//! Equality, not closeness: the decoder computes each target's rows independently of the others
//! in the batch, and ONNX Runtime's CPU kernels give the same bits for a row whatever the batch
//! on this model (checked here: if that stopped holding, this test says so before a client
//! sees exact answers depend on their neighbours).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_e2e::{Server, metric, ort_available, upload_synthetic};
use reqwest::blocking::Client;
use serde_json::json;

fn metrics(server: &Server) -> String {
    Client::new()
        .get(server.at("/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap()
}

fn decode(server: &Server, id: &str, t: f64) -> Vec<u8> {
    let response = Client::new()
        .post(server.at(&format!("/v1/clips/{id}/gaussians")))
        .json(&json!({"t": t, "format": "binary"}))
        .send()
        .unwrap();
    assert_eq!(response.status(), 200);
    response.bytes().unwrap().to_vec()
}

fn render(server: &Server, id: &str, t: f64) -> Vec<u8> {
    let response = Client::new()
        .post(server.at(&format!("/v1/clips/{id}/render")))
        .json(&json!({"t": t, "width": 64, "height": 64}))
        .send()
        .unwrap();
    assert_eq!(response.status(), 200);
    response.bytes().unwrap().to_vec()
}

#[test]
fn concurrent_exact_requests_share_decoder_runs_and_get_what_they_would_alone() {
    if !ort_available() {
        return;
    }
    let server = Server::start_env(
        &[
            ("C4G_BATCH_WAIT_MS", "100"),
            ("C4G_MAX_CONCURRENT_WORK", "16"),
        ],
        &[],
    );
    let id = upload_synthetic(&server);
    let decode_times: Vec<f64> = (0..8).map(|k| 0.05 + 0.07 * f64::from(k)).collect();
    let render_times = [0.1, 0.25, 0.4, 0.55];

    let before = metric(&metrics(&server), "c4g_decode_duration_seconds_count");
    let (decoded, rendered) = std::thread::scope(|s| {
        let decodes: Vec<_> = decode_times
            .iter()
            .map(|&t| {
                let (server, id) = (&server, &id);
                s.spawn(move || decode(server, id, t))
            })
            .collect();
        let renders: Vec<_> = render_times
            .iter()
            .map(|&t| {
                let (server, id) = (&server, &id);
                s.spawn(move || render(server, id, t))
            })
            .collect();
        (
            decodes
                .into_iter()
                .map(|h| h.join().unwrap())
                .collect::<Vec<_>>(),
            renders
                .into_iter()
                .map(|h| h.join().unwrap())
                .collect::<Vec<_>>(),
        )
    });
    let text = metrics(&server);
    let runs = metric(&text, "c4g_decode_duration_seconds_count") - before;
    let requests = decode_times.len() + render_times.len();
    assert!(
        runs < requests as f64,
        "{requests} concurrent requests took {runs} decoder runs: nothing was batched"
    );
    assert_eq!(
        metric(&text, "c4g_decode_batch_requests_sum"),
        requests as f64
    );
    assert_eq!(
        metric(&text, "c4g_decode_batch_targets_sum"),
        requests as f64
    );
    assert_eq!(metric(&text, "c4g_decode_batch_requests_count"), runs);
    eprintln!("batching: {requests} concurrent single-target requests in {runs} decoder runs");

    // Alone, one after another: the same bytes.
    for (t, batched) in decode_times.iter().zip(&decoded) {
        assert!(
            decode(&server, &id, *t) == *batched,
            "the set at t={t} decoded in a batch differs from the set decoded alone"
        );
    }
    for (t, batched) in render_times.iter().zip(&rendered) {
        assert!(
            render(&server, &id, *t) == *batched,
            "the render at t={t} differs when its decode was batched"
        );
    }
}

#[test]
fn without_a_wait_every_request_decodes_on_its_own() {
    if !ort_available() {
        return;
    }
    // The CPU default: no batching.
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    let before = metric(&metrics(&server), "c4g_decode_duration_seconds_count");
    std::thread::scope(|s| {
        for k in 0..4 {
            let (server, id) = (&server, &id);
            s.spawn(move || decode(server, id, 0.1 * f64::from(k)));
        }
    });
    let text = metrics(&server);
    assert_eq!(
        metric(&text, "c4g_decode_duration_seconds_count") - before,
        4.0
    );
    assert_eq!(metric(&text, "c4g_decode_batch_requests_count"), 0.0);
}
