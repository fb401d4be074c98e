//! `c4g-fitter`: the worker that runs fit jobs (issue 38) for `c4g-server`, in a process of its own
//! so that a fit, minutes of CPU, never starves serving. It pulls jobs over gRPC (`c4g.v1.Jobs`:
//! `TakeFit`, `Progress`, `FinishFit`, `Fail`, `Release`), as refinement workers do.
//!
//! - [`work`]: a job's message turned into the fit's inputs (frames at the working size, their
//!   cameras mapped from the model's square crop onto the whole frame, the start with the area
//!   outside the crop covered), the fit run, and its result;
//! - [`worker`]: the loop: take, fit with progress (the heartbeat, and how a cancellation is
//!   heard), finish or fail, and the drain on SIGTERM (the job goes back to the queue).

pub mod work;
pub mod worker;
