//! The measured-only MDP's definition: the cells it trains and is judged on ([`ScenarioConfig`]), which
//! learned calibrator it trains ([`Design`]) and that calibrator's settings. It is part of the run config
//! and travels with every policy file; the environment that steps it lives in bcal-calib
//! (`bcal_calib::env`).

use super::scenario::ScenarioConfig;
use super::tracker::{AdaptiveRule, JointUkfSettings, TrackerSpec, OBS_DIM};
use serde::{Deserialize, Serialize};

/// Features the correction policy observes (`bcal_calib::correction`).
pub const CORRECTION_OBS_DIM: usize = 24;
/// Its largest action: a shift of each estimate and the log-scales of the parameter walk and the
/// measurement noise (the last two only with [`CorrectionSpec::noise_actions`]).
pub const CORRECTION_ACT_DIM: usize = 4;

/// Everything that defines the measured-only MDP: the cells it trains and is judged on, and the calibrator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MeasuredSpec {
    pub scenario: ScenarioConfig,
    /// The calibrator's model, ranges and prior (both designs), and the window fit's settings.
    pub tracker: TrackerSpec,
    /// Which learned calibrator trains: "ukf-correction" (default) or "window-fit" (issue 12's; run
    /// folders and policy files written before designs existed read as it).
    #[serde(default = "Design::legacy")]
    pub design: Design,
    /// The joint UKF the correction starts from. None in a config: `bcal train` tunes it on the validation
    /// cells (the same grid as the evaluator's baseline) and writes the chosen settings into the run's task,
    /// so the actors, the learner and the evaluator all run that one filter.
    pub ukf: Option<JointUkfSettings>,
    pub correction: CorrectionSpec,
    pub cost: PredictiveCost,
    /// The cell's capacity lifetime model (`bcal cell-config` writes the one `bcal calibrate` uses on judged
    /// discharges): a live stream moves what one discharge hands the next by the fade and the recovery after
    /// rest it expects ([`crate::lifetime::LifeTracker::carry`]). None: the carried value as it is. Training
    /// does not read it.
    pub lifetime: Option<crate::lifetime::LifetimeModel>,
}

impl Default for MeasuredSpec {
    fn default() -> Self {
        Self {
            scenario: ScenarioConfig::default(),
            tracker: TrackerSpec::default(),
            design: Design::UkfCorrection,
            ukf: None,
            correction: CorrectionSpec::default(),
            cost: PredictiveCost::default(),
            lifetime: None,
        }
    }
}

impl MeasuredSpec {
    pub fn obs_dim(&self) -> usize {
        match self.design {
            Design::WindowFit => OBS_DIM,
            Design::UkfCorrection => CORRECTION_OBS_DIM,
        }
    }

    pub fn act_dim(&self) -> usize {
        match self.design {
            Design::WindowFit => 2,
            Design::UkfCorrection if self.correction.noise_actions => CORRECTION_ACT_DIM,
            Design::UkfCorrection => 2,
        }
    }

    /// The joint UKF the correction runs on: the tuned one, or the defaults before tuning.
    pub fn ukf_settings(&self) -> JointUkfSettings {
        self.ukf.unwrap_or_default()
    }
}

/// Which learned calibrator the measured-only MDP trains.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Design {
    /// Issue 12's: the policy moves its tracker's estimate (or corrects its window fit's step) and pays its
    /// window's misfit, whose optimum is that fit: the policy learns to copy it.
    WindowFit,
    /// Issue 18's: the policy corrects the tuned joint UKF (a shift of its estimate in units of its standard
    /// deviation, and log-scales of its parameter walk and measurement noise); zero action is the filter.
    /// It pays the calibrated model's error at predicting what comes next ([`PredictiveCost`]).
    UkfCorrection,
}

impl Design {
    /// What a spec without the key was trained as.
    pub fn legacy() -> Self {
        Design::WindowFit
    }

    pub fn name(self) -> &'static str {
        match self {
            Design::WindowFit => "window-fit",
            Design::UkfCorrection => "ukf-correction",
        }
    }
}

