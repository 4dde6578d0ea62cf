//! Shared harness for end-to-end tests across real bcal processes: a temporary run folder with a config
//! and an MDP, a command wrapper that starts a bcal binary with its log in the run folder, sends it
//! signals and reaps it (never leaving a stray process), and a dump of every log when a test fails.
//!
//! Finding the binaries: `CARGO_BIN_EXE_*` only exists for a package's own binaries, so the harness
//! derives the target folder from the test executable (`target/<profile>/deps/<test>` -> `target/<profile>`)
//! and, once per test process, runs `cargo build -p <package> --bin <name>` with that profile and target
//! folder so the binary is never stale (a no-op when it is up to date; cargo has released its lock
//! while tests run). Set `BCAL_TEST_NO_BUILD=1` to skip the build and use what is there (CI that built
//! everything first), or `BCAL_BIN_DIR` to take binaries from another folder.

use bcal_common::battery::BatteryModel;
use bcal_common::config::{TrainConfig, Validated};
use bcal_common::dataset::{default_cache_dir, load_or_generate, Dataset, Split};
use bcal_common::mdp::MdpSpec;
use bcal_common::task::Task;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// A temporary run folder with `config.toml` and `mdp.json` as the supervisor would write them.
pub struct RunFolder {
    dir: tempfile::TempDir,
    pub config: TrainConfig,
    pub validated: Validated,
    /// The run's task, as `mdp.json` holds it.
    pub task: Task,
    /// The experiment's training split (the paper MDP's scales come from it); None for a measured task.
    pub dataset: Option<Dataset>,
}

impl RunFolder {
    /// Writes `config` (validated first) and the task of its experiment and observation; a paper task's
    /// dataset comes from the cache.
    pub fn new(config: TrainConfig) -> Self {
        let validated = config.validate().expect("test config validates");
        let dir = tempfile::Builder::new().prefix("bcal-test-").tempdir().expect("temp run folder");
        std::fs::write(dir.path().join("config.toml"), config.to_toml()).expect("write config.toml");
        let (task, dataset) = match config.env.observation.paper_kind() {
            Some(_) => {
                let (dataset, _) =
                    load_or_generate(&validated.def, &BatteryModel::default(), &default_cache_dir(), Split::Train)
                        .expect("dataset");
                (Task::Paper(MdpSpec::new(config.experiment, &config.env, &dataset)), Some(dataset))
            }
            None => (Task::Measured(config.measured.clone()), None),
        };
        std::fs::write(dir.path().join("mdp.json"), serde_json::to_string_pretty(&task).unwrap()).unwrap();
        std::fs::create_dir_all(dir.path().join("logs")).unwrap();
        Self { dir, config, validated, task, dataset }
    }

    pub fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Reads a JSON file of the run folder (None while it does not exist or is being replaced).
    pub fn json(&self, rel: &str) -> Option<serde_json::Value> {
        let text = std::fs::read_to_string(self.path().join(rel)).ok()?;
        serde_json::from_str(&text).ok()
    }

    /// Every process log of the run, for a failure message.
    pub fn logs(&self) -> String {
        let mut out = String::new();
        if let Ok(rd) = std::fs::read_dir(self.path().join("logs")) {
            let mut paths: Vec<PathBuf> = rd.flatten().map(|e| e.path()).collect();
            paths.sort();
            for p in paths {
                let text = std::fs::read_to_string(&p).unwrap_or_default();
                let tail: String =
                    text.lines().rev().take(40).collect::<Vec<_>>().into_iter().rev().collect::<Vec<_>>().join("\n");
                out.push_str(&format!("----- {} (last 40 lines)\n{tail}\n", p.display()));
            }
        }
        out
    }

    /// Keeps the folder after the test (for debugging a failure); returns its path.
    pub fn keep(self) -> PathBuf {
        self.dir.keep()
    }
}

/// Workspace root (this crate lives in `<root>/tests`).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// `target/<profile>` of the running test executable.
fn profile_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let deps = exe.parent().expect("deps folder");
    deps.parent().expect("profile folder").to_path_buf()
}

