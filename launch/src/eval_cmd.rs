//! `bcal eval`: evaluate the run's RL-LAC policy against a UKF and a supervised direct mapping on the
//! held-out (high-load) test trajectories, and write report.json, report.md and the figures into the run
//! folder. Reads from the run folder when present: the delivered policy (policy.best.bcalpol, the best by
//! validation; `--policy-choice` for another), config.toml (experiment, env settings and the training budget
//! the direct mapping gets too), mdp.json (observation scales) and metrics.jsonl (training curve). Without
//! a policy the baselines are still evaluated and the report says RL was not.

use anyhow::{bail, Context};
use bcal_common::battery::BatteryModel;
use bcal_common::config::Observation;
use bcal_common::config::TrainConfig;
use bcal_common::dataset::{self, Dataset, Experiment, Split};
use bcal_common::mdp::MdpSpec;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::policy::PolicyFile;
use bcal_common::task::Task;
use bcal_eval::measured_eval::{evaluate_measured, MeasuredEvalOptions, MeasuredInput};
use bcal_eval::metrics::Param;
use bcal_eval::plots::TrainingCurve;
use bcal_eval::{EvalInput, EvalOptions, PolicyInput, Report};
use clap::ValueEnum;
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Run folder: read policy.bcalpol, config.toml, mdp.json and metrics.jsonl from it when present, and
    /// write report.json, report.md and the plots into it. It must exist (an empty folder evaluates the
    /// baselines alone).
    #[arg(long)]
    pub run: PathBuf,
    /// Folder for report.json, report.md and the plots (default: the run folder), e.g. to keep the
    /// reports of two policy choices side by side.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Experiment to evaluate (default: the policy's, else the run's config.toml, else multi).
    #[arg(long, value_enum)]
    pub experiment: Option<Experiment>,
    /// Quick run (well under a minute): 12 test trajectories per load, a small UKF tuning grid and a few
    /// seconds of direct-mapping training.
    #[arg(long)]
    pub quick: bool,
    /// Methods to evaluate, comma separated.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "rl,ukf,direct")]
    pub methods: Vec<MethodArg>,
    /// Evaluate the UKF alone (same as --methods ukf).
    #[arg(long)]
    pub ukf_only: bool,
    /// Which of the run's policies to evaluate: `best` (the best by the run's `learner.select_by`
    /// validation score, policy.best.bcalpol), `last` (the weights when training stopped), or the best by a
    /// given validation score (`best-tracking-error`, `best-nrmse`).
    #[arg(long, value_enum, default_value_t = PolicyChoice::Best)]
    pub policy_choice: PolicyChoice,
    /// Policy file (overrides --policy-choice).
    #[arg(long)]
    pub policy: Option<PathBuf>,
    /// Test trajectories per test load, spread over the parameter grid (default: all; --quick: 12).
    #[arg(long)]
    pub per_load: Option<usize>,
    /// Wall-clock budget of the direct mapping's training, s (default: the run's training budget, so both
    /// learners get the same time; 900 s without a run config; --quick: 8). Early stopping on the
    /// validation split usually ends it sooner.
    #[arg(long, value_parser = crate::cli::positive_f64)]
    pub dm_budget_s: Option<f64>,
    /// Cap on the direct mapping's Adam updates, at least 1 (default: none).
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub dm_updates: Option<usize>,
    /// Dataset cache folder (default: $BCAL_CACHE/datasets or ~/.cache/bcal/datasets).
    #[arg(long)]
    pub cache_dir: Option<PathBuf>,
}

#[derive(Clone, Copy, Debug, ValueEnum, PartialEq, Eq)]
pub enum MethodArg {
    /// The trained RL-LAC policy (needs a policy file).
    Rl,
    /// The unscented Kalman filter, tuned on validation trajectories.
    Ukf,
    /// The supervised direct mapping (trained here, in tch, early-stopped on validation).
    Direct,
}

/// Which of a run's policy files to evaluate.
#[derive(Clone, Copy, Debug, ValueEnum, PartialEq, Eq)]
pub enum PolicyChoice {
    Best,
    Last,
    BestTrackingError,
    BestNrmse,
}

