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
use bcal_common::battery::{BatteryModel, Degradation};
use bcal_common::dataset::Split;
use bcal_common::measured::cellmodel::{interval_drive, start_xn_std, xn_from_rest_voltage, DriveKind, Settle};
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::scenario::{episode_set, rest_state, Episode};
use bcal_common::measured::tracker::{JointUkfSettings, TrackerSpec};
use bcal_common::nrmse::Param;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

/// Shares of each discharge (from its load-on to its last reading) the two are compared at.
const AT: [f64; 5] = [0.55, 0.65, 0.75, 0.85, 0.95];

/// The model's voltage at every reading up to `upto` under (xn0, d), driven as the joint UKF drives its
/// points (`JointUkf::propagate`: the reading's load over each interval's parts, Euler substeps of at most
/// `max_substep_s`, a power load following P / V).
fn voltages(model: &BatteryModel, spec: &TrackerSpec, e: &Episode, upto: usize, xn0: f64, d: &Degradation) -> Vec<f64> {
    let s = &e.samples;
    let t_of = |k: usize| if spec.use_measured_temperature { s[k].temperature_k } else { model.params.tb0_k };
    let mut x = rest_state(model, d, xn0, t_of(0));
    let mut out = Vec::with_capacity(upto + 1);
    out.push(model.voltage_v(&x, d));
    for k in 1..=upto {
        x[bcal_common::math::idx::T_B] = t_of(k);
        for (dt_s, kind) in interval_drive(&s[k - 1], &s[k], spec.max_substep_s, false) {
            if dt_s <= 0.0 {
                continue;
            }
            let nsub = (dt_s / spec.max_substep_s - 1e-9).ceil().max(1.0);
            let h = dt_s / nsub;
            let v0 = model.voltage_v(&x, d);
            for _ in 0..nsub as usize {
                let i_a = match kind {
                    DriveKind::Current(i) => i,
                    DriveKind::Power(i) => {
                        let v = model.voltage_v(&x, d);
                        if v > 0.0 && v.is_finite() && v0.is_finite() {
                            i * v0 / v
                        } else {
                            i
                        }
                    }
                };
                x = model.step_current(&x, i_a, h, d);
            }
        }
        out.push(model.voltage_v(&x, d));
    }
    out
}

/// The posterior of (xn0, qMobile z, Ro z) given readings 0..=upto: whitened residuals of every reading (by
/// the filter's measurement noise `meas_std_v` and, after a switch of unknown time, the filter's own added
/// variance) and the prior's three terms (the filter's start: the rest reading's mole fraction and width,
/// the prior and its widths).
struct Posterior<'a> {
    model: &'a BatteryModel,
    spec: &'a TrackerSpec,
    e: &'a Episode,
    upto: usize,
    sd_v: Vec<f64>,
    mean: [f64; 3],
    std: [f64; 3],
    /// With Some(the simulated cells' own ranges of qMobile and Ro, z units), the prior on the two is
    /// uniform over them (what the cells are drawn from) instead of the filter's Gaussian.
    uniform: Option<[[f64; 2]; 2]>,
}

impl<'a> Posterior<'a> {
    fn new(
        model: &'a BatteryModel,
        spec: &'a TrackerSpec,
        ukf: &JointUkfSettings,
        meas_std_v: f64,
        e: &'a Episode,
        upto: usize,
        uniform: Option<[[f64; 2]; 2]>,
    ) -> Self {
        let s = &e.samples;
        let t0 = if spec.use_measured_temperature { s[0].temperature_k } else { model.params.tb0_k };
        let xn = xn_from_rest_voltage(model, s[0].voltage_v, t0);
        let xn_std = start_xn_std(model, xn, t0, ukf.meas_std_v, 0.005);
        let prior_z = spec.to_z(&spec.prior);
        let mut settle = Settle::default();
        let mut sd_v = vec![meas_std_v; upto + 1];
        for k in 1..=upto {
            settle.unsettled(&s[k - 1], &s[k], spec.max_substep_s, spec.settle_s);
            let extra = settle.voltage_variance_v2(s[k].t_s, spec.prior.r_o_ohm, model.params.t_o_s);
            sd_v[k] = (meas_std_v.powi(2) + extra).sqrt();
        }
        Self {
            model,
            spec,
            e,
            upto,
            sd_v,
            mean: [xn, prior_z[0], prior_z[1]],
            std: [xn_std, ukf.prior_std_z[0], ukf.prior_std_z[1]],
            uniform,
        }
    }

