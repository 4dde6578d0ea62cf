//! Each LAC loss (Eq. 4-8) and the squashed-Gaussian log-probability against numbers computed by hand on
//! tiny tensors, plus the stop-gradients each equation requires and the shape checks that keep a
//! [n] vs [n, 1] mix-up from broadcasting silently.

use bcal_learner::lac::{
    actor_loss, beta_loss, beta_of, critic_loss, critic_target, critic_target_bounded, lambda_loss, lambda_of,
    lyapunov_decrease, squashed_gaussian,
};
use tch::Tensor;

fn t(v: &[f32]) -> Tensor {
    Tensor::from_slice(v)
}

fn scalar(v: f32) -> Tensor {
    Tensor::from(v)
}

fn val(x: &Tensor) -> f64 {
    x.double_value(&[])
}

fn vec(x: &Tensor) -> Vec<f32> {
    Vec::<f32>::try_from(&x.flatten(0, -1)).unwrap()
}

/// Within 64 f32 ulps of the magnitude: each value is a handful of f32 elementwise operations (libtorch's
/// vectorised exp/log/softplus are within a few ulps each, whatever kernel level the CPU selects) and the
/// hand-computed references carry 7-8 significant digits.
fn close(got: f64, want: f64) {
    let tol = 64.0 * f64::from(f32::EPSILON) * want.abs().max(1.0);
    assert!((got - want).abs() <= tol, "got {got}, want {want} (tolerance {tol:e})");
}

#[test]
fn critic_target_eq5_bootstraps_unless_terminal_and_carries_no_gradient() {
    // cost [1, 2], terminal [0, 1], L_targ(s', a') [10, 10], gamma 0.5: [1 + 0.5 * 10, 2 + 0] = [6, 2].
    let l_next = t(&[10.0, 10.0]).set_requires_grad(true);
    let y = critic_target(&t(&[1.0, 2.0]), 0.5, &t(&[0.0, 1.0]), &l_next).unwrap();
    assert_eq!(vec(&y), vec![6.0, 2.0]);
    assert!(!y.requires_grad(), "the critic target is a stop-gradient");
}

#[test]
fn a_bounded_critic_target_is_eq5_within_the_bound_and_clipped_past_it() {
    // cost [1, 2, 3], L_targ [10, 1000, 20], gamma 0.5, bound 100: [6, 502 -> 100, 13].
    let l_next = t(&[10.0, 1000.0, 20.0]);
    let (cost, terminal) = (t(&[1.0, 2.0, 3.0]), t(&[0.0, 0.0, 0.0]));
    let y = critic_target_bounded(&cost, 0.5, &terminal, &l_next, Some(100.0)).unwrap();
    assert_eq!(vec(&y), vec![6.0, 100.0, 13.0]);
    let plain = critic_target_bounded(&cost, 0.5, &terminal, &l_next, None).unwrap();
    assert_eq!(vec(&plain), vec(&critic_target(&cost, 0.5, &terminal, &l_next).unwrap()));
}

#[test]
fn critic_loss_eq4_is_half_mean_squared_error() {
    // L [1, 3], target [2, 1]: errors [-1, 2], squares [1, 4], mean 2.5, half 1.25.
    let l_sa = t(&[1.0, 3.0]).set_requires_grad(true);
    let loss = critic_loss(&l_sa, &t(&[2.0, 1.0])).unwrap();
    close(val(&loss), 1.25);
    // d/dL = (L - target) / n = [-0.5, 1].
    loss.backward();
    assert_eq!(vec(&l_sa.grad()), vec![-0.5, 1.0]);
}

#[test]
fn lyapunov_decrease_eq3_detaches_l_sa_and_keeps_l_next() {
    // L(s', pi(s')) [2, 4], L(s, a) [1, 5], cost [0.5, 1], alpha3 2: [2 - 1 + 1, 4 - 5 + 2] = [2, 1], mean 1.5.
    let l_next = t(&[2.0, 4.0]).set_requires_grad(true);
    let l_sa = t(&[1.0, 5.0]).set_requires_grad(true);
    let l_delta = lyapunov_decrease(&l_next, &l_sa, &t(&[0.5, 1.0]), 2.0).unwrap();
    close(val(&l_delta), 1.5);
    l_delta.backward();
    assert_eq!(vec(&l_next.grad()), vec![0.5, 0.5], "the gradient must reach L(s', pi(s'))");
    assert!(!l_sa.grad().defined(), "L(s, a) is detached in the decrease term");
}

#[test]
fn actor_loss_eq6_treats_lambda_and_beta_as_constants() {
    // lambda 0.5, l_delta 1.5, beta 0.2, log pi [-1, -3]: 0.5 * 1.5 + 0.2 * (-2) = 0.35.
    let lambda = scalar(0.5).set_requires_grad(true);
    let beta = scalar(0.2).set_requires_grad(true);
    let l_delta = scalar(1.5).set_requires_grad(true);
    let log_pi = t(&[-1.0, -3.0]).set_requires_grad(true);
    let loss = actor_loss(&lambda, &l_delta, &beta, &log_pi).unwrap();
    close(val(&loss), 0.35);
    loss.backward();
    close(val(&l_delta.grad()), 0.5);
    assert_eq!(vec(&log_pi.grad()), vec![0.1, 0.1]); // beta / n
    assert!(!lambda.grad().defined() && !beta.grad().defined(), "multipliers are constants in Eq. (6)");
}

