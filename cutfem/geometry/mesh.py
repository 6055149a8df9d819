"""Background tetrahedral meshes: the general tet mesh, its checks and topology, pytetwild, files.

A :class:`TetMesh` holds ``points`` (N, 3) and positively oriented ``tets`` (M, 4) that cover
their domain once (checked on construction: no coincident nodes, no fold, no overlap).  Its
topology (unique faces with their one or two tets, edges, boundary) is computed on demand,
vectorized, by sorting integer keys (:mod:`cutfem.geometry.keys`).  Unstructured meshes of a box
come from pytetwild (:func:`unstructured_box`, :func:`unstructured_around`), files through meshio
(:func:`read_mesh`, :func:`write_mesh`); the structured box of Kuhn tets is
:class:`cutfem.geometry.box.StructuredBox`.

Mesh size: the global value ``h = N**(-1/3)`` (N = number of background nodes), as in docs/math.md §2.
"""

from __future__ import annotations

import math
import os
import tempfile
from functools import cached_property
from pathlib import Path

import numpy as np

from .keys import pair_up, sorted_row_keys, tet_face_keys, unique_keys
from .numbering import CUBE_CORNERS, TET_EDGES, TET_FACES
from . import mesh_kernels

__all__ = [
    "TetMesh",
    "COINCIDENT_TOLERANCE",
    "close_pairs",
    "unstructured_box",
    "unstructured_around",
    "read_mesh",
    "write_mesh",
    "barycentric_gradients",
    "cross",
    "triangle_areas",
]


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of (..., 3) arrays, written out (``np.cross`` costs several times more)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def triangle_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """|T| = |(x_1 - x_0) x (x_2 - x_0)| / 2 of triangles (m, 3) of ``points`` (p, 3), one compiled
    pass (:func:`cutfem.geometry.mesh_kernels.triangle_areas`; numpy's nine gathers and twenty array operations
    took 1.4 s for the 4.5 million triangles of the torus at spacing 0.00625)."""

    return mesh_kernels.triangle_areas(points, triangles)


def barycentric_gradients(vertices: np.ndarray):
    """Gradients of the barycentric coordinates of tetrahedra.

    ``vertices`` (m, 4, 3).  With the edges e_k = x_k - x_0 (k = 1, 2, 3) and
    ``det = e_1 . (e_2 x e_3)``, lambda_k has gradient ``(e_{k+1} x e_{k+2}) / det`` (indices
    1..3 cyclic: the rows of the inverse of the edge matrix by the adjugate) and
    ``grad lambda_0 = -sum_k grad lambda_k``.
    Returns ``(grads (m, 4, 3), volumes (m,))`` with signed volumes ``det/6``.
    """
    v = np.asarray(vertices, dtype=float)
    e1, e2, e3 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], v[:, 3] - v[:, 0]
    grads = np.empty((v.shape[0], 4, 3))
    grads[:, 1] = cross(e2, e3)
    grads[:, 2] = cross(e3, e1)
    grads[:, 3] = cross(e1, e2)
    det = np.einsum("ij,ij->i", e1, grads[:, 1])
    grads[:, 1:] /= det[:, None, None]
    grads[:, 0] = -(grads[:, 1] + grads[:, 2] + grads[:, 3])
    return grads, det / 6.0


def _used_mask(n: int, tets) -> np.ndarray:
    """(n,) bool: which of n points are nodes of the tets."""
    used = np.zeros(n, dtype=bool)
    used[np.asarray(tets).reshape(-1)] = True
    return used


#: Two nodes of the tets closer than COINCIDENT_TOLERANCE times the diagonal of the box of those
#: nodes are one point written twice (see :func:`_check_coincident`).
COINCIDENT_TOLERANCE = 1e-10

