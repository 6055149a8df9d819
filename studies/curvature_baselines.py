"""Mesh-processing curvature formulas against the stabilized mean curvature vector (meshed torus).

On the four torus families of docs/math.md §6.1 (structured, flipped, perturbed, perturbed-flipped; seed 0)
we compute the mean curvature vector at the nodes by

* ``cotan-voronoi``: the cotangent Laplacian with the mixed Voronoi lumped mass,
  H_i = (L X)_i / m_i (:mod:`cutfem.studies.baselines`);
* ``cotan-barycentric``: the same with the barycentric lumped mass (|K|/3 per corner);
* ``pyvista``: ``PolyData.curvature("mean")`` (VTK), which is (k1 + k2)/2, turned into a vector
  2 c_i n_i with area-weighted vertex normals;
* ``P1, tau_E=0``: the consistent-mass L2 projection of docs/math.md §3 without stabilization
  (``cutfem.run("mean-curvature-meshed", tau_e=0)``);
* ``stabilized``: the same with tau_E = 1/10 (the paper's method).

Errors against the exact H = (k1 + k2) n at the nodes (which lie on the torus): the nodal maximum
max_i |H_i - H(x_i)|, the nodal RMS, and the discrete L2 error ||pi_h H - H_h||_{S_h} through the
P1 mass matrix (docs/math.md §5; the pointwise formulas are read as P1 functions for this norm).  h = N^(-1/2).
Wall times: the formula itself for the baselines (mesh given; best of three calls, after a warm-up
call that loads VTK), assembly + solve for the FEM (one call, from the problem's timer).

Outputs (prefix ``curvature_baselines``): ``.json``, ``.csv`` (one row per family, method, level),
``_errors.png/.pdf`` (discrete L2 and nodal max against h, one column per family, one legend for
all panels), ``_time.png/.pdf`` and ``_rates.tex`` (the fitted rates per method and family).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import cutfem
from cutfem.studies.baselines import cotangent_mean_curvature, pyvista_mean_curvature_vector
from cutfem.fem.norms import discrete_error, fitted_rate
from cutfem.geometry.shapes import Torus
from cutfem.fem.spaces import SurfaceP1Space
from cutfem.geometry.surface_meshes import TORUS_FAMILIES, torus_mesh
from cutfem.runs.convergence import significant

from .common import PAGE_WIDTH, figure_style, fmt_rate, pick, save_csv, save_figure, save_json, save_latex_table, study_main, torus_family

NAME = "curvature_baselines"
OUTPUTS = [NAME, f"{NAME}_errors", f"{NAME}_time", f"{NAME}_rates"]
METHODS = ("cotan-voronoi", "cotan-barycentric", "pyvista", "P1, tau_E=0", "stabilized")
STYLE = {
    "cotan-voronoi": dict(color="C0", marker="s"),
    "cotan-barycentric": dict(color="C1", marker="v"),
    "pyvista": dict(color="C2", marker="^"),
    "P1, tau_E=0": dict(color="C3", marker="x", ls="--"),
    "stabilized": dict(color="k", marker="o"),
}
SEED = 0
TAU_E = 0.1


def _say(progress, msg):
    if progress:
        progress(msg)


def _errors(He, H, space):
    e = H - He
    nodal = np.linalg.norm(e, axis=1)
    return {
        "max_error": float(nodal.max()),
        "rms_error": float(np.sqrt(np.mean(nodal**2))),
        "discrete_error": discrete_error(space, e),
    }


def _fem(n, family, tau_e):
    """H_h at the nodes and the assembly + solve time from the registered problem."""
    res = cutfem.run("mean-curvature-meshed", levels=[n], surface="torus", tau_e=tau_e, **torus_family(family, SEED))
    rec = res.records[0]
    H = np.asarray(rec["fields"]["surface"].point_data["H_h"])
    return H, rec["time"].get("assembly", 0.0) + rec["time"].get("solve", 0.0)


def _baseline(method, mesh, repeat=3):
    """Nodal H of a baseline formula and its best wall time over ``repeat`` calls."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        if method == "cotan-voronoi":
            H = cotangent_mean_curvature(mesh.points, mesh.triangles, mass="voronoi")
        elif method == "cotan-barycentric":
            H = cotangent_mean_curvature(mesh.points, mesh.triangles, mass="barycentric")
        else:
            H = pyvista_mean_curvature_vector(mesh.points, mesh.triangles)
        best = min(best, time.perf_counter() - t0)
    return H, best


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    levels = pick(size, [16, 32, 64], [16, 32, 64, 128], [16, 32, 64, 128, 256, 512])
    torus = Torus()
    warm = torus_mesh(8)
    for method in METHODS[:3]:  # first calls load pyvista/VTK: keep that out of the timings
        _baseline(method, warm, repeat=1)
    rows = []
    for family in TORUS_FAMILIES:
        for n in levels:
            _say(progress, f"{family} n={n}")
            mesh = torus_mesh(n, family=family, seed=SEED)
            space = SurfaceP1Space(mesh)
            He = torus.exact_mean_curvature_vector(mesh.points)
            for method in METHODS:
                if method == "stabilized":
                    H, secs = _fem(n, family, TAU_E)
                elif method == "P1, tau_E=0":
                    H, secs = _fem(n, family, 0.0)
                else:
                    H, secs = _baseline(method, mesh)
                rows.append({"family": family, "method": method, "n": n, "nodes": mesh.n_points, "h": space.h, "seconds": secs, **_errors(He, H, space)})

    rates = {}
    for family in TORUS_FAMILIES:
        for method in METHODS:
            sel = [r for r in rows if r["family"] == family and r["method"] == method]
            h = [r["h"] for r in sel]
            entry = {}
            for key in ("discrete_error", "max_error", "rms_error"):
                e = [r[key] for r in sel]
                entry[key] = {"fitted": fitted_rate(h, e), "last": float(np.log(e[-2] / e[-1]) / np.log(h[-2] / h[-1]))}
            rates.setdefault(family, {})[method] = entry

    summary = {
        "size": size,
        "levels": levels,
        "seed": SEED,
        "tau_e": TAU_E,
        "conventions": {
            "H": "mean curvature vector (k1 + k2) n, outward (docs/math.md §1)",
            "pyvista": "PolyData.curvature('mean') = (k1 + k2)/2; used as 2 c n with area-weighted vertex normals",
            "h": "N^(-1/2), N = number of surface nodes",
            "seconds": "baselines: the formula on a given mesh; FEM: assembly + solve",
        },
        "rates": rates,
        "finest": {f: {m: next(r for r in rows[::-1] if r["family"] == f and r["method"] == m) for m in METHODS} for f in TORUS_FAMILIES},
        "records": rows,
    }
    save_json(out, NAME, summary)
    save_csv(out, NAME, rows)
    _plot_errors(out, significant(rows))  # the digits the tables carry
    _plot_time(out, rows)
    header = ["method"] + [f.replace("-", " ") for f in TORUS_FAMILIES]
    table = [
        [m] + [f"{fmt_rate(rates[f][m]['discrete_error']['fitted'])} / {fmt_rate(rates[f][m]['max_error']['fitted'])}" for f in TORUS_FAMILIES]
        for m in METHODS
    ]
    save_latex_table(out, f"{NAME}_rates", header, table,
                     caption="Fitted rates of the discrete L2 error / nodal maximum error of the mean curvature vector on the torus families.")
    return {k: summary[k] for k in ("size", "levels", "rates", "finest")}


