//! Shared harness of the doctor's integration tests: a synthetic "measured" data generator with one hidden
//! effect, realistic sensor noise, irregular sampling, CC and variable loads and aged parameters, written
//! through the generic CSV so every test also exercises the reader.
//!
//! The generator steps [`ExtendedCell`] (the doctor's own simulator with the hidden extension switched on)
//! at 1 s; the thermal truth evolves a thermal state whose temperature becomes the measured column.

#![allow(dead_code)]

use bcal_common::battery::{BatteryParams, Degradation};
use bcal_doctor::read::read_generic;
use bcal_doctor::sim::{ExtParams, ExtendedCell};
use bcal_doctor::{DiagnoseConfig, Discharge};
use rand::rngs::StdRng;
use rand::Rng;
use rand_distr::{Distribution, Normal};
use std::io::Write;
use std::path::Path;

/// Ambient of every synthetic record, deg C.
pub const AMBIENT_C: f64 = 24.0;
/// Cut-off voltage of the synthetic protocol, V.
pub const CUTOFF_V: f64 = 3.0;
/// Rest before the load and relaxation after the cut-off, s.
pub const REST_S: u32 = 30;
pub const RELAX_S: u32 = 300;
/// Sensor noise: voltage (V), current (A), temperature (K), one standard deviation each.
pub const NOISE_V: f64 = 0.003;
pub const NOISE_A: f64 = 0.005;
pub const NOISE_K: f64 = 0.1;

/// The hidden truth of one synthetic cell.
#[derive(Clone, Debug)]
pub struct Truth {
    pub ext: ExtParams,
    /// Lumped heat capacity, J/K, for a thermal truth (the thermal state runs when `ext.temperature_driven`).
    pub mc_j_per_k: f64,
    /// New-cell qMobile, C, and Ro, ohm; each cycle ages them.
    pub q_mobile_c: f64,
    pub r_o_ohm: f64,
}

impl Truth {
    /// A cell with random aged parameters and no hidden effect.
    pub fn aged(rng: &mut StdRng) -> Self {
        Self {
            ext: ExtParams::default(),
            mc_j_per_k: BatteryParams::default().mc_j_per_k,
            q_mobile_c: rng.random_range(5400.0..7200.0),
            r_o_ohm: rng.random_range(0.10..0.17),
        }
    }

    /// Degradation at a cycle: 1.5 % capacity loss and 3 % resistance growth per cycle.
    pub fn degradation(&self, cycle: u32) -> Degradation {
        let k = f64::from(cycle - 1);
        Degradation { q_mobile_c: self.q_mobile_c * (1.0 - 0.015 * k), r_o_ohm: self.r_o_ohm * (1.0 + 0.03 * k) }
    }
}

/// A load: constant current, or random segments (0.5-3 A, 120-480 s, sometimes a rest).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LoadKind {
    Cc,
    Variable,
}

/// Current (sensor reading, A) of a load at `t_s` since load-on.
struct Load {
    segments: Vec<(f64, f64)>,
}

impl Load {
    fn new(kind: LoadKind, rng: &mut StdRng) -> Self {
        match kind {
            LoadKind::Cc => Self { segments: vec![(0.0, rng.random_range(1.6..2.4))] },
            LoadKind::Variable => {
                let mut segments = Vec::new();
                let mut t = 0.0;
                while t < 20_000.0 {
                    let current_a =
                        if !segments.is_empty() && rng.random_bool(0.15) { 0.0 } else { rng.random_range(0.5..3.0) };
                    segments.push((t, current_a));
                    t += rng.random_range(120.0..480.0);
                }
                Self { segments }
            }
        }
    }
    fn at(&self, t_s: f64) -> f64 {
        self.segments.iter().rev().find(|(s, _)| *s <= t_s).map_or(0.0, |s| s.1)
    }
}

/// One synthetic record: rest, load until the cut-off, relaxation; samples every 5-20 s with noise.
pub fn record(truth: &Truth, cycle: u32, kind: LoadKind, rng: &mut StdRng) -> Vec<(f64, f64, f64, f64)> {
    let base = BatteryParams { mc_j_per_k: truth.mc_j_per_k, ..BatteryParams::default() };
    let ambient_k = AMBIENT_C + 273.15;
    let mut cell =
        ExtendedCell::new(&base, truth.degradation(cycle), truth.ext, ambient_k, false).expect("valid truth");
    let load = Load::new(kind, rng);
    let (nv, ni, nt) =
        (Normal::new(0.0, NOISE_V).unwrap(), Normal::new(0.0, NOISE_A).unwrap(), Normal::new(0.0, NOISE_K).unwrap());
    let mut rows = Vec::new();
    let mut next_sample = 0u32;
    let mut cut_at: Option<u32> = None;
    let mut t = 0u32;
    loop {
        let current_a = match cut_at {
            Some(_) => 0.0,
            None if t < REST_S => 0.0,
            None => load.at(f64::from(t - REST_S)),
        };
        if t == next_sample {
            let v = cell.voltage_v();
            rows.push((
                f64::from(t),
                v + nv.sample(rng),
                current_a + ni.sample(rng),
                cell.temperature_k() - 273.15 + nt.sample(rng),
            ));
            next_sample += rng.random_range(5..=20);
        }
        if cut_at.is_none() && t > REST_S && cell.voltage_v() < CUTOFF_V {
            cut_at = Some(t);
        }
        if cut_at.is_some_and(|c| t >= c + RELAX_S) || t > 30_000 {
            break;
        }
        cell.step(current_a, 1.0);
        t += 1;
    }
    rows
}

/// Writes cycles as a generic CSV (`time_s,voltage_v,current_a,temperature_c,cycle`) and reads it back.
pub fn write_and_read(dir: &Path, truth: &Truth, kinds: &[LoadKind], rng: &mut StdRng) -> Vec<Discharge> {
    let path = dir.join("cell.csv");
    let mut f = std::fs::File::create(&path).unwrap();
    writeln!(f, "time_s,voltage_v,current_a,temperature_c,cycle").unwrap();
    for (k, kind) in kinds.iter().enumerate() {
        let cycle = k as u32 + 1;
        for (t, v, i, tc) in record(truth, cycle, *kind, rng) {
            writeln!(f, "{t},{v:.6},{i:.6},{tc:.4},{cycle}").unwrap();
        }
    }
    drop(f);
    read_generic(&path, Some(AMBIENT_C)).unwrap()
}

/// The load plan of every hidden-effect test: three training cycles, two held-out.
pub const PLAN: [LoadKind; 5] =
    [LoadKind::Cc, LoadKind::Variable, LoadKind::Variable, LoadKind::Variable, LoadKind::Cc];
pub const N_TRAIN: usize = 3;

/// The doctor's settings in the tests: a 2 s simulator step keeps the suite quick.
pub fn config() -> DiagnoseConfig {
    let mut cfg = DiagnoseConfig::default();
    cfg.fit.dt_max_s = 2.0;
    cfg
}
