//! One Cholesky rescue and one counter type for every unscented filter (the paper-setting UKF in bcal-eval,
//! the joint and adaptive UKFs here): a failed factorisation is a handled `None`, never unchecked, and every
//! rescue is counted, never hidden.

use nalgebra::{Cholesky, SMatrix};
use serde::{Deserialize, Serialize};

/// Cholesky retries with diagonal jitter before the covariance is reset to P0.
const JITTER_TRIES: usize = 3;

/// Counts of the numerical rescues of one run (reported, never hidden).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct UkfCounters {
    /// Steps whose sigma-point covariance needed diagonal jitter to factorise.
    pub jittered: u64,
    /// Steps where even jitter failed and the covariance was reset to P0.
    pub covariance_resets: u64,
    /// Updates skipped: innovation covariance not positive definite or a non-finite prediction.
    pub skipped_updates: u64,
}

/// Lower Cholesky factor of the covariance `p`: as it is, else with diagonal jitter growing from
/// `jitter0` times its mean variance (the jittered `p` is kept), else after resetting `p` to `p0`; `None`
/// only when even that fails. Every rescue is counted.
pub fn sqrt_or_rescue<const M: usize>(
    p: &mut SMatrix<f64, M, M>,
    p0: &SMatrix<f64, M, M>,
    jitter0: f64,
    counters: &mut UkfCounters,
) -> Option<SMatrix<f64, M, M>> {
    if let Some(c) = Cholesky::new(*p) {
        return Some(c.l());
    }
    let scale = (p.trace().abs() / M as f64).max(1e-18);
    let mut jitter = jitter0 * scale;
    for _ in 0..JITTER_TRIES {
        let pj = *p + SMatrix::<f64, M, M>::identity() * jitter;
        if let Some(c) = Cholesky::new(pj) {
            counters.jittered += 1;
            *p = pj;
            return Some(c.l());
        }
        jitter *= 1e3;
    }
    counters.covariance_resets += 1;
    *p = *p0;
    Cholesky::new(*p).map(|c| c.l())
}

impl UkfCounters {
    pub fn add(&mut self, o: &UkfCounters) {
        self.jittered += o.jittered;
        self.covariance_resets += o.covariance_resets;
        self.skipped_updates += o.skipped_updates;
    }
}
