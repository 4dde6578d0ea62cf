//! Actor -> replay transport: transitions per second and one-way latency of a batch through iceoryx2
//! across real processes, beside an in-process crossbeam channel carrying the same batches.
//!
//! iceoryx2: this process is the subscriber (it creates the run's `transitions` service, exactly as the
//! replay does, through `bcal_common::ipc`); N publisher processes (the caller supplies the command, in
//! `bcal` a hidden `bcal bench-publish`) each send batches of `actors.publish_batch` transitions as fast
//! as the subscriber drains them (iceoryx2 back-pressure: a full buffer makes the publisher wait), or at a
//! fixed rate. Each message is stamped with CLOCK_MONOTONIC just before `send()`; the subscriber reads the
//! clock when it takes the message: the one-way latency of that batch.
//!
//! Baseline, same run: N threads send the same batches (`Box<[Transition]>`, copied from the same
//! template) over one bounded crossbeam channel (128 messages per sender, the subscriber buffer of the
//! iceoryx2 service) to one receiving thread, stamped the same way, for the same warm-up and window.
//!
//! Both receivers do the same work per message: copy the transitions into a ring store (as the replay
//! inserts them) and record the latency. The iceoryx2 subscriber polls (yielding the core when its
//! buffer is empty); the crossbeam receiver blocks in `recv_timeout`: each transport as it is used.
//!
//! Child processes are owned by a guard that kills (SIGKILL) and reaps every one still running when it
//! goes out of scope, on every path; publishers also die with this process (PR_SET_PDEATHSIG), stop on
//! SIGTERM, when the subscriber disappears, and at a hard deadline.

use anyhow::{bail, Context};
use bcal_common::config::TrainConfig;
use bcal_common::ipc::{self, Role, RunIpc, TRANSITION_BUFFER_MESSAGES};
use bcal_common::wire::{monotonic_ns, Transition, TransitionBatchHeader, MAX_ACT, MAX_OBS};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Transitions the receivers' ring store holds (about 8.9 MB, larger than the caches, like a replay).
const STORE: usize = 32_768;
/// How long the subscriber waits for every publisher's first message.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(30);
/// How long publishers get to stop after SIGTERM before they are killed.
const STOP_GRACE: Duration = Duration::from_secs(3);

/// What one publisher process is told (`bcal bench-publish --run DIR --id K --seconds S --rate R`).
#[derive(Clone, Debug, PartialEq)]
pub struct PublisherArgs {
    /// Temporary run folder holding `config.toml` (names the services and their limits).
    pub run_dir: PathBuf,
    /// Publisher id (the header's actor_id).
    pub id: u32,
    /// Hard deadline: the publisher stops after this many seconds whatever happens.
    pub seconds: f64,
    /// Messages per second; 0 = as fast as the subscriber drains them.
    pub rate: f64,
}

/// Builds the command that runs one publisher process.
pub type SpawnPublisher<'a> = &'a dyn Fn(&PublisherArgs) -> Command;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TransportSettings {
    /// Publisher counts (actors) to measure.
    pub actors: Vec<usize>,
    /// Warm-up before each window, s.
    pub warmup_s: f64,
    /// Measurement window per setting and transport, s.
    pub window_s: f64,
    /// Rate of the paced single-publisher row, messages/s (0 = no paced row).
    pub paced_rate: f64,
}

