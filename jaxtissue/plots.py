"""Figures a user would otherwise draw by hand (the paper's Figs 5–10, calibration and
optimisation diagnostics). Each takes what it shows as arguments and a path to write."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .data import observations  # noqa: E402
from .result import OUTPUTS  # noqa: E402

DAY_S = 86400.0
_PANELS = ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa")
"""The series of `time_series`, labelled from `OUTPUTS`."""


def _label(name: str) -> str:
    """An axis label from the output registry: its label, else description (unit)."""
    out = OUTPUTS[name]
    return out.label or f"{out.description.split(' (')[0]} ({out.unit})"


def _panel_row(ncols: int, width_in: float, height_in: float = 3.8, title: bool = True):
    """A figure of `ncols` panels side by side with margins fixed in inches (room for
    tick labels of up to ~7 characters and an axis label): constrained layout would
    measure every label by drawing the figure an extra time (~0.1 s a figure)."""
    fig, axes = plt.subplots(1, ncols, figsize=(width_in, height_in))
    left, right, gap, bottom, top = 0.85, 0.15, 0.95, 0.55, 0.45 if title else 0.15
    panel = (width_in - left - right - (ncols - 1) * gap) / ncols
    fig.subplots_adjust(left=left / width_in, right=1 - right / width_in, bottom=bottom / height_in, top=1 - top / height_in,
                        wspace=gap / panel)
    return fig, axes


def profile_days(ts, wanted=(0, 3, 7, 14, 21)):
    """Indices of the save times closest to the wanted days, and the last one."""
    ts = np.asarray(ts)
    idx = [int(np.argmin(np.abs(ts - d * DAY_S))) for d in wanted if d * DAY_S <= ts[-1] + 1]
    return sorted(set(idx + [len(ts) - 1]))


def profiles(result, path, title="static culture"):
    """Transmural O2, cell and ECM profiles at the mid-section over time (Fig. 5)."""
    ts = np.asarray(result.ts)
    y_mm = 10 * np.asarray(result.y_cm)
    fig, axes = _panel_row(3, 12)
    labels = (("profile_o", "O2  o (-)"), ("profile_c", "cells  c (-)"), ("profile_m", "ECM  m (-)"))
    colours = plt.cm.viridis(np.linspace(0, 0.9, len(profile_days(ts))))
    for ax, (key, label) in zip(axes, labels):
        data = np.asarray(getattr(result, key))
        for colour, i in zip(colours, profile_days(ts)):
            ax.plot(y_mm, data[i], color=colour, label=f"day {ts[i] / DAY_S:.1f}")
        ax.set_xlabel("y across the thickness (mm)")
        ax.set_ylabel(label)
    axes[0].axhline(float(result.params.o_m), color="grey", ls=":", lw=1)
    axes[0].text(y_mm[0], float(result.params.o_m), " ECM threshold o_m", va="bottom", fontsize=8, color="grey")
    axes[-1].legend(fontsize=8)
    fig.suptitle(f"Mid-section profiles, {title}")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _band(ax, bands, label, key, colour, scale=1.0):
    """The calibrated model's median (dashed) and 90 % band of `key` for case `label`."""
    if bands and label in bands:
        b = bands[label]
        days = np.asarray(b["time_s"]) / DAY_S
        lo, mid, hi = (scale * np.asarray(b[key][i]) for i in range(3))
        ax.fill_between(days, lo, hi, color=colour, alpha=0.18, lw=0)
        ax.plot(days, mid, color=colour, ls="--", lw=1, label=f"calibrated, {label} (median, 90 %)")


