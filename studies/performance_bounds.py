"""What the measured stages of the performance benchmark (:mod:`cutfem.studies.performance`) are
held against: a lower bound for each stage from the bytes it must move through memory, compiled
libraries doing the same operation on the same data, and the per-stage target that puts the two
side by side.

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
"""

from __future__ import annotations

import time

import numpy as np

from cutfem.fem import element_kernels
from cutfem.fem.forms import assemble
from cutfem.fem.terms import position_load
from cutfem.fem.spaces import CutSpace
from cutfem.geometry.cut import CUT, cut_mesh
from cutfem.geometry.shapes import Torus
from cutfem.geometry.markers import interior_facets
from cutfem.geometry.keys import dense_unique
from cutfem.geometry.box import structured_box
from cutfem.geometry.numbering import TET_EDGES, index_dtype
from cutfem.problems.mean_curvature import mean_curvature_form
from cutfem.solvers import multigrid_kernels, sparse_kernels
from cutfem.solvers.multigrid import lattice_hierarchy, lattice_indices

from .performance_levels import BOX, CUT_STAGES, fresh_process_result

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

#: a call of this module in a fresh interpreter with the allocation settings of the levels
_CALL_CODE = ("import json, cutfem.memory\ncutfem.memory.configure()\nimport cutfem.studies.performance_bounds as bounds\n"
              "print('RESULT ' + json.dumps(bounds.{call}))\n")


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
    is one; ``measured_fresh`` the first run's, which also pays the process's start-up (see
    :mod:`cutfem.studies.performance_levels`).  An estimate: see the module docstring."""
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
      distinct values and the inverse): :func:`cutfem.geometry.keys.dense_unique` against
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
    * the whole topology stage (the field on the cut tets, :class:`cutfem.fem.spaces.CutSpace`, and
      the interior faces of the active mesh, :func:`cutfem.geometry.markers.interior_facets`) against VTK's
      geometry filter (vtkGeometryFilter, C++, pyvista's ``extract_surface``, one thread) on the
      active tets: it matches every face of the tets with its twin and keeps those met once (the
      boundary), the same matching; ``difference`` is |its boundary faces - (4 T - 2 F)|, T tets
      and F interior faces;
    * the whole right-hand-side stage (:func:`cutfem.fem.forms.assemble` of
      :func:`cutfem.fem.terms.position_load`: b_i = sum_K |S_K| P_h grad phi_i, element vectors and
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

    import pyvista as pv

    box = structured_box(*BOX, spacing=spacing)
    torus = Torus(1.0, 0.5)
    cut = cut_mesh(box, torus)
    space = CutSpace(cut)
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
        return CutSpace(cut), interior_facets(es.tets, es.n_nodes, es.kuhn_types)

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


def references_in_fresh_process(spacing: float) -> list:
    """:func:`compiled_references` in a fresh process with the allocation settings of the levels."""
    return fresh_process_result(_CALL_CODE.format(call=f"compiled_references({float(spacing)!r})"), f"compiled references at spacing {spacing}")


def bandwidth_in_fresh_process(mebibytes: int) -> dict:
    """:func:`memory_bandwidth` in a fresh process with the allocation settings of the levels (and
    without leaving its arrays on this process's heap)."""
    return fresh_process_result(_CALL_CODE.format(call=f"memory_bandwidth({int(mebibytes)})"), "the bandwidth measurement")
