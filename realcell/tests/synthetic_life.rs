//! A whole cell life from a generator independent of the code under test (the doctor's test cell: the NASA
//! model written a second time and integrated by RK4 at 0.5 s), read as a cycler records it: a rest, then
//! 2 A until the voltage crosses the cut-off under load (the record stops there), sampled every 9-19 s,
//! 3 mV voltage noise. qMobile fades and Ro grows from cycle to cycle along values off any grid. Train on
//! the first 12 cycles, judge the next 12: `bcal calibrate`'s pipeline must recover capacity and the end of
//! discharge where the truth is known, and its references must rank as they should.

#[path = "../../doctor/tests/common/cell.rs"]
#[allow(dead_code)]
mod cell;

use bcal_calib::tune::{AdaptiveGrid, JointUkfGrid};
use bcal_doctor::Discharge;
use bcal_realcell::calibrate::{
    calibrate, choose_cell_ukf, extension_of, fits, model_parts, CalibrateInput, CellHistory,
};
use bcal_realcell::record::{prepare, CellRecord};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use std::ops::Div;
use std::path::PathBuf;

/// Above the model family's floor at 2 A (its surface mole fractions clip near 3.0 V): a cut-off both reach.
const CUTOFF_V: f64 = 3.1;
const CURRENT_A: f64 = 2.0;
const AMBIENT_K: f64 = 297.15;

/// The hidden degradation of cycle n (1-based): a fade that speeds up, off any grid.
fn truth(n: u32) -> (f64, f64) {
    let x = f64::from(n - 1);
    (6913.7 - 31.3 * x - 0.97 * x * x, 0.0987 + 0.00113 * x)
}

/// One discharge at 2 A and 24 C as a cycler writes it, and its true capacity down to the cut-off, Ah.
fn discharge(n: u32, rng: &mut StdRng) -> (Discharge, f64) {
    discharge_at(n, CURRENT_A, AMBIENT_K, rng)
}

/// One discharge at `load_a` from a cell at `ambient_k`, and its true capacity down to the cut-off, Ah.
fn discharge_at(n: u32, load_a: f64, ambient_k: f64, rng: &mut StdRng) -> (Discharge, f64) {
    let (q, r) = truth(n);
    discharge_of(n, cell::CellParams::base(q, r, ambient_k), load_a, rng)
}

/// Cycle n's discharge of the cell `p` at `load_a`, and its true capacity down to the cut-off, Ah.
fn discharge_of(n: u32, p: cell::CellParams, load_a: f64, rng: &mut StdRng) -> (Discharge, f64) {
    let ambient_k = p.ambient_k;
    let c = cell::Cell::new(p);
    let mut s = c.full();
    let noise = Normal::new(0.0, 0.003).unwrap();
    let h = 0.5;
    let rest_s = 30.0 + 10.0 * rng.random::<f64>();
    let (mut t, mut next) = (0.0f64, 0.0f64);
    let (mut time_s, mut voltage_v, mut current_a) = (Vec::new(), Vec::new(), Vec::new());
    let mut drawn_c = 0.0;
    loop {
        let i = if t < rest_s { 0.0 } else { load_a };
        if t >= next - 1e-9 {
            let v = c.voltage_v(&s);
            time_s.push(t);
            voltage_v.push(v + noise.sample(rng));
            current_a.push(i + 0.002 * noise.sample(rng) / 0.003);
            next += 9.0 + 10.0 * rng.random::<f64>();
            if i > 0.0 && v <= CUTOFF_V {
                break;
            }
        }
        s = c.rk4(&s, i, h);
        drawn_c += i * h;
        t += h;
        assert!(t < 20_000.0, "cycle {n} never reached the cut-off");
    }
    let _ = drawn_c;
    let d = Discharge {
        cell: "SYN".into(),
        cycle: n,
        source: PathBuf::from(format!("synthetic/{n:03}.csv")),
        ambient_k,
        time_s,
        voltage_v,
        current_a,
        temperature_k: None,
        stated_capacity_ah: None,
    };
    (d, charge_of_ah(p, load_a, CUTOFF_V))
}