def time_series(results: dict, path, bands: dict | None = None):
    """DNA, collagen and E_eff versus time with the Engelmayr data (Figs 9, 10a).

    `results` maps a label (its regime first: "static", "flex…") to a `Result`;
    `bands` (optional) maps some labels to {"time_s": times, key: (q05, q50, q95)}:
    the calibrated model's posterior predictive, drawn beside the runs."""
    fig, axes = _panel_row(3, 13)
    for (label, result), colour in zip(results.items(), plt.cm.tab10.colors):
        days = np.asarray(result.ts) / DAY_S
        regime = "flex" if label.startswith("flex") else "static"
        for ax, key in zip(axes, _PANELS):
            ax.plot(days, np.asarray(getattr(result, key)), color=colour, label=f"model, {label}")
            _band(ax, bands, label, key, colour)
            if label in ("static", "flex"):
                obs = [o for o in observations(key, regime) if o.regime == regime]
                if obs:
                    ax.errorbar(
                        [o.time_s / DAY_S for o in obs], [o.mean for o in obs], yerr=[o.sd for o in obs],
                        fmt="o", color=colour, capsize=4, label=f"Engelmayr, {regime}",
                    )
            ax.set_xlabel("time (days)")
            ax.set_ylabel(_label(key))
    for ax, key in zip(axes, _PANELS):
        seeded = [o for o in observations(key, "static") if o.regime == "seeded"]
        if seeded:
            ax.errorbar([0.0], [seeded[0].mean], yerr=[seeded[0].sd], fmt="s", color="k", capsize=4, label="Engelmayr, seeded")
    axes[0].legend(fontsize=7)
    fig.suptitle("Bulk contents and stiffness, model and Engelmayr et al. (mean ± SD)")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def rigidity_and_force(results: dict, path, bands: dict | None = None):
    """Flexural rigidity EI and peak post force versus time (Fig. 10), with the
    calibrated model's bands (`time_series`) where given."""
    fig, axes = _panel_row(2, 10, title=False)
    for (label, result), colour in zip(results.items(), plt.cm.tab10.colors):
        days = np.asarray(result.ts) / DAY_S
        axes[0].plot(days, 1e6 * np.asarray(result.EI_N_m2), color=colour, label=label)
        _band(axes[0], bands, label, "EI_N_m2", colour, 1e6)
        if label != "static":
            axes[1].plot(days, 1e3 * np.asarray(result.post_force_max_N), color=colour, label=label)
            _band(axes[1], bands, label, "post_force_max_N", colour, 1e3)
    axes[0].set_ylabel("EI at mid-section (N mm²)")
    axes[1].set_ylabel("peak post force (mN)")
    for ax in axes:
        ax.set_xlabel("time (days)")
        ax.legend(fontsize=7)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def ecm_maps(results: dict, path):
    """The final ECM field over the strip for each case (Fig. 8)."""
    n = len(results)
    fig, axes = plt.subplots(n, 1, figsize=(10, 1.6 * n + 0.6), constrained_layout=True, squeeze=False)
    vmax = max(float(np.max(np.asarray(r.final.m))) for r in results.values())
    for ax, (label, r) in zip(axes[:, 0], results.items()):
        m = np.asarray(r.final.m)
        length, thickness = float(r.params.length_mm), float(r.params.thickness_mm)
        x_edges = np.linspace(-length / 2, length / 2, m.shape[0] + 1)
        y_edges = np.linspace(-thickness / 2, thickness / 2, m.shape[1] + 1)
        im = ax.pcolormesh(x_edges, y_edges, m.T, shading="flat", vmin=0, vmax=vmax, cmap="magma")
        ax.set_title(f"{label}: ECM m at day {float(r.ts[-1]) / DAY_S:.1f}", fontsize=9)
        ax.set_ylabel("y (mm)")
        ax.set_aspect("auto")
    axes[-1, 0].set_xlabel("x along the strip (mm)")
    fig.colorbar(im, ax=axes[:, 0].tolist(), label="m (-)")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def cycle_figures(cycle, beam, shape_path, flow_path):
    """One loading cycle: beam shapes, post displacement and force (Fig. 6, left), and
    the seepage velocity across the mid-section over the cycle (Fig. 6, right)."""
    import jax.numpy as jnp

    t = np.asarray(cycle.t)
    theta = np.asarray(cycle.fields["theta"])
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), constrained_layout=True)
    for k in np.linspace(0, len(t) - 1, 9).astype(int):
        x, y = beam.shape(jnp.concatenate([jnp.asarray(theta[k]), jnp.zeros(1)]))
        axes[0].plot(1e3 * np.asarray(x), 1e3 * np.asarray(y), label=f"t = {t[k]:.2f} s")
    axes[0].set_xlabel("x (mm)")
    axes[0].set_ylabel("y (mm)")
    axes[0].set_aspect("equal")
    axes[0].legend(fontsize=6, ncol=2)
    axes[1].plot(t, 1e3 * np.asarray(cycle.u), label="post displacement (mm)")
    axes[1].plot(t, 1e3 * np.asarray(cycle.midspan_deflection_m), label="mid-span deflection (mm)")
    axes[1].set_xlabel("t (s)")
    axes[1].legend(fontsize=8)
    axes[2].plot(t, 1e3 * np.asarray(cycle.post_force_N))
    axes[2].set_xlabel("t (s)")
    axes[2].set_ylabel("post force (mN)")
    fig.savefig(shape_path, dpi=120)
    plt.close(fig)

    mid = theta.shape[1] // 2 - 1
    vy = 100 * np.asarray(cycle.fields["vy"])[:, mid, :]  # cm/s
    y_mm = 1e3 * np.asarray(beam.geometry.y_cells(beam.ny))
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), constrained_layout=True)
    lim = np.abs(vy).max() or 1.0
    im = axes[0].pcolormesh(t, y_mm, vy.T, shading="nearest", cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=axes[0], label="v_f,y (cm/s)")
    axes[0].set_xlabel("t (s)")
    axes[0].set_ylabel("y at mid-section (mm)")
    axes[1].plot(100 * np.asarray(cycle.mean_vy)[mid], y_mm, label="(1/T)∫ v_f,y dt")
    axes[1].plot(100 * np.asarray(cycle.mean_abs_vy)[mid], y_mm, label="(1/T)∫ |v_f,y| dt")
    axes[1].set_xlabel("cycle-mean velocity (cm/s)")
    axes[1].legend(fontsize=8)
    fig.suptitle("Seepage velocity across the mid-section over one cycle from rest")
    fig.savefig(flow_path, dpi=120)
    plt.close(fig)


