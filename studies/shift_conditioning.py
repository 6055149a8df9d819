"""Condition numbers at orders 1 and 2 over random positions of the surface against the grid (part of
the higher-order study, :mod:`cutfem.studies.higher_order`; docs/math.md §17-§18).

For each system, order and spacing s, the unit sphere's centre is moved by 20 uniformly random vectors
in [0, s)^3 (seeded, :func:`cutfem.studies.bulk_conditioning.random_centers`; the grid's nodes stay
at multiples of s) and the 2-norm condition number of the diagonally scaled matrix
D^{-1/2} K D^{-1/2} is computed (:func:`cutfem.solvers.diagnose.condition_number`).  The systems:

* ``sphere-face`` and ``sphere-normal``: the Laplace-Beltrami trace system A_Gamma + M + stabilization
  on the cut sphere (P1 on S_h, P2 on Theta_h(S_h)), with the face stabilization tau_F h^a J_F
  (laplace-beltrami-cut's default; at order 2 J_F holds the jumps of the first and second normal
  derivatives) or the normal-gradient stabilization tau_N h^a (n_h . grad u, n_h . grad v) over the
  cut tets, each with laplace-beltrami-cut's parameters at that order (read from its registry entry
  and its ``auto`` choice: the normal-gradient term is tau_N h at order 1, tau_N h^-1 at order 2);
* ``sphere-mcv``: mean-curvature-cut's system M + J on the cut unit sphere with its default
  stabilization at each order (:meth:`MeanCurvatureCut.stabilization_for` of ``auto``: the face term at
  order 1; at order 2 the face term with a = 1 plus tau_N h J_N);
* ``ball``: poisson-cut's fictitious-domain system in the unit ball (Nitsche penalty gamma k^2, ghost
  penalty of order k, :class:`cutfem.studies.bulk_conditioning.PoissonParts`), down to spacing 0.2
  (0.1 at the full size: :data:`FINEST`).

Per (system, order, spacing): the min, median and max over the positions and their ratio max / min,
and whether the system is its problem's default at that order (``default``: laplace-beltrami-cut's
``auto`` is the face term at order 1 and the normal-gradient term at order 2; the mean curvature
system and the ball are always their problems' defaults);
per (system, order): the exponent p of the least-squares fit kappa ~ s^(-p) of the max and of the
median (expected p = 2, a stabilized method's condition number independent of the cut position).
The exponent between the last two spacings is recorded too: on coarse grids the smallest eigenvalue
may still belong to a boundary mode of a size nearly independent of s
(:mod:`cutfem.studies.bulk_conditioning`), so the fit over all spacings can sit below 2.

Measured (quick: spacings 0.4, 0.2, 0.1): every system at both orders varies by less than a factor
1.6 over the positions.  The normal-gradient stabilization gives kappa ~ h^-2 at both orders
(p = 2.02 with tau_N h at order 1; 2.10 with tau_N h and 2.02 with tau_N h^-1 at order 2).  The face stabilization gives it at order 1 (p = 1.82, 1.94 between the last
two) but not at order 2: kappa 3.2e5, 4.2e6, 6.6e7, p = 3.85 (4.0 between the last two), whatever
the power of h in front of J_F (a = -1, 0, 1 give the same smallest eigenvalue): a P2 field on the
band holds functions that neither the face jumps nor the trace on Gamma_h see to that order; hence
the order-2 defaults of both trace problems hold a normal-gradient term (docs/math.md §18).  The
mean curvature system with its defaults: p = 1.76 at order 1 (kappa 301, 927, 3.4e3) and 1.02 at
order 2 (face a = 1 plus tau_N h J_N: 5.3e3, 1.0e4, 2.2e4), within a factor 1.2 over the positions.  The
ball's kappa stays at about 1e4 at order 2 (80-190 at order 1) at these spacings: as at order 1
(:mod:`cutfem.studies.bulk_conditioning`), the smallest eigenvalue belongs to a boundary mode of a
size independent of s until the smooth first mode, O(s^2), drops below it.

Outputs (prefix ``higher_order_conditioning``): ``.json``, ``.csv`` (one row per system, order and
spacing), ``_table.tex`` and the figure (max and median against s, one panel per system).
"""

from __future__ import annotations

import time

import numpy as np

from cutfem.fem.forms import assemble
from cutfem.fem.spaces import CutSpace
from cutfem.fem.terms import face_jump_penalty, mass, normal_gradient_penalty, tangential_stiffness
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import CUT
from cutfem.geometry.shapes import Sphere
from cutfem.problems.common import background_for
from cutfem.problems.laplace_beltrami import LaplaceBeltramiCut
from cutfem.problems.mean_curvature import MeanCurvatureCut, mean_curvature_form
from cutfem.solvers.diagnose import condition_number

from .bulk_conditioning import PoissonParts, fitted_exponent, random_centers
from .common import PAGE_WIDTH, figure_style, save_csv, save_figure, save_json, save_latex_table

