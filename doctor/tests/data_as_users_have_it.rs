//! Data as users have it (issue 13, section 4): cycler exports read as they are. A discharge that stops at
//! the cut-off still under load is complete; the sign of the current is decided from the data and reported;
//! current in mA and time in ms are converted when the column says so and refused with the column to
//! rename when it does not; Battery Data Format files (labels or machine names, charge positive) read as
//! they are, a long multi-cycle file cut into its discharges; irregular sampling and gaps work; and a bad
//! cycle or file is one line naming it while the others still read.
//!
//! The files are written by a small cycler here (an equivalent circuit: linear open-circuit voltage, one
//! resistance, coulomb counting); what is tested is the reading, not the model.

mod common;

use bcal_doctor::read::{
    read_csv, read_generic, read_nasa_with, CurrentSign, ReadOptions, ReadReport, SignEvidence, MAX_CELL_CURRENT_A,
};
use bcal_doctor::record::DEFAULT_CUTOFF_V;
use bcal_doctor::{diagnose, Cause, DiagnoseConfig, DoctorError};
use std::path::{Path, PathBuf};

/// One sample as the cycler logs it: (test time s, voltage V, current A positive while discharging,
/// temperature deg C, cycle).
type Sample = (f64, f64, f64, f64, u32);

/// A cell on a cycler: open-circuit voltage 2.8 + 1.4 soc V, 0.1 ohm, 2 Ah.
struct Cycler {
    soc: f64,
    t: f64,
    cycle: u32,
    log: Vec<Sample>,
}

impl Cycler {
    const CAPACITY_AH: f64 = 2.0;
    const R_OHM: f64 = 0.1;

    fn new() -> Self {
        Cycler { soc: 1.0, t: 0.0, cycle: 1, log: Vec::new() }
    }

    fn volts(&self, i_a: f64) -> f64 {
        2.8 + 1.4 * self.soc - Self::R_OHM * i_a
    }

    /// Logs the current sample, then advances `dt_s` at `i_a`.
    fn step(&mut self, i_a: f64, dt_s: f64) {
        let temp_c = 24.0 + 3.0 * i_a.abs() * (1.0 - self.soc).clamp(0.0, 1.0);
        self.log.push((self.t, self.volts(i_a), i_a, temp_c, self.cycle));
        self.soc -= i_a * dt_s / (3600.0 * Self::CAPACITY_AH);
        self.t += dt_s;
    }

    fn rest(&mut self, dur_s: f64, dt_s: f64) {
        let end = self.t + dur_s;
        while self.t < end {
            self.step(0.0, dt_s);
        }
    }

    /// Discharges at `i_a` until the voltage under load is at or below `cutoff_v`; that last sample is logged.
    fn discharge(&mut self, i_a: f64, cutoff_v: f64, dt_s: f64) {
        while self.volts(i_a) > cutoff_v {
            self.step(i_a, dt_s);
        }
        self.step(i_a, dt_s);
    }

