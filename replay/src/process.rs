//! The replay process loop: create every service of the run, then every [`REPLAY_CYCLE`] drain the actors'
//! transitions into the [`ReplayStore`], answer the learner's batch requests the limiter admits, and
//! publish the limiter's verdict to the actors. Counters go to `DIR/replay.json` about once a second and
//! at exit.
//!
//! Why request-response for batches: a batch is exactly the answer to "the learner is ready for one
//! more", so the request itself is the learner's credit; the replay holds requests it may not yet serve
//! (the limiter says the learner is too far ahead) and answers them in order once actors caught up. The
//! learner keeps up to two requests open, so the next batch is ready while it computes an update. A
//! pub/sub push would need a second channel to carry the same credit back.
//!
//! The loop is `while node.wait(cycle)`: SIGINT/SIGTERM end it, the final counters are written, and Drop
//! releases the services.

use crate::snapshot::{self, Snapshot, SnapshotError};
use crate::store::ReplayStore;
use bcal_common::config::{ConfigError, TrainConfig, Validated};
use bcal_common::ipc::{self, BatchActiveRequest, IpcError, Role, RunIpc, REPLAY_CYCLE};
use bcal_common::wire::{monotonic_ns, BatchHeader, ReplayStatus, Transition};
use serde::Serialize;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Status is re-published at least this often (a heartbeat for actors), and at once when it changes.
const STATUS_EVERY: Duration = Duration::from_millis(10);
/// `replay.json` refresh period.
const REPORT_EVERY: Duration = Duration::from_secs(1);
/// Dead-node cleanup period (frees slots of crashed actors for their restarts).
const CLEANUP_EVERY: Duration = Duration::from_secs(2);
/// After a termination signal, keep draining until no message arrived for this long (bounded by the
/// actors, which stop on the same signal).
const FINAL_DRAIN_QUIET: Duration = Duration::from_millis(50);

#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Ipc(#[from] IpcError),
    #[error("cannot write {path}: {source}")]
    Write { path: PathBuf, source: std::io::Error },
    #[error("iceoryx2 {what}: {detail}")]
    Transport { what: &'static str, detail: String },
}

fn transport(what: &'static str) -> impl FnOnce(&dyn std::fmt::Debug) -> ReplayError {
    move |e| ReplayError::Transport { what, detail: format!("{e:?}") }
}

/// What `DIR/replay.json` holds.
#[derive(Clone, Debug, Serialize)]
pub struct ReplayReport {
    pub pid: u32,
    /// "running" while the loop runs, "stopped" after a termination signal.
    pub state: &'static str,
    pub uptime_s: f64,
    pub updated_unix_s: f64,
    pub received_total: u64,
    pub inserted_total: u64,
    pub quarantined_total: u64,
    pub dropped_total: u64,
    pub sampled_total: u64,
    pub batches_served: u64,
    pub size: u64,
    pub capacity: u64,
    /// Transitions received per second since the previous report.
    pub received_per_s: f64,
    /// Mean one-way latency (actor send -> replay receive) of the messages since the previous report, µs.
    pub latency_mean_us: f64,
    pub inserts_allowed: bool,
    pub insert_credit: u64,
    /// The limiter's error buffer in use (configured, or widened against a deadlock).
    pub ratio_error_buffer: f64,
    pub actors_seen: usize,
    /// Batch requests waiting for the limiter at the time of the report.
    pub pending_requests: usize,
    /// Requests for an impossible batch size (answered with an empty batch).
    pub requests_refused: u64,
    /// Dead iceoryx2 nodes (of killed processes) whose resources this replay removed.
    pub dead_nodes_cleaned: u64,
    /// "snapshot" when this replay resumed the buffer of its predecessor, "empty" when it refills.
    pub started_from: &'static str,
    /// Transitions restored from the snapshot at start.
    pub restored_transitions: u64,
    /// Why the buffer started as it did (snapshots disabled, none yet, restored, or why one was refused).
    pub start_note: String,
    /// Snapshots written by this replay (`replay.snapshot_every_s` > 0).
    pub snapshots_written: u64,
    /// Transitions in the newest snapshot this replay wrote.
    pub last_snapshot_transitions: u64,
    /// The last snapshot write failure, if any (the previous snapshot is kept; training goes on).
    pub snapshot_error: Option<String>,
}