/// One transport's flow over one window.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Flow {
    pub transitions_per_s: f64,
    pub messages_per_s: f64,
    /// One-way latency of a batch (stamped before send, read when the receiver takes it), us.
    pub latency_mean_us: f64,
    pub latency_p50_us: f64,
    pub latency_p99_us: f64,
    /// Messages received in the window.
    pub messages: u64,
    /// Window length as measured, s.
    pub seconds: f64,
    /// Messages received in the window from each sender (iceoryx2 serves its publishers' buffers in
    /// order, so a saturated subscriber can starve later publishers: this shows it).
    pub per_actor_messages: Vec<u64>,
    /// iceoryx2 only: from spawning the publisher processes to every one's first delivered batch, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub startup_s: Option<f64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TransportRow {
    pub actors: u64,
    /// Messages per second each publisher is paced to (absent = as fast as drained).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rate_per_actor: Option<f64>,
    pub iceoryx2: Flow,
    pub crossbeam: Flow,
    /// iceoryx2 transitions/s / crossbeam transitions/s.
    pub throughput_ratio: f64,
    /// iceoryx2 mean latency / crossbeam mean latency.
    pub latency_ratio: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TransportReport {
    /// Transitions per message (actors.publish_batch).
    pub publish_batch: u64,
    /// Bytes of one transition on the wire.
    pub transition_bytes: u64,
    /// Saturated: every publisher sends as fast as the receiver drains.
    pub rows: Vec<TransportRow>,
    /// One publisher at a fixed rate (the latency of an unloaded transport).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub paced: Option<TransportRow>,
}