NAME = "higher_order_conditioning"
#: the systems, with their labels in the table and the figure
SYSTEMS = {"sphere-face": "sphere, face", "sphere-normal": "sphere, normal gradient",
           "sphere-mcv": "sphere, mean curvature (default)", "ball": "ball (Poisson)"}
#: random positions of the surface per spacing, and their seed
N_SHIFTS = 20
SEED = 2024
#: the finest spacing of a system at each size: the ball's P2 matrix at 0.05 (303 thousand unknowns of
#: a 3-D stencil) is beyond the sparse LU of :func:`condition_number` twenty times over, and at 0.1 (42
#: thousand unknowns, about a minute a position) only the full size takes it, so that ``cutfem
#: reproduce`` stays within minutes
FINEST = {"full": {"ball": 0.1}, "default": {"ball": 0.2}}


def _lb_parameters(order: int, stabilization: str) -> dict:
    """laplace-beltrami-cut's parameters of ``stabilization`` at ``order``: tau_f, face_h_power, tau_n,
    normal_h_power; those its ``auto`` takes when it picks this stabilization at this order, else the
    defaults of ``--stabilization`` ``stabilization``."""
    p = {q.name: q.default for q in LaplaceBeltramiCut.params}
    kind, tau_n, normal_h_power = LaplaceBeltramiCut.stabilization_for(p["stabilization"], order, p["tau_f"], p["face_h_power"],
                                                                       p["tau_n"], p["normal_h_power"])
    if kind == stabilization:
        p.update(tau_n=tau_n, normal_h_power=normal_h_power)
    return {k: p[k] for k in ("tau_f", "face_h_power", "tau_n", "normal_h_power")}


def sphere_matrix(center, spacing: float, order: int, stabilization: str):
    """laplace-beltrami-cut's matrix on the unit sphere centred at ``center``, on the grid of nodes at
    multiples of ``spacing``, with the stabilization "face" or "normal" and its parameters at ``order``
    (:func:`_lb_parameters`)."""
    if stabilization not in ("face", "normal"):
        raise ValueError(f"stabilization must be 'face' or 'normal', got {stabilization!r}")
    levelset = Sphere(1.0, center=center)
    cut = cut_mesh(background_for(levelset, spacing, anchored=True), levelset, order=order)
    space = CutSpace(cut, order=order)
    p = _lb_parameters(order, stabilization)
    if stabilization == "face":
        stab = p["tau_f"] * face_jump_penalty(cut.dF(cut.interior_facets(CUT)), h_power=p["face_h_power"])
    else:
        stab = p["tau_n"] * normal_gradient_penalty(cut.dx(CUT), h_power=p["normal_h_power"])
    ds = cut.ds()
    return assemble(tangential_stiffness(ds) + mass(ds) + stab, space).tocsr()


def mean_curvature_matrix(center, spacing: float, order: int):
    """mean-curvature-cut's matrix M + J on the unit sphere centred at ``center``, with its default
    stabilization at ``order`` (:meth:`MeanCurvatureCut.stabilization_for`)."""
    p = {q.name: q.default for q in MeanCurvatureCut.params}
    _, tau_f, face_h_power, tau_n, normal_h_power = MeanCurvatureCut.stabilization_for(
        p["stabilization"], order, p["tau_f"], p["face_h_power"], p["tau_n"], p["normal_h_power"])
    levelset = Sphere(1.0, center=center)
    cut = cut_mesh(background_for(levelset, spacing, anchored=True), levelset, order=order)
    form = mean_curvature_form(cut.ds(), tau_f=tau_f, faces=cut.dF(cut.interior_facets(CUT)), face_h_power=face_h_power,
                               tau_n=tau_n, band=cut.dx(CUT), normal_h_power=normal_h_power)
    return assemble(form, CutSpace(cut, order=order)).tocsr()


def is_default(system: str, order: int) -> bool:
    """Whether ``system`` is its problem's default at ``order`` (laplace-beltrami-cut's ``auto`` picks
    the sphere's stabilization by order)."""
    if system.startswith("sphere-") and system != "sphere-mcv":
        p = {q.name: q.default for q in LaplaceBeltramiCut.params}
        kind = LaplaceBeltramiCut.stabilization_for(p["stabilization"], order, p["tau_f"], p["face_h_power"], p["tau_n"],
                                                    p["normal_h_power"])[0]
        return kind == system.split("-", 1)[1]
    return True


def system_matrix(system: str, center, spacing: float, order: int):
    """The matrix of one of :data:`SYSTEMS` for the surface centred at ``center``."""
    if system == "ball":
        return PoissonParts(center, spacing, order=order).matrix()
    if system == "sphere-mcv":
        return mean_curvature_matrix(center, spacing, order)
    if system.startswith("sphere-"):
        return sphere_matrix(center, spacing, order, system.split("-", 1)[1])
    raise ValueError(f"unknown system {system!r}; use one of {', '.join(SYSTEMS)}")


