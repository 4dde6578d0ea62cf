//! Prediction intervals learned from how a method's predictions fared on the discharges that have ended
//! (issue 18 item 6): a 90 % half-width, per side, of `sqrt((s w)^2 + (a x)^2 + c^2)`, `w` the calibrator's own
//! half-width on that side (0 without one), `x` the size of the prediction (the predicted duration from the
//! load-on for an end of discharge, the predicted capacity for a capacity), `c` what the discharge's own start
//! adds (an end of discharge from a start read off a rest on the flat part of the open-circuit curve:
//! [`start_half`]; 0 for a capacity, and for a start near full), and `(s, a)` the pair that covers
//! [`COVER`] of the last [`WINDOW`] discharges' scored predictions, with the finite-sample rank of split
//! conformal prediction, with the narrowest intervals. `bcal calibrate` learns it on a cell's validation
//! cycles and then each judged discharge (`bcal_realcell::interval`); a live stream on the discharges it
//! has followed to their cut-off ([`crate::stream`]).
//!
//! The window's conformal rank holds when the errors to come are like the last ones. As a cell ages they
//! are not: the model's error drifts, and a long rest's jump leaves the window after ten discharges. So the
//! learned widening is scaled by [`Adapt`], adaptive conformal inference on the log of the width (Gibbs and
//! Candès, 2021): after every scored prediction the log-scale moves up by [`ADAPT_RATE`] times 0.9 on a
//! miss and down by it times 0.1 on a hit, which holds the long-run miss rate at 10 % whatever the errors
//! do, while the window sets the width's shape. Pure arithmetic: nothing here reads or prints.

use serde::Serialize;

/// How many of the latest complete discharges the error term is learned on.
pub const WINDOW: usize = 10;
/// The coverage the intervals aim at.
pub const COVER: f64 = 0.9;
/// Factors tried on the calibrator's own half-width (0: the model-error term alone).
pub const OWN_FACTORS: [f64; 5] = [0.0, 0.25, 0.5, 1.0, 2.0];
/// Shares of each discharge at which the end of discharge is predicted and scored, %.
pub const EOD_FRACTIONS_PCT: [u32; 3] = [10, 50, 90];
/// The fewest scored predictions whose conformal rank reaches [`COVER`]: with n of them the
/// `ceil((n + 1) COVER)`-th smallest error must exist, so n >= 9. With fewer, the largest error so far covers
/// only n / (n + 1) of a new one.
pub const MIN_OUTCOMES: usize = 9;

/// Step of [`Adapt`]'s log-scale per scored prediction: a miss widens the next intervals by
/// exp(0.9 x 0.1) = 9.4 %, a hit narrows them by 1 %. Not tuned on any cell: large enough to answer a run of
/// misses within a few discharges (three scored predictions each), small enough that one miss is a nudge.
pub const ADAPT_RATE: f64 = 0.1;
/// The log-scale stays within +-this (a factor of 1/8 to 8 on the learned widening).
pub const ADAPT_MAX_LOG: f64 = 2.08;

/// Which of [`EOD_FRACTIONS_PCT`] (its index) a reading at `t_s` is nearest to, by the share of the
/// discharge passed as the reading's own predicted end `eod_s` puts it (no look-ahead).
pub fn share_bin(load_on_s: f64, t_s: f64, eod_s: f64) -> usize {
    let passed_pct = 100.0 * (t_s - load_on_s) / (eod_s - load_on_s).max(1.0);
    let off = |i: usize| (f64::from(EOD_FRACTIONS_PCT[i]) - passed_pct).abs();
    (0..EOD_FRACTIONS_PCT.len()).min_by(|&i, &j| off(i).total_cmp(&off(j))).unwrap_or(0)
}

/// The standard normal quantile of [`COVER`] two-sided: a Gaussian error within +-this many sds 90 % of the time.
pub const Z_COVER: f64 = 1.645;

/// What a discharge's start adds to the 90 % half-width of its end, s: its starting charge known to
/// `share_sd` of the cell's qMobile (one sd; `bcal_common::measured::cellmodel::start_share_sd`, the rest
/// voltage's noise through the open-circuit curve's slope) shifts the end by that charge over the current,
/// for every method alike (each reads its start off the same rest). A term apart from the learned ones: the
/// discharges they are learned on mostly start full, where it is nil, so no scale learned there speaks for a
/// start on the curve's plateau. 0 without a current.
pub fn start_half(share_sd: f64, q_mobile_c: f64, current_a: f64) -> f64 {
    if current_a > 0.0 && share_sd.is_finite() {
        Z_COVER * share_sd * q_mobile_c / current_a
    } else {
        0.0
    }
}

