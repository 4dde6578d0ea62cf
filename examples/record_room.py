"""How much of a calibrator's error on a real cell could a learner on its record over past discharges take?

    python examples/record_room.py RUN [RUN ...] [--method ukf] [--window 30] [--min-pairs 10]
        [--inputs last,mean5,rest]

RUN is a `bcal calibrate --out` folder. The design this measures (docs/calibrator.md, "a learner on the
record"): before each judged discharge, a learner sees the method's signed errors on the discharges that
ended before it (at 50 % of each: the end of discharge in % of the discharge, the capacity in Ah against the
data's charge to the interpolated cut-off, both as `bcal calibrate` scores them, from readings/METHOD/) and
the rest before this one, and moves the method's prediction at 50 % by the error it expects. The learner:
least squares refitted before every discharge on the last `--window` discharges' pairs (at least
`--min-pairs`; before that, no move), on three inputs: the last error, the mean of the last five, and the
log of the rest before against the cell's usual rest (`calibration.json`, settings.prior). Within linear
policies on these inputs, this is the optimum of a policy trained on the same record by cost alone (the
squared error it leaves). The settings were fixed before any figure was seen.

Printed per run and quantity, over the discharges after the first `--min-pairs` + 1: the method as
delivered; recentred (the median of its last 10 signed errors taken off, where that earns its place by the
rule `bcal calibrate` gates every alternative with, `bcal_calib::tune::earns`: the non-learned rule the
learner must beat); the learner served always and served where it earns; on how many discharges the learner
beat the delivered prediction; and the errors' lag-1 correlation (what a learner on the record works from).
Standard library only.
"""

import argparse
import csv
import json
import math
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import eod_by_age  # noqa: E402  (its scoring of a calibrate run's readings)


def signed_errors(path, cutoff_v):
    """(EOD error in % of the discharge, capacity error in Ah), both signed (predicted - measured) at the first
    reading at or after 50 % of the discharge, or None where `bcal calibrate` would not score it."""
    rows = list(csv.DictReader(open(path, newline="")))
    eod = eod_by_age.eod_error_pct(path, cutoff_v, signed=True)
    if eod is None or "capacity_ah" not in rows[0]:
        return None
    t = [float(r["t_s"]) for r in rows]
    v = [float(r["voltage_v"]) for r in rows]
    i = [float(r["current_a"]) for r in rows]
    on = next(k for k, a in enumerate(i) if a > eod_by_age.LOAD_THRESHOLD_A)
    k = len(rows) - 1
    frac = min(max((v[k - 1] - cutoff_v) / (v[k - 1] - v[k]), 0.0), 1.0) if v[k - 1] > v[k] else 1.0
    end_s = t[k - 1] + (t[k] - t[k - 1]) * frac
    # The data's charge: the trapezoid of the current to the last reading above the cut-off, then that
    # reading's current to the interpolated crossing.
    drawn_as = sum(0.5 * (i[j] + i[j + 1]) * (t[j + 1] - t[j]) for j in range(k - 1)) + i[k - 1] * (end_s - t[k - 1])
    at = t[on] + 0.5 * (end_s - t[on])
    j = next(j for j, x in enumerate(t) if x >= at - 1e-9)
    if rows[j]["capacity_ah"] == "":
        return None
    return eod, float(rows[j]["capacity_ah"]) - drawn_as / 3600.0


def solve(a, b):
    """x with a x = b (a small symmetric positive definite matrix, as lists), by Gaussian elimination."""
    n = len(b)
    m = [row[:] + [b[r]] for r, row in enumerate(a)]
    for c in range(n):
        p = max(range(c, n), key=lambda r: abs(m[r][c]))
        m[c], m[p] = m[p], m[c]
        for r in range(n):
            if r != c:
                f = m[r][c] / m[c][c]
                m[r] = [x - f * y for x, y in zip(m[r], m[c])]
    return [m[r][n] / m[r][r] for r in range(n)]


def least_squares(xs, ys, ridge=1e-9):
    """Coefficients of y on x (x rows start with 1), a tiny ridge on all but the intercept for a singular
    record (a constant rest, say)."""
    n = len(xs[0])
    a = [[sum(x[p] * x[q] for x in xs) + (ridge * len(xs) if p == q and p > 0 else 0.0) for q in range(n)]
         for p in range(n)]
    return solve(a, [sum(x[p] * y for x, y in zip(xs, ys)) for p in range(n)])


INPUTS = ("last", "mean5", "rest")