/// What the report needs besides the store.
#[derive(Clone, Debug, Default)]
struct LoopState {
    pending: usize,
    requests_refused: u64,
    dead_nodes_cleaned: u64,
    received_per_s: f64,
    /// One-way latency of the messages since the last report: (sum ns, count).
    latency: (u64, u64),
    started_from: &'static str,
    restored_transitions: u64,
    start_note: String,
    snapshots_written: u64,
    last_snapshot_transitions: u64,
    snapshot_error: Option<String>,
}

/// Restores the store from the run's snapshot when snapshots are enabled; says what happened.
fn restore(run_dir: &Path, enabled: bool, store: &mut ReplayStore, st: &mut LoopState) {
    let path = snapshot::path(run_dir);
    st.started_from = "empty";
    st.start_note = if !enabled {
        "snapshots disabled (replay.snapshot_every_s = 0): refilling from the actors".into()
    } else {
        match Snapshot::load(&path) {
            Ok(snap) => match snap.restore_into(store) {
                Ok(n) => {
                    st.started_from = "snapshot";
                    st.restored_transitions = n as u64;
                    format!("restored {n} transitions from {}", path.display())
                }
                Err(why) => format!("snapshot {} not used: {why}; refilling", path.display()),
            },
            Err(SnapshotError::Read { source, .. }) if source.kind() == std::io::ErrorKind::NotFound => {
                "no snapshot yet: refilling from the actors".into()
            }
            Err(e) => format!("{e}; refilling"),
        }
    };
}

/// Writes snapshots every `every_s` on a background thread (the loop only pays for copying the buffer),
/// one at a time; a failed write is reported and the previous snapshot stays.
struct SnapshotWriter {
    path: PathBuf,
    every: Option<Duration>,
    last: Instant,
    running: Option<(usize, std::thread::JoinHandle<Result<(), SnapshotError>>)>,
}

impl SnapshotWriter {
    fn new(path: PathBuf, every_s: f64) -> Self {
        let every = (every_s > 0.0).then(|| Duration::from_secs_f64(every_s));
        Self { path, every, last: Instant::now(), running: None }
    }

    fn due(&self) -> bool {
        self.every.is_some_and(|e| self.last.elapsed() >= e)
    }

    /// Collects a finished write, then starts the next one unless one is still running.
    fn start(&mut self, snap: Snapshot, st: &mut LoopState) {
        if self.running.as_ref().is_some_and(|(_, h)| !h.is_finished()) {
            return;
        }
        self.collect(st);
        self.last = Instant::now();
        let path = self.path.clone();
        let n = snap.items.len();
        self.running = Some((n, std::thread::spawn(move || snap.save(&path))));
    }

    fn collect(&mut self, st: &mut LoopState) {
        if let Some((n, h)) = self.running.take() {
            match h.join() {
                Ok(Ok(())) => {
                    st.snapshots_written += 1;
                    st.last_snapshot_transitions = n as u64;
                    st.snapshot_error = None;
                }
                Ok(Err(e)) => st.snapshot_error = Some(e.to_string()),
                Err(_) => st.snapshot_error = Some("the snapshot thread panicked".into()),
            }
        }
    }

    /// Waits for a running write, then writes the final state (when snapshots are enabled).
    fn finish(&mut self, store: &ReplayStore, st: &mut LoopState) {
        self.collect(st);
        if self.every.is_some() {
            let snap = Snapshot::of(store);
            let n = snap.items.len();
            match snap.save(&self.path) {
                Ok(()) => {
                    st.snapshots_written += 1;
                    st.last_snapshot_transitions = n as u64;
                }
                Err(e) => st.snapshot_error = Some(e.to_string()),
            }
        }
    }
}

