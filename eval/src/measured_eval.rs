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
use crate::metrics::ParamValues;
use crate::plots::TrainingCurve;
use bcal_calib::direct::{DirectCalibrator, DirectInputs};
use bcal_calib::joint_ukf::{JointUkf, JointUkfCounters};
pub use bcal_calib::tune::{
    interval_scale_on, tune_adaptive, tune_joint_ukf, AdaptiveGrid, AdaptiveTuning, JointUkfGrid, Make, UkfTuning,
};
use bcal_calib::{
    predict_eod_s, tracker_state, Calibrator, EodQuery, Interval, RlCalibrator, Tracker, Uncalibrated,
    WindowFitCalibrator,
};
use bcal_calib::{AdaptiveUkf, CorrectionCalibrator};
use bcal_common::battery::Degradation;
use bcal_common::battery::LoadProfile;
use bcal_common::dataset::Split;
use bcal_common::math::ModelState;
use bcal_common::measured::env::Design;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::scenario::{episode_set, Episode, ScenarioConfig};
use bcal_common::measured::tracker::TrackerSpec;
use bcal_common::measured::LoadMean;
use bcal_common::nrmse::Param;
use bcal_common::policy::PolicyNet;
use bcal_common::stats::median;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Instant;

/// Method keys in report order, with display names.
pub const METHODS: [(&str, &str); 6] = [
    ("rl_lac", "RL-LAC"),
    ("ukf", "Joint UKF"),
    ("adaptive_ukf", "Adaptive UKF (covariance matching)"),
    ("direct_mapping", "Direct mapping"),
    ("window_fit", "Window fit (no learning)"),
    ("uncalibrated", "Uncalibrated"),
];

/// Fractions of each discharge at which the end of discharge is predicted.
pub const EOD_FRACTIONS: [f64; 3] = [0.1, 0.5, 0.9];
/// Threshold of the convergence time, % of each parameter's Table-1 range.
pub const WITHIN_PCT: f64 = 2.0;

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
    /// The adaptive UKF's rules (tried on top of the tuned filter, on validation).
    pub adaptive_grid: AdaptiveGrid,
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
            adaptive_grid: AdaptiveGrid::default(),
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
            adaptive_grid: AdaptiveGrid::quick(),
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
    /// Predicted end of discharge at each of [`EOD_FRACTIONS`] under the load so far ([`LoadMean::load`]: the
    /// mean measured current, or the mean power where the load has been held at power), as a BMS (and
    /// `bcal calibrate` on real cells) predicts it (None: the prediction failed).
    pub eod_pred_s: [Option<f64>; 3],
    /// The same under the cell's true future load (an oracle of the load, not of the cell: it isolates the
    /// calibration's share of the error).
    pub eod_oracle_load_s: [Option<f64>; 3],
}

/// Runs a calibrator along an episode, predicting the end of discharge at the set fractions on the
/// calibrators' model `ext` (its Arrhenius factors, if any, at the cell's temperature then), under the load
/// so far and under the true future load.
fn run_episode(cal: &mut dyn Calibrator, e: &Episode, ext: &ModelExtension, cutoff_v: f64) -> Trace {
    let ref_k = ext.reference_k.or(e.samples.first().map(|s| s.temperature_k)).unwrap_or(ext.params().tb0_k);
    let n = e.samples.len();
    let end = e.eod_s.unwrap_or_else(|| e.samples[n - 1].t_s);
    let start = e.spec.rest_s;
    let at: Vec<f64> = EOD_FRACTIONS.iter().map(|f| start + f * (end - start)).collect();
    let mut next = 0;
    let mut out = Trace {
        estimates: Vec::with_capacity(n),
        intervals: Vec::with_capacity(n),
        eod_pred_s: [None; 3],
        eod_oracle_load_s: [None; 3],
    };
    // The load so far as a real cell's predictions assume it (`LoadMean`): the mean current of the loaded
    // readings, over time where the load alternates, or their mean power where it has been held at power.
    let mut load = LoadMean::default();
    for s in &e.samples {
        cal.step(s);
        out.estimates.push(cal.estimate());
        out.intervals.push(cal.interval());
        load.push(s.t_s, s.current_a, s.voltage_v);
        while next < at.len() && s.t_s >= at[next] {
            if let Some(x) = cal.state() {
                let (model, ro_factor) =
                    ext.model_at(x[bcal_common::math::idx::T_B], ref_k).expect("the config checks the model extension");
                let d = Degradation { r_o_ohm: cal.estimate().r_o_ohm * ro_factor, ..cal.estimate() };
                let max_s = 4.0 * (end + 100.0);
                let oracle = EodQuery { profile: &e.spec.profile, cutoff_v, dt_s: 1.0, max_s };
                out.eod_oracle_load_s[next] = predict_eod_s(&model, &x, &d, s.t_s, &oracle);
                if let Some(assumed) = load.load() {
                    let mean = LoadProfile::Constant(assumed);
                    let q = EodQuery { profile: &mean, cutoff_v, dt_s: 1.0, max_s };
                    out.eod_pred_s[next] = predict_eod_s(&model, &x, &d, s.t_s, &q);
                }
            }
            next += 1;
        }
    }
    out
}

