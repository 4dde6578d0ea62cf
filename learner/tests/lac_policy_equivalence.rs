//! The learner's tch actor and common's pure-Rust [`PolicyNet`] (what actors and the evaluator run) give
//! the same mean and log-std from `Lac::actor_flat_params`, for the paper's shape (obs 15, act 2, hidden
//! [256; 3]) and a single-action shape, on fresh weights and after Adam has moved them.
//!
//! "The same" means within [`PolicyNet::rounding_bound`]: libtorch picks its CPU kernels at run time
//! (`ATEN_CPU_CAPABILITY` = default / avx2 / avx512) and so its summation order, so the bound grows with
//! the dot-product length and the magnitudes summed instead of being a constant that suits one CPU.

use bcal_common::config::{TrainConfig, Validated};
use bcal_common::dataset::Experiment;
use bcal_common::policy::{PolicyLayout, PolicyNet, Scratch};
use bcal_common::wire::Transition;
use bcal_learner::Lac;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};

fn config(experiment: Experiment, hidden: &[usize]) -> Validated {
    let mut c = TrainConfig { experiment, ..Default::default() };
    c.lac.hidden = hidden.to_vec();
    c.learner.torch_threads = 1;
    c.validate().unwrap()
}

fn random_obs(rng: &mut SmallRng, n: usize, dim: usize) -> Vec<f32> {
    // Wide inputs so that LeakyReLU's negative side and the log-std clip are both exercised.
    (0..n * dim).map(|_| rng.sample::<f32, _>(rand_distr::StandardNormal) * 3.0).collect()
}

fn assert_equivalent(lac: &Lac, rng: &mut SmallRng) {
    let layout = lac.layout().clone();
    let net = PolicyNet::from_flat(layout.clone(), lac.actor_flat_params()).unwrap();
    let n = 64;
    let obs = random_obs(rng, n, layout.obs_dim);
    let (mean_tch, log_std_tch) = lac.actor_mean_log_std(&obs).unwrap();
    let mut scratch = Scratch::new(&layout);
    let (mut mean, mut log_std) = (vec![0f32; layout.act_dim], vec![0f32; layout.act_dim]);
    // Worst ratio of the observed difference to its bound (<= 1 passes), and the largest difference.
    let (mut worst_ratio, mut worst_diff) = (0f64, 0f64);
    for i in 0..n {
        let row = &obs[i * layout.obs_dim..(i + 1) * layout.obs_dim];
        net.forward(row, &mut scratch, &mut mean, &mut log_std);
        let (mean_bound, log_std_bound) = net.rounding_bound(row);
        for j in 0..layout.act_dim {
            let k = i * layout.act_dim + j;
            for (d, b) in [(mean[j] - mean_tch[k], mean_bound[j]), (log_std[j] - log_std_tch[k], log_std_bound[j])] {
                let d = f64::from(d.abs());
                worst_diff = worst_diff.max(d);
                worst_ratio = worst_ratio.max(d / b.max(f64::MIN_POSITIVE));
            }
        }
    }
    eprintln!("{layout:?}: largest difference {worst_diff:e}, {worst_ratio:.3}x the bound");
    assert!(
        worst_ratio <= 1.0,
        "pure-Rust and tch actors differ by {worst_diff:e}, {worst_ratio:.2}x the rounding bound, for {layout:?}"
    );
}

fn nudge(lac: &mut Lac, rng: &mut SmallRng) {
    let (od, ad) = (lac.layout().obs_dim, lac.layout().act_dim);
    let batch = Transition::synthetic_batch(rng.random(), 32, od, ad);
    for _ in 0..3 {
        assert!(!lac.update(&batch).unwrap().quarantined);
    }
}

#[test]
fn paper_shape_obs15_act2_hidden_256x3() {
    let cfg = config(Experiment::Multi, &[256, 256, 256]);
    let layout = PolicyLayout { obs_dim: 15, act_dim: 2, hidden: vec![256; 3] };
    let mut lac = Lac::new(&cfg, layout.clone(), 7).unwrap();
    assert_eq!(lac.actor_flat_params().len(), layout.n_params());
    let mut rng = SmallRng::seed_from_u64(11);
    assert_equivalent(&lac, &mut rng);
    nudge(&mut lac, &mut rng);
    assert_equivalent(&lac, &mut rng);
}

#[test]
fn single_action_shape() {
    let cfg = config(Experiment::SingleQ, &[32, 16]);
    let layout = PolicyLayout { obs_dim: 15, act_dim: 1, hidden: vec![32, 16] };
    let mut lac = Lac::new(&cfg, layout, 8).unwrap();
    let mut rng = SmallRng::seed_from_u64(12);
    assert_equivalent(&lac, &mut rng);
    nudge(&mut lac, &mut rng);
    assert_equivalent(&lac, &mut rng);
}

#[test]
fn layout_must_match_config_and_experiment() {
    let cfg = config(Experiment::SingleQ, &[16]);
    let e = Lac::new(&cfg, PolicyLayout { obs_dim: 15, act_dim: 2, hidden: vec![16] }, 1).err().unwrap();
    assert!(e.to_string().contains("act_dim 2"), "{e}");
    let e = Lac::new(&cfg, PolicyLayout { obs_dim: 15, act_dim: 1, hidden: vec![32] }, 1).err().unwrap();
    assert!(e.to_string().contains("lac.hidden"), "{e}");
}
