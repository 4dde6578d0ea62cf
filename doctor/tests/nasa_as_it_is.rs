//! The NASA PCoE cells in `../shared` read as they are (skipped, with a line on stderr, where the folder is
//! absent): each cell's documented cut-off comes from its experiment description; B0006's 25 records (and
//! B0029's 4) that end under load below it are complete, no record of the six cells is truncated; `Auto`
//! finds NASA's negative discharge current in every record and reads exactly what the fixed-sign reader
//! reads; and only B0055's first discharge, which rests at 3.84 V before its load, starts partly discharged.

use bcal_common::battery::BatteryParams;
use bcal_doctor::read::{nasa_cutoff_v, read_nasa, read_nasa_with, ReadOptions};
use bcal_doctor::record::PARTIAL_START_DROP_V;
use std::path::PathBuf;

/// The six cells present in `../shared`, with how many of their records end under load at or below the
/// documented cut-off.
const CELLS: [(&str, f64, usize); 6] =
    [("B0005", 2.7, 0), ("B0006", 2.5, 25), ("B0018", 2.5, 0), ("B0025", 2.0, 0), ("B0029", 2.0, 4), ("B0055", 2.5, 0)];

fn shared() -> Option<PathBuf> {
    let root = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data/nasa-pcoe"));
    if root.join("metadata.csv").is_file() {
        Some(root)
    } else {
        eprintln!("skipped: no NASA data at {}", root.display());
        None
    }
}

#[test]
fn documented_cutoffs_are_read_from_the_experiment_descriptions() {
    let Some(root) = shared() else { return };
    for (cell, want) in [
        ("B0005", 2.7),
        ("B0006", 2.5),
        ("B0007", 2.2),
        ("B0018", 2.5),
        ("B0025", 2.0),
        ("B0029", 2.0),
        ("B0033", 2.0),
        ("B0034", 2.2),
        ("B0036", 2.7),
        ("B0047", 2.5),
        ("B0055", 2.5),
        ("B0056", 2.7),
    ] {
        assert_eq!(nasa_cutoff_v(&root, cell), Some(want), "{cell}");
    }
    assert_eq!(nasa_cutoff_v(&root, "B0099"), None);
    assert_eq!(nasa_cutoff_v(&root, "cell"), None);
    assert_eq!(nasa_cutoff_v(&root.join("nowhere"), "B0005"), None);
}

#[test]
fn the_cells_read_as_they_are_complete_at_their_cutoff_with_the_sign_found_from_the_data() {
    let Some(root) = shared() else { return };
    let base = BatteryParams::default();
    let mut partial = Vec::new();
    for (cell, cutoff_v, at_cutoff) in CELLS {
        assert_eq!(nasa_cutoff_v(&root, cell), Some(cutoff_v));
        let (fixed, _) = read_nasa(&root, cell, None).unwrap();
        let (auto, report) = read_nasa_with(&root, cell, None, &ReadOptions::default()).unwrap();
        assert!(report.skipped.is_empty() && report.notes.is_empty(), "{cell}: {:?}", report.summary());
        assert_eq!(auto.len(), fixed.len(), "{cell}");
        assert!(report.signs.iter().all(|s| !s.discharge_positive && s.from_data), "{cell}");
        let least = report.signs.iter().filter_map(|s| s.evidence.share_for(false)).fold(1.0, f64::min);
        for (a, f) in auto.iter().zip(&fixed) {
            assert_eq!(
                (a.cycle, &a.voltage_v, &a.current_a, &a.time_s),
                (f.cycle, &f.voltage_v, &f.current_a, &f.time_s)
            );
        }
        let windows: Vec<_> = auto.iter().map(|d| d.windows_with_cutoff(0.05, 2.9, Some(cutoff_v)).unwrap()).collect();
        assert_eq!(windows.iter().filter(|w| w.ended_at_cutoff).count(), at_cutoff, "{cell}");
        assert_eq!(windows.iter().filter(|w| w.truncated).count(), 0, "{cell}");
        // How far below the full cell's open-circuit voltage each record rests before its load.
        let mut drops = Vec::new();
        for d in &auto {
            let s = d.start_state(&base, 0.05, PARTIAL_START_DROP_V).unwrap().unwrap();
            drops.push(s.full_ocv_v - s.rest_v);
            if s.partial {
                partial.push((cell, d.cycle));
            }
        }
        let lo = drops.iter().copied().fold(f64::INFINITY, f64::min);
        let mut sorted = drops.clone();
        sorted.sort_by(f64::total_cmp);
        eprintln!(
            "{cell}: {} records, sign from the data (least share {:.3}), {at_cutoff} ended at the {cutoff_v} V \
             cut-off; rest below the full-cell OCV {:.0} to {:.0} mV (second largest {:.0} mV)",
            auto.len(),
            least,
            1e3 * lo,
            1e3 * sorted[sorted.len() - 1],
            1e3 * sorted[sorted.len() - 2],
        );
    }
    assert_eq!(partial, vec![("B0055", 1)]);
}

