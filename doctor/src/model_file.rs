//! Reading back the model a diagnosis chose (`diagnosis.json`'s `extended` part): its causes and the
//! shared parameters fitted on the training cycles. `bcal calibrate --model` and `bcal cell-config
//! --model` run the calibrators on it; the per-cycle parameters are calibrated again on every cycle. A live
//! stream (`--follow`, the Python package) starts with the per-cycle parameters at the median of the last
//! training cycles' fits ([`DiagnosedModel::latest`]) and refits them on every discharge it follows to the
//! cut-off ([`DiagnosedModel::refit`]), as `bcal calibrate` refits every discharge that ends.
//! [`load_lifetime`] reads the capacity lifetime model (recovery after rest) a calibrator's prior can use.
//!
//! A calibrator's model carries only some of the doctor's causes
//! ([`bcal_common::measured::extension::SUPPORTED_CAUSES`]): a sensor offset or gain or an extra RC branch
//! change the measurement or add a state the filter and the policy would have to run. When a
//! diagnosis names such a cause, the model read back here is the diagnosis's carriable causes with their
//! fitted values, and [`DiagnosedModel::dropped`] names the rest, so every face (`bcal calibrate`, `bcal
//! cell-config`, `--follow`, the Python package) calibrates on what it can carry and says what it left out,
//! instead of refusing the cell.

use crate::fit::{refit_cycles, FitConfig, FitRecord};
use crate::lifetime::LifetimeModel;
use crate::record::Discharge;
use crate::sim::{Cause, ExtParams};
use crate::DoctorError;
use bcal_common::battery::Degradation;
use bcal_common::measured::extension::{ModelExtension, SUPPORTED_CAUSES};
use bcal_common::measured::scenario::Sample;
use bcal_common::measured::TrackerSpec;
use bcal_common::text::shown;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The extended model of a diagnosis.
#[derive(Clone, Debug, PartialEq)]
pub struct DiagnosedModel {
    /// The cell the diagnosis was made on.
    pub cell: String,
    /// Where it was read from.
    pub path: PathBuf,
    /// The causes of the extended model a calibrator's model carries, in the doctor's order (empty: the base
    /// model won, or none of its causes can be carried).
    pub causes: Vec<Cause>,
    /// The causes the diagnosis named that a calibrator's model cannot carry: left out, their values neutral.
    pub dropped: Vec<Cause>,
    /// Those of them a calibrator's model could carry but whose fit sits at a bound of its range
    /// ([`crate::diagnose::at_bounds`]), with their fitted values as said.
    pub at_bounds: Vec<(Cause, String)>,
    /// The shared parameters (per-cycle ones at their neutral values), with what the causes switch on.
    pub shared: ExtParams,
    /// The shared parameters with the per-cycle ones at the median of the last [`LATEST_CYCLES`] training
    /// cycles' fits (as `shared` when the diagnosis holds no per-cycle fit).
    pub latest: ExtParams,
    /// The training cycles `latest` took its per-cycle values from.
    pub latest_cycles: Vec<u32>,
    /// The cycles the diagnosis fitted or judged (its model has seen them).
    pub cycles: Vec<u32>,
    /// The cut-off the diagnosis was made at, where it was given or documented (None: the doctor's default,
    /// no fact of the cell).
    pub cutoff_v: Option<f64>,
}

/// How many of the last training cycles give a live stream its per-cycle values (their median: one odd
/// fit does not set the model).
pub const LATEST_CYCLES: usize = 5;

impl DiagnosedModel {
    /// The model as a live stream runs it: the causes with their shared values and the per-cycle ones at
    /// the last training cycles' ([`Self::latest`]), its Arrhenius reference `reference_k` (None: the first
    /// reading's temperature). Neutral per-cycle values would make a model whose causes are all per cycle
    /// (B0005's electrode balance and charge transfer) the base model under another name.
    pub fn extension(&self, reference_k: Option<f64>) -> ModelExtension {
        extension_of(&self.causes, &self.latest, reference_k)
    }

    /// The model refitted on one discharge a live stream has followed to its cut-off, as `bcal calibrate`
    /// fits every discharge that ends ([`fit_discharge`] under the diagnosis's causes and shared values).
    pub fn refit(
        &self,
        samples: &[Sample],
        cutoff_v: f64,
        reference_k: Option<f64>,
    ) -> Option<(Degradation, ModelExtension)> {
        fit_discharge(&self.cell, &self.causes, &self.shared, samples, cutoff_v, reference_k)
    }

