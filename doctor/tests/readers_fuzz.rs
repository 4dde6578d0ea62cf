//! Hostile input to the doctor's readers, by property (proptest): arbitrary bytes and mutations of a real
//! NASA record never panic; every error names the file, and a line it names exists in the input (and holds
//! the bad value); whatever a reader accepts satisfies the documented invariants; valid files round-trip
//! exactly (Battery Data Format files in any of their spellings and units too, within rounding of the unit
//! conversion); a corrupt file neither poisons later reads nor hides which file of a folder is bad (the
//! skipping reader reads the others and names it), and the metadata cannot send the reader outside `data/`.

use bcal_doctor::read::{
    read_csv, read_generic, read_nasa, read_nasa_record, read_nasa_with, CurrentSign, ReadOptions, MIN_SAMPLES,
};
use bcal_doctor::record::CELSIUS_TO_KELVIN;
use bcal_doctor::{Discharge, DoctorError};
use proptest::prelude::*;
use proptest::sample::Index;
use std::path::{Path, PathBuf};

/// The first 24 lines of the measured NASA record `05122.csv` (B0005, first discharge), verbatim.
const SAMPLE: &str = "\
Voltage_measured,Current_measured,Temperature_measured,Current_load,Voltage_load,Time
4.191491807505295,-0.004901589207462691,24.330033885570543,-0.0006,0.0,0.0
4.190749067776103,-0.0014780055516425076,24.325993424022467,-0.0006,4.206,16.781
3.9748709122299895,-2.0125283240860368,24.389085127564876,-1.9982,3.062,35.702999999999996
3.9517167075108937,-2.0139793620987403,24.544752316727223,-1.9982,3.03,53.781
3.934352489432596,-2.011143595991146,24.731385200934106,-1.9982,3.011,71.922
3.920058441667911,-2.0130066278129433,24.909816397303786,-1.9982,2.991,90.094
3.9079035099130923,-2.0143996570526377,25.105884152527363,-1.9982,2.977,108.281
3.8970357216910942,-2.01160288530172,25.3170185607883,-1.9982,2.967,126.453
3.8874765805404445,-2.0180146876333027,25.50942310048985,-1.9982,2.959,144.641
3.878958592475142,-2.0131347535115096,25.70360345147403,-1.9982,2.951,162.844
3.871015984807792,-2.0131622022459528,25.887208193567197,-1.9982,2.943,181.016
3.863479677493402,-2.0130302341846087,26.077814856061327,-1.9982,2.935,199.219
3.856660507031456,-2.013710498518572,26.254314624563154,-1.9982,2.93,217.391
3.850013579168339,-2.0141501374546595,26.436710686894443,-1.9982,2.925,235.594
3.8438419054138055,-2.0134639832409995,26.61127890990982,-1.9982,2.925,253.75
3.837687975719061,-2.012645836387535,26.781347653774752,-1.9982,2.919,271.984
3.831938252983524,-2.013409300587134,26.957458850986356,-1.9982,2.913,290.141
3.826414443009924,-2.013145499824814,27.129800142459914,-1.9982,2.907,308.359
3.8210957343825593,-2.0120412894303126,27.305824075615053,-1.9982,2.902,326.5
3.815896664668625,-2.0144632529994038,27.464816676940977,-1.9982,2.897,344.75
3.8106968219063564,-2.013140029715948,27.617964522755162,-1.9982,2.892,362.906
3.8058373809696873,-2.0092264361962906,27.775477825458733,-1.9982,2.887,381.047
3.801121633463299,-2.0146661803839097,27.93132997915235,-1.9982,2.882,399.187
";

const AMBIENT_K: f64 = 24.0 + CELSIUS_TO_KELVIN;

/// Longest error message allowed besides the file paths it names: a hostile field is shown shortened.
const MAX_MESSAGE_CHARS: usize = 600;

/// Bytes shown as an escaped string in failure reports.
#[derive(Clone)]
struct Bytes(Vec<u8>);

impl std::fmt::Debug for Bytes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "b\"{}\"", self.0.escape_ascii())
    }
}

