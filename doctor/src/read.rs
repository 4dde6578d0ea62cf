//! Readers for measured discharges: NASA PCoE records chosen through `metadata.csv`; the documented generic
//! CSV `time_s,voltage_v,current_a[,temperature_c][,cycle]` (current positive while discharging); and, through
//! [`read_csv`], any CSV whose columns name time, voltage and current with their units: the generic names,
//! the Battery Data Format's labels and machine names (`Test Time / s` or `test_time_second`, `Voltage / V`
//! or `voltage_volt`, `Current / A` or `current_ampere`, `Cycle Count / 1`, `Temperature T1 / degC`, ...),
//! unit suffixes (`time_ms`, `voltage_mv`, `current_ma`, `Current (mA)`, `Current / mA`), NASA's record names.
//!
//! Units, sign and discharge boundaries are decided here, once, and reported in a [`ReadReport`]:
//! - units: a unit in the column name is converted (ms, min, h; mV; mA; K); a column declared in volts
//!   whose median reads 500-5000 is refused as millivolts, a current above [`MAX_CELL_CURRENT_A`] as
//!   milliamperes, a record drawing more than [`MAX_RECORD_CHARGE_AH`] as time in milliseconds, each with
//!   the column to rename;
//! - sign ([`CurrentSign`]): `Auto` decides from the data which sign is discharge (the voltage falls under
//!   discharge current and steps down when it rises; [`SignEvidence`]) and reports its choice, or refuses
//!   a file it cannot decide; the other two take the caller's word;
//! - boundaries: rows group by their cycle column when there is one; a long file is cut at its charging
//!   runs into discharge records, each with the rest before its load and the relaxation after it; gaps
//!   (a time step over [`ReadOptions::gap_factor`] median steps) are kept and noted.
//!
//! Bad input never passes silently: files named in the metadata but absent are skipped and counted, non-finite or
//! non-numeric fields are errors naming file and line, time must increase (two rows written in the wrong order are
//! read in time order, said), a metadata row may name only a bare file in `data/`. Error lines are the lines
//! records start on (CRLF and blank lines counted); file content in a message is shown escaped and shortened.
//! Through [`read_nasa_with`] and [`read_csv`] a bad record (cycle) is skipped and reported with its one-line error
//! while the others read; the older [`read_nasa`], [`read_nasa_record`] and [`read_generic`] keep their fixed sign
//! and fail on the first bad record. Records that end under load are told apart later by
//! [`crate::record::Discharge::windows_with_cutoff`] (complete at the cut-off, or truncated) and [`nasa_cutoff_v`]
//! gives a NASA cell's documented cut-off. Readers never fit and never print.

use crate::error::DoctorError;
use crate::record::{Discharge, CELSIUS_TO_KELVIN};
use bcal_common::text::shown;
use serde::Serialize;
use std::collections::BTreeMap;
use std::ops::{Range, RangeInclusive};
use std::path::{Path, PathBuf};

/// Fewest samples a record must hold to be worth a fit.
pub const MIN_SAMPLES: usize = 10;

/// Ambient temperature assumed for a generic CSV without a temperature column, deg C.
pub const DEFAULT_AMBIENT_C: f64 = 25.0;

use bcal_common::measured::{
    current_glitch, CELL_TEMPERATURE_RANGE_C, GLITCH_RUN_READINGS, LOADED_A, NEW_DISCHARGE_GAP_S,
};
pub use bcal_common::measured::{MAX_CELL_CURRENT_A, MAX_LOADED_S, MAX_RECORD_CHARGE_AH};

/// Least evidence the sign decision needs, V of voltage change (see [`SignEvidence`]).
pub const MIN_SIGN_EVIDENCE_V: f64 = 0.02;

/// Share of the evidence the decided sign needs (3 to 1).
pub const SIGN_AGREEMENT: f64 = 0.75;

/// Which sign of the measured current is discharge.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CurrentSign {
    /// Decided from the data per file ([`SignEvidence`]); a file it cannot decide is refused.
    #[default]
    Auto,
    /// Positive current discharges (the generic CSV's documented convention).
    DischargePositive,
    /// Negative current discharges (NASA's `Current_measured`; the Battery Data Format counts charge positive).
    DischargeNegative,
}

impl CurrentSign {
    /// Every option, in `--help` order.
    pub const ALL: [CurrentSign; 3] =
        [CurrentSign::Auto, CurrentSign::DischargePositive, CurrentSign::DischargeNegative];

    /// The option's name on the command line: `auto`, `discharge-positive`, `discharge-negative`.
    pub fn name(self) -> &'static str {
        match self {
            CurrentSign::Auto => "auto",
            CurrentSign::DischargePositive => "discharge-positive",
            CurrentSign::DischargeNegative => "discharge-negative",
        }
    }

    fn of(discharge_positive: bool) -> Self {
        if discharge_positive {
            CurrentSign::DischargePositive
        } else {
            CurrentSign::DischargeNegative
        }
    }
}

impl std::fmt::Display for CurrentSign {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for CurrentSign {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        CurrentSign::ALL.into_iter().find(|c| c.name() == s.trim()).ok_or_else(|| {
            format!("current sign `{}` is none of auto, discharge-positive, discharge-negative", shown(s, 40))
        })
    }
}

/// How [`read_csv`] and [`read_nasa_with`] read. Defaults suit NASA records and cycler exports.
#[derive(Clone, Debug, PartialEq)]
pub struct ReadOptions {
    /// Which sign of the current is discharge. Default [`CurrentSign::Auto`].
    pub current_sign: CurrentSign,
    /// Ambient temperature, deg C, for every record of a CSV (NASA takes its metadata's). Default: the
    /// file's ambient column, else each record's first temperature, else [`DEFAULT_AMBIENT_C`].
    pub ambient_c: Option<f64>,
    /// A sample discharges when its current exceeds this and charges below its negative, A. Default 0.05
    /// (the fit's `load_threshold_a`).
    pub load_threshold_a: f64,
    /// A current change above this between two samples is a load step (sign evidence), A. Default 0.2.
    pub step_threshold_a: f64,
    /// A time step longer than this many median steps of its record is a gap: kept, noted. Default 10.
    pub gap_factor: f64,
    /// A charging run at least this long splits a file into discharge records, s; shorter ones (a
    /// regenerative pulse) stay inside their record. Default 120.
    pub min_charge_split_s: f64,
    /// In a file without a cycle column, a gap in the readings longer than this, s, after which the cell
    /// reads at rest, also splits records (discharges logged without the charges between them); one after
    /// which it is still loaded (readings lost within a discharge) is kept and bridged. Default
    /// [`NEW_DISCHARGE_GAP_S`], as a live stream splits.
    pub min_gap_split_s: f64,
    /// Rest kept before a record's first load, s (a long file may rest for hours). Default 1800.
    pub max_rest_before_s: f64,
    /// Relaxation kept after a record's last load, s. Default 3600.
    pub max_rest_after_s: f64,
}

impl Default for ReadOptions {
    fn default() -> Self {
        Self {
            current_sign: CurrentSign::Auto,
            ambient_c: None,
            load_threshold_a: 0.05,
            step_threshold_a: 0.2,
            gap_factor: 10.0,
            min_charge_split_s: 120.0,
            min_gap_split_s: NEW_DISCHARGE_GAP_S,
            max_rest_before_s: 1800.0,
            max_rest_after_s: 3600.0,
        }
    }
}

/// Which sign a file was read with, and why.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SignChoice {
    pub file: PathBuf,
    /// True when positive current was read as discharge.
    pub discharge_positive: bool,
    /// True when the data decided ([`CurrentSign::Auto`]); false when the caller's option did.
    pub from_data: bool,
    /// The evidence the data gave (also computed when the caller decided).
    pub evidence: SignEvidence,
}

/// A record (or a whole file) skipped, with its one-line error.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Skipped {
    pub file: PathBuf,
    pub cycle: Option<u32>,
    pub reason: String,
}

/// What a read returned besides the records: what it skipped and why, and what it decided.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ReadReport {
    /// Files named in the metadata for the selected cell and cycles that are not on disk.
    pub missing_files: Vec<String>,
    /// Their cycle numbers, in the same order (empty for readers without cycles).
    pub missing_cycles: Vec<u32>,
    /// Discharge rows of the selected cell in the metadata (present or not) inside the cycle range.
    pub rows_selected: usize,
    /// `nasa`, `generic` or `bdf` (the vocabulary of the columns read; empty for the older readers).
    pub format: &'static str,
    /// The sign each file was read with.
    pub signs: Vec<SignChoice>,
    /// Unit conversions made, one line per column.
    pub units: Vec<String>,
    /// Records skipped while the others were read.
    pub skipped: Vec<Skipped>,
    /// Everything else worth saying: gaps kept, segments dropped, a sign against the format's convention.
    pub notes: Vec<String>,
    /// When each record read started on the source's clock (NASA: `start_time` in metadata.csv, as seconds
    /// since 1970 read as UTC; a CSV: its time column at the record's first sample), for the lifetime
    /// diagnosis's rest between discharges ([`crate::lifetime`]). Records whose start is unknown are absent.
    pub starts: Vec<RecordStart>,
}

/// When a record started, s on the source's clock (only differences between records of one session mean
/// anything).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RecordStart {
    pub cycle: u32,
    pub start_s: f64,
    /// The logger session whose clock `start_s` is on (a CSV's logger that restarted starts another, 0 first):
    /// no rest is taken between records of two sessions.
    pub session: u32,
}

/// The step of a cell's record numbering, the one its consecutive records read take most (1 for NASA's
/// discharges; 2 for a log that numbers charges and discharges alike and keeps only the discharges, 1, 3,
/// 5, ...): the record before another is one step back (none where that one was not read).
pub fn numbering_step(starts: &[RecordStart]) -> u32 {
    let mut cycles: Vec<u32> = starts.iter().map(|s| s.cycle).collect();
    cycles.sort_unstable();
    cycles.dedup();
    let mut steps: Vec<u32> = cycles.windows(2).map(|w| w[1] - w[0]).collect();
    steps.sort_unstable();
    steps.get(steps.len().saturating_sub(1) / 2).copied().unwrap_or(1)
}

/// Parses NASA's `start_time`, a MATLAB date vector printed by numpy (`[2008. 4. 2. 15. 25. 41.593]` or
/// `[2.0080e+03 4.0000e+00 ...]`), into seconds since 1970-01-01 read as UTC. `None` unless it holds six
/// finite numbers forming a calendar date and time.
pub fn parse_matlab_datevec(text: &str) -> Option<f64> {
    let inner = text.trim().strip_prefix('[')?.strip_suffix(']')?;
    let v: Vec<f64> = inner
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|s| !s.is_empty())
        .map(str::parse)
        .collect::<Result<_, _>>()
        .ok()?;
    let [y, mo, d, h, mi, sec] = <[f64; 6]>::try_from(v).ok()?;
    let whole = |x: f64, lo: f64, hi: f64| (x.fract() == 0.0 && (lo..=hi).contains(&x)).then_some(x as i64);
    let (y, mo, d, h, mi) = (
        whole(y, 1900.0, 2200.0)?,
        whole(mo, 1.0, 12.0)?,
        whole(d, 1.0, 31.0)?,
        whole(h, 0.0, 23.0)?,
        whole(mi, 0.0, 59.0)?,
    );
    if !(0.0..61.0).contains(&sec) {
        return None;
    }
    // Days from 1970-01-01 to the civil date (H. Hinnant's days_from_civil).
    let yy = if mo <= 2 { y - 1 } else { y };
    let era = yy.div_euclid(400);
    let yoe = yy - era * 400;
    let doy = (153 * (mo + if mo > 2 { -3 } else { 9 }) + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    Some(days as f64 * 86_400.0 + (h * 3600 + mi * 60) as f64 + sec)
}

impl ReadReport {
    /// The report as lines for a person: the sign decisions condensed per sign, unit conversions, skipped
    /// records, notes. The CLI prints these; the library never does.
    pub fn summary(&self) -> Vec<String> {
        let mut out = Vec::new();
        if !self.missing_files.is_empty() {
            out.push(format!(
                "{} of {} files named in the metadata are missing and skipped (first: {})",
                self.missing_files.len(),
                self.rows_selected,
                self.missing_files[0]
            ));
        }
        for positive in [true, false] {
            let these: Vec<&SignChoice> = self.signs.iter().filter(|s| s.discharge_positive == positive).collect();
            if these.is_empty() {
                continue;
            }
            let from_data = these.iter().filter(|s| s.from_data).count();
            let shares: Vec<f64> = these.iter().filter_map(|s| s.evidence.share_for(positive)).collect();
            let lo = shares.iter().copied().fold(f64::INFINITY, f64::min);
            let why = if from_data == 0 {
                "as asked (--current-sign)".to_string()
            } else if shares.is_empty() {
                format!("decided from the data in {from_data}")
            } else {
                format!(
                    "decided from the data in {from_data} (the voltage falls under that current and steps down as it \
                     rises: at least {:.0} % of the evidence)",
                    100.0 * lo
                )
            };
            out.push(format!(
                "current sign: {} in {} file{}, {why}",
                if positive { "discharge positive" } else { "discharge negative" },
                these.len(),
                if these.len() == 1 { "" } else { "s" }
            ));
        }
        out.extend(self.units.iter().map(|u| format!("unit: {u}")));
        out.extend(self.skipped.iter().map(|s| match s.cycle {
            Some(c) => format!("skipped: record {c}: {}", s.reason),
            None => format!("skipped: {}", s.reason),
        }));
        out.extend(self.notes.iter().cloned());
        out
    }
}

/// Parses `A..B` (inclusive) into a cycle range.
pub fn parse_cycle_range(text: &str) -> Result<RangeInclusive<u32>, DoctorError> {
    let bad = || DoctorError::BadRange { text: text.to_string() };
    let (a, b) = text.split_once("..").ok_or_else(bad)?;
    let a: u32 = a.trim().parse().map_err(|_| bad())?;
    let b: u32 = b.trim().trim_start_matches('=').parse().map_err(|_| bad())?;
    // Cycle 0 is a cycle where a CSV's cycle column counts from 0 (NASA's numbering has none, and selects none).
    if b < a {
        return Err(bad());
    }
    Ok(a..=b)
}

