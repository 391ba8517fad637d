"""Calibration problems as PEtab v2 files, with jaxtissue as the model language
(docs/model.md §9; the format: docs/numerics.md "Calibration").

A PEtab v2 problem is a YAML file naming a model and five tables. Here the model is a
jaxtissue model file (`language: jaxtissue`, a TOML file with the `[model]` resolution
and the `[fit]` settings of a TOML problem), registered with the `petab` library as a
`petab.v2.models.Model` (`JaxtissueModel`), and the tables map onto a
`calibration.Problem`:

* parameters: a row per `Params` field that differs from its default. `estimate =
  true`: a free parameter with its bounds, `nominalValue` as its start, its prior
  (`uniform`, `log-uniform`, `normal`, `log-normal`; none: flat in the fit coordinate)
  and the fit coordinate in an optional `parameterScale` column (`log` or `lin`;
  default `log` where the lower bound is > 0). `estimate = false`: a fixed value.
* conditions set the protocol fields `period_s`, `post_displacement_mm`,
  `hold_fraction`; an experiment whose periods set none of them is static culture,
  otherwise cyclic flexure (the fields it does not set keep `Protocol.flex`'s
  defaults). Periods at 0, S, 2S, … with flexure conditions are a schedule of stages
  of S seconds (`Protocol.schedule`).
* observables: `observableFormula` is a `Result` output (`data.QUANTITIES`);
  `noiseFormula` a number or a placeholder set by each measurement's
  `noiseParameters`; `noiseDistribution` `normal` or `log-normal`.
* measurements at time 0 compare with the seeded state, common to every experiment.

`load` reads a problem, `lint` checks it with the `petab` linter plus jaxtissue's own
checks (`CHECKS`), `to_problem` converts it, `export` writes a `calibration.Problem` as
PEtab files. The `petab` library is imported with this module (a few seconds).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import warnings
from collections.abc import Iterable

import numpy as np
import pandas as pd
import sympy as sp
from petab.v1.yaml import load_yaml
from petab.v2 import C
from petab.v2.core import Problem as PetabProblem
from petab.v2.lint import ValidationError, ValidationIssueSeverity, ValidationTask
from petab.v2.models import Model

from .. import io
from ..data import NOISE, QUANTITIES, Observation
from ..io import InputError, read_toml
from ..params import FIELDS, Params
from ..protocol import PROTOCOL_FIELDS, Protocol
from ._problem_files import ModelSettings, settings, table
from .calibration import FitSettings, FreeParameter, Problem, free_parameter

LANGUAGE = "jaxtissue"
"""The model language of jaxtissue model files in a PEtab problem's `model_files`."""
SCALES = {"log": "log", "lin": "linear"}
"""`parameterScale` → the fit coordinate (`FreeParameter.transform`)."""
PRIORS = ("uniform", "log-uniform", "normal", "log-normal")
"""The PEtab prior distributions a jaxtissue problem takes (docs/model.md §9)."""


