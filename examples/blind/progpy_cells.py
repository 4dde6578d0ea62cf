"""Blind-test cells: synthetic NASA-PCoE-layout lives simulated with progpy's BatteryElectroChemEOD, of the
protocols of NASA cells bcal has no data of (README_33_34_36, _38_39_40, _41_42_43_44, _45_46_47_48).

Independent of bcal's code (progpy's own model and integrator). Writes OUT/{metadata.csv, data/NNNNN.csv,
extra_infos/...} and the truth of every discharge (qMobile, Ro, current, ambient, end) to TRUTH.

    python3 -m venv venv && venv/bin/pip install progpy numpy
    venv/bin/python examples/blind/progpy_cells.py --out blind/data-root --truth blind/truth.csv
    target/release/bcal calibrate --data blind/data-root --cell B0042 --out blind/B0042

Cells (ids of the protocols they mimic; not NASA's data): B0038 (1 / 2 / 4 A, 24 and 44 C in blocks, 2.2 V),
B0042 (4 C with a 22 C block, 4 A with every fourth at 1 A, a block stopped under load at 40-60 %, 2.2 V),
B0045 (1 A at 4 C, 2.0 V), B0033 (4 A at 24 C, 2.0 V), B0041 (a cold cell of high resistance: 42 discharges
at 4 A that deliver about 0.02 Ah above 2.7 V, then 25 at 1 A, 2.0 V), B0049 (README_49_50_51_52: 2 A at 4 C,
2.0 V, 25 discharges, four of them started from a charge cut short, at 55, 25, 5 and 40 % of full, as NASA's
cells whose control software crashed hold runs "where the capacity as well as voltage levels were very low";
added 2026-11-30). Generated 2026-11-29 for the blind test of that day's note; `doctor/tests/data/progpy-4a-4c-late.csv`
is B0042's cycle 57.

Model: progpy 1.9 BatteryElectroChemEOD, stepped with its own `next_state` (forward Euler), dt = 1 s (steps
shortened to land on logging times; the step that crosses the cut-off is re-done in dt/10 sub-steps, twice if
needed, so the cycler stops at the first model voltage below the cut-off, as a cycler checking every second).

Temperature: the model HAS a temperature state `tb` (its own Newman heating with mC = 37.04, tau = 100 s gives
only ~2 K at 2 A). We DRIVE it: every step tb is overwritten with ambient + dT, where dT follows a lumped
thermal model dT' = (Rth * P / (1 + P / Psat) - dT) / tau_th with P = i * (Vo + Vsn + Vsp) (the model's own
overpotential heat, i.e. I^2 R_eff), Rth = 44 K/W, Psat = 0.8 W, tau_th = 1400 s: a 2 A discharge heats ~14-17 K
as NASA's cells do, 1 A ~7 K, 4 A ~18-22 K (B0029's 4 A discharges heat ~15 K).
The written Temperature_measured is that tb (+ 0.2 K noise); the model's voltage sees the same tb.

Initial state: full charge, x0 qnS/qnB = qMax * xnMax * (VolSFraction | 1 - VolSFraction) set explicitly per
discharge (progpy 1.9's parameter callbacks do NOT update qnS/qnB when qMobile changes; without this the cell
would start with the 7600 C default's charge whatever qMobile says). Open-circuit voltage at start ~4.19 V. A
part-charged start (`partial`) moves the charge not put back into the positive electrode, lithium conserved, at
rest (surface and bulk alike).
"""

import argparse
import csv
import datetime as dt_
import math
import os
from multiprocessing import Pool

try:
    import numpy as np
    from progpy.models import BatteryElectroChemEOD
except ImportError as e:
    raise SystemExit(f"{e}: the generator runs progpy's model (python3 -m venv venv && venv/bin/pip install progpy "
                     "numpy, then venv/bin/python examples/blind/progpy_cells.py)") from None

DT = 1.0
RTH = 44.0  # K/W at low power
P_SAT = 0.8  # W: heat rise saturates (cooling improves as the cell warms)
TAU_TH = 1400.0  # s
V_NOISE, I_NOISE, T_NOISE = 0.004, 0.005, 0.2


