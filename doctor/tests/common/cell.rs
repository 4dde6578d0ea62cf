//! The test generator's own cell: the NASA Li-ion electrochemistry model (Daigle & Kulkarni 2013, the
//! equations progpy's `BatteryElectroChemEOD` implements) written a second time, apart from
//! `bcal_common::battery` and `bcal_doctor::sim`, and integrated by classic fourth-order Runge-Kutta on a
//! fine fixed step. Every hidden effect a test can switch on is part of this file's own right-hand side or
//! output equation, in its own parametrisation: electrode capacity and stoichiometry at full charge instead
//! of qMobile and bound shifts, exchange-current scale, an RC branch as one more ODE state, a lumped heat
//! balance, an additive deviation of the positive electrode's potential.
//!
//! Only the published constants are shared with the doctor (they define the model); no code is. The
//! generator must never call the doctor's simulator: the doctor's tests would then be graded by the code
//! that answers them. `generator_check.rs` holds this model equal to the doctor's on the base model, to
//! the integrators' difference.

use nalgebra::SVector;

/// Gas constant, J/(mol K), and Faraday's constant, C/mol (the model's published values).
pub const R_GAS: f64 = 8.3144621;
pub const F_FARADAY: f64 = 96487.0;

/// Published constants of the model (Daigle & Kulkarni 2013, as progpy ships them).
pub mod nasa {
    pub const XN_MIN: f64 = 0.0;
    pub const XN_MAX: f64 = 0.6;
    pub const XP_MIN: f64 = 0.4;
    pub const XP_MAX: f64 = 1.0;
    pub const ALPHA: f64 = 0.5;
    pub const SN_M2: f64 = 0.000437545;
    pub const SP_M2: f64 = 0.00030962;
    pub const KN: f64 = 2120.96;
    pub const KP: f64 = 248898.0;
    pub const VOL_M3: f64 = 2e-5;
    pub const VOL_S_FRACTION: f64 = 0.1;
    pub const T_DIFFUSION_S: f64 = 7e6;
    pub const T_O_S: f64 = 6.08671;
    pub const T_SN_S: f64 = 1001.38;
    pub const T_SP_S: f64 = 46.4311;
    pub const U0P_V: f64 = 4.03;
    pub const U0N_V: f64 = 0.01;
    /// Redlich-Kister coefficients of the positive electrode, J/mol.
    pub const AP: [f64; 13] = [
        -31593.7, 0.106747, 24606.4, -78561.9, 13317.9, 307387.0, 84916.1, -1.07469e6, 2285.04, 990894.0, 283920.0,
        -161513.0, -469218.0,
    ];
    /// The negative electrode's expansion has a single term, J/mol.
    pub const AN0: f64 = 86.19;
}

/// Self-heating of the cell and the temperature dependence it drives.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Heat {
    /// Lumped heat capacity, J/K.
    pub capacity_j_per_k: f64,
    /// Time constant of the exchange with ambient, s.
    pub exchange_s: f64,
    /// Arrhenius activation temperature of the ohmic resistance, K (resistance falls as the cell warms).
    pub ro_activation_k: f64,
    /// Arrhenius activation temperature of the exchange currents, K (they grow as the cell warms).
    pub kinetics_activation_k: f64,
}

/// An additive deviation of the positive electrode's equilibrium potential from its Redlich-Kister
/// curve: `amplitude_v * (sin(2 pi (periods y + phase)) - its mean over y in [0, 1])`, y the positive
/// electrode's surface lithiation normalised over [XP_MIN, XP_MAX]. Not a polynomial, so no candidate
/// holds it exactly.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OcvDeviation {
    pub amplitude_v: f64,
    pub periods: f64,
    pub phase: f64,
}

impl OcvDeviation {
    pub fn at(&self, y: f64) -> f64 {
        let w = std::f64::consts::TAU * self.periods;
        let p = std::f64::consts::TAU * self.phase;
        // Mean of sin(w y + p) over [0, 1] in closed form.
        let mean = (p.cos() - (w + p).cos()) / w;
        self.amplitude_v * ((w * y + p).sin() - mean)
    }
}

/// Everything that defines one discharge of the generator's cell.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellParams {
    /// Lithium capacity of each electrode, C (both electrodes alike in this model).
    pub q_max_c: f64,
    /// Lithiation of the positive and of the negative electrode at full charge.
    pub xp_full: f64,
    pub xn_full: f64,
    /// Ohmic resistance at ambient, ohm.
    pub r_o_ohm: f64,
    /// Bulk-surface diffusion time of both electrodes, s.
    pub diffusion_s: f64,
    /// Factor on both electrodes' exchange currents (charge-transfer speed).
    pub exchange_scale: f64,
    /// Ambient temperature, K.
    pub ambient_k: f64,
    pub heat: Option<Heat>,
    /// A second polarisation: resistance, ohm, and time constant, s.
    pub rc: Option<(f64, f64)>,
    pub ocv_deviation: Option<OcvDeviation>,
}

