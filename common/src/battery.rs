//! The NASA prognostics Li-ion electrochemistry model (Daigle & Kulkarni 2013), as progpy's
//! `BatteryElectroChemEOD` implements it, stepped by explicit Euler.
//!
//! This is the hot loop of everything (data generation, environments, UKF sigma points, the doctor's fits):
//! it never allocates per step and works on fixed-size [`ModelState`] vectors. The degradation parameters
//! (`q_mobile_c`, `r_o_ohm`) are passed to every call rather than stored, because calibrators change them at
//! every step; the quantities derived from them cost one division.
//!
//! Fidelity: every expression follows progpy's `dx` / `output` term by term; tests hold the reference
//! table of the foundation issue to 1e-9 V. The one deliberate addition is the clip of the surface mole
//! fractions to [0.01, 0.99] inside the potentials and the Butler-Volmer terms, which keeps the logarithms
//! and square roots finite when a calibrator proposes an extreme capacity.

use crate::math::{idx, ModelState};
use serde::{Deserialize, Serialize};

/// Universal gas constant, J/(mol K) (progpy's value).
pub const GAS_CONSTANT: f64 = 8.3144621;
/// Faraday's constant, C/mol (progpy's value).
pub const FARADAY: f64 = 96487.0;

/// Lower and upper clip of the surface mole fractions inside potentials and kinetics.
pub const MOLE_FRACTION_CLIP: (f64, f64) = (0.01, 0.99);

/// The two degradation parameters the calibrators track.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Degradation {
    /// Mobile lithium charge qMobile, C. Default 7600 C (new cell).
    pub q_mobile_c: f64,
    /// Lumped ohmic resistance Ro, ohm. Default 0.117215 ohm (new cell).
    pub r_o_ohm: f64,
}

impl Default for Degradation {
    fn default() -> Self {
        Self { q_mobile_c: 7600.0, r_o_ohm: 0.117215 }
    }
}

/// Fixed electrochemical parameters (everything but the degradation parameters). Defaults are progpy's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BatteryParams {
    /// Maximum mole fraction, negative electrode. Default 0.6.
    pub xn_max: f64,
    /// Minimum mole fraction, negative electrode. Default 0.
    pub xn_min: f64,
    /// Maximum mole fraction, positive electrode. Default 1.0.
    pub xp_max: f64,
    /// Minimum mole fraction, positive electrode. Default 0.4.
    pub xp_min: f64,
    /// Butler-Volmer transfer coefficient. Default 0.5.
    pub alpha: f64,
    /// Surface area, negative electrode, m^2. Default 0.000437545.
    pub sn_m2: f64,
    /// Surface area, positive electrode, m^2. Default 0.00030962.
    pub sp_m2: f64,
    /// Lumped Butler-Volmer rate constant, negative electrode. Default 2120.96.
    pub kn: f64,
    /// Lumped Butler-Volmer rate constant, positive electrode. Default 248898.
    pub kp: f64,
    /// Interior volume of one electrode, m^3. Default 2e-5.
    pub vol_m3: f64,
    /// Fraction of the volume that is surface. Default 0.1.
    pub vol_s_fraction: f64,
    /// Bulk-surface diffusion time constant, s. Default 7e6.
    pub t_diffusion_s: f64,
    /// Ohmic voltage time constant, s. Default 6.08671.
    pub t_o_s: f64,
    /// Surface overpotential time constant, negative electrode, s. Default 1001.38.
    pub t_sn_s: f64,
    /// Surface overpotential time constant, positive electrode, s. Default 46.4311.
    pub t_sp_s: f64,
    /// Reference potential, positive electrode, V. Default 4.03.
    pub u0p_v: f64,
    /// Redlich-Kister coefficients, positive electrode, J/mol.
    pub ap: [f64; 13],
    /// Reference potential, negative electrode, V. Default 0.01.
    pub u0n_v: f64,
    /// Redlich-Kister coefficients, negative electrode, J/mol.
    pub an: [f64; 13],
    /// End-of-discharge voltage, V. Default 3.0.
    pub v_eod_v: f64,
    /// Initial (and ambient) bulk temperature, K. Default 292.1.
    pub tb0_k: f64,
    /// Lumped heat capacity used by the thermal option, J/K. Default 37.04.
    pub mc_j_per_k: f64,
    /// Heat-exchange time constant of the thermal option, s. Default 100.
    pub tau_thermal_s: f64,
    /// Legendre coefficients (degrees 1, 2, 3) of an additive correction of the positive electrode's
    /// equilibrium potential, V ([`ocv_correction_v`]; the doctor's `ocv` cause). Default 0: progpy's curve.
    #[serde(default, skip_serializing_if = "is_neutral_ocv")]
    pub ocv_legendre_v: [f64; 3],
}