/// `n` cases per property, or `BCAL_FUZZ_CASES` of them (a soak run, not for CI).
fn cases(n: u32) -> ProptestConfig {
    let n = std::env::var("BCAL_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(n);
    ProptestConfig { cases: n, max_shrink_iters: 2000, ..ProptestConfig::default() }
}

// ---------------------------------------------------------------------------------------------------
// Checks shared by the properties.

/// Lines of `bytes` as the CSV reader counts them (1-based, one per `\n`).
fn lines_of(bytes: &[u8]) -> Vec<&[u8]> {
    bytes.split(|b| *b == b'\n').collect()
}

fn contains(hay: &[u8], needle: &[u8]) -> bool {
    needle.is_empty() || hay.windows(needle.len()).any(|w| w == needle)
}

/// Every number N in `line N` or `line: N` of a message.
fn named_lines(msg: &str) -> Vec<u64> {
    msg.match_indices("line")
        .filter_map(|(k, _)| {
            let rest = msg[k + 4..].trim_start_matches([':', ' ']);
            let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
            digits.parse().ok()
        })
        .collect()
}

/// An error of a reader that read `bytes` from `path`: it names the file, any line it names exists in the
/// input, a bad field's value is on that line (inputs without quoting), the message stays readable.
fn check_err(err: &DoctorError, path: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    let msg = err.to_string();
    let shown = path.display().to_string();
    prop_assert!(msg.contains(&shown), "the error does not name {shown}: {msg}");
    prop_assert!(msg.replace(&shown, "").chars().count() <= MAX_MESSAGE_CHARS, "overlong message: {msg}");
    prop_assert!(!msg.chars().any(|c| c.is_control()), "control characters in the message: {msg:?}");
    let lines = lines_of(bytes);
    let exists = |line: u64| line >= 1 && line as usize <= lines.len();
    for line in named_lines(&msg.replace(&shown, "")) {
        prop_assert!(exists(line), "line {line} of {} lines: {msg}", lines.len());
    }
    match err {
        DoctorError::BadField { line, value, column, .. } => {
            prop_assert!(exists(*line), "line {line} of {} lines: {msg}", lines.len());
            prop_assert!(msg.contains(&format!("line {line}")) && msg.contains(column.as_str()), "{msg}");
            let plain =
                value.len() < 40 && value.chars().all(|c| c.is_ascii_graphic() || c == ' ') && !value.contains('\\');
            if plain && !bytes.contains(&b'"') {
                let text = lines[*line as usize - 1];
                prop_assert!(
                    contains(text, value.as_bytes()),
                    "line {line} {:?} does not hold `{value}`",
                    String::from_utf8_lossy(text)
                );
            }
        }
        DoctorError::TimeNotIncreasing { line, .. }
        | DoctorError::NotAFileName { line, .. }
        | DoctorError::VoltageGlitch { line, .. }
        | DoctorError::FrozenEnd { line, .. }
        | DoctorError::CurrentGlitch { line, .. } => {
            prop_assert!(exists(*line), "line {line} of {} lines: {msg}", lines.len());
            prop_assert!(msg.contains(&format!("line {line}")), "{msg}");
        }
        DoctorError::Csv { .. }
        | DoctorError::MissingColumn { .. }
        | DoctorError::EmptyFile { .. }
        | DoctorError::TooFewSamples { .. }
        | DoctorError::VoltageInMillivolts { .. }
        | DoctorError::VoltageOutOfRange { .. }
        | DoctorError::NoLoad { .. }
        | DoctorError::NoDischarge { .. }
        | DoctorError::SignUndecided { .. }
        | DoctorError::SuspectUnit { .. }
        | DoctorError::MissingValues { .. }
        | DoctorError::UnknownUnit { .. } => {}
        other => prop_assert!(false, "unexpected error kind for a file read: {other:?}"),
    }
    Ok(())
}

/// What a reader accepted is a validated record of that file.
fn check_ok(d: &Discharge, path: &Path) -> Result<(), TestCaseError> {
    let n = d.len();
    prop_assert!(n >= MIN_SAMPLES, "{n} samples accepted");
    prop_assert_eq!(&d.source, path);
    prop_assert!(d.voltage_v.len() == n && d.current_a.len() == n);
    prop_assert!(d.temperature_k.as_ref().is_none_or(|t| t.len() == n));
    prop_assert!(d.time_s.windows(2).all(|w| w[0] < w[1]), "time not strictly increasing");
    let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
    prop_assert!(finite(&d.time_s) && finite(&d.voltage_v) && finite(&d.current_a));
    prop_assert!(d.temperature_k.as_deref().is_none_or(finite) && d.ambient_k.is_finite());
    let mut v = d.voltage_v.clone();
    v.sort_by(f64::total_cmp);
    prop_assert!((0.5..=5.0).contains(&v[n / 2]), "median voltage {}", v[n / 2]);
    Ok(())
}

fn check_nasa(path: &Path, bytes: &[u8]) -> Result<Option<Discharge>, TestCaseError> {
    match read_nasa_record(path, "B0005", 1, AMBIENT_K) {
        Ok(d) => check_ok(&d, path).map(|()| Some(d)),
        Err(e) => check_err(&e, path, bytes).map(|()| None),
    }
}

fn check_generic(path: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    match read_generic(path, None) {
        Ok(records) => {
            prop_assert!(!records.is_empty());
            let mut cycles: Vec<u32> = records.iter().map(|d| d.cycle).collect();
            cycles.dedup();
            prop_assert_eq!(cycles.len(), records.len(), "one record per cycle");
            records.iter().try_for_each(|d| check_ok(d, path))
        }
        Err(e) => check_err(&e, path, bytes),
    }
}

/// The general reader, with the sign decided from the data and with the sign given: Ok (valid records,
/// one per cycle number, each from its own start, the sign reported) or an error naming the file.
fn check_csv(path: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    for current_sign in [CurrentSign::Auto, CurrentSign::DischargePositive] {
        match read_csv(path, &ReadOptions { current_sign, ..ReadOptions::default() }) {
            Ok((records, report)) => {
                prop_assert!(!records.is_empty());
                prop_assert_eq!(report.signs.len(), 1);
                prop_assert_eq!(report.signs[0].from_data, current_sign == CurrentSign::Auto);
                let mut cycles: Vec<u32> = records.iter().map(|d| d.cycle).collect();
                cycles.dedup();
                prop_assert_eq!(cycles.len(), records.len(), "one record per cycle number");
                for d in &records {
                    check_ok(d, path)?;
                    prop_assert_eq!(d.time_s[0], 0.0);
                    prop_assert!(d.current_a.iter().any(|i| *i > 0.05), "a record without discharge");
                }
                for s in &report.skipped {
                    prop_assert!(s.reason.contains(&path.display().to_string()), "{}", s.reason);
                }
            }
            Err(e) => check_err(&e, path, bytes)?,
        }
    }
    Ok(())
}

/// Every field of two records is identical (bit for bit).
fn assert_same(a: &Discharge, b: &Discharge) -> Result<(), TestCaseError> {
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    prop_assert_eq!((&a.cell, a.cycle, &a.source), (&b.cell, b.cycle, &b.source));
    prop_assert_eq!(a.ambient_k.to_bits(), b.ambient_k.to_bits());
    prop_assert_eq!(bits(&a.time_s), bits(&b.time_s));
    prop_assert_eq!(bits(&a.voltage_v), bits(&b.voltage_v));
    prop_assert_eq!(bits(&a.current_a), bits(&b.current_a));
    prop_assert_eq!(a.temperature_k.as_deref().map(bits), b.temperature_k.as_deref().map(bits));
    prop_assert_eq!(a.stated_capacity_ah.map(f64::to_bits), b.stated_capacity_ah.map(f64::to_bits));
    Ok(())
}

// ---------------------------------------------------------------------------------------------------
// Strategies.

/// A hostile field: non-finite and overlong numbers, empty, quoted, NUL, invalid UTF-8, near misses.
fn hostile_field() -> impl Strategy<Value = Vec<u8>> {
    const TOKENS: &[&str] = &[
        "",
        "NaN",
        "nan",
        "inf",
        "-inf",
        "+inf",
        "infinity",
        "1e400",
        "-1e400",
        "1e308",
        "4.9e-324",
        "-0",
        "0x10",
        "1_000",
        "--1",
        "+-1",
        "1e",
        "e5",
        ".",
        "-",
        " 3.9 ",
        "\t4.1",
        "\"3.9\"",
        "\"a,b\"",
        "\"x\"\"y\"",
        "\"",
        "\"unterminated",
        "\0",
        "3.9\0",
        "4294967296",
        "1e20",
        "1.5",
        "-1",
        "0",
        "2",
        "\u{feff}1",
        "٣",
        "1 2",
        "\u{1b}[31mred",
        "Time",
        "Voltage_measured",
        "time_s",
    ];
    prop_oneof![
        3 => prop::sample::select(TOKENS).prop_map(|s| s.as_bytes().to_vec()),
        1 => prop::collection::vec(b'0'..=b'9', 300..700),
        1 => (prop::collection::vec(b'0'..=b'9', 1..20), prop::collection::vec(b'0'..=b'9', 300..400))
            .prop_map(|(a, b)| [a, b".".to_vec(), b].concat()),
        1 => prop::collection::vec(any::<u8>(), 0..8),
        1 => Just(vec![0xff, 0xfe, b'1']),
        1 => any::<f64>().prop_map(|v| v.to_string().into_bytes()),
    ]
}

const GENERIC_COLS: &[&str] = &["time_s", "voltage_v", "current_a", "temperature_c", "cycle"];
const NASA_COLS: &[&str] =
    &["Voltage_measured", "Current_measured", "Temperature_measured", "Current_load", "Voltage_load", "Time"];

/// A plausible value for column `name` at row `k` (so that reads get past the first row).
fn good_value(name: &str, k: usize) -> String {
    match name {
        "time_s" | "Time" => format!("{}", 10 * k),
        "voltage_v" | "Voltage_measured" | "Voltage_load" => format!("{}", 4.1 - 0.01 * k as f64),
        "current_a" => "2.0".into(),
        "Current_measured" | "Current_load" => "-2.0".into(),
        "temperature_c" | "Temperature_measured" => "24.5".into(),
        "cycle" => format!("{}", 1 + k / 12),
        _ => "x".into(),
    }
}

/// A CSV-shaped file of either layout in which cells, rows, headers and line endings are damaged at random.
fn hostile_csv() -> impl Strategy<Value = Vec<u8>> {
    let cell = (0u8..100, hostile_field());
    let row = (0u8..100, prop::collection::vec(cell, 8));
    (
        any::<bool>(),
        Just((0..8).collect::<Vec<usize>>()).prop_shuffle(),
        0usize..9,
        prop::collection::vec(row, 0..30),
        prop::sample::select(&["\n", "\r\n", "\r"][..]),
        0u8..100,
    )
        .prop_map(|(nasa, order, drop_cols, rows, eol, flags)| {
            let base = if nasa { NASA_COLS } else { GENERIC_COLS };
            // Column names: the layout's, shuffled, with extras, some dropped.
            let mut names: Vec<String> =
                order.iter().map(|&i| base.get(i).map_or_else(|| format!("extra{i}"), |s| s.to_string())).collect();
            names.truncate(8 - drop_cols.min(3));
            let mut out = Vec::new();
            if flags % 13 == 0 {
                out.extend_from_slice("\u{feff}".as_bytes());
            }
            out.extend_from_slice(names.join(",").as_bytes());
            out.extend_from_slice(eol.as_bytes());
            for (k, (dice, cells)) in rows.iter().enumerate() {
                let mut fields: Vec<Vec<u8>> = names
                    .iter()
                    .zip(cells)
                    .map(|(name, (d, bad))| if *d < 92 { good_value(name, k).into_bytes() } else { bad.clone() })
                    .collect();
                match dice {
                    0..=2 => {
                        fields.pop();
                    }
                    3..=5 => fields.push(b"1".to_vec()),
                    6 => fields.clear(),
                    _ => {}
                }
                out.extend_from_slice(&fields.join(&b","[..]));
                out.extend_from_slice(if *dice == 7 { b"\r\n" } else { eol.as_bytes() });
                if *dice == 8 {
                    out.extend_from_slice(names.join(",").as_bytes());
                    out.extend_from_slice(eol.as_bytes());
                }
            }
            if flags % 7 == 0 {
                while out.last().is_some_and(|b| *b == b'\n' || *b == b'\r') {
                    out.pop();
                }
            }
            out
        })
}

/// Bytes the readers see: raw noise, or a damaged CSV.
fn hostile_bytes() -> impl Strategy<Value = Bytes> {
    prop_oneof![
        1 => prop::collection::vec(any::<u8>(), 0..600),
        1 => prop::collection::vec(prop::sample::select(&b"0123456789.,-e\n\r \"naNIf"[..]), 0..600),
        4 => hostile_csv(),
    ]
    .prop_map(Bytes)
}

/// One edit of a file's bytes.
#[derive(Clone, Debug)]
enum Mutation {
    Truncate(Index),
    FlipBit(Index, u8),
    InsertByte(Index, u8),
    DeleteByte(Index),
    DeleteLine(Index),
    DuplicateLine(Index),
    SwapLines(Index, Index),
    /// Repeats the header line before line `Index`.
    DuplicateHeader(Index),
    /// Replaces one numeric token by something else.
    ReplaceNumber(Index, Bytes),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        1 => any::<Index>().prop_map(Mutation::Truncate),
        1 => (any::<Index>(), 0u8..8).prop_map(|(i, b)| Mutation::FlipBit(i, b)),
        1 => (any::<Index>(), any::<u8>()).prop_map(|(i, b)| Mutation::InsertByte(i, b)),
        1 => any::<Index>().prop_map(Mutation::DeleteByte),
        1 => any::<Index>().prop_map(Mutation::DeleteLine),
        1 => any::<Index>().prop_map(Mutation::DuplicateLine),
        1 => (any::<Index>(), any::<Index>()).prop_map(|(a, b)| Mutation::SwapLines(a, b)),
        1 => any::<Index>().prop_map(Mutation::DuplicateHeader),
        3 => (any::<Index>(), hostile_field()).prop_map(|(i, f)| Mutation::ReplaceNumber(i, Bytes(f))),
    ]
}

