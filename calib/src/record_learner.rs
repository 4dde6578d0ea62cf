//! A learner on a calibrator's record across a real cell's discharges: before each discharge it expects the
//! calibrator's signed error there from the errors of the discharges that ended before it, the rest before
//! this one, how warm it runs and how its current differs from the last one's, and the prediction is moved by
//! that expectation. Least squares, refitted before every discharge on the last [`RECORD_WINDOW`] discharges
//! (at least [`MIN_RECORD_PAIRS`]), on five inputs: the last error, the mean of the last five, the log of the
//! rest before, a temperature input (in `bcal calibrate`: how much warmer the discharge's loaded readings ran
//! up to where its error is taken, or so far, than the record's at the same time after the load-on), scaled
//! by the record's spread, and a current input ([`current_switch`]: the log of the ratio of its loaded
//! readings' mean current so far to the last discharge's, 0 for a like current ([`LIKE_CURRENT`]); learned
//! only from a window where the current moved on [`MIN_CURRENT_SWITCHES`] discharges or more). Within linear
//! policies on these inputs this is the optimum of a policy trained by cost alone (the squared error it
//! leaves) on the same record; the first three settings were fixed before any figure was seen
//! (docs/calibrator.md, "a learner on the record", where `examples/record_room.py` measures the learner on
//! those three on `bcal calibrate` runs); the temperature input was added after the cold cell B0055 (4 C) showed
//! its errors following the discharge's temperature ("the temperature on the record"), the current input after a
//! blind cell cycled at 1, 2 and 4 A in no order showed the joint UKF's end erring by the current of the discharge
//! before (what it carries over holds that current's model error; "the current on the record"). On NASA cells its
//! gain is on the capacity, from the rest before the discharge on some cells (a cell regains charge over a rest,
//! by more than the lifetime model's long-rest jump carries for the rests it sees most) and from a persistent bias
//! on others, and on the cold cell's end of discharge, from its temperature. `bcal calibrate`
//! (`bcal_realcell::tune::learn_on_record`) blends its capacity and end with the joint UKF's as [`crate::blend`]
//! weighs any two and delivers that as a method of its own, `ukf_learned`. Pure arithmetic: nothing here reads or
//! prints.

use crate::recentre::Transition;
use crate::widening::EOD_FRACTIONS_PCT;
use nalgebra::{Matrix6, Vector6};
use std::collections::VecDeque;

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
/// Two discharges whose mean currents' ratio lies between 1 / (1 + this) and 1 + this ran at a like current:
/// the current input is 0 (a cell cycled at one current, whose means differ by the cycler's noise, learns
/// nothing of it).
pub const LIKE_CURRENT: f64 = 0.2;
/// The current input is held within the log of this ratio (NASA's protocols span 1-4 A; a current far
/// outside the record's is not carried far down a line).
pub const MAX_CURRENT_RATIO: f64 = 8.0;
/// Fewest discharges in a learner's window whose current moved from the last one's ([`LIKE_CURRENT`]) for it
/// to learn the current input; with fewer its coefficient is 0.
pub const MIN_CURRENT_SWITCHES: usize = 3;

/// One discharge of the record: its signed error (predicted minus measured), the rest before it, s (None
/// where the schedule does not tell), and its temperature input, K (in `bcal calibrate`, how much warmer its
/// loaded readings ran up to where the error was taken than the discharges before it did at the same time
/// after their load-on; None where there is nothing to compare with. A reader without a temperature column
/// fills in the ambient, which gives 0), and its current input ([`current_switch`]; None where no discharge
/// before it is known, which gives 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Entry {
    pub error: f64,
    pub rest_before_s: Option<f64>,
    pub temperature_k: Option<f64>,
    pub current_switch: Option<f64>,
}

/// The current input of a discharge whose loaded readings' mean current so far is `now_a` after one whose
/// mean current was `before_a`: the log of their ratio, 0 where they differ by less than [`LIKE_CURRENT`],
/// held within the log of [`MAX_CURRENT_RATIO`]; None where either is not a positive current. What a
/// discharge starts from (the end fit carried over, the model's knee) holds the model's error at the current
/// it was measured at, and a model whose error depends on the current errs the more the further the
/// current moved.
pub fn current_switch(now_a: f64, before_a: f64) -> Option<f64> {
    let x = (now_a / before_a).ln();
    if !(now_a > 0.0 && before_a > 0.0 && x.is_finite()) {
        return None;
    }
    let max = MAX_CURRENT_RATIO.ln();
    Some(if x.abs() < (1.0 + LIKE_CURRENT).ln() { 0.0 } else { x.clamp(-max, max) })
}

