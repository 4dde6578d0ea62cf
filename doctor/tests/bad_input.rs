//! Bad input never passes silently: missing files named in the metadata are skipped with a count,
//! truncated records (ending under load above the cut-off) are flagged and kept out of the fits while
//! records ending under load at the cut-off are used, a cut-off above a record's first loaded voltage is
//! refused for that record while the others run, non-finite or non-numeric fields are reported with file
//! and line, a millivolt voltage column is refused with a hint, and a discharge current written negative
//! (NASA's sign) in the generic CSV is refused with the sign convention.

mod common;

use bcal_doctor::read::{read_generic, read_nasa};
use bcal_doctor::{diagnose, Cause, DiagnoseConfig, DoctorError};
use common::{config, record, LoadKind, Truth};
use rand::rngs::StdRng;
use rand::SeedableRng;
use std::io::Write;
use std::path::Path;

fn write(path: &Path, text: &str) {
    std::fs::File::create(path).unwrap().write_all(text.as_bytes()).unwrap();
}

/// A small NASA-layout discharge record (current negative while discharging).
fn nasa_record(rows: usize) -> String {
    let mut s = String::from("Voltage_measured,Current_measured,Temperature_measured,Current_load,Voltage_load,Time\n");
    for k in 0..rows {
        let i = if k == 0 || k + 3 >= rows { -0.001 } else { -2.0 };
        s.push_str(&format!("{},{i},24.5,-2.0,3.0,{}\n", 4.2 - 0.01 * k as f64, 10.0 * k as f64));
    }
    s
}

#[test]
fn missing_files_named_in_metadata_are_skipped_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("data")).unwrap();
    write(
        &dir.path().join("metadata.csv"),
        "type,start_time,ambient_temperature,battery_id,test_id,uid,filename,Capacity,Re,Rct\n\
         charge,[2008 4 2 13 8 17],24,B0005,0,1,00001.csv,,,\n\
         discharge,[2008 4 2 15 25 41],24,B0005,1,2,00002.csv,1.85,,\n\
         discharge,[2008 4 2 19 43 48],24,B0005,3,3,00003.csv,[],,\n\
         discharge,[2008 4 3 19 43 48],24,B0005,5,4,00004.csv,1.80,,\n\
         discharge,[2010 7 21 15 0 35],4,B0047,0,5,00005.csv,1.67,,\n",
    );
    write(&dir.path().join("data/00002.csv"), &nasa_record(20));
    write(&dir.path().join("data/00004.csv"), &nasa_record(20));
    let (records, report) = read_nasa(dir.path(), "B0005", None).unwrap();
    assert_eq!(report.missing_files, vec!["00003.csv".to_string()]);
    assert_eq!(report.rows_selected, 3);
    // Cycle numbers follow the metadata order, so the gap stays visible.
    assert_eq!(records.iter().map(|d| d.cycle).collect::<Vec<_>>(), vec![1, 3]);
    assert_eq!(records[0].stated_capacity_ah, Some(1.85));
    assert!(records[0].current_a[5] > 0.0, "NASA discharge current is flipped to positive");
    assert!((records[0].ambient_k - 297.15).abs() < 1e-9);
    let (only, _) = read_nasa(dir.path(), "B0005", Some(&(3..=3))).unwrap();
    assert_eq!(only.len(), 1);
}

/// An empty file (NASA's B0049-B0052 hold some: the software crashed) is called empty, not a file that lacks
/// a column, in the generic reader and in a NASA folder (where it is skipped while the others read).
#[test]
fn an_empty_file_is_called_empty() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("empty.csv");
    write(&path, "");
    let err = read_generic(&path, None).unwrap_err();
    assert!(matches!(err, DoctorError::EmptyFile { .. }) && err.to_string().contains("empty.csv: empty"), "{err}");
    std::fs::create_dir(dir.path().join("data")).unwrap();
    write(
        &dir.path().join("metadata.csv"),
        "type,start_time,ambient_temperature,battery_id,test_id,uid,filename,Capacity,Re,Rct\n\
         discharge,[2010 7 21 15 0 35],4,B0049,0,1,00001.csv,1.6,,\n\
         discharge,[2010 7 21 19 0 35],4,B0049,1,2,00002.csv,1.6,,\n",
    );
    write(&dir.path().join("data/00001.csv"), &nasa_record(20));
    write(&dir.path().join("data/00002.csv"), "");
    let opts = bcal_doctor::read::ReadOptions::default();
    let (records, report) = bcal_doctor::input::read_any(dir.path(), "B0049", None, &opts).unwrap();
    assert_eq!(records.len(), 1);
    assert!(report.skipped.iter().any(|s| s.reason.contains("00002.csv: empty")), "{:?}", report.skipped);
}

#[test]
fn non_numeric_and_nan_fields_are_reported_with_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.csv");
    let mut text = String::from("time_s,voltage_v,current_a\n");
    for k in 0..12 {
        text.push_str(&format!("{},{},2.0\n", 10 * k, if k == 4 { "nan".to_string() } else { "3.9".to_string() }));
    }
    write(&path, &text);
    let err = read_generic(&path, None).unwrap_err();
    assert!(matches!(err, DoctorError::BadField { line: 6, .. }), "{err:?}");
    let msg = err.to_string();
    assert!(msg.contains("bad.csv") && msg.contains("line 6") && msg.contains("voltage_v"), "{msg}");

    write(&path, &text.replace("nan", "3.9").replacen("2.0\n", "two\n", 3));
    let msg = read_generic(&path, None).unwrap_err().to_string();
    assert!(msg.contains("line 2") && msg.contains("current_a") && msg.contains("`two`"), "{msg}");

    // The same check holds for NASA records.
    let rec = dir.path().join("05122.csv");
    write(&rec, &nasa_record(15).replacen("24.5", "abc", 2));
    let msg = bcal_doctor::read::read_nasa_record(&rec, "B0005", 1, 297.15).unwrap_err().to_string();
    assert!(msg.contains("05122.csv") && msg.contains("line 2") && msg.contains("Temperature_measured"), "{msg}");
}

#[test]
fn voltage_in_millivolts_is_refused_with_a_hint() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mv.csv");
    let mut text = String::from("time_s,voltage_v,current_a\n");
    for k in 0..12 {
        text.push_str(&format!("{},{},2.0\n", 10 * k, 3900 - k));
    }
    write(&path, &text);
    let err = read_generic(&path, None).unwrap_err();
    assert!(matches!(err, DoctorError::VoltageInMillivolts { .. }), "{err:?}");
    assert!(err.to_string().contains("divide by 1000"), "{err}");
}

#[test]
fn negative_discharge_current_in_the_generic_csv_is_refused_with_the_sign_convention() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("neg.csv");
    let mut text = String::from("time_s,voltage_v,current_a\n");
    for k in 0..12 {
        text.push_str(&format!("{},3.9,-2.0\n", 10 * k));
    }
    write(&path, &text);
    let err = read_generic(&path, None).unwrap_err().to_string();
    assert!(err.contains("POSITIVE while discharging"), "{err}");
}

#[test]
fn time_going_backwards_is_an_error_with_the_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.csv");
    write(&path, "time_s,voltage_v,current_a\n0,4.1,2\n10,4.0,2\n5,3.9,2\n");
    let err = read_generic(&path, None).unwrap_err().to_string();
    assert!(err.contains("line 4") && err.contains("does not increase"), "{err}");
}

