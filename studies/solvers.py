"""Linear solvers on every registered problem: unknowns, method, CG iterations and solve time.

For every registered problem with a ``solver`` parameter (:func:`cutfem.available_problems`; the
heat equation on the cut surface, whose solver solves one system a time step, is left out: its
module docstring has its own table) and each of its choices

* ``auto``: direct up to :data:`cutfem.solvers.solve.DIRECT_LIMIT` unknowns, then CG with geometric
  multigrid where there is a hierarchy, else direct up to :data:`cutfem.solvers.solve.DIRECT_LIMIT_NO_MG`
  and CG with smoothed-aggregation AMG above;
* ``direct`` (banded Cholesky or SuperLU of the diagonally scaled matrix), ``cg-mg`` (CG with the
  geometric multigrid), ``cg-amg`` (CG with pyamg's smoothed aggregation), ``cg-jacobi`` (CG with
  the diagonal),

each level is solved by :func:`cutfem.run` (one call per level, ``keep_finished=True``) and one row
records: the unknowns (``dofs``: the size of the linear system; a product space counts all its
fields, and the mean-curvature problems solve one system with three right-hand sides), the method
actually used (``method``), the CG iterations (0 for a direct solve), the solve time
(``record["time"]["solve"]``: setup and iterations together), the end-to-end time of the level
(the sum of ``record["time"]``: geometry, assembly, solve, errors), the solve time per million
unknowns and the record's errors (``*_error``, ``*_error_<field>``: the same discrete solution up to the solver
tolerance, so they agree between the solvers to about 1e-5 relative: the relative residual 1e-8
(1e-6 for mean curvature) times the condition number; 6e-6 measured at the ``quick`` levels).

The cases: the fictitious-domain Poisson problem on a structured Kuhn background and on a
pytetwild background (``background="tetwild"``: no lattice, so ``cg-mg`` raises and ``auto`` picks
direct or ``cg-amg``; pytetwild is not deterministic, each solver meshes anew and the unknowns
differ by a few per cent between the solvers), the interface problem with the contrasts
a_inside : a_outside = 1 : 1 and 1 : 1000, the coupled bulk-surface problem, the Laplace-Beltrami
and mean-curvature problems on cut surfaces (spacing levels) and on meshed surfaces (levels n).

A combination is not run, and its row says why (``status = "skipped"``, ``reason``), when it would
be too slow: a direct solve of a 3-D bulk system above :data:`DIRECT_BULK_LIMIT` unknowns (its
fill-in grows like n^{4/3}; 40k unknowns took 14 s), a direct solve of a surface system above
:data:`DIRECT_SURFACE_LIMIT`, CG with Jacobi above :data:`JACOBI_LIMIT` (iterations grow like
1/h), CG with AMG on a surface system above :data:`AMG_SURFACE_LIMIT` (its iterations grow), and
every level after one that failed.  The unknowns of a level not yet solved are the ones
another solver found at that level, else an extrapolation from the finest level solved
(h^-3 for bulk, h^-2 for surface problems).  A combination that raises (``cg-mg`` without a
geometric hierarchy, a CG that does not converge) keeps its row with ``status = "error"`` and the
message; warnings raised by a solve (many CG iterations) are kept in ``warnings``.  Before the
timed runs each solver solves two small problems once (:func:`warm_up`), so that no timing includes
an import or the first compilation of a kernel.

Levels: ``tiny`` two small levels per problem (Poisson at 0.2 and 0.1: at 0.2 its multigrid
hierarchy is a single grid; one tetwild level: meshing costs about 1 s);
``quick`` up to about 50k unknowns per problem; ``full`` four levels per problem, for the bulk
problems up to 360k-570k unknowns, for the meshed ones n = 128 to 1024 (the torus 1024 x 512:
524k nodes) (peak memory measured with the automatic solver: 0.67 GB for
Poisson at spacing 0.05 (40k unknowns), 4.2 GB at 0.025 (292k); 1.9 GB for the interface problem
at 0.05 (125k)).

Outputs (prefix ``solvers``): ``.json`` (cases, limits and one row per level and solver; written
after each case too, with ``complete`` false until the last),
``.csv`` (the rows), ``.png`` / ``.pdf`` (two panels: CG iterations of the automatic choice
against the unknowns, with ``cg-mg`` at every level; solve seconds per million unknowns against the
unknowns for each solver).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import cutfem
from cutfem.runs.convergence import new_figure

from .common import PAGE_WIDTH, figure_style, pick, save_csv, save_figure, save_json, study_main

NAME = "solvers"
OUTPUTS = [NAME]

#: direct solves of 3-D bulk systems above this many unknowns are skipped
DIRECT_BULK_LIMIT = 60_000
#: direct solves of surface systems (cut or meshed) above this many unknowns are skipped
DIRECT_SURFACE_LIMIT = 300_000
#: CG with the Jacobi preconditioner above this many unknowns is skipped
JACOBI_LIMIT = 100_000
#: CG with AMG on a surface system above this many unknowns is skipped (on the cut torus its
#: iterations grow from 20 to 72 between 1k and 73k unknowns, 27 s at 73k)
AMG_SURFACE_LIMIT = 100_000

#: the interface contrasts a_inside : a_outside
CONTRASTS = (1.0, 1000.0)


def cases(size: str) -> list[dict]:
    """The problems of the study at a size: one dict per case with ``key`` (the label in the
    tables), ``problem`` (the registered name), ``params`` (passed to :func:`cutfem.run`),
    ``levels``, ``dim`` (3 for a bulk system, 2 for a surface one: the exponent of the
    extrapolation of the unknowns) and ``solvers`` (the problem's ``solver`` choices, ``auto``
    first)."""
    bulk = pick(size, [0.2, 0.1], [0.2, 0.1, 0.05], [0.1, 0.05, 0.025, 0.02])
    interface = pick(size, [0.4, 0.2], [0.2, 0.1, 0.07], [0.2, 0.1, 0.05, 0.035])
    coupled = pick(size, [0.4, 0.2], [0.2, 0.1, 0.05], [0.2, 0.1, 0.05, 0.025])
    tetwild = pick(size, [0.4], [0.2, 0.1], [0.2, 0.1, 0.05])
    cut_surface = pick(size, [0.4, 0.2], [0.1, 0.05, 0.025], [0.1, 0.05, 0.025, 0.0125])
    mc_cut = pick(size, [0.4, 0.2], [0.2, 0.1, 0.05, 0.025], [0.1, 0.05, 0.025, 0.0125])
    meshed = pick(size, [8, 16], [64, 128, 256], [128, 256, 512, 1024])
    spec = [
        ("poisson-cut", "poisson-cut", {}, bulk, 3),
        ("poisson-cut tetwild", "poisson-cut", {"background": "tetwild"}, tetwild, 3),
        *[(f"interface-poisson-cut 1:{c:g}", "interface-poisson-cut", {"a_outside": c}, interface, 3) for c in CONTRASTS],
        ("bulk-surface-cut", "bulk-surface-cut", {}, coupled, 3),
        ("laplace-beltrami-cut", "laplace-beltrami-cut", {}, cut_surface, 2),
        ("mean-curvature-cut", "mean-curvature-cut", {}, mc_cut, 2),
        ("laplace-beltrami-meshed", "laplace-beltrami-meshed", {}, meshed, 2),
        ("mean-curvature-meshed", "mean-curvature-meshed", {}, meshed, 2),
    ]
    problems = cutfem.available_problems()
    out = []
    for key, name, params, levels, dim in spec:
        if name not in problems:
            continue
        solver = problems[name].param_map().get("solver")
        if solver is None or not solver.choices:
            continue
        choices = ["auto"] + [c for c in solver.choices if c != "auto"]
        out.append({"key": key, "problem": name, "params": params, "levels": list(levels), "dim": dim, "solvers": choices,
                    "level_name": problems[name].level_name})
    return out


def predicted_dofs(case: dict, level, known: dict) -> int | None:
    """The unknowns of ``case`` at ``level``: measured by another solver (``known``: level ->
    dofs), else extrapolated from the finest measured level as dofs (l_known / l)^dim for spacings
    and dofs (l / l_known)^2 for the meshed levels n; None when nothing is known."""
    if level in known:
        return known[level]
    if not known:
        return None
    meshed = case["level_name"] != "spacing"
    ref = max(known) if meshed else min(known)
    ratio = (level / ref) ** 2 if meshed else (ref / level) ** case["dim"]
    return int(round(known[ref] * ratio))


def skip_reason(case: dict, solver: str, dofs: int | None) -> str | None:
    """Why a solver is not run on a system of ``dofs`` unknowns (None: it is run)."""
    if dofs is None:
        return None
    if solver == "direct":
        limit = DIRECT_BULK_LIMIT if case["dim"] == 3 else DIRECT_SURFACE_LIMIT
        if dofs > limit:
            return f"direct above {limit} unknowns ({dofs}; {'3-D bulk' if case['dim'] == 3 else 'surface'} system)"
    if solver == "cg-jacobi" and dofs > JACOBI_LIMIT:
        return f"cg-jacobi above {JACOBI_LIMIT} unknowns ({dofs})"
    if solver == "cg-amg" and case["dim"] == 2 and dofs > AMG_SURFACE_LIMIT:
        return f"cg-amg above {AMG_SURFACE_LIMIT} unknowns ({dofs}; surface system)"
    return None


def solve_row(case: dict, solver: str, level) -> dict:
    """Solve one level of a case with one solver (:func:`cutfem.run`); the row with ``status``
    "ok" or "error" (the exception's type and message in ``error``)."""
    row = _row(case, solver, level)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            res = cutfem.run(case["problem"], levels=[level], solver=solver, keep_finished=True, **case["params"])
        except Exception as exc:  # a bad parameter combination: kept, not hidden
            res, failure = None, {"error_type": type(exc).__name__, "message": str(exc)}
        else:
            failure = res.failure
    row["warnings"] = sorted({str(w.message) for w in caught}) or None
    if failure is not None:
        row.update(status="error", error=f"{failure['error_type']}: {failure['message']}")
        return row
    rec = res.records[0]
    times = rec.get("time", {})
    dofs = int(rec["dofs"])
    solve_s = float(times.get("solve", math.nan))
    row.update(
        status="ok",
        dofs=dofs,
        method=rec.get("solver"),
        iterations=rec.get("solver_iterations"),
        solve_s=solve_s,
        total_s=float(sum(times.values())),
        solve_s_per_M=solve_s / (dofs / 1e6) if dofs else None,
        **{k: float(v) for k, v in rec.items() if _is_error_key(k, v)},
    )
    return row


def _is_error_key(key: str, value) -> bool:
    """An error of the record (as :meth:`cutfem.runs.runner.RunResult.error_keys`: ``*_error`` and
    ``*_error_<field>``, not the solver's entries)."""
    return "_error" in key and not key.startswith("solver") and isinstance(value, (int, float)) and not isinstance(value, bool)


def _row(case, solver, level) -> dict:
    return {"case": case["key"], "problem": case["problem"], "params": dict(case["params"]), "solver": solver,
            "level_name": case["level_name"], "level": level, "status": None, "dofs": None, "method": None,
            "iterations": None, "solve_s": None, "total_s": None, "solve_s_per_M": None, "reason": None, "error": None}


def study_case(case: dict, progress=None) -> list[dict]:
    """All rows of one case: each solver over the levels, ``auto`` first (its unknowns decide the
    skips of the others); after a failed level the finer ones are skipped."""
    rows, known = [], {}
    for solver in case["solvers"]:
        failed_at = None
        for level in case["levels"]:
            if failed_at is not None:
                row = _row(case, solver, level)
                row.update(status="skipped", reason=f"failed at {case['level_name']} {failed_at:g}")
                rows.append(row)
                continue
            dofs = predicted_dofs(case, level, known)
            reason = skip_reason(case, solver, dofs)
            if reason is not None:
                row = _row(case, solver, level)
                row.update(status="skipped", reason=reason, dofs=dofs)
                rows.append(row)
                continue
            if progress:
                progress(f"{case['key']} {solver} {case['level_name']} {level:g}" + (f" (~{dofs} unknowns)" if dofs else ""))
            row = solve_row(case, solver, level)
            rows.append(row)
            if row["status"] == "ok":
                known.setdefault(level, row["dofs"])
            else:
                failed_at = level
    return rows


#: the warm-up runs: one and three right-hand sides, each on a level whose multigrid has two grids
#: (every kernel of the cycle and of CG runs; on one grid the cycle is the coarsest solve alone)
WARM_UP = (("poisson-cut", 0.1), ("mean-curvature-meshed", 64))


def warm_up() -> None:
    """Solve a Poisson level (one right-hand side) and a meshed mean curvature level (three) once
    with each solver, results discarded, so that the first timed solve of a method pays neither for
    importing it (pyamg's import: about 1 s) nor, after an install, for compiling the kernels it
    runs (the first multigrid solve of a fresh environment took 6.8 s at 3.6 thousand unknowns
    against 0.015 s once compiled; a level whose hierarchy is one grid runs none of the cycle's
    kernels)."""
    for solver in ("direct", "cg-mg", "cg-amg", "cg-jacobi"):
        for problem, level in WARM_UP:
            cutfem.run(problem, levels=[level], solver=solver)


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    todo = cases(size)
    warm_up()
    from cutfem.problems.mean_curvature import SOLVER_TOL
    from cutfem.solvers.krylov import DEFAULT_TOL
    from cutfem.solvers.solve import DIRECT_LIMIT, DIRECT_LIMIT_NO_MG

    rows = []
    summary = {
        "size": size,
        "limits": {"direct_bulk": DIRECT_BULK_LIMIT, "direct_surface": DIRECT_SURFACE_LIMIT, "jacobi": JACOBI_LIMIT,
                   "amg_surface": AMG_SURFACE_LIMIT,
                   "auto_direct_limit": DIRECT_LIMIT, "auto_direct_limit_no_mg": DIRECT_LIMIT_NO_MG, "cg_tolerance": DEFAULT_TOL,
                   "cg_tolerance_mean_curvature": SOLVER_TOL},
        "cases": todo,
        "rows": rows,
        "complete": False,
    }
    for case in todo:
        rows += study_case(case, progress)
        # the rows so far, so that a long run stopped part way keeps what it measured
        save_json(out, NAME, summary)
    summary["complete"] = True
    paths = [save_json(out, NAME, summary), save_csv(out, NAME, rows)]
    paths += plot(out, rows, todo)
    print(table(rows))
    for p in paths:
        print(p)
    iterations = {}
    for r in rows:
        iterations.setdefault(r["case"], {}).setdefault(r["solver"], []).append(r["iterations"] if r["status"] == "ok" else None)
    return {"size": size, "rows": rows, "iterations": iterations, "paths": [str(p) for p in paths],
            "errors": sum(r["status"] == "error" for r in rows), "skipped": sum(r["status"] == "skipped" for r in rows)}


def table(rows: list[dict]) -> str:
    """The rows as text: problem, solver, level, dofs, method, iterations, solve s, s per million
    unknowns, total s; a skipped or failed row gives its reason instead."""
    head = ["problem", "solver", "level", "dofs", "method", "its", "solve s", "s/M dofs", "total s"]
    lines = []
    for r in rows:
        base = [r["case"], r["solver"], f"{r['level']:g}"]
        if r["status"] == "ok":
            lines.append(base + [str(r["dofs"]), r["method"], str(r["iterations"]), f"{r['solve_s']:.3f}",
                                 f"{r['solve_s_per_M']:.2f}", f"{r['total_s']:.2f}"])
        else:
            text = r["reason"] if r["status"] == "skipped" else r["error"]
            lines.append(base + ["" if r["dofs"] is None else f"~{r['dofs']}", f"{r['status']}: {_short(text)}"])
    widths = [max([len(h)] + [len(line[j]) for line in lines if j < len(line) and not _is_note(line, j)]) for j, h in enumerate(head)]

    def fmt(cells):
        parts = []
        for j, c in enumerate(cells):
            if _is_note(cells, j):
                parts.append(c)  # the reason of a skip or error runs on to the end of the line
            else:
                parts.append(c.ljust(widths[j]) if j < 3 or j == 4 else c.rjust(widths[j]))
        return "  ".join(parts)

    return "\n".join([fmt(head), fmt(["-" * w for w in widths])] + [fmt(line) for line in lines])


def _is_note(cells, j) -> bool:
    return j == 4 and len(cells) == 5


def _short(text: str, n: int = 110) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 3] + "..."


