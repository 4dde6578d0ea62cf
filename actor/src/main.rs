//! `bcal-actor --run DIR --actor-id K`: one actor process (see the library for what it does). Exits 0
//! on SIGINT/SIGTERM after writing its final counters.

use clap::Parser;
use std::path::PathBuf;

/// An actor process of a bcal training run.
#[derive(Parser, Debug)]
#[command(name = "bcal-actor", version)]
struct Args {
    /// Run folder holding config.toml and mdp.json (written by `bcal train`).
    #[arg(long = "run", value_name = "DIR")]
    run_dir: PathBuf,
    /// This actor's id, 0 .. actor count - 1 (seeds its random streams, names its counters file).
    #[arg(long)]
    actor_id: u32,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let report = bcal_actor::run(&bcal_actor::ActorArgs { run_dir: args.run_dir, actor_id: args.actor_id })?;
    eprintln!(
        "bcal-actor {}: stopped; published {} undelivered {} weights version {}",
        report.actor_id, report.published_transitions, report.undelivered_transitions, report.weights_version
    );
    Ok(())
}
