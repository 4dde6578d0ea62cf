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


def test_eod_by_age_scores_each_discharge_as_calibrate_does(tmp_path):
    """Two hand-made discharges (load on at 10 s, cut-off 2.5 V crossed at 1010 s by interpolation): the
    prediction at the first reading at or after 50 % counts, in % of the 1000 s discharge."""
    run = tmp_path / "cal"
    (run / "readings").mkdir(parents=True)
    (run / "calibration.json").write_text('{"cutoff_v": 2.5}')
    head = "t_s,voltage_v,current_a,q_mobile_c,q_mobile_lo_c,q_mobile_hi_c,r_o_ohm,r_o_lo_ohm,r_o_hi_ohm,eod_s\n"
    # (method, cycle) -> the end of discharge it predicts at 510 s (50 %) and at every other reading.
    predictions = {("rl", 41): (1030.0, 0.0), ("ukf", 41): (1000.0, 0.0), ("rl", 90): (1011.0, 9e9),
                   ("ukf", 90): (1050.0, 9e9)}
    for (method, cycle), (at_half, elsewhere) in predictions.items():
        d = run / "readings" / method
        d.mkdir(exist_ok=True)
        rows = [(0.0, 4.2, 0.0), (10.0, 4.0, 2.0), (510.0, 3.6, 2.0), (1000.0, 2.6, 2.0), (1020.0, 2.4, 2.0)]
        lines = [f"{t},{v},{i},0,0,0,0,0,0,{at_half if t == 510.0 else elsewhere}" for t, v, i in rows]
        (d / f"B0000-{cycle:04d}.csv").write_text(head + "\n".join(lines) + "\n")
    out = run_example("eod_by_age.py", str(run), "--bins", "41-80,81-120")
    # rl: |1030 - 1010| / 1000 = 2 %, |1011 - 1010| = 0.1 %; ukf: 1 %, 4 %.
    assert "41-80: 2.00 against 1.00 %, better on 0 of 1" in out, out
    assert "81-120: 0.10 against 4.00 %, better on 1 of 1" in out, out


