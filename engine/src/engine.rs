//! The engine: one model package on ONNX Runtime, from context frames to Gaussian sets.
//!
//! `encode` runs once per clip (all context frames in one encoder run: the encoder attends across
//! frames); `decode` runs the small decoder once per target time, batching targets up to
//! `max_batch` per run and fewer when one run would exceed `decoder_memory_budget`. Every shape
//! is checked against the package's manifest before it reaches
//! ONNX Runtime, and every output against the contract after, so a caller sees a clear error
//! rather than a runtime shape failure or a silently wrong scene.
//!
//! A package in the precomputed decoder form also has a context projection graph: `encode` runs
//! it once per clip and the encoding keeps its result, which every decode of the clip feeds the
//! decoder (an encoding rebuilt from its parts gets it on its first decode).
//!
//! A package whose decoder takes `query_indices` also decodes a [`QuerySubset`] of its queries
//! alone (`decode_subset`): an approximation, since the kept queries attend to fewer tokens. Its
//! full decodes leave the indices out, and the graph's default (every query) gives the full
//! decoder's Gaussians, bit for bit.
//!
//! Each graph is a `c4g_runtime::Graph`, its session behind a mutex (`ort` 2.0 runs sessions
//! through `&mut`): the engine is `Send + Sync` and calls on one graph are serialised (ONNX
//! Runtime already uses every core inside one run; more throughput means more engines or a GPU).

use std::borrow::Cow;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use c4g_runtime::{ExecutionProvider, Graph, RunOutputs, RuntimeError, create_session};
use c4g_scene::{FeatureBlock, GaussianSet};
use image::RgbImage;
use ort::memory::AllocationDevice;
use ort::value::{Tensor, TensorRef};

use crate::encoding::{ContextFrame, Encoding, encoding_order};
use crate::error::ShapeDim::{Fixed, Free};
use crate::graph::{Contract, GAUSSIAN_CHANNELS, context_projection_width};
use crate::options::{DEFAULT_RESIDENT_BUDGET, EngineOptions};
use crate::package::{AttentionKind, DecoderForm, Manifest, Package};
use crate::query_subset::QuerySubset;
use crate::resident::{Resident, ResidentCache, ResidentStats};
use crate::time::{NormalizedTimes, TimePolicy};
use crate::{EngineError, Result, preprocess};

/// Heads assumed when a package does not declare `architecture.decoder_heads` (C4G's own count).
const DEFAULT_DECODER_HEADS: usize = 16;

/// Identifies an engine to the context projections it leaves in encodings (they depend on its
/// package's weights); unique within the process.
static NEXT_ENGINE_ID: AtomicU64 = AtomicU64::new(0);

/// A loaded model package, ready to encode clips and decode Gaussian sets.
pub struct Engine {
    id: u64,
    package: Package,
    options: EngineOptions,
    time_policy: TimePolicy,
    encoder: Graph,
    context_projection: Option<Graph>,
    decoder: Graph,
    feature_decoder: Option<Graph>,
    /// Device-resident encodings, when on (`EngineOptions::resident_budget`).
    resident: Option<ResidentCache>,
}

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Engine")
            .field("package", &self.package.dir())
            .field("options", &self.options)
            .field("time_policy", &self.time_policy)
            .field("context_projection", &self.context_projection.is_some())
            .field("feature_decoder", &self.feature_decoder.is_some())
            .finish()
    }
}

impl Engine {
    /// Opens the package in `package_dir` and loads its graphs.
    pub fn load(package_dir: impl AsRef<Path>, options: EngineOptions) -> Result<Self> {
        Self::from_package(Package::open(package_dir)?, options)
    }

