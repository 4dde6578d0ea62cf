//! Analysis behind docs/calibrator.md (`cargo run --release -p bcal-calib --example distil [TRAIN] [VAL]`):
//! is the gain of the full-information posterior over the joint UKF (`bound`) a function of what the
//! correction policy observes? At points of the second half of each discharge, the posterior mean (the cells'
//! own uniform prior, the filter's 5 mV) is set on TRAIN training cells (192) and the correction's 24 features
//! read there; least squares with the features, their squares and products (ridge) maps the features to the
//! posterior's shift of the filter's estimate (a target computed from readings alone, no true parameter) and,
//! for comparison, to the true one's (an oracle: what a supervised mapping from true parameters could reach).
//! Both are judged on VAL validation cells (96) by the error of the shifted estimate.
//!
//! Second part (2026-11-28): does a learner do better with inputs that do not move with the load level (test
//! loads lie above training's, so a map through the current, voltage or charge drawn extrapolates), or with
//! what a bank of differently tuned joint UKFs estimates beside the tuned one (each member alone is scored
//! too: the non-learned estimators such a learner builds on)? Linear maps, and with squares and products.
#![allow(clippy::type_complexity)] // one-off analysis tables
#[path = "shared/mod.rs"]
mod shared;
use bcal_calib::{Correction, JointUkf, JointUkfSettings};
use bcal_common::dataset::Split;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::scenario::{draw_spec, episode_set, simulate, Episode};
use bcal_common::nrmse::Param;
use nalgebra::{DMatrix, DVector, Vector3};
use rand::SeedableRng;
use rayon::prelude::*;
use shared::posterior::Posterior;

/// One point: regime, features, the filter's z, the posterior mean's z, the truth's z, the bank's z.
type Point = (&'static str, Vec<f64>, [f64; 2], [f64; 2], [f64; 2], Vec<[f64; 2]>);

/// The bank beside the tuned filter: a prior twice as wide (nearer the cells' flat one), and the sensor's
/// own 3 mV and twice the tuned 5 mV as measurement noise.
fn bank(tuned: JointUkfSettings) -> Vec<(&'static str, JointUkfSettings)> {
    vec![
        ("prior x2", JointUkfSettings { prior_std_z: tuned.prior_std_z.map(|v| 2.0 * v), ..tuned }),
        ("3 mV", JointUkfSettings { meas_std_v: 0.003, ..tuned }),
        ("10 mV", JointUkfSettings { meas_std_v: 0.01, ..tuned }),
    ]
}

/// Indices of the correction's features that do not scale with the load level: the filter's statistics and
/// innovations, the times, the sampling interval, whether the load is on.
const LOAD_FREE: [usize; 15] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 12, 15, 16, 19, 23];

fn points(spec: &MeasuredSpec, eps: &[Episode]) -> Vec<Point> {
    let tracker = &spec.tracker;
    let model = tracker.model.model().expect("the default model");
    let ukf = spec.ukf_settings();
    let cells = shared::posterior::cell_ranges_z(spec);
    eps.par_iter()
        .flat_map_iter(|e| {
            let at = shared::posterior::points(e);
            let mut c = Correction::of_task(spec);
            let mut members: Vec<JointUkf> = bank(ukf).into_iter().map(|(_, b)| JointUkf::new(b, tracker)).collect();
            let mut obs = vec![0f32; spec.obs_dim()];
            let mut out = Vec::new();
            for (k, s) in e.samples.iter().enumerate() {
                c.ingest(s);
                members.iter_mut().for_each(|m| m.step(s));
                if !at.contains(&k) {
                    continue;
                }
                c.observe(&mut obs);
                let z = tracker.to_z(&c.ukf().estimate());
                let post = Posterior::new(&model, tracker, &ukf, ukf.meas_std_v, e, k, Some(cells));
                let (mode, _) = post.map(Vector3::new(post.mean[0], z[0], z[1]));
                let (mean, _) = post.mean(mode);
                let features = obs.iter().map(|v| f64::from(*v)).collect();
                let bz = members.iter().map(|m| tracker.to_z(&m.estimate())).collect();
                out.push((shared::regime(e), features, z, [mean[1], mean[2]], tracker.to_z(&e.spec.truth), bz));
            }
            out
        })
        .collect()
}

