"""The paper's study (Soares & Sacks 2016, Figs 5–10): static culture and flexure at
1 Hz / 5 mm, 0.5 and 2 Hz, 2.5 and 10 mm, plus the paper's literal lumping rule,
into figures, a summary and a Markdown report."""

from __future__ import annotations

import pathlib

import equinox as eqx
import jax
import numpy as np

from .. import cache, io, limits, plots
from ..beam import BeamGrid
from ..data import observations
from ..protocol import T_END_S, THREE_WEEKS_S, Protocol
from ..result import MEASURABLE
from ..simulate import SolverOptions, simulate

CASES = {
    "static": Protocol.static(),
    "flex": Protocol.flex(),
    "flex_0.5Hz": Protocol.flex(period_s=2.0),
    "flex_2Hz": Protocol.flex(period_s=0.5),
    "flex_2.5mm": Protocol.flex(post_displacement_mm=2.5),
    "flex_10mm": Protocol.flex(post_displacement_mm=10.0),
}
KEYS = MEASURABLE
"""The outputs the report compares with data."""

CALIBRATED = pathlib.Path(__file__).resolve().parent / "engelmayr2005_posterior"
"""Shipped posterior draws of the Engelmayr calibration (`jaxtissue calibrate
calibrate/engelmayr2005.toml --posterior`): posterior.nc and fitted.toml."""
BANDED = ("static", "flex")
"""The cases drawn with the calibrated model's predictive bands."""


def calibrated_bands(t_end_s=T_END_S, draws: int = 32, folder=CALIBRATED, progress=None) -> dict | None:
    """The calibrated model's posterior predictive of the `BANDED` cases: {case:
    {"time_s": times, output: (q05, q50, q95)}}, from `draws` shipped posterior draws at
    the calibration's resolution; None where no posterior is shipped."""
    from . import posterior

    if not (pathlib.Path(folder) / "posterior.nc").is_file():
        return None
    saved = posterior.read_saved(folder)
    az = posterior.import_arviz()
    r_hat = float(max(az.rhat(saved.values[..., i]) for i in range(len(saved.names))))
    bands = {}
    for name in BANDED:
        ds = posterior.predict(saved, CASES[name], t_end_s, draws=draws, progress=progress)
        bands[name] = {"time_s": ds["time_s"].values, "draws": int(ds.sizes["draw"]), "failed": int(ds["failed"].values.sum()),
                       "r_hat_max": r_hat,
                       **{k: tuple(ds[f"{k}_q{q:02d}"].values for q in (5, 50, 95)) for k in KEYS + ("EI_N_m2",)}}
    return bands


def run_cases(params, t_end_s=T_END_S, progress=False, log=print, flex_grid=None, beam=BeamGrid()):
    """Every case of `CASES`, and flexure with the paper's rule (with the paper's C = 70
    unless `params` chose another, `coupling.with_rule_constant`); flexure on
    `flex_grid` (default `Grid.default("flex")`) with the beam `beam`. The flex cases
    differ only in period and amplitude: they run as one program (`_batch`)."""
    results = {}
    log("running static ...")
    results["static"] = simulate(params, CASES["static"], t_end_s=t_end_s, progress=progress,
                                 options=SolverOptions(static_series="intervals"))  # a program the cache keeps
    flex = [name for name, protocol in CASES.items() if protocol.regime == "flex"]
    log(f"running {', '.join(flex)} ...")
    results.update(zip(flex, _batch(params, [CASES[name] for name in flex], t_end_s, flex_grid, beam)))
    log("running flex with the paper's lumping rule ...")
    results["flex_paper_rule"] = simulate(params, Protocol.flex(lumping="paper"), t_end_s=t_end_s, grid=flex_grid, beam=beam,
                                          progress=progress)
    return results


def _batch(params, protocols: list, t_end_s, grid, beam) -> list:
    """`simulate` of `protocols` (equal but for their floats) as one program, its runs
    split over the devices (`sweep.map_over_devices`; padded to a multiple of their
    count): a Result per protocol. On one device, one run after another with
    `simulate`'s own program (the same work, and no second program to compile)."""
    from .sweep import even_batches

    if len(jax.devices()) == 1:
        return [simulate(params, q, t_end_s, grid, beam=beam) for q in protocols]
    n = even_batches(len(protocols), len(protocols))
    padded = protocols + protocols[-1:] * (n - len(protocols))
    stacked = jax.tree_util.tree_map(lambda *x: np.stack([np.asarray(v, float) for v in x]), *padded)
    out = jax.device_get(cache.call(_over_devices, params, stacked, t_end_s, grid, beam, n))
    # split on the host: indexing device arrays would compile a gather for every leaf
    return [jax.tree_util.tree_map(lambda x, i=i: jax.device_put(x[i]), out) for i in range(len(protocols))]