impl CellParams {
    /// The model's base cell for a given mobile charge (C) and resistance (ohm): full charge at the
    /// published stoichiometry, so the electrode capacity is qMobile over the negative electrode's span.
    pub fn base(q_mobile_c: f64, r_o_ohm: f64, ambient_k: f64) -> Self {
        Self {
            q_max_c: q_mobile_c / (nasa::XN_MAX - nasa::XN_MIN),
            xp_full: nasa::XP_MIN,
            xn_full: nasa::XN_MAX,
            r_o_ohm,
            diffusion_s: nasa::T_DIFFUSION_S,
            exchange_scale: 1.0,
            ambient_k,
            heat: None,
            rc: None,
            ocv_deviation: None,
        }
    }
}

/// State: surface and bulk charge of each electrode (C), the three overpotentials (V), temperature (K),
/// and the extra RC branch's voltage (V).
pub type State = SVector<f64, 9>;
const QP_SURF: usize = 0;
const QP_BULK: usize = 1;
const QN_SURF: usize = 2;
const QN_BULK: usize = 3;
const V_OHM: usize = 4;
const V_NEG: usize = 5;
const V_POS: usize = 6;
const TEMP: usize = 7;
const V_RC: usize = 8;

/// Clip of a surface lithiation inside the logarithms and square roots (the model's documented range).
fn clip(x: f64) -> f64 {
    x.clamp(0.01, 0.99)
}

/// Redlich-Kister excess potential of a 13-term expansion at lithiation `x`, V:
/// sum_k A_k / F ((2x - 1)^(k + 1) - 2 k x (1 - x) (2x - 1)^(k - 1)).
fn redlich_kister_v(a: &[f64], x: f64) -> f64 {
    let u = 2.0 * x - 1.0;
    let sum: f64 = a
        .iter()
        .enumerate()
        .map(|(k, ak)| {
            let k_i = k as i32;
            let second = if k == 0 { 0.0 } else { 2.0 * k as f64 * x * (1.0 - x) * u.powi(k_i - 1) };
            ak * (u.powi(k_i + 1) - second)
        })
        .sum();
    sum / F_FARADAY
}

/// The cell: parameters plus the quantities derived from them once.
#[derive(Clone, Debug)]
pub struct Cell {
    pub p: CellParams,
    surf_vol_m3: f64,
    bulk_vol_m3: f64,
    /// Surface capacity of one electrode, C.
    surf_cap_c: f64,
}

impl Cell {
    pub fn new(p: CellParams) -> Self {
        let surf_vol_m3 = nasa::VOL_M3 * nasa::VOL_S_FRACTION;
        Self { p, surf_vol_m3, bulk_vol_m3: nasa::VOL_M3 - surf_vol_m3, surf_cap_c: p.q_max_c * nasa::VOL_S_FRACTION }
    }

    /// Full charge at rest, at ambient.
    pub fn full(&self) -> State {
        let mut s = State::zeros();
        let frac = nasa::VOL_S_FRACTION;
        s[QP_SURF] = self.p.q_max_c * self.p.xp_full * frac;
        s[QP_BULK] = self.p.q_max_c * self.p.xp_full * (1.0 - frac);
        s[QN_SURF] = self.p.q_max_c * self.p.xn_full * frac;
        s[QN_BULK] = self.p.q_max_c * self.p.xn_full * (1.0 - frac);
        s[TEMP] = self.p.ambient_k;
        s
    }

    fn temperature_k(&self, s: &State) -> f64 {
        if self.p.heat.is_some() {
            s[TEMP]
        } else {
            self.p.ambient_k
        }
    }

    /// exp(Ea/R (1/T - 1/T_ambient)) for an activation temperature `ea_k`.
    fn arrhenius(&self, ea_k: f64, t_k: f64) -> f64 {
        (ea_k * (1.0 / t_k - 1.0 / self.p.ambient_k)).exp()
    }

    /// Equilibrium potential of the positive electrode at surface lithiation `x`, V (with the deviation).
    fn positive_potential_v(&self, x: f64, t_k: f64) -> f64 {
        let xc = clip(x);
        let mut u = nasa::U0P_V + R_GAS * t_k / F_FARADAY * ((1.0 - xc) / xc).ln() + redlich_kister_v(&nasa::AP, xc);
        if let Some(dev) = self.p.ocv_deviation {
            let y = ((x - nasa::XP_MIN) / (nasa::XP_MAX - nasa::XP_MIN)).clamp(0.0, 1.0);
            u += dev.at(y);
        }
        u
    }

    fn negative_potential_v(&self, x: f64, t_k: f64) -> f64 {
        let xc = clip(x);
        nasa::U0N_V + R_GAS * t_k / F_FARADAY * ((1.0 - xc) / xc).ln() + redlich_kister_v(&[nasa::AN0], xc)
    }