/// The charge cycle n's cell truly delivers from full at `load_a` until its voltage first falls to `level_v`,
/// on the generator's fine grid, Ah.
fn true_charge_ah(n: u32, load_a: f64, ambient_k: f64, level_v: f64) -> f64 {
    let (q, r) = truth(n);
    charge_of_ah(cell::CellParams::base(q, r, ambient_k), load_a, level_v)
}

/// The charge the cell `p` delivers from full at `load_a` until its voltage first falls to `level_v`, Ah.
fn charge_of_ah(p: cell::CellParams, load_a: f64, level_v: f64) -> f64 {
    let c = cell::Cell::new(p);
    let mut s = c.full();
    let mut q_c = 0.0;
    while c.voltage_v(&s) > level_v || q_c == 0.0 {
        s = c.rk4(&s, load_a, 0.1);
        q_c += load_a * 0.1;
    }
    q_c / 3600.0
}

/// The calibration of `all[..12]` (training) against `all[12..]` with the UKF and the offline fit.
fn calibrate_life(all: &[(Discharge, f64)]) -> bcal_realcell::calibrate::Calibration {
    let input = CalibrateInput {
        cell: "SYN".into(),
        train: all[..12].iter().map(|(d, _)| d.clone()).collect(),
        judged: all[12..].iter().map(|(d, _)| d.clone()).collect(),
        cutoff_v: CUTOFF_V,
        cutoff_source: "test".into(),
        policies: Vec::new(),
        ukf: true,
        adaptive_ukf: true,
        adaptive_grid: AdaptiveGrid::quick(),
        fit: true,
        spec: None,
        ukf_grid: JointUkfGrid::real_cells_quick(),
        model: None,
        starts: Vec::new(),
        rests: None,
        unread: Vec::new(),
        noted: Vec::new(),
    };
    calibrate(&input, &mut |m| eprintln!("{m}")).expect("the synthetic life calibrates")
}

/// Issue 19, item 2: a life whose discharges run at 1, 2 and 4 A from 24 and 44 C is scored per condition,
/// and every reference, which carries parameters through the model to each discharge's own current and
/// temperature, does better than the new-cell model on every condition.
#[test]
fn a_life_under_mixed_conditions_is_scored_per_condition_and_its_references_beat_the_new_cell_model() {
    let mut rng = StdRng::seed_from_u64(20261126);
    let conditions = [(1.0, 297.15), (2.0, 317.15), (4.0, 297.15), (1.0, 317.15), (2.0, 297.15), (4.0, 317.15)];
    let all: Vec<(Discharge, f64)> = (1..=24)
        .map(|n| {
            let (i, t) = conditions[(n as usize - 1) % conditions.len()];
            discharge_at(n, i, t, &mut rng)
        })
        .collect();
    let cal = calibrate_life(&all);
    let r = &cal.report;
    let by = &r.methods["uncalibrated"].scores.by_condition;
    assert_eq!(by.len(), conditions.len(), "one score per condition: {:?}", by.keys().collect::<Vec<_>>());
    let cap = |m: &str| r.methods[m].scores.capacity_vs_data["50"].rmse;
    eprintln!(
        "mixed conditions, capacity RMSE from 50 %: previous {:.4} trend {:.4} ukf {:.4} fit {:.4} uncalibrated {:.4} Ah",
        cap("previous_cycle"),
        cap("trend"),
        cap("ukf"),
        cap("fit"),
        cap("uncalibrated")
    );
    for m in ["previous_cycle", "trend", "ukf", "fit"] {
        assert!(cap(m) < cap("uncalibrated"), "{m} {} vs uncalibrated {}", cap(m), cap("uncalibrated"));
        for (key, s) in &r.methods[m].scores.by_condition {
            let (ours, new_cell) = (s.capacity_vs_data["50"].rmse, by[key].capacity_vs_data["50"].rmse);
            assert!(ours < new_cell, "{m} at {key}: {ours} vs uncalibrated {new_cell}");
        }
    }
}

