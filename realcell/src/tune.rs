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

/// The per-discharge [`objective`] of `runs` along `records`, % (infinite where a prediction failed).
pub fn per_cycle(records: &[CellRecord], runs: &[CycleRun]) -> Vec<f64> {
    (0..records.len().min(runs.len())).map(|k| objective(&records[k..=k], &runs[k..=k])).collect()
}

/// Share of the validation cycles on which a learned calibrator must beat the joint UKF chosen there to be
/// delivered ([`first_consistent`]): 8 of 10 (were the two equally good, that would happen 5 times in 100).
pub const MIN_WIN_SHARE: f64 = 0.75;

/// The wins of [`MIN_WIN_SHARE`] of `n` validation cycles.
pub fn wins_needed(n: usize) -> usize {
    (MIN_WIN_SHARE * n as f64).ceil() as usize
}

/// One candidate's validation figures.
#[derive(Clone, Debug, Serialize)]
pub struct Candidate {
    pub label: String,
    /// [`objective`], %.
    pub eod_error_pct: f64,
    /// Its index among the candidates [`choose`] was given.
    #[serde(skip)]
    pub index: usize,
    /// [`per_cycle`] along the validation cycles.
    #[serde(skip)]
    pub per_cycle_pct: Vec<f64>,
}

/// The first of `candidates` (best first) that beats `reference` (the per-cycle objective of the filter it
/// must earn its place against) both in the mean and on at least [`MIN_WIN_SHARE`] of the cycles, as a
/// position in `candidates`; None when none does. A mean over 10 validation cycles can be won on two or
/// three of them, and policies chosen that way lost to the filter on most of the discharges that followed
/// (docs/calibrator.md, "where along the life the policies lose").
pub fn first_consistent(candidates: &[Candidate], reference: &[f64]) -> Option<usize> {
    let n = reference.len();
    if n == 0 {
        return None;
    }
    let need = wins_needed(n);
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    candidates.iter().position(|c| {
        c.per_cycle_pct.len() == n
            && mean(&c.per_cycle_pct) < mean(reference)
            && c.per_cycle_pct.iter().zip(reference).filter(|(a, b)| a < b).count() >= need
    })
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
    let mut scored: Vec<Candidate> = candidates
        .par_iter()
        .enumerate()
        .map(|(k, (label, cal))| {
            let runs = run_sequence(cal, records, before, cutoff_v, &[1.0], true).pop().unwrap_or_default();
            Candidate {
                label: label.clone(),
                eod_error_pct: objective(records, &runs),
                index: k,
                per_cycle_pct: per_cycle(records, &runs),
            }
        })
        .collect();
    scored.sort_by(|a, b| a.eod_error_pct.total_cmp(&b.eod_error_pct));
    Some(chosen_at(scored, 0, candidates, records, before, cutoff_v))
}

/// The choice of `scored[position]` (candidates scored best first, as a [`Choice`] lists them), with its
/// runs along `records`.
pub fn chosen_at(
    scored: Vec<Candidate>,
    position: usize,
    candidates: &[(String, Streaming<'_>)],
    records: &[CellRecord],
    before: &[Before],
    cutoff_v: f64,
) -> Choice {
    let index = scored[position].index;
    let runs = run_sequence(&candidates[index].1, records, before, cutoff_v, &[1.0], false).pop().unwrap_or_default();
    Choice {
        index,
        chosen: candidates[index].0.clone(),
        validation_cycles: records.iter().map(|r| r.cycle).collect(),
        candidates: scored,
        runs,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn candidate(index: usize, per_cycle_pct: Vec<f64>) -> Candidate {
        let eod_error_pct = per_cycle_pct.iter().sum::<f64>() / per_cycle_pct.len() as f64;
        Candidate { label: format!("c{index}"), eod_error_pct, index, per_cycle_pct }
    }

    /// A candidate that wins the mean on two cycles and loses the other eight is passed over for one that
    /// wins on eight; with neither, none is delivered; a tie is not a win.
    #[test]
    fn a_policy_must_beat_the_filter_on_most_validation_cycles() {
        let filter = vec![0.5; 10];
        let lucky = candidate(3, [vec![0.0, 0.0], vec![0.55; 8]].concat()); // mean 0.44, 2 wins
        let steady = candidate(7, [vec![0.45; 8], vec![0.6; 2]].concat()); // mean 0.48, 8 wins
        let seven = candidate(1, [vec![0.4; 7], vec![0.55; 3]].concat()); // mean 0.445, 7 wins
        assert_eq!(first_consistent(&[lucky.clone(), steady.clone()], &filter), Some(1));
        assert_eq!(first_consistent(&[lucky.clone(), seven.clone()], &filter), None);
        assert_eq!(first_consistent(&[steady.clone(), lucky], &filter), Some(0));
        // Eight wins but a worse mean: not delivered.
        let worse = candidate(2, [vec![0.49; 8], vec![2.0; 2]].concat());
        assert_eq!(first_consistent(&[worse], &filter), None);
        assert_eq!(first_consistent(&[candidate(0, filter.clone())], &filter), None);
        assert_eq!(first_consistent(&[steady], &[]), None);
    }
}