fn split_lines(bytes: &[u8]) -> Vec<Vec<u8>> {
    bytes.split_inclusive(|b| *b == b'\n').map(<[u8]>::to_vec).collect()
}

fn apply(bytes: &mut Vec<u8>, m: &Mutation) {
    let n = bytes.len();
    match m {
        Mutation::Truncate(i) => bytes.truncate(i.index(n + 1)),
        Mutation::FlipBit(i, b) if n > 0 => bytes[i.index(n)] ^= 1 << b,
        Mutation::InsertByte(i, b) => bytes.insert(i.index(n + 1), *b),
        Mutation::DeleteByte(i) if n > 0 => {
            bytes.remove(i.index(n));
        }
        Mutation::DeleteLine(i) | Mutation::DuplicateLine(i) | Mutation::DuplicateHeader(i) if n > 0 => {
            let mut lines = split_lines(bytes);
            let k = i.index(lines.len());
            match m {
                Mutation::DeleteLine(_) => {
                    lines.remove(k);
                }
                Mutation::DuplicateLine(_) => lines.insert(k, lines[k].clone()),
                _ => lines.insert(k, lines[0].clone()),
            }
            *bytes = lines.concat();
        }
        Mutation::SwapLines(a, b) if n > 0 => {
            let mut lines = split_lines(bytes);
            let len = lines.len();
            lines.swap(a.index(len), b.index(len));
            *bytes = lines.concat();
        }
        Mutation::ReplaceNumber(i, with) => {
            // Numeric tokens: maximal runs of [0-9.eE+-].
            let numeric = |b: u8| b.is_ascii_digit() || b".eE+-".contains(&b);
            let mut spans = Vec::new();
            let mut k = 0;
            while k < n {
                if numeric(bytes[k]) {
                    let start = k;
                    while k < n && numeric(bytes[k]) {
                        k += 1;
                    }
                    spans.push((start, k));
                } else {
                    k += 1;
                }
            }
            if !spans.is_empty() {
                let (a, b) = spans[i.index(spans.len())];
                bytes.splice(a..b, with.0.iter().copied());
            }
        }
        _ => {}
    }
}

