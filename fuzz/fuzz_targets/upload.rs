//! Uploads as the image intake reads them: the sniffer, zip and tar archives (names, links,
//! declared and inflated sizes), image headers and decoding limits, frame times and context
//! sampling, with intake options. Input: `[n][n bytes of options JSON][media]`.
#![no_main]

libfuzzer_sys::fuzz_target!(|input: &[u8]| {
    if let Err(bug) = c4g_server::fuzzing::upload(input) {
        panic!("{bug}");
    }
});
