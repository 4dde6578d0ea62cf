//! What defines a measured-only calibrator apart from its weights: [`TrackerSpec`] (ranges, prior, action
//! scaling, fit window, cost scale, interval scales, the calibrator's model), which travels with the policy
//! file and lives in the run config. The calibrators themselves (the tracker that reads one sample at a
//! time, the RL policy, the joint UKF, the window fit) live in bcal-calib; this module holds only the
//! settings every process reads.

use super::extension::ModelExtension;
use crate::battery::Degradation;
use serde::{Deserialize, Serialize};

/// Features of the tracker's observation (bcal-calib).
pub const OBS_DIM: usize = 24;

/// Everything that defines the calibrator apart from the policy weights; travels with the policy file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerSpec {
    /// Estimate ranges, qMobile C and Ro ohm; the estimate is clamped inside, and z in [0, 1] spans them.
    pub q_mobile_range_c: [f64; 2],
    pub r_o_range_ohm: [f64; 2],
    /// The estimate before any reading (the prior), C and ohm.
    pub prior: Degradation,
    /// Largest change of each estimate per reading, fraction of its range (the action's scale).
    pub step_max: f64,
    /// What the policy's action is: "absolute" (the move itself, in units of `step_max`) or "residual" (a
    /// correction added to the window fit's own Gauss-Newton step, the sum limited to `step_max`): with
    /// "residual" a zero action is the window fit, and the policy learns where to depart from it.
    pub action: ActionMode,
    /// Points of the fit window and the time they span, s (earlier readings are summarised).
    pub window_points: usize,
    pub window_span_s: f64,
    /// Standard deviation of the prior around `prior`, in fractions of each range: it damps the fit's step
    /// while the readings cannot tell the parameters apart (as the joint UKF's prior does).
    pub prior_std_z: f64,
    /// Longest Euler substep of the calibrator's model, s (the reference model's 1 s; below 2 t_o = 12.2 s
    /// for stability).
    pub max_substep_s: f64,
    /// Readings less than this after the last reading before a load switch of unknown time (between
    /// readings farther apart than a model step) are left out of the fit, s: until then the ohmic lag
    /// (t_o = 6.1 s) still holds part of i Ro that depends on when the switch came. 5 t_o, as the doctor's
    /// settle window; 1 s readings are exact and never wait.
    pub settle_s: f64,
    /// Scale of the cost ln(1 + rms / cost_scale_v), V: the log keeps residuals from the sensor noise
    /// (3 mV) to a wrong estimate's hundreds of mV within one order, so the critic resolves both.
    pub cost_scale_v: f64,
    /// Residual floor of the intervals' width, V (the sensor's noise).
    pub noise_floor_v: f64,
    /// The window fit weighs the starting charge with its uncertainty (the joint UKF's, from the rest
    /// voltage) instead of holding the rest reading's value as exact: the uncertainty widens the fit's
    /// information and interval, and a start no rest was read for (the first reading under load) is fitted
    /// with the parameters. Policies written before it held the start as exact, and read as such.
    #[serde(default = "legacy_fit_start")]
    pub fit_start: bool,
    /// Factors on the fit's standard deviations of qMobile and Ro for their 90 % intervals, chosen on
    /// validation (1.645 for a Gaussian fit with independent residuals).
    pub interval_scale: [f64; 2],
    /// The model runs at the measured temperature (thermal cells) instead of its isothermal 292.1 K.
    pub use_measured_temperature: bool,
    /// Cut-off voltage of end-of-discharge predictions, V.
    pub cutoff_v: f64,
    /// The calibrator's model: the base one, or the doctor's extended one (`bcal calibrate --model`).
    pub model: ModelExtension,
}

impl Default for TrackerSpec {
    fn default() -> Self {
        Self {
            q_mobile_range_c: [3500.0, 7500.0],
            r_o_range_ohm: [0.05, 0.25],
            // The middle of the data ranges: the only prior a calibrator may take from them.
            prior: Degradation { q_mobile_c: 5500.0, r_o_ohm: 0.15 },
            step_max: 0.05,
            // Chosen on the validation cells (300 s runs, seed 1, best policy by validation tracking error):
            // residual 1.3746 (NRMSE q / Ro 11.2 / 5.7 %), absolute 1.3715 (11.6 / 6.0 %); the label-free
            // score ties, the NRMSE favours residual. docs/tuning.md.
            action: ActionMode::Residual,
            // Chosen on the validation episodes (the window-fit calibrator alone, all readings, NRMSE q / Ro):
            // 48 points over 900 s 16.8 / 6.4 %, 64 over 1800 s 17.7 / 6.9 %, 96 over 3600 s 13.4 / 6.3 %.
            window_points: 96,
            window_span_s: 3600.0,
            prior_std_z: 0.25,
            max_substep_s: 1.0,
            settle_s: 30.0,
            cost_scale_v: 0.001,
            noise_floor_v: 0.003,
            fit_start: true,
            interval_scale: [1.645, 1.645],
            use_measured_temperature: false,
            cutoff_v: 3.0,
            model: ModelExtension::default(),
        }
    }
}

