//! The one place where bcal's iceoryx2 services are declared: their names, payloads and limits, and the
//! port builders every process uses. Replay, actors, learner, tests and benchmarks all call these
//! functions, so a limit is stated once and a service can never be opened with a different shape.
//!
//! The transport stays behind this module (DESIGN "Beyond one host"): processes see typed ports and the
//! re-exported [`iceoryx2`] crate, never a service name string or a limit of their own.
//!
//! | service (`bcal/v{WIRE_VERSION}/{run}/…`) | pattern | payload | history | buffer | max ports | overflow |
//! | --- | --- | --- | --- | --- | --- | --- |
//! | `transitions` | pub/sub | `[Transition]` ≤ publish_batch + [`TransitionBatchHeader`] | 0 | [`TRANSITION_BUFFER_MESSAGES`] per actor | pub: actors + [`RESTART_SLACK`], sub: [`MAX_TAPS`] | none: the publisher waits up to [`PUBLISH_GIVE_UP`], then fails and the loss is counted |
//! | `weights` | pub/sub | `[f32]` = n_params + [`WeightsHeader`] | 1 | 2 | pub: [`MAX_LEARNERS`], sub: actors + slack + taps | newest wins (old weights are worthless) |
//! | `status` | pub/sub | [`ReplayStatus`] | 1 | 2 | pub: [`MAX_REPLAYS`], sub: actors + slack + taps | newest wins |
//! | `batches` | request-response | [`BatchRequest`] -> `[Transition]` = batch_size + [`BatchHeader`] | - | [`MAX_BATCH_REQUESTS_IN_FLIGHT`] | servers: [`MAX_REPLAYS`], clients: [`MAX_LEARNERS`] | none (at most that many requests are ever open) |
//!
//! `{run}` is an FNV-1a hash of the canonical run folder, so parallel runs (and parallel tests) never
//! share a service. The replay creates every service (`open_or_create`, so a restarted replay re-joins
//! services that live actors keep alive); everyone else opens them, retrying until the replay made them.
//! Every process starts by removing the stale resources of dead nodes (a `kill -9`ed earlier run), and
//! the replay repeats that periodically so slots of crashed actors are freed for their restarts.
//!
//! Never here: any printing, any process exit, any training logic.

pub use iceoryx2;
/// Publishers deliver history (the newest weights, the newest status) to subscribers that joined since
/// their last send only when they update their connections: call this in every loop round.
pub use iceoryx2::port::update_connections::UpdateConnections;

use crate::config::Validated;
use crate::hash::fnv1a64;
use crate::wire::{
    BatchHeader, BatchRequest, ReplayStatus, Transition, TransitionBatchHeader, WeightsHeader, MAX_PUBLISH_BATCH,
    WIRE_VERSION,
};
use iceoryx2::node::NodeWaitFailure;
use iceoryx2::port::BackpressureAction;
use iceoryx2::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The iceoryx2 service variant: inter-process, shared memory.
pub type Service = ipc::Service;
pub type Node = iceoryx2::node::Node<Service>;

pub type TransitionsService =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<Service, [Transition], TransitionBatchHeader>;
pub type TransitionPublisher = iceoryx2::port::publisher::Publisher<Service, [Transition], TransitionBatchHeader>;
pub type TransitionSubscriber = iceoryx2::port::subscriber::Subscriber<Service, [Transition], TransitionBatchHeader>;

pub type WeightsService =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<Service, [f32], WeightsHeader>;
pub type WeightsPublisher = iceoryx2::port::publisher::Publisher<Service, [f32], WeightsHeader>;
pub type WeightsSubscriber = iceoryx2::port::subscriber::Subscriber<Service, [f32], WeightsHeader>;

pub type StatusService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<Service, ReplayStatus, ()>;
pub type StatusPublisher = iceoryx2::port::publisher::Publisher<Service, ReplayStatus, ()>;
pub type StatusSubscriber = iceoryx2::port::subscriber::Subscriber<Service, ReplayStatus, ()>;

