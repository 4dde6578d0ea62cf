//! A cell's whole life for the lifetime tests: [`LIFE_CYCLES`] constant-current discharges on a test
//! schedule (a usual rest between discharges and longer pauses every few discharges, as NASA's test
//! campaigns ran), written as one generic CSV on one clock so the reader hands the doctor each record's start.
//!
//! Each discharge is the independent generator's cell ([`super::cell`], RK4 at 0.1 s) with the protocol of
//! NASA's 2 A cells: a rest of 20-60 s before the load (one to a few samples), one current for the whole life
//! (1.5-2.5 A, drawn per cell) down to the 3.0 V cut-off, a 300-600 s relaxation, samples every 5-20 s with
//! the harness's sensor noise. The cell ages slowly (qMobile -0.15..-0.4 % and Ro +0.2..+0.8 % per
//! discharge, 0.2 % cycle-to-cycle jitter on qMobile) and may hide:
//! - a voltage-sensor offset of 15-30 mV (either sign) over the whole life;
//! - recovery after rest, in the generator's own terms (not the doctor's): a reservoir of recoverable
//!   capacity, its fill level f in [0, 1], refills toward full during a rest (1 - f falls as exp(-rest /
//!   refill_s), refill_s 5-50 h); a discharge gains `gain` x f of qMobile (2-5 %: NASA's jumps are 0.02-0.15
//!   Ah of 1.3-1.9) and then uses a share `use_share` (0.15-0.5) of what was left. The cell starts at the
//!   fill level its usual rest keeps.

use super::cell::{Cell, CellParams};
use super::{Row, CUTOFF_V, NOISE_V, STEP_S};
use bcal_doctor::read::{read_csv, ReadOptions, RecordStart};
use bcal_doctor::Discharge;
use rand::rngs::StdRng;
use rand::Rng;
use rand_distr::{Distribution, Normal};
use std::io::Write;
use std::path::Path;

/// Discharges in a life.
pub const LIFE_CYCLES: u32 = 40;
/// The lifetime diagnosis fits cycles 1..=LIFE_TRAIN and judges the rest.
pub const LIFE_TRAIN: u32 = 20;
/// The records the voltage diagnosis sees (four fitted, two judged), as in the other hidden-effect cells.
pub const VOLTAGE_TRAIN: [u32; 4] = [2, 8, 14, 20];
pub const VOLTAGE_HELDOUT: [u32; 2] = [27, 38];

/// Recovery after rest, in the generator's terms (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reservoir {
    pub gain: f64,
    pub refill_s: f64,
    pub use_share: f64,
}

impl Reservoir {
    fn refilled(&self, fill: f64, rest_s: f64) -> f64 {
        1.0 - (1.0 - fill) * (-rest_s / self.refill_s).exp()
    }
}

/// The hidden truth of one life.
#[derive(Clone, Debug, PartialEq)]
pub struct LifeTruth {
    /// `voltage_offset` or `recovery`.
    pub cause: &'static str,
    pub ambient_c: f64,
    pub current_a: f64,
    pub q_mobile_c: f64,
    pub r_o_ohm: f64,
    pub q_fade_per_cycle: f64,
    pub r_growth_per_cycle: f64,
    pub noise_a: f64,
    pub noise_k: f64,
    pub offset_v: f64,
    pub reservoir: Option<Reservoir>,
    /// Rest before each discharge, s (the first is the rest before the life's first discharge).
    pub rests_s: Vec<f64>,
    /// The usual rest, s.
    pub usual_rest_s: f64,
    /// Each discharge's true qMobile, C (fade, jitter and recovery).
    pub q_by_cycle: Vec<f64>,
}

fn log_uniform(rng: &mut StdRng, lo: f64, hi: f64) -> f64 {
    rng.random_range(lo.ln()..hi.ln()).exp()
}

