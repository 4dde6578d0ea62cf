//! The evaluator of the measured-only setting, top to bottom: build the validation and test cells, choose
//! everything each method needs on validation only (the joint UKF's noise settings by grid search, the
//! direct mapping's early stopping, the 90 % interval scale of the tracker-based calibrators), then run
//! every calibrator one reading at a time along every test cell at each voltage-noise level, score the
//! estimates against the hidden truth, the end-of-discharge predictions against the true end, the intervals'
//! coverage, and time one calibration step of each on one thread.
//!
//! Methods: `rl_lac` (the trained policy), `ukf` (the joint UKF over states and parameters), `direct_mapping`
//! (a supervised network on the RL's inputs, trained on true parameters of training cells), `window_fit`
//! (the calibrator's own least-squares step with no learning: what the RL's features alone give) and
//! `uncalibrated` (the prior, never moved). Progress goes to a callback; this module never prints.

use crate::direct::{DirectMap, DirectMapConfig, DirectMapError, Pairs, TrainLog};
use crate::evaluate::{median_of, PolicyInput, TIMING_REPEATS};
use crate::joint_ukf::{JointUkf, JointUkfCounters, JointUkfSettings};
use crate::metrics::ParamValues;
use crate::plots::TrainingCurve;
use bcal_common::battery::Degradation;
use bcal_common::dataset::Split;
use bcal_common::math::ModelState;
use bcal_common::measured::calibrator::{
    predict_eod_s, tracker_state, Calibrator, EodQuery, RlCalibrator, Uncalibrated, WindowFitCalibrator,
};
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::scenario::{episode_set, Episode, ScenarioConfig};
use bcal_common::measured::tracker::{Interval, Tracker, TrackerSpec, OBS_DIM};
use bcal_common::nrmse::Param;
use bcal_common::policy::{PolicyNet, Scratch};
use bcal_common::stats::median;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Instant;

/// Method keys in report order, with display names.
pub const METHODS: [(&str, &str); 5] = [
    ("rl_lac", "RL-LAC"),
    ("ukf", "Joint UKF"),
    ("direct_mapping", "Direct mapping"),
    ("window_fit", "Window fit (no learning)"),
    ("uncalibrated", "Uncalibrated"),
];

/// Fractions of each discharge at which the end of discharge is predicted.
pub const EOD_FRACTIONS: [f64; 3] = [0.1, 0.5, 0.9];
/// Threshold of the convergence time, % of each parameter's Table-1 range.
pub const WITHIN_PCT: f64 = 2.0;

/// The joint UKF's search space (every combination is tried on validation).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointUkfGrid {
    pub meas_std_v: Vec<f64>,
    pub param_walk_per_sqrt_s: Vec<f64>,
    pub charge_walk_c_per_sqrt_s: Vec<f64>,
    pub voltage_walk_v_per_sqrt_s: Vec<f64>,
    pub prior_std_z: Vec<[f64; 2]>,
}

impl Default for JointUkfGrid {
    fn default() -> Self {
        Self {
            meas_std_v: vec![0.002, 0.003, 0.005, 0.01],
            param_walk_per_sqrt_s: vec![0.0, 1e-5, 1e-4],
            charge_walk_c_per_sqrt_s: vec![0.01, 0.1, 1.0],
            voltage_walk_v_per_sqrt_s: vec![JointUkfSettings::default().voltage_walk_v_per_sqrt_s],
            // The prototype prior (1000 C, 0.03 ohm over the 4000 C and 0.2 ohm ranges) and a wider one.
            prior_std_z: vec![[0.25, 0.15], [0.35, 0.3]],
        }
    }
}

impl JointUkfGrid {
    pub fn quick() -> Self {
        Self {
            meas_std_v: vec![0.003, 0.005],
            param_walk_per_sqrt_s: vec![1e-5],
            charge_walk_c_per_sqrt_s: vec![0.1],
            voltage_walk_v_per_sqrt_s: vec![JointUkfSettings::default().voltage_walk_v_per_sqrt_s],
            prior_std_z: vec![[0.25, 0.15], [0.35, 0.3]],
        }
    }

    /// For real cells: the measurement noise a filter must assume there is mostly the model's own error
    /// (15-40 mV RMS on the NASA cells, bcal diagnose), so the grid reaches further, and the overpotential
    /// states may walk to absorb a slowly varying part of that error instead of moving the charges.
    pub fn real_cells() -> Self {
        Self {
            meas_std_v: vec![0.003, 0.01, 0.02, 0.04],
            voltage_walk_v_per_sqrt_s: vec![1e-4, 1e-3, 5e-3],
            // Tighter priors too: on a real cell the prior is the previous discharge's fit, and a cell
            // changes by a fraction of a percent from one discharge to the next.
            prior_std_z: vec![[0.01, 0.01], [0.02, 0.02], [0.05, 0.05], [0.1, 0.1]],
            ..Self::default()
        }
    }

    pub fn real_cells_quick() -> Self {
        Self {
            meas_std_v: vec![0.01, 0.03],
            voltage_walk_v_per_sqrt_s: vec![1e-4, 5e-3],
            prior_std_z: vec![[0.05, 0.05], [0.25, 0.15]],
            ..Self::quick()
        }
    }