/// Reads the discharges of `cell` whose cycle number (1-based order of the cell's discharge rows in
/// `metadata.csv`) lies in `cycles` (all when `None`). Rows whose file is absent are skipped and listed.
/// Current is read negative while discharging (NASA's sign); the first bad record fails the read: with the first by
/// line of what the lenient reader reads past (a glitch, rows out of order, written twice or at one time, a damaged
/// end, an empty field), or with what it refuses too (a unit, a voltage out of a cell's range under load).
pub fn read_nasa(
    root: &Path,
    cell: &str,
    cycles: Option<&RangeInclusive<u32>>,
) -> Result<(Vec<Discharge>, ReadReport), DoctorError> {
    let opts = ReadOptions { current_sign: CurrentSign::DischargeNegative, ..ReadOptions::default() };
    nasa_folder(root, cell, cycles, &opts, true)
}

/// [`read_nasa`] with options: the sign from [`ReadOptions::current_sign`] ([`CurrentSign::Auto`] finds
/// NASA's negative discharge current from each record's data); a record that fails (unreadable, no
/// discharge, a sign it cannot decide, too short, millivolts) is skipped and listed in
/// [`ReadReport::skipped`] while the others read; the read fails only when no record is left, with the first
/// record's error. Gaps in time are noted.
pub fn read_nasa_with(
    root: &Path,
    cell: &str,
    cycles: Option<&RangeInclusive<u32>>,
    opts: &ReadOptions,
) -> Result<(Vec<Discharge>, ReadReport), DoctorError> {
    nasa_folder(root, cell, cycles, opts, false)
}

fn nasa_folder(
    root: &Path,
    cell: &str,
    cycles: Option<&RangeInclusive<u32>>,
    opts: &ReadOptions,
    strict: bool,
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
    // Optional: without it the records read as before and the lifetime diagnosis has no schedule.
    let c_start = headers.iter().position(|h| h.trim() == "start_time");
    // (test_id, filename, ambient_c, capacity_ah, start, metadata line) of the cell's discharges.
    let mut rows = Vec::new();
    let mut bad_starts = Vec::new();
    // The cell's rows of a type the layout does not have: (line, type).
    let mut other_types: Vec<(u64, String)> = Vec::new();
    // A metadata file the logger stopped writing (a half row at its end) is read up to it, as a data file is.
    let meta_read = read_rows(&meta_path, &mut rdr, &mut lines, 1, |rec, line| {
        // Ids and types as a person or a spreadsheet may have written them: spaces around, another case.
        if !rec.get(c_cell).is_some_and(|id| id.trim().eq_ignore_ascii_case(cell.trim())) {
            return Ok(Taken::Kept);
        }
        let kind = rec.get(c_type).unwrap_or("").trim();
        if !kind.eq_ignore_ascii_case("discharge") {
            if !["charge", "impedance"].iter().any(|k| kind.eq_ignore_ascii_case(k)) {
                other_types.push((line, kind.to_string()));
            }
            return Ok(Taken::Kept);
        }
        let test_id = number(rec, c_test, "test_id", &meta_path, line)?;
        let ambient_c = number(rec, c_amb, "ambient_temperature", &meta_path, line)?;
        let capacity_ah =
            rec.get(c_cap).and_then(|s| s.trim().parse::<f64>().ok()).filter(|c| c.is_finite() && *c > 0.0);
        let file = rec.get(c_file).unwrap_or("");
        // A bare file name in `data/`: a path (`../x`, `/etc/x`, `sub/x`) would read outside the folder.
        let mut parts = Path::new(file).components();
        if !matches!((parts.next(), parts.next()), (Some(std::path::Component::Normal(_)), None)) {
            return Err(DoctorError::NotAFileName { path: meta_path.clone(), line, value: shown(file, 80) });
        }
        let start_s = c_start.and_then(|c| rec.get(c)).and_then(parse_matlab_datevec);
        if let (Some(c), None) = (c_start, start_s) {
            bad_starts.push(format!("line {line}: `{}`", shown(rec.get(c).unwrap_or(""), 40)));
        }
        rows.push((test_id, file.to_string(), ambient_c, capacity_ah, start_s));
        Ok(Taken::Kept)
    })?;
    if strict {
        if let Some(damage) = meta_read.damaged_end {
            return Err(damage.error);
        }
    }
    if rows.is_empty() {
        return Err(DoctorError::NothingSelected {
            why: format!("{} has no discharge rows for cell `{cell}`", meta_path.display()),
        });
    }
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut report = ReadReport { format: if strict { "" } else { "nasa" }, ..ReadReport::default() };
    report.notes.extend(meta_read.notes());
    if let Some((line, kind)) = other_types.first() {
        report.notes.push(format!(
            "{}, line {line}: type `{}` is none of discharge, charge or impedance; {} such row{} of cell `{cell}` left \
             out (a discharge's row must say `discharge`)",
            meta_path.display(),
            shown(kind, 40),
            other_types.len(),
            if other_types.len() == 1 { "" } else { "s" }
        ));
    }
    if !bad_starts.is_empty() {
        report.notes.push(format!(
            "{}: field `start_time` is not a date vector [Y M D h m s] on {} of the cell's discharge rows (first: {}); \
             the rest before those discharges is unknown",
            meta_path.display(),
            bad_starts.len(),
            bad_starts[0]
        ));
    }
    let mut out = Vec::new();
    let mut first_error = None;
    for (k, (_, file, ambient_c, capacity_ah, start_s)) in rows.into_iter().enumerate() {
        let cycle = k as u32 + 1;
        if cycles.is_some_and(|r| !r.contains(&cycle)) {
            continue;
        }
        report.rows_selected += 1;
        let path = root.join("data").join(&file);
        if !path.is_file() {
            report.missing_files.push(file);
            report.missing_cycles.push(cycle);
            continue;
        }
        let read = nasa_record(&path, cell, cycle, ambient_c + CELSIUS_TO_KELVIN, opts).and_then(|read| {
            if strict {
                return whole(read).map(|(d, sign)| (d, sign, RowsRead::default()));
            }
            has_discharge(&read.0, opts, &read.1)?;
            Ok(read)
        });
        match read {
            Ok((mut d, sign, rows)) => {
                d.stated_capacity_ah = capacity_ah;
                report.starts.extend(start_s.map(|start_s| RecordStart { cycle, start_s, session: 0 }));
                if !strict {
                    report.notes.extend(rows.notes());
                    report.notes.extend(gap_note(&d, opts.gap_factor));
                    report.signs.push(sign);
                }
                out.push(d);
            }
            Err(e) if strict => return Err(e),
            Err(e) => {
                report.skipped.push(Skipped { file: path, cycle: Some(cycle), reason: e.to_string() });
                first_error.get_or_insert(e);
            }
        }
    }
    report.notes.extend(sign_outliers(&report.signs));
    match first_error {
        Some(e) if out.is_empty() => Err(e),
        _ => Ok((out, report)),
    }
}

/// A note naming the files of a folder whose current sign the data decided against most of the others' (a
/// file exported with the other convention, or one whose evidence misled: worth a look either way).
fn sign_outliers(signs: &[SignChoice]) -> Option<String> {
    let positive: Vec<&SignChoice> = signs.iter().filter(|s| s.discharge_positive).collect();
    let negative: Vec<&SignChoice> = signs.iter().filter(|s| !s.discharge_positive).collect();
    let (few, most) = if positive.len() <= negative.len() { (positive, negative) } else { (negative, positive) };
    if few.is_empty() || few.len() == most.len() || !few.iter().all(|s| s.from_data) {
        return None;
    }
    let shown: Vec<String> = few.iter().take(5).map(|s| s.file.display().to_string()).collect();
    Some(format!(
        "current sign: {} of the cell's {} files read as {} from their data, the other {} as {}: {}{}; check \
         {} export (--current-sign sets one sign for all)",
        few.len(),
        signs.len(),
        CurrentSign::of(few[0].discharge_positive).name(),
        most.len(),
        CurrentSign::of(most[0].discharge_positive).name(),
        shown.join(", "),
        if few.len() > shown.len() { ", ..." } else { "" },
        if few.len() == 1 { "that file's" } else { "those files'" }
    ))
}

/// Reads one NASA discharge file (`Voltage_measured`, `Current_measured` negative while discharging,
/// `Temperature_measured` deg C, `Time` s).
pub fn read_nasa_record(path: &Path, cell: &str, cycle: u32, ambient_k: f64) -> Result<Discharge, DoctorError> {
    let opts = ReadOptions { current_sign: CurrentSign::DischargeNegative, ..ReadOptions::default() };
    nasa_record(path, cell, cycle, ambient_k, &opts).and_then(whole).map(|(d, _)| d)
}

/// [`read_nasa_record`] with the sign from `opts` (reported), refusing a record without discharge.
pub fn read_nasa_record_with(
    path: &Path,
    cell: &str,
    cycle: u32,
    ambient_k: f64,
    opts: &ReadOptions,
) -> Result<(Discharge, SignChoice), DoctorError> {
    let (d, sign) = whole(nasa_record(path, cell, cycle, ambient_k, opts)?)?;
    has_discharge(&d, opts, &sign)?;
    Ok((d, sign))
}

/// A NASA record and what [`read_rows`] met reading it.
type NasaRecord = (Discharge, SignChoice, RowsRead);

fn nasa_record(
    path: &Path,
    cell: &str,
    cycle: u32,
    ambient_k: f64,
    opts: &ReadOptions,
) -> Result<NasaRecord, DoctorError> {
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
    let mut line_of = Vec::new();
    let mut unconfirmed: Option<UnconfirmedSwap> = None;
    let mut rows = read_rows(path, &mut rdr, &mut lines, MIN_SAMPLES, |rec, line| {
        let time_s = number(rec, cs, "Time", path, line)?;
        let voltage_v = number(rec, cv, "Voltage_measured", path, line)?;
        // As measured for now; the sign is decided on the whole record below.
        let current_a = number(rec, ci, "Current_measured", path, line)?;
        // NaN while a sensor is out: filled below, and said.
        let temperature_k = match missing(rec, ct) {
            true => f64::NAN,
            false => number(rec, ct, "Temperature_measured", path, line)? + CELSIUS_TO_KELVIN,
        };
        if let Err(e) = check_time(&d.time_s, time_s, path, line) {
            let same = |k: usize| {
                same_bits(&[d.voltage_v[k], d.current_a[k], temps[k]], &[voltage_v, current_a, temperature_k])
            };
            let between = |k: usize| (k == 0 || d.time_s[k - 1] < time_s) && time_s < d.time_s[k];
            return match d.time_s.binary_search_by(|t| t.total_cmp(&time_s)) {
                Ok(k) if same(k) => Ok(Taken::Again(e)),
                Ok(k) if k + 1 == d.time_s.len() => Ok(Taken::SameTime(e)),
                Err(k) if k + 1 == d.time_s.len() && between(k) => match unconfirmed.take() {
                    Some(first) => Err(first.error(path)),
                    None => {
                        let previous_s = d.time_s[k];
                        unconfirmed = Some(UnconfirmedSwap { line, time_s, previous_s });
                        d.time_s.insert(k, time_s);
                        d.voltage_v.insert(k, voltage_v);
                        d.current_a.insert(k, current_a);
                        temps.insert(k, temperature_k);
                        line_of.insert(k, line);
                        Ok(Taken::Swapped(e))
                    }
                },
                _ => Err(unconfirmed.take().map_or(e, |first| first.error(path))),
            };
        }
        unconfirmed = None;
        d.time_s.push(time_s);
        d.voltage_v.push(voltage_v);
        d.current_a.push(current_a);
        temps.push(temperature_k);
        line_of.push(line);
        Ok(Taken::Kept)
    })?;
    if let Some(first) = unconfirmed {
        // Nothing after the swap confirmed it: the reading it went before (now the last) is left out.
        let time_s = d.time_s.pop().expect("a swap went before a reading");
        d.voltage_v.pop();
        d.current_a.pop();
        temps.pop();
        let line = line_of.pop().expect("a line per reading");
        rows.unconfirmed_note = Some(first.left_out_note(path, line, time_s));
    }
    // The frozen end first (a temperature left empty repeats as itself), so that the fill counts only the
    // readings kept.
    if let Some(frozen) = frozen_end(&mut d, &mut line_of) {
        if d.len() < MIN_SAMPLES {
            return Err(frozen.error);
        }
        let after = rows.damaged_end.as_ref().map_or(0, |e| e.records);
        rows.damaged_end = Some(DamagedEnd { records: frozen.records + after, ..frozen });
    }
    let first_missing = d.temperature_k.as_ref().and_then(|t| t.iter().position(|t| !t.is_finite()));
    rows.temperature_note = fill_missing(&mut d, &line_of, "Temperature_measured")?
        .map(|note| (line_of[first_missing.expect("a note only where a temperature was missing")], note));
    let mut d = validate(d)?;
    // Units the layout does not have, whatever the sign (a current in mA reads as no sign at all): a current
    // above what a cell carries, and time in ms (more charge than a cell holds, days under load).
    let in_ma = |current_a: &[f64]| DoctorError::SuspectUnit {
        path: path.to_path_buf(),
        column: "Current_measured".into(),
        why: format!("peaks at {} A, more than a cell carries ({MAX_CELL_CURRENT_A} A)", short(peak_abs(current_a))),
        hint: "NASA's layout gives current in A: if it is in mA, divide it by 1000".into(),
    };
    if beyond_a_cell(&d.current_a) > READ_GLITCH_RUN_READINGS {
        return Err(in_ma(&d.current_a));
    }
    let magnitude_a: Vec<f64> = d.current_a.iter().map(|i| i.abs()).collect();
    if let Some(why) = implausible(&d, &magnitude_a) {
        return Err(DoctorError::SuspectUnit {
            path: path.to_path_buf(),
            column: "Time".into(),
            why,
            hint: "NASA's layout gives time in s: if it is in ms, divide it by 1000".into(),
        });
    }
    // Current glitches after the units are checked (a square wave in mA would read as pulses the voltage does
    // not follow, and left out, as no load) and before the sign is decided (said as the file has them).
    rows.glitched = leave_out_glitches(&mut d, &mut line_of);
    if d.len() < MIN_SAMPLES {
        return Err(DoctorError::TooFewSamples { path: d.source.clone(), rows: d.len(), min: MIN_SAMPLES });
    }
    if beyond_a_cell(&d.current_a) > 0 {
        return Err(in_ma(&d.current_a));
    }
    voltage_glitch(&d, &line_of)?;
    if opts.current_sign == CurrentSign::Auto && d.current_a.iter().all(|i| i.abs() <= opts.load_threshold_a) {
        return Err(no_current(path, opts));
    }
    let mut evidence = SignEvidence::default();
    evidence.add_record(&d.voltage_v, &d.current_a, opts);
    let sign = decide_sign(path, evidence, opts.current_sign)?;
    if !sign.discharge_positive {
        d.current_a.iter_mut().for_each(|i| *i = -*i);
    }
    Ok((d, sign, rows))
}

