//! Faults with real processes and real signals, each pinning one line of the reliability issue:
//!
//! - `kill -9` of an actor, of the learner and of the replay under `bcal train`: the supervisor restarts
//!   the victim, the others carry on (and reconnect), the learner resumes from its last checkpoint, the
//!   replay from its snapshot when snapshots are on;
//! - the whole tree killed with `kill -9`: its stale iceoryx2 resources do not stop the next run;
//! - Ctrl-C stops the tree within seconds, leaving a usable checkpoint and no stray process (exit 130, the
//!   resume said); `kill -9` of the supervisor alone leaves no stray either;
//! - a full disk while checkpointing: a clear error, the previous checkpoint kept;
//! - a peer built with another wire layout: refused with a clear message, never fed garbage;
//! - shared memory: not writable by other users.
//!
//! Training uses both cores, so the tests of this file run one at a time (the mutex under `cargo test`,
//! the `training` test group of .config/nextest.toml under nextest).

use bcal_common::config::TrainConfig;
use bcal_common::ipc::{self as bipc, Role, RunIpc};
use bcal_common::wire::WIRE_VERSION;
use bcal_tests::{alive, field, signal, tiny_config, wait_until, Proc, RunFolder, Train};
use std::time::{Duration, Instant};

static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// A small config the supervisor trains for longer than any test needs (tests stop it with Ctrl-C).
fn supervised_config(actors: usize) -> TrainConfig {
    let mut c = tiny_config(actors);
    c.learner.time_budget_s = 300.0;
    c.learner.checkpoint_every = 100;
    c.learner.validate_every = 0;
    c.replay.snapshot_every_s = 0.0;
    // Tiny actors outrun the limiter's first verdict by tens of thousands of transitions, which at 16 samples
    // per insert a slow CI learner needs over a minute to sample down, with every actor throttled meanwhile;
    // at 2 the tree is back to publishing within seconds, so the liveness waits below measure restarts, not
    // that backlog.
    c.replay.samples_per_insert = 2.0;
    c
}

/// Waits for the learner to pass `update`, with the run's logs on failure.
fn wait_update(t: &Train, update: u64, within: Duration) {
    assert!(wait_until(within, || t.last_update() >= update), "never reached update {update}\n{}", t.logs());
}

/// Ctrl-C to the supervisor; returns the exit code and how long the stop took.
fn ctrl_c(t: &mut Train) -> (Option<i32>, Duration) {
    let t0 = Instant::now();
    t.sup.signal(libc::SIGINT);
    let st = t.sup.wait_timeout(Duration::from_secs(40));
    (st.and_then(|s| s.code()), t0.elapsed())
}

fn latest_step(t: &Train) -> Option<u64> {
    let text = std::fs::read_to_string(t.run_dir.join("checkpoints/LATEST")).ok()?;
    text.trim().trim_start_matches("step-").parse().ok()
}

#[test]
fn kill9_of_an_actor_restarts_it_and_training_goes_on() {
    let _s = serial();
    let mut t = Train::start(supervised_config(2), &[]);
    wait_update(&t, 200, Duration::from_secs(90));
    let (replay, learner) = (t.pid("replay").unwrap(), t.pid("learner").unwrap());
    let victim = t.pid("actor-0").unwrap();
    let survivor = t.pid("actor-1").unwrap();

    let received = field(&t.json("replay.json"), "received_total");
    let killed_at = Instant::now();
    signal(victim, libc::SIGKILL);
    // A liveness wait, not a timing bound: the restarted actor first waits for weights and then for the
    // replay's insert credit, which the learner's pace decides (once more than 15 s on a CI machine).
    assert!(
        wait_until(Duration::from_secs(60), || {
            let a = t.json("actors/actor-0.json");
            field(&a, "pid") as i32 != victim && field(&a, "published_transitions") > 0
        }),
        "actor-0 was not restarted and publishing again\nactor-0.json: {:#?}\nreplay.json: {:#?}\n{}",
        t.json("actors/actor-0.json"),
        t.json("replay.json"),
        t.logs()
    );
    let restart_s = killed_at.elapsed().as_secs_f64();
    // Training goes on through the restart.
    let u = t.last_update();
    wait_update(&t, u + 200, Duration::from_secs(60));
    // The replay goes on receiving (the limiter paces actors to the learner, so slowly under load).
    assert!(
        wait_until(Duration::from_secs(30), || field(&t.json("replay.json"), "received_total") > received),
        "replay stopped receiving: {:#?}\n{}",
        t.json("replay.json"),
        t.logs()
    );
    // Nobody else noticed: same replay, same learner, same other actor; no other restart.
    assert_eq!(t.pid("replay"), Some(replay));
    assert_eq!(t.pid("learner"), Some(learner));
    assert_eq!(t.pid("actor-1"), Some(survivor));
    let restarts: Vec<_> = t.supervisor_log().lines().filter(|l| l.contains("restarted")).map(String::from).collect();
    assert_eq!(restarts.len(), 1, "{restarts:?}");
    assert!(restarts[0].contains("actor-0"), "{restarts:?}");
    eprintln!("actor-0 restarted and publishing again {restart_s:.1} s after kill -9");

    let (code, took) = ctrl_c(&mut t);
    assert_eq!(code, Some(130), "{}", t.logs());
    eprintln!("Ctrl-C stop took {:.1} s", took.as_secs_f64());
}

