//! Across discharges (issue 18 item 5): what each discharge of a real cell starts from, as a prior with an
//! honest width learned from the cell's own history.
//!
//! - **Mean.** The fit the previous discharge hands on ([`crate::carry`]: its end fit, once that discharge
//!   had ended), moved by
//!   the change the cell's lifetime model expects since then: the capacity fade, and the capacity a rest
//!   gives back (NASA cells regain capacity after long rests and lose it again over the next discharges;
//!   [`bcal_doctor::lifetime`]). qMobile follows the expected relative change of the capacity; Ro is carried.
//! - **Width.** Fitted on the training cycles: each consecutive pair of carried fits gives a residual, the
//!   fit of discharge k minus its prior mean from discharge k - 1, in each parameter (z units of the
//!   calibrator's ranges). Its variance is modelled as `a + b h(rest)`, `h(rest) = ln(max(rest, usual) /
//!   usual)` (zero after the usual rest, growing with a longer one), fitted by least squares on the squared
//!   residuals with a, b >= 0. A rest longer than any the training cycles saw is also covered by the
//!   lifetime model's own uncertainty of the jump it predicts, added in quadrature, so the width grows with
//!   the rest even where the training cycles held no long pause. Nothing in it is set per cell.
//!
//! Pure functions of the records, their fits and their start times: nothing here prints or simulates.

use crate::record::CellRecord;
pub use bcal_calib::prior_width::{CurrentSlope, RestWidth, LONG_REST_S, MIN_PAIRS, MIN_SD_Z};
use bcal_common::battery::Degradation;
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::tracker::TrackerSpec;
use bcal_doctor::lifetime::{Carry, Condition, LifeTracker, LifetimeModel};
use bcal_doctor::read::RecordStart;
use bcal_doctor::Discharge;
use serde::Serialize;
use std::collections::BTreeMap;

/// The rest before each record, s: the time from the end of the record of the cycle before (when present,
/// both start times are known and on one logger session's clock) to this record's start. Records with an unknown rest are absent. The
/// cycle before is one step of the data's own numbering back, the step its consecutive records take most
/// (1 for NASA's discharges; 2 for a log that numbers charges and discharges alike and keeps only the
/// discharges, 1, 3, 5, ..., which lost every rest while the step was taken to be 1), over every record
/// read (`starts`): a record after one that was not read (a missing file) has no known rest.
pub fn rests_before(records: &[&Discharge], starts: &[RecordStart]) -> BTreeMap<u32, f64> {
    let start_of: BTreeMap<u32, (f64, u32)> = starts.iter().map(|s| (s.cycle, (s.start_s, s.session))).collect();
    // (end, session) of each record whose start is known.
    let end_of: BTreeMap<u32, (f64, u32)> = records
        .iter()
        .filter_map(|d| {
            let (s, session) = start_of.get(&d.cycle)?;
            let span = d.time_s.last()? - d.time_s.first()?;
            Some((d.cycle, (s + span, *session)))
        })
        .collect();
    // The step of every record read (`starts`), not of the ones passed: a subset that left some out would
    // take a longer step, and a rest spanning a discharge.
    let step = bcal_doctor::read::numbering_step(starts);
    let mut out = BTreeMap::new();
    for d in records {
        let (Some((start, session)), Some((prev_end, prev_session))) =
            (start_of.get(&d.cycle), d.cycle.checked_sub(step).and_then(|c| end_of.get(&c)))
        else {
            continue;
        };
        // Two sessions of a logger that restarted: clocks that do not agree, no rest.
        if session != prev_session {
            continue;
        }
        let rest = start - prev_end;
        // A clock that restarts per record gives overlaps: no schedule, no rest.
        if rest >= -60.0 {
            out.insert(d.cycle, rest.max(0.0));
        }
    }
    out
}

/// What one discharge starts from.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Prior {
    /// The prior mean: the previous fit moved by the expected change.
    pub mean: Degradation,
    /// The previous discharge's offline fit itself (the previous-cycle reference).
    pub previous: Degradation,
    /// Standard deviation per parameter, z units (None: no history to learn it from).
    pub sd_z: Option<[f64; 2]>,
    /// Its part after the usual rest (the same gap), z units: what a calibrator's prior width factor scales.
    pub usual_sd_z: Option<[f64; 2]>,
    /// The rest before this discharge, s (None: unknown).
    pub rest_before_s: Option<f64>,
    /// The relative change of capacity the lifetime model expects since the previous discharge.
    pub expected_capacity_change: f64,
}

