//! The actor process loop: open the run's services, wait for the replay's status and the learner's first
//! weights, then step the environments and publish their transitions in messages of
//! `actors.publish_batch`, picking up newer weights between steps without ever blocking on them.
//!
//! Backpressure: the replay publishes its rate limiter's verdict (history 1, every 10 ms); while it says
//! inserts are too far ahead of the learner's samples, or no status arrived for [`STATUS_STALE`] (no
//! replay), the actor sleeps in `node.wait` instead of producing data nobody reads. A publish that
//! finds the replay's buffer full waits inside iceoryx2 (bounded, see `ipc::transition_publisher`), and
//! a message that still cannot be delivered is counted as `undelivered_transitions` (the replay counts it
//! too, as `dropped_total`).
//!
//! Counters go to `DIR/actors/actor-K.json` every [`REPORT_EVERY`] and at exit.

use crate::envs::{actor_seed, ActorEnvs};
use bcal_common::battery::BatteryModel;
use bcal_common::config::{ConfigError, TrainConfig, Validated};
use bcal_common::dataset::{default_cache_dir, load_or_generate, DatasetError, Split};
use bcal_common::ipc::{self, IpcError, Role, RunIpc, StatusSubscriber, WeightsSubscriber, OPEN_TIMEOUT};
use bcal_common::policy::{PolicyLayout, PolicyNet, Scratch};
use bcal_common::task::Task;
use bcal_common::wire::{monotonic_ns, ReplayStatus, Transition, TransitionBatchHeader};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Sleep of one idle round (no weights yet, throttled, or no replay).
const IDLE_WAIT: Duration = Duration::from_millis(2);
/// A status older than this means the replay is gone: stop publishing until it is back.
pub const STATUS_STALE: Duration = Duration::from_secs(1);
/// Counters file refresh period.
pub const REPORT_EVERY: Duration = Duration::from_secs(2);

#[derive(Debug, thiserror::Error)]
pub enum ActorError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Ipc(#[from] IpcError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("cannot read the MDP {path}: {why}; the supervisor writes it before starting actors")]
    Mdp { path: PathBuf, why: String },
    #[error("actor id {id} is out of range: the run has {count} actors")]
    ActorId { id: u32, count: usize },
    #[error("cannot write {path}: {source}")]
    Write { path: PathBuf, source: std::io::Error },
    #[error("iceoryx2 {what}: {detail}")]
    Transport { what: &'static str, detail: String },
    #[error("{0}")]
    Recorded(String),
}

fn transport(what: &'static str) -> impl FnOnce(&dyn std::fmt::Debug) -> ActorError {
    move |e| ActorError::Transport { what, detail: format!("{e:?}") }
}

/// What `DIR/actors/actor-K.json` holds.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ActorReport {
    pub actor_id: u32,
    pub pid: u32,
    /// This incarnation's epoch (in every message header).
    pub epoch: u64,
    /// "starting", "waiting_for_weights", "running", "stopped".
    pub state: &'static str,
    pub uptime_s: f64,
    pub updated_unix_s: f64,
    /// Transitions delivered to the replay.
    pub published_transitions: u64,
    pub published_messages: u64,
    /// Transitions whose message could not be delivered (replay buffer full past the give-up time, or no
    /// replay connected).
    pub undelivered_transitions: u64,
    /// Transitions generated (published + undelivered + at most one partial message at exit).
    pub generated_transitions: u64,
    /// Learner update step of the weights in use (0 = none yet).
    pub weights_version: u64,
    pub weights_received: u64,
    /// Weight messages refused (layout fingerprint or size differs from this run's network, or
    /// non-finite values).
    pub weights_refused: u64,
    /// Seconds spent waiting because the replay's limiter said inserts are ahead (or no replay).
    pub throttled_s: f64,
    pub waiting_for_weights_s: f64,
    /// Published transitions per second of uptime since the first weights arrived.
    pub transitions_per_s: f64,
}

/// Arguments of one actor process.
#[derive(Clone, Debug)]
pub struct ActorArgs {
    pub run_dir: PathBuf,
    pub actor_id: u32,
}

/// Reads the run's task from `DIR/mdp.json` (written by the supervisor).
pub fn read_task(run_dir: &Path) -> Result<Task, ActorError> {
    let path = run_dir.join("mdp.json");
    let text =
        std::fs::read_to_string(&path).map_err(|e| ActorError::Mdp { path: path.clone(), why: e.to_string() })?;
    Task::from_json(&text).map_err(|e| ActorError::Mdp { path, why: e.to_string() })
}