    pub fn candidates(&self) -> Vec<JointUkfSettings> {
        let mut v = Vec::new();
        for &meas_std_v in &self.meas_std_v {
            for &param_walk_per_sqrt_s in &self.param_walk_per_sqrt_s {
                for &charge_walk_c_per_sqrt_s in &self.charge_walk_c_per_sqrt_s {
                    for &voltage_walk_v_per_sqrt_s in &self.voltage_walk_v_per_sqrt_s {
                        for &prior_std_z in &self.prior_std_z {
                            v.push(JointUkfSettings {
                                meas_std_v,
                                param_walk_per_sqrt_s,
                                charge_walk_c_per_sqrt_s,
                                voltage_walk_v_per_sqrt_s,
                                prior_std_z,
                                ..JointUkfSettings::default()
                            });
                        }
                    }
                }
            }
        }
        v
    }
}

/// What the measured evaluation runs and how much effort each method gets.
#[derive(Clone, Debug, PartialEq)]
pub struct MeasuredEvalOptions {
    pub quick: bool,
    pub rl: bool,
    pub ukf: bool,
    pub direct_mapping: bool,
    /// Voltage noise levels of the test cells, V (current and temperature noise as configured).
    pub voltage_noise_levels_v: Vec<f64>,
    /// Test cells (None = the configured number).
    pub test_episodes: Option<usize>,
    /// Validation cells for every choice (None = the configured number).
    pub validation_episodes: Option<usize>,
    pub ukf_grid: JointUkfGrid,
    pub direct: DirectMapConfig,
    /// Training cells the direct mapping's pairs come from.
    pub direct_train_episodes: usize,
    /// Readings timed per method.
    pub timing_readings: usize,
    /// Test cells drawn in the estimate-versus-time figure.
    pub plot_episodes: usize,
}

impl MeasuredEvalOptions {
    pub fn full() -> Self {
        Self {
            quick: false,
            rl: true,
            ukf: true,
            direct_mapping: true,
            voltage_noise_levels_v: vec![0.0, 0.003, 0.010],
            test_episodes: None,
            validation_episodes: None,
            ukf_grid: JointUkfGrid::default(),
            direct: DirectMapConfig { hidden: vec![128, 128], ..DirectMapConfig::default() },
            direct_train_episodes: 400,
            timing_readings: 20_000,
            plot_episodes: 3,
        }
    }

    pub fn quick() -> Self {
        Self {
            quick: true,
            test_episodes: Some(16),
            validation_episodes: Some(12),
            ukf_grid: JointUkfGrid::quick(),
            direct: DirectMapConfig { hidden: vec![64, 64], ..DirectMapConfig::quick() },
            direct_train_episodes: 40,
            timing_readings: 2_000,
            ..Self::full()
        }
    }
}

/// Everything the evaluation reads.
pub struct MeasuredInput<'a> {
    /// The task: the policy's own when there is one (its cells, sensor and calibrator), else the run's.
    pub spec: &'a MeasuredSpec,
    pub policy: PolicyInput<'a>,
    pub training_curve: Option<TrainingCurve>,
    /// Seed of the direct mapping's training cells and initialisation.
    pub seed: u64,
}

