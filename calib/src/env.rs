//! The RL environment of the measured-only setting and the rollouts the learner's validation and the
//! evaluator share, for both designs of the learned calibrator ([`Design`]).
//!
//! An episode is one simulated discharge (a fresh random training cell each time), read one sample at a
//! time. The episode ends at the cut-off reading: a time limit, not a terminal state (the learner
//! bootstraps).
//! - `ukf-correction` (issue 18): s_k = the [`Correction`]'s observation after reading k (the tuned joint
//!   UKF's statistics); a_k corrects the estimate at k and sets the filter's noise for reading k + 1; c_k =
//!   the error of the corrected model's prediction of what comes next, from reading k ([`crate::cost`]).
//! - `window-fit` (issue 12): s_k = the [`Tracker`]'s features; a_k moves its estimate; c_k = its window's
//!   RMS residual under the new estimate once reading k + 1 is in.

use crate::correction::Correction;
use crate::cost::{predictive_cost, PredictionModel};
use crate::tracker::Tracker;
use crate::Interval;
use bcal_common::battery::Degradation;
use bcal_common::dataset::Split;
use bcal_common::mdp::EnvStep;
use bcal_common::measured::env::{Design, MeasuredSpec};
use bcal_common::measured::scenario::{draw_spec, simulate, Episode};
use bcal_common::measured::tracker::TrackerSpec;
use bcal_common::nrmse::NrmseAccumulator;
use bcal_common::policy::{PolicyNet, Scratch};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use std::sync::Arc;

