"""Many discharges of a real cell as one live stream: a NASA PCoE cell's discharge records joined end to end
at their recorded start times (the charges between them are not in the data, so the stream jumps from the
cut-off to a charged cell's rest across each gap), fed to `bcal calibrate --follow -`, and each discharge's
end-of-discharge prediction at half its loaded time scored against the time the voltage first fell below
the cut-off under load. Standard library only.

    python examples/follow_nasa_stream.py [--data ../shared/data/nasa-pcoe] [--cell B0005] [--cycles 41..80]
        [--history-from 1] [--kind ukf] [--cutoff-v 3.0] [--model diagnosis.json] [--config cell.toml] [--bcal PATH]

Prints, per discharge, the prediction's error in % of the time from the load's start to the end of
discharge (and whether the stream's 90 % interval held the end), and the median and 90th percentile of its
size and the interval's coverage, two ways: the stream as one (`--follow` starts
each discharge from what the last one told, with a prior width learned from the discharges before), and
each discharge alone from the calibrator's default prior (what `--follow` did with a stream per discharge),
with the median error at 10 and 90 % of each discharge beside them: one share alone can flatter an estimate
that drifts through every discharge the same way (B0055 alone: 1.34 % at half, 10-33 % elsewhere).
`--history-from H` starts the stream at discharge H, before the scored ones (the cell's history a BMS would
have followed: the learner on the record of `--kind ukf_learned` and the stream's prior width learn from it);
those discharges are followed but not scored. The charge each discharge delivers as the stream predicted
it at half (`delivered_ah`) is scored too, against the charge to the interpolated cut-off (RMSE, Ah).
"""

import argparse
import csv
import json
import os
import pathlib
import re
import shutil
import statistics
import subprocess
import sys
from datetime import datetime, timezone

REPO = pathlib.Path(__file__).resolve().parent.parent
HEADER = "time_s,voltage_v,current_a,temperature_c\n"
# Scored predictions at half a discharge that were the prior alone's (the stream's gate), one entry each.
PRIOR_SERVED: list = []
# The same for the calibrator's own prediction recentred on its bias over the last discharges.
RECENTRED_SERVED: list = []
# The same for the calibrator's own prediction moved on the voltage change against the discharge before.
VOLTAGE_SERVED: list = []
# The prior alone's weight in each scored prediction at half a discharge blended with it (0 < weight < 1).
BLEND_WEIGHTS: list = []
# The previous discharge's fit's weight in each scored prediction at half a discharge blended with it.
PREVIOUS_WEIGHTS: list = []
# The learner on the record's weight in each scored prediction at half a discharge it moved (kind ukf_learned).
LEARNED_WEIGHTS: list = []
# The CLI's closing summary of the last stream followed (its stderr).
LAST_SUMMARY: list = [""]


def find_bcal() -> str:
    for c in (os.environ.get("BCAL_BIN"), REPO / "target" / "release" / "bcal", REPO / "target" / "debug" / "bcal",
              shutil.which("bcal")):
        if c and pathlib.Path(c).is_file():
            return str(c)
    raise SystemExit("the bcal CLI is not built: cargo build --release -p bcal, or pass --bcal PATH")


def start_s(vec: str) -> float:
    """NASA's start_time, a MATLAB date vector printed by numpy, in seconds (UTC)."""
    v = [float(x) for x in vec.strip("[]").split()]
    whole = datetime(int(v[0]), int(v[1]), int(v[2]), int(v[3]), int(v[4]), tzinfo=timezone.utc)
    return whole.timestamp() + v[5]


def discharges(root: pathlib.Path, cell: str, first: int, last: int) -> list:
    """The cell's discharge records `first..last` (1-based, in file order) as lists of CSV rows with
    absolute times, NASA's sign (negative discharges)."""
    if not (root / "metadata.csv").is_file():
        raise SystemExit(f"{root}: no metadata.csv (give the NASA PCoE folder with --data)")
    meta = [r for r in csv.DictReader(open(root / "metadata.csv")) if r["battery_id"] == cell and r["type"] == "discharge"]
    if len(meta) < last:
        raise SystemExit(f"{cell} has {len(meta)} discharges in {root / 'metadata.csv'}; --cycles asks for {last}")
    out, latest = [], float("-inf")
    for r in meta[first - 1:last]:
        path = root / "data" / r["filename"]
        if not path.is_file():
            raise SystemExit(f"{path}: missing (the folder holds only some cells' records)")
        t0 = start_s(r["start_time"])
        rows = []
        for d in csv.DictReader(open(path)):
            t = t0 + float(d["Time"])
            if t <= latest:
                continue  # a clock that steps back: keep time order, as the stream requires
            latest = t
            rows.append((t, float(d["Voltage_measured"]), float(d["Current_measured"]), float(d["Temperature_measured"])))
        out.append(rows)
    return out