fn mutated(base: &[u8], edits: &[Mutation]) -> Vec<u8> {
    let mut bytes = base.to_vec();
    edits.iter().for_each(|m| apply(&mut bytes, m));
    bytes
}

/// One sample: (time_s, voltage_v, current_a, temperature_c).
type Row = (f64, f64, f64, f64);

/// A valid generic CSV and the records it must read back as.
#[derive(Clone, Debug)]
struct GenericFile {
    /// Per cycle: (cycle, rows of (time_s, voltage_v, current_a, temperature_c)).
    cycles: Vec<(u32, Vec<Row>)>,
    with_temperature: bool,
    with_cycle: bool,
    extra_column: bool,
    /// Permutation of the written columns.
    order: Vec<usize>,
    crlf: bool,
    padded: bool,
    interleave: bool,
    /// Starts with a UTF-8 byte-order mark (spreadsheet exports).
    bom: bool,
}

fn rows() -> impl Strategy<Value = Vec<Row>> {
    // Currents within 4.9 A of each other (the first up to 0.5 A more): a lone reading 5 A off both its
    // neighbours, the voltage unmoved, is a glitch the readers leave out (and the strict ones refuse).
    prop::collection::vec((1e-3f64..100.0, 2.5f64..4.3, -2.0f64..2.4, -20.0f64..60.0), MIN_SAMPLES..40).prop_map(
        |steps| {
            let mut t = -50.0;
            let mut out: Vec<Row> = steps
                .into_iter()
                .map(|(dt, v, i, c)| {
                    t += dt;
                    (t, v, i, c)
                })
                .collect();
            // At least one sample under load (positive current while discharging).
            out[0].2 = out[0].2.abs() + 0.5;
            out
        },
    )
}

fn generic_file() -> impl Strategy<Value = GenericFile> {
    (
        prop::collection::btree_map(0u32..1000, rows(), 1..4),
        any::<(bool, bool, bool, bool, bool, bool)>(),
        Just((0..6).collect::<Vec<usize>>()).prop_shuffle(),
        any::<bool>(),
    )
        .prop_map(|(map, (with_temperature, with_cycle, extra_column, crlf, padded, interleave), order, bom)| {
            let mut cycles: Vec<_> = map.into_iter().collect();
            if !with_cycle {
                cycles.truncate(1);
                cycles[0].0 = 1;
            }
            GenericFile { cycles, with_temperature, with_cycle, extra_column, order, crlf, padded, interleave, bom }
        })
}

