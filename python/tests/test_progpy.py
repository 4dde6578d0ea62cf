"""bcal's model against progpy's own BatteryElectroChemEOD (the implementation it is taken from), side by
side on the same parameters, loads and steps: constant power, constant current and a load step.

Conventions (python/README.md has the full table): progpy's qMobile / Ro are bcal's q_mobile / ro; progpy
always runs the thermal state (tb with self-heating), so bcal runs with thermal=True here (bcal's default
is isothermal at 292.1 K: 1 s earlier EOD at 8 W, see test_isothermal_default_differs_by_the_heat);
progpy's input is the current i (positive while discharging, as bcal's), so a power load is a
future_loading function returning P / v(x) at the state the step starts from, which is what bcal does;
progpy evaluates the load at the step's midpoint t + dt/2, which for dt = 1 s and load steps on whole
seconds is the segment in force at t, as in bcal; progpy's EOD threshold is v < VEOD = 3.0 V at a saved
step, bcal's the first step below 3.0 V: the same time.

Tolerance, derived. Both integrate x[k+1] = x[k] + dt f(x[k], u[k]) by explicit Euler with dt = 1 s and
the same expressions, so they differ only by rounding (a different order of operations: the
Redlich-Kister sum, powers by repeated products against `**`, arcsinh, the state limits):
  - one voltage evaluation: 13 Redlich-Kister terms of at most max|A_k| / F = 1.07e6 / 96487 = 11 V each,
    rounded at eps = 2.2e-16: 13 * 11 V * eps = 3e-14 V;
  - one state step: charges up to q_max = qMobile / 0.6 = 12 667 C rounded at eps: 3e-12 C per step, which
    after N steps is at most N * 3e-12 C (no growth: the dynamics are contracting, time constants of
    6-1000 s and 7e6 s for diffusion). A surface charge error moves the voltage by
    dV/dx_s * dq / q_smax with q_smax = 0.1 q_max = 1267 C and |dV/dx_s| <= 10 V per unit mole
    fraction over the discharge (the steepest part of the Redlich-Kister curves before VEOD):
    N * 3e-12 * 10 / 1267 = N * 2.4e-14 V; for N = 3100 steps, 7e-11 V.
So |V_bcal - V_progpy| <= N * 2.4e-14 + 3e-14 V, and we allow ten times that (volt_tol below). The EOD
then falls on the same step unless a step's voltage lies within that tolerance of 3.0 V, which the test
checks rather than assumes (near EOD the voltage falls by about 5 mV per step).
"""

import numpy as np
import pytest

import bcal

progpy_models = pytest.importorskip("progpy.models", reason="progpy is installed by launch/test.sh")

EPS = np.finfo(float).eps
RK_TERM_V = 1.07469e6 / 96487.0  # largest Redlich-Kister coefficient / F
DV_DXS_MAX = 10.0  # V per unit surface mole fraction, steepest before VEOD


def volt_tol(steps: int, q_mobile: float) -> float:
    """Ten times the rounding bound of the module docstring for `steps` Euler steps."""
    q_max = q_mobile / 0.6
    q_smax = 0.1 * q_max
    per_step_v = q_max * EPS * DV_DXS_MAX / q_smax
    return 10.0 * (steps * per_step_v + 13 * RK_TERM_V * EPS)


def run_progpy(q_mobile: float, ro: float, load_w=None, current_a=None, step=None, dt=1.0,
               integration_method="euler"):
    """progpy's BatteryElectroChemEOD to its EOD threshold with a constant step `dt`, every step saved.
    `step`: (start_s, value) of a load step in the load's unit."""
    m = progpy_models.BatteryElectroChemEOD(qMobile=q_mobile, Ro=ro)

    def value_at(t):
        first = load_w if load_w is not None else current_a
        return step[1] if step is not None and t >= step[0] else first

    def future_loading(t, x=None):
        if x is None:  # progpy's first call, before a state exists (its value is not used)
            return m.InputContainer({"i": 0.0})
        if load_w is not None:
            return m.InputContainer({"i": value_at(t) / m.output(x)["v"]})
        return m.InputContainer({"i": value_at(t)})

    r = m.simulate_to_threshold(future_loading, dt=dt, save_freq=dt, events="EOD",
                                integration_method=integration_method)
    times = np.asarray(r.times, dtype=float)
    volts = np.array([float(z["v"]) for z in r.outputs])
    tb = np.array([float(x["tb"]) for x in r.states])
    return times, volts, tb