/// NRMSE and coverage of one set of cells.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Breakdown {
    pub cells: usize,
    pub readings: usize,
    /// Over every reading of these cells, pooled, %.
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub nrmse_pct: ParamValues,
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub second_half_nrmse_pct: ParamValues,
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub coverage_90_pct: ParamValues,
    /// Each cell's figure first, then their mean: every cell weighs the same, however many readings it
    /// has (a cell without a second half, or without an interval, is left out of that mean).
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub per_cell_nrmse_pct: ParamValues,
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub per_cell_second_half_nrmse_pct: ParamValues,
    #[serde(serialize_with = "crate::metrics::both_keys")]
    pub per_cell_coverage_90_pct: ParamValues,
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
    /// The same figures per cell (mean over cells) beside the pooled ones, over all cells.
    pub all_cells: Breakdown,
    /// By sampling regime ("1s", "10-20s"): 1 s cells hold most readings, so the pooled figure is theirs.
    pub by_sampling: BTreeMap<String, Breakdown>,
    /// End-of-discharge prediction made at 10 / 50 / 90 % of each discharge under the load so far
    /// (as on real cells: [`LoadMean::load`]): absolute error, s, and the predictions that failed.
    pub eod: BTreeMap<String, EodSummary>,
    /// The same under the cell's true future load (labelled oracle: the load is known, the cell is not).
    pub eod_oracle_load: BTreeMap<String, EodSummary>,
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
    /// Predictions that failed (the model never reached the cut-off, or no state): not in the errors.
    pub failures: usize,
}

/// The sampling regime of a cell, as the report names it.
pub fn sampling_regime(e: &Episode) -> String {
    let [lo, hi] = e.spec.interval_s;
    if (hi - lo).abs() < 1e-9 {
        format!("{lo:.0}s")
    } else {
        format!("{lo:.0}-{hi:.0}s")
    }
}

/// One cell's sums.
#[derive(Clone, Copy, Debug, Default)]
struct CellSums {
    sq: [f64; 2],
    n: usize,
    sq2: [f64; 2],
    n2: usize,
    cover: [usize; 2],
    with_iv: usize,
}

fn breakdown(cells: &[&CellSums]) -> Breakdown {
    let pv = |v: [f64; 2]| ParamValues { q_mobile: Some(v[0]), r_o: Some(v[1]) };
    let (mut sq, mut sq2, mut n, mut n2, mut cover, mut with_iv) = ([0.0; 2], [0.0; 2], 0, 0, [0usize; 2], 0);
    let (mut pc, mut pc2, mut pcc) = (Vec::new(), Vec::new(), Vec::new());
    for c in cells {
        for k in 0..2 {
            sq[k] += c.sq[k];
            sq2[k] += c.sq2[k];
            cover[k] += c.cover[k];
        }
        n += c.n;
        n2 += c.n2;
        with_iv += c.with_iv;
        if c.n > 0 {
            pc.push(c.sq.map(|x| (x / c.n as f64).sqrt()));
        }
        if c.n2 > 0 {
            pc2.push(c.sq2.map(|x| (x / c.n2 as f64).sqrt()));
        }
        if c.with_iv > 0 {
            pcc.push(c.cover.map(|x| 100.0 * x as f64 / c.with_iv as f64));
        }
    }
    let mean = |v: &[[f64; 2]]| {
        if v.is_empty() {
            ParamValues::default()
        } else {
            pv([0, 1].map(|k| v.iter().map(|x| x[k]).sum::<f64>() / v.len() as f64))
        }
    };
    Breakdown {
        cells: cells.len(),
        readings: n,
        nrmse_pct: pv(sq.map(|x| (x / n.max(1) as f64).sqrt())),
        second_half_nrmse_pct: pv(sq2.map(|x| (x / n2.max(1) as f64).sqrt())),
        coverage_90_pct: if with_iv > 0 {
            pv(cover.map(|c| 100.0 * c as f64 / with_iv as f64))
        } else {
            ParamValues::default()
        },
        per_cell_nrmse_pct: mean(&pc),
        per_cell_second_half_nrmse_pct: mean(&pc2),
        per_cell_coverage_90_pct: mean(&pcc),
    }
}

