//! Wire types shared by actors, replay and learner: fixed-size `#[repr(C)]` payloads and their limits.
//!
//! A layout change must bump [`WIRE_VERSION`]: the version is part of every service name, so a process
//! built with an older layout can never open (and misread) a newer service.

/// Layout version of every payload below; part of each service name.
pub const WIRE_VERSION: u32 = 1;
/// Largest observation any observation builder may produce.
pub const MAX_OBS: usize = 32;
/// Largest action dimension (qMobile and Ro).
pub const MAX_ACT: usize = 2;
/// Largest learner minibatch the replay serves in one message.
pub const MAX_BATCH: usize = 1024;
/// Largest number of transitions in one actor message.
pub const MAX_PUBLISH_BATCH: usize = 256;
/// Largest number of actor processes (publishers on the transition service).
pub const MAX_ACTORS: usize = 64;

/// One MDP transition (s, a, c, s'); `terminal` is 1.0 only for a true terminal state (window ends are
/// time limits and bootstrap).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq)]
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
    /// True when every number is finite (the replay quarantines the others).
    pub fn is_finite(&self) -> bool {
        self.obs.iter().chain(&self.next_obs).chain(&self.action).all(|v| v.is_finite())
            && self.cost.is_finite()
            && self.terminal.is_finite()
    }
}