/// One record read strictly: whatever the lenient readers read and say (a damaged end, a reading written twice, rows
/// written in the wrong order, a second reading at one time, a current glitch, a temperature filled) fails it as a bad
/// record anywhere does, naming the first of those by line.
fn whole((d, sign, rows): NasaRecord) -> Result<(Discharge, SignChoice), DoctorError> {
    let temperature = rows.temperature_note.map(|(line, note)| {
        (line, DoctorError::MissingValues { why: format!("refused by the strict reader: {note}") })
    });
    // An error without a line is a damaged end's, at the file's end.
    let refusals = [
        rows.first_swapped,
        rows.first_same_time,
        rows.glitched.map(|g| g.error),
        rows.first_again,
        rows.damaged_end.map(|e| e.error),
    ]
    .into_iter()
    .flatten()
    .map(|e| (e.line().unwrap_or(u64::MAX), e))
    .chain(temperature);
    match refusals.min_by_key(|(line, _)| *line) {
        Some((_, e)) => Err(e),
        None => Ok((d, sign)),
    }
}

/// Readings a NASA logger that froze leaves at a record's end: the same reading, to the last of the layout's
/// sixteen digits, over and over under load while the time runs on (a live cell's noise never repeats so).
/// The record keeps the first of them; the rest is returned as its damaged end.
fn frozen_end(d: &mut Discharge, line_of: &mut Vec<u64>) -> Option<DamagedEnd> {
    let n = d.len();
    let temps = d.temperature_k.as_ref()?;
    let reading = |k: usize| [d.voltage_v[k], d.current_a[k], temps[k]];
    let same = |k: usize| same_bits(&reading(k), &reading(k - 1));
    let first = (1..n).rev().take_while(|&k| same(k)).last()?;
    let readings = n - first;
    if readings < FROZEN_READINGS || d.current_a[first].abs() <= LOADED_A {
        return None;
    }
    let span_s = d.time_s[n - 1] - d.time_s[first - 1];
    let error = DoctorError::FrozenEnd { path: d.source.clone(), line: line_of[first], readings, span_s };
    d.time_s.truncate(first);
    d.voltage_v.truncate(first);
    d.current_a.truncate(first);
    d.temperature_k.as_mut().expect("checked above").truncate(first);
    line_of.truncate(first);
    Some(DamagedEnd { error, records: readings })
}

/// Refuses a reading whose voltage a logger got wrong while the load is on (from the first loaded reading to
/// the last, whatever the sign), naming its line: a voltage outside a cell's (a 0 V sample, which would be read
/// as the cut-off and end the discharge there). Readings at rest before or after the load (a record that starts
/// before its cell is connected) are read as they are. Current glitches are left out before ([`current_glitches`]).
fn voltage_glitch(d: &Discharge, line_of: &[u64]) -> Result<(), DoctorError> {
    let (v, i) = (&d.voltage_v, &d.current_a);
    let loaded = |i: &f64| i.abs() > LOADED_A;
    let first = i.iter().position(loaded).unwrap_or(0);
    let last = i.iter().rposition(loaded).map_or(0, |k| k + 1);
    let outside = |v: &f64| !(CELL_VOLTAGE_V[0]..=CELL_VOLTAGE_V[1]).contains(v);
    match v[first..last.max(first)].iter().position(outside).map(|k| first + k) {
        Some(k) => Err(DoctorError::VoltageGlitch { path: d.source.clone(), line: line_of[k], voltage_v: v[k] }),
        None => Ok(()),
    }
}

/// A run of readings whose current a logger got wrong ([`current_glitches`]): `first..first + readings`, off the
/// level of readings `neighbours`, which agree (either side of the run; at a record's first or last readings,
/// the two on its one side).
#[derive(Clone, Copy, Debug)]
struct GlitchRun {
    first: usize,
    readings: usize,
    neighbours: [usize; 2],
}

/// Readings in a row a reader takes for one current glitch ([`current_glitches`]). More than a live stream's
/// [`GLITCH_RUN_READINGS`]: a reader sees both sides of a run, and a current at least 5 A off two neighbours that
/// agree, the voltage not following on any of its readings, is no cell's (a load step whose voltage sample lags is
/// unfollowed on its first reading only). A longer run is read as it is; a shorter hole than six readings raises
/// no gap note.
const READ_GLITCH_RUN_READINGS: usize = 5;

/// How many of the currents `current_a` lie beyond what a cell carries ([`MAX_CELL_CURRENT_A`]): more than a glitch
/// spans says the unit is not amperes (a glitch's few are left out first, and any left after refuse the record).
fn beyond_a_cell(current_a: &[f64]) -> usize {
    current_a.iter().filter(|i| i.abs() > MAX_CELL_CURRENT_A).count()
}

/// The largest magnitude of `values`.
fn peak_abs(values: &[f64]) -> f64 {
    values.iter().fold(0.0, |m, v| m.max(v.abs()))
}

/// The runs of one to [`READ_GLITCH_RUN_READINGS`] readings whose current lies at least
/// [`CURRENT_GLITCH_A`](bcal_common::measured::CURRENT_GLITCH_A) off the level of two neighbours that agree, on the
/// same side of it, the voltage not moving with them ([`current_glitch`]), within the readings `v`, `i` (volts,
/// amperes, either sign); and of up to [`GLITCH_RUN_READINGS`] at their first or last readings, against the two
/// nearest readings no run holds, where the current lies further from zero than theirs (a spike: seen from one
/// side, a current that falls toward zero is also a load switched off under a voltage sample that lags). A load
/// step whose voltage sample lags is none (its neighbours do not agree, and from its second reading on the voltage
/// has moved). Left out, a glitch is not read as a load: it cannot move a load-on or a cut-off, nor add charge.
fn current_glitches(v: &[f64], i: &[f64]) -> Vec<GlitchRun> {
    let n = i.len();
    let glitch = |first: usize, readings: usize, [a, b]: [usize; 2]| {
        let off = |j: usize| (i[j] - 0.5 * (i[a] + i[b]), v[j] - 0.5 * (v[a] + v[b]));
        let off_a = off(first).0;
        let agree = (i[a] - i[b]).abs() < 0.2 * off_a.abs();
        let run = (first..first + readings).all(|j| {
            let (o, moved_v) = off(j);
            o * off_a > 0.0 && current_glitch(o, moved_v)
        });
        (agree && run).then_some(GlitchRun { first, readings, neighbours: [a, b] })
    };
    let mut out: Vec<GlitchRun> = Vec::new();
    let mut k = 1;
    while k + 1 < n {
        match (1..=READ_GLITCH_RUN_READINGS).filter(|&r| k + r < n).find_map(|r| glitch(k, r, [k - 1, k + r])) {
            Some(g) => {
                out.push(g);
                k += g.readings + 1;
            }
            None => k += 1,
        }
    }
    let inside = |j: usize| out.iter().any(|g| (g.first..g.first + g.readings).contains(&j));
    // At an end the run is seen from one side only, as a live stream sees it: as short as the stream's, a spike.
    let at_end = |run: Range<usize>, mut clean: Vec<usize>| -> Option<GlitchRun> {
        if run.clone().any(inside) || clean.len() < 2 {
            return None;
        }
        clean.truncate(2);
        let level_a = 0.5 * (i[clean[0]] + i[clean[1]]).abs();
        let spike = run.clone().all(|j| i[j].abs() > level_a);
        glitch(run.start, run.len(), [clean[0], clean[1]]).filter(|_| spike)
    };
    let start = (1..=GLITCH_RUN_READINGS)
        .filter(|&r| r + 2 <= n)
        .find_map(|r| at_end(0..r, (r..n).filter(|&j| !inside(j)).take(2).collect()));
    let end = (1..=GLITCH_RUN_READINGS)
        .filter(|&r| r + 2 <= n)
        .find_map(|r| at_end(n - r..n, (0..n - r).rev().filter(|&j| !inside(j)).take(2).collect()));
    out.extend(start);
    out.extend(end);
    out.sort_by_key(|g| g.first);
    out
}

/// The error a strict reader refuses a record with for its first current glitch `g` (the record's readings `v`,
/// `i` as the file has them, `g`'s first line `line`), and that the readers' note tells.
fn glitch_error(path: &Path, line: u64, v: &[f64], i: &[f64], g: &GlitchRun) -> DoctorError {
    let [a, b] = g.neighbours;
    DoctorError::CurrentGlitch {
        path: path.to_path_buf(),
        line,
        current_a: i[g.first],
        readings: g.readings,
        before_a: i[a.min(b)],
        after_a: i[a.max(b)],
        moved_mv: 1e3 * (v[g.first] - 0.5 * (v[a] + v[b])).abs(),
    }
}

/// Readings a logger got wrong, left out of a record ([`current_glitches`]): the first one's error (which a
/// strict reader refuses the record with) and how many.
#[derive(Debug)]
struct Glitched {
    error: DoctorError,
    readings: usize,
}

/// Leaves the current glitches out of `d` (and their lines out of `line_of`), returning what was left out.
fn leave_out_glitches(d: &mut Discharge, line_of: &mut Vec<u64>) -> Option<Glitched> {
    let runs = current_glitches(&d.voltage_v, &d.current_a);
    let first = runs.first()?;
    let error = glitch_error(&d.source, line_of[first.first], &d.voltage_v, &d.current_a, first);
    let keep = outside_runs(&runs, d.len());
    retain_by(&mut d.time_s, &keep);
    retain_by(&mut d.voltage_v, &keep);
    retain_by(&mut d.current_a, &keep);
    if let Some(t) = d.temperature_k.as_mut() {
        retain_by(t, &keep);
    }
    retain_by(line_of, &keep);
    Some(Glitched { error, readings: keep.iter().filter(|k| !**k).count() })
}

/// Per reading of `n`, whether it lies outside every run of `runs`.
fn outside_runs(runs: &[GlitchRun], n: usize) -> Vec<bool> {
    let mut keep = vec![true; n];
    runs.iter().flat_map(|g| g.first..g.first + g.readings).for_each(|k| keep[k] = false);
    keep
}

/// Keeps the items of `v` whose flag in `keep` is set.
fn retain_by<T>(v: &mut Vec<T>, keep: &[bool]) {
    let mut flags = keep.iter();
    v.retain(|_| *flags.next().expect("one flag per item"));
}

/// The note a reader gives of the glitches it left out.
fn glitch_note(g: &Glitched) -> String {
    let more = match g.readings {
        1 => String::new(),
        n => format!(", {n} readings in all"),
    };
    let text = g.error.to_string();
    let text = text.strip_suffix("; fix or remove that row").unwrap_or(&text);
    format!("{text}: left out{more} (the readings around it read as they are)")
}

/// Repeats of one reading at a record's end that [`frozen_end`] reads as a frozen logger.
const FROZEN_READINGS: usize = 10;

/// Refuses a record in which no sample discharges.
fn has_discharge(d: &Discharge, opts: &ReadOptions, sign: &SignChoice) -> Result<(), DoctorError> {
    if d.current_a.iter().any(|i| *i > opts.load_threshold_a) {
        return Ok(());
    }
    Err(DoctorError::NoDischarge { path: d.source.clone(), threshold_a: opts.load_threshold_a, sign: sign_words(sign) })
}

/// No discharge because no current flows at all (the sign cannot matter).
fn no_current(path: &Path, opts: &ReadOptions) -> DoctorError {
    DoctorError::NoDischarge {
        path: path.to_path_buf(),
        threshold_a: opts.load_threshold_a,
        sign: "either sign (no current beyond it at all)".into(),
    }
}

fn sign_words(sign: &SignChoice) -> String {
    format!(
        "{} ({})",
        CurrentSign::of(sign.discharge_positive).name(),
        if sign.from_data { "decided from the data" } else { "as asked" }
    )
}

/// The documented discharge cut-off of a NASA PCoE cell (`B0006` -> 2.5 V), read from the experiment
/// descriptions `extra_infos/README_*.txt` of the folder `root`; `None` when the folder has none or they do
/// not name the cell. (In `../shared`: B0005 2.7 V, B0006 2.5 V, B0007 2.2 V, B0018 2.5 V, B0025 2.0 V,
/// B0029 2.0 V, B0055 2.5 V, ...)
pub fn nasa_cutoff_v(root: &Path, cell: &str) -> Option<f64> {
    let id: u32 = cell.trim().trim_start_matches(|c: char| c.is_ascii_alphabetic()).parse().ok()?;
    let mut files: Vec<PathBuf> = std::fs::read_dir(root.join("extra_infos"))
        .ok()?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("README") && n.ends_with(".txt"))
        })
        .collect();
    files.sort();
    files
        .iter()
        .filter_map(|p| std::fs::read_to_string(p).ok())
        .find_map(|text| parse_nasa_cutoffs(&text).into_iter().find(|(cell_id, _)| *cell_id == id).map(|(_, v)| v))
}

