//! One measured discharge in the doctor's units (seconds, volts, amperes positive while discharging,
//! kelvin), and the windows every later stage agrees on: rest before the load, the loaded part down to the
//! fit floor, and the relaxation after cut-off.
//!
//! A record that ends under load is one of two things: a discharge that reached the cell's cut-off and
//! was logged without the relaxation after it (complete: [`Windows::ended_at_cutoff`]), or one cut short
//! above the cut-off ([`Windows::truncated`]), whose capacity is only a lower bound. The cut-off comes from
//! the caller ([`DEFAULT_CUTOFF_V`] when unknown). The rest before the load tells where the discharge
//! starts ([`Discharge::start_state`]): a cell that rests clearly below the full cell's open-circuit
//! voltage did not start full.
//!
//! Readers build [`Discharge`] values; nothing here reads files or fits anything.

use crate::error::DoctorError;
use bcal_common::battery::{BatteryModel, BatteryParams};
use bcal_common::measured::cellmodel::{ocv_v, xn_from_rest_voltage};
use bcal_common::measured::load_mean::alternates;
use bcal_common::measured::SHORT_START_NEIGHBOURS;
use serde::Serialize;
use std::path::PathBuf;

/// Offset from degrees Celsius to kelvin.
pub const CELSIUS_TO_KELVIN: f64 = 273.15;

/// Discharge cut-off assumed when the caller knows none, V: a record ending under load at or below it is
/// complete. 2.5 V is the lowest cut-off of the NASA 2 A cells in `../shared` (B0006, B0018; B0005 stops
/// at 2.7 V, B0007 at 2.2 V) and a common 18650 cut-off; give the cell's own when it differs.
pub const DEFAULT_CUTOFF_V: f64 = 2.5;
/// How far below its settled load-on voltage a record's fit window may reach where that lies under the fit's
/// floor, V, when the load pulled the voltage down by more than [`LOAD_ON_DROP_V`] from the rest before it (a
/// cold or worn cell at a high current: NASA's B0041-B0044 deliver 0.05-0.09 Ah above 2.7 V at 4 A and 4 C),
/// never below the cut-off where it is known. A start from a partial charge lies low for its charge, not its
/// resistance, and keeps the floor. Every discharge of the six NASA cells at hand drops less than that, or
/// reads 3.18 V or more in its load's first minute, so none of their windows moves.
pub const FLOOR_BELOW_LOAD_ON_V: f64 = 0.25;
/// The drop from the rest to the settled load-on voltage beyond which the load, not a low charge, put the cell
/// near its floor, V (the six NASA cells' discharges at 2 and 4 A drop 0.27-0.59 V).
pub const LOAD_ON_DROP_V: f64 = 0.6;
/// How long after the last reading at rest a loaded reading is taken as settled, s (the fit's `settle_s`).
pub const LOAD_ON_SETTLE_S: f64 = 30.0;

/// The cut-off the records themselves show, V, when nobody gives one: a cycler stops a discharge at its
/// cut-off under load, so records that end still loaded end just below it. It is read when at least two
/// records (and a quarter of them) end under load, within 100 mV of each other at the 10th and 90th
/// percentiles, below 3.6 V: the highest such end voltage rounded up to the next 10 mV (every one of them
/// then counts as complete). Cyclers are set to round cut-offs and log the first reading past them, a few
/// mV below at 10 s sampling: the highest end of a few training records alone lies below the cut-off by
/// the least of those overshoots, and a later discharge that stopped closer to it would read as cut short.
/// None otherwise (the caller's default decides and says so).
pub fn infer_cutoff_v(ds: &[Discharge], load_threshold_a: f64) -> Option<f64> {
    let mut ends: Vec<f64> = ds
        .iter()
        .filter(|d| d.current_a.last().is_some_and(|i| *i > load_threshold_a))
        .filter_map(|d| d.voltage_v.last().copied())
        .collect();
    if ends.len() < 2 || 4 * ends.len() < ds.len() {
        return None;
    }
    let lo = bcal_common::stats::quantile(&mut ends, 0.1)?;
    let hi = bcal_common::stats::quantile(&mut ends, 0.9)?;
    let top = bcal_common::stats::quantile(&mut ends, 1.0)?;
    // The guard keeps a round end (2.7 V, 270.00000000000006 in hundredths) from rising a step.
    (hi - lo <= 0.1 && top < 3.6).then(|| (top * 100.0 - 1e-6).ceil() / 100.0)
}

