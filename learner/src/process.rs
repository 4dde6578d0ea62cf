//! The learner process loop (its design note is this header and docs/learner.md): load or resume the
//! LAC learner, publish its weights at once, then
//!
//! 1. keep [`PREFETCH`] batch requests open at the replay (the next batch is sampled while an update
//!    runs; the replay holds a request until its rate limiter admits it),
//! 2. take a batch -> `lac.update` (zero-copy: the batch is read straight from shared memory),
//! 3. every `learner.weights_every` updates publish the actor's weights (history 1),
//! 4. every `learner.checkpoint_every` updates checkpoint and write `policy.bcalpol` (the latest weights),
//! 5. every `learner.validate_every` updates score the policy on the validation split and keep the best
//!    policy by each score (`policy.best-tracking-error.bcalpol`, `policy.best-nrmse.bcalpol`, and
//!    `policy.best.bcalpol` by `learner.select_by`): what a run delivers is its best validated policy,
//!    not whichever one was current when the budget ran out,
//! 6. set every learning rate by the schedule (`lac.lr_schedule`) at the run's progress,
//! 7. about once a second append a `train` line to `metrics.jsonl`,
//!
//! until `learner.max_updates` or `learner.time_budget_s` (final checkpoint, policy file, validation,
//! then `learner.done`) or SIGTERM/SIGINT (checkpoint and policy file, no `learner.done`). Every way out
//! of the loop is a clean exit 0. Training time and the best scores survive a restart: the time budget
//! counts seconds trained across restarts, and the best scores are read back from `metrics.jsonl`.
//!
//! The learner reads only the validation split (never training or test data). Validation reads the true
//! parameters of its trajectories for the NRMSE score: it is evaluation, never a gradient.

use crate::{Lac, UpdateMetrics};
use anyhow::Context;
use bcal_calib::env as measured_env;
use bcal_common::battery::BatteryModel;
use bcal_common::config::{SelectBy, TrainConfig, Validated};
use bcal_common::dataset::{default_cache_dir, load_or_generate, Dataset, Split};
use bcal_common::ipc::{
    self, BatchClient, BatchPending, IpcError, Role, RunIpc, StatusSubscriber, UpdateConnections, WeightsPublisher,
    OPEN_TIMEOUT,
};
use bcal_common::mdp::{validate_policy, PolicyScore};
use bcal_common::measured::{scenario, Episode};
use bcal_common::policy::{best_policy_file, PolicyLayout, PolicyNet, POLICY_BEST, POLICY_LAST};
use bcal_common::task::Task;
use bcal_common::wire::{BatchRequest, ReplayCounters, WeightsHeader};
use serde_json::{json, Map, Value};
use std::collections::VecDeque;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Batch requests kept open at the replay.
pub const PREFETCH: usize = 2;
/// Period of the `train` lines in metrics.jsonl.
const TRAIN_LINE_EVERY: Duration = Duration::from_secs(1);
/// Sleep while no batch is ready (the replay answers within its 1 ms cycle once the limiter admits).
const IDLE_WAIT: Duration = Duration::from_micros(500);

/// Arguments of the learner process.
#[derive(Clone, Debug)]
pub struct LearnerArgs {
    pub run_dir: PathBuf,
    pub resume: bool,
}

/// How the learner ended.
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    /// Reached `max_updates` or `time_budget_s` (`reason` says which); `learner.done` is written.
    Finished { reason: &'static str, updates: u64 },
    /// SIGTERM/SIGINT: checkpoint written, no `learner.done`.
    Stopped { updates: u64 },
}

/// Running means of the numeric [`UpdateMetrics`] fields over the updates of one `train` line.
#[derive(Default)]
struct MetricsWindow {
    sums: Map<String, Value>,
    updates: u64,
    quarantined_updates: u64,
}

impl MetricsWindow {
    fn add(&mut self, m: &UpdateMetrics) {
        let Ok(Value::Object(fields)) = serde_json::to_value(m) else { return };
        self.updates += 1;
        for (k, v) in fields {
            match v {
                Value::Bool(b) => self.quarantined_updates += u64::from(b),
                Value::Number(x) => {
                    let x = x.as_f64().unwrap_or(f64::NAN);
                    let s = self.sums.get(&k).and_then(Value::as_f64).unwrap_or(0.0);
                    self.sums.insert(k, json!(s + x));
                }
                _ => {}
            }
        }
    }

