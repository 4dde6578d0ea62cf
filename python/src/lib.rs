//! The `bcal` Python extension module: a thin pyo3 layer over the workspace's crates, with no logic of its
//! own. `simulate` runs [`bcal_common::simulate`] (what `bcal simulate` runs), `diagnose` runs the doctor
//! as `bcal diagnose` does, and `Calibrator` runs one calibrator on readings through the same stream
//! (`bcal_calib::stream`) as `bcal calibrate --follow`. Every use of calibrator types sits in
//! [`calibrator`]. Errors become Python exceptions carrying the CLI's messages ([`errors`]).

mod calibrator;
mod convert;
mod diagnose;
mod errors;
mod simulate;

use pyo3::prelude::*;

/// bcal: keep the NASA Li-ion electrochemistry model (Daigle & Kulkarni 2013; progpy's
/// BatteryElectroChemEOD) true to its cell. simulate() runs the model, Calibrator calibrates it one
/// reading at a time, diagnose() finds what the model gets wrong on measured data.
#[pymodule(name = "bcal")]
mod bcal_module {
    #[pymodule_export]
    use super::calibrator::Calibrator;
    #[pymodule_export]
    use super::diagnose::diagnose;
    #[pymodule_export]
    use super::simulate::simulate;

    #[pymodule_init]
    fn init(m: &pyo3::Bound<'_, pyo3::types::PyModule>) -> pyo3::PyResult<()> {
        use pyo3::types::PyModuleMethods;
        m.add("__version__", env!("CARGO_PKG_VERSION"))?;
        m.add("VEOD_V", bcal_common::battery::BatteryParams::default().v_eod_v)?;
        Ok(())
    }
}
