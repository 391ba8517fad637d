"""Experimental data: Engelmayr et al. (2005, 2008), mean ± SD (docs/model.md §6), and a
reader for measurement tables laid out as PEtab's (observableId,
simulationConditionId, time, measurement, noiseParameters)."""

from __future__ import annotations

import csv
import math
import pathlib
from typing import NamedTuple

from .params import suggest
from .protocol import THREE_WEEKS_S
from .result import MEASURABLE, OUTPUTS

QUANTITIES = {k: OUTPUTS[k].unit for k in MEASURABLE}
"""Observables that can be compared with data (the `Result` keys) and their units."""


class Observation(NamedTuple):
    quantity: str  # the `Result`/summary key it compares with (`QUANTITIES`)
    regime: str  # a condition ("static", "flex", ...); "seeded": t = 0, common to all
    time_s: float
    mean: float
    sd: float
    unit: str
    source: str = ""
    noise: str = "normal"  # `NOISE`: "normal": sd in the quantity's unit; "log-normal": sd of ln(value)


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


COLUMNS = ("observableId", "simulationConditionId", "time", "measurement", "noiseParameters")
NOISE = ("normal", "log-normal")
"""Measurement noise models (docs/model.md §9): "normal", value ~ N(model, sd²); "log-normal",
ln value ~ N(ln model, sd²), sd then being the standard deviation of ln value."""


class DataError(ValueError):
    """A measurement table is malformed; the message names the file and row."""


def read_measurements(path) -> tuple[Observation, ...]:
    """Observations from a CSV measurement table.

    Required columns: `observableId` (a key of `QUANTITIES`), `simulationConditionId`
    (a regime name; `seeded` for the t = 0 state common to all), `time` (s),
    `measurement` (mean), `noiseParameters` (SD > 0); optional `unit` (must match the
    observable's), `source` and `noiseDistribution` (`NOISE`, default "normal"; for
    "log-normal" the SD is that of ln measurement, and measurements must be > 0). Any
    mistake is a `DataError` naming the row."""
    path = pathlib.Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")  # a spreadsheet's "CSV UTF-8" starts with a byte-order mark
    except FileNotFoundError:
        raise DataError(f"{path}: no such measurement file") from None
    except (IsADirectoryError, UnicodeDecodeError) as err:
        raise DataError(f"{path}: not a CSV measurement file ({type(err).__name__})") from None
    reader = csv.DictReader(text.splitlines())
    header = reader.fieldnames or []
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise DataError(f"{path}: missing column {missing[0]!r} (required: {', '.join(COLUMNS)})")
    rows = []
    for line, row in enumerate(reader, start=2):
        where = f"{path}, row {line}"
        name = (row["observableId"] or "").strip()
        if name not in QUANTITIES:
            raise DataError(f"{where}: unknown observableId {name!r}; {suggest(name, QUANTITIES)}")
        condition = (row["simulationConditionId"] or "").strip()
        if not condition:
            raise DataError(f"{where}: empty simulationConditionId")
        values = {}
        for column in ("time", "measurement", "noiseParameters"):
            try:
                values[column] = float(row[column])
            except (TypeError, ValueError):
                raise DataError(f"{where}: {column} = {row[column]!r} is not a number") from None
            if not math.isfinite(values[column]):
                raise DataError(f"{where}: {column} = {row[column]!r} must be finite")
        if values["time"] < 0:
            raise DataError(f"{where}: time = {values['time']:g} s must be >= 0")
        if values["noiseParameters"] <= 0:
            raise DataError(f"{where}: noiseParameters (SD) = {values['noiseParameters']:g} must be > 0")
        unit = (row.get("unit") or QUANTITIES[name]).strip()
        if unit != QUANTITIES[name]:
            raise DataError(f"{where}: unit {unit!r} of {name} must be {QUANTITIES[name]!r}")
        noise = (row.get("noiseDistribution") or "normal").strip()
        if noise not in NOISE:
            raise DataError(f"{where}: noiseDistribution = {noise!r}; allowed: {', '.join(NOISE)}")
        if noise == "log-normal" and values["measurement"] <= 0:
            raise DataError(f"{where}: measurement = {values['measurement']:g} must be > 0 with log-normal noise")
        rows.append(Observation(name, condition, values["time"], values["measurement"], values["noiseParameters"], unit,
                                (row.get("source") or "").strip(), noise))
    if not rows:
        raise DataError(f"{path}: no measurements")
    return tuple(rows)
