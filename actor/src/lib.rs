//! bcal-actor: one of the actor processes of a run. [`envs`] steps the battery environments in lockstep
//! with the pure-Rust policy (no libtorch), [`process`] runs the iceoryx2 loop: wait for the replay and the
//! first weights, publish transitions in messages, pick up newer weights, respect the replay's limiter.
//! The library never prints and never exits; `main` does both.

pub mod envs;
pub mod process;

pub use process::{run, ActorArgs, ActorError, ActorReport};
