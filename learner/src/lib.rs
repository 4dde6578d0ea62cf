//! bcal-learner as a library: the Lyapunov-based actor-critic ([`lac`]: networks, one function per loss,
//! the update step) and its checkpoints ([`checkpoint`]: safetensors + meta.json, atomic, resumable). The
//! process loop (`process.rs`, `main.rs`) feeds it batches from the replay and broadcasts the actor's
//! weights. Like every bcal library it returns typed errors and never prints or exits.

pub mod checkpoint;
pub mod lac;

pub use lac::{Lac, LacError, UpdateMetrics};
