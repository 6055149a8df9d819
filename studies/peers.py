"""Side by side with a peer: cutfem and ngsxfem (NGSolve + xfem) on the identical cut mean
curvature, fictitious-domain Poisson and cut Stokes problems, and the meshed torus against the
cotangent Laplacian.

Both codes solve the same discrete problems: ngsxfem on cutfem's own tets, level set and penalties
(:mod:`cutfem.studies.peers_ngsxfem` says how, and how it meets the exact zeros of the level set:
the zero rules ``+eps`` and ``+eps-cutfem-active``, and the ``shifted`` torus).  Each record
checks that both codes have the same number of active tets, ghost faces and unknowns
(``same_problem``).  cutfem runs through ``cutfem.run("mean-curvature-cut", levels=[s], tau_f=0.1,
solver="direct")``, so that both codes solve with a sparse direct factorization.

What the remaining difference is
--------------------------------
With netgen's vertex order the errors differ by 2.4e-7 (relative) at spacing 0.2 and 1e-8 or less
below: both codes split a quadrilateral piece of S_h into two triangles, along diagonals that
depend on the vertex order of the tet, and a degree-4 rule on two different triangulations of the
same planar quadrilateral gives different values for a non-polynomial integrand.  Measured at
spacing 0.2: the difference is 2.4e-7, 2.1e-9, 6.3e-11 at quadrature degree 4, 6, 8; and with the
tets handed to NGSolve in cutfem's own vertex order (``orientation="cutfem"``) it is 5e-15 at
degree 4.  The study repeats the ngsxfem solve in cutfem's vertex order at spacings >= 0.05
(``same_vertex_order``).

Timings (seconds; quick and full keep the faster of two runs at spacings >= 0.05, one run below)
-----------------------------------------------------------------------------------------------
ngsxfem: ``mesh`` (materialize cutfem's points/tets, boundary triangles, netgen and NGSolve meshes),
``levelset`` (nodal values, GridFunction), ``cut`` (CutInfo, IF elements, ghost facets, compressed
space), ``assembly`` (bilinear form and the three linear forms), ``solve`` (factorization + three
solves; NGSolve's default ``sparsecholesky``), ``errors``.  NGSolve runs single-threaded (no
``TaskManager``); at spacings >= 0.025 the pipeline is timed once more inside ``TaskManager()``
(all cores, mesh build reused).  cutfem: the problem's own stages ``geometry`` (box, level set,
cut, space), ``assembly``, ``solve`` (:class:`~cutfem.solvers.solve.DirectSolver`: banded Cholesky after
reverse Cuthill-McKee, or SuperLU for wide bands), ``errors``; its total is their sum (the run's wall
time, which also builds pyvista output fields, is recorded as ``wall``).  Same-solver comparison:
the NGSolve matrix exported (CSR) and factorized by cutfem's :class:`~cutfem.solvers.solve.DirectSolver`
(the same factorization choice), ``solve_superlu``.  Ratios are ngsxfem / cutfem.  Where cutfem's
default solver ("auto") is not the direct one (more than ``cutfem.solvers.solve.DIRECT_LIMIT`` unknowns)
cutfem is timed once more with it (``cutfem_auto``).  The structural
difference: ngsxfem's mesh, CutInfo, facet search and element/facet loops visit the whole
background mesh (8 times more per halving of the spacing) while cutfem visits only a band around
the surface (4 times more).

Memory: the NGSolve side needs about 350 bytes per background tet (1.86 GB peak at 4.7M tets,
spacing 0.025); a level whose estimate (:data:`~cutfem.studies.peers_ngsxfem.BYTES_PER_TET`)
exceeds 90 % of the available memory is skipped for ngsxfem with the reason recorded
(``ngsxfem_skipped``).

The meshed case
---------------
On the flipped and perturbed torus families (seed 0) the cotangent Laplacian with the mixed
Voronoi lumped mass (:func:`cutfem.studies.baselines.cotangent_mean_curvature`) against the stabilized
method (tau_E = 1/10): discrete error ||pi_h H - H_h||_{S_h} (P1 mass matrix), nodal maximum
error, and times (cotangent: the formula on a given mesh, best of three; stabilized: assembly +
solve from the problem's timer; both also end to end including the mesh), with the ratios
cotangent / stabilized.

Fictitious-domain Poisson (``--problem poisson``; ``both`` runs the two comparisons)
-----------------------------------------------------------------------------------
``cutfem.run("poisson-cut")`` (docs/math.md §8: unit ball in its default structured box, gamma = 10
with h_T, gamma_g = 0.1 with h_F^1 on the ghost faces of NEG, u = sin(pi x/2) cos(pi y/3) exp(z/2))
against :func:`~cutfem.studies.peers_ngsxfem.ngsxfem_poisson` on the same tets, the same snapped P1
level set (zeros -> +EPS and the collapsed tets not counted as cut), the same h_T and h_F, the same
quadrature degrees (2 for the form and the volume load, 4 for the Nitsche load and the errors).
Solvers: each code's fastest for this SPD system -- cutfem's default, CG
with the geometric multigrid on the nested Kuhn lattices; NGSolve's CG with Jacobi ("local"; its
multigrid needs a mesh hierarchy that an imported mesh does not have, BDDC on P1 keeps every
vertex in the coarse space, i.e. a direct solve, CG with h1amg stops at a wrong answer at 40k
unknowns; its sparse Cholesky is timed once per level as ``solve_direct``).  Each level runs both codes ``repeat`` times,
alternating, and reports the median.  Outputs ``peers_poisson.json``/``.csv`` and a table.

Stokes in the cut ball (``--problem stokes``)
---------------------------------------------
``cutfem.run("stokes-cut")`` (docs/math.md §12: P1-P1 in the unit ball, its default box and
parameters) against :func:`~cutfem.studies.peers_ngsxfem.ngsxfem_stokes`: the same tets, snapped
level set, h_T and h_F as the Poisson comparison, the same form term by term (Nitsche with
nu gamma / h_T, ghost penalties nu gamma_u h_F and gamma_p / nu h_F^3, Brezzi-Pitkaranta
(beta / nu) h_T^2 (grad p, grad q) over the cut parts), the same manufactured solution and
quadrature degrees.  What differs: the mean-value multiplier (cutfem a ``RealSpace`` field of the
product space; ngsxfem the assembled matrix bordered by (q, 1), because its ``NumberSpace`` beside
ghost facets makes the first assembly very slow), and the solvers, each code's fastest here.  cutfem:
its default, MINRES with multigrid on the velocity block and the pressure Schur approximation
(direct up to 5000 unknowns).  ngsxfem: NGSolve's MINRES with the block-diagonal preconditioner
diag(A, (1/nu) M_p + stabilization, nu |Omega_h|) factorized by its sparse Cholesky (exact block
solves: fewer iterations; cheaper than its direct solve of the whole matrix, which is timed once
per level beside it, ``ngsxfem_direct``).  Every run is a fresh process (:func:`stokes_level`):
stage times, the resident memory after the imports and the peak (VmHWM); ``repeat`` alternating
runs per code and the median total and median peak.  Outputs ``peers_stokes.json``/``.csv`` and a
table.

Outputs (prefix ``peers``): ``peers.json``, ``peers.csv`` (cut levels), ``peers_meshed.csv``,
``peers.png/.pdf`` (time against active tets for both codes; errors of both codes and their relative
difference; the meshed comparison).  Without ngsolve/xfem, ``run`` writes ``peers.json`` saying so
and returns ``{"skipped": 'install with pip install -e ".[peers]"'}``.
"""

