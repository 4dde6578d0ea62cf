"""Does a cell's knee depend on where its discharge started? progpy's own BatteryElectroChemEOD (no code of
bcal), the cell "B0049" of progpy_cells.py mimics (2 A at 4 C to 2.0 V; qMobile 7000 C, Ro 0.13 ohm), at rest
from 100 / 40 / 25 / 5 % of full: the charge it delivers below 3.0 V and 2.8 V (where bcal's model ends, its
electrode surface empty) and after its negative electrode's surface fraction falls under 1 %, and the bulk's
charge above the surface's at that moment.

    python examples/blind/knee_by_start.py

bcal adds the knee the discharges before measured to every end it predicts, from any start (`docs/realcell.md`,
"what a discharge hands on"); this shows where that holds (from 25 % up) and where not (near empty, the
particles' gradient not yet built: a smaller knee).
"""
import os
import sys
import warnings

import numpy as np

warnings.filterwarnings("ignore")  # progpy's log of a surface fraction at 0 past the end
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from progpy.models import BatteryElectroChemEOD  # noqa: E402

import progpy_cells as pc  # noqa: E402


def main() -> None:
    m = BatteryElectroChemEOD()
    q_mobile_c, r_o_ohm, ambient_c, current_a, cutoff_v, dt_s = 7000.0, 0.13, 4.0, 2.0, 2.0, 0.1
    for frac in [1.0, 0.4, 0.25, 0.05]:
        x = pc.set_full(m, q_mobile_c, r_o_ohm, ambient_c, frac)
        u = m.InputContainer({"i": current_a})
        t_s, drawn_c, rows = 0.0, 0.0, []
        while t_s < 20000.0:
            v = m.output(x)["v"]
            rows.append((t_s, v, x["qnS"] / m.parameters["qSMax"], drawn_c, x["qnB"] / m.parameters["qBMax"]))
            if not np.isfinite(v) or v < cutoff_v:
                break
            x = m.next_state(x, u, dt_s)
            t_s += dt_s
            drawn_c += current_a * dt_s
        rows = np.array(rows)
        end_c = rows[-1, 3]

        def after(mask):
            return end_c - rows[np.argmax(mask), 3] if mask.any() else float("nan")

        # The bulk's charge above the surface's when the surface fraction falls under 1 %: what the particles'
        # gradient strands there (a candidate measure of the knee from the model's own state).
        k = int(np.argmax(rows[:, 2] < 0.01))
        stranded_c = (rows[k, 4] - rows[k, 2]) * m.parameters["qBMax"]
        print(f"start {frac:4.2f}: {rows[-1, 0]:7.1f} s to {cutoff_v} V; charge below 3.0 V "
              f"{after(rows[:, 1] < 3.0):6.1f} C, below 2.8 V {after(rows[:, 1] < 2.8):6.1f} C, "
              f"after a surface fraction under 1 % {after(rows[:, 2] < 0.01):6.1f} C; "
              f"bulk charge stranded there {stranded_c:6.1f} C")


if __name__ == "__main__":
    main()
