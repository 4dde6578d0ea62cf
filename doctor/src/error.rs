//! The doctor's typed errors. Each message says what was wrong, where (file and line when a file is
//! involved), and what to do about it.

use std::path::PathBuf;

/// Everything that can go wrong in the doctor.
#[derive(Debug, thiserror::Error)]
pub enum DoctorError {
    #[error("cannot read {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: CSV error: {source}")]
    Csv { path: PathBuf, source: csv::Error },
    #[error("{path}: missing column `{column}` (found: {found}); {hint}")]
    MissingColumn { path: PathBuf, column: String, found: String, hint: &'static str },
    #[error("{path}: empty (no header, no rows): the logger wrote nothing; leave the file out or export it again")]
    EmptyFile { path: PathBuf },
    #[error("{path}, line {line}: field `{column}` = `{value}` is not a finite number; fix or remove that row")]
    BadField { path: PathBuf, line: u64, column: String, value: String },
    #[error(
        "{path}, line {line}: field `filename` = `{value}` is not a file name in data/; write the bare file name \
         (e.g. 00042.csv)"
    )]
    NotAFileName { path: PathBuf, line: u64, value: String },
    #[error("{path}, line {line}: time {time_s:?} s does not increase (previous {previous_s:?} s); samples must be in time order")]
    TimeNotIncreasing { path: PathBuf, line: u64, time_s: f64, previous_s: f64 },
    #[error(
        "{path}: voltage median {median_v:.1} looks like millivolts (a Li-ion cell reads 2.0-4.5 V); \
         convert the column to volts (divide by 1000) or name it voltage_mv (or `Voltage / mV`)"
    )]
    VoltageInMillivolts { path: PathBuf, median_v: f64 },
    #[error(
        "{path}: voltage median {median_v:?} V is outside a Li-ion cell's range (0.5-5 V); check the column and its unit"
    )]
    VoltageOutOfRange { path: PathBuf, median_v: f64 },
    #[error(
        "{path}, line {line}: voltage {voltage_v:?} V is outside a Li-ion cell's range (0.5-5 V) amid readings \
         within it (a logger's glitch); fix or remove that row"
    )]
    VoltageGlitch { path: PathBuf, line: u64, voltage_v: f64 },
    #[error(
        "{path}, line {line}: current {current_a:?} A on {readings} reading(s) where the readings around read \
         {before_a:?} and {after_a:?} A, the voltage moving {moved_mv:.1} mV with it (a cell drawing that would move \
         it by far more: a logger's glitch); fix or remove that row"
    )]
    CurrentGlitch {
        path: PathBuf,
        line: u64,
        current_a: f64,
        readings: usize,
        before_a: f64,
        after_a: f64,
        moved_mv: f64,
    },
    /// Values a strict reader refuses where the others fill them and say so (the note).
    #[error("{why}")]
    MissingValues { why: String },
    #[error(
        "{path}, line {line}: from here the {readings} readings to the file's end repeat one reading to its last \
         digit while the time runs on {span_s:.0} s under load (a logger that froze)"
    )]
    FrozenEnd { path: PathBuf, line: u64, readings: usize, span_s: f64 },
    #[error(
        "{path}: cell temperature median {median_c:.1} deg C is outside where a Li-ion cell works (-60 to 120 deg C); \
         a column in kelvin must say so (temperature_k, or `Temperature / K`)"
    )]
    TemperatureOutOfRange { path: PathBuf, median_c: f64 },
    #[error(
        "{path}: no sample carries a discharge current above {threshold_a} A; the generic CSV expects \
         current_a POSITIVE while discharging (NASA files use negative and are read through metadata.csv); \
         or let the reader decide the sign (--current-sign auto)"
    )]
    NoLoad { path: PathBuf, threshold_a: f64 },
    #[error(
        "{path}: no discharge: no sample carries a discharge current above {threshold_a} A with {sign}; check \
         the current column and its unit, or the sign (--current-sign)"
    )]
    NoDischarge { path: PathBuf, threshold_a: f64, sign: String },
    #[error(
        "{path}: cannot tell which current sign is discharge: {why}; pass --current-sign discharge-positive or \
         --current-sign discharge-negative"
    )]
    SignUndecided { path: PathBuf, why: String },
    #[error("{path}: column `{column}` {why}; {hint}")]
    SuspectUnit { path: PathBuf, column: String, why: String, hint: String },
    #[error("{path}: column `{column}` is in `{unit}`, a unit the doctor does not read; write it in {accepted}")]
    UnknownUnit { path: PathBuf, column: String, unit: String, accepted: &'static str },
    #[error(
        "{path}, cycle {cycle}: the cut-off {cutoff_v} V is above the first loaded voltage ({first_loaded_v:.3} V \
         at {time_s} s); give the cell's discharge cut-off in volts (e.g. --cutoff-v 2.5), below its loaded voltages"
    )]
    CutoffAboveLoad { path: PathBuf, cycle: u32, cutoff_v: f64, first_loaded_v: f64, time_s: f64 },
    #[error("{path}: only {rows} usable samples; a discharge needs at least {min}")]
    TooFewSamples { path: PathBuf, rows: usize, min: usize },
    #[error("{path}: {why}; pass the diagnosis.json that bcal diagnose wrote")]
    BadModelFile { path: PathBuf, why: String },
    #[error("no discharge records selected: {why}")]
    NothingSelected { why: String },
    #[error("cycle range `{text}` is not A..B (inclusive, e.g. 1..40)")]
    BadRange { text: String },
    #[error("configuration: {0}")]
    BadConfig(String),
    #[error("battery model: {0}")]
    Model(#[from] bcal_common::battery::ModelError),
    #[error("plot {path}: {message}")]
    Plot { path: PathBuf, message: String },
    #[error("cannot write {path}: {source}")]
    Write { path: PathBuf, source: std::io::Error },
    #[error("JSON: {0}")]
    Json(#[from] serde_json::Error),
}

impl DoctorError {
    /// The line of the file the error names, where it names one: a strict reader refuses a record with the
    /// first of its errors in the file's order.
    pub fn line(&self) -> Option<u64> {
        match self {
            Self::BadField { line, .. }
            | Self::NotAFileName { line, .. }
            | Self::TimeNotIncreasing { line, .. }
            | Self::VoltageGlitch { line, .. }
            | Self::CurrentGlitch { line, .. }
            | Self::FrozenEnd { line, .. } => Some(*line),
            _ => None,
        }
    }
}