#[test]
fn truncated_records_are_flagged_and_kept_out_of_the_fits() {
    let mut rng = StdRng::seed_from_u64(11);
    let truth = Truth::aged(&mut rng);
    let mut records: Vec<_> = (1..=3)
        .map(|c| {
            let rows = record(&truth, c, LoadKind::Cc, &mut rng);
            to_discharge(c, truth.ambient_c, &rows)
        })
        .collect();
    // Cut cycle 2 while still under load: no cut-off, no relaxation.
    let d = &mut records[1];
    let keep = d.len() / 2;
    d.time_s.truncate(keep);
    d.voltage_v.truncate(keep);
    d.current_a.truncate(keep);
    d.temperature_k.as_mut().unwrap().truncate(keep);
    let diag = diagnose(&config(), &records[..2], &records[2..]).unwrap();
    let info = diag.records.iter().find(|r| r.cycle == 2).unwrap();
    assert!(info.truncated && info.role == "excluded" && info.capacity_ah.is_none(), "{info:?}");
    assert_eq!(diag.truncated_count, 1);
    assert_eq!(diag.base.train_cycles.iter().map(|c| c.cycle).collect::<Vec<_>>(), vec![1]);
    let full = diag.records.iter().find(|r| r.cycle == 1).unwrap();
    assert!(full.capacity_ah.is_some_and(|c| c > 0.5), "{full:?}");
}

/// A NASA folder whose metadata names one B0005 discharge, `data/00002.csv` (not written).
fn one_record_folder() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("data")).unwrap();
    write(
        &dir.path().join("metadata.csv"),
        "type,start_time,ambient_temperature,battery_id,test_id,uid,filename,Capacity,Re,Rct\n\
         discharge,[2008 4 2 15 25 41],24,B0005,1,2,00002.csv,1.85,,\n",
    );
    dir
}

/// [`one_record_folder`] with a 134-reading record written ([`nasa_record`]): the folder, the record's path, its
/// text and the record as the folder reader reads it.
fn one_clean_record() -> (tempfile::TempDir, std::path::PathBuf, String, bcal_doctor::Discharge) {
    let dir = one_record_folder();
    let path = dir.path().join("data/00002.csv");
    let good = nasa_record(134);
    write(&path, &good);
    let opts = bcal_doctor::read::ReadOptions::default();
    let clean = bcal_doctor::read::read_nasa_with(dir.path(), "B0005", None, &opts).unwrap().0.remove(0);
    (dir, path, good, clean)
}

/// Four synthetic discharges of one cell (rest, constant load to 3.0 V, relaxation).
fn four_cycles(seed: u64) -> Vec<bcal_doctor::Discharge> {
    let mut rng = StdRng::seed_from_u64(seed);
    let truth = Truth::aged(&mut rng);
    (1..=4).map(|c| to_discharge(c, truth.ambient_c, &record(&truth, c, LoadKind::Cc, &mut rng))).collect()
}

/// The doctor with one candidate: these tests are about which records it uses, not what it names.
fn quick_config(cutoff_v: Option<f64>) -> DiagnoseConfig {
    let mut cfg = DiagnoseConfig { cutoff_v, causes: vec![Cause::VoltageOffset], ..config() };
    cfg.max_causes = 1;
    cfg
}

#[test]
fn a_record_ending_under_load_at_the_cutoff_is_complete_and_used() {
    let mut records = four_cycles(12);
    let full_capacity = |d: &bcal_doctor::Discharge| {
        let w = d.windows(0.05, 2.9).unwrap();
        d.charge_ah(w.load_on, w.load_end)
    };
    let want_ah = full_capacity(&records[1]);
    // Cycle 2 logged without its relaxation: it stops on its last loaded sample (about 3.0 V).
    let d = &mut records[1];
    let keep = d.windows(0.05, 2.9).unwrap().load_end;
    d.time_s.truncate(keep);
    d.voltage_v.truncate(keep);
    d.current_a.truncate(keep);
    d.temperature_k.as_mut().unwrap().truncate(keep);
    let last_v = d.voltage_v[keep - 1];
    // This cell's cut-off is the protocol's: the record reached it and is a complete discharge.
    let diag = diagnose(&quick_config(Some(last_v + 0.001)), &records[..2], &records[2..]).unwrap();
    let info = diag.records.iter().find(|r| r.cycle == 2).unwrap();
    assert!(info.ended_at_cutoff && !info.truncated && info.role == "train", "{info:?}");
    assert!(info.capacity_ah.is_some_and(|q| (q - want_ah).abs() < 1e-12), "{info:?} vs {want_ah}");
    assert_eq!((diag.ended_at_cutoff_count, diag.truncated_count), (1, 0));
    assert_eq!(diag.base.train_cycles.iter().map(|c| c.cycle).collect::<Vec<_>>(), vec![1, 2]);
    assert!(diag.settings.cutoff_given && diag.settings.cutoff_v == last_v + 0.001);
    // For a cell with a lower cut-off (the default 2.5 V among them) the same record was cut short.
    for cutoff in [Some(last_v - 0.01), None] {
        let diag = diagnose(&quick_config(cutoff), &records[..2], &records[2..]).unwrap();
        let info = diag.records.iter().find(|r| r.cycle == 2).unwrap();
        assert!(info.truncated && info.role == "excluded" && info.capacity_ah.is_none(), "{info:?}");
        assert!(info.note.as_deref().is_some_and(|n| n.contains("truncated")), "{info:?}");
    }
}

#[test]
fn a_cutoff_above_the_first_loaded_voltage_is_refused_for_that_record_and_the_others_run() {
    let mut records = four_cycles(13);
    // Cycle 4 reads 1.2 V low throughout (a wrong channel): the 3.0 V cut-off lies above its first load.
    records[3].voltage_v.iter_mut().for_each(|v| *v -= 1.2);
    let diag = diagnose(&quick_config(Some(3.0)), &records[..2], &records[2..]).unwrap();
    let info = diag.records.iter().find(|r| r.cycle == 4).unwrap();
    let note = info.note.as_deref().unwrap();
    assert_eq!(info.role, "excluded");
    assert!(
        note.contains("cycle4.csv, cycle 4") && note.contains("cut-off 3 V is above") && note.contains("--cutoff-v"),
        "{note}"
    );
    assert!(!note.contains('\n'));
    assert_eq!(diag.base.heldout_cycles.iter().map(|c| c.cycle).collect::<Vec<_>>(), vec![3]);
    // Above every record's: nothing is left, and the error says why, naming the files.
    let msg = diagnose(&quick_config(Some(4.5)), &records[..2], &records[2..]).unwrap_err().to_string();
    assert!(msg.contains("cycle1.csv") && msg.contains("cut-off 4.5 V is above the first loaded voltage"), "{msg}");
    // A cut-off that is no voltage (millivolts) is refused before anything runs.
    let msg = diagnose(&quick_config(Some(2500.0)), &records[..2], &records[2..]).unwrap_err().to_string();
    assert!(msg.contains("cutoff_v = 2500 V") && msg.contains("in volts"), "{msg}");
}

fn to_discharge(cycle: u32, ambient_c: f64, rows: &[(f64, f64, f64, f64)]) -> bcal_doctor::Discharge {
    bcal_doctor::Discharge {
        cell: "synthetic".into(),
        cycle,
        source: format!("cycle{cycle}.csv").into(),
        ambient_k: ambient_c + 273.15,
        time_s: rows.iter().map(|r| r.0).collect(),
        voltage_v: rows.iter().map(|r| r.1).collect(),
        current_a: rows.iter().map(|r| r.2).collect(),
        temperature_k: Some(rows.iter().map(|r| r.3 + 273.15).collect()),
        stated_capacity_ah: None,
    }
}

