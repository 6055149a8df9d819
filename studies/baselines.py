"""Mesh-processing baselines for the mean curvature of a triangulated surface (no FEM solve).

These are the usual pointwise formulas of geometry processing, used in the studies as a point of
comparison for the stabilized P1 mean curvature vector of docs/math.md §3.  All are vectorized over the
triangles of a closed triangle mesh with ``points`` (N, 3) and ``triangles`` (M, 3).

Cotangent formula
-----------------
The cotangent Laplacian is the P1 stiffness matrix of the surface mesh,

    L_ij = -(cot a_ij + cot b_ij) / 2   (i != j an edge; a_ij, b_ij the angles opposite to it),
    L_ii = -sum_{j != i} L_ij,

so that (L x)_i = (grad_{S_h} x, grad_{S_h} phi_i)_{S_h} ~ (H, phi_i) with the convention of
docs/math.md §1 (H = -Lap_S x = (k1 + k2) n, outward).  With a lumped (diagonal) mass m_i the nodal mean
curvature vector is

    H_i = (L X)_i / m_i        (X the (N, 3) node coordinates),

which points outward with |H_i| ~ 2/R on a sphere of radius R.  Two lumped masses are offered:

* ``"barycentric"``: m_i = sum over the triangles K at i of |K| / 3 (the row sums of the P1 mass);
* ``"voronoi"``: the mixed Voronoi area -- in a non-obtuse triangle with vertices i, j, k the part
  of the Voronoi cell of i, (|x_i - x_j|^2 cot(angle at k) + |x_i - x_k|^2 cot(angle at j)) / 8;
  in an obtuse triangle |K| / 2 to the obtuse vertex and |K| / 4 to the other two (so the m_i still
  sum to the total area).

Compared with the consistent-mass L2 projection of docs/math.md §3 with tau_E = 0, these are the same
right-hand side with the mass matrix lumped; they do not add any stabilization.

VTK / pyvista curvature
-----------------------
``pyvista.PolyData.curvature("mean")`` (vtkCurvatures) returns, per node, a discrete *mean*
curvature in the differential-geometry sense, (k1 + k2) / 2, positive on a sphere with outward
normals (1/R on a sphere of radius R; this is checked in the tests).  To compare it with the mean
curvature vector of docs/math.md §1 we use H_i = 2 c_i n_i with c_i the pyvista value and n_i the
area-weighted vertex normal (:func:`vertex_normals`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = [
    "corner_cotangents",
    "cotangent_laplacian",
    "lumped_mass",
    "vertex_normals",
    "cotangent_mean_curvature",
    "pyvista_mean_curvature",
    "pyvista_mean_curvature_vector",
]


def _arrays(points, triangles):
    p = np.asarray(points, dtype=float)
    t = np.asarray(triangles, dtype=np.int64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {p.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise ValueError(f"triangles must have shape (M, 3) with M > 0, got {t.shape}")
    if t.min() < 0 or t.max() >= len(p):
        raise ValueError(f"triangles index points outside 0..{len(p) - 1}")
    return p, t


def corner_cotangents(points, triangles):
    """Cotangents of the three corner angles of every triangle, (M, 3); column k is the corner at
    vertex k.  cot = (e1 . e2) / |e1 x e2| with e1, e2 the two edges leaving the corner.
    ValueError for a degenerate (zero-area) triangle."""
    p, t = _arrays(points, triangles)
    x = p[t]  # (M, 3, 3)
    e1 = np.roll(x, -1, axis=1) - x  # to the next vertex
    e2 = np.roll(x, 1, axis=1) - x  # to the previous vertex
    cross = np.linalg.norm(np.cross(e1, e2), axis=2)
    if np.any(cross <= 0):
        raise ValueError(f"{int(np.sum(cross[:, 0] <= 0))} degenerate (zero-area) triangles: cotangents undefined")
    return np.einsum("mkd,mkd->mk", e1, e2) / cross


def cotangent_laplacian(points, triangles) -> sp.csr_matrix:
    """The cotangent Laplacian L (N, N), symmetric positive semidefinite, L 1 = 0.

    Each corner k of a triangle contributes w = cot(angle at k) / 2 to the edge (i, j) opposite to
    it: L_ij -= w, L_ji -= w, L_ii += w, L_jj += w.  Equal to the P1 stiffness matrix of the mesh.
    """
    p, t = _arrays(points, triangles)
    w = 0.5 * corner_cotangents(p, t)  # (M, 3), corner k
    i = np.roll(t, -1, axis=1)  # the edge opposite to corner k is (v_{k+1}, v_{k+2})
    j = np.roll(t, 1, axis=1)
    rows = np.concatenate([i, j, i, j], axis=None)
    cols = np.concatenate([j, i, i, j], axis=None)
    vals = np.concatenate([-w, -w, w, w], axis=None)
    n = len(p)
    return sp.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr()


def lumped_mass(points, triangles, kind: str = "voronoi") -> np.ndarray:
    """Lumped nodal areas m (N,): ``"barycentric"`` or ``"voronoi"`` (mixed Voronoi), see the module
    docstring.  Both sum to the area of the mesh."""
    p, t = _arrays(points, triangles)
    x = p[t]
    area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)  # (M,)
    n = len(p)
    if kind == "barycentric":
        local = np.repeat(area[:, None] / 3.0, 3, axis=1)
    elif kind == "voronoi":
        cot = corner_cotangents(p, t)  # corner k
        # squared length of the edge from vertex k to vertex k+1 and to vertex k-1
        to_next = np.sum((np.roll(x, -1, axis=1) - x) ** 2, axis=2)
        to_prev = np.sum((np.roll(x, 1, axis=1) - x) ** 2, axis=2)
        # edge (k, k+1) is opposite to corner k+2 = k-1; edge (k, k-1) opposite to corner k+1
        local = (to_next * np.roll(cot, 1, axis=1) + to_prev * np.roll(cot, -1, axis=1)) / 8.0
        obtuse_corner = cot < 0  # angle > 90 degrees
        obtuse = obtuse_corner.any(axis=1)
        fallback = np.where(obtuse_corner, 0.5, 0.25) * area[:, None]
        local = np.where(obtuse[:, None], fallback, local)
    else:
        raise ValueError(f"kind must be 'barycentric' or 'voronoi', got {kind!r}")
    return np.bincount(t.reshape(-1), weights=local.reshape(-1), minlength=n)


def vertex_normals(points, triangles) -> np.ndarray:
    """Area-weighted unit vertex normals (N, 3): the normalized sum of (x1 - x0) x (x2 - x0) over the
    triangles at each node (outward for an outward-oriented mesh)."""
    p, t = _arrays(points, triangles)
    x = p[t]
    c = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    n = np.zeros_like(p)
    for k in range(3):  # three corners, not a loop over triangles
        np.add.at(n, t[:, k], c)
    return n / np.linalg.norm(n, axis=1)[:, None]


def cotangent_mean_curvature(points, triangles, mass: str = "voronoi") -> np.ndarray:
    """Nodal mean curvature vectors H_i = (L X)_i / m_i (N, 3) of the cotangent formula, with the
    lumped mass ``mass`` ("voronoi" or "barycentric").  H = (k1 + k2) n, outward (docs/math.md §1)."""
    p, t = _arrays(points, triangles)
    L = cotangent_laplacian(p, t)
    m = lumped_mass(p, t, mass)
    return (L @ p) / m[:, None]


def _polydata(points, triangles):
    import pyvista as pv

    p, t = _arrays(points, triangles)
    return pv.PolyData.from_regular_faces(np.array(p), np.array(t))


def pyvista_mean_curvature(points, triangles) -> np.ndarray:
    """pyvista/VTK's nodal mean curvature (N,): ``PolyData.curvature("mean")`` = (k1 + k2) / 2 in
    VTK's convention (1/R on an outward sphere of radius R)."""
    return np.asarray(_polydata(points, triangles).curvature("mean"), dtype=float)


def pyvista_mean_curvature_vector(points, triangles) -> np.ndarray:
    """The pyvista value as a mean curvature vector in the convention of docs/math.md §1:
    H_i = 2 c_i n_i, c_i = :func:`pyvista_mean_curvature`, n_i = :func:`vertex_normals`; (N, 3)."""
    c = pyvista_mean_curvature(points, triangles)
    return 2.0 * c[:, None] * vertex_normals(points, triangles)
