"""Assembly cost on the cut torus of docs/math.md §6: how the time to build the matrices grows with the mesh.

``python -m cutfem.studies.assembly_benchmark [--out DIR] [--spacings 0.05 0.025 0.0125] [--repeat 3]
[--cold-repeat 2]``
(or ``--tiny`` / ``--quick`` / ``--full`` for preset spacings; the default is ``--quick``, the three
spacings above).

Setting: the structured Kuhn background mesh of the box [-1.6, 1.6] x [-1.6, 1.6] x [-0.6, 0.6]
with the given cube spacing, cut by the torus R = 1, r = 1/2 (:class:`cutfem.geometry.shapes.Torus`).
For each spacing we record the sizes (background nodes, h = N^(-1/3), active tets, active nodes,
interior faces, triangles of S_h, non-zeros) and wall-clock times (``time.perf_counter``) of

* ``cut``: :func:`cutfem.geometry.cut.cut_mesh` (band search, marching tetrahedra, active mesh), best of
  all the cuts made;
* ``mass``, ``stiffness``, ``face_jump``: the surface mass matrix, the tangential stiffness matrix
  and J_F (:mod:`cutfem.fem.forms`), each
  - *cold*: the first assembly on a freshly cut mesh and a new space, so it includes everything the
    form needs the first time (quadrature on S_h, basis gradients, interior faces, the sparsity
    pattern and its scatter map); best of ``cold_repeat`` fresh cuts;
  - *warm*: the best of ``repeat`` further assemblies on the same space (pattern and geometry
    cached): the cost of assembling one more matrix of that kind;
* ``together``: the three in a row on a fresh cut (cold, best of ``cold_repeat``: the element
  pattern is shared by mass and stiffness) and the best of ``repeat`` repetitions of the three
  (warm);
* seconds per million active tets for ``together`` (cold and warm).

Timings depend on the machine and its load (the reference runs share 2 cores with other jobs);
the JSON records the platform, the library versions and the CPU count next to the numbers.

Outputs in the output folder (default ``out/assembly_benchmark``): ``assembly_benchmark.json``
(all numbers), ``assembly_benchmark.csv`` (the table), ``assembly_benchmark.png`` (log-log plot
of the times against the number of active tets, with a slope-1 guide).
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np
import scipy

from cutfem.geometry.cut import CUT, cut_mesh
from cutfem.fem.forms import assemble
from cutfem.fem.terms import face_jump_penalty, mass, tangential_stiffness
from cutfem.geometry.shapes import Torus
from cutfem.memory import InsufficientMemoryError
from cutfem.geometry.box import structured_box
from cutfem.runs.registry import ProblemError
from cutfem.runs.runner import check_output, text_table
from cutfem.fem.spaces import CutSpace

from .common import PAGE_WIDTH, Progress, add_size_arguments, figure_style, pick, save_csv, save_json

NAME = "assembly_benchmark"
OUTPUTS = [NAME]
BOX = ([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6])
TORUS = (1.0, 0.5)


def _mass(V):
    return assemble(mass(V.cut.ds()), V)


def _stiffness(V):
    return assemble(tangential_stiffness(V.cut.ds()), V)


def _face_jump(V):
    return assemble(face_jump_penalty(V.cut.dF(V.cut.interior_facets(CUT))), V)


OPERATIONS = {"mass": _mass, "stiffness": _stiffness, "face_jump": _face_jump}


def spacings_for(size: str) -> list[float]:
    """Preset spacings: tiny (seconds), quick (the default of the CLI), full (adds 0.1)."""
    return pick(size, [0.2, 0.1], [0.05, 0.025, 0.0125], [0.1, 0.05, 0.025, 0.0125])


def _timed(fn, *args):
    gc.collect()
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def _fresh_space(spacing: float):
    cut, seconds = _timed(cut_mesh, structured_box(*BOX, spacing=spacing), Torus(*TORUS))
    return CutSpace(cut), seconds


def _peak_memory_mb() -> float:
    """Peak resident set size of this process so far (MB; ru_maxrss is in kB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def measure(spacing: float, repeat: int = 3, cold_repeat: int = 2) -> dict:
    """Sizes and times for one background spacing (see the module docstring).

    Cold times are the best of ``cold_repeat`` runs, each on a freshly cut mesh; warm times the best
    of ``repeat`` further runs on the last space.
    """
    row: dict = {"spacing": spacing}
    V, t_cut = _fresh_space(spacing)
    bg = V.cut.background
    row.update(
        background_nodes=bg.n_points,
        h=V.h,
        active_tets=V.n_elements,
        active_nodes=V.n_dofs,
        surface_triangles=V.cut.n_triangles,
        interior_faces=V.cut.interior_facets(CUT).n_facets,
    )
    cut_times = [t_cut]
    # each operation cold on its own fresh cut, then warm on the same space
    for name, op in OPERATIONS.items():
        colds = []
        for _ in range(cold_repeat):
            V, t_cut = _fresh_space(spacing)
            cut_times.append(t_cut)
            matrix, cold = _timed(op, V)
            colds.append(cold)
        warm = min(_timed(op, V)[1] for _ in range(repeat))
        row[f"{name}_cold"], row[f"{name}_warm"], row[f"{name}_nnz"] = min(colds), warm, matrix.nnz
        del matrix

    # the three together
    def together(space):
        for op in OPERATIONS.values():
            op(space)

    colds = []
    for _ in range(cold_repeat):
        V, t_cut = _fresh_space(spacing)
        cut_times.append(t_cut)
        colds.append(_timed(together, V)[1])
    row["cut_seconds"] = min(cut_times)
    row["together_cold"] = min(colds)
    row["together_warm"] = min(_timed(together, V)[1] for _ in range(repeat))
    million = V.n_elements / 1e6
    row["together_cold_per_million_tets"] = row["together_cold"] / million
    row["together_warm_per_million_tets"] = row["together_warm"] / million
    row["peak_memory_mb"] = _peak_memory_mb()
    return row


COLUMNS = [
    ("spacing", "spacing", "{:g}"),
    ("active_tets", "active tets", "{:d}"),
    ("active_nodes", "nodes", "{:d}"),
    ("cut_seconds", "cut", "{:.3f}"),
    ("mass_cold", "mass", "{:.3f}"),
    ("mass_warm", "(warm)", "{:.3f}"),
    ("stiffness_cold", "stiff", "{:.3f}"),
    ("stiffness_warm", "(warm)", "{:.3f}"),
    ("face_jump_cold", "J_F", "{:.3f}"),
    ("face_jump_warm", "(warm)", "{:.3f}"),
    ("together_cold", "all 3", "{:.3f}"),
    ("together_warm", "(warm)", "{:.3f}"),
    ("together_cold_per_million_tets", "s/Mtet", "{:.2f}"),
    ("together_warm_per_million_tets", "(warm)", "{:.2f}"),
]


def format_table(rows: list[dict]) -> str:
    """The measured table as fixed-width text (times in seconds)."""
    return text_table([label for _, label, _ in COLUMNS], [[fmt.format(r[key]) for key, _, fmt in COLUMNS] for r in rows])


@figure_style
def plot(rows: list[dict], out: Path) -> Path:
    from cutfem.runs.convergence import new_figure, save_reproducible

    fig, ax = new_figure(PAGE_WIDTH, 4.0)
    n = np.array([r["active_tets"] for r in rows], dtype=float)
    styles = {"mass": "C0", "stiffness": "C1", "face_jump": "C2", "together": "k"}
    labels = {"mass": "mass", "stiffness": "tangential stiffness", "face_jump": "$J_F$", "together": "all three"}
    for key, colour in styles.items():
        ax.loglog(n, [r[f"{key}_cold"] for r in rows], "o-", color=colour, label=f"{labels[key]} (first)")
        ax.loglog(n, [r[f"{key}_warm"] for r in rows], "s--", color=colour, alpha=0.7, label=f"{labels[key]} (again)")
    ax.loglog(n, [r["cut_seconds"] for r in rows], "^:", color="C3", label="cut")
    guide = max(r["together_cold"] for r in rows) / n.max()
    ax.loglog(n, guide * n, color="0.6", lw=0.8, label="slope 1")
    from matplotlib.ticker import NullFormatter

    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("active tetrahedra")
    ax.set_ylabel("wall time [s]")
    ax.set_title("Assembly on the cut torus (docs/math.md §6.3)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(ncol=2)
    return save_reproducible(fig, out / f"{NAME}.png")


def environment() -> dict:
    return {
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def run(out: Path, size: str = "quick", progress=None, spacings=None, repeat: int = 3, cold_repeat: int = 2) -> dict:
    """Measure every spacing, write JSON, CSV and the plot into ``out``; return the summary dict."""
    progress = progress or Progress(NAME, enabled=False)
    out = Path(out)
    spacings = list(spacings) if spacings else spacings_for(size)
    rows = []
    for s in spacings:
        progress(f"spacing {s:g}")
        rows.append(measure(s, repeat=repeat, cold_repeat=cold_repeat))
        progress(f"spacing {s:g}: {rows[-1]['active_tets']} active tets, all three {rows[-1]['together_cold']:.2f} s")
    data = {
        "setting": {"box": BOX, "torus": {"R": TORUS[0], "r": TORUS[1]}, "repeat": repeat, "cold_repeat": cold_repeat, "spacings": spacings},
        "environment": environment(),
        "rows": rows,
        "table": format_table(rows),
    }
    save_json(out, NAME, data)
    save_csv(out, NAME, rows)
    plot(rows, out)
    return data


def main(argv=None) -> int:
    from cutfem.memory import configure

    configure()  # a benchmark: opt into the allocation settings (cutfem.memory)
    p = argparse.ArgumentParser(prog=f"python -m cutfem.studies.{NAME}", description=__doc__.split("\n")[0])
    p.add_argument("--out", default=f"out/{NAME}", help="output folder (default out/assembly_benchmark)")
    p.add_argument("--spacings", type=float, nargs="+", help="background cube spacings (default 0.05 0.025 0.0125)")
    p.add_argument("--repeat", type=int, default=3, help="repetitions for the warm timings (best of)")
    p.add_argument("--cold-repeat", type=int, default=2, help="repetitions for the cold timings, each on a fresh cut (best of)")
    add_size_arguments(p)
    a = p.parse_args(argv)
    if a.repeat < 1 or a.cold_repeat < 1:
        p.error("--repeat and --cold-repeat must be at least 1")
    if a.spacings and not all(np.isfinite(s) and 0 < s < 0.5 for s in a.spacings):
        p.error(f"--spacings must be finite numbers between 0 and 0.5 (the torus's tube has radius 0.5), got {a.spacings}")
    if a.spacings and a.size:
        p.error(f"--spacings and --{a.size} both choose the spacings; give one of them")
    try:
        check_output("--out", a.out, folder=True)
    except ProblemError as exc:
        p.error(str(exc))
    try:
        data = run(Path(a.out), a.size or "quick", Progress(NAME, not a.quiet), spacings=a.spacings, repeat=a.repeat,
                   cold_repeat=a.cold_repeat)
    except InsufficientMemoryError as exc:  # refused by the cut before allocating
        p.error(f"--spacings: {exc}")
    print(data["table"])
    print(f"results in {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
