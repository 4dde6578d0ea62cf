//! The supervised direct-mapping baseline (paper Section 4.3.2): the actor's network shape (hidden
//! [256, 256, 256], LeakyReLU) with one output per calibrated parameter, trained in tch with Adam (5e-4, the
//! paper's optimiser) on (observation -> true action) pairs of the TRAINING trajectories, with the same
//! effort as RL: the RL run's wall-clock budget, early stopping on the VALIDATION split's loss (the paper:
//! "until the L2-loss converged"), and the weights of the best validation loss kept. It is the only
//! method that sees true parameters while training. Observations are built exactly as the RL evaluation builds them
//! ([x_t, x_{t+1}, u] normalised, x_hat = the measured state), targets are `ActionMap::to_action` of the
//! true degradation, in [-1, 1]; the output layer is linear (an MSE regression) and the prediction is
//! clamped to [-1, 1] when mapped back to parameters.
//!
//! [`DirectMap::to_policy_net`] exports the trained weights into the pure-Rust [`PolicyNet`] (mean head =
//! the output layer), so its inference cost can be timed on the same forward pass as the RL policy.
//! This module never prints.

use bcal_common::dataset::Trajectory;
use bcal_common::mdp::{state_at, MdpSpec};
use bcal_common::policy::{PolicyError, PolicyLayout, PolicyNet};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
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
    /// Validation pairs (from the validation split) the early stopping scores on.
    pub max_validation_pairs: usize,
    /// Wall-clock budget, s: the evaluator sets it to the RL run's training budget (equal effort).
    pub time_budget_s: f64,
    /// Cap on Adam updates (0 = none; the budget and early stopping decide).
    pub max_updates: usize,
    /// Updates between two validation losses.
    pub validate_every: usize,
    /// Validations without a new best loss before training stops (early stopping).
    pub patience: usize,
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
            max_validation_pairs: 20_000,
            time_budget_s: 900.0,
            max_updates: 0,
            validate_every: 500,
            patience: 20,
            seed: 1,
        }
    }
}

