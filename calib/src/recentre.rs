//! End-of-discharge predictions recentred on a method's own record: a model that is wrong the same way
//! discharge after discharge (its end comes 0.25 % of the duration early on every one of B0006's, 0.3 %
//! late on B0018's) predicts better once that bias is taken off. At each share of the discharge the scores
//! read ([`EOD_FRACTIONS_PCT`]) the bias is the median of the method's signed relative errors there
//! (`(predicted - measured) / size`, size the predicted duration from the load-on, as the intervals measure
//! it) over the last [`WINDOW`] discharges that ended; a reading takes the share its own prediction puts
//! it at ([`share_bin`]). The recentred prediction is an alternative, not a replacement: it serves where it
//! has beaten the method's own on the last discharges, by the rule that gates every alternative
//! ([`crate::tune::earns`]), since a bias that flips from one discharge to the next (B0055's, after rests
//! of alternating length) is made worse by a shift. A second twin takes off what a median cannot, the part
//! of a discharge's error that follows its voltage against the discharge before at the same time since the
//! load came on ([`VoltageChange`], [`voltage_regressions`]); it serves where it beat the first. `bcal
//! calibrate` (`bcal_realcell::recentre`) and a live stream ([`crate::stream`]) both use this. Pure
//! arithmetic: nothing here reads or prints.

pub use crate::widening::{share_bin, Outcome, EOD_FRACTIONS_PCT, WINDOW};
use bcal_common::measured::scenario::Sample;

/// The signed relative error of a scored prediction: positive when the predicted end came late.
pub fn signed_error(o: &Outcome) -> f64 {
    (o.value - o.measured) / o.size
}

/// The bias at each share ([`EOD_FRACTIONS_PCT`]) from the scored predictions of the discharges that
/// ended (oldest first; only the last [`WINDOW`] count): the median signed relative error there, None at
/// a share without any.
pub fn biases(ended: &[Vec<Outcome>]) -> [Option<f64>; 3] {
    biases_of(ended.iter())
}

/// How far back a discharge's twins by current are looked for ([`Transition`]), discharges: a cell cycled
/// at three currents in no order has nine ways to move its current, so a window of [`WINDOW`] twins of one
/// reaches far back.
pub const TWIN_SPAN: usize = 30;

/// How a discharge's current stands against the discharge's before it: the mean current of its loaded
/// readings so far, A, and the mean current of the discharge before it, A (None: not known). What a
/// discharge starts from holds the model's error at the current it was measured at (the end fit, the knee),
/// so a method's bias follows the move of current from one discharge to the next (a blind cell cycled at 1,
/// 2 and 4 A in no order: the joint UKF's end at half +1.2 to +1.7 % after a lower current, -0.6 to -1.3 %
/// after a higher one).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Transition {
    pub before_a: Option<f64>,
    pub now_a: Option<f64>,
}

impl Transition {
    /// The current input of a discharge that moved its current so ([`crate::record_learner::current_switch`]).
    pub fn switch(&self) -> Option<f64> {
        crate::record_learner::current_switch(self.now_a?, self.before_a?)
    }

    /// Whether two discharges moved their current alike: each current like the other's
    /// ([`crate::record_learner::like_current`]) where both are known; one not known is alike to any.
    pub fn alike(&self, other: &Transition) -> bool {
        let like = |a: Option<f64>, b: Option<f64>| match (a, b) {
            (Some(a), Some(b)) => crate::record_learner::like_current(a, b),
            _ => true,
        };
        like(self.before_a, other.before_a) && like(self.now_a, other.now_a)
    }
}

/// The bias at each share, as [`biases`] (the last [`WINDOW`] count), from the discharges among the last
/// [`TWIN_SPAN`] that ended that moved their current as this one does (`now`; [`Transition::alike`]), where
/// at least [`MIN_TWINS`] did; else, and before the discharge's load (its current not known), from every one
/// (a median of one or two is noise: a cell cycled at three currents in no order repeats each of its nine
/// moves rarely). On a cell cycled at one current every discharge is alike, and the bias is [`biases`]'.
pub fn biases_alike(ended: &[(Transition, Vec<Outcome>)], now: &Transition) -> [Option<f64>; 3] {
    let span = &ended[ended.len().saturating_sub(TWIN_SPAN)..];
    let twins = span.iter().filter(|(t, _)| t.alike(now));
    if now.now_a.is_some() && twins.clone().count() >= MIN_TWINS {
        biases_of(twins.map(|(_, o)| o))
    } else {
        biases_of(ended.iter().map(|(_, o)| o))
    }
}

