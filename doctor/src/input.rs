//! What a user points the doctor at, resolved once for every face of bcal (`bcal diagnose`, `bcal
//! calibrate`, `bcal cell-config` and the Python package's `bcal.diagnose`): the cell's name, the
//! discharges of a NASA folder or any CSV the readers take, the split into training and held-out cycles,
//! and the cut-off voltage. Each refusal names the path and the option to give; nothing here prints.

use crate::lifetime::{assess, LifetimeConfig};
use crate::read::{nasa_cutoff_v, read_csv, read_nasa_with, ReadOptions, ReadReport, RecordStart};
use crate::record::infer_cutoff_v;
use crate::{DiagnoseConfig, Diagnosis, Discharge, DoctorError};
use std::ops::RangeInclusive;
use std::path::Path;

/// The cell's name: given, else (a CSV) the file's name; a NASA folder needs one.
pub fn cell_name(given: Option<&str>, data: &Path) -> Result<String, DoctorError> {
    match given {
        Some(c) => Ok(c.to_string()),
        None if data.is_dir() => Err(DoctorError::NothingSelected {
            why: format!(
                "{} is a NASA folder: pass --cell with one of its battery_id values (e.g. --cell B0005)",
                data.display()
            ),
        }),
        None => Ok(data.file_stem().map_or_else(|| "cell".into(), |s| s.to_string_lossy().into_owned())),
    }
}

/// The discharges of `cycles` (all when None): a NASA folder, else any CSV the doctor reads (the generic
/// layout, the Battery Data Format; units and current sign as `opts` say), with what the reader decided
/// or skipped.
pub fn read_any(
    data: &Path,
    cell: &str,
    cycles: Option<&RangeInclusive<u32>>,
    opts: &ReadOptions,
) -> Result<(Vec<Discharge>, ReadReport), DoctorError> {
    if data.is_dir() {
        read_nasa_with(data, cell, cycles, opts)
    } else {
        let (all, rep) = read_csv(data, opts)?;
        Ok((all.into_iter().filter(|d| cycles.is_none_or(|c| c.contains(&d.cycle))).collect(), rep))
    }
}

/// Most training cycles a cell gets by default: B0005, B0006 and B0018 train on their first 40 of 132-168.
pub const DEFAULT_TRAIN_MAX: usize = 40;

/// Fewest training cycles a cell gets by default while it leaves one to judge: `bcal calibrate` chooses its
/// filters soundly on 4 training discharges that reach the cut-off (on fewer, weakly, and says so).
pub const DEFAULT_TRAIN_MIN: usize = 4;

/// The training cycles `bcal calibrate` and `bcal cell-config` take when none are given: the cell's first
/// third of discharges, at most [`DEFAULT_TRAIN_MAX`], so a short life (NASA's cells of 25-47 discharges)
/// still leaves two thirds to judge, and at least [`DEFAULT_TRAIN_MIN`] while one is left to judge (a
/// life of 8: 1..4). Refused, saying so, for a cell with fewer than 2 discharges.
pub fn default_train_cycles(cell: &str, all: &[Discharge]) -> Result<RangeInclusive<u32>, DoctorError> {
    let cycles = distinct_cycles(all);
    let k = default_train_len(cycles.len());
    if cycles.is_empty() {
        return Err(DoctorError::NothingSelected {
            why: format!("{cell} has no readable discharge (the reader's lines above say what was missing or refused)"),
        });
    }
    if k == 0 {
        return Err(DoctorError::NothingSelected {
            why: format!(
                "{cell} has {} readable discharge(s): too few to set up on some and judge the others; give \
                 --train-cycles and --cycles",
                cycles.len()
            ),
        });
    }
    Ok(cycles[0]..=cycles[k - 1])
}

/// How many of a life's `n` discharges [`default_train_cycles`] trains on.
fn default_train_len(n: usize) -> usize {
    (n / 3).max(DEFAULT_TRAIN_MIN.min(n.saturating_sub(1))).min(DEFAULT_TRAIN_MAX)
}

/// The cycle numbers of `all`, sorted, each once.
fn distinct_cycles(all: &[Discharge]) -> Vec<u32> {
    let mut cycles: Vec<u32> = all.iter().map(|d| d.cycle).collect();
    cycles.sort_unstable();
    cycles.dedup();
    cycles
}

/// Fewest training cycles whose default 3:1 split ([`cycle_ranges`]) leaves a held-out part of two or more
/// (`launch/run.sh --cell` asks as many); a shorter life is split the same way, its held-out part shorter.
pub const MIN_DEFAULT_SPLIT: usize = 8;

