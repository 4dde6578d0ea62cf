//! `bcal calibrate` and `bcal cell-config`: real cells in real time.
//!
//! `calibrate` reads a NASA PCoE folder or a generic CSV, feeds each judged discharge to the calibrators one
//! reading at a time (no look-ahead), writes every reading's estimates, 90 % intervals, predicted end of
//! discharge and capacity, and scores them against what the cycler measured (calibration.json, .md,
//! figures). `cell-config` writes the training config of a policy for one cell (the measured-only setting
//! with the cell's load, sampling, temperature, cut-off and parameter ranges from its training cycles).

use anyhow::{bail, Context};
use bcal_calib::tune::{AdaptiveGrid, JointUkfGrid};
use bcal_common::config::{Preset, TrainConfig};
use bcal_common::measured::scenario::RestJumpConfig;
use bcal_common::policy::{PolicyFile, POLICY_BEST};
use bcal_doctor::lifetime::{LifetimeModel, Quantity};
use bcal_doctor::read::{parse_cycle_range, CurrentSign, ReadOptions, RecordStart};
use bcal_doctor::Discharge;
use bcal_realcell::calibrate::{calibrate, choose_cell_rule, choose_cell_ukf, CalibrateInput, CellHistory};
use bcal_realcell::cellspec::cell_spec;
use bcal_realcell::record::{prepare, RecordSummary};
use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct CalibrateArgs {
    /// Measured data: a NASA PCoE folder (metadata.csv and data/) or a generic CSV
    /// (time_s,voltage_v,current_a[,temperature_c][,cycle], current positive while discharging).
    #[arg(long, value_name = "PATH", required_unless_present = "follow")]
    pub data: Option<PathBuf>,
    /// Live readings instead of --data: `-` reads standard input, FILE follows a file another process is
    /// still writing (from its start, then every line appended). CSV rows under a header
    /// `time_s,voltage_v,current_a[,temperature_c]` or JSON lines with those keys (other units named as the
    /// CSV readers read them: time_ms, voltage_mv, current_ma, NASA's Voltage_measured); one JSON line per reading
    /// on standard output (estimate, 90 % interval, predicted EOD) as soon as it is computed. A bad line is
    /// reported with its number and skipped; end of input, --idle-s or Ctrl-C ends with a summary. Runs one
    /// calibrator (--calibrator ukf by default; `fit` is then the streaming window fit) on a new cell's prior,
    /// or on --config / --model. A stream may hold many discharges: after a charge or a gap of more than
    /// 30 min a new one starts (`discharge` counts them) from what the last one told (the charge its end
    /// measured where it reached the cut-off, else its final estimate), with a prior width learned from the
    /// discharges before, the last one's posterior until enough are known; the end of discharge gets a 90 %
    /// interval learned from the discharges followed to their cut-off (docs/follow.md).
    #[arg(long, value_name = "-|FILE", conflicts_with_all = ["data", "cycles", "quick"])]
    pub follow: Option<String>,
    /// With --follow: the cell's config (a `bcal cell-config` TOML) whose measured.tracker sets the
    /// calibrator's ranges, prior and cut-off, measured.ukf its filter, and measured.lifetime how each
    /// discharge's carried value moves to the next (fade, capacity regained over a rest).
    #[arg(long, value_name = "FILE.toml", requires = "follow")]
    pub config: Option<PathBuf>,
    /// With --follow FILE: end when no new line has come for this long, s (default: follow until Ctrl-C).
    #[arg(long, value_name = "S", requires = "follow", value_parser = crate::cli::positive_f64)]
    pub idle_s: Option<f64>,
    /// Cell to read from a NASA folder (battery_id in metadata.csv; required there); for a CSV, the name the
    /// report gives it (default: the file's name).
    #[arg(long)]
    pub cell: Option<String>,
    /// The doctor's extended model to calibrate (`diagnosis.json` of `bcal diagnose` on the training
    /// cycles, or its folder): the calibrators then track its per-cycle parameters (electrode balance,
    /// charge-transfer factor) too, from discharge to discharge, and run its shared ones (Arrhenius
    /// temperature dependence). Without it, the base model.
    #[arg(long, value_name = "DIAG")]
    pub model: Option<PathBuf>,
    /// Cycles to judge, A..B (NASA: the order of the cell's discharges from 1; a CSV: its cycle column's numbers, from
    /// 0 or 1). Default: those after --train-cycles.
    #[arg(long, value_name = "A..B")]
    pub cycles: Option<String>,
    /// Training cycles, A..B: the capacity trend, the cell's setting and the first previous-cycle reference.
    /// Default: the cell's first third of discharges, at most 40 and at least 4 while one is left to judge
    /// (B0005: 1..40; a cell of 28 discharges: 1..9; of 8: 1..4), said on stderr.
    #[arg(long, value_name = "A..B")]
    pub train_cycles: Option<String>,
    /// Calibrators, comma separated: `rl:RUN` (the RL policy of a measured-only run folder, or a policy file;
    /// `rl:` given more than once: an ensemble of runs of one cell config trained from other seeds, each run's
    /// delivered policy, whose mean action corrects the filter),
    /// `ukf` (the joint UKF, its settings chosen on the last training cycles; with it `ukf_learned`, the same
    /// filter with its capacity and end of discharge moved by a learner on its own record across the cell's
    /// discharges, reported beside it; `ukf_learned` asks for the two as well), `adaptive_ukf` (that filter
    /// with its noise adapted by covariance matching, the rule chosen on the same cycles), `fit` (the doctor's
    /// offline least squares on the whole discharge: an oracle that sees the future). The references
    /// (uncalibrated, previous cycle, prior, parameter trend) always run. Over a cell's discharges the
    /// policy serves each share of a discharge where it beat the joint UKF on 8 of the last 10 that ended,
    /// else the filter, and every streaming calibrator hands a share to its prior alone where the prior
    /// did; a discharge after a rest of more than a day goes to the filter (docs/realcell.md, "who serves
    /// each discharge").
    /// Default `ukf,adaptive_ukf,fit`; with --follow one of ukf, adaptive_ukf, ukf_learned (the joint UKF with
    /// its end of discharge moved by the learner on the stream's own record), fit (the streaming window fit),
    /// uncalibrated or rl:FILE (default ukf).
    #[arg(long, value_delimiter = ',')]
    pub calibrator: Vec<String>,
    /// Cut-off voltage of the end-of-discharge predictions, V (default: the cell's documented protocol, else
    /// what the training records show: where their discharges end under load; with --follow the config's,
    /// else the --model diagnosis's where it was the cell's own, else 3.0).
    #[arg(long, value_parser = crate::cli::positive_f64)]
    pub cutoff_v: Option<f64>,
    /// Ambient temperature for a generic CSV without a temperature column, deg C.
    #[arg(long, allow_hyphen_values = true, value_parser = crate::cli::ambient_c)]
    pub ambient_c: Option<f64>,
    /// Which sign of the current is discharge: `auto` decides from the data and says what it chose.
    #[arg(long, default_value = "auto")]
    pub current_sign: CurrentSign,
    /// Use every N-th judged cycle (a whole-life run stays quick; the previous-cycle reference and each
    /// discharge's start then come from the judged cycle N before).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    pub stride: u32,
    /// A quick run: a small joint UKF grid.
    #[arg(long)]
    pub quick: bool,
    /// Output folder for calibration.json, calibration.md, the figures and readings/<method>/<cell>-<cycle>.csv.
    #[arg(long, value_name = "DIR", required_unless_present_any = ["follow", "print_train_cycles"])]
    pub out: Option<PathBuf>,
    /// Print the training cycles the cell gets (A..B: --train-cycles or its default) and exit
    /// (`launch/run.sh --cell` splits them for the doctor).
    #[arg(long)]
    pub print_train_cycles: bool,
}

