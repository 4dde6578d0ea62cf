//! Where the gradients go and what happens to bad numbers:
//! - l_delta alone gives the actor a non-zero gradient through the sampled pi(s') and the critic none
//!   (regression: a public PyTorch port sampled pi(s') under no_grad; that variant gives the actor zero);
//! - a non-finite loss is quarantined: no step, weights and counter unchanged, the quarantine counted;
//! - an invalid batch is an error naming the transition and the field.

use bcal_common::config::{TrainConfig, Validated};
use bcal_common::dataset::Experiment;
use bcal_common::policy::PolicyLayout;
use bcal_common::wire::Transition;
use bcal_learner::{Lac, LacError};

fn setup() -> (Validated, PolicyLayout) {
    let mut c = TrainConfig { experiment: Experiment::Multi, ..Default::default() };
    c.lac.hidden = vec![16, 16];
    c.learner.torch_threads = 1;
    (c.validate().unwrap(), PolicyLayout { obs_dim: 5, act_dim: 2, hidden: vec![16, 16] })
}

fn batch(seed: u64, n: usize) -> Vec<Transition> {
    Transition::synthetic_batch(seed, n, 5, 2)
}

#[test]
fn lyapunov_decrease_reaches_the_actor_through_the_sampled_next_action() {
    let (cfg, layout) = setup();
    let mut lac = Lac::new(&cfg, layout, 1).unwrap();
    let b = batch(2, 32);
    let before = lac.actor_flat_params();
    let (actor, critic) = lac.lyapunov_decrease_grad_norms(&b, false).unwrap();
    assert!(actor > 1e-6, "l_delta must train the actor, actor gradient norm {actor}");
    assert_eq!(critic, 0.0, "l_delta must not train the critic's parameters");
    // The bug this pins: pi(s') sampled without gradient leaves the actor nothing to learn from l_delta.
    let (actor_cut, _) = lac.lyapunov_decrease_grad_norms(&b, true).unwrap();
    assert_eq!(actor_cut, 0.0);
    assert_eq!(lac.actor_flat_params(), before, "the diagnostic never steps");
    assert_eq!(lac.updates(), 0);
}

#[test]
fn a_non_finite_loss_is_quarantined_and_changes_nothing() {
    let (cfg, layout) = setup();
    let mut lac = Lac::new(&cfg, layout, 3).unwrap();
    let mut b = batch(4, 16);
    // Finite inputs whose squared error overflows f32: the critic loss is inf.
    b[3].cost = 3.0e38;
    let (params, l_before) = (lac.actor_flat_params(), lac.lyapunov_values(&b).unwrap());
    let m = lac.update(&b).unwrap();
    assert!(m.quarantined && !m.critic_loss.is_finite(), "{m:?}");
    assert_eq!(lac.actor_flat_params(), params);
    assert_eq!(lac.lyapunov_values(&b).unwrap(), l_before);
    assert_eq!((lac.updates(), lac.quarantined()), (0, 1));
    // Training continues on good data.
    let m = lac.update(&batch(5, 16)).unwrap();
    assert!(!m.quarantined && m.critic_loss.is_finite());
    assert_eq!((lac.updates(), lac.quarantined()), (1, 1));
    assert_ne!(lac.actor_flat_params(), params);
}

#[test]
fn invalid_batches_are_errors_naming_the_problem() {
    let (cfg, layout) = setup();
    let mut lac = Lac::new(&cfg, layout, 5).unwrap();
    let good = batch(6, 8);
    assert!(matches!(lac.update(&[]), Err(LacError::EmptyBatch)));
    let mut b = good.clone();
    b[2].next_obs[4] = f32::NAN;
    let e = lac.update(&b).unwrap_err().to_string();
    assert!(e.contains("transition 2") && e.contains("next_obs[4]"), "{e}");
    let mut b = good.clone();
    b[5].cost = -1.0;
    let e = lac.update(&b).unwrap_err().to_string();
    assert!(e.contains("transition 5") && e.contains("cost"), "{e}");
    let mut b = good.clone();
    b[0].terminal = 2.0;
    assert!(lac.update(&b).unwrap_err().to_string().contains("terminal"));
    // Unused slots (obs beyond obs_dim, action beyond act_dim) are ignored.
    let mut b = good;
    b[1].obs[20] = f32::INFINITY;
    assert!(lac.update(&b).is_ok());
    // A single transition is a valid batch.
    assert!(!lac.update(&b[..1]).unwrap().quarantined);
}

#[test]
fn lac_can_move_to_another_thread() {
    fn is_send<T: Send>() {}
    is_send::<Lac>();
}
