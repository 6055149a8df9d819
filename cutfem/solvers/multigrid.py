"""Geometric multigrid, the preconditioner of CG for the large cut and meshed surface systems
("cg-mg", docs/math.md §12): the hierarchies of prolongations and :class:`GeometricMultigrid`.

Why geometric multigrid
-----------------------
The cut systems are dominated by the face penalty: for K = M + tau_F J_F the entries of J_F are
O(1) per face while those of the surface mass matrix M are O(h^2).  The kernel of J_F is the
globally linear functions on the band, its near-kernel the *locally* linear ones: a function with
slowly varying gradient has face jumps O(h |D^2 u|), so J_F acts like h^2 times a biharmonic along
the surface (and a second-order operator across the band, for functions vanishing on S_h, which M
does not see).  The diagonally scaled spectrum runs from O(h^2) to O(1) with a fourth-order
character.  On it aggregation AMG needs more CG iterations at every refinement (with constant
candidates, and still with the linear functions as candidates), and a sparse factorization fills
in like a 3-D one, the band being a thick surface.  A hierarchy whose prolongations reproduce the
linear functions on every level keeps the iterations nearly independent of h.

Nested lattices
---------------
The structured Kuhn meshes are nested: the Kuhn triangulation of the lattice 2h Z^3 is made of
unions of tets of that of h Z^3 (both are the arrangements of the planes x_i = k s, x_i - x_j = k s).
So the P1 space of the coarse lattice restricted to the band is a subspace of the fine one and its
prolongation is exact and trivial (:func:`kuhn_prolongation`): a fine node with lattice index i
takes the value of the coarse node i/2 (all indices even) or the mean of the two coarse nodes
(i -/+ o)/2 at the ends of the coarse Kuhn edge it halves (o = i mod 2, a 0/1 vector).  It
reproduces linear functions, the near-kernel of J_F, on every level.  The coarse matrices are
Galerkin products P^T A P (each level has about 4 times fewer unknowns and nonzeros, the band
being two-dimensional: operator complexity 1.33), built by one compiled pass that sums the upper
triangle and mirrors it, so they are exactly symmetric
(:func:`cutfem.solvers.multigrid_kernels.galerkin`).  Cycle: one forward Gauss-Seidel sweep,
coarse correction, one backward sweep; V-cycle on the finest level, K-cycles below (two coarse
cycles combined by two steps of flexible CG, see :class:`GeometricMultigrid`; CG then takes
flexible directions); :class:`~cutfem.solvers.direct.DirectSolver` on the coarsest level (<= 1500
unknowns).  The residual after the forward sweep from zero is -U x (U the strictly upper part):
half a product.

Meshed surfaces
---------------
The meshed system M + tau_E J_E has the same fourth-order character (J_E penalizes the jumps of
the conormal derivatives, O(1) per edge against O(h^2) for the mass).  A surface mesh with a
doubly periodic grid (the torus families) coarsens along its grid (:func:`grid_hierarchy`: every
second node, weights from the node positions reproducing linear functions); any other goes
through a Kuhn lattice of spacing twice the mean edge (:func:`surface_hierarchy`), then the nested
lattices.  The lattice is uniform, so it needs a roughly uniform mesh: on the torus grid, whose
edges vary 3:1, the slowest multigrid error lives on the inner equator, where the first coarse
space is six fine edges wide, and CG needs two to three times the iterations it needs along the
grid.  :func:`multigrid_hierarchy` picks the hierarchy of a space.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..geometry.box import StructuredBox
from ..geometry.keys import dense_unique, unique_keys
from ..geometry.numbering import index_dtype
from . import multigrid_kernels
from . import sparse_kernels
from .common import _canonical_csr, _diagonal, _one_blas_thread
from .diagnose import SolverError, _Checks, diagnose
from .direct import DirectSolver

__all__ = [
    "GeometricMultigrid",
    "lattice_indices",
    "kuhn_prolongation",
    "surface_lattice_prolongation",
    "grid_prolongation",
    "lattice_hierarchy",
    "surface_hierarchy",
    "grid_hierarchy",
    "augmented_hierarchy",
    "multigrid_hierarchy",
]


def lattice_indices(space):
    """Integer lattice indices (n, 3) of the dofs of a space on a structured box, or None.

    Works for spaces whose dofs are background nodes (``node_ids``) of a
    :class:`~cutfem.geometry.box.StructuredBox` (``space.cut.background`` or ``space.background``),
    and for P2 spaces on one (``order`` 2, ``edge_nodes``): their dofs, the nodes and the edge
    midpoints, are the nodes of the Kuhn lattice of half the spacing (a Kuhn edge joins ijk and
    ijk + o, o in {0, 1}^3, its midpoint is 2 ijk + o there), so the first prolongation of
    :func:`lattice_hierarchy` is the embedding of P1 into P2 and the hierarchy continues on P1.
    """
    node_ids = getattr(space, "node_ids", None)
    cut = getattr(space, "cut", None)
    box = getattr(cut, "background", None) if cut is not None else getattr(space, "background", None)
    if node_ids is None or not isinstance(box, StructuredBox):
        return None
    ijk = box.node_index(node_ids)
    if getattr(space, "order", 1) == 2:
        edges = space.edge_nodes
        return np.concatenate([2 * ijk, ijk[edges[:, 0]] + ijk[edges[:, 1]]])
    return ijk


def kuhn_prolongation(ijk):
    """Prolongation from the lattice 2Z^3 to the nodes ``ijk`` (m, 3) of Z^3 (Kuhn meshes).

    Row i interpolates the coarse P1 function at fine node ijk[i]: weight 1 on the coarse node
    ijk/2 when every index is even, otherwise 1/2 on each end (ijk -/+ o)/2, o = ijk mod 2, of the
    coarse Kuhn edge whose midpoint it is.  Returns (P (m, mc) CSR, coarse indices (mc, 3)); the
    coarse nodes are those the rows use, in lexicographic (z, y, x) order.  Compiled passes
    (:func:`cutfem.solvers.multigrid_kernels.kuhn_ends_bounds`, :func:`~cutfem.solvers.multigrid_kernels.kuhn_ends_codes`,
    :func:`~cutfem.solvers.multigrid_kernels.kuhn_prolongation_csr`) give the bounding box of the edge ends, their
    lexicographic numbers and the CSR arrays (one or two entries a row, the lower end first: its
    number is the smaller), with the numbering between them (:func:`_number_lattice_codes`), where
    numpy needed a dozen (m, 3) integer arrays and axis reductions over them, a large part of the
    multigrid setup on the finest levels.
    """

    ijk = np.ascontiguousarray(ijk, dtype=np.int64)
    m = len(ijk)
    if ijk.ndim != 2 or ijk.shape[1] != 3 or m == 0:
        raise ValueError(f"kuhn_prolongation needs lattice indices of shape (m, 3), m >= 1; got {ijk.shape}")
    bounds = np.empty((2, 3), dtype=np.int64)
    multigrid_kernels.kuhn_ends_bounds(ijk, bounds)
    base, dims = bounds[0], bounds[1] - bounds[0] + 1
    codes = np.empty(2 * m, dtype=np.int64)
    multigrid_kernels.kuhn_ends_codes(ijk, base, dims, codes)
    cols, cijk = _number_lattice_codes(codes, base, dims)
    index = index_dtype(2 * m)
    indptr = np.empty(m + 1, dtype=index)
    indices, data = np.empty(2 * m, dtype=index), np.empty(2 * m)
    multigrid_kernels.kuhn_prolongation_csr(ijk, cols, indptr, indices, data)
    nnz = int(indptr[-1])
    P = sp.csr_matrix((data[:nnz], indices[:nnz], indptr), shape=(m, len(cijk)))
    P.has_sorted_indices = True
    P.has_canonical_format = True
    return P, cijk


def _number_lattice_nodes(ijk):
    """Number the distinct lattice nodes among ``ijk`` (m, 3) in lexicographic (z, y, x) order:
    returns (number of each row (m,), the distinct nodes (mc, 3)); see :func:`_number_lattice_codes`."""
    base = ijk.min(axis=0)
    rel = ijk - base
    dims = rel.max(axis=0) + 1
    return _number_lattice_codes(rel[:, 0] + dims[0] * (rel[:, 1] + dims[1] * rel[:, 2]), base, dims)


def _number_lattice_codes(code, base, dims):
    """Number the distinct lattice nodes given by their lexicographic numbers ``code`` (m,) in the
    box ``base`` + [0, dims): returns (number of each (m,), the distinct nodes (mc, 3)).  A bitmap
    over the box (:func:`~cutfem.geometry.keys.dense_unique`, a bit a lattice point) when it is not much
    larger than the input, else one sort (:func:`~cutfem.geometry.mesh.unique_keys`)."""
    if int(np.prod(dims)) <= 64 * code.size + 10_000_000:
        keys, cols = dense_unique(code, int(np.prod(dims)))
    else:
        keys, cols = unique_keys(code, return_inverse=True)
    nodes = np.stack([keys % dims[0], (keys // dims[0]) % dims[1], keys // (dims[0] * dims[1])], axis=1) + base
    return cols, nodes


def surface_lattice_prolongation(points, spacing: float):
    """Prolongation from the Kuhn lattice ``spacing`` Z^3 to the nodes ``points`` (N, 3) of a
    surface mesh: row i holds the barycentric coordinates of points[i] in the Kuhn tet of the
    lattice that contains it, so P reproduces every linear function of R^3 exactly.

    The lattice is anchored half a spacing below the smallest coordinates.  In a unit cube with
    local coordinates t (Freudenthal/Kuhn: the tets of the cube are t_s1 >= t_s2 >= t_s3 for the
    permutations s), the point with sorted coordinates u1 >= u2 >= u3 has the weights
    1 - u1, u1 - u2, u2 - u3, u3 at the corners 0, e_s1, e_s1 + e_s2, (1, 1, 1).  These are the
    tets of :func:`kuhn_prolongation`, so the lattice levels below are nested as usual.  Columns of
    lattice nodes that get no weight are dropped.  Returns (P (N, mc) CSR, lattice indices (mc, 3)).
    """
    X = np.asarray(points, dtype=float)
    y = (X - (X.min(axis=0) - 0.5 * spacing)) / spacing
    cell = np.floor(y).astype(np.int64)
    t = y - cell
    order = np.argsort(-t, axis=1, kind="stable")
    u = np.take_along_axis(t, order, axis=1)
    w = np.column_stack([1.0 - u[:, 0], u[:, 0] - u[:, 1], u[:, 1] - u[:, 2], u[:, 2]])
    unit = np.eye(3, dtype=np.int64)[order]  # (N, 3, 3): unit[:, k] = e_{s_k}
    corner = np.stack([np.zeros_like(cell), unit[:, 0], unit[:, 0] + unit[:, 1], np.ones_like(cell)], axis=1)
    keep = w.reshape(-1) > 0
    cols, cijk = _number_lattice_nodes((cell[:, None, :] + corner).reshape(-1, 3)[keep])
    rows = np.repeat(np.arange(len(X)), 4)[keep]
    P = sp.csr_matrix((w.reshape(-1)[keep], (rows, cols)), shape=(len(X), len(cijk)))
    P.sum_duplicates()
    return P, cijk


#: the weights of a node on a coarse edge off that edge below which the grid prolongation drops
#: them (:func:`grid_prolongation`)
GRID_DROP = 0.01


def grid_prolongation(points, shape, drop: float = GRID_DROP):
    """Prolongation on a logically structured, doubly periodic surface grid (e.g. the torus
    families of :func:`~cutfem.geometry.surface_meshes.torus_mesh`).

    ``shape`` = (n, m), both even: node (i, j) has index i m + j and neighbours (i +- 1, j),
    (i, j +- 1) modulo (n, m).  The coarse grid keeps the nodes (2a, 2b), index a (m/2) + b.  A
    coarse node keeps its value; any other fine node x takes the minimum-norm weights w on the four
    corners x_1..x_4 of its coarse cell (2a, 2b) + {0, 2}^2 that reproduce the functions linear in
    the plane of the cell's diagonals d = x_3 - x_1, e = x_4 - x_2:

        min |w|^2  subject to  sum_k w_k = 1,  sum_k w_k (x_k - x).d = 0,  sum_k w_k (x_k - x).e = 0.

    With C the 3 x 4 matrix of the constraints (rows 1, u_k = (x_k - x).d, v_k = (x_k - x).e),
    w = C^T G^{-1} (1, 0, 0)^T, G = C C^T, whose first column is the first row of adj(G) / det G.
    Constants are reproduced exactly, linear functions of R^3 up to the offsets of the corners
    from that plane, O(H^2) times the curvature; weights from the node positions, not from the grid
    indices, keep this true on perturbed grids.

    A node on a coarse edge (one index odd) whose two weights off that edge are both below
    ``drop`` in magnitude takes the weights (1 - s, s) of its projection x_1 + s (x_2 - x_1) on the
    edge instead.  On an unperturbed curved grid those two weights only answer the curvature (the
    corners off the plane: 1e-3 on the torus 768 x 384, where the nodes of the perturbed families
    have 4.5e-2 in the median), yet they make every coarse operator a 25-point stencil.  Dropped,
    the node reproduces linear functions up to its offset from the edge, at most about
    ``drop`` times the cell, and a planar grid stays exact where the node lies on its edge.  On the
    meshed torus CG needs the same iterations as with ``drop=0`` in every family, and the
    unperturbed families solve faster (sparser coarse operators).  ``drop=0`` keeps the
    minimum-norm weights everywhere.  Returns (P (n m, n m / 4) CSR, coarse points, coarse shape).
    """
    n, m = (int(v) for v in shape)
    X = np.asarray(points, dtype=float)
    if n % 2 or m % 2 or X.shape != (n * m, 3):
        raise ValueError(f"grid_prolongation needs an even grid shape matching the points; got {shape} and {X.shape}")
    if not 0 <= drop < 0.5:
        raise ValueError(f"drop must be in [0, 0.5) (0 keeps the minimum-norm weights), got {drop!r}")

    nc, mc = n // 2, m // 2
    cols, w = multigrid_kernels.grid_weights(np.array(X, order="C"), n, m, float(drop))  # a writable copy: one compiled signature
    P = sp.csr_matrix((w.reshape(-1), cols.reshape(-1), np.arange(0, 4 * n * m + 1, 4)), shape=(n * m, nc * mc))
    P.eliminate_zeros()
    coarse_points = X[(2 * np.arange(nc))[:, None] * m + 2 * np.arange(mc)[None, :]].reshape(-1, 3)
    return P, coarse_points, (nc, mc)


def lattice_hierarchy(lattice):
    """The prolongations of :func:`kuhn_prolongation`, level after level, from lattice indices."""
    ijk = np.asarray(lattice)
    while True:
        P, ijk = kuhn_prolongation(ijk)
        yield P


def surface_hierarchy(points, spacing: float):
    """Surface nodes -> Kuhn lattice of ``spacing`` (:func:`surface_lattice_prolongation`), then
    the nested Kuhn lattices."""
    P, ijk = surface_lattice_prolongation(points, spacing)
    yield P
    yield from lattice_hierarchy(ijk)


def grid_hierarchy(points, shape):
    """:func:`grid_prolongation` level after level while both grid dimensions are even and at
    least 6 (a coarser doubly periodic grid would not be a simplicial complex any more)."""
    X, shape = np.asarray(points, dtype=float), tuple(shape)
    while shape[0] % 2 == 0 and shape[1] % 2 == 0 and min(shape) >= 12:
        P, X, shape = grid_prolongation(X, shape)
        yield P


def augmented_hierarchy(prolongations, w):
    """The hierarchy ``prolongations`` with every coarse space doubled by the products with the
    nodal vector w (n,): P_0 becomes [P_0, diag(w) P_0] (n, 2 n_1) and P_l, l >= 1, becomes
    diag(P_l, P_l), so level l holds the fine functions P_0..P_{l-1} v + w P_0..P_{l-1} v'.
    With several vectors w (n, k), the products with each: [P_0, diag(w_1) P_0, ..., diag(w_k) P_0]
    and diag(P_l, ..., P_l) (k + 1 times).

    Why (w = phi_h, the surface operators of a cut band, docs/math.md §4): the functions w g, g
    smooth, are normally linear with zero trace on Gamma_h, so only the face penalty sees them,
    through the gradient jumps of their interpolant, O(h) times the curvature.  The coarse Kuhn
    lattice of spacing H interpolates them with jumps O(H) on its faces instead: their energy grows
    with H / h and each level adds a cluster of small eigenvalues to the preconditioned operator
    (on the cut unit sphere the eigenvector of the smallest is nearly all face energy and follows
    |phi_h|), so the CG iterations grow as h shrinks.  With the products w v in the coarse spaces
    the w g are represented on every level (with g coarse P1) and the iterations stay flat
    (docs/performance.md, "Iterations of the solvers").  The price: the coarse levels have twice
    the unknowns and four times the nonzeros (operator complexity 2.3 instead of 1.3).  Where the
    face penalty dominates the whole operator (M + tau_F J_F, the mean curvature system) the plain
    hierarchy already needs few iterations and the larger coarse levels made it slower, hence an
    option.

    The same near-kernel, one order up, in fictitious-domain P2 fields (docs/math.md §20): outside
    Omega_h only the ghost penalty sees a function, and the functions that vanish inside and grow
    outward, (phi)_+ g, have tiny face jumps of the first and second normal derivatives; the P1
    coarse space of the P2 level holds none of them (CG's slowest modes live on the dofs outside,
    A-orthogonal to it), so w = (phi)_+ there.  And for P2 trace fields the normally quadratic
    functions phi_h^2 g vanish on Gamma_h to second order: only the face penalty sees them, through
    jumps O(h) smaller than those of phi_h g; with w = (phi_h, phi_h^2) the coarse levels hold both
    (phi_h the P1 level set: phi_h v and phi_h^2 v are its products with P1 functions, exactly P2
    on the finest level).  A coarse node whose support w misses gives a zero
    column, an empty row of the coarse matrices: the sweeps leave it at zero (its right-hand side is
    zero) and the coarsest level, singular, takes its pseudo-inverse (:meth:`GeometricMultigrid._coarse_pseudo_inverse`).
    """
    prolongations = iter(prolongations)
    P = next(prolongations, None)
    if P is None:
        return
    P = sp.csr_matrix(P)
    w = np.asarray(w).reshape(len(w), -1)
    yield sp.hstack([P] + [sp.diags(w[:, k]) @ P for k in range(w.shape[1])], format="csr")
    for P in prolongations:
        yield sp.block_diag([P] * (w.shape[1] + 1), format="csr")


def _single(M):
    """M as a CSR matrix of float32 values, sharing M's index arrays."""
    M = M if type(M) is sp.csr_matrix else sp.csr_matrix(M)
    out = sp.csr_matrix((M.data.astype(np.float32), M.indices, M.indptr), shape=M.shape)
    out.has_sorted_indices = M.has_sorted_indices
    return out


