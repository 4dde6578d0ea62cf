"""The signed end-of-discharge error at half of each discharge of a blind cell (`progpy_cells.py`), grouped by its
current and the previous discharge's: whether what a discharge starts from carries a bias from the current of the
one before (a cell cycled at mixed currents). Standard library only.

    python3 examples/blind/by_previous_current.py --out OUT --truth blind/truth.csv --cell B0038 [--method ukf]

OUT is `bcal calibrate --out OUT`'s folder; the error is (predicted - true end) / (true end - load-on), %, at the
reading nearest half the true discharge, the true end from the generator's truth (`eod_from_load_s`).
"""
import argparse
import csv
import os
import statistics


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--out", required=True, help="bcal calibrate's output folder")
    p.add_argument("--truth", required=True, help="the generator's truth.csv")
    p.add_argument("--cell", required=True)
    p.add_argument("--method", default="ukf")
    a = p.parse_args()
    truth = {int(r["cycle"]): r for r in csv.DictReader(open(a.truth)) if r["cell"] == a.cell}
    if not truth:
        raise SystemExit(f"{a.truth}: no discharge of {a.cell}")
    groups = {}
    for c in sorted(truth):
        path = os.path.join(a.out, "readings", a.method, f"{a.cell}-{c:04d}.csv")
        t, before = truth[c], truth.get(c - 1)
        if before is None or t["eod_from_load_s"] == "" or not os.path.exists(path):
            continue
        on_s, eod_s = float(t["t_on_s"]), float(t["eod_from_load_s"])
        rows = [r for r in csv.DictReader(open(path)) if r["eod_s"]]
        if not rows:
            continue
        r = min(rows, key=lambda r: abs(float(r["t_s"]) - (on_s + 0.5 * eod_s)))
        err = 100.0 * (float(r["eod_s"]) - (on_s + eod_s)) / eod_s
        groups.setdefault((float(t["current_a"]), float(before["current_a"])), []).append(err)
    if not groups:
        raise SystemExit(f"{a.out}: no readings of {a.method} for {a.cell} (run bcal calibrate --out {a.out} first)")
    for (now, prev), errs in sorted(groups.items()):
        print(f"{a.method} at {now:g} A after {prev:g} A: {len(errs):3d} discharges, signed median "
              f"{statistics.median(errs):+.2f} %")


if __name__ == "__main__":
    main()