/// A NASA record in other units than its layout's (current in mA, time in ms: each reads as 1000 times the
/// charge a cell holds) is refused naming both columns and what to do, whatever sign is asked; one reading
/// at 0 V while the load is on (a logger's glitch, which would be read as the cut-off and end the discharge
/// there) is refused naming its line; one at rest before the load is read as before.
#[test]
fn a_nasa_record_in_ma_or_ms_or_with_a_0_v_reading_is_refused_naming_it() {
    use bcal_doctor::read::{read_nasa_record, read_nasa_record_with, ReadOptions};
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("05122.csv");
    // Ten seconds at rest, 22 minutes under load at 2 A (0.72 Ah; in ms 720 Ah, more than a cell holds).
    let good = nasa_record(134);
    write(&rec, &good);
    read_nasa_record(&rec, "B0005", 1, 297.15).unwrap();
    let milli = |field: usize| -> String {
        let mut lines = good.lines();
        let mut out = format!("{}\n", lines.next().unwrap());
        for l in lines {
            let mut f: Vec<String> = l.split(',').map(str::to_string).collect();
            f[field] = format!("{}", f[field].parse::<f64>().unwrap() * 1000.0);
            out.push_str(&(f.join(",") + "\n"));
        }
        out
    };
    for (field, column, why) in
        [(1, "Current_measured", "more than a cell carries"), (5, "Time", "more than a cell holds")]
    {
        write(&rec, &milli(field));
        for err in [
            read_nasa_record(&rec, "B0005", 1, 297.15).unwrap_err(),
            read_nasa_record_with(&rec, "B0005", 1, 297.15, &ReadOptions::default()).unwrap_err(),
        ] {
            let msg = err.to_string();
            assert!(matches!(err, DoctorError::SuspectUnit { .. }), "{column}: {msg}");
            assert!(msg.contains("05122.csv") && msg.contains(&format!("column `{column}`")), "{msg}");
            assert!(msg.contains(why) && msg.contains("divide it by 1000"), "{msg}");
        }
    }
    // Row k = 5 (line 7, at 4.15 V) at 0 V.
    write(&rec, &good.replacen("4.15,", "0.0,", 1));
    let err = read_nasa_record(&rec, "B0005", 1, 297.15).unwrap_err();
    assert!(matches!(err, DoctorError::VoltageGlitch { line: 7, .. }), "{err:?}");
    assert!(err.to_string().contains("05122.csv, line 7") && err.to_string().contains("remove that row"), "{err}");
    // At rest before the load (a cell not yet connected reads near 0 V) the record is read as before.
    write(&rec, &good.replacen("4.2,", "0.2,", 1));
    assert_eq!(read_nasa_record(&rec, "B0005", 1, 297.15).unwrap().voltage_v[0], 0.2);
    // A lone -40 A reading amid 2 A (row 50, line 52) with the voltage unmoved is a glitch; a 20 A pulse that
    // moves the voltage as a cell's resistance would (2 V, 0.11 ohm) is read.
    write(&rec, &good.replacen(",-2,24.5,-2.0,3.0,500\n", ",-40.0,24.5,-2.0,3.0,500\n", 1));
    let err = read_nasa_record(&rec, "B0005", 1, 297.15).unwrap_err();
    assert!(matches!(err, DoctorError::CurrentGlitch { line: 52, .. }), "{err:?}");
    assert!(
        err.to_string().contains("05122.csv, line 52: current -40.0 A") && err.to_string().contains("remove"),
        "{err}"
    );
    let mut lines: Vec<String> = good.lines().map(str::to_string).collect();
    lines[51] = format!("{},-20.0,24.5,-2.0,3.0,500", 4.2 - 0.5 - 2.0);
    write(&rec, &(lines.join("\n") + "\n"));
    assert_eq!(read_nasa_record(&rec, "B0005", 1, 297.15).unwrap().current_a[50], 20.0);
    // The same two readings in a row (a logger that wrote the value twice): the glitch is refused at its
    // first line, the pulse is read.
    let twice = |current_a: f64, drop_v: f64| {
        let mut lines: Vec<String> = good.lines().map(str::to_string).collect();
        for row in [51, 52] {
            let mut f: Vec<String> = lines[row].split(',').map(str::to_string).collect();
            f[0] = format!("{}", f[0].parse::<f64>().unwrap() - drop_v);
            f[1] = format!("{current_a}");
            lines[row] = f.join(",");
        }
        write(&rec, &(lines.join("\n") + "\n"));
        read_nasa_record(&rec, "B0005", 1, 297.15)
    };
    let err = twice(-40.0, 0.0).unwrap_err();
    assert!(matches!(err, DoctorError::CurrentGlitch { line: 52, .. }), "{err:?}");
    assert_eq!(twice(-20.0, 2.0).unwrap().current_a[51], 20.0);
}

/// A current glitch of one to five readings (the voltage unmoved, two neighbours that agree) is left out by the
/// folder reader and said, naming file, line and value, inside a record or at its first or last readings (where
/// it would have moved the load-on or added charge after the cut-off); the strict reader refuses the record at
/// the same line. The charge read is the clean record's to within the readings left out.
#[test]
fn a_current_glitch_is_left_out_and_said_anywhere_in_a_record() {
    use bcal_doctor::read::{read_nasa, read_nasa_with, ReadOptions};
    let (dir, path, good, clean) = one_clean_record();
    let charge_ah = |d: &bcal_doctor::Discharge| d.charge_ah(0, d.len());
    // Rows (0-based, header on line 1) set to -40 A, the voltage as it was.
    let spiked = |rows: &[usize]| -> String {
        let mut lines: Vec<String> = good.lines().map(str::to_string).collect();
        for &row in rows {
            let mut f: Vec<String> = lines[row + 1].split(',').map(str::to_string).collect();
            f[1] = "-40.0".into();
            lines[row + 1] = f.join(",");
        }
        lines.join("\n") + "\n"
    };
    let three = vec![50, 51, 52];
    for (rows, line) in
        [(vec![50], 52), (vec![50, 51], 52), (three, 52), (vec![0], 2), (vec![0, 1], 2), (vec![133], 135)]
    {
        write(&path, &spiked(&rows));
        let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
        let d = &records[0];
        assert_eq!(d.len(), 134 - rows.len(), "{rows:?}");
        assert!(d.current_a.iter().all(|i| i.abs() < 2.1), "{rows:?}: a glitch read");
        assert!((charge_ah(d) - charge_ah(&clean)).abs() < 2.0 * 10.0 / 3600.0 * rows.len() as f64, "{rows:?}");
        assert_eq!(d.first_loaded(0.1), clean.first_loaded(0.1).map(|k| k - rows.iter().filter(|&&r| r == 0).count()));
        let note = report.notes.iter().find(|n| n.contains("glitch")).expect("the glitch is said");
        assert!(
            note.contains(&format!("00002.csv, line {line}: current -40.0 A")) && note.contains("left out"),
            "{note}"
        );
        assert_eq!(note.contains("readings in all"), rows.len() > 1, "{note}");
        let err = read_nasa(dir.path(), "B0005", None).unwrap_err().to_string();
        assert!(err.contains(&format!("00002.csv, line {line}: current -40.0 A")), "{err}");
    }
    // A logger's overflow value (6553.5 A) on one reading: a glitch left out, not a record in mA.
    let mut lines: Vec<String> = good.lines().map(str::to_string).collect();
    lines[61] = lines[61].replacen(",-2,", ",6553.5,", 1);
    write(&path, &(lines.join("\n") + "\n"));
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].len(), 133);
    assert!(report.notes.iter().any(|n| n.contains("line 62: current 6553.5 A")), "{:?}", report.notes);
    // Six in a row is past what is taken for one glitch: read as it is, as a load the voltage never follows.
    write(&path, &spiked(&(50..56).collect::<Vec<usize>>()));
    let (records, _) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].len(), 134);
    // With a frozen end too (a logger that froze under load after 100 readings): the end is cut, the glitch left
    // out, both said.
    let head: Vec<String> = spiked(&[50]).lines().take(101).map(str::to_string).collect();
    let stuck = head[100].rsplit_once(',').unwrap().0.to_string();
    let frozen: String = (100..112).map(|k| format!("{stuck},{}\n", 10 * k)).collect();
    write(&path, &format!("{}\n{frozen}", head.join("\n")));
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].len(), 99, "rows 0-99 but the glitch");
    assert!(report.notes.iter().any(|n| n.contains("line 52: current -40.0 A")), "{:?}", report.notes);
    assert!(report.notes.iter().any(|n| n.contains("froze")), "{:?}", report.notes);
    // With a reading written twice too: the strict reader names whichever comes first in the file.
    for (glitch_row, copied_row, line) in [(50, 80, "line 52: current -40.0 A"), (100, 30, "line 33: time")] {
        let mut lines: Vec<String> = spiked(&[glitch_row]).lines().map(str::to_string).collect();
        lines.insert(copied_row + 2, lines[copied_row + 1].clone());
        write(&path, &(lines.join("\n") + "\n"));
        let err = read_nasa(dir.path(), "B0005", None).unwrap_err().to_string();
        assert!(err.contains(line), "{line}: {err}");
    }
    // A square wave in mA (1 reading at 4000 "A" in 3, the voltage following by less than 2 mV per "A") is
    // refused as milliamperes, not read as pulses left out.
    let mut lines: Vec<String> = good.lines().map(str::to_string).collect();
    for (k, line) in lines.iter_mut().enumerate().skip(1) {
        let mut f: Vec<String> = line.split(',').map(str::to_string).collect();
        f[1] = if k % 3 == 0 { "-4000.0" } else { "-1.0" }.into();
        *line = f.join(",");
    }
    write(&path, &(lines.join("\n") + "\n"));
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("Current_measured") && err.contains("divide it by 1000"), "{err}");
}

