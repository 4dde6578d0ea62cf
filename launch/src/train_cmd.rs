//! `bcal train`: prepare a run folder, start replay, learner and N actors as separate processes, watch
//! them (restarting crashed ones by policy), show progress, and stop the tree cleanly at the end or on
//! Ctrl-C (a second Ctrl-C kills at once).
//!
//! Run folder (`runs/<name>/` by default): config.toml (the effective config), mdp.json (observation scales
//! and action map, shared by every process), metrics.jsonl (learner), checkpoints/, policy.bcalpol, logs/
//! (one file per process plus supervisor.log), and later the evaluation report.

use crate::supervisor::{self, decide, Decision, Exit, RestartPolicy, Role, Supervised};
use anyhow::{bail, Context};
use bcal_calib::tune::{tune_joint_ukf, JointUkfGrid};
use bcal_common::battery::BatteryModel;
use bcal_common::config::{Preset, TrainConfig};
use bcal_common::dataset::{self, CacheStatus, Experiment, Split};
use bcal_common::mdp::MdpSpec;
use bcal_common::measured::env::{Design, MeasuredSpec};
use bcal_common::measured::scenario;
use bcal_common::measured::tracker::JointUkfSettings;
use bcal_common::task::Task;
use clap::Args;
use std::io::{BufRead, IsTerminal, Seek, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[derive(Args, Debug, Clone)]
pub struct TrainArgs {
    /// Starting point of the config: `measured` (calibration from sensor readings: voltage, current,
    /// temperature), `paper-tuned` (the paper's full-state setting, hyperparameters measured on the
    /// validation split) or `paper` (the paper's setting and hyperparameters). Default measured.
    #[arg(long, value_enum)]
    pub preset: Option<Preset>,
    /// TOML config file; absent keys take the preset's values (see `bcal train --print-config`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Experiment to train on (overrides the config's `experiment`).
    #[arg(long, value_enum)]
    pub experiment: Option<Experiment>,
    /// Run name: the run folder is runs/<name> (default: <experiment>-<UTC time>).
    #[arg(long)]
    pub name: Option<String>,
    /// Run folder (overrides --name).
    #[arg(long)]
    pub run: Option<PathBuf>,
    /// Training time budget in seconds (overrides learner.time_budget_s).
    #[arg(long, allow_hyphen_values = true)]
    pub budget_s: Option<f64>,
    /// Stop after this many learner updates (overrides learner.max_updates).
    #[arg(long)]
    pub max_updates: Option<u64>,
    /// Number of actor processes, at least 1 (overrides actors.count; default: one per core).
    #[arg(long)]
    pub actors: Option<usize>,
    /// Seed of every random stream (overrides seed).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Continue the run in --run/--name from its last checkpoint (same update counter).
    #[arg(long)]
    pub resume: bool,
    /// Print the effective config as TOML and exit.
    #[arg(long)]
    pub print_config: bool,
    /// Seconds a process gets to exit after SIGTERM before it is killed (0 to 3600).
    #[arg(long, default_value_t = 20.0, value_parser = crate::cli::grace_s, allow_hyphen_values = true)]
    pub grace_s: f64,
}

/// What `bcal train` finished with (the caller may go on to evaluate).
pub struct TrainOutcome {
    pub run_dir: PathBuf,
    pub stopped: Stopped,
}

/// Why the supervision ended without an error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Stopped {
    /// The learner met its budget.
    Finished,
    /// Ctrl-C or SIGTERM to `bcal train`: the tree stopped, the learner checkpointed on its way out.
    Signal { name: &'static str, exit_code: i32 },
    /// The learner exited cleanly before its budget without being asked (a signal from outside the
    /// supervisor): the run ends with its checkpoint.
    ByLearner,
}

pub fn run(a: TrainArgs) -> anyhow::Result<()> {
    let out = train(a)?;
    let dir = out.run_dir.display();
    match out.stopped {
        Stopped::Finished => {
            println!("run folder: {dir}");
            println!("next: bcal eval --run {dir}");
            Ok(())
        }
        // Stopped before its budget: said, with how to go on, and a signal's exit status, so a script running
        // `bcal train` then `bcal eval` (launch/run.sh) stops too.
        Stopped::Signal { name, exit_code } => {
            eprintln!(
                "stopped by {name} before the training budget; its last checkpoint is kept: continue with bcal train \
                 --run {dir} --resume, or evaluate what it has with bcal eval --run {dir}"
            );
            std::process::exit(exit_code)
        }
        Stopped::ByLearner => bail!(
            "the learner stopped before the training budget without being asked (a signal from outside bcal \
             train?); its last checkpoint is kept: continue with bcal train --run {dir} --resume"
        ),
    }
}

pub fn train(a: TrainArgs) -> anyhow::Result<TrainOutcome> {
    let run_dir = resolve_run_dir(&a)?;
    let preset = a.preset.unwrap_or(Preset::Measured);
    let mut cfg = if a.resume {
        let p = run_dir.join("config.toml");
        if !p.exists() {
            bail!("--resume: {} has no config.toml; is this a bcal run folder?", run_dir.display());
        }
        // The run trains on to its own config: a setting given now would be ignored, or mix two settings.
        let given: Vec<&str> = [
            a.config.is_some().then_some("--config"),
            a.preset.is_some().then_some("--preset"),
            a.experiment.is_some().then_some("--experiment"),
        ]
        .into_iter()
        .flatten()
        .collect();
        if !given.is_empty() {
            bail!(
                "--resume continues {} on its own config.toml; {} cannot change it (--budget-s, --max-updates, \
                 --actors and --seed can): train a new run for another setting",
                run_dir.display(),
                given.join(", ")
            );
        }
        // Without a checkpoint the learner starts again from update 0 and overwrites what the run holds.
        // (A run stopped before its first checkpoint and policy has nothing to lose, and starts again.)
        let trained = std::fs::read_dir(&run_dir)
            .is_ok_and(|entries| entries.flatten().any(|e| e.file_name().to_string_lossy().ends_with(".bcalpol")));
        if trained && !run_dir.join("checkpoints").join("LATEST").exists() {
            bail!(
                "--resume: {} holds a trained policy but no checkpoint to continue from (checkpoints/LATEST is \
                 missing); resuming would start again from update 0 and overwrite it: restore checkpoints/ or train a \
                 new run (--name)",
                run_dir.display()
            );
        }
        TrainConfig::from_file(&p)?
    } else {
        match &a.config {
            Some(p) => TrainConfig::from_file_over(p, preset)?,
            None => preset.config(),
        }
    };
    if let Some(e) = a.experiment {
        cfg.experiment = e;
    }
    if let Some(b) = a.budget_s {
        cfg.learner.time_budget_s = b;
    }
    if let Some(m) = a.max_updates {
        cfg.learner.max_updates = m;
    }
    if let Some(n) = a.actors {
        cfg.actors.count = Some(n);
    }
    if let Some(s) = a.seed {
        cfg.seed = s;
    }
    let v = cfg.validate()?;
    // The budget counts every leg of a run: one already spent trains nothing (it did so silently).
    if a.resume {
        if let Some((trained_s, updates)) = trained_so_far(&run_dir) {
            let (budget_s, max_updates) = (cfg.learner.time_budget_s, cfg.learner.max_updates);
            if (budget_s > 0.0 && trained_s >= budget_s) || (max_updates > 0 && updates >= max_updates) {
                bail!(
                    "--resume: {} has trained {trained_s:.0} s and {updates} updates, its budget is {budget_s} s / \
                     {max_updates} updates (0: no limit), counted over every leg: nothing is left to train; give a \
                     larger --budget-s or --max-updates",
                    run_dir.display()
                );
            }
        }
    }
    if a.print_config {
        print!("{}", cfg.to_toml());
        std::process::exit(0);
    }
    if !a.resume && run_dir.join("config.toml").exists() {
        bail!("{} already holds a run; pass --resume to continue it or choose another --name", run_dir.display());
    }
    std::fs::create_dir_all(run_dir.join("logs"))
        .with_context(|| format!("cannot create the run folder {}: check the path is writable", run_dir.display()))?;
    write_atomic(&run_dir.join("config.toml"), cfg.to_toml().as_bytes())?;
    // A finished marker from an earlier leg must not end a resumed run at once.
    let _ = std::fs::remove_file(run_dir.join("learner.done"));

    // The task every process reads from mdp.json. Paper task: warm the cache of the splits training reads
    // (actors: train, learner: validation) so the processes only read it; the observation scales come from
    // the training split. Measured task: no data set, actors simulate their cells.
    let mdp_path = run_dir.join("mdp.json");
    match cfg.env.observation.paper_kind() {
        Some(_) => {
            let model = BatteryModel::default();
            let cache_dir = dataset::default_cache_dir();
            let mut train = None;
            for split in [Split::Train, Split::Validation] {
                let (ds, rep) = dataset::load_or_generate(&v.def, &model, &cache_dir, split)?;
                report_cache(cfg.experiment, split, &rep);
                v.check_dataset(&ds)?;
                if split == Split::Train {
                    train = Some(ds);
                }
            }
            if !(a.resume && mdp_path.exists()) {
                let spec = MdpSpec::new(cfg.experiment, &cfg.env, train.as_ref().expect("loaded above"));
                write_atomic(&mdp_path, serde_json::to_string_pretty(&Task::Paper(spec))?.as_bytes())?;
            }
        }
        None => {
            if !(a.resume && mdp_path.exists()) {
                let mut spec = cfg.measured.clone();
                if let Some(p) = &spec.scenario.recorded.path {
                    // Relative to the config file's folder; every process reads the absolute path.
                    let base = a.config.as_ref().and_then(|c| c.parent()).unwrap_or(Path::new("."));
                    let path = std::path::absolute(base.join(p))
                        .with_context(|| format!("measured.scenario.recorded.path = {p}"))?;
                    let set = bcal_common::measured::scenario::RecordedSet::load(&path).map_err(anyhow::Error::msg)?;
                    println!(
                        "recorded discharges of {}: {} for training (share {}), {} for validation ({})",
                        set.cell,
                        set.train.len(),
                        spec.scenario.recorded.share,
                        set.validation.len(),
                        path.display()
                    );
                    spec.scenario.recorded.path = Some(path.display().to_string());
                }
                if spec.design == Design::UkfCorrection && spec.ukf.is_none() {
                    spec.ukf = Some(tune_base_filter(&spec)?);
                }
                let task = Task::Measured(spec);
                write_atomic(&mdp_path, serde_json::to_string_pretty(&task)?.as_bytes())?;
            }
        }
    }

    println!(
        "training {} / {} observation (preset {}{}) with {} actor(s) x {} envs, budget {} s / {} updates, run folder {}",
        cfg.experiment,
        Task::observation_label(cfg.env.observation),
        preset.name(),
        a.config.as_ref().map(|p| format!(" + {}", p.display())).unwrap_or_default(),
        v.actor_count,
        cfg.actors.envs_per_actor,
        cfg.learner.time_budget_s,
        cfg.learner.max_updates,
        run_dir.display()
    );
    let policy = RestartPolicy { max_restarts: cfg.actors.max_restarts, ..RestartPolicy::default() };
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    let stopped = rt.block_on(watch(
        run_dir.clone(),
        v.actor_count,
        a.resume,
        policy,
        Duration::from_secs_f64(a.grace_s),
        cfg.learner.time_budget_s,
    ))?;
    Ok(TrainOutcome { run_dir, stopped })
}

/// Seconds of training and updates of a run's last checkpoint (its `meta.json`: `trained_s` and `update_step` of
/// `bcal_learner::checkpoint::CheckpointMeta`, read here without the learner's libtorch), if it has one.
fn trained_so_far(run_dir: &Path) -> Option<(f64, u64)> {
    let dir = run_dir.join("checkpoints");
    let step = std::fs::read_to_string(dir.join("LATEST")).ok()?;
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join(step.trim()).join("meta.json")).ok()?).ok()?;
    Some((meta.get("trained_s")?.as_f64()?, meta.get("update_step")?.as_u64()?))
}