    /// Means (UpdateMetrics' names) and the count of quarantined updates; empties the window.
    fn drain_into(&mut self, line: &mut Map<String, Value>) {
        if self.updates > 0 {
            for (k, v) in std::mem::take(&mut self.sums) {
                line.insert(k, json!(v.as_f64().unwrap_or(f64::NAN) / self.updates as f64));
            }
        }
        // UpdateMetrics' own `quarantined` flag, summed: "quarantined" is the replay's transition count.
        line.insert("updates_quarantined".into(), json!(self.quarantined_updates));
        line.insert("updates_in_line".into(), json!(self.updates));
        self.updates = 0;
        self.quarantined_updates = 0;
    }
}

/// Appends JSON lines to metrics.jsonl; `t_s` continues after a resume.
struct MetricsLog {
    file: std::fs::File,
    path: PathBuf,
    started: Instant,
    t_offset_s: f64,
}

impl MetricsLog {
    fn open(run_dir: &Path) -> anyhow::Result<Self> {
        let path = run_dir.join("metrics.jsonl");
        // A resumed run continues the time axis of the existing log.
        let t_offset_s = std::fs::read_to_string(&path)
            .ok()
            .map(|text| {
                text.lines()
                    .filter_map(|l| serde_json::from_str::<Value>(l).ok())
                    .filter_map(|v| v.get("t_s").and_then(Value::as_f64))
                    .fold(0.0, f64::max)
            })
            .unwrap_or(0.0);
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .with_context(|| format!("cannot open {} for appending", path.display()))?;
        Ok(Self { file, path, started: Instant::now(), t_offset_s })
    }

    fn t_s(&self) -> f64 {
        self.t_offset_s + self.started.elapsed().as_secs_f64()
    }

    fn write(&mut self, line: &Map<String, Value>) -> anyhow::Result<()> {
        let mut text = serde_json::to_string(line)?;
        text.push('\n');
        self.file.write_all(text.as_bytes()).with_context(|| format!("cannot append to {}", self.path.display()))
    }
}

/// The lowest validation score seen under one selection rule, and at which update.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Best {
    score: f64,
    update: u64,
}

/// The validation data of the run's task (the learner reads no other data). One per process.
#[allow(clippy::large_enum_variant)]
enum ValidationSet {
    /// The paper task's validation split and the trajectories scored each time.
    Paper { model: BatteryModel, val: Dataset, trajectories: Vec<usize> },
    /// The measured task's validation episodes (fixed cells of the validation loads).
    Measured { episodes: Vec<Episode> },
}

impl ValidationSet {
    fn score(&self, task: &Task, net: &PolicyNet) -> PolicyScore {
        match (self, task) {
            (ValidationSet::Paper { model, val, trajectories }, Task::Paper(spec)) => {
                validate_policy(spec, model, val, trajectories, net)
            }
            (ValidationSet::Measured { episodes }, Task::Measured(spec)) => {
                measured_env::validate_policy(spec, episodes, net)
            }
            _ => unreachable!("the validation set is built for the run's task"),
        }
    }

    fn len(&self) -> usize {
        match self {
            ValidationSet::Paper { trajectories, .. } => trajectories.len(),
            ValidationSet::Measured { episodes } => episodes.len(),
        }
    }
}

/// Everything the loop needs besides the learner itself.
struct Ctx {
    run_dir: PathBuf,
    cfg: Validated,
    task: Task,
    val: ValidationSet,
    /// Best score so far under each [`SelectBy`], in `SelectBy::ALL` order.
    best: [Option<Best>; 2],
}

impl Ctx {
    fn publish_weights(&self, lac: &Lac, publisher: &WeightsPublisher) -> anyhow::Result<()> {
        let params = lac.actor_flat_params();
        let layout = lac.layout();
        let mut sample =
            publisher.loan_slice_uninit(params.len()).map_err(|e| anyhow::anyhow!("loan weights: {e:?}"))?;
        *sample.user_header_mut() = WeightsHeader {
            update_step: lac.updates(),
            layout_fingerprint: layout.fingerprint(),
            n_params: params.len() as u64,
        };
        sample.write_from_slice(&params).send().map_err(|e| anyhow::anyhow!("publish weights: {e:?}"))?;
        Ok(())
    }

