//! The extended simulator: the common battery model plus the candidate causes' extensions, driven by a
//! measured current series and sampled exactly at the measured sample times.
//!
//! The base model is [`bcal_common::battery::BatteryModel`], isothermal at the record's ambient temperature.
//! Every extension has a neutral value at which it changes nothing ([`ExtParams::default`]), so one
//! simulator serves the base model, each candidate and their combinations. The simulator steps on its own
//! grid (at most `dt_max_s`, landing on every sample time), holds the current linearly interpolated between
//! samples, and never allocates per step. It does not fit and it never reads which cause is being tested.
//!
//! Integration: the common model's explicit Euler step, except that the three overpotentials (first-order
//! lags toward their steady values, 6 s, 46 s and 1000 s) are advanced exactly over each step with their
//! steady values taken at the step's start (exponential Euler). Plain Euler lags the 6 s ohmic term by up
//! to 8 mV at 1 s steps (16 mV at 2 s) in the first 10-20 s after every load step (measured against an RK4
//! reference in `tests/generator_check.rs`); a candidate with a short time constant would otherwise be
//! fitted to that integration error instead of to the cell. The right-hand side is the common model's
//! (`BatteryModel::derivative`), written out here with a faster asinh and held equal to it by a test.

use bcal_common::battery::{
    legendre_correction_v, BatteryModel, BatteryParams, Degradation, ModelError, FARADAY, GAS_CONSTANT,
    MOLE_FRACTION_CLIP,
};
use bcal_common::math::{idx, ModelState};
use bcal_common::measured::cellmodel::xn_from_rest_voltage;
use bcal_common::measured::scenario::rest_state;
use serde::Serialize;

/// A candidate cause of model-data disagreement: each is one small extension of the model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Cause {
    /// Temperature dependence: the cell temperature (measured, else a thermal state) drives the model, and
    /// the ohmic resistance follows Arrhenius, Ro(T) = Ro * exp(Ea/R * (1/T - 1/T_ambient)), Ea >= 0, and
    /// so do the Butler-Volmer rate constants, k(T) = k * exp(-Ea_k/R * (1/T - 1/T_ambient)), Ea_k >= 0.
    /// Bounds of every cause are physical ranges, so a cause cannot stand in for another by going wild.
    Thermal,
    /// The open-circuit-voltage curve differs from the Redlich-Kister one: an additive Legendre
    /// correction (degrees 1..3) in the positive electrode's normalised surface mole fraction.
    Ocv,
    /// The bulk-surface diffusion time constant differs from the default 7e6 s.
    Diffusion,
    /// An unmodelled RC branch: a second polarisation with its own resistance and time constant.
    ExtraPolarization,
    /// A constant voltage-sensor bias.
    VoltageOffset,
    /// A current-sensor scale error: measured current = gain * true current.
    CurrentGain,
    /// The electrodes' balance shifts as the cell ages (loss of lithium inventory against loss of active
    /// material): the positive electrode starts each discharge at a shifted mole fraction, so the discharge
    /// runs over another window of its OCV curve. One parameter per cycle, calibrated like qMobile and Ro.
    ElectrodeBalance,
    /// Charge-transfer kinetics slow down as the cell ages (growing charge-transfer resistance, which
    /// NASA's impedance records show as a rising Rct): one factor on both Butler-Volmer rate constants
    /// kn and kp, calibrated per cycle like qMobile and Ro.
    ChargeTransfer,
}

impl Cause {
    /// Every candidate, in reporting order.
    pub const ALL: [Cause; 8] = [
        Cause::Thermal,
        Cause::Ocv,
        Cause::Diffusion,
        Cause::ExtraPolarization,
        Cause::VoltageOffset,
        Cause::CurrentGain,
        Cause::ElectrodeBalance,
        Cause::ChargeTransfer,
    ];

