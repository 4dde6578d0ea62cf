//! Wire types shared by actors, replay and learner: fixed-size `#[repr(C)]` payloads and their limits.
//!
//! Every type here is plain old data (`Copy`, `#[repr(C)]`, no pointers, no `Vec`/`String`) and derives
//! iceoryx2's `ZeroCopySend`, so it can live in shared memory. Messages whose length varies (a batch of
//! transitions, the policy weights) are slices of such elements with a fixed-size user header; the
//! largest length of each is a constant below and is stated again where [`crate::ipc`] declares the
//! service.
//!
//! A layout change must bump [`WIRE_VERSION`]: the version is part of every service name, so a process
//! built with an older layout can never open (and misread) a newer service. On top of that, iceoryx2
//! compares type name, size and alignment of payload and header when a service is opened, and refuses
//! a mismatch (`IncompatibleTypes`).

use iceoryx2::prelude::ZeroCopySend;

/// Layout version of every payload below; part of each service name.
pub const WIRE_VERSION: u32 = 3;
/// Largest observation any observation builder may produce.
pub const MAX_OBS: usize = 32;
/// Largest action dimension (the correction policy's: two shifts and two noise log-scales).
pub const MAX_ACT: usize = 4;
/// Largest learner minibatch the replay serves in one message.
pub const MAX_BATCH: usize = 1024;
/// Largest number of transitions in one actor message.
pub const MAX_PUBLISH_BATCH: usize = 256;
/// Largest number of actor processes (publishers on the transition service).
pub const MAX_ACTORS: usize = 64;

/// One MDP transition (s, a, c, s'); `terminal` is 1.0 only for a true terminal state (window ends are
/// time limits and bootstrap).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, ZeroCopySend)]
#[type_name("bcal::Transition")]
pub struct Transition {
    pub obs: [f32; MAX_OBS],
    pub next_obs: [f32; MAX_OBS],
    pub action: [f32; MAX_ACT],
    pub cost: f32,
    pub terminal: f32,
}

impl Default for Transition {
    fn default() -> Self {
        Self { obs: [0.0; MAX_OBS], next_obs: [0.0; MAX_OBS], action: [0.0; MAX_ACT], cost: 0.0, terminal: 0.0 }
    }
}

impl Transition {
    /// `n` synthetic transitions for tests and benchmarks: observations N(0, 1) in the first `obs_dim`
    /// slots, actions uniform in [-1, 1] in the first `act_dim`, costs uniform in [0, 1), seeded.
    pub fn synthetic_batch(seed: u64, n: usize, obs_dim: usize, act_dim: usize) -> Vec<Transition> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::SmallRng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let mut t = Transition::default();
                for k in 0..obs_dim.min(MAX_OBS) {
                    t.obs[k] = rng.sample(rand_distr::StandardNormal);
                    t.next_obs[k] = rng.sample(rand_distr::StandardNormal);
                }
                for a in &mut t.action[..act_dim.min(MAX_ACT)] {
                    *a = rng.random_range(-1.0..=1.0);
                }
                t.cost = rng.random();
                t
            })
            .collect()
    }

    /// True when every number is finite (the replay quarantines the others).
    pub fn is_finite(&self) -> bool {
        self.obs.iter().chain(&self.next_obs).chain(&self.action).all(|v| v.is_finite())
            && self.cost.is_finite()
            && self.terminal.is_finite()
    }
}

/// User header of one actor message (payload: `[Transition]` of length `len`).
///
/// `published_before` is the number of transitions this actor incarnation tried to publish before this
/// message; with `epoch` it lets the replay count transitions that were lost on the way (a gap between
/// one message's `published_before + len` and the next message's `published_before`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("bcal::TransitionBatchHeader")]
pub struct TransitionBatchHeader {
    /// Actor id (`--actor-id`).
    pub actor_id: u32,
    /// Transitions in this message (equals the payload's slice length).
    pub len: u32,
    /// Identifies one actor incarnation (a restarted actor has a new epoch and restarts its counters).
    pub epoch: u64,
    /// Message sequence number of this incarnation, from 0.
    pub seq: u64,
    /// Transitions this incarnation tried to publish before this message (delivered or not).
    pub published_before: u64,
    /// Learner update step of the weights that acted (0 = none yet).
    pub weights_version: u64,
    /// [`monotonic_ns`] when the message was sent (the receiver's clock is the same: one host), so the
    /// replay and `bcal bench` measure the one-way latency of a message.
    pub sent_mono_ns: u64,
}