class JaxtissueModel(Model):
    """A jaxtissue model file: its entities are the `Params` fields (parameter table),
    the protocol fields (condition table) and the `Result` outputs (observable
    formulas)."""

    type_id = LANGUAGE

    def __init__(self, model: ModelSettings = ModelSettings(), fit: FitSettings = FitSettings(), name: str = "calibration",
                 model_id: str = "jaxtissue"):
        self.model, self.fit, self.name, self._model_id = model, fit, name, model_id

    @staticmethod
    def from_file(filepath_or_buffer, model_id: str, base_path=None) -> JaxtissueModel:
        path = pathlib.Path(base_path or ".") / filepath_or_buffer
        doc, _ = read_toml(path, "jaxtissue model", {"name", "model", "fit"})
        where = str(path)
        return JaxtissueModel(settings(ModelSettings, table(doc, "model", where), where, "model"),
                              settings(FitSettings, table(doc, "fit", where), where, "fit"),
                              str(doc.get("name", path.stem)), model_id)

    def to_file(self, filename=None):
        lines = ["# A jaxtissue model (docs/model.md): the resolution its fit simulates at and the fit's settings.",
                 f"name = {self.name!r}".replace("'", '"'), "", "[model]"]
        lines += [f"{k} = {_toml(v)}" for k, v in dataclasses.asdict(self.model).items()]
        lines += ["", "[fit]"] + [f"{k} = {_toml(v)}" for k, v in dataclasses.asdict(self.fit).items()]
        io.atomic_write_text(filename, "\n".join(lines) + "\n")

    @property
    def model_id(self):
        return self._model_id

    def get_parameter_value(self, id_: str) -> float:
        if id_ not in FIELDS:
            raise ValueError(f"unknown parameter {id_!r}")
        return float(getattr(Params(), id_))

    def get_free_parameter_ids_with_values(self) -> Iterable[tuple[str, float]]:
        return ((name, self.get_parameter_value(name)) for name in FIELDS)

    def get_parameter_ids(self) -> Iterable[str]:
        return iter(FIELDS)

    def has_entity_with_id(self, entity_id) -> bool:
        return entity_id in FIELDS or entity_id in PROTOCOL_FIELDS or entity_id in QUANTITIES

    def get_valid_parameters_for_parameter_table(self) -> Iterable[str]:
        return iter(FIELDS)

    def get_valid_ids_for_condition_table(self) -> Iterable[str]:
        return iter(PROTOCOL_FIELDS)

    def symbol_allowed_in_observable_formula(self, id_: str) -> bool:
        return id_ in QUANTITIES

    def is_valid(self) -> bool:
        return True  # `from_file` has checked it

    def is_state_variable(self, id_: str) -> bool:
        return False


def _toml(value) -> str:
    return ("true" if value else "false") if isinstance(value, bool) else repr(value)


# ---------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------


def load(path) -> PetabProblem:
    """A PEtab v2 problem with its jaxtissue model and jaxtissue's checks (`CHECKS`)
    among its validation tasks. A file that cannot be read is an `InputError`."""
    path = pathlib.Path(path)
    where = str(path)
    if path.is_dir():
        if not (path / "problem.yaml").is_file():
            raise InputError(f"{where}: a folder without problem.yaml; give the PEtab problem's YAML file")
        path = path / "problem.yaml"
    if path.suffix.lower() == ".toml":
        raise InputError(f"{where}: a TOML file, not a PEtab YAML problem; `jaxtissue calibrate {where} --export-petab DIR` "
                         "converts a TOML calibration problem")
    try:
        config = load_yaml(path)
    except FileNotFoundError:
        raise InputError(f"{where}: no such PEtab problem file") from None
    except Exception as err:  # noqa: BLE001 -- YAML errors come in many types
        raise InputError(f"{where}: not a PEtab YAML file ({_one_line(err)})") from None
    if not isinstance(config, dict):
        raise InputError(f"{where}: not a PEtab problem (a YAML mapping with format_version, model_files, ...)")
    models = config.get("model_files") or {}
    if not isinstance(models, dict) or len(models) != 1:
        raise InputError(f"{where}: model_files must name exactly one model (language: {LANGUAGE})")
    (model_id, info), = models.items()
    if not isinstance(info, dict) or info.get("language") != LANGUAGE or "location" not in info:
        raise InputError(f"{where}: model {model_id!r} must have location: FILE.toml and language: {LANGUAGE}, "
                         f"got {info!r}")
    model = JaxtissueModel.from_file(info["location"], model_id, path.parent)
    try:
        with warnings.catch_warnings():  # the petab library's own use of deprecated pandas calls
            warnings.filterwarnings("ignore", message="The inplace keyword", module=r"petab\.")
            problem = PetabProblem.from_yaml({**config, "model_files": {}}, base_path=path.parent)
    except Exception as err:  # noqa: BLE001 -- pandas, pydantic and jsonschema errors of malformed tables
        raise InputError(f"{where}: {_one_line(err)}") from None
    problem.models = [model]
    problem.config.model_files = models
    problem.validation_tasks += [task() for task in CHECKS]
    return problem


def _one_line(err: Exception) -> str:
    """An exception's message on one line (pydantic's: each error's location and message)."""
    errors = getattr(err, "errors", None)
    if callable(errors):  # pydantic: the table row's type (e.g. Measurement), each field and message
        try:
            where = f"{err.title} row" if getattr(err, "title", None) else "row"
            return "; ".join(f"{where}: {' '.join(map(str, e.get('loc', ())))}: {e.get('msg')}" for e in errors())
        except Exception:  # noqa: BLE001
            pass
    message = getattr(err, "message", None)  # jsonschema's, without the schema it quotes
    text = " ".join((message if isinstance(message, str) else str(err)).split())
    return f"{type(err).__name__}: {text}" if isinstance(err, KeyError) else text


