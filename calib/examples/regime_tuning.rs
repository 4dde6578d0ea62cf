//! Analysis behind docs/calibrator.md (`cargo run --release -p bcal-calib --example regime_tuning [VAL] [TEST]`):
//! the joint UKF is tuned once on the pooled NRMSE of every validation reading, where the 1 s cells carry
//! about 94 % of the weight. Is a filter tuned on each sampling regime's validation cells alone (the logger's
//! interval is known to a BMS) better on that regime's test cells? Both choices are made on VAL validation
//! cells (48, the evaluator's) over the evaluator's grid and scored on TEST test cells (96) per regime: NRMSE
//! over every reading and over each discharge's second half (by time), qMobile / Ro %.
#[path = "shared/mod.rs"]
mod shared;
use bcal_calib::tune::{tune_joint_ukf, JointUkfGrid};
use bcal_calib::{JointUkf, JointUkfSettings};
use bcal_common::dataset::Split;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::scenario::{episode_set, Episode};
use bcal_common::nrmse::Param;
use rayon::prelude::*;

/// NRMSE over every reading and over the second half of each discharge, qMobile / Ro %.
fn score(spec: &MeasuredSpec, eps: &[&Episode], ukf: JointUkfSettings) -> [[f64; 2]; 2] {
    // Per cell: squared errors summed over every reading and over the second half, and their counts.
    let sums: Vec<([[f64; 2]; 2], [usize; 2])> = eps
        .par_iter()
        .map(|e| {
            let mut f = JointUkf::new(ukf, &spec.tracker);
            let half = 0.5 * e.samples.last().map_or(0.0, |s| s.t_s);
            let (mut sq, mut n) = ([[0.0; 2]; 2], [0usize; 2]);
            for s in &e.samples {
                f.step(s);
                let second = s.t_s >= half;
                n[0] += 1;
                n[1] += usize::from(second);
                for (k, p) in Param::BOTH.into_iter().enumerate() {
                    let err = p.err_pct(&f.estimate(), &e.spec.truth);
                    sq[0][k] += err * err;
                    if second {
                        sq[1][k] += err * err;
                    }
                }
            }
            (sq, n)
        })
        .collect();
    [0, 1].map(|w| {
        let n = sums.iter().map(|c| c.1[w]).sum::<usize>() as f64;
        [0, 1].map(|k| (sums.iter().map(|c| c.0[w][k]).sum::<f64>() / n).sqrt())
    })
}

fn main() {
    let arg = |k: usize| std::env::args().nth(k);
    let n_val: usize = arg(1).map_or(48, |a| a.parse().expect("VAL, a count of validation cells"));
    let n_test: usize = arg(2).map_or(96, |a| a.parse().expect("TEST, a count of test cells"));
    let spec = MeasuredSpec::default();
    let val = episode_set(&spec.scenario, Split::Validation, n_val).unwrap();
    let test = episode_set(&spec.scenario, Split::Test, n_test).unwrap();
    let grid = JointUkfGrid::default();
    let t0 = std::time::Instant::now();
    let pooled = tune_joint_ukf(&spec.tracker, &val, &grid).best;
    let show = |s: &JointUkfSettings| {
        format!(
            "{} mV, walk {:e}, charge walk {} C, prior {:?}",
            s.meas_std_v * 1e3,
            s.param_walk_per_sqrt_s,
            s.charge_walk_c_per_sqrt_s,
            s.prior_std_z
        )
    };
    println!("tuned on every validation cell (pooled, as today): {}", show(&pooled));
    println!("| sampling | test cells | tuned on | settings | NRMSE q / Ro % | second half q / Ro % |");
    println!("| --- | ---: | --- | --- | ---: | ---: |");
    for r in ["1s", "10-20s"] {
        let v: Vec<Episode> = val.iter().filter(|e| shared::regime(e) == r).cloned().collect();
        let own = tune_joint_ukf(&spec.tracker, &v, &grid).best;
        let te: Vec<&Episode> = test.iter().filter(|e| shared::regime(e) == r).collect();
        for (name, s) in [("all validation cells", pooled), ("this regime's", own)] {
            let [a, b] = score(&spec, &te, s);
            println!(
                "| {r} | {} | {name} ({}) | {} | {:.2} / {:.2} | {:.2} / {:.2} |",
                te.len(),
                v.len(),
                show(&s),
                a[0],
                a[1],
                b[0],
                b[1]
            );
        }
    }
    eprintln!("{:.0} s", t0.elapsed().as_secs_f64());
}
