//! `bcal calibrate`'s side of [`bcal_calib::recentre`]: each method's end-of-discharge predictions
//! recentred on the bias of its own last discharges (the validation cycles first, then every judged
//! discharge once it has ended), and served where the recentred ones beat the method's own on the last
//! discharges ([`tune::gate_runs`], the rule that gates every alternative; never right after a rest of more
//! than a day). The bias is learned on the method's own predictions, never on the recentred ones.

use crate::interval::outcomes;
use crate::record::CellRecord;
use crate::run::CycleRun;
use crate::tune::{self, Runs, Served};
use bcal_calib::recentre::{
    biases_alike, regressed_shift_s, shift_s, voltage_regressions, Outcome, Previous, Start, Transition, VoltageChange,
};

/// `runs` along `records` (in order) with every predicted end of discharge, and its interval, moved by the
/// bias of the discharges before it in the sequence that moved their current as this one has so far
/// ([`biases_alike`]: its loaded readings' mean current up to the reading against the record before's).
fn recentred_along(records: &[&CellRecord], runs: &[&CycleRun]) -> Vec<CycleRun> {
    let mut ended: Vec<(Transition, Vec<Outcome>)> = Vec::new();
    records
        .iter()
        .zip(runs)
        .map(|(r, run)| {
            let current = r.loaded_current();
            let mut out = (*run).clone();
            for s in &mut out.steps {
                if let Some(v) = s.eod.value {
                    let now = Transition { before_a: r.current_before_a, now_a: current.at(s.t_s - r.load_on_s) };
                    s.eod = s.eod.shifted(shift_s(&biases_alike(&ended, &now), r.load_on_s, s.t_s, v));
                }
            }
            let (eod, _) = outcomes(r, run);
            if !eod.is_empty() {
                ended.push((Transition { before_a: r.current_before_a, now_a: current.whole() }, eod));
            }
            out
        })
        .collect()
}

/// How a record started: its ambient and its last reading before the load came on.
fn start(r: &CellRecord) -> Start {
    Start::at_load_on(&r.samples, r.load_on_s, r.ambient_k)
}

/// The voltage change at each reading of each record against the record before it in the sequence
/// ([`VoltageChange`]; None before the load came on and on the first record).
fn voltage_changes(records: &[&CellRecord]) -> Vec<Vec<Option<f64>>> {
    fn loaded(r: &CellRecord) -> impl Iterator<Item = (f64, f64, f64)> + '_ {
        r.samples.iter().filter(|s| s.t_s >= r.load_on_s).map(|s| (s.t_s - r.load_on_s, s.voltage_v, s.current_a))
    }
    records
        .iter()
        .enumerate()
        .map(|(k, r)| {
            let previous = k.checked_sub(1).and_then(|j| Previous::new(loaded(records[j]), start(records[j])));
            let mut change = VoltageChange::new(previous, start(r));
            r.samples
                .iter()
                .map(|s| {
                    (s.t_s >= r.load_on_s).then(|| change.push(s.t_s - r.load_on_s, s.voltage_v, s.current_a)).flatten()
                })
                .collect()
        })
        .collect()
}

/// `runs` along `records` (in order) with every predicted end of discharge, and its interval, moved by the
/// error its share's regression on the voltage change expects ([`voltage_regressions`] of the method's own
/// errors on the discharges before it in the sequence).
fn regressed_along(records: &[&CellRecord], runs: &[&CycleRun]) -> Vec<CycleRun> {
    let changes = voltage_changes(records);
    let mut ended: Vec<Vec<(Outcome, Option<f64>)>> = Vec::new();
    records
        .iter()
        .zip(runs)
        .zip(&changes)
        .map(|((r, run), dv)| {
            let lines = voltage_regressions(&ended);
            let mut out = (*run).clone();
            for (k, s) in out.steps.iter_mut().enumerate() {
                if let Some(v) = s.eod.value {
                    let d = dv.get(k).copied().flatten();
                    s.eod = s.eod.shifted(regressed_shift_s(&lines, d, r.load_on_s, s.t_s, v));
                }
            }
            let (eod, _) = outcomes(r, run);
            if !eod.is_empty() {
                let at =
                    |f: u32| r.reading_at_fraction(f64::from(f) / 100.0).and_then(|k| dv.get(k).copied().flatten());
                ended.push(eod.into_iter().map(|o| (o, at(o.fraction))).collect());
            }
            out
        })
        .collect()
}

