//! One measured discharge as a calibrator meets it: readings in time order from the start of the record
//! (the rest before the load) to the cut-off reading, and what the cycler measured about it (when the load
//! came on, when the voltage reached the cut-off, the charge drawn until then, the capacity its metadata
//! states). Everything after the cut-off (the relaxation) is left out: a calibrator predicts the end of
//! discharge before it happens.

use bcal_calib::eod::charge_to_ah;
use bcal_common::battery::BatteryModel;
use bcal_common::battery::Load;
use bcal_common::measured::cellmodel::start_share_sd;
use bcal_common::measured::noise::{voltage_noise_v, NOISE_WINDOW};
use bcal_common::measured::scenario::{Request, Sample};
use bcal_common::measured::{ShortStartWatch, SHORT_START_CARRY_DROP_V, SHORT_START_DROP_V};
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
    /// Mean current under load, A (over time where the load alternates; [`CellRecord::load`] is the load
    /// predictions assume, a power where it was held at power).
    pub current_a: f64,
    /// Charge drawn from the load-on to the cut-off, Ah (the capacity the data itself shows).
    pub data_capacity_ah: Option<f64>,
    /// Capacity the source states (NASA metadata), Ah.
    pub stated_capacity_ah: Option<f64>,
    /// Ambient temperature, K.
    pub ambient_k: f64,
    /// The rest before the discharge (from the end of the record before it), s; None when unknown.
    pub rest_before_s: Option<f64>,
    /// The mean current of the loaded readings of the record before it, A ([`set_currents_before`]; None for
    /// the first): what a discharge's current is compared with (the learner on the record, the twins by
    /// current).
    pub current_before_a: Option<f64>,
    /// Whether it started from a partial charge, as its neighbours' rest voltages show (records after it
    /// among them: for the scores only). The charge it delivered is not the cell's capacity, so its
    /// capacity is not scored; its end of discharge is.
    pub partial_start: bool,
    /// Whether it started so far short of a full charge, as the rests of the discharges before it show
    /// ([`set_short_starts_seen`]; no look-ahead), that its end fit does not measure the cell: it hands on what
    /// was carried into it, as one cut short does ([`CellRecord::measured_its_charge`]).
    pub short_start_seen: bool,
    /// Whether it started from a partial charge as the rests of the discharges before it show
    /// ([`set_short_starts_seen`], the rule of [`CellRecord::partial_start`] without look-ahead): the charge it
    /// delivered is not the cell's capacity, so the capacity intervals do not learn from it
    /// ([`crate::interval`]).
    pub partial_start_seen: bool,
    /// How well the charge it starts with is known, as a share of qMobile (one sd; None without a rest reading
    /// before the load or a sensor noise to read it with): its rest voltage's noise through the open-circuit
    /// curve ([`set_start_spreads`]), what its end of discharge's interval adds for it
    /// ([`bcal_calib::widening::start_half`]).
    pub start_share_sd: Option<f64>,
    /// The charge the discharges before it drew between the voltage the source's stated capacity is drawn to
    /// and the cut-off, Ah ([`set_stated_tails`]; None where the stated capacity is the charge to the cut-off):
    /// what a capacity predicted to the cut-off holds beyond the stated one.
    pub stated_tail_ah: Option<f64>,
}

/// Sets each record's [`CellRecord::current_before_a`] from the one before it in `records` (in order: every
/// record kept, training and judged, cut short or not, as a stream counts every discharge that ran a while;
/// a record refused as unfittable is not among them, where a stream would count its discharge).
pub fn set_currents_before<'r>(records: impl IntoIterator<Item = &'r mut CellRecord>) {
    let mut last: Option<f64> = None;
    for r in records {
        r.current_before_a = last;
        last = r.loaded_current().whole().or(last);
    }
}

/// Sets each record's [`CellRecord::short_start_seen`] and [`CellRecord::partial_start_seen`] against the rests
/// of the records before it in `records` (in order: every record kept, training and judged, as
/// [`set_currents_before`]; `ShortStartWatch`).
pub fn set_short_starts_seen<'r>(records: impl IntoIterator<Item = &'r mut CellRecord>) {
    let mut watch = ShortStartWatch::default();
    for r in records {
        let drop_v = watch.see_drop_v(r.rest_before_load_v());
        r.short_start_seen = drop_v.is_some_and(|d| d > SHORT_START_CARRY_DROP_V);
        r.partial_start_seen = drop_v.is_some_and(|d| d > SHORT_START_DROP_V);
    }
}

