//! The evaluation metrics, computed from each method's per-step estimates on the same test trajectories:
//! the paper's Table-1 normalised RMSE over every step, the error of a per-cycle estimate (the median over
//! the trajectory), the time to come within 2 % of the truth, and the end-of-discharge prediction error of
//! the calibrated model at 10 % and 50 % of the discharge.
//!
//! Every parameter error is in % of its Table-1 range (qMobile 4000..7000 C, Ro 0.1..0.2 ohm). Only the
//! calibrated parameters are reported: a field of [`ParamValues`] is `None` (and absent from JSON) for a
//! parameter the experiment does not calibrate. Pure functions; this module never prints.

use bcal_common::battery::{BatteryModel, Degradation, Load, LoadProfile};
use bcal_common::dataset::Trajectory;
use bcal_common::mdp::{model_state_at, Calibrated};
pub use bcal_common::nrmse::Param;
use bcal_common::stats::{median, quantile as percentile};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Threshold of the convergence time, % of the parameter's range.
pub const CONVERGED_WITHIN_PCT: f64 = 2.0;
/// Fractions of the discharge at which the calibrated model predicts the EOD.
pub const EOD_FRACTIONS: [f64; 2] = [0.1, 0.5];
/// Safety stop of an EOD prediction (steps); a prediction that never reaches EOD counts as a failure.
pub const EOD_MAX_STEPS: usize = 100_000;

/// One method's estimate at every step t = 0 .. len - 2 of one test trajectory.
#[derive(Clone, Debug, PartialEq)]
pub struct TrajEstimates {
    /// Index of the trajectory in the dataset.
    pub index: usize,
    pub load_w: f64,
    pub truth: Degradation,
    pub estimates: Vec<Degradation>,
}

/// A number per calibrated parameter; absent for a parameter the experiment does not calibrate.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ParamValues {
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub q_mobile: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub r_o: Option<f64>,
}

/// Serialises a [`ParamValues`] with both keys, null where there is no value: the measured-only report, which
/// always calibrates both parameters, keeps the same keys whether or not a value exists (`serialize_with`).
pub fn both_keys<S: serde::Serializer>(v: &ParamValues, s: S) -> Result<S::Ok, S::Error> {
    use serde::ser::SerializeStruct;
    let mut m = s.serialize_struct("ParamValues", 2)?;
    m.serialize_field("q_mobile", &v.q_mobile)?;
    m.serialize_field("r_o", &v.r_o)?;
    m.end()
}

impl ParamValues {
    pub fn from_fn(calibrated: Calibrated, mut f: impl FnMut(Param) -> f64) -> Self {
        let (q, r) = match calibrated {
            Calibrated::QMobile => (true, false),
            Calibrated::ROhm => (false, true),
            Calibrated::Both => (true, true),
        };
        Self { q_mobile: q.then(|| f(Param::QMobile)), r_o: r.then(|| f(Param::ROhm)) }
    }

    pub fn get(&self, p: Param) -> Option<f64> {
        match p {
            Param::QMobile => self.q_mobile,
            Param::ROhm => self.r_o,
        }
    }
}

/// The calibrated parameters of an experiment.
pub fn params_of(calibrated: Calibrated) -> &'static [Param] {
    match calibrated {
        Calibrated::QMobile => &[Param::QMobile],
        Calibrated::ROhm => &[Param::ROhm],
        Calibrated::Both => &Param::BOTH,
    }
}

/// Convergence of one parameter over the test trajectories.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ParamConvergence {
    /// Median over trajectories of the first time the estimate is within the threshold, s (the time of the
    /// measurement x_{t+1} that produced it); over the trajectories that get there.
    pub first_within_s_median: Option<f64>,
    pub first_within_s_mean: Option<f64>,
    /// Median time after which the estimate stays within the threshold to the end of the trajectory, s.
    pub settled_s_median: Option<f64>,
    /// Trajectories whose estimate is never within the threshold.
    pub never_within: usize,
    /// Trajectories whose estimate is outside the threshold at the last step.
    pub not_settled: usize,
}