fn is_neutral_ocv(c: &[f64; 3]) -> bool {
    *c == [0.0; 3]
}

/// The positive electrode's mole-fraction window an OCV correction is normalised on (the base model's xp_min and
/// xp_max): the correction is a property of the material, so an electrode-balance shift does not move it.
pub const OCV_CORRECTION_XP_WINDOW: [f64; 2] = [0.4, 1.0];

/// An additive OCV correction at the positive electrode's surface mole fraction `xp_s`, V: the Legendre series
/// `c[0] P1(s) + c[1] P2(s) + c[2] P3(s)` with s = 2 z - 1 and z = `xp_s` normalised on
/// [`OCV_CORRECTION_XP_WINDOW`] (clamped to it). One formula for the doctor's fit and the calibrators' model.
#[inline]
pub fn ocv_correction_v(c: &[f64; 3], xp_s: f64) -> f64 {
    let [lo, hi] = OCV_CORRECTION_XP_WINDOW;
    legendre_correction_v(c, ((xp_s - lo) / (hi - lo)).clamp(0.0, 1.0))
}

/// The Legendre series of [`ocv_correction_v`] at the normalised coordinate `z` in [0, 1], V.
#[inline]
pub fn legendre_correction_v(c: &[f64; 3], z: f64) -> f64 {
    let s = 2.0 * z - 1.0;
    c[0] * s + c[1] * 0.5 * (3.0 * s * s - 1.0) + c[2] * 0.5 * (5.0 * s * s * s - 3.0 * s)
}

impl Default for BatteryParams {
    fn default() -> Self {
        Self {
            xn_max: 0.6,
            xn_min: 0.0,
            xp_max: 1.0,
            xp_min: 0.4,
            alpha: 0.5,
            sn_m2: 0.000437545,
            sp_m2: 0.00030962,
            kn: 2120.96,
            kp: 248898.0,
            vol_m3: 2e-5,
            vol_s_fraction: 0.1,
            t_diffusion_s: 7e6,
            t_o_s: 6.08671,
            t_sn_s: 1001.38,
            t_sp_s: 46.4311,
            u0p_v: 4.03,
            ap: [
                -31593.7, 0.106747, 24606.4, -78561.9, 13317.9, 307387.0, 84916.1, -1.07469e6, 2285.04, 990894.0,
                283920.0, -161513.0, -469218.0,
            ],
            u0n_v: 0.01,
            an: [86.19, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            v_eod_v: 3.0,
            tb0_k: 292.1,
            mc_j_per_k: 37.04,
            tau_thermal_s: 100.0,
            ocv_legendre_v: [0.0; 3],
        }
    }
}

impl BatteryParams {
    /// These parameters with the electrode balance shifted (xp_min and xn_max, the mole fractions at full
    /// charge) and both Butler-Volmer rate constants scaled: the doctor's per-cycle ageing causes
    /// `electrode_balance` and `charge_transfer`, in the one place that maps them onto the model.
    pub fn aged(&self, xp_shift: f64, xn_shift: f64, kinetics_scale: f64) -> Self {
        Self {
            xp_min: self.xp_min + xp_shift,
            xn_max: self.xn_max + xn_shift,
            kn: self.kn * kinetics_scale,
            kp: self.kp * kinetics_scale,
            ..self.clone()
        }
    }
}

/// Errors of model construction and simulation.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ModelError {
    #[error("battery parameter `{name}` = {value} is invalid: {why}")]
    BadParam { name: &'static str, value: f64, why: &'static str },
    #[error("the voltage became {voltage_v} V at t = {t_s} s under a power load: current = P / V is undefined; use a smaller load or a current input")]
    NonPositiveVoltage { t_s: f64, voltage_v: f64 },
    #[error("the state became non-finite at t = {t_s} s; the parameters or the load are outside the model's range")]
    NonFinite { t_s: f64 },
}

