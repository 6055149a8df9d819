"""The levels of the performance benchmark (:mod:`cutfem.studies.performance`), measured: each in
a fresh Python process, timed stage by stage, with its own peak memory, CPU times and page faults;
and the commands of the targets timed end to end from a fresh process.

A cut level (:func:`cut_level`) is the cut torus of docs/math.md §6 (box [-1.6,1.6]^2 x
[-0.6,0.6], structured Kuhn background, tau_F = 0.1) at one spacing, a meshed level
(:func:`meshed_level`) the meshed torus of one family (tau_E = 0.1) at one n.  Every level runs
in a fresh Python process (:func:`level_in_fresh_process`), so that its peak resident memory is
its own; the stages are timed with ``perf_counter``:

* cut: background mesh (a :class:`~cutfem.geometry.box.StructuredBox`, nothing stored), cut (band search,
  level-set values near the surface, marching tets), topology (interior faces of the active mesh);
* assembly: the matrix K = M + tau J (``matrix``: one form,
  :func:`~cutfem.problems.mean_curvature.mean_curvature_form`, as ``cutfem run`` assembles it; on
  the structured box the piece mass and the face penalty sum into one set of lattice slots) and the
  right-hand sides A x_k (``rhs``, :func:`~cutfem.fem.terms.position_load`, without A);
* solve: :func:`cutfem.solvers.solve.solve` with the automatic choice (setup and iterations together,
  with the method and iteration count recorded);
* errors: the L2 error on S_h (degree-4 quadrature).

Each level's process runs the level a second time (``warm``: its stage times, total,
iterations and page faults).  The first run also pays the start-up that falls inside the stages
of a fresh process (numba's type registries on the first compiled kernel, a few milliseconds for
each cached kernel it loads) and the first touches of its memory; the second pays only the
stages' own work.  Between the two the process collects its
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

Peak memory is each process's own VmHWM (``/proc/self/status``), not ``ru_maxrss``, which on Linux
also counts the parent's peak (the parent's address space at fork/exec).

The commands are run as from the shell (:func:`command_run`: the wall time of the whole process,
interpreter start, imports and numba's start included).  Before any process is timed the
package's modules are compiled to bytecode (:func:`compile_bytecode`), as an install does: where
``PYTHONDONTWRITEBYTECODE`` is set and the checkout carries no current ``.pyc`` files, every
process would compile the sources again (86 ms a process on the 2-core machine, measured with the
meshed torus 16 x 8, 0.61 against 0.52 s).
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

import cutfem
from cutfem.fem.forms import assemble
from cutfem.fem.terms import position_load
from cutfem.fem.norms import l2_error
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.geometry.cut import CUT, cut_mesh
from cutfem.geometry.shapes import Torus
from cutfem.geometry.box import structured_box
from cutfem.geometry.surface_meshes import TORUS_FAMILIES, torus_mesh
from cutfem.problems.mean_curvature import SOLVER_TOL, mean_curvature_form
from cutfem.runs.runner import Timer
from cutfem.solvers.solve import solve

from .common import pick
from .peers_ngsxfem import ngsxfem_mean_curvature

BOX = ([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6])

#: the timed stages of a cut level, in order
CUT_STAGES = ("background", "cut", "topology", "matrix", "rhs", "solve", "errors")


class StageTimer(Timer):
    """:class:`~cutfem.runs.runner.Timer` that also keeps, per stage, the process's user and system
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
    t = StageTimer()
    with t("background"):
        torus = Torus(1.0, 0.5)
        box = structured_box(*BOX, spacing=spacing)
    with t("cut"):
        cut = cut_mesh(box, torus)
    with t("topology"):
        space = CutSpace(cut)
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
    t = StageTimer()
    with t("mesh"):
        mesh = torus_mesh(n, family, seed=1)
        space = SurfaceP1Space(mesh)
    shared = _timed_system_solve_error(t, space, mesh.ds(), mean_curvature_form(mesh.ds(), tau_e=tau_e), Torus())
    return {"kind": f"meshed-{family}", "level": n, "triangles": int(mesh.n_triangles), **shared}


def ngsxfem_level(spacing: float) -> dict:
    """The cut torus level of :func:`cut_level` in ngsxfem (:func:`cutfem.studies.peers_ngsxfem.ngsxfem_mean_curvature`
    with the zeros of the level set moved to +1e-14 and the collapsed tets left out: cutfem's
    discrete problem; NGSolve's sparse Cholesky, no TaskManager).  ``time`` has the stages mesh,
    levelset, cut, assembly, solve, errors; ``total`` is their sum."""
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
from cutfem.studies.performance_levels import cut_level, meshed_level, ngsxfem_level
kind, level, warm = {kind!r}, {level!r}, {warm!r}
import pyamg, threadpoolctl, cutfem.geometry.cut, cutfem.fem.norms, cutfem.fem.forms, cutfem.geometry.levelset, cutfem.geometry.mesh, cutfem.solvers.solve, cutfem.fem.spaces, cutfem.geometry.surface
if kind == 'ngsxfem':
    import ngsolve, xfem, cutfem.studies.peers_ngsxfem
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
    env = dict(os.environ)
    root = str(Path(cutfem.__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    return env


def compile_bytecode() -> None:
    """Write the ``.pyc`` files of the cutfem package and of its problems and studies (those that
    are missing or stale), as ``pip install`` does for an installed package; the timed processes
    then load bytecode instead of compiling the sources (see the module docstring)."""
    import compileall

    for package in ("cutfem", "problems", "studies"):
        mod = cutfem if package == "cutfem" else importlib.import_module(f"cutfem.{package}")
        compileall.compile_dir(str(Path(mod.__file__).resolve().parent), quiet=1)


def level_in_fresh_process(kind: str, level, warm: bool = True) -> dict:
    """Run one level (``kind`` "cut", "meshed-<family>" or "ngsxfem") in a fresh interpreter that
    first applies :func:`cutfem.memory.configure` and imports everything the stages use (so that
    the CPU times are the stages' own); returns its record with the peak memory (GiB), CPU times
    and page faults.  ``warm``: the level runs a second time in the process (its stages' own
    times, ``warm`` and ``start_up`` of the record; never for ngsxfem)."""
    return fresh_process_result(_LEVEL_CODE.format(kind=kind, level=level, warm=warm and kind != "ngsxfem"), f"level {kind} {level}")


def fresh_process_result(code: str, what: str):
    """Run ``code`` in a fresh interpreter (:func:`_child_env`) and return the JSON of the last line
    it printed that starts with ``RESULT``; a RuntimeError naming ``what``, with the end of its
    standard error, when it fails."""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_child_env())
    if proc.returncode != 0:
        raise RuntimeError(f"{what} failed:\n{proc.stderr[-3000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


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
