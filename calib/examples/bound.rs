//! Analysis behind docs/calibrator.md (`cargo run --release -p bcal-calib --example bound [N]`): how far any
//! causal estimator could go below the tuned joint UKF on the simulated cells of the headline, with
//! the exact model. At points of the second half of each validation discharge, the full-information
//! estimate (the maximum a posteriori of the starting charge, qMobile and Ro given every reading so far, the
//! joint UKF's prior and noise, each candidate run through the very model the filter runs: deterministic
//! dynamics, so no state is left to estimate) is set beside the filter's estimate at the same reading. The
//! filter is a Gaussian approximation of that posterior; what the full-information estimate gains over it is
//! what a correction of the filter could gain at most on average, whatever learns it.
//!
//! Arguments: the number of validation cells (48), the voltage noise the posterior assumes (the filter's
//! tuned 5 mV), and `uniform` for the cells' own prior (uniform over the ranges they are drawn from) in
//! place of the filter's Gaussian. `BOUND_POINTS=1` prints every comparison point.
#![allow(clippy::type_complexity)] // one-off analysis tables
#[path = "shared/mod.rs"]
mod shared;
use bcal_calib::JointUkf;
use bcal_common::dataset::Split;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::scenario::episode_set;
use bcal_common::nrmse::Param;
use nalgebra::Vector3;
use rayon::prelude::*;
use shared::posterior::Posterior;

type Row = (&'static str, [f64; 2], [f64; 2], [f64; 2], f64, [f64; 2], [f64; 2]);

/// The standard normal's cumulative distribution (Abramowitz and Stegun 7.1.26, error under 2e-7).
fn normal_cdf(x: f64) -> f64 {
    let z = x.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.3275911 * z);
    let poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))));
    let erf = 1.0 - poly * (-z * z).exp();
    0.5 * (1.0 + erf.copysign(x))
}

