//! What a calibrated model predicts for the cell: when the voltage will reach the cut-off under the
//! discharge's load (its current, or its power where it is held at constant power: `bcal_calib::LoadMean`)
//! from the calibrated state now, and the capacity, the charge a full cell delivers under that load down to
//! the cut-off. Each with a 90 % interval from the parameters' interval: the
//! earliest end under (least qMobile, most Ro), the latest under (most qMobile, least Ro), since the end
//! comes sooner with less capacity and more resistance.

use bcal_calib::Interval;
use bcal_calib::{predict_eod, predict_eod_s, EodQuery};
use bcal_common::battery::{BatteryModel, Degradation, Load, LoadProfile};
use bcal_common::math::{idx, ModelState};
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::scenario::rest_state;
use serde::Serialize;

/// Euler step of predictions, s (the reference model's).
pub const PREDICT_DT_S: f64 = 1.0;
/// Longest prediction horizon, s.
pub const PREDICT_MAX_S: f64 = 40_000.0;

/// A prediction with its 90 % interval (None where the calibrator has no interval or a bound fails).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Predicted {
    pub value: Option<f64>,
    pub lo: Option<f64>,
    pub hi: Option<f64>,
}

impl Predicted {
    /// The prediction with `by` added to the value and both bounds.
    pub fn shifted(self, by: f64) -> Self {
        Self { value: self.value.map(|v| v + by), lo: self.lo.map(|v| v + by), hi: self.hi.map(|v| v + by) }
    }
}

/// Bounds in order: near the empty point the corners' ends can swap by a step of the prediction's grid.
fn ordered(lo: Option<f64>, hi: Option<f64>) -> Predicted {
    match (lo, hi) {
        (Some(a), Some(b)) => Predicted { value: None, lo: Some(a.min(b)), hi: Some(a.max(b)) },
        _ => Predicted { value: None, lo, hi },
    }
}

/// The parameter corners that bound the end of discharge: (earliest, latest).
fn corners(iv: &Interval) -> (Degradation, Degradation) {
    (
        Degradation { q_mobile_c: iv.q_mobile_c[0], r_o_ohm: iv.r_o_ohm[1] },
        Degradation { q_mobile_c: iv.q_mobile_c[1], r_o_ohm: iv.r_o_ohm[0] },
    )
}

/// The calibrator's model as predictions run it: its parameters (base or extended) with the rate constants
/// at the cell's temperature now, and the Arrhenius factor on Ro there (1 without the doctor's `thermal`).
/// The calibrator's state already holds Ro's factor in its ohmic lag, so only the dynamics of the
/// prediction apply it.
#[derive(Clone, Debug)]
pub struct Predictor {
    pub model: BatteryModel,
    pub ro_factor: f64,
}

impl Predictor {
    /// The base model, no temperature dependence.
    pub fn base(model: BatteryModel) -> Self {
        Self { model, ro_factor: 1.0 }
    }

    /// `ext`'s model at `t_k` (its Arrhenius reference the extension's, else `t_k` itself).
    pub fn at(ext: &ModelExtension, t_k: f64) -> Self {
        let (model, ro_factor) =
            ext.model_at(t_k, ext.reference_k.unwrap_or(t_k)).expect("model extensions are checked when loaded");
        Self { model, ro_factor }
    }

    fn dynamics(&self, d: &Degradation) -> Degradation {
        Degradation { r_o_ohm: d.r_o_ohm * self.ro_factor, ..*d }
    }

    /// The predicted end of discharge (absolute time, s) from `state(d)` at `t_now_s` under `load`, with
    /// the interval's corners. `state` rebuilds the calibrated state under any parameters.
    pub fn eod(
        &self,
        state: &dyn Fn(&Degradation) -> Option<ModelState>,
        d: &Degradation,
        iv: Option<&Interval>,
        t_now_s: f64,
        load: Load,
        cutoff_v: f64,
    ) -> Predicted {
        let value = self.eod_at(state, d, t_now_s, load, cutoff_v);
        Predicted { value, ..self.eod_bounds(state, iv, t_now_s, load, cutoff_v) }
    }

    fn eod_at(
        &self,
        state: &dyn Fn(&Degradation) -> Option<ModelState>,
        d: &Degradation,
        t_now_s: f64,
        load: Load,
        cutoff_v: f64,
    ) -> Option<f64> {
        let profile = LoadProfile::Constant(load);
        let q = EodQuery { profile: &profile, cutoff_v, dt_s: PREDICT_DT_S, max_s: PREDICT_MAX_S };
        state(d).and_then(|x| predict_eod_s(&self.model, &x, &self.dynamics(d), t_now_s, &q))
    }