    /// The cut-off a live stream without a cell config or a cut-off of its own predicts at: the diagnosis's,
    /// where it was the cell's (given or documented), set in `tracker`. The sentence to say, if it was set.
    /// (The prior stays the tracker's: starting it at the last training cycles' fits instead was measured on
    /// B0005 / B0006 / B0018 as streams, docs/follow.md, and gained nothing.)
    pub fn settle_stream(&self, tracker: &mut TrackerSpec) -> Option<String> {
        let v = self.cutoff_v?;
        tracker.cutoff_v = v;
        Some(format!("cut-off {v} V, the diagnosis's (give --cutoff-v for another)"))
    }

    /// What the calibrators run instead of the diagnosis's model, when they cannot carry all of it: one
    /// sentence for the user (None: the diagnosis's model as it is).
    pub fn carrying_note(&self) -> Option<String> {
        if self.dropped.is_empty() {
            return None;
        }
        let names = |cs: &[Cause]| cs.iter().map(|c| c.name()).collect::<Vec<_>>().join(" + ");
        let uncarriable: Vec<Cause> =
            self.dropped.iter().copied().filter(|c| self.at_bounds.iter().all(|(b, _)| b != c)).collect();
        let mut why = Vec::new();
        if !uncarriable.is_empty() {
            why.push(format!(
                "{}, which a calibrator's model cannot carry (it carries: {})",
                names(&uncarriable),
                SUPPORTED_CAUSES.join(", ")
            ));
        }
        for (c, values) in &self.at_bounds {
            why.push(format!(
                "{}, whose fit sits at the bound of its range ({values}): it stands in for an effect beyond what it \
                 can hold, and its curve outside the fit window would be an extrapolation",
                c.name()
            ));
        }
        Some(format!(
            "the diagnosis also named {}: calibrating on {} (its fitted values, the others left neutral)",
            why.join("; and "),
            if self.causes.is_empty() {
                "the base model".to_string()
            } else {
                format!("base + {}", names(&self.causes))
            }
        ))
    }
}

/// Whether a calibrator's model can carry `cause`.
pub fn carriable(cause: Cause) -> bool {
    SUPPORTED_CAUSES.contains(&cause.name())
}

/// The calibrators' model of `causes` with the values of `ext` (shared and per-cycle), its Arrhenius
/// reference `reference_k`: the one place that maps the doctor's parameters onto the model extension.
pub fn extension_of(causes: &[Cause], ext: &ExtParams, reference_k: Option<f64>) -> ModelExtension {
    ModelExtension {
        causes: causes.iter().map(|c| c.name().to_string()).collect(),
        xp_shift: ext.xp_shift,
        xn_shift: ext.xn_shift,
        kinetics_scale: ext.kinetics_scale,
        ro_activation_k: ext.ro_activation_k,
        kinetics_activation_k: ext.kinetics_activation_k,
        t_diffusion_s: ext.t_diffusion_s,
        ocv_legendre_v: ext.ocv_legendre_v,
        reference_k,
    }
}

#[derive(Deserialize)]
struct File {
    cell: String,
    extended: Extended,
    #[serde(default)]
    records: Vec<Record>,
    #[serde(default)]
    settings: Option<Settings>,
}

/// What a diagnosis was made with: the cut-off, and whether it was the cell's (given or documented).
#[derive(Deserialize)]
struct Settings {
    cutoff_v: Option<f64>,
    #[serde(default)]
    cutoff_given: bool,
}

#[derive(Deserialize)]
struct Record {
    cycle: u32,
    role: String,
}

#[derive(Deserialize)]
struct Extended {
    causes: Vec<String>,
    params: BTreeMap<String, f64>,
    #[serde(default)]
    train_cycles: Vec<TrainCycle>,
}

/// One training cycle's fit: its per-cycle parameters.
#[derive(Deserialize)]
struct TrainCycle {
    cycle: u32,
    #[serde(default)]
    extra: BTreeMap<String, f64>,
}

