"""Structured backgrounds: the box of cubes split into Kuhn tetrahedra, numbered arithmetically.

A :class:`StructuredBox` is a tetrahedral mesh of an axis-aligned box made of cubes (cuboids), each
split into the six Kuhn tetrahedra that share the main diagonal; the split is the same in every
cube, so the mesh is conforming.  A structured box never needs to store its whole point or tet
arrays: the band search (:mod:`cutfem.geometry.band_search`) asks it only for the cells near the
surface; ``points``/``tets`` are built lazily if a user wants the whole mesh.  Its edges and faces
have an arithmetic numbering (lowest node and lattice direction: :data:`KUHN_EDGE_CODES`,
:func:`kuhn_face_keys`) in the order of their sorted node ids, which the cut uses instead of
sorting.  :func:`structured_box` makes one from its corners and a spacing or cell counts.

Mesh size: the global value ``h = N**(-1/3)`` (N = number of background nodes), as in docs/math.md §2.
"""

from __future__ import annotations

import math
from fractions import Fraction
from functools import cached_property, lru_cache

import numpy as np

from .keys import unique_keys
from .mesh import TetMesh
from .numbering import CUBE_CORNERS, TET_FACES
from . import mesh_kernels

__all__ = [
    "StructuredBox",
    "SPACING_TOLERANCE",
    "structured_box",
    "KUHN_TETS",
    "KUHN_GRADIENTS",
    "KUHN_CORNER_COUNTS",
    "KUHN_EDGE_CODES",
    "kuhn_face_keys",
    "kuhn_face_pairs",
    "kuhn_neighbour_offsets",
]

# The six Kuhn tetrahedra of the unit cube: each follows a monotone path 000 -> 111 along the
# axes in one of the 3! orders.  Corner c of the cube has offset ((c>>0)&1, (c>>1)&1, (c>>2)&1).
_PERMS = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]


def _kuhn_local_tets() -> np.ndarray:
    tets = []
    corner = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], float)
    for perm in _PERMS:
        path = [0]
        code = 0
        for axis in perm:
            code |= 1 << axis
            path.append(code)
        a, b, c, d = corner[path]
        if np.linalg.det(np.array([b - a, c - a, d - a])) < 0:
            path[2], path[3] = path[3], path[2]
        tets.append(path)
    return np.array(tets, dtype=np.int64)


KUHN_TETS = _kuhn_local_tets()  # (6, 4) local cube-corner indices, positively oriented


def _kuhn_reference_gradients() -> np.ndarray:
    """(6, 4, 3) gradients of the barycentric coordinates of the six Kuhn tets of the unit cube.

    Kuhn tet l has the vertices CUBE_CORNERS[KUHN_TETS[l]]; its edge matrix has entries 0 and 1
    and determinant 1 (it is positively oriented), so the gradients (rows of its inverse, and minus
    their sum) have entries -1, 0, 1 and are exact in floating point."""
    grads = np.empty((6, 4, 3))
    for l, tet in enumerate(KUHN_TETS):
        x = CUBE_CORNERS[tet].astype(float)
        inv = np.rint(np.linalg.inv((x[1:] - x[0]).T))
        grads[l, 1:] = inv
        grads[l, 0] = -inv.sum(axis=0)
    return grads


KUHN_GRADIENTS = _kuhn_reference_gradients()

KUHN_CORNER_COUNTS = ((np.arange(256)[:, None] >> np.arange(8)) & 1)[:, KUHN_TETS].sum(axis=2).astype(np.int8)
"""(256, 6) how many nodes of Kuhn tet l are among the cube corners of a set (bit c for corner c)."""


