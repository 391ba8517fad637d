"""Model parameters in physical units (docs/model.md §7), their SI view (`SIParams`,
for the mechanics and the observables) and the growth solver's non-dimensional view
(`Coefficients`).

Every number a user may want to change lives in [`Params`][] as an ordinary float field,
so that `jax.grad` reaches all of them. `FIELDS` documents each one (unit, allowed range,
source); it drives validation, the `jaxtissue params` table and the TOML files. Units
are converted here and nowhere else.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class FieldInfo(NamedTuple):
    unit: str
    low: float  # allowed range, see `closed_low` / `closed_high`
    high: float
    closed_low: bool
    closed_high: bool
    doc: str

    def contains(self, value: float) -> bool:
        above = value >= self.low if self.closed_low else value > self.low
        below = value <= self.high if self.closed_high else value < self.high
        return bool(above and below)

    def range_text(self) -> str:
        lo = "[" if self.closed_low else "("
        hi = "]" if self.closed_high else ")"
        return f"{lo}{self.low:g}, {self.high:g}{hi}"

    @property
    def unit_text(self) -> str:
        """" (unit)" for messages, "" for a dimensionless field (unit "1")."""
        return "" if self.unit == "1" else f" ({self.unit})"


inf = math.inf
CM_PER_M = 100.0


def _pos(unit: str, doc: str) -> FieldInfo:
    return FieldInfo(unit, 0.0, inf, False, False, doc)


def _nonneg(unit: str, doc: str) -> FieldInfo:
    return FieldInfo(unit, 0.0, inf, True, False, doc)


def _unit_interval(doc: str) -> FieldInfo:
    return FieldInfo("1", 0.0, 1.0, False, False, doc)


FIELDS: dict[str, FieldInfo] = {
    # geometry (§1)
    "length_mm": _pos("mm", "strip length L between the posts (§1)"),
    "thickness_mm": _pos("mm", "strip thickness h (§1)"),
    "depth_mm": _pos("mm", "strip depth d, the plane-strain direction (§1)"),
    # oxygen (§2, eq. 2.1, A.4, 2.2)
    "o_ext": FieldInfo("1", 0.0, 1.0, False, True, "O2 at the faces, o = rho_o/(5 rho_o,ext); 0.2 = 20 % O2 (§2)"),
    "D_o0": _pos("cm^2/s", "O2 diffusivity in the scaffold, D_o(m=0) (A.4)"),
    "kappa": _pos("1", "Chang unit-cell conductivity ratio kappa (A.4)"),
    "psi": _pos("1", "Chang unit-cell shape factor psi (A.4)"),
    "Q_o": _nonneg("1/s", "maximal O2 consumption rate per cell, non-dimensional form (2.2)"),
    "o_h": _pos("1", "Michaelis-Menten half-saturation O2 (2.2)"),
    # cells (eq. 2.3, A.6)
    "k_c_max": _nonneg("1/s", "maximal net proliferation rate; k_p is derived from it (A.6)"),
    "k_a": _nonneg("1/s", "apoptosis rate (A.6)"),
    "n_moser": _pos("1", "Moser exponent n (A.6)"),
    "o_c": _unit_interval("Moser half-saturation O2 o_c (A.6)"),
    "k_i": _nonneg("1", "Aiba O2-inhibition constant k_i (A.6)"),
    "c_max": FieldInfo("1", 1.0, inf, False, False, "maximal cell density / seeding density (2.3)"),
    "D_c": _nonneg("cm^2/s", "cell random-motility coefficient (2.3)"),
    "chi": _nonneg("cm^2/s", "chemotactic coefficient (2.3)"),
    # ECM (eq. 2.5, 2.6)
    "k_m0": _nonneg("1/s", "ECM synthesis rate per unit O2 above threshold (2.6)"),
    "o_m": _unit_interval("O2 threshold for ECM synthesis (2.6)"),
    # mechanics (§3, §4)
    "E_s_kPa": _pos("kPa", "scaffold Young's modulus E_s (A.25)"),
    "E_m0_kPa_per_ug_g": _nonneg("kPa/(ug/g)", "ECM stiffness per ECM concentration, E_m0 bar (A.25)"),
    "nu_s": FieldInfo("1", 0.0, 0.5, True, False, "Poisson ratio of the scaffold (2.13)"),
    "nu_t": FieldInfo("1", 0.0, 0.5, True, False, "Poisson ratio of the tissue (2.13)"),
    "phi_s": _unit_interval("porosity of the scaffold (2.7)"),
    "phi_t": _unit_interval("porosity of the tissue (2.7)"),
    "k_hyd_s_cm_s": _pos("cm/s", "hydraulic conductivity of the scaffold (2.8)"),
    "k_hyd_t_cm_s": _pos("cm/s", "hydraulic conductivity of the tissue (2.8)"),
    "p_ext_kPa": _nonneg("kPa", "external pore pressure, a reference level (§4)"),
    # coupling (§5)
    "lumping_C": _nonneg("1", "lumping constant C of the coupling (2.15); default set for the dispersive rule so that flex/static 3-week collagen = 1.55 (calibrate/lumping_C.py); the paper's 70 belongs to its literal rule"),
    # scales and assay conversions (§2, §3)
    "rho_o_ext_mol_cm3": _pos("mol/cm^3", "O2 concentration of medium at 20 % O2 (§2 scale)"),
    "rho_c_seed_cells_cm3": _pos("cells/cm^3", "seeding cell density, c = 1 (§2 scale)"),
    "rho_m_max_mg_g": _pos("mg/g ww", "maximal ECM concentration, m = 1 (§2 scale; collagen assay, §3)"),
    "dna_ug_g_per_c": _pos("ug/g ww", "DNA assay of c = 1 (536 ug/g at 7.6 pg DNA/cell, §3)"),
}


class Params(eqx.Module):
    """All model parameters in physical units, with the paper's defaults (docs/model.md §7).

    Every field is a float (or a float array under `vmap`) and differentiable. See
    `jaxtissue.params.FIELDS` (or `jaxtissue params`) for each one's unit, range and
    source. Invalid concrete values raise `ValueError` naming the field, the value and
    the allowed range.
    """

    length_mm: float = 25.0
    thickness_mm: float = 1.0
    depth_mm: float = 5.0
    o_ext: float = 0.2
    D_o0: float = 1.5e-5
    kappa: float = 0.43
    psi: float = 23.07
    Q_o: float = 8.393e-4
    o_h: float = 0.05
    k_c_max: float = 1.24e-5
    k_a: float = 1.0e-5
    n_moser: float = 5.0
    o_c: float = 0.45
    k_i: float = 14.0
    c_max: float = 1.308
    D_c: float = 0.0
    chi: float = 0.0
    k_m0: float = 1.675e-7
    o_m: float = 0.16
    E_s_kPa: float = 174.0
    E_m0_kPa_per_ug_g: float = 0.8881
    nu_s: float = 0.1
    nu_t: float = 0.45
    phi_s: float = 0.96
    phi_t: float = 0.61
    k_hyd_s_cm_s: float = 3.66e-6
    k_hyd_t_cm_s: float = 3.66e-7
    p_ext_kPa: float = 101.325
    lumping_C: float = 0.3371
    rho_o_ext_mol_cm3: float = 2.10e-7
    rho_c_seed_cells_cm3: float = 70.5e6
    rho_m_max_mg_g: float = 108.3
    dna_ug_g_per_c: float = 536.0

    def __check_init__(self):
        for name, info in FIELDS.items():
            value = getattr(self, name)
            try:
                concrete = concrete_value(value)
            except TypeError:
                raise TypeError(f"parameter {name} = {value!r} must be a number{info.unit_text}") from None
            if concrete is None:
                continue  # traced: checked where it is born, not inside jit
            bad = [v for v in np.ravel(concrete) if not (np.isfinite(v) and info.contains(float(v)))]
            if bad:
                raise ValueError(
                    f"parameter {name} = {bad[0]:g} is outside its allowed range "
                    f"{info.range_text()}{info.unit_text}: {info.doc}"
                )

    def replace(self, **changes) -> "Params":
        """A copy with some fields changed (validated); unknown names raise `ValueError`."""
        unknown = [k for k in changes if k not in FIELDS]
        if unknown:
            raise ValueError(f"unknown parameter {unknown[0]!r}; {suggest(unknown[0], FIELDS)}")
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, float]:
        """Field name -> Python float (concrete parameters only)."""
        return {name: float(getattr(self, name)) for name in FIELDS}

    def si(self) -> "SIParams":
        """The dimensional fields in SI units (`SIParams`)."""
        return SIParams(
            length_m=self.length_mm * 1e-3,
            thickness_m=self.thickness_mm * 1e-3,
            depth_m=self.depth_mm * 1e-3,
            E_s_Pa=self.E_s_kPa * 1e3,
            E_m0_Pa_per_ug_g=self.E_m0_kPa_per_ug_g * 1e3,
            rho_m_max_ug_g=self.rho_m_max_mg_g * 1e3,
            nu_s=self.nu_s,
            nu_t=self.nu_t,
            phi_s=self.phi_s,
            phi_t=self.phi_t,
            k_hyd_s_m_s=self.k_hyd_s_cm_s * 1e-2,
            k_hyd_t_m_s=self.k_hyd_t_cm_s * 1e-2,
            p_ext_Pa=self.p_ext_kPa * 1e3,
        )


class SIParams(eqx.Module):
    """The parameters of the mechanics (docs/model.md §4) and of the flexural rigidity
    (§3) in SI units: m, Pa, m/s (`Params.si()`); ECM concentrations in µg/g ww, as
    the stiffening Ē_m0 is per µg/g."""

    length_m: jax.Array
    thickness_m: jax.Array
    depth_m: jax.Array
    E_s_Pa: jax.Array
    E_m0_Pa_per_ug_g: jax.Array
    rho_m_max_ug_g: jax.Array
    nu_s: jax.Array
    nu_t: jax.Array
    phi_s: jax.Array
    phi_t: jax.Array
    k_hyd_s_m_s: jax.Array
    k_hyd_t_m_s: jax.Array
    p_ext_Pa: jax.Array


def concrete_value(value):
    """`value` as a NumPy array, or None if it is traced (then checks wait for later); a
    `TypeError` if it is not a number or an array of numbers (None, a string, a bool, a
    list: an array is one leaf of the pytree, a list one leaf per item)."""
    if isinstance(value, jax.core.Tracer):
        return None
    if value is None or isinstance(value, (str, bytes, bool, np.bool_, list, tuple, dict)):  # a list: a pytree of many leaves
        raise TypeError(f"{value!r} is not a number")
    try:
        concrete = np.asarray(value)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        return None
    if not (np.issubdtype(concrete.dtype, np.integer) or np.issubdtype(concrete.dtype, np.floating)):
        raise TypeError(f"{value!r} is not a number")
    return concrete.astype(float)


def suggest(name: str, choices) -> str:
    """'did you mean …' text for an unknown name."""
    import difflib

    choices = list(choices)
    close = difflib.get_close_matches(name, choices, n=1, cutoff=0.5)
    if close:
        return f"did you mean {close[0]!r}?"
    return f"allowed: {', '.join(choices)}" if len(choices) <= 8 else "see `jaxtissue params` for the valid names"


def paper_parameters(**changes) -> Params:
    """The paper's parameter set (docs/model.md §7), optionally with some fields changed."""
    return Params().replace(**changes) if changes else Params()


