"""The paper's meshed-torus experiments (docs/math.md §6.1-6.2).

* The torus mesh families on the n x n/2 grid in the angles (t, p): structured, flipped, perturbed
  (the paper's "unstructured") and perturbed-flipped, rendered off-screen with pyvista, one PNG
  each plus a combined 2 x 2 figure.
* Convergence of the discrete error ||pi_h H - H_h||_{S_h} (and of the L2 error on S_h) of the
  mean curvature vector on every family, with the edge stabilization tau_E = 1/10 and without it
  (tau_E = 0); one log-log figure with least-squares rates, JSON/CSV with every number, LaTeX tables
  of errors and of fitted rates.
* Iso-levels of the computed signed mean curvature H_h . n (vertex normals) on the flipped mesh,
  stabilized and unstabilized, next to the exact k1 + k2: filled contours with contour lines on the
  (t, p) parameter square, one shared colour scale; and the same on the surface in 3D (pyvista).

Rates: "fit" is the least-squares slope of log(error) against log(h) over all levels, "last" the
rate between the two finest levels.  h = N^(-1/2) with N surface nodes (docs/math.md §2).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

import cutfem
from cutfem.runs.convergence import log_ticks, loglog_with_rates, new_figure, rate_triangle, significant
from cutfem.geometry.surface_meshes import TORUS_FAMILIES, torus_mesh

from .common import PAGE_WIDTH, figure_style, fmt_rate, pick, read_png, roundoff_zero, save_csv, save_figure, save_json, save_latex_table, study_main, torus_family

NAME = "paper_meshed"
R_MAJOR, R_MINOR = 1.0, 0.5
SEED = 0
TAUS = (0.1, 0.0)
FAMILY_LABEL = {
    "structured": "structured",
    "flipped": "flipped",
    "perturbed": "perturbed",
    "perturbed-flipped": "perturbed + flipped",
}
PICTURE_N = 24  # resolution of the mesh pictures (24 x 12 cells)
#: the exact discrete solutions, so that the tables and the zero-integral identity are those of the
#: method and not of a solver tolerance; "auto" (CG with the grid multigrid above 5 000 nodes, i.e.
#: n >= 128) is faster there and gives the same L2 errors to 6 digits at n = 768 (see cutfem.solvers.solve)
SOLVER = "direct"

#: every file a run writes (tiny, quick and full alike)
OUTPUTS = (
    [f"meshed_mesh_{f}.png" for f in TORUS_FAMILIES]
    + ["meshed_meshes.png", "meshed_meshes.pdf"]
    + ["meshed_convergence.png", "meshed_convergence.pdf", "meshed_convergence.json", "meshed_convergence.csv"]
    + ["meshed_errors_stabilized.tex", "meshed_errors_unstabilized.tex", "meshed_rates.tex"]
    + ["meshed_isolines.png", "meshed_isolines.pdf", "meshed_isolines_3d.png", "meshed_isolines_3d.pdf", "meshed_isolines.json"]
)


def levels_for(size: str) -> list[int]:
    return pick(size, [8, 16, 32], [16, 32, 64, 128, 256], [16, 32, 64, 128, 256, 512])


def isoline_n(size: str) -> int:
    return pick(size, 16, 32, 32)


# ---------------------------------------------------------------------------------------------
# off-screen rendering (pyvista)
# ---------------------------------------------------------------------------------------------


def offscreen_plotter(shape=(1, 1), window_size=(1200, 900)):
    """A pyvista Plotter that renders off-screen (a headless OpenGL window when there is no display:
    chosen by :func:`cutfem.runs.plotting.offscreen_backend`, else EGL)."""
    try:
        from cutfem.runs.plotting import offscreen_backend
    except ImportError:
        if not os.environ.get("DISPLAY"):
            os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    else:
        offscreen_backend()
    import pyvista as pv

    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, shape=shape, window_size=list(window_size), border=False)
    plotter.set_background("white")
    return plotter


def torus_camera(plotter, zoom=1.35):
    """An oblique view of a torus about the z axis, from above."""
    plotter.camera_position = [(3.2, -4.2, 3.3), (0.0, 0.0, -0.05), (0.0, 0.0, 1.0)]
    plotter.camera.zoom(zoom)


def render_mesh(mesh, path: Path, window_size=(1000, 720)):
    """One triangulated surface with its edges, off-screen, to a PNG."""
    plotter = offscreen_plotter(window_size=window_size)
    plotter.add_mesh(mesh.to_pyvista(), color="#c9d9ea", show_edges=True, edge_color="#1b2a3a", line_width=1.0, smooth_shading=False)
    torus_camera(plotter)
    plotter.screenshot(str(path))
    plotter.close()
    return path


@figure_style
def combine_pngs(paths, titles, out: Path, name: str, ncols=2, width=PAGE_WIDTH, panel_height=2.0):
    """Several PNG renderings (white margins cropped) as one figure, ``width`` inches wide with
    rows of ``panel_height`` inches, and panel titles (PNG + PDF)."""
    nrows = -(-len(paths) // ncols)
    fig, axes = new_figure(width, panel_height * nrows, nrows=nrows, ncols=ncols)
    for ax, path, title in zip(np.ravel(axes), paths, titles):
        ax.imshow(read_png(path))
        ax.set_title(title)
    for ax in np.ravel(axes):
        ax.set_axis_off()
    return save_figure(fig, out, name)


# ---------------------------------------------------------------------------------------------
# convergence
# ---------------------------------------------------------------------------------------------


def _series(family, tau_e, levels, progress):
    progress(f"mean-curvature-meshed family={family} tau_E={tau_e} n={levels}")
    res = cutfem.run("mean-curvature-meshed", levels=levels, surface="torus", tau_e=tau_e, R=R_MAJOR, r=R_MINOR, solver=SOLVER, **torus_family(family, SEED))
    recs = res.records
    h = [r["h"] for r in recs]
    out = {
        "family": family,
        "tau_e": tau_e,
        "n": list(levels),
        "h": h,
        "dofs": [r["dofs"] for r in recs],
        "triangles": [r["triangles"] for r in recs],
        "edges": [r["edges"] for r in recs],
        "discrete_error": [r["discrete_error"] for r in recs],
        "l2_error": [r["l2_error"] for r in recs],
        "area": [r["area"] for r in recs],
        "area_error": [r.get("area_error") for r in recs],
        "integral_H_max": [roundoff_zero(float(np.max(np.abs(r["integral_H"])))) for r in recs],  # zero in exact arithmetic
        "solver": [r["solver"] for r in recs],
        "wall_time": [r["wall_time"] for r in recs],
        "rates_discrete": res.rates["discrete_error"],
        "rates_l2": res.rates["l2_error"],
    }
    for key, short in (("discrete_error", "discrete"), ("l2_error", "l2"), ("area_error", "area")):
        e = np.array(out[key], float)
        out[f"rate_fit_{short}"] = float(np.polyfit(np.log(h), np.log(e), 1)[0])
        out[f"rate_last_{short}"] = float(np.log(e[-2] / e[-1]) / np.log(h[-2] / h[-1]))
    return out


def _sci(x) -> str:
    return "--" if x is None or not np.isfinite(x) else f"{x:.2e}"


def _error_table(out, name, series, levels, key="discrete_error", rates="rates_discrete"):
    header = ["$n$", "$h$"] + [c for f in TORUS_FAMILIES for c in (FAMILY_LABEL[f], "rate")]
    rows = []
    for i, n in enumerate(levels):
        row = [str(n), f"{series[0]['h'][i]:.4f}"]
        for f in TORUS_FAMILIES:
            s = next(s for s in series if s["family"] == f)
            row += [_sci(s[key][i]), "--" if i == 0 else fmt_rate(s[rates][i - 1])]
        rows.append(row)
    return save_latex_table(out, name, header, rows)


def _rates_table(out, series):
    header = ["family", "$\\tau_E$", "fit (discrete)", "last (discrete)", "fit ($L^2$)", "last ($L^2$)"]
    rows = [
        [FAMILY_LABEL[s["family"]], f"{s['tau_e']:g}", fmt_rate(s["rate_fit_discrete"]), fmt_rate(s["rate_last_discrete"]), fmt_rate(s["rate_fit_l2"]), fmt_rate(s["rate_last_l2"])]
        for s in series
    ]
    return save_latex_table(out, "meshed_rates", header, rows)


COLORS = {"structured": "#1f77b4", "flipped": "#d62728", "perturbed": "#2ca02c", "perturbed-flipped": "#9467bd"}
MARKERS = {"structured": "o", "flipped": "s", "perturbed": "^", "perturbed-flipped": "D"}


@figure_style
def _convergence_figure(out, series):
    fig, ax = new_figure(PAGE_WIDTH, 3.4)
    for s in series:
        dashed = s["tau_e"] == 0
        loglog_with_rates(
            ax, s["h"], s["discrete_error"], FAMILY_LABEL[s["family"]],
            marker=MARKERS[s["family"]], color=COLORS[s["family"]], ls="--" if dashed else "-",
            mfc="white" if dashed else COLORS[s["family"]], ms=5, lw=1.3,
        )
    # rate triangles above the highest stabilized curve (slope 1) and under the structured unstabilized one (2)
    stab = max((s for s in series if s["tau_e"] > 0), key=lambda s: s["discrete_error"][-1])
    rate_triangle(ax, stab["h"], stab["discrete_error"], 1, below=False)
    sup = next(s for s in series if s["tau_e"] == 0 and s["family"] == "structured")
    rate_triangle(ax, sup["h"], sup["discrete_error"], 2)
    ax.set_xlabel("$h = N^{-1/2}$")
    ax.set_ylabel(r"$\|\pi_h H - H_h\|_{S_h}$")
    ax.grid(True, which="major", alpha=0.3)
    log_ticks(ax)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), title="solid: $\\tau_E = 0.1$, dashed: $\\tau_E = 0$")
    return save_figure(fig, out, "meshed_convergence")


# ---------------------------------------------------------------------------------------------
# iso-levels of the computed mean curvature
# ---------------------------------------------------------------------------------------------


def torus_angles(points, R=R_MAJOR):
    """(t, p) in [0, 2 pi) of points on (or near) the torus about the z axis."""
    t = np.mod(np.arctan2(points[:, 1], points[:, 0]), 2 * np.pi)
    p = np.mod(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]) - R), 2 * np.pi)
    return t, p


def parameter_triangulation(points, triangles, R=R_MAJOR):
    """The surface triangulation unrolled on the (t, p) plane, periodically repeated around the
    square [0, 2 pi)^2 so that it covers it: (tp (K, 2), triangles (L, 3), vertex (K,)) with
    ``vertex`` the surface vertex of each plane point.  Each triangle is unwrapped relative to its
    first vertex and copied with shifts of -2 pi, 0, 2 pi in each angle; copies of a vertex with the
    same shift are merged, so the plane triangulation is connected."""
    t, p = torus_angles(points, R)
    tt, pp = t[triangles], p[triangles]
    two_pi = 2 * np.pi
    wt = -np.round((tt - tt[:, :1]) / two_pi).astype(np.int64)  # winding added to each corner
    wp = -np.round((pp - pp[:, :1]) / two_pi).astype(np.int64)
    shifts = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)])
    ka = (wt[None] + shifts[:, 0, None, None]).reshape(-1, 3)
    kb = (wp[None] + shifts[:, 1, None, None]).reshape(-1, 3)
    vid = np.broadcast_to(triangles, (len(shifts),) + triangles.shape).reshape(-1, 3)
    nv = len(points)
    keys = (vid * 5 + (ka + 2)) * 5 + (kb + 2)
    uniq, inv = np.unique(keys.reshape(-1), return_inverse=True)
    vertex = uniq // 25
    a = (uniq // 5) % 5 - 2
    b = uniq % 5 - 2
    tp = np.stack([t[vertex] + two_pi * a, p[vertex] + two_pi * b], axis=1)
    assert vertex.max() < nv
    return tp, inv.reshape(-1, 3), vertex


def exact_mean_curvature(points, R=R_MAJOR, r=R_MINOR):
    """k1 + k2 = (R + 2 r cos p) / (r (R + r cos p)) at the angle p of each point."""
    _, p = torus_angles(points, R)
    return (R + 2 * r * np.cos(p)) / (r * (R + r * np.cos(p)))


def ISO_CMAP():
    """viridis, white above the range and black below it (the same in 2D and 3D pictures)."""
    import matplotlib

    return matplotlib.colormaps["viridis"].with_extremes(over="white", under="black")


def _isoline_runs(n, progress):
    fields = {}
    errors = {}
    for tau in TAUS:
        progress(f"iso-levels: flipped n={n} tau_E={tau}")
        res = cutfem.run("mean-curvature-meshed", levels=[n], surface="torus", family="flipped", tau_e=tau, seed=SEED, R=R_MAJOR, r=R_MINOR, solver=SOLVER)
        rec = res.records[0]
        fields[tau] = rec["fields"]["surface"]
        errors[tau] = {"discrete_error": rec["discrete_error"], "l2_error": rec["l2_error"]}
    return fields, errors


def _thirds_ticks(colorbar, levels):
    """Every second level of ``levels`` (multiples of 1/3) as a colour-bar tick, labelled as a
    fraction of 3 (``0``, ``2/3``, ``4/3``, ``2``, ``8/3``)."""
    from fractions import Fraction

    ticks = np.asarray(levels)[::2]
    colorbar.set_ticks(ticks, labels=[str(Fraction(float(t)).limit_denominator(3)) for t in ticks])


@figure_style
def _isoline_figure(out, fields, n, levels):
    from matplotlib.tri import Triangulation

    surf = fields[TAUS[0]]
    pts = np.asarray(surf.points)
    tri = np.asarray(surf.faces).reshape(-1, 4)[:, 1:]
    tp, ptri, vertex = parameter_triangulation(pts, tri)
    T = Triangulation(tp[:, 0], tp[:, 1], ptri)
    panels = [
        ("exact $\\kappa_1 + \\kappa_2$", exact_mean_curvature(pts)),
        (f"$H_h\\cdot n$, $\\tau_E = {TAUS[0]:g}$", np.asarray(fields[TAUS[0]].point_data["mean_curvature"])),
        ("$H_h\\cdot n$, $\\tau_E = 0$", np.asarray(fields[TAUS[1]].point_data["mean_curvature"])),
    ]
    fig, axes = new_figure(PAGE_WIDTH, 2.55, nrows=1, ncols=3, sharey=True)
    cmap = ISO_CMAP()
    cs = None
    for ax, (title, vals) in zip(axes, panels):
        z = vals[vertex]
        cs = ax.tricontourf(T, z, levels=levels, cmap=cmap, extend="both")
        ax.tricontour(T, z, levels=levels, colors="k", linewidths=0.5)
        ax.set_xlim(0, 2 * np.pi)
        ax.set_ylim(0, 2 * np.pi)
        ax.set_aspect("equal")
        ax.set_title(title)
        ax.set_xlabel("$t$")
        ticks = [0, np.pi, 2 * np.pi]
        ax.set_xticks(ticks, ["0", "$\\pi$", "$2\\pi$"])
        ax.set_yticks(ticks, ["0", "$\\pi$", "$2\\pi$"])
    axes[0].set_ylabel("$p$")
    cb = fig.colorbar(cs, ax=axes, shrink=0.9, pad=0.015)
    cb.set_label("mean curvature")
    _thirds_ticks(cb, levels)
    return save_figure(fig, out, "meshed_isolines")


@figure_style
def _isoline_figure_3d(out, fields, levels):
    """The two computed fields on the surface (pyvista, one rendering each, same clim) with their
    contour lines, put side by side with one matplotlib colour bar."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    clim = (float(levels[0]), float(levels[-1]))
    paths = []
    for tau in TAUS:
        plotter = offscreen_plotter(window_size=(1100, 800))
        surf = fields[tau].copy()
        surf.set_active_scalars("mean_curvature")
        plotter.add_mesh(
            surf, scalars="mean_curvature", cmap="viridis", clim=clim, show_scalar_bar=False, smooth_shading=False,
            above_color="#ffffff", below_color="#000000", ambient=0.35, diffuse=0.7, specular=0.0,
        )
        lines = surf.contour(isosurfaces=list(levels), scalars="mean_curvature")
        if lines.n_points:
            plotter.add_mesh(lines, color="black", line_width=2.0)
        torus_camera(plotter, zoom=1.3)
        path = Path(out) / f"_isolines_3d_tau{tau:g}.png"
        plotter.screenshot(str(path))
        plotter.close()
        paths.append(path)
    fig, axes = new_figure(PAGE_WIDTH, 2.5, nrows=1, ncols=2)
    titles = [f"stabilized ($\\tau_E = {TAUS[0]:g}$)", "unstabilized ($\\tau_E = 0$)"]
    for ax, path, title in zip(axes, paths, titles):
        ax.imshow(read_png(path))
        ax.set_title(title)
        ax.set_axis_off()
        path.unlink()
    sm = ScalarMappable(norm=Normalize(*clim), cmap=ISO_CMAP())
    cb = fig.colorbar(sm, ax=axes, shrink=0.85, pad=0.01, extend="both", extendfrac=0.04)
    _thirds_ticks(cb, levels)
    cb.set_label("$H_h\\cdot n$")
    return save_figure(fig, out, "meshed_isolines_3d")