pub type BatchService = iceoryx2::service::port_factory::request_response::PortFactory<
    Service,
    BatchRequest,
    (),
    [Transition],
    BatchHeader,
>;
pub type BatchClient = iceoryx2::port::client::Client<Service, BatchRequest, (), [Transition], BatchHeader>;
pub type BatchServer = iceoryx2::port::server::Server<Service, BatchRequest, (), [Transition], BatchHeader>;
pub type BatchPending =
    iceoryx2::pending_response::PendingResponse<Service, BatchRequest, (), [Transition], BatchHeader>;
pub type BatchActiveRequest =
    iceoryx2::active_request::ActiveRequest<Service, BatchRequest, (), [Transition], BatchHeader>;

/// Extra publisher/subscriber slots per actor-facing service, so restarted actors can join before the
/// dead-node cleanup has freed their predecessors' slots.
pub const RESTART_SLACK: usize = 4;
/// Learner-side slots (the learner, or a restarted learner, or a test's stand-in weights publisher).
pub const MAX_LEARNERS: usize = 2;
/// Replay-side slots (the replay, or a restarted replay whose predecessor is not yet cleaned up).
pub const MAX_REPLAYS: usize = 2;
/// Extra read-only subscribers (a benchmark or test tap, the evaluator).
pub const MAX_TAPS: usize = 2;
/// Transition messages the replay's subscriber buffers per actor connection. The replay drains every
/// [`REPLAY_CYCLE`] (1 ms), so 128 messages (8192 transitions at the default publish batch) cover a
/// replay stalled for well over 100 ms before any actor has to wait.
pub const TRANSITION_BUFFER_MESSAGES: usize = 128;
/// How long an actor's publish waits for room in a full replay buffer before it gives up; the message
/// is then lost, and both the actor (`undelivered`) and the replay (`dropped_total`) count it.
pub const PUBLISH_GIVE_UP: Duration = Duration::from_millis(500);
/// Batch requests one learner may have open at once (it prefetches the next batch during an update).
pub const MAX_BATCH_REQUESTS_IN_FLIGHT: usize = 4;
/// The replay's loop period.
pub const REPLAY_CYCLE: Duration = Duration::from_millis(1);
/// How long actors and learner wait for the replay's services to appear before giving up.
pub const OPEN_TIMEOUT: Duration = Duration::from_secs(60);

#[derive(Debug, thiserror::Error)]
pub enum IpcError {
    #[error("cannot resolve run folder {path}: {source}")]
    RunDir { path: PathBuf, source: std::io::Error },
    #[error("iceoryx2 {what} failed: {detail}")]
    Iceoryx { what: String, detail: String },
    #[error(
        "service {service} exists with an incompatible layout or limits ({detail}); a process from another \
         build or config is running on this run folder: stop it, or use a new run folder"
    )]
    Incompatible { service: String, detail: String },
    #[error("service {service} did not appear within {seconds} s (last error: {detail}); is bcal-replay running for this run folder?")]
    Timeout { service: String, seconds: u64, detail: String },
    #[error(
        "run folder {run_id} is served by bcal processes of wire version {found} but this binary speaks version \
         {ours}; a process from an older or newer build is running: stop it (or rebuild), or use a new run folder"
    )]
    WireVersion { run_id: String, found: u32, ours: u32 },
    #[error("interrupted by a termination signal")]
    Interrupted,
}

fn iox(what: impl Into<String>) -> impl FnOnce(&dyn std::fmt::Debug) -> IpcError {
    let what = what.into();
    move |e| IpcError::Iceoryx { what, detail: format!("{e:?}") }
}

/// Whether a process makes the services (the replay) or only opens them (everyone else).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// Open if present, else create with the limits below.
    Create,
    /// Open, retrying up to `timeout` while the service does not exist yet.
    Open { timeout: Duration },
}

