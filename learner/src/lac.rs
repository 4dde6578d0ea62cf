//! The Lyapunov-based actor-critic (LAC; Han et al. 2020, paper Section 3.3) on tch, read top to bottom:
//! errors, the batch, the networks, one free function per loss, then [`Lac`] with its update step.
//! It owns the learner's networks and optimisers; it never prints, never exits and never touches the wire
//! (the process loop in `process.rs` feeds it batches and publishes [`Lac::actor_flat_params`]).
//!
//! Loss names (logged under these names in [`UpdateMetrics`]) and the paper's equations:
//!
//! | name                | formula                                                         | paper        |
//! | ------------------- | --------------------------------------------------------------- | ------------ |
//! | `critic_target`     | c + gamma (1 - terminal) L_targ(s', pi_targ(s')), no gradient   | Eq. (5)      |
//! | `critic_loss`       | 0.5 mean (L(s, a) - target)^2                                   | Eq. (4)      |
//! | `lyapunov_decrease` | mean(L(s', pi(s')) - stopgrad L(s, a) + alpha3 c)               | Eq. (3), (6) |
//! | `actor_loss`        | lambda l_delta + beta mean(log pi(a~ given s)), a~ ~ pi(s)      | Eq. (6)      |
//! | `lambda_loss`       | -log_lambda stopgrad(l_delta)                                   | Eq. (8)      |
//! | `beta_loss`         | -log_beta mean(stopgrad(log pi + H_target))                     | Eq. (7)      |
//!
//! with lambda = clamp(exp(log_lambda), 0, 1) and beta = exp(log_beta), constants inside `actor_loss`.
//!
//! One backward pass serves all four losses because each reaches only its own parameters: the critic
//! target is computed without gradient, `L(s', pi(s'))` in `lyapunov_decrease` runs the critic with
//! *detached weights* (gradient flows through the action into the actor, never into the critic's
//! parameters), and lambda, beta, l_delta and log pi are detached where the equations say stop-gradient.
//!
//! Non-finite chokepoint (DESIGN habit 8): a non-finite loss or gradient skips every optimiser step, the
//! update is counted as quarantined and the weights stay as they were.

use bcal_common::config::Observation;
use bcal_common::config::Validated;
use bcal_common::dataset::Experiment;
use bcal_common::mdp::ActionMap;
use bcal_common::policy::{PolicyFile, PolicyLayout, LOG_STD_MAX, LOG_STD_MIN};
use bcal_common::task::Task;
use bcal_common::wire::{Transition, MAX_ACT, MAX_OBS};
use tch::nn::{self, Module, OptimizerConfig};
use tch::{Device, Kind, Tensor};

