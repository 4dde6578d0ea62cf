//! In-process LAC training for hyperparameter studies: the same environments, policy refresh and
//! sample-to-insert ratio as the distributed run, without processes, so two configs can run side by side.
//!
//! `cargo run --release -p bcal-learner --example tune -- CONFIG.toml UPDATES [VALIDATE_EVERY]`
//! Prints one validation line (held-out cost and Table-1 NRMSE) every VALIDATE_EVERY updates.

use bcal_common::battery::BatteryModel;
use bcal_common::config::TrainConfig;
use bcal_common::dataset::{default_cache_dir, load_or_generate};
use bcal_common::mdp::{validate_policy, CalibrationEnv, MdpSpec, SplitMix64};
use bcal_common::policy::{PolicyLayout, PolicyNet, Scratch};
use bcal_common::wire::Transition;
use bcal_learner::Lac;
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let cfg = TrainConfig::from_file(std::path::Path::new(&args[1]))?;
    let updates: u64 = args[2].parse()?;
    let validate_every: u64 = args.get(3).map(|s| s.parse()).transpose()?.unwrap_or(1000);
    let v = cfg.validate()?;
    let model = BatteryModel::default();
    let (ds, _) = load_or_generate(&v.def, &model, &default_cache_dir())?;
    let spec = MdpSpec::new(cfg.experiment, &cfg.env, &ds);
    let layout = PolicyLayout { obs_dim: spec.obs_dim(), act_dim: spec.act_dim(), hidden: cfg.lac.hidden.clone() };
    let mut lac = Lac::new(&v, layout.clone(), cfg.seed)?;
    let train = ds.train_indices();
    let val = ds.spread_test_indices(cfg.learner.validate_trajectories);
    // Diagnostic: the same metric on a spread of TRAINING trajectories (learning vs extrapolation).
    let n_tv = 16.min(train.len());
    let train_val: Vec<usize> = (0..n_tv).map(|k| train[k * train.len() / n_tv]).collect();

    let mut rng = SplitMix64(cfg.seed);
    let n_envs = cfg.actors.envs_per_actor;
    let mut envs: Vec<CalibrationEnv> =
        (0..n_envs).map(|_| CalibrationEnv::new(&spec, &model, &ds, &train, &mut rng)).collect();
    let mut net = PolicyNet::from_flat(layout.clone(), lac.actor_flat_params())?;
    let mut scratch = Scratch::new(&layout);
    let mut buffer: Vec<Transition> = Vec::with_capacity(cfg.replay.capacity.min(2_000_000));
    let mut next_slot = 0usize;
    let (od, ad) = (spec.obs_dim(), spec.act_dim());
    let insert_per_update = (cfg.lac.batch_size as f64 / cfg.replay.samples_per_insert).max(1.0);
    let mut insert_credit = 0.0;
    let mut step_envs = |n: usize,
                         net: &PolicyNet,
                         scratch: &mut Scratch,
                         buffer: &mut Vec<Transition>,
                         rng: &mut SplitMix64,
                         next_slot: &mut usize| {
        for _ in 0..n {
            let e = rng.below(n_envs);
            let mut t = Transition::default();
            envs[e].observe(&spec, &ds, &mut t.obs[..od]);
            net.act_stochastic(&t.obs[..od], scratch, || rng.normal(), &mut t.action[..ad]);
            let action = t.action;
            let s = envs[e].step(&spec, &model, &ds, &train, &action[..ad], &mut t.next_obs[..od], rng);
            t.cost = s.cost as f32;
            if buffer.len() < cfg.replay.capacity {
                buffer.push(t);
            } else {
                buffer[*next_slot] = t;
                *next_slot = (*next_slot + 1) % cfg.replay.capacity;
            }
        }
    };
    step_envs(cfg.replay.learning_starts, &net, &mut scratch, &mut buffer, &mut rng, &mut next_slot);
    let started = Instant::now();
    let mut batch = vec![Transition::default(); cfg.lac.batch_size];
    let validate_on = |net: &PolicyNet, set: &[usize]| {
        let (cost, q, r) = validate_policy(&spec, &model, &ds, set, net);
        (cost, (q, r))
    };
    let validate = |net: &PolicyNet| validate_on(net, &val);
    let (c0, (q0, r0)) = validate(&net);
    println!("update 0 t 0 val_cost {c0:.4} q {q0:.2} r {r0:.2}");
    for u in 1..=updates {
        insert_credit += insert_per_update;
        let n = insert_credit.floor() as usize;
        insert_credit -= n as f64;
        step_envs(n, &net, &mut scratch, &mut buffer, &mut rng, &mut next_slot);
        for b in batch.iter_mut() {
            *b = buffer[rng.below(buffer.len())];
        }
        let m = lac.update(&batch)?;
        if u % cfg.learner.weights_every == 0 {
            net.set_params(&lac.actor_flat_params())?;
        }
        if u % validate_every == 0 {
            net.set_params(&lac.actor_flat_params())?;
            let (c, (q, r)) = validate(&net);
            let (_, (tq, tr)) = validate_on(&net, &train_val);
            println!(
                "update {u} t {:.0} val_cost {c:.4} q {q:.2} r {r:.2} train_q {tq:.2} train_r {tr:.2} | critic {:.3e} l_delta {:.3e} lambda {:.3} beta {:.3e} entropy {:.2} cost {:.4} L {:.3}",
                started.elapsed().as_secs_f64(),
                m.critic_loss,
                m.lyapunov_decrease,
                m.lambda,
                m.beta,
                m.entropy,
                m.mean_cost,
                m.lyapunov_value
            );
        }
    }
    Ok(())
}
