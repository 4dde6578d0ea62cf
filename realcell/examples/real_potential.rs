//! Analysis behind docs/calibrator.md (`cargo run --release -p bcal-realcell --example real_potential CELL [DATA]`): on a real cell's recorded discharges, is the joint UKF's estimate biased for the predictive
//! cost in a way a correction could learn from the training cycles?
#![allow(clippy::type_complexity, clippy::field_reassign_with_default)] // one-off analysis tables
use bcal_calib::env::correction_cost;
use bcal_calib::Correction;
use bcal_common::battery::Degradation;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::tracker::JointUkfSettings;
use bcal_doctor::read::{nasa_cutoff_v, read_nasa_with, ReadOptions};
use bcal_realcell::record::prepare;
use std::path::Path;

fn main() {
    let cell = std::env::args().nth(1).unwrap_or("B0005".into());
    let data = std::env::args().nth(2).unwrap_or("../shared/data/nasa-pcoe".into());
    let root = Path::new(&data);
    let (all, _) = read_nasa_with(root, &cell, None, &ReadOptions::default()).unwrap();
    let cut = nasa_cutoff_v(root, &cell).unwrap();
    let mut spec = MeasuredSpec::default();
    spec.tracker.q_mobile_range_c = [2000.0, 12000.0];
    spec.tracker.r_o_range_ohm = [0.01, 0.5];
    spec.tracker.cutoff_v = cut;
    spec.tracker.prior = Degradation { q_mobile_c: 7000.0, r_o_ohm: 0.1 };
    spec.ukf = Some(JointUkfSettings {
        meas_std_v: 0.02,
        voltage_walk_v_per_sqrt_s: 1e-3,
        prior_std_z: [0.02, 0.02],
        ..Default::default()
    });
    let grid: Vec<[f32; 2]> = [-1.0f32, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0]
        .iter()
        .flat_map(|&a| [-1.0f32, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0].map(|b| [a, b]))
        .collect();
    let zero = grid.iter().position(|a| a == &[0.0, 0.0]).unwrap();
    // (cycle, quarter, costs)
    let mut pts: Vec<(u32, usize, Vec<f64>)> = Vec::new();
    let mut prior = spec.tracker.prior;
    for d in all.iter().filter(|d| d.cycle <= 100) {
        let Ok(r) = prepare(d, cut) else { continue };
        let Some(eod) = r.eod_s else { continue };
        let Some(ep) = bcal_realcell::recorded::episode_of(&r, Some(prior)) else { continue };
        let t0 = r.samples[0].t_s;
        let mut s2 = spec.clone();
        s2.tracker.prior = prior;
        s2.tracker.model.reference_k = Some(r.ambient_k);
        let mut c = Correction::of_task(&s2);
        let n = ep.samples.len();
        for (k, s) in ep.samples.iter().enumerate() {
            c.ingest(s);
            if k % 5 != 0 || k + 1 >= n || s.t_s < ep.spec.rest_s {
                continue;
            }
            let q = (((s.t_s - ep.spec.rest_s) / (eod - t0 - ep.spec.rest_s)) * 4.0).floor().clamp(0.0, 3.0) as usize;
            let costs: Vec<f64> = grid
                .iter()
                .map(|a| {
                    c.apply_action(a);
                    correction_cost(&s2, &c, &ep, k)
                })
                .collect();
            pts.push((d.cycle, q, costs));
        }
        c.apply_action(&[0.0, 0.0]);
        prior = c.estimate();
        eprintln!("cycle {}: {} readings, end estimate {:?}", d.cycle, n, prior);
    }
    let mean = |f: &dyn Fn(&(u32, usize, Vec<f64>)) -> bool, a: usize| {
        let v: Vec<f64> = pts.iter().filter(|p| f(p)).map(|p| p.2[a]).collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    };
    for q in 0..4 {
        let tr = |p: &(u32, usize, Vec<f64>)| p.0 <= 40 && p.1 == q;
        let te = |p: &(u32, usize, Vec<f64>)| p.0 > 40 && p.1 == q;
        let b = (0..grid.len()).min_by(|&a, &c| mean(&tr, a).total_cmp(&mean(&tr, c))).unwrap();
        println!(
            "{cell} quarter {q}: best on 1-40 {:?}: train {:.3}, judged 41+ {:.3} (zero {:.3})",
            grid[b],
            mean(&tr, b),
            mean(&te, b),
            mean(&te, zero)
        );
    }
}
