//! The codec of every c4g service: prost's, except that a message which does not decode is
//! `INVALID_ARGUMENT`, not `INTERNAL`.
//!
//! gRPC's status code table (`doc/statuscodes.md`) files "error parsing request proto" under
//! `INTERNAL`, and tonic follows it. For a service whose callers are people writing clients that
//! is the wrong signal: bytes that are not the request message are the caller's to fix (as any
//! other malformed request is), and an `INTERNAL` answer tells them the server broke. So the
//! server says `INVALID_ARGUMENT` with prost's description of what did not decode. The same
//! codec serves the generated clients, where an undecodable *response* reads as
//! `INVALID_ARGUMENT` too: a server sending such bytes is a bug either way.

use std::marker::PhantomData;

use prost::Message;
use tonic::codec::{BufferSettings, Codec as TonicCodec, DecodeBuf, Decoder};
use tonic::{Code, Status};
use tonic_prost::{ProstCodec, ProstDecoder, ProstEncoder};

/// [`ProstCodec`] with undecodable messages as `INVALID_ARGUMENT`.
#[derive(Debug, Clone, Default)]
pub struct Codec<T, U>(PhantomData<(T, U)>);

impl<T, U> TonicCodec for Codec<T, U>
where
    T: Message + Send + 'static,
    U: Message + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = ProstEncoder<T>;
    type Decoder = StrictDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        ProstCodec::<T, U>::raw_encoder(BufferSettings::default())
    }

    fn decoder(&mut self) -> Self::Decoder {
        StrictDecoder(ProstCodec::<T, U>::raw_decoder(BufferSettings::default()))
    }
}

/// Prost's decoder, its parse errors as `INVALID_ARGUMENT`.
#[derive(Debug, Clone)]
pub struct StrictDecoder<U>(ProstDecoder<U>);

impl<U: Message + Default> Decoder for StrictDecoder<U> {
    type Item = U;
    type Error = Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
        self.0.decode(buf).map_err(|status| match status.code() {
            // Prost's decoder fails in one way only: the bytes are not the message.
            Code::Internal => Status::invalid_argument(format!(
                "the message is not a valid protobuf encoding of the method's request: {}",
                status.message()
            )),
            _ => status,
        })
    }

    fn buffer_settings(&self) -> BufferSettings {
        self.0.buffer_settings()
    }
}