    /// CC at `i_a` to 4.2 V, then CV until the current falls to 20 mA.
    fn charge(&mut self, i_a: f64, dt_s: f64) {
        while self.volts(-i_a) < 4.2 {
            self.step(-i_a, dt_s);
        }
        let mut i = i_a;
        while i > 0.02 {
            self.step(-i, dt_s);
            i *= 0.9;
        }
    }
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

/// Writes one sample as a CSV line.
type Row = fn(&Sample) -> String;

/// The samples as CSV: `header`, then one line per sample from `row`.
fn csv_of(header: &str, log: &[Sample], row: impl Fn(&Sample) -> String) -> String {
    let mut s = format!("{header}\n");
    for x in log {
        s += &row(x);
        s.push('\n');
    }
    s
}

/// Three cycles of charge, rest, 2 A discharge to `cutoff_v`, then (if `relax`) a rest: how a cycler logs
/// an ageing test. Sampling every 30 s.
fn cycling(cutoff_v: f64, relax: bool) -> Vec<Sample> {
    let mut c = Cycler::new();
    c.soc = 0.3;
    for cycle in 1..=3 {
        c.cycle = cycle;
        c.charge(1.5, 30.0);
        c.rest(600.0, 30.0);
        c.discharge(2.0, cutoff_v, 30.0);
        if relax {
            c.rest(900.0, 30.0);
        }
    }
    c.log
}

fn reason_of(report: &ReadReport) -> Vec<String> {
    report.skipped.iter().map(|s| s.reason.clone()).collect()
}

#[test]
fn a_bdf_export_with_labels_reads_as_it_is_one_discharge_per_cycle() {
    let dir = tempfile::tempdir().unwrap();
    let log = cycling(2.75, true);
    // The Battery Data Format: its preferred labels, charge positive, a second temperature ignored.
    let text = csv_of(
        "Test Time / s,Voltage / V,Current / A,Cycle Count / 1,Step Index / 1,Temperature T1 / degC,\
         Temperature T2 / degC,Ambient Temperature / degC",
        &log,
        |&(t, v, i, tc, c)| format!("{t},{v},{},{c},1,{tc},99,23.5", -i),
    );
    let path = write(dir.path(), "UCam__A0001__20241031_001.bdf.csv", &text);
    let (records, report) = read_csv(&path, &ReadOptions::default()).unwrap();
    assert_eq!(report.format, "bdf");
    assert_eq!(records.iter().map(|d| d.cycle).collect::<Vec<_>>(), vec![1, 2, 3]);
    // The sign was decided from the data: discharge is negative in BDF, and the summary says so.
    assert_eq!(report.signs.len(), 1);
    assert!(!report.signs[0].discharge_positive && report.signs[0].from_data, "{report:?}");
    assert!(report.summary().iter().any(|l| l.contains("discharge negative") && l.contains("from the data")));
    for d in &records {
        assert_eq!(d.cell, "UCam__A0001__20241031_001");
        // The charge is cut away: the record starts at the rest before the load (the charger's last
        // milliamperes of CV included), time from its start.
        let w = d.windows(0.05, 2.9).unwrap();
        assert_eq!(d.time_s[0], 0.0);
        assert!(d.current_a.iter().all(|i| *i >= -0.05) && d.current_a[..w.load_on].iter().all(|i| i.abs() <= 0.05));
        assert!((d.ambient_k - (23.5 + 273.15)).abs() < 1e-9);
        let temps = d.temperature_k.as_ref().unwrap();
        assert!(temps.iter().all(|t| *t < 40.0 + 273.15), "T1, not T2 = 99 degC");
        assert!(!w.truncated && !w.ended_at_cutoff);
        assert!((20..=30).contains(&w.load_on), "600 s of rest at 30 s and the CV tail: {}", w.load_on);
        let q = d.charge_ah(w.load_on, w.load_end);
        assert!(q > 1.5 && q < 2.0, "{q} Ah");
    }
}

#[test]
fn machine_names_without_a_cycle_column_are_cut_into_discharges_at_the_charges() {
    let dir = tempfile::tempdir().unwrap();
    let log = cycling(2.75, true);
    let text =
        csv_of("unix_time_second,test_time_second,voltage_volt,current_ampere,temperature_t1_celsius", &log, |s| {
            format!("{},{},{},{},{}", 1.7e9 + s.0, s.0, s.1, -s.2, s.3)
        });
    let path = write(dir.path(), "cell.bdf", &text);
    let (records, report) = read_csv(&path, &ReadOptions::default()).unwrap();
    assert_eq!(report.format, "bdf");
    assert_eq!(records.iter().map(|d| d.cycle).collect::<Vec<_>>(), vec![1, 2, 3], "numbered in time order");
    // Without test time the Unix time serves.
    let unix =
        csv_of("unix_time_second,voltage_volt,current_ampere", &log, |s| format!("{},{},{}", 1.7e9 + s.0, s.1, -s.2));
    let (by_unix, _) = read_csv(&write(dir.path(), "unix.bdf.csv", &unix), &ReadOptions::default()).unwrap();
    assert_eq!(by_unix.len(), 3);
    assert!(by_unix[1].time_s.iter().zip(&records[1].time_s).all(|(a, b)| (a - b).abs() < 1e-5));
    // Each record holds its rest and the relaxation after (trimmed to the option's limits).
    let opts = ReadOptions { max_rest_before_s: 300.0, max_rest_after_s: 120.0, ..ReadOptions::default() };
    let (trimmed, _) = read_csv(&path, &opts).unwrap();
    for (d, t) in records.iter().zip(&trimmed) {
        let (w, wt) = (d.windows(0.05, 2.9).unwrap(), t.windows(0.05, 2.9).unwrap());
        assert!((20..=30).contains(&w.load_on) && wt.load_on == 10, "{w:?} {wt:?}");
        assert_eq!((d.len() - w.load_end, t.len() - wt.load_end), (30, 4));
    }
}

/// The case the issue names: every discharge stops at the cut-off with no rest after it, and the next
/// charge starts at once. Each is a complete discharge, used by the diagnosis (it was refused outright:
/// "no discharge records selected").
#[test]
fn discharges_that_stop_at_the_cutoff_without_a_rest_are_complete_and_diagnosed() {
    let dir = tempfile::tempdir().unwrap();
    let cutoff_v = 2.75;
    let log = cycling(cutoff_v, false);
    let text = csv_of("Test Time / s,Voltage / V,Current / A,Cycle Count / 1", &log, |&(t, v, i, _, c)| {
        format!("{t},{v},{},{c}", -i)
    });
    let path = write(dir.path(), "maker.csv", &text);
    let (records, _) = read_csv(&path, &ReadOptions::default()).unwrap();
    assert_eq!(records.len(), 3);
    for d in &records {
        let w = d.windows_with_cutoff(0.05, 2.9, Some(cutoff_v)).unwrap();
        assert!(w.ended_at_cutoff && !w.truncated && w.load_end == d.len(), "{w:?}");
        // The same record with a lower cut-off was cut short.
        assert!(d.windows_with_cutoff(0.05, 2.9, Some(2.5)).unwrap().truncated);
    }
    let mut cfg = DiagnoseConfig { cutoff_v: Some(cutoff_v), causes: vec![Cause::VoltageOffset], ..Default::default() };
    cfg.fit.dt_max_s = 5.0;
    let diag = diagnose(&cfg, &records[..2], &records[2..]).unwrap();
    assert_eq!(diag.ended_at_cutoff_count, 3);
    assert_eq!(diag.truncated_count, 0);
    assert_eq!(diag.base.train_cycles.len(), 2);
    for r in &diag.records {
        assert!(r.role != "excluded" && r.ended_at_cutoff && r.capacity_ah.is_some_and(|q| q > 1.0), "{r:?}");
        assert!(r.note.as_deref().is_some_and(|n| n.contains("complete")), "{r:?}");
    }
    // Without the cut-off the default (2.5 V) calls them cut short, and says what it assumed.
    cfg.cutoff_v = None;
    let err = diagnose(&cfg, &records[..2], &records[2..]).unwrap_err().to_string();
    assert!(err.contains("above the default cut-off 2.5 V (none given): truncated"), "{err}");
    assert_eq!(DEFAULT_CUTOFF_V, 2.5);
    // The records themselves show the cut-off (`bcal diagnose` and `bcal calibrate` read it when nobody
    // gives one): they all end under load just below 2.75 V, the round cut-off they show, and with it they
    // are complete again.
    let read = bcal_doctor::record::infer_cutoff_v(&records, 0.05).expect("the records show their cut-off");
    assert_eq!(read, cutoff_v);
    // The two that stopped furthest below it show it too, and the third, which stopped closer to it, is
    // complete under what they show (the higher end of the two, unrounded, would call it cut short).
    let mut by_end: Vec<&bcal_doctor::Discharge> = records.iter().collect();
    by_end.sort_by(|a, b| a.voltage_v.last().unwrap().total_cmp(b.voltage_v.last().unwrap()));
    let (low, closest) = ([by_end[0].clone(), by_end[1].clone()], by_end[2]);
    assert!(closest.voltage_v.last() > low[1].voltage_v.last(), "three ends, not all equal");
    let from_low = bcal_doctor::record::infer_cutoff_v(&low, 0.05);
    assert_eq!(from_low, Some(cutoff_v));
    let w = closest.windows_with_cutoff(0.05, 2.9, from_low).unwrap();
    assert!(w.ended_at_cutoff && !w.truncated, "{w:?}");
    cfg.cutoff_v = Some(read);
    assert_eq!(diagnose(&cfg, &records[..2], &records[2..]).unwrap().ended_at_cutoff_count, 3);
    // Records that end at rest (a relaxation logged after the cut-off) show none.
    let (relaxed, _) = read_csv(
        &write(
            dir.path(),
            "relaxed.csv",
            &csv_of(
                "Test Time / s,Voltage / V,Current / A,Cycle Count / 1",
                &cycling(cutoff_v, true),
                |&(t, v, i, _, c)| format!("{t},{v},{},{c}", -i),
            ),
        ),
        &ReadOptions::default(),
    )
    .unwrap();
    assert_eq!(bcal_doctor::record::infer_cutoff_v(&relaxed, 0.05), None);
}

#[test]
fn the_current_sign_is_decided_from_the_data_and_reported() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = Cycler::new();
    c.rest(60.0, 10.0);
    c.discharge(2.0, 3.0, 10.0);
    c.rest(300.0, 10.0);
    let row = |flip: f64| move |&(t, v, i, _, _): &Sample| format!("{t},{v},{}", flip * i);
    for (flip, positive) in [(1.0, true), (-1.0, false)] {
        let path = write(dir.path(), "g.csv", &csv_of("time_s,voltage_v,current_a", &c.log, row(flip)));
        let (records, report) = read_csv(&path, &ReadOptions::default()).unwrap();
        assert_eq!(report.signs[0].discharge_positive, positive);
        assert!(report.signs[0].evidence.share_for(positive).unwrap() > 0.99, "{report:?}");
        assert!(records[0].current_a.iter().any(|i| *i > 1.9), "read positive while discharging");
        // The generic CSV documents positive discharge: a file against it is read by its data, and noted.
        assert_eq!(report.notes.iter().any(|n| n.contains("generic CSV counts discharge positive")), !positive);
        // Asked for the sign the data contradicts, this file has no discharge at all: said so, naming the sign.
        let against = CurrentSign::ALL[if positive { 2 } else { 1 }];
        let msg =
            read_csv(&path, &ReadOptions { current_sign: against, ..Default::default() }).unwrap_err().to_string();
        assert!(msg.contains("no discharge") && msg.contains(&format!("{against} (as asked)")), "{msg}");
    }
    // A cycling file read against its data: its charges become the "discharges"; read as asked, with a note.
    let log = cycling(2.75, true);
    let path =
        write(dir.path(), "c.csv", &csv_of("time_s,voltage_v,current_a", &log, |s| format!("{},{},{}", s.0, s.1, s.2)));
    let opts = ReadOptions { current_sign: CurrentSign::DischargeNegative, ..Default::default() };
    let (_, report) = read_csv(&path, &opts).unwrap();
    assert!(!report.signs[0].from_data && report.notes.iter().any(|n| n.contains("but the data says")), "{report:?}");
    // The option's names parse, and nonsense is refused naming the choices.
    assert_eq!("discharge-negative".parse::<CurrentSign>().unwrap(), CurrentSign::DischargeNegative);
    assert!("negative".parse::<CurrentSign>().unwrap_err().contains("auto, discharge-positive, discharge-negative"));
}

