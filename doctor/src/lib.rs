//! bcal-doctor: a doctor for the battery model. Given measured discharges, it calibrates the base model per
//! cycle, shows where and how the model disagrees with the cell, fits candidate causes (each a small,
//! physically meaningful extension of the model), judges them on held-out cycles, and extends the model with
//! the winner(s).
//!
//! Data flow: [`input`] (what the user pointed at: cell, cycles, cut-off) and [`read`] (NASA PCoE records
//! or the generic CSV) -> [`record::Discharge`] -> [`fit`] (bounded least squares over [`sim`], the extended
//! simulator) -> [`analysis`] (residual structure) -> [`diagnose`] (candidates, ranking, extension) ->
//! [`report`] (JSON, Markdown) and [`plot`] (PNG, SVG). Across discharges, [`lifetime`] looks at the cell's
//! life: capacity and the fitted parameters against cycle, rest and conditions, and recovery after rest.
//!
//! The doctor never prints and never learns which effect a test hid: it sees only the data it is given.

pub mod analysis;
pub mod diagnose;
pub mod error;
pub mod fit;
pub mod input;
pub mod lifetime;
pub mod model_file;
pub mod plot;
pub mod read;
pub mod record;
pub mod report;
pub mod sim;

pub use diagnose::{diagnose, DiagnoseConfig, Diagnosis};
pub use error::DoctorError;
pub use record::Discharge;
pub use sim::{Cause, ExtParams};