#[derive(clap::Args, Debug)]
pub struct CellConfigArgs {
    /// Measured data, as for `bcal calibrate`.
    #[arg(long, value_name = "PATH")]
    pub data: PathBuf,
    /// Cell to read from a NASA folder (required there), as for `bcal calibrate`.
    #[arg(long)]
    pub cell: Option<String>,
    /// The doctor's extended model (`diagnosis.json`), as for `bcal calibrate`: the simulated cells and
    /// the policy's calibrator run it.
    #[arg(long, value_name = "DIAG")]
    pub model: Option<PathBuf>,
    /// Training cycles, A..B. Default: as `bcal calibrate` takes them (the first third of the cell's
    /// discharges, at most 40), said on stderr.
    #[arg(long, value_name = "A..B")]
    pub train_cycles: Option<String>,
    #[arg(long, value_parser = crate::cli::positive_f64)]
    pub cutoff_v: Option<f64>,
    #[arg(long, allow_hyphen_values = true, value_parser = crate::cli::ambient_c)]
    pub ambient_c: Option<f64>,
    #[arg(long, default_value = "auto")]
    pub current_sign: CurrentSign,
    /// The run's training budget, s.
    #[arg(long, default_value_t = 900.0, value_parser = crate::cli::positive_f64)]
    pub budget_s: f64,
    /// The TOML file to write (a complete config over the measured preset: `bcal train --config FILE`).
    #[arg(long, value_name = "FILE.toml")]
    pub out: PathBuf,
}

