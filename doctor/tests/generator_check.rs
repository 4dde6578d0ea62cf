//! The test generator is shown correct on its own: on the base model (no hidden effect) its RK4 voltage
//! at 0.1 s and the doctor's Euler simulator converge to the same discharge, and they differ by no more
//! than the doctor's own integration error, estimated from the doctor alone (Euler is first order, so
//! halving its step halves its error: V(dt) - V_exact ~ 2 (V(dt) - V(dt/2))). The same check maps the
//! effects that a candidate holds exactly (diffusion, an RC branch, exchange-current scale, electrode
//! balance) onto the candidate's parameters: a sign or unit slip in either implementation would show.

mod common;

use bcal_common::battery::{BatteryParams, Degradation};
use bcal_doctor::sim::{simulate_voltage, Drive, ExtParams};
use common::cell::{nasa, Cell, CellParams};
use common::STEP_S;

/// A smooth load (A) both integrators evaluate exactly: 2 A with a 0.8 A swing of period 900 s.
fn load_a(t_s: f64) -> f64 {
    2.0 + 0.8 * (std::f64::consts::TAU * t_s / 900.0).sin()
}

/// The generator's voltage every second until the cell first reads below 3.05 V (before the clip of
/// the mole fractions could matter), with the RK4 step `h_s`.
fn generator_volts(p: CellParams, h_s: f64) -> Vec<f64> {
    let cell = Cell::new(p);
    let mut s = cell.full();
    let per_s = (1.0 / h_s).round() as usize;
    let mut out = vec![cell.voltage_v(&s)];
    let mut t = 0.0;
    while out.last().is_some_and(|v| *v > 3.05) && out.len() < 10_000 {
        for _ in 0..per_s {
            s = cell.rk4_by(&s, h_s, |tau| load_a(t + tau));
            t += h_s;
        }
        out.push(cell.voltage_v(&s));
    }
    out
}

/// The doctor's simulator on the same load sampled every second, with step `dt_s`.
fn doctor_volts(d: Degradation, ext: &ExtParams, ambient_k: f64, n: usize, dt_s: f64) -> Vec<f64> {
    let time_s: Vec<f64> = (0..n).map(|k| k as f64).collect();
    let current_a: Vec<f64> = time_s.iter().map(|t| load_a(*t)).collect();
    let mut out = vec![0.0; n];
    let drive = Drive { time_s: &time_s, current_a: &current_a, temperature_k: None, ambient_k, alternating: false };
    simulate_voltage(&BatteryParams::default(), d, ext, drive, dt_s, &mut out).unwrap();
    out
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}