/// Follows the cell's life discharge by discharge and gives each its [`Prior`].
pub struct PriorWalk<'a> {
    spec: &'a TrackerSpec,
    life: Option<LifeTracker>,
    width: RestWidth,
    /// Whether each prior's qMobile moves with the current ([`CurrentSlope`]) ...
    moves_with_current: bool,
    /// ... and what the walk has learned of how.
    slope: CurrentSlope,
    /// The previous discharge's current at its load-on, A ([`CellRecord::load_on_current_a`]).
    last_load_on_a: Option<f64>,
    /// The previous discharge: its cycle, fit, data capacity and mean current, A.
    last: Option<(u32, Degradation, Option<f64>, f64)>,
}

impl<'a> PriorWalk<'a> {
    pub fn new(spec: &'a TrackerSpec, life: Option<&LifetimeModel>, width: RestWidth) -> Self {
        let slope = CurrentSlope::default();
        let life = life.map(|m| LifeTracker::new(*m));
        Self { spec, life, width, moves_with_current: false, slope, last_load_on_a: None, last: None }
    }

    /// The walk with each prior's qMobile moved with the current's move from the last discharge, as the
    /// discharges it has observed show ([`CurrentSlope`]).
    pub fn moving_with_current(self) -> Self {
        Self { moves_with_current: true, ..self }
    }

    /// What it has learned of the carried qMobile's move with the current.
    pub fn current_slope(&self) -> CurrentSlope {
        self.slope
    }

    /// The prior of `record` (rest before it `rest_s`), from what the walk has seen; `first` is the prior
    /// of the very first discharge (no history).
    pub fn prior(&self, record: &CellRecord, rest_s: Option<f64>, first: &Degradation) -> Prior {
        let mut p = self.unmoved_prior(record, rest_s, first);
        if let (Some(now_a), Some(before_a)) = (record.load_on_current_a(), self.last_load_on_a) {
            if self.moves_with_current && self.last.is_some() {
                p.mean.q_mobile_c = self.slope.moved(p.mean.q_mobile_c, now_a, before_a).unwrap_or(p.mean.q_mobile_c);
            }
        }
        p
    }

    /// [`PriorWalk::prior`] before the current's move: the lifetime model's alone.
    fn unmoved_prior(&self, record: &CellRecord, rest_s: Option<f64>, first: &Degradation) -> Prior {
        let Some((cycle, prev, prev_cap, prev_current_a)) = self.last else {
            return Prior {
                mean: *first,
                previous: *first,
                sd_z: None,
                usual_sd_z: None,
                rest_before_s: rest_s,
                expected_capacity_change: 0.0,
            };
        };
        // The ambient is the test's setting, known before the discharge; its current is known only as it
        // runs (its mean to the cut-off, once it has ended), so the lifetime model assumes the last one's, as a
        // live stream does.
        let at = Condition { current_a: prev_current_a, ..condition(record) };
        let carry = self.life.as_ref().map_or(Carry::NONE, |t| t.carry(record.cycle, rest_s, at, prev_cap));
        let mean = carry.mean(&prev);
        let gap = record.cycle.saturating_sub(cycle);
        let span = self.spec.q_mobile_range_c[1] - self.spec.q_mobile_range_c[0];
        let sd_z = self.width.fitted().then(|| carry.widen_z(self.width.sd_z(rest_s, gap), prev.q_mobile_c, span));
        let usual_sd_z = self.width.fitted().then(|| self.width.sd_z(None, gap));
        Prior {
            mean,
            previous: prev,
            sd_z,
            usual_sd_z,
            rest_before_s: rest_s,
            expected_capacity_change: carry.ratio - 1.0,
        }
    }

