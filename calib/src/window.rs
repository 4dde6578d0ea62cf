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
    /// Mean of J J^T (Gauss-Newton information), V^2: [qq, qr, rr].
    pub info: [f64; 3],
    /// The damped Gauss-Newton step that minimises the window's squared residual, in z units.
    pub step: [f64; 2],
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

/// Readings that left the window, as a quadratic in z: their residual sum of squares is
/// c - 2 b.z + z'Az (each residual linearised where it left: r(z) ~ a - J.z).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct History {
    /// Sum of J J' as [qq, qr, rr].
    a: [f64; 3],
    /// Sum of a J.
    b: [f64; 2],
    /// Sum of a^2.
    c: f64,
    /// Readings folded in.
    m: f64,
}

impl History {
    fn sum_sq(&self, z: [f64; 2]) -> f64 {
        let zaz = self.a[0] * z[0] * z[0] + 2.0 * self.a[1] * z[0] * z[1] + self.a[2] * z[1] * z[1];
        (self.c - 2.0 * (self.b[0] * z[0] + self.b[1] * z[1]) + zaz).max(0.0)
    }
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
    /// opens a new one. A bin that leaves is summarised at the estimate `d` (z units over `ranges`).
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
            let (r, j) = residual_and_sensitivity(&old, cell, d, ranges);
            let z = z_of(d, ranges);
            let a = r + j[0] * z[0] + j[1] * z[1];
            let (h, w) = (&mut self.history, old.weight);
            h.a[0] += w * j[0] * j[0];
            h.a[1] += w * j[0] * j[1];
            h.a[2] += w * j[1] * j[1];
            h.b[0] += w * a * j[0];
            h.b[1] += w * a * j[1];
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
        ((window + self.history.sum_sq(z_of(d, ranges))) / total).sqrt()
    }

    /// The least-squares statistics over every reading at `d`; `ranges` scale the parameters to z. A
    /// Gaussian prior (mean `prior_z`, standard deviation `prior_std_z`, weighed as `noise_v` of sensor
    /// noise) damps the step while the readings cannot tell the parameters apart yet.
    pub fn stats(
        &self,
        cell: &CellModel,
        d: &Degradation,
        ranges: &[[f64; 2]; 2],
        prior: Option<([f64; 2], f64, f64)>,
    ) -> FitStats {
        let total = self.readings();
        if total == 0.0 {
            return FitStats::default();
        }
        let z = z_of(d, ranges);
        let (mut sq, mut g, mut h) = (0.0, [0.0; 2], [0.0; 3]);
        for p in &self.points {
            let (r, j) = residual_and_sensitivity(p, cell, d, ranges);
            let w = p.weight;
            sq += w * r * r;
            g[0] += w * r * j[0];
            g[1] += w * r * j[1];
            h[0] += w * j[0] * j[0];
            h[1] += w * j[0] * j[1];
            h[2] += w * j[1] * j[1];
        }
        // The summarised readings: residual sum of squares c - 2 b.z + z'Az, gradient of its half b - A z.
        let hs = &self.history;
        sq += hs.sum_sq(z);
        g[0] += hs.b[0] - (hs.a[0] * z[0] + hs.a[1] * z[1]);
        g[1] += hs.b[1] - (hs.a[1] * z[0] + hs.a[2] * z[1]);
        for (hk, ak) in h.iter_mut().zip(hs.a) {
            *hk += ak;
        }
        let inv = 1.0 / total;
        let (g, h) = (g.map(|x| x * inv), h.map(|x| x * inv));
        // The step: damped Gauss-Newton on the mean squared residual plus the prior's term.
        let (mut a, b, mut c) = (h[0], h[1], h[2]);
        let (mut g0, mut g1) = (g[0], g[1]);
        let mut sq_map = sq;
        if let Some((pz, sd, noise_v)) = prior {
            let w = (noise_v / sd).powi(2) * inv;
            a += w;
            c += w;
            g0 += w * (pz[0] - z[0]);
            g1 += w * (pz[1] - z[1]);
            sq_map += (noise_v / sd).powi(2) * ((z[0] - pz[0]).powi(2) + (z[1] - pz[1]).powi(2));
        }
        // Levenberg damping relative to the information, so a parameter the readings cannot see stays put.
        let mu = 1e-3 * (a + c) + 1e-12;
        let (a, c) = (a + mu, c + mu);
        let det = a * c - b * b;
        let step = if det > 0.0 { [(c * g0 - b * g1) / det, (a * g1 - b * g0) / det] } else { [0.0; 2] };
        FitStats {
            n: total.round() as usize,
            rms_v: (sq * inv).max(0.0).sqrt(),
            map_rms_v: (sq_map * inv).max(0.0).sqrt(),
            grad: g,
            info: h,
            step,
        }
    }
}