/// The packages whose binaries the tests start. They are built by one command, so cargo resolves one
/// feature set for them: building each alone (`-p bcal-replay`) resolves another set per package and
/// recompiles the dependencies each time on a fresh machine. launch/test.sh runs the same command
/// before the tests.
const BIN_PACKAGES: &[&str] = &["bcal", "bcal-replay", "bcal-actor", "bcal-learner"];

static BUILT: Mutex<bool> = Mutex::new(false);

/// Path of a workspace binary (`bcal-replay`, `bcal-actor`, `bcal-learner`, `bcal`); all four are built
/// (or found up to date) on the first call.
pub fn bin(name: &str) -> PathBuf {
    if let Some(dir) = std::env::var_os("BCAL_BIN_DIR") {
        return PathBuf::from(dir).join(name);
    }
    let profile_dir = profile_dir();
    let path = profile_dir.join(name);
    if std::env::var_os("BCAL_TEST_NO_BUILD").is_some() {
        assert!(path.exists(), "{} missing and BCAL_TEST_NO_BUILD is set", path.display());
        return path;
    }
    let mut built = BUILT.lock().unwrap_or_else(|e| e.into_inner());
    if !*built {
        let profile = profile_dir.file_name().and_then(|s| s.to_str()).unwrap_or("debug").to_string();
        let target_dir = profile_dir.parent().expect("target folder");
        let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
        let mut cmd = Command::new(cargo);
        cmd.current_dir(workspace_root()).args(["build", "--quiet", "--bins"]);
        for p in BIN_PACKAGES {
            cmd.args(["-p", p]);
        }
        cmd.arg("--target-dir").arg(target_dir);
        match profile.as_str() {
            "debug" => {}
            "release" => {
                cmd.arg("--release");
            }
            other => {
                cmd.args(["--profile", other]);
            }
        }
        let status = cmd.status().expect("run cargo build");
        assert!(status.success(), "cargo build of {BIN_PACKAGES:?} failed");
        *built = true;
    }
    assert!(path.exists(), "{} was not built", path.display());
    path
}

/// A started bcal process; killed (SIGKILL) and reaped on drop if the test did not stop it.
pub struct Proc {
    pub name: String,
    child: Child,
    status: Option<ExitStatus>,
}

impl Proc {
    /// Starts `bin(exe)` with `args`; stdout and stderr go to `<run>/logs/<name>.log`.
    pub fn start(run: &RunFolder, name: &str, exe: &str, args: &[&str]) -> Self {
        Self::start_with(run, name, exe, args, |_| {})
    }

    /// As [`Proc::start`], with `configure` applied to the command first (limits, environment).
    pub fn start_with(
        run: &RunFolder,
        name: &str,
        exe: &str,
        args: &[&str],
        configure: impl FnOnce(&mut Command),
    ) -> Self {
        let log = std::fs::File::create(run.path().join("logs").join(format!("{name}.log"))).expect("log file");
        let mut cmd = Command::new(bin(exe));
        configure(&mut cmd);
        let child = cmd
            .args(args)
            .stdin(Stdio::null())
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {exe}: {e}"));
        Self { name: name.to_string(), child, status: None }
    }

    pub fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    pub fn signal(&self, sig: i32) {
        if self.status.is_none() {
            // SAFETY: kill(2) on our own child's pid; it is not reaped yet, so the pid is still ours.
            unsafe {
                libc::kill(self.pid(), sig);
            }
        }
    }

    /// The exit status if the process has ended.
    pub fn try_status(&mut self) -> Option<ExitStatus> {
        if self.status.is_none() {
            self.status = self.child.try_wait().expect("try_wait");
        }
        self.status
    }

