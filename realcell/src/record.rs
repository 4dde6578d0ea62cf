//! One measured discharge as a calibrator meets it: readings in time order from the start of the record
//! (the rest before the load) to the cut-off reading, and what the cycler measured about it (when the load
//! came on, when the voltage reached the cut-off, the charge drawn until then, the capacity its metadata
//! states). Everything after the cut-off (the relaxation) is left out: a calibrator predicts the end of
//! discharge before it happens.

use bcal_calib::eod::charge_to_ah;
use bcal_common::measured::scenario::{Request, Sample};
use bcal_doctor::Discharge;
use serde::Serialize;
use std::path::PathBuf;

/// A reading counts as under load above this current, A.
pub const LOAD_THRESHOLD_A: f64 = 0.05;

/// A discharge prepared for real-time calibration.
#[derive(Clone, Debug)]
pub struct CellRecord {
    pub cell: String,
    pub cycle: u32,
    pub source: PathBuf,
    /// Readings from the record's start to the cut-off reading (inclusive).
    pub samples: Vec<Sample>,
    /// Time of the first reading under load, s.
    pub load_on_s: f64,
    /// When the voltage reached the cut-off under load, s (interpolated between the readings around the
    /// crossing); `None` when the record never reaches it (cut short).
    pub eod_s: Option<f64>,
    /// Mean current under load, A (the test current of capacity predictions).
    pub current_a: f64,
    /// Charge drawn from the load-on to the cut-off, Ah (the capacity the data itself shows).
    pub data_capacity_ah: Option<f64>,
    /// Capacity the source states (NASA metadata), Ah.
    pub stated_capacity_ah: Option<f64>,
    /// Ambient temperature, K.
    pub ambient_k: f64,
    /// The rest before the discharge (from the end of the record before it), s; None when unknown.
    pub rest_before_s: Option<f64>,
    /// Whether it started from a partial charge, as its neighbours' rest voltages show (records after it
    /// among them: for the scores only). The charge it delivered is not the cell's capacity, so its
    /// capacity is not scored; its end of discharge is.
    pub partial_start: bool,
}

impl CellRecord {
    /// Duration of the discharge from the load-on to the cut-off, s.
    pub fn discharge_s(&self) -> Option<f64> {
        self.eod_s.map(|e| e - self.load_on_s)
    }

    /// Whether the discharge follows a rest of more than a day ([`crate::prior::LONG_REST_S`]), after which a
    /// NASA cell has regained capacity.
    pub fn after_long_rest(&self) -> bool {
        self.rest_before_s.is_some_and(|s| s > crate::prior::LONG_REST_S)
    }

    /// Index of the first reading at or after `fraction` of the discharge (by time from the load-on).
    pub fn reading_at_fraction(&self, fraction: f64) -> Option<usize> {
        let t = self.load_on_s + fraction * self.discharge_s()?;
        self.samples.iter().position(|s| s.t_s >= t - 1e-9)
    }
}

/// Why a discharge cannot be calibrated; each names the record and what to do.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RecordError {
    #[error("{file}: cycle {cycle} holds no reading under load (above {LOAD_THRESHOLD_A} A): not a discharge; select discharge records or check the current's sign (--current-sign)")]
    NoDischarge { file: String, cycle: u32 },
    #[error("{file}: cycle {cycle}: the cut-off {cutoff_v} V lies above the first voltage under load ({first_v:.3} V); pass the cell's real cut-off with --cutoff-v")]
    CutoffAboveStart { file: String, cycle: u32, cutoff_v: f64, first_v: f64 },
}

/// Prepares a discharge: readings up to the cut-off, the load-on, the measured end of discharge.
pub fn prepare(d: &Discharge, cutoff_v: f64) -> Result<CellRecord, RecordError> {
    let file = d.source.display().to_string();
    let on = d
        .current_a
        .iter()
        .position(|i| *i > LOAD_THRESHOLD_A)
        .ok_or_else(|| RecordError::NoDischarge { file: file.clone(), cycle: d.cycle })?;
    if d.voltage_v[on] <= cutoff_v {
        return Err(RecordError::CutoffAboveStart { file, cycle: d.cycle, cutoff_v, first_v: d.voltage_v[on] });
    }
    // The cut-off: the first reading under load at or below it. A record that stops under load above it
    // is cut short: calibrated, but no end of discharge to score.
    let cut = (on..d.len()).find(|&k| d.current_a[k] > LOAD_THRESHOLD_A && d.voltage_v[k] <= cutoff_v);
    let last = cut.unwrap_or_else(|| (on..d.len()).rev().find(|&k| d.current_a[k] > LOAD_THRESHOLD_A).unwrap_or(on));
    let eod_s = cut.map(|k| {
        // Linear between the reading before and the one at the cut-off.
        let (v0, v1, t0, t1) = (d.voltage_v[k - 1], d.voltage_v[k], d.time_s[k - 1], d.time_s[k]);
        if k > on && v0 > v1 {
            t0 + (t1 - t0) * ((v0 - cutoff_v) / (v0 - v1)).clamp(0.0, 1.0)
        } else {
            t1
        }
    });
    let samples: Vec<Sample> = (0..=last)
        .map(|k| Sample {
            t_s: d.time_s[k],
            voltage_v: d.voltage_v[k],
            current_a: d.current_a[k],
            temperature_k: d.temperature_at_k(k),
            request: Request::Unknown,
        })
        .collect();
    // The discharge's current as its predictions assume it at its end (`bcal_calib::LoadMean`): the mean of
    // its loaded readings, or over time where the load alternates.
    let mut load = bcal_calib::LoadMean::default();
    for s in &samples {
        load.push(s.t_s, s.current_a);
    }
    let current_a = load.current_a().unwrap_or(0.0);
    // The charge drawn up to the interpolated cut-off, not to the first reading below it (which can lie a
    // sample interval, 10-20 s on a NASA cycler, past it).
    let data_capacity_ah = cut.zip(eod_s).map(|(k, eod)| charge_to_ah(&samples[on.saturating_sub(1)..=k], eod));
    Ok(CellRecord {
        cell: d.cell.clone(),
        cycle: d.cycle,
        source: d.source.clone(),
        load_on_s: d.time_s[on],
        eod_s,
        current_a,
        data_capacity_ah,
        stated_capacity_ah: d.stated_capacity_ah,
        ambient_k: d.ambient_k,
        rest_before_s: None,
        partial_start: false,
        samples,
    })
}