    /// The vocabulary name (`thermal`, `ocv`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Cause::Thermal => "thermal",
            Cause::Ocv => "ocv",
            Cause::Diffusion => "diffusion",
            Cause::ExtraPolarization => "extra_polarization",
            Cause::VoltageOffset => "voltage_offset",
            Cause::CurrentGain => "current_gain",
            Cause::ElectrodeBalance => "electrode_balance",
            Cause::ChargeTransfer => "charge_transfer",
        }
    }

    /// The free parameters this cause adds to every cycle (calibrated per cycle like qMobile and Ro, on
    /// held-out cycles too), with bounds and neutral starting values.
    pub fn cycle_params(self) -> Vec<ParamSpec> {
        match self {
            Cause::ElectrodeBalance => {
                vec![ParamSpec::lin("xp_shift", -0.2, 0.3, 0.0), ParamSpec::lin("xn_shift", -0.3, 0.3, 0.0)]
            }
            Cause::ChargeTransfer => vec![ParamSpec::log("kinetics_scale", 1e-3, 20.0, 1.0)],
            _ => Vec::new(),
        }
    }

    /// The free parameters this cause adds, with bounds and starting values. `has_temperature` says
    /// whether the records carry a measured temperature (else the thermal cause fits a thermal state).
    pub fn params(self, has_temperature: bool) -> Vec<ParamSpec> {
        match self {
            Cause::Thermal if has_temperature => vec![
                ParamSpec::lin("ro_activation_k", 0.0, 10000.0, 1000.0),
                ParamSpec::lin("kinetics_activation_k", 0.0, 10000.0, 1000.0),
            ],
            Cause::Thermal => vec![
                ParamSpec::lin("ro_activation_k", 0.0, 10000.0, 1000.0),
                ParamSpec::lin("kinetics_activation_k", 0.0, 10000.0, 1000.0),
                ParamSpec::log("tau_thermal_s", 50.0, 5000.0, 500.0),
            ],
            Cause::Ocv => vec![
                ParamSpec::lin("ocv_p1_v", -0.3, 0.3, 0.0),
                ParamSpec::lin("ocv_p2_v", -0.3, 0.3, 0.0),
                ParamSpec::lin("ocv_p3_v", -0.3, 0.3, 0.0),
            ],
            Cause::Diffusion => vec![ParamSpec::log("t_diffusion_s", 1e5, 1e9, 7e6)],
            Cause::ExtraPolarization => {
                vec![ParamSpec::lin("rc_r_ohm", -0.02, 0.4, 0.02), ParamSpec::log("rc_tau_s", 20.0, 20000.0, 300.0)]
            }
            Cause::VoltageOffset => vec![ParamSpec::lin("voltage_offset_v", -0.1, 0.1, 0.0)],
            Cause::CurrentGain => vec![ParamSpec::lin("current_gain", 0.85, 1.15, 1.0)],
            Cause::ElectrodeBalance | Cause::ChargeTransfer => Vec::new(),
        }
    }
}

/// One free parameter: name, bounds, start, and whether it is searched on a log scale.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ParamSpec {
    pub name: &'static str,
    pub lo: f64,
    pub hi: f64,
    pub start: f64,
    pub log: bool,
}

impl ParamSpec {
    fn lin(name: &'static str, lo: f64, hi: f64, start: f64) -> Self {
        Self { name, lo, hi, start, log: false }
    }
    fn log(name: &'static str, lo: f64, hi: f64, start: f64) -> Self {
        Self { name, lo, hi, start, log: true }
    }
}

/// Every extension's parameters. [`Default`] is the base model (each extension neutral).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ExtParams {
    /// When true the cell temperature drives the model: the measured temperature if the record has one,
    /// else the model's thermal state. Default false (isothermal at ambient).
    pub temperature_driven: bool,
    /// Arrhenius activation temperature of Ro, Ea/R, K. Default 0 (no temperature dependence).
    pub ro_activation_k: f64,
    /// Arrhenius activation temperature of the Butler-Volmer rate constants kn and kp, Ea/R, K: the
    /// exchange current grows as exp(-Ea/R (1/T - 1/T_ambient)). Default 0.
    pub kinetics_activation_k: f64,
    /// Heat-exchange time constant of the thermal state, s (used without measured temperature). Default 100.
    pub tau_thermal_s: f64,
    /// Legendre coefficients (degrees 1, 2, 3) of the additive OCV correction, V. Default 0.
    pub ocv_legendre_v: [f64; 3],
    /// Bulk-surface diffusion time constant, s. Default 7e6 (the base model's).
    pub t_diffusion_s: f64,
    /// Resistance of the extra RC branch, ohm. Default 0.
    pub rc_r_ohm: f64,
    /// Time constant of the extra RC branch, s. Default 300.
    pub rc_tau_s: f64,
    /// Voltage-sensor bias added to the model's terminal voltage, V. Default 0.
    pub voltage_offset_v: f64,
    /// Current-sensor gain: measured = gain * true. Default 1.
    pub current_gain: f64,
    /// Shift of the positive electrode's mole fraction at full charge (xp_min), added to the base value.
    /// Default 0.
    pub xp_shift: f64,
    /// Shift of the negative electrode's mole fraction at full charge (xn_max), added to the base value.
    /// Default 0.
    pub xn_shift: f64,
    /// Factor on both Butler-Volmer rate constants kn and kp (below 1: slower charge transfer). Default 1.
    pub kinetics_scale: f64,
}