/// Holds the generator's cell `p` equal to the doctor's simulator with (`d`, `ext`) to the doctor's
/// integration error; returns (generator - Euler at 1 s, the Euler error estimate), V.
fn assert_agree(what: &str, p: CellParams, d: Degradation, ext: &ExtParams) -> (f64, f64) {
    let gen = generator_volts(p, STEP_S);
    let n = gen.len();
    assert!(n > 1500, "{what}: the discharge should last a while, {n} s");
    // RK4's own error at 0.1 s, from the same halving argument (fourth order: error ~ diff / 15).
    let gen_coarse = generator_volts(p, 2.0 * STEP_S);
    let m = n.min(gen_coarse.len()) - 1;
    let rk4_err = max_abs_diff(&gen[..m], &gen_coarse[..m]) / 15.0;
    let euler_1 = doctor_volts(d, ext, p.ambient_k, n, 1.0);
    let euler_half = doctor_volts(d, ext, p.ambient_k, n, 0.5);
    let euler_quarter = doctor_volts(d, ext, p.ambient_k, n, 0.25);
    // The doctor's error at 1 s, estimated from the doctor alone.
    let euler_err = 2.0 * max_abs_diff(&euler_1, &euler_half);
    let gap_1 = max_abs_diff(&gen, &euler_1);
    let gap_half = max_abs_diff(&gen, &euler_half);
    let gap_quarter = max_abs_diff(&gen, &euler_quarter);
    // Richardson's extrapolation of the doctor's Euler runs is second order: it must land on the generator
    // far closer than either run does.
    let richardson: Vec<f64> = euler_half.iter().zip(&euler_quarter).map(|(h, q)| 2.0 * q - h).collect();
    let gap_richardson = max_abs_diff(&gen, &richardson);
    eprintln!(
        "{what}: {n} s; generator - Euler max |dV| at 1 / 0.5 / 0.25 s: {:.3} / {:.3} / {:.3} mV; \
         Euler error estimate at 1 s {:.3} mV; Richardson {:.4} mV; RK4 error {:.1e} mV",
        1e3 * gap_1,
        1e3 * gap_half,
        1e3 * gap_quarter,
        1e3 * euler_err,
        1e3 * gap_richardson,
        1e3 * rk4_err
    );
    assert!(rk4_err < 1e-6, "{what}: RK4 at 0.1 s should be exact to 1 uV, {rk4_err:e} V");
    // Both integrators solve the same equations: the gap is the doctor's first-order error (it halves
    // with the doctor's step) plus RK4's, and no more.
    assert!(gap_1 <= 1.2 * euler_err + rk4_err + 1e-6, "{what}: gap {gap_1:e} V vs Euler error {euler_err:e} V");
    for (a, b) in [(gap_1, gap_half), (gap_half, gap_quarter)] {
        let ratio = b / a;
        assert!((0.4..0.6).contains(&ratio), "{what}: gap ratio {ratio:.3} on halving the step (first order: 0.5)");
    }
    assert!(gap_richardson < 0.1 * gap_quarter, "{what}: Richardson {gap_richardson:e} V vs {gap_quarter:e} V");
    (gap_1, euler_err)
}

#[test]
fn generator_matches_the_doctors_base_model_to_the_integrator_difference() {
    let (q, r, ambient_k) = (6300.0, 0.14, 297.15);
    let (gap, euler_err) = assert_agree(
        "base",
        CellParams::base(q, r, ambient_k),
        Degradation { q_mobile_c: q, r_o_ohm: r },
        &ExtParams::default(),
    );
    // A real gap: the two are not the same code (Euler at 1 s is a few tenths of a millivolt off).
    assert!(gap > 1e-5 && euler_err > 1e-5, "gap {gap:e} V");
}

#[test]
fn effects_a_candidate_holds_exactly_map_onto_its_parameters() {
    let (q, r, ambient_k) = (6000.0, 0.12, 299.15);
    let base = CellParams::base(q, r, ambient_k);
    let d = Degradation { q_mobile_c: q, r_o_ohm: r };
    let cases = [
        (
            "diffusion",
            CellParams { diffusion_s: 2.6e6, ..base },
            d,
            ExtParams { t_diffusion_s: 2.6e6, ..Default::default() },
        ),
        (
            "extra_polarization",
            CellParams { rc: Some((0.05, 240.0)), ..base },
            d,
            ExtParams { rc_r_ohm: 0.05, rc_tau_s: 240.0, ..Default::default() },
        ),
        (
            "charge_transfer",
            CellParams { exchange_scale: 0.07, ..base },
            d,
            ExtParams { kinetics_scale: 0.07, ..Default::default() },
        ),
        // The generator keeps the electrode capacity and moves the stoichiometry; the doctor's qMobile is
        // the negative electrode's usable charge, so it moves with the negative's shift.
        (
            "electrode_balance",
            CellParams { xp_full: nasa::XP_MIN + 0.06, xn_full: nasa::XN_MAX - 0.08, ..base },
            Degradation { q_mobile_c: base.q_max_c * (nasa::XN_MAX - 0.08 - nasa::XN_MIN), r_o_ohm: r },
            ExtParams { xp_shift: 0.06, xn_shift: -0.08, ..Default::default() },
        ),
    ];
    for (what, p, d, ext) in cases {
        assert_agree(what, p, d, &ext);
    }
}