class GeometricMultigrid:
    """Galerkin multigrid for an SPD matrix with a geometric hierarchy of prolongations (docs/math.md §12).

    The hierarchy is either ``lattice`` (n, 3), integer indices of unknowns that are nodes of a Kuhn
    lattice (see :func:`lattice_indices`; levels by :func:`kuhn_prolongation`), or
    ``prolongations``, an iterable giving P_0, P_1, ... lazily (:func:`surface_hierarchy`,
    :func:`grid_hierarchy`, :func:`multigrid_hierarchy`).  Levels A_{l+1} = P_l^T A_l P_l are built
    until at most ``coarse_size`` unknowns remain, the hierarchy ends, or coarsening stalls; the
    coarsest system is solved by :class:`~cutfem.solvers.direct.DirectSolver` (a pseudo-inverse if that level is singular
    only because of the coarse space).
    The cycle: one forward Gauss-Seidel sweep, coarse correction on level l+1, one backward sweep
    (the rows of each level in the chunk order of :func:`cutfem.solvers.sparse_kernels.sweep_chunks`, so that both
    cores sweep: the same iterations as in the natural order, the same bits on any number of threads).
    The coarse correction is ``visits[l]`` recursive cycles: 1 is a V-cycle; 2 is a K-cycle
    (Notay and Vassilevski, Numer. Linear Algebra Appl. 15, 2008): the two cycles are combined by
    two steps of flexible CG on level l+1 (:meth:`_krylov_correction`), where a W-cycle would add
    them as stationary iterations.  Default: V on the finest level, K below.  A K-cycle is not a
    linear operator, so the CG it preconditions takes flexible directions
    (:func:`~cutfem.solvers.krylov._pcg`).  On the cut torus the K-cycle keeps the CG iterations
    flat under refinement where the W-cycle's grew, at about the W-cycle's cost per iteration (one
    coarse product more per visit).  ``apply(R)`` acts on (n, c).

    ``augment`` (n,) or (n, k), nodal vectors w: every coarse space holds, beside the prolongated coarse
    functions v, their products w v (:func:`augmented_hierarchy`).  For a surface operator on a cut
    band, w = phi_h: see :func:`augmented_hierarchy` for why and what it costs.

    The cycle runs in single precision: the smoothed levels' matrices, transfers and vectors are
    float32 (the Galerkin products and the coarsest solve stay in double).  A preconditioner's
    rounding at 1e-7 relative is far below what CG asks of it (on the cut torus CG needs the same
    iterations as with a double-precision cycle, at tolerances 1e-6 and 1e-8), and the cycle moves a
    third less memory (8 instead of 12 bytes a nonzero).
    """

    def __init__(self, A, lattice=None, coarse_size: int = 1500, visits=(1, 2), max_levels: int = 20, prolongations=None,
                 augment=None, _checks=None):
        if not len(visits) or any(v not in (1, 2) for v in visits):
            raise ValueError(f"visits must be a non-empty sequence of 1 (V-cycle) and 2 (K-cycle) per level, got {visits!r}")
        # used as it is when already a double CSR matrix: a new wrapper would scan its indices again
        # for scipy's format flags
        A = A if type(A) is sp.csr_matrix and A.dtype == np.float64 else sp.csr_matrix(A, dtype=float)
        self._finest = A  # in double precision, for the null-vector checks
        n = A.shape[0]
        if (lattice is None) == (prolongations is None):
            raise ValueError("give either lattice= (Kuhn lattice indices) or prolongations= (a hierarchy), not both")
        if lattice is not None:
            lattice = np.asarray(lattice)
            if lattice.shape != (n, 3) or not np.issubdtype(lattice.dtype, np.integer):
                raise ValueError(f"lattice must be integer indices of shape ({n}, 3), got {lattice.shape} {lattice.dtype}")
            prolongations = lattice_hierarchy(lattice)
        if augment is not None:
            augment = np.asarray(augment, dtype=float)
            if augment.shape[:1] != (n,) or augment.ndim > 2 or not np.all(np.isfinite(augment)) \
                    or not np.all(np.any(augment.reshape(n, -1), axis=0)):
                raise ValueError(f"augment must be finite, nonzero nodal vectors of shape ({n},) or ({n}, k) (e.g. the "
                                 f"level-set values phi_h of a cut space), got shape {augment.shape}; pass augment=None for "
                                 "the plain hierarchy")
            prolongations = augmented_hierarchy(prolongations, augment)
        self._checks = _checks if _checks is not None else _Checks.of(n=n)
        if np.any(_diagonal(A) <= 0):
            raise diagnose(A, where="the geometric multigrid", _checks=self._checks)

        self.levels = []
        prolongations = iter(prolongations)
        while A.shape[0] > coarse_size and len(self.levels) < max_levels:
            P = next(prolongations, None)
            if P is None or P.shape[1] >= 0.9 * P.shape[0]:
                break
            if P.shape[0] != A.shape[0]:
                raise ValueError(f"prolongation {len(self.levels)} has {P.shape[0]} rows for {A.shape[0]} unknowns")
            A = self._prepare(A)
            P = sp.csr_matrix(P)
            R = sp.csr_matrix(P.T)
            Ac = multigrid_kernels.galerkin(A, P, R)  # exactly symmetric
            self.levels.append(dict(A=_single(A), P=_single(P), R=_single(R), chunks=sparse_kernels.sweep_chunks(A)))
            A = Ac
        close = getattr(prolongations, "close", None)
        if close is not None:  # a generator: its frame holds the lattice of a level (108 MB at 4.7 million unknowns)
            close()
        self.coarse_n = A.shape[0]
        where = "the coarsest multigrid level (a Galerkin product P^T A P: a negative direction there is one of A)"
        try:
            self._coarse = ("lu", DirectSolver(A, where=where, _checks=_Checks({}, None, self._checks.indefinite_hint)))
        except SolverError as exc:
            if exc.cause == "indefinite":
                raise
            self._coarse = ("pinv", self._coarse_pseudo_inverse(A, exc))
        self.visits = [visits[min(k, len(visits) - 1)] for k in range(len(self.levels))]
        self._work = {}
        self.sizes = [lv["A"].shape[0] for lv in self.levels] + [self.coarse_n]
        self.nnz = [lv["A"].nnz for lv in self.levels] + [A.nnz]

    def _coarse_pseudo_inverse(self, A, exc, tol: float = 1e-10):
        """Pseudo-inverse of a singular coarsest matrix, after checking that its null vectors are not
        null vectors of the finest matrix (then the system itself is singular: :class:`~cutfem.solvers.diagnose.SolverError`
        from :func:`~cutfem.solvers.diagnose.diagnose` with that vector).

        A coarse matrix P^T A P is singular either because A is (a null vector of the coarse matrix,
        prolongated, has zero energy) or because the coarse space is rank-deficient (two coarse
        nodes seen only through one fine node, possible at the edge of the band: its prolongation
        vanishes); only the second is harmless.
        """
        d = A.diagonal()
        s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
        with _one_blas_thread():
            w, V = np.linalg.eigh(s[:, None] * A.toarray() * s[None, :])
        null = w <= tol * max(w.max(), 1e-300)
        U = s[:, None] * V[:, null]
        for lv in reversed(self.levels):
            U = lv["P"] @ U
        A0 = self._finest
        d0 = A0.diagonal()
        for k in range(U.shape[1]):
            u = U[:, k]
            norm = float(u @ (d0 * u))
            if norm > 0:
                rayleigh = float(u @ (A0 @ u)) / norm
                if rayleigh <= tol:
                    raise diagnose(A0, vectors=[u], smallest=rayleigh, _checks=self._checks,
                                   where="the geometric multigrid (a null vector found on the coarsest level)") from exc
        keep = ~null
        return (s[:, None] * (V[:, keep] / w[keep])) @ (V[:, keep].T * s[None, :])

    @staticmethod
    def _prepare(A):
        A = _canonical_csr(A)
        if A.indices.dtype != np.int32 and A.shape[0] < 2**31 and A.nnz < 2**31:
            A = sp.csr_matrix((A.data, A.indices.astype(np.int32), A.indptr.astype(np.int32)), shape=A.shape)
            A.has_canonical_format = True  # a new object (the caller's keeps its arrays), with the same order
        return A

    @property
    def operator_complexity(self) -> float:
        return sum(self.nnz) / self.nnz[0]

    def __repr__(self) -> str:
        return f"GeometricMultigrid(levels={self.sizes}, operator_complexity={self.operator_complexity:.2f})"

    def _coarse_solve(self, b):
        # column by column: SuperLU's solve with several right-hand sides, and a matrix product, sum in
        # another order than with one, and a column would not give what it gives alone
        kind, f = self._coarse
        apply = f.solve if kind == "lu" else f.__matmul__
        return np.column_stack([apply(np.ascontiguousarray(b[:, k])) for k in range(b.shape[1])])

    def _buffers(self, level: int, c: int) -> dict:
        """The work arrays of a cycle on ``level`` for blocks of c columns, made on first use and
        kept: at 4.7 million unknowns a block is 56 MB, and arrays that large come fresh from the
        system on every allocation (page faults and zeroing each time, not reuse)."""
        key = (level, c)
        if key not in self._work:
            n = self.sizes[level]
            w = {"X": np.empty((n, c), np.float32), "r": np.empty((n, c), np.float32)}
            nc = self.sizes[level + 1]
            w["rc"] = np.empty((nc, c), np.float32)
            if self.visits[level] > 1 and level + 1 < len(self.levels):
                for name in ("c1", "v1", "rt", "v2"):
                    w[name] = np.empty((nc, c), np.float32)
            self._work[key] = w
        return self._work[key]

    def cycle(self, B, level: int = 0):
        """One cycle for A_level X = B from X = 0 on a block B (n, c) of columns (single precision,
        see the class; the sweeps and products pass over each matrix once for all columns,
        :mod:`cutfem.solvers.sparse_kernels`).  Returns the level's work array X (:meth:`_buffers`): valid until
        the next cycle on that level."""
        if level == len(self.levels):
            return np.ascontiguousarray(self._coarse_solve(B.astype(float)), dtype=np.float32)

        lv = self.levels[level]
        A = lv["A"]
        w = self._buffers(level, B.shape[1])
        X = w["X"]
        r = sparse_kernels.presmooth(A, X, B, w["r"], lv["chunks"])  # forward sweep from zero and its residual, one pass
        rc = sparse_kernels.matmul(lv["R"], r, out=w["rc"])
        xc = self.cycle(rc, level + 1)
        if "c1" in w:
            xc = self._krylov_correction(level, rc, xc, w)
        sparse_kernels.matmul(lv["P"], xc, out=X, accumulate=True)
        sparse_kernels.gauss_seidel(A, X, B, forward=False, chunks=lv["chunks"])
        return X

    def _krylov_correction(self, level, rc, first, w):
        """The K-cycle's coarse correction on level l + 1 (A_c = A_{l+1}, right-hand sides rc):
        two steps of flexible CG from zero, each preconditioned by a recursive cycle, ``first`` the
        first cycle's output.  Per column, with c1 = B rc, v1 = A_c c1, rho1 = c1.v1, a1 = c1.rc,
        rt = rc - (a1/rho1) v1, c2 = B rt, v2 = A_c c2, g = c2.v1, b = c2.v2, a2 = c2.rt and
        rho2 = b - g^2/rho1 (the energy of c2 made A_c-orthogonal to c1):

            x = (a1/rho1 - g a2/(rho1 rho2)) c1 + (a2/rho2) c2,

        the A_c-energy-minimal combination of the two cycles (where rho1 or rho2 is not positive,
        the term is dropped).  Scalars in double precision, vectors in single.  Returned in the
        work array c1."""

        Ac = self.levels[level + 1]["A"]
        c1, v1, rt, v2 = w["c1"], w["v1"], w["rt"], w["v2"]
        np.copyto(c1, first)  # the next cycle on level l + 1 overwrites its output
        rho1 = np.empty(rc.shape[1])
        sparse_kernels.matmul(Ac, c1, out=v1, dots=rho1)
        ok1 = rho1 > 0
        rho1 = np.where(ok1, rho1, 1.0)  # a zero column: its terms vanish below
        s1 = np.where(ok1, sparse_kernels.column_dots(c1, rc) / rho1, 0.0)
        np.multiply(v1, (-s1).astype(np.float32), out=rt)
        rt += rc
        c2 = self.cycle(rt, level + 1)
        b = np.empty(rc.shape[1])
        sparse_kernels.matmul(Ac, c2, out=v2, dots=b)
        g = np.where(ok1, sparse_kernels.column_dots(c2, v1), 0.0)
        rho2 = b - g * g / rho1
        ok2 = rho2 > 0
        s2 = np.where(ok2, sparse_kernels.column_dots(c2, rt) / np.where(ok2, rho2, 1.0), 0.0)
        s1 = s1 - g * s2 / rho1
        c1 *= s1.astype(np.float32)
        np.multiply(c2, s2.astype(np.float32), out=v2)
        c1 += v2
        return c1

    def apply(self, R, out=None, single: bool = False):
        """The preconditioner on the columns of R (n, c), returned in double precision (n, c), in
        ``out`` when given (an (n, c) float64 array).  ``single=True`` returns the finest level's
        float32 work array itself (R 2-D), valid until the next application: for a caller that
        reads it once (CG, whose dot products and directions take float32 blocks without a copy;
        at 4.7 million unknowns and three columns that saves writing and reading a 113 MB
        double-precision block an iteration)."""
        R = np.asarray(R)
        shape = R.shape
        R = R.reshape(shape[0], -1)
        key = ("B", R.shape[1])
        if key not in self._work:
            self._work[key] = np.empty(R.shape, np.float32)
        block = self._work[key]
        np.copyto(block, R, casting="same_kind")
        X = self.cycle(block)
        if single:
            return X
        if out is None:
            return X.astype(float).reshape(shape)
        np.copyto(out.reshape(X.shape), X)
        return out


