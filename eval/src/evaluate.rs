//! The evaluator's loop, top to bottom: pick the held-out test trajectories, run every method along each of
//! them (RL-LAC, the UKF tuned on the validation split, the direct mapping trained on the training split
//! with early stopping on validation), time one step of each on one thread beside one battery-model step,
//! score them with [`crate::metrics`], and assemble the [`Report`]; then [`write_outputs`] writes
//! report.json, report.md and the figures into the run folder.
//!
//! Every method sees the same test trajectories and the same information per step (the measured x_t, the
//! next measured x_{t+1} and the load); only the direct mapping was trained with true parameters, and only
//! on training trajectories. Every choice any method makes is made on the validation split; the test split
//! is only scored. Progress goes to a caller-supplied callback: this module never prints.

use crate::direct::{self, DirectMap, DirectMapConfig, DirectMapError};
use crate::metrics::{self, accuracy, params_of, EodMetrics, Param, ParamValues, TrajEstimates};
use crate::plots::{self, method_color, MethodSeries, TrainingCurve};
use crate::report::{
    paper_json, render_markdown, DirectMapInfo, EodReferences, MethodReport, Methods, Report, RlInfo, UkfInfo,
};
use crate::ukf::{self, UkfCalibrator, UkfCounters, UkfGrid, PRIOR_MEAN};
use bcal_common::battery::{BatteryModel, Degradation, Load};
use bcal_common::dataset::{Dataset, Trajectory};
use bcal_common::math::ModelState;
use bcal_common::mdp::{model_state_at, rollout_calibrator, MdpSpec};
use bcal_common::policy::{PolicyFile, PolicyNet, Scratch};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What x_hat is during evaluation, stated in the report.
pub const X_HAT_NOTE: &str = "the measured state x_t, re-synced at every step (common::mdp::rollout_calibrator): a \
deployed calibrator observes the real battery at every step, training windows start from measured states, and an \
open-loop x_hat drifting for thousands of steps would mix state-estimation error into the parameter error. The UKF \
and the direct mapping get the same x_t and x_{t+1}.";

/// Which methods to run and how much work each gets.
#[derive(Clone, Debug, PartialEq)]
pub struct EvalOptions {
    pub quick: bool,
    pub rl: bool,
    pub ukf: bool,
    pub direct_mapping: bool,
    /// Test trajectories per test load (`None` = all), spread evenly over the parameter grid.
    pub test_per_load: Option<usize>,
    pub ukf_grid: UkfGrid,
    /// Validation trajectories the UKF is tuned on, spread over the validation split (0 = all).
    pub ukf_tune_trajectories: usize,
    pub direct: DirectMapConfig,
    /// Training trajectories on which the direct mapping's training error is measured.
    pub direct_train_eval_trajectories: usize,
    /// Steps timed per method (the battery model gets 20 times as many).
    pub timing_steps: usize,
}

impl EvalOptions {
    /// The full evaluation: every test trajectory, the full UKF grid, the full direct-mapping training.
    pub fn full() -> Self {
        Self {
            quick: false,
            rl: true,
            ukf: true,
            direct_mapping: true,
            test_per_load: None,
            ukf_grid: UkfGrid::default(),
            ukf_tune_trajectories: 16,
            direct: DirectMapConfig::default(),
            direct_train_eval_trajectories: 140,
            timing_steps: 20_000,
        }
    }

    /// `--quick`: 12 test trajectories per load, a small UKF grid and a few seconds of direct-mapping training.
    pub fn quick() -> Self {
        Self {
            quick: true,
            test_per_load: Some(12),
            ukf_grid: UkfGrid::quick(),
            ukf_tune_trajectories: 6,
            direct: DirectMapConfig::quick(),
            direct_train_eval_trajectories: 28,
            timing_steps: 3_000,
            ..Self::full()
        }
    }
}

/// The trained policy, or why there is none.
pub enum PolicyInput<'a> {
    /// `choice` says which of the run's policies this is and why (e.g. "best by validation tracking error").
    Loaded {
        file: &'a PolicyFile,
        path: String,
        choice: String,
    },
    Missing {
        reason: String,
    },
}