/// Sets each record's [`CellRecord::start_share_sd`] under the calibrators' `model` (in order: every record
/// kept, training and judged, as [`set_currents_before`]): its rest readings read with the voltage noise of
/// the [`NOISE_WINDOW`] records before it (the median of each one's own, `voltage_noise_v`; no look-ahead),
/// the first record with its own. Returns each record's own noise, V, in order (None where too few readings
/// say it).
pub fn set_start_spreads<'r>(
    records: impl IntoIterator<Item = &'r mut CellRecord>,
    model: &BatteryModel,
) -> Vec<Option<f64>> {
    let mut noises: std::collections::VecDeque<f64> = std::collections::VecDeque::new();
    let mut owns = Vec::new();
    for r in records {
        let own = voltage_noise_v(&r.samples);
        owns.push(own);
        let mut before: Vec<f64> = noises.iter().copied().collect();
        let noise_v = bcal_common::stats::median(&mut before).or(own);
        r.start_share_sd = noise_v.and_then(|n| start_share_sd(model, &r.samples, n));
        if let Some(n) = own {
            if noises.len() == NOISE_WINDOW {
                noises.pop_front();
            }
            noises.push_back(n);
        }
    }
    owns
}

/// The discharge's load as its predictions assume it at its end (`bcal_calib::LoadMean`): the mean current
/// of its loaded readings, or over time where the load alternates, or their mean power where it was held at
/// power.
pub(crate) fn load_mean(samples: &[Sample]) -> bcal_calib::LoadMean {
    let mut load = bcal_calib::LoadMean::default();
    for s in samples {
        load.push(s.t_s, s.current_a, s.voltage_v);
    }
    load
}

impl CellRecord {
    /// The running mean current of its loaded readings from the load-on, A (against the time after it, s).
    pub fn loaded_current(&self) -> bcal_calib::record_learner::LoadedMean {
        self.loaded_mean(|s| s.current_a)
    }

    /// The running mean of `of` (a loaded reading's temperature, its current) from the load-on.
    pub fn loaded_mean(&self, of: impl Fn(&Sample) -> f64) -> bcal_calib::record_learner::LoadedMean {
        let mut mean = bcal_calib::record_learner::LoadedMean::default();
        for s in self.samples.iter().filter(|s| s.t_s >= self.load_on_s && s.current_a > LOAD_THRESHOLD_A) {
            mean.push(s.t_s - self.load_on_s, of(s));
        }
        mean
    }

    /// The load its predictions assume at its end ([`load_mean`]; a current of 0 A with no loaded reading).
    pub fn load(&self) -> Load {
        load_mean(&self.samples).load().unwrap_or(Load::CurrentA(0.0))
    }

    /// The mean voltage of its readings at rest before the load came on, V (None without one), as its end fit
    /// reads its starting charge off it.
    pub fn rest_before_load_v(&self) -> Option<f64> {
        bcal_calib::end_fit::rest_voltage_v(&self.samples)
    }

    /// Whether its end measured the charge the cell holds: it reached its cut-off, not from a partial charge as
    /// far as the discharges before it tell ([`CellRecord::short_start_seen`]). One that did not hands on what
    /// was carried into it ([`crate::carry::over_cut_short`]) and gives the prior's width no pair.
    pub fn measured_its_charge(&self) -> bool {
        self.eod_s.is_some() && !self.short_start_seen
    }

    /// The current of its first loaded reading, A (None without one): what a discharge shows of its current at
    /// the load-on, as a live stream reads it there (`bcal_calib::stream`).
    pub fn load_on_current_a(&self) -> Option<f64> {
        self.samples.iter().find(|s| s.t_s >= self.load_on_s && s.current_a > LOAD_THRESHOLD_A).map(|s| s.current_a)
    }

    /// Duration of the discharge from the load-on to the cut-off, s.
    pub fn discharge_s(&self) -> Option<f64> {
        self.eod_s.map(|e| e - self.load_on_s)
    }

    /// Whether the discharge follows a rest of more than a day ([`crate::prior::LONG_REST_S`]), after which a
    /// NASA cell has regained capacity.
    pub fn after_long_rest(&self) -> bool {
        self.rest_before_s.is_some_and(|s| s > crate::prior::LONG_REST_S)
    }