@eqx.filter_jit
def _over_devices(params, protocols, t_end_s, grid, beam, n):
    from .sweep import map_over_devices

    return map_over_devices(lambda q: simulate(params, q, t_end_s, grid, beam=beam), n)(protocols)


def _three_week_index(result) -> int:
    """The index of the save time at 3 weeks (the last one of a shorter run)."""
    return result.index(min(THREE_WEEKS_S, result.ts[-1]))


def three_week(result) -> dict:
    """The values at 3 weeks (at the end of a shorter run)."""
    i = _three_week_index(result)
    return {k: float(getattr(result, k)[i]) for k in KEYS}


def _when(result) -> str | None:
    """None at 3 weeks, else the time that `three_week` reads ("t = … s") for a run
    that stops short of it."""
    t = result.ts[_three_week_index(result)]
    return None if abs(t - THREE_WEEKS_S) < 1.0 else f"t = {t:g} s"


def extrapolations(results: dict, params) -> list[str]:
    """One line for each value of the cases (`params`, protocols, end time) outside its
    supported range (`limits.extrapolation`): `summary.json`'s and the report's warnings."""
    lines = limits.extrapolation(params, None, max(r.ts[-1] for r in results.values()))
    for protocol in CASES.values():
        lines += limits.extrapolation(None, protocol)
    return list(dict.fromkeys(lines))


def write(results: dict, params, folder, bands: dict | None = None) -> None:
    """Figures, per-case NetCDF files, summary.json and report.md into `folder`
    (`write_cases`, then `write_report`); `bands` (`calibrated_bands`) add the
    calibrated model to Figs 9 and 10."""
    write_cases(results, folder)
    write_report(results, params, folder, bands)


def write_cases(results: dict, folder) -> None:
    """What needs no posterior: Figs 5, 7 and 8 and the per-case NetCDF files (the
    command line draws them while the posterior draws run)."""
    plots.profiles(results["static"], folder / "fig5_profiles_static.png", "static culture")
    plots.profiles(results["flex"], folder / "fig7_profiles_flex.png", "flex 1 Hz, 5 mm")
    plots.ecm_maps({k: results[k] for k in ("static", "flex", "flex_paper_rule")}, folder / "fig8_ecm_maps.png")
    (folder / "cases").mkdir()
    for name, r in results.items():
        io.write_netcdf(r.contents(), folder / "cases" / f"{name}.nc")


def write_report(results: dict, params, folder, bands: dict | None = None) -> None:
    """Figs 9 and 10 (with the calibrated model's `bands`), summary.json and report.md."""
    main = {k: results[k] for k in CASES}
    plots.time_series(main, folder / "fig9_contents.png", bands)
    plots.rigidity_and_force(main, folder / "fig10_rigidity_force.png", bands)
    summary = {name: three_week(r) for name, r in results.items()}
    summary["params"] = params.as_dict()
    summary["warnings"] = extrapolations(results, params)
    if bands:
        summary["calibrated"] = {name: {k: {"q05": float(b[k][0][-1]), "q50": float(b[k][1][-1]), "q95": float(b[k][2][-1])} for k in KEYS}
                                 for name, b in bands.items()}
    io.write_json(folder / "summary.json", summary)
    io.atomic_write_text(folder / "report.md", report(results, params, bands))


def _data_cell(quantity, regime):
    obs = [o for o in observations(quantity, regime) if o.regime == regime]
    return f"{obs[0].mean:g} ± {obs[0].sd:g}" if obs else "—"