/// Whether two discharges ran at a like current: [`current_switch`] gives 0 ([`LIKE_CURRENT`]).
pub fn like_current(a: f64, b: f64) -> bool {
    current_switch(a, b) == Some(0.0)
}

/// A learner fitted on a record: what it expects of the next discharge given the rest before it, its
/// loaded readings' mean temperature so far and its current input.
#[derive(Clone, Debug, PartialEq)]
pub struct Learned {
    coef: Vector6<f64>,
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
    /// readings so far had a mean temperature of `temperature_k` (None: the record's mean, which says nothing)
    /// and a current input of `current_switch` ([`current_switch`]; None: 0).
    pub fn expected(
        &self,
        rest_before_s: Option<f64>,
        temperature_k: Option<f64>,
        current_switch: Option<f64>,
    ) -> Option<f64> {
        let x = Vector6::new(
            1.0,
            self.last,
            self.mean5,
            rest_before_s.map_or(self.mean_log_rest, log_rest),
            temperature_k.map_or(0.0, |t| standardized(t, self.mean_k, self.spread_k)),
            current_input(current_switch),
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
    // The current input is learned only from a window that moved its current on a few discharges: one switch
    // alone makes the input that discharge's own intercept, which takes it out of every other input's fit (a
    // cold cell's single move from 4 A to 1 A, after a long rest, left the rest's line to one discharge).
    let window = (1..n).rev().take(RECORD_WINDOW);
    let switches = window.clone().filter(|&k| current_input(kept[k].current_switch) != 0.0).count();
    let with_current = switches >= MIN_CURRENT_SWITCHES;
    let inputs = |k: usize| {
        let (last, mean5) = tail(k);
        let e = kept[k];
        Vector6::new(
            1.0,
            last,
            mean5,
            e.rest_before_s.map_or(mean_log_rest, log_rest),
            e.temperature_k.filter(|t| t.is_finite()).map_or(0.0, |t| standardized(t, mean_k, spread_k)),
            if with_current { current_input(e.current_switch) } else { 0.0 },
        )
    };
    let (mut a, mut b) = (Matrix6::<f64>::zeros(), Vector6::<f64>::zeros());
    let mut count = 0usize;
    for k in window {
        let x = inputs(k);
        a += x * x.transpose();
        b += x * errors[k];
        count += 1;
    }
    for p in 1..6 {
        a[(p, p)] += RIDGE * count as f64;
    }
    let coef = a.cholesky()?.solve(&b);
    let (last, mean5) = tail(n);
    Some(Learned { coef, scale, last, mean5, mean_log_rest, mean_k, spread_k })
}

/// The error the learner on `record` expects of the next discharge ([`fit`], [`Learned::expected`]).
pub fn expected_error(
    record: &[Entry],
    rest_before_s: Option<f64>,
    temperature_k: Option<f64>,
    current_switch: Option<f64>,
) -> Option<f64> {
    fit(record)?.expected(rest_before_s, temperature_k, current_switch)
}

/// Discharges whose ambients differ by no more than this, K, ran at the same ambient (NASA gives whole degrees;
/// B0038-B0040 moved from 24 to 44 C, B0042-B0044 from 22 to 4 C, in the middle of their lives). A stream,
/// which knows no chamber, takes each discharge's load-on temperature for its ambient and compares those
/// within [`crate::recentre::SAME_AMBIENT_K`].
pub const SAME_AMBIENT_K: f64 = 1.0;

/// A discharge's loaded readings' mean so far of one quantity (its cell temperature, K, or its current, A): a
/// BMS's running mean from the load-on.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LoadedMean {
    /// (time of a loaded reading after the load-on, s; the mean of the loaded readings up to it).
    means: Vec<(f64, f64)>,
    sum: f64,
}

impl LoadedMean {
    /// Adds a loaded reading `tau_s` after the load-on (in time order) of `value`; a non-finite value is no
    /// reading of it.
    pub fn push(&mut self, tau_s: f64, value: f64) {
        if value.is_finite() {
            self.sum += value;
            self.means.push((tau_s, self.sum / (self.means.len() + 1) as f64));
        }
    }

