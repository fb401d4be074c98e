//! What was uploaded: the lowest layer of the core. An upload becomes timed context frames
//! (`intake`), is encoded once and kept (`store`, as `record`s and features), optionally shared
//! with other replicas (`shared`), always through crash-safe writes (`durable`). What a fit made of
//! a clip's frames is kept with it (`fitted`).

pub mod durable;
pub mod fitted;
pub mod intake;
pub mod record;
pub mod shared;
pub mod store;
