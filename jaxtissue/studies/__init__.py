"""Workflows on top of `simulate`, one module each: `calibration` (fits, Laplace
approximation, profile likelihoods), `posterior` (Bayesian calibration with the
`priors` of the free parameters, predictive bands), `optimization` (protocol design, with the `objectives` and limits it may use), `sweep` (batch
runs; `sweep_dask` on a Dask cluster), `sensitivity` (d ln output / d ln parameter), `reproduce` (the paper's study)
and `checkpoint` (runs in saved segments). Their problem files share one reader
(`_problem_files`); `petab_problems` reads and writes calibration problems as PEtab v2
files (import it on use: the petab library takes seconds to import)."""

_MODULES = frozenset({"calibration", "checkpoint", "objectives", "optimization", "posterior", "priors", "reproduce",
                      "sensitivity", "sweep", "sweep_dask"})


def __getattr__(name: str):
    """Each workflow loads on first use (`jaxtissue.studies.calibration`, …)."""
    if name not in _MODULES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return importlib.import_module(f".{name}", __name__)


def __dir__():
    return sorted(set(globals()) | _MODULES)