def check(path) -> tuple[list[str], PetabProblem | None]:
    """(the PEtab linter's messages, `LEVEL: message` one per line with jaxtissue's checks
    included, and the loaded problem); a file that cannot be read at all gives its one
    message and None."""
    try:
        problem = load(path)
    except InputError as err:
        return [f"ERROR: {str(err).removeprefix(f'{path}: ')}"], None
    messages = [f"{issue.level.name}: {line}" for issue in problem.validate() for line in str(issue.message).splitlines()
                if line.strip()]
    return messages, problem


def lint(path) -> list[str]:
    """The messages of `check`; [] for a clean problem."""
    return check(path)[0]


def errors(messages: list[str]) -> list[str]:
    """The messages of `lint` at level ERROR or above."""
    bad = {level.name for level in ValidationIssueSeverity if level >= ValidationIssueSeverity.ERROR}
    return [m for m in messages if m.split(":", 1)[0] in bad]


def read(path) -> Problem:
    """A `calibration.Problem` from a PEtab v2 file; an `InputError` with the linter's
    first error if the problem has errors."""
    messages, problem = check(path)
    messages = errors(messages)
    if messages:
        more = f" (and {len(messages) - 1} more)" if len(messages) > 1 else ""
        raise InputError(f"{path}: {messages[0].split(': ', 1)[1]}{more}; `jaxtissue lint {path}` lists every message")
    return to_problem(problem)


def _observables(problem: PetabProblem) -> dict:
    """{observable id: (quantity, noise distribution)}."""
    out = {}
    for o in problem.observables:
        if o.formula is None:
            raise InputError(f"observable {o.id}: observableFormula is missing; give one model output, one of {', '.join(QUANTITIES)}")
        if not isinstance(o.formula, sp.Symbol) or str(o.formula) not in QUANTITIES:
            raise InputError(f"observable {o.id}: observableFormula = {o.formula} must be one model output, "
                             f"one of {', '.join(QUANTITIES)}")
        noise = str(o.noise_distribution.value if hasattr(o.noise_distribution, "value") else o.noise_distribution)
        if noise not in NOISE:
            raise InputError(f"observable {o.id}: noiseDistribution = {noise!r}; allowed: {', '.join(NOISE)}")
        out[o.id] = (str(o.formula), noise)
    return out


def _noise_sd(problem: PetabProblem, m) -> float:
    """The noise SD of measurement m: its observable's noiseFormula with the
    placeholders set to m's noiseParameters."""
    o = problem[m.observable_id]
    if o.noise_formula is None:
        raise InputError(f"observable {o.id}: noiseFormula is empty; give the measurements' SD (a placeholder set by noiseParameters)")
    values = dict(zip(o.noise_placeholders, m.noise_parameters))
    sd = o.noise_formula.subs(values)
    what = f"measurement of {m.observable_id} in experiment {m.experiment_id} at time {m.time:g} s"
    if not sd.is_number:
        raise InputError(f"{what}: noise SD {sd} must be a number (estimated noise parameters are not supported)")
    sd = float(sd)
    if not (math.isfinite(sd) and sd > 0):
        raise InputError(f"{what}: noise SD = {sd:g} must be > 0")
    return sd


def _measurements(problem: PetabProblem) -> tuple[Observation, ...]:
    observables = _observables(problem)
    rows = []
    for m in problem.measurements:
        if m.observable_id not in observables:
            raise InputError(f"measurement observable {m.observable_id!r} is not in the observable table")
        quantity, noise = observables[m.observable_id]
        if noise == "log-normal" and m.measurement <= 0:
            raise InputError(f"measurement of {m.observable_id} at time {m.time:g} s: {m.measurement:g} must be > 0 with log-normal noise")
        if not (math.isfinite(m.time) and m.time >= 0):
            raise InputError(f"measurement of {m.observable_id} in experiment {m.experiment_id}: time = {m.time:g} s must be finite and >= 0")
        regime = "seeded" if m.time == 0 else m.experiment_id
        if regime is None:
            raise InputError(f"measurement of {m.observable_id} at time {m.time:g} s: experimentId is empty")
        source = (m.model_extra or {}).get("source")
        source = "" if source is None or (isinstance(source, float) and math.isnan(source)) else str(source)
        rows.append(Observation(quantity, regime, float(m.time), float(m.measurement), _noise_sd(problem, m), QUANTITIES[quantity],
                                source, noise))
    return tuple(rows)