# --------------------------------------------------------------------------------------
# The non-dimensional view used by the solver.
# --------------------------------------------------------------------------------------


def moser_aiba(o, n, o_c, k_i):
    """The O2 dependence of proliferation, `oⁿ/(o_cⁿ + oⁿ) exp(−k_i o)` (A.6), for o ≥ 0."""
    o = jnp.maximum(o, 1e-30)
    # (o_c/o)ⁿ as exp(n (ln o_c − ln o)), the log in a kernel of its own: XLA:CPU
    # vectorises a lone log but not one fused with other operations (`power` is slower
    # still); this function is a large part of the growth right-hand side's cost.
    log_o = jax.lax.optimization_barrier(jnp.log(o))
    ratio = jnp.exp(n * (jnp.log(o_c) - log_o))
    return jnp.exp(-k_i * o) / (1.0 + ratio)


def moser_aiba_argmax(n, o_c, k_i):
    """The O2 level at which `moser_aiba` peaks (bisection on its log-derivative).

    `d/do log g = n o_cⁿ / (o (o_cⁿ + oⁿ)) − k_i`, decreasing in o, so bisection is
    safe. The result is wrapped in `stop_gradient`: by the envelope theorem the gradient
    of `max g` needs only ∂g/∂θ at the maximiser.
    """
    n, o_c, k_i = (jax.lax.stop_gradient(jnp.asarray(v, float)) for v in (n, o_c, k_i))

    def dlog(o):
        return n / (o * (1.0 + jnp.power(o / o_c, n))) - k_i

    def body(_, bracket):
        lo, hi = bracket
        mid = jnp.sqrt(lo * hi)
        up = dlog(mid) > 0
        return jnp.where(up, mid, lo), jnp.where(up, hi, mid)

    lo, hi = jax.lax.fori_loop(0, 200, body, (jnp.full_like(o_c, 1e-8), jnp.full_like(o_c, 1e3)))
    # with k_i = 0 the function increases monotonically: its sup is 1 at o → ∞
    return jnp.sqrt(lo * hi)