/// What a tracker spec written before `fit_start` existed did: hold the start.
fn legacy_fit_start() -> bool {
    false
}

impl TrackerSpec {
    pub fn ranges(&self) -> [[f64; 2]; 2] {
        [self.q_mobile_range_c, self.r_o_range_ohm]
    }

    /// `d` in z units ([0, 1] over the ranges).
    pub fn to_z(&self, d: &Degradation) -> [f64; 2] {
        let z = |v: f64, [lo, hi]: [f64; 2]| (v - lo) / (hi - lo);
        [z(d.q_mobile_c, self.q_mobile_range_c), z(d.r_o_ohm, self.r_o_range_ohm)]
    }

    pub fn from_z(&self, z: [f64; 2]) -> Degradation {
        let v = |z: f64, [lo, hi]: [f64; 2]| lo + z.clamp(0.0, 1.0) * (hi - lo);
        Degradation { q_mobile_c: v(z[0], self.q_mobile_range_c), r_o_ohm: v(z[1], self.r_o_range_ohm) }
    }
}

/// How the policy's action moves the estimate (see [`TrackerSpec::action`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ActionMode {
    Absolute,
    Residual,
}

/// Every setting of the joint filter; `bcal_calib::tune` picks them on validation (the joint UKF lives in bcal-calib; its
/// settings live here, with the rest of the config).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointUkfSettings {
    /// Measurement noise standard deviation, V.
    pub meas_std_v: f64,
    /// Random walk of each parameter per sqrt(second), z units.
    pub param_walk_per_sqrt_s: f64,
    /// Process noise of the charge states per sqrt(second), C.
    pub charge_walk_c_per_sqrt_s: f64,
    /// Process noise of the overpotential states per sqrt(second), V.
    pub voltage_walk_v_per_sqrt_s: f64,
    /// Prior standard deviations of qMobile and Ro, z units (the prototype: 1000 C and 0.03 ohm).
    pub prior_std_z: [f64; 2],
    /// Merwe sigma-point spread.
    pub alpha: f64,
}

impl Default for JointUkfSettings {
    fn default() -> Self {
        Self {
            meas_std_v: 0.003,
            param_walk_per_sqrt_s: 1e-5,
            charge_walk_c_per_sqrt_s: 0.05,
            voltage_walk_v_per_sqrt_s: 1e-4,
            prior_std_z: [0.25, 0.15],
            alpha: 0.5,
        }
    }
}

/// The covariance-matching rule of the adaptive joint UKF (issue 18, item 3; `bcal_calib::adaptive` runs it):
/// the filter's measurement variance, and with `adapt_walk` its parameter walk, follow its own innovations.
/// It lives here because the correction policy may run on top of it ([`crate::measured::env::CorrectionSpec`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdaptiveRule {
    /// Readings the innovation averages span (exponential weights 1/n), at least 1.
    pub window_readings: f64,
    /// Bounds of the measurement variance as factors of the tuned one.
    pub meas_scale_range: [f64; 2],
    /// Whether the parameters' random walk adapts too.
    pub adapt_walk: bool,
    /// Largest random-walk variance of a parameter, z^2 per second.
    pub walk_max_var_per_s: f64,
}

impl Default for AdaptiveRule {
    fn default() -> Self {
        Self { window_readings: 32.0, meas_scale_range: [0.25, 100.0], adapt_walk: true, walk_max_var_per_s: 1e-6 }
    }
}

impl AdaptiveRule {
    /// Why the rule cannot run, naming the field, or None.
    pub fn check(&self) -> Option<(&'static str, String, &'static str)> {
        let [lo, hi] = self.meas_scale_range;
        if !(self.window_readings.is_finite() && self.window_readings >= 1.0) {
            return Some(("window_readings", self.window_readings.to_string(), "must be at least 1 reading"));
        }
        if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && lo <= hi) {
            return Some(("meas_scale_range", format!("{:?}", self.meas_scale_range), "must be 0 < low <= high"));
        }
        if !(self.walk_max_var_per_s.is_finite() && self.walk_max_var_per_s >= 0.0) {
            return Some(("walk_max_var_per_s", self.walk_max_var_per_s.to_string(), "must be finite and >= 0"));
        }
        None
    }
}
