//! One calibrator on a live stream of readings, as `bcal calibrate --follow` and the Python package's
//! `bcal.Calibrator` both run it: [`resolve`] turns a kind, the cell's config, an RL policy's task and the
//! doctor's model into one [`Setup`], [`build`] makes its calibrator (the one place that does, for both),
//! and [`Stream`] checks each reading (finite numbers, a cell's voltage, time going forward) before the
//! calibrator sees it and answers with the estimate, its 90 % interval and the end of discharge predicted
//! from the calibrated state at the mean discharge current so far (no look-ahead: the current a BMS has
//! seen). A refused reading leaves the calibrator as it was, so a caller can report it and go on. Reading
//! lines, printing and Python conversion live with the callers; this never prints.
//!
//! A stream may span many discharges (a BMS's feed, or records joined end to end). A stream made with
//! [`Stream::of`] starts a new discharge after a charge (the first reading that no longer charges) or after
//! a gap of more than [`NEW_DISCHARGE_GAP_S`] without readings (the cell rested or was charged out of
//! sight): the calibrator is built anew on the same setting, and the EOD current starts over (a load of less
//! than [`MIN_DISCHARGE_S`], a spurious sample, was no discharge and hands nothing on). Its prior
//! mean is what the last discharge told of the cell: where its voltage reached the cut-off under load, the
//! qMobile that puts the model's end there ([`crate::end_fit`], at the calibrator's final Ro; the knee the
//! cell goes on down past a model that ends above the cut-off kept apart, the last three's median added to
//! every end predicted), as `bcal calibrate` starts from the previous discharge's end fit; else the estimate
//! it ended with. The
//! prior's width is learned from the stream's own history as `bcal calibrate` learns it from a cell's
//! training cycles ([`RestWidth`]): the change from the mean each discharge started from to the value it
//! hands on, growing with the rest before the discharge. With the cell's lifetime model
//! ([`MeasuredSpec::lifetime`], written by `bcal cell-config`) the carried qMobile moves by the capacity
//! change the model expects since the last discharge (its fade, and what the rest before the new one gives
//! back), and the width adds that jump's own uncertainty, by the rule `bcal calibrate`'s prior walk uses
//! ([`LifeTracker::carry`]); the stream measures each discharge's capacity (the charge to its interpolated
//! cut-off, [`crate::eod::charge_to_ah`]) for it. Without one it follows the life by the recovery NASA's cells
//! show ([`LifetimeModel::population`], no fade: each measured capacity carries it), from the first measured
//! discharge after [`POPULATION_RESTS`](bcal_common::lifetime::POPULATION_RESTS) known rests, their median the usual rest; a model of the fade alone
//! (amplitude 0) turns that off. Until
//! [`crate::prior_width::MIN_PAIRS`] such changes are known, it is the last discharge's own posterior (its
//! 90 % interval read as 1.645 standard deviations): what one filter would carry across, had it known the
//! cell was recharged ([`WidthSource`]). Until then
//! one filter ran on across the gap and read the charged cell's voltage as its own misfit: on B0005's
//! discharges 41-46 joined end to end, the joint UKF's qMobile ran to the top of its range from the second
//! discharge on.
//!
//! Beside the calibrator a stream runs its prior alone (the same setting, never moved by the readings), and
//! delivers the end of discharge as `bcal calibrate` delivers it: each of the two recentred by its own
//! twins ([`crate::recentre`]) where they earned it, the two blended by their records ([`crate::blend`]),
//! that blend blended in turn with the last discharge's fit carried over ([`Refit`]: the previous-cycle
//! reference; never after a rest of more than a day), the prior alone predicting alone where it beat the
//! blend; the interval is learned on what was served.

use crate::adaptive::{AdaptiveRule, AdaptiveUkf};
use crate::correction::CorrectionCalibrator;
use crate::joint_ukf::JointUkf;
use crate::prior_width::{CurrentSlope, RestWidth, LONG_REST_S};
use crate::recentre::{Previous, Start, Transition, VoltageChange};
use crate::record_learner::{EndRecord, LoadedMean};
use crate::tracker_based::{RlCalibrator, Uncalibrated, WindowFitCalibrator};
use crate::widening::{share_bin, Adapt, Outcome, Widening, EOD_FRACTIONS_PCT, MIN_OUTCOMES, WINDOW};
use crate::{predict_eod, Calibrator, EodPrediction, EodQuery};
use bcal_common::battery::{Degradation, Load, LoadProfile};
use bcal_common::lifetime::{Carry, Condition, LifeTracker, LifetimeModel};
use bcal_common::math::idx;
use bcal_common::measured::env::{Design, MeasuredSpec};
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::scenario::{Request, Sample, KELVIN_0C};
use bcal_common::measured::tracker::TrackerSpec;
use bcal_common::measured::{
    current_glitch, LoadMean, ShortStartWatch, CURRENT_GLITCH_A, GLITCH_RUN_READINGS, LOADED_A, MAX_CELL_CURRENT_A,
    MAX_LOADED_S, MAX_RECORD_CHARGE_AH,
};
use bcal_common::policy::PolicyNet;
use bcal_common::task::Task;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// A reading discharges the cell when its current exceeds this, A (the readers' and the records' threshold).
pub const LOAD_THRESHOLD_A: f64 = 0.05;
/// Euler step of the end-of-discharge predictions, s (the reference model's).
pub const PREDICT_DT_S: f64 = 1.0;
/// Longest prediction horizon, s.
pub const PREDICT_MAX_S: f64 = 40_000.0;
/// The voltages a Li-ion cell can read, V: outside them the column is in another unit or broken.
pub const CELL_VOLTAGE_RANGE_V: [f64; 2] = [0.5, 5.0];
pub use bcal_common::measured::CELL_TEMPERATURE_RANGE_C;
pub use bcal_common::measured::NEW_DISCHARGE_GAP_S;
/// A charge lasts at least this long, s: a shorter negative current (a regenerative pulse, a noisy reading
/// at rest) is not a charge and does not end the discharge it falls in. Measured from the first charging
/// reading to the first reading after it, so a charge read once an hour still counts.
pub const MIN_CHARGE_S: f64 = 60.0;
/// A discharge lasts at least this long under load, s: a shorter one that never reached its cut-off (a single
/// loaded reading, as the spurious first sample of NASA's charge records reads) hands nothing on, and the
/// next discharge starts from what was carried into it, its rest measured from the last discharge that
/// counted. Measured from the first loaded reading to the first reading after the load, as a charge's
/// ([`MIN_CHARGE_S`]), so a discharge read every few minutes still counts.
pub const MIN_DISCHARGE_S: f64 = 60.0;
/// How near an edge of its range, in z units (a share of the range), a discharge's fit sits to be at it
/// ([`RangeEdges`]): a calibrator's estimate is held within its ranges, so a cell outside them is followed at
/// their edge.
pub const AT_EDGE_Z: f64 = 0.01;
/// Discharges in a row whose fit sat at the same edge of a range before the stream widens it
/// ([`Stream::widen_ranges`]).
pub const EDGE_RUN: usize = 2;
/// How far a stream may widen a range: this many times the setting's own span.
pub const MAX_RANGE_GROWTH: f64 = 8.0;

/// The discharges a stream has counted and those whose fit handed on sat at an edge of the setting's ranges
/// ([`AT_EDGE_Z`]; [`Stream::range_edges`]). A cell outside the ranges (a blind cold cell of high resistance
/// under the default ones, its Ro of 0.44-0.52 ohm above their 0.25: 59 of its 66 fits at the top, the end of
/// discharge at half 32 % off) was followed at their edge, and its ends were far off; the stream now widens a
/// range after [`EDGE_RUN`] discharges in a row at one edge ([`Stream::widen_ranges`]: 5 of 66 at the top, 0.69
/// % off), and the cell's own setting (`bcal cell-config`, ranges read off its records) holds it from the start.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RangeEdges {
    /// Discharges finished (each counts once it has handed its fit on, when the next begins) ...
    pub discharges: usize,
    /// ... those whose fit sat at an edge of either range ...
    pub at_edge: usize,
    /// ... and, per parameter (qMobile, Ro), how many sat at its floor and at its top.
    pub by_edge: [[usize; 2]; 2],
}

impl RangeEdges {
    /// Counts a discharge whose fit handed on is `end_z` (z units).
    fn push(&mut self, end_z: [f64; 2]) {
        self.discharges += 1;
        let mut any = false;
        for (k, z) in end_z.into_iter().enumerate() {
            let edge = if z <= AT_EDGE_Z {
                Some(0)
            } else if z >= 1.0 - AT_EDGE_Z {
                Some(1)
            } else {
                None
            };
            if let Some(j) = edge {
                self.by_edge[k][j] += 1;
                any = true;
            }
        }
        self.at_edge += usize::from(any);
    }
}

/// A reading later than the one before by more than this is refused as a clock error, s (a year): taken,
/// one timestamp far in the future (a glitch, milliseconds since the epoch read as seconds) would have every
/// later reading refused as not increasing.
pub const MAX_GAP_S: f64 = 365.0 * 86_400.0;

/// Readings in a row on a clock that went back by more than [`NEW_DISCHARGE_GAP_S`] after which the stream
/// takes it as the readings' clock (the ones before stay refused): a clock glitch that jumped ahead and
/// was corrected, or a clock set back, would otherwise have every later reading refused until it caught up
/// with the glitch.
pub const CLOCK_BACK_READINGS: usize = 3;

/// One reading as a user gives it, in the CLI's and the Python package's names and units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Reading {
    pub time_s: f64,
    /// Terminal voltage, V.
    pub voltage_v: f64,
    /// Current, A, positive while discharging.
    pub current_a: f64,
    /// Cell temperature, deg C (None: the last reading's, within half an hour; else the stream's ambient).
    #[serde(default)]
    pub temperature_c: Option<f64>,
}

/// Why a reading was refused (the calibrator did not see it).
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ReadingError {
    #[error("field `{field}` = {value} is not a finite number")]
    NotFinite { field: &'static str, value: f64 },
    #[error(
        "voltage_v = {voltage_v} is outside a Li-ion cell's range ({}-{} V); give volts (a millivolt column divided \
         by 1000)",
        CELL_VOLTAGE_RANGE_V[0],
        CELL_VOLTAGE_RANGE_V[1]
    )]
    VoltageOutOfRange { voltage_v: f64 },
    #[error(
        "temperature_c = {temperature_c} is outside where a Li-ion cell works (from {} to {} deg C); give degrees Celsius \
         (a kelvin column named temperature_k)",
        CELL_TEMPERATURE_RANGE_C[0],
        CELL_TEMPERATURE_RANGE_C[1]
    )]
    TemperatureOutOfRange { temperature_c: f64 },
    #[error(
        "current_a = {current_a} is more than a cell carries ({} A); give amperes (a milliampere column divided by \
         1000, or named current_ma)",
        MAX_CELL_CURRENT_A
    )]
    CurrentOutOfRange { current_a: f64 },
    #[error("time_s = {time_s} does not increase (previous reading {previous_s}); readings must come in time order")]
    TimeNotIncreasing { time_s: f64, previous_s: f64 },
    #[error(
        "time_s = {time_s} is more than a year after the previous reading ({previous_s}): a clock error, or \
         milliseconds given as seconds (name the column time_ms); start a new stream if the cell really rested \
         that long"
    )]
    TimeJump { time_s: f64, previous_s: f64 },
    #[error(
        "time_s = {time_s} would keep the cell under load for {:.1} days without a pause and draw {drawn_ah:.1} Ah, \
         more than a discharge lasts ({:.0} days) or a cell holds ({} Ah): most likely milliseconds given as \
         seconds (name the column time_ms, or divide it by 1000)",
        loaded_s / 86_400.0,
        MAX_LOADED_S / 86_400.0,
        MAX_RECORD_CHARGE_AH
    )]
    LoadTooLong { time_s: f64, loaded_s: f64, drawn_ah: f64 },
    #[error(
        "current_a = {current_a} steps {:.1} A from the last reading taken ({previous_a} A) while the voltage \
         moves {:.1} mV (a cell drawing it would move it by far more): a logger's glitch",
        (current_a - previous_a).abs(),
        1e3 * moved_v.abs()
    )]
    CurrentGlitch { current_a: f64, previous_a: f64, moved_v: f64 },
}

/// What the stream answers at each reading. Interval bounds and the prediction are None while the
/// calibrator cannot tell (no interval yet, no loaded reading yet, or the model does not reach the cut-off
/// within [`PREDICT_MAX_S`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Estimate {
    pub time_s: f64,
    /// qMobile, C, and its 90 % interval.
    pub q_mobile: f64,
    pub q_mobile_lo: Option<f64>,
    pub q_mobile_hi: Option<f64>,
    /// Ro, ohm, and its 90 % interval.
    pub r_o: f64,
    pub r_o_lo: Option<f64>,
    pub r_o_hi: Option<f64>,
    /// Predicted end of discharge (absolute time, s) at `eod_current_a` (or `eod_power_w`) down to the
    /// spec's cut-off.
    pub eod_s: Option<f64>,
    /// The current the prediction assumes, A: the mean of the loaded readings so far (over time where the
    /// load alternates); under a load held at constant power, the mean current the model draws at
    /// `eod_power_w` from now to its own end (the calibrator's run, before any rule moves it).
    pub eod_current_a: Option<f64>,
    /// The power the prediction assumes, W, where the load has been held at constant power (its loaded
    /// readings' power varied less than half as much as their current: [`LoadMean::power_held`]); None
    /// under a current.
    pub eod_power_w: Option<f64>,
    /// The prediction's 90 % interval (absolute times, s), learned from how the stream's own predictions
    /// fared on the discharges it followed to their cut-off (None until [`MIN_OUTCOMES`] of them are scored
    /// at the share of the discharge the prediction puts this reading at).
    pub eod_lo_s: Option<f64>,
    pub eod_hi_s: Option<f64>,
    /// The charge this discharge will have delivered at its end, Ah: what its readings drew so far plus
    /// `eod_current_a` until `eod_s` (from a full cell, its capacity at that current as a cycler measures
    /// it), and the same at the interval's ends; under a power, plus the charge the model draws to its own
    /// end and, from there to `eod_s` (or an interval's end), the current the power draws at the cut-off.
    /// Once the discharge has crossed its cut-off, the charge it delivered to the crossing, measured (as
    /// `bcal calibrate`'s records measure it), without an interval. None before the load, in a piece of a discharge whose start the stream did not see (after
    /// lost readings) and in streams that keep no readings ([`Stream::new`]).
    pub delivered_ah: Option<f64>,
    pub delivered_lo_ah: Option<f64>,
    pub delivered_hi_ah: Option<f64>,
    /// Whether the prediction is the prior alone's (the estimate the discharge started from, never moved by
    /// its readings): at a share of the discharge where the prior beat what it replaces (the calibrator's
    /// own, recentred where that serves) on at least 8 of the last 10 discharges followed to the cut-off and
    /// in their mean, unless the rest before this discharge was longer than a day.
    pub eod_from_prior: bool,
    /// Whether the prediction is the calibrator's own recentred on its bias over the last discharges
    /// followed to the cut-off ([`crate::recentre`]): at a share of the discharge where that beat the
    /// calibrator's own on at least 8 of the last 10 and in their mean, unless the prior alone predicts there
    /// or the rest before this discharge was longer than a day.
    pub eod_recentred: bool,
    /// Whether the prediction is the calibrator's own moved by the error its record expects at the voltage
    /// the discharge reads against the one before it at the same time since the load came on
    /// ([`crate::recentre::voltage_regressions`]): at a share where that beat what the recentring gives
    /// (recentred or not) on at least 8 of the last 10 and in their mean, unless the prior alone predicts
    /// there or the rest before this discharge was longer than a day.
    pub eod_on_voltage_change: bool,
    /// The prior alone's weight in the prediction: 1 where it predicts alone (`eod_from_prior`), its weight
    /// in the blend of the two ([`crate::blend`]) where one is learned (from the ninth discharge, once eight
    /// have been followed to the cut-off) times that blend's share against the previous discharge's fit (one
    /// minus `eod_previous_weight`), else 0. Where it is below 1, `eod_recentred` and
    /// `eod_on_voltage_change` tell which of the calibrator's predictions is blended.
    pub eod_prior_weight: f64,
    /// The previous discharge's voltage fit's weight in the prediction: that blend is blended in turn with
    /// the prediction of the fit the last discharge measured, carried over as it is ([`Refit`]; recentred
    /// where that serves), by their records on the discharges after rests of up to a day; 0 where the prior
    /// alone predicts, after a longer rest, without a fit, or before 8 such discharges have been followed.
    pub eod_previous_weight: f64,
    /// The learner on the record's weight in the prediction (the `ukf_learned` kind): what the rules above
    /// deliver is moved by the signed error the learner expects of it from the discharges followed to the
    /// cut-off before, the rest before this one, how warm it runs against them and how far its current moved
    /// from the last one's ([`crate::record_learner::EndRecord`]), and blended with the unmoved by the two's
    /// records; 0 where it does not move it (other kinds, or before 11 discharges have been followed to the
    /// cut-off and 8 more weighed). The flags and weights above tell how the rules gave the end before this move.
    pub eod_learned_weight: f64,
    /// The discharge the reading belongs to, from 0 (a new one after a charge or a long gap; the readings of
    /// a charge take the number of the discharge after it).
    pub discharge: u32,
}

/// The calibrators a stream can run, by the names the CLI (`--calibrator`) and Python (`kind`) use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CalibratorKind {
    /// The joint unscented Kalman filter (9 states: the model's and both parameters).
    Ukf,
    /// The joint UKF with its noise adapted from its innovations.
    AdaptiveUkf,
    /// The joint UKF with the learner on its record ([`crate::record_learner::EndRecord`]): its end of
    /// discharge moved by the error the stream's own record expects of it, as `bcal calibrate`'s `ukf_learned`.
    UkfLearned,
    /// The RL policy of a policy file (`.bcalpol`), on the window fit's features.
    Rl,
    /// The window fit alone (the RL policy's own least squares, no learning).
    Fit,
    /// The prior, never calibrated (its state from the readings): the reference.
    Uncalibrated,
}

impl CalibratorKind {
    pub const ALL: [CalibratorKind; 6] = [
        CalibratorKind::Ukf,
        CalibratorKind::AdaptiveUkf,
        CalibratorKind::UkfLearned,
        CalibratorKind::Rl,
        CalibratorKind::Fit,
        CalibratorKind::Uncalibrated,
    ];

    pub fn name(self) -> &'static str {
        match self {
            CalibratorKind::Ukf => "ukf",
            CalibratorKind::AdaptiveUkf => "adaptive_ukf",
            CalibratorKind::UkfLearned => "ukf_learned",
            CalibratorKind::Rl => "rl",
            CalibratorKind::Fit => "fit",
            CalibratorKind::Uncalibrated => "uncalibrated",
        }
    }
}

impl std::str::FromStr for CalibratorKind {
    type Err = StreamError;

    fn from_str(s: &str) -> Result<Self, StreamError> {
        let t = s.trim();
        CalibratorKind::ALL
            .into_iter()
            .find(|k| k.name() == t || k.name().replace('_', "-") == t)
            .ok_or_else(|| StreamError::UnknownKind(bcal_common::text::shown(s, 40)))
    }
}

/// Why a stream's calibrator cannot be set up; the messages are the CLI's.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum StreamError {
    #[error(
        "unknown calibrator `{0}`: use ukf, adaptive_ukf, ukf_learned, rl (with a policy file), fit or uncalibrated"
    )]
    UnknownKind(String),
    #[error("the rl calibrator needs a policy file (a .bcalpol that bcal train wrote: --calibrator rl:FILE)")]
    NoPolicy,
    #[error("a policy file is only read by the rl calibrator, not by {0}")]
    PolicyWithoutRl(&'static str),
    #[error(
        "the policy {path} was trained on the {observation} observation; live calibration runs measured-only policies (retrain with --preset measured)"
    )]
    PolicyTask { path: String, observation: String },
    #[error(
        "the policy {path} was trained on the {trained} model, but this calibration runs the {model} model: train a policy on it (bcal cell-config with the same --model, then bcal train --config)"
    )]
    PolicyModel { path: String, trained: String, model: String },
}

/// What a stream's calibrator is built from.
#[derive(Clone, Debug, PartialEq)]
pub struct Setup {
    pub kind: CalibratorKind,
    /// The cell's setting: `tracker` (model, ranges, prior, cut-off) for every kind, `ukf` for the filters
    /// (the defaults when None), and the RL policy's `design` and `correction`.
    pub spec: MeasuredSpec,
}

impl Setup {
    /// The joint UKF's settings: the task's (a trained run's filter, tuned on validation) or the defaults.
    pub fn ukf(&self) -> crate::JointUkfSettings {
        self.spec.ukf.unwrap_or_default()
    }
}

/// The calibrator's setting: the cell's config (`config`: a `bcal cell-config` file's `measured` part),
/// else the RL policy's own task (its run's cell setting and filter), else the default (a cell of the
/// paper's ranges, prior in the middle); on the doctor's extended model when `model` is given (then
/// following the measured temperature exactly when the model has the doctor's `thermal`, as `bcal
/// calibrate --model` does). `policy` is the policy file's task and where it came from; only `rl` takes
/// one, and needs one; its design (window fit or UKF correction) always comes from it.
pub fn resolve(
    kind: CalibratorKind,
    config: Option<&MeasuredSpec>,
    policy: Option<(&Task, &str)>,
    model: Option<&ModelExtension>,
) -> Result<Setup, StreamError> {
    let policy_spec = match (kind, policy) {
        (CalibratorKind::Rl, None) => return Err(StreamError::NoPolicy),
        (CalibratorKind::Rl, Some((task, path))) => {
            let m = task.measured().ok_or_else(|| StreamError::PolicyTask {
                path: path.to_string(),
                observation: task.observation_name(),
            })?;
            if let Some(ext) = model {
                if !m.tracker.model.same_kind(ext) {
                    return Err(StreamError::PolicyModel {
                        path: path.to_string(),
                        trained: m.tracker.model.label(),
                        model: ext.label(),
                    });
                }
            }
            Some(m.clone())
        }
        (k, Some(_)) => return Err(StreamError::PolicyWithoutRl(k.name())),
        (_, None) => None,
    };
    let mut spec = match (config, &policy_spec) {
        // The cell's config sets the cell; the policy keeps what it was trained as.
        (Some(c), Some(p)) => MeasuredSpec {
            scenario: c.scenario.clone(),
            tracker: c.tracker.clone(),
            ukf: c.ukf.or(p.ukf),
            lifetime: c.lifetime.or(p.lifetime),
            ..p.clone()
        },
        (Some(c), None) => c.clone(),
        (None, Some(p)) => p.clone(),
        (None, None) => MeasuredSpec::default(),
    };
    if let Some(ext) = model {
        spec.tracker.model = ext.clone();
        spec.tracker.use_measured_temperature = ext.has("thermal");
    }
    Ok(Setup { kind, spec })
}

/// The calibrator of `setup` (`net`: the RL policy's network, for `rl`): the one place the live loop and
/// the Python package make one.
pub fn build<'a>(setup: &Setup, net: Option<&'a PolicyNet>) -> Result<Box<dyn Calibrator + Send + 'a>, StreamError> {
    let tracker = &setup.spec.tracker;
    Ok(match setup.kind {
        // The learner on the record moves the stream's end of discharge, not the filter.
        CalibratorKind::Ukf | CalibratorKind::UkfLearned => Box::new(JointUkf::new(setup.ukf(), tracker)),
        CalibratorKind::AdaptiveUkf => Box::new(AdaptiveUkf::new(setup.ukf(), AdaptiveRule::default(), tracker)),
        CalibratorKind::Fit => Box::new(WindowFitCalibrator::new(tracker)),
        CalibratorKind::Uncalibrated => Box::new(Uncalibrated::new(tracker)),
        CalibratorKind::Rl => {
            let net = net.ok_or(StreamError::NoPolicy)?;
            match setup.spec.design {
                Design::WindowFit => Box::new(RlCalibrator::new(tracker, net)),
                Design::UkfCorrection => Box::new(CorrectionCalibrator::new(&setup.spec, net)),
            }
        }
    })
}