/// Two rows written in the wrong order (a reading whose time falls between the two before it) are read in their
/// place by time and said, by the folder reader and the general reader; the strict reader refuses them, naming
/// the line; a clock that steps further back (a logger restarted) still refuses the record.
#[test]
fn two_rows_written_in_the_wrong_order_are_read_in_time_order_and_said() {
    use bcal_doctor::read::{read_csv, read_nasa, read_nasa_with, ReadOptions};
    let (dir, path, good, clean) = one_clean_record();
    let mut lines: Vec<&str> = good.lines().collect();
    lines.swap(51, 52);
    write(&path, &(lines.join("\n") + "\n"));
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].time_s, clean.time_s);
    assert_eq!(records[0].current_a, clean.current_a);
    assert_eq!(records[0].voltage_v, clean.voltage_v);
    let note = report.notes.iter().find(|n| n.contains("wrong order")).expect("said");
    assert!(note.contains("00002.csv, line 53") && note.contains("1 such reading"), "{note}");
    let err = read_nasa(dir.path(), "B0005", None).unwrap_err().to_string();
    assert!(err.contains("00002.csv, line 53") && err.contains("does not increase"), "{err}");
    // The last two rows swapped: nothing after them tells a swap from a clock that jumped ahead on the first of
    // them, which is left out (the relaxation's last reading), said.
    let mut lines: Vec<&str> = good.lines().collect();
    lines.swap(133, 134);
    write(&path, &(lines.join("\n") + "\n"));
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].time_s, clean.time_s[..133]);
    let note = report.notes.iter().find(|n| n.contains("jumped ahead")).expect("said");
    assert!(note.contains("00002.csv, line 134: the reading at 1330.0 s") && note.contains("left out"), "{note}");
    // A time of -0 after 0 is no swap (it does not fall between two readings): refused as before.
    let minus_zero = good.replacen(",10\n", ",-0\n", 1);
    write(&path, &minus_zero);
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("line 3") && err.contains("does not increase"), "{err}");
    // A logger restarted mid-record: its clock from 0 again.
    let restarted: String = good
        .lines()
        .enumerate()
        .map(|(k, l)| match k {
            k if k > 80 => {
                let (head, t) = l.rsplit_once(',').unwrap();
                format!("{head},{}\n", t.parse::<f64>().unwrap() - 800.0)
            }
            _ => format!("{l}\n"),
        })
        .collect();
    write(&path, &restarted);
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("00002.csv, line 82") && err.contains("does not increase"), "{err}");
    // The general reader.
    let g = dir.path().join("g.csv");
    let rows: Vec<String> = (0..40).map(|k| format!("{},{},2.0", 10 * k, 4.1 - 0.01 * k as f64)).collect();
    let mut swapped = rows.clone();
    swapped.swap(20, 21);
    write(&g, &format!("time_s,voltage_v,current_a\n{}\n", rows.join("\n")));
    let clean = read_csv(&g, &ReadOptions::default()).unwrap().0.remove(0);
    write(&g, &format!("time_s,voltage_v,current_a\n{}\n", swapped.join("\n")));
    let (records, report) = read_csv(&g, &ReadOptions::default()).unwrap();
    assert_eq!((&records[0].time_s, &records[0].voltage_v), (&clean.time_s, &clean.voltage_v));
    assert!(
        report.notes.iter().any(|n| n.contains("g.csv, line 23") && n.contains("wrong order")),
        "{:?}",
        report.notes
    );
    // With a cycle column, a swap at a cycle's last rows is unconfirmed: the reading it went before is left out.
    let cycles: Vec<String> =
        (0..80).map(|k| format!("{},{},2.0,{}", 10 * (k % 40), 4.1 - 0.01 * (k % 40) as f64, 1 + k / 40)).collect();
    let mut swapped = cycles.clone();
    swapped.swap(38, 39);
    write(&g, &format!("time_s,voltage_v,current_a,cycle\n{}\n", swapped.join("\n")));
    let (records, report) = read_csv(&g, &ReadOptions::default()).unwrap();
    assert_eq!((records[0].len(), records[1].len()), (39, 40));
    assert!(report.notes.iter().any(|n| n.contains("g.csv, line 40") && n.contains("left out")), "{:?}", report.notes);
}

/// A NASA `metadata.csv` whose type or cell id a spreadsheet wrote with spaces around or in another case reads as
/// the layout's; a row of the cell whose type is none of the layout's is left out and said, naming its line.
#[test]
fn metadata_types_and_ids_as_people_write_them() {
    use bcal_doctor::read::{read_nasa_with, ReadOptions};
    let (dir, _path, good, clean) = one_clean_record();
    write(&dir.path().join("data/00003.csv"), &good);
    write(
        &dir.path().join("metadata.csv"),
        "type,start_time,ambient_temperature,battery_id,test_id,uid,filename,Capacity,Re,Rct\n\
         charge,[2008 4 2 13 25 41],24,B0005,0,1,00001.csv,,,\n\
          Discharge ,[2008 4 2 15 25 41],24,b0005 ,1,2,00002.csv,1.85,,\n\
         discharge_cc,[2008 4 3 15 25 41],24,B0005,2,3,00003.csv,1.84,,\n\
         discharge,[2008 4 4 15 25 41],24,B0006,3,4,00003.csv,1.84,,\n",
    );
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records.len(), 1);
    assert_eq!(records[0].voltage_v, clean.voltage_v);
    let note = report.notes.iter().find(|n| n.contains("none of discharge")).expect("said");
    assert!(note.contains("metadata.csv, line 4: type `discharge_cc`") && note.contains("1 such row"), "{note}");
}

