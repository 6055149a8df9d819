"""phi_h at the background nodes as the cut sees it: the nodal values, the zero rule, the first checks.

phi_h is the nodal interpolant of the level set (docs/math.md §2); :func:`nodal_values` evaluates it
at every node of a mesh (by blocks of node ids on a structured box, never forming its coordinates),
:func:`snapped_nodal_values` applies the zero rule to them.  The checks every cut makes before its
pieces are built live here too: finite values, a declared Lipschitz bound that is a positive
number (:func:`_declared_lipschitz`), and a surface inside the box (:func:`_check_boundary`, which
raises :class:`CutError`, the error of the cut).

The zero rule
-------------
A nodal value that is exactly zero counts as *outside* (phi >= 0 is outside, phi < 0 inside).
Equivalently S_h is the limit, as eps -> 0+, of the surfaces {phi_h + eps = 0}, each of which has no
zero nodal values; so S_h is the boundary of the union of the inside parts {phi_h < 0} of the tets,
closed and oriented.  In the limit some pieces collapse: a vertex of S_h that falls on a background
node is identified by that node (not by the edge that produced it), pieces with fewer than three
distinct vertices (segments or points) are dropped, and a tet whose piece collapsed is not active.
A piece lying in a face shared by two tets is therefore owned by the single tet on the negative side
(the tet on the other side has all its nodes >= 0 and is not cut).

Values that are zero up to rounding count as zero: before anything else, nodal values with
``|phi_i| <= tol_i`` are set to exactly 0, with per node ``tol_i = 1e-12 max |phi_j|`` over the
nodes j of the node's own tets (its neighbours), whether or not a Lipschitz bound is declared.  That
maximum lies between |phi_i| and |phi_i| + L_loc d (L_loc the level set's local Lipschitz constant,
d the diameter of the node's cells), so the snap moves S_h by at most
tol_i / |grad phi| ~ 1e-12 (|phi_i| / |grad phi| + d): round-off on the local scale.  Neither the
box's largest value (a level set such as z exp(20 x) spans many orders of magnitude across the box)
nor a declared bound (a true but generous L = 1e10 made a global 1e-12 L diam zero nodes 0.04 from
the unit sphere) sets the scale.  The band search (:mod:`cutfem.geometry.band_search`) evaluates the
corners of its cells only; every cell around a node that the snap may zero is among them (its slack
bounds the tolerance, see :func:`_zero_tolerance`), so it snaps exactly the nodes that the full
evaluation snaps.  Without the snap, a node that lies on S mathematically but gets phi = 1e-16 (the
paper's torus on its box at spacing 0.1 has such nodes) gives cut points that coincide with the node
in floating point under different vertex keys: zero-length edges, zero-area triangles and undefined
conormals.
"""

from __future__ import annotations

import numpy as np

from .box import StructuredBox
from .levelset import FunctionLevelSet
from .mesh import TetMesh

__all__ = ["CutError", "nodal_values", "snapped_nodal_values", "NODE_BLOCK"]


class CutError(ValueError):
    """The level set and the background mesh do not give a closed cut surface inside the box."""


def _as_values_function(levelset):
    """A callable x (..., 3) -> (...) from a LevelSet-like object or a plain callable; a plain
    callable is wrapped in a FunctionLevelSet, whose output-shape check names the fix at the first
    evaluation (e.g. a function written for one point, or returning shape (n, 1))."""
    if hasattr(levelset, "value"):
        return levelset.value
    if callable(levelset):
        return FunctionLevelSet(levelset).value
    raise TypeError("levelset must be a LevelSet, a callable f(x) with x of shape (..., 3), or an array of nodal values")


