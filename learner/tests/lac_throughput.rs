//! Measurement, not a timed test (run on demand): learner updates per second at batch 256 with the
//! paper's networks (obs 15, act 2, hidden [256; 3]) for 1 and 2 libtorch threads.
//! `cargo test -p bcal-learner --release --test lac_throughput -- --ignored --nocapture`

use bcal_common::config::TrainConfig;
use bcal_common::dataset::Experiment;
use bcal_common::policy::PolicyLayout;
use bcal_common::wire::Transition;
use bcal_learner::Lac;

#[test]
#[ignore = "measurement; run with --ignored --nocapture"]
fn updates_per_second_paper_networks_batch_256() {
    let batch = Transition::synthetic_batch(1, 256, 15, 2);
    for threads in [1, 2] {
        let mut c = TrainConfig { experiment: Experiment::Multi, ..Default::default() };
        c.learner.torch_threads = threads;
        // The paper's networks, not the config's default widths: the layout must match lac.hidden.
        c.lac.hidden = vec![256; 3];
        let cfg = c.validate().unwrap();
        let mut lac = Lac::new(&cfg, PolicyLayout { obs_dim: 15, act_dim: 2, hidden: vec![256; 3] }, 1).unwrap();
        for _ in 0..30 {
            lac.update(&batch).unwrap();
        }
        let n = 400;
        let started = std::time::Instant::now();
        for _ in 0..n {
            lac.update(&batch).unwrap();
        }
        let secs = started.elapsed().as_secs_f64();
        eprintln!("torch_threads {threads}: {:.0} updates/s ({:.2} ms/update)", n as f64 / secs, 1e3 * secs / n as f64);
    }
}