/// The load drawn from the cell over one step.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Load {
    /// Constant power, W; the current is P / V(x_t) at the start of each step (the paper's input).
    PowerW(f64),
    /// Current, A, positive while discharging (measured data are current-controlled).
    CurrentA(f64),
}

/// A load over time: constant, or piecewise constant with each segment starting at `start_s`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum LoadProfile {
    Constant(Load),
    /// Segments sorted by start time; the first must start at 0 s. The last one holds to the end.
    Piecewise(Vec<(f64, Load)>),
}

impl LoadProfile {
    /// The load in force at time `t_s`.
    #[inline]
    pub fn at(&self, t_s: f64) -> Load {
        match self {
            LoadProfile::Constant(l) => *l,
            LoadProfile::Piecewise(segs) => {
                // Segments are few (a handful per discharge): a reverse scan beats a binary search here.
                segs.iter().rev().find(|(start_s, _)| *start_s <= t_s).map_or(segs[0].1, |s| s.1)
            }
        }
    }
}

/// One simulated step: the state at `t_s`, its voltage, and the current drawn during the following step.
#[derive(Clone, Copy, Debug)]
pub struct StepRecord {
    pub step: usize,
    pub t_s: f64,
    pub x: ModelState,
    pub voltage_v: f64,
    /// Current drawn over [t, t + dt): P / V for a power load. Zero on the final (below-EOD) row.
    pub current_a: f64,
    /// The load in force at `t_s`.
    pub load: Load,
}

/// Summary of a simulation run to end of discharge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EodOutcome {
    /// Time of the first step whose voltage is below VEOD, s; `None` if `max_steps` came first.
    pub eod_s: Option<f64>,
    /// Steps recorded (rows), including t = 0 and the EOD row.
    pub rows: usize,
}

/// The battery model: fixed parameters plus the isothermal/thermal choice.
#[derive(Clone, Debug, PartialEq)]
pub struct BatteryModel {
    pub params: BatteryParams,
    /// When on, the bulk temperature follows progpy's heat balance; when off it stays at `tb0_k`.
    pub thermal: bool,
    // Derived once from `params` (progpy's param callbacks), constant for every degradation.
    vol_s_m3: f64,
    vol_b_m3: f64,
    x_span: f64,
}

impl Default for BatteryModel {
    fn default() -> Self {
        Self::new(BatteryParams::default(), false).expect("default parameters are valid")
    }
}

impl BatteryModel {
    /// Validates `params` once and derives the constant volumes.
    pub fn new(params: BatteryParams, thermal: bool) -> Result<Self, ModelError> {
        let positive: [(&'static str, f64); 15] = [
            ("alpha", params.alpha),
            ("sn_m2", params.sn_m2),
            ("sp_m2", params.sp_m2),
            ("kn", params.kn),
            ("kp", params.kp),
            ("vol_m3", params.vol_m3),
            ("vol_s_fraction", params.vol_s_fraction),
            ("t_diffusion_s", params.t_diffusion_s),
            ("t_o_s", params.t_o_s),
            ("t_sn_s", params.t_sn_s),
            ("t_sp_s", params.t_sp_s),
            ("v_eod_v", params.v_eod_v),
            ("tb0_k", params.tb0_k),
            ("mc_j_per_k", params.mc_j_per_k),
            ("tau_thermal_s", params.tau_thermal_s),
        ];
        for (name, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return Err(ModelError::BadParam { name, value, why: "must be finite and > 0" });
            }
        }
        if let Some(c) = params.ocv_legendre_v.iter().find(|c| !c.is_finite()) {
            return Err(ModelError::BadParam { name: "ocv_legendre_v", value: *c, why: "must be finite" });
        }
        if params.vol_s_fraction >= 1.0 {
            return Err(ModelError::BadParam {
                name: "vol_s_fraction",
                value: params.vol_s_fraction,
                why: "must be < 1",
            });
        }
        if params.xn_max.partial_cmp(&params.xn_min) != Some(std::cmp::Ordering::Greater) {
            return Err(ModelError::BadParam { name: "xn_max", value: params.xn_max, why: "must exceed xn_min" });
        }
        if params.xp_max.partial_cmp(&params.xp_min) != Some(std::cmp::Ordering::Greater) {
            return Err(ModelError::BadParam { name: "xp_max", value: params.xp_max, why: "must exceed xp_min" });
        }
        for v in params.ap.iter().chain(params.an.iter()).chain([params.u0p_v, params.u0n_v].iter()) {
            if !v.is_finite() {
                return Err(ModelError::BadParam { name: "ap/an/u0", value: *v, why: "must be finite" });
            }
        }
        Ok(Self {
            vol_s_m3: params.vol_s_fraction * params.vol_m3,
            vol_b_m3: params.vol_m3 * (1.0 - params.vol_s_fraction),
            x_span: params.xn_max - params.xn_min,
            params,
            thermal,
        })
    }