/// The fit of one discharge a live stream has followed to its cut-off, as `bcal calibrate` fits every
/// discharge that ends ([`crate::fit::refit_cycles`], the shared values frozen): qMobile, Ro and the model's
/// per-cycle values (none for the base model, `causes` empty) on its readings from the first (the rest
/// before the load included) to the first loaded one at or below `cutoff_v`, the model's Arrhenius
/// reference `reference_k`. Returns the fit and the model it was made under; None when the readings hold no
/// load window or the fit fails.
pub fn fit_discharge(
    cell: &str,
    causes: &[Cause],
    shared: &ExtParams,
    samples: &[Sample],
    cutoff_v: f64,
    reference_k: Option<f64>,
) -> Option<(Degradation, ModelExtension)> {
    let t0 = samples.first()?.t_s;
    let temps: Vec<f64> = samples.iter().map(|x| x.temperature_k).collect();
    let d = Discharge {
        cell: cell.to_string(),
        cycle: 0,
        source: PathBuf::from("(stream)"),
        ambient_k: temps[0],
        time_s: samples.iter().map(|x| x.t_s - t0).collect(),
        voltage_v: samples.iter().map(|x| x.voltage_v).collect(),
        current_a: samples.iter().map(|x| x.current_a).collect(),
        temperature_k: Some(temps),
        stated_capacity_ah: None,
    };
    let cfg = FitConfig::default();
    let w = d.windows_with_cutoff(cfg.load_threshold_a, cfg.v_floor_v, Some(cutoff_v))?;
    let rec = FitRecord::new(&d, w, &cfg);
    let f = refit_cycles(&cfg, &[rec], causes, shared, None).ok()?;
    let (q, ext) = (f.per_cycle.first()?, f.cycle_ext.first()?);
    (q.q_mobile_c.is_finite() && q.r_o_ohm.is_finite()).then(|| (*q, extension_of(causes, ext, reference_k)))
}

/// What a live stream fits on each discharge it follows to its cut-off (`bcal_calib::stream::Refit`): on
/// the diagnosis's model, its per-cycle values refitted with qMobile and Ro, the next discharge running the
/// refitted model; on the base model (`model` None), qMobile and Ro, the model staying `base`. The fit is
/// the previous discharge's fit the stream blends with, and its Ro the end fit's.
pub fn stream_refit(
    model: Option<DiagnosedModel>,
    base: ModelExtension,
    cutoff_v: f64,
    reference_k: Option<f64>,
) -> impl FnMut(&[Sample]) -> Option<(Degradation, ModelExtension)> + Send {
    move |samples| match &model {
        Some(m) => m.refit(samples, cutoff_v, reference_k),
        None => fit_discharge("(stream)", &[], &ExtParams::default(), samples, cutoff_v, reference_k)
            .map(|(d, _)| (d, base.clone())),
    }
}