#[test]
fn kill9_of_the_learner_resumes_from_its_checkpoint_while_actors_keep_their_weights() {
    let _s = serial();
    let mut cfg = supervised_config(1);
    // Checkpoints come often, so the kill may well land during one: it must never leave a broken one.
    cfg.learner.checkpoint_every = 25;
    let mut t = Train::start(cfg, &[]);
    assert!(wait_until(Duration::from_secs(90), || latest_step(&t).unwrap_or(0) >= 300), "{}", t.logs());
    let (learner, actor, replay) = (t.pid("learner").unwrap(), t.pid("actor-0").unwrap(), t.pid("replay").unwrap());
    // The actor's counters file is refreshed every 2 s.
    assert!(
        wait_until(Duration::from_secs(10), || field(&t.json("actors/actor-0.json"), "weights_version") > 0),
        "{}",
        t.logs()
    );
    let actor_version = field(&t.json("actors/actor-0.json"), "weights_version");

    signal(learner, libc::SIGKILL);
    let lines_at_kill = t.metrics().len();
    // LATEST after the kill is what the restarted learner must resume from (a checkpoint in progress
    // at the kill never became LATEST).
    std::thread::sleep(Duration::from_millis(100));
    let step = latest_step(&t).expect("LATEST survives the kill");
    assert!(
        wait_until(Duration::from_secs(20), || t.pid("learner").is_some_and(|p| p != learner)),
        "learner not restarted\n{}",
        t.logs()
    );
    // While the learner was gone the actor kept running with the weights it had.
    assert!(alive(actor));
    assert!(field(&t.json("actors/actor-0.json"), "weights_version") >= actor_version);

    // The restarted learner continues the update counter from the checkpoint.
    assert!(wait_until(Duration::from_secs(60), || t.metrics().len() > lines_at_kill + 3), "{}", t.logs());
    let after: Vec<u64> = t.metrics()[lines_at_kill..].iter().filter_map(|v| v["update"].as_u64()).collect();
    assert!(after.iter().all(|u| *u >= step), "counter restarted below checkpoint {step}: {after:?}");
    // The restarted learner's first line says where it starts: exactly the checkpoint LATEST named.
    let first = &t.metrics()[lines_at_kill];
    assert_eq!(
        (first["kind"].as_str(), first["update"].as_u64(), first["resumed"].as_bool()),
        (Some("start"), Some(step), Some(true)),
        "{first}"
    );
    // New weights reach the same actor process.
    assert!(
        wait_until(Duration::from_secs(30), || field(&t.json("actors/actor-0.json"), "weights_version") > step),
        "{}",
        t.logs()
    );
    assert_eq!(t.pid("actor-0"), Some(actor));
    assert_eq!(t.pid("replay"), Some(replay));
    let (code, _) = ctrl_c(&mut t);
    assert_eq!(code, Some(130), "{}", t.logs());
    eprintln!("learner killed after checkpoint {step}; resumed at update {}", after[0]);
}