/// Fewest discharges alike in their move of current ([`Transition::alike`]) whose bias a discharge takes.
pub const MIN_TWINS: usize = 3;

/// [`biases`] of the discharges `ended` (oldest first; the last [`WINDOW`] count).
fn biases_of<'a>(ended: impl DoubleEndedIterator<Item = &'a Vec<Outcome>> + Clone) -> [Option<f64>; 3] {
    std::array::from_fn(|b| {
        let mut e: Vec<f64> = ended
            .clone()
            .rev()
            .take(WINDOW)
            .flatten()
            .filter(|o| o.fraction == EOD_FRACTIONS_PCT[b])
            .map(signed_error)
            .filter(|e| e.is_finite())
            .collect();
        bcal_common::stats::median(&mut e)
    })
}

/// The shift, s, that recentres a predicted end `eod_s` made at `t_s` of a discharge loaded at
/// `load_on_s` under `biases` (to be added to the prediction and its bounds; 0 without a bias at its share).
/// The recentred end is never before `t_s`: the discharge is still running when the prediction is made.
pub fn shift_s(biases: &[Option<f64>; 3], load_on_s: f64, t_s: f64, eod_s: f64) -> f64 {
    shift_by(biases[share_bin(load_on_s, t_s, eod_s)], load_on_s, t_s, eod_s)
}

/// The shift, s, that takes a relative `bias` (signed error, positive late) off a predicted end.
fn shift_by(bias: Option<f64>, load_on_s: f64, t_s: f64, eod_s: f64) -> f64 {
    bias.map_or(0.0, |bias| (-bias * (eod_s - load_on_s).max(1.0)).max((t_s - eod_s).min(0.0)))
}

/// Discharges the voltage-change regression learns on: the last that ended with a voltage change at the
/// share. Two coefficients want more pairs than the median's [`WINDOW`].
pub const VOLTAGE_WINDOW: usize = 15;
/// Fewest pairs a regression is fitted on.
const MIN_PAIRS: usize = 8;
/// The voltage change is averaged over the readings of the last minute (3-6 readings at a NASA cell's
/// 10-20 s sampling, 60 at 1 s), not one reading's noise.
pub const VOLTAGE_SPAN_S: f64 = 60.0;
/// Two readings compare when their currents differ by at most this share of the larger (a discharge at
/// another current, or a square wave out of step with the one before, has no voltage change).
const SAME_LOAD: f64 = 0.05;
/// Two discharges compare when they start within this of each other's temperature, K: a cell cycled at
/// several ambients (NASA's B0038-B0040 alternate 24 and 44 C) reads tens of mV apart from one to the next
/// for the temperature alone; NASA's chambers run 19 K or more apart, a chamber's own swing is 2-3 K.
pub const SAME_AMBIENT_K: f64 = 5.0;
/// Two discharges compare when they start from rest voltages within this of each other, V: one that
/// started from a partial charge (the doctor's rule: a rest more than 50 mV below its neighbours') reads
/// lower all along for the charge it lacks, which its filter already knows from that rest; its voltage
/// change, and the next discharge's against it, would enter the regression far outside the ordinary
/// discharge's range (B0055 cycle 48, 69 mV below).
pub const SAME_REST_V: f64 = 0.05;

/// How a discharge started: the temperature (its ambient, K) and the rest voltage just before its load came
/// on (V; None when it joined under load or its rest is unknown).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Start {
    pub temperature_k: f64,
    pub rest_v: Option<f64>,
}

impl Start {
    /// A discharge of `samples` whose load came on at `load_on_s`, at `temperature_k`: its rest is its last
    /// reading before the load (none when it joined under load).
    pub fn at_load_on(samples: &[Sample], load_on_s: f64, temperature_k: f64) -> Self {
        let rest_v = samples.iter().take_while(|s| s.t_s < load_on_s).last().map(|s| s.voltage_v);
        Start { temperature_k, rest_v }
    }

    /// Whether a discharge that started so compares with one that started as `other`: ambients within
    /// [`SAME_AMBIENT_K`], rest voltages (where both are known) within [`SAME_REST_V`].
    fn compares(&self, other: &Start) -> bool {
        let rest_alike = match (self.rest_v, other.rest_v) {
            (Some(a), Some(b)) => (a - b).abs() <= SAME_REST_V,
            _ => true,
        };
        (self.temperature_k - other.temperature_k).abs() <= SAME_AMBIENT_K && rest_alike
    }
}

