//! Where the residual lives and what it follows. For each fitted record the residual (measured - model, mV)
//! is split into the discharge's parts (rest before the load, load-on step, plateau, knee before cut-off,
//! relaxation after) and thirds of the loaded time, and pooled correlations say whether it follows state of
//! charge, current, time under load or measured temperature rise. A robust second-difference estimate gives
//! the sensor-noise floor the residual is compared with.
//!
//! Pure functions of data and simulated voltage: nothing here fits or prints.

use crate::record::{Discharge, Windows};
use serde::Serialize;

/// Samples within this time after the load goes on belong to the load-on step, s.
pub const LOAD_ON_WINDOW_S: f64 = 150.0;
/// Loaded samples past this fraction of the window's discharged charge belong to the knee.
pub const KNEE_FRACTION: f64 = 0.85;

/// RMSE of a part of the discharge, mV, and how many samples it holds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Part {
    pub rmse_mv: f64,
    pub mean_mv: f64,
    pub samples: usize,
}

/// Residual of one record, ready for summaries and plots.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RecordResidual {
    pub cycle: u32,
    /// Time since the load went on, s, every sample.
    pub time_s: Vec<f64>,
    /// Measured - model, mV, every sample.
    pub residual_mv: Vec<f64>,
    /// Fraction of the fit window's charge drawn at each sample (0 before, 1 after).
    pub discharged_fraction: Vec<f64>,
    pub windows: Windows,
    /// Per sample: inside the fit window and not right after a load step (the fitted samples).
    pub fitted: Vec<bool>,
}

/// Pooled residual structure over a set of records.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Structure {
    /// The fit window (load on to the floor).
    pub under_load: Part,
    pub rest_before: Part,
    pub load_on: Part,
    pub plateau: Part,
    pub knee: Part,
    /// After cut-off; records that end under load contribute nothing.
    pub relaxation: Part,
    /// First, middle and last third of the fit window by time.
    pub thirds: [Part; 3],
    /// Pearson correlation of the loaded residual with discharged fraction (state of charge).
    pub corr_soc: f64,
    /// ... with the measured current.
    pub corr_current: f64,
    /// ... with time since load-on.
    pub corr_time: f64,
    /// ... with measured temperature rise above ambient (0 when the records have no temperature).
    pub corr_temperature: f64,
    /// Robust white-noise estimate from second differences of the loaded residual, mV.
    pub noise_mv: f64,
}

