//! The paper's Table-1 metric in one place: each degradation parameter scaled to [0, 1] by its data range
//! (qMobile 4000..7000 C, Ro 0.1..0.2 ohm), and the normalised RMSE in % over estimates. The UKF tracks
//! parameters in the same scaled units, and every report's parameter error is in % of the same ranges.

use crate::battery::Degradation;

/// Table-1 range of qMobile, C.
pub const RANGE_Q_MOBILE_C: [f64; 2] = [4000.0, 7000.0];
/// Table-1 range of Ro, ohm.
pub const RANGE_R_O_OHM: [f64; 2] = [0.1, 0.2];

/// One degradation parameter.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Param {
    QMobile,
    ROhm,
}

impl Param {
    pub const BOTH: [Param; 2] = [Param::QMobile, Param::ROhm];

    /// JSON key.
    pub fn key(self) -> &'static str {
        match self {
            Param::QMobile => "q_mobile",
            Param::ROhm => "r_o",
        }
    }

    /// Name as the paper's tables write it.
    pub fn label(self) -> &'static str {
        match self {
            Param::QMobile => "qMobile (Qmax)",
            Param::ROhm => "Ro",
        }
    }

    pub fn unit(self) -> &'static str {
        match self {
            Param::QMobile => "C",
            Param::ROhm => "ohm",
        }
    }

    pub fn value(self, d: &Degradation) -> f64 {
        match self {
            Param::QMobile => d.q_mobile_c,
            Param::ROhm => d.r_o_ohm,
        }
    }

    pub fn set(self, d: &mut Degradation, v: f64) {
        match self {
            Param::QMobile => d.q_mobile_c = v,
            Param::ROhm => d.r_o_ohm = v,
        }
    }

    /// The Table-1 range of the parameter.
    pub fn range(self) -> [f64; 2] {
        match self {
            Param::QMobile => RANGE_Q_MOBILE_C,
            Param::ROhm => RANGE_R_O_OHM,
        }
    }

    /// `v` in [0, 1] units of the range.
    #[inline]
    pub fn normalise(self, v: f64) -> f64 {
        let [lo, hi] = self.range();
        (v - lo) / (hi - lo)
    }

    /// Inverse of [`Self::normalise`].
    #[inline]
    pub fn denormalise(self, z: f64) -> f64 {
        let [lo, hi] = self.range();
        lo + z * (hi - lo)
    }

    /// Signed error of `est` against `truth` in % of the range.
    #[inline]
    pub fn err_pct(self, est: &Degradation, truth: &Degradation) -> f64 {
        100.0 * (self.normalise(self.value(est)) - self.normalise(self.value(truth)))
    }
}

/// Accumulates squared normalised parameter errors over steps (Table 1's metric).
#[derive(Clone, Debug, Default)]
pub struct NrmseAccumulator {
    pub n: u64,
    pub sq_q_mobile: f64,
    pub sq_r_o: f64,
}

impl NrmseAccumulator {
    #[inline]
    pub fn add(&mut self, estimate: &Degradation, truth: &Degradation) {
        let eq = Param::QMobile.err_pct(estimate, truth) / 100.0;
        let er = Param::ROhm.err_pct(estimate, truth) / 100.0;
        self.n += 1;
        self.sq_q_mobile += eq * eq;
        self.sq_r_o += er * er;
    }

    /// Adds another accumulator's sums (accumulators filled in parallel).
    pub fn merge(&mut self, o: &NrmseAccumulator) {
        self.n += o.n;
        self.sq_q_mobile += o.sq_q_mobile;
        self.sq_r_o += o.sq_r_o;
    }

    /// (qMobile, Ro) normalised RMSE in %.
    pub fn pct(&self) -> (f64, f64) {
        let n = self.n.max(1) as f64;
        (100.0 * (self.sq_q_mobile / n).sqrt(), 100.0 * (self.sq_r_o / n).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_are_in_percent_of_the_table_1_ranges() {
        let truth = Degradation { q_mobile_c: 5000.0, r_o_ohm: 0.15 };
        let est = Degradation { q_mobile_c: 5300.0, r_o_ohm: 0.14 };
        assert!((Param::QMobile.err_pct(&est, &truth) - 10.0).abs() < 1e-9);
        assert!((Param::ROhm.err_pct(&est, &truth) + 10.0).abs() < 1e-9);
        for p in Param::BOTH {
            assert!((p.denormalise(p.normalise(1234.5)) - 1234.5).abs() < 1e-9);
        }
        let mut acc = NrmseAccumulator::default();
        acc.add(&est, &truth);
        acc.add(&truth, &truth);
        let (q, r) = acc.pct();
        assert!((q - 10.0 / 2f64.sqrt()).abs() < 1e-9 && (r - 10.0 / 2f64.sqrt()).abs() < 1e-9);
    }
}
