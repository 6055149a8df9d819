"""The paper's cut torus (docs/math.md §6.3).

The torus R = 1, r = 1/2 is the zero level set of its signed distance, interpolated on a structured
(Kuhn: six tetrahedra per cube) background mesh of the box [-1.6, 1.6] x [-1.6, 1.6] x [-0.6, 0.6],
independent of the torus.  The mean curvature vector is computed with the face stabilization
tau_F = 1/10 (no power of h) and tau_E = 0.

* Pictures at a coarse spacing: the induced surface mesh S_h with its edges; a cut-away of the
  active tetrahedra around S_h; and a plane section (y = const) of the active mesh with the curve
  S_h ∩ {y = const}.
* Convergence: the L2(S_h) error of H_h against H^e = H o p versus h = N^(-1/3) (N the number of
  background nodes), the error of the area of S_h, the integral of H_h over S_h (zero up to the
  solver tolerance), active tetrahedra, degrees of freedom; JSON, CSV, a LaTeX table and a log-log
  figure with least-squares rates.

At spacings 0.1 and finer some background nodes lie exactly on the torus (e.g. (1.5, 0, 0)): the
cut's zero rule (cutfem.geometry.cut) is exercised; the number of such nodes is recorded per level.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import cutfem
from cutfem.runs.convergence import log_ticks, loglog_with_rates, new_figure, rate_triangle, significant
from cutfem.geometry.shapes import Torus

from .common import PAGE_WIDTH, figure_style, fmt_rate, fmt_roundoff, pick, read_png, roundoff_zero, save_csv, save_figure, save_json, save_latex_table, study_main
from .paper_meshed import offscreen_plotter

NAME = "paper_cut"
BOX = (-1.6, -1.6, -0.6, 1.6, 1.6, 0.6)
R_MAJOR, R_MINOR = 1.0, 0.5
TAU_F = 0.1
TAU_E = 0.0
PICTURE_SPACING = 0.2
SECTION_Y = 0.03  # the section plane of the picture: off the grid planes, so no tet face lies in it

OUTPUTS = [
    "cut_surface_mesh.png",
    "cut_active_tets.png",
    "cut_mesh.png",
    "cut_mesh.pdf",
    "cut_convergence.png",
    "cut_convergence.pdf",
    "cut_convergence.json",
    "cut_convergence.csv",
    "cut_errors.tex",
]


def levels_for(size: str) -> list[float]:
    return pick(size, [0.4, 0.2, 0.1], [0.2, 0.1, 0.05, 0.025], [0.2, 0.1, 0.05, 0.025, 0.0125])


def box_string() -> str:
    return ",".join(f"{v:g}" for v in BOX)


def nodes_on_surface(spacing: float) -> int:
    """Number of background nodes of the paper's box at this spacing where the torus' signed
    distance is zero up to 1e-12 (the nodes the zero rule decides about)."""
    lo, hi = np.array(BOX[:3]), np.array(BOX[3:])
    cells = np.rint((hi - lo) / spacing).astype(int)
    axes = [np.linspace(lo[k], hi[k], cells[k] + 1) for k in range(3)]
    # the torus only meets |z| <= r; evaluate plane by plane to keep memory small at fine spacings
    total = 0
    X, Y = np.meshgrid(axes[0], axes[1], indexing="ij")
    rho_xy = np.hypot(X, Y) - R_MAJOR
    for z in axes[2][np.abs(axes[2]) <= R_MINOR + 1e-12]:
        total += int(np.count_nonzero(np.abs(np.hypot(z, rho_xy) - R_MINOR) <= 1e-12))
    return total


def _solve(levels, progress, solver="direct"):
    progress(f"mean-curvature-cut torus, box {BOX}, tau_F={TAU_F}, spacings {levels}")
    return cutfem.run(
        "mean-curvature-cut", levels=levels, surface="torus", R=R_MAJOR, r=R_MINOR, box=box_string(),
        tau_f=TAU_F, tau_e=TAU_E, solver=solver,
        progress=lambda i, n, level, rec: progress(f"  spacing {level}: " + ("..." if rec is None else f"done in {rec['wall_time']:.1f} s")),
    )


# ---------------------------------------------------------------------------------------------
# pictures
# ---------------------------------------------------------------------------------------------


def _fit_view(plotter, direction=(0.62, -0.8, 0.75), zoom=1.0):
    """Look at the scene's centre from ``direction``, fitted to its bounds, then zoom."""
    plotter.view_vector(direction, viewup=(0, 0, 1))
    plotter.reset_camera()
    plotter.camera.zoom(zoom)


