"""Checkpointed runs: a simulation in segments of N coupling intervals, each finished
segment written atomically to `FOLDER/segment_KKKK.npz` (its saved series and its final
state), so that a killed run resumes from the last segment.

A resumed run repeats exactly the computations of an uninterrupted one with the same
segments (the same compiled segment from the same state bits), so it gives the same
result to the last bit on the same machine. Each segment starts the growth solve afresh
from its first state. The model does not depend on time itself (docs/model.md §2), so
under a time-invariant protocol every segment is solved from t = 0 and its times moved
to where it lies: the full segments share one compiled program (schedules, whose stages
are fixed in time, solve each segment at its own times and compile it once).
"""

from __future__ import annotations

import dataclasses
import pathlib

import jax.numpy as jnp
import numpy as np

from ..io import atomic_write, read_arrays
from ..protocol import COUPLING_INTERVAL_S, interval_bounds, save_times
from ..result import RESULTS, SERIES, Result, coordinates_cm
from ..simulate import simulate
from ..state import State


def segment_edges(t_end_s: float, coupling_interval_s: float, every: int) -> np.ndarray:
    """0, every `every`-th coupling interval bound, and `t_end_s`."""
    bounds = interval_bounds(t_end_s, coupling_interval_s)
    return np.unique(np.concatenate([bounds[::every], bounds[-1:]]))


def _save(path: pathlib.Path, r: Result) -> None:
    data = {k: np.asarray(getattr(r, k)) for k in SERIES}
    data.update(ts=np.asarray(r.ts), o=np.asarray(r.final.o), c=np.asarray(r.final.c), m=np.asarray(r.final.m),
                num_steps=np.asarray(r.num_steps))
    atomic_write(path, lambda f: np.savez(f, **data))


def _load(path: pathlib.Path) -> dict:
    """A segment `_save` wrote (`io.read_arrays`: a damaged one is an `InputError`)."""
    return read_arrays(path, ("ts", "o", "c", "m", "num_steps", *SERIES), "compute that segment again")


def _combine(parts: list[dict], params, grid) -> Result:
    """One `Result` from the segments' series (each later segment's first time, the
    previous one's last, dropped)."""
    cut = [p if i == 0 else {k: v[1:] for k, v in p.items() if k in SERIES + ("ts",)} for i, p in enumerate(parts)]
    series = {k: jnp.asarray(np.concatenate([p[k] for p in cut])) for k in SERIES}
    ts = tuple(np.concatenate([p["ts"] for p in cut]).tolist())
    final = State(*(jnp.asarray(parts[-1][k]) for k in ("o", "c", "m")))
    x_cm, y_cm = coordinates_cm(params, grid)
    return Result(ts=ts, **series, final=final, x_cm=x_cm, y_cm=y_cm,
                  num_steps=jnp.asarray(sum(int(p["num_steps"]) for p in parts)), failed=jnp.asarray(False),
                  status=RESULTS.successful, t_reached_s=jnp.asarray(ts[-1]), params=params)


def _segment(params, protocol, t0: float, t1: float, grid, coupling_interval_s: float, state, simulate_kw) -> Result:
    """The run from `state` at t0 to t1, at its own times: solved from t = 0 where that
    gives the same interval plan (a time-invariant protocol, no 3-week split in between)."""
    times = save_times(t1, coupling_interval_s, t0)
    shifted = save_times(t1 - t0, coupling_interval_s) + t0
    if (protocol.stage_length_s is not None or state is None or len(shifted) != len(times)
            or np.max(np.abs(shifted - times)) > 1e-9 * coupling_interval_s):
        return simulate(params, protocol, t1, grid, coupling_interval_s=coupling_interval_s, initial_state=state, t_start_s=t0,
                        **simulate_kw)
    r = simulate(params, protocol, t1 - t0, grid, coupling_interval_s=coupling_interval_s, initial_state=state, **simulate_kw)
    ts = tuple(times[-len(r.ts):].tolist())  # every save time, or the end alone (`save = "end"`)
    return dataclasses.replace(r, ts=ts, t_reached_s=r.t_reached_s + t0)


def simulate_checkpointed(params, protocol, t_end_s: float, grid, folder, every: int, *, coupling_interval_s: float = COUPLING_INTERVAL_S,
                          progress=None, **simulate_kw) -> Result:
    """`simulate` in segments of `every` coupling intervals, each saved in `folder`;
    segments already there are loaded instead of solved. `progress(k, n)` after each
    segment. A failed segment ends the run (its `Result`, which reports the failure, is
    returned) and is not saved."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    edges = segment_edges(t_end_s, coupling_interval_s, every)
    parts, state = [], None
    for k in range(len(edges) - 1):
        path = folder / f"segment_{k:04d}.npz"
        if not path.exists():
            t0, t1 = float(edges[k]), float(edges[k + 1])
            r = _segment(params, protocol, t0, t1, grid, coupling_interval_s, state, simulate_kw)
            if bool(r.failed):
                return r
            _save(path, r)
        # always continue from what is on disk: a resumed run reads the same bits
        parts.append(_load(path))
        state = State(*(jnp.asarray(parts[-1][n]) for n in ("o", "c", "m")))
        if progress is not None:
            progress(k + 1, len(edges) - 1)
    return _combine(parts, params, grid)
