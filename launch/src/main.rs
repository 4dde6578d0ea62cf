//! `bcal`: the command-line entry point. `main` only parses and dispatches; each subcommand lives in its
//! own module with a `run` function returning `anyhow::Result`.

mod bench_cmd;
mod calibrate_cmd;
mod cli;
mod dataset_cmd;
mod diagnose_cmd;
mod eval_cmd;
mod follow;
mod simulate;
mod summarize_cmd;
mod supervisor;
mod train_cmd;

use clap::Parser;

fn main() {
    let args = cli::Cli::parse();
    let result = match args.command {
        cli::Command::Simulate(a) => simulate::run(a),
        cli::Command::Dataset(a) => dataset_cmd::run(a),
        cli::Command::Diagnose(a) => diagnose_cmd::run(a),
        cli::Command::Calibrate(a) => calibrate_cmd::run(a),
        cli::Command::CellConfig(a) => calibrate_cmd::run_cell_config(a),
        cli::Command::Train(a) => train_cmd::run(a),
        cli::Command::Eval(a) => eval_cmd::run(a),
        cli::Command::Summarize(a) => summarize_cmd::run(a),
        cli::Command::Bench(a) => bench_cmd::run(a),
        cli::Command::BenchPublish(a) => bench_cmd::publish(a),
    };
    if let Err(e) = result {
        eprintln!("error: {}", error_text(&e));
        std::process::exit(1);
    }
}

/// The error and its causes, each once: many errors hold their source in their own message as well (a
/// plain `{:#}` printed "no sample in any fit window: ...: no sample in any fit window").
fn error_text(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let c = cause.to_string();
        if out.contains(&c) {
            continue;
        }
        if !out.is_empty() {
            out.push_str(": ");
        }
        out.push_str(&c);
    }
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn an_error_prints_each_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such file");
        let e = anyhow::Error::new(io).context("cannot read a.csv: no such file").context("reading the cell");
        assert_eq!(super::error_text(&e), "reading the cell: cannot read a.csv: no such file");
        let e = anyhow::anyhow!("inner").context("outer");
        assert_eq!(super::error_text(&e), "outer: inner");
    }
}