    /// Loads the graphs of an opened package, checking each against the package contract.
    pub fn from_package(package: Package, options: EngineOptions) -> Result<Self> {
        if options.max_batch == 0 {
            return Err(EngineError::InvalidInput(
                "max_batch must be at least 1".to_owned(),
            ));
        }
        let m = package.manifest();
        let load = |name: &str, path: &Path, contract: Contract| -> Result<Graph> {
            let session = create_session(path, &options.session)?;
            contract.check(&session, package.dir())?;
            Ok(Graph::new(name, session))
        };
        let encoder = load("encoder", &package.encoder_path(), Contract::encoder(m))?;
        let context_projection = match (m.decoder_form, package.context_projection_path()) {
            (DecoderForm::Precomputed, Some(path)) => Some(load(
                "context projection",
                &path,
                Contract::context_projection(m),
            )?),
            _ => None,
        };
        let decoder = load("decoder", &package.decoder_path(), Contract::decoder(m))?;
        let feature_decoder = match (package.feature_decoder_path(), m.feature_decoder_width()) {
            (Some(path), Some(width)) => Some(load(
                "feature decoder",
                &path,
                Contract::feature_decoder(m, width),
            )?),
            _ => None,
        };
        let time_policy = options
            .time_policy
            .unwrap_or_else(|| m.declared_time_policy());
        let resident = resident_cache(&options);
        Ok(Self {
            id: NEXT_ENGINE_ID.fetch_add(1, Ordering::Relaxed),
            package,
            options,
            time_policy,
            encoder,
            context_projection,
            decoder,
            feature_decoder,
            resident,
        })
    }

    /// What the device-resident encodings hold and have done (`None`: residency is off).
    pub fn resident_stats(&self) -> Option<ResidentStats> {
        self.resident.as_ref().map(ResidentCache::stats)
    }

    /// The package this engine runs.
    pub fn package(&self) -> &Package {
        &self.package
    }

    /// The package's manifest.
    pub fn manifest(&self) -> &Manifest {
        self.package.manifest()
    }

    /// The options the engine was loaded with.
    pub fn options(&self) -> &EngineOptions {
        &self.options
    }

    /// The time policy decodes use: the options' when they name one, else the package's.
    pub fn time_policy(&self) -> TimePolicy {
        self.time_policy
    }

    /// True when the package's decoder can run a [`QuerySubset`] of its queries alone.
    pub fn has_query_subset(&self) -> bool {
        self.manifest().decoder_query_subset
    }

    /// True when the package can lift feature maps onto its Gaussians.
    pub fn has_feature_decoder(&self) -> bool {
        self.feature_decoder.is_some()
    }

    /// The package's preprocessing of one decoded RGB frame: `[3, H, W]` encoder input.
    pub fn preprocess(&self, frame: &RgbImage) -> Result<Vec<f32>> {
        preprocess::preprocess(frame, &self.manifest().input)
    }

    /// Encodes context frames into an [`Encoding`].
    ///
    /// Frames are encoded in time order (ties by pixel content), whatever order they come in; the
    /// encoding remembers where each came from. For a package in the precomputed decoder form the
    /// encoding also holds the context projection.
    pub fn encode(&self, frames: &[ContextFrame]) -> Result<Encoding> {
        self.check_frames(frames)?;
        let order = encoding_order(frames);
        let mut pixels = Vec::with_capacity(frames.len() * frames[0].pixels.len());
        for &i in &order {
            pixels.extend_from_slice(&frames[i].pixels);
        }
        let m = self.manifest();
        let (t, h, w) = (
            frames.len(),
            m.input.height as usize,
            m.input.width as usize,
        );
        let (p, c) = (m.tokens_per_frame, m.feature_width);
        let input = TensorRef::from_array_view(([t, 3, h, w], pixels.as_slice()))
            .map_err(RuntimeError::ort("preparing the frames tensor"))?;
        let features = self
            .encoder
            .run(ort::inputs!["frames" => input], |outputs| {
                Ok(outputs.f32("features", &[t, p, c])?.to_vec())
            })?;
        let times = order.iter().map(|&i| frames[i].time).collect();
        let encoding = Encoding::from_parts(times, order, features, [t, p, c])?;
        // Made now and kept in the encoding, for every decode of this clip.
        self.context_projection(&encoding)?;
        Ok(encoding)
    }

    /// Decodes the Gaussians at each target time, normalising times with the engine's policy
    /// (and the encoding's source frame step, when it has one).
    pub fn decode(&self, encoding: &Encoding, targets: &[f64]) -> Result<Vec<GaussianSet>> {
        let times = self.normalize(encoding, targets)?;
        self.decode_normalized(encoding, &times)
    }

