//! The outputs of `bcal calibrate`: `calibration.json` ([`CalibrationReport`]; per calibrator
//! `capacity_rmse_ah` and `eod_error_pct` keyed by the fraction seen, and `coverage_90_pct`),
//! `calibration.md` (the tables and a reading generated from the numbers), the per-reading CSV of every
//! calibrator and cycle, and the figures: estimated against measured capacity over the cell's life, the
//! end-of-discharge error against the fraction of discharge seen, and a few discharges with the prediction
//! and its interval over time. Formats; never measures or prints.

use crate::record::{CellRecord, RecordSummary};
use crate::run::{CycleRun, METHODS};
use crate::score::{MethodScore, Quantiles, CAPACITY_FRACTIONS_PCT, EOD_FRACTIONS_PCT};
use plotters::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt::Write;
use std::path::{Path, PathBuf};

/// The issue's targets on held-out cycles: capacity RMSE from the first half, Ah; EOD error at half the
/// discharge, % of its duration (median, p90); interval coverage, %.
pub const TARGET_CAPACITY_RMSE_AH: f64 = 0.02;
pub const TARGET_EOD_PCT: [f64; 2] = [1.0, 2.0];

/// One calibrator's headline figures (the layout scripts read) and its full scores.
#[derive(Clone, Debug, Serialize)]
pub struct MethodEntry {
    pub name: String,
    /// Capacity RMSE against the metadata's stated capacity, Ah, by fraction of the discharge seen (a
    /// fraction without any scored prediction, as in data that states no capacity, is left out: no score,
    /// not a perfect one).
    pub capacity_rmse_ah: BTreeMap<String, f64>,
    /// The same against the charge the data shows down to the cut-off.
    pub capacity_rmse_ah_vs_data: BTreeMap<String, f64>,
    /// End-of-discharge error, % of the discharge's duration, median and p90, by fraction seen.
    pub eod_error_pct: BTreeMap<String, Quantiles>,
    /// The mean of the capacity and the end-of-discharge coverage: % of each kind of prediction whose 90 %
    /// interval holds the measurement, averaged over the two kinds (null for a method without intervals;
    /// `scores.coverage_90_pct` has each).
    pub coverage_90_pct: Option<f64>,
    pub scores: MethodScore,
}

impl MethodEntry {
    pub fn new(key: &str, s: MethodScore) -> Self {
        let name = METHODS.iter().find(|m| m.0 == key).map_or(key, |m| m.1).to_string();
        let by = |m: &BTreeMap<String, crate::score::Errors>| {
            m.iter().filter(|(_, e)| e.n > 0).map(|(k, e)| (k.clone(), e.rmse)).collect()
        };
        let cov: Vec<f64> = s.coverage_90_pct.values().flatten().copied().collect();
        Self {
            name,
            capacity_rmse_ah: by(&s.capacity),
            capacity_rmse_ah_vs_data: by(&s.capacity_vs_data),
            eod_error_pct: s.eod_error_pct.clone(),
            coverage_90_pct: (!cov.is_empty()).then(|| cov.iter().sum::<f64>() / cov.len() as f64),
            scores: s,
        }
    }
}

/// Everything `calibration.json` holds.
#[derive(Clone, Debug, Serialize)]
pub struct CalibrationReport {
    pub cell: String,
    pub cutoff_v: f64,
    /// Where the cut-off came from ("--cutoff-v", "the cell's documented protocol", ...).
    pub cutoff_source: String,
    pub train_cycles: Vec<u32>,
    pub cycles_judged: Vec<u32>,
    pub records: RecordSummary,
    /// The model every calibrator runs ("base": the NASA electrochemistry model, qMobile and Ro calibrated).
    pub model: String,
    pub methods: BTreeMap<String, MethodEntry>,
    /// How each calibrator was set up (policy file, UKF settings and what they were chosen on, the trend).
    pub settings: serde_json::Value,
    pub plots: Vec<String>,
    pub notes: Vec<String>,
    pub seconds: f64,
}