/// The cut-offs a NASA experiment description states, as (battery number, V): sentences such as "... until
/// the battery voltage fell to 2.7V, 2.5V, 2.2V and 2.5V for batteries 5 6 7 and 18 respectively", "...
/// the discharge runs were stopped at 2V, 2.2V, 2.5V and 2.7V for batteries 41, 42, 43 and 44" or "For
/// battery 36 discharge was done at 2A until voltage fell to 2.7V".
pub fn parse_nasa_cutoffs(text: &str) -> Vec<(u32, f64)> {
    let mut out = Vec::new();
    let text = text.replace(['\n', '\r'], " ");
    for sentence in text.split(". ") {
        let lower = sentence.to_lowercase();
        let words: Vec<&str> = lower.split_whitespace().collect();
        let Some(at) = words.windows(2).position(|w| matches!(w, ["fell", "to"] | ["stopped", "at"])) else {
            continue;
        };
        let clean = |w: &str| w.trim_matches(|c: char| matches!(c, ',' | '.' | ';' | '(' | ')' | '#')).to_string();
        let volts: Vec<f64> = words[at + 2..]
            .iter()
            .map(|w| clean(w))
            .filter(|w| w != "and")
            .map_while(|w| w.strip_suffix('v').and_then(|n| n.parse::<f64>().ok()))
            .collect();
        let ids: Vec<u32> = words
            .iter()
            .enumerate()
            .filter(|(_, w)| w.starts_with("batter"))
            .map(|(k, _)| {
                words[k + 1..].iter().map(|w| clean(w)).filter(|w| w != "and").map_while(|w| w.parse().ok()).collect()
            })
            .find(|ids: &Vec<u32>| !ids.is_empty())
            .unwrap_or_default();
        if volts.len() == ids.len() {
            out.extend(ids.into_iter().zip(volts));
        } else if volts.len() == 1 {
            out.extend(ids.into_iter().map(|id| (id, volts[0])));
        }
    }
    out
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

/// Reads any CSV of measured samples whose columns name time, voltage and current (see the module doc: the generic
/// names, the Battery Data Format's labels or machine names, NASA's record names, units in the names), with optional
/// cell temperature, ambient temperature and cycle columns. Units are converted or refused, the sign comes from
/// `opts.current_sign` (decided on the whole file under `Auto`), rows group by cycle when there is a cycle column, and
/// each group (or the whole file) is cut at its charging runs into discharge records: each holds the rest before its
/// load, the load (with any rests inside it) and the relaxation after, its time counted from its first sample. A cycle
/// holding two discharges keeps the larger and notes the other; without a cycle column records are numbered 1, 2, ...
/// in time order, and a time that steps back before the last two readings and runs on from there (a logger restarted)
/// starts a new session on its own clock, noted ([`RecordStart::session`]: no rest is known across it).  File-level
/// problems (unreadable, missing columns, a field that is not a number, time going backwards beyond two rows written in
/// the wrong order, which are read in time order and noted, or a restart without a cycle column; with one, within a
/// cycle), a unit it cannot read or a current too large to be amperes, a sign it cannot decide, no discharge at all)
/// fail the read naming the file (and line). A record that fails on its own (too few samples, millivolts, time in
/// milliseconds) is skipped and listed in [`ReadReport::skipped`]; the read fails only when none is left.
pub fn read_csv(path: &Path, opts: &ReadOptions) -> Result<(Vec<Discharge>, ReadReport), DoctorError> {
    let bytes = read_file(path)?;
    let mut lines = Lines::new(&bytes);
    let delimiter = delimiter(&bytes);
    let mut rdr = csv::ReaderBuilder::new().delimiter(delimiter).from_reader(bytes.as_slice());
    let headers = rdr.headers().map_err(|e| csv_error(path, e, &mut lines))?.clone();
    let mut cols = Columns::find(&headers, path)?;
    // Where the comma does not separate fields it may be the decimal mark (a spreadsheet's locale).
    let decimal_comma = decimal_comma(&bytes, delimiter);
    for c in [&mut cols.time, &mut cols.voltage, &mut cols.current]
        .into_iter()
        .chain(&mut cols.temperature)
        .chain(&mut cols.ambient)
        .chain(&mut cols.cycle)
    {
        c.decimal_comma = decimal_comma;
    }
    let mut groups: BTreeMap<u32, Vec<Row>> = BTreeMap::new();
    let mut line_of: BTreeMap<u32, Vec<u64>> = BTreeMap::new();
    let mut unconfirmed: BTreeMap<u32, Option<UnconfirmedSwap>> = BTreeMap::new();
    // Without a cycle column, each logger session (a clock restarted) is a group of its own.
    let mut session = 0u32;
    let mut restart: Option<Restart> = None;
    let mut restart_notes = Vec::new();
    let rows_read = read_rows(path, &mut rdr, &mut lines, MIN_SAMPLES, |rec, line| {
        let cycle = match &cols.cycle {
            Some(c) => {
                let v = number(rec, c.index, &c.header, path, line)?;
                // Beyond u32 the cast would saturate and merge distinct cycles.
                if v < 0.0 || v.fract() != 0.0 || v > f64::from(u32::MAX) {
                    return Err(bad_field(path, line, &c.header, rec.get(c.index).unwrap_or("")));
                }
                v as u32
            }
            None => session,
        };
        let row = Row {
            time_s: cols.time.value(rec, path, line)?,
            voltage_v: cols.voltage.value(rec, path, line)?,
            current_a: cols.current.value(rec, path, line)?,
            // NaN while a sensor is out: filled per record, and said.
            temperature_c: cols
                .temperature
                .as_ref()
                .map(|c| if missing(rec, c.index) { Ok(f64::NAN) } else { c.value(rec, path, line) })
                .transpose()?,
            ambient_c: cols.ambient.as_ref().map(|c| c.value(rec, path, line)).transpose()?,
        };
        // The reading after a restart confirms it by coming after it and before the clock it left; one that
        // does not leaves the reading that stepped back a time the logger got wrong, refused as before. One at
        // the restart's own time (written again, or a clock coarser than the logging) waits for the next.
        if let Some(r) = restart.filter(|r| row.time_s != r.time_s) {
            restart = None;
            if !(r.time_s < row.time_s && row.time_s <= r.previous_s) {
                return Err(r.error(path));
            }
            restart_notes.push(r.note(path));
        }
        let rows = groups.entry(cycle).or_default();
        let unconfirmed = unconfirmed.entry(cycle).or_default();
        if let Some(previous_s) = rows.last().map(|r| r.time_s).filter(|p| row.time_s <= *p) {
            let e = DoctorError::TimeNotIncreasing { path: path.to_path_buf(), line, time_s: row.time_s, previous_s };
            let between = |k: usize| (k == 0 || rows[k - 1].time_s < row.time_s) && row.time_s < rows[k].time_s;
            return match rows.binary_search_by(|r| r.time_s.total_cmp(&row.time_s)) {
                // Written again: a logger's buffer sends its last readings again, not the session's first hours
                // back (without a cycle column, a clock back there with a like reading is a restart, below).
                Ok(k) if rows[k].same(&row) && (cols.cycle.is_some() || previous_s - row.time_s <= AGAIN_WITHIN_S) => {
                    Ok(Taken::Again(e))
                }
                Ok(k) if k + 1 == rows.len() => Ok(Taken::SameTime(e)),
                Err(k) if k + 1 == rows.len() && between(k) => match unconfirmed.take() {
                    Some(first) => Err(first.error(path)),
                    None => {
                        *unconfirmed = Some(UnconfirmedSwap { line, time_s: row.time_s, previous_s });
                        rows.insert(k, row);
                        line_of.entry(cycle).or_default().insert(k, line);
                        Ok(Taken::Swapped(e))
                    }
                },
                // Before the last two readings, with no swap pending and no cycle column: a logger restarted (its
                // clock from 0, or set back), the readings from here a new session, once the next confirms it.
                Ok(k) | Err(k) if k + 1 < rows.len() && unconfirmed.is_none() && cols.cycle.is_none() => {
                    session += 1;
                    restart = Some(Restart { line, time_s: row.time_s, previous_s });
                    groups.entry(session).or_default().push(row);
                    line_of.entry(session).or_default().push(line);
                    Ok(Taken::Kept)
                }
                _ => Err(unconfirmed.take().map_or(e, |first| first.error(path))),
            };
        }
        *unconfirmed = None;
        rows.push(row);
        line_of.entry(cycle).or_default().push(line);
        Ok(Taken::Kept)
    })?;
    // A restart at the file's last reading: nothing confirms it, and that reading is left out.
    if let Some(r) = restart {
        groups.remove(&session);
        line_of.remove(&session);
        restart_notes.push(r.left_out_note(path));
    }
    let mut order_notes = Vec::new();
    for (cycle, first) in unconfirmed.into_iter().filter_map(|(c, f)| f.map(|f| (c, f))) {
        let row = groups.get_mut(&cycle).and_then(Vec::pop).expect("a swap went before a reading");
        let line = line_of.get_mut(&cycle).and_then(Vec::pop).expect("a line per reading");
        order_notes.push(first.left_out_note(path, line, row.time_s));
    }
    if groups.is_empty() {
        return Err(DoctorError::TooFewSamples { path: path.to_path_buf(), rows: 0, min: MIN_SAMPLES });
    }
    let currents = |groups: &BTreeMap<u32, Vec<Row>>, cycle: u32| -> Vec<f64> {
        groups.get(&cycle).map_or_else(Vec::new, |rows| rows.iter().map(|r| r.current_a).collect())
    };
    let peak_a =
        |groups: &BTreeMap<u32, Vec<Row>>| groups.values().flatten().fold(0.0_f64, |m, r| m.max(r.current_a.abs()));
    let in_ma = |peak_a: f64| {
        let hint = if cols.current.unit == "A" {
            "if it is in mA, name the column current_ma (or `Current / mA`), or divide it by 1000".to_string()
        } else {
            format!("check the column's unit (read as {})", cols.current.unit)
        };
        DoctorError::SuspectUnit {
            path: path.to_path_buf(),
            column: shown(&cols.current.header, 60),
            why: format!("peaks at {} A, more than a cell carries ({MAX_CELL_CURRENT_A} A)", short(peak_a)),
            hint,
        }
    };
    // More currents beyond a cell's in a group than a glitch spans: another unit (a glitch's are left out below).
    if groups.keys().any(|&c| beyond_a_cell(&currents(&groups, c)) > READ_GLITCH_RUN_READINGS) {
        return Err(in_ma(peak_a(&groups)));
    }
    if peak_a(&groups) <= opts.load_threshold_a {
        return Err(no_current(path, opts));
    }
    // Current glitches left out of each group before its sign and records are read (said as the file has them).
    let mut glitch_notes = Vec::new();
    for (cycle, rows) in groups.iter_mut() {
        let v: Vec<f64> = rows.iter().map(|r| r.voltage_v).collect();
        let i: Vec<f64> = rows.iter().map(|r| r.current_a).collect();
        let runs = current_glitches(&v, &i);
        let Some(first) = runs.first() else { continue };
        let lines = line_of.get_mut(cycle).expect("a line per row");
        let error = glitch_error(path, lines[first.first], &v, &i, first);
        let keep = outside_runs(&runs, rows.len());
        retain_by(rows, &keep);
        retain_by(lines, &keep);
        glitch_notes.push(glitch_note(&Glitched { error, readings: keep.iter().filter(|k| !**k).count() }));
    }
    if peak_a(&groups) > MAX_CELL_CURRENT_A {
        return Err(in_ma(peak_a(&groups)));
    }
    let mut report = ReadReport { format: cols.format, ..ReadReport::default() };
    report.units = cols.conversions();
    if delimiter != b',' {
        let shown = if delimiter == b'\t' { "a tab".to_string() } else { format!("`{}`", delimiter as char) };
        let mark = if decimal_comma { "the comma" } else { "the point" };
        report.units.push(format!("fields separated by {shown}, {mark} their decimal mark"));
    }
    let mut evidence = SignEvidence::default();
    for rows in groups.values() {
        let v: Vec<f64> = rows.iter().map(|r| r.voltage_v).collect();
        let i: Vec<f64> = rows.iter().map(|r| r.current_a).collect();
        evidence.add_record(&v, &i, opts);
    }
    let sign = decide_sign(path, evidence, opts.current_sign)?;
    report.notes.extend(rows_read.notes());
    report.notes.extend(glitch_notes);
    report.notes.extend(order_notes);
    report.notes.extend(restart_notes);
    report.notes.extend(convention_note(path, cols.format, &sign));
    let flip = if sign.discharge_positive { 1.0 } else { -1.0 };
    let cell = cell_name(path);

    let with_cycle = cols.cycle.is_some();
    let mut out: Vec<Discharge> = Vec::new();
    let mut first_error: Option<DoctorError> = None;
    let mut any_discharge = false;
    let mut next_number = 1u32;
    for (cycle, rows) in &groups {
        let t: Vec<f64> = rows.iter().map(|r| r.time_s).collect();
        let i: Vec<f64> = rows.iter().map(|r| flip * r.current_a).collect();
        let mut segments = discharge_segments(&t, &i, opts, !with_cycle);
        for pulse in charger_pulses(&t, &i, &mut segments, opts) {
            report.notes.push(format!(
                "{}, line {}: a discharge current of {} A on {} reading{} right before a charge, {} after the load \
                 before it (a charger's first readings, as NASA's charges open): not read as a discharge",
                path.display(),
                line_of[cycle][pulse.start],
                short(i[pulse.start]),
                pulse.len(),
                if pulse.len() == 1 { "" } else { "s" },
                pulse_rest(&t, &i, pulse.start, opts).map_or("with no load".to_string(), |s| format!("{} s", short(s)))
            ));
        }
        if segments.is_empty() {
            if with_cycle {
                report.notes.push(format!("{}, cycle {cycle}: no discharge, skipped", path.display()));
            }
            continue;
        }
        any_discharge = true;
        if with_cycle && segments.len() > 1 {
            // One record per cycle: the largest discharge; the others are noted.
            let drawn = |s: &Range<usize>| charge_drawn_ah(&t[s.clone()], &i[s.clone()]);
            let best = (0..segments.len()).max_by(|&a, &b| drawn(&segments[a]).total_cmp(&drawn(&segments[b])));
            let best = best.expect("non-empty");
            for s in segments.iter().enumerate().filter(|(k, _)| *k != best).map(|(_, s)| s) {
                report.notes.push(format!(
                    "{}, cycle {cycle}: another discharge ({:.3} Ah, from {} s) split from the kept one by a charge; \
                     skipped",
                    path.display(),
                    drawn(s),
                    short(t[s.start])
                ));
            }
            segments = vec![segments.swap_remove(best)];
        }
        for seg in segments {
            let number = if with_cycle { *cycle } else { next_number };
            next_number += 1;
            let lines = &line_of[cycle][seg.clone()];
            let rows = &rows[seg.clone()];
            let t0 = rows[0].time_s;
            let mut d = empty(&cell, number, path, f64::NAN, cols.temperature.is_some());
            d.time_s = rows.iter().map(|r| r.time_s - t0).collect();
            d.voltage_v = rows.iter().map(|r| r.voltage_v).collect();
            d.current_a = i[seg].to_vec();
            if let Some(temps) = d.temperature_k.as_mut() {
                *temps = rows.iter().map(|r| r.temperature_c.unwrap_or(f64::NAN) + CELSIUS_TO_KELVIN).collect();
            }
            let first_c = rows.iter().filter_map(|r| r.temperature_c).find(|t| t.is_finite());
            d.ambient_k =
                CELSIUS_TO_KELVIN + opts.ambient_c.or(rows[0].ambient_c).or(first_c).unwrap_or(DEFAULT_AMBIENT_C);
            let header = cols.temperature.as_ref().map_or("", |c| c.header.as_str());
            let checked = fill_missing(&mut d, lines, header).and_then(|filled| {
                let d = validate(d)?;
                voltage_glitch(&d, lines)?;
                Ok((plausible_charge(d, &cols.time.header)?, filled))
            });
            match checked {
                Ok((d, filled)) => {
                    report.notes.extend(filled);
                    report.notes.extend(gap_note(&d, opts.gap_factor));
                    // Without a cycle column the groups are the logger's sessions, each on its own clock.
                    let session = if with_cycle { 0 } else { *cycle };
                    report.starts.push(RecordStart { cycle: number, start_s: t0, session });
                    out.push(d);
                }
                Err(e) => {
                    report.skipped.push(Skipped {
                        file: path.to_path_buf(),
                        cycle: Some(number),
                        reason: e.to_string(),
                    });
                    first_error.get_or_insert(e);
                }
            }
        }
    }
    if !any_discharge {
        return Err(DoctorError::NoDischarge {
            path: path.to_path_buf(),
            threshold_a: opts.load_threshold_a,
            sign: sign_words(&sign),
        });
    }
    report.signs.push(sign);
    match first_error {
        Some(e) if out.is_empty() => Err(e),
        _ => Ok((out, report)),
    }
}

/// One sample of a CSV in the doctor's units, current with the file's sign.
#[derive(Clone, Copy, Debug)]
struct Row {
    time_s: f64,
    voltage_v: f64,
    current_a: f64,
    temperature_c: Option<f64>,
    ambient_c: Option<f64>,
}

impl Row {
    /// The same reading, a temperature left empty in both included.
    fn same(&self, other: &Row) -> bool {
        let values =
            |r: &Row| [r.time_s, r.voltage_v, r.current_a, r.temperature_c.unwrap_or(0.0), r.ambient_c.unwrap_or(0.0)];
        self.temperature_c.is_some() == other.temperature_c.is_some()
            && self.ambient_c.is_some() == other.ambient_c.is_some()
            && same_bits(&values(self), &values(other))
    }
}

/// What a column holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Quantity {
    Time,
    UnixTime,
    Voltage,
    Current,
    Temperature,
    Ambient,
    Cycle,
}

