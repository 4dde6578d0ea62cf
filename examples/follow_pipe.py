"""Follow a simulated discharge through a pipe: readings go one at a time into `bcal calibrate --follow -`
(as a cycler or a BMS gateway would send them), and each estimate is read back as soon as it is out.

    python examples/follow_pipe.py [--bcal PATH] [--every-s 20] [--kind ukf]

The cell is bcal's own model at qMobile 6000 C and Ro 0.14 ohm (unknown to the calibrator, which starts
from its prior), discharged at 2 A after a 60 s rest, read every `--every-s` seconds with 3 mV of noise.
"""

import argparse
import json
import os
import pathlib
import shutil
import subprocess

import numpy as np

import bcal

REPO = pathlib.Path(__file__).resolve().parent.parent


def find_bcal() -> str:
    for c in (os.environ.get("BCAL_BIN"), REPO / "target" / "release" / "bcal", REPO / "target" / "debug" / "bcal",
              shutil.which("bcal")):
        if c and pathlib.Path(c).is_file():
            return str(c)
    raise SystemExit("the bcal CLI is not built: cargo build --release -p bcal, or pass --bcal PATH")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bcal", default=None, help="the bcal executable (default: this clone's build)")
    p.add_argument("--every-s", type=int, default=20)
    p.add_argument("--kind", default="ukf")
    a = p.parse_args()

    sim = bcal.simulate(current_a=2.0, q_mobile=6000.0, ro=0.14)
    rng = np.random.default_rng(1)
    rest = [(float(t), sim["voltage_v"][0], 0.0) for t in range(0, 60, a.every_s)]
    loaded = [(60.0 + t, v, i) for t, v, i in zip(sim["time_s"], sim["voltage_v"], sim["current_a"])
              if t % a.every_s == 0 and i > 0]

    follow = subprocess.Popen([a.bcal or find_bcal(), "calibrate", "--follow", "-", "--calibrator", a.kind],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)
    follow.stdin.write("time_s,voltage_v,current_a\n")
    print(f"{'time_s':>7} {'voltage_v':>9} {'q_mobile':>9} {'r_o':>7} {'eod_s':>6}")
    for k, (t, v, i) in enumerate(rest + loaded):
        follow.stdin.write(f"{t},{v + rng.normal(0, 0.003):.5f},{i}\n")
        follow.stdin.flush()
        e = json.loads(follow.stdout.readline())  # this reading's estimate, before the next is sent
        if k % 10 == 0:
            eod = "-" if e["eod_s"] is None else f"{e['eod_s']:.0f}"
            print(f"{e['time_s']:7.0f} {v:9.3f} {e['q_mobile']:9.0f} {e['r_o']:7.4f} {eod:>6}")
    follow.stdin.close()
    follow.wait()
    print(f"truth: q_mobile 6000 C, r_o 0.14 ohm, EOD {60 + sim['eod_s']:.0f} s; last estimate "
          f"q_mobile {e['q_mobile']:.0f} C, r_o {e['r_o']:.4f} ohm")


if __name__ == "__main__":
    main()
