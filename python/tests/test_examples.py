"""The examples a user runs (examples/): each runs to its end and says what it found."""

import os
import subprocess
import sys

import pytest

from conftest import REPO

NASA = REPO.parent / "shared" / "data" / "nasa-pcoe"


def run_example(name: str, *args: str, env: dict | None = None) -> str:
    out = subprocess.run([sys.executable, str(REPO / "examples" / name), *args], capture_output=True, text=True,
                         timeout=300, env={**os.environ, **(env or {})})
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_follow_pipe(bcal_cli):
    out = run_example("follow_pipe.py", "--bcal", str(bcal_cli), "--kind", "fit")
    assert "truth: q_mobile 6000 C, r_o 0.14 ohm" in out
    last = out.strip().splitlines()[-1]
    q = float(last.split("q_mobile ")[-1].split(" C")[0])
    assert abs(q - 6000.0) < 300.0, last


@pytest.mark.skipif(not NASA.is_dir(), reason=f"the measured NASA data is not beside the clone ({NASA})")
def test_calibrate_nasa_cell(tmp_path):
    png = tmp_path / "estimates.png"
    out = run_example("calibrate_nasa_cell.py", "--kind", "fit", "--out", str(png))
    assert "B0005 cycle 100:" in out and png.stat().st_size > 10_000