/// The joint UKF the correction policy learns on: every setting of the evaluator's grid on the validation
/// cells, the best by their mean NRMSE (the same choice the evaluator's `ukf` baseline makes, so the
/// learned calibrator starts exactly where that baseline stands).
fn tune_base_filter(spec: &MeasuredSpec) -> anyhow::Result<JointUkfSettings> {
    let started = Instant::now();
    let sc = &spec.scenario;
    let validation = scenario::episode_set(sc, Split::Validation, sc.validation_episodes)
        .map_err(|e| anyhow::anyhow!("cannot simulate the validation cells: {e}"))?;
    let grid = JointUkfGrid::default();
    println!(
        "tuning the joint UKF the correction starts from: {} settings on {} validation cells ...",
        grid.candidates().len(),
        validation.len()
    );
    let t = tune_joint_ukf(&spec.tracker, &validation, &grid);
    println!(
        "joint UKF: meas_std {:.1} mV, parameter walk {:e}/sqrt(s), charge walk {} C/sqrt(s), prior std {:?}: \
         validation mean NRMSE {:.2} % ({:.0} s)",
        t.best.meas_std_v * 1e3,
        t.best.param_walk_per_sqrt_s,
        t.best.charge_walk_c_per_sqrt_s,
        t.best.prior_std_z,
        t.top[0].1,
        started.elapsed().as_secs_f64()
    );
    Ok(t.best)
}

