//! `bcal calibrate`'s work, top to bottom: prepare the training and judged discharges (readings up to the
//! cut-off), fit every one offline with the doctor on the calibrators' model (the base one, or the doctor's
//! extended one with `--model`: the `fit` oracle, the previous-cycle reference, and the per-cycle values
//! of the extended model each discharge starts from), learn what each discharge starts from (the prior and
//! its width from the cell's history and its lifetime model, [`crate::prior`]), fit the parameter trend on
//! the training cycles, set up the streaming calibrators on validation cycles (the last training cycles:
//! the joint UKF's settings and prior-width factor, the RL policy file; see [`crate::tune`]), run every
//! method along every judged discharge, set every method's intervals from its errors on the discharges
//! before each ([`crate::interval`]), score them against the cycler and assemble the report. Progress goes
//! to a callback; nothing here prints.
//!
//! With an extended model the streaming calibrators track qMobile and Ro in real time and the model's
//! per-cycle parameters (electrode balance, charge-transfer factor) from discharge to discharge: each
//! discharge runs on the values the doctor fitted on the discharge before it, once that one had ended.

use crate::carry::{before, end_fits, Carrying};
use crate::cellspec::{cell_spec, CellFacts};
use crate::interval::calibrate_intervals;
use crate::prior::{rests_before, PriorWalk, RestWidth};
use crate::record::{prepare, CellRecord, RecordSummary};
use crate::report::{CalibrationReport, MethodEntry};
use crate::run::{run_all, run_sequence, Before, CycleRun, Knees, ParamTrend, Streaming};
use crate::score::{score, EOD_FRACTIONS_PCT};
use crate::tune;
use bcal_calib::tune::{AdaptiveGrid, JointUkfGrid};
use bcal_common::battery::Degradation;
use bcal_common::lifetime::{LifeTracker, POPULATION_RECOVERY_UNSEEN_REST_S};
use bcal_common::measured::env::{Design, MeasuredSpec};
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::tracker::TrackerSpec;
use bcal_common::measured::tracker::{AdaptiveRule, JointUkfSettings};
use bcal_common::policy::PolicyFile;
use bcal_common::policy::PolicyNet;
use bcal_common::stats::median;
use bcal_doctor::fit::{refit_cycles, FitConfig, FitRecord};
use bcal_doctor::lifetime::{assess, Lifetime, LifetimeConfig, LifetimeModel};
use bcal_doctor::model_file::DiagnosedModel;
use bcal_doctor::read::RecordStart;
use bcal_doctor::{Cause, Discharge, ExtParams};
use std::collections::BTreeMap;
use std::time::Instant;

