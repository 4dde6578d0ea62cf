//! The current a prediction assumes for the rest of a discharge, from its readings so far (no look-ahead):
//! the mean of the loaded readings, or, where the load switches about as often as it is sampled, the mean
//! over time since the load came on. A square wave sampled once per half-period (NASA's B0025-B0028: 4 A at
//! half duty, a 20 s period, a reading every 10-12 s in step with it) reads 4 A at every loaded reading and
//! draws 2 A on average; predicted at 4 A its end comes at half the time. At the mean over time the model
//! runs the charge the cell really draws, and the end it then predicts late (the square wave's peaks reach
//! the cut-off first) is what the knee and the recentring measured on the discharges before take off.
//!
//! A load held at constant power (a cycler in CP mode, a motor or converter behind the cell) draws more
//! current as the voltage falls: about a third more at a 3.0 V cut-off than at 4.0 V. Its mean current so
//! far is what it drew while the voltage was high, and predicted at it the end comes late by most of that
//! rise. Where the loaded readings' power has held steadier than their current (a coefficient of
//! variation under half the current's), the prediction runs at their mean power instead; a cycler in CC mode
//! holds its current and its power falls with the voltage, so nothing changes for it. Readings that followed
//! a load step stay out of that comparison: a reading caught on the way up at load-on (mid-step, in a
//! ramp of steps of more than [`STEP_A`]) sets both spreads alike and hid a held power for most of a
//! discharge. A ramp in smaller steps still delays the power (never takes a current for one): leaving out
//! the first minute under load instead cost the simulated test cells at 15 W most of their detections at
//! 10 % of the discharge (`cargo run --release -p bcal-calib --example load_rule`).

use super::{LOADED_A, MIN_ALTERNATING_LOADED, STEP_A};
use crate::battery::Load;

/// The rule of an alternating load, for a stream and a whole record alike: at least
/// [`MIN_ALTERNATING_LOADED`] loaded readings, more than half of which followed a load step.
pub fn alternates(loaded: usize, followed_a_step: usize) -> bool {
    loaded >= MIN_ALTERNATING_LOADED as usize && 2 * followed_a_step > loaded
}

/// The load is taken as held at constant power where the settled loaded readings' power varies (sd over mean)
/// less than this share of their current's variation ...
pub const POWER_HELD_RATIO: f64 = 0.5;
/// ... and, once taken, let go only where it varies more than this share (a dead band: near the threshold,
/// early in a discharge sampled at 1 s, the noise alone flipped the assumption back and forth).
pub const POWER_RELEASED_RATIO: f64 = 0.7;

/// Running mean and sum of squared deviations (Welford's update: the spread of a few mA on 2 A is not lost
/// to cancellation).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Spread {
    mean: f64,
    m2: f64,
}

impl Spread {
    fn push(&mut self, n: u32, x: f64) {
        let d = x - self.mean;
        self.mean += d / f64::from(n);
        self.m2 += d * (x - self.mean);
    }

    /// Standard deviation over mean (the population's), with `n` values taken.
    fn variation(&self, n: u32) -> f64 {
        (self.m2 / f64::from(n)).sqrt() / self.mean.abs()
    }
}

/// The running means of one discharge's current and power.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LoadMean {
    loaded_sum_a: f64,
    loaded_n: u32,
    /// The settled loaded readings' current, A, and power, W (those that did not follow a load step), how
    /// many, and whether their power is taken as held.
    current: Spread,
    power: Spread,
    settled_n: u32,
    power_held: bool,
    /// Loaded readings whose current stepped from the reading before.
    switched_n: u32,
    /// The first loaded reading, s.
    on_s: Option<f64>,
    /// Charge drawn since then, A s (trapezoids between readings).
    drawn_as: f64,
    last: Option<(f64, f64)>,
}