fn resolve_run_dir(a: &TrainArgs) -> anyhow::Result<PathBuf> {
    if let Some(r) = &a.run {
        return Ok(r.clone());
    }
    let name = match &a.name {
        Some(n) => {
            if n.is_empty() || n.contains('/') || n.starts_with('.') {
                bail!("--name `{n}` must be a plain folder name (no '/', not starting with '.')");
            }
            n.clone()
        }
        None => {
            if a.resume {
                bail!("--resume needs --run DIR or --name NAME of the run to continue");
            }
            let exp = a.experiment.map(|e| e.name().to_string()).unwrap_or_else(|| "run".into());
            let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH)?.as_secs();
            format!("{exp}-{}", utc_stamp(secs))
        }
    };
    Ok(PathBuf::from("runs").join(name))
}

/// YYYYmmdd-HHMMSS in UTC, from seconds since the epoch (civil-from-days, Howard Hinnant's algorithm).
fn utc_stamp(secs: u64) -> String {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!("{y:04}{m:02}{d:02}-{:02}{:02}{:02}", rem / 3600, rem / 60 % 60, rem % 60)
}

pub fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    bcal_common::fsutil::write_atomic(path, bytes)
        .with_context(|| format!("cannot write {} (disk full or folder not writable?)", path.display()))
}