/// Every discharge of the three 2 A cells has its start from `metadata.csv`, and their capacity jumps after
/// the pauses of the test schedule: the lifetime diagnosis, fitted on cycles 1-40 and judged on 41 onwards,
/// names recovery after rest on each with a held-out capacity gain one ahead of at least 30 % (measured: 36,
/// 34, 53 %), a long rest adding 0.05-0.15 Ah with a time constant of 5-50 h of rest.
#[test]
fn recovery_after_rest_is_named_on_the_2_a_cells() {
    use bcal_doctor::lifetime::{assess, LifetimeConfig};
    let Some(root) = shared() else { return };
    for cell in ["B0005", "B0006", "B0018"] {
        let (records, report) = read_nasa_with(&root, cell, None, &ReadOptions::default()).unwrap();
        assert_eq!(report.starts.len(), records.len(), "{cell}: every record has its start");
        let cfg = LifetimeConfig { cutoff_v: nasa_cutoff_v(&root, cell), ..LifetimeConfig::default() };
        let last = records.iter().map(|d| d.cycle).max().unwrap();
        let life = assess(&cfg, &records, &report.starts, &(1..=40), &(41..=last), None).unwrap();
        assert!(life.schedule, "{cell}: {:?}", life.notes);
        // B0005's pause before cycle 20 is its longest: 310 h.
        let longest_h = life.longest_rest_s.unwrap() / 3600.0;
        assert!(longest_h > 200.0, "{cell}: longest rest {longest_h:.0} h");
        assert!(life.recovery, "{cell}: {}", life.verdict);
        assert!(life.gain_pct.unwrap() >= 30.0, "{cell}: {}", life.verdict);
        let (a, tau_h) = (life.amplitude_ah.unwrap(), life.tau_rest_h.unwrap());
        assert!((0.05..0.15).contains(&a) && (5.0..50.0).contains(&tau_h), "{cell}: A {a:.3} Ah, tau {tau_h:.1} h");
    }
}

/// The fit window's floor under a load-on voltage (`FLOOR_BELOW_LOAD_ON_V`, for cells pulled under 2.9 V at
/// once) moves no window of the six cells: each ends at the first loaded sample below 2.9 V, as before it.
#[test]
fn the_load_on_floor_moves_no_window_of_the_six_cells() {
    let Some(root) = shared() else { return };
    for (cell, cutoff_v, _) in CELLS {
        let (records, _) = read_nasa(&root, cell, None).unwrap();
        for d in &records {
            let Some(w) = d.windows_with_cutoff(0.05, 2.9, Some(cutoff_v)) else { continue };
            let fixed = (w.load_on..w.load_end).find(|&k| d.voltage_v[k] < 2.9).unwrap_or(w.load_end);
            assert_eq!(w.fit_end, fixed, "{cell} cycle {}", d.cycle);
        }
    }
}