#[derive(Debug, thiserror::Error)]
pub enum MeasuredEvalError {
    #[error("the policy was trained on the {policy} observation; this evaluation is of the {data} setting. Evaluate it with the task it was trained on")]
    TaskMismatch { policy: String, data: String },
    #[error("the policy's network ({got}) does not fit the measured-only observation ({want})")]
    PolicyShape { got: String, want: String },
    #[error("cannot simulate the {split} cells: {why}")]
    Episodes { split: &'static str, why: String },
    #[error(transparent)]
    DirectMap(#[from] DirectMapError),
    #[error("policy: {0}")]
    Policy(#[from] bcal_common::policy::PolicyError),
}

/// Estimates of one method along one episode.
#[derive(Clone, Debug, PartialEq)]
pub struct Trace {
    pub estimates: Vec<Degradation>,
    pub intervals: Vec<Option<Interval>>,
    /// Predicted end of discharge at each of [`EOD_FRACTIONS`] (None: the prediction failed).
    pub eod_pred_s: [Option<f64>; 3],
}

/// A calibrator that needs building per episode.
pub type Make<'a> = Box<dyn Fn() -> Box<dyn Calibrator + 'a> + Sync + 'a>;

/// The direct mapping as a calibrator: the window fit runs for its inputs, the network answers.
struct DirectCalibrator<'a> {
    fit: WindowFitCalibrator,
    net: &'a PolicyNet,
    scratch: Scratch,
    spec: TrackerSpec,
    interval_scale: [f64; 2],
    estimate: Degradation,
}

impl Calibrator for DirectCalibrator<'_> {
    fn step(&mut self, s: &bcal_common::measured::Sample) {
        self.fit.step(s);
        let mut obs = [0f32; OBS_DIM];
        self.fit.tracker().observe(&mut obs);
        let (mut mean, mut log_std) = ([0f32; 2], [0f32; 2]);
        self.net.forward(&obs, &mut self.scratch, &mut mean, &mut log_std);
        self.estimate = self.spec.from_z([f64::from(mean[0] + 1.0) * 0.5, f64::from(mean[1] + 1.0) * 0.5]);
    }
    fn estimate(&self) -> Degradation {
        self.estimate
    }
    fn interval(&self) -> Option<Interval> {
        // The fit's spread around the network's answer, scaled on validation.
        let sd = self.fit.tracker().stats().std_z(self.spec.noise_floor_v)?;
        Some(interval_around(&self.spec, &self.estimate, sd, self.interval_scale))
    }
    fn state(&self) -> Option<ModelState> {
        let t = self.fit.tracker();
        t.cell().map(|c| c.state(&c.track, &self.estimate))
    }
}

impl Calibrator for JointUkf {
    fn step(&mut self, s: &bcal_common::measured::Sample) {
        JointUkf::step(self, s)
    }
    fn estimate(&self) -> Degradation {
        JointUkf::estimate(self)
    }
    fn interval(&self) -> Option<Interval> {
        JointUkf::interval(self)
    }
    fn state(&self) -> Option<ModelState> {
        Some(JointUkf::state(self))
    }
    fn state_under(&self, d: &Degradation) -> Option<ModelState> {
        Some(JointUkf::state_given(self, d))
    }
}

fn interval_around(spec: &TrackerSpec, d: &Degradation, sd_z: [f64; 2], k: [f64; 2]) -> Interval {
    let z = spec.to_z(d);
    let lo = spec.from_z([z[0] - k[0] * sd_z[0], z[1] - k[1] * sd_z[1]]);
    let hi = spec.from_z([z[0] + k[0] * sd_z[0], z[1] + k[1] * sd_z[1]]);
    Interval { q_mobile_c: [lo.q_mobile_c, hi.q_mobile_c], r_o_ohm: [lo.r_o_ohm, hi.r_o_ohm] }
}

/// Runs a calibrator along an episode, predicting the end of discharge at the set fractions on the
/// calibrators' model `ext` (its Arrhenius factors, if any, at the cell's temperature then).
fn run_episode(cal: &mut dyn Calibrator, e: &Episode, ext: &ModelExtension, cutoff_v: f64) -> Trace {
    let ref_k = ext.reference_k.or(e.samples.first().map(|s| s.temperature_k)).unwrap_or(ext.params().tb0_k);
    let n = e.samples.len();
    let end = e.eod_s.unwrap_or_else(|| e.samples[n - 1].t_s);
    let start = e.spec.rest_s;
    let at: Vec<f64> = EOD_FRACTIONS.iter().map(|f| start + f * (end - start)).collect();
    let mut next = 0;
    let mut out = Trace { estimates: Vec::with_capacity(n), intervals: Vec::with_capacity(n), eod_pred_s: [None; 3] };
    for s in &e.samples {
        cal.step(s);
        out.estimates.push(cal.estimate());
        out.intervals.push(cal.interval());
        while next < at.len() && s.t_s >= at[next] {
            out.eod_pred_s[next] = cal.state().and_then(|x| {
                let q = EodQuery { profile: &e.spec.profile, cutoff_v, dt_s: 1.0, max_s: 4.0 * (end + 100.0) };
                let (model, ro_factor) =
                    ext.model_at(x[bcal_common::math::idx::T_B], ref_k).expect("the config checks the model extension");
                let d = Degradation { r_o_ohm: cal.estimate().r_o_ohm * ro_factor, ..cal.estimate() };
                predict_eod_s(&model, &x, &d, s.t_s, &q)
            });
            next += 1;
        }
    }
    out
}

/// Accuracy of one method at one noise level.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MethodScores {
    /// Table-1 NRMSE over every reading of every test cell, %.
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub nrmse_pct: ParamValues,
    /// The same over the readings of each discharge's second half (by time).
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub second_half_nrmse_pct: ParamValues,
    /// Median over cells of the time from the first reading after which the estimate stays within 2 % of
    /// the range, s; null when more than half the cells never settle.
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub time_to_2pct_s: ParamValues,
    /// Cells whose estimate settles within 2 %, fraction.
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub settled_fraction: ParamValues,
    /// Readings whose 90 % interval holds the truth, % of the readings that have an interval (null for a
    /// method without intervals).
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub coverage_90_pct: ParamValues,
    /// Readings that have an interval, %.
    pub interval_available_pct: f64,
    /// End-of-discharge prediction made at 10 / 50 / 90 % of each discharge: absolute error, s.
    pub eod: BTreeMap<String, EodSummary>,
    /// Per-reading calibration cost, us (one thread); in the headline noise level only.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub step_us: Option<f64>,
}

/// End-of-discharge prediction errors at one fraction.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EodSummary {
    pub mae_s: f64,
    pub median_abs_s: f64,
    /// Mean absolute error in % of each discharge's duration (load on to cut-off).
    pub mae_pct_of_discharge: f64,
    pub bias_s: f64,
    pub n: usize,
    pub failures: usize,
}