#[test]
fn a_current_sign_that_cannot_be_decided_is_one_line_naming_the_file_and_the_option() {
    let dir = tempfile::tempdir().unwrap();
    // A pulse train on a cell whose voltage does not answer it, and a noisy one answering both ways.
    let flat = (0..60).map(|k| format!("{},3.7,{}", 10 * k, if k % 2 == 0 { 2.0 } else { -2.0 })).collect::<Vec<_>>();
    // The voltage follows the current one way in the first half and the other way in the second.
    let noisy = (0..60)
        .map(|k| {
            let i: f64 = if k % 4 < 2 { 2.0 } else { -2.0 };
            let v = 3.7 + 0.05 * i.signum() * if k < 30 { 1.0 } else { -1.0 };
            format!("{},{v},{i}", 10 * k)
        })
        .collect::<Vec<_>>();
    for (name, rows) in [("flat.csv", flat), ("noisy.csv", noisy)] {
        let path = write(dir.path(), name, &format!("time_s,voltage_v,current_a\n{}\n", rows.join("\n")));
        let err = read_csv(&path, &ReadOptions::default()).unwrap_err();
        assert!(matches!(err, DoctorError::SignUndecided { .. }), "{name}: {err}");
        let msg = err.to_string();
        assert!(
            msg.contains(name) && msg.contains("--current-sign discharge-positive") && !msg.contains('\n'),
            "{msg}"
        );
        // Told the sign, the reader reads it.
        let opts = ReadOptions { current_sign: CurrentSign::DischargePositive, ..Default::default() };
        assert!(read_csv(&path, &opts).is_ok(), "{name}");
    }
    // The evidence itself: a falling voltage under positive current is 100 % "positive discharges".
    let mut e = SignEvidence::default();
    e.add_record(&[4.0, 3.9, 3.8, 3.7], &[2.0, 2.0, 2.0, 2.0], &ReadOptions::default());
    assert_eq!(e.decide(), Ok(true));
    assert!((e.positive_v - 0.3).abs() < 1e-12 && e.negative_v == 0.0, "{e:?}");
}

