//! The predictive cost's horizon and end-of-discharge weight, chosen on validation cells
//! (`cargo run --release -p bcal-calib --example cost_choice`; docs/calibrator.md).
//!
//! A cost teaches what its optimum is. For each (horizon, EOD weight) this finds, at readings of the
//! default setting's validation cells, the shift of the tuned joint UKF's estimate that the cost rates best
//! in hindsight (a 9 x 9 grid of shifts from -2 to 2, the correction's action times 2), and scores that optimum as every method is scored
//! on validation: NRMSE of qMobile and Ro against the cells' truths, per sampling regime. The cost itself
//! never reads a true parameter; only this choice does, on validation cells, as the filter's own tuning does.
//! The setting whose optimum lies nearest the truth is the one a policy trained on it can at best approach.
#![allow(clippy::type_complexity, clippy::field_reassign_with_default)] // one-off analysis table
#[path = "shared/mod.rs"]
mod shared;
use bcal_calib::cost::{predictive_cost, PredictionModel};
use bcal_calib::Correction;
use bcal_common::dataset::Split;
use bcal_common::measured::env::{MeasuredSpec, PredictiveCost};
use bcal_common::measured::scenario::{episode_set, Episode};
use bcal_common::nrmse::Param;
use rayon::prelude::*;

/// Validation cells used, and every how many readings a hindsight optimum is taken.
const CELLS: usize = 48;
const EVERY: usize = 10;

/// Per regime: (points, RMS % error of qMobile and Ro at the filter, the same at the cost's optimum).
fn optimum(spec: &MeasuredSpec, cost: &PredictiveCost, cells: &[Episode]) -> Vec<(&'static str, usize, [f64; 4])> {
    let grid: Vec<f64> = (0..9).map(|k| -2.0 + 0.5 * k as f64).collect();
    let rows: Vec<(&'static str, [f64; 4])> = cells
        .par_iter()
        .flat_map_iter(|e| {
            let mut c = Correction::of_task(spec);
            let mut out = Vec::new();
            let n = e.samples.len();
            for (k, s) in e.samples.iter().enumerate() {
                c.ingest(s);
                if k % EVERY != 0 || k + 1 >= n {
                    continue;
                }
                let Some(x0) = c.state() else { continue };
                let m = PredictionModel::at(&spec.tracker.model, x0[7], e.samples[0].temperature_k, 3.0);
                let mut best = (f64::INFINITY, [0.0, 0.0]);
                for &a in &grid {
                    for &b in &grid {
                        c.apply_action(&[(a / 2.0) as f32, (b / 2.0) as f32, 0.0, 0.0]);
                        let Some(x) = c.state() else { continue };
                        let v = predictive_cost(cost, &m, e, k, &x, &c.estimate()).cost;
                        // Ties go to the smaller shift (the filter itself first).
                        if v < best.0 - 1e-12 || (v <= best.0 + 1e-12 && a.abs() + b.abs() < best.1[0] + best.1[1]) {
                            best = (v, [a, b]);
                        }
                    }
                }
                c.apply_action(&[(best.1[0] / 2.0) as f32, (best.1[1] / 2.0) as f32, 0.0, 0.0]);
                let at_best = c.estimate();
                c.apply_action(&[0.0; 4]);
                let at_filter = c.estimate();
                let t = e.spec.truth;
                out.push((
                    shared::regime(e),
                    [
                        Param::QMobile.err_pct(&at_filter, &t),
                        Param::ROhm.err_pct(&at_filter, &t),
                        Param::QMobile.err_pct(&at_best, &t),
                        Param::ROhm.err_pct(&at_best, &t),
                    ],
                ));
            }
            out
        })
        .collect();
    ["1s", "10-20s"]
        .into_iter()
        .map(|r| {
            let v: Vec<&[f64; 4]> = rows.iter().filter(|x| x.0 == r).map(|x| &x.1).collect();
            let n = v.len().max(1) as f64;
            let rms = |j: usize| (v.iter().map(|x| x[j].powi(2)).sum::<f64>() / n).sqrt();
            (r, v.len(), [rms(0), rms(1), rms(2), rms(3)])
        })
        .collect()
}

fn main() {
    let mut spec = MeasuredSpec::default();
    // The filter docs/calibrator.md's other analyses correct (the evaluator's tuned one at 3 mV).
    spec.ukf = Some(shared::tuned_ukf());
    let val = episode_set(&spec.scenario, Split::Validation, CELLS).expect("the default setting simulates");
    println!("| horizon s | EOD weight | regime | points | filter q / Ro % | cost's optimum q / Ro % | mean |");
    println!("| ---: | ---: | --- | ---: | --- | --- | ---: |");
    let mut table: Vec<(f64, f64, f64)> = Vec::new();
    for horizon_s in [120.0, 300.0, 600.0, 1200.0, 1800.0] {
        for eod_weight in [0.0, 0.5, 1.0, 2.0, 4.0] {
            let cost = PredictiveCost { horizon_s, eod_weight, ..spec.cost.clone() };
            let rows = optimum(&spec, &cost, &val);
            let mut mean = 0.0;
            for (r, n, e) in &rows {
                let m = (e[2] + e[3]) / 2.0;
                mean += m / rows.len() as f64;
                println!(
                    "| {horizon_s} | {eod_weight} | {r} | {n} | {:.2} / {:.2} | {:.2} / {:.2} | {m:.2} |",
                    e[0], e[1], e[2], e[3]
                );
            }
            table.push((horizon_s, eod_weight, mean));
        }
    }
    table.sort_by(|a, b| a.2.total_cmp(&b.2));
    println!("\nbest on validation (mean over regimes of the optimum's mean NRMSE):");
    for (h, w, m) in &table {
        println!("  horizon {h} s, EOD weight {w}: {m:.2} %");
    }
}