# Lattice numbering of the edges and faces of a structured box.  The nodes of a Kuhn tet form a
# chain for the componentwise order of their cube corners (a monotone path 000 -> 111), so an edge
# of the lattice is {v, v + e_S} and a face {v, v + e_A, v + e_A + e_B}: v its lowest node, S, A, B
# nonempty sets of axes (A and B disjoint), e_S the sum of their unit steps.  With the code
# c(S) = sum of 2**axis over S (1..7), the node above v along S has the id v + o(c(S)),
# o(c) = (c & 1) + (nx + 1) ((c >> 1) & 1) + (nx + 1)(ny + 1) (c >> 2), which increases with c
# (nx, ny >= 1).  So (v, c(S)) numbers the edges, (v, c(A), c(A u B)) the faces, and ordering them
# by these integers orders them by their sorted node ids: no sort of node triples is needed.
KUHN_EDGE_CODES = (KUHN_TETS[:, :, None] ^ KUHN_TETS[:, None, :]).astype(np.int8)
"""(6, 4, 4) c(S) of the edge between local nodes i and j of Kuhn tet l (0 on the diagonal)."""

# the 12 face types (c(A), c(A u B)), in increasing order
_FACE_TYPES = sorted((a, a | b) for a in range(1, 8) for b in range(1, 8) if a & b == 0)


def _kuhn_face_tables():
    """(6, 4) local node of the lowest corner of face k (opposite to node k) of Kuhn tet l, and
    (6, 4) the rank of the face's type (c(A), c(A u B)) in :data:`_FACE_TYPES`."""
    low = np.zeros((6, 4), dtype=np.int8)
    kind = np.zeros((6, 4), dtype=np.int8)
    for l, tet in enumerate(KUHN_TETS):
        for k, face in enumerate(TET_FACES):
            order = np.argsort(tet[face])
            c0, c1, c2 = tet[face][order]
            low[l, k] = face[order[0]]
            kind[l, k] = _FACE_TYPES.index((c1 ^ c0, c2 ^ c0))
    return low, kind


_KUHN_FACE_LOW, _KUHN_FACE_TYPE = _kuhn_face_tables()


@lru_cache(maxsize=1)
def kuhn_neighbour_offsets() -> np.ndarray:
    """(13, 3) the lattice vectors q - p between two nodes p != q of one Kuhn tet or of two Kuhn tets
    sharing a face, oriented with (dz, dy, dx) lexicographically positive (q after p in the node
    numbering of a box), in that order: the 7 edge directions of the Kuhn lattice and the 6 vectors
    between the opposite vertices of face-adjacent tets.  Enumerated from the tets of the 27 cells
    around the cell at the origin and each tet of that cell (every pair of face-adjacent tets is one
    of those up to translation)."""
    cells = np.array([(x, y, z) for z in (-1, 0, 1) for y in (-1, 0, 1) for x in (-1, 0, 1)])
    tets = (cells[:, None, None, :] + CUBE_CORNERS[KUHN_TETS][None]).reshape(-1, 4, 3)
    as_sets = [frozenset(map(tuple, t)) for t in tets]
    found = set()
    for a in as_sets[13 * 6 : 14 * 6]:  # the six tets of cell (0, 0, 0)
        for b in as_sets:
            if len(a & b) >= 3:  # the same tet or a shared face
                for p in a | b:
                    for q in a | b:
                        d = tuple(int(v) for v in np.subtract(q, p))
                        if d[::-1] > (0, 0, 0):
                            found.add(d)
    return np.array(sorted(found, key=lambda d: d[::-1]), dtype=np.int64)


def kuhn_face_keys(tets: np.ndarray, kuhn: np.ndarray) -> np.ndarray:
    """Keys of the faces of tets of a structured box: ``12 v + type`` (4m,), with v the node
    number (in ``tets``) of the face's lowest lattice node and type in 0..11 its (c(A), c(A u B))
    rank (see :data:`KUHN_EDGE_CODES`).  Row 4t + k is the face opposite to local vertex k of tet t.

    ``tets`` (m, 4) node numbers of Kuhn tets in their :data:`KUHN_TETS` vertex order (any node
    numbering of the box's nodes), ``kuhn`` (m,) their Kuhn type (background tet id % 6).  Equal
    faces have equal keys, and when the node numbers increase with the background ids the keys
    increase with the sorted node triples of :func:`~cutfem.geometry.keys.tet_face_keys`: grouping them gives the same
    faces in the same order, with keys below 12 n (n nodes) instead of three columns.
    """

    tets = np.ascontiguousarray(tets)
    out = np.empty(4 * len(tets), dtype=np.int64)
    mesh_kernels.kuhn_face_keys(tets, np.ascontiguousarray(kuhn).reshape(-1), _KUHN_FACE_LOW, _KUHN_FACE_TYPE, out)
    return out


