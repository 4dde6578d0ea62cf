//! bcal-learner as a library: the Lyapunov-based actor-critic ([`lac`]: networks, one function per loss,
//! the update step), its checkpoints ([`checkpoint`]: safetensors + meta.json, atomic, resumable) and the
//! process loop ([`process`]: batches from the replay, weights broadcast, validation, best-policy files);
//! `main.rs` only parses arguments. Like every bcal library it never prints or exits.

pub mod checkpoint;
pub mod lac;
pub mod process;

pub use lac::{Lac, LacError, UpdateMetrics};
