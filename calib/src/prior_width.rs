//! The width of a discharge's prior, learned from a cell's own history (issue 18 item 5): the variance of
//! the change from one discharge's estimate to the next, in each parameter, modelled as `a + b h(rest)`
//! with `h(rest) = ln(max(rest, usual) / usual)` (zero after the usual rest, growing with a longer one).
//! `bcal calibrate` fits it on a cell's training fits (`bcal_realcell::prior`); a live stream on the ends of
//! the discharges it has followed ([`crate::stream`]). Pure arithmetic: nothing here reads or prints.

use serde::Serialize;

/// A day, s: the "long rest".
pub const LONG_REST_S: f64 = 86_400.0;
/// Fewest consecutive training pairs the width is fitted on; with fewer, [`RestWidth::fallback`].
pub const MIN_PAIRS: usize = 4;
/// The smallest width, z units: below the resolution of an offline fit (a few coulombs, a fraction of a
/// milliohm), a prior would claim more than the fits that make it can know.
pub const MIN_SD_Z: f64 = 1e-3;
/// The width model of the prior: per parameter (qMobile, Ro), variance `a + b h(rest)` in z^2.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RestWidth {
    /// Variance after the usual rest, z^2.
    pub a_z2: [f64; 2],
    /// Variance added per unit of `h(rest)`, z^2.
    pub b_z2: [f64; 2],
    /// The usual rest (median of the training rests), s; 0 when no rest is known.
    pub usual_rest_s: f64,
    /// The consecutive training pairs it was fitted on, and how many of them followed a rest of more than
    /// a day.
    pub pairs: usize,
    pub long_rest_pairs: usize,
}

impl RestWidth {
    /// The width without a history: the calibrator's own setting decides.
    pub fn fallback() -> Self {
        Self { a_z2: [f64::NAN; 2], b_z2: [0.0; 2], usual_rest_s: 0.0, pairs: 0, long_rest_pairs: 0 }
    }

    pub fn fitted(&self) -> bool {
        self.a_z2.iter().all(|a| a.is_finite())
    }

    /// `h(rest)`: zero at or below the usual rest, the log of the ratio above it.
    pub fn h(&self, rest_s: Option<f64>) -> f64 {
        match rest_s {
            Some(r) if self.usual_rest_s > 0.0 && r > self.usual_rest_s => (r / self.usual_rest_s).ln(),
            _ => 0.0,
        }
    }

    /// The standard deviation of each parameter after a rest of `rest_s` and `gap` discharges since the
    /// fit it starts from (the per-discharge variance adds up over a gap), z units.
    pub fn sd_z(&self, rest_s: Option<f64>, gap: u32) -> [f64; 2] {
        let h = self.h(rest_s);
        std::array::from_fn(|k| (self.a_z2[k] * f64::from(gap.max(1)) + self.b_z2[k] * h).sqrt().max(MIN_SD_Z))
    }

    /// Least squares of `e^2 = a + b h` with a, b >= 0 over `(h, residual)` pairs, per parameter.
    pub fn fit(residuals: &[(f64, [f64; 2])], usual_rest_s: f64, long_rest_pairs: usize) -> Self {
        if residuals.len() < MIN_PAIRS {
            return Self { usual_rest_s, pairs: residuals.len(), long_rest_pairs, ..Self::fallback() };
        }
        let n = residuals.len() as f64;
        let mut a_z2 = [0.0; 2];
        let mut b_z2 = [0.0; 2];
        for k in 0..2 {
            let pts: Vec<(f64, f64)> = residuals.iter().map(|(h, e)| (*h, e[k] * e[k])).collect();
            let (mh, my) = (pts.iter().map(|p| p.0).sum::<f64>() / n, pts.iter().map(|p| p.1).sum::<f64>() / n);
            let shh: f64 = pts.iter().map(|p| (p.0 - mh).powi(2)).sum();
            let shy: f64 = pts.iter().map(|p| (p.0 - mh) * (p.1 - my)).sum();
            let (mut a, mut b) = if shh > 1e-12 { (my - shy / shh * mh, shy / shh) } else { (my, 0.0) };
            if b < 0.0 {
                // Longer rests did not spread the fits more: one variance for all.
                (a, b) = (my, 0.0);
            }
            if a < 0.0 {
                // The usual rest's variance cannot be negative: through the origin.
                let shh0: f64 = pts.iter().map(|p| p.0 * p.0).sum();
                (a, b) = (0.0, if shh0 > 0.0 { pts.iter().map(|p| p.0 * p.1).sum::<f64>() / shh0 } else { 0.0 });
            }
            a_z2[k] = a;
            b_z2[k] = b;
        }
        Self { a_z2, b_z2, usual_rest_s, pairs: residuals.len(), long_rest_pairs }
    }
}

