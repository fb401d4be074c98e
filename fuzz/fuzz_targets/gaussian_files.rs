//! The readers of Gaussian files and payloads (`.ply`, `.splat`, `C4GS`, `C4GV`, `.spz`, frames
//! zip, `.splatv`): what decodes renders to finite pixels and writes back. Input: `[format]bytes`
//! (see `c4g_server::fuzzing::gaussian_files`).
#![no_main]

libfuzzer_sys::fuzz_target!(|input: &[u8]| {
    if let Err(bug) = c4g_server::fuzzing::gaussian_files(input) {
        panic!("{bug}");
    }
});
