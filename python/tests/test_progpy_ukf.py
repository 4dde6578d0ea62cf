"""A sanity anchor: progpy's own UnscentedKalmanFilter beside bcal.Calibrator("ukf") on one simulated
discharge (the same noisy readings). progpy's filter estimates the model's state with the true qMobile
and Ro given; bcal's joint UKF estimates state and both parameters from its prior (5500 C, 0.15 ohm).
They are different filters with different knowledge, so the anchor is not equality: both must find the
cell's charge, and bcal's must land near the truth that progpy was handed.

Setting: a thermal cell (progpy always heats; bcal.simulate(thermal=True)) at qMobile 6000 C, Ro 0.14
ohm, 30 s rest then 2 A to 3.0 V, read every 10 s with 3 mV voltage noise and the simulated temperature.
progpy's filter steps its model every 1 s between readings (its `dt`); its noise: Q as progpy's default
(1e-3 on every state), R from the sensor (0.5 K, 3 mV).
"""

import numpy as np
import pytest

import bcal
from conftest import generated_discharge

progpy_models = pytest.importorskip("progpy.models", reason="progpy is installed by launch/test.sh")
progpy_se = pytest.importorskip("progpy.state_estimators")
uncertain = pytest.importorskip("progpy.uncertain_data")

Q_MOBILE, RO = 6000.0, 0.14


def xn(state: dict, q_mobile: float) -> float:
    """Negative-electrode mole fraction: charge in the negative electrode / qMax."""
    return (state["qnB"] + state["qnS"]) / (q_mobile / 0.6)


def test_progpy_ukf_and_bcal_joint_ukf_find_the_same_charge():
    cal = bcal.Calibrator("ukf")
    df = generated_discharge(q_mobile=Q_MOBILE, ro=RO, thermal=True)
    truth = bcal.simulate(current_a=2.0, q_mobile=Q_MOBILE, ro=RO, thermal=True)

    m = progpy_models.BatteryElectroChemEOD(qMobile=Q_MOBILE, Ro=RO)
    x0 = m.initialize()
    cov = np.diag([1e-3] * len(m.states))
    filt = progpy_se.UnscentedKalmanFilter(
        m, uncertain.MultivariateNormalDist(x0.keys(), list(x0.values()), cov), dt=1.0,
        R=np.diag([0.5**2, 0.003**2]))

    ours, theirs, true_xn = [], [], []
    for r in df.itertuples():
        e = cal.step(r.time_s, r.voltage_v, r.current_a, r.temperature_c)
        filt.estimate(r.time_s, {"i": r.current_a}, {"t": r.temperature_c, "v": r.voltage_v})
        if r.current_a > 0:
            mean = filt.x.mean
            theirs.append(xn(mean, Q_MOBILE))
            ours.append(xn(cal.state(), e["q_mobile"]))
            k = int(r.time_s) - 30  # the simulation's row at this reading (the rest came first)
            true_xn.append(xn({n: truth["state"][n][k] for n in ("qnB", "qnS")}, Q_MOBILE))
    ours, theirs, true_xn = map(np.asarray, (ours, theirs, true_xn))
    second_half = slice(len(ours) // 2, None)
    # progpy's filter, handed the true parameters, tracks the charge closely.
    assert np.abs(theirs - true_xn)[second_half].max() < 0.02
    # bcal's joint filter, from its prior, agrees with it within 0.01 of a mole fraction in the second half
    # (measured: 0.003) ...
    assert np.abs(ours - theirs)[second_half].max() < 0.01
    # ... and lands within 2 % of the parameters progpy was given (measured: 0.2 % and 0.4 %).
    assert abs(e["q_mobile"] - Q_MOBILE) / Q_MOBILE < 0.02
    assert abs(e["r_o"] - RO) / RO < 0.02
    print(f"second half: max |xn progpy - truth| = {np.abs(theirs - true_xn)[second_half].max():.4f}, "
          f"max |xn bcal - xn progpy| = {np.abs(ours - theirs)[second_half].max():.4f}; "
          f"final q_mobile {e['q_mobile']:.0f} C, r_o {e['r_o']:.4f} ohm")
