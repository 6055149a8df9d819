"""Runs: a problem solved level by level, timed, with the rates between levels, and its record.

:func:`run` solves the levels of a registered problem (:mod:`cutfem.runs.registry`) one after the
other: it reports progress (one line a level, with the stages of a long level and a note when
cutfem's kernels compile), applies the allocation settings of a large run
(:func:`cutfem.memory.large_run`), collects the garbage of a large level before the next, and
either raises a level's failure or keeps the finished levels.  Its :class:`RunResult` holds the
records and the rates, and writes them as a text table or as self-describing JSON (the problem,
its parameters, the definitions of the entries, the command, the git commit, the threads and the
versions).  :class:`Timer` is the stage timer the problems fill.
"""

from __future__ import annotations

import contextlib
import contextvars
import gc
import json
import math
import numbers
import platform
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..distributed import DISTRIBUTED_LEVELS, DISTRIBUTED_ORDERS, distributed_level, distributed_orders, launched, launched_size
from ..memory import large_run
from .registry import COMMON_DEFINITIONS, ProblemError, check_levels, get_problem

__all__ = [
    "run",
    "RunResult",
    "Timer",
    "SCHEMA_VERSION",
]

#: version of the layout of :meth:`RunResult.to_json` (2: metadata, definitions, failure)
SCHEMA_VERSION = 2

#: the listener of the stages of the level being solved (set by :func:`run` with ``progress=True``)
_STAGE_LISTENER: contextvars.ContextVar = contextvars.ContextVar("cutfem_stage_listener", default=None)

#: seconds a level runs before its progress line shows its stages (:class:`_StageLine`)
STAGES_AFTER = 1.0

#: after a level that ran this many seconds or more, the next level :func:`run` solves in the
#: process starts with a full collection of the process's garbage.  A cut and the element sets,
#: facet sets and measures it caches refer to each other, so Python frees them, and the arrays they
#: hold, by its cycle collector, whose full collections come rarely: a level's objects, once its
#: result is dropped, stayed in memory while the next levels allocated beside them.  Six runs of the
#: cut torus at spacing 0.0125 in one process, each result dropped for the next (a stabilization
#: sweep), reached a peak of 845-884 MiB without the collections and 622-628 MiB with them.  A full
#: collection takes about 50 ms (numba's registries hold some 120 thousand objects), under 5 % of a
#: level of a second; small levels leave little garbage and skip it, and so does a process that
#: turned the collector off (``gc.disable()``).  (The levels of one run keep their objects until
#: the run's result is dropped, unless ``keep_fields=False``: their fields are built from them.)
COLLECT_AFTER = 1.0

#: the wall time of the last level :func:`run` solved in this process (for :data:`COLLECT_AFTER`)
_last_level = {"seconds": 0.0}


class Timer(dict):
    """Stage -> seconds; ``with timer("assembly"): ...`` adds to a stage.  Under :func:`run` with
    ``progress=True`` the end of each stage is also reported to the progress line."""

    @contextmanager
    def __call__(self, stage):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            seconds = time.perf_counter() - t0
            self[stage] = self.get(stage, 0.0) + seconds
            listener = _STAGE_LISTENER.get()
            if listener is not None:
                listener(stage, seconds)


class _StageLine:
    """The stages of a level on its progress line (standard error), once the level has run
    :data:`STAGES_AFTER` seconds: then the stages so far at once, and each later one as it ends,
    so that a long level shows where it is and where its time went
    (``[1/1] mean-curvature-cut spacing=0.003125 ... geometry 3.62 s, assembly 3.67 s, ...``),
    and a short one keeps its one short line."""

    def __init__(self):
        self.t0 = time.perf_counter()
        self.pending = []  # [stage, seconds] not printed yet
        self.last = None  # the stage printed last
        self.shown = False

    def __call__(self, stage, seconds):
        # a stage entered again right after itself (the matrix, then the load: both "assembly") is
        # one entry: summed while not printed, else printed as "+ s" after the first
        if self.pending and self.pending[-1][0] == stage:
            self.pending[-1][1] += seconds
        else:
            self.pending.append([stage, seconds])
        if self.shown or time.perf_counter() - self.t0 >= STAGES_AFTER:
            parts = [f"{name} {t:.2f} s" for name, t in self.pending]
            if self.pending[0][0] == self.last:
                parts[0] = f"+{self.pending[0][1]:.2f} s"
            print(" " + ", ".join(parts) + ",", end="", file=sys.stderr, flush=True)
            self.last = self.pending[-1][0]
            self.pending.clear()
            self.shown = True


