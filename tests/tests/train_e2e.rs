//! Full training across real processes: bcal-replay, bcal-learner and two bcal-actor processes on a small
//! `multi` config for about a minute, started the way the supervisor starts them. Pins the acceptance of
//! the training issue: transitions published equal transitions received (nothing dropped), the weight
//! version seen by the actors advances, the critic loss falls, the trained policy's held-out tracking
//! cost is well below the initial policy's, the learner finishes by itself (exit 0, `learner.done`,
//! checkpoint and policy file), and replay and actors exit 0 on SIGTERM.

use bcal_tests::{field, tiny_config, Proc, RunFolder};
use serde_json::Value;
use std::time::Duration;

/// Training runs use both cores: the tests of this file run one at a time.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn metrics(run: &RunFolder) -> Vec<Value> {
    std::fs::read_to_string(run.path().join("metrics.jsonl"))
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}

#[test]
fn two_actors_replay_and_learner_train_and_stop_cleanly() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let mut cfg = tiny_config(2);
    cfg.lac.hidden = vec![64, 64];
    cfg.lac.batch_size = 64;
    cfg.replay.learning_starts = 2_000;
    cfg.replay.samples_per_insert = 8.0;
    cfg.replay.ratio_error_buffer = 20_000.0;
    cfg.actors.envs_per_actor = 16;
    cfg.actors.publish_batch = 64;
    cfg.learner.weights_every = 20;
    cfg.learner.checkpoint_every = 1_000;
    cfg.learner.validate_every = 1_000;
    cfg.learner.validate_trajectories = 4;
    cfg.learner.time_budget_s = 45.0;
    let run = RunFolder::new(cfg);
    let dir = run.path().to_str().unwrap().to_string();

    let mut replay = Proc::start(&run, "replay", "bcal-replay", &["--run", &dir]);
    let mut learner = Proc::start(&run, "learner", "bcal-learner", &["--run", &dir]);
    let mut actors: Vec<Proc> = (0..2)
        .map(|k| {
            let id = k.to_string();
            Proc::start(&run, &format!("actor-{k}"), "bcal-actor", &["--run", &dir, "--actor-id", &id])
        })
        .collect();

    let finished = learner.wait_timeout(Duration::from_secs(150));
    let logs = run.logs();
    assert_eq!(finished.and_then(|s| s.code()), Some(0), "learner did not finish cleanly\n{logs}");
    assert!(run.path().join("learner.done").exists(), "{logs}");
    assert!(run.path().join("policy.bcalpol").exists(), "{logs}");
    assert!(run.path().join("checkpoints/LATEST").exists(), "{logs}");

    // Actors first (so everything they sent is on the wire), then the replay drains and stops.
    let versions: Vec<u64> =
        (0..2).map(|k| field(&run.json(&format!("actors/actor-{k}.json")), "weights_version")).collect();
    for a in actors.iter_mut() {
        assert_eq!(a.terminate(Duration::from_secs(10)).and_then(|s| s.code()), Some(0), "{}", run.logs());
    }
    assert_eq!(replay.terminate(Duration::from_secs(10)).and_then(|s| s.code()), Some(0), "{}", run.logs());

    let r = run.json("replay.json");
    let published: u64 =
        (0..2).map(|k| field(&run.json(&format!("actors/actor-{k}.json")), "published_transitions")).sum();
    assert!(published > 0);
    assert_eq!(field(&r, "received_total"), published, "replay {r:?}");
    assert_eq!(field(&r, "dropped_total"), 0, "replay {r:?}");
    assert!(versions.iter().all(|v| *v > 0), "actors never got trained weights: {versions:?}");

    let m = metrics(&run);
    let train: Vec<&Value> = m.iter().filter(|v| v["kind"] == "train" && v["critic_loss"].is_number()).collect();
    let val: Vec<&Value> = m.iter().filter(|v| v["kind"] == "validation").collect();
    assert!(train.len() >= 10, "{} train lines\n{logs}", train.len());
    assert!(val.len() >= 2, "{} validation lines", val.len());
    let early: f64 = train[..3].iter().map(|v| v["critic_loss"].as_f64().unwrap()).sum::<f64>() / 3.0;
    // A policy shift late in the run briefly raises the critic's TD error: judge the median of the second half.
    let mut second_half: Vec<f64> =
        train[train.len() / 2..].iter().map(|v| v["critic_loss"].as_f64().unwrap()).collect();
    second_half.sort_by(f64::total_cmp);
    let late = second_half[second_half.len() / 2];
    let (c0, c1) =
        (val[0]["val_tracking_error"].as_f64().unwrap(), val[val.len() - 1]["val_tracking_error"].as_f64().unwrap());
    eprintln!(
        "updates {} critic loss {early:.4} -> {late:.4}; held-out cost {c0:.4} -> {c1:.4}; published {published}",
        val[val.len() - 1]["update"]
    );
    let curve: Vec<String> = val.iter().map(|v| format!("{:.3}", v["val_tracking_error"].as_f64().unwrap())).collect();
    eprintln!("held-out cost curve: {}", curve.join(" "));
    assert!(late < early, "critic loss did not fall: {early} -> {late}");
    // The policy still wanders late in a short run: judge the median of the last five validations.
    let mut tail: Vec<f64> =
        val[val.len().saturating_sub(5)..].iter().map(|v| v["val_tracking_error"].as_f64().unwrap()).collect();
    tail.sort_by(f64::total_cmp);
    let median = tail[tail.len() / 2];
    assert!(median < 0.6 * c0, "held-out cost {c0} -> median of the last validations {median} (final {c1})");
}