    /// The charge drawn from the load-on until the voltage first fell to `level_v` under load, Ah, as
    /// [`CellRecord::data_capacity_ah`] is drawn to the cut-off (None where it never fell that far).
    pub fn charge_to_v_ah(&self, level_v: f64) -> Option<f64> {
        let on = self.samples.iter().position(|s| s.t_s >= self.load_on_s)?;
        let at = |k: usize| {
            let s = &self.samples[k];
            (s.t_s, s.voltage_v, s.current_a)
        };
        let (k, t_s) = crossing(self.samples.len(), on, level_v, at)?;
        Some(charge_to_ah(&self.samples[on.saturating_sub(1)..=k], t_s))
    }

    /// Index of the first reading at or after `fraction` of the discharge (by time from the load-on).
    pub fn reading_at_fraction(&self, fraction: f64) -> Option<usize> {
        let t = self.load_on_s + fraction * self.discharge_s()?;
        self.samples.iter().position(|s| s.t_s >= t - 1e-9)
    }
}

/// The first reading from `on` (of `n`, each `at(k)` = time s, voltage V, current A) under load at or below
/// `level_v`, and when the voltage reached it: linear between that reading and the one before.
fn crossing(n: usize, on: usize, level_v: f64, at: impl Fn(usize) -> (f64, f64, f64)) -> Option<(usize, f64)> {
    let k = (on..n).find(|&k| {
        let (_, v, i) = at(k);
        i > LOAD_THRESHOLD_A && v <= level_v
    })?;
    let (t1, v1, _) = at(k);
    if k == on || k == 0 {
        return Some((k, t1));
    }
    let (t0, v0, _) = at(k - 1);
    Some((k, if v0 > v1 { t0 + (t1 - t0) * ((v0 - level_v) / (v0 - v1)).clamp(0.0, 1.0) } else { t1 }))
}

/// Why a discharge cannot be calibrated; each names the record and what to do.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RecordError {
    #[error("{file}: cycle {cycle} holds no reading under load (above {LOAD_THRESHOLD_A} A): not a discharge; select discharge records or check the current's sign (--current-sign)")]
    NoDischarge { file: String, cycle: u32 },
    #[error("{file}: cycle {cycle}: the voltage is at or below the {cutoff_v} V cut-off from its first reading under load ({first_v:.3} V): a load the cell could not carry (a cold cell's very-low-capacity run), or a cut-off above this cell's (pass its real one with --cutoff-v)")]
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
    let crossed = crossing(d.len(), on, cutoff_v, |k| (d.time_s[k], d.voltage_v[k], d.current_a[k]));
    let cut = crossed.map(|(k, _)| k);
    let last = cut.unwrap_or_else(|| (on..d.len()).rev().find(|&k| d.current_a[k] > LOAD_THRESHOLD_A).unwrap_or(on));
    let eod_s = crossed.map(|(_, t)| t);
    let samples: Vec<Sample> = (0..=last)
        .map(|k| Sample {
            t_s: d.time_s[k],
            voltage_v: d.voltage_v[k],
            current_a: d.current_a[k],
            temperature_k: d.temperature_at_k(k),
            request: Request::Unknown,
        })
        .collect();
    let current_a = load_mean(&samples).current_a().unwrap_or(0.0);
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
        current_before_a: None,
        partial_start: false,
        short_start_seen: false,
        partial_start_seen: false,
        start_share_sd: None,
        stated_tail_ah: None,
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
    /// Records of the selected cycles the reader could not read (a file missing, empty or malformed), with
    /// the reason.
    pub unread: Vec<String>,
    /// The reader's notes (a damaged end read up to, readings written twice, a gap, a cycle without discharge).
    pub noted: Vec<String>,
    /// Judged discharges that started from a partial charge ([`CellRecord::partial_start`]): their end of
    /// discharge is scored, their capacity is not.
    pub partial_start: Vec<u32>,
    /// What the source's stated capacity measures, read off the training records ([`stated_capacity`]).
    pub stated_capacity: Option<StatedCapacity>,
    /// Each judged discharge's capacity references, so that a run can be scored again from its report alone
    /// (`examples/record_room.py --against stated`).
    pub capacity_refs: Vec<CapacityRefs>,
}