    /// Checks a degradation before it is used for a whole run (the per-step path does not re-check).
    pub fn check_degradation(&self, d: &Degradation) -> Result<(), ModelError> {
        if !(d.q_mobile_c.is_finite() && d.q_mobile_c > 0.0) {
            return Err(ModelError::BadParam {
                name: "q_mobile_c",
                value: d.q_mobile_c,
                why: "must be finite and > 0",
            });
        }
        if !(d.r_o_ohm.is_finite() && d.r_o_ohm >= 0.0) {
            return Err(ModelError::BadParam { name: "r_o_ohm", value: d.r_o_ohm, why: "must be finite and >= 0" });
        }
        Ok(())
    }

    /// qMax = qMobile / (xnMax - xnMin), C.
    #[inline]
    pub fn q_max_c(&self, d: &Degradation) -> f64 {
        d.q_mobile_c / self.x_span
    }

    /// Surface charge capacity qSMax = qMax * VolSFraction, C.
    #[inline]
    fn q_s_max_c(&self, d: &Degradation) -> f64 {
        self.q_max_c(d) * self.params.vol_s_fraction
    }

    /// progpy's x0: positive electrode at xpMin, negative at xnMax, split surface/bulk by VolSFraction,
    /// overpotentials zero, temperature tb0.
    pub fn initial_state(&self, d: &Degradation) -> ModelState {
        let p = &self.params;
        let q_max = self.q_max_c(d);
        let mut x = ModelState::zeros();
        x[idx::QP_S] = q_max * p.xp_min * p.vol_s_fraction;
        x[idx::QP_B] = q_max * p.xp_min * (1.0 - p.vol_s_fraction);
        x[idx::QN_B] = q_max * p.xn_max * (1.0 - p.vol_s_fraction);
        x[idx::QN_S] = q_max * p.xn_max * p.vol_s_fraction;
        x[idx::T_B] = p.tb0_k;
        x
    }

    /// Whether an electrode's surface mole fraction has reached its clip ([`MOLE_FRACTION_CLIP`]): the model
    /// is empty there and its voltage stops falling (about 3.0 V at 2 A), while a real cell drops through
    /// its knee to any lower cut-off within a minute or two.
    #[inline]
    pub fn surface_empty(&self, x: &ModelState, d: &Degradation) -> bool {
        let (lo, hi) = MOLE_FRACTION_CLIP;
        let q_s_max = self.q_s_max_c(d);
        x[idx::QN_S] / q_s_max <= lo || x[idx::QP_S] / q_s_max >= hi
    }

    /// Terminal voltage V = Vep - Ven - Vo - Vsn - Vsp, V (progpy `output`).
    #[inline]
    pub fn voltage_v(&self, x: &ModelState, d: &Degradation) -> f64 {
        let (vep, ven) = self.electrode_potentials_v(x, d);
        vep - ven - x[idx::V_O] - x[idx::V_SN] - x[idx::V_SP]
    }

    /// Equilibrium potentials (Vep, Ven) at the current surface mole fractions, V.
    #[inline]
    pub fn electrode_potentials_v(&self, x: &ModelState, d: &Degradation) -> (f64, f64) {
        let p = &self.params;
        let q_s_max = self.q_s_max_c(d);
        let xn_s = clip_mole_fraction(x[idx::QN_S] / q_s_max);
        let xp_s = clip_mole_fraction(x[idx::QP_S] / q_s_max);
        let rt_f = GAS_CONSTANT * x[idx::T_B] / FARADAY;
        let ven = p.u0n_v + rt_f * ((1.0 - xn_s) / xn_s).ln() + redlich_kister(&p.an, xn_s);
        let mut vep = p.u0p_v + rt_f * ((1.0 - xp_s) / xp_s).ln() + redlich_kister(&p.ap, xp_s);
        if p.ocv_legendre_v != [0.0; 3] {
            // On the unclipped fraction, as the doctor fits it (the window's clamp bounds it).
            vep += ocv_correction_v(&p.ocv_legendre_v, x[idx::QP_S] / q_s_max);
        }
        (vep, ven)
    }

