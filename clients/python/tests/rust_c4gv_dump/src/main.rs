//! Reads a C4GV stream (argv[1]) with the formats crate's decoder and writes its sets as C4GS f32
//! (argv[2]): the reference the Python decoder is compared with byte for byte.

use c4g_formats::{c4gs, c4gv};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let [_, input, output] = args.as_slice() else {
        eprintln!("usage: c4gv-dump STREAM.c4gv OUT.c4gs");
        std::process::exit(2);
    };
    let bytes = std::fs::read(input).expect("reading the stream");
    let frames = c4gv::decode(&bytes).expect("decoding the stream");
    let out = c4gs::encode(frames.iter().map(|(t, s)| (*t, s)), c4gs::Precision::F32)
        .expect("encoding C4GS");
    std::fs::write(output, out).expect("writing C4GS");
}