/// Scores traces of test episodes.
pub fn score(episodes: &[Episode], traces: &[Trace]) -> MethodScores {
    let mut m = MethodScores::default();
    let mut settle: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
    let (mut sq, mut sq2, mut n, mut n2) = ([0.0; 2], [0.0; 2], 0usize, 0usize);
    let (mut cover, mut with_iv) = ([0usize; 2], 0usize);
    for (e, t) in episodes.iter().zip(traces) {
        let truth = e.spec.truth;
        let half = 0.5 * e.samples.last().map_or(0.0, |s| s.t_s);
        let mut last_outside = [None::<f64>; 2];
        for ((s, est), iv) in e.samples.iter().zip(&t.estimates).zip(&t.intervals) {
            for (k, p) in Param::BOTH.into_iter().enumerate() {
                let err = p.err_pct(est, &truth);
                sq[k] += err * err;
                if s.t_s >= half {
                    sq2[k] += err * err;
                }
                if err.abs() > WITHIN_PCT {
                    last_outside[k] = Some(s.t_s);
                }
            }
            n += 1;
            n2 += usize::from(s.t_s >= half);
            if let Some(iv) = iv {
                with_iv += 1;
                cover[0] += usize::from(iv.q_mobile_c[0] <= truth.q_mobile_c && truth.q_mobile_c <= iv.q_mobile_c[1]);
                cover[1] += usize::from(iv.r_o_ohm[0] <= truth.r_o_ohm && truth.r_o_ohm <= iv.r_o_ohm[1]);
            }
        }
        let t0 = e.samples.first().map_or(0.0, |s| s.t_s);
        let t_end = e.samples.last().map_or(0.0, |s| s.t_s);
        for k in 0..2 {
            // Settled from the reading after the last one outside; never when the last reading is outside.
            let settled = match last_outside[k] {
                None => Some(0.0),
                Some(t) if t < t_end => {
                    let after = e.samples.iter().find(|s| s.t_s > t).map_or(t_end, |s| s.t_s);
                    Some(after - t0)
                }
                Some(_) => None,
            };
            settle[k].push(settled.unwrap_or(f64::INFINITY));
        }
    }
    let pv = |v: [f64; 2]| ParamValues { q_mobile: Some(v[0]), r_o: Some(v[1]) };
    let rmse = |s: [f64; 2], n: usize| s.map(|x| (x / n.max(1) as f64).sqrt());
    m.nrmse_pct = pv(rmse(sq, n));
    m.second_half_nrmse_pct = pv(rmse(sq2, n2));
    let mut med = [None, None];
    let mut frac = [0.0; 2];
    for k in 0..2 {
        frac[k] = settle[k].iter().filter(|t| t.is_finite()).count() as f64 / settle[k].len().max(1) as f64;
        med[k] = median(&mut settle[k]).filter(|t| t.is_finite());
    }
    m.time_to_2pct_s = ParamValues { q_mobile: med[0], r_o: med[1] };
    m.settled_fraction = pv(frac);
    m.coverage_90_pct =
        if with_iv > 0 { pv(cover.map(|c| 100.0 * c as f64 / with_iv as f64)) } else { ParamValues::default() };
    m.interval_available_pct = 100.0 * with_iv as f64 / n.max(1) as f64;
    for (k, f) in EOD_FRACTIONS.iter().enumerate() {
        let mut errs = Vec::new();
        let mut pct = Vec::new();
        let mut failures = 0;
        for (e, t) in episodes.iter().zip(traces) {
            let Some(eod) = e.eod_s else { continue };
            match t.eod_pred_s[k] {
                Some(p) => {
                    errs.push(p - eod);
                    pct.push(100.0 * (p - eod).abs() / (eod - e.spec.rest_s).max(1.0));
                }
                None => failures += 1,
            }
        }
        let n = errs.len().max(1) as f64;
        let mut abs: Vec<f64> = errs.iter().map(|e| e.abs()).collect();
        m.eod.insert(
            format!("{:.0}", f * 100.0),
            EodSummary {
                mae_s: abs.iter().sum::<f64>() / n,
                median_abs_s: median(&mut abs).unwrap_or(f64::NAN),
                mae_pct_of_discharge: pct.iter().sum::<f64>() / n,
                bias_s: errs.iter().sum::<f64>() / n,
                n: errs.len(),
                failures,
            },
        );
    }
    m
}

/// The joint UKF's tuning on validation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UkfTuning {
    pub best: JointUkfSettings,
    /// Mean of the two NRMSEs on validation, %, of the best and of each candidate tried (best first).
    pub top: Vec<(JointUkfSettings, f64)>,
    pub candidates: usize,
    pub validation_episodes: usize,
    pub counters_on_test: JointUkfCounters,
}

/// One noise level's results.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NoiseLevel {
    pub voltage_noise_mv: f64,
    pub methods: BTreeMap<String, MethodScores>,
}

