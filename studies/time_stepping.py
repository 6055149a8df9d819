"""The surface heat equation's time steps under each solver: seconds, iterations and the final error.

For backward Euler (theta = 1, dt = h^2) and Crank-Nicolson (theta = 1/2, dt = h) on the cut sphere of
:mod:`cutfem.problems.heat_surface` (final time 1/2), every level runs with each of the steps'
solvers by :func:`cutfem.run`, one call per level, scheme and solver, in this process (after a warm-up
call per solver at the coarsest level, so that no timing includes an import or a compilation):

* ``direct``: one factorization of M_h + theta dt A_h, a solve with it every step;
* ``cg-jacobi``: CG with the inverse diagonal, each step from the quadratic through the last three
  solutions extrapolated to the new time (tolerance :data:`cutfem.problems.heat_surface.STEP_TOL`);
* ``cg-mg``: the same with the geometric multigrid.

The problem's ``solver="auto"`` picks one of these (direct up to
:data:`cutfem.problems.heat_surface.STEP_DIRECT_LIMIT` unknowns, then cg-jacobi for backward Euler
and cg-mg for Crank-Nicolson): this study is what that rule was read from.

A row records the unknowns, the steps, the solver, the mean CG iterations a step (0 for the
factor), the seconds of the steps and of the whole level (the sum of the record's stages: the
factorization is in "assembly"), the final L2 error and its relative difference from the
factorized steps' error at that level (the same discrete solution up to the steps' tolerance).  A
combination is not run, and its row says why, when it would take long for nothing: Jacobi under
Crank-Nicolson above :data:`JACOBI_CN_LIMIT` unknowns (its iterations grow like h^-1/2, and it is
slower than the factor at every level measured).

Levels: ``tiny`` 0.2 and 0.1; ``quick`` 0.1, 0.05 and 0.025; ``full`` down to 0.0125 (190 thousand
unknowns, 3200 backward Euler steps: about 4 minutes factorized, 1 minute by cg-jacobi).

Outputs (prefix ``time_stepping``): ``.json``, ``.csv`` and ``.png`` / ``.pdf`` (two columns, one per
scheme: the seconds of the whole level, factorization included, against the unknowns, and the CG
iterations a step).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import cutfem

from .common import PAGE_WIDTH, figure_style, pick, save_csv, save_figure, save_json, save_latex_table, study_main

NAME = "time_stepping"
OUTPUTS = [NAME]
PROBLEM = "heat-surface-cut"
SCHEMES = {1.0: "backward Euler", 0.5: "Crank-Nicolson"}
SOLVERS = ("direct", "cg-jacobi", "cg-mg")

#: Jacobi-CG under Crank-Nicolson is skipped above this many unknowns (150 iterations a step at
#: 47 thousand, slower than the factor there)
JACOBI_CN_LIMIT = 60_000


def _say(progress, msg):
    if progress:
        progress(msg)


def skip_reason(theta: float, solver: str, dofs: int | None) -> str | None:
    """Why a combination is not run (None: it is run); ``dofs`` None when not known yet."""
    if theta == 0.5 and solver == "cg-jacobi" and dofs is not None and dofs > JACOBI_CN_LIMIT:
        return f"Jacobi-CG under Crank-Nicolson above {JACOBI_CN_LIMIT} unknowns (iterations grow like h^-1/2)"
    return None


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    levels = pick(size, [0.2, 0.1], [0.1, 0.05, 0.025], [0.1, 0.05, 0.025, 0.0125])
    for solver in SOLVERS:  # warm-up: imports and compiled kernels out of the timings
        cutfem.run(PROBLEM, levels=[levels[0]], solver=solver)
    rows = []
    for theta, scheme in SCHEMES.items():
        for level in levels:
            dofs = None
            reference = None
            for solver in SOLVERS:
                row = {"scheme": scheme, "theta": theta, "spacing": level, "solver": solver}
                why = skip_reason(theta, solver, dofs)
                if why is not None:
                    rows.append({**row, "dofs": dofs, "status": "skipped", "reason": why})
                    continue
                _say(progress, f"{scheme}, spacing {level}, {solver}")
                rec = cutfem.run(PROBLEM, levels=[level], theta=theta, solver=solver).records[0]
                dofs = int(rec["dofs"])
                if solver == "direct":
                    reference = rec["l2_error"]
                rows.append({**row, "dofs": dofs, "status": "ok", "time_steps": int(rec["time_steps"]), "dt": rec["dt"],
                             "method": rec["solver"], "step_iterations": rec["step_iterations"],
                             "steps_s": rec["time"]["time steps"], "total_s": float(sum(rec["time"].values())),
                             "l2_error": rec["l2_error"],
                             "error_change": abs(rec["l2_error"] - reference) / reference})
    fastest = {}
    for theta, scheme in SCHEMES.items():
        for level in levels:
            ok = [r for r in rows if r["theta"] == theta and r["spacing"] == level and r["status"] == "ok"]
            fastest[f"{scheme}, {level}"] = min(ok, key=lambda r: r["total_s"])["solver"]
    summary = {"size": size, "levels": levels, "solvers": list(SOLVERS), "rows": rows, "fastest": fastest,
               "largest_error_change": max(r["error_change"] for r in rows if r["status"] == "ok")}
    save_json(out, NAME, summary)
    save_csv(out, NAME, rows)
    header = ["scheme", "spacing", "dofs", "steps", "solver", "its/step", "seconds", "L2 error", "vs direct"]
    table = [[r["scheme"], f"{r['spacing']:g}", str(r["dofs"]), str(r["time_steps"]), r["solver"],
              "--" if r["solver"] == "direct" else f"{r['step_iterations']:.1f}", f"{r['total_s']:.2f}",
              f"{r['l2_error']:.4e}", f"{r['error_change']:.1e}"] for r in rows if r["status"] == "ok"]
    save_latex_table(out, f"{NAME}_table", header, table,
                     caption="Surface heat equation: each scheme, spacing and solver; CG iterations a step, seconds of the "
                             "level, final L2 error and its relative change against the factorized steps.")
    _plot(out, rows)
    return {"size": size, "fastest": fastest, "largest_error_change": summary["largest_error_change"]}


@figure_style
def _plot(out, rows):
    from cutfem.runs.convergence import log_ticks, new_figure

    fig, axes = new_figure(PAGE_WIDTH, 4.2, nrows=2, ncols=len(SCHEMES), sharex="col")
    marks = {"direct": "s", "cg-jacobi": "o", "cg-mg": "^"}
    for col, (theta, scheme) in enumerate(SCHEMES.items()):
        for k, solver in enumerate(SOLVERS):
            sel = [r for r in rows if r["theta"] == theta and r["solver"] == solver and r["status"] == "ok"]
            if not sel:
                continue
            n = np.array([r["dofs"] for r in sel], dtype=float)
            axes[0, col].loglog(n, [r["total_s"] for r in sel], marker=marks[solver], color=f"C{k}", label=solver)
            if solver != "direct":
                axes[1, col].semilogx(n, [r["step_iterations"] for r in sel], marker=marks[solver], color=f"C{k}", label=solver)
        steps = sorted({(r["dofs"], r["time_steps"]) for r in rows if r["theta"] == theta and r["status"] == "ok"})
        axes[0, col].set_title(f"{scheme} ({', '.join(str(s) for _, s in steps)} steps)")
        axes[0, col].set_ylabel("seconds of the level")
        axes[1, col].set_ylabel("CG iterations a step")
        axes[1, col].set_xlabel("unknowns")
        axes[1, col].set_ylim(bottom=0)
        for ax in axes[:, col]:
            ax.grid(True, which="major", alpha=0.3)
        log_ticks(axes[0, col])
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(SOLVERS))
    save_figure(fig, out, NAME)


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
