//! Compiles `c4g/v1/*.proto` with protox (a protobuf compiler in Rust: no `protoc` needed) and
//! generates the prost messages and tonic client and server (on our [`codec`](src/codec.rs)). The encoded descriptor set is kept
//! for gRPC reflection.

use prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=c4g");
    let descriptors = protox::compile(["c4g/v1/c4g.proto", "c4g/v1/jobs.proto"], ["."])?;
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("c4g_descriptor.bin"), descriptors.encode_to_vec())?;
    tonic_prost_build::configure()
        .codec_path("crate::codec::Codec")
        .compile_fds(descriptors)?;
    Ok(())
}
