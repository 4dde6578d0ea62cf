//! Readers for measured discharges: NASA PCoE records chosen through `metadata.csv`, and the documented
//! generic CSV `time_s,voltage_v,current_a[,temperature_c][,cycle]` (current positive while discharging).
//!
//! Bad input never passes silently: files named in the metadata but absent are skipped and counted,
//! non-finite or non-numeric fields are errors naming file and line, a voltage column in millivolts is
//! refused with a hint, time must increase, a metadata row may name only a bare file in `data/`. Error
//! lines are the lines records start on (CRLF and blank lines counted); file content in a message is shown
//! escaped and shortened. Truncated records (ending under load) are found later by
//! [`crate::record::Discharge::windows`] and flagged by the diagnosis. Readers never fit and never print.

use crate::error::DoctorError;
use crate::record::{Discharge, CELSIUS_TO_KELVIN};
use bcal_common::text::shown;
use std::collections::BTreeMap;
use std::ops::RangeInclusive;
use std::path::Path;

/// Fewest samples a record must hold to be worth a fit.
pub const MIN_SAMPLES: usize = 10;

/// Ambient temperature assumed for a generic CSV without a temperature column, deg C.
pub const DEFAULT_AMBIENT_C: f64 = 25.0;

/// What a read returned besides the records: what it skipped and why.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReadReport {
    /// Files named in the metadata for the selected cell and cycles that are not on disk.
    pub missing_files: Vec<String>,
    /// Discharge rows of the selected cell in the metadata (present or not) inside the cycle range.
    pub rows_selected: usize,
}

/// Parses `A..B` (inclusive) into a cycle range.
pub fn parse_cycle_range(text: &str) -> Result<RangeInclusive<u32>, DoctorError> {
    let bad = || DoctorError::BadRange { text: text.to_string() };
    let (a, b) = text.split_once("..").ok_or_else(bad)?;
    let a: u32 = a.trim().parse().map_err(|_| bad())?;
    let b: u32 = b.trim().trim_start_matches('=').parse().map_err(|_| bad())?;
    if a == 0 || b < a {
        return Err(bad());
    }
    Ok(a..=b)
}

/// Reads the discharges of `cell` whose cycle number (1-based order of the cell's discharge rows in
/// `metadata.csv`) lies in `cycles` (all when `None`). Rows whose file is absent are skipped and listed.
pub fn read_nasa(
    root: &Path,
    cell: &str,
    cycles: Option<&RangeInclusive<u32>>,
) -> Result<(Vec<Discharge>, ReadReport), DoctorError> {
    let meta_path = root.join("metadata.csv");
    let bytes = read_file(&meta_path)?;
    let mut lines = Lines::new(&bytes);
    let mut rdr = csv::Reader::from_reader(bytes.as_slice());
    let headers = rdr.headers().map_err(|e| csv_error(&meta_path, e, &mut lines))?.clone();
    let col = |name: &str| column(&headers, name, &meta_path, "expected the NASA PCoE metadata.csv layout");
    let (c_type, c_amb, c_cell, c_test, c_file, c_cap) = (
        col("type")?,
        col("ambient_temperature")?,
        col("battery_id")?,
        col("test_id")?,
        col("filename")?,
        col("Capacity")?,
    );
    // (test_id, filename, ambient_c, capacity_ah, metadata line) of the cell's discharges.
    let mut rows = Vec::new();
    for rec in rdr.records() {
        let rec = rec.map_err(|e| csv_error(&meta_path, e, &mut lines))?;
        if rec.get(c_type) != Some("discharge") || rec.get(c_cell) != Some(cell) {
            continue;
        }
        let line = lines.of(&rec);
        let test_id = number(&rec, c_test, "test_id", &meta_path, line)?;
        let ambient_c = number(&rec, c_amb, "ambient_temperature", &meta_path, line)?;
        let capacity_ah =
            rec.get(c_cap).and_then(|s| s.trim().parse::<f64>().ok()).filter(|c| c.is_finite() && *c > 0.0);
        let file = rec.get(c_file).unwrap_or("");
        // A bare file name in `data/`: a path (`../x`, `/etc/x`, `sub/x`) would read outside the folder.
        let mut parts = Path::new(file).components();
        if !matches!((parts.next(), parts.next()), (Some(std::path::Component::Normal(_)), None)) {
            return Err(DoctorError::NotAFileName { path: meta_path, line, value: shown(file, 80) });
        }
        rows.push((test_id, file.to_string(), ambient_c, capacity_ah));
    }
    if rows.is_empty() {
        return Err(DoctorError::NothingSelected {
            why: format!("{} has no discharge rows for cell `{cell}`", meta_path.display()),
        });
    }
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut report = ReadReport::default();
    let mut out = Vec::new();
    for (k, (_, file, ambient_c, capacity_ah)) in rows.into_iter().enumerate() {
        let cycle = k as u32 + 1;
        if cycles.is_some_and(|r| !r.contains(&cycle)) {
            continue;
        }
        report.rows_selected += 1;
        let path = root.join("data").join(&file);
        if !path.is_file() {
            report.missing_files.push(file);
            continue;
        }
        let mut d = read_nasa_record(&path, cell, cycle, ambient_c + CELSIUS_TO_KELVIN)?;
        d.stated_capacity_ah = capacity_ah;
        out.push(d);
    }
    Ok((out, report))
}

