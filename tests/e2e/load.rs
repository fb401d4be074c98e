//! 64 concurrent decode and render requests against one clip: all succeed, and the server's
//! memory stays bounded (the work queue, not the request count, sets how much is in flight).
//! Latency numbers come from the bench (`cargo bench -p c4g-e2e --bench load`), not from here.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_e2e::{Server, burst, mixed_requests, ort_available, peak_rss, upload_synthetic};

#[test]
fn sixty_four_concurrent_decodes_and_renders_all_succeed_in_bounded_memory() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&["--max-concurrent-work", "2"]);
    let id = upload_synthetic(&server);
    let before = peak_rss(server.pid()).unwrap();
    let result = burst(&server, &mixed_requests(&id));
    assert!(result.failures.is_empty(), "{:?}", result.failures);
    assert_eq!(result.latencies.len(), 64);
    let after = peak_rss(server.pid()).unwrap();
    // Two pieces of work at a time, each a decoder run and one 128² image: tens of MB, not 64 times that.
    let growth = after.saturating_sub(before);
    assert!(
        growth < 256 << 20,
        "peak memory grew by {} MiB",
        growth >> 20
    );
}
