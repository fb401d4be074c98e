//! The alignment's specification as tests: the camera Jacobian against finite differences and
//! its invariants (`jacobian.rs`), and camera recovery on synthetic scenes (`alignment.rs`), both
//! on the deterministic random scenes of `scenes.rs`; the translation-scale fit (`scale.rs`); and
//! the time an alignment takes (`timing.rs`, ignored unless asked for).

mod alignment;
mod jacobian;
mod scale;
mod scenes;
mod timing;