/// A whole life in a CSV without a cycle column whose charges open with a reading at a discharge's current (as
/// NASA's charge files do): that reading is no part of the discharge before it (whose end stays its load's) nor a
/// discharge of its own (it takes no record's number), said naming its line; a pulsed load's last pulse before a
/// charge stays the load's.
#[test]
fn a_charger_pulse_before_a_charge_is_no_discharge() {
    use bcal_doctor::read::{read_csv, ReadOptions};
    let dir = tempfile::tempdir().unwrap();
    let g = dir.path().join("life.csv");
    // A rest, a 2 A discharge to 3.22 V, a relaxation of 640 s, `gap_s` without readings, the charger's first
    // reading at 3.36 A and a charge, one reading every 10 s, from `t0_s`; `pulsed`: the load on every other reading.
    let cycle = |t0_s: f64, gap_s: f64, pulsed: bool| -> Vec<(f64, f64, f64)> {
        let mut rows = Vec::new();
        let mut t = t0_s;
        let mut push = |v: f64, i: f64, dt: f64| {
            rows.push((t, v, i));
            t += dt;
        };
        (0..10).for_each(|_| push(4.15, 0.0, 10.0));
        for k in 0..40 {
            let on = !pulsed || k % 2 == 1;
            push(if on { 4.0 - 0.02 * k as f64 } else { 4.05 - 0.02 * k as f64 }, if on { 2.0 } else { 0.0 }, 10.0);
        }
        if !pulsed {
            (0..64).for_each(|k| push(3.6, 0.0, if k == 63 { 10.0 + gap_s } else { 10.0 }));
            push(3.0, 3.36, 10.0);
        }
        (0..20).for_each(|_| push(4.1, -1.5, 10.0));
        rows
    };
    let csv = |rows: &[(f64, f64, f64)]| -> String {
        let body: String = rows.iter().map(|(t, v, i)| format!("{t},{v},{i}\n")).collect();
        format!("time_s,voltage_v,current_a\n{body}")
    };
    let life: Vec<_> = [cycle(0.0, 0.0, false), cycle(2000.0, 2000.0, false), cycle(6000.0, 0.0, false)].concat();
    write(&g, &csv(&life));
    let (records, report) = read_csv(&g, &ReadOptions::default()).unwrap();
    assert_eq!(records.iter().map(|d| d.cycle).collect::<Vec<_>>(), [1, 2, 3], "{:?}", report.notes);
    for d in &records {
        let last = (0..d.len()).rev().find(|&k| d.current_a[k] > 0.1).unwrap();
        assert!((d.voltage_v[last] - 3.22).abs() < 1e-9 && d.current_a[last] == 2.0, "cycle {}", d.cycle);
        assert_eq!(d.len(), 114, "cycle {}: the rest, the load and the relaxation", d.cycle);
    }
    let said: Vec<&String> = report.notes.iter().filter(|n| n.contains("a charger's first readings")).collect();
    assert_eq!(said.len(), 3, "{:?}", report.notes);
    assert!(
        said[0].contains("life.csv, line 116: a discharge current of 3.36 A on 1 reading") && said[0].contains("650 s"),
        "{}",
        said[0]
    );
    // A pulsed load (10 s on, 10 s off) whose last pulse comes right before a charge keeps it.
    write(&g, &csv(&cycle(0.0, 0.0, true)));
    let (records, report) = read_csv(&g, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].current_a.iter().filter(|&&i| i > 0.1).count(), 20, "{:?}", report.notes);
    assert!(!report.notes.iter().any(|n| n.contains("charger")), "{:?}", report.notes);
}

/// A reading at the time of the one before with other values (a clock coarser than the logging) is left out and
/// said by the folder reader and the general reader (the first at each time kept); the strict reader refuses the
/// record naming its line.
#[test]
fn a_second_reading_at_the_same_time_is_left_out_and_said() {
    use bcal_doctor::read::{read_csv, read_nasa, read_nasa_with, ReadOptions};
    let (dir, path, good, clean) = one_clean_record();
    // Rows 40 and 90 (lines 42 and 92) written again at their own times, the voltage 1 mV lower.
    let mut lines: Vec<String> = good.lines().map(str::to_string).collect();
    for row in [90, 40] {
        let f: Vec<String> = lines[row + 1].split(',').map(str::to_string).collect();
        let v: f64 = f[0].parse().unwrap();
        lines.insert(row + 2, [vec![format!("{}", v - 0.001)], f[1..].to_vec()].concat().join(","));
    }
    write(&path, &(lines.join("\n") + "\n"));
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!((&records[0].time_s, &records[0].voltage_v), (&clean.time_s, &clean.voltage_v));
    let note = report.notes.iter().find(|n| n.contains("the time of the one before")).expect("said");
    assert!(note.contains("00002.csv, line 43: a reading at 400.0 s") && note.contains("2 such readings"), "{note}");
    let err = read_nasa(dir.path(), "B0005", None).unwrap_err().to_string();
    assert!(err.contains("00002.csv, line 43: time 400.0 s does not increase"), "{err}");
    // The general reader.
    let g = dir.path().join("g.csv");
    let rows: Vec<String> = (0..40).map(|k| format!("{},{},2.0", 10 * k, 4.1 - 0.01 * k as f64)).collect();
    write(&g, &format!("time_s,voltage_v,current_a\n{}\n", rows.join("\n")));
    let plain = read_csv(&g, &ReadOptions::default()).unwrap().0.remove(0);
    let mut again = rows.clone();
    again.insert(21, format!("200,{},2.0", 4.1 - 0.01 * 20.0 - 0.002));
    write(&g, &format!("time_s,voltage_v,current_a\n{}\n", again.join("\n")));
    let (records, report) = read_csv(&g, &ReadOptions::default()).unwrap();
    assert_eq!((&records[0].time_s, &records[0].voltage_v), (&plain.time_s, &plain.voltage_v));
    assert!(report.notes.iter().any(|n| n.contains("g.csv, line 23: a reading at 200.0 s")), "{:?}", report.notes);
}

