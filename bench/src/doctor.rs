//! The doctor's cost: one diagnosis with every candidate cause (what `bcal diagnose` runs) on a cell the
//! doctor's own simulator draws, timed and divided per record and cause. The cell is NASA-like (2 A
//! constant-current discharges sampled every 10 s, qMobile fading and Ro growing by record) and hides an OCV
//! deviation, so the candidates have something to find and the extended model grows as on a real cell.

use bcal_common::battery::{BatteryParams, Degradation};
use bcal_doctor::sim::{simulate_voltage, Drive, ExtParams};
use bcal_doctor::{diagnose, Cause, DiagnoseConfig, Discharge};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// One timed diagnosis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DoctorRow {
    pub records: usize,
    pub causes: usize,
    /// Samples per record.
    pub samples: usize,
    /// Simulator step, s (`bcal diagnose`'s default).
    pub dt_s: f64,
    pub seconds: f64,
    pub seconds_per_record_and_cause: f64,
    /// What the diagnosis named (a check that it ran the whole way).
    pub cause: String,
}

/// A 2 A discharge of record `k`: 30 s rest, load until 2.9 V, sampled every 10 s.
fn record(k: usize, ocv: &ExtParams) -> anyhow::Result<Discharge> {
    let base = BatteryParams::default();
    let d = Degradation { q_mobile_c: 7000.0 * (1.0 - 0.01 * k as f64), r_o_ohm: 0.12 * (1.0 + 0.02 * k as f64) };
    let time_s: Vec<f64> = (0..400).map(|j| 10.0 * j as f64).collect();
    let current_a: Vec<f64> = time_s.iter().map(|t| if *t < 30.0 { 0.0 } else { 2.0 }).collect();
    let mut voltage_v = vec![0.0; time_s.len()];
    let drive =
        Drive { time_s: &time_s, current_a: &current_a, temperature_k: None, ambient_k: 297.15, alternating: false };
    simulate_voltage(&base, d, ocv, drive, 1.0, &mut voltage_v)?;
    // End the record at its first sample below 2.8 V, as a cycler stops at its cut-off.
    let end = voltage_v.iter().position(|v| *v < 2.8).map_or(voltage_v.len(), |k| k + 1);
    Ok(Discharge {
        cell: "bench".into(),
        cycle: k as u32 + 1,
        source: format!("bench/{k}.csv").into(),
        ambient_k: 297.15,
        time_s: time_s[..end].to_vec(),
        voltage_v: voltage_v[..end].to_vec(),
        current_a: current_a[..end].to_vec(),
        temperature_k: None,
        stated_capacity_ah: None,
    })
}

/// Diagnoses `records` records (a third fitted, the rest judged) with every cause at `bcal diagnose`'s
/// defaults and times it.
pub fn measure(records: usize) -> anyhow::Result<DoctorRow> {
    let ocv = ExtParams { ocv_legendre_v: [0.02, -0.015, 0.01], ..ExtParams::default() };
    let all: Vec<Discharge> = (0..records.max(2)).map(|k| record(k, &ocv)).collect::<anyhow::Result<_>>()?;
    let split = (all.len() / 3).max(1);
    let mut cfg = DiagnoseConfig { cutoff_v: Some(2.8), ..DiagnoseConfig::default() };
    cfg.fit.dt_max_s = 2.0;
    let started = Instant::now();
    let diag = diagnose(&cfg, &all[..split], &all[split..])?;
    let seconds = started.elapsed().as_secs_f64();
    Ok(DoctorRow {
        records: all.len(),
        causes: Cause::ALL.len(),
        samples: all.iter().map(Discharge::len).sum::<usize>() / all.len(),
        dt_s: cfg.fit.dt_max_s,
        seconds,
        seconds_per_record_and_cause: seconds / (all.len() * Cause::ALL.len()) as f64,
        cause: diag.cause.to_string(),
    })
}
