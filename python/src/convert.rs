//! Rust values as Python ones: NumPy arrays from vectors, dicts from anything serde serialises (through
//! Python's own `json`, so a dict equals what the CLI writes as JSON), `None` for missing numbers.

use pyo3::prelude::*;
use pyo3::types::PyDict;

/// A float64 NumPy array of `v`.
pub fn array<'py>(py: Python<'py>, v: &[f64]) -> PyResult<Bound<'py, PyAny>> {
    let np = py.import("numpy")?;
    np.call_method1("asarray", (v.to_vec(), "float64"))
}

/// `value` as Python objects (dicts, lists, floats, None), as `json.loads` of its JSON.
pub fn from_serde<'py>(py: Python<'py>, value: &impl serde::Serialize) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value).map_err(crate::errors::value_error)?;
    py.import("json")?.call_method1("loads", (text,))
}

/// A new dict.
pub fn dict(py: Python<'_>) -> Bound<'_, PyDict> {
    PyDict::new(py)
}
