//! `bcal.Calibrator`: one calibrator fed one reading at a time through the stream `bcal calibrate
//! --follow` runs (`bcal_calib::stream`: the same setup, the same calibrator built by the same function),
//! so a reading gives the same estimate here as there. Every use of calibrator types in the Python package
//! sits in this module.

use crate::convert::{dict, from_serde};
use crate::errors::{doctor_error, value_error};
use bcal_calib::stream::{resolve, CalibratorKind, Estimate, Reading, Stream, StreamError};
use bcal_common::battery::Load;
use bcal_common::config::{Preset, TrainConfig};
use bcal_common::math::idx;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::policy::{PolicyFile, PolicyNet};
use bcal_doctor::read::{reading_columns, NamedColumn};
use pyo3::exceptions::PyOSError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

type StreamOf<'a> = Stream<'a>;

self_cell::self_cell!(
    /// The RL policy's network (None for other kinds) and the stream whose calibrator borrows it.
    struct Owned {
        owner: Option<PolicyNet>,
        #[not_covariant]
        dependent: StreamOf,
    }
);

/// A calibrator of the NASA Li-ion model fed one reading at a time, with no look-ahead: the estimate of
/// qMobile (C) and Ro (ohm) with their 90 % intervals, and the end of discharge predicted from the
/// calibrated state. The same code as `bcal calibrate --follow`: the same readings give the same estimates.
///
/// `kind`: "ukf" (joint unscented Kalman filter), "adaptive_ukf", "ukf_learned" (the joint UKF with its end
/// of discharge moved by the learner on the stream's own record), "rl" (an RL policy: `policy` is its
/// .bcalpol file), "fit" (the window fit, no learning) or "uncalibrated" (the prior, never moved).
/// `model`: the doctor's extended model (diagnosis.json of `bcal diagnose`, or its folder; its per-cycle
/// parameters start at the median of the last five training cycles' fits and are refitted on every discharge
/// followed to the cut-off). `config`: a bcal config TOML (`bcal cell-config` writes one per cell) whose
/// `measured.tracker` sets ranges, prior and cut-off. `ambient_c`: the temperature of readings that give none
/// before any other did within half an hour, deg C (default the model's 18.95 C). `cutoff_v`: the cut-off of
/// the EOD predictions, V (default the config's, else the diagnosis's where it was the cell's own, else 3.0).
/// The joint UKF's settings are the config's or the RL run's (tuned on validation by `bcal train`), else the
/// defaults; an RL policy runs as it was trained (on the window fit or as a correction of the joint UKF).
/// Raises ValueError (bad kind or files) and FileNotFoundError / OSError (unreadable files).
#[pyclass(module = "bcal")]
pub struct Calibrator {
    kind: CalibratorKind,
    stream: Mutex<Owned>,
}

fn load_policy(path: &Path) -> PyResult<PolicyFile> {
    PolicyFile::load(path).map_err(|e| {
        let msg = format!("the RL policy {}: {e}", path.display());
        if path.exists() {
            value_error(msg)
        } else {
            pyo3::exceptions::PyFileNotFoundError::new_err(msg)
        }
    })
}

fn load_config(path: &Path) -> PyResult<MeasuredSpec> {
    let c = TrainConfig::from_file_over(path, Preset::Measured).map_err(|e| match e {
        bcal_common::config::ConfigError::Read { .. } => PyOSError::new_err(e.to_string()),
        e => value_error(e),
    })?;
    c.validate().map_err(|e| value_error(format!("config {}: {e}", path.display())))?;
    Ok(c.measured)
}

