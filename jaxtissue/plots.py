"""Figures a user would otherwise draw by hand (the paper's Figs 5, 9 and 10a)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .data import observations  # noqa: E402

DAY_S = 86400.0
SERIES = (
    ("dna_ug_per_g", "DNA (µg/g ww)"),
    ("collagen_mg_per_g", "collagen (mg/g ww)"),
    ("E_eff_kPa", "effective modulus E (kPa)"),
)


def profile_days(ts, wanted=(0, 3, 7, 14, 21)):
    """Indices of the save times closest to the wanted days, and the last one."""
    ts = np.asarray(ts)
    idx = [int(np.argmin(np.abs(ts - d * DAY_S))) for d in wanted if d * DAY_S <= ts[-1] + 1]
    return sorted(set(idx + [len(ts) - 1]))


def profiles(result, path, title="static culture"):
    """Transmural O2, cell and ECM profiles at the mid-section over time (Fig. 5)."""
    ts = np.asarray(result.ts)
    y_mm = 10 * np.asarray(result.y_cm)
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8), constrained_layout=True)
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


def time_series(results: dict, path):
    """DNA, collagen and E_eff versus time with the Engelmayr data (Figs 9, 10a).

    `results` maps a label (its regime first: "static", "flex…") to a `Result`."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    for (label, result), colour in zip(results.items(), plt.cm.tab10.colors):
        days = np.asarray(result.ts) / DAY_S
        regime = "flex" if label.startswith("flex") else "static"
        for ax, (key, ylabel) in zip(axes, SERIES):
            ax.plot(days, np.asarray(getattr(result, key)), color=colour, label=f"model, {label}")
            if label in ("static", "flex"):
                obs = [o for o in observations(key, regime) if o.regime == regime]
                if obs:
                    ax.errorbar(
                        [o.time_s / DAY_S for o in obs], [o.mean for o in obs], yerr=[o.sd for o in obs],
                        fmt="o", color=colour, capsize=4, label=f"Engelmayr, {regime}",
                    )
            ax.set_xlabel("time (days)")
            ax.set_ylabel(ylabel)
    for ax, (key, _) in zip(axes, SERIES):
        seeded = [o for o in observations(key, "static") if o.regime == "seeded"]
        if seeded:
            ax.errorbar([0.0], [seeded[0].mean], yerr=[seeded[0].sd], fmt="s", color="k", capsize=4, label="Engelmayr, seeded")
    axes[0].legend(fontsize=7)
    fig.suptitle("Bulk contents and stiffness, model and Engelmayr et al. (mean ± SD)")
    fig.savefig(path, dpi=120)
    plt.close(fig)
