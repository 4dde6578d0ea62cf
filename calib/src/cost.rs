//! The correction policy's training cost: the calibrated model's error at predicting what comes next
//! (issue 18, item 1). Its optimum is the estimate that predicts the simulated cell's own future best, not
//! any filter's estimate, so a policy has something to learn beyond copying one.
//!
//! From the estimate chosen at a reading (the parameters and the filter's model state given them), the
//! calibrator's model runs forward under the simulated cell's own load (what the simulator knows of the
//! future, as the paper's cost knows the simulated state) in Euler substeps of `substep_s`: its voltage at
//! the readings within `horizon_s` is compared with the cell's noise-free voltage there, and, where the
//! episode reaches the cut-off, the run goes on to the model's own end of discharge, compared with the
//! cell's. The true parameters never enter. Training only: nothing deployed reads the future.

use bcal_common::battery::{BatteryModel, Degradation, Load};
use bcal_common::math::{idx, ModelState};
use bcal_common::measured::env::PredictiveCost;
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::scenario::Episode;

/// The parts of one cost.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CostParts {
    /// RMS of predicted minus true voltage at the readings within the horizon, V (0 when none is ahead).
    pub voltage_rms_v: f64,
    /// Readings the voltage term compared.
    pub readings: usize,
    /// Predicted minus true end of discharge, s (None when the episode never reached the cut-off). A
    /// prediction that never ends within the search counts as the search's length.
    pub eod_error_s: Option<f64>,
    /// The cost: voltage weight ln(1 + rms / voltage scale) + EOD weight ln(1 + |EOD error| / EOD scale).
    pub cost: f64,
}

/// The calibrator's model as its predictions run it: the model at the state's temperature, the factor on
/// Ro there (Arrhenius, 1 without), and the cut-off.
pub struct PredictionModel {
    pub model: BatteryModel,
    pub ro_factor: f64,
    pub cutoff_v: f64,
}

impl PredictionModel {
    /// The extension `ext` at temperature `t_k` (Arrhenius factors against `ref_k`).
    pub fn at(ext: &ModelExtension, t_k: f64, ref_k: f64, cutoff_v: f64) -> Self {
        let (model, ro_factor) = ext.model_at(t_k, ref_k).expect("the config checks the model extension");
        Self { model, ro_factor, cutoff_v }
    }
}

/// The cost of predicting from reading `k` of `episode` with model state `x` and parameters `d` on `m`.
pub fn predictive_cost(
    c: &PredictiveCost,
    m: &PredictionModel,
    episode: &Episode,
    k: usize,
    x: &ModelState,
    d: &Degradation,
) -> CostParts {
    let (model, ro_factor, cutoff_v) = (&m.model, m.ro_factor, m.cutoff_v);
    let samples = &episode.samples;
    let t0 = samples[k].t_s;
    let d = Degradation { r_o_ohm: d.r_o_ohm * ro_factor, ..*d };
    let profile = &episode.spec.profile;
    // How far to run: to the horizon, or past the cell's end of discharge to find the model's.
    let eod = episode.eod_s;
    let run_to = match eod {
        Some(e) => (t0 + c.horizon_s).max(e) + 2.0 * (e - t0).max(0.0) + 600.0,
        None => t0 + c.horizon_s,
    };
    let mut x = *x;
    let mut t = t0;
    let mut j = k + 1;
    let (mut sq, mut n) = (0.0, 0usize);
    let mut model_eod = None;
    loop {
        let h_max = if t - t0 < c.horizon_s { c.substep_s } else { c.eod_substep_s }.max(1e-3);
        let v = model.voltage_v(&x, &d);
        if !v.is_finite() {
            break;
        }
        // The readings passed by now (the next substep ends at a reading, so none is stepped over).
        while j < samples.len() && samples[j].t_s <= t + 1e-9 {
            if samples[j].t_s - t0 <= c.horizon_s + 1e-9 {
                sq += (v - episode.true_voltage_v[j]).powi(2);
                n += 1;
            }
            j += 1;
        }
        if model_eod.is_none() && (v < cutoff_v || model.surface_empty(&x, &d)) {
            model_eod = Some(t);
        }
        let horizon_done = t - t0 >= c.horizon_s || j >= samples.len();
        if horizon_done && (eod.is_none() || model_eod.is_some()) || t >= run_to {
            break;
        }
        // Step to the next reading within the horizon or by a whole substep, whichever comes first.
        let to_reading =
            if j < samples.len() && samples[j].t_s - t0 <= c.horizon_s { samples[j].t_s - t } else { h_max };
        let h = to_reading.clamp(1e-6, h_max);
        let i = match profile.at(t) {
            Load::CurrentA(a) => a,
            Load::PowerW(w) => w / v.max(0.1),
        };
        x = model.step_current(&x, i, h, &d);
        t += h;
    }
    let voltage_rms_v = if n > 0 { (sq / n as f64).sqrt() } else { 0.0 };
    let eod_error_s = eod.map(|e| model_eod.unwrap_or(run_to) - e);
    let mut cost = c.voltage_weight * (voltage_rms_v / c.voltage_scale_v).ln_1p();
    if let Some(err) = eod_error_s {
        cost += c.eod_weight * (err.abs() / c.eod_scale_s).ln_1p();
    }
    CostParts { voltage_rms_v, readings: n, eod_error_s, cost }
}