#: whether this process has announced the compiling of cutfem's kernels (:func:`compile_notice`)
_COMPILE_ANNOUNCED = False

#: the note of :func:`compile_notice`
COMPILE_NOTE = "compiling cutfem's kernels for this machine: once after an install or an update, then loaded from numba's cache on disk"


def _note_on_progress_line(note: str) -> None:
    print(f" ({note})", end="", file=sys.stderr, flush=True)


@contextmanager
def compile_notice(say: Callable[[str], None] = _note_on_progress_line):
    """Within the context, the first compilation of one of cutfem's kernels (the functions of the
    ``cutfem`` package that numba compiles) is announced by ``say(COMPILE_NOTE)``, once a process
    (default: on the progress line of :func:`run`).  Numba's cache on disk is empty after an
    install, an update or an edit of a kernel module (``cutfem/*/*_kernels.py``); a first run then spends up to a minute
    compiling, which would otherwise look like the level's own time.  A listener of numba's
    ``numba:compile`` events, registered for the duration of the context only; loading a kernel
    from the cache is not a compilation and says nothing."""
    if _COMPILE_ANNOUNCED:
        yield
        return
    from numba.core import event

    class Notice(event.Listener):
        def on_start(self, ev):
            global _COMPILE_ANNOUNCED
            function = getattr((ev.data or {}).get("dispatcher"), "py_func", None)
            module = getattr(function, "__module__", None) or ""
            if not _COMPILE_ANNOUNCED and (module == "cutfem" or module.startswith("cutfem.")):
                _COMPILE_ANNOUNCED = True
                say(COMPILE_NOTE)

        def on_end(self, ev):
            pass

    with event.install_listener("numba:compile", Notice()):
        yield


def check_output(flag: str, path: str, suffixes=None, folder: bool = False) -> None:
    """Refuse (ProblemError naming ``flag``), before anything runs, an output that cannot be written:
    a wrong extension, a path that is (or is not) a folder, or a nearest existing parent folder that
    is not writable (tried by a real write)."""
    target = Path(path)
    if suffixes is not None and target.suffix.lower() not in suffixes:
        raise ProblemError(f"{flag}: {path!r} should end in {' or '.join(suffixes)}")
    if target.exists() and target.is_dir() != folder:
        raise ProblemError(f"{flag}: {path!r} is {'not ' if folder else ''}a folder; give {'a folder' if folder else 'a file path'}")
    parent = target if folder and target.exists() else target.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ProblemError(f"{flag}: cannot write {path!r}: {str(parent)!r} is a file, not a folder; choose another path")
    try:  # a real write (permission bits say nothing to root, nor about read-only file systems)
        with tempfile.TemporaryFile(dir=parent, prefix=".cutfem-write-test-"):
            pass
    except OSError:
        raise ProblemError(f"{flag}: cannot write {path!r}: the folder {str(parent)!r} is not writable; choose another path") from None


def _utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