fn replay_kill9(snapshots: bool) {
    let _s = serial();
    let mut cfg = supervised_config(1);
    cfg.replay.snapshot_every_s = if snapshots { 1.0 } else { 0.0 };
    let mut t = Train::start(cfg, &[]);
    wait_update(&t, 200, Duration::from_secs(90));
    if snapshots {
        assert!(
            wait_until(Duration::from_secs(10), || field(&t.json("replay.json"), "snapshots_written") >= 1),
            "{}",
            t.logs()
        );
    }
    let (replay, learner, actor) = (t.pid("replay").unwrap(), t.pid("learner").unwrap(), t.pid("actor-0").unwrap());
    let published = field(&t.json("actors/actor-0.json"), "published_transitions");

    signal(replay, libc::SIGKILL);
    let killed_at = Instant::now();
    assert!(
        wait_until(Duration::from_secs(20), || {
            let r = t.json("replay.json");
            field(&r, "pid") as i32 != replay && r.is_some_and(|r| r["state"] == "running")
        }),
        "replay not restarted\n{}",
        t.logs()
    );
    let r = t.json("replay.json").unwrap();
    if snapshots {
        assert_eq!(r["started_from"], "snapshot", "{r:#}");
        assert!(r["restored_transitions"].as_u64().unwrap() > 0, "{r:#}");
    } else {
        assert_eq!(r["started_from"], "empty", "{r:#}");
        assert!(r["start_note"].as_str().unwrap().contains("disabled"), "{r:#}");
    }
    // Actor and learner reconnect by themselves: the same processes publish and train again.
    let u = t.last_update();
    wait_update(&t, u + 200, Duration::from_secs(90));
    assert!(
        wait_until(Duration::from_secs(20), || field(&t.json("actors/actor-0.json"), "published_transitions")
            > published + 1_000),
        "{}",
        t.logs()
    );
    assert_eq!(t.pid("learner"), Some(learner), "the learner should reconnect, not be restarted");
    assert_eq!(t.pid("actor-0"), Some(actor), "the actor should reconnect, not be restarted");
    eprintln!(
        "replay restarted from {} ({} transitions); training resumed within {:.1} s",
        r["started_from"],
        r["restored_transitions"],
        killed_at.elapsed().as_secs_f64()
    );
    let (code, _) = ctrl_c(&mut t);
    assert_eq!(code, Some(130), "{}", t.logs());
}

#[test]
fn kill9_of_the_replay_restores_its_snapshot_and_peers_reconnect() {
    replay_kill9(true);
}

#[test]
fn kill9_of_the_replay_without_snapshots_refills_and_peers_reconnect() {
    replay_kill9(false);
}

#[test]
fn ctrl_c_stops_the_tree_within_seconds_with_a_usable_checkpoint_and_no_strays() {
    let _s = serial();
    let mut cfg = supervised_config(2);
    cfg.learner.checkpoint_every = 1_000_000; // only the checkpoint written on the way out
    let mut t = Train::start(cfg, &[]);
    wait_update(&t, 150, Duration::from_secs(90));
    let before = t.last_update();
    let (code, took) = ctrl_c(&mut t);
    assert_eq!(code, Some(130), "{}", t.logs());
    assert!(took < Duration::from_secs(15), "stopping took {took:?}\n{}", t.logs());
    let pids = t.started();
    assert_eq!(pids.len(), 4, "{pids:?}");
    let strays: Vec<_> = pids.iter().filter(|(_, p)| alive(*p)).collect();
    assert!(strays.is_empty(), "stray processes after Ctrl-C: {strays:?}");
    let step = latest_step(&t).expect("a checkpoint on the way out");
    assert!(step >= before, "checkpoint {step} older than update {before} seen before Ctrl-C");
    assert!(t.run_dir.join("policy.bcalpol").exists());
    // Usable: a resumed run continues from it.
    t.resume(&[]);
    wait_update(&t, step + 100, Duration::from_secs(90));
    let (code, _) = ctrl_c(&mut t);
    assert_eq!(code, Some(130), "{}", t.logs());
    eprintln!("Ctrl-C stopped 4 processes in {:.1} s; resumed from checkpoint {step}", took.as_secs_f64());
}

