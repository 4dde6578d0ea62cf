//! `bcal calibrate --follow -|FILE`: one calibrator on readings as they arrive, from standard input or from
//! a file another process is still writing. Each line (CSV rows under a `time_s,voltage_v,current_a
//! [,temperature_c]` header, or JSON lines with those keys) goes through the stream the Python package
//! runs too (`bcal_calib::stream`, which also builds the calibrator), and its estimate, interval and EOD
//! prediction leave as
//! one JSON line on standard output as soon as they are computed. A bad line is reported on standard
//! error with its line number and skipped; end of input, `--idle-s` without a new line, or Ctrl-C
//! (SIGINT, SIGTERM) ends the loop with a summary on standard error.
//!
//! A reader thread hands complete lines to the loop over a channel, so the loop can stop on a signal
//! while the reader is blocked in a read.

use anyhow::{bail, Context};
use bcal_calib::stream::{
    resolve, CalibratorKind, Estimate, RangeEdges, Reading, Stream, WidthSource, LOAD_THRESHOLD_A,
};
use bcal_common::config::{Preset, TrainConfig};
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::policy::PolicyFile;
use bcal_doctor::read::{reading_columns, CurrentSign, NamedColumn, ReadingColumns};
use std::io::{BufRead, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How often a followed file is polled for new lines, and the loop checks for a stop.
const POLL: Duration = Duration::from_millis(20);

/// What `--follow` needs from `bcal calibrate`'s arguments.
pub struct FollowArgs {
    /// `-` (standard input) or a file.
    pub source: String,
    /// The calibrator: ukf, adaptive_ukf, ukf_learned, fit, uncalibrated or rl:FILE.
    pub calibrator: String,
    pub model: Option<PathBuf>,
    pub config: Option<PathBuf>,
    pub cutoff_v: Option<f64>,
    pub ambient_c: Option<f64>,
    pub current_sign: CurrentSign,
    pub idle_s: Option<f64>,
}

/// Events from the reader thread.
enum Event {
    /// A complete line and its number (1-based).
    Line(u64, String),
    /// End of input (a pipe or standard input closed).
    End,
    /// The source failed.
    Failed(String),
}

/// Reads `source` line by line into `tx`: standard input until it closes; a file from its start, then
/// every line appended to it, polling at [`POLL`] (only complete lines: a line still being written waits
/// for its newline).
fn reader(source: String, tx: Sender<Event>, unterminated: Arc<AtomicUsize>) {
    let send_lines = |buf: &mut Vec<u8>, line_no: &mut u64| -> bool {
        while let Some(nl) = buf.iter().position(|b| *b == b'\n') {
            let line: Vec<u8> = buf.drain(..=nl).collect();
            *line_no += 1;
            let text = String::from_utf8_lossy(&line).trim_end_matches(['\n', '\r']).to_string();
            if tx.send(Event::Line(*line_no, text)).is_err() {
                return false;
            }
        }
        // What waits for its newline, for the summary should the follow end first.
        unterminated.store(buf.len(), Ordering::SeqCst);
        true
    };
    let mut line_no = 0u64;
    let mut buf = Vec::new();
    if source == "-" {
        let stdin = std::io::stdin();
        let mut lock = stdin.lock();
        loop {
            match lock.read_until(b'\n', &mut buf) {
                Ok(0) => {
                    if !buf.is_empty() {
                        buf.push(b'\n');
                        send_lines(&mut buf, &mut line_no);
                    }
                    let _ = tx.send(Event::End);
                    return;
                }
                Ok(_) => {
                    if !send_lines(&mut buf, &mut line_no) {
                        return;
                    }
                }
                Err(e) => {
                    let _ = tx.send(Event::Failed(format!("reading standard input: {e}")));
                    return;
                }
            }
        }
    }
    let path = PathBuf::from(&source);
    let mut file = match std::fs::File::open(&path) {
        Ok(f) => f,
        Err(e) => {
            let _ = tx.send(Event::Failed(format!("cannot open {}: {e}", path.display())));
            return;
        }
    };
    let mut read_so_far = 0u64;
    let mut chunk = [0u8; 64 * 1024];
    loop {
        match file.read(&mut chunk) {
            Ok(0) => {
                // Nothing new: a file that shrank was replaced or truncated, and one whose path now names
                // another file was replaced (rotated); following either would mix two streams or miss one.
                if let Ok(meta) = std::fs::metadata(&path) {
                    if replaced(&file, &meta) {
                        let _ = tx.send(Event::Failed(format!(
                            "{} was replaced by another file while followed (rotated or moved); start the follow \
                             again on the new file",
                            path.display()
                        )));
                        return;
                    }
                    if meta.len() < read_so_far {
                        let _ = tx.send(Event::Failed(format!(
                            "{} shrank from {read_so_far} to {} bytes while followed (truncated or replaced); \
                             start the follow again on the new file",
                            path.display(),
                            meta.len()
                        )));
                        return;
                    }
                }
                std::thread::sleep(POLL);
            }
            Ok(n) => {
                read_so_far += n as u64;
                buf.extend_from_slice(&chunk[..n]);
                if !send_lines(&mut buf, &mut line_no) {
                    return;
                }
            }
            Err(e) => {
                let _ = tx.send(Event::Failed(format!("reading {}: {e}", path.display())));
                return;
            }
        }
    }
}

/// Whether `path_meta` (the followed path's metadata now) names another file than the one `file` reads.
#[cfg(unix)]
fn replaced(file: &std::fs::File, path_meta: &std::fs::Metadata) -> bool {
    use std::os::unix::fs::MetadataExt;
    file.metadata().is_ok_and(|m| (m.dev(), m.ino()) != (path_meta.dev(), path_meta.ino()))
}

#[cfg(not(unix))]
fn replaced(_file: &std::fs::File, _path_meta: &std::fs::Metadata) -> bool {
    false
}

/// The layout of the lines, decided by the first one that is not empty or a `#` comment.
enum Layout {
    /// CSV under a header: where each quantity is and its unit, how many fields a row has, what separates them
    /// (`bcal_doctor::read::delimiter`) and, where that is not the comma, whether the decimal mark is the comma:
    /// the first value with a comma or a point says (as `bcal_doctor::read::decimal_comma` reads a file), and a
    /// value with the other mark is refused.
    Csv { columns: Box<ReadingColumns>, width: usize, delimiter: u8, decimal_comma: std::cell::Cell<Option<bool>> },
    /// One JSON object per line, its keys read as a CSV header is.
    Json,
}

const JSON_HINT: &str =
    "or give JSON lines like {\"time_s\": 0, \"voltage_v\": 4.1, \"current_a\": 2.0, \"temperature_c\": 24}";

fn csv_fields(line: &str, delimiter: u8) -> Result<Vec<String>, String> {
    let mut rdr =
        csv::ReaderBuilder::new().has_headers(false).flexible(true).delimiter(delimiter).from_reader(line.as_bytes());
    match rdr.records().next() {
        Some(Ok(r)) => Ok(r.iter().map(|f| f.trim().to_string()).collect()),
        Some(Err(e)) => Err(format!("not a CSV row ({e})")),
        None => Ok(Vec::new()),
    }
}

/// A reading from the fields `value` gives for each column: time, voltage and current required, the
/// temperature read as missing (the stream fills it in) where it gives none; each converted by its column's unit.
fn reading_of(
    c: &ReadingColumns,
    value: impl Fn(&NamedColumn) -> Result<Option<f64>, String>,
) -> Result<Reading, String> {
    let need = |col: &NamedColumn| -> Result<f64, String> {
        Ok(col.si(value(col)?.ok_or_else(|| format!("no value for `{}`", col.name))?))
    };
    let temperature_c = match &c.temperature {
        Some(col) => value(col)?.map(|t| col.si(t)),
        None => None,
    };
    Ok(Reading { time_s: need(&c.time)?, voltage_v: need(&c.voltage)?, current_a: need(&c.current)?, temperature_c })
}

impl Layout {
    /// The layout a first line sets; an error names what the header lacks.
    fn from_first(line: &str) -> Result<Self, String> {
        if line.trim_start().starts_with('{') {
            return Ok(Layout::Json);
        }
        let delimiter = bcal_doctor::read::delimiter(line.as_bytes());
        let names = csv_fields(line, delimiter)?;
        let refs: Vec<&str> = names.iter().map(String::as_str).collect();
        let columns = reading_columns(&refs)
            .map_err(|e| format!("the header `{}`: {e}; {JSON_HINT}", bcal_common::text::shown(line, 80)))?;
        let decimal_comma = std::cell::Cell::new((delimiter == b',').then_some(false));
        Ok(Layout::Csv { columns: Box::new(columns), width: names.len(), delimiter, decimal_comma })
    }

    /// One reading from a data line, in s, V, A and deg C, current with the sign as written (the caller
    /// applies the stream's convention).
    fn parse(&self, line: &str) -> Result<Reading, String> {
        let number = |field: &str, text: &str, decimal_comma: &std::cell::Cell<Option<bool>>| -> Result<f64, String> {
            let text = text.trim();
            if decimal_comma.get().is_none() {
                decimal_comma.set(bcal_doctor::read::decimal_mark(text));
            }
            bcal_doctor::read::decimal(text, decimal_comma.get() == Some(true))
                .ok_or_else(|| format!("field `{field}` = `{}` is not a number", bcal_common::text::shown(text, 40)))
        };
        match self {
            Layout::Csv { columns, width, delimiter, decimal_comma } => {
                let f = csv_fields(line, *delimiter)?;
                if f.len() != *width {
                    return Err(format!("{} fields where the header has {width}", f.len()));
                }
                reading_of(columns, |c| match f[c.index].as_str() {
                    "" => Ok(None),
                    text => number(&c.name, text, decimal_comma).map(Some),
                })
            }
            Layout::Json => {
                let v: serde_json::Value =
                    serde_json::from_str(line).map_err(|e| format!("not a JSON object ({e})"))?;
                let object = v.as_object().ok_or_else(|| format!("not a JSON object: {}", v))?;
                let keys: Vec<&str> = object.keys().map(String::as_str).collect();
                let columns = reading_columns(&keys)?;
                reading_of(&columns, |c| match &object[keys[c.index]] {
                    serde_json::Value::Null => Ok(None),
                    x => x.as_f64().map(Some).ok_or_else(|| format!("key `{}` = {x} is not a number", c.name)),
                })
            }
        }
    }
}

/// Sets `flag` on SIGINT or SIGTERM (registered before this returns, so no signal is missed).
fn stop_on_signals(flag: Arc<AtomicBool>) -> anyhow::Result<()> {
    use tokio::signal::unix::{signal, SignalKind};
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let (mut int, mut term) = {
        let _guard = rt.enter();
        (signal(SignalKind::interrupt())?, signal(SignalKind::terminate())?)
    };
    std::thread::spawn(move || {
        rt.block_on(async {
            tokio::select! {
                _ = int.recv() => {}
                _ = term.recv() => {}
            }
        });
        flag.store(true, Ordering::SeqCst);
    });
    Ok(())
}

/// Why the loop ended.
#[derive(Debug, PartialEq)]
enum Ended {
    EndOfInput,
    Signal,
    Idle(f64),
    OutputClosed,
}

/// Runs the follow loop; errors before the first reading (bad options, files, a header without the
/// columns) end it at once.
pub fn run(a: FollowArgs) -> anyhow::Result<()> {
    // The calibrator: kind, its policy, the cell's config and model.
    let (kind, policy_path) = match a.calibrator.trim().split_once(':') {
        Some(("rl", p)) => (CalibratorKind::Rl, Some(PathBuf::from(p))),
        _ => (a.calibrator.parse::<CalibratorKind>()?, None),
    };
    if kind == CalibratorKind::Rl && policy_path.is_none() {
        bail!("--calibrator rl needs its policy file: --calibrator rl:FILE.bcalpol");
    }
    let policy = policy_path
        .as_deref()
        .map(|p| PolicyFile::load(p).with_context(|| format!("the RL policy {}", p.display())))
        .transpose()?;
    let net = policy.as_ref().map(|p| p.net()).transpose()?;
    let config = a
        .config
        .as_deref()
        .map(|p| -> anyhow::Result<MeasuredSpec> {
            let c = TrainConfig::from_file_over(p, Preset::Measured)?;
            c.validate().with_context(|| format!("config {}", p.display()))?;
            Ok(c.measured)
        })
        .transpose()?;
    let reference_k = a.ambient_c.map(|c| c + bcal_common::measured::scenario::KELVIN_0C);
    let diagnosed = a.model.as_deref().map(bcal_doctor::model_file::load_model).transpose()?;
    if let Some(note) = diagnosed.as_ref().and_then(|m| m.carrying_note()) {
        eprintln!("--model: {note}");
    }
    if let Some(m) = diagnosed.as_ref().filter(|m| !m.latest_cycles.is_empty()) {
        let (first, last) = (m.latest_cycles[0], m.latest_cycles[m.latest_cycles.len() - 1]);
        eprintln!("--model: its per-cycle parameters start at the median of training cycles {first}-{last}'s fits");
    }
    let model = diagnosed.as_ref().map(|m| m.extension(reference_k));
    let policy_name = policy_path.as_ref().map(|p| p.display().to_string()).unwrap_or_default();
    let mut setup =
        resolve(kind, config.as_ref(), policy.as_ref().map(|p| (&p.task, policy_name.as_str())), model.as_ref())?;
    if let Some(v) = a.cutoff_v {
        setup.spec.tracker.cutoff_v = v;
    }
    // Without the cell's config or a cut-off given, the diagnosis's cut-off where it was the cell's own.
    if let (None, None, Some(m)) = (&config, a.cutoff_v, &diagnosed) {
        if let Some(said) = m.settle_stream(&mut setup.spec.tracker) {
            eprintln!("--model: {said}");
        }
    }
    // A diagnosis's capacity lifetime model moves the carried value when the cell's config gave none.
    if let (None, Some(p)) = (&setup.spec.lifetime, &a.model) {
        setup.spec.lifetime = bcal_doctor::model_file::load_lifetime(p)?;
    }
    if let Some(l) = &setup.spec.lifetime {
        eprintln!(
            "lifetime model: each discharge starts from the last one's value moved by {:+.4} Ah per discharge{}",
            l.per_cycle,
            if l.amplitude > 0.0 {
                format!(
                    " and up to {:.3} Ah regained over a rest (time constant {:.1} h)",
                    l.amplitude,
                    l.tau_rest_s / 3600.0
                )
            } else {
                String::new()
            }
        );
    }
    let spec = setup.spec.tracker.clone();
    let mut stream = Stream::of(&setup, net.as_ref(), a.ambient_c)?;
    // Every discharge the stream follows to its cut-off is fitted, as `bcal calibrate` fits every discharge
    // that ends: the diagnosis's per-cycle values refitted with qMobile and Ro, on the base model qMobile and
    // Ro; the next discharge blends with that fit carried over and starts from the end fit at its Ro.
    let (cutoff_v, reference_k) = (setup.spec.tracker.cutoff_v, setup.spec.tracker.model.reference_k);
    if diagnosed.as_ref().is_some_and(|m| m.causes.iter().any(|c| !c.cycle_params().is_empty())) {
        eprintln!("--model: its per-cycle parameters refitted on every discharge that reaches the cut-off");
    }
    let base = setup.spec.tracker.model.clone();
    stream = stream.with_refit(Box::new(bcal_doctor::model_file::stream_refit(diagnosed, base, cutoff_v, reference_k)));
    // The current's sign: positive discharges unless told otherwise (a stream cannot be read ahead to
    // decide, so `auto` takes the documented convention).
    let sign = if a.current_sign == CurrentSign::DischargeNegative { -1.0 } else { 1.0 };

    let stop = Arc::new(AtomicBool::new(false));
    stop_on_signals(stop.clone())?;
    if a.source != "-" && Path::new(&a.source).is_dir() {
        bail!(
            "--follow {}: a folder, not a log: give the file another process writes (a folder of records is read \
             by bcal calibrate --data)",
            a.source
        );
    }
    if a.source != "-" && !Path::new(&a.source).is_file() {
        bail!("--follow {}: no such file (give a file another process writes, or - for standard input)", a.source);
    }
    let (tx, rx): (Sender<Event>, Receiver<Event>) = mpsc::channel();
    let source = a.source.clone();
    let unterminated = Arc::new(AtomicUsize::new(0));
    let pending = Arc::clone(&unterminated);
    std::thread::spawn(move || reader(source, tx, pending));
    eprintln!(
        "follow: {} on {} (model {}, cut-off {} V, prior q_mobile {} C, r_o {} ohm); one JSON line per reading",
        kind.name(),
        if a.source == "-" { "standard input".to_string() } else { a.source.clone() },
        spec.model.label(),
        spec.cutoff_v,
        spec.prior.q_mobile_c,
        spec.prior.r_o_ohm
    );

    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    let mut layout: Option<Layout> = None;
    let mut skipped: Vec<u64> = Vec::new();
    let mut watch = Watches { sign: SignWatch::default(), temperature: TemperatureWatch::new(&spec) };
    let mut last = None;
    let mut step_us: Vec<f64> = Vec::new();
    let mut last_line_at = Instant::now();
    // Whether the fits at an edge of the ranges were said (once, as soon as a discharge hands one on).
    let mut edges_said = false;
    let ended = loop {
        if !edges_said {
            if let Some(text) = at_edge_text(&stream) {
                eprintln!("follow: {text}");
                edges_said = true;
            }
        }
        if stop.load(Ordering::SeqCst) {
            break Ended::Signal;
        }
        if let Some(idle) = a.idle_s.filter(|s| last_line_at.elapsed().as_secs_f64() > *s) {
            break Ended::Idle(idle);
        }
        let (line_no, line) = match rx.recv_timeout(POLL) {
            Ok(Event::Line(n, l)) => (n, l),
            Ok(Event::End) | Err(RecvTimeoutError::Disconnected) => break Ended::EndOfInput,
            Ok(Event::Failed(why)) => bail!("{why}"),
            Err(RecvTimeoutError::Timeout) => continue,
        };
        last_line_at = Instant::now();
        if line.trim().is_empty() || line.trim_start().starts_with('#') {
            continue;
        }
        // A CSV header again (files joined, a logger restarted): the rows after it are read by it, whatever
        // order or units it names (read by the first one they would be scrambled or refused).
        // (Only a line with letters beyond an exponent's is tried: a data row is parsed once.)
        let wordy = line.bytes().any(|b| b.is_ascii_alphabetic() && !matches!(b, b'e' | b'E'));
        if wordy && matches!(layout, Some(Layout::Csv { .. })) {
            if let Ok(again @ Layout::Csv { .. }) = Layout::from_first(&line) {
                eprintln!("line {line_no}: a header again: the rows after it are read by it");
                layout = Some(again);
                continue;
            }
        }
        let Some(lay) = &layout else {
            layout = Some(Layout::from_first(&line).map_err(|why| anyhow::anyhow!("line {line_no}: {why}"))?);
            if let Some(Layout::Csv { columns, .. }) = &layout {
                if columns.temperature.is_none() && watch.temperature.thermal {
                    bail!("line {line_no}: {}", TemperatureWatch::NO_COLUMN);
                }
                continue;
            }
            // A JSON first line is a reading too: take it below.
            let lay = layout.as_ref().expect("set above");
            if let Some(e) = take(lay, &line, line_no, sign, &mut stream, &mut watch, &mut step_us, &mut skipped) {
                if emit(&mut out, line_no, &e).is_err() {
                    break Ended::OutputClosed;
                }
                last = Some(e);
            }
            continue;
        };
        if let Some(e) = take(lay, &line, line_no, sign, &mut stream, &mut watch, &mut step_us, &mut skipped) {
            if emit(&mut out, line_no, &e).is_err() {
                break Ended::OutputClosed;
            }
            last = Some(e);
        }
    };
    drop(out);
    // A last line without its newline when a followed file went idle or the follow was stopped (a writer
    // that died mid-line): said, not taken (standard input's end takes it as a line).
    let tail = unterminated.load(Ordering::SeqCst);
    if tail > 0 && !matches!(ended, Ended::EndOfInput) {
        eprintln!("follow: the last {tail} bytes had no newline when the follow ended (a line cut short): not read");
    }
    eprintln!("{}", summary(&ended, &stream, &skipped, last.as_ref(), &step_us));
    Ok(())
}

/// What the loop watches the readings for, to say once on stderr.
struct Watches {
    sign: SignWatch,
    temperature: TemperatureWatch,
}

/// A model with the doctor's `thermal` runs on the measured temperature: a stream without one runs it at the
/// ambient, which a CSV header without the column refuses (as `bcal calibrate --data` refuses such records)
/// and a JSON line without the key says, once.
struct TemperatureWatch {
    thermal: bool,
    seen: bool,
    said: bool,
}

impl TemperatureWatch {
    const NO_COLUMN: &'static str = "the header has no temperature column, and the model's `thermal` cause runs on \
                                     the cell's measured temperature: give readings with temperature_c, or --model \
                                     a diagnosis without `thermal` (bcal diagnose names the causes)";

    fn new(spec: &bcal_common::measured::TrackerSpec) -> Self {
        Self { thermal: spec.use_measured_temperature, seen: false, said: false }
    }

    fn see(&mut self, r: &Reading) -> Option<&'static str> {
        self.seen |= r.temperature_c.is_some();
        if !self.thermal || self.seen || self.said {
            return None;
        }
        self.said = true;
        Some(
            "no temperature, nor any before: the model's `thermal` cause runs at the ambient (--ambient-c, else the \
             model's) until a reading gives one",
        )
    }
}