impl LoadMean {
    /// Takes a reading: its time, s, current, A (positive while discharging), and terminal voltage, V.
    pub fn push(&mut self, t_s: f64, current_a: f64, voltage_v: f64) {
        let loaded = current_a > LOADED_A;
        let mut stepped = true;
        if let Some((t0_s, i0_a)) = self.last {
            if self.on_s.is_some() {
                self.drawn_as += 0.5 * (i0_a + current_a) * (t_s - t0_s);
            }
            stepped = (current_a - i0_a).abs() > STEP_A;
            if loaded && stepped {
                self.switched_n += 1;
            }
        }
        if loaded {
            self.loaded_sum_a += current_a;
            self.loaded_n += 1;
            self.on_s.get_or_insert(t_s);
            if !stepped {
                self.settled_n += 1;
                self.current.push(self.settled_n, current_a);
                self.power.push(self.settled_n, current_a * voltage_v);
                if self.settled_n >= MIN_ALTERNATING_LOADED {
                    let ratio = self.power.variation(self.settled_n) / self.current.variation(self.settled_n);
                    let bound = if self.power_held { POWER_RELEASED_RATIO } else { POWER_HELD_RATIO };
                    self.power_held = ratio < bound;
                }
            }
        }
        self.last = Some((t_s, current_a));
    }

    /// Whether the load switches about as often as it is sampled: more than half of at least
    /// [`MIN_ALTERNATING_LOADED`] loaded readings followed a step.
    pub fn alternating(&self) -> bool {
        alternates(self.loaded_n as usize, self.switched_n as usize)
    }

    /// The current to assume, A: None before the first loaded reading.
    pub fn current_a(&self) -> Option<f64> {
        if self.loaded_n == 0 {
            return None;
        }
        match (self.on_s, self.last) {
            (Some(on_s), Some((t_s, _))) if self.alternating() && t_s > on_s => Some(self.drawn_as / (t_s - on_s)),
            _ => Some(self.loaded_sum_a / f64::from(self.loaded_n)),
        }
    }

    /// Whether the load has been held at constant power: not alternating, and at least
    /// [`MIN_ALTERNATING_LOADED`] settled loaded readings whose power varied less than [`POWER_HELD_RATIO`]
    /// times their current did (once taken, until it varies more than [`POWER_RELEASED_RATIO`] times).
    pub fn power_held(&self) -> bool {
        self.power_held && !self.alternating()
    }

    /// The load to assume for the rest of the discharge: the settled loaded readings' mean power where the
    /// load has been held at power ([`LoadMean::power_held`]), else [`LoadMean::current_a`]. None before the first
    /// loaded reading.
    pub fn load(&self) -> Option<Load> {
        if self.power_held() {
            return Some(Load::PowerW(self.power.mean));
        }
        self.current_a().map(Load::CurrentA)
    }

