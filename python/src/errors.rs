//! Rust errors as Python exceptions: bad input (arguments, readings, files that are not what they should
//! be) is `ValueError`, a file that cannot be read is `OSError` (`FileNotFoundError` when missing); each
//! carries the message the CLI prints.

use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::PyErr;

/// `ValueError` with `e`'s message.
pub fn value_error(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// The doctor's errors: reading failures as `OSError`, everything else as `ValueError`.
pub fn doctor_error(e: bcal_doctor::DoctorError) -> PyErr {
    match &e {
        bcal_doctor::DoctorError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(e.to_string())
        }
        bcal_doctor::DoctorError::Io { .. } | bcal_doctor::DoctorError::Write { .. } => {
            PyOSError::new_err(e.to_string())
        }
        _ => value_error(e),
    }
}