/// Watches for a charge whose voltage falls: a discharge written with the other sign (a stream cannot be read
/// ahead, so `--current-sign auto` takes discharges positive). Said once on stderr.
#[derive(Default)]
struct SignWatch {
    /// Where the present run of charging readings began: time s, voltage V.
    start: Option<(f64, f64)>,
    warned: bool,
}

/// A charge read for this long ...
const SIGN_WATCH_S: f64 = 300.0;
/// ... whose voltage fell by this much is a discharge, V (a charge's voltage rises, or holds under CV).
const SIGN_WATCH_FALL_V: f64 = 0.1;
/// A current this negative counts as charging, A.
const SIGN_WATCH_A: f64 = -0.5;

impl SignWatch {
    /// `r` with the stream's sign applied; `flipped`: the sign was `--current-sign discharge-negative`.
    fn see(&mut self, r: &Reading, flipped: bool) -> Option<String> {
        if r.current_a > LOAD_THRESHOLD_A {
            // A discharge: the run of charging readings is over.
            self.start = None;
            return None;
        }
        // Rests and a charge's tail (the off halves of a square wave, too) neither start nor end a run.
        if r.current_a > SIGN_WATCH_A {
            return None;
        }
        let (t0, v0) = *self.start.get_or_insert((r.time_s, r.voltage_v));
        if self.warned || r.time_s - t0 < SIGN_WATCH_S || v0 - r.voltage_v < SIGN_WATCH_FALL_V {
            return None;
        }
        self.warned = true;
        let what = if flipped {
            "a discharge written positive? leave out --current-sign discharge-negative"
        } else {
            "a discharge written negative? give --current-sign discharge-negative"
        };
        Some(format!(
            "the current has been charging for {:.0} s while the voltage fell from {v0:.3} to {:.3} V: {what} \
             (estimates so far read it as a charge)",
            r.time_s - t0,
            r.voltage_v
        ))
    }
}

