//! `bcal bench`: measure every performance figure the README quotes, each beside its baseline, print the
//! tables and write bench.json (the measurements live in `bcal-bench`; what each figure is:
//! docs/bench.md). `bcal bench-publish` (hidden) is one transport publisher process, started by the bench
//! itself from this same executable.

use anyhow::{bail, Context};
use bcal_bench::{Parts, PublisherArgs, Settings};
use bcal_common::dataset;
use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// Short windows: every figure in under 20 s, noisier (the default run takes about a minute).
    #[arg(long)]
    pub quick: bool,
    /// Write every figure, the machine facts and the settings as JSON here (atomically).
    #[arg(long, value_name = "FILE.json", default_value = "bench.json")]
    pub out: PathBuf,
    /// Parts to run, comma separated: model (battery-model steps/s), calib (UKF, RL policy and
    /// direct-mapping step cost), transport (iceoryx2 vs crossbeam, 1/2/4 actors), learner (LAC updates/s),
    /// follow (latency per reading of `bcal calibrate --follow -`).
    #[arg(long, value_name = "PARTS", value_parser = Parts::parse, default_value = "model,calib,transport,learner,follow")]
    pub only: Parts,
    /// Dataset cache folder for the calibrator timings (default: $BCAL_CACHE/datasets or
    /// ~/.cache/bcal/datasets).
    #[arg(long)]
    pub cache_dir: Option<PathBuf>,
}

/// One transport publisher process (started by `bcal bench`; not for direct use).
#[derive(clap::Args, Debug)]
pub struct BenchPublishArgs {
    /// Temporary run folder with the config.toml that names the services.
    #[arg(long)]
    pub run: PathBuf,
    /// Publisher id (the messages' actor_id).
    #[arg(long)]
    pub id: u32,
    /// Stop after this many seconds whatever happens.
    #[arg(long, value_parser = crate::cli::positive_f64)]
    pub seconds: f64,
    /// Batches per second; 0 = as fast as the subscriber drains them.
    #[arg(long, default_value_t = 0.0, value_parser = crate::cli::non_negative_f64)]
    pub rate: f64,
}

pub fn run(a: BenchArgs) -> anyhow::Result<()> {
    let mut settings = if a.quick { Settings::quick() } else { Settings::full() };
    settings.parts = a.only;
    // Refuse an unwritable destination before a minute of measuring.
    let parent = a.out.parent().filter(|p| !p.as_os_str().is_empty()).map_or_else(|| PathBuf::from("."), PathBuf::from);
    if !parent.is_dir() {
        bail!("cannot write {}: folder {} does not exist", a.out.display(), parent.display());
    }
    let exe = std::env::current_exe().context("cannot locate the bcal executable to start publisher processes")?;
    let spawn = |p: &PublisherArgs| {
        let mut c = Command::new(&exe);
        c.arg("bench-publish").arg("--run").arg(&p.run_dir).args([
            "--id",
            &p.id.to_string(),
            "--seconds",
            &p.seconds.to_string(),
            "--rate",
            &p.rate.to_string(),
        ]);
        c
    };
    let spawn_follow = |kind: &str| {
        let mut c = Command::new(&exe);
        c.args(["calibrate", "--follow", "-", "--calibrator", kind]);
        c
    };
    let cache_dir = a.cache_dir.clone().unwrap_or_else(dataset::default_cache_dir);
    let started = Instant::now();
    let mut progress = |msg: &str| eprintln!("[{:6.1} s] {msg}", started.elapsed().as_secs_f64());
    progress(&format!(
        "bcal bench{}: {} (the figures come with their baselines; timing never fails the run)",
        if a.quick { " --quick" } else { "" },
        Parts::NAMES
            .iter()
            .zip([a.only.model, a.only.calib, a.only.transport, a.only.learner, a.only.follow])
            .filter(|(_, on)| *on)
            .map(|(n, _)| *n)
            .collect::<Vec<_>>()
            .join(", ")
    ));
    let report = bcal_bench::run(&settings, &cache_dir, &spawn, &spawn_follow, &mut progress)?;
    print!("{}", bcal_bench::render_table(&report));
    bcal_common::fsutil::write_json_atomic(&a.out, &report)
        .with_context(|| format!("cannot write {}", a.out.display()))?;
    println!("\nwrote {}", a.out.display());
    Ok(())
}

pub fn publish(a: BenchPublishArgs) -> anyhow::Result<()> {
    let summary = bcal_bench::publish(&PublisherArgs { run_dir: a.run, id: a.id, seconds: a.seconds, rate: a.rate })?;
    eprintln!("{summary}");
    Ok(())
}