/// Reads the discharges of `cycles` (all when None): a NASA folder, else any CSV the doctor reads (the
/// generic layout, the Battery Data Format, units and current sign as `opts` say), with when each record
/// started (the rests between discharges, for the prior across them); what the reader decided or skipped
/// goes to stderr, and what it could not read and its notes to the report.
pub fn read_with_starts(
    data: &Path,
    cell: &str,
    cycles: Option<&RangeInclusive<u32>>,
    opts: &ReadOptions,
) -> anyhow::Result<(Vec<Discharge>, Vec<RecordStart>, Said)> {
    let (ds, rep) = bcal_doctor::input::read_any(data, cell, cycles, opts).with_context(|| {
        if data.is_dir() {
            format!("reading cell {cell} from {}", data.display())
        } else {
            format!("reading {}", data.display())
        }
    })?;
    for line in rep.summary() {
        eprintln!("{line}");
    }
    // What was not read goes into the report too (a record is never dropped without a word there).
    let mut unread: Vec<Unread> = rep
        .missing_files
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let cycle = rep.missing_cycles.get(k).copied();
            let of = cycle.map_or(String::new(), |c| format!(" (cycle {c})"));
            Unread { cycle, why: format!("{f}{of}: named in the metadata, not on disk") }
        })
        .collect();
    unread.extend(rep.skipped.iter().map(|s| Unread { cycle: s.cycle, why: s.reason.clone() }));
    Ok((ds, rep.starts, Said { unread, notes: rep.notes }))
}

/// What the reader said beside the records it gave: the ones it could not read, and its notes (a damaged end
/// read up to, readings written twice, a gap, a file read against its format's sign, a cycle without
/// discharge), each naming the file.
#[derive(Default)]
pub struct Said {
    pub unread: Vec<Unread>,
    pub notes: Vec<String>,
}

/// A record the reader could not read: its cycle where known, and why (naming the file).
pub struct Unread {
    pub cycle: Option<u32>,
    pub why: String,
}

/// The training cycles given, or the cell's default ([`bcal_doctor::input::default_train_cycles`], said on
/// stderr) with every record it was read from.
#[allow(clippy::type_complexity)]
fn train_cycles(
    given: Option<&str>,
    data: &Path,
    cell: &str,
    opts: &ReadOptions,
) -> anyhow::Result<(RangeInclusive<u32>, Option<(Vec<Discharge>, Vec<RecordStart>, Said)>)> {
    if let Some(t) = given {
        let range = parse_cycle_range(t)?;
        // A folder is read by the cycles asked; a CSV is read whole whatever they are: once, not once per range.
        if data.is_dir() {
            return Ok((range, None));
        }
        return Ok((range, Some(read_with_starts(data, cell, None, opts)?)));
    }
    let (all, starts, said) = read_with_starts(data, cell, None, opts)?;
    let range = bcal_doctor::input::default_train_cycles(cell, &all)?;
    eprintln!(
        "training cycles {}..{} (the first third of {cell}'s {} discharges, at most {}, at least {}; --train-cycles \
         sets them)",
        range.start(),
        range.end(),
        all.len(),
        bcal_doctor::input::DEFAULT_TRAIN_MAX,
        bcal_doctor::input::DEFAULT_TRAIN_MIN
    );
    Ok((range, Some((all, starts, said))))
}

