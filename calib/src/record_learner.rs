//! A learner on a calibrator's record across a real cell's discharges: before each discharge it expects the
//! calibrator's signed error there from the errors of the discharges that ended before it and the rest before
//! this one, and the prediction is moved by that expectation. Least squares, refitted before every discharge
//! on the last [`RECORD_WINDOW`] discharges (at least [`MIN_RECORD_PAIRS`]), on three inputs: the last error,
//! the mean of the last five, and the log of the rest before. Within linear policies on these inputs this is
//! the optimum of a policy trained by cost alone (the squared error it leaves) on the same record; the
//! settings were fixed before any figure was seen (docs/calibrator.md, "a learner on the record", where
//! `examples/record_room.py` measures the same learner on `bcal calibrate` runs). On NASA cells its gain is
//! on the capacity, from the rest before the discharge on some cells (a cell regains charge over a rest, by
//! more than the lifetime model's long-rest jump carries for the rests it sees most) and from a persistent
//! bias on others. `bcal calibrate` (`bcal_realcell::tune::learn_capacity`) blends its capacity with the
//! joint UKF's as [`crate::blend`] weighs any two and delivers that as a method of its own, `ukf_learned`.
//! Pure arithmetic: nothing here reads or prints.

use nalgebra::{Matrix4, Vector4};

/// Discharges the learner fits on: the last that ended with a scored error.
pub const RECORD_WINDOW: usize = 30;
/// Fewest (input, error) pairs it fits on; before that, no expectation. Each pair needs the discharge
/// before it, so the first expectation comes after `MIN_RECORD_PAIRS + 1` scored discharges.
pub const MIN_RECORD_PAIRS: usize = 10;
/// Ridge on the three inputs' coefficients (not the intercept), per pair, in units of the errors' spread:
/// only enough to keep a record whose rests were all the same (a constant input) solvable.
const RIDGE: f64 = 1e-3;

/// One discharge of the record: its signed error (predicted minus measured) and the rest before it, s
/// (None where the schedule does not tell).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Entry {
    pub error: f64,
    pub rest_before_s: Option<f64>,
}

/// The error the learner expects of the next discharge (rest before it `rest_before_s`) from the `record` of
/// those that ended before it, oldest first (entries without a finite error are not part of the record).
/// None with fewer than [`MIN_RECORD_PAIRS`] pairs, or a record without any spread.
pub fn expected_error(record: &[Entry], rest_before_s: Option<f64>) -> Option<f64> {
    let kept: Vec<&Entry> = record.iter().filter(|e| e.error.is_finite()).collect();
    // Each pair takes its inputs from the discharges before it; the window counts pairs.
    let n = kept.len();
    if n < MIN_RECORD_PAIRS + 1 {
        return None;
    }
    let scale = (kept.iter().map(|e| e.error * e.error).sum::<f64>() / n as f64).sqrt();
    if scale.is_nan() || scale <= 0.0 {
        return None;
    }
    let errors: Vec<f64> = kept.iter().map(|e| e.error / scale).collect();
    // A rest the schedule does not give takes the record's mean log rest (the input then says nothing).
    let logs: Vec<f64> = kept.iter().filter_map(|e| e.rest_before_s).map(log_rest).collect();
    let mean_log = if logs.is_empty() { 0.0 } else { logs.iter().sum::<f64>() / logs.len() as f64 };
    let rest_input = |rest: Option<f64>| rest.map_or(mean_log, log_rest);
    let inputs = |k: usize, rest: Option<f64>| {
        let last5 = &errors[k.saturating_sub(5)..k];
        Vector4::new(1.0, errors[k - 1], last5.iter().sum::<f64>() / last5.len() as f64, rest_input(rest))
    };
    let pairs = (1..n).rev().take(RECORD_WINDOW);
    let (mut a, mut b) = (Matrix4::<f64>::zeros(), Vector4::<f64>::zeros());
    let mut count = 0usize;
    for k in pairs {
        let x = inputs(k, kept[k].rest_before_s);
        a += x * x.transpose();
        b += x * errors[k];
        count += 1;
    }
    for p in 1..4 {
        a[(p, p)] += RIDGE * count as f64;
    }
    let coef = a.cholesky()?.solve(&b);
    let expected = coef.dot(&inputs(n, rest_before_s)) * scale;
    expected.is_finite().then_some(expected)
}