def _protocols(problem: PetabProblem) -> dict:
    """{experiment id: Protocol}."""
    conditions = {c.id: c for c in problem.conditions}
    out = {}
    for e in problem.experiments:
        where = f"experiment {e.id}"
        stages = []
        for period in e.sorted_periods:
            values = {}
            for cid in period.condition_ids:
                if cid not in conditions:
                    raise InputError(f"{where}: condition {cid!r} is not in the condition table")
                for change in conditions[cid].changes:
                    if change.target_id not in PROTOCOL_FIELDS:
                        raise InputError(f"{where}: condition {cid} sets {change.target_id}; allowed targets: {', '.join(PROTOCOL_FIELDS)}")
                    if not change.target_value.is_number:
                        raise InputError(f"{where}: condition {cid} sets {change.target_id} = {change.target_value}; must be a number")
                    values[change.target_id] = float(change.target_value)
            stages.append((float(period.time), values))
        if not stages or stages[0][0] != 0:
            raise InputError(f"{where}: its first period must start at time 0, got {stages[0][0] if stages else 'no period'}")
        try:
            if len(stages) == 1:
                values = stages[0][1]
                out[e.id] = Protocol.flex(**values) if values else Protocol.static()
                continue
            starts = np.array([s for s, _ in stages])
            length = starts[1]
            if not np.allclose(np.diff(starts), length, rtol=1e-9, atol=0) or not all(v for _, v in stages):
                raise InputError(f"{where}: periods at {', '.join(f'{s:g}' for s in starts)} s; a schedule needs periods at 0, S, 2S, ... "
                                 "each with a flexure condition")
            merged = [{**dict(period_s=1.0, post_displacement_mm=5.0, hold_fraction=0.05), **v} for _, v in stages]
            if len({m["hold_fraction"] for m in merged}) != 1:
                raise InputError(f"{where}: hold_fraction must be the same in every period of a schedule")
            out[e.id] = Protocol.schedule([m["period_s"] for m in merged], [m["post_displacement_mm"] for m in merged],
                                          stage_length_s=float(length), hold_fraction=merged[0]["hold_fraction"])
        except (TypeError, ValueError) as err:
            raise InputError(f"{where}: {err}") from None
    return out


def _parameters(problem: PetabProblem) -> tuple[Params, tuple[FreeParameter, ...]]:
    """(base parameters, free parameters) from the parameter table."""
    changes, free = {}, []
    for p in problem.parameters:
        where = f"parameter {p.id}"
        if p.id not in FIELDS:
            continue  # an output or noise parameter: the petab linter's to judge
        if p.nominal_value is not None:
            if not FIELDS[p.id].contains(p.nominal_value):
                raise InputError(f"{where}: nominalValue = {p.nominal_value:g} must be in {FIELDS[p.id].range_text()} {FIELDS[p.id].unit}")
            changes[p.id] = float(p.nominal_value)
        if not p.estimate:
            continue
        scale = (p.model_extra or {}).get("parameterScale")
        if scale is None or (isinstance(scale, float) and math.isnan(scale)) or scale == "":
            scale = "log" if p.lb > 0 else "lin"
        if scale not in SCALES:
            raise InputError(f"{where}: parameterScale = {scale!r}; allowed: {', '.join(SCALES)}")
        free.append(free_parameter(p.id, p.lb, p.ub, SCALES[scale], _prior(p, where), where))
    return Params().replace(**changes) if changes else Params(), tuple(free)


