//! A learner on a calibrator's record across a real cell's discharges: before each discharge it expects the
//! calibrator's signed error there from the errors of the discharges that ended before it, the rest before
//! this one and how warm it runs, and the prediction is moved by that expectation. Least squares, refitted
//! before every discharge on the last [`RECORD_WINDOW`] discharges (at least [`MIN_RECORD_PAIRS`]), on four
//! inputs: the last error, the mean of the last five, the log of the rest before, and a temperature input
//! (in `bcal calibrate`: how much warmer the discharge's loaded readings ran up to where its error is taken,
//! or so far, than the record's at the same time after the load-on), scaled by the record's spread. Within
//! linear policies on these inputs this is the optimum of a policy trained by cost alone (the squared error
//! it leaves) on the same record; the first three settings were fixed before any figure was seen
//! (docs/calibrator.md, "a learner on the record", where `examples/record_room.py` measures the learner on
//! those three on `bcal calibrate` runs); the temperature input was added after the cold cell B0055 (4 C)
//! showed its errors following the discharge's temperature ("the temperature on the record"). On NASA cells
//! its gain is on the capacity, from the rest before the discharge on some cells (a cell regains charge over
//! a rest, by more than the lifetime model's long-rest jump carries for the rests it sees most) and from a
//! persistent bias on others, and on the cold cell's end of discharge, from its temperature. `bcal calibrate`
//! (`bcal_realcell::tune::learn_on_record`) blends its capacity and end with the joint UKF's as
//! [`crate::blend`] weighs any two and delivers that as a method of its own, `ukf_learned`. Pure arithmetic:
//! nothing here reads or prints.

use nalgebra::{Matrix5, Vector5};

/// Discharges the learner fits on: the last that ended with a scored error.
pub const RECORD_WINDOW: usize = 30;
/// Fewest (input, error) pairs it fits on; before that, no expectation. Each pair needs the discharge
/// before it, so the first expectation comes after `MIN_RECORD_PAIRS + 1` scored discharges.
pub const MIN_RECORD_PAIRS: usize = 10;
/// Ridge on the inputs' coefficients (not the intercept), per pair, in units of the errors' spread: only
/// enough to keep a record whose rests or temperatures were all the same (a constant input) solvable.
const RIDGE: f64 = 1e-3;
/// The temperature input is in units of the record's spread of temperatures, but of no less than this, K:
/// about a cell sensor's resolution, so that a cell held at one temperature (its readings differing by the
/// sensor's noise) gives an input near 0, not noise blown up to unit size.
pub const MIN_TEMPERATURE_SPREAD_K: f64 = 0.1;
/// The temperature input is held within this many spreads of the record's mean: a line fitted on the
/// record is not carried far past what the record held (a sensor that shifts, a discharge far colder).
pub const MAX_TEMPERATURE_INPUT: f64 = 3.0;

/// One discharge of the record: its signed error (predicted minus measured), the rest before it, s (None
/// where the schedule does not tell), and its temperature input, K (in `bcal calibrate`, how much warmer its
/// loaded readings ran up to where the error was taken than the discharges before it did at the same time
/// after their load-on; None where there is nothing to compare with. A reader without a temperature column
/// fills in the ambient, which gives 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Entry {
    pub error: f64,
    pub rest_before_s: Option<f64>,
    pub temperature_k: Option<f64>,
}

/// A learner fitted on a record: what it expects of the next discharge given the rest before it and its
/// loaded readings' mean temperature so far.
#[derive(Clone, Debug, PartialEq)]
pub struct Learned {
    coef: Vector5<f64>,
    /// The record's error spread: the fit is on errors in this unit.
    scale: f64,
    /// The last error and the mean of the last five (in units of `scale`): the next discharge's inputs.
    last: f64,
    mean5: f64,
    /// The record's mean log rest (an unknown rest's input) and its temperatures' mean and spread, K.
    mean_log_rest: f64,
    mean_k: f64,
    spread_k: f64,
}

impl Learned {
    /// The error expected of the next discharge, after a rest of `rest_before_s`, at a reading whose loaded
    /// readings so far had a mean temperature of `temperature_k` (None: the record's mean, which says nothing).
    pub fn expected(&self, rest_before_s: Option<f64>, temperature_k: Option<f64>) -> Option<f64> {
        let x = Vector5::new(
            1.0,
            self.last,
            self.mean5,
            rest_before_s.map_or(self.mean_log_rest, log_rest),
            temperature_k.map_or(0.0, |t| standardized(t, self.mean_k, self.spread_k)),
        );
        let expected = self.coef.dot(&x) * self.scale;
        expected.is_finite().then_some(expected)
    }
}

