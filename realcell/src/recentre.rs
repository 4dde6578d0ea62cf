//! `bcal calibrate`'s side of [`bcal_calib::recentre`]: each method's end-of-discharge predictions
//! recentred on the bias of its own last discharges (the validation cycles first, then every judged
//! discharge once it has ended), and served where the recentred ones beat the method's own on the last
//! discharges ([`tune::gate_runs`], the rule that gates every alternative; never right after a rest of more
//! than a day). The bias is learned on the method's own predictions, never on the recentred ones.

use crate::interval::outcomes;
use crate::record::CellRecord;
use crate::run::CycleRun;
use crate::tune::{self, Runs, Served};
use bcal_calib::recentre::{biases, shift_s, Outcome};

/// `runs` along `records` (in order) with every predicted end of discharge, and its interval, moved by the
/// bias of the discharges before it in the sequence.
fn recentred_along(records: &[&CellRecord], runs: &[&CycleRun]) -> Vec<CycleRun> {
    let mut ended: Vec<Vec<Outcome>> = Vec::new();
    records
        .iter()
        .zip(runs)
        .map(|(r, run)| {
            let b = biases(&ended);
            let mut out = (*run).clone();
            for s in &mut out.steps {
                if let Some(v) = s.eod.value {
                    s.eod = s.eod.shifted(shift_s(&b, r.load_on_s, s.t_s, v));
                }
            }
            let (eod, _) = outcomes(r, run);
            if !eod.is_empty() {
                ended.push(eod);
            }
            out
        })
        .collect()
}

/// A method's runs along the validation and judged cycles, recentred where that has earned it, and the
/// judged discharges where it did, per share.
pub fn serve(runs: &Runs, validation: &[CellRecord], judged: &[CellRecord]) -> (Runs, Served) {
    let records: Vec<&CellRecord> = validation.iter().chain(judged).collect();
    let all: Vec<&CycleRun> = runs.validation.iter().chain(&runs.judged).collect();
    let mut moved = recentred_along(&records, &all);
    let moved_judged = moved.split_off(runs.validation.len().min(moved.len()));
    tune::gate_runs(&Runs { validation: moved, judged: moved_judged }, runs, validation, judged)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::predict::Predicted;
    use crate::record::test_discharge;
    use bcal_calib::recentre::WINDOW;

    /// Discharges of 100 s whose predictions end `late_s(k)` seconds after the measured end, with a +-5 s
    /// interval; the first `n_val` are the validation cycles.
    fn sequence(n: usize, late_s: impl Fn(usize) -> f64) -> (Vec<CellRecord>, Runs) {
        let (mut records, mut runs) = (Vec::new(), Vec::new());
        for k in 0..n {
            let e = 100.0 + late_s(k);
            let (r, run) = test_discharge(
                k as u32 + 1,
                1.0,
                |_| Predicted { value: Some(e), lo: Some(e - 5.0), hi: Some(e + 5.0) },
                Predicted { value: Some(1.0), lo: None, hi: None },
            );
            records.push(r);
            runs.push(run);
        }
        (records, Runs { validation: Vec::new(), judged: runs })
    }

    fn eod_at_half(run: &CycleRun) -> Predicted {
        run.steps[50].eod
    }

    /// A method 3 s late on every discharge, with a wiggle of +-1 s: once a window of recentred predictions
    /// has beaten its own, each discharge is served within the wiggle of the measured end, its interval
    /// moved with it; before that, its own predictions. Never right after a rest of more than a day.
    #[test]
    fn a_steady_bias_is_served_recentred_once_it_has_earned_it() {
        let wiggle = |k: usize| if k.is_multiple_of(2) { 1.0 } else { -1.0 };
        let (mut records, runs) = sequence(40, |k| 3.0 + wiggle(k));
        // Judged discharge 5 follows a rest of two days.
        records[12 + 5].rest_before_s = Some(2.0 * 86_400.0);
        let (val, judged) = records.split_at(12);
        let runs = Runs { validation: runs.judged[..12].to_vec(), judged: runs.judged[12..].to_vec() };
        let (served, gates) = serve(&runs, val, judged);
        for (k, run) in served.judged.iter().enumerate() {
            let p = eod_at_half(run);
            if gates[1][k] {
                let (v, lo, hi) = (p.value.unwrap(), p.lo.unwrap(), p.hi.unwrap());
                assert!((v - 100.0).abs() <= 2.0 + 1e-9, "judged {k}: recentred {v}");
                assert!((lo - (v - 5.0)).abs() < 1e-9 && (hi - (v + 5.0)).abs() < 1e-9, "{lo} {v} {hi}");
            } else {
                assert_eq!(p, eod_at_half(&runs.judged[k]));
            }
        }
        // Validation alone holds 12 discharges: the gate opens within it, so every judged one is served at
        // every share, except the one after the long rest.
        for g in &gates {
            assert!(g.iter().enumerate().all(|(k, s)| *s == (k != 5)), "{g:?}");
        }
    }

    /// A bias that flips sign from one discharge to the next (late 4 s, then early 2 s): the median of
    /// the window shifts every prediction the wrong way half the time, so the recentred predictions never
    /// earn their place and the method's own are served throughout.
    #[test]
    fn a_bias_that_flips_is_not_served() {
        let (records, runs) = sequence(3 * WINDOW, |k| if k.is_multiple_of(2) { 4.0 } else { -2.0 });
        let (served, gates) = serve(&runs, &[], &records);
        assert!(gates.iter().flatten().all(|g| !g));
        for (a, b) in served.judged.iter().zip(&runs.judged) {
            assert_eq!(eod_at_half(a), eod_at_half(b));
        }
    }
}
