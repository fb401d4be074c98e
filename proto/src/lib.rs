//! The c4g gRPC contract: the messages and services of `proto/c4g/v1/c4g.proto`, generated at
//! build time, and the descriptor set that gRPC reflection serves.

#![allow(missing_docs, clippy::all)]

/// Package `c4g.v1`.
pub mod v1 {
    tonic::include_proto!("c4g.v1");
}

/// The encoded `FileDescriptorSet` of every c4g proto file, for `grpc.reflection`.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/c4g_descriptor.bin"));
