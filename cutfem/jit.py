"""The compile wrapper of cutfem's kernels: numba, the team of threads a call gets, and the
compiled primitives more than one stage shares.

Every parallel kernel is a :class:`_Kernel` (:func:`parallel_kernel`): compiled with numba's
threads (``prange``), cached on disk beside its source, compiled on its first call for each array
type (a few seconds after an install, then loaded).  Each call runs on the team :func:`team` gives
it, and the kernels sum in fixed blocks (:data:`SUM_BLOCK`, :func:`_add_blocks`), so a result has
the same bits on any number of threads.

Team size.  A parallel loop waits at its end for its slowest thread; on a core another process
keeps busy that thread runs only in its time slices, so every loop waits a millisecond or more
however little work it holds, and on an idle machine a loop of a few microseconds of work is
dominated by waking the team.  So a call runs on the calling thread alone when its array arguments
hold less than :data:`PARALLEL_MIN_BYTES` or when the usable cores (``os.sched_getaffinity``, at
most numba's own count) are busy: the busy ticks of those cores in ``/proc/stat`` less this
process's own CPU time, sampled at most every :data:`SAMPLE_SECONDS` (a process's first call counts
the runnable tasks of ``/proc/loadavg``); a core is busy when others use :data:`BUSY_MARGIN` of it.
The count is set for the one call through numba's per-thread setter and put back after it.

Forks.  GNU OpenMP (numba's layer on Linux) cannot serve a process forked after its threads started
(``multiprocessing``'s default start method); in such a process each kernel runs a serial
compilation of the same source, with one warning naming the fix ('spawn' or 'forkserver').

Import time.  The stage modules import their kernel modules at the top, and so numba (0.2 s); the
package's face (:mod:`cutfem`) is the one lazy place: ``import cutfem`` imports nothing heavy, and
each public name imports its stage on first use.
"""

from __future__ import annotations

import math
import os
import time
import warnings

import numpy as np
from numba import njit


#: the arrays of a call below which it runs on the calling thread (bytes): on an idle 2-core machine
#: two threads beat one from about 0.1 MiB (``sparse_kernels.matmul``, docs/performance.md "On a shared
#: machine"); the threshold leaves a margin for a team that has gone to sleep between calls
PARALLEL_MIN_BYTES = 1 << 18

#: the least time between two samples of the machine's load (seconds)
SAMPLE_SECONDS = 0.1

#: the share of a core that the other processes may use while it still counts as free
BUSY_MARGIN = 0.3

_BUSY_FIELDS = (0, 1, 2, 5, 6, 7)  # user, nice, system, irq, softirq, steal of a /proc/stat cpu line

_state = {"time": None, "busy": None, "own": None, "others": 0.0, "cpus": None}