/// The prior alone of `setup`: its model never calibrated (its state from the readings), to hold the
/// calibrator to where it starts (issue 18 item 5); None for the uncalibrated kind, which is it.
fn prior_alone<'a>(setup: &Setup) -> Option<Box<dyn Calibrator + Send + 'a>> {
    (setup.kind != CalibratorKind::Uncalibrated)
        .then(|| Box::new(Uncalibrated::new(&setup.spec.tracker)) as Box<dyn Calibrator + Send + 'a>)
}

/// A calibrator with its stream bookkeeping.
pub struct Stream<'a> {
    cal: Box<dyn Calibrator + Send + 'a>,
    /// Whether `cal` has read a reading since it was built (its estimate is the prior's only from then).
    cal_read: bool,
    /// The estimate and interval the charge under way began with (what the stream shows during it).
    charge_start_estimate: Option<(Degradation, Option<crate::Interval>)>,
    spec: TrackerSpec,
    ambient_k: f64,
    /// The last reading's time on the stream's clock, s: the readings' own plus `clock_offset_s` ...
    last_t_s: Option<f64>,
    /// ... which moves each time their clock went back and stayed there ([`CLOCK_BACK_READINGS`]) ...
    clock_offset_s: f64,
    /// ... the readings' own times of the refused ones in a row of such a clock so far ...
    behind: Vec<f64>,
    /// ... and how many times it moved.
    clock_changes: u32,
    loaded_n: u64,
    /// The current this discharge's predictions assume (the loaded mean, or the mean over time where the
    /// load alternates: [`LoadMean`]).
    load: LoadMean,
    readings: u64,
    /// What builds the calibrator of a new discharge (streams made by [`Stream::of`]).
    rebuild: Option<(Setup, Option<&'a PolicyNet>)>,
    discharge: u32,
    /// When the charge under way began (its first reading), s; None while not charging.
    charge_started_s: Option<f64>,
    /// When the current discharge's calibrator was built, s (None: the stream's first, built before it).
    discharge_start_s: Option<f64>,
    /// The last reading, as the calibrator took it: a discharge whose load comes on long after it was
    /// built starts again from the rest reading before the load ([`Stream::step`]).
    last_sample: Option<Sample>,
    /// The current of the attempt just before, if it was refused as a glitch ([`current_glitch`]), A, and how
    /// many attempts in a row were refused at that level.
    glitch_a: Option<(f64, usize)>,
    /// The current and voltage of the last reading taken before a level that was taken unfollowed (at its
    /// attempt after [`GLITCH_RUN_READINGS`] refusals, the voltage unmoved), A and V, until the voltage follows
    /// that level: a reading back at that current ends a spike of more readings, and is taken at once.
    unfollowed_from: Option<(f64, f64)>,
    /// Whether the current discharge began under load (after a gap in the readings): a piece of a
    /// discharge, whose start is unseen. It is neither scored nor measured nor end-fitted.
    joined_under_load: bool,
    /// Time of the last reading that discharged the cell before its discharge ended, s (a loaded reading
    /// after the cut-off, NASA's spurious first charge sample, does not move the rest's start) ...
    last_loaded_t_s: Option<f64>,
    /// ... and the same as the last discharge that counted left it (what a load too short to count,
    /// [`MIN_DISCHARGE_S`], gives back).
    counted_last_loaded_t_s: Option<f64>,
    /// The first reading after the load of this discharge went off, s: how long a load lasted is measured
    /// to it, as a charge's is ([`MIN_DISCHARGE_S`]).
    load_off_s: Option<f64>,
    /// How long the load has stayed on since it last came on, s, and the charge drawn meanwhile, Ah (across
    /// gaps in the readings, which a stream read in the wrong time unit is made of).
    loaded_run: (f64, f64),
    /// Each finished discharge's carried value, the rest before it and the prior mean it started from ...
    ends: Vec<Carried>,
    /// ... and how many of those values sat at an edge of the ranges.
    range_edges: RangeEdges,
    /// The setting's own ranges (qMobile C, Ro ohm), and those the stream widened them to
    /// ([`Stream::widen_ranges`]).
    first_ranges: [[f64; 2]; 2],
    widened: Option<[[f64; 2]; 2]>,
    /// What the last finished discharge hands on (its end fit, else its final estimate).
    carried: Option<Degradation>,
    /// That discharge's posterior standard deviations, z units (None: its calibrator gives no interval).
    carried_sd_z: Option<[f64; 2]>,
    /// The rest voltages before the load of the last discharges ...
    rests_v: ShortStartWatch,
    /// How the carried qMobile moves with the current ([`CurrentSlope`]), learned on the discharges followed ...
    current_slope: CurrentSlope,
    /// ... the current of this discharge's first loaded reading and of the last discharge's, A ...
    load_on_a: Option<f64>,
    last_load_on_a: Option<f64>,
    /// ... and the setting this discharge was built from, its prior chosen again at the load-on by them.
    discharge_setup: Option<Setup>,
    /// ... and whether the current discharge started so far short of a full charge, as the rests show
    /// ([`ShortStartWatch`]), that its end fit does not measure the cell: it hands on what was carried into it,
    /// as `bcal calibrate`'s records do (`bcal_realcell::carry::over_cut_short`), and its errors teach the
    /// rules nothing ([`Stream::learn_from_end`]).
    short_start: bool,
    /// ... what its start adds to its end's interval, s (`widening::start_half`: its rest voltage known to the
    /// sensor's noise, through the open-circuit curve's slope; 0 near full or with no noise known yet) ...
    start_half_s: f64,
    /// ... and the sensor's voltage noise each of the last discharges read (`voltage_noise_v`; the median of
    /// them reads the next one's rest).
    noises_v: VecDeque<f64>,
    /// The prior mean the current discharge started from (None for the first: the setting's own prior).
    prior_mean: Option<Degradation>,
    /// The cell's life ([`MeasuredSpec::lifetime`]), following the finished discharges.
    life: Option<LifeTracker>,
    /// Discharges finished with readings under load (the life's discharge count).
    discharged: u32,
    /// The current discharge's capacity: the charge to its interpolated cut-off, Ah.
    capacity_ah: Option<f64>,
    /// The last finished discharge's capacity (None: it stopped above its cut-off) and conditions.
    last_discharge: Option<(Option<f64>, Condition)>,
    /// The rest before the current discharge, s (None for the first).
    rest_before_s: Option<f64>,
    /// The current discharge's prior width, z units, and where it came from (None: the calibrator's own).
    prior_width: Option<([f64; 2], WidthSource)>,
    /// The current discharge's end-of-discharge record (for its predictions' scores).
    eod_track: EodTrack,
    /// The predictions of the calibrator ([`METHOD`]), of its prior alone ([`PRIOR`]), each one's twins
    /// ([`Twins`]: the calibrator's from [`METHOD_TWINS`], as delivered at [`DELIVERED`], the prior's from
    /// [`PRIOR_TWINS`]), the two as delivered blended ([`BLENDED`]), what is served ([`SERVED`], whose
    /// interval every prediction takes), the previous discharge's fit ([`PREVIOUS`], its twins from
    /// [`PREVIOUS_TWINS`]) and the blend blended with it ([`WITH_PREVIOUS`]), with their scores.
    sources: [EodSource; N_SOURCES],
    /// The twins of the calibrator's own predictions, of the prior alone's and of the previous discharge's
    /// fit's ([`METHOD_TWINS`], [`PRIOR_TWINS`], [`PREVIOUS_TWINS`]), as `bcal calibrate` recentres every
    /// method and reference.
    twins: [Twins; 3],
    /// The last discharge's loaded readings, to the cut-off (None: no discharge before, or a piece).
    previous_loaded: Option<Previous>,
    /// The current discharge's loaded readings' running mean current from its load-on, A, to the cut-off,
    /// and the last counted discharge's (None: none yet): how a discharge's current stands against the one
    /// before ([`Transition`]: the twins' bias is their record's at like moves of current).
    current_now: LoadedMean,
    current_before_a: Option<f64>,
    /// The current discharge's voltage against the last one's (None before its load came on).
    voltage_change: Option<VoltageChange>,
    /// The voltage change at each of the current discharge's predictions (time s, change V).
    voltage_changes: Vec<(f64, Option<f64>)>,
    /// The prior alone: the same setting never calibrated, from what the last discharge told (streams made
    /// by [`Stream::of`] of a calibrating kind).
    prior_cal: Option<Box<dyn Calibrator + Send + 'a>>,
    /// Per share ([`EOD_FRACTIONS_PCT`]): whether the prior alone predicts the end there ([`crate::tune::earns`]
    /// on the last [`WINDOW`] discharges scored).
    prior_serves: [bool; 3],
    /// The record of the calibrator and the prior alone, each as delivered (recentred where that serves),
    /// and the calibrator's weight in their blend ...
    prior_blend: BlendRecord,
    /// ... and of that blend and the previous discharge's fit as delivered, on the discharges scored after
    /// rests of up to a day (the fit carries no recovery), and the blend's weight against the fit.
    previous_blend: BlendRecord,
    /// The calibrator's signed errors with the knee's whole warmth move and without it, and the share of the
    /// move it takes per share of the discharge (`bcal calibrate`'s `tune::scale_warmth`).
    warmth_share: BlendRecord,
    /// The previous discharge's fit, pinned for the whole discharge (its state from the readings), where the
    /// last discharge was fitted ([`Refit`]) ...
    previous_cal: Option<Box<dyn Calibrator + Send + 'a>>,
    /// ... that fit ...
    previous_fit: Option<Degradation>,
    /// ... and the fit of the discharge under way, once it has reached its cut-off.
    voltage_fit: Option<Degradation>,
    /// The current discharge's readings (streams made by [`Stream::of`]: for its end fit) ...
    samples: Vec<Sample>,
    /// ... the charge they drew, C, and how many of them that sums (the estimate's `delivered_ah`).
    drawn: (f64, usize),
    /// The current discharge's end fit: qMobile putting the model's end at the measured one (its knee kept
    /// apart), at the calibrator's Ro as the cell passed the model's end voltage ([`crate::end_fit`]).
    end_fit: Option<Degradation>,
    /// The model's knees the last discharges' end fits measured, C ([`crate::end_fit::EndFit::knee_c`]; the
    /// last [`crate::end_fit::KNEE_WINDOW`]): their median is added to every end predicted, from any start.
    knees_c: VecDeque<f64>,
    /// ... and their median, C (0 before any), taken when one is added, not at every prediction.
    knee_c: f64,
    /// The last discharges' temperatures at [`crate::end_fit::KNEE_WARMTH_AT_S`] after their load-on, K, with
    /// their knees, C, and their currents at the load-on, A (those that had all three) ...
    knee_warmth_seen: VecDeque<(f64, f64, f64)>,
    /// ... how the knee moves with that temperature at the current discharge's current, learned on them when its
    /// warmth is read (as `bcal calibrate` learns it) ...
    knee_warmth: Option<crate::end_fit::KneeWarmth>,
    /// ... and the current discharge's temperature then, once it has been read.
    warmth_k: Option<f64>,
    /// The calibrator's Ro after each reading of the current discharge kept in `samples` (time s, ohm): the
    /// end fit's Ro is the one it had as the cell passed the model's end voltage, before the knee below it
    /// pulled the filter's Ro up (B0049's joint UKF: 0.131 -> 0.149 ohm over its last minute, before the joint
    /// UKF held past its own model's end, 2026-12-01; the window fit still takes the knee, and a filter reads
    /// it until its own model, at its own estimate, has emptied).
    r_o_along: Vec<(f64, f64)>,
    /// Fits a discharge that reached its cut-off ([`Refit`]; None: no fit, the model stays as set up) ...
    refit: Option<Refit<'a>>,
    /// ... and the model the next discharge runs from it (None: the one set up).
    model_next: Option<ModelExtension>,
    /// The learner on the stream's record of its ends of discharge (the `ukf_learned` kind): it moves what
    /// the rules deliver ([`RULES`]) to what is served ([`SERVED`]).
    end_record: Option<EndRecord>,
}

/// What one finished discharge told, for the prior width ([`RestWidth`]), z units.
#[derive(Clone, Copy, Debug)]
struct Carried {
    /// What it hands on (its end fit, else its final estimate).
    end_z: [f64; 2],
    /// The rest before it, s.
    rest_s: Option<f64>,
    /// The prior mean it started from (None: the first, on the setting's own prior).
    mean_z: Option<[f64; 2]>,
}

/// One discharge's load-on and measured end, so that its predictions can be scored once the voltage
/// reaches the cut-off under load.
#[derive(Clone, Debug, Default)]
struct EodTrack {
    /// The first loaded reading's time, s.
    load_on_s: Option<f64>,
    /// The last reading above the cut-off since the load-on, loaded or not (time s, voltage V), to
    /// interpolate the crossing.
    above_cutoff: Option<(f64, f64)>,
    /// The measured end of discharge, s: the interpolated time the voltage fell below the cut-off.
    ended_s: Option<f64>,
}

/// Index of the calibrator's own predictions in [`Stream::sources`].
const METHOD: usize = 0;
/// Index of the prior alone's.
const PRIOR: usize = 1;
/// Index of the first of the calibrator's twins' four sources ([`Twins`]).
const METHOD_TWINS: usize = 2;
/// Index of the calibrator as delivered: moved on the voltage change, recentred or its own ([`Twins`]).
const DELIVERED: usize = METHOD_TWINS + TWIN_DELIVERED;
/// Index of the first of the prior alone's twins' four sources.
const PRIOR_TWINS: usize = 6;
/// Index of the calibrator blended with the prior alone, both as delivered ([`crate::blend`]) where a
/// weight is learned, else [`DELIVERED`] (the base the prior alone is judged against: what it would replace).
const BLENDED: usize = 10;
/// Index of what is served: its scores learn the interval of every prediction given, as `bcal calibrate`
/// learns the intervals on what was delivered (a source's own interval, learned on the discharges after
/// which it was chosen for its small errors, covered 81 % of B0055's ends). [`RULES`] moved by the learner on
/// the record where the stream runs one (the `ukf_learned` kind), else [`RULES`].
const SERVED: usize = 11;
/// Index of the previous discharge's fit carried over as it is ([`Refit`]): `bcal calibrate`'s
/// `previous_cycle` reference.
const PREVIOUS: usize = 12;
/// Index of the first of its twins' four sources.
const PREVIOUS_TWINS: usize = 13;
/// Index of [`BLENDED`] blended with the previous discharge's fit as delivered where a weight is learned and
/// the rest was no longer than a day, else [`BLENDED`]: what the prior alone would replace.
const WITH_PREVIOUS: usize = 17;
/// Index of what the rules deliver: the prior alone where it earned it, else [`WITH_PREVIOUS`] (the learner on
/// the record learns its errors).
const RULES: usize = 18;
/// Index of the calibrator's own predictions with the knee's whole move by the cell's warmth ...
const METHOD_WHOLE: usize = 19;
/// ... and without it: their records give the share of the move [`METHOD`] takes
/// ([`crate::end_fit::warmth_share`]).
const METHOD_UNMOVED: usize = 20;
/// How many sources a stream keeps.
const N_SOURCES: usize = 21;
/// Offsets of a [`Twins`]' sources from its first: its base recentred on its bias ...
const TWIN_RECENTRED: usize = 0;
/// ... what the recentring serves (the recentred where it has earned it, else the base) ...
const TWIN_RECENTRING: usize = 1;
/// ... the base moved by the error its record expects at the voltage change ...
const TWIN_ON_VOLTAGE: usize = 2;
/// ... and the base as delivered (moved, recentred or its own).
const TWIN_DELIVERED: usize = 3;

/// Whether `alt`'s scores at share index `b` earn it its place against `base`'s ([`crate::tune::earns`] on
/// the last [`WINDOW`] discharges both were scored on).
fn earns(sources: &[EodSource], alt: usize, base: usize, b: usize) -> bool {
    let f = EOD_FRACTIONS_PCT[b];
    let (mine, theirs): (Vec<f64>, Vec<f64>) =
        sources[alt].errors_at(f).into_iter().zip(sources[base].errors_at(f)).filter_map(|(p, m)| p.zip(m)).unzip();
    mine.len() == WINDOW && crate::tune::earns(&mine, &theirs)
}

/// The two twins of one source of predictions ([`crate::recentre`]): its bias and its line in the voltage
/// change per share, learned from its scored discharges, and where each serves. Its four sources sit at
/// `at` ([`TWIN_RECENTRED`] and the offsets after it).
#[derive(Clone, Debug)]
struct Twins {
    /// Index of the source the twins move ([`METHOD`] or [`PRIOR`]) ...
    base: usize,
    /// ... and of the first of its twins' sources.
    at: usize,
    /// The base's last [`crate::recentre::TWIN_SPAN`] scored discharges, each with how its current stood
    /// against the one before: a reading's bias is theirs at its own move of current
    /// ([`crate::recentre::biases_alike`]).
    ended: Vec<(Transition, Vec<Outcome>)>,
    /// Per share: whether the recentred predictions serve there (against the base).
    recentred_serves: [bool; 3],
    /// The base's error per share as a line in the voltage change ([`crate::recentre::voltage_regressions`]
    /// of its last scored discharges, each with the voltage change at its scored readings) ...
    lines: [Option<(f64, f64)>; 3],
    /// ... those discharges (the last [`crate::recentre::VOLTAGE_WINDOW`]) ...
    record: VecDeque<Vec<(Outcome, Option<f64>)>>,
    /// ... and per share whether the moved predictions serve there (against what the recentring serves).
    voltage_serves: [bool; 3],
}

/// Which of a [`Twins`]' predictions is delivered.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Twin {
    Own,
    Recentred,
    OnVoltage,
}

impl Twins {
    fn new(base: usize, at: usize) -> Self {
        Self {
            base,
            at,
            ended: Vec::new(),
            recentred_serves: [false; 3],
            lines: [None; 3],
            record: VecDeque::new(),
            voltage_serves: [false; 3],
        }
    }

    /// At a reading (time `t_s` of a discharge loaded at `load_on_s`, voltage change `dv`, its current
    /// against the last discharge's `now`) where the base predicts `own_s`: the recentred, the recentring's,
    /// the moved and the delivered predictions (by the offsets), and which twin is delivered. None of them
    /// serves after a rest of more than a day (`long_rest`).
    fn predict(
        &self,
        own_s: Option<f64>,
        dv: Option<f64>,
        now: &Transition,
        (load_on_s, t_s, long_rest): (f64, f64, bool),
    ) -> ([Option<f64>; 4], Twin) {
        let recentred = own_s.map(|e| {
            let bias = crate::recentre::biases_alike(&self.ended, now);
            e + crate::recentre::shift_s(&bias, load_on_s, t_s, e)
        });
        let moved = own_s.map(|e| e + crate::recentre::regressed_shift_s(&self.lines, dv, load_on_s, t_s, e));
        let bin = own_s.map(|e| share_bin(load_on_s, t_s, e));
        let recentring = match bin {
            Some(b) if self.recentred_serves[b] && !long_rest => recentred,
            _ => own_s,
        };
        let (delivered, from) = match bin {
            Some(b) if self.voltage_serves[b] && !long_rest => (moved, Twin::OnVoltage),
            Some(b) if self.recentred_serves[b] && !long_rest => (recentred, Twin::Recentred),
            _ => (own_s, Twin::Own),
        };
        ([recentred, recentring, moved, delivered], from)
    }

    /// Learns again, once a discharge (load-on `on_s`, measured end `end_s`, its current against the one
    /// before `moved`) has been scored in `sources`: where each twin serves, the record the bias is taken
    /// from, and the line in the voltage change from the base's scored predictions, each with the voltage
    /// change at the reading it was made (`changes`, time s and change).
    fn learn(
        &mut self,
        sources: &[EodSource],
        (on_s, end_s, moved): (f64, f64, Transition),
        changes: &[(f64, Option<f64>)],
    ) {
        let (base, at) = (self.base, self.at);
        self.recentred_serves = std::array::from_fn(|b| earns(sources, at + TWIN_RECENTRED, base, b));
        self.voltage_serves = std::array::from_fn(|b| earns(sources, at + TWIN_ON_VOLTAGE, at + TWIN_RECENTRING, b));
        let scored = &sources[base].scored;
        if self.ended.len() == crate::recentre::TWIN_SPAN {
            self.ended.remove(0);
        }
        self.ended.push((moved, scored.back().cloned().unwrap_or_default()));
        // The last made by then, as the scores take them.
        let last: Vec<(Outcome, Option<f64>)> = scored
            .back()
            .into_iter()
            .flatten()
            .map(|o| {
                let at_s = on_s + f64::from(o.fraction) / 100.0 * (end_s - on_s);
                let k = changes.partition_point(|x| x.0 <= at_s).checked_sub(1);
                (*o, k.and_then(|k| changes[k].1))
            })
            .collect();
        if self.record.len() == crate::recentre::VOLTAGE_WINDOW {
            self.record.pop_front();
        }
        self.record.push_back(last);
        self.lines = crate::recentre::voltage_regressions(self.record.make_contiguous());
    }
}

/// Two sources' record for their blend ([`crate::blend`]): per discharge scored (the last
/// [`crate::blend::BLEND_WINDOW`]) and share, the two relative errors where both predicted there, and per
/// share the first's weight learned from them ([`crate::blend::blend_weight`]; None: too few yet).
#[derive(Clone, Debug, Default)]
struct BlendRecord {
    record: VecDeque<[Option<(f64, f64)>; 3]>,
    weights: [Option<f64>; 3],
}

impl BlendRecord {
    /// Adds a discharge's pairs of errors and learns the weights again (`learn`: [`crate::blend::blend_weight`],
    /// or another rule on the pairs).
    fn push(&mut self, pairs: [Option<(f64, f64)>; 3], learn: fn(&[(f64, f64)]) -> Option<f64>) {
        if self.record.len() == crate::blend::BLEND_WINDOW {
            self.record.pop_front();
        }
        self.record.push_back(pairs);
        self.weights = std::array::from_fn(|b| {
            let pairs: Vec<(f64, f64)> = self.record.iter().filter_map(|d| d[b]).collect();
            learn(&pairs)
        });
    }
}

/// One source of end-of-discharge predictions: its predictions in the current discharge, the scores of
/// the last discharges followed to their cut-off, and the interval learned from them.
#[derive(Clone, Debug, Default)]
struct EodSource {
    /// Each loaded reading's prediction (time s, predicted end s) until the end.
    predictions: Vec<(f64, f64)>,
    /// The scored predictions of the last [`WINDOW`] discharges (one entry per discharge, aligned across
    /// the sources).
    scored: VecDeque<Vec<Outcome>>,
    /// The interval's widening per share ([`EOD_FRACTIONS_PCT`]; None: too few scores at that share), as
    /// the window learned it ...
    widening: [Option<Widening>; 3],
    /// ... and its online scale per share ([`Adapt`]: how the intervals given so far fared).
    adapt: [Adapt; 3],
}

impl EodSource {
    /// Scores the discharge's predictions (load-on `on_s`, measured end `end_s`) at each share of it, and
    /// learns the interval again from the last [`WINDOW`] discharges.
    /// `start_s`: what the discharge's start adds to its intervals ([`crate::widening::start_half`]).
    fn score(&mut self, on_s: f64, end_s: f64, start_s: f64) {
        let p = std::mem::take(&mut self.predictions);
        let outcomes: Vec<Outcome> = EOD_FRACTIONS_PCT
            .iter()
            .filter_map(|&f| {
                let at_s = on_s + f64::from(f) / 100.0 * (end_s - on_s);
                // The last prediction made by then (none made yet: no score at this share).
                let k = p.partition_point(|x| x.0 <= at_s).checked_sub(1)?;
                let value = p[k].1;
                let size = (value - on_s).max(1.0);
                Some(Outcome { value, below: 0.0, above: 0.0, size, measured: end_s, fraction: f, start: start_s })
            })
            .collect();
        for (b, w) in self.widening.iter().enumerate() {
            if let Some(w) = w {
                let applied = self.adapt[b].scaled(*w);
                self.adapt[b].update(&applied, outcomes.iter().filter(|o| o.fraction == EOD_FRACTIONS_PCT[b]));
            }
        }
        if self.scored.len() == WINDOW {
            self.scored.pop_front();
        }
        self.scored.push_back(outcomes);
        self.widening = std::array::from_fn(|b| {
            let at: Vec<Outcome> =
                self.scored.iter().flatten().filter(|o| o.fraction == EOD_FRACTIONS_PCT[b]).copied().collect();
            (at.len() >= MIN_OUTCOMES).then(|| Widening::learn(&at, self.scored.len()))
        });
    }

    /// The interval at share index `b` as it is given now: the window's widening, scaled online.
    fn interval(&self, b: usize) -> Option<Widening> {
        self.widening[b].map(|w| self.adapt[b].scaled(w))
    }

    /// The relative error of each of the last discharges at share `fraction` (None where it made no
    /// prediction by then).
    fn errors_at(&self, fraction: u32) -> Vec<Option<f64>> {
        self.scored
            .iter()
            .map(|d| d.iter().find(|o| o.fraction == fraction).map(|o| (o.measured - o.value).abs() / o.size))
            .collect()
    }
}

/// Fits one discharge followed to its cut-off, as `bcal calibrate` fits every discharge that ends: qMobile,
/// Ro and the model's per-cycle values (a diagnosis's electrode balance, charge-transfer scale; none on the
/// base model) on its readings from the first (the rest before the load included) to the first loaded one
/// at or below the cut-off. Returns the fit and the model the next discharge runs (None: no fit, the model
/// kept). The next discharge starts from the end fit at the fit's Ro and blends with the fit carried over. A
/// stream cannot fit by itself (the fit is the doctor's); `bcal calibrate --follow` and the Python package
/// hand it one (`bcal_doctor::model_file::stream_refit`).
pub type Refit<'a> = Box<dyn FnMut(&[Sample]) -> Option<(Degradation, ModelExtension)> + Send + 'a>;

/// Where a discharge's prior width came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WidthSource {
    /// The changes between the stream's earlier discharges ([`RestWidth`]).
    Learned,
    /// The last discharge's own posterior, while too few changes are known.
    Posterior,
}

impl<'a> Stream<'a> {
    /// `cal` built on `spec` (its model and cut-off run the predictions); readings without a temperature
    /// take the last reading's, or `ambient_c` where none came within half an hour (None: the model's own
    /// 292.1 K).
    pub fn new(cal: Box<dyn Calibrator + Send + 'a>, spec: &TrackerSpec, ambient_c: Option<f64>) -> Self {
        let ambient_k = ambient_c.map_or_else(
            || spec.model.model().map_or(bcal_common::battery::BatteryParams::default().tb0_k, |m| m.params.tb0_k),
            |c| c + KELVIN_0C,
        );
        Self {
            cal,
            cal_read: false,
            charge_start_estimate: None,
            spec: spec.clone(),
            ambient_k,
            last_t_s: None,
            clock_offset_s: 0.0,
            behind: Vec::new(),
            clock_changes: 0,
            loaded_n: 0,
            load: LoadMean::default(),
            readings: 0,
            rebuild: None,
            discharge: 0,
            charge_started_s: None,
            discharge_start_s: None,
            last_sample: None,
            glitch_a: None,
            unfollowed_from: None,
            joined_under_load: false,
            last_loaded_t_s: None,
            counted_last_loaded_t_s: None,
            load_off_s: None,
            loaded_run: (0.0, 0.0),
            ends: Vec::new(),
            range_edges: RangeEdges::default(),
            first_ranges: [spec.q_mobile_range_c, spec.r_o_range_ohm],
            widened: None,
            carried: None,
            carried_sd_z: None,
            rests_v: ShortStartWatch::default(),
            short_start: false,
            start_half_s: 0.0,
            noises_v: VecDeque::new(),
            current_slope: CurrentSlope::default(),
            load_on_a: None,
            last_load_on_a: None,
            discharge_setup: None,
            prior_mean: None,
            life: None,
            discharged: 0,
            capacity_ah: None,
            last_discharge: None,
            rest_before_s: None,
            prior_width: None,
            eod_track: EodTrack::default(),
            sources: Default::default(),
            prior_cal: None,
            prior_serves: [false; 3],
            prior_blend: BlendRecord::default(),
            previous_blend: BlendRecord::default(),
            warmth_share: BlendRecord::default(),
            previous_cal: None,
            previous_fit: None,
            voltage_fit: None,
            twins: [
                Twins::new(METHOD, METHOD_TWINS),
                Twins::new(PRIOR, PRIOR_TWINS),
                Twins::new(PREVIOUS, PREVIOUS_TWINS),
            ],
            previous_loaded: None,
            current_now: LoadedMean::default(),
            current_before_a: None,
            voltage_change: None,
            voltage_changes: Vec::new(),
            samples: Vec::new(),
            drawn: (0.0, 0),
            end_fit: None,
            knees_c: VecDeque::new(),
            knee_warmth_seen: VecDeque::new(),
            knee_warmth: None,
            warmth_k: None,
            knee_c: 0.0,
            r_o_along: Vec::new(),
            refit: None,
            model_next: None,
            end_record: None,
        }
    }

    /// The stream fitting each discharge it follows to the cut-off ([`Refit`]); each next discharge runs the
    /// refitted model, starts from the end fit under it and blends with the fit carried over.
    pub fn with_refit(mut self, refit: Refit<'a>) -> Self {
        self.refit = Some(refit);
        self
    }

    /// The calibrator of `setup` on a stream that starts a new discharge after a charge or a long gap,
    /// each from what the one before told of the cell (the module's doc).
    pub fn of(setup: &Setup, net: Option<&'a PolicyNet>, ambient_c: Option<f64>) -> Result<Self, StreamError> {
        let mut s = Self::new(build(setup, net)?, &setup.spec.tracker, ambient_c);
        s.rebuild = Some((setup.clone(), net));
        s.prior_cal = prior_alone(setup);
        s.life = setup.spec.lifetime.map(LifeTracker::new);
        s.end_record = (setup.kind == CalibratorKind::UkfLearned).then(EndRecord::default);
        Ok(s)
    }

    /// The width of the current discharge's prior (qMobile, Ro; standard deviations in z units of the
    /// calibrator's ranges) and where it came from; None while the calibrator's own width holds (the first
    /// discharge, or a calibrator without an interval before it).
    pub fn prior_width(&self) -> Option<([f64; 2], WidthSource)> {
        self.prior_width
    }

    /// Discharges begun so far (0 before the first reading).
    pub fn discharges(&self) -> u32 {
        if self.readings == 0 {
            0
        } else {
            self.discharge + 1
        }
    }

    /// Readings taken so far (refused ones not counted).
    pub fn readings(&self) -> u64 {
        self.readings
    }