from __future__ import annotations

import gc
import importlib
import math
import time
from pathlib import Path

import numpy as np

import cutfem
from cutfem.fem.norms import discrete_error
from cutfem.fem.spaces import SurfaceP1Space
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.geometry.markers import NEG
from cutfem.geometry.surface_meshes import torus_mesh
from cutfem.problems.common import background_for
from cutfem.runs.convergence import new_figure
from cutfem.solvers.solve import DIRECT_LIMIT

from .baselines import cotangent_mean_curvature
from .common import PAGE_WIDTH, figure_style, pick, save_csv, save_figure, save_json, study_main, torus_family
from .peers_ngsxfem import (BYTES_PER_TET, EPS, INSTALL, MINRES_TOL, ORDER, POISSON_GAMMA, POISSON_GAMMA_G, STOKES_PARAMS, TAU_F,
                            NgBackground, available_memory, ngsxfem_mean_curvature, ngsxfem_poisson, ngsxfem_stokes, peer_missing,
                            peer_versions)
from .performance_levels import _PEAK_CODE, fresh_process_result

NAME = "peers"
OUTPUTS = [NAME, f"{NAME}_meshed"]  # peers.json/.csv/.png/.pdf, peers_meshed.csv
POISSON_NAME = f"{NAME}_poisson"  # --problem poisson: peers_poisson.json/.csv
STOKES_NAME = f"{NAME}_stokes"  # --problem stokes: peers_stokes.json/.csv
#: ngsxfem's Stokes solver (the fastest here: block-preconditioned MINRES) and the direct one timed beside it
STOKES_SOLVER, STOKES_DIRECT = "minres", "sparsecholesky"
BOX = "-1.6,-1.6,-0.6,1.6,1.6,0.6"
TAU_E = 0.1
SHIFT = 1e-6 * np.sqrt([2.0, 3.0, 5.0]) / 3.0
SEED = 0
FAMILIES = ("flipped", "perturbed")
#: the ngsxfem pipeline is timed a second time inside TaskManager() at spacings >= this
TASKMANAGER_DOWN_TO = 0.025
#: ngsxfem is run a second time on tets in cutfem's vertex order at spacings >= this
SAME_ORDER_DOWN_TO = 0.05
#: at spacings >= this, quick and full time both pipelines twice and keep the faster run
REPEAT_DOWN_TO = 0.05


def _say(progress, msg):
    if progress:
        progress(msg)


# ---------------------------------------------------------------------------------------------
# the cutfem side
# ---------------------------------------------------------------------------------------------


def cutfem_mean_curvature(spacing, levelset="torus", box=None, tau_f=TAU_F, solver="direct") -> dict:
    kw = {} if box is None else {"box": box}
    t0 = time.perf_counter()
    res = cutfem.run("mean-curvature-cut", levels=[spacing], surface=levelset, tau_f=tau_f, solver=solver, **kw)
    wall = time.perf_counter() - t0
    r = res.records[0]
    rec = {k: r[k] for k in ("l2_error", "area", "dofs", "active_tets", "interior_faces", "background_nodes", "solver") if k in r}
    rec["time"] = dict(r["time"])
    rec["total"] = sum(r["time"].values())
    rec["wall"] = wall
    return rec


def _rel(a, b):
    return abs(a - b) / abs(b)


def _sig_digits(rel):
    return float("inf") if rel == 0 else float(-math.log10(rel))


def _stage_ratios(ng, cf):
    cg, ngt = cf["time"], ng["time"]
    ratios = {
        "geometry": (ngt["mesh"] + ngt["levelset"] + ngt["cut"]) / cg["geometry"],
        "assembly": ngt["assembly"] / cg["assembly"],
        "solve": ngt["solve"] / cg["solve"],
        "errors": ngt["errors"] / cg["errors"],
    }
    if "solve_superlu" in ng:
        ratios["solve_same_superlu"] = ng["solve_superlu"] / cg["solve"]
    return ratios