impl Default for ExtParams {
    fn default() -> Self {
        Self {
            temperature_driven: false,
            ro_activation_k: 0.0,
            kinetics_activation_k: 0.0,
            tau_thermal_s: BatteryParams::default().tau_thermal_s,
            ocv_legendre_v: [0.0; 3],
            t_diffusion_s: BatteryParams::default().t_diffusion_s,
            rc_r_ohm: 0.0,
            rc_tau_s: 300.0,
            voltage_offset_v: 0.0,
            current_gain: 1.0,
            xp_shift: 0.0,
            xn_shift: 0.0,
            kinetics_scale: 1.0,
        }
    }
}

impl ExtParams {
    /// Sets the named parameter (a [`ParamSpec::name`]); also switches on what the parameter needs.
    pub fn set(&mut self, name: &str, value: f64) {
        match name {
            "ro_activation_k" => {
                self.ro_activation_k = value;
                self.temperature_driven = true;
            }
            "kinetics_activation_k" => {
                self.kinetics_activation_k = value;
                self.temperature_driven = true;
            }
            "tau_thermal_s" => self.tau_thermal_s = value,
            "ocv_p1_v" => self.ocv_legendre_v[0] = value,
            "ocv_p2_v" => self.ocv_legendre_v[1] = value,
            "ocv_p3_v" => self.ocv_legendre_v[2] = value,
            "t_diffusion_s" => self.t_diffusion_s = value,
            "rc_r_ohm" => self.rc_r_ohm = value,
            "rc_tau_s" => self.rc_tau_s = value,
            "voltage_offset_v" => self.voltage_offset_v = value,
            "current_gain" => self.current_gain = value,
            "xp_shift" => self.xp_shift = value,
            "xn_shift" => self.xn_shift = value,
            "kinetics_scale" => self.kinetics_scale = value,
            other => debug_assert!(false, "unknown extension parameter {other}"),
        }
    }

    /// Turns on what a cause needs even before its parameters are set (the thermal cause's temperature).
    pub fn enable(&mut self, cause: Cause) {
        if cause == Cause::Thermal {
            self.temperature_driven = true;
        }
    }

    /// Puts a cause's parameters back at their neutral values (the base model's), as if it were never named.
    pub fn disable(&mut self, cause: Cause) {
        let n = ExtParams::default();
        match cause {
            Cause::Thermal => {
                self.temperature_driven = n.temperature_driven;
                self.ro_activation_k = n.ro_activation_k;
                self.kinetics_activation_k = n.kinetics_activation_k;
                self.tau_thermal_s = n.tau_thermal_s;
            }
            Cause::Ocv => self.ocv_legendre_v = n.ocv_legendre_v,
            Cause::Diffusion => self.t_diffusion_s = n.t_diffusion_s,
            Cause::ExtraPolarization => (self.rc_r_ohm, self.rc_tau_s) = (n.rc_r_ohm, n.rc_tau_s),
            Cause::VoltageOffset => self.voltage_offset_v = n.voltage_offset_v,
            Cause::CurrentGain => self.current_gain = n.current_gain,
            Cause::ElectrodeBalance => (self.xp_shift, self.xn_shift) = (n.xp_shift, n.xn_shift),
            Cause::ChargeTransfer => self.kinetics_scale = n.kinetics_scale,
        }
    }
}

/// The cell as the doctor simulates it: base model state plus the extension states.
#[derive(Clone, Debug)]
pub struct ExtendedCell {
    model: BatteryModel,
    d: Degradation,
    ext: ExtParams,
    ambient_k: f64,
    x: ModelState,
    /// Voltage across the extra RC branch, V.
    v_rc_v: f64,
    /// Normalised positive-electrode span, for the OCV correction.
    xp_min: f64,
    xp_span: f64,
    q_s_max_c: f64,
    /// Reciprocals the step multiplies by (a division costs several multiplications).
    per_step: PerStep,
    /// Rate constants at ambient temperature (the Arrhenius reference).
    kn: f64,
    kp: f64,
    /// The step the decay factors below were computed for, s, and exp(-dt / tau) of the ohmic, negative
    /// and positive overpotential lags (steps repeat between samples: one exp per lag per sample).
    decay_dt_s: f64,
    decay: [f64; 3],
}

/// Constants of the right-hand side, as reciprocals.
#[derive(Clone, Copy, Debug)]
struct PerStep {
    inv_q_s_max: f64,
    inv_vol_s: f64,
    inv_vol_b: f64,
    inv_t_diffusion: f64,
    half_inv_sn: f64,
    half_inv_sp: f64,
    /// R / (F alpha), V/K.
    v_part_per_k: f64,
}