/// A method's runs along the validation and judged cycles, recentred where that has earned it, and the
/// judged discharges where it did, per share: first on its median bias, then, where that has earned it
/// against the median's, on the voltage change against the discharge before (the second gate's
/// discharges, per share).
pub fn serve(runs: &Runs, validation: &[CellRecord], judged: &[CellRecord]) -> (Runs, Served, Served) {
    let records: Vec<&CellRecord> = validation.iter().chain(judged).collect();
    let all: Vec<&CycleRun> = runs.validation.iter().chain(&runs.judged).collect();
    let split = |mut moved: Vec<CycleRun>| {
        let judged = moved.split_off(runs.validation.len().min(moved.len()));
        Runs { validation: moved, judged }
    };
    let (median, median_gates) = tune::gate_runs(&split(recentred_along(&records, &all)), runs, validation, judged);
    let moved = split(regressed_along(&records, &all));
    let (served, voltage_gates) = tune::gate_runs_onto(&moved, &median, &median, runs, validation, judged);
    (served, median_gates, voltage_gates)
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
        let (served, gates, _) = serve(&runs, val, judged);
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

    /// A cell at 4 A with every third discharge at 1 A whose method ends 4 s late after a move up, 3 s early
    /// after a move down and 1 s late at 4 A after 4 A (a median over every discharge takes 1 s off each,
    /// which leaves the moves 3 and 4 s off): each discharge is recentred on its twins, the discharges that
    /// moved their current as it does, and served so, on the measured end (the gate opens within the
    /// validation cycles).
    #[test]
    fn each_discharge_is_recentred_on_the_discharges_that_moved_their_current_alike() {
        let current_a = |k: usize| if k % 3 == 2 { 1.0 } else { 4.0 };
        let late_s = |k: usize| match (k.checked_sub(1).map(current_a), current_a(k)) {
            (Some(1.0), 4.0) => 4.0,
            (Some(4.0), 1.0) => -3.0,
            _ => 1.0,
        };
        let (mut records, runs) = sequence(45, late_s);
        for (k, r) in records.iter_mut().enumerate() {
            r.samples.iter_mut().for_each(|s| s.current_a = current_a(k));
        }
        crate::record::set_currents_before(records.iter_mut());
        let (val, judged) = records.split_at(15);
        let runs = Runs { validation: runs.judged[..15].to_vec(), judged: runs.judged[15..].to_vec() };
        let (served, gates, _) = serve(&runs, val, judged);
        assert!(gates[1].iter().all(|&g| g), "served at half: {:?}", gates[1]);
        for (k, run) in served.judged.iter().enumerate() {
            let v = eod_at_half(run).value.unwrap();
            assert!((v - 100.0).abs() < 1e-9, "judged {k}: {v}, erred {}", late_s(15 + k));
        }
    }

    /// A method whose end comes late by an amount that follows the voltage against the discharge before
    /// (0.5 % of the duration, less 5 % for every volt the discharge reads above the one before at the same
    /// time since the load came on, the voltage swinging by +-8 mV from one discharge to the next): the
    /// median cannot take that off, the regression on the voltage change can. Once it has beaten the
    /// recentred (or the method's own) predictions on a window of discharges it serves, on the measured end.
    #[test]
    fn an_error_that_follows_the_voltage_change_is_served_regressed() {
        let offset_v = |k: usize| 0.008 * ((k as f64) * 2.1).sin();
        // Late by 0.5 % of the predicted duration, less 5 % for every volt above the discharge before.
        let error = |k: usize| 0.005 - 5.0 * (offset_v(k) - if k == 0 { 0.0 } else { offset_v(k - 1) });
        let (mut records, runs) = sequence(45, |k| 100.0 / (1.0 - error(k)) - 100.0);
        for (k, r) in records.iter_mut().enumerate() {
            for s in &mut r.samples {
                s.voltage_v += offset_v(k);
            }
        }
        let (val, judged) = records.split_at(10);
        let runs = Runs { validation: runs.judged[..10].to_vec(), judged: runs.judged[10..].to_vec() };
        let (served, _, on_voltage) = serve(&runs, val, judged);
        let served_at_half: Vec<usize> = (0..judged.len()).filter(|&k| on_voltage[1][k]).collect();
        // The regression needs 8 discharges that ended with a voltage change, then a window of 10 scored to
        // earn its place: it serves the last judged discharges at least.
        assert!(served_at_half.len() >= 15, "served at half: {served_at_half:?}");
        // On the measured end, where the method's own were up to 8 s off.
        let mut own_off = 0.0f64;
        for &k in &served_at_half {
            let v = eod_at_half(&served.judged[k]).value.unwrap();
            assert!((v - 100.0).abs() < 1e-6, "judged {k}: {v}");
            own_off = own_off.max((eod_at_half(&runs.judged[k]).value.unwrap() - 100.0).abs());
        }
        assert!(own_off > 5.0, "{own_off}");
        // Where it does not serve, the prediction is the method's own or the median's.
        let first = served_at_half[0];
        assert!(first > 0 && !on_voltage[1][..first].iter().any(|s| *s));
    }

    /// A bias that flips sign from one discharge to the next (late 4 s, then early 2 s): the median of
    /// the window shifts every prediction the wrong way half the time, so the recentred predictions never
    /// earn their place and the method's own are served throughout.
    #[test]
    fn a_bias_that_flips_is_not_served() {
        let (records, runs) = sequence(3 * WINDOW, |k| if k.is_multiple_of(2) { 4.0 } else { -2.0 });
        let (served, gates, _) = serve(&runs, &[], &records);
        assert!(gates.iter().flatten().all(|g| !g));
        for (a, b) in served.judged.iter().zip(&runs.judged) {
            assert_eq!(eod_at_half(a), eod_at_half(b));
        }
    }

    /// A discharge that started from a partial charge (its rest 70 mV below the one before's) has no voltage
    /// change, and neither has the one after it (against it); the next, from a rest like the one before
    /// it, compares again.
    #[test]
    fn a_discharge_from_a_partial_charge_has_no_voltage_change_nor_the_one_after_it() {
        let records: Vec<CellRecord> = [4.19, 4.12, 4.19, 4.18]
            .iter()
            .enumerate()
            .map(|(k, &rest_v)| {
                let (mut r, _) = test_discharge(k as u32 + 1, 1.0, |_| Predicted::default(), Predicted::default());
                r.samples[0].current_a = 0.0;
                r.samples[0].voltage_v = rest_v;
                r.load_on_s = 1.0;
                r
            })
            .collect();
        let refs: Vec<&CellRecord> = records.iter().collect();
        let dv = voltage_changes(&refs);
        let any = |k: usize| dv[k].iter().any(Option::is_some);
        assert!(!any(0), "the first has none before it");
        assert!(!any(1) && !any(2), "the partial start and the one after it");
        assert!(any(3), "from a rest 10 mV apart it compares");
    }
}