/// The learner fitted on the `record` of the discharges that ended, oldest first (entries without a finite
/// error are not part of it). None with fewer than [`MIN_RECORD_PAIRS`] pairs, or a record without any spread.
pub fn fit(record: &[Entry]) -> Option<Learned> {
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
    // A rest the schedule does not give takes the record's mean log rest (the input then says nothing); so
    // does a temperature the record does not have.
    let mean = |v: &[f64]| if v.is_empty() { 0.0 } else { v.iter().sum::<f64>() / v.len() as f64 };
    let logs: Vec<f64> = kept.iter().filter_map(|e| e.rest_before_s).map(log_rest).collect();
    let mean_log_rest = mean(&logs);
    let temps: Vec<f64> = kept.iter().filter_map(|e| e.temperature_k).filter(|t| t.is_finite()).collect();
    let mean_k = mean(&temps);
    let spread_k = (temps.iter().map(|t| (t - mean_k).powi(2)).sum::<f64>() / temps.len().max(1) as f64)
        .sqrt()
        .max(MIN_TEMPERATURE_SPREAD_K);
    let tail = |k: usize| {
        let last5 = &errors[k.saturating_sub(5)..k];
        (errors[k - 1], last5.iter().sum::<f64>() / last5.len() as f64)
    };
    let inputs = |k: usize| {
        let (last, mean5) = tail(k);
        let e = kept[k];
        Vector5::new(
            1.0,
            last,
            mean5,
            e.rest_before_s.map_or(mean_log_rest, log_rest),
            e.temperature_k.filter(|t| t.is_finite()).map_or(0.0, |t| standardized(t, mean_k, spread_k)),
        )
    };
    let (mut a, mut b) = (Matrix5::<f64>::zeros(), Vector5::<f64>::zeros());
    let mut count = 0usize;
    for k in (1..n).rev().take(RECORD_WINDOW) {
        let x = inputs(k);
        a += x * x.transpose();
        b += x * errors[k];
        count += 1;
    }
    for p in 1..5 {
        a[(p, p)] += RIDGE * count as f64;
    }
    let coef = a.cholesky()?.solve(&b);
    let (last, mean5) = tail(n);
    Some(Learned { coef, scale, last, mean5, mean_log_rest, mean_k, spread_k })
}

/// The error the learner on `record` expects of the next discharge ([`fit`], [`Learned::expected`]).
pub fn expected_error(record: &[Entry], rest_before_s: Option<f64>, temperature_k: Option<f64>) -> Option<f64> {
    fit(record)?.expected(rest_before_s, temperature_k)
}

/// A temperature's input: in spreads from the record's mean, held within [`MAX_TEMPERATURE_INPUT`] (a
/// non-finite one says nothing).
fn standardized(t_k: f64, mean_k: f64, spread_k: f64) -> f64 {
    let x = (t_k - mean_k) / spread_k;
    if x.is_finite() {
        x.clamp(-MAX_TEMPERATURE_INPUT, MAX_TEMPERATURE_INPUT)
    } else {
        0.0
    }
}