/// One line on what the dataset cache did for a split.
pub fn report_cache(experiment: Experiment, split: Split, rep: &dataset::LoadReport) {
    match &rep.status {
        CacheStatus::Hit => println!("dataset {experiment} {split}: cached ({:.1} s to read)", rep.seconds),
        CacheStatus::Generated => println!("dataset {experiment} {split}: generated in {:.1} s", rep.seconds),
        CacheStatus::Regenerated { reason } => {
            println!("dataset {experiment} {split}: cache was corrupt ({reason}); regenerated in {:.1} s", rep.seconds)
        }
    }
}

struct Program {
    role: Role,
    exe: PathBuf,
    args: Vec<String>,
}

fn program(role: Role, bin: &Path, run_dir: &Path, resume: bool) -> Program {
    let run = run_dir.display().to_string();
    let (exe, mut args) = match role {
        Role::Replay => ("bcal-replay", vec!["--run".to_string(), run]),
        Role::Learner => ("bcal-learner", vec!["--run".to_string(), run]),
        Role::Actor(k) => ("bcal-actor", vec!["--run".to_string(), run, "--actor-id".into(), k.to_string()]),
    };
    if role == Role::Learner && resume {
        args.push("--resume".into());
    }
    Program { role, exe: bin.join(exe), args }
}