/// A CSV written in a locale whose decimal mark is the comma (fields separated by `;`) or separated by tabs reads as
/// its comma-separated twin, and says how it was read; in a comma-separated file a decimal comma is a bad field.
#[test]
fn semicolons_tabs_and_decimal_commas_read_as_commas_and_points() {
    use bcal_doctor::read::{read_csv, ReadOptions};
    let dir = tempfile::tempdir().unwrap();
    let rows: Vec<[String; 4]> = (0..60)
        .map(|k| {
            let i = if (10..50).contains(&k) { 2.0 } else { 0.0 };
            let v = if i > 0.0 { 4.0 - 0.02 * (k - 10) as f64 } else { 4.15 };
            [format!("{}", 10.5 * k as f64), format!("{v}"), format!("{i}"), format!("{}", 24.25 + 0.01 * k as f64)]
        })
        .collect();
    let write_with = |name: &str, sep: &str, comma: bool| {
        let body: String = rows
            .iter()
            .map(|r| {
                let fields: Vec<String> =
                    r.iter().map(|f| if comma { f.replace('.', ",") } else { f.clone() }).collect();
                fields.join(sep) + "\n"
            })
            .collect();
        let path = dir.path().join(name);
        write(&path, &format!("{}\n{body}", ["time_s", "voltage_v", "current_a", "temperature_c"].join(sep)));
        path
    };
    let (plain, report) = read_csv(&write_with("plain.csv", ",", false), &ReadOptions::default()).unwrap();
    assert!(!report.units.iter().any(|u| u.contains("separated")), "{:?}", report.units);
    for (name, sep, comma, said) in [("semi.csv", ";", true, "`;`"), ("tab.csv", "\t", false, "a tab")] {
        let (records, report) = read_csv(&write_with(name, sep, comma), &ReadOptions::default()).unwrap();
        assert_eq!(records.len(), plain.len(), "{name}");
        for (a, b) in records.iter().zip(&plain) {
            assert_eq!(
                (&a.time_s, &a.voltage_v, &a.current_a, &a.temperature_k),
                (&b.time_s, &b.voltage_v, &b.current_a, &b.temperature_k),
                "{name}"
            );
        }
        assert!(report.units.iter().any(|u| u.contains(&format!("separated by {said}"))), "{name}: {:?}", report.units);
    }
    // A temperature in Fahrenheit (`temperature_f`) is converted, as one in K is, not dropped.
    let path = dir.path().join("f.csv");
    let body: String = rows
        .iter()
        .map(|r| format!("{},{},{},{}\n", r[0], r[1], r[2], r[3].parse::<f64>().unwrap() * 9.0 / 5.0 + 32.0))
        .collect();
    write(&path, &format!("time_s,voltage_v,current_a,temperature_f\n{body}"));
    let (records, report) = read_csv(&path, &ReadOptions::default()).unwrap();
    let (got, want) = (records[0].temperature_k.as_ref().unwrap(), plain[0].temperature_k.as_ref().unwrap());
    assert!(got.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-9), "{got:?}");
    assert!(report.units.iter().any(|u| u.contains("degF")), "{:?}", report.units);
    // The first value with a mark sets the file's: a value with the other one (a thousands separator, `1.000` or
    // `1,000`) is refused, named, not read as a decimal.
    for (name, sep, comma, row, thousand) in [
        ("semi2.csv", ";", true, "\n42;4,15;", "\n1.042;4,15;"),
        ("tab2.csv", "\t", false, "\n42\t4.15\t", "\n1,042\t4.15\t"),
    ] {
        let path = write_with(name, sep, comma);
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains(row), "{name}");
        write(&path, &text.replacen(row, thousand, 1));
        let err = read_csv(&path, &ReadOptions::default()).unwrap_err().to_string();
        let shown = thousand[1..].split(sep).next().unwrap();
        assert!(err.contains(&format!("{name}, line 6: field `time_s` = `{shown}`")), "{name}: {err}");
    }
    // A decimal comma in a comma-separated file (the field quoted): a bad field, named.
    let path = dir.path().join("quoted.csv");
    let mut text = std::fs::read_to_string(write_with("q.csv", ",", false)).unwrap();
    text = text.replacen("\n10.5,4.15,", "\n\"10,5\",4.15,", 1);
    write(&path, &text);
    let err = read_csv(&path, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("quoted.csv, line 3: field `time_s` = `10,5`"), "{err}");
}

/// A general CSV without a cycle column whose logger restarted (its clock from 0 again) between discharges: every
/// discharge is read, the restart said, and the records after it on a session of their own, so that no rest is
/// taken across clocks that do not agree; a time that steps back on one reading only is refused naming its line, and a restart at the
/// file's last reading is left out and said.
#[test]
fn a_logger_restart_in_a_csv_without_cycles_starts_a_new_session() {
    use bcal_doctor::read::{read_csv, ReadOptions};
    let dir = tempfile::tempdir().unwrap();
    let g = dir.path().join("life.csv");
    // (time, voltage, current) rows of a rest, a 2 A discharge and a relaxation, from `t0_s`, one every 10 s; a
    // charge after it.
    let discharge = |t0_s: f64, dv: f64| -> Vec<(f64, f64, f64)> {
        let rest = (0..10).map(|k| (4.15, 0.0, k));
        let load = (0..40).map(|k| (4.0 - 0.02 * k as f64, 2.0, 10 + k));
        let relax = (0..10).map(|k| (3.6, 0.0, 50 + k));
        let charge = (0..20).map(|k| (4.1, -1.5, 60 + k));
        rest.chain(load).chain(relax).chain(charge).map(|(v, i, k)| (t0_s + 10.0 * k as f64, v + dv, i)).collect()
    };
    let csv = |rows: &[(f64, f64, f64)]| -> String {
        let body: String = rows.iter().map(|(t, v, i)| format!("{t},{v},{i}\n")).collect();
        format!("time_s,voltage_v,current_a\n{body}")
    };
    let before: Vec<_> = [discharge(0.0, 0.0), discharge(800.0, 0.0)].concat();
    // The session after the restart reads other voltages (a copy of readings kept is a buffer written again).
    let life: Vec<_> = [before.clone(), discharge(0.0, -0.001)].concat();
    write(&g, &csv(&before));
    let (alone, _) = read_csv(&g, &ReadOptions::default()).unwrap();
    write(&g, &csv(&life));
    let (records, report) = read_csv(&g, &ReadOptions::default()).unwrap();
    assert_eq!(records.iter().map(|d| d.cycle).collect::<Vec<_>>(), [1, 2, 3]);
    for (a, b) in alone.iter().zip(&records) {
        assert_eq!((&a.time_s, &a.voltage_v, &a.current_a), (&b.time_s, &b.voltage_v, &b.current_a));
    }
    assert_eq!((&records[2].time_s, &records[2].current_a), (&records[0].time_s, &records[0].current_a));
    // The restart is the file's row 160 (line 162), at 0 s after 1590 s.
    let note = report.notes.iter().find(|n| n.contains("restarted")).expect("the restart is said");
    assert!(note.contains("life.csv, line 162: the time steps back from 1590.0 s to 0.0 s"), "{note}");
    // Each start on its session's clock: no rest is taken between sessions (`prior::rests_before`, the lifetime).
    let starts: Vec<(u32, f64, u32)> = report.starts.iter().map(|s| (s.cycle, s.start_s, s.session)).collect();
    assert_eq!(starts, [(1, 0.0, 0), (2, 800.0, 0), (3, 0.0, 1)]);
    // The session after the restart reading what the first read, to the last digit (a cell at rest, a logger of
    // few digits): a session of its own, not readings written again; nor is a second reading at the restart's
    // time (a clock coarser than the logging) more than a reading left out.
    // (A buffer written again sends its last readings: a like reading more than an hour back is the restart's.)
    let same: Vec<_> = [before.clone(), discharge(4000.0, 0.0), discharge(0.0, 0.0)].concat();
    let mut coarse = [before.clone(), discharge(4000.0, 0.0), discharge(0.0, -0.001)].concat();
    coarse.insert(241, (0.0, 4.148, 0.0));
    for (rows, what) in [(&same, "the same readings"), (&coarse, "a second reading at 0 s")] {
        write(&g, &csv(rows));
        let (records, report) = read_csv(&g, &ReadOptions::default()).unwrap();
        assert_eq!(records.len(), 4, "{what}: {:?}", report.notes);
        assert_eq!(records[3].time_s, records[0].time_s, "{what}");
        assert!(report.notes.iter().any(|n| n.contains("line 242") && n.contains("restarted")), "{what}");
    }
    // One reading's time written wrong (back to 5 s amid a discharge, the next on the clock it left): refused.
    let mut wrong = life.clone();
    wrong[30].0 = 5.0;
    write(&g, &csv(&wrong));
    let err = read_csv(&g, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("life.csv, line 32: time 5.0 s does not increase"), "{err}");
    // A restart at the last reading: nothing confirms it; left out, said.
    let last: Vec<_> = [before.clone(), vec![(0.0, 4.1, 0.0)]].concat();
    write(&g, &csv(&last));
    let (records, report) = read_csv(&g, &ReadOptions::default()).unwrap();
    assert_eq!(records.len(), 2);
    assert!(
        report
            .notes
            .iter()
            .any(|n| n.contains("life.csv, line 162: the last reading's time 0.0 s") && n.contains("left out")),
        "{:?}",
        report.notes
    );
    // With a cycle column the clocks of cycles are their own: a restart within a cycle is refused, named.
    let body: String = life.iter().map(|(t, v, i)| format!("{t},{v},{i},1\n")).collect();
    write(&g, &format!("time_s,voltage_v,current_a,cycle\n{body}"));
    let err = read_csv(&g, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("life.csv, line 162") && err.contains("does not increase"), "{err}");
}