#[test]
fn a_synthetic_life_is_calibrated_and_scored_against_its_known_capacity() {
    let mut rng = StdRng::seed_from_u64(20261123);
    let mut all: Vec<(Discharge, f64)> = (1..=24).map(|n| discharge(n, &mut rng)).collect();
    // The source states each capacity to a tenth of a volt above the cut-off, as NASA's metadata states the
    // charge to 2.7 V whatever a cell's cut-off.
    for (d, _) in &mut all {
        d.stated_capacity_ah = Some(true_charge_ah(d.cycle, CURRENT_A, AMBIENT_K, CUTOFF_V + 0.1));
    }
    // A last record cut 20 s after its load came on: nothing settled for the offline fit to use. It is left
    // out, named, and the rest calibrates (it used to end the whole calibration).
    let (mut cut, cap_ah) = discharge(25, &mut rng);
    let on = cut.current_a.iter().position(|i| *i > 0.5).expect("a load");
    let keep = cut.time_s.iter().position(|t| *t > cut.time_s[on] + 20.0).unwrap_or(cut.time_s.len());
    cut.time_s.truncate(keep);
    cut.voltage_v.truncate(keep);
    cut.current_a.truncate(keep);
    all.push((cut, cap_ah));
    let cal = calibrate_life(&all);
    let r = &cal.report;
    assert_eq!(r.cycles_judged, (13..=24).collect::<Vec<u32>>());
    // What the stated capacity measures is read off the training records and said beside the capacities.
    let sc = r.records.stated_capacity.as_ref().expect("twelve training records state a capacity");
    assert!((sc.voltage_v - (CUTOFF_V + 0.1)).abs() < 1e-9, "{sc:?}");
    assert!(sc.median_gap_ah.abs() < 0.003 && sc.cutoff_median_gap_ah < -0.01, "{sc:?}");
    let md = bcal_realcell::report::render_markdown(r);
    assert!(md.contains("the stated capacity is the data's charge to about 3.2 V"), "{md}");
    assert!(md.contains("against the data's charge to the cut-off") && md.contains("target met there"), "{md}");
    assert_eq!(r.records.reaching_cutoff, 12, "every synthetic record ends at the cut-off under load");
    // Each judged discharge's references travel with the report, so that a run is scored again from it alone.
    assert_eq!(r.records.capacity_refs.len(), cal.judged.len());
    for (refs, rec) in r.records.capacity_refs.iter().zip(&cal.judged) {
        assert_eq!(
            (refs.cycle, refs.data_ah, refs.stated_ah, refs.stated_tail_ah),
            (rec.cycle, rec.data_capacity_ah, rec.stated_capacity_ah, rec.stated_tail_ah)
        );
        // Stated to 0.1 V above the cut-off: each is scored less the charge the discharges before it drew
        // below that, about what the training records' two gaps differ by.
        let tail = refs.stated_tail_ah.expect("a tail where the stated capacity is not the cut-off's");
        let trained = sc.median_gap_ah - sc.cutoff_median_gap_ah;
        assert!(tail > 0.0 && (tail - trained).abs() < 0.5 * trained, "{tail} against {trained}");
    }
    assert!(
        r.records.refused.iter().any(|why| why.contains("cycle 25") && why.contains("left out")),
        "{:?}",
        r.records.refused
    );

    // The data's own charge to the interpolated cut-off is the truth within the load-on's and the crossing's
    // share of a sample interval (the switch and the crossing fall between readings 9-19 s apart: a few
    // seconds of 2 A each), far better than integrating to the first reading below the cut-off.
    for (rec, (_, truth_ah)) in cal.judged.iter().zip(&all[12..]) {
        let data = rec.data_capacity_ah.expect("every record reaches the cut-off");
        assert!(
            (data - truth_ah).abs() < 8.0 * CURRENT_A / 3600.0,
            "cycle {}: data {data} truth {truth_ah}",
            rec.cycle
        );
    }
    let cap = |m: &str, f: &str| r.methods[m].scores.capacity_vs_data[f].rmse;
    let eod50 = |m: &str| r.methods[m].scores.eod_error_pct["50"].median;
    eprintln!(
        "capacity RMSE from 50 %: fit {:.4} ukf {:.4} adaptive ukf {:.4} previous {:.4} trend {:.4} uncalibrated {:.4} Ah; EOD at 50 %: fit {:.2} ukf {:.2} uncalibrated {:.2} %",
        cap("fit", "50"),
        cap("ukf", "50"),
        cap("adaptive_ukf", "50"),
        cap("previous_cycle", "50"),
        cap("trend", "50"),
        cap("uncalibrated", "50"),
        eod50("fit"),
        eod50("ukf"),
        eod50("uncalibrated")
    );
    // The offline fit sees the whole discharge of a cell its model describes: capacity to 10 mAh, EOD to 1 %.
    assert!(cap("fit", "100") < 0.010, "fit {}", cap("fit", "100"));
    assert!(eod50("fit") < 1.0, "fit EOD {}", eod50("fit"));
    // The streaming UKF, from half the discharge, beats carrying the last cycle over on a fading cell, and
    // every calibrated method beats the new-cell model by far.
    assert!(cap("ukf", "50") < 0.03, "ukf {}", cap("ukf", "50"));
    assert!(
        cap("ukf", "50") < cap("previous_cycle", "50"),
        "ukf {} previous {}",
        cap("ukf", "50"),
        cap("previous_cycle", "50")
    );
    for m in ["fit", "ukf", "adaptive_ukf", "previous_cycle"] {
        assert!(
            cap(m, "50") < 0.3 * cap("uncalibrated", "50"),
            "{m} {} vs uncalibrated {}",
            cap(m, "50"),
            cap("uncalibrated", "50")
        );
    }
    // Intervals are widened by the model error learned on the discharges that ended before each (the
    // validation cycles first, `realcell::interval`) and hold on the judged ones about as often as a 90 %
    // interval should (12 cycles at three shares each: a discharge missed at all three moves it by 8 points).
    let cov = r.methods["ukf"].scores.coverage_90_pct["eod"].expect("the UKF has intervals");
    assert!((75.0..=100.0).contains(&cov), "ukf EOD coverage {cov}");

    // `bcal cell-config` picks the filter a cell's policy trains on from the training cycles alone, the way
    // `bcal calibrate` picks its joint UKF (the same prior walk, learned width and factors): the policy then
    // learns on top of the very baseline it is judged against.
    let train: Vec<Discharge> = all[..12].iter().map(|(d, _)| d.clone()).collect();
    let mut records: Vec<CellRecord> = train.iter().map(|d| prepare(d, CUTOFF_V).expect("usable")).collect();
    let (causes, shared) = model_parts(None);
    let refs: Vec<&Discharge> = train.iter().collect();
    let fits = fits(&refs, &bcal_doctor::fit::FitConfig::default(), &causes, &shared).expect("fits");
    let spec = bcal_realcell::cellspec::cell_spec(&records, &fits, CUTOFF_V).0;
    let neutral = extension_of(&causes, &shared, records[0].ambient_k);
    let history = CellHistory::read(&spec.tracker, &train, &[], &mut records, &fits, &neutral, CUTOFF_V);
    let grid = JointUkfGrid::real_cells_quick().candidates();
    let (ukf, factor, _) = choose_cell_ukf(&spec.tracker, &records, &history, &grid, CUTOFF_V).expect("validation");
    let chosen = &cal.report.settings["ukf"];
    let mut ukf_json = serde_json::to_value(ukf).unwrap();
    let mut calibrate_json = chosen["settings"].clone();
    if factor.is_some() {
        // With a learned width the grid's own prior width is not used (either may be named).
        ukf_json["prior_std_z"] = serde_json::Value::Null;
        calibrate_json["prior_std_z"] = serde_json::Value::Null;
    }
    assert_eq!(ukf_json, calibrate_json);
    assert_eq!(serde_json::to_value(factor).unwrap(), chosen["prior_factor"]);
}