#[test]
fn milliamperes_and_milliseconds_are_converted_when_named_and_refused_with_a_hint_when_not() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = Cycler::new();
    c.rest(60.0, 10.0);
    c.discharge(2.0, 3.0, 10.0);
    c.rest(120.0, 10.0);
    let (reference, _) = read_csv(
        &write(
            dir.path(),
            "si.csv",
            &csv_of("time_s,voltage_v,current_a", &c.log, |s| format!("{},{},{}", s.0, s.1, s.2)),
        ),
        &ReadOptions::default(),
    )
    .unwrap();
    let variants: [(&str, Row); 4] = [
        ("time_ms,voltage_mv,current_ma", |s| format!("{},{},{}", 1e3 * s.0, 1e3 * s.1, 1e3 * s.2)),
        ("Test Time / ms,Voltage / mV,Current / mA", |s| format!("{},{},{}", 1e3 * s.0, 1e3 * s.1, -1e3 * s.2)),
        ("Time (min),Voltage [V],Current (mA)", |s| format!("{},{},{}", s.0 / 60.0, s.1, 1e3 * s.2)),
        ("time_h,voltage_v,current_milliampere", |s| format!("{},{},{}", s.0 / 3600.0, s.1, 1e3 * s.2)),
    ];
    for (header, row) in variants {
        let (got, report) =
            read_csv(&write(dir.path(), "u.csv", &csv_of(header, &c.log, row)), &ReadOptions::default())
                .unwrap_or_else(|e| panic!("{header}: {e}"));
        assert_eq!(got.len(), 1, "{header}");
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-9 * (1.0 + y.abs()));
        assert!(close(&got[0].time_s, &reference[0].time_s), "{header}");
        assert!(close(&got[0].voltage_v, &reference[0].voltage_v), "{header}");
        assert!(close(&got[0].current_a, &reference[0].current_a), "{header}");
        assert!(
            !report.units.is_empty() && report.units.iter().all(|u| u.contains("converted")),
            "{header}: {report:?}"
        );
    }
    // Not named: milliamperes under an ampere name are refused, naming the file, the column and the fix.
    let path = write(
        dir.path(),
        "ma.csv",
        &csv_of("time_s,voltage_v,current_a", &c.log, |s| format!("{},{},{}", s.0, s.1, 1e3 * s.2)),
    );
    let err = read_csv(&path, &ReadOptions::default()).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, DoctorError::SuspectUnit { .. }), "{msg}");
    assert!(msg.contains("ma.csv") && msg.contains("`current_a`") && msg.contains("current_ma"), "{msg}");
    assert!(msg.contains(&format!("{MAX_CELL_CURRENT_A} A")) && !msg.contains('\n'), "{msg}");
    // Milliseconds under a seconds name: the discharge would hold 1000 times the charge.
    let path = write(
        dir.path(),
        "ms.csv",
        &csv_of("time_s,voltage_v,current_a", &c.log, |s| format!("{},{},{}", 1e3 * s.0, s.1, s.2)),
    );
    let msg = read_csv(&path, &ReadOptions::default()).unwrap_err().to_string();
    assert!(msg.contains("ms.csv") && msg.contains("`time_s`") && msg.contains("time_ms"), "{msg}");
    // A short partial discharge in milliseconds holds a plausible charge but lasts a week: refused too.
    let partial: Vec<Sample> = c.log.iter().filter(|s| s.0 < c.log[0].0 + 600.0).copied().collect();
    let path = write(
        dir.path(),
        "ms_partial.csv",
        &csv_of("time_s,voltage_v,current_a", &partial, |s| format!("{},{},{}", 1e3 * s.0, s.1, s.2)),
    );
    let msg = read_csv(&path, &ReadOptions::default()).unwrap_err().to_string();
    assert!(msg.contains("ms_partial.csv") && msg.contains("days") && msg.contains("time_ms"), "{msg}");
    // Millivolts under a volts name: the existing refusal, now also naming the column to rename.
    let path = write(
        dir.path(),
        "mv.csv",
        &csv_of("time_s,voltage_v,current_a", &c.log, |s| format!("{},{},{}", s.0, 1e3 * s.1, s.2)),
    );
    let err = read_csv(&path, &ReadOptions::default()).unwrap_err();
    assert!(matches!(err, DoctorError::VoltageInMillivolts { .. }), "{err}");
    assert!(err.to_string().contains("voltage_mv") && err.to_string().contains("mv.csv"), "{err}");
    // A unit the doctor does not read is named.
    let path = write(
        dir.path(),
        "ka.csv",
        &csv_of("time_s,voltage_v,Current / kA", &c.log, |s| format!("{},{},{}", s.0, s.1, s.2)),
    );
    let msg = read_csv(&path, &ReadOptions::default()).unwrap_err().to_string();
    assert!(msg.contains("ka.csv") && msg.contains("`kA`") && msg.contains("A or mA"), "{msg}");
    // Kelvin under a Celsius name: refused, naming the file and the name to give (it ran the model 273 K hot,
    // and the doctor fitted it to a wrong cause). Named as kelvin, it reads as the Celsius column does.
    let header = "time_s,voltage_v,current_a,temperature_c";
    let path =
        write(dir.path(), "k.csv", &csv_of(header, &c.log, |s| format!("{},{},{},{}", s.0, s.1, s.2, s.3 + 273.15)));
    let err = read_csv(&path, &ReadOptions::default()).unwrap_err();
    assert!(matches!(err, DoctorError::TemperatureOutOfRange { .. }), "{err}");
    assert!(err.to_string().contains("k.csv") && err.to_string().contains("temperature_k"), "{err}");
    let (celsius, _) = read_csv(
        &write(dir.path(), "c.csv", &csv_of(header, &c.log, |s| format!("{},{},{},{}", s.0, s.1, s.2, s.3))),
        &ReadOptions::default(),
    )
    .unwrap();
    let kelvin_header = "time_s,voltage_v,current_a,temperature_k";
    let (kelvin, _) = read_csv(
        &write(
            dir.path(),
            "kk.csv",
            &csv_of(kelvin_header, &c.log, |s| format!("{},{},{},{}", s.0, s.1, s.2, s.3 + 273.15)),
        ),
        &ReadOptions::default(),
    )
    .unwrap();
    let (a, b) = (celsius[0].temperature_k.as_ref().unwrap(), kelvin[0].temperature_k.as_ref().unwrap());
    assert!(a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9), "kelvin named as kelvin reads as Celsius does");
}