def _declared_lipschitz(levelset):
    """The level set's declared Lipschitz bound (``levelset.lipschitz``) as a float, or None; ValueError
    unless it is a finite positive number: the band search drops cells by it (inf keeps every cell,
    NaN or a bound <= 0 drops every cell, and the cut then says that the level set misses the box)."""
    lipschitz = None if isinstance(levelset, np.ndarray) else getattr(levelset, "lipschitz", None)
    if lipschitz is None:
        return None
    try:
        value = float(lipschitz)
    except (TypeError, ValueError):
        value = np.nan
    if not (np.isfinite(value) and value > 0):
        raise ValueError(
            f"the level set's Lipschitz bound (levelset.lipschitz) is {lipschitz!r}; a Lipschitz bound must be a finite "
            "positive number, a true bound on |grad phi| (1 for a signed distance): declare one, or None to evaluate "
            "every node")
    return value


def _check_finite(values, where):
    bad = ~np.isfinite(values)
    if np.any(bad):
        k = np.flatnonzero(bad.reshape(-1))
        raise ValueError(
            f"the level set gave {k.size} NaN or infinite values at {where}; "
            "check that it is defined on the whole background box"
        )


_SNAP = 1e-12  # relative size of the nodal values that count as zero (see "The zero rule")


def _zero_tolerance(mesh: TetMesh, lipschitz, values=None):
    """The zero rule's tolerance.

    With ``values`` (phi at every node, an array): per node ``tol_i = 1e-12 * max |phi_j|`` over
    the nodes j of the tets around node i (on a structured box the 3 x 3 x 3 block of nodes around
    it, the corners of its 8 cells).  That maximum is at least |phi_i| and at most
    |phi_i| + L_loc d, L_loc the level set's Lipschitz constant over the node's cells and d their
    diameter, so the snap sets to zero only values below 1e-12 of the level set's own scale there,
    and moves S_h by at most tol / |grad phi| ~ 1e-12 (|phi_i| / |grad phi| + d): round-off on the
    scale of the node's cells.  Local, because a level set's values may span many orders of
    magnitude across the box (z exp(20 x) on [-1, 1]^3), and never from a declared Lipschitz bound,
    which may be generous: 1e-12 L diam with L = 1e10 was 0.043 on a 2.5-wide box and zeroed nodes
    0.04 from the unit sphere (area 15.98 instead of 12.56).

    Without ``values`` and with a bound ``lipschitz`` (a number): ``1e-12 * L * diam`` (diam the
    diagonal of the bounding box), not a snap tolerance but the slack that the band search adds to
    its tests (:func:`~cutfem.geometry.band_search._lipschitz_slack`): it bounds every node's tolerance when L is a true bound
    (the node's neighbours lie within a cell diagonal, so max |phi_j| <= |phi_i| + L |spacing|),
    so a cell with a corner that the snap may zero is never dropped."""
    if values is None:
        if lipschitz is None:
            return 0.0
        lo, hi = mesh.bounds
        return _SNAP * float(lipschitz) * float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    if not values.size:
        return 0.0
    size = np.abs(values)
    if isinstance(mesh, StructuredBox):
        from scipy.ndimage import maximum_filter

        nx, ny, nz = (int(n) for n in mesh.node_shape)
        local = maximum_filter(size.reshape(nz, ny, nx), size=3, mode="nearest").reshape(-1)
    else:
        local = size.copy()
        np.maximum.at(local, mesh.tets.reshape(-1), np.repeat(size[mesh.tets].max(axis=1), 4))
    return _SNAP * local


def _snap_zeros(values, tol) -> np.ndarray:
    """A copy of ``values`` with the entries of modulus <= tol (a number or one per entry) set to
    exactly 0."""
    values = np.array(values, dtype=float)
    values[np.abs(values) <= tol] = 0.0
    return values


#: nodes of a structured box whose level-set values are computed at once (:func:`nodal_values`)
NODE_BLOCK = 1 << 20