/// The loaded readings of the discharge before: its voltage and current against the time since its load
/// came on. What the end of the next discharge follows beyond what its filter reads: a discharge whose
/// voltage runs above the one before it at the same time since the load came on lasts longer than the
/// filter predicts, on B0018 and B0006 (docs/calibrator.md, "the voltage against the discharge before").
#[derive(Clone, Debug, PartialEq)]
pub struct Previous {
    elapsed_s: Vec<f64>,
    voltage_v: Vec<f64>,
    current_a: Vec<f64>,
    /// How it started.
    start: Start,
}

impl Previous {
    /// From a discharge's readings `(time since its load came on s, voltage V, current A)`, from the
    /// load-on to the cut-off, in time order, and how it started; None with fewer than two.
    pub fn new(readings: impl IntoIterator<Item = (f64, f64, f64)>, start: Start) -> Option<Self> {
        let mut p = Previous { elapsed_s: Vec::new(), voltage_v: Vec::new(), current_a: Vec::new(), start };
        for (t, v, i) in readings {
            let later = p.elapsed_s.last().is_none_or(|&last| t > last);
            if t >= 0.0 && later && t.is_finite() && v.is_finite() && i.is_finite() {
                p.elapsed_s.push(t);
                p.voltage_v.push(v);
                p.current_a.push(i);
            }
        }
        (p.elapsed_s.len() >= 2).then_some(p)
    }

    /// Its voltage and current `elapsed_s` after its load came on, linear between its readings; None
    /// outside them.
    fn at(&self, elapsed_s: f64) -> Option<(f64, f64)> {
        let k = self.elapsed_s.partition_point(|&t| t <= elapsed_s);
        if k == 0 || (k == self.elapsed_s.len() && elapsed_s > self.elapsed_s[k - 1]) {
            return None;
        }
        if k == self.elapsed_s.len() {
            return Some((self.voltage_v[k - 1], self.current_a[k - 1]));
        }
        let (t0, t1) = (self.elapsed_s[k - 1], self.elapsed_s[k]);
        let w = (elapsed_s - t0) / (t1 - t0);
        let lerp = |x: &[f64]| x[k - 1] + w * (x[k] - x[k - 1]);
        Some((lerp(&self.voltage_v), lerp(&self.current_a)))
    }
}

/// A discharge's voltage against the one before it at the same time since the load came on, averaged
/// over the readings of the last [`VOLTAGE_SPAN_S`] that compare (the same load within 5 %), fed one
/// loaded reading at a time: `bcal calibrate` and a live stream both keep one.
#[derive(Clone, Debug)]
pub struct VoltageChange {
    previous: Option<Previous>,
    recent: std::collections::VecDeque<(f64, f64)>,
}

impl VoltageChange {
    /// For a discharge that started as `start` and follows `previous` (None: the first one, or one whose
    /// predecessor is unknown); one that started otherwise ([`Start::compares`]) does not compare.
    pub fn new(previous: Option<Previous>, start: Start) -> Self {
        let previous = previous.filter(|p| p.start.compares(&start));
        VoltageChange { previous, recent: Default::default() }
    }

    /// Takes a reading `elapsed_s` after the load came on, and returns the voltage change now (V); None
    /// without a discharge before, past its end, or without a reading that compares in the last minute.
    pub fn push(&mut self, elapsed_s: f64, voltage_v: f64, current_a: f64) -> Option<f64> {
        let prev = self.previous.as_ref()?;
        if let Some((v, i)) = prev.at(elapsed_s) {
            let same = (current_a - i).abs() <= SAME_LOAD * current_a.abs().max(i.abs());
            if same && voltage_v.is_finite() {
                self.recent.push_back((elapsed_s, voltage_v - v));
            }
        } else {
            self.recent.clear();
            return None;
        }
        while self.recent.front().is_some_and(|&(t, _)| t < elapsed_s - VOLTAGE_SPAN_S) {
            self.recent.pop_front();
        }
        (!self.recent.is_empty()).then(|| self.recent.iter().map(|&(_, d)| d).sum::<f64>() / self.recent.len() as f64)
    }
}