def waterfall(chi2, path):
    """Final χ² of every start, sorted (a flat first step = a reproducible optimum)."""
    c = np.sort(np.asarray(chi2))
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(np.arange(1, len(c) + 1), c, "o-", ms=4)
    ax.set(xlabel="start (sorted)", ylabel="final χ²", yscale="log", title="multi-start waterfall")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def fit_against_data(observations, model, path, band=None):
    """Data (mean ± SD) and the fitted model, one panel per observable; `band`: a
    (2, observations) posterior predictive interval drawn around each model value."""
    names = list(dict.fromkeys(o.quantity for o in observations))
    fig, axes = plt.subplots(1, len(names), figsize=(3.6 * len(names), 3.4), squeeze=False)
    for ax, name in zip(axes[0], names):
        rows = [(k, o) for k, o in enumerate(observations) if o.quantity == name]
        labels = [f"{o.regime}\n{o.time_s / DAY_S:.0f} d" for _, o in rows]
        x = np.arange(len(rows))
        ax.errorbar(x, [o.mean for _, o in rows], yerr=[o.sd for _, o in rows], fmt="o", color="k", capsize=3, label="data")
        ax.plot(x, [model[k] for k, _ in rows], "s", color="C3", label="model")
        if band is not None:
            ax.vlines(x + 0.12, [band[0][k] for k, _ in rows], [band[1][k] for k, _ in rows], color="C3", lw=4, alpha=0.35,
                      label="90 % predictive")
        ax.set_xticks(x, labels)
        ax.set_title(name)
    axes[0][0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def correlation(names, corr, path):
    """Parameter correlations of the Laplace approximation."""
    fig, ax = plt.subplots(figsize=(1.2 * len(names) + 2, 1.0 * len(names) + 1.5))
    im = ax.imshow(corr, vmin=-1, vmax=1, cmap="RdBu_r")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_yticks(range(len(names)), names)
    for i in range(len(names)):
        for j in range(len(names)):
            ax.text(j, i, f"{corr[i, j]:.2f}", ha="center", va="center", fontsize=8)
    fig.colorbar(im, ax=ax, label="correlation")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def likelihood_profiles(profiles, chi2_min, threshold, best, path):
    """Profile likelihood of each free parameter with the 95 % threshold."""
    n = len(profiles)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.2 * rows), squeeze=False)
    for ax, pr in zip(axes.flat, profiles):
        ax.plot(pr.values, pr.chi2, "o-", ms=3)
        ax.axhline(chi2_min + threshold, color="grey", ls="--", lw=1, label="95 % threshold")
        ax.axvline(best[pr.name], color="C3", lw=1, label="optimum")
        ax.set(xlabel=pr.name, ylabel="profile χ²", title=("" if pr.identifiable else "not identifiable: ") + pr.name)
    for ax in axes.flat[n:]:
        ax.axis("off")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def sensitivities(table, path, title=""):
    """Normalised sensitivities d ln(output)/d ln(parameter), one panel per output;
    parameters with |S| < 1e-3 everywhere are left out."""
    names = [n for n in next(iter(table.values())) if max(abs(t[n]) for t in table.values()) >= 1e-3]
    fig, axes = plt.subplots(1, len(table), figsize=(3.2 * len(table) + 1.5, 0.28 * len(names) + 1.5), sharey=True, squeeze=False)
    y = np.arange(len(names))
    for ax, (key, row) in zip(axes[0], table.items()):
        ax.barh(y, [row[n] for n in names], color=["C3" if row[n] < 0 else "C0" for n in names])
        ax.axvline(0, color="k", lw=0.8)
        ax.set_title(key, fontsize=9)
        ax.set_xlabel("d ln(output) / d ln(parameter)", fontsize=8)
    axes[0][0].set_yticks(y, names, fontsize=8)
    axes[0][0].invert_yaxis()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def protocol_landscape(periods_s, displacements_mm, objective, feasible, paths, best, grid_best, baseline, label, path):
    """The objective over a grid of constant protocols (`objective` and `feasible`:
    (periods, displacements); infeasible points hatched), each start's optimisation
    path (`paths`: (iterates, starts, stages, 2); for a schedule each stage's (period,
    displacement)), the optimum `best` (stages, 2) or None, the best grid point and
    the reference protocol (dicts of period_s and post_displacement_mm)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    P, U = np.meshgrid(periods_s, displacements_mm, indexing="ij")
    cs = ax.contourf(P, U, objective, levels=20, cmap="viridis")
    fig.colorbar(cs, ax=ax, label=label)
    if not np.all(feasible):
        ax.contourf(P, U, (~feasible).astype(float), levels=[0.5, 1.5], colors="none", hatches=["//"])
        ax.contour(P, U, feasible.astype(float), levels=[0.5], colors="w", linewidths=1.0)
    for i in range(paths.shape[1]):
        for k in range(paths.shape[2]):
            ax.plot(paths[:, i, k, 0], paths[:, i, k, 1], "-", color="w", lw=0.8, alpha=0.8)
            ax.plot(paths[0, i, k, 0], paths[0, i, k, 1], "o", color="w", ms=3)
    if best is not None:
        ax.plot(best[:, 0], best[:, 1], "*", color="r", ms=14, mec="k", label="gradient optimum", zorder=5)
    if grid_best is not None:
        ax.plot(grid_best["period_s"], grid_best["post_displacement_mm"], "s", mfc="none", mec="orange", ms=10, mew=2, label="best grid point")
    ax.plot(baseline["period_s"], baseline["post_displacement_mm"], "D", color="k", ms=6, label="paper (1 Hz, 5 mm)")
    ax.set(xscale="log", xlabel="period T (s)", ylabel="post displacement u_max (mm)",
           title="objective over constant protocols" + ("" if np.all(feasible) else " (hatched: infeasible)"))
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def optimisation_history(objective, feasible, grid_best, baseline, title, unit, path):
    """Objective per Adam step for every start (`objective`, `feasible`: (steps,
    starts); feasible iterates filled), with the best grid point's objective (or None)
    and the reference protocol's for comparison."""
    fig, ax = plt.subplots(figsize=(6, 3.8))
    steps = np.arange(objective.shape[0])
    for i in range(objective.shape[1]):
        line, = ax.plot(steps, objective[:, i], "-", lw=1, label=f"start {i}")
        ax.plot(steps[feasible[:, i]], objective[feasible[:, i], i], "o", ms=3, color=line.get_color())
    if grid_best is not None:
        ax.axhline(grid_best, color="orange", ls="--", label="best grid point")
    ax.axhline(baseline, color="k", ls=":", label="paper protocol")
    ax.set(xlabel="Adam step", ylabel=unit, title=f"{title} (dots: constraints met)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def schedule(best, stage_length_s, constant, path):
    """A schedule's period and post displacement per stage (`best`: (stages, 2)),
    against the best constant protocol (a dict of period_s and post_displacement_mm,
    or None)."""
    weeks = np.arange(best.shape[0] + 1) * stage_length_s / (7 * DAY_S)
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
    for ax, k, key, label in ((axes[0], 0, "period_s", "period T (s)"), (axes[1], 1, "post_displacement_mm", "post displacement (mm)")):
        ax.stairs(best[:, k], weeks, lw=2, label="optimal schedule")
        if constant is not None:
            ax.axhline(constant[key], color="orange", ls="--", label="best constant (grid)")
        ax.set(xlabel="stage start (weeks)", ylabel=label)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def posterior_pairs(names, draws, diverging, path, reference=None):
    """Pair plot of posterior draws (chains, draws, k): histograms on the diagonal,
    scatter below it, divergent transitions in red, `reference` values (e.g. the fit's
    optimum) as lines."""
    x = np.asarray(draws).reshape(-1, len(names))
    bad = np.asarray(diverging).ravel()
    k = len(names)
    fig, axes = plt.subplots(k, k, figsize=(1.9 * k + 1, 1.9 * k + 1), squeeze=False)
    for i in range(k):
        for j in range(k):
            ax = axes[i][j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(x[:, i], bins=30, color="C0", alpha=0.8)
                ax.set_yticks([])
            else:
                ax.plot(x[~bad, j], x[~bad, i], ".", ms=1.5, alpha=0.4, color="C0")
                ax.plot(x[bad, j], x[bad, i], ".", ms=4, color="C3")
                if reference is not None:
                    ax.axhline(reference[i], color="k", lw=0.6)
            if reference is not None:
                ax.axvline(reference[j], color="k", lw=0.6)
            if i == k - 1:
                ax.set_xlabel(names[j], fontsize=8)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(names[i], fontsize=8)
            elif j > 0:
                ax.set_yticklabels([])
            ax.tick_params(labelsize=6)
    fig.suptitle(f"posterior draws ({len(x)}; divergent in red: {int(bad.sum())}); lines: best fit", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def posterior_traces(names, draws, path):
    """Trace of each free parameter, one line per chain, with its histogram per chain."""
    d = np.asarray(draws)
    k = len(names)
    fig, axes = plt.subplots(k, 2, figsize=(9, 1.6 * k + 0.6), squeeze=False, gridspec_kw={"width_ratios": [3, 1]})
    for i, name in enumerate(names):
        for c in range(d.shape[0]):
            axes[i][0].plot(d[c, :, i], lw=0.5, color=f"C{c % 10}")
            axes[i][1].hist(d[c, :, i], bins=25, histtype="step", color=f"C{c % 10}", orientation="horizontal")
        axes[i][0].set_ylabel(name, fontsize=8)
        axes[i][1].set_yticklabels([])
        for ax in axes[i]:
            ax.tick_params(labelsize=6)
    axes[-1][0].set_xlabel("draw")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def predictive_bands(times_s, bands: dict, data: dict, title, path):
    """Posterior predictive median and 90 % band of each output over time (days), with
    the data (mean ± SD) it was conditioned on. `bands`: name -> (q05, q50, q95) arrays;
    `data`: name -> [(time_s, mean, sd, condition), ...]."""
    names = list(bands)
    cols = min(3, len(names))
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.1 * rows), squeeze=False)
    days = np.asarray(times_s) / DAY_S
    for ax, name in zip(axes.flat, names):
        lo, mid, hi = bands[name]
        ax.fill_between(days, lo, hi, color="C0", alpha=0.3, label="90 % band")
        ax.plot(days, mid, color="C0", label="median")
        for k, (t, mean, sd, condition) in enumerate(data.get(name, [])):
            ax.errorbar([t / DAY_S], [mean], yerr=[sd], fmt="o", color="k", capsize=3, label="data" if k == 0 else None)
        ax.set(xlabel="time (days)", ylabel=_label(name))
    for ax in axes.flat[len(names):]:
        ax.axis("off")
    axes[0][0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
