//! Every choice of a real-cell calibration is made on validation cycles: the last training cycles, measured
//! discharges of the same cell that are never judged. The streaming calibrators get the same effort: the
//! joint UKF's settings (its noise, and the factor on the prior width each discharge learns from the cell's
//! history, [`PRIOR_FACTORS`]) and the RL policy file (among the run's checkpoints) are chosen by their
//! end-of-discharge error there. Their 90 % intervals start from the validation cycles' errors and follow
//! the cell as it ages ([`crate::interval`]).

use crate::record::CellRecord;
use crate::run::{run_sequence, Before, CycleRun, Streaming};
use crate::score::{score, EOD_FRACTIONS_PCT};
use rayon::prelude::*;
use serde::Serialize;

/// Share of the training cycles (the last ones) held out for validation, and the least count.
pub const VALIDATION_SHARE: f64 = 0.25;
pub const MIN_VALIDATION: usize = 2;

/// Factors on the prior width learned from the cell's history ([`crate::prior`]) that the streaming
/// calibrators are tried with: 1 is the width as learned; more lets the readings move the estimate further,
/// less holds it nearer the prior (B0006 and B0018 chose the grid's lowest, 1, before 0.25 and 0.5 joined).
pub const PRIOR_FACTORS: [f64; 5] = [0.25, 0.5, 1.0, 2.0, 4.0];

/// The validation cycles, as indices into `train`: the last quarter of the training cycles that reach the
/// cut-off (at least [`MIN_VALIDATION`]; none when there are fewer than twice that).
pub fn validation_records(train: &[CellRecord]) -> Vec<usize> {
    let complete: Vec<usize> = (0..train.len()).filter(|&k| train[k].eod_s.is_some()).collect();
    if complete.len() < 2 * MIN_VALIDATION {
        return Vec::new();
    }
    let n = ((complete.len() as f64 * VALIDATION_SHARE).ceil() as usize).max(MIN_VALIDATION);
    complete[complete.len() - n..].to_vec()
}

/// The objective every choice minimises: the mean absolute end-of-discharge error, % of the discharge,
/// averaged over the fractions seen (10 / 50 / 90 %). Infinite when a prediction failed.
pub fn objective(records: &[CellRecord], runs: &[CycleRun]) -> f64 {
    let s = score(records, runs);
    if s.failures > 0 {
        return f64::INFINITY;
    }
    let v: Vec<f64> =
        EOD_FRACTIONS_PCT.iter().filter_map(|f| s.eod_error_pct.get(&f.to_string())).map(|q| q.mean).collect();
    if v.is_empty() {
        return f64::INFINITY;
    }
    v.iter().sum::<f64>() / v.len() as f64
}

/// One candidate's validation figures.
#[derive(Clone, Debug, Serialize)]
pub struct Candidate {
    pub label: String,
    /// [`objective`], %.
    pub eod_error_pct: f64,
}

/// What the validation cycles chose for one calibrator.
#[derive(Clone, Debug, Serialize)]
pub struct Choice {
    /// Index of the chosen candidate.
    #[serde(skip)]
    pub index: usize,
    pub chosen: String,
    pub validation_cycles: Vec<u32>,
    /// Every candidate, best first.
    pub candidates: Vec<Candidate>,
    /// The chosen candidate's runs along the validation cycles (their errors start its intervals).
    #[serde(skip)]
    pub runs: Vec<CycleRun>,
}

/// Chooses among `candidates` (label, calibrator) by [`objective`] on `records` (each run along them in
/// order, each discharge starting from what was known before it), and keeps the chosen one's runs with a
/// prediction at every reading.
pub fn choose(
    candidates: &[(String, Streaming<'_>)],
    records: &[CellRecord],
    before: &[Before],
    cutoff_v: f64,
) -> Option<Choice> {
    if candidates.is_empty() || records.is_empty() {
        return None;
    }
    let mut scored: Vec<(usize, f64)> = candidates
        .par_iter()
        .enumerate()
        .map(|(k, (_, cal))| {
            let runs = run_sequence(cal, records, before, cutoff_v, &[1.0], true).pop().unwrap_or_default();
            (k, objective(records, &runs))
        })
        .collect();
    scored.sort_by(|a, b| a.1.total_cmp(&b.1));
    let index = scored[0].0;
    let runs = run_sequence(&candidates[index].1, records, before, cutoff_v, &[1.0], false).pop().unwrap_or_default();
    Some(Choice {
        index,
        chosen: candidates[index].0.clone(),
        validation_cycles: records.iter().map(|r| r.cycle).collect(),
        candidates: scored
            .iter()
            .map(|(k, e)| Candidate { label: candidates[*k].0.clone(), eod_error_pct: *e })
            .collect(),
        runs,
    })
}