/// What the discharges whose fit sat at an edge of the setting's ranges say ([`RangeEdges`]; None where none
/// did): a cell outside the ranges is followed at their edge, and its ends are far off.
fn at_edge_text(stream: &Stream) -> Option<String> {
    let e: RangeEdges = stream.range_edges();
    if e.at_edge == 0 {
        return None;
    }
    let [q_range, r_range] = stream.setting_ranges();
    let mut parts = Vec::new();
    for (k, (name, unit, range)) in [("q_mobile", "C", q_range), ("r_o", "ohm", r_range)].into_iter().enumerate() {
        for (j, edge) in ["floor", "top"].into_iter().enumerate() {
            let n = e.by_edge[k][j];
            if n > 0 {
                parts.push(format!("{name} at its {edge}, {} {unit}: {n}", range[j]));
            }
        }
    }
    let widened = stream.widened_ranges().map_or(String::new(), |[q, r]| {
        format!(
            "; after {} in a row at an edge the stream widened them, to qMobile {:.0}-{:.0} C and Ro {:.3}-{:.3} ohm",
            bcal_calib::stream::EDGE_RUN,
            q[0],
            q[1],
            r[0],
            r[1]
        )
    });
    Some(format!(
        "{} of {} discharge{} handed on a fit at the edge of the setting's ranges ({}){widened}: a cell outside \
         them is followed at their edge, its predictions off; where most discharges do, follow it on its own \
         setting (bcal cell-config --data DIR --cell ID --out CELL.toml on its records, then --config CELL.toml)",
        e.at_edge,
        e.discharges,
        if e.discharges == 1 { "" } else { "s" },
        parts.join("; ")
    ))
}