def _render_surface(surface, path):
    plotter = offscreen_plotter(window_size=(1200, 850))
    plotter.add_mesh(surface, color="#f2b880", show_edges=True, edge_color="#4a2a10", line_width=0.9, ambient=0.25, specular=0.0)
    _fit_view(plotter, zoom=1.55)
    plotter.screenshot(str(path))
    plotter.close()


def _render_active(surface, active, path):
    """A quarter of the torus removed: S_h and the edges of the active tets of the rest."""
    def keep(ds):
        c = ds.cell_centers().points
        return ds.extract_cells(np.flatnonzero(~((c[:, 0] > 0) & (c[:, 1] < 0))))

    plotter = offscreen_plotter(window_size=(1200, 850))
    plotter.add_mesh(keep(surface), color="#f2b880", show_edges=True, edge_color="#4a2a10", line_width=0.8, ambient=0.25, specular=0.0)
    plotter.add_mesh(keep(active).extract_all_edges(), color="#1f3b70", opacity=0.35, line_width=0.7)
    _fit_view(plotter, zoom=1.45)
    plotter.screenshot(str(path))
    plotter.close()


def _section(active, surface, y):
    """The plane {y = const} through the active mesh and S_h, in (x, z): triangles filling the
    section of the active tets (T, 3, 2), the edges of the section polygons (E, 2, 2), and the
    segments of S_h (S, 2, 2)."""
    origin = (0.0, y, 0.0)
    section = active.slice(normal="y", origin=origin)
    fill = section.triangulate()
    tri = np.asarray(fill.points)[np.asarray(fill.faces).reshape(-1, 4)[:, 1:]][..., [0, 2]]
    edges = section.extract_all_edges()
    edge_xz = np.asarray(edges.points)[np.asarray(edges.lines).reshape(-1, 3)[:, 1:]][..., [0, 2]]
    curve = surface.slice(normal="y", origin=origin)
    seg_xz = np.asarray(curve.points)[np.asarray(curve.lines).reshape(-1, 3)[:, 1:]][..., [0, 2]]
    return tri, edge_xz, seg_xz


@figure_style
def _mesh_figure(out, surface, active, spacing):
    from matplotlib.collections import LineCollection, PolyCollection

    _render_surface(surface, out / "cut_surface_mesh.png")
    _render_active(surface, active, out / "cut_active_tets.png")
    tri, edges, segments = _section(active, surface, SECTION_Y)
    fig, _ = new_figure(PAGE_WIDTH, 2.3, nrows=0)
    gs = fig.add_gridspec(1, 3, width_ratios=[1.0, 1.0, 0.75])
    for k, (name, title) in enumerate((("cut_surface_mesh.png", f"(a) $S_h$, spacing {spacing:g}"), ("cut_active_tets.png", "(b) active tetrahedra"))):
        ax = fig.add_subplot(gs[0, k])
        ax.imshow(read_png(out / name))
        ax.set_title(title)
        ax.set_axis_off()
    ax = fig.add_subplot(gs[0, 2])
    ax.add_collection(PolyCollection(tri[tri[:, :, 0].mean(axis=1) > 0], facecolors="#dbe6f4", edgecolors="none"))
    ax.add_collection(LineCollection(edges[edges[:, :, 0].mean(axis=1) > 0], colors="#1f3b70", linewidths=0.5))
    ax.add_collection(LineCollection(segments[segments[:, :, 0].mean(axis=1) > 0], colors="#c0392b", linewidths=1.8))
    tt = np.linspace(0, 2 * np.pi, 200)
    ax.plot(R_MAJOR + R_MINOR * np.cos(tt), R_MINOR * np.sin(tt), ":", color="k", lw=0.8)
    ax.set_xlim(0.35, 1.65)
    ax.set_ylim(-0.65, 0.65)
    ax.set_aspect("equal")
    ax.set_xlabel("$x$")
    ax.set_ylabel("$z$")
    ax.set_title(f"(c) section $y = {SECTION_Y:g}$")
    return save_figure(fig, out, "cut_mesh")