    /// The mean over every loaded reading (None: none).
    pub fn whole(&self) -> Option<f64> {
        self.means.last().map(|m| m.1)
    }

    /// The mean at `tau_s` after the load-on (of the loaded readings at or before it; past the last, the
    /// whole discharge's); None before the first.
    pub fn at(&self, tau_s: f64) -> Option<f64> {
        let k = self.means.partition_point(|(t, _)| *t <= tau_s + 1e-9);
        (k > 0).then(|| self.means[k - 1].1)
    }
}

/// The temperature input of a discharge at `tau_s` after its load-on: its loaded readings' mean temperature so
/// far (`own`) less the mean of the same, at the same time after their load-on, over `refs` (the discharges
/// before it in a learner's window run at the same ambient: a cell moved to another chamber, or a sensor that
/// shifts, is not a warmer discharge). A cell warms through a discharge, so the mean so far alone would tell
/// the time into the discharge more than how warm this discharge runs. None without a reference.
pub fn warmth_k<'h>(own: &LoadedMean, refs: impl IntoIterator<Item = &'h LoadedMean>, tau_s: f64) -> Option<f64> {
    let own = own.at(tau_s)?;
    let (sum, n) = refs.into_iter().filter_map(|h| h.at(tau_s)).fold((0.0, 0usize), |(s, n), t| (s + t, n + 1));
    (n > 0).then(|| own - sum / n as f64)
}

/// The learner on a live stream's record of its own ends of discharge ([`crate::stream`], the `ukf_learned`
/// kind), as `bcal calibrate`'s `ukf_learned` learns on the joint UKF's record
/// (`bcal_realcell::tune::learn_on_record`): per share of the discharge ([`EOD_FRACTIONS_PCT`]) the end the
/// stream delivers is moved by the signed error (% of the discharge) the learner expects of it from the
/// discharges followed to their cut-off before, the rest before this one, how warm it runs against the
/// discharges before it that started at its temperature and how far its current moved from the last
/// discharge's ([`current_switch`]), and the moved and unmoved are blended by their
/// records ([`crate::blend`]). The end only: a stream measures a discharge's capacity once it has ended, so
/// it has none to move while the discharge runs.
#[derive(Clone, Debug, Default)]
pub struct EndRecord {
    /// Per share, every discharge that counted since the stream began: its entry (a NaN error where it was not
    /// followed to its cut-off, as `bcal calibrate`'s record has one).
    entries: [Vec<Entry>; EOD_FRACTIONS_PCT.len()],
    /// The last [`RECORD_WINDOW`] + 1 counted discharges with a temperature: their running temperature and
    /// load-on temperature, K, the references of the temperature input.
    past: VecDeque<(LoadedMean, f64)>,
    /// Whether the current discharge's load has come on, its running temperature and the first temperature
    /// read under its load, K (None: none read yet; readings without a temperature are not read as the
    /// ambient a stream fills in, which would be a temperature the cell never had) ...
    started: bool,
    heat: LoadedMean,
    start_k: Option<f64>,
    /// ... and, once it has been followed to its cut-off, its signed error per share, % of the discharge, and
    /// the time after its load-on the error was taken at, s.
    scored: Option<[Option<(f64, f64)>; EOD_FRACTIONS_PCT.len()]>,
    /// Per share, the learner fitted on the record (None: too short a record) ...
    fitted: [Option<Learned>; EOD_FRACTIONS_PCT.len()],
    /// ... the absolute errors, moved and unmoved, of the discharges closed since it was first fitted ...
    pairs: [Vec<(f64, f64)>; EOD_FRACTIONS_PCT.len()],
    /// ... and the moved end's weight learned from them (None: too few yet; the end is not moved).
    weights: [Option<f64>; EOD_FRACTIONS_PCT.len()],
}

impl EndRecord {
    /// The current discharge's load came on.
    pub fn load_on(&mut self) {
        self.started = true;
        self.heat = LoadedMean::default();
        self.start_k = None;
    }