impl PolicyChoice {
    fn file_and_why(self, config: Option<&TrainConfig>) -> (String, String) {
        use bcal_common::config::SelectBy;
        use bcal_common::policy::{best_policy_file, POLICY_BEST, POLICY_LAST};
        let select = config.map(|c| c.learner.select_by);
        match self {
            PolicyChoice::Best => (
                POLICY_BEST.into(),
                format!("the best by validation {}", select.map_or("score".into(), |s| s.name().replace('-', " "))),
            ),
            PolicyChoice::Last => (POLICY_LAST.into(), "the weights when training stopped".into()),
            PolicyChoice::BestTrackingError => {
                (best_policy_file(SelectBy::TrackingError), "the best by validation tracking error".into())
            }
            PolicyChoice::BestNrmse => (best_policy_file(SelectBy::Nrmse), "the best by validation NRMSE".into()),
        }
    }
}

pub fn run(a: EvalArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let run_dir = &a.run;
    // A mistyped run folder was created and evaluated in the paper's setting, exit 0 (a fuzz of the CLI,
    // 2026-11-30): a folder to evaluate must exist.
    if !run_dir.is_dir() {
        bail!(
            "the run folder {} does not exist: pass the folder a `bcal train` run wrote (runs/NAME), or create \
             it first to evaluate the baselines alone (with a config.toml from `bcal train --print-config` for \
             a setting other than the paper's)",
            run_dir.display()
        );
    }

    let config_path = run_dir.join("config.toml");
    let config = if config_path.exists() { Some(TrainConfig::from_file(&config_path)?) } else { None };
    // The policy, if there is one: a damaged file is an error, a missing one only skips RL.
    let (policy_path, choice) = match &a.policy {
        // A policy named and missing is a mistake, not a run without one.
        Some(p) if !p.is_file() => {
            bail!("--policy {}: no such file (a .bcalpol a bcal train run wrote, e.g. RUN/policy.bcalpol)", p.display())
        }
        Some(p) => (p.clone(), "given with --policy".to_string()),
        None => {
            let (file, why) = a.policy_choice.file_and_why(config.as_ref());
            (run_dir.join(file), why)
        }
    };
    let policy = if policy_path.exists() {
        Some(
            PolicyFile::load(&policy_path)
                .with_context(|| "the policy file cannot be used; retrain or pass --policy")?,
        )
    } else {
        None
    };

    // A policy is evaluated in the setting it was trained for, and the run says which setting it evaluates:
    // the two must agree.
    if let (Some(p), Some(c)) = (&policy, &config) {
        let (trained, run_obs) = (p.task.observation_name(), Task::observation_label(c.env.observation));
        if trained != run_obs {
            bail!(
                "the policy {} was trained on the {trained} observation, but the run {} evaluates the {run_obs} \
                 observation (its config.toml): pass a policy of that run, or evaluate this policy in its own run",
                policy_path.display(),
                run_dir.display()
            );
        }
    }
    // A measured-only policy of another setting (other cells or another calibrator) would be evaluated in its
    // own setting under this run's name: refused, as one of another observation is.
    if let (Some(m), Some(c)) = (policy.as_ref().and_then(|p| p.task.measured()), &config) {
        if c.env.observation == Observation::Measured && !same_setting(m, &c.measured) {
            bail!(
                "the policy {} was trained on another measured setting than the run {} (its config.toml: other \
                 cells or another calibrator): evaluate it in its own run, or pass a policy of this run",
                policy_path.display(),
                run_dir.display()
            );
        }
    }
    // The setting: the policy's task, else the run's observation, else the paper's.
    let measured_spec = match (&policy, &config) {
        (Some(p), _) => p.task.measured().cloned(),
        (None, Some(c)) if c.env.observation == Observation::Measured => Some(c.measured.clone()),
        _ => None,
    };
    if let Some(spec) = measured_spec {
        if a.experiment.is_some_and(|e| e != Experiment::Multi) {
            bail!("the measured-only setting calibrates qMobile and Ro together; drop --experiment");
        }
        return run_measured(
            &a,
            &spec,
            policy.as_ref().map(|p| (p, policy_path.clone(), choice)),
            config.as_ref(),
            started,
        );
    }

    let experiment = match (a.experiment, &policy, &config) {
        (Some(e), Some(p), _) if p.experiment != e => bail!(
            "the policy {} was trained on {}, not {e}; drop --experiment or pass --experiment {}",
            policy_path.display(),
            p.experiment,
            p.experiment
        ),
        (Some(e), _, _) => e,
        (None, Some(p), _) => p.experiment,
        (None, None, Some(c)) => c.experiment,
        (None, None, None) => Experiment::Multi,
    };
    println!("evaluating experiment {experiment} in {}", run_dir.display());

    let mut opts = if a.quick { EvalOptions::quick() } else { EvalOptions::full() };
    let wanted = |m: MethodArg| if a.ukf_only { m == MethodArg::Ukf } else { a.methods.contains(&m) };
    opts.rl = wanted(MethodArg::Rl);
    opts.ukf = wanted(MethodArg::Ukf);
    opts.direct_mapping = wanted(MethodArg::Direct);

    // The splits: test (scored), validation (every choice), training (the direct mapping's pairs and, when
    // there is no MDP to read, the observation scales).
    let model = BatteryModel::default();
    let cache_dir = a.cache_dir.clone().unwrap_or_else(dataset::default_cache_dir);
    let def = experiment.definition();
    let load = |split: Split| -> anyhow::Result<Dataset> {
        let (ds, rep) = dataset::load_or_generate(&def, &model, &cache_dir, split)?;
        crate::train_cmd::report_cache(experiment, split, &rep);
        Ok(ds)
    };
    let test = load(Split::Test)?;
    let validation = load(Split::Validation)?;
    let needs_train = opts.direct_mapping || policy.is_none();
    let train = if needs_train { Some(load(Split::Train)?) } else { None };

    // The MDP: the policy's own (its scales travel with it), else the run's mdp.json, else derived here.
    let spec = match &policy {
        Some(p) => match &p.task {
            bcal_common::task::Task::Paper(m) => m.clone(),
            other => bail!(
                "the policy {} was trained on the {} observation; this evaluation is of the paper's setting",
                policy_path.display(),
                other.observation_name()
            ),
        },
        None => {
            let mdp_path = run_dir.join("mdp.json");
            let from_run = match &config {
                Some(c) if c.experiment == experiment && mdp_path.exists() => {
                    let text = std::fs::read_to_string(&mdp_path)
                        .with_context(|| format!("cannot read {}", mdp_path.display()))?;
                    Some(
                        serde_json::from_str::<MdpSpec>(&text)
                            .with_context(|| format!("{} is not a valid MDP description", mdp_path.display()))?,
                    )
                }
                _ => None,
            };
            match from_run {
                Some(s) => s,
                None => {
                    let env = config.as_ref().filter(|c| c.experiment == experiment).map(|c| c.env.clone());
                    MdpSpec::new(experiment, &env.unwrap_or_default(), train.as_ref().expect("loaded when no policy"))
                }
            }
        }
    };

    let metrics_path = run_dir.join("metrics.jsonl");
    let training_curve = std::fs::read_to_string(&metrics_path).ok().map(|t| TrainingCurve::parse(&t));

    if let Some(k) = a.per_load {
        if k == 0 {
            bail!("--per-load must be at least 1");
        }
        opts.test_per_load = Some(k);
    }
    // Equal effort: the direct mapping gets the RL run's wall-clock budget unless told otherwise.
    match (a.dm_budget_s, &config) {
        (Some(s), _) => opts.direct.time_budget_s = s,
        (None, Some(c)) if !a.quick && c.learner.time_budget_s > 0.0 => {
            opts.direct.time_budget_s = c.learner.time_budget_s
        }
        _ => {}
    }
    if let Some(c) = &config {
        opts.direct.seed = c.seed;
    }
    if let Some(n) = a.dm_updates {
        opts.direct.max_updates = n;
    }

    let policy_input = match &policy {
        Some(file) => PolicyInput::Loaded { file, path: policy_path.display().to_string(), choice },
        None => PolicyInput::Missing {
            reason: format!(
                "no policy file at {}: train one first (bcal train --run {}) or pass --policy FILE",
                policy_path.display(),
                run_dir.display()
            ),
        },
    };
    let input = EvalInput {
        test: &test,
        validation: &validation,
        train: train.as_ref(),
        spec: &spec,
        model: &model,
        policy: policy_input,
        training_curve,
    };
    let mut eval = bcal_eval::evaluate(&input, &opts, &mut |msg| {
        println!("[{:6.1} s] {msg}", started.elapsed().as_secs_f64());
    })?;
    let out_dir = a.out.clone().unwrap_or_else(|| run_dir.clone());
    let written = bcal_eval::write_outputs(&mut eval, &out_dir, None)?;
    print_summary(&eval.report);
    for n in &eval.report.notes {
        println!("note: {n}");
    }
    println!(
        "wrote {} files into {} in {:.1} s: report.json, report.md, {}",
        written.len(),
        out_dir.display(),
        started.elapsed().as_secs_f64(),
        eval.report.plots.join(", ")
    );
    Ok(())
}