/// How the correction policy's action acts on the joint UKF. Action a in [-1, 1]^2 (or ^4): the reported
/// estimate is the filter's mean plus a|a| * (`shift_max_sd` standard deviations of the filter +
/// `shift_floor_z` of the range) (the filter itself keeps its own mean: the floor lets a correction reach a
/// bias larger than the filter believes it can be, as model error makes it); with `noise_actions`, the
/// parameter walk's variance of the next steps is max(tuned, floor) * 10^(a[2] * `walk_decades`) and the
/// measurement variance the tuned one * 10^(a[3] * `meas_decades`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CorrectionSpec {
    /// Largest shift of each estimate, in the filter's standard deviations (default 2).
    pub shift_max_sd: f64,
    /// Part of the largest shift that does not shrink with the filter's spread, fraction of each range
    /// (default 0.1: 400 C of qMobile, 0.02 ohm of Ro).
    pub shift_floor_z: f64,
    /// Extra transitions per step with other actions at the same reading: the zero action (the filter) and
    /// `counterfactual_actions - 1` drawn uniformly. A shift only moves the reported estimate, not the
    /// filter, so the next observation is the same whatever the action: each is a true transition of the
    /// MDP, and together they show the critic what the action changes at one reading (default 3; 0 off;
    /// ignored with `noise_actions`, whose actions act on what comes next).
    pub counterfactual_actions: usize,
    /// Whether the policy also sets the filter's noise (actions 3 and 4). Off by default: on the validation
    /// cells no setting of the tuned filter's noise per sampling regime gains more than 1 % of its NRMSE, while
    /// the extra actions' delayed effect on the cost makes the learning noisier (docs/tuning.md).
    pub noise_actions: bool,
    /// Largest change of the parameter walk's variance, decades either way (default 2).
    pub walk_decades: f64,
    /// Largest change of the measurement variance, decades either way (default 1).
    pub meas_decades: f64,
    /// The parameter walk the scaling starts from when the tuned one is zero, z units per sqrt(s)
    /// (default 1e-6: over a 3000 s discharge a walk of 5e-5 of the range, nothing).
    pub walk_floor_per_sqrt_s: f64,
    /// Factors on the filter's standard deviations of qMobile and Ro for the 90 % interval around the
    /// corrected estimate, chosen on validation (1.645 for a Gaussian).
    pub interval_scale: [f64; 2],
    /// The covariance-matching rule that sets the filter's noise under the correction, so the policy learns
    /// on top of the adaptive UKF (on real cells the best filter); zero action is then that filter. None
    /// (default): the tuned filter's fixed noise. The rule owns the noise: not with `noise_actions`.
    pub adaptive: Option<AdaptiveRule>,
}

impl Default for CorrectionSpec {
    fn default() -> Self {
        Self {
            shift_max_sd: 2.0,
            shift_floor_z: 0.1,
            counterfactual_actions: 3,
            noise_actions: false,
            walk_decades: 2.0,
            meas_decades: 1.0,
            walk_floor_per_sqrt_s: 1e-6,
            interval_scale: [1.645, 1.645],
            adaptive: None,
        }
    }
}

/// The relative predictive cost is exp(e(corrected) - e(filter)) with the difference clamped to
/// +-RELATIVE_LOG_CLAMP: one reading's cost lies in [e^-4, e^4].
pub const RELATIVE_LOG_CLAMP: f64 = 4.0;

/// The correction policy's cost (training only): the calibrated model's error at predicting what comes
/// next. At each reading the model runs forward from the estimate chosen then (the filter's state given
/// that estimate) under the simulated cell's own load, over `horizon_s`, against the cell's own voltage
/// at the readings there; where the episode reaches the cut-off, the end of discharge it predicts joins
/// it: e = `voltage_weight` ln(1 + rms / `voltage_scale_v`) + `eod_weight` ln(1 + |EOD error| / `eod_scale_s`). With
/// `relative` (the default) the cost is exp(e(corrected) - e(filter)), clamped to e^-4..e^4: the same
/// prediction judged against the uncorrected filter's at the same reading. Its minimum is still the
/// estimate that predicts best (the filter's error does not depend on the action), but the critic no longer
/// has to learn how hard each reading is before it can see what an action changes. The true parameters
/// never enter it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PredictiveCost {
    /// How far ahead the voltage is predicted, s (default 600).
    pub horizon_s: f64,
    /// Longest Euler substep of the prediction over the horizon, s (default 2; below 2 t_o = 12.2 s for the
    /// ohmic lag).
    pub substep_s: f64,
    /// Longest Euler substep from the horizon on to the end of discharge, s (default 5).
    pub eod_substep_s: f64,
    /// Judge the corrected prediction against the filter's own (default true).
    pub relative: bool,
    /// Voltage error scale, V (default 2 mV).
    pub voltage_scale_v: f64,
    /// Weight of the voltage term (default 1; 0 leaves it out: a real cell's policy, whose choices are made
    /// on the end-of-discharge error alone, `bcal cell-config`).
    pub voltage_weight: f64,
    /// Weight of the end-of-discharge term (default 1; 0 leaves it out).
    pub eod_weight: f64,
    /// End-of-discharge error scale, s (default 30).
    pub eod_scale_s: f64,
}

impl Default for PredictiveCost {
    fn default() -> Self {
        Self {
            horizon_s: 600.0,
            substep_s: 2.0,
            eod_substep_s: 5.0,
            relative: true,
            voltage_scale_v: 0.002,
            voltage_weight: 1.0,
            eod_weight: 1.0,
            eod_scale_s: 30.0,
        }
    }
}