@dataclass
class RunResult:
    """Records of a convergence run, with rates between levels for every ``*_error`` entry:
    ``rates[k][i] = log(e_i / e_i+1) / log(h_i / h_i+1)`` between the finished levels i and i + 1,
    None where an error or h is missing, zero, infinite or NaN, or the two h are equal.

    ``levels`` are the levels asked for, ``records`` those of the finished levels (the first
    ``len(records)``).  ``failure`` is None, or the level that failed (:func:`run` with
    ``keep_finished=True``): ``{"index", "level", "error_type", "message"}``.
    """

    problem: str
    parameters: dict
    levels: list
    records: list
    rates: dict = field(default_factory=dict)
    failure: dict | None = None
    level_name: str = "level"
    components: int = 1
    definitions: dict = field(default_factory=dict)
    command: list | None = None
    created_utc: str = field(default_factory=_utc_now)
    #: the exception of the failed level (not saved to JSON)
    exception: BaseException | None = field(default=None, repr=False, compare=False)

    def to_json(self) -> dict:
        """The run as plain JSON data, self-describing (``schema_version`` :data:`SCHEMA_VERSION`):
        the problem, its parameters, the levels asked for and the records of those finished, the
        rates, the failure (or None), the definitions of ``h``, ``dofs`` and every error key, the
        number of components and the dofs per component of each level, the command line, the UTC
        time the run started, the git commit of the source and whether its tracked files were
        modified (None outside a git checkout), the thread pools (threadpoolctl) and the versions
        of cutfem, numpy, scipy, pyvista, VTK and Python."""
        keys = ["h", "dofs"] + self.error_keys()
        definitions = {k: self.definitions.get(k, COMMON_DEFINITIONS.get(k, "not defined by the problem")) for k in keys}
        return jsonable(
            {
                "schema_version": SCHEMA_VERSION,
                "problem": self.problem,
                "level_name": self.level_name,
                "parameters": self.parameters,
                "levels": self.levels,
                "records": [{k: v for k, v in r.items() if k != "fields"} for r in self.records],
                "rates": self.rates,
                "failure": self.failure,
                "components": self.components,
                "dofs_per_component": [r.get("dofs") for r in self.records],
                "definitions": definitions,
                "command": self.command,
                "created_utc": self.created_utc,
                **_git_state(),
                "threads": _thread_info(),
                "versions": _versions(),
            }
        )

    def dumps(self) -> str:
        return json.dumps(self.to_json(), indent=2)

    def error_keys(self) -> list:
        """The record keys that hold errors: ``*_error`` and per-field ``*_error_<field>``, with a
        number as value (a Python or numpy int or float, ``np.float32`` included; not a bool)."""
        keys = []
        for r in self.records:
            for k, v in r.items():
                if ("_error" in k and not k.startswith("solver")) and k not in keys and _is_number(v):
                    keys.append(k)
        return keys

    def table(self) -> str:
        """A readable table: level, h, dofs, errors with rates, the size of the domain (``area`` of a
        surface or ``volume`` of a bulk domain, the column left out when no record has it), time
        (the level's wall time; the sum of its stages for a record without one).  A record's
        ``notes`` (a list of sentences: a result to read with care, a column left out and why) are
        printed under the table, each once with the levels that carry it."""
        keys = self.error_keys()
        sizes = [k for k in ("area", "volume") if any(k in r for r in self.records)]
        head = ["level", "h", "dofs"] + [c for k in keys for c in (k, "rate")] + sizes + ["time[s]"]
        rows = []
        for i, r in enumerate(self.records):
            row = [f"{self.levels[i]:g}" if isinstance(self.levels[i], (int, float)) else str(self.levels[i]), f"{r['h']:.4g}", str(r.get("dofs", ""))]
            for k in keys:
                e = r.get(k)
                row.append("" if e is None else f"{e:.4e}")
                rr = self.rates.get(k)
                row.append("" if i == 0 or rr is None or rr[i - 1] is None else f"{rr[i - 1]:.2f}")
            row += [f"{r[k]:.6f}" if _is_number(r.get(k)) else "" for k in sizes]
            row.append(f"{r.get('wall_time', sum(r.get('time', {}).values())):.2f}")
            rows.append(row)
        lines = text_table(head, rows).split("\n")
        notes = {}  # each note once, with the levels that carry it
        for level, r in zip(self.levels, self.records):
            for note in r.get("notes", ()):
                notes.setdefault(note, []).append(f"{level:g}" if isinstance(level, (int, float)) else str(level))
        for note, levels in notes.items():
            lines.append(f"note ({self.level_name}={', '.join(levels)}): {note}")
        if self.failure is not None:
            f = self.failure
            lines.append(f"{self.level_name}={f['level']} failed ({f['error_type']}): {f['message']}")
        return "\n".join(lines)


def text_table(head, rows, left: int = 0) -> str:
    """Fixed-width text of a table: the header, a rule of dashes, the rows (lists of strings);
    columns two spaces apart, the first ``left`` left-aligned, the others right-aligned."""
    widths = [max([len(h)] + [len(r[j]) for r in rows]) for j, h in enumerate(head)]

    def line(cells):
        return "  ".join(c.ljust(w) if j < left else c.rjust(w) for j, (c, w) in enumerate(zip(cells, widths)))

    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in rows])


