//! The learner process loop (its design note is this header): load or resume the
//! LAC learner, publish its weights at once, then
//!
//! 1. keep [`PREFETCH`] batch requests open at the replay (the next batch is sampled while an update
//!    runs; the replay holds a request until its rate limiter admits it),
//! 2. take a batch -> `lac.update` (zero-copy: the batch is read straight from shared memory),
//! 3. every `learner.weights_every` updates publish the actor's weights (history 1),
//! 4. every `learner.checkpoint_every` updates checkpoint and write `policy.bcalpol`,
//! 5. every `learner.validate_every` updates run the held-out validation,
//! 6. about once a second append a `train` line to `metrics.jsonl`,
//!
//! until `learner.max_updates` or `learner.time_budget_s` (final checkpoint, policy file, validation,
//! then `learner.done`) or SIGTERM/SIGINT (checkpoint and policy file, no `learner.done`). Every way out
//! of the loop is a clean exit 0.
//!
//! Validation sees the true parameters of the test trajectories: it is evaluation, never a gradient.

use anyhow::Context;
use bcal_common::battery::BatteryModel;
use bcal_common::config::{TrainConfig, Validated};
use bcal_common::dataset::{default_cache_dir, load_or_generate, Dataset};
use bcal_common::ipc::{
    self, BatchClient, BatchPending, IpcError, Role, RunIpc, StatusSubscriber, UpdateConnections, WeightsPublisher,
    OPEN_TIMEOUT,
};
use bcal_common::mdp::{validate_policy, MdpSpec};
use bcal_common::policy::{PolicyLayout, PolicyNet};
use bcal_common::wire::{BatchRequest, ReplayCounters, WeightsHeader};
use bcal_learner::{Lac, UpdateMetrics};
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

/// Everything the loop needs besides the learner itself.
struct Ctx {
    run_dir: PathBuf,
    cfg: Validated,
    spec: MdpSpec,
    model: BatteryModel,
    ds: Dataset,
    val_trajectories: Vec<usize>,
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
        let path = self.run_dir.join("policy.bcalpol");
        lac.policy_file(self.spec.clone(), self.cfg.config.experiment)
            .save(&path)
            .with_context(|| format!("policy file {}", path.display()))?;
        Ok(())
    }

    fn validation_line(&self, lac: &Lac, log: &MetricsLog) -> anyhow::Result<Map<String, Value>> {
        let net = PolicyNet::from_flat(lac.layout().clone(), lac.actor_flat_params()).context("validation policy")?;
        let (cost, q, r) = validate_policy(&self.spec, &self.model, &self.ds, &self.val_trajectories, &net);
        let mut line = Map::new();
        line.insert("kind".into(), json!("validation"));
        line.insert("t_s".into(), json!(log.t_s()));
        line.insert("update".into(), json!(lac.updates()));
        line.insert("val_cost".into(), json!(cost));
        line.insert("val_nrmse_q_pct".into(), json!(q));
        line.insert("val_nrmse_r_pct".into(), json!(r));
        line.insert("val_trajectories".into(), json!(self.val_trajectories.len()));
        Ok(line)
    }
}

fn read_config(run_dir: &Path) -> anyhow::Result<Validated> {
    let path = run_dir.join("config.toml");
    Ok(TrainConfig::from_file(&path)?.validate()?)
}