/// The supervision loop: start, watch, restart, report progress, stop.
async fn watch(
    run_dir: PathBuf,
    actors: usize,
    resume: bool,
    policy: RestartPolicy,
    grace: Duration,
    budget_s: f64,
) -> anyhow::Result<Stopped> {
    let bin = supervisor::bin_dir()?;
    for exe in ["bcal-replay", "bcal-learner", "bcal-actor"] {
        if !bin.join(exe).exists() {
            bail!(
                "{} not found in {}; build the workspace (cargo build --release) or set BCAL_BIN_DIR",
                exe,
                bin.display()
            );
        }
    }
    let logs = run_dir.join("logs");
    let mut sup_log = std::fs::OpenOptions::new().create(true).append(true).open(logs.join("supervisor.log"))?;
    let started = Instant::now();
    let mut note = |msg: &str| {
        let _ = writeln!(sup_log, "[{:8.1} s] {msg}", started.elapsed().as_secs_f64());
    };

    let mut roles = vec![Role::Replay, Role::Learner];
    roles.extend((0..actors).map(Role::Actor));
    let mut children: Vec<Supervised> = Vec::new();
    for role in &roles {
        let p = program(*role, &bin, &run_dir, resume);
        let s = supervisor::spawn(p.role, &p.exe, &p.args, &logs.join(format!("{}.log", p.role.name())), &[])
            .with_context(|| format!("cannot start {}", p.exe.display()))?;
        note(&format!("started {} pid {}", role.name(), s.pid));
        children.push(s);
        if *role == Role::Replay {
            // The replay creates the services; give it a head start so peers find them at once.
            tokio::time::sleep(Duration::from_millis(300)).await;
        }
    }

    let mut progress = Progress::new(&run_dir, budget_s);
    let mut rng = <rand::rngs::SmallRng as rand::SeedableRng>::seed_from_u64(u64::from(std::process::id()));
    let mut pending: Vec<(Instant, Role, u32)> = Vec::new();
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    let mut outcome: Option<anyhow::Result<Stopped>> = None;
    let ctrl_c = tokio::signal::ctrl_c();
    tokio::pin!(ctrl_c);
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;

    while outcome.is_none() {
        tokio::select! {
            _ = &mut ctrl_c => {
                note("Ctrl-C: stopping");
                eprintln!("\nstopping (Ctrl-C again to kill at once)...");
                outcome = Some(Ok(Stopped::Signal { name: "Ctrl-C", exit_code: 130 }));
            }
            _ = sigterm.recv() => {
                note("SIGTERM: stopping");
                outcome = Some(Ok(Stopped::Signal { name: "SIGTERM", exit_code: 143 }));
            }
            _ = tick.tick() => {
                progress.update();
                // Restarts that are due.
                let now = Instant::now();
                let due: Vec<_> = pending.iter().filter(|(t, _, _)| *t <= now).cloned().collect();
                pending.retain(|(t, _, _)| *t > now);
                for (_, role, restarts) in due {
                    let p = program(role, &bin, &run_dir, role == Role::Learner);
                    match supervisor::spawn(role, &p.exe, &p.args, &logs.join(format!("{}.log", role.name())), &[]) {
                        Ok(mut s) => {
                            s.restarts = restarts;
                            note(&format!("restarted {} (restart {restarts}) pid {}", role.name(), s.pid));
                            children.push(s);
                        }
                        Err(e) => outcome = Some(Err(anyhow::anyhow!("cannot restart {}: {e}", role.name()))),
                    }
                }
                // Exits.
                let mut k = 0;
                while k < children.len() {
                    let st = children[k].child.try_wait()?;
                    let Some(st) = st else { k += 1; continue };
                    let s = children.remove(k);
                    let exit = Exit::from_status(st);
                    let done = run_dir.join("learner.done").exists();
                    let d = decide(s.role, exit, done, s.restarts, &policy);
                    note(&format!("{} exited: {exit:?} -> {d:?}", s.role.name()));
                    match d {
                        Decision::Finish if done => outcome = Some(Ok(Stopped::Finished)),
                        Decision::Finish => outcome = Some(Ok(Stopped::ByLearner)),
                        Decision::Abort => {
                            let log = logs.join(format!("{}.log", s.role.name()));
                            outcome = Some(Err(anyhow::anyhow!(
                                "{} failed {} times ({exit:?}){}; see {}",
                                s.role.name(),
                                s.restarts + 1,
                                last_error(&log).map_or(String::new(), |e| format!(", last with: {e}")),
                                log.display()
                            )))
                        }
                        Decision::Restart => {
                            let n = s.restarts + 1;
                            let delay = policy.delay(n, rand::Rng::random::<f64>(&mut rng)).unwrap_or(Duration::ZERO);
                            eprintln!("{} exited ({exit:?}); restarting in {:.1} s", s.role.name(), delay.as_secs_f64());
                            pending.push((Instant::now() + delay, s.role, n));
                        }
                    }
                }
            }
        }
    }

    // Stop order: actors (producers), then the learner (it checkpoints on SIGTERM), then the replay.
    let stop_all = async {
        for phase in [0, 1, 2] {
            for s in children.iter_mut() {
                let in_phase = matches!((phase, s.role), (0, Role::Actor(_)) | (1, Role::Learner) | (2, Role::Replay));
                if in_phase {
                    let e = supervisor::stop(s, grace).await;
                    let _ = writeln!(
                        std::fs::OpenOptions::new().append(true).open(logs.join("supervisor.log")).expect("log open"),
                        "stopped {}: {e:?}",
                        s.role.name()
                    );
                }
            }
        }
    };
    tokio::select! {
        _ = stop_all => {}
        _ = tokio::signal::ctrl_c() => {
            eprintln!("killing every process now");
            for s in children.iter_mut() {
                supervisor::signal_group(s.pid, libc::SIGKILL);
                let _ = s.child.wait().await;
            }
        }
    }
    progress.update();
    progress.finish();
    outcome.unwrap_or(Ok(Stopped::Finished))
}