/// A column [`read_csv`] reads, with the factor and offset to the doctor's unit (s, V, A, deg C).
#[derive(Clone, Debug)]
struct Col {
    index: usize,
    header: String,
    scale: f64,
    offset: f64,
    /// The unit the column is read in (`s`, `ms`, `V`, `mV`, `A`, `mA`, `degC`, `K`, ...).
    unit: &'static str,
    /// Whether a comma in a value is its decimal mark ([`decimal_comma`]).
    decimal_comma: bool,
}

impl Col {
    fn value(&self, rec: &csv::StringRecord, path: &Path, line: u64) -> Result<f64, DoctorError> {
        let v = match self.decimal_comma {
            // A point there is no decimal mark but a thousands separator, or another locale's: refused, not guessed.
            true => {
                let raw = rec.get(self.index).unwrap_or("");
                decimal(raw, true).ok_or_else(|| bad_field(path, line, &self.header, raw))?
            }
            false => number(rec, self.index, &self.header, path, line)?,
        } * self.scale
            + self.offset;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(bad_field(path, line, &self.header, rec.get(self.index).unwrap_or("")))
        }
    }
}

/// The columns of a CSV, found by name.
struct Columns {
    time: Col,
    voltage: Col,
    current: Col,
    temperature: Option<Col>,
    ambient: Option<Col>,
    cycle: Option<Col>,
    /// `bdf`, `nasa` or `generic`: the vocabulary of the time, voltage and current columns.
    format: &'static str,
}

/// The Battery Data Format's machine names this reader knows (its labels are recognised by their ` / `).
const BDF_NAMES: &[&str] = &[
    "test_time_second",
    "unix_time_second",
    "voltage_volt",
    "current_ampere",
    "cycle_count",
    "ambient_temperature_celsius",
    "temperature_t1_celsius",
];

const COLUMNS_HINT: &str = "name a time, a voltage and a current column: time_s,voltage_v,current_a (generic), \
    Test Time / s,Voltage / V,Current / A or test_time_second,voltage_volt,current_ampere (Battery Data Format); \
    other units in the name (time_ms, voltage_mv, current_ma, Current / mA)";

impl Columns {
    fn find(headers: &csv::StringRecord, path: &Path) -> Result<Columns, DoctorError> {
        let mut found: Vec<(Quantity, Col, bool)> = Vec::new();
        for (index, header) in headers.iter().enumerate() {
            let Some((quantity, unit)) = classify(header) else { continue };
            if found.iter().any(|(q, _, _)| *q == quantity) {
                continue; // The first column of a quantity is read (T1 before T2, ...).
            }
            let Some((scale, offset, unit)) = unit_of(quantity, unit.as_deref()) else {
                return Err(DoctorError::UnknownUnit {
                    path: path.to_path_buf(),
                    column: shown(header, 60),
                    unit: shown(unit.as_deref().unwrap_or(""), 20),
                    accepted: accepted_units(quantity),
                });
            };
            let bdf = header.contains(" / ") || BDF_NAMES.contains(&header.trim());
            found.push((
                quantity,
                Col { index, header: header.trim().to_string(), scale, offset, unit, decimal_comma: false },
                bdf,
            ));
        }
        let mut take = |q: Quantity| {
            found.iter().position(|(fq, _, _)| *fq == q).map(|k| {
                let (_, col, bdf) = found.remove(k);
                (col, bdf)
            })
        };
        let missing = |what: &str| {
            if no_header(headers) {
                return DoctorError::EmptyFile { path: path.to_path_buf() };
            }
            DoctorError::MissingColumn {
                path: path.to_path_buf(),
                column: what.to_string(),
                found: shown(&headers.iter().collect::<Vec<_>>().join(","), 200),
                hint: COLUMNS_HINT,
            }
        };
        let time = take(Quantity::Time).or_else(|| take(Quantity::UnixTime));
        let (time, bdf_t) = time.ok_or_else(|| missing("time (time_s, Test Time / s)"))?;
        let (voltage, bdf_v) = take(Quantity::Voltage).ok_or_else(|| missing("voltage (voltage_v, Voltage / V)"))?;
        let (current, bdf_i) = take(Quantity::Current).ok_or_else(|| missing("current (current_a, Current / A)"))?;
        let nasa = current.header == "Current_measured";
        Ok(Columns {
            time,
            voltage,
            current,
            temperature: take(Quantity::Temperature).map(|c| c.0),
            ambient: take(Quantity::Ambient).map(|c| c.0),
            cycle: take(Quantity::Cycle).map(|c| c.0),
            format: if bdf_t || bdf_v || bdf_i {
                "bdf"
            } else if nasa {
                "nasa"
            } else {
                "generic"
            },
        })
    }

    /// One line per column read in another unit than the doctor's.
    fn conversions(&self) -> Vec<String> {
        let si =
            |c: &Col, si: &str| (c.unit != si).then(|| format!("`{}` read in {}, converted to {si}", c.header, c.unit));
        [
            si(&self.time, "s"),
            si(&self.voltage, "V"),
            si(&self.current, "A"),
            self.temperature.as_ref().and_then(|c| si(c, "degC")),
            self.ambient.as_ref().and_then(|c| si(c, "degC")),
        ]
        .into_iter()
        .flatten()
        .collect()
    }
}

/// One quantity of a reading as a column (or a JSON key) names it: where it is and how it converts to s, V,
/// A or deg C.
#[derive(Clone, Debug, PartialEq)]
pub struct NamedColumn {
    /// Its position among the names given.
    pub index: usize,
    /// The name as given.
    pub name: String,
    scale: f64,
    offset: f64,
    /// The unit it is read in (`s`, `ms`, `V`, `mV`, `A`, `mA`, `degC`, `K`, ...).
    pub unit: &'static str,
}

impl NamedColumn {
    /// `value` (in the column's unit) in the doctor's unit.
    pub fn si(&self, value: f64) -> f64 {
        value * self.scale + self.offset
    }
}

/// The columns of one reading (time, terminal voltage, current, and the cell's temperature if named) among
/// `names`, in the vocabulary the CSV readers know: `time_s`, `time_ms`, `Test Time / s`, `voltage_mv`,
/// `Voltage_measured`, `Current (mA)`, `current_ampere`, `temperature_c`, `Temperature / K`, ... So what a
/// user's CSV is read with offline, a live stream of the same columns is read with too. The error names the
/// quantity that is missing, or the unit that is not read, and what would be.
pub fn reading_columns(names: &[&str]) -> Result<ReadingColumns, String> {
    let mut found: Vec<(Quantity, NamedColumn)> = Vec::new();
    for (index, name) in names.iter().enumerate() {
        let Some((quantity, unit)) = classify(name) else { continue };
        if found.iter().any(|(q, _)| *q == quantity) {
            continue; // The first of a quantity is read, as by the CSV readers.
        }
        let Some((scale, offset, unit)) = unit_of(quantity, unit.as_deref()) else {
            return Err(format!(
                "`{}` is read in {}, not `{}`",
                shown(name, 60),
                accepted_units(quantity),
                shown(unit.as_deref().unwrap_or(""), 20)
            ));
        };
        found.push((quantity, NamedColumn { index, name: name.trim().to_string(), scale, offset, unit }));
    }
    let mut take = |q: Quantity| found.iter().position(|(fq, _)| *fq == q).map(|k| found.remove(k).1);
    let time = take(Quantity::Time).or_else(|| take(Quantity::UnixTime));
    let (voltage, current, temperature) =
        (take(Quantity::Voltage), take(Quantity::Current), take(Quantity::Temperature));
    match (time, voltage, current) {
        (Some(time), Some(voltage), Some(current)) => Ok(ReadingColumns { time, voltage, current, temperature }),
        (t, v, c) => {
            let missing: Vec<&str> = [(t.is_none(), "time"), (v.is_none(), "voltage"), (c.is_none(), "current")]
                .into_iter()
                .filter_map(|(m, what)| m.then_some(what))
                .collect();
            Err(format!("no {} among `{}`; {COLUMNS_HINT}", missing.join(", no "), shown(&names.join(","), 200)))
        }
    }
}

/// The columns of a reading found by [`reading_columns`].
#[derive(Clone, Debug, PartialEq)]
pub struct ReadingColumns {
    pub time: NamedColumn,
    pub voltage: NamedColumn,
    pub current: NamedColumn,
    /// The cell's temperature (an ambient column is not read as it).
    pub temperature: Option<NamedColumn>,
}

/// The quantity a header names and the unit it gives, if the reader knows the name: `Voltage / mV`
/// (Battery Data Format labels), `Current (mA)`, `current [mA]`, `current_ma`, `test_time_second`,
/// `Voltage_measured`, `voltage`. The unit is `None` when the name gives none.
fn classify(header: &str) -> Option<(Quantity, Option<String>)> {
    let h = header.trim().trim_start_matches('\u{feff}');
    let (base, unit) = if let Some((b, u)) = h.split_once('/') {
        (b, Some(u.trim()))
    } else if let Some((b, u)) = h.strip_suffix(')').and_then(|s| s.rsplit_once('(')) {
        (b, Some(u.trim()))
    } else if let Some((b, u)) = h.strip_suffix(']').and_then(|s| s.rsplit_once('[')) {
        (b, Some(u.trim()))
    } else {
        match h.rsplit_once('_') {
            Some((b, u)) if UNIT_WORDS.contains(&u.to_lowercase().as_str()) => (b, Some(u)),
            _ => (h, None),
        }
    };
    let base = base.to_lowercase().replace(['_', '-'], " ").split_whitespace().collect::<Vec<_>>().join(" ");
    let quantity = match base.as_str() {
        "time" | "test time" | "elapsed time" => Quantity::Time,
        "unix time" => Quantity::UnixTime,
        "voltage" | "voltage measured" | "cell voltage" | "terminal voltage" => Quantity::Voltage,
        "current" | "current measured" | "cell current" => Quantity::Current,
        "temperature"
        | "temperature measured"
        | "cell temperature"
        | "surface temperature"
        | "temperature t1"
        | "surface temperature t1" => Quantity::Temperature,
        "ambient temperature" => Quantity::Ambient,
        "cycle" | "cycle count" | "cycle index" | "cycle number" => Quantity::Cycle,
        _ => return None,
    };
    Some((quantity, unit.map(str::to_string)))
}

/// Unit words recognised as the last `_` part of a machine-readable name (`time_ms`, `voltage_volt`).
const UNIT_WORDS: &[&str] = &[
    "s",
    "sec",
    "second",
    "seconds",
    "ms",
    "millisecond",
    "milliseconds",
    "min",
    "minute",
    "minutes",
    "h",
    "hour",
    "hours",
    "v",
    "volt",
    "volts",
    "mv",
    "millivolt",
    "millivolts",
    "a",
    "amp",
    "ampere",
    "amperes",
    "ma",
    "milliamp",
    "milliampere",
    "milliamperes",
    "c",
    "degc",
    "celsius",
    "k",
    "kelvin",
    "f",
    "degf",
    "fahrenheit",
];

/// (scale, offset, unit name) from a quantity's unit word to the doctor's unit; `None` for a unit it does not
/// read. No unit means the doctor's own.
fn unit_of(q: Quantity, unit: Option<&str>) -> Option<(f64, f64, &'static str)> {
    let u = unit.map(|u| u.trim().trim_start_matches('°').to_lowercase());
    let u = u.as_deref().unwrap_or("");
    Some(match q {
        Quantity::Time | Quantity::UnixTime => match u {
            "" | "s" | "sec" | "second" | "seconds" => (1.0, 0.0, "s"),
            "ms" | "millisecond" | "milliseconds" => (1e-3, 0.0, "ms"),
            "min" | "minute" | "minutes" => (60.0, 0.0, "min"),
            "h" | "hour" | "hours" => (3600.0, 0.0, "h"),
            _ => return None,
        },
        Quantity::Voltage => match u {
            "" | "v" | "volt" | "volts" => (1.0, 0.0, "V"),
            "mv" | "millivolt" | "millivolts" => (1e-3, 0.0, "mV"),
            _ => return None,
        },
        Quantity::Current => match u {
            "" | "a" | "amp" | "ampere" | "amperes" => (1.0, 0.0, "A"),
            "ma" | "milliamp" | "milliampere" | "milliamperes" => (1e-3, 0.0, "mA"),
            _ => return None,
        },
        Quantity::Temperature | Quantity::Ambient => match u {
            "" | "c" | "degc" | "deg c" | "celsius" => (1.0, 0.0, "degC"),
            "k" | "kelvin" => (1.0, -CELSIUS_TO_KELVIN, "K"),
            "f" | "degf" | "deg f" | "fahrenheit" => (5.0 / 9.0, -32.0 * 5.0 / 9.0, "degF"),
            _ => return None,
        },
        Quantity::Cycle => match u {
            "" | "1" | "-" => (1.0, 0.0, "1"),
            _ => return None,
        },
    })
}

