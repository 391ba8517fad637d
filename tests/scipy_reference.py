"""An independent SciPy method-of-lines solution of the static growth problem (docs/model.md §2).

Written from docs/model.md alone with NumPy (it shares no code with jaxtissue): the 1-D
transmural problem on `ny` cell-centred finite volumes, o = o_ext half a cell outside
the first and last cells, harmonic-mean face diffusivities, integrated by
`scipy.integrate.solve_ivp(method="BDF")` with the Jacobian's sparsity pattern
(interleaved o, c, m: a banded matrix). It is the reference the tests compare with and
the baseline `benchmarks/static.py` times.

    python tests/scipy_reference.py  # prints the 3-week values at ny = 400
"""

from __future__ import annotations

import numpy as np
import scipy.integrate
import scipy.sparse

PAPER = dict(
    thickness_mm=1.0, depth_mm=5.0, o_ext=0.2, D_o0=1.5e-5, kappa=0.43, psi=23.07,
    Q_o=8.393e-4, o_h=0.05, k_c_max=1.24e-5, k_a=1.0e-5, n_moser=5.0, o_c=0.45, k_i=14.0,
    c_max=1.308, k_m0=1.675e-7, o_m=0.16, E_s_kPa=174.0, E_m0_kPa_per_ug_g=0.8881,
    rho_m_max_mg_g=108.3, dna_ug_g_per_c=536.0,
)
THREE_WEEKS_S = 21 * 86400.0


def moser_aiba(o, p):
    o = np.maximum(o, 1e-30)
    return o ** p["n_moser"] / (p["o_c"] ** p["n_moser"] + o ** p["n_moser"]) * np.exp(-p["k_i"] * o)


def derived_k_p(p):
    """k_p = (k_c,max + k_a)/max g, the maximum found on a fine grid refined twice."""
    lo, hi = 1e-4, 5.0
    for _ in range(3):
        o = np.linspace(lo, hi, 20001)
        i = int(np.argmax(moser_aiba(o, p)))
        lo, hi = o[max(i - 1, 0)], o[min(i + 1, o.size - 1)]
    return (p["k_c_max"] + p["k_a"]) / moser_aiba(0.5 * (lo + hi), p)


class StaticProblem:
    """Right-hand side and sparsity of the 1-D static problem on `ny` cells."""

    def __init__(self, ny: int, **changes):
        self.p = dict(PAPER, **changes)
        self.ny = ny
        self.h = self.p["thickness_mm"] / 10.0  # cm
        self.dy = self.h / ny
        self.k_p = derived_k_p(self.p)

    def diffusivity(self, m):
        p, k, psi = self.p, self.p["kappa"], self.p["psi"]
        num = 9 * k * m - 6 * m * (1 - m) * (k - 1) + 2 * (1 - m) * k * psi
        den = 9 * m + 3 * m * (1 - m) * (k - 1) + (2 + m) * k * psi
        return p["D_o0"] * num / den

    def rhs(self, t, u):
        p, dy = self.p, self.dy
        o, c, m = u[0::3], u[1::3], u[2::3]
        D = self.diffusivity(m)
        Df = 2 * D[1:] * D[:-1] / (D[1:] + D[:-1])
        flux = np.empty(self.ny + 1)  # D do/dy on faces
        flux[1:-1] = Df * (o[1:] - o[:-1]) / dy
        flux[0] = D[0] * (o[0] - p["o_ext"]) / (dy / 2)
        flux[-1] = D[-1] * (p["o_ext"] - o[-1]) / (dy / 2)
        op = np.maximum(o, 0.0)
        do = (flux[1:] - flux[:-1]) / dy - p["Q_o"] * c * op / (p["o_h"] + op)
        kc = self.k_p * moser_aiba(o, p) - p["k_a"]
        dc = kc * c * (p["c_max"] - c)
        dm = p["k_m0"] * np.maximum(o - p["o_m"], 0.0) * c * (1 - m)
        out = np.empty_like(u)
        out[0::3], out[1::3], out[2::3] = do, dc, dm
        return out

    def sparsity(self):
        n = 3 * self.ny
        return scipy.sparse.diags([1.0] * 11, list(range(-5, 6)), shape=(n, n), format="csc")

    def initial(self):
        u = np.empty(3 * self.ny)
        u[0::3], u[1::3], u[2::3] = self.p["o_ext"], 1.0, 0.0
        return u

    def solve(self, t_eval, rtol=1e-8, atol=1e-11):
        return scipy.integrate.solve_ivp(
            self.rhs, (0.0, float(t_eval[-1])), self.initial(), method="BDF",
            t_eval=t_eval, rtol=rtol, atol=atol, jac_sparsity=self.sparsity(),
        )

    def observables(self, u):
        """DNA (µg/g), collagen (mg/g), E_eff (kPa) of a state (§3), or of each column
        of u (states × times)."""
        p = self.p
        o, c, m = u[0::3], u[1::3], u[2::3]
        h_m = self.h / 100.0
        yf = np.linspace(-h_m / 2, h_m / 2, self.ny + 1)
        y2 = (yf[1:] ** 3 - yf[:-1] ** 3) / 3
        d_m = p["depth_mm"] * 1e-3
        EI = p["E_s_kPa"] * 1e3 * h_m**3 * d_m / 12 + p["E_m0_kPa_per_ug_g"] * 1e3 * d_m * np.tensordot(
            y2, p["rho_m_max_mg_g"] * 1e3 * m, axes=1
        )
        return dict(
            dna_ug_per_g=p["dna_ug_g_per_c"] * c.mean(axis=0),
            collagen_mg_per_g=p["rho_m_max_mg_g"] * m.mean(axis=0),
            E_eff_kPa=12 * EI / (h_m**3 * d_m) / 1e3,
        )


def values_at(t_eval, ny=400, rtol=1e-8, atol=1e-11, **changes):
    """DNA, collagen and E_eff at each of the times `t_eval` (s; the first is 0)."""
    prob = StaticProblem(ny, **changes)
    sol = prob.solve(np.asarray(t_eval, float), rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(sol.message)
    return prob.observables(sol.y)


def three_week_values(ny=400, rtol=1e-8, atol=1e-11, **changes):
    return {k: v[-1] for k, v in values_at([0.0, THREE_WEEKS_S], ny, rtol, atol, **changes).items()}


if __name__ == "__main__":
    print(three_week_values())