class Coefficients(eqx.Module):
    """The solver's view of `Params`: lengths in cm, concentrations non-dimensional
    (o = ρ_o/(5ρ_o,ext), c = ρ_c/ρ_c,seed, m = ρ_m/ρ_m,max; docs/model.md §2), time in s.

    `k_p` is derived from `k_c_max` (docs/model.md §2): k_p = (k_c,max + k_a) / max_o g(o)
    with g the Moser–Aiba factor of A.6.
    """

    length_cm: jax.Array
    thickness_cm: jax.Array
    depth_cm: jax.Array
    o_ext: jax.Array
    D_o0: jax.Array
    kappa: jax.Array
    psi: jax.Array
    Q_o: jax.Array
    o_h: jax.Array
    k_p: jax.Array
    k_a: jax.Array
    n_moser: jax.Array
    o_c: jax.Array
    k_i: jax.Array
    c_max: jax.Array
    D_c: jax.Array
    chi: jax.Array
    k_m0: jax.Array
    o_m: jax.Array


def proliferation_prefactor(p: Params):
    """k_p derived from k_c,max (docs/model.md §2)."""
    o_star = moser_aiba_argmax(p.n_moser, p.o_c, p.k_i)
    g_max = jnp.where(jnp.asarray(p.k_i) > 0, moser_aiba(o_star, p.n_moser, p.o_c, p.k_i), 1.0)
    return (p.k_c_max + p.k_a) / g_max


def nondimensionalise(p: Params) -> Coefficients:
    """The solver's coefficients (see `Coefficients`)."""
    f = lambda v: jnp.asarray(v, dtype=float)  # noqa: E731
    return Coefficients(
        length_cm=f(p.length_mm) / 10.0,
        thickness_cm=f(p.thickness_mm) / 10.0,
        depth_cm=f(p.depth_mm) / 10.0,
        o_ext=f(p.o_ext),
        D_o0=f(p.D_o0),
        kappa=f(p.kappa),
        psi=f(p.psi),
        Q_o=f(p.Q_o),
        o_h=f(p.o_h),
        k_p=f(proliferation_prefactor(p)),
        k_a=f(p.k_a),
        n_moser=f(p.n_moser),
        o_c=f(p.o_c),
        k_i=f(p.k_i),
        c_max=f(p.c_max),
        D_c=f(p.D_c),
        chi=f(p.chi),
        k_m0=f(p.k_m0),
        o_m=f(p.o_m),
    )