    fn checkpoint(&self, lac: &Lac) -> anyhow::Result<()> {
        lac.save_checkpoint(&self.run_dir).with_context(|| {
            let latest = std::fs::read_to_string(self.run_dir.join("checkpoints/LATEST")).unwrap_or_default();
            let kept = match latest.trim() {
                "" => "no earlier checkpoint exists".to_string(),
                name => format!("the previous checkpoint {name} is kept"),
            };
            format!(
                "cannot write the checkpoint of update {} into {} (disk full or folder not writable?); {kept}",
                lac.updates(),
                self.run_dir.join("checkpoints").display()
            )
        })?;
        self.save_policy(lac, POLICY_LAST)
    }

    fn save_policy(&self, lac: &Lac, name: &str) -> anyhow::Result<()> {
        let path = self.run_dir.join(name);
        lac.policy_file(self.task.clone(), self.cfg.config.experiment)
            .save(&path)
            .with_context(|| format!("policy file {}", path.display()))
    }

    /// Scores the current policy on the validation split, keeps the best policy by each score, and
    /// returns the `validation` line for metrics.jsonl.
    fn validate(&mut self, lac: &Lac, log: &MetricsLog) -> anyhow::Result<Map<String, Value>> {
        let net = PolicyNet::from_flat(lac.layout().clone(), lac.actor_flat_params()).context("validation policy")?;
        let score = self.val.score(&self.task, &net);
        let mut line = Map::new();
        line.insert("kind".into(), json!("validation"));
        line.insert("t_s".into(), json!(log.t_s()));
        line.insert("update".into(), json!(lac.updates()));
        line.insert("val_tracking_error".into(), json!(score.tracking_error));
        line.insert("val_nrmse_q_pct".into(), json!(score.nrmse_q_pct));
        line.insert("val_nrmse_r_pct".into(), json!(score.nrmse_r_pct));
        line.insert("val_trajectories".into(), json!(self.val.len()));
        for (k, select) in SelectBy::ALL.into_iter().enumerate() {
            let s = score.by(select);
            if s.is_finite() && self.best[k].is_none_or(|b| s < b.score) {
                self.best[k] = Some(Best { score: s, update: lac.updates() });
                self.save_policy(lac, &best_policy_file(select))?;
                if select == self.cfg.config.learner.select_by {
                    self.save_policy(lac, POLICY_BEST)?;
                }
                line.insert(format!("best_{}", select.name().replace('-', "_")), json!(true));
            }
        }
        Ok(line)
    }
}

/// The best score under each selection rule among the validation lines of an existing metrics.jsonl (a
/// resumed learner keeps comparing against them).
fn best_from_log(text: &str) -> [Option<Best>; 2] {
    let mut best = [None; 2];
    for v in text.lines().filter_map(|l| serde_json::from_str::<Value>(l).ok()) {
        if v.get("kind").and_then(Value::as_str) != Some("validation") {
            continue;
        }
        let f = |k: &str| v.get(k).and_then(Value::as_f64);
        let (Some(e), Some(q), Some(r), Some(update)) = (
            f("val_tracking_error"),
            f("val_nrmse_q_pct"),
            f("val_nrmse_r_pct"),
            v.get("update").and_then(Value::as_u64),
        ) else {
            continue;
        };
        let score = PolicyScore { tracking_error: e, nrmse_q_pct: q, nrmse_r_pct: r };
        for (k, select) in SelectBy::ALL.into_iter().enumerate() {
            let s = score.by(select);
            if best[k].is_none_or(|b: Best| s < b.score) {
                best[k] = Some(Best { score: s, update });
            }
        }
    }
    best
}

/// Progress of the run in [0, 1]: the larger of the update and time fractions of the budget.
fn progress(l: &bcal_common::config::LearnerConfig, updates: u64, trained_s: f64) -> f64 {
    let by_updates = if l.max_updates > 0 { updates as f64 / l.max_updates as f64 } else { 0.0 };
    let by_time = if l.time_budget_s > 0.0 { trained_s / l.time_budget_s } else { 0.0 };
    by_updates.max(by_time).min(1.0)
}

