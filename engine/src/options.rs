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
    /// Bytes of execution-provider memory for device-resident encodings (`crate::resident`):
    /// decodes bind a clip's features there instead of copying them on every run. `None`: the
    /// provider's default ([`DEFAULT_RESIDENT_BUDGET`] on CUDA; off on the CPU, where there is
    /// no copy to save); `Some(0)`: off; `Some(bytes)`: on, on any provider.
    pub resident_budget: Option<usize>,
}

/// The device-resident encodings' budget on a GPU when none is given: room for a few dozen
/// official-size clips of 16 context frames (features 4096 × 2048 floats, 32 MiB; with the
/// context projection, 128 MiB each), a small part of a serving GPU's memory.
pub const DEFAULT_RESIDENT_BUDGET: usize = 4 << 30;

impl Default for EngineOptions {
    fn default() -> Self {
        Self {
            // The CPU arena on and spinning off: faster in every measured case, at c4g-tiny's size
            // (18-30 % a decode) and at the official one (docs/benchmarks.md, "Session
            // defaults"); the runtime's own default (ONNX Runtime's) stays for the refiner.
            session: SessionOptions {
                cpu_arena: true,
                intra_op_spinning: false,
                ..SessionOptions::default()
            },
            time_policy: None,
            max_batch: 16,
            decoder_memory_budget: 4 << 30,
            resident_budget: None,
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
        assert!(o.session.cpu_arena && !o.session.intra_op_spinning);
    }
}
