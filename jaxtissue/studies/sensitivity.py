"""Local sensitivities: d ln(output)/d ln(parameter) of a run's final outputs for every
parameter and protocol field, one reverse-mode pass per output."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import cache, limits
from ..grid import Grid
from ..params import Params
from ..protocol import COUPLING_INTERVAL_S, PROTOCOL_FIELDS, THREE_WEEKS_S, Protocol
from ..simulate import simulate

SENSITIVITY_OUTPUTS = ("dna_ug_per_g", "collagen_mg_per_g", "EI_N_m2", "post_force_max_N")


def sensitivities(params: Params, protocol: Protocol, t_end_s: float = THREE_WEEKS_S, **simulate_kw) -> dict:
    """{output: {parameter: d ln(output)/d ln(parameter)}} at `t_end_s` (one reverse
    pass per output; the protocol's floats count as parameters). Outputs that are zero
    (the post force in static culture) are left out."""
    grid = simulate_kw.get("grid") or Grid.default(protocol.regime)
    options = simulate_kw.get("options")
    need = limits.estimate(grid.nx * grid.ny, t_end_s, simulate_kw.get("coupling_interval_s", COUPLING_INTERVAL_S), save_series=False,
                           reverse=not (options is not None and options.nest_intervals), batch=len(SENSITIVITY_OUTPUTS),
                           regime=protocol.regime)
    limits.check_memory(need, f"computing the sensitivities of a {grid.nx} x {grid.ny} {protocol.regime} run",
                        "a coarser `grid`" + (" or `nest_intervals`" if protocol.regime == "flex" else ""))
    params = jax.tree_util.tree_map(lambda x: jnp.asarray(x, float), params)
    protocol = jax.tree_util.tree_map(lambda x: jnp.asarray(x, float), protocol)

    program = eqx.filter_jit(_values_and_jacobian)  # jitted here: its compiled program is freed with it
    values, (gp, gq) = cache.call(program, params, protocol, float(t_end_s), simulate_kw)
    out = {}
    for i, key in enumerate(SENSITIVITY_OUTPUTS):
        y = float(values[i])
        if y == 0.0:
            continue
        row = {n: float(getattr(gp, n)[i] * getattr(params, n) / y) for n in params.as_dict()}
        if protocol.regime == "flex":
            row |= {n: float(getattr(gq, n)[i] * getattr(protocol, n) / y) for n in PROTOCOL_FIELDS}
        out[key] = row
    return out


def _values_and_jacobian(params, protocol, t_end_s, simulate_kw):
    """The outputs at `t_end_s` and their Jacobian from one forward pass (`jax.vjp`), the
    reverse passes vmapped over the outputs' unit cotangents (as `jax.jacrev` does, which
    would run the forward pass again for the values). A program the command line saves."""

    def outputs(p, q):  # the end state only: no series to differentiate, and no host callback (a cached program)
        r = simulate(p, q, t_end_s, **{**simulate_kw, "save": "end"})
        return jnp.stack([getattr(r, k)[-1] for k in SENSITIVITY_OUTPUTS])

    values, pullback = jax.vjp(outputs, params, protocol)
    return values, jax.vmap(pullback)(jnp.eye(values.size, dtype=values.dtype))