/// Everything `report.json` holds for the measured-only setting.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeasuredReport {
    pub observation: String,
    /// The headline noise level (the sensor the policy was trained with), mV.
    pub voltage_noise_mv: f64,
    pub quick: bool,
    /// The headline level's methods (same layout as the paper report: `methods.<name>.nrmse_pct`, `step_us`).
    pub methods: BTreeMap<String, MethodScores>,
    pub noise_levels: Vec<NoiseLevel>,
    pub test_episodes: usize,
    pub test_readings: usize,
    pub validation_episodes: usize,
    pub test_loads: serde_json::Value,
    pub sampling_intervals_s: Vec<[f64; 2]>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub rl: Option<serde_json::Value>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub ukf: Option<UkfTuning>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub direct_mapping: Option<TrainLog>,
    /// The 90 % interval scale chosen on validation for each tracker-based method.
    pub interval_scales: BTreeMap<String, [f64; 2]>,
    pub not_evaluated: BTreeMap<String, String>,
    pub plots: Vec<String>,
    pub notes: Vec<String>,
    pub seconds: f64,
}

/// A finished measured evaluation: the report and the traces the figures need.
pub struct MeasuredEvaluation {
    pub report: MeasuredReport,
    /// Test cells at the headline noise level and each method's traces on them.
    pub episodes: Vec<Episode>,
    pub traces: Vec<(&'static str, Vec<Trace>)>,
    pub training_curve: Option<TrainingCurve>,
}

fn with_voltage_noise(cfg: &ScenarioConfig, v: f64) -> ScenarioConfig {
    let mut c = cfg.clone();
    c.sensor.voltage_noise_v = v;
    c
}

/// Every grid setting of the joint UKF on `validation` cells, the best by the mean of the two NRMSEs over
/// every reading (validation only: the test cells never choose anything).
pub fn tune_joint_ukf(spec: &TrackerSpec, validation: &[Episode], grid: &JointUkfGrid) -> UkfTuning {
    let cands = grid.candidates();
    let mut rows: Vec<(JointUkfSettings, f64)> = cands
        .par_iter()
        .map(|s| {
            let mut acc = bcal_common::nrmse::NrmseAccumulator::default();
            for e in validation {
                let mut f = JointUkf::new(*s, spec);
                for r in &e.samples {
                    f.step(r);
                    acc.add(&f.estimate(), &e.spec.truth);
                }
            }
            let (q, r) = acc.pct();
            let m = 0.5 * (q + r);
            (*s, if m.is_finite() { m } else { f64::INFINITY })
        })
        .collect();
    rows.sort_by(|a, b| a.1.total_cmp(&b.1));
    UkfTuning {
        best: rows[0].0,
        candidates: rows.len(),
        top: rows.into_iter().take(5).collect(),
        validation_episodes: validation.len(),
        counters_on_test: JointUkfCounters::default(),
    }
}

/// Per parameter, the 90th percentile of |error| / sd over the readings with a spread: the interval scales
/// that cover 90 % of validation readings. `make` builds the calibrator with scale 1.
pub fn interval_scale_on(spec: &TrackerSpec, episodes: &[Episode], make: &Make) -> [f64; 2] {
    let ratios: Vec<(usize, f64)> = episodes
        .par_iter()
        .flat_map_iter(|e| {
            let mut cal = make();
            let mut out = Vec::new();
            for s in &e.samples {
                cal.step(s);
                let Some(iv) = cal.interval() else { continue };
                // The interval of scale 1 is recovered from the one of the calibrator's current scale.
                let est = spec.to_z(&cal.estimate());
                let truth = spec.to_z(&e.spec.truth);
                let (lo, hi) = (
                    spec.to_z(&Degradation { q_mobile_c: iv.q_mobile_c[0], r_o_ohm: iv.r_o_ohm[0] }),
                    spec.to_z(&Degradation { q_mobile_c: iv.q_mobile_c[1], r_o_ohm: iv.r_o_ohm[1] }),
                );
                for k in 0..2 {
                    let half = 0.5 * (hi[k] - lo[k]);
                    if half > 1e-12 {
                        out.push((k, (truth[k] - est[k]).abs() / half));
                    }
                }
            }
            out
        })
        .collect();
    [0, 1].map(|k| {
        let mut r: Vec<f64> = ratios.iter().filter(|(j, _)| *j == k).map(|(_, v)| *v).collect();
        if r.is_empty() {
            return 1.0;
        }
        r.sort_by(f64::total_cmp);
        r[((r.len() - 1) as f64 * 0.9).round() as usize]
    })
}

/// Readings timed per method on one thread: per reading, us (median of repeats).
fn time_method(episodes: &[Episode], readings: usize, make: &Make) -> f64 {
    let per = (readings / TIMING_REPEATS).max(1);
    let reps: Vec<f64> = (0..TIMING_REPEATS)
        .map(|_| {
            let t0 = Instant::now();
            let mut done = 0;
            'outer: loop {
                for e in episodes {
                    let mut cal = make();
                    for s in &e.samples {
                        cal.step(s);
                        std::hint::black_box(cal.estimate());
                        done += 1;
                        if done >= per {
                            break 'outer;
                        }
                    }
                }
            }
            t0.elapsed().as_secs_f64() * 1e6 / done as f64
        })
        .collect();
    median_of(reps)
}