/// Reads one NASA discharge file (`Voltage_measured`, `Current_measured` negative while discharging,
/// `Temperature_measured` deg C, `Time` s).
pub fn read_nasa_record(path: &Path, cell: &str, cycle: u32, ambient_k: f64) -> Result<Discharge, DoctorError> {
    let bytes = read_file(path)?;
    let mut lines = Lines::new(&bytes);
    let mut rdr = csv::Reader::from_reader(bytes.as_slice());
    let headers = rdr.headers().map_err(|e| csv_error(path, e, &mut lines))?.clone();
    let hint = "expected a NASA PCoE discharge record (Voltage_measured, Current_measured, Temperature_measured, Time)";
    let cv = column(&headers, "Voltage_measured", path, hint)?;
    let ci = column(&headers, "Current_measured", path, hint)?;
    let ct = column(&headers, "Temperature_measured", path, hint)?;
    let cs = column(&headers, "Time", path, hint)?;
    let mut d = empty(cell, cycle, path, ambient_k, true);
    let temps = d.temperature_k.as_mut().expect("allocated");
    for rec in rdr.records() {
        let rec = rec.map_err(|e| csv_error(path, e, &mut lines))?;
        let line = lines.of(&rec);
        let time_s = number(&rec, cs, "Time", path, line)?;
        check_time(&d.time_s, time_s, path, line)?;
        d.time_s.push(time_s);
        d.voltage_v.push(number(&rec, cv, "Voltage_measured", path, line)?);
        d.current_a.push(-number(&rec, ci, "Current_measured", path, line)?);
        temps.push(number(&rec, ct, "Temperature_measured", path, line)? + CELSIUS_TO_KELVIN);
    }
    validate(d)
}

