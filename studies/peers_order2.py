"""Side by side with the peer at order 2: cutfem and ngsxfem with P2 fields on isoparametric cut
geometry, for fictitious-domain Poisson in the unit ball, TraceFEM Laplace-Beltrami on the unit
sphere and the mean curvature vector on the paper's cut torus (issue 48, item 7).

``python -m cutfem.studies.peers_order2 [--problem poisson|laplace-beltrami|mean-curvature|all]
[--tiny|--quick|--full] [--out DIR]``

The peer's scripts (:mod:`cutfem.studies.peers_ngsxfem_order2`) run ngsxfem's own isoparametric
pipeline on cutfem's structured tets.  cutfem runs through ``cutfem.run(problem, levels=[s],
order=2, ...)`` with the same parameters (:data:`PROBLEMS`), when the problem has an ``order``
parameter; a cutfem without it gets the note :data:`CUTFEM_MISSING` in its column and the peer
still runs.

Levels (spacings): tiny 0.2 and 0.1; quick 0.2, 0.1, 0.05; full adds 0.025.  Every level of every
code runs in a fresh process (as :mod:`cutfem.studies.peers`' Stokes comparison): stage times, the
total (their sum), the process's peak resident memory (VmHWM) and the resident memory after the
imports.  A level whose estimated peak (:data:`PEAK_BYTES_PER_TET` per background tet, measured)
exceeds 90 % of the available memory is skipped with the reason.  The machine may be shared: the
times are indicative.

Outputs (prefix ``peers_order2``): ``.json`` (records, rates, parameters, versions), ``.csv`` (one
row per problem, code and level), ``.tex`` (the table, also printed), ``.png``/``.pdf`` (errors
against unknowns of both codes, one panel per problem).  Without ngsolve/xfem the JSON says so and
``run`` returns ``{"skipped": ...}``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

import cutfem
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.problems.common import background_for
from cutfem.runs.convergence import new_figure
from cutfem.runs.registry import get_problem

from .common import PAGE_WIDTH, figure_style, pick, save_csv, save_figure, save_json, save_latex_table, study_main
from .peers import import_peer
from .peers_ngsxfem import INSTALL, available_memory, peer_missing, peer_versions
from .peers_ngsxfem_order2 import (LAPLACE_BELTRAMI_PARAMS, POISSON_PARAMS, ngsxfem_laplace_beltrami_p2,
                                   ngsxfem_mean_curvature_p2, ngsxfem_poisson_p2)
from .performance_levels import _PEAK_CODE, fresh_process_result

NAME = "peers_order2"
CUTFEM_MISSING = "cutfem order 2 not available in this version"
#: per problem: cutfem's problem and its parameters (the peer's, where cutfem has them: laplace-beltrami-cut's
#: names, ``stabilization`` "normal" with ``tau_n`` and ``normal_h_power``; the mean curvature vector each code
#: with its own order-2 default, cutfem's face term with a = 1 plus tau_N h J_N, whose multigrid converges where
#: the peer's h^-1 normal-gradient weight does not; Poisson: cutfem's gamma is multiplied by k^2 = 4 in its form, so the peer's
#: gamma 40 is cutfem's 10, and the peer's gamma_g weighs its patch ghost penalty, another term than cutfem's
#: derivative jumps, which keep cutfem's order-2 default), the peer's script, the exact geometry, the error keys (in both
#: records), the geometric error key
PROBLEMS = {
    "poisson": {"cutfem": "poisson-cut", "params": {"gamma": POISSON_PARAMS["gamma"] / 4}, "peer": ngsxfem_poisson_p2, "shape": Sphere(),
                "errors": ("l2_error", "h1_error"), "geometry": "volume_error"},
    "laplace-beltrami": {"cutfem": "laplace-beltrami-cut", "params": {"surface": "sphere", "stabilization": "normal", **LAPLACE_BELTRAMI_PARAMS},
                         "peer": ngsxfem_laplace_beltrami_p2, "shape": Sphere(), "errors": ("l2_error", "h1_error"), "geometry": "area_error"},
    "mean-curvature": {"cutfem": "mean-curvature-cut", "params": {"surface": "torus"}, "peer": ngsxfem_mean_curvature_p2,
                       "shape": Torus(), "errors": ("l2_error",), "geometry": "area_error"},
}
CODES = ("cutfem", "ngsxfem")
#: peak resident bytes per background tet of the peer's levels, with a margin: measured at spacing 0.05,
#: 1720 (Poisson, 511k tets, 0.82 GiB), 1740 (Laplace-Beltrami) and 1820 (mean curvature, 590k tets, 1.00 GiB),
#: the imports' 0.3 GiB included
PEAK_BYTES_PER_TET = 2500


def spacings_for(size: str) -> list[float]:
    return pick(size, [0.2, 0.1], [0.2, 0.1, 0.05], [0.2, 0.1, 0.05, 0.025])


def cutfem_order2_missing(problem: str) -> str | None:
    """None when cutfem's problem takes ``order`` (and the peer's parameters), else :data:`CUTFEM_MISSING`."""
    params = get_problem(PROBLEMS[problem]["cutfem"]).param_map()
    return None if "order" in params else CUTFEM_MISSING


def cutfem_params(problem: str) -> dict:
    """The peer's parameters that cutfem's problem has (the others keep cutfem's order-2 defaults)."""
    allowed = get_problem(PROBLEMS[problem]["cutfem"]).param_map()
    return {k: v for k, v in PROBLEMS[problem]["params"].items() if k in allowed}


_LEVEL_CODE = _PEAK_CODE + """\
import json
from cutfem.studies.peers_order2 import order2_level
print('RESULT ' + json.dumps(order2_level({code!r}, {problem!r}, {spacing!r}, _peak)))
"""


def order2_level(code: str, problem: str, spacing: float, peak) -> dict:
    """One code's level in the calling process, after its imports: the record (errors, unknowns,
    stage times, total) with the resident memory before the level and the peak after it."""
    spec = PROBLEMS[problem]
    start = import_peer(code)
    if code == "cutfem":
        t0 = time.perf_counter()
        r = cutfem.run(spec["cutfem"], levels=[spacing], order=2, keep_fields=False, **cutfem_params(problem)).records[0]
        measure = spec["geometry"].removesuffix("_error")  # "volume" or "area": |Omega_h| or |S_h| against the exact one
        rec = {k: r[k] for k in (*spec["errors"], measure, "dofs", "active_tets", "solver", "solver_iterations") if k in r}
        if measure in r:
            rec[spec["geometry"]] = abs(r[measure] - getattr(spec["shape"], measure))
        rec.update(time=dict(r["time"]), total=sum(r["time"].values()), wall=time.perf_counter() - t0)
    else:
        rec = spec["peer"](spacing)
    return dict(rec, start_memory_gib=start, peak_memory_gib=peak())


def _process(code, problem, spacing) -> dict:
    t0 = time.perf_counter()
    rec = fresh_process_result(_LEVEL_CODE.format(code=code, problem=problem, spacing=spacing), f"{problem} {code} spacing {spacing}")
    return dict(rec, process_wall=time.perf_counter() - t0)


def _too_big(problem, spacing) -> str | None:
    shape = PROBLEMS[problem]["shape"]
    n_tets = background_for(shape, spacing).n_tets  # lazy: nothing is built
    need, avail = PEAK_BYTES_PER_TET * n_tets, available_memory()
    if avail is not None and need > 0.9 * avail:
        return f"{n_tets} background tets need about {need / 1e9:.1f} GB, {avail / 1e9:.1f} GB available"
    return None


def compare_level(problem, spacing, progress=None) -> dict:
    """Both codes at one spacing, each in a fresh process: {"cutfem": record or {"note": ...},
    "ngsxfem": record or {"note": ...}} (a note when the level is too big, cutfem has no order 2, or
    the code's process failed: then also its ``failure``, the end of its standard error)."""
    out = {"problem": problem, "spacing": spacing}
    skip = _too_big(problem, spacing)
    for code in CODES:
        note = skip or (cutfem_order2_missing(problem) if code == "cutfem" else None)
        if note:
            out[code] = {"note": note}
            continue
        if progress:
            progress(f"{problem} spacing {spacing}: {code}")
        try:
            out[code] = _process(code, problem, spacing)
        except RuntimeError as exc:  # a code's failure is recorded; the other column still runs
            out[code] = {"note": f"{code} failed", "failure": str(exc)[-2000:]}
    return out


def rates(levels, code, key) -> list:
    """Rates of ``key`` between consecutive levels of ``code`` (None where either has no number)."""
    out = [None]
    for prev, cur in zip(levels, levels[1:]):
        a, b = prev[code].get(key), cur[code].get(key)
        ok = a is not None and b is not None and a > 0 and b > 0
        out.append(math.log(a / b) / math.log(prev["spacing"] / cur["spacing"]) if ok else None)
    return out


def table_rows(levels) -> list[dict]:
    """One row per problem, code and level: errors, rates, unknowns, stage times, total, memory."""
    rows = []
    for problem in dict.fromkeys(c["problem"] for c in levels):
        sel = [c for c in levels if c["problem"] == problem]
        spec = PROBLEMS[problem]
        for code in CODES:
            keys = (*spec["errors"], spec["geometry"])
            rate = {k: rates(sel, code, k) for k in keys}
            for i, c in enumerate(sel):
                r = c[code]
                row = {"problem": problem, "code": code, "spacing": c["spacing"], "dofs": r.get("dofs")}
                for k in keys:
                    row[k], row[f"{k}_rate"] = r.get(k), rate[k][i]
                row.update(total=r.get("total"), peak_memory_gib=r.get("peak_memory_gib"), start_memory_gib=r.get("start_memory_gib"),
                           solver=r.get("solver"), solver_iterations=r.get("solver_iterations"), note=r.get("note"))
                row.update({f"time_{k}": v for k, v in r.get("time", {}).items()})
                rows.append(row)
    return rows


def _num(x, fmt=".2e"):
    return "--" if x is None else format(x, fmt)


def latex_rows(rows) -> tuple[list, list]:
    header = ["problem", "code", "$h$", "unknowns", "$L^2$ error", "rate", "$H^1$ error", "rate", "geometry error", "rate",
              "time [s]", "peak [GiB]"]
    body = []
    for r in rows:
        if r["note"]:
            body.append([r["problem"], r["code"], f"{r['spacing']:g}", r["note"], *["--"] * 8])
            continue
        body.append([r["problem"], r["code"], f"{r['spacing']:g}", str(r["dofs"]), _num(r["l2_error"]), _num(r["l2_error_rate"], ".2f"),
                     _num(r.get("h1_error")), _num(r.get("h1_error_rate"), ".2f"), _num(r.get("volume_error", r.get("area_error"))),
                     _num(r.get("volume_error_rate", r.get("area_error_rate")), ".2f"), _num(r["total"], ".2f"), _num(r["peak_memory_gib"], ".2f")])
    return header, body


def run(out: Path, size: str = "quick", progress=None, problem: str = "all") -> dict:
    """The comparison at ``size`` for one problem or ``"all"``; writes the outputs and returns
    {"size", "table": rows} (or {"skipped": ...} without the peer)."""
    out = Path(out)
    missing = peer_missing()
    if missing is not None:
        print(f"{NAME}: ngsolve/xfem not importable ({missing}); {INSTALL}")
        save_json(out, NAME, {"size": size, "peer": "ngsxfem", "available": False, "reason": missing, "skipped": INSTALL})
        return {"skipped": INSTALL}
    problems = list(PROBLEMS) if problem == "all" else [problem]
    levels = [compare_level(p, s, progress) for p in problems for s in spacings_for(size)]
    rows = table_rows(levels)
    save_json(out, NAME, {
        "size": size, "peer": "ngsxfem", "available": True, "versions": peer_versions(), "order": 2,
        "problems": {p: {"cutfem_problem": PROBLEMS[p]["cutfem"], "params": PROBLEMS[p]["params"], "cutfem_params": cutfem_params(p),
                         "cutfem": cutfem_order2_missing(p) or "cutfem.run(..., order=2, **cutfem_params)"} for p in problems},
        "geometry": "ngsxfem: LevelSetMeshAdaptation(order=2), its P1 level set and P2 deformation, on cutfem's structured tets",
        "threads": "NGSolve without TaskManager (one thread); cutfem numpy/scipy/numba",
        "timing": "each level of each code in a fresh process, one run; the machine may be shared: times are indicative",
        "levels": levels, "table": rows,
    })
    save_csv(out, NAME, rows)
    header, body = latex_rows(rows)
    save_latex_table(out, NAME, header, body, caption="cutfem and ngsxfem at order 2 (P2 fields, isoparametric geometry)")
    _plot(out, rows)
    return {"size": size, "table": rows}


@figure_style
def _plot(out, rows):
    from matplotlib.ticker import NullFormatter

    problems = list(dict.fromkeys(r["problem"] for r in rows))
    fig, axes = new_figure(PAGE_WIDTH, 2.4, nrows=1, ncols=len(problems), squeeze=False)
    for ax, problem in zip(axes[0], problems):
        for code, color in zip(CODES, ("C0", "C3")):
            sel = [r for r in rows if r["problem"] == problem and r["code"] == code and r["dofs"] is not None]
            for key, ls, label in (("l2_error", "-", "$L^2$"), ("h1_error", "--", "$H^1$")):
                pts = [(r["dofs"], r[key]) for r in sel if r.get(key) is not None]
                if pts:
                    x, y = np.array(pts).T
                    ax.loglog(x, y, marker="o" if code == "cutfem" else "x", color=color, ls=ls, label=f"{code} {label}")
        ax.set_title(problem)
        ax.set_xlabel("unknowns per component" if problem == "mean-curvature" else "unknowns")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend()
    axes[0, 0].set_ylabel("error")
    save_figure(fig, out, NAME)


def main(argv=None) -> int:
    """``python -m cutfem.studies.peers_order2 [--problem ...]`` plus the usual study options."""
    import argparse

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--problem", default="all", choices=(*PROBLEMS, "all"), help="which problem to compare at order 2 (default all)")
    return study_main(run, NAME, p)(argv)


if __name__ == "__main__":
    raise SystemExit(main())
