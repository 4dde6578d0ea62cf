//! Shared harness of the doctor's integration tests: an independent synthetic-cell generator that makes
//! "measured" discharges with one hidden effect, and writes them through the generic CSV so every test
//! also exercises the reader.
//!
//! The generator ([`cell`]) is the model written a second time and integrated by RK4 at 0.1 s, never the
//! doctor's Euler simulator; each hidden effect is its own code in its own parametrisation, and every
//! truth is drawn from a continuous range (no candidate's grid, start or bound). A cell is six discharges
//! at 1-3 A (constant current, or piecewise with short rests), each a rest, the load down to the 3.0 V
//! cut-off and a relaxation, sampled at irregular 5-20 s with Gaussian sensor noise (3 mV; 5-10 mA and
//! 0.1-0.5 K drawn per cell). Capacity and resistance age from cycle to cycle; the two ageing effects
//! (`electrode_balance`, `charge_transfer`) drift per cycle on top. [`life`] makes whole lives (40
//! constant-current discharges on a test schedule) for the two lifetime truths, [`LIFE_CAUSES`].

#![allow(dead_code)]

pub mod cell;
pub mod life;

use bcal_doctor::read::read_generic;
use bcal_doctor::{DiagnoseConfig, Discharge};
use cell::{Cell, CellParams, Heat, OcvDeviation};
use rand::rngs::StdRng;
use rand::Rng;
use rand_distr::{Distribution, Normal};
use std::io::Write;
use std::path::Path;

/// Cut-off voltage of the synthetic protocol, V.
pub const CUTOFF_V: f64 = 3.0;
/// The generator's integration step, s.
pub const STEP_S: f64 = 0.1;
/// Voltage-sensor noise, V (one standard deviation).
pub const NOISE_V: f64 = 0.003;
/// Discharges per synthetic cell.
pub const CYCLES: usize = 6;
/// Every truth a test can hide, `none` first: the rows of the soak run's confusion matrix.
pub const CAUSES: [&str; 9] = [
    "none",
    "thermal",
    "ocv",
    "diffusion",
    "extra_polarization",
    "voltage_offset",
    "current_gain",
    "electrode_balance",
    "charge_transfer",
];

/// The hidden effect of one synthetic cell, in the generator's own terms.
#[derive(Clone, Debug, PartialEq)]
pub enum Effect {
    None,
    /// Self-heating with Arrhenius resistance and kinetics; the measured temperature column shows it.
    Thermal(Heat),
    /// The positive electrode's equilibrium potential deviates from its Redlich-Kister curve.
    Ocv(OcvDeviation),
    /// Bulk-surface diffusion time, s (the model's is 7e6 s).
    Diffusion {
        time_s: f64,
    },
    /// A second RC polarisation.
    ExtraPolarization {
        r_ohm: f64,
        tau_s: f64,
    },
    /// The voltage sensor reads this much high, V.
    VoltageOffset {
        v: f64,
    },
    /// The current sensor reads `gain` times the true current.
    CurrentGain {
        gain: f64,
    },
    /// Stoichiometry at full charge drifts per cycle: the positive electrode starts more lithiated by
    /// `xp[c]`, the negative by `xn[c]` (negative: lithium lost), at an unchanged electrode capacity.
    ElectrodeBalance {
        xp: [f64; CYCLES],
        xn: [f64; CYCLES],
    },
    /// Both exchange currents scaled by `scale[c]` on cycle c (slowing charge transfer).
    ChargeTransfer {
        scale: [f64; CYCLES],
    },
}

/// The hidden truth of one synthetic cell.
#[derive(Clone, Debug, PartialEq)]
pub struct Truth {
    /// Which cause the effect stands for (a [`CAUSES`] name).
    pub cause: &'static str,
    pub effect: Effect,
    pub ambient_c: f64,
    /// New-cell mobile charge, C, and resistance, ohm, and how they age per cycle (fractions).
    pub q_mobile_c: f64,
    pub r_o_ohm: f64,
    pub q_fade_per_cycle: f64,
    pub r_growth_per_cycle: f64,
    /// Current and temperature sensor noise (one standard deviation), A and K.
    pub noise_a: f64,
    pub noise_k: f64,
}

fn sign(rng: &mut StdRng) -> f64 {
    if rng.random_bool(0.5) {
        1.0
    } else {
        -1.0
    }
}

fn log_uniform(rng: &mut StdRng, lo: f64, hi: f64) -> f64 {
    rng.random_range(lo.ln()..hi.ln()).exp()
}

/// A per-cycle drift from about `start` to about `end` over the cycles, with cycle-to-cycle jitter.
fn drift(rng: &mut StdRng, start: f64, end: f64, jitter: f64) -> [f64; CYCLES] {
    let n = Normal::new(0.0, jitter).unwrap();
    std::array::from_fn(|c| start + (end - start) * c as f64 / (CYCLES - 1) as f64 + n.sample(rng))
}