/// The state indices of the three overpotential lags advanced exactly over a step (ohmic, negative, positive).
const LAGS: [usize; 3] = [idx::V_O, idx::V_SN, idx::V_SP];

/// asinh(x) = sign(x) ln(|x| + sqrt(x^2 + 1)), about four times faster than `f64::asinh` (which goes through
/// `hypot` and `log1p` to stay exact near 0 and beyond 1e154). Below 0.03 its Taylor series to x^9 (next term
/// under 1e-17 of x); above, the logarithm's absolute error (about 1e-16) is under 1e-14 of the result.
#[inline]
fn asinh(x: f64) -> f64 {
    let a = x.abs();
    let r = if a < 0.03 {
        let a2 = a * a;
        a * (1.0 - a2 * (1.0 / 6.0 - a2 * (3.0 / 40.0 - a2 * (15.0 / 336.0 - a2 * 105.0 / 3456.0))))
    } else {
        (a + (a * a + 1.0).sqrt()).ln()
    };
    r.copysign(x)
}

impl ExtendedCell {
    /// A full cell at rest at `ambient_k`. `measured_temperature` says whether the caller will feed the
    /// temperature each step (else, when temperature-driven, the model's thermal state evolves).
    pub fn new(
        base: &BatteryParams,
        d: Degradation,
        ext: ExtParams,
        ambient_k: f64,
        measured_temperature: bool,
    ) -> Result<Self, ModelError> {
        let params = BatteryParams {
            tb0_k: ambient_k,
            t_diffusion_s: ext.t_diffusion_s,
            tau_thermal_s: ext.tau_thermal_s,
            ..base.aged(ext.xp_shift, ext.xn_shift, ext.kinetics_scale)
        };
        let thermal_state = ext.temperature_driven && !measured_temperature;
        let model = BatteryModel::new(params, thermal_state)?;
        model.check_degradation(&d)?;
        let x = model.initial_state(&d);
        let p = &model.params;
        Ok(Self {
            // The OCV correction is a property of the material: normalised on the base electrode window.
            xp_min: base.xp_min,
            xp_span: base.xp_max - base.xp_min,
            q_s_max_c: model.q_max_c(&d) * p.vol_s_fraction,
            per_step: PerStep {
                inv_q_s_max: 1.0 / (model.q_max_c(&d) * p.vol_s_fraction),
                // The surface and bulk volumes, as the common model derives them.
                inv_vol_s: 1.0 / (p.vol_s_fraction * p.vol_m3),
                inv_vol_b: 1.0 / (p.vol_m3 * (1.0 - p.vol_s_fraction)),
                inv_t_diffusion: 1.0 / p.t_diffusion_s,
                half_inv_sn: 0.5 / p.sn_m2,
                half_inv_sp: 0.5 / p.sp_m2,
                v_part_per_k: GAS_CONSTANT / FARADAY / p.alpha,
            },
            kn: p.kn,
            kp: p.kp,
            model,
            d,
            ext,
            ambient_k,
            x,
            v_rc_v: 0.0,
            decay_dt_s: f64::NAN,
            decay: [0.0; 3],
        })
    }

    /// Puts the cell at rest at the state whose open-circuit voltage (under this cell's own electrode
    /// window) is `rest_v` at `t_k`: the start of a discharge that did not begin full
    /// ([`crate::record::Discharge::start_state`]). Replaces the full-cell start of [`ExtendedCell::new`].
    pub fn start_at_rest_voltage(&mut self, rest_v: f64, t_k: f64) {
        let xn0 = xn_from_rest_voltage(&self.model, rest_v, t_k);
        let t_b = self.x[idx::T_B];
        self.x = rest_state(&self.model, &self.d, xn0, t_b);
    }

    /// Feeds the measured cell temperature, K (used only when temperature-driven).
    #[inline]
    pub fn set_temperature_k(&mut self, t_k: f64) {
        if self.ext.temperature_driven {
            self.x[idx::T_B] = t_k;
        }
    }

    /// The model's cell temperature, K.
    #[inline]
    pub fn temperature_k(&self) -> f64 {
        self.x[idx::T_B]
    }

