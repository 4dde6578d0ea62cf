"""How much of a cold cell's end-of-discharge error is its knee, and does the cell's temperature tell it?

    python examples/knee_by_temperature.py --data ../shared/data/nasa-pcoe --cell B0055 --cutoff-v 2.5
        [--train-cycles 1..34] [--judge-cycles A..B] [--tail-from-v 3.0] [--at-s 600] [--against RUN]

The tail of a discharge: the time it takes under load from its first reading below `--tail-from-v` (3.0 V,
about where bcal's base model empties at 2 A) to the cut-off, both crossings interpolated. bcal adds the
model's knee to every end it predicts as the median of the last three discharges' (`KNEE_WINDOW`), so a
tail that moves from one discharge to the next against that median is an error no calibrator of qMobile
and Ro removes. Printed, on the judged discharges (after the training cycles; default as `bcal calibrate`:
the first third, at most 40): the tail's mean and sd, its move against the median of the last three as a
share of the discharge (median / p90 %), and the same with a temperature term: the move predicted as b
times the cell's temperature `--at-s` seconds after the load came on against the median of the last
three's at the same time (b fitted by least squares on the training cycles, none fitted on judged ones).
Also the correlation of the move with that temperature and with the temperature at the end (which comes
too late to use). With `--against RUN` (a `bcal calibrate --out` folder of the same cell and cut-off), that
run's joint UKF (`--method`) end-of-discharge error at 50 % on the same discharges.

NASA PCoE folders only (metadata.csv and data/). Standard library only.
"""

import argparse
import csv
import pathlib
import statistics
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import eod_by_age  # noqa: E402  (its scoring of a calibrate run's readings)
from previous_discharge_signal import LOAD_THRESHOLD_A, p90  # noqa: E402

WINDOW = 3  # calib/src/end_fit.rs KNEE_WINDOW


def crossing_s(t, v, on, level):
    """Seconds after the load-on at which the voltage first falls to `level` under load, interpolated."""
    k = next((k for k in range(on + 1, len(v)) if v[k] <= level), None)
    if k is None:
        return None
    return t[k - 1] + (t[k] - t[k - 1]) * (v[k - 1] - level) / (v[k - 1] - v[k]) - t[on]


def interp(t, y, at):
    k = next((k for k in range(1, len(t)) if t[k] >= at), None)
    if k is None:
        return None
    return y[k - 1] + (y[k] - y[k - 1]) * (at - t[k - 1]) / (t[k] - t[k - 1]) if t[k] > t[k - 1] else y[k]


def discharges(data, cell, cutoff_v, tail_from_v, at_s):
    """{cycle: (duration s, tail s, temperature at at_s C, temperature at the end C)} for every discharge that
    reaches the cut-off."""
    meta = pathlib.Path(data) / "metadata.csv"
    if not meta.exists():
        raise SystemExit(f"{meta}: not found (--data is a NASA PCoE folder with metadata.csv and data/)")
    rows = [r for r in csv.DictReader(open(meta, newline="")) if r["battery_id"] == cell and r["type"] == "discharge"]
    if not rows:
        raise SystemExit(f"{meta}: no discharge of cell {cell}")
    out = {}
    for cycle, r in enumerate(rows, start=1):
        path = pathlib.Path(data) / "data" / r["filename"]
        if not path.exists():
            continue
        d = list(csv.DictReader(open(path, newline="")))
        try:
            t = [float(x["Time"]) for x in d]
            v = [float(x["Voltage_measured"]) for x in d]
            i = [-float(x["Current_measured"]) for x in d]
            temp = [float(x["Temperature_measured"]) for x in d]
        except (KeyError, ValueError) as e:
            raise SystemExit(f"{path}: not a NASA discharge record ({e})") from None
        on = next((k for k, a in enumerate(i) if a > LOAD_THRESHOLD_A), None)
        if on is None:
            continue
        end_s, tail_at_s = crossing_s(t, v, on, cutoff_v), crossing_s(t, v, on, tail_from_v)
        if end_s is None or tail_at_s is None or end_s < 2 * at_s:
            continue
        t_at, t_end = interp(t, temp, t[on] + at_s), interp(t, temp, t[on] + end_s)
        if t_at is not None and t_end is not None:
            out[cycle] = (end_s, end_s - tail_at_s, t_at, t_end)
    return out


