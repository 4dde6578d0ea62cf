//! One training environment of the paper's MDP: a window of `window_steps` steps of a training
//! trajectory starting at a random step, with x_hat set to the real state at the window start.
//!
//! Why windows: a whole discharge is 600-3000 steps and its early steps would dominate the buffer; short
//! windows from random starts cover every state of charge evenly, and re-syncing x_hat at the start keeps
//! the model's state close enough to the real one that the one-step cost measures the parameters, not
//! accumulated drift (the paper's code used 16). The environment reads only states and loads of a
//! trajectory, never its `degradation` field: the agent never sees the true parameters.

use super::spec::{model_state_at, state_at, MdpSpec};
use crate::battery::BatteryModel;
use crate::dataset::Dataset;
use crate::math::{electro, ModelState};
use rand::Rng;

/// One environment: a window of one training trajectory, stepped by a calibrator's actions.
#[derive(Clone, Debug)]
pub struct CalibrationEnv {
    traj: usize,
    /// Current step t (x_hat is the model's state at t; the observation looks at t + 1).
    t: usize,
    window_end: usize,
    x_hat: ModelState,
}

/// What one environment step returns.
#[derive(Clone, Copy, Debug)]
pub struct EnvStep {
    /// The RL cost (after the configured shaping).
    pub cost: f64,
    /// The normalised tracking error || x_hat_{t+1} - x_{t+1} ||.
    pub tracking_error: f64,
    /// True when the window (or the trajectory) ended: the next observation is still valid (a time limit,
    /// not a terminal state), and the environment has been reset.
    pub window_done: bool,
}

impl CalibrationEnv {
    /// A new environment at a random window of one of the trajectories of `train`.
    pub fn new(spec: &MdpSpec, model: &BatteryModel, train: &Dataset, rng: &mut impl Rng) -> Self {
        let mut env = Self { traj: 0, t: 0, window_end: 0, x_hat: ModelState::zeros() };
        env.reset(spec, model, train, rng);
        env
    }

    /// Starts a new window: random trajectory, random start step, x_hat = the real state there.
    pub fn reset(&mut self, spec: &MdpSpec, model: &BatteryModel, ds: &Dataset, rng: &mut impl Rng) {
        self.traj = rng.random_range(0..ds.trajectories.len());
        let len = ds.trajectories[self.traj].len();
        // The observation at step t needs row t + 1, so a window can start at most at len - 2.
        let last_start = len.saturating_sub(2);
        self.t = rng.random_range(0..=last_start);
        self.window_end = (self.t + spec.window_steps).min(len - 1);
        self.x_hat = model_state_at(model, &ds.trajectories[self.traj], self.t);
    }

    /// The current observation, written into `out[..spec.obs_dim()]`.
    #[inline]
    pub fn observe(&self, spec: &MdpSpec, ds: &Dataset, out: &mut [f32]) {
        let traj = &ds.trajectories[self.traj];
        spec.observation.build(&spec.scales, &electro(&self.x_hat), traj, self.t + 1, out);
    }

    /// Applies action `a`: x_hat advances under the action's parameters; returns the cost. When the window
    /// ends, `next_obs` is the observation after the step (for the transition) and the env is reset.
    pub fn step(
        &mut self,
        spec: &MdpSpec,
        model: &BatteryModel,
        ds: &Dataset,
        a: &[f32],
        next_obs: &mut [f32],
        rng: &mut impl Rng,
    ) -> EnvStep {
        let traj = &ds.trajectories[self.traj];
        let x_next = state_at(traj, self.t + 1);
        let (x_hat_next, error) = spec.transition(model, &self.x_hat, a, traj.load_w, &x_next);
        self.x_hat = x_hat_next;
        self.t += 1;
        // The next observation pairs x_hat_{t+1} with the real x_{t+2}; at the trajectory's last row there
        // is no x_{t+2}, so the last usable step is len - 2 and we pair with the last row instead.
        let look = (self.t + 1).min(traj.len() - 1);
        spec.observation.build(&spec.scales, &electro(&self.x_hat), traj, look, next_obs);
        let window_done = self.t >= self.window_end || self.t + 1 >= traj.len();
        if window_done {
            self.reset(spec, model, ds, rng);
        }
        EnvStep { cost: spec.cost_of(error), tracking_error: error, window_done }
    }
}