impl GenericFile {
    fn text(&self) -> String {
        // Columns 0..6: time, voltage, current, temperature, cycle, extra.
        let names = ["time_s", "voltage_v", "current_a", "temperature_c", "cycle", "note"];
        let used = [true, true, true, self.with_temperature, self.with_cycle, self.extra_column];
        let cols: Vec<usize> = self.order.iter().copied().filter(|&c| used[c]).collect();
        let pad = |s: String| if self.padded { format!(" {s} ") } else { s };
        let eol = if self.crlf { "\r\n" } else { "\n" };
        let mut rows: Vec<(u32, Row)> = Vec::new();
        if self.interleave {
            // Rows of different cycles alternate; each cycle's rows stay in time order.
            let longest = self.cycles.iter().map(|c| c.1.len()).max().unwrap_or(0);
            for k in 0..longest {
                for (cycle, r) in &self.cycles {
                    if let Some(row) = r.get(k) {
                        rows.push((*cycle, *row));
                    }
                }
            }
        } else {
            rows = self.cycles.iter().flat_map(|(c, r)| r.iter().map(move |row| (*c, *row))).collect();
        }
        let mut s: String = if self.bom { "\u{feff}".into() } else { String::new() };
        s += &cols.iter().map(|&c| pad(names[c].to_string())).collect::<Vec<_>>().join(",");
        s += eol;
        for (cycle, (t, v, i, temp)) in rows {
            let fields = [t.to_string(), v.to_string(), i.to_string(), temp.to_string(), cycle.to_string(), "n".into()];
            s += &cols.iter().map(|&c| pad(fields[c].clone())).collect::<Vec<_>>().join(",");
            s += eol;
        }
        s
    }
}

/// A valid Battery Data Format file (or a generic one with units in its names) and what it must read back as.
#[derive(Clone, Debug)]
struct BdfFile {
    /// Per cycle: rows of (time_s, voltage_v, current_a discharging positive, temperature_c).
    cycles: Vec<(u32, Vec<Row>)>,
    /// Preferred labels (`Test Time / s`) or machine names (`test_time_second`), or the generic names.
    spelling: u8,
    with_temperature: bool,
    with_cycle: bool,
    /// Time in ms, voltage in mV, current in mA (in the names).
    milli: (bool, bool, bool),
    order: Vec<usize>,
    crlf: bool,
}

/// Rows with the current never charging (so each cycle is one discharge record), loaded at both ends.
fn discharge_rows() -> impl Strategy<Value = Vec<Row>> {
    rows().prop_map(|mut rows| {
        for r in rows.iter_mut() {
            r.2 = r.2.abs();
        }
        let last = rows.len() - 1;
        rows[last].2 += 0.5;
        rows
    })
}

fn bdf_file() -> impl Strategy<Value = BdfFile> {
    (
        prop::collection::btree_map(0u32..1000, discharge_rows(), 1..4),
        (0u8..3, any::<bool>(), any::<bool>()),
        any::<(bool, bool, bool)>(),
        Just((0..6).collect::<Vec<usize>>()).prop_shuffle(),
        any::<bool>(),
    )
        .prop_map(|(map, (spelling, with_temperature, with_cycle), milli, order, crlf)| {
            let mut cycles: Vec<_> = map.into_iter().collect();
            if !with_cycle {
                cycles.truncate(1);
                cycles[0].0 = 1;
            }
            BdfFile { cycles, spelling, with_temperature, with_cycle, milli, order, crlf }
        })
}

impl BdfFile {
    fn text(&self) -> String {
        let (ms, mv, ma) = self.milli;
        let names: [String; 6] = match self.spelling {
            0 => [
                format!("Test Time / {}", if ms { "ms" } else { "s" }),
                format!("Voltage / {}", if mv { "mV" } else { "V" }),
                format!("Current / {}", if ma { "mA" } else { "A" }),
                "Temperature T1 / degC".into(),
                "Cycle Count / 1".into(),
                "Step Index / 1".into(),
            ],
            1 => [
                (if ms { "test_time_millisecond" } else { "test_time_second" }).into(),
                (if mv { "voltage_millivolt" } else { "voltage_volt" }).into(),
                (if ma { "current_milliampere" } else { "current_ampere" }).into(),
                "temperature_t1_celsius".into(),
                "cycle_count".into(),
                "step_index".into(),
            ],
            _ => [
                (if ms { "time_ms" } else { "time_s" }).into(),
                (if mv { "voltage_mv" } else { "voltage_v" }).into(),
                (if ma { "current_ma" } else { "current_a" }).into(),
                "temperature_c".into(),
                "cycle".into(),
                "note".into(),
            ],
        };
        let used = [true, true, true, self.with_temperature, self.with_cycle, true];
        let cols: Vec<usize> = self.order.iter().copied().filter(|&c| used[c]).collect();
        let eol = if self.crlf { "\r\n" } else { "\n" };
        let k = |milli: bool| if milli { 1e3 } else { 1.0 };
        let mut s = cols.iter().map(|&c| names[c].clone()).collect::<Vec<_>>().join(",") + eol;
        for (cycle, rows) in &self.cycles {
            for (t, v, i, temp) in rows {
                // Charge positive, as the Battery Data Format counts it.
                let fields = [
                    (t * k(ms)).to_string(),
                    (v * k(mv)).to_string(),
                    (-i * k(ma)).to_string(),
                    temp.to_string(),
                    cycle.to_string(),
                    "1".into(),
                ];
                s += &(cols.iter().map(|&c| fields[c].clone()).collect::<Vec<_>>().join(",") + eol);
            }
        }
        s
    }
}

/// A folder in the NASA layout: B0005 with three discharges (`00002`, `00004`, `00005`), B0006 with one
/// (`00007`), a charge row between; each file is the sample with its voltages shifted per file.
struct NasaFolder {
    root: tempfile::TempDir,
}

const B0005_FILES: [&str; 3] = ["00002.csv", "00004.csv", "00005.csv"];
const METADATA: &str = "\
type,start_time,ambient_temperature,battery_id,test_id,uid,filename,Capacity,Re,Rct
charge,[2008 4 2 13 8 17],24,B0005,0,1,00001.csv,,,
discharge,[2.0080e+03 4.0000e+00 2.0000e+00 1.5000e+01 2.5000e+01 4.1593e+01],24,B0005,1,2,00002.csv,1.8564874208181574,,
charge,[2008 4 2 19 43 48],24,B0005,2,3,00003.csv,,,
discharge,[2008 4 3 19 43 48],24,B0005,3,4,00004.csv,[],,
discharge,[2008 4 4 19 43 48],24,B0005,5,5,00005.csv,1.80,,
impedance,[2008 4 4 23 0 0],24,B0006,0,6,00006.csv,,0.05,0.2
discharge,[2008 4 5 1 0 0],24,B0006,1,7,00007.csv,2.03,,
";

