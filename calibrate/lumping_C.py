"""Set the default lumping constant C of the dispersive rule (docs/model.md §5).

Until the full calibration, C is chosen so that the model's 3-week flex/static
collagen ratio matches Engelmayr's 0.846/0.546 = 1.55 on the default grids; the secant
iterations run on log C. Prints each iterate and the value to put in `Params`.

    python calibrate/lumping_C.py
"""

from __future__ import annotations

import math

import jaxtissue as jt

TARGET = 0.846 / 0.546


def collagen_ratio(C: float) -> float:
    p = jt.paper_parameters(lumping_C=C)
    flex = jt.simulate(p, jt.Protocol.flex(), t_end_s=jt.THREE_WEEKS_S)
    static = jt.simulate(p, jt.Protocol.static(), t_end_s=jt.THREE_WEEKS_S)
    return float(flex.collagen_mg_per_g[-1] / static.collagen_mg_per_g[-1])


def main(c0=0.03, c1=0.3, tol=1e-4, max_iter=8):
    x0, x1 = math.log(c0), math.log(c1)
    f0, f1 = collagen_ratio(c0) - TARGET, collagen_ratio(c1) - TARGET
    print(f"C = {c0:.6g}: ratio {f0 + TARGET:.5f}\nC = {c1:.6g}: ratio {f1 + TARGET:.5f}")
    for _ in range(max_iter):
        x0, x1, f0 = x1, x1 - f1 * (x1 - x0) / (f1 - f0), f1
        f1 = collagen_ratio(math.exp(x1)) - TARGET
        print(f"C = {math.exp(x1):.6g}: ratio {f1 + TARGET:.5f}")
        if abs(f1) < tol:
            break
    print(f"lumping_C = {math.exp(x1):.4g}  (flex/static collagen ratio {f1 + TARGET:.4f}, target {TARGET:.4f})")


if __name__ == "__main__":
    main()