/// The inputs a learner gets.
#[derive(Clone, Copy)]
struct Inputs {
    /// Only the features of [`LOAD_FREE`].
    load_free: bool,
    /// The bank's estimates less the tuned filter's, as more features.
    bank: bool,
    /// Squares and pairwise products too.
    quadratic: bool,
}

impl Inputs {
    fn name(&self) -> String {
        format!(
            "{}{}{}",
            if self.load_free { "load-free 15" } else { "all 24" },
            if self.bank { " + bank" } else { "" },
            if self.quadratic { ", quadratic" } else { ", linear" }
        )
    }

    /// The inputs of `p`, their squares and pairwise products where asked, and a constant.
    fn expand(&self, p: &Point) -> Vec<f64> {
        let mut f: Vec<f64> = if self.load_free { LOAD_FREE.iter().map(|&i| p.1[i]).collect() } else { p.1.clone() };
        if self.bank {
            for b in &p.5 {
                f.extend([b[0] - p.2[0], b[1] - p.2[1]]);
            }
        }
        let mut out = f.clone();
        if self.quadratic {
            for i in 0..f.len() {
                for j in i..f.len() {
                    out.push(f[i] * f[j]);
                }
            }
        }
        out.push(1.0);
        out
    }
}

/// Ridge weights from the expanded inputs of `pts` to `target(point)` (one per parameter), standardised.
fn fit(
    pts: &[Point],
    inputs: Inputs,
    target: impl Fn(&Point) -> [f64; 2],
    ridge: f64,
) -> (Vec<DVector<f64>>, Vec<(f64, f64)>) {
    let rows: Vec<Vec<f64>> = pts.iter().map(|p| inputs.expand(p)).collect();
    let d = rows[0].len();
    // Standardise each column (the constant stays 1).
    let scale: Vec<(f64, f64)> = (0..d)
        .map(|j| {
            if j + 1 == d {
                return (0.0, 1.0);
            }
            let m = rows.iter().map(|r| r[j]).sum::<f64>() / rows.len() as f64;
            let v = rows.iter().map(|r| (r[j] - m).powi(2)).sum::<f64>() / rows.len() as f64;
            (m, v.sqrt().max(1e-9))
        })
        .collect();
    let x = DMatrix::from_fn(rows.len(), d, |i, j| (rows[i][j] - scale[j].0) / scale[j].1);
    let xtx = x.transpose() * &x + DMatrix::identity(d, d) * ridge;
    let chol = xtx.cholesky().expect("ridge makes it positive definite");
    let w =
        (0..2).map(|k| chol.solve(&(x.transpose() * DVector::from_fn(pts.len(), |i, _| target(&pts[i])[k])))).collect();
    (w, scale)
}

fn predict(w: &[DVector<f64>], scale: &[(f64, f64)], inputs: Inputs, p: &Point) -> [f64; 2] {
    let e = inputs.expand(p);
    let x: Vec<f64> = e.iter().zip(scale).map(|(v, (m, s))| (v - m) / s).collect();
    [0, 1].map(|k| w[k].iter().zip(&x).map(|(a, b)| a * b).sum())
}

