//! The calibrators' cost per step, each beside one battery-model step timed in the same process on the
//! same states: the evaluator's timing code (`bcal_eval::evaluate`: [`time_per_call_us`], [`time_net`],
//! the step cycle over test trajectories) on the evaluator's first 8 held-out test trajectories, one
//! thread (libtorch set to one intra-op thread).
//!
//! Network weights are freshly initialised (a trained policy costs the same: no step depends on the
//! values); the pure-Rust nets carry the same weights as the tch actor they are compared with.

use crate::shape;
use anyhow::Context;
use bcal_calib::Calibrator;
use bcal_common::battery::{BatteryModel, Degradation, Load};
use bcal_common::config::TrainConfig;
use bcal_common::dataset::{Dataset, Experiment, Trajectory};
use bcal_common::math::ModelState;
use bcal_common::mdp::{model_state_at, MdpSpec};
use bcal_common::policy::{PolicyLayout, PolicyNet, Scratch};
use bcal_eval::direct::{self, DirectMap};
use bcal_eval::evaluate::{median_of, spread_by_load, step_cycle, time_net, time_per_call_us, TIMING_REPEATS};
use bcal_eval::ukf::{UkfCalibrator, UkfSettings};
use bcal_eval::{EvalInput, PolicyInput};
use bcal_learner::Lac;
use serde::{Deserialize, Serialize};
use std::hint::black_box;
use std::time::Instant;

/// The default (tuned) network and the paper's.
pub const HIDDEN_DEFAULT: [usize; 2] = [128, 128];
pub const HIDDEN_PAPER: [usize; 3] = [256, 256, 256];
/// Observations per tch forward in the batched rows (an actor's publish batch).
pub const BATCH: usize = 64;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibRow {
    /// Stable key (`ukf`, `rl_rust_b1_256x3`, ...).
    pub key: String,
    /// What the row is, as printed in the table.
    pub label: String,
    /// Cost per step (per sample for the batched rows), us.
    pub us: f64,
    /// `us` / one battery-model step measured in the same process.
    pub model_steps: f64,
    /// Calls timed (steps, or batches for the batched rows).
    pub calls: u64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibReport {
    /// The unit: one `BatteryModel::step` on the timing trajectories' states and loads, us.
    pub model_step_us: f64,
    /// Test trajectories the timing cycles over (experiment multi, held-out loads).
    pub timing_trajectories: u64,
    pub rows: Vec<CalibRow>,
}

/// A tch actor of `hidden` with the LAC learner's initialisation, and the same weights as a pure-Rust net.
fn actor_pair(obs_dim: usize, act_dim: usize, hidden: &[usize]) -> anyhow::Result<(Lac, PolicyNet)> {
    let mut c = TrainConfig { experiment: Experiment::Multi, ..Default::default() };
    c.lac.hidden = hidden.to_vec();
    c.learner.torch_threads = 1;
    let v = c.validate()?;
    let layout = PolicyLayout { obs_dim, act_dim, hidden: hidden.to_vec() };
    let lac = Lac::new(&v, layout.clone(), 1).context("building the tch actor")?;
    let net = PolicyNet::from_flat(layout, lac.actor_flat_params())?;
    Ok((lac, net))
}

/// The measured-only setting's steps, per reading, on the default setting's test cells (3 mV noise): the RL
/// environment's step (what an actor pays per transition), the RL calibrator's step (tracker + 128x128
/// policy), the window fit's and the joint UKF's (default settings; the evaluator times the tuned one).
fn measured_rows(steps: usize, push: &mut dyn FnMut(String, String, f64, usize)) -> anyhow::Result<()> {
    use bcal_calib::env::MeasuredEnv;
    use bcal_calib::joint_ukf::{JointUkf, JointUkfSettings};
    use bcal_calib::{RlCalibrator, WindowFitCalibrator};
    use bcal_common::dataset::Split;
    use bcal_common::measured::env::MeasuredSpec;
    use bcal_common::measured::scenario::episode_set;
    use bcal_common::measured::tracker::OBS_DIM;

    let spec = MeasuredSpec::default();
    let episodes = episode_set(&spec.scenario, Split::Test, 4).context("simulating the measured test cells")?;
    let readings: usize = episodes.iter().map(|e| e.samples.len()).sum();
    anyhow::ensure!(readings > 0, "the measured test cells have no readings to time on");

    let mut env = MeasuredEnv::new(&spec, 1);
    let mut obs = [0f32; OBS_DIM];
    let n = steps.min(20_000);
    let us = time_per_call_us(n, |_| {
        black_box(env.step(&spec, &[0.0, 0.0], &mut obs));
    });
    push("measured_env".into(), "measured-only RL environment step (sensor + tracker + cost)".into(), us, n);

    let layout = PolicyLayout { obs_dim: OBS_DIM, act_dim: 2, hidden: HIDDEN_DEFAULT.to_vec() };
    let net = PolicyNet::from_flat(layout.clone(), vec![0.01; layout.n_params()])?;
    let flat: Vec<(usize, &bcal_common::measured::scenario::Sample)> =
        episodes.iter().flat_map(|e| e.samples.iter().enumerate()).collect();
    let t = &spec.tracker;
    let us = time_readings(&flat, n, &|| Box::new(RlCalibrator::new(t, &net)));
    push(
        "measured_rl".into(),
        "measured-only RL calibrator step, window-fit design (tracker + 128x128 policy)".into(),
        us,
        n,
    );
    // The default design: the joint UKF (default settings) read and corrected by a 24-feature policy.
    let mut cspec = spec.clone();
    cspec.ukf = Some(JointUkfSettings::default());
    let clayout = PolicyLayout { obs_dim: cspec.obs_dim(), act_dim: cspec.act_dim(), hidden: HIDDEN_DEFAULT.to_vec() };
    let cnet = PolicyNet::from_flat(clayout.clone(), vec![0.01; clayout.n_params()])?;
    let us = time_readings(&flat, n, &|| Box::new(bcal_calib::CorrectionCalibrator::new(&cspec, &cnet)));
    push(
        "measured_rl_correction".into(),
        "measured-only RL calibrator step, correction design (joint UKF + 24 features + 128x128 policy)".into(),
        us,
        n,
    );
    let us = time_readings(&flat, n, &|| Box::new(WindowFitCalibrator::new(t)));
    push("measured_window_fit".into(), "measured-only window fit step (Gauss-Newton, 2 params)".into(), us, n);
    let us = time_readings(&flat, n, &|| Box::new(JointUkf::new(JointUkfSettings::default(), t)));
    push("measured_joint_ukf".into(), "joint UKF step (9 states, 19 sigma points, default settings)".into(), us, n);
    Ok(())
}

/// us per reading of calibrators built by `make`, one fresh calibrator per cell (readings with index 0).
fn time_readings<'a>(
    flat: &[(usize, &bcal_common::measured::scenario::Sample)],
    n: usize,
    make: &dyn Fn() -> Box<dyn Calibrator + 'a>,
) -> f64 {
    let mut cal = make();
    time_per_call_us(n, |i| {
        let (k, s) = flat[i % flat.len()];
        if k == 0 {
            cal = make();
        }
        cal.step(s);
        black_box(cal.estimate());
    })
}

