//! An actor's environments stepped in lockstep with one policy: each step observes every environment,
//! draws a stochastic action (squashed Gaussian) and appends one [`Transition`] per environment. The
//! environments are the paper's (windows of training trajectories) or the measured-only setting's
//! (simulated cells read through a sensor), as the run's task says. No IPC here, so a unit test can step it.

use bcal_calib::env::MeasuredEnv;
use bcal_common::battery::BatteryModel;
use bcal_common::dataset::Dataset;
use bcal_common::hash::fnv1a64;
use bcal_common::mdp::{CalibrationEnv, MdpSpec};
use bcal_common::measured::env::{Design, MeasuredSpec};
use bcal_common::policy::{PolicyNet, Scratch};
use bcal_common::wire::{Transition, MAX_ACT, MAX_OBS};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

/// The seed of one random stream of one actor: distinct per (run seed, actor id, stream), reproducible.
pub fn actor_seed(run_seed: u64, actor_id: u32, stream: &str) -> u64 {
    let mut bytes = Vec::with_capacity(16 + stream.len());
    bytes.extend_from_slice(&run_seed.to_le_bytes());
    bytes.extend_from_slice(&u64::from(actor_id).to_le_bytes());
    bytes.extend_from_slice(stream.as_bytes());
    fnv1a64(&bytes)
}

/// The other actions a correction step is also scored with: the zero action (the filter itself) and
/// uniform draws, `correction.counterfactual_actions` in all (none for other designs, or when the policy
/// sets the filter's noise: those actions change what comes next).
fn counterfactual_actions(spec: &MeasuredSpec, rng: &mut SmallRng) -> Vec<([f32; 2], f64)> {
    let c = &spec.correction;
    if spec.design != Design::UkfCorrection || c.noise_actions || c.counterfactual_actions == 0 {
        return Vec::new();
    }
    let mut v = vec![([0.0f32; 2], 0.0)];
    for _ in 1..c.counterfactual_actions {
        v.push(([rng.random_range(-1.0..=1.0), rng.random_range(-1.0..=1.0)], 0.0));
    }
    v
}

/// The environments of one task (one per actor process).
#[allow(clippy::large_enum_variant)]
enum Kind {
    /// The paper's setting: windows of training trajectories (which the actor owns).
    Paper { spec: MdpSpec, model: BatteryModel, train: Dataset, envs: Vec<CalibrationEnv> },
    /// The measured-only setting: simulated cells read through the sensor, drawn on the fly.
    Measured { spec: MeasuredSpec, envs: Vec<MeasuredEnv> },
}

/// N environments of one task, their random streams and the policy's scratch space.
pub struct ActorEnvs {
    kind: Kind,
    env_rng: SmallRng,
    noise_rng: SmallRng,
    scratch: Scratch,
    obs_dim: usize,
    act_dim: usize,
}

impl ActorEnvs {
    /// `n_envs` paper environments on the trajectories of `train` (the training split); `policy_scratch`
    /// sized for the policy's layout.
    pub fn paper(
        spec: MdpSpec,
        model: BatteryModel,
        train: Dataset,
        n_envs: usize,
        seeds: (u64, u64),
        policy_scratch: Scratch,
    ) -> Self {
        assert!(!train.trajectories.is_empty(), "no training trajectories");
        assert!(spec.obs_dim() <= MAX_OBS && spec.act_dim() <= MAX_ACT, "MDP larger than the wire types");
        let mut env_rng = SmallRng::seed_from_u64(seeds.0);
        let envs = (0..n_envs).map(|_| CalibrationEnv::new(&spec, &model, &train, &mut env_rng)).collect();
        let (obs_dim, act_dim) = (spec.obs_dim(), spec.act_dim());
        Self {
            kind: Kind::Paper { spec, model, train, envs },
            env_rng,
            noise_rng: SmallRng::seed_from_u64(seeds.1),
            scratch: policy_scratch,
            obs_dim,
            act_dim,
        }
    }

    /// `n_envs` measured-only environments, each on its own stream of random training cells.
    /// `recorded`: a real cell's recorded training discharges, drawn beside the simulated cells with the
    /// scenario's share (empty: simulated cells only).
    pub fn measured(
        spec: MeasuredSpec,
        recorded: Vec<bcal_common::measured::Episode>,
        n_envs: usize,
        seeds: (u64, u64),
        policy_scratch: Scratch,
    ) -> Self {
        assert!(spec.obs_dim() <= MAX_OBS && spec.act_dim() <= MAX_ACT, "MDP larger than the wire types");
        let mut env_rng = SmallRng::seed_from_u64(seeds.0);
        let recorded = std::sync::Arc::new(recorded);
        let envs = (0..n_envs).map(|_| MeasuredEnv::with_recorded(&spec, env_rng.random(), recorded.clone())).collect();
        let (obs_dim, act_dim) = (spec.obs_dim(), spec.act_dim());
        Self {
            kind: Kind::Measured { spec, envs },
            env_rng,
            noise_rng: SmallRng::seed_from_u64(seeds.1),
            scratch: policy_scratch,
            obs_dim,
            act_dim,
        }
    }