    /// One step of `dt_s` at measured current `measured_current_a` (positive discharging).
    #[inline]
    pub fn step(&mut self, measured_current_a: f64, dt_s: f64) {
        let i_a = measured_current_a / self.ext.current_gain;
        let mut d = self.d;
        if self.ext.ro_activation_k != 0.0 {
            d.r_o_ohm *= (self.ext.ro_activation_k * (1.0 / self.x[idx::T_B] - 1.0 / self.ambient_k)).exp();
        }
        if self.ext.kinetics_activation_k != 0.0 {
            let f = (-self.ext.kinetics_activation_k * (1.0 / self.x[idx::T_B] - 1.0 / self.ambient_k)).exp();
            self.model.params.kn = self.kn * f;
            self.model.params.kp = self.kp * f;
        }
        let (rates, steady) = self.rates_and_steady(i_a, &d);
        let prev = self.x;
        for k in [idx::QP_S, idx::QP_B, idx::QN_B, idx::QN_S, idx::T_B] {
            // The common model's Euler step with its state limits (charges and temperature never negative).
            self.x[k] = (prev[k] + rates[k] * dt_s).max(0.0);
        }
        if dt_s > 0.0 {
            if dt_s != self.decay_dt_s {
                let p = &self.model.params;
                self.decay = [p.t_o_s, p.t_sn_s, p.t_sp_s].map(|tau_s| (-dt_s / tau_s).exp());
                self.decay_dt_s = dt_s;
            }
            for ((k, steady_v), decay) in LAGS.into_iter().zip(steady).zip(self.decay) {
                self.x[k] = steady_v + (prev[k] - steady_v) * decay;
            }
        }
        if self.ext.rc_r_ohm != 0.0 {
            // Exact update of the linear RC branch over the step (stable for any dt).
            let target_v = i_a * self.ext.rc_r_ohm;
            self.v_rc_v = target_v + (self.v_rc_v - target_v) * (-dt_s / self.ext.rc_tau_s).exp();
        }
    }

    /// The common model's right-hand side at the current state (`BatteryModel::derivative`, Daigle & Kulkarni
    /// 2013 as progpy ships it), split the way the step uses it: the rates of the charges and the temperature,
    /// and the steady values the three overpotential lags (ohmic, negative, positive) relax toward. Written
    /// here rather than called because the common model's asinh (then `f64::asinh`, glibc `hypot` and `log1p`;
    /// the C library's since 2026-11-28) was half of the doctor's run time;
    /// `tests::rates_and_steady_values_match_the_common_model` holds the two equal.
    #[inline]
    fn rates_and_steady(&self, i_a: f64, d: &Degradation) -> (ModelState, [f64; 3]) {
        let p = &self.model.params;
        let x = &self.x;
        let k = &self.per_step;
        let (lo, hi) = MOLE_FRACTION_CLIP;
        let v_part = k.v_part_per_k * x[idx::T_B];
        let pow_alpha = |v: f64| if p.alpha == 0.5 { v.sqrt() } else { v.powf(p.alpha) };
        let xn_s = (x[idx::QN_S] * k.inv_q_s_max).clamp(lo, hi);
        let diff_n = (x[idx::QN_B] * k.inv_vol_b - x[idx::QN_S] * k.inv_vol_s) * k.inv_t_diffusion;
        let jn0 = p.kn * pow_alpha((1.0 - xn_s) * xn_s);
        let xp_s = (x[idx::QP_S] * k.inv_q_s_max).clamp(lo, hi);
        let diff_p = (x[idx::QP_B] * k.inv_vol_b - x[idx::QP_S] * k.inv_vol_s) * k.inv_t_diffusion;
        let jp0 = p.kp * pow_alpha((1.0 - xp_s) * xp_s);
        let steady =
            [i_a * d.r_o_ohm, v_part * asinh(i_a * k.half_inv_sn / jn0), v_part * asinh(i_a * k.half_inv_sp / jp0)];
        let mut rates = ModelState::zeros();
        rates[idx::QP_S] = i_a + diff_p;
        rates[idx::QP_B] = -diff_p;
        rates[idx::QN_B] = -diff_n;
        rates[idx::QN_S] = diff_n - i_a;
        if self.model.thermal {
            let voltage_eta = x[idx::V_O] + x[idx::V_SN] + x[idx::V_SP];
            rates[idx::T_B] = voltage_eta * i_a / p.mc_j_per_k + (p.tb0_k - x[idx::T_B]) / p.tau_thermal_s;
        }
        (rates, steady)
    }

    /// Terminal voltage the sensor reads, V.
    #[inline]
    pub fn voltage_v(&self) -> f64 {
        let mut v = self.model.voltage_v(&self.x, &self.d) - self.v_rc_v + self.ext.voltage_offset_v;
        let c = &self.ext.ocv_legendre_v;
        if c.iter().any(|a| *a != 0.0) {
            let z = ((self.x[idx::QP_S] / self.q_s_max_c - self.xp_min) / self.xp_span).clamp(0.0, 1.0);
            v += legendre_correction_v(c, z);
        }
        v
    }
}

