//! The RL environment of the measured-only setting and the rollout the learner's validation and the
//! evaluator share.
//!
//! An episode is one simulated discharge (a fresh random training cell each time), read one sample at a
//! time by a [`Tracker`]. Observation s_t = the tracker's features after reading t; action a_t moves the
//! estimate; cost c_t = the tracker's window RMS residual under the new estimate once reading t + 1 is in.
//! The episode ends at the cut-off reading: a time limit, not a terminal state (the learner bootstraps).

use super::scenario::{draw_spec, simulate, Episode, ScenarioConfig};
use super::tracker::{Interval, Tracker, TrackerSpec, OBS_DIM};
use crate::battery::Degradation;
use crate::dataset::Split;
use crate::mdp::EnvStep;
use crate::nrmse::NrmseAccumulator;
use crate::policy::{PolicyNet, Scratch};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

/// Everything that defines the measured-only MDP: the cells it trains and is judged on, and the calibrator.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MeasuredSpec {
    pub scenario: ScenarioConfig,
    pub tracker: TrackerSpec,
}

impl MeasuredSpec {
    pub fn obs_dim(&self) -> usize {
        OBS_DIM
    }

    pub fn act_dim(&self) -> usize {
        2
    }
}

/// Draws and simulates a training episode; a draw the model cannot simulate (none in the default ranges)
/// is replaced by the next.
fn training_episode(spec: &MeasuredSpec, rng: &mut SmallRng) -> Episode {
    for _ in 0..100 {
        let s = draw_spec(&spec.scenario, Split::Train, rng);
        if let Ok(e) = simulate(&spec.scenario, &s) {
            if e.samples.len() >= 2 {
                return e;
            }
        }
    }
    panic!("100 training episodes in a row could not be simulated: the scenario ranges are outside the model");
}

/// One training environment.
#[derive(Clone, Debug)]
pub struct MeasuredEnv {
    episode: Episode,
    /// Index of the latest reading the tracker has taken.
    k: usize,
    tracker: Tracker,
    rng: SmallRng,
}

impl MeasuredEnv {
    pub fn new(spec: &MeasuredSpec, seed: u64) -> Self {
        let mut rng = SmallRng::seed_from_u64(seed);
        let episode = training_episode(spec, &mut rng);
        let mut env = Self { tracker: Tracker::new(&spec.tracker), episode, k: 0, rng };
        env.tracker.ingest(&env.episode.samples[0]);
        env
    }

    fn reset(&mut self, spec: &MeasuredSpec) {
        self.episode = training_episode(spec, &mut self.rng);
        self.k = 0;
        self.tracker = Tracker::new(&spec.tracker);
        self.tracker.ingest(&self.episode.samples[0]);
    }

    pub fn observe(&self, out: &mut [f32]) {
        self.tracker.observe(out);
    }

    /// Applies `action`, reads the next sample, writes the next observation; resets after the last reading.
    pub fn step(&mut self, spec: &MeasuredSpec, action: &[f32], next_obs: &mut [f32]) -> EnvStep {
        self.tracker.apply_action(action);
        self.k += 1;
        self.tracker.ingest(&self.episode.samples[self.k]);
        let cost = self.tracker.cost();
        self.tracker.observe(next_obs);
        let done = self.k + 1 >= self.episode.samples.len();
        if done {
            self.reset(spec);
        }
        EnvStep { cost, tracking_error: cost, window_done: done }
    }

    /// A fresh random seed for the next environment of an actor.
    pub fn next_seed(&mut self) -> u64 {
        self.rng.random()
    }
}

/// A calibrator's estimate after each reading of an episode.
#[derive(Clone, Debug, PartialEq)]
pub struct Trace {
    /// Estimate after reading k (index = reading).
    pub estimates: Vec<Degradation>,
    /// Its 90 % interval, when the calibrator has one.
    pub intervals: Vec<Option<Interval>>,
    /// The tracker's cost after each reading (window RMS residual / cost scale).
    pub costs: Vec<f64>,
}

