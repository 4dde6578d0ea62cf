"""bcal.Calibrator against `bcal calibrate --follow`: a generated discharge fed one reading at a time gives
the same estimates, intervals and EOD predictions, float for float, as the CLI gives on the same
readings; DataFrames, errors and the model state."""

import json
import math

import numpy as np
import pandas as pd
import pytest

import bcal
from conftest import generated_discharge, run_cli

KINDS = ["ukf", "adaptive_ukf", "ukf_learned", "fit", "uncalibrated"]
FIELDS = ["time_s", "q_mobile", "q_mobile_lo", "q_mobile_hi", "r_o", "r_o_lo", "r_o_hi", "eod_s", "eod_current_a",
          "eod_power_w", "eod_lo_s", "eod_hi_s", "delivered_ah", "delivered_lo_ah", "delivered_hi_ah", "eod_from_prior",
          "eod_recentred", "eod_on_voltage_change", "eod_prior_weight", "eod_previous_weight", "eod_learned_weight", "discharge"]


def make(kind: str, **kw) -> bcal.Calibrator:
    return bcal.Calibrator(kind, **kw)


@pytest.fixture(scope="module")
def discharge() -> pd.DataFrame:
    return generated_discharge()


@pytest.mark.parametrize("kind", KINDS)
def test_step_by_step_equals_the_cli_follow(bcal_cli, discharge, kind):
    cal = make(kind)
    ours = [cal.step(r.time_s, r.voltage_v, r.current_a, r.temperature_c) for r in discharge.itertuples()]
    out = run_cli(bcal_cli, "calibrate", "--follow", "-", "--calibrator", kind,
                  stdin=discharge.to_csv(index=False, float_format="%.17g"))
    assert out.returncode == 0, out.stderr
    theirs = [json.loads(line) for line in out.stdout.splitlines()]
    assert len(theirs) == len(ours) == len(discharge)
    for k, (a, b) in enumerate(zip(ours, theirs)):
        assert b["line"] == k + 2  # the header is line 1
        for f in FIELDS:
            assert a[f] == b[f], f"{kind}, reading {k}, {f}: python {a[f]!r}, cli {b[f]!r}"
    assert f"end of input: {len(discharge)} readings taken, 0 bad lines skipped" in out.stderr
    if kind != "uncalibrated":
        # It calibrates: by the end the estimate has left the prior (5500 C, 0.15 ohm) towards the truth.
        q_end, r_end = ours[-1]["q_mobile"], ours[-1]["r_o"]
        assert abs(q_end - 6000.0) < abs(5500.0 - 6000.0), q_end
        assert abs(r_end - 0.14) < abs(0.15 - 0.14), r_end


def test_an_rl_policy_file_gives_the_cli_s_estimates(bcal_cli, discharge, rl_policy):
    cal = make("rl", policy=rl_policy)
    ours = [cal.step(r.time_s, r.voltage_v, r.current_a, r.temperature_c) for r in discharge.itertuples()]
    out = run_cli(bcal_cli, "calibrate", "--follow", "-", "--calibrator", f"rl:{rl_policy}",
                  stdin=discharge.to_csv(index=False, float_format="%.17g"))
    assert out.returncode == 0, out.stderr
    theirs = [json.loads(line) for line in out.stdout.splitlines()]
    assert [[a[f] for f in FIELDS] for a in ours] == [[b[f] for f in FIELDS] for b in theirs]
    assert any(abs(a["q_mobile"] - 5500.0) > 1.0 for a in ours), "the policy moves the estimate"


def test_run_on_a_dataframe_equals_stepping(discharge):
    frame = make("fit").run(discharge)
    assert list(frame.columns) == FIELDS + ["row"]
    assert frame["row"].tolist() == list(range(len(discharge)))
    cal = make("fit")
    for r, row in zip(discharge.itertuples(), frame.itertuples()):
        e = cal.step(r.time_s, r.voltage_v, r.current_a, r.temperature_c)
        for f in FIELDS:
            want = math.nan if e[f] is None else e[f]
            got = getattr(row, f)
            assert got == want or (math.isnan(got) and math.isnan(want)), (f, got, want)