fn f(v: f64, d: usize) -> String {
    if v.is_finite() {
        format!("{v:.d$}")
    } else {
        "-".into()
    }
}

/// `calibration.md`.
pub fn render_markdown(r: &CalibrationReport) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# bcal calibrate: {}\n", r.cell);
    let _ = writeln!(
        s,
        "Held-out cycles {} ({} records, {} reaching the {} V cut-off: {}); trained or fitted on cycles {}. Every \
         streaming calibrator read each discharge one reading at a time, with no look-ahead, and is scored as \
         delivered: each prediction recentred on the method's own record where that earned it, blended with the \
         prior alone's by their errors over the last discharges that ended, its end of discharge blended in turn \
         with the previous cycle's fit's (not after rests of more than a day), the prior alone serving where it \
         beat that (`settings.<method>.recentred`, `blended`, `held_to_prior`). Model: {}.\n",
        span(&r.cycles_judged),
        r.records.records,
        r.records.reaching_cutoff,
        r.cutoff_v,
        r.cutoff_source,
        span(&r.train_cycles),
        r.model
    );
    for refused in &r.records.refused {
        let _ = writeln!(s, "- refused: {refused}");
    }
    for unread in &r.records.unread {
        let _ = writeln!(s, "- not read: {unread}");
    }
    for note in &r.records.noted {
        let _ = writeln!(s, "- the reader noted: {note}");
    }
    if !r.records.partial_start.is_empty() {
        let _ = writeln!(
            s,
            "- started from a partial charge (cycles {:?}): ends of discharge scored, capacity not",
            r.records.partial_start
        );
    }
    let validation = &r.settings["validation"];
    let validated = validation["cycles"].as_array().is_some_and(|c| !c.is_empty());
    if validated && validation["short"].as_bool() == Some(true) {
        let _ = writeln!(
            s,
            "- few training cycles reach the cut-off: every choice of the streaming calibrators rests on cycle(s) {} \
             alone and is weak (more training cycles, --train-cycles, make it sound)",
            validation["cycles"]
        );
    }
    if let Some(sc) = r.records.stated_capacity.as_ref().filter(|sc| sc.differs_from_cutoff(r.cutoff_v)) {
        let _ = writeln!(
            s,
            "- the stated capacity is the data's charge to about {:.1} V (median gap {:+.3} Ah over {} training \
             records), not to the {} V cut-off the capacities are predicted to ({:+.3} Ah): against it each \
             capacity is scored less the charge the last {} discharges before it at a like current (else at \
             any) drew below {:.1} V \
             (`records.capacity_refs`, `stated_tail_ah`); against the data's charge (in brackets) as predicted",
            sc.voltage_v,
            sc.median_gap_ah,
            sc.records,
            r.cutoff_v,
            sc.cutoff_median_gap_ah,
            crate::record::STATED_TAIL_WINDOW,
            sc.voltage_v
        );
    }
    let _ = writeln!(s, "## Capacity (RMSE against the stated capacity, Ah; against the data's charge in brackets)\n");
    let mut head = String::from("| Method |");
    let mut rule = String::from("| --- |");
    for f in CAPACITY_FRACTIONS_PCT {
        let _ = write!(head, " from {f} % |");
        rule.push_str(" ---: |");
    }
    let _ = writeln!(s, "{head}\n{rule}");
    for (key, name) in METHODS {
        let Some(m) = r.methods.get(key) else { continue };
        let mut row = format!("| {name} |");
        for fr in CAPACITY_FRACTIONS_PCT {
            let k = fr.to_string();
            let _ = write!(
                row,
                " {} ({}) |",
                f(*m.capacity_rmse_ah.get(&k).unwrap_or(&f64::NAN), 3),
                f(*m.capacity_rmse_ah_vs_data.get(&k).unwrap_or(&f64::NAN), 3)
            );
        }
        let _ = writeln!(s, "{row}");
    }
    let _ = writeln!(s, "\n## End of discharge (absolute error, % of the discharge: median / p90; s in brackets)\n");
    let mut head = String::from("| Method |");
    let mut rule = String::from("| --- |");
    for f in EOD_FRACTIONS_PCT {
        let _ = write!(head, " at {f} % |");
        rule.push_str(" ---: |");
    }
    let _ = writeln!(s, "{head} coverage 90 % |\n{rule} ---: |");
    for (key, name) in METHODS {
        let Some(m) = r.methods.get(key) else { continue };
        let mut row = format!("| {name} |");
        for fr in EOD_FRACTIONS_PCT {
            let k = fr.to_string();
            let (p, sec) = (m.eod_error_pct.get(&k), m.scores.eod_error_s.get(&k));
            match (p, sec) {
                (Some(p), Some(sec)) if p.n > 0 => {
                    let _ = write!(row, " {} / {} ({:.0} / {:.0}) |", f(p.median, 2), f(p.p90, 2), sec.median, sec.p90);
                }
                _ => row.push_str(" - |"),
            }
        }
        let _ = writeln!(s, "{row} {} |", m.coverage_90_pct.map_or("-".into(), |c| format!("{c:.1}")));
    }
    write_by_life(&mut s, r);
    bcal_eval::report::write_reading_plots_notes(&mut s, &reading(r), &r.plots, &r.notes);
    let _ = writeln!(
        s,
        "\n## Setup (every choice, and what it was made on)\n\n```json\n{}\n```",
        serde_json::to_string_pretty(&r.settings).unwrap_or_default()
    );
    let _ = writeln!(s, "\nCalibration took {:.0} s.", r.seconds);
    s
}