impl Truth {
    /// A cell with random ageing and no hidden effect.
    pub fn aged(rng: &mut StdRng) -> Self {
        Self {
            cause: "none",
            effect: Effect::None,
            ambient_c: rng.random_range(20.0..30.0),
            q_mobile_c: rng.random_range(5400.0..7200.0),
            r_o_ohm: rng.random_range(0.10..0.17),
            q_fade_per_cycle: rng.random_range(0.008..0.02),
            r_growth_per_cycle: rng.random_range(0.01..0.04),
            noise_a: rng.random_range(0.005..0.010),
            noise_k: rng.random_range(0.1..0.5),
        }
    }

    /// A cell hiding `cause` (a [`CAUSES`] name), every value drawn from a continuous physical range.
    pub fn draw(cause: &str, rng: &mut StdRng) -> Self {
        let mut t = Self::aged(rng);
        t.effect = match cause {
            "none" => Effect::None,
            // Self-heating of roughly 5-20 K at 1-3 A.
            "thermal" => Effect::Thermal(Heat {
                capacity_j_per_k: rng.random_range(30.0..45.0),
                exchange_s: rng.random_range(500.0..1200.0),
                ro_activation_k: rng.random_range(1500.0..4000.0),
                kinetics_activation_k: rng.random_range(500.0..3000.0),
            }),
            // A 12-30 mV wave of 0.3-0.6 periods over the positive electrode's window.
            "ocv" => Effect::Ocv(OcvDeviation {
                amplitude_v: rng.random_range(0.012..0.03),
                periods: rng.random_range(0.3..0.6),
                phase: rng.random_range(0.0..1.0),
            }),
            // Solid diffusion 2.5-4 times slower or faster than the model's.
            "diffusion" => {
                let factor = log_uniform(rng, 2.5, 4.0);
                Effect::Diffusion { time_s: cell::nasa::T_DIFFUSION_S * factor.powf(sign(rng)) }
            }
            // A second polarisation of 30-80 mohm and 100-600 s.
            "extra_polarization" => {
                Effect::ExtraPolarization { r_ohm: rng.random_range(0.03..0.08), tau_s: log_uniform(rng, 100.0, 600.0) }
            }
            // A voltage-sensor bias of 15-30 mV either way.
            "voltage_offset" => Effect::VoltageOffset { v: sign(rng) * rng.random_range(0.015..0.03) },
            // A current-sensor gain off by 4-10 % either way.
            "current_gain" => Effect::CurrentGain { gain: 1.0 + sign(rng) * rng.random_range(0.04..0.10) },
            // The window drifts along both electrodes (loss of lithium and of active material), ending
            // 0.05-0.10 further into the positive's curve and 0.05-0.12 lower on the negative's.
            "electrode_balance" => {
                let (p0, p1) = (rng.random_range(-0.01..0.02), rng.random_range(0.05..0.10));
                let (n0, n1) = (rng.random_range(-0.03..0.0), rng.random_range(-0.12..-0.05));
                Effect::ElectrodeBalance { xp: drift(rng, p0, p1, 0.004), xn: drift(rng, n0, n1, 0.004) }
            }
            // Exchange currents falling from 0.3-0.8 to 0.04-0.12 of the model's over the six cycles.
            "charge_transfer" => {
                let (s0, s1) = (rng.random_range(0.3f64..0.8).ln(), rng.random_range(0.04f64..0.12).ln());
                Effect::ChargeTransfer { scale: drift(rng, s0, s1, 0.08).map(f64::exp) }
            }
            other => panic!("unknown cause {other}"),
        };
        t.cause = CAUSES.iter().copied().find(|c| *c == cause).expect("a known cause");
        t
    }

    /// Mobile charge (C) and resistance (ohm) at a cycle (1-based).
    pub fn degradation(&self, cycle: u32) -> (f64, f64) {
        let k = f64::from(cycle - 1);
        (self.q_mobile_c * (1.0 - self.q_fade_per_cycle * k), self.r_o_ohm * (1.0 + self.r_growth_per_cycle * k))
    }

    /// The generator's cell on a cycle (1-based).
    pub fn cell(&self, cycle: u32) -> CellParams {
        let (q, r) = self.degradation(cycle);
        let mut p = CellParams::base(q, r, self.ambient_c + 273.15);
        let c = cycle as usize - 1;
        match &self.effect {
            Effect::Thermal(h) => p.heat = Some(*h),
            Effect::Ocv(dev) => p.ocv_deviation = Some(*dev),
            Effect::Diffusion { time_s } => p.diffusion_s = *time_s,
            Effect::ExtraPolarization { r_ohm, tau_s } => p.rc = Some((*r_ohm, *tau_s)),
            Effect::ElectrodeBalance { xp, xn } => {
                p.xp_full += xp[c];
                p.xn_full += xn[c];
            }
            Effect::ChargeTransfer { scale } => p.exchange_scale = scale[c],
            Effect::None | Effect::VoltageOffset { .. } | Effect::CurrentGain { .. } => {}
        }
        p
    }