/// Parses and steps one data line: the estimate, or None (reported on standard error, counted in
/// `skipped`) for a bad line.
#[allow(clippy::too_many_arguments)]
fn take(
    layout: &Layout,
    line: &str,
    line_no: u64,
    sign: f64,
    stream: &mut Stream,
    watch: &mut Watches,
    step_us: &mut Vec<f64>,
    skipped: &mut Vec<u64>,
) -> Option<Estimate> {
    let started = Instant::now();
    let result = layout.parse(line).and_then(|r| {
        let r = Reading { current_a: sign * r.current_a, ..r };
        if let Some(why) = watch.sign.see(&r, sign < 0.0) {
            eprintln!("line {line_no}: {why}");
        }
        if let Some(why) = watch.temperature.see(&r) {
            eprintln!("line {line_no}: {why}");
        }
        stream.step(&r).map_err(|e| e.to_string())
    });
    match result {
        Ok(e) => {
            step_us.push(started.elapsed().as_secs_f64() * 1e6);
            Some(e)
        }
        Err(why) => {
            eprintln!("line {line_no}: {why}; skipped");
            skipped.push(line_no);
            None
        }
    }
}

/// Writes one estimate as a JSON line and flushes it.
fn emit(out: &mut impl Write, line_no: u64, e: &Estimate) -> std::io::Result<()> {
    let mut v = serde_json::to_value(e).map_err(std::io::Error::other)?;
    v["line"] = serde_json::json!(line_no);
    writeln!(out, "{v}")?;
    out.flush()
}

