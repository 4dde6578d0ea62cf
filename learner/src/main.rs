//! `bcal-learner --run DIR [--resume]`: the learner process. The loop lives in `process.rs`; this file
//! only parses arguments and reports how the run ended. Exit code 0 at the end of training and on
//! SIGINT/SIGTERM (after a checkpoint).
//!
//! Arguments are parsed by hand (two flags) so the learner crate, shared with the LAC code, needs no
//! argument-parser dependency.

mod process;

use anyhow::bail;
use std::path::PathBuf;

const USAGE: &str = "usage: bcal-learner --run DIR [--resume]\n\n  \
    --run DIR   run folder holding config.toml and mdp.json (written by `bcal train`)\n  \
    --resume    continue from the run folder's latest checkpoint, with the same update counter";

fn parse(mut args: impl Iterator<Item = String>) -> anyhow::Result<Option<process::LearnerArgs>> {
    let (mut run_dir, mut resume) = (None, false);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--run" => {
                run_dir =
                    Some(PathBuf::from(args.next().ok_or_else(|| anyhow::anyhow!("--run needs a folder\n{USAGE}"))?))
            }
            s if s.starts_with("--run=") => run_dir = Some(PathBuf::from(&s["--run=".len()..])),
            "--resume" => resume = true,
            "-h" | "--help" => return Ok(None),
            other => bail!("unexpected argument {other:?}\n{USAGE}"),
        }
    }
    match run_dir {
        Some(run_dir) => Ok(Some(process::LearnerArgs { run_dir, resume })),
        None => bail!("--run DIR is required\n{USAGE}"),
    }
}

fn main() -> anyhow::Result<()> {
    let Some(args) = parse(std::env::args().skip(1))? else {
        println!("{USAGE}");
        return Ok(());
    };
    match process::run(&args)? {
        process::Outcome::Finished { reason, updates } => {
            eprintln!("bcal-learner: finished ({reason}) after {updates} updates")
        }
        process::Outcome::Stopped { updates } => eprintln!("bcal-learner: stopped by signal at update {updates}"),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(v: &[&str]) -> anyhow::Result<Option<process::LearnerArgs>> {
        parse(v.iter().map(|s| s.to_string()))
    }

    #[test]
    fn arguments_parse_and_errors_say_what_is_wrong() {
        let a = p(&["--run", "runs/x", "--resume"]).unwrap().unwrap();
        assert_eq!(a.run_dir, PathBuf::from("runs/x"));
        assert!(a.resume);
        assert!(!p(&["--run=r"]).unwrap().unwrap().resume);
        assert!(p(&["--help"]).unwrap().is_none());
        assert!(p(&[]).unwrap_err().to_string().contains("--run DIR is required"));
        assert!(p(&["--run", "r", "--fast"]).unwrap_err().to_string().contains("--fast"));
    }
}