    /// Takes the discharge `record` once it has ended: its offline fit and measured capacity. A record cut
    /// short measures none and hands on the fit carried into it ([`crate::carry::over_cut_short`]): with it
    /// goes the capacity that fit was measured with, so the discharges after a block cut short still move by
    /// the fade over the block (they stood at the block's first prior: the fade alone, B0042-like cell of
    /// 2026-11-29, five discharges).
    pub fn observe(&mut self, record: &CellRecord, rest_s: Option<f64>, fit: &Degradation) {
        if let Some((cycle, _, _, _)) = self.last {
            let x = current_move(record, self.last_load_on_a)
                .filter(|_| cycle + 1 == record.cycle && record.measured_its_charge());
            if let Some(x) = x {
                let p = self.unmoved_prior(record, rest_s, fit);
                self.slope.push(x, (fit.q_mobile_c / p.mean.q_mobile_c).ln());
            }
        }
        if let Some(t) = self.life.as_mut() {
            t.advance_to(record.cycle, rest_s, condition(record));
            if let Some(c) = record.data_capacity_ah {
                t.observe(c);
            }
        }
        self.last_load_on_a = record.load_on_current_a();
        let capacity_ah = record.data_capacity_ah.or_else(|| self.last.and_then(|l| l.2));
        self.last = Some((record.cycle, *fit, capacity_ah, record.current_a));
    }
}

/// The log of the ratio of `record`'s current at its load-on ([`CellRecord::load_on_current_a`]) to the last
/// discharge's at its own (the same reading of each: a square wave's loaded readings at their level, not a mean
/// over its time); None without both.
fn current_move(record: &CellRecord, last_load_on_a: Option<f64>) -> Option<f64> {
    bcal_calib::prior_width::current_move(record.load_on_current_a()?, last_load_on_a?)
}

fn condition(r: &CellRecord) -> Condition {
    Condition { ambient_c: r.ambient_k - bcal_doctor::record::CELSIUS_TO_KELVIN, current_a: r.current_a }
}

