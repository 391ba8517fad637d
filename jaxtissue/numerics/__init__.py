"""General numerics with no model types: banded solves, the Rosenbrock-W solver and the
vector fields it integrates, rematerialised loops and bounded least squares
(docs/numerics.md).

The solvers (`ROS34PW2`, `Rodas4P2`, `SOLVERS`, `ReproducibleSteps`, `quantise`: diffrax) and the least-squares
solver (`LevenbergMarquardt`: optimistix) load on first use, so that a run loaded as a
saved program (`jaxtissue.cache`) does not import the libraries that trace it."""

from ._banded import (
    FivePoint as FivePoint,
    FivePointFactor as FivePointFactor,
    Thomas as Thomas,
    colouring as colouring,
    line_sweeps as line_sweeps,
    neighbour_colours as neighbour_colours,
    thomas_factor as thomas_factor,
    thomas_solve as thomas_solve,
)
from ._remat import chunking as chunking, nested_checkpoint_scan as nested_checkpoint_scan, replayed_scan as replayed_scan
from ._structured import (
    AbstractStructuredField as AbstractStructuredField,
    Rescaled as Rescaled,
    Stacked as Stacked,
    stack as stack,
)

_ON_FIRST_USE = {
    "ROS34PW2": "_rosenbrock",
    "Rodas4P2": "_rosenbrock",
    "SOLVERS": "_rosenbrock",
    "ReproducibleSteps": "_rosenbrock",
    "quantise": "_rosenbrock",
    "LevenbergMarquardt": "_least_squares",
}


def __getattr__(name: str):
    """The names of `_ON_FIRST_USE`, imported from their module when first asked for."""
    if name not in _ON_FIRST_USE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f".{_ON_FIRST_USE[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_ON_FIRST_USE))
