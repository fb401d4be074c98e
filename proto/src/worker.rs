//! The worker's end of `c4g.v1.Jobs`, shared by `c4g-refiner` and `c4g-fitter`: what a worker is
//! told ([`WorkerConfig`]), its client to the server ([`connect`]: one lazy channel, the API key
//! on every call) and how its loops notice a stop ([`stopping`]). What each worker does with a
//! job stays in its own crate.

use tokio::sync::watch;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};

use crate::v1::jobs_client::JobsClient;

/// A worker's settings.
#[derive(Debug, Clone)]
pub struct WorkerConfig {
    /// The server, e.g. `http://127.0.0.1:8080`.
    pub server: String,
    /// The API key, if the server wants one.
    pub api_key: Option<String>,
    /// How this worker names itself in job records.
    pub name: String,
}

/// Adds the API key to every call.
#[derive(Clone)]
pub struct Auth(Option<MetadataValue<Ascii>>);

impl Interceptor for Auth {
    fn call(
        &mut self,
        mut request: tonic::Request<()>,
    ) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request
                .metadata_mut()
                .insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// A worker's client: every call carries the API key.
pub type Client = JobsClient<InterceptedService<Channel, Auth>>;

/// The client for `config`'s server. Lazy: nothing is dialled until the first call, so a worker
/// started before its server waits for it instead of failing. Messages are unbounded both ways
/// (the server bounds what it accepts); refused only for an address or key that cannot be used.
pub fn connect(config: &WorkerConfig) -> Result<Client, String> {
    let auth = match &config.api_key {
        Some(key) => Some(
            format!("Bearer {key}")
                .parse()
                .map_err(|_| "the API key must be printable ASCII".to_owned())?,
        ),
        None => None,
    };
    let channel = Endpoint::from_shared(config.server.clone())
        .map_err(|e| format!("bad server address {}: {e}", config.server))?
        .connect_lazy();
    Ok(JobsClient::with_interceptor(channel, Auth(auth))
        .max_decoding_message_size(usize::MAX)
        .max_encoding_message_size(usize::MAX))
}

/// Resolves once `shutdown` is true; never when its sender is gone (a dropped sender never
/// stops a worker).
pub async fn stopping(shutdown: &mut watch::Receiver<bool>) {
    if shutdown.wait_for(|stop| *stop).await.is_err() {
        std::future::pending::<()>().await;
    }
}
