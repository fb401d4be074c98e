//! gRPC requests through the real router, model and store: protobuf messages for every method
//! that reads a request (uploads excepted: their media is the `upload` target's). Input:
//! `[method]message` (see `c4g_server::fuzzing::Edge::grpc`); no answer may be INTERNAL or UNKNOWN.
#![no_main]

libfuzzer_sys::fuzz_target!(|input: &[u8]| {
    if let Err(bug) = c4g_server::fuzzing::Edge::get().grpc(input) {
        panic!("{bug}");
    }
});