/// Everything the evaluation reads.
pub struct EvalInput<'a> {
    /// The test split: only ever scored.
    pub test: &'a Dataset,
    /// The validation split: UKF tuning, the direct mapping's early stopping, the policy's validation score.
    pub validation: &'a Dataset,
    /// The training split: the direct mapping's supervised pairs (None when it is not evaluated).
    pub train: Option<&'a Dataset>,
    /// The MDP (observation scales, action map): the policy's own when there is one.
    pub spec: &'a MdpSpec,
    pub model: &'a BatteryModel,
    pub policy: PolicyInput<'a>,
    pub training_curve: Option<TrainingCurve>,
}

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(
        "the policy was trained on experiment {policy}, but the evaluation is of {data}; pass --experiment {policy}"
    )]
    ExperimentMismatch { policy: String, data: String },
    #[error("the policy's network ({got}) does not fit the MDP ({want})")]
    PolicyShape { got: String, want: String },
    #[error("no test trajectories to evaluate (the dataset's test split is empty)")]
    NoTestTrajectories,
    #[error("the direct mapping needs the training split; pass it or disable the direct mapping")]
    NoTrainingSplit,
    #[error("no method to evaluate: enable at least one of RL, UKF, direct mapping")]
    NoMethods,
    #[error(transparent)]
    DirectMap(#[from] DirectMapError),
    #[error("policy: {0}")]
    Policy(#[from] bcal_common::policy::PolicyError),
    #[error("cannot write {path}: {source}; check that the run folder is writable")]
    Write { path: PathBuf, source: std::io::Error },
}

/// A finished evaluation: the report plus the per-step estimates the figures need.
pub struct Evaluation {
    pub report: Report,
    /// (method key, estimates on the test trajectories), in report order.
    pub estimates: Vec<(&'static str, Vec<TrajEstimates>)>,
    pub training_curve: Option<TrainingCurve>,
}

/// Indices of `candidates` (dataset indices), at most `per_load` per load, evenly spread over each load's
/// trajectories (which are ordered by parameter).
pub fn spread_by_load(ds: &Dataset, candidates: &[usize], per_load: Option<usize>) -> Vec<usize> {
    let mut loads: Vec<f64> = candidates.iter().map(|&i| ds.trajectories[i].load_w).collect();
    loads.sort_by(f64::total_cmp);
    loads.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    let mut out = Vec::new();
    for l in loads {
        let group: Vec<usize> =
            candidates.iter().copied().filter(|&i| (ds.trajectories[i].load_w - l).abs() < 1e-9).collect();
        match per_load {
            Some(k) if k < group.len() => {
                let step = group.len() as f64 / k as f64;
                out.extend((0..k).map(|j| group[((j as f64 + 0.5) * step) as usize]));
            }
            _ => out.extend(group),
        }
    }
    out
}

/// Timing repeats; the median repeat is reported (the paper averaged five runs of 2000 transitions; the
/// median is robust to a repeat preempted by another process on a shared machine).
pub const TIMING_REPEATS: usize = 5;

pub fn median_of(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Wall time per call, us: [`TIMING_REPEATS`] repeats of `n / TIMING_REPEATS` calls after `n / 10` warm-up
/// calls, median repeat.
pub fn time_per_call_us(n: usize, mut f: impl FnMut(usize)) -> f64 {
    let per = (n / TIMING_REPEATS).max(1);
    for i in 0..n / 10 {
        f(i);
    }
    let mut i = 0;
    let reps = (0..TIMING_REPEATS)
        .map(|_| {
            let t0 = Instant::now();
            for _ in 0..per {
                f(i);
                i += 1;
            }
            t0.elapsed().as_secs_f64() * 1e6 / per as f64
        })
        .collect();
    median_of(reps)
}

/// Steps (trajectory, t) cycling over the test trajectories, for timing loops.
pub fn step_cycle<'a>(trajs: &'a [&'a Trajectory]) -> impl Fn(usize) -> (&'a Trajectory, usize) + 'a {
    let total: usize = trajs.iter().map(|t| t.len() - 1).sum();
    move |i| {
        let mut k = i % total;
        for t in trajs {
            if k < t.len() - 1 {
                return (t, k);
            }
            k -= t.len() - 1;
        }
        unreachable!("k < total")
    }
}

/// Runs a pure-Rust network as a calibrator on trajectories of `ds` (all cores).
fn run_net(input: &EvalInput, ds: &Dataset, net: &PolicyNet, idx: &[usize]) -> Vec<TrajEstimates> {
    idx.par_iter()
        .map_init(
            || Scratch::new(net.layout()),
            |scratch, &i| {
                let traj = &ds.trajectories[i];
                let mut estimates = Vec::with_capacity(traj.len());
                rollout_calibrator(
                    input.spec,
                    input.model,
                    traj,
                    |obs, a| net.act_deterministic(obs, scratch, a),
                    |_, d, _| estimates.push(*d),
                );
                TrajEstimates { index: i, load_w: traj.load_w, truth: traj.degradation, estimates }
            },
        )
        .collect()
}

/// Per-step cost of a pure-Rust network as a calibrator (observation, forward pass, action map), us.
pub fn time_net(input: &EvalInput, net: &PolicyNet, trajs: &[&Trajectory], n: usize, tanh: bool) -> f64 {
    let mut scratch = Scratch::new(net.layout());
    let (od, ad) = (input.spec.obs_dim(), input.spec.act_dim());
    let mut obs = vec![0f32; od];
    let (mut a, mut log_std) = ([0f32; 2], [0f32; 2]);
    let at = step_cycle(trajs);
    time_per_call_us(n, |i| {
        let (traj, t) = at(i);
        direct::observation(input.spec, traj, t, &mut obs);
        if tanh {
            net.act_deterministic(&obs, &mut scratch, &mut a[..ad]);
        } else {
            net.forward(&obs, &mut scratch, &mut a[..ad], &mut log_std[..ad]);
        }
        black_box(input.spec.actions.to_degradation(&a[..ad]));
    })
}

fn eod_of(input: &EvalInput, est: &[TrajEstimates], dt_s: f64) -> EodMetrics {
    let trajs: Vec<&Trajectory> = est.iter().map(|e| &input.test.trajectories[e.index]).collect();
    metrics::eod_metrics(input.model, &trajs, dt_s, |k, step| est[k].estimates[step])
}

/// Runs the whole evaluation.
pub fn evaluate(
    input: &EvalInput,
    opts: &EvalOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<Evaluation, EvalError> {
    let started = Instant::now();
    let ds = input.test;
    let val = input.validation;
    let spec = input.spec;
    let model = input.model;
    let dt_s = ds.def.dt_s;
    let calibrated = spec.actions.calibrated;
    let params = params_of(calibrated);
    if !(opts.rl || opts.ukf || opts.direct_mapping) {
        return Err(EvalError::NoMethods);
    }
    let all_test: Vec<usize> = (0..ds.trajectories.len()).collect();
    let test = spread_by_load(ds, &all_test, opts.test_per_load);
    if test.is_empty() {
        return Err(EvalError::NoTestTrajectories);
    }
    let test_trajs: Vec<&Trajectory> = test.iter().map(|&i| &ds.trajectories[i]).collect();
    let test_steps: usize = test_trajs.iter().map(|t| t.len() - 1).sum();
    let round = |v: Vec<f64>| v.iter().map(|l| (l * 10.0).round() / 10.0).collect::<Vec<_>>();
    progress(&format!(
        "{}: {} test trajectories ({test_steps} steps) at loads {:?} W; validation: {} trajectories at {:?} W",
        ds.def.experiment,
        test.len(),
        round(ds.loads_w()),
        val.trajectories.len(),
        round(val.loads_w()),
    ));
    // Timing subset: the first few test trajectories (timing cycles over them).
    let timing_trajs: Vec<&Trajectory> = test_trajs.iter().take(8).copied().collect();

    // The unit of cost: one battery-model step, in this process, on one thread.
    let states: Vec<(ModelState, Degradation, f64)> = timing_trajs
        .iter()
        .flat_map(|t| (0..t.len() - 1).map(move |k| (model_state_at(model, t, k), t.degradation, t.load_w)))
        .collect();
    let model_step_us = time_per_call_us(opts.timing_steps * 20, |i| {
        let (x, d, load) = &states[i % states.len()];
        black_box(model.step(black_box(x), Load::PowerW(*load), dt_s, d));
    });
    progress(&format!("one battery-model step: {model_step_us:.3} us"));

    let mut methods = Methods::default();
    let mut not_evaluated = BTreeMap::new();
    let mut estimates: Vec<(&'static str, Vec<TrajEstimates>)> = Vec::new();
    let finish = |acc_est: &[TrajEstimates], step_us: f64, timing_steps: usize| MethodReport {
        accuracy: accuracy(calibrated, acc_est, dt_s),
        eod: eod_of(input, acc_est, dt_s),
        step_us,
        step_in_model_steps: step_us / model_step_us,
        timing_steps,
        ukf: None,
        direct_mapping: None,
        rl: None,
    };

    // 1. RL-LAC: the trained policy, deterministic action tanh(mean), x_hat = measured state.
    if opts.rl {
        match &input.policy {
            PolicyInput::Missing { reason } => {
                progress(&format!("RL-LAC not evaluated: {reason}"));
                not_evaluated.insert("rl_lac".to_string(), reason.clone());
            }
            PolicyInput::Loaded { file, path, choice } => {
                if file.experiment != ds.def.experiment {
                    return Err(EvalError::ExperimentMismatch {
                        policy: file.experiment.to_string(),
                        data: ds.def.experiment.to_string(),
                    });
                }
                if file.layout.obs_dim != spec.obs_dim() || file.layout.act_dim != spec.act_dim() {
                    return Err(EvalError::PolicyShape {
                        got: format!("{} -> {}", file.layout.obs_dim, file.layout.act_dim),
                        want: format!("{} -> {}", spec.obs_dim(), spec.act_dim()),
                    });
                }
                let net = file.net()?;
                progress(&format!(
                    "RL-LAC: policy {path} ({choice}, update {}), {} test trajectories",
                    file.update_step,
                    test.len()
                ));
                let est = run_net(input, ds, &net, &test);
                // The same policy on the whole validation split: how far test lands from what was selected on.
                let all_val: Vec<usize> = (0..val.trajectories.len()).collect();
                let validation_nrmse_pct = accuracy(calibrated, &run_net(input, val, &net, &all_val), dt_s).nrmse_pct;
                let step_us = time_net(input, &net, &timing_trajs, opts.timing_steps, true);
                let mut m = finish(&est, step_us, opts.timing_steps);
                m.rl = Some(RlInfo {
                    policy_file: path.clone(),
                    choice: choice.clone(),
                    update_step: file.update_step,
                    hidden: file.layout.hidden.clone(),
                    action: "deterministic tanh(mean), pure-Rust PolicyNet".into(),
                    validation_nrmse_pct,
                });
                progress(&format!("RL-LAC: NRMSE {}", fmt_pv(&m.accuracy.nrmse_pct, params)));
                methods.rl_lac = Some(m);
                estimates.push(("rl_lac", est));
            }
        }
    }

    // 2. UKF: tuned on validation trajectories only, then run on the test trajectories.
    if opts.ukf {
        let all_val: Vec<usize> = (0..val.trajectories.len()).collect();
        let per_load =
            (opts.ukf_tune_trajectories > 0).then(|| opts.ukf_tune_trajectories.div_ceil(val.loads_w().len().max(1)));
        let tune_trajs: Vec<&Trajectory> =
            spread_by_load(val, &all_val, per_load).into_iter().map(|i| &val.trajectories[i]).collect();
        let cands = opts.ukf_grid.candidates(spec.act_dim()).len();
        progress(&format!("UKF: tuning {cands} settings on {} validation trajectories", tune_trajs.len()));
        let tuned = ukf::tune(&opts.ukf_grid, &tune_trajs, model, &spec.actions, &spec.scales, dt_s);
        let s = tuned.best;
        progress(&format!(
            "UKF: chose q_std {:e}, r_std {:e}, p0_std {}, alpha {}, beta {}, kappa {} (validation NRMSE {:.3} %)",
            s.q_std, s.r_std, s.p0_std, s.alpha, s.beta, s.kappa, tuned.best_validation_nrmse_pct
        ));
        let cal = UkfCalibrator::new(s, &spec.actions, &spec.scales, dt_s);
        let runs: Vec<(TrajEstimates, UkfCounters)> = test
            .par_iter()
            .map(|&i| {
                let traj = &ds.trajectories[i];
                let mut est = Vec::with_capacity(traj.len());
                let c = cal.run(model, traj, |_, d| est.push(*d));
                (TrajEstimates { index: i, load_w: traj.load_w, truth: traj.degradation, estimates: est }, c)
            })
            .collect();
        let mut counters = UkfCounters::default();
        let mut est = Vec::with_capacity(runs.len());
        for (e, c) in runs {
            counters.add(&c);
            est.push(e);
        }
        // Timing: whole trajectories (the filter restarts with each), one thread, until enough steps; median
        // of the repeats.
        let per_repeat = (opts.timing_steps / TIMING_REPEATS).max(1);
        let mut total_steps = 0;
        let reps = (0..TIMING_REPEATS)
            .map(|_| {
                let (mut steps, t0) = (0usize, Instant::now());
                'outer: loop {
                    for traj in &timing_trajs {
                        cal.run(model, traj, |_, d| {
                            black_box(d);
                        });
                        steps += traj.len() - 1;
                        if steps >= per_repeat {
                            break 'outer;
                        }
                    }
                }
                total_steps += steps;
                t0.elapsed().as_secs_f64() * 1e6 / steps as f64
            })
            .collect();
        let step_us = median_of(reps);
        let mut m = finish(&est, step_us, total_steps);
        m.ukf = Some(UkfInfo { settings: s, tuning: tuned, counters, prior_mean: PRIOR_MEAN });
        progress(&format!("UKF: NRMSE {}, {step_us:.2} us per step", fmt_pv(&m.accuracy.nrmse_pct, params)));
        methods.ukf = Some(m);
        estimates.push(("ukf", est));
    }

    // 3. Direct mapping: supervised on training pairs, early-stopped on validation pairs, then applied to the
    // test trajectories.
    if opts.direct_mapping {
        let train_ds = input.train.ok_or(EvalError::NoTrainingSplit)?;
        let train_trajs: Vec<&Trajectory> = train_ds.trajectories.iter().collect();
        let val_trajs: Vec<&Trajectory> = val.trajectories.iter().collect();
        let pairs = direct::sample_pairs(spec, &train_trajs, opts.direct.max_pairs, opts.direct.seed);
        let val_pairs = direct::sample_pairs(spec, &val_trajs, opts.direct.max_validation_pairs, opts.direct.seed + 1);
        progress(&format!(
            "direct mapping: training on {} pairs, early stopping on {} validation pairs (budget {} s)",
            pairs.len(),
            val_pairs.len(),
            opts.direct.time_budget_s
        ));
        let (net, log) = DirectMap::train(&pairs, &val_pairs, &opts.direct)?;
        drop(pairs);
        progress(&format!(
            "direct mapping: {} updates in {:.1} s ({}), best validation MSE {:.2e} at update {}",
            log.updates,
            log.seconds,
            log.stopped_by.replace('_', " "),
            log.best_validation_loss,
            log.best_update
        ));
        let predict = |ds: &Dataset, idx: &[usize]| -> Result<Vec<TrajEstimates>, EvalError> {
            idx.iter()
                .map(|&i| {
                    let traj = &ds.trajectories[i];
                    let ad = spec.act_dim();
                    let pred = direct::predict_trajectory(&net, spec, traj)?;
                    let estimates = pred.chunks(ad).map(|a| spec.actions.to_degradation(a)).collect();
                    Ok(TrajEstimates { index: i, load_w: traj.load_w, truth: traj.degradation, estimates })
                })
                .collect()
        };
        let est = predict(ds, &test)?;
        let all_train: Vec<usize> = (0..train_ds.trajectories.len()).collect();
        let train_eval = spread_by_load(
            train_ds,
            &all_train,
            Some(opts.direct_train_eval_trajectories.div_ceil(train_ds.loads_w().len().max(1))),
        );
        let train_nrmse = accuracy(calibrated, &predict(train_ds, &train_eval)?, dt_s).nrmse_pct;
        // Timing in tch: batch of one, one intra-op thread.
        let threads = tch::get_num_threads();
        tch::set_num_threads(1);
        let n_tch = opts.timing_steps.min(5_000);
        let (od, ad) = (spec.obs_dim(), spec.act_dim());
        let mut obs = vec![0f32; od];
        let at = step_cycle(&timing_trajs);
        let mut failed = None;
        let step_us = time_per_call_us(n_tch, |i| {
            let (traj, t) = at(i);
            direct::observation(spec, traj, t, &mut obs);
            match net.predict(&obs) {
                Ok(a) => {
                    black_box(spec.actions.to_degradation(&a[..ad]));
                }
                Err(e) => failed = Some(e),
            }
        });
        tch::set_num_threads(threads);
        if let Some(e) = failed {
            return Err(e.into());
        }
        let pure = net.to_policy_net()?;
        let step_us_pure_rust = time_net(input, &pure, &timing_trajs, opts.timing_steps, false);
        let mut m = finish(&est, step_us, n_tch);
        m.direct_mapping = Some(DirectMapInfo {
            config: opts.direct.clone(),
            training: log,
            train_nrmse_pct: train_nrmse,
            step_us_pure_rust,
        });
        progress(&format!(
            "direct mapping: NRMSE {} (train {}), {step_us:.2} us per step in tch, {step_us_pure_rust:.2} us in pure Rust",
            fmt_pv(&m.accuracy.nrmse_pct, params),
            fmt_pv(&train_nrmse, params)
        ));
        methods.direct_mapping = Some(m);
        estimates.push(("direct_mapping", est));
    } else {
        not_evaluated.insert("direct_mapping".into(), "disabled by the command line".into());
    }
    if !opts.ukf {
        not_evaluated.insert("ukf".into(), "disabled by the command line".into());
    }
    if !opts.rl {
        not_evaluated.insert("rl_lac".into(), "disabled by the command line".into());
    }

    // EOD references: the true parameters (floor) and the uncalibrated new-cell model.
    let uncalibrated = Degradation::default();
    let eod_references = EodReferences {
        true_parameters: metrics::eod_metrics(model, &test_trajs, dt_s, |k, _| test_trajs[k].degradation),
        uncalibrated: metrics::eod_metrics(model, &test_trajs, dt_s, |_, _| uncalibrated),
        uncalibrated_parameters: uncalibrated,
    };

    let report = Report {
        experiment: ds.def.experiment.to_string(),
        calibrated: params.iter().map(|p| p.key().to_string()).collect(),
        quick: opts.quick,
        test_trajectories: test.len(),
        test_steps,
        test_loads_w: ds.loads_w(),
        validation_trajectories: val.trajectories.len(),
        validation_loads_w: val.loads_w(),
        test_eod_s: [
            test_trajs.iter().map(|t| t.eod_s(dt_s)).fold(f64::INFINITY, f64::min),
            test_trajs.iter().map(|t| t.eod_s(dt_s)).fold(0.0, f64::max),
        ],
        train_trajectories: input.train.map_or(0, |t| t.trajectories.len()),
        x_hat: X_HAT_NOTE.into(),
        methods,
        not_evaluated,
        model_step_us,
        eod_references,
        paper: paper_json(calibrated),
        plots: Vec::new(),
        notes: Vec::new(),
        seconds: started.elapsed().as_secs_f64(),
    };
    Ok(Evaluation { report, estimates, training_curve: input.training_curve.clone() })
}

fn fmt_pv(v: &ParamValues, params: &[Param]) -> String {
    params.iter().map(|p| format!("{} {:.3} %", p.key(), v.get(*p).unwrap_or(f64::NAN))).collect::<Vec<_>>().join(", ")
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), EvalError> {
    bcal_common::fsutil::write_atomic(path, bytes)
        .map_err(|source| EvalError::Write { path: path.to_path_buf(), source })
}

/// Writes the figures, report.json and report.md into `dir`; `text = None` detects the font. Returns the
/// paths written.
pub fn write_outputs(eval: &mut Evaluation, dir: &Path, text: Option<bool>) -> Result<Vec<PathBuf>, EvalError> {
    std::fs::create_dir_all(dir).map_err(|source| EvalError::Write { path: dir.to_path_buf(), source })?;
    let names: BTreeMap<&str, &str> = crate::report::METHODS.iter().copied().collect();
    let series: Vec<MethodSeries> = eval
        .estimates
        .iter()
        .map(|(k, est)| MethodSeries { name: names[k], color: method_color(k), trajs: est })
        .collect();
    let calibrated = match eval.report.calibrated_params().as_slice() {
        [Param::QMobile] => bcal_common::mdp::Calibrated::QMobile,
        [Param::ROhm] => bcal_common::mdp::Calibrated::ROhm,
        _ => bcal_common::mdp::Calibrated::Both,
    };
    let outcome = plots::write_all(dir, calibrated, &series, eval.training_curve.as_ref(), text);
    let r = &mut eval.report;
    r.plots = outcome.files.clone();
    if !outcome.text {
        r.notes.push(
            "no sans-serif font was found, so the plots have no captions, labels or legends; install \
             fonts-dejavu-core (Debian) and run the evaluation again"
                .into(),
        );
    }
    for f in &outcome.failures {
        r.notes.push(format!("plot failed: {f}"));
    }
    match &eval.training_curve {
        None => r.notes.push("no metrics.jsonl in the run folder: no training curve".into()),
        Some(tc) if tc.skipped_lines > 0 => {
            r.notes.push(format!("metrics.jsonl: {} malformed lines skipped", tc.skipped_lines))
        }
        _ => {}
    }
    let mut written: Vec<PathBuf> = outcome.files.iter().map(|f| dir.join(f)).collect();
    let json = serde_json::to_string_pretty(&eval.report).expect("reports serialise");
    let p = dir.join("report.json");
    write_atomic(&p, json.as_bytes())?;
    written.push(p);
    let p = dir.join("report.md");
    write_atomic(&p, render_markdown(&eval.report).as_bytes())?;
    written.push(p);
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::config::EnvConfig;
    use bcal_common::dataset::{generate, Experiment, ExperimentDef, Grid, Split, ValidationDef};
    use bcal_common::policy::PolicyLayout;

    /// A small version of `experiment`: its training, validation and test splits and the MDP.
    fn small(experiment: Experiment) -> ([Dataset; 3], MdpSpec) {
        let paper = experiment.definition();
        let shrink = |g: Grid, n: usize| if g.n > 1 { Grid { n, ..g } } else { g };
        let def = ExperimentDef {
            q_mobile_c: shrink(paper.q_mobile_c, 3),
            r_o_ohm: shrink(paper.r_o_ohm, 2),
            validation: ValidationDef {
                q_mobile_c: shrink(paper.validation.q_mobile_c, 2),
                r_o_ohm: shrink(paper.validation.r_o_ohm, 2),
                ..paper.validation.clone()
            },
            ..paper
        };
        let model = BatteryModel::default();
        let [train, val, test] = Split::ALL.map(|s| generate(&def, &model, s).unwrap());
        let spec = MdpSpec::new(experiment, &EnvConfig::default(), &train);
        ([train, val, test], spec)
    }

    fn small_opts() -> EvalOptions {
        EvalOptions {
            ukf_grid: UkfGrid {
                q_std: vec![0.0, 1e-4],
                r_std: vec![1e-5],
                p0_std: vec![0.5],
                sigma: vec![(0.5, 2.0, 0.0)],
            },
            ukf_tune_trajectories: 4,
            direct: DirectMapConfig {
                hidden: vec![32, 32],
                max_pairs: 4_000,
                max_validation_pairs: 1_000,
                max_updates: 150,
                validate_every: 50,
                time_budget_s: 20.0,
                ..DirectMapConfig::default()
            },
            direct_train_eval_trajectories: 6,
            timing_steps: 400,
            test_per_load: Some(4),
            ..EvalOptions::quick()
        }
    }

    /// The report files are written and parse back, with the RL path run on a tiny zero-weight policy file.
    #[test]
    fn report_files_are_written_and_parseable_with_a_policy() {
        let dir = tempfile::tempdir().unwrap();
        let ([train, val, test], spec) = small(Experiment::Multi);
        let layout = PolicyLayout { obs_dim: spec.obs_dim(), act_dim: spec.act_dim(), hidden: vec![8] };
        let pf = PolicyFile {
            params: vec![0.0; layout.n_params()],
            layout,
            task: bcal_common::task::Task::Paper(spec.clone()),
            experiment: Experiment::Multi,
            update_step: 7,
        };
        let path = dir.path().join("policy.bcalpol");
        pf.save(&path).unwrap();
        let pf = PolicyFile::load(&path).unwrap();
        let curve = TrainingCurve::parse(
            "{\"kind\":\"train\",\"update\":10,\"mean_cost\":3.0,\"critic_loss\":1.0}\n\
             {\"kind\":\"validation\",\"update\":20,\"val_tracking_error\":0.5,\"val_nrmse_q_pct\":9.0,\"val_nrmse_r_pct\":3.0}\n",
        );
        let model = BatteryModel::default();
        let input = EvalInput {
            test: &test,
            validation: &val,
            train: Some(&train),
            spec: pf.task.paper().unwrap(),
            model: &model,
            policy: PolicyInput::Loaded { file: &pf, path: path.display().to_string(), choice: "test policy".into() },
            training_curve: Some(curve),
        };
        let mut lines = Vec::new();
        let mut eval = evaluate(&input, &small_opts(), &mut |m| lines.push(m.to_string())).unwrap();
        assert!(lines.iter().any(|l| l.starts_with("RL-LAC")), "{lines:?}");
        write_outputs(&mut eval, dir.path(), None).unwrap();

        let text = std::fs::read_to_string(dir.path().join("report.json")).unwrap();
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        // Typed read-back (floats may differ in the last digit, so compare the structure and a few numbers).
        let back: Report = serde_json::from_str(&text).unwrap();
        assert_eq!((back.test_steps, back.plots.len()), (eval.report.test_steps, eval.report.plots.len()));
        let (a, b) = (back.methods.ukf.unwrap().step_us, eval.report.methods.ukf.as_ref().unwrap().step_us);
        assert!((a - b).abs() <= 1e-12 * b);
        assert_eq!(v["experiment"], "multi");
        assert_eq!(v["test_trajectories"], 3 * 4);
        assert!(v["test_steps"].as_u64().unwrap() > 1000);
        for m in ["rl_lac", "ukf", "direct_mapping"] {
            for k in ["q_mobile", "r_o"] {
                assert!(v["methods"][m]["nrmse_pct"][k].is_number(), "{m} {k}");
                assert!(v["methods"][m]["cycle_nrmse_pct"][k].is_number(), "{m} {k}");
            }
            assert!(v["methods"][m]["step_us"].as_f64().unwrap() > 0.0, "{m}");
            assert!(v["methods"][m]["eod"]["at_10pct"]["mae_s"].is_number(), "{m}");
        }
        // The zero policy answers the middle of the action range: Ro 0.15 against truths 0.1 and 0.2 is 50 %.
        let rl_r = v["methods"]["rl_lac"]["nrmse_pct"]["r_o"].as_f64().unwrap();
        assert!((rl_r - 50.0).abs() < 1e-6, "{rl_r}");
        // The filter, tuned on validation trajectories, is far better than the zero policy.
        assert!(v["methods"]["ukf"]["nrmse_pct"]["q_mobile"].as_f64().unwrap() < 1.0);
        assert_eq!(v["paper"]["table1_nrmse_pct"]["multi_parameter"]["ukf"]["q_mobile"], 19.75);
        assert!(v["methods"]["ukf"]["ukf"]["settings"]["r_std"].is_number());
        for stem in ["params_vs_truth", "error_distribution", "training_curve"] {
            for ext in ["png", "svg"] {
                let f = dir.path().join(format!("{stem}.{ext}"));
                assert!(std::fs::metadata(&f).map(|m| m.len() > 500).unwrap_or(false), "{}", f.display());
            }
        }
        let md = std::fs::read_to_string(dir.path().join("report.md")).unwrap();
        assert!(md.contains("Table 1") && md.contains("Table 2") && md.contains("End-of-discharge"), "{md}");
        assert!(md.contains("| RL-LAC | 8.39 |"), "{md}");
    }

    /// Without a policy the evaluation still runs the baselines and says RL was not evaluated; a single-
    /// parameter report omits the other parameter; plots without a font are still written.
    #[test]
    fn missing_policy_is_reported_not_fatal_and_textless_plots_are_written() {
        let dir = tempfile::tempdir().unwrap();
        let ([_, val, test], spec) = small(Experiment::SingleQ);
        let model = BatteryModel::default();
        let input = EvalInput {
            test: &test,
            validation: &val,
            train: None,
            spec: &spec,
            model: &model,
            policy: PolicyInput::Missing { reason: "no policy.bcalpol in the run folder".into() },
            training_curve: None,
        };
        let opts = EvalOptions { direct_mapping: false, ..small_opts() };
        let mut eval = evaluate(&input, &opts, &mut |_| {}).unwrap();
        write_outputs(&mut eval, dir.path(), Some(false)).unwrap();
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.path().join("report.json")).unwrap()).unwrap();
        assert!(v["methods"].get("rl_lac").is_none());
        assert!(v["not_evaluated"]["rl_lac"].as_str().unwrap().contains("policy.bcalpol"));
        assert!(v["methods"]["ukf"]["nrmse_pct"]["q_mobile"].is_number());
        assert!(v["methods"]["ukf"]["nrmse_pct"].get("r_o").is_none());
        assert!(dir.path().join("params_vs_truth.svg").exists() && dir.path().join("params_vs_truth.png").exists());
        let md = std::fs::read_to_string(dir.path().join("report.md")).unwrap();
        assert!(md.contains("RL-LAC was not evaluated"), "{md}");
        assert!(md.contains("fonts-dejavu-core"), "{md}");
    }
}
