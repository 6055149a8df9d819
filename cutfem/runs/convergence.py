"""Convergence plots: errors against h on log-log axes with fitted rates and rate triangles.

Everything here draws on a :class:`matplotlib.figure.Figure` with its own Agg canvas
(:func:`new_figure`), so nothing in matplotlib's global state (the pyplot backend, the list of open
figures) is touched.  Text sizes come from :data:`STYLE`, applied with :func:`style` around the
drawing *and* the saving (matplotlib reads some font sizes only when it draws).

The rate of a curve is the least-squares slope of ``log e`` against ``log h`` over all points with
``e > 0`` (:func:`cutfem.fem.norms.fitted_rate`, the project's one fit).  A rate triangle (:func:`rate_triangle`) is a right triangle whose
hypotenuse has slope ``order`` on the log-log axes, with its legs labelled ``1`` and ``order``.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np

from ..fem.norms import fitted_rate

__all__ = [
    "STYLE",
    "convergence_plot",
    "log_ticks",
    "loglog_with_rates",
    "new_figure",
    "plotted_keys",
    "rate_triangle",
    "save_reproducible",
    "significant",
    "style",
]

#: significant digits of the numbers cutfem writes to its tables (see :func:`significant`)
SIGNIFICANT_DIGITS = 6

#: matplotlib settings for figures drawn at the size they print: every text 8 pt (titles 9 pt).
STYLE = {
    "font.size": 8,
    "axes.titlesize": 9,
    "axes.labelsize": 8,
    "xtick.labelsize": 8,
    "ytick.labelsize": 8,
    "legend.fontsize": 8,
    "legend.title_fontsize": 8,
    "figure.titlesize": 9,
    "lines.markersize": 4,
    "lines.linewidth": 1.2,
    "axes.linewidth": 0.6,
    "grid.linewidth": 0.4,
    "legend.handlelength": 2.2,
    "legend.borderaxespad": 0.3,
    "legend.labelspacing": 0.3,
}


def style():
    """A context in which matplotlib uses :data:`STYLE` (``matplotlib.rc_context``); the settings
    before it are restored on exit."""
    import matplotlib

    return matplotlib.rc_context(STYLE)


def new_figure(width: float, height: float, **subplots):
    """``(fig, axes)``: a Figure of exactly ``width`` x ``height`` inches with constrained layout
    and an Agg canvas; ``subplots`` go to :meth:`Figure.subplots` (``nrows``, ``ncols``,
    ``sharex``, ``gridspec_kw`` ...; ``nrows=0`` gives no axes, ``axes`` is then None).

    The size is the printed size: a figure saved by :func:`save_reproducible` keeps it (no tight
    bounding box), so that a document includes it at scale 1."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not (np.isfinite(width) and np.isfinite(height) and width > 0 and height > 0):
        raise ValueError(f"a figure needs a positive finite width and height in inches, got {width!r} x {height!r}")
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    if subplots.get("nrows", 1) == 0:
        return fig, None
    return fig, fig.subplots(**subplots)


def significant(data, digits: int = SIGNIFICANT_DIGITS, exact=frozenset()):
    """``data`` (a float, or nested dicts, lists, tuples and numpy arrays) with every float rounded
    to ``digits`` significant decimal digits; integers, booleans, strings, None, NaN and infinities
    are left as they are, numpy scalars become Python numbers and arrays lists.

    Why: a sum computed in another order (another thread count, BLAS, processor) differs in its
    last one or two digits, about 1e-14 relative for the studies' errors and rates and 1e-11 at
    worst.  Six digits keep every digit a measurement supports and drop those, so the same run on
    another machine writes the same bytes unless a value lies within 1e-11 of a rounding boundary
    (about one chance in 10^5 per number).  The rounding is decimal and exact:
    ``float(f"{x:.5e}")``, whose shortest repr is what JSON and CSV then print.

    ``exact``: dict keys whose values are left whole (inputs of a run such as a mesh spacing of
    0.4/3, which must be written exactly to rerun it)."""
    if not (isinstance(digits, (int, np.integer)) and 1 <= digits <= 17):
        raise ValueError(f"digits must be an integer from 1 to 17, got {digits!r}")
    if isinstance(data, dict):
        return {k: v if k in exact else significant(v, digits, exact) for k, v in data.items()}
    if isinstance(data, list):
        return [significant(v, digits, exact) for v in data]
    if isinstance(data, tuple):
        return tuple(significant(v, digits, exact) for v in data)
    if isinstance(data, np.ndarray):
        return significant(data.tolist(), digits, exact)
    if isinstance(data, (bool, np.bool_)):
        return bool(data)
    if isinstance(data, (int, np.integer)):
        return int(data)
    if isinstance(data, (float, np.floating)):
        v = float(data)
        return float(f"{v:.{digits - 1}e}") if math.isfinite(v) else v
    return data


#: savefig metadata that would differ between runs or machines (dates, matplotlib's version)
FIGURE_METADATA = {".pdf": {"CreationDate": None, "ModDate": None, "Producer": None, "Creator": None},
                   ".png": {"Software": None},
                   ".svg": {"Date": None, "Creator": None}}