#[test]
fn learner_sigterm_checkpoints_and_resume_continues_the_update_counter() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let mut cfg = tiny_config(1);
    cfg.learner.checkpoint_every = 1_000_000; // only the SIGTERM checkpoint
    cfg.learner.validate_every = 0;
    cfg.learner.time_budget_s = 120.0;
    let run = RunFolder::new(cfg);
    let dir = run.path().to_str().unwrap().to_string();
    let mut replay = Proc::start(&run, "replay", "bcal-replay", &["--run", &dir]);
    let mut actor = Proc::start(&run, "actor-0", "bcal-actor", &["--run", &dir, "--actor-id", "0"]);
    let last_update = |run: &RunFolder| metrics(run).iter().filter_map(|v| v["update"].as_u64()).max().unwrap_or(0);

    let mut learner = Proc::start(&run, "learner", "bcal-learner", &["--run", &dir]);
    assert!(bcal_tests::wait_until(Duration::from_secs(60), || last_update(&run) >= 200), "{}", run.logs());
    assert_eq!(learner.terminate(Duration::from_secs(20)).and_then(|s| s.code()), Some(0), "{}", run.logs());
    assert!(!run.path().join("learner.done").exists(), "a stopped learner is not done");
    let latest = std::fs::read_to_string(run.path().join("checkpoints/LATEST")).expect("SIGTERM checkpoint");
    let step: u64 = latest.trim().trim_start_matches("step-").parse().expect("step-<N>");
    assert!(step >= 200, "checkpoint at {step}");
    assert!(run.path().join("policy.bcalpol").exists());

    let lines_before = metrics(&run).len();
    let mut resumed = Proc::start(&run, "learner-resumed", "bcal-learner", &["--run", &dir, "--resume"]);
    assert!(
        bcal_tests::wait_until(Duration::from_secs(60), || metrics(&run).len() > lines_before + 2),
        "{}",
        run.logs()
    );
    let after: Vec<u64> = metrics(&run)[lines_before..].iter().filter_map(|v| v["update"].as_u64()).collect();
    assert!(after.iter().all(|u| *u >= step), "resumed counter restarted: {after:?} after step {step}");
    // The resumed learner's first line says where it starts: exactly the checkpoint.
    let first = &metrics(&run)[lines_before];
    assert_eq!(
        (first["kind"].as_str(), first["update"].as_u64(), first["resumed"].as_bool()),
        (Some("start"), Some(step), Some(true))
    );
    for p in [&mut resumed, &mut actor, &mut replay] {
        assert_eq!(p.terminate(Duration::from_secs(20)).and_then(|s| s.code()), Some(0), "{}: {}", p.name, run.logs());
    }
}