/// The width learned from the training records and their fits (in order), with the residual of every
/// consecutive pair in z units and the rest before it.
pub fn learn_width(
    spec: &TrackerSpec,
    life: Option<&LifetimeModel>,
    train: &[CellRecord],
    fits: &[(Degradation, ModelExtension)],
    rests: &BTreeMap<u32, f64>,
) -> RestWidth {
    let mut known: Vec<f64> = train.iter().filter_map(|r| rests.get(&r.cycle).copied()).collect();
    let usual_rest_s = bcal_common::stats::median(&mut known).unwrap_or(0.0);
    let probe = RestWidth { usual_rest_s, ..RestWidth::fallback() };
    let mut walk = PriorWalk::new(spec, life, probe);
    let mut residuals = Vec::new();
    let mut long = 0;
    for (r, (fit, _)) in train.iter().zip(fits) {
        let rest = rests.get(&r.cycle).copied();
        let consecutive = walk.last.is_some_and(|(c, _, _, _)| c + 1 == r.cycle);
        // A record cut short or started short measured no fit of its own (it hands on the one carried into
        // it): no pair.
        if consecutive && r.measured_its_charge() {
            let p = walk.prior(r, rest, fit);
            let (z, m) = (spec.to_z(fit), spec.to_z(&p.mean));
            residuals.push((probe.h(rest), [z[0] - m[0], z[1] - m[1]]));
            long += usize::from(rest.is_some_and(|x| x > LONG_REST_S));
        }
        walk.observe(r, rest, fit);
    }
    RestWidth::fit(&residuals, usual_rest_s, long)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(cycle: u32, rest_s: Option<f64>, capacity_ah: f64) -> CellRecord {
        CellRecord {
            cell: "T".into(),
            cycle,
            source: "t".into(),
            load_on_s: 10.0,
            eod_s: Some(3000.0),
            current_a: 2.0,
            data_capacity_ah: Some(capacity_ah),
            stated_capacity_ah: None,
            ambient_k: 297.15,
            rest_before_s: rest_s,
            current_before_a: None,
            partial_start: false,
            short_start_seen: false,
            partial_start_seen: false,
            start_share_sd: None,
            stated_tail_ah: None,
            samples: Vec::new(),
        }
    }

    /// A record whose load comes on at 10 s at `current_a` (its readings, at rest then loaded, as a cycler's).
    fn at_current(cycle: u32, current_a: f64) -> CellRecord {
        let reading = |t_s: f64, current_a: f64| bcal_common::measured::scenario::Sample {
            t_s,
            voltage_v: 4.0 - 0.1 * current_a,
            current_a,
            temperature_k: 297.15,
            request: bcal_common::measured::scenario::Request::Unknown,
        };
        let samples =
            vec![reading(0.0, 0.0), reading(10.0, current_a), reading(25.0, current_a), reading(60.0, current_a)];
        CellRecord { current_a, samples, ..record(cycle, None, 1.8) }
    }

    /// A cell cycled at 1 and 4 A whose end fits sit 1.3 % above its qMobile at 1 A and 0.2 % at 4 A (the blind
    /// "B0038"'s): once three pairs have moved their current, a discharge at another current than the last
    /// one's starts from the last fit moved by what the moves before it showed, to within the fits' own scatter;
    /// before that, and on a cell at one current throughout, every prior is the last fit to the bit.
    #[test]
    fn the_carried_fit_moves_with_the_current_once_the_moves_before_it_show_how() {
        let spec = TrackerSpec::default();
        let currents = [1.0, 4.0, 4.0, 1.0, 4.0, 1.0, 1.0, 4.0, 1.0, 4.0, 4.0, 1.0];
        let fit_at = |k: usize, a: f64| {
            let wobble = 1.0 + 0.0005 * if k.is_multiple_of(2) { 1.0 } else { -1.0 };
            Degradation { q_mobile_c: 7000.0 * if a < 2.0 { 1.013 } else { 1.002 } * wobble, r_o_ohm: 0.12 }
        };
        let mut walk = PriorWalk::new(&spec, None, RestWidth::fallback()).moving_with_current();
        let mut plain = PriorWalk::new(&spec, None, RestWidth::fallback());
        let first = fit_at(0, currents[0]);
        for (k, &a) in currents.iter().enumerate() {
            let r = at_current(k as u32 + 1, a);
            let (p, q) = (walk.prior(&r, None, &first), plain.prior(&r, None, &first));
            if walk.current_slope().learned().is_none() {
                assert_eq!(p, q, "discharge {}: no slope yet, the last fit as it is", k + 1);
            } else if a != currents[k - 1] {
                let want = fit_at(k, a).q_mobile_c;
                let (moved, carried) = (p.mean.q_mobile_c / want - 1.0, q.mean.q_mobile_c / want - 1.0);
                assert!(
                    moved.abs() < 0.002 && carried.abs() > 0.009,
                    "discharge {} at {a} A: moved {moved:+.4}, carried as it was {carried:+.4}",
                    k + 1
                );
            }
            walk.observe(&r, None, &fit_at(k, a));
            plain.observe(&r, None, &fit_at(k, a));
        }
        let slope = walk.current_slope();
        assert_eq!((slope.pairs, slope.moved), (11, 8));
        let want = (1.002f64 / 1.013).ln() / 4f64.ln();
        assert!((slope.learned().unwrap() / want - 1.0).abs() < 0.1, "{slope:?} against {want}");

        let mut one = PriorWalk::new(&spec, None, RestWidth::fallback()).moving_with_current();
        let mut plain = PriorWalk::new(&spec, None, RestWidth::fallback());
        for k in 0..12 {
            let r = at_current(k + 1, 2.0 * (1.0 + 0.01 * f64::from(k % 3)));
            assert_eq!(one.prior(&r, None, &first), plain.prior(&r, None, &first));
            one.observe(&r, None, &fit_at(k as usize, 4.0));
            plain.observe(&r, None, &fit_at(k as usize, 4.0));
        }
        assert_eq!(one.current_slope().learned(), None, "a cell at one current learns no slope");
    }

    /// A capacity lifetime model that fades 3 mAh per discharge from 1.8 Ah at cycle 20, `per_ampere` Ah per A
    /// away from 2 A, regaining up to `amplitude` Ah over a rest of about 15 h.
    fn fading_life(per_ampere: f64, amplitude: f64) -> LifetimeModel {
        LifetimeModel {
            quantity: bcal_doctor::lifetime::Quantity::CapacityAh,
            intercept: 1.8,
            per_cycle: -0.003,
            reference_cycle: 20.0,
            per_kelvin: 0.0,
            per_ampere,
            reference: Condition { ambient_c: 24.0, current_a: 2.0 },
            amplitude,
            tau_rest_s: 54_720.0,
            decay_discharges: 5.0,
            usual_rest_s: 3_600.0,
            residual_sd: 0.004,
            jump_sd_fraction: 0.5,
        }
    }

    #[test]
    fn the_prior_mean_follows_the_recovery_after_a_long_rest_and_its_width_grows_with_it() {
        // A cell that fades 3 mAh per discharge and regains up to 65 mAh over a rest of about 15 h.
        let life = fading_life(0.0, 0.065);
        let spec = TrackerSpec::default();
        let width =
            RestWidth { a_z2: [1e-4; 2], b_z2: [4e-4, 0.0], usual_rest_s: 3_600.0, pairs: 20, long_rest_pairs: 2 };
        let mut walk = PriorWalk::new(&spec, Some(&life), width);
        let fit = Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.12 };
        for c in 1..=10 {
            walk.observe(&record(c, Some(3_600.0), 1.8 - 0.003 * f64::from(c)), Some(3_600.0), &fit);
        }
        let usual = walk.prior(&record(11, Some(3_600.0), 0.0), Some(3_600.0), &fit);
        let long = walk.prior(&record(11, Some(3.0 * LONG_REST_S), 0.0), Some(3.0 * LONG_REST_S), &fit);
        // After the usual rest the prior fades from the last fit; after three days it regains capacity, and
        // qMobile follows the capacity's relative change. Ro is carried.
        assert!(usual.mean.q_mobile_c < fit.q_mobile_c, "{usual:?}");
        assert!(long.mean.q_mobile_c > fit.q_mobile_c * 1.02, "{long:?}");
        assert!((long.mean.q_mobile_c / fit.q_mobile_c - 1.0 - long.expected_capacity_change).abs() < 1e-12);
        assert_eq!((long.previous, long.mean.r_o_ohm), (fit, fit.r_o_ohm));
        // The width grows with the rest (the learned term and the jump's own uncertainty), in qMobile only.
        let (su, sl) = (usual.sd_z.unwrap(), long.sd_z.unwrap());
        assert!(sl[0] > 2.0 * su[0] && (sl[1] - su[1]).abs() < 1e-12, "{su:?} {sl:?}");
        // Without a lifetime model the previous fit is carried as it is.
        let mut plain = PriorWalk::new(&spec, None, width);
        plain.observe(&record(10, None, 1.77), None, &fit);
        assert_eq!(plain.prior(&record(11, Some(3.0 * LONG_REST_S), 0.0), Some(3.0 * LONG_REST_S), &fit).mean, fit);
    }

    /// A discharge's own current is measured as it runs: its prior is the same whatever current it will
    /// draw, the lifetime model assuming the last discharge's (a cell whose capacity depends on the current).
    #[test]
    fn the_prior_does_not_know_the_current_the_discharge_will_draw() {
        let life = fading_life(-0.05, 0.0);
        let spec = TrackerSpec::default();
        let width = RestWidth { a_z2: [1e-4; 2], b_z2: [0.0; 2], usual_rest_s: 3_600.0, pairs: 20, long_rest_pairs: 0 };
        let mut walk = PriorWalk::new(&spec, Some(&life), width);
        let fit = Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.12 };
        walk.observe(&record(10, Some(3_600.0), 1.77), Some(3_600.0), &fit);
        let at = |current_a: f64| {
            let r = CellRecord { current_a, ..record(11, Some(3_600.0), 0.0) };
            walk.prior(&r, Some(3_600.0), &fit).mean
        };
        assert_eq!(at(1.0), at(4.0));
        // Carried at the last discharge's own current, the change the model expects from one discharge to the
        // next is its fade and recovery alone, whatever that current was.
        let mut fast = PriorWalk::new(&spec, Some(&life), width);
        fast.observe(&CellRecord { current_a: 4.0, ..record(10, Some(3_600.0), 1.77) }, Some(3_600.0), &fit);
        let after_fast = fast.prior(&record(11, Some(3_600.0), 0.0), Some(3_600.0), &fit).mean;
        assert!((after_fast.q_mobile_c - at(2.0).q_mobile_c).abs() < 1e-9, "{after_fast:?}");
    }

    /// After a block of discharges cut short (no capacity measured; each hands on the fit carried into it)
    /// the next prior moves by the fade over the whole block, as if the block had not been there.
    #[test]
    fn a_block_cut_short_still_fades_the_prior_after_it() {
        let life = fading_life(0.0, 0.0);
        let spec = TrackerSpec::default();
        let width = RestWidth { a_z2: [1e-4; 2], b_z2: [0.0; 2], usual_rest_s: 3_600.0, pairs: 20, long_rest_pairs: 0 };
        let fit = Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.12 };
        let walked = |cut_short: bool| {
            let mut walk = PriorWalk::new(&spec, Some(&life), width);
            walk.observe(&record(10, Some(3_600.0), 1.77), Some(3_600.0), &fit);
            if cut_short {
                for c in 11..=15 {
                    let r = CellRecord { eod_s: None, data_capacity_ah: None, ..record(c, Some(3_600.0), 0.0) };
                    walk.observe(&r, Some(3_600.0), &fit);
                }
            }
            walk.prior(&record(16, Some(3_600.0), 0.0), Some(3_600.0), &fit).mean
        };
        let (after_block, without) = (walked(true), walked(false));
        // Six discharges of 3 mAh fade from 1.77 Ah: 1 % of qMobile.
        assert!((without.q_mobile_c / fit.q_mobile_c - (1.77 - 0.018) / 1.77).abs() < 1e-9, "{without:?}");
        assert!((after_block.q_mobile_c - without.q_mobile_c).abs() < 1e-9, "{after_block:?} vs {without:?}");
    }

    /// The width is learned on consecutive pairs of measured fits: a record cut short hands on the fit carried
    /// into it and makes no pair (its residual against a prior that fades over the block would grow along it);
    /// the discharge after the block does.
    #[test]
    fn a_block_cut_short_makes_no_pairs_for_the_width() {
        let life = fading_life(0.0, 0.0);
        let spec = TrackerSpec::default();
        let fit = (Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.12 }, ModelExtension::default());
        let train: Vec<CellRecord> = (1..=20)
            .map(|c| {
                let r = record(c, Some(3_600.0), 1.8 - 0.003 * f64::from(c));
                if (11..=15).contains(&c) {
                    CellRecord { eod_s: None, data_capacity_ah: None, ..r }
                } else {
                    r
                }
            })
            .collect();
        let rests: BTreeMap<u32, f64> = (1..=20).map(|c| (c, 3_600.0)).collect();
        let width = learn_width(&spec, Some(&life), &train, &vec![fit.clone(); 20], &rests);
        // Pairs 2-10, 16 (after the block) and 17-20.
        assert_eq!(width.pairs, 14, "{width:?}");
    }

    #[test]
    fn rests_come_from_the_end_of_the_record_before() {
        let d = |cycle: u32| Discharge {
            cell: "T".into(),
            cycle,
            source: "t.csv".into(),
            ambient_k: 297.15,
            time_s: vec![0.0, 100.0, 1000.0],
            voltage_v: vec![4.2, 3.9, 3.0],
            current_a: vec![0.0, 2.0, 2.0],
            temperature_k: None,
            stated_capacity_ah: None,
        };
        let (a, b, c) = (d(1), d(2), d(4));
        let starts = [
            RecordStart { cycle: 1, start_s: 0.0, session: 0 },
            RecordStart { cycle: 2, start_s: 5000.0, session: 0 },
            RecordStart { cycle: 4, start_s: 9000.0, session: 0 },
        ];
        let r = rests_before(&[&a, &b, &c], &starts);
        assert_eq!(r.get(&2), Some(&4000.0));
        // The first record and one after a missing cycle have no known rest.
        assert!(!r.contains_key(&1) && !r.contains_key(&4));
        // A log that numbers charges and discharges alike keeps the discharges 1, 3, 5, 9 (7 not read): the
        // rest before each is from the end of the discharge two numbers back, none after the missing one.
        let (a, b, c, e) = (d(1), d(3), d(5), d(9));
        let starts = [1, 3, 5, 9].map(|cycle| RecordStart { cycle, start_s: 5000.0 * f64::from(cycle), session: 0 });
        let r = rests_before(&[&a, &b, &c, &e], &starts);
        assert_eq!((r.get(&3), r.get(&5)), (Some(&9000.0), Some(&9000.0)));
        assert!(!r.contains_key(&1) && !r.contains_key(&9), "{r:?}");
        // A logger that restarted after each discharge (a CSV's sessions, each clock set 100 s behind the last
        // one's end): no rest across two sessions, however the clocks fall.
        let (a, b, c) = (d(1), d(2), d(3));
        let starts = [(1, 0.0, 0), (2, 7000.0, 1), (3, 14000.0, 2)].map(|(cycle, start_s, session)| RecordStart {
            cycle,
            start_s,
            session,
        });
        assert!(rests_before(&[&a, &b, &c], &starts).is_empty());
    }
}