impl Structure {
    /// The named parts in a fixed order (for evidence and reports).
    pub fn parts(&self) -> [(&'static str, Part); 5] {
        [
            ("load_on", self.load_on),
            ("plateau", self.plateau),
            ("knee", self.knee),
            ("relaxation", self.relaxation),
            ("rest_before", self.rest_before),
        ]
    }
}

/// The residual of one record given the model's voltage at every sample; `used` lists the fitted samples.
pub fn record_residual(d: &Discharge, w: Windows, used: &[usize], model_v: &[f64]) -> RecordResidual {
    let mut fitted = vec![false; d.len()];
    for &k in used {
        fitted[k] = true;
    }
    let t_on = d.time_s[w.load_on];
    let total_ah = d.charge_ah(w.load_on, w.fit_end).max(1e-12);
    let mut drawn = 0.0;
    let mut discharged_fraction = Vec::with_capacity(d.len());
    for k in 0..d.len() {
        if k > w.load_on && k < w.fit_end {
            drawn += d.charge_ah(k - 1, k + 1);
        }
        let f = if k < w.load_on {
            0.0
        } else if k >= w.fit_end {
            1.0
        } else {
            (drawn / total_ah).min(1.0)
        };
        discharged_fraction.push(f);
    }
    RecordResidual {
        cycle: d.cycle,
        time_s: d.time_s.iter().map(|t| t - t_on).collect(),
        residual_mv: d.voltage_v.iter().zip(model_v).map(|(m, s)| 1000.0 * (m - s)).collect(),
        discharged_fraction,
        windows: w,
        fitted,
    }
}

#[derive(Default)]
struct Acc {
    sse: f64,
    sum: f64,
    n: usize,
}

impl Acc {
    fn add(&mut self, r: f64) {
        self.sse += r * r;
        self.sum += r;
        self.n += 1;
    }
    fn part(&self) -> Part {
        if self.n == 0 {
            return Part::default();
        }
        Part { rmse_mv: (self.sse / self.n as f64).sqrt(), mean_mv: self.sum / self.n as f64, samples: self.n }
    }
}

/// Pools the residual structure of several records (`records[i]` is the data behind `residuals[i]`).
pub fn structure(records: &[&Discharge], residuals: &[RecordResidual]) -> Structure {
    let (mut all, mut rest, mut on, mut plateau, mut knee, mut relax) =
        (Acc::default(), Acc::default(), Acc::default(), Acc::default(), Acc::default(), Acc::default());
    let mut thirds = [Acc::default(), Acc::default(), Acc::default()];
    let mut cols: [Vec<f64>; 5] = Default::default();
    let mut second_diffs = Vec::new();
    for (d, r) in records.iter().zip(residuals) {
        let w = r.windows;
        let span_s = (r.time_s[w.fit_end - 1]).max(1e-9);
        // Where the load alternates from sample to sample, so may the residual's bias (loaded and unloaded
        // samples): the noise is read off samples of one kind, two apart.
        let lag =
            if d.alternating_load(bcal_common::measured::LOADED_A, bcal_common::measured::STEP_A) { 2 } else { 1 };
        for k in 0..d.len() {
            let e = r.residual_mv[k];
            if k < w.load_on {
                rest.add(e);
            } else if k < w.fit_end {
                if !r.fitted[k] {
                    continue;
                }
                all.add(e);
                if r.time_s[k] < LOAD_ON_WINDOW_S {
                    on.add(e);
                } else if r.discharged_fraction[k] >= KNEE_FRACTION {
                    knee.add(e);
                } else {
                    plateau.add(e);
                }
                thirds[((3.0 * r.time_s[k] / span_s) as usize).min(2)].add(e);
                cols[0].push(e);
                cols[1].push(r.discharged_fraction[k]);
                cols[2].push(d.current_a[k]);
                cols[3].push(r.time_s[k]);
                cols[4].push(d.temperature_at_k(k) - d.ambient_k);
                if k >= w.load_on + 2 * lag && r.fitted[k - lag] && r.fitted[k - 2 * lag] {
                    second_diffs.push((e - 2.0 * r.residual_mv[k - lag] + r.residual_mv[k - 2 * lag]).abs());
                }
            } else if k >= w.load_end {
                relax.add(e);
            }
        }
    }
    second_diffs.sort_by(f64::total_cmp);
    let noise_mv = if second_diffs.is_empty() {
        0.0
    } else {
        // For white noise, a second difference has sd sqrt(6) sigma; the median of |N(0, s)| is 0.6745 s.
        second_diffs[second_diffs.len() / 2] / 0.6745 / 6f64.sqrt()
    };
    Structure {
        under_load: all.part(),
        rest_before: rest.part(),
        load_on: on.part(),
        plateau: plateau.part(),
        knee: knee.part(),
        relaxation: relax.part(),
        thirds: [thirds[0].part(), thirds[1].part(), thirds[2].part()],
        corr_soc: pearson(&cols[0], &cols[1]),
        corr_current: pearson(&cols[0], &cols[2]),
        corr_time: pearson(&cols[0], &cols[3]),
        corr_temperature: pearson(&cols[0], &cols[4]),
        noise_mv,
    }
}

/// Pearson correlation; 0 when either series is constant.
pub fn pearson(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    if n < 2 {
        return 0.0;
    }
    let (ma, mb) = (a[..n].iter().sum::<f64>() / n as f64, b[..n].iter().sum::<f64>() / n as f64);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for k in 0..n {
        let (x, y) = (a[k] - ma, b[k] - mb);
        sab += x * y;
        saa += x * x;
        sbb += y * y;
    }
    if saa <= 0.0 || sbb <= 0.0 {
        0.0
    } else {
        sab / (saa * sbb).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pearson_of_known_series() {
        assert!((pearson(&[1.0, 2.0, 3.0], &[2.0, 4.0, 6.0]) - 1.0).abs() < 1e-12);
        assert!((pearson(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]) + 1.0).abs() < 1e-12);
        assert_eq!(pearson(&[1.0, 1.0], &[1.0, 2.0]), 0.0);
    }

    #[test]
    fn structure_puts_a_knee_error_in_the_knee_and_estimates_noise() {
        let n = 400;
        let time_s: Vec<f64> = (0..n).map(|k| 10.0 * k as f64).collect();
        let current_a: Vec<f64> = (0..n).map(|k| if (2..350).contains(&k) { 2.0 } else { 0.0 }).collect();
        // Deterministic pseudo-noise of sd ~1 mV (alternating signs), plus 20 mV in the last 10 % of the load.
        let noise = |k: usize| if k & 1 == 0 { 1.0 } else { -1.0 } * 1e-3;
        let model_v: Vec<f64> = (0..n).map(|k| 4.0 - 0.002 * k as f64).collect();
        let voltage_v: Vec<f64> =
            (0..n).map(|k| model_v[k] + noise(k) + if (316..350).contains(&k) { 0.02 } else { 0.0 }).collect();
        let d = Discharge {
            cell: "T".into(),
            cycle: 1,
            source: "t.csv".into(),
            ambient_k: 297.15,
            time_s,
            voltage_v,
            current_a,
            temperature_k: None,
            stated_capacity_ah: None,
        };
        let w = d.windows(0.05, 2.0).unwrap();
        let used: Vec<usize> = (w.load_on..w.fit_end).collect();
        let r = record_residual(&d, w, &used, &model_v);
        let s = structure(&[&d], &[r]);
        assert!(s.knee.rmse_mv > 15.0, "{:?}", s.knee);
        assert!(s.plateau.rmse_mv < 2.0, "{:?}", s.plateau);
        assert!(s.corr_soc > 0.3, "{}", s.corr_soc);
        // Alternating +-1 mV has |second difference| 4 mV: the estimator reads 4 / 0.6745 / 2.449 = 2.4 mV.
        assert!(s.noise_mv > 1.0 && s.noise_mv < 3.0, "{}", s.noise_mv);
    }
}