/// Per share ([`EOD_FRACTIONS_PCT`]), the signed relative error as a line in the voltage change, `(a, b)`
/// of `a + b dv`, by least squares over the last [`VOLTAGE_WINDOW`] discharges that ended with a voltage
/// change at the share (`ended`: each discharge's scored predictions, each with the voltage change at its
/// reading; oldest first). None with fewer than 8 pairs or voltage changes that do not vary (spread under
/// 0.1 mV).
pub fn voltage_regressions(ended: &[Vec<(Outcome, Option<f64>)>]) -> [Option<(f64, f64)>; 3] {
    std::array::from_fn(|b| {
        let mut pairs: Vec<(f64, f64)> = ended
            .iter()
            .rev()
            .filter_map(|d| {
                d.iter()
                    .find(|(o, _)| o.fraction == EOD_FRACTIONS_PCT[b])
                    .and_then(|(o, dv)| Some((dv.as_ref().copied()?, signed_error(o))))
            })
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .take(VOLTAGE_WINDOW)
            .collect();
        if pairs.len() < MIN_PAIRS {
            return None;
        }
        pairs.reverse();
        let n = pairs.len() as f64;
        let (mx, my) = (pairs.iter().map(|p| p.0).sum::<f64>() / n, pairs.iter().map(|p| p.1).sum::<f64>() / n);
        let sxx: f64 = pairs.iter().map(|p| (p.0 - mx).powi(2)).sum();
        let sxy: f64 = pairs.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
        if (sxx / n).sqrt() < 1e-4 {
            return None;
        }
        let slope = sxy / sxx;
        Some((my - slope * mx, slope))
    })
}