/// The measured inputs of one record, borrowed.
#[derive(Clone, Copy, Debug)]
pub struct Drive<'a> {
    pub time_s: &'a [f64],
    pub current_a: &'a [f64],
    pub temperature_k: Option<&'a [f64]>,
    pub ambient_k: f64,
    /// How the current runs between samples: `false` linearly interpolated; `true` (a load that switches
    /// about as often as it is sampled, [`crate::record::Discharge::alternating_load`]) the current a sample
    /// reads runs the whole interval before it, as the streaming calibrators run it there
    /// (`bcal_common::measured::cellmodel::interval_drive`).
    pub alternating: bool,
}

/// Simulates the record's first `out.len()` samples and writes the model's voltage at each sample time.
/// The current between samples is linearly interpolated (taken at each step's midpoint), or, where the load
/// alternates, the current each sample reads ([`Drive::alternating`]).
pub fn simulate_voltage(
    base: &BatteryParams,
    d: Degradation,
    ext: &ExtParams,
    drive: Drive<'_>,
    dt_max_s: f64,
    out: &mut [f64],
) -> Result<(), ModelError> {
    simulate_voltage_from(base, d, ext, drive, None, dt_max_s, out)
}

/// [`simulate_voltage`] from a given start: a full cell (`None`, progpy's initial state) or the rest state
/// whose open-circuit voltage is `rest_v` at `t_k` (`Some((rest_v, t_k))`).
pub fn simulate_voltage_from(
    base: &BatteryParams,
    d: Degradation,
    ext: &ExtParams,
    drive: Drive<'_>,
    start_rest: Option<(f64, f64)>,
    dt_max_s: f64,
    out: &mut [f64],
) -> Result<(), ModelError> {
    let n = out.len().min(drive.time_s.len());
    if n == 0 {
        return Ok(());
    }
    let mut cell = ExtendedCell::new(base, d, *ext, drive.ambient_k, drive.temperature_k.is_some())?;
    if let Some((rest_v, t_k)) = start_rest {
        cell.start_at_rest_voltage(rest_v, t_k);
    }
    let (t, i) = (drive.time_s, drive.current_a);
    if let Some(tk) = drive.temperature_k {
        cell.set_temperature_k(tk[0]);
    }
    out[0] = cell.voltage_v();
    for k in 1..n {
        let span_s = t[k] - t[k - 1];
        let steps = (span_s / dt_max_s).ceil().max(1.0);
        let h_s = span_s / steps;
        for j in 0..steps as usize {
            let frac = (j as f64 + 0.5) / steps;
            if let Some(tk) = drive.temperature_k {
                cell.set_temperature_k(tk[k - 1] + (tk[k] - tk[k - 1]) * (j as f64 / steps));
            }
            let i_a = if drive.alternating { i[k] } else { i[k - 1] + (i[k] - i[k - 1]) * frac };
            cell.step(i_a, h_s);
        }
        if let Some(tk) = drive.temperature_k {
            cell.set_temperature_k(tk[k]);
        }
        let v = cell.voltage_v();
        if !v.is_finite() {
            return Err(ModelError::NonFinite { t_s: t[k] });
        }
        out[k] = v;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::battery::{Load, LoadProfile};

    /// The common model's voltage every second of a 2 A discharge, stepped by Euler at `dt_s`.
    fn common_model_volts(d: Degradation, dt_s: f64) -> Vec<f64> {
        let model = BatteryModel::new(BatteryParams { tb0_k: 297.15, ..BatteryParams::default() }, false).unwrap();
        let per_s = (1.0 / dt_s).round() as usize;
        let mut want = Vec::new();
        model
            .simulate_until_eod(
                &model.initial_state(&d),
                &d,
                &LoadProfile::Constant(Load::CurrentA(2.0)),
                dt_s,
                4000 * per_s,
                |r| {
                    if r.step % per_s == 0 {
                        want.push(r.voltage_v)
                    }
                },
            )
            .unwrap();
        want
    }

    /// The measured inputs of a record at 25 C without a measured temperature, the current interpolated.
    fn drive_at_25_c<'a>(time_s: &'a [f64], current_a: &'a [f64]) -> Drive<'a> {
        Drive { time_s, current_a, temperature_k: None, ambient_k: 297.15, alternating: false }
    }

    #[test]
    fn neutral_extensions_reproduce_the_common_model() {
        let d = Degradation { q_mobile_c: 6500.0, r_o_ohm: 0.14 };
        // The common model's equations solved finely (Euler at 0.01 s) ...
        let fine = common_model_volts(d, 0.01);
        let coarse = common_model_volts(d, 1.0);
        let n = fine.len().min(coarse.len()) - 1;
        let time_s: Vec<f64> = (0..n).map(|k| k as f64).collect();
        let current_a = vec![2.0; n];
        let mut got = vec![0.0; n];
        let drive = drive_at_25_c(&time_s, &current_a);
        simulate_voltage(&BatteryParams::default(), d, &ExtParams::default(), drive, 1.0, &mut got).unwrap();
        let gap = |a: &[f64]| a.iter().zip(&fine).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
        // ... are met by the doctor's 1 s steps within a fraction of a millivolt, where the common model's
        // own Euler steps of 1 s miss the load step's ohmic lag by several millivolts.
        assert!(gap(&got) < 1e-3, "doctor at 1 s vs fine Euler: {:.3} mV", 1e3 * gap(&got));
        assert!(gap(&coarse[..n]) > 5e-3, "plain Euler at 1 s: {:.3} mV", 1e3 * gap(&coarse[..n]));
    }

    /// The OCV correction the doctor fits (`ExtParams::ocv_legendre_v`, on its extended cell) is the one the
    /// calibrators' model runs (`BatteryParams::ocv_legendre_v`, a diagnosis carried by `bcal calibrate --model`):
    /// the same voltages along a discharge, with electrode balance shifted too (the correction stays on the base
    /// window), to rounding; and the correction moves the voltage by tens of millivolts.
    #[test]
    fn the_fitted_ocv_correction_is_the_one_the_calibrators_run() {
        let d = Degradation { q_mobile_c: 6500.0, r_o_ohm: 0.14 };
        let n = 3000;
        let time_s: Vec<f64> = (0..n).map(|k| k as f64).collect();
        let current_a = vec![2.0; n];
        let drive = drive_at_25_c(&time_s, &current_a);
        let c = [0.05, -0.03, 0.02];
        let balance = ExtParams { xp_shift: 0.03, xn_shift: -0.02, ..ExtParams::default() };
        let run = |base: &BatteryParams, ext: &ExtParams| {
            let mut v = vec![0.0; n];
            simulate_voltage(base, d, ext, drive, 1.0, &mut v).unwrap();
            v
        };
        let fitted = run(&BatteryParams::default(), &ExtParams { ocv_legendre_v: c, ..balance });
        let carried = run(&BatteryParams { ocv_legendre_v: c, ..BatteryParams::default() }, &balance);
        let without = run(&BatteryParams::default(), &balance);
        let gap = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
        assert!(gap(&fitted, &carried) < 1e-12, "{:e} V", gap(&fitted, &carried));
        assert!(gap(&fitted, &without) > 0.02, "{} V", gap(&fitted, &without));
    }

    /// The doctor's own right-hand side (written for speed, with its own asinh) is the common model's: the
    /// charge and temperature rates and the lags' steady values (x + tau dx) agree to 1e-12 relative over
    /// states across the electrode window, both current signs, thermal on and off, fast and slow kinetics.
    #[test]
    fn rates_and_steady_values_match_the_common_model() {
        let base = BatteryParams::default();
        let mut worst: f64 = 0.0;
        for (k, (q_mobile_c, r_o_ohm, i_a, scale, thermal)) in [
            (7600.0, 0.117, 2.0, 1.0, false),
            (5200.0, 0.2, 4.0, 0.01, true),
            (6400.0, 0.05, -1.5, 3.0, false),
            (6900.0, 0.15, 1e-9, 1.0, true),
            (6000.0, 0.1, 0.3, 0.2, true),
        ]
        .into_iter()
        .enumerate()
        {
            let d = Degradation { q_mobile_c, r_o_ohm };
            let ext = ExtParams {
                kinetics_scale: scale,
                temperature_driven: thermal,
                xp_shift: 0.02 * k as f64,
                ..Default::default()
            };
            let mut cell = ExtendedCell::new(&base, d, ext, 300.15, false).unwrap();
            for frac in [0.0, 0.1, 0.5, 0.9, 0.99] {
                // A state partway through the window, out of equilibrium, with nonzero overpotentials.
                let mut x = cell.model.initial_state(&d);
                let moved_c = frac * q_mobile_c;
                x[idx::QN_S] -= 0.7 * moved_c * cell.model.params.vol_s_fraction;
                x[idx::QN_B] -= moved_c * (1.0 - 0.7 * cell.model.params.vol_s_fraction);
                x[idx::QP_S] += 0.9 * moved_c * cell.model.params.vol_s_fraction;
                x[idx::QP_B] += moved_c * (1.0 - 0.9 * cell.model.params.vol_s_fraction);
                x[idx::V_O] = 0.2;
                x[idx::V_SN] = 0.01;
                x[idx::V_SP] = 0.03;
                x[idx::T_B] = 305.0;
                cell.x = x;
                let want = cell.model.derivative(&x, i_a, &d);
                let (rates, steady) = cell.rates_and_steady(i_a, &d);
                let p = &cell.model.params;
                // (got, want, scale): a lag's steady value is rebuilt from x + tau dx, exact to the state's size.
                let mut pairs: Vec<(f64, f64, f64)> = [idx::QP_S, idx::QP_B, idx::QN_B, idx::QN_S, idx::T_B]
                    .into_iter()
                    // Rates in C/s (A) and K/s: to 1e-12 of an ampere where they vanish (a cell at rest).
                    .map(|j| (rates[j], want[j], want[j].abs().max(1.0)))
                    .collect();
                for ((j, tau_s), got) in LAGS.into_iter().zip([p.t_o_s, p.t_sn_s, p.t_sp_s]).zip(steady) {
                    let w = x[j] + tau_s * want[j];
                    pairs.push((got, w, w.abs().max(x[j].abs())));
                }
                for (got, want, scale) in pairs {
                    let rel = (got - want).abs() / scale.max(1e-12);
                    assert!(rel < 1e-12, "case {k} at {frac}: {got} vs {want}");
                    worst = worst.max(rel);
                }
            }
        }
        eprintln!("largest relative gap to the common model: {worst:.1e}");
    }

    #[test]
    fn asinh_is_the_standard_one() {
        for x in [0.0, 1e-12, -3e-5, 1e-4, 0.0299, -0.03, 0.031, -0.3, 1.0, 7.5, -250.0, 1e8] {
            let (got, want) = (asinh(x), f64::asinh(x));
            assert!((got - want).abs() <= 1e-14 * want.abs(), "{x}: {got} vs {want}");
        }
    }

    #[test]
    fn each_extension_moves_the_voltage_the_physical_way() {
        let base = BatteryParams::default();
        let d = Degradation { q_mobile_c: 6500.0, r_o_ohm: 0.14 };
        let time_s: Vec<f64> = (0..200).map(|k| 10.0 * k as f64).collect();
        let current_a = vec![2.0; 200];
        let hot_k: Vec<f64> = (0..200).map(|k| 297.15 + 0.05 * k as f64).collect();
        let run = |ext: ExtParams, temps: Option<&[f64]>| {
            let mut v = vec![0.0; 200];
            let drive = Drive {
                time_s: &time_s,
                current_a: &current_a,
                temperature_k: temps,
                ambient_k: 297.15,
                alternating: false,
            };
            simulate_voltage(&base, d, &ext, drive, 2.0, &mut v).unwrap();
            v[199]
        };
        let v0 = run(ExtParams::default(), None);
        let offset = run(ExtParams { voltage_offset_v: 0.01, ..Default::default() }, None);
        assert!((offset - v0 - 0.01).abs() < 1e-12);
        // A warmer cell with Arrhenius resistance drops less voltage.
        let warm =
            run(ExtParams { temperature_driven: true, ro_activation_k: 3000.0, ..Default::default() }, Some(&hot_k));
        assert!(warm > v0 + 0.01, "warm {warm} vs {v0}");
        // An extra RC branch drops i * R after many time constants.
        let rc = run(ExtParams { rc_r_ohm: 0.05, rc_tau_s: 50.0, ..Default::default() }, None);
        assert!((v0 - rc - 0.1).abs() < 1e-6, "rc drop {}", v0 - rc);
        // A sensor reading 10 % high means less true charge drawn: a higher voltage.
        let gain = run(ExtParams { current_gain: 1.1, ..Default::default() }, None);
        assert!(gain > v0);
        // Slower charge transfer adds Butler-Volmer overpotential: a lower voltage under load.
        let slow = run(ExtParams { kinetics_scale: 0.05, ..Default::default() }, None);
        assert!(slow < v0 - 0.02, "slow kinetics {slow} vs {v0}");
        // A positive electrode starting more lithiated reaches its knee sooner: a lower voltage late on.
        let shifted = run(ExtParams { xp_shift: 0.05, ..Default::default() }, None);
        assert!(shifted < v0 - 0.005, "shifted balance {shifted} vs {v0}");
        // Arrhenius kinetics: a warmer cell with slow kinetics drops less voltage than a cell at ambient.
        let slow_warm = run(
            ExtParams {
                temperature_driven: true,
                kinetics_scale: 0.05,
                kinetics_activation_k: 4000.0,
                ..Default::default()
            },
            Some(&hot_k),
        );
        let slow_hot_no_arrhenius =
            run(ExtParams { temperature_driven: true, kinetics_scale: 0.05, ..Default::default() }, Some(&hot_k));
        assert!(slow_warm > slow_hot_no_arrhenius + 0.005, "{slow_warm} vs {slow_hot_no_arrhenius}");
    }
}
