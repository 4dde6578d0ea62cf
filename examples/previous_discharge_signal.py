"""Does a discharge's voltage, against the discharge before it at the same time, tell how much longer it lasts?

    python examples/previous_discharge_signal.py --data ../shared/data/nasa-pcoe --cell B0018 --cutoff-v 2.5
        [--train-cycles 1..40] [--against RUN]

A question about what a learned calibrator could add on a real cell (docs/calibrator.md, "does the cost have
something to learn"). The predictor: the end of discharge k is the duration of discharge k - 1 plus
b (v_k(t) - v_{k-1}(t)), v the measured voltage t seconds after the load came on. The slope b is fitted by
least squares on the training cycles' consecutive pairs; t (of 120 to 1200 s, below 0.4 of the last training
discharge, so that it falls before half of the later, shorter ones, the share `bcal calibrate` scores; a
discharge shorter than twice t is not scored) is the one whose fit on the first three quarters of
the training cycles predicts the last quarter best, then b is refitted on all of them. Printed: that choice,
the validation error, and on the judged cycles (every discharge after the training ones) the error of the
duration carried as it is (b = 0) and with the correction, median and p90 in % of the discharge. With
`--against RUN` (a `bcal calibrate --out` folder of the same cell and cut-off) also that run's joint UKF
(`--method`) at 50 % on the same discharges, and on how many the correction beat it.

The end is interpolated at the cut-off between the last reading above it and the first below, as `bcal
calibrate` scores it. NASA PCoE folders only (metadata.csv and data/). Standard library only.
"""

import argparse
import csv
import pathlib
import statistics
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import eod_by_age  # noqa: E402  (its scoring of a calibrate run's readings)

TIMES_S = [120, 300, 450, 600, 800, 1000, 1200]
# realcell/src/record.rs LOAD_THRESHOLD_A; NASA's discharge current is negative.
LOAD_THRESHOLD_A = 0.05


def discharges(data, cell, cutoff_v):
    """{cycle: (duration_s, {t: voltage at t s after load-on})} for every discharge that reaches the cut-off."""
    meta = pathlib.Path(data) / "metadata.csv"
    if not meta.exists():
        raise SystemExit(f"{meta}: not found (--data is a NASA PCoE folder with metadata.csv and data/)")
    rows = [r for r in csv.DictReader(open(meta, newline="")) if r["battery_id"] == cell and r["type"] == "discharge"]
    if not rows:
        raise SystemExit(f"{meta}: no discharge of cell {cell}")
    out, missing = {}, 0
    for cycle, r in enumerate(rows, start=1):
        path = pathlib.Path(data) / "data" / r["filename"]
        if not path.exists():
            missing += 1
            continue
        d = list(csv.DictReader(open(path, newline="")))
        t = [float(x["Time"]) for x in d]
        v = [float(x["Voltage_measured"]) for x in d]
        i = [-float(x["Current_measured"]) for x in d]
        on = next((k for k, a in enumerate(i) if a > LOAD_THRESHOLD_A), None)
        if on is None:
            continue
        end = next((k for k in range(on + 1, len(v)) if v[k] <= cutoff_v), None)
        if end is None:
            continue
        eod = t[end - 1] + (t[end] - t[end - 1]) * (v[end - 1] - cutoff_v) / (v[end - 1] - v[end])
        duration = eod - t[on]

        def at(sec):
            k = next((k for k in range(on + 1, end) if t[k] - t[on] >= sec), None)
            if k is None:
                return None
            a, b = t[k - 1] - t[on], t[k] - t[on]
            return v[k - 1] + (v[k] - v[k - 1]) * (sec - a) / (b - a) if b > a else v[k]

        out[cycle] = (duration, {s: at(s) for s in TIMES_S if s < 0.5 * duration})
    if missing:
        print(f"{cell}: {missing} of {len(rows)} discharge files missing", file=sys.stderr)
    return out