    /// The calibrator's setting.
    pub fn spec(&self) -> &TrackerSpec {
        &self.spec
    }

    /// The calibrator (its state, for callers that need more than the estimate).
    pub fn calibrator(&self) -> &(dyn Calibrator + Send + 'a) {
        self.cal.as_ref()
    }

    /// Checks `r`, steps the calibrator and answers; a refused reading changes nothing (but that a current
    /// glitch's level is remembered for the next attempt: a step held there is taken).
    pub fn step(&mut self, r: &Reading) -> Result<Estimate, ReadingError> {
        // An error's times on the readings' clock, as the attempt that failed read them (`off`).
        let user = |e: ReadingError, off: f64| match e {
            ReadingError::TimeNotIncreasing { time_s, previous_s } => {
                ReadingError::TimeNotIncreasing { time_s: time_s - off, previous_s: previous_s - off }
            }
            ReadingError::TimeJump { time_s, previous_s } => {
                ReadingError::TimeJump { time_s: time_s - off, previous_s: previous_s - off }
            }
            ReadingError::LoadTooLong { time_s, loaded_s, drawn_ah } => {
                ReadingError::LoadTooLong { time_s: time_s - off, loaded_s, drawn_ah }
            }
            e => e,
        };
        let off = self.clock_offset_s;
        let refused_a = self.glitch_a;
        let result = match self.step_on_clock(&Reading { time_s: r.time_s + off, ..*r }) {
            Err(ReadingError::TimeNotIncreasing { .. }) if self.clock_went_back(r.time_s) => {
                // A clock that went back and stays there: its readings continue the stream after the last one.
                // The load's run so far is the glitch's as much as the cell's: it starts again here. All of it
                // is kept only if the reading is taken on the new clock (a refused reading changes nothing).
                let interval_s = r.time_s - self.behind[self.behind.len() - 2];
                let new_off = self.last_t_s.unwrap_or(r.time_s) + interval_s - r.time_s;
                let run = std::mem::take(&mut self.loaded_run);
                // The same attempt, again: as the first try met it.
                self.glitch_a = refused_a;
                match self.step_on_clock(&Reading { time_s: r.time_s + new_off, ..*r }) {
                    Ok(e) => {
                        self.clock_offset_s = new_off;
                        self.clock_changes += 1;
                        Ok(e)
                    }
                    Err(e) => {
                        self.loaded_run = run;
                        return Err(user(e, new_off));
                    }
                }
            }
            other => other,
        };
        let off = self.clock_offset_s;
        match result {
            Ok(e) => {
                self.behind.clear();
                let at = |t: Option<f64>| t.map(|t| t - off);
                Ok(Estimate {
                    time_s: r.time_s,
                    eod_s: at(e.eod_s),
                    eod_lo_s: at(e.eod_lo_s),
                    eod_hi_s: at(e.eod_hi_s),
                    ..e
                })
            }
            Err(e) => Err(user(e, off)),
        }
    }

    /// Whether `time_s` (the reading's own clock), refused as not later than the last reading, is the
    /// [`CLOCK_BACK_READINGS`]-th in a row, in time order among themselves, of a clock that went back by more
    /// than [`NEW_DISCHARGE_GAP_S`]: one that went back by less (a resent stretch of readings, a clock
    /// corrected by seconds) is not taken, and those readings stay refused.
    fn clock_went_back(&mut self, time_s: f64) -> bool {
        let Some(last_s) = self.last_t_s else { return false };
        if last_s - (time_s + self.clock_offset_s) <= NEW_DISCHARGE_GAP_S {
            self.behind.clear();
            return false;
        }
        if self.behind.last().is_some_and(|p| time_s <= *p) {
            self.behind.clear();
        }
        self.behind.push(time_s);
        self.behind.len() >= CLOCK_BACK_READINGS
    }

    /// [`Self::step`] on the stream's own clock (the readings' plus [`Self::clock_offset_s`]).
    fn step_on_clock(&mut self, r: &Reading) -> Result<Estimate, ReadingError> {
        // Only the attempt right after a glitch's refusal can hold its level ([`Self::glitch_a`]).
        let refused_a = self.glitch_a.take();
        for (field, value) in [("time_s", r.time_s), ("voltage_v", r.voltage_v), ("current_a", r.current_a)]
            .into_iter()
            .chain(r.temperature_c.map(|c| ("temperature_c", c)))
        {
            if !value.is_finite() {
                return Err(ReadingError::NotFinite { field, value });
            }
        }
        if !(CELL_VOLTAGE_RANGE_V[0]..=CELL_VOLTAGE_RANGE_V[1]).contains(&r.voltage_v) {
            return Err(ReadingError::VoltageOutOfRange { voltage_v: r.voltage_v });
        }
        if r.current_a.abs() > MAX_CELL_CURRENT_A {
            return Err(ReadingError::CurrentOutOfRange { current_a: r.current_a });
        }
        if let Some(t) =
            r.temperature_c.filter(|t| !(CELL_TEMPERATURE_RANGE_C[0]..=CELL_TEMPERATURE_RANGE_C[1]).contains(t))
        {
            return Err(ReadingError::TemperatureOutOfRange { temperature_c: t });
        }
        if let Some(previous_s) = self.last_t_s.filter(|p| r.time_s <= *p) {
            return Err(ReadingError::TimeNotIncreasing { time_s: r.time_s, previous_s });
        }
        if let Some(previous_s) = self.last_t_s.filter(|p| r.time_s - *p > MAX_GAP_S) {
            return Err(ReadingError::TimeJump { time_s: r.time_s, previous_s });
        }
        // Against the last reading taken, within a discharge's sampling: a spike of one or two readings is
        // refused and the reading after it, back where the current was, meets no step. A step the voltage
        // sample lagged meets a voltage that moved at its next reading. A level refused on
        // GLITCH_RUN_READINGS attempts in a row is taken at the next (a load that stepped under a voltage
        // sensor that never followed loses those readings, not the stream).
        // A spike of more readings was taken from its third: the reading back where the current was before it
        // meets no step against it.
        let mut unfollowed_from = None;
        if let Some(p) = self.last_sample.filter(|p| r.time_s - p.t_s <= NEW_DISCHARGE_GAP_S) {
            let moved_v = r.voltage_v - p.voltage_v;
            let level = refused_a.filter(|(g, _)| (r.current_a - g).abs() < CURRENT_GLITCH_A).map_or(0, |(_, n)| n);
            let glitch = current_glitch(r.current_a - p.current_a, moved_v);
            let back = self.unfollowed_from.is_some_and(|(a, _)| (r.current_a - a).abs() < CURRENT_GLITCH_A);
            if glitch && !back && level < GLITCH_RUN_READINGS {
                self.glitch_a = Some((r.current_a, level + 1));
                return Err(ReadingError::CurrentGlitch { current_a: r.current_a, previous_a: p.current_a, moved_v });
            }
            unfollowed_from = match self.unfollowed_from {
                _ if glitch && !back => Some((p.current_a, p.voltage_v)),
                // Kept while the level stays unfollowed; dropped once the voltage follows it, or back.
                Some((a, v)) if !back && current_glitch(r.current_a - a, r.voltage_v - v) => Some((a, v)),
                _ => None,
            };
        }
        // Milliseconds read as seconds stretch every interval a thousandfold: the load then seems to stay on
        // for days and to draw more than a cell holds (the readers refuse such a record the same way).
        let loaded_run = match self.last_sample {
            Some(p) if p.current_a > LOADED_A && r.current_a > LOADED_A => {
                let dt_s = r.time_s - p.t_s;
                (self.loaded_run.0 + dt_s, self.loaded_run.1 + 0.5 * (p.current_a + r.current_a) * dt_s / 3600.0)
            }
            _ => (0.0, 0.0),
        };
        if loaded_run.0 > MAX_LOADED_S || loaded_run.1 > MAX_RECORD_CHARGE_AH {
            return Err(ReadingError::LoadTooLong { time_s: r.time_s, loaded_s: loaded_run.0, drawn_ah: loaded_run.1 });
        }
        self.unfollowed_from = unfollowed_from;
        let s = Sample {
            t_s: r.time_s,
            voltage_v: r.voltage_v,
            current_a: r.current_a,
            // A reading without a temperature takes the one before it (a cell's temperature moves slowly; the
            // readers fill a record's the same way), the ambient where none came within half an hour.
            temperature_k: r
                .temperature_c
                .map(|c| c + KELVIN_0C)
                .or_else(|| {
                    self.last_sample.filter(|p| r.time_s - p.t_s <= NEW_DISCHARGE_GAP_S).map(|p| p.temperature_k)
                })
                .unwrap_or(self.ambient_k),
            request: Request::Unknown,
        };
        let charging = r.current_a < -LOAD_THRESHOLD_A;
        let after_gap = self.last_t_s.is_some_and(|p| r.time_s - p > NEW_DISCHARGE_GAP_S);
        let charged = !charging && self.charge_started_s.is_some_and(|t0| r.time_s - t0 >= MIN_CHARGE_S);
        let loaded = r.current_a > LOAD_THRESHOLD_A;
        if self.last_t_s.is_none() && loaded && self.rebuild.is_some() {
            // A stream that begins under load joins a discharge whose start it did not see.
            self.joined_under_load = true;
        }
        if (after_gap || charged) && self.rebuild.is_some() {
            self.new_discharge(r.time_s);
            // After lost readings a discharge seen first under load is a piece of one; after a charge it is
            // a discharge that started at once.
            self.joined_under_load = after_gap && loaded;
        } else if loaded && self.loaded_n == 0 && self.rebuild.is_some() {
            // The load comes on long after this discharge's calibrator was built at the end of a charge: the
            // rest before it lasted until now. It starts again from the rest reading before the load, its
            // prior's rest measured to there (as `bcal calibrate` measures it, to the record's start).
            let idle = self.last_sample.filter(|x| x.current_a.abs() <= LOAD_THRESHOLD_A);
            if let (Some(idle), Some(t0)) = (idle, self.discharge_start_s) {
                if idle.t_s - t0 > NEW_DISCHARGE_GAP_S {
                    // The same discharge, started again: its number stays.
                    let number = self.discharge;
                    self.new_discharge(idle.t_s);
                    self.discharge = number;
                    self.step_calibrators(&idle);
                    self.samples.push(idle);
                }
            }
        }
        self.charge_started_s = if charging { self.charge_started_s.or(Some(r.time_s)) } else { None };
        self.loaded_run = loaded_run;
        // The discharge's warmth, read as its readings pass the time after the load-on the knee's rule reads.
        if let (Some(on), None, Some(prev)) = (self.eod_track.load_on_s, self.warmth_k, self.last_sample) {
            let at_s = on + crate::end_fit::KNEE_WARMTH_AT_S;
            if prev.t_s < at_s && s.t_s >= at_s {
                self.warmth_k = crate::end_fit::temperature_at_k(&[prev, s], at_s);
                let seen = self.knee_warmth_seen.make_contiguous();
                self.knee_warmth = self.load_on_a.and_then(|a| crate::end_fit::KneeWarmth::learn(seen, a));
            }
        }
        self.last_sample = Some(s);
        // What a charge shows: the estimate the charge began with, not the filter following it. A discharge
        // starts afresh after a charge (built again from what the last one told), so what the filter takes
        // from the charge is kept by no discharge, and on the way it showed qMobile and Ro at their ranges'
        // ends (a stream that began on a charge, until the load). The filter still reads every reading (a
        // short charge is no new discharge, and a regenerative pulse is part of one). Held before any load of
        // the discharge under way, and past a charge's first minute; a stream that keeps no readings never
        // starts afresh and shows its filter.
        let charge_held = charging
            && self.rebuild.is_some()
            && (self.loaded_n == 0 || self.charge_started_s.is_some_and(|t0| r.time_s - t0 >= MIN_CHARGE_S));
        if !charging {
            self.charge_start_estimate = None;
        } else if self.charge_start_estimate.is_none() && self.cal_read {
            self.charge_start_estimate = Some((self.cal.estimate(), self.cal.interval()));
        }
        if loaded && self.loaded_n == 0 && self.load_on_a.is_none() && !self.joined_under_load {
            self.load_on_a = Some(r.current_a);
            self.choose_prior_at_load_on();
        }
        self.step_calibrators(&s);
        // A calibrator that had read nothing has its start (and its prior as an estimate) only now.
        if charging && self.charge_start_estimate.is_none() {
            self.charge_start_estimate = Some((self.cal.estimate(), self.cal.interval()));
        }
        self.last_t_s = Some(r.time_s);
        self.readings += 1;
        self.load.push(r.time_s, r.current_a, r.voltage_v);
        if r.current_a > LOAD_THRESHOLD_A {
            self.loaded_n += 1;
            if self.eod_track.ended_s.is_none() {
                self.last_loaded_t_s = Some(r.time_s);
            }
            self.load_off_s = None;
        } else if self.loaded_n > 0 && self.load_off_s.is_none() {
            self.load_off_s = Some(r.time_s);
        }
        let eod_load = self.load.load();
        let method = eod_load.and_then(|l| self.predict_from(self.cal.as_ref(), l));
        let prior_run = eod_load.and_then(|l| self.prior_cal.as_deref().and_then(|p| self.predict_from(p, l)));
        let previous_run = eod_load.and_then(|l| self.previous_cal.as_deref().and_then(|p| self.predict_from(p, l)));
        // The calibrator's end takes the share of the knee's warmth move its record says it has not read
        // yet, at the reading's share of the discharge (the whole move until that is learned).
        let warmth_s = eod_load.map_or(0.0, |l| self.warmth_move_s(l));
        let whole_s = method.map(|p| p.eod_s);
        let eod_method_s = whole_s.map(|e| {
            let b = share_bin(self.eod_track.load_on_s.unwrap_or(r.time_s), r.time_s, e);
            e + (self.warmth_share.weights[b].unwrap_or(1.0) - 1.0) * warmth_s
        });
        let (eod_prior_s, eod_previous_s) = (prior_run.map(|p| p.eod_s), previous_run.map(|p| p.eod_s));
        // The current assumed to the end: the load's, or under a power held constant the mean current the
        // model's run draws (it rises as the voltage falls), else the power at the present voltage.
        let eod_power_w = match eod_load {
            Some(Load::PowerW(w)) => Some(w),
            _ => None,
        };
        // Under a power, the model's run to its own end: the calibrator's, else the prior's, else the previous fit's.
        let power_run = eod_power_w.and_then(|w| method.or(prior_run).or(previous_run).map(|p| (w, p)));
        let eod_current_a = match eod_load {
            Some(Load::CurrentA(a)) => Some(a),
            Some(Load::PowerW(w)) => power_run.and_then(|(_, p)| p.mean_current_a(r.time_s)).or(Some(w / r.voltage_v)),
            None => None,
        };
        // The load-on: the first loaded reading of the discharge (this one, when it is).
        let load_on_s =
            self.eod_track.load_on_s.or((r.current_a > LOAD_THRESHOLD_A).then_some(r.time_s)).unwrap_or(r.time_s);
        // The voltage against the last discharge's at the same time since the load came on, until the end.
        let loaded_since = (r.current_a > LOAD_THRESHOLD_A || self.eod_track.load_on_s.is_some())
            && self.eod_track.ended_s.is_none()
            && !self.joined_under_load;
        let dv = if loaded_since {
            // Made once per discharge, at its first loaded reading: the rest before it is read then, not at
            // every reading (a BMS logging a long rest at 1 s would scan it each time).
            if self.voltage_change.is_none() {
                let start = Start::at_load_on(&self.samples, load_on_s, s.temperature_k);
                self.voltage_change = Some(VoltageChange::new(self.previous_loaded.clone(), start));
            }
            self.voltage_change.as_mut().and_then(|c| c.push(r.time_s - load_on_s, r.voltage_v, r.current_a))
        } else {
            None
        };
        // How the discharge's current stands against the last one's so far (its loaded readings to the cut-off).
        if loaded_since && loaded {
            self.current_now.push(r.time_s - load_on_s, r.current_a);
        }
        let now = Transition {
            before_a: self.current_before_a,
            now_a: self.current_now.at(r.time_s - load_on_s).filter(|_| loaded_since),
        };
        // Each twin of the calibrator's and of the prior's, and each as delivered (none after a long rest).
        let long_rest = self.after_long_rest();
        let at = (load_on_s, r.time_s, long_rest);
        let (own, delivered_from) = self.twins[0].predict(eod_method_s, dv, &now, at);
        let (prior, _) = self.twins[1].predict(eod_prior_s, dv, &now, at);
        let (previous, _) = self.twins[2].predict(eod_previous_s, dv, &now, at);
        let (delivered_s, prior_delivered_s) = (own[TWIN_DELIVERED], prior[TWIN_DELIVERED]);
        // The two blended by their records at this share (after a long rest too: a weighted mean of two
        // estimates is no switch to one whose record does not speak for the rest).
        let own_bin = eod_method_s.map(|e| share_bin(load_on_s, r.time_s, e));
        let prior_share = match (own_bin.and_then(|b| self.prior_blend.weights[b]), delivered_s, prior_delivered_s) {
            (Some(w), Some(_), Some(_)) => 1.0 - w,
            _ => 0.0,
        };
        let blended_s = match (delivered_s, prior_delivered_s) {
            (Some(d), Some(p)) if prior_share > 0.0 => Some(crate::blend::blended(1.0 - prior_share, d, p)),
            _ => delivered_s,
        };
        // That blend blended in turn with the previous discharge's fit, never after a long rest: the fit
        // carries no recovery (`bcal calibrate`'s rule).
        let previous_share =
            match (own_bin.and_then(|b| self.previous_blend.weights[b]), blended_s, previous[TWIN_DELIVERED]) {
                (Some(w), Some(_), Some(_)) if !long_rest => 1.0 - w,
                _ => 0.0,
            };
        let with_previous_s = match (blended_s, previous[TWIN_DELIVERED]) {
            (Some(b), Some(p)) if previous_share > 0.0 => Some(crate::blend::blended(1.0 - previous_share, b, p)),
            _ => blended_s,
        };
        if self.rebuild.is_some() {
            self.samples.push(s);
            self.r_o_along.push((s.t_s, self.cal.estimate().r_o_ohm));
            let (drawn_c, upto) = &mut self.drawn;
            for w in self.samples[upto.saturating_sub(1)..].windows(2) {
                *drawn_c += crate::eod::drawn_between_c(&w[0], &w[1]);
            }
            *upto = self.samples.len();
        }
        // Who predicts: the prior alone at a share of the discharge where it has earned it, except after a
        // rest of more than a day (the record of ordinary rests does not speak for it; `bcal calibrate`'s rule).
        let bin = eod_method_s.or(eod_prior_s).map(|e| share_bin(load_on_s, r.time_s, e));
        let from_prior = matches!(bin, Some(b) if self.prior_serves[b] && eod_prior_s.is_some() && !long_rest);
        let rules_s = if from_prior { eod_prior_s } else { with_previous_s };
        // The learner on the record (the `ukf_learned` kind): its loaded readings' temperature from the load-on
        // (their current is `now`'s), and what the rules deliver moved by the error the record expects,
        // blended with it by their records.
        let counting = !self.joined_under_load && self.eod_track.ended_s.is_none();
        if let Some(rec) = self.end_record.as_mut().filter(|_| counting && loaded) {
            if self.eod_track.load_on_s.is_none() {
                rec.load_on();
            }
            // The reading's own temperature, not the one filled in for a reading without.
            rec.push(r.time_s - load_on_s, r.temperature_c.map_or(f64::NAN, |c| c + KELVIN_0C));
        }
        let learned = match (&self.end_record, rules_s, bin) {
            (Some(rec), Some(e), Some(b)) if counting && (loaded || self.eod_track.load_on_s.is_some()) => {
                rec.moved(b, e, load_on_s, r.time_s - load_on_s, self.rest_before_s, now.switch())
            }
            _ => None,
        };
        let eod_s = learned.map_or(rules_s, |(e, _)| Some(e));
        let mut eods = [None; N_SOURCES];
        eods[METHOD] = eod_method_s;
        eods[PRIOR] = eod_prior_s;
        eods[METHOD_TWINS..METHOD_TWINS + 4].copy_from_slice(&own);
        eods[PRIOR_TWINS..PRIOR_TWINS + 4].copy_from_slice(&prior);
        eods[BLENDED] = blended_s;
        eods[SERVED] = eod_s;
        eods[PREVIOUS] = eod_previous_s;
        eods[PREVIOUS_TWINS..PREVIOUS_TWINS + 4].copy_from_slice(&previous);
        eods[WITH_PREVIOUS] = with_previous_s;
        eods[RULES] = rules_s;
        eods[METHOD_WHOLE] = whole_s;
        eods[METHOD_UNMOVED] = whole_s.map(|e| e - warmth_s);
        self.track_eod(r, eods, dv);
        let on = self.eod_track.load_on_s;
        let (eod_lo_s, eod_hi_s) = match (eod_s, on, bin.and_then(|b| self.sources[SERVED].interval(b))) {
            (Some(eod), Some(on), Some(w)) => {
                let half = w.half(0.0, (eod - on).max(1.0), self.start_half_s);
                (Some((eod - half).max(r.time_s)), Some(eod + half))
            }
            _ => (None, None),
        };
        // The charge delivered at the end: drawn so far plus the assumed current to it (the end measured once
        // it has been, the discharge's capacity as the stream measured it).
        let (delivered_ah, delivered_lo_ah, delivered_hi_ah) = match (self.capacity_ah, eod_current_a) {
            _ if self.rebuild.is_none() || self.joined_under_load => (None, None, None),
            (Some(measured_ah), _) => (Some(measured_ah), None, None),
            (None, Some(current_a)) => {
                let drawn_ah = self.drawn.0 / 3600.0;
                // The charge from now to an end, C: the current times the time; under a power, the model's
                // run's charge to its own end, and from there to this end the current the power draws at the
                // cut-off (the ends differ near it, where the current is highest).
                let to_c = |e_s: f64| match power_run {
                    Some((w, p)) => p.drawn_c + (e_s - p.eod_s) * w / self.spec.cutoff_v,
                    None => current_a * (e_s - r.time_s),
                };
                let at = |end_s: Option<f64>| end_s.map(|e| drawn_ah + to_c(e.max(r.time_s)).max(0.0) / 3600.0);
                (at(eod_s), at(eod_lo_s), at(eod_hi_s))
            }
            (None, None) => (None, None, None),
        };
        let (d, iv) = match self.charge_start_estimate {
            Some(held) if charge_held => held,
            _ => (self.cal.estimate(), self.cal.interval()),
        };
        // A charge past its first minute has ended the discharge: its end is the one measured (the cut-off
        // crossed), else unknown (a log too coarse to read the crossing), and what it delivered likewise; the
        // filter following the charge predicts no end (it ran ahead of the clock, the charge counted as drawn).
        let (eod_s, eod_lo_s, eod_hi_s, delivered_ah, delivered_lo_ah, delivered_hi_ah) =
            if charge_held && self.loaded_n > 0 {
                let ended_s = self.eod_track.ended_s;
                (ended_s, None, None, ended_s.and(self.capacity_ah), None, None)
            } else {
                (eod_s, eod_lo_s, eod_hi_s, delivered_ah, delivered_lo_ah, delivered_hi_ah)
            };
        Ok(Estimate {
            time_s: r.time_s,
            q_mobile: d.q_mobile_c,
            q_mobile_lo: iv.map(|iv| iv.q_mobile_c[0]),
            q_mobile_hi: iv.map(|iv| iv.q_mobile_c[1]),
            r_o: d.r_o_ohm,
            r_o_lo: iv.map(|iv| iv.r_o_ohm[0]),
            r_o_hi: iv.map(|iv| iv.r_o_ohm[1]),
            eod_s,
            eod_current_a,
            eod_power_w,
            eod_lo_s,
            eod_hi_s,
            delivered_ah,
            delivered_lo_ah,
            delivered_hi_ah,
            eod_from_prior: from_prior,
            eod_recentred: !from_prior && delivered_s.is_some() && delivered_from == Twin::Recentred,
            eod_on_voltage_change: !from_prior && delivered_s.is_some() && delivered_from == Twin::OnVoltage,
            eod_prior_weight: if from_prior { 1.0 } else { prior_share * (1.0 - previous_share) },
            eod_previous_weight: if from_prior { 0.0 } else { previous_share },
            eod_learned_weight: learned.map_or(0.0, |(_, w)| w),
            discharge: self.discharge,
        })
    }