def design(cell, rng):
    """Per-discharge protocol of a cell: list of dicts (current, ambient, cutoff, early stop, long rest before,
    part-charged start)."""
    partial = {}
    if cell == "B0038":
        n, cutoff = 47, 2.2
        cur = rng.choice([1.0, 2.0, 4.0], size=n)
        amb = [24 if (k // 10) % 2 == 0 else 44 for k in range(n)]
        rests = {13: 4.0, 30: 6.5, 41: 3.0}
        early = {}
        q0, r0, fade, rise = 7300.0, 0.120, 0.25, 0.45
        t0 = dt_.datetime(2010, 4, 14, 16, 43, 39)
    elif cell == "B0042":
        n, cutoff = 84, 2.2
        cur = np.array([1.0 if k % 4 == 3 else 4.0 for k in range(n)])
        amb = [22 if 30 <= k < 45 else 4 for k in range(n)]
        rests = {15: 3.0, 30: 5.0, 47: 2.5, 57: 4.5, 70: 8.0}
        early = {k: rng.uniform(0.40, 0.60) for k in range(50, 55)}
        for k in early:
            cur[k] = 4.0
        q0, r0, fade, rise = 7100.0, 0.118, 0.28, 0.55
        t0 = dt_.datetime(2010, 6, 3, 20, 31, 2)
    elif cell == "B0045":
        n, cutoff = 72, 2.0
        cur = np.full(n, 1.0)
        amb = [4] * n
        rests = {12: 3.0, 33: 3.5, 50: 2.2, 63: 6.0}
        early = {}
        q0, r0, fade, rise = 7200.0, 0.115, 0.22, 0.35
        t0 = dt_.datetime(2010, 7, 21, 15, 0, 35)
    elif cell == "B0041":
        n, cutoff = 67, 2.0
        cur = np.array([4.0 if k < 42 else 1.0 for k in range(n)])
        amb = [4] * n
        rests = {20: 3.0, 42: 5.0, 55: 4.0}
        early = {}
        q0, r0, fade, rise = 7000.0, 0.40, 0.25, 0.30
        t0 = dt_.datetime(2010, 6, 3, 20, 31, 2)
    elif cell == "B0049":
        # NASA's "experiment control software crashed" cells: 2 A at 4 C, a short life, and discharges whose
        # capacity and voltages were very low (here: charges cut short, the cell starting part-charged)
        n, cutoff = 25, 2.0
        cur = np.full(n, 2.0)
        amb = [4] * n
        rests = {9: 3.0, 17: 5.0}
        early = {}
        partial = {6: 0.55, 12: 0.25, 13: 0.05, 20: 0.4}
        q0, r0, fade, rise = 7150.0, 0.120, 0.12, 0.25
        t0 = dt_.datetime(2010, 9, 1, 11, 2, 47)
    elif cell == "B0033":
        n, cutoff = 100, 2.0
        cur = np.full(n, 4.0)
        amb = [24] * n
        rests = {21: 3.5, 44: 2.0, 60: 12.0, 78: 4.0, 90: 7.0}
        early = {}
        q0, r0, fade, rise = 7400.0, 0.116, 0.27, 0.50
        t0 = dt_.datetime(2009, 6, 19, 17, 18, 16)
    else:
        raise ValueError(cell)
    return dict(n=n, cutoff=cutoff, cur=cur, amb=amb, rests=rests, early=early, q0=q0, r0=r0, fade=fade,
                rise=rise, t0=t0, partial=partial)


def aging(d, rng):
    """qMobile (C) and Ro (ohm) per discharge: smooth fade/growth, recovery after long rests, small noise."""
    n = d["n"]
    s = np.arange(n) / (n - 1)
    q_trend = d["q0"] * (1 - d["fade"] * (0.6 * s + 0.4 * s ** 2))
    r_trend = d["r0"] * (1 + d["rise"] * (0.7 * s + 0.3 * s ** 2))
    rec = np.zeros(n)
    jumps = {}
    for k, days in d["rests"].items():
        a = float(np.clip(0.015 + 0.008 * days, 0.02, 0.08)) * rng.uniform(0.85, 1.15)
        a = float(np.clip(a, 0.02, 0.08))
        jumps[k] = a
        kk = np.arange(k, n)
        rec[kk] += a * np.exp(-(kk - k) / 4.0)
    q = q_trend * (1 + rec) * (1 + rng.normal(0, 0.003, n))
    r = r_trend * (1 + rng.normal(0, 0.012, n))
    return q, r, rec, jumps


def set_full(m, q, ro, amb_c, frac=1.0):
    """The cell at rest, charged to `frac` of its mobile charge (1: full)."""
    m.parameters["qMobile"] = float(q)
    m.parameters["Ro"] = float(ro)
    p = m.parameters
    qmax = p["qMax"]
    x0 = dict(p["x0"])
    x0["qnS"] = qmax * p["xnMax"] * p["VolSFraction"]
    x0["qnB"] = qmax * p["xnMax"] * (1 - p["VolSFraction"])
    if frac < 1.0:
        # the charge not put back stays in the positive electrode (lithium conserved)
        moved = qmax * p["xnMax"] * (1 - frac)
        x0["qnS"] -= moved * p["VolSFraction"]
        x0["qnB"] -= moved * (1 - p["VolSFraction"])
        x0["qpS"] = qmax * p["xpMin"] * p["VolSFraction"] + moved * p["VolSFraction"]
        x0["qpB"] = qmax * p["xpMin"] * (1 - p["VolSFraction"]) + moved * (1 - p["VolSFraction"])
    x0["tb"] = amb_c + 273.15
    x0["Vo"] = x0["Vsn"] = x0["Vsp"] = 0.0
    p["x0"] = x0
    return m.initialize()


def simulate(m, q, ro, cur, amb_c, cutoff, t_on, relax_s, sample_dt, rng, frac=1.0):
    """One discharge record. Returns rows (t, v, i, T, loaded) true values, plus summary."""
    x = set_full(m, q, ro, amb_c, frac)
    T_amb = amb_c + 273.15
    dT = 0.0
    t = 0.0
    # logging times
    def next_log(tl):
        return tl + max(1.0, sample_dt + rng.normal(0, 0.12) + (0.6 if rng.random() < 0.05 else 0.0))

    rows = []
    z = m.output(x)
    rows.append((0.0, float(z["v"]), 0.0, float(z["t"]), False))
    tlog = next_log(0.0)
    u0 = m.InputContainer({"i": 0.0})
    uI = m.InputContainer({"i": float(cur)})
    t_cut = None
    max_dT = 0.0
    phase = "rest"
    t_end = None
    while True:
        loaded = phase == "load"
        u = uI if loaded else u0
        i_now = cur if loaded else 0.0
        # step target
        targets = [t + DT, tlog]
        if phase == "rest":
            targets.append(t_on)
        if phase == "relax":
            targets.append(t_end)
        tn = min(targets)
        h = tn - t
        if h <= 1e-9:
            h = 0.0
        xn = m.next_state(x, u, h) if h > 0 else x
        P = i_now * float(x["Vo"] + x["Vsn"] + x["Vsp"])
        dTn = dT + h * (RTH * P / (1 + P / P_SAT) - dT) / TAU_TH
        xn["tb"] = T_amb + dTn
        zn = m.output(xn)
        vn = float(zn["v"])
        if loaded and (not np.isfinite(vn) or vn < cutoff):
            # refine: sub-steps of h/10 (and h/100) from x until the first finite v < cutoff
            xs, ts, dTs = x, t, dT
            found = False
            for level in (10, 100, 1000):
                hs = h / level
                xs2, ts2, dTs2 = xs, ts, dTs
                for _ in range(level + 1):
                    xc = m.next_state(xs2, u, hs)
                    Pc = i_now * float(xs2["Vo"] + xs2["Vsn"] + xs2["Vsp"])
                    dTc = dTs2 + hs * (RTH * Pc / (1 + Pc / P_SAT) - dTs2) / TAU_TH
                    xc["tb"] = T_amb + dTc
                    vc = float(m.output(xc)["v"])
                    if np.isfinite(vc) and vc < cutoff:
                        xs2, ts2, dTs2 = xc, ts2 + hs, dTc
                        found = True
                        break
                    if not np.isfinite(vc):
                        break  # refine from xs2 with a smaller step
                    xs2, ts2, dTs2 = xc, ts2 + hs, dTc
                if found:
                    break
                xs, ts, dTs = xs2, ts2, dTs2
            if not found:
                raise RuntimeError(f"cut-off crossing not resolved q={q} I={cur}")
            x, t, dT = xs2, ts2, dTs2
            zc = m.output(x)
            rows.append((t, float(zc["v"]), cur, float(zc["t"]), True))
            t_cut = t
            phase = "relax"
            t_end = t + relax_s
            tlog = next_log(t)
            continue
        x, t, dT = xn, tn, dTn
        max_dT = max(max_dT, dT)
        if phase == "rest" and abs(t - t_on) < 1e-9:
            phase = "load"
        if abs(t - tlog) < 1e-9:
            rows.append((t, vn, i_now if phase != "rest" or loaded else 0.0, float(zn["t"]), loaded))
            tlog = next_log(t)
        if phase == "relax" and abs(t - t_end) < 1e-9:
            break
    return rows, dict(t_cut=t_cut, max_dT=max_dT)


def write_record(path, rows, cur, rng, cutoff=None):
    """NASA cleaned layout with noise; returns charge to cut-off/end (Ah) and to 2.7 V on the noisy data."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["Voltage_measured", "Current_measured", "Temperature_measured", "Current_load", "Voltage_load", "Time"])
        meas = []
        n = len(rows)
        last_loaded = max((k for k, r in enumerate(rows) if r[4]), default=-1)
        for k, (t, v, i, T, loaded) in enumerate(rows):
            vm = v + rng.normal(0, V_NOISE)
            if cutoff is not None and k == last_loaded and v < cutoff:
                # the cycler stopped on its own (noisy) reading: the logged stop reading is below the cut-off
                vm = min(vm, cutoff - 0.001 - abs(rng.normal(0, V_NOISE)))
            im = -i + rng.normal(0, I_NOISE)
            Tm = T - 273.15 + rng.normal(0, T_NOISE) if T > 200 else T + rng.normal(0, T_NOISE)
            if loaded:
                cl = -round(cur * 0.9991, 4)
                vl = round(max(v - 0.45 * cur, 0.0), 3)
            else:
                cl = -0.0006 if rng.random() < 0.8 else -0.0004
                vl = 4.206 if k == 1 else (0.0 if rng.random() < 0.85 else 0.001)
            meas.append((t, vm, im, loaded))
            w.writerow([repr(float(vm)), repr(float(im)), repr(float(Tm)), repr(cl), repr(vl), repr(round(t, 3))])
    return meas


def charges(meas, cutoff):
    """From the written (noisy) record: charge to the cut-off crossing under load, and to 2.7 V (NASA Capacity)."""
    q = 0.0
    q27 = None
    for k in range(1, len(meas)):
        t0, v0, i0, l0 = meas[k - 1]
        t1, v1, i1, l1 = meas[k]
        q += -i0 * (t1 - t0) / 3600
        if q27 is None and l1 and v1 < 2.7:
            q27 = q
        if l1 and v1 <= cutoff:
            return q, q27 if q27 is not None else q
    return q, q27 if q27 is not None else q


def datevec(t):
    s = t.second + t.microsecond / 1e6
    return str(np.array([float(t.year), float(t.month), float(t.day), float(t.hour), float(t.minute), round(s, 3)]))


def gen_cell(args):
    cell, out, seed = args
    rng = np.random.default_rng(seed)
    d = design(cell, rng)
    q, r, rec, jumps = aging(d, rng)
    m = BatteryElectroChemEOD()
    meta = []
    truth = []
    t_start = d["t0"]
    base_dt = rng.uniform(17.5, 19.0)
    late_dt = rng.uniform(9.2, 9.8)
    switch = int(d["n"] * rng.uniform(0.25, 0.4))
    test_id = 0
    prev_end = None
    for k in range(d["n"]):
        cur = float(d["cur"][k])
        amb = d["amb"][k]
        t_on = rng.uniform(20.0, 36.0)
        relax = rng.uniform(360, 480)
        sdt = base_dt if k < switch else late_dt
        early = d["early"].get(k)
        stop_t = None
        if early is not None:
            # simulate full first to know the charge it would deliver, then stop at `early` of it
            full_rows, full_info = simulate(m, q[k], r[k], cur, amb, d["cutoff"], t_on, relax, sdt,
                                            np.random.default_rng(seed * 1000 + k))
            stop_t = early * (full_info["t_cut"] - t_on)
        frac = d["partial"].get(k, 1.0)
        if frac < 1.0:
            rows, info = simulate(m, q[k], r[k], cur, amb, d["cutoff"], t_on, relax, sdt, rng, frac)
        else:
            rows, info = simulate_wrap(m, q[k], r[k], cur, amb, d["cutoff"], t_on, relax, sdt, early, stop_t, rng)
        fn = None
        meta_rows = []
        # a charge row before every discharge but the first, occasionally an impedance row
        if k > 0:
            meta_rows.append(("charge", None))
            if rng.random() < 0.25:
                meta_rows.append(("impedance", None))
        meta_rows.append(("discharge", rows))
        rest_days = d["rests"].get(k)
        if k > 0:
            gap_h = rng.uniform(2.3, 3.2) if rest_days is None else rest_days * 24 + rng.uniform(0, 5)
            t_start = prev_end + dt_.timedelta(hours=gap_h)
        for kind, payload in meta_rows:
            uid = len(out["meta"]) + 1 + out["uid0"]
            if kind == "discharge":
                st = t_start
            elif kind == "charge":
                st = t_start - dt_.timedelta(hours=rng.uniform(1.6, 2.2))
            else:
                st = t_start - dt_.timedelta(minutes=rng.uniform(15, 40))
            row = dict(type=kind, start_time=datevec(st), ambient_temperature=amb if kind != "impedance" else 24,
                       battery_id=cell, test_id=test_id, uid=uid, filename=f"{uid:05d}.csv", Capacity="", Re="", Rct="")
            if kind == "impedance":
                row["Re"] = repr(0.055 * (r[k] / r[0]) * rng.uniform(0.98, 1.02))
                row["Rct"] = repr(0.2 * (r[k] / r[0]) * rng.uniform(0.95, 1.05))
            if kind == "discharge":
                fn = row["filename"]
                meas = write_record(os.path.join(out["root"], "data", fn), rows, cur, rng, d["cutoff"])
                q_cut, q27 = charges(meas, d["cutoff"])
                row["Capacity"] = repr(float(q27))
                rest_h = (t_start - prev_end).total_seconds() / 3600 if prev_end else float("nan")
                t_cut = info["t_cut"]
                truth.append(dict(cell=cell, cycle=k + 1, test_id=test_id, filename=fn, qMobile_C=round(q[k], 3),
                                  Ro_ohm=round(r[k], 6), current_a=cur, ambient_c=amb, cutoff_v=d["cutoff"],
                                  recovery_frac=round(rec[k], 5), jump_here=round(jumps.get(k, 0.0), 4),
                                  rest_before_h=round(rest_h, 3), t_on_s=round(t_on, 3),
                                  eod_from_load_s=round(t_cut - t_on, 2) if t_cut is not None else "",
                                  early_stop_frac=round(early, 3) if early is not None else "",
                                  start_frac=frac,
                                  q_to_cutoff_ah=round(q_cut, 5), capacity_2p7_ah=round(q27, 5),
                                  max_self_heat_k=round(info["max_dT"], 2), n_rows=len(rows)))
            out["meta"].append(row)
            test_id += 1
        prev_end = t_start + dt_.timedelta(seconds=rows[-1][0])
    return cell, truth


def simulate_wrap(m, q, ro, cur, amb, cutoff, t_on, relax, sdt, early, stop_t, rng):
    if early is None:
        return simulate(m, q, ro, cur, amb, cutoff, t_on, relax, sdt, rng)
    return simulate_stopped(m, q, ro, cur, amb, cutoff, t_on, relax, sdt, stop_t, rng)


def simulate_stopped(m, q, ro, cur, amb, cutoff, t_on, relax, sdt, stop_t, rng):
    """Discharge stopped under load `stop_t` s after load-on (never reaches the cut-off)."""
    x = set_full(m, q, ro, amb)
    T_amb = amb + 273.15
    dT, t = 0.0, 0.0
    rows = []
    z = m.output(x)
    rows.append((0.0, float(z["v"]), 0.0, float(z["t"]), False))
    u0 = m.InputContainer({"i": 0.0})
    uI = m.InputContainer({"i": float(cur)})
    tlog = t + max(1.0, sdt + rng.normal(0, 0.12))
    t_stop = t_on + stop_t
    max_dT = 0.0
    while True:
        loaded = t >= t_on - 1e-9
        u = uI if loaded else u0
        i_now = cur if loaded else 0.0
        targets = [t + DT, tlog, t_stop]
        if not loaded:
            targets.append(t_on)
        tn = min(targets)
        h = tn - t
        xn = m.next_state(x, u, h)
        P = i_now * float(x["Vo"] + x["Vsn"] + x["Vsp"])
        dT = dT + h * (RTH * P / (1 + P / P_SAT) - dT) / TAU_TH
        xn["tb"] = T_amb + dT
        x, t = xn, tn
        max_dT = max(max_dT, dT)
        if abs(t - tlog) < 1e-9 or abs(t - t_stop) < 1e-9:
            zn = m.output(x)
            rows.append((t, float(zn["v"]), cur if loaded else 0.0, float(zn["t"]), loaded))
            tlog = t + max(1.0, sdt + rng.normal(0, 0.12))
        if abs(t - t_stop) < 1e-9:
            break
    return rows, dict(t_cut=None, max_dT=max_dT)


def main():
    ap = argparse.ArgumentParser()
    here = os.path.dirname(os.path.abspath(__file__))
    ap.add_argument("--out", default=os.path.join("blind", "data-root"))
    ap.add_argument("--truth", default=os.path.join("blind", "truth.csv"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--cells", default="B0038,B0042,B0045,B0033,B0041,B0049")
    ap.add_argument("--extra-infos", default=os.path.join(here, "..", "..", "..", "shared", "data", "nasa-pcoe",
                                                          "extra_infos"),
                    help="NASA's experiment descriptions (bcal reads the cut-offs from them)")
    a = ap.parse_args()
    os.makedirs(os.path.join(a.out, "data"), exist_ok=True)
    cells = a.cells.split(",")
    seeds = {"B0038": 38, "B0042": 42, "B0045": 45, "B0033": 33, "B0041": 41, "B0049": 49}
    uid0 = {"B0038": 10000, "B0042": 20000, "B0045": 30000, "B0033": 40000, "B0041": 50000, "B0049": 60000}
    jobs = [(c, {"root": a.out, "meta": [], "uid0": uid0[c]}, seeds[c]) for c in cells]
    with Pool(a.jobs) as pool:
        res = pool.map(gen_cell_full, jobs)
    meta = [row for _, _, rows in res for row in rows]
    with open(os.path.join(a.out, "metadata.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["type", "start_time", "ambient_temperature", "battery_id", "test_id", "uid",
                                          "filename", "Capacity", "Re", "Rct"])
        w.writeheader()
        w.writerows(meta)
    truth = [t for _, tr, _ in res for t in tr]
    with open(a.truth, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(truth[0].keys()))
        w.writeheader()
        w.writerows(truth)
    # the experiment descriptions, as the real folder has them (bcal reads cut-offs from them)
    ei = os.path.join(a.out, "extra_infos")
    os.makedirs(ei, exist_ok=True)
    src = a.extra_infos
    for fn in ["README_33_34_36.txt", "README_38_39_40.txt", "README_41_42_43_44.txt", "README_45_46_47_48.txt",
               "README_49_50_51_52.txt"]:
        if os.path.exists(os.path.join(src, fn)):
            with open(os.path.join(src, fn)) as fi, open(os.path.join(ei, fn), "w") as fo:
                fo.write(fi.read())
    for c, tr, _ in res:
        print(c, len(tr), "discharges")


def gen_cell_full(job):
    cell, out, seed = job
    c, truth = gen_cell(job)
    return c, truth, out["meta"]


if __name__ == "__main__":
    main()
