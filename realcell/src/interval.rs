//! Prediction intervals that hold as the cell ages (issue 18 item 6): the 90 % interval of every end-of-
//! discharge and capacity prediction is the calibrator's own (from its parameter interval, the filter's
//! covariance) widened by a model-error term learned from how the method's predictions fared on the last
//! discharges that have ended.
//!
//! A calibrator's covariance speaks of sensor noise and of what the readings cannot tell apart; on a real
//! cell the model's own error dominates, and it grows as the cell ages away from the cycles the method was
//! set up on (the validation cycles). So each discharge's interval half-width, per side, is
//! `sqrt((s w)^2 + (a x)^2)`: `w` the calibrator's own half-width on that side, `x` the size of the
//! prediction (the predicted duration of the discharge from the load-on for an end of discharge, the
//! predicted capacity for a capacity), and `(s, a)` chosen on the [`WINDOW`] discharges before it that have
//! ended (the validation cycles at first, then each judged discharge once the cycler has measured it, as a
//! BMS learns its own error): the pair that covers [`COVER`] of their scored predictions (with the
//! finite-sample rank of split conformal prediction) with the narrowest intervals. The end of discharge has
//! one pair per share of the discharge the scores read (10, 50, 90 %), each reading taking the one nearest
//! the share it predicts has passed. Each kind's widening is then scaled online by how the intervals
//! before fared ([`Adapt`]: adaptive conformal inference, from the first judged discharge on), so that a
//! model error that drifts as the cell ages does not leave the window's rank behind. No look-ahead: a
//! discharge's own outcome never sets its interval. Methods without an interval of their own get the
//! model-error term alone. The learning itself is [`bcal_calib::widening`], which a live stream shares.

use crate::predict::Predicted;
use crate::record::CellRecord;
use crate::run::CycleRun;
use crate::score::{share_bin, CAPACITY_FRACTIONS_PCT, EOD_FRACTIONS_PCT};
pub use bcal_calib::widening::{start_half, Adapt, Outcome, Widening, COVER, OWN_FACTORS, WINDOW};
use serde::Serialize;

/// The widenings one discharge ran with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct DischargeWidening {
    pub cycle: u32,
    /// For the end of discharge, one per share of the discharge the scores read ([`EOD_FRACTIONS_PCT`]): a
    /// reading takes the one nearest the share of the discharge it predicts has passed.
    pub eod: [Widening; 3],
    pub capacity: Widening,
}

fn own_halves(p: &Predicted) -> Option<(f64, f64, f64)> {
    let v = p.value?;
    let (below, above) = match (p.lo, p.hi) {
        (Some(lo), Some(hi)) => ((v - lo).max(0.0), (hi - v).max(0.0)),
        _ => (0.0, 0.0),
    };
    Some((v, below, above))
}

/// What a discharge's start adds to the half-width of its end predicted at each step ([`start_half`]: its
/// starting charge's spread under the step's qMobile, over its current at the load-on).
fn start_halves(r: &CellRecord, run: &CycleRun) -> Vec<f64> {
    let at = r.start_share_sd.zip(r.load_on_current_a());
    run.steps.iter().map(|s| at.map_or(0.0, |(sd, i)| start_half(sd, s.estimate.q_mobile_c, i))).collect()
}

/// The scored predictions of one finished discharge: (end of discharge, capacity against the data).
pub(crate) fn outcomes(r: &CellRecord, run: &CycleRun) -> (Vec<Outcome>, Vec<Outcome>) {
    outcomes_with(r, run, &start_halves(r, run))
}

/// [`outcomes`] with each step's start term given ([`start_halves`]).
fn outcomes_with(r: &CellRecord, run: &CycleRun, starts: &[f64]) -> (Vec<Outcome>, Vec<Outcome>) {
    let (mut eod, mut cap) = (Vec::new(), Vec::new());
    let at = |f: u32| r.reading_at_fraction(f64::from(f) / 100.0).filter(|&k| k < run.steps.len());
    if let Some(m) = r.eod_s {
        for f in EOD_FRACTIONS_PCT {
            let Some(k) = at(f) else { continue };
            if let Some((value, below, above)) = own_halves(&run.steps[k].eod) {
                eod.push(Outcome {
                    value,
                    below,
                    above,
                    size: (value - r.load_on_s).max(1.0),
                    measured: m,
                    fraction: f,
                    start: starts[k],
                });
            }
        }
    }
    // A discharge from a partial charge delivers less than the cell holds (a start at 25 % of full: three
    // quarters of its capacity "missed", which made every later capacity interval hundreds of % wide).
    if let Some(m) = r.data_capacity_ah.filter(|_| !r.partial_start_seen) {
        for f in CAPACITY_FRACTIONS_PCT {
            let Some(k) = at(f) else { continue };
            if let Some((value, below, above)) = own_halves(&run.steps[k].capacity) {
                let size = value.abs().max(1e-6);
                cap.push(Outcome { value, below, above, size, measured: m, fraction: f, start: 0.0 });
            }
        }
    }
    (eod, cap)
}

