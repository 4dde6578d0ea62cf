//! `bcal calibrate`'s work, top to bottom: prepare the training and judged discharges (readings up to the
//! cut-off), fit every one offline with the doctor on the calibrators' model (the base one, or the doctor's
//! extended one with `--model`: the `fit` oracle, the previous-cycle reference, and the per-cycle values
//! of the extended model each discharge starts from), fit the capacity trend on the training cycles, set
//! up the streaming calibrators on validation cycles (the last training cycles: the joint UKF's settings,
//! the RL policy file, both interval scales; see [`crate::tune`]), run every method along every judged
//! discharge, score them against the cycler and assemble the report. Progress goes to a callback;
//! nothing here prints.
//!
//! With an extended model the streaming calibrators track qMobile and Ro in real time and the model's
//! per-cycle parameters (electrode balance, charge-transfer factor) from discharge to discharge: each
//! discharge runs on the values the doctor fitted on the discharge before it, once that one had ended.

use crate::cellspec::{cell_spec, CellFacts};
use crate::record::{prepare, CellRecord, RecordSummary};
use crate::report::{CalibrationReport, MethodEntry};
use crate::run::{knee_s, knees_before, run_all, run_sequence, Before, CycleRun, Streaming, Trend};
use crate::score::score;
use crate::tune;
use bcal_calib::tune::JointUkfGrid;
use bcal_common::battery::Degradation;
use bcal_common::measured::env::{Design, MeasuredSpec};
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::tracker::JointUkfSettings;
use bcal_common::measured::tracker::TrackerSpec;
use bcal_common::policy::PolicyFile;
use bcal_common::policy::PolicyNet;
use bcal_doctor::fit::{refit_cycles, FitConfig, FitRecord};
use bcal_doctor::model_file::DiagnosedModel;
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
    /// The RL policy candidates (a run's checkpoints) and where each came from: the validation cycles
    /// choose one.
    pub policies: Vec<(&'a PolicyFile, String)>,
    pub ukf: bool,
    pub fit: bool,
    /// The cell's setting (None: derived from the training cycles here).
    pub spec: Option<MeasuredSpec>,
    /// The joint UKF's search space (chosen on the validation cycles).
    pub ukf_grid: JointUkfGrid,
    /// The doctor's extended model (`--model diagnosis.json`); None: the base model.
    pub model: Option<DiagnosedModel>,
}

