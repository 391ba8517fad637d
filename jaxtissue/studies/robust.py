"""Protocol design under uncertainty: objectives and limits over posterior draws.

An optimisation problem's `[uncertainty]` table names a posterior (a `jaxtissue
calibrate --posterior` folder). The protocol is then judged over a batch of posterior
draws (the free parameters' values replacing those of `parameters`), simulated at once
under `vmap` and differentiated as before:

* `risk = "mean"`: the objective's mean over the draws; `risk = "quantile"`: its
  `quantile` in the unfavourable tail (for a maximised objective the `quantile`-quantile,
  e.g. 0.05: the collagen that 95 % of plausible tissues reach; for a minimised one the
  (1 − `quantile`)-quantile);
* `constraint_probability = p`: chance constraints, all limits together. Each draw's
  worst limit is its largest relative violation; the draws are ranked by it, and the
  limits are judged on the values of the k-th best draw, k = ⌈p·(n + 1)⌉ of n. Where
  that draw meets every limit, so do at least k draws, and a fresh draw, exchangeable
  with them, meets every limit with probability at least k/(n + 1) ≥ p. That needs
  n ≥ p/(1 − p) draws (19 for p = 0.95); fewer are refused.

The optimum's objective and constraint probability are then checked on a fresh set
of draws, beside those of the point-estimate optimum (the same problem without
`[uncertainty]`).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import jax.numpy as jnp
import numpy as np

from ..io import InputError
from ..params import FIELDS, suggest

RISKS = ("mean", "quantile")
_KEYS = {"posterior", "risk", "quantile", "constraint_probability", "draws", "check_draws", "seed"}


@dataclasses.dataclass(frozen=True, eq=False)
class Uncertainty:
    """The `[uncertainty]` table with the posterior draws it names."""

    posterior: str
    names: tuple[str, ...]
    values: np.ndarray  # (all draws, free parameters), natural units
    risk: str = "mean"
    quantile: float = 0.05
    constraint_probability: float | None = None
    draws: int = 20  # posterior draws the optimisation averages over
    check_draws: int = 64  # fresh draws of the check
    seed: int = 0

    def split(self) -> tuple[np.ndarray, np.ndarray]:
        """(draws for the optimisation, fresh draws for the check), disjoint."""
        order = np.random.default_rng(self.seed).permutation(len(self.values))
        used = order[: self.draws]
        fresh = order[self.draws : self.draws + self.check_draws]
        return self.values[used], self.values[fresh]

    def objective(self, J, sense: int):
        """The risk measure of per-draw objectives J (last axis: draws)."""
        if self.risk == "mean":
            return jnp.mean(J, axis=-1)
        q = self.quantile if sense > 0 else 1.0 - self.quantile
        return jnp.quantile(J, q, axis=-1)

    def limit_values(self, values, violation):
        """Per-draw constraint values (draws, constraints) -> the values the limits are
        judged on: their means, or with chance constraints those of the draw ranked k-th
        by its largest relative violation (module docstring), `violation(values)` the
        per-draw violations (≤ 0 where a limit is met)."""
        if self.constraint_probability is None:
            return jnp.mean(values, axis=0)
        if values.shape[1] == 0:
            return jnp.zeros(0)
        k = chance_rank(self.constraint_probability, values.shape[0])
        worst = jnp.max(violation(values), axis=1)
        return values[jnp.argsort(worst)[k - 1]]


def chance_rank(p: float, n: int) -> int:
    """k = ⌈p·(n + 1)⌉: the draws of n that must meet the limits for a fresh draw to meet
    them with probability ≥ p (at most n, reached from n ≥ p/(1 − p))."""
    return min(n, math.ceil(p * (n + 1) - 1e-9))


def fewest_draws(p: float) -> int:
    """The fewest draws for which `chance_rank` ≤ n: ⌈p/(1 − p)⌉."""
    return math.ceil(p / (1.0 - p) - 1e-9)


def read_uncertainty(spec, where: str, base: pathlib.Path) -> Uncertainty:
    """An `Uncertainty` from the `[uncertainty]` table of the file `where`
    (`posterior` relative to the file's folder `base`)."""
    from .posterior import read_saved

    if not isinstance(spec, dict):
        raise InputError(f"{where}: [uncertainty] must be a table")
    for k in spec:
        if k not in _KEYS:
            raise InputError(f"{where}: unknown key {k!r} in [uncertainty]; {suggest(k, sorted(_KEYS))}")
    if not isinstance(spec.get("posterior"), str):
        raise InputError(f"{where}: [uncertainty] posterior = \"DIR\" (a `jaxtissue calibrate --posterior` folder) is required")
    folder = base / spec["posterior"]
    try:
        saved = read_saved(folder)
    except InputError as err:
        raise InputError(f"{where}: [uncertainty] {str(err).replace('`posterior` ', 'posterior = ')}") from None
    unknown = [n for n in saved.names if n not in FIELDS]
    if unknown:
        raise InputError(f"{where}: [uncertainty] posterior = {spec['posterior']!r} is from another model (unknown parameters: {', '.join(unknown)})")
    risk = spec.get("risk", "mean")
    if risk not in RISKS:
        raise InputError(f"{where}: [uncertainty] risk = {risk!r}; allowed: 'mean', 'quantile'")
    quantile = _fraction(spec.get("quantile", 0.05), where, "quantile")
    probability = spec.get("constraint_probability")
    probability = None if probability is None else _fraction(probability, where, "constraint_probability")
    counts = {}
    fewest = 1 if probability is None else fewest_draws(probability)
    for k, default in (("draws", max(20, fewest)), ("check_draws", 64), ("seed", 0)):
        v = spec.get(k, default)
        if isinstance(v, bool) or not isinstance(v, int) or v < (0 if k == "seed" else 1):
            raise InputError(f"{where}: [uncertainty] {k} = {v!r} must be {'an integer >= 0' if k == 'seed' else 'a positive integer'}")
        counts[k] = v
    if counts["draws"] < fewest:
        raise InputError(f"{where}: [uncertainty] draws = {counts['draws']} is too few for constraint_probability = "
                         f"{probability:g}: a fresh draw keeps the limits with that probability only from draws >= "
                         f"{fewest}")
    values = saved.values.reshape(-1, len(saved.names))
    if counts["draws"] + counts["check_draws"] > len(values):
        raise InputError(f"{where}: [uncertainty] draws + check_draws = {counts['draws'] + counts['check_draws']} exceeds the "
                         f"posterior's {len(values)} draws")
    return Uncertainty(str(folder), saved.names, values, risk, quantile, probability, **counts)


def _fraction(value, where, key) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and 0 < value < 1):
        raise InputError(f"{where}: [uncertainty] {key} = {value!r} must be a number in (0, 1)")
    return float(value)


def check(design, theta, fresh: np.ndarray, evaluate_draws) -> dict:
    """The protocol θ on fresh draws: its risk-measured objective and the fraction of
    draws for which every limit holds. `evaluate_draws(θ, draws)` -> (J, values,
    failed) per draw."""
    from .objectives import OBJECTIVES

    J, values, failed = (np.asarray(a) for a in evaluate_draws(theta, fresh))
    ok = ~failed
    held = np.all(np.asarray(design.violation(jnp.asarray(values))).reshape(len(J), -1) <= 0, axis=1)  # as the optimiser judges a draw
    u = design.uncertainty
    return {
        "objective": float(u.objective(jnp.asarray(J[ok]), OBJECTIVES[design.objective].sense)),
        "objective_mean": float(np.mean(J[ok])),
        "constraint_probability": float(np.mean(held & ok)),
        "draws": int(len(J)),
        "failed": int(failed.sum()),
    }