def kuhn_face_pairs(tets: np.ndarray, kuhn: np.ndarray, n_nodes: int):
    """The faces shared by two of the Kuhn tets ``tets`` (m, 4) (node numbers below ``n_nodes``,
    types ``kuhn``): ``(pairs (F, 2), opposite (F, 2) int8)`` as :func:`cutfem.geometry.markers.interior_facets`
    returns them, the keys of :func:`kuhn_face_keys` grouped without making them
    (:func:`cutfem.geometry.mesh_kernels.kuhn_face_pairs`)."""

    return mesh_kernels.kuhn_face_pairs(tets, np.asarray(kuhn).reshape(-1), _KUHN_FACE_LOW, _KUHN_FACE_TYPE, 12 * int(n_nodes))


#: :func:`structured_box` keeps the box when (upper - lower) / spacing is within this relative
#: amount of a whole number, and :class:`StructuredBox` accepts a spacing that differs from
#: (upper - lower) / cells by this relative amount (plus the round-off of the corners): round-off
#: of a spacing written in decimal, never a different mesh.
SPACING_TOLERANCE = 1e-9

#: the largest node or tet id of a structured box: ids are int64
_LARGEST_ID = 2**63 - 1


def _readable_count(n) -> str:
    """An exact (Python) integer for a message: '3,000,000' below a billion, '2.70e+19' above, at
    any size (a float would overflow past 1.8e308 and int64 wraps past 9.2e18)."""
    n = int(n)
    if abs(n) < 10**9:
        return f"{n:,}"
    digits = str(abs(n))
    return f"{'-' if n < 0 else ''}{digits[0]}.{digits[1:3]}e+{len(digits) - 1}"


def _whole_cells(cells) -> tuple:
    """The three cell counts as Python ints (exact, whatever their size)."""
    a = np.asarray(cells)
    if a.dtype.kind == "f":
        return tuple(int(v) for v in np.broadcast_to(a, (3,)))
    return tuple(int(v) for v in np.broadcast_to(a, (3,)).tolist())


def _check_box_size(cells, what: str, fix: str) -> None:
    """Refuse a structured box whose node or tet ids do not fit in int64 (more than 9.2e18 nodes or
    tets) with :class:`cutfem.memory.InsufficientMemoryError`, stating the real counts (exact
    Python integers) and the memory of the band search's node bitmap (a quarter byte a node, the
    least any use of the box needs).  Such a box cannot be numbered, let alone held."""
    n_points = math.prod(c + 1 for c in cells)
    n_tets = 6 * math.prod(cells)
    if max(n_points, n_tets) <= _LARGEST_ID:
        return
    from ..memory import BYTES_PER_BOX_NODE, InsufficientMemoryError, available_memory, format_bytes

    available, source = available_memory()
    need = n_points * int(4 * BYTES_PER_BOX_NODE) // 4  # exact: BYTES_PER_BOX_NODE is a quarter byte
    raise InsufficientMemoryError(
        f"{what} has {_readable_count(n_points)} nodes and {_readable_count(n_tets)} tets: their ids do not fit in "
        f"64-bit integers (at most {_readable_count(_LARGEST_ID)}), and the band search's node bitmap alone needs about "
        f"{_readable_count(need)} bytes of memory, more than the {format_bytes(available)} available ({source}); {fix}"
    )


def _spacing_whose_ids_fit(extent) -> float:
    """The smallest spacing at which a box of the given side lengths has fewer than 2**63 / 6 cells
    (so that its tet ids fit in int64), from logarithms (the product of the sides may overflow)."""
    logs = sum(math.log(float(e)) for e in extent)
    return math.exp((logs + math.log(6.0) - math.log(_LARGEST_ID)) / 3.0)