/// The iceoryx2 configuration of every bcal process: the built-in defaults (stated here, never searched
/// for in config files, so every process of a run agrees), with a per-user file prefix `bcal{uid}_` so
/// bcal's shared memory never mixes with another user's or another iceoryx2 application's.
pub fn iox_config() -> Config {
    let mut config = Config::default();
    // SAFETY: geteuid has no preconditions and cannot fail.
    let uid = unsafe { libc::geteuid() };
    if let Ok(prefix) = FileName::new(format!("bcal{uid}_").as_bytes()) {
        config.global.prefix = prefix;
    }
    config
}

/// Creates this process's node (termination signals make `node.wait` fail, so loops end cleanly) and
/// removes the stale resources of dead nodes. Returns the node and how many dead nodes were cleaned.
/// iceoryx2's own log level is Warn unless `IOX2_LOG_LEVEL` says otherwise.
///
/// Permissions: iceoryx2 creates every service segment owner-read-write (0600); only its domain-wide
/// node counter is made writable by everyone (it is meant to be shared between users). Under bcal's
/// per-user prefix nobody else needs it, so it is narrowed to 0600 as well.
pub fn create_node(name: &str) -> Result<(Node, u64), IpcError> {
    set_log_level_from_env_or(LogLevel::Warn);
    let config = iox_config();
    let node_name = NodeName::new(name).map_err(|e| iox(format!("node name {name:?}"))(&e))?;
    let node = NodeBuilder::new()
        .config(&config)
        .name(&node_name)
        .signal_handling_mode(SignalHandlingMode::HandleTerminationRequests)
        .create::<Service>()
        .map_err(|e| iox("node creation")(&e))?;
    restrict_shared_files(&config);
    let cleaned = node.try_cleanup_dead_nodes();
    Ok((node, cleaned.cleanups))
}

/// Shared-memory files of this user's bcal domain (`/dev/shm/bcal{uid}_*`), for permission checks.
pub fn shared_memory_files(config: &Config) -> Vec<PathBuf> {
    let prefix = config.global.prefix.to_string();
    std::fs::read_dir("/dev/shm")
        .map(|rd| {
            rd.flatten()
                .map(|e| e.path())
                .filter(|p| p.file_name().is_some_and(|n| n.to_string_lossy().starts_with(&prefix)))
                .collect()
        })
        .unwrap_or_default()
}

/// Removes group and other access from this user's bcal shared-memory files (the node counter is the
/// only one iceoryx2 makes world-writable). Best effort: a file another user owns is left alone.
fn restrict_shared_files(config: &Config) {
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    // SAFETY: geteuid has no preconditions and cannot fail.
    let uid = unsafe { libc::geteuid() };
    for path in shared_memory_files(config) {
        if let Ok(meta) = std::fs::metadata(&path) {
            if meta.uid() == uid && meta.mode() & 0o077 != 0 {
                let _ = std::fs::set_permissions(&path, std::fs::Permissions::from_mode(meta.mode() & 0o700));
            }
        }
    }
}

/// Removes dead nodes' resources now (the replay calls this periodically); returns the number cleaned.
pub fn cleanup_dead_nodes(node: &Node) -> u64 {
    node.try_cleanup_dead_nodes().cleanups
}

/// `node.wait` that maps a termination request to [`IpcError::Interrupted`].
pub fn wait(node: &Node, cycle: Duration) -> Result<(), IpcError> {
    match node.wait(cycle) {
        Ok(()) => Ok(()),
        Err(NodeWaitFailure::TerminationRequest) | Err(NodeWaitFailure::Interrupt) => Err(IpcError::Interrupted),
    }
}

/// Every service limit of one run, derived from its validated config.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Actor processes of the run.
    pub actors: usize,
    /// Largest transition message (actors.publish_batch).
    pub publish_batch: usize,
    /// Learner minibatch (lac.batch_size).
    pub batch_size: usize,
}

impl Limits {
    pub fn new(cfg: &Validated) -> Self {
        Self {
            actors: cfg.actor_count,
            publish_batch: cfg.config.actors.publish_batch.min(MAX_PUBLISH_BATCH),
            batch_size: cfg.config.lac.batch_size,
        }
    }