/// One discharge under a square wave, `peak_a` at half duty with a 20 s period, from a cell at 24 C, and the
/// charge it truly delivered until its loaded voltage first crossed the cut-off, Ah. `in_step`: read once per
/// half-period near its end, as NASA's B0025 logger reads its 4 A wave (every 10-12 s, in step with it);
/// otherwise every 10-11.6 s whatever the wave's phase, as a logger not tied to the load would.
fn square_discharge(n: u32, peak_a: f64, in_step: bool, rng: &mut StdRng) -> (Discharge, f64) {
    let (q, r) = truth(n);
    let c = cell::Cell::new(cell::CellParams::base(q, r, AMBIENT_K));
    let mut s = c.full();
    let noise = Normal::new(0.0, 0.003).unwrap();
    let (h, half_s) = (0.25, 10.0);
    let rest_s = 20.0 + 10.0 * rng.random::<f64>();
    let load_at = |t: f64| {
        let on = t >= rest_s && ((t - rest_s) / half_s).floor() as i64 % 2 == 0;
        if on {
            peak_a
        } else {
            0.0
        }
    };
    // Before the load every 10 s; then 8.5-9.75 s into each half-period.
    let mut next = 0.0f64;
    let mut half = 0u32;
    let (mut t, mut drawn_c, mut truth_c) = (0.0f64, 0.0f64, None);
    let (mut time_s, mut voltage_v, mut current_a) = (Vec::new(), Vec::new(), Vec::new());
    loop {
        let i = load_at(t);
        let v = c.voltage_v(&s);
        if i > 0.0 && v <= CUTOFF_V && truth_c.is_none() {
            truth_c = Some(drawn_c);
        }
        if t >= next - 1e-9 {
            let read_v = v + noise.sample(rng);
            time_s.push(t);
            voltage_v.push(read_v);
            current_a.push(i + 0.002 * noise.sample(rng) / 0.003);
            if i > 0.0 && read_v <= CUTOFF_V {
                break;
            }
            next = if t + 10.0 < rest_s {
                t + 10.0
            } else if !in_step {
                t + 10.0 + 1.6 * rng.random::<f64>()
            } else {
                while rest_s + f64::from(half) * half_s + 8.5 <= t + 1e-9 {
                    half += 1;
                }
                rest_s + f64::from(half) * half_s + 8.5 + 1.25 * rng.random::<f64>()
            };
        }
        s = c.rk4(&s, i, h);
        drawn_c += i * h;
        t += h;
        assert!(t < 30_000.0, "cycle {n} never reached the cut-off");
    }
    let d = Discharge {
        cell: "SQW".into(),
        cycle: n,
        source: PathBuf::from(format!("square/{n:03}.csv")),
        ambient_k: AMBIENT_K,
        time_s,
        voltage_v,
        current_a,
        temperature_k: None,
        stated_capacity_ah: None,
    };
    (d, truth_c.expect("the loop ends past the crossing") / 3600.0)
}