/// One scored prediction of a finished discharge: its value, its own bounds, its size and the measurement.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Outcome {
    pub value: f64,
    /// The calibrator's own half-widths below and above the value (0 without an interval).
    pub below: f64,
    pub above: f64,
    pub size: f64,
    pub measured: f64,
    /// The share of the discharge it was scored at, % (one of the scores' fractions).
    pub fraction: u32,
    /// What its discharge's start adds to its half-width ([`start_half`]; 0: nothing).
    pub start: f64,
}

/// The widening of one prediction kind: own half-width times `own`, model error `model` times the size.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Widening {
    pub own: f64,
    pub model: f64,
    /// The discharges it was learned on.
    pub learned_on: usize,
}

impl Widening {
    /// The half-width on a side whose own half-width is `own_half`, for a prediction of size `size` whose
    /// start adds `start` ([`start_half`]).
    pub fn half(&self, own_half: f64, size: f64, start: f64) -> f64 {
        (self.own * own_half).hypot(self.model * size).hypot(start)
    }

    pub fn covers(&self, o: &Outcome) -> bool {
        let e = o.measured - o.value;
        if e >= 0.0 {
            e <= self.half(o.above, o.size, o.start)
        } else {
            -e <= self.half(o.below, o.size, o.start)
        }
    }

    /// The narrowest widening that covers the conformal share of `outcomes` (none: unchanged), learned on
    /// `discharges` discharges.
    pub fn learn(outcomes: &[Outcome], discharges: usize) -> Self {
        if outcomes.is_empty() {
            return Self { own: 1.0, model: 0.0, learned_on: 0 };
        }
        let n = outcomes.len();
        // Split conformal: the ceil((n + 1) COVER)-th smallest score covers COVER of a new one.
        let need = (((n + 1) as f64 * COVER).ceil() as usize).min(n);
        let mut best: Option<(f64, Self)> = None;
        for own in OWN_FACTORS {
            // The least model term that covers `need` outcomes: each outcome's own threshold, sorted.
            let mut thresholds: Vec<f64> = outcomes
                .iter()
                .map(|o| {
                    let e = o.measured - o.value;
                    let w = (own * if e >= 0.0 { o.above } else { o.below }).hypot(o.start);
                    if e.abs() <= w {
                        0.0
                    } else if o.size > 0.0 {
                        (e * e - w * w).sqrt() / o.size
                    } else {
                        f64::INFINITY
                    }
                })
                .collect();
            thresholds.sort_by(f64::total_cmp);
            let model = thresholds[need - 1];
            if !model.is_finite() {
                continue;
            }
            let cand = Self { own, model, learned_on: discharges };
            let width: f64 = outcomes
                .iter()
                .map(|o| cand.half(o.below, o.size, o.start) + cand.half(o.above, o.size, o.start))
                .sum();
            if best.as_ref().is_none_or(|(w, _)| width < *w - 1e-12) {
                best = Some((width, cand));
            }
        }
        best.map_or(Self { own: 1.0, model: 0.0, learned_on: discharges }, |b| b.1)
    }
}

/// The online scale of one prediction kind's widening (the module's doc).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Adapt {
    pub log_scale: f64,
}

impl Adapt {
    /// `w` with both of its terms scaled.
    pub fn scaled(&self, w: Widening) -> Widening {
        let f = self.log_scale.exp();
        Widening { own: w.own * f, model: w.model * f, ..w }
    }