    /// Publishers on `transitions` (and subscribers on `weights`, `status`): actors and restarts.
    pub fn actor_ports(&self) -> usize {
        self.actors + RESTART_SLACK
    }

    /// Nodes that may open one service at once.
    pub fn max_nodes(&self) -> usize {
        self.actor_ports() + MAX_LEARNERS + MAX_REPLAYS + MAX_TAPS
    }
}

/// The services of one run folder.
#[derive(Clone, Debug)]
pub struct RunIpc {
    /// 16 hex digits identifying the run folder.
    pub run_id: String,
    pub limits: Limits,
}

impl RunIpc {
    /// The services of the run in `run_dir` (hashed after canonicalisation, so `./runs/x` and its
    /// absolute path name the same run).
    pub fn new(run_dir: &Path, cfg: &Validated) -> Result<Self, IpcError> {
        let canonical = std::fs::canonicalize(run_dir)
            .map_err(|source| IpcError::RunDir { path: run_dir.to_path_buf(), source })?;
        let run_id = format!("{:016x}", fnv1a64(canonical.as_os_str().as_encoded_bytes()));
        Ok(Self { run_id, limits: Limits::new(cfg) })
    }

    /// `bcal/v{WIRE_VERSION}/{run}/{leaf}`.
    pub fn service_name(&self, leaf: &str) -> String {
        format!("bcal/v{WIRE_VERSION}/{}/{leaf}", self.run_id)
    }

    fn name(&self, leaf: &str) -> Result<ServiceName, IpcError> {
        let s = self.service_name(leaf);
        ServiceName::new(&s).map_err(|e| iox(format!("service name {s}"))(&e))
    }

    /// Actor -> replay transitions. No overflow: a full replay buffer makes the publisher wait (bounded,
    /// see [`Self::transition_publisher`]) instead of overwriting unread transitions.
    pub fn transitions(&self, node: &Node, role: Role) -> Result<TransitionsService, IpcError> {
        let name = self.name("transitions")?;
        let l = &self.limits;
        let build = || {
            node.service_builder(&name)
                .publish_subscribe::<[Transition]>()
                .user_header::<TransitionBatchHeader>()
                .enable_safe_overflow(false)
                .history_size(0)
                .subscriber_max_buffer_size(TRANSITION_BUFFER_MESSAGES)
                .subscriber_max_borrowed_samples(2)
                .max_publishers(l.actor_ports())
                .max_subscribers(MAX_TAPS)
                .max_nodes(l.max_nodes())
        };
        match role {
            Role::Create => build().open_or_create().map_err(|e| classify(&name, &e)),
            Role::Open { timeout } => retry_open(node, &name, timeout, || build().open()),
        }
    }

    /// Learner -> actors weights: history 1 so a late or restarted actor gets the newest at once;
    /// overflow keeps the newest (an actor never wants old weights).
    pub fn weights(&self, node: &Node, role: Role) -> Result<WeightsService, IpcError> {
        let name = self.name("weights")?;
        let l = &self.limits;
        let build = || {
            node.service_builder(&name)
                .publish_subscribe::<[f32]>()
                .user_header::<WeightsHeader>()
                .enable_safe_overflow(true)
                .history_size(1)
                .subscriber_max_buffer_size(2)
                .subscriber_max_borrowed_samples(1)
                .max_publishers(MAX_LEARNERS)
                .max_subscribers(l.actor_ports() + MAX_TAPS)
                .max_nodes(l.max_nodes())
        };
        match role {
            Role::Create => build().open_or_create().map_err(|e| classify(&name, &e)),
            Role::Open { timeout } => retry_open(node, &name, timeout, || build().open()),
        }
    }

