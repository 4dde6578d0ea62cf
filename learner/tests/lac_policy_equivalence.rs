//! The learner's tch actor and common's pure-Rust [`PolicyNet`] (what actors and the evaluator run) give
//! the same mean and log-std to 1e-5 from `Lac::actor_flat_params`, for the paper's shape (obs 15, act 2,
//! hidden [256; 3]) and a single-action shape, on fresh weights and after Adam has moved them.

use bcal_common::config::{TrainConfig, Validated};
use bcal_common::dataset::Experiment;
use bcal_common::mdp::SplitMix64;
use bcal_common::policy::{PolicyLayout, PolicyNet, Scratch};
use bcal_common::wire::Transition;
use bcal_learner::Lac;

fn config(experiment: Experiment, hidden: &[usize]) -> Validated {
    let mut c = TrainConfig { experiment, ..Default::default() };
    c.lac.hidden = hidden.to_vec();
    c.learner.torch_threads = 1;
    c.validate().unwrap()
}

fn random_obs(rng: &mut SplitMix64, n: usize, dim: usize) -> Vec<f32> {
    // Wide inputs so that LeakyReLU's negative side and the log-std clip are both exercised.
    (0..n * dim).map(|_| (rng.normal() * 3.0) as f32).collect()
}

fn assert_equivalent(lac: &Lac, rng: &mut SplitMix64) {
    let layout = lac.layout().clone();
    let net = PolicyNet::from_flat(layout.clone(), lac.actor_flat_params()).unwrap();
    let n = 64;
    let obs = random_obs(rng, n, layout.obs_dim);
    let (mean_tch, log_std_tch) = lac.actor_mean_log_std(&obs).unwrap();
    let mut scratch = Scratch::new(&layout);
    let (mut mean, mut log_std) = (vec![0f32; layout.act_dim], vec![0f32; layout.act_dim]);
    let mut worst = 0f32;
    for i in 0..n {
        net.forward(&obs[i * layout.obs_dim..(i + 1) * layout.obs_dim], &mut scratch, &mut mean, &mut log_std);
        for j in 0..layout.act_dim {
            let k = i * layout.act_dim + j;
            worst = worst.max((mean[j] - mean_tch[k]).abs()).max((log_std[j] - log_std_tch[k]).abs());
        }
    }
    assert!(worst < 1e-5, "pure-Rust and tch actors differ by {worst} for {layout:?}");
}

fn nudge(lac: &mut Lac, rng: &mut SplitMix64) {
    let (od, ad) = (lac.layout().obs_dim, lac.layout().act_dim);
    let batch: Vec<Transition> = (0..32)
        .map(|_| {
            let mut t = Transition::default();
            for k in 0..od {
                t.obs[k] = rng.normal() as f32;
                t.next_obs[k] = rng.normal() as f32;
            }
            for k in 0..ad {
                t.action[k] = (rng.unit_f64() * 2.0 - 1.0) as f32;
            }
            t.cost = rng.unit_f64() as f32;
            t
        })
        .collect();
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
    let mut rng = SplitMix64(11);
    assert_equivalent(&lac, &mut rng);
    nudge(&mut lac, &mut rng);
    assert_equivalent(&lac, &mut rng);
}

#[test]
fn single_action_shape() {
    let cfg = config(Experiment::SingleQ, &[32, 16]);
    let layout = PolicyLayout { obs_dim: 15, act_dim: 1, hidden: vec![32, 16] };
    let mut lac = Lac::new(&cfg, layout, 8).unwrap();
    let mut rng = SplitMix64(12);
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