/// The table of each method's scores by third of the judged discharges ([`MethodScore::by_life`]): the
/// coverage of its 90 % intervals (end / capacity) and its capacity RMSE from half against the data's charge.
fn write_by_life(s: &mut String, r: &CalibrationReport) {
    // Every method is scored on the same judged discharges: the first with thirds names them.
    let Some(thirds) = r.methods.values().find(|m| !m.scores.by_life.is_empty()) else { return };
    let thirds: Vec<String> = thirds.scores.by_life.keys().cloned().collect();
    let _ = writeln!(
        s,
        "\n## By third of the judged discharges (coverage of the 90 % intervals, end / capacity %; capacity from half \
         against the data's charge, RMSE Ah)\n"
    );
    let _ = writeln!(s, "| Method | {} |\n| --- |{}", thirds.join(" | "), " ---: |".repeat(thirds.len()));
    for (key, name) in METHODS {
        let Some(m) = r.methods.get(key).filter(|m| !m.scores.by_life.is_empty()) else { continue };
        let mut row = format!("| {name} |");
        for t in &thirds {
            let Some(p) = m.scores.by_life.get(t) else {
                row.push_str(" - |");
                continue;
            };
            let cov = |k: &str| p.coverage_90_pct.get(k).copied().flatten().map_or("-".into(), |c| format!("{c:.1}"));
            let cap = p.capacity_vs_data.get("50").filter(|e| e.n > 0).map_or("-".into(), |e| format!("{:.4}", e.rmse));
            let _ = write!(row, " {} / {}, {cap} |", cov("eod"), cov("capacity"));
        }
        let _ = writeln!(s, "{row}");
    }
}

fn span(cycles: &[u32]) -> String {
    match (cycles.first(), cycles.last()) {
        (Some(a), Some(b)) => format!("{a}..{b} ({} cycles)", cycles.len()),
        _ => "none".into(),
    }
}