/// The estimate as the dict `step` returns (None where the calibrator cannot tell yet).
fn estimate_dict<'py>(py: Python<'py>, e: &Estimate) -> PyResult<Bound<'py, PyDict>> {
    let d = dict(py);
    d.set_item("time_s", e.time_s)?;
    d.set_item("q_mobile", e.q_mobile)?;
    d.set_item("q_mobile_lo", e.q_mobile_lo)?;
    d.set_item("q_mobile_hi", e.q_mobile_hi)?;
    d.set_item("r_o", e.r_o)?;
    d.set_item("r_o_lo", e.r_o_lo)?;
    d.set_item("r_o_hi", e.r_o_hi)?;
    d.set_item("eod_s", e.eod_s)?;
    d.set_item("eod_current_a", e.eod_current_a)?;
    d.set_item("eod_power_w", e.eod_power_w)?;
    d.set_item("eod_lo_s", e.eod_lo_s)?;
    d.set_item("eod_hi_s", e.eod_hi_s)?;
    d.set_item("delivered_ah", e.delivered_ah)?;
    d.set_item("delivered_lo_ah", e.delivered_lo_ah)?;
    d.set_item("delivered_hi_ah", e.delivered_hi_ah)?;
    d.set_item("eod_from_prior", e.eod_from_prior)?;
    d.set_item("eod_recentred", e.eod_recentred)?;
    d.set_item("eod_on_voltage_change", e.eod_on_voltage_change)?;
    d.set_item("eod_prior_weight", e.eod_prior_weight)?;
    d.set_item("eod_previous_weight", e.eod_previous_weight)?;
    d.set_item("eod_learned_weight", e.eod_learned_weight)?;
    d.set_item("discharge", e.discharge)?;
    Ok(d)
}

/// The columns `run` returns, in order.
const RUN_COLUMNS: [&str; 23] = [
    "time_s",
    "q_mobile",
    "q_mobile_lo",
    "q_mobile_hi",
    "r_o",
    "r_o_lo",
    "r_o_hi",
    "eod_s",
    "eod_current_a",
    "eod_power_w",
    "eod_lo_s",
    "eod_hi_s",
    "delivered_ah",
    "delivered_lo_ah",
    "delivered_hi_ah",
    "eod_from_prior",
    "eod_recentred",
    "eod_on_voltage_change",
    "eod_prior_weight",
    "eod_previous_weight",
    "eod_learned_weight",
    "discharge",
    "row",
];

impl Calibrator {
    fn with_stream<T>(&self, f: impl FnOnce(&mut Stream<'_>) -> T) -> T {
        let mut s = self.stream.lock().unwrap_or_else(|e| e.into_inner());
        s.with_dependent_mut(|_, stream| f(stream))
    }
}

#[pymethods]
impl Calibrator {
    #[new]
    #[pyo3(signature = (kind, policy=None, model=None, config=None, ambient_c=None, cutoff_v=None))]
    fn new(
        kind: &str,
        policy: Option<PathBuf>,
        model: Option<PathBuf>,
        config: Option<PathBuf>,
        ambient_c: Option<f64>,
        cutoff_v: Option<f64>,
    ) -> PyResult<Self> {
        let kind: CalibratorKind = kind.parse().map_err(value_error)?;
        if let Some(c) = ambient_c.filter(|c| !c.is_finite()) {
            return Err(value_error(format!("ambient_c = {c} is not a finite number")));
        }
        if policy.is_some() && kind != CalibratorKind::Rl {
            return Err(value_error(StreamError::PolicyWithoutRl(kind.name())));
        }
        let policy_file = policy.as_deref().map(load_policy).transpose()?;
        let config_spec = config.as_deref().map(load_config).transpose()?;
        let reference_k = ambient_c.map(|c| c + bcal_common::measured::scenario::KELVIN_0C);
        let diagnosed = model.as_deref().map(bcal_doctor::model_file::load_model).transpose().map_err(doctor_error)?;
        let ext = diagnosed.as_ref().map(|m| m.extension(reference_k));
        let policy_name = policy.as_ref().map(|p| p.display().to_string()).unwrap_or_default();
        let mut setup = resolve(
            kind,
            config_spec.as_ref(),
            policy_file.as_ref().map(|p| (&p.task, policy_name.as_str())),
            ext.as_ref(),
        )
        .map_err(value_error)?;
        if let Some(v) = cutoff_v {
            setup.spec.tracker.cutoff_v =
                bcal_common::simulate::positive(v).map_err(|why| value_error(format!("cutoff_v: {why}")))?;
        }
        // Without the cell's config or a cut-off given, the diagnosis's cut-off where it was the cell's own.
        if let (None, None, Some(m)) = (&config_spec, cutoff_v, &diagnosed) {
            m.settle_stream(&mut setup.spec.tracker);
        }
        // A diagnosis's capacity lifetime model moves the carried value when the cell's config gave none.
        if let (None, Some(p)) = (&setup.spec.lifetime, &model) {
            setup.spec.lifetime = bcal_doctor::model_file::load_lifetime(p).map_err(doctor_error)?;
        }
        let net = policy_file.as_ref().map(|p| p.net()).transpose().map_err(value_error)?;
        // Every discharge followed to its cut-off fitted (the diagnosis's per-cycle values with qMobile and
        // Ro, or on the base model those two), as `bcal calibrate --follow` does.
        let (cut, reference) = (setup.spec.tracker.cutoff_v, setup.spec.tracker.model.reference_k);
        let base = setup.spec.tracker.model.clone();
        let owned = Owned::try_new(net, |net| {
            let stream = Stream::of(&setup, net.as_ref(), ambient_c)?;
            let refit = bcal_doctor::model_file::stream_refit(diagnosed, base, cut, reference);
            Ok::<_, StreamError>(stream.with_refit(Box::new(refit)))
        })
        .map_err(value_error)?;
        Ok(Self { kind, stream: Mutex::new(owned) })
    }