/// The measured-only evaluation (issue 12) of a run: every calibrator on test cells read through the sensor.
/// Whether two measured settings hold the same cells and calibrator: their scenario and tracker alike, floats
/// within 1e-9 relative (a policy's task went through JSON, which may move a value's last bit), the recorded
/// discharges' path aside (training writes it absolute into the task).
fn same_setting(a: &MeasuredSpec, b: &MeasuredSpec) -> bool {
    fn close(x: &serde_json::Value, y: &serde_json::Value) -> bool {
        use serde_json::Value::{Array, Number, Object};
        match (x, y) {
            (Number(p), Number(q)) => match (p.as_f64(), q.as_f64()) {
                (Some(p), Some(q)) => (p - q).abs() <= 1e-9 * p.abs().max(q.abs()).max(1e-300),
                _ => p == q,
            },
            (Array(p), Array(q)) => p.len() == q.len() && p.iter().zip(q).all(|(p, q)| close(p, q)),
            (Object(p), Object(q)) => {
                p.len() == q.len() && p.iter().all(|(k, v)| q.get(k).is_some_and(|w| close(v, w)))
            }
            _ => x == y,
        }
    }
    let setting = |s: &MeasuredSpec| {
        let mut scenario = s.scenario.clone();
        scenario.recorded.path = None;
        serde_json::json!({ "scenario": scenario, "tracker": s.tracker })
    };
    close(&setting(a), &setting(b))
}

