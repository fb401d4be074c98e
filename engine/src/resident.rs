//! Device-resident encodings: the tensors every decode of a clip reads (its features, and in the
//! precomputed decoder form its context projection), kept in the execution provider's memory so
//! that a decode binds them (ONNX Runtime I/O binding) instead of copying them host-to-device
//! on every run. Only the targets' times cross the bus per decode.
//!
//! The copies live in a byte-budget LRU of their own (`EngineOptions::resident_budget`): the
//! host's copy stays authoritative (the clip store's LRU in memory, then its files on disk), so
//! spilling a clip from the device is dropping its device copy; its next decode places it there
//! again. A copy is kept under its encoding's serial number (clones of an encoding share it: they
//! hold the same values); an encoding dropped by the host keeps its device copy until the budget
//! needs the room. An encoding larger than the whole budget is not placed: it decodes from host
//! memory as without residency.
//!
//! On the CPU there is no bus to save (a host tensor is bound as it is), so residency is off by
//! default there; turned on, it runs the same path with host memory as the "device", which is how
//! the CPU tests hold the bound decode to the plain one.

use std::sync::{Arc, Mutex, PoisonError};

use c4g_runtime::Graph;
use ort::memory::AllocationDevice;
use ort::value::DynValue;

use crate::{Encoding, Result};

/// An encoding's decoder inputs in device memory.
pub(crate) struct Resident {
    /// `features` [T, P, C].
    pub(crate) features: DynValue,
    /// `context_projection` [T, P, 3C] (precomputed decoder form only).
    pub(crate) context_projection: Option<DynValue>,
    bytes: usize,
}

/// What the cache holds now and has done, for metrics and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ResidentStats {
    /// Encodings resident now.
    pub encodings: usize,
    /// Their bytes.
    pub bytes: usize,
    /// Copies made to the device (a first decode, or one after a spill).
    pub placements: u64,
    /// Decodes that found their encoding resident.
    pub hits: u64,
    /// Copies dropped to make room.
    pub spills: u64,
}

/// The device copies, least recently used first.
pub(crate) struct ResidentCache {
    budget: usize,
    device: AllocationDevice<'static>,
    device_id: i32,
    state: Mutex<State>,
}

#[derive(Default)]
struct State {
    entries: Vec<(u64, Arc<Resident>)>,
    stats: ResidentStats,
}

impl ResidentCache {
    /// A cache of at most `budget` bytes in `device`'s memory (ordinal `device_id`).
    pub(crate) fn new(budget: usize, device: AllocationDevice<'static>, device_id: i32) -> Self {
        Self {
            budget,
            device,
            device_id,
            state: Mutex::new(State::default()),
        }
    }

    /// `encoding`'s resident copy (with `context_projection`, `[T, P, width]`, when the decoder
    /// takes one), placed now if it is not there; `None` when it alone is over the budget.
    pub(crate) fn get(
        &self,
        encoding: &Encoding,
        context_projection: Option<(&[f32], usize)>,
    ) -> Result<Option<Arc<Resident>>> {
        let serial = encoding.serial();
        {
            let mut state = self.lock();
            if let Some(k) = state.entries.iter().position(|(s, _)| *s == serial) {
                let entry = state.entries.remove(k);
                let found = entry.1.clone();
                state.entries.push(entry);
                state.stats.hits += 1;
                return Ok(Some(found));
            }
        }
        let bytes =
            4 * (encoding.features().len() + context_projection.map_or(0, |(v, _)| v.len()));
        if bytes > self.budget {
            return Ok(None);
        }
        // Placed outside the lock: a copy to the device takes a while, and a second decode of the
        // same clip meanwhile places it again at worst (the later copy replaces the earlier).
        let [t, p, c] = encoding.shape();
        let features = Graph::resident(
            &[t, p, c],
            encoding.features(),
            self.device.clone(),
            self.device_id,
        )?;
        let context_projection = context_projection
            .map(|(values, width)| {
                Graph::resident(&[t, p, width], values, self.device.clone(), self.device_id)
            })
            .transpose()?;
        let resident = Arc::new(Resident {
            features,
            context_projection,
            bytes,
        });
        let mut state = self.lock();
        state.entries.retain(|(s, _)| *s != serial);
        let mut used: usize = state.entries.iter().map(|(_, r)| r.bytes).sum();
        while used + bytes > self.budget && !state.entries.is_empty() {
            let (_, spilled) = state.entries.remove(0);
            used -= spilled.bytes;
            state.stats.spills += 1;
        }
        state.entries.push((serial, resident.clone()));
        state.stats.placements += 1;
        Ok(Some(resident))
    }

    /// What the cache holds and has done.
    pub(crate) fn stats(&self) -> ResidentStats {
        let state = self.lock();
        ResidentStats {
            encodings: state.entries.len(),
            bytes: state.entries.iter().map(|(_, r)| r.bytes).sum(),
            ..state.stats
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }
}
