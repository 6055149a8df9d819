"""Memory: estimates checked before large allocations, and the process-wide allocation settings of a
large run.

Estimates before allocating
---------------------------
A run that cannot fit is refused before its large arrays exist, with a
:class:`InsufficientMemoryError` (a ``MemoryError``) that states the estimate, the memory available
and the fix.  :func:`available_memory` is the kernel's ``MemAvailable`` (/proc/meminfo; else
``os.sysconf`` available, then physical pages), or the limit set by the environment variable
``CUTFEM_MEMORY_LIMIT`` (bytes, or a number with K, M, G, T, KiB, MiB, GiB, TiB; for tests and
shared machines).  :func:`check_memory` compares.  Each estimate is a fixed part plus a cost per
item, fitted to the peak resident memory of fresh ``cutfem run`` processes and rounded up so that
every measured size stays below its estimate (by 15-50 %, most where the fixed part dominates):

* :data:`CUT_BASE_BYTES` + :data:`BYTES_PER_BAND_CELL` per cell of the band: the cut (band search,
  level-set values, marching tets, surface; the compiled kernels' runtime is loaded during it).
  It is checked once before the band search (:func:`cutfem.geometry.band_search.cut_memory_estimate`), on
  :data:`BAND_MARGIN` times the cells predicted from the surface's area as a survey of a few ten
  thousand cubes sees it (:func:`cutfem.geometry.band_search._surface_survey`: the band at spacing h is
  about sqrt(3) A / h**2 cells for a signed distance);
* :data:`BYTES_PER_BOX_NODE`: what the band search keeps per node of the structured box, a bitmap
  of the band's nodes and a running count per 64-bit word of it
  (:func:`cutfem.geometry.keys.dense_unique`, a quarter byte a node); with it
  :data:`BYTES_PER_BOUNDARY_NODE` per boundary node (checked node by node when the band reaches a
  face of the box), and without a Lipschitz bound :data:`BYTES_PER_EVALUATED_NODE` per node of the
  box instead of the bitmap and the band (every node evaluated; both counted from the arrays);
* :data:`SOLVE_BASE_BYTES` + bytes per active tet: what the stages after the cut (space, faces,
  mass, penalty, solve, errors) add to the resident memory at the check
  (:func:`cutfem.problems.common.check_cut_memory`; the cut's freed temporaries stay in the
  allocator's heap and are reused): 64 MiB plus 200 bytes a tet for the mean curvature problem
  (its own constant), plus :data:`BYTES_PER_ACTIVE_TET` for the others.  The problems give their
  cost to the cut, which checks it before cutting on :data:`TETS_PER_BAND_CELL` active tets per
  predicted band cell, and again on the real active tets after the cut;
* :data:`BYTES_PER_SURFACE_NODE`: a meshed surface problem per node.

A refusal names a spacing that fits: :func:`spacing_that_fits` solves the model of the estimate
at t times the spacing, each part with its own scaling (the fixed parts not at all, the band, the
box's boundary and the active tets like t**-2, the box's nodes like t**-3), for the smallest t at
which every estimate of the run fits, and rounds the spacing up to two digits.  The same command
at that spacing is not refused, and a spacing 1.3 times finer is (tests/test_memory.py).

Allocation settings
-------------------
Process-wide allocation settings for large arrays (Linux): opt-in, never applied on import.

Importing cutfem leaves the process as it was.  :func:`cutfem.run`, from a script or the ``cutfem``
command alike, solves its levels inside :func:`large_run`, which applies the settings and puts them
back after the run.  :func:`configure` applies them for good: the studies' command lines
(``python -m cutfem.studies.NAME``, ``cutfem reproduce``) and every timed level of the performance
benchmark call it, and a script that builds large problems from the pieces may call it, once,
before the large arrays.

A cut or meshed pipeline at a million elements allocates and frees hundreds of arrays of 1-300 MB,
and two defaults of a Linux process make the first touch of that memory the dominant cost: glibc
serves every allocation above its mmap threshold (128 KB, raised dynamically up to 32 MB) by a
fresh ``mmap`` and unmaps it on free, so each new large array page-faults all its pages again; and
numpy advises the kernel to back arrays of 4 MB and more by transparent huge pages, whose faults
are slow (and may compact memory synchronously) when the kernel's THP defrag mode is ``madvise``,
``always`` or ``defer+madvise``.

So :func:`configure` sets glibc's ``M_MMAP_THRESHOLD`` and ``M_TRIM_THRESHOLD`` to
:data:`MMAP_THRESHOLD` (2047 MiB, the largest whole MiB that ``mallopt``'s int parameter takes:
arrays below it come from the heap, and freed memory stays with the process until that much is
free at its top, so the arrays one stage frees serve the next, up to the 0.3-1.3 GB arrays of the
finest levels), and turns numpy's huge-page advice off when the defrag mode would stall.  The gain
is the system time of the first touches of memory, paid for by a few per cent more peak memory
(docs/performance.md).

The settings are a trade: memory freed by the program stays with the process (up to the
threshold) instead of returning to the system, which suits a run that allocates and frees large
arrays repeatedly, not a long-lived host process that should give memory back; that is why
importing the library does not apply them.

The command line and the studies skip them when the environment has ``CUTFEM_ALLOCATOR=system``;
a ``NUMPY_MADVISE_HUGEPAGE`` set by the user is respected.  ``SETTINGS`` records what was applied
(empty until :func:`configure` runs; the benchmark saves it with every level).

How threads wait
----------------
Nothing here: OpenMP's wait policy is left as the environment has it.  Each kernel call runs on
the calling thread alone when the cores are busy or its arrays are small (:mod:`cutfem.jit`), so
the team's threads are not woken then and the policy does not matter; scripts and the command line
run alike (``studies/contention.py``).
"""