fn eod_summaries(episodes: &[Episode], preds: &[[Option<f64>; 3]]) -> BTreeMap<String, EodSummary> {
    let mut out = BTreeMap::new();
    for (k, f) in EOD_FRACTIONS.iter().enumerate() {
        let (mut errs, mut pct, mut failures) = (Vec::new(), Vec::new(), 0);
        for (e, p) in episodes.iter().zip(preds) {
            let Some(eod) = e.eod_s else { continue };
            match p[k] {
                Some(p) => {
                    errs.push(p - eod);
                    pct.push(100.0 * (p - eod).abs() / (eod - e.spec.rest_s).max(1.0));
                }
                None => failures += 1,
            }
        }
        let n = errs.len().max(1) as f64;
        let mut abs: Vec<f64> = errs.iter().map(|e| e.abs()).collect();
        out.insert(
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
    out
}

/// Scores traces of test episodes.
pub fn score(episodes: &[Episode], traces: &[Trace]) -> MethodScores {
    let mut m = MethodScores::default();
    let mut settle: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
    let mut cells = Vec::with_capacity(episodes.len());
    for (e, t) in episodes.iter().zip(traces) {
        let truth = e.spec.truth;
        let half = 0.5 * e.samples.last().map_or(0.0, |s| s.t_s);
        let mut last_outside = [None::<f64>; 2];
        let mut c = CellSums::default();
        for ((s, est), iv) in e.samples.iter().zip(&t.estimates).zip(&t.intervals) {
            for (k, p) in Param::BOTH.into_iter().enumerate() {
                let err = p.err_pct(est, &truth);
                c.sq[k] += err * err;
                if s.t_s >= half {
                    c.sq2[k] += err * err;
                }
                if err.abs() > WITHIN_PCT {
                    last_outside[k] = Some(s.t_s);
                }
            }
            c.n += 1;
            c.n2 += usize::from(s.t_s >= half);
            if let Some(iv) = iv {
                c.with_iv += 1;
                c.cover[0] += usize::from(iv.q_mobile_c[0] <= truth.q_mobile_c && truth.q_mobile_c <= iv.q_mobile_c[1]);
                c.cover[1] += usize::from(iv.r_o_ohm[0] <= truth.r_o_ohm && truth.r_o_ohm <= iv.r_o_ohm[1]);
            }
        }
        cells.push((sampling_regime(e), c));
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
    let all = breakdown(&cells.iter().map(|(_, c)| c).collect::<Vec<_>>());
    m.nrmse_pct = all.nrmse_pct;
    m.second_half_nrmse_pct = all.second_half_nrmse_pct;
    m.coverage_90_pct = all.coverage_90_pct;
    let with_iv: usize = cells.iter().map(|(_, c)| c.with_iv).sum();
    m.interval_available_pct = 100.0 * with_iv as f64 / all.readings.max(1) as f64;
    let regimes: std::collections::BTreeSet<&String> = cells.iter().map(|(r, _)| r).collect();
    for r in regimes {
        let of: Vec<&CellSums> = cells.iter().filter(|(x, _)| x == r).map(|(_, c)| c).collect();
        m.by_sampling.insert(r.clone(), breakdown(&of));
    }
    m.all_cells = all;
    let pv = |v: [f64; 2]| ParamValues { q_mobile: Some(v[0]), r_o: Some(v[1]) };
    let mut med = [None, None];
    let mut frac = [0.0; 2];
    for k in 0..2 {
        frac[k] = settle[k].iter().filter(|t| t.is_finite()).count() as f64 / settle[k].len().max(1) as f64;
        med[k] = median(&mut settle[k]).filter(|t| t.is_finite());
    }
    m.time_to_2pct_s = ParamValues { q_mobile: med[0], r_o: med[1] };
    m.settled_fraction = pv(frac);
    m.eod = eod_summaries(episodes, &traces.iter().map(|t| t.eod_pred_s).collect::<Vec<_>>());
    m.eod_oracle_load = eod_summaries(episodes, &traces.iter().map(|t| t.eod_oracle_load_s).collect::<Vec<_>>());
    m
}

/// One test condition's results: a noise level, and the probability of each model-error cause the cells
/// carry ([`bcal_common::measured::scenario::ModelErrorConfig`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NoiseLevel {
    pub voltage_noise_mv: f64,
    #[serde(default)]
    pub model_error_probability: f64,
    pub methods: BTreeMap<String, MethodScores>,
}

/// The model error the other test condition's cells carry when the task's cells carry none.
pub const OTHER_MODEL_ERROR_PROBABILITY: f64 = 0.5;

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
    /// The same methods on the test cells of the other model at the headline noise: the exact model when the
    /// task's cells carry model error, cells that carry it otherwise.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub other_model: Option<NoiseLevel>,
    pub test_episodes: usize,
    pub test_readings: usize,
    pub validation_episodes: usize,
    pub test_loads: serde_json::Value,
    pub sampling_intervals_s: Vec<[f64; 2]>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub rl: Option<serde_json::Value>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub ukf: Option<UkfTuning>,
    /// The joint UKF every filter-based method runs (the task's, or the one tuned here).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub ukf_settings: Option<bcal_common::measured::tracker::JointUkfSettings>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub adaptive_ukf: Option<AdaptiveTuning>,
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
fn direct_pairs(task: &MeasuredSpec, episodes: &[Episode], max_pairs: usize, seed: u64) -> Pairs {
    let total: usize = episodes.iter().map(|e| e.samples.len()).sum();
    let keep = (max_pairs as f64 / total.max(1) as f64).min(1.0);
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut p = Pairs { obs_dim: task.obs_dim(), act_dim: 2, ..Default::default() };
    let mut obs = vec![0f32; task.obs_dim()];
    for e in episodes {
        let z = task.tracker.to_z(&e.spec.truth);
        let mut inputs = DirectInputs::of_task(task);
        for s in &e.samples {
            inputs.step(s);
            if rng.random::<f64>() < keep {
                inputs.observe(&mut obs);
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
            if file.layout.obs_dim != spec.obs_dim() || file.layout.act_dim != spec.act_dim() {
                return Err(MeasuredEvalError::PolicyShape {
                    got: format!("{} -> {}", file.layout.obs_dim, file.layout.act_dim),
                    want: format!("{} -> {} ({})", spec.obs_dim(), spec.act_dim(), spec.design.name()),
                });
            }
            rl_info = Some(serde_json::json!({
                "policy_file": path, "choice": choice, "update_step": file.update_step, "hidden": file.layout.hidden,
                "action": "deterministic tanh(mean), pure-Rust PolicyNet",
                "design": spec.design.name(),
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

    // The joint UKF: the task's (tuned on these validation cells when training started, with the same grid),
    // else every grid setting on validation, the best by the mean of the two NRMSEs.
    let mut ukf_tuning = None;
    let base_ukf = match spec.ukf {
        Some(b) => {
            progress(&format!(
                "joint UKF: the task's (tuned on validation when training started): meas_std {:.1} mV, parameter walk {:e}/sqrt(s), charge walk {} C/sqrt(s), prior std {:?}",
                b.meas_std_v * 1e3, b.param_walk_per_sqrt_s, b.charge_walk_c_per_sqrt_s, b.prior_std_z
            ));
            b
        }
        None => {
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
            best
        }
    };
    let mut task = spec.clone();
    task.ukf = Some(base_ukf);
    if !opts.ukf {
        not_evaluated.insert("ukf".into(), "disabled by the command line".into());
        not_evaluated.insert("adaptive_ukf".into(), "disabled by the command line".into());
    }

    // Every method's 90 % interval is scaled on validation (the factor on its own spread that covers 90 %
    // of validation readings), the filters' too.
    let scale_of = |key: &str, make: &Make, interval_scales: &mut BTreeMap<String, [f64; 2]>| {
        let k = interval_scale_on(&spec.tracker, &validation, make);
        interval_scales.insert(key.to_string(), k);
        k
    };
    let mut rl_task = task.clone();
    if let Some(net) = &net {
        match spec.design {
            Design::WindowFit => {
                let unit = MeasuredSpec {
                    tracker: TrackerSpec { interval_scale: [1.0; 2], ..task.tracker.clone() },
                    ..task.clone()
                };
                let make: Make = Box::new(|| Box::new(RlCalibrator::new(&unit.tracker, net)));
                rl_task.tracker.interval_scale = scale_of("rl_lac", &make, &mut interval_scales);
            }
            Design::UkfCorrection => {
                let mut unit = task.clone();
                unit.correction.interval_scale = [1.0; 2];
                let make: Make = Box::new(|| Box::new(CorrectionCalibrator::new(&unit, net)));
                rl_task.correction.interval_scale = scale_of("rl_lac", &make, &mut interval_scales);
            }
        }
        progress(&format!(
            "RL-LAC: 90 % interval scales qMobile {:.2}, Ro {:.2} (validation)",
            interval_scales["rl_lac"][0], interval_scales["rl_lac"][1]
        ));
    }
    let unit = TrackerSpec { interval_scale: [1.0; 2], ..spec.tracker.clone() };
    let fit_spec = {
        let make: Make = Box::new(|| Box::new(WindowFitCalibrator::new(&unit)));
        TrackerSpec { interval_scale: scale_of("window_fit", &make, &mut interval_scales), ..spec.tracker.clone() }
    };
    let mut ukf_scale = [1.645; 2];
    let mut adaptive = None;
    if opts.ukf {
        let make: Make = Box::new(|| Box::new(JointUkf::new(base_ukf, &spec.tracker).with_interval_scale([1.0; 2])));
        ukf_scale = scale_of("ukf", &make, &mut interval_scales);
        progress(&format!(
            "adaptive UKF: tuning {} covariance-matching rules on top of the joint UKF on validation",
            opts.adaptive_grid.candidates().len()
        ));
        let t = tune_adaptive(&spec.tracker, base_ukf, &validation, &opts.adaptive_grid);
        progress(&format!(
            "adaptive UKF: chose {:?} (validation mean NRMSE {:.2} %, the filter without the rule {:.2} %)",
            t.best, t.top[0].1, t.without_rule_pct
        ));
        let rule = t.best;
        let make: Make =
            Box::new(move || Box::new(AdaptiveUkf::new(base_ukf, rule, &spec.tracker).with_interval_scale([1.0; 2])));
        let scale = scale_of("adaptive_ukf", &make, &mut interval_scales);
        adaptive = Some((t, scale));
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
        let pairs = direct_pairs(&task, &train, opts.direct.max_pairs, input.seed);
        let val_pairs = direct_pairs(&task, &validation, opts.direct.max_validation_pairs, input.seed + 1);
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
            let make: Make = Box::new(|| Box::new(DirectCalibrator::new(&task, &pure, [1.0; 2])));
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
    // The test conditions: each noise level on the task's cells, then the same cells' other model (the exact
    // model when the task's cells carry model error, else cells that do) at the headline noise.
    let mut conditions: Vec<(f64, ScenarioConfig, bool)> =
        opts.voltage_noise_levels_v.iter().map(|&v| (v, with_voltage_noise(sc, v), false)).collect();
    let mut other = with_voltage_noise(sc, headline_v);
    other.model_error.probability = if sc.model_error.probability > 0.0 { 0.0 } else { OTHER_MODEL_ERROR_PROBABILITY };
    conditions.push((headline_v, other, true));
    let mut other_model = None;
    for (v, cond, is_other) in conditions {
        let test = episodes_of(&cond, Split::Test, n_test, "test")?;
        let mut methods: Vec<(&'static str, Make)> = Vec::new();
        if let Some(net) = &net {
            let t = rl_task.clone();
            match t.design {
                Design::WindowFit => {
                    methods.push(("rl_lac", Box::new(move || Box::new(RlCalibrator::new(&t.tracker, net)))))
                }
                Design::UkfCorrection => {
                    methods.push(("rl_lac", Box::new(move || Box::new(CorrectionCalibrator::new(&t, net)))))
                }
            }
        }
        if opts.ukf {
            let s = spec.tracker.clone();
            methods
                .push(("ukf", Box::new(move || Box::new(JointUkf::new(base_ukf, &s).with_interval_scale(ukf_scale)))));
        }
        if let Some((t, scale)) = &adaptive {
            let (s, rule, k) = (spec.tracker.clone(), t.best, *scale);
            methods.push((
                "adaptive_ukf",
                Box::new(move || Box::new(AdaptiveUkf::new(base_ukf, rule, &s).with_interval_scale(k))),
            ));
        }
        if let Some((pure, _, scale)) = &dm {
            let (t, k) = (task.clone(), *scale);
            methods.push(("direct_mapping", Box::new(move || Box::new(DirectCalibrator::new(&t, pure, k)))));
        }
        {
            let s = fit_spec.clone();
            methods.push(("window_fit", Box::new(move || Box::new(WindowFitCalibrator::new(&s)))));
            let s = spec.tracker.clone();
            methods.push(("uncalibrated", Box::new(move || Box::new(Uncalibrated::new(&s)))));
        }
        let headline = (v - headline_v).abs() < 1e-12 && !is_other;
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
                        let mut f = JointUkf::new(base_ukf, &spec.tracker);
                        for s in &e.samples {
                            f.step(s);
                        }
                        counters.add(&f.counters);
                    }
                }
                headline_traces.push((*key, traces));
            }
            progress(&format!(
                "{:>4.1} mV{} {key}: NRMSE q {:.2} % r {:.2} % (second half {:.2} / {:.2}), coverage {} / {} %{}",
                v * 1e3,
                if is_other { format!(", model error {:.1}", cond.model_error.probability) } else { String::new() },
                m.nrmse_pct.q_mobile.unwrap_or(f64::NAN),
                m.nrmse_pct.r_o.unwrap_or(f64::NAN),
                m.second_half_nrmse_pct.q_mobile.unwrap_or(f64::NAN),
                m.second_half_nrmse_pct.r_o.unwrap_or(f64::NAN),
                m.coverage_90_pct.q_mobile.map_or("-".into(), |x| format!("{x:.1}")),
                m.coverage_90_pct.r_o.map_or("-".into(), |x| format!("{x:.1}")),
                m.step_us.map_or(String::new(), |us| format!(", {us:.2} us/step"))
            ));
            scores.insert(key.to_string(), m);
        }
        if headline {
            test_readings = test.iter().map(|e| e.samples.len()).sum();
            headline_episodes = test;
        }
        let level = NoiseLevel {
            voltage_noise_mv: v * 1e3,
            model_error_probability: cond.model_error.probability,
            methods: scores,
        };
        if is_other {
            other_model = Some(level);
        } else {
            levels.push(level);
        }
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
        other_model,
        test_episodes: n_test,
        test_readings,
        validation_episodes: validation.len(),
        test_loads: serde_json::json!({"power_w": sc.test.power_w, "current_a": sc.test.current_a}),
        sampling_intervals_s: sc.sample_interval_s.clone(),
        rl: rl_info,
        ukf: ukf_tuning,
        ukf_settings: Some(base_ukf),
        adaptive_ukf: adaptive.map(|a| a.0),
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
        e.spec.interval_s = [1.0, 1.0];
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
            eod_oracle_load_s: [None, None, e.eod_s],
        };
        // A second cell of another sampling regime, every estimate 10 % off in qMobile, no interval.
        let mut e2 = e.clone();
        e2.spec.interval_s = [10.0, 20.0];
        let trace2 = Trace {
            estimates: vec![off(300.0); 4],
            intervals: vec![None; 4],
            eod_pred_s: [None; 3],
            eod_oracle_load_s: [None; 3],
        };
        let both = score(&[e.clone(), e2.clone()], &[trace.clone(), trace2]);
        let pooled = ((100.0f64 + 9.0 + 4.0 * 100.0) / 8.0).sqrt();
        let per_cell = 0.5 * (((100.0f64 + 9.0) / 4.0).sqrt() + 10.0);
        assert!((both.nrmse_pct.q_mobile.unwrap() - pooled).abs() < 1e-9);
        assert!((both.all_cells.per_cell_nrmse_pct.q_mobile.unwrap() - per_cell).abs() < 1e-9);
        assert_eq!(both.by_sampling.keys().collect::<Vec<_>>(), ["10-20s", "1s"]);
        assert!((both.by_sampling["10-20s"].nrmse_pct.q_mobile.unwrap() - 10.0).abs() < 1e-9);
        // The second cell has no interval: per-cell coverage is the first cell's alone.
        assert!((both.all_cells.per_cell_coverage_90_pct.q_mobile.unwrap() - 200.0 / 3.0).abs() < 1e-9);
        assert_eq!(both.eod["10"].failures, 1);
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
        assert_eq!((m.eod_oracle_load["10"].failures, m.eod_oracle_load["90"].mae_s), (1, 0.0));
    }
}
