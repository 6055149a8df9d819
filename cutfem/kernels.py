"""Compiled kernels (numba): the sparse block kernels of the iterative solvers and the element
kernels of the assembly that numpy cannot vectorize without large temporaries.

Sparse blocks
-------------
Several right-hand sides share one matrix: the mean curvature problems solve for the three
components of H at once, and CG with multigrid is one recurrence per column.  scipy and pyamg
have only single-vector kernels here (scipy's multi-vector CSR product is no faster than one
product per column, pyamg's Gauss-Seidel takes one vector), so every column read the whole matrix
again.  These kernels read a row of the matrix once for up to :data:`WIDTH` columns stored side by
side, (n, c) in row-major order, with one accumulator per column in registers.

Measured on the 2-core machine (cut torus at spacing 0.0125: 293 244 unknowns, 4.9 million
nonzeros; medians of 21 calls in two runs, ms):

=================================  ============================  ==========
kernel                             one column at a time          one pass
=================================  ============================  ==========
product, 3 columns, float32        13-15 (scipy, 3 products)     5.8-5.9
product, 3 columns, float64 (CG)   19-21 (scipy, 3 products)     9.2-9.4
product, 1 column, float32         4.4-5.9 (scipy)               4.4-6.0
Gauss-Seidel, 3 columns, float32   15-21 (pyamg, 3 sweeps)       6.6-10.7
Gauss-Seidel, 1 column, float32    5.4-6.7 (pyamg)               5.0-7.3
=================================  ============================  ==========

The sparse kernels share the rows between the cores (numba's ``prange``; the timings above are
on one thread).  A product, a column reduction or a CG update splits its rows in blocks of
:data:`SUM_BLOCK`; the sums are taken per block and the blocks' partial sums added in row order
afterwards, so the result is bitwise the same on any number of threads.  A Gauss-Seidel sweep is
sequential by nature; on a matrix whose rows follow a lattice or a grid (the levels of the
geometric multigrid) :func:`sweep_chunks` cuts the rows into 8 or 4 chunks such that chunks of the
same parity are not coupled, and the sweep takes the even chunks at the same time, then the odd
ones: the Gauss-Seidel sweep of that reordering of the rows, again the same bits on any number of
threads (the multigrid needed 20 CG iterations with it on the cut torus at spacing 0.0125, as
with the rows in their order).  The whole solve there: 0.63-0.67 s on the two cores of the
2-core machine against 0.96 s on one (``NUMBA_NUM_THREADS=1``), and ``cutfem run`` 1.85 s against
2.13 s (medians of six interleaved pairs, 2026-12-03); with the Galerkin products, the error sums,
the face penalty's lattice sums and the cut's maps on both cores as well, 1.75 s against 2.16 s.  Splitting only the products had gained
7 %.  numba starts its threads at the first parallel kernel.  Each call takes the team
:mod:`cutfem.threads` gives it: the calling thread alone for arrays under 256 KiB or on busy cores
(beside one busy process a parallel loop waits for its second thread's time slice at every join).
GNU OpenMP (numba's layer on Linux) cannot serve a process forked after its threads started, and
numba ends such a process at its first parallel loop: ``multiprocessing`` forks by default on
Linux, so a parameter study in a pool of workers after a solve in the parent would have lost every
worker.  Each kernel is a :class:`_Kernel`: in such a process it runs a compilation of the same
source for the calling thread (the same bits, compiled on first use there, with one warning that
names the fix, the 'spawn' or 'forkserver' start method; tested).  The module registers an at-fork
callback for this (``os.register_at_fork``) that sets only its own flag.

Indices are read as unsigned and the error model is numpy's: with Python's negative-index and
division-by-zero checks in the inner loop the one-column sweep took 11-15 ms.  The sums run row by
row in the matrix's order, as in scipy and pyamg, so a column's result does not depend on the
columns beside it (bitwise).

Element kernels
---------------
:func:`piece_moments`: the exact surface mass matrix and basis integrals of each piece of S_h in its
cut tet, summed over the piece's triangles in one pass (numpy needed the basis values at every
triangle vertex, or three Gram rows per tet and a sparse product: 2.1 s for the mass matrix of the
cut torus at spacing 0.0125, 853k cut tets).  On a structured box the mass goes triangle by
triangle into the lattice slots instead (:func:`lattice_add_pieces`, no per-tet arrays);
:func:`piece_integrals` gives the basis integrals alone.

:func:`vertex_values`: the trace of a P1 function at the vertices of S_h, each vertex once (numpy
kept (V, 4) dof and basis arrays on the space: 0.86-1.78 s at 1.7 million vertices, spacing
0.00625, against 0.21-0.30 s).

:func:`mixed_kuhn_tets`: the Kuhn tets with nodal values of both signs in the band cells of a
structured box, with their nodes and values, the zero rule's snap and the check of the Lipschitz
bound at the cells' corners on the way (numpy: the (k, 8) corner values, their differences from the
centres and the snap as (k, 8) temporaries, sign bytes, a table, and two (n, 4) gathers through a
flat index, 0.6 s at 3.4 million tets).

:func:`marching`, :func:`slot_keys` and :func:`surface`: the marching tetrahedra.  The sign code of
each candidate tet, the tets whose piece collapsed dropped in place, the keys of the polygon slots
(node or edge), and from their numbering the vertices (each once) and the oriented triangles of
S_h, tet by tet.  numpy needed (m, 4) slot arrays of local edge ends and values, a boolean
compaction of seven arrays, per-slot gathers and a first-slot search: about 3 s for these steps at
3.4 million cut tets (torus, spacing 0.00625, line profile), against 0.8 s now.

:func:`kuhn_face_pairs`: the interior faces of the active mesh of a structured box from their
lattice face keys, computed on the fly and paired by two marker arrays (numpy grouped them by a
radix sort: the faces of the 3.4 million cut tets took 2.5 s, then 0.7 s with the keys made by
numpy and paired here, 0.22-0.34 s with the keys made on the fly; the same pairs).
:func:`face_normals_areas`: their unit normals and areas from the gradient table (numpy: a
gathered (F, 3) block and four passes, 0.43-0.70 s for the 5.6 million faces, against 0.15 s).

:func:`level_set_normals`: n_h = grad phi_h / |grad phi_h| of each cut tet from its nodal values
(numpy: an (m, 4, 3) gradient block and an einsum, 0.18 s at 853k tets).

:func:`tangential_gradient_sums`: sum_K w_K P_h grad lambda_i per dof, the right-hand sides of the
mean curvature problem (numpy built the (m, 4, 3) tangential gradients first: 0.55 s at 853k
cut tets).

:func:`refine_blocks`: the band search's next level, the children of the kept blocks inside the
box with their centres and their parent's value (numpy: an (k, 8, 3) array of children, a mask,
the centres by three array operations; the band of the torus at spacing 0.00625 took 0.87 s, now
0.43 s, the same cells and values).

:func:`dense_unique`: the distinct values of ids in a known range [0, n) and their ranks, from a
bitmap of n bits and the counts of set bits per 64-bit word.  numpy marked a boolean array of
length n and looked the ranks up in an int32 array of length n: for the band of the box at spacing
0.003125 (404 million nodes, 28 million corner ids) 0.9-2.3 s and 2 GB of address space, most of
the time in page faults, against 0.18-0.22 s and 100 MB.

:func:`symmetric_pattern`: the CSR structure of the closed-form matrices of a surface mesh (a
diagonal and one value per pair of nodes) by a counting sort of the pairs on their smaller node, in
int32 while it fits (numpy sorted the pair keys and built the mirrors by a sparse transpose: the
edge-penalty stencil of the meshed torus 768 x 384, 1.77 million pairs, in 150 ms against 59 ms;
the same arrays).

:func:`meshed_edge_penalty`, :func:`symmetric_data`, :func:`triangle_geometry` and
:func:`closed_halfedges`: the meshed surface's edge penalty in closed form, the CSR values of a
:class:`~cutfem.assembly.SymmetricPattern`, the triangles' cross products and edge dots, and the
one-sort half-edge table of a closed mesh (a counting sort on the smaller node).  numpy took a dozen
(M, 3) temporaries, a bincount and three scatters, two dozen column passes a block, and an argsort:
at 768 x 384 the edge penalty 75-130 ms against 30 ms, the mesh checks 85 ms against 21 ms, the
same bits.

:func:`grid_weights`: the corners and weights of the prolongation of a doubly periodic surface
grid (the meshed torus's multigrid), one pass over the nodes (numpy: (n m, 4, 3) blocks of corner
offsets; 100-146 ms at 768 x 384 against 14 ms, equal to 1e-14 relative).

:func:`triangle_points` and :func:`squared_error`: the quadrature points of a block of triangles
of S_h and the weighted squared error there (the L2 error of a trace; numpy needed a dozen small
array operations a block, so blocks of 1024 triangles and a millisecond of overhead each).

:func:`rule_points`, :func:`barycentric_values`, :func:`cell_value_error` and
:func:`cell_gradient_error`: the volume (and cell) quadrature of the bulk fields: the points of a
reference rule on a block of simplices (gathered from the mesh's nodes in the same pass), the P1
basis values at points of cut cells, and the weighted squared errors of values and gradients over a
block (per-point accumulators, so the loops pipeline without reassociating a sum).  With
:func:`kuhn_tet_nodes` (the node ids of Kuhn tets from their ids) and :func:`side_split` (the tets
wholly or partly on one side of the level set) they replaced numpy passes and temporaries over
every element of a side: the fictitious-domain Poisson problem at 2.7 million unknowns took 36 s
instead of 44 s and 3.2 instead of 3.8 GiB.

:func:`jump_rows`: the rows of the jump of normal derivatives across pairs of tets (face and edge
penalties), a block of pairs at a time.

:func:`galerkin`: the setup of the geometric multigrid.  The coarse matrix P^T A P row by row
with a dense accumulator, only its upper triangle, then mirrored (scipy: A P, then P^T (A P), then
(G + G^T) / 2 for exact symmetry): the first Galerkin product on the cut torus at spacing 0.00625
(1.18 million unknowns) took 1.2-1.6 s with scipy, 0.64 s here.

:func:`presmooth`: the forward Gauss-Seidel sweep of a cycle from zero with its residual in one
pass over the rows, each row read up to its diagonal (the strict upper triangle U of each level,
kept for the residual -U X, took 1.1 s to extract at spacing 0.003125 and 0.3 GB; the
presmoothing of the finest level at spacing 0.00625 takes 25-27 ms against 35 ms for the sweep
and the product by U, for three columns).

Lattice sums
------------
On a structured box the nodes of two tets that share a face differ by one of 13 lattice vectors
(:func:`~cutfem.mesh.kuhn_neighbour_offsets`), so a symmetric matrix assembled from tets and
faces has at most 13 entries right of the diagonal in each row.  :func:`lattice_add_elements` and
:func:`lattice_add_rows` (with :func:`lattice_add_face_jumps` and :func:`lattice_add_pieces`) add
element matrices and Gram rows, each times a scale, into 13 slots a node (the slot of the pair
(a, b), a < b, is 13 a + the rank of the node-id difference), and :func:`lattice_csr` writes the
CSR arrays from them on all cores, each entry at a position fixed by the slots: no sort, no
sparse product, exactly symmetric.  This is what
:class:`cutfem.assembly.LatticeSum` does; :func:`cutfem.forms.assemble` sums all the lattice
terms of a form into one set of slots.  The face penalty (:func:`lattice_add_face_jumps`) builds
each face's row in scalars on the five nodes the opposite vertices name: 140 ns a face at spacing
0.00625, against 230-250 ns with generic rows merged by search.  Its time is computation, not
traffic: the faces sorted by their lowest node ran no faster, and neither did the sums and the
partners side by side in one array.

Compilation
-----------
A kernel is compiled on its first call for each width c (1, 2 or 3) and array type, and cached on
disk by numba (``cache=True``, in ``__pycache__`` beside this file): the first run after an
install spends a few seconds compiling, later runs load the machine code (0.4 s for the first
kernel, the start of numba's compiler, 15 ms for each further one).  Wider blocks go through in
groups of :data:`WIDTH` columns.
"""

from __future__ import annotations

import math
import os

import numpy as np
import scipy.sparse as sp
import warnings

from numba import njit, prange

from .numbering import TET_EDGES, index_dtype
from .threads import team

_TET_EDGES = np.ascontiguousarray(TET_EDGES, dtype=np.int64)  # a global array: a compile-time constant

__all__ = ["WIDTH", "matmul", "csr_diagonal", "gauss_seidel", "presmooth", "sweep_chunks", "column_dots", "cg_step", "cg_direction", "piece_moments", "piece_integrals", "scatter_add", "radix_argsort", "kuhn_tet_nodes", "side_split", "rule_points", "barycentric_values", "cell_value_error", "cell_gradient_error", "vertex_values", "mixed_kuhn_tets", "label_scales", "marching", "slot_keys", "surface", "kuhn_face_keys", "kuhn_face_pairs", "face_normals_areas", "edge_census", "galerkin", "kuhn_ends_bounds", "kuhn_ends_codes", "kuhn_prolongation_csr", "dense_unique", "prune_blocks", "kept_cells", "refine_blocks", "box_cell_corner_ids", "box_ids_on_faces", "kuhn_types", "level_set_normals", "torus_mean_curvature_vector", "tangential_gradient_sums", "meshed_position_load", "triangle_points",
           "squared_error", "triangle_areas", "jump_rows", "lattice_add_elements", "lattice_add_pieces", "lattice_add_rows",
           "lattice_add_face_jumps",
           "lattice_csr", "scatter_chunks"]

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
    the team :func:`cutfem.threads.team` gives for the bytes of its array arguments and the cores
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
                    f"cutfem.kernels.{self.__name__}: this process was forked after numba's OpenMP threads had started "
                    "in its parent, so cutfem's kernels run on one thread here and each is compiled on its first use; "
                    "start worker processes with multiprocessing's 'spawn' or 'forkserver' method to keep the threads "
                    "and the compiled cache", RuntimeWarning, stacklevel=2)
            self._serial = njit(error_model="numpy")(self.parallel.py_func)
        return self._serial(*args)


def parallel_kernel(fn):
    """``fn`` compiled with numba's threads and cached on disk (see :class:`_Kernel`)."""
    return _Kernel(njit(cache=True, error_model="numpy", parallel=True)(fn))


#: columns served by one pass over the matrix (one register accumulator each)
WIDTH = 3

#: rows per partial sum of the column reductions: the order every column is summed in
SUM_BLOCK = 256

#: the chunk counts :func:`sweep_chunks` tries, in order
SWEEP_CHUNKS = (8, 4)

_COMPILED: dict = {}


@njit(cache=True, error_model="numpy", inline="always")
def _add_blocks(part, out):
    """out[l] += part[b, l] over the blocks b in order: per-block partial sums (taken on any thread)
    added as a sequential pass would add them, so a sum does not depend on the number of threads."""
    for b in range(part.shape[0]):
        for l in range(out.shape[0]):
            out[l] += part[b, l]