/// 24 discharges under a square wave of `peak_a` ([`square_discharge`], read `in_step` or not) and their
/// calibration (12 training, 12 judged): every one is read as an alternating load, reaches the cut-off and is
/// kept.
fn square_wave_life(peak_a: f64, in_step: bool) -> (Vec<(Discharge, f64)>, bcal_realcell::calibrate::Calibration) {
    let mut rng = StdRng::seed_from_u64(20261128);
    let all: Vec<(Discharge, f64)> = (1..=24).map(|n| square_discharge(n, peak_a, in_step, &mut rng)).collect();
    let fc = bcal_doctor::fit::FitConfig::default();
    assert!(all.iter().all(|(d, _)| d.alternating_load(fc.load_threshold_a, fc.step_threshold_a)));
    let cal = calibrate_life(&all);
    assert_eq!(cal.report.records.reaching_cutoff, 12, "{:?}", cal.report.records);
    assert!(cal.report.records.refused.is_empty(), "{:?}", cal.report.records.refused);
    (all, cal)
}

/// A load that switches as often as it is sampled (a square wave read once per half-period) calibrates, as
/// NASA's B0025 does, where it used to be refused: every reading is fitted with its load run over the
/// interval before it, and predictions assume the mean current over time (half the peak), not the loaded
/// readings' (the peak, which would put every end at half its time).
#[test]
fn a_square_wave_read_once_per_half_period_is_calibrated_at_its_mean_current() {
    let peak_a = 4.0;
    let (all, cal) = square_wave_life(peak_a, true);
    let r = &cal.report;
    for rec in &cal.judged {
        assert!((rec.current_a - 0.5 * peak_a).abs() < 0.05, "cycle {}: {} A", rec.cycle, rec.current_a);
    }
    let cap = |m: &str| r.methods[m].scores.capacity_vs_data["50"].rmse;
    let eod50 = |m: &str| r.methods[m].scores.eod_error_pct["50"].median;
    let truth_rmse = (cal.judged.iter().zip(&all[12..]))
        .map(|(rec, (_, t))| (rec.data_capacity_ah.unwrap() - t).powi(2))
        .sum::<f64>()
        .div(12.0)
        .sqrt();
    eprintln!(
        "square wave: capacity RMSE from 50 %: fit {:.4} ukf {:.4} previous {:.4} uncalibrated {:.4} Ah; EOD at 50 %: fit {:.2} ukf {:.2} previous {:.2} uncalibrated {:.2} %; data against truth, RMSE {:.4} Ah",
        cap("fit"),
        cap("ukf"),
        cap("previous_cycle"),
        cap("uncalibrated"),
        eod50("fit"),
        eod50("ukf"),
        eod50("previous_cycle"),
        eod50("uncalibrated"),
        truth_rmse
    );
    // The data's charge to the interpolated cut-off: within the half-period whose reading first shows the
    // crossing (10 s at 4 A, 11 mAh) of the truth.
    for (rec, (_, truth_ah)) in cal.judged.iter().zip(&all[12..]) {
        let data = rec.data_capacity_ah.expect("every record reaches the cut-off");
        assert!((data - truth_ah).abs() < 0.012, "cycle {}: data {data} truth {truth_ah}", rec.cycle);
    }
    // The joint UKF and the offline fit carry the capacity and the end as they do under a constant load
    // (the test above: 0.03 Ah, 1 %), far better than the new-cell model.
    assert!(cap("ukf") < 0.03 && cap("fit") < 0.03, "ukf {} fit {}", cap("ukf"), cap("fit"));
    assert!(cap("ukf") < 0.1 * cap("uncalibrated"), "ukf {} uncalibrated {}", cap("ukf"), cap("uncalibrated"));
    assert!(eod50("ukf") < 1.0 && eod50("fit") < 1.0, "ukf {} fit {}", eod50("ukf"), eod50("fit"));
}