fn widen(p: &mut Predicted, w: &Widening, size: impl Fn(f64) -> f64, start: f64) {
    let Some((v, below, above)) = own_halves(p) else { return };
    let x = size(v);
    p.lo = Some(v - w.half(below, x, start));
    p.hi = Some(v + w.half(above, x, start));
}

/// Sets the intervals of `runs` (along `records`, in order) from the errors of the discharges before each:
/// `history` holds the method's runs on the discharges before `records` (the validation cycles), whose
/// intervals are left as they are. Returns the widening each discharge of `records` ran with.
pub fn calibrate_intervals(
    history: &[(&CellRecord, &CycleRun)],
    records: &[CellRecord],
    runs: &mut [CycleRun],
) -> Vec<DischargeWidening> {
    let mut past: Vec<(Vec<Outcome>, Vec<Outcome>)> =
        history.iter().map(|(r, run)| outcomes(r, run)).filter(|(e, c)| !e.is_empty() || !c.is_empty()).collect();
    let mut out = Vec::with_capacity(records.len());
    let (mut adapt_eod, mut adapt_cap) = ([Adapt::default(); 3], Adapt::default());
    for (r, run) in records.iter().zip(runs.iter_mut()) {
        let recent = &past[past.len().saturating_sub(WINDOW)..];
        let eod_past: Vec<Outcome> = recent.iter().flat_map(|p| p.0.iter().copied()).collect();
        let cap_past: Vec<Outcome> = recent.iter().flat_map(|p| p.1.iter().copied()).collect();
        // The end of discharge per share of the discharge: a filter's own interval narrows as the discharge
        // goes on while the model's error near the knee grows, so one widening for all would cover early
        // predictions too often and late ones too rarely (60 % at 90 % of B0005's discharges, pooled).
        let eod: [Widening; 3] = std::array::from_fn(|b| {
            let at: Vec<Outcome> = eod_past.iter().filter(|o| o.fraction == EOD_FRACTIONS_PCT[b]).copied().collect();
            adapt_eod[b].scaled(Widening::learn(&at, recent.len()))
        });
        let cap = adapt_cap.scaled(Widening::learn(&cap_past, recent.len()));
        // The outcome is taken with the calibrator's own bounds, before this widening.
        let starts = start_halves(r, run);
        let own = outcomes_with(r, run, &starts);
        for (s, start) in run.steps.iter_mut().zip(starts) {
            let load_on = r.load_on_s;
            if let Some(v) = s.eod.value {
                let b = share_bin(load_on, s.t_s, v);
                widen(&mut s.eod, &eod[b], |v| (v - load_on).max(1.0), start);
            }
            widen(&mut s.capacity, &cap, |v| v.abs().max(1e-6), 0.0);
        }
        for (b, a) in adapt_eod.iter_mut().enumerate() {
            a.update(&eod[b], own.0.iter().filter(|o| o.fraction == EOD_FRACTIONS_PCT[b]));
        }
        adapt_cap.update(&cap, &own.1);
        if !own.0.is_empty() || !own.1.is_empty() {
            past.push(own);
        }
        out.push(DischargeWidening { cycle: r.cycle, eod, capacity: cap });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A synthetic sequence: every discharge predicts 1.0 Ah with an own interval of +-1 mAh (far too
    /// narrow), and the cell delivers 1.0 Ah plus an error spread evenly over +-50 mAh.
    fn sequence(n: usize, seed: u64) -> (Vec<CellRecord>, Vec<CycleRun>) {
        let mut x = seed;
        let mut records = Vec::new();
        let mut runs = Vec::new();
        for k in 0..n {
            // A small LCG: deterministic, no dependency.
            x = x.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            let u = (x >> 11) as f64 / (1u64 << 53) as f64;
            let none = Predicted { value: None, lo: None, hi: None };
            let own = Predicted { value: Some(1.0), lo: Some(0.999), hi: Some(1.001) };
            let (record, run) = crate::record::test_discharge(k as u32 + 1, 1.0 + 0.1 * (u - 0.5), |_| none, own);
            records.push(record);
            runs.push(run);
        }
        (records, runs)
    }

    fn covered_at_half(r: &CellRecord, run: &CycleRun) -> bool {
        let p = run.steps[r.reading_at_fraction(0.5).unwrap()].capacity;
        let m = r.data_capacity_ah.unwrap();
        p.lo.unwrap() <= m && m <= p.hi.unwrap()
    }

    /// `n` simulated 2 A discharges to 2.5 V (the simulator's own integrator and sensor: 3 mV of noise, 9-19 s
    /// sampling, a minute's rest before the load), the k-th from `soc0(k)` of a full charge and noise seed
    /// `seed + k`, each followed by the model pinned at the cell's truth.
    fn pinned_discharges(n: usize, soc0: impl Fn(usize) -> f64, seed: u64) -> (Vec<CellRecord>, Vec<CycleRun>) {
        use crate::run::{checkpoints, run_cycle_with, Knee, Streaming};
        use bcal_common::battery::Degradation;
        use bcal_common::measured::{ScenarioConfig, TrackerSpec};
        let cfg = ScenarioConfig { cutoff_v: 2.5, ..ScenarioConfig::default() };
        let spec = TrackerSpec { cutoff_v: 2.5, ..TrackerSpec::default() };
        let truth = Degradation { q_mobile_c: 7400.0, r_o_ohm: 0.12 };
        let records: Vec<CellRecord> = (0..n)
            .map(|k| crate::testing::simulated_record(&cfg, truth, soc0(k), seed + k as u64, k as u32 + 1))
            .collect();
        let pinned = Streaming::Pinned { spec, d: truth };
        let runs = records
            .iter()
            .map(|r| run_cycle_with(&pinned, r, 2.5, Knee::default(), &[1.0], Some(&checkpoints(r))).remove(0))
            .collect();
        (records, runs)
    }

    /// `runs` with their intervals learned: the first `history` discharges the history, the rest judged.
    fn with_intervals(records: &[CellRecord], runs: &[CycleRun], history: usize) -> Vec<CycleRun> {
        let mut runs = runs.to_vec();
        let (before, judged) = runs.split_at_mut(history);
        let hist: Vec<(&CellRecord, &CycleRun)> = records.iter().zip(before.iter()).collect();
        calibrate_intervals(&hist, &records[history..], judged);
        runs
    }

    #[test]
    fn intervals_learned_on_the_discharges_before_cover_about_ninety_percent_of_a_sequence() {
        let (hist_r, hist_runs) = sequence(10, 1);
        let hist: Vec<(&CellRecord, &CycleRun)> = hist_r.iter().zip(&hist_runs).collect();
        let (records, mut runs) = sequence(200, 2);
        let own_cover = records.iter().zip(&runs).filter(|(r, u)| covered_at_half(r, u)).count();
        assert!(own_cover < 10, "the own intervals are too narrow to start with: {own_cover}");
        let w = calibrate_intervals(&hist, &records, &mut runs);
        let cover = records.iter().zip(&runs).filter(|(r, u)| covered_at_half(r, u)).count() as f64 / 2.0;
        assert!((82.0..=97.0).contains(&cover), "coverage {cover} %");
        assert!(w.iter().all(|d| d.capacity.learned_on == WINDOW), "{:?}", &w[..2]);
    }

    /// Simulated 2 A discharges (the simulator's own integrator and sensor: 3 mV of noise, 9-19 s sampling, a
    /// minute's rest before the load) followed by the model pinned at the cell's truth, so that only the start
    /// read off the rest errs: every third starts at 40 % of a full charge, on the flat of the voltage curve,
    /// where that noise moves the end by tens of seconds; the full starts end where predicted. With each
    /// record's start spread the part-charged ends fall inside their 90 % intervals; without it the learned
    /// model term must stand for them, which widens every full start's interval and still misses more.
    #[test]
    fn a_start_read_off_the_plateau_of_the_curve_widens_its_own_interval() {
        let part = |k: usize| k % 3 == 2;
        let (mut records, runs) = pinned_discharges(45, |k| if part(k) { 0.4 } else { 1.0 }, 40);
        // (part-charged ends covered, of; the full ones' median half-width at half, s)
        let judge = |records: &[CellRecord]| {
            let runs = with_intervals(records, &runs, 12);
            let (mut hit, mut of, mut full_half) = (0, 0, Vec::new());
            for (k, (r, u)) in records.iter().zip(&runs).enumerate().skip(12) {
                for f in EOD_FRACTIONS_PCT {
                    let p = u.steps[r.reading_at_fraction(f64::from(f) / 100.0).unwrap()].eod;
                    let (m, lo, hi) = (r.eod_s.unwrap(), p.lo.unwrap(), p.hi.unwrap());
                    if part(k) {
                        of += 1;
                        hit += usize::from(lo <= m && m <= hi);
                    } else if f == 50 {
                        full_half.push(0.5 * (hi - lo));
                    }
                }
            }
            (hit, of, bcal_common::stats::median(&mut full_half).unwrap())
        };
        let without = judge(&records);
        crate::record::set_start_spreads(records.iter_mut(), &bcal_common::battery::BatteryModel::default());
        assert!(records.iter().enumerate().all(|(k, r)| part(k) == (r.start_share_sd.unwrap() > 0.003)));
        let with = judge(&records);
        // 33 of 33 and 8 s, against 24 of 33 and 192 s without.
        assert!(with.0 as f64 >= 0.8 * with.1 as f64, "with the start's spread {} of {} covered", with.0, with.1);
        assert!(without.0 < with.0, "without it {} of {} covered", without.0, without.1);
        assert!(with.2 < 0.2 * without.2, "full starts' half-width {} s, {} s without", with.2, without.2);
    }

    /// Simulated 2 A discharges followed by the model pinned at the cell's truth, one of them started at 25 % of
    /// full: the charge it delivers is a quarter of the cell's capacity, an error its neighbours' rests name
    /// (no look-ahead) and the capacity intervals must not learn (the blind "B0049"'s cycle 13 made every later
    /// capacity interval +-1.6 Ah wide on a 1.8 Ah cell).
    #[test]
    fn a_part_charged_start_teaches_the_capacity_intervals_nothing() {
        let part = 14;
        let (mut records, runs) = pinned_discharges(24, |k| if k == part { 0.25 } else { 1.0 }, 70);
        for r in &mut records {
            r.data_capacity_ah = r.eod_s.map(|end_s| bcal_calib::eod::charge_to_ah(&r.samples, end_s));
        }
        crate::record::set_short_starts_seen(records.iter_mut());
        let seen: Vec<usize> = (0..records.len()).filter(|&k| records[k].partial_start_seen).collect();
        assert_eq!(seen, vec![part], "the rests before each name the part-charged start alone");
        // The widest capacity interval at half after the part-charged start, % of its prediction.
        let widest_after = |records: &[CellRecord]| {
            let runs = with_intervals(records, &runs, 8);
            (part + 1..records.len())
                .map(|k| {
                    let p = runs[k].steps[records[k].reading_at_fraction(0.5).unwrap()].capacity;
                    100.0 * (p.hi.unwrap() - p.lo.unwrap()) / (2.0 * p.value.unwrap())
                })
                .fold(0.0, f64::max)
        };
        let kept_apart = widest_after(&records);
        records[part].partial_start_seen = false;
        let learned = widest_after(&records);
        // 0.2 %, against 86 % learned from.
        assert!(kept_apart < 2.0, "the widest half-width after it {kept_apart:.2} % ({learned:.1} % if learned)");
        assert!(learned > 20.0, "learned from, it widens them: {learned:.1} %");
    }

    #[test]
    fn a_discharge_s_own_outcome_never_sets_its_interval() {
        let (hist_r, hist_runs) = sequence(10, 3);
        let hist: Vec<(&CellRecord, &CycleRun)> = hist_r.iter().zip(&hist_runs).collect();
        let (records, runs) = sequence(20, 4);
        let mut a = runs.clone();
        calibrate_intervals(&hist, &records, &mut a);
        // Discharge 12 turns out far off: its own interval and every one before it stay as they were; the
        // next one learns from it.
        let mut changed = records.clone();
        changed[12].data_capacity_ah = Some(5.0);
        let mut b = runs.clone();
        calibrate_intervals(&hist, &changed, &mut b);
        let half = |r: &CellRecord, u: &CycleRun| u.steps[r.reading_at_fraction(0.5).unwrap()].capacity;
        for k in 0..=12 {
            assert_eq!(half(&records[k], &a[k]), half(&changed[k], &b[k]), "discharge {k}");
        }
        assert!(half(&changed[13], &b[13]).hi.unwrap() > half(&records[13], &a[13]).hi.unwrap());
    }
}