/// The training and held-out cycle ranges: as given, or what the other leaves (the held-out cycles start
/// after the training ones). By default the cycles `bcal calibrate` trains on ([`default_train_cycles`]):
/// their first three quarters fitted, the last quarter held out (B0005: 1..30 against 31..40), so the
/// diagnosis feeds `bcal calibrate --model` (which refuses a model whose choice saw the cycles it judges).
/// A life of fewer than [`MIN_DEFAULT_SPLIT`] training cycles is split the same way, within them, though its
/// held-out part is then short (a split past them made a diagnosis `bcal calibrate` refused: a 23-discharge
/// life trains on 1..7 and was diagnosed on 1..8); one of two discharges splits its first third against the
/// rest.
pub fn cycle_ranges(
    all: &[Discharge],
    cycles: Option<RangeInclusive<u32>>,
    holdout: Option<RangeInclusive<u32>>,
) -> (RangeInclusive<u32>, RangeInclusive<u32>) {
    let last = all.iter().map(|d| d.cycle).max().unwrap_or(1);
    let first = all.iter().map(|d| d.cycle).min().unwrap_or(1);
    match (cycles, holdout) {
        (Some(c), Some(h)) => (c, h),
        (Some(c), None) => (c.clone(), c.end() + 1..=last),
        (None, Some(h)) => (first..=h.start().saturating_sub(1).max(first), h),
        (None, None) => {
            let cycles = distinct_cycles(all);
            let k = default_train_len(cycles.len());
            if k >= 2 {
                let fit = (k * 3 / 4).max(1);
                (cycles[0]..=cycles[fit - 1], cycles[fit]..=cycles[k - 1])
            } else {
                let split = first + (last - first) / 3;
                (first..=split, split + 1..=last)
            }
        }
    }
}

/// Splits `all` into training and held-out records: the ranges given, else the training cycles and
/// everything after them, else everything before the held-out ones, else [`cycle_ranges`]' default; every
/// `stride`-th cycle of each range.
pub fn split_cycles(
    all: &[Discharge],
    cycles: Option<RangeInclusive<u32>>,
    holdout: Option<RangeInclusive<u32>>,
    stride: u32,
) -> Result<(Vec<Discharge>, Vec<Discharge>), DoctorError> {
    if all.is_empty() {
        return Err(DoctorError::NothingSelected { why: "the data holds no discharge record".into() });
    }
    let (train_r, held_r) = cycle_ranges(all, cycles, holdout);
    // A record held out that was also fitted would judge the fit on what it saw.
    if train_r.start() <= held_r.end() && held_r.start() <= train_r.end() {
        return Err(DoctorError::NothingSelected {
            why: format!(
                "the training cycles {}..{} and the held-out cycles {}..{} overlap: hold out cycles the fit does not \
                 see (e.g. --cycles {}..{} --holdout {}..{})",
                train_r.start(),
                train_r.end(),
                held_r.start(),
                held_r.end(),
                train_r.start(),
                train_r.end(),
                train_r.end().saturating_add(1),
                held_r.end().max(&train_r.end().saturating_add(1))
            ),
        });
    }
    let pick = |r: &RangeInclusive<u32>| -> Vec<Discharge> {
        let wanted: Vec<u32> = r.clone().step_by(stride.max(1) as usize).collect();
        all.iter().filter(|d| wanted.contains(&d.cycle)).cloned().collect()
    };
    let (train, held) = (pick(&train_r), pick(&held_r));
    if train.is_empty() {
        return Err(DoctorError::NothingSelected { why: format!("no training record in cycles {train_r:?}") });
    }
    if held.is_empty() {
        return Err(DoctorError::NothingSelected { why: format!("no held-out record in cycles {held_r:?}") });
    }
    Ok((train, held))
}

/// Longest simulator step of a diagnosis, s (the simulator also lands on every sample time): 2 s gives the
/// same verdicts and held-out RMSEs as 1 s within 0.05 mV on the NASA cells, at half the cost.
pub const DIAGNOSE_DT_MAX_S: f64 = 2.0;

/// The diagnosis every face runs (`bcal diagnose`, `bcal.diagnose`): the voltage diagnosis on `train`
/// against `held`, then, when `lifetime`, the lifetime diagnosis on every record of the two ranges (capacity
/// needs no fit, so the stride does not thin it). A lifetime that cannot be judged is returned as the
/// reason, never an error: the voltage diagnosis stands on its own.
#[allow(clippy::too_many_arguments)]
pub fn diagnose_with_lifetime(
    cfg: &DiagnoseConfig,
    all: &[Discharge],
    starts: &[RecordStart],
    ranges: (&RangeInclusive<u32>, &RangeInclusive<u32>),
    train: &[Discharge],
    held: &[Discharge],
    lifetime: bool,
) -> Result<(Diagnosis, Option<String>), DoctorError> {
    let mut diag = crate::diagnose(cfg, train, held)?;
    let mut skipped = None;
    if lifetime {
        match assess(&LifetimeConfig::from_diagnose(cfg), all, starts, ranges.0, ranges.1, Some(&diag)) {
            Ok(l) => diag.lifetime = Some(l),
            Err(e) => skipped = Some(e.to_string()),
        }
    }
    Ok((diag, skipped))
}

