//! The model extensions a calibrator's own model can carry: the doctor's ageing causes (`bcal diagnose`
//! names them, `bcal calibrate --model diagnosis.json` loads them). `electrode_balance` (the positive and
//! negative electrodes' mole fractions at full charge shifted) and `charge_transfer` (one factor on both
//! Butler-Volmer rate constants) are parameters of the base model ([`BatteryParams::aged`]); `thermal`
//! (Arrhenius temperature dependence of Ro and of the rate constants, driven by the measured temperature)
//! is a factor on each at the cell's temperature; `diffusion` is the base model's diffusion time; `ocv` is an
//! additive correction of the open-circuit curve ([`crate::battery::ocv_correction_v`]). Neutral
//! values are the base model. The simulated cells, the RL calibrator's tracker and the joint UKF all build
//! their model here, so a policy and a filter run the model the doctor chose.

use crate::battery::{BatteryModel, BatteryParams};
use serde::{Deserialize, Serialize};

/// Temperatures the model is taken at, K (exclusive): a cell's ambient and its extensions' reference.
pub const TEMPERATURE_RANGE_K: [f64; 2] = [200.0, 400.0];

/// The doctor's causes a calibrator's model can carry; the others (a sensor offset or gain, an extra RC
/// branch) change the measurement or add a state, and are the doctor's alone.
pub const SUPPORTED_CAUSES: [&str; 5] = ["electrode_balance", "charge_transfer", "thermal", "diffusion", "ocv"];

/// A calibrator's model beyond the base one.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelExtension {
    /// The doctor's causes this model holds, by name, in the doctor's order (empty: the base model). A
    /// policy trained on one model is refused for a model with other causes.
    pub causes: Vec<String>,
    /// Shift of the positive electrode's mole fraction at full charge (xp_min), added to the base 0.4.
    pub xp_shift: f64,
    /// Shift of the negative electrode's mole fraction at full charge (xn_max), added to the base 0.6.
    pub xn_shift: f64,
    /// Factor on both Butler-Volmer rate constants kn and kp (below 1: slower charge transfer).
    pub kinetics_scale: f64,
    /// Arrhenius activation temperature of Ro, Ea/R, K: Ro(T) = Ro exp(a (1/T - 1/T_ref)).
    pub ro_activation_k: f64,
    /// Arrhenius activation temperature of the rate constants, K: k(T) = k exp(-b (1/T - 1/T_ref)).
    pub kinetics_activation_k: f64,
    /// Bulk-surface diffusion time constant, s (the base model's 7e6).
    pub t_diffusion_s: f64,
    /// Legendre coefficients of the additive OCV correction, V (the doctor's `ocv_p1_v` .. `ocv_p3_v`; 0: the
    /// base curve).
    pub ocv_legendre_v: [f64; 3],
    /// The cell's ambient, K: where the Arrhenius factors are 1 and the temperature an isothermal model runs
    /// at (the doctor's: the record's ambient). None: the Arrhenius reference is the first reading's
    /// temperature (a cell at rest in its ambient) and an isothermal model runs at the base 292.1 K.
    pub reference_k: Option<f64>,
}

impl Default for ModelExtension {
    fn default() -> Self {
        Self {
            causes: Vec::new(),
            xp_shift: 0.0,
            xn_shift: 0.0,
            kinetics_scale: 1.0,
            ro_activation_k: 0.0,
            kinetics_activation_k: 0.0,
            t_diffusion_s: BatteryParams::default().t_diffusion_s,
            ocv_legendre_v: [0.0; 3],
            reference_k: None,
        }
    }
}

impl ModelExtension {
    /// The base model's parameters with this extension (at the reference temperature, when there is one).
    pub fn params(&self) -> BatteryParams {
        let base = BatteryParams::default();
        BatteryParams {
            t_diffusion_s: self.t_diffusion_s,
            tb0_k: self.reference_k.unwrap_or(base.tb0_k),
            ocv_legendre_v: self.ocv_legendre_v,
            ..base.aged(self.xp_shift, self.xn_shift, self.kinetics_scale)
        }
    }

    /// Whether the doctor named `cause` for this model.
    pub fn has(&self, cause: &str) -> bool {
        self.causes.iter().any(|c| c == cause)
    }

    /// The isothermal model of a calibrator (its temperature is the state's, set from the readings).
    pub fn model(&self) -> Result<BatteryModel, crate::battery::ModelError> {
        BatteryModel::new(self.params(), false)
    }

    /// Whether any Arrhenius factor differs from 1.
    pub fn temperature_dependent(&self) -> bool {
        self.ro_activation_k != 0.0 || self.kinetics_activation_k != 0.0
    }

    /// The Arrhenius factors (Ro, rate constants) at `t_k` against the reference `ref_k`.
    #[inline]
    pub fn factors(&self, t_k: f64, ref_k: f64) -> (f64, f64) {
        if !(self.temperature_dependent() && t_k > 0.0 && ref_k > 0.0) {
            return (1.0, 1.0);
        }
        let inv = 1.0 / t_k - 1.0 / ref_k;
        ((self.ro_activation_k * inv).exp(), (-self.kinetics_activation_k * inv).exp())
    }