/// What `bcal calibrate` runs.
pub struct CalibrateInput<'a> {
    pub cell: String,
    /// Training cycles: the trend, the cell's setting, the reference for the first judged cycle.
    pub train: Vec<Discharge>,
    /// The cycles judged.
    pub judged: Vec<Discharge>,
    pub cutoff_v: f64,
    pub cutoff_source: String,
    /// The RL policy candidates and where each came from: the validation cycles choose one. A candidate is
    /// one policy file (a run's checkpoints are candidates each) or an ensemble: several runs of one task
    /// (other seeds), whose mean action corrects the filter (correction design only).
    pub policies: Vec<Vec<(&'a PolicyFile, String)>>,
    pub ukf: bool,
    /// The adaptive UKF (its rule chosen among `adaptive_grid` on top of the chosen joint UKF).
    pub adaptive_ukf: bool,
    pub adaptive_grid: AdaptiveGrid,
    pub fit: bool,
    /// The cell's setting (None: derived from the training cycles here).
    pub spec: Option<MeasuredSpec>,
    /// The joint UKF's search space (chosen on the validation cycles).
    pub ukf_grid: JointUkfGrid,
    /// The doctor's extended model (`--model diagnosis.json`); None: the base model.
    pub model: Option<DiagnosedModel>,
    /// When each record started (the reader's [`bcal_doctor::read::ReadReport::starts`]): the rests between
    /// discharges. Empty: rests unknown (the priors' widths then do not depend on them).
    pub starts: Vec<RecordStart>,
    /// The rest before each discharge, s, when the caller knows more records than it passes (`--stride`
    /// leaves judged records out, and each still ends the rest before the next); None: from `starts` and
    /// the records given ([`crate::prior::rests_before`]).
    pub rests: Option<BTreeMap<u32, f64>>,
    /// Records of the selected cycles the reader could not read, each with why (naming the file): said in
    /// the report beside the ones refused here.
    pub unread: Vec<String>,
    /// The reader's notes (a damaged end read up to, readings written twice, a gap, a cycle without
    /// discharge), each naming the file: said in the report.
    pub noted: Vec<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    #[error("the policy {path} was trained on the {observation} observation; bcal calibrate runs measured-only policies (retrain with --preset measured)")]
    PolicyTask { path: String, observation: String },
    #[error("the policy {path} was trained on the {trained} model, but this calibration runs the {model} model: train a policy on it (bcal cell-config with the same --model, then bcal train --config)")]
    PolicyModel { path: String, trained: String, model: String },
    #[error("the policy {path} cannot join {first} in an ensemble: the members must be correction-design runs of one task (the same cell config, other --seed)")]
    Ensemble { path: String, first: String },
    #[error("no usable judged discharge: {0}")]
    NothingToJudge(String),
    /// Not the error's source as well: the message holds it, and a chain would print it twice.
    #[error("the doctor's fit failed: {0}")]
    Fit(bcal_doctor::DoctorError),
    #[error("{0}")]
    Validation(String),
    #[error("policy: {0}")]
    Policy(#[from] bcal_common::policy::PolicyError),
    #[error("{path}: {why}")]
    Model { path: String, why: String },
}

impl From<bcal_doctor::DoctorError> for CalibrateError {
    fn from(e: bcal_doctor::DoctorError) -> Self {
        Self::Fit(e)
    }
}

/// Records that can be calibrated, and the refusals (each naming the record and what to do).
fn prepare_all(ds: &[Discharge], cutoff_v: f64, summary: &mut RecordSummary) -> (Vec<CellRecord>, Vec<usize>) {
    let mut out = Vec::new();
    let mut kept = Vec::new();
    for (k, d) in ds.iter().enumerate() {
        match prepare(d, cutoff_v) {
            Ok(r) => {
                out.push(r);
                kept.push(k);
            }
            Err(e) => summary.refused.push(e.to_string()),
        }
    }
    (out, kept)
}

/// Marks the records (`train`, `judged`, prepared from `train_read`, `judged_read`) that started from a partial
/// charge, as their neighbours' rest voltages show (the doctor's rule), and reads what the stated capacity
/// measures ([`crate::record::stated_capacity`]). Which training records started partial is read off the training
/// records alone (since 2026-11-30: the stated capacity's definition and the choices made on the validation
/// records no longer look at the judged records' rests); which judged ones did off every record, later ones among
/// the neighbours, for the scores only (a partial start's capacity is not scored).
fn mark_partial_starts(
    train: &mut [CellRecord],
    judged: &mut [CellRecord],
    train_read: &[Discharge],
    judged_read: &[Discharge],
    cutoff_v: f64,
) -> Option<crate::record::StatedCapacity> {
    let life_cfg = bcal_doctor::lifetime::LifetimeConfig::default();
    let short = |read: Vec<&Discharge>| -> Vec<u32> {
        bcal_doctor::record::short_starts(&read, life_cfg.load_threshold_a, life_cfg.partial_start_v)
            .into_iter()
            .map(|(cycle, _, _)| cycle)
            .collect()
    };
    let short_train = short(train_read.iter().collect());
    for r in train.iter_mut() {
        r.partial_start = short_train.contains(&r.cycle);
    }
    let stated = crate::record::stated_capacity(train, cutoff_v);
    let short_all = short(train_read.iter().chain(judged_read).collect());
    for r in judged.iter_mut() {
        r.partial_start = short_all.contains(&r.cycle);
    }
    stated
}

/// Fewer loaded samples than this, settled after a load step and above the fit's voltage floor, leave a
/// record's offline fit undetermined (the protocol-wide check in [`fits`] uses the same count).
const MIN_FIT_SAMPLES: usize = 5;

/// How many of `d`'s samples the offline fit can use.
fn fit_samples(d: &Discharge, cfg: &FitConfig) -> usize {
    d.windows(cfg.load_threshold_a, cfg.v_floor_v).map_or(0, |w| FitRecord::new(d, w, cfg).used.len())
}

/// Leaves out, one by one and each named, the prepared records the offline fit cannot use (a discharge
/// that starts from a partial charge below the fit's voltage floor, one cut short within seconds of its load
/// step), unless the training or the judged records hold none that could be used: then [`fits`] says why for
/// the whole cell (a load that switches as often as it is sampled).
fn refuse_unfittable(
    sets: [(&mut Vec<CellRecord>, &mut Vec<usize>, &[Discharge]); 2],
    cfg: &FitConfig,
    summary: &mut RecordSummary,
) {
    let usable = |ds: &[Discharge], kept: &[usize], k: usize| fit_samples(&ds[kept[k]], cfg) >= MIN_FIT_SAMPLES;
    // A set none of whose records can be used is left whole: the fit then says why.
    if !sets.iter().all(|(recs, kept, ds)| recs.is_empty() || (0..recs.len()).any(|k| usable(ds, kept, k))) {
        return;
    }
    for (recs, kept, ds) in sets {
        let keep: Vec<bool> = (0..recs.len()).map(|k| usable(ds, kept, k)).collect();
        for (k, r) in recs.iter().enumerate().filter(|(k, _)| !keep[*k]) {
            summary.refused.push(format!(
                "{} cycle {}: fewer than {MIN_FIT_SAMPLES} loaded samples above the fit's floor ({} V, or lower \
                 for a cell the load pulls under it at once) settled {} s after a load step ({} of them): the \
                 offline fit that starts the next discharge has nothing to fit (a start from a partial charge, or \
                 a load cut within seconds); left out",
                r.cell,
                r.cycle,
                cfg.v_floor_v,
                cfg.settle_s,
                fit_samples(&ds[kept[k]], cfg)
            ));
        }
        let mut it = keep.iter();
        recs.retain(|_| *it.next().unwrap_or(&true));
        let mut it = keep.iter();
        kept.retain(|_| *it.next().unwrap_or(&true));
    }
}

/// One record's model as the calibrators run it: the doctor's causes with the values of `ext` (shared
/// and per-cycle), at the record's ambient.
pub fn extension_of(causes: &[Cause], ext: &ExtParams, ambient_k: f64) -> ModelExtension {
    bcal_doctor::model_file::extension_of(causes, ext, Some(ambient_k))
}

/// The causes and shared values of `model` (the base model without one).
pub fn model_parts(model: Option<&DiagnosedModel>) -> (Vec<Cause>, ExtParams) {
    model.map_or_else(|| (Vec::new(), ExtParams::default()), |m| (m.causes.clone(), m.shared))
}

/// The doctor's offline per-cycle fit of every record (qMobile, Ro and the model's per-cycle parameters,
/// its shared ones frozen), with each record's model.
pub fn fits(
    ds: &[&Discharge],
    cfg: &FitConfig,
    causes: &[Cause],
    shared: &ExtParams,
) -> Result<Vec<(Degradation, ModelExtension)>, CalibrateError> {
    let recs: Vec<FitRecord> = ds
        .iter()
        .filter_map(|d| d.windows(cfg.load_threshold_a, cfg.v_floor_v).map(|w| FitRecord::new(d, w, cfg)))
        .collect();
    if recs.len() != ds.len() {
        return Err(CalibrateError::NothingToJudge("a record without a load window reached the fit".into()));
    }
    // A load that switches about as often as it is sampled (B0025's 20 s square wave at 10-20 s samples)
    // leaves no sampled voltage whose load is known: the fit has nothing, and says why.
    if let Some(r) = recs.first().filter(|_| recs.iter().all(|r| r.used.len() < 5)) {
        let why = format!(
            "in every record the loaded samples follow a load step by less than {} s (cycle {}: {} of {}): the load \
             switches about as often as it is sampled, so no sampled voltage can be fitted and no calibrator set up",
            cfg.settle_s,
            ds[0].cycle,
            r.w.fit_len() - r.used.len(),
            r.w.fit_len()
        );
        return Err(CalibrateError::Fit(bcal_doctor::DoctorError::NothingSelected { why }));
    }
    let f = refit_cycles(cfg, &recs, causes, shared, None)?;
    Ok(f.per_cycle
        .iter()
        .zip(&f.cycle_ext)
        .zip(ds)
        .map(|((d, e), disc)| (*d, extension_of(causes, e, disc.ambient_k)))
        .collect())
}

/// A cell's capacity lifetime models ([`bcal_doctor::lifetime`]), both read off its training records.
#[derive(Clone, Debug)]
pub struct CellLife {
    /// Fitted on the training cycles before the last quarter (the validation cycles): what the training
    /// and validation discharges start from, so every choice made on the validation cycles sees the prior
    /// out of sample, as a judged discharge will.
    pub tuning: LifetimeModel,
    /// Fitted on every training cycle: what the judged discharges start from.
    pub used: LifetimeModel,
    /// Whether a recovery after rest is there (judged on the last quarter) and what each model says.
    pub verdict: String,
}

/// The cell's capacity lifetime models from its training records: whether a recovery after rest is there
/// is judged as `launch/run.sh` diagnoses (fitted on the first three quarters, judged on the last); the
/// model fitted on those three quarters is the [`CellLife::tuning`] one, and the same form fitted on
/// every training record the [`CellLife::used`] one. Records too few (under eight cycles) or too sparse to fit
/// one follow the life by NASA's cells' recovery alone ([`population_life`]). None without a schedule.
pub fn lifetime_model(train: &[Discharge], starts: &[RecordStart], cutoff_v: f64) -> Option<CellLife> {
    own_lifetime_model(train, starts, cutoff_v).or_else(|| population_life(train, starts, cutoff_v))
}

/// The cell's own lifetime models ([`lifetime_model`]); None without a schedule, eight training cycles or a
/// capacity series to fit.
fn own_lifetime_model(train: &[Discharge], starts: &[RecordStart], cutoff_v: f64) -> Option<CellLife> {
    let (first, last) = (train.iter().map(|d| d.cycle).min()?, train.iter().map(|d| d.cycle).max()?);
    if last < first + 7 {
        return None;
    }
    let split = first + (last - first + 1) * 3 / 4;
    let cfg = LifetimeConfig { cutoff_v: Some(cutoff_v), ..LifetimeConfig::default() };
    let life = assess(&cfg, train, starts, &(first..=split - 1), &(split..=last), None).ok()?;
    let fit = life.capacity.as_ref()?;
    // Records with no rest of a day or more cannot say what a long rest later gives back, and NASA's cells all
    // regain capacity after one: a model fitted on such records takes theirs (`POPULATION_RECOVERY`; the blind
    // "B0049", 25 discharges at 4 C with 3- and 5-day rests after its 8 training ones, started those 0.07-0.11
    // Ah low). A model whose records held such a rest keeps what they said, recovery or none.
    let own_or_population = |l: &Lifetime, m: LifetimeModel| {
        let longest_s =
            l.series.iter().filter(|p| p.role == "train").filter_map(|p| p.rest_before_s).fold(0.0, f64::max);
        if longest_s < POPULATION_RECOVERY_UNSEEN_REST_S {
            m.with_population_recovery()
        } else {
            m
        }
    };
    let tuning = if life.recovery { fit.with_recovery? } else { own_or_population(&life, fit.without_recovery) };
    // The last quarter holds rests the first three may not (B0006: a 37 h pause at cycle 31 beside the 310 h
    // one at cycle 20), and with one long rest alone the recovery's time constant is not determined.
    let whole = assess(&cfg, train, starts, &(first..=last), &(last + 1..=last + 1), None).ok();
    let refit = whole.as_ref().and_then(|l| l.capacity.as_ref());
    let (used, assumed) = match (life.recovery, whole.as_ref().zip(refit)) {
        (true, Some((_, r))) => (r.with_recovery.unwrap_or(tuning), false),
        // Not judged on the last quarter when the first three held no long rest: the population's then too.
        (false, Some((w, r))) => {
            let m = if tuning != fit.without_recovery {
                r.without_recovery.with_population_recovery()
            } else {
                own_or_population(w, r.without_recovery)
            };
            (m, m != r.without_recovery)
        }
        (_, None) => (tuning, !life.recovery && tuning != fit.without_recovery),
    };
    let says = |m: &LifetimeModel| {
        if m.amplitude > 0.0 {
            format!(
                "a long rest adds {:.3} Ah (time constant {:.1} h), worn off over {:.1} discharges",
                m.amplitude,
                m.tau_rest_s / 3600.0,
                m.decay_discharges
            )
        } else {
            "the fade alone".to_string()
        }
    };
    let mut verdict =
        format!("{}; used on the judged discharges, fitted on cycles {first}-{last}: {}", life.verdict, says(&used));
    if assumed && used.amplitude > 0.0 {
        verdict += " (the recovery NASA's cells show: no training rest was long enough to fit the cell's own)";
    }
    if let Some(w) = &whole {
        if !w.partial_start_cycles.is_empty() {
            let cycles: Vec<String> = w.partial_start_cycles.iter().map(u32::to_string).collect();
            verdict += &format!(
                "; capacity of cycle {} left out: started from a partial charge (its rest voltage well below its \
                 neighbours')",
                cycles.join(", ")
            );
        }
    }
    Some(CellLife { tuning, used, verdict })
}

/// The lifetime model of a cell whose training records are too few to fit its own (a short life's first third:
/// NASA's cells of 25 discharges or fewer train on under eight): no fade (each discharge's measured capacity
/// carries it, as before) and the recovery NASA's cells show after a rest longer than the usual, as a live stream
/// without the cell's model follows it ([`LifetimeModel::population`]). The usual rest is the median of the
/// training records' known rests, [`POPULATION_RESTS`](bcal_common::lifetime::POPULATION_RESTS) of them at least; None with fewer, or with no measured
/// capacity (every training record cut short of the cut-off).
pub fn population_life(train: &[Discharge], starts: &[RecordStart], cutoff_v: f64) -> Option<CellLife> {
    let (first, last) = (train.iter().map(|d| d.cycle).min()?, train.iter().map(|d| d.cycle).max()?);
    let cfg = LifetimeConfig { cutoff_v: Some(cutoff_v), ..LifetimeConfig::default() };
    let life = assess(&cfg, train, starts, &(first..=last), &(last + 1..=last + 1), None).ok()?;
    let mut capacities: Vec<f64> = life.series.iter().filter_map(|p| p.capacity_ah).collect();
    let rests = || life.series.iter().filter_map(|p| p.rest_before_s).filter(|r| *r > 0.0);
    let population = LifetimeModel::population_from_rests(median(&mut capacities)?, rests())?;
    let usual_s = population.usual_rest_s;
    // A training rest longer than the usual says how much of that recovery is the cell's (NASA's B0025
    // regains nothing after its 87 h rest before cycle 6, nor after the 9 and 13 days later in its life).
    let mut walk = LifeTracker::learning_its_recovery(population);
    for p in &life.series {
        walk.advance_to(p.cycle, p.rest_before_s, p.condition);
        if let Some(c) = p.capacity_ah {
            walk.observe(c);
        }
    }
    let (scale, _) = walk.recovery_scale();
    let m = population.with_recovery_scaled(scale);
    let verdict = format!(
        "no lifetime model of the cell's own from its training records ({} cycles, {first}-{last}, {} of them \
         measuring a capacity; a fit needs eight cycles): the recovery NASA's cells show after a rest longer than \
         the usual {:.1} h (the median of {} known rests), times {scale:.2} as the training rests longer than the \
         usual said, a 3-day rest giving back {:.3} Ah; no fade beyond what each measured capacity carries",
        life.series.len(),
        capacities.len(),
        usual_s / 3600.0,
        rests().count(),
        m.jump_over_usual(72.0 * 3600.0)
    );
    Some(CellLife { tuning: m, used: m, verdict })
}

/// The joint UKF chosen among `grid` (settings, prior width factor) by [`tune::choose`] on the validation
/// records, each starting from its [`Before`].
pub fn choose_ukf(
    spec: &TrackerSpec,
    grid: &[(JointUkfSettings, Option<f64>)],
    validation: &[CellRecord],
    validation_before: &[Before],
    cutoff_v: f64,
) -> Option<(JointUkfSettings, Option<f64>, tune::Choice)> {
    let cands: Vec<(String, Streaming)> = grid
        .iter()
        .map(|(g, f)| {
            (
                format!("{g:?}, prior width factor {f:?}"),
                Streaming::Ukf { spec: spec.clone(), settings: *g, prior_factor: *f },
            )
        })
        .collect();
    let choice = tune::choose(&cands, validation, validation_before, cutoff_v)?;
    let (best, factor) = grid[choice.index];
    Some((best, factor, choice))
}

/// What a cell's training cycles say of the discharges to come, as `bcal calibrate` reads them: the
/// lifetime model (fade, recovery after rest), the fit each discharge hands on ([`crate::carry`]: its end
/// fit) and the prior width learned from consecutive ones. Sets each record's rest before it
/// from the records' start times.
pub struct CellHistory {
    pub life: Option<CellLife>,
    /// The carried fits, the prior width learned from them and the priors along the training records.
    pub carrying: Carrying,
}

impl CellHistory {
    pub fn read(
        spec: &TrackerSpec,
        train_ds: &[Discharge],
        starts: &[RecordStart],
        train: &mut [CellRecord],
        train_fits: &[(Degradation, ModelExtension)],
        neutral: &ModelExtension,
        cutoff_v: f64,
    ) -> Self {
        let refs: Vec<&Discharge> = train_ds.iter().collect();
        let rests = rests_before(&refs, starts);
        for r in train.iter_mut() {
            r.rest_before_s = rests.get(&r.cycle).copied();
        }
        crate::record::set_currents_before(train.iter_mut());
        crate::record::set_short_starts_seen(train.iter_mut());
        if let Ok(model) = neutral.model() {
            crate::record::set_start_spreads(train.iter_mut(), &model);
        }
        let life = lifetime_model(train_ds, starts, cutoff_v);
        let tuning = life.as_ref().map(|l| &l.tuning);
        let carrying = Carrying::end_fits(spec, tuning, train, train_fits, neutral, &rests, cutoff_v);
        Self { life, carrying }
    }

    /// The prior widths a streaming calibrator is tried with: factors on the learned width, or (without a
    /// history to learn it from) the settings' own.
    pub fn factors(&self) -> Vec<Option<f64>> {
        prior_factors(&self.carrying.tuning_width)
    }

    /// The learned prior standard deviations after the usual rest times `factor`, z; None without them.
    pub fn usual_sd_z(&self, factor: Option<f64>) -> Option<[f64; 2]> {
        let f = factor?;
        let w = &self.carrying.width;
        w.fitted().then(|| w.a_z2.map(|a| f * a.sqrt()))
    }
}

/// The prior widths a streaming calibrator is tried with: factors on the learned width, or (without a
/// history to learn it from) the settings' own.
fn prior_factors(width: &RestWidth) -> Vec<Option<f64>> {
    if width.fitted() {
        tune::PRIOR_FACTORS.iter().map(|f| Some(*f)).collect()
    } else {
        vec![None]
    }
}

/// A cell's joint UKF chosen among `grid` and `history`'s prior widths on its training cycles' validation
/// cycles, each starting from the prior `bcal calibrate` gives it (the previous discharge's end fit moved by
/// the lifetime model, the learned width times the factor): the filter and width `bcal calibrate` chooses
/// from the same cycles, so the policy trains on top of the baseline it is judged against. None without
/// validation cycles.
pub fn choose_cell_ukf(
    spec: &TrackerSpec,
    train: &[CellRecord],
    history: &CellHistory,
    grid: &[JointUkfSettings],
    cutoff_v: f64,
) -> Option<(JointUkfSettings, Option<f64>, tune::Choice)> {
    let (validation, validation_before) = cell_validation(train, history);
    let mut cands: Vec<(JointUkfSettings, Option<f64>)> = Vec::new();
    for g in grid {
        for f in history.factors() {
            // With a learned width the grid's own prior widths make no difference: one of each.
            let g = if f.is_some() { JointUkfSettings { prior_std_z: grid[0].prior_std_z, ..*g } } else { *g };
            if !cands.contains(&(g, f)) {
                cands.push((g, f));
            }
        }
    }
    choose_ukf(spec, &cands, &validation, &validation_before, cutoff_v)
}

/// The best filter a cell's correction policy can learn on top of: the chosen joint UKF `ukf` (with its
/// prior width factor) alone (None) or under one of the covariance-matching `rules`, whichever predicts the
/// end of discharge best on the same validation cycles. None without validation cycles.
#[allow(clippy::too_many_arguments)]
pub fn choose_cell_rule(
    spec: &TrackerSpec,
    train: &[CellRecord],
    history: &CellHistory,
    (ukf, prior_factor): (JointUkfSettings, Option<f64>),
    rules: &[AdaptiveRule],
    cutoff_v: f64,
) -> Option<(Option<AdaptiveRule>, tune::Choice)> {
    let (validation, validation_before) = cell_validation(train, history);
    if validation.is_empty() {
        return None;
    }
    let mut cands = vec![("joint UKF".to_string(), Streaming::Ukf { spec: spec.clone(), settings: ukf, prior_factor })];
    cands.extend(adaptive_candidates(spec, ukf, prior_factor, rules));
    let choice = tune::choose(&cands, &validation, &validation_before, cutoff_v)?;
    // Candidate 0 is the filter alone.
    Some((choice.index.checked_sub(1).map(|k| rules[k]), choice))
}

/// The adaptive UKF's candidates: the filter `ukf` at `prior_factor` under each of `rules`, labelled by rule.
fn adaptive_candidates<'a>(
    spec: &TrackerSpec,
    ukf: JointUkfSettings,
    prior_factor: Option<f64>,
    rules: &[AdaptiveRule],
) -> Vec<(String, Streaming<'a>)> {
    rules
        .iter()
        .map(|r| {
            (format!("{r:?}"), Streaming::AdaptiveUkf { spec: spec.clone(), settings: ukf, rule: *r, prior_factor })
        })
        .collect()
}