def multigrid_hierarchy(space):
    """The geometric hierarchy of prolongations for the unknowns of ``space``, or None.

    * a space whose dofs are nodes of a structured Kuhn box (cut spaces on a
      :class:`~cutfem.geometry.box.StructuredBox`): the nested Kuhn lattices (:func:`lattice_hierarchy`);
    * a surface space whose mesh carries a doubly periodic grid (``mesh.grid = (n, m)``, set by
      :func:`~cutfem.geometry.surface_meshes.torus_mesh`): the coarser grids (:func:`grid_hierarchy`);
    * a vector field (:class:`~cutfem.fem.spaces.VectorSpace`): three copies of its scalar space's
      hierarchy, block-diagonal prolongations (and a product space: its fields' hierarchies, block-diagonal);
    * any other surface space (dofs = the nodes of ``space.mesh``): the Kuhn lattice of spacing
      twice the mean edge length, then the nested lattices (:func:`surface_hierarchy`).  This
      needs a roughly uniform mesh: where the edges are much shorter than the mean, the first
      coarse space is too coarse (the torus grid, whose edges vary 3:1, needs two to three times as
      many iterations this way as with its grid).
    """
    fields = getattr(space, "fields", None)
    if fields is not None:  # a product space: one hierarchy per field, block-diagonal prolongations
        hierarchies = [multigrid_hierarchy(f) for f in fields]
        return None if any(h is None for h in hierarchies) else _block_hierarchy(hierarchies)
    scalar = getattr(space, "scalar", None)
    if scalar is not None:  # a vector field: its components' hierarchy three times, kron(I_3, P)
        hierarchy = multigrid_hierarchy(scalar)
        return None if hierarchy is None else _repeated_hierarchy(hierarchy, space.components)
    ijk = lattice_indices(space)
    if ijk is not None:
        return lattice_hierarchy(ijk)
    mesh = getattr(space, "mesh", None)
    points = getattr(space, "dof_points", None)
    if mesh is None or points is None or len(points) != len(getattr(mesh, "points", ())):
        return None
    grid = getattr(mesh, "grid", None)
    if grid is not None:
        return grid_hierarchy(points, grid)
    return _mean_edge_hierarchy(points, np.asarray(mesh.triangles))


def _block_hierarchy(hierarchies):
    """The block-diagonal prolongations diag(P_1, ..., P_k) of the fields' hierarchies, level by
    level (a monolithic multigrid: the coarse operators P^T A P keep the couplings between fields)."""
    while True:
        Ps = [next(h, None) for h in hierarchies]
        if any(P is None for P in Ps):
            return
        yield sp.block_diag(Ps, format="csr")


def _repeated_hierarchy(hierarchy, c):
    """kron(I_c, P) of each prolongation P of ``hierarchy``: the hierarchy of a vector field of c
    components numbered component-major (each coarse space holds the coarse vector fields)."""
    for P in hierarchy:
        yield sp.block_diag([P] * c, format="csr")


def _mean_edge_hierarchy(points, triangles):
    edges = np.linalg.norm(points[triangles] - points[np.roll(triangles, 1, axis=1)], axis=2)
    yield from surface_hierarchy(points, 2.0 * float(edges.mean()))