#[test]
fn lambda_loss_eq8_raises_lambda_while_the_decrease_condition_is_violated() {
    // log_lambda = ln 0.5, l_delta 1.5: -(-0.693147 * 1.5) = 1.039721; d/dlog_lambda = -1.5 (descent raises it).
    let log_lambda = scalar(0.5f32.ln()).set_requires_grad(true);
    let l_delta = scalar(1.5).set_requires_grad(true);
    let loss = lambda_loss(&log_lambda, &l_delta).unwrap();
    close(val(&loss), 1.039_720_8);
    loss.backward();
    close(val(&log_lambda.grad()), -1.5);
    assert!(!l_delta.grad().defined(), "l_delta is detached in Eq. (8)");
}

#[test]
fn beta_loss_eq7_lowers_beta_while_entropy_exceeds_the_target() {
    // log_beta = ln 0.2, log pi [-1, -3], H_target -1: mean(log pi + H) = -3; loss = -(-1.609438 * -3) = -4.828314.
    // Entropy estimate 2 > target -1, so the gradient (+3) makes descent lower beta.
    let log_beta = scalar(0.2f32.ln()).set_requires_grad(true);
    let log_pi = t(&[-1.0, -3.0]).set_requires_grad(true);
    let loss = beta_loss(&log_beta, &log_pi, -1.0).unwrap();
    close(val(&loss), -4.828_313_7);
    loss.backward();
    close(val(&log_beta.grad()), 3.0);
    assert!(!log_pi.grad().defined(), "log pi is detached in Eq. (7)");
}

#[test]
fn lambda_is_clipped_to_one_and_beta_is_exp() {
    close(val(&lambda_of(&scalar(0.5f32.ln()))), 0.5);
    close(val(&lambda_of(&scalar(3.0))), 1.0);
    close(val(&beta_of(&scalar(0.0))), 1.0);
}

#[test]
fn squashed_gaussian_log_prob_matches_hand_values() {
    // Two action dimensions, mean [0, 1], log_std 0, eps 0: u = [0, 1], a = [0, tanh 1].
    // log N(u_j) = -0.5 ln(2 pi) = -0.918939 each; tanh correction: log(1 - tanh(0)^2) = 0,
    // log(1 - tanh(1)^2) = -0.867562. log pi = -1.837877 + 0.867562 = -0.970315.
    let (a, log_pi) = squashed_gaussian(
        &Tensor::from_slice2(&[[0.0f32, 1.0]]),
        &Tensor::zeros([1, 2], tch::kind::FLOAT_CPU),
        &Tensor::zeros([1, 2], tch::kind::FLOAT_CPU),
    );
    let a = vec(&a);
    assert_eq!(a[0], 0.0);
    close(f64::from(a[1]), 1f64.tanh());
    assert_eq!(log_pi.size(), vec![1]);
    close(val(&log_pi.squeeze()), -0.970_315_4);
    // One dimension, mean 0, log_std ln 2, eps 0.5: u = 1;
    // log N = -0.5 * 0.25 - ln 2 - 0.918939 = -1.737086; + 0.867562 = -0.869524.
    let (_, log_pi) = squashed_gaussian(
        &Tensor::from_slice2(&[[0.0f32]]),
        &Tensor::from_slice2(&[[2f32.ln()]]),
        &Tensor::from_slice2(&[[0.5f32]]),
    );
    close(val(&log_pi.squeeze()), -0.869_524_05);
}

#[test]
fn squashed_gaussian_stays_finite_where_the_naive_form_breaks() {
    // tanh(20)^2 rounds to 1 in f32, so log(1 - tanh^2) = -inf; the stable form gives 2 (ln 2 - 20 - softplus(-40)).
    let (_, log_pi) = squashed_gaussian(
        &Tensor::from_slice2(&[[20.0f32]]),
        &Tensor::zeros([1, 1], tch::kind::FLOAT_CPU),
        &Tensor::zeros([1, 1], tch::kind::FLOAT_CPU),
    );
    let want = -0.918_938_5 - 2.0 * (std::f64::consts::LN_2 - 20.0);
    close(val(&log_pi.squeeze()), want);
}

#[test]
fn mismatched_shapes_are_errors_not_broadcasts() {
    let column = Tensor::ones([2, 1], tch::kind::FLOAT_CPU);
    let row = Tensor::ones([2], tch::kind::FLOAT_CPU);
    let e = critic_loss(&column, &row).unwrap_err().to_string();
    assert!(e.contains("critic_loss") && e.contains("[2, 1]"), "{e}");
    assert!(lyapunov_decrease(&row, &column, &row, 1.0).is_err());
    assert!(critic_target(&row, 0.9, &row, &column).is_err());
    assert!(actor_loss(&row, &scalar(1.0), &scalar(1.0), &row).is_err());
}