/// Convergence of every calibrated parameter.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Convergence {
    pub within_pct: f64,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub q_mobile: Option<ParamConvergence>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub r_o: Option<ParamConvergence>,
}

/// Accuracy of one method on the test trajectories.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Accuracy {
    /// Table 1: normalised RMSE over every step of every test trajectory, %.
    pub nrmse_pct: ParamValues,
    /// Normalised RMSE of the per-cycle estimate (median of the estimates along each trajectory), %.
    pub cycle_nrmse_pct: ParamValues,
    /// Mean signed error over every step, % of the range (bias).
    pub bias_pct: ParamValues,
    /// 95th percentile of the absolute per-step error, %.
    pub p95_abs_err_pct: ParamValues,
    pub convergence: Convergence,
}

/// The median estimate of a trajectory (per parameter), the method's per-cycle answer.
pub fn cycle_estimate(t: &TrajEstimates) -> Degradation {
    let mut q: Vec<f64> = t.estimates.iter().map(|d| d.q_mobile_c).collect();
    let mut r: Vec<f64> = t.estimates.iter().map(|d| d.r_o_ohm).collect();
    Degradation {
        q_mobile_c: median(&mut q).unwrap_or(t.truth.q_mobile_c),
        r_o_ohm: median(&mut r).unwrap_or(t.truth.r_o_ohm),
    }
}

/// Every accuracy metric of one method; `dt_s` turns steps into seconds.
pub fn accuracy(calibrated: Calibrated, trajs: &[TrajEstimates], dt_s: f64) -> Accuracy {
    let params = params_of(calibrated);
    let mut acc = Accuracy {
        convergence: Convergence { within_pct: CONVERGED_WITHIN_PCT, ..Default::default() },
        ..Default::default()
    };
    for &p in params {
        let (mut sq, mut sum, mut n) = (0.0, 0.0, 0usize);
        let mut abs_all = Vec::new();
        let (mut cycle_sq, mut n_cycles) = (0.0, 0usize);
        let (mut firsts, mut settles) = (Vec::new(), Vec::new());
        let (mut never, mut not_settled) = (0usize, 0usize);
        for t in trajs {
            if t.estimates.is_empty() {
                continue;
            }
            let mut first = None;
            let mut last_outside = None;
            for (k, est) in t.estimates.iter().enumerate() {
                let e = p.err_pct(est, &t.truth);
                sq += e * e;
                sum += e;
                n += 1;
                abs_all.push(e.abs());
                if e.abs() <= CONVERGED_WITHIN_PCT {
                    first.get_or_insert(k);
                } else {
                    last_outside = Some(k);
                }
            }
            match first {
                Some(k) => firsts.push((k + 1) as f64 * dt_s),
                None => never += 1,
            }
            match last_outside {
                None => settles.push(dt_s),
                Some(k) if k + 1 < t.estimates.len() => settles.push((k + 2) as f64 * dt_s),
                Some(_) => not_settled += 1,
            }
            let ce = p.err_pct(&cycle_estimate(t), &t.truth);
            cycle_sq += ce * ce;
            n_cycles += 1;
        }
        let nn = n.max(1) as f64;
        let rmse = (sq / nn).sqrt();
        let set = |pv: &mut ParamValues, v: f64| match p {
            Param::QMobile => pv.q_mobile = Some(v),
            Param::ROhm => pv.r_o = Some(v),
        };
        set(&mut acc.nrmse_pct, rmse);
        set(&mut acc.cycle_nrmse_pct, (cycle_sq / n_cycles.max(1) as f64).sqrt());
        set(&mut acc.bias_pct, sum / nn);
        set(&mut acc.p95_abs_err_pct, percentile(&mut abs_all, 0.95).unwrap_or(0.0));
        let mean = (!firsts.is_empty()).then(|| firsts.iter().sum::<f64>() / firsts.len() as f64);
        let conv = ParamConvergence {
            first_within_s_median: median(&mut firsts),
            first_within_s_mean: mean,
            settled_s_median: median(&mut settles),
            never_within: never,
            not_settled,
        };
        match p {
            Param::QMobile => acc.convergence.q_mobile = Some(conv),
            Param::ROhm => acc.convergence.r_o = Some(conv),
        }
    }
    acc
}

