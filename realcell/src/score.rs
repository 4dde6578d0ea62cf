//! Scores against what the cycler measured, on held-out discharges:
//! - capacity: the calibrated model's capacity at the discharge's current down to the cut-off, predicted
//!   from the data up to 25 / 50 / 100 % of each discharge, against the capacity the metadata states and
//!   against the charge the data itself shows down to the same voltage (RMSE and MAE, Ah and %);
//! - end of discharge: the predicted time the voltage reaches the cut-off, made at 10 / 50 / 90 % of each
//!   discharge, against the measured time (median and 90th percentile of the absolute error, s and % of
//!   the discharge's duration);
//! - coverage: how often the 90 % intervals of those predictions hold the measured value (the end of
//!   discharge measured by the cycler, and the capacity the data itself shows down to the cut-off);
//! - the same per condition (each discharge's current and ambient temperature, rounded) when the judged
//!   discharges ran under more than one, and the capacity errors at the discharges that follow a rest of more
//!   than a day (where the cell has regained capacity);
//! - the same on the first, middle and last third of the judged discharges in order: an interval is only as
//!   good as its coverage late in a cell's life, where the training discharges are furthest behind.

use crate::record::CellRecord;
use crate::run::CycleRun;
use serde::Serialize;
use std::collections::BTreeMap;

/// Fractions of each discharge from which capacity is predicted, %.
pub const CAPACITY_FRACTIONS_PCT: [u32; 3] = [25, 50, 100];
pub use bcal_calib::widening::{share_bin, EOD_FRACTIONS_PCT};

/// Error statistics of one prediction against one measurement kind.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Errors {
    pub n: usize,
    pub rmse: f64,
    pub mae: f64,
    /// RMSE and MAE relative to the measured value, %.
    pub rmse_pct: f64,
    pub mae_pct: f64,
    pub bias: f64,
}

fn errors(pairs: &[(f64, f64)]) -> Errors {
    let n = pairs.len();
    if n == 0 {
        return Errors::default();
    }
    let nf = n as f64;
    let e: Vec<f64> = pairs.iter().map(|(p, m)| p - m).collect();
    let rel: Vec<f64> = pairs.iter().map(|(p, m)| 100.0 * (p - m) / m).collect();
    Errors {
        n,
        rmse: (e.iter().map(|x| x * x).sum::<f64>() / nf).sqrt(),
        mae: e.iter().map(|x| x.abs()).sum::<f64>() / nf,
        rmse_pct: (rel.iter().map(|x| x * x).sum::<f64>() / nf).sqrt(),
        mae_pct: rel.iter().map(|x| x.abs()).sum::<f64>() / nf,
        bias: e.iter().sum::<f64>() / nf,
    }
}

/// Median and 90th percentile of absolute errors.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Quantiles {
    pub n: usize,
    pub median: f64,
    pub p90: f64,
    pub mean: f64,
}

fn quantiles(mut v: Vec<f64>) -> Quantiles {
    if v.is_empty() {
        return Quantiles::default();
    }
    let (n, mean) = (v.len(), v.iter().sum::<f64>() / v.len() as f64);
    let mut q = |f: f64| bcal_common::stats::quantile(&mut v, f).unwrap_or(f64::NAN);
    Quantiles { n, median: q(0.5), p90: q(0.9), mean }
}

/// Signed end-of-discharge errors, % of the duration: a steady sign is a bias the method's own record shows
/// ([`crate::recentre`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Signed {
    pub n: usize,
    /// Median of predicted - measured, %.
    pub median: f64,
    /// Predictions that came late (after the measured end).
    pub late: usize,
}

fn signed(mut v: Vec<f64>) -> Signed {
    let late = v.iter().filter(|x| **x > 0.0).count();
    Signed { n: v.len(), median: bcal_common::stats::median(&mut v).unwrap_or(f64::NAN), late }
}

