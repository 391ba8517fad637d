"""jaxtissue: a differentiable JAX simulator of engineered-tissue formation under
in-vitro mechanical conditioning (Soares & Sacks 2016). See MODEL.md for the physics."""

import jax

jax.config.update("jax_enable_x64", True)  # the solves are float64 throughout

from .grid import Grid as Grid  # noqa: E402
from .growth import GrowthModel as GrowthModel, State as State, Transport as Transport  # noqa: E402
from .params import Params as Params, paper_parameters as paper_parameters  # noqa: E402
from .simulate import (  # noqa: E402
    THREE_WEEKS_S as THREE_WEEKS_S,
    Protocol as Protocol,
    Result as Result,
    SolverOptions as SolverOptions,
    simulate as simulate,
)

from . import calibration as calibration  # noqa: E402

__version__ = "0.1.0"