/// Reads a generic CSV: `time_s,voltage_v,current_a` plus optional `temperature_c` and `cycle` columns
/// (any order; current positive while discharging). Rows are grouped by `cycle` (all cycle 1 without it);
/// time restarts per cycle. The ambient is `ambient_c` if given, else each record's first temperature,
/// else [`DEFAULT_AMBIENT_C`].
pub fn read_generic(path: &Path, ambient_c: Option<f64>) -> Result<Vec<Discharge>, DoctorError> {
    let bytes = read_file(path)?;
    let mut lines = Lines::new(&bytes);
    let mut rdr = csv::Reader::from_reader(bytes.as_slice());
    let headers = rdr.headers().map_err(|e| csv_error(path, e, &mut lines))?.clone();
    let hint = "the generic CSV needs time_s,voltage_v,current_a[,temperature_c][,cycle]";
    let cs = column(&headers, "time_s", path, hint)?;
    let cv = column(&headers, "voltage_v", path, hint)?;
    let ci = column(&headers, "current_a", path, hint)?;
    let ct = headers.iter().position(|h| h.trim() == "temperature_c");
    let cc = headers.iter().position(|h| h.trim() == "cycle");
    let cell = path.file_stem().map_or_else(|| "cell".to_string(), |s| s.to_string_lossy().into_owned());
    let mut by_cycle: BTreeMap<u32, Discharge> = BTreeMap::new();
    for rec in rdr.records() {
        let rec = rec.map_err(|e| csv_error(path, e, &mut lines))?;
        let line = lines.of(&rec);
        let cycle = match cc {
            Some(c) => {
                let v = number(&rec, c, "cycle", path, line)?;
                // Beyond u32 the cast would saturate and merge distinct cycles.
                if v < 0.0 || v.fract() != 0.0 || v > f64::from(u32::MAX) {
                    return Err(bad_field(path, line, "cycle", rec.get(c).unwrap_or("")));
                }
                v as u32
            }
            None => 1,
        };
        let d = by_cycle.entry(cycle).or_insert_with(|| empty(&cell, cycle, path, f64::NAN, ct.is_some()));
        let time_s = number(&rec, cs, "time_s", path, line)?;
        check_time(&d.time_s, time_s, path, line)?;
        d.time_s.push(time_s);
        d.voltage_v.push(number(&rec, cv, "voltage_v", path, line)?);
        d.current_a.push(number(&rec, ci, "current_a", path, line)?);
        if let (Some(c), Some(t)) = (ct, d.temperature_k.as_mut()) {
            t.push(number(&rec, c, "temperature_c", path, line)? + CELSIUS_TO_KELVIN);
        }
    }
    if by_cycle.is_empty() {
        return Err(DoctorError::TooFewSamples { path: path.to_path_buf(), rows: 0, min: MIN_SAMPLES });
    }
    by_cycle
        .into_values()
        .map(|mut d| {
            d.ambient_k = match (ambient_c, &d.temperature_k) {
                (Some(a), _) => a + CELSIUS_TO_KELVIN,
                (None, Some(t)) if !t.is_empty() => t[0],
                _ => DEFAULT_AMBIENT_C + CELSIUS_TO_KELVIN,
            };
            if d.current_a.iter().all(|i| *i <= 0.0) {
                return Err(DoctorError::NoLoad { path: d.source.clone(), threshold_a: 0.0 });
            }
            validate(d)
        })
        .collect()
}

fn empty(cell: &str, cycle: u32, path: &Path, ambient_k: f64, with_temperature: bool) -> Discharge {
    Discharge {
        cell: cell.to_string(),
        cycle,
        source: path.to_path_buf(),
        ambient_k,
        time_s: Vec::new(),
        voltage_v: Vec::new(),
        current_a: Vec::new(),
        temperature_k: with_temperature.then(Vec::new),
        stated_capacity_ah: None,
    }
}

/// Whole-record checks: enough samples, voltage in volts.
fn validate(d: Discharge) -> Result<Discharge, DoctorError> {
    if d.len() < MIN_SAMPLES {
        return Err(DoctorError::TooFewSamples { path: d.source.clone(), rows: d.len(), min: MIN_SAMPLES });
    }
    let mut v = d.voltage_v.clone();
    v.sort_by(f64::total_cmp);
    let median_v = v[v.len() / 2];
    if (500.0..=5000.0).contains(&median_v) {
        return Err(DoctorError::VoltageInMillivolts { path: d.source.clone(), median_v });
    }
    if !(0.5..=5.0).contains(&median_v) {
        return Err(DoctorError::VoltageOutOfRange { path: d.source.clone(), median_v });
    }
    Ok(d)
}