/// Times every calibrator step on test trajectories `ds`; `steps` per row (the model unit gets 20 times as
/// many, as in the evaluator).
pub fn measure(
    ds: &Dataset,
    spec: &MdpSpec,
    model: &BatteryModel,
    steps: usize,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<CalibReport> {
    let all: Vec<usize> = (0..ds.trajectories.len()).collect();
    let test = spread_by_load(ds, &all, None);
    let trajs: Vec<&Trajectory> = test.iter().take(8).map(|&i| &ds.trajectories[i]).collect();
    anyhow::ensure!(!trajs.is_empty(), "the dataset has no test trajectories to time on");
    let dt_s = ds.def.dt_s;
    // Only the step timing reads this input: the test trajectories stand in for every split.
    let input = EvalInput {
        test: ds,
        validation: ds,
        train: None,
        spec,
        model,
        policy: PolicyInput::Missing { reason: "bench: networks are built in place".into() },
        training_curve: None,
    };
    let (od, ad) = (spec.obs_dim(), spec.act_dim());
    let threads = tch::get_num_threads();
    tch::set_num_threads(1);

    // The unit: one battery-model step, exactly as the evaluator times it.
    let states: Vec<(ModelState, Degradation, f64)> = trajs
        .iter()
        .flat_map(|t| (0..t.len() - 1).map(move |k| (model_state_at(model, t, k), t.degradation, t.load_w)))
        .collect();
    let model_step_us = time_per_call_us(steps * 20, |i| {
        let (x, d, load) = &states[i % states.len()];
        black_box(model.step(black_box(x), Load::PowerW(*load), dt_s, d));
    });
    progress(&format!("calib: one battery-model step {model_step_us:.3} us (the unit)"));

    let mut rows = Vec::new();
    let mut push = |rows: &mut Vec<CalibRow>, key: String, label: String, us: f64, calls: usize| {
        progress(&format!("calib: {label}: {us:.3} us ({:.1} model steps)", us / model_step_us));
        rows.push(CalibRow { key, label, us, model_steps: us / model_step_us, calls: calls as u64 });
    };

    // UKF: whole trajectories (the filter restarts with each), the evaluator's loop; default settings.
    let cal = UkfCalibrator::new(UkfSettings::default(), &spec.actions, &spec.scales, dt_s);
    let per_repeat = (steps / TIMING_REPEATS).max(1);
    let mut ukf_steps = 0;
    let reps = (0..TIMING_REPEATS)
        .map(|_| {
            let (mut n, t0) = (0usize, Instant::now());
            'outer: loop {
                for traj in &trajs {
                    cal.run(model, traj, |_, d| {
                        black_box(d);
                    });
                    n += traj.len() - 1;
                    if n >= per_repeat {
                        break 'outer;
                    }
                }
            }
            ukf_steps += n;
            t0.elapsed().as_secs_f64() * 1e6 / n as f64
        })
        .collect();
    push(
        &mut rows,
        "ukf".into(),
        "UKF step (2 params, 5 sigma points, default settings)".into(),
        median_of(reps),
        ukf_steps,
    );

    measured_rows(steps, &mut |key, label, us, calls| push(&mut rows, key, label, us, calls))?;

    // RL policy: pure Rust batch 1 (the actors' and the evaluator's path) and the tch actor.
    let at = step_cycle(&trajs);
    for hidden in [&HIDDEN_DEFAULT[..], &HIDDEN_PAPER[..]] {
        let s = shape(hidden);
        let (lac, net) = actor_pair(od, ad, hidden)?;
        let us = time_net(&input, &net, &trajs, steps, true);
        push(&mut rows, format!("rl_rust_b1_{s}"), format!("RL policy {s}, pure Rust, batch 1"), us, steps);

        if hidden == HIDDEN_PAPER {
            // 64 sequential pure-Rust forwards (an actor steps its envs one forward each), per sample.
            let mut scratch = Scratch::new(net.layout());
            let mut obs = vec![0f32; od];
            let mut a = [0f32; 2];
            let n = (steps / BATCH).max(20);
            let us = time_per_call_us(n, |i| {
                for j in 0..BATCH {
                    let (traj, t) = at(i * BATCH + j);
                    direct::observation(spec, traj, t, &mut obs);
                    net.act_deterministic(&obs, &mut scratch, &mut a[..ad]);
                    black_box(spec.actions.to_degradation(&a[..ad]));
                }
            }) / BATCH as f64;
            push(
                &mut rows,
                format!("rl_rust_seq64_{s}"),
                format!("RL policy {s}, pure Rust, 64 sequential, per sample"),
                us,
                n,
            );

            // tch actor, batch of one.
            let mut failed = None;
            let n = steps.min(5_000);
            let us = time_per_call_us(n, |i| {
                let (traj, t) = at(i);
                direct::observation(spec, traj, t, &mut obs);
                match lac.actor_mean_log_std(&obs) {
                    Ok((mean, _)) => {
                        let act: Vec<f32> = mean.iter().map(|m| m.tanh()).collect();
                        black_box(spec.actions.to_degradation(&act));
                    }
                    Err(e) => failed = Some(e),
                }
            });
            if let Some(e) = failed {
                return Err(e).context("tch actor forward");
            }
            push(&mut rows, format!("rl_tch_b1_{s}"), format!("RL policy {s}, tch, batch 1"), us, n);
        }

        // tch actor, 64 observations per forward, per sample.
        let mut obs = vec![0f32; BATCH * od];
        let mut failed = None;
        let n = (steps / 16).max(50);
        let us = time_per_call_us(n, |i| {
            for j in 0..BATCH {
                let (traj, t) = at(i * BATCH + j);
                direct::observation(spec, traj, t, &mut obs[j * od..(j + 1) * od]);
            }
            match lac.actor_mean_log_std(&obs) {
                Ok((mean, _)) => {
                    for row in mean.chunks(ad) {
                        let act: [f32; 2] = std::array::from_fn(|k| row.get(k).map_or(0.0, |m| m.tanh()));
                        black_box(spec.actions.to_degradation(&act[..ad]));
                    }
                }
                Err(e) => failed = Some(e),
            }
        }) / BATCH as f64;
        if let Some(e) = failed {
            return Err(e).context("tch actor forward");
        }
        push(&mut rows, format!("rl_tch_b64_{s}"), format!("RL policy {s}, tch, batch 64, per sample"), us, n);
    }

    // Direct mapping: the paper's shape with a linear head, tch batch 1 and exported to pure Rust.
    let dm = DirectMap::new(od, ad, &HIDDEN_PAPER, 1);
    let mut obs = vec![0f32; od];
    let mut failed = None;
    let n = steps.min(5_000);
    let us = time_per_call_us(n, |i| {
        let (traj, t) = at(i);
        direct::observation(spec, traj, t, &mut obs);
        match dm.predict(&obs) {
            Ok(a) => {
                black_box(spec.actions.to_degradation(&a[..ad]));
            }
            Err(e) => failed = Some(e),
        }
    });
    if let Some(e) = failed {
        return Err(e).context("direct mapping forward");
    }
    push(&mut rows, "direct_tch_b1_256x3".into(), "direct mapping 256x3, tch, batch 1".into(), us, n);
    let pure = dm.to_policy_net()?;
    let us = time_net(&input, &pure, &trajs, steps, false);
    push(&mut rows, "direct_rust_b1_256x3".into(), "direct mapping 256x3, pure Rust, batch 1".into(), us, steps);

    tch::set_num_threads(threads);
    Ok(CalibReport { model_step_us, timing_trajectories: trajs.len() as u64, rows })
}