/// The general CSV reader refuses a 0 V sample in a discharge, naming the line, and leaves out a current spike
/// of up to five readings the voltage does not follow (two at either end), saying so, as the NASA reader does.
#[test]
fn a_glitch_in_a_generic_csv_discharge_is_refused_or_left_out_naming_its_line() {
    use bcal_doctor::read::{read_csv, ReadOptions};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("g.csv");
    let row = |k: usize, v: f64, i: f64| format!("{},{v},{i}\n", 10 * k);
    let text = |glitch: &dyn Fn(usize) -> Option<String>| -> String {
        let rows: String = (0..40).map(|k| glitch(k).unwrap_or_else(|| row(k, 4.1 - 0.01 * k as f64, 2.0))).collect();
        format!("time_s,voltage_v,current_a\n{rows}")
    };
    write(&path, &text(&|_| None));
    assert_eq!(read_csv(&path, &ReadOptions::default()).unwrap().0[0].len(), 40);
    write(&path, &text(&|k| (k == 20).then(|| row(20, 0.0, 2.0))));
    let msg = read_csv(&path, &ReadOptions::default()).unwrap_err().to_string();
    assert!(msg.contains("g.csv, line 22") && msg.contains("voltage 0.0 V"), "{msg}");
    // Once, twice (rows 20 and 21), three times or at the first or last reading: left out and said; six in a
    // row is past what is taken for one glitch.
    let spike =
        |rows: std::ops::Range<usize>| text(&|k| rows.contains(&k).then(|| row(k, 4.1 - 0.01 * k as f64, 40.0)));
    for (rows, line) in [(20..21, 22), (20..22, 22), (20..23, 22), (0..1, 2), (39..40, 41)] {
        write(&path, &spike(rows.clone()));
        let (records, report) = read_csv(&path, &ReadOptions::default()).unwrap();
        assert_eq!(records[0].len(), 40 - rows.len(), "{rows:?}");
        let note = report.notes.iter().find(|n| n.contains("glitch")).expect("said");
        assert!(note.contains(&format!("g.csv, line {line}: current 40.0 A")) && note.contains("left out"), "{note}");
    }
    write(&path, &spike(20..26));
    assert_eq!(read_csv(&path, &ReadOptions::default()).unwrap().0[0].len(), 40);
}

/// A logger that stops mid-write (NASA's B0049-B0052 hold such files) leaves a damaged end: a half line, NUL
/// padding, a last line cut within its time, a reading frozen while the time runs on. The record is read up to the
/// damage, said in a note naming file and line, and ends under load as a record cut short does. Readings
/// written twice (a buffer written again) are read once and said. Damage that good readings follow still
/// refuses the record naming its line, and the strict reader refuses what the others read and say.
#[test]
fn a_crashed_loggers_damaged_end_is_read_up_to_it_and_said() {
    use bcal_doctor::read::{read_csv, read_nasa_with, ReadOptions};
    let dir = one_record_folder();
    // The first 40 of 60 readings (header on line 1): the logger stopped under load at line 41.
    let whole = nasa_record(60);
    let written: String = whole.lines().take(41).map(|l| format!("{l}\n")).collect();
    let path = dir.path().join("data/00002.csv");
    write(&path, &whole);
    let clean = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap().0.remove(0);
    for (damage, end) in [
        ("half line", "3.8,-2.0,24.5,-2."),
        ("NUL padding", &"\0".repeat(512)),
        ("time cut to its first digit", "3.8,-2.0,24.5,-2.0,3.0,4"),
    ] {
        write(&path, &format!("{written}{end}"));
        let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
        assert!(report.skipped.is_empty(), "{damage}: {:?}", report.skipped);
        let d = &records[0];
        assert_eq!(d.len(), 40, "{damage}");
        assert!((d.current_a[39] - 2.0).abs() < 1e-12, "{damage}: ends under load");
        let note = report.notes.iter().find(|n| n.contains("read up to a damaged end")).expect(damage);
        assert!(note.contains("00002.csv") && note.contains("line 42") && note.contains("cut short"), "{note}");
        // The strict reader refuses it, naming the same line.
        let err = read_nasa(dir.path(), "B0005", None).unwrap_err().to_string();
        assert!(err.contains("00002.csv") && err.contains("line 42"), "{damage}: {err}");
    }
    // A logger that froze: its last reading repeated under load while the time runs on.
    let stuck = written.lines().last().unwrap().rsplit_once(',').unwrap().0;
    let frozen: String = (40..55).map(|k| format!("{stuck},{}\n", 10 * k)).collect();
    write(&path, &format!("{written}{frozen}"));
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].len(), 40);
    let note =
        report.notes.iter().find(|n| n.contains("froze") && n.contains("cut short")).expect("a frozen end is said");
    assert!(note.contains("00002.csv, line 42") && note.contains("15 readings") && note.contains("150 s"), "{note}");
    // Frozen after fewer readings than a record needs: refused, naming the freeze.
    let short: String = whole.lines().take(9).map(|l| format!("{l}\n")).collect();
    let stuck9 = short.lines().last().unwrap().rsplit_once(',').unwrap().0.to_string();
    let frozen9: String = (8..20).map(|k| format!("{stuck9},{}\n", 10 * k)).collect();
    write(&path, &format!("{short}{frozen9}"));
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("line 10") && err.contains("froze"), "{err}");
    // Readings written twice (a buffer written again mid-file, a row copied) are read once, and said.
    let lines: Vec<&str> = whole.lines().collect();
    let again = [&lines[..31], &lines[25..31], &lines[31..], &lines[59..]].concat().join("\n") + "\n";
    write(&path, &again);
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!((&records[0].time_s, &records[0].voltage_v), (&clean.time_s, &clean.voltage_v));
    let note = report.notes.iter().find(|n| n.contains("read once")).expect("readings written twice are said");
    assert!(note.contains("00002.csv, line 32") && note.contains("8 such readings"), "{note}");
    assert!(read_nasa(dir.path(), "B0005", None).unwrap_err().to_string().contains("line 32"));
    // A clock that steps back or jumps ahead amid whole lines is no damaged end (the readings after it would
    // be lost), nor is a half line a new session follows: refused, named.
    let session: String = (0..12).map(|k| format!("{},-2,24.5,-2.0,3.0,{}\n", 4.1 - 0.01 * k as f64, 10 * k)).collect();
    write(&path, &format!("{written}3.9,-2.0,24\n{session}"));
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("line 42") && err.contains("fields where"), "{err}");
    write(&path, &format!("{written}4.1,-2.0,24.5,-2.0,3.0,0\n4.0,-2.0,24.5,-2.0,3.0,10\n"));
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("line 42") && err.contains("does not increase"), "{err}");
    let mut ahead: Vec<String> = whole.lines().map(str::to_string).collect();
    ahead[21] = ahead[21].replace(",200", ",5000");
    write(&path, &(ahead.join("\n") + "\n"));
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("line 23") && err.contains("previous 5000"), "{err}");
    // The metadata a logger stopped writing (half a row at its end): read up to it, said; the strict reader
    // refuses it.
    write(&path, &whole);
    let meta = dir.path().join("metadata.csv");
    let mut text = std::fs::read_to_string(&meta).unwrap();
    text.push_str("discharge,[2008 4 3 15 25 41],24,B0005,3,3,000");
    write(&meta, &text);
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records.len(), 1);
    assert!(report.notes.iter().any(|n| n.contains("metadata.csv") && n.contains("line 3")), "{:?}", report.notes);
    assert!(read_nasa(dir.path(), "B0005", None).unwrap_err().to_string().contains("metadata.csv"));
    write(&meta, &text[..text.rfind("discharge").unwrap()]);
    // Damage that good readings follow is not an end: the record is refused, named.
    let middle: Vec<&str> = whole.lines().collect();
    write(&path, &format!("{}\n3.9,-2.0,24\n{}\n", middle[..21].join("\n"), middle[21..].join("\n")));
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("00002.csv") && err.contains("line 22") && err.contains("fields where"), "{err}");
    // The generic reader reads up to a damaged end too, and says so.
    let csv = dir.path().join("cell.csv");
    let rows: String = (0..30).map(|k| format!("{},{},2.0\n", 10 * k, 4.1 - 0.01 * k as f64)).collect();
    write(&csv, &format!("time_s,voltage_v,current_a\n{rows}290,3.8"));
    let (records, report) = read_csv(&csv, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].len(), 30);
    assert!(report.notes.iter().any(|n| n.contains("cell.csv") && n.contains("line 32")), "{:?}", report.notes);
    // And reads a row copied once.
    let copied: String = rows.lines().take(12).chain(rows.lines().skip(11)).map(|l| format!("{l}\n")).collect();
    write(&csv, &format!("time_s,voltage_v,current_a\n{copied}"));
    let (records, report) = read_csv(&csv, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].len(), 30);
    assert!(
        report.notes.iter().any(|n| n.contains("cell.csv, line 14") && n.contains("read once")),
        "{:?}",
        report.notes
    );
}

