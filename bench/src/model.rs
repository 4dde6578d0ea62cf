//! The battery model's speed on one core: one Euler step at 8 W (the paper's hot loop; the same loop as
//! `common/benches/battery.rs`) and a whole discharge from a new cell to VEOD.

use anyhow::Context;
use bcal_common::battery::{BatteryModel, Degradation, Load, LoadProfile};
use bcal_eval::evaluate::time_per_call_us;
use serde::{Deserialize, Serialize};
use std::hint::black_box;

/// Steps after which the step loop restarts from the new cell, so every timed step is mid-discharge
/// (a discharge at 8 W lasts 3102 steps).
const RESTART_EVERY: u32 = 3000;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelReport {
    /// One `BatteryModel::step` (power input 8 W, dt 1 s), ns: median of the repeats.
    pub step_ns: f64,
    /// 1e9 / step_ns.
    pub steps_per_s: f64,
    /// Steps timed (after a tenth as many warm-up steps).
    pub steps_timed: u64,
    /// One whole discharge at 8 W from the new cell to the first step below VEOD, us.
    pub discharge_us: f64,
    /// Steps of that discharge.
    pub discharge_steps: u64,
    /// discharge_steps / discharge time.
    pub discharge_steps_per_s: f64,
    /// Discharges timed.
    pub discharges_timed: u64,
}

/// Times `steps` model steps and `discharges` whole discharges on the calling thread.
pub fn measure(model: &BatteryModel, steps: usize, discharges: usize) -> anyhow::Result<ModelReport> {
    let d = Degradation::default();
    let x0 = model.initial_state(&d);
    let mut x = x0;
    let mut n = 0u32;
    let step_us = time_per_call_us(steps, |_| {
        let (next, _) = model.step(black_box(&x), Load::PowerW(8.0), 1.0, black_box(&d));
        n += 1;
        x = if n.is_multiple_of(RESTART_EVERY) { x0 } else { next };
        black_box(&x);
    });
    let profile = LoadProfile::Constant(Load::PowerW(8.0));
    let discharge_steps = model
        .simulate_until_eod(&x0, &d, &profile, 1.0, 100_000, |_| {})
        .context("the reference discharge at 8 W did not reach VEOD")?
        .rows as u64;
    let discharge_us = time_per_call_us(discharges, |_| {
        let _ = black_box(model.simulate_until_eod(&x0, black_box(&d), &profile, 1.0, 100_000, |r| {
            black_box(r.voltage_v);
        }));
    });
    Ok(ModelReport {
        step_ns: step_us * 1e3,
        steps_per_s: 1e6 / step_us,
        steps_timed: steps as u64,
        discharge_us,
        discharge_steps,
        discharge_steps_per_s: discharge_steps as f64 * 1e6 / discharge_us,
        discharges_timed: discharges as u64,
    })
}