pub fn read_config(run_dir: &Path) -> Result<Validated, ConfigError> {
    TrainConfig::from_file(&run_dir.join("config.toml"))?.validate()
}

/// Runs one actor until a termination signal; returns the final report (also written to disk).
pub fn run(args: &ActorArgs) -> Result<ActorReport, ActorError> {
    let started = Instant::now();
    let (node, _) = ipc::create_node(&format!("bcal-actor-{}", args.actor_id))?;
    let cfg = read_config(&args.run_dir)?;
    if args.actor_id as usize >= cfg.actor_count {
        return Err(ActorError::ActorId { id: args.actor_id, count: cfg.actor_count });
    }
    let task = read_task(&args.run_dir)?;
    // Paper task: the training split only (an actor never holds validation or test data). Measured task:
    // no data at all, the actor simulates its training cells.
    let train = match &task {
        Task::Paper(_) => {
            let (ds, _) = load_or_generate(&cfg.def, &BatteryModel::default(), &default_cache_dir(), Split::Train)?;
            cfg.check_dataset(&ds)?;
            Some(ds)
        }
        Task::Measured(_) => None,
    };

    let report_dir = args.run_dir.join("actors");
    std::fs::create_dir_all(&report_dir).map_err(|source| ActorError::Write { path: report_dir.clone(), source })?;
    let report_path = report_dir.join(format!("actor-{}.json", args.actor_id));
    let epoch = bcal_common::hash::fnv1a64(format!("{}:{}", std::process::id(), ipc::unix_time_s()).as_bytes());
    let mut report = ActorReport {
        actor_id: args.actor_id,
        pid: std::process::id(),
        epoch,
        state: "starting",
        ..ActorReport::default()
    };
    let write = |r: &mut ActorReport| {
        r.uptime_s = started.elapsed().as_secs_f64();
        r.updated_unix_s = ipc::unix_time_s();
        bcal_common::fsutil::write_json_atomic(&report_path, r)
            .map_err(|source| ActorError::Write { path: report_path.clone(), source })
    };
    write(&mut report)?;

    let run = RunIpc::new(&args.run_dir, &cfg)?;
    let open = Role::Open { timeout: OPEN_TIMEOUT };
    let services =
        (|| Ok::<_, IpcError>((run.transitions(&node, open)?, run.weights(&node, open)?, run.status(&node, open)?)))();
    let (transitions, weights, status) = match services {
        Ok(s) => s,
        // Stopped before the replay was up: a clean exit, not an error.
        Err(IpcError::Interrupted) => {
            report.state = "stopped";
            write(&mut report)?;
            return Ok(report);
        }
        Err(e) => return Err(e.into()),
    };
    let publisher = run.transition_publisher(&transitions)?;
    let weights_sub = run.weights_subscriber(&weights)?;
    let status_sub = run.status_subscriber(&status)?;

    let layout =
        PolicyLayout { obs_dim: task.obs_dim(), act_dim: task.act_dim(), hidden: cfg.config.lac.hidden.clone() };
    let seeds =
        (actor_seed(cfg.config.seed, args.actor_id, "env"), actor_seed(cfg.config.seed, args.actor_id, "noise"));
    let n_envs = cfg.config.actors.envs_per_actor;
    let mut envs = match (task, train) {
        (Task::Paper(spec), Some(train)) => {
            ActorEnvs::paper(spec, BatteryModel::default(), train, n_envs, seeds, Scratch::new(&layout))
        }
        (Task::Measured(spec), _) => {
            let recorded = match &spec.scenario.recorded.path {
                Some(p) => {
                    bcal_common::measured::scenario::RecordedSet::load(std::path::Path::new(p))
                        .map_err(ActorError::Recorded)?
                        .train
                }
                None => Vec::new(),
            };
            ActorEnvs::measured(spec, recorded, n_envs, seeds, Scratch::new(&layout))
        }
        (Task::Paper(_), None) => unreachable!("the paper task loads its training split above"),
    };
    let publish_batch = run.limits.publish_batch;
    let mut pending: Vec<Transition> = Vec::with_capacity(publish_batch + envs.len());
    let mut policy: Option<PolicyNet> = None;
    let mut latest_status: Option<(ReplayStatus, Instant)> = None;
    let mut seq = 0u64;
    let mut attempted = 0u64;
    let mut first_weights_at: Option<Instant> = None;
    let mut last_report = Instant::now();
    let mut idle: Option<&'static str> = None;
    let mut last_round = Instant::now();
    report.state = "waiting_for_weights";

    loop {
        let cycle = if idle.is_some() { IDLE_WAIT } else { Duration::ZERO };
        if node.wait(cycle).is_err() {
            break;
        }
        // Account the time the previous round spent idle.
        let round = last_round.elapsed().as_secs_f64();
        last_round = Instant::now();
        match idle {
            Some("weights") => report.waiting_for_weights_s += round,
            Some(_) => report.throttled_s += round,
            None => {}
        }
        idle = None;

        poll_weights(&weights_sub, &layout, &mut policy, &mut report)?;
        if let Some(s) = poll_status(&status_sub)? {
            latest_status = Some((s, Instant::now()));
        }
        if last_report.elapsed() >= REPORT_EVERY {
            report.transitions_per_s = rate(report.published_transitions, first_weights_at);
            write(&mut report)?;
            last_report = Instant::now();
        }

        let Some(net) = policy.as_ref() else {
            idle = Some("weights");
            continue;
        };
        if first_weights_at.is_none() {
            first_weights_at = Some(Instant::now());
            report.state = "running";
        }
        let replay_says_go = match &latest_status {
            Some((s, at)) => s.inserts_allowed != 0 && at.elapsed() < STATUS_STALE,
            None => false,
        };
        if !replay_says_go {
            idle = Some("throttled");
            continue;
        }

        envs.step(net, &mut pending);
        report.generated_transitions += envs.len() as u64;
        while pending.len() >= publish_batch {
            let header = TransitionBatchHeader {
                actor_id: args.actor_id,
                len: publish_batch as u32,
                epoch,
                seq,
                published_before: attempted,
                weights_version: report.weights_version,
                sent_mono_ns: 0,
            };
            let sample = publisher.loan_slice_uninit(publish_batch).map_err(|e| transport("loan transitions")(&e))?;
            let mut sample = sample.write_from_slice(&pending[..publish_batch]);
            // Stamped last, so the latency the replay sees is transport only.
            *sample.user_header_mut() = TransitionBatchHeader { sent_mono_ns: monotonic_ns(), ..header };
            match sample.send() {
                Ok(receivers) if receivers > 0 => {
                    report.published_transitions += publish_batch as u64;
                    report.published_messages += 1;
                }
                // No replay connected, or its buffer stayed full past the give-up time.
                Ok(_) | Err(_) => report.undelivered_transitions += publish_batch as u64,
            }
            seq += 1;
            attempted += publish_batch as u64;
            pending.drain(..publish_batch);
        }
    }

    report.state = "stopped";
    report.transitions_per_s = rate(report.published_transitions, first_weights_at);
    write(&mut report)?;
    Ok(report)
}

