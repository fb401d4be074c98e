//! The end-to-end tests: `c4g-server`, the `c4g` CLI and the refiner worker as real processes on
//! loopback, the viewer in Chromium, the job stores against real PostgreSQL. One test binary, one
//! module per file: `cargo test -p c4g-e2e --test e2e -- service::` runs one file's tests.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

mod bad_inputs;
mod batching;
mod cameras;
mod cli;
mod compact_stream;
mod contract;
mod exports;
mod faults;
mod features;
mod fit;
mod job_queues;
mod keyframes;
mod load;
mod media;
mod quality;
mod recovered_cameras;
mod refine;
mod security;
mod service;
mod shared_store;
mod tracks;
mod viewer;