/// The shift, s, that takes off a predicted end the error its share's regression expects at voltage
/// change `dv` (0 without a regression there or a voltage change now); never before `t_s`, as
/// [`shift_s`].
pub fn regressed_shift_s(
    regressions: &[Option<(f64, f64)>; 3],
    dv: Option<f64>,
    load_on_s: f64,
    t_s: f64,
    eod_s: f64,
) -> f64 {
    let line = regressions[share_bin(load_on_s, t_s, eod_s)];
    shift_by(line.zip(dv).map(|((a, b), dv)| a + b * dv), load_on_s, t_s, eod_s)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn outcome(fraction: u32, value: f64, measured: f64) -> Outcome {
        Outcome { value, below: 0.0, above: 0.0, size: value, measured, fraction, start: 0.0 }
    }

    /// The voltage change reads the discharge before at the same time since its load came on, averages
    /// the last minute, leaves out readings at another load, and has nothing to say past the end of the
    /// one before, without one, or after one at another ambient.
    #[test]
    fn the_voltage_change_compares_like_with_like_over_the_last_minute() {
        // The discharge before: 2 A for 100 s, its voltage falling from 4.0 V by 1 mV a second.
        let at = |temperature_k: f64, rest_v: Option<f64>| Start { temperature_k, rest_v };
        let prev =
            Previous::new((0..=100).map(|t| (f64::from(t), 4.0 - 0.001 * f64::from(t), 2.0)), at(297.0, Some(4.19)))
                .unwrap();
        assert_eq!(prev.at(50.5).map(|(v, _)| (v * 1e4).round() / 1e4), Some(3.9495));
        assert!(prev.at(100.5).is_none() && prev.at(-1.0).is_none());
        let mut dv = VoltageChange::new(Some(prev.clone()), at(298.0, Some(4.18)));
        // 5 mV above it until 30 s, then 15 mV above: at 60 s the minute holds 31 readings of the first and
        // 30 of the second, by 90 s only the second.
        for t in 0..=100 {
            let up = if t <= 30 { 0.005 } else { 0.015 };
            let now = dv.push(f64::from(t), 4.0 - 0.001 * f64::from(t) + up, 2.0).unwrap();
            if t == 60 {
                assert!((now - (31.0 * 0.005 + 30.0 * 0.015) / 61.0).abs() < 1e-12, "{now}");
            }
            if t >= 91 {
                assert!((now - 0.015).abs() < 1e-12, "{t}: {now}");
            }
        }
        // A reading at another load does not count: one at 1 A, 100 mV higher, leaves the mean as it was.
        let mut dv = VoltageChange::new(Some(prev.clone()), at(297.0, None));
        assert!((dv.push(10.0, 4.0 - 0.010 + 0.002, 2.0).unwrap() - 0.002).abs() < 1e-12);
        assert!((dv.push(11.0, 4.0 - 0.011 + 0.100, 1.0).unwrap() - 0.002).abs() < 1e-12);
        // Past the end of the discharge before there is nothing to compare with.
        assert_eq!(dv.push(101.0, 3.0, 2.0), None);
        // Nor without one, at another load from the start, after one at another ambient (44 C after 24 C), or
        // from a rest 60 mV below the one before's (a partial charge) or above it (the one before was).
        assert_eq!(VoltageChange::new(None, at(297.0, None)).push(10.0, 4.0, 2.0), None);
        assert_eq!(VoltageChange::new(Some(prev.clone()), at(297.0, None)).push(10.0, 4.0, 4.0), None);
        assert_eq!(VoltageChange::new(Some(prev.clone()), at(317.0, None)).push(10.0, 4.0, 2.0), None);
        assert_eq!(VoltageChange::new(Some(prev.clone()), at(297.0, Some(4.13))).push(10.0, 3.95, 2.0), None);
        let partial =
            Previous::new((0..=100).map(|t| (f64::from(t), 3.9 - 0.001 * f64::from(t), 2.0)), at(297.0, Some(4.13)));
        assert_eq!(VoltageChange::new(partial, at(297.0, Some(4.19))).push(10.0, 3.99, 2.0), None);
        // Within 50 mV it compares.
        assert!(VoltageChange::new(Some(prev), at(297.0, Some(4.15))).push(10.0, 3.99, 2.0).is_some());
    }

    /// Errors that are a line in the voltage change are read back as that line from the last 15
    /// discharges, and the shift takes the expected error off; with too few discharges, or a voltage
    /// change that never varies, there is no line.
    #[test]
    fn an_error_that_follows_the_voltage_change_is_regressed_and_taken_off() {
        let ended: Vec<Vec<(Outcome, Option<f64>)>> = (0..20)
            .map(|k| {
                let dv = 0.01 * ((k as f64) * 1.3).sin();
                // The end predicted (0.002 - 0.5 dv) late, relative to its size.
                let e = 0.002 - 0.5 * dv;
                EOD_FRACTIONS_PCT.iter().map(|&f| (outcome(f, 1000.0, 1000.0 * (1.0 - e)), Some(dv))).collect()
            })
            .collect();
        for line in voltage_regressions(&ended) {
            let (a, b) = line.unwrap();
            assert!((a - 0.002).abs() < 1e-9 && (b + 0.5).abs() < 1e-9, "{a} {b}");
        }
        // A prediction of 2000 s from a load-on at 0, made at 1000 s, with the voltage 10 mV above the
        // discharge before: the line expects it 0.3 % early, so it moves 6 s later.
        let lines = voltage_regressions(&ended);
        let s = regressed_shift_s(&lines, Some(0.01), 0.0, 1000.0, 2000.0);
        assert!((s - 0.003 * 2000.0).abs() < 1e-6, "{s}");
        assert_eq!(regressed_shift_s(&lines, None, 0.0, 1000.0, 2000.0), 0.0);
        // Seven discharges are too few; a voltage change that never varies has no slope.
        assert!(voltage_regressions(&ended[..7]).iter().all(Option::is_none));
        let flat: Vec<Vec<(Outcome, Option<f64>)>> =
            (0..15).map(|_| vec![(outcome(50, 1010.0, 1000.0), Some(0.004))]).collect();
        assert!(voltage_regressions(&flat)[1].is_none());
    }

    /// A cell cycled at 1 and 4 A whose method ends 1.5 % late after a move up, 1 % early after a move down
    /// and on time at a like current: the bias a discharge takes is its twins' (the discharges that moved
    /// their current as it does), from three of them on; with fewer, every discharge's; one whose current
    /// is not known yet (before its load) takes every discharge's. A cell at one current takes the bias of
    /// every discharge, as [`biases`] does.
    #[test]
    fn the_bias_is_taken_from_the_discharges_that_moved_their_current_alike() {
        let move_of = |before_a: f64, now_a: f64| Transition { before_a: Some(before_a), now_a: Some(now_a) };
        let late = |pct: f64| vec![outcome(50, 1000.0 * (1.0 + pct / 100.0), 1000.0)];
        let mut ended = Vec::new();
        for _ in 0..4 {
            ended.push((move_of(1.0, 4.0), late(1.5)));
            ended.push((move_of(4.0, 4.0), late(0.0)));
            ended.push((move_of(4.0, 1.0), late(-1.0)));
        }
        let bias = |now: Transition| biases_alike(&ended, &now)[1].unwrap();
        assert!((bias(move_of(1.0, 4.1)) - 0.015 / 1.015).abs() < 1e-12);
        assert!((bias(move_of(3.9, 1.05)) + 0.01 / 0.99).abs() < 1e-12);
        assert_eq!(bias(move_of(4.0, 4.0)), 0.0);
        // No twin among them (2 A after 1 A): the last WINDOW discharges'.
        let all: Vec<Vec<Outcome>> = ended.iter().map(|(_, o)| o.clone()).collect();
        assert_eq!(biases_alike(&ended, &move_of(1.0, 2.0)), biases(&all));
        // Two twins are too few.
        let two = &ended[..6];
        let two_all: Vec<Vec<Outcome>> = two.iter().map(|(_, o)| o.clone()).collect();
        assert_eq!(biases_alike(two, &move_of(1.0, 4.0)), biases(&two_all));
        // Before the load, the current is not known: every discharge.
        assert_eq!(biases_alike(&ended, &Transition { before_a: Some(1.0), now_a: None }), biases(&all));
        // A long record: the twins are looked for among the last TWIN_SPAN discharges only, and the last
        // WINDOW of them count. Forty-one discharges: ten 1 -> 4 A ones 3 % late, then thirty holding four
        // 1.5 % late, then one 5 % late. The last thirty hold four twins (median 1.5 %); without the span the
        // last ten twins would reach the 3 % ones, and the first ten are those alone.
        let mut long: Vec<(Transition, Vec<Outcome>)> = (0..10).map(|_| (move_of(1.0, 4.0), late(3.0))).collect();
        for k in 0..30 {
            long.push(if k % 8 == 0 { (move_of(1.0, 4.0), late(1.5)) } else { (move_of(4.0, 4.0), late(0.0)) });
        }
        long.push((move_of(1.0, 4.0), late(5.0)));
        let b = biases_alike(&long, &move_of(1.0, 4.0))[1].unwrap();
        assert!((b - 0.015 / 1.015).abs() < 1e-12, "{b}");
        // One current: every discharge is a twin, and the bias is the plain one to the bit.
        let one: Vec<(Transition, Vec<Outcome>)> =
            (0..14).map(|k| (move_of(2.0, 2.0 + 0.01 * f64::from(k % 3)), late(f64::from(k % 5) - 1.0))).collect();
        let plain: Vec<Vec<Outcome>> = one.iter().map(|(_, o)| o.clone()).collect();
        assert_eq!(biases_alike(&one, &move_of(2.01, 1.99)), biases(&plain));
    }

    /// A method that ends 1 % late at every share is shifted back onto the measured end; the window forgets
    /// discharges older than [`WINDOW`].
    #[test]
    fn a_steady_bias_is_taken_off_and_old_discharges_are_forgotten() {
        let late: Vec<Vec<Outcome>> =
            (0..WINDOW).map(|_| EOD_FRACTIONS_PCT.iter().map(|&f| outcome(f, 1010.0, 1000.0)).collect()).collect();
        let b = biases(&late);
        for x in b {
            assert!((x.unwrap() - 10.0 / 1010.0).abs() < 1e-12);
        }
        // A new discharge, loaded at 0, predicting 2020 s at half of it: the shift takes 1 % of it off.
        let s = shift_s(&b, 0.0, 1000.0, 2020.0);
        assert!((2020.0 + s - 2000.0).abs() < 1e-9, "recentred {}", 2020.0 + s);
        // Early discharges that were far off no longer count once a window of later ones has ended.
        let mut old: Vec<Vec<Outcome>> = (0..5).map(|_| vec![outcome(50, 2000.0, 1000.0)]).collect();
        old.extend(late);
        assert_eq!(biases(&old), b);
        // No record at a share: no shift there.
        let only_half = biases(&[vec![outcome(50, 1010.0, 1000.0)]]);
        assert!(only_half[0].is_none() && only_half[2].is_none());
        assert_eq!(shift_s(&only_half, 0.0, 100.0, 2000.0), 0.0);
        // Near its end a late method's recentred end would fall before the reading: it stops at the reading.
        let s = shift_s(&b, 0.0, 2015.0, 2020.0);
        assert!((2020.0 + s - 2015.0).abs() < 1e-9, "recentred {}", 2020.0 + s);
        // A record holding a non-finite error (a degenerate discharge) leaves the bias finite.
        let mut nan = vec![vec![outcome(50, f64::NAN, 1000.0)]];
        nan.push(vec![outcome(50, 1010.0, 1000.0)]);
        assert!((biases(&nan)[1].unwrap() - 10.0 / 1010.0).abs() < 1e-12);
    }
}