fn rate(n: u64, since: Option<Instant>) -> f64 {
    match since {
        Some(t) if t.elapsed().as_secs_f64() > 0.0 => n as f64 / t.elapsed().as_secs_f64(),
        _ => 0.0,
    }
}

/// Takes every weights message that arrived (normally at most one) and installs the valid ones.
fn poll_weights(
    sub: &WeightsSubscriber,
    layout: &PolicyLayout,
    policy: &mut Option<PolicyNet>,
    report: &mut ActorReport,
) -> Result<(), ActorError> {
    while let Some(sample) = sub.receive().map_err(|e| transport("receive weights")(&e))? {
        report.weights_received += 1;
        let h = *sample.user_header();
        let params = sample.payload();
        let shape_ok = h.layout_fingerprint == layout.fingerprint()
            && h.n_params as usize == layout.n_params()
            && params.len() == layout.n_params();
        let installed = shape_ok
            && match policy {
                Some(net) => net.set_params(params).is_ok(),
                None => match PolicyNet::from_flat(layout.clone(), params.to_vec()) {
                    Ok(net) => {
                        *policy = Some(net);
                        true
                    }
                    Err(_) => false,
                },
            };
        if installed {
            report.weights_version = h.update_step;
        } else {
            report.weights_refused += 1;
        }
    }
    Ok(())
}

/// The newest status message, if any arrived.
fn poll_status(sub: &StatusSubscriber) -> Result<Option<ReplayStatus>, ActorError> {
    let mut newest = None;
    while let Some(sample) = sub.receive().map_err(|e| transport("receive status")(&e))? {
        newest = Some(*sample.payload());
    }
    Ok(newest)
}