#[test]
fn stale_resources_of_a_killed_run_do_not_block_the_next_run() {
    let _s = serial();
    let mut t = Train::start(supervised_config(1), &[]);
    wait_update(&t, 150, Duration::from_secs(90));
    // The whole tree dies at once: every iceoryx2 node and service of the run is left behind.
    t.kill_all();
    let step = latest_step(&t).expect("a periodic checkpoint before the crash");
    // Same run folder, so the very same service names: the new processes clean up and carry on.
    t.resume(&[]);
    wait_update(&t, step + 200, Duration::from_secs(90));
    // The learner may train on the restored buffer before the actors' first new batches land; the actors
    // must publish again, which replay.json (refreshed about once a second) shows.
    let received = wait_until(Duration::from_secs(60), || field(&t.json("replay.json"), "received_total") > 0);
    assert!(received, "no transition reached the resumed replay\n{}", t.logs());
    let (code, _) = ctrl_c(&mut t);
    assert_eq!(code, Some(130), "{}", t.logs());
    eprintln!("after kill -9 of the whole tree, the resumed run trained from {step} on");
}

/// `kill -9` of the supervisor alone: its children take SIGTERM as it dies (PR_SET_PDEATHSIG) and stop as on
/// Ctrl-C, leaving no stray (a fuzz of the CLI, 2026-11-30, found the replay and an actor running on for minutes,
/// and the orphan actor publishing into the next `--resume` of the folder); the resumed run trains on.
#[test]
fn kill9_of_the_supervisor_leaves_no_strays_and_the_run_resumes() {
    let _s = serial();
    let mut t = Train::start(supervised_config(1), &[]);
    wait_update(&t, 150, Duration::from_secs(90));
    let pids = t.started();
    assert_eq!(pids.len(), 3, "{pids:?}");
    t.sup.signal(libc::SIGKILL);
    let _ = t.sup.wait_timeout(Duration::from_secs(10));
    let gone = wait_until(Duration::from_secs(40), || pids.iter().all(|(_, p)| !alive(*p)));
    let strays: Vec<_> = pids.iter().filter(|(_, p)| alive(*p)).collect();
    assert!(gone, "stray processes after kill -9 of the supervisor: {strays:?}\n{}", t.logs());
    let step = latest_step(&t).expect("a checkpoint");
    t.resume(&[]);
    wait_update(&t, step + 100, Duration::from_secs(90));
    let (code, _) = ctrl_c(&mut t);
    assert_eq!(code, Some(130), "{}", t.logs());
    // A budget already spent (the budget counts every leg) is refused, naming it, not run for nothing.
    t.resume(&["--budget-s", "1"]);
    let code = t.sup.wait_timeout(Duration::from_secs(30)).and_then(|s| s.code());
    let out = std::fs::read_to_string(t.run_dir.parent().unwrap().join("supervisor-resumed.out")).unwrap_or_default();
    assert!(code == Some(1) && out.contains("nothing is left to train"), "{out}");
}

/// SIGTERM to the learner alone (from outside the supervisor): it checkpoints and exits cleanly before its
/// budget, and `bcal train` ends saying so, with how to continue, and exit 1 (it ended with exit 0 and "next:
/// bcal eval", as if the budget had been met: a fuzz of the CLI, 2026-11-30).
#[test]
fn a_learner_stopped_from_outside_ends_the_run_saying_so() {
    let _s = serial();
    let mut t = Train::start(supervised_config(1), &[]);
    wait_update(&t, 150, Duration::from_secs(90));
    signal(t.pid("learner").expect("a learner"), libc::SIGTERM);
    let code = t.sup.wait_timeout(Duration::from_secs(60)).and_then(|s| s.code());
    let out = std::fs::read_to_string(t.run_dir.parent().unwrap().join("supervisor.out")).unwrap_or_default();
    assert_eq!(code, Some(1), "{out}\n{}", t.logs());
    assert!(out.contains("the learner stopped before the training budget") && out.contains("--resume"), "{out}");
    assert!(!out.contains("next: bcal eval"), "{out}");
}