/// A temperature sensor that drops out leaves fields empty or NaN: the readers fill each with the reading's
/// before (a cell's temperature moves slowly) and say how many and where, in a NASA folder and a general
/// CSV; a record with none read at all is refused, said; the strict reader refuses any. Before, one empty
/// field refused the whole record.
#[test]
fn a_temperature_sensor_that_drops_out_is_filled_and_said() {
    use bcal_doctor::read::{read_csv, read_nasa_with, ReadOptions};
    let dir = one_record_folder();
    // Rows 10-15 (lines 12-17) without a temperature, one of them NaN; the cell warms 0.1 deg C a reading.
    let row = |k: usize, t: &str| {
        let i = if k == 0 || k + 3 >= 60 { -0.001 } else { -2.0 };
        format!("{},{i},{t},-2.0,3.0,{}\n", 4.2 - 0.01 * k as f64, 10 * k)
    };
    let header = "Voltage_measured,Current_measured,Temperature_measured,Current_load,Voltage_load,Time\n";
    let text: String = (0..60)
        .map(|k| match k {
            12 => row(k, "NaN"),
            10..=15 => row(k, ""),
            _ => row(k, &format!("{}", 24.0 + 0.1 * k as f64)),
        })
        .collect();
    write(&dir.path().join("data/00002.csv"), &format!("{header}{text}"));
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    let t = records[0].temperature_k.as_ref().unwrap();
    assert!(t[10..16].iter().all(|x| *x == t[9]) && t[16] > t[9], "{t:?}");
    let note = report.notes.iter().find(|n| n.contains("Temperature_measured")).expect("the gap is said");
    assert!(note.contains("00002.csv, line 12") && note.contains("6 of 60"), "{note}");
    let err = read_nasa(dir.path(), "B0005", None).unwrap_err().to_string();
    assert!(err.contains("line 12") && err.contains("empty"), "{err}");
    // A reading written twice with its temperature left empty is still the same reading, read once; the
    // voltage's NaN is still refused.
    let twice: String = (0..60)
        .map(|k| match k {
            10 => row(10, ""),
            11 => row(10, "") + &row(11, "24.5"),
            _ => row(k, "24.5"),
        })
        .collect();
    write(&dir.path().join("data/00002.csv"), &format!("{header}{twice}"));
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].len(), 60);
    assert!(report.notes.iter().any(|n| n.contains("read once")), "{:?}", report.notes);
    let nan_v: String =
        (0..60).map(|k| if k == 5 { "nan,-2,24.5,-2.0,3.0,50\n".into() } else { row(k, "24.5") }).collect();
    write(&dir.path().join("data/00002.csv"), &format!("{header}{nan_v}"));
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("Voltage_measured") && err.contains("nan"), "{err}");
    // A logger that froze with its temperature left empty (rows 45-59, lines 47-61): the frozen end is cut and
    // said, and the fill counts only the readings kept (the first frozen one, kept: 1 of 46, not 15 of 60).
    let frozen: String =
        (0..60).map(|k| if k >= 45 { format!("3.5,-2.0,,-2.0,3.0,{}\n", 10 * k) } else { row(k, "24.5") }).collect();
    write(&dir.path().join("data/00002.csv"), &format!("{header}{frozen}"));
    let (records, report) = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap();
    assert_eq!(records[0].len(), 46, "read to the first frozen reading");
    assert!(report.notes.iter().any(|n| n.contains("line 48") && n.contains("froze")), "{:?}", report.notes);
    let filled = report.notes.iter().find(|n| n.contains("Temperature_measured")).expect("the kept one is said");
    assert!(filled.contains("line 47") && filled.contains("1 of 46"), "{filled}");
    // None read at all: refused, said (a temperature column promises measured ones).
    let blank: String = (0..60).map(|k| row(k, "")).collect();
    write(&dir.path().join("data/00002.csv"), &format!("{header}{blank}"));
    let err = read_nasa_with(dir.path(), "B0005", None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("empty on all 60 readings"), "{err}");
    // The general CSV: the same.
    let csv = dir.path().join("cell.csv");
    let rows: String = (0..30)
        .map(|k| {
            let t = if (5..8).contains(&k) { String::new() } else { format!("{}", 25.0 + 0.1 * k as f64) };
            format!("{},{},2.0,{t}\n", 10 * k, 4.1 - 0.01 * k as f64)
        })
        .collect();
    write(&csv, &format!("time_s,voltage_v,current_a,temperature_c\n{rows}"));
    let (records, report) = read_csv(&csv, &ReadOptions::default()).unwrap();
    let t = records[0].temperature_k.as_ref().unwrap();
    assert!(t[5..8].iter().all(|x| *x == t[4]), "{t:?}");
    assert!(report.notes.iter().any(|n| n.contains("cell.csv, line 7") && n.contains("3 of 30")), "{:?}", report.notes);
}
