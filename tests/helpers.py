"""Shared test utilities."""

import time

import numpy as np


def observed_orders(hs, errors):
    """log(e_i/e_{i+1}) / log(h_i/h_{i+1}) for successive refinements."""
    hs, errors = np.asarray(hs, float), np.asarray(errors, float)
    return np.log(errors[:-1] / errors[1:]) / np.log(hs[:-1] / hs[1:])


def relative_error(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300))


def frozen_cells(**changes):
    """Paper parameters with cell and ECM kinetics switched off (c, m stay put)."""
    import jaxtissue as jt

    return jt.paper_parameters(k_c_max=0.0, k_a=0.0, k_m0=0.0, **changes)


TINY_MODEL = """[model]
ny = 8
flex_nx = 2
beam_segments = 8
beam_steps_per_cycle = 24
coupling_interval_s = 604800.0
"""
"""The [model] table of the small flex problems of the calibration and optimisation tests."""


SMALL_FLEX = dict(t_end_s=4e4, grid_shape=(2, 6))
"""A short flex run on a small growth grid (default beam): `t_end_s` and the `Grid`
shape. Tests that run flex through `simulate`, `reproduce` and the command use this one
configuration, so that they share one compiled program through the test run's
compilation cache."""

SMALL_FLEX_ARGS = ["--grid", *map(str, SMALL_FLEX["grid_shape"]), "--t-end", repr(SMALL_FLEX["t_end_s"]), "--no-progress"]
"""`SMALL_FLEX` as command-line arguments."""


def wait_for(condition, proc, seconds, what):
    """Poll `condition()` while the subprocess `proc` runs; fail if it ends first or
    `seconds` pass."""
    deadline = time.time() + seconds
    while not condition():
        assert proc.poll() is None, f"the command ended before {what}"
        assert time.time() < deadline, f"no {what} within {seconds} s"
        time.sleep(0.05)
