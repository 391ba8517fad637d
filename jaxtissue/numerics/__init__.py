"""General numerics with no model types: banded solves, the Rosenbrock-W solver,
rematerialised loops and bounded least squares (docs/numerics.md)."""

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
from ._least_squares import LevenbergMarquardt as LevenbergMarquardt
from ._remat import chunking as chunking, nested_checkpoint_scan as nested_checkpoint_scan, replayed_scan as replayed_scan
from ._rosenbrock import (
    ROS34PW2 as ROS34PW2,
    AbstractStructuredField as AbstractStructuredField,
    ReproducibleSteps as ReproducibleSteps,
    Rescaled as Rescaled,
    Stacked as Stacked,
    quantise as quantise,
    stack as stack,
)
