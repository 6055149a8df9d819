"""Higher order: the planar cut with P1 fields (order 1) against the isoparametric cut with P2 fields
(order 2), for the geometry on three surfaces and for three problems (docs/math.md §17-§18).

For the unit sphere (centre off the lattice's symmetry, ``SPHERE_CENTER``), the paper's torus
(R = 1, r = 1/2, on the paper's box) and the ellipsoid with semi-axes (1, 0.8, 0.6) (a level set that
is not a distance), on structured boxes of decreasing spacing, each cut at order 1 (S_h = {phi_h1 = 0},
planar) and at order 2 (Theta_h(S_h), :mod:`cutfem.geometry.isoparametric`):

* ``area``: |area of the discrete surface - area of S| (``cut.ds().size``);
* ``volume``: |volume of the discrete inside - volume inside S| (``cut.dx(NEG).size``);
* ``distance``: the largest distance |x - p(x)| of the points x of the degree-4 surface rule
  (six per triangle of S_h, mapped by Theta_h at order 2) to S, p the closest point;

and their rates against h = N^(-1/3) (N background nodes, docs/math.md §2).  Expected: order 1 area and
volume O(h^2), distance O(h^2); order 2 distance O(h^3), area and volume O(h^3) or better.  Writes
``higher_order_geometry.json``, ``.csv`` and ``higher_order_geometry_table.tex`` (printed).

The problems (:data:`PROBLEMS`), each at orders 1 and 2 through :func:`cutfem.run` with its defaults:
fictitious-domain Poisson in the unit ball, Laplace-Beltrami on the unit sphere, the mean curvature
vector on the paper's torus; their L2 (and H1) errors and rates, in ``higher_order_problems.json``,
``.csv``, ``higher_order_problems_table.tex`` and the figure ``higher_order_problems`` (errors against
h, P1 dashed, P2 solid).

Condition numbers over 20 random positions of the sphere and the ball against the grid, orders 1 and 2
(:mod:`cutfem.studies.shift_conditioning`): ``higher_order_conditioning.json``, ``.csv``, ``_table.tex``
and the figure.  ``python -m cutfem.studies.higher_order --out DIR [--tiny | --quick | --full]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import cutfem
from cutfem.geometry.box import structured_box
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
from cutfem.geometry.shapes import Ellipsoid, Sphere, Torus
from cutfem.fem.norms import rates

from .common import PAGE_WIDTH, figure_style, fmt_rate, pick, save_csv, save_figure, save_json, save_latex_table, study_main
from .paper_cut import BOX as TORUS_BOX
from .shift_conditioning import NAME as CONDITIONING, conditioning_outputs

NAME = "higher_order"
OUTPUTS = [f"{NAME}_geometry", f"{NAME}_geometry_table", f"{NAME}_problems", f"{NAME}_problems_table", CONDITIONING,
           f"{CONDITIONING}_table"]

#: (problem, its surface by default, the error keys of its record)
PROBLEMS = (("poisson-cut", "ball", ("l2_error", "h1_error")), ("laplace-beltrami-cut", "sphere", ("l2_error", "h1_error")),
            ("mean-curvature-cut", "torus", ("l2_error",)))
#: the panel titles of the figure
TITLES = {"poisson-cut": "Poisson, ball", "laplace-beltrami-cut": "Laplace-Beltrami, sphere", "mean-curvature-cut": "H_h, torus"}

#: the sphere's centre: off the symmetry of the lattice, so that no level is a special case
SPHERE_CENTER = (0.031, -0.017, 0.023)
#: the quantities measured, each with its rate
QUANTITIES = ("area", "volume", "distance")


def surfaces() -> dict:
    """name -> (level set, box corners (lower, upper)): every box a whole number of cells at the
    spacings of :func:`run` (multiples of 0.1 on each side) and clear of the surface."""
    return {
        "sphere": (Sphere(1.0, center=SPHERE_CENTER), ([-1.3] * 3, [1.3] * 3)),
        "torus": (Torus(1.0, 0.5), (list(TORUS_BOX[:3]), list(TORUS_BOX[3:]))),
        "ellipsoid": (Ellipsoid(1.0, 0.8, 0.6), ([-1.2, -1.0, -0.8], [1.2, 1.0, 0.8])),
    }


def geometry_errors(levelset, lower, upper, spacing: float, order: int) -> dict:
    """The geometry errors of the cut of ``levelset`` at one spacing and order (module docstring)."""
    cut = cut_mesh(structured_box(lower, upper, spacing=spacing), levelset, order=order)
    ds = cut.ds()
    x = ds.quadrature(4).points.reshape(-1, 3)
    return {"spacing": spacing, "order": order, "h": cut.h, "cut_tets": int(cut.n_tets),
            "area": abs(ds.size - levelset.area), "volume": abs(cut.dx(NEG).size - levelset.volume),
            "distance": float(np.linalg.norm(x - levelset.closest_point(x), axis=1).max())}


def problem_rows(spacings, progress=None) -> list[dict]:
    """The records of :data:`PROBLEMS` at both orders, with the rates of their errors."""
    rows = []
    for name, surface, keys in PROBLEMS:
        for order in (1, 2):
            if progress:
                progress(f"{name}, order {order}")
            recs = cutfem.run(name, levels=spacings, order=order).records
            hs = [r["h"] for r in recs]
            level = [{"problem": name, "surface": surface, "order": order, "spacing": s, "h": r["h"], "dofs": int(r["dofs"]),
                      **{k: r[k] for k in keys}} for s, r in zip(spacings, recs)]
            for k in keys:
                for e, rate in zip(level, [None] + list(rates(hs, [e[k] for e in level]))):
                    e[f"{k}_rate"] = rate
            rows.extend(level)
    return rows


def _problems_outputs(out, size, rows):
    save_json(out, f"{NAME}_problems", {"size": size, "rows": rows})
    save_csv(out, f"{NAME}_problems", rows)
    header = ["problem", "order", "spacing", "unknowns", "L2 error", "rate", "H1 error", "rate"]
    table = [[r["problem"], str(r["order"]), f"{r['spacing']:g}", str(r["dofs"]), f"{r['l2_error']:.2e}", fmt_rate(r["l2_error_rate"]),
              f"{r['h1_error']:.2e}" if "h1_error" in r else "--", fmt_rate(r.get("h1_error_rate"))] for r in rows]
    save_latex_table(out, f"{NAME}_problems_table", header, table,
                     caption="P1 on the planar cut (order 1) and P2 on the isoparametric cut (order 2): Poisson in the ball, "
                             "Laplace-Beltrami on the sphere, the mean curvature vector on the torus (unknowns per component); "
                             f"rates against h = N^(-1/3) ({size}).")
    _plot(out, rows)


@figure_style
def _plot(out, rows):
    from cutfem.runs.convergence import log_ticks, new_figure

    fig, axes = new_figure(PAGE_WIDTH, 2.9, nrows=1, ncols=len(PROBLEMS))
    for ax, (name, surface, keys) in zip(axes, PROBLEMS):
        for order, style in ((1, "--"), (2, "-")):
            sel = [r for r in rows if r["problem"] == name and r["order"] == order]
            for k, key in enumerate(keys):
                ax.loglog([r["h"] for r in sel], [r[key] for r in sel], style, marker="o", color=f"C{k}",
                          label=f"{key.split('_')[0].upper()}, P{order}")
        ax.set_title(TITLES[name])
        ax.set_xlabel("h")
        ax.grid(True, which="major", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=4)
    for ax in axes:
        log_ticks(ax)
    axes[0].set_ylabel("error")
    save_figure(fig, out, f"{NAME}_problems")


def run(out: Path, size: str = "quick", progress=None) -> dict:
    spacings = pick(size, [0.2, 0.1], [0.2, 0.1, 0.05], [0.2, 0.1, 0.05, 0.025])
    _problems_outputs(out, size, problem_rows(pick(size, [0.2, 0.1], [0.2, 0.1], [0.2, 0.1, 0.05, 0.025]), progress))
    conditioning_outputs(out, size, pick(size, [0.4, 0.2], [0.4, 0.2, 0.1], [0.4, 0.2, 0.1, 0.05]), progress)
    rows = []
    for name, (levelset, (lower, upper)) in surfaces().items():
        for order in (1, 2):
            level = []
            for s in spacings:
                if progress:
                    progress(f"{name}, order {order}, spacing {s:g}")
                level.append({"surface": name, **geometry_errors(levelset, lower, upper, s, order)})
            for q in QUANTITIES:
                r = rates([e["h"] for e in level], [e[q] for e in level])
                for e, rate in zip(level, [None] + list(r)):
                    e[f"{q}_rate"] = rate
            rows.extend(level)
    last = {(r["surface"], r["order"]): r for r in rows}  # the finest level of each
    summary = {"size": size, "spacings": spacings, "rows": rows,
               "last_rates": {f"{s}_order{o}": {q: r[f"{q}_rate"] for q in QUANTITIES} for (s, o), r in last.items()}}
    save_json(out, f"{NAME}_geometry", summary)
    save_csv(out, f"{NAME}_geometry", rows)
    header = ["surface", "order", "spacing", "h", "area error", "rate", "volume error", "rate", "distance", "rate"]
    table = [[r["surface"], str(r["order"]), f"{r['spacing']:g}", f"{r['h']:.4f}"]
             + [c for q in QUANTITIES for c in (f"{r[q]:.2e}", fmt_rate(r[f"{q}_rate"]))] for r in rows]
    save_latex_table(out, f"{NAME}_geometry_table", header, table,
                     caption="Geometry errors of the planar cut (order 1) and of the isoparametric one (order 2, Theta_h(S_h)): "
                             "area, enclosed volume, largest distance of the surface's quadrature points to S; rates against "
                             f"h = N^(-1/3) ({size}).")
    return summary


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