    fn residuals(&self, th: &Vector3<f64>) -> Vec<f64> {
        let p = &self.model.params;
        let xn0 = th[0].clamp(p.xn_min + 1e-3, p.xn_max);
        let d = self.spec.from_z([th[1], th[2]]);
        let v = voltages(self.model, self.spec, self.e, self.upto, xn0, &d);
        let s = &self.e.samples;
        let mut r: Vec<f64> = (0..=self.upto).map(|k| (s[k].voltage_v - v[k]) / self.sd_v[k]).collect();
        r.push((th[0] - self.mean[0]) / self.std[0]);
        match self.uniform {
            None => r.extend((1..3).map(|j| (th[j] - self.mean[j]) / self.std[j])),
            // Flat inside, a steep wall outside (1 % of the range outside costs 100).
            Some(b) => r.extend((1..3).map(|j| {
                let [lo, hi] = b[j - 1];
                1e3 * ((lo - th[j]).max(0.0) + (th[j] - hi).max(0.0))
            })),
        }
        r
    }

    /// Minus twice the log posterior, up to a constant.
    fn cost(&self, th: &Vector3<f64>) -> f64 {
        self.residuals(th).iter().map(|x| x * x).sum()
    }

    /// The maximum a posteriori from `start` (Levenberg-Marquardt, Jacobian by central differences) and the
    /// Gauss-Newton information there.
    fn map(&self, start: Vector3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
        self.fit(start, [true; 3])
    }

