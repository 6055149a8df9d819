"""Convergence plots: errors against h on log-log axes with fitted rates (matplotlib, no display needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["convergence_plot", "loglog_with_rates"]


def loglog_with_rates(ax, h, errors, label, marker="o", **kw):
    """Plot one error curve on ``ax`` and put its least-squares rate in the legend label."""
    h = np.asarray(h, float)
    e = np.asarray(errors, float)
    ok = np.isfinite(e) & (e > 0)
    rate = float(np.polyfit(np.log(h[ok]), np.log(e[ok]), 1)[0]) if ok.sum() >= 2 else float("nan")
    ax.loglog(h[ok], e[ok], marker=marker, label=f"{label} (rate {rate:.2f})", **kw)
    return rate


def _reference_slope(ax, h, e, order, style=":"):
    h = np.asarray(h, float)
    ref = e * (h / h[0]) ** order
    ax.loglog(h, ref, style, color="gray", lw=1)
    ax.annotate(f"$h^{order}$", (h[-1], ref[-1]), color="gray", fontsize=8)


def convergence_plot(result, path, title=None):
    """Errors of a :class:`~cutfem.registry.RunResult` against h, with fitted rates; PNG or PDF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = [r["h"] for r in result.records]
    fig, ax = plt.subplots(figsize=(5, 4))
    for k in result.error_keys():
        e = [r.get(k, np.nan) for r in result.records]
        loglog_with_rates(ax, h, e, k.replace("_", " "))
    keys = result.error_keys()
    if keys:
        e0 = result.records[0][keys[0]]
        _reference_slope(ax, h, e0, 1)
        _reference_slope(ax, h, e0, 2, "--")
    ax.set_xlabel("h")
    ax.set_ylabel("error")
    ax.set_title(title or result.problem)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150)
    plt.close(fig)
    return Path(path)