/// Runs `policy`'s deterministic action along `episode` (the deployed calibrator: read, act, repeat).
pub fn rollout_policy(spec: &TrackerSpec, episode: &Episode, net: &PolicyNet, scratch: &mut Scratch) -> Trace {
    let mut tr = Tracker::new(spec);
    let mut obs = [0f32; OBS_DIM];
    let mut action = [0f32; 2];
    let n = episode.samples.len();
    let mut out =
        Trace { estimates: Vec::with_capacity(n), intervals: Vec::with_capacity(n), costs: Vec::with_capacity(n) };
    for s in &episode.samples {
        tr.ingest(s);
        tr.observe(&mut obs);
        net.act_deterministic(&obs, scratch, &mut action);
        tr.apply_action(&action);
        out.estimates.push(tr.estimate());
        out.intervals.push(tr.interval());
        out.costs.push(tr.cost());
    }
    out
}

/// The learner's validation score of a policy on measured-only episodes: mean cost (label-free) and the
/// Table-1 NRMSE over every reading (reads the truth).
pub fn validate_policy(spec: &TrackerSpec, episodes: &[Episode], net: &PolicyNet) -> crate::mdp::PolicyScore {
    let mut scratch = Scratch::new(net.layout());
    let mut acc = NrmseAccumulator::default();
    let (mut cost_sum, mut n) = (0.0, 0usize);
    for e in episodes {
        let t = rollout_policy(spec, e, net, &mut scratch);
        for (est, c) in t.estimates.iter().zip(&t.costs) {
            acc.add(est, &e.spec.truth);
            cost_sum += c;
            n += 1;
        }
    }
    let (q, r) = acc.pct();
    crate::mdp::PolicyScore { tracking_error: cost_sum / n.max(1) as f64, nrmse_q_pct: q, nrmse_r_pct: r }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::PolicyLayout;

    #[test]
    fn environments_step_through_episodes_and_reset_with_finite_transitions() {
        let spec = MeasuredSpec::default();
        let mut env = MeasuredEnv::new(&spec, 11);
        let (mut obs, mut next) = ([0f32; OBS_DIM], [0f32; OBS_DIM]);
        let mut resets = 0;
        for k in 0..6000 {
            env.observe(&mut obs);
            let a = [((k % 7) as f32 - 3.0) / 3.0, ((k % 5) as f32 - 2.0) / 2.0];
            let s = env.step(&spec, &a, &mut next);
            assert!(s.cost.is_finite() && s.cost >= 0.0, "{s:?}");
            assert!(next.iter().all(|v| v.is_finite()));
            resets += usize::from(s.window_done);
        }
        assert!(resets >= 2, "6000 steps cover several discharges: {resets}");
    }

    #[test]
    fn a_policy_that_holds_the_prior_scores_the_prior() {
        let mut spec = MeasuredSpec::default();
        spec.tracker.action = crate::measured::tracker::ActionMode::Absolute;
        let eps = crate::measured::scenario::episode_set(&spec.scenario, Split::Validation, 3).unwrap();
        // Zero weights: mean 0, so the action is 0 and, as absolute moves, the estimate stays at the prior.
        let layout = PolicyLayout { obs_dim: OBS_DIM, act_dim: 2, hidden: vec![8] };
        let net = PolicyNet::from_flat(layout.clone(), vec![0.0; layout.n_params()]).unwrap();
        let score = validate_policy(&spec.tracker, &eps, &net);
        let mut acc = NrmseAccumulator::default();
        for e in &eps {
            for _ in &e.samples {
                acc.add(&spec.tracker.prior, &e.spec.truth);
            }
        }
        let (q, r) = acc.pct();
        assert!((score.nrmse_q_pct - q).abs() < 1e-9 && (score.nrmse_r_pct - r).abs() < 1e-9);
        assert!(score.tracking_error > 0.0);
    }
}