@figure_style
def _plot_errors(out, rows):
    from cutfem.runs.convergence import log_ticks, new_figure, rate_triangle

    fig, axes = new_figure(PAGE_WIDTH, 4.6, nrows=2, ncols=len(TORUS_FAMILIES), sharex=True, sharey="row")
    for j, family in enumerate(TORUS_FAMILIES):
        for i, (key, label) in enumerate((("discrete_error", r"$\|\pi_h H - H_h\|_{S_h}$"), ("max_error", r"$\max_i |H(x_i) - H_i|$"))):
            ax = axes[i, j]
            for m in METHODS:
                sel = [r for r in rows if r["family"] == family and r["method"] == m]
                ax.loglog([r["h"] for r in sel], [r[key] for r in sel], label=m.replace("tau_E=0", "$\\tau_E = 0$"), **STYLE[m])
                if m == "stabilized" and i == 0:
                    rate_triangle(ax, [r["h"] for r in sel], [r[key] for r in sel], 1)
            if i == 1:
                ax.set_xlabel(r"$h = N^{-1/2}$")
            if j == 0:
                ax.set_ylabel(label)
            ax.set_title(family if i == 0 else "")
            ax.grid(True, which="major", alpha=0.3)
    for ax in axes.ravel():
        log_ticks(ax)
    # one legend for all panels; the fitted rates of every panel are in the rates table
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=3)
    save_figure(fig, out, f"{NAME}_errors")


@figure_style
def _plot_time(out, rows):
    from cutfem.runs.convergence import new_figure

    fig, ax = new_figure(4.2, 3.2)
    for m in METHODS:
        sel = [r for r in rows if r["method"] == m]
        nodes = sorted({r["nodes"] for r in sel})
        t = [np.median([r["seconds"] for r in sel if r["nodes"] == k]) for k in nodes]
        ax.loglog(nodes, t, label=m, **STYLE[m])
    ax.set_xlabel("surface nodes N")
    ax.set_ylabel("wall time [s] (median of the families)")
    ax.set_title("Cost of the curvature computations")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    save_figure(fig, out, f"{NAME}_time")


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