fn read_mdp(run_dir: &Path) -> anyhow::Result<MdpSpec> {
    let path = run_dir.join("mdp.json");
    let text = std::fs::read_to_string(&path).with_context(|| {
        format!("cannot read {}; the supervisor writes it before starting the learner", path.display())
    })?;
    serde_json::from_str(&text).with_context(|| format!("{} is not an MDP description", path.display()))
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
    let spec = read_mdp(&args.run_dir)?;
    let model = BatteryModel::default();
    let (ds, _) = load_or_generate(&cfg.def, &model, &default_cache_dir()).context("dataset")?;
    cfg.check_dataset(&ds)?;
    let layout =
        PolicyLayout { obs_dim: spec.obs_dim(), act_dim: spec.act_dim(), hidden: cfg.config.lac.hidden.clone() };
    let seed = cfg.config.seed ^ ipc::fnv1a64(b"learner");
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
        false => Lac::new(&cfg, layout.clone(), seed)?,
    };
    let l = cfg.config.learner.clone();
    let batch_size = cfg.config.lac.batch_size;
    let ctx = Ctx {
        run_dir: args.run_dir.clone(),
        val_trajectories: ds.spread_test_indices(l.validate_trajectories),
        cfg,
        spec,
        model,
        ds,
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
        let line = ctx.validation_line(&lac, &log)?;
        log.write(&line)?;
    }

    let started = Instant::now();
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
                ctx.checkpoint(&lac)?;
                last_checkpoint = updates;
            }
            if l.validate_every > 0 && updates >= last_validation + l.validate_every {
                let line = ctx.validation_line(&lac, &log)?;
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
            window.drain_into(&mut line);
            log.write(&line)?;
            last_line = (Instant::now(), updates, counters.received_total);
        }

        if l.max_updates > 0 && lac.updates() >= l.max_updates {
            break Some("max_updates");
        }
        if l.time_budget_s > 0.0 && started.elapsed().as_secs_f64() >= l.time_budget_s {
            break Some("time_budget");
        }
    };

    // Open requests are abandoned: the replay sees the learner disconnect and drops them.
    drop(in_flight);
    ctx.checkpoint(&lac)?;
    let updates = lac.updates();
    match finished {
        Some(reason) => {
            ctx.publish_weights(&lac, &weights_pub)?;
            if l.validate_every > 0 && updates != last_validation {
                let line = ctx.validation_line(&lac, &log)?;
                log.write(&line)?;
            }
            let done = json!({
                "reason": reason,
                "updates": updates,
                "elapsed_s": started.elapsed().as_secs_f64(),
                "unix_time_s": ipc::unix_time_s(),
            });
            let path = args.run_dir.join("learner.done");
            ipc::write_json_atomic(&path, &done).with_context(|| format!("cannot write {}", path.display()))?;
            Ok(Outcome::Finished { reason, updates })
        }
        None => Ok(Outcome::Stopped { updates }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::config::EnvConfig;
    use bcal_common::dataset::{generate, Experiment, ExperimentDef, Grid};

    fn tiny() -> (Dataset, MdpSpec, BatteryModel) {
        let def = ExperimentDef {
            experiment: Experiment::Multi,
            q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 2 },
            r_o_ohm: Grid { start: 0.1, end: 0.2, n: 2 },
            loads_w: Grid { start: 8.0, end: 16.0, n: 9 },
            n_test_loads: 3,
            dt_s: 1.0,
            max_steps: 100_000,
        };
        let model = BatteryModel::default();
        let ds = generate(&def, &model).unwrap();
        let spec = MdpSpec::new(Experiment::Multi, &EnvConfig::default(), &ds);
        (ds, spec, model)
    }

    #[test]
    fn validation_trajectories_are_test_trajectories_spread_evenly() {
        let (ds, _, _) = tiny();
        let n_test = ds.test().count();
        assert_eq!(n_test, 12);
        let v = ds.spread_test_indices(4);
        assert_eq!(v.len(), 4);
        assert!(v.iter().all(|i| ds.def.is_test_load(ds.trajectories[*i].load_w)));
        assert!(v.windows(2).all(|w| w[0] < w[1]), "{v:?}");
        // Spread: 4 of 12 are every third test trajectory.
        let test: Vec<usize> =
            (0..ds.trajectories.len()).filter(|i| ds.def.is_test_load(ds.trajectories[*i].load_w)).collect();
        assert_eq!(v, vec![test[0], test[3], test[6], test[9]]);
        assert_eq!(ds.spread_test_indices(100).len(), 12);
    }

    #[test]
    fn validation_of_a_policy_that_outputs_the_truth_is_near_perfect() {
        // A network whose output ignores the observation: zero weights, bias = atanh(action of the truth).
        let (ds, spec, model) = tiny();
        let val = ds.spread_test_indices(1);
        let traj = &ds.trajectories[val[0]];
        let truth = spec.actions.to_action(&traj.degradation);
        let layout = PolicyLayout { obs_dim: spec.obs_dim(), act_dim: 2, hidden: vec![4] };
        let mut p = vec![0f32; layout.n_params()];
        // Mean head bias sits right after the hidden layer and the mean head's weights.
        let mean_bias = (spec.obs_dim() * 4 + 4) + 4 * 2;
        p[mean_bias] = truth[0].clamp(-0.999_999, 0.999_999).atanh();
        p[mean_bias + 1] = truth[1].clamp(-0.999_999, 0.999_999).atanh();
        let net = PolicyNet::from_flat(layout, p).unwrap();
        let (cost, q, r) = validate_policy(&spec, &model, &ds, &val, &net);
        assert!(q < 0.01 && r < 0.01, "{q} {r}");
        assert!(cost < 1e-2, "{cost}");
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
