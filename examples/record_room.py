"""How much of a calibrator's error on a real cell could a learner on its record over past discharges take?

    python examples/record_room.py RUN [RUN ...] [--method ukf] [--window 30] [--min-pairs 10]
        [--inputs last,mean5,rest] [--against data|stated]

RUN is a `bcal calibrate --out` folder. The design this measures (docs/calibrator.md, "a learner on the
record"): before each judged discharge, a learner sees the method's signed errors on the discharges that
ended before it (at 50 % of each: the end of discharge in % of the discharge, the capacity in Ah against the
data's charge to the interpolated cut-off, both as `bcal calibrate` scores them, from readings/METHOD/; a
discharge that started from a partial charge has no capacity score) and the rest before this one, and moves
the method's prediction at 50 % by the error it expects. The learner: least squares refitted before every
discharge on the last `--window` discharges' pairs (at least `--min-pairs`; before that, no move), on three
inputs beside an intercept: the last error, the mean of the last five, and the log of the rest before
against the cell's usual rest (`calibration.json`, settings.prior; a rest the schedule does not give counts
as the usual one); a ridge of 1e-3 per pair on the inputs'
coefficients (inputs scaled by the record's spread) keeps a record of equal rests solvable. Within linear
policies on these inputs this is what a policy trained by cost alone (the squared error it leaves) on the
same window would settle on. The settings were fixed before any figure was seen.

`--against stated` puts the capacity the source states (`calibration.json`'s records.capacity_refs) where
the data's charge stands, in what the learner sees and in its score: the two references differ where the
source states the charge to another voltage than the cut-off (NASA: to 2.6-2.7 V on every cell), and there,
as `bcal calibrate` scores it since 2026-11-30, a prediction counts less the charge the discharges before it
drew below that voltage (`stated_tail_ah`).

Printed per run and quantity, over the discharges after the first `--min-pairs` + 1 (the record only):
the method as delivered; recentred (the median of its last 10 signed errors taken off, the rule
`bcal_calib::recentre::biases` applies to the end of discharge, here to either quantity) where that earns
its place by the rule `bcal calibrate` gates every alternative with (`bcal_realcell::tune::online_gate`: a
lower mean and a lower error on 8 of the last 10, never after a rest of more than a day): the non-learned
rule the learner must beat; the learner served always and served where it earns; on how many discharges the
learner beat the delivered prediction and was served; and the errors' lag-1 correlation. Standard library
only.
"""

import argparse
import csv
import json
import math
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import eod_by_age  # noqa: E402  (its scoring of a calibrate run's readings)


def charge_to_ah(t, i, end_s):
    """The charge drawn from the first reading to `end_s`, Ah, as `bcal_calib::eod::charge_to_ah` takes it: the
    discharging current (charging counts 0) by the trapezoid rule, the interval holding `end_s` cut there with
    the current taken linear in it."""
    q_c = 0.0
    for k in range(len(t) - 1):
        i0, i1 = max(i[k], 0.0), max(i[k + 1], 0.0)
        if t[k + 1] <= end_s:
            q_c += 0.5 * (i0 + i1) * (t[k + 1] - t[k])
        else:
            if t[k] < end_s:
                f = (end_s - t[k]) / (t[k + 1] - t[k])
                q_c += 0.5 * (i0 + (i0 + f * (i1 - i0))) * (end_s - t[k])
            break
    return q_c / 3600.0


def signed_errors(path, cutoff_v, reference_ah=None):
    """(EOD error in % of the discharge, capacity error in Ah), each signed (predicted - measured) at the first
    reading at or after 50 % of the discharge, or None where `bcal calibrate` would not score it (the
    capacity against `reference_ah` where given, else against the data's charge from the reading before the
    load came on to the interpolated cut-off, as `bcal calibrate`'s records measure it)."""
    rows = list(csv.DictReader(open(path, newline="")))
    eod = eod_by_age.eod_error_pct(path, cutoff_v, signed=True)
    if eod is None:
        return None, None
    t = [float(r["t_s"]) for r in rows]
    v = [float(r["voltage_v"]) for r in rows]
    i = [float(r["current_a"]) for r in rows]
    on = next(k for k, a in enumerate(i) if a > eod_by_age.LOAD_THRESHOLD_A)
    k = len(rows) - 1
    ended_s = eod_by_age.end_s(t, v, on, cutoff_v)
    at = t[on] + 0.5 * (ended_s - t[on])
    j = next(j for j, x in enumerate(t) if x >= at - 1e-9)
    if rows[j].get("capacity_ah", "") == "":
        return eod, None
    if reference_ah is None:
        reference_ah = charge_to_ah(t[max(on - 1, 0):k + 1], i[max(on - 1, 0):k + 1], ended_s)
    return eod, float(rows[j]["capacity_ah"]) - reference_ah


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