    /// What the sensors add: voltage offset, V, and current gain.
    fn sensor(&self) -> (f64, f64) {
        match self.effect {
            Effect::VoltageOffset { v } => (v, 1.0),
            Effect::CurrentGain { gain } => (0.0, gain),
            _ => (0.0, 1.0),
        }
    }
}

/// A load: constant current, or piecewise.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LoadKind {
    Cc,
    Variable,
}

/// A drawn load: (first fine step, true current A) segments counted from load-on.
#[derive(Clone, Debug)]
pub struct Load {
    segments: Vec<(u64, f64)>,
}

/// Fine steps in `s` seconds (times land on the generator's grid, so a load step is never inside a step).
fn steps(s: f64) -> u64 {
    (s / STEP_S).round() as u64
}

impl Load {
    /// Constant current: 1-3 A. Piecewise: segments of 150-600 s at 1-3 A, sometimes a 60-300 s rest.
    pub fn draw(kind: LoadKind, rng: &mut StdRng) -> Self {
        match kind {
            LoadKind::Cc => Self { segments: vec![(0, rng.random_range(1.0..3.0))] },
            LoadKind::Variable => {
                let mut segments = Vec::new();
                let mut at = 0;
                while at < steps(30_000.0) {
                    let rest = !segments.is_empty() && rng.random_bool(0.15);
                    let (current_a, span_s) = if rest {
                        (0.0, rng.random_range(60.0..300.0))
                    } else {
                        (rng.random_range(1.0..3.0), rng.random_range(150.0..600.0))
                    };
                    segments.push((at, current_a));
                    at += steps(span_s);
                }
                Self { segments }
            }
        }
    }

    fn at(&self, step: u64) -> f64 {
        self.segments.iter().rev().find(|(s, _)| *s <= step).map_or(0.0, |s| s.1)
    }
}

/// One sampled row: time s, voltage V, current A (positive discharging), temperature deg C.
pub type Row = (f64, f64, f64, f64);

/// One synthetic discharge: a 30-120 s rest, the load until the true voltage crosses the cut-off, a
/// 300-900 s relaxation; samples every 5-20 s (on the fine grid) with sensor noise.
pub fn record(truth: &Truth, cycle: u32, kind: LoadKind, rng: &mut StdRng) -> Vec<Row> {
    let cell = Cell::new(truth.cell(cycle));
    let load = Load::draw(kind, rng);
    let (rest, relax) = (steps(rng.random_range(30.0..120.0)), steps(rng.random_range(300.0..900.0)));
    let (offset_v, gain) = truth.sensor();
    let (nv, ni, nt) = (
        Normal::new(0.0, NOISE_V).unwrap(),
        Normal::new(0.0, truth.noise_a).unwrap(),
        Normal::new(0.0, truth.noise_k).unwrap(),
    );
    let mut s = cell.full();
    let mut rows = Vec::new();
    let (mut n, mut next_sample, mut cut) = (0u64, 0u64, None::<u64>);
    loop {
        let current_a = match cut {
            Some(_) => 0.0,
            None if n < rest => 0.0,
            None => load.at(n - rest),
        };
        if n == next_sample {
            rows.push((
                n as f64 * STEP_S,
                cell.voltage_v(&s) + offset_v + nv.sample(rng),
                gain * current_a + ni.sample(rng),
                cell.temperature(&s) - 273.15 + nt.sample(rng),
            ));
            next_sample += steps(rng.random_range(5.0..20.0));
        }
        if cut.is_some_and(|c| n >= c + relax) || n > steps(40_000.0) {
            break;
        }
        s = cell.rk4(&s, current_a, STEP_S);
        n += 1;
        if cut.is_none() && n > rest && cell.voltage_v(&s) < CUTOFF_V {
            cut = Some(n);
        }
    }
    rows
}

/// Writes cycles as a generic CSV (`time_s,voltage_v,current_a,temperature_c,cycle`) and reads it back.
pub fn write_and_read(dir: &Path, truth: &Truth, kinds: &[LoadKind], rng: &mut StdRng) -> Vec<Discharge> {
    let path = dir.join("cell.csv");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    writeln!(f, "time_s,voltage_v,current_a,temperature_c,cycle").unwrap();
    for (k, kind) in kinds.iter().enumerate() {
        let cycle = k as u32 + 1;
        for (t, v, i, tc) in record(truth, cycle, *kind, rng) {
            writeln!(f, "{t:.1},{v:.6},{i:.6},{tc:.4},{cycle}").unwrap();
        }
    }
    drop(f);
    read_generic(&path, Some(truth.ambient_c)).unwrap()
}