/// A discharge starts partly discharged when the mean voltage of its rest before the load lies more than
/// this below the base model's full-cell open-circuit voltage at the rest temperature, V. Chosen on the
/// NASA records in `../shared` (every one charged CC-CV to 4.2 V before it; `tests/nasa_as_it_is.rs`): they
/// rest from 31 mV above to 70 mV below the full-cell OCV, except B0055 cycle 1, 347 mV below (3.84 V;
/// 0.80 Ah against 1.32 Ah on the next cycle), which did not start full; and on the synthetic test cells,
/// whose ageing electrode balance lowers a full cell's rest by up to 174 mV (the generator's largest drift;
/// `record::tests`), a full cell that a lower threshold would call partial.
pub const PARTIAL_START_DROP_V: f64 = 0.2;

/// The records among `records` (one cell's, any order) that started from a partial charge as their own
/// neighbours show it ([`bcal_common::measured::short_start`]): the rest voltage before the load lies more than
/// `drop_v` below the median of the [`SHORT_START_NEIGHBOURS`] records with a rest on each side, by cycle,
/// where the model rule ([`Discharge::start_state`], 200 mV against the model's full-cell voltage) must allow
/// for an electrode balance that drifts over the life (B0029 cycle 1: 77 mV below its neighbours, 0.15 Ah
/// short of the next discharge).
/// Returns each flagged cycle with its rest voltage and the neighbours' median, V.
pub fn short_starts(records: &[&Discharge], load_threshold_a: f64, drop_v: f64) -> Vec<(u32, f64, f64)> {
    let mut rests: Vec<(u32, f64)> =
        records.iter().filter_map(|d| d.rest_before_load_v(load_threshold_a).map(|v| (d.cycle, v))).collect();
    rests.sort_by_key(|r| r.0);
    let mut out = Vec::new();
    for (k, &(cycle, v)) in rests.iter().enumerate() {
        let around: Vec<f64> = rests[k.saturating_sub(SHORT_START_NEIGHBOURS)..k]
            .iter()
            .chain(rests.iter().skip(k + 1).take(SHORT_START_NEIGHBOURS))
            .map(|r| r.1)
            .collect();
        if let Some(m) = bcal_common::measured::short_start(v, &around, drop_v) {
            out.push((cycle, v, m));
        }
    }
    out
}

/// A measured discharge record, validated by a reader.
#[derive(Clone, Debug)]
pub struct Discharge {
    /// Cell name (e.g. `B0005`, or the generic CSV's file stem).
    pub cell: String,
    /// Cycle number within the cell (NASA: the discharge's order among the cell's discharges, from 1; a CSV: its
    /// cycle column's).
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
    /// True when the record ends under load ABOVE the cut-off: cut short, its capacity a lower bound.
    pub truncated: bool,
    /// True when the record ends under load at or below the cut-off: a complete discharge logged without the
    /// relaxation after it (its capacity is the full capacity to the cut-off).
    pub ended_at_cutoff: bool,
}

impl Windows {
    /// Number of samples in the fit window.
    pub fn fit_len(&self) -> usize {
        self.fit_end - self.load_on
    }
}

