"""Workflows on top of `simulate`, one module each: `calibration` (fits, Laplace
approximation, profile likelihoods), `posterior` (Bayesian calibration with the
`priors` of the free parameters, predictive bands), `optimization` (protocol design, with the `objectives` and limits it may use), `sweep` (batch
runs; `sweep_dask` on a Dask cluster), `sensitivity` (d ln output / d ln parameter), `reproduce` (the paper's study)
and `checkpoint` (runs in saved segments). Their problem files share one reader
(`_problem_files`); `petab_problems` reads and writes calibration problems as PEtab v2
files (import it on use: the petab library takes seconds to import)."""

from . import (
    calibration as calibration,
    checkpoint as checkpoint,
    objectives as objectives,
    optimization as optimization,
    posterior as posterior,
    priors as priors,
    reproduce as reproduce,
    sensitivity as sensitivity,
    sweep as sweep,
    sweep_dask as sweep_dask,
)