def _prior(p, where: str) -> dict | str | None:
    """The problem-file form (`priors.read_prior`) of a PEtab prior."""
    if p.prior_distribution is None:
        return None
    kind = str(p.prior_distribution.value if hasattr(p.prior_distribution, "value") else p.prior_distribution)
    if kind not in PRIORS:
        raise InputError(f"{where}: priorDistribution = {kind!r}; allowed: {', '.join(PRIORS)}")
    a, b = (list(p.prior_parameters) + [math.nan, math.nan])[:2]
    if kind in ("uniform", "log-uniform"):
        if not (math.isclose(a, p.lb, rel_tol=1e-12) and math.isclose(b, p.ub, rel_tol=1e-12)):
            raise InputError(f"{where}: a {kind} prior on [{a:g}, {b:g}] must span the bounds [{p.lb:g}, {p.ub:g}]")
        return kind
    if kind == "normal":
        return {"normal": [a, b]}  # mean, SD
    return {"log-normal": [math.exp(a), b]}  # PEtab: mean and SD of ln θ; jaxtissue: median exp(mean), SD of ln θ


def to_problem(problem: PetabProblem) -> Problem:
    """The `calibration.Problem` of a PEtab problem with a jaxtissue model (`load`)."""
    base, free = _parameters(problem)
    if not free:
        raise InputError("the parameter table estimates no model parameter")
    observations = _measurements(problem)
    conditions = _protocols(problem)
    for o in observations:
        if o.regime != "seeded" and o.regime not in conditions:
            raise InputError(f"measurement experiment {o.regime!r} is not in the experiment table")
    model = problem.model
    return Problem(base=base, free=free, observations=observations, conditions=conditions, model=model.model, fit=model.fit,
                   name=problem.id or model.name)


class _Check(ValidationTask):
    """A jaxtissue check: the `InputError` of one step of `to_problem`, as a linter error."""

    step = staticmethod(lambda problem: None)

    def run(self, problem):
        try:
            type(self).step(problem)
        except InputError as err:
            return ValidationError(str(err))
        return None


class CheckObservables(_Check):
    """Observable formulas are model outputs; noise normal or log-normal."""

    step = staticmethod(_observables)


class CheckMeasurements(_Check):
    """Noise SDs are positive numbers; log-normal data positive; times >= 0."""

    @staticmethod
    def step(problem):
        try:
            known = _observables(problem)
        except InputError:
            return  # CheckObservables reports it
        if all(m.observable_id in known for m in problem.measurements):  # else the petab linter reports it
            _measurements(problem)


class CheckProtocols(_Check):
    """Conditions set protocol fields with values in their ranges; schedules are regular."""

    step = staticmethod(_protocols)


class CheckParameters(_Check):
    """Bounds, nominal values, scales and priors of the model's parameters."""

    step = staticmethod(_parameters)


class CheckProblem(_Check):
    """The whole conversion (measurement times at save times, ...), once the parts pass."""

    @staticmethod
    def step(problem):
        for part in (_observables, _measurements, _protocols, _parameters):
            try:
                part(problem)
            except InputError:
                return  # reported by its own check
        to_problem(problem)


CHECKS = (CheckObservables, CheckMeasurements, CheckProtocols, CheckParameters, CheckProblem)
"""jaxtissue's validation tasks, run by `lint` after the `petab` library's own."""


# ---------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------


def observable_id(o: Observation) -> str:
    return f"obs_{o.quantity}" + ("_log" if o.noise == "log-normal" else "")