def _kernels(c: int):
    """The product and sweep kernels for blocks of exactly ``c`` columns (c <= WIDTH); ``c`` is a
    compile-time constant of the closures, so the unused accumulators vanish."""
    if c in _COMPILED:
        return _COMPILED[c]

    @parallel_kernel
    def product(indptr, indices, data, X, Y, alpha, accumulate, dots):
        """Y = alpha A X (accumulate: Y += alpha A X), X (n_in, c), Y (n_out, c); with ``dots`` (c,)
        not empty (A square), also dots += the column dot products of X and the new Y in double
        precision, summed as :func:`column_dots` sums."""
        n = Y.shape[0]
        with_dots = dots.shape[0] > 0
        nblocks = (n + SUM_BLOCK - 1) // SUM_BLOCK
        part = np.zeros((nblocks if with_dots else 0, 3))
        for b in prange(nblocks):
            d0 = d1 = d2 = 0.0
            for i in range(b * SUM_BLOCK, min((b + 1) * SUM_BLOCK, n)):
                s0 = s1 = s2 = Y.dtype.type(0)
                for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + 1])):
                    j = np.uint64(indices[k])
                    a = data[k]
                    s0 += a * X[j, 0]
                    if c > 1:
                        s1 += a * X[j, 1]
                    if c > 2:
                        s2 += a * X[j, 2]
                if accumulate:
                    Y[i, 0] += alpha * s0
                    if c > 1:
                        Y[i, 1] += alpha * s1
                    if c > 2:
                        Y[i, 2] += alpha * s2
                else:
                    Y[i, 0] = alpha * s0
                    if c > 1:
                        Y[i, 1] = alpha * s1
                    if c > 2:
                        Y[i, 2] = alpha * s2
                if with_dots:
                    d0 += np.float64(X[i, 0]) * np.float64(Y[i, 0])
                    if c > 1:
                        d1 += np.float64(X[i, 1]) * np.float64(Y[i, 1])
                    if c > 2:
                        d2 += np.float64(X[i, 2]) * np.float64(Y[i, 2])
            if with_dots:
                part[b, 0] = d0
                part[b, 1] = d1
                part[b, 2] = d2
        if with_dots:
            _add_blocks(part, dots)

    @parallel_kernel
    def sweep(indptr, indices, data, X, B, forward, bounds):
        """One Gauss-Seidel sweep for A X = B in place in the chunk order of ``bounds`` (see
        :func:`sweep_chunks`): forward, the even chunks (in parallel, each in increasing row order),
        then the odd ones; backward, the reverse.  A must have its diagonal stored."""
        nch = bounds.shape[0] - 1
        for phase in range(2):
            color = phase if forward else 1 - phase
            for h in prange((nch - color + 1) // 2):
                ch = 2 * h + color
                lo, hi = bounds[ch], bounds[ch + 1]
                for t in range(hi - lo):
                    i = np.uint64(lo + t if forward else hi - 1 - t)
                    d = data[0]
                    s0 = B[i, 0]
                    s1 = B[i, 1] if c > 1 else s0
                    s2 = B[i, 2] if c > 2 else s0
                    for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + 1])):
                        j = np.uint64(indices[k])
                        a = data[k]
                        if j == i:
                            d = a
                        else:
                            s0 -= a * X[j, 0]
                            if c > 1:
                                s1 -= a * X[j, 1]
                            if c > 2:
                                s2 -= a * X[j, 2]
                    X[i, 0] = s0 / d
                    if c > 1:
                        X[i, 1] = s1 / d
                    if c > 2:
                        X[i, 2] = s2 / d

    @parallel_kernel
    def presweep(indptr, indices, data, X, B, R, bounds):
        """One forward Gauss-Seidel sweep (the chunk order of ``bounds``) for A X = B from X = 0
        (X written, not read first) and the residual R = B - A X; A exactly symmetric with sorted
        rows and its diagonal stored.  The entries of row i swept before it: in an even chunk
        [lo, hi), those with lo <= j < i; in an odd one, those with j < i or j >= hi."""
        nch = bounds.shape[0] - 1
        zero = R.dtype.type(0)
        one = np.uint64(1)
        for color in range(2):
            for h in prange((nch - color + 1) // 2):
                ch = 2 * h + color
                lo, hi = np.uint64(bounds[ch]), np.uint64(bounds[ch + 1])
                for i in range(lo, hi):
                    start, stop = np.uint64(indptr[i]), np.uint64(indptr[i + 1])
                    first = start
                    if color == 0:
                        while first < stop and np.uint64(indices[first]) < lo:  # another chunk, not swept yet
                            first += one
                    s0 = B[i, 0]
                    s1 = B[i, 1] if c > 1 else s0
                    s2 = B[i, 2] if c > 2 else s0
                    if color == 1:
                        first = start
                    # the entries before the diagonal, summed while it is found (a search first, then one
                    # loop over both segments as in the residual below, was 10 % slower: 6.2 against 5.5 ms)
                    diag = first
                    while diag < stop:
                        j = np.uint64(indices[diag])
                        if j >= i:
                            break
                        a = data[diag]
                        s0 -= a * X[j, 0]
                        if c > 1:
                            s1 -= a * X[j, 1]
                        if c > 2:
                            s2 -= a * X[j, 2]
                        diag += one
                    d = data[diag] if diag < stop and np.uint64(indices[diag]) == i else data[0]
                    above = stop  # the entries in the chunk after, swept before row i when it is odd
                    if color == 1:
                        while above > diag and np.uint64(indices[above - one]) >= hi:
                            above -= one
                        for k in range(above, stop):
                            j = np.uint64(indices[k])
                            a = data[k]
                            s0 -= a * X[j, 0]
                            if c > 1:
                                s1 -= a * X[j, 1]
                            if c > 2:
                                s2 -= a * X[j, 2]
                    x0, x1, x2 = s0 / d, s1 / d, s2 / d
                    X[i, 0] = x0
                    R[i, 0] = zero
                    if c > 1:
                        X[i, 1] = x1
                        R[i, 1] = zero
                    if c > 2:
                        X[i, 2] = x2
                        R[i, 2] = zero
                    for seg in range(2):  # x_i is final: its term in the rows swept before it
                        for k in range(first, diag) if seg == 0 else range(above, stop):
                            j = np.uint64(indices[k])
                            a = data[k]
                            R[j, 0] -= a * x0
                            if c > 1:
                                R[j, 1] -= a * x1
                            if c > 2:
                                R[j, 2] -= a * x2

    _COMPILED[c] = (product, sweep, presweep)
    return product, sweep, presweep


def _csr(A):
    if not sp.isspmatrix_csr(A) and not isinstance(A, sp.csr_array):
        raise TypeError(f"the compiled kernels take a CSR matrix, got {type(A).__name__}")
    return A.indptr, A.indices, A.data


def _groups(c: int):
    return [slice(g, min(g + WIDTH, c)) for g in range(0, c, WIDTH)]


_NO_DOTS = np.zeros(0)


def matmul(A, X, out=None, alpha: float = 1.0, accumulate: bool = False, dots=None):
    """``out = alpha A X`` (``accumulate``: ``out += alpha A X``) for a CSR matrix A and a block X
    (n, c) of the matrix's dtype, C-contiguous; returns ``out`` (allocated when None).  One pass
    over A for each :data:`WIDTH` columns.

    ``dots``: a float64 array (c,) for a square A, overwritten with the column dot products of X
    and ``out`` computed in the same pass, bitwise :func:`column_dots` (X, out), in double
    precision whatever the blocks' dtype (CG's p^T A p without reading p and A p again: at 4.7
    million unknowns and three columns, 0.23 GB an iteration)."""
    indptr, indices, data = _csr(A)
    if X.ndim != 2 or X.shape[0] != A.shape[1] or X.dtype != data.dtype or not X.flags.c_contiguous:
        raise ValueError(f"X must be a C-contiguous ({A.shape[1]}, c) block of {data.dtype}, got {X.shape} {X.dtype}")
    c = X.shape[1]
    if out is None:
        if accumulate:
            raise ValueError("accumulate=True needs out=")
        out = np.empty((A.shape[0], c), dtype=data.dtype)
    if dots is None:
        dots = _NO_DOTS
    elif dots.shape != (c,) or dots.dtype != np.float64 or A.shape[0] != A.shape[1]:
        raise ValueError(f"dots must be a float64 array ({c},) and A square, got {dots.shape} {dots.dtype} and A {A.shape}")
    else:
        dots[:] = 0.0
    alpha = data.dtype.type(alpha)
    if c <= WIDTH:
        _kernels(c)[0](indptr, indices, data, X, out, alpha, accumulate, dots)
        return out
    for g in _groups(c):
        Y = np.ascontiguousarray(out[:, g]) if accumulate else np.empty((A.shape[0], g.stop - g.start), data.dtype)
        part = dots[g] if dots.shape[0] else _NO_DOTS
        _kernels(g.stop - g.start)[0](indptr, indices, data, np.ascontiguousarray(X[:, g]), Y, alpha, accumulate, part)
        out[:, g] = Y
    return out


@parallel_kernel
def _csr_diagonal(indptr, indices, data, canonical, out):
    for i in prange(out.shape[0]):
        s = data.dtype.type(0)
        lo, hi = indptr[i], indptr[i + 1]
        if canonical:  # sorted, no duplicates: a binary search reads a few indices of the row
            while lo < hi:
                mid = (lo + hi) // 2
                if indices[mid] < i:
                    lo = mid + 1
                else:
                    hi = mid
            if lo < indptr[i + 1] and indices[lo] == i:
                s = data[lo]
        else:
            for k in range(lo, hi):
                if indices[k] == i:
                    s += data[k]
        out[i] = s


def csr_diagonal(A):
    """The diagonal of a CSR matrix (min(n, m),), the entries of a row on the diagonal summed as
    scipy's ``A.diagonal()`` sums them, on all cores; in a matrix flagged canonical (sorted rows
    without duplicates) each row's entry is found by a binary search.  scipy's serial pass took
    29 ms for the 19.8 million entries of the cut torus at spacing 0.00625, and a solve asked for
    it twice."""
    indptr, indices, data = _csr(A)
    out = np.empty(min(A.shape), dtype=data.dtype)
    _csr_diagonal(indptr, indices, data, bool(A.has_canonical_format), out)
    return out


@parallel_kernel
def _column_dots(a, b, c, out, out_c):
    n, k = a.shape
    with_c = c.shape[0] > 0
    nblocks = (n + SUM_BLOCK - 1) // SUM_BLOCK
    part = np.zeros((nblocks, k))
    part_c = np.zeros((nblocks, k if with_c else 0))
    for blk in prange(nblocks):
        for i in range(blk * SUM_BLOCK, min((blk + 1) * SUM_BLOCK, n)):
            for l in range(k):
                bi = np.float64(b[i, l])
                part[blk, l] += np.float64(a[i, l]) * bi
                if with_c:
                    part_c[blk, l] += bi * np.float64(c[i, l])
    _add_blocks(part, out)
    if with_c:
        _add_blocks(part_c, out_c)


_NO_BLOCK = np.zeros((0, 0))


def _float_block(a):
    a = np.ascontiguousarray(a)
    return a if a.dtype in (np.float32, np.float64) else a.astype(float)


def column_dots(a, b, c=None):
    """The dot products of the columns of a and b (n, k), in double precision: in blocks of
    :data:`SUM_BLOCK` rows, in row order, so a column's result does not depend on the columns
    beside it (numpy's strided reductions change their order with k; CG's scalars, and so its
    iterates, would differ in the last bits between a column solved alone and in a block).
    float32 and float64 blocks are read as they are (the products are formed in double precision,
    so the result is that of the blocks converted to float64), anything else as float64.

    With ``c`` (n, k): returns ``(a^T b, b^T c)`` column by column, both from one pass over the
    three blocks and each bitwise what it is alone (CG's r^T z and z^T q: one read of z)."""
    a, b = _float_block(a), _float_block(b)
    out = np.zeros(a.shape[1])
    if c is None:
        _column_dots(a, b, _NO_BLOCK, out, out)
        return out
    c = _float_block(c)
    out_c = np.zeros(a.shape[1])
    _column_dots(a, b, c, out, out_c)
    return out, out_c


@parallel_kernel
def _cg_step(x, r, p, q, alpha, act, out):
    n, k = p.shape
    nblocks = (n + SUM_BLOCK - 1) // SUM_BLOCK
    part = np.zeros((nblocks, k))
    for blk in prange(nblocks):
        for i in range(blk * SUM_BLOCK, min((blk + 1) * SUM_BLOCK, n)):
            for l in range(k):
                c = act[l]
                x[i, c] += alpha[l] * p[i, l]
                ri = r[i, c] - alpha[l] * q[i, l]
                r[i, c] = ri
                part[blk, l] += ri * ri
    _add_blocks(part, out)


def cg_step(x, r, p, q, alpha, act):
    """The CG update of the active columns ``act`` (k,) of x and r (n, c) in place:
    x[:, act] += alpha p, r[:, act] -= alpha q (p, q (n, k)); returns ||r[:, act]||^2 (k,), summed as
    :func:`column_dots` sums (one pass instead of five numpy operations on (n, c) arrays)."""
    out = np.zeros(len(act))
    _cg_step(x, r, np.ascontiguousarray(p), np.ascontiguousarray(q), np.asarray(alpha, dtype=float),
             np.asarray(act, dtype=np.int64), out)
    return out


@parallel_kernel
def _cg_direction(p, z, beta):
    n, k = p.shape
    for i in prange(n):
        for l in range(k):
            p[i, l] = np.float64(z[i, l]) + beta[l] * p[i, l]


def cg_direction(p, z, beta):
    """p = z + beta p in place (the next CG search directions, (n, k), C-contiguous, float64; z of
    float64 or float32, read as it is)."""
    _cg_direction(p, _float_block(z), np.asarray(beta, dtype=float))
    return p


def _check_blocks(A, names, X, *others):
    """ValueError unless X and ``others`` are C-contiguous (n, c) blocks of A's dtype, all of X's shape."""
    for Z in (X, *others):
        if Z.shape != X.shape or Z.ndim != 2 or Z.shape[0] != A.shape[0] or Z.dtype != A.dtype \
                or not Z.flags.c_contiguous:
            raise ValueError(f"{names} must be C-contiguous ({A.shape[0]}, c) blocks of {A.dtype}, got {Z.shape} {Z.dtype}")


def _bounds(A, chunks):
    if chunks is None:
        return np.array([0, A.shape[0]], dtype=np.int64)
    chunks = np.asarray(chunks, dtype=np.int64)
    if chunks.ndim != 1 or chunks.size < 2 or chunks[0] != 0 or chunks[-1] != A.shape[0] or np.any(np.diff(chunks) < 0) \
            or (chunks.size > 2 and (chunks.size - 1) % 2):
        raise ValueError(f"chunks must be the bounds 0 = b_0 <= ... <= b_k = {A.shape[0]} of 1 or an even number k of row "
                         f"chunks (sweep_chunks(A)), got {chunks!r}")
    return chunks


def gauss_seidel(A, X, B, forward: bool = True, chunks=None):
    """One Gauss-Seidel sweep for ``A X = B`` in place on X (n, c), C-contiguous, of A's dtype: rows in
    increasing order (``forward``) or the reverse.  A is CSR with its diagonal stored (nonzero).

    ``chunks``: the row-chunk bounds of :func:`sweep_chunks` (None: one chunk, the rows in their
    order).  The sweep then takes the rows chunk by chunk, the even chunks first (at the same time on
    the available cores: no two of them are coupled), then the odd ones, each chunk in increasing
    row order; backward, the exact reverse.  It is the Gauss-Seidel sweep of that reordering of the
    rows, whatever the number of threads (bitwise)."""
    indptr, indices, data = _csr(A)
    _check_blocks(A, "X and B", X, B)
    bounds = _bounds(A, chunks)
    c = X.shape[1]
    if c <= WIDTH:
        _kernels(c)[1](indptr, indices, data, X, B, forward, bounds)
        return X
    for g in _groups(c):
        Y = np.ascontiguousarray(X[:, g])
        _kernels(g.stop - g.start)[1](indptr, indices, data, Y, np.ascontiguousarray(B[:, g]), forward, bounds)
        X[:, g] = Y
    return X


def presmooth(A, X, B, R, chunks=None):
    """The first half of a multigrid cycle on one pass over A: X = one forward Gauss-Seidel sweep for
    ``A X = B`` from X = 0 (in the order of ``chunks``, as :func:`gauss_seidel`), and R = B - A X,
    for an exactly symmetric CSR matrix A with sorted rows and its diagonal stored (nonzero); X, B,
    R (n, c) C-contiguous blocks of A's dtype; returns R.

    Row i of the sweep meets only the entries of the rows swept before it (the others' X is still
    zero), and once x_i is known its terms a_ji x_i in those rows j are the only ones they still
    miss: B_j - sum_{i swept up to j} a_ji x_i vanishes row by row, so r_j = -sum_{i swept after j}
    a_ji x_i, added as the rows go (with one chunk, in the order of the columns of row j: bitwise
    the product -U X with the strict upper triangle U that this replaces; the sweep read every
    entry of A, and the product read U again and kept it, 0.3 GB at spacing 0.003125)."""
    indptr, indices, data = _csr(A)
    if not A.has_sorted_indices:
        raise ValueError("presmooth needs a CSR matrix with sorted indices (A.sort_indices())")
    _check_blocks(A, "X, B and R", X, B, R)
    bounds = _bounds(A, chunks)
    c = X.shape[1]
    if c <= WIDTH:
        _kernels(c)[2](indptr, indices, data, X, B, R, bounds)
        return R
    for g in _groups(c):
        Y, Q = np.empty((X.shape[0], g.stop - g.start), X.dtype), np.empty((X.shape[0], g.stop - g.start), X.dtype)
        _kernels(g.stop - g.start)[2](indptr, indices, data, Y, np.ascontiguousarray(B[:, g]), Q, bounds)
        X[:, g], R[:, g] = Y, Q
    return R


@parallel_kernel
def _chunks_apart(indptr, indices, bounds):
    """Whether no row couples two chunks of the same parity, nor more than one chunk besides its own."""
    nch = bounds.shape[0] - 1
    owner = np.empty(indptr.shape[0] - 1, dtype=np.int32)
    for ch in range(nch):
        owner[bounds[ch]:bounds[ch + 1]] = ch
    bad = 0
    for i in prange(owner.shape[0]):
        own, other = owner[i], -1
        for k in range(indptr[i], indptr[i + 1]):
            cj = owner[indices[k]]
            if cj == own:
                continue
            if (cj - own) % 2 == 0 or (other >= 0 and cj != other):
                bad += 1
                break
            other = cj
    return bad == 0


def sweep_chunks(A, counts=SWEEP_CHUNKS):
    """Row-chunk bounds (k + 1,) for the Gauss-Seidel kernels (:func:`gauss_seidel`,
    :func:`presmooth`): the first k of ``counts`` for which k contiguous chunks of about equal
    nonzeros leave no row coupled to another chunk of its parity, nor to two other chunks (so that
    the even chunks can be swept at the same time, then the odd ones, and the residual of
    :func:`presmooth` gets each row's terms from one chunk); [0, n] (the rows in their order) when
    none does.  Rows ordered along a lattice or a grid, as the levels of the geometric multigrid,
    have their couplings within a band of neighbouring rows: chunks wider than the band pass."""
    indptr, indices, _ = _csr(A)
    n = A.shape[0]
    for k in counts:
        if k < 2 or k % 2 or n < 2 * k:
            continue
        bounds = np.searchsorted(indptr, np.arange(k + 1) * (indptr[-1] / k)).astype(np.int64)
        bounds[0], bounds[-1] = 0, n
        if np.all(np.diff(bounds) > 0) and _chunks_apart(indptr, indices, bounds):
            return bounds
    return np.array([0, n], dtype=np.int64)


@njit(cache=True, error_model="numpy", inline="always")
def _barycentric(x, points, tets, g, k, lam):
    """lam (4,) = the P1 basis values of tet k (vertices ``tets[k]`` into ``points``, basis gradients
    g (4, 3)) at x: delta_i0 + grad lambda_i . (x - x_0)."""
    o = tets[k, 0]
    d0, d1, d2 = x[0] - points[o, 0], x[1] - points[o, 1], x[2] - points[o, 2]
    for i in range(4):
        lam[i] = g[i, 0] * d0 + g[i, 1] * d1 + g[i, 2] * d2
    lam[0] += 1.0


@njit(cache=True, error_model="numpy")
def _piece_moments(vertices, triangles, tets_of, areas, points, tets, table, types, edges, diagonal, integrals):
    lam = np.empty((3, 4))
    for t in range(triangles.shape[0]):
        k = tets_of[t]
        g = table[types[k]]
        for v in range(3):
            _barycentric(vertices[triangles[t, v]], points, tets, g, k, lam[v])
        w = areas[t] / 12.0
        for i in range(4):
            si = lam[0, i] + lam[1, i] + lam[2, i]
            integrals[k, i] += areas[t] * si / 3.0
            diagonal[k, i] += w * (lam[0, i] * lam[0, i] + lam[1, i] * lam[1, i] + lam[2, i] * lam[2, i] + si * si)
        for e in range(6):
            i, j = _TET_EDGES[e, 0], _TET_EDGES[e, 1]
            si = lam[0, i] + lam[1, i] + lam[2, i]
            sj = lam[0, j] + lam[1, j] + lam[2, j]
            edges[k, e] += w * (lam[0, i] * lam[0, j] + lam[1, i] * lam[1, j] + lam[2, i] * lam[2, j] + si * sj)


def piece_moments(vertices, triangles, tets_of, areas, points, tets, table, types):
    """The exact P1 moments of the pieces of S_h over their m cut tets ``tets`` (m, 4) (vertex ids into
    ``points``): ``(edges (m, 6), diagonal (m, 4), integrals (m, 4))`` with
    M_K[i, j] = int_{S_K} lambda_i lambda_j for the local edges (i, j) of
    :data:`~cutfem.numbering.TET_EDGES` and on the diagonal, and int_{S_K} lambda_i.

    The piece S_K is the union of its triangles T (``triangles`` (T, 3) into ``vertices``, in tet
    ``tets_of`` (T,), area ``areas``); the basis functions are affine on T, so with their values
    lambda_v at the three vertices and s = lambda_1 + lambda_2 + lambda_3,

        int_T lambda_i lambda_j = |T| / 12 (sum_v lambda_{v,i} lambda_{v,j} + s_i s_j),
        int_T lambda_i = |T| s_i / 3.

    The values come from the tet's first vertex and its basis gradients ``table[types[k]]``
    (:meth:`~cutfem.markers.ElementSet.gradient_lookup`): lambda_i(x) = delta_i0 + grad lambda_i . (x - x_0)."""
    m = len(tets)
    edges, diagonal, integrals = np.zeros((m, 6)), np.zeros((m, 4)), np.zeros((m, 4))
    _piece_moments(np.ascontiguousarray(vertices, dtype=float), np.ascontiguousarray(triangles),
                   np.ascontiguousarray(tets_of), np.ascontiguousarray(areas, dtype=float),
                   np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(tets),
                   np.ascontiguousarray(table, dtype=float), np.ascontiguousarray(types), edges, diagonal, integrals)
    return edges, diagonal, integrals


@njit(cache=True, error_model="numpy")
def piece_integrals(vertices, triangles, tets_of, areas, points, tets, table, types, dofs, out):
    """out[dofs[k, i]] += int_T lambda_i = |T| lambda_i(centroid of T) for the triangles ``triangles``
    (T, 3) into ``vertices``, of areas ``areas``, lying in the tets ``tets_of`` (T,) (vertex ids
    ``tets`` (m, 4) into ``points``, basis gradients ``table[types[k]]``, dofs ``dofs`` (m, 4)):
    the integrals of the P1 basis functions over the pieces of S_h, exact (lambda_i is affine on T)."""
    lam = np.empty(4)
    x = np.empty(3)
    for t in range(triangles.shape[0]):
        k = tets_of[t]
        for d in range(3):
            x[d] = (vertices[triangles[t, 0], d] + vertices[triangles[t, 1], d] + vertices[triangles[t, 2], d]) / 3.0
        _barycentric(x, points, tets, table[types[k]], k, lam)
        for i in range(4):
            out[dofs[k, i]] += areas[t] * lam[i]


@njit(cache=True, error_model="numpy")
def _vertex_values(vertices, triangles, tets_of, points, tets, table, types, dofs, coeffs, out):
    done = np.zeros(vertices.shape[0], dtype=np.bool_)
    lam = np.empty(4)
    for t in range(triangles.shape[0] - 1, -1, -1):
        k = tets_of[t]
        for v in range(3):
            p = triangles[t, v]
            if done[p]:
                continue
            done[p] = True
            _barycentric(vertices[p], points, tets, table[types[k]], k, lam)
            for c in range(coeffs.shape[1]):
                s = 0.0
                for i in range(4):
                    s += lam[i] * coeffs[dofs[k, i], c]
                out[p, c] = s


def vertex_values(vertices, triangles, tets_of, points, tets, table, types, dofs, coeffs):
    """A P1 function on the tets ``tets`` (m, 4) (vertex ids into ``points``, basis gradients
    ``table[types[k]]``, dofs ``dofs`` (m, 4), coefficients ``coeffs`` (n, c)) at the vertices of the
    triangles ``triangles`` (T, 3) lying in the tets ``tets_of`` (T,): (V, c), each vertex valued in
    the tet of the last triangle that has it (the trace is continuous: any of them would do).  One
    pass over the triangles, last to first, each vertex once; no per-vertex basis arrays."""
    coeffs = np.ascontiguousarray(coeffs, dtype=float)
    out = np.zeros((len(vertices), coeffs.shape[1]))
    _vertex_values(np.ascontiguousarray(vertices, dtype=float), np.ascontiguousarray(triangles),
                   np.ascontiguousarray(tets_of), np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(tets),
                   np.ascontiguousarray(table, dtype=float), np.ascontiguousarray(types), np.ascontiguousarray(dofs),
                   coeffs, out)
    return out


@njit(cache=True, error_model="numpy")
def jump_rows(pairs, normals_a, normals_b, sign_b, weights, dofs, table, types, out_dofs, out_values):
    """Rows of the jumps c = sqrt(w) (t_a . G_{K_a}, t_b . G_{K_b}) for the pairs (K_a, K_b) =
    ``pairs`` (F, 2) of elements with k dofs, t_a = ``normals_a`` (F, 3), t_b = ``sign_b``
    ``normals_b``, w = ``weights`` (F,): ``out_dofs`` (F, 2k) the dofs of K_a then K_b (``dofs``
    (m, k)), ``out_values`` (F, 2k); the gradients are ``table[types[K]]`` (k, 3)
    (:meth:`~cutfem.spaces.CutP1Space.gradient_lookup`)."""
    k = dofs.shape[1]
    for f in range(pairs.shape[0]):
        w = np.sqrt(weights[f])
        for side in range(2):
            el = pairs[f, side]
            g = table[types[el]]
            t = normals_a[f] if side == 0 else normals_b[f]
            scale = w if side == 0 else w * sign_b
            for i in range(k):
                out_dofs[f, k * side + i] = dofs[el, i]
                out_values[f, k * side + i] = scale * (g[i, 0] * t[0] + g[i, 1] * t[1] + g[i, 2] * t[2])


@njit(cache=True, error_model="numpy")
def _slot(ids, code, a, b):
    """The slot of the pair a < b, or -1 when their node ids differ by no lattice offset
    (``code`` (d_max + 1,) int8: the rank of each node-id difference d among the offsets, or -1)."""
    d = ids[b] - ids[a]
    if d >= code.shape[0]:
        return -1
    c = code[d]
    return -1 if c < 0 else a * 13 + c


@njit(cache=True, error_model="numpy", inline="always")
def _add_pair(ids, code, a, b, value, sums, partner):
    """Add ``value`` at the slot of the pair {a, b}; returns 1 when the pair is outside the lattice
    offsets (nothing added), else 0."""
    if a > b:
        a, b = b, a
    s = _slot(ids, code, a, b)
    if s < 0:
        return 1
    sums[s] += value
    partner[s] = b
    return 0


@parallel_kernel
def lattice_add_elements(ids, code, dofs, elements, edges, diagonal, types, weights, scale, sums, partner, diag, bounds):
    """Add ``scale`` times symmetric 4 x 4 element matrices into the slots: for each element k
    (``elements`` (n,), or every row of ``dofs`` (m, 4) when empty) the matrix with entries
    ``weights[k] edges[r]`` on the local edges and ``weights[k] diagonal[r]`` on the diagonal
    (tables ``edges`` (L, 6), ``diagonal`` (L, 4)), r = ``types[k]``, or r = 0 for a one-row table
    and r = k otherwise when ``types`` is empty; ``weights`` empty: 1.  Returns the number of pairs
    outside the lattice offsets (then the caller must not use the sums).  The elements in the
    chunks ``bounds`` of :func:`scatter_chunks`: the even chunks at once, then the odd ones."""
    outside = 0
    nch = bounds.shape[0] - 1
    for color in range(2):
        for h in prange((nch - color + 1) // 2):
            ch = 2 * h + color
            outside += _add_elements(ids, code, dofs, elements, edges, diagonal, types, weights, scale, sums, partner,
                                     diag, bounds[ch], bounds[ch + 1])
    return outside


@njit(cache=True, error_model="numpy")
def _add_elements(ids, code, dofs, elements, edges, diagonal, types, weights, scale, sums, partner, diag, start, stop):
    outside = 0
    for t in range(start, stop):
        k = elements[t] if elements.shape[0] > 0 else t
        r = types[k] if types.shape[0] > 0 else (0 if edges.shape[0] == 1 else k)
        w = scale * weights[k] if weights.shape[0] > 0 else scale
        for e in range(6):
            outside += _add_pair(ids, code, dofs[k, _TET_EDGES[e, 0]], dofs[k, _TET_EDGES[e, 1]], w * edges[r, e], sums,
                                 partner)
        for i in range(4):
            diag[dofs[k, i]] += w * diagonal[r, i]
    return outside


@parallel_kernel
def lattice_add_pieces(ids, code, vertices, triangles, tets_of, areas, points, tets, table, types, dofs, scale, sums,
                       partner, diag, bounds):
    """Add ``scale`` times the exact P1 mass matrices of the triangles ``triangles`` (T, 3) into
    ``vertices``, of areas ``areas``, lying in the tets ``tets_of`` (T,) (vertex ids ``tets`` into
    ``points``, basis gradients ``table[types[k]]``, dofs ``dofs`` (m, 4)) into the slots, triangle
    by triangle: int_T lambda_i lambda_j = |T| / 12 (sum_v lambda_vi lambda_vj + s_i s_j) as in
    :func:`piece_moments`, without its per-tet arrays; returns the number of pairs outside the
    lattice offsets.  The triangles in the chunks ``bounds`` of :func:`scatter_chunks`: the even
    chunks at once, then the odd ones."""
    outside = 0
    nch = bounds.shape[0] - 1
    for color in range(2):
        for h in prange((nch - color + 1) // 2):
            ch = 2 * h + color
            outside += _add_pieces(ids, code, vertices, triangles, tets_of, areas, points, tets, table, types, dofs, scale,
                                   sums, partner, diag, bounds[ch], bounds[ch + 1])
    return outside


@njit(cache=True, error_model="numpy")
def _add_pieces(ids, code, vertices, triangles, tets_of, areas, points, tets, table, types, dofs, scale, sums, partner,
                diag, start, stop):
    lam = np.empty((3, 4))
    outside = 0
    for t in range(start, stop):
        k = tets_of[t]
        g = table[types[k]]
        for v in range(3):
            _barycentric(vertices[triangles[t, v]], points, tets, g, k, lam[v])
        w = scale * areas[t] / 12.0
        for i in range(4):
            si = lam[0, i] + lam[1, i] + lam[2, i]
            diag[dofs[k, i]] += w * (lam[0, i] * lam[0, i] + lam[1, i] * lam[1, i] + lam[2, i] * lam[2, i] + si * si)
        for e in range(6):
            i, j = _TET_EDGES[e, 0], _TET_EDGES[e, 1]
            si = lam[0, i] + lam[1, i] + lam[2, i]
            sj = lam[0, j] + lam[1, j] + lam[2, j]
            value = w * (lam[0, i] * lam[0, j] + lam[1, i] * lam[1, j] + lam[2, i] * lam[2, j] + si * sj)
            outside += _add_pair(ids, code, dofs[k, i], dofs[k, j], value, sums, partner)
    return outside


@njit(cache=True, error_model="numpy")
def _add_gram_row(ids, code, row_dofs, row_values, u, v, scale, sums, partner, diag):
    """Add scale c c^T for one row c (``row_values`` on ``row_dofs``), its repeated dofs merged first (a
    face row has 8 entries on 5 nodes: 10 pairs instead of 28), ``u``, ``v`` scratch of the row's
    length; returns the number of pairs outside the lattice offsets."""
    nu = 0
    for p in range(row_dofs.shape[0]):
        a = row_dofs[p]
        for q in range(nu + 1):
            if q == nu:
                u[nu] = a
                v[nu] = row_values[p]
                nu += 1
            elif u[q] == a:
                v[q] += row_values[p]
                break
    outside = 0
    for p in range(nu):
        a, vp = u[p], v[p]
        diag[a] += scale * (vp * vp)
        for q in range(p + 1, nu):
            outside += _add_pair(ids, code, a, u[q], scale * (vp * v[q]), sums, partner)
    return outside


@parallel_kernel
def lattice_add_rows(ids, code, dofs, values, scale, sums, partner, diag, bounds):
    """Add ``scale`` times the Gram matrix sum_r c_r c_r^T of rows c_r (``values`` (r, k) on ``dofs`` (r, k); a dof
    repeated in a row counts with the sum of its values) into the slots; returns the number of
    pairs outside the lattice offsets.  The rows in the chunks ``bounds`` of
    :func:`scatter_chunks`: the even chunks at once, then the odd ones."""
    outside = 0
    nch = bounds.shape[0] - 1
    for color in range(2):
        for h in prange((nch - color + 1) // 2):
            ch = 2 * h + color
            u = np.empty(dofs.shape[1], dtype=dofs.dtype)
            v = np.empty(dofs.shape[1])
            for r in range(bounds[ch], bounds[ch + 1]):
                outside += _add_gram_row(ids, code, dofs[r], values[r], u, v, scale, sums, partner, diag)
    return outside


@parallel_kernel
def lattice_add_face_jumps(ids, code, pairs, opposite, factors, volumes, dofs, table, types, scale, sums, partner, diag,
                           bounds):
    """Add ``scale`` times sum_F c_F c_F^T into the slots, c_F the jump row of the face F between the
    tets ``pairs[F]`` (K_a, K_b) (dofs ``dofs`` (m, 4), gradients ``table[types[K]]``):
    c_F = sqrt(w_F) (n . G_{K_a}, -n . G_{K_b}), n the unit normal out of K_a, w_F = |F| times
    ``factors[F]`` (or ``factors[0]`` for all faces when it has one entry), on the five nodes of the
    two tets: those of K_a, then the vertex ``opposite[F, 1]`` of K_b, each shared node with the sum
    of its two values (as :func:`lattice_add_rows` merges them).  n and |F| come from the vertex
    k = ``opposite[F, 0]`` of K_a: n = -g / |g| and |F| = 3 |K_a| |g|, g = grad lambda_k
    (|K| = |F| height / 3, |g| = 1 / height; volumes ``volumes``).

    One face at a time in scalars: no normals, areas or rows stored (the normals and areas alone
    took 32 bytes a face, 0.7 GB for the 22 million interior faces of the cut torus at spacing
    0.003125), and the five nodes known from the opposite vertices instead of merged by search:
    5.7 million faces at spacing 0.00625 in 0.78-0.81 s against 1.29-1.40 s for the generic rows of
    :func:`jump_rows` merged and added by :func:`lattice_add_rows`'s loop (the same sums, bitwise).
    Returns the number of pairs outside the lattice offsets.  The faces in the chunks ``bounds``
    of :func:`scatter_chunks`: the even chunks at once, then the odd ones."""
    outside = 0
    nch = bounds.shape[0] - 1
    for color in range(2):
        for h in prange((nch - color + 1) // 2):
            ch = 2 * h + color
            outside += _add_face_jumps(ids, code, pairs, opposite, factors, volumes, dofs, table, types, scale, sums,
                                       partner, diag, bounds[ch], bounds[ch + 1])
    return outside


@njit(cache=True, error_model="numpy")
def _add_face_jumps(ids, code, pairs, opposite, factors, volumes, dofs, table, types, scale, sums, partner, diag, start,
                    stop):
    u = np.empty(5, dtype=dofs.dtype)
    v = np.empty(5)
    one = factors.shape[0] == 1
    outside = 0
    for f in range(start, stop):
        ea, eb = pairs[f, 0], pairs[f, 1]
        oa, ob = opposite[f, 0], opposite[f, 1]
        ta, tb = types[ea], types[eb]
        nx, ny, nz, area = _face_normal_area(table, ta, oa, volumes[ea])
        w = np.sqrt(area * factors[0 if one else f])
        for i in range(4):
            u[i] = dofs[ea, i]
            v[i] = w * (table[ta, i, 0] * nx + table[ta, i, 1] * ny + table[ta, i, 2] * nz)
        for j in range(4):
            d = dofs[eb, j]
            vb = -w * (table[tb, j, 0] * nx + table[tb, j, 1] * ny + table[tb, j, 2] * nz)
            if j == ob:
                u[4], v[4] = d, vb
            else:
                for i in range(4):
                    if u[i] == d:
                        v[i] += vb
                        break
        for p in range(5):
            a, vp = u[p], v[p]
            diag[a] += scale * (vp * vp)
            for q in range(p + 1, 5):
                outside += _add_pair(ids, code, a, u[q], scale * (vp * v[q]), sums, partner)
    return outside


@parallel_kernel
def _chunk_spans(dofs, owners, bounds, lo, hi):
    """lo[ch], hi[ch]: the least and largest dof the elements of chunk ch read (``owners`` (E, r), or
    (0, 1) when element e reads row e of ``dofs``)."""
    own = owners.shape[0] > 0
    for ch in prange(bounds.shape[0] - 1):
        a, b = np.int64(2**62), np.int64(-1)
        for e in range(bounds[ch], bounds[ch + 1]):
            for o in range(owners.shape[1]):
                row = owners[e, o] if own else e
                for i in range(dofs.shape[1]):
                    d = np.int64(dofs[row, i])
                    a = min(a, d)
                    b = max(b, d)
        lo[ch], hi[ch] = a, b


def scatter_chunks(dofs, owners, counts=SWEEP_CHUNKS):
    """Chunk bounds (k + 1,) of the elements of a lattice sum (:func:`lattice_add_elements`,
    :func:`lattice_add_pieces`, :func:`lattice_add_rows`, :func:`lattice_add_face_jumps`): element e
    adds into the nodes ``dofs[owners[e]]`` (``owners`` (E, r): the rows of ``dofs`` that element e
    reads, e.g. its tet, the two tets of a face, or its own row of Gram dofs).  The first k of
    ``counts`` for which k contiguous chunks of about equal elements give chunks of one parity
    disjoint ranges of nodes (so the even chunks can add at the same time, then the odd ones);
    [0, E] when none does.  Elements listed along the lattice pass: the whole tets of a side, the
    interior faces of a cut, and the cut's tets and the triangles of S_h, since the band search
    returns its cells in id order (in the order of its blocks, the cut's chunks spanned most node
    numbers and got one chunk: the piece mass and the cut rows ran on one core).
    The chunk order changes the order of the sums at nodes shared by two chunks: the same bits on
    any number of threads, not those of one pass in element order.  ``owners`` None: element e reads
    row e (no (E, 1) array of 0..E-1: 0.24 s for the 29 million tets of a side at spacing 0.01)."""
    if owners is None:  # the empty placeholder has the type the callers' owners have at this size: one signature
        owners, E = np.zeros((0, 1), index_dtype(len(dofs))), len(dofs)
    else:
        owners = np.ascontiguousarray(owners).reshape(len(owners), -1)
        E = owners.shape[0]
    for k in counts:
        if k < 2 or k % 2 or E < 64 * k:
            continue
        bounds = (np.arange(k + 1, dtype=np.int64) * E) // k
        lo, hi = np.empty(k, dtype=np.int64), np.empty(k, dtype=np.int64)
        _chunk_spans(dofs, owners, bounds, lo, hi)
        ok = True
        for parity in (0, 1):
            order = np.argsort(lo[parity::2])
            a, b = lo[parity::2][order], hi[parity::2][order]
            ok &= bool(np.all(a[1:] > b[:-1]))
        if ok:
            return bounds
    return np.array([0, E], dtype=np.int64)


@parallel_kernel
def _incoming_offsets(sums, partner, bounds, parity, incoming):
    """incoming[b] |= 1 << c for every nonzero slot (a, c) of the rows a of the chunks of ``bounds``
    with the given ``parity`` (their targets b lie in their own chunk or the next)."""
    S = 13
    for k in prange((bounds.shape[0] - parity) // 2):
        ch = 2 * k + parity
        for a in range(bounds[ch], bounds[ch + 1]):
            for c in range(S):
                if sums[a * S + c] != 0.0:
                    b = partner[a * S + c]
                    incoming[b] |= np.uint16(1 << c)


@parallel_kernel
def _lattice_fill(sums, partner, diag, incoming, indptr, indices, data):
    """Row a of the CSR arrays of :func:`lattice_csr` (diagonal and upper slots) and the mirrors of
    its slots, each at its own position: in row b the mirror of slot (a, c) comes after those of
    the slots with a larger offset rank c' (a smaller a'), the bits of ``incoming[b]`` above c."""
    n = diag.shape[0]
    S = 13
    for a in prange(n):
        pos = indptr[a] + _popcount(np.uint64(incoming[a]))
        indices[pos] = a
        data[pos] = diag[a]
        pos += 1
        for c in range(S):
            v = sums[a * S + c]
            if v != 0.0:
                b = partner[a * S + c]
                indices[pos] = b
                data[pos] = v
                pos += 1
                m = indptr[b] + _popcount(np.uint64(incoming[b]) >> np.uint64(c + 1))
                indices[m] = a
                data[m] = v


def lattice_csr(sums, partner, diag, indptr, indices, data):
    """The CSR arrays of the symmetric matrix held by the slots (``indptr`` (n + 1,) filled here,
    ``indices`` and ``data`` of length ``indptr[n]``, see :func:`lattice_nnz`): in row a the
    mirrors (a, c) of the slots (c, a), c < a, in increasing c, the diagonal, then the slots of a
    in increasing partner.  Slots whose sum is exactly zero are left out.

    On the available cores: a 13-bit mask per row of the slots that point at it (by chunks of rows
    whose targets stay in the chunk or the next, even chunks at once, then odd; else one chunk),
    the row pointers from the masks' bit counts, then every row and the mirrors of its slots,
    each entry at a position fixed by the masks: the same arrays as one pass in row order, which
    took 1.2 s at spacing 0.003125 (4.7 million rows)."""
    n = diag.shape[0]
    incoming = np.zeros(n, dtype=np.uint16)
    bounds = np.array([0, n], dtype=np.int64)
    for k in SWEEP_CHUNKS:
        if n < 64 * k:
            break
        cand = (np.arange(k + 1, dtype=np.int64) * n) // k
        last = _chunk_reach(partner, sums, cand)
        if np.all(last[:-2] < cand[2:-1]):  # targets of chunk i stay below chunk i + 2
            bounds = cand
            break
    for parity in (0, 1):
        _incoming_offsets(sums, partner, bounds, parity, incoming)
    indptr[0] = 0
    np.cumsum(_row_lengths(sums, incoming), out=indptr[1:])
    _lattice_fill(sums, partner, diag, incoming, indptr, indices, data)


@parallel_kernel
def _chunk_reach(partner, sums, bounds):
    """The largest target of a nonzero slot of each chunk of rows (its first row if none)."""
    S = 13
    out = np.empty(bounds.shape[0] - 1, dtype=np.int64)
    for ch in prange(bounds.shape[0] - 1):
        top = bounds[ch]
        for a in range(bounds[ch], bounds[ch + 1]):
            for c in range(S):
                if sums[a * S + c] != 0.0 and partner[a * S + c] > top:
                    top = partner[a * S + c]
        out[ch] = top
    return out


@parallel_kernel
def _row_lengths(sums, incoming):
    """Entries of each row of :func:`lattice_csr`: the mirrors (bits of ``incoming``), the
    diagonal and the nonzero slots."""
    S = 13
    out = np.empty(incoming.shape[0], dtype=np.int64)
    for b in prange(incoming.shape[0]):
        k = _popcount(np.uint64(incoming[b])) + 1
        for c in range(S):
            if sums[b * S + c] != 0.0:
                k += 1
        out[b] = k
    return out


@njit(cache=True, error_model="numpy")
def lattice_nnz(sums, n):
    """Stored entries of the matrix of :func:`lattice_csr`: n + 2 (nonzero slots)."""
    nz = 0
    for s in range(sums.shape[0]):
        if sums[s] != 0.0:
            nz += 1
    return n + 2 * nz


@parallel_kernel
def triangle_points(points, triangles, bary, x, area):
    """The quadrature points x (b, q, 3) = sum_v bary[q, v] x_v and the areas ``area`` (b,) of the
    triangles ``triangles`` (b, 3) into ``points``."""
    for t in prange(triangles.shape[0]):
        p0, p1, p2 = points[triangles[t, 0]], points[triangles[t, 1]], points[triangles[t, 2]]
        for i in range(bary.shape[0]):
            for d in range(3):
                x[t, i, d] = bary[i, 0] * p0[d] + bary[i, 1] * p1[d] + bary[i, 2] * p2[d]
        area[t] = _area(p0, p1, p2)


@njit(cache=True, error_model="numpy", inline="always")
def _area(p0, p1, p2):
    """|(p1 - p0) x (p2 - p0)| / 2."""
    e0, e1, e2 = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
    f0, f1, f2 = p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]
    c0, c1, c2 = e1 * f2 - e2 * f1, e2 * f0 - e0 * f2, e0 * f1 - e1 * f0
    return 0.5 * np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)


@njit(cache=True, error_model="numpy")
def _triangle_areas(points, triangles, area):
    for t in range(triangles.shape[0]):
        area[t] = _area(points[triangles[t, 0]], points[triangles[t, 1]], points[triangles[t, 2]])


def triangle_areas(points, triangles):
    """(m,) |T| = |(x_1 - x_0) x (x_2 - x_0)| / 2 of the triangles (m, 3) of ``points`` (p, 3)."""
    points = np.ascontiguousarray(points, dtype=float)
    triangles = np.ascontiguousarray(triangles)
    area = np.empty(len(triangles))
    _triangle_areas(points, triangles, area)
    return area


@parallel_kernel
def squared_error(values, triangles, bary, weights, area, exact):
    """sum_T |T| sum_q w_q |u^e(x_q) - u_h(x_q)|^2 over the triangles (b, 3), u_h linear on each with
    ``values`` (V, c) at the vertices, u_h(x_q) = sum_v bary[q, v] u_v; ``exact`` (b, q, c), or an
    empty array for u^e = 0 (the norm of u_h itself).  Summed per block of :data:`SUM_BLOCK`
    triangles, the blocks in order (the same bits on any number of threads)."""
    c = values.shape[1]
    n = triangles.shape[0]
    with_exact = exact.shape[0] > 0
    nblocks = (n + SUM_BLOCK - 1) // SUM_BLOCK
    part = np.zeros((nblocks, 1))
    for b in prange(nblocks):
        for t in range(b * SUM_BLOCK, min((b + 1) * SUM_BLOCK, n)):
            v0, v1, v2 = values[triangles[t, 0]], values[triangles[t, 1]], values[triangles[t, 2]]
            s = 0.0
            for i in range(bary.shape[0]):
                for l in range(c):
                    d = (exact[t, i, l] if with_exact else 0.0) - (bary[i, 0] * v0[l] + bary[i, 1] * v1[l] + bary[i, 2] * v2[l])
                    s += weights[i] * d * d
            part[b, 0] += area[t] * s
    total = np.zeros(1)
    _add_blocks(part, total)
    return total[0]


@njit(cache=True, error_model="numpy")
def scatter_add(dofs, local, out):
    """out[dofs[e, a], l] += local[e, a, l] for the elements e (m, k), in element order."""
    for e in range(dofs.shape[0]):
        for a in range(dofs.shape[1]):
            i = dofs[e, a]
            for l in range(out.shape[1]):
                out[i, l] += local[e, a, l]


RADIX_BITS = 8
"""Bits of the digit of each pass of :func:`radix_argsort`: 256 buckets, so the scattered writes of
a pass go to few enough places to stay in cache (8 bits sorted 1.77 million 37-bit keys in 87-94 ms,
10 bits in 118 ms, 11 bits in 131 ms on the 2-core machine)."""


@njit(cache=True, error_model="numpy")
def radix_argsort(keys, bits, order):
    """The stable sorting order of the non-negative int64 ``keys`` (n,) below 2**bits, by LSD radix
    passes of :data:`RADIX_BITS` bits (a counting sort each, stable; the digit counts of all the
    passes from one read of the keys, and a pass whose digit is the same for every key skipped);
    ``order`` (n,) int64 is overwritten with the result.  O(n) a pass: no comparisons."""
    n = keys.shape[0]
    nb = 1 << RADIX_BITS
    mask = np.int64(nb - 1)
    passes = max((bits + RADIX_BITS - 1) // RADIX_BITS, 1)
    count = np.zeros((passes, nb), dtype=np.int64)
    for i in range(n):
        x = keys[i]
        for q in range(passes):
            count[q, (x >> (q * RADIX_BITS)) & mask] += 1
    k, k2 = keys, np.empty(n, dtype=np.int64)
    idx, idx2 = np.arange(n), np.empty(n, dtype=np.int64)
    first = True
    for q in range(passes):
        c = count[q]
        constant = False
        for b in range(nb):
            if c[b] == n:
                constant = True
        if constant:
            continue
        total = 0
        for b in range(nb):  # exclusive prefix sums: the first slot of each digit
            t = c[b]
            c[b] = total
            total += t
        shift = q * RADIX_BITS
        for i in range(n):
            d = (k[i] >> shift) & mask
            p = c[d]
            c[d] = p + 1
            k2[p] = k[i]
            idx2[p] = idx[i]
        if first:  # the input keys are never written
            k, k2 = k2, np.empty(n, dtype=np.int64)
            first = False
        else:
            k, k2 = k2, k
        idx, idx2 = idx2, idx
    order[:] = idx


@parallel_kernel
def kuhn_tet_nodes(tet_ids, cells_x, cells_y, nodes_x, nodes_y, offsets, out):
    """out[t] = the node ids of the Kuhn tet ``tet_ids[t]`` of a structured box: cell c = id // 6
    with indices (i, j, k) on a grid of ``cells_x`` x ``cells_y`` cells, lowest corner node id
    i + nodes_x (j + nodes_y k), plus the row id % 6 of the node offsets ``offsets`` (6, 4)."""
    for t in prange(tet_ids.shape[0]):
        c = tet_ids[t] // 6
        l = tet_ids[t] - 6 * c
        i = c % cells_x
        r = c // cells_x
        j = r % cells_y
        k = r // cells_y
        base = i + nodes_x * (j + nodes_y * k)
        for v in range(4):
            out[t, v] = base + offsets[l, v]


@parallel_kernel
def signed_volumes(v, out):
    """out[e] = (x_1 - x_0) x (x_2 - x_0) . (x_3 - x_0) / 6 for the tets ``v`` (m, 4, 3), in the
    order of :func:`cutfem.quadrature.signed_volumes`' terms (the same bits)."""
    for e in prange(v.shape[0]):
        a0, a1, a2 = v[e, 1, 0] - v[e, 0, 0], v[e, 1, 1] - v[e, 0, 1], v[e, 1, 2] - v[e, 0, 2]
        b0, b1, b2 = v[e, 2, 0] - v[e, 0, 0], v[e, 2, 1] - v[e, 0, 1], v[e, 2, 2] - v[e, 0, 2]
        c0, c1, c2 = v[e, 3, 0] - v[e, 0, 0], v[e, 3, 1] - v[e, 0, 1], v[e, 3, 2] - v[e, 0, 2]
        out[e] = (a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2) + a2 * (b0 * c1 - b1 * c0)) / 6.0


@parallel_kernel
def box_node_coordinates(ids, nodes_x, nodes_y, lower, spacing, out):
    """out[t] = lower + (i, j, k) spacing for the node id ``ids[t]`` = i + nodes_x (j + nodes_y k) of
    a structured box (componentwise; the bits of numpy's ``lower + ijk * spacing``)."""
    for t in prange(ids.shape[0]):
        n = ids[t]
        r = n // nodes_x
        k = r // nodes_y
        out[t, 0] = lower[0] + np.float64(n - nodes_x * r) * spacing[0]
        out[t, 1] = lower[1] + np.float64(r - nodes_y * k) * spacing[1]
        out[t, 2] = lower[2] + np.float64(k) * spacing[2]


@parallel_kernel
def box_cell_corner_ids(cell_ids, cells_x, cells_y, nodes_x, nodes_y, offsets, out):
    """out[t, b] = the node id of corner b of the cell ``cell_ids[t]`` = i + cells_x (j + cells_y k)
    of a structured box: i + nodes_x (j + nodes_y k) + ``offsets[b]`` (the corners' id offsets)."""
    for t in prange(cell_ids.shape[0]):
        c = cell_ids[t]
        r = c // cells_x
        k = r // cells_y
        base = (c - cells_x * r) + nodes_x * ((r - cells_y * k) + nodes_y * k)
        for b in range(offsets.shape[0]):
            out[t, b] = base + offsets[b]


@njit(cache=True, error_model="numpy")
def box_ids_on_faces(ids, nodes_x, nodes_y, nodes_z):
    """Whether any node id ``ids[t]`` = i + nodes_x (j + nodes_y k) of a structured box lies on one
    of its faces (i, j or k first or last); stops at the first."""
    for t in range(ids.shape[0]):
        n = ids[t]
        r = n // nodes_x
        k = r // nodes_y
        i, j = n - nodes_x * r, r - nodes_y * k
        if i == 0 or i == nodes_x - 1 or j == 0 or j == nodes_y - 1 or k == 0 or k == nodes_z - 1:
            return True
    return False


@parallel_kernel
def _kuhn_types(tet_ids, out):
    for t in prange(tet_ids.shape[0]):
        out[t] = tet_ids[t] % 6


def kuhn_types(tet_ids):
    """(m,) int8: the Kuhn type (tet id % 6) of tets of a structured box, in one pass on all cores
    (numpy's remainder and cast: 64 ms for 13.7 million tets)."""
    tet_ids = np.ascontiguousarray(tet_ids, dtype=np.int64)
    out = np.empty(len(tet_ids), dtype=np.int8)
    _kuhn_types(tet_ids, out)
    return out


@njit(cache=True, error_model="numpy")
def side_split(tets, values, neg, whole, partial, counts):
    """Split the tets (m, 4) by the sign of the nodal ``values`` on one side (``neg``: phi < 0, else
    phi > 0): writes the tets wholly on the side (NEG: all values < 0; POS: all >= 0) into ``whole``
    and those with 1-3 nodes on it (and not whole) into ``partial``, with those counts into
    ``counts``, both in increasing order; returns (number whole, number partial)."""
    nw = 0
    npart = 0
    for e in range(tets.shape[0]):
        k = 0
        ge = 0
        for v in range(4):
            x = values[tets[e, v]]
            if (x < 0.0) if neg else (x > 0.0):
                k += 1
            if x >= 0.0:
                ge += 1
        if k == 4 or (not neg and ge == 4):
            whole[nw] = e
            nw += 1
        elif k > 0:
            partial[npart] = e
            counts[npart] = k
            npart += 1
    return nw, npart


@njit(cache=True, error_model="numpy", inline="always")
def _cut_point(x, w, i, j, out, row):
    t = w[i] / (w[i] - w[j])
    for d in range(3):
        out[row, d] = x[i, d] + t * (x[j, d] - x[i, d])


@parallel_kernel
def side_pieces(points, tets, values, neg, partial, counts, rank, base, sizes, sub, parent):
    """The sub-tetrahedra of :func:`cutfem.markers.side_subtetrahedra` (which states them) for the
    ``partial`` tets with ``counts`` nodes on the side: tet q of the group of count c, of rank
    ``rank[q]`` in it, writes its sub-tet s at ``base[c] + s sizes[c] + rank[q]`` of ``sub`` (s, 4, 3)
    and ``parent``, the order of the numpy expression (a group at a time, sub-tet by sub-tet), the
    same points operation for operation."""
    for q in prange(partial.shape[0]):
        e = partial[q]
        c = counts[q]
        x = np.empty((4, 3))
        w = np.empty(4)
        n = 0
        for pas in range(2):  # the side's nodes first, each part in the tet's order
            for v in range(4):
                val = values[tets[e, v]]
                on = (val < 0.0) if neg else (val > 0.0)
                if on == (pas == 0):
                    for d in range(3):
                        x[n, d] = points[tets[e, v], d]
                    w[n] = val
                    n += 1
        pts = np.empty((6, 3))  # the prism a, b, c, a2, b2, c2 (or the one tet in its first four)
        if c == 1:
            pts[0] = x[0]
            _cut_point(x, w, 0, 1, pts, 1)
            _cut_point(x, w, 0, 2, pts, 2)
            _cut_point(x, w, 0, 3, pts, 3)
            nsub = 1
        elif c == 2:
            pts[0] = x[0]
            _cut_point(x, w, 0, 2, pts, 1)
            _cut_point(x, w, 0, 3, pts, 2)
            pts[3] = x[1]
            _cut_point(x, w, 1, 2, pts, 4)
            _cut_point(x, w, 1, 3, pts, 5)
            nsub = 3
        else:
            pts[0], pts[1], pts[2] = x[0], x[1], x[2]
            _cut_point(x, w, 0, 3, pts, 3)
            _cut_point(x, w, 1, 3, pts, 4)
            _cut_point(x, w, 2, 3, pts, 5)
            nsub = 3
        for s in range(nsub):
            row = base[c] + s * sizes[c] + rank[q]
            parent[row] = e
            for v in range(4):
                src = v + s  # the prism's tets: (a, b, c, a2), (b, c, a2, b2), (c, a2, b2, c2)
                for d in range(3):
                    sub[row, v, d] = pts[src, d]


@parallel_kernel
def tets_near(tets, marked, n_nodes, out):
    """out[t] = whether tet t shares a node with a tet of ``marked`` (m,) (itself included): the
    marked tets' nodes flagged in one pass (the marked tets are few: a serial pass), then every tet
    tested on all cores.  ``tets`` (m, 4) node numbers below ``n_nodes``."""
    near = np.zeros(n_nodes, np.bool_)
    for t in range(tets.shape[0]):
        if marked[t]:
            for k in range(4):
                near[tets[t, k]] = True
    for t in prange(tets.shape[0]):
        out[t] = near[tets[t, 0]] or near[tets[t, 1]] or near[tets[t, 2]] or near[tets[t, 3]]


@parallel_kernel
def longest_edges(points, simplices, out):
    """out[e] = the longest edge of simplex e, the nodes ``simplices`` (m, k) of ``points`` (N, 3),
    k = 3 or 4 (:func:`cutfem.markers.longest_edges`): the coordinates gathered in the same pass,
    each edge's length as numpy's norm computes it."""
    k = simplices.shape[1]
    for e in prange(simplices.shape[0]):
        top = 0.0
        for a in range(k):
            for b in range(a + 1, k):
                p, q = simplices[e, a], simplices[e, b]
                d0 = points[q, 0] - points[p, 0]
                d1 = points[q, 1] - points[p, 1]
                d2 = points[q, 2] - points[p, 2]
                top = max(top, np.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
        out[e] = top


@parallel_kernel
def rule_points(bary, nodes, simplices, out):
    """out[e, i] = sum_v bary[i, v] x_ev, the points of a reference rule (q, k) on b simplices: x_ev
    = nodes[simplices[e, v]] (node coordinates (N, 3) and node numbers (b, k), gathered in the same
    pass), or x_ev = nodes[k e + v] when ``simplices`` is empty (the vertices (b, k, 3) as (b k, 3)).
    The vertices of a simplex (k = 2, 3 or 4) are held in scalars and the sums over v unrolled
    (the same sums in the same order): 1.24 against 1.62 ns a point on both cores with the
    14-point rule on the tets of a structured box."""
    q, k = bary.shape
    gather = simplices.shape[0] > 0
    m = out.shape[0]
    for e in prange(m):
        x = np.zeros((4, 3))  # hoisted out of the point loop; the unused rows stay zero
        for v in range(k):
            n = simplices[e, v] if gather else k * e + v
            x[v, 0], x[v, 1], x[v, 2] = nodes[n, 0], nodes[n, 1], nodes[n, 2]
        x0, y0, z0, x1, y1, z1 = x[0, 0], x[0, 1], x[0, 2], x[1, 0], x[1, 1], x[1, 2]
        x2, y2, z2, x3, y3, z3 = x[2, 0], x[2, 1], x[2, 2], x[3, 0], x[3, 1], x[3, 2]
        for i in range(q):
            b0, b1 = bary[i, 0], bary[i, 1]
            p0, p1, p2 = b0 * x0 + b1 * x1, b0 * y0 + b1 * y1, b0 * z0 + b1 * z1
            if k > 2:
                b2 = bary[i, 2]
                p0, p1, p2 = p0 + b2 * x2, p1 + b2 * y2, p2 + b2 * z2
            if k > 3:
                b3 = bary[i, 3]
                p0, p1, p2 = p0 + b3 * x3, p1 + b3 * y3, p2 + b3 * z3
            out[e, i, 0], out[e, i, 1], out[e, i, 2] = p0, p1, p2


@parallel_kernel
def rule_weights(sizes, w, out):
    """out[e, i] = sizes[e] w[i]: a reference rule's weights (q,) scaled by the cells' measures (m,)
    (numpy's broadcast product of (m, 1) and (1, q) runs an inner loop of q per row: 0.57 against
    0.07 ms for 65536 cells and q = 4)."""
    for e in prange(out.shape[0]):
        s = sizes[e]
        for i in range(out.shape[1]):
            out[e, i] = s * w[i]


@parallel_kernel
def barycentric_values(points, origin, grads, out):
    """out[e, i, a] = delta_a0 + grads[e, a] . (points[e, i] - origin[e]): the P1 basis values at
    ``points`` (m, q, 3) of elements with first vertex ``origin`` (m, 3) and basis gradients
    ``grads`` (m, k, 3)."""
    for e in prange(points.shape[0]):
        o0, o1, o2 = origin[e, 0], origin[e, 1], origin[e, 2]
        for i in range(points.shape[1]):
            y0, y1, y2 = points[e, i, 0] - o0, points[e, i, 1] - o1, points[e, i, 2] - o2
            for a in range(grads.shape[1]):
                out[e, i, a] = grads[e, a, 0] * y0 + grads[e, a, 1] * y1 + grads[e, a, 2] * y2
            out[e, i, 0] += 1.0


@parallel_kernel
def cell_value_error(phi, local, exact, weights):
    """sum_K sum_q w_Kq |u^e(x_Kq) - u_h(x_Kq)|^2 over the cells K of a block, u_h(x_Kq) =
    sum_a phi[K, q, a] local[K, a, :]: basis values ``phi`` (b, q, k), or (1, q, k) when every
    cell shares them (whole cells: the rule's barycentric coordinates), the cells' coefficients
    ``local`` (b, k, c), ``exact`` (b, q, c), ``weights`` (b, q).  The sums run per point q across
    the cells of each block of :data:`SUM_BLOCK` (independent accumulators, so the loops pipeline),
    the blocks on all cores and added in order at the end."""
    b, nq = weights.shape
    k, c = local.shape[1], local.shape[2]
    shared = phi.shape[0] == 1
    nblocks = (b + SUM_BLOCK - 1) // SUM_BLOCK
    acc = np.zeros((nblocks, nq))
    for blk in prange(nblocks):
        uh = np.empty(nq)
        for e in range(blk * SUM_BLOCK, min((blk + 1) * SUM_BLOCK, b)):
            p = phi[0] if shared else phi[e]
            for l in range(c):
                uh[:] = 0.0
                for a in range(k):
                    la = local[e, a, l]
                    for i in range(nq):
                        uh[i] += p[i, a] * la
                for i in range(nq):
                    d = exact[e, i, l] - uh[i]
                    acc[blk, i] += weights[e, i] * (d * d)
    total = np.zeros(nq)
    _add_blocks(acc, total)
    return total.sum()


@parallel_kernel
def cell_gradient_error(table, types, local, exact, weights, normals):
    """sum_K sum_q w_Kq |P (grad u^e(x_Kq) - grad u_h|_K)|^2 over the cells K of a block, grad u_h
    = sum_a local[K, a] G_K[a] constant on K (gradients G_K = ``table[types[K]]`` (k, 3), read in
    place: a gathered (b, k, 3) copy took a third of this sum's time; ``local`` (b, k)),
    ``exact`` (b, q, 3), ``weights`` (b, q); P = I - n n^T with the cells' unit ``normals`` (b, 3)
    on a surface, P = I when ``normals`` is empty.  Summed per point q as :func:`cell_value_error`."""
    b, nq = weights.shape
    surface = normals.shape[0] > 0
    nblocks = (b + SUM_BLOCK - 1) // SUM_BLOCK
    acc = np.zeros((nblocks, nq))
    for blk in prange(nblocks):
        for e in range(blk * SUM_BLOCK, min((blk + 1) * SUM_BLOCK, b)):
            G = table[types[e]]
            g0 = g1 = g2 = 0.0
            for a in range(G.shape[0]):
                g0 += local[e, a] * G[a, 0]
                g1 += local[e, a] * G[a, 1]
                g2 += local[e, a] * G[a, 2]
            if surface:
                n0, n1, n2 = normals[e, 0], normals[e, 1], normals[e, 2]
                for i in range(nq):
                    d0, d1, d2 = exact[e, i, 0] - g0, exact[e, i, 1] - g1, exact[e, i, 2] - g2
                    dn = d0 * n0 + d1 * n1 + d2 * n2
                    d0, d1, d2 = d0 - dn * n0, d1 - dn * n1, d2 - dn * n2
                    acc[blk, i] += weights[e, i] * (d0 * d0 + d1 * d1 + d2 * d2)
            else:
                for i in range(nq):
                    d0, d1, d2 = exact[e, i, 0] - g0, exact[e, i, 1] - g1, exact[e, i, 2] - g2
                    acc[blk, i] += weights[e, i] * (d0 * d0 + d1 * d1 + d2 * d2)
    total = np.zeros(nq)
    _add_blocks(acc, total)
    return total.sum()


@njit(cache=True, error_model="numpy")
def tangential_gradient_sums(dofs, table, types, normals, weights, out):
    """out[dofs[K, i]] += weights[K] (I - n_K n_K^T) grad lambda_i for the elements K: ``dofs`` (m, 4),
    gradients ``table[types[K]]``, unit ``normals`` (m, 3), ``out`` (n, 3)."""
    for t in range(dofs.shape[0]):
        g = table[types[t]]
        n0, n1, n2 = normals[t, 0], normals[t, 1], normals[t, 2]
        w = weights[t]
        for i in range(4):
            gn = g[i, 0] * n0 + g[i, 1] * n1 + g[i, 2] * n2
            a = dofs[t, i]
            out[a, 0] += w * (g[i, 0] - gn * n0)
            out[a, 1] += w * (g[i, 1] - gn * n1)
            out[a, 2] += w * (g[i, 2] - gn * n2)


@parallel_kernel
def torus_value(x, center, R, r, out):
    """out[i] = hypot(y_2, hypot(y_0, y_1) - R) - r, y = x[i] - center: the torus level set
    (:meth:`cutfem.levelset.Torus.value`) for points ``x`` (n, 3), by libm's ``hypot`` as numpy
    calls it, so the same bits (tested).  Returns whether every coordinate is finite (the caller
    reports the bad points otherwise).  0.08 s for 5 million points against 0.20-0.25 s in numpy."""
    ok = 0.0  # v - v is 0 for a finite v and NaN otherwise
    for i in prange(x.shape[0]):
        y0, y1, y2 = x[i, 0] - center[0], x[i, 1] - center[1], x[i, 2] - center[2]
        ok += (y0 - y0) + (y1 - y1) + (y2 - y2)
        out[i] = math.hypot(y2, math.hypot(y0, y1) - R) - r
    return ok == 0.0


@parallel_kernel
def torus_mean_curvature_vector(x, center, R, r, out):
    """out[i] = kappa / d ((1 - R/s) y_0, (1 - R/s) y_1, y_2), y = x[i] - center, s = |(y_0, y_1)|,
    d = |(s - R, y_2)|, kappa = (R + 2 r cos p) / (r (R + r cos p)), cos p = (s - R) / d: the
    mean curvature vector of the torus at the closest point (the lean form of
    :meth:`cutfem.levelset.Torus.exact_mean_curvature_vector`, operation for operation), for
    points ``x`` (n, 3).  Returns whether every value is finite (the caller falls back to the
    careful evaluation otherwise).

    In blocks of 512 points copied to three coordinate arrays, so that the square roots and
    divisions run on SIMD lanes: 4.1 ns a point against 9.4 ns for the same loop reading the
    (n, 3) rows and 12-13 ns for the numpy expression (its dozen passes)."""
    c0, c1, c2 = center[0], center[1], center[2]
    two_r = 2.0 * r
    B = 512
    check = 0.0  # v - v is 0 for a finite v and NaN otherwise (in any order of the sum)
    n = x.shape[0]
    for blk in prange((n + B - 1) // B):
        start = blk * B
        m = min(B, n - start)
        y0, y1, y2 = np.empty(B), np.empty(B), np.empty(B)
        for j in range(m):
            y0[j] = x[start + j, 0] - c0
            y1[j] = x[start + j, 1] - c1
            y2[j] = x[start + j, 2] - c2
        for j in range(m):
            a, b, c = y0[j], y1[j], y2[j]
            s = np.sqrt(a * a + b * b)
            s_minus_R = s - R
            d = np.sqrt(s_minus_R * s_minus_R + c * c)
            cos_p = s_minus_R / d
            scale = (R + two_r * cos_p) / (r * d * (R + r * cos_p))
            y2[j] = scale * c
            scale *= s_minus_R / s
            y0[j] = scale * a
            y1[j] = scale * b
        for j in range(m):
            out[start + j, 0] = y0[j]
            out[start + j, 1] = y1[j]
            out[start + j, 2] = y2[j]
            check += (y0[j] - y0[j]) + (y1[j] - y1[j]) + (y2[j] - y2[j])
    return check == 0.0


@parallel_kernel
def level_set_normals(values, table, types, out):
    """out[t] = g / |g|, g = sum_k values[t, k] grad lambda_k with the gradients ``table[types[t]]``
    (4, 3): the unit normals n_h of the zero level set of the P1 interpolant in each tet.  Where
    |g|^2 overflows or underflows (a level set of values near 1e300 or 1e-300), g is first divided
    by its largest component; elsewhere the plain formula (the same bits as before).  A tet with
    g = 0, or g not finite, gets NaN (the caller checks)."""
    for t in prange(values.shape[0]):
        G = table[types[t]]
        g0 = g1 = g2 = 0.0
        for k in range(4):
            v = values[t, k]
            g0 += v * G[k, 0]
            g1 += v * G[k, 1]
            g2 += v * G[k, 2]
        square = g0 * g0 + g1 * g1 + g2 * g2
        if not (1e-290 < square < 1e300):
            a = max(abs(g0), abs(g1), abs(g2))
            if 0.0 < a < np.inf:
                g0, g1, g2 = g0 / a, g1 / a, g2 / a
                square = g0 * g0 + g1 * g1 + g2 * g2
        norm = np.sqrt(square)
        out[t, 0] = g0 / norm
        out[t, 1] = g1 / norm
        out[t, 2] = g2 / norm


@njit(cache=True, error_model="numpy")
def _marching(tet_ids, labels, vals, edge_i_table, edge_j_table, code):
    n = 0
    for t in range(vals.shape[0]):
        c = 0
        for k in range(4):
            if vals[t, k] < 0:
                c |= 1 << k
        keep = True
        for s in range(4):
            if vals[t, edge_j_table[c, s]] == 0.0:
                keep = _distinct_slots(vals, t, c, edge_i_table, edge_j_table) >= 3
                break
        if keep:
            if n != t:
                tet_ids[n] = tet_ids[t]
                for k in range(4):
                    labels[n, k] = labels[t, k]
                    vals[n, k] = vals[t, k]
            code[n] = c
            n += 1
    return n


@njit(cache=True, error_model="numpy")
def _distinct_slots(vals, t, c, edge_i_table, edge_j_table):
    """How many distinct vertices the four slots of tet t (sign code c) have: a slot is the node j
    when phi_j == 0, else its edge (i, j)."""
    k4 = np.empty(4, dtype=np.int64)
    distinct = 0
    for s in range(4):
        i, j = edge_i_table[c, s], edge_j_table[c, s]
        k4[s] = j if vals[t, j] == 0.0 else 4 + 4 * i + j
        new = True
        for r in range(s):
            if k4[s] == k4[r]:
                new = False
        if new:
            distinct += 1
    return distinct


def marching(tet_ids, labels, vals, edge_i_table, edge_j_table):
    """Marching tetrahedra on the candidate tets ``tet_ids`` (m,) with node labels ``labels``
    (m, 4) and nodal values ``vals`` (m, 4): the sign code of each tet (bit k: vals[k] < 0), and
    the tets whose piece has fewer than three distinct vertices dropped.  The polygon slots of the
    sign code are the edges (i, j) of the case tables; a slot is the node j when phi_j == 0, else
    its edge (see :func:`cutfem.cut._marching`).

    The three arrays are compacted **in place**; returns ``(n, code)``: the kept tets are their
    first n rows, ``code`` (n,) uint8 their sign codes."""
    code = np.empty(len(vals), dtype=np.uint8)
    n = _marching(tet_ids, labels, vals, np.ascontiguousarray(edge_i_table), np.ascontiguousarray(edge_j_table), code)
    return n, code[:n]


@parallel_kernel
def _slot_keys(tets, types, code, vals, edge_i_table, edge_j_table, edge_codes, p, lattice, key):
    for t in prange(tets.shape[0]):
        c = code[t]
        for s in range(4):
            i, j = edge_i_table[c, s], edge_j_table[c, s]
            a, b = tets[t, i], tets[t, j]
            lo, hi = min(a, b), max(a, b)
            if vals[t, j] == 0.0:
                key[t, s] = b
            elif lattice:
                key[t, s] = p - 1 + 7 * lo + edge_codes[types[t], i, j]
            else:
                key[t, s] = p + lo * p + hi


def slot_keys(tets, code, vals, edge_i_table, edge_j_table, p, lattice=None):
    """(m, 4) int64 keys of the polygon slots of the pieces: the active node j (``< p``) for a slot
    at a node (phi_j == 0), else a key of its edge {a, b} = the active nodes of (i, j), lo = min:
    ``p + lo p + hi`` in general, or with ``lattice = (edge_codes (6, 4, 4), types (m,))`` on a
    structured box ``p - 1 + 7 lo + c(S)``, c(S) in 1..7 the lattice code of the edge
    (:data:`~cutfem.mesh.KUHN_EDGE_CODES` of the Kuhn type), keys below 8p when the active nodes
    increase with the background ids."""
    m = len(tets)
    key = np.empty((m, 4), dtype=np.int64)
    if lattice is None:
        edge_codes, types, flag = np.zeros((1, 4, 4), dtype=np.int8), np.zeros(m, dtype=np.int8), False
    else:
        (edge_codes, types), flag = lattice, True
    _slot_keys(tets, types, code, vals, edge_i_table, edge_j_table, np.ascontiguousarray(edge_codes), np.int64(p), flag, key)
    return key


@njit(cache=True, error_model="numpy")
def _surface(vinv, tets, code, vals, points, edge_i_table, edge_j_table, nvert, flip, negative, tri_slots,
             vertices, tri, tri_tet, fill):
    seen = np.zeros(vertices.shape[0], dtype=np.bool_)
    n = 0
    for t in range(vinv.shape[0]):
        c = code[t]
        if fill:
            for s in range(4):
                v = vinv[t, s]
                if seen[v]:
                    continue
                seen[v] = True
                i, j = edge_i_table[c, s], edge_j_table[c, s]
                a, b = tets[t, i], tets[t, j]
                pa, pb = vals[t, i], vals[t, j]
                if pb == 0.0:
                    for d in range(3):
                        vertices[v, d] = points[b, d]
                else:
                    u = pa / (pa - pb)
                    for d in range(3):
                        vertices[v, d] = points[a, d] + u * (points[b, d] - points[a, d])
        f = 1 if flip[c] else 0
        if negative.shape[0] > 0 and negative[t]:
            f = 1 - f
        for q in range(2 if nvert[c] == 4 else 1):
            v0 = vinv[t, tri_slots[f, 3 * q]]
            v1 = vinv[t, tri_slots[f, 3 * q + 1]]
            v2 = vinv[t, tri_slots[f, 3 * q + 2]]
            if v0 != v1 and v1 != v2 and v0 != v2:
                if fill:
                    tri[n, 0], tri[n, 1], tri[n, 2] = v0, v1, v2
                    tri_tet[n] = t
                n += 1
    return n


def surface(vinv, n_vertices, tets, code, vals, points, edge_i_table, edge_j_table, nvert, flip, tri_slots, negative=None):
    """The vertices and triangles of S_h from the vertex numbers ``vinv`` (m, 4) of the polygon
    slots of the pieces.  Each vertex is computed once, from its first slot in the order of
    ``vinv``: ``x_a + u (x_b - x_a)``, u = phi_a / (phi_a - phi_b), for the slot's edge (a, b), or
    the node b itself when phi_b == 0.  The triangles of a piece are the slots ``tri_slots[f]``
    (f = flip[code], turned over where ``negative``), (0, 1, 2) and for quads (0, 2, 3); those with
    a repeated vertex are dropped.  Returns ``(vertices (V, 3), triangles (T, 3) of vinv's dtype,
    triangle_tets (T,) int32 while the tets' count fits, else int64)``, in tet order; two passes
    (count, then fill)."""
    vinv = np.ascontiguousarray(vinv)
    neg = np.zeros(0, dtype=np.bool_) if negative is None else np.ascontiguousarray(negative, dtype=np.bool_)
    tables = (np.ascontiguousarray(edge_i_table), np.ascontiguousarray(edge_j_table), np.ascontiguousarray(nvert),
              np.ascontiguousarray(flip, dtype=np.bool_), neg, np.ascontiguousarray(tri_slots, dtype=np.int64))
    vertices = np.empty((n_vertices, 3))
    args = (vinv, tets, code, vals, points) + tables[:4]
    tet_dtype = index_dtype(len(vinv))  # the counting pass gets empty arrays of the same types: one compiled signature
    n = _surface(*args, tables[4], tables[5], vertices, np.empty((0, 3), dtype=vinv.dtype), np.empty(0, dtype=tet_dtype), False)
    tri, tri_tet = np.empty((n, 3), dtype=vinv.dtype), np.empty(n, dtype=tet_dtype)
    _surface(*args, tables[4], tables[5], vertices, tri, tri_tet, True)
    return vertices, tri, tri_tet


@parallel_kernel
def _mixed_kuhn_tets(values, corner, cell_ids, mixed_table, kuhn_tets, tol, centre, bound, dist, bounds, starts,
                     broken, ratio, tet_ids, nodes, vals):
    fill = tet_ids.shape[0] > 0
    check = centre.shape[0] > 0 and not fill
    for ch in prange(bounds.shape[0] - 1):
        n = starts[ch] if fill else 0
        bad, top = 0, 0.0
        cv = np.empty(8)
        for c in range(bounds[ch], bounds[ch + 1]):
            signs = 0
            for b in range(8):
                v = values[corner[c, b]]
                if check:
                    d = abs(v - centre[c])
                    top = max(top, d / dist)
                    if d > bound:
                        bad += 1
                if abs(v) <= tol[corner[c, b]]:  # the zero rule's snap, the node's own tolerance
                    v = 0.0
                cv[b] = v
                if v < 0:
                    signs |= 1 << b
            for l in range(6):
                if mixed_table[signs, l]:
                    if fill:
                        tet_ids[n] = 6 * cell_ids[c] + l
                        for k in range(4):
                            nodes[n, k] = corner[c, kuhn_tets[l, k]]
                            vals[n, k] = cv[kuhn_tets[l, k]]
                    n += 1
        if not fill:
            starts[ch] = n
            broken[ch] = bad
            ratio[ch] = top


@njit(cache=True, error_model="numpy")
def label_scales(values, corner, cap):
    """(L,): for each label l with |values[l]| <= ``cap``, the largest |values[m]| over the labels m
    of the cells ``corner`` (k, 8) that have l as a corner: the scale of the level set's values
    around a node, from its own cells (the local scale of the zero rule,
    :func:`cutfem.cut._zero_tolerance`); 0 for the other labels.  With cap >= 1e-12 max |values|
    no other label can be snapped (its value exceeds 1e-12 times any maximum around it), so only
    the cells with such a corner are reduced: one read-mostly serial pass, 0.04 s for the torus's
    0.9 million band cells at spacing 0.00625 (0.08-0.16 s scattering to every label); the (k, 8)
    corner values are never made."""
    out = np.zeros(values.shape[0])
    for c in range(corner.shape[0]):
        small = False
        for b in range(8):
            if abs(values[corner[c, b]]) <= cap:
                small = True
        if not small:
            continue
        top = 0.0
        for b in range(8):
            top = max(top, abs(values[corner[c, b]]))
        for b in range(8):
            label = corner[c, b]
            if abs(values[label]) <= cap and top > out[label]:
                out[label] = top
    return out


#: rows per chunk of the kernels that count their output chunk by chunk, then fill it from each
#: chunk's offset, on all cores (:func:`mixed_kuhn_tets`, :func:`refine_blocks`): the same arrays
#: as one pass in row order
COUNT_FILL_CHUNK = 1 << 14


def _count_fill_bounds(k: int):
    """The chunk bounds (c + 1,) of k rows for the count-then-fill kernels."""
    return np.append(np.arange(0, k, COUNT_FILL_CHUNK, dtype=np.int64), np.int64(k))


def _offsets(counts):
    """(each chunk's first output row (c,), the output's length) from the chunks' counts."""
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64), int(counts.sum())


def mixed_kuhn_tets(values, corner, cell_ids, mixed_table, kuhn_tets, tol=0.0, centre=None, bound: float = 0.0,
                    dist: float = 1.0):
    """The Kuhn tets of the cells ``cell_ids`` (k,) whose corner values have both signs by
    ``mixed_table`` (256, 6) (bit c of the row: corner c has phi < 0).  Corner c of cell i has the
    label ``corner[i, c]`` and the value ``values[corner[i, c]]``, set to 0 where its modulus is at
    most ``tol`` (the zero rule's snap: one number, or one per label, (L,), see
    :func:`label_scales`).  Returns ``(tet_ids (n,), nodes (n, 4), vals (n, 4), broken,
    ratio)``: the tets in cell order, then Kuhn type, the nodes (labels) and snapped values in
    :data:`~cutfem.mesh.KUHN_TETS` order; with ``centre`` (k,), the value at each cell's centre,
    also the count ``broken`` of corners whose unsnapped value differs from their cell's centre
    value by more than ``bound``, and the largest |value - centre| / ``dist`` (a Lipschitz bound
    checked where the band search relies on it; 0 and 0.0 without ``centre``).  Two passes over
    chunks of :data:`COUNT_FILL_CHUNK` cells, each on any core: count (and check) per chunk, then fill
    from the chunk's offset (the same arrays as one pass in cell order); the (k, 8) corner values
    are never made."""
    values, corner = np.ascontiguousarray(values, dtype=float), np.ascontiguousarray(corner)
    cell_ids = np.ascontiguousarray(cell_ids, dtype=np.int64)
    centre = np.zeros(0) if centre is None else np.ascontiguousarray(centre, dtype=float)
    table = np.ascontiguousarray(mixed_table, dtype=np.bool_)
    kt = np.ascontiguousarray(kuhn_tets, dtype=np.int64)
    bounds = _count_fill_bounds(len(cell_ids))
    nch = len(bounds) - 1
    counts, broken, ratio = np.zeros(nch, dtype=np.int64), np.zeros(nch, dtype=np.int64), np.zeros(nch)
    tol = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, dtype=float), values.shape))
    args = (values, corner, cell_ids, table, kt, tol, centre, float(bound), float(dist), bounds)
    empty = np.empty(0, dtype=np.int64)
    _mixed_kuhn_tets(*args, counts, broken, ratio, empty, np.empty((0, 4), dtype=corner.dtype), np.empty((0, 4)))
    starts, n = _offsets(counts)
    tet_ids, nodes, vals = np.empty(n, dtype=np.int64), np.empty((n, 4), dtype=corner.dtype), np.empty((n, 4))
    if n:
        _mixed_kuhn_tets(*args, starts, broken, ratio, tet_ids, nodes, vals)
    return tet_ids, nodes, vals, int(broken.sum()), float(ratio.max()) if nch else 0.0


@njit(cache=True, error_model="numpy")
def _edge_census(triangles, n_vertices, start, upper):
    T = triangles.shape[0]
    for t in range(T):  # half-edges bucketed by their lower end: how many in each bucket
        for k in range(3):
            a, b = triangles[t, k], triangles[t, (k + 1) % 3]
            start[min(a, b) + 1] += 1
    for v in range(n_vertices):
        start[v + 1] += start[v]
    fill = start[:-1].copy()
    for t in range(T):
        for k in range(3):
            a, b = triangles[t, k], triangles[t, (k + 1) % 3]
            lo = min(a, b)
            upper[fill[lo]] = max(a, b)
            fill[lo] += 1


@parallel_kernel
def _sorted_runs(start, upper, n_vertices):
    n = not_two = 0
    for v in prange(n_vertices):  # each bucket (a few entries) sorted in place, its runs counted
        s, e = start[v], start[v + 1]
        for i in range(s + 1, e):
            x = upper[i]
            j = i - 1
            while j >= s and upper[j] > x:
                upper[j + 1] = upper[j]
                j -= 1
            upper[j + 1] = x
        i = s
        while i < e:
            j = i + 1
            while j < e and upper[j] == upper[i]:
                j += 1
            n += 1
            if j - i != 2:
                not_two += 1
            i = j
    return n, not_two


def edge_census(triangles, n_vertices: int):
    """``(E, B)`` of the ``triangles`` (T, 3) (vertex numbers below ``n_vertices``): how many distinct
    edges they have, and how many of those are not held by exactly two triangles (B = 0: closed and
    edge-manifold).  The 3T half-edges are bucketed by their lower end (a counting pass and a
    scatter) and each bucket, a few entries, is sorted in place: no sort of 3T keys (numpy's sort of
    the int64 keys min V + max took 1.3 s of 2.5 s at 27 million half-edges, the surface of the
    torus at spacing 0.003125), and no array of counts is made (108 MB there)."""
    triangles = np.ascontiguousarray(triangles)
    start = np.zeros(n_vertices + 1, dtype=np.int64)
    upper = np.empty(3 * len(triangles), dtype=triangles.dtype)
    _edge_census(triangles, n_vertices, start, upper)
    n, not_two = _sorted_runs(start, upper, n_vertices)
    return int(n), int(not_two)


@njit(cache=True, error_model="numpy", inline="always")
def _face_normal_area(table, l, k, volume):
    """(n_x, n_y, n_z, |F|) of the face opposite to vertex k of a tet of gradient type l and volume
    ``volume``: n = -g / |g| out of the tet and |F| = 3 |T| |g|, g = grad lambda_k = ``table[l, k]``
    (|T| = |F| height / 3, |g| = 1 / height)."""
    gx, gy, gz = table[l, k, 0], table[l, k, 1], table[l, k, 2]
    gn = gx * gx
    gn += gy * gy
    gn += gz * gz
    gn = np.sqrt(gn)
    return gx / -gn, gy / -gn, gz / -gn, 3.0 * volume * gn


@njit(cache=True, error_model="numpy")
def face_normals_areas(pairs, opposite, table, types, volumes, normals, areas):
    """For each face f between tets ``pairs[f]``: ``normals[f]`` = -g / |g| and ``areas[f]`` =
    3 |T| |g|, with g = grad lambda_k of the first tet T for the vertex k = ``opposite[f, 0]``
    opposite to the face (``table[types[T], k]``, volumes ``volumes``): the unit normal out of T and
    the face area (|T| = |F| height / 3, |g| = 1 / height)."""
    for f in range(pairs.shape[0]):
        t = pairs[f, 0]
        normals[f, 0], normals[f, 1], normals[f, 2], areas[f] = _face_normal_area(table, types[t], opposite[f, 0], volumes[t])


@njit(cache=True, error_model="numpy", inline="always")
def _kuhn_face_key(tets, kinds, low, ftype, r):
    """The lattice key 12 v + type of face row r = 4 t + k (the face opposite to local vertex k of
    tet t), see :func:`cutfem.mesh.kuhn_face_keys`."""
    t, k = r >> 2, r & 3
    l = kinds[t]
    return 12 * np.int64(tets[t, low[l, k]]) + ftype[l, k]


@njit(cache=True, error_model="numpy")
def kuhn_face_keys(tets, kinds, low, ftype, out):
    """out[4 t + k] = the lattice key of the face opposite to local vertex k of Kuhn tet t."""
    for r in range(out.shape[0]):
        out[r] = _kuhn_face_key(tets, kinds, low, ftype, r)


@njit(cache=True, error_model="numpy")
def _mark_kuhn_faces(tets, kinds, low, ftype, first, second):
    for r in range(4 * tets.shape[0]):
        key = _kuhn_face_key(tets, kinds, low, ftype, r)
        if first[key] < 0:
            first[key] = r
        elif second[key] == -1:
            second[key] = r
        else:
            second[key] = -2  # a third row: not a pair
    n = 0
    for key in range(first.shape[0]):
        if second[key] >= 0:
            n += 1
    return n


@njit(cache=True, error_model="numpy")
def _collect_pairs(first, second, pairs, opposite):
    n = 0
    for key in range(first.shape[0]):
        if second[key] >= 0:
            a, b = first[key], second[key]
            pairs[n, 0], pairs[n, 1] = a >> 2, b >> 2
            opposite[n, 0], opposite[n, 1] = a & 3, b & 3
            n += 1


def kuhn_face_pairs(tets, kinds, low, ftype, n_keys: int):
    """The interior faces of Kuhn tets ``tets`` (m, 4) (node numbers below n_keys / 12, types
    ``kinds`` (m,), key tables ``low``, ``ftype`` (6, 4) of :func:`cutfem.mesh.kuhn_face_keys`):
    ``(pairs (F, 2), opposite (F, 2) int8)``, the two tets of each face whose key occurs exactly
    twice (first the earlier row) and the local vertex opposite to it in each, in increasing key
    order.  The keys are computed on the fly and paired by two marker arrays of length n_keys: no
    (4m,) key array and no sort.  ``pairs`` is int32 when m < 2**31."""
    tets = np.ascontiguousarray(tets)
    kinds = np.ascontiguousarray(kinds)
    rows = 4 * len(tets)
    dtype = index_dtype(rows)
    first, second = np.full(n_keys, -1, dtype=dtype), np.full(n_keys, -1, dtype=dtype)
    n = _mark_kuhn_faces(tets, kinds, low, ftype, first, second)
    pairs, opposite = np.empty((n, 2), dtype=dtype), np.empty((n, 2), dtype=np.int8)
    _collect_pairs(first, second, pairs, opposite)
    return pairs, opposite


@njit(cache=True, error_model="numpy", inline="always")
def _orientation(a0, a1, a2, b, c, d, points):
    """(b - a) . ((c - a) x (d - a)) for a = (a0, a1, a2) and the points rows b, c, d."""
    u0, u1, u2 = points[b, 0] - a0, points[b, 1] - a1, points[b, 2] - a2
    v0, v1, v2 = points[c, 0] - a0, points[c, 1] - a1, points[c, 2] - a2
    w0, w1, w2 = points[d, 0] - a0, points[d, 1] - a1, points[d, 2] - a2
    return u0 * (v1 * w2 - v2 * w1) + u1 * (v2 * w0 - v0 * w2) + u2 * (v0 * w1 - v1 * w0)


@njit(cache=True, error_model="numpy")
def points_inside_tets(points, tets, node_cells, probes, dims, cell_start, cell_probes, tolerance, hits):
    """The pairs (tet, probe) with the probe strictly inside the positively oriented tet: its four
    barycentric coordinates above ``tolerance`` (each the signed volume of the tet with one vertex
    replaced by the probe, over the tet's).  Candidates: the probes in the grid cells (``dims`` (3,)
    cells, cell c = i + dims[0] (j + dims[1] k)) met by the tet's bounding box, listed by cell as
    ``cell_probes[cell_start[c]:cell_start[c + 1]]``, and inside that box.  The box's cells come
    from ``node_cells`` (N, 3) int32, the cell of each node clipped to [-1, dims] (floor is
    monotone, so the cells of the box are those between its nodes'); the coordinates are read only
    for the tets that meet a probe's cell, and the probes of a row of cells are one run.
    Writes the first ``len(hits)`` pairs into ``hits`` (k, 2); returns how many there are.  One
    pass over the tets, no per-tet arrays (:func:`cutfem.mesh._check_overlap`)."""
    found = 0
    c0 = np.empty(3, dtype=np.int64)
    c1 = np.empty(3, dtype=np.int64)
    lo = np.empty(3)
    hi = np.empty(3)
    for t in range(tets.shape[0]):
        a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        empty = False
        for x in range(3):
            c0[x] = max(min(min(node_cells[a, x], node_cells[b, x]), min(node_cells[c, x], node_cells[d, x])), 0)
            c1[x] = min(max(max(node_cells[a, x], node_cells[b, x]), max(node_cells[c, x], node_cells[d, x])), dims[x] - 1)
            if c1[x] < c0[x]:
                empty = True
        if empty:
            continue
        volume = -1.0
        for k in range(c0[2], c1[2] + 1):
            for j in range(c0[1], c1[1] + 1):
                g = c0[0] + dims[0] * (j + dims[1] * k)
                for q in range(cell_start[g], cell_start[g + c1[0] - c0[0] + 1]):
                    p = cell_probes[q]
                    if volume < 0.0:  # the tet's box and volume, once
                        for x in range(3):
                            lo[x] = min(min(points[a, x], points[b, x]), min(points[c, x], points[d, x]))
                            hi[x] = max(max(points[a, x], points[b, x]), max(points[c, x], points[d, x]))
                        volume = _orientation(points[a, 0], points[a, 1], points[a, 2], b, c, d, points)
                    p0, p1, p2 = probes[p, 0], probes[p, 1], probes[p, 2]
                    if not (lo[0] < p0 < hi[0] and lo[1] < p1 < hi[1] and lo[2] < p2 < hi[2]):
                        continue
                    limit = tolerance * volume
                    if (_orientation(p0, p1, p2, b, c, d, points) > limit
                            and _orientation(p0, p1, p2, c, a, d, points) > limit
                            and _orientation(p0, p1, p2, a, b, d, points) > limit
                            and _orientation(p0, p1, p2, b, a, c, points) > limit):
                        if found < hits.shape[0]:
                            hits[found, 0], hits[found, 1] = t, p
                        found += 1
    return found


@njit(cache=True, error_model="numpy")
def vertex_solid_angles(points, tets, out):
    """Adds to ``out`` (N,) the solid angle of each tet (m, 4) at each of its vertices: with a, b, c
    the other three vertices minus the vertex, tan(Omega / 2) = |det[a b c]| / (|a||b||c| +
    (a.b)|c| + (b.c)|a| + (c.a)|b|) (Van Oosterom and Strackee), summed tet by tet in order
    (:func:`cutfem.mesh._check_wound`)."""
    for t in range(tets.shape[0]):
        for k in range(4):
            v = tets[t, k]
            i, j, l = tets[t, (k + 1) % 4], tets[t, (k + 2) % 4], tets[t, (k + 3) % 4]
            a0, a1, a2 = points[i, 0] - points[v, 0], points[i, 1] - points[v, 1], points[i, 2] - points[v, 2]
            b0, b1, b2 = points[j, 0] - points[v, 0], points[j, 1] - points[v, 1], points[j, 2] - points[v, 2]
            c0, c1, c2 = points[l, 0] - points[v, 0], points[l, 1] - points[v, 1], points[l, 2] - points[v, 2]
            det = abs(a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2) + a2 * (b0 * c1 - b1 * c0))
            la = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            lb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
            lc = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            den = (la * lb * lc + (a0 * b0 + a1 * b1 + a2 * b2) * lc + (b0 * c0 + b1 * c1 + b2 * c2) * la
                   + (c0 * a0 + c1 * a1 + c2 * a2) * lb)
            out[v] += 2.0 * np.arctan2(det, den)


@njit(cache=True, error_model="numpy")
def kuhn_ends_bounds(ijk, bounds):
    """``bounds`` (2, 3) = the smallest and largest indices of the ends (ijk - o) / 2 and
    (ijk + o) / 2, o = ijk mod 2, of the coarse Kuhn edges of the fine nodes ``ijk`` (m, 3)
    (:func:`cutfem.solve.kuhn_prolongation`)."""
    for a in range(3):
        bounds[0, a] = (ijk[0, a] - (ijk[0, a] & 1)) >> 1
        bounds[1, a] = bounds[0, a]
    for i in range(ijk.shape[0]):
        for a in range(3):
            o = ijk[i, a] & 1
            lo = (ijk[i, a] - o) >> 1
            if lo < bounds[0, a]:
                bounds[0, a] = lo
            if lo + o > bounds[1, a]:
                bounds[1, a] = lo + o


@njit(cache=True, error_model="numpy")
def kuhn_ends_codes(ijk, base, dims, codes):
    """``codes`` (2m,): the lexicographic numbers x + dims_0 (y + dims_1 z) relative to ``base`` of
    the lower ends of the coarse Kuhn edges of the fine nodes ``ijk`` (m, 3), then of the upper
    ends (the node itself twice where every index is even)."""
    m = ijk.shape[0]
    for i in range(m):
        lo = 0
        hi = 0
        for a in range(2, -1, -1):
            o = ijk[i, a] & 1
            x = ((ijk[i, a] - o) >> 1) - base[a]
            lo = lo * dims[a] + x
            hi = hi * dims[a] + x + o
        codes[i] = lo
        codes[m + i] = hi


@njit(cache=True, error_model="numpy")
def kuhn_prolongation_csr(ijk, cols, indptr, indices, data):
    """The CSR arrays of the Kuhn prolongation (:func:`cutfem.solve.kuhn_prolongation`): row i is 1
    at column ``cols[i]`` when every index of ``ijk[i]`` is even, else 1/2 at ``cols[i]`` and at
    ``cols[m + i]`` (the two ends of its coarse edge, the lower first); ``indptr`` (m + 1,)."""
    m = ijk.shape[0]
    indptr[0] = 0
    n = 0
    for i in range(m):
        two = ((ijk[i, 0] | ijk[i, 1] | ijk[i, 2]) & 1) != 0
        indices[n] = cols[i]
        if two:
            data[n] = 0.5
            indices[n + 1] = cols[m + i]
            data[n + 1] = 0.5
            n += 2
        else:
            data[n] = 1.0
            n += 1
        indptr[i + 1] = n


@parallel_kernel
def _galerkin_upper(r_ptr, r_idx, r_val, a_ptr, a_idx, a_val, p_ptr, p_idx, p_val, nc, bounds, starts, stops, todo, count,
                    idx, val, strict):
    """The upper triangles of the rows of P^T A P for the chunks ``ch`` of ``bounds`` with
    ``todo[ch]`` (in parallel): the rows of chunk ch one after the other in idx/val[starts[ch]:
    stops[ch]], the length of row I in count[I].  strict[ch] becomes -1 if the chunk's rows
    overflowed their room, else the number of its entries right of the diagonal."""
    nch = bounds.shape[0] - 1
    for ch in prange(nch):
        if not todo[ch]:
            continue
        strict[ch] = 0
        acc = np.zeros(nc)
        mark = np.full(nc, -1, dtype=np.int64)
        cols = np.empty(nc, dtype=np.int64)
        nnz = starts[ch]
        room = stops[ch]
        for I in range(bounds[ch], bounds[ch + 1]):
            ncols = 0
            for ii in range(r_ptr[I], r_ptr[I + 1]):
                i, ri = r_idx[ii], r_val[ii]
                for jj in range(a_ptr[i], a_ptr[i + 1]):
                    j, ra = a_idx[jj], ri * a_val[jj]
                    for kk in range(p_ptr[j], p_ptr[j + 1]):
                        J = p_idx[kk]
                        if J < I:
                            continue
                        if mark[J] != I:
                            mark[J] = I
                            cols[ncols] = J
                            ncols += 1
                            acc[J] = 0.0
                        acc[J] += ra * p_val[kk]
            if nnz + ncols > room:
                strict[ch] = -1
                break
            for x in range(1, ncols):  # insertion sort of the row's columns (a few dozen)
                c = cols[x]
                y = x - 1
                while y >= 0 and cols[y] > c:
                    cols[y + 1] = cols[y]
                    y -= 1
                cols[y + 1] = c
            for x in range(ncols):
                idx[nnz + x] = cols[x]
                val[nnz + x] = acc[cols[x]]
                if cols[x] > I:
                    strict[ch] += 1
            nnz += ncols
            count[I] = ncols


@njit(cache=True, error_model="numpy")
def _mirror_upper(bounds, starts, count, idx, val, indptr, indices, data):
    """The full CSR arrays of the symmetric matrix whose upper triangles :func:`_galerkin_upper`
    wrote (row I of chunk ch after the rows before it, from starts[ch])."""
    n = count.shape[0]
    start = np.empty(n, dtype=np.int64)
    for ch in range(bounds.shape[0] - 1):
        pos = starts[ch]
        for I in range(bounds[ch], bounds[ch + 1]):
            start[I] = pos
            pos += count[I]
    lower = np.zeros(n, dtype=np.int64)
    for I in range(n):
        for x in range(start[I], start[I] + count[I]):
            if idx[x] > I:
                lower[idx[x]] += 1
    indptr[0] = 0
    for I in range(n):
        indptr[I + 1] = indptr[I] + lower[I] + count[I]
    nxt = indptr[:-1].copy()
    for I in range(n):
        pos = indptr[I] + lower[I]
        for x in range(start[I], start[I] + count[I]):
            J = idx[x]
            indices[pos], data[pos] = J, val[x]
            pos += 1
            if J > I:
                indices[nxt[J]], data[nxt[J]] = I, val[x]
                nxt[J] += 1


#: coarse rows of the Galerkin product per parallel chunk (about; at most 64 chunks)
GALERKIN_ROWS = 4096

#: the room first given to each coarse row's upper triangle in the Galerkin product (entries; a
#: chunk whose rows need more is done again with twice its room, the others are kept).  Room that
#: is not written costs address space only: the pages of np.empty are never touched.  The upper
#: triangles need about 9 entries a row on the cut torus, 13 on the perturbed torus grids (25-point
#: coarse stencils) and more than 24 with the augmented hierarchy of the cut Laplace-Beltrami
#: problem; with room for 12, every chunk of those two was computed twice or three times (the
#: coarse operators of the meshed torus 768 x 384, perturbed: 0.19 s against 0.31 s; the Galerkin
#: products of `cutfem run laplace-beltrami-cut --levels 0.025 0.0125`: 0.21-0.24 s against
#: 0.49-0.74 s, 11 passes against 25).
GALERKIN_ROOM = 32


def galerkin(A, P, R=None):
    """The Galerkin product P^T A P of a symmetric CSR matrix A (n, n) and a CSR prolongation P
    (n, m), as a CSR matrix with sorted indices, exactly symmetric: each coarse row I sums only its
    columns J >= I (sum over i, j of R[I, i] A[i, j] P[j, J], R = P^T, with a dense accumulator
    and a marker per coarse column), and the lower triangle is their mirror.  ``R``: P^T in CSR,
    when the caller has it.  One pass over the products, where scipy's two sparse products build
    A P first (and their result still needs symmetrizing).  The coarse rows go in chunks on the
    available cores, each into room for :data:`GALERKIN_ROOM` entries a row; a chunk that needs
    more is done again, alone, with twice its room (the chunks that fitted are kept: on the cut
    torus at spacing 0.00625, 2 chunks of 64 overflowed, and redoing all of them doubled the
    product's time).  The values depend neither on the number of threads nor on the retries."""
    R = sp.csr_matrix(P.T) if R is None else R
    R, A, P = (sp.csr_matrix(M) for M in (R, A, P))
    m = P.shape[1]
    args = []
    for M in (R, A, P):
        args += [M.indptr, M.indices, M.data.astype(float, copy=False)]
    nch = int(min(64, max(1, m // GALERKIN_ROWS)))
    bounds = (np.arange(nch + 1, dtype=np.int64) * m) // nch
    count = np.zeros(m, dtype=np.int64)
    rooms = GALERKIN_ROOM * np.diff(bounds)
    starts = np.concatenate([[0], np.cumsum(rooms)[:-1]]).astype(np.int64)
    strict, todo = np.zeros(nch, dtype=np.int64), np.ones(nch, dtype=np.bool_)
    idx, val = np.empty(int(rooms.sum()), dtype=index_dtype(m)), np.empty(int(rooms.sum()))
    while True:
        _galerkin_upper(*args, np.int64(m), bounds, starts, starts + rooms, todo, count, idx, val, strict)
        todo = strict < 0
        if not todo.any():
            break
        # the chunks that overflowed get twice their room in new arrays, into which the others'
        # rows are copied (only what they wrote: the pages of unused room are never touched)
        csum = np.concatenate([[0], np.cumsum(count)])
        used = csum[bounds[1:]] - csum[bounds[:-1]]
        rooms = np.where(todo, 2 * rooms, rooms)
        fresh = np.concatenate([[0], np.cumsum(rooms)[:-1]]).astype(np.int64)
        new_idx, new_val = np.empty(int(rooms.sum()), dtype=idx.dtype), np.empty(int(rooms.sum()))
        for ch in np.flatnonzero(~todo):  # chunks (at most 64), not rows
            a, b, k = starts[ch], fresh[ch], used[ch]
            new_idx[b : b + k] = idx[a : a + k]
            new_val[b : b + k] = val[a : a + k]
        idx, val, starts = new_idx, new_val, fresh
    nnz = int(count.sum() + strict.sum())
    index = index_dtype(nnz)  # int32 written here: scipy checks int64 contents min/max to narrow them
    indptr, indices, data = np.empty(m + 1, dtype=index), np.empty(nnz, dtype=index), np.empty(nnz)
    _mirror_upper(bounds, starts, count, idx, val, indptr, indices, data)
    out = sp.csr_matrix((data, indices, indptr), shape=(m, m))
    out.has_canonical_format = True  # sorted rows without duplicates, by construction (saves scipy's scans)
    return out


@njit(cache=True, error_model="numpy", inline="always")
def _popcount(x):
    """Set bits of a 64-bit word (SWAR)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@njit(cache=True, error_model="numpy")
def _mark_bits(ids, words):
    for r in range(ids.shape[0]):
        i = np.uint64(ids[r])
        words[i >> np.uint64(6)] |= np.uint64(1) << (i & np.uint64(63))


@njit(cache=True, error_model="numpy")
def _rank_bits(words, prefix, unique):
    total = 0
    for w in range(words.shape[0]):
        prefix[w] = total
        x = words[w]
        while x:
            b = _trailing_bit(x)
            unique[total] = 64 * w + b
            total += 1
            x &= x - np.uint64(1)
    return total


@njit(cache=True, error_model="numpy", inline="always")
def _trailing_bit(x):
    """Position of the lowest set bit of a nonzero 64-bit word."""
    return _popcount((x & (~x + np.uint64(1))) - np.uint64(1))


@parallel_kernel
def _bit_ranks(ids, words, prefix, inverse):
    for r in prange(ids.shape[0]):
        i = np.uint64(ids[r])
        w = i >> np.uint64(6)
        below = words[w] & ((np.uint64(1) << (i & np.uint64(63))) - np.uint64(1))
        inverse[r] = prefix[w] + _popcount(below)


def dense_unique(ids, n: int, inverse_dtype=None):
    """Sorted distinct values of integer ids in [0, n) and the inverse map: ``(unique (u,) int64,
    inverse)`` with ``unique[inverse] == ids`` (inverse of the shape of ids, of ``inverse_dtype`` when
    given (it must hold u - 1), else int32 when u < 2**31: a caller that keeps int64 numbers gets
    them written directly, not converted from an int32 copy).
    A bitmap of n bits and a running count of its set bits per 64-bit word (n / 4 bytes in all)
    instead of a marker and a lookup array of length n (5 n bytes: 2 GB for the 404 million nodes of
    the box at spacing 0.003125, of which the band touches a few), and no sort."""
    ids = np.asarray(ids)
    flat = np.ascontiguousarray(ids.reshape(-1))
    words = np.zeros((int(n) + 63) // 64, dtype=np.uint64)
    _mark_bits(flat, words)
    prefix = np.empty(len(words), dtype=np.int64)
    unique = np.empty(min(int(n), flat.size), dtype=np.int64)
    u = _rank_bits(words, prefix, unique)
    dtype = np.dtype(inverse_dtype) if inverse_dtype is not None else np.dtype(index_dtype(u))
    if u > 0 and np.iinfo(dtype).max < u - 1:
        raise ValueError(f"inverse_dtype {dtype} cannot hold {u} distinct values")
    inverse = np.empty(flat.size, dtype=dtype)
    _bit_ranks(flat, words, prefix, inverse)
    return unique[:u].copy(), inverse.reshape(ids.shape)


@parallel_kernel
def _refine_blocks(blocks, phi, keep, size, cells, lower, spacing, corners, bounds, starts, children, centres, parent_phi):
    fill = children.shape[0] > 0
    for ch in prange(bounds.shape[0] - 1):
        n = starts[ch] if fill else 0
        for b in range(bounds[ch], bounds[ch + 1]):
            if not keep[b]:
                continue
            for c in range(8):
                i0 = blocks[b, 0] + size * corners[c, 0]
                i1 = blocks[b, 1] + size * corners[c, 1]
                i2 = blocks[b, 2] + size * corners[c, 2]
                if i0 < cells[0] and i1 < cells[1] and i2 < cells[2]:
                    if fill:
                        children[n, 0], children[n, 1], children[n, 2] = i0, i1, i2
                        centres[n, 0] = lower[0] + (i0 + 0.5 * size) * spacing[0]
                        centres[n, 1] = lower[1] + (i1 + 0.5 * size) * spacing[1]
                        centres[n, 2] = lower[2] + (i2 + 0.5 * size) * spacing[2]
                        parent_phi[n] = phi[b]
                    n += 1
        if not fill:
            starts[ch] = n


@njit(cache=True, error_model="numpy")
def _prune_blocks(phi, parent_phi, slack, dist, keep):
    nonfinite = broken = kept = 0
    top = 0.0
    check = parent_phi.shape[0] > 0
    for t in range(phi.shape[0]):
        v = phi[t]
        if not np.isfinite(v):
            nonfinite += 1
            keep[t] = False
            continue
        if check:
            d = abs(v - parent_phi[t])
            top = max(top, d / dist)
            if d > slack:
                broken += 1
        keep[t] = abs(v) <= slack
        if keep[t]:
            kept += 1
    return nonfinite, broken, top, kept


def prune_blocks(phi, parent_phi, slack: float, dist: float):
    """One level of the band search over the values ``phi`` (k,) at the centres of blocks of
    half-diagonal ``dist``: ``(keep (k,) bool, kept, nonfinite, broken, ratio)``, keep = |phi| <=
    ``slack`` (L dist and its rounding slack; finite values only), the counts of kept blocks and of
    non-finite values, and with the parents' values ``parent_phi`` (k,) (None on the first level;
    each centre lies ``dist`` from its parent's) the count of blocks whose |phi - parent| exceeds
    ``slack`` and the largest |phi - parent| / ``dist`` (0 and 0.0 without parents).  One pass,
    where numpy made five (k,) temporaries."""
    phi = np.ascontiguousarray(phi, dtype=float)
    parent = np.zeros(0) if parent_phi is None else np.ascontiguousarray(parent_phi, dtype=float)
    keep = np.empty(len(phi), dtype=np.bool_)
    nonfinite, broken, ratio, kept = _prune_blocks(phi, parent, float(slack), float(dist), keep)
    return keep, int(kept), int(nonfinite), int(broken), float(ratio)


@njit(cache=True, error_model="numpy")
def kept_cells(blocks, phi, keep, cells_x, cells_y, ids, kept_phi):
    """The cell ids i + cells_x (j + cells_y k) of the blocks (k, 3) of one cell with ``keep``, and
    their values, in block order, into ``ids`` and ``kept_phi``."""
    n = 0
    for t in range(blocks.shape[0]):
        if keep[t]:
            ids[n] = blocks[t, 0] + cells_x * (blocks[t, 1] + cells_y * blocks[t, 2])
            kept_phi[n] = phi[t]
            n += 1


def refine_blocks(blocks, phi, keep, size: int, cells, lower, spacing, corners):
    """The children of the kept blocks of the band search: for each block ``blocks`` (k, 3) (lower
    cell index) with ``keep``, its 8 sub-blocks of ``size`` cells at ``corners`` (8, 3) that start
    inside the box of ``cells`` (3,), in block order then corner order: ``(children (k', 3), their
    centres lower + (child + size / 2) spacing (k', 3), the parent's phi (k',))``.  Two passes
    (count, fill) over chunks of :data:`COUNT_FILL_CHUNK` blocks on all cores; no (k, 8, 3) arrays."""
    bounds = _count_fill_bounds(len(blocks))
    args = (np.ascontiguousarray(blocks, dtype=np.int64), np.ascontiguousarray(phi, dtype=float),
            np.ascontiguousarray(keep, dtype=np.bool_), np.int64(size), np.ascontiguousarray(cells, dtype=np.int64),
            np.ascontiguousarray(lower, dtype=float), np.ascontiguousarray(spacing, dtype=float),
            np.ascontiguousarray(corners, dtype=np.int64), bounds)
    counts = np.zeros(len(bounds) - 1, dtype=np.int64)
    _refine_blocks(*args, counts, np.empty((0, 3), dtype=np.int64), np.empty((0, 3)), np.empty(0))
    starts, n = _offsets(counts)
    children, centres, parent_phi = np.empty((n, 3), dtype=np.int64), np.empty((n, 3)), np.empty(n)
    if n:
        _refine_blocks(*args, starts, children, centres, parent_phi)
    return children, centres, parent_phi


@parallel_kernel
def triangle_geometry(points, tri):
    """Cross products, their lengths and edge-vector dot products of triangles, for
    :func:`cutfem.surface._triangle_geometry` (which states them): ``(cross (M, 3), twice_area (M,),
    dots (2, M, 3), longest (M,))``.  One pass over the triangles, where numpy gathered coordinate
    columns and made two dozen temporaries a block."""
    M = tri.shape[0]
    cross, twice, dots, longest = np.empty((M, 3)), np.empty(M), np.empty((2, M, 3)), np.empty(M)
    for t in prange(M):
        e = np.empty((3, 3))
        for k in range(3):
            a, b = tri[t, k], tri[t, (k + 1) % 3]
            for d in range(3):
                e[k, d] = points[b, d] - points[a, d]
        # (x_1 - x_0) x (x_2 - x_0), with x_2 - x_0 = -e_2
        cross[t, 0] = e[0, 2] * e[2, 1] - e[0, 1] * e[2, 2]
        cross[t, 1] = e[0, 0] * e[2, 2] - e[0, 2] * e[2, 0]
        cross[t, 2] = e[0, 1] * e[2, 0] - e[0, 0] * e[2, 1]
        twice[t] = np.sqrt(cross[t, 0] * cross[t, 0] + cross[t, 1] * cross[t, 1] + cross[t, 2] * cross[t, 2])
        top = 0.0
        for k in range(3):
            nx = (k + 1) % 3
            sq = e[k, 0] * e[k, 0] + e[k, 1] * e[k, 1] + e[k, 2] * e[k, 2]
            dots[0, t, k] = sq
            dots[1, t, k] = e[k, 0] * e[nx, 0] + e[k, 1] * e[nx, 1] + e[k, 2] * e[nx, 2]
            top = max(top, sq)
        longest[t] = top
    return cross, twice, dots, longest


@parallel_kernel
def triangle_gradients(v, grads, normals, areas):
    """Surface gradients of the barycentric coordinates of triangles ``v`` (m, 3, 3), for
    :func:`cutfem.spaces.triangle_gradients` (which states them), into ``grads`` (m, 3, 3),
    ``normals`` (m, 3) and ``areas`` (m,): one pass, where numpy made four cross products of
    (m, 3) temporaries (0.13 s for the 590 thousand triangles of the torus 768 x 384)."""
    for t in prange(v.shape[0]):
        a0, a1, a2 = v[t, 1, 0] - v[t, 0, 0], v[t, 1, 1] - v[t, 0, 1], v[t, 1, 2] - v[t, 0, 2]
        b0, b1, b2 = v[t, 2, 0] - v[t, 0, 0], v[t, 2, 1] - v[t, 0, 1], v[t, 2, 2] - v[t, 0, 2]
        c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        twice = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        n0, n1, n2 = c0 / twice, c1 / twice, c2 / twice
        normals[t, 0], normals[t, 1], normals[t, 2] = n0, n1, n2
        areas[t] = 0.5 * twice
        for i in range(3):
            p, q = (i + 2) % 3, (i + 1) % 3
            e0, e1, e2 = v[t, p, 0] - v[t, q, 0], v[t, p, 1] - v[t, q, 1], v[t, p, 2] - v[t, q, 2]
            grads[t, i, 0] = (n1 * e2 - n2 * e1) / twice
            grads[t, i, 1] = (n2 * e0 - n0 * e2) / twice
            grads[t, i, 2] = (n0 * e1 - n1 * e0) / twice


@parallel_kernel
def tangential_entries(table, types, normals, areas, edges, diagonal):
    """The entries of |K| (P G)(P G)^T, P = I - n n^T, for tets whose gradients G (4, 3) are
    ``table[types[k]]``, with normal ``normals[k]`` and weight ``areas[k]``: on the local edges
    (:data:`~cutfem.numbering.TET_EDGES` order) into ``edges`` (m, 6) and on the diagonal into
    ``diagonal`` (m, 4), for :func:`cutfem.forms._kuhn_tangential_stiffness`:
    |K| (G_a . G_b - (G_a . n)(G_b . n)).  One pass (numpy's masks per type, gathers and products
    took 0.17 s for the 853 thousand cut tets at spacing 0.0125)."""
    for k in prange(types.shape[0]):
        G = table[types[k]]
        c = np.empty(4)
        for a in range(4):
            c[a] = G[a, 0] * normals[k, 0] + G[a, 1] * normals[k, 1] + G[a, 2] * normals[k, 2]
        w = areas[k]
        for a in range(4):
            diagonal[k, a] = (G[a, 0] * G[a, 0] + G[a, 1] * G[a, 1] + G[a, 2] * G[a, 2] - c[a] * c[a]) * w
        for e in range(6):
            a, b = _TET_EDGES[e, 0], _TET_EDGES[e, 1]
            edges[k, e] = (G[a, 0] * G[b, 0] + G[a, 1] * G[b, 1] + G[a, 2] * G[b, 2] - c[a] * c[b]) * w


@njit(cache=True, error_model="numpy")
def _rows_sorted(lo, key, n, order):
    """Writes into ``order`` (m,) the indices k in the order of (lo[k], key[k]), stable (equal
    entries in index order), and returns the row starts (n + 1,) of lo = 0..n-1 in it (``order``'s
    integer type): a counting sort on lo, then an insertion sort on key within each row (the rows
    of a surface mesh hold a handful of entries)."""
    start = np.zeros(n + 1, order.dtype)
    for k in range(lo.shape[0]):
        start[lo[k] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    for k in range(lo.shape[0]):
        order[fill[lo[k]]] = k
        fill[lo[k]] += 1
    for i in range(n):
        s, e = start[i], start[i + 1]
        for t in range(s + 1, e):
            k = order[t]
            u = t
            while u > s and key[order[u - 1]] > key[k]:
                order[u] = order[u - 1]
                u -= 1
            order[u] = k
    return start


@njit(cache=True, error_model="numpy")
def closed_halfedges(tri, n):
    """The half-edges of a triangle mesh with n nodes in the order of the key
    2 (min(a, b) n + max(a, b)) + [a > b] of half-edge a -> b, for
    :func:`cutfem.surface._closed_halfedge_table` (which states what it is for): a stable counting
    sort on min(a, b), then an insertion sort on the rest of the key within each node's few
    half-edges (numpy: an argsort of the keys).  Returns ``(closed, order (3 M,), edges (3 M / 2,
    2), halfedge_edge (3 M,))``: ``closed`` is whether the sorted keys come in pairs
    (2 k, 2 k + 1), i.e. every edge has one forward and one backward half-edge and nothing else;
    the other arrays are meaningful only then."""
    H = 3 * tri.shape[0]
    lo, rest = np.empty(H, np.int64), np.empty(H, np.int64)
    for t in range(tri.shape[0]):
        for k in range(3):
            a, b = tri[t, k], tri[t, (k + 1) % 3]
            lo[3 * t + k] = min(a, b)
            rest[3 * t + k] = 2 * max(a, b) + (1 if a > b else 0)
    order = np.empty(H, np.int64)
    _rows_sorted(lo, rest, n, order)
    edges = np.empty((H // 2, 2), np.int64)
    halfedge_edge = np.empty(H, np.int64)
    if H % 2:
        return False, order, edges, halfedge_edge
    for p in range(H // 2):
        f, b = order[2 * p], order[2 * p + 1]
        if lo[f] != lo[b] or rest[f] & 1 or rest[b] != rest[f] + 1:
            return False, order, edges, halfedge_edge
        edges[p, 0], edges[p, 1] = lo[f], rest[f] >> 1
        halfedge_edge[f], halfedge_edge[b] = p, p
    return True, order, edges, halfedge_edge


@njit(cache=True, error_model="numpy")
def symmetric_data(diagonal_position, upper, lower, slot, diagonal, values, nnz):
    """The CSR values of :meth:`cutfem.assembly.SymmetricPattern.matrix`: ``diagonal`` at
    ``diagonal_position``, and the value of each given pair k added at the positions of its
    distinct pair ``slot[k]`` (k itself when ``slot`` is empty), in the upper triangle and its
    mirror (repeated pairs summed in the order given).  One pass, where numpy summed the repeats by
    ``bincount`` and scattered three times."""
    data = np.zeros(nnz)
    for i in range(diagonal.shape[0]):
        data[diagonal_position[i]] = diagonal[i]
    for k in range(values.shape[0]):
        u = slot[k] if slot.shape[0] else k
        data[upper[u]] += values[k]
    for u in range(upper.shape[0]):
        data[lower[u]] = data[upper[u]]
    return data


@njit(cache=True, error_model="numpy")
def meshed_position_load(points, tri, out):
    """out[v] += |T| grad lambda_v over the triangles T of a triangulated surface, for
    :func:`cutfem.forms.position_load`: with c = (x_1 - x_0) x (x_2 - x_0) = 2 |T| n_T,

        |T| grad lambda_k = (1/2) n_T x (x_{k+2} - x_{k+1}) = c x (x_{k+2} - x_{k+1}) / (2 |c|),

    the in-plane edge opposite vertex k turned a quarter towards it.  One pass over the triangles
    (no gradients stored, no stiffness matrix)."""
    for t in range(tri.shape[0]):
        a, b, d = tri[t, 0], tri[t, 1], tri[t, 2]
        u0, u1, u2 = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
        w0, w1, w2 = points[d, 0] - points[a, 0], points[d, 1] - points[a, 1], points[d, 2] - points[a, 2]
        c0, c1, c2 = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
        s = 0.5 / np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        c0, c1, c2 = c0 * s, c1 * s, c2 * s
        for k in range(3):
            p, q = tri[t, (k + 1) % 3], tri[t, (k + 2) % 3]
            e0, e1, e2 = points[q, 0] - points[p, 0], points[q, 1] - points[p, 1], points[q, 2] - points[p, 2]
            v = tri[t, k]
            out[v, 0] += c1 * e2 - c2 * e1
            out[v, 1] += c2 * e0 - c0 * e2
            out[v, 2] += c0 * e1 - c1 * e0


@njit(cache=True, error_model="numpy")
def meshed_edge_penalty(tri, S, Q, areas, h, h1, h2, n):
    """The edge penalty J_E of a closed triangulated surface in closed form, for
    :func:`cutfem.forms._meshed_edge_penalty` (which derives it): per half-edge g = 3 t + k the
    scaled jump coefficients b_start, b_end, b_opp, then ``(diagonal (n,), on_edges (E,),
    opposite (E,))``: the values on the edges {i, j} and on the pairs {k, l} of vertices opposite
    them (:meth:`cutfem.spaces.SurfaceP1Space.edge_stencil_pattern`).  ``S``, ``Q`` (M, 3) the edge-vector dot
    products, ``areas`` (M,), ``h1``, ``h2`` (E,) the half-edges of each edge.  Two passes over
    the half-edges and one over the edges, where numpy made a dozen (M, 3) temporaries."""
    M = tri.shape[0]
    E = h1.shape[0]
    twin = np.empty(3 * M, np.int64)
    for e in range(E):
        twin[h1[e]], twin[h2[e]] = h2[e], h1[e]
    c_end = np.empty(3 * M)  # sqrt(h |E|) c_end of each half-edge, then b_start
    b_opp = np.empty(3 * M)
    b_start = np.empty(3 * M)
    for t in range(M):
        for k in range(3):
            length = np.sqrt(S[t, k])
            cs = -0.5 * np.sqrt(length * h) / (length * areas[t])
            c_end[3 * t + k] = Q[t, (k + 2) % 3] * cs
            b_start[3 * t + k] = Q[t, k] * cs  # sqrt(h |E|) c_start, plus the twin's c_end below
            b_opp[3 * t + k] = S[t, k] * cs
    for g in range(3 * M):
        b_start[g] += c_end[twin[g]]
    received = c_end  # reused: what each half-edge receives from the two others of its triangle
    diagonal = np.zeros(n)
    for t in range(M):
        for k in range(3):
            g, nx, pv = 3 * t + k, 3 * t + (k + 1) % 3, 3 * t + (k + 2) % 3
            # the half-edge before g gives b_end b_opp, the one after it b_opp b_start
            received[g] = b_start[twin[pv]] * b_opp[pv] + b_opp[nx] * b_start[nx]
            diagonal[tri[t, k]] += b_start[g] * b_start[g] + b_opp[nx] * b_opp[nx]
    on_edges, opposite = np.empty(E), np.empty(E)
    for e in range(E):
        a, b = h1[e], h2[e]
        on_edges[e] = b_start[a] * b_start[b] + received[a] + received[b]
        opposite[e] = b_opp[a] * b_opp[b]
    return diagonal, on_edges, opposite


@njit(cache=True, error_model="numpy")
def symmetric_pattern(pairs, n, presorted, like):
    """The CSR structure of a symmetric n x n matrix with its full diagonal and the undirected pairs
    {a_k, b_k} = ``pairs[k]`` (a_k != b_k, both in [0, n)), for :class:`cutfem.assembly.SymmetricPattern`.

    The pairs (lo, hi) = (min, max) are put in lexicographic order by a stable counting sort on lo
    and an insertion sort on hi within each lo (rows of a surface mesh hold a handful of pairs), and
    repeated pairs become one; ``presorted`` promises they are unique and in that order already
    (then nothing is sorted).  Row i holds, in increasing column order, the mirrors (i, lo) of the
    pairs (lo, i), the diagonal, then the pairs (i, hi).  Returns (indptr (n + 1,), indices,
    diagonal (n,), upper (p,), lower (p,), slot (m,)): the positions in ``indices`` of the diagonal,
    of each distinct pair (lo, hi) and of its mirror (hi, lo), the pairs in lexicographic order; and
    the distinct pair of each given pair (empty when ``presorted``), so that the values of repeated
    pairs sum in the order given; and first ``(k, why)``: -1 when the pairs are valid, else the
    first invalid pair k and why (0: a_k == b_k, 1: outside [0, n)), with empty arrays.  Every
    array has the integer type of the empty array ``like``, which must hold n + 2 m (a fresh array
    is a first touch of its pages: int32 halves them); the pairs are checked before they are
    narrowed to it."""
    m = pairs.shape[0]
    dt = like.dtype
    lo, hi = np.empty(m, dt), np.empty(m, dt)
    for k in range(m):
        a, b = pairs[k, 0], pairs[k, 1]
        if a == b or min(a, b) < 0 or max(a, b) >= n:
            e = np.empty(0, dt)
            return k, 0 if a == b else 1, e, e, e, e, e, e
        lo[k], hi[k] = min(a, b), max(a, b)
    if presorted:
        slot = np.empty(0, dt)
        ulo, uhi, p = lo, hi, m
    else:
        order = np.empty(m, dt)
        start = _rows_sorted(lo, hi, n, order)  # stable: equal pairs in the order given
        slot = np.empty(m, dt)
        ulo = np.empty(m, dt)
        uhi = np.empty(m, dt)
        p = 0
        for i in range(n):
            s, e = start[i], start[i + 1]
            for t in range(s, e):
                k = order[t]
                if t == s or hi[k] != uhi[p - 1]:
                    ulo[p], uhi[p] = i, hi[k]
                    p += 1
                slot[k] = p - 1
    n_upper = np.zeros(n, dt)
    n_lower = np.zeros(n, dt)
    for u in range(p):
        n_upper[ulo[u]] += 1
        n_lower[uhi[u]] += 1
    indptr = np.empty(n + 1, dt)
    diagonal = np.empty(n, dt)
    indices = np.empty(n + 2 * p, dt)
    indptr[0] = 0
    for i in range(n):
        diagonal[i] = indptr[i] + n_lower[i]
        indices[diagonal[i]] = i
        indptr[i + 1] = diagonal[i] + 1 + n_upper[i]
    upper = np.empty(p, dt)
    lower = np.empty(p, dt)
    next_upper = n_upper  # reused as the next free position of each row's pairs
    next_lower = n_lower  # and of its mirrors
    for i in range(n):
        next_upper[i] = diagonal[i] + 1
        next_lower[i] = indptr[i]
    for u in range(p):  # lexicographic order: each row's columns come in increasing order
        r, c = ulo[u], uhi[u]
        upper[u] = next_upper[r]
        next_upper[r] += 1
        indices[upper[u]] = c
        lower[u] = next_lower[c]
        next_lower[c] += 1
        indices[lower[u]] = r
    return -1, -1, indptr, indices, diagonal, upper, lower, slot


@njit(cache=True, error_model="numpy")
def grid_weights(X, n, m, drop):
    """The four coarse corners and weights of each node of a doubly periodic (n, m) surface grid,
    for :func:`cutfem.solve.grid_prolongation` (which states the weights): node (i, j), index
    i m + j, in the coarse cell (2a, 2b) + {0, 2}^2, corners (a, b), (a + 1, b), (a + 1, b + 1),
    (a, b + 1) modulo (n/2, m/2).  Returns (cols (n m, 4), weights (n m, 4)); a coarse node gets
    the weights (1, 0, 0, 0).  A node on a coarse edge (one index odd) whose two weights off that
    edge are both below ``drop`` in magnitude takes the weights (1 - s, s) of its projection
    X_0 + s (X_1 - X_0) on the edge instead.  One pass over the nodes, where numpy made (n m, 4, 3)
    blocks."""
    nc, mc = n // 2, m // 2
    N = n * m
    cols = np.empty((N, 4), np.int64)
    w = np.empty((N, 4))
    D = np.empty((4, 3))
    u = np.empty(4)
    v = np.empty(4)
    for p in range(N):
        i, j = p // m, p % m
        a, b = i // 2, j // 2
        a1, b1 = (a + 1) % nc, (b + 1) % mc
        cols[p, 0], cols[p, 1], cols[p, 2], cols[p, 3] = a * mc + b, a1 * mc + b, a1 * mc + b1, a * mc + b1
        if i % 2 == 0 and j % 2 == 0:
            w[p, 0], w[p, 1], w[p, 2], w[p, 3] = 1.0, 0.0, 0.0, 0.0
            continue
        for k in range(4):
            q = 2 * (cols[p, k] // mc) * m + 2 * (cols[p, k] % mc)
            for c in range(3):
                D[k, c] = X[q, c] - X[p, c]
        su = sv = suu = svv = suv = 0.0
        for k in range(4):
            u[k] = D[k, 0] * (D[2, 0] - D[0, 0]) + D[k, 1] * (D[2, 1] - D[0, 1]) + D[k, 2] * (D[2, 2] - D[0, 2])
            v[k] = D[k, 0] * (D[3, 0] - D[1, 0]) + D[k, 1] * (D[3, 1] - D[1, 1]) + D[k, 2] * (D[3, 2] - D[1, 2])
            su += u[k]
            sv += v[k]
            suu += u[k] * u[k]
            svv += v[k] * v[k]
            suv += u[k] * v[k]
        c0 = suu * svv - suv * suv
        c1 = suv * sv - su * svv
        c2 = su * suv - suu * sv
        det = 4.0 * c0 + su * c1 + sv * c2
        for k in range(4):
            w[p, k] = (c0 + c1 * u[k] + c2 * v[k]) / det
        if i % 2 == 1 and j % 2 == 1:
            continue
        e = 1 if j % 2 == 0 else 3  # the other end of the node's coarse edge, from corner 0
        f, g = (2, 3) if e == 1 else (1, 2)  # the corners off it
        if abs(w[p, f]) < drop and abs(w[p, g]) < drop:
            se = sx = 0.0  # X_p - X_0 = -D_0, X_1 - X_0 = D_e - D_0
            for c in range(3):
                se += (D[e, c] - D[0, c]) * (D[e, c] - D[0, c])
                sx += -D[0, c] * (D[e, c] - D[0, c])
            s = sx / se
            w[p, 0], w[p, e], w[p, f], w[p, g] = 1.0 - s, s, 0.0, 0.0
    return cols, w


# ---------------------------------------------------------------------------------------------
# the difference stencil of a user level set (cutfem.levelset.FunctionLevelSet)
# ---------------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def difference_stencil(x, h1, h2, hessian_offsets, out):
    """The 25 points at which one call of a user's phi gives phi, its difference gradient and its
    difference Hessian at each point x[i] (n, 3): rows 0-2 x + h1 e_j, rows 3-5 x - h1 e_j (the
    gradient's steps h1[i]), rows 6-24 x + h2[i] s_k with s_k the offsets (19, 3) of the Hessian's
    stencil (row 6 is x itself, s = 0).  Each coordinate is formed as numpy forms
    ``x + h * e`` and ``x - h * e``, so the values are those of the separate calls, bit for bit.
    One thread: it runs per chunk of :meth:`cutfem.levelset.LevelSet.closest_point`, between calls
    of the user's numpy phi, and moves a few MB (threads would only wait for each other)."""
    for i in range(x.shape[0]):
        for j in range(3):
            for k in range(3):
                e = 1.0 if j == k else 0.0
                out[i, j, k] = x[i, k] + h1[i] * e
                out[i, 3 + j, k] = x[i, k] - h1[i] * e
        for r in range(hessian_offsets.shape[0]):
            for k in range(3):
                out[i, 6 + r, k] = x[i, k] + h2[i] * hessian_offsets[r, k]


@njit(cache=True, error_model="numpy")
def difference_derivatives(f, h1, h2, pairs, value, gradient, hessian):
    """phi, the central-difference gradient and Hessian at each point from phi at its 25 points
    ``f`` (n, 25) (:func:`difference_stencil`): g_j = (f(x + h1 e_j) - f(x - h1 e_j)) / (2 h1),
    H_ii = (f(x + 2 h2 e_i) - 2 f(x) + f(x - 2 h2 e_i)) / (4 h2^2) and
    H_ij = (f(++) - f(+-) - f(-+) + f(--)) / (4 h2^2) for the pairs (i, j) (3, 2), the same
    operations in the same order as :meth:`cutfem.levelset.FunctionLevelSet.gradient` and
    ``hessian``."""
    for i in range(f.shape[0]):
        value[i] = f[i, 6]
        for j in range(3):
            gradient[i, j] = (f[i, j] - f[i, 3 + j]) / (2.0 * h1[i])
        d = 4.0 * (h2[i] * h2[i])
        for j in range(3):
            hessian[i, j, j] = (f[i, 7 + j] - 2.0 * f[i, 6] + f[i, 10 + j]) / d
        for q in range(3):
            a, b = pairs[q, 0], pairs[q, 1]
            o = 13 + 4 * q
            v = (f[i, o] - f[i, o + 1] - f[i, o + 2] + f[i, o + 3]) / d
            hessian[i, a, b] = v
            hessian[i, b, a] = v


@njit(cache=True, error_model="numpy")
def closest_point_newton_step(todo, p, y, mu, scale, f, g, hess, saddle, failed, keep):
    """One step of the closest-point Newton iteration (:meth:`cutfem.levelset.LevelSet.closest_point`)
    for the points ``todo`` (k,), with phi, grad phi and Hess phi at their current p in ``f`` (k,),
    ``g`` (k, 3), ``hess`` (k, 3, 3): the residual r = p - y + mu g, the convergence test, the
    second-order test of the converged points (n n^T + P (I + mu Hess) P positive definite, P = I -
    n n^T, by Sylvester's criterion) into ``saddle``, and the Newton update of (p, mu) from the 4 x 4
    system [[I + mu Hess, g], [g^T, 0]] d = -(r, phi) by Gaussian elimination with partial pivoting,
    for every point (a converged one gets a last polishing step).  ``keep[i]`` is set for the
    points still to iterate; ``failed`` where the step is not finite before convergence.  One
    thread: it runs between calls of the user's numpy phi on a chunk of points."""
    a = np.empty((4, 5))
    for i in range(todo.shape[0]):
        k = todo[i]
        mk = mu[k]
        r0 = p[k, 0] - y[k, 0] + mk * g[i, 0]
        r1 = p[k, 1] - y[k, 1] + mk * g[i, 1]
        r2 = p[k, 2] - y[k, 2] + mk * g[i, 2]
        gn = np.sqrt(g[i, 0] * g[i, 0] + g[i, 1] * g[i, 1] + g[i, 2] * g[i, 2])
        e0, e1, e2 = y[k, 0] - p[k, 0], y[k, 1] - p[k, 1], y[k, 2] - p[k, 2]
        done = abs(f[i]) <= 1e-12 * gn * scale[k] and \
            np.sqrt(r0 * r0 + r1 * r1 + r2 * r2) <= 1e-12 * scale[k] + 1e-9 * np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        if done:
            n = np.empty(3)
            for c in range(3):
                n[c] = g[i, c] / gn
            # m = P (I + mu H) P + n n^T
            b = np.empty((3, 3))
            pr = np.empty((3, 3))
            for s in range(3):
                for t in range(3):
                    pr[s, t] = (1.0 if s == t else 0.0) - n[s] * n[t]
                    b[s, t] = (1.0 if s == t else 0.0) + mk * hess[i, s, t]
            bp = np.zeros((3, 3))
            for s in range(3):
                for t in range(3):
                    for u in range(3):
                        bp[s, t] += b[s, u] * pr[u, t]
            m = np.zeros((3, 3))
            for s in range(3):
                for t in range(3):
                    for u in range(3):
                        m[s, t] += pr[s, u] * bp[u, t]
                    m[s, t] += n[s] * n[t]
            m00, m01, m02, m11, m12, m22 = m[0, 0], m[0, 1], m[0, 2], m[1, 1], m[1, 2], m[2, 2]
            minor2 = m00 * m11 - m01 * m01
            det = m00 * (m11 * m22 - m12 * m12) - m01 * (m01 * m22 - m12 * m02) + m02 * (m01 * m12 - m11 * m02)
            saddle[k] = not (m00 > 0 and minor2 > 0 and det > 0)
        # the Newton system, augmented with its right-hand side
        for s in range(3):
            for t in range(3):
                a[s, t] = (1.0 if s == t else 0.0) + mk * hess[i, s, t]
            a[s, 3] = g[i, s]
            a[3, s] = g[i, s]
        a[3, 3] = 0.0
        a[0, 4], a[1, 4], a[2, 4], a[3, 4] = -r0, -r1, -r2, -f[i]
        ok = True
        for c in range(4):
            piv = c
            for s in range(c + 1, 4):
                if abs(a[s, c]) > abs(a[piv, c]):
                    piv = s
            if not (a[piv, c] != 0.0 and np.isfinite(a[piv, c])):
                ok = False
                break
            if piv != c:
                for t in range(c, 5):
                    a[c, t], a[piv, t] = a[piv, t], a[c, t]
            for s in range(c + 1, 4):
                factor = a[s, c] / a[c, c]
                for t in range(c, 5):
                    a[s, t] -= factor * a[c, t]
        if ok:
            d = np.empty(4)
            for c in range(3, -1, -1):
                v = a[c, 4]
                for t in range(c + 1, 4):
                    v -= a[c, t] * d[t]
                d[c] = v / a[c, c]
            for c in range(4):
                if not np.isfinite(d[c]):
                    ok = False
            if ok:
                p[k, 0] += d[0]
                p[k, 1] += d[1]
                p[k, 2] += d[2]
                mu[k] += d[3]
        if not ok and not done:
            failed[k] = True
        keep[i] = ok and not done
