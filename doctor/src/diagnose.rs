//! The diagnosis, top to bottom: calibrate the base model per cycle, analyse its residual, fit every
//! candidate cause on the training cycles (shared cause parameters jointly with the per-cycle ones: qMobile,
//! Ro and the cause's own per-cycle parameters, if any), judge each on held-out cycles (shared parameters
//! frozen, per-cycle parameters re-calibrated on every held-out cycle by the same procedure), rank by
//! held-out RMSE with a complexity penalty (a fixed cost per shared parameter, the BIC's cost with a floor
//! for per-cycle ones), name the winner or `none` (judging the rest before the load too, which nothing is
//! calibrated on), then grow the extended model greedily while each added cause still buys held-out
//! accuracy and lowers the penalised score.
//!
//! Records that end under load above the cell's cut-off (truncated) are kept out of every fit: their
//! capacity is a lower bound and qMobile is a capacity. Records that end under load at or below the cut-off
//! reached it: they are complete discharges logged without the relaxation after, and are used. A cut-off
//! above a record's first loaded voltage is refused for that record (it cannot be the cell's). The diagnosis
//! sees only the records; it never prints.

use crate::analysis::{record_residual, structure, RecordResidual, Structure};
use crate::error::DoctorError;
use crate::fit::{fit, refit_cycles, simulate_record, CycleStart, FitConfig, FitRecord, Fitted};
use crate::record::{Discharge, Windows, DEFAULT_CUTOFF_V, PARTIAL_START_DROP_V};
use crate::sim::{Cause, ExtParams};
use bcal_common::battery::Degradation;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;

/// Every knob of the diagnosis, with its default.
#[derive(Clone, Debug, PartialEq)]
pub struct DiagnoseConfig {
    /// Fitting settings (simulator step, load threshold, fit floor, patience).
    pub fit: FitConfig,
    /// Held-out RMSE gain a cause needs to be named, %. Default 10.
    pub min_gain_pct: f64,
    /// Further held-out gain each cause added to the extended model must bring, %; the penalised score must
    /// fall too. Default 5.
    pub min_step_gain_pct: f64,
    /// Complexity penalty: the ranking score is held-out RMSE * (1 + this * added parameters). Default 0.02.
    pub penalty_per_param: f64,
    /// Least cost of each per-cycle parameter beyond qMobile and Ro in the ranking score: the RMSE is
    /// multiplied by at least (1 + this * per-cycle parameters), or by the BIC's factor when larger. Default
    /// 0.05. A per-cycle parameter is calibrated on the very held-out cycles it is judged on, so it buys some
    /// held-out accuracy with no effect behind it: on the synthetic tuning cells (seeds 100-119 of
    /// `tests/soak.rs`, 180 cells) one bought up to 5 % over the best shared cause on cells with no per-cycle
    /// effect, while real per-cycle effects beat the best shared cause by 3x or more.
    pub min_cycle_penalty: f64,
    /// The base fit is called noise when its held-out RMSE is within this factor of the noise estimate.
    /// Default 1.15.
    pub noise_factor: f64,
    /// Most causes the extended model combines. Default 3.
    pub max_causes: usize,
    /// The candidates to test. Default all.
    pub causes: Vec<Cause>,
    /// The cell's discharge cut-off, V (`read::nasa_cutoff_v` gives a NASA cell's). A record that ends under
    /// load at or below it reached it and is used; above it, the record was cut short (truncated) and is kept
    /// out; a record whose first loaded voltage is below it is refused (wrong cut-off). `None`:
    /// [`DEFAULT_CUTOFF_V`] (2.5 V) decides complete against truncated, noted on every record it decides, and
    /// nothing is refused. Default `None`.
    pub cutoff_v: Option<f64>,
    /// A record whose rest before the load lies more than this below the full cell's open-circuit voltage
    /// is reported as starting partly discharged (`RecordInfo::partial_start`), V. Default
    /// [`PARTIAL_START_DROP_V`].
    pub partial_start_drop_v: f64,
}

impl Default for DiagnoseConfig {
    fn default() -> Self {
        Self {
            fit: FitConfig::default(),
            min_gain_pct: 10.0,
            min_step_gain_pct: 5.0,
            penalty_per_param: 0.02,
            min_cycle_penalty: 0.05,
            noise_factor: 1.15,
            max_causes: 3,
            causes: Cause::ALL.to_vec(),
            cutoff_v: None,
            partial_start_drop_v: PARTIAL_START_DROP_V,
        }
    }
}

