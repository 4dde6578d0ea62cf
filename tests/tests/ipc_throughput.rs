//! Measurement, not a timed test (ignored by default; run with
//! `cargo test -p bcal-tests --release --test ipc_throughput -- --ignored --nocapture`): transitions per
//! second from 1 and 2 real bcal-actor processes into a real bcal-replay, with this process standing in
//! for the learner's weights and the limiter opened wide (no learner samples). Prints one line per
//! setting; asserts only that nothing was dropped.

use bcal_common::config::TrainConfig;
use bcal_common::ipc::{self, Role, RunIpc, UpdateConnections};
use bcal_common::policy::PolicyLayout;
use bcal_common::wire::WeightsHeader;
use bcal_tests::{field, tiny_config, wait_until, Proc, RunFolder};
use std::time::{Duration, Instant};

fn measure(label: &str, mut cfg: TrainConfig, actors: usize, window: Duration) {
    cfg.actors.count = Some(actors);
    cfg.replay.samples_per_insert = 1.0;
    cfg.replay.ratio_error_buffer = 1e12;
    cfg.replay.capacity = 1_000_000;
    let run = RunFolder::new(cfg);
    let dir = run.path().to_str().unwrap().to_string();
    let mut replay = Proc::start(&run, "replay", "bcal-replay", &["--run", &dir]);
    assert!(wait_until(Duration::from_secs(20), || run.json("replay.json").is_some()), "{}", run.logs());
    let (node, _) = ipc::create_node("bcal-bench-weights").unwrap();
    let ipc_run = RunIpc::new(run.path(), &run.validated).unwrap();
    let weights = ipc_run.weights(&node, Role::Open { timeout: Duration::from_secs(10) }).unwrap();
    let layout = PolicyLayout {
        obs_dim: run.task.obs_dim(),
        act_dim: run.task.act_dim(),
        hidden: run.config.lac.hidden.clone(),
    };
    let publisher = ipc_run.weights_publisher(&weights, layout.n_params()).unwrap();
    let params: Vec<f32> = (0..layout.n_params()).map(|i| ((i % 13) as f32 - 6.0) * 0.01).collect();
    let mut s = publisher.loan_slice_uninit(params.len()).unwrap();
    *s.user_header_mut() =
        WeightsHeader { update_step: 1, layout_fingerprint: layout.fingerprint(), n_params: params.len() as u64 };
    s.write_from_slice(&params).send().unwrap();

    let mut procs: Vec<Proc> = (0..actors)
        .map(|k| {
            let id = k.to_string();
            Proc::start(&run, &format!("actor-{k}"), "bcal-actor", &["--run", &dir, "--actor-id", &id])
        })
        .collect();
    assert!(
        wait_until(Duration::from_secs(60), || {
            let _ = publisher.update_connections();
            field(&run.json("replay.json"), "received_total") > 0
        }),
        "{}",
        run.logs()
    );
    // Warm up, then measure the replay's received counter over the window.
    std::thread::sleep(Duration::from_secs(2));
    let r0 = run.json("replay.json");
    let t0 = Instant::now();
    std::thread::sleep(window);
    let r1 = run.json("replay.json");
    let dt_uptime =
        r1.as_ref().unwrap()["uptime_s"].as_f64().unwrap() - r0.as_ref().unwrap()["uptime_s"].as_f64().unwrap();
    let got = field(&r1, "received_total") - field(&r0, "received_total");
    for p in procs.iter_mut() {
        assert_eq!(p.terminate(Duration::from_secs(10)).and_then(|s| s.code()), Some(0));
    }
    assert_eq!(replay.terminate(Duration::from_secs(10)).and_then(|s| s.code()), Some(0));
    let r = run.json("replay.json");
    let published: u64 =
        (0..actors).map(|k| field(&run.json(&format!("actors/actor-{k}.json")), "published_transitions")).sum();
    println!(
        "{label}: {actors} actor(s): {:.0} transitions/s into the replay ({got} in {dt_uptime:.1} s; wall {:.1} s); \
         published {published} received {} dropped {}",
        got as f64 / dt_uptime,
        t0.elapsed().as_secs_f64(),
        field(&r, "received_total"),
        field(&r, "dropped_total"),
    );
    assert_eq!(field(&r, "received_total"), published);
    assert_eq!(field(&r, "dropped_total"), 0);
}

#[test]
#[ignore = "measurement; run explicitly with --ignored --nocapture"]
fn transitions_per_second_with_one_and_two_actors() {
    let window = Duration::from_secs(8);
    let paper = {
        let mut c = tiny_config(1);
        c.lac.hidden = vec![256, 256, 256];
        c.actors.envs_per_actor = 32;
        c.actors.publish_batch = 64;
        c
    };
    for actors in [1, 2] {
        measure("paper network 3x256, 32 envs, batch 64", paper.clone(), actors, window);
    }
    for actors in [1, 2] {
        measure("tiny network 2x16, 8 envs, batch 32", tiny_config(1), actors, window);
    }
}
