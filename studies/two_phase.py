"""The static bubble of two-phase Stokes with surface tension: spurious currents and the pressure jump
against h, for both curvature routes and three viscosity ratios.

:mod:`cutfem.problems.two_phase_stokes` (``two-phase-stokes-cut``, docs/math.md §15): a ball of
radius 1/2 in [-1, 1]^3, tau = 1, exact u = 0 and p_NEG - p_POS = 2 tau / R = 4.  The surface
tension is -tau (H_h, <v>)_Gamma_h with H_h the stabilized mean curvature vector of docs/math.md §3
on the same cut (``discrete``), or -tau (grad_Gamma x, grad_Gamma <v>)_Gamma_h
(``laplace-beltrami``); the viscosities mu_inside : mu_outside are 1:1, 1:10 and 10:1.  Each
combination runs its levels through :func:`cutfem.run`.

A row records the route, the ratio, the spacing, h, the unknowns, the spurious velocity ||u_h||_L2
over both sides, the relative pressure-jump error (the means of the pressure over each side's cut
volume), the MINRES iterations, and the rates between levels.

Levels: ``tiny`` 0.25 and 0.2 (the tests); ``quick`` 0.2 and 0.1; ``full`` 0.2 to 0.025 (290 thousand unknowns
at 0.05, 2.2 million at 0.025).

Outputs (prefix ``two_phase``): ``.json``, ``.csv``, a LaTeX table and ``.png`` / ``.pdf`` (two panels:
the spurious velocity and the pressure-jump error against h, one colour per ratio, solid lines for
the discrete curvature and dashed for Laplace-Beltrami).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import cutfem

from .common import PAGE_WIDTH, figure_style, fmt_rate, pick, save_csv, save_figure, save_json, save_latex_table, study_main

NAME = "two_phase"
OUTPUTS = [NAME, f"{NAME}_table"]
PROBLEM = "two-phase-stokes-cut"
ROUTES = ("discrete", "laplace-beltrami")
#: (mu_inside, mu_outside)
RATIOS = ((1.0, 1.0), (1.0, 10.0), (10.0, 1.0))


def _rates(errors, hs):
    return [None] + [float(np.log(errors[i] / errors[i + 1]) / np.log(hs[i] / hs[i + 1])) for i in range(len(errors) - 1)]


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    levels = pick(size, [0.25, 0.2], [0.2, 0.1], [0.2, 0.1, 0.05, 0.025])
    rows = []
    for route in ROUTES:
        for mu_in, mu_out in RATIOS:
            if progress:
                progress(f"{route}, mu {mu_in:g}:{mu_out:g}")
            recs = cutfem.run(PROBLEM, levels=levels, curvature=route, mu_inside=mu_in, mu_outside=mu_out).records
            hs = [r["h"] for r in recs]
            velocity = [r["l2_error_velocity"] for r in recs]
            jump = [r["pressure_jump_error"] for r in recs]
            for r, level, rv, rp in zip(recs, levels, _rates(velocity, hs), _rates(jump, hs)):
                rows.append({"curvature": route, "mu_inside": mu_in, "mu_outside": mu_out, "spacing": level, "h": r["h"],
                             "dofs": int(r["dofs"]), "l2_error_velocity": r["l2_error_velocity"], "velocity_rate": rv,
                             "pressure_jump_error": r["pressure_jump_error"], "pressure_jump_rate": rp,
                             "solver_iterations": int(r["solver_iterations"])})
    finest = [r for r in rows if r["spacing"] == levels[-1]]
    summary = {"size": size, "levels": levels, "rows": rows,
               "largest_velocity_at_finest": max(r["l2_error_velocity"] for r in finest),
               "largest_pressure_jump_error_at_finest": max(r["pressure_jump_error"] for r in finest)}
    save_json(out, NAME, summary)
    save_csv(out, NAME, rows)
    header = ["curvature", "mu in:out", "spacing", "unknowns", "||u_h||", "rate", "jump error", "rate", "MINRES"]
    table = [[r["curvature"], f"{r['mu_inside']:g}:{r['mu_outside']:g}", f"{r['spacing']:g}", str(r["dofs"]),
              f"{r['l2_error_velocity']:.3e}", fmt_rate(r["velocity_rate"]), f"{r['pressure_jump_error']:.3e}",
              fmt_rate(r["pressure_jump_rate"]), str(r["solver_iterations"])] for r in rows]
    save_latex_table(out, f"{NAME}_table", header, table,
                     caption="Static bubble (R = 1/2, tau = 1): spurious velocity ||u_h||, relative error of the pressure "
                             "jump 2 tau / R and MINRES iterations, by curvature route and viscosity ratio.")
    _plot(out, rows)
    return {k: summary[k] for k in ("size", "levels", "largest_velocity_at_finest", "largest_pressure_jump_error_at_finest")}


@figure_style
def _plot(out, rows):
    from cutfem.runs.convergence import log_ticks, new_figure

    fig, axes = new_figure(PAGE_WIDTH, 2.8, nrows=1, ncols=2)
    for k, (mu_in, mu_out) in enumerate(RATIOS):
        for route, style in zip(ROUTES, ("-", "--")):
            sel = [r for r in rows if r["curvature"] == route and (r["mu_inside"], r["mu_outside"]) == (mu_in, mu_out)]
            h = [r["h"] for r in sel]
            label = f"{route}, {mu_in:g}:{mu_out:g}"
            axes[0].loglog(h, [r["l2_error_velocity"] for r in sel], style, marker="o", color=f"C{k}", label=label)
            axes[1].loglog(h, [r["pressure_jump_error"] for r in sel], style, marker="o", color=f"C{k}", label=label)
    axes[0].set_ylabel("spurious velocity ||u_h||")
    axes[1].set_ylabel("pressure-jump error")
    for ax in axes:
        ax.set_xlabel("h")
        ax.grid(True, which="major", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=3)
    for ax in axes:
        log_ticks(ax)
    save_figure(fig, out, NAME)


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
