"""What every study shares: sizes, output folders, progress, JSON/CSV/LaTeX tables, figures.

A study is a module with a function ``run(out: Path, size: str, progress) -> dict`` that writes its
numbers (JSON, and CSV or LaTeX tables) and figures (PNG and PDF) into ``out`` and returns a summary
dict, plus ``main = study_main(run, "name")`` so that it runs as
``python -m cutfem.studies.NAME [--out DIR] [--tiny | --quick | --full]``.

Sizes: ``tiny`` (seconds, for the tests), ``quick`` (the default: all studies together in a few
minutes on 2 cores), ``full`` (the paper's finest levels).
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

from cutfem.runs.convergence import SIGNIFICANT_DIGITS, save_reproducible, significant, style
from cutfem.memory import configure
from cutfem.runs.registry import ProblemError
from cutfem.runs.runner import check_output, compile_notice, jsonable, text_table

SIZES = ("tiny", "quick", "full")


def pick(size: str, tiny, quick, full):
    """The value for a size."""
    return {"tiny": tiny, "quick": quick, "full": full}[size]


class Progress:
    """One line per step on standard error: ``[study] step (i/n) ... 1.23 s``."""

    def __init__(self, study: str, enabled: bool = True):
        self.study, self.enabled, self.t0 = study, enabled, time.perf_counter()

    def __call__(self, message: str):
        if self.enabled:
            print(f"[{self.study} {time.perf_counter() - self.t0:7.1f}s] {message}", file=sys.stderr, flush=True)


#: |values| below this, of a quantity that is zero in exact arithmetic (the integral of H_h over
#: a closed S_h), are round-off: the studies write them as 0 and the tables as "< 1e-10".  The
#: measured values are 1e-16 to 1e-12 and change with the order of the sums; the tests and the
#: paper's claim ask for less than 1e-10 and 1e-8.
ROUNDOFF_INTEGRAL = 1e-10


def roundoff_zero(values, floor: float = ROUNDOFF_INTEGRAL):
    """``values`` (a number or a sequence) with the entries of modulus below ``floor`` replaced by
    0.0: a quantity that vanishes in exact arithmetic, whose computed digits are round-off that
    differs between machines and thread counts.  NaN and larger values are kept (they are news)."""
    if np.ndim(values) == 0:
        v = float(values)
        return 0.0 if abs(v) < floor else v
    return [roundoff_zero(v, floor) for v in values]


def fmt_roundoff(x, floor: float = ROUNDOFF_INTEGRAL) -> str:
    """A round-off quantity for a LaTeX table: ``$<10^{-10}$`` below ``floor``, else ``1.2e-09``
    (``--`` for NaN or None)."""
    if x is None or not np.isfinite(x):
        return "--"
    return f"$<10^{{{int(round(np.log10(floor)))}}}$" if abs(x) < floor else f"{x:.1e}"


#: keys whose values are the inputs of a run (mesh spacings, shifts, time steps, boxes): written
#: whole by :func:`save_json` and :func:`save_csv`, so that a table can be rerun (a spacing of 0.4/3
#: at six digits is another mesh); they are the same on every machine
INPUT_KEYS = frozenset({"spacing", "spacings", "levels", "shift", "dt", "box", "center"})


def save_json(out: Path, name: str, data, digits: int = SIGNIFICANT_DIGITS) -> Path:
    """``data`` as ``OUT/name.json``: every float to ``digits`` significant digits
    (:func:`cutfem.runs.convergence.significant`: six, the digits that do not depend on the machine or
    the thread count) but the inputs under :data:`INPUT_KEYS`, keys sorted, two-space indent,
    trailing newline, so that the same measurement gives the same bytes on every machine."""
    path = Path(out) / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(significant(jsonable(data), digits, INPUT_KEYS), indent=2, sort_keys=True) + "\n")
    return path


def save_csv(out: Path, name: str, rows: list[dict], digits: int = SIGNIFICANT_DIGITS) -> Path:
    """``rows`` as ``OUT/name.csv``, one column per key (in order of first appearance), every float
    to ``digits`` significant digits as in :func:`save_json`."""
    path = Path(out) / f"{name}.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: jsonable(v) if k in INPUT_KEYS else significant(jsonable(v), digits) for k, v in r.items()})
    return path


def latex_cell(cell) -> str:
    """A table cell as LaTeX: text outside $...$ gets _ % & # escaped; math is left alone."""
    text = str(cell)
    parts = text.split("$")
    for i in range(0, len(parts), 2):  # even parts are outside math
        for ch in "_%&#":
            parts[i] = parts[i].replace("\\" + ch, ch).replace(ch, "\\" + ch)
    return "$".join(parts)


def plain_cell(cell) -> str:
    """A LaTeX table cell as plain text for the terminal: no $, braces or backslashes
    (``$\\tau_F$`` -> ``tau_F``, ``$h^{-1}$`` -> ``h^-1``)."""
    return re.sub(r"\\([A-Za-z]+)", r"\1", str(cell)).replace("$", "").replace("{", "").replace("}", "").replace("\\", "")