def pairs(d, sec, lo, hi):
    """(cycle, duration change, voltage change at sec) over consecutive discharges lo..hi."""
    return [
        (c, d[c][0] - d[c - 1][0], d[c][1][sec] - d[c - 1][1][sec])
        for c in sorted(d)
        if lo <= c <= hi and c - 1 in d and d[c][1].get(sec) is not None and d[c - 1][1].get(sec) is not None
    ]


def slope(ps):
    mx, my = statistics.mean(p[2] for p in ps), statistics.mean(p[1] for p in ps)
    sxx = sum((p[2] - mx) ** 2 for p in ps)
    return sum((p[2] - mx) * (p[1] - my) for p in ps) / sxx if sxx > 0 else 0.0


def errors(d, ps, b):
    return {p[0]: abs(p[1] - b * p[2]) / d[p[0]][0] * 100.0 for p in ps}


def p90(values):
    v = sorted(values)
    return v[min(len(v) - 1, int(0.9 * len(v)))]


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--cell", required=True)
    p.add_argument("--cutoff-v", type=float, required=True)
    p.add_argument("--train-cycles", default=None, help="A..B; default the first third, at most 40, at least 4")
    p.add_argument("--against", type=pathlib.Path, default=None)
    p.add_argument("--method", default="ukf")
    a = p.parse_args()
    d = discharges(a.data, a.cell, a.cutoff_v)
    last = max(d) if d else 0
    if a.train_cycles:
        lo, hi = (int(x) for x in a.train_cycles.split(".."))
    else:
        lo, hi = 1, min(40, max(4, last // 3))
    fit_hi = lo + (hi - lo + 1) * 3 // 4 - 1
    # Times the cell will still reach by half of its later, shorter discharges: below 0.4 of the last
    # training discharge.
    last_train = max((c for c in d if lo <= c <= hi), default=None)
    if last_train is None:
        raise SystemExit(f"{a.cell}: no training discharge in {lo}..{hi} reaches {a.cutoff_v} V")
    best = None
    for sec in (s for s in TIMES_S if s < 0.4 * d[last_train][0]):
        fit, val = pairs(d, sec, lo, fit_hi), pairs(d, sec, fit_hi + 1, hi)
        if len(fit) < 4 or len(val) < 2:
            continue
        e = statistics.mean(errors(d, val, slope(fit)).values())
        if best is None or e < best[0]:
            best = (e, sec, statistics.mean(errors(d, val, 0.0).values()))
    if best is None:
        raise SystemExit(f"{a.cell}: too few consecutive training discharges reach {a.cutoff_v} V")
    val_e, sec, val_carry = best
    b = slope(pairs(d, sec, lo, hi))
    judged = pairs(d, sec, hi + 1, 10**9)
    carry, corrected = errors(d, judged, 0.0), errors(d, judged, b)
    print(
        f"{a.cell}: training {lo}..{hi}, t = {sec} s (validation {val_e:.2f} % against {val_carry:.2f} % carried), "
        f"slope {b:.0f} s/V; judged {len(judged)}: carried {statistics.median(carry.values()):.2f} / "
        f"{p90(carry.values()):.2f} %, corrected {statistics.median(corrected.values()):.2f} / "
        f"{p90(corrected.values()):.2f} % (median / p90)"
    )
    if a.against:
        theirs = eod_by_age.errors_against(a.against, a.method, a.cutoff_v)
        both = sorted(set(theirs) & set(corrected))
        if both:
            wins = sum(corrected[c] < theirs[c] for c in both)
            print(
                f"  on the {len(both)} judged discharges both score: {a.method} "
                f"{statistics.median(theirs[c] for c in both):.2f} / {p90([theirs[c] for c in both]):.2f} %, "
                f"corrected {statistics.median(corrected[c] for c in both):.2f} / "
                f"{p90([corrected[c] for c in both]):.2f} %, corrected better on {wins}"
            )


if __name__ == "__main__":
    main()
