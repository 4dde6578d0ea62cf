"""bcal.simulate against `bcal simulate`: the same EOD, the same rows to the last digit, the same
error messages."""

import numpy as np
import pytest

import bcal
from conftest import run_cli


def test_eod_at_8_w_is_the_cli_s(bcal_cli):
    r = bcal.simulate(load_w=8.0)
    assert r["eod_s"] == 3102.0
    out = run_cli(bcal_cli, "simulate", "--load-w", "8")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"EOD {r['eod_s']:.0f} s"), out.stdout
    assert r["time_s"].size == 3103 and r["time_s"].dtype == np.float64
    assert r["voltage_v"][-1] < bcal.VEOD_V <= r["voltage_v"][-2]


def test_every_row_equals_the_cli_csv(bcal_cli, tmp_path):
    path = tmp_path / "sim.csv"
    out = run_cli(bcal_cli, "simulate", "--current-a", "2", "--q-mobile", "6500", "--ro", "0.15", "--thermal",
                  "--out", str(path))
    assert out.returncode == 0, out.stderr
    cli = np.genfromtxt(path, delimiter=",", names=True)
    r = bcal.simulate(current_a=2.0, q_mobile=6500.0, ro=0.15, thermal=True)
    # The CLI prints shortest round-trip decimals: equal floats, not close ones.
    np.testing.assert_array_equal(cli["t_s"], r["time_s"])
    np.testing.assert_array_equal(cli["voltage_v"], r["voltage_v"])
    for name in ["qpS", "qpB", "qnB", "qnS", "Vo", "Vsn", "Vsp"]:
        np.testing.assert_array_equal(cli[name], r["state"][name])
    np.testing.assert_array_equal(cli["tb_k"], r["state"]["tb"])
    np.testing.assert_allclose(r["temperature_c"], r["state"]["tb"] - 273.15)
    assert r["state"]["tb"][-1] > r["state"]["tb"][0] + 0.3, "the thermal cell heats under 2 A"


def test_a_load_step_switches_the_current():
    r = bcal.simulate(load_w=8.0, steps=[(1000.0, 16.0)])
    k = 1000
    assert r["time_s"][k] == 1000.0
    assert r["current_a"][k - 1] == pytest.approx(8.0 / r["voltage_v"][k - 1], rel=1e-15)
    assert r["current_a"][k] == pytest.approx(16.0 / r["voltage_v"][k], rel=1e-15)
    assert r["eod_s"] < bcal.simulate(load_w=8.0)["eod_s"]


@pytest.mark.parametrize(
    "kwargs, cli_args, message",
    [
        # The CLI's clap refuses this one itself (an argument group); the library's message names its flags.
        ({}, None, "give exactly one of --load-w or --current-a"),
        ({"load_w": -1.0}, ["--load-w=-1"], "-1 must be greater than 0"),
        ({"current_a": 2.0, "ro": -0.1}, ["--current-a", "2", "--ro=-0.1"], "-0.1 must not be negative"),
        ({"current_a": 0.001, "max_steps": 10}, ["--current-a", "0.001", "--max-steps", "10"],
         "the voltage stayed above VEOD for 10 steps (10 s); raise --max-steps or the load"),
    ],
)
def test_errors_are_value_errors_with_the_cli_s_message(bcal_cli, kwargs, cli_args, message):
    with pytest.raises(ValueError) as e:
        bcal.simulate(**kwargs)
    assert message in str(e.value)
    if cli_args is None:
        return
    out = run_cli(bcal_cli, "simulate", *cli_args)
    assert out.returncode != 0
    assert message in out.stderr, out.stderr
