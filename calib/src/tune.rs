//! Choices made on validation cells, never on test: the joint UKF's noise settings (a grid search), and
//! the 90 % interval scale of a calibrator (the factor that makes its interval cover 90 % of validation
//! readings). The evaluator, `bcal calibrate` on real cells and the RL pipeline all choose here.

use crate::adaptive::{AdaptiveRule, AdaptiveUkf};
use crate::joint_ukf::{JointUkf, JointUkfCounters, JointUkfSettings};
use crate::Calibrator;
use bcal_common::battery::Degradation;
use bcal_common::measured::scenario::Episode;
use bcal_common::measured::tracker::TrackerSpec;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

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

/// A calibrator that needs building per episode.
pub type Make<'a> = Box<dyn Fn() -> Box<dyn Calibrator + 'a> + Sync + 'a>;

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

/// Every grid setting of the joint UKF on `validation` cells, the best by the mean of the two NRMSEs over
/// every reading (validation only: the test cells never choose anything).
pub fn tune_joint_ukf(spec: &TrackerSpec, validation: &[Episode], grid: &JointUkfGrid) -> UkfTuning {
    let cands = grid.candidates();
    let mut rows: Vec<(JointUkfSettings, f64)> = cands
        .iter()
        .map(|s| {
            let s = *s;
            let make: Make = Box::new(move || Box::new(JointUkf::new(s, spec)));
            (s, mean_nrmse_pct(validation, &make))
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

/// Mean of the two Table-1 NRMSEs over every reading of `episodes`, % (infinite when not finite): the score
/// every filter setting is chosen by.
pub fn mean_nrmse_pct(episodes: &[Episode], make: &Make) -> f64 {
    let accs: Vec<bcal_common::nrmse::NrmseAccumulator> = episodes
        .par_iter()
        .map(|e| {
            let mut acc = bcal_common::nrmse::NrmseAccumulator::default();
            let mut c = make();
            for r in &e.samples {
                c.step(r);
                acc.add(&c.estimate(), &e.spec.truth);
            }
            acc
        })
        .collect();
    let mut acc = bcal_common::nrmse::NrmseAccumulator::default();
    for a in &accs {
        acc.merge(a);
    }
    let (q, r) = acc.pct();
    let m = 0.5 * (q + r);
    if m.is_finite() {
        m
    } else {
        f64::INFINITY
    }
}

/// The adaptive rule's search space, on top of the tuned filter.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdaptiveGrid {
    pub window_readings: Vec<f64>,
    /// Largest parameter walk variance, z^2/s; 0 leaves the walk as tuned (the rule adapts R alone).
    pub walk_max_var_per_s: Vec<f64>,
}

impl Default for AdaptiveGrid {
    fn default() -> Self {
        Self { window_readings: vec![16.0, 64.0, 256.0], walk_max_var_per_s: vec![0.0, 1e-8, 1e-6] }
    }
}

impl AdaptiveGrid {
    pub fn quick() -> Self {
        Self { window_readings: vec![64.0], walk_max_var_per_s: vec![0.0, 1e-6] }
    }

    pub fn candidates(&self) -> Vec<AdaptiveRule> {
        let mut v = Vec::new();
        for &window_readings in &self.window_readings {
            for &w in &self.walk_max_var_per_s {
                v.push(AdaptiveRule {
                    window_readings,
                    adapt_walk: w > 0.0,
                    walk_max_var_per_s: w,
                    ..AdaptiveRule::default()
                });
            }
        }
        v
    }
}

/// The adaptive rule's tuning on validation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdaptiveTuning {
    pub base: JointUkfSettings,
    pub best: AdaptiveRule,
    /// Mean of the two NRMSEs on validation, %, of each rule tried (best first), and of the filter without
    /// the rule.
    pub top: Vec<(AdaptiveRule, f64)>,
    pub without_rule_pct: f64,
    pub validation_episodes: usize,
}

/// Every rule of `grid` on top of the tuned filter `base`, on `validation` cells, the best by the mean of the
/// two NRMSEs over every reading (the filter's own criterion).
pub fn tune_adaptive(
    spec: &TrackerSpec,
    base: JointUkfSettings,
    validation: &[Episode],
    grid: &AdaptiveGrid,
) -> AdaptiveTuning {
    let mut rows: Vec<(AdaptiveRule, f64)> = grid
        .candidates()
        .into_iter()
        .map(|rule| {
            let make: Make = Box::new(move || Box::new(AdaptiveUkf::new(base, rule, spec)));
            (rule, mean_nrmse_pct(validation, &make))
        })
        .collect();
    rows.sort_by(|a, b| a.1.total_cmp(&b.1));
    let plain: Make = Box::new(move || Box::new(JointUkf::new(base, spec)));
    AdaptiveTuning {
        base,
        best: rows[0].0,
        without_rule_pct: mean_nrmse_pct(validation, &plain),
        top: rows,
        validation_episodes: validation.len(),
    }
}

/// Share of the validation cycles on which a learned calibrator must beat the joint UKF chosen there to be
/// delivered (`bcal_realcell::tune::first_consistent`; a live stream's prior holds a share of a discharge by the same rule, `crate::stream`): 8 of 10 (were the two equally good, that would happen 5 times in 100).
pub const MIN_WIN_SHARE: f64 = 0.75;

/// The wins of [`MIN_WIN_SHARE`] of `n` validation cycles.
pub fn wins_needed(n: usize) -> usize {
    (MIN_WIN_SHARE * n as f64).ceil() as usize
}

/// Whether a learned calibrator whose per-discharge objective (`bcal_realcell::tune::objective`) was `mine` earns its place against the
/// filter's `theirs` on the same discharges: it beats it in the mean and on at least [`MIN_WIN_SHARE`] of
/// them (a tie is not a win). Nothing to judge on: no.
pub fn earns(mine: &[f64], theirs: &[f64]) -> bool {
    let n = theirs.len();
    if n == 0 || mine.len() != n {
        return false;
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    mean(mine) < mean(theirs) && mine.iter().zip(theirs).filter(|(a, b)| a < b).count() >= wins_needed(n)
}
