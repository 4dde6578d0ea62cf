//! A live stream over many discharges of a real cell (`bcal calibrate --follow`, `bcal.Calibrator`): B0005's
//! discharges 41-46 from `../shared` (skipped, with a line on stderr, where the folder is absent), joined
//! end to end at their recorded start times, the charges between them unseen.

use bcal_calib::stream::{build, resolve, CalibratorKind, Estimate, Reading, Stream};
use bcal_doctor::read::read_nasa;
use std::collections::BTreeMap;
use std::path::PathBuf;

fn shared() -> Option<PathBuf> {
    let root = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data/nasa-pcoe"));
    if root.join("metadata.csv").is_file() {
        Some(root)
    } else {
        eprintln!("skipped: no NASA data at {}", root.display());
        None
    }
}

/// The last estimate of each discharge, by the stream's own count.
fn ends(estimates: &[Estimate]) -> Vec<f64> {
    let mut by: BTreeMap<u32, f64> = BTreeMap::new();
    for e in estimates {
        by.insert(e.discharge, e.q_mobile);
    }
    by.into_values().collect()
}

/// Each discharge starts a new calibrator from what the last one told and stays on the cell (B0005's
/// capacity moves by 1.5 % over these six discharges); one joint UKF run on across the gaps reads every
/// recharge as its own misfit and ends each later discharge far off (at the top of qMobile's range).
#[test]
fn a_real_cells_discharges_joined_end_to_end_each_start_from_the_last_and_stay_on_the_cell() {
    let Some(root) = shared() else { return };
    let (records, report) = read_nasa(&root, "B0005", Some(&(41..=46))).unwrap();
    let start_of: BTreeMap<u32, f64> = report.starts.iter().map(|s| (s.cycle, s.start_s)).collect();
    let mut readings = Vec::new();
    for d in &records {
        let t0_s = start_of[&d.cycle];
        for k in 0..d.time_s.len() {
            readings.push(Reading {
                time_s: t0_s + d.time_s[k],
                voltage_v: d.voltage_v[k],
                current_a: d.current_a[k],
                temperature_c: d.temperature_k.as_ref().map(|t| t[k] - 273.15),
            });
        }
    }
    assert_eq!(records.len(), 6);
    let setup = resolve(CalibratorKind::Ukf, None, None, None).unwrap();
    let mut stream = Stream::of(&setup, None, None).unwrap();
    let mut plain = Stream::new(build(&setup, None).unwrap(), &setup.spec.tracker, None);
    let (mut ours, mut theirs) = (Vec::new(), Vec::new());
    for r in &readings {
        ours.push(stream.step(r).unwrap());
        theirs.push(plain.step(r).unwrap());
    }
    assert_eq!((stream.discharges(), plain.discharges()), (6, 1));
    let (ours, theirs) = (ends(&ours), ends(&theirs));
    assert_eq!(theirs.len(), 1);
    let last_plain =
        plain.step(&Reading { time_s: readings.last().unwrap().time_s + 1.0, ..*readings.last().unwrap() });
    let first = ours[0];
    for (k, q) in ours.iter().enumerate() {
        assert!((q / first - 1.0).abs() < 0.05, "discharge {}: {q} C against the first's {first} C", 41 + k);
    }
    let off = last_plain.unwrap().q_mobile;
    assert!((off / first - 1.0).abs() > 0.1, "one filter across the gaps: {off} C against {first} C");
}