    /// Sets `model`'s rate constants to this extension's at `t_k` and returns the Ro factor there.
    #[inline]
    pub fn apply_at(&self, model: &mut BatteryModel, base_kn_kp: (f64, f64), t_k: f64, ref_k: f64) -> f64 {
        let (ro, kin) = self.factors(t_k, ref_k);
        model.params.kn = base_kn_kp.0 * kin;
        model.params.kp = base_kn_kp.1 * kin;
        ro
    }

    /// The calibrator's model as a prediction runs it at `t_k`: its rate constants there, and the factor on
    /// Ro there (against the reference `ref_k`).
    pub fn model_at(&self, t_k: f64, ref_k: f64) -> Result<(BatteryModel, f64), crate::battery::ModelError> {
        let mut model = self.model()?;
        let kn_kp = (model.params.kn, model.params.kp);
        let ro_factor = self.apply_at(&mut model, kn_kp, t_k, ref_k);
        Ok((model, ro_factor))
    }

    /// Checks the values: what the model can run, named as the config names them under `key`.
    pub fn check(&self, key: &str) -> Result<(), String> {
        for c in &self.causes {
            if !SUPPORTED_CAUSES.contains(&c.as_str()) {
                return Err(format!(
                    "{key}.causes: `{c}` is not a cause a calibrator's model can carry (it can: {})",
                    SUPPORTED_CAUSES.join(", ")
                ));
            }
        }
        let finite = [
            self.xp_shift,
            self.xn_shift,
            self.kinetics_scale,
            self.ro_activation_k,
            self.kinetics_activation_k,
            self.t_diffusion_s,
            self.ocv_legendre_v[0],
            self.ocv_legendre_v[1],
            self.ocv_legendre_v[2],
        ];
        if finite.iter().any(|v| !v.is_finite()) {
            return Err(format!("{key}: every value must be finite"));
        }
        if !(self.kinetics_scale > 0.0 && self.t_diffusion_s > 0.0) {
            return Err(format!("{key}: kinetics_scale and t_diffusion_s must be > 0"));
        }
        if self.ro_activation_k < 0.0 || self.kinetics_activation_k < 0.0 {
            return Err(format!("{key}: activation temperatures must be >= 0"));
        }
        if let Some(r) = self.reference_k {
            let [lo, hi] = TEMPERATURE_RANGE_K;
            if !(r.is_finite() && r > lo && r < hi) {
                return Err(format!("{key}.reference_k = {r}: must be a temperature in K ({lo}-{hi})"));
            }
        }
        self.model().map(|_| ()).map_err(|e| format!("{key}: {e}"))
    }

    /// Whether `other` has the same causes (a policy trained on one runs on the other).
    pub fn same_kind(&self, other: &ModelExtension) -> bool {
        let set = |m: &ModelExtension| {
            let mut v = m.causes.clone();
            v.sort();
            v
        };
        set(self) == set(other)
    }

    /// The causes as the report names them ("base" without any).
    pub fn label(&self) -> String {
        if self.causes.is_empty() {
            "base".into()
        } else {
            format!("base + {}", self.causes.join(" + "))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn neutral_is_the_base_model_and_factors_follow_arrhenius() {
        let e = ModelExtension::default();
        assert_eq!(e.params(), BatteryParams::default());
        let at = ModelExtension { reference_k: Some(297.15), ..Default::default() };
        assert_eq!(at.params(), BatteryParams { tb0_k: 297.15, ..BatteryParams::default() });
        assert_eq!(e.factors(310.0, 297.15), (1.0, 1.0));
        let t = ModelExtension { ro_activation_k: 4000.0, kinetics_activation_k: 500.0, ..Default::default() };
        let (ro, kin) = t.factors(310.0, 297.15);
        // Warmer: less resistance, faster kinetics.
        assert!(ro < 1.0 && kin > 1.0, "{ro} {kin}");
        assert!((ro - (4000.0 * (1.0 / 310.0 - 1.0 / 297.15f64)).exp()).abs() < 1e-15);
        assert_eq!(t.factors(297.15, 297.15), (1.0, 1.0));
        let aged = ModelExtension { xp_shift: 0.05, xn_shift: -0.1, kinetics_scale: 0.2, ..Default::default() };
        let p = aged.params();
        let b = BatteryParams::default();
        assert!((p.xp_min - (b.xp_min + 0.05)).abs() < 1e-15 && (p.xn_max - (b.xn_max - 0.1)).abs() < 1e-15);
        assert!((p.kn - 0.2 * b.kn).abs() < 1e-9 && (p.kp - 0.2 * b.kp).abs() < 1e-6);
        assert!(aged.check("m").is_ok());
        let bad = ModelExtension { causes: vec!["voltage_offset".into()], ..Default::default() };
        assert!(bad.check("m").unwrap_err().contains("voltage_offset"));
        let a = ModelExtension { causes: vec!["thermal".into(), "electrode_balance".into()], ..Default::default() };
        let b = ModelExtension { causes: vec!["electrode_balance".into(), "thermal".into()], ..Default::default() };
        assert!(a.same_kind(&b) && !a.same_kind(&ModelExtension::default()));
    }
}