fn file_text(k: usize) -> String {
    // Distinct contents per file so that a swapped or misattributed record shows.
    SAMPLE.replacen("4.19", &format!("4.1{k}"), 1)
}

impl NasaFolder {
    fn new() -> Self {
        let root = tempfile::tempdir().unwrap();
        std::fs::create_dir(root.path().join("data")).unwrap();
        std::fs::write(root.path().join("metadata.csv"), METADATA).unwrap();
        for (k, f) in B0005_FILES.iter().chain(&["00007.csv"]).enumerate() {
            std::fs::write(root.path().join("data").join(f), file_text(k)).unwrap();
        }
        NasaFolder { root }
    }

    fn data(&self, file: &str) -> PathBuf {
        self.root.path().join("data").join(file)
    }
}

// ---------------------------------------------------------------------------------------------------
// Properties.

proptest! {
    #![proptest_config(cases(512))]

    /// Arbitrary bytes (noise, or CSV with hostile fields, missing or extra columns, mixed line endings):
    /// both readers return Ok or an Err naming the file and an existing line, never panic; what they accept
    /// is a validated record.
    #[test]
    fn arbitrary_bytes_give_ok_or_an_error_naming_file_and_line(bytes in hostile_bytes()) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("input.csv");
        let bytes = bytes.0;
        std::fs::write(&path, &bytes).unwrap();
        check_nasa(&path, &bytes)?;
        check_generic(&path, &bytes)?;
        check_csv(&path, &bytes)?;
    }

    /// Mutations of a real NASA record (truncation, bit flips, inserted or deleted bytes and lines, a repeated
    /// header, a number replaced by garbage): no panic, errors name the file and a line of the input; and the
    /// pristine record read next in the same process gives exactly its reference result.
    #[test]
    fn mutated_real_record_errors_name_file_and_line_and_poison_nothing(
        edits in prop::collection::vec(mutation(), 1..5),
    ) {
        let reference = read_nasa_record(&good_path(), "B0005", 1, AMBIENT_K).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("05122.csv");
        let bytes = mutated(SAMPLE.as_bytes(), &edits);
        std::fs::write(&path, &bytes).unwrap();
        check_nasa(&path, &bytes)?;
        check_generic(&path, &bytes)?;
        check_csv(&path, &bytes)?;
        let again = read_nasa_record(&good_path(), "B0005", 1, AMBIENT_K).unwrap();
        assert_same(&reference, &again)?;
    }

    /// Valid generic CSVs (1-3 cycles, rows interleaved or not, columns in any order, optional temperature,
    /// cycle and unknown columns, CRLF, padded fields) read back exactly what was written.
    #[test]
    fn valid_generic_files_round_trip(file in generic_file()) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cellX.csv");
        std::fs::write(&path, file.text()).unwrap();
        let records = read_generic(&path, None).map_err(|e| TestCaseError::fail(format!("{e}\n{}", file.text())))?;
        prop_assert_eq!(records.len(), file.cycles.len());
        for (d, (cycle, rows)) in records.iter().zip(&file.cycles) {
            prop_assert_eq!(d.cycle, *cycle);
            prop_assert_eq!(&d.cell, "cellX");
            prop_assert_eq!(&d.time_s, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
            prop_assert_eq!(&d.voltage_v, &rows.iter().map(|r| r.1).collect::<Vec<_>>());
            prop_assert_eq!(&d.current_a, &rows.iter().map(|r| r.2).collect::<Vec<_>>());
            let temps: Vec<f64> = rows.iter().map(|r| r.3 + CELSIUS_TO_KELVIN).collect();
            if file.with_temperature {
                prop_assert_eq!(d.temperature_k.as_ref(), Some(&temps));
                prop_assert_eq!(d.ambient_k, temps[0]);
            } else {
                prop_assert!(d.temperature_k.is_none());
                prop_assert_eq!(d.ambient_k, 25.0 + CELSIUS_TO_KELVIN);
            }
        }
    }

    /// Valid Battery Data Format files (labels or machine names, or generic names with units; s or ms, V or
    /// mV, A or mA; 1-3 cycles; columns in any order; charge positive) read back what was written: one record
    /// per cycle, time from its start, within the rounding of the unit conversion.
    #[test]
    fn valid_bdf_files_round_trip(file in bdf_file()) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cellY.bdf.csv");
        std::fs::write(&path, file.text()).unwrap();
        let opts = ReadOptions { current_sign: CurrentSign::DischargeNegative, ..ReadOptions::default() };
        let (records, report) =
            read_csv(&path, &opts).map_err(|e| TestCaseError::fail(format!("{e}\n{}", file.text())))?;
        // Machine names in milli-units are not the format's own (its units are fixed), so they alone do not
        // make a file BDF.
        let (ms, mv, ma) = file.milli;
        let bdf = file.spelling == 0 || (file.spelling == 1 && !(ms && mv && ma));
        prop_assert_eq!(report.format, if bdf { "bdf" } else { "generic" });
        prop_assert_eq!(records.len(), file.cycles.len());
        let close = |a: &[f64], b: &[f64]| {
            a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-9 * (1.0 + y.abs()))
        };
        for (d, (cycle, rows)) in records.iter().zip(&file.cycles) {
            prop_assert_eq!(d.cycle, if file.with_cycle { *cycle } else { 1 });
            prop_assert_eq!(&d.cell, "cellY");
            let t0 = rows[0].0;
            prop_assert!(close(&d.time_s, &rows.iter().map(|r| r.0 - t0).collect::<Vec<_>>()), "time");
            prop_assert!(close(&d.voltage_v, &rows.iter().map(|r| r.1).collect::<Vec<_>>()), "voltage");
            prop_assert!(close(&d.current_a, &rows.iter().map(|r| r.2).collect::<Vec<_>>()), "current");
            let temps: Vec<f64> = rows.iter().map(|r| r.3 + CELSIUS_TO_KELVIN).collect();
            match &d.temperature_k {
                Some(t) => prop_assert!(file.with_temperature && close(t, &temps)),
                None => prop_assert!(!file.with_temperature),
            }
        }
        // Deciding the sign from these (random) rows either agrees or refuses, naming the file.
        match read_csv(&path, &ReadOptions::default()) {
            Ok((_, report)) => prop_assert!(report.signs[0].from_data),
            Err(e) => check_err(&e, &path, file.text().as_bytes())?,
        }
    }

    /// Valid NASA records (current negative while discharging, extra load columns) read back exactly, the
    /// current flipped to positive.
    #[test]
    fn valid_nasa_records_round_trip(rows in rows(), crlf in any::<bool>()) {
        let eol = if crlf { "\r\n" } else { "\n" };
        let mut text = format!("{}{eol}", NASA_COLS.join(","));
        for (t, v, i, c) in &rows {
            text += &format!("{v},{},{c},-2.0,3.0,{t}{eol}", -i);
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("01234.csv");
        std::fs::write(&path, &text).unwrap();
        let d = read_nasa_record(&path, "B0005", 7, AMBIENT_K).map_err(|e| TestCaseError::fail(e.to_string()))?;
        prop_assert_eq!((d.cycle, d.ambient_k), (7, AMBIENT_K));
        prop_assert_eq!(&d.time_s, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
        prop_assert_eq!(&d.voltage_v, &rows.iter().map(|r| r.1).collect::<Vec<_>>());
        prop_assert_eq!(&d.current_a, &rows.iter().map(|r| r.2).collect::<Vec<_>>());
        let temps: Vec<f64> = rows.iter().map(|r| r.3 + CELSIUS_TO_KELVIN).collect();
        prop_assert_eq!(d.temperature_k.as_ref(), Some(&temps));
    }
}

/// The pristine sample, written once per process.
fn good_path() -> PathBuf {
    static GOOD: std::sync::OnceLock<tempfile::TempDir> = std::sync::OnceLock::new();
    let dir = GOOD.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("05122.csv"), SAMPLE).unwrap();
        dir
    });
    dir.path().join("05122.csv")
}

