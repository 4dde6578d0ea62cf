//! `bcal-learner --run DIR [--resume]`: the learner process. The loop lives in the library
//! (`bcal_learner::process`); this file parses arguments and reports how the run ended. Exit code 0 at
//! the end of training and on SIGINT/SIGTERM (after a checkpoint).

use bcal_learner::process::{self, LearnerArgs, Outcome};
use clap::Parser;
use std::path::PathBuf;

/// The learner process of a bcal training run (started by `bcal train`).
#[derive(Parser, Debug)]
#[command(name = "bcal-learner", version)]
struct Args {
    /// Run folder holding config.toml and mdp.json (written by `bcal train`).
    #[arg(long = "run", value_name = "DIR")]
    run_dir: PathBuf,
    /// Continue from the run folder's latest checkpoint, with the same update counter.
    #[arg(long)]
    resume: bool,
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    match process::run(&LearnerArgs { run_dir: a.run_dir, resume: a.resume })? {
        Outcome::Finished { reason, updates } => eprintln!("bcal-learner: finished ({reason}) after {updates} updates"),
        Outcome::Stopped { updates } => eprintln!("bcal-learner: stopped by signal at update {updates}"),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arguments_parse_and_errors_say_what_is_wrong() {
        let a = Args::try_parse_from(["bcal-learner", "--run", "runs/x", "--resume"]).unwrap();
        assert_eq!((a.run_dir, a.resume), (PathBuf::from("runs/x"), true));
        assert!(!Args::try_parse_from(["bcal-learner", "--run=r"]).unwrap().resume);
        let e = Args::try_parse_from(["bcal-learner"]).unwrap_err().to_string();
        assert!(e.contains("--run"), "{e}");
        let e = Args::try_parse_from(["bcal-learner", "--run", "r", "--fast"]).unwrap_err().to_string();
        assert!(e.contains("--fast"), "{e}");
    }
}