#: the salt of the SVG element ids (matplotlib draws a random one per file otherwise)
SVG_HASHSALT = "cutfem"


def save_reproducible(fig, path, dpi: int = 200) -> Path:
    """Save ``fig`` to ``path`` (PNG, PDF or SVG by its suffix) at its own size, without the
    creation date or software version that matplotlib writes by default (:data:`FIGURE_METADATA`)
    and with fixed SVG ids (:data:`SVG_HASHSALT`), so that the same figure gives the same bytes on
    every run.  The figure's numbers are the caller's: plot values rounded by :func:`significant`
    so that digits that differ between machines do not move a coordinate.  Returns the path."""
    import matplotlib

    path = Path(path)
    suffix = path.suffix.lower()
    metadata = FIGURE_METADATA.get(suffix)
    if metadata is None:
        raise ValueError(f"figures are saved as .png, .pdf or .svg; got {path.name!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with style(), matplotlib.rc_context({"svg.hashsalt": SVG_HASHSALT}):
        fig.savefig(path, dpi=dpi, metadata=dict(metadata))
    return path


def loglog_with_rates(ax, h, errors, label, marker="o", **kw):
    """Plot one error curve on ``ax`` (log-log) with its fitted rate in the legend label,
    ``"label (rate 1.23)"``, or the label alone when there is no rate (fewer than two points);
    points with ``e <= 0`` or NaN are left out.  Returns the rate (NaN without one)."""
    h = np.asarray(h, float)
    e = np.asarray(errors, float)
    ok = np.isfinite(e) & (e > 0) & np.isfinite(h) & (h > 0)
    rate = fitted_rate(h[ok], e[ok]) if len(np.unique(h[ok])) >= 2 else float("nan")
    ax.loglog(h[ok], e[ok], marker=marker, label=f"{label} (rate {rate:.2f})" if np.isfinite(rate) else label, **kw)
    return rate


def rate_triangle(ax, h, errors, order, *, below=True, color="0.3", size=0.5):
    """A slope triangle for the rate ``order`` next to the fine end of the curve ``(h, errors)``.

    The triangle's hypotenuse has slope ``order`` on the log-log axes; it spans the fraction
    ``size`` of the last interval ``[h[-1], h[-2]]`` in log h (the two smallest h), and sits a
    factor 1.6 below the curve (``below=True``) or above it.  The horizontal leg is labelled
    ``1``, the vertical one ``order``.  Returns the three vertices (3, 2) in data coordinates, or
    None when fewer than two positive finite errors are given."""
    from matplotlib.patches import Polygon

    h = np.asarray(h, float)
    e = np.asarray(errors, float)
    ok = np.isfinite(e) & (e > 0) & np.isfinite(h) & (h > 0)
    if ok.sum() < 2:
        return None
    h, e = h[ok], e[ok]
    idx = np.argsort(h)
    h0, h1 = h[idx[0]], h[idx[1]]
    x0 = h0 * (h1 / h0) ** ((1 - size) / 2)
    x1 = x0 * (h1 / h0) ** size
    e_at = float(np.exp(np.interp(np.log(x0), np.log(h[idx]), np.log(e[idx]))))
    shift = 1 / 1.6 if below else 1.6
    y0 = e_at * shift
    y1 = y0 * (x1 / x0) ** order
    if below:  # right angle under the hypotenuse
        verts = np.array([[x0, y0], [x1, y1], [x1, y0]])
        leg_x, leg_y = (math.sqrt(x0 * x1), y0), (x1, math.sqrt(y0 * y1))
        va, ha = "top", "left"
    else:  # right angle above it
        verts = np.array([[x0, y0], [x1, y1], [x0, y1]])
        leg_x, leg_y = (math.sqrt(x0 * x1), y1), (x0, math.sqrt(y0 * y1))
        va, ha = "bottom", "right"
    ax.add_patch(Polygon(verts, closed=True, fill=False, edgecolor=color, lw=0.8))
    ax.annotate("1", leg_x, xytext=(0, -2 if below else 2), textcoords="offset points", ha="center", va=va, color=color)
    ax.annotate(f"{order:g}", leg_y, xytext=(2 if below else -2, 0), textcoords="offset points", ha=ha, va="center", color=color)
    ax.update_datalim(verts)
    return verts


def _tick_text(v: float) -> str:
    if v <= 0 or not np.isfinite(v):
        return ""
    k = math.floor(math.log10(v) + 1e-9)
    m = v / 10.0**k
    if -3 <= k <= 3:
        return f"{v:.{max(0, -k)}f}" if abs(m - round(m)) < 1e-6 else f"{v:g}"
    m_text = "" if abs(m - 1) < 1e-6 else f"{m:g}\\cdot"
    return f"${m_text}10^{{{k}}}$"


def log_ticks(ax, axis: str = "both") -> None:
    """Readable ticks on a log axis: call after plotting (and with the figure at its final size).

    Major ticks at ``m * 10^k`` for the densest of the mantissa sets (1, 1.5, 2, 3, 5, 7),
    (1, 2, 5), (1, 3), (1,) that puts no more labels on the axis than fit side by side (one per
    0.45 in along x, one per 0.25 in along y, at the 8 pt of :data:`STYLE`); with decades only and
    still too many, every second or third decade.  Minor ticks unlabelled; labels as plain numbers
    between 1e-3 and 1e3, else as powers of ten."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    box = ax.get_position()
    fig_w, fig_h = ax.figure.get_size_inches()
    for name in ("x", "y") if axis == "both" else (axis,):
        a = ax.xaxis if name == "x" else ax.yaxis
        lo, hi = sorted(ax.get_xlim() if name == "x" else ax.get_ylim())
        if lo <= 0:
            continue
        length = box.width * fig_w if name == "x" else box.height * fig_h
        room = max(2, int(length / (0.45 if name == "x" else 0.25)))
        k = np.arange(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1)
        subs = (1.0,)
        for cand in ((1.0, 1.5, 2.0, 3.0, 5.0, 7.0), (1.0, 2.0, 5.0), (1.0, 3.0), (1.0,)):
            ticks = (np.asarray(cand)[None, :] * 10.0 ** k[:, None]).ravel()
            if np.count_nonzero((ticks >= lo) & (ticks <= hi)) <= room:
                subs = cand
                break
        a.set_major_locator(LogLocator(base=10, subs=subs, numticks=room + 1))
        a.set_minor_locator(LogLocator(base=10, subs=np.arange(2, 10) * 1.0, numticks=100))
        a.set_major_formatter(FuncFormatter(lambda v, _pos: _tick_text(v)))
        a.set_minor_formatter(NullFormatter())


def _title(result) -> str:
    params = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in sorted(result.parameters.items())
                       if v is not None)  # a parameter left to its default rule (box=None) says nothing
    head = result.problem + (f": {params}" if params else "")
    return "\n".join(textwrap.wrap(head, width=64)) or result.problem


def _h_label(result) -> str:
    """The x label: h with its definition when the problem gives one of the two built-in ones
    (:data:`cutfem.runs.registry.H_AXIS_LABELS`), else h alone."""
    from .registry import H_AXIS_LABELS

    return H_AXIS_LABELS.get(result.definitions.get("h"), "$h$")


def plotted_keys(result) -> list:
    """The error keys of ``result`` that :func:`convergence_plot` draws: those with at least one
    finite error > 0 (a key that is NaN, infinite or zero at every level would be an empty curve)."""
    def drawable(v):
        return v is not None and np.isfinite(float(v)) and float(v) > 0

    return [k for k in result.error_keys() if any(drawable(r.get(k)) for r in result.records)]


def convergence_plot(result, path, title=None, width: float = 5.0, height: float = 3.8):
    """Errors of a :class:`~cutfem.runs.runner.RunResult` against h, one curve per ``*_error`` key
    with a finite positive error (:func:`plotted_keys`) with its fitted rate in the legend and a rate triangle (slope: the rate between the two finest
    levels rounded to the nearest 1/2, left out below 1/2; one triangle per slope, under the lowest curve with it) at the fine end; the title names the
    problem and its parameters (``title`` replaces it).  Written as PNG, PDF or SVG by the suffix
    of ``path`` at ``width`` x ``height`` inches, with :data:`STYLE` fonts (8 pt); returns the path."""
    h = np.array([r["h"] for r in result.records], float)
    keys = plotted_keys(result)
    with style():
        fig, ax = new_figure(width, height)
        triangles = {}  # slope -> (h, e, colour) of the lowest curve with it
        for j, k in enumerate(keys):
            e = np.array([np.nan if r.get(k) is None else r[k] for r in result.records], float)
            color = f"C{j % 10}"
            loglog_with_rates(ax, h, e, k.replace("_", " "), marker="os^Dv<>ph*"[j % 10], color=color)
            ok = np.isfinite(e) & (e > 0)
            if ok.sum() >= 2:
                hh, ee = h[ok], e[ok]
                i = np.argsort(hh)[:2]
                last = math.log(ee[i[1]] / ee[i[0]]) / math.log(hh[i[1]] / hh[i[0]])
                order = round(2 * last) / 2
                if order >= 0.5 and (order not in triangles or ee.min() < triangles[order][1].min()):
                    triangles[order] = (hh, ee, color)
        for order, (hh, ee, color) in sorted(triangles.items()):
            rate_triangle(ax, hh, ee, order, color=color)
        ax.set_xlabel(_h_label(result))
        ax.set_ylabel("error")
        ax.set_title(title or _title(result), loc="left", fontsize=8)
        ax.grid(True, which="major", alpha=0.35)
        ax.grid(True, which="minor", alpha=0.12)
        ax.autoscale_view()
        if len(h):
            log_ticks(ax)
        if keys:
            ax.legend(loc="best")
        return save_reproducible(fig, path, dpi=200)