/// The cut-off and where it came from: given, else the documented protocol of a NASA cell, else what the
/// records show (where the discharges that end under load, above `load_threshold_a`, end), else None.
pub fn cutoff(
    given: Option<f64>,
    data: &Path,
    cell: &str,
    records: &[Discharge],
    load_threshold_a: f64,
) -> Option<(f64, String)> {
    if let Some(v) = given {
        return Some((v, "--cutoff-v".into()));
    }
    if data.is_dir() {
        if let Some(v) = nasa_cutoff_v(data, cell) {
            return Some((v, "the cell's documented protocol (extra_infos)".into()));
        }
    }
    infer_cutoff_v(records, load_threshold_a)
        .map(|v| (v, format!("read off the data: the discharges that end under load end at or below {v:.3} V")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(cycle: u32) -> Discharge {
        Discharge {
            cell: "c".into(),
            cycle,
            source: "c.csv".into(),
            ambient_k: 297.15,
            time_s: vec![0.0, 1.0],
            voltage_v: vec![4.1, 4.0],
            current_a: vec![0.0, 2.0],
            temperature_k: None,
            stated_capacity_ah: None,
        }
    }

    #[test]
    fn split_defaults_within_calibrates_training_cycles_and_honours_ranges() {
        let all: Vec<Discharge> = (1..=9).map(record).collect();
        let (t, h) = split_cycles(&all, None, None, 1).unwrap();
        assert_eq!(t.iter().map(|d| d.cycle).collect::<Vec<_>>(), vec![1, 2, 3]);
        assert_eq!(h.iter().map(|d| d.cycle).collect::<Vec<_>>(), vec![4], "within calibrate's 1..4");
        // A longer life: calibrate's training cycles, fitted on three quarters and judged on the last.
        let life = |n: u32| cycle_ranges(&(1..=n).map(record).collect::<Vec<_>>(), None, None);
        assert_eq!(life(168), (1..=30, 31..=40));
        assert_eq!(life(40), (1..=9, 10..=13));
        // A short one too, within calibrate's training cycles (1..7 of 23), so calibrate takes the model.
        assert_eq!(life(23), (1..=5, 6..=7));
        assert_eq!(life(2), (1..=1, 2..=2));
        let (t, h) = split_cycles(&all, Some(2..=4), None, 2).unwrap();
        assert_eq!((t.iter().map(|d| d.cycle).collect::<Vec<_>>(), h[0].cycle), (vec![2, 4], 5));
        // Held-out cycles the fit also sees: refused, naming both ranges.
        let e = split_cycles(&all, Some(1..=3), Some(3..=5), 1).unwrap_err().to_string();
        assert!(e.contains("1..3") && e.contains("3..5") && e.contains("overlap"), "{e}");
        let e = split_cycles(&all, Some(20..=30), None, 1).unwrap_err();
        assert!(e.to_string().contains("no training record in cycles 20..=30"), "{e}");
    }

    #[test]
    fn the_default_training_cycles_are_a_third_at_most_forty() {
        let cycles = |n: u32| default_train_cycles("c", &(1..=n).map(record).collect::<Vec<_>>());
        // NASA's lives: B0005 (168), B0018 (132), the 28-discharge B0025 and the 40-discharge B0029.
        assert_eq!(cycles(168).unwrap(), 1..=40);
        assert_eq!(cycles(132).unwrap(), 1..=40);
        assert_eq!(cycles(28).unwrap(), 1..=9);
        assert_eq!(cycles(40).unwrap(), 1..=13);
        // Gaps in the numbering count records, not numbers.
        let gappy: Vec<Discharge> = [3, 7, 8, 20, 21, 40].into_iter().map(record).collect();
        assert_eq!(default_train_cycles("c", &gappy).unwrap(), 3..=20);
        // A short life still sets its filters up on 4 discharges, while one is left to judge.
        assert_eq!(cycles(8).unwrap(), 1..=4);
        assert_eq!(cycles(4).unwrap(), 1..=3);
        assert_eq!(cycles(2).unwrap(), 1..=1);
        let e = cycles(1).unwrap_err().to_string();
        assert!(e.contains("1 readable discharge(s)") && e.contains("--train-cycles"), "{e}");
        let e = cycles(0).unwrap_err().to_string();
        assert!(e.contains("no readable discharge"), "{e}");
    }

    #[test]
    fn a_nasa_folder_needs_a_cell() {
        let dir = tempfile::tempdir().unwrap();
        let e = cell_name(None, dir.path()).unwrap_err();
        assert!(e.to_string().contains("pass --cell"), "{e}");
        assert_eq!(cell_name(None, Path::new("/x/my-cell.csv")).unwrap(), "my-cell");
    }
}
