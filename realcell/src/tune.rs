//! Every choice of a real-cell calibration is made on validation cycles: the last training cycles, measured
//! discharges of the same cell that are never judged. The streaming calibrators get the same effort: the
//! joint UKF's settings and the RL policy file (among the run's checkpoints) are chosen by their end-of-
//! discharge error there, and both calibrators' 90 % intervals are scaled there to cover 90 % of the
//! measured ends (the parameter intervals of a calibrator account for sensor noise, not for the model's
//! own error on a real cell, which dominates).

use crate::record::CellRecord;
use crate::run::{run_sequence, Before, CycleRun, Streaming};
use crate::score::{score, EOD_FRACTIONS_PCT};
use rayon::prelude::*;
use serde::Serialize;

/// Share of the training cycles (the last ones) held out for validation, and the least count.
pub const VALIDATION_SHARE: f64 = 0.25;
pub const MIN_VALIDATION: usize = 2;

/// Interval scales searched: 2^(k/2), 1/16 to 128.
pub fn scale_grid() -> Vec<f64> {
    (-8..=14).map(|k| 2f64.powf(f64::from(k) / 2.0)).collect()
}

/// The RL tracker's prior widths tried beside the one it was trained with (fractions of each range): on a
/// real cell the prior is the previous discharge's estimate, as for the joint UKF's grid.
pub const RL_PRIOR_STD_Z: [f64; 4] = [0.01, 0.02, 0.05, 0.1];

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
    /// The interval scale and the coverage of the measured ends it gave on validation, %.
    pub interval_scale: f64,
    pub validation_eod_coverage_pct: Option<f64>,
}

/// Chooses among `candidates` (label, calibrator) by [`objective`] on `records` (each run along them in
/// order, each discharge starting from what was known before it), then the interval scale
/// whose end-of-discharge coverage on them is nearest 90 % (the smaller scale on a tie).
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
    let scales = scale_grid();
    let runs = run_sequence(&candidates[index].1, records, before, cutoff_v, &scales, true);
    let mut best: Option<(f64, Option<f64>)> = None;
    for (scale, runs) in scales.iter().zip(&runs) {
        let cov = score(records, runs).coverage_90_pct.get("eod").copied().flatten();
        let better = match (best, cov) {
            (None, _) => true,
            (Some((_, Some(b))), Some(c)) => (c - 90.0).abs() < (b - 90.0).abs() - 1e-9,
            (Some((_, None)), Some(_)) => true,
            _ => false,
        };
        if better {
            best = Some((*scale, cov));
        }
    }
    let (interval_scale, validation_eod_coverage_pct) = best.unwrap_or((1.0, None));
    Some(Choice {
        index,
        chosen: candidates[index].0.clone(),
        validation_cycles: records.iter().map(|r| r.cycle).collect(),
        candidates: scored
            .iter()
            .map(|(k, e)| Candidate { label: candidates[*k].0.clone(), eod_error_pct: *e })
            .collect(),
        interval_scale,
        validation_eod_coverage_pct,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scale_grid_spans_a_sixteenth_to_128_and_contains_one() {
        let g = scale_grid();
        assert!((g[0] - 0.0625).abs() < 1e-12 && (g[g.len() - 1] - 128.0).abs() < 1e-9);
        assert!(g.iter().any(|s| (s - 1.0).abs() < 1e-12));
    }
}
