//! One measured discharge in the doctor's units (seconds, volts, amperes positive while discharging,
//! kelvin), and the windows every later stage agrees on: rest before the load, the loaded part down to the
//! fit floor, and the relaxation after cut-off.
//!
//! Readers build [`Discharge`] values; nothing here reads files or fits anything.

use serde::Serialize;
use std::path::PathBuf;

/// Offset from degrees Celsius to kelvin.
pub const CELSIUS_TO_KELVIN: f64 = 273.15;

/// A measured discharge record, validated by a reader.
#[derive(Clone, Debug)]
pub struct Discharge {
    /// Cell name (e.g. `B0005`, or the generic CSV's file stem).
    pub cell: String,
    /// Cycle number within the cell, 1-based (NASA: the discharge's order among the cell's discharges).
    pub cycle: u32,
    /// File the samples came from.
    pub source: PathBuf,
    /// Ambient temperature, K.
    pub ambient_k: f64,
    /// Sample times from record start, s, strictly increasing.
    pub time_s: Vec<f64>,
    /// Terminal voltage, V.
    pub voltage_v: Vec<f64>,
    /// Current, A, positive while discharging.
    pub current_a: Vec<f64>,
    /// Measured (surface) temperature, K, when the record has it.
    pub temperature_k: Option<Vec<f64>>,
    /// Capacity the source states for the record, Ah (NASA metadata), if any.
    pub stated_capacity_ah: Option<f64>,
}

/// Where the parts of a discharge lie, as sample index ranges.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Windows {
    /// First sample under load.
    pub load_on: usize,
    /// One past the last loaded sample at or above the fit floor (the fit window is `load_on..fit_end`).
    pub fit_end: usize,
    /// One past the last loaded sample (the cut-off).
    pub load_end: usize,
    /// True when the record ends while still under load: no cut-off, no relaxation.
    pub truncated: bool,
}

impl Windows {
    /// Number of samples in the fit window.
    pub fn fit_len(&self) -> usize {
        self.fit_end - self.load_on
    }
}

impl Discharge {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.time_s.len()
    }

    /// True when the record holds no samples.
    pub fn is_empty(&self) -> bool {
        self.time_s.is_empty()
    }

    /// Finds the load window: loaded means `current_a > load_threshold_a`; the fit window stops at the first
    /// loaded sample below `v_floor_v` (the knee is beyond the model's reach there) or at the cut-off.
    /// `None` when no sample is loaded.
    pub fn windows(&self, load_threshold_a: f64, v_floor_v: f64) -> Option<Windows> {
        let load_on = self.current_a.iter().position(|i| *i > load_threshold_a)?;
        let last_loaded = self.current_a.iter().rposition(|i| *i > load_threshold_a)?;
        let load_end = last_loaded + 1;
        let fit_end = (load_on..load_end).find(|&k| self.voltage_v[k] < v_floor_v).unwrap_or(load_end);
        Some(Windows { load_on, fit_end, load_end, truncated: load_end == self.len() })
    }

    /// Charge drawn between two sample indices, Ah (trapezoidal; only the discharging part counts).
    pub fn charge_ah(&self, from: usize, to: usize) -> f64 {
        let mut q_c = 0.0;
        for k in from + 1..to.min(self.len()) {
            let i_mean = 0.5 * (self.current_a[k].max(0.0) + self.current_a[k - 1].max(0.0));
            q_c += i_mean * (self.time_s[k] - self.time_s[k - 1]);
        }
        q_c / 3600.0
    }

    /// Measured temperature at sample `k`, K, or the ambient when the record has none.
    pub fn temperature_at_k(&self, k: usize) -> f64 {
        self.temperature_k.as_ref().map_or(self.ambient_k, |t| t[k])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(current_a: Vec<f64>, voltage_v: Vec<f64>) -> Discharge {
        let n = current_a.len();
        Discharge {
            cell: "T".into(),
            cycle: 1,
            source: "t.csv".into(),
            ambient_k: 297.15,
            time_s: (0..n).map(|k| 10.0 * k as f64).collect(),
            voltage_v,
            current_a,
            temperature_k: None,
            stated_capacity_ah: None,
        }
    }

    #[test]
    fn windows_find_load_floor_and_cutoff() {
        let r = record(vec![0.0, 2.0, 2.0, 2.0, 2.0, 0.0, 0.0], vec![4.2, 4.0, 3.8, 2.85, 2.7, 3.3, 3.4]);
        let w = r.windows(0.05, 2.9).unwrap();
        assert_eq!(w, Windows { load_on: 1, fit_end: 3, load_end: 5, truncated: false });
        assert_eq!(w.fit_len(), 2);
    }

    #[test]
    fn a_record_ending_under_load_is_truncated() {
        let r = record(vec![0.0, 2.0, 2.0, 2.0], vec![4.2, 4.0, 3.9, 3.8]);
        let w = r.windows(0.05, 2.9).unwrap();
        assert!(w.truncated);
        assert_eq!(w.fit_end, 4);
        assert!(record(vec![0.0, 0.0], vec![4.2, 4.2]).windows(0.05, 2.9).is_none());
    }

    #[test]
    fn charge_integrates_discharge_current_only() {
        let r = record(vec![-1.0, 2.0, 2.0, 0.0], vec![4.2; 4]);
        // Trapezoids: (0 + 2)/2*10 + 2*10 + (2 + 0)/2*10 = 40 C.
        assert!((r.charge_ah(0, 4) - 40.0 / 3600.0).abs() < 1e-12);
    }
}
