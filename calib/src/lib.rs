//! bcal-calib: every calibrator that reads a cell as a BMS does, behind one [`Calibrator`] trait, so the
//! same code serves the simulator (the evaluator, with the truth known), the RL actors (which learn on top of
//! the joint UKF), real data (`bcal calibrate`), `bcal bench` and the Python package: a reading in; the
//! parameter estimate, its 90 % interval and the calibrated model state out.
//!
//! - [`tracker`] and [`window`]: the calibrator's own model with its least-squares view of the readings;
//!   [`tracker_based`]: the RL policy on it, the window fit alone and the uncalibrated (pinned) model;
//! - [`joint_ukf`]: the joint unscented Kalman filter over the model's states and both parameters;
//!   [`adaptive`]: the same filter with its noise adapted by a fixed rule (covariance matching);
//!   [`correction`]: the learned correction on top of it (the RL calibrator of issue 18), trained on the
//!   predictive cost of [`cost`];
//! - [`direct`]: the direct mapping's inference (a network trained elsewhere on true parameters);
//! - [`eod`]: end-of-discharge prediction from a calibrated state; [`env`]: the RL environment and the
//!   rollouts the learner's validation and the evaluator share; [`tune`]: choices made on validation cells;
//!   [`stream`]: one calibrator on live readings (`bcal calibrate --follow`, the Python package);
//!   [`prior_width`] and [`widening`]: a discharge's prior width and its prediction intervals, learned from
//!   the discharges before it (for `bcal calibrate` and a live stream alike); [`record_learner`]: a learner
//!   on a calibrator's errors across discharges (`bcal calibrate`); [`end_fit`]: the qMobile a
//!   discharge's measured end gives, which a live stream hands on.
//!
//! No libtorch here (the learner and the direct mapping's training own it), and nothing prints.

pub mod adaptive;
pub mod blend;
pub mod correction;
pub mod cost;
pub mod direct;
pub mod end_fit;
pub mod env;
pub mod eod;
pub mod joint_ukf;
pub mod prior_width;
pub mod recentre;
pub mod record_learner;
pub mod rescue;
pub mod stream;
pub mod tracker;
pub mod tracker_based;
pub mod tune;
pub mod widening;
pub mod window;

pub use adaptive::{AdaptiveRule, AdaptiveUkf, CovarianceMatching};
pub use bcal_common::measured::LoadMean;
pub use correction::{Correction, CorrectionCalibrator};
pub use eod::{predict_eod, predict_eod_s, EodPrediction, EodQuery};
pub use joint_ukf::{JointUkf, JointUkfSettings};
pub use tracker::Tracker;
pub use tracker_based::{tracker_state, RlCalibrator, Uncalibrated, WindowFitCalibrator};

use bcal_common::battery::Degradation;
use bcal_common::math::ModelState;
use bcal_common::measured::scenario::Sample;
use serde::{Deserialize, Serialize};

/// A calibrator fed one reading at a time, in time order, with no look-ahead.
pub trait Calibrator {
    /// Takes the next reading.
    fn step(&mut self, s: &Sample);
    /// The current estimate.
    fn estimate(&self) -> Degradation;
    /// The 90 % interval of the estimate (None while the calibrator cannot tell).
    fn interval(&self) -> Option<Interval>;
    /// The calibrated model state now (for end-of-discharge predictions); None before the first reading.
    fn state(&self) -> Option<ModelState>;
    /// The model state now as it would be under parameters `d` (the bounds of an interval): a calibrator
    /// that keeps its state consistent with any parameters rebuilds it; others give their own state.
    fn state_under(&self, _d: &Degradation) -> Option<ModelState> {
        self.state()
    }
}

/// A 90 % interval per parameter.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    pub q_mobile_c: [f64; 2],
    pub r_o_ohm: [f64; 2],
}