    /// Time derivative of the state at current `current_a` (progpy `dx`).
    #[inline]
    pub fn derivative(&self, x: &ModelState, current_a: f64, d: &Degradation) -> ModelState {
        let p = &self.params;
        let q_s_max = self.q_s_max_c(d);
        let i = current_a;

        // Negative electrode: bulk -> surface diffusion, Butler-Volmer overpotential.
        let xn_s = clip_mole_fraction(x[idx::QN_S] / q_s_max);
        let diff_n = (x[idx::QN_B] / self.vol_b_m3 - x[idx::QN_S] / self.vol_s_m3) / p.t_diffusion_s;
        let jn = i / p.sn_m2;
        let jn0 = p.kn * pow_alpha((1.0 - xn_s) * xn_s, p.alpha);
        let v_part = GAS_CONSTANT / FARADAY * x[idx::T_B] / p.alpha;
        let vsn_nominal = v_part * asinh(jn / (jn0 + jn0));

        // Positive electrode.
        let xp_s = clip_mole_fraction(x[idx::QP_S] / q_s_max);
        let diff_p = (x[idx::QP_B] / self.vol_b_m3 - x[idx::QP_S] / self.vol_s_m3) / p.t_diffusion_s;
        let jp = i / p.sp_m2;
        let jp0 = p.kp * pow_alpha((1.0 - xp_s) * xp_s, p.alpha);
        let vsp_nominal = v_part * asinh(jp / (jp0 + jp0));

        let vo_nominal = i * d.r_o_ohm;

        let mut dx = ModelState::zeros();
        dx[idx::QP_S] = i + diff_p;
        dx[idx::QP_B] = -diff_p;
        dx[idx::QN_B] = -diff_n;
        dx[idx::QN_S] = diff_n - i;
        dx[idx::V_O] = (vo_nominal - x[idx::V_O]) / p.t_o_s;
        dx[idx::V_SN] = (vsn_nominal - x[idx::V_SN]) / p.t_sn_s;
        dx[idx::V_SP] = (vsp_nominal - x[idx::V_SP]) / p.t_sp_s;
        if self.thermal {
            let voltage_eta = x[idx::V_O] + x[idx::V_SN] + x[idx::V_SP];
            dx[idx::T_B] = voltage_eta * i / p.mc_j_per_k + (p.tb0_k - x[idx::T_B]) / p.tau_thermal_s;
        }
        dx
    }

    /// One explicit Euler step at current `current_a` for `dt_s`, with progpy's state limits
    /// (charges and temperature never negative).
    #[inline]
    pub fn step_current(&self, x: &ModelState, current_a: f64, dt_s: f64, d: &Degradation) -> ModelState {
        let mut next = x + self.derivative(x, current_a, d) * dt_s;
        for k in [idx::QP_S, idx::QP_B, idx::QN_B, idx::QN_S, idx::T_B] {
            next[k] = next[k].max(0.0);
        }
        next
    }

    /// The current drawn at state `x` under `load`, A: P / V(x) for a power load.
    #[inline]
    pub fn current_a(&self, x: &ModelState, load: Load, d: &Degradation) -> f64 {
        match load {
            Load::CurrentA(i) => i,
            Load::PowerW(p_w) => p_w / self.voltage_v(x, d),
        }
    }

    /// One Euler step under any load; returns the next state and the current used.
    #[inline]
    pub fn step(&self, x: &ModelState, load: Load, dt_s: f64, d: &Degradation) -> (ModelState, f64) {
        let i = self.current_a(x, load, d);
        (self.step_current(x, i, dt_s, d), i)
    }