    /// A loaded reading of the current discharge, `tau_s` after its load-on, at a cell temperature of
    /// `temperature_k` (NaN: the reading gave none).
    pub fn push(&mut self, tau_s: f64, temperature_k: f64) {
        if !self.started {
            return;
        }
        if temperature_k.is_finite() {
            self.heat.push(tau_s, temperature_k);
            self.start_k.get_or_insert(temperature_k);
        }
    }

    /// The temperature input of the current discharge at `tau_s` after its load-on ([`warmth_k`]) against the
    /// last discharges that started within [`crate::recentre::SAME_AMBIENT_K`] of it.
    fn warmth(&self, tau_s: f64) -> Option<f64> {
        self.warmth_of(&self.heat, self.start_k?, tau_s)
    }

    /// The same of a discharge's `heat` whose load came on at `start_k`.
    fn warmth_of(&self, heat: &LoadedMean, start_k: f64, tau_s: f64) -> Option<f64> {
        let same = |k: f64| (k - start_k).abs() <= crate::recentre::SAME_AMBIENT_K;
        warmth_k(heat, self.past.iter().filter(|(_, k)| same(*k)).map(|(h, _)| h), tau_s)
    }

    /// The end delivered at share index `b` of a discharge loaded at `load_on_s` and `tau_s` into it, after a
    /// rest of `rest_before_s`, its current input `switch` by then ([`current_switch`]; the stream tracks the
    /// currents, for its twins too), where the stream's rules give `eod_s`, and the moved end's weight in it;
    /// None where the learner does not move it (too short a record, or too few discharges to weigh it by).
    pub fn moved(
        &self,
        b: usize,
        eod_s: f64,
        load_on_s: f64,
        tau_s: f64,
        rest_before_s: Option<f64>,
        switch: Option<f64>,
    ) -> Option<(f64, f64)> {
        let (learned, w) = (self.fitted[b].as_ref()?, self.weights[b]?);
        let x = learned.expected(rest_before_s, self.warmth(tau_s), switch)?;
        // An error in % of the discharge, the predicted one standing for it.
        let shift_s = x / 100.0 * (eod_s - load_on_s).max(0.0);
        Some((crate::blend::blended(w, eod_s - shift_s, eod_s), w))
    }

    /// The current discharge was followed to its cut-off: its signed error per share (predicted minus
    /// measured, % of the discharge) of the end the rules gave, and the time after the load-on it was taken
    /// at, s (None at a share where no prediction had been made by then).
    pub fn score(&mut self, errors: [Option<(f64, f64)>; EOD_FRACTIONS_PCT.len()]) {
        self.scored = Some(errors);
    }

    /// The current discharge is over (the rest before it `rest_before_s`, its loaded readings' running
    /// `current`, the last counted discharge's mean current `before_a`): it joins the record where its load
    /// came on, and the learner is fitted again; a discharge that `counted` not (a load too short, a piece
    /// whose start is unseen) leaves the record as it was.
    pub fn close(&mut self, counted: bool, rest_before_s: Option<f64>, current: &LoadedMean, before_a: Option<f64>) {
        let scored = self.scored.take();
        let heat = std::mem::take(&mut self.heat);
        let start_k = self.start_k.take();
        if !std::mem::take(&mut self.started) || !counted {
            return;
        }
        for b in 0..EOD_FRACTIONS_PCT.len() {
            let at = scored.and_then(|s| s[b]);
            let temperature_k = at.zip(start_k).and_then(|((_, tau_s), k)| self.warmth_of(&heat, k, tau_s));
            let current_switch = at.and_then(|(_, tau_s)| Transition { before_a, now_a: current.at(tau_s) }.switch());
            let error = at.map_or(f64::NAN, |(e, _)| e);
            let expected =
                self.fitted[b].as_ref().and_then(|l| l.expected(rest_before_s, temperature_k, current_switch));
            if let Some(x) = expected {
                self.pairs[b].push(((error - x).abs(), error.abs()));
            }
            self.entries[b].push(Entry { error, rest_before_s, temperature_k, current_switch });
            self.fitted[b] = fit(&self.entries[b]);
            self.weights[b] = crate::blend::blend_weight(&self.pairs[b]);
        }
        let Some(start_k) = start_k else { return };
        if self.past.len() == RECORD_WINDOW + 1 {
            self.past.pop_front();
        }
        self.past.push_back((heat, start_k));
    }

