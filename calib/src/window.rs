//! The calibrator's least-squares view of everything it has read: a window of recent readings with the
//! parameter-free model state at each, so the predicted voltage at every point can be re-evaluated under
//! any candidate parameters, plus a quadratic summary of every earlier reading. It gives the RL cost (how
//! well the current estimate explains what was measured) and the fit statistics the policy observes
//! (residual, sensitivities, the Gauss-Newton step and the information of the fit). Everything here is
//! computed from readings and the calibrator's own model: nothing of the true cell.
//!
//! Window points are bins at least `span_s / capacity` long, so the window spans about `span_s` whatever
//! the sampling interval. Every reading counts: one that arrives within the newest bin's span joins it (its
//! voltage and model state averaged in, the bin's weight counting its readings), so at 1 s sampling a bin
//! holds tens of readings and weighs as many. Averaging the parameter-free state is exact for the terms
//! the voltage holds linearly (the overpotentials, the ohmic lag) and close for the charges, which move a
//! fraction of a percent within a bin. (Until issue 18 the newest reading replaced the last point instead,
//! and about 97 % of 1 s readings never reached the fit.) A bin pushed out at the front is not forgotten:
//! its residual is linearised at the estimate of that moment and added to the summary (the residual sum of
//! squares as a quadratic in the parameters, as sliding-window smoothers marginalise old states), so a
//! constant-current discharge keeps what its one load step said about Ro long after the step left the
//! window.
//!
//! The starting charge (the negative electrode's mole fraction at the start, read off the rest voltage) is
//! a third unknown of the fit when the caller gives it a prior ([`StartPrior`], the joint UKF's start
//! uncertainty). The information the policy and the interval see is then qMobile's and Ro's with the start
//! profiled out (its Schur complement), so an interval widens by what the start leaves open; and where the
//! start moves, the step is joint with it and the fit says how far the start should go
//! ([`FitStats::step_start`]). Until issue 18's review the start was exact to the fit: its uncertainty
//! never reached the interval, and a discharge that begins under load carried the loaded voltage's error
//! into qMobile for the whole discharge.

use bcal_common::battery::Degradation;
use bcal_common::measured::cellmodel::{CellModel, Track};
use bcal_common::nrmse::Param;
use std::collections::VecDeque;

/// One bin of readings: their mean voltage and the mean of the model's parameter-free state at their
/// times, weighing as many readings as it holds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitPoint {
    /// Time of the newest reading in the bin, s.
    pub t_s: f64,
    pub track: Track,
    pub voltage_v: f64,
    /// Time of the bin's first reading, s.
    pub first_t_s: f64,
    /// Readings in the bin.
    pub weight: f64,
}

impl FitPoint {
    /// One reading.
    pub fn reading(t_s: f64, track: Track, voltage_v: f64) -> Self {
        Self { t_s, track, voltage_v, first_t_s: t_s, weight: 1.0 }
    }

    /// Averages the reading `p` into the bin.
    fn absorb(&mut self, p: &FitPoint) {
        let w = p.weight / (self.weight + p.weight);
        let mix = |a: &mut f64, b: f64| *a += w * (b - *a);
        for (a, b) in self.track.dq_c.iter_mut().zip(p.track.dq_c) {
            mix(a, b);
        }
        mix(&mut self.track.current_lag_a, p.track.current_lag_a);
        mix(&mut self.track.vsn_v, p.track.vsn_v);
        mix(&mut self.track.vsp_v, p.track.vsp_v);
        mix(&mut self.track.t_k, p.track.t_k);
        mix(&mut self.voltage_v, p.voltage_v);
        self.weight += p.weight;
        self.t_s = p.t_s;
    }
}

/// Least-squares statistics of the window at one estimate, in normalised parameter units (z = the
/// parameter scaled to [0, 1] over the calibrator's range, qMobile first).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FitStats {
    /// Points in the window.
    pub n: usize,
    /// Root mean square of measured minus predicted voltage, V.
    pub rms_v: f64,
    /// The same with the prior's term added to the sum of squares (the fit's own objective: misfit plus
    /// prior, both in volts squared), V; equals `rms_v` without a prior.
    pub map_rms_v: f64,
    /// Mean of r J (r: residual, J: dV/dz), V^2.
    pub grad: [f64; 2],
    /// Mean of J J^T (Gauss-Newton information), V^2: [qq, qr, rr], with the starting charge profiled out
    /// when it is fitted (what the readings say of qMobile and Ro whatever the start was).
    pub info: [f64; 3],
    /// The damped Gauss-Newton step that minimises the window's squared residual, in z units (jointly
    /// with the starting charge when it is fitted).
    pub step: [f64; 2],
    /// The step of the starting mole fraction that minimises the objective at this estimate of qMobile
    /// and Ro (0 when the start is not fitted).
    pub step_start: f64,
}