    /// [`Self::map`] over the parameters `free` marks, the others held at `start`'s.
    fn fit(&self, start: Vector3<f64>, free: [bool; 3]) -> (Vector3<f64>, Matrix3<f64>) {
        let mut th = start;
        let mut r = self.residuals(&th);
        let mut c: f64 = r.iter().map(|x| x * x).sum();
        let mut lambda = 1e-3;
        let h = [1e-5, 1e-4, 1e-4];
        let mut jtj = Matrix3::identity();
        for _ in 0..30 {
            let cols: Vec<Vec<f64>> = (0..3)
                .map(|j| {
                    if !free[j] {
                        return vec![0.0; r.len()];
                    }
                    let (mut a, mut b) = (th, th);
                    a[j] += h[j];
                    b[j] -= h[j];
                    let (ra, rb) = (self.residuals(&a), self.residuals(&b));
                    ra.iter().zip(&rb).map(|(x, y)| (x - y) / (2.0 * h[j])).collect()
                })
                .collect();
            jtj = Matrix3::zeros();
            let mut jtr = Vector3::zeros();
            for k in 0..r.len() {
                let row = Vector3::new(cols[0][k], cols[1][k], cols[2][k]);
                jtj += row * row.transpose();
                jtr += row * r[k];
            }
            for j in (0..3).filter(|j| !free[*j]) {
                jtj[(j, j)] = 1.0;
            }
            let mut improved = false;
            for _ in 0..10 {
                let a = jtj + Matrix3::from_diagonal(&jtj.diagonal()) * lambda;
                let Some(step) = a.lu().solve(&jtr) else { break };
                // Gauss-Newton on the residuals' own Jacobian: the step goes against J^T r.
                let cand = th - step;
                let rc = self.residuals(&cand);
                let cc: f64 = rc.iter().map(|x| x * x).sum();
                if cc < c {
                    let done = (c - cc) < 1e-9 * c.max(1.0) || step.norm() < 1e-8;
                    (th, r, c) = (cand, rc, cc);
                    lambda = (lambda * 0.3).max(1e-9);
                    improved = true;
                    if done {
                        return (th, jtj);
                    }
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        (th, jtj)
    }

    /// The posterior mean (the estimate of least mean squared error): qMobile, the one the readings pin
    /// least, on a grid over the filter's range, the other two profiled out at each point (their fit, with
    /// the Laplace factor of their information); first 21 points over the whole range, then 41 over where
    /// the first grid holds the mass. Returns the mean and the fine grid's effective number of points.
    fn mean(&self, mode: Vector3<f64>) -> (Vector3<f64>, f64) {
        let profile = |lo: f64, hi: f64, n: usize| -> Vec<(f64, Vector3<f64>)> {
            let mut at = mode;
            let mut out = Vec::with_capacity(n);
            // Outward from the point nearest the mode, each fit warm-started from its neighbour.
            let qs: Vec<f64> = (0..n).map(|k| lo + (hi - lo) * k as f64 / (n - 1) as f64).collect();
            let near = qs.iter().enumerate().min_by(|a, b| (a.1 - mode[1]).abs().total_cmp(&(b.1 - mode[1]).abs()));
            let near = near.map_or(0, |x| x.0);
            let order: Vec<usize> = (near..n).chain((0..near).rev()).collect();
            for (m, &k) in order.iter().enumerate() {
                if m > 0 && k + 1 == near {
                    at = mode;
                }
                at[1] = qs[k];
                let (th, info) = self.fit(at, [true, false, true]);
                at = th;
                let det = info[(0, 0)] * info[(2, 2)] - info[(0, 2)] * info[(2, 0)];
                out.push((-0.5 * self.cost(&th) - 0.5 * det.max(1e-300).ln(), th));
            }
            out
        };
        let weights = |pts: &[(f64, Vector3<f64>)]| -> Vec<f64> {
            let top = pts.iter().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
            pts.iter().map(|p| (p.0 - top).exp()).collect()
        };
        let coarse = profile(0.0, 1.0, 21);
        let w = weights(&coarse);
        let held: Vec<f64> = coarse.iter().zip(&w).filter(|(_, w)| **w > 1e-4).map(|(p, _)| p.1[1]).collect();
        let lo = held.iter().copied().fold(f64::INFINITY, f64::min) - 0.05;
        let hi = held.iter().copied().fold(f64::NEG_INFINITY, f64::max) + 0.05;
        let fine = profile(lo.max(0.0), hi.min(1.0), 41);
        let w = weights(&fine);
        let sum: f64 = w.iter().sum();
        let mean = fine.iter().zip(&w).fold(Vector3::zeros(), |a, (p, w)| a + p.1 * (w / sum));
        (mean, sum * sum / w.iter().map(|w| w * w).sum::<f64>())
    }
}

type Row = (&'static str, [f64; 2], [f64; 2], [f64; 2], f64, [f64; 2]);

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
    let sc = &spec.scenario;
    // The ranges the simulated cells are drawn from, z units.
    let cells = {
        let lo = tracker.to_z(&Degradation { q_mobile_c: sc.q_mobile_c[0], r_o_ohm: sc.r_o_ohm[0] });
        let hi = tracker.to_z(&Degradation { q_mobile_c: sc.q_mobile_c[1], r_o_ohm: sc.r_o_ohm[1] });
        [[lo[0], hi[0]], [lo[1], hi[1]]]
    };
    let uniform = (arg(3).as_deref() == Some("uniform")).then_some(cells);
    let rows: Vec<Row> = val
        .par_iter()
        .flat_map_iter(|e| {
            let on = e.samples.iter().position(|s| s.current_a > 0.05).unwrap_or(0);
            let last = e.samples.len() - 1;
            let at: Vec<usize> = AT.iter().map(|f| on + (f * (last - on) as f64).round() as usize).collect();
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
                out.push((shared::regime(e), err(z[0], z[1]), err(mode[1], mode[2]), err(mean[1], mean[2]), ess, held));
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
        "| sampling | points | joint UKF | UKF held in the cells' ranges | posterior mode | posterior mean | mean / UKF | \
         median grid points |"
    );
    println!("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    for r in ["1s", "10-20s"] {
        let sel: Vec<&Row> = rows.iter().filter(|x| x.0 == r).collect();
        if sel.is_empty() {
            continue;
        }
        let rms = |g: &dyn Fn(&Row) -> f64| (sel.iter().map(|x| g(x).powi(2)).sum::<f64>() / sel.len() as f64).sqrt();
        let pair = |g: &dyn Fn(&Row) -> [f64; 2]| [rms(&|x| g(x)[0]), rms(&|x| g(x)[1])];
        let (u, m, p, h) = (pair(&|x| x.1), pair(&|x| x.2), pair(&|x| x.3), pair(&|x| x.5));
        let mut ess: Vec<f64> = sel.iter().map(|x| x.4).collect();
        let ess = bcal_common::stats::median(&mut ess).unwrap_or(f64::NAN);
        println!(
            "| {r} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {ess:.0} |",
            sel.len(),
            u[0],
            u[1],
            h[0],
            h[1],
            m[0],
            m[1],
            p[0],
            p[1],
            p[0] / u[0],
            p[1] / u[1]
        );
    }
}
