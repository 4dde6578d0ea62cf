//! The current a prediction assumes for the rest of a discharge, from its readings so far (no look-ahead):
//! the mean of the loaded readings, or, where the load switches about as often as it is sampled, the mean
//! over time since the load came on. A square wave sampled once per half-period (NASA's B0025-B0028: 4 A at
//! half duty, a 20 s period, a reading every 10-12 s in step with it) reads 4 A at every loaded reading and
//! draws 2 A on average; predicted at 4 A its end comes at half the time. At the mean over time the model
//! runs the charge the cell really draws, and the end it then predicts late (the square wave's peaks reach
//! the cut-off first) is what the knee and the recentring measured on the discharges before take off.

use super::{LOADED_A, MIN_ALTERNATING_LOADED, STEP_A};

/// The rule of an alternating load, for a stream and a whole record alike: at least
/// [`MIN_ALTERNATING_LOADED`] loaded readings, more than half of which followed a load step.
pub fn alternates(loaded: usize, followed_a_step: usize) -> bool {
    loaded >= MIN_ALTERNATING_LOADED as usize && 2 * followed_a_step > loaded
}

/// The running means of one discharge's current.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LoadMean {
    loaded_sum_a: f64,
    loaded_n: u32,
    /// Loaded readings whose current stepped from the reading before.
    switched_n: u32,
    /// The first loaded reading, s.
    on_s: Option<f64>,
    /// Charge drawn since then, A s (trapezoids between readings).
    drawn_as: f64,
    last: Option<(f64, f64)>,
}

impl LoadMean {
    /// Takes a reading: its time, s, and current, A (positive while discharging).
    pub fn push(&mut self, t_s: f64, current_a: f64) {
        let loaded = current_a > LOADED_A;
        if let Some((t0_s, i0_a)) = self.last {
            if self.on_s.is_some() {
                self.drawn_as += 0.5 * (i0_a + current_a) * (t_s - t0_s);
            }
            if loaded && (current_a - i0_a).abs() > STEP_A {
                self.switched_n += 1;
            }
        }
        if loaded {
            self.loaded_sum_a += current_a;
            self.loaded_n += 1;
            self.on_s.get_or_insert(t_s);
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
            cc.push(f64::from(k) * 9.7, i);
        }
        assert!(!cc.alternating());
        assert_eq!(cc.current_a(), cc.loaded_mean_a());
        // 4 A at half duty: the readings alternate 0 / 4 A every 10.4 s.
        let mut sq = LoadMean::default();
        for k in 0..400 {
            let i = if k < 3 || k % 2 == 0 { 0.001 } else { 4.02 };
            sq.push(f64::from(k) * 10.4, i);
            if k == 12 {
                assert!(!sq.alternating(), "5 loaded readings are too few to call it");
                assert!((sq.current_a().unwrap() - 4.02).abs() < 1e-9);
            }
        }
        assert!(sq.alternating());
        assert!((sq.current_a().unwrap() - 2.01).abs() < 0.02, "{:?}", sq.current_a());
        assert!((sq.loaded_mean_a().unwrap() - 4.02).abs() < 1e-9);
    }
}
