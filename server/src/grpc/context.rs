//! What every gRPC method is given: the server's state (the service once the model has loaded),
//! and the stream type of the streaming methods.

use std::pin::Pin;
use std::sync::Arc;

use c4g_service::service::Service;
use tokio_stream::Stream;
use tonic::Status;

use crate::AppState;
use crate::error::status;

/// The `c4g.v1.C4G` service over the server's state.
pub(super) struct Grpc {
    pub(super) state: AppState,
}

impl Grpc {
    /// The loaded service, or `UNAVAILABLE` while the model loads.
    pub(super) fn service(&self) -> Result<&Arc<Service>, Status> {
        self.state.service().map_err(status)
    }
}

/// The messages of a streaming method.
pub(super) type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;
