//! How an engine runs its package: the sessions' options, the time policy, decoder batching.

use c4g_runtime::SessionOptions;

use crate::time::TimePolicy;

/// How an [`Engine`](crate::Engine) runs its package.
#[derive(Debug, Clone, PartialEq)]
pub struct EngineOptions {
    /// How the graphs' sessions are configured: threads, execution provider, CPU arena.
    pub session: SessionOptions,
    /// How timestamps are normalised for the decoder: `None` uses the policy the package declares
    /// (`model.json`'s `time_policy`, frame-step when it says none), `Some` overrides it.
    pub time_policy: Option<TimePolicy>,
    /// Most targets decoded in one decoder run; larger requests are split into chunks.
    pub max_batch: usize,
    /// Bytes of working memory one decoder run may need; batches shrink (down to one target) to
    /// stay under it. With fused attention a target costs about `8 · C · (T·P + N) · 4` bytes
    /// (~350 MB for the official model at T = 16); a package exported with plain attention
    /// materialises every score matrix, `2 · heads · (T·P + N)² · 4` bytes (~5 GB). 0 disables
    /// the limit (only `max_batch` applies). See [`Engine::decode_batch_size`](crate::Engine::decode_batch_size).
    pub decoder_memory_budget: usize,
}

impl Default for EngineOptions {
    fn default() -> Self {
        Self {
            session: SessionOptions::default(),
            time_policy: None,
            max_batch: 16,
            decoder_memory_budget: 4 << 30,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ExecutionProvider;

    #[test]
    fn default_options_run_on_the_cpu_with_the_packages_policy() {
        let o = EngineOptions::default();
        assert_eq!(o.session.execution_provider, ExecutionProvider::Cpu);
        assert_eq!(o.time_policy, None);
        assert_eq!((o.session.intra_op_threads, o.max_batch), (0, 16));
        assert_eq!(o.decoder_memory_budget, 4 << 30);
        assert!(!o.session.cpu_arena);
    }
}
