//! The c4g gRPC contract: the messages and services of `proto/c4g/v1/c4g.proto`, generated at
//! build time, the descriptor set that gRPC reflection serves, the [`codec`] both ends use, and
//! the [`worker`]s' end of `c4g.v1.Jobs`.

/// Prost's codec, with messages that do not decode as `INVALID_ARGUMENT`.
pub mod codec;

/// The worker's end of `c4g.v1.Jobs`: its settings, its client, its stop signal.
pub mod worker;

/// Package `c4g.v1` (generated: its items are documented in the proto files).
#[allow(missing_docs, clippy::all)]
pub mod v1 {
    tonic::include_proto!("c4g.v1");
}

/// The encoded `FileDescriptorSet` of every c4g proto file, for `grpc.reflection`.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/c4g_descriptor.bin"));