/// The temperature a model state runs at, K.
pub fn temperature_of(x: &ModelState) -> f64 {
    x[idx::T_B]
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::dataset::Split;
    use bcal_common::measured::scenario::{draw_spec, rest_state, simulate, xn_of_soc, ScenarioConfig};
    use rand::SeedableRng;

    /// From the cell's own state and parameters the prediction is the cell's future: the voltage term is
    /// the difference of a 2 s and a 1 s Euler integration (well under a millivolt) and the end of
    /// discharge within a few substeps; wrong parameters cost more, the further off the more.
    #[test]
    fn the_truth_costs_least_and_the_cost_grows_with_the_error() {
        let cfg = ScenarioConfig { sensor: Default::default(), ..Default::default() };
        let mut rng = rand::rngs::SmallRng::seed_from_u64(21);
        let spec = loop {
            let s = draw_spec(&cfg, Split::Train, &mut rng);
            if s.kind == bcal_common::measured::LoadKind::ConstantPower {
                break s;
            }
        };
        let ep = simulate(&cfg, &spec).unwrap();
        let model = BatteryModel::default();
        let x0 = rest_state(&model, &spec.truth, xn_of_soc(&model.params, spec.soc0), model.params.tb0_k);
        let c = PredictiveCost::default();
        let m = PredictionModel { model: model.clone(), ro_factor: 1.0, cutoff_v: 3.0 };
        let at = |d: &Degradation| {
            let x = rest_state(&model, d, xn_of_soc(&model.params, spec.soc0), model.params.tb0_k);
            predictive_cost(&c, &m, &ep, 0, &x, d)
        };
        // At the simulator's own 1 s step the prediction from the truth IS the cell: the same Euler steps.
        let exact = PredictiveCost { substep_s: 1.0, eod_substep_s: 1.0, ..c.clone() };
        let same = predictive_cost(&exact, &m, &ep, 0, &x0, &spec.truth);
        assert!(same.readings > 0);
        assert!(same.voltage_rms_v < 1e-9 && same.eod_error_s == Some(0.0), "{same:?}");
        // The default's coarser steps cost a few millivolts around the load switch (its 1 s timing falls
        // inside a 2 s substep) and a few of its 5 s steps at the end.
        let truth = predictive_cost(&c, &m, &ep, 0, &x0, &spec.truth);
        assert!(truth.voltage_rms_v < 5e-3, "{truth:?}");
        assert!(truth.eod_error_s.unwrap().abs() <= 2.0 * c.eod_substep_s, "{truth:?}");
        let off =
            |dq: f64, dr: f64| Degradation { q_mobile_c: spec.truth.q_mobile_c + dq, r_o_ohm: spec.truth.r_o_ohm + dr };
        let small = at(&off(100.0, 0.002));
        let large = at(&off(600.0, 0.02));
        assert!(truth.cost < small.cost && small.cost < large.cost, "{truth:?} {small:?} {large:?}");
        // More capacity ends later, more resistance earlier.
        assert!(at(&off(600.0, 0.0)).eod_error_s.unwrap() > 30.0);
        assert!(at(&off(0.0, 0.03)).eod_error_s.unwrap() < -10.0);
    }
}