    /// Decodes the Gaussians for already-normalised times (one row per target, context times in
    /// the encoding's order): the decoder with nothing in front of it, for parity tests and for
    /// callers with their own time policy.
    pub fn decode_normalized(
        &self,
        encoding: &Encoding,
        times: &[NormalizedTimes],
    ) -> Result<Vec<GaussianSet>> {
        self.decode_queries(encoding, times, None)
    }

    /// Decodes the Gaussians of the queries `subset` alone at each target time: each set holds
    /// `subset.len()` Gaussians, in the full set's order. Not the full decode's Gaussians with the
    /// others removed: the dropped queries' tokens leave the decoder, and the kept ones attend to
    /// each other and the context without them (an approximation, measured in
    /// `docs/tradeoffs.md`). A package whose decoder does not take `query_indices` refuses it.
    pub fn decode_subset(
        &self,
        encoding: &Encoding,
        targets: &[f64],
        subset: &QuerySubset,
    ) -> Result<Vec<GaussianSet>> {
        let times = self.normalize(encoding, targets)?;
        self.decode_subset_normalized(encoding, &times, subset)
    }

    /// [`decode`](Self::decode), or [`decode_subset`](Self::decode_subset) when `queries` is
    /// given.
    pub fn decode_on(
        &self,
        encoding: &Encoding,
        targets: &[f64],
        queries: Option<&QuerySubset>,
    ) -> Result<Vec<GaussianSet>> {
        match queries {
            Some(subset) => self.decode_subset(encoding, targets, subset),
            None => self.decode(encoding, targets),
        }
    }

    /// [`decode_subset`](Self::decode_subset) for already-normalised times.
    pub fn decode_subset_normalized(
        &self,
        encoding: &Encoding,
        times: &[NormalizedTimes],
        subset: &QuerySubset,
    ) -> Result<Vec<GaussianSet>> {
        if !self.has_query_subset() {
            return Err(EngineError::NoQuerySubset {
                package: self.manifest().name.clone(),
            });
        }
        let n = self.manifest().gaussian_count;
        if let Some(&last) = subset.indices().last()
            && last as usize >= n
        {
            return Err(EngineError::InvalidInput(format!(
                "query index {last} is out of range: the package decodes {n} queries"
            )));
        }
        self.decode_queries(encoding, times, Some(subset))
    }

    /// The decoder over `times` in batches, on `queries` when given (else on all).
    fn decode_queries(
        &self,
        encoding: &Encoding,
        times: &[NormalizedTimes],
        queries: Option<&QuerySubset>,
    ) -> Result<Vec<GaussianSet>> {
        self.check_encoding(encoding, times)?;
        let projection = self.context_projection(encoding)?;
        let resident = match &self.resident {
            Some(cache) => {
                let width = context_projection_width(self.manifest());
                cache.get(encoding, projection.as_deref().map(|p| (p, width)))?
            }
            None => None,
        };
        let batch = self.decode_batch_size(encoding.frame_count());
        let mut sets = Vec::with_capacity(times.len());
        for chunk in times.chunks(batch) {
            let mut inputs = DecoderInputs::new(encoding, projection.as_deref(), chunk, queries);
            inputs.resident = resident.clone();
            sets.extend(self.decode_chunk(&inputs, None)?);
        }
        Ok(sets)
    }

    /// Decodes the Gaussians at each target time with one lifted feature vector per Gaussian.
    ///
    /// `context_feature_maps` is `[T, P, F]` (one F-wide vector per patch of each context frame),
    /// frames in the order they were given to [`encode`](Self::encode).
    pub fn decode_features(
        &self,
        encoding: &Encoding,
        context_feature_maps: &[f32],
        targets: &[f64],
    ) -> Result<Vec<GaussianSet>> {
        let times = self.normalize(encoding, targets)?;
        self.decode_features_normalized(encoding, context_feature_maps, &times)
    }