/// Supervised pairs for the direct mapping: the window fit's observation at sampled readings of `episodes`,
/// target the truth in action units ([-1, 1] over the calibrator's ranges).
fn direct_pairs(spec: &TrackerSpec, episodes: &[Episode], max_pairs: usize, seed: u64) -> Pairs {
    let total: usize = episodes.iter().map(|e| e.samples.len()).sum();
    let keep = (max_pairs as f64 / total.max(1) as f64).min(1.0);
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut p = Pairs { obs_dim: OBS_DIM, act_dim: 2, ..Default::default() };
    let mut obs = [0f32; OBS_DIM];
    for e in episodes {
        let z = spec.to_z(&e.spec.truth);
        let mut fit = WindowFitCalibrator::new(spec);
        for s in &e.samples {
            fit.step(s);
            if rng.random::<f64>() < keep {
                fit.tracker().observe(&mut obs);
                p.obs.extend_from_slice(&obs);
                p.target.extend_from_slice(&[(2.0 * z[0] - 1.0) as f32, (2.0 * z[1] - 1.0) as f32]);
            }
        }
    }
    p
}

/// Runs the whole measured-only evaluation.
pub fn evaluate_measured(
    input: &MeasuredInput,
    opts: &MeasuredEvalOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<MeasuredEvaluation, MeasuredEvalError> {
    let started = Instant::now();
    let spec = input.spec;
    let sc = &spec.scenario;
    // End-of-discharge predictions run the calibrators' own model: it must build.
    spec.tracker.model.model().map_err(|e| MeasuredEvalError::Episodes { split: "model", why: e.to_string() })?;
    let cutoff_v = spec.tracker.cutoff_v;
    let n_val = opts.validation_episodes.unwrap_or(sc.validation_episodes);
    let n_test = opts.test_episodes.unwrap_or(sc.test_episodes);
    let episodes_of = |cfg: &ScenarioConfig, split: Split, n: usize, name: &'static str| {
        episode_set(cfg, split, n).map_err(|e| MeasuredEvalError::Episodes { split: name, why: e.to_string() })
    };
    let validation = episodes_of(sc, Split::Validation, n_val, "validation")?;
    progress(&format!(
        "validation: {} cells at loads {:?} W / {:?} A; test: {n_test} cells at {:?} W / {:?} A, voltage noise {:?} mV",
        validation.len(),
        sc.validation.power_w,
        sc.validation.current_a,
        sc.test.power_w,
        sc.test.current_a,
        opts.voltage_noise_levels_v.iter().map(|v| v * 1e3).collect::<Vec<_>>()
    ));
    let mut notes = Vec::new();
    let mut not_evaluated = BTreeMap::new();
    let mut interval_scales = BTreeMap::new();
    let mut rl_info = None;

    // The policy, checked against the task.
    let net = match &input.policy {
        PolicyInput::Loaded { file, path, choice } if opts.rl => {
            let Some(_) = file.task.measured() else {
                return Err(MeasuredEvalError::TaskMismatch {
                    policy: file.task.observation_name(),
                    data: "Measured".into(),
                });
            };
            if file.layout.obs_dim != OBS_DIM || file.layout.act_dim != 2 {
                return Err(MeasuredEvalError::PolicyShape {
                    got: format!("{} -> {}", file.layout.obs_dim, file.layout.act_dim),
                    want: format!("{OBS_DIM} -> 2"),
                });
            }
            rl_info = Some(serde_json::json!({
                "policy_file": path, "choice": choice, "update_step": file.update_step, "hidden": file.layout.hidden,
                "action": "deterministic tanh(mean), pure-Rust PolicyNet",
            }));
            Some(file.net()?)
        }
        PolicyInput::Missing { reason } if opts.rl => {
            not_evaluated.insert("rl_lac".to_string(), reason.clone());
            None
        }
        _ => {
            not_evaluated.insert("rl_lac".to_string(), "disabled by the command line".into());
            None
        }
    };

    // Interval scales of the tracker-based calibrators, chosen on validation.
    let mut rl_spec = spec.tracker.clone();
    if let Some(net) = &net {
        let unit = TrackerSpec { interval_scale: [1.0; 2], ..spec.tracker.clone() };
        let make: Make = Box::new(|| Box::new(RlCalibrator::new(&unit, net)));
        rl_spec.interval_scale = interval_scale_on(&unit, &validation, &make);
        interval_scales.insert("rl_lac".to_string(), rl_spec.interval_scale);
        progress(&format!(
            "RL-LAC: 90 % interval scales qMobile {:.2}, Ro {:.2} (validation)",
            rl_spec.interval_scale[0], rl_spec.interval_scale[1]
        ));
    }
    let unit = TrackerSpec { interval_scale: [1.0; 2], ..spec.tracker.clone() };
    let fit_spec = {
        let make: Make = Box::new(|| Box::new(WindowFitCalibrator::new(&unit)));
        TrackerSpec { interval_scale: interval_scale_on(&unit, &validation, &make), ..spec.tracker.clone() }
    };
    interval_scales.insert("window_fit".to_string(), fit_spec.interval_scale);

    // The joint UKF: every grid setting on validation, the best by the mean of the two NRMSEs.
    let mut ukf_tuning = None;
    if opts.ukf {
        progress(&format!(
            "joint UKF: tuning {} settings on {} validation cells",
            opts.ukf_grid.candidates().len(),
            validation.len()
        ));
        let t = tune_joint_ukf(&spec.tracker, &validation, &opts.ukf_grid);
        let best = t.best;
        progress(&format!(
            "joint UKF: chose meas_std {:.1} mV, parameter walk {:e}/sqrt(s), charge walk {} C/sqrt(s), prior std {:?} (validation mean NRMSE {:.2} %)",
            best.meas_std_v * 1e3, best.param_walk_per_sqrt_s, best.charge_walk_c_per_sqrt_s, best.prior_std_z, t.top[0].1
        ));
        ukf_tuning = Some(t);
    } else {
        not_evaluated.insert("ukf".into(), "disabled by the command line".into());
    }

    // The direct mapping: pairs from training cells, early stopping on validation cells.
    let mut dm: Option<(PolicyNet, TrainLog, [f64; 2])> = None;
    if opts.direct_mapping {
        let mut rng = SmallRng::seed_from_u64(input.seed ^ 0xd1ec7);
        let train: Vec<Episode> = (0..opts.direct_train_episodes)
            .filter_map(|_| {
                let s = bcal_common::measured::scenario::draw_spec(sc, Split::Train, &mut rng);
                bcal_common::measured::scenario::simulate(sc, &s).ok()
            })
            .collect();
        let pairs = direct_pairs(&spec.tracker, &train, opts.direct.max_pairs, input.seed);
        let val_pairs = direct_pairs(&spec.tracker, &validation, opts.direct.max_validation_pairs, input.seed + 1);
        progress(&format!(
            "direct mapping: {} pairs from {} training cells, early stopping on {} validation pairs (budget {:.0} s)",
            pairs.len(),
            train.len(),
            val_pairs.len(),
            opts.direct.time_budget_s
        ));
        let (map, log) =
            DirectMap::train(&pairs, &val_pairs, &DirectMapConfig { seed: input.seed, ..opts.direct.clone() })?;
        progress(&format!(
            "direct mapping: {} updates in {:.0} s ({}), best validation MSE {:.2e}",
            log.updates,
            log.seconds,
            log.stopped_by.replace('_', " "),
            log.best_validation_loss
        ));
        let pure = map.to_policy_net()?;
        let scale = {
            let make: Make = Box::new(|| {
                Box::new(DirectCalibrator {
                    fit: WindowFitCalibrator::new(&spec.tracker),
                    net: &pure,
                    scratch: Scratch::new(pure.layout()),
                    spec: spec.tracker.clone(),
                    interval_scale: [1.0; 2],
                    estimate: spec.tracker.prior,
                })
            });
            interval_scale_on(&spec.tracker, &validation, &make)
        };
        interval_scales.insert("direct_mapping".to_string(), scale);
        dm = Some((pure, log, scale));
    } else {
        not_evaluated.insert("direct_mapping".into(), "disabled by the command line".into());
    }

    // Every method on the test cells at every noise level.
    let headline_v = sc.sensor.voltage_noise_v;
    let mut levels = Vec::new();
    let mut headline_traces = Vec::new();
    let mut headline_episodes = Vec::new();
    let mut counters = JointUkfCounters::default();
    let mut test_readings = 0;
    for &v in &opts.voltage_noise_levels_v {
        let test = episodes_of(&with_voltage_noise(sc, v), Split::Test, n_test, "test")?;
        let mut methods: Vec<(&'static str, Make)> = Vec::new();
        if let Some(net) = &net {
            let s = rl_spec.clone();
            methods.push(("rl_lac", Box::new(move || Box::new(RlCalibrator::new(&s, net)))));
        }
        if let Some(t) = &ukf_tuning {
            let (b, s) = (t.best, spec.tracker.clone());
            methods.push(("ukf", Box::new(move || Box::new(JointUkf::new(b, &s)))));
        }
        if let Some((pure, _, scale)) = &dm {
            let (s, k) = (spec.tracker.clone(), *scale);
            methods.push((
                "direct_mapping",
                Box::new(move || {
                    Box::new(DirectCalibrator {
                        fit: WindowFitCalibrator::new(&s),
                        net: pure,
                        scratch: Scratch::new(pure.layout()),
                        spec: s.clone(),
                        interval_scale: k,
                        estimate: s.prior,
                    })
                }),
            ));
        }
        {
            let s = fit_spec.clone();
            methods.push(("window_fit", Box::new(move || Box::new(WindowFitCalibrator::new(&s)))));
            let s = spec.tracker.clone();
            methods.push(("uncalibrated", Box::new(move || Box::new(Uncalibrated::new(&s)))));
        }
        let headline = (v - headline_v).abs() < 1e-12;
        let mut scores = BTreeMap::new();
        for (key, make) in &methods {
            let traces: Vec<Trace> =
                test.par_iter().map(|e| run_episode(make().as_mut(), e, &spec.tracker.model, cutoff_v)).collect();
            let mut m = score(&test, &traces);
            if headline {
                m.step_us = Some(time_method(&test, opts.timing_readings, make));
                if *key == "ukf" {
                    // Rescues of the headline run, counted on a fresh pass (the traces do not keep them).
                    for e in &test {
                        let mut f = JointUkf::new(ukf_tuning.as_ref().expect("ukf runs").best, &spec.tracker);
                        for s in &e.samples {
                            f.step(s);
                        }
                        counters.add(&f.counters);
                    }
                }
                headline_traces.push((*key, traces));
            }
            progress(&format!(
                "{:>4.1} mV {key}: NRMSE q {:.2} % r {:.2} % (second half {:.2} / {:.2}), coverage {:?}/{:?}{}",
                v * 1e3,
                m.nrmse_pct.q_mobile.unwrap_or(f64::NAN),
                m.nrmse_pct.r_o.unwrap_or(f64::NAN),
                m.second_half_nrmse_pct.q_mobile.unwrap_or(f64::NAN),
                m.second_half_nrmse_pct.r_o.unwrap_or(f64::NAN),
                m.coverage_90_pct.q_mobile.map(|x| (x * 10.0).round() / 10.0),
                m.coverage_90_pct.r_o.map(|x| (x * 10.0).round() / 10.0),
                m.step_us.map_or(String::new(), |us| format!(", {us:.2} us/step"))
            ));
            scores.insert(key.to_string(), m);
        }
        if headline {
            test_readings = test.iter().map(|e| e.samples.len()).sum();
            headline_episodes = test;
        }
        levels.push(NoiseLevel { voltage_noise_mv: v * 1e3, methods: scores });
    }
    if let Some(t) = &mut ukf_tuning {
        t.counters_on_test = counters;
    }
    let methods =
        levels.iter().find(|l| (l.voltage_noise_mv - headline_v * 1e3).abs() < 1e-9).map(|l| l.methods.clone());
    if methods.is_none() {
        notes.push(format!(
            "the sensor's own noise ({:.1} mV) is not among the evaluated levels: `methods` is empty",
            headline_v * 1e3
        ));
    }
    let report = MeasuredReport {
        observation: "Measured".into(),
        voltage_noise_mv: headline_v * 1e3,
        quick: opts.quick,
        methods: methods.unwrap_or_default(),
        noise_levels: levels,
        test_episodes: n_test,
        test_readings,
        validation_episodes: validation.len(),
        test_loads: serde_json::json!({"power_w": sc.test.power_w, "current_a": sc.test.current_a}),
        sampling_intervals_s: sc.sample_interval_s.clone(),
        rl: rl_info,
        ukf: ukf_tuning,
        direct_mapping: dm.map(|d| d.1),
        interval_scales,
        not_evaluated,
        plots: Vec::new(),
        notes,
        seconds: started.elapsed().as_secs_f64(),
    };
    Ok(MeasuredEvaluation {
        report,
        episodes: headline_episodes,
        traces: headline_traces,
        training_curve: input.training_curve.clone(),
    })
}

/// The tracker's state under an estimate (for EOD predictions of tracker-based calibrators).
pub fn state_of(t: &Tracker) -> Option<ModelState> {
    tracker_state(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Scores of hand-made traces: NRMSE, second half, settling and coverage as computed on paper.
    #[test]
    fn scores_on_hand_made_traces() {
        let cfg = ScenarioConfig::default();
        let mut e = episode_set(&cfg, Split::Test, 1).unwrap().remove(0);
        e.samples.truncate(4);
        for (k, s) in e.samples.iter_mut().enumerate() {
            s.t_s = k as f64 * 10.0;
        }
        let t = e.spec.truth;
        let off = |dq: f64| Degradation { q_mobile_c: t.q_mobile_c + dq, ..t };
        // qMobile errors: 300 C (10 %), 90 C (3 %), 0, 0; Ro exact.
        let iv = Interval { q_mobile_c: [t.q_mobile_c - 1.0, t.q_mobile_c + 1.0], r_o_ohm: [0.0, 1.0] };
        let miss = Interval { q_mobile_c: [t.q_mobile_c + 80.0, t.q_mobile_c + 100.0], ..iv };
        let trace = Trace {
            estimates: vec![off(300.0), off(90.0), off(0.0), off(0.0)],
            intervals: vec![None, Some(miss), Some(iv), Some(iv)],
            eod_pred_s: [e.eod_s, None, e.eod_s.map(|x| x + 10.0)],
        };
        let m = score(std::slice::from_ref(&e), &[trace]);
        assert!((m.nrmse_pct.q_mobile.unwrap() - ((100.0f64 + 9.0) / 4.0).sqrt()).abs() < 1e-9);
        assert_eq!(m.nrmse_pct.r_o, Some(0.0));
        // Second half: readings at 20 and 30 s of a 30 s record.
        assert_eq!(m.second_half_nrmse_pct.q_mobile, Some(0.0));
        // Within 2 % from the reading at 20 s (the last outside is at 10 s).
        assert_eq!(m.time_to_2pct_s.q_mobile, Some(20.0));
        assert_eq!(m.time_to_2pct_s.r_o, Some(0.0));
        // Three readings with an interval; the one at 10 s misses qMobile (its interval is 80-100 C above).
        assert!((m.coverage_90_pct.q_mobile.unwrap() - 200.0 / 3.0).abs() < 1e-9);
        assert_eq!(m.coverage_90_pct.r_o, Some(100.0));
        assert_eq!(m.interval_available_pct, 75.0);
        assert_eq!(m.eod["10"].mae_s, 0.0);
        assert_eq!(m.eod["50"].failures, 1);
        assert_eq!(m.eod["90"].mae_s, 10.0);
    }
}