/// Statements derived from the numbers, so the reading cannot contradict the tables.
pub fn reading(r: &CalibrationReport) -> Vec<String> {
    let mut out = Vec::new();
    let cap50 = |k: &str| r.methods.get(k).and_then(|m| m.capacity_rmse_ah.get("50").copied());
    let cap50_data = |k: &str| r.methods.get(k).and_then(|m| m.capacity_rmse_ah_vs_data.get("50").copied());
    // Where the stated capacity is drawn to another voltage than the cut-off, the capacity is scored against it
    // less the tail below that voltage, and the data's charge is said beside it.
    let stated_elsewhere = r.records.stated_capacity.as_ref().filter(|sc| sc.differs_from_cutoff(r.cutoff_v));
    let eod50 = |k: &str| r.methods.get(k).and_then(|m| m.eod_error_pct.get("50").copied());
    let met = |x: f64| if x <= TARGET_CAPACITY_RMSE_AH { "met" } else { "missed" };
    for (key, name) in METHODS {
        // Data that states no capacity: the data's charge is the only reference.
        if let (None, Some(d)) = (cap50(key), cap50_data(key)) {
            let trend = cap50_data("trend").unwrap_or(f64::NAN);
            out.push(format!(
                "{name}: capacity RMSE {d:.3} Ah from the first half of each discharge against the data's charge to \
                 the cut-off, the data stating no capacity (target {TARGET_CAPACITY_RMSE_AH} Ah: {}; trend fit {}).",
                met(d),
                if d < trend { "beaten" } else { "not beaten" }
            ));
        }
        if let Some(c) = cap50(key) {
            let trend = cap50("trend").unwrap_or(f64::NAN);
            let data = match (stated_elsewhere, cap50_data(key)) {
                (Some(sc), Some(d)) => format!(
                    "; against the data's charge to the cut-off {d:.3} Ah, target {} there (the stated capacity is the \
                     charge to {:.1} V, scored less the tail below it)",
                    met(d),
                    sc.voltage_v
                ),
                _ => String::new(),
            };
            out.push(format!(
                "{name}: capacity RMSE {c:.3} Ah from the first half of each discharge (target {TARGET_CAPACITY_RMSE_AH} Ah: {}; trend fit {}){data}.",
                met(c),
                if c < trend { "beaten" } else { "not beaten" }
            ));
        }
    }
    for key in ["rl", "ukf"] {
        if let (Some(q), Some(m)) = (eod50(key), r.methods.get(key)) {
            out.push(format!(
                "{}: end of discharge predicted at half the discharge within {:.2} % (median) and {:.2} % (p90) of its duration (targets {} and {} %).",
                m.name, q.median, q.p90, TARGET_EOD_PCT[0], TARGET_EOD_PCT[1]
            ));
        }
    }
    if let (Some(a), Some(b)) = (eod50("rl"), eod50("ukf")) {
        out.push(format!(
            "RL-LAC against the joint UKF at half the discharge: median {:.2} vs {:.2} %, p90 {:.2} vs {:.2} %.",
            a.median, b.median, a.p90, b.p90
        ));
    }
    // The learner on the record against the filter it builds on: what learning adds.
    if let (Some(l), Some(u)) = (cap50("ukf_learned"), cap50("ukf")) {
        let data = match (cap50_data("ukf_learned"), cap50_data("ukf")) {
            (Some(ld), Some(ud)) => format!("; against the data's charge {ld:.4} vs {ud:.4} Ah ({:.2} times)", ld / ud),
            _ => String::new(),
        };
        out.push(format!(
            "Joint UKF + learner on its record against the joint UKF, capacity from half of each discharge: {l:.4} vs \
             {u:.4} Ah against the stated capacity ({:.2} times){data}.",
            l / u
        ));
    }
    if let (Some(l), Some(u)) = (eod50("ukf_learned"), eod50("ukf")) {
        out.push(format!(
            "Joint UKF + learner on its record against the joint UKF, end of discharge at half the discharge: median \
             {:.2} vs {:.2} %, p90 {:.2} vs {:.2} %.",
            l.median, u.median, l.p90, u.p90
        ));
    }
    out
}

