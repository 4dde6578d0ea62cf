//! `bcal calibrate`'s work, top to bottom: prepare the training and judged discharges (readings up to the
//! cut-off), fit every one offline with the doctor (the `fit` oracle and the previous-cycle reference),
//! fit the capacity trend on the training cycles, set up the streaming calibrators on validation cycles
//! (the last training cycles: the joint UKF's settings, the RL policy file, both interval scales; see
//! [`crate::tune`]), run every method along
//! every judged discharge, score them against the cycler and assemble the report. Progress goes to a
//! callback; nothing here prints.

use crate::cellspec::{cell_spec, CellFacts};
use crate::record::{prepare, CellRecord, RecordSummary};
use crate::report::{CalibrationReport, MethodEntry};
use crate::run::{run_all, run_sequence, CycleRun, Streaming, Trend};
use crate::score::score;
use crate::tune;
use bcal_common::battery::Degradation;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::tracker::TrackerSpec;
use bcal_common::policy::PolicyFile;
use bcal_doctor::fit::{refit_cycles, FitConfig, FitRecord};
use bcal_doctor::Discharge;
use bcal_eval::measured_eval::JointUkfGrid;
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
}

#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    #[error("the policy {path} was trained on the {observation} observation; bcal calibrate runs measured-only policies (retrain with --preset measured)")]
    PolicyTask { path: String, observation: String },
    #[error("no usable judged discharge: {0}")]
    NothingToJudge(String),
    #[error("the doctor's fit failed: {0}")]
    Fit(#[from] bcal_doctor::DoctorError),
    #[error("{0}")]
    Validation(String),
    #[error("policy: {0}")]
    Policy(#[from] bcal_common::policy::PolicyError),
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

/// The doctor's offline per-cycle fit (base model: qMobile and Ro) of every record.
fn fits(ds: &[&Discharge], cfg: &FitConfig) -> Result<Vec<Degradation>, CalibrateError> {
    let recs: Vec<FitRecord> = ds
        .iter()
        .filter_map(|d| d.windows(cfg.load_threshold_a, cfg.v_floor_v).map(|w| FitRecord::new(d, w, cfg)))
        .collect();
    if recs.len() != ds.len() {
        return Err(CalibrateError::NothingToJudge("a record without a load window reached the fit".into()));
    }
    Ok(refit_cycles(cfg, &recs, &[], &bcal_doctor::ExtParams::default(), None)?.per_cycle)
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

    // Offline fits (the doctor, base model) of the training and judged cycles.
    let fit_cfg = FitConfig::default();
    let t0 = Instant::now();
    let train_ds: Vec<&Discharge> = train_kept.iter().map(|&k| &input.train[k]).collect();
    let judged_ds: Vec<&Discharge> = judged_kept.iter().map(|&k| &input.judged[k]).collect();
    let train_fits = if train_ds.is_empty() { Vec::new() } else { fits(&train_ds, &fit_cfg)? };
    let judged_fits = fits(&judged_ds, &fit_cfg)?;
    progress(&format!(
        "offline fits of {} cycles in {:.0} s",
        train_fits.len() + judged_fits.len(),
        t0.elapsed().as_secs_f64()
    ));

    // The model's knee: how much later than the model's own end the training cycles reached the cut-off.
    let knee_s = crate::run::knee_offset_s(&train, &train_fits, cut);
    progress(&format!("model knee: the training cycles reach {cut} V a median {knee_s:.0} s after the model empties"));

    // The cell's setting: given (the RL run's), else derived from the training cycles.
    let (derived, facts) = cell_spec(&train, &train_fits, cut);
    let spec = input.spec.clone().unwrap_or(derived);

    let mut runs: Vec<(&'static str, Vec<CycleRun>)> = Vec::new();
    let mut settings = serde_json::Map::new();
    settings.insert("cell_setting".into(), serde_json::to_value(&facts).unwrap_or_default());
    settings.insert(
        "model_knee_s".into(),
        serde_json::json!({"value": knee_s, "what": "median of (measured cut-off time - the model's end of discharge) over \
            the training cycles under their offline fits; added to every model-based end-of-discharge prediction \
            and, times the current, to every capacity"}),
    );

    // Every choice of the streaming calibrators is made on the last training cycles.
    let validation = tune::validation_records(&train);
    if (input.ukf || !input.policies.is_empty()) && validation.is_empty() {
        return Err(CalibrateError::Validation(format!(
            "the streaming calibrators' settings are chosen on the last training cycles, and {} of the training \
             cycles reach the {cut} V cut-off (at least {} are needed): widen --train-cycles",
            train.iter().filter(|r| r.eod_s.is_some()).count(),
            2 * tune::MIN_VALIDATION
        )));
    }

    // RL: the run's policy files, the one the validation cycles prefer.
    if !input.policies.is_empty() {
        let mut cands = Vec::new();
        let mut nets = Vec::new();
        for (pf, path) in &input.policies {
            let Some(task) = pf.task.measured() else {
                return Err(CalibrateError::PolicyTask { path: path.clone(), observation: pf.task.observation_name() });
            };
            let net = pf.net()?;
            let mut widths = vec![task.tracker.prior_std_z];
            widths.extend(tune::RL_PRIOR_STD_Z.iter().filter(|w| **w != task.tracker.prior_std_z));
            for w in widths {
                let unit = TrackerSpec { interval_scale: [1.0; 2], prior_std_z: w, ..task.tracker.clone() };
                nets.push((net.clone(), unit, path.clone(), pf.update_step));
            }
        }
        for (net, unit, path, update) in &nets {
            cands.push((
                format!("{path} (update {update}), prior_std_z {}", unit.prior_std_z),
                Streaming::Rl { spec: unit.clone(), net },
            ));
        }
        progress(&format!(
            "RL-LAC: choosing among {} policy files on {} validation cycles",
            cands.len(),
            validation.len()
        ));
        let choice = tune::choose(&cands, &validation, cut, knee_s).expect("candidates and validation checked");
        let (net, unit, path, update) = &nets[choice.index];
        progress(&format!(
            "RL-LAC: policy {path} (update {update}, prior_std_z {}); validation EOD error {:.2} %, interval scale {:.2} (EOD coverage {})",
            unit.prior_std_z,
            choice.candidates[0].eod_error_pct,
            choice.interval_scale,
            choice.validation_eod_coverage_pct.map_or("-".into(), |c| format!("{c:.0} %"))
        ));
        let t0 = Instant::now();
        let cal = Streaming::Rl { spec: unit.clone(), net };
        let cal = choice.last_estimate.map_or_else(|| cal.with_prior(&unit.prior), |d| cal.with_prior(&d));
        let r = run_sequence(&cal, &judged, cut, knee_s, &[choice.interval_scale], false).0.remove(0);
        progress(&format!("RL-LAC: {} discharges in {:.0} s", judged.len(), t0.elapsed().as_secs_f64()));
        runs.push(("rl", r));
        settings.insert(
            "rl".into(),
            serde_json::json!({"policy_file": path, "update_step": update, "validation": choice, "tracker": unit}),
        );
    }
    // The joint UKF: the grid's settings, chosen the same way.
    if input.ukf {
        let grid = input.ukf_grid.candidates();
        progress(&format!(
            "joint UKF: choosing among {} settings on {} validation cycles",
            grid.len(),
            validation.len()
        ));
        let cands: Vec<(String, Streaming)> = grid
            .iter()
            .map(|g| (format!("{g:?}"), Streaming::Ukf { spec: spec.tracker.clone(), settings: *g }))
            .collect();
        let choice = tune::choose(&cands, &validation, cut, knee_s).expect("candidates and validation checked");
        let best = grid[choice.index];
        progress(&format!(
            "joint UKF: validation EOD error {:.2} %, interval scale {:.2} (EOD coverage {})",
            choice.candidates[0].eod_error_pct,
            choice.interval_scale,
            choice.validation_eod_coverage_pct.map_or("-".into(), |c| format!("{c:.0} %"))
        ));
        let t0 = Instant::now();
        let cal = Streaming::Ukf { spec: spec.tracker.clone(), settings: best };
        let cal = choice.last_estimate.map_or_else(|| cal.with_prior(&spec.tracker.prior), |d| cal.with_prior(&d));
        let r = run_sequence(&cal, &judged, cut, knee_s, &[choice.interval_scale], false).0.remove(0);
        progress(&format!("joint UKF: {} discharges in {:.0} s", judged.len(), t0.elapsed().as_secs_f64()));
        runs.push(("ukf", r));
        let mut top = choice.clone();
        top.candidates.truncate(5);
        settings.insert("ukf".into(), serde_json::json!({"settings": best, "validation": top}));
    }
    // The references.
    let pinned = |ds: Vec<Degradation>| {
        let s = spec.tracker.clone();
        run_all(&judged, cut, knee_s, move |k| Streaming::Pinned { spec: s.clone(), d: ds[k] })
    };
    if input.fit {
        runs.push(("fit", pinned(judged_fits.clone())));
    }
    let previous: Vec<Degradation> = (0..judged.len())
        .map(|k| if k > 0 { judged_fits[k - 1] } else { train_fits.last().copied().unwrap_or(spec.tracker.prior) })
        .collect();
    runs.push(("previous_cycle", pinned(previous)));
    let train_capacities: Vec<(u32, f64)> = train
        .iter()
        .filter_map(|r| r.stated_capacity_ah.filter(|c| *c > 0.0).or(r.data_capacity_ah).map(|c| (r.cycle, c)))
        .collect();
    if let Some(trend) = Trend::fit(&train_capacities) {
        runs.push(("trend", judged.iter().map(|r| trend.run(r)).collect()));
        settings.insert("trend".into(), serde_json::to_value(trend).unwrap_or_default());
    }
    runs.push(("uncalibrated", pinned(vec![Degradation::default(); judged.len()])));
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
        model: "base (the NASA electrochemistry model; qMobile and Ro calibrated)".into(),
        methods,
        settings: serde_json::Value::Object(settings),
        plots: Vec::new(),
        notes: Vec::new(),
        seconds: started.elapsed().as_secs_f64(),
    };
    Ok(Calibration { report, judged, train_capacities, runs, facts })
}