/// A damaged checkpoint on `--resume`: the learner refuses it (its log names the file and what to do), and when
/// its restarts are spent `bcal train`'s own error carries that line, not only "see learner.log" (a fuzz of the
/// CLI, 2026-11-30).
#[test]
fn a_damaged_checkpoint_on_resume_is_named_by_bcal_train_itself() {
    let _s = serial();
    let mut cfg = supervised_config(1);
    cfg.actors.max_restarts = 1;
    let mut t = Train::start(cfg, &[]);
    wait_update(&t, 150, Duration::from_secs(90));
    let (code, _) = ctrl_c(&mut t);
    assert_eq!(code, Some(130), "{}", t.logs());
    let step = std::fs::read_to_string(t.run_dir.join("checkpoints/LATEST")).unwrap();
    let folder = t.run_dir.join("checkpoints").join(step.trim());
    let damaged = std::fs::read_dir(&folder)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|x| x == "safetensors"))
        .expect("a tensor file in the checkpoint");
    let bytes = std::fs::read(&damaged).unwrap();
    std::fs::write(&damaged, &bytes[..bytes.len() / 2]).unwrap();
    t.resume(&[]);
    let code = t.sup.wait_timeout(Duration::from_secs(120)).and_then(|s| s.code());
    let out = std::fs::read_to_string(t.run_dir.parent().unwrap().join("supervisor-resumed.out")).unwrap_or_default();
    assert_eq!(code, Some(1), "{out}\n{}", t.logs());
    let error = out.lines().find(|l| l.starts_with("error: learner failed")).unwrap_or_default();
    assert!(error.contains("last with:") && error.contains("safetensors"), "{out}");
}