impl LifeTruth {
    /// A life hiding `cause` (`voltage_offset` or `recovery`), every value drawn from a continuous range.
    pub fn draw(cause: &str, rng: &mut StdRng) -> Self {
        let usual_rest_s = rng.random_range(2.0..6.0) * 3600.0;
        // Pauses of 1-14 days every 6-12 discharges, the first after 3-8.
        let mut rests_s = Vec::with_capacity(LIFE_CYCLES as usize);
        let mut next_pause = rng.random_range(3..=8);
        for k in 0..LIFE_CYCLES {
            if k == next_pause {
                rests_s.push(log_uniform(rng, 86_400.0, 14.0 * 86_400.0));
                next_pause += rng.random_range(6..=12);
            } else {
                rests_s.push(usual_rest_s * rng.random_range(0.9..1.1));
            }
        }
        let mut t = Self {
            cause: if cause == "recovery" { "recovery" } else { "voltage_offset" },
            ambient_c: rng.random_range(20.0..30.0),
            current_a: rng.random_range(1.5..2.5),
            q_mobile_c: rng.random_range(5400.0..7200.0),
            r_o_ohm: rng.random_range(0.10..0.17),
            q_fade_per_cycle: rng.random_range(0.0015..0.004),
            r_growth_per_cycle: rng.random_range(0.002..0.008),
            noise_a: rng.random_range(0.005..0.010),
            noise_k: rng.random_range(0.1..0.5),
            offset_v: 0.0,
            reservoir: None,
            rests_s,
            usual_rest_s,
            q_by_cycle: Vec::new(),
        };
        match cause {
            "voltage_offset" => {
                t.offset_v = if rng.random_bool(0.5) { 1.0 } else { -1.0 } * rng.random_range(0.015..0.03)
            }
            "recovery" => {
                t.reservoir = Some(Reservoir {
                    gain: rng.random_range(0.02..0.05),
                    refill_s: log_uniform(rng, 5.0 * 3600.0, 50.0 * 3600.0),
                    use_share: rng.random_range(0.15..0.5),
                })
            }
            other => panic!("no life hides {other}"),
        }
        let jitter = Normal::new(0.0, 0.002).unwrap();
        let mut fill = t.reservoir.map_or(0.0, |r| {
            // The level the usual rest keeps: iterate the cycle until it settles.
            let mut f = 0.0;
            for _ in 0..500 {
                f = r.refilled(f, usual_rest_s) * (1.0 - r.use_share);
            }
            f
        });
        for (k, rest_s) in t.rests_s.clone().into_iter().enumerate() {
            let mut q = t.q_mobile_c * (1.0 - t.q_fade_per_cycle * k as f64) * (1.0 + jitter.sample(rng));
            if let Some(r) = t.reservoir {
                fill = r.refilled(fill, rest_s);
                q *= 1.0 + r.gain * fill;
                fill *= 1.0 - r.use_share;
            }
            t.q_by_cycle.push(q);
        }
        t
    }

    /// The generator's cell on a cycle (1-based).
    pub fn cell(&self, cycle: u32) -> CellParams {
        let k = (cycle - 1) as usize;
        CellParams::base(
            self.q_by_cycle[k],
            self.r_o_ohm * (1.0 + self.r_growth_per_cycle * k as f64),
            self.ambient_c + 273.15,
        )
    }
}

/// One discharge of the life: rest, constant current to the cut-off, relaxation; sampled with noise. Time
/// counts from the record's start.
pub fn life_record(truth: &LifeTruth, cycle: u32, rng: &mut StdRng) -> Vec<Row> {
    let cell = Cell::new(truth.cell(cycle));
    let steps = |s: f64| (s / STEP_S).round() as u64;
    let (rest, relax) = (steps(rng.random_range(20.0..60.0)), steps(rng.random_range(300.0..600.0)));
    let (nv, ni, nt) = (
        Normal::new(0.0, NOISE_V).unwrap(),
        Normal::new(0.0, truth.noise_a).unwrap(),
        Normal::new(0.0, truth.noise_k).unwrap(),
    );
    let mut s = cell.full();
    let mut rows = Vec::new();
    let (mut n, mut next_sample, mut cut) = (0u64, 0u64, None::<u64>);
    loop {
        let current_a = if cut.is_some() || n < rest { 0.0 } else { truth.current_a };
        if n == next_sample {
            rows.push((
                n as f64 * STEP_S,
                cell.voltage_v(&s) + truth.offset_v + nv.sample(rng),
                current_a + ni.sample(rng),
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

/// Writes the whole life as one generic CSV (`time_s` on the schedule's clock, `cycle`) and reads it back
/// with [`read_csv`]: every record and its start.
pub fn write_and_read_life(dir: &Path, truth: &LifeTruth, rng: &mut StdRng) -> (Vec<Discharge>, Vec<RecordStart>) {
    let path = dir.join("life.csv");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    writeln!(f, "time_s,voltage_v,current_a,temperature_c,cycle").unwrap();
    let mut clock_s = 0.0;
    for cycle in 1..=LIFE_CYCLES {
        clock_s += truth.rests_s[cycle as usize - 1];
        let rows = life_record(truth, cycle, rng);
        for (t, v, i, tc) in &rows {
            writeln!(f, "{:.1},{v:.6},{i:.6},{tc:.4},{cycle}", clock_s + t).unwrap();
        }
        clock_s += rows.last().map_or(0.0, |r| r.0);
    }
    drop(f);
    let opts = ReadOptions { ambient_c: Some(truth.ambient_c), ..ReadOptions::default() };
    let (records, report) = read_csv(&path, &opts).unwrap();
    (records, report.starts)
}
