"""bcal.diagnose against `bcal diagnose`: on measured NASA cycles the dict is diagnosis.json, and bad
input is refused with the CLI's words."""

import json

import pytest

import bcal
from conftest import REPO, run_cli

NASA = REPO.parent / "shared" / "data" / "nasa-pcoe"


@pytest.mark.skipif(not NASA.is_dir(), reason=f"the measured NASA data is not beside the clone ({NASA})")
def test_diagnosis_equals_the_cli_s_diagnosis_json(bcal_cli, tmp_path):
    ours = bcal.diagnose(NASA, cell="B0005", cycles="1..3", holdout="4..5")
    out = run_cli(bcal_cli, "diagnose", "--data", str(NASA), "--cell", "B0005", "--cycles", "1..3",
                  "--holdout", "4..5", "--no-plots", "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    theirs = json.loads((tmp_path / "diagnosis.json").read_text())
    assert ours.pop("cutoff_source") == "the cell's documented protocol (extra_infos)"
    assert any("discharge negative" in n for n in ours.pop("read_notes"))
    assert ours == theirs
    assert ours["cell"] == "B0005" and ours["cause"] in ours["ranking"] + ["none"]


def test_bad_input_is_refused_with_the_cli_s_message(bcal_cli, tmp_path):
    with pytest.raises(FileNotFoundError, match="no-such.csv"):
        bcal.diagnose(tmp_path / "no-such.csv")
    with pytest.raises(ValueError) as e:
        bcal.diagnose(tmp_path)
    assert "is a NASA folder: pass --cell with one of its battery_id values" in str(e.value)
    out = run_cli(bcal_cli, "diagnose", "--data", str(tmp_path), "--out", str(tmp_path / "out"))
    assert out.returncode != 0 and str(e.value) in out.stderr, out.stderr
    with pytest.raises(ValueError, match=r"cycle range `1-3` is not A..B"):
        bcal.diagnose(tmp_path, cell="B0005", cycles="1-3")
    with pytest.raises(ValueError, match="current sign `up` is none of auto, discharge-positive, discharge-negative"):
        bcal.diagnose(tmp_path, current_sign="up")
