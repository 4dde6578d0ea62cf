//! The measured-only setting (issue 12): calibration from what a battery management system measures.
//!
//! [`scenario`] simulates hidden true cells read through a sensor model (noise, bias, sampling), with any
//! starting charge and constant-power, constant-current or piecewise loads; [`cellmodel`] is the
//! calibrator's own model of the cell, consistent with whatever parameters it believes; [`window`] is its
//! least-squares view of recent readings; [`tracker`] puts them together per reading (observation, action,
//! cost, intervals); [`env`] is the RL environment built on it. The paper's full-state setting lives in
//! [`crate::mdp`].

pub mod calibrator;
pub mod cellmodel;
pub mod env;
pub mod extension;
pub mod scenario;
pub mod tracker;
pub mod window;

pub use calibrator::Calibrator;
pub use extension::ModelExtension;
pub use scenario::{Episode, EpisodeSpec, LoadKind, Sample, ScenarioConfig, SensorConfig};
pub use tracker::{ActionMode, Interval, Tracker, TrackerSpec, OBS_DIM};