def test_a_missing_temperature_is_read_as_in_the_cli(bcal_cli, discharge):
    """A NaN temperature in a DataFrame and an empty CSV field on the CLI's stream are the same reading
    without one (the last reading's temperature stands in, `stream::tests::a_reading_without_a_temperature_
    takes_the_last_ones`), in `run` and in `step`."""
    gappy = discharge.copy()
    gappy.loc[3:9, "temperature_c"] = np.nan
    frame = make("ukf").run(gappy)
    csv = gappy.to_csv(index=False, float_format="%.17g")  # NaN is written as an empty field
    out = run_cli(bcal_cli, "calibrate", "--follow", "-", "--calibrator", "ukf", stdin=csv)
    assert out.returncode == 0, out.stderr
    theirs = [json.loads(line) for line in out.stdout.splitlines()]
    assert [b["q_mobile"] for b in theirs] == frame["q_mobile"].tolist()
    cal = make("ukf")
    stepped = [cal.step(r.time_s, r.voltage_v, r.current_a, r.temperature_c)["q_mobile"] for r in gappy.itertuples()]
    assert stepped == frame["q_mobile"].tolist()


def test_columns_in_other_units_are_read_as_their_names_say_in_both_faces(bcal_cli, discharge):
    milli = pd.DataFrame({"time_ms": discharge["time_s"] * 1000.0, "voltage_mv": discharge["voltage_v"] * 1000.0,
                          "current_ma": discharge["current_a"] * 1000.0, "temperature_c": discharge["temperature_c"]})
    # The same readings in s, V and A, converted as the readers convert (times 1e-3).
    si = pd.DataFrame({"time_s": milli["time_ms"] * 1e-3, "voltage_v": milli["voltage_mv"] * 1e-3,
                       "current_a": milli["current_ma"] * 1e-3, "temperature_c": milli["temperature_c"]})
    frame = make("ukf").run(milli)
    assert frame["q_mobile"].tolist() == make("ukf").run(si)["q_mobile"].tolist()
    out = run_cli(bcal_cli, "calibrate", "--follow", "-", "--calibrator", "ukf",
                  stdin=milli.to_csv(index=False, float_format="%.17g"))
    assert out.returncode == 0, out.stderr
    assert [json.loads(line)["q_mobile"] for line in out.stdout.splitlines()] == frame["q_mobile"].tolist()
    with pytest.raises(ValueError, match="no voltage among"):
        make("ukf").run(milli.rename(columns={"voltage_mv": "volts"}))


def test_two_discharges_in_one_stream_are_counted_and_the_second_starts_from_the_first(bcal_cli, discharge):
    # The same discharge again three hours after the first ended (its charge unseen).
    later = discharge.assign(time_s=discharge["time_s"] + discharge["time_s"].iloc[-1] + 3 * 3600.0)
    both = pd.concat([discharge, later], ignore_index=True)
    frame = make("ukf").run(both)
    n = len(discharge)
    assert frame["discharge"].tolist() == [0] * n + [1] * n
    # The second starts from what the first told: the charge its end measured where a loaded reading fell
    # below the cut-off (3.0 V), else the estimate it ended with.
    first = discharge[discharge["current_a"] > 0.05]
    if (first["voltage_v"] < 3.0).any():
        assert abs(frame["q_mobile"].iloc[n] / 6000.0 - 1.0) < 0.03, frame["q_mobile"].iloc[n]
    else:
        assert frame["q_mobile"].iloc[n] == frame["q_mobile"].iloc[n - 1], "the second starts where the first ended"
    assert math.isnan(frame["eod_current_a"].iloc[n]) and frame["eod_current_a"].iloc[n + 5] > 1.0
    out = run_cli(bcal_cli, "calibrate", "--follow", "-", "--calibrator", "ukf",
                  stdin=both.to_csv(index=False, float_format="%.17g"))
    assert out.returncode == 0, out.stderr
    theirs = [json.loads(line) for line in out.stdout.splitlines()]
    assert [b["discharge"] for b in theirs] == frame["discharge"].tolist()
    assert [b["q_mobile"] for b in theirs] == frame["q_mobile"].tolist()
    assert "; 2 discharges" in out.stderr
    # A cell within the ranges: the first discharge's fit is handed on away from their edges.
    cal = make("ukf")
    cal.run(both)
    assert cal.range_edges == {"discharges": 1, "at_edge": 0, "q_mobile_floor": 0, "q_mobile_top": 0,
                               "r_o_floor": 0, "r_o_top": 0}
    assert "at the edge of the setting's ranges" not in out.stderr


