//! Every choice of a real-cell calibration is made on validation cycles: the last training cycles, measured
//! discharges of the same cell that are never judged. The streaming calibrators get the same effort: the
//! joint UKF's settings (its noise, and the factor on the prior width each discharge learns from the cell's
//! history, [`PRIOR_FACTORS`]) and the RL policy file (among the run's checkpoints) are chosen by their
//! end-of-discharge error there. Their 90 % intervals start from the validation cycles' errors and follow
//! the cell as it ages ([`crate::interval`]).

use crate::predict::Predicted;
use crate::record::CellRecord;
use crate::run::{run_sequence, Before, CycleRun, Step, Streaming};
use crate::score::{score, share_bin, CAPACITY_FRACTIONS_PCT, EOD_FRACTIONS_PCT};
use rayon::prelude::*;
use serde::Serialize;

/// Share of the training cycles (the last ones) held out for validation, and the least count.
pub const VALIDATION_SHARE: f64 = 0.25;
pub const MIN_VALIDATION: usize = 2;

/// Factors on the prior width learned from the cell's history ([`crate::prior`]) that the streaming
/// calibrators are tried with: 1 is the width as learned; more lets the readings move the estimate further,
/// less holds it nearer the prior (B0006 and B0018 chose the grid's lowest, 1, before 0.25 and 0.5 joined).
pub const PRIOR_FACTORS: [f64; 5] = [0.25, 0.5, 1.0, 2.0, 4.0];

/// The validation cycles, as indices into `train`: the last quarter of the training cycles that reach the
/// cut-off (at least [`MIN_VALIDATION`]). A short life has fewer than twice that (NASA's B0049-B0052 ran 25
/// discharges, most of B0052's files are empty, and a third trains): then every complete one but the first
/// (one of one), so the choice is weak but made and the cell still calibrates ([`validation_is_short`]); none
/// when no training cycle reaches the cut-off.
pub fn validation_records(train: &[CellRecord]) -> Vec<usize> {
    let complete: Vec<usize> = (0..train.len()).filter(|&k| train[k].eod_s.is_some()).collect();
    let n = match complete.len() {
        m @ (0 | 1) => m,
        m if m < 2 * MIN_VALIDATION => m - 1,
        m => ((m as f64 * VALIDATION_SHARE).ceil() as usize).max(MIN_VALIDATION),
    };
    complete[complete.len() - n..].to_vec()
}

/// Whether [`validation_records`] of `train` are fewer than a choice usually rests on (said in the log and
/// the report: every choice on them is weak).
pub fn validation_is_short(train: &[CellRecord]) -> bool {
    train.iter().filter(|r| r.eod_s.is_some()).count() < 2 * MIN_VALIDATION
}

/// The objective every choice minimises: the mean absolute end-of-discharge error, % of the discharge,
/// averaged over the fractions seen (10 / 50 / 90 %). Infinite when a prediction failed; NaN when no
/// discharge reached the cut-off (nothing to judge: [`online_gate`] skips such a discharge).
pub fn objective(records: &[CellRecord], runs: &[CycleRun]) -> f64 {
    objective_at(records, runs, &EOD_FRACTIONS_PCT)
}

/// [`objective`] over some of the fractions only.
fn objective_at(records: &[CellRecord], runs: &[CycleRun], fractions: &[u32]) -> f64 {
    let s = score(records, runs);
    if s.failures > 0 {
        return f64::INFINITY;
    }
    let v: Vec<f64> = fractions
        .iter()
        .filter_map(|f| s.eod_error_pct.get(&f.to_string()))
        .filter(|q| q.n > 0)
        .map(|q| q.mean)
        .collect();
    if v.is_empty() {
        return f64::NAN;
    }
    v.iter().sum::<f64>() / v.len() as f64
}

/// The per-discharge [`objective`] of `runs` along `records`, % (infinite where a prediction failed).
pub fn per_cycle(records: &[CellRecord], runs: &[CycleRun]) -> Vec<f64> {
    per_cycle_at(records, runs, &EOD_FRACTIONS_PCT)
}

fn per_cycle_at(records: &[CellRecord], runs: &[CycleRun], fractions: &[u32]) -> Vec<f64> {
    (0..records.len().min(runs.len())).map(|k| objective_at(&records[k..=k], &runs[k..=k], fractions)).collect()
}

pub use bcal_calib::tune::{earns, wins_needed, MIN_WIN_SHARE};

/// One candidate's validation figures.
#[derive(Clone, Debug, Serialize)]
pub struct Candidate {
    pub label: String,
    /// [`objective`], %.
    pub eod_error_pct: f64,
    /// Its index among the candidates [`choose`] was given.
    #[serde(skip)]
    pub index: usize,
    /// [`per_cycle`] along the validation cycles.
    #[serde(skip)]
    pub per_cycle_pct: Vec<f64>,
}

/// The first of `candidates` (best first) that [`earns`] its place against `reference` (the per-cycle
/// objective of the filter along the validation cycles), as a position in `candidates`; None when none
/// does. A mean over 10 validation cycles can be won on two or three of them, and policies chosen that way
/// lost to the filter on most of the discharges that followed (docs/calibrator.md, "where along the life
/// the policies lose").
pub fn first_consistent(candidates: &[Candidate], reference: &[f64]) -> Option<usize> {
    candidates.iter().position(|c| earns(&c.per_cycle_pct, reference))
}

/// How many of the latest ended discharges [`online_gate`] judges on (as many as the intervals learn on).
pub const GATE_WINDOW: usize = crate::interval::WINDOW;

/// Per discharge of `judged` ((alternative, base) [`objective`] pairs, in order), whether the alternative (a
/// policy, or the prior alone) serves it: when it [`earns`] its place against the base on the last
/// [`GATE_WINDOW`] discharges that ended before it and were scored for both (`history`, the validation
/// cycles, first), else the base does. The start of each discharge is all it looks at, so it runs as a cell's
/// discharges come: a policy that predicts better only at some ages of the cell is used there
/// (docs/calibrator.md, "where along the life the policies lose"). A discharge neither scored (cut short)
/// does not count; until a full window has ended, the base. A discharge that follows a rest of more than a
/// day (`after_long_rest`, one per judged discharge) goes to the base too: the window's record was made
/// after ordinary rests and does not speak for it (a prior that carried well from one daily discharge to the
/// next misses the capacity a long pause gives back; B0005, docs/realcell.md "who serves each discharge").
pub fn online_gate(history: &[(f64, f64)], judged: &[(f64, f64)], after_long_rest: &[bool]) -> Vec<bool> {
    let scored = |p: &&(f64, f64)| p.0.is_finite() || p.1.is_finite();
    let mut past: Vec<(f64, f64)> = history.iter().filter(scored).copied().collect();
    let mut out = Vec::with_capacity(judged.len());
    for (k, pair) in judged.iter().enumerate() {
        let recent = &past[past.len().saturating_sub(GATE_WINDOW)..];
        let (mine, theirs): (Vec<f64>, Vec<f64>) = recent.iter().copied().unzip();
        let unlike = after_long_rest.get(k).copied().unwrap_or(false);
        out.push(!unlike && recent.len() == GATE_WINDOW && earns(&mine, &theirs));
        if scored(&pair) {
            past.push(*pair);
        }
    }
    out
}

/// One calibrator's runs before their intervals are widened: along the validation cycles and the judged ones.
#[derive(Clone, Debug, Default)]
pub struct Runs {
    pub validation: Vec<CycleRun>,
    pub judged: Vec<CycleRun>,
}

/// Per share of the discharge ([`EOD_FRACTIONS_PCT`]), the discharges on which [`gate_runs`] served `alt`.
pub type Served = [Vec<bool>; EOD_FRACTIONS_PCT.len()];

/// `alt` where [`online_gate`] delivers it against `base`, else `base`, decided per share of the discharge
/// (each reading goes by [`share_bin`], the share its `base` prediction puts it at), each on that share's
/// EOD error: a correction can predict better at half the discharge and worse at a tenth (B0006), and a
/// reading near the start is then served by the filter, one near the middle by the policy. Validation cycles
/// are gated on the ones before them alone (they start the intervals), judged ones on every discharge that
/// ended before. Each calibrator runs every discharge from its own prior, so choosing after the fact is
/// what running the gate live would give.
pub fn gate_runs(alt: &Runs, base: &Runs, validation: &[CellRecord], judged: &[CellRecord]) -> (Runs, Served) {
    gate_runs_onto(alt, base, base, base, validation, judged)
}

/// [`gate_runs`] decided against `base` and composed onto `onto` (the same readings), a reading's share read
/// off `shares` (the calibrator's own predictions, as a live stream reads it): the prior alone is judged
/// against a calibrator's predictions as delivered (recentred where that serves, [`crate::recentre`]) and
/// served in place of them, as a live stream does.
pub fn gate_runs_onto(
    alt: &Runs,
    base: &Runs,
    onto: &Runs,
    shares: &Runs,
    validation: &[CellRecord],
    judged: &[CellRecord],
) -> (Runs, Served) {
    let (val_gates, gates) =
        share_gates(alt, base, validation, judged, |r, runs, b| per_cycle_at(r, runs, &[EOD_FRACTIONS_PCT[b]]));
    let runs = Runs {
        validation: compose(validation, &val_gates, &alt.validation, &onto.validation, &shares.validation),
        judged: compose(judged, &gates, &alt.judged, &onto.judged, &shares.judged),
    };
    (runs, gates)
}