def _is_number(v) -> bool:
    """Whether ``v`` is a real number (Python or numpy, any width), not a bool."""
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _positive(v) -> bool:
    """Whether ``v`` is a finite number > 0: what a rate log(e_i / e_i+1) / log(h_i / h_i+1) needs
    (a zero, an infinite or a NaN error has no rate; math.log(0) would raise)."""
    return _is_number(v) and math.isfinite(v) and v > 0


def _git_state() -> dict:
    """{"git_commit": the commit of the checkout cutfem runs from, "git_modified": whether its
    tracked files differ from that commit}; both None without git or outside a checkout (never
    fails)."""
    import subprocess

    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5)
        commit = head.stdout.strip()
        if head.returncode != 0 or len(commit) < 40:
            return {"git_commit": None, "git_modified": None}
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here, capture_output=True,
                                text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return {"git_commit": None, "git_modified": None}
    return {"git_commit": commit, "git_modified": bool(status.stdout.strip()) if status.returncode == 0 else None}


def _thread_info() -> dict:
    """CPU count, the native thread pools (BLAS, OpenMP) with their thread counts, and numba's threads
    (the compiled kernels': their number, threading layer once started, and OMP_WAIT_POLICY)."""
    import os
    import sys

    info = {"cpu_count": os.cpu_count(), "pools": [], "numba": None}
    if "numba" in sys.modules:  # asking numba for its threads would start them: read what is known
        import numba

        parallel = sys.modules.get("numba.np.ufunc.parallel")
        started = bool(getattr(parallel, "_is_initialized", False))
        info["numba"] = {"num_threads": numba.get_num_threads() if started else numba.config.NUMBA_NUM_THREADS,
                         "threading_layer": numba.threading_layer() if started else None,
                         "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY")}
    try:
        from ..solvers.common import _threadpoolctl

        info["pools"] = [
            {k: p.get(k) for k in ("user_api", "internal_api", "num_threads", "version")}
            for p in _threadpoolctl().threadpool_info()
        ]
    except Exception:  # pragma: no cover - threadpoolctl missing or failing: the record says so
        info["pools"] = None
    return info


def _versions() -> dict:
    import scipy

    from .. import __version__

    out = {"cutfem": __version__, "numpy": np.__version__, "scipy": scipy.__version__, "python": platform.python_version()}
    for name, module in (("pyvista", "pyvista"), ("vtk", "vtkmodules")):
        try:
            from importlib.metadata import version

            out[name] = version("vtk" if name == "vtk" else name)
        except Exception:
            out[name] = getattr(sys.modules.get(module), "__version__", None)
    return out


