//! What a discharge that ended hands on to the next (issue 18, item 5): its **end fit**, the offline fit's
//! Ro with the qMobile that puts the model's end of discharge where the cell ended ([`bcal_calib::end_fit`]:
//! at the measured cut-off crossing where the model reaches the cut-off itself; where it ends above it, an
//! electrode's surface emptied, where the cell last passed the voltage the model ends at, the charge from
//! there to the cut-off kept apart as the model's knee), as a live stream carries it ([`bcal_calib::stream`]).
//! The prior walk ([`crate::prior`]) moves it by the lifetime model and learns its width from consecutive
//! ones; the model's knees ([`crate::run::Knee`]) are measured against it and added back to every prediction,
//! from any start (until 2026-11-30 the end fit held the knee as more qMobile, of which a discharge started
//! at a share f of full gets f: the blind "B0049"'s start at 25 % ended 44 s early).
//!
//! Where the model is wrong (NASA cells: electrode balance, kinetics) a fit that makes its voltage right and
//! one that makes its end right differ, and the next end is what is predicted. On B0005, B0006 and B0018 the
//! two give their prior alone the same one-ahead error along the training cycles (within 0.05 points), and
//! the end fit the better joint UKF on every judged life (docs/realcell.md, "what a discharge hands on").
//! The references that carry a fit (the previous cycle's, the oracle's) keep the voltage fit and its knee.
//! A discharge whose end no qMobile within the calibrator's range reaches hands on its voltage fit. One that
//! stopped above its cut-off, or started from a partial charge as the discharges before it show, hands on what
//! was carried into it ([`over_cut_short`]): a fit on part of a discharge does not pin qMobile down.

use crate::prior::{learn_width, PriorWalk, RestWidth};
use crate::record::CellRecord;
use crate::run::{knees_along, Before, Knees};
use bcal_common::battery::Degradation;
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::tracker::TrackerSpec;
use bcal_doctor::lifetime::LifetimeModel;
use std::collections::BTreeMap;

/// Every record's end fit (its voltage fit's Ro and model), with how many records kept their voltage fit
/// (no qMobile in range reaches the end) or, cut short or started far short of full, handed on what was carried
/// into them ([`over_cut_short`]; `before_first`: what the first record starts from).
pub fn end_fits(
    spec: &TrackerSpec,
    records: &[CellRecord],
    fits: &[(Degradation, ModelExtension)],
    before_first: Option<&(Degradation, ModelExtension)>,
    cutoff_v: f64,
) -> (Vec<(Degradation, ModelExtension)>, usize) {
    let mut kept = 0;
    let out: Vec<(Degradation, ModelExtension)> = records
        .iter()
        .zip(fits)
        .map(|(r, (d, ext))| {
            let s = TrackerSpec { model: ext.clone(), cutoff_v, ..spec.clone() };
            let q = r
                .eod_s
                .and_then(|end| bcal_calib::end_fit::end_fit(&s, &r.samples, end, d.r_o_ohm))
                .map(|f| f.q_mobile_c);
            kept += usize::from(q.is_none() || !r.measured_its_charge());
            (q.map_or(*d, |q| Degradation { q_mobile_c: q, ..*d }), ext.clone())
        })
        .collect();
    (over_cut_short(records, &out, before_first), kept)
}

/// `fits` (one per record) with each record that did not measure the charge the cell holds (stopped above its
/// cut-off, or started from a partial charge: [`CellRecord::measured_its_charge`]) handing on what was carried
/// into it: the fit of the record before (`before_first` before the first; without it the record keeps its
/// own). The offline fit of part of a discharge makes that part's voltage right with a qMobile the part does
/// not pin down: B0055's discharges cut at 40 % and 25 % of their load (as NASA's B0049-B0052 records end where
/// the software crashed) fit 30 % and 57 % low, and the discharge after each started there; a synthetic cell
/// started at 40 % of its charge (`examples/blind/progpy_cells.py`, "B0049" cycle 21) fits 10 % high, its
/// starting charge read off a rest voltage on the flat of the curve.
pub fn over_cut_short(
    records: &[CellRecord],
    fits: &[(Degradation, ModelExtension)],
    before_first: Option<&(Degradation, ModelExtension)>,
) -> Vec<(Degradation, ModelExtension)> {
    let mut out: Vec<(Degradation, ModelExtension)> = Vec::with_capacity(fits.len());
    for (r, f) in records.iter().zip(fits) {
        let carried = if r.measured_its_charge() { None } else { out.last().or(before_first).cloned() };
        out.push(carried.unwrap_or_else(|| f.clone()));
    }
    out
}