/// Measures every setting: iceoryx2 then crossbeam for each actor count, then the paced row.
pub fn measure(
    s: &TransportSettings,
    spawn: SpawnPublisher,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<TransportReport> {
    let publish_batch = TrainConfig::default().validate()?.config.actors.publish_batch;
    let (warmup, window) = (Duration::from_secs_f64(s.warmup_s), Duration::from_secs_f64(s.window_s));
    // One node for the part: from its creation on, iceoryx2 captures SIGINT and SIGTERM, so every loop
    // below asks it (`Interrupt`) and stops at once on Ctrl-C.
    let (node, _) = ipc::create_node("bcal-bench-subscriber")?;
    let node = &node;
    let row = |actors: usize, rate: f64, progress: &mut dyn FnMut(&str)| -> anyhow::Result<TransportRow> {
        let pace = if rate > 0.0 { format!(" at {rate} batches/s") } else { String::new() };
        progress(&format!("transport: {actors} publisher process(es){pace} -> iceoryx2 -> this process ..."));
        let ice = iceoryx2_flow(node, actors, rate, warmup, window, spawn)?;
        progress(&format!("transport: {actors} thread(s){pace} -> crossbeam -> 1 thread ..."));
        let cb = crossbeam_flow(node, actors, rate, publish_batch, warmup, window)?;
        progress(&format!(
            "transport: {actors} actor(s): iceoryx2 {:.0} transitions/s (latency mean {:.1} us; publishers up in \
             {:.2} s), crossbeam {:.0} ({:.1} us)",
            ice.transitions_per_s,
            ice.latency_mean_us,
            ice.startup_s.unwrap_or(f64::NAN),
            cb.transitions_per_s,
            cb.latency_mean_us
        ));
        Ok(TransportRow {
            actors: actors as u64,
            rate_per_actor: (rate > 0.0).then_some(rate),
            throughput_ratio: ice.transitions_per_s / cb.transitions_per_s,
            latency_ratio: ice.latency_mean_us / cb.latency_mean_us,
            iceoryx2: ice,
            crossbeam: cb,
        })
    };
    let mut rows = Vec::new();
    for &n in &s.actors {
        rows.push(row(n, 0.0, progress)?);
    }
    let paced = if s.paced_rate > 0.0 { Some(row(1, s.paced_rate, progress)?) } else { None };
    Ok(TransportReport {
        publish_batch: publish_batch as u64,
        transition_bytes: std::mem::size_of::<Transition>() as u64,
        rows,
        paced,
    })
}

/// The batch every sender sends: finite pseudo-random transitions.
fn template(n: usize, seed: u64) -> Vec<Transition> {
    Transition::synthetic_batch(seed, n, MAX_OBS, MAX_ACT)
}

/// The receivers' shared bookkeeping: a ring store the transitions are copied into, and the latencies.
struct Recorder {
    store: Vec<Transition>,
    at: usize,
    latencies_ns: Vec<u64>,
    transitions: u64,
    per_actor: Vec<u64>,
}

impl Recorder {
    fn new(actors: usize) -> Self {
        Self {
            store: vec![Transition::default(); STORE],
            at: 0,
            latencies_ns: Vec::new(),
            transitions: 0,
            per_actor: vec![0; actors],
        }
    }

    /// Stores a batch; records it when `record`.
    fn take(&mut self, batch: &[Transition], sent_ns: u64, actor: u32, record: bool) {
        let now = monotonic_ns();
        for chunk in batch.chunks(STORE) {
            let first = chunk.len().min(STORE - self.at);
            self.store[self.at..self.at + first].copy_from_slice(&chunk[..first]);
            self.store[..chunk.len() - first].copy_from_slice(&chunk[first..]);
            self.at = (self.at + chunk.len()) % STORE;
        }
        if record {
            self.latencies_ns.push(now.saturating_sub(sent_ns));
            self.transitions += batch.len() as u64;
            if let Some(c) = self.per_actor.get_mut(actor as usize) {
                *c += 1;
            }
        }
    }

    fn flow(mut self, seconds: f64) -> anyhow::Result<Flow> {
        let n = self.latencies_ns.len();
        if n == 0 {
            bail!("no message arrived in the {seconds:.2} s window");
        }
        std::hint::black_box(&self.store);
        self.latencies_ns.sort_unstable();
        let pct = |p: f64| self.latencies_ns[((n as f64 * p) as usize).min(n - 1)] as f64 / 1e3;
        Ok(Flow {
            transitions_per_s: self.transitions as f64 / seconds,
            messages_per_s: n as f64 / seconds,
            latency_mean_us: self.latencies_ns.iter().map(|&v| v as f64).sum::<f64>() / n as f64 / 1e3,
            latency_p50_us: pct(0.5),
            latency_p99_us: pct(0.99),
            messages: n as u64,
            seconds,
            per_actor_messages: self.per_actor,
            startup_s: None,
        })
    }
}

// ---------------------------------------------------------------------------------------------------
// iceoryx2, across processes
// ---------------------------------------------------------------------------------------------------

/// One running publisher process.
struct Publisher {
    child: Child,
    program: String,
    log: PathBuf,
}

/// Owns the publisher processes: whatever is still running when it is dropped is killed and reaped.
#[derive(Default)]
struct Publishers(Vec<Publisher>);

impl Drop for Publishers {
    fn drop(&mut self) {
        for p in &mut self.0 {
            if matches!(p.child.try_wait(), Ok(None)) {
                let _ = p.child.kill();
            }
            let _ = p.child.wait();
        }
    }
}

fn log_tail(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    let tail = lines[lines.len().saturating_sub(15)..].join("\n");
    if tail.is_empty() {
        "(its log is empty)".into()
    } else {
        format!("its log {} ends:\n{tail}", path.display())
    }
}

impl Publishers {
    /// Fails when a publisher has exited (nobody should before they are told to stop).
    fn check_running(&mut self) -> anyhow::Result<()> {
        for (k, p) in self.0.iter_mut().enumerate() {
            if let Some(status) = p.child.try_wait()? {
                bail!("publisher process {k} ({}) exited early ({status}); {}", p.program, log_tail(&p.log));
            }
        }
        Ok(())
    }

    /// SIGTERM to every publisher, `drain` while they stop, SIGKILL after [`STOP_GRACE`]; errors when one
    /// failed or had to be killed.
    fn stop(&mut self, mut drain: impl FnMut()) -> anyhow::Result<()> {
        for p in &self.0 {
            // SAFETY: kill with a pid we spawned and have not reaped yet.
            unsafe { libc::kill(p.child.id() as libc::pid_t, libc::SIGTERM) };
        }
        let started = Instant::now();
        let mut status = vec![None; self.0.len()];
        while status.iter().any(Option::is_none) && started.elapsed() < STOP_GRACE {
            drain();
            for (s, p) in status.iter_mut().zip(&mut self.0) {
                if s.is_none() {
                    *s = p.child.try_wait()?;
                }
            }
        }
        for (k, (s, p)) in status.iter().zip(&mut self.0).enumerate() {
            match s {
                Some(st) if st.success() => {}
                Some(st) => bail!("publisher process {k} ({}) failed ({st}); {}", p.program, log_tail(&p.log)),
                None => {
                    let _ = p.child.kill();
                    let _ = p.child.wait();
                    bail!(
                        "publisher process {k} ({}) did not stop within {} s of SIGTERM and was killed; {}",
                        p.program,
                        STOP_GRACE.as_secs(),
                        log_tail(&p.log)
                    );
                }
            }
        }
        Ok(())
    }
}

/// A termination request (Ctrl-C, SIGTERM), asked of the node at most every 10 ms.
struct Interrupt<'a> {
    node: &'a ipc::Node,
    last: Instant,
}