    /// A new calibrator on the same setting from `start_s` on, its prior what the last discharge told (its
    /// end fit, else its final estimate; moved by the lifetime model when the setting has one), its width
    /// learned from the discharges before (the module's doc). A stretch that never discharged (a charge
    /// after a gap) is no discharge to learn from or carry: the one before it is.
    fn new_discharge(&mut self, start_s: f64) {
        let Some((setup, net)) = &self.rebuild else { return };
        // A charge that goes on into the new discharge shows the new calibrator's start; the one that ended
        // the last discharge held what its filter knew at the charge's start (before it read the charge).
        let held = self.charge_start_estimate.take();
        let spec = &setup.spec.tracker;
        for src in &mut self.sources {
            // Predictions of a discharge that stopped above its cut-off are never scored.
            src.predictions.clear();
        }
        self.discharge_start_s = Some(start_s);
        let piece = std::mem::take(&mut self.joined_under_load);
        // A load too short to be a discharge (`MIN_DISCHARGE_S`) tells nothing of the cell's charge, and the
        // calibrator's estimate after it has read one loaded reading at a rested cell's voltage.
        // (One that reached its cut-off counted, however short: its end was scored.)
        let off_s = self.load_off_s.unwrap_or(start_s);
        let blip = self.loaded_n > 0
            && self.eod_track.ended_s.is_none()
            && self.eod_track.load_on_s.is_none_or(|on| off_s - on < MIN_DISCHARGE_S);
        let discharged = self.loaded_n > 0 && !blip;
        if let Some(rec) = self.end_record.as_mut() {
            rec.close(discharged && !piece, self.rest_before_s, &self.current_now, self.current_before_a);
        }
        // The next discharge's current is compared with this one's, however it ended (not a piece's).
        if let Some(a) = self.current_now.whole().filter(|_| discharged && !piece) {
            self.current_before_a = Some(a);
        }
        if blip {
            // No discharge: the next one keeps its number (`reset_discharge`), and its rest runs from the
            // last discharge that counted.
            self.loaded_n = 0;
            self.last_loaded_t_s = self.counted_last_loaded_t_s;
        } else if discharged {
            self.counted_last_loaded_t_s = self.last_loaded_t_s;
        }
        // A piece joined under load hands nothing on: its calibrator started from a loaded reading of a
        // discharge whose start it did not see, so its estimate reads the unseen charge into qMobile (a stream
        // picked up mid-discharge ended at a range's edge and put the next whole discharge's end far off).
        // The next discharge starts from what the last whole one told, else the setting's prior.
        if (!discharged || piece) && self.carried.is_none() {
            // Nothing has discharged yet (a stream that began on a charge, at rest or under load): the next
            // discharge starts from the setting's own prior, as the stream's first does, with no rest known
            // before it.
            self.cal = build(setup, *net).expect("the stream's calibrator was built from this setting");
            self.cal_read = false;
            self.prior_cal = prior_alone(setup);
            self.discharge_setup = None;
            self.rest_before_s = None;
            self.reset_discharge();
            return;
        }
        // The rest: from the last reading that discharged (a charge seen in between is part of it).
        let rest_s = self.last_loaded_t_s.or(self.last_t_s).map(|t| (start_s - t).max(0.0));
        // A discharge started from a partial charge hands on what was carried into it, and measured nothing the
        // width or the life can learn from.
        let short = self.short_start && self.carried.is_some();
        if discharged && !piece && !short {
            // Where the cut-off was not read (a coarse log), the estimate it ended with: at the charge's start,
            // not after the filter read the charge.
            let (held_end, held_iv) = held.map_or((None, None), |(d, iv)| (Some(d), iv));
            let end = self.end_fit.take().or(held_end).unwrap_or_else(|| self.cal.estimate());
            let mean_z = self.prior_mean.map(|m| spec.to_z(&m));
            let end_z = spec.to_z(&end);
            self.ends.push(Carried { end_z, rest_s: self.rest_before_s, mean_z });
            // Against the prior mean before the load-on moved it, as `bcal calibrate`'s walk learns it.
            if let (Some(now), Some(before), Some(m)) = (self.load_on_a, self.last_load_on_a, self.prior_mean) {
                if let Some(x) = crate::prior_width::current_move(now, before) {
                    self.current_slope.push(x, (end.q_mobile_c / m.q_mobile_c).ln());
                }
            }
            self.range_edges.push(end_z);
            self.carried = Some(end);
            // Its own posterior, read as 1.645 standard deviations of its 90 % interval: the width a
            // discharge after it carries while too few changes are known to learn one.
            self.carried_sd_z = held_iv.or_else(|| self.cal.interval()).map(|iv| {
                let (lo, hi) = (
                    spec.to_z(&Degradation { q_mobile_c: iv.q_mobile_c[0], r_o_ohm: iv.r_o_ohm[0] }),
                    spec.to_z(&Degradation { q_mobile_c: iv.q_mobile_c[1], r_o_ohm: iv.r_o_ohm[1] }),
                );
                let sd = |k: usize| ((hi[k] - lo[k]) / (2.0 * 1.645)).max(crate::prior_width::MIN_SD_Z);
                [sd(0), sd(1)]
            });
        }
        if discharged && !piece {
            self.last_load_on_a = self.load_on_a;
        }
        // The discharge's loaded readings, to the cut-off, for the voltage change of the next, and its fit;
        // after a piece, the last whole discharge's (a piece's start is unseen: its times since the load came
        // on are not the discharge's).
        if discharged && !piece {
            self.previous_loaded = self.loaded_readings();
            self.previous_fit = self.voltage_fit.take();
        }
        // A piece joined under load is the rest of a discharge the life has counted already.
        if discharged && !piece {
            self.discharged += 1;
            let at =
                Condition { ambient_c: self.ambient_k - KELVIN_0C, current_a: self.load.current_a().unwrap_or(0.0) };
            // Without the cell's own lifetime model (`measured.lifetime`), the life is followed by the recovery
            // NASA's cells show (a long rest gives capacity back on every cell of the set) from the first
            // measured discharge after `POPULATION_RESTS` known rests, their median the usual one: the tracker
            // starts where that rest holds the cell, and a first rest far from the usual (a weekend) would have
            // every later one read as a change.
            if let (None, Some(c), false) = (&self.life, self.capacity_ah, short) {
                let rests = self.ends.iter().filter_map(|e| e.rest_s);
                self.life = LifetimeModel::population_from_rests(c, rests).map(LifeTracker::new);
            }
            if let Some(t) = self.life.as_mut() {
                t.advance_to(self.discharged, self.rest_before_s, at);
                if let Some(c) = self.capacity_ah.filter(|_| !short) {
                    t.observe(c);
                }
            }
            if !short {
                self.last_discharge = Some((self.capacity_ah, at));
            }
        }
        let end = self.carried.expect("set above");
        // The lifetime model's change since the last discharge (none without a model or a measured capacity).
        let carry = match (&self.life, self.last_discharge) {
            (Some(t), Some((capacity_ah, at))) => t.carry(self.discharged + 1, rest_s, at, capacity_ah),
            _ => Carry::NONE,
        };
        let mean = carry.mean(&end);
        let mut rests: Vec<f64> = self.ends.iter().filter_map(|e| e.rest_s).chain(rest_s).collect();
        let usual_rest_s = bcal_common::stats::median(&mut rests).unwrap_or(0.0);
        let probe = RestWidth { usual_rest_s, ..RestWidth::fallback() };
        let changes: Vec<(f64, [f64; 2])> = self
            .ends
            .iter()
            .filter_map(|e| e.mean_z.map(|m| (probe.h(e.rest_s), [e.end_z[0] - m[0], e.end_z[1] - m[1]])))
            .collect();
        let long = self.ends.iter().skip(1).filter(|e| e.rest_s.is_some_and(|r| r > LONG_REST_S)).count();
        let width = RestWidth::fit(&changes, usual_rest_s, long);
        let span_c = spec.q_mobile_range_c[1] - spec.q_mobile_range_c[0];
        self.prior_width = if width.fitted() {
            Some((carry.widen_z(width.sd_z(rest_s, 1), end.q_mobile_c, span_c), WidthSource::Learned))
        } else {
            // The last discharge's own, not the calibrator's now (after a charge or a rest read since, that
            // is a prior that has only walked).
            self.carried_sd_z.map(|sd| (carry.widen_z(sd, end.q_mobile_c, span_c), WidthSource::Posterior))
        };
        let mut next = setup.clone();
        // A copy of the network's handle: `widen_ranges` below takes the stream mutably.
        let net = *net;
        if let Some(m) = &self.model_next {
            next.spec.tracker.model = m.clone();
            self.spec.model = m.clone();
        }
        next.spec.tracker.prior = mean;
        if let Some((sd, _)) = self.prior_width {
            next.spec.ukf = Some(crate::JointUkfSettings { prior_std_z: sd, ..next.ukf() });
            next.spec.tracker.prior_std_z = sd[0].max(sd[1]);
        }
        self.widen_ranges(&mut next);
        // The same kind, setting and network built once already: it builds again.
        self.cal = build(&next, net).expect("the stream's calibrator was built from this setting");
        self.cal_read = false;
        self.prior_cal = prior_alone(&next);
        self.previous_cal = self.previous_fit.and_then(|d| {
            (next.kind != CalibratorKind::Uncalibrated)
                .then(|| Box::new(Uncalibrated::pinned(&next.spec.tracker, &d)) as Box<dyn Calibrator + Send + 'a>)
        });
        self.rest_before_s = rest_s;
        self.prior_mean = Some(mean);
        self.discharge_setup = Some(next);
        self.reset_discharge();
    }

    /// The ranges of `next` and of every discharge after it widened where the last [`EDGE_RUN`] discharges
    /// handed on a fit at the same edge of one ([`AT_EDGE_Z`]): a cell outside the setting's ranges (a cold cell at
    /// 4 A, its resistance above the default top) was followed at their edge for its whole life. The top moves up
    /// by the range's span, the floor down by half of it (never below half the floor), up to
    /// [`MAX_RANGE_GROWTH`] times the setting's own span; the next discharge starts from the carried value with the
    /// setting's own width, the history of changes at the edge forgotten. Not for an RL policy, whose inputs are
    /// scaled by the ranges it was trained on.
    fn widen_ranges(&mut self, next: &mut Setup) {
        if next.kind == CalibratorKind::Rl || self.ends.len() < EDGE_RUN {
            return;
        }
        let last = &self.ends[self.ends.len() - EDGE_RUN..];
        let old = [next.spec.tracker.q_mobile_range_c, next.spec.tracker.r_o_range_ohm];
        let mut new = old;
        for k in 0..2 {
            let [lo, hi] = old[k];
            let span = hi - lo;
            let room = MAX_RANGE_GROWTH * (self.first_ranges[k][1] - self.first_ranges[k][0]);
            if last.iter().all(|e| e.end_z[k] >= 1.0 - AT_EDGE_Z) {
                new[k][1] = (hi + span).min(lo + room);
            } else if last.iter().all(|e| e.end_z[k] <= AT_EDGE_Z) {
                new[k][0] = (lo - 0.5 * span).max(0.5 * lo).max(hi - room);
            }
        }
        if new == old {
            return;
        }
        // What was learned at the edge says nothing of the cell inside the new ranges (the changes between
        // discharges pinned there are none, a width learned on them holds the next at the edge): the next
        // discharge starts from the carried value with the setting's own width, as the stream's first did.
        self.ends.clear();
        self.carried_sd_z = None;
        self.prior_width = None;
        if let Some((s, _)) = self.rebuild.as_mut() {
            s.spec.tracker.q_mobile_range_c = new[0];
            s.spec.tracker.r_o_range_ohm = new[1];
            next.spec.ukf = s.spec.ukf;
            next.spec.tracker.prior_std_z = s.spec.tracker.prior_std_z;
        }
        for t in [&mut next.spec.tracker, &mut self.spec] {
            t.q_mobile_range_c = new[0];
            t.r_o_range_ohm = new[1];
        }
        self.widened = Some(new);
    }

    /// At the load-on of a discharge that starts from a carried value: its prior's qMobile moved by the
    /// current's move from the last discharge, as the discharges followed have shown it ([`CurrentSlope`]),
    /// and its calibrators built again on it, reading the rest before the load again.
    fn choose_prior_at_load_on(&mut self) {
        let (Some(now), Some(before), Some(mean)) = (self.load_on_a, self.last_load_on_a, self.prior_mean) else {
            return;
        };
        let Some(q_mobile_c) = self.current_slope.moved(mean.q_mobile_c, now, before) else { return };
        let (Some(setup), Some((_, net))) = (self.discharge_setup.as_ref(), self.rebuild.as_ref()) else { return };
        let mut next = setup.clone();
        next.spec.tracker.prior.q_mobile_c = q_mobile_c;
        self.cal = build(&next, *net).expect("the stream's calibrator was built from this setting");
        self.prior_cal = prior_alone(&next);
        self.cal_read = !self.samples.is_empty();
        for s in &self.samples {
            self.cal.step(s);
            if let Some(p) = self.prior_cal.as_mut() {
                p.step(s);
            }
        }
    }

    /// The current discharge's readings from its load-on to the first below its cut-off under load (all
    /// of them when it stopped above it), as times since the load came on.
    fn loaded_readings(&self) -> Option<Previous> {
        let on = self.eod_track.load_on_s?;
        let end = self.eod_track.ended_s;
        let start = Start::at_load_on(&self.samples, on, self.samples.iter().find(|x| x.t_s >= on)?.temperature_k);
        let mut past_end = false;
        let readings = self.samples.iter().filter(|x| x.t_s >= on).map_while(|x| {
            if past_end {
                return None;
            }
            past_end = end.is_some_and(|e| x.t_s >= e);
            Some((x.t_s - on, x.voltage_v, x.current_a))
        });
        Previous::new(readings, start)
    }

    /// At a discharge's load-on: its rest voltage against the last discharges' ([`Stream::short_start`]).
    /// And how well the rest tells the discharge's starting charge: what its end's interval adds.
    fn see_rest(&mut self) {
        self.short_start = self.rests_v.see(crate::end_fit::rest_voltage_v(&self.samples));
        let mut noises: Vec<f64> = self.noises_v.iter().copied().collect();
        let share_sd = bcal_common::stats::median(&mut noises).and_then(|noise_v| {
            let model = self.spec.model.model().ok()?;
            bcal_common::measured::cellmodel::start_share_sd(&model, &self.samples, noise_v)
        });
        self.start_half_s = match (share_sd, self.load_on_a) {
            (Some(sd), Some(i)) => crate::widening::start_half(sd, self.cal.estimate().q_mobile_c, i),
            _ => 0.0,
        };
    }

    /// What the current discharge has measured, cleared for the next one.
    fn reset_discharge(&mut self) {
        self.short_start = false;
        self.warmth_k = None;
        self.knee_warmth = None;
        self.start_half_s = 0.0;
        if let Some(noise_v) = bcal_common::measured::noise::voltage_noise_v(&self.samples) {
            if self.noises_v.len() == bcal_common::measured::noise::NOISE_WINDOW {
                self.noises_v.pop_front();
            }
            self.noises_v.push_back(noise_v);
        }
        self.load_on_a = None;
        self.voltage_change = None;
        self.voltage_changes.clear();
        self.capacity_ah = None;
        self.eod_track = EodTrack::default();
        self.samples.clear();
        self.r_o_along.clear();
        self.drawn = (0.0, 0);
        self.end_fit = None;
        self.voltage_fit = None;
        self.load = LoadMean::default();
        self.current_now = LoadedMean::default();
        // A stretch that never drew a load (a charge seen after lost readings, a stream that began on a
        // charge) was no discharge: the next one keeps its number.
        self.discharge += u32::from(self.loaded_n > 0);
        self.loaded_n = 0;
        self.load_off_s = None;
    }

    /// Records the reading's predictions (the calibrator's and the prior's) and, at the first loaded
    /// reading below the cut-off, scores the discharge's predictions at each share of it against the
    /// interpolated crossing, learns the EOD intervals again from the last [`WINDOW`] scored discharges (a
    /// discharge's own interval is never set by its own outcome: a prediction is made before its end is
    /// known), learns the calibrator's bias and its line in the voltage change per share again, and decides
    /// again at which shares the prior alone and the two twins predict.
    fn track_eod(&mut self, r: &Reading, eod_s: [Option<f64>; N_SOURCES], dv: Option<f64>) {
        if r.current_a > LOAD_THRESHOLD_A && self.eod_track.load_on_s.is_none() && self.eod_track.ended_s.is_none() {
            self.see_rest();
        }
        let t = &mut self.eod_track;
        let cutoff_v = self.spec.cutoff_v;
        if t.ended_s.is_some() {
            return;
        }
        if r.current_a <= LOAD_THRESHOLD_A {
            // The load paused: the crossing is interpolated from the last reading above the cut-off, loaded
            // or not, as `bcal calibrate` interpolates it, never across the pause.
            if t.load_on_s.is_some() && r.voltage_v >= cutoff_v {
                t.above_cutoff = Some((r.time_s, r.voltage_v));
            }
            return;
        }
        let on = *t.load_on_s.get_or_insert(r.time_s);
        if r.voltage_v >= cutoff_v {
            t.above_cutoff = Some((r.time_s, r.voltage_v));
            for (src, e) in self.sources.iter_mut().zip(eod_s) {
                if let Some(e) = e {
                    src.predictions.push((r.time_s, e));
                }
            }
            if eod_s[METHOD].is_some() || eod_s[PRIOR].is_some() {
                self.voltage_changes.push((r.time_s, dv));
            }
            return;
        }
        // A discharge joined below its cut-off has no span to score.
        let Some((t0, v0)) = t.above_cutoff else { return };
        let end_s = t0 + (v0 - cutoff_v) / (v0 - r.voltage_v) * (r.time_s - t0);
        t.ended_s = Some(end_s);
        if self.joined_under_load {
            // A piece whose start is unseen: its span, its charge and its end fit are not the discharge's.
            return;
        }
        if !self.short_start {
            self.learn_from_end(on, end_s);
        }
        self.measure_end(end_s);
    }

    /// Scores the discharge's predictions that ended at `end_s` (load-on `on_s`) and learns the rules
    /// again from them: the intervals, the gates of the prior alone, the blends, the twins and the learner
    /// on the record. Not for a discharge started so far short of full that its end fit does not measure the
    /// cell ([`Stream::short_start`]): its errors, relative to its span, are not those of the discharges the
    /// rules serve ("B0049" of `examples/blind/progpy_cells.py`: discharge 14, 59 s from 5 % of full, missed
    /// its end by 65 % of its span, and the intervals of the discharges after it grew to a median 77 % of
    /// theirs, 11 % without it). Its predictions are dropped at the next load-on.
    fn learn_from_end(&mut self, on: f64, end_s: f64) {
        for src in &mut self.sources {
            src.score(on, end_s, self.start_half_s);
        }
        if let Some(rec) = self.end_record.as_mut() {
            // The rules' signed error per share, % of the discharge, and where it was taken after the load-on.
            let last = self.sources[RULES].scored.back();
            rec.score(std::array::from_fn(|b| {
                let f = EOD_FRACTIONS_PCT[b];
                let o = last.and_then(|d| d.iter().find(|o| o.fraction == f))?;
                Some((100.0 * (o.value - o.measured) / (end_s - on).max(1.0), f64::from(f) / 100.0 * (end_s - on)))
            }));
        }
        self.prior_serves =
            std::array::from_fn(|b| self.prior_cal.is_some() && earns(&self.sources, PRIOR, WITH_PREVIOUS, b));
        // The blends' records: this discharge's errors of the two each blends, as delivered, per share; the
        // previous fit's not after a long rest (it never serves there).
        let last = |src: usize, f: u32| self.sources[src].errors_at(f).last().copied().flatten();
        let pairs = |a: usize, b: usize| {
            std::array::from_fn(|k| last(a, EOD_FRACTIONS_PCT[k]).zip(last(b, EOD_FRACTIONS_PCT[k])))
        };
        self.prior_blend.push(pairs(DELIVERED, PRIOR_TWINS + TWIN_DELIVERED), crate::blend::blend_weight);
        if !self.after_long_rest() {
            self.previous_blend.push(pairs(BLENDED, PREVIOUS_TWINS + TWIN_DELIVERED), crate::blend::blend_weight);
        }
        // The calibrator's signed errors with the whole warmth move and without it, % of the discharge.
        let signed = |src: usize, f: u32| {
            let o = self.sources[src].scored.back()?.iter().find(|o| o.fraction == f)?;
            Some(100.0 * (o.value - o.measured) / (end_s - on).max(1.0))
        };
        self.warmth_share.push(
            std::array::from_fn(|k| {
                let f = EOD_FRACTIONS_PCT[k];
                signed(METHOD_WHOLE, f).zip(signed(METHOD_UNMOVED, f))
            }),
            crate::end_fit::warmth_share,
        );
        let changes = std::mem::take(&mut self.voltage_changes);
        let moved = Transition { before_a: self.current_before_a, now_a: self.current_now.whole() };
        for twins in &mut self.twins {
            twins.learn(&self.sources, (on, end_s, moved), &changes);
        }
    }

    /// What a discharge that ended at `end_s` measured of the cell: the charge it held, the end fit the next
    /// discharge starts from and the model's knee.
    fn measure_end(&mut self, end_s: f64) {
        // The charge the cell held, measured by its end: what the next discharge starts from.
        if self.rebuild.is_some() {
            self.capacity_ah = Some(crate::eod::charge_to_ah(&self.samples, end_s));
            // The model's per-cycle values refitted on this discharge, and the end fit under them at the
            // refit's Ro, as `bcal calibrate` hands on each record's end fit under its own refit model.
            let refitted = self.refit.as_mut().and_then(|f| f(&self.samples));
            let (spec, r_o_ohm) = match &refitted {
                Some((d, m)) => (TrackerSpec { model: m.clone(), ..self.spec.clone() }, d.r_o_ohm),
                None => (self.spec.clone(), self.cal.estimate().r_o_ohm),
            };
            let own_ro = refitted.is_none();
            if let Some((d, m)) = refitted {
                self.model_next = Some(m);
                self.voltage_fit = Some(d);
            }
            let before = &self.samples[..self.samples.len().saturating_sub(1)];
            let mut fit = crate::end_fit::end_fit(&spec, before, end_s, r_o_ohm);
            // Without a refit, the filter's own Ro as the cell passed the model's end voltage.
            let mut r_o_ohm = r_o_ohm;
            if let Some(f) = fit.filter(|f| own_ro && f.knee_c > 0.0) {
                let at = self.r_o_along.partition_point(|x| x.0 <= f.passed_s).checked_sub(1);
                if let Some(r) = at.map(|k| self.r_o_along[k].1) {
                    r_o_ohm = r;
                    fit = crate::end_fit::end_fit(&spec, before, end_s, r_o_ohm).or(fit);
                }
            }
            self.end_fit = fit.map(|f| Degradation { q_mobile_c: f.q_mobile_c, r_o_ohm });
            if let Some(f) = fit {
                if self.knees_c.len() == crate::end_fit::KNEE_WINDOW {
                    self.knees_c.pop_front();
                }
                self.knees_c.push_back(f.knee_c);
                let mut knees: Vec<f64> = self.knees_c.iter().copied().collect();
                self.knee_c = bcal_common::stats::median(&mut knees).unwrap_or(0.0);
                if let (Some(w), Some(a)) = (self.warmth_k, self.load_on_a) {
                    if self.knee_warmth_seen.len() == crate::end_fit::KNEE_WARMTH_SEEN {
                        self.knee_warmth_seen.pop_front();
                    }
                    self.knee_warmth_seen.push_back((w, f.knee_c, a));
                }
            }
        }
    }

    /// The EOD interval's relative half-width per share of the discharge ([`EOD_FRACTIONS_PCT`]: a fraction
    /// of the predicted duration from the load-on, learned on the predictions served) and the discharges it
    /// was learned on; None at a share with too few scores yet.
    pub fn eod_widening(&self) -> [Option<(f64, usize)>; 3] {
        std::array::from_fn(|b| self.sources[SERVED].interval(b).map(|w| (w.model, w.learned_on)))
    }

    /// Per share of the discharge ([`EOD_FRACTIONS_PCT`]): whether the prior alone predicts the end there
    /// now (it beat what it replaces, the calibrator's own recentred where that serves, on at least 8 of the
    /// last 10 discharges scored and in their mean).
    pub fn prior_serves(&self) -> [bool; 3] {
        self.prior_serves
    }

    /// Per share of the discharge ([`EOD_FRACTIONS_PCT`]): the prior alone's weight in the blend given there
    /// now ([`Estimate::eod_prior_weight`] where the prior alone does not predict; None before 8 discharges
    /// have been followed to the cut-off with both predicting there).
    pub fn prior_blend_weights(&self) -> [Option<f64>; 3] {
        self.prior_blend.weights.map(|w| w.map(|w| 1.0 - w))
    }

    /// Whether the current discharge followed a rest of more than a day (no twin, gate or previous fit serves
    /// after one).
    fn after_long_rest(&self) -> bool {
        self.rest_before_s.is_some_and(|x| x > LONG_REST_S)
    }

    /// Per share of the discharge: the previous discharge's fit's weight in the blend given there now
    /// ([`Estimate::eod_previous_weight`] after a rest of up to a day; None before 8 such discharges have
    /// been followed to the cut-off with both predicting there).
    pub fn previous_blend_weights(&self) -> [Option<f64>; 3] {
        self.previous_blend.weights.map(|w| w.map(|w| 1.0 - w))
    }

    /// Per share of the discharge: the weight of the end moved by the learner on the stream's record
    /// ([`Estimate::eod_learned_weight`]; None for kinds without one, or before it has one there).
    pub fn learned_weights(&self) -> [Option<f64>; 3] {
        self.end_record.as_ref().map_or([None; 3], EndRecord::weights)
    }

    /// Per share of the discharge: whether the calibrator's own prediction recentred on its bias is given
    /// there now (where the prior alone does not predict; [`Estimate::eod_recentred`]).
    pub fn recentred_serves(&self) -> [bool; 3] {
        self.twins[0].recentred_serves
    }

    /// Per share of the discharge: whether the calibrator's own prediction moved on the voltage change is
    /// given there now (where the prior alone does not predict; [`Estimate::eod_on_voltage_change`]).
    pub fn voltage_serves(&self) -> [bool; 3] {
        self.twins[0].voltage_serves
    }

    /// The end of discharge (absolute time, s) if the cell now draws `current_a` until the cut-off, from the
    /// calibrated state under the current estimate; the model runs at the cell's temperature now (with the
    /// doctor's Arrhenius factors when the model has them). None before the first reading, or when the model
    /// does not reach the cut-off within [`PREDICT_MAX_S`].
    pub fn predict_eod_s(&self, current_a: f64) -> Option<f64> {
        self.predict_eod_under_s(Load::CurrentA(current_a))
    }

    /// [`Self::predict_eod_s`] under any load: a current, or a power held to the cut-off (the current P / V
    /// rising as the voltage falls).
    pub fn predict_eod_under_s(&self, load: Load) -> Option<f64> {
        self.predict_from(self.cal.as_ref(), load).map(|p| p.eod_s - self.clock_offset_s)
    }

    /// The discharges finished so far (each counts once it has handed its fit on, when the next begins) and
    /// those whose fit sat at an edge of the setting's ranges ([`RangeEdges`]).
    pub fn range_edges(&self) -> RangeEdges {
        self.range_edges
    }

    /// The ranges (qMobile C, Ro ohm) the stream widened the setting's to, if it did ([`Stream::widen_ranges`]).
    pub fn widened_ranges(&self) -> Option<[[f64; 2]; 2]> {
        self.widened
    }

    /// The setting's own ranges (qMobile C, Ro ohm), before any widening.
    pub fn setting_ranges(&self) -> [[f64; 2]; 2] {
        self.first_ranges
    }

    /// How many times the readings' clock went back and the stream took the new one ([`CLOCK_BACK_READINGS`]).
    pub fn clock_changes(&self) -> u32 {
        self.clock_changes
    }

    /// The calibrator and its twins (the prior alone, the previous discharge's fit) read `s`.
    fn step_calibrators(&mut self, s: &Sample) {
        self.cal.step(s);
        self.cal_read = true;
        for p in self.prior_cal.iter_mut().chain(self.previous_cal.iter_mut()) {
            p.step(s);
        }
    }

    /// The knee's move by the cell's warmth, C: none until the warmth is read and a slope learned.
    fn knee_warmth_c(&self) -> f64 {
        self.knee_warmth.zip(self.warmth_k).map_or(0.0, |(w, t)| w.move_c(t))
    }

    /// What [`Self::knee_warmth_c`] adds to a predicted end under `load`, s.
    fn warmth_move_s(&self, load: Load) -> f64 {
        let knee_a = crate::end_fit::knee_current_a(load, self.spec.cutoff_v);
        if knee_a > 0.0 {
            self.knee_warmth_c() / knee_a
        } else {
            0.0
        }
    }

    /// [`Self::predict_eod_s`] from the state and estimate of `cal`, under `load` (a current or a power), with
    /// the charge drawn on the way.
    fn predict_from(&self, cal: &(dyn Calibrator + Send + 'a), load: Load) -> Option<EodPrediction> {
        let (x, t_now_s) = (cal.state()?, self.last_t_s?);
        let d = cal.estimate();
        let t_k = x[idx::T_B];
        let ext = &self.spec.model;
        let (model, ro_factor) = ext.model_at(t_k, ext.reference_k.unwrap_or(t_k)).ok()?;
        // The calibrated state already holds Ro's temperature factor in its ohmic lag; the dynamics apply it.
        let dynamics = Degradation { r_o_ohm: d.r_o_ohm * ro_factor, ..d };
        let profile = LoadProfile::Constant(load);
        let q = EodQuery { profile: &profile, cutoff_v: self.spec.cutoff_v, dt_s: PREDICT_DT_S, max_s: PREDICT_MAX_S };
        // The model's knee, as the last discharges' end fits measured it: the charge past the model's end,
        // moved with the discharge's warmth once that has been read.
        let knee_c = self.knee_c + self.knee_warmth_c();
        let knee_a = crate::end_fit::knee_current_a(load, self.spec.cutoff_v);
        predict_eod(&model, &x, &dynamics, t_now_s, &q).map(|p| match knee_a > 0.0 {
            true => EodPrediction { eod_s: p.eod_s + knee_c / knee_a, drawn_c: p.drawn_c + knee_c },
            false => p,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::widening::ADAPT_MAX_LOG;
    use bcal_common::measured::scenario::{draw_spec, simulate, CellError, EpisodeSpec, LoadKind, ScenarioConfig};
    use rand::SeedableRng;

    fn episode() -> Vec<Reading> {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(4);
        let spec = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let ep = simulate(&cfg, &spec).unwrap();
        ep.samples
            .iter()
            .map(|s| Reading {
                time_s: s.t_s,
                voltage_v: s.voltage_v,
                current_a: s.current_a,
                temperature_c: Some(s.temperature_k - KELVIN_0C),
            })
            .collect()
    }

    /// A reading without a temperature takes the last reading's, as the record readers fill one (a sensor that
    /// drops out for a few readings is no jump to the ambient), and the ambient after half an hour without one.
    #[test]
    fn a_reading_without_a_temperature_takes_the_last_ones() {
        let mut spec = MeasuredSpec::default();
        // As a real cell's setting has it: the model runs at the measured temperature.
        spec.tracker.use_measured_temperature = true;
        let readings = episode();
        let on = readings.iter().position(|r| r.current_a > LOADED_A).expect("a load");
        let gap = on + 20..on + 30;
        let run = |temps: &dyn Fn(usize, &Reading) -> Option<f64>, ambient_c: Option<f64>| {
            let mut stream =
                Stream::new(Box::new(JointUkf::new(spec.ukf_settings(), &spec.tracker)), &spec.tracker, ambient_c);
            let mut out = Vec::new();
            for (k, r) in readings.iter().enumerate() {
                out.push(stream.step(&Reading { temperature_c: temps(k, r), ..*r }).expect("a plausible reading"));
            }
            // Then a reading an hour later, without a temperature.
            let later =
                Reading { time_s: readings.last().unwrap().time_s + 3600.0, temperature_c: None, ..readings[0] };
            out.push(stream.step(&later).expect("a plausible reading"));
            let later_k = stream.last_sample.expect("taken").temperature_k;
            (out.iter().map(|e| (e.q_mobile.to_bits(), e.r_o.to_bits())).collect::<Vec<_>>(), later_k)
        };
        let held = readings[gap.start - 1].temperature_c;
        let dropped = run(&|k, r| if gap.contains(&k) { None } else { r.temperature_c }, Some(5.0));
        let filled = run(&|k, r| if gap.contains(&k) { held } else { r.temperature_c }, Some(5.0));
        assert_eq!(dropped.0, filled.0, "the gap read at the reading before it");
        assert_eq!(dropped.1, 5.0 + KELVIN_0C, "the reading an hour later at the ambient");
        let at_ambient = run(&|k, r| if gap.contains(&k) { Some(5.0) } else { r.temperature_c }, Some(5.0));
        assert_ne!(dropped.0, at_ambient.0, "a cell at 5 C moves the estimate: the rule is seen");
    }

    /// A square wave read once per half-period (B0025's logger) is predicted at its mean current over time,
    /// once its loaded readings have been seen to alternate; a constant load at its loaded mean.
    #[test]
    fn an_alternating_load_is_predicted_at_its_mean_current_over_time() {
        let spec = MeasuredSpec::default();
        let ukf = JointUkf::new(spec.ukf_settings(), &spec.tracker);
        let mut stream = Stream::new(Box::new(ukf), &spec.tracker, None);
        let mut last = None;
        for k in 0..200u32 {
            let on = k >= 3 && k % 2 == 1;
            let r = Reading {
                time_s: 10.2 * f64::from(k),
                voltage_v: if on { 3.75 } else { 4.15 } - 0.001 * f64::from(k),
                current_a: if on { 4.02 } else { 0.001 },
                temperature_c: None,
            };
            last = Some(stream.step(&r).expect("a plausible reading"));
        }
        let i = last.and_then(|e| e.eod_current_a).expect("a load");
        assert!((i - 2.01).abs() < 0.05, "{i} A");
    }

    /// Milliseconds given as seconds: the load then seems to stay on for days. Each reading that would take
    /// it past two days under load without a pause is refused, naming the likely cause; the same readings in
    /// seconds pass.
    #[test]
    fn a_stream_in_milliseconds_read_as_seconds_is_refused_once_its_load_outlasts_any_discharge() {
        let spec = TrackerSpec::default();
        let readings = episode();
        let mut stream = Stream::new(Box::new(WindowFitCalibrator::new(&spec)), &spec, None);
        assert!(readings.iter().all(|r| stream.step(r).is_ok()), "the same readings in seconds");
        let mut stream = Stream::new(Box::new(WindowFitCalibrator::new(&spec)), &spec, None);
        let on = readings.iter().position(|r| r.current_a > LOADED_A).expect("a load");
        let (mut taken, mut refused) = (0usize, 0usize);
        for r in &readings {
            match stream.step(&Reading { time_s: r.time_s * 1000.0, ..*r }) {
                Ok(_) => taken += 1,
                Err(e) => {
                    assert!(matches!(e, ReadingError::LoadTooLong { .. }), "{e}");
                    assert!(e.to_string().contains("time_ms"), "{e}");
                    refused += 1;
                }
            }
        }
        // Every loaded reading after the first two days (in stretched time) of load is refused.
        let load_on_s = readings[on].time_s * 1000.0;
        let late = readings.iter().filter(|r| r.current_a > LOADED_A && r.time_s * 1000.0 - load_on_s > MAX_LOADED_S);
        assert!(refused > 0 && refused >= late.count(), "refused {refused}, taken {taken}");
        assert_eq!(taken + refused, readings.len());
    }

    /// A current step the voltage does not follow is refused, for up to two readings at its level (a spike
    /// written twice); a step whose voltage sample lagged is taken at its next reading, and after a gap of
    /// more than half an hour no step is measured against the stale reading (a rest that resumes near the
    /// last loaded voltage).
    #[test]
    fn a_current_step_the_voltage_does_not_follow_is_refused_for_two_readings() {
        let spec = TrackerSpec::default();
        let mut stream = Stream::new(Box::new(WindowFitCalibrator::new(&spec)), &spec, None);
        let at =
            |time_s: f64, voltage_v: f64, current_a: f64| Reading { time_s, voltage_v, current_a, temperature_c: None };
        for k in 0..5 {
            stream.step(&at(10.0 * k as f64, 3.9 - 0.001 * k as f64, 2.0)).unwrap();
        }
        let e = stream.step(&at(50.0, 3.895, 8.0)).unwrap_err();
        assert!(matches!(e, ReadingError::CurrentGlitch { .. }), "{e}");
        // A logger that wrote the bad value twice: the second is refused too, and the reading after, back at
        // 2 A, meets no step.
        assert!(matches!(stream.step(&at(51.0, 3.895, 8.0)), Err(ReadingError::CurrentGlitch { .. })));
        stream.step(&at(52.0, 3.895, 2.0)).unwrap();
        // A step of the load the voltage sample lags: its first reading is refused, the next, moved, taken.
        assert!(matches!(stream.step(&at(53.0, 3.894, 8.0)), Err(ReadingError::CurrentGlitch { .. })));
        stream.step(&at(54.0, 3.5, 8.0)).unwrap();
        assert_eq!(stream.readings(), 7);
        // A level the voltage never follows is taken at its third attempt in a row, and only in a row: after
        // another refusal the count starts again.
        let mut stream = Stream::new(Box::new(WindowFitCalibrator::new(&spec)), &spec, None);
        for k in 0..5 {
            stream.step(&at(10.0 * k as f64, 3.9 - 0.001 * k as f64, 2.0)).unwrap();
        }
        assert!(matches!(stream.step(&at(50.0, 3.895, 8.0)), Err(ReadingError::CurrentGlitch { .. })));
        assert!(stream.step(&at(55.0, f64::NAN, 8.0)).is_err());
        assert!(matches!(stream.step(&at(56.0, 3.895, 8.0)), Err(ReadingError::CurrentGlitch { .. })));
        assert!(matches!(stream.step(&at(57.0, 3.895, 8.0)), Err(ReadingError::CurrentGlitch { .. })));
        stream.step(&at(60.0, 3.894, 8.0)).unwrap();
        stream.step(&at(70.0, 3.6, 8.0)).unwrap();
        // Two days later, at rest 5 mV above the last loaded reading: no step against it.
        stream.step(&at(70.0 + 2.0 * 86_400.0, 3.605, 0.0)).unwrap();
        assert_eq!(stream.readings(), 8);
        // A spike of four readings the voltage never follows: taken from its third (the stream cannot know it
        // will end), and the reading back at the current before it is taken at once, not refused against it.
        let mut stream = Stream::new(Box::new(WindowFitCalibrator::new(&spec)), &spec, None);
        for k in 0..5 {
            stream.step(&at(10.0 * k as f64, 3.9 - 0.001 * k as f64, 2.0)).unwrap();
        }
        for t in [50.0, 51.0] {
            assert!(matches!(stream.step(&at(t, 3.895, 42.0)), Err(ReadingError::CurrentGlitch { .. })));
        }
        stream.step(&at(52.0, 3.895, 42.0)).unwrap();
        stream.step(&at(53.0, 3.895, 42.0)).unwrap();
        stream.step(&at(54.0, 3.895, 2.0)).unwrap();
        // Once back, a new spike is refused as before.
        assert!(matches!(stream.step(&at(60.0, 3.894, 42.0)), Err(ReadingError::CurrentGlitch { .. })));
        stream.step(&at(61.0, 3.894, 2.0)).unwrap();
        assert_eq!(stream.readings(), 9);
    }

    /// The stream gives what the calibrator alone gives, reading by reading, and refuses a bad reading
    /// without stepping the calibrator (the run after it is the run without it).
    #[test]
    fn stream_matches_the_bare_calibrator_and_skips_bad_readings() {
        let spec = TrackerSpec::default();
        let readings = episode();
        let mut bare = WindowFitCalibrator::new(&spec);
        let mut stream = Stream::new(Box::new(WindowFitCalibrator::new(&spec)), &spec, None);
        for (k, r) in readings.iter().enumerate() {
            if k == 5 {
                let bad = Reading { voltage_v: f64::NAN, ..*r };
                let e = stream.step(&bad).unwrap_err();
                assert_eq!(e.to_string(), "field `voltage_v` = NaN is not a finite number");
                let back = Reading { time_s: r.time_s - 100.0, ..*r };
                assert!(matches!(stream.step(&back), Err(ReadingError::TimeNotIncreasing { .. })));
                let mv = Reading { voltage_v: r.voltage_v * 1000.0, ..*r };
                assert!(matches!(stream.step(&mv), Err(ReadingError::VoltageOutOfRange { .. })));
                let ma = Reading { current_a: 2000.0, ..*r };
                let e = stream.step(&ma).unwrap_err();
                assert!(matches!(e, ReadingError::CurrentOutOfRange { .. }) && e.to_string().contains("current_ma"));
                let kelvin = Reading { temperature_c: Some(297.15), ..*r };
                let e = stream.step(&kelvin).unwrap_err();
                assert!(
                    matches!(e, ReadingError::TemperatureOutOfRange { .. }) && e.to_string().contains("temperature_k")
                );
                // One timestamp in milliseconds since the epoch: refused, and the readings after it go on.
                let far = Reading { time_s: 1.7e12, ..*r };
                assert!(matches!(stream.step(&far), Err(ReadingError::TimeJump { .. })));
                // A lone current spike the voltage does not follow (40 A, the voltage as it was): refused, and
                // the reading after it meets no step.
                let spike = Reading { current_a: r.current_a + 40.0, ..*r };
                let e = stream.step(&spike).unwrap_err();
                assert!(matches!(e, ReadingError::CurrentGlitch { .. }) && e.to_string().contains("glitch"), "{e}");
            }
            let s = Sample {
                t_s: r.time_s,
                voltage_v: r.voltage_v,
                current_a: r.current_a,
                temperature_k: r.temperature_c.unwrap() + KELVIN_0C,
                request: Request::Unknown,
            };
            bare.step(&s);
            let e = stream.step(r).unwrap();
            assert_eq!(e.q_mobile, bare.estimate().q_mobile_c, "reading {k}");
            assert_eq!(e.r_o, bare.estimate().r_o_ohm, "reading {k}");
            assert_eq!(e.q_mobile_lo, bare.interval().map(|iv| iv.q_mobile_c[0]));
        }
        assert_eq!(stream.readings(), readings.len() as u64);
    }

    /// The setting: default, the config's, the policy's (its design and filter kept under a config), the
    /// doctor's model on top; and the refusals.
    #[test]
    fn resolve_takes_config_then_policy_then_default() {
        let d = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        assert_eq!(d.spec, MeasuredSpec::default());
        let mut trained = MeasuredSpec { design: Design::WindowFit, ..MeasuredSpec::default() };
        trained.tracker.prior = Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.12 };
        trained.ukf = Some(crate::JointUkfSettings { meas_std_v: 0.01, ..Default::default() });
        let task = Task::Measured(trained.clone());
        let rl = resolve(CalibratorKind::Rl, None, Some((&task, "p.bcalpol")), None).unwrap();
        assert_eq!(rl.spec, trained);
        let mut cell = MeasuredSpec::default();
        cell.tracker.cutoff_v = 2.7;
        let both = resolve(CalibratorKind::Rl, Some(&cell), Some((&task, "p.bcalpol")), None).unwrap();
        assert_eq!((both.spec.tracker.cutoff_v, both.spec.design), (2.7, Design::WindowFit));
        assert_eq!(both.ukf().meas_std_v, 0.01);
        let ext = ModelExtension { causes: vec!["thermal".into()], ..Default::default() };
        let on = resolve(CalibratorKind::Fit, Some(&cell), None, Some(&ext)).unwrap();
        assert!(on.spec.tracker.use_measured_temperature && on.spec.tracker.model.has("thermal"));
        assert_eq!(resolve(CalibratorKind::Rl, None, None, None).unwrap_err(), StreamError::NoPolicy);
        assert_eq!(
            resolve(CalibratorKind::Fit, None, Some((&task, "p")), None).unwrap_err(),
            StreamError::PolicyWithoutRl("fit")
        );
        let e = resolve(CalibratorKind::Rl, None, Some((&task, "p")), Some(&ext)).unwrap_err();
        assert!(e.to_string().contains("trained on the base model"), "{e}");
        assert_eq!("adaptive-ukf".parse::<CalibratorKind>().unwrap(), CalibratorKind::AdaptiveUkf);
        assert!("kalman".parse::<CalibratorKind>().is_err());
    }

    /// The prediction comes after the first loaded reading, lies ahead of it, and moves earlier with a
    /// larger current.
    #[test]
    fn eod_prediction_is_ahead_and_falls_with_current() {
        let spec = TrackerSpec::default();
        let mut stream = Stream::new(Box::new(Uncalibrated::new(&spec)), &spec, Some(20.0));
        let rest = stream.step(&Reading { time_s: 0.0, voltage_v: 4.1, current_a: 0.0, temperature_c: None }).unwrap();
        assert_eq!((rest.eod_s, rest.eod_current_a), (None, None));
        let e = stream.step(&Reading { time_s: 10.0, voltage_v: 3.95, current_a: 2.0, temperature_c: None }).unwrap();
        assert_eq!(e.eod_current_a, Some(2.0));
        let at_2a = e.eod_s.expect("a prediction once loaded");
        assert!(at_2a > 10.0, "{at_2a}");
        let at_4a = stream.predict_eod_s(4.0).unwrap();
        assert!(at_4a < at_2a, "{at_4a} vs {at_2a}");
    }

    /// At the first reading past half of a discharge: the calibrator's own predicted end, the one served and
    /// its interval (absolute times, s), whether the flag held, and the discharge's last reading's time, s.
    #[derive(Clone, Copy, Debug)]
    struct Half {
        own_s: f64,
        served_s: f64,
        interval_s: Option<(f64, f64)>,
        flag: bool,
        end_s: f64,
    }

    /// Steps `stream` through each discharge of `readings` (each from `starts[d]`, `starts` ending with the
    /// readings' count) and returns, per discharge, its [`Half`] at the first reading past half of it
    /// (`flag` of the estimate there), and the first discharge where `flag` held at any reading.
    fn at_half_of_each(
        stream: &mut Stream<'_>,
        readings: &[Reading],
        starts: &[usize],
        flag: impl Fn(&Estimate) -> bool,
    ) -> (Vec<Half>, Option<usize>) {
        let (mut halves, mut first) = (Vec::new(), None);
        for (d, w) in starts.windows(2).enumerate() {
            let run = &readings[w[0]..w[1]];
            let on = run.iter().find(|r| r.current_a > LOAD_THRESHOLD_A).unwrap().time_s;
            let end = run.last().unwrap().time_s;
            let mut at_half = None;
            for r in run {
                let e = stream.step(r).unwrap();
                if flag(&e) {
                    first.get_or_insert(d);
                }
                if at_half.is_none() && r.time_s >= on + 0.5 * (end - on) {
                    let own = stream.predict_eod_s(e.eod_current_a.unwrap()).unwrap();
                    at_half = Some(Half {
                        own_s: own,
                        served_s: e.eod_s.unwrap(),
                        interval_s: e.eod_lo_s.zip(e.eod_hi_s),
                        flag: flag(&e),
                        end_s: end,
                    });
                }
            }
            halves.push(at_half.unwrap());
        }
        (halves, first)
    }

    /// `n` discharges of a cycler's protocol (a constant 2 A after a 30 s rest, read every 10-20 s) joined
    /// end to end, `cell(k, spec)` setting discharge k's cell. Each ends where the cell's true voltage
    /// crossed 3.0 V: its last reading reads it. The readings and where each discharge starts, the end last.
    fn cycler_life(n: u64, cell: impl Fn(u64, EpisodeSpec) -> EpisodeSpec) -> (Vec<Reading>, Vec<usize>) {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(4);
        let first = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let (mut readings, mut starts) = joined(
            &cfg,
            (0..n).map(|k| {
                cell(
                    k,
                    EpisodeSpec {
                        noise_seed: first.noise_seed + k,
                        kind: LoadKind::ConstantCurrent,
                        profile: LoadProfile::Piecewise(vec![(0.0, Load::CurrentA(0.0)), (30.0, Load::CurrentA(2.0))]),
                        rest_s: 30.0,
                        interval_s: [10.0, 20.0],
                        ..first.clone()
                    },
                )
            }),
        );
        starts.push(readings.len());
        for end in &starts[1..] {
            let last = &mut readings[end - 1];
            last.voltage_v = last.voltage_v.min(2.99);
        }
        (readings, starts)
    }

    /// Simulated discharges joined end to end, each 3 h after the last one's final reading (the charges
    /// between them unseen): the readings and where each discharge starts.
    fn joined(cfg: &ScenarioConfig, specs: impl IntoIterator<Item = EpisodeSpec>) -> (Vec<Reading>, Vec<usize>) {
        let (mut readings, mut starts, mut offset_s) = (Vec::new(), Vec::new(), 0.0);
        for spec in specs {
            starts.push(readings.len());
            readings.extend(simulate(cfg, &spec).unwrap().samples.iter().map(|s| Reading {
                time_s: s.t_s + offset_s,
                voltage_v: s.voltage_v,
                current_a: s.current_a,
                temperature_c: Some(s.temperature_k - KELVIN_0C),
            }));
            offset_s = readings.last().unwrap().time_s + 3.0 * 3600.0;
        }
        (readings, starts)
    }

    /// Simulated discharges joined end to end, each `gaps_h[k]` hours after the last one's final reading.
    fn joined_with_gaps(cfg: &ScenarioConfig, specs: &[EpisodeSpec], gaps_h: &[f64]) -> (Vec<Reading>, Vec<usize>) {
        let (mut readings, mut starts, mut offset_s) = (Vec::new(), Vec::new(), 0.0);
        for (k, spec) in specs.iter().enumerate() {
            starts.push(readings.len());
            readings.extend(simulate(cfg, spec).unwrap().samples.iter().map(|s| Reading {
                time_s: s.t_s + offset_s,
                voltage_v: s.voltage_v,
                current_a: s.current_a,
                temperature_c: Some(s.temperature_k - KELVIN_0C),
            }));
            offset_s = readings.last().unwrap().time_s + gaps_h.get(k).copied().unwrap_or(3.0) * 3600.0;
        }
        (readings, starts)
    }

    /// A discharge started far short of full (30 % of a full charge after nine from 80-98 %: its rest 150 mV and
    /// more below its neighbours') is scored like any, but teaches the stream's rules nothing: its error is not
    /// the error of the discharges they serve. The intervals' widening, learned on the nine before it, stays
    /// learned on those nine when it ends, where a discharge from a full charge adds itself to them.
    #[test]
    fn a_discharge_from_far_short_of_full_teaches_the_rules_nothing() {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(7);
        let first = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let soc0 = |k: u64| if k == 9 { 0.3 } else { 0.8 + 0.02 * (k % 10) as f64 };
        let (readings, starts) = joined(
            &cfg,
            (0..11u64).map(|k| EpisodeSpec { soc0: soc0(k), noise_seed: first.noise_seed + k, ..first.clone() }),
        );
        let mut setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        setup.spec.tracker.cutoff_v = 3.1;
        let mut stream = Stream::of(&setup, None, None).unwrap();
        // The widening's discharges learned on at the start of each discharge, and whether it was seen short.
        let (mut learned_on, mut short) = (Vec::new(), Vec::new());
        for (k, r) in readings.iter().enumerate() {
            if starts.contains(&k) {
                learned_on.push(stream.eod_widening()[1].map(|w| w.1));
            }
            stream.step(r).unwrap();
            if r.current_a > LOAD_THRESHOLD_A && starts.iter().rposition(|&s| s <= k) == Some(short.len()) {
                short.push(stream.short_start);
            }
        }
        learned_on.push(stream.eod_widening()[1].map(|w| w.1));
        assert_eq!(short.iter().filter(|&&s| s).count(), 1, "{short:?}");
        assert!(short[9], "the start at 30 % is seen short: {short:?}");
        assert_eq!(&learned_on[9..], &[Some(9), Some(9), Some(10)], "{learned_on:?}");
    }

    /// A cell's life of `n` simulated 2 A discharges (the simulator's own integrator and sampling), each cut at
    /// the cell's 3.0 V and given a knee to a 2.5 V cut-off that lasts 150 s plus 60 s per kelvin the discharge
    /// runs warmer (its temperatures offset by -1 to 1 K, no pattern), its qMobile `q_per_k` C per kelvin
    /// higher too. Returns the readings, each discharge's first reading and (start, measured end) times, s, and
    /// the knee's length per discharge, s.
    #[allow(clippy::type_complexity)]
    fn warm_knee_life(n: usize, q_per_k: f64) -> (Vec<Reading>, Vec<usize>, Vec<(f64, f64)>, Vec<f64>) {
        use bcal_common::battery::Load;
        let cfg = ScenarioConfig { cutoff_v: 2.5, ..ScenarioConfig::default() };
        let offset_k = |k: usize| 2.0 * ((k as f64 * 0.618_034).fract() - 0.5);
        let knee_s: Vec<f64> = (0..n).map(|k| 150.0 + 60.0 * offset_k(k)).collect();
        let (mut readings, mut starts, mut ends, mut offset_s) = (Vec::new(), Vec::new(), Vec::new(), 0.0);
        for (k, &knee_k_s) in knee_s.iter().enumerate() {
            let truth = Degradation { q_mobile_c: 7200.0 - 10.0 * k as f64 + q_per_k * offset_k(k), r_o_ohm: 0.12 };
            let spec = EpisodeSpec::rest_then(truth, 1.0, Load::CurrentA(2.0), cfg.model.params().tb0_k, 60 + k as u64);
            let ep = simulate(&cfg, &spec).unwrap();
            let t_k = cfg.model.params().tb0_k + offset_k(k);
            let cut = ep.samples.iter().position(|s| s.current_a > 1.0 && s.voltage_v < 3.0).unwrap();
            let reading = |t_s: f64, voltage_v: f64, current_a: f64| Reading {
                time_s: t_s + offset_s,
                voltage_v,
                current_a,
                temperature_c: Some(t_k - KELVIN_0C),
            };
            starts.push(readings.len());
            readings.extend(ep.samples[..cut].iter().map(|s| reading(s.t_s, s.voltage_v, s.current_a)));
            let (a, b) = (ep.samples[cut - 1], ep.samples[cut]);
            let at_s = a.t_s + (b.t_s - a.t_s) * (a.voltage_v - 3.0) / (a.voltage_v - b.voltage_v);
            readings.extend(
                (0..=20).map(|j| reading(at_s + knee_k_s * j as f64 / 20.0, 3.0 - 0.51 * j as f64 / 20.0, 2.0)),
            );
            ends.push((ep.samples[0].t_s + offset_s, at_s + knee_k_s * 0.5 / 0.51 + offset_s));
            offset_s = readings.last().unwrap().time_s + 3.0 * 3600.0;
        }
        (readings, starts, ends, knee_s)
    }

    /// A live stream learns how the knee moves with the cell's warmth as `bcal calibrate` does ([`warm_knee_life`]).
    /// Once eight pairs have taught it, the slope is within 10 % of the written one
    /// (in the stream's measure of the knee) and the ends predicted at half of the later discharges scatter
    /// (sd) under two thirds as much as without the knee's move (0.49 against 0.98 % of the discharge).
    #[test]
    fn a_stream_follows_a_knee_that_moves_with_the_cell_s_warmth() {
        let n = 18;
        let (readings, starts, ends, knee_s) = warm_knee_life(n, 0.0);
        let mut setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        setup.spec.tracker.cutoff_v = 2.5;
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let (mut at_half, mut shares) = (vec![None; n], Vec::new());
        for (i, r) in readings.iter().enumerate() {
            let e = stream.step(r).unwrap();
            let k = starts.iter().rposition(|&s| s <= i).unwrap();
            let (start_s, end_s) = ends[k];
            let on_s = start_s + 60.0;
            if at_half[k].is_none() && r.time_s >= on_s + 0.5 * (end_s - on_s) {
                // The end predicted, and the same without the knee's move with warmth (2 A through the knee).
                let move_s = stream.knee_warmth.zip(stream.warmth_k).map_or(0.0, |(w, t)| w.move_c(t) / 2.0);
                at_half[k] = e.eod_s.map(|p| ((p - end_s) / (end_s - on_s), (p - move_s - end_s) / (end_s - on_s)));
            }
            if starts.contains(&(i + 1)) || i + 1 == readings.len() {
                // The stream's knee runs from where the cell passed the model's end voltage (below 3.0 V): a
                // fixed share of the written one here.
                shares.push(stream.knees_c.back().expect("a knee") / (2.0 * knee_s[k]));
            }
        }
        let share = shares.iter().sum::<f64>() / n as f64;
        assert!(shares.iter().all(|s| (s / share - 1.0).abs() < 0.05), "{shares:?}");
        let w = stream.knee_warmth.expect("learned");
        assert!((w.c_per_k / (120.0 * share) - 1.0).abs() < 0.1, "{w:?}, written {:.1} C per K", 120.0 * share);
        let sd = |v: &[f64]| {
            let m = v.iter().sum::<f64>() / v.len() as f64;
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
        };
        let (with, without): (Vec<f64>, Vec<f64>) =
            (3 + 8 + 1..n).map(|k| at_half[k].expect("a prediction at half")).unzip();
        assert!(with.iter().zip(&without).any(|(a, b)| a != b), "the knee moved");
        assert!(sd(&with) < 0.65 * sd(&without), "at half {with:?}; without the move {without:?}");
    }

    /// The stream's end takes the share of the knee's warmth move its own record asks, per share of the
    /// discharge, as `bcal calibrate` does (`tune::scale_warmth`, whose test and
    /// [`crate::end_fit::warmth_share`]'s show the share taking off what the method has read): on a life where
    /// the warmth that lengthens the knee also shortens the discharge before it (the cell's qMobile 150 C per
    /// kelvin lower), the calibrator's end is the whole move's until eight moved discharges have ended, then at
    /// every reading the end without the move plus the learned share of it at the reading's share of the
    /// discharge, the share at the end being the least-squares one of the scored ends with and without it.
    #[test]
    fn a_stream_takes_the_share_of_the_knee_s_warmth_move_its_record_asks() {
        let n = 21;
        let (readings, starts, ends, _) = warm_knee_life(n, -150.0);
        let mut setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        setup.spec.tracker.cutoff_v = 2.5;
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let (mut moved_before, mut checked) = (0, 0);
        for (i, r) in readings.iter().enumerate() {
            stream.step(r).unwrap();
            let k = starts.iter().rposition(|&s| s <= i).unwrap();
            let last = |src: usize| stream.sources[src].predictions.last().filter(|p| p.0 == r.time_s).map(|p| p.1);
            let (Some(taken), Some(whole), Some(unmoved)) = (last(METHOD), last(METHOD_WHOLE), last(METHOD_UNMOVED))
            else {
                continue;
            };
            let on_s = ends[k].0 + 60.0;
            match stream.warmth_share.weights[share_bin(on_s, r.time_s, whole)] {
                None => {
                    assert_eq!(taken, whole, "discharge {k}: the whole move before a share is learned");
                    moved_before += usize::from(whole != unmoved);
                }
                Some(a) => {
                    let want = unmoved + a * (whole - unmoved);
                    assert!((taken - want).abs() < 1e-6, "discharge {k} at {}: {taken} against {want}", r.time_s);
                    checked += usize::from(whole != unmoved);
                }
            }
        }
        assert!(moved_before > 0 && checked > 100, "moved readings: {moved_before} before, {checked} with a share");
        // The share at half the discharge, learned on the ten moved discharges the sources still hold.
        let pairs: Vec<(f64, f64)> = stream.sources[METHOD_WHOLE]
            .scored
            .iter()
            .zip(&stream.sources[METHOD_UNMOVED].scored)
            .filter_map(|(w, u)| {
                // Signed, % of the discharge from its load-on (the prediction less its size) to its end.
                let at = |d: &Vec<Outcome>| {
                    let o = d.iter().find(|o| o.fraction == 50)?;
                    Some(100.0 * (o.value - o.measured) / (o.measured - (o.value - o.size)).max(1.0))
                };
                Some((at(w)?, at(u)?))
            })
            .collect();
        let moved = pairs.iter().filter(|p| p.0 != p.1).count();
        assert!(moved >= crate::blend::MIN_BLEND_PAIRS, "{pairs:?}");
        let want = crate::end_fit::warmth_share(&pairs).expect("learned");
        let got = stream.warmth_share.weights[1].expect("learned");
        assert!((got - want).abs() < 1e-9, "{got} against {want}");
    }

    /// A cell whose resistance lies above the setting's range (0.33 ohm against its top of 0.25; the blind cold
    /// cell at 4 A has 0.44-0.52) was followed at the range's top for its whole life, its qMobile bent to make up
    /// for it. After two discharges in a row whose fit sat at the top the stream widens the range (to 0.45 ohm;
    /// qMobile's floor, where its fits bent, too), and the discharges after it end within 5 % of the cell's
    /// resistance.
    #[test]
    fn a_stream_widens_a_range_its_fits_sit_at_the_edge_of() {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(4);
        let first = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let truth = Degradation { r_o_ohm: 0.33, ..first.truth };
        let specs: Vec<EpisodeSpec> = (0..6u64)
            .map(|k| EpisodeSpec { soc0: 0.9, noise_seed: first.noise_seed + k, truth, ..first.clone() })
            .collect();
        let (readings, starts) = joined_with_gaps(&cfg, &specs, &[3.0; 5]);
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let range = setup.spec.tracker.r_o_range_ohm;
        assert!(truth.r_o_ohm > range[1] * 1.3, "the cell lies above the range: {range:?}");
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let mut ends = Vec::new();
        for (k, r) in readings.iter().enumerate() {
            let e = stream.step(r).unwrap();
            if starts.contains(&(k + 1)) || k + 1 == readings.len() {
                ends.push(e.r_o);
            }
        }
        let widened = stream.widened_ranges().expect("the stream widened a range");
        eprintln!("Ro at each discharge's end: {ends:?}; ranges {widened:?}");
        assert_eq!(widened[1], [range[0], range[1] + (range[1] - range[0])]);
        assert!(ends[..2].iter().all(|r| *r <= range[1] + 1e-9), "{ends:?}");
        for r in &ends[3..] {
            assert!((r / truth.r_o_ohm - 1.0).abs() < 0.05, "Ro {r} ohm against the cell's {}", truth.r_o_ohm);
        }
        assert!(stream.range_edges().by_edge[1][1] >= 2);
    }

    /// A stream without the cell's lifetime model whose first known rest is long (60 h, a weekend) and every
    /// later one the usual 3 h, on a cell that does not change: NASA's cells' recovery, taken with the median of
    /// three known rests as the usual one, moves no discharge's start by more than 1 % from a stream with no
    /// recovery. (Taken at the first known rest, every later rest read as short of the usual: 4 % lower each.)
    #[test]
    fn a_first_long_rest_does_not_set_the_usual_one() {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(4);
        let first = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let specs: Vec<EpisodeSpec> =
            (0..8u64).map(|k| EpisodeSpec { soc0: 0.9, noise_seed: first.noise_seed + k, ..first.clone() }).collect();
        let (readings, starts) = joined_with_gaps(&cfg, &specs, &[60.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0]);
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let mut off = setup.clone();
        let fade =
            bcal_common::lifetime::LifetimeModel { amplitude: 0.0, ..LifetimeModel::population(1.4, 3.0 * 3600.0) };
        off.spec.lifetime = Some(fade);
        let run = |setup: &Setup| {
            let mut stream = Stream::of(setup, None, None).unwrap();
            readings.iter().map(|r| stream.step(r).unwrap().q_mobile).collect::<Vec<_>>()
        };
        let (plain, none) = (run(&setup), run(&off));
        for (k, n) in starts.iter().enumerate().skip(1) {
            let (a, b) = (plain[*n], none[*n]);
            assert!((a / b - 1.0).abs() < 0.01, "discharge {k} starts at {a} C against {b} C without recovery");
        }
    }

    /// A cell that regains 8 % of its capacity over a 72 h rest after six discharges 3 h apart (its qMobile
    /// set 8 % higher by hand for the seventh discharge; the lifetime model's recovery sized from the sixth
    /// discharge's capacity, measured here by a plain trapezoid to the first reading below the cut-off).
    /// With the cell's lifetime model a stream starts the seventh discharge from the last end fit moved up
    /// by the recovery (within 3 % of the cell's new qMobile, the end fit's own accuracy) and widens its
    /// prior by the jump's uncertainty; with a model of the fade alone, it starts from the last end fit,
    /// about 8 % low; with none, by NASA's cells' recovery (4.6 % for this rest), between the two and widened
    /// too. After the usual rest no model (no fade) moves anything.
    #[test]
    fn a_lifetime_model_moves_the_carried_value_by_what_a_long_rest_gives_back() {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(4);
        let first = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let q0 = first.truth.q_mobile_c;
        let jump = 0.08;
        let specs: Vec<EpisodeSpec> = (0..7u64)
            .map(|k| EpisodeSpec {
                soc0: 0.9,
                noise_seed: first.noise_seed + k,
                truth: Degradation { q_mobile_c: if k == 6 { q0 * (1.0 + jump) } else { q0 }, ..first.truth },
                ..first.clone()
            })
            .collect();
        let (readings, starts) = joined_with_gaps(&cfg, &specs, &[3.0, 3.0, 3.0, 3.0, 3.0, 72.0]);
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let cutoff_v = setup.spec.tracker.cutoff_v;
        // Every discharge reaches the cut-off: each hands on a measured capacity.
        let capacity_ah = |rs: &[Reading]| {
            let end = rs.iter().position(|r| r.current_a > LOAD_THRESHOLD_A && r.voltage_v < cutoff_v)?;
            Some(
                rs[..=end]
                    .windows(2)
                    .map(|w| 0.5 * (w[0].current_a + w[1].current_a).max(0.0) * (w[1].time_s - w[0].time_s))
                    .sum::<f64>()
                    / 3600.0,
            )
        };
        let caps: Vec<f64> = (0..7)
            .map(|k| {
                capacity_ah(&readings[starts[k]..*starts.get(k + 1).unwrap_or(&readings.len())])
                    .expect("reaches the cut-off")
            })
            .collect();
        // A over the jump a 72 h rest gives over the usual 3 h with tau = 24 h: exp(-3/24) - exp(-72/24).
        let tau_rest_s = 24.0 * 3600.0;
        let share = (-3.0f64 / 24.0).exp() - (-3.0f64).exp();
        let life = bcal_common::lifetime::LifetimeModel {
            quantity: bcal_common::lifetime::Quantity::CapacityAh,
            intercept: caps[0],
            per_cycle: 0.0,
            reference_cycle: 1.0,
            per_kelvin: 0.0,
            per_ampere: 0.0,
            reference: Condition { ambient_c: 20.0, current_a: 2.0 },
            amplitude: jump * caps[5] / share,
            tau_rest_s,
            decay_discharges: 5.0,
            usual_rest_s: 3.0 * 3600.0,
            residual_sd: 0.001,
            jump_sd_fraction: 0.5,
        };
        let mut with = setup.clone();
        with.spec.lifetime = Some(life);
        let run = |setup: &Setup| {
            let mut stream = Stream::of(setup, None, None).unwrap();
            let mut out = Vec::new();
            for r in &readings {
                out.push((stream.step(r).unwrap(), stream.prior_width()));
            }
            out
        };
        // A model of the fade alone (no recovery) turns the recovery off; no model at all follows the life by
        // the recovery NASA's cells show (`LifetimeModel::population`).
        let mut fade = setup.clone();
        fade.spec.lifetime = Some(bcal_common::lifetime::LifetimeModel { amplitude: 0.0, ..life });
        let (ours, plain, off) = (run(&with), run(&setup), run(&fade));
        for k in 1..6 {
            for other in [&plain, &off] {
                let (a, b) = (ours[starts[k]].0.q_mobile, other[starts[k]].0.q_mobile);
                assert!((a / b - 1.0).abs() < 0.005, "discharge {k} after the usual rest: {a} against {b} C");
            }
        }
        let n = starts[6];
        let truth = q0 * (1.0 + jump);
        let (a, b, c) = (ours[n].0.q_mobile, plain[n].0.q_mobile, off[n].0.q_mobile);
        eprintln!(
            "caps {caps:?}; after the rest: with {a} ({:+.4}), population {b} ({:+.4}), none {c} ({:+.4})",
            a / truth - 1.0,
            b / truth - 1.0,
            c / truth - 1.0
        );
        assert!(
            (a / truth - 1.0).abs() < 0.03,
            "with the lifetime model the 7th discharge starts from {a} C, the cell has {truth} C"
        );
        assert!((c / truth - 1.0).abs() > 0.045, "without a recovery, {c} C against the cell's {truth} C");
        // The population's 72 h rest gives back 4.6 % over a 3 h one: most of this cell's 8 %.
        assert!(c / truth < b / truth - 0.03 && b / truth < a / truth, "{c} < {b} < {a} C");
        let (wa, wb, wc) = (ours[n].1.unwrap(), plain[n].1.unwrap(), off[n].1.unwrap());
        assert_eq!((wa.1, wb.1, wc.1), (WidthSource::Learned, WidthSource::Learned, WidthSource::Learned));
        for w in [wa, wb] {
            assert!(w.0[0] > 1.5 * wc.0[0] && (w.0[1] - wc.0[1]).abs() < 0.2 * wc.0[1], "{w:?} against {wc:?}");
        }
    }

    /// Seven discharges of one cell joined end to end, three hours apart (the charges between them unseen):
    /// each starts from what the one before told: the charge its end measured (within 3 % of the cell's
    /// qMobile) where its readings reached the cut-off, else the estimate it ended with; its EOD current
    /// anew, with the one before's posterior as its width, and from the sixth on a width learned from the
    /// changes between the discharges' carried values, narrower than the filter's own where the cell does
    /// not change; and every discharge ends within the filter's own error of the cell at this sampling
    /// (10-20 s, piecewise: up to 14 % here). That one filter run on across the
    /// gaps goes wrong on a real cell is `realcell/tests/stream_across_discharges.rs`.
    #[test]
    fn a_stream_starts_each_discharge_from_the_last_with_a_width_learned_from_its_history() {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(4);
        let first = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let (readings, starts) = joined(
            &cfg,
            (0..7u64).map(|k| EpisodeSpec {
                soc0: [0.95, 0.8, 0.9, 1.0, 0.85, 0.95, 0.9][k as usize],
                noise_seed: first.noise_seed + k,
                ..first.clone()
            }),
        );
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let mut plain = Stream::new(build(&setup, None).unwrap(), &setup.spec.tracker, None);
        let (mut ours, mut widths, mut theirs) = (Vec::new(), Vec::new(), Vec::new());
        for r in &readings {
            ours.push(stream.step(r).unwrap());
            widths.push(stream.prior_width());
            theirs.push(plain.step(r).unwrap());
        }
        assert_eq!((stream.discharges(), plain.discharges()), (7, 1));
        let truth = first.truth.q_mobile_c;
        let cutoff_v = setup.spec.tracker.cutoff_v;
        let mut ended = 0;
        for (k, &n) in starts.iter().enumerate().skip(1) {
            assert!(ours[n..].iter().take_while(|e| e.discharge == k as u32).count() > 10);
            assert_eq!(ours[n - 1].discharge + 1, ours[n].discharge);
            // A discharge whose readings crossed the cut-off under load hands on the charge its end
            // measured (the end fit); one that stopped above it, its final estimate.
            if readings[starts[k - 1]..n].iter().any(|r| r.current_a > LOAD_THRESHOLD_A && r.voltage_v < cutoff_v) {
                ended += 1;
                let q = ours[n].q_mobile;
                assert!((q / truth - 1.0).abs() < 0.03, "discharge {k} starts from {q} C, truth {truth} C");
            } else {
                // Where it ended, up to the round trip of the handed-on prior through the filter's range
                // units (a few roundings of numbers of this size).
                let (start, end) = (ours[n].q_mobile, ours[n - 1].q_mobile);
                assert!(
                    (start - end).abs() <= 8.0 * f64::EPSILON * end.abs(),
                    "discharge {k} starts at {start} C, where {} ended: {end} C",
                    k - 1
                );
            }
            assert_eq!(ours[n].eod_current_a, None, "the EOD current starts over with the discharge");
            let source = if k >= 5 { WidthSource::Learned } else { WidthSource::Posterior };
            assert_eq!(widths[n].map(|w| w.1), Some(source), "discharge {k}: {:?}", widths[n]);
            let q_end = ours[n - 1].q_mobile;
            assert!((q_end / truth - 1.0).abs() < 0.2, "discharge {} ends at {q_end} C, truth {truth} C", k - 1);
        }
        assert!(ended >= 3, "only {ended} of 6 discharges reached the cut-off: the end fit is not tested");
        assert_eq!(widths[0], None, "the first discharge has the filter's own width");
        let w = widths.last().unwrap().unwrap().0;
        let own = setup.ukf().prior_std_z;
        assert!(w[0] < own[0] && w[1] < own[1], "learned {w:?}, the filter's own {own:?}");
        // The first discharge is the same either way (a stream that keeps no readings has no charge delivered).
        let undelivered =
            |e: &Estimate| Estimate { delivered_ah: None, delivered_lo_ah: None, delivered_hi_ah: None, ..*e };
        let (a, b): (Vec<Estimate>, Vec<Estimate>) = (
            ours[..starts[1]].iter().map(undelivered).collect(),
            theirs[..starts[1]].iter().map(undelivered).collect(),
        );
        assert_eq!(a, b, "the first discharge is the same either way");
        let q_end = ours.last().unwrap().q_mobile;
        assert!((q_end / truth - 1.0).abs() < 0.2, "the last discharge ends at {q_end} C, truth {truth} C");
    }

    /// Five discharges of one cell, the fourth from 40 % of a full charge: it reaches its cut-off like the
    /// others, but its rest shows the short start against the three before it, so it hands on what was
    /// carried into it (its own end fit, read from a starting charge on the flat of the voltage curve, is not
    /// what the cell holds) and the fifth starts where the fourth did; the full starts are not taken for short.
    #[test]
    fn a_discharge_started_from_a_partial_charge_hands_on_what_was_carried_into_it() {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(4);
        let first = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let socs = [1.0, 1.0, 1.0, 0.4, 1.0];
        let (readings, starts) = joined(
            &cfg,
            socs.iter().enumerate().map(|(k, &soc0)| EpisodeSpec {
                soc0,
                noise_seed: first.noise_seed + k as u64,
                kind: LoadKind::ConstantCurrent,
                profile: LoadProfile::Piecewise(vec![(0.0, Load::CurrentA(0.0)), (30.0, Load::CurrentA(2.0))]),
                rest_s: 30.0,
                ..first.clone()
            }),
        );
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let mut ours = Vec::new();
        let mut short = Vec::new();
        for r in &readings {
            ours.push(stream.step(r).unwrap());
            short.push(stream.short_start);
        }
        assert_eq!(stream.discharges(), 5);
        let cutoff_v = setup.spec.tracker.cutoff_v;
        let ended = |k: usize| {
            let to = starts.get(k + 1).copied().unwrap_or(readings.len());
            readings[starts[k]..to].iter().any(|r| r.current_a > LOAD_THRESHOLD_A && r.voltage_v < cutoff_v)
        };
        assert!((0..5).all(ended), "every discharge reaches its cut-off");
        let seen: Vec<bool> = (0..5).map(|k| short[starts.get(k + 1).copied().unwrap_or(readings.len()) - 1]).collect();
        assert_eq!(seen, [false, false, false, true, false]);
        let (fourth, fifth) = (ours[starts[3]].q_mobile, ours[starts[4]].q_mobile);
        assert!(
            (fifth - fourth).abs() <= 8.0 * f64::EPSILON * fourth.abs(),
            "the fifth starts at {fifth} C, not where the short fourth did: {fourth} C"
        );
        let truth = first.truth.q_mobile_c;
        assert!((fifth / truth - 1.0).abs() < 0.03, "the fifth starts at {fifth} C, truth {truth} C");
    }

    /// A cell whose diffusion is half again slower than the model's, cycled at 1 and 4 A: the end fit each
    /// discharge hands on holds the model's error at its current (lower at 4 A), so a discharge at the other
    /// current starts off by it. Once three discharges have moved their current, the stream moves each prior at
    /// the load-on by what those showed: the prior it reads from the load-on is nearer the end fit the
    /// discharge itself measures than the one it rested on, on most discharges after a move.
    #[test]
    fn a_discharge_at_another_current_starts_from_a_prior_moved_at_its_load_on() {
        let currents = [1.0, 4.0, 4.0, 1.0, 4.0, 1.0, 1.0, 4.0, 1.0, 4.0, 4.0, 1.0, 4.0, 1.0];
        let (readings, starts) = cycler_life(currents.len() as u64, |k, spec| EpisodeSpec {
            profile: LoadProfile::Piecewise(vec![
                (0.0, Load::CurrentA(0.0)),
                (30.0, Load::CurrentA(currents[k as usize])),
            ]),
            cell_error: CellError { diffusion_scale: 1.5, ..CellError::default() },
            ..spec
        });
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let ours: Vec<Estimate> = readings.iter().map(|r| stream.step(r).unwrap()).collect();
        let slope = stream.current_slope.learned().expect("a slope learned from the moves");
        assert!(slope < 0.0, "the end fit falls at the higher current: slope {slope}");
        let (mut nearer, mut moved) = (0, 0);
        for k in 4..currents.len() - 1 {
            if currents[k] == currents[k - 1] {
                continue;
            }
            let on = (starts[k]..starts[k + 1]).find(|&i| readings[i].current_a > LOAD_THRESHOLD_A).unwrap();
            // What it rested on, what it reads from the load-on, and what it hands on (the next one's start).
            let (rested, chosen, measured) = (ours[on - 1].q_mobile, ours[on].q_mobile, ours[starts[k + 1]].q_mobile);
            moved += 1;
            nearer += usize::from((chosen - measured).abs() < (rested - measured).abs());
        }
        assert!(moved >= 5 && 4 * nearer >= 3 * moved, "nearer the end fit on {nearer} of {moved}");
    }

    /// Twelve discharges of one cell joined end to end: each discharge's predictions are scored at 10, 50
    /// and 90 % of it once its voltage crosses the cut-off under load, and from the tenth discharge (nine
    /// scored) each prediction carries a 90 % interval whose half-width, as a share of the predicted
    /// duration, is the conformal rank of the last ten scored errors at the share the prediction is at
    /// (nine or ten of them: the largest) times the online scale those intervals earned (up 0.1 x 0.9 in
    /// log on a miss, down 0.1 x 0.1 on a hit), in quadrature with what each discharge's start adds (starts
    /// at 80-98 % of a full charge, read off rests with 3 mV of noise: the stream's own term, read here at
    /// each reading, each scored error's share beyond its start's term learned), recomputed here from the
    /// estimates and the readings.
    #[test]
    fn eod_intervals_are_learned_from_the_discharges_the_stream_followed_to_their_cut_off() {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(7);
        let first = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let (readings, mut starts) = joined(
            &cfg,
            (0..12u64).map(|k| EpisodeSpec {
                soc0: 0.8 + 0.02 * (k % 10) as f64,
                noise_seed: first.noise_seed + k,
                ..first.clone()
            }),
        );
        starts.push(readings.len());
        // A cut-off above the simulator's (3.0 V, where an episode stops, its last noisy reading not always
        // below it): every discharge crosses it under load.
        let mut setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        setup.spec.tracker.cutoff_v = 3.1;
        let cutoff_v = setup.spec.tracker.cutoff_v;
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let (est, start_s): (Vec<Estimate>, Vec<f64>) =
            readings.iter().map(|r| (stream.step(r).unwrap(), stream.start_half_s)).unzip();
        assert_eq!(stream.discharges(), 12);
        // Each discharge's scores, from its readings: the load-on, the interpolated crossing, and per share the
        // absolute error of the last prediction made by it and that prediction's duration from the load-on,
        // with what the discharge's start adds.
        let mut errors: Vec<([(f64, f64); 3], f64)> = Vec::new();
        // The share of the duration an error needs beyond its start's term.
        let beyond = |(e, size): (f64, f64), start: f64| (e * e - start * start).max(0.0).sqrt() / size;
        let learned = |errors: &[([(f64, f64); 3], f64)], d: usize, b: usize| {
            errors[d.saturating_sub(WINDOW)..d].iter().map(|(e, s)| beyond(e[b], *s)).fold(0.0, f64::max)
        };
        let scale = |errors: &[([(f64, f64); 3], f64)], scored: usize, b: usize| {
            let mut log = 0.0f64;
            for d in MIN_OUTCOMES..scored {
                let w = learned(errors, d, b) * log.exp();
                let ((e, size), start) = (errors[d].0[b], errors[d].1);
                let miss = if e > (w * size).hypot(start) { 1.0 } else { 0.0 };
                log = (log + 0.1 * (miss - 0.1)).clamp(-ADAPT_MAX_LOG, ADAPT_MAX_LOG);
            }
            log.exp()
        };
        let mut scaled = 0;
        for d in 0..12 {
            let (r, e) = (&readings[starts[d]..starts[d + 1]], &est[starts[d]..starts[d + 1]]);
            let loaded: Vec<usize> = (0..r.len()).filter(|&k| r[k].current_a > LOAD_THRESHOLD_A).collect();
            let on = r[loaded[0]].time_s;
            let cross = loaded.iter().position(|&k| r[k].voltage_v < cutoff_v).expect("every discharge ends");
            let (a, b) = (&r[loaded[cross - 1]], &r[loaded[cross]]);
            let end_s = a.time_s + (a.voltage_v - cutoff_v) / (a.voltage_v - b.voltage_v) * (b.time_s - a.time_s);
            let errs = EOD_FRACTIONS_PCT.map(|f| {
                let at_s = on + f64::from(f) / 100.0 * (end_s - on);
                let k = loaded[..cross].iter().rev().find(|&&k| r[k].time_s <= at_s && e[k].eod_s.is_some()).unwrap();
                let p = e[*k].eod_s.unwrap();
                ((end_s - p).abs(), (p - on).max(1.0))
            });
            // The start's term, as the discharge's last reading before its crossing gave it.
            let start = start_s[starts[d] + loaded[cross - 1]];
            errors.push((errs, start));
            // Readings from this discharge's own crossing on already learn from it.
            let crossed = loaded[cross];
            for (k, x) in e.iter().enumerate() {
                let scored = if k >= crossed { d + 1 } else { d };
                let (Some(p), Some(lo), Some(hi)) = (x.eod_s, x.eod_lo_s, x.eod_hi_s) else {
                    assert!(scored < 9 || x.eod_s.is_none(), "discharge {d}, reading {k}: no interval");
                    continue;
                };
                assert!(scored >= 9, "discharge {d}, reading {k}: an interval after {scored} scored discharges");
                let bin = share_bin(on, x.time_s, p);
                let expect = learned(&errors, scored, bin);
                let f = scale(&errors, scored, bin);
                scaled += usize::from((f - 1.0).abs() > 1e-9);
                let half = (expect * f * (p - on).max(1.0)).hypot(start_s[starts[d] + k]);
                assert!((hi - p - half).abs() < 1e-6 * p, "discharge {d}, reading {k}: {hi} - {p} against {half}");
                assert!((lo - (p - half).max(x.time_s)).abs() < 1e-6 * p, "discharge {d}, reading {k}");
            }
            if d >= 9 {
                let n = e[..crossed].iter().filter(|x| x.eod_lo_s.is_some()).count();
                assert!(n > crossed / 2, "discharge {d}: {n} of {crossed} readings before the end have an interval");
            }
        }
        assert!(scaled > 0, "no interval here was scaled: the online scale is not tested");
        // The first discharge has no noise read before it.
        assert!(
            errors[1..].iter().all(|(_, s)| *s > 0.0),
            "every start off full adds: {:?}",
            errors.iter().map(|e| e.1).collect::<Vec<_>>()
        );
        let w = stream.eod_widening();
        assert!(w.iter().all(|w| w.is_some_and(|(a, n)| a > 0.0 && n == WINDOW)), "{w:?}");
    }

    /// [`cycler_life`] of `n` discharges of a cell with what the doctor finds in B0005 (the electrodes'
    /// balance shifted, slower charge transfer), each from a charge of 85-94 %, with each discharge's
    /// parameters.
    fn b0005_like_life(n: u64) -> (Vec<Reading>, Vec<usize>, Vec<Degradation>) {
        let truths = std::cell::RefCell::new(Vec::new());
        let (readings, starts) = cycler_life(n, |k, spec| {
            truths.borrow_mut().push(spec.truth);
            EpisodeSpec {
                soc0: 0.85 + 0.01 * (k % 10) as f64,
                cell_error: CellError { xp_shift: 0.03, xn_shift: -0.06, kinetics_scale: 0.3, ..Default::default() },
                ..spec
            }
        });
        (readings, starts, truths.into_inner())
    }

    /// Fourteen constant-current discharges of a cell that carries what the doctor finds in B0005 (shifted
    /// electrode balance, slower charge transfer), through the joint UKF on the base model: the readings
    /// pull the filter off the charge each end measured, and the prior alone (the carried end fit, never
    /// moved by the readings) predicts the end at half of the discharge better (0.05-0.75 % against
    /// 0.6-3.5 % of the time to the end on discharges 5-14). From the eleventh discharge (ten scored for
    /// both) it predicts where it beat the filter on at least 8 of the last 10; never before.
    #[test]
    fn the_prior_alone_predicts_where_it_has_beaten_the_calibrator() {
        let (readings, starts, _) = b0005_like_life(14);
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let mut served_from = None;
        for d in 0..14 {
            for r in &readings[starts[d]..starts[d + 1]] {
                let e = stream.step(r).unwrap();
                if e.eod_from_prior {
                    served_from.get_or_insert(d);
                }
            }
        }
        assert_eq!(served_from, Some(10), "the prior predicts from the eleventh discharge");
        assert!(stream.prior_serves()[1], "at half of the discharge: {:?}", stream.prior_serves());
        // With no prior to fall back on, the uncalibrated kind never hands over.
        let plain = resolve(CalibratorKind::Uncalibrated, None, None, None).unwrap();
        let mut un = Stream::of(&plain, None, None).unwrap();
        assert!(readings.iter().all(|r| !un.step(r).unwrap().eod_from_prior));
    }

    /// That `eod_s`, given at `t_s`, is the mean of the last predictions of `sources` (both made at `t_s`),
    /// the second weighing `w`.
    fn assert_blended(stream: &Stream, sources: (usize, usize), w: f64, t_s: f64, eod_s: f64) {
        let last = |src: usize| stream.sources[src].predictions.last().unwrap();
        let (a, b) = (last(sources.0), last(sources.1));
        assert_eq!((a.0, b.0), (t_s, t_s), "both predicted at this reading");
        let want = (1.0 - w) * a.1 + w * b.1;
        assert!((eod_s - want).abs() < 1e-9 * want, "at {t_s} s: {eod_s} against {want}");
    }

    /// The cell of the test before, followed by the joint UKF for ten discharges: once eight have been
    /// followed to the cut-off, every prediction is the weighted mean of the calibrator's (as delivered) and
    /// the prior alone's, the prior's weight (`eod_prior_weight`) between 0 and 1, and at half of the ninth
    /// and tenth discharges the blend is nearer the end than the calibrator's own; before, the calibrator's
    /// own alone.
    #[test]
    fn the_calibrator_is_blended_with_its_prior_once_their_records_tell_the_weight() {
        let (readings, starts, _) = b0005_like_life(10);
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let cutoff_v = stream.spec().cutoff_v;
        for d in 0..10 {
            let run = &readings[starts[d]..starts[d + 1]];
            let on = run.iter().find(|r| r.current_a > LOAD_THRESHOLD_A).unwrap().time_s;
            let end = run.last().unwrap().time_s;
            let mut at_half = None;
            for r in run {
                let e = stream.step(r).unwrap();
                // Predictions under load above the cut-off are recorded for their scores.
                let Some(eod_s) = e.eod_s.filter(|_| r.current_a > LOAD_THRESHOLD_A && r.voltage_v >= cutoff_v) else {
                    continue;
                };
                if d < 8 {
                    assert_eq!(e.eod_prior_weight, 0.0, "discharge {d}");
                    continue;
                }
                let w = e.eod_prior_weight;
                assert!(w > 0.0 && w < 1.0, "discharge {d}: prior weight {w}");
                assert_blended(&stream, (DELIVERED, PRIOR_TWINS + TWIN_DELIVERED), w, r.time_s, eod_s);
                if at_half.is_none() && r.time_s >= on + 0.5 * (end - on) {
                    let own = stream.predict_eod_s(e.eod_current_a.unwrap()).unwrap();
                    at_half = Some(((eod_s - end).abs(), (own - end).abs()));
                }
            }
            if let Some((blend_off, own_off)) = at_half {
                assert!(blend_off < own_off, "discharge {d} at half: blend {blend_off} s off, own {own_off} s");
            }
        }
    }

    /// The blend with the prior is blended in turn with the previous discharge's fit carried over, once the
    /// records of both tell the weight: on the cell of the tests before, followed by the joint UKF with a fit
    /// of each discharge that ended (an oracle: the parameters it was simulated with; the doctor's fit is
    /// tested in `bcal_doctor`), the fit carried over predicts from the second discharge, and on the tenth
    /// (eight scored with it) every prediction is the weighted mean of the blend and the fit's as
    /// delivered, the fit's weight (`eod_previous_weight`) between 0 and 1 (where the prior alone does not
    /// predict alone: then 0); before, 0.
    #[test]
    fn the_blend_is_blended_with_the_previous_discharges_fit_once_their_records_tell_the_weight() {
        let (readings, starts, truths) = b0005_like_life(10);
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let model = setup.spec.tracker.model.clone();
        let fitted = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let n = fitted.clone();
        let mut stream = Stream::of(&setup, None, None).unwrap().with_refit(Box::new(move |_| {
            let k = n.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            Some((truths[k], model.clone()))
        }));
        let cutoff_v = stream.spec().cutoff_v;
        let mut blended_readings = 0;
        for d in 0..10 {
            for r in &readings[starts[d]..starts[d + 1]] {
                let e = stream.step(r).unwrap();
                let Some(eod_s) = e.eod_s.filter(|_| r.current_a > LOAD_THRESHOLD_A && r.voltage_v >= cutoff_v) else {
                    continue;
                };
                let previous = stream.sources[PREVIOUS].predictions.last().map(|p| p.0);
                assert_eq!(previous == Some(r.time_s), d >= 1, "discharge {d}: the fit carried over predicts");
                let w = e.eod_previous_weight;
                if d < 9 {
                    assert_eq!(w, 0.0, "discharge {d}");
                    continue;
                }
                if e.eod_from_prior {
                    // The prior alone predicts alone here (it beat the blend on 8 of the last 10).
                    assert_eq!(w, 0.0);
                    continue;
                }
                blended_readings += 1;
                assert!(w > 0.0 && w < 1.0, "discharge {d}: the fit's weight {w}");
                assert_blended(&stream, (BLENDED, PREVIOUS_TWINS + TWIN_DELIVERED), w, r.time_s, eod_s);
            }
        }
        assert!(blended_readings > 100, "readings of the tenth discharge blended with the fit: {blended_readings}");
        assert_eq!(fitted.load(std::sync::atomic::Ordering::SeqCst), 10, "one fit per discharge that ended");
        assert!(stream.previous_blend_weights().iter().all(Option::is_some), "{:?}", stream.previous_blend_weights());
    }

    /// A cell whose resistance, 0.4 ohm, lies above the default setting's range (0.05-0.25 ohm) hands on
    /// its discharges' fits at the range's top, and the stream counts them ([`Stream::range_edges`]: what
    /// `bcal calibrate --follow` warns of); a cell within the ranges hands on none there.
    #[test]
    fn a_cell_outside_the_ranges_is_followed_at_their_edge_and_counted() {
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        assert_eq!(setup.spec.tracker.r_o_range_ohm, [0.05, 0.25]);
        let edges = |r_o_ohm: f64| {
            let (readings, _) = cycler_life(4, |_, spec| EpisodeSpec {
                truth: Degradation { r_o_ohm, ..spec.truth },
                soc0: 1.0,
                ..spec
            });
            fed(&setup, &readings).range_edges()
        };
        // The fourth discharge has not handed anything on yet (no reading after it); the first, started from
        // the range's middle, may end short of the top.
        let high = edges(0.4);
        assert_eq!((high.discharges, high.by_edge), (3, [[0, 0], [0, high.at_edge]]), "{high:?}");
        assert!(high.at_edge >= 2, "{high:?}");
        let within = edges(0.15);
        assert_eq!(within, RangeEdges { discharges: 3, ..Default::default() }, "{within:?}");
    }

    /// A stream handed a refit ([`Stream::with_refit`]) calls it once per discharge that reaches its cut-off
    /// and runs each next discharge on the model it returns: on a cell with B0005's diagnosed error (the
    /// electrodes' balance shifted, slower charge transfer) followed on the base model, a refit that returns
    /// the cell's own model (an oracle: the doctor's fit is tested in `bcal_doctor`) takes the joint UKF's
    /// end of discharge at half of discharges 2-8 nearer the measured end than without it.
    #[test]
    fn a_stream_runs_each_discharge_on_the_model_refitted_on_the_one_before() {
        let err = CellError { xp_shift: 0.03, xn_shift: -0.06, kinetics_scale: 0.3, ..Default::default() };
        let cell = std::cell::Cell::new(Degradation::default());
        let (readings, starts) = cycler_life(8, |_, spec| {
            cell.set(spec.truth);
            EpisodeSpec { soc0: 1.0, cell_error: err, ..spec }
        });
        let cell = cell.get();
        let truth = err.apply(&ModelExtension {
            causes: vec!["electrode_balance".into(), "charge_transfer".into()],
            ..Default::default()
        });
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let calls = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counted = calls.clone();
        let model = truth.clone();
        let mut refitted = Stream::of(&setup, None, None).unwrap().with_refit(Box::new(move |samples| {
            counted.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            assert!(samples.len() > 10, "the discharge's readings");
            Some((cell, model.clone()))
        }));
        let mut plain = Stream::of(&setup, None, None).unwrap();
        let (with, _) = at_half_of_each(&mut refitted, &readings, &starts, |_| false);
        let (without, _) = at_half_of_each(&mut plain, &readings, &starts, |_| false);
        assert_eq!(calls.load(std::sync::atomic::Ordering::SeqCst), 8, "one refit per discharge that ended");
        assert_eq!(refitted.spec().model, truth);
        let off = |h: &[Half]| h[1..].iter().map(|h| (h.served_s - h.end_s).abs()).sum::<f64>();
        assert!(off(&with) < off(&without), "refitted {} s off in all, without {} s", off(&with), off(&without));
    }

    /// Twenty constant-current discharges of a cell that loses 1.5 % of its mobile charge per discharge,
    /// followed by the uncalibrated kind (each discharge pinned at what the last one's end measured, no
    /// prior alone to hand over to): every prediction comes late by about the charge lost since, 1.4-2.6 %
    /// of the discharge. Once a window of ten discharges has ended with the recentred predictions ahead on
    /// eight, the stream serves them (`eod_recentred`), never before the eleventh discharge; on the last three
    /// they are served at half of each discharge within 0.4 times the model's own error of the end the
    /// readings reach.
    #[test]
    fn a_steady_bias_is_recentred_once_it_has_earned_it() {
        let (readings, starts) = cycler_life(20, |k, spec| EpisodeSpec {
            truth: Degradation { q_mobile_c: 7600.0 * (1.0 - 0.015 * k as f64), ..Degradation::default() },
            soc0: 1.0,
            ..spec
        });
        let setup = resolve(CalibratorKind::Uncalibrated, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let (halves, served_from) = at_half_of_each(&mut stream, &readings, &starts, |e| {
            assert!(!e.eod_from_prior);
            e.eod_recentred
        });
        for (d, h) in halves.iter().enumerate() {
            let (own, served, recentred, end) = (h.own_s, h.served_s, h.flag, h.end_s);
            if d >= 17 {
                assert!(recentred, "discharge {d}: its own prediction at half");
                assert!((served - end).abs() < 0.4 * (own - end).abs(), "discharge {d}: {served} / {own} / {end}");
            } else if !recentred {
                assert_eq!(served, own);
            }
        }
        assert!(served_from.is_some_and(|d| d >= 10), "recentred from discharge {served_from:?}");
        assert!(stream.recentred_serves().iter().all(|s| *s), "{:?}", stream.recentred_serves());
    }

    /// Thirty-two constant-current discharges of a cell whose mobile charge swings by up to 3 % from one
    /// discharge to the next (as B0055's capacity does at 4 C), followed by the uncalibrated kind (each
    /// discharge pinned at what the last one's end measured): each prediction is off by the swing since the
    /// last discharge, which its median error cannot take off, and which the voltage against the last
    /// discharge at the same time since the load came on shows. Once 8 discharges have a voltage change
    /// and a window of ten more has ended with the moved predictions ahead of the recentring on eight, the
    /// stream serves them (`eod_on_voltage_change`), never before the nineteenth discharge; over the last
    /// five they are served at half of each discharge within 0.3 times the model's own error of the end.
    #[test]
    fn an_error_the_voltage_change_shows_is_taken_off_once_it_has_earned_it() {
        let (readings, starts) = cycler_life(32, |k, spec| EpisodeSpec {
            truth: Degradation { q_mobile_c: 7600.0 * (1.0 + 0.03 * (k as f64 * 2.1).sin()), ..Degradation::default() },
            soc0: 1.0,
            ..spec
        });
        let setup = resolve(CalibratorKind::Uncalibrated, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let (halves, served_from) = at_half_of_each(&mut stream, &readings, &starts, |e| e.eod_on_voltage_change);
        let (mut own_off, mut served_off, mut held) = (0.0, 0.0, 0);
        for h in &halves[27..] {
            assert!(h.flag, "not moved at half: {h:?}");
            own_off += (h.own_s - h.end_s).abs();
            served_off += (h.served_s - h.end_s).abs();
            // The interval, learned on what was served, holds the end.
            let (lo, hi) = h.interval_s.expect("an interval by now");
            held += usize::from((lo..=hi).contains(&h.end_s));
        }
        assert!(served_off < 0.3 * own_off, "last five at half: {served_off} s off against {own_off} s");
        assert!(held >= 4, "the served intervals held {held} of the last five ends");
        assert!(served_from.is_some_and(|d| d >= 18), "moved from discharge {served_from:?}");
        assert!(stream.voltage_serves()[1], "{:?}", stream.voltage_serves());
    }

    /// One stream of `kind` over the discharges of `readings` (each from `starts[k]` to `starts[k + 1]`): per
    /// discharge, the end served at the first reading past a tenth of it, the learner's weight there, its
    /// load-on and its last reading's time, s.
    fn served_at_tenth(kind: CalibratorKind, readings: &[Reading], starts: &[usize]) -> Vec<(f64, f64, f64, f64)> {
        let setup = resolve(kind, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let mut out = Vec::new();
        for w in starts.windows(2) {
            let run = &readings[w[0]..w[1]];
            let on = run.iter().find(|r| r.current_a > LOAD_THRESHOLD_A).unwrap().time_s;
            let end = run.last().unwrap().time_s;
            let mut tenth = None;
            for r in run {
                let e = stream.step(r).unwrap();
                if tenth.is_none() && r.time_s >= on + 0.1 * (end - on) {
                    tenth = Some((e.eod_s.unwrap(), e.eod_learned_weight, on, end));
                }
            }
            out.push(tenth.unwrap());
        }
        out
    }

    /// A cell whose charge follows how warm each discharge runs (as a cold cell's does: B0055 at 4 C), which
    /// the model does not carry: discharge k holds 3 % more or less charge as its readings run up to 2 K
    /// warmer or colder than the others (in no order), every discharge warming by 3 K as it goes. Early in each
    /// discharge the joint UKF has not yet read the difference, and the rules deliver it late or early by
    /// the difference from the last one. The `ukf_learned` kind gives what `ukf` gives until its learner on
    /// the record has a weight, then moves the end by what the record expects at the discharge's warmth: at
    /// a tenth of each of the last twelve of 44 discharges its error is less than 0.6 of `ukf`'s (0.57; with the
    /// warmth hidden from it, every discharge reading alike warm, 0.65). (The cell held
    /// 7600 C until 2026-11-30, partly above the default range's top, where the filter was held: the stream
    /// now widens a range its fits sit at the edge of, and the cell was moved inside it.)
    #[test]
    fn the_learner_on_the_record_takes_off_what_follows_the_discharges_warmth() {
        let u = |k: u64| ((k * 7) % 13) as f64 / 6.0 - 1.0;
        let (mut readings, starts) = cycler_life(44, |k, spec| EpisodeSpec {
            truth: Degradation { q_mobile_c: 7200.0 * (1.0 + 0.03 * u(k)), ..Degradation::default() },
            soc0: 1.0,
            ..spec
        });
        for (k, w) in starts.windows(2).enumerate() {
            let run = &mut readings[w[0]..w[1]];
            let (t0, t1) = (run[0].time_s, run[run.len() - 1].time_s);
            for r in run {
                r.temperature_c = Some(24.0 + 2.0 * u(k as u64) + 3.0 * (r.time_s - t0) / (t1 - t0));
            }
        }
        let at_tenth = |kind| served_at_tenth(kind, &readings, &starts);
        let (ukf, learned) = (at_tenth(CalibratorKind::Ukf), at_tenth(CalibratorKind::UkfLearned));
        let first = learned.iter().position(|x| x.1 > 0.0).expect("the learner weighs in");
        assert!(first >= 19, "moved from discharge {first}");
        assert!(ukf.iter().all(|x| x.1 == 0.0));
        assert_eq!(ukf[..first], learned[..first], "the same as ukf until the learner weighs in");
        let off = |x: &[(f64, f64, f64, f64)]| x.iter().map(|(e, _, _, end)| (e - end).abs()).sum::<f64>();
        let (theirs, ours) = (off(&ukf[32..]), off(&learned[32..]));
        assert!(ours < 0.6 * theirs, "last twelve at a tenth: {ours} s off against {theirs} s");
    }

    /// A cell cycled at 1, 2 and 4 A in no order whose charge depends on the current in a way the model does
    /// not carry (4 % more per e-fold of current, as a cell whose model errs by current): each discharge
    /// starts from what the last one, at another current, told, and early in it the joint UKF has not yet
    /// read the difference, so its end errs by how far the current moved. The twins recentre each on the
    /// discharges that moved their current alike ([`crate::recentre::biases_alike`]): at a tenth of the last
    /// twelve of 44 discharges the joint UKF's error, in % of each discharge summed over the twelve, is 0.02
    /// (0.33 with the twins taken over every discharge, as before them: checked). The `ukf_learned` kind
    /// gives the same until its learner weighs in, and keeps it (0.03: the twins leave its current input
    /// little to take off on this cell).
    #[test]
    fn the_twins_by_current_take_off_what_follows_the_current_before() {
        let amps = [1.0f64, 2.0, 4.0];
        let current_a = |k: u64| amps[((k * 7 + k / 3) % 3) as usize];
        let (readings, starts) = cycler_life(44, |k, spec| EpisodeSpec {
            truth: Degradation {
                q_mobile_c: 7600.0 * (1.0 + 0.04 * (current_a(k) / 2.0).ln()),
                ..Degradation::default()
            },
            soc0: 1.0,
            profile: LoadProfile::Piecewise(vec![(0.0, Load::CurrentA(0.0)), (30.0, Load::CurrentA(current_a(k)))]),
            ..spec
        });
        let at_tenth = |kind| served_at_tenth(kind, &readings, &starts);
        let (ukf, learned) = (at_tenth(CalibratorKind::Ukf), at_tenth(CalibratorKind::UkfLearned));
        let first = learned.iter().position(|x| x.1 > 0.0).expect("the learner weighs in");
        assert_eq!(ukf[..first], learned[..first], "the same as ukf until the learner weighs in");
        // In % of each discharge (a 1 A discharge is four times a 4 A one).
        let off =
            |x: &[(f64, f64, f64, f64)]| x.iter().map(|(e, _, on, end)| ((e - end) / (end - on)).abs()).sum::<f64>();
        let (theirs, ours) = (off(&ukf[32..]), off(&learned[32..]));
        assert!(theirs < 0.1 && ours < 0.1, "last twelve at a tenth: ukf {theirs}, ukf_learned {ours} off");
    }

    /// A gap, then a charge the stream sees, then the next discharge: a new stretch starts after the gap and
    /// again after the charge, but the charge is no discharge: not counted (it shares the next discharge's
    /// number), carried or learned from. The next discharge starts from where the last discharge ended, not
    /// from where the charge left the filter.
    #[test]
    fn a_charge_after_a_gap_is_not_carried_as_a_discharge() {
        let cfg = ScenarioConfig::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(4);
        let spec = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let samples = simulate(&cfg, &spec).unwrap().samples;
        let as_reading = |s: &Sample, offset_s: f64| Reading {
            time_s: s.t_s + offset_s,
            voltage_v: s.voltage_v,
            current_a: s.current_a,
            temperature_c: None,
        };
        let mut readings: Vec<Reading> = samples.iter().map(|s| as_reading(s, 0.0)).collect();
        let end_s = readings.last().unwrap().time_s;
        // An hour later: 30 min of charging at 1.5 A, the voltage rising, then the same discharge again.
        for k in 0..=90 {
            let v = 3.9 + 0.3 * f64::from(k) / 90.0;
            readings.push(Reading {
                time_s: end_s + 3600.0 + 20.0 * f64::from(k),
                voltage_v: v,
                current_a: -1.5,
                temperature_c: None,
            });
        }
        let again_s = readings.last().unwrap().time_s + 600.0;
        let n_before = readings.len();
        readings.extend(samples.iter().map(|s| as_reading(s, again_s)));
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let est: Vec<Estimate> = readings.iter().map(|r| stream.step(r).unwrap()).collect();
        let n_first = samples.len();
        assert_eq!(stream.discharges(), 2, "the discharge, the charge, the discharge");
        assert_eq!((est[n_first].discharge, est[n_before].discharge), (1, 1));
        // The same two discharges without the charge between them: the second starts from the same value.
        let mut plain = Stream::of(&setup, None, None).unwrap();
        let without: Vec<Estimate> =
            readings[..n_first].iter().chain(&readings[n_before..]).map(|r| plain.step(r).unwrap()).collect();
        assert_eq!(est[n_before].q_mobile, without[n_first].q_mobile, "carried from the discharge, not the charge");
        // The charge, after the gap, shows the estimate it began with: it holds through the charge (where the
        // next discharge starts from), though the filter reads every reading.
        let held = |e: &Estimate| (e.q_mobile, e.r_o);
        assert!(
            est[n_first..n_before].iter().all(|e| held(e) == held(&est[n_first])),
            "the filter moved while charging"
        );
    }

    /// The charge a discharge delivers: none before the load; while it runs, what it drew plus the assumed
    /// current to the predicted end, near the charge it then delivers, and within the ends of its interval;
    /// once it has crossed its cut-off, that charge measured, from the reading before the load to the
    /// interpolated crossing (summed here apart from the stream).
    #[test]
    fn the_charge_delivered_is_predicted_while_the_discharge_runs_and_measured_once_it_ends() {
        let (readings, starts) = cycler_life(12, |_, spec| spec);
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let cutoff_v = stream.spec.cutoff_v;
        let est: Vec<Estimate> = readings.iter().map(|r| stream.step(r).unwrap()).collect();
        let mut bracketed = 0;
        for (k, w) in starts.windows(2).enumerate() {
            let (r, e) = (&readings[w[0]..w[1]], &est[w[0]..w[1]]);
            let on = r.iter().position(|x| x.current_a > LOAD_THRESHOLD_A).unwrap();
            assert!(e[..on].iter().all(|x| x.delivered_ah.is_none()), "discharge {k}: before the load");
            let below = r.iter().position(|x| x.current_a > LOAD_THRESHOLD_A && x.voltage_v < cutoff_v).unwrap();
            let (a, b) = (&r[below - 1], &r[below]);
            let end_s = a.time_s + (a.voltage_v - cutoff_v) / (a.voltage_v - b.voltage_v) * (b.time_s - a.time_s);
            let trapezoid = |x: &Reading, y: &Reading, to_s: f64| {
                let i_end = x.current_a + (y.current_a - x.current_a) * (to_s - x.time_s) / (y.time_s - x.time_s);
                0.5 * (x.current_a.max(0.0) + i_end.max(0.0)) * (to_s - x.time_s)
            };
            let measured_c: f64 = r[..below].windows(2).map(|p| trapezoid(&p[0], &p[1], p[1].time_s)).sum::<f64>()
                + trapezoid(a, b, end_s);
            let measured_ah = measured_c / 3600.0;
            for x in &e[below..] {
                let got = x.delivered_ah.unwrap();
                assert!((got - measured_ah).abs() < 1e-9 * measured_ah, "discharge {k}: {got} against {measured_ah}");
                assert_eq!((x.delivered_lo_ah, x.delivered_hi_ah), (None, None));
            }
            // Half-way to the end: the prediction is near what it delivers, and is the charge drawn so far plus
            // the current assumed to the predicted end.
            let half =
                (on..below).min_by_key(|&j| ((r[j].time_s - (r[on].time_s + end_s) / 2.0).abs() * 1e3) as i64).unwrap();
            let x = &e[half];
            let got = x.delivered_ah.unwrap();
            assert!(
                (got - measured_ah).abs() < 0.02 * measured_ah,
                "discharge {k}: {got} at half, {measured_ah} delivered"
            );
            let drawn_c: f64 = r[..=half].windows(2).map(|p| trapezoid(&p[0], &p[1], p[1].time_s)).sum();
            let expect = drawn_c / 3600.0 + x.eod_current_a.unwrap() * (x.eod_s.unwrap() - r[half].time_s) / 3600.0;
            assert!((got - expect).abs() < 1e-9 * expect, "{got} against {expect}");
            if let (Some(lo), Some(hi)) = (x.delivered_lo_ah, x.delivered_hi_ah) {
                assert!(lo <= got && got <= hi, "discharge {k}: {lo} {got} {hi}");
                bracketed += 1;
            }
        }
        assert!(bracketed >= 2, "the last discharges have an interval: {bracketed}");
    }

    /// A full cell discharged at constant power (7.5 W after the rest, about 1.9 A at 4.0 V and 2.5 A at
    /// 3.0 V): from a fifth of each discharge on the stream assumes the loaded readings' mean power, and at
    /// half its end is within 2 % of the discharge's length of the truth on every discharge and a third or
    /// less of the error at the mean current so far (which puts it 5-6 % late), and its charge within 1.5 %
    /// of what the discharge delivers. The current it states is the mean the model draws to its end, above
    /// the mean so far.
    #[test]
    fn a_load_held_at_constant_power_is_predicted_at_its_power() {
        let (readings, starts) = cycler_life(6, |_, spec| EpisodeSpec {
            kind: LoadKind::ConstantPower,
            profile: LoadProfile::Piecewise(vec![(0.0, Load::PowerW(0.0)), (30.0, Load::PowerW(7.5))]),
            soc0: 1.0,
            ..spec
        });
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let cutoff_v = stream.spec.cutoff_v;
        for (k, w) in starts.windows(2).enumerate() {
            let r = &readings[w[0]..w[1]];
            let on = r.iter().position(|x| x.current_a > LOAD_THRESHOLD_A).unwrap();
            let below = r.iter().position(|x| x.current_a > LOAD_THRESHOLD_A && x.voltage_v < cutoff_v).unwrap();
            let end_s = r[below].time_s;
            let length_s = end_s - r[on].time_s;
            let (fifth, half) = (r[on].time_s + 0.2 * length_s, r[on].time_s + 0.5 * length_s);
            let (mut mean_a, mut at_half) = (LoadMean::default(), None);
            for x in &r[..below] {
                let e = stream.step(x).unwrap();
                mean_a.push(x.time_s, x.current_a, x.voltage_v);
                if x.time_s >= fifth {
                    let w = e.eod_power_w.unwrap_or_else(|| panic!("discharge {k} at {}: {e:?}", x.time_s));
                    assert!((w - 7.5).abs() < 0.05, "discharge {k}: {w} W");
                }
                if x.time_s >= half && x.time_s - half < 20.0 {
                    let at_power = (e.eod_s.unwrap() - end_s).abs();
                    let so_far_a = mean_a.loaded_mean_a().unwrap();
                    let at_current = (stream.predict_eod_s(so_far_a).unwrap() - end_s).abs();
                    eprintln!(
                        "discharge {k} at half: end {at_power:.0} s off at its power, {at_current:.0} s at the mean \
                         current so far, of {length_s:.0} s"
                    );
                    assert!(
                        at_power < 0.02 * length_s && 3.0 * at_power < at_current,
                        "discharge {k}: {at_power:.0} s off at power, {at_current:.0} s at the mean current so far"
                    );
                    assert!(e.eod_current_a.unwrap() > so_far_a, "{e:?}");
                    at_half = e.delivered_ah;
                }
            }
            // Past the crossing the stream states the charge measured to it (checked apart from it elsewhere).
            let measured_ah = stream.step(&r[below]).unwrap().delivered_ah.unwrap();
            let predicted_ah = at_half.unwrap();
            eprintln!("discharge {k}: charge at half {predicted_ah:.4} Ah, delivered {measured_ah:.4} Ah");
            assert!((predicted_ah - measured_ah).abs() < 0.015 * measured_ah, "{predicted_ah} against {measured_ah}");
            for x in &r[below + 1..] {
                stream.step(x).unwrap();
            }
        }
    }

    /// A charge the filter would follow to the end of its ranges (its voltage is no model's) shows the
    /// estimate it began with, while the filter still reads it: a stream that begins on it reports the prior
    /// until the charge ends, and the discharge after it is, reading for reading, what a stream that began
    /// after the charge gives; a charge that follows a discharge at once shows the filter for its first minute
    /// (it could be a regenerative pulse) and then is held.
    #[test]
    fn a_charge_shows_the_estimate_it_began_with() {
        let (readings, starts) = cycler_life(1, |_, spec| spec);
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let prior = setup.spec.tracker.prior;
        // The discharge an hour after the charge began (half an hour after it ended).
        let later: Vec<Reading> =
            readings[..starts[1]].iter().map(|r| Reading { time_s: r.time_s + 3600.0, ..*r }).collect();
        let mut first = charge(0.0, 90, -1.5, 3.9, 0.3);
        first.extend(later.iter().copied());
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let est: Vec<Estimate> = first.iter().map(|r| stream.step(r).unwrap()).collect();
        for e in &est[..91] {
            let at_prior = (e.q_mobile - prior.q_mobile_c).abs() < 1e-6 && (e.r_o - prior.r_o_ohm).abs() < 1e-12;
            assert!(at_prior, "during the charge: {e:?}");
        }
        let mut plain = Stream::of(&setup, None, None).unwrap();
        for (k, r) in later.iter().enumerate() {
            let (a, b) = (&est[91 + k], plain.step(r).unwrap());
            assert_eq!((a.q_mobile, a.r_o, a.eod_s), (b.q_mobile, b.r_o, b.eod_s), "reading {k} of the discharge");
        }
        // The same discharge, then at once a charge: read for a minute, then held.
        let end_s = readings[starts[1] - 1].time_s;
        let mut stream = fed(&setup, &readings[..starts[1]]);
        let after: Vec<Estimate> =
            charge(end_s + 20.0, 90, -1.5, 3.9, 0.3).iter().map(|r| stream.step(r).unwrap()).collect();
        let ended = est_at_end(&setup, &readings[..starts[1]]);
        assert_ne!(after[0].q_mobile, after[2].q_mobile, "the first minute shows the filter");
        assert!(after[3..].iter().all(|e| (e.q_mobile, e.r_o) == ended), "then what the charge began with");
        // A 40 s charge at rest before the load: shown held, read by the filter.
        let at = |t_s: f64, r: &Reading| Reading { time_s: t_s, ..*r };
        let rest = at(0.0, &later[0]);
        let pulse = charge(5.0, 2, -1.5, 3.9, 0.0);
        let next = at(55.0, &later[0]);
        let mut with = Stream::of(&setup, None, None).unwrap();
        let shown: Vec<Estimate> =
            std::iter::once(&rest).chain(&pulse).chain([&next]).map(|r| with.step(r).unwrap()).collect();
        assert!(shown[1..3].iter().all(|e| (e.q_mobile, e.r_o) == (shown[0].q_mobile, shown[0].r_o)));
        let without = fed(&setup, &[rest, next]);
        assert_ne!(with.calibrator().state(), without.calibrator().state(), "the short charge is read");
    }

    /// A log too coarse to read its cut-off (its last loaded reading above it) with a charge right after: once
    /// the charge has run a minute the discharge is over (no end predicted from the filter reading the charge, no
    /// charge counted as delivered), and the next discharge starts from what the filter knew when the charge
    /// began, as after a gap, not from the filter that read the charge (which ran qMobile off).
    #[test]
    fn a_charge_ends_a_discharge_whose_cut_off_was_not_read() {
        let (readings, starts, setup) = two_discharges();
        let cut = setup.spec.tracker.cutoff_v;
        let stop = (starts[0]..starts[1]).find(|&k| readings[k].current_a > 0.1 && readings[k].voltage_v < cut + 0.1);
        let stop = stop.expect("the first discharge reaches its cut-off");
        let end_s = readings[stop - 1].time_s;
        let charging = charge(end_s + 60.0, 90, -1.5, 3.6, 0.5);
        let next = readings[starts[1]];
        assert!(next.time_s > charging.last().unwrap().time_s + 60.0);
        let mut charged = fed(&setup, &readings[..stop]);
        let during: Vec<Estimate> = charging.iter().map(|r| charged.step(r).unwrap()).collect();
        for e in &during[4..] {
            assert!(e.eod_s.is_none() && e.delivered_ah.is_none() && e.eod_hi_s.is_none(), "during the charge: {e:?}");
        }
        let mut gapped = fed(&setup, &readings[..stop]);
        let (a, b) = (charged.step(&next).unwrap(), gapped.step(&next).unwrap());
        assert_eq!((a.discharge, a.q_mobile, a.r_o), (b.discharge, b.q_mobile, b.r_o));
    }

    /// A discharge started at once after a charge (the charger off, the load on within one reading, no rest):
    /// its first reading is under load, and is read as a rest. Right after a charge that is near the truth (the
    /// charge's polarisation still offsets the load's), and the end the calibrator predicts is within 5 % of
    /// what remains from the discharge's second minute. (A fuzz of the CLI cut a 20-min charge into a NASA
    /// discharge and resumed it at the voltages of no charge: read as a rest, that start put the cell near
    /// empty, its end "now" on every reading; such readings no cell gives. Reading the first loaded reading
    /// as the cell settled under its load from rest, tried on 2026-11-30, did worse here: the polarisation
    /// before the switch is the charge's, not a rest's.) The model's own cell, its parameters the stream's
    /// prior (the start alone judged), read every 10 s.
    #[test]
    fn a_discharge_started_at_once_after_a_charge_is_followed() {
        use bcal_common::battery::{BatteryModel, Load, LoadProfile};
        let model = BatteryModel::default();
        let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
        let d = setup.spec.tracker.prior;
        let x0 = bcal_common::measured::scenario::rest_state(&model, &d, model.params.xn_max, 292.1);
        // 60 s at rest, 2 A for 25 min, a 20-min charge at 1.5 A, then 2 A again to the end.
        let (charge_s, again_s) = (1560.0, 2760.0);
        let profile = LoadProfile::Piecewise(vec![
            (0.0, Load::CurrentA(0.0)),
            (60.0, Load::CurrentA(2.0)),
            (charge_s, Load::CurrentA(-1.5)),
            (again_s, Load::CurrentA(2.0)),
        ]);
        let mut readings = Vec::new();
        let out = model
            .simulate_until_eod(&x0, &d, &profile, 1.0, 100_000, |r| {
                if r.step % 10 == 5 {
                    readings.push(Reading {
                        time_s: r.t_s,
                        voltage_v: r.voltage_v,
                        current_a: r.current_a,
                        temperature_c: None,
                    });
                }
            })
            .unwrap();
        let eod_s = out.eod_s.expect("the second discharge reaches the model's end");
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let mut offs = Vec::new();
        for r in &readings {
            stream.step(r).unwrap();
            if r.time_s > again_s + 60.0 && r.time_s < again_s + 600.0 {
                assert_eq!(stream.discharges(), 2, "the discharge after the charge is a new one");
                let e = stream.predict_eod_s(r.current_a).expect("an end");
                offs.push((e - eod_s) / (eod_s - r.time_s));
            }
        }
        assert_eq!(offs.len(), 54);
        assert!(offs.iter().all(|o| o.abs() < 0.05), "the end off by {offs:?} of what remains");
    }

    /// The estimate (qMobile, Ro) a stream of `setup` shows after `readings`.
    fn est_at_end(setup: &Setup, readings: &[Reading]) -> (f64, f64) {
        let mut stream = Stream::of(setup, None, None).unwrap();
        let last = readings.iter().map(|r| stream.step(r).unwrap()).last().unwrap();
        (last.q_mobile, last.r_o)
    }

    /// Two constant-current discharges of a cycler (a 30 s rest, then 2 A to the cut-off, read every 10-20 s),
    /// the second 3 h after the first; each reading a UKF stream.
    fn two_discharges() -> (Vec<Reading>, Vec<usize>, Setup) {
        let (readings, starts) = cycler_life(2, |_, spec| spec);
        (readings, starts, resolve(CalibratorKind::Ukf, None, None, None).unwrap())
    }

    /// A stream of `setup` that has taken `readings`.
    fn fed<'a>(setup: &'a Setup, readings: &[Reading]) -> Stream<'a> {
        let mut stream = Stream::of(setup, None, None).unwrap();
        for r in readings {
            stream.step(r).unwrap();
        }
        stream
    }

    /// `n + 1` readings of a charge at `current_a` (negative), 20 s apart from `t0_s`, the voltage rising
    /// from `v0` by `dv` over them.
    fn charge(t0_s: f64, n: u32, current_a: f64, v0: f64, dv: f64) -> Vec<Reading> {
        (0..=n)
            .map(|k| Reading {
                time_s: t0_s + 20.0 * f64::from(k),
                voltage_v: v0 + dv * f64::from(k) / f64::from(n),
                current_a,
                temperature_c: None,
            })
            .collect()
    }

    /// A discharge that stops above its cut-off (as a device's do) leaves no prediction behind: the next
    /// discharge's shares are scored on its own predictions only.
    #[test]
    fn a_discharge_stopped_above_its_cut_off_leaves_no_prediction_behind() {
        let (readings, starts, setup) = two_discharges();
        let half = starts[0] + (starts[1] - starts[0]) / 2;
        let mut stream = fed(&setup, &readings[..half]);
        // Every source predicted but the previous discharge's fit (this is the first).
        let fit = PREVIOUS..PREVIOUS_TWINS + 4;
        assert!(stream.sources.iter().enumerate().all(|(k, s)| s.predictions.is_empty() == fit.contains(&k)));
        // Its next reading at rest, hours later: a new discharge, nothing of the last one's predictions kept.
        stream.step(&Reading { time_s: readings[half].time_s + 7200.0, ..readings[starts[1]] }).unwrap();
        assert_eq!(stream.discharges(), 2);
        assert!(stream.sources.iter().all(|s| s.predictions.is_empty()));
    }

    /// A stream that begins on a charge starts its first discharge from the setting's own prior, as one that
    /// begins at the discharge does: the charge is no discharge to carry.
    #[test]
    fn a_stream_that_begins_on_a_charge_starts_its_first_discharge_from_the_setting() {
        let (readings, starts, setup) = two_discharges();
        let first = &readings[..starts[1]];
        let t0 = first[0].time_s - 2400.0;
        let mut charged = fed(&setup, &charge(t0, 90, -1.5, 3.9, 0.3));
        let mut plain = Stream::of(&setup, None, None).unwrap();
        for r in first {
            let (a, b) = (charged.step(r).unwrap(), plain.step(r).unwrap());
            assert_eq!((a.q_mobile, a.r_o, a.eod_s), (b.q_mobile, b.r_o, b.eod_s), "at {} s", r.time_s);
        }
    }

    /// One reading of negative current inside a discharge (a regenerative pulse, sensor noise) is no charge:
    /// the discharge goes on. A charge of a minute or more ends it.
    #[test]
    fn a_short_negative_current_does_not_end_a_discharge() {
        let (mut readings, starts, setup) = two_discharges();
        let mid = starts[0] + (starts[1] - starts[0]) / 2;
        readings[mid].current_a = -0.06;
        let mut stream = Stream::of(&setup, None, None).unwrap();
        let est: Vec<Estimate> = readings[..starts[1]].iter().map(|r| stream.step(r).unwrap()).collect();
        assert!(est.iter().all(|e| e.discharge == est[0].discharge), "the blip split the discharge");
        // The same reading as the start of a 2-minute charge: a new discharge after it.
        let t = readings[mid].time_s;
        let mut charged = fed(&setup, &readings[..mid]);
        for k in 0..=6 {
            charged.step(&Reading { time_s: t + 20.0 * f64::from(k), current_a: -1.0, ..readings[mid] }).unwrap();
        }
        let after = charged.step(&Reading { time_s: t + 200.0, current_a: 0.0, ..readings[mid] }).unwrap();
        assert_eq!(after.discharge, est[0].discharge + 1);
    }

    /// One loaded reading at a rested cell's voltage before a charge (the spurious first sample of NASA's
    /// charge records) is no discharge: it hands nothing on, the next discharge keeps its number and starts
    /// from what the discharge before it handed on, as it does without the reading.
    #[test]
    fn a_single_loaded_reading_before_a_charge_is_no_discharge() {
        let (readings, starts, setup) = two_discharges();
        let first = &readings[..starts[1]];
        let end_s = first.last().unwrap().time_s;
        let spike = Reading { time_s: end_s + 3000.0, voltage_v: 4.19, current_a: 4.03, temperature_c: None };
        let charging = charge(end_s + 3020.0, 90, -1.5, 3.9, 0.3);
        let second_at = charging.last().unwrap().time_s + 600.0;
        let shift = second_at - readings[starts[1]].time_s;
        let second: Vec<Reading> =
            readings[starts[1]..].iter().map(|r| Reading { time_s: r.time_s + shift, ..*r }).collect();
        let run = |with_spike: bool| -> (Vec<Estimate>, Option<f64>) {
            let mut stream = fed(&setup, first);
            if with_spike {
                stream.step(&spike).unwrap();
            }
            for r in &charging {
                stream.step(r).unwrap();
            }
            // The current the next discharge's is compared with (the twins', the learner's): the first's.
            let before_a = stream.current_before_a;
            (second.iter().map(|r| stream.step(r).unwrap()).collect(), before_a)
        };
        let ((plain, plain_before_a), (spiked, spiked_before_a)) = (run(false), run(true));
        assert_eq!(plain[0].discharge, spiked[0].discharge, "the spike took a discharge number");
        assert!(plain_before_a.is_some_and(|a| (a - spike.current_a).abs() > 0.5), "{plain_before_a:?}");
        assert_eq!(spiked_before_a, plain_before_a, "the spike became the current before");
        for (a, b) in plain.iter().zip(&spiked) {
            assert_eq!((a.q_mobile, a.r_o, a.eod_s), (b.q_mobile, b.r_o, b.eod_s), "at {} s", a.time_s);
        }
        // The same sample minutes after the discharge's end, in the rest before the charge (as B0005's records
        // joined end to end read it): the rest before the next discharge still runs from the discharge's last
        // loaded reading. (The calibrator read the sample, and its width after it moves the next prior's
        // width, by half here: the estimates stay within 0.5 %. Not fixed: the calibrator reads on after a
        // discharge's end.)
        let late = Reading { time_s: end_s + 600.0, ..spike };
        let (mut joined, mut alone) = (fed(&setup, first), fed(&setup, first));
        joined.step(&late).unwrap();
        for r in &charging {
            joined.step(r).unwrap();
            alone.step(r).unwrap();
        }
        for (a, r) in plain.iter().zip(&second) {
            let b = joined.step(r).unwrap();
            alone.step(r).unwrap();
            assert_eq!(joined.rest_before_s, alone.rest_before_s, "at {} s", r.time_s);
            assert!((a.q_mobile / b.q_mobile - 1.0).abs() < 5e-3, "at {} s: {a:?} against {b:?}", a.time_s);
        }
    }

    /// A load that pauses above the cut-off and comes back below it: the end lies between the last reading
    /// above the cut-off (at rest, in the pause) and the first below, as `bcal calibrate` reads it, never
    /// back across the pause.
    #[test]
    fn the_end_is_read_between_the_last_reading_above_the_cut_off_and_the_first_below() {
        let (readings, starts, setup) = two_discharges();
        let last = starts[1] - 1;
        let mut stream = fed(&setup, &readings[..last]);
        // 20 minutes at rest, the voltage relaxing above the cut-off, then the last (loaded) reading.
        let pause_s = readings[last - 1].time_s;
        let rest_v = readings[last - 1].voltage_v + 0.2;
        for k in 1..=20 {
            let r =
                Reading { time_s: pause_s + 60.0 * f64::from(k), voltage_v: rest_v, current_a: 0.0, ..readings[last] };
            stream.step(&r).unwrap();
        }
        let resumed_s = pause_s + 1260.0;
        stream.step(&Reading { time_s: resumed_s, ..readings[last] }).unwrap();
        let end_s = stream.eod_track.ended_s.expect("the discharge ended");
        assert!(end_s > pause_s + 1200.0 && end_s <= resumed_s, "end {end_s}, pause {pause_s}");
    }

    /// A discharge, a charge, three days at rest read every 10 minutes, a discharge: its rest runs from the
    /// last discharge to its load, as `bcal calibrate` measures it, not to the end of the charge.
    #[test]
    fn the_rest_before_a_discharge_runs_to_its_load() {
        let (readings, starts, setup) = two_discharges();
        let mut stream = fed(&setup, &readings[..starts[1]]);
        let end_s = readings[starts[1] - 1].time_s;
        for r in &charge(end_s + 600.0, 90, -1.5, 3.9, 0.3) {
            stream.step(r).unwrap();
        }
        let charged_s = end_s + 600.0 + 20.0 * 90.0;
        let mut t = charged_s;
        while t < charged_s + 3.0 * 86_400.0 {
            t += 600.0;
            stream.step(&Reading { time_s: t, voltage_v: 4.15, current_a: 0.0, temperature_c: None }).unwrap();
        }
        let second = &readings[starts[1]..];
        let shift = t + 20.0 - second[0].time_s;
        for r in second {
            stream.step(&Reading { time_s: r.time_s + shift, ..*r }).unwrap();
        }
        let rest_s = stream.rest_before_s.expect("a rest before the second discharge");
        assert!(rest_s > 3.0 * 86_400.0, "rest {rest_s} s");
        assert_eq!(stream.discharges(), 2);
        // Its width is the first discharge's own posterior (too few changes to learn one), not the prior
        // that walked through the three days.
        let (sd, source) = stream.prior_width.expect("a width");
        assert_eq!((Some(sd), source), (stream.carried_sd_z, WidthSource::Posterior));
    }

    /// Readings lost for two hours after a discharge, then a charge seen whole, a rest and a discharge: the
    /// discharge after the charge carries the first discharge's own posterior width (the gap started a
    /// discharge that only charged; it hands on nothing of its own).
    #[test]
    fn a_charge_seen_after_a_gap_hands_on_the_width_of_the_discharge_before_it() {
        let (readings, starts, setup) = two_discharges();
        let mut stream = fed(&setup, &readings[..starts[1]]);
        let end_s = readings[starts[1] - 1].time_s;
        for r in &charge(end_s + 7200.0, 90, -1.5, 3.9, 0.3) {
            stream.step(r).unwrap();
        }
        let first_sd = stream.carried_sd_z.expect("the first discharge's posterior width");
        let charged_s = end_s + 7200.0 + 20.0 * 90.0;
        let second = &readings[starts[1]..];
        let shift = charged_s + 1200.0 - second[0].time_s;
        for r in second {
            stream.step(&Reading { time_s: r.time_s + shift, ..*r }).unwrap();
        }
        assert_eq!(stream.discharges(), 2);
        assert_eq!(stream.carried_sd_z, Some(first_sd));
        // Without a lifetime model nothing widens it.
        assert_eq!(stream.prior_width, Some((first_sd, WidthSource::Posterior)));
    }

    /// A charge and, at once, the load (a cycler with no rest after charging): a whole discharge, scored.
    #[test]
    fn a_charge_straight_into_a_load_is_a_whole_discharge() {
        let (readings, starts, setup) = two_discharges();
        let mut stream = fed(&setup, &readings[..starts[1]]);
        let end_s = readings[starts[1] - 1].time_s;
        for r in &charge(end_s + 600.0, 6, -1.0, 4.1, 0.0) {
            stream.step(r).unwrap();
        }
        let second = &readings[starts[1]..];
        let on = second.iter().position(|r| r.current_a > LOAD_THRESHOLD_A).unwrap();
        let shift = end_s + 600.0 + 140.0 - second[on].time_s;
        for r in &second[on..] {
            stream.step(&Reading { time_s: r.time_s + shift, ..*r }).unwrap();
        }
        assert_eq!(stream.discharges(), 2);
        assert!(!stream.joined_under_load);
        assert_eq!(stream.sources[METHOD].scored.len(), 2, "both discharges scored");
    }

    /// Readings lost for an hour within a discharge: the piece after the gap starts under load, its start
    /// unseen. It is neither scored nor measured: what the stream learns comes from whole discharges.
    #[test]
    fn a_piece_joined_under_load_is_not_scored() {
        let (readings, starts, setup) = two_discharges();
        let mid = starts[0] + (starts[1] - starts[0]) / 2;
        let mut stream = fed(&setup, &readings[..mid]);
        for r in &readings[mid..starts[1]] {
            stream.step(&Reading { time_s: r.time_s + 3600.0, ..*r }).unwrap();
        }
        assert_eq!(stream.discharges(), 2);
        assert!(stream.eod_track.ended_s.is_some(), "the piece reached the cut-off");
        assert!(stream.sources.iter().all(|s| s.scored.is_empty()), "a piece was scored");
        assert_eq!(stream.capacity_ah, None);
        // The next discharge: the life has counted one, the one the piece belonged to.
        stream.step(&Reading { time_s: readings[starts[1] - 1].time_s + 3.0 * 3600.0, ..readings[0] }).unwrap();
        assert_eq!((stream.discharges(), stream.discharged), (3, 1));
    }

    /// A clock glitch: one reading a day ahead in the middle of a discharge, then the readings' own clock
    /// again. The three after it are a day behind the stream: the first two are refused, the third starts
    /// the readings' clock on the stream's (the rest of that discharge a piece after a day's gap), and
    /// everything after is taken, with times and predicted ends on the readings' clock. A stretch resent
    /// minutes behind stays refused.
    #[test]
    fn a_clock_that_went_back_and_stays_there_is_taken_after_three_readings() {
        let (readings, starts, setup) = two_discharges();
        let glitch_at = starts[0] + (starts[1] - starts[0]) / 2;
        let mut stream = fed(&setup, &readings[..glitch_at]);
        let ahead = Reading { time_s: readings[glitch_at].time_s + 86_400.0, ..readings[glitch_at] };
        stream.step(&ahead).unwrap();
        let results: Vec<Result<Estimate, ReadingError>> =
            readings[glitch_at + 1..].iter().map(|r| stream.step(r)).collect();
        for (k, res) in results.iter().enumerate().take(CLOCK_BACK_READINGS - 1) {
            assert!(matches!(res, Err(ReadingError::TimeNotIncreasing { .. })), "reading {k}: {res:?}");
        }
        let taken: Vec<&Estimate> = results[CLOCK_BACK_READINGS - 1..].iter().map(|r| r.as_ref().unwrap()).collect();
        assert_eq!(stream.clock_changes(), 1);
        for (e, r) in taken.iter().zip(&readings[glitch_at + CLOCK_BACK_READINGS..]) {
            assert_eq!(e.time_s, r.time_s, "on the readings' clock");
        }
        // The second discharge is whole: predicted at half within 5 % of its duration, on the readings' clock.
        let second = &readings[starts[1]..];
        let on = second.iter().find(|r| r.current_a > LOAD_THRESHOLD_A).unwrap().time_s;
        let cutoff_v = stream.spec.cutoff_v;
        let end = second.iter().find(|r| r.current_a > LOAD_THRESHOLD_A && r.voltage_v < cutoff_v).unwrap().time_s;
        let k = second.iter().position(|r| r.time_s >= on + 0.5 * (end - on)).unwrap();
        let e = taken[taken.len() - second.len() + k];
        let eod = e.eod_s.unwrap();
        assert!((eod - end).abs() < 0.05 * (end - on), "predicted {eod}, crossed at {end}");
        // Readings resent ten minutes behind are refused, however many.
        let last = *readings.last().unwrap();
        for j in 0..5 {
            let resent = Reading { time_s: last.time_s - 600.0 + f64::from(j), ..last };
            assert!(matches!(stream.step(&resent), Err(ReadingError::TimeNotIncreasing { .. })));
        }
        assert_eq!(stream.clock_changes(), 1);
    }

    /// A stream that begins under load (a BMS's feed picked up in the middle of a discharge) joins a
    /// discharge whose start it did not see: a piece, as after lost readings. It predicts, but its end is not
    /// scored against the shares of a discharge it saw only the end of, measured or end-fitted.
    #[test]
    fn a_stream_that_begins_under_load_begins_with_a_piece() {
        let (readings, starts, setup) = two_discharges();
        let mid = starts[0] + (starts[1] - starts[0]) / 2;
        let mut stream = fed(&setup, &readings[mid..starts[1]]);
        assert_eq!(stream.discharges(), 1);
        assert!(stream.eod_track.ended_s.is_some(), "the piece reached the cut-off");
        assert!(stream.sources.iter().all(|s| s.scored.is_empty()), "a piece was scored");
        assert_eq!((stream.capacity_ah, stream.end_fit), (None, None));
        // The whole discharge after it is scored.
        let after: Vec<Estimate> = readings[starts[1]..].iter().map(|r| stream.step(r).unwrap()).collect();
        assert!(stream.sources[SERVED].scored.len() == 1, "{}", stream.sources[SERVED].scored.len());
        // ... and hands nothing on: its calibrator read the unseen charge into its estimate, so the whole
        // discharge starts from the setting's prior, as a stream that began with it does, reading for reading.
        let alone: Vec<Estimate> = {
            let mut fresh = Stream::of(&setup, None, None).unwrap();
            readings[starts[1]..].iter().map(|r| fresh.step(r).unwrap()).collect()
        };
        for (k, (a, b)) in after.iter().zip(&alone).enumerate() {
            assert_eq!(Estimate { discharge: b.discharge, ..*a }, *b, "reading {k}");
        }
    }
}