def follow(bcal: str, kind: str, rows: list, cutoff_v: float, extra: list) -> list:
    text = HEADER + "".join(f"{t!r},{v!r},{i!r},{c!r}\n" for t, v, i, c in rows)
    p = subprocess.run([bcal, "calibrate", "--follow", "-", "--calibrator", kind, "--current-sign", "discharge-negative",
                        "--cutoff-v", str(cutoff_v)] + extra, input=text, capture_output=True, text=True, check=False)
    if p.returncode != 0:
        raise SystemExit(f"bcal calibrate --follow failed: {p.stderr.strip()}")
    LAST_SUMMARY[0] = p.stderr
    return [json.loads(line) for line in p.stdout.splitlines()]


def crossing(rows: list, cutoff_v: float):
    """The load-on time and the end of discharge: the crossing interpolated between the last loaded reading
    above the cut-off and the first below, as the stream and `bcal calibrate` score it (the first reading
    below lies up to a sample interval, 10-20 s here, past it), that first reading's row, and whether the
    end is interpolated between two neighbouring rows; None when the discharge never reaches the cut-off
    under load."""
    loaded = [(k, r) for k, r in enumerate(rows) if -r[2] > 0.5]
    below = next((n for n, (_, r) in enumerate(loaded) if r[1] < cutoff_v), None)
    if below is None:
        return None
    t_on = loaded[0][1][0]
    k1, (t1, v1) = loaded[below][0], loaded[below][1][:2]
    if below > 0:
        k0, (t0, v0) = loaded[below - 1][0], loaded[below - 1][1][:2]
        if v0 > v1:
            return t_on, t0 + (v0 - cutoff_v) / (v0 - v1) * (t1 - t0), k1, k1 == k0 + 1
    return t_on, t1, k1, False


def eod_error_pct(rows: list, est: list, cutoff_v: float, fraction: float = 0.5):
    """The prediction at `fraction` (half by default) of the loaded time to the end of discharge, in % of that
    time (None when the discharge never reaches the cut-off under load or no prediction was made), and
    whether its 90 % interval holds the measured end (None without an interval: an older bcal, or before the
    stream has scored nine discharges). Only the half-way prediction counts toward the prior's share."""
    c = crossing(rows, cutoff_v)
    if c is None:
        return None, None
    t_on, eod = c[:2]
    mid = t_on + fraction * (eod - t_on)
    k = min(range(len(rows)), key=lambda j: abs(rows[j][0] - mid))
    p, lo, hi = est[k]["eod_s"], est[k].get("eod_lo_s"), est[k].get("eod_hi_s")
    if est[k].get("eod_from_prior") and fraction == 0.5:
        PRIOR_SERVED.append(True)
    if est[k].get("eod_recentred") and fraction == 0.5:
        RECENTRED_SERVED.append(True)
    if est[k].get("eod_on_voltage_change") and fraction == 0.5:
        VOLTAGE_SERVED.append(True)
    if 0.0 < (est[k].get("eod_prior_weight") or 0.0) < 1.0 and fraction == 0.5:
        BLEND_WEIGHTS.append(est[k]["eod_prior_weight"])
    if 0.0 < (est[k].get("eod_previous_weight") or 0.0) < 1.0 and fraction == 0.5:
        PREVIOUS_WEIGHTS.append(est[k]["eod_previous_weight"])
    if (est[k].get("eod_learned_weight") or 0.0) > 0.0 and fraction == 0.5:
        LEARNED_WEIGHTS.append(est[k]["eod_learned_weight"])
    # Whether the interval held the end, and its width (hi - lo) in % of the time to the end.
    held = None if lo is None or hi is None else (lo <= eod <= hi, 100.0 * (hi - lo) / (eod - t_on))
    return (None if p is None else 100.0 * (p - eod) / (eod - t_on)), held