/// The policy files of `rl:RUN`: a run folder's checkpoints (best and last by each criterion, duplicates
/// dropped; the validation cycles choose one), or the one file given.
fn policy_candidates(p: &Path) -> anyhow::Result<Vec<(PolicyFile, String)>> {
    let files: Vec<PathBuf> = if p.is_dir() {
        let v: Vec<PathBuf> = POLICY_CANDIDATES.iter().map(|f| p.join(f)).filter(|f| f.is_file()).collect();
        if v.is_empty() {
            bail!(
                "no policy file in {} (expected {}): train it first (bcal train --run DIR)",
                p.display(),
                POLICY_CANDIDATES.join(", ")
            );
        }
        v
    } else {
        vec![p.to_path_buf()]
    };
    let mut out: Vec<(PolicyFile, String)> = Vec::new();
    for f in files {
        let pf = PolicyFile::load(&f).with_context(|| format!("the RL policy {}", f.display()))?;
        if pf.task.measured().is_none() {
            bail!(
                "the policy {} was trained on the {} observation; bcal calibrate runs measured-only policies \
                 (train one with bcal cell-config and bcal train --config)",
                f.display(),
                pf.task.observation_name()
            );
        }
        if !out.iter().any(|(o, _)| o.update_step == pf.update_step) {
            out.push((pf, f.display().to_string()));
        }
    }
    Ok(out)
}

/// The policy files a run folder can hold, in order of preference on a tie.
const POLICY_CANDIDATES: [&str; 4] =
    [POLICY_BEST, "policy.best-tracking-error.bcalpol", "policy.best-nrmse.bcalpol", "policy.bcalpol"];

/// The cut-off and where it came from ([`bcal_doctor::input::cutoff`]).
pub fn cutoff(given: Option<f64>, data: &Path, cell: &str, records: &[Discharge]) -> Option<(f64, String)> {
    bcal_doctor::input::cutoff(given, data, cell, records, bcal_realcell::record::LOAD_THRESHOLD_A)
}

/// [`cutoff`], or a refusal saying what to do.
fn cutoff_or_refuse(
    given: Option<f64>,
    data: &Path,
    cell: &str,
    records: &[Discharge],
) -> anyhow::Result<(f64, String)> {
    cutoff(given, data, cell, records).ok_or_else(|| {
        anyhow::anyhow!(
            "no cut-off voltage is documented for {cell} in {} and the records do not show one (too few end under \
             load at one voltage); pass --cutoff-v",
            data.display()
        )
    })
}

/// The cell's name: given, else (a CSV) the file's name; a NASA folder needs one.
pub fn cell_name(given: &Option<String>, data: &Path) -> anyhow::Result<String> {
    Ok(bcal_doctor::input::cell_name(given.as_deref(), data)?)
}

/// The doctor's model from `--model`, if given.
fn load_model(path: &Option<PathBuf>) -> anyhow::Result<Option<bcal_doctor::model_file::DiagnosedModel>> {
    let m = path.as_deref().map(bcal_doctor::model_file::load_model).transpose()?;
    // A cause the calibrators cannot carry is left out, not refused: the user is told which.
    if let Some(note) = m.as_ref().and_then(|m| m.carrying_note()) {
        eprintln!("--model {}: {note}", m.as_ref().map_or_else(String::new, |m| m.path.display().to_string()));
    }
    Ok(m)
}