class StructuredBox(TetMesh):
    """Tetrahedral mesh of the box ``[lower, upper]`` with ``cells = (nx, ny, nz)`` cuboids, six
    Kuhn tets per cuboid (all sharing the cuboid's main diagonal).

    Node (i, j, k) has id ``i + (nx+1) * (j + (ny+1) * k)`` and coordinates
    ``lower + (i, j, k) * spacing``; cell (i, j, k) has id ``i + nx * (j + ny * k)``; tet
    ``6 * cell + l`` is the l-th Kuhn tet of the cell (:data:`KUHN_TETS`).  The whole ``points`` and
    ``tets`` arrays are built only when asked for; :meth:`cell_tets` and :meth:`node_coordinates`
    serve any subset.
    """

    def __init__(self, lower, upper, cells, spacing=None):
        lower = np.asarray(lower, dtype=float).reshape(3)
        upper = np.asarray(upper, dtype=float).reshape(3)
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
            raise ValueError("box corners must be finite")
        if np.any(upper <= lower):
            raise ValueError(f"box must have upper > lower in every axis, got lower={lower}, upper={upper}")
        cells = _whole_cells(cells)
        if min(cells) < 1:
            raise ValueError(f"need at least one cell per axis, got cells={list(cells)}")
        _check_box_size(cells, f"a structured box of {' x '.join(_readable_count(c) for c in cells)} cells",
                        "give fewer cells")
        cells = np.array(cells, dtype=np.int64)
        self.lower, self.upper, self.cells = lower, upper, cells
        # the spacing as requested when known (structured_box), not recomputed from the corners
        implied = (upper - lower) / cells
        if spacing is None:
            self.spacing = implied
        else:
            self.spacing = np.broadcast_to(np.asarray(spacing, float), (3,)).copy()
            # node (i, j, k) is at lower + (i, j, k) * spacing: the last one must be upper (to round-off)
            slack = SPACING_TOLERANCE * np.abs(self.spacing) + 8 * np.finfo(float).eps * np.maximum(np.abs(lower), np.abs(upper)) / cells
            if not (np.all(np.isfinite(self.spacing)) and np.all(np.abs(implied - self.spacing) <= slack)):
                raise ValueError(
                    f"spacing={self.spacing.tolist()} does not match the corners and cells: lower + cells * spacing = "
                    f"{(lower + cells * self.spacing).tolist()}, not upper = {upper.tolist()}. The consistent spacing "
                    f"is (upper - lower) / cells = {implied.tolist()}: pass that, or leave spacing out, or use "
                    "structured_box(lower, upper, spacing=...), which fits the cells to a spacing"
                )
        self.node_shape = cells + 1

    # sizes without building anything
    @property
    def n_points(self) -> int:
        return math.prod(int(n) for n in self.node_shape)  # Python ints: exact at any size

    @property
    def n_cells(self) -> int:
        return math.prod(int(c) for c in self.cells)

    @property
    def n_tets(self) -> int:
        return 6 * self.n_cells

    @property
    def n_used_points(self) -> int:  # type: ignore[override]
        return self.n_points  # every node of the lattice is a corner of a tet

    @property
    def bounds(self):
        return self.lower.copy(), self.upper.copy()

    # ids and coordinates of any subset
    def node_index(self, ids) -> np.ndarray:
        """(k, 3) integer (i, j, k) of node ids."""
        ids = np.asarray(ids, dtype=np.int64)
        nx1, ny1 = self.node_shape[0], self.node_shape[1]
        return np.stack([ids % nx1, (ids // nx1) % ny1, ids // (nx1 * ny1)], axis=-1)

    def node_id(self, ijk) -> np.ndarray:
        ijk = np.asarray(ijk, dtype=np.int64)
        return ijk[..., 0] + self.node_shape[0] * (ijk[..., 1] + self.node_shape[1] * ijk[..., 2])

    def coordinates(self, ijk) -> np.ndarray:
        """Coordinates of integer node indices ``ijk`` (..., 3): ``lower + ijk * spacing``."""
        return self.lower + np.asarray(ijk) * self.spacing

    @cached_property
    def neighbour_id_offsets(self) -> np.ndarray:
        """(13,) increasing node-id differences of :func:`kuhn_neighbour_offsets` on this box: two
        nodes of one tet or of two face-adjacent tets differ in id by one of them."""
        return np.sort(self.node_id(kuhn_neighbour_offsets()))

    def node_coordinates(self, ids) -> np.ndarray:
        """(..., 3) coordinates of node ids (...): :meth:`coordinates` of :meth:`node_index`, in one
        compiled pass (:func:`cutfem.geometry.mesh_kernels.box_node_coordinates`; numpy's integer divisions and
        stacks took 0.55 s for the 5.2 million nodes of the solid torus at spacing 0.01)."""

        ids = np.asarray(ids, dtype=np.int64)
        flat = np.ascontiguousarray(ids.reshape(-1))
        out = np.empty((len(flat), 3))
        mesh_kernels.box_node_coordinates(flat, int(self.node_shape[0]), int(self.node_shape[1]),
                                     np.asarray(self.lower, dtype=float), np.asarray(self.spacing, dtype=float), out)
        return out.reshape(ids.shape + (3,))

    def cell_index(self, cell_ids) -> np.ndarray:
        c = np.asarray(cell_ids, dtype=np.int64)
        nx, ny = self.cells[0], self.cells[1]
        return np.stack([c % nx, (c // nx) % ny, c // (nx * ny)], axis=-1)

    def cell_corner_ids(self, cell_ids) -> np.ndarray:
        """(k, 8) node ids of the cube corners (corner c has offset bits (c&1, c>>1&1, c>>2&1)), in
        one compiled pass (:func:`cutfem.geometry.mesh_kernels.box_cell_corner_ids`; numpy's divisions, stacks
        and sums took 0.14 s for the 4 million band cells at spacing 0.003125)."""

        c = np.ascontiguousarray(np.asarray(cell_ids, dtype=np.int64).reshape(-1))
        out = np.empty((len(c), 8), dtype=np.int64)
        mesh_kernels.box_cell_corner_ids(c, int(self.cells[0]), int(self.cells[1]), int(self.node_shape[0]),
                                    int(self.node_shape[1]), np.ascontiguousarray(self.node_id(CUBE_CORNERS)), out)
        return out

    @property
    def gradient_table(self) -> np.ndarray:
        """(6, 4, 3) the barycentric gradients of the six Kuhn tet types of this box, indexed by
        Kuhn type (tet id % 6).  A point of a cell is ``x = corner + xi * spacing``
        (componentwise), so they are those of the reference Kuhn tets (:data:`KUHN_GRADIENTS`,
        entries -1, 0, 1) divided by the spacing, axis by axis; no vertex coordinates are needed."""
        return KUHN_GRADIENTS / self.spacing

    @property
    def tet_volume(self) -> float:
        """Volume of every tet: the cell volume / 6."""
        return float(np.prod(self.spacing)) / 6.0

    def tet_node_counts(self, node_mask) -> np.ndarray:
        """(6 n_cells,) int8: how many of the four nodes of each tet have ``node_mask`` (N,) true.

        Each cell's eight corners give one byte (bit c for corner c, from eight shifted views of the
        mask on the node grid) and :data:`KUHN_CORNER_COUNTS` the counts of its six tets: no
        (6 n_cells, 4) array of nodes is made (the whole-box node gather took 0.85 s at 4 million tets)."""
        nx, ny, nz = (int(c) for c in self.cells)
        mask = np.asarray(node_mask, dtype=bool).reshape(nz + 1, ny + 1, nx + 1)  # node id i + (nx+1)(j + (ny+1)k)
        bits = np.zeros((nz, ny, nx), dtype=np.uint8)
        for c, (i, j, k) in enumerate(CUBE_CORNERS):
            bits |= mask[k : k + nz, j : j + ny, i : i + nx].view(np.uint8) << np.uint8(c)
        return KUHN_CORNER_COUNTS[bits.reshape(-1)].reshape(-1)  # cell id i + nx(j + ny k): tet 6 cell + l

    def kuhn_tet_nodes(self, tet_ids) -> np.ndarray:
        """(k, 4) node ids of tets ``tet_ids`` (in :data:`KUHN_TETS` order): the lowest corner of each
        cell plus a (6, 4) table of node offsets, in one compiled pass (:func:`cutfem.geometry.mesh_kernels.kuhn_tet_nodes`;
        the numpy passes took 3.9 s, this 0.4 s, for the 17 million tets of the solid torus at spacing 0.0125)."""

        tet_ids = np.ascontiguousarray(tet_ids, dtype=np.int64)
        offsets = np.ascontiguousarray(self.node_id(CUBE_CORNERS)[KUHN_TETS])  # (6, 4)
        out = np.empty((len(tet_ids), 4), dtype=np.int64)
        (cx, cy, _), (nx, ny, _) = (int(c) for c in self.cells), (int(n) for n in self.node_shape)
        mesh_kernels.kuhn_tet_nodes(tet_ids, cx, cy, nx, ny, offsets, out)
        return out

    def cell_tets(self, cell_ids) -> np.ndarray:
        """(6k, 4) node ids of the Kuhn tets of the given cells, tet ``6*c + l`` order."""
        return self.cell_corner_ids(cell_ids)[:, KUHN_TETS].reshape(-1, 4)

    @cached_property
    def points(self) -> np.ndarray:  # type: ignore[override]
        ijk = self.node_index(np.arange(self.n_points))
        return self.coordinates(ijk)

    @cached_property
    def tets(self) -> np.ndarray:  # type: ignore[override]
        return self.cell_tets(np.arange(self.n_cells))

    @cached_property
    def boundary_nodes(self) -> np.ndarray:
        """Node ids on the box boundary, from the six faces of the grid (no visit of the interior)."""
        ids = []
        for axis in range(3):
            a, b = [d for d in range(3) if d != axis]
            ga, gb = np.meshgrid(np.arange(self.node_shape[a]), np.arange(self.node_shape[b]), indexing="ij")
            for side in (0, self.node_shape[axis] - 1):
                ijk = np.empty(ga.shape + (3,), dtype=np.int64)
                ijk[..., axis], ijk[..., a], ijk[..., b] = side, ga, gb
                ids.append(self.node_id(ijk).reshape(-1))
        return unique_keys(np.concatenate(ids))

    def __repr__(self) -> str:
        return (
            f"StructuredBox(lower={self.lower.tolist()}, upper={self.upper.tolist()}, cells={self.cells.tolist()}, "
            f"n_points={self.n_points}, n_tets={self.n_tets})"
        )


def _per_axis(name: str, value, scalar: bool, integral: bool = False) -> np.ndarray:
    """``value`` as 3 numbers (x, y, z): a real array of shape (3,), or with ``scalar`` also one
    number for all axes; ``integral``: whole numbers, returned as int64.  A ValueError naming
    ``name`` for anything else (strings, booleans, 2-D corners, two values)."""
    a = np.asarray(value)
    what = "a number or 3 numbers (x, y, z)" if scalar else "3 numbers (x, y, z)"
    if integral:
        what = what.replace("number", "whole number")
    if a.dtype.kind not in "iuf" or a.shape not in (((), (3,)) if scalar else ((3,),)):
        raise ValueError(f"{name} must be {what}, got {value!r}")
    if integral:
        if not (np.all(np.isfinite(a)) and np.all(a == np.rint(a))):
            raise ValueError(f"{name} must be {what}, got {value!r}")
        if np.any(np.abs(a) >= 2.0**62):  # would wrap in int64: refuse with the exact counts
            exact = _whole_cells(a)
            if min(exact) >= 1:
                _check_box_size(exact, f"a structured box of {' x '.join(_readable_count(c) for c in exact)} cells",
                                "give fewer cells")
            raise ValueError(f"{name} must be {what} of at least 1, got {value!r}")
        return np.broadcast_to(a.astype(np.int64), (3,))
    return np.broadcast_to(a.astype(float), (3,))


def structured_box(lower, upper, spacing=None, cells=None) -> StructuredBox:
    """Structured tetrahedral mesh of the box ``[lower, upper]`` (6 Kuhn tets per cuboid).

    Give either ``cells`` (an int or 3 ints: the spacing is then ``(upper - lower) / cells``) or
    ``spacing`` (a positive finite number or 3 of them).  With ``spacing`` the mesh has exactly that
    spacing (``box.spacing`` is the number given, bit for bit) and a whole number of cells per axis:

    * when ``(upper - lower) / spacing`` is a whole number n (to within 1e-9 relative), the box is
      the one given, with n cells;
    * otherwise the box is *grown* symmetrically about its centre to the next whole number of cells,
      ``n = ceil((upper - lower) / spacing)``, so that it still contains the box asked for (and the
      surface inside it); ``box.lower``/``box.upper`` are the corners used.  It is never shrunk and
      the spacing is never changed to fit the box.

    ``lower`` and ``upper`` are 3 numbers each; ``cells`` whole numbers (2.5 is refused, not
    truncated).  Anything else is refused with a ValueError naming the argument.
    """
    lower = _per_axis("lower", lower, scalar=False)
    upper = _per_axis("upper", upper, scalar=False)
    if (spacing is None) == (cells is None):
        raise ValueError("give exactly one of spacing= or cells=")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))) or np.any(upper <= lower):
        raise ValueError(f"box must have finite corners with upper > lower in every axis, got lower={lower.tolist()}, upper={upper.tolist()}")
    if cells is not None:
        return StructuredBox(lower, upper, _per_axis("cells", cells, scalar=True, integral=True))
    spacing = _per_axis("spacing", spacing, scalar=True)
    if np.any(~np.isfinite(spacing)) or np.any(spacing <= 0):
        raise ValueError(f"spacing must be a positive finite number, got {spacing.tolist()}; give e.g. spacing=0.1")
    with np.errstate(over="ignore"):
        ratio = (upper - lower) / spacing  # inf when the quotient (or the extent) overflows
    huge = not np.all(ratio < 2.0**62)  # then 6 n_x n_y n_z > 2**63: refused below
    if huge:  # count the cells exactly (rationals of the floats) for the message
        exact = tuple(max(math.ceil((Fraction(float(u)) - Fraction(float(l))) / Fraction(float(h))), 1)
                      for l, u, h in zip(lower, upper, spacing))
    else:
        whole = np.rint(ratio)
        fits = (np.abs(ratio - whole) <= SPACING_TOLERANCE * np.maximum(ratio, 1)) & (whole >= 1)
        cells = np.where(fits, whole, np.ceil(ratio)).astype(np.int64)
        exact = tuple(int(c) for c in cells)
    # a box too large to number is refused here, in words about the spacing
    text = f"{spacing[0]:.3g}" if np.all(spacing == spacing[0]) else str(spacing.tolist())
    extent = [Fraction(float(u)) - Fraction(float(l)) for l, u in zip(lower, upper)]
    _check_box_size(exact, f"the structured box [{lower.tolist()}, {upper.tolist()}] at spacing={text}",
                    f"use a coarser spacing: at least {_spacing_whose_ids_fit(extent):.3g} for the ids to fit, and in "
                    "practice a spacing whose cut fits the memory (the cut checks that and names one), or a smaller box")
    if not fits.all():
        centre = 0.5 * (lower + upper)
        grown = ~fits
        lower = np.where(grown, centre - 0.5 * cells * spacing, lower)
        upper = np.where(grown, lower + cells * spacing, upper)
    return StructuredBox(lower, upper, cells, spacing=spacing)