impl<'a> Interrupt<'a> {
    fn new(node: &'a ipc::Node) -> Self {
        Self { node, last: Instant::now() }
    }

    fn check(&mut self) -> anyhow::Result<()> {
        if self.last.elapsed() >= Duration::from_millis(10) {
            self.last = Instant::now();
            if ipc::wait(self.node, Duration::ZERO).is_err() {
                bail!("interrupted (Ctrl-C or SIGTERM)");
            }
        }
        Ok(())
    }
}

fn iceoryx2_flow(
    node: &ipc::Node,
    actors: usize,
    rate: f64,
    warmup: Duration,
    window: Duration,
    spawn: SpawnPublisher,
) -> anyhow::Result<Flow> {
    let dir = tempfile::Builder::new().prefix("bcal-bench-").tempdir().context("creating a temporary run folder")?;
    let mut cfg = TrainConfig::default();
    cfg.actors.count = Some(actors);
    let v = cfg.validate()?;
    let config_path = dir.path().join("config.toml");
    std::fs::write(&config_path, cfg.to_toml()).with_context(|| format!("writing {}", config_path.display()))?;
    let run = RunIpc::new(dir.path(), &v)?;
    let service = run.transitions(node, Role::Create)?;
    let mut intr = Interrupt::new(node);
    let subscriber = run.transition_subscriber(&service)?;

    let mut pubs = Publishers::default();
    let deadline_s = CONNECT_TIMEOUT.as_secs_f64() + warmup.as_secs_f64() + window.as_secs_f64() + 10.0;
    for id in 0..actors {
        let args = PublisherArgs { run_dir: dir.path().to_path_buf(), id: id as u32, seconds: deadline_s, rate };
        let mut cmd = spawn(&args);
        let program = cmd.get_program().to_string_lossy().into_owned();
        let log = dir.path().join(format!("publisher-{id}.log"));
        let log_file = std::fs::File::create(&log).with_context(|| format!("creating {}", log.display()))?;
        cmd.stdin(Stdio::null()).stdout(log_file.try_clone()?).stderr(log_file);
        let child =
            cmd.spawn().with_context(|| format!("cannot start the publisher process {program} (bench-publish)"))?;
        pubs.0.push(Publisher { child, program, log });
    }

    let mut rec = Recorder::new(actors);
    let receive = |rec: &mut Recorder, record: bool| -> anyhow::Result<Option<u32>> {
        match subscriber.receive().map_err(|e| anyhow::anyhow!("iceoryx2 receive failed: {e:?}"))? {
            Some(sample) => {
                let h: TransitionBatchHeader = *sample.user_header();
                rec.take(sample.payload(), h.sent_mono_ns, h.actor_id, record);
                Ok(Some(h.actor_id))
            }
            None => {
                std::thread::yield_now();
                Ok(None)
            }
        }
    };

    // Every publisher delivers once, then warm-up, then the window.
    let started = Instant::now();
    let mut seen = vec![false; actors];
    let mut last_check = Instant::now();
    while seen.iter().any(|s| !s) {
        intr.check()?;
        if let Some(id) = receive(&mut rec, false)? {
            if let Some(s) = seen.get_mut(id as usize) {
                *s = true;
            }
        }
        if last_check.elapsed() > Duration::from_millis(10) {
            last_check = Instant::now();
            pubs.check_running()?;
            if started.elapsed() > CONNECT_TIMEOUT {
                let missing: Vec<usize> = (0..actors).filter(|&k| !seen[k]).collect();
                bail!(
                    "publisher processes {missing:?} delivered nothing within {} s; {}",
                    CONNECT_TIMEOUT.as_secs(),
                    log_tail(&pubs.0[missing[0]].log)
                );
            }
        }
    }
    let connected_s = started.elapsed().as_secs_f64();
    let t = Instant::now();
    while t.elapsed() < warmup {
        intr.check()?;
        receive(&mut rec, false)?;
    }
    let t0 = Instant::now();
    while t0.elapsed() < window {
        intr.check()?;
        receive(&mut rec, true)?;
    }
    let seconds = t0.elapsed().as_secs_f64();
    pubs.check_running()?;
    let mut drain_failed = None;
    pubs.stop(|| {
        if let Err(e) = receive(&mut rec, false) {
            drain_failed = Some(e);
        }
    })?;
    if let Some(e) = drain_failed {
        return Err(e);
    }
    drop(subscriber);
    let mut flow = rec.flow(seconds)?;
    flow.startup_s = Some(connected_s);
    Ok(flow)
}