pub fn run(a: CalibrateArgs) -> anyhow::Result<()> {
    for (flag, v) in [("--ambient-c", a.ambient_c), ("--cutoff-v", a.cutoff_v)] {
        if let Some(v) = v.filter(|v| !v.is_finite()) {
            bail!("{flag} {v}: not a finite number; give deg C for --ambient-c, volts for --cutoff-v");
        }
    }
    if let Some(source) = a.follow {
        let calibrator = match a.calibrator.as_slice() {
            [] => "ukf".to_string(),
            [one] => one.clone(),
            more => bail!("--follow runs one calibrator; --calibrator names {}: give one", more.join(",")),
        };
        return crate::follow::run(crate::follow::FollowArgs {
            source,
            calibrator,
            model: a.model,
            config: a.config,
            cutoff_v: a.cutoff_v,
            ambient_c: a.ambient_c,
            current_sign: a.current_sign,
            idle_s: a.idle_s,
        });
    }
    if a.print_train_cycles {
        let data = a.data.clone().context("--print-train-cycles needs --data PATH")?;
        let cell = cell_name(&a.cell, &data)?;
        let opts = ReadOptions { current_sign: a.current_sign, ambient_c: a.ambient_c, ..ReadOptions::default() };
        let (r, _) = train_cycles(a.train_cycles.as_deref(), &data, &cell, &opts)?;
        println!("{}..{}", r.start(), r.end());
        return Ok(());
    }
    if let Some(c) = &a.config {
        bail!(
            "--config {} is for --follow (a live stream's setting); with --data each calibrator is set up on the \
             training cycles: leave --config out (--model gives a diagnosed model)",
            c.display()
        );
    }
    let (Some(data), Some(out)) = (a.data.clone(), a.out.clone()) else {
        bail!("give --data PATH and --out DIR (or --follow - for live readings)");
    };
    let calibrators = if a.calibrator.is_empty() {
        vec!["ukf".into(), "adaptive_ukf".into(), "fit".into()]
    } else {
        a.calibrator.clone()
    };
    let started = Instant::now();
    if a.ambient_c.is_some() && data.is_dir() {
        eprintln!(
            "--ambient-c: a NASA folder gives each record's ambient (metadata.csv's ambient_temperature): not used"
        );
    }
    let cell = cell_name(&a.cell, &data)?;
    let model = load_model(&a.model)?;
    let opts = ReadOptions { current_sign: a.current_sign, ambient_c: a.ambient_c, ..ReadOptions::default() };
    let (train_range, everything) = train_cycles(a.train_cycles.as_deref(), &data, &cell, &opts)?;
    let judged_range = match &a.cycles {
        Some(c) => parse_cycle_range(c)?,
        None => (*train_range.end() + 1)..=u32::MAX,
    };
    let shown = |r: &std::ops::RangeInclusive<u32>| {
        if *r.end() == u32::MAX {
            format!("{}..", r.start())
        } else {
            format!("{}..{}", r.start(), r.end())
        }
    };
    if judged_range.start() <= train_range.end() {
        bail!(
            "--cycles {} must come after --train-cycles {}: the calibrators are set up on earlier discharges and \
             judged on later ones, as a cell ages",
            shown(&judged_range),
            shown(&train_range)
        );
    }
    // The cycles the data holds, where it was read whole (to say so if none was asked for).
    let held = everything.as_ref().and_then(|(all, _, _)| {
        let cycles = all.iter().map(|d| d.cycle);
        Some(format!("; {} holds cycles {}..{}", data.display(), cycles.clone().min()?, cycles.max()?))
    });
    let (train, mut judged, starts, said) = match everything {
        // Read once already; the starts of records outside both ranges are never looked up.
        Some((all, starts, said)) => {
            let (train, rest): (Vec<Discharge>, Vec<Discharge>) =
                all.into_iter().partition(|d| train_range.contains(&d.cycle));
            let judged = rest.into_iter().filter(|d| judged_range.contains(&d.cycle)).collect();
            (train, judged, starts, said)
        }
        None => {
            let (train, mut starts, mut said) = read_with_starts(&data, &cell, Some(&train_range), &opts)?;
            let (judged, judged_starts, judged_said) = read_with_starts(&data, &cell, Some(&judged_range), &opts)?;
            starts.extend(judged_starts);
            said.unread.extend(judged_said.unread);
            said.notes.extend(judged_said.notes);
            (train, judged, starts, said)
        }
    };
    // A CSV is read whole at each read, and a folder's metadata notes come with each: each said once, and
    // what was not read only where it lies within the cycles asked for.
    let within = |u: &Unread| u.cycle.is_none_or(|c| train_range.contains(&c) || judged_range.contains(&c));
    let once = |lines: Vec<String>| {
        lines.into_iter().fold(Vec::new(), |mut out: Vec<String>, l| {
            if !out.contains(&l) {
                out.push(l);
            }
            out
        })
    };
    let unread = once(said.unread.into_iter().filter(within).map(|u| u.why).collect());
    let noted = once(said.notes);
    if train.is_empty() && judged.is_empty() {
        bail!(
            "{cell}: no discharge read from {} in cycles {} or {}{}",
            data.display(),
            shown(&train_range),
            shown(&judged_range),
            held.unwrap_or_else(|| " (the reader's lines above say what was missing or refused)".into())
        );
    }
    if judged.is_empty() {
        let last = train.iter().map(|d| d.cycle).max().unwrap_or(0);
        bail!(
            "{cell}: no discharge to judge in cycles {} (its discharges end at cycle {last}, within --train-cycles {}); \
             give fewer training cycles, e.g. --train-cycles 1..{} (the first third), or leave --train-cycles out \
             for the cell's default",
            shown(&judged_range),
            shown(&train_range),
            (last / 3).max(2)
        );
    }
    // Read off the training records only, as cell-config does: the judged ones are not looked at.
    let (cut, cut_source) = cutoff_or_refuse(a.cutoff_v, &data, &cell, &train)?;
    // The rests between discharges, from every record read: a record left out by --stride still ends the
    // rest before the next one.
    let rests = {
        let all: Vec<&bcal_doctor::Discharge> = train.iter().chain(&judged).collect();
        bcal_realcell::prior::rests_before(&all, &starts)
    };
    if a.stride > 1 {
        let first = judged.first().map_or(0, |d| d.cycle);
        judged.retain(|d| (d.cycle - first) % a.stride == 0);
    }
    // The calibrators asked for.
    let mut runs: Vec<&str> = Vec::new();
    let (mut ukf, mut adaptive_ukf, mut fit) = (false, false, false);
    for c in &calibrators {
        match c.trim() {
            // The learner on the record runs on the filter's record: asking for either gives both.
            "ukf" | "ukf_learned" | "ukf-learned" => ukf = true,
            "adaptive_ukf" | "adaptive-ukf" => adaptive_ukf = true,
            "fit" => fit = true,
            s if s.starts_with("rl:") => runs.push(&s.trim()[3..]),
            other => bail!(
                "unknown calibrator `{other}`: use rl:RUN, ukf, ukf_learned, adaptive_ukf or fit (comma separated)"
            ),
        }
    }
    // One run: each of its checkpoints is a candidate. Several: one ensemble of each run's delivered policy.
    let mut policies: Vec<(PolicyFile, String)> = Vec::new();
    for run in &runs {
        let mut files = policy_candidates(Path::new(run))?;
        if runs.len() > 1 {
            files.truncate(1);
        }
        policies.extend(files);
    }
    let groups: Vec<Vec<(&PolicyFile, String)>> = if runs.len() > 1 {
        vec![policies.iter().map(|(pf, p)| (pf, p.clone())).collect()]
    } else {
        policies.iter().map(|(pf, p)| vec![(pf, p.clone())]).collect()
    };
    // The RL run's own cell setting (its simulated cells) sets up the UKF too, so both run the same model.
    let spec = policies.first().and_then(|(pf, _)| pf.task.measured().cloned());
    let input = CalibrateInput {
        cell,
        train,
        judged,
        cutoff_v: cut,
        cutoff_source: cut_source,
        policies: groups,
        ukf,
        adaptive_ukf,
        adaptive_grid: if a.quick { AdaptiveGrid::quick() } else { AdaptiveGrid::default() },
        fit,
        spec,
        ukf_grid: if a.quick { JointUkfGrid::real_cells_quick() } else { JointUkfGrid::real_cells() },
        model,
        starts,
        rests: Some(rests),
        unread,
        noted,
    };
    let mut cal = calibrate(&input, &mut |m| println!("[{:6.1} s] {m}", started.elapsed().as_secs_f64()))?;
    cal.report.seconds = started.elapsed().as_secs_f64();
    let written =
        bcal_realcell::report::write_outputs(&out, &mut cal.report, &cal.judged, &cal.train_capacities, &cal.runs)
            .with_context(|| format!("cannot write into {}", out.display()))?;
    println!(
        "\n{}",
        bcal_realcell::report::render_markdown(&cal.report).lines().take(40).collect::<Vec<_>>().join("\n")
    );
    println!("wrote {} files into {} in {:.0} s", written.len(), out.display(), started.elapsed().as_secs_f64());
    Ok(())
}

