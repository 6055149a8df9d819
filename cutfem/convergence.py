"""Convergence plots: errors against h on log-log axes with fitted rates (matplotlib, no display needed).

Figures are made with matplotlib's object-oriented API (:func:`new_figure`, :func:`subplots`): a
:class:`matplotlib.figure.Figure` with its own Agg canvas, never registered with pyplot, so that
drawing or saving one selects no backend and leaves the caller's pyplot state (open figures, the
interactive backend of a notebook) as it was.  ``Figure.savefig`` writes PNG through the Agg
canvas and PDF or SVG through matplotlib's vector canvases, chosen by the file's suffix.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["convergence_plot", "loglog_with_rates", "new_figure", "subplots"]


def new_figure(figsize=(6.4, 4.8), layout=None):
    """A matplotlib Figure of ``figsize`` inches (width, height) on an Agg canvas, made without pyplot.

    ``layout`` is matplotlib's layout engine name (None, "tight" or "constrained").  Nothing
    process-wide is touched; the figure is freed with its last reference (no ``close`` needed).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def subplots(nrows=1, ncols=1, *, figsize=(6.4, 4.8), constrained_layout=False, **kw):
    """(figure, axes) like ``pyplot.subplots``, but on a :func:`new_figure` (no backend touched).

    ``kw`` goes to ``Figure.subplots`` (``sharex``, ``sharey``, ``squeeze``, ...); the axes are one
    Axes for 1 x 1 and an array of shape (nrows, ncols) squeezed as pyplot does otherwise.
    """
    fig = new_figure(figsize, layout="constrained" if constrained_layout else None)
    return fig, fig.subplots(nrows, ncols, **kw)


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
    """Errors of a :class:`~cutfem.registry.RunResult` against h, with fitted rates; PNG or PDF.

    One curve per ``*_error`` entry of the records, with its least-squares rate in the legend and
    reference slopes h and h^2 through the first error; written to ``path`` (folders created, the
    format from the suffix) without touching pyplot or the matplotlib backend.  Returns the path.
    """
    h = [r["h"] for r in result.records]
    fig, ax = subplots(figsize=(5, 4))
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
    return Path(path)