fn accepted_units(q: Quantity) -> &'static str {
    match q {
        Quantity::Time | Quantity::UnixTime => "s, ms, min or h",
        Quantity::Voltage => "V or mV",
        Quantity::Current => "A or mA",
        Quantity::Temperature | Quantity::Ambient => "degC, K or degF",
        Quantity::Cycle => "plain counts (unit 1)",
    }
}

/// The cell's name from a file name: its stem without a `.bdf` part (`B1.bdf.csv` -> `B1`).
fn cell_name(path: &Path) -> String {
    let stem = path.file_stem().map_or_else(|| "cell".to_string(), |s| s.to_string_lossy().into_owned());
    stem.strip_suffix(".bdf").map_or(stem.clone(), str::to_string)
}

/// Readings a charger draws at a discharge's sign as it starts (NASA's charges open with one at 3-4 A): at most
/// this many. No voltage test tells them from a load's: the charger's reading pulls the voltage down as a load
/// does (B0005's charge record 05123: 3.325 -> 3.002 V at 3.36 A), so one or two loaded readings five minutes
/// after a discharge and right before a charge are read as the charger's whatever their voltage.
const CHARGER_PULSE_READINGS: usize = 2;
/// ... after at least this long at rest since the load before them, s (a pulsed load rests for seconds between
/// its pulses; a discharge's relaxation lasts minutes).
const CHARGER_PULSE_REST_S: f64 = 300.0;

/// The time at rest before the loaded reading `k` since the loaded reading before it, s (None: none before).
fn pulse_rest(t: &[f64], i: &[f64], k: usize, opts: &ReadOptions) -> Option<f64> {
    (0..k).rev().find(|&j| i[j] > opts.load_threshold_a).map(|j| t[k] - t[j])
}

/// Takes off the end of `segments` (of [`discharge_segments`]) the loaded runs of at most
/// [`CHARGER_PULSE_READINGS`] right before a charge that follow at least [`CHARGER_PULSE_REST_S`] at rest or no
/// load at all: a charger's first readings, not a discharge's (the segment then ends within `max_rest_after_s` of
/// the load before them). A segment left with no load is dropped (it takes no record's number). Returns the runs
/// taken off.
fn charger_pulses(t: &[f64], i: &[f64], segments: &mut Vec<Range<usize>>, opts: &ReadOptions) -> Vec<Range<usize>> {
    let loaded = |k: usize| i[k] > opts.load_threshold_a;
    let mut pulses = Vec::new();
    segments.retain_mut(|s| {
        let charge_next = s.end < i.len() && i[s.end] < -opts.load_threshold_a;
        let run = (s.start..s.end).rev().take_while(|&k| loaded(k)).count();
        if !charge_next || run == 0 || run > CHARGER_PULSE_READINGS {
            return true;
        }
        let start = s.end - run;
        if pulse_rest(t, i, start, opts).is_some_and(|rest_s| rest_s < CHARGER_PULSE_REST_S) {
            return true;
        }
        pulses.push(start..s.end);
        // The record ends as any does: within `max_rest_after_s` of its last load.
        let Some(last) = (s.start..start).rev().find(|&k| loaded(k)) else { return false };
        s.end = 1 + (last..start).rev().find(|&k| t[k] <= t[last] + opts.max_rest_after_s).unwrap_or(last);
        true
    });
    pulses
}

/// The discharge records of one group of samples (time order, current positive while discharging): the
/// stretches between charging runs of at least `min_charge_split_s` (and, with `split_gaps`, gaps of more
/// than `min_gap_split_s`, and `gap_factor` usual intervals, after which the cell reads at rest) that hold
/// a discharging sample, each trimmed
/// to `max_rest_before_s` of rest before its first discharging sample and `max_rest_after_s` after its last.
fn discharge_segments(t: &[f64], i: &[f64], opts: &ReadOptions, split_gaps: bool) -> Vec<Range<usize>> {
    let n = t.len();
    let charging = |k: usize| i[k] < -opts.load_threshold_a;
    // Boundaries at long charging runs: the stretches are the ranges between them.
    let mut stretches = Vec::new();
    let mut start = 0;
    let mut k = 0;
    while k < n {
        if !charging(k) {
            k += 1;
            continue;
        }
        let run_start = k;
        while k < n && charging(k) {
            k += 1;
        }
        // The run's span, each end half an interval beyond its samples.
        let from = if run_start > 0 { 0.5 * (t[run_start - 1] + t[run_start]) } else { t[run_start] };
        let to = if k < n { 0.5 * (t[k - 1] + t[k]) } else { t[k - 1] };
        if to - from >= opts.min_charge_split_s {
            stretches.push(start..run_start);
            start = k;
        }
    }
    stretches.push(start..n);
    let loaded = |k: usize| i[k] > opts.load_threshold_a;
    // A gap is also `gap_factor` of the group's usual interval (time in milliseconds read as seconds makes
    // every interval longer than `min_gap_split_s`, and is refused later with its own hint).
    let mut dts: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    let usual_s = bcal_common::stats::quantile(&mut dts, 0.5).unwrap_or(0.0);
    let gap_after = |k: usize| {
        let dt = t[k] - t[k - 1];
        split_gaps && dt > opts.min_gap_split_s && dt > opts.gap_factor * usual_s && !loaded(k)
    };
    stretches
        .into_iter()
        .flat_map(|s| {
            let cuts: Vec<usize> = (s.start + 1..s.end).filter(|&k| gap_after(k)).collect();
            let bounds: Vec<usize> = std::iter::once(s.start).chain(cuts).chain(std::iter::once(s.end)).collect();
            bounds.windows(2).map(|w| w[0]..w[1]).collect::<Vec<_>>()
        })
        .filter_map(|s| {
            let first = s.clone().find(|&k| i[k] > opts.load_threshold_a)?;
            let last = s.clone().rev().find(|&k| i[k] > opts.load_threshold_a)?;
            let from = (s.start..=first).find(|&k| t[k] >= t[first] - opts.max_rest_before_s).unwrap_or(first);
            let to = (last..s.end).rev().find(|&k| t[k] <= t[last] + opts.max_rest_after_s).unwrap_or(last);
            Some(from..to + 1)
        })
        .collect()
}

/// Charge drawn (discharging current only), Ah, trapezoidal.
fn charge_drawn_ah(t: &[f64], i: &[f64]) -> f64 {
    t.windows(2).zip(i.windows(2)).map(|(t, i)| 0.5 * (i[0].max(0.0) + i[1].max(0.0)) * (t[1] - t[0])).sum::<f64>()
        / 3600.0
}

/// Refuses a record that draws more charge than a cell holds, or stays under load for longer than any
/// discharge lasts ([`MAX_LOADED_S`]): its time is most likely in milliseconds.
fn plausible_charge(d: Discharge, time_header: &str) -> Result<Discharge, DoctorError> {
    let Some(why) = implausible(&d, &d.current_a) else { return Ok(d) };
    Err(DoctorError::SuspectUnit {
        path: d.source.clone(),
        column: shown(time_header, 60),
        why,
        hint: "if time is in milliseconds, name the column time_ms (or `Test Time / ms`), or divide it by 1000".into(),
    })
}

/// Why a record drawing `current_a` (discharge positive) is no cell's discharge: more charge than a cell
/// holds, or under load for longer than any discharge lasts ([`MAX_LOADED_S`]); None where it may be.
fn implausible(d: &Discharge, current_a: &[f64]) -> Option<String> {
    let q_ah = charge_drawn_ah(&d.time_s, current_a);
    let loaded_s: f64 =
        d.time_s.windows(2).zip(current_a).filter(|(_, i)| **i > LOADED_A).map(|(t, _)| t[1] - t[0]).sum();
    if q_ah > MAX_RECORD_CHARGE_AH {
        Some(format!(
            "gives cycle {} a discharge of {} Ah, more than a cell holds ({MAX_RECORD_CHARGE_AH} Ah)",
            d.cycle,
            short(q_ah)
        ))
    } else if loaded_s > MAX_LOADED_S {
        Some(format!(
            "keeps cycle {} under load for {} days, longer than a discharge lasts ({} days)",
            d.cycle,
            short(loaded_s / 86_400.0),
            short(MAX_LOADED_S / 86_400.0)
        ))
    } else {
        None
    }
}

/// A note on the gaps in a record's time (steps over `factor` times its median step), if any.
fn gap_note(d: &Discharge, factor: f64) -> Option<String> {
    let mut dt: Vec<f64> = d.time_s.windows(2).map(|w| w[1] - w[0]).collect();
    if dt.is_empty() {
        return None;
    }
    let longest = dt.iter().copied().fold(0.0, f64::max);
    dt.sort_by(f64::total_cmp);
    let median = dt[dt.len() / 2];
    let gaps = dt.iter().filter(|s| **s > factor * median).count();
    (gaps > 0).then(|| {
        format!(
            "{}, cycle {}: {gaps} gap{} in time (longest {} s against a median step of {} s); kept, the simulator \
             bridges {}",
            d.source.display(),
            d.cycle,
            if gaps == 1 { "" } else { "s" },
            short(longest),
            short(median),
            if gaps == 1 { "it" } else { "them" }
        )
    })
}

/// A number short enough for a message.
fn short(x: f64) -> String {
    if x.abs() >= 1e6 || (x != 0.0 && x.abs() < 1e-3) {
        format!("{x:.3e}")
    } else {
        format!("{}", (x * 1000.0).round() / 1000.0)
    }
}

/// Evidence on which sign of the current is discharge, in volts of voltage change: under discharge the
/// terminal voltage falls, and a step up of the discharge current steps it down (V = OCV - R I). Two
/// kinds of vote, each weighted by the voltage change it rests on:
/// - a load step (the current changes by more than `step_threshold_a` between two samples): the voltage
///   moves against the current's change if positive current discharges;
/// - a run of samples under one sign of current beyond `load_threshold_a`, with no step inside: the voltage
///   at its end against its start (noise cancels over the run) falls under discharge, rises under charge.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct SignEvidence {
    /// Voltage change that says positive current discharges, V.
    pub positive_v: f64,
    /// Voltage change that says negative current discharges, V.
    pub negative_v: f64,
}

impl SignEvidence {
    /// Adds the votes of one record (samples in time order, current as measured).
    pub fn add_record(&mut self, voltage_v: &[f64], current_a: &[f64], opts: &ReadOptions) {
        let (v, i) = (voltage_v, current_a);
        let n = v.len().min(i.len());
        let mut vote = |positive: bool, w: f64| {
            if positive {
                self.positive_v += w;
            } else {
                self.negative_v += w;
            }
        };
        let mut run_start: Option<usize> = None;
        for k in 0..n {
            let step = k > 0 && (i[k] - i[k - 1]).abs() > opts.step_threshold_a;
            if step {
                let (dv, di) = (v[k] - v[k - 1], i[k] - i[k - 1]);
                vote(dv * di < 0.0, dv.abs());
            }
            let sign = if i[k] > opts.load_threshold_a {
                1.0
            } else if i[k] < -opts.load_threshold_a {
                -1.0
            } else {
                0.0
            };
            let same_run = run_start.is_some_and(|s| !step && sign != 0.0 && i[s].signum() == sign);
            if !same_run {
                if let Some(s) = run_start.take() {
                    let dv = v[k - 1] - v[s];
                    vote(dv * i[s] < 0.0, dv.abs());
                }
                run_start = (sign != 0.0).then_some(k);
            }
        }
        if let Some(s) = run_start {
            let dv = v[n - 1] - v[s];
            vote(dv * i[s] < 0.0, dv.abs());
        }
    }

    /// Share of the evidence for the given sign being discharge, 0-1; `None` without evidence.
    pub fn share_for(&self, discharge_positive: bool) -> Option<f64> {
        let total = self.positive_v + self.negative_v;
        (total > 0.0).then(|| if discharge_positive { self.positive_v } else { self.negative_v } / total)
    }

    /// Whether positive current discharges, when the evidence says so clearly: at least
    /// [`MIN_SIGN_EVIDENCE_V`] of it, [`SIGN_AGREEMENT`] of it on one side. Else why not.
    pub fn decide(&self) -> Result<bool, String> {
        let total = self.positive_v + self.negative_v;
        if total < MIN_SIGN_EVIDENCE_V {
            return Err(format!(
                "the voltage hardly moves with the current ({:.1} mV of evidence, {:.0} mV needed)",
                1e3 * total,
                1e3 * MIN_SIGN_EVIDENCE_V
            ));
        }
        let share = self.positive_v / total;
        if share >= SIGN_AGREEMENT {
            Ok(true)
        } else if share <= 1.0 - SIGN_AGREEMENT {
            Ok(false)
        } else {
            Err(format!(
                "the voltage falls under positive current for {:.0} % of the evidence and under negative current for \
                 {:.0} %",
                100.0 * share,
                100.0 * (1.0 - share)
            ))
        }
    }
}

/// The sign a file is read with: the caller's, or the data's under `Auto` (refusing a file it cannot decide).
fn decide_sign(path: &Path, evidence: SignEvidence, option: CurrentSign) -> Result<SignChoice, DoctorError> {
    let (discharge_positive, from_data) = match option {
        CurrentSign::DischargePositive => (true, false),
        CurrentSign::DischargeNegative => (false, false),
        CurrentSign::Auto => match evidence.decide() {
            Ok(p) => (p, true),
            Err(why) => return Err(DoctorError::SignUndecided { path: path.to_path_buf(), why }),
        },
    };
    Ok(SignChoice { file: path.to_path_buf(), discharge_positive, from_data, evidence })
}