#[test]
fn irregular_sampling_and_gaps_are_kept_and_gaps_noted() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = Cycler::new();
    c.rest(60.0, 10.0);
    let mut k = 0;
    while c.volts(2.0) > 3.0 {
        // Irregular steps of 3-17 s, and once a logger outage of 20 minutes mid-discharge.
        let dt = if k == 40 { 1200.0 } else { 3.0 + ((k * 37) % 15) as f64 };
        c.step(2.0, dt);
        k += 1;
    }
    c.rest(300.0, 7.0);
    let path = write(
        dir.path(),
        "gappy.csv",
        &csv_of("time_s,voltage_v,current_a", &c.log, |s| format!("{},{},{}", s.0, s.1, s.2)),
    );
    let (records, report) = read_csv(&path, &ReadOptions::default()).unwrap();
    assert_eq!(records.len(), 1);
    assert_eq!(records[0].len(), c.log.len(), "every sample kept");
    let gaps: Vec<&String> = report.notes.iter().filter(|n| n.contains("gap")).collect();
    assert_eq!(gaps.len(), 1, "{report:?}");
    assert!(gaps[0].contains("gappy.csv, cycle 1: 1 gap") && gaps[0].contains("longest 1200 s"), "{}", gaps[0]);
    // The diagnosis runs over it (the simulator bridges the gap at its own step).
    let mut cfg = DiagnoseConfig { causes: vec![Cause::VoltageOffset], ..Default::default() };
    cfg.fit.dt_max_s = 5.0;
    let two = [records[0].clone(), records[0].clone()];
    let diag = diagnose(&cfg, &two[..1], &two[1..]).unwrap();
    assert!(diag.base.heldout_rmse_mv.is_finite());
}