    /// Per share ([`EOD_FRACTIONS_PCT`]), the moved end's weight (None: not moved yet).
    pub fn weights(&self) -> [Option<f64>; EOD_FRACTIONS_PCT.len()] {
        self.weights
    }
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

/// A current input as the fit takes it (none known: 0; a non-finite one says nothing).
fn current_input(x: Option<f64>) -> f64 {
    x.filter(|x| x.is_finite()).unwrap_or(0.0)
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
            .map(|(&error, &r)| Entry { error, rest_before_s: Some(r), temperature_k: None, current_switch: None })
            .collect()
    }

    #[test]
    fn too_short_a_record_expects_nothing() {
        let e = entries(&[0.01; MIN_RECORD_PAIRS], &[1e4; MIN_RECORD_PAIRS]);
        assert_eq!(expected_error(&e, Some(1e4), None, None), None);
        // No spread at all: nothing to scale by.
        let e = entries(&[0.0; 20], &[1e4; 20]);
        assert_eq!(expected_error(&e, Some(1e4), None, None), None);
        // A failed prediction is not part of the record.
        let mut e = entries(&[0.01; MIN_RECORD_PAIRS], &[1e4; MIN_RECORD_PAIRS]);
        e.push(Entry { error: f64::INFINITY, rest_before_s: Some(1e4), temperature_k: None, current_switch: None });
        assert_eq!(expected_error(&e, Some(1e4), None, None), None);
    }

    #[test]
    fn a_constant_bias_is_expected_again_whatever_the_rests() {
        // Every rest the same: the rest's input is constant, and the ridge keeps the fit solvable.
        let e = entries(&[0.02; 15], &[14_000.0; 15]);
        let x = expected_error(&e, Some(14_000.0), None, None).unwrap();
        assert!((x - 0.02).abs() < 1e-3 * 0.02, "{x}");
        // Unknown rests take the record's mean: the same.
        let e: Vec<Entry> = (0..15)
            .map(|_| Entry { error: 0.02, rest_before_s: None, temperature_k: None, current_switch: None })
            .collect();
        let x = expected_error(&e, None, None, None).unwrap();
        assert!((x - 0.02).abs() < 1e-3 * 0.02, "{x}");
    }