/// Writes one CSV of every reading per calibrator and cycle under `dir/readings/<method>/`.
pub fn write_readings(dir: &Path, key: &str, records: &[CellRecord], runs: &[CycleRun]) -> std::io::Result<usize> {
    let folder = dir.join("readings").join(key);
    std::fs::create_dir_all(&folder)?;
    let opt = |v: Option<f64>| v.map_or(String::new(), |x| format!("{x:.6}"));
    for (r, run) in records.iter().zip(runs) {
        let mut text = String::from(
            "t_s,voltage_v,current_a,q_mobile_c,q_mobile_lo_c,q_mobile_hi_c,r_o_ohm,r_o_lo_ohm,r_o_hi_ohm,eod_s,eod_lo_s,eod_hi_s,capacity_ah,capacity_lo_ah,capacity_hi_ah\n",
        );
        for (s, st) in r.samples.iter().zip(&run.steps) {
            let iv = st.interval;
            let _ = writeln!(
                text,
                "{},{:.6},{:.6},{:.3},{},{},{:.6},{},{},{},{},{},{},{},{}",
                s.t_s,
                s.voltage_v,
                s.current_a,
                st.estimate.q_mobile_c,
                opt(iv.map(|i| i.q_mobile_c[0])),
                opt(iv.map(|i| i.q_mobile_c[1])),
                st.estimate.r_o_ohm,
                opt(iv.map(|i| i.r_o_ohm[0])),
                opt(iv.map(|i| i.r_o_ohm[1])),
                opt(st.eod.value),
                opt(st.eod.lo),
                opt(st.eod.hi),
                opt(st.capacity.value),
                opt(st.capacity.lo),
                opt(st.capacity.hi)
            );
        }
        bcal_common::fsutil::write_atomic(&folder.join(format!("{}-{:04}.csv", r.cell, r.cycle)), text.as_bytes())?;
    }
    Ok(records.len())
}

fn color(key: &str) -> RGBColor {
    match key {
        "rl" => RGBColor(214, 39, 40),
        "ukf" => RGBColor(31, 119, 180),
        "ukf_learned" => RGBColor(23, 190, 207),
        "fit" => RGBColor(44, 160, 44),
        "previous_cycle" => RGBColor(148, 103, 189),
        "trend" => RGBColor(255, 127, 14),
        _ => RGBColor(127, 127, 127),
    }
}

type Draw = Result<(), String>;
type Chart<'a, DB> =
    ChartContext<'a, DB, Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>>;

/// One calibrator's line, in its colour, labelled with its name in the legend when `label`.
fn method_line<DB: DrawingBackend>(chart: &mut Chart<'_, DB>, key: &str, line: Vec<(f64, f64)>, label: bool) -> Draw {
    let c = color(key);
    let s = chart.draw_series(LineSeries::new(line, c.stroke_width(2))).map_err(e2s)?;
    if label {
        let name = METHODS.iter().find(|m| m.0 == key).map_or(key, |m| m.1);
        s.label(name).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], c.stroke_width(2)));
    }
    Ok(())
}

fn legend<'a, DB: DrawingBackend + 'a>(chart: &mut Chart<'a, DB>) -> Draw {
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font(("sans-serif", 11))
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(e2s)
}

fn e2s<E: std::fmt::Display>(e: E) -> String {
    e.to_string()
}