/// The load plan of every hidden-effect cell: four training discharges, two held out (the held-out pair
/// holds one constant and one piecewise load).
pub const PLAN: [LoadKind; CYCLES] =
    [LoadKind::Cc, LoadKind::Variable, LoadKind::Variable, LoadKind::Cc, LoadKind::Variable, LoadKind::Cc];
pub const N_TRAIN: usize = 4;

/// The doctor's settings in the tests: a 2 s simulator step keeps the suite quick.
pub fn config() -> DiagnoseConfig {
    let mut cfg = DiagnoseConfig::default();
    cfg.fit.dt_max_s = 2.0;
    cfg
}

/// The random stream of one synthetic cell: the truth and then its data follow from (cause, seed) alone.
pub fn cell_rng(cause: &str, seed: u64) -> StdRng {
    use rand::SeedableRng;
    let k = CAUSES.iter().position(|c| *c == cause).expect("a known cause") as u64;
    StdRng::seed_from_u64(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ (k << 56) ^ 0xd0c7)
}

/// Draws the cell hiding `cause` for `seed`, generates its six discharges, and runs the doctor with
/// the first [`N_TRAIN`] fitting and the rest held out.
pub fn diagnose_cell(cause: &str, seed: u64) -> (Truth, bcal_doctor::Diagnosis) {
    let mut rng = cell_rng(cause, seed);
    let truth = Truth::draw(cause, &mut rng);
    let dir = tempfile::tempdir().unwrap();
    let records = write_and_read(dir.path(), &truth, &PLAN, &mut rng);
    assert_eq!(records.len(), CYCLES, "every discharge reads back");
    let (train, held) = records.split_at(N_TRAIN);
    let diag = bcal_doctor::diagnose(&config(), train, held).unwrap();
    (truth, diag)
}

/// The truths of whole-life cells ([`life`]): a voltage-sensor offset over a whole constant-current life, and
/// recovery after rest. Rows of the soak run's confusion matrix after [`CAUSES`].
pub const LIFE_CAUSES: [&str; 2] = ["voltage_offset_life", "recovery"];

/// What the doctor named for a whole-life cell: the voltage diagnosis's cause, `recovery` when the lifetime
/// diagnosis names recovery and the voltage one names nothing, both joined by `+` otherwise.
pub fn life_named(diag: &bcal_doctor::Diagnosis) -> String {
    match (diag.cause, diag.lifetime.as_ref().is_some_and(|l| l.recovery)) {
        (cause, false) => cause.to_string(),
        ("none", true) => "recovery".to_string(),
        (cause, true) => format!("{cause}+recovery"),
    }
}

/// Draws the whole life hiding `cause` (a [`LIFE_CAUSES`] name) for `seed`, runs the voltage diagnosis on
/// [`life::VOLTAGE_TRAIN`] / [`life::VOLTAGE_HELDOUT`] and the lifetime diagnosis on every record (fitted
/// on cycles 1..=[`life::LIFE_TRAIN`], judged on the rest), attached to the diagnosis.
pub fn diagnose_life(cause: &str, seed: u64) -> (life::LifeTruth, bcal_doctor::Diagnosis) {
    use rand::SeedableRng;
    let k = LIFE_CAUSES.iter().position(|c| *c == cause).expect("a life cause") as u64;
    let mut rng = StdRng::seed_from_u64(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ (k << 56) ^ 0x11fe);
    let truth = life::LifeTruth::draw(if cause == "recovery" { "recovery" } else { "voltage_offset" }, &mut rng);
    let dir = tempfile::tempdir().unwrap();
    let (records, starts) = life::write_and_read_life(dir.path(), &truth, &mut rng);
    assert_eq!(records.len(), life::LIFE_CYCLES as usize, "every discharge reads back");
    let pick =
        |cycles: &[u32]| -> Vec<Discharge> { records.iter().filter(|d| cycles.contains(&d.cycle)).cloned().collect() };
    let cfg = config();
    let mut diag = bcal_doctor::diagnose(&cfg, &pick(&life::VOLTAGE_TRAIN), &pick(&life::VOLTAGE_HELDOUT)).unwrap();
    let life_cfg = bcal_doctor::lifetime::LifetimeConfig::from_diagnose(&cfg);
    let lifetime = bcal_doctor::lifetime::assess(
        &life_cfg,
        &records,
        &starts,
        &(1..=life::LIFE_TRAIN),
        &(life::LIFE_TRAIN + 1..=life::LIFE_CYCLES),
        Some(&diag),
    )
    .unwrap();
    diag.lifetime = Some(lifetime);
    (truth, diag)
}