fn check_time(times: &[f64], time_s: f64, path: &Path, line: u64) -> Result<(), DoctorError> {
    match times.last() {
        Some(&previous_s) if time_s <= previous_s => {
            Err(DoctorError::TimeNotIncreasing { path: path.to_path_buf(), line, time_s, previous_s })
        }
        _ => Ok(()),
    }
}

fn column(headers: &csv::StringRecord, name: &str, path: &Path, hint: &'static str) -> Result<usize, DoctorError> {
    headers.iter().position(|h| h.trim() == name).ok_or_else(|| DoctorError::MissingColumn {
        path: path.to_path_buf(),
        column: name.to_string(),
        found: shown(&headers.iter().collect::<Vec<_>>().join(","), 200),
        hint,
    })
}

fn number(rec: &csv::StringRecord, col: usize, name: &str, path: &Path, line: u64) -> Result<f64, DoctorError> {
    let raw = rec.get(col).unwrap_or("");
    match raw.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(bad_field(path, line, name, raw)),
    }
}

fn bad_field(path: &Path, line: u64, column: &str, value: &str) -> DoctorError {
    DoctorError::BadField { path: path.to_path_buf(), line, column: column.to_string(), value: shown(value, 40) }
}

fn read_file(path: &Path) -> Result<Vec<u8>, DoctorError> {
    std::fs::read(path).map_err(|source| DoctorError::Io { path: path.to_path_buf(), source })
}

/// Line numbers of records, counted over the file's bytes. The csv crate's `Position::line` names the line
/// where it began skipping line ends before a record: one line early after a CRLF or a blank line.
struct Lines<'a> {
    bytes: &'a [u8],
    /// Byte up to which `line` is counted, and the 1-based line holding it.
    at: usize,
    line: u64,
}

impl<'a> Lines<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        Lines { bytes, at: 0, line: 1 }
    }

    /// Line of the first byte at or after `byte` that is not a line end (where the record's text starts).
    fn at_byte(&mut self, byte: u64) -> u64 {
        let start = usize::try_from(byte).map_or(self.bytes.len(), |b| b.min(self.bytes.len()));
        let rest = &self.bytes[start..];
        let first = rest.iter().position(|b| !matches!(b, b'\r' | b'\n')).map_or(self.bytes.len(), |k| start + k);
        if first < self.at {
            // Records come in order; count afresh if ever asked about an earlier one.
            (self.at, self.line) = (0, 1);
        }
        self.line += self.bytes[self.at..first].iter().filter(|b| **b == b'\n').count() as u64;
        self.at = first;
        self.line
    }

    fn of(&mut self, rec: &csv::StringRecord) -> u64 {
        match rec.position() {
            Some(p) => self.at_byte(p.byte()),
            None => self.line,
        }
    }
}

/// A CSV error naming the line the bad record starts on (see [`Lines`]) and what to do.
fn csv_error(path: &Path, source: csv::Error, lines: &mut Lines) -> DoctorError {
    let line = source.position().map(|p| lines.at_byte(p.byte()));
    let why = match (source.kind(), line) {
        (csv::ErrorKind::UnequalLengths { expected_len, len, .. }, Some(line)) => format!(
            "line {line}: {len} fields where the first row has {expected_len}; every row needs one field per column"
        ),
        (csv::ErrorKind::Utf8 { err, .. }, Some(line)) => {
            format!("line {line}, field {}: not valid UTF-8; save the file as UTF-8 text", err.field() + 1)
        }
        _ => return DoctorError::Csv { path: path.to_path_buf(), source },
    };
    let source = csv::Error::from(std::io::Error::new(std::io::ErrorKind::InvalidData, why));
    DoctorError::Csv { path: path.to_path_buf(), source }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cycle_ranges_parse_and_refuse_nonsense() {
        assert_eq!(parse_cycle_range("1..40").unwrap(), 1..=40);
        assert_eq!(parse_cycle_range("3..=3").unwrap(), 3..=3);
        for bad in ["", "5", "0..3", "9..2", "a..b"] {
            assert!(parse_cycle_range(bad).is_err(), "{bad}");
        }
    }
}