    /// Replay -> actors limiter verdict and counters (history 1, newest wins).
    pub fn status(&self, node: &Node, role: Role) -> Result<StatusService, IpcError> {
        let name = self.name("status")?;
        let l = &self.limits;
        let build = || {
            node.service_builder(&name)
                .publish_subscribe::<ReplayStatus>()
                .enable_safe_overflow(true)
                .history_size(1)
                .subscriber_max_buffer_size(2)
                .subscriber_max_borrowed_samples(1)
                .max_publishers(MAX_REPLAYS)
                .max_subscribers(l.actor_ports() + MAX_LEARNERS + MAX_TAPS)
                .max_nodes(l.max_nodes())
        };
        match role {
            Role::Create => build().open_or_create().map_err(|e| classify(&name, &e)),
            Role::Open { timeout } => retry_open(node, &name, timeout, || build().open()),
        }
    }

    /// Learner <-> replay batches (request-response). The learner keeps at most
    /// [`MAX_BATCH_REQUESTS_IN_FLIGHT`] requests open, so neither buffer can overflow; overflow is off so
    /// a violation would be visible instead of a silently lost batch.
    pub fn batches(&self, node: &Node, role: Role) -> Result<BatchService, IpcError> {
        let name = self.name("batches")?;
        let l = &self.limits;
        let build = || {
            node.service_builder(&name)
                .request_response::<BatchRequest, [Transition]>()
                .response_user_header::<BatchHeader>()
                .enable_safe_overflow_for_requests(false)
                .enable_safe_overflow_for_responses(false)
                .enable_fire_and_forget_requests(false)
                .max_active_requests_per_client(MAX_BATCH_REQUESTS_IN_FLIGHT)
                .max_response_buffer_size(MAX_BATCH_REQUESTS_IN_FLIGHT)
                .max_loaned_requests(2)
                .max_borrowed_responses_per_pending_response(2)
                .max_servers(MAX_REPLAYS)
                .max_clients(MAX_LEARNERS)
                .max_nodes(l.max_nodes())
        };
        match role {
            Role::Create => build().open_or_create().map_err(|e| classify(&name, &e)),
            Role::Open { timeout } => retry_open(node, &name, timeout, || build().open()),
        }
    }

    /// An actor's transition publisher: slices up to `publish_batch`. When the replay's buffer is full
    /// it waits (iceoryx2's adaptive wait: yield, then sleep) up to [`PUBLISH_GIVE_UP`], then `send`
    /// fails with `UnableToDeliver` and the caller counts the message as undelivered.
    pub fn transition_publisher(&self, svc: &TransitionsService) -> Result<TransitionPublisher, IpcError> {
        svc.publisher_builder()
            .initial_max_slice_len(self.limits.publish_batch)
            .allocation_strategy(AllocationStrategy::Static)
            .max_loaned_samples(1)
            .set_backpressure_handler(|info: &iceoryx2::port::BackpressureInfo| {
                if info.elapsed_time < PUBLISH_GIVE_UP {
                    BackpressureAction::Retry
                } else {
                    BackpressureAction::DiscardDataAndFail
                }
            })
            .create()
            .map_err(|e| iox("transition publisher")(&e))
    }

    /// The replay's transition subscriber.
    pub fn transition_subscriber(&self, svc: &TransitionsService) -> Result<TransitionSubscriber, IpcError> {
        svc.subscriber_builder()
            .buffer_size(TRANSITION_BUFFER_MESSAGES)
            .create()
            .map_err(|e| iox("transition subscriber")(&e))
    }

    /// The learner's weights publisher for a network of `n_params` parameters.
    pub fn weights_publisher(&self, svc: &WeightsService, n_params: usize) -> Result<WeightsPublisher, IpcError> {
        svc.publisher_builder()
            .initial_max_slice_len(n_params.max(1))
            .allocation_strategy(AllocationStrategy::Static)
            .max_loaned_samples(1)
            .create()
            .map_err(|e| iox("weights publisher")(&e))
    }

    /// An actor's weights subscriber; asks for the newest message from history.
    pub fn weights_subscriber(&self, svc: &WeightsService) -> Result<WeightsSubscriber, IpcError> {
        svc.subscriber_builder().history_request(1).create().map_err(|e| iox("weights subscriber")(&e))
    }