from __future__ import annotations

import contextlib
import math
import os
import platform

__all__ = [
    "configure",
    "SETTINGS",
    "MMAP_THRESHOLD",
    "InsufficientMemoryError",
    "available_memory",
    "check_memory",
    "spacing_that_fits",
    "coarser_spacing_fix",
    "format_bytes",
    "CUT_BASE_BYTES",
    "BYTES_PER_BAND_CELL",
    "SOLVE_BASE_BYTES",
    "BYTES_PER_BOX_NODE",
    "BYTES_PER_ACTIVE_TET",
    "BYTES_PER_SURFACE_NODE",
    "BYTES_PER_BOUNDARY_NODE",
    "BYTES_PER_EVALUATED_NODE",
    "BAND_MARGIN",
    "TETS_PER_BAND_CELL",
    "ACTIVE_TETS_MARGIN",
]

#: the fixed part of the cut's memory (measured about 100 MB)
CUT_BASE_BYTES = 150 * 2**20
#: bytes of the cut per predicted cell of the band (measured 831-846 B at scale)
BYTES_PER_BAND_CELL = 1_000
#: bytes per node of a structured box for the band's node bitmap and its word counts (n / 4 bytes)
BYTES_PER_BOX_NODE = 0.25
#: bytes per boundary node of a structured box when its boundary is checked node by node (index
#: triples, ids and their sort; counted from those arrays)
BYTES_PER_BOUNDARY_NODE = 80
#: bytes per node of a structured box whose every node is evaluated (a level set without a Lipschitz
#: bound: coordinates, values, corner ids and the (6, 4) values of each cell's tets; counted)
BYTES_PER_EVALUATED_NODE = 400
#: the band cells predicted from the surveyed area, times this (the final band 0.92-1.05 times the prediction)
BAND_MARGIN = 1.2
#: active tets per band cell, to predict before the cut what the later stages need (measured 3.70-4.24)
TETS_PER_BAND_CELL = 4.0
#: the active tets of a cut scaled to another spacing as spacing**-2, times this (tets times
#: spacing**2 measured within 4 % from spacing 0.04 to 0.01)
ACTIVE_TETS_MARGIN = 1.1
#: the fixed part of what the stages after the cut add (measured about 16 MB)
SOLVE_BASE_BYTES = 64 * 2**20
#: bytes the stages after the cut add per active tet, by default (measured up to 969 B)
BYTES_PER_ACTIVE_TET = 850
#: peak bytes of a meshed surface problem per surface node (measured 2.2 KB)
BYTES_PER_SURFACE_NODE = 2_500

#: environment variable that sets the memory available to cutfem (bytes or "2GiB", "500M", ...)
LIMIT_VARIABLE = "CUTFEM_MEMORY_LIMIT"

