//! `bcal diagnose`: reads measured discharges (NASA PCoE through metadata.csv, or the generic CSV),
//! runs the doctor (base calibration, residual analysis, candidate causes, extended model) and writes
//! `diagnosis.json`, `diagnosis.md` and residual plots into `--out`; then the lifetime diagnosis (capacity
//! across every record of the two ranges, recovery after rest) into the same files.

use anyhow::Context;
use bcal_doctor::input::diagnose_with_lifetime;
use bcal_doctor::read::{parse_cycle_range, read_csv, read_nasa_with, CurrentSign, ReadOptions, RecordStart};
use bcal_doctor::{Cause, DiagnoseConfig, Discharge};
use clap::ValueEnum;
use std::ops::RangeInclusive;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct DiagnoseArgs {
    /// Measured data: a NASA PCoE folder (holding metadata.csv and data/) or a generic CSV file with
    /// columns time_s,voltage_v,current_a[,temperature_c][,cycle] (current positive while discharging).
    #[arg(long, value_name = "PATH")]
    pub data: PathBuf,
    /// Cell to read from a NASA folder (battery_id in metadata.csv; required there); for a CSV, the name the
    /// report gives it (default: the file's name).
    #[arg(long)]
    pub cell: Option<String>,
    /// Training cycles A..B (inclusive; NASA: the order of the cell's discharges from 1; a CSV: its cycle numbers). Default, when
    /// --holdout is not given either: the first three quarters of the cycles `bcal calibrate` trains on (the
    /// first third of the life, at most 40; B0005: 1..30, held out 31..40), so the diagnosis feeds `bcal
    /// calibrate --model`, a short life's too (within them; two discharges: the first against the second). With --holdout:
    /// every cycle before it.
    #[arg(long, value_name = "A..B")]
    pub cycles: Option<String>,
    /// Held-out cycles A..B used to judge every model. Default: the cycles after --cycles.
    #[arg(long, value_name = "A..B")]
    pub holdout: Option<String>,
    /// Use every N-th cycle of the training and held-out ranges (a whole-life run stays quick).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    pub stride: u32,
    /// Output folder for diagnosis.json, diagnosis.md and the plots.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Longest simulator step, s (the simulator also lands on every sample time). 2 s gives the same verdicts
    /// and held-out RMSEs as 1 s within 0.05 mV on the NASA cells (the overpotential lags are advanced
    /// exactly), at half the cost.
    #[arg(long, default_value_t = bcal_doctor::input::DIAGNOSE_DT_MAX_S, value_parser = crate::cli::positive_f64)]
    pub dt: f64,
    /// Fit window floor: samples under load count down to the first one below this voltage, V.
    #[arg(long, default_value_t = 2.9, value_parser = crate::cli::positive_f64)]
    pub v_floor: f64,
    /// A sample is under load when its discharge current exceeds this, A.
    #[arg(long, default_value_t = 0.05, value_parser = crate::cli::positive_f64)]
    pub load_threshold: f64,
    /// Ambient temperature for a generic CSV, deg C (default: each record's first temperature, else 25).
    #[arg(long, allow_hyphen_values = true, value_parser = crate::cli::ambient_c)]
    pub ambient_c: Option<f64>,
    /// Which sign of the current is discharge: `auto` decides from the data and says what it chose
    /// (NASA: negative; the generic CSV: positive; the Battery Data Format: negative).
    #[arg(long, default_value = "auto")]
    pub current_sign: CurrentSign,
    /// Cut-off voltage: a record ending under load at or below it is a complete discharge (default: the
    /// cell's documented protocol for a NASA folder, else 2.5 V with a note per record).
    #[arg(long, value_parser = crate::cli::positive_f64)]
    pub cutoff_v: Option<f64>,
    /// Candidate causes to test (comma-separated). Default: all.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub causes: Vec<CauseArg>,
    /// Most causes the extended model may combine.
    #[arg(long, default_value_t = 3)]
    pub max_causes: usize,
    /// Held-out gain a cause needs to be named (else the verdict is `none`), %.
    #[arg(long, default_value_t = 10.0, value_parser = crate::cli::non_negative_f64)]
    pub min_gain_pct: f64,
    /// Skip the PNG/SVG residual plots.
    #[arg(long)]
    pub no_plots: bool,
    /// Skip the lifetime diagnosis (capacity against cycle, rest and conditions; recovery after rest), which
    /// otherwise runs on every record of the training and held-out ranges.
    #[arg(long)]
    pub no_lifetime: bool,
}

#[derive(Clone, Copy, Debug, ValueEnum, PartialEq, Eq)]
pub enum CauseArg {
    Thermal,
    Ocv,
    Diffusion,
    ExtraPolarization,
    VoltageOffset,
    CurrentGain,
    ElectrodeBalance,
    ChargeTransfer,
}

impl From<CauseArg> for Cause {
    fn from(c: CauseArg) -> Self {
        match c {
            CauseArg::Thermal => Cause::Thermal,
            CauseArg::Ocv => Cause::Ocv,
            CauseArg::Diffusion => Cause::Diffusion,
            CauseArg::ExtraPolarization => Cause::ExtraPolarization,
            CauseArg::VoltageOffset => Cause::VoltageOffset,
            CauseArg::CurrentGain => Cause::CurrentGain,
            CauseArg::ElectrodeBalance => Cause::ElectrodeBalance,
            CauseArg::ChargeTransfer => Cause::ChargeTransfer,
        }
    }
}