/// The last error a child wrote to its log (from the line starting `error` or holding `panicked at`, with its
/// causes, up to 400 characters), so the supervisor's own error says why it gave up, not only where to look.
fn last_error(log: &Path) -> Option<String> {
    let text = std::fs::read_to_string(log).ok()?;
    let lines: Vec<&str> = text.lines().collect();
    let k = lines
        .iter()
        .rposition(|l| l.trim_start().to_ascii_lowercase().starts_with("error") || l.contains("panicked at"))?;
    // What follows the line belongs to it: a panic's message, an error's causes (anyhow's "Caused by:" list),
    // up to a backtrace.
    let said: Vec<&str> = lines[k..]
        .iter()
        .take(12)
        .map(|l| l.trim())
        .take_while(|l| !l.starts_with("Stack backtrace") && !l.starts_with("note: run with"))
        .filter(|l| !l.is_empty() && *l != "Caused by:")
        .collect();
    let said = said.join(" ");
    Some(bcal_common::text::shown(&said, 400))
}

/// Follows metrics.jsonl and shows a progress bar (or log lines when stdout is not a terminal).
struct Progress {
    path: PathBuf,
    offset: u64,
    bar: Option<indicatif::ProgressBar>,
    last_line: Instant,
    started: Instant,
    budget_s: f64,
    last_train: Option<serde_json::Value>,
    last_val: Option<serde_json::Value>,
}