/// Reads `DIR/config.toml` and validates it.
pub fn read_config(run_dir: &Path) -> Result<Validated, ConfigError> {
    TrainConfig::from_file(&run_dir.join("config.toml"))?.validate()
}

/// Runs the replay until a termination signal; returns the final report (also written to disk).
pub fn run(run_dir: &Path) -> Result<ReplayReport, ReplayError> {
    // The node first: from here on SIGTERM/SIGINT are flags the loop sees, not an abrupt exit.
    let (node, dead_nodes_cleaned) = ipc::create_node("bcal-replay")?;
    let cfg = read_config(run_dir)?;
    let run = RunIpc::new(run_dir, &cfg)?;
    let batch_size = cfg.config.lac.batch_size;

    // Every service of the run is made here, with the limits ipc.rs states, before anyone opens them.
    let transitions = run.transitions(&node, Role::Create)?;
    let _weights = run.weights(&node, Role::Create)?;
    let status = run.status(&node, Role::Create)?;
    let batches = run.batches(&node, Role::Create)?;
    let subscriber = run.transition_subscriber(&transitions)?;
    let server = run.batch_server(&batches)?;
    // The status publisher comes last: an actor publishes only after it saw a status, and by then the
    // transition subscriber exists, so no actor message can go to nobody.
    let status_pub = run.status_publisher(&status)?;

    let seed = cfg.config.seed ^ 0x7265_706c_6179; // "replay"
    let mut store = ReplayStore::new(&cfg.config.replay, batch_size, seed);
    let mut pending: VecDeque<BatchActiveRequest> = VecDeque::new();
    let mut scratch = vec![Transition::default(); batch_size];
    let mut st = LoopState { dead_nodes_cleaned, ..LoopState::default() };
    let snapshot_every_s = cfg.config.replay.snapshot_every_s;
    restore(run_dir, snapshot_every_s > 0.0, &mut store, &mut st);
    let mut snapshots = SnapshotWriter::new(snapshot::path(run_dir), snapshot_every_s);

    let started = Instant::now();
    let report_path = run_dir.join("replay.json");
    let mut last_status: Option<(bool, Instant)> = None;
    let mut last_report = (Instant::now(), 0u64);
    let mut last_cleanup = Instant::now();

    let make_report = |store: &ReplayStore, state: &'static str, st: &LoopState| {
        let c = store.counters;
        ReplayReport {
            pid: std::process::id(),
            state,
            uptime_s: started.elapsed().as_secs_f64(),
            updated_unix_s: ipc::unix_time_s(),
            received_total: c.received_total,
            inserted_total: c.inserted_total,
            quarantined_total: c.quarantined_total,
            dropped_total: c.dropped_total,
            sampled_total: c.sampled_total,
            batches_served: c.batches_served,
            size: c.size,
            capacity: store.ring.capacity() as u64,
            received_per_s: st.received_per_s,
            latency_mean_us: st.latency.0 as f64 / st.latency.1.max(1) as f64 / 1e3,
            inserts_allowed: store.inserts_allowed(),
            insert_credit: store.limiter.insert_credit(),
            ratio_error_buffer: store.limiter.error_buffer(),
            actors_seen: store.tracker.actors_seen(),
            pending_requests: st.pending,
            requests_refused: st.requests_refused,
            dead_nodes_cleaned: st.dead_nodes_cleaned,
            started_from: st.started_from,
            restored_transitions: st.restored_transitions,
            start_note: st.start_note.clone(),
            snapshots_written: st.snapshots_written,
            last_snapshot_transitions: st.last_snapshot_transitions,
            snapshot_error: st.snapshot_error.clone(),
        }
    };
    let write = |r: &ReplayReport| {
        bcal_common::fsutil::write_json_atomic(&report_path, r)
            .map_err(|source| ReplayError::Write { path: report_path.clone(), source })
    };
    write(&make_report(&store, "running", &st))?;

    while node.wait(REPLAY_CYCLE).is_ok() {
        // 1. Actors' transitions (all that arrived since the last cycle).
        while let Some(sample) = subscriber.receive().map_err(|e| transport("receive transitions")(&e))? {
            let sent_ns = sample.user_header().sent_mono_ns;
            st.latency.0 += monotonic_ns().saturating_sub(sent_ns);
            st.latency.1 += 1;
            store.ingest(sample.user_header(), sample.payload());
        }

        // 2. New batch requests queue behind older ones (served in order).
        while let Some(request) = server.receive().map_err(|e| transport("receive batch request")(&e))? {
            pending.push_back(request);
        }

        // 3. Serve what the limiter admits.
        while let Some(request) = pending.front() {
            if !request.is_connected() {
                pending.pop_front(); // the learner went away; nobody wants this batch
                continue;
            }
            let n = request.batch_size as usize;
            let header = BatchHeader { request_seq: request.request_seq, counters: store.counters };
            if n == 0 || n > batch_size {
                st.requests_refused += 1;
                let mut response = request.loan_slice_uninit(0).map_err(|e| transport("loan response")(&e))?;
                *response.user_header_mut() = header;
                let _ = response.write_from_slice(&[]).send();
                pending.pop_front();
                continue;
            }
            if !store.can_sample(n) {
                break;
            }
            store.sample_into(&mut scratch[..n]);
            let header = BatchHeader { request_seq: request.request_seq, counters: store.counters };
            let mut response = request.loan_slice_uninit(n).map_err(|e| transport("loan response")(&e))?;
            *response.user_header_mut() = header;
            // A learner that disconnected between the check and the send loses only its own batch.
            let _ = response.write_from_slice(&scratch[..n]).send();
            pending.pop_front();
        }

        // 4. The limiter's verdict for the actors: on change at once, else as a heartbeat.
        let allowed = store.inserts_allowed();
        let due = match last_status {
            None => true,
            Some((was, at)) => was != allowed || at.elapsed() >= STATUS_EVERY,
        };
        if due {
            let status = ReplayStatus {
                inserts_allowed: u32::from(allowed),
                _reserved: 0,
                insert_credit: store.limiter.insert_credit(),
                uptime_ms: started.elapsed().as_millis() as u64,
                counters: store.counters,
            };
            status_pub.send_copy(status).map_err(|e| transport("publish status")(&e))?;
            last_status = Some((allowed, Instant::now()));
        }

        // 5. Housekeeping.
        if last_cleanup.elapsed() >= CLEANUP_EVERY {
            st.dead_nodes_cleaned += ipc::cleanup_dead_nodes(&node);
            last_cleanup = Instant::now();
        }
        if last_report.0.elapsed() >= REPORT_EVERY {
            let received = store.counters.received_total;
            let rate = (received - last_report.1) as f64 / last_report.0.elapsed().as_secs_f64();
            st.pending = pending.len();
            st.received_per_s = rate;
            write(&make_report(&store, "running", &st))?;
            last_report = (Instant::now(), received);
            st.latency = (0, 0);
        }
        if snapshots.due() {
            snapshots.start(Snapshot::of(&store), &mut st);
        }
    }

    // Whatever was on the wire when the signal came still counts: drain until the actors fell quiet.
    let mut quiet_since = Instant::now();
    while quiet_since.elapsed() < FINAL_DRAIN_QUIET {
        let mut got = false;
        while let Ok(Some(sample)) = subscriber.receive() {
            store.ingest(sample.user_header(), sample.payload());
            got = true;
        }
        if got {
            quiet_since = Instant::now();
        }
        std::thread::sleep(REPLAY_CYCLE);
    }
    let rate = (store.counters.received_total - last_report.1) as f64 / last_report.0.elapsed().as_secs_f64();
    // The final snapshot: a clean stop loses nothing either.
    snapshots.finish(&store, &mut st);
    st.pending = pending.len();
    st.received_per_s = rate;
    let report = make_report(&store, "stopped", &st);
    write(&report)?;
    Ok(report)
}