def least_squares(xs, ys, ridge):
    """Coefficients of y on x (x rows start with 1), with `ridge` per row on all but the intercept's (a
    record of equal rests is otherwise singular)."""
    n = len(xs[0])
    a = [[sum(x[p] * x[q] for x in xs) + (ridge * len(xs) if p == q and p > 0 else 0.0) for q in range(n)]
         for p in range(n)]
    return solve(a, [sum(x[p] * y for x, y in zip(xs, ys)) for p in range(n)])


INPUTS = ("last", "mean5", "rest")
# bcal_calib::prior_width::LONG_REST_S: after a longer rest no alternative serves (`online_gate`).
LONG_REST_S = 86_400.0


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


def median(values):
    """The median as `bcal_common::stats::median` takes it (the mean of the middle two of an even count)."""
    v = sorted(values)
    n = len(v)
    return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


def recentred(errors, window=10):
    """Each discharge's error after the median of the signed errors of the last `window` discharges before it
    is taken off (none before any): the rule `bcal_calib::recentre::biases` applies to the end of discharge,
    applied here to either quantity."""
    return [e - median(errors[max(0, k - window):k]) if k else e for k, e in enumerate(errors)]


def gated(errors, alternative, long_rest, window=10, share=0.75):
    """The alternative where it earns its place as `bcal_realcell::tune::online_gate` rules (over the last
    `window` discharges before it: a lower mean absolute error and a lower one on at least `share` of them;
    never after a rest of more than a day, `long_rest`), the method's own error elsewhere."""
    out = []
    for k, e in enumerate(errors):
        mine = [abs(x) for x in alternative[max(0, k - window):k]]
        theirs = [abs(x) for x in errors[max(0, k - window):k]]
        wins = sum(a < b for a, b in zip(mine, theirs))
        earns = len(theirs) == window and sum(mine) < sum(theirs) and wins >= math.ceil(share * window)
        out.append(alternative[k] if earns and not long_rest[k] else e)
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
    p.add_argument("--against", choices=("data", "stated"), default="data",
                   help="the capacity the learner learns and is scored against: the data's charge to the cut-off, or "
                        "the capacity the source states (calibration.json's records.capacity_refs)")
    a = p.parse_args()
    inputs_used = [x for x in a.inputs.split(",") if x]
    if any(x not in INPUTS for x in inputs_used):
        raise SystemExit(f"--inputs {a.inputs}: each input is one of {', '.join(INPUTS)}")
    for run in a.runs:
        report = run / "calibration.json"
        if not report.exists():
            raise SystemExit(f"{report}: not found (RUN is a `bcal calibrate --out` folder)")
        j = json.load(open(report))
        prior = j.get("settings", {}).get("prior")
        if prior is None or "cutoff_v" not in j:
            raise SystemExit(f"{report}: no settings.prior or cutoff_v (a calibration.json of `bcal calibrate` with a "
                             "streaming method is needed)")
        # A rest the schedule does not give counts as the usual one (the input then says nothing).
        usual_s = (prior.get("width") or {}).get("usual_rest_s") or 1.0
        rest_of = {d["cycle"]: d.get("rest_before_s") for d in prior.get("judged", [])}
        # A discharge that started from a partial charge is scored on its end, not its capacity.
        partial = set(j["records"].get("partial_start", []))
        stated = None
        if a.against == "stated":
            refs = j["records"].get("capacity_refs")
            if refs is None:
                raise SystemExit(f"{report}: no records.capacity_refs (a report of a bcal older than --against "
                                 "stated; run bcal calibrate again)")
            # As `bcal calibrate` scores it: a discharge whose source states no capacity has none to score, and
            # one stated to a voltage above the cut-off is scored less the tail below it (`stated_tail_ah`).
            stated = {r["cycle"]: r["stated_ah"] + (r.get("stated_tail_ah") or 0.0) for r in refs
                      if (r.get("stated_ah") or 0.0) > 0.0}
            # How the two references stand apart on the judged discharges, beside what the training ones showed.
            gaps = sorted(r["stated_ah"] - r["data_ah"] for r in refs
                          if r["cycle"] in stated and r.get("data_ah") is not None and not r.get("partial_start"))
            tailed = sorted(stated[r["cycle"]] - r["data_ah"] for r in refs
                          if r["cycle"] in stated and r.get("data_ah") is not None and not r.get("partial_start"))
            if gaps:
                mean = sum(gaps) / len(gaps)
                sd = math.sqrt(sum((g - mean) ** 2 for g in gaps) / len(gaps))
                trained = (j["records"].get("stated_capacity") or {}).get("cutoff_median_gap_ah")
                print(f"{run.name}: the stated capacity less the data's charge to the cut-off on {len(gaps)} judged "
                      f"discharges: median {median(gaps):+.4f} Ah, sd {sd:.4f}" +
                      ("" if trained is None else f"; on the training discharges median {trained:+.4f} Ah") +
                      (f"; with the tail below the stated voltage added, median {median(tailed):+.4f} Ah"
                       if tailed != gaps else ""))
        scored = ({}, {})
        for f in sorted((run / "readings" / a.method).glob("*.csv")):
            cycle = int(f.stem.rsplit("-", 1)[1])
            if stated is not None and cycle not in stated:
                scored[0][cycle] = signed_errors(f, j["cutoff_v"])[0]
                continue
            reference = None if stated is None else stated[cycle]
            for q, e in enumerate(signed_errors(f, j["cutoff_v"], reference)):
                if e is not None and not (q == 1 and cycle in partial):
                    scored[q][cycle] = e
        scored = tuple({c: e for c, e in s.items() if e is not None} for s in scored)
        against = "the data's charge" if stated is None else "the stated capacity"
        print(f"{run.name} ({a.method}; capacity against {against}; on each quantity the first {a.min_pairs + 1} "
              "discharges scored are record only):")
        for q, (name, unit, fmt) in enumerate([("EOD at 50 %", "%", ".3f"), ("capacity from 50 %", "Ah", ".4f")]):
            cycles = sorted(scored[q])
            if len(cycles) <= a.min_pairs + 1:
                print(f"  {name}: {len(cycles)} discharges scored, too few for a record")
                continue
            e = [scored[q][c] for c in cycles]
            rests = [rest_of.get(c) or usual_s for c in cycles]
            long_rest = [r > LONG_REST_S for r in rests]
            learner = corrected(e, rests, usual_s, a.window, a.min_pairs, inputs_used)
            ways = {"delivered": e, "recentred": gated(e, recentred(e), long_rest), "learner": learner,
                    "learner where it earns": gated(e, learner, long_rest)}
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
            served = sum(ways["learner where it earns"][k] != e[k] for k in judged)
            print(f"  {name} {what}, {unit}, {len(judged)} discharges: " + ", ".join(parts) +
                  f" (the learner better than delivered on {gained}, served where it earns on {served}; lag-1 "
                  f"correlation of the errors {rho})")
            # The capacity's scoring checked against bcal calibrate's own, over every judged discharge.
            key = "capacity" if stated is not None else "capacity_vs_data"
            theirs = j.get("methods", {}).get(a.method, {}).get("scores", {}).get(key, {}).get("50", {})
            if q == 1 and "rmse" in theirs:
                print(f"    scored as bcal calibrate does: every judged discharge {rms(e):.6f} Ah, calibration.json "
                      f"{theirs['rmse']:.6f} Ah")


if __name__ == "__main__":
    main()