/// What the records of a run were, for the report.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RecordSummary {
    pub records: usize,
    pub reaching_cutoff: usize,
    pub cut_short: Vec<u32>,
    /// Records refused, with the reason.
    pub refused: Vec<String>,
    /// Judged discharges that started from a partial charge ([`CellRecord::partial_start`]): their end of
    /// discharge is scored, their capacity is not.
    pub partial_start: Vec<u32>,
}

/// Test records: a discharge of 100 readings, 1 s apart, at 2 A from t = 0 to the cut-off at 100 s, and one
/// calibrator's run on it with the given end-of-discharge and capacity predictions at every reading.
#[cfg(test)]
pub(crate) fn test_discharge(
    cycle: u32,
    data_capacity_ah: f64,
    eod: impl Fn(f64) -> crate::predict::Predicted,
    capacity: crate::predict::Predicted,
) -> (CellRecord, crate::run::CycleRun) {
    use bcal_common::measured::scenario::{Request, Sample};
    let samples: Vec<Sample> = (0..=100)
        .map(|t| Sample {
            t_s: f64::from(t),
            voltage_v: 4.0,
            current_a: 2.0,
            temperature_k: 297.0,
            request: Request::Unknown,
        })
        .collect();
    let steps = samples
        .iter()
        .map(|s| crate::run::Step {
            t_s: s.t_s,
            estimate: bcal_common::battery::Degradation::default(),
            interval: None,
            eod: eod(s.t_s),
            capacity,
        })
        .collect();
    let record = CellRecord {
        cell: "T".into(),
        cycle,
        source: "t".into(),
        load_on_s: 0.0,
        eod_s: Some(100.0),
        current_a: 2.0,
        data_capacity_ah: Some(data_capacity_ah),
        stated_capacity_ah: None,
        ambient_k: 297.0,
        rest_before_s: None,
        partial_start: false,
        samples,
    };
    (record, crate::run::CycleRun { cycle, steps })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn discharge(v: Vec<f64>, i: Vec<f64>) -> Discharge {
        let n = v.len();
        Discharge {
            cell: "T".into(),
            cycle: 3,
            source: "t.csv".into(),
            ambient_k: 297.15,
            time_s: (0..n).map(|k| 10.0 * k as f64).collect(),
            voltage_v: v,
            current_a: i,
            temperature_k: None,
            stated_capacity_ah: Some(1.5),
        }
    }

    #[test]
    fn readings_stop_at_the_cutoff_and_its_time_is_interpolated() {
        // Rest, three loaded readings, the cut-off crossed between 20 and 30 s under load, then relaxation.
        let d = discharge(vec![4.2, 4.0, 3.0, 2.6, 3.4, 3.5], vec![0.0, 2.0, 2.0, 2.0, 0.0, 0.0]);
        let r = prepare(&d, 2.7).unwrap();
        assert_eq!(r.samples.len(), 4, "relaxation is left out");
        assert_eq!(r.load_on_s, 10.0);
        // 3.0 V at 20 s, 2.6 V at 30 s: 2.7 V at 27.5 s.
        assert!((r.eod_s.unwrap() - 27.5).abs() < 1e-9);
        assert_eq!(r.current_a, 2.0);
        // Trapezoids from the rest reading before the load to the interpolated cut-off at 27.5 s:
        // 10 + 20 + 2 A * 7.5 s = 45 C (not the 50 C up to the first reading below it).
        assert!((r.data_capacity_ah.unwrap() - 45.0 / 3600.0).abs() < 1e-12);
        assert_eq!(r.reading_at_fraction(0.5), Some(2));
    }

    #[test]
    fn a_record_ending_under_load_below_the_cutoff_is_complete_and_one_above_is_cut_short() {
        let done = discharge(vec![4.2, 3.9, 3.5, 2.4], vec![0.0, 2.0, 2.0, 2.0]);
        assert!(prepare(&done, 2.5).unwrap().eod_s.is_some());
        let short = discharge(vec![4.2, 3.9, 3.5, 3.2], vec![0.0, 2.0, 2.0, 2.0]);
        let r = prepare(&short, 2.5).unwrap();
        assert!(r.eod_s.is_none() && r.data_capacity_ah.is_none());
        assert_eq!(r.samples.len(), 4);
    }

    #[test]
    fn bad_records_are_refused_naming_the_file_and_what_to_do() {
        let rest = discharge(vec![4.2; 5], vec![0.0; 5]);
        let e = prepare(&rest, 2.7).unwrap_err().to_string();
        assert!(e.contains("t.csv") && e.contains("cycle 3") && e.contains("not a discharge"), "{e}");
        let d = discharge(vec![4.2, 3.6, 3.5], vec![0.0, 2.0, 2.0]);
        let e = prepare(&d, 3.8).unwrap_err().to_string();
        assert!(e.contains("--cutoff-v") && e.contains("3.600"), "{e}");
    }
}
