"""How many threads one call of a compiled kernel gets.

A parallel loop (numba's ``prange`` on GNU OpenMP) hands its iterations to a team of threads and
waits at its end for the slowest.  On a core that another process keeps busy, a member of the team
runs only when the scheduler gives it a time slice, and every loop then waits for that slice (a
millisecond or more), however little work it holds: beside one busy process a loop over a
thousand numbers took seventy times as long on two threads as on one.  And on an idle machine a
loop that holds a few microseconds of work is dominated by waking the team.  So each call of a kernel (:class:`cutfem.kernels._Kernel`) asks :func:`team` for
its number of threads, and runs on the calling thread alone when

* its arrays hold less than :data:`PARALLEL_MIN_BYTES` (256 KiB: the work is not worth waking a
  team), or
* the cores it may use (``os.sched_getaffinity``, and never more than numba's own thread count,
  so that ``NUMBA_NUM_THREADS=1`` or ``numba.set_num_threads`` keep their meaning) are not free:
  :func:`free_cores` is the usable cores less the load of the other processes on them.

The load of the other processes is measured, not guessed: the busy time of the usable cores in
``/proc/stat`` (user, nice, system, irq, softirq and steal ticks) less this process's own CPU time
(``time.process_time``, which includes its waiting OpenMP threads), over the time since the last
sample; a sample is taken at most every :data:`SAMPLE_SECONDS`, and the first call of a process,
which has no earlier sample, counts the runnable tasks of ``/proc/loadavg`` other than itself.  A
core counts as free when the others use less than :data:`BUSY_MARGIN` of it.  Where ``/proc`` is
missing the size rule alone decides.

The team size is set for the one call with ``numba.set_num_threads``, which numba keeps per calling
thread, and put back after it: nothing outside cutfem's own calls changes.  A team of one never
wakes the waiting threads, so under contention they sleep instead of competing with the calling
thread for a core.  Every kernel sums in blocks of a fixed order (:mod:`cutfem.kernels`), so the
results are the same bits whatever the team.  ``studies/contention.py`` measures the policy:
default threads against one thread, and a script against the command line, beside a busy process.
"""

from __future__ import annotations

import math
import os
import time

#: the arrays of a call below which it runs on the calling thread (bytes): on an idle 2-core machine
#: two threads beat one from about 0.1 MiB (``kernels.matmul``, docs/performance.md "On a shared
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
