//! Checkpoints: a round trip restores the actor's flat parameters, the critic and the update counter;
//! `LATEST` names the newest step folder and only the two newest survive; a checkpoint of another
//! experiment or network shape, or a damaged or dangling one, is refused with a message saying so; no
//! checkpoint means `None`. Also: the libtorch-free policy file made by `Lac::policy_file` loads back.

use bcal_common::config::{EnvConfig, TrainConfig, Validated};
use bcal_common::dataset::Experiment;
use bcal_common::mdp::{ActionMap, MdpSpec, ObsScales, ObservationKind};
use bcal_common::policy::{PolicyFile, PolicyLayout};
use bcal_common::wire::Transition;
use bcal_learner::checkpoint::{CHECKPOINTS_DIR, LATEST_FILE};
use bcal_learner::{Lac, LacError};
use std::path::Path;

fn config(experiment: Experiment, hidden: &[usize]) -> Validated {
    let mut c = TrainConfig { experiment, ..Default::default() };
    c.lac.hidden = hidden.to_vec();
    c.learner.torch_threads = 1;
    c.validate().unwrap()
}

fn layout(act_dim: usize, hidden: &[usize]) -> PolicyLayout {
    PolicyLayout { obs_dim: 15, act_dim, hidden: hidden.to_vec() }
}

fn batch(seed: u64, n: usize) -> Vec<Transition> {
    Transition::synthetic_batch(seed, n, 15, 1)
}

fn trained(cfg: &Validated, layout: PolicyLayout, updates: usize) -> (Lac, Vec<Transition>) {
    let mut lac = Lac::new(cfg, layout, 9).unwrap();
    let b = batch(10, 32);
    for _ in 0..updates {
        lac.update(&b).unwrap();
    }
    (lac, b)
}

fn latest(run: &Path) -> String {
    std::fs::read_to_string(run.join(CHECKPOINTS_DIR).join(LATEST_FILE)).unwrap().trim().to_string()
}

#[test]
fn no_checkpoint_is_none() {
    let run = tempfile::tempdir().unwrap();
    let cfg = config(Experiment::SingleQ, &[16, 16]);
    assert!(Lac::load_latest(&cfg, layout(1, &[16, 16]), run.path()).unwrap().is_none());
}

#[test]
fn round_trip_restores_weights_and_counter_and_keeps_two_newest() {
    let run = tempfile::tempdir().unwrap();
    let cfg = config(Experiment::SingleQ, &[16, 16]);
    let (mut lac, b) = trained(&cfg, layout(1, &[16, 16]), 3);
    let first = lac.save_checkpoint(run.path()).unwrap();
    assert!(first.ends_with("checkpoints/step-3"), "{}", first.display());
    for f in ["actor.safetensors", "critic.safetensors", "actor_target.safetensors", "critic_target.safetensors"] {
        assert!(first.join(f).is_file(), "{f}");
    }
    let meta: serde_json::Value = serde_json::from_slice(&std::fs::read(first.join("meta.json")).unwrap()).unwrap();
    assert_eq!(meta["update_step"], 3);
    assert_eq!(meta["experiment"], "single-q");
    assert_eq!(meta["layout"]["hidden"], serde_json::json!([16, 16]));
    for _ in 0..2 {
        lac.update(&b).unwrap();
        lac.save_checkpoint(run.path()).unwrap();
    }
    lac.update(&b).unwrap();
    lac.save_checkpoint(run.path()).unwrap();
    assert_eq!(latest(run.path()), "step-6");
    let mut folders: Vec<String> = std::fs::read_dir(run.path().join(CHECKPOINTS_DIR))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n != LATEST_FILE)
        .collect();
    folders.sort();
    assert_eq!(folders, vec!["step-5", "step-6"], "only the two newest step folders stay (no temporaries)");

    let mut back = Lac::load_latest(&cfg, layout(1, &[16, 16]), run.path()).unwrap().expect("a checkpoint");
    assert_eq!(back.updates(), 6);
    assert_eq!(back.actor_flat_params(), lac.actor_flat_params());
    assert_eq!(back.lyapunov_values(&b).unwrap(), lac.lyapunov_values(&b).unwrap());
    assert_eq!((back.lambda(), back.beta()), (lac.lambda(), lac.beta()));
    // The counter continues after the resume.
    back.update(&b).unwrap();
    assert_eq!(back.updates(), 7);
}