    pub fn len(&self) -> usize {
        match &self.kind {
            Kind::Paper { envs, .. } => envs.len(),
            Kind::Measured { envs, .. } => envs.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// One lockstep step: appends `self.len()` transitions to `out`.
    pub fn step(&mut self, policy: &PolicyNet, out: &mut Vec<Transition>) {
        let (od, ad) = (self.obs_dim, self.act_dim);
        let n = self.len();
        for k in 0..n {
            let mut t = Transition::default();
            match &self.kind {
                Kind::Paper { spec, train, envs, .. } => envs[k].observe(spec, train, &mut t.obs[..od]),
                Kind::Measured { envs, .. } => envs[k].observe(&mut t.obs[..od]),
            }
            let noise = &mut self.noise_rng;
            policy.act_stochastic(
                &t.obs[..od],
                &mut self.scratch,
                || noise.sample(StandardNormal),
                &mut t.action[..ad],
            );
            let mut others = Vec::new();
            let s = match &mut self.kind {
                Kind::Paper { spec, model, train, envs } => {
                    envs[k].step(spec, model, train, &t.action[..ad], &mut t.next_obs[..od], &mut self.env_rng)
                }
                Kind::Measured { spec, envs } => {
                    others = counterfactual_actions(spec, &mut self.env_rng);
                    envs[k].step_with(spec, &t.action[..ad], &mut others, &mut t.next_obs[..od])
                }
            };
            t.cost = s.cost as f32;
            // Window and episode ends are time limits, not terminal states: the learner bootstraps through them.
            t.terminal = 0.0;
            out.push(t);
            for (a, cost) in others {
                let mut o = t;
                o.action = [0.0; bcal_common::wire::MAX_ACT];
                o.action[..2].copy_from_slice(&a);
                o.cost = cost as f32;
                out.push(o);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::config::EnvConfig;
    use bcal_common::dataset::{generate, Experiment, ExperimentDef, Grid, Split};
    use bcal_common::policy::PolicyLayout;

    #[test]
    fn seeds_differ_per_actor_and_stream_and_repeat() {
        assert_eq!(actor_seed(1, 0, "env"), actor_seed(1, 0, "env"));
        assert_ne!(actor_seed(1, 0, "env"), actor_seed(1, 1, "env"));
        assert_ne!(actor_seed(1, 0, "env"), actor_seed(1, 0, "noise"));
        assert_ne!(actor_seed(1, 0, "env"), actor_seed(2, 0, "env"));
    }

    #[test]
    fn lockstep_step_yields_one_finite_transition_per_env() {
        let def = ExperimentDef {
            experiment: Experiment::Multi,
            q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 2 },
            r_o_ohm: Grid { start: 0.1, end: 0.2, n: 2 },
            loads_w: Grid { start: 8.0, end: 16.0, n: 5 },
            n_test_loads: 2,
            validation: Experiment::Multi.definition().validation,
            dt_s: 1.0,
            max_steps: 100_000,
        };
        let model = BatteryModel::default();
        let ds = generate(&def, &model, Split::Train).unwrap();
        let spec = MdpSpec::new(Experiment::Multi, &EnvConfig::default(), &ds);
        let layout = PolicyLayout { obs_dim: spec.obs_dim(), act_dim: spec.act_dim(), hidden: vec![8, 8] };
        let params: Vec<f32> = (0..layout.n_params()).map(|i| ((i % 7) as f32 - 3.0) * 0.05).collect();
        let policy = PolicyNet::from_flat(layout.clone(), params).unwrap();
        let mut envs = ActorEnvs::paper(spec.clone(), model, ds, 5, (1, 2), Scratch::new(&layout));
        let mut out = Vec::new();
        for _ in 0..40 {
            envs.step(&policy, &mut out);
        }
        assert_eq!(out.len(), 200);
        assert!(out.iter().all(|t| t.is_finite() && t.cost >= 0.0));
        assert!(out.iter().all(|t| t.action[..2].iter().all(|a| a.abs() <= 1.0)));
        // Unused observation slots stay zero (the wire type is wider than the MDP).
        assert!(out.iter().all(|t| t.obs[spec.obs_dim()..].iter().all(|v| *v == 0.0)));
        // Exploration: actions differ between steps of the same env.
        assert_ne!(out[0].action, out[5].action);
    }

    #[test]
    fn measured_envs_yield_finite_transitions_from_readings_only() {
        let spec = MeasuredSpec::default();
        let layout = PolicyLayout { obs_dim: spec.obs_dim(), act_dim: spec.act_dim(), hidden: vec![8] };
        let params: Vec<f32> = (0..layout.n_params()).map(|i| ((i % 5) as f32 - 2.0) * 0.05).collect();
        let policy = PolicyNet::from_flat(layout.clone(), params).unwrap();
        let mut envs = ActorEnvs::measured(spec.clone(), Vec::new(), 4, (3, 4), Scratch::new(&layout));
        let mut out = Vec::new();
        for _ in 0..50 {
            envs.step(&policy, &mut out);
        }
        // Each step: the acted transition and the counterfactual ones at the same reading (the zero action
        // first), sharing its observations.
        let per = 1 + spec.correction.counterfactual_actions;
        assert_eq!(out.len(), 50 * 4 * per);
        assert!(out.iter().all(|t| t.is_finite() && t.cost >= 0.0));
        assert!(out.iter().all(|t| t.obs[spec.obs_dim()..].iter().all(|v| *v == 0.0)));
        for group in out.chunks(per) {
            assert!(group.iter().all(|t| t.obs == group[0].obs && t.next_obs == group[0].next_obs));
            assert_eq!(group[1].action, [0.0; bcal_common::wire::MAX_ACT]);
            // The relative cost of the zero action is the filter's own: exactly 1.
            assert_eq!(group[1].cost, 1.0);
        }
    }
}