_UNITS = {"": 1, "b": 1, "k": 2**10, "kb": 10**3, "kib": 2**10, "m": 2**20, "mb": 10**6, "mib": 2**20,
          "g": 2**30, "gb": 10**9, "gib": 2**30, "t": 2**40, "tb": 10**12, "tib": 2**40}


class InsufficientMemoryError(MemoryError):
    """A computation was refused before allocating because its estimated peak exceeds the memory available."""


def format_bytes(n: float) -> str:
    """'1.07 GiB', '850 MiB', ... (binary units)."""
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if abs(n) >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} B"


def _parse_size(text: str) -> int:
    s = text.strip().lower().replace(" ", "")
    number = s.rstrip("abcdefghijklmnopqrstuvwxyz")
    unit = s[len(number):]
    try:
        value = float(number)
    except ValueError:
        value = float("nan")
    if unit not in _UNITS or not value > 0 or value == float("inf"):
        raise ValueError(f"{LIMIT_VARIABLE}={text!r} is not a memory size; write e.g. 8GiB, 500M or 2000000000")
    return int(value * _UNITS[unit])


def available_memory() -> tuple[int, str]:
    """(bytes, where the number comes from): ``CUTFEM_MEMORY_LIMIT`` when set, else MemAvailable of
    /proc/meminfo, else ``os.sysconf`` (available pages, then physical pages) times the page size."""
    limit = os.environ.get(LIMIT_VARIABLE)
    if limit:
        return _parse_size(limit), LIMIT_VARIABLE
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "MemAvailable"
    except (OSError, ValueError, IndexError):
        pass
    for name in ("SC_AVPHYS_PAGES", "SC_PHYS_PAGES"):
        try:
            return int(os.sysconf(name)) * int(os.sysconf("SC_PAGE_SIZE")), name
        except (AttributeError, ValueError, OSError):
            continue
    return 2**62, "unknown"  # no way to tell: do not refuse


def check_memory(estimate: float, what: str, fix: str) -> None:
    """Raise :class:`InsufficientMemoryError` when ``estimate`` bytes exceed :func:`available_memory`.

    ``what`` names the computation ("the cut of a 3200 x 3200 x 1200 box at spacing 0.001"), ``fix``
    the remedy ("use a coarser spacing, at least 0.004").
    """
    available, source = available_memory()
    if estimate > available:
        raise InsufficientMemoryError(
            f"{what} needs about {format_bytes(estimate)} of memory, more than the {format_bytes(available)} available "
            f"({source}); {fix}"
        )


def spacing_that_fits(estimate, spacing: float, available: float) -> float | None:
    """The finest spacing ``t * spacing`` (t >= 1) at which ``estimate(t)`` bytes fit in
    ``available``, rounded up to two significant digits; None when no t up to a million fits (a
    fixed part alone is too large).

    ``estimate`` is a model of the run at ``t`` times the spacing, non-increasing in t: fixed parts
    and parts that shrink like t**-2 (a surface's band, its active tets) or t**-3 (the box's nodes),
    each with its own scaling.  The smallest t is found by doubling and then 60 bisection steps on
    log t (O(1) work); rounding up keeps the named spacing on the side that fits."""
    lo, hi = 1.0, 1.0
    while estimate(hi) > available:
        lo, hi = hi, 2.0 * hi
        if hi > 1e6:
            return None
    for _ in range(60 if hi > 1.0 else 0):
        mid = math.sqrt(lo * hi)
        lo, hi = (lo, mid) if estimate(mid) <= available else (mid, hi)
    x = hi * spacing
    unit = 10.0 ** (math.floor(math.log10(x)) - 1)
    return float(f"{math.ceil(x / unit) * unit:.2g}")


def coarser_spacing_fix(estimate, spacing: float, available: float, other: str = "") -> str:
    """The fix of a refusal: the spacing of :func:`spacing_that_fits` ("use a coarser spacing (about
    0.0048 or more)" + ``other``), or, when none fits, what the fixed part alone needs."""
    coarser = spacing_that_fits(estimate, spacing, available)
    if coarser is None:
        return f"no spacing fits: the fixed part alone needs about {format_bytes(estimate(1e6))}; free memory"
    return f"use a coarser spacing (about {coarser:g} or more){other}"


#: glibc mmap and trim thresholds set by :func:`configure` (bytes)
MMAP_THRESHOLD = 2047 * 2**20

