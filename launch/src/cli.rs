//! The `bcal` command line: every subcommand and flag, with the help text users read.

use bcal_common::dataset::Experiment;
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;

/// bcal keeps a Li-ion battery model true to the battery it describes: it simulates the NASA
/// electrochemistry model, generates the paper's calibration experiments, and trains and evaluates
/// calibrators.
#[derive(Parser, Debug)]
#[command(name = "bcal", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Simulate one discharge from a new cell's initial state until the voltage falls below VEOD (3.0 V).
    Simulate(SimulateArgs),
    /// Generate (and cache) or inspect the paper's experiment data sets.
    Dataset(DatasetArgs),
    /// Diagnose measured discharges: fit the model, find what it gets wrong, name the cause, extend it.
    Diagnose(crate::diagnose_cmd::DiagnoseArgs),
    /// Calibrate real cells in real time: feed measured discharges to the calibrators one reading at a time,
    /// predict the end of discharge and the capacity, and score them against what the cycler measured.
    Calibrate(crate::calibrate_cmd::CalibrateArgs),
    /// Write the training config of an RL calibrator for one real cell (its load, sampling, temperature,
    /// cut-off and parameter ranges from its training cycles).
    CellConfig(crate::calibrate_cmd::CellConfigArgs),
    /// Train the LAC calibrator: starts replay, learner and actor processes and supervises them.
    Train(crate::train_cmd::TrainArgs),
    /// Evaluate RL-LAC against the UKF and the direct mapping on the held-out (high-load) test trajectories;
    /// writes report.json, report.md and plots into the run folder (or --out).
    Eval(crate::eval_cmd::EvalArgs),
    /// Summarise evaluated runs of one setting (other seeds): mean, standard deviation, minimum and maximum
    /// of every headline figure, and each run's value.
    Summarize(crate::summarize_cmd::SummarizeArgs),
    /// Measure every performance figure the README quotes, each beside its baseline (model steps/s,
    /// calibrator step cost, iceoryx2 vs crossbeam transport, learner updates/s); prints tables and writes
    /// bench.json.
    Bench(crate::bench_cmd::BenchArgs),
    /// One transport publisher process of `bcal bench` (started by it).
    #[command(hide = true)]
    BenchPublish(crate::bench_cmd::BenchPublishArgs),
}

#[derive(Args, Debug)]
#[command(group(clap::ArgGroup::new("load").required(true).args(["load_w", "current_a"])))]
pub struct SimulateArgs {
    /// Mobile lithium charge qMobile, C (new cell: 7600).
    #[arg(long, default_value_t = 7600.0, value_parser = positive_f64, allow_hyphen_values = true)]
    pub q_mobile: f64,
    /// Internal (ohmic) resistance Ro, ohm (new cell: 0.117215).
    #[arg(long, default_value_t = 0.117215, value_parser = non_negative_f64, allow_hyphen_values = true)]
    pub ro: f64,
    /// Constant power load, W (the paper's input: current = P / V each step).
    #[arg(long, value_parser = positive_f64, allow_hyphen_values = true)]
    pub load_w: Option<f64>,
    /// Constant discharge current, A (positive while discharging).
    #[arg(long, value_parser = positive_f64, allow_hyphen_values = true)]
    pub current_a: Option<f64>,
    /// Turn on the thermal state (bulk temperature tb with self-heating); adds a `tb_k` column.
    #[arg(long)]
    pub thermal: bool,
    /// Euler time step, s (below 12.17 s, twice the ohmic lag, where explicit Euler stays stable).
    #[arg(long, default_value_t = 1.0, value_parser = positive_f64)]
    pub dt: f64,
    /// Stop after this many steps if VEOD is never reached.
    #[arg(long, default_value_t = 200_000)]
    pub max_steps: usize,
    /// Write every step as CSV: t_s,voltage_v,qpS,qpB,qnB,qnS,Vo,Vsn,Vsp, the input (load_w or current_a),
    /// and tb_k when --thermal.
    #[arg(long, value_name = "FILE.csv")]
    pub out: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct DatasetArgs {
    #[command(subcommand)]
    pub action: DatasetAction,
}

#[derive(Subcommand, Debug)]
pub enum DatasetAction {
    /// Generate an experiment's trajectories on all cores and cache them (reads the cache when valid).
    Generate(DatasetSelect),
    /// Summarise a cached experiment: trajectories, train/test split by load, steps, EOD range.
    Info(DatasetSelect),
}

#[derive(Args, Debug)]
pub struct DatasetSelect {
    /// Which experiment (paper Appendix A); all three when left out.
    #[arg(long, value_enum)]
    pub experiment: Option<Experiment>,
    /// Cache folder (default: $BCAL_CACHE/datasets or ~/.cache/bcal/datasets).
    #[arg(long)]
    pub cache_dir: Option<PathBuf>,
    /// Regenerate even when a valid cache file exists.
    #[arg(long)]
    pub force: bool,
}

impl DatasetSelect {
    pub fn experiments(&self) -> Vec<Experiment> {
        match self.experiment {
            Some(e) => vec![e],
            None => Experiment::ALL.to_vec(),
        }
    }
}

fn parse_number(s: &str) -> Result<f64, String> {
    s.trim().parse().map_err(|_| format!("`{s}` is not a number"))
}

/// A finite number > 0 (the check `bcal.simulate` makes too: [`bcal_common::simulate::positive`]).
pub fn positive_f64(s: &str) -> Result<f64, String> {
    bcal_common::simulate::positive(parse_number(s)?)
}

/// An ambient temperature, deg C, within those the model is taken at
/// ([`bcal_common::measured::extension::TEMPERATURE_RANGE_K`]).
pub fn ambient_c(s: &str) -> Result<f64, String> {
    use bcal_common::measured::{extension::TEMPERATURE_RANGE_K, scenario::KELVIN_0C};
    let c = parse_number(s)?;
    let [lo, hi] = TEMPERATURE_RANGE_K.map(|k| k - KELVIN_0C);
    if c.is_finite() && c > lo && c < hi {
        Ok(c)
    } else {
        Err(format!("`{}` is not an ambient temperature in deg C (between {lo:.2} and {hi:.2})", s.trim()))
    }
}

/// The seconds a process gets to exit after SIGTERM: 0 to an hour (a negative, NaN or astronomical grace
/// made no duration, and panicked after the run had started).
pub fn grace_s(s: &str) -> Result<f64, String> {
    let v = parse_number(s)?;
    if (0.0..=3600.0).contains(&v) {
        Ok(v)
    } else {
        Err(format!("`{}` is not a grace in seconds from 0 to 3600", s.trim()))
    }
}

/// A finite number >= 0.
pub fn non_negative_f64(s: &str) -> Result<f64, String> {
    bcal_common::simulate::non_negative(parse_number(s)?)
}