/// Draws a training episode: a recorded discharge (with the share the scenario gives them), else a
/// simulated cell; a draw the model cannot simulate (none in the default ranges) is replaced by the next.
fn training_episode(spec: &MeasuredSpec, recorded: &[Episode], rng: &mut SmallRng) -> Episode {
    if !recorded.is_empty() && rng.random_bool(spec.scenario.recorded.share.clamp(0.0, 1.0)) {
        return recorded[rng.random_range(0..recorded.len())].clone();
    }
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

/// The calibrator an environment drives.
#[derive(Clone, Debug)]
#[allow(clippy::large_enum_variant)]
enum Reader {
    Window(Tracker),
    Correction(Correction),
}

impl Reader {
    /// The calibrator for `episode`: the task's, from the episode's own prior when it has one.
    fn new(spec: &MeasuredSpec, episode: &Episode) -> Self {
        let tracker = match episode.spec.prior {
            Some(prior) => TrackerSpec { prior, ..spec.tracker.clone() },
            None => spec.tracker.clone(),
        };
        match spec.design {
            Design::WindowFit => Reader::Window(Tracker::new(&tracker)),
            Design::UkfCorrection => {
                Reader::Correction(Correction::new(&tracker, spec.ukf_settings(), &spec.correction))
            }
        }
    }

    fn ingest(&mut self, s: &bcal_common::measured::Sample) {
        match self {
            Reader::Window(t) => t.ingest(s),
            Reader::Correction(c) => c.ingest(s),
        }
    }

    fn observe(&self, out: &mut [f32]) {
        match self {
            Reader::Window(t) => t.observe(out),
            Reader::Correction(c) => c.observe(out),
        }
    }

    fn apply_action(&mut self, a: &[f32]) {
        match self {
            Reader::Window(t) => t.apply_action(a),
            Reader::Correction(c) => c.apply_action(a),
        }
    }

    fn estimate(&self) -> Degradation {
        match self {
            Reader::Window(t) => t.estimate(),
            Reader::Correction(c) => c.estimate(),
        }
    }

    fn interval(&self) -> Option<Interval> {
        match self {
            Reader::Window(t) => t.interval(),
            Reader::Correction(c) => c.interval(),
        }
    }
}

/// The predictive cost of a correction's estimate at reading `k` of `episode` ([`bcal_common::measured::env::PredictiveCost`]).
pub fn correction_cost(spec: &MeasuredSpec, c: &Correction, episode: &Episode, k: usize) -> f64 {
    let Some(x) = c.state() else { return 0.0 };
    let ext = &spec.tracker.model;
    let ref_k = ext.reference_k.unwrap_or(episode.samples[0].temperature_k);
    let m = PredictionModel::at(ext, crate::cost::temperature_of(&x), ref_k, spec.tracker.cutoff_v);
    let own = predictive_cost(&spec.cost, &m, episode, k, &x, &c.estimate()).cost;
    if !spec.cost.relative {
        return own;
    }
    let f = c.ukf();
    let filter = predictive_cost(&spec.cost, &m, episode, k, &f.state(), &f.estimate()).cost;
    let m = bcal_common::measured::env::RELATIVE_LOG_CLAMP;
    (own - filter).clamp(-m, m).exp()
}

/// One training environment.
#[derive(Clone, Debug)]
pub struct MeasuredEnv {
    episode: Episode,
    /// Index of the latest reading the calibrator has taken.
    k: usize,
    reader: Reader,
    rng: SmallRng,
    /// Recorded training discharges of a real cell drawn beside the simulated ones (shared by an actor's
    /// environments).
    recorded: Arc<Vec<Episode>>,
}

impl MeasuredEnv {
    pub fn new(spec: &MeasuredSpec, seed: u64) -> Self {
        Self::with_recorded(spec, seed, Arc::new(Vec::new()))
    }

    /// An environment that also draws from `recorded` discharges (`scenario.recorded.share` of episodes).
    pub fn with_recorded(spec: &MeasuredSpec, seed: u64, recorded: Arc<Vec<Episode>>) -> Self {
        let mut rng = SmallRng::seed_from_u64(seed);
        let episode = training_episode(spec, &recorded, &mut rng);
        let mut env = Self { reader: Reader::new(spec, &episode), episode, k: 0, rng, recorded };
        env.reader.ingest(&env.episode.samples[0]);
        env
    }

    fn reset(&mut self, spec: &MeasuredSpec) {
        self.episode = training_episode(spec, &self.recorded, &mut self.rng);
        self.k = 0;
        self.reader = Reader::new(spec, &self.episode);
        self.reader.ingest(&self.episode.samples[0]);
    }

    pub fn observe(&self, out: &mut [f32]) {
        self.reader.observe(out);
    }

    /// Applies `action`, reads the next sample, writes the next observation; resets after the last reading.
    pub fn step(&mut self, spec: &MeasuredSpec, action: &[f32], next_obs: &mut [f32]) -> EnvStep {
        self.step_with(spec, action, &mut [], next_obs)
    }

    /// [`Self::step`], with the cost of each of `others` (action, cost) at the same reading first: their
    /// transitions share this one's observations ([`bcal_common::measured::env::CorrectionSpec::counterfactual_actions`]).
    pub fn step_with(
        &mut self,
        spec: &MeasuredSpec,
        action: &[f32],
        others: &mut [([f32; 2], f64)],
        next_obs: &mut [f32],
    ) -> EnvStep {
        if let Reader::Correction(c) = &mut self.reader {
            for (a, cost) in others.iter_mut() {
                c.apply_action(a);
                *cost = correction_cost(spec, c, &self.episode, self.k);
            }
        }
        self.reader.apply_action(action);
        let cost = match &self.reader {
            // The estimate chosen at reading k, judged by how it predicts what comes after k.
            Reader::Correction(c) => correction_cost(spec, c, &self.episode, self.k),
            Reader::Window(_) => f64::NAN,
        };
        self.k += 1;
        self.reader.ingest(&self.episode.samples[self.k]);
        let cost = match &self.reader {
            Reader::Window(t) => t.cost(),
            Reader::Correction(_) => cost,
        };
        self.reader.observe(next_obs);
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
    /// The training cost at the readings it was computed at (every `cost_stride`-th for the correction;
    /// every reading for the window fit), as (reading, cost).
    pub costs: Vec<(usize, f64)>,
}

/// Runs `policy`'s deterministic action along `episode` (the deployed calibrator: read, act, repeat); the
/// correction's predictive cost is computed at every `cost_stride`-th reading (it runs the model to the end
/// of discharge each time).
pub fn rollout_policy(
    spec: &MeasuredSpec,
    episode: &Episode,
    net: &PolicyNet,
    scratch: &mut Scratch,
    cost_stride: usize,
) -> Trace {
    let mut reader = Reader::new(spec, episode);
    let mut obs = vec![0f32; spec.obs_dim()];
    let mut action = vec![0f32; spec.act_dim()];
    let n = episode.samples.len();
    let mut out = Trace { estimates: Vec::with_capacity(n), intervals: Vec::with_capacity(n), costs: Vec::new() };
    for (k, s) in episode.samples.iter().enumerate() {
        reader.ingest(s);
        reader.observe(&mut obs);
        net.act_deterministic(&obs, scratch, &mut action);
        reader.apply_action(&action);
        out.estimates.push(reader.estimate());
        out.intervals.push(reader.interval());
        match &reader {
            Reader::Window(t) => out.costs.push((k, t.cost())),
            Reader::Correction(c) => {
                if k + 1 < n && k % cost_stride.max(1) == 0 {
                    out.costs.push((k, correction_cost(spec, c, episode, k)));
                }
            }
        }
    }
    out
}

/// Readings between two predictive costs in the learner's validation (each runs the model to the end of
/// discharge).
pub const VALIDATION_COST_STRIDE: usize = 10;

/// The learner's validation score of a policy on measured-only episodes: mean cost (label-free) and the
/// Table-1 NRMSE over every reading (reads the truth).
pub fn validate_policy(spec: &MeasuredSpec, episodes: &[Episode], net: &PolicyNet) -> bcal_common::mdp::PolicyScore {
    let mut scratch = Scratch::new(net.layout());
    let mut acc = NrmseAccumulator::default();
    let (mut cost_sum, mut n) = (0.0, 0usize);
    for e in episodes {
        let t = rollout_policy(spec, e, net, &mut scratch, VALIDATION_COST_STRIDE);
        // Recorded discharges have no true parameters: they count in the cost alone.
        if e.spec.truth.q_mobile_c.is_finite() && e.spec.truth.r_o_ohm.is_finite() {
            for est in &t.estimates {
                acc.add(est, &e.spec.truth);
            }
        }
        for (_, c) in &t.costs {
            cost_sum += c;
            n += 1;
        }
    }
    let (q, r) = acc.pct();
    bcal_common::mdp::PolicyScore { tracking_error: cost_sum / n.max(1) as f64, nrmse_q_pct: q, nrmse_r_pct: r }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::policy::PolicyLayout;

    fn window_spec() -> MeasuredSpec {
        MeasuredSpec { design: Design::WindowFit, ..MeasuredSpec::default() }
    }

    #[test]
    fn environments_step_through_episodes_and_reset_with_finite_transitions() {
        for spec in [window_spec(), MeasuredSpec::default()] {
            let mut env = MeasuredEnv::new(&spec, 11);
            let (mut obs, mut next) = (vec![0f32; spec.obs_dim()], vec![0f32; spec.obs_dim()]);
            let mut resets = 0;
            let t0 = std::time::Instant::now();
            let mut k = 0;
            while resets < 2 && k < 30_000 {
                k += 1;
                env.observe(&mut obs);
                let a: Vec<f32> = (0..spec.act_dim()).map(|j| (((k + j) % 7) as f32 - 3.0) / 3.0).collect();
                let s = env.step(&spec, &a, &mut next);
                assert!(s.cost.is_finite() && s.cost >= 0.0, "{s:?}");
                assert!(next.iter().all(|v| v.is_finite()), "{next:?}");
                resets += usize::from(s.window_done);
            }
            assert!(resets >= 2, "{k} steps cover two discharges: {resets}");
            eprintln!(
                "{}: {k} steps, {:.1} us per step",
                spec.design.name(),
                t0.elapsed().as_secs_f64() * 1e6 / k as f64
            );
        }
    }

    #[test]
    fn a_policy_that_holds_the_prior_scores_the_prior() {
        let mut spec = window_spec();
        spec.tracker.action = bcal_common::measured::tracker::ActionMode::Absolute;
        let eps = bcal_common::measured::scenario::episode_set(&spec.scenario, Split::Validation, 3).unwrap();
        // Zero weights: mean 0, so the action is 0 and, as absolute moves, the estimate stays at the prior.
        let layout = PolicyLayout { obs_dim: spec.obs_dim(), act_dim: 2, hidden: vec![8] };
        let net = PolicyNet::from_flat(layout.clone(), vec![0.0; layout.n_params()]).unwrap();
        let score = validate_policy(&spec, &eps, &net);
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

    /// Zero action is the tuned filter: a policy whose weights are all zero reproduces the joint UKF's
    /// estimates reading for reading.
    /// On top of the adaptive UKF (`correction.adaptive`) the zero action is that filter, rule and all; and
    /// the rule does change the estimates (else the first check would prove nothing).
    #[test]
    fn a_zero_correction_is_the_filter() {
        use crate::Calibrator;
        let plain = MeasuredSpec::default();
        let rule = crate::AdaptiveRule { window_readings: 16.0, adapt_walk: false, ..Default::default() };
        let mut adaptive = plain.clone();
        adaptive.correction.adaptive = Some(rule);
        let eps = bcal_common::measured::scenario::episode_set(&plain.scenario, Split::Validation, 2).unwrap();
        let layout = PolicyLayout { obs_dim: plain.obs_dim(), act_dim: plain.act_dim(), hidden: vec![8] };
        let net = PolicyNet::from_flat(layout.clone(), vec![0.0; layout.n_params()]).unwrap();
        let mut scratch = Scratch::new(net.layout());
        let mut differ = 0;
        for e in &eps {
            let t = rollout_policy(&plain, e, &net, &mut scratch, 50);
            let ta = rollout_policy(&adaptive, e, &net, &mut scratch, 50);
            let mut f = crate::JointUkf::new(plain.ukf_settings(), &plain.tracker);
            let mut fa = crate::AdaptiveUkf::new(plain.ukf_settings(), rule, &plain.tracker);
            for ((s, est), est_a) in e.samples.iter().zip(&t.estimates).zip(&ta.estimates) {
                f.step(s);
                fa.step(s);
                assert_eq!(f.estimate(), *est);
                assert_eq!(fa.estimate(), *est_a);
                differ += usize::from(est != est_a);
            }
            assert!(!t.costs.is_empty() && t.costs.iter().all(|(_, c)| c.is_finite() && *c >= 0.0));
        }
        assert!(differ > 0, "the rule never changed an estimate");
    }
}