def shift_rows(spacings, systems=tuple(SYSTEMS), orders=(1, 2), n_shifts: int = N_SHIFTS, seed: int = SEED,
               progress=None, finest=FINEST["default"]) -> list[dict]:
    """One row per (system, order, spacing): the condition numbers over ``n_shifts`` positions
    (``kappas``), their min, median, max and ratio max / min, the unknowns (median) and how many
    matrices were not positive definite (``not_definite``, by :func:`condition_number`'s verdict)."""
    rows = []
    for system in systems:
        for order in orders:
            for s in [s for s in spacings if s >= finest.get(system, 0.0)]:
                if progress:
                    progress(f"condition numbers: {system}, order {order}, spacing {s:g}, {n_shifts} positions")
                t0 = time.perf_counter()
                kappas, dofs, bad = [], [], 0
                for c in random_centers(n_shifts, s, seed):
                    K = system_matrix(system, c, s, order)
                    kappa = condition_number(K)
                    kappas.append(float(kappa))
                    dofs.append(K.shape[0])
                    bad += kappa.cause is not None
                k = np.asarray(kappas)
                rows.append({"system": system, "order": order, "default": is_default(system, order), "spacing": s,
                             "dofs": int(np.median(dofs)),
                             "kappa_min": float(k.min()), "kappa_median": float(np.median(k)), "kappa_max": float(k.max()),
                             "ratio": float(k.max() / k.min()), "not_definite": int(bad), "kappas": kappas,
                             "seconds": time.perf_counter() - t0})
    return rows


def slopes(rows) -> dict:
    """"system_order" -> the fitted exponents p of kappa ~ s^(-p) of the max and the median over all
    spacings, and of the max between the last two."""
    out = {}
    for system in dict.fromkeys(r["system"] for r in rows):
        for order in sorted({r["order"] for r in rows if r["system"] == system}):
            sel = sorted((r for r in rows if r["system"] == system and r["order"] == order), key=lambda r: -r["spacing"])
            s = [r["spacing"] for r in sel]
            out[f"{system}_order{order}"] = {"max": fitted_exponent(s, [r["kappa_max"] for r in sel]),
                                             "median": fitted_exponent(s, [r["kappa_median"] for r in sel]),
                                             "max_last": fitted_exponent(s[-2:], [r["kappa_max"] for r in sel[-2:]])}
    return out


def conditioning_outputs(out, size: str, spacings, progress=None) -> dict:
    """The rows of :func:`shift_rows` at ``spacings``, their :func:`slopes`, and the files (module docstring)."""
    rows = shift_rows(spacings, progress=progress, finest=FINEST["full" if size == "full" else "default"])
    fits = slopes(rows)
    summary = {"size": size, "spacings": list(spacings), "n_shifts": N_SHIFTS, "seed": SEED, "rows": rows, "slopes": fits}
    save_json(out, NAME, summary)
    save_csv(out, NAME, [{k: v for k, v in r.items() if k != "kappas"} for r in rows])
    header = ["system", "order", "default", "spacing", "unknowns", "kappa median", "kappa max", "max / min", "slope (max)", "slope (median)"]
    table = []
    for r in rows:
        fit = fits[f"{r['system']}_order{r['order']}"]
        first = r["spacing"] == max(spacings)
        table.append([r["system"], str(r["order"]), "yes" if r["default"] else "", f"{r['spacing']:g}", str(r["dofs"]), f"{r['kappa_median']:.3g}",
                      f"{r['kappa_max']:.3g}", f"{r['ratio']:.2f}"]
                     + ([f"{fit['max']:.2f}", f"{fit['median']:.2f}"] if first else ["", ""]))
    save_latex_table(out, f"{NAME}_table", header, table,
                     caption=f"Condition numbers of the diagonally scaled matrices over {N_SHIFTS} random positions of the "
                             "sphere against the grid (seeded), orders 1 and 2; the exponent p of kappa ~ s^(-p) fitted over "
                             f"the spacings, on each system's first row ({size}).")
    _plot(out, rows, fits)
    return summary


@figure_style
def _plot(out, rows, fits):
    from cutfem.runs.convergence import log_ticks, new_figure

    fig, axes = new_figure(PAGE_WIDTH, 2.9, nrows=1, ncols=len(SYSTEMS))
    for ax, (system, title) in zip(axes, SYSTEMS.items()):
        for order, color in ((1, "C0"), (2, "C1")):
            sel = sorted((r for r in rows if r["system"] == system and r["order"] == order), key=lambda r: r["spacing"])
            s = [r["spacing"] for r in sel]
            p = fits[f"{system}_order{order}"]["max"]
            ax.loglog(s, [r["kappa_max"] for r in sel], "-", marker="o", color=color,
                      label=f"P{order} max" + (f" (p = {p:.2f})" if p is not None else ""))
            ax.loglog(s, [r["kappa_median"] for r in sel], "--", marker=".", color=color, label=f"P{order} median")
        ax.set_title(title)
        ax.set_xlabel("spacing s")
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize="small")
        log_ticks(ax)
    axes[0].set_ylabel(r"$\kappa(D^{-1/2} K D^{-1/2})$")
    save_figure(fig, out, NAME)