# a unit direction with no simple ratio between its components: the points of a lattice aligned
# with the axes (a structured mesh written to a file) have distinct projections on it
_PROJECTION = np.array([0.5390573056, 0.6293836337, 0.5597298126])
_PROJECTION = _PROJECTION / np.linalg.norm(_PROJECTION)


def close_pairs(points, r: float) -> np.ndarray:
    """(k, 2) the pairs ``i < j`` of rows of ``points`` (n, 3) at distance ``|p_i - p_j| <= r``, in
    O(n log n): one sort of the projections ``p . d`` on a fixed unit direction d, then a k-d tree
    (scipy's cKDTree) on the few points whose projection lies within r of a neighbour's (two points
    within r have projections within r, and so do all the projections sorted between them).  d has
    no simple ratio between its components, so the points of a mesh, structured or not, have well
    separated projections and almost none reach the tree.  On a million mesh nodes 40-90 ms,
    against 0.5-0.9 s for the k-d tree of all of them."""
    p = np.asarray(points, dtype=float)
    if len(p) < 2:
        return np.empty((0, 2), dtype=np.int64)
    s = p @ _PROJECTION
    order = np.argsort(s, kind="stable")
    # the projections' rounding: a few units in the last place of |p| (|d| = 1)
    slack = 8.0 * np.finfo(float).eps * float(np.abs(p).max())
    near = np.diff(s[order]) <= float(r) + slack
    if not near.any():
        return np.empty((0, 2), dtype=np.int64)
    from scipy.spatial import cKDTree  # imported only when some points are that close (about 40 ms)

    mark = np.zeros(len(p), dtype=bool)
    mark[:-1] |= near
    mark[1:] |= near
    ids = np.sort(order[mark])
    pairs = cKDTree(p[ids]).query_pairs(float(r), output_type="ndarray").astype(np.int64)
    pairs = ids[pairs]
    pairs.sort(axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def _check_coincident(points, used) -> None:
    """Refuse nodes of the tets (``used``, a mask of the points) that lie at one point: closer than
    ``r = COINCIDENT_TOLERANCE * diam`` (1e-10 times the diagonal of the box of the nodes of the
    tets; :func:`close_pairs`).  Their tets do not share the faces there, so the mesh has a crack, a
    P1 field is discontinuous across it and the faces drop out of the face penalties.  A mesher that
    writes a node twice writes equal coordinates or coordinates that differ by its rounding, a few
    units in the last place (1e-16 |x|, so 1e-12 for coordinates of 1e4), far below r; the nodes of
    any usable mesh are far above it (r is 1e-6 of the spacing of a mesh with 1e4 cells a side).  The
    scale is that of the whole mesh, not of its shortest edge: the copies in a crack are not joined by
    an edge, and a collapsed edge is itself such a defect.  Copies further apart than r are two nodes
    (a crack wider than r that the surface crosses is named by the cut: a hole in the background).
    Points that no tet uses may coincide with anything."""
    ids = np.flatnonzero(used)
    if ids.size < 2:
        return
    p = points[ids]
    r = COINCIDENT_TOLERANCE * float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    pairs = close_pairs(p, r)
    if len(pairs):
        a, b = (int(v) for v in ids[pairs[0]])
        involved = np.unique(pairs).size
        raise ValueError(
            f"{involved} nodes coincide with other nodes of the tets (first: nodes {a} and {b} at "
            f"{points[a].tolist()}, {float(np.linalg.norm(points[a] - points[b])):.3g} apart, closer than "
            f"{r:.3g} = {COINCIDENT_TOLERANCE:g} times the mesh's diagonal): the mesh is split there, its tets do not "
            "share those faces; merge the duplicated nodes (one node per point; in gmsh 'Coherence Mesh') and "
            "renumber the tets"
        )


#: A point of the boundary of a tet mesh lies strictly inside a tet when its four barycentric
#: coordinates there exceed this (see :func:`_check_overlap`): far above their round-off (1e-16
#: times the tet's condition), far below any real overlap.
OVERLAP_TOLERANCE = 1e-8


def _face_parities(tets: np.ndarray) -> np.ndarray:
    """(4m,) int8: for each face row 4 t + k (the face opposite to local vertex k of tet t), the
    parity of the permutation that takes the tet's vertex order to (lo, mid, hi, apex), the face's
    sorted nodes followed by its opposite vertex.  For a positively oriented tet, orient(lo, mid,
    hi, apex) > 0 exactly when the parity is even, so two positively oriented tets sharing a face
    lie on opposite sides of it exactly when their parities on it differ.  The parity is the number
    of inversions of the tet's order plus the number of face nodes above the apex, mod 2."""
    cols = [np.ascontiguousarray(tets[:, j]) for j in range(4)]
    inversions = np.zeros(len(tets), dtype=np.int8)
    for i in range(4):
        for j in range(i + 1, 4):
            inversions += cols[i] > cols[j]
    out = np.empty((len(tets), 4), dtype=np.int8)
    for k, face in enumerate(TET_FACES):
        above = inversions.copy()
        for j in face:
            above += cols[j] > cols[k]
        out[:, k] = above & 1
    return out.reshape(-1)


def _check_folded(tets: np.ndarray, face_rows: np.ndarray, flipped) -> None:
    """Refuse positively oriented tets (m, 4) two of which share a face and lie on the same side of
    it (:func:`_face_parities`): they overlap, the mesh is folded there.  A valid mesh has every
    interior face between two tets on opposite sides.  ``flipped`` (m,) bool or None: the tets that
    were inverted in the input (reordered by ``orient=True``), named as the likely culprits."""
    interior = face_rows[:, 1] >= 0
    if not interior.any():
        return
    rows = face_rows[interior]
    parity = _face_parities(tets)
    bad = np.flatnonzero(parity[rows[:, 0]] == parity[rows[:, 1]])
    if not bad.size:
        return
    pairs = rows[bad] // 4
    folded = unique_keys(pairs.reshape(-1))
    pair_text = ", ".join(f"({a}, {b})" for a, b in pairs[:5].tolist())
    text = f"{bad.size} interior faces have their two tets on the same side (first tet pairs: {pair_text}; {folded.size} tets in all)"
    if flipped is not None and np.any(flipped[folded]):
        inverted = folded[flipped[folded]]
        text += (f"; {inverted.size} of them are inverted (negative volume) in the input, first tets "
                 f"{inverted[:5].tolist()}, and reordering them (orient=True) cannot make the mesh consistent")
    raise ValueError(
        f"the mesh is tangled: {text}. Such tets overlap their neighbours (a node moved through the opposite face of "
        "its tets), so volumes and integrals count the overlap twice; untangle the mesh (move the nodes back or "
        "re-mesh the region)"
    )


def _check_wound(points: np.ndarray, tets: np.ndarray, boundary: np.ndarray) -> None:
    """Refuse an interior node (one on no boundary face; ``boundary`` its sorted ids) whose tets wind
    around it more than once: the solid angles of its tets at it sum to 4 pi k, k the number of
    times they cover the directions around it (:func:`cutfem.geometry.mesh_kernels.vertex_solid_angles`), 4 pi
    for a mesh that covers its domain once.  With every interior face between tets on opposite
    sides (:func:`_check_folded`) k is a whole number, so the threshold 6 pi is far from round-off.
    Such a star passes the face test and has no boundary near it for :func:`_check_overlap`."""

    total = np.zeros(len(points))
    mesh_kernels.vertex_solid_angles(points, np.ascontiguousarray(tets), total)
    total[boundary] = 0.0
    wound = np.flatnonzero(total > 6.0 * np.pi)
    if not wound.size:
        return
    node = int(wound[0])
    star = np.flatnonzero(np.any(tets == node, axis=1))
    raise ValueError(
        f"the mesh winds around {wound.size} interior nodes more than once (first: node {node} at "
        f"{points[node].tolist()}, whose {star.size} tets {star[:5].tolist()}{', ...' if star.size > 5 else ''} cover "
        f"the directions around it {total[node] / (4 * np.pi):.3g} times: solid angles summing to "
        f"{total[node]:.4g} instead of 4 pi), so the domain is covered more than once there; re-mesh the region"
    )


def _check_overlap(points: np.ndarray, tets: np.ndarray, triangles: np.ndarray) -> None:
    """Refuse a mesh with a point of its boundary strictly inside one of its tets (all barycentric
    coordinates above :data:`OVERLAP_TOLERANCE`).  In a mesh that covers each point of its domain
    once, the boundary faces (``triangles``, (b, 3)) lie on the domain's boundary and meet no tet's
    interior; when two parts overlap (two meshes stacked, or a part wound over another), the
    boundary of one runs through the tets of the other.  The probes are the boundary nodes and the
    boundary faces' centroids, sorted into a uniform grid of cells about the median tet size; one
    compiled pass over the tets tests the probes in the cells their bounding box meets
    (:func:`cutfem.geometry.mesh_kernels.points_inside_tets`).  The interior face check (:func:`_check_folded`)
    sees folds; this sees overlap at a distance."""

    if not len(triangles):
        return
    nodes = unique_keys(triangles.reshape(-1))
    probes = np.concatenate([points[nodes], points[triangles].mean(axis=1)])
    lower = probes.min(axis=0)
    span = probes.max(axis=0) - lower
    # the cell: the median largest bounding-box side of a sample of the tets
    xs = points[tets[:: max(1, len(tets) // 65536)]]
    cell = float(np.median(np.max(xs.max(axis=1) - xs.min(axis=1), axis=1)))
    cell = max(cell, 1e-9 * float(span.max()), np.finfo(float).tiny)
    while True:
        dims = np.floor(span / cell).astype(np.int64) + 1
        if math.prod(int(d) for d in dims) <= max(len(tets) // 2, 1_000_000):  # Python ints: no wrap
            break
        cell *= 2.0
    pc = np.minimum(np.floor((probes - lower) / cell).astype(np.int64), dims - 1)
    pkey = pc[:, 0] + dims[0] * (pc[:, 1] + dims[1] * pc[:, 2])
    cell_probes = np.argsort(pkey, kind="stable")
    cell_start = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
    np.cumsum(np.bincount(pkey, minlength=int(np.prod(dims))), out=cell_start[1:])
    # the cell of every point, clipped to [-1, dims] (outside the probes' box on that side)
    node_cells = np.empty(points.shape, dtype=np.int32)
    with np.errstate(invalid="ignore"):  # points no tet uses may be NaN; they are never read
        for a in range(3):
            node_cells[:, a] = np.clip(np.floor((points[:, a] - lower[a]) / cell), -1, dims[a])
    hits = np.empty((64, 2), dtype=np.int64)
    found = mesh_kernels.points_inside_tets(points, np.ascontiguousarray(tets), node_cells, probes, dims, cell_start,
                                       cell_probes, OVERLAP_TOLERANCE, hits)
    if not found:
        return
    hits = hits[: min(found, len(hits))]
    t, q = (int(v) for v in hits[0])
    where = (f"boundary node {int(nodes[q])}" if q < len(nodes)
             else f"the centroid of the boundary face {triangles[q - len(nodes)].tolist()}")
    raise ValueError(
        f"the mesh overlaps itself: {found} (point of its boundary, tet) pairs have the point strictly inside the tet "
        f"(first: {where} at {np.round(probes[q], 12).tolist()} inside tet {t}; overlapping tets "
        f"{unique_keys(hits[:, 0])[:5].tolist()}), so parts of the domain are covered twice and volumes and integrals "
        "count them twice (two meshes stacked, or a part wound over another). Give one conforming mesh of the domain: "
        "remove the duplicated part, or merge the parts with a mesher"
    )


class TetMesh:
    """A conforming tetrahedral mesh.

    Parameters
    ----------
    points : (N, 3) float
    tets : (M, 4) int, vertex indices of each tetrahedron
    orient : if True, tets with negative volume are reordered (two vertices swapped); if False
        (default), negative volumes are an error.
    check : validate finiteness, index range, non-degeneracy (volume > 1e-12 * mean |volume|),
        that no two nodes of the tets coincide (closer than :data:`COINCIDENT_TOLERANCE` = 1e-10
        times the diagonal of their box: a crack, see :func:`_check_coincident`), and that the
        tets cover each point of their domain once: no face in more than two tets, the two tets
        of every interior face on opposite sides of it (:func:`_check_folded`; reordering inverted
        tets with ``orient`` is accepted only where that makes them agree with their neighbours),
        no interior node wound round more than once (:func:`_check_wound`), and no boundary point
        strictly inside a tet (:func:`_check_overlap`).  At least one tet.  Not seen: tets wound
        twice around an edge whose two ends are both on the boundary when, by symmetry, every
        boundary point of one turn lies on a face of the other (a perturbed ring is seen by the
        overlap test; an edge test would need a sort of the 6 M edges).

    Cached topology: ``faces`` (F, 3) sorted node triples, ``face_tets`` (F, 2) with -1 for the
    missing neighbour of a boundary face (the first entry is always a tet), ``tet_faces`` (M, 4)
    (face opposite to local vertex k), ``edges`` (E, 2), ``boundary_faces`` (indices into faces),
    ``boundary_nodes``, ``interior_faces``.  Mesh size ``h = N**(-1/3)``, N the nodes of the tets.
    """

    def __init__(self, points, tets, *, orient: bool = False, check: bool = True):
        points = np.ascontiguousarray(points, dtype=float)
        tets = np.ascontiguousarray(tets, dtype=np.int64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {points.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise ValueError(f"tets must have shape (M, 4), got {tets.shape}")
        if len(tets) == 0:
            raise ValueError(
                f"a TetMesh needs at least one tet; got 0 tets (on {len(points)} points): give the tets' vertex indices "
                "(M, 4), or read the mesh file with read_mesh"
            )
        if check:
            if tets.size and (tets.min() < 0 or tets.max() >= len(points)):
                raise ValueError(f"tet vertex indices must lie in [0, {len(points)}); got range [{tets.min()}, {tets.max()}]")
            used = self.__dict__["_used"] = _used_mask(len(points), tets)  # the cached _used
            if not np.all(np.isfinite(points)):  # only the nodes of the tets count (stray points of a file do not)
                bad = np.flatnonzero(used & ~np.all(np.isfinite(points), axis=1))
                if bad.size:
                    raise ValueError(f"{bad.size} nodes of the tets are NaN or infinite (first: point {bad[0]}); fix the input mesh")
            vol = self._signed_volumes(points, tets)
            scale = np.mean(np.abs(vol)) if vol.size else 0.0
            degenerate = np.abs(vol) <= 1e-12 * scale
            if np.any(degenerate):
                k = np.flatnonzero(degenerate)
                raise ValueError(
                    f"{k.size} degenerate (zero-volume) tetrahedra, first: tet {k[0]} with vertices {tets[k[0]].tolist()}; "
                    "remove them or re-mesh"
                )
            _check_coincident(points, used)
            inverted = vol < 0
            if np.any(inverted):
                tets = tets.copy()
                tets[inverted, 2], tets[inverted, 3] = tets[inverted, 3], tets[inverted, 2].copy()
        self.points = points
        self.tets = tets
        if check:
            # a valid mesh covers each point of its domain once: no fold, no overlap (the faces
            # found here are kept for the topology).  Folds first: a tangled mesh is named as such
            # even without orient, where reordering its inverted tets would not help
            face_rows = self._face_topology[3]
            _check_folded(tets, face_rows, inverted if np.any(inverted) else None)
            if np.any(inverted) and not orient:
                k = np.flatnonzero(inverted)
                raise ValueError(
                    f"{k.size} inverted (negatively oriented) tetrahedra, first: tet {k[0]}; "
                    "swap two vertices of each, or pass orient=True to reorder them"
                )
            boundary_faces = self._face_topology[0][face_rows[:, 1] < 0]
            _check_wound(points, tets, unique_keys(boundary_faces.reshape(-1)))
            _check_overlap(points, tets, boundary_faces)

    @staticmethod
    def _signed_volumes(points, tets):
        v = points[tets]
        return np.einsum("ij,ij->i", np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), v[:, 3] - v[:, 0]) / 6.0

    def tet_node_counts(self, node_mask) -> np.ndarray:
        """(M,) int8: how many of the four nodes of each tet have ``node_mask`` (N,) true."""
        return np.asarray(node_mask, dtype=bool)[self.tets].sum(axis=1, dtype=np.int8)

    # -- sizes ---------------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return len(self.points)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @cached_property
    def _used(self) -> np.ndarray:
        """(N,) bool: the points that are nodes of a tet."""
        return _used_mask(len(self.points), self.tets)

    @cached_property
    def n_used_points(self) -> int:
        """The number of nodes of the tets: ``n_points`` less the points that no tet uses."""
        return int(np.count_nonzero(self._used))

    @property
    def h(self) -> float:
        """Global mesh size N**(-1/3), N = the number of nodes of the tets (docs/math.md §2): points
        that no tet uses (stray points of a mesh file) are not nodes of the mesh and do not count."""
        return float(self.n_used_points) ** (-1.0 / 3.0)

    @cached_property
    def volumes(self) -> np.ndarray:
        """(M,) tet volumes (positive)."""
        return self._signed_volumes(self.points, self.tets)

    @cached_property
    def bounds(self):
        """(lower (3,), upper (3,)) bounding box of the nodes of the tets (points no tet uses left out)."""
        if self.n_used_points == self.n_points:
            return self.points.min(axis=0), self.points.max(axis=0)
        return self.points[self._used].min(axis=0), self.points[self._used].max(axis=0)

    # -- topology ------------------------------------------------------------------------
    @cached_property
    def _face_topology(self):
        """(faces, face_tets, tet_faces, face_rows): face_rows (F, 2) the rows 4 t + k (face
        opposite to local vertex k of tet t) of each face, -1 for the missing one."""
        m, n = self.n_tets, self.n_points
        keys = tet_face_keys(self.tets, n)
        order, starts, counts = pair_up(keys)
        if np.any(counts > 2):
            many = np.flatnonzero(counts > 2)
            g = many[0]
            tets = (order[starts[g] : starts[g] + counts[g]] // 4).tolist()
            raise ValueError(
                f"{many.size} faces are shared by more than two tets (first: face {[int(c[order[starts[g]]]) for c in keys]} "
                f"of tets {tets}): the mesh is not conforming, tets overlap there (a tet given twice, or two meshes "
                "stacked); give each tet once and one conforming mesh of the domain"
            )
        first = order[starts]
        faces = np.stack([col[first] for col in keys], axis=1).astype(np.int64)
        face_rows = np.full((len(starts), 2), -1, dtype=np.int64)
        face_rows[:, 0] = first
        two = counts == 2
        face_rows[two, 1] = order[starts[two] + 1]
        face_tets = np.where(face_rows >= 0, face_rows // 4, -1)
        face_of_row = np.empty(4 * m, dtype=np.int64)
        face_of_row[order] = np.repeat(np.arange(len(starts)), counts)
        return faces, face_tets, face_of_row.reshape(m, 4), face_rows

    @property
    def faces(self) -> np.ndarray:
        """(F, 3) unique faces as sorted vertex triples."""
        return self._face_topology[0]

    @property
    def face_tets(self) -> np.ndarray:
        """(F, 2) the tets of each face; -1 in the second column for boundary faces."""
        return self._face_topology[1]

    @property
    def tet_faces(self) -> np.ndarray:
        """(M, 4) face index of the face opposite to each local vertex."""
        return self._face_topology[2]

    @cached_property
    def boundary_faces(self) -> np.ndarray:
        """Indices (into ``faces``) of faces with a single tet."""
        return np.flatnonzero(self.face_tets[:, 1] < 0)

    @cached_property
    def interior_faces(self) -> np.ndarray:
        """Indices (into ``faces``) of faces shared by two tets."""
        return np.flatnonzero(self.face_tets[:, 1] >= 0)

    @cached_property
    def boundary_nodes(self) -> np.ndarray:
        """Sorted indices of the nodes on boundary faces."""
        return unique_keys(self.faces[self.boundary_faces])

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) unique edges as sorted vertex pairs."""
        n = self.n_points
        keys = np.concatenate([sorted_row_keys(self.tets[:, e], n) for e in TET_EDGES])
        keys = unique_keys(keys)
        return np.stack([keys // n, keys % n], axis=1)

    @property
    def euler_characteristic(self) -> int:
        """V - E + F - T; equals 1 for a mesh of a ball (e.g. a box)."""
        return self.n_points - len(self.edges) + len(self.faces) - self.n_tets

    def to_pyvista(self):
        """The mesh as a ``pyvista.UnstructuredGrid``."""
        import pyvista as pv

        return pv.UnstructuredGrid({pv.CellType.TETRA: self.tets}, self.points)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(n_points={self.n_points}, n_tets={self.n_tets})"


def _box_surface(lower, upper):
    """Closed triangulated surface of a box (8 vertices, 12 outward triangles)."""
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    v = lower + CUBE_CORNERS * (upper - lower)
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    tris = []
    for a, b, c, d in quads:
        tris += [[a, b, c], [a, c, d]]
    return v, np.array(tris, dtype=np.int32)


def _tetwild(vertices, faces, edge_length, optimize=True) -> TetMesh:
    import pytetwild

    if not np.isfinite(edge_length) or edge_length <= 0:
        raise ValueError(f"edge_length must be positive, got {edge_length}")
    # fTetWild writes a debug file (__tracked_surface.stl) into the working directory: run it in a
    # scratch directory so that meshing never litters the user's folder
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="cutfem-tetwild-") as scratch:
        os.chdir(scratch)
        try:
            pts, tets = pytetwild.tetrahedralize(
                np.asarray(vertices, float), np.asarray(faces, np.int32), edge_length_abs=float(edge_length), optimize=optimize
            )
        finally:
            os.chdir(cwd)
    used, inv = unique_keys(np.asarray(tets, np.int64), return_inverse=True)
    return TetMesh(np.asarray(pts)[used], inv.reshape(-1, 4), orient=True)


def unstructured_box(lower, upper, edge_length: float, optimize: bool = True) -> TetMesh:
    """Unstructured tetrahedral mesh of the box ``[lower, upper]`` by pytetwild at a target edge length."""
    v, f = _box_surface(lower, upper)
    return _tetwild(v, f, edge_length, optimize)


def unstructured_around(surface, edge_length: float, padding: float = 0.2, optimize: bool = True) -> TetMesh:
    """Unstructured tetrahedral mesh (pytetwild) of the box around a closed surface.

    ``surface`` has ``points`` (N, 3) (a SurfaceMesh or pyvista.PolyData); the box is its bounding
    box grown by ``padding`` times its diagonal on every side, so the surface stays strictly inside.
    """
    p = np.asarray(surface.points, float)
    lo, hi = p.min(axis=0), p.max(axis=0)
    pad = padding * np.linalg.norm(hi - lo)
    return unstructured_box(lo - pad, hi + pad, edge_length, optimize)


def _volume_cell_kind(cell_type: str):
    """'tet' for meshio's tetrahedra of any order (their first four nodes are the corners, in the
    vtk and gmsh orders alike), 'other' for the other volume cells, None for points, lines and faces."""
    name = cell_type.lower()
    if name.startswith("tetra") or name == "vtk_lagrange_tetrahedron":
        return "tet"
    if name.startswith(("hexahedron", "wedge", "pyramid", "polyhedron", "vtk_lagrange_hexahedron", "vtk_lagrange_wedge",
                        "vtk_lagrange_pyramid")):
        return "other"
    return None


def read_mesh(path) -> TetMesh:
    """Read a tetrahedral mesh with meshio (any format meshio reads: .vtu, .vtk, .msh, .mesh, .xdmf, ...).

    The tets are the file's tetra cells, of every block.  Higher-order tets (tetra10, ...) give
    their four corners: the straight-sided tets of the same vertices, the mid-edge nodes being
    points that no tet uses (they count nowhere, e.g. not in ``h``).  Points, lines and surface
    cells (the boundary triangles and physical groups of a gmsh file) are left out.  A file with
    other volume cells (hexahedra, wedges, pyramids) is refused: the tets alone would leave holes
    where those cells are.  So is a file without tets (a surface or 2-D mesh).  Tets written with
    negative volume are reordered, and the mesh is then checked as every :class:`TetMesh` is: a
    tangled mesh (a node moved through a face of its tets) or one that overlaps itself (two meshes
    in one file) is refused, naming the tets.
    """
    import meshio

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        m = meshio.read(path)
    except ModuleNotFoundError as exc:  # formats whose reader needs another package (.xdmf: h5py)
        raise ValueError(f"cannot read mesh file {path}: meshio needs the package {exc.name!r} for this format; install it "
                         f"(pip install {exc.name}) or convert the file to .vtu or .msh") from exc
    except (Exception, SystemExit) as exc:  # meshio raises several types (even SystemExit) for broken files
        raise ValueError(f"cannot read mesh file {path}: {exc}. Use a format meshio reads (.vtu, .vtk, .msh, .mesh, .xdmf)") from exc
    kinds = [(c, _volume_cell_kind(c.type)) for c in m.cells if len(c.data)]
    other = {}
    for c, kind in kinds:
        if kind == "other":
            other[c.type] = other.get(c.type, 0) + len(c.data)
    if other:
        raise ValueError(
            f"{path} holds volume cells other than tetrahedra ({', '.join(f'{n} {t}' for t, n in other.items())}): the "
            "tets alone would leave holes where they are. Mesh the domain with tetrahedra only, or split those cells "
            "into conforming tetrahedra before reading"
        )
    blocks = [np.asarray(c.data)[:, :4] for c, kind in kinds if kind == "tet"]
    if not blocks:
        dim = np.asarray(m.points).shape[1] if np.asarray(m.points).ndim == 2 else 0
        raise ValueError(
            f"{path} holds no tetrahedra (cell types: {sorted({c.type for c in m.cells}) or 'none'}, points with {dim} "
            "coordinates): the background must be a 3-D mesh of tetrahedra; a surface mesh is read by "
            "cutfem.geometry.surface.read_surface"
        )
    points = np.asarray(m.points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path} has tetrahedra on points of shape {points.shape}; a 3-D mesh needs (N, 3)")
    return TetMesh(points, np.concatenate(blocks), orient=True)


def write_mesh(mesh: TetMesh, path, point_data=None, cell_data=None) -> None:
    """Write a tetrahedral mesh (and optional point/cell data dicts of arrays) with meshio."""
    import meshio

    cd = {k: [np.asarray(v)] for k, v in (cell_data or {}).items()}
    meshio.write(Path(path), meshio.Mesh(mesh.points, [("tetra", mesh.tets)], point_data=point_data or {}, cell_data=cd))