/// A note when a file is read against its format's documented sign, or the caller's sign against the data.
fn convention_note(path: &Path, format: &str, sign: &SignChoice) -> Option<String> {
    let against_data = !sign.from_data && sign.evidence.decide().is_ok_and(|p| p != sign.discharge_positive);
    if against_data {
        return Some(format!(
            "{}: read {} as asked, but the data says {} (the voltage falls under the other sign)",
            path.display(),
            CurrentSign::of(sign.discharge_positive),
            CurrentSign::of(!sign.discharge_positive)
        ));
    }
    let documented = match format {
        "bdf" => false,
        "generic" => true,
        _ => return None,
    };
    (sign.from_data && sign.discharge_positive != documented).then(|| {
        format!(
            "{}: the {} counts {} positive, but this file's data says {}; read it so (check the export)",
            path.display(),
            if format == "bdf" { "Battery Data Format" } else { "generic CSV" },
            if documented { "discharge" } else { "charge" },
            CurrentSign::of(sign.discharge_positive)
        )
    })
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

/// A Li-ion cell's voltage lies within this range, V.
const CELL_VOLTAGE_V: [f64; 2] = [0.5, 5.0];

/// Whole-record checks: enough samples, voltage in volts, a cell temperature in degrees Celsius (a kelvin
/// column read as Celsius would run the model 273 K too warm and still fit, to a wrong cause).
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
    if !(CELL_VOLTAGE_V[0]..=CELL_VOLTAGE_V[1]).contains(&median_v) {
        return Err(DoctorError::VoltageOutOfRange { path: d.source.clone(), median_v });
    }
    let mut t_c: Vec<f64> =
        d.temperature_k.iter().flatten().filter(|t| t.is_finite()).map(|t| t - CELSIUS_TO_KELVIN).collect();
    if let Some(median_c) = bcal_common::stats::quantile(&mut t_c, 0.5) {
        if !(CELL_TEMPERATURE_RANGE_C[0]..=CELL_TEMPERATURE_RANGE_C[1]).contains(&median_c) {
            return Err(DoctorError::TemperatureOutOfRange { path: d.source.clone(), median_c });
        }
    }
    Ok(d)
}

/// The damaged end of a file a logger stopped writing mid-way: the first bad record's error and how many
/// records from it on were left out.
#[derive(Debug)]
struct DamagedEnd {
    error: DoctorError,
    records: usize,
}

/// What a reader of [`read_rows`] made of one record.
enum Taken {
    Kept,
    /// The same reading, at the same time, as one already kept (a row copied, a logger's buffer written
    /// again): read once. The error is the one a strict reader refuses it with.
    Again(DoctorError),
    /// A reading whose time falls between the last two kept (two rows written in the wrong order): read in its
    /// place by time. The error is the one a strict reader refuses it with.
    Swapped(DoctorError),
    /// Another reading at the time of the last one kept (a clock coarser than the logging): left out, since
    /// no order between the two is known. The error is the one a strict reader refuses it with.
    SameTime(DoctorError),
}

/// A reading whose time falls between the last two kept, read in its place ([`Taken::Swapped`]), until the next
/// reading confirms the two rows were written in the wrong order by coming after the last one kept. If the next
/// falls before it as well, the last reading's clock jumped ahead (more than two rows out of order): the record is
/// refused at the first, as a clock that steps back or jumps ahead amid whole lines is.
#[derive(Clone, Copy, Debug)]
struct UnconfirmedSwap {
    line: u64,
    time_s: f64,
    previous_s: f64,
}

impl UnconfirmedSwap {
    /// What a reader says when nothing after the swap confirmed it (the record's last rows): the reading it went
    /// before, at `time_s` on line `line`, may be one whose clock jumped ahead, and is left out.
    fn left_out_note(self, path: &Path, line: u64, time_s: f64) -> String {
        format!(
            "{}, line {line}: the reading at {time_s:?} s comes before one at {:?} s (line {}), and no reading after \
             them tells two rows written in the wrong order from a clock that jumped ahead: left out",
            path.display(),
            self.time_s,
            self.line
        )
    }

    fn error(self, path: &Path) -> DoctorError {
        let UnconfirmedSwap { line, time_s, previous_s } = self;
        DoctorError::TimeNotIncreasing { path: path.to_path_buf(), line, time_s, previous_s }
    }
}

/// How far back, s, a reading written again may lie in a CSV without a cycle column: further back, a reading like a
/// kept one at its time is a restarted logger's (at rest, a cell reads the same to the logger's digits).
const AGAIN_WITHIN_S: f64 = 3600.0;

/// A reading of a CSV without a cycle column whose time falls before the last two kept ([`read_csv`]): a logger
/// that restarted (its clock from 0, or set back), once the next reading comes after it; from it the readings are a
/// new session on their own clock.
#[derive(Clone, Copy, Debug)]
struct Restart {
    line: u64,
    time_s: f64,
    previous_s: f64,
}

impl Restart {
    fn note(self, path: &Path) -> String {
        let Restart { line, time_s, previous_s } = self;
        format!(
            "{}, line {line}: the time steps back from {previous_s:?} s to {time_s:?} s and runs on from there (a \
             logger restarted): the readings from here are read as a new session on its own clock; no rest is known \
             between the sessions",
            path.display()
        )
    }

    /// What is said when the restart is the file's last reading: nothing confirms it, and it is left out.
    fn left_out_note(self, path: &Path) -> String {
        format!(
            "{}, line {}: the last reading's time {:?} s steps back from {:?} s, and no reading after it tells a logger \
             that restarted from a time written wrong: left out",
            path.display(),
            self.line,
            self.time_s,
            self.previous_s
        )
    }

    fn error(self, path: &Path) -> DoctorError {
        let Restart { line, time_s, previous_s } = self;
        DoctorError::TimeNotIncreasing { path: path.to_path_buf(), line, time_s, previous_s }
    }
}

/// What [`read_rows`] met beside the records it kept.
#[derive(Debug, Default)]
struct RowsRead {
    damaged_end: Option<DamagedEnd>,
    /// Readings written twice and read once, and the first of them.
    again: usize,
    first_again: Option<DoctorError>,
    /// Temperatures left empty and filled ([`fill_missing`]), said, and the first one's line.
    temperature_note: Option<(u64, String)>,
    /// Current glitches left out ([`leave_out_glitches`]), said.
    glitched: Option<Glitched>,
    /// Readings read in their place by time ([`Taken::Swapped`]), and the first of them.
    swapped: usize,
    first_swapped: Option<DoctorError>,
    /// Readings left out at the time of the one before with other values ([`Taken::SameTime`]), and the first.
    same_time: usize,
    first_same_time: Option<DoctorError>,
    /// A swap no reading after it confirmed ([`UnconfirmedSwap::left_out_note`]), said.
    unconfirmed_note: Option<String>,
}

impl RowsRead {
    /// What a person reading the data is told of it.
    fn notes(&self) -> Vec<String> {
        let plural = |n: usize| if n == 1 { "" } else { "s" };
        let mut out = Vec::new();
        if let Some(DoctorError::TimeNotIncreasing { path, line, time_s, .. }) = &self.first_again {
            out.push(format!(
                "{}, line {line}: the reading at {time_s:?} s once more, to its last digit (a row copied, a logger's \
                 buffer written again); {} such reading{} read once",
                path.display(),
                self.again,
                plural(self.again)
            ));
        }
        if let Some(DoctorError::TimeNotIncreasing { path, line, time_s, previous_s }) = &self.first_swapped {
            out.push(format!(
                "{}, line {line}: the reading at {time_s:?} s comes after the one at {previous_s:?} s (two rows written \
                 in the wrong order); {} such reading{} read in {} place by time",
                path.display(),
                self.swapped,
                plural(self.swapped),
                if self.swapped == 1 { "its" } else { "their" }
            ));
        }
        if let Some(DoctorError::TimeNotIncreasing { path, line, time_s, .. }) = &self.first_same_time {
            out.push(format!(
                "{}, line {line}: a reading at {time_s:?} s, the time of the one before, with other values (a clock \
                 coarser than the logging); {} such reading{} left out, the first at each time kept",
                path.display(),
                self.same_time,
                plural(self.same_time)
            ));
        }
        out.extend(self.unconfirmed_note.clone());
        out.extend(self.glitched.as_ref().map(glitch_note));
        out.extend(self.temperature_note.as_ref().map(|(_, note)| note.clone()));
        match &self.damaged_end {
            Some(DamagedEnd { error: error @ DoctorError::FrozenEnd { .. }, .. }) => {
                out.push(format!("{error}: read up to them, as a record cut short"));
            }
            Some(DamagedEnd { error, records }) => out.push(format!(
                "read up to a damaged end (a logger that stopped mid-write leaves one; {} record{} from it to the \
                 file's end left out; a discharge so read is a record cut short): {error}",
                records,
                plural(*records)
            )),
            None => {}
        }
        out
    }
}

/// Reads a CSV's records in order with `read`, which checks one and keeps it, or keeps nothing and fails.
/// A logger that stops mid-write (power lost, a crash) leaves a damaged end: a half line, NUL padding, a last
/// line cut short. Where nothing after the first bad record is more data (see below), the file is read up to
/// it and the damage returned for the caller to say; a bad record that data follows fails the read naming
/// it, as does a damaged end with fewer than `min_kept` records before it. Readings written again
/// (a buffer written twice) are read once wherever they are, and rows written in the wrong order in their place
/// ([`Taken::Swapped`], counted among those kept).
fn read_rows(
    path: &Path,
    rdr: &mut csv::Reader<&[u8]>,
    lines: &mut Lines,
    min_kept: usize,
    mut read: impl FnMut(&csv::StringRecord, u64) -> Result<Taken, DoctorError>,
) -> Result<RowsRead, DoctorError> {
    let mut out = RowsRead::default();
    let mut kept = 0;
    let mut records = rdr.records();
    while let Some(rec) = records.next() {
        let outcome = rec.map_err(|e| csv_error(path, e, lines)).and_then(|rec| {
            let line = lines.of(&rec);
            read(&rec, line)
        });
        let error = match outcome {
            Ok(Taken::Kept) => {
                kept += 1;
                continue;
            }
            Ok(Taken::Again(e)) => {
                out.again += 1;
                out.first_again.get_or_insert(e);
                continue;
            }
            Ok(Taken::Swapped(e)) => {
                kept += 1;
                out.swapped += 1;
                out.first_swapped.get_or_insert(e);
                continue;
            }
            Ok(Taken::SameTime(e)) => {
                out.same_time += 1;
                out.first_same_time.get_or_insert(e);
                continue;
            }
            Err(error) => error,
        };
        // What a stopped write leaves: records that do not parse (a half line, NUL padding) or repeat earlier
        // ones to the file's end, or a last line without its line end, whatever it parses to (a time cut to its
        // first digits). A record after it that parses and is no repeat (a session whose clock restarts) is
        // more data, as is a clock that steps back or jumps ahead amid whole lines: the record is refused.
        let unparsed = |e: &DoctorError| matches!(e, DoctorError::Csv { .. } | DoctorError::BadField { .. });
        let mut left_out = 1;
        for rec in records.by_ref() {
            left_out += 1;
            let outcome = rec.map_err(|e| csv_error(path, e, lines)).and_then(|rec| {
                let line = lines.of(&rec);
                read(&rec, line)
            });
            match outcome {
                Ok(Taken::Again(_)) => {}
                Err(e) if unparsed(&e) => {}
                _ => return Err(error),
            }
        }
        let cut_line = left_out == 1 && !lines.bytes.ends_with(b"\n") && !lines.bytes.ends_with(b"\r");
        if kept < min_kept || !(unparsed(&error) || cut_line) {
            return Err(error);
        }
        out.damaged_end = Some(DamagedEnd { error, records: left_out });
        break;
    }
    Ok(out)
}

/// Whether a field is left empty or NaN (a value the logger did not have).
fn missing(rec: &csv::StringRecord, col: usize) -> bool {
    let raw = rec.get(col).unwrap_or("").trim();
    raw.is_empty() || raw.eq_ignore_ascii_case("nan")
}

/// Fills the temperatures a sensor left out (NaN) with the reading's before (those before the first read
/// with it), as a cell's temperature moves slowly, and says how many and where (None when none was left
/// out). A record with none read at all is refused: a temperature column promises measured ones (a model's
/// thermal cause runs on them), and the ambient would pass for one.
fn fill_missing(d: &mut Discharge, line_of: &[u64], column: &str) -> Result<Option<String>, DoctorError> {
    let Some(temps) = d.temperature_k.as_mut() else { return Ok(None) };
    let left: Vec<usize> = (0..temps.len()).filter(|&k| !temps[k].is_finite()).collect();
    let Some(&first) = left.first() else { return Ok(None) };
    let place = format!("{}, line {}", d.source.display(), line_of[first]);
    let Some(known) = temps.iter().copied().find(|t| t.is_finite()) else {
        return Err(DoctorError::MissingValues {
            why: format!(
                "{place}: field `{column}` is empty on all {} readings (a sensor that dropped out); give the \
                 record without the column, or with its temperatures",
                left.len()
            ),
        });
    };
    let mut last = known;
    for t in temps.iter_mut() {
        if t.is_finite() {
            last = *t;
        } else {
            *t = last;
        }
    }
    Ok(Some(format!(
        "{place}: field `{column}` is empty on {} of {} readings from here (a sensor that dropped out): each read \
         as the reading's before",
        left.len(),
        temps.len()
    )))
}

