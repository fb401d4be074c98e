//! One graph's session behind a mutex, and its runs.
//!
//! ONNX Runtime's sessions run through `&mut` in `ort` 2.0, so a model that is shared between
//! threads keeps each session behind a mutex: the model is `Send + Sync` and runs of one graph are
//! serialised (ONNX Runtime already uses every core inside one run; more throughput means more
//! models or a GPU). A run's outputs borrow the session, so [`Graph::run`] hands them to a closure
//! while it still holds the lock; the closure copies out what it needs.
//!
//! [`Graph::run_bound`] runs through an I/O binding instead: inputs that already live in the
//! execution provider's memory ([`Graph::resident`], a copy made once) are bound as they are, so
//! a run reads them without a host-to-device copy; outputs come back to host memory.

use std::sync::{Mutex, PoisonError};

use ort::memory::{AllocationDevice, AllocatorType, MemoryInfo, MemoryType};
use ort::session::{IoBinding, Session, SessionInputs};
use ort::value::{DynValue, Tensor};

use crate::output::RunOutputs;
use crate::{Result, RuntimeError};

/// A named graph's session, run by one caller at a time.
pub struct Graph {
    name: String,
    session: Mutex<Session>,
}

impl std::fmt::Debug for Graph {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Graph")
            .field("name", &self.name)
            .finish_non_exhaustive()
    }
}

impl Graph {
    /// `session` under `name`, the graph's name in error messages ("encoder", "VAE decoder").
    pub fn new(name: impl Into<String>, session: Session) -> Self {
        Self {
            name: name.into(),
            session: Mutex::new(session),
        }
    }

    /// The graph's name in error messages.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Runs the graph on `inputs` and hands its outputs to `read`, under the lock.
    ///
    /// A failed run is [`RuntimeError::Ort`] with the context "running the {name}". A panic while
    /// a run held the lock leaves the session itself intact, so a poisoned lock is taken over
    /// rather than failing every later run.
    pub fn run<'i, 'v: 'i, const N: usize, T>(
        &self,
        inputs: impl Into<SessionInputs<'i, 'v, N>>,
        read: impl FnOnce(&RunOutputs<'_, '_>) -> Result<T>,
    ) -> Result<T> {
        let mut session = self.session.lock().unwrap_or_else(PoisonError::into_inner);
        let outputs = session
            .run(inputs)
            .map_err(RuntimeError::ort(format!("running the {}", self.name)))?;
        read(&RunOutputs::new(&self.name, &outputs))
    }

    /// Runs the graph on the inputs `bind` binds (resident values as they are; host ones are
    /// copied to the device as the binding is made), with `outputs` bound to host memory, and
    /// hands them to `read`, under the lock. Errors as [`run`](Self::run)'s.
    pub fn run_bound<T>(
        &self,
        outputs: &[&str],
        bind: impl FnOnce(&mut IoBinding) -> ort::Result<()>,
        read: impl FnOnce(&RunOutputs<'_, '_>) -> Result<T>,
    ) -> Result<T> {
        let context = || format!("running the {} on bound inputs", self.name);
        let mut session = self.session.lock().unwrap_or_else(PoisonError::into_inner);
        let host = MemoryInfo::new(
            AllocationDevice::CPU,
            0,
            AllocatorType::Device,
            MemoryType::Default,
        )
        .map_err(RuntimeError::ort(context()))?;
        let mut binding = session
            .create_binding()
            .map_err(RuntimeError::ort(context()))?;
        bind(&mut binding).map_err(RuntimeError::ort(context()))?;
        for name in outputs {
            binding
                .bind_output_to_device(*name, &host)
                .map_err(RuntimeError::ort(context()))?;
        }
        let results = session
            .run_binding(&binding)
            .map_err(RuntimeError::ort(context()))?;
        read(&RunOutputs::new(&self.name, &results))
    }

    /// An f32 tensor of `shape` holding `values`, in the memory of `device` (ordinal
    /// `device_id`): a graph run on that device reads it without copying. On the CPU it is an
    /// owned copy.
    pub fn resident(
        shape: &[usize],
        values: &[f32],
        device: AllocationDevice,
        device_id: i32,
    ) -> Result<DynValue> {
        let place = format!("placing {} floats in {device:?} memory", values.len());
        let context = || place.clone();
        let host = Tensor::from_array((shape.to_vec(), values.to_vec()))
            .map_err(RuntimeError::ort(context()))?;
        if device == AllocationDevice::CPU {
            return Ok(host.into_dyn());
        }
        let placed = host
            .to(device, device_id)
            .map_err(RuntimeError::ort(context()))?;
        Ok(placed.into_dyn())
    }
}