#[test]
fn files_without_a_discharge_are_refused_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = Cycler::new();
    c.soc = 0.2;
    c.rest(300.0, 10.0);
    let rest_only = c.log.clone();
    c.charge(1.5, 30.0);
    for (name, log) in [("rest.csv", rest_only), ("charge.csv", c.log.clone())] {
        let path = write(
            dir.path(),
            name,
            &csv_of("time_s,voltage_v,current_a", &log, |s| format!("{},{},{}", s.0, s.1, s.2)),
        );
        let err = read_csv(&path, &ReadOptions::default()).unwrap_err();
        let msg = err.to_string();
        assert!(matches!(err, DoctorError::NoDischarge { .. }), "{name}: {msg}");
        assert!(msg.contains(name) && msg.contains("no discharge") && !msg.contains('\n'), "{msg}");
    }
}

#[test]
fn a_bad_cycle_is_skipped_with_its_error_and_the_other_cycles_read() {
    let dir = tempfile::tempdir().unwrap();
    let mut log: Vec<Sample> = cycling(2.75, true).into_iter().filter(|s| s.4 < 3).collect();
    // Cycle 3: a handful of samples only.
    let t3 = log.last().unwrap().0 + 30.0;
    for (k, (v, i)) in [(4.1, 0.0), (4.1, 0.0), (3.9, 2.0), (3.85, 2.0), (3.8, 2.0), (4.0, 0.0)].into_iter().enumerate()
    {
        log.push((t3 + 30.0 * k as f64, v, i, 25.0, 3));
    }
    // Cycle 2 logged in millivolts (a firmware switch).
    let text = csv_of("time_s,voltage_v,current_a,cycle", &log, |&(t, v, i, _, c)| {
        let v = if c == 2 { 1e3 * v } else { v };
        format!("{t},{v},{i},{c}")
    });
    let path = write(dir.path(), "mixed.csv", &text);
    let (records, report) = read_csv(&path, &ReadOptions::default()).unwrap();
    assert_eq!(records.iter().map(|d| d.cycle).collect::<Vec<_>>(), vec![1]);
    let reasons = reason_of(&report);
    assert_eq!(reasons.len(), 2, "{reasons:?}");
    assert!(reasons[0].contains("mixed.csv") && reasons[0].contains("millivolts"), "{}", reasons[0]);
    assert!(report.skipped[0].cycle == Some(2) && report.skipped[1].cycle == Some(3));
    assert!(report.summary().iter().filter(|l| l.starts_with("skipped: ")).count() == 2);
    // When no cycle is left, the first cycle's error is the read's.
    let only2 = text.lines().filter(|l| !l.ends_with(",1") && !l.ends_with(",3")).collect::<Vec<_>>().join("\n");
    let err = read_csv(&write(dir.path(), "only2.csv", &only2), &ReadOptions::default()).unwrap_err();
    assert!(matches!(err, DoctorError::VoltageInMillivolts { .. }), "{err}");
}