/// Share of a cell policy's training episodes that are the cell's own recorded discharges (the rest are
/// simulated cells around its model): half, so the policy meets the cell's real model error as often as the
/// simulated variety around it.
pub const RECORDED_SHARE: f64 = 0.5;

/// The simulated cells' capacity jumps after long rests (issue 18, item 4), read off the cell's training
/// records: as often as their discharges followed a rest of more than a day, up to what the cell's lifetime
/// model says such a rest adds (relative to the records' median capacity). None (probability 0) without
/// long rests, a lifetime model with recovery, or capacities.
fn rest_jump(
    kept: &[&Discharge],
    records: &[bcal_realcell::record::CellRecord],
    starts: &[RecordStart],
    life: Option<&LifetimeModel>,
) -> RestJumpConfig {
    let none = RestJumpConfig::default();
    let rests = bcal_realcell::prior::rests_before(kept, starts);
    let long = rests.values().filter(|r| **r > bcal_realcell::prior::LONG_REST_S).count();
    let Some(life) = life else { return none };
    let mut caps: Vec<f64> = records.iter().filter_map(|r| r.data_capacity_ah).collect();
    let cap_ah = bcal_common::stats::median(&mut caps).unwrap_or(0.0);
    if long == 0 || life.amplitude <= 0.0 || life.quantity != Quantity::CapacityAh || cap_ah <= 0.0 {
        return none;
    }
    RestJumpConfig {
        probability: long as f64 / records.len() as f64,
        q_mobile_frac: [0.0, (life.amplitude / cap_ah).min(0.5)],
    }
}