    #[test]
    fn an_error_that_follows_the_rest_is_expected_from_it() {
        // The error grows by 0.01 Ah per e-fold of rest (the cell regains charge the prior does not carry),
        // on rests of 2-8 h in no order: a discharge after a rest of a day is expected from the line, not
        // from the last error.
        let rests: Vec<f64> = (0..30).map(|k| 3600.0 * (2.0 + ((k * 7) % 13) as f64 * 0.5)).collect();
        let errors: Vec<f64> = rests.iter().map(|r| 0.01 * (r / 14_400.0).ln()).collect();
        let x = expected_error(&entries(&errors, &rests), Some(86_400.0), None, None).unwrap();
        let truth = 0.01 * (86_400.0f64 / 14_400.0).ln();
        assert!((x - truth).abs() < 0.05 * truth, "{x} against {truth}");
        // Only the last RECORD_WINDOW pairs count: an old record of another law is forgotten.
        let mut long: Vec<Entry> = entries(&[0.5; 40], &[3600.0; 40]);
        long.extend(entries(&errors, &rests));
        let y = expected_error(&long, Some(86_400.0), None, None).unwrap();
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
        let x = expected_error(&entries(&errors, &rests), Some(14_000.0), None, None).unwrap();
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
                current_switch: None,
            })
            .collect();
        let x = expected_error(&record, Some(14_000.0), Some(mean_k + 2.0), None).unwrap();
        let truth = 0.005 - 0.02;
        assert!((x - truth).abs() < 0.05 * truth.abs(), "{x} against {truth}");
        // A discharge far colder than any on the record (a sensor that shifted by 15 K) is expected as one
        // at three spreads from the mean, not on the line carried fifteen kelvin out.
        let spread_k = (temps.iter().map(|t| (t - mean_k).powi(2)).sum::<f64>() / temps.len() as f64).sqrt();
        let far = expected_error(&record, Some(14_000.0), Some(mean_k - 15.0), None).unwrap();
        let edge = 0.005 + 0.01 * MAX_TEMPERATURE_INPUT * spread_k;
        assert!((far - edge).abs() < 0.05 * edge, "{far} against {edge}");
        // Without the temperature the learner expects the record's mean error, about.
        let y = expected_error(&record, Some(14_000.0), None, None).unwrap();
        assert!((y - 0.005).abs() < 0.003, "{y}");
        // A record held at one temperature learns nothing of it: a discharge reading warmer is expected the same.
        let flat: Vec<Entry> = record.iter().map(|e| Entry { temperature_k: Some(297.0), ..*e }).collect();
        let (a, b) = (
            expected_error(&flat, Some(14_000.0), Some(297.0), None).unwrap(),
            expected_error(&flat, Some(14_000.0), Some(299.0), None).unwrap(),
        );
        assert!((a - b).abs() < 1e-12, "{a} {b}");
    }
    #[test]
    fn a_current_within_a_fifth_of_the_last_is_a_like_current() {
        assert_eq!(current_switch(2.0, 2.0), Some(0.0));
        // The cycler's noise, a square wave's mean: like currents.
        assert_eq!(current_switch(2.02, 1.98), Some(0.0));
        assert_eq!(current_switch(1.0, 1.19), Some(0.0));
        let x = current_switch(4.0, 2.0).unwrap();
        assert!((x - 2f64.ln()).abs() < 1e-12, "{x}");
        let x = current_switch(1.0, 4.0).unwrap();
        assert!((x + 4f64.ln()).abs() < 1e-12, "{x}");
        // Held within the log of MAX_CURRENT_RATIO.
        assert_eq!(current_switch(20.0, 0.1), Some(MAX_CURRENT_RATIO.ln()));
        // No current to compare: nothing known.
        assert_eq!(current_switch(2.0, 0.0), None);
        assert_eq!(current_switch(f64::NAN, 2.0), None);
        assert_eq!(current_switch(-1.0, 2.0), None);
    }

    /// A cell cycled at 1, 2 and 4 A in no order, whose calibrator carries each discharge's model error
    /// into the next (the error 0.3 + 1.2 times the current input, % of the discharge, and a fresh part of
    /// +-0.1): a discharge at 4 A after one at 1 A is expected about 1.2 ln 4 + 0.3 off, one at a like current
    /// about 0.3; without the current input the learner expects neither.
    #[test]
    fn an_error_that_follows_the_current_before_is_expected_from_it() {
        let amps = [1.0, 2.0, 4.0];
        let current = |k: usize| amps[(k * 7 + k / 3) % 3];
        let mut seed = 99u64;
        let mut fresh = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.2
        };
        let record: Vec<Entry> = (1..31)
            .map(|k| {
                let switch = current_switch(current(k), current(k - 1));
                Entry {
                    error: 0.3 + 1.2 * switch.unwrap() + fresh(),
                    rest_before_s: Some(14_000.0),
                    temperature_k: None,
                    current_switch: switch,
                }
            })
            .collect();
        let up = expected_error(&record, Some(14_000.0), None, current_switch(4.0, 1.0)).unwrap();
        let truth = 0.3 + 1.2 * 4f64.ln();
        assert!((up - truth).abs() < 0.1, "{up} against {truth}");
        let like = expected_error(&record, Some(14_000.0), None, Some(0.0)).unwrap();
        assert!((like - 0.3).abs() < 0.1, "{like}");
        // The same record without the input: the switches look like noise about their mean.
        let blind: Vec<Entry> = record.iter().map(|e| Entry { current_switch: None, ..*e }).collect();
        let x = expected_error(&blind, Some(14_000.0), None, current_switch(4.0, 1.0)).unwrap();
        assert!((x - truth).abs() > 0.5, "{x} against {truth}");
        // A cell that moved its current once in the window (a cold cell's 4 A life, then 1 A): fewer than
        // MIN_CURRENT_SWITCHES moves teach nothing, and the learner is the one without the input.
        let once: Vec<Entry> = record
            .iter()
            .enumerate()
            .map(|(k, e)| Entry { current_switch: Some(if k == 20 { -(4f64.ln()) } else { 0.0 }), ..*e })
            .collect();
        let plain: Vec<Entry> = once.iter().map(|e| Entry { current_switch: None, ..*e }).collect();
        for next in [Some(0.0), current_switch(1.0, 4.0), None] {
            let (with, without) =
                (expected_error(&once, Some(14_000.0), None, next), expected_error(&plain, Some(14_000.0), None, None));
            assert!(with.is_some() && with == without, "{with:?} {without:?}");
        }
    }

    /// A stream's record at mixed currents ([`EndRecord`]): 25 discharges at 1, 2 or 4 A in no order, the
    /// rules' error 0.2 + 1.5 times the current input (the stream hands each discharge's running current and
    /// the last one's mean at the close). The next discharge, at 4 A after 1 A, is moved by the error the line
    /// gives, times the moved end's weight; at a like current by the intercept alone. A discharge joins the
    /// record with its current input where each share was taken, not its whole discharge's (no look-ahead).
    #[test]
    fn a_streams_record_moves_the_end_by_how_far_the_current_moved() {
        let amps = [1.0, 2.0, 4.0];
        let current = |k: usize| amps[(k * 7 + k / 3) % 3];
        let feed = |rec: &mut EndRecord, a: &dyn Fn(f64) -> f64| {
            rec.load_on();
            let mut mean = LoadedMean::default();
            for i in 0..=30 {
                let tau_s = 100.0 * f64::from(i);
                rec.push(tau_s, 297.0);
                mean.push(tau_s, a(tau_s));
            }
            mean
        };
        let rest = Some(14_400.0);
        let mut rec = EndRecord::default();
        for k in 0..26 {
            let mean = feed(&mut rec, &|_| current(k));
            let e = if k == 0 { 0.2 } else { 0.2 + 1.5 * current_switch(current(k), current(k - 1)).unwrap() };
            rec.score([Some((e, 300.0)), Some((e, 1500.0)), Some((e, 2700.0))]);
            rec.close(true, rest, &mean, k.checked_sub(1).map(current));
        }
        assert!(rec.weights().iter().all(|w| w.is_some_and(|w| w > 0.9)), "{:?}", rec.weights());
        // (load-on 1000 s, the rules' end at 4000 s.)
        let shift_of = |switch: Option<f64>| {
            let (moved_s, w) = rec.moved(1, 4000.0, 1000.0, 0.0, rest, switch).expect("a learner with a weight");
            (moved_s - 4000.0) / w
        };
        let expected_s = -(0.2 + 1.5 * 4f64.ln()) / 100.0 * 3000.0;
        let shift = shift_of(current_switch(4.0, 1.0));
        assert!((shift - expected_s).abs() < 0.05 * expected_s.abs(), "moved by {shift} s, not {expected_s}");
        let shift = shift_of(current_switch(1.1, 1.0));
        assert!((shift + 0.2 / 100.0 * 3000.0).abs() < 1.0, "{shift}");
        // At 1 A until 1000 s, then 4 A, after 1 A: a like current at the first share, the mean so far later
        // (ten readings at 1 A, then six and eighteen at 4 A).
        let mut stepped = rec.clone();
        let mean = feed(&mut stepped, &|tau_s| if tau_s < 1000.0 { 1.0 } else { 4.0 });
        stepped.score([Some((0.2, 300.0)), Some((0.2, 1500.0)), Some((0.2, 2700.0))]);
        stepped.close(true, rest, &mean, Some(1.0));
        let taken: Vec<_> = stepped.entries.iter().map(|e| e.last().unwrap().current_switch).collect();
        let (mid, late) = (current_switch(34.0 / 16.0, 1.0), current_switch(82.0 / 28.0, 1.0));
        assert_eq!(taken, [Some(0.0), mid, late]);
        assert!(mid.zip(late).is_some_and(|(m, l)| 0.5 < m && m < l), "{mid:?} {late:?}");
    }

    /// A stream's record ([`EndRecord`]): 25 discharges whose load comes on at 24 C plus 2 u K (u in -1..1, in
    /// no order) and which warm by 3 K over 3000 s, the rules' error at each share 0.2 - 1.5 u % of the
    /// discharge. The next discharge, 1.6 K warmer than the record's mean, is moved by about the error the
    /// line gives (0.2 - 1.2 = -1 %: 30 s later over 3000 s), times the moved end's weight; a discharge that
    /// did not count (a load too short, a piece) leaves the record as it was; one whose load comes on 20 K
    /// away (another chamber) is compared with none of them and takes the record's mean warmth.
    #[test]
    fn a_streams_record_moves_the_end_by_how_warm_the_discharge_runs() {
        let u = |k: u64| ((k * 7) % 13) as f64 / 6.0 - 1.0;
        let feed = |rec: &mut EndRecord, start_k: f64| {
            rec.load_on();
            for i in 0..=30 {
                let tau_s = 100.0 * f64::from(i);
                rec.push(tau_s, start_k + 3.0 * tau_s / 3000.0);
            }
        };
        let rest = Some(14_400.0);
        let mut rec = EndRecord::default();
        for k in 0..25 {
            feed(&mut rec, 297.0 + 2.0 * u(k));
            let e = 0.2 - 1.5 * u(k);
            rec.score([Some((e, 300.0)), Some((e, 1500.0)), Some((e, 2700.0))]);
            rec.close(true, rest, &LoadedMean::default(), None);
        }
        assert!(rec.weights().iter().all(|w| w.is_some_and(|w| w > 0.5)), "{:?}", rec.weights());
        let mean_u = (0..25).map(u).sum::<f64>() / 25.0;
        let next_k = 297.0 + 2.0 * (mean_u + 0.8);
        // (load-on 1000 s, the rules' end at 4000 s, 1500 s in.)
        let shift_of = |rec: &EndRecord| {
            let (moved_s, w) = rec.moved(1, 4000.0, 1000.0, 1500.0, rest, None).expect("a learner with a weight");
            (moved_s - 4000.0) / w
        };
        let mut warm = rec.clone();
        feed(&mut warm, next_k);
        let shift = shift_of(&warm);
        assert!((shift - 30.0).abs() < 3.0, "moved by {shift} s, not 30");
        // A load that did not count: the same record after it.
        let mut skipped = rec.clone();
        feed(&mut skipped, 299.0);
        skipped.score([Some((5.0, 300.0)); 3]);
        skipped.close(false, rest, &LoadedMean::default(), None);
        feed(&mut skipped, next_k);
        assert_eq!(shift_of(&skipped), shift);
        // Another chamber: no reference, so the record's mean warmth.
        let mut other = rec.clone();
        feed(&mut other, next_k + 20.0);
        let at_mean = other.fitted[1].as_ref().unwrap().expected(rest, None, None).unwrap() / 100.0 * 3000.0;
        let shift = shift_of(&other);
        assert!((shift + at_mean).abs() < 1e-9, "{shift} against {at_mean}");
        assert!(shift.abs() < 10.0, "{shift}");
        // A reading without a temperature is no reading of it (not the ambient a stream fills in): the warmth
        // is that of the same discharge without it, its load-on temperature the first one read.
        let (mut gap, mut without) = (rec.clone(), rec.clone());
        gap.load_on();
        without.load_on();
        for i in 0..=30 {
            let tau_s = 100.0 * f64::from(i);
            let k = next_k + 3.0 * tau_s / 3000.0;
            gap.push(tau_s, if i < 3 { f64::NAN } else { k });
            if i >= 3 {
                without.push(tau_s, k);
            }
        }
        assert_eq!(gap.warmth(1500.0), without.warmth(1500.0));
        assert!(gap.warmth(1500.0).is_some());
        // A discharge whose readings give no temperature at all still joins the record (its error counts) but
        // is no reference for the warmth of those after it.
        let mut cold = rec.clone();
        cold.load_on();
        for i in 0..=30 {
            cold.push(100.0 * f64::from(i), f64::NAN);
        }
        cold.score([Some((0.2, 300.0)); 3]);
        cold.close(true, rest, &LoadedMean::default(), None);
        assert_eq!(cold.entries[1].len(), rec.entries[1].len() + 1);
        assert_eq!(cold.entries[1].last().unwrap().temperature_k, None);
        assert_eq!(cold.past, rec.past);
    }
}