/// What a judged discharge's predicted capacities are scored against.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct CapacityRefs {
    pub cycle: u32,
    /// The capacity the source states, Ah ([`CellRecord::stated_capacity_ah`]).
    pub stated_ah: Option<f64>,
    /// The data's charge to the interpolated cut-off, Ah ([`CellRecord::data_capacity_ah`]).
    pub data_ah: Option<f64>,
    /// What a capacity predicted to the cut-off is taken down by before it is scored against `stated_ah`, Ah
    /// ([`CellRecord::stated_tail_ah`]).
    pub stated_tail_ah: Option<f64>,
    /// Started from a partial charge: its capacity is not scored.
    pub partial_start: bool,
}

/// The voltage the source's stated capacity is drawn to, as the data shows it: NASA's metadata states the
/// charge to about 2.7 V on every cell, whatever its cut-off (B0055 at 4 C, cut off at 2.5 V: 0.05 Ah less than
/// its charge to the cut-off), so a capacity predicted to the cut-off and scored against the stated one carried
/// that difference as an error until 2026-11-30; it is now scored less the tail below that voltage
/// ([`set_stated_tails`]).
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct StatedCapacity {
    /// The voltage whose charge matches the stated capacity best (by the median absolute gap), V.
    pub voltage_v: f64,
    /// Median of the stated capacity less the data's charge to `voltage_v`, Ah ...
    pub median_gap_ah: f64,
    /// ... and less the data's charge to the cut-off, Ah.
    pub cutoff_median_gap_ah: f64,
    /// Records it was read on.
    pub records: usize,
}

impl StatedCapacity {
    /// Whether the stated capacity is drawn to another voltage than the cut-off, clearly: its gap there less
    /// than half the cut-off's and at least 2 mAh smaller (a gap at the level of one discharge's scatter
    /// names nothing).
    pub fn differs_from_cutoff(&self, cutoff_v: f64) -> bool {
        let (here, there) = (self.median_gap_ah.abs(), self.cutoff_median_gap_ah.abs());
        (self.voltage_v - cutoff_v).abs() > 1e-9 && here < 0.5 * there && there - here >= STATED_CLEAR_AH
    }
}

/// Voltages a stated capacity is looked for at: the cut-off and every tenth of a volt above it to 3.2 V.
const STATED_LEVELS_STEP_V: f64 = 0.1;
const STATED_LEVELS_TOP_V: f64 = 3.2;
/// How much closer the stated capacity must lie to another voltage's charge than to the cut-off's, Ah.
const STATED_CLEAR_AH: f64 = 0.002;
/// Records needed to say what the stated capacity measures.
const STATED_MIN_RECORDS: usize = 3;

/// Reads what `records`' stated capacities measure ([`StatedCapacity`]) on the ones that reach the cut-off,
/// state a capacity and started from a full charge; None with fewer than three.
pub fn stated_capacity(records: &[CellRecord], cutoff_v: f64) -> Option<StatedCapacity> {
    let usable: Vec<(&CellRecord, f64)> = records
        .iter()
        .filter(|r| r.data_capacity_ah.is_some() && !r.partial_start)
        .filter_map(|r| r.stated_capacity_ah.filter(|c| *c > 0.0).map(|c| (r, c)))
        .collect();
    if usable.len() < STATED_MIN_RECORDS {
        return None;
    }
    let median_gap = |level_v: f64| -> Option<f64> {
        let mut gaps: Vec<f64> = usable.iter().filter_map(|(r, c)| r.charge_to_v_ah(level_v).map(|q| c - q)).collect();
        if gaps.len() < usable.len() {
            return None;
        }
        bcal_common::stats::median(&mut gaps)
    };
    let at_cutoff = median_gap(cutoff_v)?;
    // The first tenth strictly above the cut-off (2.5 / 0.1 is 24.999...: a nudge before the floor).
    let first = (cutoff_v / STATED_LEVELS_STEP_V + 1e-9).floor() as i64 + 1;
    let above = (first..).map(|k| k as f64 * STATED_LEVELS_STEP_V).take_while(|v| *v <= STATED_LEVELS_TOP_V + 1e-9);
    let mut best = (cutoff_v, at_cutoff);
    for level_v in above {
        if let Some(g) = median_gap(level_v) {
            if g.abs() < best.1.abs() {
                best = (level_v, g);
            }
        }
    }
    Some(StatedCapacity {
        voltage_v: best.0,
        median_gap_ah: best.1,
        cutoff_median_gap_ah: at_cutoff,
        records: usable.len(),
    })
}