pub fn run_cell_config(a: CellConfigArgs) -> anyhow::Result<()> {
    let cell = cell_name(&a.cell, &a.data)?;
    let model = load_model(&a.model)?;
    let opts = ReadOptions { current_sign: a.current_sign, ambient_c: a.ambient_c, ..ReadOptions::default() };
    let (range, everything) = train_cycles(a.train_cycles.as_deref(), &a.data, &cell, &opts)?;
    let (ds, starts) = match everything {
        Some((all, starts, _)) => (all.into_iter().filter(|d| range.contains(&d.cycle)).collect(), starts),
        None => {
            let (ds, starts, _) = read_with_starts(&a.data, &cell, Some(&range), &opts)?;
            (ds, starts)
        }
    };
    let (cut, cut_source) = cutoff_or_refuse(a.cutoff_v, &a.data, &cell, &ds)?;
    let mut summary = RecordSummary::default();
    let mut records = Vec::new();
    let mut kept = Vec::new();
    for d in &ds {
        match prepare(d, cut) {
            Ok(r) => {
                records.push(r);
                kept.push(d);
            }
            Err(e) => summary.refused.push(e.to_string()),
        }
    }
    if records.is_empty() {
        bail!("no usable training discharge of {cell} in cycles {range:?}: {}", summary.refused.join("; "));
    }
    let (causes, shared) = bcal_realcell::calibrate::model_parts(model.as_ref());
    let fits = bcal_realcell::calibrate::fits(&kept, &bcal_doctor::fit::FitConfig::default(), &causes, &shared)?;
    let (mut spec, facts) = cell_spec(&records, &fits, cut);
    // The filter the correction policy trains on is the one `bcal calibrate` runs on this cell: chosen on the
    // same validation cycles, each starting from the same prior (the previous end fit moved by the cell's
    // lifetime model, the width learned from its history times the chosen factor), so a zero action is that
    // baseline in training and on the judged cycles. Simulated and recorded training discharges start from a
    // prior at that width after the usual rest.
    let neutral = bcal_realcell::calibrate::extension_of(&causes, &shared, records[0].ambient_k);
    let owned: Vec<Discharge> = kept.iter().map(|d| (*d).clone()).collect();
    let history = CellHistory::read(&spec.tracker, &owned, &starts, &mut records, &fits, &neutral, cut);
    let grid = JointUkfGrid::real_cells().candidates();
    let too_few = || {
        anyhow::anyhow!(
            "too few training cycles of {cell} reach the cut-off to choose its filter: widen --train-cycles"
        )
    };
    eprintln!(
        "choosing the cell's joint UKF among {} settings x {} prior widths on its validation cycles ...",
        grid.len(),
        history.factors().len()
    );
    let validating = bcal_realcell::tune::validation_records(&records).len();
    if validating > 0 && bcal_realcell::tune::validation_is_short(&records) {
        eprintln!(
            "  (few training cycles reach the cut-off: the choice rests on {validating} of them and is weak; more \
             training cycles, --train-cycles, make it sound)"
        );
    }
    let (mut ukf, factor, choice) =
        choose_cell_ukf(&spec.tracker, &records, &history, &grid, cut).ok_or_else(too_few)?;
    eprintln!(
        "joint UKF of {cell}: {ukf:?}, prior width factor {factor:?}; validation EOD error {:.2} %",
        choice.candidates[0].eod_error_pct
    );
    // The policy learns on top of the best filter: that UKF alone or under the covariance-matching rule the
    // same validation cycles prefer (the adaptive UKF `bcal calibrate` runs beside it).
    let rules = AdaptiveGrid::default().candidates();
    eprintln!("choosing the filter's covariance-matching rule among {} and none on the same cycles ...", rules.len());
    let (rule, choice) =
        choose_cell_rule(&spec.tracker, &records, &history, (ukf, factor), &rules, cut).ok_or_else(too_few)?;
    eprintln!("rule under the correction: {rule:?}; validation EOD error {:.2} %", choice.candidates[0].eod_error_pct);
    spec.correction.adaptive = rule;
    if let Some(sd) = history.usual_sd_z(factor) {
        ukf.prior_std_z = sd;
    }
    spec.ukf = Some(ukf);
    spec.scenario.prior_sd_z = Some(ukf.prior_std_z);
    // The lifetime model `bcal calibrate` moves the judged discharges' priors by: a live stream on this
    // config moves what each discharge hands the next by it too.
    spec.lifetime = history.life.as_ref().map(|l| l.used).filter(|m| m.unusable().is_none());
    spec.scenario.rest_jump = rest_jump(&kept, &records, &starts, spec.lifetime.as_ref());
    // `bcal calibrate` chooses among the cell's policies by their end-of-discharge error on its validation
    // cycles, so the policy learns from that term alone (B0006: with it, the policy chosen there beat the
    // tuned UKF's EOD on the judged cycles; docs/calibrator.md).
    spec.cost.voltage_weight = 0.0;
    if spec.scenario.rest_jump.probability > 0.0 {
        let j = &spec.scenario.rest_jump;
        eprintln!(
            "capacity regained over long rests: {:.0} % of the simulated cells start from a prior up to {:.1} % below \
             their qMobile (the training cycles' share of discharges after a rest of more than a day, and what the \
             cell's lifetime model says such a rest adds)",
            100.0 * j.probability,
            100.0 * j.q_mobile_frac[1]
        );
    }
    // The cell's own recorded training discharges join the simulated ones in training (beside the config),
    // each starting from the fit the one before it hands on, as `bcal calibrate` starts it.
    let set = bcal_realcell::recorded::recorded_set(&cell, &records, &history.carrying.fits);
    let recorded_path = a.out.with_extension("recorded.bin");
    bcal_common::fsutil::write_atomic(&recorded_path, &set.to_bytes())
        .with_context(|| format!("cannot write {}", recorded_path.display()))?;
    let file_name = recorded_path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    spec.scenario.recorded =
        bcal_common::measured::scenario::RecordedConfig { path: Some(file_name), share: RECORDED_SHARE };
    let mut c: TrainConfig = Preset::Measured.config();
    c.measured = spec;
    c.learner.time_budget_s = a.budget_s;
    c.validate().with_context(|| "the derived cell setting does not validate")?;
    let header = format!(
        "# bcal cell-config for {cell} from cycles {range:?} of {} (cut-off {cut} V: {cut_source}; model {}).\n# Read off \
         the training cycles: {}\n",
        a.data.display(),
        c.measured.tracker.model.label(),
        serde_json::to_string(&facts)?
    );
    bcal_common::fsutil::write_atomic(&a.out, format!("{header}{}", c.to_toml()).as_bytes())
        .with_context(|| format!("cannot write {}", a.out.display()))?;
    println!(
        "wrote {} and its {} recorded training discharges ({} for validation) in {} (train with: bcal train --config {} \
         --name NAME)",
        a.out.display(),
        set.train.len(),
        set.validation.len(),
        recorded_path.display(),
        a.out.display()
    );
    for r in &summary.refused {
        println!("refused: {r}");
    }
    Ok(())
}