/// Capacity over the cell's life: measured (stated and the data's) and each method's prediction from half
/// of each discharge, to the voltage the stated capacity is drawn to, as it is scored against it
/// ([`CellRecord::stated_tail_ah`]).
fn draw_capacity<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    records: &[CellRecord],
    train: &[(u32, f64)],
    runs: &[(&str, &[CycleRun])],
    text: bool,
) -> Draw {
    root.fill(&WHITE).map_err(e2s)?;
    let mut pts: Vec<(f64, f64)> = train.iter().map(|(n, c)| (f64::from(*n), *c)).collect();
    pts.extend(records.iter().filter_map(|r| r.stated_capacity_ah.map(|c| (f64::from(r.cycle), c))));
    let x_max = pts.iter().map(|p| p.0).fold(1.0, f64::max) + 1.0;
    let (y_lo, y_hi) = pts.iter().fold((f64::INFINITY, 0.0f64), |(a, b), p| (a.min(p.1), b.max(p.1)));
    let (y_lo, y_hi) = (y_lo - 0.15, y_hi + 0.15);
    let mut b = ChartBuilder::on(root);
    b.margin(10);
    if text {
        let caption = if records.iter().any(|r| r.stated_tail_ah.is_some()) {
            "capacity over the cell's life: stated vs predicted from half of each discharge, to the stated voltage (Ah)"
        } else {
            "capacity over the cell's life: measured vs predicted from half of each discharge (Ah)"
        };
        b.caption(caption, ("sans-serif", 15)).x_label_area_size(35).y_label_area_size(50);
    }
    let mut chart = b.build_cartesian_2d(0.0..x_max, y_lo..y_hi).map_err(e2s)?;
    if text {
        chart.configure_mesh().x_desc("cycle").y_desc("Ah").light_line_style(TRANSPARENT).draw().map_err(e2s)?;
    }
    let s = chart.draw_series(pts.iter().map(|p| Circle::new(*p, 3, BLACK.filled()))).map_err(e2s)?;
    if text {
        s.label("measured (metadata)").legend(|(x, y)| Circle::new((x + 8, y), 3, BLACK.filled()));
    }
    for (key, method_runs) in runs {
        let line: Vec<(f64, f64)> = records
            .iter()
            .zip(method_runs.iter())
            .filter_map(|(r, run)| {
                let k = r.reading_at_fraction(0.5)?;
                run.steps.get(k)?.capacity.value.map(|c| (f64::from(r.cycle), c - r.stated_tail_ah.unwrap_or(0.0)))
            })
            .collect();
        method_line(&mut chart, key, line, text)?;
    }
    if text {
        legend(&mut chart)?;
    }
    root.present().map_err(e2s)
}

/// Median |EOD error| (% of the discharge) against the fraction of the discharge seen.
fn draw_eod_vs_fraction<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    records: &[CellRecord],
    runs: &[(&str, &[CycleRun])],
    text: bool,
) -> Draw {
    root.fill(&WHITE).map_err(e2s)?;
    let fracs: Vec<f64> = (1..20).map(|k| f64::from(k) * 0.05).collect();
    let mut series = Vec::new();
    let mut y_max: f64 = 1.0;
    for (key, method_runs) in runs {
        let line: Vec<(f64, f64)> = fracs
            .iter()
            .filter_map(|fr| {
                let mut e: Vec<f64> = records
                    .iter()
                    .zip(method_runs.iter())
                    .filter_map(|(r, run)| {
                        let (eod, dur, k) = (r.eod_s?, r.discharge_s()?, r.reading_at_fraction(*fr)?);
                        run.steps.get(k)?.eod.value.map(|v| 100.0 * (v - eod).abs() / dur.max(1.0))
                    })
                    .collect();
                if e.is_empty() {
                    return None;
                }
                e.sort_by(f64::total_cmp);
                Some((100.0 * fr, e[e.len() / 2]))
            })
            .collect();
        y_max = line.iter().map(|p| p.1).fold(y_max, f64::max);
        series.push((*key, line));
    }
    let y_max = y_max.min(50.0) * 1.1;
    let mut b = ChartBuilder::on(root);
    b.margin(10);
    if text {
        b.caption(
            "end-of-discharge error vs the fraction of the discharge seen (median, % of the discharge)",
            ("sans-serif", 15),
        )
        .x_label_area_size(35)
        .y_label_area_size(50);
    }
    let mut chart = b.build_cartesian_2d(0.0..100.0, 0.0..y_max).map_err(e2s)?;
    if text {
        chart
            .configure_mesh()
            .x_desc("% of the discharge seen")
            .y_desc("% of the discharge")
            .light_line_style(TRANSPARENT)
            .draw()
            .map_err(e2s)?;
    }
    for (key, line) in series {
        method_line(&mut chart, key, line, text)?;
    }
    if text {
        legend(&mut chart)?;
    }
    root.present().map_err(e2s)
}

