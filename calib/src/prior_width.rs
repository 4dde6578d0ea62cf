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