CASES = [
    # (id, bcal.simulate kwargs, run_progpy kwargs)
    ("8 W", {"load_w": 8.0}, {"load_w": 8.0}),
    ("2 A, aged", {"current_a": 2.0, "q_mobile": 6000.0, "ro": 0.15}, {"current_a": 2.0, "q_mobile": 6000.0, "ro": 0.15}),
    ("8 W then 16 W at 1000 s", {"load_w": 8.0, "steps": [(1000.0, 16.0)]}, {"load_w": 8.0, "step": (1000.0, 16.0)}),
]


@pytest.mark.parametrize("name, ours, theirs", CASES, ids=[c[0] for c in CASES])
def test_same_voltages_and_eod_as_progpy(name, ours, theirs):
    q_mobile = ours.get("q_mobile", 7600.0)
    ro = ours.get("ro", 0.117215)
    r = bcal.simulate(thermal=True, **ours)
    t_p, v_p, tb_p = run_progpy(q_mobile, ro, **{k: v for k, v in theirs.items() if k not in ("q_mobile", "ro")})
    # Same time grid (dt = 1 s from 0) to the shorter run's end.
    n = min(r["time_s"].size, t_p.size)
    np.testing.assert_array_equal(r["time_s"][:n], t_p[:n])
    tol = volt_tol(n, q_mobile)
    diff = np.abs(r["voltage_v"][:n] - v_p[:n])
    assert diff.max() <= tol, f"{name}: max |dV| {diff.max():.3e} V at t = {t_p[diff.argmax()]} s > {tol:.2e} V"
    # The thermal state too: a different temperature would show in the voltage, but check it directly.
    np.testing.assert_allclose(r["state"]["tb"][:n], tb_p[:n], rtol=0, atol=1e-9)
    # EOD: the same step, unless some step sits within the tolerance of VEOD (checked, not assumed).
    margin = np.abs(v_p - bcal.VEOD_V).min()
    assert margin > tol, f"{name}: a step lies {margin:.2e} V from VEOD; the EOD step is not decidable"
    assert r["eod_s"] == t_p[-1], f"{name}: EOD bcal {r['eod_s']} s, progpy {t_p[-1]} s"
    print(f"{name}: {n} steps, max |dV| = {diff.max():.2e} V (tolerance {tol:.1e} V), EOD {r['eod_s']:.0f} s both")


def test_isothermal_default_differs_by_the_heat():
    """bcal's default (isothermal at progpy's initial 292.1 K) is not progpy: the cell heats by 2.7 K at 8 W,
    which moves the voltage by 26 uV at 100 s, 1 mV at 2000 s and 7 mV at the end (the RT/F terms and the
    Butler-Volmer overpotentials follow tb), and the isothermal discharge ends one step (1 s) later."""
    iso = bcal.simulate(load_w=8.0)
    thermal = bcal.simulate(load_w=8.0, thermal=True)
    t_p, v_p, tb_p = run_progpy(7600.0, 0.117215, load_w=8.0)
    assert (iso["eod_s"], thermal["eod_s"], t_p[-1]) == (3102.0, 3101.0, 3101.0)
    assert tb_p[-1] - tb_p[0] == pytest.approx(2.65, abs=0.05)
    gap = np.abs(iso["voltage_v"][: t_p.size] - v_p)
    assert 1e-5 < gap[100] < 1e-4 and 1e-3 < gap.max() < 2e-2, (gap[100], gap.max())


def test_integration_error_of_euler_against_progpy_rk4():
    """The Euler step itself: progpy's RK4 at dt = 1 s is the reference and bcal's Euler is off by its global
    error, O(dt). Derived tolerance: Richardson's estimate from bcal alone, |V(dt) - V(dt/2)| (the error at
    dt is about twice it), with a factor 2 of margin and the rounding bound on top."""
    kw = {"current_a": 2.0, "q_mobile": 6000.0, "ro": 0.15}
    coarse = bcal.simulate(thermal=True, dt_s=1.0, **kw)
    fine = bcal.simulate(thermal=True, dt_s=0.5, **kw)
    t_p, v_p, _ = run_progpy(6000.0, 0.15, current_a=2.0, integration_method="rk4")
    n = min(coarse["time_s"].size, t_p.size) - 30  # leave out the knee, where the error grows by the slope
    richardson = np.abs(coarse["voltage_v"][:n] - fine["voltage_v"][: 2 * n : 2])
    bound = 2.0 * 2.0 * richardson + volt_tol(n, 6000.0)
    diff = np.abs(coarse["voltage_v"][:n] - v_p[:n])
    assert (diff <= bound).all(), f"max excess {np.max(diff - bound):.2e} V at t = {t_p[np.argmax(diff - bound)]} s"
    # And the error is really the step's: not at rounding level.
    assert diff.max() > 100 * volt_tol(n, 6000.0)
    print(f"Euler vs RK4 at dt = 1 s: max |dV| = {diff.max():.2e} V, Richardson bound max {bound.max():.2e} V")