    pub fn status_publisher(&self, svc: &StatusService) -> Result<StatusPublisher, IpcError> {
        svc.publisher_builder().max_loaned_samples(1).create().map_err(|e| iox("status publisher")(&e))
    }

    pub fn status_subscriber(&self, svc: &StatusService) -> Result<StatusSubscriber, IpcError> {
        svc.subscriber_builder().history_request(1).create().map_err(|e| iox("status subscriber")(&e))
    }

    /// The replay's batch server: responses are slices of exactly `batch_size` transitions.
    pub fn batch_server(&self, svc: &BatchService) -> Result<BatchServer, IpcError> {
        svc.server_builder()
            .initial_max_slice_len(self.limits.batch_size)
            .allocation_strategy(AllocationStrategy::Static)
            .create()
            .map_err(|e| iox("batch server")(&e))
    }

    /// The learner's batch client.
    pub fn batch_client(&self, svc: &BatchService) -> Result<BatchClient, IpcError> {
        svc.client_builder()
            .max_active_requests(MAX_BATCH_REQUESTS_IN_FLIGHT)
            .create()
            .map_err(|e| iox("batch client")(&e))
    }
}

/// Errors that mean "the service exists but is not ours" (layout or limits differ): never retried.
fn is_incompatible(detail: &str) -> bool {
    ["Incompatible", "DoesNotSupport", "VersionMismatch"].iter().any(|k| detail.contains(k))
}

fn classify(name: &ServiceName, e: &dyn std::fmt::Debug) -> IpcError {
    let detail = format!("{e:?}");
    if is_incompatible(&detail) {
        IpcError::Incompatible { service: name.to_string(), detail }
    } else {
        IpcError::Iceoryx { what: format!("service {name}"), detail }
    }
}

/// Opens a service, retrying every 20 ms while it does not exist (or is being created or torn down),
/// until `timeout`. A termination signal ends the wait with [`IpcError::Interrupted`].
fn retry_open<T, E: std::fmt::Debug>(
    node: &Node,
    name: &ServiceName,
    timeout: Duration,
    mut open: impl FnMut() -> Result<T, E>,
) -> Result<T, IpcError> {
    let started = std::time::Instant::now();
    let mut version_checked: Option<std::time::Instant> = None;
    loop {
        match open() {
            Ok(v) => return Ok(v),
            Err(e) => {
                let detail = format!("{e:?}");
                if is_incompatible(&detail) {
                    return Err(IpcError::Incompatible { service: name.to_string(), detail });
                }
                // Listing services reads the service folder: a few times a second is plenty.
                if version_checked.is_none_or(|t| t.elapsed() >= Duration::from_millis(250)) {
                    version_checked = Some(std::time::Instant::now());
                    if let Some(found) = other_wire_version(name) {
                        return Err(IpcError::WireVersion { run_id: run_id_of(name), found, ours: WIRE_VERSION });
                    }
                }
                if started.elapsed() >= timeout {
                    return Err(IpcError::Timeout { service: name.to_string(), seconds: timeout.as_secs(), detail });
                }
            }
        }
        wait(node, Duration::from_millis(20))?;
    }
}

/// The `{run}` part of `bcal/v{N}/{run}/{leaf}`.
fn run_id_of(name: &ServiceName) -> String {
    let name: &str = name.as_ref();
    name.split('/').nth(2).unwrap_or_default().to_string()
}

/// The wire version of another build's service for the same run and leaf, if one exists: an old binary
/// finds the new one's services (and vice versa) and says so at once instead of waiting to time out.
fn other_wire_version(name: &ServiceName) -> Option<u32> {
    let ours = name.to_string();
    let parts: Vec<&str> = ours.split('/').collect();
    let [app, _, run, leaf] = parts[..] else { return None };
    let mut found = None;
    let _ = <Service as iceoryx2::service::Service>::list(&iox_config(), |details| {
        let other = details.static_details.name().to_string();
        let p: Vec<&str> = other.split('/').collect();
        if let [a, v, r, l] = p[..] {
            if a == app && r == run && l == leaf {
                if let Some(n) = v.strip_prefix('v').and_then(|n| n.parse::<u32>().ok()) {
                    if n != WIRE_VERSION {
                        found = Some(n);
                        return CallbackProgression::Stop;
                    }
                }
            }
        }
        CallbackProgression::Continue
    });
    found
}