@figure_style
def _convergence_figure(out, data):
    h = np.array(data["h"])
    fig, ax = new_figure(4.2, 3.0)
    loglog_with_rates(ax, h, data["l2_error"], "$\\|H^e - H_h\\|_{L^2(S_h)}$", marker="o", color="#c0392b", lw=1.5)
    loglog_with_rates(ax, h, data["area_error"], "$|\\,|S_h| - |S|\\,|$", marker="s", color="#1f3b70", lw=1.2, ls="--")
    rate_triangle(ax, h, data["l2_error"], 1)
    rate_triangle(ax, h, data["area_error"], 2)
    ax.set_xlabel("$h = N^{-1/3}$ (background nodes)")
    ax.set_ylabel("error")
    ax.set_title(f"Cut torus, $\\tau_F = {TAU_F:g}$, $\\tau_E = {TAU_E:g}$")
    ax.grid(True, which="major", alpha=0.3)
    log_ticks(ax)
    ax.legend(loc="lower right")
    return save_figure(fig, out, "cut_convergence")


def _sci(x) -> str:
    return "--" if x is None or not np.isfinite(x) else f"{x:.2e}"


def run(out: Path, size: str = "quick", progress=print) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    levels = levels_for(size)
    res = _solve(levels, progress)
    recs = res.records
    h = [r["h"] for r in recs]
    data = {
        "study": NAME,
        "size": size,
        "surface": {"name": "torus", "R": R_MAJOR, "r": R_MINOR},
        "box": list(BOX),
        "background": "structured, 6 Kuhn tetrahedra per cube",
        "tau_f": TAU_F,
        "tau_e": TAU_E,
        "face_h_power": 0.0,
        "h_definition": "N^(-1/3), N = number of background nodes",
        "spacing": levels,
        "h": h,
        "background_nodes": [r["background_nodes"] for r in recs],
        "nodes_on_surface": [nodes_on_surface(s) for s in levels],
        "active_tets": [r["active_tets"] for r in recs],
        "surface_triangles": [r["surface_triangles"] for r in recs],
        "interior_faces": [r["interior_faces"] for r in recs],
        "dofs": [r["dofs"] for r in recs],
        "l2_error": [r["l2_error"] for r in recs],
        "area": [r["area"] for r in recs],
        "exact_area": Torus(R_MAJOR, R_MINOR).area,
        "area_error": [r["area_error"] for r in recs],
        "integral_H": [roundoff_zero(r["integral_H"]) for r in recs],  # zero in exact arithmetic
        "integral_H_max": [roundoff_zero(float(np.max(np.abs(r["integral_H"])))) for r in recs],
        "solver": [r["solver"] for r in recs],
        "wall_time": [r["wall_time"] for r in recs],
        "time": [r["time"] for r in recs],
        "rates_l2": res.rates["l2_error"],
        "rates_area": res.rates["area_error"],
    }
    for key, short in (("l2_error", "l2"), ("area_error", "area")):
        e = np.array(data[key], float)
        data[f"rate_fit_{short}"] = float(np.polyfit(np.log(h), np.log(e), 1)[0])
        data[f"rate_last_{short}"] = float(np.log(e[-2] / e[-1]) / np.log(h[-2] / h[-1]))
    save_json(out, "cut_convergence", data)
    save_csv(
        out,
        "cut_convergence",
        [
            {k: data[k][i] for k in ("spacing", "h", "background_nodes", "nodes_on_surface", "active_tets", "dofs", "l2_error", "area", "area_error", "integral_H_max", "wall_time")}
            for i in range(len(levels))
        ],
    )
    header = ["spacing", "$h$", "active tets", "dofs", "$L^2$ error", "rate", "area error", "rate", "$\\max_k |\\int_{S_h} H_{h,k}|$"]
    rows = [
        [f"{s:g}", f"{h[i]:.4f}", str(data["active_tets"][i]), str(data["dofs"][i]), _sci(data["l2_error"][i]),
         "--" if i == 0 else fmt_rate(data["rates_l2"][i - 1]), _sci(data["area_error"][i]),
         "--" if i == 0 else fmt_rate(data["rates_area"][i - 1]), fmt_roundoff(data["integral_H_max"][i])]
        for i, s in enumerate(levels)
    ]
    save_latex_table(out, "cut_errors", header, rows)
    _convergence_figure(out, significant(data))  # the digits the tables carry

    progress(f"pictures of the cut at spacing {PICTURE_SPACING}")
    pic = recs[levels.index(PICTURE_SPACING)] if PICTURE_SPACING in levels else _solve([PICTURE_SPACING], progress).records[0]
    _mesh_figure(out, pic["fields"]["surface"], pic["fields"]["active_mesh"], PICTURE_SPACING)
    progress("done")
    return {"levels": levels, "rate_fit_l2": data["rate_fit_l2"], "rate_last_l2": data["rate_last_l2"], "rate_fit_area": data["rate_fit_area"]}


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