    /// The calibrator's kind ("ukf", "adaptive_ukf", "ukf_learned", "rl", "fit", "uncalibrated").
    #[getter]
    fn kind(&self) -> &'static str {
        self.kind.name()
    }

    /// Readings taken so far (refused ones not counted).
    #[getter]
    fn readings(&self) -> u64 {
        self.with_stream(|s| s.readings())
    }

    /// The calibrator's setting (ranges, prior, cut-off, model) as a dict, as bcal's config writes it.
    #[getter]
    fn spec<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let spec = self.with_stream(|s| s.spec().clone());
        from_serde(py, &spec)
    }

    /// Takes the next reading (time order; current positive while discharging) and returns the estimate:
    /// a dict of `time_s`, `q_mobile` (C), `q_mobile_lo`, `q_mobile_hi` (its 90 % interval), `r_o` (ohm),
    /// `r_o_lo`, `r_o_hi`, `eod_s` (predicted end of discharge, absolute time, s, at `eod_current_a`: the
    /// mean discharge current so far; under a load held at constant power, at `eod_power_w`, the mean power
    /// so far, and `eod_current_a` is the mean current the model then draws to the end), `eod_lo_s`, `eod_hi_s` (its 90 % interval, learned from the
    /// stream's own discharges followed to the cut-off: from the ninth on), `delivered_ah` (the charge the
    /// discharge will have delivered at its end, Ah: drawn so far plus `eod_current_a` until `eod_s`; from a
    /// full cell, its capacity as a cycler measures it; once the cut-off is crossed, the charge measured to
    /// it), `delivered_lo_ah`, `delivered_hi_ah` (the same at the interval's ends), `eod_from_prior` (the prediction
    /// is the prior alone's, where it beat the calibrator's, recentred where that serves, on 8 of the last 10
    /// discharges), `eod_recentred` (the calibrator's own moved by its median error over the last 10, where
    /// that beat it on 8 of them), `eod_on_voltage_change` (the calibrator's own moved by the error its last
    /// 15 discharges expect at the voltage this one reads against the one before at the same time since the
    /// load came on, where that beat the recentring on 8 of the last 10), `eod_prior_weight` (the prior
    /// alone's weight in eod_s: 1 where it predicts alone, its weight in the blend of the two, learned by
    /// inverse mean squared error over the last 15 discharges, from the ninth on, times that blend's share
    /// against the previous discharge's fit, else 0),
    /// `eod_previous_weight` (the previous discharge's fit's weight in eod_s: that blend blended in turn
    /// with the fit carried over, by the same rule on the discharges after rests of up to a day; 0 after a
    /// longer rest or where the prior alone predicts), `eod_learned_weight` (kind `ukf_learned`: the weight of
    /// the end moved by the error the learner on the stream's record expects, from its last errors, the rest
    /// before, how warm the discharge runs and how far its current moved from the last one's; 0 for other
    /// kinds and until 19 discharges have been followed to the cut-off) and `discharge` (from 0: a new one
    /// after a charge or a gap of more than half an hour, started from what the last one told: the charge its
    /// end measured, else its final estimate).
    /// Intervals and prediction are None while the calibrator cannot tell.
    /// A reading that is not finite, not a cell's voltage, not later than the last or a current glitch (a step
    /// of 5 A or more the voltage does not follow) raises ValueError and leaves the calibrator as it was
    /// (except that a third in a row more than half an hour behind, a clock that went back and stays there, is
    /// taken on the readings' new clock, and a current level refused twice in a row as a glitch is taken at the
    /// third attempt).
    #[pyo3(signature = (time_s, voltage_v, current_a, temperature_c=None))]
    fn step<'py>(
        &self,
        py: Python<'py>,
        time_s: f64,
        voltage_v: f64,
        current_a: f64,
        temperature_c: Option<f64>,
    ) -> PyResult<Bound<'py, PyDict>> {
        // NaN is pandas' missing value: a reading without a temperature, as an empty CSV field is.
        let r = Reading { time_s, voltage_v, current_a, temperature_c: temperature_c.filter(|t| !t.is_nan()) };
        let e = self.with_stream(|s| s.step(&r)).map_err(value_error)?;
        estimate_dict(py, &e)
    }

    /// The end of discharge (absolute time, s) if the cell now draws `current_a` (A), or `power_w` (W: the
    /// current P / V rising as the voltage falls), until the cut-off, from the calibrated state; None before
    /// the first reading or beyond the 40 000 s horizon.
    #[pyo3(signature = (current_a=None, *, power_w=None))]
    fn predict_eod_s(&self, current_a: Option<f64>, power_w: Option<f64>) -> PyResult<Option<f64>> {
        let load = match (current_a, power_w) {
            (Some(a), None) => {
                bcal_common::simulate::positive(a).map_err(|why| value_error(format!("current_a: {why}")))?;
                Load::CurrentA(a)
            }
            (None, Some(w)) => {
                bcal_common::simulate::positive(w).map_err(|why| value_error(format!("power_w: {why}")))?;
                Load::PowerW(w)
            }
            _ => return Err(value_error("give the load as one of current_a (A) or power_w (W)")),
        };
        Ok(self.with_stream(|s| s.predict_eod_under_s(load)))
    }

    /// The discharges finished so far (each counts once it has handed its fit on, when the next begins) and
    /// those whose fit sat at an edge of the setting's ranges:
    /// a dict of `discharges`, `at_edge`, `q_mobile_floor`, `q_mobile_top`, `r_o_floor`, `r_o_top`. A cell
    /// outside the ranges (a cold cell of high resistance under the default ones) is followed at their edge
    /// and its predictions are far off: give it its own setting (`config=`, from `bcal cell-config`).
    #[getter]
    fn range_edges<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let e = self.with_stream(|s| s.range_edges());
        let d = dict(py);
        d.set_item("discharges", e.discharges)?;
        d.set_item("at_edge", e.at_edge)?;
        for (k, name) in ["q_mobile", "r_o"].into_iter().enumerate() {
            d.set_item(format!("{name}_floor"), e.by_edge[k][0])?;
            d.set_item(format!("{name}_top"), e.by_edge[k][1])?;
        }
        Ok(d)
    }

    /// The ranges the stream widened the setting's to after two discharges in a row handed on a fit at the same
    /// edge of one, as `[[q_mobile_lo_c, q_mobile_hi_c], [r_o_lo_ohm, r_o_hi_ohm]]`, or None while it has not.
    #[getter]
    fn widened_ranges(&self) -> Option<[[f64; 2]; 2]> {
        self.with_stream(|s| s.widened_ranges())
    }

    /// The calibrated model state now under progpy's state names (qpS, qpB, qnB, qnS in C; Vo, Vsn, Vsp in
    /// V; tb in K), or None before the first reading.
    fn state<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(x) = self.with_stream(|s| s.calibrator().state()) else { return Ok(None) };
        let d = dict(py);
        for (name, k) in [
            ("qpS", idx::QP_S),
            ("qpB", idx::QP_B),
            ("qnB", idx::QN_B),
            ("qnS", idx::QN_S),
            ("Vo", idx::V_O),
            ("Vsn", idx::V_SN),
            ("Vsp", idx::V_SP),
            ("tb", idx::T_B),
        ] {
            d.set_item(name, x[k])?;
        }
        Ok(Some(d))
    }

    /// Feeds every row of a pandas DataFrame with columns `time_s`, `voltage_v`, `current_a` (and optionally
    /// `temperature_c`; or the same quantities in other units named as the CSV readers read them: `time_ms`,
    /// `current_ma`, `Voltage / mV`, NASA's `Voltage_measured`) in order, and returns a DataFrame with one
    /// row per reading: the columns of `step` (NaN where `step` gives None) and `row`, the reading's position
    /// in `df`. A missing temperature (NaN) is a reading without one, at the last reading's (within half an hour;
    /// else the ambient), as an empty field of `bcal calibrate --follow`'s CSV is. A bad row raises ValueError naming its
    /// position; the readings before it have been taken.
    fn run<'py>(&self, py: Python<'py>, df: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
        let columns: Vec<String> = df.getattr("columns")?.call_method0("tolist")?.extract()?;
        let names: Vec<&str> = columns.iter().map(String::as_str).collect();
        let cols = reading_columns(&names).map_err(|e| value_error(format!("the DataFrame's columns: {e}")))?;
        // Each column in s, V, A or deg C, converted by the unit its name gives (`time_ms`, `current_ma`).
        let column = |c: &NamedColumn| -> PyResult<Vec<f64>> {
            let kwargs = PyDict::new(py);
            kwargs.set_item("dtype", "float64")?;
            let values =
                df.get_item(&columns[c.index])?.call_method("to_numpy", (), Some(&kwargs))?.call_method0("tolist")?;
            Ok(values.extract::<Vec<f64>>()?.into_iter().map(|v| c.si(v)).collect())
        };
        let (time_s, voltage_v, current_a) = (column(&cols.time)?, column(&cols.voltage)?, column(&cols.current)?);
        let temperature_c = cols.temperature.as_ref().map(column).transpose()?;
        let mut out: Vec<Vec<f64>> = vec![Vec::with_capacity(time_s.len()); RUN_COLUMNS.len()];
        let opt = |v: Option<f64>| v.unwrap_or(f64::NAN);
        let result = self.with_stream(|s| -> Result<(), String> {
            for k in 0..time_s.len() {
                let r = Reading {
                    time_s: time_s[k],
                    voltage_v: voltage_v[k],
                    current_a: current_a[k],
                    temperature_c: temperature_c.as_ref().map(|t| t[k]).filter(|t| !t.is_nan()),
                };
                let e = s.step(&r).map_err(|e| format!("row {k}: {e}"))?;
                let row = [
                    e.time_s,
                    e.q_mobile,
                    opt(e.q_mobile_lo),
                    opt(e.q_mobile_hi),
                    e.r_o,
                    opt(e.r_o_lo),
                    opt(e.r_o_hi),
                    opt(e.eod_s),
                    opt(e.eod_current_a),
                    opt(e.eod_power_w),
                    opt(e.eod_lo_s),
                    opt(e.eod_hi_s),
                    opt(e.delivered_ah),
                    opt(e.delivered_lo_ah),
                    opt(e.delivered_hi_ah),
                    f64::from(u8::from(e.eod_from_prior)),
                    f64::from(u8::from(e.eod_recentred)),
                    f64::from(u8::from(e.eod_on_voltage_change)),
                    e.eod_prior_weight,
                    e.eod_previous_weight,
                    e.eod_learned_weight,
                    f64::from(e.discharge),
                    k as f64,
                ];
                for (col, v) in out.iter_mut().zip(row) {
                    col.push(v);
                }
            }
            Ok(())
        });
        result.map_err(value_error)?;
        let data = PyDict::new(py);
        for (name, values) in RUN_COLUMNS.iter().zip(out) {
            data.set_item(*name, crate::convert::array(py, &values)?)?;
        }
        let frame = py.import("pandas")?.call_method1("DataFrame", (data,))?;
        for name in ["discharge", "row"] {
            let ints = frame.get_item(name)?.call_method1("astype", ("int64",))?;
            frame.set_item(name, ints)?;
        }
        Ok(frame)
    }

    fn __repr__(&self) -> String {
        format!("Calibrator('{}', readings={})", self.kind.name(), self.readings())
    }
}