/// The same square wave read at a random phase (every 10-11.6 s, not tied to the load): each reading's current
/// is then not the load over the interval before it, which is how an alternating load is read (as B0025's
/// logger, in step, allows). The calibration completes and every record is kept, and the filter still beats
/// the new-cell model, but far less well than in step: a known limit, not a target (the figures print with
/// `-- --nocapture`). A cycler whose logger runs free of its square wave would want the load taken at its
/// mean over each interval instead.
#[test]
fn a_square_wave_read_at_a_random_phase_is_calibrated_though_less_well() {
    let (_, cal) = square_wave_life(4.0, false);
    let r = &cal.report;
    let cap = |m: &str| r.methods[m].scores.capacity_vs_data["50"].rmse;
    let eod50 = |m: &str| r.methods[m].scores.eod_error_pct["50"].median;
    eprintln!(
        "square wave at a random phase: capacity RMSE from 50 %: ukf {:.4} previous {:.4} uncalibrated {:.4} Ah; \
         EOD at 50 %: ukf {:.2} previous {:.2} uncalibrated {:.2} %; partial starts flagged {:?}",
        cap("ukf"),
        cap("previous_cycle"),
        cap("uncalibrated"),
        eod50("ukf"),
        eod50("previous_cycle"),
        eod50("uncalibrated"),
        r.records.partial_start
    );
    assert!(cap("ukf") < 0.5 * cap("uncalibrated"), "ukf {} uncalibrated {}", cap("ukf"), cap("uncalibrated"));
    assert!(eod50("ukf") < 0.5 * eod50("uncalibrated"), "ukf {} uncalibrated {}", eod50("ukf"), eod50("uncalibrated"));
}