def save_latex_table(out: Path, name: str, header: list[str], rows: list[list], caption: str = "", label: str | None = None) -> Path:
    """A booktabs-free LaTeX tabular (only \\hline), numbers formatted by the caller; ``caption``
    is written above it as a comment (what the table holds, for a reader of the file: the
    manuscript's caption is its own).  The table is also printed on standard output as plain text
    (:func:`plain_cell`), under its caption and file name."""
    title = f"{name}.tex" + (f": {' '.join(caption.split())}" if caption else "")
    table = text_table([plain_cell(c) for c in header], [[plain_cell(c) for c in row] for row in rows], left=1)
    print(f"{title}\n{table}\n", flush=True)
    path = Path(out) / f"{name}.tex"
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = "l" + "r" * (len(header) - 1)
    comment = [f"% {line}" for line in caption.splitlines()] if caption else []
    lines = comment + [f"\\begin{{tabular}}{{{cols}}}", "\\hline", " & ".join(latex_cell(h) for h in header) + " \\\\", "\\hline"]
    lines += [" & ".join(latex_cell(c) for c in row) + " \\\\" for row in rows]
    lines += ["\\hline", "\\end{tabular}"]
    path.write_text("\n".join(lines) + "\n")
    return path


#: printed width of a full-width figure in paper/main.tex (A4 with 2.5 cm margins): 16 cm
PAGE_WIDTH = 6.3


def figure_style(plot):
    """Decorator: run a plotting function with the 8 pt fonts of :data:`cutfem.runs.convergence.STYLE`
    (a ``matplotlib.rc_context``; the settings before it are restored)."""

    @functools.wraps(plot)
    def styled(*args, **kwargs):
        with style():
            return plot(*args, **kwargs)

    return styled


def read_png(path):
    """A PNG as a float array (rows, cols, channels) in [0, 1], cropped to its drawn part plus
    5 pixels (a white margin is removed)."""
    import matplotlib.image

    img = matplotlib.image.imread(path)
    ink = (img[..., :3] < 0.99).any(axis=2)
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    if rows.size == 0:
        return img
    return img[max(rows[0] - 5, 0) : rows[-1] + 6, max(cols[0] - 5, 0) : cols[-1] + 6]


def save_figure(fig, out: Path, name: str) -> list[Path]:
    """Save a figure as PNG (200 dpi) and PDF at its own size (the size it prints at: no tight
    bounding box), without dates or version strings, so that an unchanged figure gives unchanged
    files."""
    out = Path(out)
    return [save_reproducible(fig, out / f"{name}.png", dpi=200), save_reproducible(fig, out / f"{name}.pdf", dpi=200)]


def fmt_rate(r) -> str:
    return "--" if r is None or not np.isfinite(r) else f"{r:.2f}"


def add_size_arguments(parser) -> None:
    """The mutually exclusive --tiny / --quick / --full flags (stored as ``size``) and --quiet."""
    g = parser.add_mutually_exclusive_group()
    for size in SIZES:
        g.add_argument(f"--{size}", dest="size", action="store_const", const=size)
    parser.add_argument("--quiet", action="store_true")


def torus_family(family: str, seed: int) -> dict:
    """The parameters of a meshed torus family for ``cutfem.run``: the family, and the seed for the
    families drawn at random (the structured grid takes none)."""
    from cutfem.geometry.surface_meshes import RANDOM_FAMILIES

    return {"family": family, **({"seed": seed} if family in RANDOM_FAMILIES else {})}


def study_main(run, name: str, options=None):
    """A ``main(argv)`` for ``python -m cutfem.studies.NAME``; it applies :func:`cutfem.memory.configure`.

    ``options``: an ``argparse.ArgumentParser(add_help=False)`` with the study's own options; they
    join the usual ones (``--out``, the size flags, ``--quiet``) in one parser and one help, and
    are handed to ``run`` as keywords (their ``dest`` names)."""

    def main(argv=None) -> int:
        p = argparse.ArgumentParser(prog=f"python -m cutfem.studies.{name}", parents=[options] if options else [])
        p.add_argument("--out", default=f"out/{name}", help="output folder")
        add_size_arguments(p)
        a = p.parse_args(argv)
        extra = {k: getattr(a, k) for k in vars(options.parse_args([]))} if options else {}
        try:
            check_output("--out", a.out, folder=True)
        except ProblemError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        configure()  # a study is a large run: opt into the allocation settings (cutfem.memory)
        t0 = time.perf_counter()
        progress = Progress(name, not a.quiet)
        with compile_notice(progress):  # Progress says nothing when quiet
            run(Path(a.out), a.size or "quick", progress, **extra)
        print(f"{name}: done in {time.perf_counter() - t0:.1f} s, results in {a.out}", file=sys.stderr)
        return 0

    return main