#[test]
fn another_shape_or_experiment_is_refused() {
    let run = tempfile::tempdir().unwrap();
    let cfg = config(Experiment::SingleQ, &[16, 16]);
    trained(&cfg, layout(1, &[16, 16]), 1).0.save_checkpoint(run.path()).unwrap();

    let wider = config(Experiment::SingleQ, &[16, 16, 16]);
    let e = Lac::load_latest(&wider, layout(1, &[16, 16, 16]), run.path()).err().expect("refused");
    assert!(matches!(e, LacError::CheckpointMismatch { .. }), "{e}");
    assert!(e.to_string().contains("network shape"), "{e}");

    let other = config(Experiment::SingleR, &[16, 16]);
    let e = Lac::load_latest(&other, layout(1, &[16, 16]), run.path()).err().expect("refused");
    assert!(e.to_string().contains("experiment single-q"), "{e}");
}

#[test]
fn damaged_or_dangling_checkpoints_are_refused() {
    let run = tempfile::tempdir().unwrap();
    let cfg = config(Experiment::SingleQ, &[16, 16]);
    let folder = trained(&cfg, layout(1, &[16, 16]), 2).0.save_checkpoint(run.path()).unwrap();
    let load = || Lac::load_latest(&cfg, layout(1, &[16, 16]), run.path());

    // A flipped byte in a tensor file.
    let critic = folder.join("critic.safetensors");
    let good = std::fs::read(&critic).unwrap();
    let mut bad = good.clone();
    let k = bad.len() - 3;
    bad[k] ^= 0x5a;
    std::fs::write(&critic, &bad).unwrap();
    let e = load().err().expect("refused");
    assert!(matches!(e, LacError::CheckpointCorrupt { .. }) && e.to_string().contains("checksum"), "{e}");
    // A truncated file.
    std::fs::write(&critic, &good[..good.len() / 2]).unwrap();
    assert!(matches!(load(), Err(LacError::CheckpointCorrupt { .. })));
    std::fs::write(&critic, &good).unwrap();
    assert!(load().unwrap().is_some());
    // Missing metadata (a half-written folder).
    std::fs::remove_file(folder.join("meta.json")).unwrap();
    let e = load().err().expect("refused");
    assert!(e.to_string().contains("meta.json"), "{e}");
    // LATEST pointing nowhere.
    std::fs::write(run.path().join(CHECKPOINTS_DIR).join(LATEST_FILE), "step-99\n").unwrap();
    let e = load().err().expect("refused");
    assert!(e.to_string().contains("does not exist"), "{e}");
}

#[test]
fn policy_file_round_trips_without_libtorch() {
    let run = tempfile::tempdir().unwrap();
    let cfg = config(Experiment::SingleQ, &[16, 16]);
    let (lac, _) = trained(&cfg, layout(1, &[16, 16]), 2);
    let mdp = MdpSpec {
        observation: ObservationKind::FullState,
        actions: ActionMap::from_config(Experiment::SingleQ, &EnvConfig::default()),
        scales: ObsScales {
            state_mean: [0.0; 7],
            state_std: [1.0; 7],
            load_mean_w: 12.0,
            load_std_w: 2.0,
            r_app_mean_ohm: 0.0,
            r_app_std_ohm: 1.0,
        },
        window_steps: 16,
        dt_s: 1.0,
        cost_log_e0: 0.0,
    };
    let path = run.path().join("policy.bcalpol");
    lac.policy_file(bcal_common::task::Task::Paper(mdp), Experiment::SingleQ).save(&path).unwrap();
    let pf = PolicyFile::load(&path).unwrap();
    assert_eq!(pf.update_step, 2);
    assert_eq!(pf.params, lac.actor_flat_params());
    assert_eq!(pf.layout, *lac.layout());
}