/// A life whose judged cycles 17-20 come from the cold: 4 C, the resistance multiplied by `ro_factor` and
/// the charge transfer slowed by `exchange_scale`, at `load_a` (cycles 1-16 and 21-32 at 2 A, 24 C).
fn life_with_a_cold_block(ro_factor: f64, exchange_scale: f64, load_a: f64) -> Vec<(Discharge, f64)> {
    let mut rng = StdRng::seed_from_u64(20261129);
    (1..=32)
        .map(|n| {
            if (17..=20).contains(&n) {
                let (q, r) = truth(n);
                let mut p = cell::CellParams::base(q, ro_factor * r, 277.15);
                p.exchange_scale = exchange_scale;
                discharge_of(n, p, load_a, &mut rng)
            } else {
                discharge(n, &mut rng)
            }
        })
        .collect()
}

/// The mean capacity error from half of each judged discharge of `cycles` (against the data's charge, Ah)
/// and the mean EOD error there (% of the discharge), of method `m` as delivered.
fn errors_over(
    cal: &bcal_realcell::calibrate::Calibration,
    m: &str,
    cycles: std::ops::RangeInclusive<u32>,
) -> (f64, f64) {
    let runs = &cal.runs.iter().find(|(k, _)| *k == m).expect("the method ran").1;
    let rows: Vec<(f64, f64)> = cal
        .judged
        .iter()
        .zip(runs)
        .filter(|(rec, _)| cycles.contains(&rec.cycle))
        .filter_map(|(rec, run)| {
            let k = rec.reading_at_fraction(0.5)?;
            let step = &run.steps[k.min(run.steps.len() - 1)];
            let cap = (step.capacity.value? - rec.data_capacity_ah?).abs();
            let eod = (step.eod.value? - rec.eod_s?).abs() / rec.discharge_s()? * 100.0;
            Some((cap, eod))
        })
        .collect();
    assert!(!rows.is_empty(), "{m}: nothing scored over {cycles:?}");
    let n = rows.len() as f64;
    (rows.iter().map(|x| x.0).sum::<f64>() / n, rows.iter().map(|x| x.1).sum::<f64>() / n)
}

/// NASA's cold cells (B0041-B0056, 4 C) hold runs "where the capacity was very low" (B0043: 46 in a row at a
/// twentieth of the cell's capacity): a load the cold cell cannot carry for long. A life with a block of such
/// runs among its judged discharges calibrates through, whether they last minutes (calibrated and scored: a
/// quarter of the capacity, 11-12 min at 3 A) or under a minute (refused by name: nothing settled to fit,
/// or the cut-off passed at the first loaded reading), and the discharges after the block are carried as well
/// as those before it: the joint UKF within 15 mAh and 1 % of the end from half of each.
#[test]
fn a_block_of_runs_that_end_early_does_not_derail_the_discharges_after_it() {
    // Minutes: every run judged and scored.
    let all = life_with_a_cold_block(2.0, 0.2, 3.0);
    let short: Vec<f64> = all[16..20].iter().map(|x| x.1).collect();
    assert!(short.iter().all(|q| (0.3..0.8).contains(q)), "a quarter of the capacity: {short:?} Ah");
    let cal = calibrate_life(&all);
    let r = &cal.report;
    assert!(r.records.refused.is_empty(), "{:?}", r.records.refused);
    assert!((17..=20).all(|c| cal.judged.iter().any(|rec| rec.cycle == c && rec.eod_s.is_some())));
    let (before, after) = (errors_over(&cal, "ukf", 13..=16), errors_over(&cal, "ukf", 25..=32));
    eprintln!("minutes: joint UKF before the block {before:?}, after it {after:?}");
    assert!(after.0 < 0.015 && after.1 < 1.0, "after the block {after:?} (before {before:?})");

    // Under a minute: refused, each named, the rest calibrated.
    let all = life_with_a_cold_block(3.0, 0.05, 4.0);
    let cal = calibrate_life(&all);
    let r = &cal.report;
    for c in 17..=20 {
        assert!(
            r.records.refused.iter().any(|why| why.contains(&format!("cycle {c}:"))),
            "cycle {c}: {:?}",
            r.records.refused
        );
    }
    assert_eq!(r.cycles_judged, [13, 14, 15, 16].into_iter().chain(21..=32).collect::<Vec<u32>>());
    let after = errors_over(&cal, "ukf", 25..=32);
    eprintln!("under a minute: joint UKF after the block {after:?}");
    assert!(after.0 < 0.015 && after.1 < 1.0, "after the block {after:?}");
}