/// Per-cycle fit result.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CycleFit {
    pub cycle: u32,
    pub q_mobile_c: f64,
    pub r_o_ohm: f64,
    /// The per-cycle extension parameters calibrated on this cycle (empty for the base model and for
    /// causes with shared parameters only).
    pub extra: BTreeMap<&'static str, f64>,
    pub rmse_mv: f64,
    /// The cycle's full extension (shared and per-cycle values).
    #[serde(skip)]
    pub ext: ExtParams,
}

impl CycleFit {
    /// The fitted degradation pair.
    pub fn degradation(&self) -> Degradation {
        Degradation { q_mobile_c: self.q_mobile_c, r_o_ohm: self.r_o_ohm }
    }

    /// This cycle's fit as the start of another.
    pub fn start(&self) -> CycleStart {
        CycleStart { d: self.degradation(), ext: self.ext, rmse_v: Some(self.rmse_mv / 1000.0) }
    }
}

/// A model (base, a candidate, or the extended one) on training and held-out cycles.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ModelResult {
    pub causes: Vec<&'static str>,
    /// Shared parameters (fitted on the training cycles, frozen on held-out ones).
    pub params: BTreeMap<&'static str, f64>,
    /// Number of shared parameters.
    pub n_params: usize,
    /// Shared parameters the fit left at a bound of their physical range ([`at_bounds`]): the cause stands in
    /// for an effect beyond what it can hold, and its curve outside the fit window is an extrapolation.
    pub at_bounds: Vec<&'static str>,
    /// Per-cycle parameters beyond qMobile and Ro (calibrated on every cycle, held-out ones included).
    pub cycle_params: Vec<&'static str>,
    pub train_rmse_mv: f64,
    pub heldout_rmse_mv: f64,
    /// Held-out gain over the base model, %.
    pub gain_pct: f64,
    /// Held-out RMSE over the whole judged record, mV: the fit window (calibrated) and the rest before the
    /// load, which no parameter is calibrated on (the model predicts it from its full-charge state).
    pub heldout_record_rmse_mv: f64,
    /// Gain of that RMSE over the base model's, %.
    pub record_gain_pct: f64,
    /// Held-out RMSE with the complexity penalty, mV (the ranking key).
    pub score_mv: f64,
    pub train_cycles: Vec<CycleFit>,
    pub heldout_cycles: Vec<CycleFit>,
    /// Residual structure on the held-out cycles.
    pub heldout_structure: Structure,
    /// The discharge part whose RMSE this model lowers most against the base, and by how many mV.
    pub removes: Option<Evidence>,
    #[serde(skip)]
    pub ext: ExtParams,
    #[serde(skip)]
    pub heldout_residuals: Vec<RecordResidual>,
}

/// Which residual feature a candidate removes.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Evidence {
    pub part: &'static str,
    pub base_rmse_mv: f64,
    pub rmse_mv: f64,
    /// Correlations of the residual that fell most in magnitude (name, base, candidate).
    pub correlation: (&'static str, f64, f64),
}

/// A candidate's line in the report (the schema plus evidence).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Candidate {
    pub cause: &'static str,
    pub params: BTreeMap<&'static str, f64>,
    /// Per-cycle parameters beyond qMobile and Ro.
    pub cycle_params: Vec<&'static str>,
    pub train_rmse_mv: f64,
    pub heldout_rmse_mv: f64,
    pub gain_pct: f64,
    /// Gain over the fit window and the rest before the load (see [`ModelResult::record_gain_pct`]), %.
    pub record_gain_pct: f64,
    pub score_mv: f64,
    pub removes: Option<Evidence>,
}

/// One input record and what became of it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RecordInfo {
    pub cycle: u32,
    pub file: String,
    /// `train`, `heldout`, or `excluded`.
    pub role: &'static str,
    /// Ends under load above the cut-off: cut short, kept out of the fits.
    pub truncated: bool,
    /// Ends under load at or below the cut-off: complete (used), without the relaxation after it.
    pub ended_at_cutoff: bool,
    /// Charge drawn under load, Ah; `None` for truncated records (a lower bound only).
    pub capacity_ah: Option<f64>,
    /// Mean voltage of the rest before the load, V (`None` without one).
    pub rest_before_v: Option<f64>,
    /// The rest lies more than `partial_start_drop_v` below the full cell's open-circuit voltage: the
    /// discharge did not start full, and the fit starts it from that rest (through the open-circuit curve).
    pub partial_start: bool,
    pub samples: usize,
    pub note: Option<String>,
}

