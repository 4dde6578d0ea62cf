"""Where along a cell's life one calibrator predicts the end of discharge better than another.

    python examples/eod_by_age.py RUN [RUN ...] [--method rl] [--against ukf] [--bins 41-80,81-120,121-999]

RUN is a `bcal calibrate --out` folder. From its per-reading files (readings/METHOD/CELL-CYCLE.csv) this
scores each judged discharge as `bcal calibrate` does (the end of discharge interpolated at the cut-off
from the last two readings, the prediction read at the first reading at or after 50 % of the discharge
from the load-on, the error in % of the discharge) and prints, per bin of cycles, both methods' median
error and on how many discharges the first beat the second. `calibration.json` gives only the pooled
figures; this says whether a loss comes right after the validation cycles or as the cell ages.
Standard library only.
"""

import argparse
import csv
import json
import pathlib

# realcell/src/record.rs LOAD_THRESHOLD_A: a reading under load draws more than this, A.
LOAD_THRESHOLD_A = 0.05


def median(values):
    """The median as `bcal calibrate` takes it (common/src/stats.rs: the value at rank round((n - 1) / 2))."""
    v = sorted(values)
    return v[int((len(v) - 1) * 0.5 + 0.5)]


def end_s(t, v, on, cutoff_v):
    """The measured end of a discharge whose last reading is its first at or below the cut-off under load:
    interpolated at the cut-off between the last two readings, or the last reading's time."""
    k = len(t) - 1
    if k > on and v[k - 1] > v[k]:
        return t[k - 1] + (t[k] - t[k - 1]) * min(max((v[k - 1] - cutoff_v) / (v[k - 1] - v[k]), 0.0), 1.0)
    return t[k]


def eod_error_pct(path, cutoff_v, fraction=0.5, signed=False):
    """|predicted - measured end of discharge| in % of the discharge (`signed`: predicted - measured, positive
    late), or None (cut short, no prediction)."""
    rows = list(csv.DictReader(open(path, newline="")))
    t = [float(r["t_s"]) for r in rows]
    v = [float(r["voltage_v"]) for r in rows]
    i = [float(r["current_a"]) for r in rows]
    on = next((k for k, a in enumerate(i) if a > LOAD_THRESHOLD_A), None)
    if on is None or not (i[-1] > LOAD_THRESHOLD_A and v[-1] <= cutoff_v) or len(rows) < 2:
        return None
    eod = end_s(t, v, on, cutoff_v)
    duration = eod - t[on]
    at = t[on] + fraction * duration
    j = next(j for j, x in enumerate(t) if x >= at - 1e-9)
    predicted = rows[j]["eod_s"]
    if predicted == "" or duration <= 0:
        return None
    error = (float(predicted) - eod) / duration * 100.0
    return error if signed else abs(error)


def errors_against(run, method, cutoff_v):
    """`errors` of a `bcal calibrate --out` folder given with `--against`, refused clearly where it is none."""
    report = run / "calibration.json"
    if not report.exists():
        raise SystemExit(f"{report}: not found (--against is a `bcal calibrate --out` folder)")
    return errors(run, method, cutoff_v)


def errors(run, method, cutoff_v):
    out = {}
    for f in sorted((run / "readings" / method).glob("*.csv")):
        e = eod_error_pct(f, cutoff_v)
        if e is not None:
            out[int(f.stem.rsplit("-", 1)[1])] = e
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", type=pathlib.Path)
    p.add_argument("--method", default="rl")
    p.add_argument("--against", default="ukf")
    p.add_argument("--bins", default="41-80,81-120,121-999")
    a = p.parse_args()
    bins = [tuple(int(x) for x in b.split("-")) for b in a.bins.split(",")]
    for run in a.runs:
        report = run / "calibration.json"
        if not report.exists():
            raise SystemExit(f"{report}: not found (RUN is a `bcal calibrate --out` folder)")
        cutoff_v = json.load(open(report))["cutoff_v"]
        mine, theirs = errors(run, a.method, cutoff_v), errors(run, a.against, cutoff_v)
        both = sorted(set(mine) & set(theirs))
        if not both:
            raise SystemExit(f"{run}: no discharge scored by both {a.method} and {a.against} (readings/ missing?)")
        parts = [f"all: {a.method} {median(mine[c] for c in both):.2f} {a.against} "
                 f"{median(theirs[c] for c in both):.2f} %"]
        for lo, hi in bins:
            cs = [c for c in both if lo <= c <= hi]
            if cs:
                wins = sum(mine[c] < theirs[c] for c in cs)
                parts.append(f"{lo}-{hi}: {median(mine[c] for c in cs):.2f} against "
                             f"{median(theirs[c] for c in cs):.2f} %, better on {wins} of {len(cs)}")
        print(f"{run}: " + " | ".join(parts))


if __name__ == "__main__":
    main()