def export(problem: Problem, folder) -> list[str]:
    """Write `problem` as PEtab v2 files into `folder` (problem.yaml, model.toml and the
    tables); returns the file names. Protocols with a non-default lumping rule or pins
    cannot be expressed and are an `InputError`."""
    folder = pathlib.Path(folder)
    names = list(problem.conditions)
    for name, protocol in problem.conditions.items():
        if protocol.lumping != "dispersive" or protocol.pins != "centroid":
            raise InputError(f"condition {name}: lumping = {protocol.lumping!r}, pins = {protocol.pins!r} have no PEtab form; "
                             "only the defaults ('dispersive', 'centroid') export")
    seeded_in = names[0]

    observables = {}
    for o in problem.observations:
        oid = observable_id(o)
        placeholder = f"noiseParameter1_{oid}"
        observables[oid] = {C.OBSERVABLE_ID: oid, C.OBSERVABLE_NAME: f"{o.quantity} ({o.unit})", C.OBSERVABLE_FORMULA: o.quantity,
                            C.NOISE_FORMULA: placeholder, C.NOISE_DISTRIBUTION: o.noise, C.NOISE_PLACEHOLDERS: placeholder}
    measurements = [{C.OBSERVABLE_ID: observable_id(o), C.EXPERIMENT_ID: seeded_in if o.regime == "seeded" else o.regime,
                     C.TIME: o.time_s, C.MEASUREMENT: o.mean, C.NOISE_PARAMETERS: o.sd, "source": o.source}
                    for o in problem.observations]

    conditions, experiments = [], []
    for name, protocol in problem.conditions.items():
        if protocol.regime == "static":
            experiments.append({C.EXPERIMENT_ID: name, C.TIME: 0.0, C.CONDITION_ID: ""})
            continue
        stages = protocol.stages if protocol.stage_length_s is not None else 1
        for k in range(stages):
            cid = f"{name}_protocol" if stages == 1 else f"{name}_stage{k + 1}"
            for field in PROTOCOL_FIELDS:
                value = np.ravel(np.asarray(getattr(protocol, field), float))
                conditions.append({C.CONDITION_ID: cid, C.TARGET_ID: field, C.TARGET_VALUE: float(value[min(k, value.size - 1)])})
            start = 0.0 if stages == 1 else k * protocol.stage_length_s
            experiments.append({C.EXPERIMENT_ID: name, C.TIME: start, C.CONDITION_ID: cid})

    free = {f.name: f for f in problem.free}
    default = Params()
    parameters = []
    for name in [*free, *(n for n in FIELDS if n not in free)]:  # the free ones in their order: the starts depend on it
        value = float(getattr(problem.base, name))
        if name in free:
            f = free[name]
            prior, prior_parameters = "", ""
            if f.prior is not None:
                prior = f.prior.kind
                prior_parameters = (f"{f.lower!r};{f.upper!r}" if prior in ("uniform", "log-uniform") else
                                    f"{f.prior.location!r};{f.prior.scale!r}" if prior == "normal" else
                                    f"{math.log(f.prior.location)!r};{f.prior.scale!r}")
            parameters.append({C.PARAMETER_ID: name, "parameterScale": "log" if f.transform == "log" else "lin",
                               C.LOWER_BOUND: f.lower, C.UPPER_BOUND: f.upper, C.NOMINAL_VALUE: value, C.ESTIMATE: "true",
                               C.PRIOR_DISTRIBUTION: prior, C.PRIOR_PARAMETERS: prior_parameters})
        elif value != float(getattr(default, name)):
            parameters.append({C.PARAMETER_ID: name, "parameterScale": "", C.LOWER_BOUND: "", C.UPPER_BOUND: "",
                               C.NOMINAL_VALUE: value, C.ESTIMATE: "false", C.PRIOR_DISTRIBUTION: "", C.PRIOR_PARAMETERS: ""})

    files = {
        "observables.tsv": pd.DataFrame(list(observables.values())),
        "measurements.tsv": pd.DataFrame(measurements),
        "conditions.tsv": pd.DataFrame(conditions, columns=[C.CONDITION_ID, C.TARGET_ID, C.TARGET_VALUE]),
        "experiments.tsv": pd.DataFrame(experiments),
        "parameters.tsv": pd.DataFrame(parameters),
    }
    for name, df in files.items():
        io.atomic_write_text(folder / name, df.to_csv(sep="\t", index=False, float_format=None))
    JaxtissueModel(problem.model, problem.fit, problem.name).to_file(folder / "model.toml")
    yaml = [
        f"# {problem.name}: a PEtab v2 calibration problem with a jaxtissue model (`jaxtissue lint`, `jaxtissue calibrate`).",
        "format_version: 2.0.0",
        *([f"id: {problem.name}"] if problem.name.isidentifier() else []),
        "model_files:",
        "  jaxtissue:",
        "    location: model.toml",
        f"    language: {LANGUAGE}",
        "parameter_files: [parameters.tsv]",
        "observable_files: [observables.tsv]",
        "measurement_files: [measurements.tsv]",
        "condition_files: [conditions.tsv]",
        "experiment_files: [experiments.tsv]",
    ]
    io.atomic_write_text(folder / "problem.yaml", "\n".join(yaml) + "\n")
    return ["problem.yaml", "model.toml", *files]