# ---------------------------------------------------------------------------------------------
# the study
# ---------------------------------------------------------------------------------------------


def run(out: Path, size: str = "quick", progress=print) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)

    # (a) the mesh families
    progress("rendering the torus mesh families")
    mesh_paths = []
    for fam in TORUS_FAMILIES:
        mesh_paths.append(render_mesh(torus_mesh(PICTURE_N, family=fam, R=R_MAJOR, r=R_MINOR, seed=SEED), out / f"meshed_mesh_{fam}.png"))
    combine_pngs(mesh_paths, [f"({c}) {FAMILY_LABEL[f]}" for c, f in zip("abcd", TORUS_FAMILIES)], out, "meshed_meshes")

    # (b) convergence
    levels = levels_for(size)
    series = [_series(fam, tau, levels, progress) for tau in TAUS for fam in TORUS_FAMILIES]
    data = {
        "study": NAME,
        "size": size,
        "surface": {"name": "torus", "R": R_MAJOR, "r": R_MINOR},
        "seed": SEED,
        "levels": levels,
        "h_definition": "N^(-1/2), N = number of surface nodes",
        "error": "discrete_error = ||pi_h H - H_h||_{S_h} (P1 mass matrix); l2_error = ||H^e - H_h||_{L2(S_h)}",
        "series": series,
    }
    save_json(out, "meshed_convergence", data)
    save_csv(
        out,
        "meshed_convergence",
        [
            {"family": s["family"], "tau_e": s["tau_e"], "n": n, "h": s["h"][i], "dofs": s["dofs"][i],
             "discrete_error": s["discrete_error"][i], "l2_error": s["l2_error"][i], "area_error": s["area_error"][i],
             "integral_H_max": s["integral_H_max"][i], "wall_time": s["wall_time"][i]}
            for s in series for i, n in enumerate(s["n"])
        ],
    )
    _error_table(out, "meshed_errors_stabilized", [s for s in series if s["tau_e"] > 0], levels)
    _error_table(out, "meshed_errors_unstabilized", [s for s in series if s["tau_e"] == 0], levels)
    _rates_table(out, series)
    _convergence_figure(out, significant(series))  # the digits the tables carry

    # (c) iso-levels on the flipped mesh
    n_iso = isoline_n(size)
    fields, iso_errors = _isoline_runs(n_iso, progress)
    iso_levels = np.linspace(0.0, 8.0 / 3.0, 9)  # the range of k1 + k2 on the torus R = 1, r = 1/2
    progress("drawing the iso-levels")
    _isoline_figure(out, fields, n_iso, iso_levels)
    _isoline_figure_3d(out, fields, iso_levels)
    ranges = {str(tau): [float(np.min(f.point_data["mean_curvature"])), float(np.max(f.point_data["mean_curvature"]))] for tau, f in fields.items()}
    save_json(out, "meshed_isolines", {"n": n_iso, "family": "flipped", "seed": SEED, "levels": iso_levels, "errors": {str(k): v for k, v in iso_errors.items()}, "range_of_H_h_dot_n": ranges})

    summary = {
        "levels": levels,
        "rates_fit_discrete": {f"{s['family']}/tau_e={s['tau_e']:g}": s["rate_fit_discrete"] for s in series},
        "rates_last_discrete": {f"{s['family']}/tau_e={s['tau_e']:g}": s["rate_last_discrete"] for s in series},
    }
    progress("done")
    return summary


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