impl Progress {
    fn new(run_dir: &Path, budget_s: f64) -> Self {
        let bar = std::io::stdout().is_terminal().then(|| {
            let b = indicatif::ProgressBar::new(budget_s.max(1.0) as u64);
            b.set_style(
                indicatif::ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} s  {msg}")
                    .expect("static template")
                    .progress_chars("=> "),
            );
            b
        });
        Self {
            path: run_dir.join("metrics.jsonl"),
            offset: 0,
            bar,
            last_line: Instant::now(),
            started: Instant::now(),
            budget_s,
            last_train: None,
            last_val: None,
        }
    }

    fn update(&mut self) {
        if let Ok(mut f) = std::fs::File::open(&self.path) {
            if f.seek(std::io::SeekFrom::Start(self.offset)).is_ok() {
                let mut r = std::io::BufReader::new(f);
                let mut line = String::new();
                while let Ok(n) = r.read_line(&mut line) {
                    if n == 0 || !line.ends_with('\n') {
                        break; // a half-written last line is read again next time
                    }
                    self.offset += n as u64;
                    if let Ok(v) = serde_json::from_str::<serde_json::Value>(&line) {
                        match v.get("kind").and_then(|k| k.as_str()) {
                            Some("validation") => self.last_val = Some(v),
                            Some("train") => self.last_train = Some(v),
                            _ => {}
                        }
                    }
                    line.clear();
                }
            }
        }
        let msg = self.message();
        let elapsed = self.started.elapsed().as_secs_f64();
        match &self.bar {
            Some(b) => {
                b.set_position(elapsed.min(self.budget_s) as u64);
                b.set_message(msg);
            }
            None => {
                if self.last_line.elapsed() >= Duration::from_secs(10) {
                    println!("[{elapsed:7.0} s] {msg}");
                    self.last_line = Instant::now();
                }
            }
        }
    }

    fn message(&self) -> String {
        let f = |v: &Option<serde_json::Value>, k: &str| v.as_ref().and_then(|v| v.get(k)).and_then(|x| x.as_f64());
        let mut s = match f(&self.last_train, "update") {
            Some(u) => format!(
                "upd {u:.0} | {:.0} upd/s | {:.0} tr/s | cost {:.4}",
                f(&self.last_train, "updates_per_s").unwrap_or(0.0),
                f(&self.last_train, "transitions_per_s").unwrap_or(0.0),
                f(&self.last_train, "mean_cost").unwrap_or(f64::NAN)
            ),
            None => "waiting for the learner (filling the replay buffer)".to_string(),
        };
        if let Some(c) = f(&self.last_val, "val_tracking_error") {
            s += &format!(" | val err {c:.4}");
            if let Some(q) = f(&self.last_val, "val_nrmse_q_pct") {
                s += &format!(" q {q:.2}%");
            }
            if let Some(r) = f(&self.last_val, "val_nrmse_r_pct") {
                s += &format!(" r {r:.2}%");
            }
        }
        s
    }

    /// The message once training stopped: the learner logs a train line every so many updates and stops between
    /// two, so the update count is its last checkpoint's where that is later (a fuzz of the CLI, 2026-11-30: the
    /// last line said 7507 updates where 7671 were made).
    fn final_message(&mut self) -> String {
        let run_dir = self.path.parent().unwrap_or(Path::new("."));
        if let (Some((_, saved)), Some(serde_json::Value::Object(train))) =
            (trained_so_far(run_dir), self.last_train.as_mut())
        {
            if train.get("update").and_then(|u| u.as_u64()).is_some_and(|logged| logged < saved) {
                train.insert("update".into(), saved.into());
            }
        }
        self.message()
    }

    fn finish(&mut self) {
        let msg = self.final_message();
        if let Some(b) = &self.bar {
            b.finish_with_message(msg);
        } else {
            println!("{msg}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_stamp_is_civil_time() {
        assert_eq!(utc_stamp(0), "19700101-000000");
        // 2026-11-22 01:50:44 UTC.
        assert_eq!(utc_stamp(1_795_312_244), "20261122-015044");
    }

    #[test]
    fn the_last_progress_line_counts_the_updates_of_the_final_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let line = |u: u64| format!("{{\"kind\":\"train\",\"update\":{u},\"updates_per_s\":250.0}}\n");
        std::fs::write(dir.path().join("metrics.jsonl"), line(7000) + &line(7507)).unwrap();
        let mut p = Progress::new(dir.path(), 60.0);
        p.update();
        assert!(p.final_message().starts_with("upd 7507 "), "{}", p.message());
        let step = dir.path().join("checkpoints/step-7671");
        std::fs::create_dir_all(&step).unwrap();
        std::fs::write(dir.path().join("checkpoints/LATEST"), "step-7671\n").unwrap();
        std::fs::write(step.join("meta.json"), r#"{"trained_s": 60.1, "update_step": 7671}"#).unwrap();
        assert!(p.final_message().starts_with("upd 7671 "), "{}", p.message());
        // An older leg's checkpoint never lowers what this leg logged.
        std::fs::write(step.join("meta.json"), r#"{"trained_s": 30.0, "update_step": 4000}"#).unwrap();
        let mut q = Progress::new(dir.path(), 60.0);
        q.update();
        assert!(q.final_message().starts_with("upd 7507 "), "{}", q.message());
    }

    #[test]
    fn program_lines_match_the_process_contract() {
        let p = program(Role::Actor(3), Path::new("/b"), Path::new("runs/x"), false);
        assert_eq!(p.exe, PathBuf::from("/b/bcal-actor"));
        assert_eq!(p.args, vec!["--run", "runs/x", "--actor-id", "3"]);
        let l = program(Role::Learner, Path::new("/b"), Path::new("runs/x"), true);
        assert_eq!(l.args, vec!["--run", "runs/x", "--resume"]);
    }
}