/// Where a discharge starts, from the rest before its load (see [`Discharge::start_state`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct StartState {
    /// Mean voltage of the samples before the first loaded one, V.
    pub rest_v: f64,
    /// Mean temperature over those samples (the ambient without a measured temperature), K.
    pub rest_temperature_k: f64,
    /// The base model's open-circuit voltage of a full cell at that temperature, V.
    pub full_ocv_v: f64,
    /// The negative electrode's mole fraction whose open-circuit voltage is `rest_v` (the base model's
    /// curve, clamped to its window; `xn_max` for a full cell).
    pub xn0: f64,
    /// True when `rest_v` lies more than the given drop below `full_ocv_v`: the discharge did not start full.
    pub partial: bool,
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
    /// loaded sample below `v_floor_v` (the knee is beyond the model's reach there), or below the settled
    /// load-on voltage less [`FLOOR_BELOW_LOAD_ON_V`] where that is lower and the load pulled the voltage more
    /// than [`LOAD_ON_DROP_V`] under the rest (a cell whose resistance puts it under the floor from the load
    /// on, as NASA's 4 A discharges at 4 C run, still has its voltage fitted; never below a cut-off given),
    /// or at the cut-off. A
    /// record ending under load is taken as ending at the [`DEFAULT_CUTOFF_V`] cut-off if its last loaded
    /// voltage is at or below it (see [`Discharge::windows_with_cutoff`]). `None` when no sample is loaded.
    pub fn windows(&self, load_threshold_a: f64, v_floor_v: f64) -> Option<Windows> {
        self.windows_with_cutoff(load_threshold_a, v_floor_v, None)
    }

    /// [`Discharge::windows`] with the cell's discharge cut-off, V ([`DEFAULT_CUTOFF_V`] when `None`): a record
    /// whose last sample is still loaded ended at the cut-off when that sample's voltage is at or below it,
    /// else it was cut short (truncated).
    pub fn windows_with_cutoff(&self, load_threshold_a: f64, v_floor_v: f64, cutoff_v: Option<f64>) -> Option<Windows> {
        let load_on = self.first_loaded(load_threshold_a)?;
        let last_loaded = self.current_a.iter().rposition(|i| *i > load_threshold_a)?;
        let load_end = last_loaded + 1;
        let floor_v = match (self.load_on_drop(load_on, load_end, load_threshold_a), cutoff_v) {
            (Some((on_v, drop_v)), cut) if drop_v > LOAD_ON_DROP_V => {
                v_floor_v.min(on_v - FLOOR_BELOW_LOAD_ON_V).max(cut.unwrap_or(f64::NEG_INFINITY))
            }
            _ => v_floor_v,
        };
        let fit_end = (load_on..load_end).find(|&k| self.voltage_v[k] < floor_v).unwrap_or(load_end);
        let under_load_at_end = load_end == self.len();
        let ended_at_cutoff = under_load_at_end && self.voltage_v[last_loaded] <= cutoff_v.unwrap_or(DEFAULT_CUTOFF_V);
        Some(Windows { load_on, fit_end, load_end, truncated: under_load_at_end && !ended_at_cutoff, ended_at_cutoff })
    }

    /// The settled load-on voltage, V, and how far the load pulled the voltage down from the rest before it,
    /// V: the first loaded reading [`LOAD_ON_SETTLE_S`] or more after the last reading at rest (one read
    /// sooner can come before the voltage settles under the load). None without a reading at rest before
    /// the load, or without such a loaded reading.
    fn load_on_drop(&self, load_on: usize, load_end: usize, load_threshold_a: f64) -> Option<(f64, f64)> {
        let rest = load_on.checked_sub(1)?;
        let settled = (load_on..load_end).find(|&k| {
            self.current_a[k] > load_threshold_a && self.time_s[k] - self.time_s[rest] >= LOAD_ON_SETTLE_S
        })?;
        let on_v = self.voltage_v[settled];
        Some((on_v, self.voltage_v[rest] - on_v))
    }

    /// Whether the load switches about as often as the record samples it ([`alternates`]: more than half of
    /// enough loaded samples follow a load step, the current changed by more than `step_threshold_a` since the
    /// sample before; a stream's `LoadMean` applies the same rule). B0025's square wave (4 A at half duty, a 20 s period)
    /// is read every 10-12 s in step with it, so every loaded sample follows a switch of unknown time.
    pub fn alternating_load(&self, load_threshold_a: f64, step_threshold_a: f64) -> bool {
        let loaded: Vec<usize> = (1..self.len()).filter(|&k| self.current_a[k] > load_threshold_a).collect();
        let stepped =
            loaded.iter().filter(|&&k| (self.current_a[k] - self.current_a[k - 1]).abs() > step_threshold_a).count();
        alternates(loaded.len(), stepped)
    }

    /// Index of the first sample under load (`current_a > load_threshold_a`).
    pub fn first_loaded(&self, load_threshold_a: f64) -> Option<usize> {
        self.current_a.iter().position(|i| *i > load_threshold_a)
    }

    /// Refuses a cut-off above the first loaded voltage: the cycler would have stopped at once, so the
    /// cut-off given is not this cell's (a wrong value, or millivolts). Records without load pass.
    pub fn check_cutoff(&self, cutoff_v: f64, load_threshold_a: f64) -> Result<(), DoctorError> {
        let first = self.first_loaded(load_threshold_a);
        match first.and_then(|k| Some((*self.voltage_v.get(k)?, *self.time_s.get(k)?))) {
            Some((first_loaded_v, time_s)) if first_loaded_v < cutoff_v => Err(DoctorError::CutoffAboveLoad {
                path: self.source.clone(),
                cycle: self.cycle,
                cutoff_v,
                first_loaded_v,
                time_s,
            }),
            _ => Ok(()),
        }
    }

    /// Mean voltage of the rest before the load (the samples before the first loaded one), V; `None` when the
    /// record starts under load or has no load.
    pub fn rest_before_load_v(&self, load_threshold_a: f64) -> Option<f64> {
        let k = self.first_loaded(load_threshold_a)?;
        let rest = self.voltage_v.get(..k).filter(|r| !r.is_empty())?;
        Some(rest.iter().sum::<f64>() / k as f64)
    }

    /// Where the discharge starts: the rest voltage before the load mapped through the base model's
    /// open-circuit curve (`bcal_common::measured::cellmodel::xn_from_rest_voltage`) to the negative
    /// electrode's starting mole fraction, and whether it lies more than `partial_drop_v` below the full
    /// cell's open-circuit voltage ([`PARTIAL_START_DROP_V`] is the doctor's rule). A cell charged to its
    /// end voltage rests near the full-cell curve; one that rests clearly below did not start full, and
    /// starting it from a full cell (progpy's initial state) would credit it with charge it never held.
    /// `Ok(None)` when the record has no rest before its load.
    pub fn start_state(
        &self,
        base: &BatteryParams,
        load_threshold_a: f64,
        partial_drop_v: f64,
    ) -> Result<Option<StartState>, DoctorError> {
        let (Some(k), Some(rest_v)) = (self.first_loaded(load_threshold_a), self.rest_before_load_v(load_threshold_a))
        else {
            return Ok(None);
        };
        let rest_temperature_k = match self.temperature_k.as_deref().and_then(|t| t.get(..k)) {
            Some(t) => t.iter().sum::<f64>() / k as f64,
            None => self.ambient_k,
        };
        let model = BatteryModel::new(base.clone(), false)?;
        let full_ocv_v = ocv_v(&model, base.xn_max, rest_temperature_k);
        let xn0 = xn_from_rest_voltage(&model, rest_v, rest_temperature_k);
        Ok(Some(StartState {
            rest_v,
            rest_temperature_k,
            full_ocv_v,
            xn0,
            partial: rest_v < full_ocv_v - partial_drop_v,
        }))
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

    /// `d` read once a minute.
    fn minutely(d: Discharge) -> Discharge {
        Discharge { time_s: (0..d.len()).map(|k| 60.0 * k as f64).collect(), ..d }
    }

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
    fn a_short_start_shows_against_its_neighbours_and_a_drift_over_life_does_not() {
        // 60 discharges whose full-charge rest falls 174 mV over the life (the synthetic cells' largest
        // electrode-balance drift), with a 15 mV wiggle; cycle 20 starts 60 mV below where it should.
        let rest_v = |c: u32| 4.19 - 0.174 * f64::from(c) / 60.0 + 0.015 * (f64::from(c) * 1.7).sin();
        let records: Vec<Discharge> = (1..=60u32)
            .map(|c| {
                let v = rest_v(c) - if c == 20 { 0.06 } else { 0.0 };
                Discharge { cycle: c, ..record(vec![0.0, 0.0, 2.0, 2.0], vec![v, v, 3.9, 3.8]) }
            })
            .collect();
        let refs: Vec<&Discharge> = records.iter().rev().collect();
        let flagged = short_starts(&refs, 0.05, 0.05);
        assert_eq!(flagged.iter().map(|f| f.0).collect::<Vec<_>>(), vec![20], "{flagged:?}");
        assert!((flagged[0].1 - (rest_v(20) - 0.06)).abs() < 1e-12);
        // Against the whole life's median, the drift alone would flag the last fifth of the records.
        let mut all: Vec<f64> = (1..=60).map(rest_v).collect();
        let median = bcal_common::stats::quantile(&mut all, 0.5).unwrap();
        assert!((1..=60).filter(|&c| rest_v(c) < median - 0.05).count() >= 10);
    }

    #[test]
    fn windows_find_load_floor_and_cutoff() {
        // A reading a minute (the load-on voltage, 3.8 V, leaves the floor where it is).
        let r = minutely(record(vec![0.0, 2.0, 2.0, 2.0, 2.0, 0.0, 0.0], vec![4.2, 4.0, 3.8, 2.85, 2.7, 3.3, 3.4]));
        let w = r.windows(0.05, 2.9).unwrap();
        assert_eq!(w, Windows { load_on: 1, fit_end: 3, load_end: 5, truncated: false, ended_at_cutoff: false });
        assert_eq!(w.fit_len(), 2);
    }

    /// A cell the load pulls far under its rest and near or under the floor at once (a 4 A discharge at 4 C)
    /// is fitted down to 0.25 V below its settled load-on voltage (the first loaded reading 30 s after the rest,
    /// not the one read before the voltage settled), never below the cut-off; a start from a partial charge,
    /// low for its charge, and a cell that starts above the floor by more than that keep the floor.
    #[test]
    fn a_record_under_the_floor_from_its_load_on_is_fitted_to_below_its_start() {
        let every_20_s = |d: Discharge| Discharge { time_s: (0..d.len()).map(|k| 20.0 * k as f64).collect(), ..d };
        let cold = every_20_s(record(
            vec![0.0, 4.0, 4.0, 4.0, 4.0, 4.0, 4.0, 4.0],
            vec![4.1, 3.5, 2.6, 2.55, 2.45, 2.34, 2.2, 1.98],
        ));
        // Settled at 40 s, 2.6 V (1.5 V under the rest): the floor 2.35 V.
        let w = cold.windows_with_cutoff(0.05, 2.9, Some(2.0)).unwrap();
        assert_eq!((w.load_on, w.fit_end, w.load_end), (1, 5, 8), "{w:?}");
        assert!(w.ended_at_cutoff);
        // Never below the cut-off.
        assert_eq!(cold.windows_with_cutoff(0.05, 2.9, Some(2.4)).unwrap().fit_end, 5);
        assert_eq!(cold.windows_with_cutoff(0.05, 2.9, Some(2.5)).unwrap().fit_end, 4);
        // From a partial charge: 3.6 V at rest, 3.3 V settled (0.3 V under it): the floor stays at 2.9 V.
        let partial = every_20_s(record(vec![0.0, 2.0, 2.0, 2.0, 2.0, 2.0], vec![3.6, 3.35, 3.3, 3.0, 2.85, 2.6]));
        assert_eq!(partial.windows(0.05, 2.9).unwrap().fit_end, 4);
        let warm = Discharge {
            time_s: (0..8).map(|k| 30.0 * k as f64).collect(),
            ..record(vec![0.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0], vec![4.2, 3.4, 3.35, 3.3, 3.1, 2.95, 2.88, 2.6])
        };
        // Load-on 3.4 V: 3.15 V is above the floor, which stays.
        assert_eq!(warm.windows(0.05, 2.9).unwrap().fit_end, 6);
    }

    #[test]
    fn a_record_ending_under_load_above_the_cutoff_is_truncated() {
        let r = record(vec![0.0, 2.0, 2.0, 2.0], vec![4.2, 4.0, 3.9, 3.8]);
        let w = r.windows(0.05, 2.9).unwrap();
        assert!(w.truncated && !w.ended_at_cutoff);
        assert_eq!(w.fit_end, 4);
        assert!(record(vec![0.0, 0.0], vec![4.2, 4.2]).windows(0.05, 2.9).is_none());
    }

    #[test]
    fn a_record_ending_under_load_at_or_below_the_cutoff_is_complete() {
        // B0006's way: still loaded at the last sample, 2.35 V, below its 2.5 V cut-off.
        let r = minutely(record(vec![0.0, 2.0, 2.0, 2.0, 2.0], vec![4.2, 4.0, 3.6, 2.8, 2.35]));
        for cutoff in [None, Some(2.5), Some(2.35)] {
            let w = r.windows_with_cutoff(0.05, 2.9, cutoff).unwrap();
            assert!(w.ended_at_cutoff && !w.truncated, "{cutoff:?}: {w:?}");
            assert_eq!((w.load_end, w.fit_end), (5, 3));
        }
        // The same record is cut short for a cell whose cut-off is lower (B0007: 2.2 V).
        let w = r.windows_with_cutoff(0.05, 2.9, Some(2.2)).unwrap();
        assert!(w.truncated && !w.ended_at_cutoff);
        // A record with its relaxation is neither.
        let relaxed = record(vec![0.0, 2.0, 2.0, 0.0], vec![4.2, 4.0, 2.4, 3.3]);
        let w = relaxed.windows_with_cutoff(0.05, 2.9, Some(2.5)).unwrap();
        assert!(!w.truncated && !w.ended_at_cutoff);
    }

    #[test]
    fn a_cutoff_above_the_first_loaded_voltage_is_refused_naming_file_and_cycle() {
        let r = record(vec![0.0, 2.0, 2.0, 0.0], vec![4.2, 4.0, 3.0, 3.5]);
        assert!(r.check_cutoff(2.5, 0.05).is_ok());
        let msg = r.check_cutoff(4.1, 0.05).unwrap_err().to_string();
        assert!(msg.contains("t.csv, cycle 1") && msg.contains("4.1 V") && msg.contains("4.000 V"), "{msg}");
        assert!(msg.contains("--cutoff-v") && !msg.contains('\n'), "{msg}");
        // A cut-off in millivolts is caught the same way.
        assert!(r.check_cutoff(2500.0, 0.05).is_err());
    }

    #[test]
    fn the_rest_before_the_load_gives_the_starting_state() {
        let base = BatteryParams::default();
        let model = BatteryModel::new(base.clone(), false).unwrap();
        let full = ocv_v(&model, base.xn_max, 297.15);
        let half_xn = 0.5 * (base.xn_min + base.xn_max);
        let half = ocv_v(&model, half_xn, 297.15);
        let start = |rest_v: f64| {
            let r = record(vec![0.0, 0.0, 2.0, 2.0], vec![rest_v - 0.001, rest_v + 0.001, 3.9, 3.8]);
            assert!((r.rest_before_load_v(0.05).unwrap() - rest_v).abs() < 1e-12);
            r.start_state(&base, 0.05, PARTIAL_START_DROP_V).unwrap().unwrap()
        };
        let s = start(full);
        assert!(!s.partial && (s.xn0 - base.xn_max).abs() < 1e-6 && (s.full_ocv_v - full).abs() < 1e-12, "{s:?}");
        // A rest just inside the rule is still a full start; the half-charged cell is not.
        assert!(!start(full - 0.9 * PARTIAL_START_DROP_V).partial);
        let s = start(half);
        assert!(s.partial && (s.xn0 - half_xn).abs() < 1e-6, "{s:?}");
        // No rest before the load: no starting state to read.
        let r = record(vec![2.0, 2.0, 0.0], vec![4.0, 3.9, 4.1]);
        assert!(r.rest_before_load_v(0.05).is_none() && r.start_state(&base, 0.05, 0.1).unwrap().is_none());
    }

    /// What the rule's threshold is measured against (figures quoted beside [`PARTIAL_START_DROP_V`]): the
    /// drop of a full cell's rest under the synthetic generator's largest electrode-balance drift.
    #[test]
    fn an_aged_electrode_balance_lowers_the_full_rest_less_than_the_rule() {
        let base = BatteryParams::default();
        let model = BatteryModel::new(base.clone(), false).unwrap();
        let full = ocv_v(&model, base.xn_max, 297.15);
        let mut worst: f64 = 0.0;
        for (dxp, dxn) in [(0.05, -0.05), (0.10, -0.05), (0.05, -0.12), (0.10, -0.12), (0.11, -0.15)] {
            let shifted = BatteryParams { xp_min: base.xp_min + dxp, xn_max: base.xn_max + dxn, ..base.clone() };
            let m = BatteryModel::new(shifted.clone(), false).unwrap();
            let drop = full - ocv_v(&m, shifted.xn_max, 297.15);
            eprintln!("balance shift xp {dxp:+.2} xn {dxn:+.2}: full rest {:.1} mV lower", 1e3 * drop);
            worst = worst.max(drop);
        }
        assert!(worst < PARTIAL_START_DROP_V, "{worst}");
    }

    #[test]
    fn charge_integrates_discharge_current_only() {
        let r = record(vec![-1.0, 2.0, 2.0, 0.0], vec![4.2; 4]);
        // Trapezoids: (0 + 2)/2*10 + 2*10 + (2 + 0)/2*10 = 40 C.
        assert!((r.charge_ah(0, 4) - 40.0 / 3600.0).abs() < 1e-12);
    }
}