def _calibrated_lines(bands: dict | None) -> list[str]:
    if not bands:
        return ["", "No calibrated posterior is shipped with this installation, so Figs 9 and 10 show the paper's parameters only."]
    b = next(iter(bands.values()))
    out = ["", "## The calibrated model", "",
           f"Dashed lines and shaded bands in Figs 9 and 10: median and 90 % band of the model over {b['draws']} draws of the "
           "shipped posterior of the Engelmayr calibration (`jaxtissue calibrate calibrate/engelmayr2005.toml --posterior`; "
           "draws simulated at that calibration's resolution, not fitted on the fly). "
           + (f"**Its chains have not converged** (largest R-hat {b['r_hat_max']:.3f} > 1.01): read the bands as indicative. "
              if b["r_hat_max"] > 1.01 else f"Its chains have converged (largest R-hat {b['r_hat_max']:.3f}). ")
           + "At the end of the run:", "",
           "| case | DNA (µg/g) | collagen (mg/g) | E_eff (kPa) |", "|---|---|---|---|"]
    for name, b in bands.items():
        cells = [f"{b[k][1][-1]:.4g} [{b[k][0][-1]:.4g}, {b[k][2][-1]:.4g}]" for k in ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa")]
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    return out


def report(results: dict, params, bands: dict | None = None) -> str:
    s = {name: three_week(r) for name, r in results.items()}
    when = _when(results["static"])
    lines = [
        "# Reproduction of Soares & Sacks (2016): static and flexed culture",
        "",
        f"Lumping rule: dispersive (default), C = {params.lumping_C:g}; growth grid "
        f"{results['flex'].final.m.shape[0]} × {results['flex'].final.m.shape[1]}; "
        + ("3-week values (t = 1.8144e6 s)." if when is None else f"values at {when} (the run ends before 3 weeks); the data are at 3 weeks."),
        "",
        "| case | DNA (µg/g) | collagen (mg/g) | E_eff (kPa) | peak post force (mN) |",
        "|---|---|---|---|---|",
    ]
    for name, v in s.items():
        force = "—" if name == "static" else f"{1e3 * v['post_force_max_N']:.2f}"
        lines.append(f"| {name} | {v['dna_ug_per_g']:.1f} | {v['collagen_mg_per_g']:.3f} | {v['E_eff_kPa']:.0f} | {force} |")
    for regime in ("static", "flex"):
        lines.append(
            f"| Engelmayr {regime} | {_data_cell('dna_ug_per_g', regime)} | "
            f"{_data_cell('collagen_mg_per_g', regime)} | {_data_cell('E_eff_kPa', regime)} | — |"
        )
    c = {k: v["collagen_mg_per_g"] for k, v in s.items()}
    d = {k: v["dna_ug_per_g"] for k, v in s.items()}
    freq_spread = c["flex_2Hz"] - c["flex_0.5Hz"]
    amp_spread = c["flex_10mm"] - c["flex_2.5mm"]
    ei = {k: np.asarray(results[k].EI_N_m2) for k in CASES}
    force = np.asarray(results["flex"].post_force_max_N)
    lines += [
        "",
        "## Findings",
        "",
        f"* Flex versus static at {when or '3 weeks'}: collagen × {c['flex'] / c['static']:.3f} "
        f"(data × {0.846 / 0.546:.3f}), DNA × {d['flex'] / d['static']:.3f} (data × {344 / 307:.3f}).",
        f"* Frequency: collagen {c['flex_0.5Hz']:.3f} (0.5 Hz) → {c['flex']:.3f} (1 Hz) → {c['flex_2Hz']:.3f} (2 Hz); "
        f"amplitude: {c['flex_2.5mm']:.3f} (2.5 mm) → {c['flex']:.3f} (5 mm) → {c['flex_10mm']:.3f} (10 mm).",
        f"* The 0.5 ↔ 2 Hz spread of collagen ({freq_spread:+.3f} mg/g) is "
        + ("larger" if abs(freq_spread) > abs(amp_spread) else "smaller")
        + f" than the 2.5 ↔ 10 mm spread ({amp_spread:+.3f} mg/g)"
        + (", as the paper found." if abs(freq_spread) > abs(amp_spread) else
           ", unlike the paper: in this beam model the dispersive supply grows with the"
           " seepage speed, which scales with both frequency and curvature."),
        f"* EI rises over time in every case ({min(e[-1] / e[0] for e in ei.values()):.2f}–"
        f"{max(e[-1] / e[0] for e in ei.values()):.2f} × its initial value); the peak post force at "
        f"1 Hz / 5 mm rises from {1e3 * force[0]:.2f} to {1e3 * force[-1]:.2f} mN.",
        f"* The paper's literal rule (signed mean velocity over one cycle from rest, C = "
        f"{float(results['flex_paper_rule'].params.lumping_C):g}) gives collagen × "
        f"{c['flex_paper_rule'] / c['static']:.3f} and DNA × {d['flex_paper_rule'] / d['static']:.3f} "
        "against static: the from-rest mean flow is small, symmetric about the mid-plane and not "
        "divergence-free, so it does not reproduce the enhanced supply of the experiments; the "
        "dispersive rule (default) does (docs/model.md §5).",
        "",
        "Figures: `fig5_profiles_static.png`, `fig7_profiles_flex.png`, `fig8_ecm_maps.png`, "
        "`fig9_contents.png`, `fig10_rigidity_force.png`; per-case results in `cases/*.nc`.",
    ]
    lines += _calibrated_lines(bands)
    warned = extrapolations(results, params)
    if warned:
        lines += ["", "## Warnings", ""] + [f"* {line}" for line in warned]
    return "\n".join(lines) + "\n"