fn z_of(d: &Degradation, ranges: &[[f64; 2]; 2]) -> [f64; 2] {
    [
        (d.q_mobile_c - ranges[0][0]) / (ranges[0][1] - ranges[0][0]),
        (d.r_o_ohm - ranges[1][0]) / (ranges[1][1] - ranges[1][0]),
    ]
}

/// Residual (measured minus predicted, V) and sensitivity dV/dz of one point at `d`: qMobile by a forward
/// difference, Ro exactly (V has -Ro * lag).
fn residual_and_sensitivity(
    p: &FitPoint,
    cell: &CellModel,
    d: &Degradation,
    ranges: &[[f64; 2]; 2],
) -> (f64, [f64; 2]) {
    let v = cell.voltage_at(&p.track, d);
    let mut dq = *d;
    Param::QMobile.set(&mut dq, d.q_mobile_c + DZ_Q * (ranges[0][1] - ranges[0][0]));
    let jq = (cell.voltage_at(&p.track, &dq) - v) / DZ_Q;
    let jr = -p.track.current_lag_a * (ranges[1][1] - ranges[1][0]);
    (p.voltage_v - v, [jq, jr])
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

    /// Readings made by the model itself under known parameters: the window's fit step points at them, and
    /// the residual there is zero.
    #[test]
    fn the_gauss_newton_step_points_at_the_parameters_that_made_the_readings() {
        let truth = Degradation { q_mobile_c: 5600.0, r_o_ohm: 0.13 };
        let ranges = [[3500.0, 7500.0], [0.05, 0.25]];
        let mut c = cell();
        let mut w = FitWindow::new(64, 1200.0);
        let mut t = 0.0;
        for k in 0..400 {
            // Steps between two currents so that Ro is visible.
            let i = if (k / 40) % 2 == 0 { 3.0 } else { 1.0 };
            c.advance(i, 3.0, &truth, c.track.t_k);
            t += 3.0;
            w.push(FitPoint::reading(t, c.track, c.voltage(&truth)), &c, &truth, &ranges);
        }
        // Bins span 1200 / 64 = 18.75 s: 7 readings 3 s apart each, so 400 readings fill 58 of the 64.
        assert_eq!(w.len(), 58);
        assert_eq!(w.readings(), 400.0, "every reading counts, and nothing has left the window yet");
        // Exact readings: a bin's mean state predicts its mean voltage up to the open-circuit curve's
        // curvature over the ~50 C a bin draws (tens of microvolts).
        assert!(w.rms_v(&c, &truth, &ranges) < 1e-4, "{}", w.rms_v(&c, &truth, &ranges));
        let guess = Degradation { q_mobile_c: 5400.0, r_o_ohm: 0.14 };
        let s = w.stats(&c, &guess, &ranges, None);
        assert!(s.rms_v > 1e-3, "a wrong guess leaves a residual: {}", s.rms_v);
        let want = [(5600.0 - 5400.0) / 4000.0, (0.13 - 0.14) / 0.2];
        for k in 0..2 {
            assert!((s.step[k] - want[k]).abs() < 0.2 * want[k].abs(), "step {:?} vs {want:?}", s.step);
        }
        // Iterating the step converges to the truth.
        let mut d = guess;
        for _ in 0..6 {
            let s = w.stats(&c, &d, &ranges, None);
            d.q_mobile_c += s.step[0] * 4000.0;
            d.r_o_ohm += s.step[1] * 0.2;
        }
        // Within the bins' averaging error (their mean state stands for their readings' states).
        assert!((d.q_mobile_c - 5600.0).abs() < 2.0 && (d.r_o_ohm - 0.13).abs() < 5e-5, "{d:?}");
        assert!(s.std_z(0.003).is_some());
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
