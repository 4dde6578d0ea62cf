//! `bcal-replay --run DIR`: the replay process (see the library for what it does). Exits 0 on
//! SIGINT/SIGTERM after writing its final counters.

use clap::Parser;
use std::path::PathBuf;

/// The replay process of a bcal training run.
#[derive(Parser, Debug)]
#[command(name = "bcal-replay", version)]
struct Args {
    /// Run folder holding config.toml (written by `bcal train`).
    #[arg(long = "run", value_name = "DIR")]
    run_dir: PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let report = bcal_replay::run(&args.run_dir)?;
    eprintln!("bcal-replay: started from {}: {}", report.started_from, report.start_note);
    if let Some(e) = &report.snapshot_error {
        eprintln!("bcal-replay: {e}");
    }
    eprintln!(
        "bcal-replay: stopped; received {} inserted {} quarantined {} dropped {} batches served {}",
        report.received_total,
        report.inserted_total,
        report.quarantined_total,
        report.dropped_total,
        report.batches_served
    );
    Ok(())
}
