"""Report plots: the NR heatmap and the severity curves."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D

matplotlib.use("Agg")  # files only, no display


def plot_heatmap(summary: Mapping[str, Any], path: Path, reused: set[tuple[str, str]] = frozenset()) -> Path:
    """NR over degradation × severity, one panel per policy (RdYlGn, 0..1; NaN grey); a † marks
    the (policy, degradation) pairs in ``reused`` (the degradation misses the policy's inputs)."""
    pols = list(summary["policies"])
    cors = summary["corruptions"]
    sev = summary["severities"]
    n = len(pols)
    fig, axes = plt.subplots(1, n, figsize=(2.2 + 0.8 * len(sev) * n + 1.2, 1.3 + 0.42 * len(cors)), squeeze=False,
                             layout="constrained")
    cmap = plt.get_cmap("RdYlGn").with_extremes(bad="0.85")
    im = None
    for ax, p in zip(axes[0], pols):
        m = np.full((len(cors), len(sev)), np.nan)
        for i, c in enumerate(cors):
            for j, s in enumerate(sev):
                v = summary["policies"][p]["corruptions"][c]["severities"][str(s)]["nr"]
                m[i, j] = np.nan if v is None else v
        im = ax.imshow(np.ma.masked_invalid(m), cmap=cmap, vmin=0.0, vmax=1.0, aspect="auto")
        for i in range(len(cors)):
            for j in range(len(sev)):
                txt = "n/a" if np.isnan(m[i, j]) else f"{m[i, j]:.2f}" + ("†" if (p, cors[i]) in reused and sev[j] else "")
                ax.text(j, i, txt, ha="center", va="center", fontsize=8,
                        color="k" if np.isnan(m[i, j]) or 0.25 < m[i, j] < 0.85 else "w")
        ax.set_xticks(range(len(sev)), [str(s) for s in sev])
        ax.set_yticks(range(len(cors)), cors if ax is axes[0][0] else [""] * len(cors))
        ax.set_xlabel("severity")
        ax.set_title(p, fontsize=10)
    fig.colorbar(im, ax=axes[0].tolist(), label="normalised return NR", shrink=0.9)
    title = "Normalised return NR by degradation and severity (1 = clean, 0 = random driving)"
    if reused:
        title += "\n† not observed by the policy: its clean run stands in"
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_severity_curves(summary: Mapping[str, Any], path: Path, reused: set[tuple[str, str]] = frozenset()) -> Path:
    """NR against severity, one panel per degradation, one line per policy with its 95 % band
    (dotted, hollow markers: a policy that does not observe what the degradation corrupts)."""
    pols = list(summary["policies"])
    cors = summary["corruptions"]
    sev = summary["severities"]
    ncol = min(4, len(cors))
    nrow = int(math.ceil(len(cors) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.3 * ncol, 2.7 * nrow + 0.6), squeeze=False, sharey=True)
    colors = plt.get_cmap("tab10")
    for k, c in enumerate(cors):
        ax = axes[k // ncol][k % ncol]
        for i, p in enumerate(pols):
            cs = summary["policies"][p]["corruptions"][c]["severities"]
            y = np.array([np.nan if cs[str(s)]["nr"] is None else cs[str(s)]["nr"] for s in sev], dtype=float)
            lo = np.array([np.nan if cs[str(s)]["nr_ci"][0] is None else cs[str(s)]["nr_ci"][0] for s in sev], dtype=float)
            hi = np.array([np.nan if cs[str(s)]["nr_ci"][1] is None else cs[str(s)]["nr_ci"][1] for s in sev], dtype=float)
            if (p, c) in reused:
                ax.plot(sev, y, "o:", color=colors(i % 10), lw=1.2, ms=4, mfc="none")
            else:
                ax.plot(sev, y, "o-", color=colors(i % 10), label=p, lw=1.6, ms=4)
            ax.fill_between(sev, lo, hi, color=colors(i % 10), alpha=0.18, lw=0)
        ax.axhline(1.0, color="0.6", lw=0.8, ls="--")
        ax.axhline(0.0, color="0.6", lw=0.8, ls=":")
        ax.set_title(c, fontsize=9)
        ax.set_xticks(sev)
        ax.set_xlabel("severity (0 = clean)")
        if k % ncol == 0:
            ax.set_ylabel("NR")
        ax.grid(alpha=0.3)
    for k in range(len(cors), nrow * ncol):
        axes[k // ncol][k % ncol].set_visible(False)
    handles = [Line2D([], [], color=colors(i % 10), marker="o", lw=1.6, ms=4) for i in range(len(pols))]
    labels = list(pols)
    if reused:
        handles.append(Line2D([], [], color="0.4", marker="o", ls=":", mfc="none", ms=4))
        labels.append("not observed (clean run)")
    fig.legend(handles, labels, loc="upper center", ncol=min(len(handles), 5), fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