/// The whole diagnosis (serialised as `diagnosis.json`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Diagnosis {
    pub cell: String,
    /// The named cause: the best candidate, or `none`.
    pub cause: &'static str,
    /// What the verdict rests on: `fit_window` (the held-out loads, as ranked in `candidates`),
    /// `rest_before` (the load showed nothing and the rest before it named the cause: `rest_candidates`),
    /// or `none`.
    pub named_on: &'static str,
    /// Every candidate's name, best first.
    pub ranking: Vec<&'static str>,
    pub candidates: Vec<Candidate>,
    /// When the load showed nothing but the rest before it did: the candidates with shared parameters
    /// fitted on the training rests too, best first by held-out RMSE over the load and the rest (their
    /// `score_mv` stays the fit window's). Empty otherwise.
    pub rest_candidates: Vec<Candidate>,
    pub base: ModelResult,
    pub extended: ModelResult,
    /// Held-out gain of the extended model over the base, %.
    pub gain_pct: f64,
    /// Sensor-noise estimate from the base residual, mV.
    pub noise_mv: f64,
    /// Residual structure of the base model on the training cycles.
    pub base_train_structure: Structure,
    pub records: Vec<RecordInfo>,
    /// Truncated records kept out of the fits.
    pub truncated_count: usize,
    /// Records that ended under load at or below the cut-off, used as complete discharges.
    pub ended_at_cutoff_count: usize,
    pub settings: Settings,
    /// The cell's life across discharges ([`crate::lifetime::assess`]): `None` until the caller adds it (it
    /// needs every record of the life and their start times, which the voltage diagnosis does not see).
    pub lifetime: Option<crate::lifetime::Lifetime>,
}

/// The settings the diagnosis ran with.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Settings {
    pub dt_max_s: f64,
    pub load_threshold_a: f64,
    pub v_floor_v: f64,
    pub settle_s: f64,
    pub min_gain_pct: f64,
    pub min_step_gain_pct: f64,
    pub penalty_per_param: f64,
    pub min_cycle_penalty: f64,
    pub noise_factor: f64,
    pub max_causes: usize,
    /// The cut-off that told complete records from truncated ones, V, and whether the caller gave it (else
    /// [`DEFAULT_CUTOFF_V`]).
    pub cutoff_v: f64,
    pub cutoff_given: bool,
    pub partial_start_drop_v: f64,
}

struct Prepared<'a> {
    train: Vec<FitRecord<'a>>,
    heldout: Vec<FitRecord<'a>>,
    records: Vec<RecordInfo>,
    truncated: usize,
}