def corrected(errors, rests, usual_s, window, min_pairs, inputs_used=INPUTS):
    """Each discharge's error after the move a least-squares learner on the record before it expects, on
    `inputs_used` (of INPUTS) beside its intercept."""
    def inputs(k, e):
        last5 = e[max(0, k - 5):k]
        every = {"last": e[k - 1], "mean5": sum(last5) / len(last5),
                 "rest": math.log(max(rests[k], 1.0) / usual_s)}
        return [1.0] + [every[name] for name in inputs_used]

    out = []
    for k, e in enumerate(errors):
        pairs = list(range(1, k))[-window:]
        if len(pairs) < min_pairs:
            out.append(e)
            continue
        # Inputs scaled by the record's spread so that the ridge means the same for Ah and %.
        scale = max(math.sqrt(sum(x * x for x in errors[:k]) / k), 1e-12)
        es = [x / scale for x in errors]
        coef = least_squares([inputs(j, es) for j in pairs], [es[j] for j in pairs], ridge=1e-3)
        out.append(e - scale * sum(c * x for c, x in zip(coef, inputs(k, es))))
    return out


def recentred(errors, window=10):
    """Each discharge's error after the move the recentre rule makes (`bcal_calib::recentre::biases`): the
    median of the signed errors of the last `window` discharges before it; none before any."""
    return [e - eod_by_age.median(errors[max(0, k - window):k]) if k else e for k, e in enumerate(errors)]


def gated(errors, alternative, window=10, share=0.75):
    """The alternative where it earns its place as `bcal_calib::tune::earns` rules (over the last `window`
    discharges before it: a lower mean absolute error and a lower one on at least `share` of them), the
    method's own error elsewhere."""
    out = []
    for k, e in enumerate(errors):
        mine = [abs(x) for x in alternative[max(0, k - window):k]]
        theirs = [abs(x) for x in errors[max(0, k - window):k]]
        wins = sum(a < b for a, b in zip(mine, theirs))
        earns = len(theirs) == window and sum(mine) < sum(theirs) and wins >= math.ceil(share * window)
        out.append(alternative[k] if earns else e)
    return out


def rms(values):
    return math.sqrt(sum(x * x for x in values) / len(values))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", type=pathlib.Path)
    p.add_argument("--method", default="ukf")
    p.add_argument("--window", type=int, default=30)
    p.add_argument("--min-pairs", type=int, default=10)
    p.add_argument("--inputs", default=",".join(INPUTS),
                   help="the learner's inputs beside its intercept, of last,mean5,rest (to see which carries a gain)")
    a = p.parse_args()
    inputs_used = [x for x in a.inputs.split(",") if x]
    if any(x not in INPUTS for x in inputs_used):
        raise SystemExit(f"--inputs {a.inputs}: each input is one of {', '.join(INPUTS)}")
    for run in a.runs:
        report = run / "calibration.json"
        if not report.exists():
            raise SystemExit(f"{report}: not found (RUN is a `bcal calibrate --out` folder)")
        j = json.load(open(report))
        prior = j["settings"]["prior"]
        rest_of = {d["cycle"]: d["rest_before_s"] for d in prior["judged"]}
        usual_s = prior["width"]["usual_rest_s"]
        scored = {}
        for f in sorted((run / "readings" / a.method).glob("*.csv")):
            cycle = int(f.stem.rsplit("-", 1)[1])
            e = signed_errors(f, j["cutoff_v"])
            if e is not None and rest_of.get(cycle) is not None:
                scored[cycle] = e
        if len(scored) <= a.min_pairs + 1:
            raise SystemExit(f"{run}: {len(scored)} discharges scored by {a.method}, too few for a record")
        cycles = sorted(scored)
        rests = [rest_of[c] for c in cycles]
        print(f"{run.name} ({a.method}, {len(cycles)} discharges scored, the first {a.min_pairs + 1} only as record):")
        for q, (name, unit, fmt) in enumerate([("EOD at 50 %", "%", ".3f"), ("capacity from 50 %", "Ah", ".4f")]):
            e = [scored[c][q] for c in cycles]
            learner = corrected(e, rests, usual_s, a.window, a.min_pairs, inputs_used)
            ways = {"delivered": e, "recentred": gated(e, recentred(e)), "learner": learner,
                    "learner where it earns": gated(e, learner)}
            judged = range(a.min_pairs + 1, len(e))
            mean = sum(e) / len(e)
            d = [x - mean for x in e]
            spread = sum(x * x for x in d)
            rho = f"{sum(x * y for x, y in zip(d, d[1:])) / spread:+.2f}" if spread > 0 else "undefined (all equal)"
            if unit == "%":
                def figure(v):
                    v = sorted(abs(v[k]) for k in judged)
                    return f"{eod_by_age.median(v):{fmt}} / {v[int(0.9 * (len(v) - 1) + 0.5)]:{fmt}}"
                what = "median / p90"
            else:
                def figure(v):
                    return f"{rms([v[k] for k in judged]):{fmt}}"
                what = "RMSE"
            parts = [f"{w} {figure(v)}" for w, v in ways.items()]
            gained = sum(abs(learner[k]) < abs(e[k]) for k in judged)
            print(f"  {name} {what}, {unit}: " + ", ".join(parts) + f" (the learner better than delivered on "
                  f"{gained} of {len(judged)}; lag-1 correlation of the errors {rho})")


if __name__ == "__main__":
    main()