    /// Only the interval of [`Predictor::eod`] (value None): the ends under the interval's corners.
    pub fn eod_bounds(
        &self,
        state: &dyn Fn(&Degradation) -> Option<ModelState>,
        iv: Option<&Interval>,
        t_now_s: f64,
        load: Load,
        cutoff_v: f64,
    ) -> Predicted {
        let at = |p: &Degradation| self.eod_at(state, p, t_now_s, load, cutoff_v);
        let (lo, hi) = match iv.map(corners) {
            Some((early, late)) => (at(&early), at(&late)),
            None => (None, None),
        };
        ordered(lo, hi)
    }

    /// The capacity a full cell at rest at `t_k` delivers under `load` down to `cutoff_v` under `d`, Ah.
    pub fn capacity_ah(&self, d: &Degradation, load: Load, cutoff_v: f64, t_k: f64) -> Option<f64> {
        let x0 = rest_state(&self.model, d, self.model.params.xn_max, t_k);
        let profile = LoadProfile::Constant(load);
        let q = EodQuery { profile: &profile, cutoff_v, dt_s: PREDICT_DT_S, max_s: PREDICT_MAX_S };
        match load {
            // Time times current, exactly (a sum of the same steps can differ in its last bits).
            Load::CurrentA(a) => predict_eod_s(&self.model, &x0, &self.dynamics(d), 0.0, &q).map(|t| t * a / 3600.0),
            Load::PowerW(_) => predict_eod(&self.model, &x0, &self.dynamics(d), 0.0, &q).map(|p| p.drawn_c / 3600.0),
        }
    }

    /// The capacity with the interval's corners (least capacity: least qMobile, most Ro).
    pub fn capacity(&self, d: &Degradation, iv: Option<&Interval>, load: Load, cutoff_v: f64, t_k: f64) -> Predicted {
        Predicted { value: self.capacity_ah(d, load, cutoff_v, t_k), ..self.capacity_bounds(iv, load, cutoff_v, t_k) }
    }

    /// Only the interval of [`Predictor::capacity`] (value None).
    pub fn capacity_bounds(&self, iv: Option<&Interval>, load: Load, cutoff_v: f64, t_k: f64) -> Predicted {
        let at = |p: &Degradation| self.capacity_ah(p, load, cutoff_v, t_k);
        let (lo, hi) = match iv.map(corners) {
            Some((small, large)) => (at(&small), at(&large)),
            None => (None, None),
        };
        ordered(lo, hi)
    }
}

/// The temperature the model runs a capacity prediction at: the state's, else the ambient.
pub fn temperature_of(x: Option<&ModelState>, ambient_k: f64) -> f64 {
    x.map_or(ambient_k, |x| x[idx::T_B])
}

#[cfg(test)]
mod tests {
    use super::*;

    const A2: Load = Load::CurrentA(2.0);

    #[test]
    fn capacity_falls_with_qmobile_and_with_resistance_and_the_interval_brackets_it() {
        let m = BatteryModel::default();
        let p = Predictor::base(m.clone());
        let d = Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.15 };
        let c = p.capacity_ah(&d, A2, 3.0, 298.15).unwrap();
        assert!(c > 1.0 && c < 6000.0 / 3600.0, "{c}");
        assert!(p.capacity_ah(&Degradation { q_mobile_c: 5000.0, ..d }, A2, 3.0, 298.15).unwrap() < c);
        assert!(p.capacity_ah(&Degradation { r_o_ohm: 0.25, ..d }, A2, 3.0, 298.15).unwrap() < c);
        let iv = Interval { q_mobile_c: [5800.0, 6200.0], r_o_ohm: [0.14, 0.16] };
        let cap = p.capacity(&d, Some(&iv), A2, 3.0, 298.15);
        assert!(cap.lo.unwrap() < cap.value.unwrap() && cap.value.unwrap() < cap.hi.unwrap(), "{cap:?}");
        // A constant-current discharge from full lasts capacity / current.
        let x0 = |q: &Degradation| Some(rest_state(&m, q, m.params.xn_max, 298.15));
        let e = p.eod(&x0, &d, Some(&iv), 0.0, A2, 3.0);
        assert!((e.value.unwrap() * 2.0 / 3600.0 - c).abs() < 2.0 * 2.0 / 3600.0);
        assert!(e.lo.unwrap() < e.value.unwrap() && e.value.unwrap() < e.hi.unwrap());
        // A warm cell with Arrhenius resistance: less resistance, more capacity at the same current.
        let ext = ModelExtension {
            causes: vec!["thermal".into()],
            ro_activation_k: 4000.0,
            reference_k: Some(298.15),
            ..Default::default()
        };
        let warm = Predictor::at(&ext, 310.0);
        assert!(warm.ro_factor < 1.0);
        assert!(
            warm.capacity_ah(&Degradation { r_o_ohm: 0.25, ..d }, A2, 3.0, 298.15).unwrap()
                > p.capacity_ah(&Degradation { r_o_ohm: 0.25, ..d }, A2, 3.0, 298.15).unwrap()
        );
    }
}