impl DirectMapConfig {
    /// The `--quick` variant: a few seconds of training.
    pub fn quick() -> Self {
        Self { max_pairs: 50_000, max_validation_pairs: 5_000, time_budget_s: 8.0, patience: 5, ..Self::default() }
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
    let mut rng = SmallRng::seed_from_u64(seed ^ 0xd1ec7);
    let mut p = Pairs { obs_dim: od, act_dim: ad, ..Default::default() };
    let mut buf = vec![0f32; od];
    for traj in trajs {
        let target = spec.actions.to_action(&traj.degradation);
        for t in 0..traj.len().saturating_sub(1) {
            if rng.random::<f64>() >= keep {
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
    pub validation_pairs: usize,
    pub updates: usize,
    pub seconds: f64,
    /// Why training stopped: "early_stopping", "time_budget" or "max_updates".
    pub stopped_by: String,
    /// (update, mean training MSE over the preceding window of updates), in target units ([-1, 1]).
    pub loss_curve: Vec<(usize, f64)>,
    /// (update, validation MSE) at every validation.
    pub validation_curve: Vec<(usize, f64)>,
    /// The update whose weights are kept (the best validation loss) and that loss.
    pub best_update: usize,
    pub best_validation_loss: f64,
    /// Mean training MSE of the first and last windows.
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

    /// Mean squared error of the predictions on `pairs`, no gradient.
    fn mse(&self, pairs: &Pairs) -> Result<f64, DirectMapError> {
        let pred = self.predict(&pairs.obs)?;
        let n = pred.len().max(1) as f64;
        Ok(pred.iter().zip(&pairs.target).map(|(p, t)| f64::from(p - t).powi(2)).sum::<f64>() / n)
    }

    /// A copy of every weight (to keep the best ones while training goes on).
    fn snapshot(&self) -> Vec<(String, Tensor)> {
        self.vs.variables().into_iter().map(|(k, t)| (k, t.detach().copy())).collect()
    }

    fn restore(&self, snapshot: &[(String, Tensor)]) -> Result<(), DirectMapError> {
        let mut vars = self.vs.variables();
        for (k, src) in snapshot {
            if let Some(v) = vars.get_mut(k) {
                tch::no_grad(|| v.f_copy_(src))?;
            }
        }
        Ok(())
    }

    /// Trains on `pairs` with Adam and MSE (minibatches drawn with replacement), scoring `validation` every
    /// `cfg.validate_every` updates, until the validation loss has not improved for `cfg.patience`
    /// validations, the time budget or the update cap. Returns the network with the weights of its best
    /// validation loss, and its curves.
    pub fn train(pairs: &Pairs, validation: &Pairs, cfg: &DirectMapConfig) -> Result<(Self, TrainLog), DirectMapError> {
        if pairs.is_empty() || validation.is_empty() {
            return Err(DirectMapError::NoPairs);
        }
        let started = Instant::now();
        let net = Self::new(pairs.obs_dim, pairs.act_dim, &cfg.hidden, cfg.seed);
        let n = pairs.len();
        let x_all = Tensor::f_from_slice(&pairs.obs)?.f_reshape([n as i64, pairs.obs_dim as i64])?;
        let y_all = Tensor::f_from_slice(&pairs.target)?.f_reshape([n as i64, pairs.act_dim as i64])?;
        let mut opt = nn::Adam::default().build(&net.vs, cfg.lr)?;
        let mut rng = SmallRng::seed_from_u64(cfg.seed ^ 0xba7c4);
        let window = 100usize;
        let mut log = TrainLog {
            pairs: n,
            validation_pairs: validation.len(),
            best_validation_loss: f64::INFINITY,
            ..Default::default()
        };
        let (mut acc, mut acc_n) = (0.0, 0usize);
        let mut idx = vec![0i64; cfg.batch_size];
        let mut best = net.snapshot();
        let mut since_best = 0usize;
        let mut update = 0usize;
        log.stopped_by = loop {
            update += 1;
            for v in idx.iter_mut() {
                *v = rng.random_range(0..n) as i64;
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
            if acc_n == window {
                log.loss_curve.push((update, acc / acc_n as f64));
                (acc, acc_n) = (0.0, 0);
            }
            log.updates = update;
            if update.is_multiple_of(cfg.validate_every.max(1)) {
                let v = net.mse(validation)?;
                log.validation_curve.push((update, v));
                if v < log.best_validation_loss {
                    (log.best_validation_loss, log.best_update, since_best) = (v, update, 0);
                    best = net.snapshot();
                } else {
                    since_best += 1;
                    if since_best >= cfg.patience {
                        break "early_stopping";
                    }
                }
            }
            if started.elapsed().as_secs_f64() >= cfg.time_budget_s {
                break "time_budget";
            }
            if cfg.max_updates > 0 && update >= cfg.max_updates {
                break "max_updates";
            }
        }
        .to_string();
        if acc_n > 0 {
            log.loss_curve.push((log.updates, acc / acc_n as f64));
        }
        // The last stretch since the previous validation is scored too, then the best weights are kept.
        let v = net.mse(validation)?;
        if v < log.best_validation_loss {
            (log.best_validation_loss, log.best_update) = (v, log.updates);
        } else {
            net.restore(&best)?;
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
    use bcal_common::dataset::{generate, Dataset, Experiment, ExperimentDef, Grid, Split, ValidationDef};
    use bcal_common::policy::Scratch;

    fn small_set() -> (Dataset, Dataset, MdpSpec) {
        let def = ExperimentDef {
            experiment: Experiment::Multi,
            q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 4 },
            r_o_ohm: Grid { start: 0.1, end: 0.2, n: 3 },
            loads_w: Grid { start: 8.0, end: 16.0, n: 9 },
            n_test_loads: 3,
            validation: ValidationDef {
                loads_w: vec![13.5],
                q_mobile_c: Grid { start: 4500.0, end: 6500.0, n: 3 },
                r_o_ohm: Grid { start: 0.125, end: 0.175, n: 2 },
            },
            dt_s: 1.0,
            max_steps: 100_000,
        };
        let model = BatteryModel::default();
        let train = generate(&def, &model, Split::Train).unwrap();
        let val = generate(&def, &model, Split::Validation).unwrap();
        let spec = MdpSpec::new(Experiment::Multi, &EnvConfig::default(), &train);
        (train, val, spec)
    }

    /// The direct mapping trains on a small set: the loss falls, predictions improve, the validation loss
    /// is tracked and the best weights are the ones kept.
    #[test]
    fn trains_on_a_small_set_loss_falls_and_predictions_improve() {
        tch::set_num_threads(2);
        let (train, val, spec) = small_set();
        let train: Vec<&Trajectory> = train.trajectories.iter().collect();
        let val: Vec<&Trajectory> = val.trajectories.iter().collect();
        let pairs = sample_pairs(&spec, &train, 6_000, 3);
        let val_pairs = sample_pairs(&spec, &val, 2_000, 4);
        assert!(pairs.len() > 3_000 && pairs.len() <= 7_000, "{}", pairs.len());
        let cfg = DirectMapConfig {
            hidden: vec![64, 64],
            max_updates: 800,
            validate_every: 100,
            patience: 1_000,
            time_budget_s: 60.0,
            lr: 2e-3,
            ..DirectMapConfig::default()
        };
        let untrained = DirectMap::new(spec.obs_dim(), spec.act_dim(), &cfg.hidden, cfg.seed);
        let (net, log) = DirectMap::train(&pairs, &val_pairs, &cfg).unwrap();
        assert_eq!((log.updates, log.stopped_by.as_str()), (800, "max_updates"));
        assert_eq!(log.validation_curve.len(), 8);
        assert!(log.final_loss < 0.2 * log.first_loss, "loss {} -> {}", log.first_loss, log.final_loss);
        let mse = |m: &DirectMap| {
            let p = m.predict(&pairs.obs).unwrap();
            p.iter().zip(&pairs.target).map(|(a, b)| f64::from(a - b).powi(2)).sum::<f64>() / p.len() as f64
        };
        let (before, after) = (mse(&untrained), mse(&net));
        assert!(after < 0.1 * before && after < 0.02, "prediction MSE {before} -> {after}");
        // The kept weights are the best validated ones.
        let best = log.validation_curve.iter().map(|v| v.1).fold(f64::INFINITY, f64::min);
        assert!((net.mse(&val_pairs).unwrap() - log.best_validation_loss).abs() < 1e-9);
        assert!(log.best_validation_loss <= best + 1e-12);

        // Early stopping: with the weights frozen (lr 0) the validation loss never improves, and training
        // stops after `patience` validations, long before the cap.
        let slow = DirectMapConfig { lr: 0.0, patience: 2, max_updates: 100_000, ..cfg.clone() };
        let (_, log) = DirectMap::train(&pairs, &val_pairs, &slow).unwrap();
        assert_eq!((log.stopped_by.as_str(), log.updates), ("early_stopping", 300), "{log:?}");

        // The pure-Rust export computes the same function.
        let pn = net.to_policy_net().unwrap();
        let mut s = Scratch::new(pn.layout());
        let pred = net.predict(&pairs.obs[..10 * spec.obs_dim()]).unwrap();
        for k in 0..10 {
            let (mut mean, mut ls) = ([0f32; 2], [0f32; 2]);
            let row = &pairs.obs[k * spec.obs_dim()..(k + 1) * spec.obs_dim()];
            pn.forward(row, &mut s, &mut mean, &mut ls);
            // Within the f32 rounding bound of two summation orders (libtorch picks its kernels per CPU).
            let (bound, _) = pn.rounding_bound(row);
            for j in 0..2 {
                let d = f64::from((mean[j] - pred[k * 2 + j]).abs());
                assert!(
                    d <= bound[j],
                    "row {k}: {} vs {} differ by {d:e}, bound {:e}",
                    mean[j],
                    pred[k * 2 + j],
                    bound[j]
                );
            }
        }
    }
}