#[test]
fn a_full_disk_while_checkpointing_is_a_clear_error_and_the_previous_checkpoint_stays() {
    let _s = serial();
    let mut cfg = tiny_config(1);
    cfg.lac.hidden = vec![256, 256]; // checkpoint files of ~300 kB, well above the limit below
    cfg.learner.checkpoint_every = 100;
    cfg.learner.validate_every = 0;
    cfg.learner.time_budget_s = 300.0;
    let run = RunFolder::new(cfg);
    let dir = run.path().to_str().unwrap().to_string();
    let _replay = Proc::start(&run, "replay", "bcal-replay", &["--run", &dir]);
    let _actor = Proc::start(&run, "actor-0", "bcal-actor", &["--run", &dir, "--actor-id", "0"]);
    let latest = || std::fs::read_to_string(run.path().join("checkpoints/LATEST")).unwrap_or_default();
    let mut learner = Proc::start(&run, "learner", "bcal-learner", &["--run", &dir]);
    assert!(wait_until(Duration::from_secs(90), || !latest().is_empty()), "{}", run.logs());
    assert_eq!(learner.terminate(Duration::from_secs(20)).and_then(|s| s.code()), Some(0), "{}", run.logs());
    let first_dir = run.path().join("checkpoints").join(latest().trim());
    let biggest =
        std::fs::read_dir(&first_dir).unwrap().flatten().map(|e| e.metadata().unwrap().len()).max().unwrap() as usize;
    let metrics_len = std::fs::metadata(run.path().join("metrics.jsonl")).map(|m| m.len()).unwrap_or(0) as usize;
    // The disk "fills": no file of this learner may grow past the limit (EFBIG, like ENOSPC, fails the
    // write; SIGXFSZ is ignored so the process sees the error instead of dying).
    let limit = metrics_len + 64 * 1024;
    assert!(limit < biggest, "limit {limit} must be below the checkpoint file size {biggest}");
    let mut full = Proc::start_with(&run, "learner-disk-full", "bcal-learner", &["--run", &dir, "--resume"], |cmd| {
        use std::os::unix::process::CommandExt;
        // SAFETY: signal is async-signal-safe; nothing else runs between fork and exec.
        unsafe {
            cmd.pre_exec(|| {
                libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
                Ok(())
            });
        }
    });
    // Once the learner runs (its shared memory is made, and that counts against the limit too), the
    // disk "fills" for it: prlimit(2) from outside, as an administrator's quota would.
    let lines_before = std::fs::read_to_string(run.path().join("metrics.jsonl")).unwrap().lines().count();
    assert!(
        wait_until(Duration::from_secs(60), || {
            std::fs::read_to_string(run.path().join("metrics.jsonl")).unwrap().lines().count() > lines_before
        }),
        "{}",
        run.logs()
    );
    let lim = libc::rlimit { rlim_cur: limit as u64, rlim_max: limit as u64 };
    // SAFETY: prlimit on our own child's pid with a valid rlimit; the old value is not read.
    let rc = unsafe { libc::prlimit(full.pid(), libc::RLIMIT_FSIZE, &lim, std::ptr::null_mut()) };
    assert_eq!(rc, 0, "prlimit: {}", std::io::Error::last_os_error());
    let st = full.wait_timeout(Duration::from_secs(90));
    let log = std::fs::read_to_string(run.path().join("logs/learner-disk-full.log")).unwrap();
    assert!(st.is_some_and(|s| s.code() == Some(1)), "expected a failed exit: {st:?}\n{log}");
    assert!(log.contains("disk full or folder not writable"), "{log}");
    // LATEST still names a whole checkpoint (the newest that fitted), and the error names it.
    let kept = latest();
    assert!(log.contains(&format!("the previous checkpoint {} is kept", kept.trim())), "LATEST {kept:?}\n{log}");
    let failed: u64 = log
        .split("checkpoint of update ")
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .expect("the error names the update");
    let kept_step: u64 = kept.trim().trim_start_matches("step-").parse().unwrap();
    assert!(kept_step < failed, "LATEST {kept_step} must predate the failed checkpoint {failed}");
    // Nothing half-written under a real step name, and no temporary folder left to fill the disk.
    let steps: Vec<String> = std::fs::read_dir(run.path().join("checkpoints"))
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("step-"))
        .collect();
    assert!(
        !steps.iter().any(|n| n.trim_start_matches("step-").parse::<u64>().is_ok_and(|u| u == failed)),
        "{steps:?}"
    );
    let leftovers: Vec<_> = std::fs::read_dir(run.path().join("checkpoints"))
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "temporary files left after the failed write: {leftovers:?}");
    // And it is usable: a learner with room again resumes from it.
    let lines = std::fs::read_to_string(run.path().join("metrics.jsonl")).unwrap().lines().count();
    let mut again = Proc::start(&run, "learner-again", "bcal-learner", &["--run", &dir, "--resume"]);
    let step = kept_step;
    assert!(
        wait_until(Duration::from_secs(60), || {
            let text = std::fs::read_to_string(run.path().join("metrics.jsonl")).unwrap_or_default();
            text.lines()
                .skip(lines)
                .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
                .any(|v| v["kind"] == "train" && v["update"].as_u64().is_some_and(|u| u > step))
        }),
        "{}",
        run.logs()
    );
    assert_eq!(again.terminate(Duration::from_secs(20)).and_then(|s| s.code()), Some(0), "{}", run.logs());

    // A lost LATEST is never a silent fresh start on top of existing checkpoints.
    std::fs::remove_file(run.path().join("checkpoints/LATEST")).unwrap();
    let mut lost = Proc::start(&run, "learner-no-latest", "bcal-learner", &["--run", &dir, "--resume"]);
    let st = lost.wait_timeout(Duration::from_secs(60));
    let log = std::fs::read_to_string(run.path().join("logs/learner-no-latest.log")).unwrap();
    assert_eq!(st.and_then(|s| s.code()), Some(1), "{log}");
    assert!(log.contains("no LATEST") && log.contains("step-"), "{log}");
}