/// One method's scores.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct MethodScore {
    /// Against the metadata's stated capacity, by fraction seen ("25", "50", "100").
    pub capacity: BTreeMap<String, Errors>,
    /// Against the charge the data shows down to the cut-off.
    pub capacity_vs_data: BTreeMap<String, Errors>,
    /// |predicted - measured end of discharge|, s, by fraction ("10", "50", "90").
    pub eod_error_s: BTreeMap<String, Quantiles>,
    /// The same in % of each discharge's duration (load-on to cut-off).
    pub eod_error_pct: BTreeMap<String, Quantiles>,
    /// Their sign: how the predicted ends lie against the measured ones, by fraction.
    pub eod_signed_pct: BTreeMap<String, Signed>,
    /// Predictions whose 90 % interval holds the measurement, % (None without intervals).
    pub coverage_90_pct: BTreeMap<String, Option<f64>>,
    /// Predictions that failed (the model never reached the cut-off within the horizon).
    pub failures: usize,
    /// Capacity errors from half of each discharge that follows a rest of more than a day (against the
    /// stated capacity and against the data's charge); None without such a discharge.
    pub after_long_rest: Option<AfterRest>,
    /// The same scores per condition (`"2.0 A, 24 C"`), when the judged discharges ran under more than one.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub by_condition: BTreeMap<String, MethodScore>,
    /// The same scores on the first, middle and last third of the judged discharges in order ([`life_thirds`]:
    /// `"1: cycles 41-82"`, `"2: ..."`, `"3: ..."`), when there are at least [`MIN_BY_LIFE`].
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub by_life: BTreeMap<String, MethodScore>,
}

/// Judged discharges needed to score the thirds of a life apart ([`MethodScore::by_life`]): three each.
pub const MIN_BY_LIFE: usize = 9;

/// The first, middle and last third of `records` (in order; the last takes what does not divide), each keyed
/// by its place and cycles (`"1: cycles 41-82"`); none with fewer than [`MIN_BY_LIFE`].
pub fn life_thirds(records: &[CellRecord]) -> Vec<(String, std::ops::Range<usize>)> {
    let n = records.len();
    if n < MIN_BY_LIFE {
        return Vec::new();
    }
    let third = n / 3;
    [0..third, third..2 * third, 2 * third..n]
        .into_iter()
        .enumerate()
        .map(|(k, r)| (format!("{}: cycles {}-{}", k + 1, records[r.start].cycle, records[r.end - 1].cycle), r))
        .collect()
}

/// Capacity from half of the discharges that follow a long rest.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct AfterRest {
    pub cycles: Vec<u32>,
    pub capacity_50: Errors,
    pub capacity_50_vs_data: Errors,
}

/// The condition a discharge ran under, as the reports group them: its mean current to the nearest
/// quarter ampere and its ambient to the nearest degree.
pub fn condition_key(r: &CellRecord) -> String {
    format!(
        "{:.2} A, {:.0} C",
        (r.current_a * 4.0).round() / 4.0,
        r.ambient_k - bcal_common::measured::scenario::KELVIN_0C
    )
}

/// Scores one method's runs (`runs[k]` along `records[k]`), per condition too when there are several.
pub fn score(records: &[CellRecord], runs: &[CycleRun]) -> MethodScore {
    let mut s = score_flat(records, runs);
    let mut groups: BTreeMap<String, Vec<usize>> = BTreeMap::new();
    for (k, r) in records.iter().enumerate() {
        groups.entry(condition_key(r)).or_default().push(k);
    }
    if groups.len() > 1 {
        for (key, idx) in groups {
            let rs: Vec<CellRecord> = idx.iter().map(|&k| records[k].clone()).collect();
            let us: Vec<CycleRun> = idx.iter().map(|&k| runs[k].clone()).collect();
            s.by_condition.insert(key, score_flat(&rs, &us));
        }
    }
    for (key, part) in life_thirds(records) {
        s.by_life.insert(key, score_flat(&records[part.clone()], &runs[part]));
    }
    s
}

