"""The cut by several level sets against the cut by one, on the same mesh (docs/math.md §16).

A benchmark note, not a test: the goal of issue 49 is that the cut of a domain of m level sets costs
at most 2 times the cut by one level set per level set.  On the box [-1.2, 1.2]^3 at each spacing:

* ``one``: ``cut_mesh(box, ball)`` (the band search of a signed distance), then the element set of
  NEG and the cells of ``dx(NEG)``: what a bulk problem asks of its cut before assembling;
* ``csg m``: the same for domains of m = 1, 2, 3 and 7 level sets, the unit ball (radius 1)
  intersected with 0, 1, 2 planes and with a cube of six planes (half-width 0.8, through the ball);
  every level set evaluated at every node, the tets where one changes sign clipped.

Each time is the least of ``repeat`` runs after one to compile and warm up, in processor seconds
of the process (all its threads: on a machine that others share, the wall clock also counts their
work, the processor time much less so) and in wall seconds; the ratio is
``time(csg m) / (m time(one))`` in processor seconds.  Timings depend on the machine and its load;
the study prints them and writes ``csg_cut.json`` and ``csg_cut_table.tex``
(``python -m cutfem.studies.csg_cut --quick``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cutfem.geometry.box import structured_box
from cutfem.geometry.csg import intersection
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
from cutfem.geometry.shapes import Plane, Sphere

from .common import pick, save_json, save_latex_table, study_main

NAME = "csg_cut"
OUTPUTS = [NAME, f"{NAME}_table"]


def _domains():
    ball = Sphere(1.0)
    planes = [Plane((0, 0, 1), (0, 0, 0.5)), Plane((1, 0, 0), (0.6, 0, 0))]
    cube = [Plane(s * e, s * 0.8 * e) for e in np.eye(3) for s in (1.0, -1.0)]
    return {1: intersection(ball), 2: intersection(ball, planes[0]), 3: intersection(ball, *planes), 7: intersection(ball, *cube)}


def _time(make, repeat: int) -> tuple[float, float, object]:
    """(least processor seconds, least wall seconds of ``repeat`` runs of ``make``, its last result)."""
    cpu, wall, out = np.inf, np.inf, None
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        out = make()
        cpu, wall = min(cpu, time.process_time() - c0), min(wall, time.perf_counter() - t0)
    return cpu, wall, out


def _cut_and_sides(box, levelset):
    cut = cut_mesh(box, levelset)
    cut.elements(NEG)
    cut.dx(NEG).n_cells  # the cells of the side (whole tets and sub-tets)
    return cut


def run(out: Path, size: str = "quick", progress=None, repeat=None) -> dict:
    spacings = pick(size, [0.2], [0.1, 0.05], [0.05, 0.025])
    repeat = repeat or pick(size, 1, 3, 3)
    domains = _domains()
    rows = []
    for s in spacings:
        box = structured_box([-1.2] * 3, [1.2] * 3, spacing=s)
        _cut_and_sides(box, Sphere(1.0)), _cut_and_sides(box, domains[2])  # compile and warm up
        one, wall, cut = _time(lambda: _cut_and_sides(box, Sphere(1.0)), repeat)
        row = {"spacing": s, "tets": int(box.n_tets), "one": one, "one_wall": wall, "one_cut_tets": int(cut.n_tets)}
        for m, domain in domains.items():
            if progress:
                progress(f"spacing {s:g}: {m} level set{'s' if m > 1 else ''}")
            t, wall, cut = _time(lambda: _cut_and_sides(box, domain), repeat)
            row[f"csg{m}"], row[f"csg{m}_wall"] = t, wall
            row[f"ratio{m}"] = t / (m * one)
            row[f"csg{m}_cut_tets"] = int(cut.n_tets)
        rows.append(row)
    summary = {"size": size, "repeat": repeat, "rows": rows,
               "worst_ratio_per_level_set": max(r[f"ratio{m}"] for r in rows for m in domains)}
    save_json(out, NAME, summary)
    header = ["spacing", "tets", "one [s]"] + [f"{m} level sets [s] (ratio)" if m > 1 else "1 as a domain [s] (ratio)" for m in domains]
    table = [[f"{r['spacing']:g}", str(r["tets"]), f"{r['one']:.3f}"] + [f"{r[f'csg{m}']:.3f} ({r[f'ratio{m}']:.2f})" for m in domains]
             for r in rows]
    save_latex_table(out, f"{NAME}_table", header, table,
                     caption="The cut and the sides (element set of NEG, cells of dx(NEG)) of the unit ball alone, and of domains of "
                             "m level sets (the ball and 0, 1, 2 planes, or a cube of six), processor seconds; ratio = time / "
                             f"(m * time of the ball alone), the goal at most 2; least of {repeat} runs ({size}).")
    return summary


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