fn run_measured(
    a: &EvalArgs,
    spec: &MeasuredSpec,
    policy: Option<(&PolicyFile, PathBuf, String)>,
    config: Option<&TrainConfig>,
    started: Instant,
) -> anyhow::Result<()> {
    let run_dir = &a.run;
    println!("evaluating the measured-only setting in {}", run_dir.display());
    let mut opts = if a.quick { MeasuredEvalOptions::quick() } else { MeasuredEvalOptions::full() };
    let wanted = |m: MethodArg| if a.ukf_only { m == MethodArg::Ukf } else { a.methods.contains(&m) };
    opts.rl = wanted(MethodArg::Rl);
    opts.ukf = wanted(MethodArg::Ukf);
    opts.direct_mapping = wanted(MethodArg::Direct);
    if let Some(k) = a.per_load {
        if k == 0 {
            bail!("--per-load must be at least 1");
        }
        opts.test_episodes = Some(k);
    }
    match (a.dm_budget_s, config) {
        (Some(s), _) => opts.direct.time_budget_s = s,
        (None, Some(c)) if !a.quick && c.learner.time_budget_s > 0.0 => {
            opts.direct.time_budget_s = c.learner.time_budget_s
        }
        _ => {}
    }
    if let Some(n) = a.dm_updates {
        opts.direct.max_updates = n;
    }
    let policy_input = match &policy {
        Some((file, path, choice)) => {
            PolicyInput::Loaded { file, path: path.display().to_string(), choice: choice.clone() }
        }
        None => PolicyInput::Missing {
            reason: format!(
                "no policy file in {}: train one first (bcal train --run {})",
                run_dir.display(),
                run_dir.display()
            ),
        },
    };
    let training_curve = std::fs::read_to_string(run_dir.join("metrics.jsonl")).ok().map(|t| TrainingCurve::parse(&t));
    let input = MeasuredInput { spec, policy: policy_input, training_curve, seed: config.map_or(1, |c| c.seed) };
    let mut eval = evaluate_measured(&input, &opts, &mut |msg| {
        println!("[{:6.1} s] {msg}", started.elapsed().as_secs_f64());
    })?;
    let out_dir = a.out.clone().unwrap_or_else(|| run_dir.clone());
    let written = bcal_eval::measured_report::write_outputs(&mut eval, &out_dir, opts.plot_episodes)
        .with_context(|| format!("cannot write the report into {}", out_dir.display()))?;
    let r = &eval.report;
    println!(
        "
measured-only, {:.1} mV: NRMSE qMobile / Ro % (second half), time to 2 % s, coverage %, us per reading",
        r.voltage_noise_mv
    );
    for (key, name) in bcal_eval::measured_eval::METHODS {
        let Some(m) = r.methods.get(key) else {
            let why = r.not_evaluated.get(key).map_or(String::new(), |w| format!(": {w}"));
            println!("  {name:<25} not evaluated{why}");
            continue;
        };
        let g = |v: &bcal_eval::metrics::ParamValues, d: usize| {
            format!(
                "{} / {}",
                v.q_mobile.map_or("-".into(), |x| format!("{x:.d$}")),
                v.r_o.map_or("-".into(), |x| format!("{x:.d$}"))
            )
        };
        println!(
            "  {name:<25} {} ({})  {}  {}  {}",
            g(&m.nrmse_pct, 2),
            g(&m.second_half_nrmse_pct, 2),
            g(&m.time_to_2pct_s, 0),
            g(&m.coverage_90_pct, 1),
            m.step_us.map_or("-".into(), |x| format!("{x:.2}"))
        );
    }
    for n in &r.notes {
        println!("note: {n}");
    }
    println!("wrote {} files into {} in {:.1} s", written.len(), out_dir.display(), started.elapsed().as_secs_f64());
    Ok(())
}