def test_a_cell_outside_the_ranges_is_said_in_both_faces(bcal_cli):
    # Resistance 0.4 ohm, above the default range's 0.25: the fits are handed on at its top.
    one = generated_discharge(ro=0.4)
    gap_s = one["time_s"].iloc[-1] + 3 * 3600.0
    three = pd.concat([one.assign(time_s=one["time_s"] + k * gap_s) for k in range(3)], ignore_index=True)
    cal = make("ukf")
    cal.run(three)
    edges = cal.range_edges
    assert edges["discharges"] == 2 and edges["at_edge"] >= 1, edges
    assert edges["r_o_top"] == edges["at_edge"] and edges["q_mobile_floor"] + edges["q_mobile_top"] == 0, edges
    out = run_cli(bcal_cli, "calibrate", "--follow", "-", "--calibrator", "ukf",
                  stdin=three.to_csv(index=False, float_format="%.17g"))
    assert out.returncode == 0, out.stderr
    n = edges["at_edge"]
    said = f"{n} of 2 discharges handed on a fit at the edge of the setting's ranges (r_o at its top, 0.25 ohm: {n})"
    assert said in out.stderr and "bcal cell-config" in out.stderr, out.stderr
    # Two in a row at the top: the third discharge runs on a range widened by its span (0.05-0.45 ohm).
    widened = cal.widened_ranges
    assert (widened is not None) == (edges["r_o_top"] >= 2), (widened, edges)
    if widened is not None:
        assert widened[1] == pytest.approx([0.05, 0.45]), widened
        assert "the stream widened them, to qMobile" in out.stderr and "Ro 0.050-0.450 ohm" in out.stderr, out.stderr


def test_run_names_a_missing_column_and_a_bad_row(discharge):
    with pytest.raises(ValueError, match="the DataFrame's columns: no voltage among"):
        make("fit").run(discharge.drop(columns=["voltage_v"]))
    bad = discharge.copy()
    bad.loc[7, "time_s"] = bad.loc[5, "time_s"]
    cal = make("fit")
    with pytest.raises(ValueError, match=r"row 7: time_s = 50 does not increase \(previous reading 60\)"):
        cal.run(bad)
    assert cal.readings == 7


def test_a_bad_reading_is_a_value_error_with_the_cli_s_message_and_changes_nothing(bcal_cli, discharge):
    cal = make("fit")
    rows = list(discharge.itertuples())
    for r in rows[:5]:
        cal.step(r.time_s, r.voltage_v, r.current_a, r.temperature_c)
    with pytest.raises(ValueError) as e:
        cal.step(rows[2].time_s, rows[2].voltage_v, rows[2].current_a)
    message = str(e.value)
    assert message == "time_s = 20 does not increase (previous reading 40); readings must come in time order"
    with pytest.raises(ValueError, match="field `voltage_v` = NaN is not a finite number"):
        cal.step(100.0, float("nan"), 2.0)
    with pytest.raises(ValueError, match="outside a Li-ion cell's range"):
        cal.step(100.0, 3900.0, 2.0)
    # A lone spike the voltage does not follow (40 A more, the last voltage): a logger's glitch.
    with pytest.raises(ValueError, match="a logger's glitch"):
        cal.step(100.0, rows[4].voltage_v, rows[4].current_a + 40.0)
    assert cal.readings == 5
    # The CLI skips the same reading with the same words, naming its line.
    text = "time_s,voltage_v,current_a\n" + "".join(f"{r.time_s},{r.voltage_v},{r.current_a}\n" for r in rows[:5])
    text += f"{rows[2].time_s},{rows[2].voltage_v},{rows[2].current_a}\n"
    out = run_cli(bcal_cli, "calibrate", "--follow", "-", "--calibrator", "fit", stdin=text)
    assert out.returncode == 0, out.stderr
    assert f"line 7: {message}; skipped" in out.stderr, out.stderr