/// Per share of the discharge ([`EOD_FRACTIONS_PCT`], by index), whether `alt` serves each discharge against
/// `base` ([`online_gate`]) by their per-discharge errors `err(records, runs, share)`: along the validation
/// cycles (each on the ones before it) and along the judged ones (on every discharge that ended before).
fn share_gates(
    alt: &Runs,
    base: &Runs,
    validation: &[CellRecord],
    judged: &[CellRecord],
    err: impl Fn(&[CellRecord], &[CycleRun], usize) -> Vec<f64>,
) -> (Served, Served) {
    let (mut val_gates, mut gates): (Served, Served) = Default::default();
    let rested = |records: &[CellRecord]| -> Vec<bool> { records.iter().map(CellRecord::after_long_rest).collect() };
    let (val_rested, judged_rested) = (rested(validation), rested(judged));
    for b in 0..EOD_FRACTIONS_PCT.len() {
        let (history, later) = error_pairs(alt, base, validation, judged, &err, b);
        val_gates[b] = online_gate(&[], &history, &val_rested);
        gates[b] = online_gate(&history, &later, &judged_rested);
    }
    (val_gates, gates)
}

/// Two methods' errors on one discharge.
type ErrorPair = (f64, f64);

/// Per discharge of the validation cycles and of the judged ones, the pair of `a`'s and `b`'s errors at
/// share index `share` (`err(records, runs, share)`, one per discharge).
fn error_pairs(
    a: &Runs,
    b: &Runs,
    validation: &[CellRecord],
    judged: &[CellRecord],
    err: &impl Fn(&[CellRecord], &[CycleRun], usize) -> Vec<f64>,
    share: usize,
) -> (Vec<ErrorPair>, Vec<ErrorPair>) {
    let pairs = |records: &[CellRecord], x: &[CycleRun], y: &[CycleRun]| -> Vec<ErrorPair> {
        err(records, x, share).into_iter().zip(err(records, y, share)).collect()
    };
    (pairs(validation, &a.validation, &b.validation), pairs(judged, &a.judged, &b.judged))
}

/// Per discharge, the capacity error of `runs` at `fraction_pct` of it against the charge the data shows
/// (what a BMS counts by the end), Ah: NaN where there is none to score (a partial start, a discharge cut
/// short), infinite where the prediction failed.
fn capacity_error_at(records: &[CellRecord], runs: &[CycleRun], fraction_pct: u32) -> Vec<f64> {
    capacity_signed_error_at(records, runs, fraction_pct).into_iter().map(f64::abs).collect()
}

/// [`capacity_error_at`] with its sign: predicted minus the data's charge, Ah.
fn capacity_signed_error_at(records: &[CellRecord], runs: &[CycleRun], fraction_pct: u32) -> Vec<f64> {
    records
        .iter()
        .zip(runs)
        .map(|(r, run)| {
            let (Some(m), Some(k)) = (r.data_capacity_ah, r.reading_at_fraction(f64::from(fraction_pct) / 100.0))
            else {
                return f64::NAN;
            };
            if r.partial_start || run.steps.is_empty() {
                return f64::NAN;
            }
            run.steps[k.min(run.steps.len() - 1)].capacity.value.map_or(f64::INFINITY, |v| v - m)
        })
        .collect()
}

/// Where the capacity of share index `b` is judged: where the scores take the capacity within the share (25,
/// 50, 100 %), since what the share serves runs to the end of the discharge, where a correction's capacity
/// drifts most.
fn capacity_scored_at(b: usize) -> u32 {
    CAPACITY_FRACTIONS_PCT
        .into_iter()
        .find(|c| share_bin(0.0, f64::from(*c), 100.0) == b)
        .unwrap_or(EOD_FRACTIONS_PCT[b])
}

/// The capacity's own gate, after [`gate_runs_onto`] has served the end of discharge: a reading's capacity
/// (value and bounds) is `alt`'s where `alt` beat `base` on the capacity error where the scores take it in
/// that share of the discharge (25, 50, 100 %; [`online_gate`], the same window, rule and long-rest
/// exception), else `base`'s, whoever served the reading's end. The two predictions are judged on their own
/// records: the one that carries the capacity better need not predict the end better (B0005, cycles 41 on,
/// capacity from half the discharge: the prior alone 0.0087 Ah, the joint UKF alone 0.0136 Ah, whose end the
/// prior served at half of 48 of 128 discharges, and its capacity with it, before this gate). `onto` holds
/// the served runs (the same readings); a reading's share is the one `base`'s predicted end puts it at.
pub fn gate_capacity(
    alt: &Runs,
    base: &Runs,
    onto: &mut Runs,
    validation: &[CellRecord],
    judged: &[CellRecord],
) -> Served {
    let (val_gates, gates) =
        share_gates(alt, base, validation, judged, |r, runs, b| capacity_error_at(r, runs, capacity_scored_at(b)));
    for (set, records, served, a, b) in [
        (&mut onto.validation, validation, &val_gates, &alt.validation, &base.validation),
        (&mut onto.judged, judged, &gates, &alt.judged, &base.judged),
    ] {
        for (k, ((run, r), (ar, br))) in set.iter_mut().zip(records).zip(a.iter().zip(b)).enumerate() {
            if ar.steps.len() != run.steps.len() || br.steps.len() != run.steps.len() {
                continue;
            }
            for ((s, sa), sb) in run.steps.iter_mut().zip(&ar.steps).zip(&br.steps) {
                let bin = sb.eod.value.map_or(0, |v| share_bin(r.load_on_s, sb.t_s, v));
                s.capacity = if served[bin][k] { sa.capacity } else { sb.capacity };
            }
        }
    }
    gates
}

/// What a streaming method delivers and why, from its own runs ([`deliver`]).
#[derive(Clone, Debug)]
pub struct Delivered {
    /// Its runs as delivered, before their intervals are widened.
    pub runs: Runs,
    /// Per share, the judged discharges where its median twin and its voltage twin served
    /// ([`crate::recentre::serve`]) ...
    pub recentred: Served,
    pub on_voltage: Served,
    /// ... its weights in the blend with the prior alone, on the end and on the capacity ([`blend_runs`]) ...
    pub eod_weights: Weights,
    pub capacity_weights: Weights,
    /// ... that blend's weights in the blend with the previous cycle's fit ...
    pub previous_eod_weights: Weights,
    pub previous_capacity_weights: Weights,
    /// ... and where the prior alone served the end and the capacity in place of the blend.
    pub prior_gate: Served,
    pub capacity_gate: Served,
}

/// The other predictions a streaming method is combined with, each as delivered (recentred where that
/// earned it): the prior alone and the previous cycle's fit carried over.
pub struct Companions<'r> {
    /// The prior alone as it runs (what the gate serves) and as delivered (what the method is blended with).
    pub prior: &'r Runs,
    pub prior_delivered: &'r Runs,
    pub previous_delivered: &'r Runs,
}

/// A streaming method's runs `own` as `bcal calibrate` delivers them: recentred where either twin earned it,
/// blended with the prior alone as delivered, that blend blended with the previous cycle's fit as delivered
/// (the prior moves the end fit by the lifetime model, the previous cycle carries the voltage fit: on cells
/// whose voltage the model gets wrong, B0025's square wave and B0055 at 4 C, the voltage fit predicts the
/// next end better than both), and held to the prior alone: it serves the end of discharge, and apart from
/// it the capacity, where it beat the blend (what it would replace) on 8 of the last 10 and in their mean
/// (issue 18, item 5). Shares are read off `own`'s predictions throughout, as a live stream reads them.
pub fn deliver(own: &Runs, with: &Companions, validation: &[CellRecord], judged: &[CellRecord]) -> Delivered {
    let (recentred_runs, recentred, on_voltage) = crate::recentre::serve(own, validation, judged);
    let (blended, eod_weights, capacity_weights) =
        blend_runs(with.prior_delivered, &recentred_runs, own, validation, judged);
    let (blended, previous_eod_weights, previous_capacity_weights) =
        blend_runs_where(with.previous_delivered, &blended, own, validation, judged, Blend::EndNotAfterLongRest);
    let (mut runs, prior_gate) = gate_runs_onto(with.prior, &blended, &blended, own, validation, judged);
    let capacity_gate = gate_capacity(with.prior, &blended, &mut runs, validation, judged);
    Delivered {
        runs,
        recentred,
        on_voltage,
        eod_weights,
        capacity_weights,
        previous_eod_weights,
        previous_capacity_weights,
        prior_gate,
        capacity_gate,
    }
}

/// `own` with the knee's move by the cell's warmth ([`Step::eod_warmth_s`]) in each end of discharge scaled, per
/// share of the discharge, to the share of it the method's record there says it still needs
/// ([`bcal_calib::end_fit::warmth_share`], on its signed errors with and without the move over the discharges
/// that ended before each, validation cycles first; the whole move until it is learned), as a live stream
/// scales it. A reading's share is the one its own predicted end puts it at. Returns the runs and, per share,
/// the judged discharges' shares of the move.
pub fn scale_warmth(own: &Runs, validation: &[CellRecord], judged: &[CellRecord]) -> (Runs, Weights) {
    let unmoved = |runs: &[CycleRun]| -> Vec<CycleRun> {
        runs.iter()
            .map(|run| CycleRun {
                cycle: run.cycle,
                steps: run
                    .steps
                    .iter()
                    .map(|s| Step { eod: s.eod.shifted(-s.eod_warmth_s), eod_warmth_s: 0.0, ..s.clone() })
                    .collect(),
            })
            .collect()
    };
    let without = Runs { validation: unmoved(&own.validation), judged: unmoved(&own.judged) };
    let (val, jud) = share_learned(
        &without,
        own,
        validation,
        judged,
        |r, runs, b| eod_signed_error_pct_at(r, runs, EOD_FRACTIONS_PCT[b]),
        bcal_calib::end_fit::warmth_share,
    );
    let set = |records: &[CellRecord], runs: &[CycleRun], shares: &Weights| {
        by_share(
            records,
            runs,
            runs,
            runs,
            |_| true,
            |k, bin, s, _| match shares[bin][k] {
                Some(a) if s.eod_warmth_s != 0.0 => Step {
                    eod: s.eod.shifted((a - 1.0) * s.eod_warmth_s),
                    eod_warmth_s: a * s.eod_warmth_s,
                    ..s.clone()
                },
                _ => s.clone(),
            },
        )
    };
    let runs = Runs { validation: set(validation, &own.validation, &val), judged: set(judged, &own.judged, &jud) };
    (runs, jud)
}