/// The rest's input: its log, from a second up (a rest of 0 s is a schedule's glitch, not an input).
fn log_rest(rest_s: f64) -> f64 {
    rest_s.max(1.0).ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entries(errors: &[f64], rests: &[f64]) -> Vec<Entry> {
        errors
            .iter()
            .zip(rests)
            .map(|(&error, &r)| Entry { error, rest_before_s: Some(r), temperature_k: None })
            .collect()
    }

    #[test]
    fn too_short_a_record_expects_nothing() {
        let e = entries(&[0.01; MIN_RECORD_PAIRS], &[1e4; MIN_RECORD_PAIRS]);
        assert_eq!(expected_error(&e, Some(1e4), None), None);
        // No spread at all: nothing to scale by.
        let e = entries(&[0.0; 20], &[1e4; 20]);
        assert_eq!(expected_error(&e, Some(1e4), None), None);
        // A failed prediction is not part of the record.
        let mut e = entries(&[0.01; MIN_RECORD_PAIRS], &[1e4; MIN_RECORD_PAIRS]);
        e.push(Entry { error: f64::INFINITY, rest_before_s: Some(1e4), temperature_k: None });
        assert_eq!(expected_error(&e, Some(1e4), None), None);
    }

    #[test]
    fn a_constant_bias_is_expected_again_whatever_the_rests() {
        // Every rest the same: the rest's input is constant, and the ridge keeps the fit solvable.
        let e = entries(&[0.02; 15], &[14_000.0; 15]);
        let x = expected_error(&e, Some(14_000.0), None).unwrap();
        assert!((x - 0.02).abs() < 1e-3 * 0.02, "{x}");
        // Unknown rests take the record's mean: the same.
        let e: Vec<Entry> = (0..15).map(|_| Entry { error: 0.02, rest_before_s: None, temperature_k: None }).collect();
        let x = expected_error(&e, None, None).unwrap();
        assert!((x - 0.02).abs() < 1e-3 * 0.02, "{x}");
    }

    #[test]
    fn an_error_that_follows_the_rest_is_expected_from_it() {
        // The error grows by 0.01 Ah per e-fold of rest (the cell regains charge the prior does not carry),
        // on rests of 2-8 h in no order: a discharge after a rest of a day is expected from the line, not
        // from the last error.
        let rests: Vec<f64> = (0..30).map(|k| 3600.0 * (2.0 + ((k * 7) % 13) as f64 * 0.5)).collect();
        let errors: Vec<f64> = rests.iter().map(|r| 0.01 * (r / 14_400.0).ln()).collect();
        let x = expected_error(&entries(&errors, &rests), Some(86_400.0), None).unwrap();
        let truth = 0.01 * (86_400.0f64 / 14_400.0).ln();
        assert!((x - truth).abs() < 0.05 * truth, "{x} against {truth}");
        // Only the last RECORD_WINDOW pairs count: an old record of another law is forgotten.
        let mut long: Vec<Entry> = entries(&[0.5; 40], &[3600.0; 40]);
        long.extend(entries(&errors, &rests));
        let y = expected_error(&long, Some(86_400.0), None).unwrap();
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
        let x = expected_error(&entries(&errors, &rests), Some(14_000.0), None).unwrap();
        assert!((-0.9..=-0.3).contains(&(x / last)), "{x} after {last}");
    }

    #[test]
    fn an_error_that_follows_the_temperature_is_expected_from_it() {
        // A cold cell: the warmer a discharge runs (its readings so far 12-16 C in no order), the more it
        // delivers, which an isothermal model does not carry: the calibrator's error falls by 0.01 Ah per K.
        // A discharge running 2 K above the record's mean is expected 0.02 Ah below the mean error.
        let temps: Vec<f64> = (0..30).map(|k| 285.0 + f64::from((k * 7) % 9) * 0.5).collect();
        let mean_k = temps.iter().sum::<f64>() / temps.len() as f64;
        let record: Vec<Entry> = temps
            .iter()
            .map(|&t| Entry {
                error: 0.005 - 0.01 * (t - mean_k),
                rest_before_s: Some(14_000.0),
                temperature_k: Some(t),
            })
            .collect();
        let x = expected_error(&record, Some(14_000.0), Some(mean_k + 2.0)).unwrap();
        let truth = 0.005 - 0.02;
        assert!((x - truth).abs() < 0.05 * truth.abs(), "{x} against {truth}");
        // A discharge far colder than any on the record (a sensor that shifted by 15 K) is expected as one
        // at three spreads from the mean, not on the line carried fifteen kelvin out.
        let spread_k = (temps.iter().map(|t| (t - mean_k).powi(2)).sum::<f64>() / temps.len() as f64).sqrt();
        let far = expected_error(&record, Some(14_000.0), Some(mean_k - 15.0)).unwrap();
        let edge = 0.005 + 0.01 * MAX_TEMPERATURE_INPUT * spread_k;
        assert!((far - edge).abs() < 0.05 * edge, "{far} against {edge}");
        // Without the temperature the learner expects the record's mean error, about.
        let y = expected_error(&record, Some(14_000.0), None).unwrap();
        assert!((y - 0.005).abs() < 0.003, "{y}");
        // A record held at one temperature learns nothing of it: a discharge reading warmer is expected the same.
        let flat: Vec<Entry> = record.iter().map(|e| Entry { temperature_k: Some(297.0), ..*e }).collect();
        let (a, b) = (
            expected_error(&flat, Some(14_000.0), Some(297.0)).unwrap(),
            expected_error(&flat, Some(14_000.0), Some(299.0)).unwrap(),
        );
        assert!((a - b).abs() < 1e-12, "{a} {b}");
    }
}
