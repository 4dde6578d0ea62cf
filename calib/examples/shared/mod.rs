//! What the analysis examples behind docs/calibrator.md share (`#[path = "shared/mod.rs"] mod shared;`).
#![allow(dead_code)] // each example uses part of it

pub mod posterior;

use bcal_common::measured::scenario::Episode;
use bcal_common::measured::tracker::JointUkfSettings;

/// The joint UKF the analyses correct: the evaluator's tuned one at 3 mV on the default setting.
pub fn tuned_ukf() -> JointUkfSettings {
    JointUkfSettings {
        meas_std_v: 0.005,
        param_walk_per_sqrt_s: 0.0,
        charge_walk_c_per_sqrt_s: 0.01,
        ..Default::default()
    }
}

/// A cell's sampling regime, as the reports split them.
pub fn regime(e: &Episode) -> &'static str {
    if e.spec.interval_s[0] == 1.0 {
        "1s"
    } else {
        "10-20s"
    }
}