    /// Simulates from `x0` until the first step whose voltage is below VEOD (that row included), calling
    /// `on_step` for every row from t = 0. Stops early (eod_s = None) after `max_steps` steps.
    pub fn simulate_until_eod(
        &self,
        x0: &ModelState,
        d: &Degradation,
        profile: &LoadProfile,
        dt_s: f64,
        max_steps: usize,
        mut on_step: impl FnMut(&StepRecord),
    ) -> Result<EodOutcome, ModelError> {
        self.check_degradation(d)?;
        if !(dt_s.is_finite() && dt_s > 0.0) {
            return Err(ModelError::BadParam { name: "dt_s", value: dt_s, why: "must be finite and > 0" });
        }
        let mut x = *x0;
        for step in 0..=max_steps {
            let t_s = step as f64 * dt_s;
            let voltage_v = self.voltage_v(&x, d);
            if !voltage_v.is_finite() || x.iter().any(|v| !v.is_finite()) {
                return Err(ModelError::NonFinite { t_s });
            }
            let load = profile.at(t_s);
            if voltage_v < self.params.v_eod_v {
                on_step(&StepRecord { step, t_s, x, voltage_v, current_a: 0.0, load });
                return Ok(EodOutcome { eod_s: Some(t_s), rows: step + 1 });
            }
            let current_a = match load {
                Load::CurrentA(i) => i,
                Load::PowerW(p_w) => {
                    if voltage_v <= 0.0 {
                        return Err(ModelError::NonPositiveVoltage { t_s, voltage_v });
                    }
                    p_w / voltage_v
                }
            };
            on_step(&StepRecord { step, t_s, x, voltage_v, current_a, load });
            if step == max_steps {
                break;
            }
            x = self.step_current(&x, current_a, dt_s, d);
        }
        Ok(EodOutcome { eod_s: None, rows: max_steps + 1 })
    }
}

#[inline]
fn clip_mole_fraction(x: f64) -> f64 {
    x.clamp(MOLE_FRACTION_CLIP.0, MOLE_FRACTION_CLIP.1)
}

extern "C" {
    /// The C library's asinh (C99), the one numpy's `arcsinh` (progpy's) calls where it has no SIMD kernel.
    #[link_name = "asinh"]
    fn libm_asinh(x: f64) -> f64;
}

/// asinh through the C library: within a few ulps of `f64::asinh` (the test holds 4), which goes through
/// `hypot` and `log1p`, the dearest part of a model step (two asinh each); `bcal bench` measures the gain.
#[inline]
fn asinh(x: f64) -> f64 {
    // SAFETY: a pure C99 function of one double, defined for every input (NaN in, NaN out).
    unsafe { libm_asinh(x) }
}

/// `v^alpha`; the default alpha of 0.5 takes the exact square root (at most one ulp from `powf`).
#[inline]
fn pow_alpha(v: f64, alpha: f64) -> f64 {
    if alpha == 0.5 {
        v.sqrt()
    } else {
        v.powf(alpha)
    }
}