def nodal_values(mesh: TetMesh, levelset) -> np.ndarray:
    """phi at every node of ``mesh`` (N,), with a clear error for NaN/inf values.  On a
    :class:`~cutfem.geometry.box.StructuredBox` the nodes go by blocks of :data:`NODE_BLOCK` ids, their
    coordinates made per block: the box's (N, 3) coordinates are never formed (300 MB, and 700 MB
    while being made, for the 12.5 million nodes of the solid torus's box at spacing 0.01).
    Points that no tet uses (a file's stray points, the mid-edge nodes of quadratic tets) are not
    nodes: the level set is not evaluated there, their entries are NaN (given values may be
    anything there), and nothing reads them."""
    used = None if mesh.n_used_points == mesh.n_points else mesh._used  # a StructuredBox: every node is used
    if isinstance(levelset, np.ndarray):
        values = np.asarray(levelset, dtype=float).reshape(-1)
        if values.size != mesh.n_points:
            raise ValueError(f"got {values.size} nodal values for a mesh of {mesh.n_points} nodes")
    elif isinstance(mesh, StructuredBox):
        f, n = _as_values_function(levelset), mesh.n_points
        values = np.empty(n)
        for start in range(0, n, NODE_BLOCK):  # blocks of nodes, not single nodes
            stop = min(start + NODE_BLOCK, n)
            values[start:stop] = np.asarray(f(mesh.node_coordinates(np.arange(start, stop))), dtype=float).reshape(-1)
    elif used is None:
        values = np.asarray(_as_values_function(levelset)(mesh.points), dtype=float).reshape(-1)
    else:
        values = np.full(mesh.n_points, np.nan)
        values[used] = np.asarray(_as_values_function(levelset)(mesh.points[used]), dtype=float).reshape(-1)
    _check_finite(values if used is None else values[used], "background nodes")
    return values


def snapped_nodal_values(mesh: TetMesh, levelset) -> np.ndarray:
    """phi_h at every node of ``mesh`` as the cut sees it: :func:`nodal_values` with the values of
    modulus at most 1e-12 max |phi| over the node and its neighbours set to exactly 0 (the zero
    rule, :func:`_zero_tolerance`).  Visits every node; for handing the same
    discrete level set to other codes and for volume integrals."""
    values = nodal_values(mesh, levelset)
    return _snap_zeros(values, _zero_tolerance(mesh, None, values))


def _check_boundary(mesh: TetMesh, f_or_values, tol: float = 0.0, boundary_values=None):
    """All boundary nodes must be outside (phi >= -tol; ``f_or_values`` the snapped nodal values, or
    ``boundary_values`` those of ``mesh.boundary_nodes``): otherwise the surface leaves the box."""
    b = mesh.boundary_nodes
    if boundary_values is not None:
        vb = boundary_values
    elif isinstance(f_or_values, np.ndarray):
        vb = f_or_values[b]
    else:
        pts = mesh.node_coordinates(b) if isinstance(mesh, StructuredBox) else mesh.points[b]
        vb = np.asarray(f_or_values(pts), dtype=float)
        _check_finite(vb, "boundary nodes")
    if np.any(vb < -tol):
        inside = vb < -tol
        k = int(np.sum(inside))
        lo, hi = mesh.bounds
        if not isinstance(mesh, StructuredBox):  # a box's boundary nodes all lie on its faces
            # boundary nodes away from every face of the bounding box: the mesh has an inner boundary
            # (a cavity, a crack) or is not a box; 1e-2 of the diagonal leaves room for pytetwild's envelope
            x = mesh.points[b[inside]]
            gap = np.minimum(x - lo, hi - x).min(axis=1)
            off = gap > 1e-2 * float(np.linalg.norm(hi - lo))
            if np.any(off):
                raise CutError(
                    f"{k} boundary nodes of the background mesh are inside the surface (phi < 0), {int(np.sum(off))} of "
                    f"them off the faces of the mesh's bounding box [{lo.tolist()}, {hi.tolist()}] (first at "
                    f"{x[np.argmax(off)].tolist()}): the mesh has a hole or a crack there (duplicated nodes make one), or "
                    "does not cover the surface. Mesh the whole box around the surface in one conforming piece, "
                    "or check the sign of the level set (negative inside)."
                )
        raise CutError(
            f"{k} boundary nodes of the background mesh are inside the surface (phi < 0): the surface reaches "
            f"or leaves the box [{lo.tolist()}, {hi.tolist()}]. Enlarge the box so that it contains the surface "
            "with at least one cell to spare, or check the sign of the level set (negative inside)."
        )