proptest! {
    #![proptest_config(cases(256))]

    /// A folder with one corrupt B0005 record: reading B0005 either succeeds with the untouched records
    /// unchanged or fails naming exactly the corrupt file; B0006 and the other B0005 cycles still read.
    #[test]
    fn one_corrupt_cell_file_is_named_and_the_rest_still_reads(
        which in 0usize..3,
        edits in prop::collection::vec(mutation(), 1..4),
    ) {
        let pristine = NasaFolder::new();
        let (reference, _) = read_nasa(pristine.root.path(), "B0005", None).unwrap();
        let (reference6, _) = read_nasa(pristine.root.path(), "B0006", None).unwrap();
        let folder = NasaFolder::new();
        let bad = folder.data(B0005_FILES[which]);
        let bytes = mutated(file_text(which).as_bytes(), &edits);
        std::fs::write(&bad, &bytes).unwrap();
        let with_root = |d: &Discharge| -> Discharge {
            let mut d = d.clone();
            d.source = folder.root.path().join("data").join(d.source.file_name().unwrap());
            d
        };
        match read_nasa(folder.root.path(), "B0005", None) {
            Ok((records, report)) => {
                prop_assert!(report.missing_files.is_empty());
                prop_assert_eq!(records.len(), 3);
                for (k, (got, want)) in records.iter().zip(&reference).enumerate() {
                    if k == which {
                        check_ok(got, &bad)?;
                    } else {
                        assert_same(got, &with_root(want))?;
                    }
                }
            }
            Err(e) => {
                check_err(&e, &bad, &bytes)?;
                for (k, f) in B0005_FILES.iter().enumerate() {
                    if k != which {
                        prop_assert!(!e.to_string().contains(&folder.data(f).display().to_string()), "{e}");
                    }
                }
            }
        }
        // The skipping reader, deciding the sign from the data: the untouched records as the fixed-sign reader
        // read them, the corrupt one read or skipped naming it, never the whole cell refused.
        let (records, report) = read_nasa_with(folder.root.path(), "B0005", None, &ReadOptions::default())
            .map_err(|e| TestCaseError::fail(format!("one bad file failed the cell: {e}")))?;
        let bad_cycle = which as u32 + 1;
        prop_assert_eq!(records.len() + report.skipped.len(), 3);
        for s in &report.skipped {
            prop_assert_eq!(s.cycle, Some(bad_cycle));
            prop_assert!(s.reason.contains(&bad.display().to_string()), "{}", s.reason);
        }
        for d in &records {
            if d.cycle == bad_cycle {
                check_ok(d, &bad)?;
            } else {
                assert_same(d, &with_root(&reference[d.cycle as usize - 1]))?;
            }
        }
        // The other cell and the other cycles of this cell are unaffected.
        let (b6, _) = read_nasa(folder.root.path(), "B0006", None).unwrap();
        assert_same(&b6[0], &with_root(&reference6[0]))?;
        for k in (0..3).filter(|&k| k != which) {
            let cycle = k as u32 + 1;
            let (one, _) = read_nasa(folder.root.path(), "B0005", Some(&(cycle..=cycle))).unwrap();
            prop_assert_eq!(one.len(), 1);
            assert_same(&one[0], &with_root(&reference[k]))?;
        }
    }

    /// A damaged metadata.csv: Ok or an error naming metadata.csv (or a data file it names) with an existing
    /// line; never a record read from outside `data/`.
    #[test]
    fn damaged_metadata_is_named_and_never_leaves_the_data_folder(
        edits in prop::collection::vec(mutation(), 1..4),
    ) {
        let folder = NasaFolder::new();
        let meta = folder.root.path().join("metadata.csv");
        let bytes = mutated(METADATA.as_bytes(), &edits);
        std::fs::write(&meta, &bytes).unwrap();
        for cell in ["B0005", "B0006"] {
            match read_nasa(folder.root.path(), cell, None) {
                Ok((records, _)) => {
                    let data = folder.root.path().join("data");
                    for d in &records {
                        prop_assert_eq!(d.source.parent(), Some(data.as_path()));
                        check_ok(d, &d.source)?;
                    }
                }
                Err(DoctorError::NothingSelected { why }) => {
                    prop_assert!(why.contains(&meta.display().to_string()), "{why}");
                }
                Err(e) => {
                    let msg = e.to_string();
                    if msg.contains(&meta.display().to_string()) {
                        check_err(&e, &meta, &bytes)?;
                    } else {
                        // A data file named by the damaged metadata: one of ours, untouched, so this cannot be.
                        prop_assert!(false, "error names neither metadata.csv nor a bad data file: {msg}");
                    }
                }
            }
        }
    }
}