/// The three tables, compactly, on stdout.
fn print_summary(r: &Report) {
    let params = r.calibrated_params();
    println!("\nTable 1 ({}): normalised RMSE %, every step (per-cycle median in brackets)", r.experiment);
    for (key, name) in bcal_eval::report::METHODS {
        let Some(m) = r.methods.get(key) else {
            println!("  {name:<15} not evaluated");
            continue;
        };
        let cells: Vec<String> = params
            .iter()
            .map(|p| {
                format!(
                    "{} {:.3} ({:.3})",
                    short(*p),
                    m.accuracy.nrmse_pct.get(*p).unwrap_or(f64::NAN),
                    m.accuracy.cycle_nrmse_pct.get(*p).unwrap_or(f64::NAN)
                )
            })
            .collect();
        println!("  {name:<15} {}", cells.join("   "));
    }
    println!("Table 2: per-step inference cost (one battery-model step = {:.3} us)", r.model_step_us);
    for (key, name) in bcal_eval::report::METHODS {
        if let Some(m) = r.methods.get(key) {
            println!("  {name:<15} {:8.2} us  ({:.1} model steps)", m.step_us, m.step_in_model_steps);
        }
    }
    println!("EOD prediction MAE, s (% of EOD): at 10 % / at 50 % of the discharge");
    let line = |name: &str, e: &bcal_eval::metrics::EodMetrics| {
        println!(
            "  {name:<15} {:7.1} ({:.2} %) / {:7.1} ({:.2} %)",
            e.at_10pct.mae_s, e.at_10pct.mae_pct, e.at_50pct.mae_s, e.at_50pct.mae_pct
        )
    };
    line("true params", &r.eod_references.true_parameters);
    for (key, name) in bcal_eval::report::METHODS {
        if let Some(m) = r.methods.get(key) {
            line(name, &m.eod);
        }
    }
    line("uncalibrated", &r.eod_references.uncalibrated);
    for (k, why) in &r.not_evaluated {
        println!("not evaluated: {k}: {why}");
    }
}

fn short(p: Param) -> &'static str {
    match p {
        Param::QMobile => "Qmax",
        Param::ROhm => "Ro",
    }
}
