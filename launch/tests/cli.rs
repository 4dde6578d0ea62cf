//! The `bcal` binary as a user meets it: outputs, files and error messages of `simulate` and `dataset`.

use std::process::{Command, Output};

fn bcal(args: &[&str], cache: &std::path::Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_bcal")).args(args).env("BCAL_CACHE", cache).output().expect("bcal runs")
}

fn text(o: &Output) -> (String, String) {
    (String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned())
}

#[test]
fn simulate_prints_the_reference_eod() {
    let dir = tempfile::tempdir().unwrap();
    let o = bcal(&["simulate", "--q-mobile", "7600", "--ro", "0.117215", "--load-w", "8"], dir.path());
    let (out, err) = text(&o);
    assert!(o.status.success(), "{err}");
    assert!(out.contains("EOD 3102 s"), "{out}");
}

#[test]
fn simulate_writes_every_step_as_csv_through_the_eod_row() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("d.csv");
    let o = bcal(&["simulate", "--load-w", "16", "--out", csv.to_str().unwrap()], dir.path());
    assert!(o.status.success(), "{}", text(&o).1);
    let body = std::fs::read_to_string(&csv).unwrap();
    let mut lines = body.lines();
    assert_eq!(lines.next().unwrap(), "t_s,voltage_v,qpS,qpB,qnB,qnS,Vo,Vsn,Vsp,load_w");
    let rows: Vec<Vec<f64>> = lines.map(|l| l.split(',').map(|v| v.parse().unwrap()).collect()).collect();
    assert_eq!(rows.len(), 1164, "t = 0 through the EOD row at 1163 s");
    assert_eq!(rows[0][0], 0.0);
    assert!((rows[1][1] - 4.1120644120).abs() < 1e-9);
    assert_eq!(rows.last().unwrap()[0], 1163.0);
    assert!(rows.last().unwrap()[1] < 3.0 && rows[rows.len() - 2][1] >= 3.0);
    assert!(rows.iter().all(|r| r.len() == 10 && r[9] == 16.0));
}

#[test]
fn thermal_current_run_adds_temperature_column() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("t.csv");
    let o =
        bcal(&["simulate", "--current-a", "2", "--thermal", "--dt", "2", "--out", csv.to_str().unwrap()], dir.path());
    assert!(o.status.success(), "{}", text(&o).1);
    let body = std::fs::read_to_string(&csv).unwrap();
    assert!(body.starts_with("t_s,voltage_v,qpS,qpB,qnB,qnS,Vo,Vsn,Vsp,current_a,tb_k\n"));
    let last: Vec<f64> = body.lines().last().unwrap().split(',').map(|v| v.parse().unwrap()).collect();
    assert!(last[10] > 292.1, "the cell heats: {}", last[10]);
    assert_eq!(body.lines().nth(2).unwrap().split(',').next().unwrap(), "2", "dt = 2 s steps");
}

#[test]
fn bad_values_get_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let cases: &[(&[&str], &str)] = &[
        (&["simulate", "--load-w", "-3"], "must be greater than 0"),
        (&["simulate", "--load-w", "abc"], "is not a number"),
        (&["simulate", "--load-w", "NaN"], "not a finite number"),
        (&["simulate", "--load-w", "8", "--current-a", "2"], "cannot be used with"),
        (&["simulate"], "--load-w"),
        (&["simulate", "--load-w", "8", "--dt", "0"], "must be greater than 0"),
        (&["simulate", "--load-w", "8", "--ro", "-0.1"], "must not be negative"),
        (&["simulate", "--load-w", "8", "--out", "/nonexistent-dir/x.csv"], "cannot create /nonexistent-dir/x.csv"),
        (&["simulate", "--load-w", "8", "--max-steps", "10"], "stayed above VEOD"),
        (&["dataset", "info", "--experiment", "multi"], "bcal dataset generate"),
        (&["dataset", "generate", "--experiment", "quadruple"], "invalid value"),
        (&["calibrate", "--data", "x.csv", "--out", "o", "--ambient-c", "150"], "not an ambient temperature in deg C"),
        (&["diagnose", "--data", "x.csv", "--ambient-c=-100"], "between -73.15 and 126.85"),
        (&["calibrate", "--data", "x.csv", "--out", "o", "--config", "c.toml"], "--config c.toml is for --follow"),
    ];
    for (args, want) in cases {
        let o = bcal(args, dir.path());
        let (out, err) = text(&o);
        assert!(!o.status.success(), "{args:?} should fail: {out}");
        assert!(err.contains(want), "{args:?}: stderr lacks `{want}`:\n{err}");
    }
}

#[test]
fn every_subcommand_documents_its_flags() {
    let dir = tempfile::tempdir().unwrap();
    let o = bcal(&["simulate", "--help"], dir.path());
    let (out, _) = text(&o);
    for flag in ["--q-mobile", "--ro", "--load-w", "--current-a", "--thermal", "--dt", "--out"] {
        assert!(out.contains(flag), "simulate --help lacks {flag}");
    }
    let o = bcal(&["--help"], dir.path());
    let (out, _) = text(&o);
    for sub in ["simulate", "dataset", "train"] {
        assert!(out.contains(sub), "--help lacks {sub}");
    }
}