/// What [`learn_on_record`] learned, per share of the discharge ([`EOD_FRACTIONS_PCT`], by index): the
/// judged discharges' weights on the moved capacity and on the moved end.
pub struct LearnedWeights {
    pub capacity: Weights,
    pub eod: Weights,
}

/// `delivered`'s capacity and end of discharge, each blended with the same moved by what a learner on its
/// record expects ([`bcal_calib::record_learner`]): per share of the discharge, before each discharge
/// (validation cycles first) the learner fits the signed errors where the scores take the capacity in that
/// share (as [`gate_capacity`] judges it, against the data's charge, Ah) and the end (at 10 / 50 / 90 %, in %
/// of the discharge) over the discharges that ended before, with the rest before each, the mean temperature
/// of its loaded readings up to there and their mean current against the discharge before it
/// ([`CellRecord::current_before_a`]; [`bcal_calib::record_learner::current_switch`]), and moves each reading's
/// prediction (value and bounds) in that share by the error it expects from the rest before this discharge and its
/// loaded readings' mean temperature and current so far (no look-ahead). The moved and the delivered prediction
/// are then blended ([`bcal_calib::blend`]) by their squared errors over the last discharges where the learner
/// moved it: a learner that errs more gets little weight, before it has a record none. The temperature carries
/// what an isothermal model misses on a cold cell (B0055 at 4 C: the warmer a discharge runs, the more it delivers
/// and the later it ends; docs/calibrator.md, "the temperature on the record"); the current what the filter
/// carries from a discharge at another current (a cell cycled at mixed currents; "the current on the record"). A
/// reading's share is the one `shares`' predicted end puts it at. `bcal calibrate` delivers the joint UKF so
/// learned as a method of its own (`ukf_learned`) beside it.
pub fn learn_on_record(
    delivered: &Runs,
    shares: &Runs,
    validation: &[CellRecord],
    judged: &[CellRecord],
) -> (Runs, LearnedWeights) {
    use bcal_calib::recentre::Transition;
    use bcal_calib::record_learner::{fit, warmth_k, Entry, Learned, LoadedMean, RECORD_WINDOW, SAME_AMBIENT_K};
    let records: Vec<&CellRecord> = validation.iter().chain(judged).collect();
    let n_val = validation.len();
    let heat: Vec<LoadedMean> = records.iter().map(|r| r.loaded_mean(|s| s.temperature_k)).collect();
    let current: Vec<LoadedMean> = records.iter().map(|r| r.loaded_current()).collect();
    // The current input of discharge `j` at `tau_s` after its load-on, against the whole of the discharge
    // before it, both the mean of loaded readings, as a stream takes them.
    let switch = |j: usize, tau_s: f64| {
        Transition { before_a: records[j].current_before_a, now_a: current[j].at(tau_s) }.switch()
    };
    // The temperature input of discharge `j` at `tau_s` after its load-on ([`warmth_k`]), against the
    // discharges before it in a learner's window run at the same ambient.
    let anomaly = |j: usize, tau_s: f64| -> Option<f64> {
        let refs = (j.saturating_sub(RECORD_WINDOW + 1)..j)
            .filter(|&i| (records[i].ambient_k - records[j].ambient_k).abs() <= SAME_AMBIENT_K)
            .map(|i| &heat[i]);
        warmth_k(&heat[j], refs, tau_s)
    };
    // Per share, for the capacity and the end: each discharge's learner (None: no record yet) and its weight.
    type PerShare = [Vec<Option<(Learned, f64)>>; EOD_FRACTIONS_PCT.len()];
    type SignedErrors = dyn Fn(&[CellRecord], &[CycleRun], u32) -> Vec<f64>;
    let learn = |errors_at: &SignedErrors, at: &dyn Fn(usize) -> u32| {
        let mut out: PerShare = Default::default();
        for (b, slot) in out.iter_mut().enumerate() {
            let at = at(b);
            let errors: Vec<f64> = errors_at(validation, &delivered.validation, at)
                .into_iter()
                .chain(errors_at(judged, &delivered.judged, at))
                .collect();
            // Where each discharge's error is taken, s after its load-on.
            let taken_s: Vec<Option<f64>> = records
                .iter()
                .map(|r| r.reading_at_fraction(f64::from(at) / 100.0).map(|i| r.samples[i].t_s - r.load_on_s))
                .collect();
            let entries: Vec<Entry> = (0..records.len())
                .map(|j| Entry {
                    error: errors[j],
                    rest_before_s: records[j].rest_before_s,
                    temperature_k: taken_s[j].and_then(|tau| anomaly(j, tau)),
                    current_switch: taken_s[j].and_then(|tau| switch(j, tau)),
                })
                .collect();
            // (moved, delivered) absolute errors where the learner moved the prediction.
            let mut pairs: Vec<(f64, f64)> = Vec::new();
            *slot = (0..records.len())
                .map(|k| {
                    let learned = fit(&entries[..k])?;
                    let e = &entries[k];
                    let x = learned.expected(e.rest_before_s, e.temperature_k, e.current_switch);
                    let weight = bcal_calib::blend::blend_weight(&pairs);
                    if let Some(x) = x {
                        pairs.push(((errors[k] - x).abs(), errors[k].abs()));
                    }
                    weight.map(|w| (learned, w))
                })
                .collect();
        }
        out
    };
    let capacity = learn(&capacity_signed_error_at, &capacity_scored_at);
    let eod = learn(&eod_signed_error_pct_at, &|b| EOD_FRACTIONS_PCT[b]);
    let set = |records: &[CellRecord], runs: &[CycleRun], by: &[CycleRun], offset: usize| {
        by_share(
            records,
            runs,
            runs,
            by,
            |k| capacity.iter().chain(&eod).any(|per| per[offset + k].is_some()),
            |k, bin, _, so| {
                let r = &records[k];
                let t_k = anomaly(offset + k, so.t_s - r.load_on_s);
                let sw = switch(offset + k, so.t_s - r.load_on_s);
                let mut step = so.clone();
                if let Some((learned, w)) = &capacity[bin][offset + k] {
                    if let Some(x) = learned.expected(r.rest_before_s, t_k, sw) {
                        let mix = |v: Option<f64>| v.map(|v| bcal_calib::blend::blended(*w, v - x, v));
                        let c = so.capacity;
                        step.capacity = Predicted { value: mix(c.value), lo: mix(c.lo), hi: mix(c.hi) };
                    }
                }
                if let (Some((learned, w)), Some(v)) = (&eod[bin][offset + k], so.eod.value) {
                    // An error in % of the discharge, the predicted one standing for it.
                    if let Some(x) = learned.expected(r.rest_before_s, t_k, sw) {
                        let shift_s = x / 100.0 * (v - r.load_on_s).max(0.0);
                        let mix = |e: Option<f64>| e.map(|e| bcal_calib::blend::blended(*w, e - shift_s, e));
                        let e = so.eod;
                        step.eod = Predicted { value: mix(e.value), lo: mix(e.lo), hi: mix(e.hi) };
                    }
                }
                step
            },
        )
    };
    let runs = Runs {
        validation: set(validation, &delivered.validation, &shares.validation, 0),
        judged: set(judged, &delivered.judged, &shares.judged, n_val),
    };
    let weights = |per: &PerShare| -> Weights {
        std::array::from_fn(|b| per[b][n_val..].iter().map(|x| x.as_ref().map(|x| x.1)).collect())
    };
    (runs, LearnedWeights { capacity: weights(&capacity), eod: weights(&eod) })
}

/// Per discharge, the signed error of `runs`' end of discharge at `fraction_pct` of it, % of the discharge
/// (predicted minus measured, as the scores take it): NaN where there is none to score, infinite where the
/// prediction failed.
fn eod_signed_error_pct_at(records: &[CellRecord], runs: &[CycleRun], fraction_pct: u32) -> Vec<f64> {
    records
        .iter()
        .zip(runs)
        .map(|(r, run)| {
            let (Some(eod), Some(dur), Some(k)) =
                (r.eod_s, r.discharge_s(), r.reading_at_fraction(f64::from(fraction_pct) / 100.0))
            else {
                return f64::NAN;
            };
            if run.steps.is_empty() {
                return f64::NAN;
            }
            run.steps[k.min(run.steps.len() - 1)].eod.value.map_or(f64::INFINITY, |v| 100.0 * (v - eod) / dur.max(1.0))
        })
        .collect()
}

/// Per share of the discharge ([`EOD_FRACTIONS_PCT`], by index), the calibrator's weight in its blend with
/// the prior alone at each judged discharge (None: too few discharges had ended to learn one).
pub type Weights = [Vec<Option<f64>>; EOD_FRACTIONS_PCT.len()];