def test_previous_discharge_signal_recovers_the_slope_it_was_made_with(tmp_path):
    """A hand-made NASA folder whose discharges last 3000 s plus 5000 s per volt their voltage reads above
    the discharge before at the same time: the slope comes back, the corrected ends are exact, and the
    duration carried as it is misses by the change."""
    import random

    rng = random.Random(7)
    (tmp_path / "data").mkdir()
    meta = ["type,start_time,ambient_temperature,battery_id,test_id,uid,filename,Capacity,Re,Rct"]
    for k in range(1, 15):
        offset_v = 0.002 * rng.randint(-5, 5)
        duration_s = 3000.0 + 5000.0 * offset_v  # a multiple of 10 s: a reading lands on the crossing
        knee_s = duration_s - 100.0
        knee_v = 4.0 + offset_v - 0.0005 * knee_s
        rows = ["Voltage_measured,Current_measured,Temperature_measured,Current_load,Voltage_load,Time",
                "4.2,0.0,24.0,0.0,0.0,0.0"]
        for step in range(0, int(duration_s) // 10 + 2):
            t = 10.0 * step
            v = 4.0 + offset_v - 0.0005 * t if t <= knee_s else knee_v + (2.5 - knee_v) * (t - knee_s) / 100.0
            rows.append(f"{v:.6f},-2.0,24.0,2.0,{v:.6f},{t + 10.0}")
        (tmp_path / "data" / f"{k:05d}.csv").write_text("\n".join(rows) + "\n")
        meta.append(f"discharge,[2010. 1. 1. 0. 0. 0.],24,B0000,{k},{k},{k:05d}.csv,1.6,,")
    (tmp_path / "metadata.csv").write_text("\n".join(meta) + "\n")
    out = run_example("previous_discharge_signal.py", "--data", str(tmp_path), "--cell", "B0000", "--cutoff-v",
                      "2.5", "--train-cycles", "1..8")
    assert "slope 5000 s/V" in out, out
    assert "corrected 0.00 / 0.00 %" in out, out
    carried = float(out.split("carried ")[-1].split(" /")[0])
    assert carried > 0.2, out


def test_knee_by_temperature_recovers_the_slope_it_was_made_with(tmp_path):
    """A hand-made NASA folder whose discharges fall to 3.0 V at 2010 s and then run a tail to the 2.5 V cut-off
    of 300 s plus 50 s per kelvin their temperature lies above 5 C: the slope comes back, the tail's move is
    exact with it and missed without it."""
    import random

    rng = random.Random(11)
    (tmp_path / "data").mkdir()
    meta = ["type,start_time,ambient_temperature,battery_id,test_id,uid,filename,Capacity,Re,Rct"]
    for k in range(1, 21):
        warm_k = 0.2 * rng.randint(-5, 5)
        tail_s = 300.0 + 50.0 * warm_k  # a multiple of 10 s: readings land on both crossings
        rows = ["Voltage_measured,Current_measured,Temperature_measured,Current_load,Voltage_load,Time",
                f"4.2,0.0,{5.0 + warm_k},0.0,0.0,0.0"]
        for step in range(1, int(2010.0 + tail_s) // 10 + 2):
            t = 10.0 * step
            v = 4.0 - (t - 10.0) / 2000.0 if t <= 2010.0 else 3.0 - 0.5 * (t - 2010.0) / tail_s
            rows.append(f"{v:.6f},-2.0,{5.0 + warm_k},2.0,{v:.6f},{t}")
        (tmp_path / "data" / f"{k:05d}.csv").write_text("\n".join(rows) + "\n")
        meta.append(f"discharge,[2010. 1. 1. 0. 0. 0.],4,B0000,{k},{k},{k:05d}.csv,1.2,,")
    (tmp_path / "metadata.csv").write_text("\n".join(meta) + "\n")
    out = run_example("knee_by_temperature.py", "--data", str(tmp_path), "--cell", "B0000", "--cutoff-v", "2.5",
                      "--train-cycles", "1..10")
    assert "with 50.0 s per K" in out and "0.00 / 0.00 %" in out.split("with 50.0 s per K")[1], out
    carried = float(out.split("last 3: ")[1].split(" /")[0])
    assert carried > 0.2, out


def record_room_run(tmp_path, stated_offset_ah=None, stated_tail_ah=None):
    """A hand-made `bcal calibrate --out` folder of 200 judged discharges for record_room.py: each discharge's
    capacity error at 50 % is -0.8 times the last one plus a fresh part (what a prior that carries one
    discharge's noise into the next gives), and every end comes 0.5 % late. With `stated_offset_ah` its
    report carries each discharge's capacity references (records.capacity_refs), the stated capacity that
    much above the data's charge, and with `stated_tail_ah` the tail below the stated voltage each is scored less."""
    import json
    import random

    rng = random.Random(3)
    run = tmp_path / "cal"
    d = run / "readings" / "ukf"
    d.mkdir(parents=True)
    judged = list(range(41, 241))
    # Load on at 10 s, 2 A, the 2.5 V cut-off crossed at 1010 s by interpolation: 2010 A s drawn from the
    # reading before the load came on (10 A s on the way up, then 2 A for 1000 s); the prediction at 510 s
    # (50 %) counts.
    drawn_ah = 2010.0 / 3600.0
    records = {"partial_start": []}
    if stated_offset_ah is not None:
        records["capacity_refs"] = [{"cycle": c, "stated_ah": drawn_ah + stated_offset_ah, "data_ah": drawn_ah,
                                     "partial_start": False, "stated_tail_ah": stated_tail_ah} for c in judged]
    (run / "calibration.json").write_text(json.dumps({"cutoff_v": 2.5, "records": records, "settings": {
        "prior": {"judged": [{"cycle": c, "rest_before_s": 14000.0} for c in judged],
                  "width": {"usual_rest_s": 14000.0}}}}))
    head = ("t_s,voltage_v,current_a,q_mobile_c,q_mobile_lo_c,q_mobile_hi_c,r_o_ohm,r_o_lo_ohm,r_o_hi_ohm,eod_s,"
            "eod_lo_s,eod_hi_s,capacity_ah,capacity_lo_ah,capacity_hi_ah\n")
    error_ah = 0.0
    for c in judged:
        error_ah = -0.8 * error_ah + rng.gauss(0.0, 0.01)
        rows = [(0.0, 4.2, 0.0), (10.0, 4.0, 2.0), (510.0, 3.6, 2.0), (1000.0, 2.6, 2.0), (1020.0, 2.4, 2.0)]
        lines = [f"{t},{v},{i},0,0,0,0,0,0,1015,1000,1030,{drawn_ah + error_ah if t == 510.0 else 0.0},0,1"
                 for t, v, i in rows]
        (d / f"B0000-{c:04d}.csv").write_text(head + "\n".join(lines) + "\n")
    return run


def capacity_figures(out):
    capacity = next(line for line in out.splitlines() if line.startswith("  capacity"))
    return capacity, {w: float(capacity.split(w + " ")[1].split(",")[0].split(" ")[0])
                      for w in ("delivered", "recentred", "learner")}


def test_record_room_learns_what_the_record_holds(tmp_path):
    """On the hand-made run (`record_room_run`) the learner on the record takes off about what the record
    predicts (its error near the fresh part's, 0.6 of the delivered one's; 0.50-0.85 over 200 seeds), the
    median recentre none of it; the recentre takes the constant end error off entirely."""
    out = run_example("record_room.py", str(record_room_run(tmp_path)))
    eod = next(line for line in out.splitlines() if line.startswith("  EOD"))
    capacity, figure = capacity_figures(out)
    # 1015 s against 1010 s: 0.5 % late on every discharge; recentred to nothing.
    assert "delivered 0.500 / 0.500, recentred 0.000 / 0.000" in eod, out
    assert 0.4 * figure["delivered"] < figure["learner"] < 0.9 * figure["delivered"], out
    # The median of errors that turn each time is near 0: recentred or not, about the same.
    assert figure["recentred"] > 0.95 * figure["delivered"], out
    assert "lag-1 correlation of the errors -0." in capacity, out


def test_record_room_against_the_stated_capacity(tmp_path):
    """`--against stated` learns and scores against the capacities the report states: here 0.06 Ah above the
    data's charge, so every prediction errs 0.06 Ah low beside the alternating part: the delivered error is
    the offset's size, the learner takes it off (to below the data's delivered error), the gated recentre
    most of it. A report without the references is refused, naming what to do."""
    run = record_room_run(tmp_path, stated_offset_ah=0.06)
    _, data = capacity_figures(run_example("record_room.py", str(run)))
    out = run_example("record_room.py", "--against", "stated", str(run))
    assert "capacity against the stated capacity" in out, out
    _, stated = capacity_figures(out)
    assert stated["delivered"] > 0.06 > 2.0 * data["delivered"], (out, data)
    assert stated["learner"] < 0.9 * data["delivered"] and stated["recentred"] < 0.5 * stated["delivered"], out
    # Stated to a voltage above the cut-off (0.04 Ah below the data's charge) and scored, as bcal calibrate
    # scores it, less the tail below that voltage: the errors are the data's again.
    tailed = record_room_run(tmp_path / "tailed", stated_offset_ah=-0.04, stated_tail_ah=0.04)
    out = run_example("record_room.py", "--against", "stated", str(tailed))
    _, figure = capacity_figures(out)
    assert abs(figure["delivered"] - data["delivered"]) < 1e-4, (out, data)
    assert "with the tail below the stated voltage added, median +0.0000 Ah" in out, out
    bare = record_room_run(tmp_path / "bare")
    fail = subprocess.run([sys.executable, str(REPO / "examples" / "record_room.py"), "--against", "stated", str(bare)],
                          capture_output=True, text=True, timeout=300)
    assert fail.returncode != 0 and "records.capacity_refs" in fail.stderr and "bcal calibrate again" in fail.stderr


def test_record_rooms_learner_sees_only_the_discharges_before():
    """The move the learner makes at a discharge does not change with that discharge's own error or any
    later one: the corrected error moves by exactly what the error itself moves."""
    import importlib.util
    import random

    spec = importlib.util.spec_from_file_location("record_room", REPO / "examples" / "record_room.py")
    record_room = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(record_room)
    rng = random.Random(11)
    errors = [rng.gauss(0.0, 0.01) for _ in range(60)]
    rests = [3600.0 * rng.uniform(2.0, 30.0) for _ in errors]
    base = record_room.corrected(errors, rests, 14000.0, 30, 10)
    for k in (11, 30, 59):
        changed = errors[:k] + [x + 0.05 for x in errors[k:]]
        moved = record_room.corrected(changed, rests, 14000.0, 30, 10)
        assert moved[:k] == base[:k]
        assert abs((moved[k] - changed[k]) - (base[k] - errors[k])) < 1e-12, k
        assert base[k] != errors[k], "the learner moves once it has a record"


def test_by_previous_current_groups_each_discharge_by_its_current_and_the_one_before(tmp_path):
    """Three hand-made discharges of a blind cell (load on at 10 s, true end 1000 s after it): the second at 2 A
    after 1 A predicted 20 s late at half (+2 %), the third at 2 A after 2 A 10 s early (-1 %); the first has no
    discharge before it and is left out."""
    truth = tmp_path / "truth.csv"
    truth.write_text("cell,cycle,current_a,t_on_s,eod_from_load_s\n"
                     "X,1,1.0,10,1000\nX,2,2.0,10,1000\nX,3,2.0,10,1000\n")
    ukf = tmp_path / "cal" / "readings" / "ukf"
    ukf.mkdir(parents=True)
    for cycle, off_s in [(1, 0.0), (2, 20.0), (3, -10.0)]:
        rows = ["t_s,eod_s"] + [f"{t},{1010.0 + off_s * (t == 510)}" for t in (0, 300, 510, 900)]
        (ukf / f"X-{cycle:04d}.csv").write_text("\n".join(rows) + "\n")
    out = run_example("blind/by_previous_current.py", "--out", str(tmp_path / "cal"), "--truth", str(truth),
                      "--cell", "X")
    assert out.splitlines() == ["ukf at 2 A after 1 A:   1 discharges, signed median +2.00 %",
                                "ukf at 2 A after 2 A:   1 discharges, signed median -1.00 %"], out