/// Seconds since the Unix epoch (for counters files).
pub fn unix_time_s() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TrainConfig;

    fn cfg(actors: usize) -> Validated {
        let mut c = TrainConfig::default();
        c.actors.count = Some(actors);
        c.validate().unwrap()
    }

    #[test]
    fn names_carry_version_and_run_and_differ_per_run_folder() {
        let a = tempfile::tempdir().unwrap();
        let b = tempfile::tempdir().unwrap();
        let ra = RunIpc::new(a.path(), &cfg(2)).unwrap();
        let rb = RunIpc::new(b.path(), &cfg(2)).unwrap();
        assert_ne!(ra.run_id, rb.run_id);
        let n = ra.service_name("transitions");
        assert_eq!(n, format!("bcal/v{WIRE_VERSION}/{}/transitions", ra.run_id));
        // The same folder through another spelling is the same run.
        let dotted = a.path().join(".");
        assert_eq!(RunIpc::new(&dotted, &cfg(2)).unwrap().run_id, ra.run_id);
    }

    #[test]
    fn limits_follow_the_actor_count() {
        let l = Limits::new(&cfg(3));
        assert_eq!(l.actor_ports(), 3 + RESTART_SLACK);
        assert_eq!(l.publish_batch, 64);
        assert_eq!(l.batch_size, 256);
    }

    #[test]
    fn services_round_trip_in_process() {
        let dir = tempfile::tempdir().unwrap();
        let c = cfg(1);
        let run = RunIpc::new(dir.path(), &c).unwrap();
        let (node, _) = create_node("bcal-ipc-test").unwrap();
        let t = run.transitions(&node, Role::Create).unwrap();
        let sub = run.transition_subscriber(&t).unwrap();
        // A second node opens what the first created, with the same limits.
        let (other, _) = create_node("bcal-ipc-test-opener").unwrap();
        let t2 = run.transitions(&other, Role::Open { timeout: Duration::from_secs(1) }).unwrap();
        let publ = run.transition_publisher(&t2).unwrap();
        let batch = [Transition { cost: 2.5, ..Transition::default() }; 3];
        let mut s = publ.loan_slice_uninit(3).unwrap();
        *s.user_header_mut() = TransitionBatchHeader { actor_id: 7, len: 3, ..Default::default() };
        let s = s.write_from_slice(&batch);
        assert_eq!(s.send().unwrap(), 1);
        let got = sub.receive().unwrap().expect("one message");
        assert_eq!(got.user_header().actor_id, 7);
        assert_eq!(got.payload(), &batch[..]);
        // Opening a service nobody made times out with a message naming it.
        let other_dir = tempfile::tempdir().unwrap();
        let missing = RunIpc::new(other_dir.path(), &c).unwrap();
        let e = missing.weights(&node, Role::Open { timeout: Duration::from_millis(50) }).unwrap_err();
        assert!(matches!(e, IpcError::Timeout { .. }), "{e}");
        assert!(e.to_string().contains("weights"), "{e}");
    }

    #[test]
    fn a_different_limit_is_refused_not_retried() {
        let dir = tempfile::tempdir().unwrap();
        let run = RunIpc::new(dir.path(), &cfg(1)).unwrap();
        let (node, _) = create_node("bcal-ipc-test-limits").unwrap();
        let _svc = run.status(&node, Role::Create).unwrap();
        // A peer that believes in 40 actors wants more subscriber slots than the service has.
        let bigger = RunIpc { run_id: run.run_id.clone(), limits: Limits { actors: 40, ..run.limits.clone() } };
        let e = bigger.status(&node, Role::Open { timeout: Duration::from_secs(5) }).unwrap_err();
        assert!(matches!(e, IpcError::Incompatible { .. }), "{e}");
    }
}