fn summary(ended: &Ended, stream: &Stream, skipped: &[u64], last: Option<&Estimate>, step_us: &[f64]) -> String {
    let (readings, discharges) = (stream.readings(), stream.discharges());
    let why = match ended {
        Ended::EndOfInput => "end of input".to_string(),
        Ended::Signal => "stopped (Ctrl-C / SIGTERM)".to_string(),
        Ended::Idle(s) => format!("no new line for {s} s (--idle-s)"),
        Ended::OutputClosed => "standard output closed".to_string(),
    };
    let mut s = format!(
        "follow: {why}: {readings} readings taken, {} bad line{} skipped",
        skipped.len(),
        if skipped.len() == 1 { "" } else { "s" }
    );
    if !skipped.is_empty() {
        let shown: Vec<String> = skipped.iter().take(20).map(u64::to_string).collect();
        s.push_str(&format!(" (lines {}{})", shown.join(", "), if skipped.len() > 20 { ", ..." } else { "" }));
    }
    s.push_str(&format!("; {discharges} discharge{}", if discharges == 1 { "" } else { "s" }));
    if let Some((sd, source)) = stream.prior_width() {
        let spec = stream.spec();
        let span = |[lo, hi]: [f64; 2]| hi - lo;
        let from = match source {
            WidthSource::Learned => "learned from the changes between the ones before",
            WidthSource::Posterior => "the one before's own posterior",
        };
        s.push_str(&format!(
            " (the last from a prior width {from}: sd q_mobile {:.0} C, r_o {:.4} ohm)",
            sd[0] * span(spec.q_mobile_range_c),
            sd[1] * span(spec.r_o_range_ohm)
        ));
    }
    let widening = stream.eod_widening();
    if let Some(n) = widening.iter().flatten().map(|w| w.1).max() {
        let shown: Vec<String> = bcal_calib::widening::EOD_FRACTIONS_PCT
            .iter()
            .zip(widening)
            .map(|(f, w)| format!("{f} %: {}", w.map_or("-".to_string(), |w| format!("+-{:.1} %", 100.0 * w.0))))
            .collect();
        s.push_str(&format!(
            "; EOD 90 % intervals learned on the last {n} discharges that reached the cut-off ({} of the predicted \
             duration)",
            shown.join(", ")
        ));
    }
    let held: Vec<String> = bcal_calib::widening::EOD_FRACTIONS_PCT
        .iter()
        .zip(stream.prior_serves())
        .filter(|(_, on)| *on)
        .map(|(f, _)| format!("{f} %"))
        .collect();
    if !held.is_empty() {
        s.push_str(&format!(
            "; the prior alone predicts the end at {} of a discharge (it beat the calibrator's, recentred where that \
             serves, there on at least 8 of the last 10)",
            held.join(", ")
        ));
    }
    let on_voltage: Vec<String> = bcal_calib::widening::EOD_FRACTIONS_PCT
        .iter()
        .zip(stream.voltage_serves())
        .zip(stream.prior_serves())
        .filter(|((_, on), prior)| *on && !*prior)
        .map(|((f, _), _)| format!("{f} %"))
        .collect();
    if !on_voltage.is_empty() {
        s.push_str(&format!(
            "; its own prediction moved by the error its last 15 discharges expect at the voltage against the one \
             before gives the end at {} of a discharge (it beat the recentring there on at least 8 of the last 10)",
            on_voltage.join(", ")
        ));
    }
    let moved: Vec<String> = bcal_calib::widening::EOD_FRACTIONS_PCT
        .iter()
        .zip(stream.recentred_serves())
        .zip(stream.prior_serves().iter().zip(stream.voltage_serves()).map(|(p, v)| *p || v))
        .filter(|((_, on), other)| *on && !*other)
        .map(|((f, _), _)| format!("{f} %"))
        .collect();
    if !moved.is_empty() {
        s.push_str(&format!(
            "; its own prediction moved by its median error over the last 10 discharges gives the end at {} of a \
             discharge (it beat the unmoved one there on at least 8 of them)",
            moved.join(", ")
        ));
    }
    // Per share, a blend's weights as "10 %: 0.40, ..." (None when no share has one yet).
    let per_share = |weights: [Option<f64>; 3]| -> Option<String> {
        weights.iter().any(Option::is_some).then(|| {
            let shown: Vec<String> = bcal_calib::widening::EOD_FRACTIONS_PCT
                .iter()
                .zip(weights)
                .map(|(f, w)| format!("{f} %: {}", w.map_or("-".to_string(), |w| format!("{w:.2}"))))
                .collect();
            shown.join(", ")
        })
    };
    if let Some(shown) = per_share(stream.prior_blend_weights()) {
        s.push_str(&format!(
            "; where the prior alone does not predict alone, the end is blended with it, the prior's weight by the \
             two records over the last 15 discharges ({shown})"
        ));
    }
    if let Some(shown) = per_share(stream.previous_blend_weights()) {
        s.push_str(&format!(
            "; after rests of up to a day that blend is blended with the previous discharge's fit carried over, \
             its weight ({shown})"
        ));
    }
    if let Some(shown) = per_share(stream.learned_weights()) {
        s.push_str(&format!(
            "; what those rules deliver is moved by the error the learner on the stream's record expects of it, the moved end's weight by the two records over the last 15 discharges ({shown})"
        ));
    }
    if stream.clock_changes() > 0 {
        s.push_str(&format!(
            "; the readings' clock went back by more than half an hour and stayed there {} time(s): the stream took \
             it after {} readings in a row on it (the ones before were refused)",
            stream.clock_changes(),
            bcal_calib::stream::CLOCK_BACK_READINGS
        ));
    }
    if let Some(text) = at_edge_text(stream) {
        s.push_str(&format!("; {text}"));
    }
    if let Some(e) = last {
        s.push_str(&format!(
            "; last estimate at {} s: q_mobile {:.1} C, r_o {:.5} ohm, EOD {}{}",
            e.time_s,
            e.q_mobile,
            e.r_o,
            e.eod_s.map_or("-".to_string(), |t| format!("{t:.0} s")),
            e.eod_lo_s.zip(e.eod_hi_s).map_or(String::new(), |(lo, hi)| format!(" ({lo:.0}-{hi:.0} s)"))
        ));
    }
    if !step_us.is_empty() {
        let mut v = step_us.to_vec();
        v.sort_by(f64::total_cmp);
        s.push_str(&format!(
            "; parse + step + predict per reading: median {:.0} us, max {:.0} us",
            v[v.len() / 2],
            v[v.len() - 1]
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A discharge written negative reads as a charge whose voltage falls: said once, after five minutes; a
    /// real charge (its voltage rising, then held) and short negative pulses are not.
    #[test]
    fn a_charge_whose_voltage_falls_is_named_once() {
        let at = |t: f64, v: f64, i: f64| Reading { time_s: t, voltage_v: v, current_a: i, temperature_c: None };
        let falling = |i: f64| (0..100).map(move |k| at(10.0 * k as f64, 4.1 - 0.002 * k as f64, i));
        let said = |readings: &mut dyn Iterator<Item = Reading>, flipped: bool| -> Vec<String> {
            let mut w = SignWatch::default();
            readings.filter_map(|r| w.see(&r, flipped)).collect()
        };
        let plain = said(&mut falling(-2.0), false);
        assert!(plain.len() == 1 && plain[0].contains("give --current-sign discharge-negative"), "{plain:?}");
        // The same under --current-sign discharge-negative: leave it out.
        let flipped = said(&mut falling(-2.0), true);
        assert!(flipped.len() == 1 && flipped[0].contains("leave out --current-sign"), "{flipped:?}");
        // A square wave written negative (its off halves at rest) is named too.
        let mut square = (0..100).map(|k| at(10.0 * k as f64, 4.1 - 0.002 * k as f64, -4.0 * f64::from(k % 2 == 0)));
        assert_eq!(said(&mut square, false).len(), 1);
        // A charge (constant current, its voltage rising, then constant voltage, the current tapering) is not.
        let mut cc_cv = (0..200).map(|k| {
            let v = (3.6 + 0.01 * k as f64).min(4.2);
            at(10.0 * k as f64, v, if v < 4.2 { -1.5 } else { -1.5 * (-0.05 * (k - 60) as f64).exp() })
        });
        assert!(said(&mut cc_cv, false).is_empty());
        // Nor short negative pulses within a discharge.
        let mut pulsed =
            (0..100).map(|k| at(10.0 * k as f64, 4.0 - 0.002 * k as f64, if k % 10 == 0 { -2.0 } else { 2.0 }));
        assert!(said(&mut pulsed, false).is_empty());
    }

    #[test]
    fn csv_header_finds_columns_in_any_order_and_names_what_is_missing() {
        let l = Layout::from_first("current_a, time_s,voltage_v").unwrap();
        let r = l.parse("2.0,10,3.9").unwrap();
        assert_eq!(r, Reading { time_s: 10.0, voltage_v: 3.9, current_a: 2.0, temperature_c: None });
        assert!(l.parse("2.0,abc,3.9").unwrap_err().contains("field `time_s` = `abc` is not a number"));
        assert!(l.parse("2.0,10").unwrap_err().contains("2 fields where the header has 3"));
        assert!(l.parse("2.0,,3.9").unwrap_err().contains("no value for `time_s`"));
        let e = Layout::from_first("time_s,volts,current_a").err().unwrap();
        assert!(e.contains("no voltage among `time_s,volts,current_a`") && e.contains("JSON lines"), "{e}");
    }

    /// A stream whose fields a semicolon separates (a decimal comma read as a point) or a tab reads as the CSV
    /// readers read the same file; under commas a decimal comma stays a bad field.
    #[test]
    fn semicolons_and_tabs_separate_fields_as_the_readers_take_them() {
        let want = Reading { time_s: 10.5, voltage_v: 3.9, current_a: 2.0, temperature_c: Some(24.25) };
        let l = Layout::from_first("time_s;voltage_v;current_a;temperature_c").unwrap();
        assert_eq!(l.parse("10,5;3,9;2;24,25").unwrap(), want);
        // The first mark sets the stream's: a point then is a thousands separator or another locale, refused.
        assert!(l.parse("10.5;3.9;2.0;24.25").unwrap_err().contains("` is not a number"));
        let l = Layout::from_first("time_s;voltage_v;current_a;temperature_c").unwrap();
        assert_eq!(l.parse("10.5;3.9;2.0;24.25").unwrap(), want);
        assert!(l.parse("1,050;3.9;2.0;24.25").unwrap_err().contains("`1,050` is not a number"));
        let l = Layout::from_first("time_s\tvoltage_v\tcurrent_a\ttemperature_c").unwrap();
        assert_eq!(l.parse("10.5\t3.9\t2\t24.25").unwrap(), want);
        let l = Layout::from_first("time_s,voltage_v,current_a,temperature_c").unwrap();
        assert!(l.parse("\"10,5\",3.9,2,24.25").unwrap_err().contains("field `time_s` = `10,5` is not a number"));
    }

    /// A stream logged in milliseconds, millivolts and milliamperes (or NASA's own record columns) is read
    /// as the CSV readers read the same file: each column in the unit its name gives.
    #[test]
    fn a_header_in_other_units_is_converted_as_the_readers_convert_it() {
        let l = Layout::from_first("time_ms,voltage_mv,current_ma,temperature_c").unwrap();
        let r = l.parse("1500,3900,2000,").unwrap();
        assert_eq!(r, Reading { time_s: 1.5, voltage_v: 3.9, current_a: 2.0, temperature_c: None });
        let l =
            Layout::from_first("Voltage_measured,Current_measured,Temperature_measured,Current_load,Voltage_load,Time")
                .unwrap();
        let r = l.parse("4.19,-2.01,24.3,-2.0,3.0,18.7").unwrap();
        assert_eq!(r, Reading { time_s: 18.7, voltage_v: 4.19, current_a: -2.01, temperature_c: Some(24.3) });
        let e = Layout::from_first("Time (fortnights),voltage_v,current_a").err().unwrap();
        assert!(e.contains("is read in s, ms, min or h"), "{e}");
    }

    #[test]
    fn json_lines_take_optional_temperature_and_units_in_their_keys() {
        let l = Layout::from_first("{\"time_s\": 1}").unwrap();
        let r = l.parse("{\"time_s\": 1, \"voltage_v\": 4.0, \"current_a\": 0.5, \"temperature_c\": 25}").unwrap();
        assert_eq!(r.temperature_c, Some(25.0));
        let r =
            l.parse("{\"time_ms\": 1000, \"voltage_v\": 4.0, \"current_ma\": 500, \"temperature_c\": null}").unwrap();
        assert_eq!(r, Reading { time_s: 1.0, voltage_v: 4.0, current_a: 0.5, temperature_c: None });
        assert!(l.parse("{\"time_s\": 1, \"current_a\": 0.5}").unwrap_err().contains("no voltage among"));
        assert!(l
            .parse("{\"time_s\": 1, \"voltage_v\": \"x\", \"current_a\": 0.5}")
            .unwrap_err()
            .contains("key `voltage_v`"));
        assert!(l.parse("time_s,1").unwrap_err().contains("not a JSON object"));
        assert!(l.parse("[1, 2]").unwrap_err().contains("not a JSON object"));
    }
}