/// Reads `path` (a `diagnosis.json` written by `bcal diagnose`, or the folder holding one).
pub fn load_model(path: &Path) -> Result<DiagnosedModel, DoctorError> {
    let file = if path.is_dir() { path.join("diagnosis.json") } else { path.to_path_buf() };
    let text = std::fs::read_to_string(&file).map_err(|source| DoctorError::Io { path: file.clone(), source })?;
    let bad = |why: String| DoctorError::BadModelFile { path: file.clone(), why };
    let f: File =
        serde_json::from_str(&text).map_err(|e| bad(format!("not a diagnosis written by bcal diagnose ({e})")))?;
    let mut causes = Vec::new();
    let mut shared = ExtParams::default();
    for name in &f.extended.causes {
        let c = Cause::ALL
            .into_iter()
            .find(|c| c.name() == name)
            .ok_or_else(|| bad(format!("unknown cause `{}`", shown(name, 40))))?;
        shared.enable(c);
        causes.push(c);
    }
    for (name, value) in &f.extended.params {
        // With or without a measured temperature, `thermal` has its own parameter set: accept either.
        let known =
            causes.iter().flat_map(|c| c.params(true).into_iter().chain(c.params(false))).any(|s| s.name == name);
        if !known {
            return Err(bad(format!(
                "parameter `{}` belongs to none of the causes {:?}",
                shown(name, 40),
                f.extended.causes
            )));
        }
        if !value.is_finite() {
            return Err(bad(format!("parameter `{name}` = {value} is not a finite number")));
        }
        shared.set(name, *value);
    }
    let cycles = f.records.iter().filter(|r| r.role == "train" || r.role == "heldout").map(|r| r.cycle).collect();
    // A cause whose fit sits at a bound of its range stands in for something it cannot hold: its curve beyond
    // the fit window is an extrapolation the calibrators would run on every discharge, so it is left out too.
    let shared_fit: Vec<(&'static str, f64)> = causes
        .iter()
        .flat_map(|c| c.params(false))
        .filter_map(|s| f.extended.params.get(s.name).map(|v| (s.name, *v)))
        .collect();
    let bounded = crate::diagnose::at_bounds(&causes, &shared_fit);
    let at_bounds: Vec<Cause> =
        causes.iter().copied().filter(|c| c.params(false).iter().any(|s| bounded.contains(&s.name))).collect();
    // The causes a calibrator cannot carry leave the model, their values neutral: the rest keep theirs.
    let (causes, dropped): (Vec<Cause>, Vec<Cause>) =
        causes.into_iter().partition(|c| carriable(*c) && !at_bounds.contains(c));
    for c in &dropped {
        shared.disable(*c);
    }
    // The per-cycle parameters of the carried causes: each at its median over the last training cycles.
    let mut fitted: Vec<&TrainCycle> = f.extended.train_cycles.iter().filter(|t| !t.extra.is_empty()).collect();
    fitted.sort_by_key(|t| t.cycle);
    let last = &fitted[fitted.len().saturating_sub(LATEST_CYCLES)..];
    let mut latest = shared;
    let per_cycle: std::collections::BTreeSet<&String> = last.iter().flat_map(|t| t.extra.keys()).collect();
    for name in per_cycle {
        let carried = causes.iter().flat_map(|c| c.cycle_params()).any(|s| s.name == name);
        let mut values: Vec<f64> = last.iter().filter_map(|t| t.extra.get(name).copied()).collect();
        if values.iter().any(|v| !v.is_finite()) {
            return Err(bad(format!("training cycle parameter `{}` is not a finite number", shown(name, 40))));
        }
        if let (true, Some(m)) = (carried, bcal_common::stats::median(&mut values)) {
            latest.set(name, m);
        }
    }
    // The model a live stream runs must be one the calibrators can run (values edited by hand, or from a fit
    // that ran off: refused here, named, rather than met mid-stream).
    extension_of(&causes, &latest, None)
        .check("the last training cycles' model")
        .map_err(|e| bad(format!("{e}; the diagnosis's values make no model the calibrators run: diagnose again")))?;
    let latest_cycles = last.iter().map(|t| t.cycle).collect();
    let cutoff_v = f
        .settings
        .filter(|s| s.cutoff_given)
        .and_then(|s| s.cutoff_v)
        .filter(|v| bcal_common::measured::CUTOFF_RANGE_V.contains(v));
    let at_bounds = at_bounds.into_iter().map(|c| (c, bounded_text(c, &shared_fit))).collect();
    Ok(DiagnosedModel {
        cell: f.cell,
        path: file,
        causes,
        dropped,
        at_bounds,
        shared,
        latest,
        latest_cycles,
        cycles,
        cutoff_v,
    })
}

/// `cause`'s fitted shared values, as the note on a cause left out at its bounds gives them.
fn bounded_text(cause: Cause, shared_fit: &[(&'static str, f64)]) -> String {
    let names: Vec<&str> = cause.params(false).iter().map(|s| s.name).collect();
    shared_fit
        .iter()
        .filter(|(n, _)| names.contains(n))
        .map(|(n, v)| format!("{n} = {v:.3}"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The capacity lifetime model of a diagnosis (`diagnosis.json`'s `lifetime`, see [`crate::lifetime`]), for a
/// calibrator's prior across discharges ([`crate::lifetime::LifeTracker`]): the model with recovery when the
/// diagnosis named recovery after rest, else the trend alone. `Ok(None)` when the diagnosis has no lifetime
/// section or its capacity series was not fitted.
pub fn load_lifetime(path: &Path) -> Result<Option<LifetimeModel>, DoctorError> {
    let file = if path.is_dir() { path.join("diagnosis.json") } else { path.to_path_buf() };
    let text = std::fs::read_to_string(&file).map_err(|source| DoctorError::Io { path: file.clone(), source })?;
    let bad = |why: String| DoctorError::BadModelFile { path: file.clone(), why };
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| bad(format!("not a diagnosis written by bcal diagnose ({e})")))?;
    let Some(life) = v.get("lifetime").filter(|l| !l.is_null()) else { return Ok(None) };
    let Some(capacity) = life.get("capacity").filter(|c| !c.is_null()) else { return Ok(None) };
    let recovery = life.get("recovery").and_then(serde_json::Value::as_bool).unwrap_or(false);
    let key = if recovery { "with_recovery" } else { "without_recovery" };
    let model = capacity.get(key).ok_or_else(|| bad(format!("`lifetime.capacity.{key}` is missing")))?;
    let m: LifetimeModel = serde_json::from_value(model.clone())
        .map_err(|e| bad(format!("`lifetime.capacity.{key}` is not a lifetime model ({e})")))?;
    if let Some(why) = m.unusable() {
        return Err(bad(format!("`lifetime.capacity.{key}` cannot move a prior: {why}: {m:?}")));
    }
    Ok(Some(m))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_diagnosis_reads_back_its_lifetime_model() {
        use crate::lifetime::{Condition, Quantity};
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("diagnosis.json");
        let m = LifetimeModel {
            quantity: Quantity::CapacityAh,
            intercept: 1.8,
            per_cycle: -0.003,
            reference_cycle: 20.5,
            per_kelvin: 0.0,
            per_ampere: 0.0,
            reference: Condition { ambient_c: 24.0, current_a: 2.0 },
            amplitude: 0.065,
            tau_rest_s: 54_720.0,
            decay_discharges: 5.0,
            usual_rest_s: 17_000.0,
            residual_sd: 0.004,
            jump_sd_fraction: 0.5,
        };
        let trend = LifetimeModel { amplitude: 0.0, tau_rest_s: 0.0, decay_discharges: 0.0, ..m };
        let file = |recovery: bool| {
            serde_json::json!({"cell": "B0005", "lifetime": {"recovery": recovery,
                "capacity": {"with_recovery": m, "without_recovery": trend}}})
            .to_string()
        };
        std::fs::write(&p, file(true)).unwrap();
        assert_eq!(load_lifetime(dir.path()).unwrap(), Some(m));
        std::fs::write(&p, file(false)).unwrap();
        assert_eq!(load_lifetime(&p).unwrap(), Some(trend));
        std::fs::write(&p, r#"{"cell":"B0005","lifetime":null}"#).unwrap();
        assert_eq!(load_lifetime(&p).unwrap(), None);
        std::fs::write(&p, r#"{"lifetime":{"recovery":true,"capacity":{"with_recovery":{"quantity":"capacity_ah"}}}}"#)
            .unwrap();
        let e = load_lifetime(&p).unwrap_err().to_string();
        assert!(e.contains("lifetime.capacity.with_recovery") && e.contains("diagnosis.json"), "{e}");
    }

    #[test]
    fn a_diagnosis_reads_back_its_causes_and_shared_values_and_bad_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("diagnosis.json");
        std::fs::write(
            &p,
            r#"{"cell":"B0005","extended":{"causes":["electrode_balance","charge_transfer","thermal"],
                "params":{"kinetics_activation_k":512.75,"ro_activation_k":4015.08},"cycle_params":["xp_shift"]},
                "records":[{"cycle":1,"role":"train"},{"cycle":2,"role":"heldout"},{"cycle":3,"role":"excluded"}]}"#,
        )
        .unwrap();
        let m = load_model(dir.path()).unwrap();
        assert_eq!(m.causes, vec![Cause::ElectrodeBalance, Cause::ChargeTransfer, Cause::Thermal]);
        assert!(m.shared.temperature_driven && m.shared.ro_activation_k == 4015.08);
        assert_eq!((m.shared.xp_shift, m.shared.kinetics_scale), (0.0, 1.0));
        assert_eq!((m.latest, m.latest_cycles.len()), (m.shared, 0), "no per-cycle fit: the shared values");
        assert_eq!(m.cycles, vec![1, 2]);
        assert!(m.dropped.is_empty() && m.carrying_note().is_none());
        // A diagnosis naming causes a calibrator cannot carry: those leave the model, the rest keep their values.
        std::fs::write(
            &p,
            r#"{"cell":"B0005","extended":{"causes":["ocv","diffusion","voltage_offset"],
                "params":{"ocv_p1_v":0.02,"t_diffusion_s":3e6,"voltage_offset_v":-0.02}}}"#,
        )
        .unwrap();
        let m = load_model(&p).unwrap();
        assert_eq!(
            (m.causes.clone(), m.dropped.clone()),
            (vec![Cause::Ocv, Cause::Diffusion], vec![Cause::VoltageOffset])
        );
        assert_eq!(
            (m.shared.t_diffusion_s, m.shared.ocv_legendre_v, m.shared.voltage_offset_v),
            (3e6, [0.02, 0.0, 0.0], 0.0)
        );
        let note = m.carrying_note().unwrap();
        assert!(note.contains("also named voltage_offset, which") && note.contains("base + ocv + diffusion"), "{note}");
        // The OCV correction reaches the calibrators' model with its fitted value.
        let ext = m.extension(None);
        assert!(ext.check("m").is_ok() && ext.has("ocv") && ext.params().ocv_legendre_v == [0.02, 0.0, 0.0]);
        // An OCV correction fitted to the bounds of its range (B0055's, at 4 C: -0.3, -0.3, -0.219 V) stands in for
        // something else: left out, and said with its values.
        std::fs::write(
            &p,
            r#"{"cell":"B0055","extended":{"causes":["ocv","charge_transfer"],
                "params":{"ocv_p1_v":-0.3,"ocv_p2_v":-0.29999999777833997,"ocv_p3_v":-0.21868}}}"#,
        )
        .unwrap();
        let m = load_model(&p).unwrap();
        assert_eq!((m.causes.clone(), m.dropped.clone()), (vec![Cause::ChargeTransfer], vec![Cause::Ocv]));
        assert_eq!(m.shared.ocv_legendre_v, [0.0; 3]);
        let note = m.carrying_note().unwrap();
        assert!(
            note.contains("also named ocv, whose fit sits at the bound") && note.contains("ocv_p1_v = -0.300"),
            "{note}"
        );
        assert!(!note.contains("cannot carry") && note.contains("base + charge_transfer"), "{note}");
        // Per-cycle parameters: a stream runs the median of the last five training cycles' fits (cycle 1's
        // outlier is not among them; a dropped cause's values stay neutral).
        let cycle = |c: u32, xp: f64| {
            serde_json::json!({"cycle": c, "q_mobile_c": 6500.0, "r_o_ohm": 0.07,
                "extra": {"xp_shift": xp, "kinetics_scale": 0.3 + 0.01 * f64::from(c), "voltage_offset_v": 0.01}})
        };
        let cycles: Vec<_> = [(1, 0.25), (2, 0.02), (3, 0.04), (4, 0.03), (5, 0.05), (6, 0.01)]
            .into_iter()
            .map(|(c, x)| cycle(c, x))
            .collect();
        let file = serde_json::json!({"cell": "B0005", "extended": {"causes": ["electrode_balance", "charge_transfer",
            "voltage_offset"], "params": {}, "train_cycles": cycles}});
        std::fs::write(&p, file.to_string()).unwrap();
        let m = load_model(&p).unwrap();
        assert_eq!(m.latest_cycles, vec![2, 3, 4, 5, 6]);
        assert_eq!(
            (m.latest.xp_shift, m.latest.kinetics_scale, m.latest.voltage_offset_v),
            (0.03, 0.3 + 0.01 * 4.0, 0.0)
        );
        assert_eq!((m.shared.xp_shift, m.shared.kinetics_scale), (0.0, 1.0), "calibrate's per-cycle start is neutral");
        let ext = m.extension(None);
        assert_eq!((ext.xp_shift, ext.kinetics_scale), (0.03, 0.3 + 0.01 * 4.0));
        // Values that make no model (an electrode shift past the electrode's range, edited by hand): refused when
        // loaded, named, not met by a live stream's filter mid-run.
        let cycles: Vec<_> = (1..=5).map(|c| cycle(c, 0.6)).collect();
        let file = serde_json::json!({"cell": "B0005", "extended": {"causes": ["electrode_balance"], "params": {},
            "train_cycles": cycles}});
        std::fs::write(&p, file.to_string()).unwrap();
        let e = load_model(&p).unwrap_err().to_string();
        assert!(e.contains("xp_max") && e.contains("diagnose again"), "{e}");
        std::fs::write(&p, r#"{"cell":"B0005","extended":{"causes":["gremlins"],"params":{}}}"#).unwrap();
        let e = load_model(&p).unwrap_err().to_string();
        assert!(e.contains("gremlins") && e.contains("diagnosis.json"), "{e}");
        std::fs::write(&p, "not json").unwrap();
        assert!(load_model(&p).unwrap_err().to_string().contains("bcal diagnose"));
        assert!(load_model(&dir.path().join("missing.json")).is_err());
    }

    /// A stream's refit recovers a discharge's per-cycle value (the charge-transfer scale, 0.3 where the
    /// diagnosis's latest value is neutral) with its qMobile and Ro, on the readings as a stream holds them;
    /// the base model fits qMobile and Ro alone. (The record comes from the doctor's own model:
    /// this checks that the stream's readings reach the fit, not the fit itself, which `fit`'s tests check.)
    #[test]
    fn a_stream_refits_the_per_cycle_values_on_a_discharge_it_followed() {
        use bcal_common::measured::scenario::{Request, Sample};
        let d = crate::fit::tests::synthetic(6000.0, 0.12, &ExtParams { kinetics_scale: 0.3, ..Default::default() });
        let samples: Vec<Sample> = (0..d.len())
            .map(|k| Sample {
                t_s: 1.0e6 + d.time_s[k],
                voltage_v: d.voltage_v[k],
                current_a: d.current_a[k],
                temperature_k: 297.15,
                request: Request::Unknown,
            })
            .collect();
        let m = DiagnosedModel {
            cell: "S".into(),
            path: "diagnosis.json".into(),
            causes: vec![Cause::ChargeTransfer],
            dropped: vec![],
            at_bounds: vec![],
            shared: ExtParams::default(),
            latest: ExtParams::default(),
            latest_cycles: vec![],
            cycles: vec![],
            cutoff_v: None,
        };
        let (q, ext) = m.refit(&samples, 2.5, Some(297.15)).expect("a load window to fit");
        assert!((ext.kinetics_scale / 0.3 - 1.0).abs() < 0.2, "kinetics {}", ext.kinetics_scale);
        assert!((q.q_mobile_c / 6000.0 - 1.0).abs() < 0.02 && (q.r_o_ohm / 0.12 - 1.0).abs() < 0.1, "{q:?}");
        assert_eq!(ext.causes, vec!["charge_transfer".to_string()]);
        let mut base = stream_refit(None, ModelExtension::default(), 2.5, Some(297.15));
        let (q, ext) = base(&samples).expect("a load window to fit");
        assert_eq!(ext, ModelExtension::default(), "the base model stays as it is");
        assert!(q.q_mobile_c.is_finite() && q.r_o_ohm > 0.0, "{q:?}");
    }

    /// A live stream without a cell config predicts at the diagnosis's cut-off where the diagnosis had the
    /// cell's own, not the doctor's default.
    #[test]
    fn a_stream_without_a_config_takes_the_diagnosis_cut_off() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("diagnosis.json");
        let write = |settings: serde_json::Value| {
            let file = serde_json::json!({"cell": "B0005", "settings": settings,
                "extended": {"causes": [], "params": {}}});
            std::fs::write(&p, file.to_string()).unwrap();
            load_model(&p).unwrap()
        };
        let m = write(serde_json::json!({"cutoff_v": 2.7, "cutoff_given": true}));
        let mut t = TrackerSpec::default();
        let said = m.settle_stream(&mut t).expect("a cut-off taken");
        assert!(t.cutoff_v == 2.7 && said.contains("2.7 V"), "{said}");
        assert_eq!(t.prior, TrackerSpec::default().prior, "the prior stays the tracker's");
        // The doctor's default, or a value no cell ends at, is no fact of the cell.
        for settings in [
            serde_json::json!({"cutoff_v": 2.5, "cutoff_given": false}),
            serde_json::json!({"cutoff_v": 42.0, "cutoff_given": true}),
            serde_json::json!({}),
        ] {
            let mut t = TrackerSpec::default();
            assert!(write(settings).settle_stream(&mut t).is_none());
            assert_eq!(t.cutoff_v, TrackerSpec::default().cutoff_v);
        }
    }
}