/// A NASA folder in which one record has no discharge and another a sign the data cannot decide: each is
/// skipped with its one-line error; the other records and the other cell read, with NASA's negative
/// discharge current found by `Auto`.
#[test]
fn a_bad_nasa_record_is_skipped_and_the_other_cycles_and_cells_read() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("data")).unwrap();
    std::fs::write(
        dir.path().join("metadata.csv"),
        "type,start_time,ambient_temperature,battery_id,test_id,uid,filename,Capacity,Re,Rct\n\
         discharge,[2008 4 2 15 25 41],24,B0005,1,1,00001.csv,1.85,,\n\
         discharge,[2008 4 3 15 25 41],24,B0005,2,2,00002.csv,1.84,,\n\
         discharge,[2008 4 4 15 25 41],24,B0005,3,3,00003.csv,1.83,,\n\
         discharge,[2008 4 5 15 25 41],24,B0006,1,4,00004.csv,1.80,,\n",
    )
    .unwrap();
    let nasa = |current: &dyn Fn(usize) -> f64, volts: &dyn Fn(usize) -> f64| {
        let mut s =
            String::from("Voltage_measured,Current_measured,Temperature_measured,Current_load,Voltage_load,Time\n");
        for k in 0..30 {
            s += &format!("{},{},24.5,-2.0,3.0,{}\n", volts(k), current(k), 10 * k);
        }
        s
    };
    let loaded = |k: usize| if k == 0 || k >= 27 { -0.001 } else { -2.0 };
    let good = nasa(&loaded, &|k| if k == 0 || k >= 27 { 4.2 } else { 4.0 - 0.02 * k as f64 });
    for f in ["00001.csv", "00003.csv", "00004.csv"] {
        std::fs::write(dir.path().join("data").join(f), &good).unwrap();
    }
    // Cycle 2: the load was never applied.
    std::fs::write(dir.path().join("data/00002.csv"), nasa(&|_| -0.001, &|_| 4.19)).unwrap();
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records.iter().map(|d| d.cycle).collect::<Vec<_>>(), vec![1, 3]);
    assert!(records.iter().all(|d| d.current_a[5] > 1.9 && d.stated_capacity_ah.is_some()));
    assert_eq!(report.skipped.len(), 1);
    let reason = &report.skipped[0].reason;
    assert!(reason.contains("00002.csv") && reason.contains("no discharge") && !reason.contains('\n'), "{reason}");
    assert!(report.signs.iter().all(|s| !s.discharge_positive && s.from_data), "{report:?}");
    assert!(report.summary()[0].starts_with("current sign: discharge negative in 2 files, decided from the data"));
    // A pulse train the voltage does not answer: the sign cannot be decided; named, skipped.
    std::fs::write(dir.path().join("data/00002.csv"), nasa(&|k| if k % 2 == 0 { -2.0 } else { 2.0 }, &|_| 3.9))
        .unwrap();
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records.len(), 2);
    assert!(report.skipped[0].reason.contains("00002.csv") && report.skipped[0].reason.contains("--current-sign"));
    let (b6, _) = read_nasa_with(dir.path(), "B0006", None, &ReadOptions::default()).unwrap();
    assert_eq!(b6.len(), 1);
    // One file of three exported with the other sign: read from its data, and named in a note.
    let flipped = nasa(&|k| -loaded(k), &|k| if k == 0 || k >= 27 { 4.2 } else { 4.0 - 0.02 * k as f64 });
    std::fs::write(dir.path().join("data/00002.csv"), flipped).unwrap();
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert!(records.len() == 3 && records.iter().all(|d| d.current_a[5] > 1.9), "{report:?}");
    let note = report.notes.iter().find(|n| n.starts_with("current sign:")).expect("the odd file is named");
    assert!(
        note.contains("1 of the cell's 3 files read as discharge-positive") && note.contains("00002.csv"),
        "{note}"
    );
    assert!(!report.notes.iter().any(|n| n.contains("00001.csv")), "{:?}", report.notes);
}