def jsonable(obj):
    """Plain Python (dict, list, float, int, bool, str, None) for JSON, numpy scalars and arrays
    included; non-finite floats become None (JSON has no NaN or infinity)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.bool_):  # not an np.integer: it would fall through to repr, the string "np.True_"
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, (int, str, bool)) or obj is None:
        return obj
    return repr(obj)


def _level_solver(problem):
    """The function that solves one level: under an MPI launcher the problem's distributed level
    (:mod:`cutfem.distributed`) on every rank, or its serial one on a single rank; a problem that is
    not distributed is refused on several ranks (ProblemError), never run N times over."""
    if not launched():
        return problem.solve_level
    level = distributed_level(problem.name)
    if level is not None:
        orders = distributed_orders(problem.name)

        def distributed(spacing, order=1, **params):  # most distributed levels are P1 on the planar cut
            if order == 1 or (order in orders and launched_size() > 1):  # order 2 on one rank: the serial level, as ever
                return level(spacing, **params, **({"order": order} if len(orders) > 1 else {}))
            if launched_size() > 1:
                twos = ", ".join(n for n, o in DISTRIBUTED_ORDERS.items() if 2 in o)
                raise ProblemError(f"{problem.name} --order {order} is not distributed (the ranks assemble P1 fields on the "
                                   f"planar cut): run it on one rank, or --order 1 on several (distributed at order 2: {twos})")
            return problem.solve_level(spacing, order=order, **params)

        return distributed
    if launched_size() > 1:
        raise ProblemError(f"{problem.name} is not distributed: run it on one rank (without mpiexec, or mpiexec -n 1). "
                           f"The problems that run on several ranks: {', '.join(sorted(DISTRIBUTED_LEVELS))}")
    return problem.solve_level


def run(name: str, levels=None, progress: bool | Callable = False, keep_finished: bool = False, command=None,
        keep_fields: bool = True, **params) -> RunResult:
    """Solve problem ``name`` at each level (default: the problem's levels) and compute rates.

    ``levels`` are checked before anything is solved (:func:`check_levels`).  ``progress``: True
    prints one line per level to standard error (with the times of its stages when it runs more
    than :data:`STAGES_AFTER` seconds); a callable gets (index, count, level, record-or-None).
    A record's ``notes`` (sentences) are printed under the level's progress line and kept in
    the record (and the JSON).  When a level fails its exception propagates, unless ``keep_finished``: then the run stops
    there and returns the finished levels with ``failure`` set (the command line writes those).
    ``command``: the command line to record in the JSON.  ``keep_fields`` False drops each
    record's ``"fields"`` as soon as its level is solved: the fields are built on demand from the
    level's cut, space and solution, which a record that keeps them keeps in memory while the next
    levels run (the cut torus at spacings 0.025, 0.0125 and 0.00625 in one run: peak 1.54 GiB with
    the fields kept, 1.39 GiB without, 1.35 GiB for 0.00625 alone).  The command line keeps them
    only for ``--vtk``.
    """
    problem = get_problem(name)
    p = problem.resolve(params)
    levels = check_levels(problem, problem.levels_for(levels, p))
    solve_level = _level_solver(problem)
    records, failure = [], None
    started = _utc_now()
    for i, level in enumerate(levels):
        if progress is True:
            print(f"[{i + 1}/{len(levels)}] {problem.name} {problem.level_name}={level} ...", file=sys.stderr, end="", flush=True)
        elif callable(progress):
            progress(i, len(levels), level, None)
        if _last_level["seconds"] >= COLLECT_AFTER and gc.isenabled():
            gc.collect()  # the objects of dropped results of large levels, before this one allocates beside them
        t0 = time.perf_counter()
        token = _STAGE_LISTENER.set(_StageLine() if progress is True else None)
        try:
            with large_run(), (compile_notice() if progress is True else contextlib.nullcontext()):
                rec = solve_level(level, **p)
            if not isinstance(rec, dict) or "h" not in rec:
                raise TypeError(f"{problem.name}: the level {level!r} returned {type(rec).__name__} "
                                f"{'without the key h' if isinstance(rec, dict) else 'instead of a record'}; a level "
                                "returns a dict with at least 'h', the mesh size the rates are taken against")
        except Exception as exc:
            if progress is True:
                print(" failed", file=sys.stderr, flush=True)
            if not keep_finished:
                raise
            failure = {"index": i, "level": level, "error_type": type(exc).__name__, "message": str(exc), "exception": exc}
            break
        except BaseException:
            if progress is True:
                print(" failed", file=sys.stderr, flush=True)
            raise
        finally:
            _STAGE_LISTENER.reset(token)
        rec.setdefault("time", {})
        if not keep_fields:
            rec.pop("fields", None)
        rec["wall_time"] = _last_level["seconds"] = time.perf_counter() - t0
        rec[problem.level_name] = level
        records.append(rec)
        if progress is True:
            print(f" done in {rec['wall_time']:.2f} s", file=sys.stderr, flush=True)
            for note in rec.get("notes", ()):
                print(f"  note: {note}", file=sys.stderr, flush=True)
        elif callable(progress):
            progress(i, len(levels), level, rec)
    result = RunResult(
        problem.name, problem.applicable(p), levels, records, level_name=problem.level_name, components=problem.components,
        definitions=dict(problem.definitions), command=None if command is None else list(command), created_utc=started,
    )
    if failure is not None:
        result.exception = failure.pop("exception")
        result.failure = failure
    h = [r["h"] for r in records]
    for k in result.error_keys():
        e = [r.get(k) for r in records]
        rs = []
        for i in range(len(e) - 1):
            if not (_positive(e[i]) and _positive(e[i + 1]) and _positive(h[i]) and _positive(h[i + 1])) or h[i] == h[i + 1]:
                rs.append(None)
            else:
                rs.append(math.log(e[i] / e[i + 1]) / math.log(h[i] / h[i + 1]))
        result.rates[k] = rs
    return result
