//! Learner updates per second: `Lac::update` in process on a fixed minibatch of random finite transitions
//! (the same measurement as `learner/tests/lac_throughput.rs`), experiment multi (obs 15, act 2).

use bcal_common::config::TrainConfig;
use bcal_common::dataset::Experiment;
use bcal_common::mdp::{ActionMap, ObservationKind};
use bcal_common::policy::PolicyLayout;
use bcal_common::wire::Transition;
use bcal_learner::Lac;
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LearnerRow {
    /// Actor and critic hidden widths.
    pub hidden: Vec<usize>,
    /// Minibatch.
    pub batch: u64,
    /// libtorch intra-op threads.
    pub torch_threads: u64,
    pub updates_per_s: f64,
    pub ms_per_update: f64,
    /// Transitions consumed per second (updates/s x batch).
    pub samples_per_s: f64,
    /// Updates timed (after the warm-up).
    pub updates: u64,
}

/// Warm-up updates (allocator, libtorch kernels) before the clock starts.
const WARMUP: usize = 10;

/// Times `Lac::update` for `window` (at least 10 updates) with `hidden` networks at `batch`.
pub fn measure(hidden: &[usize], batch: usize, torch_threads: usize, window: Duration) -> anyhow::Result<LearnerRow> {
    let mut c = TrainConfig { experiment: Experiment::Multi, ..Default::default() };
    c.lac.hidden = hidden.to_vec();
    c.lac.batch_size = batch;
    c.learner.torch_threads = torch_threads;
    let v = c.validate()?;
    let obs_dim = ObservationKind::FullState.dim();
    let act_dim = ActionMap::from_config(c.experiment, &c.env).dim();
    let transitions = Transition::synthetic_batch(1, batch, obs_dim, act_dim);
    let threads_before = tch::get_num_threads();
    let mut lac = Lac::new(&v, PolicyLayout { obs_dim, act_dim, hidden: hidden.to_vec() }, 1)?;
    let result = (|| {
        for _ in 0..WARMUP {
            lac.update(&transitions)?;
        }
        let started = Instant::now();
        let mut updates = 0u64;
        while updates < 10 || started.elapsed() < window {
            lac.update(&transitions)?;
            updates += 1;
        }
        let secs = started.elapsed().as_secs_f64();
        Ok(LearnerRow {
            hidden: hidden.to_vec(),
            batch: batch as u64,
            torch_threads: torch_threads as u64,
            updates_per_s: updates as f64 / secs,
            ms_per_update: secs * 1e3 / updates as f64,
            samples_per_s: (updates * batch as u64) as f64 / secs,
            updates,
        })
    })();
    tch::set_num_threads(threads_before);
    result
}