fn prepare<'a>(cfg: &DiagnoseConfig, train: &'a [Discharge], heldout: &'a [Discharge]) -> Prepared<'a> {
    let fc = &cfg.fit;
    let cutoff_v = cfg.cutoff_v.unwrap_or(DEFAULT_CUTOFF_V);
    let cutoff_said = if cfg.cutoff_v.is_some() {
        format!("the cut-off {cutoff_v} V")
    } else {
        format!("the default cut-off {cutoff_v} V (none given)")
    };
    let mut p = Prepared { train: Vec::new(), heldout: Vec::new(), records: Vec::new(), truncated: 0 };
    for (set, role) in [(train, "train"), (heldout, "heldout")] {
        for d in set {
            let w: Option<Windows> = d.windows_with_cutoff(fc.load_threshold_a, fc.v_floor_v, cfg.cutoff_v);
            let refused = cfg.cutoff_v.and_then(|c| d.check_cutoff(c, fc.load_threshold_a).err());
            let last_v = |w: &Windows| d.voltage_v[w.load_end - 1];
            let (role, note) = match w {
                None => ("excluded", Some(format!("no sample above {} A", fc.load_threshold_a))),
                Some(_) if refused.is_some() => ("excluded", refused.map(|e| e.to_string())),
                Some(w) if w.truncated => (
                    "excluded",
                    Some(format!("ends under load at {:.3} V, above {cutoff_said}: truncated", last_v(&w))),
                ),
                Some(w) if w.fit_len() < 5 => ("excluded", Some("fewer than 5 loaded samples above the floor".into())),
                // Every loaded sample follows a load step (or its settling time): the load switches about as
                // often as it is sampled (B0025's 20 s square wave at 10 s samples), so when each step came,
                // and with it every sampled voltage, is unknown.
                Some(w) if FitRecord::new(d, w, fc).used.len() < 5 => (
                    "excluded",
                    Some(format!(
                        "{} of {} loaded samples above the floor follow a load step by less than {} s: the load \
                         switches about as often as it is sampled, so no sampled voltage can be fitted",
                        w.fit_len() - FitRecord::new(d, w, fc).used.len(),
                        w.fit_len(),
                        fc.settle_s
                    )),
                ),
                Some(w) if w.ended_at_cutoff => (
                    role,
                    Some(format!(
                        "ends under load at {:.3} V, at or below {cutoff_said}: a complete discharge without the \
                         relaxation after it",
                        last_v(&w)
                    )),
                ),
                Some(_) if d.alternating_load(fc.load_threshold_a, fc.step_threshold_a) => (
                    role,
                    Some(
                        "the load switches about as often as it is sampled: every sample fitted, the load each reads \
                         run over the interval before it"
                            .into(),
                    ),
                ),
                Some(_) => (role, None),
            };
            let truncated = w.is_some_and(|w| w.truncated);
            p.truncated += usize::from(truncated);
            let start = d.start_state(&fc.base, fc.load_threshold_a, cfg.partial_start_drop_v).ok().flatten();
            p.records.push(RecordInfo {
                cycle: d.cycle,
                file: d.source.file_name().map_or_else(String::new, |f| f.to_string_lossy().into_owned()),
                role,
                truncated,
                ended_at_cutoff: w.is_some_and(|w| w.ended_at_cutoff),
                capacity_ah: w.filter(|w| !w.truncated).map(|w| d.charge_ah(w.load_on, w.load_end)),
                rest_before_v: start.map(|s| s.rest_v),
                partial_start: start.is_some_and(|s| s.partial),
                samples: d.len(),
                note,
            });
            if let (Some(w), "train") = (w, role) {
                p.train.push(FitRecord::new(d, w, fc));
            } else if let (Some(w), "heldout") = (w, role) {
                p.heldout.push(FitRecord::new(d, w, fc));
            }
        }
    }
    p
}