    /// Terminal voltage of the cell (no sensor), V.
    pub fn voltage_v(&self, s: &State) -> f64 {
        let t_k = self.temperature_k(s);
        let up = self.positive_potential_v(s[QP_SURF] / self.surf_cap_c, t_k);
        let un = self.negative_potential_v(s[QN_SURF] / self.surf_cap_c, t_k);
        up - un - s[V_OHM] - s[V_NEG] - s[V_POS] - s[V_RC]
    }

    /// Steady Butler-Volmer overpotential of one electrode, V: (RT / alpha F) asinh(j / 2 j0), with the
    /// exchange current density j0 = k (x (1 - x))^alpha.
    fn butler_volmer_v(&self, i_a: f64, area_m2: f64, k: f64, x: f64, t_k: f64) -> f64 {
        let xc = clip(x);
        let j0 = k * (xc * (1.0 - xc)).powf(nasa::ALPHA);
        R_GAS * t_k / (nasa::ALPHA * F_FARADAY) * (i_a / area_m2 / (2.0 * j0)).asinh()
    }

    /// Time derivative of the state at true current `i_a` (positive discharging).
    pub fn derivative(&self, s: &State, i_a: f64) -> State {
        let t_k = self.temperature_k(s);
        let (r_o, k_scale) = match self.p.heat {
            Some(h) => (
                self.p.r_o_ohm * self.arrhenius(h.ro_activation_k, t_k),
                self.p.exchange_scale / self.arrhenius(h.kinetics_activation_k, t_k),
            ),
            None => (self.p.r_o_ohm, self.p.exchange_scale),
        };
        // Concentration difference between bulk and surface drives diffusion toward the surface.
        let flux_p = (s[QP_BULK] / self.bulk_vol_m3 - s[QP_SURF] / self.surf_vol_m3) / self.p.diffusion_s;
        let flux_n = (s[QN_BULK] / self.bulk_vol_m3 - s[QN_SURF] / self.surf_vol_m3) / self.p.diffusion_s;
        let xp = s[QP_SURF] / self.surf_cap_c;
        let xn = s[QN_SURF] / self.surf_cap_c;
        let v_neg_ss = self.butler_volmer_v(i_a, nasa::SN_M2, nasa::KN * k_scale, xn, t_k);
        let v_pos_ss = self.butler_volmer_v(i_a, nasa::SP_M2, nasa::KP * k_scale, xp, t_k);
        let mut d = State::zeros();
        // Discharge moves lithium from the negative surface to the positive surface.
        d[QP_SURF] = i_a + flux_p;
        d[QP_BULK] = -flux_p;
        d[QN_SURF] = flux_n - i_a;
        d[QN_BULK] = -flux_n;
        d[V_OHM] = (i_a * r_o - s[V_OHM]) / nasa::T_O_S;
        d[V_NEG] = (v_neg_ss - s[V_NEG]) / nasa::T_SN_S;
        d[V_POS] = (v_pos_ss - s[V_POS]) / nasa::T_SP_S;
        if let Some(h) = self.p.heat {
            // Irreversible heat i * (sum of overpotentials) in, exchange with ambient out.
            let heat_w = i_a * (s[V_OHM] + s[V_NEG] + s[V_POS] + s[V_RC]);
            let loss_w = h.capacity_j_per_k * (s[TEMP] - self.p.ambient_k) / h.exchange_s;
            d[TEMP] = (heat_w - loss_w) / h.capacity_j_per_k;
        }
        if let Some((r_ohm, tau_s)) = self.p.rc {
            d[V_RC] = (i_a * r_ohm - s[V_RC]) / tau_s;
        }
        d
    }

    /// One classic Runge-Kutta step of `h_s` at a current held constant over the step.
    pub fn rk4(&self, s: &State, i_a: f64, h_s: f64) -> State {
        self.rk4_by(s, h_s, |_| i_a)
    }

    /// One classic Runge-Kutta step of `h_s` with the current a function of the time into the step.
    pub fn rk4_by(&self, s: &State, h_s: f64, current_a: impl Fn(f64) -> f64) -> State {
        let i_mid = current_a(0.5 * h_s);
        let k1 = self.derivative(s, current_a(0.0));
        let k2 = self.derivative(&(s + k1 * (0.5 * h_s)), i_mid);
        let k3 = self.derivative(&(s + k2 * (0.5 * h_s)), i_mid);
        let k4 = self.derivative(&(s + k3 * h_s), current_a(h_s));
        s + (k1 + k2 * 2.0 + k3 * 2.0 + k4) * (h_s / 6.0)
    }

    /// The cell temperature, K.
    pub fn temperature(&self, s: &State) -> f64 {
        self.temperature_k(s)
    }
}
