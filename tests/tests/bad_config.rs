//! A bad config is refused before anything starts: `bcal train` exits 1 naming the key, and neither a run
//! folder nor a process comes into being. The processes themselves refuse a bad `config.toml` in a run
//! folder the same way (someone edited it between runs).

use std::process::Command;

const CASES: &[(&str, &str)] = &[
    // Unknown key (a typo).
    ("[lac]\nlearning_rate = 1e-3\n", "learning_rate"),
    // Wrong type.
    ("[lac]\nbatch_size = \"large\"\n", "batch_size"),
    // Impossible values.
    ("[lac]\nlr = -1e-3\n", "lac.lr"),
    ("[actors]\ncount = 0\n", "actors.count"),
    ("[actors]\nenvs_per_actor = 0\n", "actors.envs_per_actor"),
    ("[replay]\ncapacity = 0\n", "replay.capacity"),
    ("[replay]\nsnapshot_every_s = -5.0\n", "replay.snapshot_every_s"),
    // A calibration range that does not contain the experiment's data.
    ("[env]\nq_mobile_range_c = [4500.0, 7500.0]\n", "env.q_mobile_range_c"),
    // Not TOML at all.
    ("[lac\nlr = 1\n", "config"),
];

#[test]
fn bcal_train_refuses_bad_configs_naming_the_key_and_starts_nothing() {
    let dir = tempfile::tempdir().unwrap();
    for (k, (toml, key)) in CASES.iter().enumerate() {
        let cfg = dir.path().join(format!("bad-{k}.toml"));
        std::fs::write(&cfg, toml).unwrap();
        let run = dir.path().join(format!("run-{k}"));
        let out = Command::new(bcal_tests::bin("bcal"))
            .args(["train", "--config"])
            .arg(&cfg)
            .arg("--run")
            .arg(&run)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{toml}: {err}");
        assert!(err.contains(key), "{toml}: the error should name {key}: {err}");
        assert!(!run.exists(), "{toml}: a run folder was created for a refused config");
    }
}

#[test]
fn a_process_refuses_a_bad_config_in_its_run_folder() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("config.toml"), "[lac]\nlr = -1e-3\n").unwrap();
    for exe in ["bcal-replay", "bcal-learner", "bcal-actor"] {
        let mut cmd = Command::new(bcal_tests::bin(exe));
        cmd.arg("--run").arg(dir.path());
        if exe == "bcal-actor" {
            cmd.args(["--actor-id", "0"]);
        }
        let out = cmd.output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{exe}: {err}");
        assert!(err.contains("lac.lr"), "{exe}: {err}");
    }
}

/// Found by a fuzz of the CLI (2026-11-30). `--resume` continues a run on its own config: a setting given
/// with it is refused (it was ignored while the banner claimed it), and a run holding a trained policy but no
/// checkpoint is refused (it started again from update 0 and overwrote the policy). A grace that makes no
/// duration is refused by the parser (it panicked after the run had started), and `bcal eval --policy` naming
/// no file is refused (RL was dropped unsaid).
#[test]
fn resume_grace_and_eval_policy_mistakes_are_refused_before_anything_starts() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    std::fs::create_dir_all(&run).unwrap();
    let cfg = bcal_common::config::Preset::Measured.config();
    std::fs::write(run.join("config.toml"), cfg.to_toml()).unwrap();
    std::fs::write(run.join("policy.bcalpol"), b"a trained policy").unwrap();
    let bcal = |args: &[&str]| {
        let out = Command::new(bcal_tests::bin("bcal")).args(args).output().unwrap();
        (out.status.code(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    let r = run.to_str().unwrap();
    let (code, err) = bcal(&["train", "--run", r, "--resume", "--preset", "paper"]);
    assert!(code == Some(1) && err.contains("--preset cannot change it"), "{err}");
    let (code, err) = bcal(&["train", "--run", r, "--resume"]);
    assert!(code == Some(1) && err.contains("no checkpoint to continue from"), "{err}");
    assert_eq!(std::fs::read(run.join("policy.bcalpol")).unwrap(), b"a trained policy", "the policy was touched");
    let (code, err) = bcal(&["train", "--run", r, "--resume", "--grace-s=-1"]);
    assert!(code == Some(2) && err.contains("grace in seconds"), "{err}");
    let (code, err) = bcal(&["eval", "--run", r, "--quick", "--policy", "/nonexistent/p.bcalpol"]);
    assert!(code == Some(1) && err.contains("--policy /nonexistent/p.bcalpol: no such file"), "{err}");
    // A measured-only policy of another setting (here: another cut-off) was evaluated in its own setting under
    // this run's name.
    let mut other = cfg.measured.clone();
    other.tracker.cutoff_v = 2.8;
    let p = bcal_tests::zero_policy(dir.path(), "other.bcalpol", bcal_common::task::Task::Measured(other));
    let (code, err) = bcal(&["eval", "--run", r, "--quick", "--policy", p.to_str().unwrap()]);
    assert!(code == Some(1) && err.contains("another measured setting"), "{err}");
}

/// `bcal summarize` takes each run once and only seeds of one setting (a fuzz of the CLI, 2026-11-30: the same
/// run twice counted as two seeds with no spread, and runs of two measured settings were averaged).
#[test]
fn summarize_refuses_a_run_twice_and_runs_of_two_settings() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = bcal_common::config::Preset::Measured.config();
    for (name, seed, lr) in [("a", 1, 2e-3), ("b", 2, 2e-3), ("c", 3, 1e-3)] {
        let run = dir.path().join(name);
        std::fs::create_dir_all(&run).unwrap();
        (c.seed, c.lac.lr) = (seed, lr);
        std::fs::write(run.join("config.toml"), c.to_toml()).unwrap();
    }
    let summarize = |runs: &[&str]| {
        let out = Command::new(bcal_tests::bin("bcal"))
            .arg("summarize")
            .args(runs.iter().map(|r| dir.path().join(r)))
            .output()
            .unwrap();
        (out.status.code(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    let (code, err) = summarize(&["a", "a"]);
    assert!(code == Some(1) && err.contains("are the same run"), "{err}");
    let (code, err) = summarize(&["a", "c"]);
    assert!(code == Some(1) && err.contains("different settings"), "{err}");
    // Seeds of one setting pass this check (and meet the next: no report yet).
    let (code, err) = summarize(&["a", "b"]);
    assert!(code == Some(1) && err.contains("evaluate the run first"), "{err}");
}
