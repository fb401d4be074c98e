//! Batching across requests: exact decodes of one clip that arrive within a few milliseconds of
//! each other share one decoder run.
//!
//! One request's single target leaves a GPU (and, for a small model, the CPU's thread pool)
//! mostly idle, and every run pays its fixed cost. So an exact decode (a plain decode, or the
//! decode behind a render) joins the open batch of its clip: the first request opens it and
//! starts its timer (`C4G_BATCH_WAIT_MS`); requests arriving meanwhile add their targets, up to
//! the engine's batch for the clip (`Engine::decode_batch_size`, its memory model); a batch that
//! is full, or whose time is up, runs as one piece of work on a work slot, and each request gets
//! its own sets back. Requests for other clips, approximations (keyframes, pruning) and long
//! requests (already a batch) go their own way.
//!
//! A request whose client goes away stops waiting; its batch still runs for the others, and runs
//! not at all when nobody waits for it. Metrics: `c4g_decode_batch_targets` (targets per batched
//! run), `c4g_decode_batch_requests` (requests it answered) and
//! `c4g_decode_batch_wait_seconds` (from a request's arrival to its batch's start).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use c4g_engine::Encoding;
use c4g_scene::GaussianSet;
use tokio::sync::oneshot;

use crate::ServiceError;
use c4g_engine::{Engine, Keyframes};

use crate::sets::decoder;
use crate::work::WorkSlots;

/// The sets one request gets back, or why its batch failed.
type Reply = Result<Vec<(f64, GaussianSet)>, Arc<ServiceError>>;

/// One request in an open batch.
struct Member {
    times: Vec<f64>,
    arrived: Instant,
    reply: oneshot::Sender<Reply>,
}

/// The open batch of one clip.
struct Open {
    /// Tells this batch from a later one of the same clip (the timer flushes only its own).
    serial: u64,
    encoding: Arc<Encoding>,
    members: Vec<Member>,
    targets: usize,
    capacity: usize,
}

/// See the module documentation.
pub struct DecodeBatcher {
    engine: Arc<Engine>,
    work: Arc<WorkSlots>,
    wait: Duration,
    open: Mutex<HashMap<String, Open>>,
    serial: std::sync::atomic::AtomicU64,
}

impl DecodeBatcher {
    /// Batches of `engine`'s decodes, run on `work`, that wait up to `wait` for company (zero:
    /// no batching).
    pub fn new(engine: Arc<Engine>, work: Arc<WorkSlots>, wait: Duration) -> Self {
        Self {
            engine,
            work,
            wait,
            open: Mutex::new(HashMap::new()),
            serial: std::sync::atomic::AtomicU64::new(0),
        }
    }

    /// How long a batch waits for company.
    pub fn wait(&self) -> Duration {
        self.wait
    }

    /// One exact decoder run on a work slot.
    async fn run_now(
        &self,
        encoding: Arc<Encoding>,
        times: Vec<f64>,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let engine = self.engine.clone();
        self.work
            .run(move || decoder::decode(&engine, &encoding, &times, &Keyframes::Exact, None))
            .await
    }

    /// The exact sets of clip `id` at `times` (already checked), decoded in a batch with other
    /// requests' targets when some arrive within the wait.
    pub async fn decode(
        self: &Arc<Self>,
        id: &str,
        encoding: Arc<Encoding>,
        times: Vec<f64>,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let capacity = self.engine.decode_batch_size(encoding.frame_count()).max(1);
        if self.wait.is_zero() || times.len() >= capacity {
            return self.run_now(encoding, times).await;
        }
        let (reply, answer) = oneshot::channel();
        let member = Member {
            times,
            arrived: Instant::now(),
            reply,
        };
        let (full, opened) = {
            let mut open = self.lock();
            let joinable = open
                .get(id)
                .is_some_and(|batch| batch.targets + member.times.len() <= batch.capacity);
            if !joinable {
                // A batch with no room runs as it is, and this request opens the next one.
                let full = open.remove(id);
                let serial = self
                    .serial
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let targets = member.times.len();
                open.insert(
                    id.to_owned(),
                    Open {
                        serial,
                        encoding,
                        members: vec![member],
                        targets,
                        capacity,
                    },
                );
                (full, Some(serial))
            } else if let Some(batch) = open.get_mut(id) {
                batch.targets += member.times.len();
                batch.members.push(member);
                let full = if batch.targets >= batch.capacity {
                    open.remove(id)
                } else {
                    None
                };
                (full, None)
            } else {
                (None, None)
            }
        };
        if let Some(full) = full {
            tokio::spawn(run(self.clone(), full));
        }
        if let Some(serial) = opened {
            self.flush_after_wait(id, serial);
        }
        match answer.await {
            Ok(Ok(sets)) => Ok(sets),
            Ok(Err(shared)) => Err(ServiceError::Shared(shared)),
            Err(_) => Err(ServiceError::Internal(
                "a batched decode ended without an answer".into(),
            )),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<String, Open>> {
        self.open.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Runs batch `serial` of clip `id` once the wait is over, unless it ran already (full).
    fn flush_after_wait(self: &Arc<Self>, id: &str, serial: u64) {
        let (batcher, id, wait) = (self.clone(), id.to_owned(), self.wait);
        tokio::spawn(async move {
            tokio::time::sleep(wait).await;
            let batch = {
                let mut open = batcher.lock();
                match open.get(&id) {
                    Some(batch) if batch.serial == serial => open.remove(&id),
                    _ => None,
                }
            };
            if let Some(batch) = batch {
                run(batcher, batch).await;
            }
        });
    }
}

/// One decoder call (chunked by the engine's batch) for every member's targets, the sets handed
/// back to each. Nobody waiting: nothing runs.
async fn run(batcher: Arc<DecodeBatcher>, batch: Open) {
    let members: Vec<Member> = batch
        .members
        .into_iter()
        .filter(|m| !m.reply.is_closed())
        .collect();
    if members.is_empty() {
        return;
    }
    let started = Instant::now();
    for member in &members {
        metrics::histogram!("c4g_decode_batch_wait_seconds")
            .record(started.duration_since(member.arrived).as_secs_f64());
    }
    let times: Vec<f64> = members.iter().flat_map(|m| m.times.clone()).collect();
    metrics::histogram!("c4g_decode_batch_targets").record(times.len() as f64);
    metrics::histogram!("c4g_decode_batch_requests").record(members.len() as f64);
    let encoding = batch.encoding;
    let decoded = batcher.run_now(encoding, times).await;
    match decoded {
        Ok(sets) => {
            let mut sets = sets.into_iter();
            for member in members {
                let own: Vec<_> = sets.by_ref().take(member.times.len()).collect();
                let _ = member.reply.send(Ok(own));
            }
        }
        Err(e) => {
            let shared = Arc::new(e);
            for member in members {
                let _ = member.reply.send(Err(shared.clone()));
            }
        }
    }
}
