"""Experimental data of Engelmayr et al. (2005, 2008), mean ± SD (MODEL.md §6)."""

from __future__ import annotations

from typing import NamedTuple


class Observation(NamedTuple):
    quantity: str  # the `Result`/summary key it compares with
    regime: str  # "static" or "flex" ("seeded" for t = 0, common to both)
    time_s: float
    mean: float
    sd: float
    unit: str


THREE_WEEKS_S = 1.8144e6

ENGELMAYR = (
    Observation("dna_ug_per_g", "seeded", 0.0, 536.0, 38.0, "ug/g"),
    Observation("dna_ug_per_g", "static", THREE_WEEKS_S, 307.0, 23.0, "ug/g"),
    Observation("dna_ug_per_g", "flex", THREE_WEEKS_S, 344.0, 5.0, "ug/g"),
    Observation("collagen_mg_per_g", "static", THREE_WEEKS_S, 0.546, 0.111, "mg/g"),
    Observation("collagen_mg_per_g", "flex", THREE_WEEKS_S, 0.846, 0.113, "mg/g"),
    Observation("E_eff_kPa", "seeded", 0.0, 174.0, 22.0, "kPa"),
    Observation("E_eff_kPa", "static", THREE_WEEKS_S, 748.0, 130.0, "kPa"),
    Observation("E_eff_kPa", "flex", THREE_WEEKS_S, 978.0, 228.0, "kPa"),
)


def observations(quantity: str, regime: str) -> list[Observation]:
    """The data points of one quantity for one regime (with the common t = 0 point)."""
    return [o for o in ENGELMAYR if o.quantity == quantity and o.regime in (regime, "seeded")]
