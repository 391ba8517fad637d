"""jaxtissue: a differentiable JAX simulator of engineered-tissue formation under
in-vitro mechanical conditioning (Soares & Sacks 2016; docs/model.md).

The model sits at the package root (params → grid → growth → beam → coupling →
simulate → result); `jaxtissue.numerics` holds the general numerics and
`jaxtissue.studies` the workflows built on `simulate` (calibration, posterior, optimisation,
sweeps, sensitivities, the paper's study, checkpointed runs)."""

import jax

jax.config.update("jax_enable_x64", True)  # the solves are float64 throughout

from . import numerics as numerics  # noqa: E402
from .beam import BeamGrid as BeamGrid  # noqa: E402
from .grid import Grid as Grid  # noqa: E402
from .growth import GrowthModel as GrowthModel  # noqa: E402
from .params import FIELDS as FIELDS, Params as Params, SIParams as SIParams, paper_parameters as paper_parameters  # noqa: E402
from .protocol import (  # noqa: E402
    COUPLING_INTERVAL_S as COUPLING_INTERVAL_S,
    T_END_S as T_END_S,
    THREE_WEEKS_S as THREE_WEEKS_S,
    Protocol as Protocol,
)
from .result import OUTPUTS as OUTPUTS, RESULTS as RESULTS, Result as Result  # noqa: E402
from .simulate import SolverOptions as SolverOptions, simulate as simulate  # noqa: E402
from .state import State as State, Transport as Transport  # noqa: E402

__version__ = "0.1.0"

_STUDIES = frozenset({"studies", "calibration", "checkpoint", "optimization", "posterior", "reproduce", "sensitivity", "sweep"})


def __getattr__(name: str):
    """`jt.studies` and its workflows (`jt.calibration`, …) load on first use: a plain run
    (`jaxtissue simulate`) does not pay for importing them."""
    if name not in _STUDIES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    module = importlib.import_module(".studies" if name == "studies" else f".studies.{name}", __name__)
    globals()[name] = module
    return module


def __dir__():
    return sorted(set(globals()) | _STUDIES)