    /// The mean over the loaded readings alone, A (None before the first).
    pub fn loaded_mean_a(&self) -> Option<f64> {
        (self.loaded_n > 0).then(|| self.loaded_sum_a / f64::from(self.loaded_n))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A constant load is its loaded mean, reading for reading; a square wave read once per half-period is
    /// its mean over time once it has been seen to alternate, and a load that steps once is not alternating.
    #[test]
    fn a_square_wave_read_once_per_half_period_is_assumed_at_its_mean_over_time() {
        let mut cc = LoadMean::default();
        for k in 0..400 {
            let i = if k < 3 { 0.0 } else { 2.0 + 0.01 * f64::from(k % 3) };
            cc.push(f64::from(k) * 9.7, i, 4.0 - 0.002 * f64::from(k));
        }
        assert!(!cc.alternating() && !cc.power_held());
        assert_eq!(cc.current_a(), cc.loaded_mean_a());
        assert_eq!(cc.load(), cc.current_a().map(Load::CurrentA));
        // 4 A at half duty: the readings alternate 0 / 4 A every 10.4 s.
        let mut sq = LoadMean::default();
        for k in 0..400 {
            let i = if k < 3 || k % 2 == 0 { 0.001 } else { 4.02 };
            sq.push(f64::from(k) * 10.4, i, 3.9);
            if k == 12 {
                assert!(!sq.alternating(), "5 loaded readings are too few to call it");
                assert!((sq.current_a().unwrap() - 4.02).abs() < 1e-9);
            }
        }
        assert!(sq.alternating());
        assert!((sq.current_a().unwrap() - 2.01).abs() < 0.02, "{:?}", sq.current_a());
        assert!((sq.loaded_mean_a().unwrap() - 4.02).abs() < 1e-9);
        assert!(!sq.power_held(), "an alternating load is taken at its mean current over time");
    }

    /// Readings every `dt_s` of a cell whose voltage falls from 4.0 to 3.2 V over 3000 s, with 3 mV and 10 mA
    /// of sensor noise (a fixed pseudo-random sequence), under a load held at `power_w` or at `current_a`,
    /// the first `ramp` loaded readings on the way up to it (at 1 / (ramp + 1), 2 / (ramp + 1), ... of it).
    fn falling(n: u32, held: Load, dt_s: f64, ramp: u32) -> LoadMean {
        let mut m = LoadMean::default();
        let mut u = 0x9e37_79b9_u32;
        let mut noise = move || {
            u ^= u << 13;
            u ^= u >> 17;
            u ^= u << 5;
            f64::from(u) / f64::from(u32::MAX) - 0.5
        };
        m.push(0.0, 0.0, 4.1);
        for k in 1..=n {
            let t_s = f64::from(k) * dt_s;
            let v = 4.0 - 0.8 * t_s / 3000.0;
            let share = if k <= ramp { f64::from(k) / f64::from(ramp + 1) } else { 1.0 };
            let i = share
                * match held {
                    Load::PowerW(w) => w / v,
                    Load::CurrentA(a) => a,
                };
            m.push(t_s, i + 0.02 * noise(), v + 0.006 * noise());
        }
        m
    }

    /// A load held at constant power is assumed at its mean power once its current has been seen to rise
    /// more than its power varies, and a constant current stays a current however far its power falls; before
    /// [`MIN_ALTERNATING_LOADED`] settled readings, and in the first minutes while the voltage has moved little
    /// more than the noise, it is a current. Readings on the way up to the load (a reading caught mid-step at
    /// load-on, a soft start) do not hide the power.
    #[test]
    fn a_load_held_at_constant_power_is_assumed_at_its_mean_power() {
        let cp = falling(3000, Load::PowerW(8.0), 1.0, 0);
        assert!(cp.power_held());
        match cp.load() {
            Some(Load::PowerW(w)) => assert!((w - 8.0).abs() < 0.01, "{w}"),
            other => panic!("{other:?}"),
        }
        let cc = falling(3000, Load::CurrentA(2.0), 1.0, 0);
        assert!(!cc.power_held());
        assert_eq!(cc.load(), cc.current_a().map(Load::CurrentA));
        assert!(!falling(10, Load::PowerW(8.0), 1.0, 0).power_held(), "9 settled readings");
        // A fifth of the discharge in, the current has risen 4 % against 0.3 % of noise, read at 1 s or at 10 s.
        assert!(falling(600, Load::PowerW(8.0), 1.0, 0).power_held());
        assert!(falling(60, Load::PowerW(8.0), 10.0, 0).power_held());
        assert!(!falling(600, Load::CurrentA(2.0), 1.0, 0).power_held());
        // A first loaded reading at 60 % of the load, or a 40 s soft start read every 10 s.
        for ramp in [1, 4] {
            let m = falling(60, Load::PowerW(8.0), 10.0, ramp);
            assert!(m.power_held(), "ramp of {ramp}");
            assert!(matches!(m.load(), Some(Load::PowerW(w)) if (w - 8.0).abs() < 0.01), "{:?}", m.load());
            assert!(!falling(300, Load::CurrentA(2.0), 10.0, ramp).power_held());
        }
    }
}