def delivered_error_ah(rows: list, est: list, cutoff_v: float):
    """The charge the discharge delivers as the stream predicted it at half its loaded time (`delivered_ah`)
    less the charge it delivered (its readings' discharging current, trapezoids, from its first reading to
    the interpolated cut-off crossing), Ah; None where it never reached the cut-off or nothing was predicted."""
    c = crossing(rows, cutoff_v)
    if c is None or not c[3]:
        return None
    t_on, eod, k1, _ = c
    drawn = 0.0
    for x, y in zip(rows[:k1], rows[1:k1 + 1]):
        to = min(y[0], eod)
        i_to = x[2] + (y[2] - x[2]) * (to - x[0]) / (y[0] - x[0])
        drawn += 0.5 * (max(-x[2], 0.0) + max(-i_to, 0.0)) * (to - x[0])
    mid = t_on + 0.5 * (eod - t_on)
    k = min(range(len(rows)), key=lambda j: abs(rows[j][0] - mid))
    p = est[k].get("delivered_ah")
    return None if p is None else p - drawn / 3600.0


def summary(name: str, scores: list, others: dict) -> None:
    """Half-way scores (`scores`) with their intervals, and the median error at the other shares (`others`:
    share -> errors), since one share alone can flatter an estimate that drifts through the discharge."""
    errors = [e for e, _ in scores]
    sizes = sorted(abs(e) for e in errors if e is not None)
    if not sizes:
        print(f"{name}: no discharge reached the cut-off with a prediction")
        return
    p90 = sizes[round(0.9 * (len(sizes) - 1))]
    held = [c for _, c in scores if c is not None]
    cover = (f"; 90 % interval holds the end on {sum(h for h, _ in held)} of {len(held)} "
             f"({100.0 * sum(h for h, _ in held) / len(held):.1f} %), median width "
             f"{statistics.median(w for _, w in held):.1f} %" if held else "")
    print(f"{name}: EOD at 50 % median {statistics.median(sizes):.2f} %, p90 {p90:.2f} % over {len(sizes)} discharges"
          f" ({errors.count(None)} without a score){cover}")
    at = []
    for share, errs in sorted(others.items()):
        e = sorted(abs(x) for x in errs if x is not None)
        if e:
            at.append(f"{round(100 * share)} % {statistics.median(e):.2f} / {e[round(0.9 * (len(e) - 1))]:.2f}")
    if at:
        print(f"  median / p90 EOD error at the other shares: {', '.join(at)} %")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(REPO.parent / "shared" / "data" / "nasa-pcoe"))
    p.add_argument("--cell", default="B0005")
    p.add_argument("--cycles", default="41..80", help="discharges A..B, 1-based in file order")
    p.add_argument("--history-from", type=int, default=None,
                   help="start the stream at discharge H (1-based, at most A): H..A-1 are followed, not scored")
    p.add_argument("--kind", default="ukf")
    p.add_argument("--cutoff-v", type=float, default=None,
                   help="the cut-off the stream predicts and is scored at, V (default 3.0, the model's own, said on "
                        "stderr: give the cell's, e.g. 2.7 for B0005, 2.5 for B0006 and B0018, from its extra_infos)")
    p.add_argument("--bcal", default=None, help="the bcal executable (default: this clone's build)")
    p.add_argument("--model", default=None, help="the doctor's diagnosis.json to calibrate on (default: the base model)")
    p.add_argument("--config", default=None, help="a bcal cell-config TOML: the cell's filter, prior, ranges and lifetime model")
    a = p.parse_args()
    try:
        first, last = (int(x) for x in a.cycles.split(".."))
    except ValueError:
        raise SystemExit(f"--cycles {a.cycles!r}: give A..B, e.g. 41..80") from None
    if not 1 <= first <= last:
        raise SystemExit(f"--cycles {a.cycles!r}: need 1 <= A <= B")
    history = first if a.history_from is None else a.history_from
    if not 1 <= history <= first:
        raise SystemExit(f"--history-from {history}: need 1 <= H <= {first} (the first scored discharge)")
    if a.cutoff_v is None:
        a.cutoff_v = 3.0
        print(f"note: scoring at the default cut-off 3.0 V, not {a.cell}'s own: give --cutoff-v (e.g. 2.7 for B0005)",
              file=sys.stderr)
    bcal = a.bcal or find_bcal()
    if a.model and not pathlib.Path(a.model).is_file():
        raise SystemExit(f"--model {a.model}: no such file (bcal diagnose --out DIR writes DIR/diagnosis.json)")
    if a.config and not pathlib.Path(a.config).is_file():
        raise SystemExit(f"--config {a.config}: no such file (bcal cell-config --out FILE writes one)")
    extra = (["--model", a.model] if a.model else []) + (["--config", a.config] if a.config else [])
    followed = discharges(pathlib.Path(a.data), a.cell, history, last)
    records = followed[first - history:]

    stream = follow(bcal, a.kind, [r for rows in followed for r in rows], a.cutoff_v, extra)
    timing = re.search(r"parse \+ step \+ predict per reading: [^;\n]*", LAST_SUMMARY[0])
    # The discharges whose fit sat at an edge of the setting's ranges (a cell outside them), as the CLI counted
    # them over the whole stream: its closing summary's, the last (a warning at the first comes before it).
    edges = re.findall(r"\d+ of \d+ discharges? handed on a fit at the edge of the setting's ranges \([^)]*\)",
                       LAST_SUMMARY[0])
    # The history's estimates are not scored.
    joined, alone, k = [], [], sum(len(rows) for rows in followed[:first - history])
    delivered = []
    shares = (0.1, 0.9)
    joined_at, alone_at = {f: [] for f in shares}, {f: [] for f in shares}
    for n, rows in enumerate(records):
        part = stream[k:k + len(rows)]
        k += len(rows)
        own = follow(bcal, a.kind, rows, a.cutoff_v, extra)
        joined.append(eod_error_pct(rows, part, a.cutoff_v))
        delivered.append(delivered_error_ah(rows, part, a.cutoff_v))
        alone.append(eod_error_pct(rows, own, a.cutoff_v))
        for f in shares:
            joined_at[f].append(eod_error_pct(rows, part, a.cutoff_v, f)[0])
            alone_at[f].append(eod_error_pct(rows, own, a.cutoff_v, f)[0])
        fmt = lambda e: "-" if e is None else f"{e:+.1f}"  # noqa: E731
        held = "" if joined[-1][1] is None else [" (outside its interval)", " (in its interval)"][joined[-1][1][0]]
        print(f"discharge {first + n} (stream's #{part[-1].get('discharge', '-')}): EOD error at 50 % {fmt(joined[-1][0])} %"
              f"{held} as one stream, {fmt(alone[-1][0])} % alone")
    served = len(PRIOR_SERVED)
    since = f" from discharge {history}" if history < first else ""
    summary(f"{a.cell} {a.cycles}, {a.kind}, one stream{since}", joined, joined_at)
    print(f"  (the prior alone predicted at half of {served} of the {len(records)} discharges, the calibrator's own "
          f"recentred on its bias at half of {len(RECENTRED_SERVED)}, moved on the voltage change against the "
          f"discharge before at half of {len(VOLTAGE_SERVED)}; blended with the prior alone at half of "
          f"{len(BLEND_WEIGHTS)}, the prior's median weight "
          f"{statistics.median(BLEND_WEIGHTS) if BLEND_WEIGHTS else 0.0:.2f}; with the previous discharge's fit at "
          f"half of {len(PREVIOUS_WEIGHTS)}, its median weight "
          f"{statistics.median(PREVIOUS_WEIGHTS) if PREVIOUS_WEIGHTS else 0.0:.2f}; moved by the learner on the record at "
          f"half of {len(LEARNED_WEIGHTS)}, its median weight "
          f"{statistics.median(LEARNED_WEIGHTS) if LEARNED_WEIGHTS else 0.0:.2f})")
    d = [e for e in delivered if e is not None]
    if d:
        rmse = (sum(e * e for e in d) / len(d)) ** 0.5
        print(f"  charge delivered (delivered_ah) at half against the data's charge to the cut-off: RMSE {rmse:.4f} Ah, "
              f"median |error| {statistics.median(abs(e) for e in d):.4f} Ah over {len(d)} discharges")
    if timing:
        print(f"  ({timing.group(0)}, as the CLI timed the one stream)")
    at_edge = edges[-1] if edges else "no discharge handed on a fit at the edge of the setting's ranges"
    print(f"  ({at_edge}, over the one stream)")
    summary(f"{a.cell} {a.cycles}, {a.kind}, each discharge alone", alone, alone_at)


if __name__ == "__main__":
    main()