/// Every number under `v` (bench.json's measurement sections) is finite and > 0, except per-sender message
/// counts (a saturated iceoryx2 subscriber may starve a publisher: that is reported, not a figure).
fn all_positive(path: &str, v: &serde_json::Value, bad: &mut Vec<String>) {
    match v {
        serde_json::Value::Number(n) => {
            let x = n.as_f64().unwrap_or(f64::NAN);
            if !(x.is_finite() && x > 0.0) {
                bad.push(format!("{path} = {x}"));
            }
        }
        serde_json::Value::Array(a) => {
            a.iter().enumerate().for_each(|(k, x)| all_positive(&format!("{path}[{k}]"), x, bad))
        }
        serde_json::Value::Object(o) => o
            .iter()
            .filter(|(k, _)| k.as_str() != "per_actor_messages")
            .for_each(|(k, x)| all_positive(&format!("{path}.{k}"), x, bad)),
        serde_json::Value::Null => bad.push(format!("{path} = null")),
        _ => {}
    }
}

#[test]
fn bench_quick_writes_every_figure() {
    // Never asserts on speed: only that every figure was measured and is a positive number.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bench.json");
    let o = bcal(&["bench", "--quick", "--out", out.to_str().unwrap()], dir.path());
    let (stdout, err) = text(&o);
    assert!(o.status.success(), "{err}");
    for section in ["## Battery model", "## Calibrator steps", "## Transport", "## Learner"] {
        assert!(stdout.contains(section), "stdout lacks {section}:\n{stdout}");
    }
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let mut bad = Vec::new();
    for section in ["model", "calib", "transport", "learner"] {
        assert!(v[section].is_object(), "bench.json lacks {section}");
        all_positive(section, &v[section], &mut bad);
    }
    assert!(bad.is_empty(), "not finite and > 0: {bad:?}");
    let actors: Vec<u64> =
        v["transport"]["rows"].as_array().unwrap().iter().map(|r| r["actors"].as_u64().unwrap()).collect();
    assert_eq!(actors, [1, 2, 4]);
    for key in ["steps_per_s", "step_ns"] {
        assert!(v["model"][key].is_number(), "model.{key}");
    }
    let calib: Vec<&str> = v["calib"]["rows"].as_array().unwrap().iter().map(|r| r["key"].as_str().unwrap()).collect();
    for key in ["ukf", "rl_rust_b1_128x2", "rl_rust_b1_256x3", "rl_tch_b64_256x3", "direct_tch_b1_256x3"] {
        assert!(calib.contains(&key), "calib rows lack {key}: {calib:?}");
    }
    let learner = &v["learner"]["rows"][0];
    assert_eq!((learner["hidden"].clone(), learner["batch"].as_u64()), (serde_json::json!([256, 256, 256]), Some(256)));
    assert_eq!(v["settings"]["quick"], true);
    assert!(v["machine"]["cores"].as_u64().unwrap() >= 1);
}

#[test]
fn bench_refuses_bad_parts_and_unwritable_output_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let cases: &[(&[&str], &str)] = &[
        (&["bench", "--only", "model,gpu"], "unknown part `gpu`"),
        (&["bench", "--out", "/nonexistent-dir/bench.json"], "/nonexistent-dir"),
    ];
    for (args, want) in cases {
        let o = bcal(args, dir.path());
        let (_, err) = text(&o);
        assert!(!o.status.success(), "{args:?} should fail");
        assert!(err.contains(want), "{args:?}: stderr lacks `{want}`:\n{err}");
    }
}

/// A policy is refused by `bcal eval` in a run of another observation kind, naming both kinds.
#[test]
fn eval_refuses_a_policy_of_another_observation_naming_both() {
    use bcal_common::config::TrainConfig;
    use bcal_common::policy::{PolicyFile, PolicyLayout};
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    std::fs::create_dir_all(&run).unwrap();
    // A paper-setting run (FullState) holding a measured-only policy.
    std::fs::write(run.join("config.toml"), TrainConfig::default().to_toml()).unwrap();
    let spec = bcal_common::measured::env::MeasuredSpec::default();
    let layout = PolicyLayout { obs_dim: spec.obs_dim(), act_dim: spec.act_dim(), hidden: vec![8] };
    let pf = PolicyFile {
        params: vec![0.0; layout.n_params()],
        layout,
        task: bcal_common::task::Task::Measured(spec),
        experiment: bcal_common::dataset::Experiment::Multi,
        update_step: 1,
    };
    pf.save(&run.join("policy.best.bcalpol")).unwrap();
    let o = bcal(&["eval", "--run", run.to_str().unwrap(), "--quick"], dir.path());
    let (_, err) = text(&o);
    assert!(!o.status.success(), "{err}");
    assert!(err.contains("Measured") && err.contains("FullState"), "{err}");
    assert!(err.contains("policy.best.bcalpol"), "{err}");
}

/// A mistyped run folder was created and evaluated in the paper's setting with exit 0 (a fuzz of the CLI,
/// 2026-11-30): it is refused, named, and not created.
#[test]
fn eval_refuses_a_run_folder_that_does_not_exist_and_creates_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let typo = dir.path().join("runs").join("c18-sed1");
    let o = bcal(&["eval", "--run", typo.to_str().unwrap(), "--quick"], dir.path());
    let (_, err) = text(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("c18-sed1") && err.contains("does not exist"), "{err}");
    assert!(!typo.exists() && !dir.path().join("runs").exists(), "the mistyped folder was created");
}
