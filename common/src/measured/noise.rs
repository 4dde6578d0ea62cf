//! The voltage sensor's noise, read off a record's own readings: what a rest voltage is known to, and so
//! how well the charge a discharge starts with is known where the open-circuit curve is flat.

use super::scenario::Sample;

/// The fewest triples of readings an estimate takes: fewer say too little of a spread.
pub const MIN_NOISE_TRIPLES: usize = 20;
/// How many of the latest discharges a cell's sensor noise is taken over (the median of what each one's own
/// readings say), by `bcal calibrate`'s records and a live stream alike.
pub const NOISE_WINDOW: usize = 5;
/// Longest time a triple of readings may span, s: over longer the voltage's own curve shows in the residual.
const MAX_TRIPLE_SPAN_S: f64 = 120.0;
/// A triple shares one current when its readings' currents lie within this share of it, or within
/// [`STEADY_CURRENT_A`] (a cycler's current wanders by a few milliamperes).
const STEADY_SHARE: f64 = 0.02;
const STEADY_CURRENT_A: f64 = 0.02;
/// A current this close to zero is a rest.
const REST_A: f64 = 0.02;
/// The median absolute deviation of a normal variable times this is its standard deviation.
const MAD_TO_SD: f64 = 1.4826;

/// The voltage sensor's noise, V (one standard deviation), from readings in time order: each reading against
/// the line through its two neighbours, where the three share one steady current (all at rest, or all under
/// a load that moved by at most 2 % or 20 mA) within two minutes. White noise of sd `s` leaves a residual of
/// sd `s sqrt(1 + wa^2 + wc^2)` (the neighbours' interpolation weights), so each residual is scaled by that,
/// and the median absolute one taken to a standard deviation: robust to the few triples that straddle the
/// settling after a load step or the knee at the end. A sensor that rounds its readings leaves at least its
/// rounding's spread (the smallest step between readings over sqrt(12)), which a median of zeros would hide.
/// None with fewer than [`MIN_NOISE_TRIPLES`] triples.
pub fn voltage_noise_v(samples: &[Sample]) -> Option<f64> {
    let steady = |w: &[Sample]| {
        let (lo, hi) =
            w.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), s| (lo.min(s.current_a), hi.max(s.current_a)));
        let at_rest = lo.abs() < REST_A && hi.abs() < REST_A;
        let loaded = lo > REST_A && hi - lo <= STEADY_CURRENT_A.max(STEADY_SHARE * hi);
        at_rest || loaded
    };
    let mut residuals: Vec<f64> = samples
        .windows(3)
        .filter(|w| {
            let span = w[2].t_s - w[0].t_s;
            span > 0.0 && span <= MAX_TRIPLE_SPAN_S && w[1].t_s > w[0].t_s && w[2].t_s > w[1].t_s && steady(w)
        })
        .map(|w| {
            let wa = (w[2].t_s - w[1].t_s) / (w[2].t_s - w[0].t_s);
            let wc = 1.0 - wa;
            let r = w[1].voltage_v - (wa * w[0].voltage_v + wc * w[2].voltage_v);
            r.abs() / (1.0 + wa * wa + wc * wc).sqrt()
        })
        .filter(|r| r.is_finite())
        .collect();
    if residuals.len() < MIN_NOISE_TRIPLES {
        return None;
    }
    residuals.sort_by(f64::total_cmp);
    let median = residuals[residuals.len() / 2];
    let rounding = samples
        .windows(2)
        .map(|w| (w[1].voltage_v - w[0].voltage_v).abs())
        .filter(|d| *d > 0.0)
        .fold(f64::INFINITY, f64::min);
    let rounding_sd = if rounding.is_finite() { rounding / 12f64.sqrt() } else { 0.0 };
    Some((MAD_TO_SD * median).max(rounding_sd))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::measured::scenario::Request;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// A discharge's readings: a rest, then 2 A with a voltage that settles and then falls and bends down at
    /// the end (the shape a cell draws), read every `dt_s` with noise `sd_v`, rounded to `step_v` (0: not).
    fn readings(dt_s: f64, sd_v: f64, step_v: f64, seed: u64) -> Vec<Sample> {
        let mut rng = rand::rngs::SmallRng::seed_from_u64(seed);
        let noise = Normal::new(0.0, sd_v.max(1e-300)).unwrap();
        let n = (3600.0 / dt_s) as usize;
        (0..n)
            .map(|k| {
                let t_s = k as f64 * dt_s;
                let (i, v) = if t_s < 60.0 {
                    (0.0, 4.19)
                } else {
                    let u = (t_s - 60.0) / 3540.0;
                    (2.0, 3.95 - 0.15 * (-(t_s - 60.0) / 40.0).exp() - 0.5 * u - 0.4 * u.powi(12))
                };
                let mut v = v + if sd_v > 0.0 { noise.sample(&mut rng) } else { 0.0 };
                if step_v > 0.0 {
                    v = (v / step_v).round() * step_v;
                }
                Sample { t_s, voltage_v: v, current_a: i, temperature_k: 298.15, request: Request::Unknown }
            })
            .collect()
    }

    #[test]
    fn the_noise_is_read_off_the_readings_at_any_sampling() {
        for (dt_s, sd_v) in [(1.0, 0.003), (18.0, 0.004), (10.0, 0.0005)] {
            for seed in 0..3 {
                let got = voltage_noise_v(&readings(dt_s, sd_v, 0.0, seed)).unwrap();
                // 200-3600 residuals: the median's spread is a few %; the voltage's own curve adds little.
                assert!((got / sd_v - 1.0).abs() < 0.15, "dt {dt_s} s, noise {sd_v} V: read {got}");
            }
        }
        // Noiseless readings rounded to 10 mV: the rounding's spread, not zero.
        let rounded = voltage_noise_v(&readings(10.0, 0.0, 0.01, 0)).unwrap();
        assert!((rounded - 0.01 / 12f64.sqrt()).abs() < 1e-9, "{rounded}");
        // Too few readings say nothing.
        assert_eq!(voltage_noise_v(&readings(18.0, 0.004, 0.0, 0)[..15]), None);
    }
}