    /// The normalised times `decode` feeds the decoder for `targets` of `encoding`.
    pub fn normalize(&self, encoding: &Encoding, targets: &[f64]) -> Result<Vec<NormalizedTimes>> {
        self.time_policy
            .normalize_all_with_step(encoding.times(), encoding.frame_step(), targets)
    }

    /// [`decode_features`](Self::decode_features) for already-normalised times.
    pub fn decode_features_normalized(
        &self,
        encoding: &Encoding,
        context_feature_maps: &[f32],
        times: &[NormalizedTimes],
    ) -> Result<Vec<GaussianSet>> {
        let width = self.feature_width()?;
        self.check_encoding(encoding, times)?;
        let maps = self.encoded_order_maps(encoding, context_feature_maps, width)?;
        let projection = self.context_projection(encoding)?;
        let batch = self.decode_batch_size(encoding.frame_count());
        let mut sets = Vec::with_capacity(times.len());
        for chunk in times.chunks(batch) {
            // The feature decoder has no query subset: its Gaussians are all N.
            let inputs = DecoderInputs::new(encoding, projection.as_deref(), chunk, None);
            sets.extend(self.decode_chunk(&inputs, Some((&maps, width)))?);
        }
        Ok(sets)
    }

    /// Targets per decoder run for an encoding of `frames` frames: `max_batch`, lowered so that
    /// one run's estimated memory stays within `decoder_memory_budget` (never below 1).
    ///
    /// The estimate per target: with plain attention the score matrices dominate,
    /// 2 · heads · L² floats (two layers' worth live at once); with fused attention only
    /// activations remain, about 8 · C · L floats (q, k, v, attention output, residual and the
    /// MLP's hidden rows), L = T·P + N tokens of width C. The precomputed decoder form holds no
    /// more per target (its first layer's q, k and v are assembled from the context projection
    /// instead of multiplied out; the projection is the encoding's, not the run's): measured at the
    /// official size with T = 16 and fused attention, a run's peak working set is about 430 MiB a
    /// target precomputed and 480 MiB plain, against this estimate's 384 MiB.
    pub fn decode_batch_size(&self, frames: usize) -> usize {
        let max = self.options.max_batch.max(1);
        if self.options.decoder_memory_budget == 0 {
            return max;
        }
        let m = self.manifest();
        let tokens = (frames * m.tokens_per_frame + m.gaussian_count) as f64;
        let floats = match m.attention {
            AttentionKind::Plain => {
                let heads = m.decoder_heads().unwrap_or(DEFAULT_DECODER_HEADS) as f64;
                2.0 * heads * tokens * tokens
            }
            AttentionKind::Fused => 8.0 * m.feature_width as f64 * tokens,
        };
        let per_target = floats * std::mem::size_of::<f32>() as f64;
        let fits = (self.options.decoder_memory_budget as f64 / per_target).floor();
        (fits as usize).clamp(1, max)
    }

    fn feature_width(&self) -> Result<usize> {
        match (
            &self.feature_decoder,
            self.manifest().feature_decoder_width(),
        ) {
            (Some(_), Some(width)) => Ok(width),
            _ => Err(EngineError::NoFeatureDecoder {
                package: self.manifest().name.clone(),
            }),
        }
    }

    fn check_frames(&self, frames: &[ContextFrame]) -> Result<()> {
        if frames.is_empty() {
            return Err(EngineError::InvalidInput(
                "encoding needs at least one context frame".to_owned(),
            ));
        }
        let input = &self.manifest().input;
        let expected = 3 * input.height as usize * input.width as usize;
        for (i, frame) in frames.iter().enumerate() {
            if !frame.time.is_finite() {
                return Err(EngineError::NonFiniteTime {
                    what: "context",
                    value: frame.time,
                });
            }
            if frame.pixels.len() != expected {
                return Err(EngineError::InvalidInput(format!(
                    "frame {i} holds {} values; the package expects preprocessed [3, {}, {}] frames ({expected} values)",
                    frame.pixels.len(),
                    input.height,
                    input.width
                )));
            }
            if frame.pixels.iter().any(|v| !v.is_finite()) {
                return Err(EngineError::InvalidInput(format!(
                    "frame {i} has pixel values that are not finite"
                )));
            }
        }
        Ok(())
    }