def moves(d):
    """(cycle, duration, tail move, temperature move, end temperature move), each against the median of the last
    WINDOW discharges before it."""
    cycles, out = sorted(d), []
    for n, c in enumerate(cycles):
        if n < WINDOW:
            continue
        last = [d[k] for k in cycles[n - WINDOW : n]]
        med = [statistics.median(x[j] for x in last) for j in range(4)]
        out.append((c, d[c][0], d[c][1] - med[1], d[c][2] - med[2], d[c][3] - med[3]))
    return out


def corr(a, b):
    return statistics.correlation(a, b) if len(a) > 2 and statistics.pstdev(a) > 0 and statistics.pstdev(b) > 0 else 0.0


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--cell", required=True)
    p.add_argument("--cutoff-v", type=float, required=True)
    p.add_argument("--train-cycles", default=None, help="A..B; default the first third, at most 40, at least 4")
    p.add_argument("--tail-from-v", type=float, default=3.0)
    p.add_argument("--at-s", type=float, default=600.0)
    p.add_argument("--judge-cycles", default=None, help="A..B; default every cycle after the training ones")
    p.add_argument("--against", type=pathlib.Path, default=None)
    p.add_argument("--method", default="ukf")
    a = p.parse_args()
    d = discharges(a.data, a.cell, a.cutoff_v, a.tail_from_v, a.at_s)
    last = max(d) if d else 0
    if a.train_cycles:
        lo, hi = (int(x) for x in a.train_cycles.split(".."))
    else:
        lo, hi = 1, min(40, max(4, last // 3))
    m = moves(d)
    train = [x for x in m if lo <= x[0] <= hi]
    jlo, jhi = (int(x) for x in a.judge_cycles.split("..")) if a.judge_cycles else (hi + 1, 10**9)
    judged = [x for x in m if jlo <= x[0] <= jhi]
    if len(train) < 4 or not judged:
        raise SystemExit(
            f"{a.cell}: too few discharges reach {a.cutoff_v} V (training {len(train)}, judged {len(judged)})"
        )
    mx, my = statistics.mean(x[3] for x in train), statistics.mean(x[2] for x in train)
    sxx = sum((x[3] - mx) ** 2 for x in train)
    b = sum((x[3] - mx) * (x[2] - my) for x in train) / sxx if sxx > 0 else 0.0
    carried = {x[0]: abs(x[2]) / x[1] * 100.0 for x in judged}
    with_t = {x[0]: abs(x[2] - b * x[3]) / x[1] * 100.0 for x in judged}
    tails = [d[x[0]][1] for x in judged]
    print(
        f"{a.cell}: judged {len(judged)} (trained on {lo}..{hi}); tail below {a.tail_from_v} V "
        f"{statistics.mean(tails):.0f} s, sd {statistics.stdev(tails):.0f} s; its move against the last {WINDOW}: "
        f"{statistics.median(carried.values()):.2f} / {p90(carried.values()):.2f} % of the discharge (median / p90); "
        f"with {b:.1f} s per K of the temperature at {a.at_s:.0f} s against the last {WINDOW}'s: "
        f"{statistics.median(with_t.values()):.2f} / {p90(with_t.values()):.2f} %"
    )
    print(
        f"  correlation of the tail's move with the temperature's at {a.at_s:.0f} s "
        f"{corr([x[2] for x in judged], [x[3] for x in judged]):+.2f}, at the end "
        f"{corr([x[2] for x in judged], [x[4] for x in judged]):+.2f}"
    )
    if a.against:
        theirs = eod_by_age.errors_against(a.against, a.method, a.cutoff_v)
        both = sorted(set(theirs) & set(carried))
        if both:
            print(
                f"  on the {len(both)} judged discharges both score: {a.method} at 50 % "
                f"{statistics.median(theirs[c] for c in both):.2f} / {p90([theirs[c] for c in both]):.2f} %"
            )


if __name__ == "__main__":
    main()