/// CLOCK_MONOTONIC in nanoseconds: one clock for every process of the host (unlike `Instant`, whose
/// value cannot be sent), for one-way latencies across processes.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes one timespec into the valid pointer; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// User header of a weights message (payload: `[f32]`, the actor network's flat parameters in
/// [`crate::policy::PolicyLayout`] order).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("bcal::WeightsHeader")]
pub struct WeightsHeader {
    /// Learner update counter when the weights were taken; strictly increasing within a run (a resumed
    /// learner continues its counter).
    pub update_step: u64,
    /// [`crate::policy::PolicyLayout::fingerprint`] of the network shape; a mismatch is refused.
    pub layout_fingerprint: u64,
    /// Number of f32 parameters (equals the payload's slice length).
    pub n_params: u64,
}

/// Learner -> replay: "send me one batch of `batch_size` transitions".
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("bcal::BatchRequest")]
pub struct BatchRequest {
    /// Transitions wanted, 1..=[`MAX_BATCH`].
    pub batch_size: u32,
    pub _reserved: u32,
    /// Learner-side request counter, echoed in the response.
    pub request_seq: u64,
}

/// Replay counters, carried by every batch response and every status message.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("bcal::ReplayCounters")]
pub struct ReplayCounters {
    /// Transitions received from actors (finite or not).
    pub received_total: u64,
    /// Finite transitions stored in the ring buffer (received - quarantined).
    pub inserted_total: u64,
    /// Non-finite transitions refused at the door.
    pub quarantined_total: u64,
    /// Transitions actors tried to publish that never reached the replay (sequence gaps).
    pub dropped_total: u64,
    /// Transitions sampled into batches (batch_size per served batch).
    pub sampled_total: u64,
    /// Batches served to the learner.
    pub batches_served: u64,
    /// Transitions currently held by the ring buffer.
    pub size: u64,
}

/// User header of a batch response (payload: `[Transition]` of length `request.batch_size`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("bcal::BatchHeader")]
pub struct BatchHeader {
    /// The request's `request_seq`.
    pub request_seq: u64,
    pub counters: ReplayCounters,
}

/// Replay -> actors (history 1): the rate limiter's verdict and the counters, published every few
/// milliseconds and whenever the verdict changes.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("bcal::ReplayStatus")]
pub struct ReplayStatus {
    /// 1 while actors may publish; 0 while inserts are too far ahead of samples (actors wait).
    pub inserts_allowed: u32,
    pub _reserved: u32,
    /// Inserts the limiter admits before it blocks (advisory; several actors share it).
    pub insert_credit: u64,
    /// Milliseconds since the replay started (a heartbeat).
    pub uptime_ms: u64,
    pub counters: ReplayCounters,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn payload_sizes_are_fixed_and_padding_free() {
        // 32 + 32 + 4 + 2 f32: no padding, 280 bytes per transition.
        assert_eq!(std::mem::size_of::<Transition>(), 280);
        assert_eq!(std::mem::size_of::<TransitionBatchHeader>(), 48);
        assert_eq!(std::mem::size_of::<WeightsHeader>(), 24);
        assert_eq!(std::mem::size_of::<BatchRequest>(), 16);
        assert_eq!(std::mem::size_of::<ReplayCounters>(), 56);
        assert_eq!(std::mem::size_of::<BatchHeader>(), 64);
        assert_eq!(std::mem::size_of::<ReplayStatus>(), 80);
    }

    #[test]
    fn non_finite_transitions_are_detected() {
        let mut t = Transition::default();
        assert!(t.is_finite());
        t.next_obs[31] = f32::NAN;
        assert!(!t.is_finite());
        t.next_obs[31] = 0.0;
        t.cost = f32::INFINITY;
        assert!(!t.is_finite());
    }
}
