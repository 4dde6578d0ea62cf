//! Process supervision for `bcal train`: start children each in its own process group, watch them,
//! restart by policy, and stop the whole tree on request.
//!
//! Stop = SIGTERM to the child's group, a grace period, then SIGKILL to the group; children are always
//! reaped. The restart arithmetic ([`RestartPolicy`]) and the decision table ([`decide`]) are pure functions
//! with unit tests; only [`Supervised`] touches real processes.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;
use tokio::process::{Child, Command};

/// When and how often a crashed child is restarted.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RestartPolicy {
    /// Restarts allowed before the run is stopped.
    pub max_restarts: u32,
    /// Delay before the first restart.
    pub initial_delay: Duration,
    /// Each further restart waits this factor longer.
    pub backoff: f64,
    /// Upper bound of the delay.
    pub max_delay: Duration,
    /// Fraction of the delay added at random (0..jitter), so restarted peers do not move in lockstep.
    pub jitter: f64,
}

impl Default for RestartPolicy {
    fn default() -> Self {
        Self {
            max_restarts: 5,
            initial_delay: Duration::from_millis(500),
            backoff: 2.0,
            max_delay: Duration::from_secs(10),
            jitter: 0.2,
        }
    }
}

impl RestartPolicy {
    /// Delay before restart number `n` (1-based), with `unit_random` in [0, 1) supplying the jitter;
    /// `None` once the restarts are used up.
    pub fn delay(&self, n: u32, unit_random: f64) -> Option<Duration> {
        if n == 0 || n > self.max_restarts {
            return None;
        }
        let base = self.initial_delay.as_secs_f64() * self.backoff.powi(n as i32 - 1);
        let capped = base.min(self.max_delay.as_secs_f64());
        Some(Duration::from_secs_f64(capped * (1.0 + self.jitter * unit_random.clamp(0.0, 1.0))))
    }
}

/// The role of a child process; decides what its exit means.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Role {
    Replay,
    Learner,
    Actor(usize),
}

impl Role {
    pub fn name(self) -> String {
        match self {
            Role::Replay => "replay".into(),
            Role::Learner => "learner".into(),
            Role::Actor(k) => format!("actor-{k}"),
        }
    }
}

/// How a child ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Exit {
    /// Exit code 0.
    Clean,
    /// Non-zero exit code.
    Failed(i32),
    /// Killed by a signal.
    Signalled(i32),
}

impl Exit {
    pub fn from_status(s: std::process::ExitStatus) -> Self {
        use std::os::unix::process::ExitStatusExt;
        match (s.code(), s.signal()) {
            (Some(0), _) => Exit::Clean,
            (Some(c), _) => Exit::Failed(c),
            (None, Some(sig)) => Exit::Signalled(sig),
            (None, None) => Exit::Failed(-1),
        }
    }
}

/// What the supervisor does about an exit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Decision {
    /// Training is over (the learner finished its budget): stop everything, success.
    Finish,
    /// Restart this child (the learner resumes from its last checkpoint).
    Restart,
    /// Stop everything, the run failed.
    Abort,
}

/// The decision table. `learner_done` is true when the learner left its done marker (it met its budget).
pub fn decide(role: Role, exit: Exit, learner_done: bool, restarts_used: u32, policy: &RestartPolicy) -> Decision {
    if learner_done {
        return Decision::Finish;
    }
    match (role, exit) {
        // A learner that exits cleanly without the done marker was told to stop: not a crash, and nothing
        // is left to train with, so the run ends.
        (Role::Learner, Exit::Clean) => Decision::Finish,
        _ if restarts_used >= policy.max_restarts => Decision::Abort,
        _ => Decision::Restart,
    }
}

/// A running child in its own process group, its output appended to a log file.
pub struct Supervised {
    pub role: Role,
    pub child: Child,
    pub pid: i32,
    pub restarts: u32,
}

/// Starts `program args` as `role` in a new process group, output appended to `log`.
pub fn spawn(
    role: Role,
    program: &Path,
    args: &[String],
    log: &Path,
    env: &[(String, String)],
) -> std::io::Result<Supervised> {
    let out = std::fs::OpenOptions::new().create(true).append(true).open(log)?;
    let err = out.try_clone()?;
    let mut cmd = Command::new(program);
    cmd.args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::from(out))
        .stderr(Stdio::from(err))
        .process_group(0)
        .kill_on_drop(false);
    for (k, v) in env {
        cmd.env(k, v);
    }
    // A supervisor killed with `kill -9` cannot stop its tree: each child takes SIGTERM when its parent dies
    // (Linux's PR_SET_PDEATHSIG) and stops as on Ctrl-C, instead of running on and publishing into the next run
    // of its folder. (The signal follows the thread that forked: the supervision loop runs on the main thread,
    // which lives as long as the process.)
    let parent = std::process::id();
    // SAFETY: between fork and exec the closure calls only async-signal-safe functions (prctl, getppid, raise).
    unsafe {
        cmd.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The parent died before the call: nobody will signal.
            if libc::getppid() as u32 != parent {
                libc::raise(libc::SIGTERM);
            }
            Ok(())
        });
    }
    let child = cmd.spawn()?;
    let pid = child.id().map(|p| p as i32).unwrap_or(-1);
    Ok(Supervised { role, child, pid, restarts: 0 })
}

