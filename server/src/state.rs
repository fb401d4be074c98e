//! What every handler shares. The model loads in the background, so `/health` answers at once
//! and `/ready` tells when the service can serve; once the server drains (SIGTERM), `/ready`
//! says so and the requests that would wait on (job events, a worker's wait for a job) stop
//! waiting.

use std::sync::{Arc, OnceLock};

use metrics_exporter_prometheus::PrometheusHandle;
use tokio::sync::watch;

use crate::auth::ApiKey;
use c4g_service::ServiceError;
use c4g_service::config::Config;
use c4g_service::service::Service;

/// Shared, cheaply cloned state of the server.
#[derive(Clone)]
pub struct AppState {
    shared: Arc<Shared>,
}

struct Shared {
    service: OnceLock<Arc<Service>>,
    config: Config,
    api_key: Option<ApiKey>,
    metrics: Option<PrometheusHandle>,
    /// True from the start of the drain on.
    draining: watch::Sender<bool>,
}

impl AppState {
    /// State with no model loaded yet.
    pub fn new(config: Config, metrics: Option<PrometheusHandle>) -> Self {
        let api_key = config.api_key.as_ref().map(|key| ApiKey::new(key.expose()));
        Self {
            shared: Arc::new(Shared {
                service: OnceLock::new(),
                config,
                api_key,
                metrics,
                draining: watch::Sender::new(false),
            }),
        }
    }

    /// Installs the loaded service; later calls are ignored.
    pub fn set_service(&self, service: Service) {
        let _ = self.shared.service.set(Arc::new(service));
    }

    /// The service, once the model has loaded.
    pub fn service(&self) -> Result<&Arc<Service>, ServiceError> {
        self.shared.service.get().ok_or(ServiceError::NotReady)
    }

    /// The settings the server started with.
    pub fn config(&self) -> &Config {
        &self.shared.config
    }

    /// The API key requests must carry, when one is configured.
    pub fn api_key(&self) -> Option<&ApiKey> {
        self.shared.api_key.as_ref()
    }

    /// The Prometheus exposition, when metrics are recorded.
    pub fn metrics(&self) -> Option<&PrometheusHandle> {
        self.shared.metrics.as_ref()
    }

    /// Starts the drain: from now on the server finishes what it has and takes nothing new.
    pub fn begin_drain(&self) {
        self.shared.draining.send_replace(true);
    }

    /// Whether the server is draining.
    pub fn is_draining(&self) -> bool {
        *self.shared.draining.borrow()
    }

    /// Resolves once the server drains (at once if it already does).
    pub fn drained(&self) -> impl std::future::Future<Output = ()> + Send + use<> {
        let mut draining = self.shared.draining.subscribe();
        async move {
            let _ = draining.wait_for(|d| *d).await;
        }
    }
}