impl FitStats {
    /// Standard deviations of the estimate from the fit, in z units: sqrt(diag((n J^T J)^-1)) times the
    /// residual standard deviation (floored at `noise_floor_v`); `None` when the information is singular.
    pub fn std_z(&self, noise_floor_v: f64) -> Option<[f64; 2]> {
        let [a, b, c] = self.info;
        let det = a * c - b * b;
        if self.n < 3 || det <= 1e-30 * (a * c).max(1e-300) || det <= 0.0 {
            return None;
        }
        let s2 = self.rms_v.max(noise_floor_v).powi(2) / self.n as f64;
        Some([(s2 * c / det).sqrt(), (s2 * a / det).sqrt()])
    }
}

/// The starting charge's prior: the mole fraction read off the rest voltage and its standard deviation
/// ([`bcal_common::measured::cellmodel::start_xn_std`]), weighed as `noise_v` of sensor noise as the
/// parameters' prior is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StartPrior {
    pub xn: f64,
    pub std: f64,
    pub noise_v: f64,
    /// The fit moves the start ([`FitStats::step_start`], the parameters' step joint with it); else the
    /// start stays where it is and only its uncertainty enters the information.
    pub moves: bool,
}

/// The fit's unknowns: qMobile and Ro in z units, then the starting mole fraction.
type P3 = [f64; 3];

/// Readings that left the window, as a quadratic in p = (z, start): their residual sum of squares is
/// c - 2 b.p + p'Ap (each residual linearised where it left: r(p) ~ a - J.p).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct History {
    /// Sum of J J', row by row.
    a: [[f64; 3]; 3],
    /// Sum of a J.
    b: P3,
    /// Sum of a^2.
    c: f64,
    /// Readings folded in.
    m: f64,
}

impl History {
    fn sum_sq(&self, p: P3) -> f64 {
        let pap: f64 = (0..3).map(|i| (0..3).map(|k| p[i] * self.a[i][k] * p[k]).sum::<f64>()).sum();
        (self.c - 2.0 * dot(&self.b, &p) + pap).max(0.0)
    }
}

