"""Calibrate a measured NASA cell with bcal from Python, one reading at a time, and plot the estimates.

    python examples/calibrate_nasa_cell.py [--cell B0005] [--cycle 100] [--kind ukf] [--out estimates.png]

Reads one discharge of a NASA PCoE cell (../shared/data/nasa-pcoe beside this clone, or --data), feeds it
to bcal.Calibrator, and draws qMobile and Ro with their 90 % intervals, and the predicted end of
discharge (3.0 V, the model's) against the time the cell's loaded voltage fell below 3.0 V. Needs pandas and matplotlib (`pip install "./python[examples]"`).
"""

import argparse
import pathlib

import matplotlib

matplotlib.use("Agg")  # files, no window
import matplotlib.pyplot as plt
import pandas as pd

import bcal

HERE = pathlib.Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data" / "nasa-pcoe"


def discharge(data: pathlib.Path, cell: str, cycle: int) -> pd.DataFrame:
    """The cell's `cycle`-th discharge (1-based) in bcal's names and units: current positive while
    discharging (NASA records it negative)."""
    meta = pd.read_csv(data / "metadata.csv")
    rows = meta[(meta.battery_id == cell) & (meta.type == "discharge")].sort_values("test_id")
    record = pd.read_csv(data / "data" / rows.iloc[cycle - 1].filename)
    return pd.DataFrame({
        "time_s": record.Time,
        "voltage_v": record.Voltage_measured,
        "current_a": -record.Current_measured,
        "temperature_c": record.Temperature_measured,
    })


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=pathlib.Path, default=DEFAULT_DATA)
    p.add_argument("--cell", default="B0005")
    p.add_argument("--cycle", type=int, default=100)
    p.add_argument("--kind", default="ukf", help="ukf, adaptive_ukf, ukf_learned, fit or uncalibrated")
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("estimates.png"))
    a = p.parse_args()

    readings = discharge(a.data, a.cell, a.cycle)
    est = bcal.Calibrator(a.kind).run(readings)  # one row per reading
    # The model's end of discharge is 3.0 V: when the cell's loaded voltage first fell below it.
    loaded = readings.current_a > 0.05
    measured_eod_s = readings.time_s[loaded & (readings.voltage_v < 3.0)].iloc[0]
    under_load = est[loaded.to_numpy() & (est.time_s <= measured_eod_s).to_numpy()]

    fig, ax = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for axis, name, unit in [(ax[0], "q_mobile", "C"), (ax[1], "r_o", "ohm")]:
        axis.plot(est.time_s, est[name], label=f"{a.kind} estimate")
        axis.fill_between(est.time_s, est[f"{name}_lo"], est[f"{name}_hi"], alpha=0.3, label="90 % interval")
        axis.set_ylabel(f"{name}, {unit}")
        axis.legend()
    ax[2].plot(under_load.time_s, under_load.eod_s, label="predicted time to 3.0 V")
    ax[2].axhline(measured_eod_s, color="k", linestyle="--", label="measured")
    ax[2].set_ylabel("EOD, s")
    ax[2].set_xlabel("time, s")
    ax[2].legend()
    fig.suptitle(f"{a.cell}, discharge {a.cycle}: bcal.Calibrator({a.kind!r})")
    fig.tight_layout()
    fig.savefig(a.out, dpi=100)
    last = est.iloc[-1]
    print(f"{a.cell} cycle {a.cycle}: {len(est)} readings; q_mobile {last.q_mobile:.0f} C "
          f"[{last.q_mobile_lo:.0f}, {last.q_mobile_hi:.0f}], r_o {last.r_o:.4f} ohm; wrote {a.out}")


if __name__ == "__main__":
    main()
