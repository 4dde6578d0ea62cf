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
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