/// Metadata naming a file outside `data/` (a path, `..`, an absolute path) is refused, naming metadata.csv,
/// the line and the `filename` column, before anything is read.
#[test]
fn metadata_cannot_point_outside_the_data_folder() {
    for hostile in ["../../etc/passwd", "/etc/passwd", "../metadata.csv", "sub/00002.csv", "..", "."] {
        let folder = NasaFolder::new();
        let meta = folder.root.path().join("metadata.csv");
        std::fs::write(&meta, METADATA.replacen("00004.csv", hostile, 1)).unwrap();
        let msg = read_nasa(folder.root.path(), "B0005", None).unwrap_err().to_string();
        assert!(
            msg.contains(&meta.display().to_string()) && msg.contains("line 5") && msg.contains("filename"),
            "{hostile}: {msg}"
        );
        // Another cell's rows are not affected by the bad row.
        assert_eq!(read_nasa(folder.root.path(), "B0006", None).unwrap().0.len(), 1);
    }
}

/// A cycle number beyond u32 is refused naming file, line and column instead of being saturated (which
/// would merge distinct cycles).
#[test]
fn a_cycle_number_beyond_u32_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.csv");
    let mut text = String::from("time_s,voltage_v,current_a,cycle\n");
    for (k, c) in ["4294967296", "4294967297"].iter().enumerate() {
        for j in 0..12 {
            text += &format!("{},{},2.0,{c}\n", 10 * j, 4.0 - 0.01 * j as f64 - k as f64 * 0.1);
        }
    }
    std::fs::write(&path, &text).unwrap();
    let err = read_generic(&path, None).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, DoctorError::BadField { line: 2, .. }), "{msg}");
    assert!(msg.contains("big.csv") && msg.contains("cycle") && msg.contains("4294967296"), "{msg}");
}

/// Found by the properties: the csv crate counts a record's line from where it began skipping line ends,
/// one line early in a CRLF file and on the blank line before a record. Errors name the record's own line.
#[test]
fn error_lines_count_crlf_and_blank_lines() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("lines.csv");
    let rows: Vec<String> = (0..12).map(|k| format!("{},{},2.0", 10 * k, if k == 3 { "nan" } else { "3.9" })).collect();
    for (eol, blank, want) in [("\n", "", 5), ("\r\n", "", 5), ("\n", "\n\n", 7), ("\r\n", "\r\n", 6)] {
        let text = format!("time_s,voltage_v,current_a{eol}{blank}{}{eol}", rows.join(eol));
        std::fs::write(&path, &text).unwrap();
        let err = read_generic(&path, None).unwrap_err();
        assert!(matches!(err, DoctorError::BadField { line, .. } if line == want), "{eol:?} {blank:?}: {err}");
        assert_eq!(text.split('\n').nth(want as usize - 1).unwrap().trim_end(), "30,nan,2.0");
    }
    // A row with a field too many, after CRLF lines: the csv crate said line 3.
    std::fs::write(&path, "time_s,voltage_v,current_a\r\n0,3.9,2\r\n10,3.9,2,7\r\n").unwrap();
    let msg = read_generic(&path, None).unwrap_err().to_string();
    assert!(msg.contains("lines.csv") && msg.contains("line 3: 4 fields where the first row has 3"), "{msg}");
    // Invalid UTF-8 names line and field.
    std::fs::write(&path, b"time_s,voltage_v,current_a\r\n0,3.9,2\r\n\r\n10,3.\xff9,2\r\n").unwrap();
    let msg = read_generic(&path, None).unwrap_err().to_string();
    assert!(msg.contains("line 4, field 2: not valid UTF-8"), "{msg}");
}

/// Found by the properties: a NUL, a terminal escape or a byte-order mark in a field or header reached the
/// message raw, and a 700-digit field was quoted whole. They are shown escaped and shortened.
#[test]
fn hostile_values_are_shown_escaped_and_shortened() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.csv");
    let long = "9".repeat(700);
    for (value, shown) in
        [("\0", "`\\u{0}`"), ("\u{1b}[31m", "`\\u{1b}[31m`"), (long.as_str(), "... (700 characters)`")]
    {
        std::fs::write(&path, format!("time_s,voltage_v,current_a\n0,{value},2\n")).unwrap();
        let msg = read_generic(&path, None).unwrap_err().to_string();
        assert!(msg.contains(shown) && msg.len() < 300 && !msg.chars().any(char::is_control), "{msg:?}");
    }
    std::fs::write(&path, "\u{200b}time_s,voltage_v,current_a\n0,3.9,2\n").unwrap();
    let msg = read_generic(&path, None).unwrap_err().to_string();
    assert!(msg.contains("(found: \\u{200b}time_s,voltage_v,current_a)"), "{msg}");
}
