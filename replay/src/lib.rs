//! bcal-replay: the one replay process of a run. [`store`] holds the data rules (ring buffer, Reverb-style
//! sample-to-insert limiter, quarantine, loss accounting) and [`process`] the iceoryx2 loop that creates
//! the run's services, feeds the store from the actors and serves batches to the learner. The library
//! never prints and never exits; `main` does both.

pub mod process;
pub mod snapshot;
pub mod store;

pub use process::{run, ReplayError, ReplayReport};