/// One parameter's filter marginal (mean `m`, variance `v`, z units) with the filter's Gaussian prior (`m0`,
/// `v0`) divided out and a uniform prior on [`lo`, `hi`] put in its place: the mean of what the readings said,
/// a normal, truncated to the range. No learning and no reading beyond the filter's own two numbers.
fn prior_swapped(m: f64, v: f64, m0: f64, v0: f64, [lo, hi]: [f64; 2]) -> f64 {
    let precision = 1.0 / v - 1.0 / v0;
    if precision <= 1e-9 {
        // The readings said nothing the prior did not: the uniform's own mean.
        return 0.5 * (lo + hi);
    }
    let vl = 1.0 / precision;
    let (ml, sl) = (vl * (m / v - m0 / v0), vl.sqrt());
    let (a, b) = ((lo - ml) / sl, (hi - ml) / sl);
    let mass = normal_cdf(b) - normal_cdf(a);
    if mass < 1e-12 {
        return ml.clamp(lo, hi);
    }
    let pdf = |x: f64| (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
    (ml + sl * (pdf(a) - pdf(b)) / mass).clamp(lo, hi)
}

fn main() {
    let arg = |k: usize| std::env::args().nth(k);
    let n: usize = arg(1).map_or(48, |a| a.parse().expect("N, a count of validation cells"));
    let spec = MeasuredSpec::default();
    let ukf = shared::tuned_ukf();
    // The noise the posterior assumes: the filter's tuned one by default (the sensor's is 3 mV; the tuned
    // filter takes more for the integrator's and the current sensor's part).
    let meas_std_v: f64 = arg(2).map_or(ukf.meas_std_v, |a| a.parse().expect("the posterior's voltage noise, V"));
    let val = episode_set(&spec.scenario, Split::Validation, n).unwrap();
    let tracker = spec.tracker.clone();
    let model = tracker.model.model().expect("the default model");
    // The ranges the simulated cells are drawn from, z units.
    let cells = shared::posterior::cell_ranges_z(&spec);
    let uniform = (arg(3).as_deref() == Some("uniform")).then_some(cells);
    let rows: Vec<Row> = val
        .par_iter()
        .flat_map_iter(|e| {
            let at = shared::posterior::points(e);
            let mut f = JointUkf::new(ukf, &tracker);
            let mut out = Vec::new();
            for (k, smp) in e.samples.iter().enumerate() {
                f.step(smp);
                if !at.contains(&k) {
                    continue;
                }
                let est = f.estimate();
                let z = tracker.to_z(&est);
                let post = Posterior::new(&model, &tracker, &ukf, meas_std_v, e, k, uniform);
                let (mode, _) = post.map(Vector3::new(post.mean[0], z[0], z[1]));
                let (mean, ess) = post.mean(mode);
                let t = e.spec.truth;
                let err = |zq: f64, zr: f64| {
                    let d = tracker.from_z([zq, zr]);
                    [Param::QMobile.err_pct(&d, &t), Param::ROhm.err_pct(&d, &t)]
                };
                if std::env::var("BOUND_POINTS").is_ok() {
                    // The misfit at the truth (the starting charge profiled) beside the mode's: how far the
                    // filter's model is from the cells' own.
                    let zt = tracker.to_z(&t);
                    let (at_truth, _) = post.fit(Vector3::new(mode[0], zt[0], zt[1]), [true, false, false]);
                    eprintln!(
                        "{} n {} qMobile z truth {:.3}: ukf {:.3} mode {:.3} mean {:.3}, grid points {ess:.0}; cost at \
                         the mode {:.1}, at the truth {:.1}",
                        shared::regime(e),
                        k + 1,
                        zt[0],
                        z[0],
                        mode[1],
                        mean[1],
                        post.cost(&mode),
                        post.cost(&at_truth)
                    );
                }
                // The filter's estimate held inside the cells' ranges: what knowing their support alone gives.
                let held = err(z[0].clamp(cells[0][0], cells[0][1]), z[1].clamp(cells[1][0], cells[1][1]));
                let cov = f.param_cov_z();
                let prior_z = tracker.to_z(&tracker.prior);
                let swap = |j: usize, v: f64| prior_swapped(z[j], v, prior_z[j], ukf.prior_std_z[j].powi(2), cells[j]);
                let swapped = err(swap(0, cov[0]), swap(1, cov[2]));
                out.push((
                    shared::regime(e),
                    err(z[0], z[1]),
                    err(mode[1], mode[2]),
                    err(mean[1], mean[2]),
                    ess,
                    held,
                    swapped,
                ));
            }
            out
        })
        .collect();
    println!(
        "{n} validation cells, points at 55-95 % of each discharge, RMS error % of range (qMobile / Ro); \
         posterior noise {:.1} mV, prior {}",
        meas_std_v * 1e3,
        if uniform.is_some() { "uniform over the cells' ranges" } else { "the filter's" }
    );
    println!(
        "| sampling | points | joint UKF | UKF held in the cells' ranges | UKF, the cells' prior swapped in | posterior \
         mode | posterior mean | mean / UKF | median grid points |"
    );
    println!("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    for r in ["1s", "10-20s"] {
        let sel: Vec<&Row> = rows.iter().filter(|x| x.0 == r).collect();
        if sel.is_empty() {
            continue;
        }
        let rms = |g: &dyn Fn(&Row) -> f64| (sel.iter().map(|x| g(x).powi(2)).sum::<f64>() / sel.len() as f64).sqrt();
        let pair = |g: &dyn Fn(&Row) -> [f64; 2]| [rms(&|x| g(x)[0]), rms(&|x| g(x)[1])];
        let (u, m, p, h, w) = (pair(&|x| x.1), pair(&|x| x.2), pair(&|x| x.3), pair(&|x| x.5), pair(&|x| x.6));
        let mut ess: Vec<f64> = sel.iter().map(|x| x.4).collect();
        let ess = bcal_common::stats::median(&mut ess).unwrap_or(f64::NAN);
        println!(
            "| {r} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | \
             {ess:.0} |",
            sel.len(),
            u[0],
            u[1],
            h[0],
            h[1],
            w[0],
            w[1],
            m[0],
            m[1],
            p[0],
            p[1],
            p[0] / u[0],
            p[1] / u[1]
        );
    }
}