/// What each record of a sequence knows before it starts (no look-ahead: only discharges that ended): the
/// prior from the walk (which has seen every discharge before `records`), the model values fitted on the
/// record before it (the first takes `first`'s), at this record's ambient, and the model's knees against the
/// carried fits over the discharges before it (`earlier_knees` those before `records`). The walk observes
/// each record's carried fit.
pub fn before(
    walk: &mut PriorWalk,
    records: &[CellRecord],
    carried: &[(Degradation, ModelExtension)],
    first: &(Degradation, ModelExtension),
    earlier_knees: &Knees,
    cutoff_v: f64,
) -> Vec<Before> {
    let mut out = Vec::with_capacity(records.len());
    for (k, (r, knee)) in records.iter().zip(knees_along(earlier_knees, records, carried, cutoff_v)).enumerate() {
        let prev = if k == 0 { first.clone() } else { carried[k - 1].clone() };
        let p = walk.prior(r, r.rest_before_s, &first.0);
        out.push(Before {
            prior: p.mean,
            prior_sd_z: p.sd_z,
            prior_usual_sd_z: p.usual_sd_z,
            previous: p.previous,
            model: ModelExtension { reference_k: Some(r.ambient_k), ..prev.1 },
            knee,
            rest_before_s: r.rest_before_s,
        });
        walk.observe(r, r.rest_before_s, &carried[k].0);
    }
    out
}

/// Fits carried along a cell's training records, and what each record starts from.
#[derive(Clone, Debug)]
pub struct Carrying {
    /// The training records' carried fits.
    pub fits: Vec<(Degradation, ModelExtension)>,
    /// The prior width learned from consecutive ones.
    pub width: RestWidth,
    /// The same learned from the pairs before the validation records alone (the whole `width` where those
    /// are too few to fit it): what the training records start from, so a prior width factor chosen on the
    /// validation records sees a width learned out of sample, as a judged record will.
    pub tuning_width: RestWidth,
    /// What each training record starts from.
    pub before: Vec<Before>,
    /// The knees of the training records, against their carried fits.
    pub knees: Knees,
    /// Records that kept their voltage fit.
    pub kept_voltage_fit: usize,
}

impl Carrying {
    /// `carried` (one fit per record of `train`, rests set) along `train`, the first record from
    /// `spec.prior` on `neutral`'s model.
    pub fn along(
        spec: &TrackerSpec,
        life: Option<&LifetimeModel>,
        train: &[CellRecord],
        carried: Vec<(Degradation, ModelExtension)>,
        neutral: &ModelExtension,
        rests: &BTreeMap<u32, f64>,
        cutoff_v: f64,
    ) -> Self {
        let width =
            if train.is_empty() { RestWidth::fallback() } else { learn_width(spec, life, train, &carried, rests) };
        let tuning_width = match crate::tune::validation_records(train).first() {
            Some(&k) => Some(learn_width(spec, life, &train[..k], &carried[..k], rests))
                .filter(RestWidth::fitted)
                .unwrap_or(width),
            None => width,
        };
        let mut walk = PriorWalk::new(spec, life, tuning_width);
        let before = before(&mut walk, train, &carried, &(spec.prior, neutral.clone()), &Knees::default(), cutoff_v);
        let knees = Knees::of(train, &carried, cutoff_v);
        Self { fits: carried, width, tuning_width, before, knees, kept_voltage_fit: 0 }
    }