    fn check_encoding(&self, encoding: &Encoding, times: &[NormalizedTimes]) -> Result<()> {
        let m = self.manifest();
        let [t, p, c] = encoding.shape();
        if p != m.tokens_per_frame || c != m.feature_width {
            return Err(EngineError::shape(
                "the encoding's features",
                &[Free("T"), Fixed(m.tokens_per_frame), Fixed(m.feature_width)],
                &[t, p, c],
            ));
        }
        for (b, row) in times.iter().enumerate() {
            if row.context.len() != t {
                return Err(EngineError::shape(
                    format!("context times of target {b}"),
                    &[Fixed(t)],
                    &[row.context.len()],
                ));
            }
            if !row.target.is_finite() || row.context.iter().any(|v| !v.is_finite()) {
                return Err(EngineError::InvalidInput(format!(
                    "normalised times of target {b} are not all finite"
                )));
            }
        }
        Ok(())
    }

    /// The caller's `[T, P, F]` feature maps, checked and rearranged into the encoding's order.
    fn encoded_order_maps(
        &self,
        encoding: &Encoding,
        maps: &[f32],
        width: usize,
    ) -> Result<Vec<f32>> {
        let (t, p) = (encoding.frame_count(), self.manifest().tokens_per_frame);
        let per_frame = p * width;
        if maps.len() != t * per_frame {
            return Err(EngineError::Shape {
                what: "context feature maps".to_owned(),
                expected: format!("[{t}, {p}, {width}] ({} values)", t * per_frame),
                actual: format!("{} values", maps.len()),
            });
        }
        if maps.iter().any(|v| !v.is_finite()) {
            return Err(EngineError::InvalidInput(
                "context feature maps hold values that are not finite".to_owned(),
            ));
        }
        let mut ordered = Vec::with_capacity(maps.len());
        for &i in encoding.frame_order() {
            ordered.extend_from_slice(&maps[i * per_frame..(i + 1) * per_frame]);
        }
        Ok(ordered)
    }