def _usable_cpus() -> frozenset:
    try:
        return frozenset(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return frozenset(range(os.cpu_count() or 1))


def _busy_seconds(cpus: frozenset) -> float | None:
    """Busy seconds of the cores ``cpus`` since boot (/proc/stat), or None where unreadable."""
    try:
        with open("/proc/stat", "rb") as f:
            lines = f.read().split(b"\n")
    except OSError:
        return None
    ticks = 0
    for line in lines[1:]:
        if not line.startswith(b"cpu"):
            break
        fields = line.split()
        if int(fields[0][3:]) in cpus:
            values = fields[1:]
            ticks += sum(int(values[i]) for i in _BUSY_FIELDS if i < len(values))
    return ticks / os.sysconf("SC_CLK_TCK")


def _runnable_others() -> float:
    """Runnable tasks of the machine other than the calling thread (/proc/loadavg), or 0."""
    try:
        with open("/proc/loadavg", "rb") as f:
            running = int(f.read().split()[3].split(b"/")[0])
    except (OSError, IndexError, ValueError):
        return 0.0
    return float(max(0, running - 1))


def others_load() -> float:
    """Cores' worth of CPU the other processes used on this process's usable cores lately."""
    now = time.monotonic()
    last = _state["time"]
    if last is not None and now - last < SAMPLE_SECONDS:
        return _state["others"]
    cpus = _usable_cpus()
    busy, own = _busy_seconds(cpus), time.process_time()
    if busy is None:
        others = 0.0
    elif last is None or cpus != _state["cpus"]:
        others = _runnable_others()
    else:
        others = max(0.0, (busy - _state["busy"]) - (own - _state["own"])) / (now - last)
    _state.update(time=now, busy=busy, own=own, others=others, cpus=cpus)
    return others


def free_cores(limit: int) -> int:
    """Threads worth running now: the usable cores, at most ``limit``, less those other processes
    keep busy (a core is busy when they use :data:`BUSY_MARGIN` of it or more); at least 1."""
    cores = min(limit, len(_usable_cpus()))
    if cores <= 1:
        return 1
    return max(1, min(cores, math.floor(cores - others_load() + BUSY_MARGIN)))


def team(nbytes: int, limit: int) -> int:
    """The threads for a kernel call whose arrays hold ``nbytes`` bytes, numba's current thread
    count being ``limit`` (see the module docstring)."""
    if limit <= 1 or nbytes < PARALLEL_MIN_BYTES:
        return 1
    return free_cores(limit)


#: True in a process forked from one whose numba threads run on GNU OpenMP: that runtime cannot
#: serve a forked child (numba ends such a child with SIGTERM at its first parallel loop)
_FORKED_FROM_THREADS = False


_WARNED_FORK = False  # the warning of :class:`_Kernel`, once a process


def _note_fork():
    global _FORKED_FROM_THREADS
    import sys

    parallel = sys.modules.get("numba.np.ufunc.parallel")
    if sys.platform.startswith("linux") and parallel is not None and getattr(parallel, "_is_initialized", False) \
            and getattr(parallel, "_threading_layer", None) == "omp":  # numba ships GNU OpenMP on Linux
        _FORKED_FROM_THREADS = True


if hasattr(os, "register_at_fork"):  # only this module's flag: nothing else in the process changes
    os.register_at_fork(after_in_child=_note_fork)


_THREAD_COUNT = None  # numba's (get, set) of the calling thread's thread count, once its threads run


def _thread_count_functions():
    """numba's getter and setter of the calling thread's thread count, starting its threads: the
    ctypes entry points behind ``numba.get_num_threads``/``set_num_threads`` where numba has them
    (0.5-0.8 us a call against 2.4 us with the public functions' checks), else the public ones."""
    global _THREAD_COUNT
    import numba

    numba.get_num_threads()  # starts the threading layer: the entry points below need it
    try:
        from numba.np.ufunc.parallel import _get_num_threads, _set_num_threads
    except ImportError:  # pragma: no cover - another numba layout
        _get_num_threads, _set_num_threads = numba.get_num_threads, numba.set_num_threads
    _THREAD_COUNT = (_get_num_threads, _set_num_threads)
    return _THREAD_COUNT


class _Kernel:
    """A kernel compiled for numba's threads (``prange``), called like the function it wraps.

    In a process forked after its parent started numba's threads on GNU OpenMP (the default layer
    on Linux; ``multiprocessing`` forks by default there), OpenMP cannot run, and numba would end
    the process at its first parallel loop.  There the same source is compiled once for the calling
    thread alone (``prange`` as ``range``; not cached on disk, so the first call of each kernel in
    such a process compiles it, with a warning naming the fix), giving the same results: every
    kernel's sums are by blocks in a fixed order, whatever the threads.  Elsewhere each call runs on
    the team :func:`cutfem.jit.team` gives for the bytes of its array arguments and the cores
    free now (the calling thread alone for small arrays or busy cores)."""

    def __init__(self, dispatcher):
        self.parallel = dispatcher
        self._serial = None
        self.__name__ = dispatcher.py_func.__name__
        self.__doc__ = dispatcher.py_func.__doc__
        self.__wrapped__ = dispatcher.py_func

    def __call__(self, *args):
        if not _FORKED_FROM_THREADS:
            get, put = _THREAD_COUNT or _thread_count_functions()
            limit = get()
            size = team(sum(a.nbytes for a in args if isinstance(a, np.ndarray)), limit)
            if size == limit:
                return self.parallel(*args)
            put(size)  # numba keeps the count per calling thread: put back below
            try:
                return self.parallel(*args)
            finally:
                put(limit)
        if self._serial is None:
            global _WARNED_FORK
            if not _WARNED_FORK:
                _WARNED_FORK = True
                warnings.warn(
                    f"cutfem kernel {self.__name__}: this process was forked after numba's OpenMP threads had started "
                    "in its parent, so cutfem's kernels run on one thread here and each is compiled on its first use; "
                    "start worker processes with multiprocessing's 'spawn' or 'forkserver' method to keep the threads "
                    "and the compiled cache", RuntimeWarning, stacklevel=2)
            self._serial = njit(error_model="numpy")(self.parallel.py_func)
        return self._serial(*args)


def parallel_kernel(fn):
    """``fn`` compiled with numba's threads and cached on disk (see :class:`_Kernel`)."""
    return _Kernel(njit(cache=True, error_model="numpy", parallel=True)(fn))


#: rows per partial sum of the column reductions: the order every column is summed in
SUM_BLOCK = 256


#: the chunk counts the lattice sweeps and sums try, in order (:func:`cutfem.solvers.sparse_kernels.sweep_chunks`,
#: :func:`cutfem.fem.assembly_kernels.scatter_chunks`)
SWEEP_CHUNKS = (8, 4)


@njit(cache=True, error_model="numpy", inline="always")
def _add_blocks(part, out):
    """out[l] += part[b, l] over the blocks b in order: per-block partial sums (taken on any thread)
    added as a sequential pass would add them, so a sum does not depend on the number of threads."""
    for b in range(part.shape[0]):
        for l in range(out.shape[0]):
            out[l] += part[b, l]


@njit(cache=True, error_model="numpy", inline="always")
def _ordered_sum(values):
    """The sum of ``values`` (1-d) in index order.  In a parallel kernel ``values.sum()`` is not
    that: numba splits an array reduction between the threads, so its last bits depend on their
    number."""
    total = 0.0
    for i in range(values.shape[0]):
        total += values[i]
    return total