    /// Waits up to `timeout` for the exit; None if still running.
    pub fn wait_timeout(&mut self, timeout: Duration) -> Option<ExitStatus> {
        let start = Instant::now();
        while start.elapsed() < timeout {
            if let Some(s) = self.try_status() {
                return Some(s);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        self.try_status()
    }

    /// SIGTERM, then wait up to `grace`; returns the exit status (None = still running, then killed).
    pub fn terminate(&mut self, grace: Duration) -> Option<ExitStatus> {
        self.signal(libc::SIGTERM);
        let s = self.wait_timeout(grace);
        if s.is_none() {
            self.signal(libc::SIGKILL);
            let _ = self.child.wait();
        }
        s
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if self.try_status().is_none() {
            self.signal(libc::SIGKILL);
            let _ = self.child.wait();
        }
    }
}

/// Polls `cond` every 50 ms until it holds or `timeout` passes; returns whether it held.
pub fn wait_until(timeout: Duration, mut cond: impl FnMut() -> bool) -> bool {
    let start = Instant::now();
    loop {
        if cond() {
            return true;
        }
        if start.elapsed() >= timeout {
            return false;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A u64 field of a JSON value (0 when absent).
pub fn field(v: &Option<serde_json::Value>, key: &str) -> u64 {
    v.as_ref().and_then(|v| v.get(key)).and_then(|x| x.as_u64()).unwrap_or(0)
}

/// A small, fast config on the `multi` experiment: tiny networks, small batches, limits that a short test
/// reaches.
pub fn tiny_config(actors: usize) -> TrainConfig {
    let mut c = TrainConfig { seed: 7, ..TrainConfig::default() };
    c.lac.hidden = vec![16, 16];
    c.lac.batch_size = 32;
    c.replay.capacity = 100_000;
    c.replay.learning_starts = 256;
    c.actors.count = Some(actors);
    c.actors.envs_per_actor = 8;
    c.actors.publish_batch = 32;
    c.learner.weights_every = 10;
    c.learner.checkpoint_every = 200;
    c.learner.validate_every = 200;
    c.learner.validate_trajectories = 2;
    c.learner.max_updates = 0;
    c.learner.time_budget_s = 60.0;
    c
}

/// True while a process with this pid runs (a zombie, dead but not yet reaped by whoever adopted it,
/// counts as dead: it holds no memory, files or locks).
pub fn alive(pid: i32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // The state letter follows the parenthesised command name.
        Ok(stat) => stat.rsplit(')').next().and_then(|r| r.split_whitespace().next()).is_some_and(|st| st != "Z"),
        Err(_) => false,
    }
}

/// Sends `sig` to `pid` (no-op when it is gone).
pub fn signal(pid: i32, sig: i32) {
    // SAFETY: kill(2) with a pid read from our own run's logs; at worst ESRCH.
    unsafe {
        libc::kill(pid, sig);
    }
}

/// A `bcal train` supervisor started on a fresh run folder (`<tmp>/run`), the way a user runs it.
/// On drop every process it ever started (pids from `logs/supervisor.log`) and itself are killed, so a
/// failing test leaves no strays.
pub struct Train {
    dir: tempfile::TempDir,
    pub run_dir: PathBuf,
    pub config: TrainConfig,
    pub sup: Proc,
    config_path: PathBuf,
}

impl Train {
    /// Writes `config` beside the run folder and starts `bcal train --config .. --run <tmp>/run`.
    pub fn start(config: TrainConfig, extra: &[&str]) -> Self {
        config.validate().expect("test config validates");
        let dir = tempfile::Builder::new().prefix("bcal-train-").tempdir().expect("temp folder");
        let config_path = dir.path().join("config.toml");
        std::fs::write(&config_path, config.to_toml()).expect("write config");
        let run_dir = dir.path().join("run");
        let sup = Self::spawn(dir.path(), &run_dir, &config_path, extra, "supervisor");
        Self { dir, run_dir, config, sup, config_path }
    }

    fn spawn(dir: &Path, run_dir: &Path, config: &Path, extra: &[&str], log: &str) -> Proc {
        let out = std::fs::File::create(dir.join(format!("{log}.out"))).expect("supervisor output");
        let mut args: Vec<String> =
            vec!["train".into(), "--run".into(), run_dir.display().to_string(), "--grace-s".into(), "10".into()];
        if !extra.contains(&"--resume") {
            args.extend(["--config".into(), config.display().to_string()]);
        }
        args.extend(extra.iter().map(|s| s.to_string()));
        let child = Command::new(bin("bcal"))
            .args(&args)
            .stdin(Stdio::null())
            .stdout(out.try_clone().unwrap())
            .stderr(out)
            .spawn()
            .expect("start bcal train");
        Proc { name: log.to_string(), child, status: None }
    }

    /// Starts `bcal train --resume` on the same run folder (after the first supervisor ended).
    pub fn resume(&mut self, extra: &[&str]) {
        let mut args = vec!["--resume"];
        args.extend_from_slice(extra);
        self.sup = Self::spawn(self.dir.path(), &self.run_dir, &self.config_path, &args, "supervisor-resumed");
    }

    /// Reads a JSON file of the run folder.
    pub fn json(&self, rel: &str) -> Option<serde_json::Value> {
        let text = std::fs::read_to_string(self.run_dir.join(rel)).ok()?;
        serde_json::from_str(&text).ok()
    }

    /// Every line of metrics.jsonl that parses.
    pub fn metrics(&self) -> Vec<serde_json::Value> {
        std::fs::read_to_string(self.run_dir.join("metrics.jsonl"))
            .unwrap_or_default()
            .lines()
            .filter_map(|l| serde_json::from_str(l).ok())
            .collect()
    }

    /// Highest learner update in metrics.jsonl.
    pub fn last_update(&self) -> u64 {
        self.metrics().iter().filter_map(|v| v["update"].as_u64()).max().unwrap_or(0)
    }

    pub fn supervisor_log(&self) -> String {
        std::fs::read_to_string(self.run_dir.join("logs/supervisor.log")).unwrap_or_default()
    }

    /// (role, pid) of every `started`/`restarted` line of supervisor.log, in order.
    pub fn started(&self) -> Vec<(String, i32)> {
        self.supervisor_log()
            .lines()
            .filter_map(|l| {
                let rest = l.split("] ").nth(1)?;
                let mut w = rest.split_whitespace();
                let verb = w.next()?;
                if verb != "started" && verb != "restarted" {
                    return None;
                }
                let role = w.next()?.to_string();
                let pid = rest.rsplit("pid ").next()?.trim().parse().ok()?;
                Some((role, pid))
            })
            .collect()
    }

    /// The newest pid the supervisor started for `role` ("replay", "learner", "actor-0", ...).
    pub fn pid(&self, role: &str) -> Option<i32> {
        self.started().into_iter().rev().find(|(r, _)| r == role).map(|(_, p)| p)
    }

    /// Supervisor output and every process log, for a failure message.
    pub fn logs(&self) -> String {
        let mut out = String::new();
        for name in ["supervisor.out", "supervisor-resumed.out"] {
            if let Ok(t) = std::fs::read_to_string(self.dir.path().join(name)) {
                out.push_str(&format!("----- {name}\n{t}\n"));
            }
        }
        if let Ok(rd) = std::fs::read_dir(self.run_dir.join("logs")) {
            let mut paths: Vec<PathBuf> = rd.flatten().map(|e| e.path()).collect();
            paths.sort();
            for p in paths {
                let text = std::fs::read_to_string(&p).unwrap_or_default();
                let tail: Vec<&str> = text.lines().rev().take(30).collect();
                let tail: Vec<&str> = tail.into_iter().rev().collect();
                out.push_str(&format!("----- {} (last 30 lines)\n{}\n", p.display(), tail.join("\n")));
            }
        }
        out
    }

    /// SIGKILL to every process of the run, supervisor first (a crash of the whole tree).
    pub fn kill_all(&mut self) {
        self.sup.signal(libc::SIGKILL);
        let _ = self.sup.wait_timeout(Duration::from_secs(5));
        for (_, pid) in self.started() {
            signal(pid, libc::SIGKILL);
        }
        // The children were the supervisor's; once it is gone, init reaps them.
        wait_until(Duration::from_secs(10), || self.started().iter().all(|(_, p)| !alive(*p)));
    }
}

impl Drop for Train {
    fn drop(&mut self) {
        if self.sup.try_status().is_none() || self.started().iter().any(|(_, p)| alive(*p)) {
            self.kill_all();
        }
    }
}

/// A bcal process whose standard input the test writes and whose output lines it reads as they come
/// (`bcal calibrate --follow -`): stdout lines arrive over a channel, stderr is collected whole. Killed
/// and reaped on drop if the test did not end it.
pub struct Piped {
    child: Child,
    stdin: Option<std::process::ChildStdin>,
    lines: std::sync::mpsc::Receiver<String>,
    stderr: std::sync::Arc<Mutex<String>>,
    status: Option<ExitStatus>,
}

impl Piped {
    /// Starts `bin(exe)` with `args`, every stream piped.
    pub fn start(exe: &str, args: &[&str]) -> Self {
        use std::io::{BufRead, Read};
        let mut child = Command::new(bin(exe))
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {exe}: {e}"));
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, lines) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    return;
                }
            }
        });
        let stderr = std::sync::Arc::new(Mutex::new(String::new()));
        let (mut err_pipe, sink) = (child.stderr.take().expect("piped stderr"), stderr.clone());
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n) = err_pipe.read(&mut buf) {
                if n == 0 {
                    return;
                }
                sink.lock().unwrap_or_else(|e| e.into_inner()).push_str(&String::from_utf8_lossy(&buf[..n]));
            }
        });
        let stdin = child.stdin.take();
        Self { child, stdin, lines, stderr, status: None }
    }

    pub fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// Writes `line` and a newline to the process's standard input and flushes it.
    pub fn write_line(&mut self, line: &str) {
        use std::io::Write;
        let stdin = self.stdin.as_mut().expect("stdin still open");
        writeln!(stdin, "{line}").and_then(|_| stdin.flush()).expect("write to the process");
    }

    /// Closes standard input (end of input for the process).
    pub fn close_stdin(&mut self) {
        self.stdin = None;
    }

    /// The next stdout line, waiting up to `timeout`.
    pub fn next_line(&self, timeout: Duration) -> Option<String> {
        self.lines.recv_timeout(timeout).ok()
    }

    /// Everything the process wrote to stderr so far.
    pub fn stderr(&self) -> String {
        self.stderr.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Waits up to `timeout` for the exit; None if still running.
    pub fn wait_timeout(&mut self, timeout: Duration) -> Option<ExitStatus> {
        let start = Instant::now();
        while self.status.is_none() && start.elapsed() < timeout {
            self.status = self.child.try_wait().expect("try_wait");
            if self.status.is_none() {
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        self.status
    }
}

impl Drop for Piped {
    fn drop(&mut self) {
        if self.status.is_none() && self.child.try_wait().ok().flatten().is_none() {
            signal(self.pid(), libc::SIGKILL);
            let _ = self.child.wait();
        }
    }
}

/// Writes a measured-only RL policy file (the default cell setting, one hidden layer of 8) with fixed,
/// non-zero weights: a policy whose actions move the estimate, for tests of `--calibrator rl:FILE` and the
/// Python package's `Calibrator("rl")`. `tests/examples/write_policy.rs` writes one from the command line.
pub fn write_test_policy(path: &Path) {
    let task = Task::Measured(bcal_common::measured::env::MeasuredSpec::default());
    save_policy(path, task, |k| 0.3 * (k as f32 * 1.618).sin());
}

/// A policy file of `task` with zero weights (hidden layer of 8), saved as `dir/name`: what the CLI's
/// checks of a policy read (its task, observation and layout), not a trained one.
pub fn zero_policy(dir: &Path, name: &str, task: Task) -> PathBuf {
    let path = dir.join(name);
    save_policy(&path, task, |_| 0.0);
    path
}

/// A policy of `task` (one hidden layer of 8), weight k `weight(k)`, saved at `path`.
fn save_policy(path: &Path, task: Task, weight: impl Fn(usize) -> f32) {
    use bcal_common::policy::{PolicyFile, PolicyLayout};
    let layout = PolicyLayout { obs_dim: task.obs_dim(), act_dim: task.act_dim(), hidden: vec![8] };
    let params = (0..layout.n_params()).map(weight).collect();
    let pf = PolicyFile { params, layout, task, experiment: bcal_common::dataset::Experiment::Multi, update_step: 1 };
    pf.save(path).expect("write the policy file");
}