/// Runs the diagnosis: `train` calibrates, `heldout` judges.
pub fn diagnose(cfg: &DiagnoseConfig, train: &[Discharge], heldout: &[Discharge]) -> Result<Diagnosis, DoctorError> {
    if !(cfg.fit.dt_max_s > 0.0 && cfg.fit.dt_max_s.is_finite()) {
        return Err(DoctorError::BadConfig(format!("dt_max_s = {} must be > 0", cfg.fit.dt_max_s)));
    }
    if let Some(c) = cfg.cutoff_v {
        if !(0.5..=5.0).contains(&c) {
            return Err(DoctorError::BadConfig(format!(
                "cutoff_v = {c} V is not a Li-ion discharge cut-off (0.5-5 V); give it in volts, e.g. 2.5"
            )));
        }
    }
    let p = prepare(cfg, train, heldout);
    if p.train.is_empty() || p.heldout.is_empty() {
        let mut reasons: Vec<String> = Vec::new();
        for r in p.records.iter().filter(|r| r.role == "excluded") {
            let why = format!("cycle {}: {}", r.cycle, r.note.as_deref().unwrap_or("excluded"));
            if reasons.len() < 3 {
                reasons.push(why);
            }
        }
        let excluded = p.records.iter().filter(|r| r.role == "excluded").count();
        return Err(DoctorError::NothingSelected {
            why: format!(
                "{} usable training and {} usable held-out records ({excluded} excluded{}); widen --cycles or --holdout",
                p.train.len(),
                p.heldout.len(),
                if reasons.is_empty() { String::new() } else { format!(": {}", reasons.join("; ")) }
            ),
        });
    }
    let cell = p.train[0].d.cell.clone();

    // 1. Base model: per-cycle qMobile and Ro.
    let base_fit = fit(&cfg.fit, &p.train, &[], &ExtParams::default(), None)?;
    let base_train_starts = base_fit.starts();
    let base_train_structure = train_structure(&cfg.fit, &p.train, &base_fit)?;
    let base = judge(cfg, &p, &[], base_fit, None, None)?;
    let base_held_starts: Vec<CycleStart> = base.heldout_cycles.iter().map(CycleFit::start).collect();
    let base_rmse = base.heldout_rmse_mv;
    let noise_mv = base_train_structure.noise_mv;

    // 2. Each candidate alone.
    // The candidates are independent: run side by side (each one's fits are parallel over records too, and
    // rayon shares the cores between both levels).
    let mut results: Vec<(Cause, ModelResult)> = cfg
        .causes
        .par_iter()
        .map(|&c| {
            let f = fit(&cfg.fit, &p.train, &[c], &ExtParams::default(), Some(&base_train_starts))?;
            Ok((c, judge(cfg, &p, &[c], f, Some(&base), Some(&base_held_starts))?))
        })
        .collect::<Result<_, DoctorError>>()?;
    results.sort_by(|a, b| a.1.score_mv.total_cmp(&b.1.score_mv));
    let ranking: Vec<&'static str> = results.iter().map(|(c, _)| c.name()).collect();
    // The verdict is `none` when the base model already meets the noise on every judged sample, or when
    // the best candidate gains too little. Both look at the rest before the load as well as the fit
    // window: a sensor offset that the calibrated Ro hides under a held-out constant current still shows
    // at rest, where nothing is calibrated.
    let base_rest = &base.heldout_structure.rest_before;
    let base_within_noise = base_rmse <= cfg.noise_factor * noise_mv
        && (base_rest.samples == 0 || base_rest.rmse_mv <= cfg.noise_factor * noise_mv);
    let best_gain = results.first().map_or(0.0, |r| r.1.gain_pct.max(r.1.record_gain_pct));
    let is_noise = base_within_noise || best_gain < cfg.min_gain_pct;
    let mut cause = if is_noise { "none" } else { results[0].0.name() };
    let mut named_on = if is_noise { "none" } else { "fit_window" };
    let mut extended_from_rest: Option<ModelResult> = None;

    // 2b. When the load shows nothing but the rest before it does, the rest is the only evidence left: under
    // one constant current a sensor offset is exactly Ro * I to the calibrated Ro, so its parameter is not
    // even determined by the fit window (a whole constant-current life hiding a 15-30 mV offset was named
    // `none`; its candidate's offset wandered to wherever the flat direction left it). The candidates with
    // shared parameters are then fitted on the training records' rests too, judged on the held-out records
    // with their rests (where nothing is calibrated), and ranked by that RMSE with the same penalty.
    let mut rest_results: Vec<(Cause, ModelResult)> = Vec::new();
    let rest_shows = base_rest.samples > 0 && base_rest.rmse_mv > cfg.noise_factor * noise_mv;
    if is_noise && rest_shows {
        let train_rest: Vec<FitRecord<'_>> = p.train.iter().cloned().map(FitRecord::with_rest_before).collect();
        let has_temperature = p.train.iter().all(|r| r.d.temperature_k.is_some());
        rest_results = cfg
            .causes
            .par_iter()
            .filter(|c| !c.params(has_temperature).is_empty())
            .map(|&c| {
                let f = fit(&cfg.fit, &train_rest, &[c], &ExtParams::default(), Some(&base_train_starts))?;
                Ok((c, judge(cfg, &p, &[c], f, Some(&base), Some(&base_held_starts))?))
            })
            .collect::<Result<_, DoctorError>>()?;
        let rest_score = |m: &ModelResult| m.heldout_record_rmse_mv * (1.0 + cfg.penalty_per_param * m.n_params as f64);
        rest_results.sort_by(|a, b| rest_score(&a.1).total_cmp(&rest_score(&b.1)));
        // Named when it lowers the judged record's RMSE by the naming gain without costing the fit window
        // more than the extension step's gain.
        if let Some((c, m)) = rest_results
            .first()
            .filter(|(_, m)| m.record_gain_pct >= cfg.min_gain_pct && m.gain_pct >= -cfg.min_step_gain_pct)
        {
            cause = c.name();
            named_on = "rest_before";
            extended_from_rest = Some(m.clone());
        }
    }

    // 3. Extended model: add causes while each buys held-out accuracy.
    let mut extended = extended_from_rest.unwrap_or_else(|| base.clone());
    if !is_noise {
        let mut chosen = vec![results[0].0];
        extended = results[0].1.clone();
        while chosen.len() < cfg.max_causes {
            let starts: Vec<CycleStart> = extended.train_cycles.iter().map(CycleFit::start).collect();
            let held: Vec<CycleStart> = extended.heldout_cycles.iter().map(CycleFit::start).collect();
            let tried: Vec<(Cause, ModelResult)> = results
                .iter()
                .filter(|(c, r)| !chosen.contains(c) && r.gain_pct >= cfg.min_step_gain_pct)
                .collect::<Vec<_>>()
                .into_par_iter()
                .map(|(c, _)| {
                    let mut causes = chosen.clone();
                    causes.push(*c);
                    let f = fit(&cfg.fit, &p.train, &causes, &extended.ext, Some(&starts))?;
                    Ok((*c, judge(cfg, &p, &causes, f, Some(&base), Some(&held))?))
                })
                .collect::<Result<_, DoctorError>>()?;
            // The first of equal scores, in ranking order, as the sequential search took it.
            let mut best_next: Option<(Cause, ModelResult)> = None;
            for (c, m) in tried {
                if best_next.as_ref().is_none_or(|(_, b)| m.score_mv < b.score_mv) {
                    best_next = Some((c, m));
                }
            }
            // A cause joins when it lowers the held-out RMSE by the step gain and also lowers the penalised
            // score: a per-cycle parameter must pay for the accuracy it buys by fitting the judged cycles.
            match best_next {
                Some((c, m))
                    if 100.0 * (extended.heldout_rmse_mv - m.heldout_rmse_mv) / extended.heldout_rmse_mv
                        >= cfg.min_step_gain_pct
                        && m.score_mv < extended.score_mv =>
                {
                    chosen.push(c);
                    extended = m;
                }
                _ => break,
            }
        }
    }
    let gain_pct = extended.gain_pct;
    let candidate = |(c, r): &(Cause, ModelResult)| Candidate {
        cause: c.name(),
        params: r.params.clone(),
        cycle_params: r.cycle_params.clone(),
        train_rmse_mv: r.train_rmse_mv,
        heldout_rmse_mv: r.heldout_rmse_mv,
        gain_pct: r.gain_pct,
        record_gain_pct: r.record_gain_pct,
        score_mv: r.score_mv,
        removes: r.removes.clone(),
    };
    let rest_candidates = rest_results.iter().map(candidate).collect();
    let candidates = results.iter().map(candidate).collect();
    Ok(Diagnosis {
        cell,
        cause,
        named_on,
        ranking,
        candidates,
        rest_candidates,
        base,
        extended,
        gain_pct,
        noise_mv,
        base_train_structure,
        ended_at_cutoff_count: p.records.iter().filter(|r| r.ended_at_cutoff).count(),
        records: p.records,
        truncated_count: p.truncated,
        settings: Settings {
            dt_max_s: cfg.fit.dt_max_s,
            load_threshold_a: cfg.fit.load_threshold_a,
            v_floor_v: cfg.fit.v_floor_v,
            settle_s: cfg.fit.settle_s,
            min_gain_pct: cfg.min_gain_pct,
            min_step_gain_pct: cfg.min_step_gain_pct,
            penalty_per_param: cfg.penalty_per_param,
            min_cycle_penalty: cfg.min_cycle_penalty,
            noise_factor: cfg.noise_factor,
            max_causes: cfg.max_causes,
            cutoff_v: cfg.cutoff_v.unwrap_or(DEFAULT_CUTOFF_V),
            cutoff_given: cfg.cutoff_v.is_some(),
            partial_start_drop_v: cfg.partial_start_drop_v,
        },
        lifetime: None,
    })
}