/// A few discharges: the predicted end of discharge over time with its interval, and the measured one.
fn draw_discharges<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    records: &[&CellRecord],
    runs: &[(&str, Vec<&CycleRun>)],
    text: bool,
) -> Draw {
    root.fill(&WHITE).map_err(e2s)?;
    let panels = root.split_evenly((1, records.len().max(1)));
    for (k, r) in records.iter().enumerate() {
        let Some(eod) = r.eod_s else { continue };
        let t_end = r.samples.last().map_or(1.0, |s| s.t_s).max(1.0);
        let mut b = ChartBuilder::on(&panels[k]);
        b.margin(8);
        if text {
            b.caption(format!("cycle {}: predicted end of discharge (s)", r.cycle), ("sans-serif", 13))
                .x_label_area_size(30)
                .y_label_area_size(50);
        }
        let mut chart = b.build_cartesian_2d(0.0..t_end, (0.6 * eod)..(1.4 * eod)).map_err(e2s)?;
        if text {
            chart.configure_mesh().x_desc("time, s").light_line_style(TRANSPARENT).draw().map_err(e2s)?;
        }
        for (key, method_runs) in runs {
            let run = method_runs[k];
            let c = color(key);
            let band: Vec<(f64, f64, f64)> = run
                .steps
                .iter()
                .filter_map(|st| Some((st.t_s, st.eod.lo?, st.eod.hi?)))
                .filter(|b| b.0 >= r.load_on_s)
                .collect();
            if band.len() > 1 {
                let mut poly: Vec<(f64, f64)> = band.iter().map(|b| (b.0, b.2.min(1.4 * eod))).collect();
                poly.extend(band.iter().rev().map(|b| (b.0, b.1.max(0.6 * eod))));
                chart.draw_series(std::iter::once(Polygon::new(poly, c.mix(0.15).filled()))).map_err(e2s)?;
            }
            let line: Vec<(f64, f64)> = run
                .steps
                .iter()
                .filter(|st| st.t_s >= r.load_on_s)
                .filter_map(|st| st.eod.value.map(|v| (st.t_s, v.clamp(0.6 * eod, 1.4 * eod))))
                .collect();
            method_line(&mut chart, key, line, text && k == 0)?;
        }
        let s =
            chart.draw_series(LineSeries::new(vec![(0.0, eod), (t_end, eod)], BLACK.stroke_width(1))).map_err(e2s)?;
        if text && k == 0 {
            s.label("measured").legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK));
            legend(&mut chart)?;
        }
    }
    root.present().map_err(e2s)
}

