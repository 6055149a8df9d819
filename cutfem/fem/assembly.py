"""Vectorized assembly into scipy.sparse CSR and numpy vectors.

* :func:`gram`: E^T E for a row operator E (:func:`row_operator`), the route of every built-in
  symmetric positive semidefinite form (a quadrature of products, a jump times a jump): exactly
  symmetric by construction.
* :class:`SymmetricPattern`: a diagonal plus one value per pair of nodes written straight into a
  cached CSR structure (the closed-form matrices of a triangulated surface).
* :class:`PairSum`: the closed-form terms of a triangulated surface summed per node, edge and
  pair of opposite vertices, one CSR at the end.
* :class:`LatticeSum`: element matrices and Gram rows of Kuhn tets and face-adjacent pairs of them
  on a structured box, summed in 13 slots a node by compiled kernels (no sort, no sparse product).
* :class:`VectorSum`: a vector field's sum, the scalar one for the terms that act per component
  and 3 x 3 blocks per lattice slot for those that couple them; :func:`block_diagonal` kron(I_c, A).
* :func:`running_sum`: the one that a field's exact terms add into, if any.
* :func:`assemble_vector`: local vectors scattered by their dof numbers.

The quadrature route of integrands (:func:`cutfem.fem.forms.assemble`) sums its local blocks through
one COO matrix per form.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..geometry.numbering import index_dtype
from . import assembly_kernels

__all__ = ["LatticeSum", "PairSum", "VectorSum", "SymmetricPattern", "assemble_vector", "block_diagonal", "gram", "gram_sum",
           "row_operator", "running_sum"]

class SymmetricPattern:
    """CSR structure of a symmetric n x n matrix: the full diagonal and the undirected ``pairs``.

    For forms written as a diagonal plus one value per pair {i, j} (i != j), which is what the
    closed-form P1 matrices of a triangulated surface are: :meth:`matrix` writes the diagonal and
    each pair's value at (i, j) and (j, i), so the matrix is exactly symmetric and needs neither
    a sort nor a sum of duplicates per assembly.  Repeated pairs are allowed (their values are
    summed in the order given); ``presorted=True`` promises that the pairs are already unique
    with i < j in lexicographic order (e.g. the edges of a :class:`~cutfem.geometry.surface.SurfaceMesh`),
    which skips the sort.

    Row i holds, in increasing column order, the mirrors (i, j) of the pairs (j, i) with j < i,
    the diagonal, then the pairs (i, j) with j > i: one compiled pass over the pairs
    (:func:`cutfem.fem.assembly_kernels.symmetric_pattern`).
    """

    def __init__(self, pairs: np.ndarray, n: int, presorted: bool = False):

        pairs = np.asarray(pairs)
        if pairs.size == 0:
            pairs = np.zeros((0, 2), dtype=np.int64)  # no pairs: a diagonal matrix
        if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.dtype.kind not in "iu":
            raise ValueError(f"pairs must be an (m, 2) array of integer dof numbers, got shape {pairs.shape} and dtype {pairs.dtype}")
        pairs = np.ascontiguousarray(pairs, dtype=np.int32 if pairs.dtype.itemsize <= 4 and pairs.dtype.kind == "i" else np.int64)
        n = int(n)
        like = np.empty(0, dtype=index_dtype(n + 2 * len(pairs)))
        bad, why, *arrays = assembly_kernels.symmetric_pattern(pairs, np.int64(n), bool(presorted), like)
        if bad >= 0:
            if why == 0:
                raise ValueError(f"pairs must join two different dofs (the diagonal is always in the pattern); pair {bad} is "
                                 f"{tuple(int(v) for v in pairs[bad])}")
            raise ValueError(f"pairs must be dof numbers in [0, {n}), got pair {bad} = {tuple(int(v) for v in pairs[bad])}")
        self.indptr, self.indices, self.diagonal_position, self.upper_position, self.lower_position, slot = arrays
        self.n, self.n_pairs = n, len(self.upper_position)
        self._slot = None if presorted else slot

    @property
    def nnz(self) -> int:
        return len(self.indices)

    def matrix(self, diagonal: np.ndarray, values: np.ndarray) -> sp.csr_matrix:
        """The CSR matrix with ``diagonal`` (n,) and ``values`` (one per pair given to the
        constructor, repeated pairs summed) at (i, j) and (j, i)."""

        diagonal = np.ascontiguousarray(diagonal, dtype=float)
        values = np.ascontiguousarray(values, dtype=float)
        slot = self.indices[:0] if self._slot is None else self._slot
        if diagonal.shape != (self.n,) or values.shape != ((self.n_pairs,) if self._slot is None else self._slot.shape):
            raise ValueError(f"SymmetricPattern.matrix needs a diagonal of shape ({self.n},) and one value per pair given "
                             f"to the constructor, got {diagonal.shape} and {values.shape}")
        data = assembly_kernels.symmetric_data(self.diagonal_position, self.upper_position, self.lower_position, slot, diagonal,
                                      values, self.nnz)
        out = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
        out.has_sorted_indices = True
        out.has_canonical_format = True
        return out

class _RunningSum:
    """Arrays that the terms of one form add into, each times its own ``scale`` (its coefficient in
    the form: c_1 a_1 + c_2 a_2 summed into one set of arrays, one CSR pass, no sparse sum of
    matrices), made on the first term added."""

    def __init__(self):
        self._store = {}  # the arrays

    @property
    def used(self) -> bool:
        """Whether any term was added (the arrays exist): a form whose summed terms all went
        elsewhere allocates nothing and adds no matrix."""
        return bool(self._store)


class PairSum(_RunningSum):
    """A symmetric matrix on the nodes of a triangulated surface, summed from terms given as a
    diagonal (n,), one value per mesh edge (E,) and, for terms that reach across an edge (the edge
    penalty), one value per pair of vertices opposite an edge (E,).

    ``space`` a :class:`~cutfem.fem.spaces.SurfaceP1Space`.  Terms are added times their ``scale``, so
    :func:`cutfem.fem.forms.assemble` sums c_1 a_1 + c_2 a_2 + ... (mass, stiffness, edge penalty) into
    one set of arrays, and
    :meth:`matrix` writes one CSR matrix: on the node graph (:meth:`~cutfem.fem.spaces.SurfaceP1Space.node_pattern`)
    or, when a term gave opposite pairs, on the edge stencil
    (:meth:`~cutfem.fem.spaces.SurfaceP1Space.edge_stencil_pattern`), whose first E pairs are the edges.
    No sparse sum of matrices: at 768 x 384 the sum M + tau J_E of two CSR matrices cost 50 ms.
    """

    def __init__(self, space):
        super().__init__()
        self.space = space

    def add(self, diagonal, edges, opposite=None, scale=1.0) -> "PairSum":
        """Add ``scale`` * (``diagonal`` (n,), ``edges`` (E,), ``opposite`` (E,) or None)."""
        st, space = self._store, self.space
        n, E = space.n_dofs, space.mesh.n_edges
        if not st:
            st.update(diagonal=np.zeros(n), edges=np.zeros(E))
        if opposite is not None and "opposite" not in st:
            st["opposite"] = np.zeros(E)
        for key, values, size in (("diagonal", diagonal, n), ("edges", edges, E), ("opposite", opposite, E)):
            if values is None:
                continue
            values = np.asarray(values, dtype=float)
            if values.shape != (size,):
                raise ValueError(f"PairSum.add: {key} must have shape ({size},), got {values.shape}")
            st[key] += values if scale == 1.0 else scale * values
        return self

    def matrix(self) -> sp.csr_matrix:
        """The CSR matrix of the terms added, on the smallest of the two patterns that holds them."""
        st, space = self._store, self.space
        if "opposite" in st:
            return space.edge_stencil_pattern().matrix(st["diagonal"], np.concatenate([st["edges"], st["opposite"]]))
        return space.node_pattern().matrix(st["diagonal"], st["edges"])

class LatticeSum(_RunningSum):
    """A symmetric matrix over nodes of a structured box, summed from element matrices and Gram rows
    of tets and face-adjacent pairs of tets, in 13 slots a node (compiled: :mod:`cutfem.fem.assembly_kernels`).

    ``node_ids`` (n,) the increasing background ids of the dofs, ``box`` the
    :class:`~cutfem.geometry.box.StructuredBox`.  Two nodes of one Kuhn tet, or of two tets sharing a face,
    differ by one of 13 lattice vectors (:func:`~cutfem.geometry.box.kuhn_neighbour_offsets`), so the entry
    (a, b), a < b, has the slot 13 a + the rank of ids[b] - ids[a] among the box's
    :attr:`~cutfem.geometry.box.StructuredBox.neighbour_id_offsets`; the ranks follow the column order, and
    :meth:`matrix` writes the CSR arrays from the slots (:func:`cutfem.fem.assembly_kernels.lattice_csr`): no sort, no sparse product,
    exactly symmetric.  Pairs whose sum is exactly zero are left out of the pattern (as a sparse
    product leaves them out: on a uniform lattice the P1 stiffness of the diagonal edges cancels);
    the diagonal is always stored.  Memory: 13 slots of 12 bytes a node while summing, allocated
    on the first term added.  Terms are added times their ``scale``: :func:`cutfem.fem.forms.assemble`
    sums all the lattice terms of a form, c_1 a_1 + c_2 a_2 + ..., into one set of slots.

    Measured at spacing 0.0125 on the cut torus (853k cut tets, 293k nodes, 1.3M interior faces):
    the piece mass 0.5 s by the former numpy edge sums, the face penalty 1.3 s by rows and a sparse
    Gram product.
    """

    def __init__(self, node_ids, box):
        self.ids = np.ascontiguousarray(node_ids, dtype=np.int64)
        offsets = box.neighbour_id_offsets
        self.code = np.full(int(offsets[-1]) + 1, -1, dtype=np.int8)  # node-id difference -> slot rank
        self.code[offsets] = np.arange(len(offsets))
        self._width = len(offsets)
        super().__init__()

    def _slots(self):
        """(sums (13 n,), partner (13 n,), diagonal (n,)), allocated on first use."""
        if not self._store:
            n, S = len(self.ids), self._width
            self._store.update(sums=np.zeros(S * n), partner=np.zeros(S * n, dtype=index_dtype(n)),
                               diagonal=np.zeros(n))
        st = self._store
        return st["sums"], st["partner"], st["diagonal"]

    def _check(self, outside, what):
        if outside:
            raise ValueError(f"LatticeSum: {outside} pairs of dofs in the {what} are not nodes of one Kuhn tet or of two "
                             "face-adjacent tets; sum these terms as a Gram product (cutfem.fem.assembly.gram) instead")

    def add_elements(self, dofs, edges, diagonal, types=None, weights=None, elements=None, scale=1.0) -> "LatticeSum":
        """Add symmetric 4 x 4 element matrices on the tets' dofs ``dofs`` (m, 4), given by their
        entries on the local edges (:data:`~cutfem.geometry.numbering.TET_EDGES` order) and on the diagonal: rows
        of the tables ``edges`` (L, 6) and ``diagonal`` (L, 4), row ``types[k]`` for element k, or
        with ``types`` None row k (L = m), or the one row of a one-row table; times ``weights[k]``
        when given; for the elements ``elements`` only when given; times ``scale``
        (:func:`cutfem.fem.assembly_kernels.lattice_add_elements`: no per-element arrays of the entries)."""

        # the empty placeholders take the types of the arrays they stand for (element ids int64, Kuhn
        # types int8): one compiled signature of the kernel whichever are given
        none_i, none_t, none_f = np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0)
        edges, diagonal = np.ascontiguousarray(edges, dtype=float), np.ascontiguousarray(diagonal, dtype=float)
        dofs = np.ascontiguousarray(dofs)
        elements = none_i if elements is None else np.ascontiguousarray(elements)
        owners = elements[:, None] if len(elements) else None  # None: element e owns row e of dofs
        self._check(assembly_kernels.lattice_add_elements(
            self.ids, self.code, dofs, elements, edges.reshape(-1, 6), diagonal.reshape(-1, 4),
            none_t if types is None else np.ascontiguousarray(types),
            none_f if weights is None else np.ascontiguousarray(weights, dtype=float), float(scale), *self._slots(),
            assembly_kernels.scatter_chunks(dofs, owners)),
            "element matrices")
        return self

    def add_pieces(self, vertices, triangles, tets_of, areas, points, tets, table, types, dofs, scale=1.0) -> "LatticeSum":
        """Add ``scale`` times the exact P1 mass matrices of triangles lying in tets (the pieces of S_h), triangle by
        triangle (:func:`cutfem.fem.assembly_kernels.lattice_add_pieces`, same arguments; the triangles in the chunks of
        :func:`cutfem.assembly_kernels.scatter_chunks`, on all cores)."""

        c = np.ascontiguousarray
        tets_of, dofs = c(tets_of), c(dofs)
        self._check(assembly_kernels.lattice_add_pieces(self.ids, self.code, c(vertices, dtype=float), c(triangles), tets_of,
                                               c(areas, dtype=float), c(points, dtype=float), c(tets), c(table, dtype=float),
                                               c(types), dofs, float(scale), *self._slots(),
                                               assembly_kernels.scatter_chunks(dofs, tets_of[:, None])),
                    "pieces")
        return self

    def add_rows(self, dofs, values, scale=1.0) -> "LatticeSum":
        """Add ``scale`` times the Gram matrix sum_r c_r c_r^T of the rows ``values`` (r, k) on ``dofs`` (r, k) (a dof
        repeated in a row counts with the sum of its values), as :func:`gram` does."""

        dofs = np.ascontiguousarray(dofs)
        self._check(assembly_kernels.lattice_add_rows(self.ids, self.code, dofs, np.ascontiguousarray(values, dtype=float),
                                             float(scale), *self._slots(),
                                             assembly_kernels.scatter_chunks(dofs, None)),
                    "rows")
        return self

    def add_face_jumps(self, pairs, opposite, factors, volumes, dofs, table, types, scale=1.0) -> "LatticeSum":
        """Add ``scale`` times the Gram matrix of the normal-gradient jumps across the faces between the tets ``pairs``
        (F, 2) with the opposite vertices ``opposite`` (F, 2), face by face
        (:func:`cutfem.fem.assembly_kernels.lattice_add_face_jumps`, same arguments; the faces in the chunks of
        :func:`cutfem.assembly_kernels.scatter_chunks`, on all cores)."""

        pairs = np.ascontiguousarray(pairs)
        self._check(assembly_kernels.lattice_add_face_jumps(self.ids, self.code, pairs,
                                                   np.ascontiguousarray(opposite), np.ascontiguousarray(factors, dtype=float),
                                                   np.ascontiguousarray(volumes, dtype=float), dofs, table, types, float(scale),
                                                   *self._slots(), assembly_kernels.scatter_chunks(dofs, pairs)), "face jump rows")
        return self

    def matrix(self) -> sp.csr_matrix:
        """The CSR matrix of the sums (canonical: sorted, no duplicates)."""

        sums, partner, diagonal = self._slots()
        n = len(diagonal)
        nnz = assembly_kernels.lattice_nnz(sums, n)
        index = index_dtype(nnz)
        indptr, indices, data = np.empty(n + 1, dtype=index), np.empty(nnz, dtype=index), np.empty(nnz)
        assembly_kernels.lattice_csr(sums, partner, diagonal, indptr, indices, data)
        out = sp.csr_matrix((data, indices, indptr), shape=(n, n))
        out.has_sorted_indices = True
        out.has_canonical_format = True
        return out


class VectorSum(_RunningSum):
    """The running sum of a vector field (:class:`~cutfem.fem.spaces.VectorSpace`, 3 n unknowns
    component-major): the terms that act component by component add into ``scalar``, the running
    sum of the scalar field (a :class:`LatticeSum` or a :class:`PairSum`), and count I_3 times;
    the terms that couple the components (elasticity) add 3 x 3 blocks of element matrices per
    lattice slot (:meth:`add_block_elements`, on a structured box).  :meth:`matrix` writes one CSR
    matrix: kron(I_3, the scalar matrix) built as three diagonal blocks, or with blocks all of them
    in one pass (:func:`cutfem.fem.assembly_kernels.vector_lattice_csr`)."""

    def __init__(self, scalar):
        super().__init__()
        self.scalar = scalar

    @property
    def used(self) -> bool:
        return self.scalar.used or bool(self._store)

    @property
    def lattice(self) -> bool:
        """Whether element blocks can be added (the scalar sum is a :class:`LatticeSum`)."""
        return isinstance(self.scalar, LatticeSum)

    def add_block_elements(self, dofs, blocks, types=None, weights=None, scale=1.0) -> "VectorSum":
        """Add ``scale`` times symmetric element matrices of the vector field on the tets' scalar dofs
        ``dofs`` (m, 4): ``blocks`` (L, 4, 4, 3, 3), K[(l, node i), (k, node j)] at [r, i, j, l, k],
        row r = ``types[t]`` of element t (or r = t with ``types`` None), times ``weights[t]``
        (:func:`cutfem.fem.assembly_kernels.lattice_add_blocks`)."""
        lattice = self.scalar
        _, partner, _ = lattice._slots()
        n = len(lattice.ids)
        if not self._store:
            self._store.update(bsums=np.zeros(9 * lattice._width * n), bdiag=np.zeros(9 * n))
        dofs = np.ascontiguousarray(dofs)
        blocks = np.ascontiguousarray(blocks, dtype=float).reshape(-1, 4, 4, 3, 3)
        none_t, none_f = np.zeros(0, np.int8), np.zeros(0)
        lattice._check(assembly_kernels.lattice_add_blocks(
            lattice.ids, lattice.code, dofs, blocks, none_t if types is None else np.ascontiguousarray(types),
            none_f if weights is None else np.ascontiguousarray(weights, dtype=float), float(scale), partner,
            self._store["bsums"], self._store["bdiag"], assembly_kernels.scatter_chunks(dofs, None)), "element blocks")
        return self

    def matrix(self) -> sp.csr_matrix:
        if not self._store:
            return block_diagonal(self.scalar.matrix(), 3)
        sums, partner, diag = self.scalar._slots()
        n = len(diag)
        width = 3 * n * (2 * self.scalar._width + 1) * 3
        indptr, indices, data = assembly_kernels.vector_lattice_csr(sums, self._store["bsums"], partner, diag,
                                                                    self._store["bdiag"], n, index_dtype(width))
        out = sp.csr_matrix((data, indices, indptr), shape=(3 * n, 3 * n))
        out.has_sorted_indices = True
        out.has_canonical_format = True
        return out


def block_diagonal(A, c: int) -> sp.csr_matrix:
    """kron(I_c, A) of a square matrix A as CSR, written from A's arrays (c copies, the columns
    shifted): the matrix of a term acting on each of c components alike."""
    A = sp.csr_matrix(A)
    n, nnz = A.shape[0], A.nnz
    index = index_dtype(max(c * n, c * nnz))
    indptr = np.concatenate([np.zeros(1, dtype=index)] + [(A.indptr[1:] + k * nnz).astype(index) for k in range(c)])
    indices = np.concatenate([(A.indices + k * n).astype(index) for k in range(c)])
    out = sp.csr_matrix((np.tile(A.data, c), indices, indptr), shape=(c * n, c * n))
    out.has_sorted_indices = A.has_sorted_indices
    return out


def running_sum(space):
    """The running sum that the exact terms of a form add into on ``space``: a :class:`PairSum` on a
    triangulated surface (:class:`~cutfem.fem.spaces.SurfaceP1Space`), a :class:`LatticeSum` when the
    dofs are nodes of a structured box (a cut space on a :class:`~cutfem.geometry.box.StructuredBox`),
    a :class:`VectorSum` around either for a vector field of such a space, else None."""
    scalar = getattr(space, "scalar", None)
    if scalar is not None:
        inner = running_sum(scalar)
        return None if inner is None else VectorSum(inner)
    if hasattr(space, "edge_stencil_pattern"):
        return PairSum(space)
    es = getattr(space, "elements", None)
    if getattr(es, "kuhn_types", None) is None or getattr(space, "node_ids", None) is None:
        return None
    return LatticeSum(space.node_ids, es.background)


def assemble_vector(dofs: np.ndarray, local: np.ndarray, n: int, out: np.ndarray | None = None) -> np.ndarray:
    """Assemble local vectors (m, k) or (m, k, c) with dof numbers (m, k) into (n,) or (n, c): added
    into ``out`` when given (a float64 array of that shape, e.g. a view of a larger vector), so
    that a form assembled block by block touches one vector, not one per block (at 2.7 million
    unknowns and 274 blocks a new (n,) vector a block, and its sum, took more than a second).
    By :func:`cutfem.fem.assembly_kernels.scatter_add`, in element order."""

    dofs = np.asarray(dofs)
    local = np.asarray(local, dtype=float)
    m, k = dofs.shape[0], dofs.shape[-1]
    shape = (n,) + local.shape[2:]
    if out is None:
        out = np.zeros(shape)
    elif out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float64 array of shape {shape}, got {out.shape} {out.dtype}")
    # out.reshape is a view of the contiguous out: the kernel writes into out
    assembly_kernels.scatter_add(np.ascontiguousarray(dofs).reshape(m, k), np.ascontiguousarray(local).reshape(m, k, -1), out.reshape(n, -1))
    return out

def row_operator(dofs: np.ndarray, values: np.ndarray, n: int, overwrite: bool = False) -> sp.csr_matrix:
    """The sparse (r x n) matrix E whose row i has ``values[i]`` at columns ``dofs[i]`` (r, k);
    repeated columns in a row are summed.

    ``overwrite=True`` lets E take over ``values`` (float64, C-contiguous) and ``dofs`` (of E's index
    type, C-contiguous) and sort them in place, instead of copying them (for temporaries of the
    caller: a copy of the rows of a million elements is 100 MB).
    """
    dofs = np.asarray(dofs)
    r, k = dofs.shape
    # int32 indices whenever they fit (scipy then stays in int32: less memory traffic in the products)
    index = index_dtype(max(n, r * k))
    # sorting the rows below works in place: on the caller's arrays only when it allows it
    if overwrite:
        data = np.ascontiguousarray(values, dtype=float).reshape(-1)
        cols = np.ascontiguousarray(dofs, dtype=index).reshape(-1)
    else:
        data = np.array(values, dtype=float).reshape(-1)
        cols = dofs.reshape(-1)
        if cols.dtype != index or np.may_share_memory(cols, dofs):
            cols = cols.astype(index)
    E = sp.csr_matrix((data, cols, k * np.arange(r + 1, dtype=index)), shape=(r, n))
    E.sum_duplicates()
    return E

#: rows of E per sparse product in :func:`gram`: larger operators are summed block by block
GRAM_ROWS = 1 << 21

def gram(dofs: np.ndarray, values: np.ndarray, n: int, overwrite: bool = False) -> sp.csr_matrix:
    """E^T E for the row operator E of (dofs, values): the matrix of the form sum_i (e_i.u)(e_i.v).

    Every symmetric positive semidefinite form of cutfem is a sum of squares of this kind (a
    quadrature of products, a jump times a jump), so it is assembled by one sparse product instead
    of a scatter of k x k blocks.  The product accumulates the contributions to (i, j) and to (j, i)
    over the same rows in the same order, and each product commutes, so the result is exactly
    symmetric.  ``overwrite``: see :func:`row_operator`.

    Above :data:`GRAM_ROWS` rows, E^T E = sum_b E_b^T E_b over blocks of rows, each product exactly
    symmetric and so their sum: E and its transpose then exist one block at a time (for the
    stiffness of 1.6 million tets, 4.8 million rows, they took 0.5 GB at once).
    """
    if len(dofs) > GRAM_ROWS:
        take = (lambda a: a) if overwrite else np.array  # blocks are sorted in place: copies unless allowed
        return gram_sum(((take(dofs[s : s + GRAM_ROWS]), take(values[s : s + GRAM_ROWS])) for s in range(0, len(dofs), GRAM_ROWS)), n)
    return _gram(dofs, values, n, overwrite)

def gram_sum(blocks, n: int) -> sp.csr_matrix:
    """sum_b E_b^T E_b over the row operators of ``blocks``, an iterable of (dofs, values) (see
    :func:`gram`; each block's arrays are handed over, so a generator can build them one block at a
    time and only one block's rows exist at once).  Exactly symmetric."""
    total = None
    for dofs, values in blocks:
        part = _gram(dofs, values, n, True)
        total = part if total is None else total + part
    return sp.csr_matrix((n, n)) if total is None else total.tocsr()

def _gram(dofs, values, n, overwrite):
    E = row_operator(dofs, values, n, overwrite)
    C = E.tocsc()  # the CSC arrays of E are the CSR arrays of E^T
    Et = sp.csr_matrix((C.data, C.indices, C.indptr), shape=(n, E.shape[0]))
    return (Et @ E).tocsr()
