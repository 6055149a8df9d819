"""Sweep of the face stabilization tau_F h^a J_F for the cut mean curvature vector (torus).

For the torus (R, r) = (1, 1/2) on the paper's box [-1.6,1.6]^2 x [-0.6,0.6] (structured Kuhn
background, spacings 0.4/k, h = N^(-1/3) with N the number of background nodes), tau_E = 0 and

    K = M + tau_F J_F^a,   J_F^a = sum_F h_F^a ([n_F . grad u], [n_F . grad v])_F,
    a in {-1, 0, 1, 2},   tau_F on a logarithmic range 1e-3 .. 10,

with h_F the local size of the face (its longest edge, docs/math.md §2: a penalty on a cut uses
local sizes, not the table's h = N^(-1/3)), so that each setting is the system of
``cutfem run mean-curvature-cut --box PAPER_BOX --tau-f tau_F --face-h-power a``; we record the L2(S_h) error ||H^e - H_h|| (docs/math.md §5, degree-4 quadrature), its least-squares rate
over the spacings, and the scaled condition number of K (:func:`cutfem.studies.conditioning.scaled_condition`,
infinite when numerically singular).  The paper's setting is a = 0, tau_F = 1/10.  M and each J_F^a are
assembled once per spacing; the direct solver raises on a numerically singular K, which is recorded
("singular", no error), never hidden.

Outputs (prefix ``stabilization_sweeps``): ``.json``, ``.csv``, ``.png/.pdf`` (error at the finest
spacing, fitted rate and condition number against tau_F, one curve per a) and ``_table.tex``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from cutfem.fem.norms import fitted_rate, l2_error
from cutfem.runs.convergence import significant
from cutfem.geometry.cut import CUT
from cutfem.fem.forms import assemble
from cutfem.fem.terms import face_jump_penalty, position_load
from cutfem.geometry.shapes import Torus
from cutfem.solvers.diagnose import SolverError
from cutfem.solvers.solve import solve

from .common import PAGE_WIDTH, figure_style, fmt_rate, pick, save_csv, save_figure, save_json, save_latex_table, study_main
from .conditioning import PAPER_BOX, matrices, scaled_condition

NAME = "stabilization_sweeps"
OUTPUTS = [NAME, f"{NAME}_table"]
POWERS = (-1, 0, 1, 2)


def _say(progress, msg):
    if progress:
        progress(msg)


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    ks = pick(size, [2, 3], [2, 3, 4], [2, 4, 6, 8])
    taus = pick(size, [1e-3, 1e-1, 10.0], list(np.logspace(-3, 1, 5)), list(np.logspace(-3, 1, 9)))
    torus = Torus(R=1.0, r=0.5)
    rows = []
    for k in ks:
        s = 0.4 / k
        _say(progress, f"spacing {s:.4g}: {len(POWERS) * len(taus)} settings")
        space, M, _ = matrices(torus, s, box=PAPER_BOX)
        B = assemble(position_load(space.cut.ds()), space)
        faces = space.cut.dF(space.cut.interior_facets(CUT))
        for a in POWERS:
            J = assemble(face_jump_penalty(faces, h_power=a), space).tocsr()  # h_F^a face by face
            for tau in taus:
                K = (M + tau * J).tocsr()
                t0 = time.perf_counter()
                try:
                    H, _ = solve(K, B, method="direct")
                    err = l2_error(space, H, torus.exact_mean_curvature_vector)
                    status = "ok"
                except SolverError:
                    err, status = None, "singular"
                secs = time.perf_counter() - t0
                rows.append({"spacing": s, "h": space.h, "dofs": int(space.n_dofs), "a": a, "tau_f": float(tau),
                             "l2_error": err, "kappa": scaled_condition(K),
                             "status": status, "seconds": secs})

    settings = []
    for a in POWERS:
        for tau in taus:
            sel = [r for r in rows if r["a"] == a and r["tau_f"] == float(tau)]
            e = [r["l2_error"] for r in sel]
            ok = all(v is not None for v in e)
            settings.append({
                "a": a,
                "tau_f": float(tau),
                "h": [r["h"] for r in sel],
                "l2_error": e,
                "kappa": [r["kappa"] for r in sel],
                "rate": fitted_rate([r["h"] for r in sel], e) if ok else None,
                "last_rate": math.log(e[-2] / e[-1]) / math.log(sel[-2]["h"] / sel[-1]["h"]) if ok else None,
            })
    paper = next(s for s in settings if s["a"] == 0 and abs(s["tau_f"] - 0.1) < 1e-12) if any(abs(t - 0.1) < 1e-12 for t in taus) else None
    finest = [s for s in settings if s["l2_error"][-1] is not None]
    best = min(finest, key=lambda s: s["l2_error"][-1]) if finest else None
    summary = {
        "size": size,
        "spacings": [0.4 / k for k in ks],
        "powers": list(POWERS),
        "taus": [float(t) for t in taus],
        "h": settings[0]["h"],
        "paper_setting": paper,
        "best_at_finest": best,
        "settings": settings,
        "records": rows,
    }
    save_json(out, NAME, summary)
    save_csv(out, NAME, rows)
    _plot(out, significant(settings), taus)  # the digits the tables carry

    def fe(v):
        return "sing." if v is None else f"{v:.3e}"

    def fk(v):
        return r"$\infty$" if v is None or not math.isfinite(v) else f"{v:.1e}"

    header = ["$a$", r"$\tau_F$"] + [f"$e$, $h={h:.3f}$" for h in summary["h"]] + ["rate", r"$\kappa$ (finest)"]
    table = [[str(s["a"]), f"{s['tau_f']:.0e}"] + [fe(v) for v in s["l2_error"]] + [fmt_rate(s["rate"]), fk(s["kappa"][-1])] for s in settings]
    save_latex_table(out, f"{NAME}_table", header, table,
                     caption="Cut torus: L2 error of the mean curvature vector and scaled condition number for K = M + tau_F J_F, "
                     "J_F with the local face size h_F^a.")
    return {
        "size": size,
        "h": summary["h"],
        "rates": {f"a={s['a']},tau={s['tau_f']:.0e}": s["rate"] for s in settings},
        "kappa_finest": {f"a={s['a']},tau={s['tau_f']:.0e}": s["kappa"][-1] for s in settings},
        "paper_setting": paper,
        "best_at_finest": best,
    }


@figure_style
def _plot(out, settings, taus):
    from cutfem.runs.convergence import log_ticks, new_figure

    fig, axes = new_figure(PAGE_WIDTH, 2.6, nrows=1, ncols=3)
    colors = {a: f"C{i}" for i, a in enumerate(POWERS)}
    h_fine = settings[0]["h"][-1]
    for a in POWERS:
        sel = [s for s in settings if s["a"] == a]
        t = np.array([s["tau_f"] for s in sel])
        e = np.array([np.nan if s["l2_error"][-1] is None else s["l2_error"][-1] for s in sel])
        r = np.array([np.nan if s["rate"] is None else s["rate"] for s in sel])
        k = np.array([s["kappa"][-1] for s in sel], dtype=float)
        lab = f"$a = {a}$"
        axes[0].loglog(t, e, marker="o", color=colors[a], label=lab)
        axes[1].semilogx(t, r, marker="o", color=colors[a], label=lab)
        fin = np.isfinite(k)
        axes[2].loglog(t[fin], k[fin], marker="o", color=colors[a], label=lab)
        if (~fin).any():
            top = np.nanmax(k[fin]) * 10 if fin.any() else 1e16
            axes[2].loglog(t[~fin], np.full((~fin).sum(), top), ls="none", marker="v", ms=9, color=colors[a])
    for ax in axes:
        ax.axvline(0.1, color="gray", lw=0.8, ls=":")
        ax.set_xlabel(r"$\tau_F$")
        ax.grid(True, which="major", alpha=0.3)
    for ax in (axes[0], axes[2]):
        log_ticks(ax)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(POWERS))
    axes[0].set_ylabel(r"$\|H^e - H_h\|_{L^2(S_h)}$")
    axes[0].set_title(f"$L^2$ error, $h = {h_fine:.3f}$")
    axes[1].set_ylabel("fitted $L^2$ rate")
    axes[1].set_title("rate over all spacings")
    axes[2].set_ylabel(r"scaled condition number of $K$")
    axes[2].set_title(f"$\\kappa(K)$, $h = {h_fine:.3f}$")
    axes[0].annotate("paper", (0.1, axes[0].get_ylim()[1]), xytext=(3, -10), textcoords="offset points", color="gray")
    save_figure(fig, out, NAME)


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
