//! The supervised direct-mapping baseline (paper Section 4.3.2): the actor's network shape (hidden
//! [256, 256, 256], LeakyReLU) with one output per calibrated parameter, trained in tch with Adam (5e-4, the
//! paper's optimiser) on (observation -> true action) pairs of the TRAINING trajectories. It is the only
//! method that sees true parameters. Observations are built exactly as the RL evaluation builds them
//! ([x_t, x_{t+1}, u] normalised, x_hat = the measured state), targets are `ActionMap::to_action` of the
//! true degradation, in [-1, 1]; the output layer is linear (an MSE regression) and the prediction is
//! clamped to [-1, 1] when mapped back to parameters.
//!
//! [`DirectMap::to_policy_net`] exports the trained weights into the pure-Rust [`PolicyNet`] (mean head =
//! the output layer), so its inference cost can be timed on the same forward pass as the RL policy.
//! This module never prints.

use bcal_common::dataset::Trajectory;
use bcal_common::mdp::{state_at, MdpSpec, SplitMix64};
use bcal_common::policy::{PolicyError, PolicyLayout, PolicyNet};
use serde::{Deserialize, Serialize};
use std::time::Instant;
use tch::nn::{self, Module, OptimizerConfig};
use tch::{Device, Kind, Tensor};

/// Every hyperparameter of the direct mapping, with the paper's values where it gives them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DirectMapConfig {
    /// Hidden layer widths (paper 4.2, the actor's: three layers of 256).
    pub hidden: Vec<usize>,
    /// Adam learning rate (paper: 5e-4).
    pub lr: f64,
    /// Minibatch size (paper: 256).
    pub batch_size: usize,
    /// Training pairs, sampled uniformly from the steps of the training trajectories (a whole set is
    /// millions of highly correlated steps; a uniform sample of this size covers it).
    pub max_pairs: usize,
    /// Stop after this many Adam updates (the binding limit on an idle 2-core machine, ~1 min, so results
    /// reproduce) ...
    pub max_updates: usize,
    /// ... or after this many seconds of training, whichever comes first (a cap for busy machines).
    pub time_budget_s: f64,
    /// Seed of the pair sampling, the initialisation and the minibatches.
    pub seed: u64,
}

impl Default for DirectMapConfig {
    fn default() -> Self {
        Self {
            hidden: vec![256, 256, 256],
            lr: 5e-4,
            batch_size: 256,
            max_pairs: 200_000,
            max_updates: 6_000,
            time_budget_s: 150.0,
            seed: 1,
        }
    }
}

impl DirectMapConfig {
    /// The `--quick` variant: a few seconds of training.
    pub fn quick() -> Self {
        Self { max_pairs: 50_000, max_updates: 1_500, time_budget_s: 8.0, ..Self::default() }
    }
}

/// Supervised pairs: observations (row-major, `obs_dim` wide) and target actions (`act_dim` wide).
#[derive(Clone, Debug, Default)]
pub struct Pairs {
    pub obs: Vec<f32>,
    pub target: Vec<f32>,
    pub obs_dim: usize,
    pub act_dim: usize,
}

impl Pairs {
    pub fn len(&self) -> usize {
        self.obs.len() / self.obs_dim.max(1)
    }

    pub fn is_empty(&self) -> bool {
        self.obs.is_empty()
    }
}

/// The observation of step `t` of `traj`, as the RL evaluation builds it (x_hat = measured x_t).
#[inline]
pub fn observation(spec: &MdpSpec, traj: &Trajectory, t: usize, out: &mut [f32]) {
    spec.observation.build(&spec.scales, &state_at(traj, t), traj, t + 1, out);
}

/// Samples up to `max_pairs` (observation, true action) pairs uniformly over the steps of `trajs`.
pub fn sample_pairs(spec: &MdpSpec, trajs: &[&Trajectory], max_pairs: usize, seed: u64) -> Pairs {
    let (od, ad) = (spec.obs_dim(), spec.act_dim());
    let total: usize = trajs.iter().map(|t| t.len().saturating_sub(1)).sum();
    let keep = (max_pairs as f64 / total.max(1) as f64).min(1.0);
    let mut rng = SplitMix64(seed ^ 0xd1ec7);
    let mut p = Pairs { obs_dim: od, act_dim: ad, ..Default::default() };
    let mut buf = vec![0f32; od];
    for traj in trajs {
        let target = spec.actions.to_action(&traj.degradation);
        for t in 0..traj.len().saturating_sub(1) {
            if rng.unit_f64() >= keep {
                continue;
            }
            observation(spec, traj, t, &mut buf);
            p.obs.extend_from_slice(&buf);
            p.target.extend_from_slice(&target[..ad]);
        }
    }
    p
}

/// The network: hidden Linear + LeakyReLU layers, then a linear output per parameter.
#[derive(Debug)]
pub struct DirectMap {
    vs: nn::VarStore,
    hidden: Vec<nn::Linear>,
    head: nn::Linear,
    layout: PolicyLayout,
}

