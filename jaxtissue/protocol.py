"""Culture protocols and the time plan of a run (docs/model.md §1, §4, §5): the
regime, the flexure waveform's period, amplitude and hold, schedules of stages, and
the coupling intervals with their save times. The times every part of jaxtissue uses
(3 weeks, T_g, the paper's end of culture) are defined here."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .params import concrete_value

THREE_WEEKS_S = 1.8144e6
"""The experiments' assay time, 21 days (docs/model.md §6)."""
COUPLING_INTERVAL_S = 2.0e4
"""The growth interval T_g of the staggered loop (docs/model.md §5)."""
T_END_S = 2.0e6
"""The paper's end of culture, ≈ 3.31 weeks (docs/model.md §5)."""
LUMPING_RULES = ("dispersive", "paper")
"""How a loading cycle's flow enters the growth model (docs/model.md §5, `coupling`)."""
PROTOCOL_FIELDS = {"period_s": "s", "post_displacement_mm": "mm", "hold_fraction": "1"}
"""The protocol's differentiable fields and their units."""


class ProtocolValueError(ValueError):
    """A protocol field out of its range, with `field`, `value` and `allowed` for callers
    that name the field their own way (the command line's flags)."""

    def __init__(self, field: str, value: float, allowed: str):
        super().__init__(f"protocol {field} = {value:g} must be {allowed}")
        self.field, self.value, self.allowed = field, value, allowed


def in_table(err: Exception) -> str:
    """A protocol error's message for a file's table of protocol fields, which names
    them itself: without the leading "protocol "."""
    return str(err).removeprefix("protocol ")


class Protocol(eqx.Module):
    """A culture protocol (docs/model.md §1, §4, §5).

    `Protocol.static()`: no motion. `Protocol.flex(...)`: cyclic flexure with post
    displacement u_M(t) of eq. A.22; `period_s`, `post_displacement_mm` and
    `hold_fraction` are differentiable. `lumping` is the coupling rule (`LUMPING_RULES`),
    `pins` where the posts hold the strip ("centroid" or "bottom" corners).

    A schedule (`Protocol.schedule(...)`): `period_s` and `post_displacement_mm` hold one
    value per stage of `stage_length_s` seconds (the last stage lasts to the end); each
    coupling interval uses the stage that holds its start (`at`). Differentiable like
    the constant protocol.
    """

    regime: str = eqx.field(static=True, default="static")
    period_s: float = 1.0
    post_displacement_mm: float = 5.0
    hold_fraction: float = 0.05
    lumping: str = eqx.field(static=True, default="dispersive")
    pins: str = eqx.field(static=True, default="centroid")
    stage_length_s: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.regime not in ("static", "flex"):
            raise ValueError(f"regime = {self.regime!r}; allowed: 'static', 'flex'")
        if self.lumping not in LUMPING_RULES:
            raise ValueError(f"lumping = {self.lumping!r}; allowed: {', '.join(map(repr, LUMPING_RULES))}")
        if self.pins not in ("centroid", "bottom"):
            raise ValueError(f"pins = {self.pins!r}; allowed: 'centroid', 'bottom'")
        checks = (
            ("period_s", lambda v: v > 0, "> 0 s"),
            ("post_displacement_mm", lambda v: 0 <= v, ">= 0 mm"),  # below the strip length: `simulate` checks
            ("hold_fraction", lambda v: (0 <= v) & (v < 0.25), "in [0, 0.25)"),
        )
        for name, ok, allowed in checks:
            try:
                value = concrete_value(getattr(self, name))
            except TypeError:
                raise TypeError(f"protocol {name} = {getattr(self, name)!r} must be a number") from None
            if value is not None and not (np.all(np.isfinite(value)) and np.all(ok(value))):
                bad = np.ravel(value)[~np.ravel(np.isfinite(value) & ok(np.where(np.isfinite(value), value, 0)))][0]
                raise ProtocolValueError(name, float(bad), allowed)
        if self.stage_length_s is not None:
            if not (isinstance(self.stage_length_s, (int, float)) and math.isfinite(self.stage_length_s) and self.stage_length_s > 0):
                raise ValueError(f"protocol stage_length_s = {self.stage_length_s!r} must be a positive number of seconds")
            shapes = {np.shape(self.period_s), np.shape(self.post_displacement_mm)}
            if len(shapes) != 1 or len(next(iter(shapes))) != 1 or next(iter(shapes))[0] < 1:
                raise ValueError("a schedule's period_s and post_displacement_mm must be lists of the same length (one value per stage)")

    @classmethod
    def static(cls) -> "Protocol":
        return cls(regime="static")

    @classmethod
    def flex(cls, period_s=1.0, post_displacement_mm=5.0, hold_fraction=0.05, lumping="dispersive", pins="centroid") -> "Protocol":
        return cls("flex", period_s, post_displacement_mm, hold_fraction, lumping, pins)

    @classmethod
    def schedule(cls, period_s, post_displacement_mm, stage_length_s=604800.0, hold_fraction=0.05, lumping="dispersive", pins="centroid") -> "Protocol":
        """Piecewise-constant flexure: stage k (from k·stage_length_s, default weekly)
        uses period_s[k] and post_displacement_mm[k]."""
        return cls("flex", jnp.asarray(period_s, float), jnp.asarray(post_displacement_mm, float), hold_fraction, lumping, pins, float(stage_length_s))

    @property
    def stages(self) -> int:
        """Number of stages (1 for a constant protocol)."""
        return 1 if self.stage_length_s is None else int(np.shape(self.period_s)[0])

    def at(self, t_s) -> "Protocol":
        """The constant protocol in force at time `t_s` (s)."""
        if self.stage_length_s is None:
            return self
        k = jnp.clip(jnp.floor(t_s / self.stage_length_s), 0, self.stages - 1).astype(int)
        return Protocol(self.regime, self.period_s[k], self.post_displacement_mm[k], self.hold_fraction, self.lumping, self.pins)

    def stage_starts_s(self) -> np.ndarray:
        return np.arange(self.stages) * (self.stage_length_s or 0.0)


def interval_bounds(t_end_s: float, coupling_interval_s: float, t_start_s: float = 0.0) -> np.ndarray:
    """The coupling intervals' bounds: `t_start_s`, every multiple of T_g in between, 3
    weeks (the assay time, where the interval holding it is split) and `t_end_s`."""
    n = int(math.floor(t_end_s / coupling_interval_s + 1e-9))
    ts = set(np.round(np.arange(n + 1) * coupling_interval_s, 9).tolist()) | {t_end_s, t_start_s, THREE_WEEKS_S}
    return np.array(sorted(t for t in ts if t_start_s <= t <= t_end_s))


def save_times(t_end_s: float, coupling_interval_s: float, t_start_s: float = 0.0) -> np.ndarray:
    """The times a `Result` holds: the interval bounds (every T_g, 3 weeks, the end)."""
    return interval_bounds(t_end_s, coupling_interval_s, t_start_s)