def test_unknown_kind_and_missing_policy_are_refused_as_the_cli_refuses_them(bcal_cli, tmp_path):
    with pytest.raises(ValueError) as e:
        make("kalman")
    assert str(e.value) == "unknown calibrator `kalman`: use ukf, adaptive_ukf, ukf_learned, rl (with a policy file), fit or uncalibrated"
    out = run_cli(bcal_cli, "calibrate", "--follow", "-", "--calibrator", "kalman", stdin="")
    assert out.returncode != 0 and str(e.value) in out.stderr, out.stderr
    with pytest.raises(ValueError, match="the rl calibrator needs a policy file"):
        make("rl")
    with pytest.raises(ValueError, match="a policy file is only read by the rl calibrator, not by fit"):
        make("fit", policy=tmp_path / "p.bcalpol")
    with pytest.raises(FileNotFoundError, match="p.bcalpol"):
        make("rl", policy=tmp_path / "p.bcalpol")
    with pytest.raises(FileNotFoundError, match="diagnosis.json"):
        make("fit", model=tmp_path)


def test_prediction_state_and_spec(discharge):
    cal = make("fit")
    assert cal.state() is None and cal.predict_eod_s(2.0) is None
    half = len(discharge) // 2
    for r in discharge.iloc[:half].itertuples():
        e = cal.step(r.time_s, r.voltage_v, r.current_a, r.temperature_c)
    assert e["eod_current_a"] == pytest.approx(2.0)
    assert e["eod_s"] == cal.predict_eod_s(e["eod_current_a"])
    assert e["time_s"] < cal.predict_eod_s(4.0) < e["eod_s"]
    # Halfway through, the predicted end is within 10 % of where the readings end (the cell reaches 3.0 V).
    assert abs(e["eod_s"] - discharge["time_s"].iloc[-1]) < 0.1 * discharge["time_s"].iloc[-1]
    x = cal.state()
    assert set(x) == {"qpS", "qpB", "qnB", "qnS", "Vo", "Vsn", "Vsp", "tb"}
    assert x["tb"] == pytest.approx(292.1)
    spec = cal.spec
    assert spec["cutoff_v"] == 3.0 and spec["prior"] == {"q_mobile_c": 5500.0, "r_o_ohm": 0.15}
    assert repr(cal) == f"Calibrator('fit', readings={half})"
    with pytest.raises(ValueError, match="current_a: -1 must be greater than 0"):
        cal.predict_eod_s(-1.0)
    # At the power the cell now draws the current rises as the voltage falls: the end comes sooner.
    now_w = e["eod_current_a"] * discharge["voltage_v"].iloc[half - 1]
    assert e["time_s"] < cal.predict_eod_s(power_w=now_w) < cal.predict_eod_s(e["eod_current_a"])
    for both_or_none in [dict(current_a=2.0, power_w=8.0), {}]:
        with pytest.raises(ValueError, match="one of current_a"):
            cal.predict_eod_s(**both_or_none)
    with pytest.raises(ValueError, match="power_w: 0 must be greater than 0"):
        cal.predict_eod_s(power_w=0.0)
    # A higher cut-off ends sooner; the same readings otherwise.
    high = make("fit", cutoff_v=3.3)
    for r in discharge.iloc[:half].itertuples():
        h = high.step(r.time_s, r.voltage_v, r.current_a, r.temperature_c)
    assert h["q_mobile"] == e["q_mobile"] and h["eod_s"] < e["eod_s"]
    with pytest.raises(ValueError, match="cutoff_v: 0 must be greater than 0"):
        make("fit", cutoff_v=0.0)


def test_a_diagnosis_gives_its_cut_off_where_it_was_the_cell_s_own(tmp_path):
    # As `bcal calibrate --follow --model`: the diagnosis's cut-off when none is given, not the doctor's default.
    def diagnosis(given: bool):
        d = tmp_path / f"given-{given}"
        d.mkdir(exist_ok=True)
        (d / "diagnosis.json").write_text(json.dumps({
            "cell": "B0005", "settings": {"cutoff_v": 2.7, "cutoff_given": given},
            "extended": {"causes": [], "params": {}}}))
        return d
    assert make("ukf", model=diagnosis(True)).spec["cutoff_v"] == 2.7
    assert make("ukf", model=diagnosis(True), cutoff_v=3.1).spec["cutoff_v"] == 3.1
    assert make("ukf", model=diagnosis(False)).spec["cutoff_v"] == 3.0