/// `own` blended with `prior` ([`bcal_calib::blend`]): at each reading the predicted end (value and bounds)
/// is the weighted mean of the two, the weight learned per share from both EOD errors there over the
/// discharges that ended before (validation cycles first), and the capacity likewise from both capacity
/// errors where the scores take the capacity in that share (as [`gate_capacity`] judges it). A reading's
/// share is the one `shares`' prediction puts it at (the calibrator's own, as a live stream reads it).
/// Where either has no prediction at a reading, `own`'s. Returns the blended runs and the judged
/// discharges' weights on the end and on the capacity.
pub fn blend_runs(
    prior: &Runs,
    own: &Runs,
    shares: &Runs,
    validation: &[CellRecord],
    judged: &[CellRecord],
) -> (Runs, Weights, Weights) {
    blend_runs_where(prior, own, shares, validation, judged, Blend::Both)
}

/// What [`blend_runs_where`] blends.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Blend {
    /// The end of discharge and the capacity, after any rest.
    Both,
    /// The end of discharge alone, and not after a rest of more than a day: what a fit carried over as it is
    /// (the previous cycle's) can add, which holds no fade and no recovery.
    EndNotAfterLongRest,
}

/// [`blend_runs`] of what `what` names; the rest is `own`'s (its capacity weights are then all None).
pub fn blend_runs_where(
    prior: &Runs,
    own: &Runs,
    shares: &Runs,
    validation: &[CellRecord],
    judged: &[CellRecord],
    what: Blend,
) -> (Runs, Weights, Weights) {
    let weights =
        |err: fn(&[CellRecord], &[CycleRun], usize) -> Vec<f64>| share_weights(prior, own, validation, judged, err);
    let none = |records: &[CellRecord]| -> Weights { std::array::from_fn(|_| vec![None; records.len()]) };
    let ((val_eod, mut jud_eod), (val_cap, jud_cap)) = match what {
        Blend::Both => (
            weights(|r, runs, b| per_cycle_at(r, runs, &[EOD_FRACTIONS_PCT[b]])),
            weights(|r, runs, b| capacity_error_at(r, runs, capacity_scored_at(b))),
        ),
        // The discharges after a long rest neither blend nor count in the record.
        Blend::EndNotAfterLongRest => (
            weights(|r, runs, b| {
                let e = per_cycle_at(r, runs, &[EOD_FRACTIONS_PCT[b]]);
                e.into_iter().zip(r).map(|(e, r)| if r.after_long_rest() { f64::NAN } else { e }).collect()
            }),
            (none(validation), none(judged)),
        ),
    };
    let rest_ok = |r: &CellRecord| what == Blend::Both || !r.after_long_rest();
    for w in &mut jud_eod {
        for (w, r) in w.iter_mut().zip(judged) {
            if !rest_ok(r) {
                *w = None;
            }
        }
    }
    let mix = |w: Option<f64>, o: Predicted, p: Predicted| -> Predicted {
        let (Some(w), Some(_), Some(_)) = (w, o.value, p.value) else { return o };
        let at = |a: Option<f64>, b: Option<f64>| match (a, b) {
            (Some(a), Some(b)) => Some(bcal_calib::blend::blended(w, a, b)),
            _ => a,
        };
        Predicted { value: at(o.value, p.value), lo: at(o.lo, p.lo), hi: at(o.hi, p.hi) }
    };
    let set = |records: &[CellRecord], o: &[CycleRun], p: &[CycleRun], s: &[CycleRun], we: &Weights, wc: &Weights| {
        by_share(
            records,
            p,
            o,
            s,
            |k| rest_ok(&records[k]),
            |k, bin, sp, so| {
                let mut step = so.clone();
                step.eod = mix(we[bin][k], so.eod, sp.eod);
                step.capacity = mix(wc[bin][k], so.capacity, sp.capacity);
                step
            },
        )
    };
    let runs = Runs {
        validation: set(validation, &own.validation, &prior.validation, &shares.validation, &val_eod, &val_cap),
        judged: set(judged, &own.judged, &prior.judged, &shares.judged, &jud_eod, &jud_cap),
    };
    (runs, jud_eod, jud_cap)
}

/// Per share of the discharge ([`EOD_FRACTIONS_PCT`], by index), `own`'s weight in its blend with `prior`
/// ([`bcal_calib::blend::blend_weight`]) at each discharge, by their per-discharge errors `err(records, runs,
/// share)` over the discharges that ended before it: along the validation cycles and along the judged ones
/// (the validation cycles first).
fn share_weights(
    prior: &Runs,
    own: &Runs,
    validation: &[CellRecord],
    judged: &[CellRecord],
    err: impl Fn(&[CellRecord], &[CycleRun], usize) -> Vec<f64>,
) -> (Weights, Weights) {
    share_learned(prior, own, validation, judged, err, bcal_calib::blend::blend_weight)
}

/// [`share_weights`] with what is learned from the (own, other) error pairs of the discharges that ended
/// before each: `learn`.
fn share_learned(
    other: &Runs,
    own: &Runs,
    validation: &[CellRecord],
    judged: &[CellRecord],
    err: impl Fn(&[CellRecord], &[CycleRun], usize) -> Vec<f64>,
    learn: fn(&[(f64, f64)]) -> Option<f64>,
) -> (Weights, Weights) {
    let (mut val, mut jud): (Weights, Weights) = Default::default();
    for b in 0..EOD_FRACTIONS_PCT.len() {
        let (mut past, later) = error_pairs(own, other, validation, judged, &err, b);
        val[b] = (0..past.len()).map(|k| learn(&past[..k])).collect();
        jud[b] = later
            .into_iter()
            .map(|pair| {
                let w = learn(&past);
                past.push(pair);
                w
            })
            .collect();
    }
    (val, jud)
}

/// Each discharge's readings from `alt` where its share's gate serves it, else from `onto` (the same
/// readings, so the steps pair up). A reading's share is the one `by`'s prediction puts it at (the
/// calibrator's own, which the gate was decided against), as in a live stream.
fn compose(
    records: &[CellRecord],
    gates: &Served,
    alt: &[CycleRun],
    onto: &[CycleRun],
    by: &[CycleRun],
) -> Vec<CycleRun> {
    by_share(
        records,
        alt,
        onto,
        by,
        |k| gates.iter().any(|g| g[k]),
        |k, bin, sa, so| if gates[bin][k] { sa.clone() } else { so.clone() },
    )
}

/// Each discharge `k` of `records` made anew where `touch(k)`, from its readings in `alt` and `onto` (the same
/// readings, so the steps pair up): each step is `make(k, share index, alt's step, onto's step)`, the share
/// the one `by`'s prediction puts the reading at (a reading without one: the first). A discharge left alone,
/// or whose runs do not pair up, is `onto`'s.
fn by_share(
    records: &[CellRecord],
    alt: &[CycleRun],
    onto: &[CycleRun],
    by: &[CycleRun],
    touch: impl Fn(usize) -> bool,
    make: impl Fn(usize, usize, &Step, &Step) -> Step,
) -> Vec<CycleRun> {
    records
        .iter()
        .zip(alt.iter().zip(onto).zip(by))
        .enumerate()
        .map(|(k, (r, ((a, o), b)))| {
            if !touch(k) || a.steps.len() != o.steps.len() || b.steps.len() != o.steps.len() {
                return o.clone();
            }
            let steps = a
                .steps
                .iter()
                .zip(&o.steps)
                .zip(&b.steps)
                .map(|((sa, so), sb)| {
                    let bin = sb.eod.value.map_or(0, |v| share_bin(r.load_on_s, sb.t_s, v));
                    make(k, bin, sa, so)
                })
                .collect();
            CycleRun { cycle: o.cycle, steps }
        })
        .collect()
}

/// What the validation cycles chose for one calibrator.
#[derive(Clone, Debug, Serialize)]
pub struct Choice {
    /// Index of the chosen candidate.
    #[serde(skip)]
    pub index: usize,
    pub chosen: String,
    pub validation_cycles: Vec<u32>,
    /// Every candidate, best first.
    pub candidates: Vec<Candidate>,
    /// The chosen candidate's runs along the validation cycles (their errors start its intervals).
    #[serde(skip)]
    pub runs: Vec<CycleRun>,
}

