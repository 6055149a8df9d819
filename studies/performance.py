"""Performance benchmark: stage times, peak memory and sizes of the mean curvature problems, with a
lower bound for every stage, the fitted exponents, the commands of the targets timed end to end,
ngsxfem beside it, bulk Poisson, and the largest level that fits in memory.

Cut torus of docs/math.md §6 (box [-1.6,1.6]^2 x [-0.6,0.6], structured Kuhn background, tau_F = 0.1) at
spacings 0.1 ... 0.0125 (down to 0.003125 with ``--full``), and the meshed torus (flipped and
perturbed families, tau_E = 0.1) at n = 64 ... 768.  Every level runs in a fresh Python process, so
that its peak resident memory (VmHWM) is its own; the stages are timed with ``perf_counter``:

* cut: background mesh (a :class:`~cutfem.geometry.mesh.StructuredBox`, nothing stored), cut (band search,
  level-set values near the surface, marching tets), topology (interior faces of the active mesh);
* assembly: the matrix K = M + tau J (``matrix``: one form,
  :func:`~cutfem.problems.mean_curvature.mean_curvature_form`, as ``cutfem run`` assembles it; on
  the structured box the piece mass and the face penalty sum into one set of lattice slots) and the
  right-hand sides A x_k (``rhs``, :func:`~cutfem.fem.forms.position_load`, without A);
* solve: :func:`cutfem.solvers.solve.solve` with the automatic choice (setup and iterations together,
  with the method and iteration count recorded);
* errors: the L2 error on S_h (degree-4 quadrature).

Each level runs three times (once at the tiny size) and the fastest run is kept, with all the
totals recorded (``totals``).  Each level's process then runs the level a second time
(``warm``: its stage times, total, iterations and page faults).  The first run also pays the
start-up that falls inside the stages of a fresh process (numba's type registries on the first
compiled kernel, a few milliseconds for each cached kernel it loads) and the first touches of its
memory; the second pays only the stages' own work.  Between the two the process collects its
garbage (``gc.collect``): the objects of a level refer to each other (a cut and the element sets and
measures it caches), so they are freed by the cycle collector, not when the first run returns, and
without the collection the second run allocated fresh memory beside them and paid its first
touches again (spacing 0.00625, two runs each: 130-139 thousand page faults instead of 5 thousand,
the matrix 0.98-1.18 s instead of 0.56-0.59 s, the whole 4.8-6.3 s instead of 4.0-4.2 s).
``start_up`` is the first total minus the second.  The peak memory, CPU times and page faults are
the first run's (taken before the second starts).

Each level also records the CPU time of the timed stages split into user and system time, and the
number of page faults, in all and per stage (``stage_cpu``, printed for the cut levels): on a
virtual machine the system time of first touches of memory varies from
run to run (0.6-5 s at spacing 0.0125; 1.4-10 us a fault), so the user-time exponent is reported
beside the wall one.  Every level's process opts into the allocation settings of
:mod:`cutfem.memory` before it imports the stages, and each record keeps what was applied
(``allocator``).

Lower bounds per stage (``bounds`` of each cut level)
-----------------------------------------------------
An estimate, not a proof: each stage of a cut level is given the bytes it must at least move
through main memory, and its bound is bytes / B, with B the machine's sustained bandwidth measured
once per run (:func:`memory_bandwidth`: numpy copy ``a[:] = b`` and triad ``a = b + s c`` on three
arrays of 200 MiB, cut into one slice per thread of the kernels and streamed on all of them at
once, best of 5 each; the copy moves 2, the triad, two numpy passes, 5 array sizes; B is the
larger of the two rates).  The solver's kernels run on all the cores (:mod:`cutfem.jit`), so
the bound is that of the whole machine; the stages that run on one core are held to it too.  The ratio measured / bound says how far a stage is from
streaming its data once; the flop counts are not modelled.  With N unknowns (per component), T active
tets (one surface piece each), S triangles of S_h, F interior faces, nnz(K) the nonzeros of
K = M + tau J (CSR: 8-byte value + 4-byte column, 12 bytes a nonzero; row pointers neglected),
c = 3 right-hand sides and ``it`` CG iterations (the most over
the columns, so the solve bound may count a few iterations too many), the bytes of
:func:`stage_bytes` are:

=============  ==================================================================================
background     0: the box is lazy (its nodes and tets are computed on demand), O(1) work; no
               bandwidth bound, no ratio
cut            16 N (level-set value and node id of each band node written) + 72 T (four values
               read, four vertex ids and the tet id written, 8 bytes each) + 24 S (three vertex
               ids of each triangle written)
topology       96 T (the tets read; four face keys a tet written and read) + 32 F (the pair of
               tets and the two opposite vertices of each interior face written)
matrix         52 S (three vertex ids, tet id and area of each triangle of S_h read, 40 bytes, and
               its share of the vertices, about half a 24-byte vertex) + 48 F (the pair of tets,
               normal and weight of each interior face read) + 328 N (13 lattice slots of
               12 bytes a node zeroed, summed into and read by the CSR pass, and the diagonal)
               + 12 nnz(K) (the CSR written)
rhs            56 T (four dof numbers, type, normal and piece area of each tet read) + 24 N (the
               N x 3 result written)
solve          it (24 nnz(K) + 80 c N): per CG iteration, all c columns in one pass over each
               matrix: the double-precision product (12 bytes a nonzero) and the single-precision
               cycle on the finest level, the forward sweep from zero with its residual (the lower
               half of each row) and the backward sweep (1.5 passes of 8 bytes a nonzero: float32
               value, int32 index); per
               column the CG vectors x, r, p read and written and q, z read (64 N) and the
               single-precision right-hand side and correction of the cycle (16 N).  The coarse
               levels and the multigrid setup are left out.  A direct
               solve (it = 0): 12 nnz(K) + 24 N (K read once, the solution written; the factor
               not counted)
errors         80 Q S: Q = 6 points of the degree-4 triangle rule, each with its coordinates (24),
               weight (8) and the discrete and exact fields (2 x 24) written
=============  ==================================================================================

Each stage's record says so in ``bound_method``.  The stage's own time, from the second run of
its process, is compared with the bound (``ratio``), and so is the first run's (``ratio_fresh``).

Beside the bounds, the kernels that carry the solve, the numbering of the cut, and the cut,
topology, matrix and right-hand-side stages whole are timed against an existing compiled library
doing the same operation on the same data (``compiled_references``, :func:`compiled_references`;
not in ``--limit`` mode): the product K X against scipy's CSR product, a Gauss-Seidel sweep
against pyamg's, the Galerkin product against scipy's two sparse products, the numbering of the
active nodes against ``numpy.unique``, the cut stage against VTK's contour filter on the active
tets (marching tets alone), the topology stage against VTK's geometry filter (the faces of the
active tets matched), the matrix stage against scipy's COO-to-CSR sum of the element matrices and
the right-hand sides against ``numpy.bincount`` of the element vectors (the sums alone); on the
cut torus at 0.0125 (0.1 at the tiny size), cutfem on all threads and on one, the reference on
one, and the largest difference of the results.  ``stage_targets`` (:func:`stage_targets`) puts
the two side by side for each stage of the cut levels: the own time over the traffic bound at the
finest level, and cutfem's time on one thread over the compiled reference's (the stage whole, or
for the solve the worst of its kernels), within 2 times if either ratio is at most 2.  The errors
have no reference; the share of their time spent in the exact field's own evaluation (the
caller's function at the quadrature points; for the torus a compiled pass) is given instead
(``exact_share``).

Options of the command line (besides ``--out`` and the size flags)
------------------------------------------------------------------
* ``--peers``: the same cut torus level in ngsxfem (:func:`cutfem.studies.peers.ngsxfem_mean_curvature`
  on the same Kuhn tets, the same snapped level set, zeros to +1e-14 and the collapsed tets left
  out, so the same unknowns; NGSolve's sparse Cholesky, one thread), once per level in a fresh
  process, down to ``--peers-down-to`` (0.025: the NGSolve mesh of the whole background needs about
  400 bytes a background tet, 15 GB at 0.0125) and only where that fits in ``--memory-gib`` and
  in 90 % of the available memory; the ratio ngsxfem / cutfem of the stage sums (``ratio``).  cutfem
  keeps its automatic solver (CG with multigrid above 20 000 unknowns).  Without ngsolve/xfem a
  note is printed and saved (``peers.skipped``).
* ``--limit``: the cut torus at spacings 0.1, 0.05, ... (one run each, fresh processes, no second
  run in the process: a level near the memory limit runs once) until the
  next level's predicted peak exceeds ``--memory-gib`` (default 20) or 90 % of the memory
  available when it would start (:func:`limit_search`); records the largest level that ran and the
  prediction for the next (:func:`predict_next`: the fitted exponents, memory at least linear in the
  active tets).  The meshed levels are not run in this mode.
* ``--bulk``: fictitious-domain Poisson on the solid torus, ``cutfem run poisson-cut --surface torus
  --spacing S --json F`` in a fresh process per level (0.1, 0.05, 0.025; with ``--full`` also
  0.0125 and 0.01, 2.7 and 5.2 million unknowns, about 7.5 GiB at the finest; one run each):
  unknowns, wall time, stages, peak memory, time and memory per million unknowns.

End to end through the command line (``commands``; not in ``--limit`` mode): the commands of the
targets (:func:`command_targets`: ``cutfem run mean-curvature-cut --spacing 0.0125``, target 2 s;
``cutfem run mean-curvature-meshed --levels 768 --family F`` for the four families, target 1 s;
with ``--full`` also ``--spacing 0.003125``, target 40 s), each run as many times as the levels
in fresh processes, the runs of the commands interleaved; the wall time of the whole process
(interpreter start, imports and numba's start included, as from the shell), the median and range
of the runs, the peak, and whether the median meets the target.  Before any process is timed the
package's modules are compiled to bytecode (:func:`compile_bytecode`), as an install does: where
``PYTHONDONTWRITEBYTECODE`` is set and the checkout carries no current ``.pyc`` files, every
process would compile the sources again (86 ms a process on the 2-core machine, measured with the
meshed torus 16 x 8, 0.61 against 0.52 s).

Peak memory is each process's own VmHWM (``/proc/self/status``), not ``ru_maxrss``, which on Linux
also counts the parent's peak (the parent's address space at fork/exec).

Exponents (``exponents``): least-squares slopes of log(wall time), log(user CPU time),
log(peak memory) and log(stage time) against log(active tets) over the three finest cut levels
that ran (none with fewer than three), and of log(wall time) and log(peak) against log(unknowns)
for the bulk levels; with more than three cut levels at spacing :data:`EXPONENT_FROM` and finer
(``--full``), also the slopes over all of them (``cut from 0.025``).  The figure
``performance_scaling`` shows time and memory against active tets (cut, with ngsxfem when run) or
surface nodes (meshed) on log-log axes with the exponents;
``performance_bounds`` shows measured / bound per stage and level, the per-stage verdict of
``stage_targets`` (both ratios of each stage against the target 2) and, with ``--bulk``, the bulk
costs per million unknowns.
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from cutfem.runs.registry import Timer
from cutfem.studies.common import PAGE_WIDTH, Progress, figure_style, pick, save_figure, save_json, study_main
from cutfem.fem import element_kernels
from cutfem.solvers import multigrid_kernels
from cutfem.solvers import sparse_kernels

OUTPUTS = ["performance", "performance_scaling", "performance_bounds"]

BOX = ([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6])

#: the coarsest cut level of the second fit of the exponents (the range of the scaling target)
EXPONENT_FROM = 0.025

#: the timed stages of a cut level, in order
CUT_STAGES = ("background", "cut", "topology", "matrix", "rhs", "solve", "errors")

#: right-hand sides of the mean curvature system (one per coordinate)
COLUMNS = 3
#: bytes of one CSR nonzero: float64 value and int32 column index
CSR_BYTES = 12
#: bytes a fine-matrix nonzero moves per CG iteration (all columns at once): the double-precision
#: product (12) and 1.5 single-precision passes of the cycle (the forward sweep from zero with its residual reads
#: the lower half of each row, the backward sweep all of it; 8 each)
SOLVE_MATRIX_BYTES = 12 + 1.5 * 8
#: bytes a fine unknown moves per CG iteration and column: x, r, p read and written, q, z read (64),
#: the cycle's single-precision right-hand side and correction (16)
SOLVE_VECTOR_BYTES = 80
#: points of the degree-4 triangle rule the L2 error uses
ERROR_POINTS = 6

#: ngsxfem runs at spacings >= this by default (the NGSolve mesh covers the whole background)
PEERS_DOWN_TO = 0.025
#: the cut levels of --limit start here and halve
LIMIT_START = 0.1
#: the bulk levels of --full (poisson-cut on the solid torus): 0.01 has 5.2 million unknowns
BULK_FULL = [0.1, 0.05, 0.025, 0.0125, 0.01]


class StageTimer(Timer):
    """:class:`~cutfem.runs.registry.Timer` that also keeps, per stage, the process's user and system
    CPU seconds and minor page faults (``getrusage`` before and after): ``cpu[stage] = {"user",
    "system", "faults"}``.  On the 2-core virtual machine a first touch of memory costs 1.4-10 us
    of system time a page, so the faults say how much of a stage is the kernel's, not the code's
    (at spacing 0.003125 about 60 % of the cut and half of the matrix)."""

    def __init__(self):
        super().__init__()
        self.cpu = {}

    @contextmanager
    def __call__(self, stage):
        import resource

        r0 = resource.getrusage(resource.RUSAGE_SELF)
        try:
            with super().__call__(stage):
                yield
        finally:
            r1 = resource.getrusage(resource.RUSAGE_SELF)
            c = self.cpu.setdefault(stage, {"user": 0.0, "system": 0.0, "faults": 0})
            c["user"] += r1.ru_utime - r0.ru_utime
            c["system"] += r1.ru_stime - r0.ru_stime
            c["faults"] += r1.ru_minflt - r0.ru_minflt


def _timed_system_solve_error(t, space, surface, form, torus):
    """The stages shared by both kinds: the matrix K of ``form`` (one assembly, as ``cutfem run``),
    the right-hand sides B = A x over the measure ``surface`` (S_h) (``rhs``), the automatic solve
    and the L2 error; returns the record entries they give (``dofs``, ``nnz`` {"K": stored
    entries}, ``l2_error``, ``solver``, ``iterations``, ``exact_time``: the seconds of the errors
    stage spent in the exact field's own evaluation at the quadrature points) and the times
    of all the stages of ``t``."""
    from cutfem.fem.norms import l2_error
    from cutfem.fem.forms import assemble
    from cutfem.fem.terms import position_load
    from cutfem.problems.mean_curvature import SOLVER_TOL
    from cutfem.solvers.solve import solve

    with t("matrix"):
        K = assemble(form, space)
    with t("rhs"):
        B = assemble(position_load(surface), space)
    nnz = {"K": int(K.nnz)}
    with t("solve"):
        H, info = solve(K, B, space=space, tol=SOLVER_TOL)  # as `cutfem run` does
    exact_time = [0.0]

    def exact(x):  # one call per block of 16384 triangles
        t0 = time.perf_counter()
        try:
            return torus.exact_mean_curvature_vector(x)
        finally:
            exact_time[0] += time.perf_counter() - t0

    with t("errors"):
        err = l2_error(space, H, exact)
    return {"dofs": int(space.n_dofs), "nnz": nnz, "l2_error": err, "solver": info.method, "iterations": info.iterations,
            "time": dict(t), "stage_cpu": t.cpu, "total": sum(t.values()), "exact_time": exact_time[0]}


def cut_level(spacing: float, tau_f: float = 0.1) -> dict:
    """One cut-torus level, timed stage by stage (runs in the calling process).  The record has
    the sizes the bounds need: ``dofs`` (N), ``active_tets`` (T), ``surface_triangles`` (S),
    ``interior_faces`` (F), ``iterations`` and ``nnz`` ({"K"})."""
    from cutfem.geometry.cut import CUT, cut_mesh
    from cutfem.geometry.levelset import Torus
    from cutfem.problems.mean_curvature import mean_curvature_form
    from cutfem.geometry.mesh import structured_box
    from cutfem.fem.spaces import CutP1Space

    t = StageTimer()
    with t("background"):
        torus = Torus(1.0, 0.5)
        box = structured_box(*BOX, spacing=spacing)
    with t("cut"):
        cut = cut_mesh(box, torus)
    with t("topology"):
        space = CutP1Space(cut)
        faces = cut.interior_facets(CUT)
    shared = _timed_system_solve_error(t, space, cut.ds(), mean_curvature_form(cut.ds(), tau_f=tau_f, faces=cut.dF(faces)), torus)
    return {
        "kind": "cut",
        "level": spacing,
        "background_nodes": int(box.n_points),
        "background_tets": int(box.n_tets),
        "active_tets": int(cut.n_tets),
        "pieces": int(cut.n_tets),
        "surface_triangles": int(cut.n_triangles),
        "interior_faces": int(faces.n_facets),
        **shared,
    }


def meshed_level(n: int, family: str, tau_e: float = 0.1) -> dict:
    """One meshed-torus level, timed stage by stage."""
    from cutfem.geometry.levelset import Torus
    from cutfem.problems.mean_curvature import mean_curvature_form
    from cutfem.fem.spaces import SurfaceP1Space
    from cutfem.geometry.surface import torus_mesh

    t = StageTimer()
    with t("mesh"):
        mesh = torus_mesh(n, family, seed=1)
        space = SurfaceP1Space(mesh)
    shared = _timed_system_solve_error(t, space, mesh.ds(), mean_curvature_form(mesh.ds(), tau_e=tau_e), Torus())
    return {"kind": f"meshed-{family}", "level": n, "triangles": int(mesh.n_triangles), **shared}


def ngsxfem_level(spacing: float) -> dict:
    """The cut torus level of :func:`cut_level` in ngsxfem (:func:`cutfem.studies.peers.ngsxfem_mean_curvature`
    with the zeros of the level set moved to +1e-14 and the collapsed tets left out: cutfem's
    discrete problem; NGSolve's sparse Cholesky, no TaskManager).  ``time`` has the stages mesh,
    levelset, cut, assembly, solve, errors; ``total`` is their sum."""
    from cutfem.geometry.levelset import Torus
    from cutfem.studies.peers import ngsxfem_mean_curvature

    r = ngsxfem_mean_curvature(spacing, Torus(1.0, 0.5), zero_rule="+eps-cutfem-active", superlu=False)
    if "failed" in r:
        raise RuntimeError(f"ngsxfem failed at spacing {spacing}: {r['failed']}")
    keep = ("dofs", "active_tets", "interior_faces", "background_tets", "l2_error", "solver", "time", "total")
    return {"kind": "ngsxfem", "level": spacing, **{k: r[k] for k in keep}}


#: defines _peak(): the process's own peak resident memory in GiB, VmHWM of /proc/self/status (the
#: high-water mark of its address space since exec).  Not ru_maxrss: on Linux a child's ru_maxrss
#: starts from its parent's peak (the parent's address space at fork/exec counts), so a parent that
#: once held 0.6 GiB made every level report 0.6 GiB.  ru_maxrss where /proc is absent.
_PEAK_CODE = """\
def _peak():
    try:
        with open('/proc/self/status') as fh:
            for line in fh:
                if line.startswith('VmHWM:'):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
"""

_LEVEL_CODE = _PEAK_CODE + """\
import json, resource, sys
import cutfem.memory
cutfem.memory.configure()
from cutfem.studies.performance import cut_level, meshed_level, ngsxfem_level
kind, level, warm = {kind!r}, {level!r}, {warm!r}
import pyamg, threadpoolctl, cutfem.geometry.cut, cutfem.fem.norms, cutfem.fem.forms, cutfem.geometry.levelset, cutfem.geometry.mesh, cutfem.solvers.solve, cutfem.fem.spaces, cutfem.geometry.surface
if kind == 'ngsxfem':
    import ngsolve, xfem, cutfem.studies.peers
r0 = resource.getrusage(resource.RUSAGE_SELF)
level_once = lambda: cut_level(level) if kind == 'cut' else ngsxfem_level(level) if kind == 'ngsxfem' else meshed_level(level, kind.split('-', 1)[1])
rec = level_once()
r1 = resource.getrusage(resource.RUSAGE_SELF)
rec['peak_memory_gib'] = _peak()
rec['cpu_user'] = r1.ru_utime - r0.ru_utime
rec['cpu_system'] = r1.ru_stime - r0.ru_stime
rec['page_faults'] = r1.ru_minflt - r0.ru_minflt
rec['allocator'] = dict(cutfem.memory.SETTINGS)
if warm:
    import gc
    gc.collect()
    r2 = resource.getrusage(resource.RUSAGE_SELF)
    again = level_once()
    rec['warm'] = {{'time': again['time'], 'total': again['total'], 'iterations': again['iterations'], 'exact_time': again['exact_time'],
                   'page_faults': resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r2.ru_minflt}}
    rec['start_up'] = rec['total'] - again['total']
print('RESULT ' + json.dumps(rec))
"""


def _child_env() -> dict:
    """The environment of a fresh process that imports the same cutfem as this one."""
    import cutfem

    env = dict(os.environ)
    root = str(Path(cutfem.__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    return env


def compile_bytecode() -> None:
    """Write the ``.pyc`` files of the cutfem package and of its problems and studies (those that
    are missing or stale), as ``pip install`` does for an installed package; the timed processes
    then load bytecode instead of compiling the sources (see the module docstring)."""
    import compileall

    import cutfem

    for package in ("cutfem", "problems", "studies"):
        mod = cutfem if package == "cutfem" else importlib.import_module(f"cutfem.{package}")
        compileall.compile_dir(str(Path(mod.__file__).resolve().parent), quiet=1)


def _in_subprocess(kind: str, level, warm: bool = True) -> dict:
    """Run one level (``kind`` "cut", "meshed-<family>" or "ngsxfem") in a fresh interpreter that
    first applies :func:`cutfem.memory.configure` and imports everything the stages use (so that
    the CPU times are the stages' own); returns its record with the peak memory (GiB), CPU times
    and page faults.  ``warm``: the level runs a second time in the process (its stages' own
    times, ``warm`` and ``start_up`` of the record; never for ngsxfem)."""
    return _child_result(_LEVEL_CODE.format(kind=kind, level=level, warm=warm and kind != "ngsxfem"), f"level {kind} {level}")


#: a call of this module in a fresh interpreter with the allocation settings of the levels
_CALL_CODE = ("import json, cutfem.memory\ncutfem.memory.configure()\nimport cutfem.studies.performance as performance\n"
              "print('RESULT ' + json.dumps(performance.{call}))\n")


def _child_result(code: str, what: str):
    """Run ``code`` in a fresh interpreter (:func:`_child_env`) and return the JSON of the last line
    it printed that starts with ``RESULT``; a RuntimeError naming ``what``, with the end of its
    standard error, when it fails."""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_child_env())
    if proc.returncode != 0:
        raise RuntimeError(f"{what} failed:\n{proc.stderr[-3000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def fitted_exponent(x, y) -> float:
    """Least-squares slope of log y against log x."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    return float(np.polyfit(np.log(x), np.log(y), 1)[0]) if len(x) >= 2 else float("nan")


# ---------------------------------------------------------------------------------------------
# lower bounds
# ---------------------------------------------------------------------------------------------


def memory_bandwidth(mebibytes: int = 200, repeat: int = 5, threads: int | None = None) -> dict:
    """The sustained memory bandwidth of the cores the kernels run on, in bytes per second.

    Three float64 arrays of ``mebibytes`` MiB each (touched before timing), cut into ``threads``
    slices (default: numba's thread count, the threads of :mod:`cutfem.jit`), each slice on its
    own thread at the same time (numpy releases the interpreter's lock on such arrays); best of
    ``repeat`` of a copy ``a[:] = b`` (2 array sizes moved) and of a triad ``a = b + s c`` done as
    two numpy passes, ``a = s c`` then ``a += b`` (5 array sizes moved; write-allocate traffic not
    counted).  Returns {"copy", "triad", "bandwidth" (the larger rate: the bound uses the fastest
    streaming seen), "mebibytes", "repeat", "threads", "method"}."""
    from concurrent.futures import ThreadPoolExecutor

    if threads is None:
        import numba

        threads = numba.get_num_threads()
    n = int(mebibytes) * 2**20 // 8
    a, b, c = np.zeros(n), np.full(n, 1.0), np.full(n, 2.0)
    cuts = np.linspace(0, n, threads + 1).astype(int)
    parts = [(a[i:j], b[i:j], c[i:j]) for i, j in zip(cuts[:-1], cuts[1:])]

    def copy(p):
        np.copyto(p[0], p[1])

    def triad(p):
        np.multiply(p[2], 3.0, out=p[0])
        np.add(p[0], p[1], out=p[0])

    best = {"copy": np.inf, "triad": np.inf}
    with ThreadPoolExecutor(threads) as pool:
        for _ in range(repeat):
            for name, f in (("copy", copy), ("triad", triad)):
                t0 = time.perf_counter()
                list(pool.map(f, parts))
                best[name] = min(best[name], time.perf_counter() - t0)
    copy_rate, triad_rate = 2 * 8 * n / best["copy"], 5 * 8 * n / best["triad"]
    return {"copy": copy_rate, "triad": triad_rate, "bandwidth": max(copy_rate, triad_rate), "mebibytes": int(mebibytes),
            "repeat": repeat, "threads": int(threads),
            "method": f"numpy copy a[:] = b (2 x {mebibytes} MiB moved) and triad a = s c; a += b (5 x {mebibytes} MiB), "
                      f"{threads} thread(s) on slices at once, best of {repeat} each; the larger rate"}


def stage_bytes(rec: dict) -> dict:
    """The bytes each stage of a cut level must at least move, {stage: (bytes, how)}, from the
    sizes in ``rec``: ``dofs`` N, ``active_tets`` T, ``surface_triangles`` S, ``interior_faces`` F,
    ``iterations`` it and ``nnz`` {"K"}; the model is the table of the module docstring
    (c = :data:`COLUMNS` right-hand sides, 12 bytes a CSR nonzero, Q = :data:`ERROR_POINTS`)."""
    N, T, S, F = rec["dofs"], rec["active_tets"], rec["surface_triangles"], rec["interior_faces"]
    it, nnz = rec["iterations"], rec["nnz"]
    nK = nnz["K"]
    c, q = COLUMNS, ERROR_POINTS
    return {
        "background": (0.0, "0 bytes: the box is lazy (nodes and tets computed on demand), O(1) work; no bandwidth bound"),
        "cut": (16 * N + 72 * T + 24 * S, "16 N + 72 T + 24 S: level-set value and id of each band node written; 4 values "
                "read, 4 vertex ids and the id of each active tet written; 3 vertex ids of each triangle of S_h written"),
        "topology": (96 * T + 32 * F, "96 T + 32 F: the tets read, 4 face keys a tet written and read; the 2 tets and 2 "
                     "opposite vertices of each interior face written"),
        "matrix": (52 * S + 48 * F + 328 * N + CSR_BYTES * nK, "52 S + 48 F + 328 N + 12 nnz(K): each triangle of "
                   "S_h (ids, tet, area, its share of the vertices) and each interior face (tets, normal, weight) read; "
                   "13 lattice slots of 12 bytes and the diagonal a node zeroed, summed into and read; the CSR of K written"),
        "rhs": (56 * T + 24 * N, "56 T + 24 N: 4 dof numbers, type, normal and piece area of each tet read; the N x 3 "
                "result written"),
        "solve": (it * (SOLVE_MATRIX_BYTES * nK + SOLVE_VECTOR_BYTES * c * N), f"it x (24 nnz(K) + 80 x {c} N): per CG "
                  "iteration one pass over the fine matrix for all columns in double precision (12 bytes a nonzero) "
                  "and 1.5 in single precision (8 bytes: the forward sweep from zero with its residual, half of each row, "
                  "and the backward sweep), "
                  "and per column the CG vectors (x, r, p read and written, q, z read) and the cycle's right-hand "
                  "side and correction; coarse levels and setup left out; it = the most iterations over the columns")
        if it > 0 else (CSR_BYTES * nK + 8 * c * N, f"12 nnz(K) + {8 * c} N (direct solve): K read once, the N x {c} "
                        "solution written; the factor not counted"),
        "errors": (80 * q * S, f"80 x {q} S: coordinates, weight, discrete and exact field (80 bytes) of each point of "
                   "the degree-4 triangle rule written"),
    }


def stage_bounds(rec: dict, bandwidth: float) -> dict:
    """{stage: {"bytes", "bound" (s), "measured" (s), "ratio" (measured / bound, None where the
    bound is 0), "measured_fresh", "ratio_fresh", "bound_method"}} for the stages of a cut level,
    with the bytes of :func:`stage_bytes` and ``bandwidth`` in bytes per second.  ``measured`` is
    the stage's own time, from the level's second run in its process (``rec["warm"]``) when there
    is one; ``measured_fresh`` the first run's, which also pays the process's start-up (see the
    module docstring).  An estimate: see the module docstring."""
    if not bandwidth > 0:
        raise ValueError(f"the bandwidth must be a positive number of bytes per second, got {bandwidth!r}: "
                         "pass memory_bandwidth()['bandwidth']")
    out = {}
    warm = rec.get("warm", {}).get("time")
    for stage, (nbytes, how) in stage_bytes(rec).items():
        bound = nbytes / bandwidth
        fresh = rec["time"][stage]
        measured = fresh if warm is None else warm[stage]
        out[stage] = {"bytes": float(nbytes), "bound": bound, "measured": measured,
                      "ratio": measured / bound if bound > 0 else None,
                      "measured_fresh": fresh, "ratio_fresh": fresh / bound if bound > 0 else None,
                      "bound_method": f"memory traffic / {bandwidth / 1e9:.2f} GB/s; {how}"}
    return out


#: repeats of each operation in :func:`compiled_references` (medians)
REFERENCE_REPEAT = 7


def _median_time(f, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def compiled_references(spacing: float = 0.0125, repeat: int = REFERENCE_REPEAT) -> list[dict]:
    """The kernels that carry the solve, the numbering of the cut, and the cut and matrix stages
    whole, beside an existing compiled library doing the same operation on the same data: the cut
    torus at ``spacing`` and its matrix K = M + tau_F J_F (as :func:`cut_level` assembles it),
    three columns.

    * ``K X`` (double precision): :func:`cutfem.solvers.sparse_kernels.matmul` against scipy's CSR product
      (C++, one thread);
    * one forward Gauss-Seidel sweep from zero, rows in their order: :func:`cutfem.solvers.sparse_kernels.gauss_seidel`
      with one chunk (so on one thread) against pyamg's ``gauss_seidel`` (C++), column by column;
    * the Galerkin product P^T K P of the first coarse level: :func:`cutfem.solvers.multigrid_kernels.galerkin`
      against scipy's ``R @ K @ P`` (two sparse products, C++, one thread; its result is not made
      exactly symmetric);
    * the numbering of the active nodes (the background ids of the cut tets' nodes, their sorted
      distinct values and the inverse): :func:`cutfem.geometry.mesh.dense_unique` against
      ``numpy.unique(..., return_inverse=True)`` (C, a sort);
    * the whole cut stage (:func:`cutfem.geometry.cut.cut_mesh` from the lazy box: the band search, the
      level set at the band's nodes, the numbering, marching tets and S_h with its normals and
      areas) against VTK's contour filter (C++, pyvista's ``contour``, one thread in the VTK of
      the wheels) on the active tets and their level-set values, given in memory: only the
      marching tets of that stage; ``difference`` is that of the two surfaces' areas, relative;
    * the whole matrix stage (:func:`cutfem.fem.forms.assemble` of the form, element matrices and
      sums) against scipy's conversion of the element matrices, given, from COO to CSR (C++, one
      thread), which only sums them: the exact piece mass matrices (4 x 4 a cut tet, from
      :func:`cutfem.fem.element_kernels.piece_moments`) and the Gram matrices c_F c_F^T of the face jumps
      (8 x 8 a face, from :func:`cutfem.fem.element_kernels.jump_rows`; a node shared by the two tets summed by
      the conversion): 104 million entries at spacing 0.0125.
    * the whole topology stage (the field on the cut tets, :class:`cutfem.fem.spaces.CutP1Space`, and
      the interior faces of the active mesh, :func:`cutfem.geometry.markers.interior_facets`) against VTK's
      geometry filter (vtkGeometryFilter, C++, pyvista's ``extract_surface``, one thread) on the
      active tets: it matches every face of the tets with its twin and keeps those met once (the
      boundary), the same matching; ``difference`` is |its boundary faces - (4 T - 2 F)|, T tets
      and F interior faces;
    * the whole right-hand-side stage (:func:`cutfem.fem.forms.assemble` of
      :func:`cutfem.fem.forms.position_load`: b_i = sum_K |S_K| P_h grad phi_i, element vectors and
      sums in one compiled pass) against ``numpy.bincount`` (C) summing the element vectors |S_K|
      P_h grad phi_i, given (made in numpy before the timing), one column at a time: the sums alone.

    Each row: the medians of ``repeat`` runs of cutfem on all of numba's threads and on one, of
    the reference, and ``per_thread`` = reference / cutfem on one thread (above 1: cutfem's kernel
    is the faster one on a core), with ``difference``, the largest difference of the two results
    (0 where they are the same bits; the reference's sums may be ordered differently).  The data
    a reference is given (the active tets, the element matrices) is made before the timing.  A
    yardstick of the compiled code a library offers for the same step, not a bound: the
    memory-traffic bounds of :func:`stage_bounds` are the lower ones."""
    import numba
    import scipy.sparse as sp
    from pyamg.relaxation.relaxation import gauss_seidel as pyamg_gauss_seidel

    from cutfem.geometry.cut import CUT, cut_mesh
    from cutfem.fem.forms import assemble
    from cutfem.fem.terms import position_load
    from cutfem.geometry.levelset import Torus
    from cutfem.geometry.markers import interior_facets
    from cutfem.geometry.mesh import dense_unique, structured_box
    from cutfem.problems.mean_curvature import mean_curvature_form
    from cutfem.solvers.solve import lattice_hierarchy, lattice_indices
    from cutfem.fem.spaces import CutP1Space

    import pyvista as pv

    box = structured_box(*BOX, spacing=spacing)
    torus = Torus(1.0, 0.5)
    cut = cut_mesh(box, torus)
    space = CutP1Space(cut)
    faces = cut.interior_facets(CUT)
    form = mean_curvature_form(cut.ds(), tau_f=0.1, faces=cut.dF(faces))
    K = sp.csr_matrix(assemble(form, space))
    n = K.shape[0]
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: np.asarray(cut.tets)}, np.asarray(cut.points))
    grid.point_data["phi"] = np.asarray(cut.values)
    entries = _element_triplets(cut, space, faces, 0.1)  # (values, (rows, columns))
    rng = np.random.default_rng(0)
    X, B = rng.standard_normal((n, COLUMNS)), rng.standard_normal((n, COLUMNS))
    P = sp.csr_matrix(next(iter(lattice_hierarchy(lattice_indices(space)))))
    R = sp.csr_matrix(P.T)
    ids = cut.node_ids[cut.tets]
    es = cut.elements(CUT)
    areas = np.asarray(cut.ds().piece_areas, dtype=float)
    vectors = (space.tangential_gradients * areas[:, None, None]).reshape(-1, 3)  # |S_K| P_h grad phi_i
    columns = [np.ascontiguousarray(vectors[:, k]) for k in range(3)]
    element_dofs = np.asarray(space.element_dofs).ravel()
    del vectors

    def sweep():
        return sparse_kernels.gauss_seidel(K, np.zeros((n, COLUMNS)), B)

    def pyamg_sweep():
        out = np.zeros((n, COLUMNS))
        for k in range(COLUMNS):
            x = np.zeros(n)
            pyamg_gauss_seidel(K, x, np.ascontiguousarray(B[:, k]), iterations=1, sweep="forward")
            out[:, k] = x
        return out

    def topology():
        return CutP1Space(cut), interior_facets(es.tets, es.n_nodes, es.kuhn_types)

    def vtk_boundary():
        return grid.extract_surface(pass_pointid=False, pass_cellid=False, algorithm="geometry")

    def bincount_rhs():
        return np.stack([np.bincount(element_dofs, weights=c, minlength=n) for c in columns], axis=1)

    def difference(a, b):
        if isinstance(a, tuple) and isinstance(b, pv.PolyData):  # faces met once against 4 T - 2 F
            return float(abs(b.n_cells - (4 * cut.n_tets - 2 * len(a[1][0]))))
        if isinstance(b, pv.PolyData):  # the cut against VTK's contour: the areas, relative
            area = float(np.sum(a.triangle_areas))
            return abs(area - float(b.area)) / area
        if isinstance(a, tuple):  # (distinct values, inverse)
            return float(max(np.max(np.abs(a[0] - b[0])), np.max(np.abs(a[1] - b[1].reshape(a[1].shape)))))
        if sp.issparse(a):
            return float(abs(sp.csr_matrix(a) - sp.csr_matrix(b)).max())
        return float(np.max(np.abs(a - b)))

    cases = [
        ("K X, 3 columns, double", lambda: sparse_kernels.matmul(K, X), "scipy.sparse CSR product (C++)", lambda: K @ X),
        ("Gauss-Seidel sweep from zero, 3 columns", sweep, "pyamg gauss_seidel (C++), a column at a time", pyamg_sweep),
        ("Galerkin P^T K P, first level", lambda: multigrid_kernels.galerkin(K, P, R), "scipy R @ K @ P (C++)", lambda: R @ K @ P),
        ("active-node numbering", lambda: dense_unique(ids, box.n_points), "numpy.unique with inverse (C)",
         lambda: np.unique(ids, return_inverse=True)),
        ("the cut stage (band, S_h), whole", lambda: cut_mesh(box, torus), "VTK contour of the active tets (C++)",
         lambda: grid.contour([0.0], scalars="phi", method="contour")),
        ("the matrix stage, whole", lambda: assemble(form, space), "scipy COO to CSR of the element matrices (C++)",
         lambda: sp.coo_matrix(entries, shape=(n, n)).tocsr()),
        ("the topology stage (interior faces), whole", topology, "VTK geometry filter of the active tets (C++)", vtk_boundary),
        ("the right-hand sides, whole", lambda: assemble(position_load(cut.ds()), space), "numpy.bincount of the element vectors (C)",
         bincount_rhs),
    ]
    threads = numba.get_num_threads()
    rows = []
    for name, ours, reference, theirs in cases:
        diff = difference(ours(), theirs())  # also the first calls: compiled kernels loaded before timing
        t_all = _median_time(ours, repeat)
        numba.set_num_threads(1)
        try:
            t_one = _median_time(ours, repeat)
        finally:
            numba.set_num_threads(threads)
        t_ref = _median_time(theirs, repeat)
        rows.append({"operation": name, "spacing": spacing, "unknowns": int(n), "cutfem": t_all, "cutfem_one_thread": t_one,
                     "threads": int(threads), "reference": reference, "reference_time": t_ref, "per_thread": t_ref / t_one,
                     "difference": diff, "repeat": int(repeat)})
    return rows


def _element_triplets(cut, space, faces, tau_f: float):
    """(values, (rows, columns)) of the element matrices of K = M + tau_F J_F on the cut space ``space``,
    for :func:`compiled_references`: the exact piece mass matrix of each cut tet (its diagonal and
    both triangles of its 4 x 4, :func:`cutfem.fem.element_kernels.piece_moments`) and tau_F c_F c_F^T of each
    interior face in ``faces`` (8 x 8, c_F the jump row of :func:`cutfem.fem.element_kernels.jump_rows` on the
    dofs of both tets, a shared node twice); their sum is K."""
    from cutfem.geometry.cut import CUT
    from cutfem.geometry.numbering import TET_EDGES, index_dtype

    dofs = np.asarray(space.element_dofs)
    table, types = space.gradient_lookup()
    es = cut.elements(CUT)
    edges, diagonal, _ = element_kernels.piece_moments(cut.vertices, cut.triangles, cut.triangle_tets, cut.triangle_areas,
                                               es.points, es.tets, table, types)
    a, b = TET_EDGES[:, 0], TET_EDGES[:, 1]
    mass_rows = np.concatenate([dofs, dofs[:, a], dofs[:, b]], axis=1)
    mass_cols = np.concatenate([dofs, dofs[:, b], dofs[:, a]], axis=1)
    mass_vals = np.concatenate([diagonal, edges, edges], axis=1)
    normals, weights = faces.normals_areas()
    pairs = np.ascontiguousarray(faces.pairs)
    index = index_dtype(space.n_dofs)
    face_dofs, face_vals = np.empty((len(pairs), 8), dtype=index), np.empty((len(pairs), 8))
    element_kernels.jump_rows(pairs, normals, normals, -1.0, np.ascontiguousarray(tau_f * weights, dtype=float), dofs, table, types,
                      face_dofs, face_vals)
    shape = (len(pairs), 8, 8)
    rows = np.concatenate([mass_rows.ravel(), np.broadcast_to(face_dofs[:, :, None], shape).ravel()]).astype(index)
    cols = np.concatenate([mass_cols.ravel(), np.broadcast_to(face_dofs[:, None, :], shape).ravel()]).astype(index)
    vals = np.concatenate([mass_vals.ravel(), (face_vals[:, :, None] * face_vals[:, None, :]).ravel()])
    return vals, (rows, cols)


#: the compiled references (:func:`compiled_references`) that stand for a stage of a cut level: the
#: stage whole, or the kernels that carry it
STAGE_REFERENCES = {
    "cut": ("the cut stage (band, S_h), whole",),
    "topology": ("the topology stage (interior faces), whole",),
    "matrix": ("the matrix stage, whole",),
    "rhs": ("the right-hand sides, whole",),
    "solve": ("K X, 3 columns, double", "Gauss-Seidel sweep from zero, 3 columns", "Galerkin P^T K P, first level"),
}


def stage_targets(cut_records: list, references: list) -> dict:
    """The target "every stage within 2 times of its compiled or memory-traffic bound", stage by
    stage: {stage: {"level", "traffic_ratio" (own time / bound at the finest cut level with
    bounds), "references" (the rows of :data:`STAGE_REFERENCES`), "compiled_ratio" (cutfem on one
    thread / the reference, the largest over those rows; None where the stage has none),
    "within_2x" (either ratio at most 2)}}.  A stage whose reference is its kernels (the solve) is
    compared by its kernels, not by the calls between them.  The errors stage also has
    "exact_share": the part of its own time spent evaluating the exact field (the caller's
    function, not the library's code), where the level recorded it."""
    with_bounds = [r for r in cut_records if "bounds" in r]
    if not with_bounds:
        return {}
    finest = min(with_bounds, key=lambda r: r["level"])
    by_name = {r["operation"]: r for r in references}
    out = {}
    for stage in CUT_STAGES[1:]:
        traffic = finest["bounds"][stage]["ratio"]
        rows = [by_name[n] for n in STAGE_REFERENCES.get(stage, ()) if n in by_name]
        compiled = max((1.0 / r["per_thread"] for r in rows), default=None)  # per_thread = reference / cutfem on a core
        out[stage] = {"level": finest["level"], "traffic_ratio": traffic, "references": [r["operation"] for r in rows],
                      "compiled_ratio": compiled,
                      "within_2x": bool((traffic is not None and traffic <= 2) or (compiled is not None and compiled <= 2))}
    own = finest.get("warm", finest)
    if own.get("exact_time") is not None and own["time"].get("errors"):
        out["errors"]["exact_share"] = own["exact_time"] / own["time"]["errors"]
    return out


def _references_in_subprocess(spacing: float) -> list:
    """:func:`compiled_references` in a fresh process with the allocation settings of the levels."""
    return _child_result(_CALL_CODE.format(call=f"compiled_references({float(spacing)!r})"), f"compiled references at spacing {spacing}")


# ---------------------------------------------------------------------------------------------
# exponents
# ---------------------------------------------------------------------------------------------


def scaling_exponents(records: list[dict], x: str = "active_tets", finest: int = 3, stages=(), time_key: str = "total") -> dict:
    """Slopes of log(``time_key``), log(cpu_user), log(peak_memory_gib) and log(time[stage]) for each of
    ``stages`` against log(``x``) over the ``finest`` records with the largest ``x`` (keys absent
    from the records are skipped).  Empty dict with fewer than ``finest`` records: an exponent
    fitted to two coarse levels says more about start-up costs than about scaling."""
    rs = sorted(records, key=lambda r: r[x])[-finest:]
    if len(rs) < finest:
        return {}
    xs = [r[x] for r in rs]
    out = {"levels": [r["level"] for r in rs], "x": x}
    for key, name in ((time_key, "time"), ("cpu_user", "user_time"), ("peak_memory_gib", "memory")):
        if all(key in r for r in rs):
            out[name] = fitted_exponent(xs, [r[key] for r in rs])
    times = {s: [r["time"].get(s, 0.0) for r in rs] for s in stages}
    out["stages"] = {s: fitted_exponent(xs, v) for s, v in times.items() if min(v) > 0}
    return out


# ---------------------------------------------------------------------------------------------
# the largest level that fits
# ---------------------------------------------------------------------------------------------


def predict_next(levels: list[dict], spacing: float) -> dict:
    """The active tets and peak memory of the cut level at ``spacing`` from the ``levels`` already
    run (records with ``level``, ``active_tets``, ``peak_memory_gib``): with q the slope of
    log(active tets) against log(spacing) and p that of log(peak) against log(active tets), both
    over the last three levels, T = T_last (spacing / s_last)^q and peak = peak_last (T / T_last)^P
    with P = max(p, 1): every array of a level grows at least like its active tets, and a fitted
    p below 1 comes from the fixed memory of the interpreter and its imports (0.12 GiB), which
    weighs less and less (measured: p = 0.32 over spacings 0.1-0.025 predicted 0.48 GiB at 0.0125,
    which took 1.02 GiB; P = 1 predicts 1.27 GiB).  With a single level, q = -2 (a surface band)
    and p = 1 are assumed."""
    last = levels[-3:]
    if len(last) >= 2:
        q = fitted_exponent([r["level"] for r in last], [r["active_tets"] for r in last])
        p = fitted_exponent([r["active_tets"] for r in last], [r["peak_memory_gib"] for r in last])
        how = f"fitted over spacings {[r['level'] for r in last]}"
    else:
        q, p, how = -2.0, 1.0, "assumed (one level): tets ~ spacing^-2, peak ~ tets"
    r = levels[-1]
    tets = r["active_tets"] * (spacing / r["level"]) ** q
    used = max(p, 1.0)
    return {"spacing": spacing, "active_tets": tets, "peak_memory_gib": r["peak_memory_gib"] * (tets / r["active_tets"]) ** used,
            "tets_exponent": q, "memory_exponent": p, "memory_exponent_used": used, "exponents": how}


def limit_search(runner, memory_gib: float, start: float = LIMIT_START, available_gib=None, progress=None,
                 max_levels: int = 16) -> dict:
    """Run cut levels at ``start``, start/2, ... with ``runner(spacing) -> record`` (a record with
    ``active_tets`` and ``peak_memory_gib``, or ``failed``) until the next level's predicted peak
    (:func:`predict_next`) exceeds ``memory_gib`` or 90 % of ``available_gib()`` (GiB available
    now; None: no such check), a level fails, or a level's measured peak exceeds the limit.

    Returns {"memory_gib", "levels" (the records run), "largest" (the finest level that ran
    within the limit, None if none did), "next" (the prediction for the level after it),
    "stopped" (why)}."""
    if not memory_gib > 0:
        raise ValueError(f"--memory-gib must be a positive number of GiB, got {memory_gib!r}")
    say = progress or (lambda msg: None)
    levels, spacing, stopped = [], float(start), None
    for _ in range(max_levels):
        if levels:
            pred = predict_next(levels, spacing)
            avail = available_gib() if available_gib else None
            cap = memory_gib if avail is None else min(memory_gib, 0.9 * avail)
            if pred["peak_memory_gib"] > cap:
                which = "the limit" if cap == memory_gib else f"90 % of the available {avail:.1f} GiB"
                stopped = f"spacing {spacing:g} predicted to need {pred['peak_memory_gib']:.2f} GiB > {cap:.2f} GiB ({which})"
                break
            say(f"limit: spacing {spacing:g}, predicted {pred['peak_memory_gib']:.2f} GiB")
        rec = runner(spacing)
        levels.append(rec)
        if "failed" in rec:
            stopped = f"spacing {spacing:g} failed"
            break
        if rec["peak_memory_gib"] > memory_gib:
            stopped = f"spacing {spacing:g} used {rec['peak_memory_gib']:.2f} GiB > {memory_gib:g} GiB"
            break
        spacing /= 2
    else:
        stopped = f"{max_levels} levels run"
    ran = [r for r in levels if "failed" not in r and r["peak_memory_gib"] <= memory_gib]
    largest = ran[-1] if ran else None
    nxt = predict_next(ran, largest["level"] / 2) if largest else None
    return {"memory_gib": memory_gib, "levels": levels, "stopped": stopped, "next": nxt,
            "largest": None if largest is None else {k: largest[k] for k in ("level", "active_tets", "dofs", "peak_memory_gib", "total") if k in largest}}


def _available_gib():
    from cutfem.studies.peers import available_memory

    avail = available_memory()
    return None if avail is None else avail / 2**30


# ---------------------------------------------------------------------------------------------
# bulk Poisson and ngsxfem
# ---------------------------------------------------------------------------------------------


_COMMAND_CODE = _PEAK_CODE + """\
import atexit
from cutfem.runs.cli import entry
atexit.register(lambda: print(f'PEAK {_peak()!r}', flush=True))
entry()
"""


def command_run(args) -> dict:
    """``cutfem ARGS --json F --quiet`` in a fresh process (the command's own entry,
    :func:`cutfem.runs.cli.entry`, and at exit a print of the process's peak resident memory, VmHWM):
    {"record": the first level's JSON record, "process_wall": the wall time of the whole process
    (interpreter start, imports and numba's start included), "peak_memory_gib", "cpu_user",
    "cpu_system" (``os.wait4``)}."""
    with tempfile.TemporaryDirectory() as tmp:
        path, out, err = Path(tmp) / "level.json", Path(tmp) / "stdout.txt", Path(tmp) / "stderr.txt"
        argv = [*args, "--json", str(path), "--quiet"]
        t0 = time.perf_counter()
        with out.open("w") as fo, err.open("w") as fe:
            proc = subprocess.Popen([sys.executable, "-c", _COMMAND_CODE, *argv], stdout=fo, stderr=fe, env=_child_env())
            _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait again
        process_wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"cutfem {' '.join(args)} failed:\n{err.read_text()[-3000:]}")
        record = json.loads(path.read_text())["records"][0]
        peak = float([ln for ln in out.read_text().splitlines() if ln.startswith("PEAK ")][-1].split()[1])
    return {"record": record, "process_wall": process_wall, "peak_memory_gib": peak, "cpu_user": usage.ru_utime,
            "cpu_system": usage.ru_stime}


def bulk_level(spacing: float) -> dict:
    """``cutfem run poisson-cut --surface torus --spacing S`` through :func:`command_run`: the
    level's unknowns, stage times and wall time from its JSON record, the peak, the CPU times, the
    process wall time (start-up included), and the time (s) and memory (GiB) per million unknowns."""
    c = command_run(["run", "poisson-cut", "--surface", "torus", "--spacing", repr(spacing)])
    r, peak = c["record"], c["peak_memory_gib"]
    mega = r["dofs"] / 1e6
    return {"kind": "bulk-poisson", "level": spacing, "dofs": r["dofs"], "active_tets": r["active_tets"],
            "solver": r["solver"], "iterations": r.get("solver_iterations"), "l2_error": r["l2_error"],
            "time": r["time"], "wall": r["wall_time"], "process_wall": c["process_wall"], "peak_memory_gib": peak,
            "cpu_user": c["cpu_user"], "cpu_system": c["cpu_system"],
            "seconds_per_million": r["wall_time"] / mega, "gib_per_million": peak / mega}


def command_targets(size: str) -> list:
    """The end-to-end targets, as (cutfem arguments, seconds or None): the cut torus at spacing
    0.0125 in 2 s and the meshed torus 768 x 384 of every family in 1 s (with ``full`` also the cut
    torus at spacing 0.003125 in 40 s); at the tiny size the coarse levels, without a target."""
    from cutfem.geometry.surface import TORUS_FAMILIES

    cut, n = pick(size, ("0.1", "32"), ("0.0125", "768"), ("0.0125", "768"))
    targets = [(["run", "mean-curvature-cut", "--spacing", cut], None if size == "tiny" else 2.0)]
    targets += [(["run", "mean-curvature-meshed", "--levels", n, "--family", f], None if size == "tiny" else 1.0)
                for f in TORUS_FAMILIES]
    if size == "full":
        targets.append((["run", "mean-curvature-cut", "--spacing", "0.003125"], 40.0))
    return targets


def command_times(size: str, repeat: int, progress) -> list:
    """Each command of :func:`command_targets` ``repeat`` times in fresh processes, the runs of all
    commands interleaved (so that a busy spell of the machine spreads over them): per command the
    process wall times (``walls``), their median and range, the peak, the target and whether the
    median meets it."""
    targets = command_targets(size)
    runs = [[] for _ in targets]
    for k in range(repeat):
        for (args, _), rs in zip(targets, runs):
            progress(f"cutfem {' '.join(args)} (run {k + 1} of {repeat})")
            rs.append(command_run(args))
    rows = []
    for (args, target), rs in zip(targets, runs):
        walls = [r["process_wall"] for r in rs]
        median = float(np.median(walls))
        rows.append({"command": "cutfem " + " ".join(args), "walls": walls, "median": median, "min": min(walls),
                     "max": max(walls), "peak_memory_gib": max(r["peak_memory_gib"] for r in rs),
                     "dofs": rs[0]["record"]["dofs"], "target": target,
                     "met": None if target is None else bool(median <= target)})
        progress(f"  {rows[-1]['command']}: median {median:.2f} s ({min(walls):.2f}-{max(walls):.2f})")
    return rows


def _peer_missing():
    import contextlib
    import io

    from cutfem.studies.peers import INSTALL, peer_missing

    with contextlib.redirect_stdout(io.StringIO()):  # xfem prints its version when imported
        why = peer_missing()
    return None if why is None else f"ngsolve/xfem are not importable ({why}); {INSTALL}"


def _peers(cut_records, memory_gib, down_to, progress) -> dict:
    """ngsxfem at the cut levels that ran (see the module docstring), with the ratio of totals."""
    from cutfem.geometry.mesh import structured_box
    from cutfem.studies.peers import BYTES_PER_TET

    missing = _peer_missing()
    if missing:
        progress(f"peers skipped: {missing}")
        print(f"note: ngsxfem comparison skipped: {missing}")
        return {"skipped": missing}
    rows = []
    for cf in cut_records:
        s = cf["level"]
        tets = structured_box(*BOX, spacing=s).n_tets
        avail = _available_gib()
        need = BYTES_PER_TET * tets / 2**30
        cap = memory_gib if avail is None else min(memory_gib, 0.9 * avail)
        row = {"level": s, "cutfem_total": cf["total"], "cutfem_solver": cf["solver"]}
        if s < down_to:
            row["skipped"] = f"finer than --peers-down-to {down_to:g} (the NGSolve mesh needs about {need:.1f} GiB)"
        elif need > cap:
            row["skipped"] = f"the NGSolve mesh of {tets} tets needs about {need:.1f} GiB > {cap:.1f} GiB"
        else:
            progress(f"ngsxfem, spacing {s}")
            try:
                ng = _in_subprocess("ngsxfem", s)
            except RuntimeError as exc:
                row["failed"] = str(exc)[-500:]
            else:
                row.update(ngsxfem=ng, ratio=ng["total"] / cf["total"],
                           same_problem=all(ng[k] == cf[k] for k in ("dofs", "active_tets", "interior_faces")))
                progress(f"  ngsxfem {ng['total']:.2f} s against cutfem {cf['total']:.2f} s: ratio {row['ratio']:.1f}")
        if "skipped" in row or "failed" in row:
            progress(f"  ngsxfem at {s}: {row.get('skipped') or row['failed'].splitlines()[-1]}")
        rows.append(row)
    return {"levels": rows, "note": "ngsxfem: NGSolve sparse Cholesky, one thread, one run a level; cutfem: its automatic "
                                   "solver, the fastest of its runs; ratio = ngsxfem / cutfem of the stage sums"}


# ---------------------------------------------------------------------------------------------
# the study
# ---------------------------------------------------------------------------------------------


def _bandwidth_in_subprocess(mebibytes: int) -> dict:
    """:func:`memory_bandwidth` in a fresh process with the allocation settings of the levels (and
    without leaving its arrays on this process's heap)."""
    return _child_result(_CALL_CODE.format(call=f"memory_bandwidth({int(mebibytes)})"), "the bandwidth measurement")


def _best_of(kind: str, level, repeat: int, warm: bool = True) -> dict:
    """Run a level ``repeat`` times (fresh processes) and keep the fastest run; all the end-to-end
    times are kept in ``totals`` and their system CPU times in ``cpu_system_all``."""
    runs = [_in_subprocess(kind, level, warm) for _ in range(repeat)]
    best = min(runs, key=lambda r: r["total"])
    best["totals"] = [r["total"] for r in runs]
    best["cpu_system_all"] = [r["cpu_system"] for r in runs]
    return best


def _spread(r) -> str:
    t = r["totals"]
    return f"{r['total']:.2f} s" if len(t) == 1 else f"{r['total']:.2f} s (best of {len(t)}; {min(t):.2f}-{max(t):.2f})"


def _cut_runner(repeat, progress, warm: bool = True):
    def run_cut(s):
        progress(f"cut torus, spacing {s}" + (f" ({repeat} runs)" if repeat > 1 else ""))
        try:
            r = _best_of("cut", s, repeat, warm)
        except RuntimeError as exc:  # e.g. out of memory: recorded, not hidden
            progress(f"  failed: {str(exc).splitlines()[-1]}")
            return {"kind": "cut", "level": s, "failed": str(exc)[-500:]}
        progress(f"  {r['active_tets']} active tets, {r['dofs']} dofs: {_spread(r)}, {r['peak_memory_gib']:.2f} GiB, "
                 f"{r['solver']} ({r['iterations']} its), L2 error {r['l2_error']:.4e}")
        return r

    return run_cut


def run(out: Path, size: str = "quick", progress=None, peers: bool = False, limit: bool = False, bulk: bool = False,
        memory_gib: float = 20.0, peers_down_to: float = PEERS_DOWN_TO) -> dict:
    """The benchmark (see the module docstring).  Each level runs ``repeat`` times (1 for tiny and
    in ``limit`` mode, 3 otherwise) and the fastest run is kept: the spread on this kind of machine
    is the kernel's page-fault time, not the algorithm (the user CPU time varies far less), and the
    minimum is the least noisy estimate of the cost.  The exponents are fitted to the kept runs;
    every run's total is in the JSON (``totals``)."""
    progress = progress or Progress("performance")
    repeat = 1 if limit else pick(size, 1, 3, 3)
    compile_bytecode()
    progress("memory bandwidth")
    bw = _bandwidth_in_subprocess(pick(size, 32, 200, 200))
    progress(f"  {bw['bandwidth'] / 1e9:.2f} GB/s (copy {bw['copy'] / 1e9:.2f}, triad {bw['triad'] / 1e9:.2f})")
    run_cut = _cut_runner(repeat, progress, warm=not limit)  # --limit: no second run beside a level near the memory limit
    summary = {"repeat": repeat, "bandwidth": bw}
    if limit:
        summary["limit"] = lim = limit_search(run_cut, memory_gib, available_gib=_available_gib, progress=progress)
        records = list(lim["levels"])
        progress(f"limit: {lim['stopped']}")
    else:
        spacings = pick(size, [0.2, 0.1], [0.1, 0.05, 0.025, 0.0125], [0.1, 0.05, 0.025, 0.0125, 0.00625, 0.003125])
        records = [run_cut(s) for s in spacings]
        ns = pick(size, [32, 64], [64, 128, 256, 512, 768], [64, 128, 256, 512, 768])
        for family in ("flipped", "perturbed"):
            for n in ns:
                progress(f"meshed torus {family}, n = {n}")
                records.append(_best_of(f"meshed-{family}", n, repeat))
                r = records[-1]
                progress(f"  {r['dofs']} dofs: {_spread(r)}, {r['peak_memory_gib']:.2f} GiB, {r['solver']}")
    ok = [r for r in records if "failed" not in r]
    cut = [r for r in ok if r["kind"] == "cut"]
    for r in cut:
        r["bounds"] = stage_bounds(r, bw["bandwidth"])
    summary["levels"] = records
    summary["exponents"] = {"cut": scaling_exponents(cut, "active_tets", stages=CUT_STAGES[1:])}  # background: microseconds
    from_target = [r for r in cut if r["level"] <= EXPONENT_FROM]  # the issue's range: 0.025 down to the finest
    if len(from_target) > 3:
        summary["exponents"][f"cut from {EXPONENT_FROM:g}"] = scaling_exponents(from_target, "active_tets", finest=len(from_target))
    if not limit:
        spacing = pick(size, 0.1, 0.0125, 0.0125)
        progress(f"compiled references, cut torus at spacing {spacing}")
        summary["compiled_references"] = _references_in_subprocess(spacing)
        summary["stage_targets"] = stage_targets(cut, summary["compiled_references"])
        summary["commands"] = command_times(size, repeat, progress)
    if peers:
        summary["peers"] = _peers(cut, memory_gib, peers_down_to, progress)
    if bulk:
        rows = []
        for s in pick(size, [0.2], [0.1, 0.05, 0.025], BULK_FULL):
            progress(f"bulk poisson-cut on the solid torus, spacing {s}")
            try:
                rows.append(bulk_level(s))
            except RuntimeError as exc:
                progress(f"  failed: {str(exc).splitlines()[-1]}")
                rows.append({"kind": "bulk-poisson", "level": s, "failed": str(exc)[-500:]})
                continue
            progress(f"  {rows[-1]['dofs']} unknowns: {rows[-1]['wall']:.2f} s, {rows[-1]['peak_memory_gib']:.2f} GiB")
        summary["bulk"] = rows
        summary["exponents"]["bulk"] = scaling_exponents([r for r in rows if "failed" not in r], "dofs", time_key="wall")
    save_json(out, "performance", summary)
    _plot(out, ok, summary)
    _plot_bounds(out, cut, summary)
    _print_tables(ok, summary)
    return summary


def _fmt(v, spec):
    return "--" if v is None or not np.isfinite(v) else format(v, spec)


def _print_tables(records, summary):
    """The kept (fastest) run of each level with the slowest run's total beside it; the bounds and
    ratios per stage of the cut levels; the exponents; ngsxfem and the bulk levels when run."""
    print(f"{'kind':18s} {'level':>8s} {'dofs':>8s} {'tets':>8s} {'total s':>8s} {'slowest':>8s} {'user s':>7s} {'sys s':>6s} {'GiB':>6s}  stages")
    for r in records:
        stages = " ".join(f"{k}={v:.2f}" for k, v in r["time"].items())
        print(f"{r['kind']:18s} {r['level']:>8g} {r['dofs']:>8d} {r.get('active_tets', 0):>8d} {r['total']:>8.2f} "
              f"{max(r['totals']):>8.2f} {r['cpu_user']:>7.2f} {r['cpu_system']:>6.2f} {r['peak_memory_gib']:>6.2f}  {stages}")
    warm = [r for r in records if "warm" in r]
    if warm:
        print("\nthe same levels run again in their process: the stages' own times, and the start-up the first run "
              "paid inside them")
        print(f"{'kind':18s} {'level':>8s} {'warm s':>8s} {'start s':>8s} {'faults':>8s}  stages")
        for r in warm:
            stages = " ".join(f"{k}={v:.3f}" for k, v in r["warm"]["time"].items())
            print(f"{r['kind']:18s} {r['level']:>8g} {r['warm']['total']:>8.2f} {r['start_up']:>8.2f} "
                  f"{r['warm']['page_faults']:>8d}  {stages}")
    cut = [r for r in records if r["kind"] == "cut"]
    if cut:
        bw = summary["bandwidth"]["bandwidth"]
        both = all("warm" in r for r in cut)
        print(f"\nlower bounds from the memory traffic at {bw / 1e9:.2f} GB/s (estimates, see the module docstring): "
              "bound [ms] and measured / bound per stage, " + ("the stage's own time (run again in its process) and "
                                                                "in parentheses a fresh process's" if both else "in a fresh process"))
        print(f"{'level':>8s} " + " ".join(f"{s:>21s}" for s in CUT_STAGES))
        for r in cut:
            b = r["bounds"]
            cells = (f"{b[s]['bound'] * 1e3:8.2f} " + ("    --" if b[s]["ratio"] is None else f"{b[s]['ratio']:5.0f}x" + (
                f" ({b[s]['ratio_fresh']:.0f}x)" if both else "")) for s in CUT_STAGES)
            print(f"{r['level']:>8g} " + " ".join(f"{c:>21s}" for c in cells))
    if cut and all("stage_cpu" in r for r in cut):
        print("\nsystem time and page faults per stage (the kernel's first touches of memory): system s / thousand faults")
        print(f"{'level':>8s} " + " ".join(f"{s:>15s}" for s in CUT_STAGES))
        for r in cut:
            cells = (f"{r['stage_cpu'][s]['system']:6.2f} / {r['stage_cpu'][s]['faults'] / 1e3:6.0f}" if s in r["stage_cpu"] else "--"
                     for s in CUT_STAGES)
            print(f"{r['level']:>8g} " + " ".join(f"{c:>15s}" for c in cells))
    for name, e in summary["exponents"].items():
        if e:
            stages = " ".join(f"{k}={v:.2f}" for k, v in e.get("stages", {}).items())
            print(f"\nexponents ({name}, against {e['x']}, levels {e['levels']}): time {_fmt(e.get('time'), '.2f')}, "
                  f"user time {_fmt(e.get('user_time'), '.2f')}, memory {_fmt(e.get('memory'), '.2f')}" + (f"; stages {stages}" if stages else ""))
        else:
            print(f"\nexponents ({name}): fewer than three levels ran")
    if summary.get("compiled_references"):
        refs = summary["compiled_references"]
        print(f"\ncompiled references: the same operation on the same data by a compiled library (cut torus at spacing "
              f"{refs[0]['spacing']:g}, {refs[0]['unknowns']} unknowns; medians of {refs[0]['repeat']}); per thread = "
              "reference / cutfem on one thread")
        width = max(len(r["operation"]) for r in refs)
        rwidth = max(len(r["reference"]) for r in refs)
        print(f"  {'operation':{width}s} {'cutfem ms':>10s} {'1 thread':>9s}  {'reference':{rwidth}s} {'ms':>8s} {'per thread':>10s} {'difference':>10s}")
        for r in refs:
            print(f"  {r['operation']:{width}s} {1e3 * r['cutfem']:10.2f} {1e3 * r['cutfem_one_thread']:9.2f}  {r['reference']:{rwidth}s} "
                  f"{1e3 * r['reference_time']:8.2f} {r['per_thread']:10.2f} {r['difference']:10.1e}")
    if summary.get("stage_targets"):
        targets = summary["stage_targets"]
        level = next(iter(targets.values()))["level"]
        print(f"\nevery stage within 2 times of its bound? own time / memory-traffic bound at spacing {level:g}; "
              "cutfem on one thread / the compiled reference (the largest over the stage's rows above; the solve by its kernels)")
        for stage, t in targets.items():
            compiled = "no reference" if t["compiled_ratio"] is None else f"{t['compiled_ratio']:.2f}"
            share = f" (the exact field's evaluation {100 * t['exact_share']:.0f} % of the stage)" if "exact_share" in t else ""
            print(f"  {stage:10s} traffic {_fmt(t['traffic_ratio'], '.0f'):>4s}x   compiled {compiled:>12s}   "
                  f"{'within 2x' if t['within_2x'] else 'not within 2x'}{share}")
    if summary.get("commands"):
        print("\nend to end through the command line (a fresh process a run, start-up included; median of the runs, range)")
        width = max(len(c["command"]) for c in summary["commands"])
        for c in summary["commands"]:
            verdict = "" if c["target"] is None else f"  target {c['target']:g} s: {'met' if c['met'] else 'not met'}"
            print(f"  {c['command']:{width}s} {c['median']:7.2f} s ({c['min']:.2f}-{c['max']:.2f}), {c['peak_memory_gib']:.2f} GiB{verdict}")
    peers = summary.get("peers")
    if peers is not None:
        print()
        if "skipped" in peers:
            print(f"ngsxfem: skipped ({peers['skipped']})")
        for p in peers.get("levels", []):
            if "ratio" in p:
                print(f"ngsxfem {p['level']:>8g}: {p['ngsxfem']['total']:.2f} s against cutfem {p['cutfem_total']:.2f} s, "
                      f"ratio {p['ratio']:.1f}, same problem {p['same_problem']}, peak {p['ngsxfem']['peak_memory_gib']:.2f} GiB")
            else:
                print(f"ngsxfem {p['level']:>8g}: {p.get('skipped') or p['failed'].splitlines()[-1]}")
    if summary.get("bulk"):
        print(f"\n{'bulk poisson':>12s} {'unknowns':>9s} {'wall s':>7s} {'GiB':>6s} {'s/M':>7s} {'GiB/M':>6s}  stages")
        for r in summary["bulk"]:
            if "failed" in r:
                print(f"{r['level']:>12g} failed")
                continue
            stages = " ".join(f"{k}={v:.2f}" for k, v in r["time"].items())
            print(f"{r['level']:>12g} {r['dofs']:>9d} {r['wall']:>7.2f} {r['peak_memory_gib']:>6.2f} {r['seconds_per_million']:>7.2f} "
                  f"{r['gib_per_million']:>6.2f}  {stages}")
    if "limit" in summary:
        lim = summary["limit"]
        big, nxt = lim["largest"], lim["next"]
        print(f"\nlimit {lim['memory_gib']:g} GiB: stopped: {lim['stopped']}")
        if big:
            print(f"  largest level run: spacing {big['level']:g}, {big['active_tets']} active tets, {big['peak_memory_gib']:.2f} GiB; "
                  f"next: spacing {nxt['spacing']:g}, predicted {nxt['active_tets']:.0f} tets, {nxt['peak_memory_gib']:.2f} GiB")


@figure_style
def _plot(out, records, summary):
    from cutfem.runs.convergence import new_figure

    fig, axes = new_figure(PAGE_WIDTH, 3.2, nrows=1, ncols=2)
    ng = [p["ngsxfem"] for p in summary.get("peers", {}).get("levels", []) if "ngsxfem" in p]
    series = [(kind, [r for r in records if r["kind"] == kind]) for kind in ("cut", "meshed-flipped", "meshed-perturbed")]
    for (kind, rs), marker in zip(series + [("ngsxfem", ng)], ("o", "s", "^", "D")):
        if not rs:
            continue
        x = [r["dofs"] if kind.startswith("meshed") else r["active_tets"] for r in rs]
        label = {"cut": "cut torus", "ngsxfem": "ngsxfem, cut torus"}.get(kind, kind.replace("-", ", "))
        for ax, key in zip(axes, ("total", "peak_memory_gib")):
            y = [r[key] for r in rs]
            ax.loglog(x, y, marker=marker, label=f"{label}: {fitted_exponent(x[-3:], y[-3:]):.2f}" if len(x) >= 3 else label)
    for ax, title in zip(axes, ("time [s]", "peak memory [GiB]")):
        ax.set_xlabel("active tets (cut) / nodes (meshed)")
        ax.set_ylabel(title)
        ax.grid(True, which="both", alpha=0.3)
        # the curves rise from the lower left: this corner stays clear
        ax.legend(loc="upper left", title="exponent, 3 finest levels")
    axes[0].set_title("all stages, imports excluded")
    axes[1].set_title("peak resident memory of the process")
    save_figure(fig, out, "performance_scaling")


@figure_style
def _plot_bounds(out, cut, summary):
    """The stage's own time (run again in its process) / bound per stage of the cut levels; with
    the compiled references, the target per stage (:func:`stage_targets`: both ratios of each
    stage against the line at 2); with bulk levels, their time and memory per million unknowns."""
    from cutfem.runs.convergence import new_figure

    bulk = [r for r in summary.get("bulk", []) if "failed" not in r]
    targets = summary.get("stage_targets") or {}
    panels = 1 + bool(targets) + bool(bulk)
    fig, axes = new_figure(PAGE_WIDTH, 3.2 if panels < 3 else 6.0, nrows=1 if panels < 3 else 2, ncols=min(panels, 2), squeeze=False)
    axes = list(axes.ravel())
    if panels == 3:
        axes[3].remove()
    ax = axes[0]
    x = [r["active_tets"] for r in cut]
    for stage in CUT_STAGES[1:]:
        ax.loglog(x, [r["bounds"][stage]["ratio"] for r in cut], marker="o", label=stage)
    ax.set_xlabel("active tets")
    ax.set_ylabel("stage time / memory-traffic bound")
    ax.set_title(f"cut torus, stages warm; {summary['bandwidth']['bandwidth'] / 1e9:.1f} GB/s")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(ncols=2)
    if targets:
        _plot_stage_targets(axes[1], targets)
    if bulk:
        ax = axes[1 + bool(targets)]
        n = [r["dofs"] for r in bulk]
        per_million = ([r["seconds_per_million"] for r in bulk], [r["gib_per_million"] for r in bulk])
        ax.semilogx(n, per_million[0], marker="o", label="wall time [s]")
        ax.semilogx(n, per_million[1], marker="s", label="peak memory [GiB]")
        ax.set_xlabel("unknowns")
        ax.set_ylabel("per million unknowns")
        ax.set_title("poisson-cut, solid torus")
        ax.set_ylim(0, 1.3 * max(max(v) for v in per_million))  # room for the legend above the first points
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper right")  # the values fall from the upper left
    save_figure(fig, out, "performance_bounds")


def _plot_stage_targets(ax, targets: dict) -> None:
    """Per stage, its own time over its memory-traffic bound and its time on one thread over the
    compiled reference's, as horizontal bars on a log axis, with the target 2 as a line."""
    stages = [s for s in CUT_STAGES if s in targets]  # the stages' order (a JSON file may have sorted them)
    y = np.arange(len(stages))
    for k, (key, label) in enumerate((("traffic_ratio", "own time / traffic bound"), ("compiled_ratio", "one thread / compiled reference"))):
        values = [targets[s][key] for s in stages]
        have = [i for i, v in enumerate(values) if v is not None]
        ax.barh(y[have] + (0.2 if k else -0.2), [values[i] for i in have], height=0.38, label=label)
    ax.axvline(2.0, color="k", linestyle="--", linewidth=1, label="target 2")
    ax.set_xscale("log")
    ax.set_yticks(y, [s + ("" if targets[s]["within_2x"] else " (not met)") for s in stages])
    ax.invert_yaxis()
    ax.set_xlabel(f"time ratio (spacing {targets[stages[0]]['level']:g})")
    ax.set_title("every stage within 2 times?")
    ax.grid(True, axis="x", which="both", alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), fontsize="small")


def _positive_gib(text: str) -> float:
    import argparse

    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number of GiB, got {text!r}")
    return value


def main(argv=None) -> int:
    """``python -m cutfem.studies.performance [--peers] [--limit] [--bulk] [--memory-gib G]
    [--peers-down-to S]`` plus the usual study options (``--out``, the size flags)."""
    import argparse

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--peers", action="store_true", help="run ngsxfem on the same cut levels (needs ngsolve and xfem)")
    p.add_argument("--limit", action="store_true", help="halve the spacing until the next cut level is predicted not to fit in --memory-gib")
    p.add_argument("--bulk", action="store_true", help="also time poisson-cut on the solid torus")
    p.add_argument("--memory-gib", type=_positive_gib, default=20.0, help="memory limit of --limit and --peers in GiB (default 20)")
    p.add_argument("--peers-down-to", type=float, default=PEERS_DOWN_TO, help=f"finest spacing for ngsxfem (default {PEERS_DOWN_TO})")
    return study_main(run, "performance", p)(argv)


if __name__ == "__main__":
    sys.exit(main())