    /// The context projection `encoding`'s decodes feed the decoder: `None` for a plain package;
    /// else the one the encoding holds from this engine, or one computed now (and kept in the
    /// encoding, unless it already holds another engine's).
    fn context_projection<'e>(&self, encoding: &'e Encoding) -> Result<Option<Cow<'e, [f32]>>> {
        let Some(graph) = &self.context_projection else {
            return Ok(None);
        };
        if let Some(values) = encoding.context_projection_by(self.id) {
            return Ok(Some(Cow::Borrowed(values)));
        }
        let [t, p, c] = encoding.shape();
        let input = TensorRef::from_array_view(([t, p, c], encoding.features()))
            .map_err(RuntimeError::ort("preparing the features tensor"))?;
        let shape = [t, p, context_projection_width(self.manifest())];
        let values = graph.run(ort::inputs!["features" => input], |outputs| {
            Ok(outputs.f32("context_projection", &shape)?.to_vec())
        })?;
        Ok(Some(encoding.keep_context_projection(self.id, values)))
    }

    /// One decoder run (and one feature-decoder run when `maps` is given) for one batch of
    /// targets.
    fn decode_chunk(
        &self,
        inputs: &DecoderInputs<'_>,
        maps: Option<(&[f32], usize)>,
    ) -> Result<Vec<GaussianSet>> {
        let gaussians = self.run_decoder(inputs)?;
        let lifted = match maps {
            Some((maps, width)) => Some((self.run_feature_decoder(inputs, maps, width)?, width)),
            None => None,
        };
        let n = inputs.query_count(self.manifest());
        (0..inputs.batch)
            .map(|i| {
                let invalid =
                    |e: c4g_scene::SceneError| EngineError::ModelOutput(format!("target {i}: {e}"));
                let per_set = n * GAUSSIAN_CHANNELS;
                let mut set =
                    GaussianSet::from_canonical(&gaussians[i * per_set..(i + 1) * per_set])
                        .map_err(invalid)?;
                if let Some((values, width)) = &lifted {
                    let rows = values[i * n * width..(i + 1) * n * width].to_vec();
                    let block = FeatureBlock::new(*width, rows).map_err(invalid)?;
                    set = set.with_features(block).map_err(invalid)?;
                }
                set.validate().map_err(invalid)?;
                Ok(set)
            })
            .collect()
    }

    /// `gaussians` [B, N, 14] for one batch ([B, Q, 14] on a query subset).
    fn run_decoder(&self, inputs: &DecoderInputs<'_>) -> Result<Vec<f32>> {
        let shape = [
            inputs.batch,
            inputs.query_count(self.manifest()),
            GAUSSIAN_CHANNELS,
        ];
        let read = |outputs: &RunOutputs<'_, '_>| Ok(outputs.f32("gaussians", &shape)?.to_vec());
        if let Some(resident) = &inputs.resident {
            return self.run_decoder_bound(inputs, resident, read);
        }
        let (features, context_times, target_times) = inputs.tensors()?;
        let mut feeds = ort::inputs![
            "features" => features,
            "context_times" => context_times,
            "target_times" => target_times,
        ];
        if let Some(projection) = inputs.context_projection_tensor(self.manifest())? {
            feeds.push(("context_projection".into(), projection.into()));
        }
        if let Some(queries) = inputs.query_indices_tensor()? {
            feeds.push(("query_indices".into(), queries.into()));
        }
        Ok(self.decoder.run(feeds, read)?)
    }

    /// [`run_decoder`](Self::run_decoder) with the encoding's tensors resident on the device:
    /// they are bound as they are, the targets' times and query indices copied in.
    fn run_decoder_bound(
        &self,
        inputs: &DecoderInputs<'_>,
        resident: &Resident,
        read: impl FnOnce(&RunOutputs<'_, '_>) -> c4g_runtime::Result<Vec<f32>>,
    ) -> Result<Vec<f32>> {
        // Owned tensors: ort clones a borrowed one through its own device copy to bind it, which
        // takes a lock the binding already holds (ort 2.0.0-rc.15 deadlocks there).
        let prepare = || RuntimeError::ort("preparing the decoder's inputs");
        let [t, _, _] = inputs.shape;
        let context_times =
            Tensor::from_array(([inputs.batch, t], inputs.context.clone())).map_err(prepare())?;
        let target_times =
            Tensor::from_array(([inputs.batch], inputs.target.clone())).map_err(prepare())?;
        let queries = inputs
            .queries
            .map(|q| Tensor::from_array(([q.len()], q.indices().to_vec())))
            .transpose()
            .map_err(RuntimeError::ort("preparing the query indices"))?;
        let bind = |binding: &mut ort::session::IoBinding| {
            binding.bind_input("features", &resident.features)?;
            binding.bind_input("context_times", &context_times)?;
            binding.bind_input("target_times", &target_times)?;
            if let Some(projection) = &resident.context_projection {
                binding.bind_input("context_projection", projection)?;
            }
            if let Some(queries) = &queries {
                binding.bind_input("query_indices", queries)?;
            }
            Ok(())
        };
        Ok(self.decoder.run_bound(&["gaussians"], bind, read)?)
    }

    /// `gaussian_features` [B, N, F] for one batch; `maps` is `[T, P, F]` in encoded order.
    fn run_feature_decoder(
        &self,
        inputs: &DecoderInputs<'_>,
        maps: &[f32],
        width: usize,
    ) -> Result<Vec<f32>> {
        let Some(graph) = &self.feature_decoder else {
            return Err(EngineError::NoFeatureDecoder {
                package: self.manifest().name.clone(),
            });
        };
        let (features, context_times, target_times) = inputs.tensors()?;
        let [t, p, _] = inputs.shape;
        let maps = TensorRef::from_array_view(([t, p, width], maps))
            .map_err(RuntimeError::ort("preparing the context feature maps"))?;
        let shape = [inputs.batch, self.manifest().gaussian_count, width];
        let inputs = ort::inputs![
            "features" => features,
            "context_times" => context_times,
            "target_times" => target_times,
            "context_feature_maps" => maps,
        ];
        Ok(graph.run(inputs, |outputs| {
            Ok(outputs.f32("gaussian_features", &shape)?.to_vec())
        })?)
    }
}