/// Chooses among `candidates` (label, calibrator) by [`objective`] on `records` (each run along them in
/// order, each discharge starting from what was known before it), and keeps the chosen one's runs with a
/// prediction at every reading.
pub fn choose(
    candidates: &[(String, Streaming<'_>)],
    records: &[CellRecord],
    before: &[Before],
    cutoff_v: f64,
) -> Option<Choice> {
    if candidates.is_empty() || records.is_empty() {
        return None;
    }
    let mut scored: Vec<Candidate> = candidates
        .par_iter()
        .enumerate()
        .map(|(k, (label, cal))| {
            let runs = run_sequence(cal, records, before, cutoff_v, &[1.0], true).pop().unwrap_or_default();
            Candidate {
                label: label.clone(),
                eod_error_pct: objective(records, &runs),
                index: k,
                per_cycle_pct: per_cycle(records, &runs),
            }
        })
        .collect();
    scored.sort_by(|a, b| a.eod_error_pct.total_cmp(&b.eod_error_pct));
    Some(chosen_at(scored, 0, candidates, records, before, cutoff_v))
}

/// The choice of `scored[position]` (candidates scored best first, as a [`Choice`] lists them), with its
/// runs along `records`.
pub fn chosen_at(
    scored: Vec<Candidate>,
    position: usize,
    candidates: &[(String, Streaming<'_>)],
    records: &[CellRecord],
    before: &[Before],
    cutoff_v: f64,
) -> Choice {
    let index = scored[position].index;
    let runs = run_sequence(&candidates[index].1, records, before, cutoff_v, &[1.0], false).pop().unwrap_or_default();
    Choice {
        index,
        chosen: candidates[index].0.clone(),
        validation_cycles: records.iter().map(|r| r.cycle).collect(),
        candidates: scored,
        runs,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Discharges `cycles` whose every reading predicts the end (measured at 100 s) `off_s` late on even
    /// cycles and as early on odd ones (interval 5 s each way), and the capacity (1 Ah) exactly.
    fn alternating(cycles: std::ops::Range<u32>, off_s: f64) -> (Vec<CellRecord>, Vec<CycleRun>) {
        use crate::predict::Predicted;
        let at = |v: f64| Predicted { value: Some(v), lo: Some(v - 5.0), hi: Some(v + 5.0) };
        cycles
            .map(|c| {
                let e = if c % 2 == 0 { off_s } else { -off_s };
                crate::record::test_discharge(c, 1.0, |_| at(100.0 + e), at(1.0))
            })
            .unzip()
    }

    /// A method that has read none of the warmth by half a discharge and 70 % of it by 90 % (its end without the
    /// knee's move errs by minus the move, then by minus 30 % of it): the move is taken whole at half and
    /// scaled to about 0.3 at 90 % once eight moved discharges have ended, so the ends there err far less than
    /// with the whole move; a discharge whose knee did not move is left as it is.
    #[test]
    fn the_knee_s_warmth_move_is_scaled_to_what_the_method_has_not_read() {
        use crate::predict::Predicted;
        let at = |v: f64| Predicted { value: Some(v), lo: Some(v - 5.0), hi: Some(v + 5.0) };
        // Each discharge's move, s (100 s long, the end measured at 100 s): no pattern, one of them none.
        let move_s = |c: u32| if c == 25 { 0.0 } else { 8.0 * ((f64::from(c) * 0.618_034).fract() - 0.5) };
        let needs = |t_s: f64| if t_s < 70.0 { 1.0 } else { 0.3 };
        let (records, runs): (Vec<CellRecord>, Vec<CycleRun>) = (1..=40)
            .map(|c| {
                let (r, mut run) = crate::record::test_discharge(c, 1.0, |t| at(100.0 - needs(t) * move_s(c)), at(1.0));
                for s in &mut run.steps {
                    s.eod = s.eod.shifted(move_s(c));
                    s.eod_warmth_s = move_s(c);
                }
                (r, run)
            })
            .unzip();
        let runs = Runs { validation: runs[..10].to_vec(), judged: runs[10..].to_vec() };
        let (scaled, shares) = scale_warmth(&runs, &records[..10], &records[10..]);
        // Learned on the validation cycles before the first judged discharge.
        assert!(shares.iter().all(|s| s.iter().all(Option::is_some)), "{shares:?}");
        assert!(shares[1].iter().flatten().all(|a| (a - 1.0).abs() < 1e-9), "{:?}", shares[1]);
        assert!(shares[2].iter().flatten().all(|a| (a - 0.3).abs() < 1e-9), "{:?}", shares[2]);
        let error_at = |run: &CycleRun, t: usize| run.steps[t].eod.value.unwrap() - 100.0;
        for (k, (s, r)) in scaled.judged.iter().zip(&runs.judged).enumerate() {
            let c = 11 + k as u32;
            assert!(error_at(s, 50).abs() < 1e-9 && error_at(s, 90).abs() < 1e-9, "cycle {c}: {:?}", error_at(s, 90));
            assert!((error_at(r, 90) - 0.7 * move_s(c)).abs() < 1e-9, "the whole move errs");
            assert!((s.steps[90].eod_warmth_s - 0.3 * move_s(c)).abs() < 1e-9);
        }
    }

    fn candidate(index: usize, per_cycle_pct: Vec<f64>) -> Candidate {
        let eod_error_pct = per_cycle_pct.iter().sum::<f64>() / per_cycle_pct.len() as f64;
        Candidate { label: format!("c{index}"), eod_error_pct, index, per_cycle_pct }
    }

    /// The last quarter of the complete training cycles validates (at least two); a short life, fewer than
    /// four complete, every complete one but the first (one of one), flagged short; none of none. Cycles cut
    /// short never validate.
    #[test]
    fn validation_takes_the_last_complete_cycles_and_a_short_life_all_but_its_first() {
        let records = |complete: &[bool]| -> Vec<CellRecord> {
            let p = Predicted { value: Some(1.0), lo: None, hi: None };
            (0..complete.len())
                .map(|k| {
                    let (r, _) = crate::record::test_discharge(k as u32 + 1, 1.0, |_| p, p);
                    CellRecord { eod_s: complete[k].then_some(100.0), ..r }
                })
                .collect()
        };
        let at = |complete: &[bool]| (validation_records(&records(complete)), validation_is_short(&records(complete)));
        assert_eq!(at(&[true; 12]), ((9..12).collect(), false));
        assert_eq!(at(&[true; 4]), (vec![2, 3], false));
        assert_eq!(at(&[true, false, true, true, false]), (vec![2, 3], true));
        assert_eq!(at(&[false, true]), (vec![1], true));
        assert_eq!(at(&[false, false]), (vec![], true));
    }

    /// A candidate that wins the mean on two cycles and loses the other eight is passed over for one that
    /// wins on eight; with neither, none is delivered; a tie is not a win.
    #[test]
    fn a_policy_must_beat_the_filter_on_most_validation_cycles() {
        let filter = vec![0.5; 10];
        let lucky = candidate(3, [vec![0.0, 0.0], vec![0.55; 8]].concat()); // mean 0.44, 2 wins
        let steady = candidate(7, [vec![0.45; 8], vec![0.6; 2]].concat()); // mean 0.48, 8 wins
        let seven = candidate(1, [vec![0.4; 7], vec![0.55; 3]].concat()); // mean 0.445, 7 wins
        assert_eq!(first_consistent(&[lucky.clone(), steady.clone()], &filter), Some(1));
        assert_eq!(first_consistent(&[lucky.clone(), seven.clone()], &filter), None);
        assert_eq!(first_consistent(&[steady.clone(), lucky], &filter), Some(0));
        // Eight wins but a worse mean: not delivered.
        let worse = candidate(2, [vec![0.49; 8], vec![2.0; 2]].concat());
        assert_eq!(first_consistent(&[worse], &filter), None);
        assert_eq!(first_consistent(&[candidate(0, filter.clone())], &filter), None);
        assert_eq!(first_consistent(&[steady], &[]), None);
    }

    /// The gate delivers the policy once it has won 8 of the last 10 ended discharges and the mean, takes
    /// it back as soon as that stops holding, looks only at discharges that ended before, and skips the ones
    /// neither method scored.
    #[test]
    fn the_gate_follows_the_policys_recent_record() {
        let lose = (0.6, 0.5);
        let win = (0.4, 0.5);
        let unscored = (f64::INFINITY, f64::INFINITY);
        // Validation: 7 wins of 10 (the losses oldest), not enough for the first judged discharge.
        let history = [vec![lose; 3], vec![win; 7]].concat();
        let judged = [vec![win; 3], vec![unscored], vec![lose; 4]].concat();
        // Wins in the window before each judged discharge: 7, 8, 9, 10, 10 (the unscored one left out), 9, 8, 7.
        assert_eq!(online_gate(&history, &judged, &[]), vec![false, true, true, true, true, true, true, false]);
        // The same, the third judged discharge after a rest of two days: the base serves it, the record goes on.
        let rested = [false, false, true];
        assert_eq!(online_gate(&history, &judged, &rested), vec![false, true, false, true, true, true, true, false]);
        // Eight wins but a mean lost to one bad discharge: not delivered.
        let history = [vec![win; 8], vec![(9.0, 0.5); 2]].concat();
        assert_eq!(online_gate(&history, &[win], &[]), vec![false]);
        // Fewer than a full window ended before: the filter.
        assert_eq!(online_gate(&[], &[win; 11], &[]), [vec![false; 10], vec![true]].concat());
        // A policy whose prediction failed loses that discharge.
        let history = [vec![win; 8], vec![(f64::INFINITY, 0.5); 2]].concat();
        assert_eq!(online_gate(&history, &[win], &[]), vec![false]);
    }

    /// A discharge of 100 s whose readings predict the end at `eod_at(t)`.
    fn discharge(cycle: u32, eod_at: impl Fn(f64) -> f64) -> (CellRecord, CycleRun) {
        use crate::predict::Predicted;
        let at = |t: f64| Predicted { value: Some(eod_at(t)), lo: None, hi: None };
        crate::record::test_discharge(cycle, 1.0, at, Predicted { value: Some(1.0), lo: None, hi: None })
    }

    /// Records of `cycles` with runs predicting the end `f(t)` at each reading ([`discharge`]).
    fn build(cycles: std::ops::Range<u32>, f: &dyn Fn(f64) -> f64) -> (Vec<CellRecord>, Vec<CycleRun>) {
        cycles.map(|c| discharge(c, f)).unzip()
    }

    /// A policy that predicts the end better mid-discharge and worse near its start and end serves only the
    /// middle once it has done so on a full window; before that, and elsewhere, the filter does.
    #[test]
    fn the_gate_serves_each_share_of_a_discharge_by_its_own_record() {
        let policy = |t: f64| if (30.0..=70.0).contains(&t) { 101.0 } else { 110.0 };
        let filter = |_: f64| 102.0;
        let (validation, pv) = build(1..11, &policy);
        let (_, fv) = build(1..11, &filter);
        let (judged, pj) = build(11..14, &policy);
        let (_, fj) = build(11..14, &filter);
        let (runs, served) = gate_runs(
            &Runs { validation: pv, judged: pj.clone() },
            &Runs { validation: fv.clone(), judged: fj.clone() },
            &validation,
            &judged,
        );
        assert_eq!(served, [vec![false; 3], vec![true; 3], vec![false; 3]]);
        for (k, r) in runs.judged.iter().enumerate() {
            for t in [5, 10, 50, 90, 100] {
                let expect = if t == 50 { &pj[k] } else { &fj[k] };
                assert_eq!(r.steps[t].eod.value, expect.steps[t].eod.value, "judged {k}, t {t}");
            }
        }
        // Along the validation cycles themselves nothing ended before the first: the filter throughout.
        assert!(runs.validation.iter().zip(&fv).all(|(a, b)| a.steps[50].eod.value == b.steps[50].eod.value));
    }

    /// Composed onto other runs (the recentred ones), a reading's share is still the one the calibrator's
    /// own prediction, which the gate was decided against, puts it at.
    #[test]
    fn a_gate_composed_onto_other_runs_reads_the_share_off_the_calibrators_own_prediction() {
        let policy = |t: f64| if (30.0..=70.0).contains(&t) { 101.0 } else { 110.0 };
        let filter = |_: f64| 102.0;
        // Onto runs whose end is far out: by them, every reading would sit in the first tenth.
        let far = |_: f64| 1000.0;
        let (validation, pv) = build(1..11, &policy);
        let (_, fv) = build(1..11, &filter);
        let (_, ov) = build(1..11, &far);
        let (judged, pj) = build(11..14, &policy);
        let (_, fj) = build(11..14, &filter);
        let (_, oj) = build(11..14, &far);
        let filter_runs = Runs { validation: fv, judged: fj };
        let (runs, served) = gate_runs_onto(
            &Runs { validation: pv, judged: pj.clone() },
            &filter_runs,
            &Runs { validation: ov, judged: oj.clone() },
            &filter_runs,
            &validation,
            &judged,
        );
        assert_eq!(served, [vec![false; 3], vec![true; 3], vec![false; 3]]);
        for (k, r) in runs.judged.iter().enumerate() {
            assert_eq!(r.steps[50].eod.value, pj[k].steps[50].eod.value, "judged {k}: served at half");
            assert_eq!(r.steps[5].eod.value, oj[k].steps[5].eod.value, "judged {k}: onto at a tenth");
        }
    }

    /// The capacity is served by its own record, whoever serves the end: an alternative that predicts the
    /// end better and the capacity worse serves the end alone, one that predicts the capacity better and the
    /// end worse serves the capacity alone, and after a long rest the base serves both.
    #[test]
    fn the_capacity_is_served_by_its_own_record_whoever_serves_the_end() {
        use crate::predict::Predicted;
        let at = |v: f64| Predicted { value: Some(v), lo: Some(v - 0.1), hi: Some(v + 0.1) };
        // Each discharge ends at 100 s and delivers 1 Ah.
        let build = |cycles: std::ops::Range<u32>, eod_s: f64, cap_ah: f64| -> (Vec<CellRecord>, Vec<CycleRun>) {
            cycles.map(|c| crate::record::test_discharge(c, 1.0, |_| at(eod_s), at(cap_ah))).unzip()
        };
        let runs = |v: Vec<CycleRun>, j: Vec<CycleRun>| Runs { validation: v, judged: j };
        // `a` predicts the end better (101 against 103 s) and the capacity worse (1.05 against 1.01 Ah).
        let (validation, av) = build(1..11, 101.0, 1.05);
        let (mut judged, aj) = build(11..14, 101.0, 1.05);
        let (_, bv) = build(1..11, 103.0, 1.01);
        let (_, bj) = build(11..14, 103.0, 1.01);
        judged[2].rest_before_s = Some(3.0 * 86_400.0);
        let (a, b) = (runs(av, aj), runs(bv, bj));
        let (mut served, eod_gate) = gate_runs(&a, &b, &validation, &judged);
        let capacity_gate = gate_capacity(&a, &b, &mut served, &validation, &judged);
        assert!(eod_gate.iter().all(|g| g == &vec![true, true, false]), "{eod_gate:?}");
        assert!(capacity_gate.iter().all(|g| g.iter().all(|s| !s)), "{capacity_gate:?}");
        for (k, run) in served.judged.iter().enumerate() {
            let want_eod = if k < 2 { 101.0 } else { 103.0 };
            assert!(run.steps.iter().all(|s| s.eod.value == Some(want_eod)), "judged {k}: the end");
            assert!(run.steps.iter().all(|s| s.capacity == at(1.01)), "judged {k}: the capacity, bounds too");
        }
        // The roles swapped: the end from the better one, the capacity from the other wherever it has won.
        let (mut served, eod_gate) = gate_runs(&b, &a, &validation, &judged);
        let capacity_gate = gate_capacity(&b, &a, &mut served, &validation, &judged);
        assert!(eod_gate.iter().all(|g| g.iter().all(|s| !s)), "{eod_gate:?}");
        assert!(capacity_gate.iter().all(|g| g == &vec![true, true, false]), "{capacity_gate:?}");
        for (k, run) in served.judged.iter().enumerate() {
            let want_cap = if k < 2 { 1.01 } else { 1.05 };
            assert!(run.steps.iter().all(|s| s.eod.value == Some(101.0)), "judged {k}: the end");
            assert!(run.steps.iter().all(|s| s.capacity.value == Some(want_cap)), "judged {k}: the capacity");
        }
        // A correction whose capacity is better until the last minutes and far off at the end: the last share
        // is judged at the end, where the scores take the capacity, and is not served there.
        let drift = |runs: &[CycleRun]| -> Vec<CycleRun> {
            let mut runs = runs.to_vec();
            for run in &mut runs {
                for s in run.steps.iter_mut().filter(|s| s.t_s >= 95.0) {
                    s.capacity = at(1.3);
                }
            }
            runs
        };
        let (_, cv) = build(1..11, 103.0, 1.0);
        let (_, cj) = build(11..14, 103.0, 1.0);
        let c = runs(drift(&cv), drift(&cj));
        let mut served = b.clone();
        let capacity_gate = gate_capacity(&c, &b, &mut served, &validation, &judged);
        assert_eq!(capacity_gate, [vec![true, true, false], vec![true, true, false], vec![false; 3]]);
        for run in &served.judged[..2] {
            assert_eq!(run.steps[50].capacity.value, Some(1.0));
            assert_eq!(run.steps[100].capacity.value, Some(1.01));
        }
    }

    /// A discharge cut short before the cut-off leaves the gate's window untouched, and one after a rest of
    /// more than a day goes to the filter.
    #[test]
    fn the_gate_skips_cut_short_discharges_and_leaves_long_rests_to_the_filter() {
        use crate::predict::Predicted;
        let build = |first: u32, eod_s: &[f64]| -> (Vec<CellRecord>, Vec<CycleRun>) {
            let cap = Predicted { value: Some(1.0), lo: None, hi: None };
            (first..)
                .zip(eod_s)
                .map(|(k, e)| {
                    let eod = |_: f64| Predicted { value: Some(*e), lo: None, hi: None };
                    crate::record::test_discharge(k, 1.0, eod, cap)
                })
                .unzip()
        };
        // Each discharge ends at 100 s; the filter predicts 102 s, the policy 101 s (a win) or 105 s (a loss).
        let (win, loss, filter) = (101.0, 105.0, 102.0);
        let policy_validation = [vec![win; 2], vec![loss; 2], vec![win; 6]].concat();
        let (validation, pv) = build(1, &policy_validation);
        let (_, fv) = build(1, &[filter; 10]);
        let (mut judged, pj) = build(11, &[win; 5]);
        let (_, fj) = build(11, &[filter; 5]);
        // Judged discharge 2 was cut short (no end: not scored); discharge 4 followed two days of rest.
        judged[1].eod_s = None;
        judged[3].rest_before_s = Some(2.0 * 86_400.0);
        let (_, served) = gate_runs(
            &Runs { validation: pv.clone(), judged: pj.clone() },
            &Runs { validation: fv.clone(), judged: fj.clone() },
            &validation,
            &judged,
        );
        // 8 wins in each window (the cut-short discharge left out: counted as a tie it would push out a win
        // and leave 7 before discharge 3); discharge 4 to the filter; 9 wins before discharge 5.
        for share in &served {
            assert_eq!(share, &vec![true, true, true, false, true]);
        }
        // The roles swapped: never served.
        let (_, served) =
            gate_runs(&Runs { validation: fv, judged: fj }, &Runs { validation: pv, judged: pj }, &validation, &judged);
        assert!(served.iter().all(|g| g.iter().all(|s| !s)));
    }

    /// Two predictions that err in turn, each 2 s one way and then the other, the prior always against the
    /// calibrator: their blend errs 0 once enough discharges have ended to learn its weight, and the capacity
    /// takes its own weight from its own record (the prior's capacity 5 times nearer: 1/26 on the
    /// calibrator's). Before 8 discharges have ended, the calibrator's alone.
    #[test]
    fn a_blend_with_the_prior_weighs_each_by_its_record_and_takes_off_what_they_err_in_turn() {
        use crate::predict::Predicted;
        let at = |v: f64| Predicted { value: Some(v), lo: Some(v - 1.0), hi: Some(v + 1.0) };
        let build = |cycles: std::ops::Range<u32>, sign: f64, cap_ah: f64| -> (Vec<CellRecord>, Vec<CycleRun>) {
            cycles
                .map(|c| {
                    let e = if c % 2 == 0 { 2.0 } else { -2.0 };
                    crate::record::test_discharge(c, 1.0, |_| at(100.0 + sign * e), at(cap_ah))
                })
                .unzip()
        };
        let (validation, ov) = build(1..11, 1.0, 1.05);
        let (judged, oj) = build(11..15, 1.0, 1.05);
        let (_, pv) = build(1..11, -1.0, 1.01);
        let (_, pj) = build(11..15, -1.0, 1.01);
        let own = Runs { validation: ov, judged: oj };
        let prior = Runs { validation: pv, judged: pj };
        let (runs, eod_w, cap_w) = blend_runs(&prior, &own, &own, &validation, &judged);
        assert!(eod_w.iter().flatten().all(|w| w.is_some_and(|w| (w - 0.5).abs() < 1e-12)), "{eod_w:?}");
        let cap_want = 0.01_f64.powi(2) / (0.05_f64.powi(2) + 0.01_f64.powi(2));
        assert!(cap_w.iter().flatten().all(|w| w.is_some_and(|w| (w - cap_want).abs() < 1e-9)), "{cap_w:?}");
        for (k, run) in runs.judged.iter().enumerate() {
            for s in &run.steps {
                assert!((s.eod.value.unwrap() - 100.0).abs() < 1e-9, "judged {k}: {:?}", s.eod);
                assert!((s.eod.hi.unwrap() - 101.0).abs() < 1e-9, "judged {k}: the bounds blend too");
                let cap = cap_want * 1.05 + (1.0 - cap_want) * 1.01;
                assert!((s.capacity.value.unwrap() - cap).abs() < 1e-12, "judged {k}: {:?}", s.capacity);
            }
        }
        for (k, run) in runs.validation.iter().enumerate() {
            let blended = run.steps.iter().all(|s| (s.eod.value.unwrap() - 100.0).abs() < 1e-9);
            assert_eq!(blended, k >= bcal_calib::blend::MIN_BLEND_PAIRS, "validation {k}");
        }
    }

    /// A calibrator whose capacity errs by 0.02 Ah per e-fold of the rest before the discharge (rests of 2-8
    /// h in no order): once the learner on its record has seen enough discharges it moves the capacity onto
    /// the data's, its moved capacity takes the weight once it has beaten the delivered one on enough of
    /// them, and the end of discharge, which it predicts exactly, is left as it was.
    #[test]
    fn the_capacity_learned_on_the_record_takes_off_what_follows_the_rest() {
        use crate::predict::Predicted;
        let at = |v: f64| Predicted { value: Some(v), lo: Some(v - 0.1), hi: Some(v + 0.1) };
        let rest_s = |c: u32| 3600.0 * (2.0 + f64::from((c * 7) % 13) * 0.5);
        let error_ah = |c: u32| 0.02 * (rest_s(c) / 14_400.0).ln();
        let build = |cycles: std::ops::Range<u32>| -> (Vec<CellRecord>, Vec<CycleRun>) {
            cycles
                .map(|c| {
                    let (mut r, run) = crate::record::test_discharge(c, 1.0, |_| at(100.0), at(1.0 + error_ah(c)));
                    r.rest_before_s = Some(rest_s(c));
                    (r, run)
                })
                .unzip()
        };
        let (validation, v) = build(1..21);
        let (judged, j) = build(21..41);
        let delivered = Runs { validation: v, judged: j };
        let (runs, weights) = learn_on_own_runs(&delivered, &validation, &judged);
        let weights = weights.capacity;
        // The learner expects from the 12th discharge (11 in its record), its blend weighs it from the 20th
        // (8 discharges moved): every judged one, near all of the weight.
        let min_pairs = bcal_calib::record_learner::MIN_RECORD_PAIRS + bcal_calib::blend::MIN_BLEND_PAIRS;
        assert_eq!(min_pairs + 1, 19);
        for w in &weights {
            assert!(w.iter().all(|w| w.is_some_and(|w| w > 0.99)), "{w:?}");
        }
        for (k, run) in runs.validation.iter().enumerate() {
            let moved = run.steps[50].capacity != delivered.validation[k].steps[50].capacity;
            assert_eq!(moved, k > min_pairs, "validation {k}");
        }
        for (k, (run, d)) in runs.judged.iter().zip(&delivered.judged).enumerate() {
            let c = judged[k].cycle;
            for (s, sd) in run.steps.iter().zip(&d.steps) {
                assert_eq!(s.eod, sd.eod, "judged {k}: the end is left alone");
                let cap = s.capacity.value.unwrap();
                // Within 5 % of the error per e-fold of rest (the delivered errs by up to 0.028 Ah).
                assert!((cap - 1.0).abs() < 1e-3, "judged {k}: {cap} (erred {})", error_ah(c));
                assert!((s.capacity.hi.unwrap() - cap - 0.1).abs() < 1e-9, "judged {k}: the bounds move with it");
            }
        }
        // A calibrator that never errs: nothing to learn, nothing moved.
        let (validation, v) = build(1..21);
        let (judged, j) = build(21..41);
        let exact = |runs: Vec<CycleRun>| -> Vec<CycleRun> {
            runs.into_iter()
                .map(|mut run| {
                    run.steps.iter_mut().for_each(|s| s.capacity = at(1.0));
                    run
                })
                .collect()
        };
        let delivered = Runs { validation: exact(v), judged: exact(j) };
        let (runs, weights) = learn_on_own_runs(&delivered, &validation, &judged);
        let weights = weights.capacity;
        assert!(weights.iter().flatten().all(Option::is_none), "{weights:?}");
        for (run, d) in runs.judged.iter().zip(&delivered.judged) {
            assert!(run.steps.iter().zip(&d.steps).all(|(s, sd)| s.capacity == sd.capacity && s.eod == sd.eod));
        }
    }

    /// [`learn_on_record`] with `delivered` its own shares, each record's current compared with the one before.
    fn learn_on_own_runs(delivered: &Runs, validation: &[CellRecord], judged: &[CellRecord]) -> (Runs, LearnedWeights) {
        learn_on_record(delivered, delivered, validation, judged)
    }

    /// A life of 30 validation and 20 judged discharges (the blend's last 15 discharges then hold the
    /// learner's own record only) whose delivered end errs by `error_pct(cycle)` % of the discharge (bounds
    /// 1 % either side) and whose capacity is exact, each record set by `edit`; with the learner on its
    /// record run on it: (validation, judged, delivered, learned, weights).
    #[allow(clippy::type_complexity)]
    fn learned_end_life(
        error_pct: &dyn Fn(u32) -> f64,
        edit: &dyn Fn(u32, &mut CellRecord),
    ) -> (Vec<CellRecord>, Vec<CellRecord>, Runs, Runs, LearnedWeights) {
        use crate::predict::Predicted;
        let at = |v: f64| Predicted { value: Some(v), lo: Some(v - 1.0), hi: Some(v + 1.0) };
        let build = |cycles: std::ops::Range<u32>| -> (Vec<CellRecord>, Vec<CycleRun>) {
            cycles
                .map(|c| {
                    let (mut r, run) = crate::record::test_discharge(c, 1.0, |_| at(100.0 + error_pct(c)), at(1.0));
                    edit(c, &mut r);
                    r.rest_before_s = Some(14_400.0);
                    (r, run)
                })
                .unzip()
        };
        let (mut validation, v) = build(1..31);
        let (mut judged, j) = build(31..51);
        crate::record::set_currents_before(validation.iter_mut().chain(judged.iter_mut()));
        let delivered = Runs { validation: v, judged: j };
        let (runs, weights) = learn_on_own_runs(&delivered, &validation, &judged);
        (validation, judged, delivered, runs, weights)
    }

    /// A cold cell's calibrator whose end of discharge errs by 1 % of the discharge per K its loaded readings
    /// ran away from the record's mean (the warmer, the later the cell ends, which an isothermal model
    /// misses; 12-16 C in no order), each discharge warming by 4 K from its load-on: the learner on its
    /// record moves the end by what the temperature so far tells, at every reading, without look-ahead, onto
    /// the measured one; the capacity, exact, is left alone.
    #[test]
    fn the_end_learned_on_the_record_takes_off_what_follows_the_temperature() {
        // Each cycle's temperature at its load-on, K, 285-289 in no order (a multiplicative hash of the cycle).
        let start_k = |c: u32| 285.0 + f64::from(c.wrapping_mul(2_654_435_761) % 1000) * 0.004;
        let (validation, judged, delivered, runs, weights) = learned_end_life(&|c| start_k(c) - 286.0, &|c, r| {
            r.samples.iter_mut().for_each(|s| s.temperature_k = start_k(c) + 0.04 * s.t_s)
        });
        assert!(weights.capacity.iter().flatten().all(Option::is_none), "{:?}", weights.capacity);
        assert!(weights.eod[1].iter().all(|w| w.is_some_and(|w| w > 0.95)), "{:?}", weights.eod[1]);
        for (k, (run, d)) in runs.judged.iter().zip(&delivered.judged).enumerate() {
            let half = judged[k].reading_at_fraction(0.5).unwrap();
            let (s, sd) = (&run.steps[half], &d.steps[half]);
            let erred = sd.eod.value.unwrap() - 100.0;

            // The error is in % of the discharge, moved by the predicted one: within 3 % of it, and 0.35 %
            // besides, since each discharge is compared with the mean of the 31 before it, which wanders by
            // about 0.2 K about the 287 K the errors are drawn around.
            let within = 0.03 * erred.abs() + 0.35;
            assert!((s.eod.value.unwrap() - 100.0).abs() < within, "judged {k}: {:?} (erred {erred})", s.eod);
            assert!((s.eod.hi.unwrap() - s.eod.value.unwrap() - 1.0).abs() < 1e-9, "judged {k}: the bounds move");
            assert!(run.steps.iter().zip(&d.steps).all(|(s, sd)| s.capacity == sd.capacity), "judged {k}");
            // At every share the input is how much warmer this discharge runs than the record's at the same
            // time after the load-on (not the mean so far, which grows as the cell warms): the end is moved onto
            // the measured one at a tenth, a third and 80 % as at half.
            for f in [0.1, 0.3, 0.8] {
                let i = judged[k].reading_at_fraction(f).unwrap();
                let moved = run.steps[i].eod.value.unwrap() - d.steps[i].eod.value.unwrap();
                assert!((moved + erred).abs() < within, "judged {k}: moved {moved} at {f} (erred {erred})");
            }
        }
        // The last judged discharge run in another chamber, 20 K warmer: no discharge before it ran at that
        // ambient, so its temperature says nothing, and the end moves by what the record alone expects (about
        // the mean error, 1 %), not by a line carried 20 K out.
        let mut judged = judged;
        let last = judged.len() - 1;
        judged[last].ambient_k += 20.0;
        judged[last].samples.iter_mut().for_each(|s| s.temperature_k += 20.0);
        let (moved_runs, _) = learn_on_own_runs(&delivered, &validation, &judged);
        let half = judged[last].reading_at_fraction(0.5).unwrap();
        let moved = moved_runs.judged[last].steps[half].eod.value.unwrap()
            - delivered.judged[last].steps[half].eod.value.unwrap();
        assert!((-2.0..0.0).contains(&moved), "moved {moved}");
    }

    /// A cell cycled at 1, 2 and 4 A in no order (some discharges at the last one's current) whose
    /// calibrator's end errs by the current of the discharge before (2 % of the discharge per e-fold the
    /// current moved, 0.5 % besides): the learner on its record moves the end by what the current so far
    /// against the last discharge's tells, at every reading, onto the measured one; a discharge whose load
    /// starts at 4 A after one at 1 A is moved from its first loaded reading. No look-ahead: a discharge
    /// whose current changes at half is moved before it as before. The capacity, exact, is left alone.
    #[test]
    fn the_end_learned_on_the_record_takes_off_what_follows_the_current_before() {
        let amps = [1.0, 2.0, 4.0];
        let order = [0, 0, 1, 2, 2, 0, 1, 1, 2, 0, 2, 1, 1];
        let current_a = |c: u32| amps[order[c as usize % order.len()]];
        let error_pct = |c: u32| {
            let switch = bcal_calib::record_learner::current_switch(current_a(c), current_a(c - 1)).unwrap();
            0.5 + 2.0 * switch
        };
        let (validation, judged, delivered, runs, weights) =
            learned_end_life(&error_pct, &|c, r| r.samples.iter_mut().for_each(|s| s.current_a = current_a(c)));
        assert!(weights.capacity.iter().flatten().all(Option::is_none), "{:?}", weights.capacity);
        assert!(weights.eod[1].iter().all(|w| w.is_some_and(|w| w > 0.95)), "{:?}", weights.eod[1]);
        let (mut switched, mut like) = (0, 0);
        for (k, (run, d)) in runs.judged.iter().zip(&delivered.judged).enumerate() {
            let erred = error_pct(judged[k].cycle);
            switched += usize::from((erred - 0.5).abs() > 1.0);
            like += usize::from(erred == 0.5);
            assert!(run.steps.iter().zip(&d.steps).all(|(s, sd)| s.capacity == sd.capacity), "judged {k}");
            // The first loaded reading (the load comes on at 0 s), a tenth, half and 80 %.
            for f in [0.0, 0.1, 0.5, 0.8] {
                let i = if f == 0.0 { 0 } else { judged[k].reading_at_fraction(f).unwrap() };
                let moved = run.steps[i].eod.value.unwrap() - d.steps[i].eod.value.unwrap();
                assert!(
                    (moved + erred).abs() < 0.05 * erred.abs() + 0.05,
                    "judged {k}: moved {moved} at {f} (erred {erred})"
                );
            }
        }
        assert!(switched >= 8 && like >= 4, "of the judged discharges {switched} moved current, {like} did not");
        // The last judged discharge's current from half on changed (to 8 A): its readings before half are
        // moved as they were, the ones after by their own current so far.
        let last = judged.len() - 1;
        let half = judged[last].reading_at_fraction(0.5).unwrap();
        let mut changed = judged.clone();
        changed[last].samples[half..].iter_mut().for_each(|s| s.current_a = 8.0);
        let (again, _) = learn_on_own_runs(&delivered, &validation, &changed);
        let eod = |r: &Runs, i: usize| r.judged[last].steps[i].eod.value.unwrap();
        assert!((0..half).all(|i| eod(&again, i) == eod(&runs, i)), "a reading before half moved");
        assert!(eod(&again, half + 20) != eod(&runs, half + 20), "a reading after half did not move");
        // Each record is compared with the one before it, training or judged.
        assert_eq!(judged[0].current_before_a, Some(current_a(validation.last().unwrap().cycle)));
        assert_eq!(validation[0].current_before_a, None);
    }

    /// The prior alone is judged against what it would replace, the method as delivered, blended with it:
    /// with a method 3 s off each way in turn and a prior 2 s off the other way, the prior beats the method on
    /// every discharge and would serve every one against it, but their blend is 0.46 s off. The prior serves
    /// the first judged discharge alone, whose record (the validation cycles) holds the method unblended on
    /// its first 8, and the blend every one after.
    #[test]
    fn the_prior_alone_is_judged_against_the_blend_it_would_replace() {
        use crate::predict::Predicted;
        let build = alternating;
        let build_none = |cycles: std::ops::Range<u32>| -> (Vec<CellRecord>, Vec<CycleRun>) {
            cycles
                .map(|c| crate::record::test_discharge(c, 1.0, |_| Predicted::default(), Predicted::default()))
                .unzip()
        };
        let (validation, ov) = build(1..11, 3.0);
        let (judged, oj) = build(11..23, 3.0);
        let (_, pv) = build(1..11, -2.0);
        let (_, pj) = build(11..23, -2.0);
        let (own, prior) = (Runs { validation: ov, judged: oj }, Runs { validation: pv, judged: pj });
        // Against the method's own predictions the prior would serve every share of every judged discharge.
        let (_, against_own) = gate_runs(&prior, &own, &validation, &judged);
        assert!(against_own.iter().all(|g| g.iter().all(|s| *s)), "{against_own:?}");
        // A previous cycle with no prediction takes no part.
        let (_, nv) = build_none(1..11);
        let (_, nj) = build_none(11..23);
        let previous = Runs { validation: nv, judged: nj };
        let with = Companions { prior: &prior, prior_delivered: &prior, previous_delivered: &previous };
        let d = deliver(&own, &with, &validation, &judged);
        let first_only = [vec![true], vec![false; 11]].concat();
        assert!(d.prior_gate.iter().all(|g| g == &first_only), "{:?}", d.prior_gate);
        assert!(d.recentred.iter().chain(&d.on_voltage).all(|g| g.iter().all(|s| !s)), "no bias, no voltage change");
        let w = 4.0 / 13.0;
        for (k, run) in d.runs.judged.iter().enumerate() {
            let sign = if (k as u32 + 11).is_multiple_of(2) { 1.0 } else { -1.0 };
            let want = 100.0 + sign * if k == 0 { -2.0 } else { w * 3.0 - (1.0 - w) * 2.0 };
            assert!(run.steps.iter().all(|s| (s.eod.value.unwrap() - want).abs() < 1e-9), "judged {k}: {want}");
        }
    }

    /// The blend with the prior is blended in turn with the previous cycle's fit: a method and a prior that
    /// err alike, 3 s late and early in turn, and a previous cycle that errs the other way. From the ninth
    /// discharge that ended (validation cycles first) they take half each and their mean lands on the end,
    /// but after a rest of more than a day (the fit carries no recovery), where the method's own is given
    /// and no weight; the prior alone, 3 s off, never serves against it.
    #[test]
    fn the_previous_cycle_takes_its_weight_by_its_record() {
        let build = alternating;
        let (validation, ov) = build(1..11, 3.0);
        let (mut judged, oj) = build(11..23, 3.0);
        judged[5].rest_before_s = Some(3.0 * 86_400.0);
        let (_, qv) = build(1..11, -3.0);
        let (_, qj) = build(11..23, -3.0);
        let own = Runs { validation: ov, judged: oj };
        let previous = Runs { validation: qv, judged: qj };
        let with = Companions { prior: &own, prior_delivered: &own, previous_delivered: &previous };
        let d = deliver(&own, &with, &validation, &judged);
        assert!(d.prior_gate.iter().flatten().all(|s| !s), "{:?}", d.prior_gate);
        for w in &d.previous_eod_weights {
            for (k, w) in w.iter().enumerate() {
                assert_eq!(w.map(|w| (w - 0.5).abs() < 1e-12), (k != 5).then_some(true), "judged {k}: {w:?}");
            }
        }
        for (k, run) in d.runs.judged.iter().enumerate() {
            // Cycle 16, after the long rest: 3 s late, as the method alone.
            let want = if k == 5 { 103.0 } else { 100.0 };
            assert!(run.steps.iter().all(|s| (s.eod.value.unwrap() - want).abs() < 1e-9), "judged {k}");
        }
        for (k, run) in d.runs.validation.iter().enumerate() {
            let on_end = run.steps.iter().all(|s| (s.eod.value.unwrap() - 100.0).abs() < 1e-9);
            assert_eq!(on_end, k >= bcal_calib::blend::MIN_BLEND_PAIRS, "validation {k}");
        }
    }
}