/// What [`load`] read: the cell, every record of its life with their starts, the two ranges and the
/// records picked from them.
struct Loaded {
    cell: String,
    all: Vec<Discharge>,
    starts: Vec<RecordStart>,
    train_r: RangeInclusive<u32>,
    held_r: RangeInclusive<u32>,
    train: Vec<Discharge>,
    held: Vec<Discharge>,
}

/// Reads every record (and when each started, for the lifetime diagnosis), then splits it into training and
/// held-out sets.
fn load(a: &DiagnoseArgs) -> anyhow::Result<Loaded> {
    let cycles = a.cycles.as_deref().map(parse_cycle_range).transpose()?;
    let holdout = a.holdout.as_deref().map(parse_cycle_range).transpose()?;
    let opts = ReadOptions { current_sign: a.current_sign, ambient_c: a.ambient_c, ..ReadOptions::default() };
    let cell = crate::calibrate_cmd::cell_name(&a.cell, &a.data)?;
    let (all, report) = if a.data.is_dir() {
        read_nasa_with(&a.data, &cell, None, &opts)
            .with_context(|| format!("reading cell {cell} from {}", a.data.display()))?
    } else {
        read_csv(&a.data, &opts).with_context(|| format!("reading {}", a.data.display()))?
    };
    for line in report.summary() {
        eprintln!("{line}");
    }
    anyhow::ensure!(!all.is_empty(), "{} holds no discharge record", a.data.display());
    let (train_r, held_r) = bcal_doctor::input::cycle_ranges(&all, cycles.clone(), holdout.clone());
    let (train, held) = bcal_doctor::input::split_cycles(&all, cycles, holdout, a.stride)?;
    Ok(Loaded { cell, starts: report.starts, all, train_r, held_r, train, held })
}

pub fn run(a: DiagnoseArgs) -> anyhow::Result<()> {
    let Loaded { cell, all, starts, train_r, held_r, train, held } = load(&a)?;
    let cut = crate::calibrate_cmd::cutoff(a.cutoff_v, &a.data, &cell, &train);
    match &cut {
        Some((v, why)) => eprintln!("cut-off {v} V: {why}"),
        None => eprintln!(
            "cut-off: none given (--cutoff-v) nor documented for {}: a record ending under load at or below {} V is \
             taken as complete, one above it as cut short (give the cell's cut-off with --cutoff-v)",
            a.data.display(),
            bcal_doctor::record::DEFAULT_CUTOFF_V
        ),
    }
    let mut cfg = DiagnoseConfig {
        cutoff_v: cut.map(|c| c.0),
        max_causes: a.max_causes,
        min_gain_pct: a.min_gain_pct,
        ..DiagnoseConfig::default()
    };
    cfg.fit.dt_max_s = a.dt;
    cfg.fit.v_floor_v = a.v_floor;
    cfg.fit.load_threshold_a = a.load_threshold;
    if !a.causes.is_empty() {
        cfg.causes = a.causes.iter().map(|c| Cause::from(*c)).collect();
    }
    eprintln!("diagnose: {} training and {} held-out records", train.len(), held.len());
    let started = std::time::Instant::now();
    let (diag, lifetime_skipped) =
        diagnose_with_lifetime(&cfg, &all, &starts, (&train_r, &held_r), &train, &held, !a.no_lifetime)
            .context("diagnosis failed")?;
    let voltage_s = started.elapsed().as_secs_f64();
    match (&diag.lifetime, lifetime_skipped) {
        (Some(l), _) => eprintln!("lifetime: recovery after rest {}", l.verdict),
        (None, Some(why)) => eprintln!("lifetime diagnosis skipped: {why}"),
        (None, None) => {}
    }
    let mut written = bcal_doctor::report::write_reports(&diag, &a.out)?;
    if !a.no_plots {
        match bcal_doctor::plot::write_plots(&diag, &a.out) {
            Ok(paths) => written.extend(paths),
            Err(e) => eprintln!("diagnose: plots skipped: {e}"),
        }
    }
    println!(
        "cause: {}{}  base held-out RMSE {:.2} mV  extended ({}) {:.2} mV  gain {:.1} %  [{:.0} s; {:.1} s per record \
         and cause]",
        diag.cause,
        if diag.named_on == "rest_before" { " (on the rest before the load)" } else { "" },
        diag.base.heldout_rmse_mv,
        if diag.extended.causes.is_empty() { "-".to_string() } else { diag.extended.causes.join("+") },
        diag.extended.heldout_rmse_mv,
        diag.gain_pct,
        voltage_s,
        voltage_s / ((train.len() + held.len()) * cfg.causes.len().max(1)) as f64
    );
    if let Some(w) = bcal_doctor::report::at_bounds_warning(&diag.extended) {
        eprintln!("diagnose: {w}");
    }
    for p in written {
        println!("wrote {}", p.display());
    }
    Ok(())
}