/// Everything that can go wrong in the learner library; each message says what to do.
#[derive(Debug, thiserror::Error)]
pub enum LacError {
    #[error("network shape: {0}")]
    Shape(String),
    #[error("empty batch: a LAC update needs at least one transition")]
    EmptyBatch,
    #[error("batch transition {index}: {what}; the replay must quarantine such transitions before serving them")]
    BadTransition { index: usize, what: String },
    #[error("libtorch: {0}")]
    Torch(#[from] tch::TchError),
    #[error("checkpoint {path}: cannot {action}: {source}")]
    CheckpointIo { action: &'static str, path: std::path::PathBuf, source: std::io::Error },
    #[error("checkpoint {path} is unusable ({why}); delete it or point checkpoints/LATEST at an intact step folder")]
    CheckpointCorrupt { path: std::path::PathBuf, why: String },
    #[error("checkpoint {path} belongs to another run ({why}); resume with the config it was trained with or use a new run folder")]
    CheckpointMismatch { path: std::path::PathBuf, why: String },
}

/// What one update measured; logged as a JSON line by the process loop under these stable names.
#[derive(Clone, Debug, serde::Serialize)]
pub struct UpdateMetrics {
    /// Eq. (4).
    pub critic_loss: f64,
    /// l_delta of Eq. (6)/(8); negative when the Lyapunov decrease condition holds on the batch.
    pub lyapunov_decrease: f64,
    /// Eq. (6).
    pub actor_loss: f64,
    /// Eq. (8).
    pub lambda_loss: f64,
    /// Eq. (7).
    pub beta_loss: f64,
    /// Lyapunov multiplier used in this update, in [0, 1].
    pub lambda: f64,
    /// Entropy temperature used in this update.
    pub beta: f64,
    /// Monte-Carlo estimate of the policy entropy, -mean(log pi(a~ given s)), nats.
    pub entropy: f64,
    /// Mean cost of the batch.
    pub mean_cost: f64,
    /// Mean L(s, a) on the batch.
    pub lyapunov_value: f64,
    /// True when a loss or gradient was not finite and the update was skipped.
    pub quarantined: bool,
}

// ------------------------------------------------------------------------------------------------------
// The batch
// ------------------------------------------------------------------------------------------------------

/// A minibatch as tensors: obs/next_obs [n, obs_dim], action [n, act_dim], cost/terminal [n].
pub struct Batch {
    pub obs: Tensor,
    pub action: Tensor,
    pub cost: Tensor,
    pub next_obs: Tensor,
    pub terminal: Tensor,
}

impl Batch {
    /// Checks every transition (finite, cost >= 0, terminal in [0, 1]) and packs the used dimensions.
    pub fn new(layout: &PolicyLayout, batch: &[Transition]) -> Result<Self, LacError> {
        if batch.is_empty() {
            return Err(LacError::EmptyBatch);
        }
        let (od, ad, n) = (layout.obs_dim, layout.act_dim, batch.len());
        let mut obs = Vec::with_capacity(n * od);
        let mut next_obs = Vec::with_capacity(n * od);
        let mut action = Vec::with_capacity(n * ad);
        let mut cost = Vec::with_capacity(n);
        let mut terminal = Vec::with_capacity(n);
        for (index, t) in batch.iter().enumerate() {
            let bad = |what: String| LacError::BadTransition { index, what };
            let non_finite = |name: &str, v: &[f32]| {
                v.iter().position(|x| !x.is_finite()).map(|k| bad(format!("{name}[{k}] = {} is not finite", v[k])))
            };
            if let Some(e) = non_finite("obs", &t.obs[..od])
                .or_else(|| non_finite("next_obs", &t.next_obs[..od]))
                .or_else(|| non_finite("action", &t.action[..ad]))
            {
                return Err(e);
            }
            if !(t.cost.is_finite() && t.cost >= 0.0) {
                return Err(bad(format!("cost = {} must be finite and >= 0", t.cost)));
            }
            if !(0.0..=1.0).contains(&t.terminal) {
                return Err(bad(format!("terminal = {} must be in [0, 1]", t.terminal)));
            }
            obs.extend_from_slice(&t.obs[..od]);
            next_obs.extend_from_slice(&t.next_obs[..od]);
            action.extend_from_slice(&t.action[..ad]);
            cost.push(t.cost);
            terminal.push(t.terminal);
        }
        let (n, od, ad) = (n as i64, od as i64, ad as i64);
        Ok(Self {
            obs: Tensor::f_from_slice(&obs)?.f_reshape([n, od])?,
            action: Tensor::f_from_slice(&action)?.f_reshape([n, ad])?,
            cost: Tensor::f_from_slice(&cost)?,
            next_obs: Tensor::f_from_slice(&next_obs)?.f_reshape([n, od])?,
            terminal: Tensor::f_from_slice(&terminal)?,
        })
    }
}

// ------------------------------------------------------------------------------------------------------
// Networks
// ------------------------------------------------------------------------------------------------------

/// The actor: hidden Linear + LeakyReLU(0.01) layers, then the mean and log-std heads. Variable names
/// (`hidden<k>`, `mean`, `log_std`) and their order are those of [`PolicyLayout`]'s flat layout.
pub(crate) struct Actor {
    pub(crate) hidden: Vec<nn::Linear>,
    pub(crate) mean: nn::Linear,
    pub(crate) log_std: nn::Linear,
}

impl Actor {
    pub(crate) fn new(p: &nn::Path, layout: &PolicyLayout) -> Self {
        let mut hidden = Vec::with_capacity(layout.hidden.len());
        let mut input = layout.obs_dim as i64;
        for (k, h) in layout.hidden.iter().enumerate() {
            hidden.push(nn::linear(p / format!("hidden{k}"), input, *h as i64, Default::default()));
            input = *h as i64;
        }
        let act = layout.act_dim as i64;
        let mean = nn::linear(p / "mean", input, act, Default::default());
        let log_std = nn::linear(p / "log_std", input, act, Default::default());
        Self { hidden, mean, log_std }
    }

    /// Mean and clipped log-std of the Gaussian before the tanh squash; obs [n, obs_dim].
    pub(crate) fn forward(&self, obs: &Tensor) -> (Tensor, Tensor) {
        let mut x = obs.shallow_clone();
        for l in &self.hidden {
            x = l.forward(&x).leaky_relu(); // torch's default slope, = policy::LEAKY_SLOPE
        }
        let log_std = self.log_std.forward(&x).clamp(f64::from(LOG_STD_MIN), f64::from(LOG_STD_MAX));
        (self.mean.forward(&x), log_std)
    }

    /// A reparameterised sample a = tanh(mean + std eps) and its log-probability [n].
    pub(crate) fn sample(&self, obs: &Tensor) -> (Tensor, Tensor) {
        let (mean, log_std) = self.forward(obs);
        let eps = mean.randn_like();
        squashed_gaussian(&mean, &log_std, &eps)
    }

    /// Every Linear in [`PolicyLayout`]'s flat order.
    pub(crate) fn linears(&self) -> impl Iterator<Item = &nn::Linear> {
        self.hidden.iter().chain([&self.mean, &self.log_std])
    }
}

/// The Lyapunov critic L(s, a): concat(s, a) through hidden Linear + LeakyReLU layers. Following Han et
/// al.'s LAC code (`_build_l` returns `reduce_sum(square(net_last))`), the squared layer is the LAST
/// HIDDEN layer's activations (after its LeakyReLU): L = sum_j h_last,j^2 >= 0. There is no output Linear.
pub(crate) struct Critic {
    pub(crate) hidden: Vec<nn::Linear>,
}

impl Critic {
    pub(crate) fn new(p: &nn::Path, obs_dim: usize, act_dim: usize, hidden: &[usize]) -> Self {
        let mut layers = Vec::with_capacity(hidden.len());
        let mut input = (obs_dim + act_dim) as i64;
        for (k, h) in hidden.iter().enumerate() {
            layers.push(nn::linear(p / format!("hidden{k}"), input, *h as i64, Default::default()));
            input = *h as i64;
        }
        Self { hidden: layers }
    }

    /// L(s, a) [n]; obs [n, obs_dim], action [n, act_dim].
    pub(crate) fn forward(&self, obs: &Tensor, action: &Tensor) -> Tensor {
        let mut x = Tensor::cat(&[obs, action], 1);
        for l in &self.hidden {
            x = l.forward(&x).leaky_relu();
        }
        x.square().sum_dim_intlist(1, false, Kind::Float)
    }

    /// L(s, a) with the weights detached: the gradient reaches `action` (hence the actor) but never the
    /// critic's parameters. Used for L(s', pi(s')) in the actor's Lyapunov decrease term.
    pub(crate) fn forward_frozen(&self, obs: &Tensor, action: &Tensor) -> Tensor {
        let mut x = Tensor::cat(&[obs, action], 1);
        for l in &self.hidden {
            let bias = l.bs.as_ref().map(Tensor::detach);
            x = x.linear(&l.ws.detach(), bias.as_ref()).leaky_relu();
        }
        x.square().sum_dim_intlist(1, false, Kind::Float)
    }
}

// ------------------------------------------------------------------------------------------------------
// Losses: pure functions of tensors, one per equation; hand-checked in tests/lac_losses.rs.
// ------------------------------------------------------------------------------------------------------

fn same_shape(what: &str, a: &Tensor, b: &Tensor) -> Result<(), LacError> {
    if a.size() != b.size() {
        return Err(LacError::Shape(format!("{what}: shapes {:?} and {:?} differ", a.size(), b.size())));
    }
    Ok(())
}

/// Squashed Gaussian (Haarnoja et al. 2018, App. C): u = mean + std eps, a = tanh(u),
/// log pi(a | s) = sum_j [log N(u_j; mean_j, std_j) - log(1 - tanh(u_j)^2)], with the stable form
/// log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)). Returns (a [n, d], log pi [n]).
pub fn squashed_gaussian(mean: &Tensor, log_std: &Tensor, eps: &Tensor) -> (Tensor, Tensor) {
    let u = mean + log_std.exp() * eps;
    let half_log_2pi = 0.5 * (2.0 * std::f64::consts::PI).ln();
    let log_normal = eps.square() * -0.5 - log_std - half_log_2pi;
    let log_det_tanh = ((-&u * 2.0).softplus() + &u - std::f64::consts::LN_2) * -2.0;
    let log_pi = (log_normal - log_det_tanh).sum_dim_intlist(1, false, Kind::Float);
    (u.tanh(), log_pi)
}

/// Eq. (5): the Lyapunov critic's target c + gamma (1 - terminal) L_targ(s', pi_targ(s')), detached.
pub fn critic_target(cost: &Tensor, gamma: f64, terminal: &Tensor, l_target_next: &Tensor) -> Result<Tensor, LacError> {
    same_shape("critic_target cost/terminal", cost, terminal)?;
    same_shape("critic_target cost/l_target_next", cost, l_target_next)?;
    Ok((cost + (terminal.ones_like() - terminal) * l_target_next * gamma).detach())
}

/// [`critic_target`] clipped into [0, max] when a bound is set (`lac.critic_target_max`): equal to it
/// wherever the target lies in the range a cost-to-go can have.
pub fn critic_target_bounded(
    cost: &Tensor,
    gamma: f64,
    terminal: &Tensor,
    l_target_next: &Tensor,
    max: Option<f64>,
) -> Result<Tensor, LacError> {
    let y = critic_target(cost, gamma, terminal, l_target_next)?;
    Ok(match max {
        Some(m) => y.clamp(0.0, m),
        None => y,
    })
}

/// Eq. (4): critic_loss = 0.5 mean (L(s, a) - target)^2.
pub fn critic_loss(l_sa: &Tensor, target: &Tensor) -> Result<Tensor, LacError> {
    same_shape("critic_loss", l_sa, target)?;
    Ok((l_sa - target).square().mean(Kind::Float) * 0.5)
}

/// Eq. (3), the term of Eq. (6) and (8): l_delta = mean(L(s', pi(s')) - stopgrad L(s, a) + alpha3 c).
/// `l_next` must carry the gradient path through pi(s') into the actor.
pub fn lyapunov_decrease(l_next: &Tensor, l_sa: &Tensor, cost: &Tensor, alpha3: f64) -> Result<Tensor, LacError> {
    same_shape("lyapunov_decrease l_next/l_sa", l_next, l_sa)?;
    same_shape("lyapunov_decrease l_next/cost", l_next, cost)?;
    Ok((l_next - l_sa.detach() + cost * alpha3).mean(Kind::Float))
}

/// Eq. (6): actor_loss = lambda l_delta + beta mean(log pi(a~ | s)); lambda and beta are constants here.
pub fn actor_loss(lambda: &Tensor, l_delta: &Tensor, beta: &Tensor, log_pi: &Tensor) -> Result<Tensor, LacError> {
    for (what, t) in [("lambda", lambda), ("l_delta", l_delta), ("beta", beta)] {
        if t.numel() != 1 {
            return Err(LacError::Shape(format!("actor_loss: {what} must be a scalar, has shape {:?}", t.size())));
        }
    }
    Ok(lambda.detach() * l_delta + beta.detach() * log_pi.mean(Kind::Float))
}

/// Eq. (8) as a minimisation: lambda_loss = -log_lambda stopgrad(l_delta). lambda grows while the
/// Lyapunov decrease condition is violated (l_delta > 0).
pub fn lambda_loss(log_lambda: &Tensor, l_delta: &Tensor) -> Result<Tensor, LacError> {
    same_shape("lambda_loss", log_lambda, l_delta)?;
    Ok(-(log_lambda * l_delta.detach()))
}

/// Eq. (7) as a minimisation: beta_loss = -log_beta mean(stopgrad(log pi + H_target)). beta grows while
/// the entropy -log pi is below the target H_target.
pub fn beta_loss(log_beta: &Tensor, log_pi: &Tensor, target_entropy: f64) -> Result<Tensor, LacError> {
    if log_beta.numel() != 1 {
        return Err(LacError::Shape(format!("beta_loss: log_beta must be a scalar, has shape {:?}", log_beta.size())));
    }
    Ok(-(log_beta * (log_pi + target_entropy).detach().mean(Kind::Float)))
}

/// lambda = clamp(exp(log_lambda), 0, 1) (Han et al.'s SCALE_lambda_MIN_MAX).
pub fn lambda_of(log_lambda: &Tensor) -> Tensor {
    log_lambda.exp().clamp(0.0, 1.0)
}

/// beta = exp(log_beta).
pub fn beta_of(log_beta: &Tensor) -> Tensor {
    log_beta.exp()
}

// ------------------------------------------------------------------------------------------------------
// The learner
// ------------------------------------------------------------------------------------------------------

/// The LAC learner: actor, Lyapunov critic, their Polyak targets, lambda and beta, four Adam optimisers.
///
/// Randomness (initial weights and the policy's noise) comes from libtorch's global generator, seeded in
/// [`Lac::new`]; one learner per process.
pub struct Lac {
    pub(crate) layout: PolicyLayout,
    pub(crate) experiment: Experiment,
    pub(crate) lac_config: bcal_common::config::LacConfig,
    gamma: f64,
    critic_target_max: Option<f64>,
    alpha3: f64,
    tau: f64,
    pub(crate) lr_multipliers: f64,
    pub(crate) target_entropy: f64,
    pub(crate) actor_vs: nn::VarStore,
    pub(crate) actor: Actor,
    pub(crate) critic_vs: nn::VarStore,
    pub(crate) critic: Critic,
    pub(crate) actor_target_vs: nn::VarStore,
    actor_target: Actor,
    pub(crate) critic_target_vs: nn::VarStore,
    critic_target: Critic,
    pub(crate) lambda_vs: nn::VarStore,
    pub(crate) log_lambda: Tensor,
    pub(crate) beta_vs: nn::VarStore,
    pub(crate) log_beta: Tensor,
    actor_opt: nn::Optimizer,
    critic_opt: nn::Optimizer,
    lambda_opt: nn::Optimizer,
    beta_opt: nn::Optimizer,
    /// (target, online) variable pairs for the Polyak update.
    polyak_pairs: Vec<(Tensor, Tensor)>,
    pub(crate) updates: u64,
    pub(crate) quarantined: u64,
    /// Seconds of training so far, across restarts (saved in checkpoints): the time budget and the
    /// learning-rate schedule continue from it after a resume.
    pub(crate) trained_s: f64,
    /// Multiplier currently applied to every learning rate (the schedule's value).
    lr_factor: f64,
}

impl Lac {
    /// Builds fresh networks for `layout` (its hidden widths must equal `cfg.lac.hidden`, its action
    /// dimension the experiment's), targets hard-copied from them, and the four Adam optimisers.
    pub fn new(cfg: &Validated, layout: PolicyLayout, seed: u64) -> Result<Self, LacError> {
        let l = &cfg.config.lac;
        check_layout(cfg, &layout)?;
        if cfg.config.learner.torch_threads > 0 {
            tch::set_num_threads(i32::try_from(cfg.config.learner.torch_threads).unwrap_or(i32::MAX));
        }
        tch::manual_seed(seed as i64);
        let device = Device::Cpu;

        let actor_vs = nn::VarStore::new(device);
        let actor = Actor::new(&actor_vs.root(), &layout);
        let critic_vs = nn::VarStore::new(device);
        let critic = Critic::new(&critic_vs.root(), layout.obs_dim, layout.act_dim, &l.hidden);

        // Targets: same shapes, hard copies, never trained directly.
        let mut actor_target_vs = nn::VarStore::new(device);
        let actor_target = Actor::new(&actor_target_vs.root(), &layout);
        actor_target_vs.copy(&actor_vs)?;
        actor_target_vs.freeze();
        let mut critic_target_vs = nn::VarStore::new(device);
        let critic_target = Critic::new(&critic_target_vs.root(), layout.obs_dim, layout.act_dim, &l.hidden);
        critic_target_vs.copy(&critic_vs)?;
        critic_target_vs.freeze();

        // Multipliers live in log space (Han et al.); lambda is clipped to [0, 1] when used.
        let lambda_vs = nn::VarStore::new(device);
        let log_lambda = lambda_vs.root().f_var("log_lambda", &[], nn::Init::Const(l.init_lambda.ln()))?;
        let beta_vs = nn::VarStore::new(device);
        let log_beta = beta_vs.root().f_var("log_beta", &[], nn::Init::Const(l.init_beta.ln()))?;

        let actor_opt = nn::Adam::default().build(&actor_vs, l.lr)?;
        let critic_opt = nn::Adam::default().build(&critic_vs, l.lr)?;
        let lambda_opt = nn::Adam::default().build(&lambda_vs, cfg.lr_multipliers)?;
        let beta_opt = nn::Adam::default().build(&beta_vs, cfg.lr_multipliers)?;

        let polyak_pairs = polyak_pairs(&actor_target_vs, &actor_vs)?
            .into_iter()
            .chain(polyak_pairs(&critic_target_vs, &critic_vs)?)
            .collect();

        Ok(Self {
            layout,
            experiment: cfg.config.experiment,
            lac_config: l.clone(),
            gamma: l.gamma,
            critic_target_max: l.cost_max.map(|c| c / (1.0 - l.gamma)),
            alpha3: l.alpha3,
            tau: l.tau,
            lr_multipliers: cfg.lr_multipliers,
            target_entropy: cfg.target_entropy,
            actor_vs,
            actor,
            critic_vs,
            critic,
            actor_target_vs,
            actor_target,
            critic_target_vs,
            critic_target,
            lambda_vs,
            log_lambda,
            beta_vs,
            log_beta,
            actor_opt,
            critic_opt,
            lambda_opt,
            beta_opt,
            polyak_pairs,
            updates: 0,
            quarantined: 0,
            trained_s: 0.0,
            lr_factor: 1.0,
        })
    }

    /// Sets the actor's mean head (and its target's) to zero, so the deterministic action starts at 0: for
    /// the correction design, the tuned filter itself, where training starts (issue 18). The log-std head
    /// keeps its initialisation, so the policy still explores around it.
    pub fn zero_mean_head(&mut self) -> Result<(), LacError> {
        tch::no_grad(|| -> Result<(), LacError> {
            for actor in [&mut self.actor, &mut self.actor_target] {
                let _ = actor.mean.ws.f_zero_()?;
                if let Some(b) = &mut actor.mean.bs {
                    let _ = b.f_zero_()?;
                }
            }
            Ok(())
        })
    }

    /// The actor's side of one update: the Lyapunov decrease term l_delta of Eq. (3)/(6)/(8) and
    /// log pi(a~ | s) [n] with a~ ~ pi(s). One actor pass over [s; s'] samples both a~ and the next action
    /// a' ~ pi(s'): a fresh sample from the CURRENT actor whose gradient path into the actor is kept (a
    /// public PyTorch port of the paper's code sampled a' under no_grad, so the actor never learned from
    /// this term). `cut_actor_path = true` reproduces that bug; only the regression test uses it.
    fn actor_terms(&self, b: &Batch, l_sa: &Tensor, cut_actor_path: bool) -> Result<(Tensor, Tensor), LacError> {
        let n = b.cost.size()[0];
        let (actions, log_pis) = self.actor.sample(&Tensor::cat(&[&b.obs, &b.next_obs], 0));
        let log_pi = log_pis.narrow(0, 0, n);
        let a_next = actions.narrow(0, n, n);
        let a_next = if cut_actor_path { a_next.detach() } else { a_next };
        // Critic weights detached: this term trains the actor only.
        let l_next = self.critic.forward_frozen(&b.next_obs, &a_next);
        let l_delta = lyapunov_decrease(&l_next, l_sa, &b.cost, self.alpha3)?; // Eq. (3)
        Ok((l_delta, log_pi))
    }

    /// One LAC update on a minibatch (normally `cfg.lac.batch_size` transitions; any length >= 1).
    /// Errors on an invalid batch; a non-finite loss or gradient is quarantined (no step, metrics say so).
    pub fn update(&mut self, batch: &[Transition]) -> Result<UpdateMetrics, LacError> {
        let b = Batch::new(&self.layout, batch)?;

        // Eq. (5): the target from the target networks, without gradient.
        let target = tch::no_grad(|| {
            let (a_next_target, _) = self.actor_target.sample(&b.next_obs);
            let l_target_next = self.critic_target.forward(&b.next_obs, &a_next_target);
            critic_target_bounded(&b.cost, self.gamma, &b.terminal, &l_target_next, self.critic_target_max)
        })?;
        // Eq. (4).
        let l_sa = self.critic.forward(&b.obs, &b.action);
        let critic_loss_t = critic_loss(&l_sa, &target)?;

        let (l_delta, log_pi) = self.actor_terms(&b, &l_sa, false)?;

        let lambda = lambda_of(&self.log_lambda).detach();
        let beta = beta_of(&self.log_beta).detach();
        let actor_loss_t = actor_loss(&lambda, &l_delta, &beta, &log_pi)?; // Eq. (6)
        let lambda_loss_t = lambda_loss(&self.log_lambda, &l_delta)?; // Eq. (8)
        let beta_loss_t = beta_loss(&self.log_beta, &log_pi, self.target_entropy)?; // Eq. (7)

        let metrics = UpdateMetrics {
            critic_loss: critic_loss_t.f_double_value(&[])?,
            lyapunov_decrease: l_delta.f_double_value(&[])?,
            actor_loss: actor_loss_t.f_double_value(&[])?,
            lambda_loss: lambda_loss_t.f_double_value(&[])?,
            beta_loss: beta_loss_t.f_double_value(&[])?,
            lambda: lambda.f_double_value(&[])?,
            beta: beta.f_double_value(&[])?,
            entropy: -log_pi.mean(Kind::Float).f_double_value(&[])?,
            mean_cost: b.cost.mean(Kind::Float).f_double_value(&[])?,
            lyapunov_value: l_sa.mean(Kind::Float).f_double_value(&[])?,
            quarantined: false,
        };
        let losses = [
            metrics.critic_loss,
            metrics.lyapunov_decrease,
            metrics.actor_loss,
            metrics.lambda_loss,
            metrics.beta_loss,
        ];
        if losses.iter().any(|v| !v.is_finite()) {
            return Ok(self.quarantine(metrics));
        }

        // Each loss reaches only its own parameters (see the module doc), so one backward pass suffices.
        self.zero_grads();
        (&critic_loss_t + &actor_loss_t + &lambda_loss_t + &beta_loss_t).f_backward()?;
        if !self.grads_finite()? {
            self.zero_grads();
            return Ok(self.quarantine(metrics));
        }
        self.critic_opt.step();
        self.actor_opt.step();
        self.lambda_opt.step();
        self.beta_opt.step();
        self.polyak_update()?;
        self.updates += 1;
        Ok(metrics)
    }

    fn quarantine(&mut self, mut metrics: UpdateMetrics) -> UpdateMetrics {
        self.quarantined += 1;
        metrics.quarantined = true;
        metrics
    }

    fn zero_grads(&mut self) {
        self.actor_opt.zero_grad();
        self.critic_opt.zero_grad();
        self.lambda_opt.zero_grad();
        self.beta_opt.zero_grad();
    }

    /// True when every defined gradient of the trained variables is finite.
    fn grads_finite(&self) -> Result<bool, LacError> {
        let vss = [&self.actor_vs, &self.critic_vs, &self.lambda_vs, &self.beta_vs];
        let sums: Vec<Tensor> = vss
            .iter()
            .flat_map(|vs| vs.trainable_variables())
            .map(|v| v.grad())
            .filter(Tensor::defined)
            .map(|g| g.abs().sum(Kind::Float))
            .collect();
        if sums.is_empty() {
            return Ok(true);
        }
        Ok(Tensor::stack(&sums, 0).sum(Kind::Float).f_double_value(&[])?.is_finite())
    }

    /// theta_targ <- (1 - tau) theta_targ + tau theta, for actor and critic.
    fn polyak_update(&mut self) -> Result<(), LacError> {
        let tau = self.tau;
        tch::no_grad(|| {
            for (target, online) in &mut self.polyak_pairs {
                let _ = target.f_lerp_(online, tau)?;
            }
            Ok::<(), tch::TchError>(())
        })?;
        Ok(())
    }

    /// Completed (not quarantined) updates; continues from the checkpoint after a resume.
    pub fn updates(&self) -> u64 {
        self.updates
    }

    /// Seconds of training so far, across restarts.
    pub fn trained_s(&self) -> f64 {
        self.trained_s
    }

    /// Sets the seconds trained so far (the process loop's clock); saved with the next checkpoint.
    pub fn set_trained_s(&mut self, seconds: f64) {
        self.trained_s = seconds;
    }

    /// Sets every learning rate to `factor` times its configured start value (the schedule of
    /// [`bcal_common::config::LacConfig::lr_factor`]): actor and critic from `lac.lr`, lambda and beta
    /// from the resolved multiplier rate.
    pub fn set_lr_factor(&mut self, factor: f64) {
        if factor == self.lr_factor {
            return;
        }
        self.lr_factor = factor;
        let lr = self.lac_config.lr * factor;
        self.actor_opt.set_lr(lr);
        self.critic_opt.set_lr(lr);
        self.lambda_opt.set_lr(self.lr_multipliers * factor);
        self.beta_opt.set_lr(self.lr_multipliers * factor);
    }

    /// The multiplier currently applied to every learning rate.
    pub fn lr_factor(&self) -> f64 {
        self.lr_factor
    }

    /// Updates skipped because a loss or gradient was not finite (restored from the checkpoint too).
    pub fn quarantined(&self) -> u64 {
        self.quarantined
    }

    /// The actor's parameters in exactly [`PolicyLayout`]'s flat order (per Linear: weight [out, in]
    /// row-major, then bias; hidden layers, mean head, log-std head).
    pub fn actor_flat_params(&self) -> Vec<f32> {
        let mut flat = Vec::with_capacity(self.layout.n_params());
        for l in self.actor.linears() {
            let bias = l.bs.as_ref().expect("every Linear has a bias");
            for t in [&l.ws, bias] {
                let v = Vec::<f32>::try_from(&t.detach().flatten(0, -1)).expect("float parameters convert");
                flat.extend_from_slice(&v);
            }
        }
        flat
    }

    pub fn layout(&self) -> &PolicyLayout {
        &self.layout
    }

    /// Current lambda = clamp(exp(log_lambda), 0, 1).
    pub fn lambda(&self) -> f64 {
        lambda_of(&self.log_lambda).double_value(&[])
    }

    /// Current beta = exp(log_beta).
    pub fn beta(&self) -> f64 {
        beta_of(&self.log_beta).double_value(&[])
    }

    /// The tch actor's mean and clipped log-std for `obs` (n rows of obs_dim, row-major), each n * act_dim.
    pub fn actor_mean_log_std(&self, obs: &[f32]) -> Result<(Vec<f32>, Vec<f32>), LacError> {
        let od = self.layout.obs_dim;
        if obs.is_empty() || !obs.len().is_multiple_of(od) {
            return Err(LacError::Shape(format!("{} observation values are not rows of {od}", obs.len())));
        }
        let x = Tensor::f_from_slice(obs)?.f_reshape([(obs.len() / od) as i64, od as i64])?;
        let (mean, log_std) = tch::no_grad(|| self.actor.forward(&x));
        Ok((Vec::<f32>::try_from(&mean.flatten(0, -1))?, Vec::<f32>::try_from(&log_std.flatten(0, -1))?))
    }

    /// L(s, a) of every transition (diagnostics; no gradient).
    pub fn lyapunov_values(&self, batch: &[Transition]) -> Result<Vec<f32>, LacError> {
        let b = Batch::new(&self.layout, batch)?;
        let l = tch::no_grad(|| self.critic.forward(&b.obs, &b.action));
        Ok(Vec::<f32>::try_from(&l)?)
    }

    /// Diagnostic behind the regression test on the actor's gradient path: back-propagates l_delta
    /// ALONE and returns (L2 norm of the actor's gradient, L2 norm of the critic's gradient), then clears
    /// all gradients. With `cut_actor_path` the next action is sampled under no_grad, as in the buggy
    /// port, and the actor's gradient is zero. No weights change.
    pub fn lyapunov_decrease_grad_norms(
        &mut self,
        batch: &[Transition],
        cut_actor_path: bool,
    ) -> Result<(f64, f64), LacError> {
        let b = Batch::new(&self.layout, batch)?;
        let l_sa = self.critic.forward(&b.obs, &b.action);
        let (l_delta, _) = self.actor_terms(&b, &l_sa, cut_actor_path)?;
        self.zero_grads();
        if l_delta.requires_grad() {
            l_delta.f_backward()?;
        }
        let norm = |vs: &nn::VarStore| -> Result<f64, LacError> {
            let mut sq = 0.0;
            for v in vs.trainable_variables() {
                let g = v.grad();
                if g.defined() {
                    sq += g.square().sum(Kind::Double).f_double_value(&[])?;
                }
            }
            Ok(sq.sqrt())
        };
        let norms = (norm(&self.actor_vs)?, norm(&self.critic_vs)?);
        self.zero_grads();
        Ok(norms)
    }

    /// The trained calibrator as a libtorch-free [`PolicyFile`]; the caller saves it (e.g. to
    /// `run_dir/policy.bcalpol`). `task` must be the task this learner trains on.
    pub fn policy_file(&self, task: Task, experiment: Experiment) -> PolicyFile {
        PolicyFile {
            layout: self.layout.clone(),
            task,
            experiment,
            update_step: self.updates,
            params: self.actor_flat_params(),
        }
    }
}

/// The layout must fit the wire limits, the config's hidden widths and the experiment's action dimension.
pub(crate) fn check_layout(cfg: &Validated, layout: &PolicyLayout) -> Result<(), LacError> {
    if layout.obs_dim == 0 || layout.obs_dim > MAX_OBS {
        return Err(LacError::Shape(format!("obs_dim {} must be in 1..={MAX_OBS}", layout.obs_dim)));
    }
    if layout.act_dim == 0 || layout.act_dim > MAX_ACT {
        return Err(LacError::Shape(format!("act_dim {} must be in 1..={MAX_ACT}", layout.act_dim)));
    }
    if layout.hidden != cfg.config.lac.hidden {
        return Err(LacError::Shape(format!(
            "policy layout hidden {:?} differs from lac.hidden {:?}",
            layout.hidden, cfg.config.lac.hidden
        )));
    }
    let want = match cfg.config.env.observation {
        Observation::Measured => cfg.config.measured.act_dim(),
        _ => ActionMap::from_config(cfg.config.experiment, &cfg.config.env).dim(),
    };
    if layout.act_dim != want {
        return Err(LacError::Shape(format!(
            "act_dim {} but experiment {} calibrates {want} parameter(s)",
            layout.act_dim, cfg.config.experiment
        )));
    }
    Ok(())
}

/// Shallow (shared-storage) handles to every (target, online) variable pair, matched by name.
fn polyak_pairs(target: &nn::VarStore, online: &nn::VarStore) -> Result<Vec<(Tensor, Tensor)>, LacError> {
    let online_vars = online.variables();
    let mut pairs: Vec<(String, Tensor, Tensor)> = Vec::new();
    for (name, t) in target.variables() {
        let o = online_vars
            .get(&name)
            .ok_or_else(|| LacError::Shape(format!("target variable {name} has no online twin")))?;
        pairs.push((name, t, o.shallow_clone()));
    }
    pairs.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(pairs.into_iter().map(|(_, t, o)| (t, o)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::config::TrainConfig;

    fn flat(vs: &nn::VarStore) -> Vec<f32> {
        let mut vars: Vec<_> = vs.variables().into_iter().collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        vars.iter().flat_map(|(_, t)| Vec::<f32>::try_from(&t.detach().flatten(0, -1)).unwrap()).collect()
    }

    /// Targets start as hard copies and then follow theta_targ <- (1 - tau) theta_targ + tau theta.
    #[test]
    fn targets_are_hard_copied_then_polyak_averaged() {
        let mut c = TrainConfig { experiment: Experiment::SingleQ, ..Default::default() };
        c.lac.hidden = vec![8];
        c.lac.tau = 0.25;
        let cfg = c.validate().unwrap();
        let mut lac = Lac::new(&cfg, PolicyLayout { obs_dim: 3, act_dim: 1, hidden: vec![8] }, 1).unwrap();
        assert_eq!(flat(&lac.actor_target_vs), flat(&lac.actor_vs));
        assert_eq!(flat(&lac.critic_target_vs), flat(&lac.critic_vs));
        let (actor_old, critic_old) = (flat(&lac.actor_vs), flat(&lac.critic_vs));
        let mut t = Transition::default();
        t.obs[..3].copy_from_slice(&[0.5, -1.0, 2.0]);
        t.action[0] = 0.3;
        t.cost = 1.0;
        assert!(!lac.update(&[t, t]).unwrap().quarantined);
        for (target, old, new) in [
            (flat(&lac.actor_target_vs), actor_old, flat(&lac.actor_vs)),
            (flat(&lac.critic_target_vs), critic_old, flat(&lac.critic_vs)),
        ] {
            assert_ne!(old, new, "the online network moved");
            for ((t, o), n) in target.iter().zip(&old).zip(&new) {
                assert!((t - (0.75 * o + 0.25 * n)).abs() < 1e-6);
            }
        }
    }
}
