"""Shared fixtures: the `bcal` CLI binary the Python package is compared with, and a generated discharge
to feed the calibrators (as a DataFrame, and as the CSV the CLI reads)."""

import os
import pathlib
import shutil
import subprocess

import numpy as np
import pandas as pd
import pytest

import bcal

REPO = pathlib.Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def bcal_cli() -> pathlib.Path:
    """The `bcal` binary: $BCAL_BIN, else target/debug/bcal or target/release/bcal of this checkout.
    launch/test.sh builds it and sets BCAL_BIN and BCAL_REQUIRE_CLI=1; run standalone without a built
    CLI, the comparisons with it skip."""
    candidates = [os.environ.get("BCAL_BIN")]
    candidates += [REPO / "target" / "debug" / "bcal", REPO / "target" / "release" / "bcal", shutil.which("bcal")]
    for c in candidates:
        if c and pathlib.Path(c).is_file():
            return pathlib.Path(c)
    msg = "the bcal CLI is not built: cargo build -p bcal --bin bcal, or set BCAL_BIN"
    if os.environ.get("BCAL_REQUIRE_CLI"):
        pytest.fail(msg)
    pytest.skip(msg)


@pytest.fixture(scope="session")
def rl_policy(tmp_path_factory) -> pathlib.Path:
    """A measured-only RL policy file with fixed non-zero weights, written by the Rust test harness
    (`cargo run -p bcal-tests --example write_policy`): Python cannot write one. Without cargo the RL
    comparison skips (with BCAL_REQUIRE_CLI=1, as launch/test.sh runs it, it fails instead)."""
    path = tmp_path_factory.mktemp("policy") / "test.bcalpol"
    cargo = shutil.which("cargo")
    if cargo is None:
        if os.environ.get("BCAL_REQUIRE_CLI"):
            pytest.fail("cargo is needed to write the test policy")
        pytest.skip("cargo is needed to write the test policy")
    out = subprocess.run([cargo, "run", "--quiet", "-p", "bcal-tests", "--example", "write_policy", "--", str(path)],
                         cwd=REPO, capture_output=True, text=True, timeout=1200)
    assert out.returncode == 0, out.stderr
    return path


def run_cli(cli: pathlib.Path, *args: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([str(cli), *args], input=stdin, capture_output=True, text=True, timeout=600)


def generated_discharge(seed: int = 7, q_mobile: float = 6000.0, ro: float = 0.14, current_a: float = 2.0,
                        every_s: int = 10, rest_s: int = 30, noise_v: float = 0.003,
                        thermal: bool = False) -> pd.DataFrame:
    """A cell at (q_mobile, ro) resting `rest_s` seconds, then discharged at `current_a` to VEOD, read every
    `every_s` seconds through `noise_v` of Gaussian voltage noise (seeded). A new cell's state has no
    overpotential and uniform charge, so its rest reads the open-circuit voltage of the simulation's first
    row."""
    sim = bcal.simulate(current_a=current_a, q_mobile=q_mobile, ro=ro, thermal=thermal)
    rng = np.random.default_rng(seed)
    rest_t = np.arange(0, rest_s, every_s, dtype=float)
    keep = (sim["time_s"] % every_s == 0) & (sim["current_a"] > 0)
    time_s = np.concatenate([rest_t, rest_s + sim["time_s"][keep]])
    voltage_v = np.concatenate([np.full(rest_t.size, sim["voltage_v"][0]), sim["voltage_v"][keep]])
    current = np.concatenate([np.zeros(rest_t.size), sim["current_a"][keep]])
    temperature_c = np.concatenate([np.full(rest_t.size, sim["temperature_c"][0]), sim["temperature_c"][keep]])
    voltage_v = voltage_v + rng.normal(0.0, noise_v, voltage_v.size)
    return pd.DataFrame({"time_s": time_s, "voltage_v": np.round(voltage_v, 6), "current_a": current,
                         "temperature_c": temperature_c})