fn read_config(run_dir: &Path) -> anyhow::Result<Validated> {
    let path = run_dir.join("config.toml");
    Ok(TrainConfig::from_file(&path)?.validate()?)
}

fn read_task(run_dir: &Path) -> anyhow::Result<Task> {
    let path = run_dir.join("mdp.json");
    let text = std::fs::read_to_string(&path).with_context(|| {
        format!("cannot read {}; the supervisor writes it before starting the learner", path.display())
    })?;
    Task::from_json(&text).with_context(|| format!("{} is not a task description", path.display()))
}

/// Newest replay status, if any arrived.
fn poll_status(sub: &StatusSubscriber, last: &mut ReplayCounters) -> anyhow::Result<()> {
    while let Some(s) = sub.receive().map_err(|e| anyhow::anyhow!("receive status: {e:?}"))? {
        *last = s.payload().counters;
    }
    Ok(())
}

fn request_batch(client: &BatchClient, batch_size: usize, seq: u64) -> anyhow::Result<BatchPending> {
    let request = client.loan_uninit().map_err(|e| anyhow::anyhow!("loan batch request: {e:?}"))?;
    request
        .write_payload(BatchRequest { batch_size: batch_size as u32, _reserved: 0, request_seq: seq })
        .send()
        .map_err(|e| anyhow::anyhow!("send batch request: {e:?}"))
}