/// Discharges a stated-capacity tail is the median over ([`set_stated_tails`]): the latest, as the model's knee
/// is taken ([`crate::run::KNEE_WINDOW`]); the tail grows as the cell ages and sags more under load.
pub const STATED_TAIL_WINDOW: usize = crate::run::KNEE_WINDOW;

/// Sets each record's [`CellRecord::stated_tail_ah`] where the source states its capacity to another voltage than
/// the cut-off (`stated`, [`StatedCapacity::differs_from_cutoff`]): the median, over the last
/// [`STATED_TAIL_WINDOW`] records before it (in order, training and judged; with `--stride`, of those kept) that
/// reach the cut-off at a like current ([`bcal_calib::record_learner::LIKE_CURRENT`]; the charge below a voltage
/// grows with the current: 0.019 / 0.028 / 0.047 Ah below 2.7 V at 1 / 2 / 4 A on a blind cell cut off at 2.2 V),
/// else at any, of the charge each drew between that voltage and the cut-off. A capacity predicted to the cut-off
/// less that tail is a prediction of the quantity the source states (NASA's metadata: the charge to about 2.7 V,
/// whatever the cut-off), from what the discharges before it measured. A record's current is its loaded readings'
/// mean over the first quarter of it, known by the first capacity it is scored on (at a quarter): no look-ahead.
/// Before any such record, the training records' median (the stated capacity's two gaps) stands in.
pub fn set_stated_tails<'r>(
    records: impl IntoIterator<Item = &'r mut CellRecord>,
    stated: Option<&StatedCapacity>,
    cutoff_v: f64,
) {
    let Some(sc) = stated.filter(|sc| sc.differs_from_cutoff(cutoff_v)) else {
        for r in records {
            r.stated_tail_ah = None;
        }
        return;
    };
    // (current A, tail Ah) of every record before, in order.
    let mut tails: Vec<(f64, f64)> = Vec::new();
    for r in records {
        let current = r.loaded_current();
        // Known by the first capacity scored.
        let first_scored = f64::from(crate::score::CAPACITY_FRACTIONS_PCT[0]) / 100.0;
        let now_a = r.discharge_s().and_then(|d| current.at(first_scored * d)).or_else(|| current.whole());
        let like = |c: f64| now_a.is_some_and(|a| bcal_calib::record_learner::like_current(a, c));
        let mut last: Vec<f64> =
            tails.iter().rev().filter(|(c, _)| like(*c)).take(STATED_TAIL_WINDOW).map(|t| t.1).collect();
        if last.is_empty() {
            last = tails.iter().rev().take(STATED_TAIL_WINDOW).map(|t| t.1).collect();
        }
        r.stated_tail_ah = bcal_common::stats::median(&mut last).or(Some(sc.median_gap_ah - sc.cutoff_median_gap_ah));
        // A discharge from a partial charge counts too: the tail is drawn at its end, and whether it started
        // partial is read off the rests of the records after it as well.
        if let (Some(to_cutoff), Some(to_stated), Some(a)) = (r.data_capacity_ah, r.charge_to_v_ah(sc.voltage_v), now_a)
        {
            tails.push((a, to_cutoff - to_stated));
        }
    }
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
            eod_warmth_s: 0.0,
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
        current_before_a: None,
        partial_start: false,
        short_start_seen: false,
        partial_start_seen: false,
        start_share_sd: None,
        stated_tail_ah: None,
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

    /// A discharge at 2 A read every 10 s whose voltage falls 0.1 V per reading from 3.95 V, scaled in time by
    /// `stretch` (a cell that holds more charge falls more slowly), to 2.45 V (a 2.5 V cut-off), with the
    /// capacity it states.
    fn linear(stretch: f64, stated_ah: f64) -> CellRecord {
        linear_at(2.0, stretch, stated_ah)
    }

    /// [`linear`] at `current_a`.
    fn linear_at(current_a: f64, stretch: f64, stated_ah: f64) -> CellRecord {
        let n = 17;
        let mut d = discharge(
            (0..n).map(|k| if k == 0 { 4.2 } else { 4.05 - 0.1 * k as f64 }).collect(),
            (0..n).map(|k| if k == 0 { 0.0 } else { current_a }).collect(),
        );
        d.time_s = (0..n).map(|k| 10.0 * stretch * k as f64).collect();
        d.stated_capacity_ah = Some(stated_ah);
        prepare(&d, 2.5).unwrap()
    }

    #[test]
    fn the_charge_to_a_voltage_is_drawn_as_the_capacity_is_drawn_to_the_cutoff() {
        let r = linear(1.0, 1.0);
        assert_eq!(r.charge_to_v_ah(2.5), r.data_capacity_ah);
        // 2.7 V: 2.75 V at 130 s, 2.65 V at 140 s, crossed at 135 s: 2 A from the rest reading at 0 s (the
        // trapezoid from it to the load-on's reading holds 10 s at 1 A) to 135 s.
        let to_2_7 = r.charge_to_v_ah(2.7).unwrap();
        assert!((to_2_7 - (10.0 + 2.0 * 125.0) / 3600.0).abs() < 1e-12, "{to_2_7}");
        assert!(to_2_7 < r.data_capacity_ah.unwrap());
        // Above the first loaded reading's 3.95 V: that reading, which crossed it, ends the charge.
        assert!((r.charge_to_v_ah(4.0).unwrap() - 10.0 / 3600.0).abs() < 1e-12);
        assert_eq!(r.charge_to_v_ah(2.0), None, "never fell that far");
    }

    #[test]
    fn the_stated_capacity_is_read_as_the_charge_to_the_voltage_it_matches() {
        // Stated as the charge to 2.7 V (NASA's), 2 mAh off either way, on cells of several capacities.
        let at_2_7 = |stretch: f64, off_ah: f64| {
            let q = linear(stretch, 0.0).charge_to_v_ah(2.7).unwrap();
            linear(stretch, q + off_ah)
        };
        let records = vec![at_2_7(1.0, 0.002), at_2_7(1.3, -0.002), at_2_7(0.8, 0.001), at_2_7(1.1, 0.0)];
        let sc = stated_capacity(&records, 2.5).expect("four records state a capacity");
        assert!((sc.voltage_v - 2.7).abs() < 1e-9 && sc.differs_from_cutoff(2.5), "{sc:?}");
        assert!(sc.median_gap_ah.abs() <= 0.001 + 1e-12, "{sc:?}");
        // To the cut-off the data holds two more tenths of a volt: 20 s at 2 A, stretched.
        assert!(sc.cutoff_median_gap_ah < -0.009, "{sc:?}");
        assert_eq!(sc.records, 4);
        // Stated to the cut-off itself: the cut-off is named and nothing differs.
        let own: Vec<CellRecord> =
            [1.0, 1.2, 0.9].iter().map(|&x| linear(x, linear(x, 0.0).data_capacity_ah.unwrap())).collect();
        let sc = stated_capacity(&own, 2.5).unwrap();
        assert!(!sc.differs_from_cutoff(2.5) && sc.median_gap_ah.abs() < 1e-12, "{sc:?}");
        // Stated to 2.6 V on cells that fall so fast that the tenth of a volt below it holds under 2 mAh: too
        // little to name; twice as slow, it is named.
        let to_2_6 = |stretch: f64| linear(stretch, linear(stretch, 0.0).charge_to_v_ah(2.6).unwrap());
        let fast: Vec<CellRecord> = [0.34, 0.35, 0.36].into_iter().map(to_2_6).collect();
        let sc = stated_capacity(&fast, 2.5).unwrap();
        assert!((sc.voltage_v - 2.6).abs() < 1e-9 && !sc.differs_from_cutoff(2.5), "{sc:?}");
        let slow: Vec<CellRecord> = [0.68, 0.7, 0.72].into_iter().map(to_2_6).collect();
        assert!(stated_capacity(&slow, 2.5).unwrap().differs_from_cutoff(2.5));
        // Too few to say, or none stated, or only partial starts: nothing is read.
        assert_eq!(stated_capacity(&records[..2], 2.5), None);
        let mut partial = records.clone();
        for r in &mut partial {
            r.partial_start = true;
        }
        assert_eq!(stated_capacity(&partial, 2.5), None);
    }

    #[test]
    fn each_capacity_is_taken_down_by_the_tail_the_discharges_before_it_drew_below_the_stated_voltage() {
        // Stated to 2.7 V, cut off at 2.5 V, on a cell that falls ever faster (its tail shrinks).
        let at_2_7 = |stretch: f64| linear(stretch, linear(stretch, 0.0).charge_to_v_ah(2.7).unwrap());
        let stretches = [1.4, 1.3, 1.2, 1.1, 1.0, 0.9];
        let mut records: Vec<CellRecord> = stretches.iter().map(|&x| at_2_7(x)).collect();
        let tail = |r: &CellRecord| r.data_capacity_ah.unwrap() - r.charge_to_v_ah(2.7).unwrap();
        let tails: Vec<f64> = records.iter().map(tail).collect();
        let sc = stated_capacity(&records[..3], 2.5).expect("three records state a capacity");
        // A discharge from a partial charge counts (its end is like the others').
        records[4].partial_start = true;
        set_stated_tails(records.iter_mut(), Some(&sc), 2.5);
        // The first has none before it: the training records' median gap stands in.
        let first = records[0].stated_tail_ah.unwrap();
        assert!((first - (sc.median_gap_ah - sc.cutoff_median_gap_ah)).abs() < 1e-12, "{first}");
        // Then the median of the last three before it, never its own.
        assert!((records[1].stated_tail_ah.unwrap() - tails[0]).abs() < 1e-12);
        assert!((records[3].stated_tail_ah.unwrap() - tails[1]).abs() < 1e-12, "median of 0, 1, 2");
        assert!((records[4].stated_tail_ah.unwrap() - tails[2]).abs() < 1e-12, "median of 1, 2, 3");
        assert!((records[5].stated_tail_ah.unwrap() - tails[3]).abs() < 1e-12, "median of 2, 3, 4 (partial)");
        assert!(tails.windows(2).all(|w| w[1] < w[0]), "a cell that falls ever faster: {tails:?}");
        // A cell cycled at 2 and 4 A: each takes the tails of the discharges at its own current (at 4 A the same
        // fall of the voltage over the same time holds twice the charge), while one at a current none before
        // ran at takes those of any.
        let at = |a: f64, stretch: f64| {
            let r = linear_at(a, stretch, 0.0);
            linear_at(a, stretch, r.charge_to_v_ah(2.7).unwrap())
        };
        let mut mixed =
            [at(2.0, 1.3), at(4.0, 1.3), at(2.0, 1.2), at(4.0, 1.2), at(2.0, 1.1), at(4.0, 1.1), at(1.0, 1.0)];
        let tails: Vec<f64> = mixed.iter().map(tail).collect();
        set_stated_tails(mixed.iter_mut(), Some(&sc), 2.5);
        assert!((mixed[4].stated_tail_ah.unwrap() - 0.5 * (tails[0] + tails[2])).abs() < 1e-12, "2 A: of 0 and 2");
        assert!((mixed[5].stated_tail_ah.unwrap() - 0.5 * (tails[1] + tails[3])).abs() < 1e-12, "4 A: of 1 and 3");
        // 3 and 5 at 4 A, 4 at 2 A: the median is 5's, the smaller of the two at 4 A.
        assert!((mixed[6].stated_tail_ah.unwrap() - tails[5]).abs() < 1e-12, "1 A: the median of 3, 4, 5");
        assert!(tails[1] > 1.9 * tails[0]);
        // A discharge at 2 A over its first quarter and 4 A after is taken at 2 A, as known by then.
        let mut late = at(2.0, 1.0);
        let quarter_s = late.load_on_s + 0.25 * late.discharge_s().unwrap();
        for s in late.samples.iter_mut().filter(|s| s.t_s > quarter_s + 10.0 && s.current_a > 1.0) {
            s.current_a = 4.0;
        }
        let mut with_late: Vec<CellRecord> = mixed[..6].to_vec();
        with_late.push(late);
        set_stated_tails(with_late.iter_mut(), Some(&sc), 2.5);
        assert!((with_late[6].stated_tail_ah.unwrap() - tails[2]).abs() < 1e-12, "2 A: the median of 0, 2, 4");
        // Stated to the cut-off: no tail anywhere.
        let own = StatedCapacity { voltage_v: 2.5, median_gap_ah: 0.0, cutoff_median_gap_ah: 0.0, records: 3 };
        set_stated_tails(records.iter_mut(), Some(&own), 2.5);
        assert!(records.iter().all(|r| r.stated_tail_ah.is_none()));
    }
}
