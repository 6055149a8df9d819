"""The signed distance to a closed triangle mesh as a level set (:class:`SignedDistance`).

The mesh is validated by :class:`~cutfem.geometry.surface.SurfaceMesh`; values and closest points
come from its compiled nearest-point search (:mod:`cutfem.geometry.closest`), the sign from the
angle-weighted pseudo-normals, which is exact for a closed, outward oriented manifold mesh.
"""

from __future__ import annotations

import numpy as np

from .keys import unique_keys
from .levelset import LevelSet, _as_points
from .surface import SurfaceMesh

__all__ = ["SignedDistance"]


def _surface_arrays(surface):
    """(points (N, 3) float64, triangles (M, 3) int64) from a PolyData or a points/triangles object,
    without the points that no triangle uses."""
    try:
        import pyvista as pv
    except ImportError:  # pragma: no cover - pyvista is a hard dependency
        pv = None
    if pv is not None and isinstance(surface, pv.PolyData):
        if surface.n_cells == 0 or not surface.is_all_triangles:
            raise ValueError(
                "surface must be a closed triangle mesh; this PolyData has non-triangle cells "
                "(or none): call surface.triangulate() first"
            )
        tris = np.asarray(surface.faces, dtype=np.int64).reshape(-1, 4)[:, 1:]
        pts = np.asarray(surface.points, dtype=float)
    elif hasattr(surface, "points") and hasattr(surface, "triangles"):
        pts = np.asarray(surface.points, dtype=float)
        tris = np.asarray(surface.triangles)
        if not np.issubdtype(tris.dtype, np.integer):
            raise ValueError(f"surface.triangles must be integer indices, got dtype {tris.dtype}")
        tris = tris.astype(np.int64)
    else:
        raise ValueError(
            f"surface must be a pyvista.PolyData or have .points (N, 3) and .triangles (M, 3), "
            f"got {type(surface).__name__}"
        )
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"surface points must be finite with shape (N, 3), got shape {pts.shape}")
    if tris.ndim != 2 or tris.shape[1] != 3 or len(tris) == 0:
        raise ValueError(f"surface triangles must have shape (M, 3), M > 0; got {tris.shape}")
    if tris.min() < 0 or tris.max() >= len(pts):
        raise ValueError(
            f"surface triangles index points outside 0..{len(pts) - 1} "
            f"(range {tris.min()}..{tris.max()})"
        )
    used = unique_keys(tris)
    return pts[used], np.searchsorted(used, tris)


class SignedDistance(LevelSet):
    """Signed distance to a closed triangle mesh (negative inside).

    The mesh is validated and oriented by :class:`cutfem.geometry.surface.SurfaceMesh`, the one validation
    of meshed surfaces (a SurfaceMesh is taken as it is; a pyvista PolyData or an object with
    ``points`` and ``triangles`` is built into one, after dropping the points no triangle uses):
    finite points, no degenerate or duplicate triangles, closed, edge- and vertex-manifold,
    consistently oriented, connected components neither intersecting nor nested, and **each
    component oriented outward on its own** (a set of disjoint spheres, some of them given inside
    out, has every sphere's inside negative).  Each failure is a ValueError naming the offenders
    and the fix.

    Values come from one compiled nearest-point pass over a bounding-volume hierarchy of the
    triangles built once (:meth:`cutfem.geometry.surface.SurfaceMesh.signed_distance`, :mod:`cutfem.geometry.closest`):
    |phi(x)| is the exact distance to the nearest point of the triangles, and the sign is that of
    (x - p) . N with N the angle-weighted pseudo-normal of the face, edge or vertex the nearest
    point p lies on (exact for a closed, outward oriented manifold mesh); points outside the mesh's
    bounding box are outside.  Points farther than 1e150 from the mesh are refused (ValueError).

    gradient: central differences of value with h = 1e-6 * (mesh bounding-box diagonal); this is
    the exact gradient wherever the distance is smooth over the stencil (away from the medial set
    and from points within h of a mesh edge or vertex).
    closest_point: the nearest point of the triangles, computed directly
    (:meth:`cutfem.geometry.surface.SurfaceMesh.closest_points`), so it lies on the mesh and
    |x - p| = |phi(x)| everywhere, also at the centre of a sphere mesh (where the difference
    gradient is 0) and far away; where the nearest point is not unique one of them is returned.
    The Hessian (and hence curvature) of a polyhedral distance carries no curvature information:
    hessian raises NotImplementedError.  ``area`` and ``volume`` are those of the polyhedron,
    lipschitz 1, is_distance True, bounds the points' bounding box; ``mesh`` is the SurfaceMesh.
    """

    is_distance = True
    lipschitz = 1.0

    def __init__(self, surface):
        mesh = surface if isinstance(surface, SurfaceMesh) else SurfaceMesh(*_surface_arrays(surface))
        pts, tris = np.asarray(mesh.points), np.asarray(mesh.triangles)
        self.mesh = mesh
        self.points = pts
        self.triangles = tris
        self.area = mesh.area
        self.volume = mesh.enclosed_volume
        self._diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))

    def __repr__(self) -> str:
        return f"SignedDistance(<{len(self.points)} points, {len(self.triangles)} triangles>)"

    def bounds(self):
        """Bounding box of the mesh points, (lower (3,), upper (3,))."""
        return self.points.min(axis=0), self.points.max(axis=0)

    def value(self, x):
        """Signed distance to the mesh (negative inside), shape (...)."""
        x = _as_points(x)
        flat = x.reshape(-1, 3)
        if flat.shape[0] == 0:
            return np.zeros(x.shape[:-1])
        return self.mesh.signed_distance(flat)[0].reshape(x.shape[:-1])

    def gradient(self, x):
        """Central differences of value, h = 1e-6 * bounding-box diagonal; shape (..., 3)."""
        x = _as_points(x)
        h = 1e-6 * self._diag
        offsets = h * np.eye(3)
        xs = np.concatenate([x[..., None, :] + offsets, x[..., None, :] - offsets], axis=-2)
        f = self.value(xs)
        return (f[..., :3] - f[..., 3:]) / (2.0 * h)

    def hessian(self, x):
        """Not available: a polyhedral distance has no meaningful Hessian (curvature)."""
        raise NotImplementedError(
            "SignedDistance is the distance to a flat-faced mesh: its Hessian carries no "
            "curvature of the underlying smooth surface; use an analytic LevelSet for curvatures"
        )

    def closest_point(self, x):
        """The nearest point of the mesh's triangles, shape (..., 3)
        (:meth:`cutfem.geometry.surface.SurfaceMesh.closest_points`)."""
        x = _as_points(x)
        return self.mesh.closest_points(x.reshape(-1, 3))[0].reshape(x.shape)
