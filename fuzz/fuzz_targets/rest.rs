//! REST requests through the real router, model and store: JSON bodies (decode, render,
//! refine) through the handlers' extractors and every check behind them (cameras, trajectories,
//! quality, keyframes, times), upload query strings, path segments. Input: `[route][head\n]body`
//! (see `c4g_server::fuzzing::Edge::rest`); no answer may be a 500.
#![no_main]

libfuzzer_sys::fuzz_target!(|input: &[u8]| {
    if let Err(bug) = c4g_server::fuzzing::Edge::get().rest(input) {
        panic!("{bug}");
    }
});