#: what :func:`configure` applied: {"malloc": bool, "numpy_hugepage": bool | None, "thp_defrag": str | None}
SETTINGS: dict = {}

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
_STALLING_DEFRAG = ("always", "madvise", "defer+madvise")


def thp_defrag_mode(path: str = "/sys/kernel/mm/transparent_hugepage/defrag") -> str | None:
    """The selected transparent-huge-page defrag mode of the kernel, or None when unknown."""
    try:
        text = open(path).read()
    except OSError:
        return None
    start, end = text.find("["), text.find("]")
    return text[start + 1 : end] if 0 <= start < end else None


def _set_glibc_thresholds(value: int) -> bool:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, value)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, value))


def _numpy_hugepage_functions():
    """numpy's (get, set) of its huge-page advice, or (None, None)."""
    for module in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            mod = __import__(module, fromlist=["_set_madvise_hugepage"])
            return mod._get_madvise_hugepage, mod._set_madvise_hugepage
        except (ImportError, AttributeError):
            continue
    return None, None


#: glibc's own mmap and trim thresholds (malloc.h defaults), which :func:`large_run` puts back
GLIBC_DEFAULT_THRESHOLD = 128 * 1024


@contextlib.contextmanager
def large_run():
    """The allocation settings of :func:`configure` for the duration of the block, put back after it.

    :func:`cutfem.run` (and so the command line) solves its levels inside it, so a script that calls
    ``cutfem.run`` allocates as the command does without opting in (without it a script's run paid
    twice the command's system time in page faults).  After the block glibc's
    thresholds are its defaults again (128 KiB; the one trace left is that glibc no longer raises
    its mmap threshold by itself) and numpy's huge-page advice is as it was.  Does nothing when
    :func:`configure` has run (the process opted in for good), inside another such block, or with
    ``CUTFEM_ALLOCATOR=system``."""
    if SETTINGS or _LARGE_RUN["depth"] or os.environ.get("CUTFEM_ALLOCATOR", "").lower() == "system":
        _LARGE_RUN["depth"] += 1
        try:
            yield
        finally:
            _LARGE_RUN["depth"] -= 1
        return
    getter, setter = _numpy_hugepage_functions()
    advice = None if getter is None else bool(getter())
    configure()
    _LARGE_RUN["depth"] += 1
    try:
        yield
    finally:
        _LARGE_RUN["depth"] -= 1
        SETTINGS.clear()
        _set_glibc_thresholds(GLIBC_DEFAULT_THRESHOLD)  # False where there is no glibc: nothing was set
        if setter is not None and advice is not None:
            setter(advice)


_LARGE_RUN = {"depth": 0}


def configure(force: bool = False) -> dict:
    """Apply the settings of the module docstring once (again with ``force``); returns SETTINGS.

    Sets glibc's mmap and trim thresholds to :data:`MMAP_THRESHOLD` (Linux with glibc only) and
    turns numpy's transparent-huge-page advice off when the kernel's defrag mode can stall a fault
    (``always``, ``madvise``, ``defer+madvise``) and ``NUMPY_MADVISE_HUGEPAGE`` is not set.
    Does nothing but record ``skipped`` when the environment has ``CUTFEM_ALLOCATOR=system``.
    Returns the dict ``SETTINGS``: {"malloc": bool (thresholds set), "numpy_hugepage": bool | None
    (numpy's advice afterwards, None where numpy has no switch), "thp_defrag": str | None}.
    """
    if SETTINGS and not force:
        return SETTINGS
    SETTINGS.clear()
    SETTINGS.update(malloc=False, numpy_hugepage=None, thp_defrag=thp_defrag_mode())
    if os.environ.get("CUTFEM_ALLOCATOR", "").lower() == "system":
        SETTINGS["skipped"] = "CUTFEM_ALLOCATOR=system"
        return SETTINGS
    SETTINGS["malloc"] = _set_glibc_thresholds(MMAP_THRESHOLD)
    getter, setter = _numpy_hugepage_functions()
    if setter is not None and "NUMPY_MADVISE_HUGEPAGE" not in os.environ and SETTINGS["thp_defrag"] in _STALLING_DEFRAG:
        setter(False)
    SETTINGS["numpy_hugepage"] = None if getter is None else bool(getter())
    return SETTINGS