/// Runs one publisher (the body of `bcal bench-publish`): sends batches until SIGTERM, the subscriber
/// goes away, the parent dies, or the deadline. Returns a one-line summary.
pub fn publish(args: &PublisherArgs) -> anyhow::Result<String> {
    // Die with the parent, whatever happens to it.
    // SAFETY: prctl(PR_SET_PDEATHSIG) takes a signal number and has no memory effects.
    unsafe { libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) };
    // SAFETY: getppid has no preconditions.
    let parent = unsafe { libc::getppid() };
    let config_path = args.run_dir.join("config.toml");
    let cfg = TrainConfig::from_file(&config_path)?;
    let v = cfg.validate()?;
    let run = RunIpc::new(&args.run_dir, &v)?;
    let (node, _) = ipc::create_node(&format!("bcal-bench-publisher-{}", args.id))?;
    let service = run.transitions(&node, Role::Open { timeout: Duration::from_secs(10) })?;
    let publisher = run.transition_publisher(&service)?;
    let n = run.limits.publish_batch;
    let batch = template(n, 0x5eed ^ u64::from(args.id));
    let started = Instant::now();
    let deadline = Duration::from_secs_f64(args.seconds);
    let period = (args.rate > 0.0).then(|| Duration::from_secs_f64(1.0 / args.rate));
    let epoch = monotonic_ns();
    let (mut seq, mut delivered, mut undelivered) = (0u64, 0u64, 0u64);
    let mut zero_since: Option<Instant> = None;
    let stop = loop {
        if started.elapsed() >= deadline {
            break "deadline";
        }
        if (period.is_some() || seq.is_multiple_of(16)) && ipc::wait(&node, Duration::ZERO).is_err() {
            break "terminated";
        }
        // SAFETY: getppid has no preconditions.
        if seq.is_multiple_of(256) && unsafe { libc::getppid() } != parent {
            break "parent gone";
        }
        if let Some(p) = period {
            let due = p * seq as u32;
            let now = started.elapsed();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
        let sample = publisher.loan_slice_uninit(n).map_err(|e| anyhow::anyhow!("loan failed: {e:?}"))?;
        let mut sample = sample.write_from_slice(&batch);
        *sample.user_header_mut() = TransitionBatchHeader {
            actor_id: args.id,
            len: n as u32,
            epoch,
            seq,
            published_before: seq * n as u64,
            weights_version: 0,
            sent_mono_ns: monotonic_ns(),
        };
        match sample.send() {
            Ok(n) if n > 0 => {
                delivered += 1;
                zero_since = None;
            }
            // No connected subscriber: not yet attached (it attaches on its next receive, and a full
            // buffer before that reads as "no receiver"), or gone. Back off; give up after a while.
            Ok(_) => {
                let since = *zero_since.get_or_insert_with(Instant::now);
                let limit = if delivered == 0 { Duration::from_secs(10) } else { Duration::from_secs(2) };
                if since.elapsed() > limit {
                    if delivered == 0 {
                        bail!("no subscriber connected within {} s", limit.as_secs());
                    }
                    break "subscriber gone";
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            // The subscriber's buffer for this publisher stayed full past the give-up time: it is serving
            // other publishers first (iceoryx2 drains connections in order). Counted; keep sending.
            Err(_) => undelivered += 1,
        }
        seq += 1;
    };
    Ok(format!(
        "publisher {}: sent {seq} messages, delivered {delivered}, undelivered after {} ms of back-pressure \
         {undelivered}; stopped: {stop}",
        args.id,
        ipc::PUBLISH_GIVE_UP.as_millis()
    ))
}

// ---------------------------------------------------------------------------------------------------
// crossbeam, in process (the baseline)
// ---------------------------------------------------------------------------------------------------

struct Msg {
    sent_ns: u64,
    actor: u32,
    batch: Box<[Transition]>,
}

fn crossbeam_flow(
    node: &ipc::Node,
    actors: usize,
    rate: f64,
    n: usize,
    warmup: Duration,
    window: Duration,
) -> anyhow::Result<Flow> {
    let (tx, rx) = crossbeam::channel::bounded::<Msg>(TRANSITION_BUFFER_MESSAGES * actors);
    let stop = Arc::new(AtomicBool::new(false));
    let period = (rate > 0.0).then(|| Duration::from_secs_f64(1.0 / rate));
    let senders: Vec<_> = (0..actors)
        .map(|id| {
            let (tx, stop) = (tx.clone(), stop.clone());
            let batch = template(n, 0x5eed ^ id as u64);
            std::thread::spawn(move || {
                let started = Instant::now();
                let mut seq = 0u32;
                while !stop.load(Ordering::Relaxed) {
                    if let Some(p) = period {
                        let due = p * seq;
                        let now = started.elapsed();
                        if due > now {
                            std::thread::sleep(due - now);
                        }
                    }
                    let batch: Box<[Transition]> = batch.as_slice().into();
                    if tx.send(Msg { sent_ns: monotonic_ns(), actor: id as u32, batch }).is_err() {
                        break;
                    }
                    seq += 1;
                }
            })
        })
        .collect();
    drop(tx);
    let mut rec = Recorder::new(actors);
    let mut intr = Interrupt::new(node);
    let mut run = |rec: &mut Recorder, d: Duration, record: bool| -> anyhow::Result<bool> {
        let t = Instant::now();
        while let Some(left) = d.checked_sub(t.elapsed()) {
            intr.check()?;
            match rx.recv_timeout(left.min(Duration::from_millis(10))) {
                Ok(m) => rec.take(&m.batch, m.sent_ns, m.actor, record),
                Err(crossbeam::channel::RecvTimeoutError::Timeout) => {}
                Err(crossbeam::channel::RecvTimeoutError::Disconnected) => return Ok(false),
            }
        }
        Ok(true)
    };
    let measured = (|| -> anyhow::Result<Option<f64>> {
        if !run(&mut rec, warmup, false)? {
            return Ok(None);
        }
        let t0 = Instant::now();
        if !run(&mut rec, window, true)? {
            return Ok(None);
        }
        Ok(Some(t0.elapsed().as_secs_f64()))
    })();
    // Stop and join the senders on every path (a sender blocked on a full channel wakes when rx drops).
    stop.store(true, Ordering::Relaxed);
    drop(rx);
    for s in senders {
        s.join().map_err(|_| anyhow::anyhow!("a crossbeam sender thread panicked"))?;
    }
    let seconds = measured?.context("a crossbeam sender thread stopped before the window ended")?;
    rec.flow(seconds)
}
