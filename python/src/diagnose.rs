//! `bcal.diagnose`: the doctor on measured data, as `bcal diagnose` runs it (the same reading, cycle
//! split and cut-off: `bcal_doctor::input`), returning `diagnosis.json`'s content as a dict.

use crate::convert::from_serde;
use crate::errors::{doctor_error, value_error};
use bcal_calib::stream::LOAD_THRESHOLD_A;
use bcal_doctor::input::{
    cell_name, cutoff, cycle_ranges, diagnose_with_lifetime, read_any, split_cycles, DIAGNOSE_DT_MAX_S,
};
use bcal_doctor::read::{parse_cycle_range, CurrentSign, ReadOptions};
use bcal_doctor::{DiagnoseConfig, DoctorError};
use pyo3::prelude::*;
use std::path::PathBuf;

/// Diagnose measured discharges: fit the model per cycle, find what it gets wrong, name the cause and
/// extend the model, judged on held-out cycles (what `bcal diagnose` does, without writing files).
///
/// `data` is a NASA PCoE folder (metadata.csv and data/; `cell` required, e.g. "B0005") or a CSV
/// (time_s,voltage_v,current_a[,temperature_c][,cycle]). `cycles` and `holdout` are "A..B" ranges
/// (inclusive; NASA cycles count from 1, a CSV's as its cycle column does; default: three quarters of the cycles `bcal calibrate` trains on against the last
/// quarter, B0005 1..30 against 31..40; a life under 24 discharges: its first third against the rest),
/// `stride` takes every
/// N-th cycle, `cutoff_v` the discharge cut-off (default: the cell's documented protocol, else read off
/// the data), `current_sign` "auto", "discharge-positive" or "discharge-negative", `ambient_c` the
/// ambient of a CSV without one.
///
/// Returns diagnosis.json's content as a dict (cause, ranking, base and extended models, per-cycle fits,
/// residual structure), plus `read_notes` (what the reader decided or skipped) and `cutoff_source`.
/// Raises FileNotFoundError / OSError when the data cannot be read, ValueError with the CLI's message for
/// anything else.
#[pyfunction]
#[pyo3(signature = (data, cell=None, cycles=None, holdout=None, stride=1, cutoff_v=None, current_sign="auto", ambient_c=None))]
#[allow(clippy::too_many_arguments)]
pub fn diagnose<'py>(
    py: Python<'py>,
    data: PathBuf,
    cell: Option<String>,
    cycles: Option<String>,
    holdout: Option<String>,
    stride: u32,
    cutoff_v: Option<f64>,
    current_sign: &str,
    ambient_c: Option<f64>,
) -> PyResult<Bound<'py, PyAny>> {
    if stride == 0 {
        return Err(value_error("stride must be at least 1"));
    }
    if let Some(v) = cutoff_v {
        bcal_common::simulate::positive(v).map_err(|why| value_error(format!("cutoff_v: {why}")))?;
    }
    let sign: CurrentSign = current_sign.parse().map_err(value_error)?;
    let cycles = cycles.as_deref().map(parse_cycle_range).transpose().map_err(doctor_error)?;
    let holdout = holdout.as_deref().map(parse_cycle_range).transpose().map_err(doctor_error)?;
    let opts = ReadOptions { current_sign: sign, ambient_c, ..ReadOptions::default() };
    let run = || -> Result<(bcal_doctor::Diagnosis, Vec<String>, Option<String>), DoctorError> {
        let cell = cell_name(cell.as_deref(), &data)?;
        let (all, report) = read_any(&data, &cell, None, &opts)?;
        let (train_r, held_r) = cycle_ranges(&all, cycles.clone(), holdout.clone());
        let (train, held) = split_cycles(&all, cycles, holdout, stride)?;
        let cut = cutoff(cutoff_v, &data, &cell, &train, LOAD_THRESHOLD_A);
        let mut cfg = DiagnoseConfig { cutoff_v: cut.as_ref().map(|c| c.0), ..DiagnoseConfig::default() };
        cfg.fit.dt_max_s = DIAGNOSE_DT_MAX_S;
        let (diag, _) = diagnose_with_lifetime(&cfg, &all, &report.starts, (&train_r, &held_r), &train, &held, true)?;
        Ok((diag, report.summary(), cut.map(|c| c.1)))
    };
    let (diag, notes, cut_source) = py.detach(run).map_err(doctor_error)?;
    let out = from_serde(py, &diag)?;
    out.set_item("read_notes", notes)?;
    out.set_item("cutoff_source", cut_source)?;
    Ok(out)
}