#: colour and marker of each solver (the right panel uses the markers)
_SOLVER_STYLE = {"auto": ("k", "o"), "direct": ("C3", "s"), "cg-mg": ("C0", "^"), "cg-amg": ("C2", "D"), "cg-jacobi": ("C1", "v")}


def _ok(rows, case, solver):
    sel = [r for r in rows if r["case"] == case and r["solver"] == solver and r["status"] == "ok"]
    return sorted(sel, key=lambda r: r["dofs"])


@figure_style
def plot(out: Path, rows: list[dict], todo: list[dict]) -> list[Path]:
    """The two-panel figure at its printed size (PNG and PDF, :func:`save_figure`).

    Left: CG iterations against the unknowns (log x) per case, for ``auto`` where it chose an
    iterative method (filled markers, solid) and for ``cg-mg`` at every level (open markers,
    dashed; the tetwild case, which has no hierarchy, shows ``cg-amg`` instead).  Right: the solve
    seconds per million unknowns against the unknowns (log-log), one line per case and solver,
    colour and marker by solver."""
    from matplotlib.lines import Line2D

    fig, (ax1, ax2) = new_figure(PAGE_WIDTH, 3.6, nrows=1, ncols=2)
    colors = {c["key"]: f"C{i % 10}" for i, c in enumerate(todo)}
    for c in todo:
        key = c["key"]
        color = colors[key]
        auto = [r for r in _ok(rows, key, "auto") if r["method"] != "direct"]
        if auto:
            ax1.plot([r["dofs"] for r in auto], [r["iterations"] for r in auto], color=color, marker="o", ms=4, lw=1.0)
        other = "cg-mg" if any(r["status"] == "ok" for r in rows if r["case"] == key and r["solver"] == "cg-mg") else "cg-amg"
        cg = _ok(rows, key, other)
        if cg:
            ax1.plot([r["dofs"] for r in cg], [r["iterations"] for r in cg], color=color, marker="^" if other == "cg-mg" else "D",
                     mfc="none", ms=4, lw=0.7, ls="--")
        for solver in c["solvers"]:
            sel = [r for r in _ok(rows, key, solver) if r["solve_s_per_M"] and r["solve_s_per_M"] > 0]
            if sel:
                scolor, marker = _SOLVER_STYLE[solver]
                ax2.plot([r["dofs"] for r in sel], [r["solve_s_per_M"] for r in sel], color=scolor, marker=marker,
                         ms=3, lw=0.5, alpha=0.8, mfc="none")
    ax1.set_xscale("log")
    ax1.set_xlabel("unknowns")
    ax1.set_ylabel("CG iterations (relative residual $10^{-8}$;\nmean curvature $10^{-6}$)")
    ax1.set_title("filled: auto (CG levels); open, dashed: cg-mg (tetwild: cg-amg)", loc="left", fontsize=7)
    top = max([max(line.get_ydata()) for line in ax1.get_lines()] + [1])
    ax1.set_ylim(0, 1.75 * top)  # room for the legend above the curves
    ax1.grid(True, which="major", alpha=0.3)
    ax1.legend(handles=[Line2D([], [], color=colors[c["key"]], lw=1.0, label=c["key"]) for c in todo], fontsize=6, loc="upper left")
    ax2.set_xscale("log")
    ax2.set_yscale("log")
    ax2.set_xlabel("unknowns")
    ax2.set_ylabel("solve seconds per million unknowns")
    ax2.set_title("one line per problem and solver", loc="left", fontsize=7)
    ax2.grid(True, which="major", alpha=0.3)
    ax2.legend(handles=[Line2D([], [], color=col, marker=m, mfc="none", lw=0.7, label=s) for s, (col, m) in _SOLVER_STYLE.items()],
               fontsize=6, loc="upper left")
    return save_figure(fig, out, NAME)


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