def compare_level(spacing, variant="paper", progress=None, taskmanager=False, repeat=1) -> dict:
    """Both codes at one spacing.  ``variant``: "paper" (the torus at the origin; when nodal values
    are zero, ngsxfem with the zero rules of :mod:`cutfem.studies.peers_ngsxfem`, the reported one being
    "+eps-cutfem-active") or "shifted" (torus moved by SHIFT, box given).  ``taskmanager``: time the
    ngsxfem pipeline once more inside ``ngsolve.TaskManager()`` (all cores; mesh build reused).
    ``repeat``: run both codes' pipelines this many times and keep the fastest run of each (the
    machine may be shared)."""
    import os

    import ngsolve

    if variant == "shifted":
        torus, box = Torus(center=tuple(SHIFT)), BOX
    else:
        torus, box = Torus(), None
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    _say(progress, f"cut {variant} spacing {spacing}: cutfem")
    cf = min((cutfem_mean_curvature(spacing, torus, box) for _ in range(repeat)), key=lambda r: r["total"])
    gc.collect()
    out = {"spacing": spacing, "variant": variant, "cutfem": cf, "load_average": load, "repeat": repeat}
    if cf["dofs"] > DIRECT_LIMIT:  # cutfem's default solver is not the direct one here: time it too
        _say(progress, f"cut {variant} spacing {spacing}: cutfem, solver auto")
        r = cutfem_mean_curvature(spacing, torus, box, solver="auto")
        out["cutfem_auto"] = dict(r, rel_diff_to_direct=_rel(r["l2_error"], cf["l2_error"]))
        gc.collect()
    n_tets = background_for(torus, spacing, "structured", box).n_tets  # lazy: nothing is built
    need, avail = BYTES_PER_TET * n_tets, available_memory()
    if avail is not None and need > 0.9 * avail:
        out["ngsxfem_skipped"] = f"the NGSolve mesh of {n_tets} tets needs about {need / 1e9:.1f} GB, {avail / 1e9:.1f} GB available"
        _say(progress, f"  ngsxfem skipped: {out['ngsxfem_skipped']}")
        return out
    _say(progress, f"cut {variant} spacing {spacing}: ngsxfem")
    background = NgBackground(spacing, torus, box)
    ng = ngsxfem_mean_curvature(spacing, torus, box, background=background)
    out["ngsxfem"] = ng
    if "failed" in ng:
        _say(progress, f"  ngsxfem failed ({ng['failed']}); zero rules +eps")
        out["ngsxfem_failed"] = ng["failed"]
        out["variants"] = {}
        for rule in ("+eps", "+eps-cutfem-active"):
            gc.collect()
            r = ngsxfem_mean_curvature(spacing, torus, box, zero_rule=rule, superlu=rule != "+eps", background=background)
            out["variants"][rule] = dict(r, rel_diff=_rel(r["l2_error"], cf["l2_error"]))
        out["ngsxfem"] = ng = out["variants"]["+eps-cutfem-active"]
    if taskmanager:
        gc.collect()
        with ngsolve.TaskManager():
            r = ngsxfem_mean_curvature(spacing, torus, box, zero_rule=ng["zero_rule"], superlu=False, background=background)
        out["ngsxfem_taskmanager"] = {"time": r["time"], "total": r["total"], "l2_error": r["l2_error"], "cores": os.cpu_count()}
    del background
    gc.collect()
    for _ in range(repeat - 1):
        r = ngsxfem_mean_curvature(spacing, torus, box, zero_rule=ng["zero_rule"])
        if r["total"] < ng["total"]:
            ng = dict(ng, time=r["time"], total=r["total"], solve_superlu=min(r["solve_superlu"], ng["solve_superlu"]))
        gc.collect()
    out["ngsxfem"] = ng
    if spacing >= SAME_ORDER_DOWN_TO:
        r = ngsxfem_mean_curvature(spacing, torus, box, zero_rule=ng["zero_rule"], superlu=False, orientation="cutfem")
        out["same_vertex_order"] = {"l2_error": r["l2_error"], "rel_diff": _rel(r["l2_error"], cf["l2_error"]), "total": r["total"]}
        gc.collect()
    out["rel_diff"] = _rel(ng["l2_error"], cf["l2_error"])
    out["significant_digits"] = _sig_digits(out["rel_diff"])
    out["same_problem"] = all(ng[k] == cf[k] for k in ("dofs", "active_tets", "interior_faces"))
    out["time_ratio"] = ng["total"] / cf["total"]
    out["stage_ratio"] = _stage_ratios(ng, cf)
    _say(progress, f"  errors {ng['l2_error']:.8g} (ngsxfem) {cf['l2_error']:.8g} (cutfem), rel diff {out['rel_diff']:.2e}, "
                   f"time {ng['total']:.2f} s / {cf['total']:.2f} s")
    return out


# ---------------------------------------------------------------------------------------------
# fictitious-domain Poisson (docs/math.md §8) in both codes
# ---------------------------------------------------------------------------------------------

def cutfem_poisson(spacing, solver="auto") -> dict:
    """cutfem's ``poisson-cut`` at one spacing (unit sphere, its default box, gamma = 10, gamma_g = 0.1);
    stage times from the problem's timer, total = their sum, wall = the whole run."""
    t0 = time.perf_counter()
    res = cutfem.run("poisson-cut", levels=[spacing], gamma=POISSON_GAMMA, gamma_g=POISSON_GAMMA_G, solver=solver)
    wall = time.perf_counter() - t0
    r = res.records[0]
    rec = {k: r[k] for k in ("l2_error", "h1_error", "volume", "dofs", "background_nodes", "solver", "solver_iterations")}
    rec["cut_tets"] = r["pieces"]  # the tets the surface cuts (active_tets: those of the NEG field)
    rec["time"] = dict(r["time"])
    rec["total"] = sum(r["time"].values())
    rec["wall"] = wall
    return rec


def cutfem_neg_sets(spacing, levelset=None) -> dict:
    """The sizes of cutfem's bulk problems (poisson-cut, stokes-cut) that ngsxfem reports too: the
    tets of NEG (the active set) and its ghost faces (untimed: one cut of the background)."""
    levelset = Sphere() if levelset is None else levelset
    cut = cut_mesh(background_for(levelset, spacing), levelset)
    return {"active_tets": int(cut.elements(NEG).n_elements), "ghost_faces": int(cut.ghost_facets(NEG).n_facets)}