/// The rest's input: its log, from a second up (a rest of 0 s is a schedule's glitch, not an input).
fn log_rest(rest_s: f64) -> f64 {
    rest_s.max(1.0).ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entries(errors: &[f64], rests: &[f64]) -> Vec<Entry> {
        errors.iter().zip(rests).map(|(&error, &r)| Entry { error, rest_before_s: Some(r) }).collect()
    }

    #[test]
    fn too_short_a_record_expects_nothing() {
        let e = entries(&[0.01; MIN_RECORD_PAIRS], &[1e4; MIN_RECORD_PAIRS]);
        assert_eq!(expected_error(&e, Some(1e4)), None);
        // No spread at all: nothing to scale by.
        let e = entries(&[0.0; 20], &[1e4; 20]);
        assert_eq!(expected_error(&e, Some(1e4)), None);
        // A failed prediction is not part of the record.
        let mut e = entries(&[0.01; MIN_RECORD_PAIRS], &[1e4; MIN_RECORD_PAIRS]);
        e.push(Entry { error: f64::INFINITY, rest_before_s: Some(1e4) });
        assert_eq!(expected_error(&e, Some(1e4)), None);
    }

    #[test]
    fn a_constant_bias_is_expected_again_whatever_the_rests() {
        // Every rest the same: the rest's input is constant, and the ridge keeps the fit solvable.
        let e = entries(&[0.02; 15], &[14_000.0; 15]);
        let x = expected_error(&e, Some(14_000.0)).unwrap();
        assert!((x - 0.02).abs() < 1e-3 * 0.02, "{x}");
        // Unknown rests take the record's mean: the same.
        let e: Vec<Entry> = (0..15).map(|_| Entry { error: 0.02, rest_before_s: None }).collect();
        let x = expected_error(&e, None).unwrap();
        assert!((x - 0.02).abs() < 1e-3 * 0.02, "{x}");
    }

    #[test]
    fn an_error_that_follows_the_rest_is_expected_from_it() {
        // The error grows by 0.01 Ah per e-fold of rest (the cell regains charge the prior does not carry),
        // on rests of 2-8 h in no order: a discharge after a rest of a day is expected from the line, not
        // from the last error.
        let rests: Vec<f64> = (0..30).map(|k| 3600.0 * (2.0 + ((k * 7) % 13) as f64 * 0.5)).collect();
        let errors: Vec<f64> = rests.iter().map(|r| 0.01 * (r / 14_400.0).ln()).collect();
        let x = expected_error(&entries(&errors, &rests), Some(86_400.0)).unwrap();
        let truth = 0.01 * (86_400.0f64 / 14_400.0).ln();
        assert!((x - truth).abs() < 0.05 * truth, "{x} against {truth}");
        // Only the last RECORD_WINDOW pairs count: an old record of another law is forgotten.
        let mut long: Vec<Entry> = entries(&[0.5; 40], &[3600.0; 40]);
        long.extend(entries(&errors, &rests));
        let y = expected_error(&long, Some(86_400.0)).unwrap();
        assert!((y - truth).abs() < 0.1 * truth, "{y} against {truth}");
    }

    #[test]
    fn errors_that_alternate_are_expected_to_turn() {
        // Each error the last one times -0.6 plus a fresh part (what a prior that carries one discharge's
        // noise into the next gives): the next is expected on the other side of the last, by about 0.6 of it.
        let mut seed = 12345u64;
        let mut fresh = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.02
        };
        let mut errors = vec![fresh()];
        for _ in 0..30 {
            let next = -0.6 * errors.last().unwrap() + fresh();
            errors.push(next);
        }
        let last = *errors.last().unwrap();
        assert!(last.abs() > 0.003, "the record ends on a small error: {last}");
        let rests = vec![14_000.0; errors.len()];
        let x = expected_error(&entries(&errors, &rests), Some(14_000.0)).unwrap();
        assert!((-0.9..=-0.3).contains(&(x / last)), "{x} after {last}");
    }
}