fn residuals_of(cfg: &FitConfig, recs: &[FitRecord<'_>], f: &Fitted) -> Result<Vec<RecordResidual>, DoctorError> {
    recs.iter()
        .zip(f.per_cycle.iter().zip(&f.cycle_ext))
        .map(|(r, (deg, ext))| Ok(record_residual(r.d, r.w, &r.used, &simulate_record(cfg, r.d, *deg, ext)?)))
        .collect()
}

fn train_structure(cfg: &FitConfig, recs: &[FitRecord<'_>], f: &Fitted) -> Result<Structure, DoctorError> {
    let res = residuals_of(cfg, recs, f)?;
    let ds: Vec<&Discharge> = recs.iter().map(|r| r.d).collect();
    Ok(structure(&ds, &res))
}

fn cycle_fits(recs: &[FitRecord<'_>], f: &Fitted) -> Vec<CycleFit> {
    recs.iter()
        .enumerate()
        .map(|(c, r)| CycleFit {
            cycle: r.d.cycle,
            q_mobile_c: f.per_cycle[c].q_mobile_c,
            r_o_ohm: f.per_cycle[c].r_o_ohm,
            extra: f
                .cycle_specs
                .iter()
                .map(|s| (s.name, crate::fit::ext_value(&f.cycle_ext[c], s.name).unwrap_or(s.start)))
                .collect(),
            rmse_mv: 1000.0 * f.rmse_v[c],
            ext: f.cycle_ext[c],
        })
        .collect()
}

/// Freezes the fitted cause parameters, re-fits qMobile and Ro on each held-out cycle, and scores.
fn judge(
    cfg: &DiagnoseConfig,
    p: &Prepared<'_>,
    causes: &[Cause],
    train_fit: Fitted,
    base: Option<&ModelResult>,
    heldout_starts: Option<&[CycleStart]>,
) -> Result<ModelResult, DoctorError> {
    // A calibrator meeting a new cycle starts its per-cycle extension parameters where the last training
    // cycle left them (unless the given start already carries values for them); the re-fit also tries the
    // neutral values from its own qMobile scan.
    let warm: Option<Vec<CycleStart>> = heldout_starts.map(|starts| {
        let last = train_fit.cycle_ext.last().copied().unwrap_or(train_fit.ext);
        starts
            .iter()
            .map(|st| {
                let mut ext = st.ext;
                for s in &train_fit.cycle_specs {
                    if crate::fit::ext_value(&ext, s.name) == Some(s.start) {
                        ext.set(s.name, crate::fit::ext_value(&last, s.name).unwrap_or(s.start));
                    }
                }
                CycleStart { d: st.d, ext, rmse_v: st.rmse_v }
            })
            .collect()
    });
    let held = refit_cycles(&cfg.fit, &p.heldout, causes, &train_fit.ext, warm.as_deref())?;
    let heldout_residuals = residuals_of(&cfg.fit, &p.heldout, &held)?;
    let ds: Vec<&Discharge> = p.heldout.iter().map(|r| r.d).collect();
    let heldout_structure = structure(&ds, &heldout_residuals);
    let n_params = train_fit.shared.len();
    let cycle_params: Vec<&'static str> = held.cycle_specs.iter().map(|s| s.name).collect();
    let heldout_rmse_mv = 1000.0 * held.rmse_all_v();
    let gain_pct = base.map_or(0.0, |b| 100.0 * (b.heldout_rmse_mv - heldout_rmse_mv) / b.heldout_rmse_mv);
    let heldout_record_rmse_mv = pooled_rmse(&[heldout_structure.under_load, heldout_structure.rest_before]);
    let record_gain_pct =
        base.map_or(0.0, |b| 100.0 * (b.heldout_record_rmse_mv - heldout_record_rmse_mv) / b.heldout_record_rmse_mv);
    let removes = base.map(|b| evidence(&b.heldout_structure, &heldout_structure));
    Ok(ModelResult {
        causes: causes.iter().map(|c| c.name()).collect(),
        params: train_fit.shared.iter().copied().collect(),
        n_params,
        at_bounds: at_bounds(causes, &train_fit.shared),
        score_mv: score(cfg, heldout_rmse_mv, n_params, cycle_params.len(), &held),
        cycle_params,
        train_rmse_mv: 1000.0 * train_fit.rmse_all_v(),
        heldout_rmse_mv,
        gain_pct,
        heldout_record_rmse_mv,
        record_gain_pct,
        train_cycles: cycle_fits(&p.train, &train_fit),
        heldout_cycles: cycle_fits(&p.heldout, &held),
        heldout_structure,
        removes,
        ext: train_fit.ext,
        heldout_residuals,
    })
}

/// The shared parameters of `causes` whose fitted values (`shared`) lie within 0.1 % of their range from a
/// bound ([`Cause::params`]). B0055 (4 C) fits `ocv` with two coefficients at -0.3 V: the correction bends the
/// curve by 0.8 V below the fit window's 2.9 V floor, and a calibrator's model carrying it predicted that cell's
/// capacity nearly four times worse (docs/realcell.md, "the model").
pub fn at_bounds(causes: &[Cause], shared: &[(&'static str, f64)]) -> Vec<&'static str> {
    let specs: Vec<_> = causes.iter().flat_map(|c| c.params(false)).collect();
    shared
        .iter()
        .filter(|(name, v)| {
            specs.iter().find(|s| s.name == *name).is_some_and(|s| {
                let tol = 1e-3 * (s.hi - s.lo);
                *v <= s.lo + tol || *v >= s.hi - tol
            })
        })
        .map(|(name, _)| *name)
        .collect()
}

/// The RMSE over the samples of several parts, mV.
fn pooled_rmse(parts: &[crate::analysis::Part]) -> f64 {
    let (sse, n) =
        parts.iter().fold((0.0, 0usize), |(sse, n), p| (sse + p.rmse_mv * p.rmse_mv * p.samples as f64, n + p.samples));
    (sse / n.max(1) as f64).sqrt()
}

/// The ranking score, mV: the held-out RMSE with a complexity penalty. Each shared parameter costs
/// `penalty_per_param`; per-cycle parameters are re-calibrated on every held-out cycle, so they are counted
/// as the Bayesian information criterion counts free parameters: m per cycle over C held-out cycles and N
/// held-out samples multiply the RMSE by exp(m C ln(N) / (2 N)) (BIC = N ln(RSS/N) + k ln(N) on the RMSE
/// scale), but by no less than 1 + `min_cycle_penalty` m: with few held-out cycles the BIC charges less
/// than a per-cycle parameter buys by fitting what is not there. qMobile and Ro are per-cycle in every
/// model, base included, so they cancel and are not counted.
fn score(cfg: &DiagnoseConfig, rmse_mv: f64, n_shared: usize, n_cycle: usize, held: &Fitted) -> f64 {
    let n = held.samples.iter().sum::<usize>().max(2) as f64;
    let k = (n_cycle * held.per_cycle.len()) as f64;
    let per_cycle = (k * n.ln() / (2.0 * n)).exp().max(1.0 + cfg.min_cycle_penalty * n_cycle as f64);
    rmse_mv * (1.0 + cfg.penalty_per_param * n_shared as f64) * per_cycle
}

fn evidence(base: &Structure, cand: &Structure) -> Evidence {
    let (mut part, mut drop, mut b_rmse, mut c_rmse) = ("under_load", f64::NEG_INFINITY, 0.0, 0.0);
    for ((name, b), (_, c)) in base.parts().iter().zip(cand.parts().iter()) {
        if b.samples > 0 && b.rmse_mv - c.rmse_mv > drop {
            (part, drop, b_rmse, c_rmse) = (name, b.rmse_mv - c.rmse_mv, b.rmse_mv, c.rmse_mv);
        }
    }
    let corrs = [
        ("soc", base.corr_soc, cand.corr_soc),
        ("current", base.corr_current, cand.corr_current),
        ("time", base.corr_time, cand.corr_time),
        ("temperature", base.corr_temperature, cand.corr_temperature),
    ];
    let correlation = corrs
        .into_iter()
        .max_by(|a, b| (a.1.abs() - a.2.abs()).total_cmp(&(b.1.abs() - b.2.abs())))
        .expect("four correlations");
    Evidence { part, base_rmse_mv: b_rmse, rmse_mv: c_rmse, correlation }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A shared value within 0.1 % of its range from a bound is at it (B0055's OCV fit); one inside is not, and
    /// per-cycle parameters (electrode balance) are never shared.
    #[test]
    fn shared_parameters_fitted_to_a_bound_are_named() {
        let shared = [("ocv_p1_v", -0.3), ("ocv_p2_v", -0.2999999978), ("ocv_p3_v", -0.2187), ("t_diffusion_s", 3e6)];
        assert_eq!(at_bounds(&[Cause::Ocv, Cause::Diffusion], &shared), vec!["ocv_p1_v", "ocv_p2_v"]);
        assert_eq!(at_bounds(&[Cause::Ocv], &[("ocv_p1_v", -0.0887), ("ocv_p2_v", 0.0492)]), Vec::<&str>::new());
        assert_eq!(at_bounds(&[Cause::Diffusion], &[("t_diffusion_s", 1e9)]), vec!["t_diffusion_s"]);
        assert!(at_bounds(&[Cause::ElectrodeBalance], &[]).is_empty());
    }
}
