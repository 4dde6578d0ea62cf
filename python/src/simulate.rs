//! `bcal.simulate`: [`bcal_common::simulate::simulate`] (what `bcal simulate` runs) with the trace as NumPy
//! arrays.

use crate::convert::{array, dict};
use crate::errors::value_error;
use bcal_common::math::idx;
use bcal_common::measured::scenario::KELVIN_0C;
use bcal_common::simulate::{simulate as run, SimulateRequest};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// One discharge of the model from a new cell's state until the first step below VEOD (3.0 V), stepped
/// by explicit Euler: what `bcal simulate` runs.
///
/// Give exactly one of `load_w` (constant power, W; the current is P / V at the start of each step) and
/// `current_a` (constant current, A, positive while discharging). `q_mobile` (C) and `ro` (ohm) are the
/// degradation parameters (new cell: 7600 C, 0.117215 ohm); `thermal` turns on the bulk temperature's heat
/// balance (progpy always runs it; off, the cell stays at 292.1 K). `steps`: later load steps as
/// (start_s, value) pairs in the first load's unit, start times increasing (a load step: 8 W, then 16 W
/// from 1000 s is `load_w=8.0, steps=[(1000.0, 16.0)]`).
///
/// Returns a dict: `time_s`, `voltage_v`, `current_a` (drawn over the step starting at each row; 0 on the
/// EOD row), `temperature_c` (NumPy float64 arrays, one row per step, t = 0 to the EOD row included),
/// `state` (a dict of arrays under progpy's state names: qpS, qpB, qnB, qnS in C, Vo, Vsn, Vsp in V, tb
/// in K) and `eod_s` (time of the first row below VEOD, s). Raises ValueError with the CLI's message for a
/// bad argument or when VEOD is not reached within `max_steps`.
#[pyfunction]
#[pyo3(signature = (load_w=None, current_a=None, q_mobile=7600.0, ro=0.117215, dt_s=1.0, thermal=false, max_steps=200_000, steps=None))]
#[allow(clippy::too_many_arguments)]
pub fn simulate<'py>(
    py: Python<'py>,
    load_w: Option<f64>,
    current_a: Option<f64>,
    q_mobile: f64,
    ro: f64,
    dt_s: f64,
    thermal: bool,
    max_steps: usize,
    steps: Option<Vec<(f64, f64)>>,
) -> PyResult<Bound<'py, PyDict>> {
    let req = SimulateRequest {
        q_mobile,
        r_o: ro,
        load_w,
        current_a,
        steps: steps.unwrap_or_default(),
        thermal,
        dt_s,
        max_steps,
    };
    let tr = py.detach(|| run(&req)).map_err(value_error)?;
    let out = dict(py);
    out.set_item("time_s", array(py, &tr.time_s)?)?;
    out.set_item("voltage_v", array(py, &tr.voltage_v)?)?;
    out.set_item("current_a", array(py, &tr.current_a)?)?;
    let temperature_c: Vec<f64> = tr.state.iter().map(|x| x[idx::T_B] - KELVIN_0C).collect();
    out.set_item("temperature_c", array(py, &temperature_c)?)?;
    let state = dict(py);
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
        let v: Vec<f64> = tr.state.iter().map(|x| x[k]).collect();
        state.set_item(name, array(py, &v)?)?;
    }
    out.set_item("state", state)?;
    out.set_item("eod_s", tr.eod_s)?;
    Ok(out)
}