/// Fewest pairs that moved their current by more than [`MOVED_RATIO`] for [`CurrentSlope`] to be learned (the
/// twins by current take as many, [`crate::recentre`]).
pub const MIN_MOVED_PAIRS: usize = 3;
/// A current this many times the last discharge's, or its inverse, moved.
pub const MOVED_RATIO: f64 = 1.2;

/// The log of the ratio of a discharge's load-on current to the last one's ([`CurrentSlope`]'s x), None unless
/// both are above 0.
pub fn current_move(now_a: f64, before_a: f64) -> Option<f64> {
    (now_a > 0.0 && before_a > 0.0).then(|| (now_a / before_a).ln())
}

/// How the end fit a discharge hands on moves with the current (issue 18, "across discharges"): on a cell
/// cycled at several currents the qMobile that puts the model's end at the measured one holds the model's error
/// at that current (the blind "B0038" of `examples/blind/progpy_cells.py` fits 1.3 % above its qMobile at 1 A,
/// 0.2 % at 4 A), so a discharge at another current than the last one's starts off by that much. The slope of
/// the log of each carried fit over its prior mean (the lifetime model's move alone) against the log of the
/// ratio of its first loaded reading's current to the last discharge's, least squares through the origin over
/// the consecutive pairs that measured their charge, as they end (no look-ahead; `bcal_realcell::prior`'s walk,
/// a live stream's own discharges in [`crate::stream`]); none (no move) until [`MIN_MOVED_PAIRS`] of them moved
/// by more than [`MOVED_RATIO`], so a cell at one current keeps every prior to the bit. A stream chooses the
/// prior again at the load-on (the rest before it says nothing of qMobile; its readings are read again);
/// `bcal calibrate` starts the discharge from the moved prior.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct CurrentSlope {
    sxy: f64,
    sxx: f64,
    /// Pairs observed, and how many of them moved their current.
    pub pairs: usize,
    pub moved: usize,
}

impl CurrentSlope {
    /// Adds a pair: `x` the log of the ratio of the currents, `y` the log of the carried fit over the prior mean.
    pub fn push(&mut self, x: f64, y: f64) {
        if x.is_finite() && y.is_finite() {
            self.sxy += x * y;
            self.sxx += x * x;
            self.pairs += 1;
            self.moved += usize::from(x.abs() > MOVED_RATIO.ln());
        }
    }

    /// `q_mobile_c` moved by the learned slope for a move of the load-on current from `before_a` to `now_a`
    /// (None: no slope yet, or a current not above 0): the one rule `bcal calibrate`'s walk and a live stream
    /// move a carried prior by.
    pub fn moved(&self, q_mobile_c: f64, now_a: f64, before_a: f64) -> Option<f64> {
        Some(q_mobile_c * (self.learned()? * current_move(now_a, before_a)?).exp())
    }

    /// The slope, per unit of the log of the current's ratio (None: too few moves yet).
    pub fn learned(&self) -> Option<f64> {
        (self.moved >= MIN_MOVED_PAIRS && self.sxx > 0.0).then(|| self.sxy / self.sxx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_width_grows_with_the_rest_when_long_rests_spread_the_fits() {
        // Residuals of 0.01 z after usual rests, 0.05 z after rests e^2 times the usual one.
        let mut res: Vec<(f64, [f64; 2])> =
            (0..20).map(|k| (0.0, [0.01 * if k % 2 == 0 { 1.0 } else { -1.0 }; 2])).collect();
        res.extend((0..4).map(|k| (2.0, [0.05 * if k % 2 == 0 { 1.0 } else { -1.0 }, 0.01])));
        let w = RestWidth::fit(&res, 3600.0, 4);
        assert!(w.fitted());
        let usual = w.sd_z(Some(3600.0), 1);
        let long = w.sd_z(Some(3600.0 * 2f64.exp()), 1);
        assert!((usual[0] - 0.01).abs() < 2e-3, "{usual:?}");
        assert!((long[0] - 0.05).abs() < 5e-3, "{long:?}");
        // Ro's residuals do not grow with the rest: the same width after any rest.
        assert!((long[1] - usual[1]).abs() < 1e-12 && (usual[1] - 0.01).abs() < 1e-3, "{usual:?} {long:?}");
        // A gap of four discharges adds four discharges' variance.
        assert!((w.sd_z(Some(3600.0), 4)[1] - 2.0 * usual[1]).abs() < 1e-9);
        // Too few pairs: no width.
        assert!(!RestWidth::fit(&res[..3], 3600.0, 0).fitted());
    }
}