/// Equal bit for bit (a NaN equals a NaN: a value left empty twice is the same reading twice).
fn same_bits(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

fn check_time(times: &[f64], time_s: f64, path: &Path, line: u64) -> Result<(), DoctorError> {
    match times.last() {
        Some(&previous_s) if time_s <= previous_s => {
            Err(DoctorError::TimeNotIncreasing { path: path.to_path_buf(), line, time_s, previous_s })
        }
        _ => Ok(()),
    }
}

/// Whether a file's first line holds nothing (an empty file, or one blank line): a header of empty names
/// (commas) is a header, and lacks columns.
fn no_header(headers: &csv::StringRecord) -> bool {
    headers.is_empty() || (headers.len() == 1 && headers[0].trim().is_empty())
}

fn column(headers: &csv::StringRecord, name: &str, path: &Path, hint: &'static str) -> Result<usize, DoctorError> {
    if no_header(headers) {
        return Err(DoctorError::EmptyFile { path: path.to_path_buf() });
    }
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

/// The field delimiter of a CSV, from its header line (the file's first): the comma, else a semicolon or a tab
/// where the header holds one and no comma (what a spreadsheet writes in a locale whose decimal mark is the
/// comma, which a reader then reads as the decimal point where the comma does not separate fields).
pub fn delimiter(bytes: &[u8]) -> u8 {
    let header = bytes.split(|b| *b == b'\n').next().unwrap_or_default();
    [b',', b';', b'\t'].into_iter().find(|d| header.contains(d)).unwrap_or(b',')
}

/// Whether a CSV separated by `delimiter` writes its decimals with a comma: the first value after the header that
/// holds a comma or a point says which the file uses (never where the comma separates fields). A value with the
/// other mark is then refused (`1.000` in a file of decimal commas is a thousand, or a point in another locale).
pub fn decimal_comma(bytes: &[u8], delimiter: u8) -> bool {
    if delimiter == b',' {
        return false;
    }
    let mark = bytes
        .split(|b| *b == b'\n')
        .skip(1)
        .flat_map(|line| line.split(move |b| *b == delimiter))
        .find_map(|field| decimal_mark(&String::from_utf8_lossy(field)));
    mark == Some(true)
}

/// The decimal mark a value shows: Some(true) for a comma, Some(false) for a point, None for neither (its first
/// one, as [`decimal_comma`] reads a file's and a live stream a stream's).
pub fn decimal_mark(text: &str) -> Option<bool> {
    text.chars().find(|c| *c == ',' || *c == '.').map(|c| c == ',')
}

/// A value under its file's decimal mark: with `decimal_comma` a point is refused (a thousands separator, or
/// another locale's mark: not guessed) and the comma read as a point; else as Rust reads a number.
pub fn decimal(text: &str, decimal_comma: bool) -> Option<f64> {
    let text = text.trim();
    match decimal_comma {
        true if text.contains('.') => None,
        true => text.replacen(',', ".", 1).parse().ok(),
        false => text.parse().ok(),
    }
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

    /// A load that steps by 6 A under a voltage sample that lags one reading, or pulses for three readings so,
    /// is no glitch: from its second reading on the voltage has moved (0.1 ohm). The same pulse with the voltage
    /// never moving is one, and so is a lone spike at either end.
    #[test]
    fn a_load_step_whose_voltage_lags_is_no_current_glitch() {
        let n = 20;
        let lagged = |on: std::ops::Range<usize>| -> (Vec<f64>, Vec<f64>) {
            let i: Vec<f64> = (0..n).map(|k| if on.contains(&k) { 6.0 } else { 0.0 }).collect();
            // The voltage answers the current of the reading before.
            let v: Vec<f64> = (0..n).map(|k| 4.0 - 0.1 * if k == 0 { 0.0 } else { i[k - 1] }).collect();
            (v, i)
        };
        for on in [5..n, 5..8] {
            let (v, i) = lagged(on.clone());
            assert!(current_glitches(&v, &i).is_empty(), "{on:?}: {:?}", current_glitches(&v, &i));
        }
        let i: Vec<f64> = (0..n).map(|k| if (5..8).contains(&k) { 6.0 } else { 0.0 }).collect();
        let g = current_glitches(&[4.0; 20], &i);
        assert_eq!(g.iter().map(|g| (g.first, g.readings)).collect::<Vec<_>>(), vec![(5, 3)]);
        let runs = |i: &[f64]| -> Vec<(usize, usize)> {
            current_glitches(&vec![3.8; i.len()], i).iter().map(|g| (g.first, g.readings)).collect()
        };
        let mut ends = vec![2.0; n];
        (ends[0], ends[n - 1]) = (-40.0, 40.0);
        assert_eq!(runs(&ends), vec![(0, 1), (n - 1, 1)]);
        // A run just after the first reading, or one next to the last reading's glitch: each run is found, and
        // no good reading is taken for one.
        let mut early = vec![2.0; n];
        (early[1], early[2]) = (-40.0, -40.0);
        assert_eq!(runs(&early), vec![(1, 2)]);
        let mut late = vec![2.0; n];
        (late[n - 3], late[n - 1]) = (-40.0, 40.0);
        assert_eq!(runs(&late), vec![(n - 3, 1), (n - 1, 1)]);
        // A load of 6 A switched off at the last reading, the voltage (falling 5 mV a reading) sampled before
        // the switch: seen from one side it could be a glitch, but a current that falls toward zero is read.
        let i: Vec<f64> = (0..n).map(|k| if k + 1 < n { 6.0 } else { 0.0 }).collect();
        let v: Vec<f64> = (0..n).map(|k| 3.8 - 0.005 * k.min(n - 2) as f64).collect();
        assert!(current_glitches(&v, &i).is_empty());
    }

    /// A stream's or a DataFrame's columns are found as the CSV readers find them, each converted by the unit
    /// its name gives; a missing quantity and an unknown unit are named.
    #[test]
    fn reading_columns_read_the_units_their_names_give() {
        let c = reading_columns(&["Current (mA)", "time_ms", "Voltage / mV", "ambient_temperature", "Temperature / K"])
            .unwrap();
        assert_eq!((c.time.index, c.voltage.index, c.current.index), (1, 2, 0));
        assert_eq!(c.time.si(1500.0), 1.5);
        assert_eq!(c.voltage.si(3900.0), 3.9);
        assert_eq!(c.current.si(-2000.0), -2.0);
        let t = c.temperature.expect("the cell's temperature, not the ambient");
        assert_eq!((t.index, t.si(300.0)), (4, 300.0 - CELSIUS_TO_KELVIN));
        let nasa = reading_columns(&["Voltage_measured", "Current_measured", "Temperature_measured", "Time"]).unwrap();
        assert_eq!((nasa.time.index, nasa.time.si(10.0), nasa.current.unit), (3, 10.0, "A"));
        let plain = reading_columns(&["time_s", "voltage_v", "current_a"]).unwrap();
        assert!(plain.temperature.is_none() && plain.time.si(7.0) == 7.0);
        let e = reading_columns(&["time_s", "volts", "current_a"]).unwrap_err();
        assert!(e.contains("no voltage among `time_s,volts,current_a`"), "{e}");
        let e = reading_columns(&["time_fortnights", "voltage_v", "current_a"]).unwrap_err();
        assert!(e.contains("no time"), "an unknown unit word is not a unit: {e}");
        let e = reading_columns(&["Time (fortnights)", "voltage_v", "current_a"]).unwrap_err();
        assert!(e.contains("`Time (fortnights)` is read in s, ms, min or h"), "{e}");
    }

    #[test]
    fn nasa_descriptions_give_each_battery_its_cutoff() {
        let text =
            "Data Description:\nA set of four Li-ion batteries (# 5, 6, 7 and 18) were run. Charging was carried \
            out until the battery voltage reached 4.2V. Discharge was carried out at a constant current (CC) level of \
            2A until the battery voltage fell to 2.7V, 2.5V, 2.2V and 2.5V for batteries 5 6 7 and 18 respectively. \
            Discharge was carried out at 4A until the battery voltage fell to 2.0V and 2.2V for batteries 33 and 34 \
            respectively. For battery 36 discharge was done at 2A until voltage fell to 2.7V. Fixed load current \
            level of 1A was used and the discharge runs were stopped at 2V, 2.2V, 2.5V and 2.7V for batteries 45, \
            46, 47 and 48 respectively. Capacity: Battery capacity (Ahr) for discharge till 2.7V";
        let got = parse_nasa_cutoffs(text);
        let want = [
            (5, 2.7),
            (6, 2.5),
            (7, 2.2),
            (18, 2.5),
            (33, 2.0),
            (34, 2.2),
            (36, 2.7),
            (45, 2.0),
            (46, 2.2),
            (47, 2.5),
            (48, 2.7),
        ];
        assert_eq!(got, want.to_vec());
    }

    #[test]
    fn column_names_give_quantity_and_unit() {
        let unit = |h: &str| classify(h).map(|(q, u)| (q, unit_of(q, u.as_deref()).map(|x| x.2)));
        for (h, q, u) in [
            ("time_s", Quantity::Time, "s"),
            ("Test Time / s", Quantity::Time, "s"),
            ("test_time_second", Quantity::Time, "s"),
            ("time_ms", Quantity::Time, "ms"),
            ("Time", Quantity::Time, "s"),
            ("Unix Time / s", Quantity::UnixTime, "s"),
            ("voltage_v", Quantity::Voltage, "V"),
            ("Voltage / mV", Quantity::Voltage, "mV"),
            ("Voltage_measured", Quantity::Voltage, "V"),
            ("voltage_volt", Quantity::Voltage, "V"),
            ("current_ampere", Quantity::Current, "A"),
            ("Current (mA)", Quantity::Current, "mA"),
            ("current [mA]", Quantity::Current, "mA"),
            ("current_ma", Quantity::Current, "mA"),
            ("Temperature T1 / degC", Quantity::Temperature, "degC"),
            ("Surface Temperature T1 / degC", Quantity::Temperature, "degC"),
            ("temperature_t1_celsius", Quantity::Temperature, "degC"),
            ("Temperature (°C)", Quantity::Temperature, "degC"),
            ("temperature_k", Quantity::Temperature, "K"),
            ("temperature_f", Quantity::Temperature, "degF"),
            ("Temperature (F)", Quantity::Temperature, "degF"),
            ("Ambient Temperature / degC", Quantity::Ambient, "degC"),
            ("Cycle Count / 1", Quantity::Cycle, "1"),
            ("cycle_count", Quantity::Cycle, "1"),
            ("cycle", Quantity::Cycle, "1"),
        ] {
            assert_eq!(unit(h), Some((q, Some(u))), "{h}");
        }
        for h in ["Step Index / 1", "step_time_second", "Current_load", "Voltage_load", "dV/dt(V/s)", "note", ""] {
            assert!(classify(h).is_none(), "{h}");
        }
        assert_eq!(unit("Current / kA"), Some((Quantity::Current, None)));
    }

    #[test]
    fn long_charges_split_records_and_short_pulses_do_not() {
        let opts = ReadOptions::default();
        // 10 s samples: rest, discharge with a 20 s regenerative pulse, rest, a 300 s charge, rest, discharge.
        let mut i = vec![0.0; 5];
        i.extend([2.0; 10]);
        i.extend([-1.0; 2]);
        i.extend([2.0; 10]);
        i.extend([0.0; 5]);
        i.extend([-1.5; 30]);
        i.extend([0.0; 5]);
        i.extend([2.0; 10]);
        let t: Vec<f64> = (0..i.len()).map(|k| 10.0 * k as f64).collect();
        assert_eq!(discharge_segments(&t, &i, &opts, false), vec![0..32, 62..77]);
        // Rest limits trim each side.
        let short = ReadOptions { max_rest_before_s: 20.0, max_rest_after_s: 10.0, ..opts };
        assert_eq!(discharge_segments(&t, &i, &short, false), vec![3..28, 65..77]);
        // No discharge, no record.
        assert!(discharge_segments(&t[..5], &i[..5], &opts, false).is_empty());
    }

    /// Discharges logged without the charges between them (a log of discharges at their clock times): a gap
    /// of hours after which the cell rests splits them, where the cycle column does not; one after which the
    /// cell is still loaded (readings lost within a discharge), or a short one, does not.
    #[test]
    fn a_long_gap_ending_at_rest_splits_records_without_a_cycle_column() {
        let opts = ReadOptions::default();
        // 10 s samples. Rest, discharge, relaxation; 3 h unseen; rest, discharge with 2 h of readings lost
        // under load, relaxation; 1 h unseen; rest, discharge, relaxation.
        let (mut t, mut i): (Vec<f64>, Vec<f64>) = (Vec::new(), Vec::new());
        // Each run starts `after_s` after the last sample.
        let run = |t: &mut Vec<f64>, i: &mut Vec<f64>, after_s: f64, currents: &[f64]| {
            let t0 = t.last().map_or(0.0, |l| l + after_s);
            for (k, c) in currents.iter().enumerate() {
                t.push(t0 + 10.0 * k as f64);
                i.push(*c);
            }
        };
        let whole = [[0.0; 3].as_slice(), &[2.0; 10], &[0.0; 3]].concat();
        run(&mut t, &mut i, 0.0, &whole);
        run(&mut t, &mut i, 3.0 * 3600.0, &[[0.0; 3].as_slice(), &[2.0; 5]].concat());
        run(&mut t, &mut i, 2.0 * 3600.0, &[[2.0; 5].as_slice(), &[0.0; 3]].concat());
        run(&mut t, &mut i, 3600.0, &whole);
        let segments = discharge_segments(&t, &i, &opts, true);
        assert_eq!(segments, vec![0..16, 16..32, 32..48]);
        // Gaps shorter than the split's: one record.
        let long = ReadOptions { min_gap_split_s: 4.0 * 3600.0, ..opts };
        assert_eq!(discharge_segments(&t, &i, &long, true), vec![0..48]);
        // With a cycle column the records are the user's: no split.
        assert_eq!(discharge_segments(&t, &i, &opts, false), vec![0..48]);
    }

    #[test]
    fn cycle_ranges_parse_and_refuse_nonsense() {
        assert_eq!(parse_cycle_range("1..40").unwrap(), 1..=40);
        assert_eq!(parse_cycle_range("3..=3").unwrap(), 3..=3);
        assert_eq!(parse_cycle_range("0..3").unwrap(), 0..=3, "a CSV's cycle column may count from 0");
        for bad in ["", "5", "9..2", "a..b", "-1..3"] {
            assert!(parse_cycle_range(bad).is_err(), "{bad}");
        }
    }
}

#[cfg(test)]
mod start_time_tests {
    use super::parse_matlab_datevec;

    #[test]
    fn nasa_start_times_parse_in_both_printings() {
        // B0005's first two discharges, as metadata.csv prints them.
        let a = parse_matlab_datevec("[2.0080e+03 4.0000e+00 2.0000e+00 1.5000e+01 2.5000e+01 4.1593e+01]").unwrap();
        let b = parse_matlab_datevec("[2008.       4.       2.      19.      43.      48.406]").unwrap();
        assert!((b - a - (4.0 * 3600.0 + 18.0 * 60.0 + 6.813)).abs() < 1e-6, "{}", b - a);
        // 2008-04-02 15:25:41.593 UTC.
        assert!((a - 1_207_149_941.593).abs() < 1e-6, "{a}");
        // Across a month and a leap day.
        let feb = parse_matlab_datevec("[2008. 2. 28. 23. 0. 0.]").unwrap();
        let mar = parse_matlab_datevec("[2008. 3. 1. 1. 0. 0.]").unwrap();
        assert_eq!(mar - feb, 26.0 * 3600.0);
        for bad in ["", "[]", "[2008 4 2 15 25]", "2008 4 2 15 25 41", "[2008 13 2 15 25 41]", "[2008 4 2 15 25 x]"] {
            assert_eq!(parse_matlab_datevec(bad), None, "{bad}");
        }
    }
}