#[test]
fn an_unwritable_run_folder_is_refused_before_anything_starts() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("not-a-folder");
    std::fs::write(&file, b"x").unwrap();
    let out = std::process::Command::new(bcal_tests::bin("bcal"))
        .args(["train", "--run"])
        .arg(file.join("run"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("cannot create the run folder") && err.contains("not-a-folder"), "{err}");
    // Where permissions bind (not root), a read-only folder is refused the same way.
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } != 0 {
        use std::os::unix::fs::PermissionsExt;
        let ro = dir.path().join("read-only");
        std::fs::create_dir(&ro).unwrap();
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
        let out = std::process::Command::new(bcal_tests::bin("bcal"))
            .args(["train", "--run"])
            .arg(ro.join("run"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(err.contains("cannot create the run folder"), "{err}");
    }
}

/// A peer of an older build, simulated by this test creating the run's services as that build would.
#[test]
fn a_peer_with_another_wire_layout_is_refused_with_a_clear_message() {
    use bcal_common::ipc::iceoryx2::prelude::{ServiceName, ZeroCopySend};
    let _s = serial();
    let run = RunFolder::new(tiny_config(1));
    let dir = run.path().to_str().unwrap().to_string();
    let rid = RunIpc::new(run.path(), &run.validated).unwrap();
    let (node, _) = bipc::create_node("bcal-test-old-build").unwrap();

    // 1. A replay of the previous wire version serves this run folder.
    let old_name = format!("bcal/v{}/{}/transitions", WIRE_VERSION - 1, rid.run_id);
    let _old = node.service_builder(&ServiceName::new(&old_name).unwrap()).publish_subscribe::<u64>().create().unwrap();
    let t0 = Instant::now();
    let mut actor = Proc::start(&run, "actor-old-replay", "bcal-actor", &["--run", &dir, "--actor-id", "0"]);
    let st = actor.wait_timeout(Duration::from_secs(30));
    let log = std::fs::read_to_string(run.path().join("logs/actor-old-replay.log")).unwrap();
    assert_eq!(st.and_then(|s| s.code()), Some(1), "{log}");
    assert!(log.contains(&format!("wire version {}", WIRE_VERSION - 1)) && log.contains("this binary speaks"), "{log}");
    eprintln!("refused in {:.1} s: {}", t0.elapsed().as_secs_f64(), log.trim());

    // 2. Same version in the name, but a header laid out as an old build had it (no send time).
    #[repr(C)]
    #[derive(Clone, Copy, Debug, Default, ZeroCopySend)]
    #[type_name("bcal::TransitionBatchHeader")]
    struct OldHeader {
        actor_id: u32,
        len: u32,
        epoch: u64,
        seq: u64,
        published_before: u64,
        weights_version: u64,
    }
    let name = rid.service_name("transitions");
    let _bad = node
        .service_builder(&ServiceName::new(&name).unwrap())
        .publish_subscribe::<[bcal_common::wire::Transition]>()
        .user_header::<OldHeader>()
        .create()
        .unwrap();
    let mut actor = Proc::start(&run, "actor-old-layout", "bcal-actor", &["--run", &dir, "--actor-id", "0"]);
    let st = actor.wait_timeout(Duration::from_secs(30));
    let log = std::fs::read_to_string(run.path().join("logs/actor-old-layout.log")).unwrap();
    assert_eq!(st.and_then(|s| s.code()), Some(1), "{log}");
    assert!(log.contains("incompatible layout") && log.contains("transitions"), "{log}");
    // The replay of the new build refuses to join that service too, rather than misread it.
    let mut replay = Proc::start(&run, "replay-old-layout", "bcal-replay", &["--run", &dir]);
    let st = replay.wait_timeout(Duration::from_secs(30));
    let log = std::fs::read_to_string(run.path().join("logs/replay-old-layout.log")).unwrap();
    assert_eq!(st.and_then(|s| s.code()), Some(1), "{log}");
    assert!(log.contains("incompatible layout"), "{log}");
}

#[test]
fn shared_memory_of_a_run_is_not_writable_by_other_users() {
    use std::os::unix::fs::MetadataExt;
    let _s = serial();
    let run = RunFolder::new(tiny_config(1));
    let dir = run.path().to_str().unwrap().to_string();
    let mut replay = Proc::start(&run, "replay", "bcal-replay", &["--run", &dir]);
    assert!(wait_until(Duration::from_secs(20), || run.json("replay.json").is_some()), "{}", run.logs());
    // Opening a service from here proves it exists under this user's prefix.
    let (node, _) = bipc::create_node("bcal-test-perms").unwrap();
    let rid = RunIpc::new(run.path(), &run.validated).unwrap();
    rid.transitions(&node, Role::Open { timeout: Duration::from_secs(10) }).unwrap();
    let files = bipc::shared_memory_files(&bipc::iox_config());
    assert!(files.len() >= 4, "expected the run's segments under /dev/shm, found {files:?}");
    let open: Vec<String> = files
        .iter()
        .filter_map(|p| std::fs::metadata(p).ok().map(|m| (p, m.mode())))
        .filter(|(_, mode)| mode & 0o022 != 0)
        .map(|(p, mode)| format!("{} {:o}", p.display(), mode & 0o777))
        .collect();
    assert!(open.is_empty(), "group/other-writable shared memory: {open:?}");
    assert_eq!(replay.terminate(Duration::from_secs(10)).and_then(|s| s.code()), Some(0));
}