def _median_run(runs):
    """The run with the median total (the lower middle one for an even count), with every total kept."""
    ordered = sorted(runs, key=lambda r: r["total"])
    return dict(ordered[(len(ordered) - 1) // 2], totals=[r["total"] for r in runs])


def compare_poisson_level(spacing, progress=None, repeat=1, also_direct=False) -> dict:
    """Both codes on the fictitious-domain Poisson problem at one spacing, ``repeat`` times each,
    alternating (cutfem, ngsxfem, cutfem, ...); the run with the median total is reported.
    ``also_direct``: the first ngsxfem run also times NGSolve's sparse Cholesky (``solve_direct``)."""
    import os

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    cfs, ngs_ = [], []
    for i in range(repeat):
        _say(progress, f"poisson spacing {spacing}: cutfem ({i + 1}/{repeat})")
        cfs.append(cutfem_poisson(spacing))
        gc.collect()
        _say(progress, f"poisson spacing {spacing}: ngsxfem ({i + 1}/{repeat})")
        ngs_.append(ngsxfem_poisson(spacing, Sphere(), also_direct=also_direct and i == 0))
        gc.collect()
    cf, ng = _median_run(cfs), _median_run(ngs_)
    if also_direct:
        ng.update({k: ngs_[0][k] for k in ("solve_direct", "direct_vs_solver")})
    cf.update(cutfem_neg_sets(spacing))
    out = {"spacing": spacing, "cutfem": cf, "ngsxfem": ng, "load_average": load, "repeat": repeat,
           "same_problem": all(ng[k] == cf[k] for k in ("dofs", "active_tets", "cut_tets", "ghost_faces")),
           "rel_diff_l2": _rel(ng["l2_error"], cf["l2_error"]), "rel_diff_h1": _rel(ng["h1_error"], cf["h1_error"]),
           "rel_diff_volume": _rel(ng["volume"], cf["volume"]), "time_ratio": ng["total"] / cf["total"]}
    _say(progress, f"  L2 {ng['l2_error']:.8g} (ngsxfem) {cf['l2_error']:.8g} (cutfem), rel diff {out['rel_diff_l2']:.1e}; "
                   f"time {ng['total']:.2f} s / {cf['total']:.2f} s")
    return out


def _poisson_row(c):
    cf, ng = c["cutfem"], c["ngsxfem"]
    row = {"spacing": c["spacing"], "dofs": cf["dofs"], "active_tets": cf["active_tets"], "ghost_faces": cf["ghost_faces"],
           "same_problem": c["same_problem"], "l2_cutfem": cf["l2_error"], "l2_ngsxfem": ng["l2_error"], "rel_diff_l2": c["rel_diff_l2"],
           "h1_cutfem": cf["h1_error"], "h1_ngsxfem": ng["h1_error"], "rel_diff_h1": c["rel_diff_h1"],
           "time_cutfem": cf["total"], "time_ngsxfem": ng["total"], "time_ratio": c["time_ratio"],
           "cutfem_solver": cf["solver"], "cutfem_iterations": cf["solver_iterations"], "ngsxfem_solver": ng["solver"],
           "ngsxfem_iterations": ng["solver_iterations"], "ngsxfem_solve_direct": ng.get("solve_direct"), "runs": c["repeat"]}
    row.update({f"cutfem_{k}": v for k, v in cf["time"].items()})
    row.update({f"ngsxfem_{k}": v for k, v in ng["time"].items()})
    return row


def _peer_unavailable(out: Path, name: str, size: str) -> bool:
    """True, with the reason printed and saved as the study's output ``name``, when ngsolve/xfem
    cannot be imported."""
    missing = peer_missing()
    if missing is None:
        return False
    print(f"peers: ngsolve/xfem not importable ({missing}); {INSTALL}")
    save_json(out, name, {"size": size, "peer": "ngsxfem", "available": False, "reason": missing, "skipped": INSTALL})
    return True


def run_poisson(out: Path, size: str = "quick", progress=None) -> dict:
    """The Poisson comparison: ``peers_poisson.json`` / ``.csv`` and a table on standard output."""
    out = Path(out)
    if _peer_unavailable(out, POISSON_NAME, size):
        return {"skipped": INSTALL}

    spacings = pick(size, [0.2], [0.1, 0.05], [0.05, 0.035, 0.025])
    levels = [compare_poisson_level(s, progress, repeat=1 if size == "tiny" or s < 0.05 else 3, also_direct=s >= 0.035)
              for s in spacings]
    rows = [_poisson_row(c) for c in levels]
    save_json(out, POISSON_NAME, {
        "size": size, "peer": "ngsxfem", "available": True,
        "versions": peer_versions(),
        "problem": {"domain": "unit ball (cutfem's default structured box)", "gamma": POISSON_GAMMA, "gamma_g": POISSON_GAMMA_G,
                    "nitsche_h": "h_T, longest edge of the cut tet", "ghost_h": "h_F^1, longest edge of the facet",
                    "exact": "sin(pi x/2) cos(pi y/3) exp(z/2)", "zero_nodal_values": f"ngsxfem: +{EPS:g}, collapsed tets not cut"},
        "solvers": {"cutfem": "solve(method='auto'): CG + geometric multigrid on the nested Kuhn lattices (direct up to 5000 unknowns)",
                    "ngsxfem": "NGSolve CG (rel. residual 1e-10) with Jacobi ('local'); solve_direct: its sparsecholesky"},
        "threads": "NGSolve without TaskManager (one thread); cutfem numpy/scipy",
        "timing": "median total of 3 alternating runs per code at spacings >= 0.05, one run below",
        "levels": levels, "table": rows,
    })
    save_csv(out, POISSON_NAME, rows)
    print(poisson_table(rows))
    return {"size": size, "table": rows}


def poisson_table(rows) -> str:
    """The Poisson comparison as a fixed-width text table."""
    head = f"{'spacing':>8} {'unknowns':>9} {'L2 cutfem':>11} {'L2 ngsxfem':>11} {'rel':>8} {'H1 cutfem':>10} {'H1 ngsxfem':>10} " \
           f"{'t cutfem':>9} {'t ngsxfem':>9} {'ratio':>6}"
    lines = [head]
    for r in rows:
        lines.append(f"{r['spacing']:>8g} {r['dofs']:>9d} {r['l2_cutfem']:>11.5e} {r['l2_ngsxfem']:>11.5e} {r['rel_diff_l2']:>8.1e} "
                     f"{r['h1_cutfem']:>10.5e} {r['h1_ngsxfem']:>10.5e} {r['time_cutfem']:>8.2f}s {r['time_ngsxfem']:>8.2f}s {r['time_ratio']:>6.1f}")
    return "\n".join(lines)

# ---------------------------------------------------------------------------------------------
# Stokes in the cut ball (docs/math.md §12) in both codes, each run in a fresh process
# ---------------------------------------------------------------------------------------------

_STOKES_CODE = _PEAK_CODE + """\
import json
from cutfem.studies.peers import stokes_level
print('RESULT ' + json.dumps(stokes_level({code!r}, {spacing!r}, {solver!r}, _peak)))
"""


def _resident_gib() -> float | None:
    """This process's resident memory now (VmRSS, GiB), None without /proc."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 2**20
    except OSError:
        return None
    return None


def import_peer(code) -> float | None:
    """Import ngsolve and xfem before a peer's level (cutfem's imports happen with the study's), then
    the resident memory at the level's start (GiB)."""
    if code == "ngsxfem":
        for module in ("ngsolve", "xfem"):
            importlib.import_module(module)
    return _resident_gib()


def stokes_level(code, spacing, solver, peak) -> dict:
    """One code's Stokes level (``code`` "cutfem": ``cutfem.run("stokes-cut")`` with ``solver``;
    "ngsxfem": :func:`~cutfem.studies.peers_ngsxfem.ngsxfem_stokes` with ``inverse=solver``) in the
    calling process, after its imports: the record with the resident memory before the level
    (``start_memory_gib``) and the process's peak after it (``peak()``, ``peak_memory_gib``)."""
    start = import_peer(code)
    if code == "cutfem":
        t0 = time.perf_counter()
        r = cutfem.run("stokes-cut", levels=[spacing], solver=solver).records[0]
        keep = ("l2_error_velocity", "h1_error_velocity", "l2_error_pressure", "volume", "dofs", "active_tets", "solver", "solver_iterations")
        rec = {k: r[k] for k in keep}
        rec.update(time=dict(r["time"]), total=sum(r["time"].values()), wall=time.perf_counter() - t0)
    else:
        rec = ngsxfem_stokes(spacing, inverse=solver)
    return dict(rec, start_memory_gib=start, peak_memory_gib=peak())


def _stokes_process(code, spacing, solver) -> dict:
    """:func:`stokes_level` in a fresh interpreter, with the wall time of the whole process
    (``process_wall``: interpreter start and imports included)."""
    t0 = time.perf_counter()
    rec = fresh_process_result(_STOKES_CODE.format(code=code, spacing=spacing, solver=solver), f"stokes {code} spacing {spacing}")
    return dict(rec, process_wall=time.perf_counter() - t0)


def _median_memory_run(runs):
    """:func:`_median_run`, with the median of the peaks (``peak_memory_gib``) and every peak kept."""
    peaks = sorted(r["peak_memory_gib"] for r in runs)
    return dict(_median_run(runs), peak_memory_gib=peaks[(len(peaks) - 1) // 2], peaks=[r["peak_memory_gib"] for r in runs])


STOKES_ERRORS = ("l2_error_velocity", "h1_error_velocity", "l2_error_pressure")


def compare_stokes_level(spacing, progress=None, repeat=1, direct=False) -> dict:
    """Both codes on ``stokes-cut`` at one spacing, each run in a fresh process ``repeat`` times,
    alternating (cutfem, ngsxfem, cutfem, ...); the run with the median total and the median peak
    memory are reported.  ``direct``: ngsxfem once more with NGSolve's direct solver
    (:data:`STOKES_DIRECT`, its own process: time and peak)."""
    import os

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    cfs, ngs_ = [], []
    for i in range(repeat):
        _say(progress, f"stokes spacing {spacing}: cutfem ({i + 1}/{repeat})")
        cfs.append(_stokes_process("cutfem", spacing, "auto"))
        _say(progress, f"stokes spacing {spacing}: ngsxfem ({i + 1}/{repeat})")
        ngs_.append(_stokes_process("ngsxfem", spacing, STOKES_SOLVER))
    cf, ng = _median_memory_run(cfs), _median_memory_run(ngs_)
    cf.update(cutfem_neg_sets(spacing))
    out = {"spacing": spacing, "cutfem": cf, "ngsxfem": ng, "load_average": load, "repeat": repeat,
           "same_problem": all(ng[k] == cf[k] for k in ("dofs", "active_tets", "ghost_faces")),
           "rel_diff": {k: _rel(ng[k], cf[k]) for k in STOKES_ERRORS},
           "time_ratio": ng["total"] / cf["total"], "memory_ratio": ng["peak_memory_gib"] / cf["peak_memory_gib"]}
    if direct:
        _say(progress, f"stokes spacing {spacing}: ngsxfem, {STOKES_DIRECT}")
        d = _stokes_process("ngsxfem", spacing, STOKES_DIRECT)
        out["ngsxfem_direct"] = {k: d[k] for k in ("time", "total", "peak_memory_gib", "residual", *STOKES_ERRORS)}
    _say(progress, f"  L2 u {ng['l2_error_velocity']:.8g} (ngsxfem) {cf['l2_error_velocity']:.8g} (cutfem); "
                   f"time {ng['total']:.2f} s / {cf['total']:.2f} s, peak {ng['peak_memory_gib']:.2f} / {cf['peak_memory_gib']:.2f} GiB")
    return out


def _stokes_row(c):
    cf, ng, d = c["cutfem"], c["ngsxfem"], c.get("ngsxfem_direct", {})
    row = {"spacing": c["spacing"], "dofs": cf["dofs"], "active_tets": cf["active_tets"], "ghost_faces": cf["ghost_faces"],
           "same_problem": c["same_problem"]}
    for k, short in zip(STOKES_ERRORS, ("l2u", "h1u", "l2p")):
        row.update({f"{short}_cutfem": cf[k], f"{short}_ngsxfem": ng[k], f"rel_diff_{short}": c["rel_diff"][k]})
    row.update(time_cutfem=cf["total"], time_ngsxfem=ng["total"], time_ratio=c["time_ratio"], memory_cutfem_gib=cf["peak_memory_gib"],
               memory_ngsxfem_gib=ng["peak_memory_gib"], memory_ratio=c["memory_ratio"], start_memory_cutfem_gib=cf["start_memory_gib"],
               start_memory_ngsxfem_gib=ng["start_memory_gib"], process_wall_cutfem=cf["process_wall"], process_wall_ngsxfem=ng["process_wall"],
               cutfem_solver=cf["solver"], cutfem_iterations=cf["solver_iterations"], ngsxfem_solver=ng["solver"],
               ngsxfem_iterations=ng["solver_iterations"], time_ngsxfem_direct=d.get("total"), memory_ngsxfem_direct_gib=d.get("peak_memory_gib"),
               runs=c["repeat"], load_average=c["load_average"])
    row.update({f"cutfem_{k}": v for k, v in cf["time"].items()})
    row.update({f"ngsxfem_{k}": v for k, v in ng["time"].items()})
    return row


def run_stokes(out: Path, size: str = "quick", progress=None) -> dict:
    """The Stokes comparison: ``peers_stokes.json`` / ``.csv`` and a table on standard output."""
    out = Path(out)
    if _peer_unavailable(out, STOKES_NAME, size):
        return {"skipped": INSTALL}

    spacings = pick(size, [0.2], [0.2, 0.1], [0.2, 0.1, 0.075, 0.0625])
    levels = [compare_stokes_level(s, progress, repeat=pick(size, 1, 3, 3), direct=size != "tiny") for s in spacings]
    rows = [_stokes_row(c) for c in levels]
    save_json(out, STOKES_NAME, {
        "size": size, "peer": "ngsxfem", "available": True, "versions": peer_versions(),
        "problem": {"domain": "unit ball (cutfem's default structured box)", **STOKES_PARAMS,
                    "nitsche_h": "h_T, longest edge of the cut tet", "ghost_h": "h_F (velocity) and h_F^3 (pressure), longest edge of the facet",
                    "pressure_stabilization": "Brezzi-Pitkaranta -(beta/nu) h_T^2 (grad p, grad q) over the cut part of each tet, in both",
                    "mean_value": "cutfem: RealSpace multiplier; ngsxfem: the assembled matrix bordered by (q, 1) (a multiplier)",
                    "exact": "u = curl (sin y sin z, sin z sin x, sin x sin y), p = x y z + x^2 - y^2",
                    "zero_nodal_values": f"ngsxfem: +{EPS:g}, collapsed tets not cut"},
        "solvers": {"cutfem": "solve(method='auto'): MINRES, block preconditioner of multigrid on the velocity block and the pressure "
                              "Schur approximation (direct up to 5000 unknowns), rel. residual 1e-8",
                    "ngsxfem": f"NGSolve MinResSolver (tol {MINRES_TOL:g}, preconditioned norm), preconditioner diag(A, (1/nu) M_p + "
                               f"stabilization, nu |Omega_h|) factorized by sparsecholesky; direct: {STOKES_DIRECT} of the whole matrix"},
        "threads": "NGSolve without TaskManager (one thread); cutfem numpy/scipy/numba",
        "timing": "each run in a fresh process; median total and median peak (VmHWM) of the alternating runs; the machine was shared",
        "levels": levels, "table": rows,
    })
    save_csv(out, STOKES_NAME, rows)
    print(stokes_table(rows))
    return {"size": size, "table": rows}


def stokes_table(rows) -> str:
    """The Stokes comparison as a fixed-width text table (errors of both codes, times, peak memory, ratios)."""
    head = f"{'spacing':>8} {'unknowns':>9} {'L2 u cutfem':>12} {'ngsxfem':>12} {'H1 u cutfem':>12} {'ngsxfem':>12} " \
           f"{'L2 p cutfem':>12} {'ngsxfem':>12} {'max rel':>8} {'t cutfem':>9} {'t ngsxfem':>9} {'ratio':>6} " \
           f"{'GiB cutfem':>10} {'ngsxfem':>8} {'ratio':>6}"
    lines = [head]
    for r in rows:
        rel = max(r["rel_diff_l2u"], r["rel_diff_h1u"], r["rel_diff_l2p"])
        lines.append(f"{r['spacing']:>8g} {r['dofs']:>9d} {r['l2u_cutfem']:>12.6e} {r['l2u_ngsxfem']:>12.6e} {r['h1u_cutfem']:>12.6e} "
                     f"{r['h1u_ngsxfem']:>12.6e} {r['l2p_cutfem']:>12.6e} {r['l2p_ngsxfem']:>12.6e} {rel:>8.1e} {r['time_cutfem']:>8.2f}s "
                     f"{r['time_ngsxfem']:>8.2f}s {r['time_ratio']:>6.1f} {r['memory_cutfem_gib']:>10.2f} {r['memory_ngsxfem_gib']:>8.2f} "
                     f"{r['memory_ratio']:>6.2f}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# the meshed case: cotangent Laplacian with lumped mass against the stabilized method
# ---------------------------------------------------------------------------------------------


def meshed_level(family, n) -> list[dict]:
    """Two rows (cotangent + Voronoi lumped mass, stabilized tau_E = 1/10) on one torus mesh."""
    t0 = time.perf_counter()
    mesh = torus_mesh(n, family=family, seed=SEED)
    t_mesh = time.perf_counter() - t0
    space = SurfaceP1Space(mesh)
    He = Torus().exact_mean_curvature_vector(mesh.points)
    rows = []
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        H = cotangent_mean_curvature(mesh.points, mesh.triangles, mass="voronoi")
        best = min(best, time.perf_counter() - t0)
    rows.append(_meshed_row(family, n, mesh, "cotan-voronoi", H, He, space, best, best + t_mesh))
    t0 = time.perf_counter()
    res = cutfem.run("mean-curvature-meshed", levels=[n], surface="torus", tau_e=TAU_E, **torus_family(family, SEED))
    wall = time.perf_counter() - t0
    rec = res.records[0]
    H = np.asarray(rec["fields"]["surface"].point_data["H_h"])
    secs = rec["time"].get("assembly", 0.0) + rec["time"].get("solve", 0.0)
    rows.append(_meshed_row(family, n, mesh, "stabilized", H, He, space, secs, sum(rec["time"].values()), wall=wall))
    rows[1]["error_ratio_cotan_over_stabilized"] = rows[0]["discrete_error"] / rows[1]["discrete_error"]
    rows[1]["time_ratio_cotan_over_stabilized"] = rows[0]["seconds"] / rows[1]["seconds"]
    return rows


def _meshed_row(family, n, mesh, method, H, He, space, secs, end_to_end, wall=None):
    e = H - He
    row = {
        "family": family,
        "n": n,
        "nodes": int(mesh.n_points),
        "h": float(mesh.n_points) ** -0.5,
        "method": method,
        "discrete_error": discrete_error(space, e),
        "max_error": float(np.linalg.norm(e, axis=1).max()),
        "seconds": secs,
        "end_to_end": end_to_end,
    }
    if wall is not None:
        row["wall"] = wall
    return row


# ---------------------------------------------------------------------------------------------
# the study
# ---------------------------------------------------------------------------------------------


def _cut_row(c):
    cf, ng = c["cutfem"], c.get("ngsxfem")
    row = {
        "variant": c["variant"],
        "spacing": c["spacing"],
        "active_tets": cf["active_tets"],
        "dofs": cf["dofs"],
        "same_problem": c.get("same_problem"),
        "zero_nodes": None if ng is None else ng.get("zero_nodes", 0),
        "ngsxfem_zero_rule": None if ng is None else ng.get("zero_rule"),
        "error_cutfem": cf["l2_error"],
        "error_ngsxfem": None if ng is None else ng["l2_error"],
        "rel_diff": c.get("rel_diff"),
        "time_cutfem": cf["total"],
        "time_ngsxfem": None if ng is None else ng["total"],
        "time_ratio": c.get("time_ratio"),
    }
    for k, v in cf["time"].items():
        row[f"cutfem_{k}"] = v
    if ng is not None:
        for k, v in ng["time"].items():
            row[f"ngsxfem_{k}"] = v
        if "solve_superlu" in ng:
            row["ngsxfem_solve_superlu"] = ng["solve_superlu"]
        for k, v in c["stage_ratio"].items():
            row[f"ratio_{k}"] = v
    if "ngsxfem_taskmanager" in c:
        row["time_ngsxfem_taskmanager"] = c["ngsxfem_taskmanager"]["total"]
        row["time_ratio_taskmanager"] = c["ngsxfem_taskmanager"]["total"] / cf["total"]
    if "cutfem_auto" in c:
        row["cutfem_auto_solver"] = c["cutfem_auto"]["solver"]
        row["time_cutfem_auto"] = c["cutfem_auto"]["total"]
        row["cutfem_auto_solve"] = c["cutfem_auto"]["time"]["solve"]
        if row["time_ngsxfem"] is not None:
            row["time_ratio_vs_cutfem_auto"] = row["time_ngsxfem"] / c["cutfem_auto"]["total"]
    if "same_vertex_order" in c:
        row["error_ngsxfem_cutfem_order"] = c["same_vertex_order"]["l2_error"]
        row["rel_diff_cutfem_order"] = c["same_vertex_order"]["rel_diff"]
    if "ngsxfem_skipped" in c:
        row["ngsxfem_skipped"] = c["ngsxfem_skipped"]
    for rule, r in c.get("variants", {}).items():
        row[f"error_ngsxfem{rule}"] = r["l2_error"]
        row[f"rel_diff{rule}"] = r["rel_diff"]
    return row


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    if _peer_unavailable(out, NAME, size):
        return {"skipped": INSTALL}

    spacings = pick(size, [0.2], [0.2, 0.1, 0.05], [0.2, 0.1, 0.05, 0.025, 0.0125])
    shifted = pick(size, [], [0.1, 0.05], [0.1, 0.05, 0.025, 0.0125])
    levels_n = pick(size, [16, 32], [16, 32, 64, 128], [16, 32, 64, 128, 256, 512])

    repeat = pick(size, 1, 2, 2)
    cut = [compare_level(s, variant, progress, taskmanager=s >= TASKMANAGER_DOWN_TO, repeat=repeat if s >= REPEAT_DOWN_TO else 1)
           for variant, levels in (("paper", spacings), ("shifted", shifted)) for s in levels]
    meshed = []
    for family in FAMILIES:
        for n in levels_n:
            _say(progress, f"meshed {family} n={n}")
            meshed += meshed_level(family, n)

    rows = [_cut_row(c) for c in cut]
    summary = {
        "size": size,
        "peer": "ngsxfem",
        "available": True,
        "versions": peer_versions(),
        "problem": {"box": BOX, "torus": {"R": 1.0, "r": 0.5}, "tau_f": TAU_F, "face_h_power": 0, "error_quadrature_order": ORDER,
                    "shift": SHIFT.tolist(), "eps": EPS},
        "solvers": {"cutfem": "DirectSolver on the diagonally scaled matrix: LAPACK banded Cholesky after RCM (SuperLU for wide bands)",
                    "ngsxfem": "NGSolve sparsecholesky; solve_superlu: the NGSolve matrix through cutfem's DirectSolver"},
        "threads": "NGSolve without TaskManager (one thread); cutfem numpy/scipy",
        "cut": cut,
        "table": rows,
        "meshed": meshed,
    }
    save_json(out, NAME, summary)
    save_csv(out, NAME, rows)
    save_csv(out, f"{NAME}_meshed", meshed)
    _plot(out, rows, meshed)
    return {"size": size, "table": rows, "meshed": [r for r in meshed if r["method"] == "stabilized"]}


@figure_style
def _plot(out, rows, meshed):
    from matplotlib.ticker import NullFormatter

    fig, axes = new_figure(PAGE_WIDTH, 5.6, nrows=2, ncols=2)
    ax = axes[0, 0]
    for variant, mk in (("paper", "o"), ("shifted", "s")):
        sel = sorted((r for r in rows if r["variant"] == variant), key=lambda r: r["active_tets"])
        if not sel:
            continue
        ls = "-" if variant == "paper" else ":"
        ax.loglog([r["active_tets"] for r in sel], [r["time_cutfem"] for r in sel], marker=mk, color="C0", ls=ls,
                  label=f"cutfem ({variant})")
        ng = [r for r in sel if r["time_ngsxfem"] is not None]
        ax.loglog([r["active_tets"] for r in ng], [r["time_ngsxfem"] for r in ng], marker=mk, color="C3", ls=ls,
                  label=f"ngsxfem, 1 thread ({variant})")
        tm = [r for r in sel if r.get("time_ngsxfem_taskmanager") is not None]
        if tm:
            ax.loglog([r["active_tets"] for r in tm], [r["time_ngsxfem_taskmanager"] for r in tm], marker=mk, color="C1", ls=ls, mfc="none",
                      label=f"ngsxfem, TaskManager ({variant})")
        au = [r for r in sel if r.get("time_cutfem_auto") is not None]
        if au:
            ax.loglog([r["active_tets"] for r in au], [r["time_cutfem_auto"] for r in au], marker=mk, color="C2", ls="none", mfc="none",
                      label=f"cutfem, default solver ({variant})")
    ax.set_xlabel("active tets")
    ax.set_ylabel("wall time, end to end [s]")
    ax.set_title("cut torus: time (mesh, level set, cut, assembly, solve, error)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()

    ax = axes[0, 1]
    ax2 = ax.twinx()
    for variant, mk in (("paper", "o"), ("shifted", "s")):
        sel = sorted((r for r in rows if r["variant"] == variant), key=lambda r: r["spacing"])
        if not sel:
            continue
        ax.loglog([r["spacing"] for r in sel], [r["error_cutfem"] for r in sel], marker=mk, color="C0", ms=9, mfc="none",
                  ls="-" if variant == "paper" else ":", label=f"cutfem ({variant})")
        ng = [r for r in sel if r["error_ngsxfem"] is not None]
        ax.loglog([r["spacing"] for r in ng], [r["error_ngsxfem"] for r in ng], marker="x", color="C3", ls="none",
                  label=f"ngsxfem ({variant})")
        ax2.semilogy([r["spacing"] for r in ng], [max(r["rel_diff"], 1e-16) for r in ng], marker=mk, color="0.5", ls="--",
                     label=f"rel. difference ({variant})")
        same = [r for r in ng if r.get("rel_diff_cutfem_order") is not None]
        if same:
            ax2.semilogy([r["spacing"] for r in same], [max(r["rel_diff_cutfem_order"], 1e-16) for r in same], marker=mk, color="C4",
                         ls="none", mfc="none", label=f"rel. difference, cutfem's vertex order ({variant})")
        eps = [r for r in ng if r.get("rel_diff+eps") is not None]
        if eps:
            ax2.semilogy([r["spacing"] for r in eps], [r["rel_diff+eps"] for r in eps], marker="^", color="C2", ls="none",
                         label="rel. difference, ngsxfem zeros -> +eps")
    ax2.axhline(5e-4, color="0.7", lw=0.8)  # 3 significant digits
    ax2.set_ylim(1e-16, 1)
    ax.set_xscale("log")
    ax.set_xlabel("background spacing")
    ax.set_ylabel(r"$\|H^e - H_h\|_{L^2(S_h)}$")
    ax2.set_ylabel("relative difference of the errors (grey line: 3 digits)")
    ax.set_title("cut torus: error agreement")
    ax.grid(True, which="both", alpha=0.3)
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], loc="lower right")

    for col, (key, ylabel, title) in enumerate((
        ("discrete_error", r"$\|\pi_h H - H_h\|_{S_h}$", "meshed torus: cotangent + lumped mass vs stabilized"),
        ("seconds", "wall time [s] (formula / assembly + solve)", "meshed torus: time"),
    )):
        ax = axes[1, col]
        for j, family in enumerate(FAMILIES):
            for method, mk in (("cotan-voronoi", "v"), ("stabilized", "o")):
                sel = [r for r in meshed if r["family"] == family and r["method"] == method]
                x = [r["h"] for r in sel] if col == 0 else [r["nodes"] for r in sel]
                ax.loglog(x, [r[key] for r in sel], marker=mk, color=f"C{j}", ls="-" if method == "stabilized" else "--",
                          label=f"{method}, {family}")
        ax.set_xlabel(r"$h = N^{-1/2}$" if col == 0 else "surface nodes N")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    for ax in axes.ravel():
        ax.xaxis.set_minor_formatter(NullFormatter())
    save_figure(fig, out, NAME)


PROBLEMS = ("mean-curvature", "poisson", "stokes", "both")


def main(argv=None) -> int:
    """``python -m cutfem.studies.peers [--problem mean-curvature|poisson|stokes|both]`` plus the usual
    study options (``--out``, the size flags).  Default: the mean curvature comparison; ``both``: it
    and the Poisson one."""
    import argparse

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--problem", default="mean-curvature", choices=PROBLEMS,
                   help="which cut problem to compare with ngsxfem (default mean-curvature)")

    def run_selected(out, size, progress, problem):
        runners = {"mean-curvature": [run], "poisson": [run_poisson], "stokes": [run_stokes], "both": [run, run_poisson]}[problem]
        return [r(out, size, progress) for r in runners]

    return study_main(run_selected, NAME, p)(argv)


if __name__ == "__main__":
    raise SystemExit(main())
