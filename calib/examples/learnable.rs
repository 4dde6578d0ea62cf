//! Analysis behind docs/calibrator.md (`cargo run --release -p bcal-calib --example learnable`): is the hindsight-best shift predictable from the correction's observation? Linear least squares
//! from features to the best shift (by the relative predictive cost) on training cells, judged on validation.
use bcal_calib::env::correction_cost;
use bcal_calib::{Calibrator, Correction, WindowFitCalibrator};
use bcal_common::dataset::Split;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::scenario::{draw_spec, episode_set, simulate, Episode};
use bcal_common::measured::tracker::JointUkfSettings;
use nalgebra::{DMatrix, DVector};
use rand::SeedableRng;
use rayon::prelude::*;

const WINDOW: bool = true;

fn points(spec: &MeasuredSpec, eps: &[Episode], stride: usize) -> Vec<(Vec<f64>, [f64; 2], f64, f64)> {
    let grid: Vec<f32> = (0..9).map(|k| -1.0 + 0.25 * k as f32).collect();
    eps.par_iter()
        .flat_map_iter(|e| {
            let mut c = Correction::of_task(spec);
            let mut wf = WindowFitCalibrator::new(&spec.tracker);
            let mut out = Vec::new();
            let n = e.samples.len();
            let mut obs = vec![0f32; spec.obs_dim() + 24];
            for (k, s) in e.samples.iter().enumerate() {
                c.ingest(s);
                wf.step(s);
                if k % stride != 0 || k + 1 >= n {
                    continue;
                }
                c.observe(&mut obs);
                if WINDOW {
                    wf.tracker().observe(&mut obs[spec.obs_dim()..]);
                }
                let mut best = (f64::INFINITY, [0f32; 2]);
                for &a in &grid {
                    for &b in &grid {
                        c.apply_action(&[a, b]);
                        let cost = correction_cost(spec, &c, e, k);
                        if cost < best.0 {
                            best = (cost, [a, b]);
                        }
                    }
                }
                out.push((
                    obs.iter().map(|v| f64::from(*v)).collect(),
                    [f64::from(best.1[0]), f64::from(best.1[1])],
                    best.0,
                    k as f64,
                ));
            }
            out
        })
        .collect()
}

fn main() {
    let mut spec = MeasuredSpec::default();
    spec.scenario.model_error.probability = std::env::args().nth(1).map_or(0.5, |s| s.parse().unwrap());
    spec.ukf = Some(JointUkfSettings {
        meas_std_v: 0.01,
        param_walk_per_sqrt_s: 1e-5,
        charge_walk_c_per_sqrt_s: 1.0,
        ..Default::default()
    });
    let mut rng = rand::rngs::SmallRng::seed_from_u64(7);
    let train: Vec<Episode> = (0..160)
        .filter_map(|_| simulate(&spec.scenario, &draw_spec(&spec.scenario, Split::Train, &mut rng)).ok())
        .collect();
    let val = episode_set(&spec.scenario, Split::Validation, 48).unwrap();
    let t0 = std::time::Instant::now();
    let tr = points(&spec, &train, 25);
    eprintln!(
        "{} training points in {:.0} s; mean best relative cost {:.3}",
        tr.len(),
        t0.elapsed().as_secs_f64(),
        tr.iter().map(|p| p.2).sum::<f64>() / tr.len() as f64
    );
    let d = tr[0].0.len() + 1;
    let x = DMatrix::from_fn(tr.len(), d, |i, j| if j + 1 == d { 1.0 } else { tr[i].0[j] });
    for ridge in [1.0, 10.0, 100.0] {
        let xtx = x.transpose() * &x + DMatrix::identity(d, d) * ridge;
        let mut w = Vec::new();
        for k in 0..2 {
            let y = DVector::from_fn(tr.len(), |i, _| tr[i].1[k]);
            w.push(xtx.clone().cholesky().unwrap().solve(&(x.transpose() * y)));
        }
        // Judge on validation: the predicted action's relative cost at every 10th reading.
        let res: Vec<(f64, f64)> = val
            .par_iter()
            .flat_map_iter(|e| {
                let mut c = Correction::of_task(&spec);
                let mut wf = WindowFitCalibrator::new(&spec.tracker);
                let mut obs = vec![0f32; spec.obs_dim() + 24];
                let mut out = Vec::new();
                let n = e.samples.len();
                for (k, s) in e.samples.iter().enumerate() {
                    c.ingest(s);
                    wf.step(s);
                    if k % 10 != 0 || k + 1 >= n {
                        continue;
                    }
                    c.observe(&mut obs);
                    if WINDOW {
                        wf.tracker().observe(&mut obs[spec.obs_dim()..]);
                    }
                    let f: Vec<f64> = obs.iter().map(|v| f64::from(*v)).chain([1.0]).collect();
                    let a: Vec<f32> = (0..2)
                        .map(|k| (w[k].iter().zip(&f).map(|(a, b)| a * b).sum::<f64>()).clamp(-1.0, 1.0) as f32)
                        .collect();
                    c.apply_action(&a);
                    let cost = correction_cost(&spec, &c, e, k);
                    let tq = bcal_common::nrmse::Param::QMobile.err_pct(&c.estimate(), &e.spec.truth);
                    out.push((cost, tq));
                }
                out
            })
            .collect();
        let n = res.len() as f64;
        println!(
            "ridge {ridge}: validation relative cost {:.3} (filter 1.000), q NRMSE {:.2}",
            res.iter().map(|r| r.0).sum::<f64>() / n,
            (res.iter().map(|r| r.1 * r.1).sum::<f64>() / n).sqrt()
        );
    }
}