    /// The end fits of `train` (their voltage fits `fits`) carried along it.
    pub fn end_fits(
        spec: &TrackerSpec,
        life: Option<&LifetimeModel>,
        train: &[CellRecord],
        fits: &[(Degradation, ModelExtension)],
        neutral: &ModelExtension,
        rests: &BTreeMap<u32, f64>,
        cutoff_v: f64,
    ) -> Self {
        // A first record cut short hands on what the first starts from: the setting's prior.
        let start = (spec.prior, neutral.clone());
        let (carried, kept) = end_fits(spec, train, fits, Some(&start), cutoff_v);
        Self { kept_voltage_fit: kept, ..Self::along(spec, life, train, carried, neutral, rests, cutoff_v) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::measured::scenario::{Sample, ScenarioConfig};

    /// Simulated 2 A discharges (the simulator's own integrator and sampling) to a 2.5 V cut-off, below the
    /// voltage where the model's electrode surface empties and its voltage stops falling, each given a knee
    /// written here: past its emptying the cell's voltage falls on, 0.4 V a minute, read every 10 s, to the
    /// cut-off (what NASA's cells do below the model's end; about 30 s here). Three start full, the fourth at
    /// 40 %. The end
    /// fits hold each cell's own qMobile (within 1 %) and the knee's charge apart (within 10 % of the written
    /// one's); the fourth discharge's end, predicted from its rest under the third's end fit with the knee
    /// added back, lands within 10 s of its measured end. An end fit that holds the knee as more qMobile
    /// (the one before 2026-11-30) is high by about half the knee (0.9 % here) and ends the fourth early by most of the
    /// knee.s 60 %.
    #[test]
    fn the_end_fit_keeps_the_knee_apart_so_a_part_charged_start_ends_on_time() {
        // A noiseless voltage sensor: a start from 40 % read off a noisy rest errs on its own (the intervals
        // carry that, `interval::tests`), and here only the knee is at stake.
        let sensor = bcal_common::measured::SensorConfig { voltage_noise_v: 0.0, ..Default::default() };
        let cfg = ScenarioConfig { cutoff_v: 2.5, sensor, ..ScenarioConfig::default() };
        let spec = TrackerSpec { cutoff_v: cfg.cutoff_v, ..TrackerSpec::default() };
        let truths: Vec<Degradation> =
            (0..4).map(|k| Degradation { q_mobile_c: 7400.0 - 40.0 * k as f64, r_o_ohm: 0.12 }).collect();
        let (mut records, mut written_c) = (Vec::new(), Vec::new());
        for (k, truth) in truths.iter().enumerate() {
            let soc0 = if k == 3 { 0.4 } else { 1.0 };
            let mut r = crate::testing::simulated_record(&cfg, *truth, soc0, 21 + k as u64, k as u32 + 1);
            let last = *r.samples.last().unwrap();
            let knee_s = (last.voltage_v - cfg.cutoff_v) / (0.4 / 60.0);
            for j in 1..=(knee_s / 10.0) as usize + 1 {
                let dt = 10.0 * j as f64;
                r.samples.push(Sample { t_s: last.t_s + dt, voltage_v: last.voltage_v - 0.4 / 60.0 * dt, ..last });
            }
            r.eod_s = Some(last.t_s + knee_s);
            written_c.push(2.0 * knee_s);
            records.push(r);
        }
        let fits: Vec<(Degradation, ModelExtension)> = truths.iter().map(|t| (*t, ModelExtension::default())).collect();
        let (carried, _) = end_fits(&spec, &records, &fits, None, cfg.cutoff_v);
        for k in 0..3 {
            let (r, truth) = (&records[k], truths[k]);
            let fit = bcal_calib::end_fit::end_fit(&spec, &r.samples, r.eod_s.unwrap(), 0.12).unwrap();
            assert_eq!(fit.q_mobile_c, carried[k].0.q_mobile_c);
            assert!((fit.q_mobile_c / truth.q_mobile_c - 1.0).abs() < 0.01, "cycle {k}: {fit:?} against {truth:?}");
            assert!((fit.knee_c / written_c[k] - 1.0).abs() < 0.1, "cycle {k}: {fit:?}, the knee {} C", written_c[k]);
            let held = bcal_calib::end_fit::q_mobile_to_end(&spec, &r.samples, r.eod_s.unwrap(), 0.12).unwrap();
            assert!(held / truth.q_mobile_c - 1.0 > 0.005, "cycle {k}: the knee held as qMobile {held} C");
        }
        // The part-charged discharge predicted at half from the third's end fit, the knee the three measured.
        let part = &records[3];
        let at_half = |d: Degradation, knee: crate::run::Knee| {
            let run =
                crate::run::run_cycle(&crate::run::Streaming::Pinned { spec: spec.clone(), d }, part, 2.5, knee, 1.0);
            run.steps[part.reading_at_fraction(0.5).unwrap()].eod.value.unwrap() - part.eod_s.unwrap()
        };
        let knee = Knees::of(&records[..3], &carried[..3], 2.5).median();
        let apart = at_half(carried[2].0, knee);
        assert!(apart.abs() < 10.0, "knee apart: {apart:+.1} s ({knee:?})");
        let held: Vec<(Degradation, ModelExtension)> = records[..3]
            .iter()
            .map(|r| {
                let q = bcal_calib::end_fit::q_mobile_to_end(&spec, &r.samples, r.eod_s.unwrap(), 0.12).unwrap();
                (Degradation { q_mobile_c: q, r_o_ohm: 0.12 }, ModelExtension::default())
            })
            .collect();
        let early = at_half(held[2].0, Knees::of(&records[..3], &held, 2.5).median());
        assert!(
            early < -0.4 * written_c[3] / 2.0,
            "knee held as qMobile: {early:+.1} s of a {} s knee",
            written_c[3] / 2.0
        );
    }

    /// Constant-current discharges of a fading simulated cell (the simulator's own integrator and sampling),
    /// each ended where the cell's model emptied above a 2.5 V cut-off, and "voltage fits" 5 % short of the
    /// cell's charge (what an offline fit gives where the model's voltage is right and its end is not): the
    /// end fits give the charge back, each discharge's prior carries the one before it, and the knee the
    /// end fit leaves is a small part of the voltage fit's.
    #[test]
    fn a_discharge_hands_on_the_charge_its_end_measured() {
        let cfg = ScenarioConfig { cutoff_v: 2.5, ..ScenarioConfig::default() };
        let spec = TrackerSpec { cutoff_v: cfg.cutoff_v, ..TrackerSpec::default() };
        let truths = [7400.0, 7250.0, 7120.0];
        let (mut records, mut fits) = (Vec::new(), Vec::new());
        for (k, q) in truths.iter().enumerate() {
            let truth = Degradation { q_mobile_c: *q, r_o_ohm: 0.12 };
            records.push(crate::testing::simulated_record(&cfg, truth, 1.0, 5 + k as u64, k as u32 + 1));
            fits.push((Degradation { q_mobile_c: 0.95 * q, ..truth }, ModelExtension::default()));
        }
        let short = CellRecord { eod_s: None, ..records[0].clone() };
        let (alone, kept) = end_fits(&spec, std::slice::from_ref(&short), &fits[..1], None, cfg.cutoff_v);
        assert_eq!((kept, alone[0].0), (1, fits[0].0), "a first discharge cut short, nothing before it: its own fit");
        // One cut short between two whole ones hands on the end fit carried into it, not its own fit (a fit of
        // part of a discharge, here 40 % low): the one after it starts from what the one before measured.
        let cut = CellRecord { cycle: 2, ..short };
        let low = (Degradation { q_mobile_c: 0.6 * truths[1], r_o_ohm: 0.12 }, ModelExtension::default());
        let three = [records[0].clone(), cut, records[2].clone()];
        let (carried, kept) = end_fits(&spec, &three, &[fits[0].clone(), low, fits[2].clone()], None, cfg.cutoff_v);
        assert_eq!(kept, 1);
        assert_eq!(carried[1], carried[0], "the cut-short record hands on the fit before it");
        assert!((carried[0].0.q_mobile_c / truths[0] - 1.0).abs() < 0.02, "{:?}", carried[0]);
        let before = (Degradation { q_mobile_c: 7000.0, r_o_ohm: 0.1 }, ModelExtension::default());
        let first_cut = over_cut_short(&three[1..], &carried[1..], Some(&before));
        assert_eq!(first_cut[0], before, "a first record cut short hands on what it started from");
        assert_eq!(first_cut[1], carried[2], "a whole record keeps its own");

        let neutral = ModelExtension::default();
        let c = Carrying::end_fits(&spec, None, &records, &fits, &neutral, &BTreeMap::new(), cfg.cutoff_v);
        assert_eq!(c.kept_voltage_fit, 0);
        for (k, (d, _)) in c.fits.iter().enumerate() {
            assert!(
                (d.q_mobile_c / truths[k] - 1.0).abs() < 0.02,
                "cycle {}: {} C against {}",
                k + 1,
                d.q_mobile_c,
                truths[k]
            );
            assert_eq!(d.r_o_ohm, fits[k].0.r_o_ohm, "Ro is the voltage fit's");
        }
        for k in 1..records.len() {
            assert_eq!(c.before[k].prior, c.fits[k - 1].0, "without a lifetime model the prior is the end fit before");
        }
        let voltage = Carrying::along(&spec, None, &records, fits.clone(), &neutral, &BTreeMap::new(), cfg.cutoff_v);
        for (e, v) in c.knees.eod_c().iter().zip(&voltage.knees.eod_c()) {
            assert!(*v > 0.0 && e.abs() < 0.25 * v, "knee against the end fit {e} C, the voltage fit {v} C");
        }
        assert_eq!(c.knees.eod_c().len(), records.len(), "every record started at rest and reached its end");
    }

    /// A discharge started at 40 % of a full charge (the simulator's own cell, read as a cycler logs it) reaches
    /// its cut-off like any other, but what it delivered is not what the cell holds: the rests before it show
    /// the short start, and it hands on the fit carried into it, so the discharge after it starts from the last
    /// whole one (before: its own end fit, read from a starting charge on the flat of the voltage curve). The
    /// full starts around it, 3 mV noise on their rests, are not taken for short ones.
    #[test]
    fn a_discharge_started_from_a_partial_charge_hands_on_what_was_carried_into_it() {
        let cfg = ScenarioConfig { cutoff_v: 2.5, ..ScenarioConfig::default() };
        let spec = TrackerSpec { cutoff_v: cfg.cutoff_v, ..TrackerSpec::default() };
        let socs = [1.0, 1.0, 1.0, 0.4, 1.0];
        let (mut records, mut fits) = (Vec::new(), Vec::new());
        for (k, soc0) in socs.iter().enumerate() {
            let truth = Degradation { q_mobile_c: 7400.0 - 40.0 * k as f64, r_o_ohm: 0.12 };
            records.push(crate::testing::simulated_record(&cfg, truth, *soc0, 11 + k as u64, k as u32 + 1));
            fits.push((truth, ModelExtension::default()));
        }
        crate::record::set_short_starts_seen(records.iter_mut());
        let seen: Vec<bool> = records.iter().map(|r| r.short_start_seen).collect();
        assert_eq!(
            seen,
            [false, false, false, true, false],
            "rests {:?}",
            records.iter().map(|r| r.rest_before_load_v()).collect::<Vec<_>>()
        );
        assert!(records[3].eod_s.is_some() && !records[3].measured_its_charge());
        let (carried, _) = end_fits(&spec, &records, &fits, None, cfg.cutoff_v);
        assert_eq!(carried[3], carried[2], "the short start hands on what was carried into it");
        assert_ne!(carried[4], carried[3], "the whole discharge after it hands on its own");
        let c = Carrying::end_fits(&spec, None, &records, &fits, &ModelExtension::default(), &BTreeMap::new(), 2.5);
        assert_eq!(c.before[4].prior, c.fits[2].0, "the discharge after it starts from the last whole one");
    }

    /// The validation records (the last quarter) start from a width learned on the pairs before them: a
    /// cell whose fits jump only there gives them the narrow width of its earlier history, and the judged
    /// records the width of all of it.
    #[test]
    fn the_validation_records_start_from_a_width_learned_without_them() {
        let cfg = ScenarioConfig { cutoff_v: 2.5, ..ScenarioConfig::default() };
        let spec = TrackerSpec { cutoff_v: cfg.cutoff_v, ..TrackerSpec::default() };
        let one = crate::testing::simulated_record(&cfg, Degradation { q_mobile_c: 7400.0, r_o_ohm: 0.12 }, 1.0, 3, 1);
        let n = 16;
        let records: Vec<CellRecord> = (1..=n).map(|c| CellRecord { cycle: c, ..one.clone() }).collect();
        let validation = crate::tune::validation_records(&records);
        assert_eq!(validation, (12..16).collect::<Vec<_>>());
        let fits: Vec<(Degradation, ModelExtension)> = (0..n as usize)
            .map(|k| {
                let wobble = if k < 12 { 5.0 } else { 300.0 } * if k % 2 == 0 { 1.0 } else { -1.0 };
                (
                    Degradation { q_mobile_c: 7400.0 - 10.0 * k as f64 + wobble, r_o_ohm: 0.12 },
                    ModelExtension::default(),
                )
            })
            .collect();
        let c = Carrying::along(&spec, None, &records, fits, &ModelExtension::default(), &BTreeMap::new(), 2.5);
        let (all, before_validation) = (c.width.a_z2[0].sqrt(), c.tuning_width.a_z2[0].sqrt());
        assert!(
            before_validation < 0.2 * all,
            "sd {before_validation} z before the validation records, {all} z in all"
        );
        for k in validation {
            let sd = c.before[k].prior_sd_z.expect("a learned width")[0];
            assert!(
                (sd / before_validation - 1.0).abs() < 1e-9,
                "record {k}: sd {sd} z, learned before {before_validation} z"
            );
        }
    }
}