/// The independent generator's cells (RK4 physics with relaxation, piecewise loads with rests, sensor
/// noise) written as the generic CSV: the general reader decides their sign from the data with a clear
/// margin and reads exactly what the fixed-sign generic reader reads.
#[test]
fn synthetic_cells_read_the_same_through_the_general_reader_with_the_sign_from_the_data() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    for cause in ["none", "thermal", "extra_polarization"] {
        let mut rng = common::cell_rng(cause, 3);
        let truth = common::Truth::draw(cause, &mut rng);
        let path = dir.path().join(format!("{cause}.csv"));
        let mut f = std::fs::File::create(&path).unwrap();
        writeln!(f, "time_s,voltage_v,current_a,temperature_c,cycle").unwrap();
        for (k, kind) in common::PLAN.iter().enumerate() {
            let cycle = k as u32 + 1;
            for (t, v, i, tc) in common::record(&truth, cycle, *kind, &mut rng) {
                writeln!(f, "{t:.1},{v:.6},{i:.6},{tc:.4},{cycle}").unwrap();
            }
        }
        drop(f);
        let fixed = read_generic(&path, None).unwrap();
        let (auto, report) = read_csv(&path, &ReadOptions::default()).unwrap();
        let share = report.signs[0].evidence.share_for(true).unwrap();
        assert!(report.signs[0].discharge_positive && share > 0.9, "{cause}: {:?}", report.signs[0]);
        assert!(report.skipped.is_empty() && report.notes.is_empty(), "{cause}: {:?}", report.summary());
        assert_eq!(auto.len(), fixed.len());
        for (a, b) in auto.iter().zip(&fixed) {
            assert_eq!(
                (a.cycle, &a.time_s, &a.voltage_v, &a.current_a),
                (b.cycle, &b.time_s, &b.voltage_v, &b.current_a)
            );
            assert_eq!((&a.temperature_k, a.ambient_k), (&b.temperature_k, b.ambient_k));
        }
    }
}
