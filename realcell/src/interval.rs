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
pub use bcal_calib::widening::{Adapt, Outcome, Widening, COVER, OWN_FACTORS, WINDOW};
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

/// The scored predictions of one finished discharge: (end of discharge, capacity against the data).
pub(crate) fn outcomes(r: &CellRecord, run: &CycleRun) -> (Vec<Outcome>, Vec<Outcome>) {
    let (mut eod, mut cap) = (Vec::new(), Vec::new());
    let step = |f: u32| r.reading_at_fraction(f64::from(f) / 100.0).and_then(|k| run.steps.get(k));
    if let Some(m) = r.eod_s {
        for f in EOD_FRACTIONS_PCT {
            if let Some((value, below, above)) = step(f).and_then(|s| own_halves(&s.eod)) {
                eod.push(Outcome {
                    value,
                    below,
                    above,
                    size: (value - r.load_on_s).max(1.0),
                    measured: m,
                    fraction: f,
                });
            }
        }
    }
    if let Some(m) = r.data_capacity_ah {
        for f in CAPACITY_FRACTIONS_PCT {
            if let Some((value, below, above)) = step(f).and_then(|s| own_halves(&s.capacity)) {
                cap.push(Outcome { value, below, above, size: value.abs().max(1e-6), measured: m, fraction: f });
            }
        }
    }
    (eod, cap)
}

fn widen(p: &mut Predicted, w: &Widening, size: impl Fn(f64) -> f64) {
    let Some((v, below, above)) = own_halves(p) else { return };
    let x = size(v);
    p.lo = Some(v - w.half(below, x));
    p.hi = Some(v + w.half(above, x));
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
        let own = outcomes(r, run);
        for s in &mut run.steps {
            let load_on = r.load_on_s;
            if let Some(v) = s.eod.value {
                let b = share_bin(load_on, s.t_s, v);
                widen(&mut s.eod, &eod[b], |v| (v - load_on).max(1.0));
            }
            widen(&mut s.capacity, &cap, |v| v.abs().max(1e-6));
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
