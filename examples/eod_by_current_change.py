"""Whether one calibrator's end of discharge errs with the change of current from the discharge before: on a
cell discharged at several currents (NASA's B0038-B0040 at 1, 2 and 4 A; B0041-B0044 at 4 and 1 A) what a
discharge starts from (the last discharge's end fit, its knee, the twins' record) was measured at another
current.

    python examples/eod_by_current_change.py RUN [--method ukf] [--fraction 0.5]

RUN is a `bcal calibrate --out` folder. Each judged discharge is scored as `bcal calibrate` scores it
(examples/eod_by_age.py: the signed error, positive late, in % of the discharge, read at `--fraction` of
it); its current is the median of its loaded readings. Prints the correlation of the signed error with the
change of current (now less before) and, per pair of currents (rounded to 0.5 A: before -> now), the
discharges, their mean signed error and median absolute error. Standard library only.
"""

import argparse
import csv
import json
import math
import pathlib

from eod_by_age import LOAD_THRESHOLD_A, eod_error_pct, median


def current_a(path):
    """The median current of a discharge's loaded readings, A (None: no loaded reading)."""
    with open(path, newline="") as f:
        loaded = [float(r["current_a"]) for r in csv.DictReader(f) if float(r["current_a"]) > LOAD_THRESHOLD_A]
    return median(loaded) if loaded else None


def corr(a, b):
    ma, mb = sum(a) / len(a), sum(b) / len(b)
    num = sum((x - ma) * (y - mb) for x, y in zip(a, b))
    den = math.sqrt(sum((x - ma) ** 2 for x in a) * sum((y - mb) ** 2 for y in b))
    return num / den if den > 0 else float("nan")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=pathlib.Path)
    p.add_argument("--method", default="ukf", help="the readings/METHOD folder (default ukf)")
    p.add_argument("--fraction", type=float, default=0.5, help="share of the discharge the prediction is read at")
    a = p.parse_args()
    folder = a.run / "readings" / a.method
    if not folder.is_dir():
        raise SystemExit(f"{folder}: no such folder (a `bcal calibrate --out` folder with --calibrator {a.method})")
    cutoff_v = json.load(open(a.run / "calibration.json"))["cutoff_v"]
    files = sorted(folder.glob("*.csv"), key=lambda f: int(f.stem.rsplit("-", 1)[1]))
    rows, before = [], None
    for f in files:
        now = current_a(f)
        err = eod_error_pct(f, cutoff_v, a.fraction, signed=True)
        if err is not None and now is not None and before is not None:
            rows.append((before, now, err))
        before = now if now is not None else before
    if len(rows) < 3:
        raise SystemExit(f"{folder}: {len(rows)} scored discharges after another: too few to say")
    errs = [r[2] for r in rows]
    print(f"{a.run.name}, {a.method}, at {100 * a.fraction:.0f} %: {len(rows)} discharges; correlation of the "
          f"signed error with the change of current {corr(errs, [n - b for b, n, _ in rows]):+.2f}")
    pairs = {}
    for b, n, e in rows:
        pairs.setdefault((round(2 * b) / 2, round(2 * n) / 2), []).append(e)
    print("before -> now A | discharges | mean signed error % | median |error| %")
    for (b, n), es in sorted(pairs.items()):
        print(f"{b:.1f} -> {n:.1f} | {len(es)} | {sum(es) / len(es):+.2f} | {median([abs(x) for x in es]):.2f}")


if __name__ == "__main__":
    main()