/// Redlich-Kister excess potential: sum_k A_k / F * ((2x-1)^(k+1) - 2 k x (1-x) (2x-1)^(k-1)), V.
#[inline]
fn redlich_kister(a: &[f64; 13], x: f64) -> f64 {
    let y = x + x - 1.0;
    let two_x_one_minus_x = 2.0 * x * (1.0 - x);
    let mut sum = a[0] * y;
    // pow_km1 = y^(k-1), pow_kp1 = y^(k+1), advanced incrementally (no powi in the loop).
    let mut pow_km1 = 1.0;
    let mut pow_kp1 = y * y;
    for (k, ak) in a.iter().enumerate().skip(1) {
        if *ak != 0.0 {
            sum += ak * (pow_kp1 - k as f64 * two_x_one_minus_x * pow_km1);
        }
        pow_km1 *= y;
        pow_kp1 *= y;
    }
    sum / FARADAY
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::electro;

    /// The C library's asinh is the standard one to a few ulps for |x| up to 200 (a Butler-Volmer argument
    /// j / 2 j0 of 200 is an overpotential of (RT / alpha F) asinh(200), about 0.3 V at 25 C, beyond those of
    /// a discharge) and at the extremes, odd, and exact at 0.
    #[test]
    fn asinh_is_the_standard_one_to_a_few_ulps() {
        let mut worst = 0f64;
        for k in -200_000..=200_000 {
            let x = f64::from(k) * 1e-3 * (1.0 + 1e-7 * f64::from(k).abs());
            let (got, want) = (asinh(x), x.asinh());
            assert_eq!(asinh(-x), -got, "odd at {x}");
            if want != 0.0 {
                worst = worst.max(((got - want) / want).abs());
            }
        }
        for x in [1e-300, 1e-12, 3e-5, 1e8, 1e200] {
            assert!((asinh(x) - x.asinh()).abs() <= 4.0 * f64::EPSILON * x.asinh().abs(), "{x}");
        }
        assert_eq!(asinh(0.0), 0.0);
        assert!(asinh(f64::NAN).is_nan());
        assert!(worst <= 4.0 * f64::EPSILON, "largest relative gap {worst:e}");
    }

    /// Runs the paper's constant-power discharge and returns (voltages, state at t = 100 s, EOD time).
    fn run(q_mobile_c: f64, r_o_ohm: f64, load_w: f64) -> (Vec<f64>, ModelState, f64) {
        let m = BatteryModel::default();
        let d = Degradation { q_mobile_c, r_o_ohm };
        let mut volts = Vec::new();
        let mut x100 = ModelState::zeros();
        let out = m
            .simulate_until_eod(
                &m.initial_state(&d),
                &d,
                &LoadProfile::Constant(Load::PowerW(load_w)),
                1.0,
                20_000,
                |r| {
                    volts.push(r.voltage_v);
                    if r.step == 100 {
                        x100 = r.x;
                    }
                },
            )
            .unwrap();
        (volts, x100, out.eod_s.unwrap())
    }

    #[test]
    fn reference_table_holds_to_1e_9_volt() {
        let table = [
            (7600.0, 0.117215, 8.0, [4.1913502938, 4.1516872214, 3.8768397207], 3102.0),
            (7600.0, 0.117215, 16.0, [4.1913502938, 4.1120644120, 3.5085112794], 1163.0),
            (4000.0, 0.117215, 8.0, [4.1913502938, 4.1491620627, 3.8168447504], 1581.0),
            (7000.0, 0.117215, 12.0, [4.1913502938, 4.1315127265, 3.6920012750], 1740.0),
        ];
        for (q, ro, load, v, eod) in table {
            let (volts, _, eod_s) = run(q, ro, load);
            for (k, t) in [0usize, 1, 100].into_iter().enumerate() {
                assert!(
                    (volts[t] - v[k]).abs() < 1e-9,
                    "q {q} ro {ro} load {load}: V({t}) = {:.12}, reference {:.10}",
                    volts[t],
                    v[k]
                );
            }
            assert_eq!(eod_s, eod, "q {q} load {load}: EOD");
        }
    }

    #[test]
    fn reference_state_at_100_s() {
        let (_, x, _) = run(7600.0, 0.117215, 8.0);
        let want = [550.454169, 4720.456447, 6679.543553, 716.2124977, 0.2417242361, 0.007376013193, 0.00120143118];
        for (k, w) in want.iter().enumerate() {
            let rel = (x[k] - w).abs() / w.abs();
            assert!(rel < 1e-8, "state {k}: {} vs {w} (rel {rel:e})", x[k]);
        }
    }

    #[test]
    fn total_charge_is_conserved() {
        let m = BatteryModel::default();
        let d = Degradation { q_mobile_c: 5200.0, r_o_ohm: 0.15 };
        let x0 = m.initial_state(&d);
        let total0 = x0[idx::QP_S] + x0[idx::QP_B] + x0[idx::QN_B] + x0[idx::QN_S];
        m.simulate_until_eod(&x0, &d, &LoadProfile::Constant(Load::PowerW(12.0)), 1.0, 20_000, |r| {
            let total = r.x[idx::QP_S] + r.x[idx::QP_B] + r.x[idx::QN_B] + r.x[idx::QN_S];
            assert!((total - total0).abs() < 1e-8 * total0, "t {}: {total} vs {total0}", r.t_s);
        })
        .unwrap();
    }

    #[test]
    fn eod_row_is_the_first_below_veod_and_the_only_one() {
        let m = BatteryModel::default();
        let d = Degradation::default();
        let mut below = Vec::new();
        let mut rows = 0;
        let out = m
            .simulate_until_eod(&m.initial_state(&d), &d, &LoadProfile::Constant(Load::PowerW(8.0)), 1.0, 20_000, |r| {
                rows += 1;
                if r.voltage_v < 3.0 {
                    below.push(r.t_s);
                }
            })
            .unwrap();
        assert_eq!(below, vec![3102.0]);
        assert_eq!(out.rows, rows);
        assert_eq!(rows, 3103);
    }

    #[test]
    fn max_steps_stops_without_eod() {
        let m = BatteryModel::default();
        let d = Degradation::default();
        let out = m
            .simulate_until_eod(&m.initial_state(&d), &d, &LoadProfile::Constant(Load::PowerW(8.0)), 1.0, 50, |_| {})
            .unwrap();
        assert_eq!(out, EodOutcome { eod_s: None, rows: 51 });
    }

    #[test]
    fn current_and_power_inputs_agree_when_fed_the_same_current() {
        let m = BatteryModel::default();
        let d = Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.13 };
        let mut currents = Vec::new();
        let mut power_states = Vec::new();
        m.simulate_until_eod(&m.initial_state(&d), &d, &LoadProfile::Constant(Load::PowerW(10.0)), 1.0, 20_000, |r| {
            currents.push((r.t_s, Load::CurrentA(r.current_a)));
            power_states.push(r.x);
        })
        .unwrap();
        // Replay the power run's currents as a piecewise current profile.
        let profile = LoadProfile::Piecewise(currents);
        let mut k = 0;
        m.simulate_until_eod(&m.initial_state(&d), &d, &profile, 1.0, 20_000, |r| {
            assert_eq!(electro(&r.x), electro(&power_states[k]), "step {k}");
            k += 1;
        })
        .unwrap();
        assert_eq!(k, power_states.len());
    }

    #[test]
    fn thermal_option_heats_the_cell_and_lowers_nothing_at_rest() {
        let thermal = BatteryModel::new(BatteryParams::default(), true).unwrap();
        let d = Degradation::default();
        let mut tb_max: f64 = 0.0;
        thermal
            .simulate_until_eod(
                &thermal.initial_state(&d),
                &d,
                &LoadProfile::Constant(Load::CurrentA(2.0)),
                1.0,
                20_000,
                |r| {
                    tb_max = tb_max.max(r.x[idx::T_B]);
                },
            )
            .unwrap();
        assert!(tb_max > 292.1 + 0.3, "the cell must heat under 2 A: max tb {tb_max}");
        // With no current and no overpotential there is no heat: the temperature stays put.
        let x0 = thermal.initial_state(&d);
        let x1 = thermal.step_current(&x0, 0.0, 1.0, &d);
        assert_eq!(x1[idx::T_B], 292.1);
        // Isothermal model keeps tb exactly.
        let iso = BatteryModel::default();
        let x = iso.step_current(&iso.initial_state(&d), 2.0, 1.0, &d);
        assert_eq!(x[idx::T_B], 292.1);
    }

    #[test]
    fn bad_parameters_are_named() {
        let p = BatteryParams { t_diffusion_s: -1.0, ..BatteryParams::default() };
        let err = BatteryModel::new(p, false).unwrap_err();
        assert!(err.to_string().contains("t_diffusion_s"), "{err}");
        let m = BatteryModel::default();
        let d = Degradation { q_mobile_c: f64::NAN, r_o_ohm: 0.1 };
        let err = m
            .simulate_until_eod(
                &m.initial_state(&Degradation::default()),
                &d,
                &LoadProfile::Constant(Load::PowerW(8.0)),
                1.0,
                10,
                |_| {},
            )
            .unwrap_err();
        assert!(err.to_string().contains("q_mobile_c"), "{err}");
    }

    #[test]
    fn piecewise_profile_picks_the_segment_in_force() {
        let p = LoadProfile::Piecewise(vec![
            (0.0, Load::CurrentA(1.0)),
            (10.0, Load::CurrentA(2.0)),
            (20.0, Load::PowerW(5.0)),
        ]);
        assert_eq!(p.at(0.0), Load::CurrentA(1.0));
        assert_eq!(p.at(9.9), Load::CurrentA(1.0));
        assert_eq!(p.at(10.0), Load::CurrentA(2.0));
        assert_eq!(p.at(25.0), Load::PowerW(5.0));
    }
}