/// Runs the learner until it finishes or is stopped.
pub fn run(args: &LearnerArgs) -> anyhow::Result<Outcome> {
    // The node first: from here on SIGTERM/SIGINT are flags the loop sees, not an abrupt exit.
    let (node, _) = ipc::create_node("bcal-learner")?;
    let cfg = read_config(&args.run_dir)?;
    let task = read_task(&args.run_dir)?;
    let val = match &task {
        Task::Paper(_) => {
            let (val, _) =
                load_or_generate(&cfg.def, &BatteryModel::default(), &default_cache_dir(), Split::Validation)
                    .context("validation set")?;
            cfg.check_dataset(&val)?;
            let trajectories = val.spread_indices(cfg.config.learner.validate_trajectories);
            ValidationSet::Paper { model: BatteryModel::default(), val, trajectories }
        }
        Task::Measured(m) => {
            let n = match cfg.config.learner.validate_trajectories {
                0 => m.scenario.validation_episodes,
                k => k.min(m.scenario.validation_episodes),
            };
            let episodes = scenario::episode_set(&m.scenario, Split::Validation, m.scenario.validation_episodes)
                .context("validation episodes")?;
            let mut episodes: Vec<_> = episodes.into_iter().take(n).collect();
            // A real cell's recorded validation discharges (the last training cycles) count too.
            if let Some(p) = &m.scenario.recorded.path {
                let set = scenario::RecordedSet::load(std::path::Path::new(p)).map_err(anyhow::Error::msg)?;
                episodes.extend(set.validation);
            }
            ValidationSet::Measured { episodes }
        }
    };
    let layout =
        PolicyLayout { obs_dim: task.obs_dim(), act_dim: task.act_dim(), hidden: cfg.config.lac.hidden.clone() };
    let seed = cfg.config.seed ^ bcal_common::hash::fnv1a64(b"learner");
    let mut lac = match args.resume {
        true => match Lac::load_latest(&cfg, layout.clone(), &args.run_dir).context("--resume")? {
            Some(lac) => lac,
            None => {
                // No LATEST: fine before the first checkpoint, but never silently start over on top of
                // step folders (LATEST was deleted or lost).
                let dir = args.run_dir.join("checkpoints");
                let mut steps: Vec<String> = std::fs::read_dir(&dir)
                    .map(|rd| rd.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect())
                    .unwrap_or_default();
                steps.retain(|n| n.starts_with("step-"));
                steps.sort();
                if let Some(newest) = steps.last() {
                    anyhow::bail!(
                        "--resume: {} has step folders ({}) but no LATEST; write the one to resume into it \
                         (e.g. `echo {newest} > {}`) or move the folder away to start over",
                        dir.display(),
                        steps.join(", "),
                        dir.join("LATEST").display()
                    );
                }
                Lac::new(&cfg, layout.clone(), seed)?
            }
        },
        false => {
            let mut lac = Lac::new(&cfg, layout.clone(), seed)?;
            // The correction design starts at zero action: the tuned filter.
            if task.measured().is_some_and(|m| m.design == bcal_common::measured::env::Design::UkfCorrection) {
                lac.zero_mean_head()?;
            }
            lac
        }
    };
    let l = cfg.config.learner.clone();
    let batch_size = cfg.config.lac.batch_size;
    let mut ctx = Ctx {
        run_dir: args.run_dir.clone(),
        best: best_from_log(&std::fs::read_to_string(args.run_dir.join("metrics.jsonl")).unwrap_or_default()),
        cfg,
        task,
        val,
    };

    let run = RunIpc::new(&args.run_dir, &ctx.cfg)?;
    let open = Role::Open { timeout: OPEN_TIMEOUT };
    let services =
        (|| Ok::<_, IpcError>((run.weights(&node, open)?, run.batches(&node, open)?, run.status(&node, open)?)))();
    let (weights, batches, status) = match services {
        Ok(s) => s,
        Err(IpcError::Interrupted) => return Ok(Outcome::Stopped { updates: lac.updates() }),
        Err(e) => return Err(e.into()),
    };
    let weights_pub = run.weights_publisher(&weights, layout.n_params())?;
    let client = run.batch_client(&batches)?;
    let status_sub = run.status_subscriber(&status)?;

    // Actors wait for these: publish before anything slow.
    ctx.publish_weights(&lac, &weights_pub)?;
    let mut log = MetricsLog::open(&args.run_dir)?;
    // One line per (re)start: where the update counter begins, so a restart shows in the log.
    let mut start = Map::new();
    start.insert("kind".into(), json!("start"));
    start.insert("t_s".into(), json!(log.t_s()));
    start.insert("update".into(), json!(lac.updates()));
    start.insert("resumed".into(), json!(args.resume && lac.updates() > 0));
    log.write(&start)?;
    if l.validate_every > 0 {
        let line = ctx.validate(&lac, &log)?;
        log.write(&line)?;
    }

    let started = Instant::now();
    let trained_before_s = lac.trained_s();
    let lac_cfg = ctx.cfg.config.lac.clone();
    let mut in_flight: VecDeque<BatchPending> = VecDeque::new();
    let mut request_seq = 0u64;
    let mut counters = ReplayCounters::default();
    let mut window = MetricsWindow::default();
    let mut last_line = (Instant::now(), lac.updates(), 0u64);
    let mut last_published = lac.updates();
    let mut last_checkpoint = lac.updates();
    let mut last_validation = lac.updates();
    let mut batches_lost = 0u64;
    let mut idle = false;
    let finished: Option<&'static str> = loop {
        if node.wait(if idle { IDLE_WAIT } else { Duration::ZERO }).is_err() {
            break None;
        }
        idle = true;
        // Late or restarted actors get the newest weights from history.
        let _ = weights_pub.update_connections();
        poll_status(&status_sub, &mut counters)?;

        while in_flight.len() < PREFETCH {
            in_flight.push_back(request_batch(&client, batch_size, request_seq)?);
            request_seq += 1;
        }
        let (response, replay_gone) = match in_flight.front() {
            // Receive first: the replay drops its side of a request once it answered, so "disconnected"
            // only means "lost" when no response is waiting.
            Some(p) => match p.receive().map_err(|e| anyhow::anyhow!("receive batch: {e:?}"))? {
                Some(r) => (Some(r), false),
                None => (None, !p.is_connected()),
            },
            None => (None, false),
        };
        if replay_gone {
            // The replay went away with our request; ask again (a restarted replay answers).
            in_flight.pop_front();
            batches_lost += 1;
        }
        if let Some(batch) = response {
            idle = false;
            counters = batch.user_header().counters;
            let transitions = batch.payload();
            if transitions.len() != batch_size {
                anyhow::bail!("the replay served {} transitions for a batch of {batch_size}", transitions.len());
            }
            let trained_s = trained_before_s + started.elapsed().as_secs_f64();
            lac.set_lr_factor(lac_cfg.lr_factor(progress(&l, lac.updates(), trained_s)));
            let metrics = lac.update(transitions)?;
            drop(batch);
            in_flight.pop_front();
            window.add(&metrics);

            let updates = lac.updates();
            if updates >= last_published + l.weights_every {
                ctx.publish_weights(&lac, &weights_pub)?;
                last_published = updates;
            }
            if updates >= last_checkpoint + l.checkpoint_every {
                lac.set_trained_s(trained_before_s + started.elapsed().as_secs_f64());
                ctx.checkpoint(&lac)?;
                last_checkpoint = updates;
            }
            if l.validate_every > 0 && updates >= last_validation + l.validate_every {
                let line = ctx.validate(&lac, &log)?;
                log.write(&line)?;
                last_validation = updates;
            }
        }

        if last_line.0.elapsed() >= TRAIN_LINE_EVERY {
            let dt = last_line.0.elapsed().as_secs_f64();
            let updates = lac.updates();
            let mut line = Map::new();
            line.insert("kind".into(), json!("train"));
            line.insert("t_s".into(), json!(log.t_s()));
            line.insert("update".into(), json!(updates));
            line.insert("updates_per_s".into(), json!((updates - last_line.1) as f64 / dt));
            line.insert("transitions_inserted".into(), json!(counters.inserted_total));
            line.insert("transitions_received".into(), json!(counters.received_total));
            line.insert(
                "transitions_per_s".into(),
                json!(counters.received_total.saturating_sub(last_line.2) as f64 / dt),
            );
            line.insert("quarantined".into(), json!(counters.quarantined_total));
            line.insert("dropped".into(), json!(counters.dropped_total));
            line.insert("replay_size".into(), json!(counters.size));
            line.insert("batches_lost".into(), json!(batches_lost));
            line.insert("lr_factor".into(), json!(lac.lr_factor()));
            window.drain_into(&mut line);
            log.write(&line)?;
            last_line = (Instant::now(), updates, counters.received_total);
        }

        if l.max_updates > 0 && lac.updates() >= l.max_updates {
            break Some("max_updates");
        }
        if l.time_budget_s > 0.0 && trained_before_s + started.elapsed().as_secs_f64() >= l.time_budget_s {
            break Some("time_budget");
        }
    };

    // Open requests are abandoned: the replay sees the learner disconnect and drops them.
    drop(in_flight);
    lac.set_trained_s(trained_before_s + started.elapsed().as_secs_f64());
    ctx.checkpoint(&lac)?;
    let updates = lac.updates();
    match finished {
        Some(reason) => {
            ctx.publish_weights(&lac, &weights_pub)?;
            if l.validate_every > 0 && updates != last_validation {
                let line = ctx.validate(&lac, &log)?;
                log.write(&line)?;
            }
            let best: Map<String, Value> = SelectBy::ALL
                .iter()
                .zip(&ctx.best)
                .filter_map(|(s, b)| b.map(|b| (s.name().to_string(), json!({"score": b.score, "update": b.update}))))
                .collect();
            let done = json!({
                "reason": reason,
                "updates": updates,
                "elapsed_s": started.elapsed().as_secs_f64(),
                "trained_s": lac.trained_s(),
                "select_by": ctx.cfg.config.learner.select_by.name(),
                "best_validation": best,
                "unix_time_s": ipc::unix_time_s(),
            });
            let path = args.run_dir.join("learner.done");
            bcal_common::fsutil::write_json_atomic(&path, &done)
                .with_context(|| format!("cannot write {}", path.display()))?;
            Ok(Outcome::Finished { reason, updates })
        }
        None => Ok(Outcome::Stopped { updates }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::config::EnvConfig;
    use bcal_common::dataset::{generate, Experiment, ExperimentDef, Grid, ValidationDef};
    use bcal_common::mdp::MdpSpec;

    /// A small validation split and the MDP of its experiment's (small) training split.
    fn tiny() -> (Dataset, MdpSpec, BatteryModel) {
        let def = ExperimentDef {
            experiment: Experiment::Multi,
            q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 2 },
            r_o_ohm: Grid { start: 0.1, end: 0.2, n: 2 },
            loads_w: Grid { start: 8.0, end: 16.0, n: 9 },
            n_test_loads: 3,
            validation: ValidationDef {
                loads_w: vec![13.5],
                q_mobile_c: Grid { start: 4500.0, end: 6500.0, n: 3 },
                r_o_ohm: Grid::single(0.15),
            },
            dt_s: 1.0,
            max_steps: 100_000,
        };
        let model = BatteryModel::default();
        let train = generate(&def, &model, Split::Train).unwrap();
        let val = generate(&def, &model, Split::Validation).unwrap();
        let spec = MdpSpec::new(Experiment::Multi, &EnvConfig::default(), &train);
        (val, spec, model)
    }

    #[test]
    fn validation_of_a_policy_that_outputs_the_truth_is_near_perfect() {
        // A network whose output ignores the observation: zero weights, bias = atanh(action of the truth).
        let (val, spec, model) = tiny();
        let idx = val.spread_indices(1);
        let traj = &val.trajectories[idx[0]];
        let truth = spec.actions.to_action(&traj.degradation);
        let layout = PolicyLayout { obs_dim: spec.obs_dim(), act_dim: 2, hidden: vec![4] };
        let mut p = vec![0f32; layout.n_params()];
        // Mean head bias sits right after the hidden layer and the mean head's weights.
        let mean_bias = (spec.obs_dim() * 4 + 4) + 4 * 2;
        p[mean_bias] = truth[0].clamp(-0.999_999, 0.999_999).atanh();
        p[mean_bias + 1] = truth[1].clamp(-0.999_999, 0.999_999).atanh();
        let net = PolicyNet::from_flat(layout, p).unwrap();
        let s = validate_policy(&spec, &model, &val, &idx, &net);
        let vs = ValidationSet::Paper { model, val: val.clone(), trajectories: idx.clone() };
        assert_eq!(vs.score(&Task::Paper(spec.clone()), &net), s);
        assert!(s.nrmse_q_pct < 0.01 && s.nrmse_r_pct < 0.01, "{s:?}");
        assert!(s.tracking_error < 1e-2, "{s:?}");
    }

    #[test]
    fn best_scores_are_read_back_from_the_log_and_progress_follows_the_budget() {
        let log = "{\"kind\":\"train\",\"update\":5}\n\
                   {\"kind\":\"validation\",\"update\":10,\"val_tracking_error\":0.5,\"val_nrmse_q_pct\":4.0,\"val_nrmse_r_pct\":2.0}\n\
                   {\"kind\":\"validation\",\"update\":20,\"val_tracking_error\":0.4,\"val_nrmse_q_pct\":5.0,\"val_nrmse_r_pct\":3.0}\n\
                   not json\n";
        let best = best_from_log(log);
        assert_eq!(best[0], Some(Best { score: 0.4, update: 20 }), "tracking error");
        assert_eq!(best[1], Some(Best { score: 3.0, update: 10 }), "mean NRMSE");
        assert_eq!(best_from_log(""), [None, None]);
        let mut l =
            bcal_common::config::LearnerConfig { max_updates: 1000, time_budget_s: 100.0, ..Default::default() };
        assert_eq!(progress(&l, 500, 10.0), 0.5);
        assert_eq!(progress(&l, 100, 80.0), 0.8);
        assert_eq!(progress(&l, 5000, 0.0), 1.0);
        l.max_updates = 0;
        assert_eq!(progress(&l, 5000, 25.0), 0.25);
    }

    #[test]
    fn metrics_window_averages_and_counts_quarantined_updates() {
        let m = |c: f64, q: bool| UpdateMetrics {
            critic_loss: c,
            lyapunov_decrease: 0.0,
            actor_loss: 0.0,
            lambda_loss: 0.0,
            beta_loss: 0.0,
            lambda: 1.0,
            beta: 1.0,
            entropy: 0.0,
            mean_cost: 2.0,
            lyapunov_value: 0.0,
            quarantined: q,
        };
        let mut w = MetricsWindow::default();
        w.add(&m(1.0, false));
        w.add(&m(3.0, true));
        let mut line = Map::new();
        w.drain_into(&mut line);
        assert_eq!(line["critic_loss"], json!(2.0));
        assert_eq!(line["mean_cost"], json!(2.0));
        assert_eq!(line["updates_quarantined"], json!(1));
        assert_eq!(line["updates_in_line"], json!(2));
        assert!(line.get("quarantined").is_none());
        let mut empty = Map::new();
        w.drain_into(&mut empty);
        assert!(empty.get("critic_loss").is_none());
    }
}