fn score_flat(records: &[CellRecord], runs: &[CycleRun]) -> MethodScore {
    let mut s = MethodScore::default();
    let mut after = AfterRest::default();
    let (mut after_stated, mut after_data) = (Vec::new(), Vec::new());
    let (mut eod_in, mut eod_n, mut cap_in, mut cap_n) = (0usize, 0usize, 0usize, 0usize);
    for f in CAPACITY_FRACTIONS_PCT {
        let (mut stated, mut data) = (Vec::new(), Vec::new());
        // A discharge from a partial charge delivers less than the cell holds: no capacity to score it on.
        for (r, run) in records.iter().zip(runs).filter(|(r, _)| !r.partial_start) {
            let Some(k) = r.reading_at_fraction(f64::from(f) / 100.0) else { continue };
            let p = run.steps[k.min(run.steps.len() - 1)].capacity;
            let Some(v) = p.value else {
                s.failures += 1;
                continue;
            };
            let long_rest = f == 50 && r.after_long_rest();
            if long_rest {
                after.cycles.push(r.cycle);
            }
            if let Some(m) = r.stated_capacity_ah.filter(|c| *c > 0.0) {
                // The capacity to the voltage the source states it to, where that is not the cut-off.
                let to_stated = v - r.stated_tail_ah.unwrap_or(0.0);
                stated.push((to_stated, m));
                if long_rest {
                    after_stated.push((to_stated, m));
                }
            }
            if let Some(m) = r.data_capacity_ah {
                data.push((v, m));
                if long_rest {
                    after_data.push((v, m));
                }
                if let (Some(lo), Some(hi)) = (p.lo, p.hi) {
                    cap_n += 1;
                    cap_in += usize::from(lo <= m && m <= hi);
                }
            }
        }
        s.capacity.insert(f.to_string(), errors(&stated));
        s.capacity_vs_data.insert(f.to_string(), errors(&data));
    }
    for f in EOD_FRACTIONS_PCT {
        let (mut abs_s, mut abs_pct, mut signed_pct) = (Vec::new(), Vec::new(), Vec::new());
        for (r, run) in records.iter().zip(runs) {
            let (Some(eod), Some(dur), Some(k)) =
                (r.eod_s, r.discharge_s(), r.reading_at_fraction(f64::from(f) / 100.0))
            else {
                continue;
            };
            let p = run.steps[k.min(run.steps.len() - 1)].eod;
            let Some(v) = p.value else {
                s.failures += 1;
                continue;
            };
            abs_s.push((v - eod).abs());
            abs_pct.push(100.0 * (v - eod).abs() / dur.max(1.0));
            signed_pct.push(100.0 * (v - eod) / dur.max(1.0));
            if let (Some(lo), Some(hi)) = (p.lo, p.hi) {
                eod_n += 1;
                eod_in += usize::from(lo <= eod && eod <= hi);
            }
        }
        s.eod_error_s.insert(f.to_string(), quantiles(abs_s));
        s.eod_error_pct.insert(f.to_string(), quantiles(abs_pct));
        s.eod_signed_pct.insert(f.to_string(), signed(signed_pct));
    }
    let pct = |a: usize, n: usize| (n > 0).then(|| 100.0 * a as f64 / n as f64);
    s.coverage_90_pct.insert("eod".into(), pct(eod_in, eod_n));
    s.coverage_90_pct.insert("capacity".into(), pct(cap_in, cap_n));
    if !after.cycles.is_empty() {
        after.capacity_50 = errors(&after_stated);
        after.capacity_50_vs_data = errors(&after_data);
        s.after_long_rest = Some(after);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::predict::Predicted;
    use crate::run::Step;
    use bcal_common::battery::Degradation;
    use bcal_common::measured::scenario::{Request, Sample};

    #[test]
    fn scores_a_hand_made_run() {
        let samples: Vec<Sample> = (0..11)
            .map(|k| Sample {
                t_s: 100.0 * k as f64,
                voltage_v: 4.0,
                current_a: 2.0,
                temperature_k: 298.0,
                request: Request::Unknown,
            })
            .collect();
        let r = CellRecord {
            cell: "T".into(),
            cycle: 1,
            source: "t".into(),
            samples,
            load_on_s: 0.0,
            eod_s: Some(1000.0),
            current_a: 2.0,
            data_capacity_ah: Some(1.0),
            stated_capacity_ah: Some(1.1),
            ambient_k: 298.0,
            rest_before_s: Some(2.0 * 86_400.0),
            current_before_a: None,
            partial_start: false,
            short_start_seen: false,
            partial_start_seen: false,
            start_share_sd: None,
            stated_tail_ah: None,
        };
        // Predicts an end 50 s late with an interval of +-100 s and a capacity of 1.2 Ah within [1.1, 1.3].
        let s_run = |r: &CellRecord| CycleRun {
            cycle: r.cycle,
            steps: r
                .samples
                .iter()
                .map(|s| Step {
                    t_s: s.t_s,
                    estimate: Degradation::default(),
                    interval: None,
                    eod: Predicted { value: Some(1050.0), lo: Some(950.0), hi: Some(1150.0) },
                    eod_warmth_s: 0.0,
                    capacity: Predicted { value: Some(1.2), lo: Some(1.1), hi: Some(1.3) },
                })
                .collect(),
        };
        let s = score(std::slice::from_ref(&r), &[s_run(&r)]);
        assert!((s.capacity["50"].rmse - 0.1).abs() < 1e-12);
        assert!((s.capacity_vs_data["50"].mae - 0.2).abs() < 1e-12);
        assert!((s.capacity_vs_data["50"].rmse_pct - 20.0).abs() < 1e-9);
        assert_eq!(s.eod_error_s["90"].median, 50.0);
        assert!((s.eod_error_pct["10"].p90 - 5.0).abs() < 1e-12);
        // Late, not early: the sign is kept.
        assert_eq!((s.eod_signed_pct["50"].n, s.eod_signed_pct["50"].late), (1, 1));
        assert!((s.eod_signed_pct["50"].median - 5.0).abs() < 1e-12);
        assert_eq!(s.coverage_90_pct["eod"], Some(100.0));
        // 1.0 Ah measured lies outside [1.1, 1.3].
        assert_eq!(s.coverage_90_pct["capacity"], Some(0.0));
        // It followed two days of rest: its capacity error is also counted there.
        let after = s.after_long_rest.as_ref().unwrap();
        assert_eq!(after.cycles, vec![1]);
        assert!((after.capacity_50_vs_data.rmse - 0.2).abs() < 1e-12);
        // One condition: no breakdown; two: one entry each.
        assert!(s.by_condition.is_empty());
        let mut r2 = r.clone();
        r2.current_a = 4.0;
        let run = s_run(&r);
        let two = score(&[r.clone(), r2], &[run.clone(), run]);
        assert_eq!(two.by_condition.keys().cloned().collect::<Vec<_>>(), vec!["2.00 A, 25 C", "4.00 A, 25 C"]);
        assert_eq!(two.by_condition["4.00 A, 25 C"].capacity["50"].n, 1);
        // Fewer than nine judged discharges: no thirds of the life; nine: 3 each; ten: 3, 3 and 4, keyed by their
        // cycles.
        assert!(two.by_life.is_empty());
        let thirds = |n: u32| {
            let rs: Vec<CellRecord> = (1..=n).map(|c| CellRecord { cycle: c, ..r.clone() }).collect();
            life_thirds(&rs).into_iter().map(|(_, part)| part.len()).collect::<Vec<_>>()
        };
        assert_eq!((thirds(8), thirds(9)), (vec![], vec![3, 3, 3]));
        let ten: Vec<CellRecord> = (1..=10).map(|c| CellRecord { cycle: c, ..r.clone() }).collect();
        let runs: Vec<CycleRun> = ten.iter().map(s_run).collect();
        let life = score(&ten, &runs).by_life;
        let keys: Vec<&str> = life.keys().map(String::as_str).collect();
        assert_eq!(keys, ["1: cycles 1-3", "2: cycles 4-6", "3: cycles 7-10"]);
        assert_eq!(life["3: cycles 7-10"].eod_error_pct["50"].n, 4);
        assert_eq!(life["1: cycles 1-3"].coverage_90_pct["eod"], Some(100.0));
        // A discharge from a partial charge: its end is scored, its capacity is not.
        let partial = CellRecord { cycle: 2, partial_start: true, ..r.clone() };
        let both = score(&[r.clone(), partial.clone()], &[s_run(&r), s_run(&partial)]);
        assert_eq!((both.capacity["50"].n, both.capacity_vs_data["50"].n), (1, 1));
        assert_eq!(both.eod_error_pct["50"].n, 2);
        assert_eq!(both.after_long_rest.as_ref().unwrap().cycles, vec![1]);
        // Stated to a voltage above the cut-off: against the stated capacity the prediction counts less the
        // tail below that voltage (1.2 - 0.15 Ah against 1.1 Ah stated), against the data's charge as it is.
        let tailed = CellRecord { stated_tail_ah: Some(0.15), ..r.clone() };
        let s = score(std::slice::from_ref(&tailed), &[s_run(&tailed)]);
        assert!((s.capacity["50"].rmse - 0.05).abs() < 1e-12 && s.capacity["50"].bias < 0.0);
        assert!((s.capacity_vs_data["50"].rmse - 0.2).abs() < 1e-12);
        let after = s.after_long_rest.unwrap();
        assert!((after.capacity_50.rmse - 0.05).abs() < 1e-12 && (after.capacity_50_vs_data.rmse - 0.2).abs() < 1e-12);
    }
}
