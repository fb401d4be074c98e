//! The time policies on any context and target: refused, or finite times within each policy's
//! stated bounds. Input: little-endian `f64`s (see `c4g_server::fuzzing::time_policy`).
#![no_main]

libfuzzer_sys::fuzz_target!(|input: &[u8]| {
    if let Err(bug) = c4g_server::fuzzing::time_policy(input) {
        panic!("{bug}");
    }
});
