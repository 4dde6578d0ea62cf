//! The full-information posterior of a simulated discharge's starting charge, qMobile and Ro given its
//! readings so far, under the joint UKF's own model and drive (`bound` and `distil`).

use bcal_common::battery::{BatteryModel, Degradation};
use bcal_common::measured::cellmodel::{interval_drive, start_xn_std, xn_from_rest_voltage, DriveKind, Settle};
use bcal_common::measured::scenario::{rest_state, Episode};
use bcal_common::measured::tracker::{JointUkfSettings, TrackerSpec};
use nalgebra::{Matrix3, Vector3};

/// Shares of each discharge (from its load-on to its last reading) the posterior is set at.
pub const AT: [f64; 5] = [0.55, 0.65, 0.75, 0.85, 0.95];

/// The ranges the simulated cells of `spec` are drawn from, z units of the calibrator's ranges (qMobile, Ro).
pub fn cell_ranges_z(spec: &bcal_common::measured::env::MeasuredSpec) -> [[f64; 2]; 2] {
    let (sc, tracker) = (&spec.scenario, &spec.tracker);
    let lo = tracker.to_z(&Degradation { q_mobile_c: sc.q_mobile_c[0], r_o_ohm: sc.r_o_ohm[0] });
    let hi = tracker.to_z(&Degradation { q_mobile_c: sc.q_mobile_c[1], r_o_ohm: sc.r_o_ohm[1] });
    [[lo[0], hi[0]], [lo[1], hi[1]]]
}

/// The readings of `e` at the shares [`AT`] of its discharge.
pub fn points(e: &Episode) -> Vec<usize> {
    let on = e.samples.iter().position(|s| s.current_a > 0.05).unwrap_or(0);
    let last = e.samples.len() - 1;
    AT.iter().map(|f| on + (f * (last - on) as f64).round() as usize).collect()
}

/// The model's voltage at every reading up to `upto` under (xn0, d), driven as the joint UKF drives its
/// points (`JointUkf::propagate`: the reading's load over each interval's parts, Euler substeps of at most
/// `max_substep_s`, a power load following P / V).
pub fn voltages(
    model: &BatteryModel,
    spec: &TrackerSpec,
    e: &Episode,
    upto: usize,
    xn0: f64,
    d: &Degradation,
) -> Vec<f64> {
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
pub struct Posterior<'a> {
    model: &'a BatteryModel,
    spec: &'a TrackerSpec,
    e: &'a Episode,
    upto: usize,
    sd_v: Vec<f64>,
    pub mean: [f64; 3],
    std: [f64; 3],
    /// With Some(the simulated cells' own ranges of qMobile and Ro, z units), the prior on the two is
    /// uniform over them (what the cells are drawn from) instead of the filter's Gaussian.
    uniform: Option<[[f64; 2]; 2]>,
}

impl<'a> Posterior<'a> {
    pub fn new(
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
    pub fn cost(&self, th: &Vector3<f64>) -> f64 {
        self.residuals(th).iter().map(|x| x * x).sum()
    }

    /// The maximum a posteriori from `start` (Levenberg-Marquardt, Jacobian by central differences) and the
    /// Gauss-Newton information there.
    pub fn map(&self, start: Vector3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
        self.fit(start, [true; 3])
    }

    /// [`Self::map`] over the parameters `free` marks, the others held at `start`'s.
    pub fn fit(&self, start: Vector3<f64>, free: [bool; 3]) -> (Vector3<f64>, Matrix3<f64>) {
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
    pub fn mean(&self, mode: Vector3<f64>) -> (Vector3<f64>, f64) {
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