    /// Takes the scored predictions of a finished discharge under the widening it ran with.
    pub fn update<'o>(&mut self, applied: &Widening, outcomes: impl IntoIterator<Item = &'o Outcome>) {
        for o in outcomes {
            let miss = f64::from(u8::from(!applied.covers(o)));
            self.log_scale =
                (self.log_scale + ADAPT_RATE * (miss - (1.0 - COVER))).clamp(-ADAPT_MAX_LOG, ADAPT_MAX_LOG);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn outcome(e: f64, own: f64) -> Outcome {
        Outcome { value: 100.0, below: own, above: own, size: 100.0, measured: 100.0 + e, fraction: 50, start: 0.0 }
    }

    #[test]
    fn the_learned_widening_covers_the_conformal_share_and_no_more() {
        // Errors of 1..=20 % of the size, own half-widths of 0.5: 19 of 20 need covering ((20 + 1) 0.9).
        let o: Vec<Outcome> =
            (1..=20).map(|k| outcome(f64::from(k) * if k % 2 == 0 { 1.0 } else { -1.0 }, 0.5)).collect();
        let w = Widening::learn(&o, 10);
        let covered = o.iter().filter(|x| w.covers(x)).count();
        assert_eq!(covered, 19, "{w:?}");
        // An own interval that already covers everything and is too wide is narrowed.
        let wide: Vec<Outcome> = (1..=20).map(|k| outcome(0.1 * f64::from(k), 10.0)).collect();
        let w = Widening::learn(&wide, 10);
        assert!(w.own < 1.0 && wide.iter().filter(|x| w.covers(x)).count() >= 19, "{w:?}");
        // Nothing learned yet: the calibrator's own interval.
        assert_eq!(Widening::learn(&[], 0), Widening { own: 1.0, model: 0.0, learned_on: 0 });
        // Nine outcomes are the fewest whose conformal rank is not the largest error's.
        let nine: Vec<Outcome> = (1..=9).map(|k| outcome(f64::from(k), 0.0)).collect();
        assert_eq!(Widening::learn(&nine[..MIN_OUTCOMES], 9).model, 0.09);
    }

    /// Discharges whose start adds a known spread (ends erring by up to +-30 on a start term of 30, as ends
    /// from a start on the flat of the voltage curve do) among ones that err by up to 5 % of their size: the
    /// start term covers its own errors, so the model term stays the one the other errors need, and the
    /// narrow intervals of the others are not widened for them.
    #[test]
    fn a_start_term_covers_the_errors_it_explains_and_leaves_the_others_narrow() {
        let mut o: Vec<Outcome> =
            (1..=20u32).map(|k| outcome(0.25 * f64::from(k) * [1.0, -1.0][k as usize % 2], 0.0)).collect();
        let alone = Widening::learn(&o, 10);
        o.extend(
            (1..=6u32)
                .map(|k| Outcome { start: 30.0, ..outcome(5.0 * f64::from(k) * [1.0, -1.0][k as usize % 2], 0.0) }),
        );
        let with = Widening::learn(&o, 10);
        assert!(o.iter().filter(|x| x.start > 0.0).all(|x| with.covers(x)), "{with:?}");
        assert!((with.model - alone.model).abs() < 0.01, "{with:?} against {alone:?}");
        // Without their start term the same errors widen every interval.
        let blind: Vec<Outcome> = o.iter().map(|x| Outcome { start: 0.0, ..*x }).collect();
        assert!(Widening::learn(&blind, 10).model > 2.0 * alone.model);
        // The online scale leaves the start term as it is.
        let adapt = Adapt { log_scale: -1.0 };
        assert_eq!(adapt.scaled(with).half(0.0, 0.0, 30.0), 30.0);
    }

    /// Errors that grow 3 % per discharge (the model's error drifting as a cell ages): a widening learned on
    /// the last ten alone lags behind them (81 % here); scaled online, the long-run miss rate comes back
    /// near 10 % (90.0 %).
    #[test]
    fn the_online_scale_holds_coverage_when_the_errors_drift() {
        let n = 200;
        let errors: Vec<f64> = (0..n)
            .map(|k| {
                let u = ((k * 7919) % 101) as f64 / 100.0; // spread over [0, 1], no order
                1.03f64.powi(k as i32) * (0.2 + u) * if k % 2 == 0 { 1.0 } else { -1.0 }
            })
            .collect();
        let run = |adaptive: bool| {
            let (mut past, mut adapt, mut hits) = (Vec::new(), Adapt::default(), 0);
            for (k, e) in errors.iter().enumerate() {
                let recent: Vec<Outcome> = past[past.len().saturating_sub(WINDOW)..].to_vec();
                let learned = Widening::learn(&recent, recent.len());
                let w = if adaptive { adapt.scaled(learned) } else { learned };
                let o = outcome(*e, 0.0);
                if k >= WINDOW {
                    hits += usize::from(w.covers(&o));
                }
                adapt.update(&w, &[o]);
                past.push(o);
            }
            hits as f64 / (n - WINDOW) as f64
        };
        let (window, online) = (run(false), run(true));
        eprintln!("coverage: window alone {window:.3}, scaled online {online:.3}");
        assert!(window < 0.83, "the window alone covers {window}");
        assert!((0.85..=0.95).contains(&online), "scaled online it covers {online}");
    }

    #[test]
    fn a_reading_takes_the_share_its_own_prediction_says_has_passed() {
        // Load on at 100 s, end predicted at 1100 s: 150 s is 5 % in, 600 s 50 %, 1000 s 90 %.
        assert_eq!([150.0, 600.0, 1000.0].map(|t| share_bin(100.0, t, 1100.0)), [0, 1, 2]);
        // A prediction already passed (the model is at its cut-off now) reads as late in the discharge.
        assert_eq!(share_bin(100.0, 1200.0, 1200.0), 2);
    }
}