/// Writes calibration.json, calibration.md and the figures into `dir`; returns the files written.
pub fn write_outputs(
    dir: &Path,
    report: &mut CalibrationReport,
    records: &[CellRecord],
    train_capacities: &[(u32, f64)],
    runs: &[(&str, Vec<CycleRun>)],
) -> std::io::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir)?;
    let text = bcal_eval::plots::font_available();
    let mut written = Vec::new();
    let refs: Vec<(&str, &[CycleRun])> = runs.iter().map(|(k, r)| (*k, r.as_slice())).collect();
    let complete: Vec<usize> = (0..records.len()).filter(|&i| records[i].eod_s.is_some()).collect();
    let picks: Vec<usize> = match complete.len() {
        0 => vec![],
        n => {
            let mut p = vec![complete[0], complete[n / 2], complete[n - 1]];
            p.dedup();
            p
        }
    };
    let pick_records: Vec<&CellRecord> = picks.iter().map(|&i| &records[i]).collect();
    let pick_runs: Vec<(&str, Vec<&CycleRun>)> = runs
        .iter()
        .filter(|(k, _)| ["rl", "ukf"].contains(k))
        .map(|(k, r)| (*k, picks.iter().map(|&i| &r[i]).collect()))
        .collect();
    let mut figure = |stem: &str, size: (u32, u32), which: u8| {
        for ext in ["png", "svg"] {
            let name = format!("{stem}.{ext}");
            let path = dir.join(&name);
            let res = match (ext, which) {
                ("png", 0) => draw_capacity(
                    &BitMapBackend::new(&path, size).into_drawing_area(),
                    records,
                    train_capacities,
                    &refs,
                    text,
                ),
                ("svg", 0) => draw_capacity(
                    &SVGBackend::new(&path, size).into_drawing_area(),
                    records,
                    train_capacities,
                    &refs,
                    text,
                ),
                ("png", 1) => {
                    draw_eod_vs_fraction(&BitMapBackend::new(&path, size).into_drawing_area(), records, &refs, text)
                }
                ("svg", 1) => {
                    draw_eod_vs_fraction(&SVGBackend::new(&path, size).into_drawing_area(), records, &refs, text)
                }
                ("png", _) => draw_discharges(
                    &BitMapBackend::new(&path, size).into_drawing_area(),
                    &pick_records,
                    &pick_runs,
                    text,
                ),
                _ => {
                    draw_discharges(&SVGBackend::new(&path, size).into_drawing_area(), &pick_records, &pick_runs, text)
                }
            };
            match res {
                Ok(()) => {
                    report.plots.push(name);
                    written.push(path);
                }
                Err(e) => report.notes.push(format!("plot {name} failed: {e}")),
            }
        }
    };
    figure("capacity_over_life", (1100, 500), 0);
    figure("eod_error_vs_fraction", (1100, 450), 1);
    if !pick_records.is_empty() && !pick_runs.is_empty() {
        figure("discharges", (1400, 420), 2);
    }
    if !text {
        report.notes.push("no sans-serif font was found: plots have no text; install fonts-dejavu-core".into());
    }
    for (key, r) in runs {
        write_readings(dir, key, records, r)?;
    }
    let p = dir.join("calibration.json");
    bcal_common::fsutil::write_atomic(&p, serde_json::to_string_pretty(report).expect("reports serialise").as_bytes())?;
    written.push(p);
    let p = dir.join("calibration.md");
    bcal_common::fsutil::write_atomic(&p, render_markdown(report).as_bytes())?;
    written.push(p);
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::score::MethodScore;

    /// The thirds' table names each third by its cycles and gives a method's coverage (end / capacity) and
    /// capacity RMSE there; a report without thirds has no such table.
    #[test]
    fn the_thirds_of_the_life_are_tabulated_per_method() {
        let third = |eod: f64, capacity: f64, rmse: f64| {
            let mut s = MethodScore::default();
            s.coverage_90_pct.insert("eod".into(), Some(eod));
            s.coverage_90_pct.insert("capacity".into(), Some(capacity));
            s.capacity_vs_data.insert("50".into(), crate::score::Errors { n: 3, rmse, ..Default::default() });
            s
        };
        let mut ukf = MethodScore::default();
        for (k, (e, c)) in [(85.0, 90.0), (88.0, 86.0), (84.0, 91.5)].into_iter().enumerate() {
            ukf.by_life.insert(format!("{}: cycles {}-{}", k + 1, 10 * k + 1, 10 * k + 10), third(e, c, 0.01));
        }
        let report = |methods: BTreeMap<String, MethodEntry>| CalibrationReport {
            cell: "T".into(),
            cutoff_v: 2.7,
            cutoff_source: "test".into(),
            train_cycles: vec![],
            cycles_judged: vec![],
            records: RecordSummary::default(),
            model: "base".into(),
            methods,
            settings: serde_json::Value::Null,
            plots: vec![],
            notes: vec![],
            seconds: 0.0,
        };
        let md = render_markdown(&report(BTreeMap::from([("ukf".to_string(), MethodEntry::new("ukf", ukf))])));
        assert!(md.contains("| Method | 1: cycles 1-10 | 2: cycles 11-20 | 3: cycles 21-30 |"), "{md}");
        assert!(md.contains("| Joint UKF | 85.0 / 90.0, 0.0100 | 88.0 / 86.0, 0.0100 | 84.0 / 91.5, 0.0100 |"), "{md}");
        let none = BTreeMap::from([("ukf".to_string(), MethodEntry::new("ukf", MethodScore::default()))]);
        assert!(!render_markdown(&report(none)).contains("By third"));
    }
}