/// EOD prediction error at one fraction of the discharge, over the test trajectories.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EodError {
    /// Fraction of the (true) discharge at which the estimate is taken.
    pub at_fraction: f64,
    /// Mean absolute error of the predicted EOD time, s.
    pub mae_s: f64,
    pub rmse_s: f64,
    /// Mean signed error (predicted - true), s.
    pub bias_s: f64,
    /// Mean absolute error in % of the true EOD time.
    pub mae_pct: f64,
    pub max_abs_s: f64,
    /// Trajectories evaluated (failures excluded from the errors above).
    pub n: usize,
    /// Predictions that failed (model error or no EOD within the step limit).
    pub failures: usize,
}

/// EOD errors at 10 % and 50 % of the discharge.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EodMetrics {
    pub at_10pct: EodError,
    pub at_50pct: EodError,
}

/// Step at which a fraction of the discharge has elapsed (an index into the estimates).
pub fn eod_step(traj_len: usize, fraction: f64) -> usize {
    let last = traj_len.saturating_sub(2);
    ((fraction * (traj_len.saturating_sub(1)) as f64).round() as usize).min(last)
}

/// Predicted EOD time, s: from the measured state at `step`, the model under `d` runs to VEOD at the
/// trajectory's load; `None` when the prediction fails.
pub fn predict_eod_s(model: &BatteryModel, traj: &Trajectory, step: usize, d: &Degradation, dt_s: f64) -> Option<f64> {
    let x0 = model_state_at(model, traj, step);
    let out = model
        .simulate_until_eod(&x0, d, &LoadProfile::Constant(Load::PowerW(traj.load_w)), dt_s, EOD_MAX_STEPS, |_| {})
        .ok()?;
    out.eod_s.map(|s| s + step as f64 * dt_s)
}