/// What every decoder graph takes for one batch of targets: the encoding's features and each
/// target's normalised times, flattened to `[B, T]` and `[B]`; and, for the Gaussian decoder of a
/// precomputed-form package, the context projection; for one that takes `query_indices`, the
/// queries to decode.
struct DecoderInputs<'a> {
    features: &'a [f32],
    /// The encoding's tensors on the device, when resident: the decoder binds those.
    resident: Option<Arc<Resident>>,
    context_projection: Option<&'a [f32]>,
    queries: Option<&'a QuerySubset>,
    shape: [usize; 3],
    batch: usize,
    context: Vec<f32>,
    target: Vec<f32>,
}

impl<'a> DecoderInputs<'a> {
    fn new(
        encoding: &'a Encoding,
        context_projection: Option<&'a [f32]>,
        times: &[NormalizedTimes],
        queries: Option<&'a QuerySubset>,
    ) -> Self {
        Self {
            features: encoding.features(),
            resident: None,
            context_projection,
            queries,
            shape: encoding.shape(),
            batch: times.len(),
            context: times
                .iter()
                .flat_map(|r| r.context.iter().copied())
                .collect(),
            target: times.iter().map(|r| r.target).collect(),
        }
    }

    /// Borrowed tensors of `features`, `context_times` and `target_times`.
    fn tensors(&self) -> Result<(TensorRef<'_, f32>, TensorRef<'_, f32>, TensorRef<'_, f32>)> {
        let prepare = || RuntimeError::ort("preparing the decoder's inputs");
        let [t, _, _] = self.shape;
        Ok((
            TensorRef::from_array_view((self.shape, self.features)).map_err(prepare())?,
            TensorRef::from_array_view(([self.batch, t], self.context.as_slice()))
                .map_err(prepare())?,
            TensorRef::from_array_view(([self.batch], self.target.as_slice())).map_err(prepare())?,
        ))
    }

    /// Gaussians per set: the subset's size, else the package's N.
    fn query_count(&self, m: &Manifest) -> usize {
        self.queries.map_or(m.gaussian_count, QuerySubset::len)
    }

    /// A borrowed int64 tensor of the query indices `[Q]`, when the decoder takes them.
    fn query_indices_tensor(&self) -> Result<Option<TensorRef<'_, i64>>> {
        let Some(queries) = self.queries else {
            return Ok(None);
        };
        let tensor = TensorRef::from_array_view(([queries.len()], queries.indices()))
            .map_err(RuntimeError::ort("preparing the query indices"))?;
        Ok(Some(tensor))
    }

    /// A borrowed tensor of the context projection `[T, P, 3C]`, when there is one.
    fn context_projection_tensor(&self, m: &Manifest) -> Result<Option<TensorRef<'_, f32>>> {
        let Some(values) = self.context_projection else {
            return Ok(None);
        };
        let [t, p, _] = self.shape;
        let tensor = TensorRef::from_array_view(([t, p, context_projection_width(m)], values))
            .map_err(RuntimeError::ort("preparing the context projection"))?;
        Ok(Some(tensor))
    }
}

/// The device-resident encodings `options` ask for (see `EngineOptions::resident_budget`).
fn resident_cache(options: &EngineOptions) -> Option<ResidentCache> {
    let (device, device_id, default) = match options.session.execution_provider {
        ExecutionProvider::Cpu => (AllocationDevice::CPU, 0, 0),
        ExecutionProvider::Cuda { device_id } => {
            (AllocationDevice::CUDA, device_id, DEFAULT_RESIDENT_BUDGET)
        }
    };
    let budget = options.resident_budget.unwrap_or(default);
    (budget > 0).then(|| ResidentCache::new(budget, device, device_id))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn engine_is_send_and_sync() {
        fn assert_send_sync<T: Send + Sync>() {}
        assert_send_sync::<Engine>();
        assert_send_sync::<Encoding>();
    }
}
