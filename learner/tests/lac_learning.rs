//! LAC learns on a toy MDP built directly from transitions: observations uniform in [-1, 1]^3, the cost
//! |a - a*(s)| with a*(s) = 0.6 s_0 depends on the action, next observations are independent of it.
//! Behaviour actions are uniform (off-policy data, as from a replay). After 1500 updates with small
//! networks the critic loss has fallen and the deterministic action tanh(mean(s)) sits near a*(s).

use bcal_common::config::TrainConfig;
use bcal_common::dataset::Experiment;
use bcal_common::policy::PolicyLayout;
use bcal_common::wire::Transition;
use bcal_learner::Lac;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};

const OBS: usize = 3;
const UPDATES: usize = 1500;

fn best_action(obs: &[f32]) -> f32 {
    0.6 * obs[0]
}

fn uniform(rng: &mut SmallRng) -> f32 {
    rng.random_range(-1.0..=1.0)
}

fn batch(rng: &mut SmallRng, n: usize) -> Vec<Transition> {
    (0..n)
        .map(|_| {
            let mut t = Transition::default();
            for k in 0..OBS {
                t.obs[k] = uniform(rng);
                t.next_obs[k] = uniform(rng);
            }
            t.action[0] = uniform(rng);
            t.cost = (t.action[0] - best_action(&t.obs[..OBS])).abs();
            t
        })
        .collect()
}

/// Mean |tanh(mean(s)) - a*(s)| over fixed test observations.
fn action_error(lac: &Lac, test_obs: &[f32]) -> f64 {
    let (mean, _) = lac.actor_mean_log_std(test_obs).unwrap();
    let n = mean.len();
    (0..n).map(|i| f64::from((mean[i].tanh() - best_action(&test_obs[i * OBS..])).abs())).sum::<f64>() / n as f64
}

#[test]
fn lac_learns_the_low_cost_action_on_a_toy_mdp() {
    let started = std::time::Instant::now();
    let mut c = TrainConfig { experiment: Experiment::SingleQ, ..Default::default() };
    c.lac.hidden = vec![32, 32];
    c.lac.batch_size = 64;
    c.lac.lr = 1e-3;
    c.lac.lr_multipliers = 3e-3;
    c.lac.gamma = 0.9;
    c.lac.tau = 0.02;
    c.lac.init_beta = 0.1;
    c.learner.torch_threads = 1;
    let cfg = c.validate().unwrap();
    let mut lac = Lac::new(&cfg, PolicyLayout { obs_dim: OBS, act_dim: 1, hidden: vec![32, 32] }, 42).unwrap();

    let mut rng = SmallRng::seed_from_u64(43);
    let test_obs: Vec<f32> = (0..512 * OBS).map(|_| uniform(&mut rng)).collect();
    let error_before = action_error(&lac, &test_obs);
    let mut critic_losses = Vec::with_capacity(UPDATES);
    for _ in 0..UPDATES {
        let m = lac.update(&batch(&mut rng, 64)).unwrap();
        assert!(!m.quarantined, "{m:?}");
        critic_losses.push(m.critic_loss);
    }
    let error_after = action_error(&lac, &test_obs);
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (loss_first, loss_last) = (mean(&critic_losses[..50]), mean(&critic_losses[UPDATES - 100..]));
    eprintln!(
        "toy LAC: critic loss {loss_first:.4} -> {loss_last:.4}, action error {error_before:.3} -> {error_after:.3}, \
         lambda {:.3}, beta {:.3}, {UPDATES} updates in {:.1?}",
        lac.lambda(),
        lac.beta(),
        started.elapsed()
    );
    assert!(loss_last < 0.5 * loss_first, "critic loss {loss_first} -> {loss_last}");
    assert!(error_after < 0.5 * error_before && error_after < 0.2, "action error {error_before} -> {error_after}");
    assert_eq!(lac.updates(), UPDATES as u64);
}