/// Sends `sig` to the child's whole process group.
pub fn signal_group(pid: i32, sig: i32) {
    if pid > 0 {
        // SAFETY: kill(2) with a negative pid targets the process group we created for this child.
        unsafe {
            libc::kill(-pid, sig);
        }
    }
}

/// SIGTERM, wait up to `grace`, then SIGKILL the group; always reaps. Returns how the child ended.
pub async fn stop(s: &mut Supervised, grace: Duration) -> Option<Exit> {
    if let Ok(Some(st)) = s.child.try_wait() {
        return Some(Exit::from_status(st));
    }
    signal_group(s.pid, libc::SIGTERM);
    match tokio::time::timeout(grace, s.child.wait()).await {
        Ok(Ok(st)) => {
            // The leader is gone; make sure nothing else of its group lingers.
            signal_group(s.pid, libc::SIGKILL);
            Some(Exit::from_status(st))
        }
        _ => {
            signal_group(s.pid, libc::SIGKILL);
            s.child.wait().await.ok().map(Exit::from_status)
        }
    }
}

/// Directory holding the bcal process binaries: `$BCAL_BIN_DIR`, else the folder of the running `bcal`.
pub fn bin_dir() -> anyhow::Result<PathBuf> {
    if let Some(d) = std::env::var_os("BCAL_BIN_DIR") {
        return Ok(PathBuf::from(d));
    }
    let exe = std::env::current_exe()?;
    Ok(exe.parent().map(Path::to_path_buf).unwrap_or_else(|| PathBuf::from(".")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_grows_caps_and_ends() {
        let p = RestartPolicy::default();
        assert_eq!(p.delay(0, 0.0), None);
        assert_eq!(p.delay(1, 0.0), Some(Duration::from_millis(500)));
        assert_eq!(p.delay(2, 0.0), Some(Duration::from_secs(1)));
        assert_eq!(p.delay(3, 0.0), Some(Duration::from_secs(2)));
        // Jitter adds at most 20 %.
        assert_eq!(p.delay(1, 0.5), Some(Duration::from_millis(550)));
        let capped = RestartPolicy { max_restarts: 20, ..p };
        assert_eq!(capped.delay(10, 0.0), Some(Duration::from_secs(10)));
        assert_eq!(p.delay(6, 0.0), None);
    }

    #[test]
    fn decision_table() {
        let p = RestartPolicy::default();
        assert_eq!(decide(Role::Actor(0), Exit::Signalled(9), false, 0, &p), Decision::Restart);
        assert_eq!(decide(Role::Actor(1), Exit::Failed(101), false, 5, &p), Decision::Abort);
        assert_eq!(decide(Role::Learner, Exit::Signalled(9), false, 0, &p), Decision::Restart);
        assert_eq!(decide(Role::Learner, Exit::Clean, false, 0, &p), Decision::Finish);
        assert_eq!(decide(Role::Replay, Exit::Signalled(9), false, 1, &p), Decision::Restart);
        assert_eq!(decide(Role::Actor(0), Exit::Clean, true, 0, &p), Decision::Finish);
    }

    #[tokio::test]
    async fn stop_terminates_and_reaps_a_real_process_group() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("sleep.log");
        // A shell that spawns a grandchild: both are in the group and both must go.
        let mut s = spawn(
            Role::Actor(0),
            Path::new("/bin/sh"),
            &["-c".into(), "sleep 30 & echo started; wait".into()],
            &log,
            &[],
        )
        .unwrap();
        tokio::time::sleep(Duration::from_millis(200)).await;
        let exit = stop(&mut s, Duration::from_secs(2)).await;
        assert_eq!(exit, Some(Exit::Signalled(libc::SIGTERM)));
        // No live member of the group is left (an orphaned grandchild may linger as a zombie until init
        // reaps it; a zombie runs nothing).
        let mut live = live_group_members(s.pid);
        for _ in 0..20 {
            if live == 0 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
            live = live_group_members(s.pid);
        }
        assert_eq!(live, 0, "the process group survived");
        assert!(std::fs::read_to_string(&log).unwrap().contains("started"));
    }

    /// Processes of group `pgid` that are not zombies, from /proc/<pid>/stat.
    fn live_group_members(pgid: i32) -> usize {
        let mut n = 0;
        for e in std::fs::read_dir("/proc").unwrap().flatten() {
            let Ok(stat) = std::fs::read_to_string(e.path().join("stat")) else { continue };
            // Fields after the parenthesised command name: state, ppid, pgrp, ...
            let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else { continue };
            let f: Vec<&str> = rest.split_whitespace().collect();
            if f.len() > 2 && f[2].parse::<i32>() == Ok(pgid) && f[0] != "Z" {
                n += 1;
            }
        }
        n
    }

    #[tokio::test]
    async fn stop_kills_a_child_that_ignores_sigterm() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = spawn(
            Role::Learner,
            Path::new("/bin/sh"),
            &["-c".into(), "trap '' TERM; echo ready; while true; do sleep 0.1; done".into()],
            &dir.path().join("l.log"),
            &[],
        )
        .unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let exit = stop(&mut s, Duration::from_millis(500)).await;
        assert_eq!(exit, Some(Exit::Signalled(libc::SIGKILL)));
    }
}
