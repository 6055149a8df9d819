"""Assembly of vector systems against scalar Poisson on the same cut: seconds per unknown.

``python -m cutfem.studies.vector_assembly [--tiny | --quick | --full] [--repeat 3] [--out DIR]``

Setting: the solid torus {phi < 0} (R = 1, r = 1/2, :class:`cutfem.geometry.shapes.Torus`) cut from
the structured Kuhn box [-1.6, 1.6]^2 x [-0.6, 0.6] at the given spacing; P1 on the NEG tets.  Three
systems, each a matrix (volume term + Nitsche on Gamma_h + ghost penalty on the ghost faces) and its
right-hand side (load + Nitsche load), data from :class:`cutfem.Exact`:

* ``poisson``: scalar, stiffness + nitsche + 0.1 face_jump_penalty (n unknowns);
* ``vector_laplacian``: the same terms on ``VectorSpace(V)`` (3 n unknowns; kron(I_3, the scalar
  matrix) from the scalar exact paths);
* ``elasticity``: elasticity(mu = 1, lam = 2) + elasticity_nitsche + (2 mu + lam) 0.1
  face_jump_penalty (3 n unknowns; its element blocks in the lattice slots).

On each cut all three are assembled once untimed (compilation and the cut's cached geometry: the
faces, the pieces' moments), then each is timed as the best of ``repeat`` assemblies.  A row holds
the spacing, the unknowns, the seconds of the matrix, of the right-hand side and of both, the
seconds per million unknowns, and each vector system's ratio to Poisson per unknown (the goal of
issue 47: at most 3).  Sizes: ``tiny`` spacing 0.2 (the test), ``quick`` 0.1 and 0.07 (about 15
and 43 thousand vector unknowns), ``full`` 0.05, 0.035, 0.025 (118 thousand to 0.95 million).
Timings depend on the machine and its load; the JSON records the environment beside them.

Outputs (prefix ``vector_assembly``): ``.json`` (rows, setting, environment, table) and ``.csv``.
"""

from __future__ import annotations

import argparse
import gc
import time
from pathlib import Path

import cutfem as cf
from cutfem.geometry.box import structured_box
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
from cutfem.geometry.shapes import Torus
from cutfem.runs.runner import text_table

from .assembly_benchmark import environment
from .common import pick, save_csv, save_json, study_main

NAME = "vector_assembly"
OUTPUTS = [NAME]
BOX = ([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6])
TORUS = (1.0, 0.5)
MU, LAM, GAMMA, GAMMA_G = 1.0, 2.0, 10.0, 0.1
SYSTEMS = ("poisson", "vector_laplacian", "elasticity")

SCALAR = cf.Exact("sin(x) * exp(y / 2) + z")
VECTOR = cf.Exact(["sin(x) * exp(y / 2)", "cos(y) * z", "x * y * z + sin(z)"])


def spacings_for(size: str) -> list[float]:
    return pick(size, [0.2], [0.1, 0.07], [0.05, 0.035, 0.025])


def systems(cut):
    """{name: (space, matrix form, right-hand side form)} of the three systems on ``cut``."""
    V = cf.CutSpace(cut, NEG)
    W = cf.VectorSpace(V)
    dx, ds, dg = cut.dx(NEG), cut.ds(), cut.dF(cut.ghost_facets(NEG))
    out = {}
    for name, space, u in (("poisson", V, SCALAR), ("vector_laplacian", W, VECTOR)):
        N = cf.nitsche(ds, GAMMA, g=u)
        out[name] = (space, cf.stiffness(dx) + N + GAMMA_G * cf.face_jump_penalty(dg, h_power=1), cf.load(-u.laplacian, dx) + N.load)
    N = cf.elasticity_nitsche(ds, MU, LAM, GAMMA, g=VECTOR)
    f = -(2 * MU * VECTOR.sym_grad + LAM * VECTOR.div * cf.Exact.identity()).div
    out["elasticity"] = (W, cf.elasticity(dx, MU, LAM) + N + (2 * MU + LAM) * GAMMA_G * cf.face_jump_penalty(dg, h_power=1),
                         cf.load(f, dx) + N.load)
    return out


def _best(fn, repeat):
    best = float("inf")
    for _ in range(repeat):
        gc.collect()
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def measure(spacing: float, repeat: int = 3) -> dict:
    """The row of one spacing (see the module docstring)."""
    cut = cut_mesh(structured_box(*BOX, spacing=spacing), Torus(*TORUS))
    forms = systems(cut)
    for space, a, b in forms.values():  # untimed: compilation and the cut's cached geometry
        cf.assemble(a, space), cf.assemble(b, space)
    row = {"spacing": spacing}
    for name, (space, a, b) in forms.items():
        matrix = _best(lambda: cf.assemble(a, space), repeat)
        rhs = _best(lambda: cf.assemble(b, space), repeat)
        row.update({f"{name}_unknowns": space.n_dofs, f"{name}_matrix_seconds": matrix, f"{name}_rhs_seconds": rhs,
                    f"{name}_seconds": matrix + rhs, f"{name}_seconds_per_million": (matrix + rhs) / space.n_dofs * 1e6})
    per = row["poisson_seconds_per_million"]
    for name in SYSTEMS[1:]:
        row[f"{name}_ratio"] = row[f"{name}_seconds_per_million"] / per
        row[f"{name}_matrix_ratio"] = (row[f"{name}_matrix_seconds"] / row[f"{name}_unknowns"]) / (
            row["poisson_matrix_seconds"] / row["poisson_unknowns"])
    return row


COLUMNS = [("spacing", "spacing", "{:g}"), ("poisson_unknowns", "scalar n", "{:d}"), ("elasticity_unknowns", "vector n", "{:d}"),
           ("poisson_seconds", "Poisson s", "{:.3f}"), ("vector_laplacian_seconds", "vec. Lap. s", "{:.3f}"),
           ("elasticity_seconds", "elast. s", "{:.3f}"), ("poisson_seconds_per_million", "Poisson s/M", "{:.2f}"),
           ("vector_laplacian_ratio", "vec. Lap. ratio", "{:.2f}"), ("elasticity_ratio", "elast. ratio", "{:.2f}"),
           ("elasticity_matrix_ratio", "(matrix)", "{:.2f}")]


def format_table(rows) -> str:
    return text_table([label for _, label, _ in COLUMNS], [[fmt.format(r[key]) for key, _, fmt in COLUMNS] for r in rows])


def run(out: Path, size: str = "quick", progress=None, repeat: int = 3) -> dict:
    """Measure every spacing of ``size``; write JSON and CSV into ``out``; print the table; return the data."""
    rows = []
    for s in spacings_for(size):
        if progress:
            progress(f"spacing {s:g}")
        rows.append(measure(s, repeat))
    data = {"setting": {"box": BOX, "torus": {"R": TORUS[0], "r": TORUS[1]}, "mu": MU, "lam": LAM, "gamma": GAMMA,
                        "gamma_g": GAMMA_G, "repeat": repeat, "spacings": spacings_for(size)},
            "environment": environment(), "rows": rows, "table": format_table(rows)}
    save_json(out, NAME, data)
    save_csv(out, NAME, rows)
    print(data["table"], flush=True)
    return data


_options = argparse.ArgumentParser(add_help=False)
_options.add_argument("--repeat", type=int, default=3, help="assemblies per system and spacing, the best timed (default 3)")
main = study_main(run, NAME, _options)

if __name__ == "__main__":
    raise SystemExit(main())