/// `tune::choose` on the validation cycles, said first: "`what.0`: choosing among N `what.1` on M validation
/// cycles". The caller has checked there are candidates and validation cycles.
fn choose_announced(
    progress: &mut dyn FnMut(&str),
    what: (&str, &str),
    cands: &[(String, Streaming<'_>)],
    validation: &[CellRecord],
    before: &[Before],
    cutoff_v: f64,
) -> tune::Choice {
    progress(&format!(
        "{}: choosing among {} {} on {} validation cycles",
        what.0,
        cands.len(),
        what.1,
        validation.len()
    ));
    tune::choose(cands, validation, before, cutoff_v).expect("candidates and validation checked")
}

/// Per share, the judged discharges' weights of a blend ([`tune::blend_runs`]): their median and how many
/// were blended.
fn weights_json(weights: &tune::Weights) -> serde_json::Value {
    let per: serde_json::Map<String, serde_json::Value> = EOD_FRACTIONS_PCT
        .iter()
        .zip(weights)
        .map(|(f, w)| {
            let mut v: Vec<f64> = w.iter().flatten().copied().collect();
            let n = v.len();
            (f.to_string(), serde_json::json!({"median": bcal_common::stats::median(&mut v), "blended": n}))
        })
        .collect();
    per.into()
}

/// The judged cycles each share's gate served ([`tune::gate_runs`]), keyed by the share, %.
fn served_cycles(judged: &[CellRecord], gates: &tune::Served) -> serde_json::Value {
    let per: serde_json::Map<String, serde_json::Value> = EOD_FRACTIONS_PCT
        .iter()
        .zip(gates)
        .map(|(f, g)| {
            let cycles: Vec<u32> = judged.iter().zip(g).filter(|(_, g)| **g).map(|(j, _)| j.cycle).collect();
            (f.to_string(), serde_json::json!(cycles))
        })
        .collect();
    serde_json::Value::Object(per)
}

/// The validation cycles among a cell's training cycles, each with the prior `bcal calibrate` gives it.
fn cell_validation(train: &[CellRecord], history: &CellHistory) -> (Vec<CellRecord>, Vec<Before>) {
    tune::validation_records(train).iter().map(|&k| (train[k].clone(), history.carrying.before[k].clone())).unzip()
}

/// What a calibration produced: the report and the runs the figures and per-reading files need.
pub struct Calibration {
    pub report: CalibrationReport,
    pub judged: Vec<CellRecord>,
    pub train_capacities: Vec<(u32, f64)>,
    pub runs: Vec<(&'static str, Vec<CycleRun>)>,
    pub facts: CellFacts,
}

pub fn calibrate(input: &CalibrateInput, progress: &mut dyn FnMut(&str)) -> Result<Calibration, CalibrateError> {
    let started = Instant::now();
    let cut = input.cutoff_v;
    let mut summary = RecordSummary::default();
    let (mut train, mut train_kept) = prepare_all(&input.train, cut, &mut summary);
    let (mut judged, mut judged_kept) = prepare_all(&input.judged, cut, &mut summary);
    let fit_cfg = FitConfig::default();
    refuse_unfittable(
        [(&mut train, &mut train_kept, &input.train), (&mut judged, &mut judged_kept, &input.judged)],
        &fit_cfg,
        &mut summary,
    );
    summary.stated_capacity = mark_partial_starts(&mut train, &mut judged, &input.train, &input.judged, cut);
    summary.partial_start = judged.iter().filter(|r| r.partial_start).map(|r| r.cycle).collect();
    summary.unread = input.unread.clone();
    summary.noted = input.noted.clone();
    crate::record::set_stated_tails(train.iter_mut().chain(judged.iter_mut()), summary.stated_capacity.as_ref(), cut);
    if let Some(sc) = summary.stated_capacity.as_ref().filter(|sc| sc.differs_from_cutoff(cut)) {
        progress(&format!(
            "the stated capacities are the charge to about {:.1} V (median gap {:+.3} Ah over {} training records), not \
             to the {cut} V cut-off ({:+.3} Ah): capacities are scored against them less the charge the last {} \
             discharges at a like current (else at any) drew below {:.1} V",
            sc.voltage_v,
            sc.median_gap_ah,
            sc.records,
            sc.cutoff_median_gap_ah,
            crate::record::STATED_TAIL_WINDOW,
            sc.voltage_v
        ));
    }
    if judged.is_empty() {
        let why = if input.judged.is_empty() {
            "no record was given to judge".to_string()
        } else {
            format!("every one of the {} was refused: {}", input.judged.len(), summary.refused.join("; "))
        };
        return Err(CalibrateError::NothingToJudge(why));
    }
    // The rest before each discharge, from the records' start times.
    let all_records: Vec<&Discharge> = input.train.iter().chain(&input.judged).collect();
    let rests = input.rests.clone().unwrap_or_else(|| rests_before(&all_records, &input.starts));
    for r in train.iter_mut().chain(judged.iter_mut()) {
        r.rest_before_s = rests.get(&r.cycle).copied();
    }
    crate::record::set_currents_before(train.iter_mut().chain(judged.iter_mut()));
    crate::record::set_short_starts_seen(train.iter_mut().chain(judged.iter_mut()));
    summary.records = judged.len();
    summary.reaching_cutoff = judged.iter().filter(|r| r.eod_s.is_some()).count();
    summary.cut_short = judged.iter().filter(|r| r.eod_s.is_none()).map(|r| r.cycle).collect();
    summary.capacity_refs = judged
        .iter()
        .map(|r| crate::record::CapacityRefs {
            cycle: r.cycle,
            stated_ah: r.stated_capacity_ah,
            data_ah: r.data_capacity_ah,
            partial_start: r.partial_start,
            stated_tail_ah: r.stated_tail_ah,
        })
        .collect();
    progress(&format!(
        "{}: {} training and {} judged discharges ({} reach the {cut} V cut-off); {} refused, {} not read; rests \
         known before {} of them",
        input.cell,
        train.len(),
        judged.len(),
        summary.reaching_cutoff,
        summary.refused.len(),
        summary.unread.len(),
        rests.len()
    ));
    if !summary.partial_start.is_empty() {
        progress(&format!(
            "judged cycles {:?} started from a partial charge (rest voltage more than {:.0} mV below their \
             neighbours'): their ends of discharge are scored, their capacity is not",
            summary.partial_start,
            bcal_doctor::lifetime::LifetimeConfig::default().partial_start_v * 1000.0
        ));
    }

    // The calibrators' model: the base one or the doctor's extended one, which they must be able to run.
    let (causes, shared) = model_parts(input.model.as_ref());
    let model_path = input.model.as_ref().map_or_else(String::new, |m| m.path.display().to_string());
    let neutral = extension_of(&causes, &shared, train.first().unwrap_or(&judged[0]).ambient_k);
    neutral.check("the model").map_err(|why| CalibrateError::Model { path: model_path.clone(), why })?;
    // How well each discharge's starting charge is known, under that model (what its end's interval adds).
    let start_model =
        neutral.model().map_err(|e| CalibrateError::Model { path: model_path.clone(), why: e.to_string() })?;
    let own_noise_v = crate::record::set_start_spreads(train.iter_mut().chain(judged.iter_mut()), &start_model);
    let mut train_noise_v: Vec<f64> = own_noise_v[..train.len()].iter().flatten().copied().collect();
    let noise_median_v = bcal_common::stats::median(&mut train_noise_v);
    if let Some(n) = noise_median_v {
        progress(&format!(
            "sensor: voltage noise {:.2} mV (median over {} training records, {:.2}-{:.2} mV; each start read off \
             its rest readings is known to that over their number's root, through the open-circuit curve, which \
             its end's interval carries)",
            n * 1e3,
            train_noise_v.len(),
            train_noise_v[0] * 1e3,
            train_noise_v[train_noise_v.len() - 1] * 1e3
        ));
    }
    if causes.contains(&Cause::Thermal) && input.train.iter().chain(&input.judged).any(|d| d.temperature_k.is_none()) {
        return Err(CalibrateError::Model {
            path: model_path,
            why: "the model's `thermal` cause runs on the cell's measured temperature, and these records have none; \
                  diagnose without it or use records with a temperature column"
                .into(),
        });
    }
    // Another cell's diagnosis runs as given (a sibling's model for a cell with few cycles of its own), said;
    // its cycle numbers are that cell's, so they hold nothing against this one's.
    let other_cell = input.model.as_ref().filter(|m| !m.cell.trim().eq_ignore_ascii_case(input.cell.trim()));
    if let Some(m) = other_cell {
        progress(&format!(
            "--model {}: a diagnosis of {}, not of {}: calibrating {} on another cell's diagnosed model (its causes \
             and fitted values); diagnose {} itself for its own (bcal diagnose --cell {})",
            m.path.display(),
            m.cell,
            input.cell,
            input.cell,
            input.cell,
            input.cell
        ));
    }
    let own = input.model.as_ref().filter(|_| other_cell.is_none());
    if let Some(c) = own.and_then(|m| judged.iter().find(|r| m.cycles.contains(&r.cycle))) {
        return Err(CalibrateError::Model {
            path: model_path,
            why: format!(
                "the model was diagnosed on cycle {}, which this calibration judges: diagnose on the training \
                 cycles only (bcal diagnose --cycles and --holdout within --train-cycles)",
                c.cycle
            ),
        });
    }
    let model_label = match &input.model {
        Some(m) => format!(
            "{} (bcal diagnose of {}: {}){}",
            neutral.label(),
            m.cell,
            m.path.display(),
            m.carrying_note().map_or_else(String::new, |n| format!("; {n}"))
        ),
        None => "base (the NASA electrochemistry model; qMobile and Ro calibrated)".into(),
    };
    progress(&format!("model: {model_label}"));

    // Offline fits (the doctor, on that model) of the training and judged cycles.
    let t0 = Instant::now();
    let train_ds: Vec<&Discharge> = train_kept.iter().map(|&k| &input.train[k]).collect();
    let judged_ds: Vec<&Discharge> = judged_kept.iter().map(|&k| &input.judged[k]).collect();
    let train_fits = if train_ds.is_empty() { Vec::new() } else { fits(&train_ds, &fit_cfg, &causes, &shared)? };
    let judged_fits = fits(&judged_ds, &fit_cfg, &causes, &shared)?;
    progress(&format!(
        "offline fits of {} cycles in {:.0} s",
        train_fits.len() + judged_fits.len(),
        t0.elapsed().as_secs_f64()
    ));

    // The model's knee: how much later than the model's own end the last discharges reached the cut-off.
    let knee_median = Knees::of(&train, &train_fits, cut).median();
    progress(&format!(
        "model knee: the training cycles deliver a median {:.4} Ah past the model's empty point to {cut} V from a \
         full cell, {:.4} Ah from their own start (each discharge takes the median of the {} before it)",
        knee_median.capacity_c / 3600.0,
        knee_median.eod_c / 3600.0,
        crate::run::KNEE_WINDOW
    ));

    // The cell's setting: given (the RL run's), else derived from the training cycles.
    let (derived, facts) = cell_spec(&train, &train_fits, cut);
    let spec = input.spec.clone().unwrap_or(derived);

    // What every discharge starts from: the prior from the cell's history (its lifetime model and the
    // spread of consecutive fits against the rest between them).
    let life = lifetime_model(&input.train, &input.starts, cut);
    let (life_tuning, life_used) = (life.as_ref().map(|l| &l.tuning), life.as_ref().map(|l| &l.used));
    // Each discharge hands on its end fit to the next ([`crate::carry`]).
    let carrying = Carrying::end_fits(&spec.tracker, life_tuning, &train, &train_fits, &neutral, &rests, cut);
    let start = (spec.tracker.prior, neutral.clone());
    let (judged_carried, judged_kept) =
        end_fits(&spec.tracker, &judged, &judged_fits, carrying.fits.last().or(Some(&start)), cut);
    let width = carrying.width;
    let end_knee_median = carrying.knees.median();
    progress(&format!(
        "prior: each discharge hands on its end fit (the qMobile that puts the model's end at the measured one, the \
         knee below the voltage the model ends at kept apart; {} \
         of {} discharges kept their voltage fit, out of range, or handed on the fit carried into them, cut short \
         or started far short of full; knee against it {:.4} Ah from a full cell, {:.4} Ah from the discharge's \
         own start); {}; width \
         learned on {} consecutive training fits ({} after a rest of more than a day): {}",
        carrying.kept_voltage_fit + judged_kept,
        train.len() + judged.len(),
        end_knee_median.capacity_c / 3600.0,
        end_knee_median.eod_c / 3600.0,
        life.as_ref().map_or("no lifetime model (the previous fit carried as it is)".into(), |l| format!(
            "lifetime model {}",
            l.verdict
        )),
        width.pairs,
        width.long_rest_pairs,
        if width.fitted() {
            format!(
                "sd after the usual rest {:.4} / {:.4} z (qMobile / Ro), + {:.4} / {:.4} z^2 per ln(rest / usual)",
                width.a_z2[0].sqrt(),
                width.a_z2[1].sqrt(),
                width.b_z2[0],
                width.b_z2[1]
            )
        } else {
            "too few pairs: each calibrator's own prior width".into()
        },
    ));
    if carrying.tuning_width != width {
        let tw = &carrying.tuning_width;
        progress(&format!(
            "prior: the training discharges (the validation cycles among them) start from the width learned on the \
             {} pairs before the validation cycles: {}",
            tw.pairs,
            if tw.fitted() {
                format!("sd after the usual rest {:.4} / {:.4} z", tw.a_z2[0].sqrt(), tw.a_z2[1].sqrt())
            } else {
                "too few pairs: each calibrator's own prior width".into()
            }
        ));
    }
    // What each training and judged discharge starts from, one walk through both: under the end fits (the
    // prior and every streaming calibrator) and under the voltage fits (the references that carry a fit: the
    // previous cycle's, the oracle's, with the knee against it; pinned, so the width does not matter).
    // The training discharges start from the tuning lifetime model, the judged ones from the one fitted on
    // every training discharge (that walk observes the training discharges first, for their history).
    // The end fits' walk moves each prior with the current's move (`crate::prior::CurrentSlope`, learned on
    // them as they end); the voltage fits' carries the previous discharge's fit as it is.
    let sequence = |train_carried: &[(Degradation, ModelExtension)],
                    judged_carried: &[(Degradation, ModelExtension)],
                    end_fits: bool| {
        let start = (spec.tracker.prior, neutral.clone());
        let none = Knees::default();
        let tuning_walk = PriorWalk::new(&spec.tracker, life_tuning, carrying.tuning_width);
        let mut tuning_walk = if end_fits { tuning_walk.moving_with_current() } else { tuning_walk };
        let tb = before(&mut tuning_walk, &train, train_carried, &start, &none, cut);
        let walk = PriorWalk::new(&spec.tracker, life_used, width);
        let mut walk = if end_fits { walk.moving_with_current() } else { walk };
        for (r, f) in train.iter().zip(train_carried) {
            walk.observe(r, r.rest_before_s, &f.0);
        }
        let knees = Knees::of(&train, train_carried, cut);
        let first = train_carried.last().cloned().unwrap_or((spec.tracker.prior, neutral.clone()));
        let jb = before(&mut walk, &judged, judged_carried, &first, &knees, cut);
        (tb, jb, walk.current_slope())
    };
    let (train_before, judged_before, slope) = sequence(&carrying.fits, &judged_carried, true);
    // The references carry voltage fits; one cut short hands on the fit before it there too.
    let train_ref_fits = crate::carry::over_cut_short(&train, &train_fits, Some(&start));
    let judged_ref_fits = crate::carry::over_cut_short(&judged, &judged_fits, train_ref_fits.last().or(Some(&start)));
    let (train_ref_before, judged_ref_before, _) = sequence(&train_ref_fits, &judged_ref_fits, false);

    let warmth_by_cycle: serde_json::Map<String, serde_json::Value> = judged
        .iter()
        .zip(&judged_before)
        .map(|(r, b)| (r.cycle.to_string(), serde_json::json!(b.knee.eod_warmth)))
        .collect();
    let warmth_s_per_k: Vec<f64> = judged
        .iter()
        .zip(&judged_before)
        .filter_map(|(r, b)| b.knee.eod_warmth.map(|w| w.c_per_k / r.current_a.abs().max(1e-3)))
        .collect();
    progress(&format!(
        "knee by warmth: moved on {} of {} judged discharges from {:.0} s after the load-on{}",
        warmth_s_per_k.len(),
        judged.len(),
        crate::run::KNEE_WARMTH_AT_S,
        bcal_common::stats::median(&mut warmth_s_per_k.clone())
            .map_or(String::new(), |m| format!(", by a median {m:+.1} s per K above the last three discharges'"))
    ));

    let mut runs: Vec<(&'static str, Vec<CycleRun>)> = Vec::new();
    let mut settings = serde_json::Map::new();
    settings.insert("cell_setting".into(), serde_json::to_value(&facts).unwrap_or_default());
    let start_share: serde_json::Map<String, serde_json::Value> =
        judged.iter().map(|r| (r.cycle.to_string(), serde_json::json!(r.start_share_sd))).collect();
    settings.insert(
        "start_spread".into(),
        serde_json::json!({"noise_v_training_median": noise_median_v, "window": bcal_common::measured::noise::NOISE_WINDOW,
            "judged_share_sd": start_share,
            "what": "how well each judged discharge's starting charge is known, as a share of qMobile (one sd): the \
            mean of its rest readings before the load with the sensor's voltage noise (the median of what the \
            `window` records before it read off their own readings) over their number's root, through the \
            open-circuit curve; 1.645 times it, times qMobile over the current, joins every method's interval of \
            the end in quadrature (`bcal_calib::widening::start_half`)"}),
    );
    settings.insert(
        "model_knee_c".into(),
        serde_json::json!({"training_median": knee_median, "training_median_end_fit": end_knee_median,
            "window": crate::run::KNEE_WINDOW, "warmth_at_s": crate::run::KNEE_WARMTH_AT_S,
            "judged_eod_warmth": warmth_by_cycle,
            "what": "the charge a complete discharge delivered between the model's end of discharge under a fit \
            and the measured cut-off, C: `training_median` under the record's offline voltage fit (the references \
            that carry it), `training_median_end_fit` under its end fit (the prior and the streaming calibrators); \
            `capacity_c` with the model started from a full cell, `eod_c` from the discharge's own start (its rest \
            voltage, as the calibrators start); each discharge adds the median of `capacity_c` over the last \
            `window` discharges before it to every predicted capacity (of a full cell), and the median of `eod_c` \
            over the current assumed to every predicted end of discharge; from `warmth_at_s` after the load-on \
            each knee moves by its slope (`c_per_k`, learned on the cell's own discharges, none before 8 pairs) \
            times the discharge's temperature then above the median of the last `window` discharges' \
            (`reference_k`): `judged_eod_warmth` per judged cycle (`bcal_calib::end_fit::KneeWarmth`)"}),
    );
    settings.insert(
        "prior".into(),
        serde_json::json!({"carried": "end_fit", "kept_voltage_fit": carrying.kept_voltage_fit + judged_kept,
            "width": width, "tuning_width": carrying.tuning_width, "current_slope": slope.learned(),
            "current_moves": slope.moved, "lifetime": life.as_ref().map(|l| serde_json::json!({"model": l.used,
            "tuning_model": l.tuning, "verdict": l.verdict})), "judged": judged_before.iter().zip(&judged).map(|(b, r)| serde_json::json!({
            "cycle": r.cycle, "rest_before_s": b.rest_before_s, "q_mobile_c": b.prior.q_mobile_c,
            "r_o_ohm": b.prior.r_o_ohm, "sd_z": b.prior_sd_z})).collect::<Vec<_>>()}),
    );

    // Every choice of the streaming calibrators is made on the last training cycles.
    let validation_idx = tune::validation_records(&train);
    let validation: Vec<CellRecord> = validation_idx.iter().map(|&k| train[k].clone()).collect();
    let validation_before: Vec<Before> = validation_idx.iter().map(|&k| train_before[k].clone()).collect();
    let validation_ref_before: Vec<Before> = validation_idx.iter().map(|&k| train_ref_before[k].clone()).collect();
    if (input.ukf || input.adaptive_ukf || !input.policies.is_empty()) && validation.is_empty() {
        let reaching = train.iter().filter(|r| r.eod_s.is_some()).count();
        // Where most records stop under load above the cut-off, the cut-off is the records' own, not this one.
        let mut ends: Vec<f64> = train
            .iter()
            .filter(|r| r.eod_s.is_none())
            .filter_map(|r| r.samples.iter().rev().find(|s| s.current_a > crate::record::LOAD_THRESHOLD_A))
            .map(|s| s.voltage_v)
            .collect();
        let what = match bcal_common::stats::median(&mut ends) {
            Some(v) if ends.len() * 2 > train.len() => format!(
                "the training records stop under load at {v:.2} V (median), above the {cut} V cut-off: if they \
                 were run to a cut-off of their own, give it with --cutoff-v (e.g. --cutoff-v {:.1}); if they were \
                 stopped before their end (partial discharges), no end of discharge can be learned from them: give \
                 discharges run to the cell's cut-off (widen --train-cycles, or other records)",
                ((v - 1e-9) * 10.0).ceil() / 10.0
            ),
            _ => "widen --train-cycles".to_string(),
        };
        return Err(CalibrateError::Validation(format!(
            "the streaming calibrators' settings are chosen on the last training cycles, and {reaching} of the \
             training cycles reach the {cut} V cut-off (at least 1 is needed, {} for a sound choice): {what}",
            2 * tune::MIN_VALIDATION
        )));
    }
    settings.insert(
        "validation".into(),
        serde_json::json!({"cycles": validation.iter().map(|r| r.cycle).collect::<Vec<_>>(),
            "short": tune::validation_is_short(&train),
            "what": format!("the training cycles every choice is made on: the last quarter of those that reach the \
                cut-off, at least {}; `short`: fewer than {} reach it, so every complete one but the first is taken \
                and the choices are weak", tune::MIN_VALIDATION, 2 * tune::MIN_VALIDATION)}),
    );
    if !validation.is_empty() && tune::validation_is_short(&train) {
        progress(&format!(
            "validation: only {} of the training cycles reach the {cut} V cut-off ({} make a sound choice): every \
             choice below rests on cycle(s) {} alone and is weak",
            train.iter().filter(|r| r.eod_s.is_some()).count(),
            2 * tune::MIN_VALIDATION,
            validation.iter().map(|r| r.cycle.to_string()).collect::<Vec<_>>().join(", ")
        ));
    }
    let factors = prior_factors(&carrying.tuning_width);
    let mut widenings = serde_json::Map::new();
    // Parameters (and extended-model values) pinned for the whole discharge, each with its own model and the
    // knee every method gets: the references, and the prior every streaming calibrator is held to.
    let pinned = |pins: &dyn Fn(&Before, &CellRecord, usize) -> (Degradation, ModelExtension),
                  recs: &[CellRecord],
                  bs: &[Before]|
     -> Vec<CycleRun> {
        let s = spec.tracker.clone();
        let pins: Vec<(Degradation, ModelExtension)> =
            bs.iter().zip(recs).enumerate().map(|(k, (b, r))| pins(b, r, k)).collect();
        let b: Vec<Before> =
            pins.iter().zip(bs).map(|((d, m), jb)| Before { prior: *d, model: m.clone(), ..jb.clone() }).collect();
        run_all(recs, &b, cut, move |k| Streaming::Pinned { spec: s.clone(), d: pins[k].0 })
    };
    // A chosen streaming calibrator's runs along the judged cycles (along the validation ones: its choice's).
    let raw = |cal: &Streaming, choice: &tune::Choice| tune::Runs {
        validation: choice.runs.clone(),
        judged: run_sequence(cal, &judged, &judged_before, cut, &[1.0], false).remove(0),
    };
    let prior_pin = |b: &Before, _: &CellRecord, _: usize| (b.prior, b.model.clone());
    let prior_runs = tune::Runs {
        validation: pinned(&prior_pin, &validation, &validation_before),
        judged: pinned(&prior_pin, &judged, &judged_before),
    };
    // The prior alone recentred where that serves (as the reference it is delivered as, below): what each
    // streaming calibrator is blended with.
    let prior_twins = crate::recentre::serve(&prior_runs, &validation, &judged);
    // The previous cycle's voltage fit carried over, recentred where that serves (as the reference it is
    // delivered as): what the blend with the prior is blended with in turn.
    let previous_pin = |b: &Before, _: &CellRecord, _: usize| (b.previous, b.model.clone());
    let previous_twins = crate::recentre::serve(
        &tune::Runs {
            validation: pinned(&previous_pin, &validation, &validation_ref_before),
            judged: pinned(&previous_pin, &judged, &judged_ref_before),
        },
        &validation,
        &judged,
    );
    let companions =
        tune::Companions { prior: &prior_runs, prior_delivered: &prior_twins.0, previous_delivered: &previous_twins.0 };
    // Every streaming calibrator is recentred, blended with the prior it starts from and held to it (issue
    // 18, item 5): the prior alone serves a share of a discharge where it beat the calibrator there, as
    // delivered (recentred where that serves, blended: what it would replace), on most of the last that
    // ended (`tune::deliver`). Then its intervals are widened from its runs along the validation cycles and
    // each judged discharge that has ended.
    // With `learned` (its key and entry), the learner on the calibrator's record (issue 18) is delivered too,
    // as a method of its own beside the one it builds on, from the same delivered runs, so that every run
    // measures what the learning adds.
    let deliver = |key: &'static str,
                   r: tune::Runs,
                   learned: Option<(&'static str, &mut serde_json::Value)>,
                   entry: &mut serde_json::Value,
                   widenings: &mut serde_json::Map<String, serde_json::Value>,
                   runs: &mut Vec<(&'static str, Vec<CycleRun>)>| {
        // The knee's warmth move scaled per share to what the calibrator's record says it has not read yet.
        let (r, warmth_shares) = tune::scale_warmth(&r, &validation, &judged);
        entry["warmth_share"] = serde_json::json!({"share": weights_json(&warmth_shares),
            "what": format!("each end of discharge takes this share of the knee's move with the cell's warmth \
                (`model_knee_c.judged_eod_warmth`), per share of the discharge (10 / 50 / 90 %): the least-squares \
                share, held to [0, 1], of the calibrator's signed errors with and without the move over the last \
                {} discharges that ended with a move (none before {}: the whole move; `share`: its median over the \
                judged discharges and how many)", bcal_calib::blend::BLEND_WINDOW, bcal_calib::blend::MIN_BLEND_PAIRS)});
        let own_score = score(&judged, &r.judged);
        let d = tune::deliver(&r, &companions, &validation, &judged);
        entry["recentred"] = serde_json::json!({"cycles": served_cycles(&judged, &d.recentred),
            "voltage_change_cycles": served_cycles(&judged, &d.on_voltage),
            "own_signed_pct": own_score.eod_signed_pct});
        let alone = MethodEntry::new(key, own_score);
        entry["blended"] = serde_json::json!({"eod_weight": weights_json(&d.eod_weights),
            "capacity_weight": weights_json(&d.capacity_weights),
            "what": format!("each reading's predicted end and capacity (values and bounds) are the weighted mean of \
                this calibrator's, recentred where that serves, and the prior alone's, recentred where that serves; \
                its weight per share of the discharge (10 / 50 / 90 %) is the prior's mean squared error over the sum \
                of both over the last {} discharges that ended (validation cycles first; none before {}), on the end \
                and on the capacity each by its own record (`eod_weight`, `capacity_weight`: the calibrator's \
                median weight over the judged discharges blended, and how many); that blend is blended in turn with \
                the previous cycle's fit (`previous_cycle`), recentred where that serves, by the same rule \
                (`previous_cycle.eod_weight`, `previous_cycle.capacity_weight`: the first blend's median weight)",
                bcal_calib::blend::BLEND_WINDOW, bcal_calib::blend::MIN_BLEND_PAIRS),
            "previous_cycle": {"eod_weight": weights_json(&d.previous_eod_weights),
                "capacity_weight": weights_json(&d.previous_capacity_weights)}});
        let (held, gate, capacity_gate) = (d.runs, d.prior_gate, d.capacity_gate);
        let learned = learned.map(|(learned_key, learned_entry)| {
            learned_entry["recentred"] = entry["recentred"].clone();
            learned_entry["blended"] = entry["blended"].clone();
            let without = MethodEntry::new(learned_key, score(&judged, &held.judged));
            let (learned_runs, weights) = tune::learn_on_record(&held, &r, &validation, &judged);
            let learner = format!(
                "a learner on this calibrator's record: least squares refitted before each \
                discharge on its signed errors where the scores take them in that share of the discharge over the \
                last {} discharges that ended (validation cycles first; at least {} pairs), on the last error, the \
                mean of the last five, the log of the rest before, how much warmer the discharge's loaded \
                readings ran up to there (at each reading: so far) than the record's at the same time after the \
                load-on, and the log of the ratio of their mean current up to there to the discharge before's (0 \
                for a ratio within 1/{like} to {like}; learned where the window moved current on {} discharges or \
                more); the moved prediction's weight per share (10 / 50 / 90 %) is the delivered one's mean \
                squared error over the sum of both over the last {} discharges it moved (none before {}; \
                `weight`: its median over the judged discharges blended, and how many); \
                `without`: the figures without it (before the intervals are widened, which leaves the values as \
                they are)",
                bcal_calib::record_learner::RECORD_WINDOW,
                bcal_calib::record_learner::MIN_RECORD_PAIRS,
                bcal_calib::record_learner::MIN_CURRENT_SWITCHES,
                bcal_calib::blend::BLEND_WINDOW,
                bcal_calib::blend::MIN_BLEND_PAIRS,
                like = 1.0 + bcal_calib::record_learner::LIKE_CURRENT,
            );
            learned_entry["learned_capacity"] = serde_json::json!({"weight": weights_json(&weights.capacity),
                "without": {"capacity_rmse_ah": without.capacity_rmse_ah,
                    "capacity_rmse_ah_vs_data": without.capacity_rmse_ah_vs_data},
                "what": format!("each reading's capacity (value and bounds), as delivered after the above, is \
                    blended with the same moved by the error expected by {learner}; the errors are against the \
                    data's charge, Ah")});
            learned_entry["learned_eod"] = serde_json::json!({"weight": weights_json(&weights.eod),
                "without": {"eod_error_pct": without.eod_error_pct},
                "what": format!("each reading's predicted end of discharge (value and bounds), as delivered after \
                    the above, is blended with the same moved by the error expected by {learner}; the errors are \
                    in % of the discharge (the predicted one standing for it when moving)")});
            (learned_key, learned_entry, learned_runs)
        });
        let held_to_prior = serde_json::json!({
            "prior_cycles": served_cycles(&judged, &gate),
            "prior_capacity_cycles": served_cycles(&judged, &capacity_gate),
            "alone": {"capacity_rmse_ah": alone.capacity_rmse_ah, "eod_error_pct": alone.eod_error_pct},
            "what": format!("the prior alone (`prior`) serves the readings of a judged discharge near a share of it \
                (10 / 50 / 90 %, by the predicted end) when it beat this calibrator's EOD error there as delivered \
                (recentred where that serves, blended with the prior and the previous cycle: what it replaces) on at least \
                {:.0} % of the last {} discharges that ended before it (validation cycles first) and in their mean \
                (`prior_cycles`, per share); the capacity there by its own record, the capacity error against \
                the data's charge (`prior_capacity_cycles`); `alone`: the calibrator's figures without it",
                tune::MIN_WIN_SHARE * 100.0, tune::GATE_WINDOW)});
        // Each delivered method's intervals are widened from its own runs.
        let own = std::iter::once((key, entry, held));
        for (k, e, mut held) in own.chain(learned) {
            let hist: Vec<(&CellRecord, &CycleRun)> = validation.iter().zip(&held.validation).collect();
            let w = calibrate_intervals(&hist, &judged, &mut held.judged);
            widenings.insert(k.into(), serde_json::to_value(&w).unwrap_or_default());
            e["held_to_prior"] = held_to_prior.clone();
            runs.push((k, held.judged));
        }
    };

    // The joint UKF: the grid's settings, chosen on the validation cycles (first: the RL correction may
    // start from it).
    let mut ukf_best: Option<(JointUkfSettings, Option<f64>, tune::Choice)> = None;
    if input.ukf
        || input.adaptive_ukf
        || input
            .policies
            .iter()
            .flatten()
            .any(|(pf, _)| pf.task.measured().is_some_and(|t| t.design == Design::UkfCorrection))
    {
        let mut grid: Vec<(JointUkfSettings, Option<f64>)> = Vec::new();
        for g in input.ukf_grid.candidates() {
            for f in &factors {
                // With a learned width the grid's own prior widths make no difference: one of each.
                let same = |(o, of): &(JointUkfSettings, Option<f64>)| {
                    of == f && (f.is_some() && JointUkfSettings { prior_std_z: g.prior_std_z, ..*o } == g || *o == g)
                };
                if !grid.iter().any(same) {
                    grid.push((g, *f));
                }
            }
        }
        progress(&format!(
            "joint UKF: choosing among {} settings on {} validation cycles",
            grid.len(),
            validation.len()
        ));
        let (best, factor, choice) = choose_ukf(&spec.tracker, &grid, &validation, &validation_before, cut)
            .expect("candidates and validation checked");
        progress(&format!(
            "joint UKF: validation EOD error {:.2} % (prior width factor {factor:?})",
            choice.candidates[0].eod_error_pct
        ));
        ukf_best = Some((best, factor, choice));
    }
    // Its runs along the judged cycles: delivered as `ukf`, and the filter the policy is gated against.
    let ukf_runs = ukf_best.as_ref().map(|(best, factor, choice)| {
        let t0 = Instant::now();
        let cal = Streaming::Ukf { spec: spec.tracker.clone(), settings: *best, prior_factor: *factor };
        let r = raw(&cal, choice);
        progress(&format!("joint UKF: {} discharges in {:.0} s", judged.len(), t0.elapsed().as_secs_f64()));
        r
    });

    // The adaptive UKF (issue 18, item 3): the covariance-matching rules on top of the chosen filter, with its
    // prior width, chosen by the same validation objective (the same effort as the filter it adapts). Chosen
    // before RL: the correction may run on top of it.
    type Chosen<'s> = (AdaptiveRule, Vec<(String, Streaming<'s>)>, tune::Choice);
    let mut adaptive_best: Option<Chosen> = None;
    if input.adaptive_ukf {
        let (best, factor, _) = ukf_best.clone().expect("chosen above");
        let rules = input.adaptive_grid.candidates();
        let cands = adaptive_candidates(&spec.tracker, best, factor, &rules);
        let what = ("adaptive UKF", "covariance-matching rules on top of the joint UKF");
        let choice = choose_announced(progress, what, &cands, &validation, &validation_before, cut);
        progress(&format!("adaptive UKF: validation EOD error {:.2} %", choice.candidates[0].eod_error_pct));
        adaptive_best = Some((rules[choice.index], cands, choice));
    }

    // RL: the run's policy files, the one the validation cycles prefer.
    if !input.policies.is_empty() {
        // Each candidate's networks, checked to run here (and an ensemble's members to share one task).
        let mut nets: Vec<Vec<PolicyNet>> = Vec::new();
        for members in &input.policies {
            let mut group = Vec::new();
            for (pf, path) in members {
                let Some(task) = pf.task.measured() else {
                    return Err(CalibrateError::PolicyTask {
                        path: path.clone(),
                        observation: pf.task.observation_name(),
                    });
                };
                if !task.tracker.model.same_kind(&neutral) {
                    return Err(CalibrateError::PolicyModel {
                        path: path.clone(),
                        trained: task.tracker.model.label(),
                        model: neutral.label(),
                    });
                }
                let (first, first_path) = &members[0];
                if members.len() > 1 && (task.design != Design::UkfCorrection || pf.task != first.task) {
                    return Err(CalibrateError::Ensemble { path: path.clone(), first: first_path.clone() });
                }
                group.push(pf.net()?);
            }
            nets.push(group);
        }
        let mut cands: Vec<(String, Streaming)> = Vec::new();
        let mut meta: Vec<(String, serde_json::Value, serde_json::Value)> = Vec::new();
        for (members, group) in input.policies.iter().zip(&nets) {
            let (pf, _) = members[0];
            let task = pf.task.measured().expect("checked above");
            let path = members.iter().map(|(_, p)| p.as_str()).collect::<Vec<_>>().join(" + ");
            let updates: Vec<u64> = members.iter().map(|(m, _)| m.update_step).collect();
            let update = if updates.len() == 1 { serde_json::json!(updates[0]) } else { serde_json::json!(updates) };
            let named = if members.len() == 1 {
                format!("{path} (update {})", pf.update_step)
            } else {
                format!("mean action of {path} (updates {updates:?})")
            };
            match task.design {
                Design::WindowFit => {
                    for f in &factors {
                        let unit = TrackerSpec { interval_scale: [1.0; 2], ..task.tracker.clone() };
                        cands.push((
                            format!("{named}, prior width factor {f:?}"),
                            Streaming::Rl { spec: unit.clone(), net: &group[0], prior_factor: *f },
                        ));
                        meta.push((
                            path.clone(),
                            update.clone(),
                            serde_json::json!({"tracker": unit, "prior_factor": f}),
                        ));
                    }
                }
                Design::UkfCorrection => {
                    // The filter it corrects: the one it trained on, or the joint UKF chosen on these
                    // validation cycles (its zero action is then that baseline), each with the learned prior
                    // widths.
                    type Filter = (String, JointUkfSettings, Option<AdaptiveRule>, Option<f64>);
                    let mut filters: Vec<Filter> = factors
                        .iter()
                        .map(|f| ("its own filter".to_string(), task.ukf_settings(), task.correction.adaptive, *f))
                        .collect();
                    if let Some((b, bf, _)) = &ukf_best {
                        filters.push(("the joint UKF chosen here".into(), *b, None, *bf));
                        if let Some((rule, _, _)) = &adaptive_best {
                            filters.push(("the adaptive UKF chosen here".into(), *b, Some(*rule), *bf));
                        }
                    }
                    for (what, filter, rule, f) in filters {
                        let mut t = task.clone();
                        t.ukf = Some(filter);
                        t.correction.adaptive = rule;
                        // A rule owns the noise: a policy trained with noise actions runs on the plain filter.
                        if rule.is_some() && t.correction.noise_actions {
                            continue;
                        }
                        t.correction.interval_scale = [1.0; 2];
                        meta.push((
                            path.clone(),
                            update.clone(),
                            serde_json::json!({"filter": filter, "rule": rule, "prior_factor": f,
                                "design": "ukf-correction", "ensemble": members.len()}),
                        ));
                        cands.push((
                            format!("{named}, {what}, prior width factor {f:?}"),
                            Streaming::Correction { task: Box::new(t), nets: group, prior_factor: f },
                        ));
                    }
                }
            }
        }
        let what = ("RL-LAC", "candidates (policy files x filters and prior widths)");
        let mut choice = choose_announced(progress, what, &cands, &validation, &validation_before, cut);
        // The policy: the best in the mean that also beats the joint UKF chosen here on most validation
        // cycles (`tune::first_consistent`), else the best in the mean; which of the two serves each judged
        // discharge is then the online gate's call.
        let reference = ukf_best.as_ref().map(|(_, _, c)| c.candidates[0].per_cycle_pct.clone());
        if let Some(p) = reference.as_ref().and_then(|r| tune::first_consistent(&choice.candidates, r)) {
            if p != 0 {
                progress(&format!(
                    "RL-LAC: the best in the mean ({}) beats the joint UKF on fewer than {} of {} validation cycles",
                    choice.chosen,
                    tune::wins_needed(validation.len()),
                    validation.len()
                ));
                choice = tune::chosen_at(choice.candidates, p, &cands, &validation, &validation_before, cut);
            }
        }
        let (path, update, setting) = &meta[choice.index];
        progress(&format!(
            "RL-LAC: {}; validation EOD error {:.2} %",
            choice.chosen,
            choice.candidates.iter().find(|c| c.index == choice.index).map_or(f64::NAN, |c| c.eod_error_pct)
        ));
        let t0 = Instant::now();
        let policy = raw(&cands[choice.index].1, &choice);
        let mut rl_settings = serde_json::json!({"policy_file": path, "update_step": update, "validation": choice,
            "setting": setting});
        let delivered = match &ukf_runs {
            // Online gate: each discharge gets the policy or the joint UKF chosen here, by their record on the
            // discharges that ended before it (`tune::gate_runs`).
            Some(filter) => {
                let (mut r, gate) = tune::gate_runs(&policy, filter, &validation, &judged);
                let capacity_gate = tune::gate_capacity(&policy, filter, &mut r, &validation, &judged);
                let served = served_cycles(&judged, &gate);
                progress(&format!(
                    "RL-LAC: the policy serves {} / {} / {} of {} judged discharges at 10 / 50 / 90 % (the joint \
                     UKF the rest)",
                    gate[0].iter().filter(|g| **g).count(),
                    gate[1].iter().filter(|g| **g).count(),
                    gate[2].iter().filter(|g| **g).count(),
                    judged.len()
                ));
                let (best, factor, _) = ukf_best.as_ref().expect("its runs are");
                let alone = MethodEntry::new("rl", score(&judged, &policy.judged));
                rl_settings["gate"] = serde_json::json!({
                    "what": format!("the readings of a judged discharge near a share of it (10 / 50 / 90 %, by the \
                        filter's predicted end) are served by the policy when it beat the joint UKF chosen here at \
                        that share on at least {:.0} % of the last {} discharges that ended before it (validation \
                        cycles first) and in their mean (`policy_cycles`, per share), else by that filter; the capacity \
                        there by its own record, the capacity error against the data's charge \
                        (`policy_capacity_cycles`)",
                        tune::MIN_WIN_SHARE * 100.0, tune::GATE_WINDOW),
                    "policy_cycles": served, "policy_capacity_cycles": served_cycles(&judged, &capacity_gate),
                    "filter": {"settings": best, "prior_factor": factor},
                    "policy_alone": {"capacity_rmse_ah": alone.capacity_rmse_ah, "eod_error_pct": alone.eod_error_pct}});
                r
            }
            None => policy,
        };
        deliver("rl", delivered, None, &mut rl_settings, &mut widenings, &mut runs);
        settings.insert("rl".into(), rl_settings);
        progress(&format!("RL-LAC: {} discharges in {:.0} s", judged.len(), t0.elapsed().as_secs_f64()));
    }
    if let (true, Some((best, factor, choice)), Some(r)) = (input.ukf, &ukf_best, &ukf_runs) {
        let mut top = choice.clone();
        top.candidates.truncate(5);
        let mut entry = serde_json::json!({"settings": best, "prior_factor": factor, "validation": top});
        let mut learned = serde_json::json!({"builds_on": "ukf"});
        deliver("ukf", r.clone(), Some(("ukf_learned", &mut learned)), &mut entry, &mut widenings, &mut runs);
        settings.insert("ukf".into(), entry);
        settings.insert("ukf_learned".into(), learned);
    }
    if let Some((rule, cands, choice)) = &adaptive_best {
        let (best, factor, _) = ukf_best.clone().expect("chosen above");
        let t0 = Instant::now();
        let r = raw(&cands[choice.index].1, choice);
        progress(&format!("adaptive UKF: {} discharges in {:.0} s", judged.len(), t0.elapsed().as_secs_f64()));
        let mut entry = serde_json::json!({"filter": best, "prior_factor": factor, "rule": rule, "validation": choice});
        deliver("adaptive_ukf", r, None, &mut entry, &mut widenings, &mut runs);
        settings.insert("adaptive_ukf".into(), entry);
    }
    // The references, run on the validation cycles too (their errors start the references' intervals).
    let validation_fits: Vec<(Degradation, ModelExtension)> =
        validation_idx.iter().map(|&k| train_fits[k].clone()).collect();
    let trend = ParamTrend::fit(&train.iter().zip(&train_fits).map(|(r, f)| (r.cycle, f.0)).collect::<Vec<_>>());
    let last_train_model = train_fits.last().map_or_else(|| neutral.clone(), |f| f.1.clone());
    type Pin<'p> = Box<dyn Fn(&Before, &CellRecord, usize, bool) -> (Degradation, ModelExtension) + 'p>;
    let mut references: Vec<(&'static str, Pin)> = Vec::new();
    if input.fit {
        let (vf, jf) = (&validation_fits, &judged_fits);
        references.push(("fit", Box::new(move |_, _, k, judged| if judged { jf[k].clone() } else { vf[k].clone() })));
    }
    references.push(("prior", Box::new(|b, _, _, _| (b.prior, b.model.clone()))));
    references.push(("previous_cycle", Box::new(|b, _, _, _| (b.previous, b.model.clone()))));
    if let Some(t) = trend {
        let m = last_train_model.clone();
        references.push((
            "trend",
            Box::new(move |_, r, _, _| (t.at(r.cycle), ModelExtension { reference_k: Some(r.ambient_k), ..m.clone() })),
        ));
        settings.insert("trend".into(), serde_json::to_value(t).unwrap_or_default());
    }
    // A new cell's model: the base one at the paper's new-cell parameters.
    references.push((
        "uncalibrated",
        Box::new(|_, r, _, _| {
            (Degradation::default(), ModelExtension { reference_k: Some(r.ambient_k), ..Default::default() })
        }),
    ));
    settings.insert("uncalibrated".into(), serde_json::to_value(Degradation::default()).unwrap_or_default());
    let mut recentrings = serde_json::Map::new();
    for (key, pin) in &references {
        let pinned_runs = || tune::Runs {
            validation: pinned(&|b, r, k| pin(b, r, k, false), &validation, &validation_ref_before),
            judged: pinned(&|b, r, k| pin(b, r, k, true), &judged, &judged_ref_before),
        };
        let own = match *key {
            // A new cell's model knows nothing of this cell: it learns nothing from its record either.
            "uncalibrated" => pinned_runs(),
            key => {
                // The prior's and the previous cycle's runs and twins were made for the streaming calibrators:
                // not made twice.
                let (own, recentred, on_voltage) = match key {
                    "prior" => prior_twins.clone(),
                    "previous_cycle" => previous_twins.clone(),
                    _ => crate::recentre::serve(&pinned_runs(), &validation, &judged),
                };
                recentrings.insert(
                    key.to_string(),
                    serde_json::json!({"cycles": served_cycles(&judged, &recentred),
                        "voltage_change_cycles": served_cycles(&judged, &on_voltage)}),
                );
                own
            }
        };
        let mut r = own.judged;
        let hist: Vec<(&CellRecord, &CycleRun)> = validation.iter().zip(&own.validation).collect();
        let w = calibrate_intervals(&hist, &judged, &mut r);
        widenings.insert(key.to_string(), serde_json::to_value(&w).unwrap_or_default());
        runs.push((key, r));
    }
    settings.insert(
        "intervals".into(),
        serde_json::json!({"what": "each discharge's 90 % interval: the method's own half-width times `own` in \
            quadrature with `model` times the predicted duration (end of discharge) or capacity, (own, model) the \
            narrowest pair covering 90 % (split-conformal rank) of the method's scored predictions on the last \
            `window` discharges that had ended (validation cycles first)", "window": crate::interval::WINDOW,
            "per_discharge": widenings}),
    );
    settings.insert(
        "recentred".into(),
        serde_json::json!({"what": format!("each method's predicted end of discharge, and its interval, moved by \
            the median of its signed relative errors at that share of the discharge (10 / 50 / 90 %) over the \
            last {} discharges that had ended (validation cycles first), served at a share of a judged discharge \
            where it beat the method's own predictions on at least {:.0} % of the last {} and in their mean, never \
            after a rest of more than a day (judged cycles served, per share: under each streaming calibrator's \
            `recentred.cycles`, beside its own predictions' signed errors, and here for the references; not \
            `uncalibrated`, a new cell's model that learns nothing of this one); then moved instead by what a \
            line in the voltage change (the last minute's mean of the voltage minus the discharge before's at \
            the same time since the load came on, at the same load and ambient), fitted on the method's own \
            signed errors at that share over its last {} discharges that ended with one, expects, served where \
            that beat the first twin's delivery by the same rule (`voltage_change_cycles`)",
            crate::interval::WINDOW, tune::MIN_WIN_SHARE * 100.0, tune::GATE_WINDOW,
            bcal_calib::recentre::VOLTAGE_WINDOW),
            "references": recentrings}),
    );
    let train_capacities: Vec<(u32, f64)> = train
        .iter()
        .filter_map(|r| r.stated_capacity_ah.filter(|c| *c > 0.0).or(r.data_capacity_ah).map(|c| (r.cycle, c)))
        .collect();

    let methods: BTreeMap<String, MethodEntry> =
        runs.iter().map(|(k, r)| (k.to_string(), MethodEntry::new(k, score(&judged, r)))).collect();
    let report = CalibrationReport {
        cell: input.cell.clone(),
        cutoff_v: cut,
        cutoff_source: input.cutoff_source.clone(),
        train_cycles: train.iter().map(|r| r.cycle).collect(),
        cycles_judged: judged.iter().map(|r| r.cycle).collect(),
        records: summary,
        model: model_label,
        methods,
        settings: serde_json::Value::Object(settings),
        plots: Vec::new(),
        notes: Vec::new(),
        seconds: started.elapsed().as_secs_f64(),
    };
    Ok(Calibration { report, judged, train_capacities, runs, facts })
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_doctor::lifetime::{Condition, LifeTracker};

    const USUAL_REST_S: f64 = 4.0 * 3600.0;
    const NOISE_AH: f64 = 0.004;

    /// A NASA-like life from a generator outside the lifetime model's family: each discharge leaves a
    /// recoverable deficit of 30 mAh, a rest gives back 1 - exp(-rest / 24 h) of the deficit, on a fade of
    /// 4 mAh per discharge and a deterministic wiggle of up to 4 mAh for measurement noise.
    /// The usual rest is 4 h; 300 h at cycle 12, 36 h at cycle 34 (in the last quarter of cycles 1-40) and
    /// the rest `last_rest_s` before cycle 41. Returns the records, their start times and the capacity of
    /// cycle 41.
    fn life(last_rest_s: f64) -> (Vec<Discharge>, Vec<RecordStart>, f64) {
        life_with(last_rest_s, true)
    }

    /// [`life`], with the two long training rests (`long_training_rests`) or every training rest the usual.
    fn life_with(last_rest_s: f64, long_training_rests: bool) -> (Vec<Discharge>, Vec<RecordStart>, f64) {
        let rest_of = |c: u32| match c {
            12 if long_training_rests => 300.0 * 3600.0,
            34 if long_training_rests => 36.0 * 3600.0,
            41 => last_rest_s,
            _ => USUAL_REST_S * (1.0 + 0.02 * f64::from(c % 3)),
        };
        let (mut deficit_ah, mut clock_s) = (0.0, 0.0);
        let (mut records, mut starts, mut last_ah) = (Vec::new(), Vec::new(), 0.0);
        for c in 1..=41u32 {
            deficit_ah *= (-rest_of(c) / (24.0 * 3600.0)).exp();
            let capacity_ah = 1.90 - 0.004 * f64::from(c) - deficit_ah
                + NOISE_AH * ((f64::from(c) * 2.3).sin() + (f64::from(c) * 5.1).cos()) / 2.0;
            clock_s += rest_of(c);
            starts.push(RecordStart { cycle: c, start_s: clock_s, session: 0 });
            let d = discharge(c, capacity_ah);
            clock_s += d.time_s.last().unwrap() - d.time_s[0];
            records.push(d);
            deficit_ah += 0.03;
            last_ah = capacity_ah;
        }
        (records, starts, last_ah)
    }

    /// A 2 A discharge whose voltage falls linearly from 4.0 V through the 2.7 V cut-off at `capacity_ah`,
    /// sampled every 10 s, to 2.6 V.
    fn discharge(cycle: u32, capacity_ah: f64) -> Discharge {
        let to_cutoff_s = capacity_ah * 3600.0 / 2.0;
        let end_s = to_cutoff_s * 1.4 / 1.3;
        let n = (end_s / 10.0).ceil() as usize;
        let mut time_s = vec![0.0];
        let mut current_a = vec![0.0];
        let mut voltage_v = vec![4.19];
        for k in 0..=n {
            let t = k as f64 * end_s / n as f64;
            time_s.push(10.0 + t);
            current_a.push(2.0);
            voltage_v.push(4.0 - 1.3 * t / to_cutoff_s);
        }
        time_s.push(time_s.last().unwrap() + 0.001);
        current_a.push(0.0);
        voltage_v.push(3.3);
        Discharge {
            cell: "L".into(),
            cycle,
            source: "l.csv".into(),
            ambient_k: 297.15,
            time_s,
            voltage_v,
            current_a,
            temperature_k: None,
            stated_capacity_ah: None,
        }
    }

    /// Which training records started partial, and so what the stated capacity measures, is read off the
    /// training records alone: a last training record that rests clearly below the ones before it is a partial
    /// start whatever the judged records after it rest at (before 2026-11-30 their rests decided it, a
    /// look-ahead into a definition and into the validation choices); judged records are read against every
    /// record.
    #[test]
    fn the_stated_capacity_is_read_without_the_judged_records() {
        // Linear discharges whose source states the charge to 2.8 V; cycle 10 rests 60 mV under the ones
        // before it (cycle 8 40 mV, not enough to call).
        let with_rest = |cycle: u32, rest_v: f64| {
            let capacity_ah = 1.8 - 0.002 * f64::from(cycle);
            let mut d = discharge(cycle, capacity_ah);
            d.voltage_v[0] = rest_v;
            d.stated_capacity_ah = Some(capacity_ah * 1.2 / 1.3);
            d
        };
        let train_read: Vec<Discharge> = (1..=10)
            .map(|c| {
                with_rest(
                    c,
                    match c {
                        8 => 4.15,
                        10 => 4.13,
                        _ => 4.19,
                    },
                )
            })
            .collect();
        let marked = |judged_rest_v: [f64; 3]| {
            let judged_read: Vec<Discharge> = (11..=13).map(|c| with_rest(c, judged_rest_v[c as usize - 11])).collect();
            let mut summary = RecordSummary::default();
            let (mut train, _) = prepare_all(&train_read, 2.7, &mut summary);
            let (mut judged, _) = prepare_all(&judged_read, 2.7, &mut summary);
            assert!(summary.refused.is_empty(), "{:?}", summary.refused);
            let stated = mark_partial_starts(&mut train, &mut judged, &train_read, &judged_read, 2.7);
            let partial = |r: &[CellRecord]| r.iter().filter(|r| r.partial_start).map(|r| r.cycle).collect::<Vec<_>>();
            (stated.expect("ten records state a capacity"), train[9].partial_start, partial(&judged))
        };
        let (as_high, partial_high, _) = marked([4.19; 3]);
        let (as_low, partial_low, _) = marked([4.10; 3]);
        assert_eq!(as_high, as_low);
        assert_eq!(as_high.records, 9, "cycle 10 left out as a partial start: {as_high:?}");
        assert!((as_high.voltage_v - 2.8).abs() < 1e-9, "{as_high:?}");
        // Nor do the choices made on the training records: cycle 10 is a partial start there whatever follows.
        assert!(partial_high && partial_low);
        // A judged record is read against its neighbours on both sides, for the scores.
        assert_eq!(marked([4.19, 4.10, 4.19]).2, vec![12]);
    }

    /// The capacity `model` predicts for cycle 41 after following cycles 1-40.
    fn predicted_ah(model: &LifetimeModel, records: &[Discharge], starts: &[RecordStart]) -> f64 {
        let refs: Vec<&Discharge> = records.iter().collect();
        let rests = rests_before(&refs, starts);
        let at = Condition { ambient_c: 24.0, current_a: 2.0 };
        let mut t = LifeTracker::new(*model);
        for d in &records[..40] {
            let w = d.windows_with_cutoff(0.1, 2.0, Some(2.7)).unwrap();
            t.advance_to(d.cycle, rests.get(&d.cycle).copied(), at);
            t.observe(d.charge_ah(w.load_on, w.load_end));
        }
        t.predict(41, rests.get(&41).copied(), at).value
    }

    /// With one long rest in the first three quarters of the training cycles, the recovery's time constant
    /// is not determined (a long one with a large amplitude fits as well); the second, in the last quarter,
    /// fixes it. The model the judged discharges start from is fitted on every training cycle: the jump it
    /// predicts after a 72 h rest is within a quarter of the true one, where the tuning model's (the first
    /// three quarters', what judged discharges started from before) is less than 60 % of it, as on B0006.
    #[test]
    fn the_judged_discharges_start_from_a_lifetime_model_fitted_on_every_training_cycle() {
        let (records, starts, truth_ah) = life(72.0 * 3600.0);
        let train = &records[..40];
        let l = lifetime_model(train, &starts, 2.7).expect("a lifetime model");
        assert!(l.used.amplitude > 0.0 && l.tuning.amplitude > 0.0, "{}", l.verdict);
        assert!(l.verdict.contains("fitted on cycles 1-40"), "{}", l.verdict);
        // The jump over what the usual rest would have given.
        let (usual_records, usual_starts, usual_ah) = life(USUAL_REST_S);
        let jump_ah = truth_ah - usual_ah;
        assert!(jump_ah > 0.05, "the generator's jump {jump_ah}");
        let jump =
            |m: &LifetimeModel| predicted_ah(m, &records, &starts) - predicted_ah(m, &usual_records, &usual_starts);
        let (used, tuning) = (jump(&l.used), jump(&l.tuning));
        assert!((used / jump_ah - 1.0).abs() < 0.25, "used model's jump {used:.4} Ah, truth {jump_ah:.4} Ah");
        assert!(tuning < 0.6 * jump_ah, "tuning model's jump {tuning:.4} Ah, truth {jump_ah:.4} Ah");
    }

    /// Training records whose rests are all about the usual cannot fit a recovery; their model takes the one
    /// NASA's cells show, so a judged discharge after a 72 h rest is predicted to regain capacity (the fade alone
    /// predicted none; this generator's cell regains 0.15 Ah, more than NASA's median cell), with the jump's
    /// uncertainty as wide as the jump. A cell whose records held a long rest keeps its own model (the test
    /// above).
    #[test]
    fn training_records_with_no_long_rest_take_the_recovery_nasa_cells_show() {
        let (records, starts, truth_ah) = life_with(72.0 * 3600.0, false);
        let l = lifetime_model(&records[..40], &starts, 2.7).expect("a lifetime model");
        assert!(l.verdict.contains("the recovery NASA's cells show"), "{}", l.verdict);
        let (usual_records, usual_starts, usual_ah) = life_with(USUAL_REST_S, false);
        let jump_ah = truth_ah - usual_ah;
        assert!(jump_ah > 0.1, "the generator's jump {jump_ah}");
        for m in [&l.used, &l.tuning] {
            let jump = predicted_ah(m, &records, &starts) - predicted_ah(m, &usual_records, &usual_starts);
            assert!(jump > 0.3 * jump_ah && jump < jump_ah, "predicted jump {jump:.4} Ah, truth {jump_ah:.4} Ah");
            assert_eq!(m.jump_sd_fraction, 1.0);
        }
        // Under the usual rests the level is the fade's: the population's recovery moves only what a rest moves.
        let at = Condition { ambient_c: 24.0, current_a: 2.0 };
        let fade = LifetimeModel { amplitude: 0.0, tau_rest_s: 0.0, decay_discharges: 0.0, ..l.used };
        let usual = Some(l.used.usual_rest_s);
        let next_after_usual = |m: LifetimeModel| {
            let mut t = LifeTracker::new(m);
            t.advance_to(40, usual, at);
            t.observe(1.7);
            t.predict(41, usual, at).value
        };
        assert!((next_after_usual(l.used) - next_after_usual(fade)).abs() < 1e-9);
    }

    /// Training records too few to fit the cell's own lifetime model (six, a short life's first third) follow the
    /// life by NASA's cells' recovery, their median rest the usual: a judged discharge after a 72 h rest is
    /// predicted to regain capacity (without a model, none). Two known rests are no usual one: no model.
    #[test]
    fn training_records_too_few_for_a_lifetime_model_take_the_recovery_nasa_cells_show() {
        let (records, starts, truth_ah) = life_with(72.0 * 3600.0, false);
        let l = lifetime_model(&records[34..40], &starts, 2.7).expect("a lifetime model");
        assert!(l.verdict.contains("the recovery NASA's cells show") && l.verdict.contains("35-40"), "{}", l.verdict);
        assert_eq!(l.used, l.tuning);
        assert!((l.used.usual_rest_s / USUAL_REST_S - 1.0).abs() < 0.03, "usual rest {} s", l.used.usual_rest_s);
        let (usual_records, usual_starts, usual_ah) = life_with(USUAL_REST_S, false);
        let jump_ah = truth_ah - usual_ah;
        let jump = predicted_ah(&l.used, &records, &starts) - predicted_ah(&l.used, &usual_records, &usual_starts);
        assert!(jump > 0.3 * jump_ah && jump < jump_ah, "predicted jump {jump:.4} Ah, truth {jump_ah:.4} Ah");
        // No fade: after the usual rest the next discharge is expected at the last one's capacity.
        let at = Condition { ambient_c: 24.0, current_a: 2.0 };
        let mut t = LifeTracker::new(l.used);
        t.advance_to(40, Some(USUAL_REST_S), at);
        t.observe(1.7);
        assert!((t.predict(41, Some(USUAL_REST_S), at).value - 1.7).abs() < 1e-3);
        assert!(lifetime_model(&records[37..40], &starts, 2.7).is_none(), "three records, two known rests");
    }

    /// Of NASA's cells' recovery, records too few to fit their own model take what their rests longer than the
    /// usual said: none where an 87 h rest gave nothing back (NASA's B0025 before its cycle 6), more where a
    /// 36 h rest gave back more than the median cell would have.
    #[test]
    fn too_few_training_records_take_the_recovery_their_long_rests_show() {
        let population = |l: &CellLife| {
            let m = LifetimeModel::population(1.8, l.used.usual_rest_s);
            m.jump_over_usual(72.0 * 3600.0)
        };
        let (mut records, mut starts, mut clock_s) = (Vec::new(), Vec::new(), 0.0);
        for c in 1..=6u32 {
            clock_s += if c == 4 { 87.0 * 3600.0 } else { USUAL_REST_S };
            starts.push(RecordStart { cycle: c, start_s: clock_s, session: 0 });
            let d = discharge(c, 1.85 - 0.004 * f64::from(c) + NOISE_AH * (f64::from(c) * 2.3).sin());
            clock_s += d.time_s.last().unwrap() - d.time_s[0];
            records.push(d);
        }
        let none = lifetime_model(&records, &starts, 2.7).expect("a lifetime model");
        let jump = none.used.jump_over_usual(72.0 * 3600.0);
        assert!(jump < 0.25 * population(&none), "{jump} Ah after 3 days: {}", none.verdict);
        let (records, starts, _) = life(72.0 * 3600.0);
        let more = lifetime_model(&records[29..35], &starts, 2.7).expect("a lifetime model");
        let jump = more.used.jump_over_usual(72.0 * 3600.0);
        assert!(jump > population(&more), "{jump} Ah after 3 days: {}", more.verdict);
    }
}