#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    #[error("the policy {path} was trained on the {observation} observation; bcal calibrate runs measured-only policies (retrain with --preset measured)")]
    PolicyTask { path: String, observation: String },
    #[error("the policy {path} was trained on the {trained} model, but this calibration runs the {model} model: train a policy on it (bcal cell-config with the same --model, then bcal train --config)")]
    PolicyModel { path: String, trained: String, model: String },
    #[error("no usable judged discharge: {0}")]
    NothingToJudge(String),
    #[error("the doctor's fit failed: {0}")]
    Fit(#[from] bcal_doctor::DoctorError),
    #[error("{0}")]
    Validation(String),
    #[error("policy: {0}")]
    Policy(#[from] bcal_common::policy::PolicyError),
    #[error("{path}: {why}")]
    Model { path: String, why: String },
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
    let f = refit_cycles(cfg, &recs, causes, shared, None)?;
    Ok(f.per_cycle
        .iter()
        .zip(&f.cycle_ext)
        .zip(ds)
        .map(|((d, e), disc)| (*d, extension_of(causes, e, disc.ambient_k)))
        .collect())
}

/// What each record's calibration knows before it starts (no look-ahead: only discharges that ended): the
/// parameters and model values fitted on the record before it (the first takes `first`), at this record's
/// ambient, and the model's knee over the discharges before it (`earlier_knees` those before `records`).
fn before(
    records: &[CellRecord],
    fits: &[(Degradation, ModelExtension)],
    first: &(Degradation, ModelExtension),
    earlier_knees: &[f64],
    cutoff_v: f64,
) -> Vec<Before> {
    let knees: Vec<Option<f64>> = records.iter().zip(fits).map(|(r, f)| knee_s(r, f, cutoff_v)).collect();
    records
        .iter()
        .zip(knees_before(earlier_knees, &knees))
        .enumerate()
        .map(|(k, (r, knee_s))| {
            let prev = if k == 0 { first.clone() } else { fits[k - 1].clone() };
            Before { prior: prev.0, model: ModelExtension { reference_k: Some(r.ambient_k), ..prev.1 }, knee_s }
        })
        .collect()
}

/// The joint UKF of a cell: the grid's settings chosen on the last training cycles (`train`, with their
/// offline fits; the first starts from `spec`'s prior on `neutral`), each discharge starting from the fit
/// of the one before it. What `bcal calibrate` runs as its `ukf`, and what `bcal cell-config` gives a cell's
/// correction policy to train on, so that training and deployment run one filter. None without validation
/// cycles.
pub fn choose_cell_ukf(
    spec: &TrackerSpec,
    train: &[CellRecord],
    train_fits: &[(Degradation, ModelExtension)],
    neutral: &ModelExtension,
    grid: &[JointUkfSettings],
    cutoff_v: f64,
) -> Option<(JointUkfSettings, tune::Choice)> {
    let train_before = before(train, train_fits, &(spec.prior, neutral.clone()), &[], cutoff_v);
    let validation_idx = tune::validation_records(train);
    let validation: Vec<CellRecord> = validation_idx.iter().map(|&k| train[k].clone()).collect();
    let validation_before: Vec<Before> = validation_idx.iter().map(|&k| train_before[k].clone()).collect();
    let cands: Vec<(String, Streaming)> =
        grid.iter().map(|g| (format!("{g:?}"), Streaming::Ukf { spec: spec.clone(), settings: *g })).collect();
    let choice = tune::choose(&cands, &validation, &validation_before, cutoff_v)?;
    Some((grid[choice.index], choice))
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
    let (train, train_kept) = prepare_all(&input.train, cut, &mut summary);
    let (judged, judged_kept) = prepare_all(&input.judged, cut, &mut summary);
    if judged.is_empty() {
        return Err(CalibrateError::NothingToJudge(summary.refused.join("; ")));
    }
    summary.records = judged.len();
    summary.reaching_cutoff = judged.iter().filter(|r| r.eod_s.is_some()).count();
    summary.cut_short = judged.iter().filter(|r| r.eod_s.is_none()).map(|r| r.cycle).collect();
    progress(&format!(
        "{}: {} training and {} judged discharges ({} reach the {cut} V cut-off); {} refused",
        input.cell,
        train.len(),
        judged.len(),
        summary.reaching_cutoff,
        summary.refused.len()
    ));

    // The calibrators' model: the base one or the doctor's extended one, which they must be able to run.
    let (causes, shared) = model_parts(input.model.as_ref());
    let model_path = input.model.as_ref().map_or_else(String::new, |m| m.path.display().to_string());
    let neutral = extension_of(&causes, &shared, train.first().unwrap_or(&judged[0]).ambient_k);
    neutral.check("the model").map_err(|why| CalibrateError::Model { path: model_path.clone(), why })?;
    if causes.contains(&Cause::Thermal) && input.train.iter().chain(&input.judged).any(|d| d.temperature_k.is_none()) {
        return Err(CalibrateError::Model {
            path: model_path,
            why: "the model's `thermal` cause runs on the cell's measured temperature, and these records have none; \
                  diagnose without it or use records with a temperature column"
                .into(),
        });
    }
    if let Some(c) = input.model.as_ref().and_then(|m| judged.iter().find(|r| m.cycles.contains(&r.cycle))) {
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
        Some(m) => format!("{} (bcal diagnose of {}: {})", neutral.label(), m.cell, m.path.display()),
        None => "base (the NASA electrochemistry model; qMobile and Ro calibrated)".into(),
    };
    progress(&format!("model: {model_label}"));

    // Offline fits (the doctor, on that model) of the training and judged cycles.
    let fit_cfg = FitConfig::default();
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
    let train_knees: Vec<f64> = train.iter().zip(&train_fits).filter_map(|(r, f)| knee_s(r, f, cut)).collect();
    let knee_median = {
        let mut v = train_knees.clone();
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(0.0)
    };
    progress(&format!(
        "model knee: the training cycles reach {cut} V a median {knee_median:.0} s after the model empties (each \
         discharge takes the median of the {} before it)",
        crate::run::KNEE_WINDOW
    ));

    // The cell's setting: given (the RL run's), else derived from the training cycles.
    let (derived, facts) = cell_spec(&train, &train_fits, cut);
    let spec = input.spec.clone().unwrap_or(derived);

    // What every discharge's calibration starts with.
    let train_before = before(&train, &train_fits, &(spec.tracker.prior, neutral.clone()), &[], cut);
    let first_judged = train_fits.last().cloned().unwrap_or((spec.tracker.prior, neutral.clone()));
    let judged_before = before(&judged, &judged_fits, &first_judged, &train_knees, cut);

    let mut runs: Vec<(&'static str, Vec<CycleRun>)> = Vec::new();
    let mut settings = serde_json::Map::new();
    settings.insert("cell_setting".into(), serde_json::to_value(&facts).unwrap_or_default());
    settings.insert(
        "model_knee_s".into(),
        serde_json::json!({"training_median": knee_median, "window": crate::run::KNEE_WINDOW,
            "what": "measured cut-off time - the model's end of discharge under the record's offline fit, from a full \
            cell; each discharge adds the median over the last `window` discharges before it to every model-based \
            end-of-discharge prediction and, times the current, to every capacity"}),
    );

    // Every choice of the streaming calibrators is made on the last training cycles.
    let validation_idx = tune::validation_records(&train);
    let validation: Vec<CellRecord> = validation_idx.iter().map(|&k| train[k].clone()).collect();
    let validation_before: Vec<Before> = validation_idx.iter().map(|&k| train_before[k].clone()).collect();
    if (input.ukf || !input.policies.is_empty()) && validation.is_empty() {
        return Err(CalibrateError::Validation(format!(
            "the streaming calibrators' settings are chosen on the last training cycles, and {} of the training \
             cycles reach the {cut} V cut-off (at least {} are needed): widen --train-cycles",
            train.iter().filter(|r| r.eod_s.is_some()).count(),
            2 * tune::MIN_VALIDATION
        )));
    }

    // The joint UKF: the grid's settings, chosen on the validation cycles (first: the RL correction may
    // start from it).
    let mut ukf_best = None;
    if input.ukf
        || input.policies.iter().any(|(pf, _)| pf.task.measured().is_some_and(|t| t.design == Design::UkfCorrection))
    {
        let grid = input.ukf_grid.candidates();
        progress(&format!(
            "joint UKF: choosing among {} settings on {} validation cycles",
            grid.len(),
            validation.len()
        ));
        let (best, choice) = choose_cell_ukf(&spec.tracker, &train, &train_fits, &neutral, &grid, cut)
            .expect("candidates and validation checked");
        progress(&format!(
            "joint UKF: validation EOD error {:.2} %, interval scale {:.2} (EOD coverage {})",
            choice.candidates[0].eod_error_pct,
            choice.interval_scale,
            choice.validation_eod_coverage_pct.map_or("-".into(), |c| format!("{c:.0} %"))
        ));
        ukf_best = Some((best, choice));
    }

    // RL: the run's policy files, the one the validation cycles prefer.
    if !input.policies.is_empty() {
        let mut nets: Vec<PolicyNet> = Vec::new();
        for (pf, path) in &input.policies {
            let Some(task) = pf.task.measured() else {
                return Err(CalibrateError::PolicyTask { path: path.clone(), observation: pf.task.observation_name() });
            };
            if !task.tracker.model.same_kind(&neutral) {
                return Err(CalibrateError::PolicyModel {
                    path: path.clone(),
                    trained: task.tracker.model.label(),
                    model: neutral.label(),
                });
            }
            nets.push(pf.net()?);
        }
        let mut cands: Vec<(String, Streaming)> = Vec::new();
        let mut meta: Vec<(String, u64, serde_json::Value)> = Vec::new();
        for ((pf, path), net) in input.policies.iter().zip(&nets) {
            let task = pf.task.measured().expect("checked above");
            match task.design {
                Design::WindowFit => {
                    let mut widths = vec![task.tracker.prior_std_z];
                    widths.extend(tune::RL_PRIOR_STD_Z.iter().filter(|w| **w != task.tracker.prior_std_z));
                    for w in widths {
                        let unit = TrackerSpec { interval_scale: [1.0; 2], prior_std_z: w, ..task.tracker.clone() };
                        cands.push((
                            format!("{path} (update {}), prior_std_z {w}", pf.update_step),
                            Streaming::Rl { spec: unit.clone(), net },
                        ));
                        meta.push((path.clone(), pf.update_step, serde_json::json!({"tracker": unit})));
                    }
                }
                Design::UkfCorrection => {
                    // The filter it corrects: the one it trained on (at the real-cell prior widths), or the
                    // joint UKF chosen on these validation cycles (its zero action is then that baseline).
                    let own = task.ukf_settings();
                    let mut filters: Vec<(String, JointUkfSettings)> = tune::RL_PRIOR_STD_Z
                        .iter()
                        .map(|w| {
                            (format!("its own filter, prior std {w}"), JointUkfSettings { prior_std_z: [*w; 2], ..own })
                        })
                        .collect();
                    if let Some((b, _)) = &ukf_best {
                        filters.push(("the joint UKF chosen here".into(), *b));
                    }
                    for (what, f) in filters {
                        let mut t = task.clone();
                        t.ukf = Some(f);
                        t.correction.interval_scale = [1.0; 2];
                        meta.push((
                            path.clone(),
                            pf.update_step,
                            serde_json::json!({"filter": f, "design": "ukf-correction"}),
                        ));
                        cands.push((
                            format!("{path} (update {}), {what}", pf.update_step),
                            Streaming::Correction { task: Box::new(t), net },
                        ));
                    }
                }
            }
        }
        progress(&format!(
            "RL-LAC: choosing among {} candidates (policy files x filters or prior widths) on {} validation cycles",
            cands.len(),
            validation.len()
        ));
        let choice =
            tune::choose(&cands, &validation, &validation_before, cut).expect("candidates and validation checked");
        let (path, update, setting) = &meta[choice.index];
        progress(&format!(
            "RL-LAC: {}; validation EOD error {:.2} %, interval scale {:.2} (EOD coverage {})",
            choice.chosen,
            choice.candidates[0].eod_error_pct,
            choice.interval_scale,
            choice.validation_eod_coverage_pct.map_or("-".into(), |c| format!("{c:.0} %"))
        ));
        let t0 = Instant::now();
        let r = run_sequence(&cands[choice.index].1, &judged, &judged_before, cut, &[choice.interval_scale], false)
            .remove(0);
        progress(&format!("RL-LAC: {} discharges in {:.0} s", judged.len(), t0.elapsed().as_secs_f64()));
        runs.push(("rl", r));
        settings.insert(
            "rl".into(),
            serde_json::json!({"policy_file": path, "update_step": update, "validation": choice, "setting": setting}),
        );
    }
    if input.ukf {
        let (best, choice) = ukf_best.clone().expect("chosen above");
        let t0 = Instant::now();
        let cal = Streaming::Ukf { spec: spec.tracker.clone(), settings: best };
        let r = run_sequence(&cal, &judged, &judged_before, cut, &[choice.interval_scale], false).remove(0);
        progress(&format!("joint UKF: {} discharges in {:.0} s", judged.len(), t0.elapsed().as_secs_f64()));
        runs.push(("ukf", r));
        let mut top = choice.clone();
        top.candidates.truncate(5);
        settings.insert("ukf".into(), serde_json::json!({"settings": best, "validation": top}));
    }
    // The references: parameters (and extended-model values) pinned for the whole discharge.
    // Each with its own model and the knee every method gets.
    let pinned = |pins: Vec<(Degradation, ModelExtension)>| {
        let s = spec.tracker.clone();
        let b: Vec<Before> = pins
            .iter()
            .zip(&judged_before)
            .map(|((d, m), jb)| Before { prior: *d, model: m.clone(), knee_s: jb.knee_s })
            .collect();
        run_all(&judged, &b, cut, move |k| Streaming::Pinned { spec: s.clone(), d: pins[k].0 })
    };
    if input.fit {
        runs.push(("fit", pinned(judged_fits.clone())));
    }
    let previous: Vec<(Degradation, ModelExtension)> =
        judged_before.iter().map(|b| (b.prior, b.model.clone())).collect();
    runs.push(("previous_cycle", pinned(previous)));
    let train_capacities: Vec<(u32, f64)> = train
        .iter()
        .filter_map(|r| r.stated_capacity_ah.filter(|c| *c > 0.0).or(r.data_capacity_ah).map(|c| (r.cycle, c)))
        .collect();
    if let Some(trend) = Trend::fit(&train_capacities) {
        runs.push(("trend", judged.iter().map(|r| trend.run(r)).collect()));
        settings.insert("trend".into(), serde_json::to_value(trend).unwrap_or_default());
    }
    // A new cell's model: the base one at the paper's new-cell parameters.
    let new_cell: Vec<(Degradation, ModelExtension)> = judged
        .iter()
        .map(|r| (Degradation::default(), ModelExtension { reference_k: Some(r.ambient_k), ..Default::default() }))
        .collect();
    runs.push(("uncalibrated", pinned(new_cell)));
    settings.insert("uncalibrated".into(), serde_json::to_value(Degradation::default()).unwrap_or_default());

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
