//! Analysis behind docs/calibrator.md (`cargo run --release -p bcal-calib --example potential`): where a correction of the tuned joint UKF could gain.
#![allow(clippy::type_complexity, clippy::field_reassign_with_default)] // one-off analysis tables
#[path = "shared/mod.rs"]
mod shared;
use bcal_calib::tune::{mean_nrmse_pct, Make};
use bcal_calib::JointUkf;
use bcal_common::dataset::Split;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::scenario::{episode_set, Episode};
use bcal_common::measured::tracker::JointUkfSettings;

fn main() {
    let spec = MeasuredSpec::default();
    let val = episode_set(&spec.scenario, Split::Validation, 48).unwrap();
    let tuned = shared::tuned_ukf();
    for r in ["1s", "10-20s"] {
        let eps: Vec<Episode> = val.iter().filter(|e| shared::regime(e) == r).cloned().collect();
        for m in [0.002, 0.003, 0.005, 0.01] {
            for w in [0.0, 1e-5] {
                let s = JointUkfSettings { meas_std_v: m, param_walk_per_sqrt_s: w, ..tuned };
                let t = &spec.tracker;
                let make: Make = Box::new(move || Box::new(JointUkf::new(s, t)));
                println!("{r} ({} cells): meas {m} walk {w}: mean NRMSE {:.3}", eps.len(), mean_nrmse_pct(&eps, &make));
            }
        }
    }

    shift_potential();
}

/// Best-in-hindsight shift of the filter's estimate, by the predictive cost, at every 10th reading.
#[allow(dead_code)]
pub fn shift_potential() {
    use bcal_calib::cost::{predictive_cost, PredictionModel};
    use bcal_calib::Correction;
    use bcal_common::nrmse::Param;
    use rayon::prelude::*;
    let mut spec = MeasuredSpec::default();
    spec.ukf = Some(shared::tuned_ukf());
    let val = episode_set(&spec.scenario, Split::Validation, 48).unwrap();
    let grid: Vec<f64> = (0..9).map(|k| -2.0 + 0.5 * k as f64).collect();
    let rows: Vec<(String, [f64; 2], [f64; 2], f64, f64)> = val
        .par_iter()
        .flat_map_iter(|e| {
            let mut c = Correction::of_task(&spec);
            let mut out = Vec::new();
            let n = e.samples.len();
            for (k, s) in e.samples.iter().enumerate() {
                c.ingest(s);
                if k % 10 != 0 || k + 1 >= n {
                    continue;
                }
                let x0 = c.state().unwrap();
                let m = PredictionModel::at(&spec.tracker.model, x0[7], e.samples[0].temperature_k, 3.0);
                let mut best = (f64::INFINITY, [0.0, 0.0]);
                let mut zero = 0.0;
                for &a in &grid {
                    for &b in &grid {
                        c.apply_action(&[(a / 2.0) as f32, (b / 2.0) as f32, 0.0, 0.0]);
                        let x = c.state().unwrap();
                        let cost = predictive_cost(&spec.cost, &m, e, k, &x, &c.estimate()).cost;
                        if a == 0.0 && b == 0.0 {
                            zero = cost;
                        }
                        if cost < best.0 {
                            best = (cost, [a, b]);
                        }
                    }
                }
                c.apply_action(&[(best.1[0] / 2.0) as f32, (best.1[1] / 2.0) as f32, 0.0, 0.0]);
                let eb = c.estimate();
                c.apply_action(&[0.0, 0.0, 0.0, 0.0]);
                let e0 = c.estimate();
                let t = e.spec.truth;
                out.push((
                    shared::regime(e).to_string(),
                    [Param::QMobile.err_pct(&e0, &t), Param::ROhm.err_pct(&e0, &t)],
                    [Param::QMobile.err_pct(&eb, &t), Param::ROhm.err_pct(&eb, &t)],
                    zero,
                    best.0,
                ));
            }
            out
        })
        .collect();
    for r in ["1s", "10-20s"] {
        let v: Vec<_> = rows.iter().filter(|x| x.0 == r).collect();
        let n = v.len() as f64;
        let rms = |f: &dyn Fn(&(String, [f64; 2], [f64; 2], f64, f64)) -> f64| {
            (v.iter().map(|x| f(x).powi(2)).sum::<f64>() / n).sqrt()
        };
        println!(
            "{r}: {} points; zero shift NRMSE q {:.2} r {:.2} cost {:.3}; best shift q {:.2} r {:.2} cost {:.3}",
            v.len(),
            rms(&|x| x.1[0]),
            rms(&|x| x.1[1]),
            v.iter().map(|x| x.3).sum::<f64>() / n,
            rms(&|x| x.2[0]),
            rms(&|x| x.2[1]),
            v.iter().map(|x| x.4).sum::<f64>() / n
        );
    }
}