fn main() {
    let arg = |k: usize| std::env::args().nth(k);
    let n_train: usize = arg(1).map_or(192, |a| a.parse().expect("TRAIN, a count of training cells"));
    let n_val: usize = arg(2).map_or(96, |a| a.parse().expect("VAL, a count of validation cells"));
    let spec = MeasuredSpec { ukf: Some(shared::tuned_ukf()), ..Default::default() };
    let mut rng = rand::rngs::SmallRng::seed_from_u64(18);
    let train: Vec<Episode> = (0..n_train)
        .filter_map(|_| simulate(&spec.scenario, &draw_spec(&spec.scenario, Split::Train, &mut rng)).ok())
        .collect();
    let val = episode_set(&spec.scenario, Split::Validation, n_val).unwrap();
    let t0 = std::time::Instant::now();
    let tr = points(&spec, &train);
    let va = points(&spec, &val);
    eprintln!("{} training and {} validation points ({:.0} s)", tr.len(), va.len(), t0.elapsed().as_secs_f64());
    let tracker = &spec.tracker;
    let err = |z: [f64; 2], truth: [f64; 2]| {
        let (d, t) = (tracker.from_z(z), tracker.from_z(truth));
        [Param::QMobile.err_pct(&d, &t), Param::ROhm.err_pct(&d, &t)]
    };
    let shift = |p: &Point, by: [f64; 2]| [p.2[0] + by[0], p.2[1] + by[1]];
    println!("RMS error at 55-95 % of each validation discharge, % of range (qMobile / Ro)");
    let rms_of = |r: &str, g: &dyn Fn(&Point) -> [f64; 2]| -> (usize, [f64; 2]) {
        let sel: Vec<&Point> = va.iter().filter(|p| p.0 == r).collect();
        let rms =
            [0, 1].map(|k| (sel.iter().map(|p| err(g(p), p.4)[k].powi(2)).sum::<f64>() / sel.len() as f64).sqrt());
        (sel.len(), rms)
    };
    println!("The bank alone (no learning), same points:");
    let names: Vec<&str> = bank(spec.ukf_settings()).iter().map(|b| b.0).collect();
    println!("| sampling | tuned joint UKF | {} |", names.join(" | "));
    for r in ["1s", "10-20s"] {
        let u = rms_of(r, &|p| p.2).1;
        let cols: Vec<String> = (0..names.len())
            .map(|m| {
                let b = rms_of(r, &|p| p.5[m]).1;
                format!("{:.2} / {:.2}", b[0], b[1])
            })
            .collect();
        println!("| {r} | {:.2} / {:.2} | {} |", u[0], u[1], cols.join(" | "));
    }
    let sets = [
        Inputs { load_free: false, bank: false, quadratic: true },
        Inputs { load_free: true, bank: false, quadratic: false },
        Inputs { load_free: true, bank: false, quadratic: true },
        Inputs { load_free: false, bank: true, quadratic: false },
        Inputs { load_free: true, bank: true, quadratic: false },
        Inputs { load_free: true, bank: true, quadratic: true },
    ];
    for inputs in sets {
        println!("\nInputs: {}", inputs.name());
        println!(
            "| ridge | sampling | joint UKF | + learned posterior shift | + learned true shift (oracle) | posterior mean |"
        );
        println!("| ---: | --- | ---: | ---: | ---: | ---: |");
        for ridge in [1.0, 10.0, 100.0, 1000.0] {
            let (wp, sp) = fit(&tr, inputs, |p| [p.3[0] - p.2[0], p.3[1] - p.2[1]], ridge);
            let (wt, st) = fit(&tr, inputs, |p| [p.4[0] - p.2[0], p.4[1] - p.2[1]], ridge);
            for r in ["1s", "10-20s"] {
                let (n, u) = rms_of(r, &|p| p.2);
                let lp = rms_of(r, &|p| shift(p, predict(&wp, &sp, inputs, p))).1;
                let lt = rms_of(r, &|p| shift(p, predict(&wt, &st, inputs, p))).1;
                let pm = rms_of(r, &|p| p.3).1;
                println!(
                    "| {ridge} | {r} ({n}) | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} |",
                    u[0], u[1], lp[0], lp[1], lt[0], lt[1], pm[0], pm[1]
                );
            }
        }
    }
}
