"""Priors of the free parameters of a calibration problem (docs/model.md §9).

A free parameter θ lives in its bounds [low, high]; its prior is a density in θ there
(truncated to the bounds):

* ``"uniform"`` — flat in θ (the default of a linear transform);
* ``"log-uniform"`` — flat in ln θ, density ∝ 1/θ (the default of a log transform);
* ``{ normal = [mean, sd] }`` — Gaussian in θ, in the parameter's units;
* ``{ log-normal = [median, sd_ln] }`` — Gaussian in ln θ with that median and the
  standard deviation `sd_ln` of ln θ.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..io import InputError

KINDS = ("uniform", "log-uniform", "normal", "log-normal")


class Prior(NamedTuple):
    kind: str  # one of KINDS
    location: float = math.nan  # normal: mean; log-normal: median (parameter's units)
    scale: float = math.nan  # normal: SD (parameter's units); log-normal: SD of ln θ

    def log_density(self, value):
        """ln p(θ) up to a constant, at θ inside the bounds."""
        if self.kind == "uniform":
            return jnp.zeros_like(value)
        if self.kind == "log-uniform":
            return -jnp.log(value)
        if self.kind == "normal":
            return -0.5 * ((value - self.location) / self.scale) ** 2
        z = (jnp.log(value) - math.log(self.location)) / self.scale
        return -jnp.log(value) - 0.5 * z**2

    def describe(self) -> str:
        if self.kind in ("uniform", "log-uniform"):
            return f"{self.kind} in the bounds"
        which = "mean" if self.kind == "normal" else "median"
        spread = "SD" if self.kind == "normal" else "SD of ln"
        return f"{self.kind} ({which} {self.location:.4g}, {spread} {self.scale:.3g}) in the bounds"

    def sd_in(self, transform: str, low: float, high: float, points: int = 4001) -> float:
        """The prior's standard deviation in the fit coordinate t (ln θ or θ), by
        quadrature over the bounds: what the posterior's spread is compared with."""
        t = np.linspace(*(np.log([low, high]) if transform == "log" else (low, high)), points)
        value = np.exp(t) if transform == "log" else t
        log_p = np.asarray(self.log_density(jnp.asarray(value))) + (t if transform == "log" else 0.0)  # density in t
        w = np.exp(log_p - log_p.max())
        w /= w.sum()
        mean = np.sum(w * t)
        return float(np.sqrt(np.sum(w * (t - mean) ** 2)))


def default_prior(transform: str) -> Prior:
    """Flat in the fit coordinate: log-uniform for a log transform, else uniform."""
    return Prior("log-uniform" if transform == "log" else "uniform")


def read_prior(spec, low: float, high: float, where: str) -> Prior:
    """A `Prior` from its problem-file form (module docstring); an `InputError` naming
    `where` for anything else."""
    allowed = "\"uniform\", \"log-uniform\", { normal = [mean, sd] } or { log-normal = [median, sd_ln] }"
    if isinstance(spec, str):
        if spec not in ("uniform", "log-uniform"):
            raise InputError(f"{where} prior = {spec!r}; allowed: {allowed}")
        if spec == "log-uniform" and low <= 0:
            raise InputError(f"{where} prior = \"log-uniform\" needs bounds > 0, got low = {low:g}")
        return Prior(spec)
    if not (isinstance(spec, dict) and len(spec) == 1 and next(iter(spec)) in ("normal", "log-normal")):
        raise InputError(f"{where} prior = {spec!r}; allowed: {allowed}")
    kind, pair = next(iter(spec.items()))
    if not (isinstance(pair, list) and len(pair) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in pair)):
        raise InputError(f"{where} prior {kind} = {pair!r}; expected two numbers [{'mean' if kind == 'normal' else 'median'}, sd]")
    location, scale = (float(v) for v in pair)
    if scale <= 0:
        raise InputError(f"{where} prior {kind}: sd = {scale:g} must be > 0")
    if not low <= location <= high:
        raise InputError(f"{where} prior {kind}: {'mean' if kind == 'normal' else 'median'} = {location:g} "
                         f"must lie in the bounds [{low:g}, {high:g}]")
    if kind == "log-normal" and low <= 0:
        raise InputError(f"{where} prior \"log-normal\" needs bounds > 0, got low = {low:g}")
    return Prior(kind, location, scale)