/// EOD errors with the parameters `pick(trajectory k, step)` (a method's estimate at that step, or a fixed
/// reference such as the truth or the new cell), on all cores. `trajs[k]` is the trajectory of `est[k]`.
pub fn eod_metrics(
    model: &BatteryModel,
    trajs: &[&Trajectory],
    dt_s: f64,
    pick: impl Fn(usize, usize) -> Degradation + Sync,
) -> EodMetrics {
    let one = |fraction: f64| -> EodError {
        let errs: Vec<Option<(f64, f64)>> = trajs
            .par_iter()
            .enumerate()
            .map(|(k, traj)| {
                let step = eod_step(traj.len(), fraction);
                let truth = traj.eod_s(dt_s);
                predict_eod_s(model, traj, step, &pick(k, step), dt_s).map(|p| (p - truth, truth))
            })
            .collect();
        let ok: Vec<(f64, f64)> = errs.iter().flatten().copied().collect();
        let n = ok.len().max(1) as f64;
        EodError {
            at_fraction: fraction,
            mae_s: ok.iter().map(|(e, _)| e.abs()).sum::<f64>() / n,
            rmse_s: (ok.iter().map(|(e, _)| e * e).sum::<f64>() / n).sqrt(),
            bias_s: ok.iter().map(|(e, _)| e).sum::<f64>() / n,
            mae_pct: 100.0 * ok.iter().map(|(e, t)| e.abs() / t).sum::<f64>() / n,
            max_abs_s: ok.iter().map(|(e, _)| e.abs()).fold(0.0, f64::max),
            n: ok.len(),
            failures: errs.len() - ok.len(),
        }
    };
    EodMetrics { at_10pct: one(EOD_FRACTIONS[0]), at_50pct: one(EOD_FRACTIONS[1]) }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn traj(truth: Degradation, est: Vec<Degradation>) -> TrajEstimates {
        TrajEstimates { index: 0, load_w: 12.0, truth, estimates: est }
    }

    /// Hand-made estimates with errors we can compute on paper.
    #[test]
    fn metrics_on_hand_made_estimates() {
        let truth = Degradation { q_mobile_c: 5000.0, r_o_ohm: 0.15 };
        let d = |q: f64, r: f64| Degradation { q_mobile_c: q, r_o_ohm: r };
        // Trajectory A: qMobile errors of +300 C (10 %), +30 C (1 %), 0, 0; Ro errors 0.01 (10 %) then exact.
        let a = traj(truth, vec![d(5300.0, 0.16), d(5030.0, 0.15), d(5000.0, 0.15), d(5000.0, 0.15)]);
        // Trajectory B: qMobile constantly -150 C (-5 %): never within 2 %; Ro exact.
        let b = traj(truth, vec![d(4850.0, 0.15); 4]);
        let acc = accuracy(Calibrated::Both, &[a.clone(), b], 1.0);
        // Per step: q errors^2 = 100, 1, 0, 0, 25 x 4 -> mean 201 / 8.
        assert!((acc.nrmse_pct.q_mobile.unwrap() - (201.0f64 / 8.0).sqrt()).abs() < 1e-9);
        // Ro: one 10 % error in 8 steps.
        assert!((acc.nrmse_pct.r_o.unwrap() - (100.0f64 / 8.0).sqrt()).abs() < 1e-9);
        // Cycle medians: A's q values 5300, 5030, 5000, 5000 -> (5000 + 5030) / 2 = 5015 (0.5 %),
        // B's = 4850 (-5 %): RMSE sqrt((0.25 + 25) / 2).
        assert!((acc.cycle_nrmse_pct.q_mobile.unwrap() - 12.625f64.sqrt()).abs() < 1e-9);
        assert!((acc.bias_pct.q_mobile.unwrap() - (10.0 + 1.0 - 20.0) / 8.0).abs() < 1e-9);
        let cq = acc.convergence.q_mobile.unwrap();
        // A is within 2 % first at step 1 (the measurement of t = 2 s) and stays; B never.
        assert_eq!(cq.first_within_s_median, Some(2.0));
        assert_eq!(cq.settled_s_median, Some(2.0));
        assert_eq!(cq.never_within, 1);
        assert_eq!(cq.not_settled, 1);
        let cr = acc.convergence.r_o.unwrap();
        assert_eq!(cr.first_within_s_median, Some(1.5)); // A at 2 s, B at 1 s
        assert_eq!(cr.never_within, 0);

        // Single-parameter experiments report only their parameter, and JSON omits the other.
        let only_q = accuracy(Calibrated::QMobile, &[a], 1.0);
        assert!(only_q.nrmse_pct.r_o.is_none());
        let json = serde_json::to_value(&only_q).unwrap();
        assert!(json["nrmse_pct"].get("r_o").is_none() && json["nrmse_pct"]["q_mobile"].is_number());
    }

    #[test]
    fn eod_with_true_parameters_is_exact_and_a_wrong_capacity_is_not() {
        let model = BatteryModel::default();
        let truth = Degradation { q_mobile_c: 5000.0, r_o_ohm: 0.12 };
        let t = bcal_common::dataset::simulate_trajectory(&model, &truth, 14.0, 1.0, 100_000).unwrap();
        let exact = eod_metrics(&model, &[&t], 1.0, |_, _| truth);
        // Only the f32 storage of the measured state separates the prediction from the truth.
        assert!(exact.at_10pct.mae_s <= 2.0 && exact.at_50pct.mae_s <= 2.0, "{exact:?}");
        assert_eq!(exact.at_10pct.failures, 0);
        let wrong = eod_metrics(&model, &[&t], 1.0, |_, _| Degradation { q_mobile_c: 6000.0, ..truth });
        assert!(wrong.at_10pct.mae_s > 20.0 * exact.at_10pct.mae_s.max(1.0), "{wrong:?}");
        assert!(wrong.at_10pct.bias_s > 0.0, "more capacity must predict a later EOD");
        assert_eq!(eod_step(101, 0.5), 50);
        assert_eq!(eod_step(3, 0.9), 1);
    }
}