/// What training did.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TrainLog {
    pub pairs: usize,
    pub updates: usize,
    pub seconds: f64,
    /// (update, mean MSE over the preceding window of updates), in target units ([-1, 1] actions).
    pub loss_curve: Vec<(usize, f64)>,
    /// Mean MSE of the first and last windows.
    pub first_loss: f64,
    pub final_loss: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum DirectMapError {
    #[error("the direct mapping has no training pairs: the training set is empty")]
    NoPairs,
    #[error("libtorch failed in the direct mapping: {0}")]
    Torch(#[from] tch::TchError),
    #[error("the direct mapping's training loss became non-finite at update {update}; lower lr")]
    NonFinite { update: usize },
    #[error("exporting the direct mapping to the pure-Rust network: {0}")]
    Export(#[from] PolicyError),
}

impl DirectMap {
    /// A freshly initialised network (torch's default Linear initialisation, seeded).
    pub fn new(obs_dim: usize, act_dim: usize, hidden: &[usize], seed: u64) -> Self {
        tch::manual_seed(seed as i64);
        let vs = nn::VarStore::new(Device::Cpu);
        let root = vs.root();
        let mut layers = Vec::new();
        let mut input = obs_dim as i64;
        for (k, h) in hidden.iter().enumerate() {
            layers.push(nn::linear(&root / format!("hidden{k}"), input, *h as i64, Default::default()));
            input = *h as i64;
        }
        let head = nn::linear(&root / "head", input, act_dim as i64, Default::default());
        Self { vs, hidden: layers, head, layout: PolicyLayout { obs_dim, act_dim, hidden: hidden.to_vec() } }
    }

    pub fn layout(&self) -> &PolicyLayout {
        &self.layout
    }

    /// Predicted actions (unclamped) for a batch of observations `[n, obs_dim]`.
    pub fn forward(&self, obs: &Tensor) -> Tensor {
        let mut h = obs.shallow_clone();
        for l in &self.hidden {
            h = l.forward(&h).leaky_relu();
        }
        self.head.forward(&h)
    }

    /// Predictions for `obs` (row-major, `obs_dim` wide), without gradients, in chunks.
    pub fn predict(&self, obs: &[f32]) -> Result<Vec<f32>, DirectMapError> {
        let (od, ad) = (self.layout.obs_dim, self.layout.act_dim);
        let n = obs.len() / od;
        let mut out = Vec::with_capacity(n * ad);
        let _guard = tch::no_grad_guard();
        for chunk in obs.chunks(65_536 * od) {
            let rows = (chunk.len() / od) as i64;
            let x = Tensor::f_from_slice(chunk)?.f_reshape([rows, od as i64])?;
            let y = self.forward(&x).f_contiguous()?.f_view([-1])?;
            out.extend(Vec::<f32>::try_from(&y)?);
        }
        Ok(out)
    }

    /// Trains on `pairs` with Adam and MSE (minibatches drawn with replacement) until `cfg`'s update or time
    /// limit. Returns the trained network and its loss curve.
    pub fn train(pairs: &Pairs, cfg: &DirectMapConfig) -> Result<(Self, TrainLog), DirectMapError> {
        if pairs.is_empty() {
            return Err(DirectMapError::NoPairs);
        }
        let started = Instant::now();
        let net = Self::new(pairs.obs_dim, pairs.act_dim, &cfg.hidden, cfg.seed);
        let n = pairs.len();
        let x_all = Tensor::f_from_slice(&pairs.obs)?.f_reshape([n as i64, pairs.obs_dim as i64])?;
        let y_all = Tensor::f_from_slice(&pairs.target)?.f_reshape([n as i64, pairs.act_dim as i64])?;
        let mut opt = nn::Adam::default().build(&net.vs, cfg.lr)?;
        let mut rng = SplitMix64(cfg.seed ^ 0xba7c4);
        let window = 100usize;
        let mut log = TrainLog { pairs: n, ..Default::default() };
        let (mut acc, mut acc_n) = (0.0, 0usize);
        let mut idx = vec![0i64; cfg.batch_size];
        for update in 1..=cfg.max_updates {
            for v in idx.iter_mut() {
                *v = rng.below(n) as i64;
            }
            let ix = Tensor::f_from_slice(&idx)?;
            let (x, y) = (x_all.f_index_select(0, &ix)?, y_all.f_index_select(0, &ix)?);
            // L2 loss between predicted and true (scaled) parameters (paper 5: "until the L2-loss converged").
            let loss = net.forward(&x).f_mse_loss(&y, tch::Reduction::Mean)?;
            let l = loss.f_double_value(&[])?;
            if !l.is_finite() {
                return Err(DirectMapError::NonFinite { update });
            }
            opt.backward_step(&loss);
            acc += l;
            acc_n += 1;
            if acc_n == window || update == cfg.max_updates {
                log.loss_curve.push((update, acc / acc_n as f64));
                (acc, acc_n) = (0.0, 0);
            }
            log.updates = update;
            if started.elapsed().as_secs_f64() >= cfg.time_budget_s {
                break;
            }
        }
        if acc_n > 0 {
            log.loss_curve.push((log.updates, acc / acc_n as f64));
        }
        log.first_loss = log.loss_curve.first().map_or(f64::NAN, |p| p.1);
        log.final_loss = log.loss_curve.last().map_or(f64::NAN, |p| p.1);
        log.seconds = started.elapsed().as_secs_f64();
        Ok((net, log))
    }

    /// The same network as a pure-Rust [`PolicyNet`]: hidden layers and mean head copied, log-std head zero,
    /// so `PolicyNet::forward`'s mean equals this network's output.
    pub fn to_policy_net(&self) -> Result<PolicyNet, DirectMapError> {
        let mut flat = Vec::with_capacity(self.layout.n_params());
        let push = |t: &Tensor, flat: &mut Vec<f32>| -> Result<(), DirectMapError> {
            let v = Vec::<f32>::try_from(&t.f_contiguous()?.f_view([-1])?.f_to_kind(Kind::Float)?)?;
            flat.extend(v);
            Ok(())
        };
        for l in self.hidden.iter().chain(std::iter::once(&self.head)) {
            push(&l.ws, &mut flat)?;
            match &l.bs {
                Some(b) => push(b, &mut flat)?,
                None => flat.extend(std::iter::repeat_n(0.0, l.ws.size()[0] as usize)),
            }
        }
        let (_, last) = *self.layout.linears().last().expect("a network has a head");
        let width = self.layout.hidden.last().copied().unwrap_or(self.layout.obs_dim);
        flat.extend(std::iter::repeat_n(0.0, width * last + last));
        Ok(PolicyNet::from_flat(self.layout.clone(), flat)?)
    }
}

/// Per-trajectory predictions of `net` along `traj` (one batched forward), as actions in [-1, 1] order.
pub fn predict_trajectory(net: &DirectMap, spec: &MdpSpec, traj: &Trajectory) -> Result<Vec<f32>, DirectMapError> {
    let od = spec.obs_dim();
    let steps = traj.len().saturating_sub(1);
    let mut obs = vec![0f32; steps * od];
    for t in 0..steps {
        observation(spec, traj, t, &mut obs[t * od..(t + 1) * od]);
    }
    net.predict(&obs)
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::battery::BatteryModel;
    use bcal_common::config::EnvConfig;
    use bcal_common::dataset::{generate, Experiment, ExperimentDef, Grid};
    use bcal_common::policy::Scratch;

    fn small_set() -> (bcal_common::dataset::Dataset, MdpSpec) {
        let def = ExperimentDef {
            experiment: Experiment::Multi,
            q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 4 },
            r_o_ohm: Grid { start: 0.1, end: 0.2, n: 3 },
            loads_w: Grid { start: 8.0, end: 16.0, n: 9 },
            n_test_loads: 3,
            dt_s: 1.0,
            max_steps: 100_000,
        };
        let ds = generate(&def, &BatteryModel::default()).unwrap();
        let spec = MdpSpec::new(Experiment::Multi, &EnvConfig::default(), &ds);
        (ds, spec)
    }

    /// The direct mapping trains on a small set: the loss falls and held-in predictions improve.
    #[test]
    fn trains_on_a_small_set_loss_falls_and_predictions_improve() {
        tch::set_num_threads(2);
        let (ds, spec) = small_set();
        let train: Vec<&Trajectory> = ds.train().collect();
        let pairs = sample_pairs(&spec, &train, 6_000, 3);
        assert!(pairs.len() > 3_000 && pairs.len() <= 7_000, "{}", pairs.len());
        let cfg = DirectMapConfig {
            hidden: vec![64, 64],
            max_updates: 800,
            time_budget_s: 60.0,
            lr: 2e-3,
            ..DirectMapConfig::default()
        };
        let untrained = DirectMap::new(spec.obs_dim(), spec.act_dim(), &cfg.hidden, cfg.seed);
        let (net, log) = DirectMap::train(&pairs, &cfg).unwrap();
        assert_eq!(log.updates, 800);
        assert!(log.final_loss < 0.2 * log.first_loss, "loss {} -> {}", log.first_loss, log.final_loss);
        let mse = |m: &DirectMap| {
            let p = m.predict(&pairs.obs).unwrap();
            p.iter().zip(&pairs.target).map(|(a, b)| f64::from(a - b).powi(2)).sum::<f64>() / p.len() as f64
        };
        let (before, after) = (mse(&untrained), mse(&net));
        assert!(after < 0.1 * before && after < 0.02, "prediction MSE {before} -> {after}");

        // The pure-Rust export computes the same function.
        let pn = net.to_policy_net().unwrap();
        let mut s = Scratch::new(pn.layout());
        let pred = net.predict(&pairs.obs[..10 * spec.obs_dim()]).unwrap();
        for k in 0..10 {
            let (mut mean, mut ls) = ([0f32; 2], [0f32; 2]);
            pn.forward(&pairs.obs[k * spec.obs_dim()..(k + 1) * spec.obs_dim()], &mut s, &mut mean, &mut ls);
            for j in 0..2 {
                assert!((mean[j] - pred[k * 2 + j]).abs() < 1e-4, "row {k}: {} vs {}", mean[j], pred[k * 2 + j]);
            }
        }
    }
}