fn dot(a: &P3, b: &P3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The window of fit points and the summary of the readings before it.
#[derive(Clone, Debug)]
pub struct FitWindow {
    points: VecDeque<FitPoint>,
    capacity: usize,
    min_spacing_s: f64,
    history: History,
}

/// Finite-difference step of the qMobile sensitivity, z units.
const DZ_Q: f64 = 1e-4;
/// Finite-difference step of the starting mole fraction's sensitivity (backward: the start may sit at a
/// full electrode).
const DX_START: f64 = 1e-4;

impl FitWindow {
    pub fn new(capacity: usize, span_s: f64) -> Self {
        let capacity = capacity.max(2);
        Self {
            points: VecDeque::with_capacity(capacity),
            capacity,
            min_spacing_s: span_s / capacity as f64,
            history: History::default(),
        }
    }

    /// Points in the window (readings summarised before it are not counted).
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Every reading the fit holds: the window's bins and the summarised ones.
    pub fn readings(&self) -> f64 {
        self.points.iter().map(|p| p.weight).sum::<f64>() + self.history.m
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn points(&self) -> impl Iterator<Item = &FitPoint> {
        self.points.iter()
    }

    /// Adds the newest reading: it joins the last bin while that bin spans less than the spacing, else it
    /// opens a new one. A bin that leaves is summarised at the estimate `d` (z units over `ranges`) and the
    /// cell's starting charge.
    pub fn push(&mut self, p: FitPoint, cell: &CellModel, d: &Degradation, ranges: &[[f64; 2]; 2]) {
        let n = self.points.len();
        let leaving = if n >= 1 && p.t_s - self.points[n - 1].first_t_s < self.min_spacing_s {
            self.points[n - 1].absorb(&p);
            None
        } else {
            let out = if n == self.capacity { self.points.pop_front() } else { None };
            self.points.push_back(p);
            out
        };
        if let Some(old) = leaving {
            let (r, j) = residual_and_sensitivity(&old, cell, d, ranges, true);
            let p = params_of(d, ranges, cell);
            let a = r + dot(&j, &p);
            let (h, w) = (&mut self.history, old.weight);
            for i in 0..3 {
                for k in 0..3 {
                    h.a[i][k] += w * j[i] * j[k];
                }
                h.b[i] += w * a * j[i];
            }
            h.c += w * a * a;
            h.m += w;
        }
    }

    /// Root mean square residual over every reading under `d`, V (0 before any).
    pub fn rms_v(&self, cell: &CellModel, d: &Degradation, ranges: &[[f64; 2]; 2]) -> f64 {
        let total = self.readings();
        if total == 0.0 {
            return 0.0;
        }
        let window: f64 =
            self.points.iter().map(|p| p.weight * (p.voltage_v - cell.voltage_at(&p.track, d)).powi(2)).sum();
        ((window + self.history.sum_sq(params_of(d, ranges, cell))) / total).sqrt()
    }

    /// The least-squares statistics over every reading at `d` and the cell's starting charge; `ranges`
    /// scale the parameters to z. A Gaussian prior (mean `prior_z`, standard deviation `prior_std_z`,
    /// weighed as `noise_v` of sensor noise) damps the step while the readings cannot tell the parameters
    /// apart yet. With `start` the starting charge's uncertainty enters the information, and the start is
    /// fitted too where it moves; without, it is exact.
    pub fn stats(
        &self,
        cell: &CellModel,
        d: &Degradation,
        ranges: &[[f64; 2]; 2],
        prior: Option<([f64; 2], f64, f64)>,
        start: Option<StartPrior>,
    ) -> FitStats {
        let total = self.readings();
        if total == 0.0 {
            return FitStats::default();
        }
        let pz = params_of(d, ranges, cell);
        let fit_start = start.is_some();
        let (mut sq, mut g, mut h) = (0.0, [0.0; 3], [[0.0; 3]; 3]);
        for p in &self.points {
            let (r, j) = residual_and_sensitivity(p, cell, d, ranges, fit_start);
            let w = p.weight;
            sq += w * r * r;
            for i in 0..3 {
                g[i] += w * r * j[i];
                for k in 0..3 {
                    h[i][k] += w * j[i] * j[k];
                }
            }
        }
        // The summarised readings: residual sum of squares c - 2 b.p + p'Ap, gradient of its half b - A p.
        let hs = &self.history;
        sq += hs.sum_sq(pz);
        for i in 0..3 {
            g[i] += hs.b[i] - dot(&hs.a[i], &pz);
            for (hk, ak) in h[i].iter_mut().zip(hs.a[i]) {
                *hk += ak;
            }
        }
        let inv = 1.0 / total;
        let g = g.map(|x| x * inv);
        let h = h.map(|row| row.map(|x| x * inv));
        // The step: damped Gauss-Newton on the mean squared residual plus the priors' terms.
        let (mut m, mut gm) = (h, g);
        let mut sq_map = sq;
        if let Some((prior_z, sd, noise_v)) = prior {
            let w = (noise_v / sd).powi(2);
            for k in 0..2 {
                m[k][k] += w * inv;
                gm[k] += w * inv * (prior_z[k] - pz[k]);
                sq_map += w * (pz[k] - prior_z[k]).powi(2);
            }
        }
        // The start's prior counts in its information too: it is what the rest readings said.
        let mut h_start = h[2][2];
        if let Some(s) = start {
            let w = (s.noise_v / s.std).powi(2);
            m[2][2] += w * inv;
            h_start += w * inv;
            gm[2] += w * inv * (s.xn - pz[2]);
            sq_map += w * (pz[2] - s.xn).powi(2);
        }
        // Levenberg damping relative to the information, so a parameter the readings cannot see stays put.
        let mu = 1e-3 * (m[0][0] + m[1][1]) + 1e-12;
        m[0][0] += mu;
        m[1][1] += mu;
        // qMobile and Ro's information whatever the start: the Schur complement of the start's.
        let info = if fit_start {
            let s = h_start.max(1e-300);
            [h[0][0] - h[0][2] * h[2][0] / s, h[0][1] - h[0][2] * h[2][1] / s, h[1][1] - h[1][2] * h[2][1] / s]
        } else {
            [h[0][0], h[0][1], h[1][1]]
        };
        let (step, step_start) = if start.is_some_and(|s| s.moves) {
            m[2][2] += 1e-3 * m[2][2] + 1e-12;
            let sol = solve3(&m, &gm).unwrap_or([0.0; 3]);
            ([sol[0], sol[1]], gm[2] / m[2][2])
        } else {
            let (a, b, c) = (m[0][0], m[0][1], m[1][1]);
            let det = a * c - b * b;
            let step =
                if det > 0.0 { [(c * gm[0] - b * gm[1]) / det, (a * gm[1] - b * gm[0]) / det] } else { [0.0; 2] };
            (step, 0.0)
        };
        FitStats {
            n: total.round() as usize,
            rms_v: (sq * inv).max(0.0).sqrt(),
            map_rms_v: (sq_map * inv).max(0.0).sqrt(),
            grad: [g[0], g[1]],
            info,
            step,
            step_start,
        }
    }
}

/// The fit's unknowns at `d` and the cell's starting charge.
fn params_of(d: &Degradation, ranges: &[[f64; 2]; 2], cell: &CellModel) -> P3 {
    [
        (d.q_mobile_c - ranges[0][0]) / (ranges[0][1] - ranges[0][0]),
        (d.r_o_ohm - ranges[1][0]) / (ranges[1][1] - ranges[1][0]),
        cell.xn0,
    ]
}

/// The solution of the symmetric positive-definite system `m x = g` (Cholesky), None when `m` is not.
fn solve3(m: &[[f64; 3]; 3], g: &P3) -> Option<P3> {
    let mat = nalgebra::Matrix3::from_fn(|i, k| m[i][k]);
    let x = mat.cholesky()?.solve(&nalgebra::Vector3::from_column_slice(g));
    Some([x[0], x[1], x[2]])
}

/// Residual (measured minus predicted, V) and sensitivity dV/dp of one point at `d`: qMobile and the
/// starting mole fraction (when `with_start`; else 0) by finite differences, Ro exactly (V has -Ro * lag).
fn residual_and_sensitivity(
    p: &FitPoint,
    cell: &CellModel,
    d: &Degradation,
    ranges: &[[f64; 2]; 2],
    with_start: bool,
) -> (f64, P3) {
    let v = cell.voltage_at(&p.track, d);
    let mut dq = *d;
    Param::QMobile.set(&mut dq, d.q_mobile_c + DZ_Q * (ranges[0][1] - ranges[0][0]));
    let jq = (cell.voltage_at(&p.track, &dq) - v) / DZ_Q;
    let jr = -p.track.current_lag_a * (ranges[1][1] - ranges[1][0]);
    let jx = if with_start { (v - cell.voltage_from(cell.xn0 - DX_START, &p.track, d)) / DX_START } else { 0.0 };
    (p.voltage_v - v, [jq, jr, jx])
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::battery::BatteryModel;

    fn cell() -> CellModel {
        let m = BatteryModel::default();
        let t = m.params.tb0_k;
        CellModel::at_rest(m, 0.55, t, 2.0)
    }

    /// 400 readings 3 s apart made by the model itself (qMobile 5600 C, Ro 0.13 ohm), the current stepping
    /// between 3 and 1 A so that Ro is visible: the truth, the ranges, the cell after them and the window.
    fn exact_readings() -> (Degradation, [[f64; 2]; 2], CellModel, FitWindow) {
        let truth = Degradation { q_mobile_c: 5600.0, r_o_ohm: 0.13 };
        let ranges = [[3500.0, 7500.0], [0.05, 0.25]];
        let mut c = cell();
        let mut w = FitWindow::new(64, 1200.0);
        let mut t = 0.0;
        for k in 0..400 {
            let i = if (k / 40) % 2 == 0 { 3.0 } else { 1.0 };
            c.advance(i, 3.0, &truth, c.track.t_k);
            t += 3.0;
            w.push(FitPoint::reading(t, c.track, c.voltage(&truth)), &c, &truth, &ranges);
        }
        (truth, ranges, c, w)
    }

    /// Readings made by the model itself under known parameters: the window's fit step points at them, and
    /// the residual there is zero.
    #[test]
    fn the_gauss_newton_step_points_at_the_parameters_that_made_the_readings() {
        let (truth, ranges, c, w) = exact_readings();
        // Bins span 1200 / 64 = 18.75 s: 7 readings 3 s apart each, so 400 readings fill 58 of the 64.
        assert_eq!(w.len(), 58);
        assert_eq!(w.readings(), 400.0, "every reading counts, and nothing has left the window yet");
        // Exact readings: a bin's mean state predicts its mean voltage up to the open-circuit curve's
        // curvature over the ~50 C a bin draws (tens of microvolts).
        assert!(w.rms_v(&c, &truth, &ranges) < 1e-4, "{}", w.rms_v(&c, &truth, &ranges));
        let guess = Degradation { q_mobile_c: 5400.0, r_o_ohm: 0.14 };
        let s = w.stats(&c, &guess, &ranges, None, None);
        assert!(s.rms_v > 1e-3, "a wrong guess leaves a residual: {}", s.rms_v);
        let want = [(5600.0 - 5400.0) / 4000.0, (0.13 - 0.14) / 0.2];
        for k in 0..2 {
            assert!((s.step[k] - want[k]).abs() < 0.2 * want[k].abs(), "step {:?} vs {want:?}", s.step);
        }
        // Iterating the step converges to the truth.
        let mut d = guess;
        for _ in 0..6 {
            let s = w.stats(&c, &d, &ranges, None, None);
            d.q_mobile_c += s.step[0] * 4000.0;
            d.r_o_ohm += s.step[1] * 0.2;
        }
        // Within the bins' averaging error (their mean state stands for their readings' states).
        assert!((d.q_mobile_c - 5600.0).abs() < 2.0 && (d.r_o_ohm - 0.13).abs() < 5e-5, "{d:?}");
        assert!(s.std_z(0.003).is_some());
    }

    /// Readings of a cell that started at another charge than its rest reading said: with the start held,
    /// the fit moves qMobile and Ro to explain the start's error; with the start fitted, it moves the start
    /// to the true one and leaves the true parameters where they are, and says qMobile is less certain.
    #[test]
    fn a_fitted_start_takes_the_start_error_off_qmobile() {
        let (truth, ranges, c, w) = exact_readings();
        // The calibrator's model of the same readings, started 0.03 low (about 5 % of the charge).
        let mut off = c.clone();
        off.xn0 = c.xn0 - 0.03;
        let held = w.stats(&off, &truth, &ranges, None, None);
        let start = StartPrior { xn: off.xn0, std: 0.05, noise_v: 0.003, moves: true };
        let fitted = w.stats(&off, &truth, &ranges, None, Some(start));
        assert!(held.step[0].abs() > 0.01, "a held start's error moves qMobile: {:?}", held.step);
        assert!(fitted.step[0].abs() < 0.2 * held.step[0].abs(), "fitted {:?} held {:?}", fitted.step, held.step);
        assert!((fitted.step_start - 0.03).abs() < 0.006, "start step {}", fitted.step_start);
        assert_eq!(held.step_start, 0.0);
        // A start that stays put keeps the held step and still counts its uncertainty in the information.
        let kept = w.stats(&off, &truth, &ranges, None, Some(StartPrior { moves: false, ..start }));
        assert_eq!((kept.step, kept.step_start, kept.info), (held.step, 0.0, fitted.info));
        // Profiling the start out leaves qMobile less information, never more.
        assert!(fitted.info[0] < held.info[0] && fitted.info[2] <= held.info[2] * (1.0 + 1e-12), "{fitted:?}");
        // Iterated, the start and the parameters reach the truth.
        let (mut d, mut m) = (Degradation { q_mobile_c: 5300.0, r_o_ohm: 0.15 }, off.clone());
        for _ in 0..12 {
            let s = w.stats(&m, &d, &ranges, None, Some(start));
            d.q_mobile_c += s.step[0] * 4000.0;
            d.r_o_ohm += s.step[1] * 0.2;
            m.xn0 += w.stats(&m, &d, &ranges, None, Some(start)).step_start;
        }
        assert!((d.q_mobile_c - 5600.0).abs() < 20.0 && (d.r_o_ohm - 0.13).abs() < 5e-4, "{d:?}");
        assert!((m.xn0 - c.xn0).abs() < 2e-3, "start {} vs {}", m.xn0, c.xn0);
    }

    #[test]
    fn every_reading_joins_a_bin_and_bins_keep_their_spacing() {
        let c = cell();
        let ranges = [[3500.0, 7500.0], [0.05, 0.25]];
        let d = Degradation::default();
        let mut w = FitWindow::new(4, 40.0);
        for k in 0..25 {
            w.push(FitPoint::reading(k as f64, c.track, k as f64), &c, &d, &ranges);
        }
        // 25 readings 1 s apart in bins of 10 s: [0-9], [10-19], [20-24], every reading counted.
        assert_eq!(w.readings(), 25.0);
        assert_eq!(w.len(), 3);
        // A bin's voltage is its readings' mean.
        assert_eq!(w.points().map(|p| p.voltage_v).collect::<Vec<_>>(), vec![4.5, 14.5, 22.0]);
        for k in 25..45 {
            w.push(FitPoint::reading(k as f64, c.track, k as f64), &c, &d, &ranges);
        }
        // [10-19], [20-29], [30-39], [40-44]: the bin [0-9] left the front and is summarised.
        assert_eq!(w.readings(), 45.0);
        let ts: Vec<f64> = w.points().map(|p| p.t_s).collect();
        assert_eq!(ts, vec![19.0, 29.0, 39.0, 44.0]);
        assert_eq!(w.points().map(|p| p.weight).sum::<f64>(), 35.0);
        assert!(FitStats::default().std_z(0.003).is_none());
    }
}
